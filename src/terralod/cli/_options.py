"""Options shared by several commands and their parsing: the reader options of un-georeferenced
heightmaps, points, sizes, views, colours and the ``-o`` rule of file outputs.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import click

from terralod.cli._errors import LAST_INPUT, out_of_memory
from terralod.output import check_target

#: The ``-o`` / ``--overwrite`` rule of file outputs (stores, images, videos); folder outputs are
#: :class:`terralod.output.Output`'s.
check_output = check_target  # the name the commands use


def is_store(path: Path) -> bool:
    """True when ``path`` is an SQLite file or a ``.terra`` file (a store or something claiming to be one;
    opening it then says what is wrong)."""
    if Path(path).suffix.lower() == ".terra" and Path(path).is_file():
        return True
    try:
        with open(path, "rb") as fh:
            return fh.read(16) == b"SQLite format 3\x00"
    except OSError:
        return False


def check_raster_size(path: str | Path) -> None:
    """The one size limit (:func:`terralod.fill.check_dimensions`), checked up front from the raster's
    header, never its samples: every command that reads a DEM calls it before reading or writing anything.
    Stores, point clouds and files GDAL cannot open are left to their readers."""
    p = Path(path)
    if not p.is_file() or is_store(p) or p.suffix.lower() in (".las", ".laz", ".npy", ".npz"):
        return
    try:
        import rasterio

        with rasterio.open(p) as src:
            height, width = src.height, src.width
    except Exception:  # noqa: BLE001 - not a raster GDAL reads: the reader names the problem
        return
    from terralod.fill import check_dimensions

    check_dimensions(height, width, str(path))


def parse_pair(text: str | None, name: str) -> tuple[float, float] | None:
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


def read_options(f: Callable[..., Any]) -> Callable[..., Any]:
    """The options that tell a reader how to decode a heightmap without georeferencing of its own."""
    f = click.option(
        "--spacing",
        "spacing",
        help="Ground spacing DX[,DY] in metres (un-georeferenced inputs; for a LiDAR "
        "pair in `change`, the grid its ground points are read on).",
    )(f)
    f = click.option("--vertical-scale", type=float, help="Metres per stored unit (PNG/NPY heightmaps).")(f)
    f = click.option("--vertical-offset", type=float, help="Metres added after scaling.")(f)
    f = click.option(
        "--encoding", type=click.Choice(["terrain-rgb", "terrarium"]), help="RGB-encoded elevation tiles."
    )(f)
    f = click.option("--tile", "tile_zxy", help="Z/X/Y of an XYZ web-map tile (georeferences it).")(f)
    f = click.option(
        "--crs", "crs", default=None,
        help="CRS of the input (EPSG:32610, WKT or PROJ string): assigns one to a file without, or overrides "
        "the file's own (said in the notes).",
    )(f)  # fmt: skip
    f = click.option(
        "--vertical-datum", "vertical_datum", default=None,
        help="What the heights are measured from when the file does not say: egm96 (SRTM, Copernicus), "
        "egm2008, navd88, ellipsoid, or a vertical CRS (EPSG:5773). The web exports then write heights above "
        "the WGS 84 ellipsoid.",
    )(f)  # fmt: skip
    return f


def load(
    path: str,
    spacing=None,
    vertical_scale=None,
    vertical_offset=None,
    encoding=None,
    tile_zxy=None,
    crs=None,
    vertical_datum=None,
):
    """Read a DEM with the reader options of :func:`read_options` → :class:`terralod.Heightfield`."""
    from terralod.io.reader import read_heightfield

    check_raster_size(path)
    LAST_INPUT["path"] = str(path)
    tile = None
    if tile_zxy:
        try:
            tile = tuple(int(v) for v in tile_zxy.replace(",", "/").split("/"))
        except ValueError:
            tile = ()
        if len(tile) != 3:
            raise click.BadParameter(f"expected Z/X/Y, got {tile_zxy!r}", param_hint="--tile")
    from terralod.errors import InputError

    try:
        return read_heightfield(
            path,
            spacing_m=parse_pair(spacing, "--spacing"),
            vertical_scale=vertical_scale,
            vertical_offset=vertical_offset,
            encoding=encoding,
            tile=tile,
            crs=crs,
            vertical_datum=vertical_datum,
        )
    except MemoryError:
        raise InputError(out_of_memory(path), str(path)) from None


def triple(text: str, name: str) -> tuple[float, float, float]:
    try:
        v = tuple(float(a) for a in text.split(","))
    except ValueError:
        raise click.BadParameter(f"expected X,Y,Z in metres, got {text!r}", param_hint=name) from None
    if len(v) != 3:
        raise click.BadParameter(f"expected X,Y,Z in metres, got {text!r}", param_hint=name)
    return v  # type: ignore[return-value]


def size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(a) for a in text.lower().split("x"))
    except ValueError:
        w = h = 0
    if not (16 <= w <= 8192 and 16 <= h <= 8192):
        raise click.BadParameter(
            f"expected WIDTHxHEIGHT between 16 and 8192, got {text!r}", param_hint="--size"
        )
    return w, h


def view_options(fn: Callable[..., Any]) -> Callable[..., Any]:
    """--fractal and --cull, shared by render, flythrough and view."""
    fn = click.option(
        "--cull", multiple=True, type=click.Choice(["backface", "region"]),
        help="Skip drawing back-facing tiles (Hu & Wang §3.2) / tiles outside the visible region (§3.1).",
    )(fn)  # fmt: skip
    return click.option(
        "--fractal", "fractal_levels", type=click.IntRange(0, 6), default=None,
        help="Fractal levels below the DEM (0-6; default: the store's, from build --fractal).",
    )(fn)  # fmt: skip


def aim_options(fn: Callable[..., Any]) -> Callable[..., Any]:
    """--look-at, --from and --water-level, shared by render and flythrough (and --water-level by view)."""
    fn = click.option(
        "--from", "from_text",
        help="Camera AZIMUTH,ELEVATION,DISTANCE from the target: degrees clockwise from north, degrees "
        "above the horizon, metres (default 200,35,half the terrain's diagonal).",
    )(fn)  # fmt: skip
    fn = click.option(
        "--look-at", "look_at", help="Aim at LON,LAT (WGS84 degrees) on the terrain instead of its centre."
    )(fn)
    return water_option(fn)


def water_option(fn: Callable[..., Any]) -> Callable[..., Any]:
    return click.option(
        "--water-level", "water_level", type=float, default=None,
        help="Draw everything at or below this height (metres) as water (default: a sea the source writes "
        "as 0 m, connected to its border).",
    )(fn)  # fmt: skip


def _memory(ctx: click.Context, param: click.Parameter, value: str | None) -> int | None:
    if value is None:
        return None
    from terralod.memory import parse_size

    try:
        return parse_size(value)
    except ValueError as exc:
        raise click.BadParameter(str(exc), ctx=ctx, param=param) from None


def memory_option(fn: Callable[..., Any]) -> Callable[..., Any]:
    """``--memory SIZE``: the peak memory of the command's process tree it plans for (bytes, as ``memory_bytes``)."""
    return click.option(
        "--memory", "memory_bytes", default=None, metavar="SIZE", callback=_memory,
        help="Memory the command may use, its workers included (e.g. 4GiB; default 2GiB): it decides the work "
        "units in flight and when one raster builds out of core; refused in one line below what one unit needs.",
    )(fn)  # fmt: skip


def numbers(text: str | None, n: int, name: str, what: str) -> tuple[float, ...] | None:
    """``n`` comma-separated numbers, or None."""
    if text is None:
        return None
    try:
        v = tuple(float(a) for a in text.split(","))
    except ValueError:
        v = ()
    if len(v) != n:
        raise click.BadParameter(f"expected {what}, got {text!r}", param_hint=name)
    return v


def aimed_pose(terrain, look_at: str | None, from_text: str | None):
    """The pose of --look-at / --from (None when neither is given)."""
    from terralod.render.offscreen import aim_pose

    ll = numbers(look_at, 2, "--look-at", "LON,LAT in degrees")
    fr = numbers(from_text, 3, "--from", "AZIMUTH,ELEVATION,DISTANCE (degrees, degrees, metres)")
    if ll is None and fr is None:
        return None
    if ll is not None and not (-180 <= ll[0] <= 360 and -90 <= ll[1] <= 90):
        raise click.BadParameter(f"expected LON,LAT in degrees, got {look_at!r}", param_hint="--look-at")
    if fr is not None and not (fr[2] > 0 and -90 < fr[1] <= 90):
        raise click.BadParameter(
            f"expected a distance > 0 and an elevation in (-90, 90], got {from_text!r}", param_hint="--from"
        )
    return aim_pose(terrain, ll, fr)  # type: ignore[arg-type]


def render_settings(background: str | None, mode: str, wireframe: bool):
    from terralod.render import RenderSettings

    st = RenderSettings(mode=mode, wireframe=wireframe, legend=mode == "elevation")
    if background:
        try:
            rgb = tuple(float(a) for a in background.split(","))
        except ValueError:
            rgb = ()
        if len(rgb) != 3:
            raise click.BadParameter(f"expected R,G,B, got {background!r}", param_hint="--background")
        st.background = tuple(c / 255.0 if max(rgb) > 1.0 else c for c in rgb)  # type: ignore[assignment]
    return st


__all__ = [
    "check_output",
    "is_store",
    "check_raster_size",
    "parse_pair",
    "read_options",
    "load",
    "triple",
    "size",
    "view_options",
    "aim_options",
    "water_option",
    "numbers",
    "aimed_pose",
    "render_settings",
]
