"""What every ``terralod`` command shares: consoles, the reader options, parsing of points and sizes,
opening any input as a terrain, progress of long jobs, and the mapping of errors to one line + exit 2.

A command module (``terralod/cli/<command>.py``) defines one click command and imports only from here and
from the library; :mod:`terralod.cli` registers it.
"""

from __future__ import annotations

import logging
import os
import sqlite3
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import click
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from terralod.output import check_target

console = Console(stderr=False, width=None if sys.stdout.isatty() else 160)
err_console = Console(stderr=True)
VERBOSE = {"on": False}
#: The DEM the command read last: a failure for want of memory names it (run_main).
LAST_INPUT: dict[str, str | None] = {"path": None}
log = logging.getLogger("terralod.cli")
#: The ``-o`` / ``--overwrite`` rule of file outputs (stores, images, videos); folder outputs are
#: :class:`terralod.output.Output`'s.
check_output = check_target


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


#: The optional parts of terralod (``pip install 'terralod[EXTRA]'``) and the modules each one brings.
EXTRAS: dict[str, tuple[str, ...]] = {
    "web": ("pyproj", "pygltflib", "pydelatin"),  # export, serve: 3D Tiles, quantized-mesh, ECEF
    "change": ("xdem", "shapely", "pyproj"),  # change: co-registration, zones, reprojection
    "dask": ("dask", "distributed"),  # build --dask
    "window": ("glfw",),  # view: the real-time window
}


class MissingExtra(click.ClickException):
    """A command whose optional dependencies are not installed: one line, exit 2."""

    exit_code = 2

    def show(self, file: Any = None) -> None:
        click.echo(self.message, err=True)


def missing_modules(extra: str) -> list[str]:
    """The modules of ``extra`` (:data:`EXTRAS`) that cannot be imported here."""
    import importlib.util

    out = []
    for name in EXTRAS[extra]:
        try:
            found = importlib.util.find_spec(name) is not None
        except (ImportError, ValueError):
            found = False
        if not found:
            out.append(name)
    return out


def require_extra(command: str, extra: str) -> None:
    """Stop ``terralod COMMAND`` with one line naming the extra to install when its modules are missing."""
    missing = missing_modules(extra)
    if missing:
        log.info("missing modules of the %s extra: %s", extra, ", ".join(missing))
        raise MissingExtra(f"terralod {command} needs the {extra} extra: pip install 'terralod[{extra}]'")


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


def out_of_memory(path: str | Path) -> str:
    """The one line for a DEM this machine has not the memory to read (its size from the header)."""
    try:
        import rasterio

        with rasterio.open(path) as src:
            n = src.width * src.height
            size = f"{src.width}x{src.height} samples (about {n * 13 / 1e9:.1f} GB to read and fill)"
    except Exception:  # noqa: BLE001 - not a GDAL raster: say it without the size
        size = "its samples"
    return f"not enough memory for {size}; crop or split it into tiles first"


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
        "--spacing", "spacing", help="Ground spacing DX[,DY] in metres (un-georeferenced inputs)."
    )(f)
    f = click.option("--vertical-scale", type=float, help="Metres per stored unit (PNG/NPY heightmaps).")(f)
    f = click.option("--vertical-offset", type=float, help="Metres added after scaling.")(f)
    f = click.option(
        "--encoding", type=click.Choice(["terrain-rgb", "terrarium"]), help="RGB-encoded elevation tiles."
    )(f)
    f = click.option("--tile", "tile_zxy", help="Z/X/Y of an XYZ web-map tile (georeferences it).")(f)
    return f


def load(path: str, spacing=None, vertical_scale=None, vertical_offset=None, encoding=None, tile_zxy=None):
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
        )
    except MemoryError:
        raise InputError(out_of_memory(path), str(path)) from None


def crs_name(crs: str | None) -> str:
    """The CRS in words: horizontal name, EPSG code and unit, vertical CRS when there is one; never WKT
    (:func:`terralod.io.georef.describe_crs`)."""
    from terralod.io.georef import describe_crs

    return describe_crs(crs)


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
        raise click.BadParameter(f"expected WIDTHxHEIGHT between 16 and 8192, got {text!r}", param_hint="--size")
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


class PlainProgress:
    """Progress as plain lines on stderr (for logs and pipes, where a bar would be noise): one line when a
    task starts, then ``label name: done/total (pct %), elapsed s`` at most every ``every_s`` seconds, and
    a last line when it ends. The subset of :class:`rich.progress.Progress` the commands use."""

    def __init__(self, label: str, every_s: float = 5.0, stream=None) -> None:
        self.label = label
        self.every_s = every_s
        self.stream = stream
        self._tasks: dict[int, dict[str, Any]] = {}

    def __enter__(self) -> PlainProgress:
        return self

    def __exit__(self, *exc: object) -> None:
        for k, t in self._tasks.items():
            if t["printed"] != (t["completed"], t["total"]):
                self._line(k)

    def add_task(self, description: str, total: float | None = None, **_: Any) -> int:
        import time

        k = len(self._tasks)
        self._tasks[k] = {"name": description, "total": total, "completed": 0, "t0": time.monotonic(),
                          "last": time.monotonic(), "printed": None}  # fmt: skip
        click.echo(f"{self.label} {description} ...", err=True, file=self.stream)
        return k

    def update(self, task: int, completed: float | None = None, total: float | None = None, **_: Any) -> None:
        import time

        t = self._tasks[task]
        if completed is not None:
            t["completed"] = completed
        if total is not None:
            t["total"] = total
        now = time.monotonic()
        done = t["total"] is not None and t["completed"] >= t["total"]
        if now - t["last"] >= self.every_s or (done and t["printed"] != (t["completed"], t["total"])):
            t["last"] = now
            self._line(task)

    def _line(self, task: int) -> None:
        import time

        t = self._tasks[task]
        t["printed"] = (t["completed"], t["total"])
        el = time.monotonic() - t["t0"]
        if t["total"]:
            pct = 100.0 * t["completed"] / t["total"]
            msg = f"{self.label} {t['name']}: {t['completed']:.0f}/{t['total']:.0f} ({pct:.0f} %), {el:.0f} s"
        else:
            msg = f"{self.label} {t['name']}: {t['completed']:.0f}, {el:.0f} s"
        click.echo(msg, err=True, file=self.stream)


def progress(label: str) -> Progress | PlainProgress:
    """A progress bar on stderr when it is a terminal; plain lines every few seconds otherwise."""
    if not sys.stderr.isatty():
        return PlainProgress(label)
    return Progress(
        TextColumn(f"[bold]{label}[/bold] {{task.description}}"), BarColumn(), MofNCompleteColumn(),
        TimeElapsedColumn(), console=err_console, transient=False,
    )  # fmt: skip


def run_build(hf, out: str, *, tile_size: int, method: str, workers: int | None, resume: bool, overwrite: bool,
              **extra: Any):  # fmt: skip
    """:func:`terralod.pyramid.builder.build_store` with a progress bar (``extra``: more of its options)."""
    from terralod.pyramid.builder import build_store

    with progress("building") as prog:
        task = prog.add_task(Path(out).name, total=None)

        def cb(done: int, total: int) -> None:
            prog.update(task, completed=done, total=total)

        try:
            return build_store(hf, out, tile_size=tile_size, method=method, workers=workers, resume=resume,
                               overwrite=overwrite, progress=cb, **extra)  # fmt: skip
        except sqlite3.Error as exc:  # disk full, I/O error, file-size limit: name the store and the way on
            raise store_write_error(exc, out) from exc


def store_write_error(exc: BaseException, out: str | Path) -> Exception:
    """The one line of a store that could not be written (full disk, I/O error, file-size limit): what
    is committed stays, and ``--resume`` finishes once there is room."""
    from terralod.errors import StoreError

    return StoreError(
        f"cannot write the store ({exc}; is the disk full?); the tiles committed so far are kept: free "
        "space, then run the same command with --resume",
        str(out),
    )


def user_cache_dir() -> Path:
    """``$XDG_CACHE_HOME/terralod`` (default ``~/.cache/terralod``): caches never go beside an input,
    whose folder may be read-only."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "terralod"


def cache_store_path(source: str | Path, digest: str) -> Path:
    """Where the cache store of a DEM goes: the user cache folder, named by the DEM and its digest."""
    p = Path(source)
    return user_cache_dir() / "views" / f"{p.stem}-{digest[:16]}.terra"


def open_or_build(path: str, read: dict[str, Any], tile_size: int | None = None) -> Path:
    """A store path as is; a DEM is built into a cache store in the user cache folder first (rebuilt only
    when missing or from another version of the DEM)."""
    from terralod.errors import StoreError
    from terralod.pyramid.builder import DEFAULT_METHOD, default_tile_size
    from terralod.store import open_store

    p = Path(path)
    tile_size = tile_size or default_tile_size(DEFAULT_METHOD)
    if p.exists() and is_store(p):
        return p
    hf = load(path, **read)
    cache = cache_store_path(p, hf.digest())
    cache.parent.mkdir(parents=True, exist_ok=True)
    if cache.exists():
        try:
            with open_store(cache) as s:
                if s.complete and s.meta.get("source_digest") == hf.digest():
                    return cache
        except StoreError:
            pass
    run_build(hf, str(cache), tile_size=tile_size, method=DEFAULT_METHOD, workers=None, resume=False,
              overwrite=True)  # fmt: skip
    return cache


def with_fractal(store, path: str, read: dict[str, Any], levels: int | None):
    """The store itself, or with ``levels`` fractal levels below its finest (Hu & Wang), generated on demand
    from the store's source DEM (the DEM given on the command line, else the one recorded in the store)."""
    if levels is None:  # not given: what the store was built with (``terralod build --fractal N``)
        levels = int(store.meta.get("fractal_levels", 0))
    if not levels:
        return store
    from terralod.errors import InputError
    from terralod.fractal import FractalDetail
    from terralod.io.reader import SAMPLE_SOURCE, sample_heightfield
    from terralod.runtime.fractal_source import FractalSource

    src = path if not is_store(Path(path)) else store.meta.get("source", "")
    hf = sample_heightfield() if src == SAMPLE_SOURCE else load(src, **read)
    if hf.digest() != store.meta.get("source_digest"):
        raise InputError("is not the DEM this store was built from; --fractal needs the store's source", src)
    return FractalSource(store, FractalDetail(hf), levels)


def open_terrain_arg(path: str, read: dict[str, Any], fractal_levels: int | None = None):
    """Any input of render / flythrough / view as a :class:`terralod.terrain.Terrain`: a grid store (with its
    fractal levels), a TIN store, or a DEM built into a cache store first. Close it when done."""
    from terralod.store import open_store
    from terralod.terrain import GridTerrain, open_terrain

    p = Path(path)
    check_raster_size(p)
    if p.is_file() and is_store(p):
        t = open_terrain(p)
        if t.kind != "grid":
            return t
        store = t.store  # type: ignore[union-attr]
    else:
        store = open_store(open_or_build(path, read))
    return GridTerrain(store, with_fractal(store, path, read, fractal_levels), own=True)


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


def frame_table(stats: dict[str, Any], title: str = "frame") -> None:
    """One row of frame statistics (tiles, triangles, screen error, select/stitch/draw ms)."""
    t = Table(title=title)
    for col in ("tiles", "triangles", "max screen error px", "select ms", "stitch ms", "draw ms"):
        t.add_column(col, justify="right")
    t.add_row(
        f"{float(stats.get('tiles', 0)):.0f}", f"{float(stats.get('triangles', 0)):,.0f}",
        f"{stats.get('max_screen_error_px', 0):.2f}", f"{stats.get('select_ms', 0):.2f}",
        f"{stats.get('stitch_ms', 0):.2f}", f"{stats.get('draw_ms', 0):.2f}",
    )  # fmt: skip
    console.print(t)


def extent_info(crs: str | None, bounds_m) -> dict[str, Any]:
    """``bounds_m`` [W, S, E, N] in the CRS, ``bounds_lonlat`` [W, S, E, N] in WGS84 degrees (None without
    a CRS) and ``size_km`` [east-west, north-south] of a footprint."""
    w, s_, e, n = (float(v) for v in bounds_m)
    lonlat = None
    if crs:
        try:  # rasterio's PROJ (pyproj is the web extra's)
            from rasterio.warp import transform_bounds

            lonlat = [float(v) for v in transform_bounds(crs, "EPSG:4326", w, s_, e, n, densify_pts=21)]
        except Exception:  # noqa: BLE001 - an unplaceable CRS has no lon/lat, the rest still holds
            lonlat = None
    return {"bounds_m": [w, s_, e, n], "bounds_lonlat": lonlat, "size_km": [(e - w) / 1e3, (n - s_) / 1e3]}


def print_extent(d: dict[str, Any], width: int = 13) -> None:
    """The footprint lines of ``info``: bounds in the CRS and in lon/lat, size in km, elevation range."""
    w, s_, e, n = d["bounds_m"]
    pad = " " * (width - 11)
    console.print(f"  bounds     {pad}W {w:,.1f}  S {s_:,.1f}  E {e:,.1f}  N {n:,.1f} m")
    if d.get("bounds_lonlat"):
        lw, ls, le, ln = d["bounds_lonlat"]
        console.print(f"  lon/lat    {pad}W {lw:.5f}  S {ls:.5f}  E {le:.5f}  N {ln:.5f} deg")
    console.print(f"  size       {pad}{d['size_km'][0]:,.2f} x {d['size_km'][1]:,.2f} km")
    lo, hi = d["elevation_range_m"]
    console.print(f"  elevation  {pad}{lo:,.2f} .. {hi:,.2f} m")


def heightfield_info(hf) -> dict[str, Any]:
    lo, hi = hf.valid_range_m()
    src = hf.nodata_fraction if hf.source_nodata_fraction is None else hf.source_nodata_fraction
    return {
        "kind": "heightfield",
        "source": hf.source,
        "size": [hf.width, hf.height],
        "crs": hf.crs,
        "spacing_m": list(hf.spacing_m),
        **extent_info(hf.crs, hf.bounds_m),
        "elevation_range_m": [lo, hi],
        "nodata_percent": 100.0 * hf.nodata_fraction,
        "source_nodata_percent": 100.0 * src,
        "reprojection_margin_percent": 100.0 * hf.margin_fraction,
        "fill_method": hf.fill_method,
        "notes": list(hf.notes),
    }


def print_store_summary(summary: dict[str, Any]) -> None:
    state = "complete" if summary["complete"] else "INCOMPLETE (finish with --resume)"
    console.print(f"{summary['path']}: {state}")
    bad = summary.get("checksum_failures")
    if bad:  # a line of its own: the path above may already fill the 80 columns
        first = ", ".join(str(tuple(c)) for c in summary.get("checksum_failures_first", [])[:2])
        console.print(f"{bad} tile(s) FAIL their checksums (e.g. {first}): run `terralod check`")
    elif bad == 0:
        console.print("every tile's checksum verified")
    from rich import box

    # compact (fits 80 columns with numbers of 10 digits): errors in metres, size in KiB
    t = Table(box=box.SIMPLE_HEAD, pad_edge=False, collapse_padding=True)
    for col in ("level", "tiles", "vertices", "triangles", "max error m", "max vert. m", "RMS m", "KiB"):
        t.add_column(col, justify="right", no_wrap=True)
    for k, d in summary["per_level"].items():
        t.add_row(
            str(k), f"{d['tiles']:,}", f"{d['vertices']:,}", f"{d['triangles']:,}", _g(d["max_error_m"]),
            _g(d["max_vertical_error_m"]), _g(d["rms_error_m"]), f"{d['bytes'] / 1024:,.0f}",
        )  # fmt: skip
    console.print(t)
    ladder = summary.get("target_error_m")
    if ladder:  # adaptive tiles: what each level was refined to (the measured errors are above)
        steps = ", ".join("0 (grid)" if v == 0 else f"{v:.4g}" for v in ladder)
        console.print(f"target max vertical error per level, m: {steps}")
    console.print(
        f"{summary['levels']} levels, {summary['tiles']}/{summary['tiles_planned']} tiles, tile size "
        f"{summary['tile_size']}, {summary['size_bytes'] / 1024 / 1024:.2f} MiB on disk"
    )


def _g(v: float) -> str:
    """A metre figure in at most 7 characters (3 decimals below 100 m)."""
    return f"{v:.3f}" if abs(v) < 100 else f"{v:,.1f}" if abs(v) < 1e5 else f"{v:.3g}"


def print_tin_summary(d: dict[str, Any]) -> None:
    """Print :func:`terralod.tin.terra.model_summary` output."""
    console.print(
        f"  TIN          {d['vertices']:,} vertices, {d['triangles']:,} triangles (full resolution)"
    )
    base_pct = 100.0 * d["base_triangles"] / max(d["triangles"], 1)
    console.print(f"  base         {d['base_triangles']:,} triangles ({base_pct:.1f} %)")
    console.print(
        f"  scales       {d['scales']:,} ({d['records']:,} ΔT records of {d['collapses_per_record']} collapse(s), "
        f"{d['triangle_changes']:,} triangle changes) in {d['sub_blocks']} sub-blocks"
    )  # fmt: skip
    lo, hi = d["elevation_range_m"]
    console.print(f"  elevation    {lo:.2f} .. {hi:.2f} m")
    svo = d["svo_length_m"]
    console.print(f"  sqrt(MMQE)   {svo['base']:.3f} m at the base, {svo['full']:.3f} m at full resolution")
    if "max_vertical_error_m" in d:
        console.print(
            f"  max error    {d['max_vertical_error_m']['base']:.3f} m vertical at the base (measured), 0 at full"
        )
    if "size_bytes" in d:
        console.print(f"  size         {d['size_bytes']:,} bytes")
    for n in d.get("notes", []):
        console.print(f"  note         {n}")


def one_line(text: object, limit: int = 300) -> str:
    """``text`` on one line (multi-line PROJJSON, GDAL messages), at most ``limit`` characters."""
    t = " ".join(str(text).split())
    return t if len(t) <= limit else t[: limit - 3] + "..."


#: Loggers of the libraries whose warnings (GDAL through rasterio, laspy, Python warnings) would print
#: before the ``terralod:`` line; they are shown with ``-v`` only.
LIBRARY_LOGGERS = ("rasterio", "fiona", "laspy", "py.warnings", "PIL", "numba", "imageio")


def quiet_libraries(verbose: bool) -> None:
    """Route library warnings to logging and show them only with ``-v`` (INFO level and up)."""
    logging.captureWarnings(True)
    if not verbose:  # GDAL's own default handler (messages outside rasterio's handler, e.g. libtiff on close)
        os.environ.setdefault("CPL_LOG", os.devnull)
    for name in LIBRARY_LOGGERS:
        logging.getLogger(name).setLevel(logging.INFO if verbose else logging.CRITICAL)


def _fail(message: str) -> None:
    """Print the one line (after the traceback with -v) and exit 2."""
    if VERBOSE["on"]:
        import traceback

        traceback.print_exc(file=sys.stderr)
    click.echo(f"terralod: {one_line(message, 1000)}", err=True)  # room for a command with two long paths
    sys.exit(2)


def run_main(group: click.Group, argv: list[str] | None) -> None:
    """Run ``group``, turning every failure into one line ``terralod: <file>: <problem>`` and exit code 2;
    ``-v`` prints the traceback before that line and keeps exit code 2."""
    from terralod.errors import TerralodError

    try:
        group.main(args=argv, prog_name="terralod", standalone_mode=False)
    except click.exceptions.Abort:
        err_console.print("terralod: aborted; a build finishes with the same command and --resume")
        sys.exit(130)
    except click.exceptions.Exit as exc:
        sys.exit(exc.exit_code)
    except click.ClickException as exc:
        exc.show()
        sys.exit(2)
    except KeyboardInterrupt:
        err_console.print("terralod: interrupted; finished tiles are saved, finish with --resume")
        sys.exit(130)
    except TerralodError as exc:
        _fail(str(exc))
    except MemoryError:
        last = LAST_INPUT["path"]
        _fail(
            f"{last}: {out_of_memory(last)}"
            if last
            else "out of memory; split the input or use a smaller --tile-size"
        )
    except OSError as exc:
        name = getattr(exc, "filename", None)
        _fail(f"{str(name) + ': ' if name else ''}{exc.strerror or exc}")
    except Exception as exc:  # a bug: still one line (the traceback with -v), never a crash dump
        _fail(f"internal error ({type(exc).__name__}: {exc}); run with -v for the traceback and report it")
