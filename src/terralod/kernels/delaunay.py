"""Delaunay TIN helpers (numba kernels): triangles made counter-clockwise, and the block-by-block
triangulation's bookkeeping (which points each block sees, which triangles it keeps).

Method: :mod:`terralod.tin.delaunay` and :mod:`terralod.tin.delaunay_blocks` (one global Delaunay
triangulation computed block by block). Pure functions on arrays: no I/O, no exceptions.
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["canonical_order", "orient_ccw", "owned_triangles", "points_by_block"]


@njit(cache=True, nogil=True)
def owned_triangles(xy, tris, nbr, core, known):  # pragma: no cover - compiled
    """Kept triangles of one block, and their open edges.

    A triangle is kept when its circumcircle lies inside ``known`` (x0, x1, y0, y1: the block's core plus
    halo) and its circumcentre inside ``core`` (x0 <= x < x1, y0 <= y < y1), each by a margin larger than
    the rounding of the centre and radius (a bound from the triangle's shape and the coordinates'
    magnitude). Infinite bounds pass.

    Parameters
    ----------
    xy : (N, 2) float64
        The block's points.
    tris : (M, 3) int64
        Its Delaunay triangles (Triangle's output).
    nbr : (M, 3) int64
        The neighbour opposite corner j (-1 on the outline).
    core, known : (4,) float64

    Returns
    -------
    kept : (K,) int64
        Indices of the kept triangles, ascending.
    edges : (E, 3) int64
        (u, v, w) local points: an edge u-v of a kept triangle whose neighbour is not kept (or absent),
        w the kept triangle's third corner.
    unused : int64
        Points used by no triangle (exact duplicates, or collinear leftovers).
    """
    m = tris.shape[0]
    n = xy.shape[0]
    own = np.zeros(m, np.bool_)
    n_kept = 0
    for t in range(m):
        a, b, c = tris[t, 0], tris[t, 1], tris[t, 2]
        ax, ay = xy[a, 0], xy[a, 1]
        bx, by = xy[b, 0] - ax, xy[b, 1] - ay
        cx, cy = xy[c, 0] - ax, xy[c, 1] - ay
        bb = bx * bx + by * by
        cc = cx * cx + cy * cy
        d = 2.0 * (bx * cy - by * cx)
        if d == 0.0:
            continue
        ux = (cy * bb - by * cc) / d
        uy = (bx * cc - cx * bb) / d
        r = np.sqrt(ux * ux + uy * uy)
        # the centre moves by about (longest edge)² / |d| times a coordinate's rounding: a generous bound
        cond = max(bb, cc) / abs(d)
        err = 1e-12 * (1.0 + cond) * (max(abs(ax), abs(ay)) + r + 1.0)
        if not (np.isfinite(r) and np.isfinite(err)):
            continue
        px = ax + ux
        py = ay + uy
        if not (px >= core[0] + err and px < core[1] - err and py >= core[2] + err and py < core[3] - err):
            continue
        if not (px - r > known[0] + err and px + r < known[1] - err and py - r > known[2] + err
                and py + r < known[3] - err):  # fmt: skip
            continue
        own[t] = True
        n_kept += 1
    kept = np.empty(n_kept, np.int64)
    n_open = 0
    k = 0
    for t in range(m):
        if own[t]:
            kept[k] = t
            k += 1
            for j in range(3):
                q = nbr[t, j]
                if q < 0 or not own[q]:
                    n_open += 1
    edges = np.empty((n_open, 3), np.int64)
    e = 0
    for i in range(n_kept):
        t = kept[i]
        for j in range(3):
            q = nbr[t, j]
            if q < 0 or not own[q]:
                edges[e, 0] = tris[t, (j + 1) % 3]
                edges[e, 1] = tris[t, (j + 2) % 3]
                edges[e, 2] = tris[t, j]
                e += 1
    used = np.zeros(n, np.bool_)
    for t in range(m):
        used[tris[t, 0]] = True
        used[tris[t, 1]] = True
        used[tris[t, 2]] = True
    unused = 0
    for i in range(n):
        if not used[i]:
            unused += 1
    return kept, edges, unused


@njit(cache=True, nogil=True)
def points_by_block(xy, xs, ys, halo):  # pragma: no cover - compiled
    """Each point listed under every block whose core plus halo holds it (closed bounds).

    Parameters
    ----------
    xy : (N, 2) float64
    xs, ys : (m + 1,) float64
        Core edges (xs[0] = ys[0] = -inf, xs[m] = ys[m] = +inf).
    halo : float

    Returns
    -------
    start : (m * m + 1,) int64
        Block b's points are ``index[start[b] : start[b + 1]]``.
    index : (P,) int64
        Point rows, ascending within each block.
    """
    m = xs.shape[0] - 1
    n = xy.shape[0]
    lo_x = xs[1:] + halo  # column c reaches down to xs[c] - halo and up to xs[c + 1] + halo
    hi_x = xs[:-1] - halo
    lo_y = ys[1:] + halo
    hi_y = ys[:-1] - halo
    count = np.zeros(m * m + 1, np.int64)
    for p in range(2):
        if p == 1:
            for b in range(m * m):
                count[b + 1] += count[b]
            fill = count[:-1].copy()
            index = np.empty(count[m * m], np.int64)
        for i in range(n):
            x, y = xy[i, 0], xy[i, 1]
            # the columns whose core grown by the halo holds x: xs[c] - halo <= x <= xs[c + 1] + halo
            # (the halo may span several cores)
            c0 = np.searchsorted(lo_x, x, side="left")
            c1 = np.searchsorted(hi_x, x, side="right") - 1
            r0 = np.searchsorted(lo_y, y, side="left")
            r1 = np.searchsorted(hi_y, y, side="right") - 1
            for rr in range(r0, r1 + 1):
                for cc in range(c0, c1 + 1):
                    b = rr * m + cc
                    if p == 0:
                        count[b + 1] += 1
                    else:
                        index[fill[b]] = i
                        fill[b] += 1
    return count, index


@njit(cache=True, nogil=True)
def orient_ccw(xy, tris):  # pragma: no cover - compiled
    """Triangles made counter-clockwise in xy, those of zero area dropped.

    Parameters
    ----------
    xy : (N, 2) float64
    tris : (M, 3) int64

    Returns
    -------
    out : (K, 3) int64
        The triangles of positive area, in order, the last two corners swapped where the triangle was
        clockwise.
    area2 : (K,) float64
        Twice their xy area.
    """
    m = tris.shape[0]
    a2 = np.empty(m, np.float64)
    k = 0
    for t in range(m):
        a, b, c = tris[t, 0], tris[t, 1], tris[t, 2]
        v = (xy[b, 0] - xy[a, 0]) * (xy[c, 1] - xy[a, 1]) - (xy[b, 1] - xy[a, 1]) * (xy[c, 0] - xy[a, 0])
        a2[t] = v
        if v > 0.0 or v < 0.0:  # (not NaN)
            k += 1
    out = np.empty((k, 3), np.int64)
    area2 = np.empty(k, np.float64)
    i = 0
    for t in range(m):
        v = a2[t]
        if not (v > 0.0 or v < 0.0):
            continue
        out[i, 0] = tris[t, 0]
        if v < 0.0:
            out[i, 1] = tris[t, 2]
            out[i, 2] = tris[t, 1]
            area2[i] = -v
        else:
            out[i, 1] = tris[t, 1]
            out[i, 2] = tris[t, 2]
            area2[i] = v
        i += 1
    return out, area2


@njit(cache=True, nogil=True)
def canonical_order(tris, n_vertices):  # pragma: no cover - compiled
    """The triangles in an order that depends on the triangle set only: each rotated to start at its
    smallest vertex (orientation kept), then sorted by that vertex and the next one (a directed edge: unique
    in a manifold mesh, so the order is total). A counting sort on the first vertex, an insertion sort of
    the few triangles sharing it.

    Parameters
    ----------
    tris : (M, 3) integer
        Triangles over vertices ``0 .. n_vertices - 1``.
    n_vertices : int

    Returns
    -------
    (M, 3) same dtype as ``tris``
    """
    m = tris.shape[0]
    rot = np.empty_like(tris)
    start = np.zeros(n_vertices + 1, np.int64)
    for t in range(m):
        a, b, c = tris[t, 0], tris[t, 1], tris[t, 2]
        if b < a and b <= c:
            a, b, c = b, c, a
        elif c < a and c < b:
            a, b, c = c, a, b
        rot[t, 0] = a
        rot[t, 1] = b
        rot[t, 2] = c
        start[a + 1] += 1
    for v in range(n_vertices):
        start[v + 1] += start[v]
    out = np.empty_like(tris)
    fill = start[:-1].copy()
    for t in range(m):
        i = fill[rot[t, 0]]
        fill[rot[t, 0]] += 1
        out[i, 0] = rot[t, 0]
        out[i, 1] = rot[t, 1]
        out[i, 2] = rot[t, 2]
    for v in range(n_vertices):
        for i in range(start[v] + 1, start[v + 1]):
            b, c = out[i, 1], out[i, 2]
            j = i - 1
            while j >= start[v] and (out[j, 1] > b or (out[j, 1] == b and out[j, 2] > c)):
                out[j + 1, 1] = out[j, 1]
                out[j + 1, 2] = out[j, 2]
                j -= 1
            out[j + 1, 1] = b
            out[j + 1, 2] = c
    return out
