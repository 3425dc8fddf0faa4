"""``terralod serve``: the web formats from a store on request, and the change site's page."""

from __future__ import annotations

from typing import Any

__all__ = ["CESIUM_HINT", "TileService", "cesium_dir", "make_server"]

from terralod.site.cesium import CESIUM_HINT, cesium_dir  # noqa: E402 - the page's CesiumJS


def __getattr__(name: str) -> Any:
    # the server (and numpy behind it) loads on first use, not on ``import terralod.serve``
    if name in ("TileService", "make_server"):
        from terralod.serve import server

        return getattr(server, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
