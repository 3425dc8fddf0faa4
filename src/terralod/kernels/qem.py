"""QEM half-edge collapse, its records and their measured error (numba kernels).

Paper: ``../shared/papers/003_2a2cfcda929de24c.txt`` §2.1 (Garland–Heckbert quadric error metric, vertex
placed at an edge endpoint: the one with the smaller quadric error) and §2.2.1 (one record per collapse:
deleted triangles with their vertex indices, replaced triangles with original and new vertex indices,
written by :func:`qem_simplify`). Pure functions on arrays: no I/O, no exceptions; validation and frames
live in :mod:`terralod.tin.qem`. The replay of the records (§2.2.1 vertex splits, §2.3.1 applying records
forwards or backwards) is in :mod:`terralod.kernels.qem_replay`, which imports this module's star-list
helpers (never the other way round).

Vocabulary
----------
- *slot*: a triangle's index in the full-resolution triangle array. A slot keeps its index for life: a
  collapse deletes two slots and rewrites the vertex triple of the others around the removed vertex.
- *star(v)*: the live slots that use vertex v, kept as one list per vertex in an *arena* (one int32
  array; list v is ``arena[start[v] : start[v] + length[v]]``, capacity ``cap[v]``; a list that outgrows
  its capacity moves to the arena's end with twice the room, and the arena doubles when full).
- *half-edge collapse u → v*: vertex u disappears, every triangle of star(u) that also uses v is deleted
  (exactly two: u is interior), the others get v in place of u. The endpoint v does not move, so no new
  vertex ever appears (Ai et al. (2019) §2.1).

Vertex kinds (what a vertex may do)::

    FREE    interior vertex of one sub-block          may be removed (u), may be a target (v)
    LOCKED  on the mesh boundary or a sub-block seam  never removed,     may be a target (v)

A collapse u → v is accepted when (table, not branches):

    u FREE and alive | v a ring neighbour of u | link(u) ∩ link(v) = the two opposite vertices
    (link condition: the result stays a 2-manifold) | every rewritten triangle keeps a counter-clockwise
    xy orientation with area > ``shape_eps`` · (sum of its squared xy edge lengths) (no fold, no sliver
    whose orientation rounding could flip; for a TIN this is the "normal z keeps its sign" test)

Quadrics: each triangle adds its plane, weighted by its area, to its three vertices (``Q`` holds the 10
distinct entries of the symmetric 4×4 matrix, ``W`` the summed area). Cost of u → v = vᵀ(Q_u + Q_v)v
(m⁴: area × squared distance) orders the heap; the same quadric divided by its area, (vᵀ(Q_u + Q_v)v) /
(W_u + W_v), is an area-weighted mean squared distance (m²) used for the paper's MMQE, so that
sqrt(MMQE) is a length in metres as §2.3.2 needs. After u → v, Q_v += Q_u (Garland–Heckbert).
Q_w(P_w) is kept per vertex, so a cost costs one quadric evaluation.

Vertical term (``vweight`` > 0, not in the paper): each live slot carries the removed vertices whose xy
it covers (a list per slot: ``head``, ``nxt``; a collapse hands the lists of star(u), and u, to the
rewritten slots). The cost of u → w adds ``vweight · W_u · g²``, g the largest vertical distance from u
and the vertices star(u) carries to the surface after the collapse (m⁴, like the quadric), so a collapse
that moves the surface far from points removed earlier waits. Only the candidates whose quadric alone is
below the best full cost get g (branch and bound), and g stops early once it passes that bound. star(u)
and its points are gathered once per evaluation (contiguous xyz), each candidate's triangles once per
candidate, and a point is looked for first in the triangle of the slot that carries it (where it almost
always stays), by signs alone, dividing only for the height. A collapse hands each point to the rewritten slot
that holds it most (the largest smallest barycentric coordinate), trying first the slot that carried it
and stopping at the first that holds it with a margin (:data:`_INSIDE`); the same slot as the full search.

Lazy validity: every FREE vertex is first queued, and after a collapse the vertices around it are
re-queued, at its cheapest collapse *untested*; the test runs when the entry leaves the heap, and a failure
re-evaluates the vertex with tests and re-queues it at its cheapest valid cost (never lower than the
untested key). Every key is a lower bound of the vertex's valid cost, so collapses still leave in
increasing valid cost; the one difference from testing at once is that a cheaper collapse that was invalid
when queued and turned valid by the time it is popped goes first. Most link tests are never run: 1.6x faster on a 512² grid TIN, with
exactly the same collapses there (and on Autzen).

Lazy vertical term: with ``vweight`` > 0 a vertex is queued (and re-queued by a refresh) at its smallest
quadric cost alone, a lower bound of its full cost (:func:`_bound`); the vertical term is computed when the
entry leaves the heap, and the vertex goes back at its full cost unless that still comes first. Every key
being a lower bound, collapses leave in the order of full costs queued at once (same collapses on Autzen,
the Autzen 4 x 4 tiling and random clouds; the Puget points part from it at collapse 363 of 210,522 where a
merged quadric's rounding moves a cost, with the same per-block maximum errors); 13-17 % less QEM time.

Refresh after u → v: v and ring(u) get a full evaluation (their stars, and the points the vertical term
measures, changed). A vertex of ring(v) outside ring(u) keeps its star and its points; only Q_v grew, so
its collapse onto v got dearer and nothing else moved: its best collapse stands unless it was onto v, and
only its MMQE term is refreshed (through x → v alone unless that gave its minimum). About a third of the
ring visits are such. With the quadric alone, a vertex of ring(u) whose best collapse is the cheapest
(untested) and is onto neither u nor v compares it with x → v alone: its other costs did not change.
The collapse sequence is the one of a full evaluation except where a full evaluation would have re-queued
an invalid collapse, or where a merged quadric lowered a cost by rounding (Q_v only grows, but
Q_v(P_v) is a sum of large terms): a few tie-broken collapses on the Puget crop, same errors.

MMQE (§2.1): per sub-block, the mean over its alive FREE vertices of their minimum (normalised) quadric
error over all ring neighbours; kept as a running sum updated on every re-evaluation.

The helpers called in the inner loops (heap, stars, quadric and vertical-term evaluation, the collapse
test) are :func:`terralod.kernels.leaf` kernels (no reference counting of their array arguments): the same
collapses bit for bit, about 5 % less time on the Puget Sound 513² crop's nine sub-blocks.

Memory: quadrics 88 bytes a vertex, arena ~ 3 int32 a triangle (x 1.5 slack), heap 24 bytes a vertex,
records ~ 2 deleted + ~4 replaced slots a collapse.
"""

from __future__ import annotations

import math

import numpy as np

from terralod.kernels import jit, leaf

FREE = np.uint8(0)  #: interior vertex of one sub-block: may be collapsed away
LOCKED = np.uint8(1)  #: mesh boundary or sub-block seam: never removed, may be a collapse target

#: A point whose smallest barycentric coordinate in a triangle of a collapse's new fan exceeds this lies
#: inside it with a margin far above rounding (about 1e-14 here): the fan's triangles do not overlap (each
#: keeps its counter-clockwise orientation), so no other one can hold it, and the search for the triangle
#: that holds it most stops there with the same answer as the full search.
_INSIDE = 1e-9

#: Rings of more candidates than this are ordered by a sort instead of insertion (quadratic).
_SORT_RING = 24


# -- vertex → triangle lists (arena) -------------------------------------------------------------------
@jit
def _empty_arena(deg, slack):
    """Empty arena lists for vertices of degree ``deg``: capacity = degree + ``slack``, the arena 1.5x the
    total (+16) for lists that move to its end; returns (arena, start, length, cap, top)."""
    n_vertices = deg.shape[0]
    start = np.empty(n_vertices, np.int64)
    cap = np.empty(n_vertices, np.int64)
    top = 0
    for v in range(n_vertices):
        start[v] = top
        cap[v] = deg[v] + slack
        top += cap[v]
    arena = np.empty(top + top // 2 + 16, np.int32)
    length = np.zeros(n_vertices, np.int64)
    return arena, start, length, cap, top


@jit
def _build_stars(tris, alive, n_vertices):
    """Arena lists star(v) of the live triangles; capacity = degree + 4 (slack for early merges)."""
    deg = np.zeros(n_vertices, np.int64)
    for t in range(tris.shape[0]):
        if alive[t]:
            for k in range(3):
                deg[tris[t, k]] += 1
    arena, start, length, cap, top = _empty_arena(deg, 4)
    for t in range(tris.shape[0]):
        if alive[t]:
            for k in range(3):
                v = tris[t, k]
                arena[start[v] + length[v]] = t
                length[v] += 1
    return arena, start, length, cap, top


@leaf
def _star_remove(arena, start, length, v, t):
    """Drop slot t from star(v) (swap with the last entry)."""
    s = start[v]
    n = length[v]
    for i in range(n):
        if arena[s + i] == t:
            arena[s + i] = arena[s + n - 1]
            length[v] = n - 1
            return


@jit
def _star_add(arena, start, length, cap, top, v, t):
    """Append slot t to star(v), moving the list to the arena's end when full; returns (arena, top)."""
    if length[v] == cap[v]:
        ncap = 2 * cap[v] + 4
        if top + ncap > arena.shape[0]:
            arena = _grow(arena, top + ncap)
        arena[top : top + length[v]] = arena[start[v] : start[v] + length[v]]
        start[v] = top
        cap[v] = ncap
        top += ncap
    arena[start[v] + length[v]] = t
    length[v] += 1
    return arena, top


@leaf
def _next_after(tris, t, u):
    """The vertex after u in triangle t (counter-clockwise order)."""
    if tris[t, 0] == u:
        return tris[t, 1]
    if tris[t, 1] == u:
        return tris[t, 2]
    return tris[t, 0]


@leaf
def _bary_xy(P, o, a, b, px, py):
    """Barycentric coordinates (l1, l2) of the point (px, py) in the xy projection of triangle (o, a, b),
    and m, the smallest of (1 - l1 - l2, l1, l2); m = -inf for a degenerate (zero-area) triangle, so that
    it never wins a "largest smallest coordinate" search."""
    ox = P[o, 0]
    oy = P[o, 1]
    ax = P[a, 0] - ox
    ay = P[a, 1] - oy
    bx = P[b, 0] - ox
    by = P[b, 1] - oy
    det = ax * by - ay * bx
    if det == 0.0:
        return 0.0, 0.0, -np.inf
    qx = px - ox
    qy = py - oy
    l1 = (qx * by - qy * bx) / det
    l2 = (ax * qy - ay * qx) / det
    return l1, l2, min(1.0 - l1 - l2, min(l1, l2))


@leaf
def _take_list(head, nxt, s, buf, n):
    """Move the vertices held by slot s (its list ``head``/``nxt``) to ``buf[n:]``, empty the list and
    return the new count."""
    p = head[s]
    while p >= 0:
        buf[n] = p
        n += 1
        p = nxt[p]
    head[s] = -1
    return n


@leaf
def _set_row(dst, i, src, j):
    """dst[i, 0:3] = src[j, 0:3] (a vertex triple)."""
    dst[i, 0] = src[j, 0]
    dst[i, 1] = src[j, 1]
    dst[i, 2] = src[j, 2]


# -- quadrics -------------------------------------------------------------------------------------------
@jit
def plane_quadrics(P, tris, alive):
    """Area-weighted plane quadrics per vertex.

    Returns ``(Q, W)``: Q (N, 10) float64, the entries (aa, ab, ac, ad, bb, bc, bd, cc, cd, dd) of
    Σ area · p pᵀ over the triangles of each vertex, p = (a, b, c, d) the unit plane; W (N,) the summed
    areas (m²). Degenerate (zero-area) triangles add nothing.
    """
    n = P.shape[0]
    Q = np.zeros((n, 10), np.float64)
    W = np.zeros(n, np.float64)
    for t in range(tris.shape[0]):
        if not alive[t]:
            continue
        i = tris[t, 0]
        j = tris[t, 1]
        k = tris[t, 2]
        e1x = P[j, 0] - P[i, 0]
        e1y = P[j, 1] - P[i, 1]
        e1z = P[j, 2] - P[i, 2]
        e2x = P[k, 0] - P[i, 0]
        e2y = P[k, 1] - P[i, 1]
        e2z = P[k, 2] - P[i, 2]
        nx = e1y * e2z - e1z * e2y
        ny = e1z * e2x - e1x * e2z
        nz = e1x * e2y - e1y * e2x
        ln = math.sqrt(nx * nx + ny * ny + nz * nz)
        if ln == 0.0:
            continue
        area = 0.5 * ln
        a = nx / ln
        b = ny / ln
        c = nz / ln
        d = -(a * P[i, 0] + b * P[i, 1] + c * P[i, 2])
        q0 = area * a * a
        q1 = area * a * b
        q2 = area * a * c
        q3 = area * a * d
        q4 = area * b * b
        q5 = area * b * c
        q6 = area * b * d
        q7 = area * c * c
        q8 = area * c * d
        q9 = area * d * d
        for v in (i, j, k):
            Q[v, 0] += q0
            Q[v, 1] += q1
            Q[v, 2] += q2
            Q[v, 3] += q3
            Q[v, 4] += q4
            Q[v, 5] += q5
            Q[v, 6] += q6
            Q[v, 7] += q7
            Q[v, 8] += q8
            Q[v, 9] += q9
            W[v] += area
    return Q, W


@leaf
def _quadric_at(Q, i, x, y, z):
    """pᵀ Q_i p for p = (x, y, z, 1)."""
    return (
        Q[i, 0] * x * x
        + 2.0 * Q[i, 1] * x * y
        + 2.0 * Q[i, 2] * x * z
        + 2.0 * Q[i, 3] * x
        + Q[i, 4] * y * y
        + 2.0 * Q[i, 5] * y * z
        + 2.0 * Q[i, 6] * y
        + Q[i, 7] * z * z
        + 2.0 * Q[i, 8] * z
        + Q[i, 9]
    )


@leaf
def _collapse_cost(Q, P, u, v):
    """vᵀ (Q_u + Q_v) v, clamped at 0 (rounding), m⁴."""
    x = P[v, 0]
    y = P[v, 1]
    z = P[v, 2]
    c = _quadric_at(Q, u, x, y, z) + _quadric_at(Q, v, x, y, z)
    return c if c > 0.0 else 0.0


@leaf
def _emin_through(x, v, c, W, emin, eminw):
    """x's MMQE term when only its collapse x -> v (quadric cost ``c``, m⁴) may have changed and was not its
    minimum: the smaller of the old minimum and c / (W_x + W_v); records v as the minimum's target if so."""
    ex = c / (W[x] + W[v])
    if ex < emin[x]:
        eminw[x] = v
        return ex
    return emin[x]


# -- indexed min-heap of (cost, vertex): one entry per vertex ----------------------------------------------
# hk[i], hv[i]: key and vertex of heap node i; hpos[v]: v's node (-1: not queued). Ties broken by vertex
# (deterministic). A vertex whose best collapse changes moves in place (no stale entries to pop), so the
# heap never holds more than the FREE vertices.
@leaf
def _before(k1, v1, k2, v2):
    """(k1, v1) < (k2, v2): by key, then by vertex."""
    return k1 < k2 or (k1 == k2 and v1 < v2)


@leaf
def _heap_place(hk, hv, hpos, i, key, v, size):
    """Put (key, v) at node i (a hole in a heap of ``size`` nodes) and sift it up or down to its place."""
    while i > 0:
        p = (i - 1) >> 1
        if not _before(key, v, hk[p], hv[p]):
            break
        hk[i] = hk[p]
        hv[i] = hv[p]
        hpos[hv[i]] = i
        i = p
    while True:
        m = 2 * i + 1
        if m >= size:
            break
        if m + 1 < size and _before(hk[m + 1], hv[m + 1], hk[m], hv[m]):
            m += 1
        if not _before(hk[m], hv[m], key, v):
            break
        hk[i] = hk[m]
        hv[i] = hv[m]
        hpos[hv[i]] = i
        i = m
    hk[i] = key
    hv[i] = v
    hpos[v] = i


@leaf
def _heap_set(hk, hv, hpos, size, key, v):
    """Queue v at ``key``, or move it there when queued; returns the new size."""
    i = hpos[v]
    if i < 0:
        _heap_place(hk, hv, hpos, size, key, v, size + 1)
        return size + 1
    _heap_place(hk, hv, hpos, i, key, v, size)
    return size


@leaf
def _heap_remove(hk, hv, hpos, size, v):
    """Unqueue v (no-op when not queued); returns the new size."""
    i = hpos[v]
    if i < 0:
        return size
    hpos[v] = -1
    size -= 1
    if i < size:
        _heap_place(hk, hv, hpos, i, hk[size], hv[size], size)
    return size


# -- collapse test and evaluation ------------------------------------------------------------------------
@leaf
def _can_collapse(u, v, P, tris, arena, start, length, mark, stampbox, shape_eps):
    """Link condition and orientation test of the half-edge collapse u → v (u FREE, interior)."""
    # Orientation first (a folding collapse, the usual failure around a concave fan, often stops at its
    # first triangles): every rewritten triangle (v, a, b) stays counter-clockwise and not a sliver.
    su = start[u]
    vx = P[v, 0]
    vy = P[v, 1]
    for i in range(length[u]):
        t = arena[su + i]
        a = _next_after(tris, t, u)
        b = _next_after(tris, t, a)
        if a == v or b == v:
            continue
        ax = P[a, 0] - vx
        ay = P[a, 1] - vy
        bx = P[b, 0] - vx
        by = P[b, 1] - vy
        area2 = ax * by - ay * bx
        size2 = ax * ax + ay * ay + bx * bx + by * by + (bx - ax) * (bx - ax) + (by - ay) * (by - ay)
        if not area2 > shape_eps * size2:
            return False
    # Link condition: the rings of u and v share exactly the two opposite vertices.
    stampbox[0] += 1
    stamp = stampbox[0]
    sv = start[v]
    for i in range(length[v]):
        t = arena[sv + i]
        for k in range(3):
            mark[tris[t, k]] = stamp
    common = 0
    for i in range(length[u]):
        a = _next_after(tris, arena[su + i], u)
        if a != v and mark[a] == stamp:
            common += 1
    return common == 2


@leaf
def _gather_star(u, P, tris, arena, su, n, head, nxt, sa, sb, geo, pxyz, ps, pst, seg):
    """star(u) and the points its collapse moves away from, gathered once per evaluation (every candidate
    target w reads them): slot i of the star is (u, sa[i], sb[i]) counter-clockwise, ``geo[i]`` = the xyz
    of sa[i] then sb[i]; the points are u then the removed vertices the slots carry, ``pxyz[j]`` their xyz
    and ``ps[j]`` the star index of the slot that carries them (-1 for u). Slot i's points are
    ``pxyz[pst[i] : pst[i + 1]]``, ``seg[i]`` their xy box (x min, x max, y min, y max) and their one height
    (NaN when they differ, or none): what lets :func:`_carried_gap2` skip a slot's level points at once.
    Returns the point count."""
    pxyz[0, 0] = P[u, 0]
    pxyz[0, 1] = P[u, 1]
    pxyz[0, 2] = P[u, 2]
    ps[0] = -1
    m = 1
    for i in range(n):
        t = arena[su + i]
        a = _next_after(tris, t, u)
        b = _next_after(tris, t, a)
        sa[i] = a
        sb[i] = b
        for k in range(3):
            geo[i, k] = P[a, k]
            geo[i, 3 + k] = P[b, k]
        q = head[t]
        pst[i] = m
        x0 = y0 = np.inf
        x1 = y1 = -np.inf
        hq = np.nan
        level = True
        while q >= 0:
            x = P[q, 0]
            y = P[q, 1]
            z = P[q, 2]
            pxyz[m, 0] = x
            pxyz[m, 1] = y
            pxyz[m, 2] = z
            ps[m] = i
            x0 = min(x0, x)
            x1 = max(x1, x)
            y0 = min(y0, y)
            y1 = max(y1, y)
            if m == pst[i]:
                hq = z
            elif z != hq:
                level = False
            m += 1
            q = nxt[q]
        seg[i, 0] = x0
        seg[i, 1] = x1
        seg[i, 2] = y0
        seg[i, 3] = y1
        seg[i, 4] = hq if level else np.nan
    pst[n] = m
    return m


@leaf
def _carried_gap2(w, P, sa, sb, n, geo, pxyz, ps, pst, seg, npts, tri, glim):
    """Largest squared vertical distance, m², from the gathered points (:func:`_gather_star`) to the
    surface after the collapse u -> w; stops early, returning a lower bound >= ``glim``, once the largest
    reaches ``glim``.

    Each point is located in the rewritten triangle (w, sa[i], sb[i]) with the largest smallest
    barycentric coordinate of its xy (so a point on an edge, or outside by rounding, still gets one),
    trying first the slot that carries it (where it usually stays) and stopping at the first that holds it.
    ``tri[i]`` gets triangle i's edge vectors from w, twice its signed area (0: deleted by the collapse or
    degenerate, never picked) and its z rises from w.
    """
    wx = P[w, 0]
    wy = P[w, 1]
    wz = P[w, 2]
    for i in range(n):
        tri[i, 0] = geo[i, 0] - wx
        tri[i, 1] = geo[i, 1] - wy
        tri[i, 2] = geo[i, 3] - wx
        tri[i, 3] = geo[i, 4] - wy
        tri[i, 4] = 0.0 if sa[i] == w or sb[i] == w else tri[i, 0] * tri[i, 3] - tri[i, 1] * tri[i, 2]
        tri[i, 5] = geo[i, 2] - wz
        tri[i, 6] = geo[i, 5] - wz
    # Level ground (sea, a lake, a platform) around w: the rewritten triangles at w's height are level, so a
    # point at that height that falls in one is exactly on the surface (distance 0). A point at w's height
    # strictly outside the xy box of every other (non-level) rewritten triangle can only fall in a level
    # one: it is skipped without being located. This is what made flat fans slow: a coast vertex carries
    # the thousands of sea points its fan covers, and every candidate located each of them. A slot whose
    # points all share w's height and whose points' box lies outside that box is skipped whole (the same
    # points the test of each would skip): looking at each sea point for every candidate was the rest.
    bx0 = by0 = np.inf
    bx1 = by1 = -np.inf
    n_level = 0
    for i in range(n):
        if tri[i, 4] == 0.0:
            continue  # deleted by the collapse, or degenerate: never picked
        if tri[i, 5] == 0.0 and tri[i, 6] == 0.0:
            n_level += 1
            continue
        bx0 = min(bx0, 0.0, tri[i, 0], tri[i, 2])
        bx1 = max(bx1, 0.0, tri[i, 0], tri[i, 2])
        by0 = min(by0, 0.0, tri[i, 1], tri[i, 3])
        by1 = max(by1, 0.0, tri[i, 1], tri[i, 3])
    g = 0.0
    j = -1
    while j + 1 < npts:
        j += 1
        if n_level > 0 and j > 0:
            i = ps[j]
            if (
                j == pst[i]
                and seg[i, 4] == wz
                and (
                    seg[i, 1] - wx < bx0
                    or seg[i, 0] - wx > bx1
                    or seg[i, 3] - wy < by0
                    or seg[i, 2] - wy > by1
                )
            ):
                j = pst[i + 1] - 1  # every point of the slot: at w's height, outside the box (below)
                continue
        qx = pxyz[j, 0] - wx
        qy = pxyz[j, 1] - wy
        if n_level > 0 and pxyz[j, 2] == wz and (qx < bx0 or qx > bx1 or qy < by0 or qy > by1):
            continue  # on a level triangle: distance 0, never the largest (g >= 0)
        # the first triangle that holds q (its own slot first), by signs alone: det·l1, det·l2 and
        # det·(1 - l1 - l2) all >= 0 with det > 0; one division pair for the height
        s0 = ps[j]
        hit = -1
        for ii in range(-1, n):
            i = s0 if ii < 0 else ii
            if i < 0 or (ii >= 0 and i == s0):
                continue
            det = tri[i, 4]
            if not det > 0.0:
                continue
            n1 = qx * tri[i, 3] - qy * tri[i, 2]
            n2 = tri[i, 0] * qy - tri[i, 1] * qx
            if n1 >= 0.0 and n2 >= 0.0 and det - n1 - n2 >= 0.0:
                hit = i
                break
        if hit >= 0:
            det = tri[hit, 4]
            l1 = (qx * tri[hit, 3] - qy * tri[hit, 2]) / det
            l2 = (tri[hit, 0] * qy - tri[hit, 1] * qx) / det
            bz = wz + l1 * tri[hit, 5] + l2 * tri[hit, 6]
        else:
            # outside every triangle (rounding, or a fold): the largest smallest barycentric coordinate
            best = -np.inf
            bz = 0.0
            for i in range(n):
                det = tri[i, 4]
                if det == 0.0:
                    continue
                l1 = (qx * tri[i, 3] - qy * tri[i, 2]) / det
                l2 = (tri[i, 0] * qy - tri[i, 1] * qx) / det
                m = min(1.0 - l1 - l2, min(l1, l2))
                if m > best:
                    best = m
                    bz = wz + l1 * tri[i, 5] + l2 * tri[i, 6]
        d = pxyz[j, 2] - bz
        d *= d
        if j == 0 or d > g:
            g = d
            if g >= glim:
                return g
    return g


@leaf
def _quadric_costs(u, P, tris, Q, W, selfq, arena, su, n, wbuf, cbuf):
    """The ring neighbours w of u (``wbuf``) and the quadric costs of u -> w (``cbuf``, m⁴); returns u's
    minimum normalised quadric error (m², the MMQE term of u). ``selfq[w]`` = Q_w(P_w), so a cost is one
    quadric evaluation: Q_u(P_w) + Q_w(P_w). Returns (emin, the neighbour that gives it)."""
    emin = np.inf
    ew = -1
    for i in range(n):
        w = _next_after(tris, arena[su + i], u)
        c = _quadric_at(Q, u, P[w, 0], P[w, 1], P[w, 2]) + selfq[w]  # = _collapse_cost(Q, P, u, w)
        if c < 0.0:
            c = 0.0
        e = c / (W[u] + W[w])
        if e < emin:
            emin = e
            ew = w
        wbuf[i] = w
        cbuf[i] = c
    return emin, ew


@jit
def _order_by_cost(cbuf, wbuf, idx, m):
    """Sort the candidate indices ``idx[:m]`` in place by increasing (cbuf, wbuf) (the vertices are
    distinct: one order): insertion for a small ring, or one with a NaN cost (which then stays where it
    is, as insertion leaves it), else two stable argsorts (a coast fan of ~200 candidates)."""
    if m > _SORT_RING and not np.isnan(cbuf[idx[:m]]).any():
        sub = idx[:m].copy()
        by_w = sub[np.argsort(wbuf[sub], kind="mergesort")]
        by_cw = by_w[np.argsort(cbuf[by_w], kind="mergesort")]
        for i in range(m):
            idx[i] = by_cw[i]
        return
    for i in range(1, m):
        k = idx[i]
        j = i
        while j > 0 and (
            cbuf[idx[j - 1]] > cbuf[k] or (cbuf[idx[j - 1]] == cbuf[k] and wbuf[idx[j - 1]] > wbuf[k])
        ):
            idx[j] = idx[j - 1]
            j -= 1
        idx[j] = k


@jit
def _evaluate(u, prev_v, prev_c, validate, arena, start, length, ctx, work):
    """Best collapse target of u and u's minimum normalised quadric error.

    Returns ``(v, cost, emin, ew)``: with ``validate``, the ring neighbour v with the smallest cost among the
    valid collapses (-1 and inf when none is valid); without, the cheapest neighbour untested (the caller
    tests it when it leaves the heap). emin is the smallest normalised error over every ring neighbour,
    valid or not (the MMQE term of u, m²), ew the neighbour that gives it. When the cheapest neighbour is
    still ``prev_v`` at cost ``prev_c`` it is returned untested (its test is repeated when it leaves the
    heap anyway); ``prev_v`` is also the candidate whose vertical term is computed first.
    ``ctx`` = (P, tris, Q, W, selfq, head, nxt, shape_eps, vweight) and ``work`` = (mark, stampbox, wbuf,
    cbuf, dbuf, qbuf, obuf, sa, sb, geo, pxyz, ps, pst, seg, tri, rbuf) are the simplifier's state and
    scratch, passed as two tuples (the arena, which moves when it grows, is passed on its own).
    """
    P, tris, Q, W, selfq, head, nxt, shape_eps, vweight = ctx
    mark, stampbox, wbuf, cbuf, dbuf, qbuf, obuf, sa, sb, geo, pxyz, ps, pst, seg, tri, rbuf = work
    su = start[u]
    n = length[u]
    exact = not vweight > 0.0
    wt = vweight * W[u]
    npts = 0
    emin, ew = _quadric_costs(u, P, tris, Q, W, selfq, arena, su, n, wbuf, cbuf)
    if not exact:
        # cbuf: lower bounds (the quadric alone); add the vertical term in increasing bound order until the
        # next bound exceeds the best exact cost (branch and bound)
        npts = _gather_star(u, P, tris, arena, su, n, head, nxt, sa, sb, geo, pxyz, ps, pst, seg)
        # obuf[:n]: candidates by increasing (bound, vertex) (the vertices are distinct: one order); a
        # candidate made exact, or found past the best, never comes before the next bound
        for i in range(n):
            dbuf[i] = False
            qbuf[i] = cbuf[i]
            obuf[i] = i
        _order_by_cost(cbuf, wbuf, obuf, n)
        best = np.inf
        for k in range(n):
            if wbuf[k] == prev_v:
                # the previous best usually still wins: made exact first, it bounds the others tightly
                cbuf[k] += wt * _carried_gap2(
                    prev_v, P, sa, sb, n, geo, pxyz, ps, pst, seg, npts, tri, np.inf
                )
                dbuf[k] = True
                best = cbuf[k]
                break
        for o in range(n):
            k = obuf[o]
            if dbuf[k]:
                continue
            if cbuf[k] >= best:
                break
            glim = (best - cbuf[k]) / wt if best < np.inf and wt > 0.0 else np.inf
            g = _carried_gap2(wbuf[k], P, sa, sb, n, geo, pxyz, ps, pst, seg, npts, tri, glim)
            cbuf[k] += wt * g
            if g < glim:  # exact (else a bound past the best: never picked before it is made exact)
                dbuf[k] = True
                if cbuf[k] < best:
                    best = cbuf[k]
    k0 = _cheapest(cbuf, wbuf, n, -np.inf, -1)
    c0 = cbuf[k0] if k0 >= 0 else np.inf
    w0 = wbuf[k0] if k0 >= 0 else -1
    if (w0 == prev_v and c0 == prev_c) or not validate:
        return w0, c0, emin, ew
    # The valid candidate of smallest (cost, vertex): candidates in increasing (cost or bound, vertex)
    # order, each tested when it first comes first (an invalid one leaves the race without its vertical
    # term: a coast vertex's fan of ~200 triangles has most of its collapses folding, and making each exact
    # before its test passed over every point the fan carries, for every candidate); a valid bound that
    # comes first is made exact and the order taken again. The same answer as testing in exact order.
    for k in range(n):
        obuf[k] = 0  # 1: tested valid, 2: tested invalid (out of the race: its cost is never needed)
    # rbuf[:m]: the candidates with a cost, by (cost or bound, vertex); walked once: an invalid candidate
    # is passed, one made exact moves on to its place (its cost only grows)
    m = 0
    for i in range(n):
        if cbuf[i] > -np.inf:
            rbuf[m] = i
            m += 1
    _order_by_cost(cbuf, wbuf, rbuf, m)
    p = 0
    while p < m:
        k = rbuf[p]
        if not cbuf[k] > -np.inf:
            p += 1
            continue
        if obuf[k] == 0:
            if not _can_collapse(u, wbuf[k], P, tris, arena, start, length, mark, stampbox, shape_eps):
                obuf[k] = 2
                p += 1
                continue
            obuf[k] = 1
        if not exact and not dbuf[k]:
            cbuf[k] = qbuf[k] + wt * _carried_gap2(
                wbuf[k], P, sa, sb, n, geo, pxyz, ps, pst, seg, npts, tri, np.inf
            )
            dbuf[k] = True
            q = p
            while q + 1 < m and (
                cbuf[rbuf[q + 1]] < cbuf[k] or (cbuf[rbuf[q + 1]] == cbuf[k] and wbuf[rbuf[q + 1]] < wbuf[k])
            ):
                rbuf[q] = rbuf[q + 1]
                q += 1
            rbuf[q] = k
            continue
        return wbuf[k], cbuf[k], emin, ew
    return -1, np.inf, emin, ew


@leaf
def _cheapest(cbuf, wbuf, n, last_c, last_w):
    """Index of the smallest (cost, vertex) after (last_c, last_w) (-1 when none)."""
    bk = -1
    for i in range(n):
        c = cbuf[i]
        w = wbuf[i]
        if (c > last_c or (c == last_c and w > last_w)) and (
            bk < 0 or c < cbuf[bk] or (c == cbuf[bk] and w < wbuf[bk])
        ):
            bk = i
    return bk


@leaf
def _bound(u, P, tris, Q, W, selfq, arena, su, n, wbuf, cbuf):
    """The quadric part of :func:`_evaluate` alone: ``(w, c, emin, ew)`` with c the smallest quadric cost
    of u's collapses (onto w), a lower bound of its cheapest full cost (the vertical term is >= 0)."""
    emin, ew = _quadric_costs(u, P, tris, Q, W, selfq, arena, su, n, wbuf, cbuf)
    k0 = _cheapest(cbuf, wbuf, n, -np.inf, -1)
    if k0 < 0:
        return -1, np.inf, emin, ew
    return wbuf[k0], cbuf[k0], emin, ew


# -- the simplifier --------------------------------------------------------------------------------------
@jit
def _grow_rows(a, n):
    out = np.empty((max(2 * a.shape[0], n),) + a.shape[1:], a.dtype)
    out[: a.shape[0]] = a
    return out


@jit
def _grow(a, n):
    out = np.empty(max(2 * a.shape[0], n), a.dtype)
    out[: a.shape[0]] = a
    return out


@jit
def qem_simplify(P, tris, alive, kind, tri_block, vert_block, target, shape_eps, vweight, Q0, W0):
    """Half-edge QEM collapses until every sub-block is down to its target triangle count.

    Parameters
    ----------
    P : (N, 3) float64
        Vertex positions, metres, in a local frame (centred: quadrics lose precision far from 0).
    tris : (M, 3) int32
        Triangles, counter-clockwise in xy; modified in place to the base (most simplified) state.
    alive : (M,) bool
        Live slots; modified in place.
    kind : (N,) uint8
        FREE or LOCKED.
    tri_block, vert_block : (M,) int32, (N,) int32
        Sub-block of each triangle and of each FREE vertex (all its triangles are in that block).
    target : (B,) int64
        Stop collapsing in block b once it has at most ``target[b]`` live triangles.
    shape_eps : float
        Orientation tolerance of rewritten triangles (see the module docstring), dimensionless.
    vweight : float
        Weight of the vertical term (see the module docstring), dimensionless; 0: the quadric alone.
    Q0, W0 : (N, 10), (N,) float64, or (0, 10), (0,)
        The initial quadrics and areas (:func:`plane_quadrics`), copied; empty: those of ``tris``. A
        sub-block simplified on its own (:func:`terralod.tin.qem.simplify`) passes the quadrics of the
        whole TIN, so a seam vertex starts with the planes of its triangles in every sub-block.

    Returns
    -------
    n, cu, cv, cblock, cmmqe, ccost, mmqe0, del_slot, del_tri, rep_ptr, rep_slot, rep_old, rep_new
        n collapses in the order performed; collapse i removed ``cu[i]`` onto ``cv[i]`` in block
        ``cblock[i]``, after which that block's MMQE was ``cmmqe[i]`` (m²) and its cost was ``ccost[i]``
        (m⁴); ``mmqe0`` (B,) is each block's MMQE before any collapse. Collapse i deleted slots
        ``del_slot[2i : 2i+2]`` (triples ``del_tri``) and rewrote slots
        ``rep_slot[rep_ptr[i] : rep_ptr[i+1]]`` from ``rep_old`` to ``rep_new``.
    """
    n_v = P.shape[0]
    n_b = target.shape[0]
    arena, start, length, cap, top = _build_stars(tris, alive, n_v)
    if Q0.shape[0] == n_v:
        Q = Q0.copy()
        W = W0.copy()
    else:
        Q, W = plane_quadrics(P, tris, alive)
    selfq = np.empty(n_v, np.float64)  # Q_w(P_w): the half of a collapse cost that depends on w only
    for w in range(n_v):
        selfq[w] = _quadric_at(Q, w, P[w, 0], P[w, 1], P[w, 2])
    mark = np.zeros(n_v, np.int64)  # stamps of the link test
    seen = np.zeros(n_v, np.int64)  # collapse number + 1 of the last ring visit
    nearu = np.zeros(n_v, np.int64)  # collapse number + 1 when in ring(u) of that collapse
    stampbox = np.zeros(1, np.int64)
    wbuf = np.empty(n_v, np.int64)
    cbuf = np.empty(n_v, np.float64)
    head = np.full(tris.shape[0], -1, np.int64)  # first removed vertex held by each slot (vertical term)
    nxt = np.full(n_v, -1, np.int64)
    pbuf = np.empty(n_v, np.int64)
    pslot = np.empty(n_v, np.int64)
    dbuf = np.zeros(n_v, np.bool_)
    qbuf = np.zeros(n_v, np.float64)
    ctx = (P, tris, Q, W, selfq, head, nxt, shape_eps, vweight)  # what _evaluate reads
    sa = np.empty(n_v, np.int64)  # star(u) as fans (u, sa[i], sb[i]), gathered for the vertical term
    sb = np.empty(n_v, np.int64)
    geo = np.empty((n_v, 6), np.float64)
    pxyz = np.empty((n_v, 3), np.float64)  # points re-measured by the vertical term, their star slot
    ps = np.empty(n_v, np.int64)
    tri = np.empty((n_v, 7), np.float64)
    obuf = np.empty(n_v, np.int64)  # candidates in increasing bound order
    rbuf = np.empty(n_v, np.int64)  # the collapse test's walk over the candidates
    pst = np.empty(n_v + 1, np.int64)
    seg = np.empty((n_v, 5), np.float64)
    work = (
        mark,
        stampbox,
        wbuf,
        cbuf,
        dbuf,
        qbuf,
        obuf,
        sa,
        sb,
        geo,
        pxyz,
        ps,
        pst,
        seg,
        tri,
        rbuf,
    )  # its scratch

    count = np.zeros(n_b, np.int64)  # live triangles per block
    for t in range(tris.shape[0]):
        if alive[t]:
            count[tri_block[t]] += 1
    removed = np.zeros(n_v, np.bool_)
    best = np.full(n_v, -1, np.int64)  # best valid target (-1: none)
    bestc = np.full(n_v, np.inf)  # its cost, m⁴
    emin = np.zeros(n_v, np.float64)
    eminw = np.full(n_v, -1, np.int64)  # the neighbour that gives emin
    cheapest = np.ones(n_v, np.bool_)  # best is the cheapest collapse, untested (False: the cheapest valid)
    lazy = vweight > 0.0  # queue lower bounds (the quadric alone); the vertical term when popped
    exact = np.zeros(n_v, np.bool_)  # bestc is the full cost (False: the quadric's lower bound)
    esum = np.zeros(n_b, np.float64)  # Σ emin over the block's live FREE vertices
    ecnt = np.zeros(n_b, np.int64)

    # Heap of every FREE vertex's cheapest collapse, untested (the test runs when it leaves the heap).
    hk = np.empty(n_v, np.float64)
    hv = np.empty(n_v, np.int64)
    hpos = np.full(n_v, -1, np.int64)
    hsize = 0
    for u in range(n_v):
        if kind[u] != FREE or length[u] == 0:
            continue
        if lazy:
            v, c, e, eminw[u] = _bound(u, P, tris, Q, W, selfq, arena, start[u], length[u], wbuf, cbuf)
        else:
            v, c, e, eminw[u] = _evaluate(u, -1, np.inf, False, arena, start, length, ctx, work)
            exact[u] = True
        b = vert_block[u]
        emin[u] = e
        esum[b] += e
        ecnt[b] += 1
        best[u] = v
        bestc[u] = c
        if v >= 0:
            hsize = _heap_set(hk, hv, hpos, hsize, c, u)
    mmqe0 = np.zeros(n_b, np.float64)
    for b in range(n_b):
        mmqe0[b] = esum[b] / ecnt[b] if ecnt[b] > 0 else 0.0

    # Records, sized for the usual case and grown on demand.
    cu = np.empty(n_v, np.int32)
    cv = np.empty(n_v, np.int32)
    cblock = np.empty(n_v, np.int32)
    cmmqe = np.empty(n_v, np.float64)
    ccost = np.empty(n_v, np.float64)
    del_slot = np.empty(2 * n_v, np.int32)
    del_tri = np.empty((2 * n_v, 3), np.int32)
    rep_ptr = np.zeros(n_v + 1, np.int64)
    rcap = 6 * n_v + 16
    rep_slot = np.empty(rcap, np.int32)
    rep_old = np.empty((rcap, 3), np.int32)
    rep_new = np.empty((rcap, 3), np.int32)
    nc = 0
    nr = 0

    while hsize > 0:
        cost = hk[0]
        u = hv[0]
        hsize = _heap_remove(hk, hv, hpos, hsize, u)
        b = vert_block[u]
        if count[b] <= target[b]:
            continue  # this block is done
        if not exact[u]:
            # a lower bound left the heap: its full cost now (the cheapest collapse, untested), and back in
            # the heap unless it still comes first (every other key is a lower bound of its own cost, so
            # the collapses leave in the order of full costs queued at once)
            v2, c2, _, _ = _evaluate(u, -1, np.inf, False, arena, start, length, ctx, work)
            exact[u] = True
            best[u] = v2
            bestc[u] = c2
            if v2 < 0:
                continue
            if hsize > 0 and _before(hk[0], hv[0], c2, u):
                hsize = _heap_set(hk, hv, hpos, hsize, c2, u)
                continue
            cost = c2
        v = best[u]
        if not _can_collapse(u, v, P, tris, arena, start, length, mark, stampbox, shape_eps):
            # The neighbourhood changed since u was evaluated: evaluate again, requeue.
            v2, c2, e2, eminw[u] = _evaluate(u, -1, np.inf, True, arena, start, length, ctx, work)
            esum[b] += e2 - emin[u]
            emin[u] = e2
            best[u] = v2
            bestc[u] = c2
            cheapest[u] = False
            exact[u] = True
            if v2 >= 0:
                hsize = _heap_set(hk, hv, hpos, hsize, c2, u)
            continue

        # -- perform the collapse u → v --------------------------------------------------------------
        need = nr + length[u]
        if need > rep_slot.shape[0]:
            rep_slot = _grow(rep_slot, need)
            rep_old = _grow_rows(rep_old, need)
            rep_new = _grow_rows(rep_new, need)
        nd = 2 * nc
        su = start[u]
        for i in range(length[u]):
            nearu[_next_after(tris, arena[su + i], u)] = nc + 1  # ring(u): their stars change
        npb = 0
        if vweight > 0.0:
            pbuf[0] = u
            npb = 1
            pslot[0] = -1  # the slot each point was carried by (u: none)
            for i in range(length[u]):
                n0 = npb
                npb = _take_list(head, nxt, arena[su + i], pbuf, npb)
                for k in range(n0, npb):
                    pslot[k] = arena[su + i]
        for i in range(length[u]):
            t = arena[su + i]
            a0 = tris[t, 0]
            a1 = tris[t, 1]
            a2 = tris[t, 2]
            if a0 == v or a1 == v or a2 == v:
                # deleted: drop from the stars of its two other vertices
                del_slot[nd] = t
                del_tri[nd, 0] = a0
                del_tri[nd, 1] = a1
                del_tri[nd, 2] = a2
                nd += 1
                alive[t] = False
                for k in range(3):
                    w = tris[t, k]
                    if w != u:
                        _star_remove(arena, start, length, w, t)
            else:
                rep_slot[nr] = t
                rep_old[nr, 0] = a0
                rep_old[nr, 1] = a1
                rep_old[nr, 2] = a2
                for k in range(3):
                    if tris[t, k] == u:
                        tris[t, k] = v
                rep_new[nr, 0] = tris[t, 0]
                rep_new[nr, 1] = tris[t, 1]
                rep_new[nr, 2] = tris[t, 2]
                nr += 1
                arena, top = _star_add(arena, start, length, cap, top, v, t)
        if vweight > 0.0:
            for k in range(npb):
                q = pbuf[k]
                bsl = -1
                bm = -np.inf
                t = pslot[k]
                if t >= 0 and alive[t]:  # its slot, rewritten, most often still holds it
                    _, _, m = _bary_xy(P, tris[t, 0], tris[t, 1], tris[t, 2], P[q, 0], P[q, 1])
                    if m > _INSIDE:
                        nxt[q] = head[t]
                        head[t] = q
                        continue
                for j in range(rep_ptr[nc], nr):
                    t = rep_slot[j]
                    _, _, m = _bary_xy(P, tris[t, 0], tris[t, 1], tris[t, 2], P[q, 0], P[q, 1])
                    if m > bm:
                        bm = m
                        bsl = t
                        if m > _INSIDE:
                            break  # inside with a margin: no other triangle of the fan can hold it
                if bsl >= 0:
                    nxt[q] = head[bsl]
                    head[bsl] = q
        length[u] = 0
        removed[u] = True
        for k in range(10):
            Q[v, k] += Q[u, k]
        W[v] += W[u]
        selfq[v] = _quadric_at(Q, v, P[v, 0], P[v, 1], P[v, 2])
        count[b] -= 2
        esum[b] -= emin[u]
        ecnt[b] -= 1
        emin[u] = 0.0
        rep_ptr[nc + 1] = nr

        # Re-evaluate v and its ring (their costs to v changed with Q_v, their rings with the collapse).
        sv = start[v]
        nv = length[v]
        for i in range(nv + 1):
            if i < nv:
                t = arena[sv + i]
                w = _next_after(tris, t, v)
                w2 = _next_after(tris, t, w)
            else:
                w = v
                w2 = v
            for x in (w, w2):
                if kind[x] != FREE or removed[x] or seen[x] == nc + 1:
                    continue
                seen[x] = nc + 1
                bx = vert_block[x]
                if x != v and nearu[x] != nc + 1 and best[x] != v:
                    # star(x) and what its slots carry did not change, only Q_v grew: x -> v got dearer,
                    # the other costs stand, so x's best collapse stands (and a collapse of x that was
                    # invalid stays so: v's ring only grew); only x's MMQE term moves, through x -> v alone
                    # unless that was its minimum
                    if eminw[x] == v:
                        ex, eminw[x] = _quadric_costs(
                            x, P, tris, Q, W, selfq, arena, start[x], length[x], wbuf, cbuf
                        )
                    else:
                        ex = _emin_through(x, v, _collapse_cost(Q, P, x, v), W, emin, eminw)
                    esum[bx] += ex - emin[x]
                    emin[x] = ex
                    continue
                if (
                    not vweight > 0.0
                    and x != v
                    and cheapest[x]
                    and best[x] >= 0
                    and best[x] != u
                    and best[x] != v
                ):
                    if eminw[x] != u and eminw[x] != v:
                        # quadric alone, x in ring(u): x lost u and has v, whose quadric grew; its other
                        # costs stand, so its cheapest collapse is the old one or x -> v
                        c = _collapse_cost(Q, P, x, v)
                        ex = _emin_through(x, v, c, W, emin, eminw)
                        esum[bx] += ex - emin[x]
                        emin[x] = ex
                        if _before(c, v, bestc[x], best[x]):
                            best[x] = v
                            bestc[x] = c
                            hsize = _heap_set(hk, hv, hpos, hsize, c, x)
                        continue
                if lazy:
                    vx, cx, ex, eminw[x] = _bound(
                        x, P, tris, Q, W, selfq, arena, start[x], length[x], wbuf, cbuf
                    )
                    exact[x] = False
                else:
                    vx, cx, ex, eminw[x] = _evaluate(
                        x, best[x], bestc[x], False, arena, start, length, ctx, work
                    )
                esum[bx] += ex - emin[x]
                emin[x] = ex
                cheapest[x] = True
                if vx == best[x] and cx == bestc[x]:
                    continue  # same best collapse: its heap entry stands
                best[x] = vx
                bestc[x] = cx
                if vx >= 0:
                    hsize = _heap_set(hk, hv, hpos, hsize, cx, x)
                else:
                    hsize = _heap_remove(hk, hv, hpos, hsize, x)
        cu[nc] = u
        cv[nc] = v
        cblock[nc] = b
        ccost[nc] = cost
        cmmqe[nc] = max(esum[b], 0.0) / ecnt[b] if ecnt[b] > 0 else 0.0
        nc += 1

    return (
        nc,
        cu[:nc].copy(),
        cv[:nc].copy(),
        cblock[:nc].copy(),
        cmmqe[:nc].copy(),
        ccost[:nc].copy(),
        mmqe0,
        del_slot[: 2 * nc].copy(),
        del_tri[: 2 * nc].copy(),
        rep_ptr[: nc + 1].copy(),
        rep_slot[:nr].copy(),
        rep_old[:nr].copy(),
        rep_new[:nr].copy(),
    )


# -- measured error of the collapses ---------------------------------------------------------------------
@leaf
def _slot_height(P, T, s, px, py):
    """(m, z): the smallest barycentric coordinate of (px, py) in slot s's xy triangle ``T[s]``
    (:func:`_bary_xy`) and the height of the triangle's plane there, metres."""
    a = T[s, 0]
    b = T[s, 1]
    d = T[s, 2]
    l1, l2, m = _bary_xy(P, a, b, d, px, py)
    return m, (1.0 - l1 - l2) * P[a, 2] + l1 * P[b, 2] + l2 * P[d, 2]


@jit
def collapse_vertical_errors(P, tris, cu, del_slot, rep_ptr, rep_slot, rep_new):
    """Max vertical distance between the vertices each collapse (and the ones before it) removed and the
    surface it left, over the region it changed.

    Replays the collapses from the full TIN, keeping every removed vertex in the list of the live slot
    whose xy triangle holds it. Collapse i (``cu[i]`` removed; slots ``del_slot[2i : 2i+2]`` deleted,
    ``rep_slot[rep_ptr[i] : rep_ptr[i+1]]`` rewritten to ``rep_new``) gathers ``cu[i]`` and the vertices
    of the slots it deleted or rewrote, puts each in the rewritten slot that holds it (the largest smallest
    barycentric coordinate, so a vertex on an edge or outside by rounding still gets one) and measures
    |z - z_surface| there. The rewritten slots cover star(u)'s region, so no vertex is lost.

    Parameters
    ----------
    P : (N, 3) float64 world metres. tris : (S, 3) int32, every slot at full resolution (not modified).
    cu : (C,) int32. del_slot : (2C,) int32. rep_ptr : (C+1,) int64. rep_slot : (R,), rep_new : (R, 3) int32.

    Returns
    -------
    (C,) float64
        e[i]: max over the vertices gathered by collapse i of their vertical distance to the surface just
        after it, metres. With the running maximum per sub-block this bounds the max vertical error of
        every intermediate mesh against the input vertices from above (the vertices collapse i did not
        gather keep their distance).
    """
    n_v = P.shape[0]
    T = tris.copy()
    head = np.full(T.shape[0], -1, np.int64)  # first vertex held by each slot
    nxt = np.full(n_v, -1, np.int64)  # next vertex in the same slot
    buf = np.empty(n_v, np.int64)
    src = np.empty(n_v, np.int64)  # the rewritten slot that held buf[k] before the collapse, or -1
    c = cu.shape[0]
    out = np.zeros(c, np.float64)
    for i in range(c):
        n = 0
        buf[0] = cu[i]
        n = 1
        for j in range(2):
            n = _take_list(head, nxt, del_slot[2 * i + j], buf, n)
        for k in range(n):
            src[k] = -1
        r0 = rep_ptr[i]
        r1 = rep_ptr[i + 1]
        for j in range(r0, r1):
            s = rep_slot[j]
            n0 = n
            n = _take_list(head, nxt, s, buf, n)
            for k in range(n0, n):
                src[k] = s
            _set_row(T, s, rep_new, j)
        e = 0.0
        for k in range(n):
            p = buf[k]
            px = P[p, 0]
            py = P[p, 1]
            best = -np.inf
            bs = -1
            bz = 0.0
            s = src[k]
            if s >= 0:  # its slot, rewritten, most often still holds it (then no other one can: _INSIDE)
                m, z = _slot_height(P, T, s, px, py)
                if m > _INSIDE:
                    best = m
                    bs = s
                    bz = z
            for j in range(r0, r1 if bs < 0 else r0):
                s = rep_slot[j]
                m, z = _slot_height(P, T, s, px, py)
                if m > best:
                    best = m
                    bs = s
                    bz = z
                    if m > _INSIDE:
                        break
            if bs < 0:
                continue
            dz = abs(P[p, 2] - bz)
            if dz > e:
                e = dz
            nxt[p] = head[bs]
            head[bs] = p
        out[i] = e
    return out


# -- edge topology of a triangle list ---------------------------------------------------------------------
@jit
def edge_topology(tris, n_v):
    """Directed edges of triangles (a → b for each consecutive pair of a triple), counted per vertex.

    Returns ``(repeated, outline)``: ``repeated`` True when some directed edge occurs twice (an inconsistent
    or non-manifold triangulation: with every directed edge once, no undirected edge has more than two
    triangles); ``outline`` (n_v,) bool, the vertices of an edge used by a single triangle (either
    direction counted). O(sum of squared vertex degrees), one pass over a CSR of the out-edges.
    """
    m = tris.shape[0]
    ptr = np.zeros(n_v + 1, np.int64)
    for t in range(m):
        for k in range(3):
            ptr[tris[t, k] + 1] += 1
    for a in range(n_v):
        ptr[a + 1] += ptr[a]
    fill = ptr[:-1].copy()
    dst = np.empty(3 * m, np.int64)
    for t in range(m):
        for k in range(3):
            a = tris[t, k]
            dst[fill[a]] = tris[t, (k + 1) % 3]
            fill[a] += 1
    repeated = False
    outline = np.zeros(n_v, np.bool_)
    for a in range(n_v):
        for i in range(ptr[a], ptr[a + 1]):
            b = dst[i]
            cnt = 0
            for j in range(ptr[a], ptr[a + 1]):
                if dst[j] == b:
                    cnt += 1
            if cnt > 1:
                repeated = True
            for j in range(ptr[b], ptr[b + 1]):
                if dst[j] == a:
                    cnt += 1
            if cnt == 1:
                outline[a] = True
                outline[b] = True
    return repeated, outline


@jit
def block_corner_bounds(P, tris, tri_block, n_blocks):
    """Per sub-block, the min and max of each coordinate over its triangles' corners ((B, 3) each; +inf /
    -inf for a block with no triangle), and per vertex the smallest and largest block of its triangles
    ((V,) int64 each; int32 max / -1 for an unused vertex). One pass (numpy's ``ufunc.at`` took seconds)."""
    n_v = P.shape[0]
    lo = np.full((n_blocks, 3), np.inf)
    hi = np.full((n_blocks, 3), -np.inf)
    bmin = np.full(n_v, np.iinfo(np.int32).max, np.int64)
    bmax = np.full(n_v, -1, np.int64)
    for t in range(tris.shape[0]):
        b = tri_block[t]
        for k in range(3):
            w = tris[t, k]
            for d in range(3):
                x = P[w, d]
                if x < lo[b, d]:
                    lo[b, d] = x
                if x > hi[b, d]:
                    hi[b, d] = x
            if b < bmin[w]:
                bmin[w] = b
            if b > bmax[w]:
                bmax[w] = b
    return lo, hi, bmin, bmax
