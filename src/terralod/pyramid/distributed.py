"""Out-of-core and Dask-distributed builds: tiles as work units that read their own windows.

:func:`build_store_windowed` builds the same store as :func:`terralod.pyramid.builder.build_store`
from a :class:`terralod.io.windowed.WindowSource` (a COG, a GeoTIFF, a VRT mosaic, or an in-memory
Heightfield behind the same interface) without ever holding the whole DEM:

1. **Plan, streamed** (:func:`scan_source`): one pass over the source in full-width strips of one tile
   row of some level (at most ``SCAN_STRIP_SAMPLES`` samples) computes the store's source digest
   (sha256 of the elevations, then of the packed mask: :meth:`Heightfield.digest`'s bytes, fed strip by
   strip; the mask bits wait in a temporary file) and every level's quantisation lattice: each strip
   gives the per-tile (min, max) of its finest tiles on every level's vertex lattice, merged up the
   quadtree, so the vertical steps are :func:`~terralod.pyramid.builder.plan_quantisation`'s exactly.
2. **Work units**: a level's tiles are grouped into g x g blocks (g * span about ``UNIT_SPAN_SAMPLES``);
   a unit reads its window (the tiles' samples, plus the halo a mesher declares, clipped to the data) and
   builds each tile with the builder's own :func:`~terralod.pyramid.builder.build_tile` on a window
   Heightfield, through a pyramid whose origins are shifted to the window (:class:`WindowPyramid`). The
   meshers only ever see the samples of ``[r0, min(r0 + span, H - 1)]`` and decide clipping from the
   window's shape, which ends where the data ends, so every tile is the in-memory build's byte for byte
   (tested on GeoTIFFs, both methods).
3. **Coarse tiles**: a tile whose window exceeds ``max_window_samples`` is meshed from a decimated copy
   (every f-th sample, f a power of two <= its stride, plus the data's last row and column, read in
   strips) through a pyramid whose strides are divided by f, and its error is then measured against
   *every* full-resolution sample it covers, streamed in strips of rows (``MEASURE_STRIP_SAMPLES``) with a
   margin of one quad of triangles above and below each strip (a sample's distance is taken to the
   triangles within that margin: an upper bound of the exact distance, equal to it unless the nearest
   surface point is over a quad away); its footprint (triangles over nodata dropped,
   :mod:`terralod.pyramid.footprint`) is judged on the decimated samples. Such tiles are not the
   in-memory build's (deviation, below);
   ``max_window_samples=None`` never decimates and gives the in-memory tiles at every level, with peak
   memory bounded by the root's window, ``(span_0 + 1)^2`` samples at 5 bytes each as read (float32 +
   mask), plus 9 for cohesion's float64 copy and mask (its coarse levels refine on the full-resolution
   source): about 3.7 GB for a 16385² root (an estimate from the array sizes, not measured). The default
   budget (4097² samples read whole) bounds a work unit at about 14 bytes x 16.8 M = 235 MB plus the
   mesher's per-quad arrays, and a thread runner runs one such large unit at a time
   (``_LARGE_UNITS_IN_FLIGHT``; the fine units go on beside it); a process also holds GDAL's block cache
   (capped at 64 MiB by the window source), the window source's caches (a fixed size whatever the
   region's, :mod:`terralod.io.windowed`, :mod:`terralod.pyramid.original`) and one plan strip (at most
   ``SCAN_STRIP_SAMPLES``). The heap a unit frees is handed back to the kernel
   (:func:`release_free_heap`), so what stays resident is the units in flight and those caches.
4. **One writer**: results stream back (threads or Dask futures, as they complete) to the caller's
   process, which commits them in transactions of at most ``_BATCH_TILES`` tiles or
   ``_COMMIT_SECONDS`` (the builder's policy). No barrier between levels: the units of the coarsest
   levels (the largest tiles: the root reads a decimated copy of the whole DEM) are submitted first, the
   rest finest first, at most ``_AHEAD_UNITS_PER_SLOT`` per worker thread in flight; a unit returns its
   tiles' *measured* errors, and the writer takes a tile once its children's errors are recorded,
   making its stored errors monotone there (:func:`_monotone`, the same numbers as before); the tiles
   waiting for their children are bounded by the units in flight plus the early ones.
   ``resume=True`` skips committed tiles.

Dask (:func:`dask_client`): ``"local"`` starts a LocalCluster of worker processes (``threads`` each), an
address ``tcp://HOST:PORT`` connects to a running scheduler (refused in one line, before anything is
written, when it cannot be reached). A :class:`~terralod.io.windowed.RasterSource` travels inside each
task (it pickles as its paths: each worker opens the file itself); an in-memory source is scattered to
every worker once. Each unit is a task with ``retries``; a worker that dies has its units rebuilt
elsewhere by the scheduler, a unit whose future the scheduler cancels (its scattered source lost with a
worker, a client reconnect) is resubmitted; a client that dies leaves a store that ``resume=True``
finishes.
Meshers are looked up by name on the workers (:data:`~terralod.pyramid.builder.METHODS` as imported there).

Beyond one SQLite writer. SQLite takes one writer; the writer's ceiling (tiles/s, measured by
``benchmarks/scale.py``) bounds a build once the workers outpace it. Two ways further: (a) a shared file
system (NFS, Lustre, an object-store mount) that every worker reads the source from and writes
*per-worker shard stores* to (``TileStore.create`` on ``big.terra.shard-<worker>``, same meta, tiles of
disjoint quadtree blocks), merged at the end by one process with ``INSERT INTO tiles SELECT * FROM
shard.tiles`` per attached shard, a bulk copy of a few hundred MB/s, not a per-tile commit; the coarse
levels, which need the children's errors, then run after the merge (they are a 1/3 of a percent of the
tiles); (b) per-worker shards kept as they are and a store that opens a set of shard files by quadtree
prefix (a directory of stores, like a COG's overviews split across files), which needs no merge at all.
Either keeps the format: each shard is an ordinary store.

Deviation: coarse tiles (window over ``max_window_samples``) are meshed from a decimated copy, so they
are not the in-memory build's tiles; their errors are measured on every full-resolution sample, so the
selection's guarantee holds. With cohesion a relocated vertex of such a tile at the data's last row or
column, where that row falls between two decimated rows, sits on the decimated lattice row after it
(at most f - 1 samples past the data's edge); its height is the last row's.
"""

from __future__ import annotations

import dataclasses
import hashlib
import itertools
import logging
import math
import os
import tempfile
import time
from collections.abc import Callable, Iterable, Iterator, MutableMapping
from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from affine import Affine

from terralod.error import measure_error_window
from terralod.errors import BuildMismatchError, InputError, StoreError, WorkerLostError
from terralod.heightfield import Heightfield
from terralod.io.windowed import ArraySource, WindowSource
from terralod.kernels import jit
from terralod.pyramid import builder
from terralod.pyramid.footprint import drop_nodata
from terralod.store import (
    EncodedTile,
    LevelQuantisation,
    TileStore,
    decode_triangles,
    decode_vertices,
    encode_triangles,
    encode_vertices,
    install_store,
    remove_store_files,
    replacement_path,
)
from terralod.store_epochs import SOURCE_BLOCK, epoch_record
from terralod.tiles import TileCode, TilePyramid, is_valid_tile_size, parent

log = logging.getLogger(__name__)

__all__ = [
    "StreamPlan",
    "WindowPyramid",
    "build_store_windowed",
    "build_unit",
    "dask_client",
    "release_free_heap",
    "scan_source",
    "tune_worker_malloc",
]

#: Samples of one full-width strip of the planning scan (float32 + bool: 5 bytes a sample).
SCAN_STRIP_SAMPLES = 1 << 25
#: Samples of one full-width strip of the ladder's read (:func:`_ladder_read`, beside the first units): the
#: scan's 2^25 held some 290 MB at once there from 64 SRTM3 tiles up, the early peak of their builds.
LADDER_STRIP_SAMPLES = 1 << 22
#: A work unit groups g x g tiles of a level so that g * span is about this many samples.
UNIT_SPAN_SAMPLES = 1024
#: Largest tile window (samples) read whole; larger (coarse) tiles are meshed from a decimated copy.
MAX_WINDOW_SAMPLES = 4097 * 4097
#: Samples per strip when a coarse tile streams its full-resolution window (or its original samples). A
#: strip's measurement holds some 200 bytes a sample at once (the window, its mask, the original samples'
#: coordinates, the kernels' arrays): 2^22 made every coarse tile of a build a 350-450 MiB spike over the
#: fine units beside it (an RSS sampler by unit in flight); 2^20 took the build of 16 SRTM3 tiles from
#: 1,094 to 847-870 MiB peak (benchmarks/region.py) at the same CPU time.
MEASURE_STRIP_SAMPLES = 1 << 20


# -- the streamed plan ---------------------------------------------------------------------------------
@jit
def _kmin(i, n, levels):
    """Coarsest level whose vertex lattice holds sample row (or column) i of n: level k's lattice is the
    multiples of its stride 2^(L - k) and the data's last sample n - 1."""
    if i == 0 or i == n - 1:
        return 0
    tz = 0
    while (i & 1) == 0 and tz < levels:
        i >>= 1
        tz += 1
    return levels - tz


@jit
def _finest_tile_ranges(z, row0, h, w, levels, span, lo, hi):
    """Per finest tile (rows of tiles of the strip starting at data row ``row0``): the min and max of its
    window's samples on each level's lattice. lo, hi: (ty, tx, L + 1), filled here."""
    nty, ntx = lo.shape[0], lo.shape[1]
    sh = z.shape[0]
    for ty in range(nty):
        r0 = ty * span
        r1 = min(r0 + span, h - 1 - row0, sh - 1)
        for tx in range(ntx):
            c0 = tx * span
            c1 = min(c0 + span, w - 1)
            for k in range(levels + 1):
                lo[ty, tx, k] = np.inf
                hi[ty, tx, k] = -np.inf
            for r in range(r0, r1 + 1):
                kr = _kmin(row0 + r, h, levels)
                for c in range(c0, c1 + 1):
                    k = max(kr, _kmin(c, w, levels))
                    v = z[r, c]
                    if v < lo[ty, tx, k]:
                        lo[ty, tx, k] = v
                    if v > hi[ty, tx, k]:
                        hi[ty, tx, k] = v
            for k in range(1, levels + 1):  # a coarser lattice is part of every finer one
                lo[ty, tx, k] = min(lo[ty, tx, k], lo[ty, tx, k - 1])
                hi[ty, tx, k] = max(hi[ty, tx, k], hi[ty, tx, k - 1])


def _merge_up(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(min, max) of the 2 x 2 children of each parent tile (missing children ignored)."""
    ny, nx, k = lo.shape
    py, px = -(-ny // 2), -(-nx // 2)
    plo = np.full((2 * py, 2 * px, k), np.inf)
    phi = np.full((2 * py, 2 * px, k), -np.inf)
    plo[:ny, :nx], phi[:ny, :nx] = lo, hi
    plo = plo.reshape(py, 2, px, 2, k).min(axis=(1, 3))
    phi = phi.reshape(py, 2, px, 2, k).max(axis=(1, 3))
    return plo, phi


@dataclass(frozen=True)
class StreamPlan:
    """What one streamed pass over a source finds: the store's digest and quantisation, nodata count.

    Attributes
    ----------
    digest : :meth:`Heightfield.digest` of the source as read (filled elevations, mask, frame).
    range_grid_m, range_all_m : per level, the largest vertex-height range of a tile, over the level's grid
        vertices (meshers such as Chunked LOD) and over every sample (cohesion), metres.
    xy_frac_bits : per level, the pyramid's horizontal fractional bits.
    n_invalid : nodata samples.
    z_range_m : (lowest, highest) valid elevation, metres.
    """

    digest: str
    range_grid_m: tuple[float, ...]
    range_all_m: tuple[float, ...]
    xy_frac_bits: tuple[int, ...]
    n_invalid: int
    n_samples: int
    z_range_m: tuple[float, float] = (0.0, 0.0)

    def quant(self, grid_vertices: bool, headroom: bool = False) -> dict[int, LevelQuantisation]:
        """The builder's lattices (:func:`~terralod.pyramid.builder.plan_quantisation`, ``headroom`` for a
        store of epochs) from the measured ranges."""
        out = {}
        for k, r in enumerate(self.range_grid_m if grid_vertices else self.range_all_m):
            rng = max(2.0 * r, r + builder.EPOCH_HEADROOM_M) if headroom else r
            out[k] = LevelQuantisation(self.xy_frac_bits[k], max(float(rng) / 65534.0, 1e-6))
        return out


def scan_source(
    src: WindowSource, pyramid: TilePyramid, *, strip_samples: int = SCAN_STRIP_SAMPLES
) -> StreamPlan:
    """Stream ``src`` once in full-width strips: digest, per-level lattices, nodata count (see module doc)."""
    h, w = src.height, src.width
    levels = pyramid.max_level
    span_f = pyramid.span(levels)
    # strip = one tile row of level kb: the coarsest level whose strip fits (the finest level always)
    kb = levels
    while kb > 0 and (pyramid.span(kb - 1) + 1) * w <= strip_samples:
        kb -= 1
    strip = pyramid.span(kb)
    per = strip // span_f  # finest tile rows per strip
    ntx = pyramid.grid_count(levels)[0]
    rng_grid = np.zeros(levels + 1)
    rng_all = np.zeros(levels + 1)
    coarse_lo: list[np.ndarray] = []
    coarse_hi: list[np.ndarray] = []
    hz = hashlib.sha256()
    n_invalid = 0
    carry = np.zeros(0, bool)
    zmin, zmax = math.inf, -math.inf
    with tempfile.TemporaryFile() as bits:
        for row0 in range(0, h - 1, strip):
            r1 = min(row0 + strip, h - 1)
            z, ok = src.read(row0, 0, r1 + 1, w)
            z = np.ascontiguousarray(z, dtype=np.float32)
            own = z.shape[0] if r1 == h - 1 else strip  # rows this strip owns (the last row is the next's)
            hz.update(np.ascontiguousarray(z[:own]))  # the bytes, without a copy
            flat = np.concatenate([carry, ok[:own].ravel()])
            cut = flat.size - flat.size % 8
            bits.write(np.packbits(flat[:cut]).tobytes())
            carry = flat[cut:]
            n_invalid += int(own * w - np.count_nonzero(ok[:own]))
            if np.any(ok[:own]):
                zv = z[:own][ok[:own]]
                zmin, zmax = min(zmin, float(zv.min())), max(zmax, float(zv.max()))
            nty = min(per, -(-(h - 1 - row0) // span_f))
            lo = np.empty((nty, ntx, levels + 1))
            hi = np.empty((nty, ntx, levels + 1))
            _finest_tile_ranges(z, row0, h, w, levels, span_f, lo, hi)
            for k in range(levels, kb - 1, -1):
                rng_grid[k] = max(rng_grid[k], float((hi[..., k] - lo[..., k]).max()))
                rng_all[k] = max(rng_all[k], float((hi[..., levels] - lo[..., levels]).max()))
                if k > kb:
                    lo, hi = _merge_up(lo, hi)
            coarse_lo.append(lo)
            coarse_hi.append(hi)
        if carry.size:
            bits.write(np.packbits(carry).tobytes())
        hz.update(_file_bytes(bits))
    if n_invalid == h * w:
        raise InputError("band has no valid samples (all nodata)", src.source)
    if max(abs(zmin), abs(zmax)) > 1e5:
        raise InputError(f"elevations reach {zmin:.6g}..{zmax:.6g} m, beyond any terrain; check the vertical "
                         "scale or nodata value", src.source)  # fmt: skip
    lo, hi = np.concatenate(coarse_lo, axis=0), np.concatenate(coarse_hi, axis=0)
    for k in range(kb - 1, -1, -1):
        lo, hi = _merge_up(lo, hi)
        rng_grid[k] = float((hi[..., k] - lo[..., k]).max())
        rng_all[k] = float((hi[..., levels] - lo[..., levels]).max())
    hz.update(repr(tuple(src.transform)[:6]).encode())
    hz.update((src.crs or "").encode())

    return StreamPlan(hz.hexdigest(), tuple(map(float, rng_grid)), tuple(map(float, rng_all)),
                      tuple(pyramid.xy_frac_bits(k) for k in pyramid.levels), n_invalid, h * w,
                      (zmin, zmax))  # fmt: skip


def _ladder_read(src: WindowSource, pyramid: TilePyramid, method: str) -> tuple | None:
    """(elevations, valid) of the decimated window a mesher's ``ladder_window`` asks for (adaptive's
    default ladder: the root's window, every f-th row and column), read in strips; None for others."""
    window = getattr(builder.METHODS[method], "ladder_window", None)
    if window is None:
        return None
    hh, ww, f = window(src.height, src.width, pyramid)
    # in strips of LADDER_STRIP_SAMPLES: this read runs beside the first work units
    z, _, own = _decimated_window(src, 0, 0, hh - 1, ww - 1, f, LADDER_STRIP_SAMPLES)
    nr, nc = len(range(0, hh, f)), len(range(0, ww, f))  # without the last row/column appended
    return np.ascontiguousarray(z[:nr, :nc]), np.ascontiguousarray(own[:nr, :nc])


def _file_bytes(f) -> bytes:
    f.seek(0)
    return f.read()


class _FrameMeta:
    """The frame attributes :func:`terralod.pyramid.builder._store_meta` reads, for a streamed source."""

    def __init__(self, src: WindowSource, plan: StreamPlan, ladder: tuple | None = None) -> None:
        from terralod.io.windowed import FILL_BLOCK, FILL_HALO

        self.source, self.crs, self.transform = src.source, src.crs, src.transform
        self.paths = [
            str(p) for p in (getattr(src, "paths", None) or [])
        ]  # a mosaic's files, for its exports
        self.spacing_m, self.width, self.height = src.spacing_m, src.width, src.height
        self.notes = tuple(src.notes)
        self.nodata_fraction = plan.n_invalid / plan.n_samples
        self.fill_method = src.fill_method
        if plan.n_invalid and not isinstance(src, ArraySource):
            how = src.fill_note or (
                f"filled per {FILL_BLOCK}-sample block (halo {FILL_HALO}) with the nearest valid sample, then relaxed"
            )
            self.fill_method = (
                f"{plan.n_invalid} nodata cells ({100.0 * plan.n_invalid / plan.n_samples:.2f} %) {how}"
            )
        # a resampled source: the samples every error is also measured against, and its own statistics
        self.original_grid = src.original_grid
        self.source_nodata_fraction = src.source_nodata_fraction
        self.margin_fraction = src.margin_fraction
        self._digest = plan.digest
        # a mesher's ``build_meta(z, valid, pyramid)`` gets no arrays here (the DEM is never held whole),
        # or, for a mesher with ``ladder_window`` (adaptive), the decimated read that window asks for
        self.elevation_m, self.valid = ladder if ladder is not None else (None, None)

    def digest(self) -> str:
        return self._digest


# -- work units ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class WindowPyramid(TilePyramid):
    """The terrain's pyramid seen from a window: origins shifted by (row_offset, col_offset) and, for a
    decimated window, divided by ``decimation`` with the strides (the tile codes stay the terrain's)."""

    row_offset: int = 0
    col_offset: int = 0
    decimation: int = 1
    #: The whole terrain's north-west sample centre (metres): a tile measured against the original samples
    #: is placed from it and its absolute rows and columns (``builder.measure_tile``), never from the
    #: window's own origin, whose rounding depends on which tiles share the window (a resumed build
    #: groups the tiles left into other windows: the same errors, bit for bit, only this way).
    frame_origin_m: tuple[float, float] | None = None

    def stride(self, level: int) -> int:
        return (1 << (self.max_level - level)) // self.decimation

    def origin_rc(self, code: TileCode) -> tuple[int, int]:
        level, x, y = code
        s = self.cells * (1 << (self.max_level - level))
        return (y * s - self.row_offset) // self.decimation, (x * s - self.col_offset) // self.decimation


def _halo(mesh_fn: Callable, stride: int) -> int:
    """Samples a mesher reads beyond its tile window: a ``window_halo(stride)`` it declares; cohesion with
    LoG attraction smooths over 2 strides; 0 otherwise."""
    if hasattr(mesh_fn, "window_halo"):
        return int(mesh_fn.window_halo(stride))
    opt = getattr(mesh_fn, "options", None)
    if opt is not None and getattr(opt, "attraction", "") == "log":
        return int(math.ceil(2.0 * stride)) + 1
    return 0


def _unit_side(pyramid: TilePyramid, level: int, unit_span: int) -> int:
    """g, the tiles a side of a work unit at ``level`` (a power of two, g * span about ``unit_span``)."""
    span = pyramid.span(level)
    g = 1
    while 2 * g * span <= unit_span:
        g *= 2
    return g


def _units(todo: np.ndarray, level: int, g: int) -> Iterator[list[TileCode]]:
    """The tiles ``todo`` (a level's (ny, nx) mask) grouped into g x g blocks, blocks and the tiles in each
    in raster order: made as they are taken, so a build holds its units in flight, not the whole plan."""
    ny, nx = todo.shape
    for by in range(0, ny, g):
        for bx in range(0, nx, g):
            ys, xs = np.nonzero(todo[by : by + g, bx : bx + g])
            if len(ys):
                yield [(level, bx + x, by + y) for y, x in zip(ys.tolist(), xs.tolist(), strict=True)]


def _unit_count(todo: np.ndarray, g: int) -> int:
    """How many of the g x g blocks of ``todo`` hold a tile to build."""
    ny, nx = todo.shape
    padded = np.zeros((-(-ny // g) * g, -(-nx // g) * g), bool)
    padded[:ny, :nx] = todo
    return int(padded.reshape(padded.shape[0] // g, g, -1, g).any(axis=(1, 3)).sum())


#: glibc's own ceilings for its adaptive thresholds on 64-bit (its DEFAULT_MMAP_THRESHOLD_MAX, and twice it)
_MMAP_THRESHOLD_BYTES = 32 << 20
_TRIM_THRESHOLD_BYTES = 64 << 20
_malloc_tuned: bool | None = None


def tune_worker_malloc() -> bool:
    """Give glibc back its adaptive allocation thresholds in a process started with a fixed one.

    Dask's nanny starts every worker with ``MALLOC_TRIM_THRESHOLD_=65536`` (its config
    ``distributed.nanny.pre-spawn-environ``). Setting any malloc threshold turns off glibc's adaptive mmap
    threshold, so every array over 128 KiB becomes a fresh mmap whose pages fault in on first touch and go
    back to the kernel when freed. Tile and sub-block builds allocate and free such arrays by the thousand:
    the 4097² chunked build ran 1.4-1.7x slower with that variable set, in or out of Dask
    (``benchmarks/scale.py``). Where the variable is set this sets the thresholds glibc adapts towards by
    itself (mmap 32 MiB, trim 64 MiB), once per process; elsewhere it does nothing. Returns whether it set
    them (False off glibc)."""
    global _malloc_tuned
    if _malloc_tuned is None:
        _malloc_tuned = False
        if "MALLOC_TRIM_THRESHOLD_" in os.environ or "MALLOC_MMAP_THRESHOLD_" in os.environ:
            try:
                import ctypes

                libc = ctypes.CDLL("libc.so.6")
                m_trim_threshold, m_mmap_threshold = -1, -3  # glibc's malloc.h
                _malloc_tuned = bool(libc.mallopt(m_mmap_threshold, _MMAP_THRESHOLD_BYTES)) and bool(
                    libc.mallopt(m_trim_threshold, _TRIM_THRESHOLD_BYTES)
                )
            except (OSError, AttributeError):  # not glibc (macOS, musl, Windows): nothing to undo
                _malloc_tuned = False
    return _malloc_tuned


_libc_trim: Any = None
_last_trim = 0.0
#: Seconds between two trims of the heap after small units (:func:`release_free_heap`).
TRIM_INTERVAL_S = 2.0


def release_free_heap(force: bool = True) -> bool:
    """Hand the heap pages glibc holds free back to the kernel (``malloc_trim(0)``): always with
    ``force``, else at most once every ``TRIM_INTERVAL_S``. False where nothing was trimmed (off glibc).

    A unit's arrays below glibc's adaptive mmap threshold (up to 32 MiB: :func:`tune_worker_malloc`)
    come from per-thread arenas, whose freed pages glibc keeps for reuse: on the 4-tile SRTM3 region
    the process sat at about 800 MiB between units against 480 MiB trimmed, and a coarse tile's window
    freed in one thread's arena stayed resident while the other thread meshed the next. Trimming after
    each large unit, and every few seconds after the others, bounds the resident heap by the units in
    flight (trimmed pages fault in again when reused)."""
    global _libc_trim, _last_trim
    if _libc_trim is None:
        try:
            import ctypes

            _libc_trim = ctypes.CDLL("libc.so.6").malloc_trim
        except (OSError, AttributeError):  # not glibc (macOS, musl, Windows)
            _libc_trim = False
    now = time.monotonic()
    if _libc_trim is False or (not force and now - _last_trim < TRIM_INTERVAL_S):
        return False
    _last_trim = now
    _libc_trim(0)
    return True


def build_unit(
    src: WindowSource,
    tile_size: int,
    method: str,
    codes: list[TileCode],
    quant: LevelQuantisation,
    child_errors: dict[TileCode, list[tuple[float, float]]],
    max_window_samples: int | None = MAX_WINDOW_SAMPLES,
    build_options: dict | None = None,
) -> list[EncodedTile]:
    """Build the tiles ``codes`` (one level, one block) from their window of ``src``: the work unit of
    threads and Dask workers alike (module-level, picklable arguments). A mesher whose options come from
    the whole terrain (adaptive's ladder) meshes with the store's stated ``build_options``. The heap the
    unit freed goes back to the kernel as it returns (:func:`release_free_heap`: after a large unit, and
    every few seconds)."""
    tune_worker_malloc()
    try:
        return _build_unit(src, tile_size, method, codes, quant, child_errors, max_window_samples,
                           build_options)  # fmt: skip
    finally:
        release_free_heap(force=_large_unit((src, tile_size, method, codes)))


def _build_unit(
    src: WindowSource,
    tile_size: int,
    method: str,
    codes: list[TileCode],
    quant: LevelQuantisation,
    child_errors: dict[TileCode, list[tuple[float, float]]],
    max_window_samples: int | None,
    build_options: dict[str, Any] | None,
) -> list[EncodedTile]:
    """:func:`build_unit`'s work."""
    pyramid = TilePyramid(src.width, src.height, tile_size)
    mesh_fn = builder.METHODS[method]
    fixed = getattr(mesh_fn, "with_build_options", None)
    if fixed is not None and build_options is not None:
        mesh_fn = fixed(build_options)
    level = codes[0][0]
    span = pyramid.span(level)
    h, w = src.height, src.width
    if max_window_samples is not None and (span + 1) ** 2 > max_window_samples and pyramid.stride(level) > 1:
        return [
            _build_decimated(src, pyramid, c, quant, mesh_fn, child_errors[c], max_window_samples)
            for c in codes
        ]
    pad = _halo(mesh_fn, pyramid.stride(level))
    rs = [pyramid.origin_rc(c) for c in codes]
    ra = max(min(r for r, _ in rs) - pad, 0)
    ca = max(min(c for _, c in rs) - pad, 0)
    rb = min(max(r for r, _ in rs) + span + pad, h - 1)
    cb = min(max(c for _, c in rs) + span + pad, w - 1)
    hf = src.window_heightfield(ra, ca, rb + 1, cb + 1)
    dx, dy = src.spacing_m
    frame = (float(src.transform.c + 0.5 * dx), float(src.transform.f - 0.5 * dy))  # Heightfield.origin_m's
    wp = WindowPyramid(w, h, tile_size, ra, ca, frame_origin_m=frame)
    grid = hf.original_grid
    if grid is None or (span + 1) ** 2 <= MEASURE_STRIP_SAMPLES:
        return [builder.build_tile(hf, wp, c, quant, mesh_fn, child_errors[c]) for c in codes]
    # a large tile of a resampled source: its original samples measured in strips (memory independent of
    # the tile's size), not in one window of its whole footprint
    hf = dataclasses.replace(hf, original_grid=None)
    out = []
    for c in codes:
        enc = builder.measure_tile(hf, wp, c, quant, mesh_fn)
        out.append(
            builder.with_child_errors(_with_original(src, grid, pyramid, c, quant, enc), child_errors[c])
        )
    return out


def _with_original(
    src: WindowSource,
    grid: Any,
    pyramid: TilePyramid,
    code: TileCode,
    quant: LevelQuantisation,
    enc: EncodedTile,
) -> EncodedTile:
    """``enc`` (measured on the grid only) with its errors also measured against the original samples of
    its footprint, streamed (:func:`_original_streamed`): the numbers of
    :func:`~terralod.pyramid.builder.measure_tile` (max of both, RMS and count over the original samples)."""
    if enc.n_vertices == 0:
        return enc
    q = decode_vertices(enc.vertices, enc.n_vertices).astype(np.float64)
    tris = decode_triangles(enc.triangles, enc.n_triangles).astype(np.int64)
    dx, dy = src.spacing_m
    inv = math.ldexp(1.0, -quant.xy_frac_bits)
    local = np.stack(
        [q[:, 0] * inv * dx, q[:, 1] * inv * dy, (enc.z0_index + q[:, 2]) * quant.z_step_m], axis=1
    )
    r0, c0 = pyramid.origin_rc(code)
    span = pyramid.span(code[0])
    r1, c1 = min(r0 + span, src.height - 1), min(c0 + span, src.width - 1)
    worst, sumsq, n = _original_streamed(src, grid, local, tris, r0, c0, r1, c1)
    err, verr = max(enc.measured_error_m, worst), max(enc.measured_vertical_error_m, worst)
    return dataclasses.replace(enc, error_m=err, vertical_error_m=verr, measured_error_m=err,
                               measured_vertical_error_m=verr, rms_error_m=math.sqrt(sumsq / n) if n else 0.0,
                               n_samples=n)  # fmt: skip


def _decimated_window(src: WindowSource, r0: int, c0: int, r1: int, c1: int, f: int, strip_samples: int):
    """Rows r0, r0 + f, ... <= r1 and columns likewise of [r0, r1] x [c0, c1] (inclusive), plus the last
    row and column when they fall between, read in strips of rows. Returns (elevations, the mesher's mask
    with that last row and column invalid (the mesher reads them as the edge), the samples' own mask)."""
    rows = np.arange(r0, r1 + 1, f)
    cols = np.arange(c0, c1 + 1, f)
    rows_ok = np.ones(len(rows), bool)
    cols_ok = np.ones(len(cols), bool)
    if rows[-1] != r1:
        rows, rows_ok = np.append(rows, r1), np.append(rows_ok, False)
    if cols[-1] != c1:
        cols, cols_ok = np.append(cols, c1), np.append(cols_ok, False)
    z = np.empty((len(rows), len(cols)), np.float32)
    ok = np.empty((len(rows), len(cols)), bool)
    step = max(1, strip_samples // ((c1 - c0 + 1) * f)) * f  # rows per strip, a multiple of f
    for a in range(r0, r1 + 1, step):
        b = min(a + step, r1 + 1)
        zs, vs = src.read(a, c0, b, c1 + 1)
        sel = (rows >= a) & (rows < b)
        z[sel] = zs[rows[sel] - a][:, cols - c0]
        ok[sel] = vs[rows[sel] - a][:, cols - c0]
    return z, ok & rows_ok[:, None] & cols_ok[None, :], ok


def _build_decimated(src, pyramid, code, quant, mesh_fn, child_errors, max_window_samples):
    """A coarse tile meshed from a decimated copy of its window, measured on every full-resolution sample
    (streamed in strips); quantised and encoded as :func:`~terralod.pyramid.builder.build_tile` does."""
    level = code[0]
    s = pyramid.stride(level)
    span = pyramid.span(level)
    f = 1
    while f < s and (span // f + 1) ** 2 > max_window_samples:
        f *= 2
    r0, c0 = pyramid.origin_rc(code)
    r1, c1 = min(r0 + span, src.height - 1), min(c0 + span, src.width - 1)
    dx, dy = src.spacing_m
    zd, vd, vd_own = _decimated_window(src, r0, c0, r1, c1, f, MEASURE_STRIP_SAMPLES)
    hf = Heightfield(zd, vd, src.transform @ Affine.scale(f), crs=src.crs)
    wp = WindowPyramid(src.width, src.height, pyramid.tile_size, r0, c0, f)
    if getattr(mesh_fn, "needs_spacing", False):
        rows, cols, hz, tris = mesh_fn(hf.elevation_m, hf.valid, wp, code, spacing_m=hf.spacing_m)
    else:
        rows, cols, hz, tris = mesh_fn(hf.elevation_m, hf.valid, wp, code)
    # the footprint (triangles over nodata not stored) judged on the decimated samples
    rows, cols, hz, tris = drop_nodata(rows, cols, hz, tris, vd_own, vd_own)
    if rows.shape[0] == 0:  # wholly in nodata: stored empty, its error its children's (as build_tile)
        zc = float(zd[0, 0])
        return EncodedTile(code=code, error_m=float(max([0.0] + [e for e, _ in child_errors])),
                           vertical_error_m=float(max([0.0] + [v for _, v in child_errors])), measured_error_m=0.0,
                           measured_vertical_error_m=0.0, rms_error_m=0.0, n_samples=0, z_min_m=zc, z_max_m=zc,
                           n_vertices=0, n_triangles=0, z0_index=0, vertices=encode_vertices(np.zeros((0, 3), np.uint16)),
                           triangles=encode_triangles(np.zeros((0, 3), np.int32)))  # fmt: skip
    qv, z0 = builder._quantise(rows * f, cols * f, hz, 0, 0, quant)
    scale = math.ldexp(1.0, -quant.xy_frac_bits)
    u = qv[:, 0] * scale
    v = qv[:, 1] * scale
    zq = (z0 + qv[:, 2].astype(np.int64)) * quant.z_step_m
    rep = _measure_streamed(src, u, v, zq, tris, r0, c0, r1, c1, s, dx, dy)
    max_v, sumsq, n, hd = rep
    grid = src.original_grid
    if grid is not None:  # a resampled source: its own samples too (terralod.pyramid.original)
        local = np.stack([u * dx, v * dy, zq], axis=1)
        o_max, sumsq, n = _original_streamed(src, grid, local, tris, r0, c0, r1, c1)
        hd, max_v = max(hd, o_max), max(max_v, o_max)
    err = max([hd] + [e for e, _ in child_errors])
    verr = max([max_v] + [x for _, x in child_errors])
    return EncodedTile(
        code=code, error_m=float(err), vertical_error_m=float(verr), measured_error_m=float(hd),
        measured_vertical_error_m=float(max_v), rms_error_m=float(math.sqrt(sumsq / n) if n else 0.0),
        n_samples=int(n), z_min_m=float(zq.min()), z_max_m=float(zq.max()), n_vertices=int(qv.shape[0]),
        n_triangles=int(tris.shape[0]), z0_index=z0, vertices=encode_vertices(qv), triangles=encode_triangles(tris),
    )  # fmt: skip


def _original_streamed(src, grid, local, tris, r0, c0, r1, c1) -> tuple[float, float, int]:
    """(max vertical gap, sum of squares, samples) of a tile mesh (``local``: metres east and south of the
    tile's north-west sample) against the original samples of its footprint, rows [r0, r1] x cols [c0, c1]
    of the grid, taken in blocks of grid rows and columns of about ``MEASURE_STRIP_SAMPLES`` original samples
    each (memory independent of the tile's size); a sample on a block's south or east edge is left to the
    next block.

    Blocks, not strips of the tile's whole width: a row of a wide region's grid (a Transverse Mercator
    across 16° of longitude) is a curve in the source's latitude, and the source window that holds a
    full-width strip of it was 7x the strip's samples on 256 SRTM3 tiles (about 300 MB more, for the
    minutes the whole-region tile took)."""
    from terralod.pyramid.original import original_error, tile_samples

    dx, dy = src.spacing_m
    t = src.transform
    origin = (float(t.c + 0.5 * dx), float(t.f - 0.5 * dy))
    gt = grid.transform
    side = math.sqrt(MEASURE_STRIP_SAMPLES)  # original samples a block side, about
    col_step = max(1, int(side * abs(gt.a * _metres_per_unit(grid)) / dx))
    row_step = max(1, int(side * abs(gt.e * _metres_per_unit(grid)) / dy))
    worst = sumsq = 0.0
    n = 0
    for a in range(r0, r1, row_step):
        b = min(a + row_step, r1)
        for ca in range(c0, c1, col_step):
            cb = min(ca + col_step, c1)
            x, y, z = tile_samples(grid, str(src.crs), origin, (dx, dy), (a, ca), (b, cb))
            keep = np.ones(x.shape, bool)
            if b < r1:
                keep &= y < (b - a) * dy
            if cb < c1:
                keep &= x < (cb - ca) * dx
            rep = original_error(local, tris, x[keep] + (ca - c0) * dx, y[keep] + (a - r0) * dy, z[keep])
            worst = max(worst, rep.max_vertical_m)
            sumsq += rep.sumsq_m2
            n += rep.n_samples
    return worst, sumsq, n


def _metres_per_unit(grid) -> float:
    """Rough ground metres of one unit of ``grid``'s CRS (a degree, or a metre), for strip sizes only."""
    from rasterio.crs import CRS

    return 111_000.0 if CRS.from_user_input(grid.crs).is_geographic else 1.0


def _measure_streamed(src, u, v, zq, tris, r0, c0, r1, c1, margin, dx, dy):
    """(max vertical, sum of squares, samples, Hausdorff) of a tile mesh (vertex (u, v) in samples from
    the tile's origin, heights zq) over rows [r0, r1] x cols [c0, c1] of ``src``, in strips of rows; each
    strip is measured with the triangles that reach it or come within ``margin`` rows of it."""
    width = c1 - c0 + 1
    step = max(1, MEASURE_STRIP_SAMPLES // width)
    tv = v[tris]
    tlo, thi = tv.min(axis=1), tv.max(axis=1)
    max_v = hd = sumsq = 0.0
    n = 0
    for a in range(0, r1 - r0 + 1, step):
        b = min(a + step, r1 - r0 + 1)  # strip rows [a, b) of the tile window
        pa, pb = max(a - 1, 0), min(b + 1, r1 - r0 + 1)  # one row of samples either side, not measured
        sel = (thi >= a - margin) & (tlo <= b - 1 + margin)
        if not sel.any():
            continue
        t = tris[sel]
        used, inv = np.unique(t, return_inverse=True)
        local = np.stack([u[used] * dx, (v[used] - pa) * dy, zq[used]], axis=1)
        zs, vs = src.read(r0 + pa, c0, r0 + pb, c1 + 1)
        vs = vs.copy()
        vs[: a - pa] = False
        vs[b - pa :] = False
        rep = measure_error_window(local, inv.reshape(-1, 3), zs, vs, dx, dy)
        max_v, hd = max(max_v, rep.max_vertical_m), max(hd, rep.hausdorff_m)
        sumsq += rep.rms_vertical_m**2 * rep.n_samples
        n += rep.n_samples
    return max_v, sumsq, n, hd


# -- executors -----------------------------------------------------------------------------------------
def dask_client(
    address: str,
    *,
    n_workers: int | None = None,
    threads: int | None = None,
    timeout_s: float = 10.0,
    memory_limit: int | None = None,
):
    """A dask.distributed Client: ``"local"`` starts a LocalCluster of ``n_workers`` processes with
    ``threads`` threads each (each allowed ``memory_limit`` bytes; Dask's default without it); else
    ``address`` is a scheduler (``tcp://HOST:PORT``). Raises :class:`InputError` naming the address when the
    scheduler cannot be reached."""
    try:
        from dask.distributed import Client, LocalCluster
    except ImportError:
        raise InputError(
            "dask[distributed] is not installed (pip install 'dask[distributed]')", address
        ) from None
    if address == "local":
        cluster = LocalCluster(n_workers=n_workers or 2, threads_per_worker=threads or 1, processes=True,
                               dashboard_address=None, silence_logs=logging.ERROR,
                               **({"memory_limit": memory_limit} if memory_limit else {}))  # fmt: skip
        return Client(cluster)
    try:
        return Client(address, timeout=timeout_s)
    except (OSError, TimeoutError, ValueError) as exc:
        raise InputError(
            f"cannot reach the Dask scheduler ({str(exc).splitlines()[0][:160]})", address
        ) from None


#: Large units (:func:`_large_unit`) a thread runner runs at once: each holds a whole coarse tile's window
#: (up to ``max_window_samples``, 4097² by default: about 235 MB as read plus the mesher's per-quad
#: arrays), so two at once doubled the build's peak memory while the fine units, a few MB each, waited.
_LARGE_UNITS_IN_FLIGHT = 1


def _large_unit(job: tuple[Any, ...]) -> bool:
    """Whether a unit's job (:func:`build_unit`'s arguments) meshes a tile whose window is over
    ``MEASURE_STRIP_SAMPLES`` samples (one tile of span 1024 or more: the coarse levels)."""
    src, tile_size, _, codes = job[:4]
    span = TilePyramid(src.width, src.height, tile_size).span(codes[0][0])
    return bool((min(span, src.height - 1) + 1) * (min(span, src.width - 1) + 1) > MEASURE_STRIP_SAMPLES)


class _ThreadRunner:
    """Units on a thread pool of this process (the numba kernels release the GIL)."""

    def __init__(self, threads: int) -> None:
        self.threads = threads
        self.pool = ThreadPoolExecutor(max_workers=threads)

    def share(self, src):
        return src

    def slots(self) -> int:
        return self.threads

    def stream(self, jobs: Iterable[tuple], ahead: int) -> Iterator[list[EncodedTile]]:
        """Results of ``build_unit(*job)`` as they complete, at most ``ahead`` units in flight, of which at
        most ``_LARGE_UNITS_IN_FLIGHT`` large ones (:func:`_large_unit`): a large unit met while that many
        run waits, in order, and the units after it go ahead, so no thread idles for it. Each unit's tiles
        are a pure function of its job, so the order changes when tiles arrive, not their bytes."""
        it = iter(jobs)
        pending: set = set()
        large: set[Any] = set()
        deferred: list[tuple[Any, ...]] = []

        def submit(job: tuple[Any, ...]) -> None:
            fut = self.pool.submit(build_unit, *job)
            pending.add(fut)
            if _large_unit(job):
                large.add(fut)

        def top_up() -> None:
            while deferred and len(large) < _LARGE_UNITS_IN_FLIGHT and len(pending) < ahead:
                submit(deferred.pop(0))
            while len(pending) < ahead:
                job = next(it, None)
                if job is None:
                    return
                if _large_unit(job) and len(large) >= _LARGE_UNITS_IN_FLIGHT:
                    deferred.append(job)
                    continue
                submit(job)

        top_up()
        try:
            while pending:
                done, rest = wait(pending, return_when=FIRST_COMPLETED)
                pending.intersection_update(rest)
                large.intersection_update(rest)
                top_up()
                for fut in done:
                    yield fut.result()
        finally:
            for fut in pending:
                fut.cancel()

    def close(self) -> None:
        self.pool.shutdown(cancel_futures=True)


#: Units resubmitted after their futures were cancelled (a scattered source lost with a dead worker, a
#: client that reconnected to its scheduler) before the build gives up in one line.
_RESUBMITS = 64


class _Packed:
    """Arguments Dask passes through as one opaque object (see :meth:`_DaskRunner.submit`)."""

    __slots__ = ("args",)

    def __init__(self, args: tuple) -> None:
        self.args = args

    def __getstate__(self) -> tuple:
        return self.args

    def __setstate__(self, args: tuple) -> None:
        self.args = args


def _build_unit_packed(src: WindowSource, packed: _Packed) -> list[EncodedTile]:
    """:func:`build_unit` of a Dask task (its arguments after the source packed)."""
    return build_unit(src, *packed.args)


class _DaskRunner:
    """Units as Dask tasks (retried on another worker when one dies), results as they complete."""

    def __init__(self, client, retries: int) -> None:
        self.client, self.retries = client, retries
        self._src: Any = None
        self._shared: Any = None
        self._args: dict[str, tuple] = {}

    def share(self, src):
        """A file source (it pickles as its paths) travels inside each task, so no scattered copy dies with
        a worker; an in-memory ArraySource is scattered to every worker once."""
        self._src = src
        if isinstance(src, ArraySource):
            self._shared = self.client.scatter(src, broadcast=True, hash=False)
        else:
            self._shared = src
        return self._shared

    def slots(self) -> int:
        return max(1, sum(self.client.nthreads().values()))

    def submit(self, *args):
        # The source goes as its own argument (a scattered one is a future the scheduler resolves); the
        # rest (codes, errors, lattice, options) goes packed, so Dask does not walk its lists and dicts
        # looking for futures on every submit.
        fut = self.client.submit(_build_unit_packed, args[0], _Packed(args[1:]), retries=self.retries,
                                 pure=False)  # fmt: skip
        self._args[fut.key] = args
        return fut

    def stream(self, jobs: Iterable[tuple], ahead: int) -> Iterator[list[EncodedTile]]:
        """Results of the units ``jobs`` as they complete, at most ``ahead`` in flight (see the module doc
        for retries and resubmission)."""
        from concurrent.futures import CancelledError

        from dask.distributed import as_completed
        from distributed import KilledWorker

        it = iter(jobs)
        # results gathered on the client's event loop as units finish, not one blocking round trip each
        pending = as_completed(with_results=True, raise_errors=False)
        in_flight = 0

        def top_up() -> None:
            nonlocal in_flight
            while in_flight < ahead:
                job = next(it, None)
                if job is None:
                    return
                pending.add(self.submit(*job))
                in_flight += 1

        top_up()
        resubmits = 0
        for fut, res in pending:
            in_flight -= 1
            try:
                if isinstance(res, CancelledError):
                    raise res
                if fut.status == "error":
                    _, exc, tb = res
                    raise exc.with_traceback(tb)
            except KilledWorker as exc:  # the unit's workers died, retries included: memory, usually
                raise WorkerLostError(
                    f"Dask workers died building a work unit ({exc}); out of memory? give each worker more "
                    "memory or fewer threads (--workers), or use a smaller --tile-size; the tiles committed "
                    "so far are kept: run the same command with --resume"
                ) from None
            except CancelledError as exc:  # the scheduler dropped it: a lost scattered source, a reconnect
                resubmits += 1
                if resubmits > _RESUBMITS:
                    raise WorkerLostError(
                        f"Dask cancelled work units {resubmits} times ({exc}); is the scheduler overloaded or "
                        "its workers restarting? the tiles committed so far are kept: run the same command "
                        "with --resume"
                    ) from None
                args = self._args.pop(fut.key)
                if args[0] is self._shared and self._shared is not self._src:
                    self.share(self._src)  # the scattered copy may be what was lost: scatter it again
                pending.add(self.submit(self._shared, *args[1:]))
                in_flight += 1
                continue
            self._args.pop(fut.key, None)
            fut.release()
            top_up()
            yield res

    def close(self) -> None:
        pass


#: Units in flight per worker thread (a bound on the finished tiles held for their parents' errors).
_AHEAD_UNITS_PER_SLOT = 4
#: The levels with at most this many units per worker thread (the coarsest, whose tiles are the largest)
#: are submitted first, so that no core waits alone for the root at the end of a build.
_EARLY_UNITS_PER_SLOT = 2


def unit_job(shared: Any, tile_size: int, method: str, unit: list[TileCode],
             quant: dict[int, LevelQuantisation], max_window_samples: int | None, options: dict | None) -> tuple:  # fmt: skip
    """The arguments of :func:`build_unit` for the tiles ``unit`` of one level (a runner's job)."""
    return (
        shared,
        tile_size,
        method,
        unit,
        quant[unit[0][0]],
        {c: [] for c in unit},
        max_window_samples,
        options,
    )


def _unit_order(
    pyramid: TilePyramid, todo: dict[int, np.ndarray], unit_span: int, early_units: int
) -> tuple[list[list[TileCode]], Iterator[list[TileCode]]]:
    """The work units of the tiles ``todo`` ({level: mask}) in submission order: (those of the levels with
    at most ``early_units`` units, coarsest first, as a list; the others, finest first, made as taken)."""
    side = {lv: _unit_side(pyramid, lv, unit_span) for lv in todo}
    early = [lv for lv in sorted(todo) if _unit_count(todo[lv], side[lv]) <= early_units]
    rest = [lv for lv in sorted(todo, reverse=True) if lv not in early]
    return (
        [u for lv in early for u in _units(todo[lv], lv, side[lv])],
        (u for lv in rest for u in _units(todo[lv], lv, side[lv])),
    )


def _todo(pyramid: TilePyramid, done: TileErrors, stop_after: int | None) -> dict[int, np.ndarray]:
    """{level: (ny, nx) mask} of the tiles a build still has to make: those not ``done``, and of them only
    the first ``stop_after`` in finest-first raster order (a tile's children come before it). A byte a
    tile, where a list of codes took about 100."""
    todo: dict[int, np.ndarray] = {}
    left = stop_after
    for level in reversed(pyramid.levels):
        mask = ~done.have(level)
        if left is not None:
            flat = mask.reshape(-1)
            at = np.flatnonzero(flat)
            flat[at[left:]] = False
            left = max(0, left - len(at))
        todo[level] = mask
    return todo


def _monotone(
    tiles: Iterable[EncodedTile], pyramid: TilePyramid, errors: MutableMapping[TileCode, tuple[float, float]]
) -> Iterator[EncodedTile]:
    """Measured tiles, in any order, to the writer's order: a tile leaves once every child's errors are in
    ``errors`` (the writer records them as it takes each tile), with its stored errors made monotone by
    :func:`~terralod.pyramid.builder.with_child_errors`. No level waits for the one before it to finish:
    the coarse tiles are meshed and measured alongside the fine ones, and wait only for their stored
    errors (the in-memory builder's policy)."""
    waiting: dict[TileCode, EncodedTile] = {}
    for enc in tiles:
        waiting[enc.code] = enc
        ready = [enc.code]
        while ready:
            code = ready.pop()
            tile = waiting.get(code)
            if tile is None or any(k not in errors for k in pyramid.children(code)):
                continue
            del waiting[code]
            yield builder.with_child_errors(tile, [errors[k] for k in pyramid.children(code)])
            up = parent(code)
            if up is not None:
                ready.append(up)
    if waiting:  # pragma: no cover - every tile's children are built before the stream ends
        raise AssertionError(f"{len(waiting)} tiles never had their children's errors")


class TileErrors(MutableMapping):
    """The (error_m, vertical_error_m) of each tile a build has finished, for its parent's monotone
    errors: one pair of float64 arrays and a flag array per level of the pyramid (17 bytes a tile),
    instead of a dict of tuples (about 200 bytes a tile in CPython: 150 MB for the 780,000 tiles of 256
    SRTM3 tiles, the one part of a build's memory that grew with the region). The values are the floats
    put in, bit for bit."""

    def __init__(self, pyramid: TilePyramid) -> None:
        self._pyramid = pyramid
        self._levels: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        self._n = 0

    def _level(self, level: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        got = self._levels.get(level)
        if got is None:
            nx, ny = self._pyramid.grid_count(level)
            got = self._levels[level] = (np.zeros((ny, nx)), np.zeros((ny, nx)), np.zeros((ny, nx), bool))
        return got

    def forget(self, level: int, mask: np.ndarray) -> None:
        """Drop the errors of the tiles of ``level`` where the (ny, nx) ``mask`` is set."""
        got = self._levels.get(level)
        if got is not None:
            self._n -= int(np.count_nonzero(got[2] & mask))
            got[2][mask] = False

    def have(self, level: int) -> np.ndarray:
        """A (ny, nx) copy of which tiles of ``level`` have their errors."""
        got = self._levels.get(level)
        nx, ny = self._pyramid.grid_count(level)
        return np.zeros((ny, nx), bool) if got is None else got[2].copy()

    def _at(self, code: TileCode) -> tuple[np.ndarray, np.ndarray, np.ndarray, int, int] | None:
        level, x, y = code
        if not self._pyramid.exists(code):
            return None
        e, v, have = self._level(level)
        return e, v, have, y, x

    def __contains__(self, code: object) -> bool:
        at = self._at(code) if isinstance(code, tuple) and len(code) == 3 else None  # type: ignore[arg-type]
        return at is not None and bool(at[2][at[3], at[4]])

    def __getitem__(self, code: TileCode) -> tuple[float, float]:
        at = self._at(code)
        if at is None or not at[2][at[3], at[4]]:
            raise KeyError(code)
        e, v, _, y, x = at
        return float(e[y, x]), float(v[y, x])

    def __setitem__(self, code: TileCode, value: tuple[float, float]) -> None:
        at = self._at(code)
        if at is None:
            raise KeyError(code)
        e, v, have, y, x = at
        self._n += not have[y, x]
        e[y, x], v[y, x] = value
        have[y, x] = True

    def __delitem__(self, code: TileCode) -> None:
        at = self._at(code)
        if at is None or not at[2][at[3], at[4]]:
            raise KeyError(code)
        at[2][at[3], at[4]] = False
        self._n -= 1

    def __iter__(self) -> Iterator[TileCode]:
        for level in sorted(self._levels):
            ys, xs = np.nonzero(self._levels[level][2])
            for y, x in zip(ys.tolist(), xs.tolist(), strict=True):
                yield (level, x, y)

    def __len__(self) -> int:
        return self._n


# -- the driver ----------------------------------------------------------------------------------------
def build_store_windowed(
    src: WindowSource | Heightfield,
    path: str | os.PathLike[str],
    *,
    tile_size: int | None = None,
    method: str = builder.DEFAULT_METHOD,
    workers: int | None = None,
    client: Any = None,
    resume: bool = False,
    overwrite: bool = False,
    progress: Callable[[int, int], None] | None = None,
    stop_after: int | None = None,
    max_window_samples: int | None = MAX_WINDOW_SAMPLES,
    unit_span_samples: int = UNIT_SPAN_SAMPLES,
    retries: int = 3,
    epoch: str | None = None,
) -> builder.BuildReport:
    """Build the tile store of a window source at ``path``, out of core (see the module docstring).

    Parameters
    ----------
    src : a :class:`~terralod.io.windowed.WindowSource` (or a Heightfield, wrapped in an ArraySource).
    path, tile_size, method, resume, overwrite, progress, stop_after : as
        :func:`terralod.pyramid.builder.build_store`.
    workers : threads of this process (without ``client``), default all cores.
    client : a ``dask.distributed.Client`` (:func:`dask_client`); units then run on its workers.
    max_window_samples : tiles with larger windows are meshed from a decimated copy (None: never).
    unit_span_samples : samples a side of a work unit's window (tiles grouped to about this).
    retries : Dask retries of a unit whose worker died.
    epoch : name of the store's first epoch, as :func:`terralod.pyramid.builder.build_store`'s: the lattice
        planned with headroom, the samples kept in the store (read again in strips of
        :data:`~terralod.store_epochs.SOURCE_BLOCK` rows, one transaction) so that
        :func:`update_store_windowed` can add epochs.
    """
    if isinstance(src, Heightfield):
        src = ArraySource(src)
    if method not in builder.METHODS:
        raise ValueError(f"Expected a method in {sorted(builder.METHODS)}, got {method!r}")
    if tile_size is None:
        tile_size = builder.default_tile_size(method)
    if not is_valid_tile_size(tile_size):
        raise ValueError(f"Expected a tile size 2^n + 1 (e.g. 33, 65, 129), got {tile_size}")
    p = Path(path)
    t_start = time.perf_counter()
    pyramid = TilePyramid(src.width, src.height, tile_size)
    plan = scan_source(src, pyramid)
    quant = plan.quant(grid_vertices=(method == "chunked"), headroom=epoch is not None)

    def make_meta() -> dict:
        return builder._store_meta(_FrameMeta(src, plan, _ladder_read(src, pyramid, method)), pyramid,
                                   method, quant)  # type: ignore[arg-type]  # fmt: skip

    fresh = not (resume and p.exists())
    if fresh:
        _check_new_target(p, overwrite)  # refused in one line before any work
    # A fresh build meshes the levels that need no stated options (adaptive's finest level, the grid)
    # while the options are computed beside them (adaptive's ladder: a read of the root's window and a
    # TIN of it, serial), and creates the store once they are known.
    free = (
        getattr(builder.METHODS[method], "levels_without_options", lambda _: set())(pyramid)
        if fresh
        else set()
    )
    side = ThreadPoolExecutor(max_workers=1)
    meta_f = side.submit(make_meta)
    runner = (
        _DaskRunner(client, retries)
        if client is not None
        else _ThreadRunner(max(1, workers or os.cpu_count() or 1))
    )
    built = n_skipped = total = 0
    store: TileStore | None = None
    target = p
    try:
        errors = TileErrors(pyramid)
        if not fresh:
            store, target = _open_or_create(p, meta_f.result(), resume, overwrite)
            _first_epoch(store, epoch, src, plan)
            errors.update(store.each_tile_error())
        total = sum(nx * ny for nx, ny in map(pyramid.grid_count, pyramid.levels))
        n_skipped = len(errors)
        if progress:
            progress(n_skipped, total)
        shared = runner.share(src)
        todo = _todo(pyramid, errors, stop_after)
        slots = runner.slots()

        def job(unit: list[TileCode], options: dict | None) -> tuple:
            return unit_job(shared, tile_size, method, unit, quant, max_window_samples, options)

        def jobs() -> Iterator[tuple]:
            _, now = _unit_order(
                pyramid, {lv: m for lv, m in todo.items() if lv in free}, unit_span_samples, 0
            )
            for unit in now:
                if meta_f.done():
                    now = itertools.chain([unit], now)
                    break
                yield job(unit, None)
            options = meta_f.result()["build_options"]
            early, rest = _unit_order(pyramid, {lv: m for lv, m in todo.items() if lv not in free},
                                      unit_span_samples, _EARLY_UNITS_PER_SLOT * slots)  # fmt: skip
            yield from (job(u, options) for u in early)
            yield from (job(u, None) for u in now)
            yield from (job(u, options) for u in rest)

        measured = (enc for tiles in runner.stream(jobs(), _AHEAD_UNITS_PER_SLOT * slots) for enc in tiles)
        ordered = _monotone(measured, pyramid, errors)
        held: list[EncodedTile] = []
        if store is None:  # tiles built before the store exists wait here (errors recorded for parents)
            held = builder.hold_until(ordered, meta_f, errors)
            store, target = _open_or_create(p, meta_f.result(), resume, overwrite)
            _first_epoch(store, epoch, src, plan)
        built = builder.commit_streamed(store, itertools.chain(held, ordered), errors, built,
                                        lambda n: progress(n_skipped + n, total) if progress else None)  # fmt: skip
        if n_skipped + built == total:
            store.complete_first_epoch()
            store.set_meta("complete", True)
    except BaseException:
        runner.close()
        side.shutdown(cancel_futures=True)
        if store is not None:
            store.close()
            if target != p:  # --overwrite: the old store was never touched
                remove_store_files(target)
        raise
    side.shutdown()
    runner.close()
    assert store is not None  # made in the try block, or it raised
    store.close()
    if target != p:
        if n_skipped + built == total:
            install_store(target, p)
        else:
            remove_store_files(target)  # stopped early (stop_after): the old store stays as it was
    seconds = time.perf_counter() - t_start
    log.info("built %d tiles (%d already present) in %.2f s, out of core", built, n_skipped, seconds)
    return builder.BuildReport(p, total, built, n_skipped, seconds, src.width * src.height)


def source_strips(
    src: WindowSource, rows: int = SOURCE_BLOCK
) -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
    """``(row0, elevation_m, valid)`` of ``src`` in full-width strips of ``rows`` rows, top to bottom."""
    for r0 in range(0, src.height, rows):
        z, ok = src.read(r0, 0, min(r0 + rows, src.height), src.width)
        yield r0, z, ok


def _first_epoch(store: TileStore, epoch: str | None, src: WindowSource, plan: StreamPlan) -> None:
    """A build with ``epoch``: begin (or find, resumed) the store's first epoch and keep ``src``'s samples
    with it, read in strips (:meth:`~terralod.store.TileStore.start_first_epoch_from`)."""
    if epoch is None:
        return
    strips = ((r0, z, ok, None) for r0, z, ok in source_strips(src))
    store.start_first_epoch_from(
        str(epoch), epoch_record(_FrameMeta(src, plan), "build"),
        lambda eid: store.put_epoch_source_strips(eid, src.width, strips), plan.z_range_m,
    )  # fmt: skip


def _check_new_target(p: Path, overwrite: bool) -> None:
    """The refusals of :func:`_open_or_create` for a new store, made before any work."""
    if p.exists() or p.is_symlink():
        if not overwrite:
            raise StoreError("already exists; use --resume to finish it or --overwrite to replace it", str(p))
        if p.is_dir():
            raise StoreError("is a directory, not a tile store", str(p))


def _open_or_create(p: Path, meta: dict, resume: bool, overwrite: bool) -> tuple[TileStore, Path]:
    """The store to write and where it is: resumed at ``p`` (its meta must match this build's), created
    at ``p`` (atomically), or with ``overwrite`` created beside ``p``, which the caller renames over ``p``
    once complete (the old store is never removed before the new one is whole)."""
    if p.exists() and resume:
        store = TileStore.open(p, writable=True)
        for key in ("source_digest", "build_options", "quantisation", "width", "height", "tile_size"):
            if store.meta.get(key) != meta[key]:
                store.close()
                raise BuildMismatchError(
                    f"cannot resume: the store's {key} differs from this build (other source or options); "
                    "use --overwrite to rebuild",
                    str(p),
                )
        return store, p
    if p.exists() or p.is_symlink():
        _check_new_target(p, overwrite)
        target = replacement_path(p)
        remove_store_files(target)
        return TileStore.create(target, meta), target
    return TileStore.create(p, meta), p
