"""One Delaunay triangulation of a big cloud, computed block by block (on threads or Dask workers).

Paper: ``../shared/papers/003_2a2cfcda929de24c.txt`` §2.1 triangulates each sub-block on its own and
fills the gaps between the sub-blocks' hulls. That gives long thin gap triangles along the seams; here
the blocks compute pieces of the one global Delaunay triangulation instead, so the TIN is the same kind
of mesh whether it is built in one piece or in many (:mod:`terralod.tin.delaunay` splits it into the
paper's sub-blocks afterwards).

The method (the blocks are independent; only the last step runs on the client):

1. The cloud's xy bounding box is cut into ``m × m`` equal *cores* (:func:`block_layout`; ``m`` depends
   on the number of points only, never on the workers). The cores of the outer row and column reach to
   infinity outwards, so they partition the plane.
2. Each block triangulates the points of its core plus a *halo* some point spacings wide
   (:func:`block_triangles`, Shewchuk's Triangle, exact predicates). A triangle of that local
   triangulation whose circumcircle lies inside the core plus halo has no point of the whole cloud
   strictly inside it: every point inside the circle is one the block saw. It is a triangle of a global
   Delaunay triangulation.
3. The block *keeps* such a triangle only when its circumcentre lies in its own core, by a margin larger
   than the rounding error of the centre. All the triangles of one co-circular set share that centre,
   so one block keeps all of them or none: two blocks cannot keep the two diagonals of one co-circular
   quadrilateral, and the kept triangles of all blocks never overlap.
4. The client fills what no block kept (near the cores' corners, big circles in sparse areas, the hull)
   with a constrained Delaunay triangulation whose segments are the kept region's outline
   (:func:`fill_holes`). Every point inside the hole is in it, and the kept triangles are Delaunay, so
   the filled mesh is a Delaunay triangulation of the whole cloud.

For points in general position the result is the one Delaunay triangulation (the triangles of
``triangle.triangulate`` on the whole cloud, in another order). Among co-circular points the diagonals may
be chosen differently than by one call, but the result depends only on the points: local threads and
Dask workers give the same bytes.

Exact xy duplicates: the lowest index is used, the others dropped (every block applies the same rule).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = [
    "BlockJob",
    "BlockLayout",
    "BlockResult",
    "block_jobs",
    "block_layout",
    "block_triangles",
    "fill_holes",
]

#: Points a block triangulates, about (the layout depends on the cloud's size only).
POINTS_PER_BLOCK = 65536
#: Halo width in mean point spacings (sqrt(bounding-box area / points)).
HALO_SPACINGS = 8.0
#: Blocks per side, at most.
MAX_PER_SIDE = 64


# -- Triangle through ctypes: the same C library the ``triangle`` package wraps, called without the GIL ---
# (the package's own binding holds the GIL, so blocks on threads would run one at a time). The structure is
# Triangle 1.6's ``struct triangulateio``; :func:`_ffi` checks it against the package's binding once and
# falls back to the binding when they disagree.


def _tio_type() -> type:
    import ctypes as C

    D, I = C.POINTER(C.c_double), C.POINTER(C.c_int)
    fields = [
        ("pointlist", D), ("pointattributelist", D), ("pointmarkerlist", I), ("numberofpoints", C.c_int),
        ("numberofpointattributes", C.c_int), ("trianglelist", I), ("triangleattributelist", D),
        ("trianglearealist", D), ("neighborlist", I), ("numberoftriangles", C.c_int),
        ("numberofcorners", C.c_int), ("numberoftriangleattributes", C.c_int), ("segmentlist", I),
        ("segmentmarkerlist", I), ("numberofsegments", C.c_int), ("holelist", D), ("numberofholes", C.c_int),
        ("regionlist", D), ("numberofregions", C.c_int), ("edgelist", I), ("edgemarkerlist", I),
        ("normlist", D), ("numberofedges", C.c_int),
    ]  # fmt: skip
    return type("TriangulateIO", (C.Structure,), {"_fields_": fields})


_FFI: list = []  # [(lib, TriangulateIO)] once checked, [None] when the binding must be used


def _ffi_triangulate(lib, tio, xy: np.ndarray, segments: np.ndarray | None, switches: bytes):
    import ctypes as C

    xy = np.ascontiguousarray(xy, np.float64)
    i, o, v = tio(), tio(), tio()
    i.pointlist = xy.ctypes.data_as(C.POINTER(C.c_double))
    i.numberofpoints = xy.shape[0]
    if segments is not None:
        seg = np.ascontiguousarray(segments, np.intc)
        i.segmentlist = seg.ctypes.data_as(C.POINTER(C.c_int))
        i.numberofsegments = seg.shape[0]
    lib.triangulate(switches, C.byref(i), C.byref(o), C.byref(v))
    try:
        nt = o.numberoftriangles
        tris = (
            np.ctypeslib.as_array(o.trianglelist, (nt, 3)).astype(np.int64)
            if nt
            else np.zeros((0, 3), np.int64)
        )
        nbr = (
            np.ctypeslib.as_array(o.neighborlist, (nt, 3)).astype(np.int64)
            if nt
            else np.zeros((0, 3), np.int64)
        )
        return tris, nbr, int(o.numberofpoints)
    finally:
        _free_outputs(lib, o, i)


def _free_outputs(lib, o, i) -> None:
    """Free what Triangle allocated in ``o`` (arrays it copied from ``i`` by pointer are not its own)."""
    import ctypes as C

    for name in ("pointlist", "pointattributelist", "pointmarkerlist", "trianglelist", "triangleattributelist",
                 "neighborlist", "segmentlist", "segmentmarkerlist", "edgelist", "edgemarkerlist", "normlist"):  # fmt: skip
        p = C.cast(getattr(o, name), C.c_void_p).value
        if p and p != C.cast(getattr(i, name), C.c_void_p).value:
            lib.trifree(C.c_void_p(p))


def _ffi():
    """(lib, TriangulateIO) when the ctypes call matches the ``triangle`` package on a test cloud, else
    None (checked once per process)."""
    if not _FFI:
        found = None
        try:
            import ctypes as C

            import triangle
            import triangle.core

            lib = C.CDLL(triangle.core.__file__)
            tio = _tio_type()
            lib.triangulate.argtypes = [C.c_char_p, C.POINTER(tio), C.POINTER(tio), C.POINTER(tio)]
            lib.triangulate.restype = None
            lib.trifree.argtypes = [C.c_void_p]
            lib.trifree.restype = None
            xy = np.random.default_rng(7).random((64, 2))
            t, nb, _ = _ffi_triangulate(lib, tio, xy, None, b"zQnB")
            ref = triangle.triangulate({"vertices": xy}, "nQ")
            if np.array_equal(t, ref["triangles"]) and np.array_equal(nb, ref["neighbors"]):
                found = (lib, tio)
        except (ImportError, OSError, AttributeError, KeyError, ValueError):
            found = None
        _FFI.append(found)
    return _FFI[0]


def triangulate_xy(
    xy: np.ndarray, segments: np.ndarray | None = None, *, hull: bool = False
) -> tuple[np.ndarray, np.ndarray, int]:
    """Triangle's Delaunay triangulation of ``xy`` (N, 2), constrained by ``segments`` (S, 2) point pairs
    when given (``hull``: the convex hull kept, as Triangle's ``c``). Returns (triangles (M, 3) int64
    counter-clockwise, neighbours (M, 3) int64, the one opposite corner j in column j, -1 on the outline,
    number of output points: more than N when Triangle had to add one). Releases the GIL."""
    sw = "zQnB" + ("p" if segments is not None else "") + ("c" if hull else "")
    ffi = _ffi()
    if ffi is not None:
        return _ffi_triangulate(ffi[0], ffi[1], xy, segments, sw.encode())
    import triangle

    inp = {"vertices": np.ascontiguousarray(xy, np.float64)}
    if segments is not None:
        inp["segments"] = np.ascontiguousarray(segments, np.int32)
    out = triangle.triangulate(inp, sw.replace("z", ""))
    if "triangles" not in out:
        return np.zeros((0, 3), np.int64), np.zeros((0, 3), np.int64), int(out["vertices"].shape[0])
    return (
        np.asarray(out["triangles"], np.int64),
        np.asarray(out["neighbors"], np.int64),
        int(out["vertices"].shape[0]),
    )


@dataclass(frozen=True)
class BlockLayout:
    """``m × m`` cores over the xy box ``lo``-``hi`` (coordinates as given), and the halo width.

    Block ``b = row * m + col`` with col along x and row along y (both from ``lo``); its core is
    ``[xs[col], xs[col + 1]) × [ys[row], ys[row + 1])``, unbounded outwards on the outer row and column.
    """

    m: int
    xs: np.ndarray  # (m + 1,) core edges along x (xs[0] = -inf, xs[m] = +inf)
    ys: np.ndarray  # (m + 1,)
    halo: float

    @property
    def n_blocks(self) -> int:
        return self.m * self.m


@dataclass(frozen=True)
class BlockJob:
    """One block's input: its points (core + halo, ascending index) and the bounds it tests against."""

    block: int
    xy: np.ndarray  # (n, 2) float64
    index: np.ndarray  # (n,) int64, ascending: rows of the cloud
    core: tuple[float, float, float, float]  # x0, x1, y0, y1 (infinite outwards at the cloud's edge)
    known: tuple[float, float, float, float]  # core plus halo (infinite outwards)


@dataclass(frozen=True)
class BlockResult:
    """What one block keeps: its triangles (cloud rows, counter-clockwise), the kept triangles' edges whose
    local neighbour it did not keep (u, v, and the triangle's third vertex w), and the core points it
    dropped as exact xy duplicates of a lower row."""

    block: int
    triangles: np.ndarray  # (T, 3) int64
    open_edges: np.ndarray  # (E, 3) int64: u, v, w
    dropped: np.ndarray  # (D,) int64


def block_layout(xy: np.ndarray, points_per_block: int | None = None) -> BlockLayout:
    """The cores for ``xy`` (N, 2): ``m = round(sqrt(N / points_per_block))`` per side (default
    :data:`POINTS_PER_BLOCK`; m = 1 for small clouds: one block is one plain triangulation), the halo
    ``HALO_SPACINGS`` mean spacings wide."""
    n = xy.shape[0]
    per = POINTS_PER_BLOCK if points_per_block is None else points_per_block
    lo = xy.min(axis=0)
    hi = xy.max(axis=0)
    span = np.maximum(hi - lo, 0.0)
    m = int(min(MAX_PER_SIDE, max(1, round(math.sqrt(n / per)))))
    area = float(span[0] * span[1])
    spacing = math.sqrt(area / max(n, 1)) if area > 0 else float(max(span.max(), 1.0))
    # a halo no narrower than 2 % of a core: thin strips would leave more to the client
    halo = max(HALO_SPACINGS * spacing, 0.02 * float(max(span.max(), 1e-300)) / m)
    xs = lo[0] + span[0] * np.arange(m + 1) / m
    ys = lo[1] + span[1] * np.arange(m + 1) / m
    xs[0] = ys[0] = -np.inf
    xs[m] = ys[m] = np.inf
    return BlockLayout(m, xs, ys, float(halo))


def block_jobs(xy: np.ndarray, layout: BlockLayout) -> list[BlockJob]:
    """One job per block: the points inside its core plus halo (closed bounds, so no point the circle
    test relies on is missed)."""
    from terralod.kernels.delaunay import points_by_block

    m, h = layout.m, layout.halo
    starts, pid = points_by_block(np.ascontiguousarray(xy, np.float64), layout.xs, layout.ys, h)
    jobs = []
    for b in range(m * m):
        r, c = divmod(b, m)
        idx = pid[starts[b] : starts[b + 1]]
        core = (float(layout.xs[c]), float(layout.xs[c + 1]), float(layout.ys[r]), float(layout.ys[r + 1]))
        known = (core[0] - h, core[1] + h, core[2] - h, core[3] + h)
        jobs.append(BlockJob(b, np.ascontiguousarray(xy[idx]), idx, core, known))
    return jobs


def _first_of_duplicates(xy: np.ndarray) -> np.ndarray:
    """(n,) bool: False on the rows that repeat the xy of an earlier row (the first row is kept)."""
    order = np.lexsort((xy[:, 1], xy[:, 0]))  # stable: within a group the lowest row comes first
    s = xy[order]
    dup = np.zeros(xy.shape[0], bool)
    dup[order[1:][(s[1:] == s[:-1]).all(axis=1)]] = True
    return ~dup


def block_triangles(job: BlockJob) -> BlockResult:
    """Triangulate one block's points and keep the triangles it owns (see the module docstring). A pure
    function of the job; the triangulation and the ownership test run without the GIL."""
    from terralod.kernels.delaunay import owned_triangles

    empty = np.zeros((0, 3), np.int64)
    pts, gidx = job.xy, job.index
    dropped = np.zeros(0, np.int64)
    core = np.array(job.core, np.float64)
    known = np.array(job.known, np.float64)
    for attempt in range(2):
        if pts.shape[0] < 3:
            return BlockResult(job.block, empty, empty, dropped)
        tris, nbr, _ = triangulate_xy(pts)
        kept, edges, unused = owned_triangles(pts, tris, nbr, core, known)
        if unused == 0 or attempt == 1:
            break
        # a point no triangle uses: exact xy duplicates (Triangle keeps one of them, not necessarily the
        # lowest row). Every block keeps the lowest row, so the blocks agree; the others are dropped.
        first = _first_of_duplicates(job.xy)
        gone = np.flatnonzero(~first)
        g = job.xy[gone]
        x0, x1, y0, y1 = job.core
        dropped = job.index[gone[(g[:, 0] >= x0) & (g[:, 0] < x1) & (g[:, 1] >= y0) & (g[:, 1] < y1)]]
        pts, gidx = job.xy[first], job.index[first]
    return BlockResult(job.block, gidx[tris[kept]], gidx[edges], dropped)


def fill_holes(xy: np.ndarray, results: list[BlockResult]) -> np.ndarray | None:
    """The whole triangulation (M, 3) int64 (cloud rows): the blocks' kept triangles, in block order, then
    the constrained Delaunay fill of what none kept. None when Triangle had to add a point (segments that
    cross: not expected; the caller then triangulates the cloud in one piece)."""
    n = xy.shape[0]
    kept = np.concatenate([r.triangles for r in results]) if results else np.zeros((0, 3), np.int64)
    open_ = np.concatenate([r.open_edges for r in results]) if results else np.zeros((0, 3), np.int64)
    dropped = np.concatenate([r.dropped for r in results]) if results else np.zeros(0, np.int64)
    # an open edge seen from both sides (kept by two blocks) is inside the kept region; once: its outline
    lo = np.minimum(open_[:, 0], open_[:, 1])
    hi = np.maximum(open_[:, 0], open_[:, 1])
    key = lo * n + hi
    order = np.argsort(key, kind="stable")
    ks = key[order]
    first = np.ones(ks.size, bool)
    first[1:] = ks[1:] != ks[:-1]
    count = np.diff(np.append(np.flatnonzero(first), ks.size))
    single = order[np.flatnonzero(first)[count == 1]]
    seg = open_[single]  # u, v, w: outline edges, w the kept triangle's third vertex
    used = np.zeros(n, bool)
    used[kept.ravel()] = True
    gone = np.zeros(n, bool)
    gone[dropped] = True
    s_mask = ~used & ~gone
    s_mask[seg[:, 0]] = True
    s_mask[seg[:, 1]] = True
    s_idx = np.flatnonzero(s_mask)
    if s_idx.size < 3:
        return kept
    remap = np.full(n, -1, np.int64)
    remap[s_idx] = np.arange(s_idx.size)
    pts = xy[s_idx]
    tris, nbr, n_out = triangulate_xy(pts, remap[seg[:, :2]] if seg.shape[0] else None, hull=True)
    if n_out != pts.shape[0]:
        return None
    if tris.shape[0] == 0:
        return kept
    nt = tris.shape[0]
    # each fill triangle's edges (opposite vertex j); which are outline segments
    eu = tris[:, [1, 2, 0]]
    ev = tris[:, [2, 0, 1]]
    m_s = pts.shape[0]
    ekey = np.minimum(eu, ev) * m_s + np.maximum(eu, ev)
    su, sv = remap[seg[:, 0]], remap[seg[:, 1]]
    skey = np.minimum(su, sv) * m_s + np.maximum(su, sv)
    sorder = np.argsort(skey)
    pos = np.clip(np.searchsorted(skey[sorder], ekey), 0, max(skey.size - 1, 0))
    is_seg = (skey.size > 0) & (skey[sorder][pos] == ekey) if skey.size else np.zeros_like(ekey, bool)
    # components of fill triangles joined across non-segment edges
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    link = (nbr >= 0) & ~is_seg
    ti, j = np.nonzero(link)
    g = coo_matrix((np.ones(ti.size, np.int8), (ti, nbr[ti, j])), shape=(nt, nt))
    n_comp, comp = connected_components(g, directed=False)
    # a triangle beside an outline segment: on the kept side when its third vertex is on the side of the
    # kept triangle's third vertex; each component takes the majority of its votes (no vote: a hole)
    ti, j = np.nonzero(is_seg)
    sid = sorder[pos[ti, j]]
    u, v, w = xy[seg[sid, 0]], xy[seg[sid, 1]], xy[seg[sid, 2]]
    q = xy[s_idx[tris[ti, j]]]

    def orient(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
        return (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])

    inside = np.sign(orient(u, v, q)) == np.sign(orient(u, v, w))
    votes = np.bincount(comp[ti], weights=np.where(inside, 1.0, -1.0), minlength=n_comp)
    hole = votes[comp] <= 0
    return np.concatenate([kept, s_idx[tris[hole]]])
