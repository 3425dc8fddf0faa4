"""``terralod serve STORE [--host H] [--port P]``: 3D Tiles, quantized-mesh and a CesiumJS viewer page."""

from __future__ import annotations

import click

from terralod.cli._console import console, err_console
from terralod.cli._errors import require_extra


@click.command()
@click.argument("store")
@click.option(
    "--host",
    default="127.0.0.1",
    show_default=True,
    help="Address to bind (anything but loopback exposes the store to the network).",
)
@click.option(
    "--port", type=click.IntRange(0, 65535), default=8000, show_default=True, help="TCP port (0: any)."
)
@click.option(
    "--no-coregister", is_flag=True, help="The page's pairs compared as they are, without lining them up."
)
@click.option("--coreg", "coreg_method", type=click.Choice(["xdem", "terralod"]), default="xdem",
              show_default=True, help="Co-registration estimator of the page's pairs.")  # fmt: skip
def serve(store: str, host: str, port: int, no_coregister: bool, coreg_method: str) -> None:
    """Serve a .terra store to the browser: viewer at /, tiles under /3dtiles/ and /terrain/ (read-only)."""
    require_extra("serve", "web")
    from terralod.errors import TerralodError
    from terralod.serve import CESIUM_HINT, make_server
    from terralod.site.plan import SiteOptions
    from terralod.terrain import open_terrain

    if host not in ("127.0.0.1", "localhost", "::1"):
        err_console.print(f"terralod: warning: serving on {host}: anyone who can reach it can read the store")
    with open_terrain(store) as terrain:
        try:
            options = SiteOptions(coregistration=not no_coregister, method=coreg_method)
            server, service = make_server(terrain, host, port, site_options=options)
        except OSError as exc:
            if isinstance(exc, TerralodError):  # a store error (StoreError is an OSError): named as such
                raise
            raise click.ClickException(f"cannot listen on {host}:{port} ({exc.strerror or exc})") from None
        if service.cesium is None:
            err_console.print(f"terralod: {CESIUM_HINT}; serving the tiles only")
        h, p = server.server_address[:2]
        console.print(f"serving {store} on http://{h}:{p}/ (3D Tiles /3dtiles/tileset.json, quantized-mesh "
                      f"/terrain/layer.json); Ctrl-C stops", highlight=False)  # fmt: skip
        try:
            server.serve_forever()
        except KeyboardInterrupt:
            pass
        finally:
            server.server_close()
