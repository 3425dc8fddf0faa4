"""Adaptive tiles: every tile of the pyramid is an adaptive TIN refined down to its level's target error.

The mesher is greedy insertion of the worst sample into a Delaunay triangulation (Garland & Heckbert 1995,
algorithm III, as mapbox/delatin implements it; no paper of ``../shared/papers`` — the papers' tiles are
regular grids, Sung, Lee & Shin (2021) §2 surveys TINs as the alternative it does not take): the kernels are in
:mod:`terralod.kernels.adaptive`. What the pyramid adds:

- the error ladder: level k < L is refined to ``target_m[k] = root_error_m / 2^k`` of vertical error over
  every source sample of the tile (its window of the full-resolution source, not the level's grid), stated
  in the store's metadata (``build_options.target_error_m``). By default ``root_error_m`` is the error the
  greedy insertion reaches on the whole terrain (decimated to at most 4097² samples, every f-th row and
  column, so that an out-of-core build computes it from one decimated read: :func:`ladder_window`) with
  as many vertices as a regular 65² tile has (:data:`ROOT_VERTICES`, whatever the tile size M), so the
  root weighs about what a regular root weighs, and each level below about the same per tile wherever the
  terrain's roughness is alike across scales (a flat plain costs 2 triangles a tile);
- the finest level L (stride 1) is by default the regular grid of its samples (target 0, lossless, as a
  regular pyramid's finest level is), not the ladder's ``root_error_m / 2^L``. The tile size M sets how
  far the ladder goes before that grid: a tile of level k spans (M - 1) 2^(L-k) samples, so halving M adds
  one level (the ladder's root and the levels M = 65 has are meshed alike), each tile a quarter of the
  area. With 65² tiles the ladder spans only L + 1 levels (Puget Sound 1k: 302 m to 37.8 m, then the grid),
  and 70 % of the triangles drawn along a 2 px camera path were grid tiles near the eye; the default
  adaptive tiles are 33² (:data:`DEFAULT_TILE_SIZE`: 302 m to 18.9 m, then the grid), which draw about
  half the triangles at 1.6-1.8x the build time (``benchmarks/results/build.md``). Ending the ladder
  with a greedy finest level instead of the grid (``finest_level_error_m=None``: the ladder's
  ``root_error_m / 2^L``; a finest level at 18.9 m cannot hold 2 px near the eye; or near-lossless 0.5 m:
  only 6-14 % fewer triangles than the grid at 2-2.7x the build time) does not pay: the grid codes in about
  a third of the bytes a triangle, and the runtime never draws a finest tile whose parent is exact, so a
  flat plain still draws its 2-triangle parents. ``finest_error_m`` sets the ladder from that end instead.
  The stored errors are measured on the stored (quantised) geometry by the builder, as for every method, so
  a tile may measure a few millimetres above its target (the vertical quantisation step). Lossless means
  against the grid meshed: for a reprojected (geographic, Mercator) source the builder also measures every
  tile against the source's own samples (:mod:`terralod.pyramid.original`), so the finest level states what
  the resampling moved them by (up to 107 m on SRTM3 N42E001), never 0;
- shared borders: the four sides of a tile are fixed before its interior, each by a 1-D simplification of
  the side's own line of source samples to the level's target (split at the worst sample until every
  segment is within it), so the two tiles sharing a side compute the same vertices from the same samples,
  bit for bit; across levels the runtime's stitcher (Li, Liu & Liu §3.3) fits the finer side onto the coarser
  polyline and fan-splits where needed, as it does for the cohesion tiles' relocated sides;
- partial tiles at the data's edge end at the last sample (no padding apron, no replicated heights): every
  level ends at the same place.

Deviations from Delatin: border fixed first (above), invalid samples never inserted nor measured,
triangles within the target never queued (see the kernel module), and a tile whose window spans >= 512
samples seeded from a pass on every (span / 256)-th sample of its window (:data:`SEED_MIN_SPAN`): the
greedy insertion on the full source starts from that pass's interior vertices, so it no longer rescans the
huge early triangles of a coarse window, and still refines until the target holds at every sample.
"""

from __future__ import annotations

import threading
import weakref
from dataclasses import dataclass

import numpy as np

from terralod.kernels.adaptive import raster_order, simplify_line, tin_window, tin_window_seeded
from terralod.pyramid import chunked
from terralod.tiles import TileCode, TilePyramid

__all__ = [
    "DEFAULT_TILE_SIZE",
    "LADDER_MAX_SIDE",
    "ROOT_VERTICES",
    "AdaptiveOptions",
    "ladder_window",
    "make_mesher",
    "mesh_tile",
    "mesher_for",
    "target_ladder",
]


@dataclass(frozen=True)
class AdaptiveOptions:
    """Settings of the adaptive mesher (keyword-only in :func:`make_mesher`).

    Attributes
    ----------
    root_error_m : target max vertical error of the root tile, metres (level k: root_error_m / 2^k);
        None: from ``finest_error_m`` if given, else from ``root_vertices``
    finest_error_m : target of the finest level (root_error_m = finest_error_m * 2^L), metres (then
        ``finest_level_error_m`` does not apply)
    root_vertices : with neither error given, root_error_m is the max vertical error of the greedy TIN of
        the whole terrain with this many vertices (None: :data:`ROOT_VERTICES`, a regular 65² tile's count,
        whatever the tile size M)
    max_tile_vertices : a tile stops refining at this many vertices (None: no cap), so a tile whose target
        is out of reach stays as heavy as that (its stored error is then its measured one, above the target)
    finest_level_error_m : the finest level's own target, metres, below the ladder's (None: the ladder's;
        default 0, the grid):
        the finest level near-lossless, the levels above it on the ladder; 0 makes the finest level the
        regular grid of its samples (lossless, as a regular pyramid's finest level is, and meshed without
        insertion: :func:`terralod.pyramid.chunked.mesh_tile` at stride 1)
    """

    root_error_m: float | None = None
    finest_error_m: float | None = None
    root_vertices: int | None = None
    max_tile_vertices: int | None = None
    finest_level_error_m: float | None = 0.0

    def __post_init__(self) -> None:
        if self.root_error_m is not None and not self.root_error_m > 0:
            raise ValueError(f"Expected root_error_m > 0, got {self.root_error_m}")
        if self.finest_error_m is not None and not self.finest_error_m > 0:
            raise ValueError(f"Expected finest_error_m > 0, got {self.finest_error_m}")
        if self.root_vertices is not None and self.root_vertices < 4:
            raise ValueError(f"Expected root_vertices >= 4, got {self.root_vertices}")
        if self.finest_level_error_m is not None and not self.finest_level_error_m >= 0:
            raise ValueError(f"Expected finest_level_error_m >= 0, got {self.finest_level_error_m}")
        if self.max_tile_vertices is not None and self.max_tile_vertices < 4:
            raise ValueError(f"Expected max_tile_vertices >= 4, got {self.max_tile_vertices}")


#: Ladders computed from the data (root_vertices), per (array id, shape, pyramid, options), with a weak
#: reference that proves the array is still the same one.
_LADDERS: dict[tuple, tuple[weakref.ref, list[float]]] = {}
_LADDERS_LOCK = threading.Lock()


def target_ladder(
    pyramid: TilePyramid, opt: AdaptiveOptions, z: np.ndarray | None = None, valid: np.ndarray | None = None
) -> list[float]:
    """Target max vertical error per level, metres, coarsest first: root_error_m / 2^k, the finest level at
    ``finest_level_error_m`` where that is lower (z and valid are needed when the root error comes from
    ``root_vertices``)."""
    ladder = _halving_ladder(pyramid, opt, z, valid)
    if opt.finest_level_error_m is not None and opt.finest_error_m is None:
        ladder[-1] = min(ladder[-1], opt.finest_level_error_m)
    return ladder


def _halving_ladder(
    pyramid: TilePyramid, opt: AdaptiveOptions, z: np.ndarray | None, valid: np.ndarray | None
) -> list[float]:
    top = pyramid.max_level
    if opt.root_error_m is not None:
        root = opt.root_error_m
    elif opt.finest_error_m is not None:
        root = opt.finest_error_m * 2.0**top
    else:
        if z is None or valid is None:
            raise ValueError("Expected the terrain (z, valid) for a ladder from root_vertices")
        key = (id(z), z.shape, pyramid, opt.root_vertices, ladder_window(*z.shape, pyramid))
        with _LADDERS_LOCK:
            hit = _LADDERS.get(key)
            if hit is not None and hit[0]() is z:
                return list(hit[1])
            root = _budget_error(z, valid, pyramid, opt.root_vertices or ROOT_VERTICES)
            ladder = [root / 2.0**k for k in range(top + 1)]
            _LADDERS[key] = (weakref.ref(z), ladder)
            return list(ladder)
    return [root / 2.0**k for k in range(top + 1)]


#: The default ladder's root holds as many vertices as a regular 65² tile: the ladder does not move with the
#: tile size M, which sets how deep it goes instead (M = 33: one level more than 65, each tile a quarter of
#: the area; the levels they share are meshed alike).
ROOT_VERTICES = 65 * 65

#: The tile size M of an adaptive build that gives none (:func:`terralod.pyramid.builder.default_tile_size`):
#: 33, one ladder level below 65's before the lossless grid. Measured side by side (benchmarks/build.py,
#: Pyrenees N42E001 / Puget Sound 1k): along the 2 px camera path 65² tiles draw 0.30x / 0.36x Chunked LOD's
#: triangles and 33² tiles 0.17x / 0.19x, at 1.6-1.8x the build time (the extra level's greedy insertion)
#: and 1.6-1.7x the store, and the uniform cut reaches 10 m / 20 m at 1.32x / 1.05x pydelatin's triangles
#: instead of falling to the grid; 17² tiles (two levels more) draw 0.17x / 0.17x at 3.1-4.0x 65²'s build
#: time.
DEFAULT_TILE_SIZE = 33

#: The default ladder's root error is measured on the root's window decimated to at most this many samples
#: a side (every f-th row and column, f a power of two), so that an out-of-core build, which never holds
#: the DEM whole, computes the same ladder from a decimated read (:func:`ladder_window`).
LADDER_MAX_SIDE = 4097


def ladder_window(height: int, width: int, pyramid: TilePyramid) -> tuple[int, int, int]:
    """``(rows, cols, f)``: the default ladder reads rows ``0, f, 2f, ... < rows`` and the same columns of
    a ``height`` x ``width`` source (the root's window, decimated to at most :data:`LADDER_MAX_SIDE`)."""
    hh, ww = min(height, pyramid.span(0) + 1), min(width, pyramid.span(0) + 1)
    f = 1
    while (max(hh, ww) - 1) // f + 1 > LADDER_MAX_SIDE:
        f *= 2
    return hh, ww, f


def _budget_error(z: np.ndarray, valid: np.ndarray, pyramid: TilePyramid, n_vertices: int) -> float:
    """The lowest max vertical error that the greedy insertion on the whole source (the root's window,
    decimated by :func:`ladder_window`) reaches within ``n_vertices`` vertices, metres (at least 1 mm, so
    that the ladder is never 0). A source already decimated (an out-of-core build's read) is taken as it
    is. The lowest, not the last mesh's: a flip can make a triangle worse than the sample just inserted,
    so the last mesh's error spikes (Puget Sound 1k: 249 m at 6,000 vertices, 591 m at 6,337, 300 m at
    6,500), and the ladder, every level's target, would double with it."""
    hh, ww, f = ladder_window(*z.shape, pyramid)
    zw = np.ascontiguousarray(z[:hh:f, :ww:f])
    vw = np.ascontiguousarray(valid[:hh:f, :ww:f])
    empty = np.zeros(0, np.int64)
    _, _, _, _, best = tin_window(zw, vw, empty, empty, 0.0, int(n_vertices))
    return max(float(best), 1e-3)


def _side(z: np.ndarray, valid: np.ndarray, target: float) -> np.ndarray:
    """Kept indices (ascending, ends included) of one side's line of samples."""
    return simplify_line(np.ascontiguousarray(z), np.ascontiguousarray(valid), float(target))


def _border(zw: np.ndarray, vw: np.ndarray, target: float) -> tuple[np.ndarray, np.ndarray]:
    """(x, y) int64 of a window's border vertices other than its corners: each side simplified from its
    own line of samples to ``target``."""
    hh, ww = zw.shape
    north = _side(zw[0], vw[0], target)[1:-1]
    south = _side(zw[-1], vw[-1], target)[1:-1]
    west = _side(zw[:, 0], vw[:, 0], target)[1:-1]
    east = _side(zw[:, -1], vw[:, -1], target)[1:-1]
    bx = np.concatenate([north, np.full(east.size, ww - 1), south, np.zeros(west.size, np.int64)])
    by = np.concatenate([np.zeros(north.size, np.int64), east, np.full(south.size, hh - 1), west])
    return bx.astype(np.int64), by.astype(np.int64)


def mesh_tile_with(
    z: np.ndarray, valid: np.ndarray, pyramid: TilePyramid, code: TileCode, opt: AdaptiveOptions
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Adaptive TIN of tile ``code`` with settings ``opt`` (see :func:`mesh_tile`)."""
    level = code[0]
    if level == pyramid.max_level and _finest_is_grid(opt):  # whatever the ladder (so without it)
        return chunked.mesh_tile(z, valid, pyramid, code)
    target = target_ladder(pyramid, opt, z, valid)[level]
    h, w = z.shape
    r0, c0 = pyramid.origin_rc(code)
    span = pyramid.span(level)
    r1 = min(r0 + span, h - 1)
    c1 = min(c0 + span, w - 1)
    zw = np.ascontiguousarray(z[r0 : r1 + 1, c0 : c1 + 1])
    vw = np.ascontiguousarray(valid[r0 : r1 + 1, c0 : c1 + 1])
    hh, ww = zw.shape
    # the four sides, each from its own line of samples (what the neighbour across it computes too)
    bx, by = _border(zw, vw, target)
    cap = hh * ww if opt.max_tile_vertices is None else max(4 + bx.size, opt.max_tile_vertices)
    # seeded from a decimated pass (coarse tiles), unless a vertex cap makes every vertex count: the
    # decimated pass's vertices would then take the cap's places before the full source's worst samples
    f = span // SEED_SAMPLES if span >= SEED_MIN_SPAN and opt.max_tile_vertices is None else 1
    sx, sy = _seeds(zw, vw, f, float(target))
    px, py, tris, _, _ = tin_window_seeded(zw, vw, bx, by, sx, sy, float(target), cap)
    # raster order of the vertices (coherent deltas for the store's coding), triangles renumbered and
    # flipped to counter-clockwise seen from above (y north: rows grow south)
    if px.size < _KERNEL_ORDER_MAX_VERTICES:
        return raster_order(zw, px, py, tris, r0, c0)
    return _raster_order_numpy(zw, px, py, tris, r0, c0)


#: A tile whose window spans s >= SEED_MIN_SPAN source samples is first meshed on every (s / SEED_SAMPLES)-th
#: sample of its window; its interior vertices then seed the greedy insertion on the full source, which goes
#: on until the target holds at every sample. The rule is the window's, not the level's stride, so that a
#: tile is meshed alike whatever the tile size M (with 65² tiles: strides >= 8, every (stride / 4)-th
#: sample). Measured per level with 65² tiles (one thread; seeded / full-source insertion alone):
#: Pyrenees N42E001 strides 32, 16, 8: 0.031 / 0.265, 0.057 / 0.137, 0.129 / 0.177 s with 3,787 / 4,146,
#: 12,889 / 12,970, 36,131 / 35,363 vertices; Puget Sound 1k strides 16, 8: 0.019 / 0.113, 0.050 / 0.073 s
#: with 3,755 / 3,987, 13,610 / 13,948 vertices. Seeding from every (s / 2)-th sample cost up to 10 % more
#: vertices (Pyrenees stride 8); at stride 4 (from every 2nd sample) it saved 18 % of the time for 5 % more.
SEED_MIN_SPAN = 512
SEED_SAMPLES = 256


def _seeds(zw: np.ndarray, vw: np.ndarray, f: int, target: float) -> tuple[np.ndarray, np.ndarray]:
    """Interior vertices (full-window x, y, raster order) of the greedy TIN of every f-th sample of the
    window to ``target`` (none when f < 2)."""
    if f < 2:
        empty = np.zeros(0, np.int64)
        return empty, empty
    zd = np.ascontiguousarray(zw[::f, ::f])
    vd = np.ascontiguousarray(vw[::f, ::f])
    hd, wd = zd.shape
    if hd < 3 or wd < 3:
        empty = np.zeros(0, np.int64)
        return empty, empty
    bx, by = _border(zd, vd, target)
    px, py, _, _, _ = tin_window(zd, vd, bx, by, target, hd * wd)
    inner = (px > 0) & (px < wd - 1) & (py > 0) & (py < hd - 1)
    px, py = px[inner] * f, py[inner] * f
    order = np.lexsort((px, py))
    return np.ascontiguousarray(px[order]), np.ascontiguousarray(py[order])


#: :func:`raster_order` keys triangles by ``(a N + b) N + c``, which fits int64 below 2^21 vertices.
_KERNEL_ORDER_MAX_VERTICES = 1 << 21


def _raster_order_numpy(
    zw: np.ndarray, px: np.ndarray, py: np.ndarray, tris: np.ndarray, r0: int, c0: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`terralod.kernels.adaptive.raster_order` with numpy's lexsort (any number of vertices)."""
    order = np.lexsort((px, py))
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)
    t = rank[tris.astype(np.int64)]
    t = t[:, [0, 2, 1]]
    t = t[np.lexsort((t[:, 2], t[:, 1], t[:, 0]))].astype(np.int32)
    rows = (r0 + py[order]).astype(np.float64)
    cols = (c0 + px[order]).astype(np.float64)
    hz = zw[py[order], px[order]].astype(np.float64)
    return rows, cols, hz, t


def make_mesher(**options):
    """A tile mesher (for :func:`terralod.pyramid.builder.register_method`) with :class:`AdaptiveOptions`."""
    opt = AdaptiveOptions(**options)

    def mesher(z: np.ndarray, valid: np.ndarray, pyramid: TilePyramid, code: TileCode):
        return mesh_tile_with(z, valid, pyramid, code, opt)

    mesher.options = opt  # type: ignore[attr-defined]
    mesher.default_tile_size = DEFAULT_TILE_SIZE  # type: ignore[attr-defined]
    mesher.window_margin = _no_margin  # type: ignore[attr-defined]
    mesher.ladder_window = ladder_window  # type: ignore[attr-defined]
    mesher.with_build_options = mesher_for  # type: ignore[attr-defined]
    mesher.levels_without_options = lambda pyramid: _levels_without_options(opt, pyramid)  # type: ignore[attr-defined]
    mesher.build_meta = lambda z, valid, pyramid: _build_meta(z, valid, pyramid, opt)  # type: ignore[attr-defined]
    return mesher


def mesher_for(build_options: dict):
    """The mesher of a store's stated adaptive build (its ``build_options``), with the ladder fixed to the
    stated one: what a partial rebuild (an epoch's dirty tiles) must mesh with, since the default ladder is
    computed from the data and would move with it (and the borders of rebuilt tiles with it)."""
    ladder = build_options.get("target_error_m")
    if not ladder:
        raise ValueError(
            f"Expected an adaptive store's build_options with target_error_m, got {build_options}"
        )
    finest = build_options.get("finest_level_error_m")
    return make_mesher(
        root_error_m=float(ladder[0]),
        max_tile_vertices=build_options.get("max_tile_vertices"),
        finest_level_error_m=None if finest is None else float(finest),
    )


def _finest_is_grid(opt: AdaptiveOptions) -> bool:
    """True when the finest level's target is 0 for any ladder (it is the regular grid of its samples)."""
    return opt.finest_error_m is None and opt.finest_level_error_m == 0.0


def _levels_without_options(opt: AdaptiveOptions, pyramid: TilePyramid) -> set[int]:
    """Levels whose tiles do not depend on the store's stated build options (the ladder): the finest when
    it is the grid. A build meshes them while it computes the ladder."""
    return {pyramid.max_level} if _finest_is_grid(opt) else set()


def _no_margin(stride: int) -> int:
    """Samples beyond its own window that the mesher reads: none (the sides are the window's own lines)."""
    return 0


def _build_meta(z: np.ndarray, valid: np.ndarray, pyramid: TilePyramid, opt: AdaptiveOptions) -> dict:
    """What the store states about an adaptive build: the options and the ladder (metres, level 0 first)."""
    return {
        "root_error_m": opt.root_error_m,
        "finest_error_m": opt.finest_error_m,
        "root_vertices": opt.root_vertices,
        "max_tile_vertices": opt.max_tile_vertices,
        "finest_level_error_m": opt.finest_level_error_m,
        "target_error_m": target_ladder(pyramid, opt, z, valid),
    }


_DEFAULT = AdaptiveOptions()


def mesh_tile(
    z: np.ndarray, valid: np.ndarray, pyramid: TilePyramid, code: TileCode
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Adaptive TIN of tile ``code`` with the default :class:`AdaptiveOptions`.

    Returns
    -------
    rows, cols : (N,) float64 source sample coordinates (row south, col east) of the vertices (integers)
    heights_m : (N,) float64 elevation, metres (the samples' own)
    triangles : (K, 3) int32, counter-clockwise seen from above
    """
    return mesh_tile_with(z, valid, pyramid, code, _DEFAULT)


mesh_tile.options = _DEFAULT  # type: ignore[attr-defined]
mesh_tile.default_tile_size = DEFAULT_TILE_SIZE  # type: ignore[attr-defined]
mesh_tile.window_margin = _no_margin  # type: ignore[attr-defined]
#: an out-of-core build reads this decimated window for ``build_meta`` and meshes its work units with
#: ``with_build_options(the stated build_options)``: the ladder fixed, never recomputed from a window
mesh_tile.ladder_window = ladder_window  # type: ignore[attr-defined]
mesh_tile.with_build_options = mesher_for  # type: ignore[attr-defined]
mesh_tile.levels_without_options = lambda pyramid: _levels_without_options(_DEFAULT, pyramid)  # type: ignore[attr-defined]
mesh_tile.build_meta = lambda z, valid, pyramid: _build_meta(z, valid, pyramid, _DEFAULT)  # type: ignore[attr-defined]
