"""View-dependent tile selection and the runtime engine (select → adjacency → stitch → normals).

Implements the selection of ``../shared/papers/000_0f8c6950ace8a2d1.txt`` §3.3–3.4: the stored per-tile
Hausdorff error is projected to pixels (DESIGN.md: rho = error_m * H / (2 d tan(fov_y / 2)), d the distance
from the eye to the tile's bounding box) and a tile is refined while rho exceeds the threshold; the
*quadtree parser* keeps the last frame's leaf list and the next frame starts from it, splitting or merging
only where the answer changed, and reusing the whole result when the camera did not move; *parent
fallback* draws a parent whose own geometry already meets the threshold where its children are no better
(cohesion maps can make a child worse than its parent). The selected leaves then go through the crack
removal of ``../shared/papers/002_037d1654b87e3b6a.txt`` §3.1–3.4 (:mod:`.adjacency`, :mod:`.stitch`,
:mod:`.normals`).

Why the incremental result equals a fresh one: a tile is *refined* when its box is in the frustum, rho > tau
and its children are in the store. Boxes are nested (each parent box is made the union of its own and its
children's) and errors are monotone (parent >= child), so "refined" is inherited upwards exactly, in floating
point too: distance, projection and the plane test are monotone in the box. The fresh selection's leaves
are the non-refined tiles whose ancestors are all refined; from each old leaf the new leaves are found by
climbing while the parent is not refined (merge) or descending while refined (split). Both give the same
set, which the tests check frame by frame.

Deviations (and why): the paper's parser lives on the GPU command side; ours is a pure query (CDLOD style):
(tree, camera, threshold) → leaves. Culled tiles are not refined and stay in the leaf list as *culled
leaves* (not drawn), so the leaves always partition the terrain and adjacency is always defined. The box
z-range is the tile's vertex range widened by its vertical error, which bounds every source sample below
the tile (so a culled tile cannot hide a finer neighbour's border). With a triangle budget the selection
refines the largest screen error first (a priority queue from the root) until the next split would exceed
the budget; that mode does a full traversal each frame (still reused when the camera is still).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from terralod.kernels import jit
from terralod.runtime.adjacency import CULLED, VISIBLE, Adjacency, QuadIndex, _parent, _slot
from terralod.runtime.camera import Camera, _box_distance, _box_visible
from terralod.runtime.loader import TileLoader
from terralod.runtime.stitch import Stitcher, TileCache, TileSource
from terralod.tiles import TileCode

log = logging.getLogger(__name__)

__all__ = ["Engine", "FrameStats", "Selection", "TileTable"]

#: Node classes of one frame: drawn as is, outside the frustum, or to be split.
_STOP, _CULL, _REFINE = 1, 2, 3


class TileTable:
    """Per-slot tile scalars for selection (from the store's summaries; no geometry is read).

    Attributes (arrays over :class:`QuadIndex` slots)
    ------------------------------------------------
    avail : bool, the tile is in the store
    error_m : monotone one-sided Hausdorff error, metres (parent >= children, enforced again here)
    measured_error_m : the tile's own measured error, metres (parent fallback)
    triangles : stored triangle count
    boxes : (n, 6) float64 (xmin, ymin, zmin, xmax, ymax, zmax) world metres, nested (parent ⊇ child)
    kids_ok : bool, the tile has children and every one of them is in the store
    """

    def __init__(self, source: TileSource, index: QuadIndex) -> None:
        pyr = source.pyramid
        n = index.n
        rows = source.tile_summaries()
        if not rows:
            raise ValueError("Expected a tile store with tiles, got an empty store")
        codes = np.array([(r["level"], r["x"], r["y"]) for r in rows], np.int64)
        slots = index.slots(codes)
        self.avail = np.zeros(n, bool)
        self.avail[slots] = True
        self.error_m = np.zeros(n)
        self.measured_error_m = np.zeros(n)
        self.triangles = np.zeros(n, np.int64)
        vert = np.zeros(n)
        zmin = np.full(n, np.inf)
        zmax = np.full(n, -np.inf)

        def col(key: str, default: float = 0.0) -> np.ndarray:
            return np.array([float(r.get(key, default)) for r in rows])

        self.error_m[slots] = col("error_m")
        self.measured_error_m[slots] = np.array(
            [float(r.get("measured_error_m", r["error_m"])) for r in rows]
        )
        self.triangles[slots] = col("n_triangles").astype(np.int64)
        vert[slots] = np.array([float(r.get("vertical_error_m", r["error_m"])) for r in rows])
        zmin[slots] = col("z_min_m")
        zmax[slots] = col("z_max_m")

        # xy from the plan: the tile square, clipped where its quads end at the data's far edge
        k, x, y = index.lvl, index.tx, index.ty
        stride = np.left_shift(1, pyr.max_level - k)
        span = pyr.cells * stride
        r0, c0 = y * span, x * span
        c_len = np.minimum(span, -(-(pyr.width - 1 - c0) // stride) * stride)
        r_len = np.minimum(span, -(-(pyr.height - 1 - r0) // stride) * stride)
        t = source.transform
        x0, y0 = t.c + 0.5 * t.a, t.f + 0.5 * t.e
        boxes = np.empty((n, 6))
        boxes[:, 0] = x0 + c0 * t.a
        boxes[:, 3] = x0 + (c0 + c_len) * t.a
        boxes[:, 1] = y0 + (r0 + r_len) * t.e
        boxes[:, 4] = y0 + r0 * t.e
        boxes[:, 2] = zmin - vert
        boxes[:, 5] = zmax + vert

        # nesting, monotone errors and child availability, finest level first
        self.kids_ok = np.zeros(n, bool)
        for lev in range(pyr.max_level, 0, -1):
            ch = np.arange(index.off[lev], index.off[lev] + index.nx[lev] * index.ny[lev])
            par = index.off[lev - 1] + (index.ty[ch] >> 1) * index.nx[lev - 1] + (index.tx[ch] >> 1)
            ok = self.avail[ch]
            for a in range(3):
                np.minimum.at(boxes[:, a], par[ok], boxes[ch[ok], a])
                np.maximum.at(boxes[:, a + 3], par[ok], boxes[ch[ok], a + 3])
            np.maximum.at(self.error_m, par[ok], self.error_m[ch[ok]])
            n_kids = np.bincount(par - index.off[lev - 1], minlength=index.nx[lev - 1] * index.ny[lev - 1])
            n_ok = np.bincount(par[ok] - index.off[lev - 1], minlength=index.nx[lev - 1] * index.ny[lev - 1])
            self.kids_ok[index.off[lev - 1] : index.off[lev]] = (n_kids > 0) & (n_kids == n_ok)
        self.kids_ok &= self.avail
        self.boxes = np.ascontiguousarray(boxes)


# -- selection kernels ---------------------------------------------------------------------------------
@jit
def _classify(s, boxes, err, kids_ok, planes, eye, k_px, tau):
    b = boxes[s]
    if not _box_visible(b, planes):
        return _CULL
    if not kids_ok[s]:
        return _STOP
    d = _box_distance(b, eye)
    rho = err[s] * k_px / d  # inf at d = 0 (numpy error model); nan (0/0) compares False: stop
    return _REFINE if rho > tau else _STOP


@jit
def _children(s, lvl, tx, ty, off, nx, ny, out):
    k = lvl[s] + 1
    m = 0
    if k >= off.shape[0]:
        return 0
    for dy in range(2):
        for dx in range(2):
            c = _slot(k, 2 * tx[s] + dx, 2 * ty[s] + dy, off, nx, ny)
            if c >= 0:
                out[m] = c
                m += 1
    return m


@jit
def _descend(
    root, cls0, boxes, err, kids_ok, planes, eye, k_px, tau, lvl, tx, ty, off, nx, ny, leaves, states, m
):
    """Depth-first selection below ``root`` (whose class is ``cls0``); appends to leaves/states at m."""
    if cls0 != _REFINE:
        leaves[m] = root
        states[m] = 2 if cls0 == _CULL else 1
        return m + 1
    stack = np.empty(4 * (off.shape[0] + 2), np.int64)
    kids = np.empty(4, np.int64)
    nk = _children(root, lvl, tx, ty, off, nx, ny, kids)
    top = 0
    for i in range(nk - 1, -1, -1):
        stack[top] = kids[i]
        top += 1
    while top > 0:
        top -= 1
        s = stack[top]
        c = _classify(s, boxes, err, kids_ok, planes, eye, k_px, tau)
        if c == _REFINE:
            nk = _children(s, lvl, tx, ty, off, nx, ny, kids)
            for i in range(nk - 1, -1, -1):
                stack[top] = kids[i]
                top += 1
        else:
            leaves[m] = s
            states[m] = 2 if c == _CULL else 1
            m += 1
    return m


@jit
def _select_full(boxes, err, kids_ok, planes, eye, k_px, tau, lvl, tx, ty, off, nx, ny):
    """Fresh selection from the root: (leaf slots, states 1 visible / 2 culled)."""
    n = boxes.shape[0]
    leaves = np.empty(n, np.int64)
    states = np.empty(n, np.int8)
    c = _classify(0, boxes, err, kids_ok, planes, eye, k_px, tau)
    m = _descend(
        0, c, boxes, err, kids_ok, planes, eye, k_px, tau, lvl, tx, ty, off, nx, ny, leaves, states, 0
    )
    return leaves[:m].copy(), states[:m].copy()


@jit
def _select_incremental(
    prev,
    boxes,
    err,
    kids_ok,
    planes,
    eye,
    k_px,
    tau,
    lvl,
    tx,
    ty,
    off,
    nx,
    ny,
    memo,
    memo_val,
    emitted,
    stamp,
):
    """Sung, Lee & Shin's (2021) quadtree parser: the new leaves from last frame's leaves, splitting/merging locally."""
    n = boxes.shape[0]
    leaves = np.empty(n, np.int64)
    states = np.empty(n, np.int8)
    m = 0
    for i in range(prev.shape[0]):
        t = prev[i]
        p = _parent(t, lvl, tx, ty, off, nx, ny)
        pc = _REFINE
        if p >= 0:
            if memo[p] != stamp:
                memo[p] = stamp
                memo_val[p] = _classify(p, boxes, err, kids_ok, planes, eye, k_px, tau)
            pc = memo_val[p]
        if pc != _REFINE:
            # merge: climb to the highest ancestor that is not refined (its parent is)
            a = p
            ac = pc
            while True:
                g = _parent(a, lvl, tx, ty, off, nx, ny)
                if g < 0:
                    break
                if memo[g] != stamp:
                    memo[g] = stamp
                    memo_val[g] = _classify(g, boxes, err, kids_ok, planes, eye, k_px, tau)
                if memo_val[g] == _REFINE:
                    break
                a = g
                ac = memo_val[g]
            if emitted[a] != stamp:
                emitted[a] = stamp
                leaves[m] = a
                states[m] = 2 if ac == _CULL else 1
                m += 1
        else:
            c = _classify(t, boxes, err, kids_ok, planes, eye, k_px, tau)
            m = _descend(
                t, c, boxes, err, kids_ok, planes, eye, k_px, tau, lvl, tx, ty, off, nx, ny, leaves, states, m
            )
    return leaves[:m].copy(), states[:m].copy()


@jit
def _heap_push(keys, vals, size, key, val):
    i = size
    keys[i] = key
    vals[i] = val
    while i > 0:
        p = (i - 1) >> 1
        if keys[p] >= keys[i]:
            break
        keys[p], keys[i] = keys[i], keys[p]
        vals[p], vals[i] = vals[i], vals[p]
        i = p
    return size + 1


@jit
def _heap_pop(keys, vals, size):
    val = vals[0]
    size -= 1
    keys[0] = keys[size]
    vals[0] = vals[size]
    i = 0
    while True:
        a = 2 * i + 1
        b = a + 1
        j = i
        if a < size and keys[a] > keys[j]:
            j = a
        if b < size and keys[b] > keys[j]:
            j = b
        if j == i:
            break
        keys[j], keys[i] = keys[i], keys[j]
        vals[j], vals[i] = vals[i], vals[j]
        i = j
    return val, size


@jit
def _select_budget(boxes, err, kids_ok, ntri, planes, eye, k_px, tau, budget, lvl, tx, ty, off, nx, ny):
    """Refine the largest screen error first until the next split would exceed ``budget`` triangles."""
    n = boxes.shape[0]
    state = np.zeros(n, np.int8)
    order = np.empty(n, np.int64)
    m = 0
    keys = np.empty(n, np.float64)
    vals = np.empty(n, np.int64)
    size = 0
    kids = np.empty(4, np.int64)
    c = _classify(0, boxes, err, kids_ok, planes, eye, k_px, tau)
    state[0] = 2 if c == _CULL else 1
    order[m] = 0
    m += 1
    total = 0 if c == _CULL else ntri[0]
    if c == _REFINE:
        size = _heap_push(keys, vals, size, err[0] * k_px / _box_distance(boxes[0], eye), 0)
    while size > 0:
        s, size = _heap_pop(keys, vals, size)
        nk = _children(s, lvl, tx, ty, off, nx, ny, kids)
        add = 0
        for i in range(nk):
            if _box_visible(boxes[kids[i]], planes):
                add += ntri[kids[i]]
        if total - ntri[s] + add > budget:
            break
        total += add - ntri[s]
        state[s] = 0
        for i in range(nk):
            q = kids[i]
            cq = _classify(q, boxes, err, kids_ok, planes, eye, k_px, tau)
            state[q] = 2 if cq == _CULL else 1
            order[m] = q
            m += 1
            if cq == _REFINE:
                size = _heap_push(keys, vals, size, err[q] * k_px / _box_distance(boxes[q], eye), q)
    cnt = 0
    for i in range(m):
        if state[order[i]] != 0:
            cnt += 1
    leaves = np.empty(cnt, np.int64)
    states = np.empty(cnt, np.int8)
    j = 0
    for i in range(m):
        s = order[i]
        if state[s] != 0:
            leaves[j] = s
            states[j] = state[s]
            j += 1
    return leaves, states


@jit
def _fallback(leaves, states, boxes, meas, eye, k_px, tau, lvl, tx, ty, off, nx, ny, work, checked, stamp):
    """Sung, Lee & Shin (2021) parent fallback, bottom-up: a parent whose existing children are all visible leaves, whose own
    measured error projects within ``tau`` and is no worse than its worst child's, is drawn instead of them.
    Returns (leaves, states, fallback flags)."""
    n0 = leaves.shape[0]
    cur = np.empty(2 * n0 + 1, np.int64)
    for i in range(n0):
        cur[i] = leaves[i]
        work[leaves[i]] = states[i]
    m = n0
    fb = np.zeros(2 * n0 + 1, np.bool_)
    kids = np.empty(4, np.int64)
    top = off.shape[0] - 1
    for k in range(top, 0, -1):
        for i in range(m):
            s = cur[i]
            if work[s] != 1 or lvl[s] != k:
                continue
            p = _parent(s, lvl, tx, ty, off, nx, ny)
            if checked[p] == stamp:
                continue
            checked[p] = stamp
            nk = _children(p, lvl, tx, ty, off, nx, ny, kids)
            ok = True
            worst = 0.0
            for j in range(nk):
                if work[kids[j]] != 1:
                    ok = False
                    break
                worst = max(worst, meas[kids[j]])
            if not ok or worst < meas[p]:
                continue
            if meas[p] * k_px / _box_distance(boxes[p], eye) > tau:
                continue
            for j in range(nk):
                work[kids[j]] = 0
            work[p] = 1
            cur[m] = p
            fb[m] = True
            m += 1
    cnt = 0
    for i in range(m):
        if work[cur[i]] != 0:
            cnt += 1
    out = np.empty(cnt, np.int64)
    ost = np.empty(cnt, np.int8)
    ofb = np.empty(cnt, np.bool_)
    j = 0
    for i in range(m):
        s = cur[i]
        if work[s] != 0:
            out[j] = s
            ost[j] = work[s]
            ofb[j] = fb[i]
            j += 1
            work[s] = 0
    for i in range(m):
        work[cur[i]] = 0
    return out, ost, ofb


@jit
def _wanted_errors(cand, boxes, err, planes, eye, k_px, tau):
    """Projected error (px) of each tile in ``cand`` where it is visible and over ``tau``, else 0."""
    out = np.zeros(cand.shape[0], np.float64)
    for i in range(cand.shape[0]):
        s = cand[i]
        if _box_visible(boxes[s], planes):
            rho = err[s] * k_px / _box_distance(boxes[s], eye)
            if rho > tau:
                out[i] = rho
    return out


@jit
def _ancestors(leaves, n, lvl, tx, ty, off, nx, ny):
    """Mask over the ``n`` slots of every proper ancestor of ``leaves`` (the tiles a selection split)."""
    out = np.zeros(n, np.bool_)
    for i in range(leaves.shape[0]):
        p = _parent(leaves[i], lvl, tx, ty, off, nx, ny)
        while p >= 0 and not out[p]:
            out[p] = True
            p = _parent(p, lvl, tx, ty, off, nx, ny)
    return out


@jit
def _screen_errors(leaves, boxes, err, eye, k_px):
    """Projected error (px) of each leaf; ``err`` is aligned with ``leaves``."""
    out = np.empty(leaves.shape[0], np.float64)
    for i in range(leaves.shape[0]):
        s = leaves[i]
        e = err[i]
        out[i] = 0.0 if e <= 0.0 else e * k_px / _box_distance(boxes[s], eye)
    return out


# -- results -------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class FrameStats:
    """One frame: drawn tiles and triangles, worst projected error of a drawn tile (px), timings (ms:
    selection; adjacency + stitching + normals; decoding tiles not yet cached, kept apart because it is I/O
    that a renderer would prefetch), tiles decoded, and the incremental bookkeeping (culled leaves,
    CrackTileVector size, tiles re-fitted, tiles whose normals were recomputed, parent fallbacks)."""

    tiles: int
    triangles: int
    max_screen_error_px: float
    select_ms: float
    stitch_ms: float
    load_ms: float = 0.0
    loaded: int = 0
    culled: int = 0
    crack_tiles: int = 0
    refitted: int = 0
    normals: int = 0
    fallback: int = 0
    backface_culled: int = 0
    region_culled: int = 0
    levels: dict[int, int] = field(default_factory=dict)
    #: tiles still queued for the loader thread (``Engine(async_loads=True)``; 0 otherwise)
    pending_loads: int = 0

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


class Selection:
    """The result of one :meth:`Engine.update`: the drawn tiles and their stitched meshes (a snapshot).

    Attributes
    ----------
    camera : the camera it was made for
    tiles : list of (level, x, y), the visible leaves, ordered by (level, y, x)
    screen_error_px : (len(tiles),) float64 projected error of each drawn tile, pixels
    fallback : set of codes drawn by parent fallback (their error is their own measured error)
    culled : list of codes of culled leaves (part of the partition, not drawn)
    stats : :class:`FrameStats`
    """

    def __init__(
        self,
        camera: Camera,
        tiles: list[TileCode],
        screen_error_px: np.ndarray,
        fallback: set[TileCode],
        culled: list[TileCode],
        meshes: list[tuple[TileCode, np.ndarray, np.ndarray, np.ndarray]],
        stats: FrameStats,
    ) -> None:
        self.camera = camera
        self.tiles = tiles
        self.screen_error_px = screen_error_px
        self.fallback = fallback
        self.culled = culled
        self._meshes = meshes
        self.stats = stats

    def __len__(self) -> int:
        return len(self.tiles)

    def meshes(self) -> Iterator[tuple[TileCode, np.ndarray, np.ndarray, np.ndarray]]:
        """Yield (code, vertices (N, 3) float64 world metres, triangles (K, 3) uint32 CCW from above,
        normals (N, 3) float32 unit) of every drawn tile, stitched. Arrays are read-only."""
        yield from self._meshes

    def mesh_dict(self) -> dict[TileCode, tuple[np.ndarray, np.ndarray, np.ndarray]]:
        return {c: (v, t, n) for c, v, t, n in self._meshes}


# -- the engine ----------------------------------------------------------------------------------------
class Engine:
    """Runtime LOD engine over a tile store: ``engine.update(camera)`` → :class:`Selection`.

    Parameters
    ----------
    store : an open :class:`terralod.store.TileStore` (or any :class:`.stitch.TileSource`)
    threshold_px : refine while the projected error exceeds this many pixels (default 2)
    triangle_budget : optional cap on drawn triangles (refine the largest error first until the cap)
    background : run selection on a worker thread: ``request(camera)`` then ``latest()``
    incremental : start each frame from the last leaf list (Sung, Lee & Shin's (2021) quadtree parser); False = from root
    stitch_mode : "incremental" (CrackTileVector, Li, Liu & Liu) or "full" (re-stitch every tile each frame,
        the conventional baseline of Li, Liu & Liu table 3)
    cache_tiles, cache_bytes : bounds of the decoded-tile LRU cache (a prepared 65² tile takes ~0.45 MB); the
        tiles of the current view (drawn leaves, plus 25 % for neighbours) are kept even beyond them
    cull_backfacing : Hu & Wang §3.2: do not draw a leaf whose every (stitched) triangle faces away from
        the eye. Exact per triangle, stopping at the first front-facing one.
    cull_region : Hu & Wang §3.1: do not draw a leaf whose footprint misses the visible region, the view
        frustum cut by the terrain's mean horizontal plane (the store's mean elevation). Approximate by
        design: a peak rising above that plane from outside the region is dropped although the 3-D
        frustum test (always on) would keep it; it exists to compare with the paper.

    async_loads : read and decode tiles on a worker thread, never on the frame path
        (:mod:`terralod.runtime.loader`): a tile is refined only once all its children are decoded, the
        resident tiles are drawn meanwhile, and the frame reports ``pending_loads``; when the loads settle
        the selection is the synchronous one. ``wait_loads()`` blocks until they have.
    max_new_tiles : with ``async_loads``, the most tiles one frame refines into that its last frame did
        not split towards: newly decoded ones, or ones cached from an earlier view after a jump (whole
        sibling groups, largest projected error first; at least one group). This bounds a frame's stitching
        work.

    Culling only removes leaves from drawing: the partition, adjacency and stitching are unchanged, so
    the drawn surface stays watertight wherever two drawn tiles meet.
    """

    def __init__(
        self,
        store: TileSource,
        threshold_px: float = 2.0,
        triangle_budget: int | None = None,
        *,
        background: bool = False,
        incremental: bool = True,
        stitch_mode: str = "incremental",
        cache_tiles: int = 1024,
        cache_bytes: int = 256 << 20,
        cull_backfacing: bool = False,
        cull_region: bool = False,
        async_loads: bool = False,
        max_new_tiles: int = 16,
    ) -> None:
        if not (isinstance(threshold_px, (int, float)) and threshold_px > 0 and math.isfinite(threshold_px)):
            raise ValueError(f"Expected threshold_px > 0, got {threshold_px!r}")
        if triangle_budget is not None and int(triangle_budget) < 1:
            raise ValueError(f"Expected triangle_budget >= 1 or None, got {triangle_budget!r}")
        if stitch_mode not in ("incremental", "full"):
            raise ValueError(f"Expected stitch_mode 'incremental' or 'full', got {stitch_mode!r}")
        self.store = store
        self.threshold_px = float(threshold_px)
        self.triangle_budget = None if triangle_budget is None else int(triangle_budget)
        self.incremental = bool(incremental)
        self.stitch_mode = stitch_mode
        self.cull_backfacing = bool(cull_backfacing)
        self.cull_region = bool(cull_region)
        self.index = QuadIndex(store.pyramid)
        self.table = TileTable(store, self.index)
        if not self.table.avail[0]:
            from terralod.errors import CorruptStoreError

            raise CorruptStoreError(
                "has no root tile (0, 0, 0); `terralod check --repair` then `terralod build SOURCE -o STORE "
                "--resume` rebuilds what is missing",
                str(getattr(store, "path", store)),
            )
        self.adjacency = Adjacency(self.index)
        self.cache = TileCache(store, max_tiles=cache_tiles, max_bytes=cache_bytes)
        self.stitcher = Stitcher(self.index, self.adjacency, self.cache)
        # resident (decoded) tiles, for asynchronous loads: selection refines only into them
        self.async_loads = bool(async_loads)
        self._resident = np.zeros(self.index.n, bool)
        self._refined = np.zeros(self.index.n, bool)  # tiles the last frame refined (split into children)
        self._n_kids = np.zeros(self.index.n, np.int64)  # children in the store, per tile
        self._waiting_groups = 0  # wanted sibling groups the last frame's stitch budget left out
        self.max_new_tiles = int(max_new_tiles)
        self._generation = 0  # bumped by every finished asynchronous load
        self._gen_lock = threading.Lock()
        self._last_generation = -1
        self._loader: TileLoader | None = None
        if self.async_loads:
            self.cache.on_put = self._on_put
            self.cache.on_evict = self._on_evict
            self._levels = self._level_parents()
            for off, _, _, n_kids in self._levels:
                self._n_kids[off : off + n_kids.size] = n_kids
            self.cache.load([(0, 0, 0)])  # the root, before the first frame
            self._loader = TileLoader(self.cache, self.cache.io_lock, self._on_loaded)
        n = self.index.n
        self._memo = np.zeros(n, np.int64)
        self._memo_val = np.zeros(n, np.int8)
        self._emitted = np.zeros(n, np.int64)
        self._work = np.zeros(n, np.int8)
        self._checked = np.zeros(n, np.int64)
        self._stamp = 0
        self._stage1: np.ndarray | None = None
        self._last: Selection | None = None
        self._last_key: tuple | None = None
        self._meshes: list[tuple[TileCode, np.ndarray, np.ndarray, np.ndarray]] = []
        self._lock = threading.RLock()
        # background mode
        self.background = bool(background)
        self._cv = threading.Condition()
        self._pending: Camera | None = None
        self._busy = False
        self._closed = False
        self._error: BaseException | None = None
        self._latest: Selection | None = None
        self._thread: threading.Thread | None = None
        if self.background:
            self._thread = threading.Thread(target=self._run, name="terralod-select", daemon=True)
            self._thread.start()

    # -- asynchronous loads ----------------------------------------------------------------------------
    def _level_parents(self) -> list[tuple[int, np.ndarray, np.ndarray, np.ndarray]]:
        """Per level >= 1: (parent slot offset, child slots, their parent slots, children per parent)."""
        ix = self.index
        out = []
        for lev in range(1, ix.max_level + 1):
            ch = np.arange(ix.off[lev], ix.off[lev] + ix.nx[lev] * ix.ny[lev])
            ch = ch[self.table.avail[ch]]
            par = ix.off[lev - 1] + (ix.ty[ch] >> 1) * ix.nx[lev - 1] + (ix.tx[ch] >> 1)
            m = ix.nx[lev - 1] * ix.ny[lev - 1]
            out.append((int(ix.off[lev - 1]), ch, par, np.bincount(par - ix.off[lev - 1], minlength=m)))
        return out

    def _kids_resident(self, planes: np.ndarray, eye: np.ndarray, k_px: float) -> np.ndarray:
        """``kids_ok`` restricted to what this frame may refine into without a read and within its stitch
        budget. A tile refines only once all its children are decoded. Refining a tile that the last frame
        refined too is free (its children were in that frame's cut); every other refinement adds a whole
        sibling group of tiles not drawn before (a newly decoded group, or one cached from an earlier view
        after a jump) and is charged against ``max_new_tiles``: the groups this camera wants (visible,
        projected error over the threshold), largest projected error first (a parent before its
        children: errors and boxes nest), at least one group. So no frame stitches more than a bounded
        number of tiles its last frame did not draw; the rest wait for the next frames."""
        kids = self.table.kids_ok.copy()
        res = self._resident
        for off, ch, par, n_kids in self._levels:
            n_res = np.bincount(par[res[ch]] - off, minlength=n_kids.size)
            kids[off : off + n_kids.size] &= n_res == n_kids  # every child decoded
        cand = np.flatnonzero(kids & ~self._refined)
        self._waiting_groups = 0
        if cand.size:
            rho = _wanted_errors(
                cand, self.table.boxes, self.table.error_m, planes, eye, k_px, self.threshold_px
            )
            want = rho > 0.0
            kids[cand[~want]] = False  # would not refine this frame anyway
            cand, rho = cand[want], rho[want]
            order = np.argsort(-rho, kind="stable")
            cost = np.cumsum(self._n_kids[cand[order]])
            admit = cost <= self.max_new_tiles
            admit[:1] = True
            kids[cand[order[~admit]]] = False
            self._waiting_groups = int((~admit).sum())
        return kids

    def _on_put(self, code: TileCode) -> None:
        self._resident[self.index.slot(code)] = True

    def _on_evict(self, code: TileCode) -> None:
        self._resident[self.index.slot(code)] = False

    def _on_loaded(self, codes: list[TileCode]) -> None:
        with self._gen_lock:
            self._generation += 1

    def wait_loads(self, timeout: float | None = None) -> bool:
        """Block until the asynchronous loads asked for so far are done; True when idle (or synchronous)."""
        return True if self._loader is None else self._loader.wait(timeout)

    @property
    def pending_loads(self) -> int:
        """Tiles queued or being read by the loader thread (0 for synchronous loads)."""
        return 0 if self._loader is None else self._loader.pending

    def _request_children(self, vis: np.ndarray, rho: np.ndarray, kids: np.ndarray) -> int:
        """Ask the loader for the children of drawn tiles that would refine if their children were decoded,
        largest projected error first."""
        assert self._loader is not None
        if self._loader.error is not None:
            raise RuntimeError("terralod: tile loading failed") from self._loader.error
        want = (rho > self.threshold_px) & self.table.kids_ok[vis] & ~kids[vis]
        if not want.any():
            return self._loader.pending
        codes: list[TileCode] = []
        prio: list[float] = []
        for s, r in zip(vis[want].tolist(), rho[want].tolist(), strict=True):
            for c in self.index.pyramid.children(self.index.code(s)):
                codes.append(c)
                prio.append(r)
        return self._loader.request(codes, prio)

    # -- synchronous -----------------------------------------------------------------------------------
    def update(self, camera: Camera) -> Selection:
        """Select, stitch and light the tiles for ``camera``; returns the frame's :class:`Selection`."""
        if not isinstance(camera, Camera):
            raise TypeError(f"Expected a terralod.runtime.Camera, got {type(camera).__name__}")
        with self._lock:
            if (self._last is not None and camera.key == self._last_key
                    and self._generation == self._last_generation):  # fmt: skip
                return self._last  # camera still: no traversal at all (Sung, Lee & Shin's (2021) parser)
            if self._loader is None:
                return self._update(camera)
            self._loader.frame_idle.clear()  # the loader pauses between tiles while this frame runs
            try:
                return self._update(camera)
            finally:
                self._loader.frame_idle.set()

    def _update(self, camera: Camera) -> Selection:
        t0 = time.perf_counter()
        tb = self.table
        ia = self.index.arrays
        planes = camera._planes
        eye = camera.eye_array
        k_px = camera.screen_factor_px
        tau = self.threshold_px
        generation = self._generation
        kids_ok = self._kids_resident(planes, eye, k_px) if self.async_loads else tb.kids_ok
        if self.triangle_budget is not None:
            leaves, states = _select_budget(
                tb.boxes,
                tb.error_m,
                kids_ok,
                tb.triangles,
                planes,
                eye,
                k_px,
                tau,
                self.triangle_budget,
                *ia,
            )
        elif self.incremental and self._stage1 is not None:
            self._stamp += 1
            leaves, states = _select_incremental(
                self._stage1, tb.boxes, tb.error_m, kids_ok, planes, eye, k_px, tau, *ia,
                self._memo, self._memo_val, self._emitted, self._stamp,
            )  # fmt: skip
        else:
            leaves, states = _select_full(tb.boxes, tb.error_m, kids_ok, planes, eye, k_px, tau, *ia)
        order = np.argsort(leaves, kind="stable")
        leaves, states = leaves[order], states[order]
        self._stage1 = leaves
        if self.async_loads:  # a tile the fallback draws instead of its children counts as refined
            self._refined = _ancestors(leaves, self.index.n, *ia)
        self._stamp += 1
        leaves, states, fb = _fallback(
            leaves,
            states,
            tb.boxes,
            tb.measured_error_m,
            eye,
            k_px,
            tau,
            *ia,
            self._work,
            self._checked,
            self._stamp,
        )
        order = np.argsort(leaves, kind="stable")
        leaves, states, fb = leaves[order], states[order], fb[order]
        t1 = time.perf_counter()

        crack = self.adjacency.update(leaves, states)
        # keep the working set decoded: drawn leaves plus a margin for the neighbours stitching reads
        self.cache.floor_tiles = int(1.25 * int((states == VISIBLE).sum())) + 16
        tl = time.perf_counter()
        loaded = self.stitcher.load(leaves[states == VISIBLE] if self.stitch_mode == "full" else crack)
        tl = time.perf_counter() - tl
        sst = self.stitcher.update(crack, full=self.stitch_mode == "full")
        vis_mask = states == VISIBLE
        vis = leaves[vis_mask]
        codes = self.index.codes(vis)
        if sst.crack_tiles or self.adjacency.changed.size or len(self._meshes) != len(vis):
            meshes = []
            for code, s in zip(codes, vis.tolist(), strict=True):
                v, t, nrm = self.stitcher.mesh(s)
                meshes.append((code, v, t, nrm))
            self._meshes = meshes
        t2 = time.perf_counter()

        errs = np.where(fb[vis_mask], tb.measured_error_m[vis], tb.error_m[vis])
        rho = _screen_errors(vis, tb.boxes, errs, eye, k_px)
        pending = 0
        if self.async_loads:
            pending = self._request_children(vis, rho, kids_ok) + self._waiting_groups
            if self._waiting_groups:
                with self._gen_lock:  # decoded tiles still to admit: the same camera selects again
                    self._generation += 1
        meshes = self._meshes
        culled_codes = self.index.codes(leaves[states == CULLED])
        n_back = n_region = 0
        if self.cull_backfacing or self.cull_region:
            drawn = self._cull(camera, vis)
            n_region = int((drawn == 1).sum())
            n_back = int((drawn == 2).sum())
            keep = drawn == 0
            culled_codes += [c for c, k in zip(codes, keep.tolist(), strict=True) if not k]
            codes = [c for c, k in zip(codes, keep.tolist(), strict=True) if k]
            meshes = [m for m, k in zip(meshes, keep.tolist(), strict=True) if k]
            vis, rho = vis[keep], rho[keep]
            t2 = time.perf_counter()
        lv = self.index.lvl[vis]
        stats = FrameStats(
            tiles=len(codes),
            triangles=int(sum(len(m[2]) for m in meshes)),
            max_screen_error_px=float(rho.max()) if rho.size else 0.0,
            select_ms=(t1 - t0) * 1e3,
            stitch_ms=(t2 - t1 - tl) * 1e3,
            load_ms=tl * 1e3,
            loaded=loaded,
            culled=int((states == CULLED).sum()),
            crack_tiles=sst.crack_tiles,
            refitted=sst.refitted,
            normals=sst.normals,
            fallback=int(fb.sum()),
            backface_culled=n_back,
            region_culled=n_region,
            levels={int(k): int(c) for k, c in zip(*np.unique(lv, return_counts=True), strict=True)},
            pending_loads=pending,
        )
        sel = Selection(
            camera, codes, rho, set(self.index.codes(leaves[fb])), culled_codes, meshes, stats,
        )  # fmt: skip
        self._last, self._last_key, self._last_generation = sel, camera.key, generation
        log.debug("frame: %s", stats)
        return sel

    def _cull(self, camera: Camera, vis: np.ndarray) -> np.ndarray:
        """Per visible leaf: 0 drawn, 1 outside the visible region (§3.1), 2 back-facing (§3.2)."""
        from terralod.fractal import boxes_in_region, visible_region
        from terralod.kernels.cull import any_front_facing

        out = np.zeros(vis.size, np.int8)
        if self.cull_region and vis.size:
            boxes = self.table.boxes
            if not hasattr(self, "_mean_z_m"):
                lv0 = self.index.lvl == 0
                self._mean_z_m = float(0.5 * (boxes[lv0, 2].min() + boxes[lv0, 5].max()))
            far = camera.far_m
            if far is None:  # reach past every tile
                d = np.linalg.norm(0.5 * (boxes[vis, :3] + boxes[vis, 3:]) - camera.eye_array, axis=1)
                far = float(d.max() + np.linalg.norm(boxes[0, 3:] - boxes[0, :3])) + 1.0
            poly = visible_region(
                camera.eye, camera.target, far_m=far, up=camera.up, fov_y_deg=camera.fov_y_deg,
                aspect=camera.aspect, near_m=camera.near_m, plane_z_m=self._mean_z_m,
            )  # fmt: skip
            out[~boxes_in_region(boxes[vis], poly)] = 1
        if self.cull_backfacing:
            ex, ey, ez = camera.eye
            for i, (_, v, t, _) in enumerate(self._meshes):
                if out[i] == 0 and not any_front_facing(v, t, ex, ey, ez):
                    out[i] = 2
        return out

    # -- background ------------------------------------------------------------------------------------
    def request(self, camera: Camera) -> None:
        """Ask the worker thread for a selection for ``camera`` (replaces any request not yet started)."""
        if not self.background:
            raise RuntimeError("Expected an Engine(..., background=True) for request(); use update()")
        if not isinstance(camera, Camera):
            raise TypeError(f"Expected a terralod.runtime.Camera, got {type(camera).__name__}")
        with self._cv:
            if self._closed:
                raise RuntimeError("engine is closed")
            self._pending = camera
            self._cv.notify_all()

    def latest(self) -> Selection | None:
        """The most recent finished selection (never waits); None before the first one."""
        if self._error is not None:
            raise RuntimeError("terralod: background selection failed") from self._error
        return self._latest

    def wait(self, timeout: float | None = None) -> Selection | None:
        """Block until no request is pending or running (or ``timeout`` seconds); returns :meth:`latest`."""
        with self._cv:
            self._cv.wait_for(lambda: (self._pending is None and not self._busy) or self._closed, timeout)
        return self.latest()

    def _run(self) -> None:
        while True:
            with self._cv:
                self._cv.wait_for(lambda: self._pending is not None or self._closed)
                if self._closed:
                    return
                cam, self._pending = self._pending, None
                self._busy = True
            try:
                assert cam is not None
                self._latest = self.update(cam)
            except BaseException as exc:  # surfaced by latest()/wait()
                self._error = exc
            finally:
                with self._cv:
                    self._busy = False
                    self._cv.notify_all()

    def close(self) -> None:
        """Stop the worker threads (background selection, asynchronous loads); the engine can still
        ``update()`` synchronously."""
        if self._loader is not None:
            self._loader.close()
            self._loader = None
            self.async_loads = False
        with self._cv:
            self._closed = True
            self._cv.notify_all()
        if self._thread is not None:
            self._thread.join(timeout=10.0)
            self._thread = None

    def __enter__(self) -> Engine:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
