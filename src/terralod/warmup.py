"""Compile the numba kernels ahead of first use, so a first ``terralod demo`` does not sit silent.

The kernels are compiled with ``cache=True`` (:mod:`terralod.kernels`): the machine code is written next
to each module (``__pycache__/*.nbi``/``*.nbc``, or under ``NUMBA_CACHE_DIR``) and later processes load it
in milliseconds. :func:`warm_up` runs a small version of everything the commands do (a build with every
registered method over a heightfield with nodata, selection + stitching + normals of each, fractal
levels below a store, a detail-increment TIN and its selection, quantized-mesh tiles of a projected and
of a geographic grid) and calls the few kernels no command reaches with its defaults, which compiles every
entry point of :func:`terralod.kernels.dispatchers` (and with them every helper kernel) for the argument
types the commands use. ``scripts/install.sh`` runs it (``python -m terralod warmup``).
:func:`kernels_cold` tells a command that the cache is empty, so it can say why it is about to wait.
"""

from __future__ import annotations

import os
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

#: Seconds of CPU a cold compile takes (``terralod warmup`` with an empty cache: 166 s user + 10 s system,
#: measured; one core does it, so an idle machine takes about this long, a loaded one longer).
COLD_COMPILE_S = 180


def kernels_cold() -> bool:
    """True when no compiled kernel is cached yet (a fresh install): cheap, imports nothing."""
    cache = os.environ.get("NUMBA_CACHE_DIR")
    here = Path(__file__).resolve().parent / "kernels"
    dirs = [here / "__pycache__"]
    if cache:
        dirs.append(Path(cache))
    for d in dirs:
        try:
            if any(p.suffix == ".nbi" for p in d.rglob("*.nbi")):
                return False
        except OSError:
            continue
    return True


def _terrain(n: int = 80, seed: int = 1):
    from terralod.heightfield import Heightfield

    rng = np.random.default_rng(seed)
    r, c = np.mgrid[0:n, 0:n].astype(np.float64)
    z = 300.0 * np.exp(-((r - n / 2) ** 2 + (c - n / 2) ** 2) / (n * n / 8)) + rng.normal(0.0, 2.0, (n, n))
    valid = np.ones((n, n), bool)
    valid[: n // 6, : n // 6] = False  # a corner of nodata: the fill and the footprint run too
    valid[rng.random((n, n)) < 0.01] = False
    return Heightfield.from_array(z.astype(np.float32), 30.0, origin_m=(500000.0, 4100000.0), valid=valid)


def _frames(terrain) -> None:
    from terralod.render.offscreen import overview_pose
    from terralod.runtime import Camera

    pose = overview_pose(terrain)
    for cull, async_loads in (((), False), (("backface", "region"), True)):  # async: as the viewer runs
        eng = terrain.engine(threshold_px=1.0, cull=cull, async_loads=async_loads)
        try:
            for d in (1.0, 0.3, 0.3):
                eye = np.asarray(pose.target) + (np.asarray(pose.eye) - np.asarray(pose.target)) * d
                frame = eng.update(
                    Camera(tuple(eye), pose.target, (0.0, 0.0, 1.0), 45.0, 320, 180, near_m=1.0)
                )
                for _ in frame.meshes():
                    pass
                if async_loads and hasattr(eng, "wait_loads"):  # the TIN engine holds its model in memory
                    eng.wait_loads(10.0)
        finally:
            eng.close()


def _web_tiles(hf) -> None:
    """Quantized-mesh tiles, with normals, of a projected grid (257² samples a tile, errors against
    scattered samples) and of a geographic one (its own lattice: clipping, u/v merge, lattice errors, the
    goal zoom's parent), the three finest zooms of each: every export kernel."""
    from affine import Affine

    from terralod.export.quantized_mesh import QuantizedMesh
    from terralod.export.source import SourceGrid

    z, valid = np.asarray(hf.elevation_m, np.float64), np.asarray(hf.valid)
    arc3 = 1.0 / 1200.0  # SRTM3's spacing, degrees
    for src in (
        SourceGrid(z, valid, hf.transform, "EPSG:32631", "warmup-utm"),
        SourceGrid(
            z.astype(np.float32), valid, Affine(arc3, 0.0, 1.0, 0.0, -arc3, 42.0), "EPSG:4326", "warmup"
        ),
    ):
        qm = QuantizedMesh(src, normals=True)
        for zoom in range(max(qm.max_zoom - 2, 0), qm.max_zoom + 1):
            x0, y0, _, _ = qm.level_range(zoom)
            qm.tile(zoom, x0, y0)


def _library_kernels(hf) -> None:
    """The kernels no step above reaches: options the commands leave at their defaults (cohesion without
    refinement), big meshes (32-bit triangle codes), the renderer's near plane, fractal statistics."""
    from terralod.fractal import FractalDetail
    from terralod.kernels import noise
    from terralod.kernels.cull import min_distance_to_triangles
    from terralod.pyramid.cohesion import make_mesher
    from terralod.pyramid.original import original_error
    from terralod.store import encode_triangles
    from terralod.tiles import TilePyramid

    pyramid = TilePyramid(hf.width, hf.height, 17)
    make_mesher(refine=False)(
        hf.elevation_m, hf.valid, pyramid, (pyramid.max_level - 1, 1, 1), spacing_m=hf.spacing_m
    )
    for dt in (np.int32, np.int64):
        encode_triangles(np.array([[0, 1, 70000]], dt))
    tri = np.array([[0, 1, 2]], np.int64)
    min_distance_to_triangles(np.eye(3) * 10.0, tri, 0.0, 0.0, 0.0)
    # a reprojected DEM's builds: a tile against the original samples (the demo's sample is projected)
    original_error(np.eye(3) * 10.0, tri, np.array([1.0]), np.array([1.0]), np.array([0.5]))
    _ = FractalDetail(hf).hurst_map
    noise.axis_variogram(np.asarray(hf.elevation_m, np.float64), 2)
    noise.gauss_grid(1, 3, 0, 0, 2, 2)
    # the 3D Tiles export's mesh topology (a terrain without a CRS exports nothing); a TIN's points are
    # read-only
    from terralod.kernels.meshtopo import (
        add_rows,
        compact_triangles,
        first_use,
        lone_edge_mask,
        merge_pairs,
        used_bounds,
    )

    pts = np.eye(3) * 10.0
    lone_edge_mask(tri, 3)
    add_rows(np.zeros((3, 3)), merge_pairs(np.ascontiguousarray(pts[:, :2]).view(np.int64)), pts)
    compact_triangles(tri, 3)
    first_use(tri.ravel(), 3)
    used_bounds(pts, tri)
    pts.setflags(write=False)
    used_bounds(pts, tri)
    # the crack detector (runtime.find_cracks): border segments of a tile and the gaps across one line
    from terralod.kernels.stitch import border_segments, line_pair_gaps

    segs = border_segments(tri, np.arange(3.0), np.ones(3, np.bool_), np.zeros(3))
    two = np.array([0, len(segs), 2 * len(segs)], np.int64)
    line_pair_gaps(
        np.concatenate([segs, segs]), two, np.zeros(2), np.full(2, 2.0), np.array([-1, 1]), np.arange(2),
        np.linspace(0.0, 1.0, 5), 1e-9,
    )  # fmt: skip
    # the change's error model: the sum of spherical variograms its fit evaluates
    from terralod.kernels.variogram import spherical_sum

    spherical_sum(np.arange(1.0, 4.0), np.array([2.0, 1.0]))
    # a TIN store's quantized-mesh export: the bucket grid that locates points in its triangles
    from terralod.kernels.tinlocate import bucket_triangles, locate_points, plane_heights

    xs, ys = np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.0, 1.0])
    start, items = bucket_triangles(xs, ys, tri, 1, 1, 0.0, 0.0, 1.0, 1.0)
    t = locate_points(xs, ys, tri, start, items, 1, 1, 0.0, 0.0, 1.0, 1.0, np.array([0.2]), np.array([0.2]))
    plane_heights(np.zeros((1, 3)), t, np.array([0.2]), np.array([0.2]))
    # a TIN's ladder of scales (its 3D Tiles pyramid)
    from terralod.kernels.qem_replay import halving_rungs

    halving_rungs(np.array([1.0, 0.4, 0.0]))


def warm_up(report: Callable[[str], None] | None = None) -> dict[str, float]:
    """Compile (and cache) every kernel the commands use. Returns seconds per step."""
    from terralod.pyramid.builder import METHODS, build_store
    from terralod.store import open_store
    from terralod.terrain import GridTerrain

    say = report or (lambda _msg: None)
    out: dict[str, float] = {}
    hf = _terrain()
    with tempfile.TemporaryDirectory(prefix="terralod-warmup-") as tmp:
        for method in sorted(METHODS):
            t0 = time.perf_counter()
            p = Path(tmp) / f"{method}.terra"
            build_store(hf, p, tile_size=17, method=method, workers=2)
            with open_store(p) as s:
                _frames(GridTerrain(s))
            out[f"build + frames ({method})"] = time.perf_counter() - t0
            say(f"  {method}: {out[f'build + frames ({method})']:.1f} s")
        t0 = time.perf_counter()
        try:
            from terralod.fractal import FractalDetail
            from terralod.runtime.fractal_source import FractalSource

            with open_store(Path(tmp) / "chunked.terra") as s:
                _frames(GridTerrain(s, FractalSource(s, FractalDetail(hf), 1)))
            out["fractal levels"] = time.perf_counter() - t0
            say(f"  fractal levels: {out['fractal levels']:.1f} s")
        except Exception as exc:  # noqa: BLE001 - a warm-up step that fails only leaves its kernels cold
            say(f"  fractal levels skipped ({exc})")
        t0 = time.perf_counter()
        try:
            from terralod.terrain import open_terrain
            from terralod.tin import DetailIncrementModel
            from terralod.tin import delaunay_blocks as db
            from terralod.tin.delaunay import delaunay_tin
            from terralod.tin.terra import save_model_to_store

            model = DetailIncrementModel.from_heightfield(_terrain(48, 2), sub_blocks=4, base_fraction=0.2)
            # a point cloud's Delaunay step, in one piece and in blocks (big clouds)
            xy = np.random.default_rng(3).uniform(0.0, 100.0, (400, 2))
            delaunay_tin(np.c_[xy, np.zeros(400)])
            db.fill_holes(xy, [db.block_triangles(j) for j in db.block_jobs(xy, db.block_layout(xy, 100))])
            save_model_to_store(model, Path(tmp) / "tin.terra", overwrite=True)
            with open_terrain(Path(tmp) / "tin.terra") as t:
                _frames(t)
            out["tin"] = time.perf_counter() - t0
            say(f"  tin: {out['tin']:.1f} s")
        except Exception as exc:  # noqa: BLE001
            say(f"  tin skipped ({exc})")
    t0 = time.perf_counter()
    try:
        _web_tiles(hf)
        out["web tiles"] = time.perf_counter() - t0
        say(f"  web tiles: {out['web tiles']:.1f} s")
    except ImportError as exc:  # the web extra (pydelatin, pyproj) is not installed
        say(f"  web tiles skipped ({exc})")
    t0 = time.perf_counter()
    _library_kernels(hf)
    out["library kernels"] = time.perf_counter() - t0
    say(f"  library kernels: {out['library kernels']:.1f} s")
    return out
