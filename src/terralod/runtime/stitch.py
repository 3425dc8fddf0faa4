"""Crack-free stitching of selected tiles for any LoD difference, edges and corners, incrementally.

Implements ``../shared/papers/002_037d1654b87e3b6a.txt`` §3.3 (elevation adjustment without LoD-difference
constraints) on the adjacency of :mod:`terralod.runtime.adjacency`, with the normals of §3.4
(:mod:`terralod.runtime.normals`).

The rule, for every boundary vertex of every visible leaf: its height is the surface of the *coarsest*
visible leaf whose square contains that position — interpolated linearly along that leaf's boundary edge
polyline, using its actual stored boundary vertices (fractional, relocated ones included). Tiles are
processed coarsest first, so the polyline a finer tile reads is already final. Per side: when the leaf
across is coarser (by any n >= 1; its edge spans 2^n of ours), every vertex of our side moves onto its
polyline; per corner: the coarsest of the (up to three) other leaves around the corner point decides.
Same-level neighbours share identical boundary vertices, so they agree without any work.

After adjustment the fine side's vertices lie *on* the coarse side's straight segments: T-junctions that
are geometrically closed but leave single-pixel holes when rasterised (the rendered magenta test saw them).
So the coarse tile takes the finer visible neighbours' boundary positions as vertices of its own (heights
from its own polyline, so its surface does not change; its boundary triangles are fan-split at them): both
sides then share bit-identical vertices and no T-junction remains. When boundary vertices were relocated (cohesion maps) a coarse vertex may fall
strictly inside a fine segment; the fine boundary triangle is then fan-split at it, so the fine edge follows
every bend of the coarse edge and the seam stays closed (the paper's grids never need this).

Incremental work (the paper's CrackTileVector): only tiles with an active Dirty flag are looked at; each
keeps its stitched result with a *neighbourhood signature* (the coarser leaves its sides were fitted to and
the final heights its corners took); a tile whose signature did not change is not touched; a tile whose
corner heights changed re-queues its finer neighbours (who read its polyline). The "full traversal"
baseline of table 3 recomputes every visible tile every frame. This module gathers each tile's
neighbourhood (the coarser polylines, the corner heights, the finer neighbours' boundary positions) and its
signature; the geometry of one tile is one kernel call (:func:`terralod.kernels.stitch.stitch_tile`: fit,
insertions, the normal-sum patch and the edge tables neighbours read, with one copy of the vertices and
one of the triangles).

Deviations (and why): the paper takes the finer tile as reference for same-level neighbours and copies its
heights to the neighbour; our same-level tiles are identical by construction (the builder shares boundary
vertices), so nothing is copied. The paper interpolates on the coarse grid cells; we interpolate on the
coarse tile's actual boundary polyline, which also covers relocated and partial (data-edge) tiles.
Culled leaves are treated as absent: a visible tile is never bent to fit a tile nobody sees.
"""

from __future__ import annotations

import math
import threading
from collections import OrderedDict
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from terralod.kernels.stitch import border_segments as _k_border_segments
from terralod.kernels.stitch import (
    line_pair_gaps,
    normal_sums,
    normalize_all,
    polyline_at,
    stitch_tile,
    tile_edges,
)
from terralod.runtime.adjacency import CULLED, OPPOSITE, VISIBLE, Adjacency, QuadIndex
from terralod.runtime.normals import boundary_normals, edge_tables
from terralod.tiles import TileCode, TilePyramid

__all__ = [
    "CrackReport",
    "StitchedTile",
    "Stitcher",
    "TileCache",
    "TilePrep",
    "TileSource",
    "find_cracks",
    "stitch_leaves",
]

#: Positions (source samples) closer than this are the same point along an edge.
POS_TOL = 1e-7
#: Corner c (LU, RU, RD, LD) lies on sides (e1, e2) at their (low, high) ends: (side, end) pairs; end 0 = first.
_CORNER_SIDES = (((0, 0), (1, 0)), ((1, -1), (2, 0)), ((2, -1), (3, -1)), ((3, 0), (0, -1)))


class TileSource(Protocol):
    """What the runtime needs from a store (a :class:`terralod.store.TileStore` is one)."""

    pyramid: TilePyramid
    transform: Any

    def tile(self, level: int, x: int, y: int) -> Any: ...

    def tile_summaries(self) -> list[dict[str, Any]]: ...


# -- per-tile preparation (cached) ---------------------------------------------------------------------
@dataclass(eq=False)
class TilePrep:
    """A decoded tile with the boundary bookkeeping the stitcher needs (computed once, cached).

    Attributes
    ----------
    code : (level, x, y); vertices (N, 3) float64 world metres; triangles (K, 3) uint32 CCW from above
    r0, c0, r1, c1 : the tile square in source samples (north row, west col, south row, east col)
    edge_vid[e], edge_t[e] : vertices on side e (L, U, R, D) ascending along it; t = row (L/R) or col (U/D)
    seg_tri[e], seg_rot[e] : per boundary segment (j, j + 1) the triangle holding it and the corner of that
        triangle where it starts (-1 where no triangle holds it)
    corner_vid : vertex at corner LU, RU, RD, LD, or -1 (partial tiles at the data edge)
    boundary_triangles, boundary_touched : triangles touching the boundary and their vertices
    base_sums, base_normals : own-triangle normal sums (float64) and normals (float32) as stored
    """

    code: TileCode
    vertices: np.ndarray
    triangles: np.ndarray
    grid_rc: np.ndarray
    r0: float
    c0: float
    r1: float
    c1: float
    edge_vid: list[np.ndarray]
    edge_t: list[np.ndarray]
    seg_tri: list[np.ndarray]
    seg_rot: list[np.ndarray]
    corner_vid: tuple[int, int, int, int]
    boundary_triangles: np.ndarray
    boundary_touched: np.ndarray
    base_sums: np.ndarray
    base_normals: np.ndarray
    base_S: list[np.ndarray] = field(default_factory=list)
    base_G: list[np.ndarray] = field(default_factory=list)
    #: the sides' vertex ids, positions and segment triangles concatenated side after side with their
    #: offsets (ev, et, eoff, seg, segoff) and the corner ids as an array: what the stitch kernel reads
    packed: tuple = ()
    #: as stored: the sorted boundary vertex ids, each side's rows in them and each side's heights
    base_bvid: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    base_rows: list[np.ndarray] = field(default_factory=list)
    base_h: list[np.ndarray] = field(default_factory=list)

    @property
    def nbytes(self) -> int:
        arrays = [self.vertices, self.triangles, self.grid_rc, self.base_sums, self.base_normals]
        arrays += self.edge_vid + self.edge_t + self.seg_tri + self.base_S + self.base_G
        arrays += list(self.packed) + [self.base_bvid] + self.base_rows + self.base_h
        return int(sum(a.nbytes for a in arrays))

    def corner_rc(self, c: int) -> tuple[float, float]:
        """(row, col) of corner c (0..3 = LU, RU, RD, LD)."""
        return ((self.r0, self.c0), (self.r0, self.c1), (self.r1, self.c1), (self.r1, self.c0))[c]

    def side_of(self, row: float, col: float) -> tuple[int, float]:
        """(side, t) of a point on this tile's square (a corner reports a side whose polyline has it)."""
        for e, (line, coord, t) in enumerate(
            ((self.c0, col, row), (self.r0, row, col), (self.c1, col, row), (self.r1, row, col))
        ):
            if abs(coord - line) <= POS_TOL and self.edge_t[e].size:
                return e, t
        return -1, math.nan

    @classmethod
    def from_tile(cls, tile: Any, pyramid: TilePyramid) -> TilePrep:
        code = tuple(int(a) for a in tile.code)
        v = np.ascontiguousarray(tile.vertices, dtype=np.float64)
        tris = np.ascontiguousarray(tile.triangles, dtype=np.uint32)
        rc = np.asarray(tile.grid_rc, dtype=np.float64)
        r0, c0 = pyramid.origin_rc(code)  # type: ignore[arg-type]
        span = pyramid.span(code[0])
        r1, c1 = r0 + span, c0 + span
        ev, et, eoff, st, sr, soff, cor, btris, touched = tile_edges(
            np.ascontiguousarray(rc), tris, float(r0), float(c0), float(r1), float(c1), POS_TOL
        )
        edge_vid = [ev[eoff[e] : eoff[e + 1]] for e in range(4)]
        edge_t = [et[eoff[e] : eoff[e + 1]] for e in range(4)]
        seg = [(st[soff[e] : soff[e + 1]], sr[soff[e] : soff[e + 1]]) for e in range(4)]
        corners = (int(cor[0]), int(cor[1]), int(cor[2]), int(cor[3]))
        sums = normal_sums(v, tris)
        prep = cls(
            code, v, tris, rc, float(r0), float(c0), float(r1), float(c1), edge_vid, edge_t,
            [s[0] for s in seg], [s[1] for s in seg], corners, btris, touched, sums, normalize_all(sums),
        )  # fmt: skip
        for e in range(4):
            s_tab, g_tab = edge_tables(v, tris, sums, edge_vid[e], prep.seg_tri[e])
            prep.base_S.append(s_tab)
            prep.base_G.append(g_tab)
        prep.packed = (
            np.concatenate(edge_vid),
            np.concatenate(edge_t),
            _offsets(edge_vid),
            np.concatenate(prep.seg_tri),
            _offsets(prep.seg_tri),
            np.array(corners, np.int64),
        )
        prep.base_bvid = np.unique(prep.packed[0])
        prep.base_rows = [np.searchsorted(prep.base_bvid, ev) for ev in edge_vid]
        prep.base_h = [v[ev, 2] for ev in edge_vid]
        for a in [prep.base_bvid, *prep.base_rows, *prep.base_h]:
            a.flags.writeable = False  # shared by every unchanged stitched state of this tile
        for a in (prep.vertices, prep.triangles, prep.base_sums, prep.base_normals):
            a.flags.writeable = False
        return prep


def _offsets(arrays: Sequence[np.ndarray]) -> np.ndarray:
    """(len + 1,) int64 start offsets of ``arrays`` concatenated (the last is the total length)."""
    off = [0]
    for a in arrays:
        off.append(off[-1] + a.shape[0])
    return np.array(off, np.int64)


_NONE = np.zeros(0)


def _pack(arrays: Sequence[np.ndarray | None]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Four optional float64 arrays as (concatenation, offsets (5,), present (4,) bool) for a kernel."""
    parts = [_NONE if a is None else a for a in arrays]
    return np.concatenate(parts), _offsets(parts), np.array([a is not None for a in arrays])


class TileCache:
    """Decoded, prepared tiles, least recently used evicted first (by count and by bytes).

    Parameters
    ----------
    source : a :class:`TileSource` (a TileStore)
    max_tiles : most tiles kept
    max_bytes : most bytes of arrays kept
    """

    def __init__(self, source: TileSource, *, max_tiles: int = 1024, max_bytes: int = 512 << 20) -> None:
        if max_tiles < 1 or max_bytes < 1:
            raise ValueError(f"Expected a positive cache size, got {max_tiles} tiles / {max_bytes} bytes")
        self.source = source
        self.max_tiles = int(max_tiles)
        self.max_bytes = int(max_bytes)
        self._items: OrderedDict[TileCode, TilePrep] = OrderedDict()
        self.nbytes = 0
        self.hits = 0
        self.misses = 0
        #: tiles always kept whatever the byte bound (the engine sets it to its working set, the drawn
        #: tiles and their neighbours, so a view needing more than the bounds never thrashes the cache)
        self.floor_tiles = 0
        #: guards the dict against a loader thread inserting (:class:`terralod.runtime.loader.TileLoader`)
        self.lock = threading.RLock()
        #: serialises reads of the source between the frame thread and a loader thread
        self.io_lock = threading.Lock()
        #: called with a code put in / evicted (the engine keeps its resident-tile mask with them)
        self.on_put: Callable[[TileCode], None] | None = None
        self.on_evict: Callable[[TileCode], None] | None = None

    def __len__(self) -> int:
        return len(self._items)

    def __contains__(self, code: object) -> bool:
        return code in self._items

    def get(self, code: TileCode) -> TilePrep:
        with self.lock:
            p = self._items.get(code)
            if p is not None:
                self.hits += 1
                self._items.move_to_end(code)
                return p
            self.misses += 1
        with self.io_lock:
            tile = self.source.tile(*code)
        return self.put(code, tile)

    def load(self, codes: list[TileCode]) -> int:
        """Decode the tiles of ``codes`` not cached yet; returns how many. A source with a ``tiles(codes)``
        method (e.g. :class:`terralod.runtime.FractalSource`, which generates them on threads) is asked for
        all of them at once."""
        with self.lock:
            missing = [c for c in dict.fromkeys(codes) if c not in self._items]
        if not missing:
            return 0
        self.misses += len(missing)
        many = getattr(self.source, "tiles", None)
        with self.io_lock:
            tiles = many(missing) if many is not None else [self.source.tile(*c) for c in missing]
        for code, t in zip(missing, tiles, strict=True):
            self.put(code, t)
        return len(missing)

    def put(self, code: TileCode, tile: Any) -> TilePrep:
        """Cache the source tile ``tile`` of ``code`` (evicting least recently used ones); its TilePrep."""
        return self.insert(code, TilePrep.from_tile(tile, self.source.pyramid))

    def insert(self, code: TileCode, p: TilePrep) -> TilePrep:
        """Cache a prepared tile (e.g. prepared on a loader thread), evicting least recently used ones."""
        with self.lock:
            old_p = self._items.pop(code, None)
            if old_p is not None:
                self.nbytes -= old_p.nbytes
            self._items[code] = p
            self.nbytes += p.nbytes
            if self.on_put is not None:
                self.on_put(code)
            while len(self._items) > max(1, self.floor_tiles) and (
                len(self._items) > self.max_tiles or self.nbytes > self.max_bytes
            ):
                gone, old = self._items.popitem(last=False)
                self.nbytes -= old.nbytes
                if self.on_evict is not None:
                    self.on_evict(gone)
        return p


# -- stitched tiles ------------------------------------------------------------------------------------
@dataclass(eq=False)
class StitchedTile:
    """The stitched state of one visible tile; arrays are never modified after publication."""

    prep: TilePrep
    signature: tuple
    vertices: np.ndarray
    triangles: np.ndarray
    sums: np.ndarray
    geometry_normals: np.ndarray
    final_t: list[np.ndarray]
    final_vid: list[np.ndarray]
    final_h: list[np.ndarray]
    S: list[np.ndarray]
    G: list[np.ndarray]
    corner_h: tuple[float | None, ...]
    boundary_vid: np.ndarray
    edge_rows: list[np.ndarray]
    normals: np.ndarray | None = None

    @property
    def code(self) -> TileCode:
        return self.prep.code


@dataclass
class StitchStats:
    """One frame of stitching: CrackTileVector size, tiles re-fitted, tiles whose normals were redone."""

    crack_tiles: int = 0
    refitted: int = 0
    normals: int = 0
    propagated: int = 0


class Stitcher:
    """Keeps the stitched meshes of the visible leaves of an :class:`Adjacency` up to date.

    ``update(crack)`` processes the CrackTileVector returned by ``Adjacency.update`` (or, with
    ``full=True``, every visible leaf: the conventional full traversal); ``mesh(slot)`` gives the result.
    """

    def __init__(self, index: QuadIndex, adjacency: Adjacency, cache: TileCache, *, park: int = 128) -> None:
        self.index = index
        self.adj = adjacency
        self.cache = cache
        t = cache.source.transform
        self._x0 = float(t.c + 0.5 * t.a)
        self._y0 = float(t.f + 0.5 * t.e)
        self._dx = float(t.a)
        self._dy = float(t.e)
        self.states: dict[int, StitchedTile] = {}
        self._parked: OrderedDict[int, StitchedTile] = OrderedDict()
        self._park = int(park)

    # -- public ----------------------------------------------------------------------------------------
    def load(self, slots: np.ndarray) -> int:
        """Decode the tiles of ``slots`` not yet cached (I/O, kept apart from stitching); returns how many."""
        return self.cache.load([self.index.code(s) for s in np.asarray(slots, dtype=np.int64).tolist()])

    def update(self, crack: np.ndarray, *, full: bool = False) -> StitchStats:
        """Stitch the tiles of the CrackTileVector ``crack`` (slots, coarsest first) and put them to sleep."""
        adj = self.adj
        lvl = self.index.lvl
        for s in adj.changed.tolist():
            if adj.state[s] != VISIBLE:
                st = self.states.pop(s, None)
                if st is not None:
                    self._parked[s] = st
                    while len(self._parked) > self._park:
                        self._parked.popitem(last=False)
        work = adj.mark_all() if full else np.asarray(crack, dtype=np.int64)
        stats = StitchStats(crack_tiles=int(work.size))
        buckets: list[list[int]] = [[] for _ in range(self.index.max_level + 1)]
        queued = set(work.tolist())
        for s in work.tolist():
            buckets[lvl[s]].append(s)
        refit: list[int] = []
        for k in range(len(buckets)):
            for s in buckets[k]:
                changed_geom, changed_corners = self._fit(s, force=full)
                if changed_geom:
                    refit.append(s)
                if changed_corners:
                    for q in adj.neighbours(s).all().tolist():
                        if adj.state[q] == VISIBLE and lvl[q] > k and q not in queued:
                            queued.add(q)
                            buckets[lvl[q]].append(q)
                            stats.propagated += 1
        stats.refitted = len(refit)
        need = set(queued)
        for s in refit:
            need.update(q for q in adj.neighbours(s).all().tolist() if adj.state[q] == VISIBLE)
        for s in sorted(need):
            self._normals(s)
        stats.normals = len(need)
        adj.sleep(np.fromiter(queued, np.int64, len(queued)))
        return stats

    def mesh(self, slot: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        st = self.states[slot]
        assert st.normals is not None
        return st.vertices, st.triangles, st.normals

    # -- geometry --------------------------------------------------------------------------------------
    def _value_at(self, slot: int, row: float, col: float) -> float:
        """Final height of visible tile ``slot``'s boundary at (row, col), linear along its edge polyline."""
        st = self.states[slot]
        e, t = st.prep.side_of(row, col)
        return float(polyline_at(st.final_t[e], st.final_h[e], np.array([t]))[0])

    def _fit(self, s: int, force: bool) -> tuple[bool, bool]:
        """Re-fit tile ``s`` if its neighbourhood signature changed: (geometry changed, corners changed)."""
        adj = self.adj
        lvl = self.index.lvl
        k = int(lvl[s])
        code = self.index.code(s)
        prep = self.cache.get(code)
        nb = adj.neighbours(s)
        # corners: the coarsest other visible leaf around the corner point decides (Li, Liu & Liu §3.3, corners)
        corner_h: list[float | None] = [None, None, None, None]
        for c in range(4):
            if prep.corner_vid[c] < 0:
                continue
            cand = [nb.corners[c]]
            for e, end in _CORNER_SIDES[c]:
                if nb.edges[e].size:
                    cand.append(int(nb.edges[e][end]))
            best = -1
            for q in cand:
                if q >= 0 and adj.state[q] == VISIBLE and lvl[q] < k and (best < 0 or lvl[q] < lvl[best]):
                    best = q
            if best >= 0:
                corner_h[c] = self._value_at(best, *prep.corner_rc(c))
        # sides: a single coarser visible leaf across a side dictates the whole side (any n >= 1)
        fit_to: list[int] = [-1, -1, -1, -1]
        sig_sides = []
        for e in range(4):
            lst = nb.edges[e]
            if lst.size == 1 and adj.state[lst[0]] == VISIBLE and lvl[lst[0]] < k and prep.edge_vid[e].size:
                q = int(lst[0])
                fit_to[e] = q
                h = self.states[q].final_h[int(OPPOSITE[e])]
                sig_sides.append((q, float(h[0]), float(h[-1])))
            else:
                sig_sides.append(None)
        # T-junctions: the boundary vertices of finer visible leaves across a side become vertices of this
        # tile too (they lie on its edge after stitching), so the rasteriser sees shared vertices only
        fine_t: list[np.ndarray | None] = [None, None, None, None]
        sig_fine = []
        for e in range(4):
            qs = [int(q) for q in nb.edges[e].tolist() if adj.state[q] == VISIBLE and lvl[q] > k]
            if qs and prep.edge_vid[e].size:
                oe = int(OPPOSITE[e])
                fine_t[e] = np.concatenate([self.cache.get(self.index.code(q)).edge_t[oe] for q in qs])
            sig_fine.append(tuple(qs))
        signature = (tuple(sig_sides), tuple(corner_h), tuple(sig_fine))
        old = self.states.get(s)
        if old is None:
            old = self._parked.pop(s, None)
        if old is not None and old.prep is not prep:
            old = None  # evicted and decoded again: rebuild (cheap, and keeps identity checks simple)
        if old is not None and not force and old.signature == signature:
            self.states[s] = old
            return False, False
        new = self._build(prep, signature, fit_to, corner_h, fine_t)
        self.states[s] = new
        corners_changed = old is None or old.corner_h != new.corner_h
        geom_changed = (
            old is None
            or not (old.vertices is new.vertices or np.array_equal(old.vertices, new.vertices))
            or old.triangles.shape != new.triangles.shape
        )
        if old is not None and not geom_changed:
            new.normals = old.normals
        return geom_changed or force, corners_changed

    def _build(
        self, prep: TilePrep, signature: tuple, fit_to: list[int], corner_h: list[float | None],
        fine_t: list[np.ndarray | None] | None = None,
    ) -> StitchedTile:  # fmt: skip
        """Stitch one tile (:func:`terralod.kernels.stitch.stitch_tile` does the work in one call)."""
        polylines = [None if q < 0 else self.states[q] for q in fit_to]
        oe = [int(OPPOSITE[e]) for e in range(4)]
        fit_t, fitoff, fit_on = _pack(
            [None if u is None else u.final_t[oe[e]] for e, u in enumerate(polylines)]
        )
        fit_h = _pack([None if u is None else u.final_h[oe[e]] for e, u in enumerate(polylines)])[0]
        fine, fineoff, fine_on = _pack(fine_t or [None, None, None, None])
        ch = np.array([math.nan if h is None else h for h in corner_h], np.float64)
        c_on = np.array([h is not None for h in corner_h])
        ev, et, eoff, seg0, segoff, cvid = prep.packed
        geo = np.array([self._x0, self._y0, self._dx, self._dy, prep.c0, prep.c1, prep.r0, prep.r1])
        zs = prep.vertices[:, 2]
        final_corners = tuple(
            None if prep.corner_vid[c] < 0 else (corner_h[c] if corner_h[c] is not None else float(zs[prep.corner_vid[c]]))
            for c in range(4)
        )  # fmt: skip
        changed, verts, tris, sums, gnormals, vid, t, h, off, s_all, g_all, goff, bvid, rows = stitch_tile(
            prep.vertices, prep.triangles, prep.base_sums, prep.base_normals, prep.boundary_triangles,
            prep.boundary_touched, ev, et, eoff, seg0, segoff, cvid, fit_t, fit_h, fitoff, fit_on, ch, c_on,
            fine, fineoff, fine_on, geo, POS_TOL,
        )  # fmt: skip
        if not changed:
            return StitchedTile(
                prep, signature, prep.vertices, prep.triangles, prep.base_sums, prep.base_normals,
                prep.edge_t, prep.edge_vid, prep.base_h, prep.base_S, prep.base_G, final_corners,
                prep.base_bvid, prep.base_rows,
            )  # fmt: skip
        if tris.shape[0] == 0:
            tris = prep.triangles
        sides = [slice(off[e], off[e + 1]) for e in range(4)]
        segs = [slice(goff[e], goff[e + 1]) for e in range(4)]
        for a in (verts, tris, sums, gnormals, vid, t, h, s_all, g_all, bvid, rows):
            a.flags.writeable = False
        return StitchedTile(
            prep, signature, verts, tris, sums, gnormals, [t[k] for k in sides], [vid[k] for k in sides],
            [h[k] for k in sides], [s_all[k] for k in sides], [g_all[k] for k in segs], final_corners, bvid,
            [rows[k] for k in sides],
        )  # fmt: skip

    # -- normals ---------------------------------------------------------------------------------------
    def _normals(self, s: int) -> None:
        """Li, Liu & Liu §3.4: boundary normals from this tile's and its visible neighbours' triangles."""
        adj = self.adj
        st = self.states[s]
        nb = adj.neighbours(s)
        contrib = []
        for e in range(4):
            oe = int(OPPOSITE[e])
            for q in nb.edges[e].tolist():
                if adj.state[q] == VISIBLE:
                    u = self.states[q]
                    contrib.append((u.final_t[oe], u.S[oe], u.G[oe], st.final_t[e], st.edge_rows[e]))
        for c in range(4):
            d = nb.corners[c]
            vid = st.prep.corner_vid[c]
            if d < 0 or vid < 0 or adj.state[d] != VISIBLE:
                continue
            if any(nb.edges[e].size and nb.edges[e][end] == d for e, end in _CORNER_SIDES[c]):
                continue  # the leaf across the corner is also across a side: already counted
            u = self.states[d]
            ed, t = u.prep.side_of(*st.prep.corner_rc(c))
            if ed < 0:
                continue
            row = np.searchsorted(st.boundary_vid, np.array([vid]))
            contrib.append((u.final_t[ed], u.S[ed], u.G[ed], np.array([t]), row))
        st.normals = boundary_normals(st.geometry_normals, st.sums, st.boundary_vid, contrib, POS_TOL)
        st.normals.flags.writeable = False


def stitch_leaves(
    source: TileSource, codes: Sequence[TileCode], visible: Sequence[bool] | None = None
) -> dict[TileCode, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Stitch an explicit leaf set (a partition of the pyramid) once.

    Parameters
    ----------
    source : the tile store
    codes : leaf tile codes; together they must cover every finest tile exactly once
    visible : per code, whether it is drawn (default all); invisible leaves are absent for stitching

    Returns
    -------
    {code: (vertices (N, 3) float64 world metres, triangles (K, 3) uint32, normals (N, 3) float32)} of the
    visible leaves.
    """
    index = QuadIndex(source.pyramid)
    slots = index.slots(list(codes))
    vis = np.ones(len(slots), bool) if visible is None else np.asarray(visible, dtype=bool)
    if vis.shape != slots.shape:
        raise ValueError(f"Expected one visibility flag per code ({len(slots)}), got {vis.shape}")
    adj = Adjacency(index)
    overlap, uncovered = adj.check_partition(slots)
    if overlap or uncovered or len(np.unique(slots)) != len(slots):
        raise ValueError(
            f"Expected leaves that partition the pyramid, got {overlap} overlapping and {uncovered} finest "
            "tiles not covered"
        )
    states = np.where(vis, VISIBLE, CULLED).astype(np.int8)
    crack = adj.update(slots, states)
    st = Stitcher(index, adj, TileCache(source, max_tiles=max(1024, len(slots))))
    st.update(crack)
    return {index.code(int(s)): st.mesh(int(s)) for s in slots[vis]}


# -- verification: a geometric crack detector ----------------------------------------------------------
@dataclass
class CrackReport:
    """Result of :func:`find_cracks`.

    ``boundaries[n]`` / ``cracked[n]``: tile pairs sharing a border segment, by LoD difference n, and how
    many of them have a gap; ``corners`` / ``cracked_corners``: pairs touching at a point only;
    ``max_gap_m``: the largest vertical gap found (inf for a hole in a border); ``points``: samples checked.
    """

    boundaries: dict[int, int] = field(default_factory=dict)
    cracked: dict[int, int] = field(default_factory=dict)
    corners: int = 0
    cracked_corners: int = 0
    max_gap_m: float = 0.0
    points: int = 0

    @property
    def total_cracked(self) -> int:
        return sum(self.cracked.values()) + self.cracked_corners


def _border_segments(
    v: np.ndarray, tris: np.ndarray, rows: np.ndarray, cols: np.ndarray, side: int, line: float
) -> np.ndarray:
    """Segments (t_a, z_a, t_b, z_b), t_a <= t_b, of triangle edges lying on one side's line, sorted."""
    coord = cols if side in (0, 2) else rows
    along = rows if side in (0, 2) else cols
    on = np.abs(coord - line) <= 1e-6
    return _k_border_segments(tris, along, on, np.ascontiguousarray(v[:, 2]))


def find_cracks(
    meshes: Mapping[TileCode, tuple[np.ndarray, ...]],
    pyramid: TilePyramid,
    transform: Any,
    *,
    tol_m: float = 1e-4,
    samples: int = 5,
) -> CrackReport:
    """Check that the union of tile meshes is watertight across every tile border.

    For every border segment of every tile (a triangle edge on the tile's square), ``samples`` points along
    it (ends included) are compared with the surface of each tile on the other side of that line — its
    border polyline there, which is where its triangles meet the line. A vertical difference above
    ``tol_m`` metres, or a point inside the other tile's border span that no border segment covers (a
    hole), is a crack. Points outside every other tile (data edge, culled neighbour) are not checked.

    Parameters
    ----------
    meshes : {code: (vertices (N, 3) world metres, triangles (K, 3), ...)}
    pyramid, transform : the store's plan and affine transform
    """
    x0 = transform.c + 0.5 * transform.a
    y0 = transform.f + 0.5 * transform.e
    lines: dict[tuple[int, float], list[tuple[TileCode, int, np.ndarray]]] = {}
    for code, m in meshes.items():
        v = np.asarray(m[0], dtype=np.float64)
        t = np.ascontiguousarray(m[1], dtype=np.int64)
        rows = (v[:, 1] - y0) / transform.e
        cols = (v[:, 0] - x0) / transform.a
        r0, c0 = pyramid.origin_rc(code)
        span = pyramid.span(code[0])
        for side, line in enumerate((c0, r0, c0 + span, r0 + span)):
            segs = _border_segments(v, t, rows, cols, side, float(line))
            if len(segs):
                # key: (orientation, line); sign -1 for L/U (tile lies after the line), +1 for R/D
                lines.setdefault((side % 2, float(line)), []).append((code, -1 if side < 2 else 1, segs))
    rep = CrackReport()
    frac = np.linspace(0.0, 1.0, max(2, samples))
    pairs: dict[tuple[TileCode, TileCode], list[float]] = {}
    code_ids: dict[TileCode, int] = {}
    for items in lines.values():
        segs = np.concatenate([sg for _, _, sg in items])
        start = np.zeros(len(items) + 1, np.int64)
        np.cumsum([len(sg) for _, _, sg in items], out=start[1:])
        lo_t = segs[start[:-1], 0]  # rows sorted: the first starts leftmost
        hi_t = np.maximum.reduceat(segs[:, 2], start[:-1])
        sign = np.array([sg for _, sg, _ in items], np.int64)
        code = np.array([code_ids.setdefault(c, len(code_ids)) for c, _, _ in items], np.int64)
        ia, ib, overlap, gap, n = line_pair_gaps(segs, start, lo_t, hi_t, sign, code, frac, 1e-9)
        rep.points += int(n.sum())
        for a, b, ov, g in zip(ia.tolist(), ib.tolist(), overlap.tolist(), gap.tolist(), strict=True):
            ca, cb = items[a][0], items[b][0]
            rec = pairs.setdefault((min(ca, cb), max(ca, cb)), [0.0, 0.0])
            rec[0] = max(rec[0], ov)
            rec[1] = max(rec[1], g)
    for (ca, cb), (overlap, gap) in pairs.items():
        bad = gap > tol_m
        rep.max_gap_m = max(rep.max_gap_m, gap)
        if overlap > 1e-9:
            n = abs(ca[0] - cb[0])
            rep.boundaries[n] = rep.boundaries.get(n, 0) + 1
            rep.cracked[n] = rep.cracked.get(n, 0) + int(bad)
        else:
            rep.corners += 1
            rep.cracked_corners += int(bad)
    return rep
