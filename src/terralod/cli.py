"""The ``terralod`` command line: ``info``, ``build``, ``demo``.

User mistakes (missing file, wrong format, no valid samples, unwritable output, corrupt store) print one
line ``terralod: <file>: <problem>`` and exit with code 2; ``-v`` adds diagnostics and the traceback.
"""

from __future__ import annotations

import json
import logging
import os
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
    console.print(
        f"{summary['path']}: {'complete' if summary['complete'] else 'INCOMPLETE (finish with --resume)'}"
    )
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
    from terralod.pyramid.builder import store_summary
    from terralod.store import open_store

    p = Path(path)
    if p.exists() and _is_store(p):
        from terralod.store import TIN_METHOD, read_tin_store, store_method

        if store_method(p) == TIN_METHOD:
            meta, _ = read_tin_store(p)  # checksum verified
            meta["size_bytes"] = p.stat().st_size
            if as_json:
                click.echo(json.dumps(meta, indent=2, default=str))
            else:
                console.print(f"source {meta.get('source')}, method tin (paper 003), CRS {_crs_name(meta.get('crs'))}")
                print_tin_summary(meta)
            return
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
    from terralod.pyramid.builder import build_store

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
@click.option(
    "--method", default="cohesion", show_default=True,
    help="Tile mesher: cohesion (paper 000, the vertex cohesion map) or chunked (Chunked LOD); tin builds a "
    "detail-increment TIN (paper 003), the default for LAS/LAZ input.",
)  # fmt: skip
@click.option("--sub-blocks", default="4", show_default=True, help="TIN: sub-blocks, a square number or auto.")
@click.option(
    "--base-fraction", type=float, default=0.2, show_default=True, help="TIN: triangles kept in the base mesh."
)
@click.option("--workers", type=int, default=None, help="Threads (default: all cores).")
@click.option("--resume", is_flag=True, help="Finish an interrupted build of the same input.")
@click.option("--overwrite", is_flag=True, help="Replace an existing output store.")
@click.option(
    "--fractal", "fractal_levels", type=click.IntRange(0, 6), default=0, show_default=True,
    help="Fractal levels below the DEM that view/render/flythrough add by default (paper 001; generated "
    "on demand from the source DEM, never stored).",
)  # fmt: skip
@_read_options
def build(
    input_path: str, output: str, tile_size: int, method: str, sub_blocks: str, base_fraction: float, workers,
    resume, overwrite, fractal_levels, **read: Any,
) -> None:  # fmt: skip
    """Build the level-of-detail tile store of a DEM, or the detail-increment TIN of a LAS/LAZ cloud."""
    from terralod.pyramid.builder import METHODS, store_summary
    from terralod.store import open_store
    from terralod.tiles import is_valid_tile_size

    if method == "tin" or Path(input_path).suffix.lower() in (".las", ".laz"):
        _build_tin(input_path, output, sub_blocks, base_fraction, overwrite, read)
        return

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
    if fractal_levels:
        from terralod.store import TileStore

        with TileStore.open(output, writable=True) as s:
            s.set_meta("fractal_levels", int(fractal_levels))
        console.print(f"fractal: {fractal_levels} levels below the DEM when viewed (from {input_path})")
    with open_store(output) as s:
        print_store_summary(store_summary(s))


def _build_tin(input_path: str, output: str, sub_blocks: str, base_fraction: float, overwrite: bool,
               read: dict[str, Any]) -> None:  # fmt: skip
    """``build --method tin``: LAS/LAZ points (or a DEM's samples) → detail-increment TIN store."""
    import time

    from terralod.errors import StoreError
    from terralod.tin import DetailIncrementModel
    from terralod.tin.terra import save_model_to_store

    blocks: int | str = sub_blocks
    if sub_blocks != "auto":
        try:
            blocks = int(sub_blocks)
        except ValueError:
            raise click.BadParameter(f"expected a square number or auto, got {sub_blocks!r}",
                                     param_hint="--sub-blocks") from None  # fmt: skip
    if not 0.0 < base_fraction <= 1.0:
        raise click.BadParameter(f"expected a fraction in (0, 1], got {base_fraction}", param_hint="--base-fraction")
    if Path(output).exists() and not overwrite:
        raise StoreError("already exists (pass --overwrite to replace it)", output)
    t0 = time.perf_counter()
    if Path(input_path).suffix.lower() in (".las", ".laz"):
        model = DetailIncrementModel.from_las(input_path, sub_blocks=blocks, base_fraction=base_fraction)
    else:
        model = DetailIncrementModel.from_heightfield(_load(input_path, **read), sub_blocks=blocks,
                                                      base_fraction=base_fraction)  # fmt: skip
    summary = save_model_to_store(model, output, overwrite=overwrite)
    console.print(f"built a detail-increment TIN (paper 003) in {time.perf_counter() - t0:.2f} s")
    print_tin_summary(summary)


def print_tin_summary(d: dict[str, Any]) -> None:
    """Print :func:`terralod.tin.terra.model_summary` output."""
    console.print(f"  TIN          {d['vertices']:,} vertices, {d['triangles']:,} triangles (full resolution)")
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
        console.print(f"  max error    {d['max_vertical_error_m']['base']:.3f} m vertical at the base (measured), 0 at full")
    if "size_bytes" in d:
        console.print(f"  size         {d['size_bytes']:,} bytes")
    for n in d.get("notes", []):
        console.print(f"  note         {n}")


# -- fractal amplification -----------------------------------------------------------------------------
@cli.command()
@click.argument("input_path", metavar="INPUT")
@click.option("-o", "--output", required=True, help="Output GeoTIFF with the finer spacing.")
@click.option("--factor", default=4, show_default=True, help="Refinement factor (power of 2).")
@click.option("--seed", default=0, show_default=True, help="Seed of the world-position hash.")
@click.option("--hurst", type=float, default=None, help="Hurst exponent H (default: estimated per region).")
@click.option("--sigma", type=float, default=None, help="fBm sigma, metres (default: estimated per region).")
@_read_options
def amplify(input_path: str, output: str, factor: int, seed: int, hurst, sigma, **read: Any) -> None:
    """Add fractal (fBm) detail below the DEM's resolution (paper 001); every DEM sample is kept exactly."""
    from terralod.fractal import amplify_command

    hf = _load(input_path, **read)
    summary = amplify_command(hf, output, factor=factor, seed=seed, hurst=hurst, sigma=sigma)
    console.print(
        f"wrote {output}: {summary['shape_out'][1]}x{summary['shape_out'][0]} samples "
        f"at {summary['spacing_out_m'][0]:.3f} m (x{factor}), mean H {summary['hurst']['mean']:.2f}, "
        f"{summary['seconds']:.2f} s"
    )


# -- rendering -----------------------------------------------------------------------------------------
def _triple(text: str, name: str) -> tuple[float, float, float]:
    try:
        v = tuple(float(a) for a in text.split(","))
    except ValueError:
        raise click.BadParameter(f"expected X,Y,Z in metres, got {text!r}", param_hint=name) from None
    if len(v) != 3:
        raise click.BadParameter(f"expected X,Y,Z in metres, got {text!r}", param_hint=name)
    return v  # type: ignore[return-value]


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(a) for a in text.lower().split("x"))
        assert 16 <= w <= 8192 and 16 <= h <= 8192
    except (ValueError, AssertionError):
        raise click.BadParameter(
            f"expected WIDTHxHEIGHT between 16 and 8192, got {text!r}", param_hint="--size"
        ) from None
    return w, h


def _view_options(fn):
    """--fractal and --cull, shared by render, flythrough and view."""
    fn = click.option(
        "--cull", multiple=True, type=click.Choice(["backface", "region"]),
        help="Skip drawing back-facing tiles (paper 001 §3.2) / tiles outside the visible region (§3.1).",
    )(fn)  # fmt: skip
    return click.option(
        "--fractal", "fractal_levels", type=click.IntRange(0, 6), default=None,
        help="Fractal levels below the DEM (0-6; default: the store's, from build --fractal).",
    )(fn)  # fmt: skip


def _open_or_build(path: str, read: dict[str, Any], tile_size: int = 65) -> Path:
    """A store path as is; a DEM is built into a cache store beside it first (rebuilt only when missing)."""
    p = Path(path)
    if p.exists() and _is_store(p):
        return p
    hf = _load(path, **read)
    cache = p.with_name(p.name + ".terra")
    from terralod.errors import StoreError
    from terralod.pyramid.builder import DEFAULT_METHOD
    from terralod.store import open_store

    if cache.exists():
        try:
            with open_store(cache) as s:
                if s.complete and s.meta.get("source_digest") == hf.digest():
                    return cache
        except StoreError:
            pass
    run_build(
        hf, str(cache), tile_size=tile_size, method=DEFAULT_METHOD, workers=None, resume=False, overwrite=True
    )
    return cache


def _with_fractal(store, path: str, read: dict[str, Any], levels: int):
    """The store itself, or with ``levels`` fractal levels below its finest (paper 001), generated on demand
    from the store's source DEM (the DEM given on the command line, else the one recorded in the store)."""
    if levels is None:  # not given: what the store was built with (``terralod build --fractal N``)
        levels = int(store.meta.get("fractal_levels", 0))
    if not levels:
        return store
    from terralod.errors import InputError
    from terralod.fractal import FractalDetail
    from terralod.io.reader import SAMPLE_SOURCE, sample_heightfield
    from terralod.runtime.fractal_source import FractalSource

    src = path if not _is_store(Path(path)) else store.meta.get("source", "")
    hf = sample_heightfield() if src == SAMPLE_SOURCE else _load(src, **read)
    if hf.digest() != store.meta.get("source_digest"):
        raise InputError("is not the DEM this store was built from; --fractal needs the store's source", src)
    return FractalSource(store, FractalDetail(hf), levels)


def _settings(background: str | None, mode: str, wireframe: bool):
    from terralod.render import RenderSettings

    st = RenderSettings(mode=mode, wireframe=wireframe)
    if background:
        try:
            rgb = tuple(float(a) for a in background.split(","))
            assert len(rgb) == 3
        except (ValueError, AssertionError):
            raise click.BadParameter(
                f"expected R,G,B, got {background!r}", param_hint="--background"
            ) from None
        st.background = tuple(c / 255.0 if max(rgb) > 1.0 else c for c in rgb)  # type: ignore[assignment]
    return st


def _stats_table(stats: dict[str, Any], title: str = "frame") -> None:
    t = Table(title=title)
    for col in ("tiles", "triangles", "max screen error px", "select ms", "stitch ms", "draw ms"):
        t.add_column(col, justify="right")
    t.add_row(
        str(stats.get("tiles")), f"{int(stats.get('triangles', 0)):,}", f"{stats.get('max_screen_error_px', 0):.2f}",
        f"{stats.get('select_ms', 0):.2f}", f"{stats.get('stitch_ms', 0):.2f}", f"{stats.get('draw_ms', 0):.2f}",
    )  # fmt: skip
    console.print(t)


@cli.command()
@click.argument("path")
@click.option("-o", "--output", required=True, help="PNG to write.")
@click.option("--eye", help="Eye X,Y,Z in world metres (default: an overview).")
@click.option("--target", help="Target X,Y,Z in world metres.")
@click.option("--size", default="1920x1080", show_default=True, help="WIDTHxHEIGHT pixels.")
@click.option("--threshold-px", default=2.0, show_default=True, help="Screen-space error threshold, pixels.")
@click.option("--background", help="Sky colour R,G,B (0..1 or 0..255).")
@click.option(
    "--mode", type=click.Choice(["elevation", "lod", "error"]), default="elevation", show_default=True
)
@click.option("--wireframe", is_flag=True)
@_view_options
@_read_options
def render(
    path, output, eye, target, size, threshold_px, background, mode, wireframe, fractal_levels, cull, **read: Any
) -> None:
    """Render one frame of a store (or a DEM, built first) to a PNG, headless (EGL)."""
    from terralod.render.offscreen import CameraPose, FrameRenderer, overview_pose, save_png
    from terralod.store import open_store

    w, h = _size(size)
    if eye and not target or target and not eye:
        raise click.BadParameter("give both --eye and --target", param_hint="--eye")
    if _is_tin_store(path):
        _render_tin(path, output, eye, target, w, h, threshold_px, _settings(background, mode, wireframe))
        return
    store_path = _open_or_build(path, read)
    with open_store(store_path) as s:
        pose = overview_pose(s)
        if eye or target:
            if not (eye and target):
                raise click.BadParameter("give both --eye and --target", param_hint="--eye")
            pose = CameraPose(_triple(eye, "--eye"), _triple(target, "--target"))
        src = _with_fractal(s, path, read, fractal_levels)
        fr = FrameRenderer(
            src, w, h, threshold_px=threshold_px, settings=_settings(background, mode, wireframe), cull=cull
        )
        img = fr.frame(pose)
        save_png(img, output)
        fr.close()
    _stats_table(fr.last_stats, f"{output}")


def _is_tin_store(path: str) -> bool:
    from terralod.store import TIN_METHOD, store_method

    p = Path(path)
    return p.is_file() and _is_store(p) and store_method(p) == TIN_METHOD


def _render_tin(path: str, output: str, eye, target, w: int, h: int, threshold_px: float, settings) -> None:
    """``render`` of a TIN store: every sub-block at its SVO scale (paper 003 §2.3.2) for the camera."""
    from terralod.render.offscreen import CameraPose, save_png
    from terralod.render.tin import TinFrameRenderer, tin_overview_pose
    from terralod.tin.terra import load_model_from_store

    model, _ = load_model_from_store(path)
    pose = tin_overview_pose(model)
    if eye and target:
        pose = CameraPose(_triple(eye, "--eye"), _triple(target, "--target"))
    fr = TinFrameRenderer(model, w, h, threshold_px=threshold_px, settings=settings)
    save_png(fr.frame(pose), output)
    fr.close()
    st = fr.last_stats
    console.print(
        f"{output}: {st['triangles']:,} triangles, {st['sub_blocks']} sub-blocks at their SVO scales "
        f"({st['records_applied']:,} ΔT records applied), select {st['select_ms']:.2f} ms, records "
        f"{st['apply_ms']:.2f} ms, meshes {st['mesh_ms']:.2f} ms, draw {st['draw_ms']:.2f} ms"
    )


@cli.command()
@click.argument("path")
@click.option("-o", "--output", required=True, help="MP4 to write.")
@click.option(
    "--path", "cam_path", default="auto", show_default=True, help="auto, or a JSON camera path file."
)
@click.option("--frames", default=120, show_default=True, help="Frames of the auto path.")
@click.option("--fps", default=24, show_default=True)
@click.option("--size", default="1280x720", show_default=True, help="WIDTHxHEIGHT pixels.")
@click.option("--threshold-px", default=2.0, show_default=True)
@_view_options
@_read_options
def flythrough(
    path, output, cam_path, frames, fps, size, threshold_px, fractal_levels, cull, **read: Any
) -> None:
    """Render a fly-through video of a store (or a DEM, built first), headless."""
    from terralod.store import open_store

    w, h = _size(size)
    store_path = _open_or_build(path, read)
    with open_store(store_path) as s:
        src = _with_fractal(s, path, read, fractal_levels)
        summary = render_flythrough(src, output, cam_path=cam_path, frames=frames, fps=fps, size=(w, h),
                                    threshold_px=threshold_px, cull=cull)  # fmt: skip
    _flythrough_table(summary)


def render_flythrough(store, output: str, *, cam_path: str = "auto", frames: int = 120, fps: int = 24,
                      size=(1280, 720), threshold_px: float = 2.0, png: str | None = None,
                      cull: tuple[str, ...] = ()) -> dict[str, Any]:  # fmt: skip
    """Render a camera path to MP4; returns per-frame statistics summarised."""
    import numpy as np

    from terralod.render.offscreen import FrameRenderer, auto_path, load_path, save_png, write_video

    poses = auto_path(store, frames) if cam_path == "auto" else load_path(cam_path)
    fr = FrameRenderer(store, size[0], size[1], threshold_px=threshold_px, cull=cull)
    per_frame: list[dict[str, Any]] = []

    def gen():
        for i, pose in enumerate(poses):
            img = fr.frame(pose)
            per_frame.append(fr.last_stats)
            if png and i == len(poses) // 2:
                save_png(img, png)
            yield img

    n = write_video(gen(), output, fps=fps)
    fr.close()
    keys = ("tiles", "triangles", "max_screen_error_px", "select_ms", "stitch_ms", "draw_ms")
    return {"output": output, "frames": n, **{k: float(np.median([f.get(k, 0.0) for f in per_frame])) for k in keys},
            "max_screen_error_px_max": float(max(f.get("max_screen_error_px", 0.0) for f in per_frame))}  # fmt: skip


def _flythrough_table(summary: dict[str, Any]) -> None:
    t = Table(title=f"{summary['output']}: {summary['frames']} frames (medians)")
    for col in ("tiles", "triangles", "max screen error px", "select ms", "stitch ms", "draw ms"):
        t.add_column(col, justify="right")
    t.add_row(
        f"{summary['tiles']:.0f}", f"{summary['triangles']:,.0f}", f"{summary['max_screen_error_px']:.2f}",
        f"{summary['select_ms']:.2f}", f"{summary['stitch_ms']:.2f}", f"{summary['draw_ms']:.2f}",
    )  # fmt: skip
    console.print(t)


@cli.command()
@click.argument("path")
@click.option("--size", default="1280x720", show_default=True, help="Window WIDTHxHEIGHT.")
@click.option("--threshold-px", default=2.0, show_default=True)
@click.option("--frames", type=int, default=None, help="Close after this many frames (scripted runs).")
@click.option("--screenshot", help="PNG written after the last frame (with --frames).")
@_view_options
@_read_options
def view(path, size, threshold_px, frames, screenshot, fractal_levels, cull, **read: Any) -> None:
    """Open the real-time viewer on a store (or a DEM, built into a cache store first)."""
    from terralod.render.viewer import run_viewer
    from terralod.store import open_store

    w, h = _size(size)
    store_path = _open_or_build(path, read)
    if not os.environ.get("DISPLAY") and not os.environ.get("WAYLAND_DISPLAY"):
        raise click.UsageError(
            "no display (DISPLAY is unset); use `terralod render` or `terralod flythrough`"
        )
    if _is_tin_store(path):
        from terralod.render.tin import run_tin_viewer
        from terralod.tin.terra import load_model_from_store

        out = run_tin_viewer(load_model_from_store(path)[0], path, width_px=w, height_px=h,
                             threshold_px=threshold_px, max_frames=frames, screenshot=screenshot)  # fmt: skip
        if frames:
            click.echo(json.dumps({"frames": out["frames"], "hud": out["hud"], "stats": out["stats"]}, default=str))
        return
    with open_store(store_path) as s:
        out = run_viewer(_with_fractal(s, path, read, fractal_levels), width_px=w, height_px=h, threshold_px=threshold_px, max_frames=frames,
                         screenshot=screenshot, cull=cull)  # fmt: skip
    if frames:
        click.echo(
            json.dumps({"frames": out["frames"], "hud": out["hud"], "stats": out["stats"]}, default=str)
        )


# -- demo ----------------------------------------------------------------------------------------------
@cli.command()
@click.option("-o", "--output", default="demo.terra", show_default=True, help="Store to build.")
@click.option("--tile-size", default=33, show_default=True, help="Vertices per tile side.")
@click.option("--frames", default=96, show_default=True, help="Fly-through frames when there is no display.")
@click.option("--no-window", is_flag=True, help="Render demo.mp4 + demo.png even when a display is present.")
def demo(output: str, tile_size: int, frames: int, no_window: bool) -> None:
    """Build the bundled real DEM (matplotlib's Jacksboro fault, Tennessee), then open the viewer, or with
    no display render a fly-through to demo.mp4 plus demo.png and print the statistics."""
    from terralod.io.reader import sample_heightfield
    from terralod.pyramid.builder import DEFAULT_METHOD, store_summary
    from terralod.store import open_store

    hf = sample_heightfield()
    d = heightfield_info(hf)
    console.print(
        f"[bold]{d['source']}[/bold]: {d['size'][0]}x{d['size'][1]} samples at {d['spacing_m'][0]:.1f} m, "
        f"{d['elevation_range_m'][0]:.0f}..{d['elevation_range_m'][1]:.0f} m, CRS {_crs_name(d['crs'])}"
    )
    rep = run_build(
        hf, output, tile_size=tile_size, method=DEFAULT_METHOD, workers=None, resume=False, overwrite=True
    )
    console.print(f"built {rep.tiles_built} tiles in {rep.seconds:.2f} s")
    with open_store(output) as s:
        print_store_summary(store_summary(s))
        if (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")) and not no_window:
            from terralod.render.viewer import run_viewer

            run_viewer(s)
            return
        stem = Path(output).with_suffix("")
        summary = render_flythrough(s, f"{stem}.mp4", frames=frames, size=(1024, 576), png=f"{stem}.png")
    _flythrough_table(summary)
    console.print(f"wrote {stem}.mp4 and {stem}.png")


@cli.group()
def bench() -> None:
    """Reproducible experiments of benchmarks/ (results in benchmarks/results/)."""


@bench.command("cohesion")
@click.option("--quick", is_flag=True, help="Puget Sound and the bundled sample only.")
@click.option("--frames", default=48, show_default=True, help="Frames of the camera path.")
def bench_cohesion(quick: bool, frames: int) -> None:
    """Vertex cohesion map vs Chunked LOD (benchmarks/cohesion_vs_chunked.py)."""
    import runpy

    script = Path(__file__).resolve().parents[2] / "benchmarks" / "cohesion_vs_chunked.py"
    if not script.exists():
        raise click.ClickException(f"{script}: benchmark script not found (run from a source checkout)")
    runpy.run_path(str(script), run_name="terralod_bench")["main"](
        ["--frames", str(frames)] + (["--quick"] if quick else [])
    )


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
    except RuntimeError as exc:  # no GPU context / no window
        if _VERBOSE["on"]:
            raise
        click.echo(f"terralod: {exc}", err=True)
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
