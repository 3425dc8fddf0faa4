"""Adaptive TIN of one tile window by greedy insertion of the worst sample (numba kernels).

Source: Garland & Heckbert, "Fast polygonal approximation of terrains and height fields" (CMU-CS-95-181,
1995), the greedy insertion algorithm III that mapbox/delatin implements (no paper of ../shared/papers);
the recipe here is Delatin's: a Delaunay triangulation refined by inserting, into the triangle of largest
vertical error, its worst sample, until every triangle is within the target; each triangle keeps its
worst sample (found by rasterising it once, when it is made) in a max-heap.

Frame: window-local integer coordinates, x = column (east), y = row (south); a window has h x w samples.
Triangles are kept counter-clockwise in that (x, y) frame (positive cross product); the caller flips
them to counter-clockwise seen from above (x east, y north). Coordinates are small integers, so the two
predicates (orientation, in-circle) are exact in int64: no fold-over, no precision trap.

Deviations from Delatin, and why:

1. The window's border is fixed in advance: the four sides' vertices come from a 1-D simplification of
   each side's line of samples (:func:`simplify_line`), inserted first, and the samples on the border are
   never candidates. Two tiles sharing a side compute it from the same samples alone, so they share their
   border vertices bit for bit and never crack (the runtime stitches across levels).
2. Invalid samples (nodata) are never candidates and never measured.
3. Triangles whose worst sample is within the target are not queued at all (they are only looked at
   again when a flip or split remakes them).

Topology (half-edges, Delaunator's layout): triangle t owns half-edges 3t, 3t + 1, 3t + 2; half-edge e
runs from ``tri[e]`` to ``tri[next(e)]``; ``half[e]`` is the opposite half-edge or -1 on the border.

Edge flip (the one topology change besides splits), the edge u-v of A = (u, v, w) and B = (v, u, q)::

          w                    w
         / \\                 /|\\
        /   \\               / | \\
       u --- v     ->      u  |  v
        \\ A /              \\ | /
         \\B/                \\|/
          q                    q
"""

from __future__ import annotations

import numpy as np

from terralod.kernels import jit, leaf


# -- 1-D: the shared border --------------------------------------------------------------------------------
@jit
def simplify_line(z, ok, target):
    """Samples kept on a line (sorted indices, both ends included): every segment between kept samples has
    max vertical error <= target over its ok samples (split at the first worst sample otherwise).

    The result does not depend on the order segments are split in (each is split on its own samples), so
    it is a function of the line's samples and the target alone.
    """
    n = z.shape[0]
    keep = np.zeros(n, np.bool_)
    keep[0] = True
    keep[n - 1] = True
    stack = np.empty(2 * n + 2, np.int64)
    sp = 0
    stack[0] = 0
    stack[1] = n - 1
    sp = 2
    while sp > 0:
        b = stack[sp - 1]
        a = stack[sp - 2]
        sp -= 2
        if b - a < 2:
            continue
        za = np.float64(z[a])
        slope = (np.float64(z[b]) - za) / (b - a)
        worst = -1
        best = target
        for i in range(a + 1, b):
            if not ok[i]:
                continue
            e = abs(np.float64(z[i]) - (za + slope * (i - a)))
            if e > best:
                best = e
                worst = i
        if worst >= 0:
            keep[worst] = True
            stack[sp] = a
            stack[sp + 1] = worst
            stack[sp + 2] = worst
            stack[sp + 3] = b
            sp += 4
    return np.flatnonzero(keep)


# -- predicates (exact: int64 on small integer coordinates) ----------------------------------------------
@leaf
def _orient(ax, ay, bx, by, cx, cy):
    """Twice the signed area of (a, b, c): > 0 counter-clockwise in the (x, y) frame."""
    return (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)


@leaf
def _in_circle(ax, ay, bx, by, cx, cy, px, py):
    """True when p lies strictly inside the circumcircle of the counter-clockwise triangle (a, b, c)."""
    adx = ax - px
    ady = ay - py
    bdx = bx - px
    bdy = by - py
    cdx = cx - px
    cdy = cy - py
    al = adx * adx + ady * ady
    bl = bdx * bdx + bdy * bdy
    cl = cdx * cdx + cdy * cdy
    return adx * (bdy * cl - cdy * bl) - ady * (bdx * cl - cdx * bl) + al * (bdx * cdy - bdy * cdx) > 0


@leaf
def _nxt(e):
    return e - e % 3 + (e % 3 + 1) % 3


@leaf
def _prv(e):
    return e - e % 3 + (e % 3 + 2) % 3


# -- the heap of triangles by worst error ----------------------------------------------------------------
@leaf
def _heap_less(err, heap, i, j):
    """Heap order: larger error first, then smaller triangle id (deterministic ties)."""
    a = heap[i]
    b = heap[j]
    return err[a] > err[b] or (err[a] == err[b] and a < b)


@leaf
def _heap_swap(heap, pos, i, j):
    a = heap[i]
    b = heap[j]
    heap[i] = b
    heap[j] = a
    pos[b] = i
    pos[a] = j


@leaf
def _heap_up(err, heap, pos, i):
    while i > 0:
        p = (i - 1) >> 1
        if not _heap_less(err, heap, i, p):
            break
        _heap_swap(heap, pos, i, p)
        i = p


@leaf
def _heap_down(err, heap, pos, i, n):
    while True:
        left = 2 * i + 1
        if left >= n:
            break
        j = left
        if left + 1 < n and _heap_less(err, heap, left + 1, left):
            j = left + 1
        if not _heap_less(err, heap, j, i):
            break
        _heap_swap(heap, pos, i, j)
        i = j


@leaf
def _heap_remove(err, heap, pos, n, t):
    """Remove triangle t (in the heap) from a heap of n entries; returns the new size."""
    i = pos[t]
    n -= 1
    pos[t] = -1
    if i == n:
        return n
    last = heap[n]
    heap[i] = last
    pos[last] = i
    _heap_up(err, heap, pos, i)
    _heap_down(err, heap, pos, pos[last], n)
    return n


# -- the mesh ----------------------------------------------------------------------------------------------
@leaf
def _link(half, e, h):
    half[e] = h
    if h >= 0:
        half[h] = e


@leaf
def _set_tri(tri, half, pending, npend, t, a, b, c, ha, hb, hc):
    """(Re)make triangle t = (a, b, c) with opposite half-edges (ha, hb, hc); queue it for a candidate."""
    tri[3 * t] = a
    tri[3 * t + 1] = b
    tri[3 * t + 2] = c
    _link(half, 3 * t, ha)
    _link(half, 3 * t + 1, hb)
    _link(half, 3 * t + 2, hc)
    pending[npend] = t
    return npend + 1


@leaf
def _candidate(z, valid, w, h, px, py, a, b, c):
    """Worst interior sample of the counter-clockwise triangle (a, b, c): (error, x, y); error -1 when it
    covers no candidate sample. Border samples (x = 0, w - 1 or y = 0, h - 1) are not candidates."""
    ax, ay, bx, by, cx, cy = px[a], py[a], px[b], py[b], px[c], py[c]
    za = np.float64(z[ay, ax])
    zb = np.float64(z[by, bx])
    zc = np.float64(z[cy, cx])
    # plane z = za + gx (x - ax) + gy (y - ay)
    d = np.float64(_orient(ax, ay, bx, by, cx, cy))
    ux = np.float64(bx - ax)
    uy = np.float64(by - ay)
    vx = np.float64(cx - ax)
    vy = np.float64(cy - ay)
    gx = ((zb - za) * vy - (zc - za) * uy) / d
    gy = ((zc - za) * ux - (zb - za) * vx) / d
    y0 = max(min(ay, by, cy), 1)
    y1 = min(max(ay, by, cy), h - 2)
    xa = max(min(ax, bx, cx), 1)
    xb = min(max(ax, bx, cx), w - 2)
    best = -1.0
    bxo = -1
    byo = -1
    # per edge e0 -> e1, inside is A x <= B with A = ey1 - ey0, B = (ex1 - ex0) (y - ey0) + A ex0 (exact
    # integers); B is carried from row to row
    a0, a1, a2 = by - ay, cy - by, ay - cy
    d0, d1, d2 = bx - ax, cx - bx, ax - cx
    b0 = d0 * (y0 - ay) + a0 * ax
    b1 = d1 * (y0 - by) + a1 * bx
    b2 = d2 * (y0 - cy) + a2 * cx
    for y in range(y0, y1 + 1):
        # the covered run of this row: [xa, xb] clipped by the three half-planes
        x0 = xa
        x1 = xb
        if a0 > 0:
            x1 = min(x1, b0 // a0)
        elif a0 < 0:
            x0 = max(x0, -(b0 // -a0))  # ceil(b0 / a0)
        elif b0 < 0:
            x1 = x0 - 1
        if a1 > 0:
            x1 = min(x1, b1 // a1)
        elif a1 < 0:
            x0 = max(x0, -(b1 // -a1))
        elif b1 < 0:
            x1 = x0 - 1
        if a2 > 0:
            x1 = min(x1, b2 // a2)
        elif a2 < 0:
            x0 = max(x0, -(b2 // -a2))
        elif b2 < 0:
            x1 = x0 - 1
        b0 += d0
        b1 += d1
        b2 += d2
        base = za + gy * (y - ay) - gx * ax
        for x in range(x0, x1 + 1):
            if not valid[y, x]:
                continue
            e = abs(np.float64(z[y, x]) - (base + gx * x))
            if e > best and not ((x == ax and y == ay) or (x == bx and y == by) or (x == cx and y == cy)):
                best = e
                bxo = x
                byo = y
    return best, bxo, byo


@leaf
def _legalize(tri, half, px, py, pending, npend, stack, e0):
    """Lawson flips from half-edge e0 until every edge around is locally Delaunay; returns npend."""
    sp = 0
    stack[sp] = e0
    sp += 1
    while sp > 0:
        sp -= 1
        e = stack[sp]
        b = half[e]
        if b < 0:
            continue
        ta = e // 3
        tb = b // 3
        u = tri[e]
        v = tri[_nxt(e)]
        w = tri[_prv(e)]
        q = tri[_prv(b)]
        if not _in_circle(px[u], py[u], px[v], py[v], px[w], py[w], px[q], py[q]):
            continue
        ha1 = half[_nxt(e)]
        ha2 = half[_prv(e)]
        hb1 = half[_nxt(b)]
        hb2 = half[_prv(b)]
        npend = _set_tri(tri, half, pending, npend, ta, w, u, q, ha2, hb1, -1)
        npend = _set_tri(tri, half, pending, npend, tb, q, v, w, hb2, ha1, 3 * ta + 2)
        stack[sp] = 3 * ta + 1
        stack[sp + 1] = 3 * tb
        sp += 2
    return npend


@leaf
def _split_edge(tri, half, px, py, pending, npend, stack, nt, e, p):
    """Insert p on half-edge e (and its opposite, if any); returns (npend, nt)."""
    b = half[e]
    ta = e // 3
    u = tri[e]
    v = tri[_nxt(e)]
    w = tri[_prv(e)]
    ha1 = half[_nxt(e)]
    ha2 = half[_prv(e)]
    a2 = nt
    nt += 1
    npend = _set_tri(tri, half, pending, npend, ta, w, u, p, ha2, -1, -1)
    npend = _set_tri(tri, half, pending, npend, a2, w, p, v, 3 * ta + 2, -1, ha1)
    if b >= 0:
        tb = b // 3
        q = tri[_prv(b)]
        hb1 = half[_nxt(b)]
        hb2 = half[_prv(b)]
        b2 = nt
        nt += 1
        npend = _set_tri(tri, half, pending, npend, tb, q, v, p, hb2, 3 * a2 + 1, -1)
        npend = _set_tri(tri, half, pending, npend, b2, q, p, u, 3 * tb + 2, 3 * ta + 1, hb1)
        npend = _legalize(tri, half, px, py, pending, npend, stack, 3 * tb)
        npend = _legalize(tri, half, px, py, pending, npend, stack, 3 * b2 + 2)
    npend = _legalize(tri, half, px, py, pending, npend, stack, 3 * ta)
    npend = _legalize(tri, half, px, py, pending, npend, stack, 3 * a2 + 2)
    return npend, nt


@leaf
def _split_triangle(tri, half, px, py, pending, npend, stack, nt, t, p):
    """Insert p strictly inside triangle t; returns (npend, nt)."""
    a = tri[3 * t]
    b = tri[3 * t + 1]
    c = tri[3 * t + 2]
    h0 = half[3 * t]
    h1 = half[3 * t + 1]
    h2 = half[3 * t + 2]
    t1 = nt
    t2 = nt + 1
    nt += 2
    npend = _set_tri(tri, half, pending, npend, t, a, b, p, h0, -1, -1)
    npend = _set_tri(tri, half, pending, npend, t1, b, c, p, h1, -1, 3 * t + 1)
    npend = _set_tri(tri, half, pending, npend, t2, c, a, p, h2, 3 * t + 2, 3 * t1 + 1)
    npend = _legalize(tri, half, px, py, pending, npend, stack, 3 * t)
    npend = _legalize(tri, half, px, py, pending, npend, stack, 3 * t1)
    npend = _legalize(tri, half, px, py, pending, npend, stack, 3 * t2)
    return npend, nt


@leaf
def _insert(tri, half, px, py, pending, npend, stack, nt, t, p):
    """Insert vertex p, inside or on the border of triangle t; returns (npend, nt)."""
    for k in range(3):
        e = 3 * t + k
        a = tri[e]
        b = tri[_nxt(e)]
        if _orient(px[a], py[a], px[b], py[b], px[p], py[p]) == 0:
            return _split_edge(tri, half, px, py, pending, npend, stack, nt, e, p)
    return _split_triangle(tri, half, px, py, pending, npend, stack, nt, t, p)


@leaf
def _border_edge(tri, half, px, py, nt, x, y):
    """A triangle with a border half-edge whose segment holds (x, y) strictly inside, or -1."""
    for e in range(3 * nt):
        if half[e] >= 0:
            continue
        a = tri[e]
        b = tri[_nxt(e)]
        if _orient(px[a], py[a], px[b], py[b], x, y) != 0:
            continue
        if min(px[a], px[b]) <= x <= max(px[a], px[b]) and min(py[a], py[b]) <= y <= max(py[a], py[b]):
            if not ((px[a] == x and py[a] == y) or (px[b] == x and py[b] == y)):
                return e
    return -1


@jit
def _grow(a, n):
    out = np.empty(n, a.dtype)
    out[: a.shape[0]] = a
    return out


@jit
def tin_window(z, valid, bx, by, target, max_vertices):
    """Greedy-insertion TIN of an (h, w) window with a fixed border.

    Parameters
    ----------
    z : (h, w) float, elevations (metres); valid : (h, w) bool, candidate and measured samples
    bx, by : (B,) int64, border vertices other than the 4 corners (x = col, y = row), each on a side
    target : max vertical error (metres) every triangle is refined to over its interior valid samples
    max_vertices : stop after this many vertices (h * w or more: no cap)

    Returns
    -------
    px, py : (N,) int64 vertex columns and rows; tris : (K, 3) int32, counter-clockwise in (x, y);
    max_error : the largest vertical error left over the interior candidates (metres; 0 when none)
    best_error : the lowest such largest error of any mesh the insertion went through (metres): the error
        the greedy insertion reaches within ``max_vertices`` vertices, never above ``max_error`` (a flip
        can make a triangle whose worst sample is worse than the one just inserted, so ``max_error`` is
        not monotone in ``max_vertices``; ``best_error`` is)
    """
    empty = np.zeros(0, np.int64)
    return tin_window_seeded(z, valid, bx, by, empty, empty, target, max_vertices)


@leaf
def _locate(tri, half, px, py, t, x, y, max_steps):
    """The triangle holding (x, y) (inside or on its border), by a visibility walk from triangle t; -1
    when the walk leaves the mesh or exceeds ``max_steps``."""
    for _ in range(max_steps):
        moved = False
        for k in range(3):
            e = 3 * t + k
            a = tri[e]
            b = tri[_nxt(e)]
            if _orient(px[a], py[a], px[b], py[b], x, y) < 0:
                h = half[e]
                if h < 0:
                    return -1
                t = h // 3
                moved = True
                break
        if not moved:
            return t
    return -1


@jit
def tin_window_seeded(z, valid, bx, by, sx, sy, target, max_vertices):
    """:func:`tin_window` that first inserts the interior vertices ``sx, sy`` (distinct valid samples,
    strictly inside the window) after the border, then refines greedily from there: what a coarse tile
    meshes on the full source after a pass on a decimated copy found most of its vertices."""
    h, w = z.shape
    cap_v = 64 + bx.shape[0] + sx.shape[0]
    cap_t = 2 * cap_v
    px = np.empty(cap_v, np.int64)
    py = np.empty(cap_v, np.int64)
    tri = np.empty(3 * cap_t, np.int64)
    half = np.full(3 * cap_t, -1, np.int64)
    pending = np.empty(64 + 8 * cap_t, np.int64)
    stack = np.empty(64 + 8 * cap_t, np.int64)
    # the 4 corners, 2 triangles
    px[0], py[0] = 0, 0
    px[1], py[1] = w - 1, 0
    px[2], py[2] = w - 1, h - 1
    px[3], py[3] = 0, h - 1
    nv = 4
    npend = 0
    npend = _set_tri(tri, half, pending, npend, 0, 0, 1, 2, -1, -1, -1)
    npend = _set_tri(tri, half, pending, npend, 1, 0, 2, 3, 2, -1, -1)
    nt = 2
    nheap = 0
    # the border, fixed first
    for i in range(bx.shape[0]):
        if nv + 1 > cap_v or nt + 2 > cap_t:
            cap_v = 2 * cap_v
            cap_t = 2 * cap_t
            px, py = _grow(px, cap_v), _grow(py, cap_v)
            tri = _grow(tri, 3 * cap_t)
            half = _grow(half, 3 * cap_t)
            pending = _grow(pending, 64 + 8 * cap_t)
            stack = _grow(stack, 64 + 8 * cap_t)
        px[nv] = bx[i]
        py[nv] = by[i]
        e = _border_edge(tri, half, px, py, nt, bx[i], by[i])
        if e >= 0:  # (always, for a border vertex strictly between two others)
            npend, nt = _split_edge(tri, half, px, py, pending, 0, stack, nt, e, nv)
            nv += 1
    # the seeds, located by a walk from the last one's triangle (they come in raster order)
    hint = 0
    for i in range(sx.shape[0]):
        if nv >= max_vertices:
            break
        t = _locate(tri, half, px, py, hint, sx[i], sy[i], nt + 16)
        if t < 0:
            for tt in range(nt):  # (a walk never fails on a Delaunay mesh; a full search if it did)
                a, b, c = tri[3 * tt], tri[3 * tt + 1], tri[3 * tt + 2]
                if (
                    _orient(px[a], py[a], px[b], py[b], sx[i], sy[i]) >= 0
                    and _orient(px[b], py[b], px[c], py[c], sx[i], sy[i]) >= 0
                    and _orient(px[c], py[c], px[a], py[a], sx[i], sy[i]) >= 0
                ):
                    t = tt
                    break
        px[nv] = sx[i]
        py[nv] = sy[i]
        npend, nt = _insert(tri, half, px, py, pending, 0, stack, nt, t, nv)
        nv += 1
        hint = t
    npend = 0
    for t in range(nt):
        pending[npend] = t
        npend += 1
    err = np.full(cap_t, -1.0)
    cx = np.zeros(cap_t, np.int64)
    cy = np.zeros(cap_t, np.int64)
    pos = np.full(cap_t, -1, np.int64)
    heap = np.empty(cap_t, np.int64)
    seen = np.full(cap_t, -1, np.int64)
    step = 0
    best = np.inf
    while True:
        # candidates of the triangles made since the last step (a triangle may be listed twice)
        for i in range(npend):
            t = pending[i]
            if pos[t] >= 0:
                nheap = _heap_remove(err, heap, pos, nheap, t)
        for i in range(npend):
            t = pending[i]
            if seen[t] == step:
                continue
            seen[t] = step
            ev, xv, yv = _candidate(z, valid, w, h, px, py, tri[3 * t], tri[3 * t + 1], tri[3 * t + 2])
            err[t] = ev
            cx[t] = xv
            cy[t] = yv
            if ev > target:
                heap[nheap] = t
                pos[t] = nheap
                nheap += 1
                _heap_up(err, heap, pos, nheap - 1)
        npend = 0
        step += 1
        top = err[heap[0]] if nheap > 0 else 0.0
        if top < best:
            best = top
        if nheap == 0 or nv >= max_vertices:
            break
        if nv + 1 > cap_v or nt + 2 > cap_t:
            cap_v = 2 * cap_v
            cap_t = 2 * cap_t
            px, py = _grow(px, cap_v), _grow(py, cap_v)
            tri = _grow(tri, 3 * cap_t)
            half = _grow(half, 3 * cap_t)
            err = _grow(err, cap_t)
            cx, cy = _grow(cx, cap_t), _grow(cy, cap_t)
            pos = _grow(pos, cap_t)
            pos[cap_t // 2 :] = -1
            seen = _grow(seen, cap_t)
            seen[cap_t // 2 :] = -1
            heap = _grow(heap, cap_t)
            pending = _grow(pending, 64 + 8 * cap_t)
            stack = _grow(stack, 64 + 8 * cap_t)
        t = heap[0]
        nheap = _heap_remove(err, heap, pos, nheap, t)
        px[nv] = cx[t]
        py[nv] = cy[t]
        npend, nt = _insert(tri, half, px, py, pending, npend, stack, nt, t, nv)
        nv += 1
    worst = 0.0
    for i in range(nheap):
        if err[heap[i]] > worst:
            worst = err[heap[i]]
    tris = np.empty((nt, 3), np.int32)
    for t in range(nt):
        tris[t, 0] = tri[3 * t]
        tris[t, 1] = tri[3 * t + 1]
        tris[t, 2] = tri[3 * t + 2]
    return px[:nv].copy(), py[:nv].copy(), tris, worst, min(best, worst)


# -- the tile's arrays in the store's order ------------------------------------------------------------------


@jit
def raster_order(zw, px, py, tris, r0, c0):
    """A window's TIN in the order the store codes best: vertices in raster order (row, then column),
    triangles renumbered, flipped to counter-clockwise seen from above ((a, b, c) -> (a, c, b)) and sorted
    by their indices (first, then second, then third).

    The same arrays as ``np.lexsort`` of (px, py) and of the triangles' columns (vertex positions are
    distinct and so are triangles, so every sort gives one order). Needs N^3 < 2^63 for N vertices (the
    caller falls back to numpy beyond). Returns rows, cols, heights_m (float64, source frame), triangles
    (int32).
    """
    n = px.shape[0]
    w = np.int64(zw.shape[1])
    key = np.empty(n, np.int64)
    for i in range(n):
        key[i] = py[i] * w + px[i]
    order = np.argsort(key)
    rank = np.empty(n, np.int64)
    for i in range(n):
        rank[order[i]] = i
    k = tris.shape[0]
    tkey = np.empty(k, np.int64)
    for t in range(k):
        a = rank[tris[t, 0]]
        b = rank[tris[t, 2]]
        c = rank[tris[t, 1]]
        tkey[t] = (a * n + b) * n + c
    torder = np.argsort(tkey)
    out = np.empty((k, 3), np.int32)
    for i in range(k):
        t = torder[i]
        out[i, 0] = rank[tris[t, 0]]
        out[i, 1] = rank[tris[t, 2]]
        out[i, 2] = rank[tris[t, 1]]
    rows = np.empty(n, np.float64)
    cols = np.empty(n, np.float64)
    hz = np.empty(n, np.float64)
    for i in range(n):
        j = order[i]
        rows[i] = np.float64(r0 + py[j])
        cols[i] = np.float64(c0 + px[j])
        hz[i] = np.float64(zw[py[j], px[j]])
    return rows, cols, hz, out
