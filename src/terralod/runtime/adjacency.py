"""Edge and corner adjacency of the selected leaves, with Dirty flags and the CrackTileVector.

Implements ``../shared/papers/002_037d1654b87e3b6a.txt`` §3.1–3.2: every selected leaf knows its edge
neighbours (LN, UN, RN, DN: one coarser or same-level leaf, or the run of finer leaves along that side, the
paper's ``LYvec``) and its corner neighbours (LUN, RUN, RDN, LDN: the leaf diagonally across each corner);
each of the 8 relations carries a Dirty flag (active / sleeping); after a split or merge only the tiles
whose neighbourhood changed get active flags, and the CrackTileVector is the set of visible leaves with an
active flag — the only tiles the stitcher looks at this frame.

Deviation (and why): the paper keeps explicit neighbour pointers and patches them case by case on split
(§3.2.1) and merge (§3.2.2), recursing into the neighbours' children. We keep the leaves in a dense array
indexed by tile code (the implicit quadtree: 0 = not a leaf, 1 = visible leaf, 2 = culled leaf) and derive a
tile's neighbours from it on demand (same-level tile across the side; its leaf ancestor if it has one —
the coarser case; else descend along the facing side — the paper's recursion to ``LChild1/LChild2``). Split
and merge then become the same operation (the leaves that left and the leaves that arrived), pointers
cannot go stale, and the neighbour lists are recomputed only for the tiles whose flags went active.
Culled leaves are part of the partition (so adjacency is always defined) but a culled neighbour is
"absent" for stitching: its visibility change dirties its neighbours like a split would.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from terralod.kernels import jit
from terralod.tiles import TileCode, TilePyramid

__all__ = [
    "CORNERS",
    "DIRECTIONS",
    "EDGES",
    "Adjacency",
    "QuadIndex",
    "TileNeighbours",
]

#: Edge sides, Li, Liu & Liu's LN, UN, RN, DN (west, north, east, south); index 0..3.
EDGES = ("L", "U", "R", "D")
#: Corners, Li, Liu & Liu's LUN, RUN, RDN, LDN (north-west, north-east, south-east, south-west); index 4..7.
CORNERS = ("LU", "RU", "RD", "LD")
DIRECTIONS = EDGES + CORNERS
#: (dx, dy) of each direction (x east, y south), indexed like DIRECTIONS.
_DXY = np.array([[-1, 0], [0, -1], [1, 0], [0, 1], [-1, -1], [1, -1], [1, 1], [-1, 1]], np.int64)
#: The direction pointing back (L <-> R, U <-> D, LU <-> RD, RU <-> LD).
OPPOSITE = np.array([2, 3, 0, 1, 6, 7, 4, 5], np.int64)

#: Leaf states in the dense array.
NOT_LEAF, VISIBLE, CULLED = 0, 1, 2


class QuadIndex:
    """Dense slot numbering of every tile the pyramid plans: ``slot = off[k] + y * nx[k] + x``.

    Attributes
    ----------
    off, nx, ny : (L + 1,) int64 per level: first slot, tiles east-west, tiles north-south
    lvl : (n,) int64 level of each slot; tx, ty : (n,) int64 tile x (east) and y (south)
    """

    def __init__(self, pyramid: TilePyramid) -> None:
        self.pyramid = pyramid
        levels = pyramid.levels
        nx = np.array([pyramid.grid_count(k)[0] for k in levels], np.int64)
        ny = np.array([pyramid.grid_count(k)[1] for k in levels], np.int64)
        off = np.zeros(len(levels), np.int64)
        off[1:] = np.cumsum(nx * ny)[:-1]
        self.off, self.nx, self.ny = off, nx, ny
        self.n = int((nx * ny).sum())
        self.max_level = pyramid.max_level
        lvl = np.repeat(np.arange(len(levels), dtype=np.int64), nx * ny)
        local = np.arange(self.n, dtype=np.int64) - off[lvl]
        self.lvl = lvl
        self.tx = local % nx[lvl]
        self.ty = local // nx[lvl]

    def slot(self, code: TileCode) -> int:
        k, x, y = code
        if not (0 <= k <= self.max_level and 0 <= x < self.nx[k] and 0 <= y < self.ny[k]):
            raise KeyError(f"Expected a tile of the pyramid, got {code}")
        return int(self.off[k] + y * self.nx[k] + x)

    def slots(self, codes: list[TileCode] | np.ndarray) -> np.ndarray:
        c = np.asarray(codes, dtype=np.int64).reshape(-1, 3)
        k, x, y = c[:, 0], c[:, 1], c[:, 2]
        bad = (k < 0) | (k > self.max_level)
        kk = np.clip(k, 0, self.max_level)
        bad |= (x < 0) | (y < 0) | (x >= self.nx[kk]) | (y >= self.ny[kk])
        if bad.any():
            raise KeyError(f"Expected tiles of the pyramid, got {tuple(c[np.argmax(bad)])}")
        return self.off[kk] + y * self.nx[kk] + x

    def code(self, slot: int) -> TileCode:
        return (int(self.lvl[slot]), int(self.tx[slot]), int(self.ty[slot]))

    def codes(self, slots: np.ndarray) -> list[TileCode]:
        s = np.asarray(slots, dtype=np.int64)
        return list(zip(self.lvl[s].tolist(), self.tx[s].tolist(), self.ty[s].tolist(), strict=True))

    @property
    def arrays(self) -> tuple[np.ndarray, ...]:
        """(lvl, tx, ty, off, nx, ny) for the kernels."""
        return self.lvl, self.tx, self.ty, self.off, self.nx, self.ny


# -- kernels: pure functions of the dense leaf-state array ---------------------------------------------
@jit
def _slot(k, x, y, off, nx, ny):
    if k < 0 or k >= off.shape[0] or x < 0 or y < 0 or x >= nx[k] or y >= ny[k]:
        return -1
    return off[k] + y * nx[k] + x


@jit
def _parent(s, lvl, tx, ty, off, nx, ny):
    k = lvl[s]
    if k == 0:
        return -1
    return _slot(k - 1, tx[s] >> 1, ty[s] >> 1, off, nx, ny)


@jit
def _leaf_ancestor(s, state, lvl, tx, ty, off, nx, ny):
    """The leaf that is ``s`` or an ancestor of it, or -1 (then ``s``'s area is split into finer leaves)."""
    while s >= 0:
        if state[s] != 0:
            return s
        s = _parent(s, lvl, tx, ty, off, nx, ny)
    return -1


@jit
def _edge_neighbours(s, d, state, lvl, tx, ty, off, nx, ny, out, start):
    """Leaves across side d (0..3 = L, U, R, D) of tile slot ``s``, ascending along the side.

    Writes into ``out[start:]`` and returns how many. One leaf when it is coarser or of the same level;
    the run of finer leaves along the facing side otherwise (Li, Liu & Liu §3.3 step 1, ``LYvec``).
    """
    k = lvl[s]
    dx = 0
    dy = 0
    if d == 0:
        dx = -1
    elif d == 1:
        dy = -1
    elif d == 2:
        dx = 1
    else:
        dy = 1
    q = _slot(k, tx[s] + dx, ty[s] + dy, off, nx, ny)
    if q < 0:
        return 0
    a = _leaf_ancestor(q, state, lvl, tx, ty, off, nx, ny)
    if a >= 0:
        out[start] = a
        return 1
    # descend along the side of q that faces s; depth-first, pushing the far child first
    stack = np.empty(4 * (off.shape[0] + 1), np.int64)
    top = 0
    stack[top] = q
    top += 1
    m = 0
    while top > 0:
        top -= 1
        c = stack[top]
        if state[c] != 0:
            out[start + m] = c
            m += 1
            continue
        kc = lvl[c] + 1
        if kc >= off.shape[0]:
            continue
        x2 = 2 * tx[c]
        y2 = 2 * ty[c]
        if d == 0:  # q is west of s: its east column, north first
            c0 = _slot(kc, x2 + 1, y2, off, nx, ny)
            c1 = _slot(kc, x2 + 1, y2 + 1, off, nx, ny)
        elif d == 2:  # q is east: its west column
            c0 = _slot(kc, x2, y2, off, nx, ny)
            c1 = _slot(kc, x2, y2 + 1, off, nx, ny)
        elif d == 1:  # q is north: its south row, west first
            c0 = _slot(kc, x2, y2 + 1, off, nx, ny)
            c1 = _slot(kc, x2 + 1, y2 + 1, off, nx, ny)
        else:  # q is south: its north row
            c0 = _slot(kc, x2, y2, off, nx, ny)
            c1 = _slot(kc, x2 + 1, y2, off, nx, ny)
        if c1 >= 0:
            stack[top] = c1
            top += 1
        if c0 >= 0:
            stack[top] = c0
            top += 1
    return m


@jit
def _corner_neighbour(s, c, state, lvl, tx, ty, off, nx, ny):
    """The leaf diagonally across corner c (0..3 = LU, RU, RD, LD) of tile slot ``s``, or -1."""
    k = lvl[s]
    dx = -1 if (c == 0 or c == 3) else 1
    dy = -1 if (c == 0 or c == 1) else 1
    q = _slot(k, tx[s] + dx, ty[s] + dy, off, nx, ny)
    if q < 0:
        return -1
    a = _leaf_ancestor(q, state, lvl, tx, ty, off, nx, ny)
    if a >= 0:
        return a
    # descend into the child of q nearest the corner (it always exists: it lies towards s)
    while state[q] == 0:
        kc = lvl[q] + 1
        if kc >= off.shape[0]:
            return -1
        cx = 2 * tx[q] + (1 if dx < 0 else 0)
        cy = 2 * ty[q] + (1 if dy < 0 else 0)
        q = _slot(kc, cx, cy, off, nx, ny)
        if q < 0:
            return -1
    return q


@jit
def _tile_adjacency(s, state, lvl, tx, ty, off, nx, ny):
    """All 8 relations of tile ``s``: (flat slots, counts[8]) with edges L, U, R, D then corners."""
    cap = 8 + 4 * (1 << (off.shape[0] - 1 - lvl[s]))
    out = np.empty(cap, np.int64)
    counts = np.zeros(8, np.int64)
    m = 0
    for d in range(4):
        n = _edge_neighbours(s, d, state, lvl, tx, ty, off, nx, ny, out, m)
        counts[d] = n
        m += n
    for c in range(4):
        q = _corner_neighbour(s, c, state, lvl, tx, ty, off, nx, ny)
        if q >= 0:
            out[m] = q
            counts[4 + c] = 1
            m += 1
    return out[:m].copy(), counts


@jit
def _apply_and_mark(old_leaves, new_leaves, new_states, state, dirty, mark, stamp, lvl, tx, ty, off, nx, ny):
    """Swap the leaf set in ``state`` and set the Dirty flags (Li, Liu & Liu §3.2).

    A tile *changed* when it left the leaf set, joined it, or changed visibility. Every changed tile that is
    a visible leaf now gets all 8 flags active; every visible leaf across a side or corner of a changed tile
    gets the flag of the direction facing it active. Returns the changed slots.
    """
    n_new = new_leaves.shape[0]
    for i in range(n_new):
        mark[new_leaves[i]] = stamp
    changed = np.empty(old_leaves.shape[0] + n_new, np.int64)
    m = 0
    for i in range(old_leaves.shape[0]):
        s = old_leaves[i]
        if mark[s] != stamp:
            changed[m] = s
            m += 1
            state[s] = 0
    for i in range(n_new):
        s = new_leaves[i]
        if state[s] != new_states[i]:
            changed[m] = s
            m += 1
            state[s] = new_states[i]
    buf = np.empty(4 * (1 << (off.shape[0] - 1)) + 8, np.int64)
    for i in range(m):
        s = changed[i]
        if state[s] == 1:
            dirty[s] = 255
        for d in range(4):
            cnt = _edge_neighbours(s, d, state, lvl, tx, ty, off, nx, ny, buf, 0)
            for j in range(cnt):
                q = buf[j]
                if state[q] == 1:
                    dirty[q] |= 1 << ((d + 2) % 4)
        for c in range(4):
            q = _corner_neighbour(s, c, state, lvl, tx, ty, off, nx, ny)
            if q >= 0 and state[q] == 1:
                dirty[q] |= 1 << (4 + (c + 2) % 4)
    return changed[:m].copy()


@jit
def _partition_errors(leaves, lvl, tx, ty, off, nx, ny, max_level):
    """Check that ``leaves`` partition the pyramid: (#overlapping leaves, #finest tiles not covered)."""
    n = off[off.shape[0] - 1] + nx[nx.shape[0] - 1] * ny[ny.shape[0] - 1]
    mark = np.zeros(n, np.bool_)
    for i in range(leaves.shape[0]):
        mark[leaves[i]] = True
    overlap = 0
    for i in range(leaves.shape[0]):
        p = _parent(leaves[i], lvl, tx, ty, off, nx, ny)
        while p >= 0:
            if mark[p]:
                overlap += 1
                break
            p = _parent(p, lvl, tx, ty, off, nx, ny)
    uncovered = 0
    k = max_level
    for y in range(ny[k]):
        for x in range(nx[k]):
            s = off[k] + y * nx[k] + x
            while s >= 0 and not mark[s]:
                s = _parent(s, lvl, tx, ty, off, nx, ny)
            if s < 0:
                uncovered += 1
    return overlap, uncovered


# -- the tracked adjacency -----------------------------------------------------------------------------
@dataclass(frozen=True)
class TileNeighbours:
    """The 8 relations of one visible leaf (slots; see :class:`QuadIndex`).

    ``edges[d]`` (d = 0..3 for L, U, R, D): leaves across that side, ascending along it (rows for L/R,
    columns for U/D); ``corners[c]`` (c = 0..3 for LU, RU, RD, LD): the leaf diagonally across, or -1.
    """

    edges: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]
    corners: tuple[int, int, int, int]

    def all(self) -> np.ndarray:
        """Every distinct neighbour slot."""
        parts = [*self.edges, np.array([c for c in self.corners if c >= 0], np.int64)]
        return np.unique(np.concatenate(parts))


class Adjacency:
    """The selected leaves of the current frame with their neighbours and Dirty flags.

    ``update(leaves, states)`` swaps in the new leaf set and returns the CrackTileVector: the visible leaves
    with an active flag, coarsest first. ``sleep(slots)`` puts their flags back to sleep once stitched.
    """

    def __init__(self, index: QuadIndex) -> None:
        self.index = index
        self.state = np.zeros(index.n, np.int8)
        self.dirty = np.zeros(index.n, np.uint8)
        self._mark = np.zeros(index.n, np.int64)
        self._stamp = 0
        self.leaves = np.zeros(0, np.int64)
        self.leaf_states = np.zeros(0, np.int8)
        self._nb: dict[int, TileNeighbours] = {}
        self.changed = np.zeros(0, np.int64)

    def neighbours(self, slot: int) -> TileNeighbours:
        """The relations of visible leaf ``slot`` (computed on first use after its flags went active)."""
        nb = self._nb.get(slot)
        if nb is None:
            nb = self._compute(slot)
            self._nb[slot] = nb
        return nb

    def _compute(self, slot: int) -> TileNeighbours:
        flat, counts = _tile_adjacency(slot, self.state, *self.index.arrays)
        ends = np.cumsum(counts)
        starts = ends - counts
        edges = tuple(flat[starts[d] : ends[d]] for d in range(4))
        corners = tuple(int(flat[starts[4 + c]]) if counts[4 + c] else -1 for c in range(4))
        return TileNeighbours(edges, corners)  # type: ignore[arg-type]

    def update(self, leaves: np.ndarray, states: np.ndarray) -> np.ndarray:
        """Swap in the new leaves (slots) with states (1 visible, 2 culled); returns the CrackTileVector."""
        leaves = np.ascontiguousarray(leaves, dtype=np.int64)
        states = np.ascontiguousarray(states, dtype=np.int8)
        self._stamp += 1
        changed = _apply_and_mark(
            self.leaves, leaves, states, self.state, self.dirty, self._mark, self._stamp, *self.index.arrays
        )
        self.changed = changed
        self.leaves, self.leaf_states = leaves, states
        # forget relations of tiles that left, and of tiles whose flags went active
        if changed.size:
            for s in changed.tolist():
                self._nb.pop(s, None)
        vis = leaves[states == VISIBLE]
        crack = vis[self.dirty[vis] != 0]
        for s in crack.tolist():
            self._nb.pop(s, None)
        # leaves that left the set keep no flags
        gone = changed[self.state[changed] == 0]
        self.dirty[gone] = 0
        culled = changed[self.state[changed] == CULLED]
        self.dirty[culled] = 0
        return crack[np.lexsort((crack, self.index.lvl[crack]))]

    def sleep(self, slots: np.ndarray) -> None:
        """Put the Dirty flags of ``slots`` to sleep (after they were stitched)."""
        self.dirty[np.asarray(slots, dtype=np.int64)] = 0

    def mark_all(self) -> np.ndarray:
        """Every visible leaf with all flags active (the full-traversal baseline), coarsest first."""
        vis = self.leaves[self.leaf_states == VISIBLE]
        self.dirty[vis] = 255
        self._nb.clear()
        return vis[np.lexsort((vis, self.index.lvl[vis]))]

    def visible(self, slot: int) -> bool:
        return bool(self.state[slot] == VISIBLE)

    def check_partition(self, leaves: np.ndarray) -> tuple[int, int]:
        """(#leaves overlapping another, #finest tiles not covered); (0, 0) for a valid leaf set."""
        ov, un = _partition_errors(
            np.ascontiguousarray(leaves, dtype=np.int64), *self.index.arrays, self.index.max_level
        )
        return int(ov), int(un)
