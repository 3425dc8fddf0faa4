"""Drive a build: plan the pyramid, mesh every tile on worker threads, quantise, measure, write the store.

Order: finest level first, so each tile's stored error can be made monotone at once
(``error_m = max(measured, children's error_m)``) and an interrupted build never needs a second pass.
Tiles are meshed on a thread pool (the numba kernels release the GIL), handed to it in tasks of
consecutive tiles of one level (:data:`_TASK_SAMPLES`), and committed to SQLite in batches, each batch one
transaction; ``resume=True`` skips the committed tiles and produces a store whose
tiles are byte-identical to an uninterrupted build (everything is deterministic).
"""

from __future__ import annotations

import collections
import dataclasses
import itertools
import logging
import math
import os
import time
from collections.abc import Callable, Iterable, Iterator, MutableMapping
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from terralod.error import measure_error_window
from terralod.errors import BuildMismatchError, StoreError
from terralod.heightfield import Heightfield
from terralod.kernels import jit
from terralod.kernels.codec import quantise_tile
from terralod.pyramid import adaptive, chunked, cohesion
from terralod.pyramid.footprint import drop_nodata
from terralod.pyramid.original import error_reference, error_reference_line, original_error, tile_samples
from terralod.store import (
    FORMAT_VERSION,
    EncodedTile,
    LevelQuantisation,
    TileStore,
    encode_triangles,
    encode_vertices,
    install_store,
    remove_store_files,
    replacement_path,
)
from terralod.tiles import TileCode, TilePyramid, is_valid_tile_size

log = logging.getLogger(__name__)

#: Tile meshers by method name: (z, valid, pyramid, code) -> (rows, cols, heights_m, triangles).
MeshFn = Callable[
    [np.ndarray, np.ndarray, TilePyramid, TileCode], tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]
]
#: A mesher with a true ``needs_spacing`` attribute is also given ``spacing_m=(dx, dy)`` (metres).
METHODS: dict[str, MeshFn] = {
    "chunked": chunked.mesh_tile,
    "cohesion": cohesion.mesh_tile,
    "adaptive": adaptive.mesh_tile,
    "adaptive_ladder": adaptive.make_mesher(finest_level_error_m=None),
}
# Adaptive tiles (halving ladder from the root, a lossless grid finest level, 33² tiles) are the default:
# along the 2 px camera paths they draw 0.39-0.43x the vertex cohesion map's triangles (Sung, Lee & Shin (2021); itself
# 0.41-0.48x Chunked LOD's) and build 1.3-1.5x faster (benchmarks/results/build.md).
DEFAULT_METHOD = "adaptive"

#: Extra relief (metres) the fixed quantisation of a store of epochs leaves at least (plan_quantisation).
EPOCH_HEADROOM_M = 500.0

#: Tiles committed per SQLite transaction (bounded by time as well, see ``_COMMIT_SECONDS``).
_BATCH_TILES = 64
_COMMIT_SECONDS = 0.5
#: Tiles in flight per worker thread (submitted, not yet committed).
_AHEAD_PER_WORKER = 8
#: Levels of at most this many tiles a worker are meshed first (their tiles are the largest).
_EARLY_PER_WORKER = 2
#: Tiles built before the store exists (while its meta is computed) held at most; then the build waits.
_HELD_TILES = 4096
#: Source samples a task of the thread pool covers at least: consecutive tiles of one level go together
#: (16 tiles of stride 1, 4 of stride 2, one from stride 4 up), so the pool's hand-off and the Python
#: around a task, held under the GIL, are paid once per about 65 k samples rather than per 65² tile
#: (a stride-1 tile is measured in about half a millisecond).
_TASK_SAMPLES = 16 * 64 * 64


#: Tile size M of a method that states none (``mesher.default_tile_size``): Chunked LOD's and the cohesion
#: map's 65² grids. Adaptive tiles state 33: with the ladder's root fixed at a 65² tile's vertex count
#: (:data:`terralod.pyramid.adaptive.ROOT_VERTICES`) that is one ladder level more than 65 before the
#: lossless grid, each tile a quarter of the area (benchmarks/results/build.md).
DEFAULT_TILE_SIZE = 65


def default_tile_size(method: str) -> int:
    """The tile size M a build of ``method`` uses when none is given."""
    fn = METHODS.get(method)
    return int(getattr(fn, "default_tile_size", DEFAULT_TILE_SIZE))


def register_method(name: str, fn: MeshFn) -> None:
    """Make a tile mesher available to :func:`build_store` under ``name``."""
    METHODS[name] = fn


@dataclass
class BuildReport:
    """What a build did: tiles written now, tiles found already done (resume), seconds, samples/s."""

    path: Path
    tiles_total: int
    tiles_built: int
    tiles_skipped: int
    seconds: float
    source_samples: int
    per_level: dict[int, dict[str, float]] = field(default_factory=dict)

    @property
    def samples_per_second(self) -> float:
        return self.source_samples / self.seconds if self.seconds > 0 else math.inf


@jit
def _level_max_range(z: np.ndarray, s: int, m: int, step: int) -> float:
    """Largest (max - min) height over the rows and columns ``step`` apart (edge-replicated) of any tile
    window of a level: ``step = s`` takes the level's grid vertices; ``step = 1`` every source sample
    (relocated vertices may sit on any sample, or between samples with bilinear heights, so all samples
    bound their heights)."""
    h, w = z.shape
    span = (m - 1) * s
    n = span // step + 1
    nty = -(-(h - 1) // span)
    ntx = -(-(w - 1) // span)
    best = 0.0
    for ty in range(nty):
        for tx in range(ntx):
            lo = np.inf
            hi = -np.inf
            for i in range(n):
                r = min(ty * span + i * step, h - 1)
                for j in range(n):
                    c = min(tx * span + j * step, w - 1)
                    v = z[r, c]
                    if v < lo:
                        lo = v
                    if v > hi:
                        hi = v
            if hi - lo > best:
                best = hi - lo
    return best


def plan_quantisation(
    hf: Heightfield, pyramid: TilePyramid, *, grid_vertices: bool = True, headroom: bool = False
) -> dict[int, LevelQuantisation]:
    """Per-level 16-bit lattices: horizontal fractional bits and a vertical step that fits every tile.

    The vertical step is the largest vertex-height range of any tile of the level over 65534 steps, so
    ``z0_index + q`` never overflows 16 bits and every tile of a level shares one lattice. With
    ``grid_vertices`` (meshers whose vertices are the level's grid, e.g. Chunked LOD) the range is taken
    over the grid vertices; otherwise over every source sample of the tile window. With ``headroom`` (a
    store of epochs, whose lattice is fixed once for all of them) the range planned is
    ``max(2 r, r + 500 m)`` for a measured range r, so later epochs may grow its relief that much.
    """
    out = {}
    for k in pyramid.levels:
        stride = pyramid.stride(k)
        rng = _level_max_range(hf.elevation_m, stride, pyramid.tile_size, stride if grid_vertices else 1)
        if headroom:
            rng = max(2.0 * rng, rng + EPOCH_HEADROOM_M)
        step = max(float(rng) / 65534.0, 1e-6)
        out[k] = LevelQuantisation(pyramid.xy_frac_bits(k), step)
    return out


def _store_meta(
    hf: Heightfield, pyramid: TilePyramid, method: str, quant: dict[int, LevelQuantisation]
) -> dict[str, Any]:
    paths = list(getattr(hf, "paths", None) or [])
    files = {"source_files": [str(Path(p).resolve()) if Path(p).exists() else str(p) for p in paths]}
    return {
        **(files if len(paths) > 1 else {}),  # a mosaic: its files, so an export can read them again
        "source": hf.source,
        "source_digest": hf.digest(),
        "crs": hf.crs,
        "transform": list(tuple(hf.transform)[:6]),
        "spacing_m": list(hf.spacing_m),
        "width": hf.width,
        "height": hf.height,
        "tile_size": pyramid.tile_size,
        "max_level": pyramid.max_level,
        "method": method,
        # a mesher with ``build_meta(z, valid, pyramid)`` states its options (the adaptive error ladder)
        "build_options": {
            "method": method,
            "tile_size": pyramid.tile_size,
            **getattr(METHODS[method], "build_meta", lambda *_: {})(hf.elevation_m, hf.valid, pyramid),
        },
        "fill_method": hf.fill_method,
        "notes": list(hf.notes),
        "nodata_fraction": hf.nodata_fraction,
        "source_nodata_fraction": getattr(hf, "source_nodata_fraction", None),  # a reprojected source's own
        "margin_fraction": getattr(hf, "margin_fraction", 0.0),  # the grid outside the source's footprint
        "quantisation": {
            str(k): {"xy_frac_bits": q.xy_frac_bits, "z_step_m": q.z_step_m} for k, q in quant.items()
        },
        "builder_version": FORMAT_VERSION,
        # a resampled source: every error includes its own samples (terralod.pyramid.original)
        **(
            {} if hf.original_grid is None else {"errors_measured_against": error_reference(hf.original_grid)}
        ),
    }


def _quantise(
    rows: np.ndarray, cols: np.ndarray, hz: np.ndarray, r0: int, c0: int, q: LevelQuantisation
) -> tuple[np.ndarray, int]:
    scale = math.ldexp(1.0, q.xy_frac_bits)  # bits < 0 at coarse levels of rasters over 32,769 samples
    u = np.rint((cols - c0) * scale)
    v = np.rint((rows - r0) * scale)
    zi = np.rint(hz / q.z_step_m).astype(np.int64)
    z0 = int(zi.min())
    qz = zi - z0
    if u.min() < 0 or v.min() < 0 or max(u.max(), v.max(), qz.max()) > 65535:
        raise AssertionError("quantisation overflow")  # the plan makes this impossible
    return np.stack([u, v, qz], axis=1).astype(np.uint16), z0


def same_file(a: str | os.PathLike[str], b: str | os.PathLike[str] | None) -> bool:
    """True when ``a`` and ``b`` name one existing file (same path, hard link or symlink)."""
    try:
        return b is not None and os.path.samefile(a, b)
    except (OSError, ValueError):
        return False


def build_tile(
    hf: Heightfield,
    pyramid: TilePyramid,
    code: TileCode,
    quant: LevelQuantisation,
    mesh_fn: MeshFn,
    child_errors: list[tuple[float, float]],
) -> EncodedTile:
    """Mesh, quantise, dequantise and measure one tile; monotone errors from its children."""
    return with_child_errors(measure_tile(hf, pyramid, code, quant, mesh_fn), child_errors)


def with_child_errors(enc: EncodedTile, child_errors: list[tuple[float, float]]) -> EncodedTile:
    """The tile with its stored errors made monotone: ``error_m = max(measured, children's error_m)`` and
    likewise the vertical error (the measured fields are left as measured)."""
    if not child_errors:
        return enc
    err = max([enc.measured_error_m] + [e for e, _ in child_errors])
    verr = max([enc.measured_vertical_error_m] + [v for _, v in child_errors])
    return dataclasses.replace(enc, error_m=float(err), vertical_error_m=float(verr))


def measure_tile(
    hf: Heightfield, pyramid: TilePyramid, code: TileCode, quant: LevelQuantisation, mesh_fn: MeshFn
) -> EncodedTile:
    """Mesh, quantise, dequantise and measure one tile, its stored errors its measured ones (the builder
    makes them monotone with :func:`with_child_errors` once its children are done)."""
    r0, c0 = pyramid.origin_rc(code)
    if getattr(mesh_fn, "needs_spacing", False):
        spaced: Callable[..., tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = mesh_fn
        rows, cols, hz, tris = spaced(hf.elevation_m, hf.valid, pyramid, code, spacing_m=hf.spacing_m)
    else:
        rows, cols, hz, tris = mesh_fn(hf.elevation_m, hf.valid, pyramid, code)
    span = pyramid.span(code[0])
    r1 = min(r0 + span, hf.height - 1)
    c1 = min(c0 + span, hf.width - 1)
    # The fill is for meshing only: triangles over nodata are not stored (terralod.pyramid.footprint).
    rows, cols, hz, tris = drop_nodata(rows, cols, hz, tris, hf.valid, hf.valid[r0 : r1 + 1, c0 : c1 + 1])
    if rows.shape[0] == 0:  # the tile lies wholly in nodata: stored empty, its error its children's
        zc = float(hf.elevation_m[r0, c0])
        return EncodedTile(code=code, error_m=0.0, vertical_error_m=0.0, measured_error_m=0.0,
                           measured_vertical_error_m=0.0, rms_error_m=0.0, n_samples=0, z_min_m=zc, z_max_m=zc,
                           n_vertices=0, n_triangles=0, z0_index=0,
                           vertices=encode_vertices(np.zeros((0, 3), np.uint16)),
                           triangles=encode_triangles(np.zeros((0, 3), np.int32)))  # fmt: skip
    # Quantised, and dequantised to measure the geometry exactly as stored (one kernel: _quantise's numbers).
    dx, dy = hf.spacing_m
    qv, z0_i, local, ok = quantise_tile(
        np.ascontiguousarray(rows, np.float64), np.ascontiguousarray(cols, np.float64),
        np.ascontiguousarray(hz, np.float64), int(r0), int(c0), int(quant.xy_frac_bits),
        float(quant.z_step_m), float(dx), float(dy),
    )  # fmt: skip
    if not ok:
        raise AssertionError("quantisation overflow")  # the plan makes this impossible
    z0 = int(z0_i)
    tris = np.ascontiguousarray(tris)
    if tris.dtype not in (np.int32, np.int64):
        tris = tris.astype(np.int64)
    # made here (quantise_tile's float64 vertices, a mesher's triangles): measured without the API's checks
    rep = measure_error_window(
        local, tris, hf.elevation_m[r0 : r1 + 1, c0 : c1 + 1], hf.valid[r0 : r1 + 1, c0 : c1 + 1], dx, dy,
        check=False,
    )  # fmt: skip
    err, verr = float(rep.hausdorff_m), float(rep.max_vertical_m)
    rms, n_samples = float(rep.rms_vertical_m), int(rep.n_samples)
    if hf.original_grid is not None:  # a resampled source: its own samples too (terralod.pyramid.original)
        origin, ro, co = hf.origin_m, 0, 0
        frame = getattr(pyramid, "frame_origin_m", None)
        if frame is not None:  # a window of the terrain: placed from the terrain's origin, absolute rows/cols
            origin, ro, co = frame, pyramid.row_offset, pyramid.col_offset  # type: ignore[attr-defined]
        px, py, pz = tile_samples(hf.original_grid, str(hf.crs), origin, (dx, dy), (r0 + ro, c0 + co),
                                  (r1 + ro, c1 + co))  # fmt: skip
        orig = original_error(local, tris, px, py, pz)
        err, verr = max(err, orig.max_vertical_m), max(verr, orig.max_vertical_m)
        rms, n_samples = orig.rms_m, orig.n_samples  # RMS and count over the source's own samples
    return EncodedTile(
        code=code,
        error_m=err,
        vertical_error_m=verr,
        measured_error_m=err,
        measured_vertical_error_m=verr,
        rms_error_m=rms,
        n_samples=n_samples,
        z_min_m=float(local[:, 2].min()),
        z_max_m=float(local[:, 2].max()),
        n_vertices=int(qv.shape[0]),
        n_triangles=int(tris.shape[0]),
        z0_index=z0,
        vertices=encode_vertices(qv),
        triangles=encode_triangles(tris, n_vertices=int(qv.shape[0])),
    )


def _tasks(pyramid: TilePyramid, codes: list[TileCode]) -> list[tuple[TileCode, ...]]:
    """``codes`` in order, cut into tasks: runs of consecutive tiles of one level covering at least
    :data:`_TASK_SAMPLES` source samples (a tile of level k covers ``span(k)^2``)."""
    tasks: list[tuple[TileCode, ...]] = []
    run: list[TileCode] = []
    for code in codes:
        if run and (run[0][0] != code[0] or len(run) * pyramid.span(code[0]) ** 2 >= _TASK_SAMPLES):
            tasks.append(tuple(run))
            run = []
        run.append(code)
    if run:
        tasks.append(tuple(run))
    return tasks


def _ordered_map(
    pool: ThreadPoolExecutor,
    fn: Callable[[Any], Any],
    items: list[Any],
    ahead: int,
    early: Iterable[Any] = (),
    early_after: Callable[[], bool] | None = None,
    hold: Callable[[Any], bool] | None = None,
) -> Iterator[Any]:
    """``pool.map(fn, items)``: results in the order of ``items`` (the builder's tasks), with at most
    ``ahead`` of them submitted ahead of the one consumed (a big build never holds more finished tasks than
    that in memory), except the ``early`` items, submitted before the others (the few largest tiles, so
    that no core waits alone for one of them at the end of the build) as soon as ``early_after()`` is true.
    An item for which ``hold(item)`` is true is not submitted ahead (nor any after it) until it is the one
    consumed."""
    futs: dict[Any, Future[Any]] = {}
    submitted: set[Any] = set()
    waiting = list(early)
    nxt = 0

    def submit(item: Any) -> None:
        if item not in submitted:
            submitted.add(item)
            futs[item] = pool.submit(fn, item)

    def top_up(limit: int) -> None:
        nonlocal nxt, waiting
        if waiting and (early_after is None or early_after()):
            for code in waiting:
                submit(code)
            waiting = []
        while nxt < len(items) and nxt < limit:
            if hold is not None and items[nxt] not in submitted and hold(items[nxt]):
                break
            submit(items[nxt])
            nxt += 1

    try:
        for i, code in enumerate(items):
            top_up(i + ahead)
            submit(code)  # the one consumed now, held or not
            done = futs.pop(code).result()
            top_up(i + 1 + ahead)
            yield done
    finally:
        for f in futs.values():
            f.cancel()


def hold_until(
    tiles: Iterator[EncodedTile], ready: Future[Any], errors: MutableMapping[TileCode, tuple[float, float]]
) -> list[EncodedTile]:
    """The tiles a build finishes before its store exists: taken from ``tiles`` until ``ready`` (the
    store's meta) is done or :data:`_HELD_TILES` are held, each one's errors recorded for its parent."""
    held: list[EncodedTile] = []
    while not ready.done() and len(held) < _HELD_TILES:
        enc = next(tiles, None)
        if enc is None:
            break
        errors[enc.code] = (enc.error_m, enc.vertical_error_m)
        held.append(enc)
    return held


def commit_streamed(
    store: TileStore,
    tiles: Iterable[EncodedTile],
    errors: MutableMapping[TileCode, tuple[float, float]],
    built: int,
    written: Callable[[int], None],
) -> int:
    """The one writer of a build: finished tiles committed in transactions of ``_BATCH_TILES`` tiles or
    ``_COMMIT_SECONDS`` seconds (local threads and Dask workers alike); each tile's errors recorded in
    ``errors`` for its parent. Returns ``built`` plus the tiles written; ``written(total so far)`` after each
    transaction."""
    batch: list[EncodedTile] = []
    last = time.perf_counter()
    for enc in tiles:
        batch.append(enc)
        errors[enc.code] = (enc.error_m, enc.vertical_error_m)
        now = time.perf_counter()
        if len(batch) >= _BATCH_TILES or now - last > _COMMIT_SECONDS:
            store.write_tiles(batch)
            built += len(batch)
            batch, last = [], now
            written(built)
    if batch:
        store.write_tiles(batch)
        built += len(batch)
        written(built)
    return built


def build_store(
    hf: Heightfield,
    path: str | os.PathLike[str],
    *,
    tile_size: int | None = None,
    method: str = DEFAULT_METHOD,
    workers: int | None = None,
    resume: bool = False,
    overwrite: bool = False,
    progress: Callable[[int, int], None] | None = None,
    stop_after: int | None = None,
    quantisation: dict[int, LevelQuantisation] | None = None,
    epoch: str | None = None,
) -> BuildReport:
    """Build the LOD tile store of ``hf`` at ``path``.

    Parameters
    ----------
    hf : the source heightfield (metres).
    path : output ``.terra`` file.
    tile_size : M, vertices per tile side, 2^n + 1 (None: the method's, :func:`default_tile_size`: 33 for
        adaptive tiles, 65 for chunked and cohesion).
    method : tile mesher, a key of :data:`METHODS` ("adaptive", "chunked", "cohesion").
    workers : threads meshing tiles (default: all cores).
    resume : continue an interrupted build of the same source and options at ``path``.
    overwrite : replace an existing file at ``path``.
    progress : called as ``progress(done, total)`` after each committed batch.
    stop_after : build at most this many new tiles, then return (tests of interrupted builds).
    quantisation : per-level lattices to use instead of planning them (e.g. a store of epochs' own, to
        compare an update with a fresh build of the same epoch).
    epoch : name of the store's first epoch (e.g. "2000-09-25"): the store keeps the source samples and
        plans its quantisation with headroom, so ``terralod update`` can add epochs (terralod.pyramid.update).
    """
    if method not in METHODS:
        raise ValueError(f"Expected a method in {sorted(METHODS)}, got {method!r}")
    if tile_size is None:
        tile_size = default_tile_size(method)
    if not is_valid_tile_size(tile_size):
        raise ValueError(f"Expected a tile size 2^n + 1 (e.g. 33, 65, 129), got {tile_size}")
    p = Path(path)
    if same_file(p, hf.source):
        raise StoreError("is the input DEM of this build; choose another output", str(p))
    t_start = time.perf_counter()
    pyramid = TilePyramid(hf.width, hf.height, tile_size)
    quant = quantisation or plan_quantisation(
        hf, pyramid, grid_vertices=(method == "chunked"), headroom=epoch is not None
    )
    fresh = not (p.exists() and resume)
    target = p  # where tiles go: p itself, or (--overwrite) a temporary renamed over p once complete
    store: TileStore | None = None
    if not fresh:
        meta = _store_meta(hf, pyramid, method, quant)
        with TileStore.open(p) as old:  # read-only first: a complete store needs no write access
            for key in ("source_digest", "build_options", "quantisation", "width", "height", "tile_size"):
                if old.meta.get(key) != meta[key]:
                    raise BuildMismatchError(
                        f"cannot resume: the store's {key} differs from this build (other source or "
                        "options); use --overwrite to rebuild",
                        str(p),
                    )
            n_done, n_total = len(old.tile_codes()), len(pyramid.all_codes())
            if old.complete and n_done == n_total:
                log.info("%s is complete; nothing to resume", p)
                return BuildReport(p, n_total, 0, n_done, time.perf_counter() - t_start, hf.width * hf.height)
        store = TileStore.open(p, writable=True)
        if epoch is not None:  # the first epoch of a store of epochs: its map and source samples
            store.start_first_epoch(str(epoch), hf)
    elif p.exists() or p.is_symlink():
        if not overwrite:
            raise StoreError("already exists; use --resume to finish it or --overwrite to replace it", str(p))
        if p.is_dir():
            raise StoreError("is a directory, not a tile store", str(p))
        target = replacement_path(p)  # the old store stays whole until the new one is complete
    mesh_fn = METHODS[method]
    # A fresh build meshes the levels that need no stated options (adaptive's finest level, the grid)
    # while the store's meta is computed beside them (the source digest; adaptive's ladder, a TIN of the
    # whole terrain), and creates the store once it is known; the levels that need the ladder start then.
    free: set[int] = getattr(mesh_fn, "levels_without_options", lambda _: set())(pyramid) if fresh else set()
    side = ThreadPoolExecutor(max_workers=1)
    meta_f = side.submit(_store_meta, hf, pyramid, method, quant)

    codes = pyramid.all_codes(finest_first=True)
    built = 0
    try:
        errors = store.tile_errors() if store is not None else {}
        done = set(errors)
        total = len(codes)
        todo = [c for c in codes if c not in done]
        n_skipped = total - len(todo)
        n_workers = max(1, workers or os.cpu_count() or 1)
        if progress:
            progress(n_skipped, total)
        if stop_after is not None:
            todo = todo[: max(0, stop_after)]
        with ThreadPoolExecutor(max_workers=n_workers) as pool:
            # One stream over every level, finest first: a tile is meshed and measured without waiting for
            # its children (only its stored errors need theirs), so the coarse tiles overlap the fine ones
            # instead of a level's last tiles leaving cores idle; the tiles are committed in order, so a
            # tile's children are recorded in ``errors`` before it is made monotone.
            def one(task: tuple[TileCode, ...]) -> list[EncodedTile]:
                return [measure_tile(hf, pyramid, code, quant[code[0]], mesh_fn) for code in task]

            def monotone(encs: Iterable[EncodedTile]) -> Iterator[EncodedTile]:
                for enc in encs:
                    yield with_child_errors(enc, [errors[c] for c in pyramid.children(enc.code)])

            # the tiles of the coarsest levels (at most _EARLY_PER_WORKER a worker) are the largest: first,
            # once the meta (the ladder they mesh to) is known
            counts = collections.Counter(c[0] for c in todo)
            early = {c[0] for c in todo if counts[c[0]] <= _EARLY_PER_WORKER * n_workers and c[0] not in free}
            tasks = _tasks(pyramid, todo)
            stream = monotone(itertools.chain.from_iterable(
                _ordered_map(pool, one, tasks, _AHEAD_PER_WORKER * n_workers, [t for t in tasks if t[0][0] in early],
                             early_after=meta_f.done, hold=lambda t: t[0][0] not in free and not meta_f.done())
            ))  # fmt: skip
            held: list[EncodedTile] = []
            if store is None:  # tiles built before the store exists wait here (errors recorded for parents)
                held = hold_until(stream, meta_f, errors)
                if target != p:
                    remove_store_files(target)
                store = TileStore.create(target, meta_f.result())
                if epoch is not None:  # the first epoch of a store of epochs: its map and source samples
                    store.start_first_epoch(str(epoch), hf)
            built = commit_streamed(store, itertools.chain(held, stream),
                                    errors, built, lambda n: progress(n_skipped + n, total) if progress else None)  # fmt: skip
        if n_skipped + built == total:
            store.complete_first_epoch()
            store.set_meta("complete", True)
    except BaseException:
        side.shutdown(cancel_futures=True)
        if store is not None:
            store.close()
        if target != p:
            remove_store_files(target)
        raise
    side.shutdown()
    store.close()
    if target != p:
        if n_skipped + built == total:
            install_store(target, p)
        else:
            remove_store_files(target)  # stopped early (stop_after): the old store stays as it was
    seconds = time.perf_counter() - t_start
    log.info("built %d tiles (%d already present) in %.2f s", built, n_skipped, seconds)
    return BuildReport(p, total, built, n_skipped, seconds, hf.width * hf.height)


def store_summary(store: TileStore) -> dict[str, Any]:
    """Per-level table of a store: tiles, vertices, triangles, max/mean error, bytes (summed by SQLite:
    memory independent of the tiles' number)."""
    per: dict[int, dict[str, Any]] = {}
    for level, d in store.level_summaries().items():
        d = dict(d)
        d.pop("z_min_m")
        d.pop("z_max_m")
        sum_rms_sq = d.pop("sum_rms_sq") or 0.0
        d["rms_error_m"] = math.sqrt(sum_rms_sq / d["samples"]) if d["samples"] else 0.0
        per[level] = d
    return {
        "path": str(store.path),
        "complete": store.complete,
        "levels": len(store.levels),
        "tile_size": store.tile_size,
        "tiles": sum(d["tiles"] for d in per.values()),
        "tiles_planned": sum(nx * ny for nx, ny in map(store.pyramid.grid_count, store.pyramid.levels)),
        "size_bytes": store.size_bytes(),
        "per_level": dict(sorted(per.items())),
        # the adaptive error ladder the store states (target max vertical error per level, metres)
        "target_error_m": (store.meta.get("build_options") or {}).get("target_error_m"),
        # one line: the samples the errors are measured against (the original ones of a resampled source)
        "errors_against": error_reference_line(store.meta),
    }
