"""The ``terralod`` command line: ``info``, ``build``, ``demo``.

User mistakes (missing file, wrong format, no valid samples, unwritable output, corrupt store) print one
line ``terralod: <file>: <problem>`` and exit with code 2; ``-v`` adds diagnostics and the traceback.
"""

from __future__ import annotations

import json
import logging
import sys
from pathlib import Path
from typing import Any

import click
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from terralod.errors import TerralodError

console = Console(stderr=False, width=None if sys.stdout.isatty() else 160)
err_console = Console(stderr=True)
_VERBOSE = {"on": False}


def _is_store(path: Path) -> bool:
    try:
        with open(path, "rb") as fh:
            return fh.read(16) == b"SQLite format 3\x00"
    except OSError:
        return False


def _parse_pair(text: str | None, name: str) -> tuple[float, float] | None:
    if text is None:
        return None
    try:
        parts = [float(v) for v in text.split(",")]
    except ValueError:
        raise click.BadParameter(f"expected a number or DX,DY, got {text!r}", param_hint=name) from None
    if len(parts) == 1:
        parts = parts * 2
    if len(parts) != 2 or min(parts) <= 0:
        raise click.BadParameter(f"expected positive DX[,DY] in metres, got {text!r}", param_hint=name)
    return parts[0], parts[1]


def _read_options(f):
    f = click.option(
        "--spacing", "spacing", help="Ground spacing DX[,DY] in metres (un-georeferenced inputs)."
    )(f)
    f = click.option("--vertical-scale", type=float, help="Metres per stored unit (PNG/NPY heightmaps).")(f)
    f = click.option("--vertical-offset", type=float, help="Metres added after scaling.")(f)
    f = click.option(
        "--encoding", type=click.Choice(["terrain-rgb", "terrarium"]), help="RGB-encoded elevation tiles."
    )(f)
    f = click.option("--tile", "tile_zxy", help="Z/X/Y of an XYZ web-map tile (georeferences it).")(f)
    return f


def _load(path: str, spacing, vertical_scale, vertical_offset, encoding, tile_zxy):
    from terralod.io.reader import read_heightfield

    tile = None
    if tile_zxy:
        try:
            tile = tuple(int(v) for v in tile_zxy.replace(",", "/").split("/"))
            assert len(tile) == 3
        except (ValueError, AssertionError):
            raise click.BadParameter(f"expected Z/X/Y, got {tile_zxy!r}", param_hint="--tile") from None
    return read_heightfield(
        path,
        spacing_m=_parse_pair(spacing, "--spacing"),
        vertical_scale=vertical_scale,
        vertical_offset=vertical_offset,
        encoding=encoding,
        tile=tile,
    )


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.option("-v", "--verbose", is_flag=True, help="Show diagnostics and tracebacks.")
@click.version_option(package_name="terralod")
def cli(verbose: bool) -> None:
    """terralod: terrain level of detail with measured geometric error."""
    _VERBOSE["on"] = verbose
    logging.basicConfig(level=logging.INFO if verbose else logging.WARNING, format="%(name)s: %(message)s")


# -- info ----------------------------------------------------------------------------------------------
def heightfield_info(hf) -> dict[str, Any]:
    lo, hi = hf.valid_range_m()
    return {
        "kind": "heightfield",
        "source": hf.source,
        "size": [hf.width, hf.height],
        "crs": hf.crs,
        "spacing_m": list(hf.spacing_m),
        "bounds_m": list(hf.bounds_m),
        "elevation_range_m": [lo, hi],
        "nodata_percent": 100.0 * hf.nodata_fraction,
        "fill_method": hf.fill_method,
        "notes": list(hf.notes),
    }


def _crs_name(crs: str | None) -> str:
    if not crs:
        return "none (local metric frame)"
    try:
        from rasterio.crs import CRS

        c = CRS.from_user_input(crs)
        epsg = c.to_epsg()
        return f"EPSG:{epsg}" if epsg else c.to_string()[:60]
    except Exception:  # noqa: BLE001 - a name is cosmetic
        return crs[:60]


def print_store_summary(summary: dict[str, Any]) -> None:
    console.print(f"{summary['path']}: {'complete' if summary['complete'] else 'INCOMPLETE (finish with --resume)'}")
    t = Table()
    for col in ("level", "tiles", "vertices", "triangles", "max error m", "max vert. m", "RMS m", "KiB"):
        t.add_column(col, justify="right")
    for k, d in summary["per_level"].items():
        t.add_row(
            str(k), str(d["tiles"]), f"{d['vertices']:,}", f"{d['triangles']:,}", f"{d['max_error_m']:.3f}",
            f"{d['max_vertical_error_m']:.3f}", f"{d['rms_error_m']:.3f}", f"{d['bytes'] / 1024:.1f}",
        )  # fmt: skip
    console.print(t)
    console.print(
        f"{summary['levels']} levels, {summary['tiles']}/{summary['tiles_planned']} tiles, tile size "
        f"{summary['tile_size']}, {summary['size_bytes'] / 1024 / 1024:.2f} MiB on disk"
    )


@cli.command()
@click.argument("path")
@click.option("--json", "as_json", is_flag=True, help="Print machine-readable JSON.")
@_read_options
def info(path: str, as_json: bool, **read: Any) -> None:
    """Describe a DEM (size, CRS, spacing, range, nodata) or a .terra store (levels, tiles, errors)."""
    from terralod.build.builder import store_summary
    from terralod.store import open_store

    p = Path(path)
    if p.exists() and _is_store(p):
        with open_store(p) as s:
            summary = store_summary(s)
            summary["crs"] = _crs_name(s.crs)
            summary["source"] = s.meta.get("source")
            summary["method"] = s.meta.get("method")
        if as_json:
            click.echo(json.dumps(summary, indent=2, default=str))
        else:
            console.print(f"source {summary['source']}, method {summary['method']}, CRS {summary['crs']}")
            print_store_summary(summary)
        return
    hf = _load(path, **read)
    d = heightfield_info(hf)
    if as_json:
        click.echo(json.dumps(d, indent=2))
        return
    console.print(f"[bold]{d['source']}[/bold]")
    console.print(f"  size         {d['size'][0]} x {d['size'][1]} samples")
    console.print(f"  CRS          {_crs_name(d['crs'])}")
    console.print(f"  spacing      {d['spacing_m'][0]:.3f} x {d['spacing_m'][1]:.3f} m")
    console.print(f"  elevation    {d['elevation_range_m'][0]:.2f} .. {d['elevation_range_m'][1]:.2f} m")
    console.print(f"  nodata       {d['nodata_percent']:.2f} %")
    for n in d["notes"] + ([d["fill_method"]] if d["fill_method"] else []):
        console.print(f"  note         {n}")


# -- build ---------------------------------------------------------------------------------------------
def run_build(
    hf, out: str, *, tile_size: int, method: str, workers: int | None, resume: bool, overwrite: bool
):
    from terralod.build.builder import build_store

    with Progress(
        TextColumn("[bold]building[/bold] {task.description}"), BarColumn(), MofNCompleteColumn(),
        TimeElapsedColumn(), console=err_console, transient=False, disable=not sys.stderr.isatty() and not _VERBOSE["on"],
    ) as prog:  # fmt: skip
        task = prog.add_task(Path(out).name, total=None)

        def cb(done: int, total: int) -> None:
            prog.update(task, completed=done, total=total)

        return build_store(
            hf,
            out,
            tile_size=tile_size,
            method=method,
            workers=workers,
            resume=resume,
            overwrite=overwrite,
            progress=cb,
        )


@cli.command()
@click.argument("input_path", metavar="INPUT")
@click.option("-o", "--output", required=True, help="Output .terra store.")
@click.option("--tile-size", default=65, show_default=True, help="Vertices per tile side (2^n + 1).")
@click.option("--method", default="chunked", show_default=True, help="Tile mesher: chunked.")
@click.option("--workers", type=int, default=None, help="Threads (default: all cores).")
@click.option("--resume", is_flag=True, help="Finish an interrupted build of the same input.")
@click.option("--overwrite", is_flag=True, help="Replace an existing output store.")
@_read_options
def build(
    input_path: str, output: str, tile_size: int, method: str, workers, resume, overwrite, **read: Any
) -> None:
    """Build the level-of-detail tile store of a DEM."""
    from terralod.build.builder import METHODS, store_summary
    from terralod.store import open_store
    from terralod.tiles import is_valid_tile_size

    if not is_valid_tile_size(tile_size) or tile_size > 257:
        raise click.BadParameter(
            f"expected 2^n + 1 between 3 and 257, got {tile_size}", param_hint="--tile-size"
        )
    if method not in METHODS:
        raise click.BadParameter(
            f"expected one of {', '.join(sorted(METHODS))}, got {method!r}", param_hint="--method"
        )
    if workers is not None and workers < 1:
        raise click.BadParameter(f"expected >= 1, got {workers}", param_hint="--workers")
    hf = _load(input_path, **read)
    rep = run_build(
        hf, output, tile_size=tile_size, method=method, workers=workers, resume=resume, overwrite=overwrite
    )
    console.print(
        f"built {rep.tiles_built} tiles ({rep.tiles_skipped} already done) in {rep.seconds:.2f} s, "
        f"{rep.samples_per_second / 1e6:.2f} M source samples/s"
    )
    with open_store(output) as s:
        print_store_summary(store_summary(s))


# -- demo ----------------------------------------------------------------------------------------------
@cli.command()
@click.option("-o", "--output", default="demo.terra", show_default=True, help="Store to build.")
@click.option("--tile-size", default=33, show_default=True, help="Vertices per tile side.")
def demo(output: str, tile_size: int) -> None:
    """Build the bundled real DEM (matplotlib's Jacksboro fault, Tennessee) and print its store summary."""
    from terralod.build.builder import store_summary
    from terralod.io.reader import sample_heightfield
    from terralod.store import open_store

    hf = sample_heightfield()
    d = heightfield_info(hf)
    console.print(
        f"[bold]{d['source']}[/bold]: {d['size'][0]}x{d['size'][1]} samples at {d['spacing_m'][0]:.1f} m, "
        f"{d['elevation_range_m'][0]:.0f}..{d['elevation_range_m'][1]:.0f} m, CRS {_crs_name(d['crs'])}"
    )
    rep = run_build(
        hf, output, tile_size=tile_size, method="chunked", workers=None, resume=False, overwrite=True
    )
    console.print(f"built {rep.tiles_built} tiles in {rep.seconds:.2f} s")
    with open_store(output) as s:
        print_store_summary(store_summary(s))


def main(argv: list[str] | None = None) -> None:
    """Entry point: run the CLI, turning terralod errors into one line and exit code 2."""
    try:
        cli.main(args=argv, prog_name="terralod", standalone_mode=False)
    except click.exceptions.Abort:
        err_console.print("terralod: aborted")
        sys.exit(130)
    except click.ClickException as exc:
        exc.show()
        sys.exit(2)
    except KeyboardInterrupt:
        err_console.print("terralod: interrupted; finished tiles are saved, finish with --resume")
        sys.exit(130)
    except TerralodError as exc:
        if _VERBOSE["on"]:
            raise
        click.echo(f"terralod: {exc}", err=True)
        sys.exit(2)
    except OSError as exc:
        if _VERBOSE["on"]:
            raise
        name = getattr(exc, "filename", None)
        click.echo(f"terralod: {name + ': ' if name else ''}{exc.strerror or exc}", err=True)
        sys.exit(2)
    except MemoryError:
        click.echo("terralod: out of memory; split the input or use a smaller --tile-size", err=True)
        sys.exit(2)


if __name__ == "__main__":  # pragma: no cover
    main(sys.argv[1:])
