"""Point location in a triangulation by a bucket grid (the web export's TIN surface, export/source.py).

A uniform grid of cells over the vertices' bounding box, about two triangles per cell: each triangle is
listed in every cell its bounding box meets (a counting sort: count, prefix sum, fill), and a point is
tested against the triangles of its one cell, in ascending triangle order, with the edges included. Build
O(T + cells), query O(triangles per cell); memory one int64 per (cell, triangle) pair. It replaces a
trapezoidal map (matplotlib's ``TrapezoidMapTriFinder``: O(T log T) to build, in Python-driven C++), whose
build was most of the time of a TIN store's quantized-mesh export.

Which triangle holds a point on an edge two triangles share is a convention: here the lowest-numbered one.
The surface value there is the same up to rounding of each triangle's plane. Pure functions on arrays.
"""

from __future__ import annotations

import math

import numpy as np

from terralod.kernels import jit
from terralod.kernels.error import csr_from_boxes

__all__ = ["bucket_triangles", "locate_points", "plane_heights"]


@jit
def bucket_triangles(x, y, tris, nx, ny, x0, y0, inv_dx, inv_dy):  # pragma: no cover - numba
    """(start (nx*ny + 1,), items): the triangles meeting each cell's bounding box, cell by cell (row-major,
    ascending triangle index within a cell); cell (i, j) spans x0 + [i, i+1) / inv_dx, y0 + [j, j+1) /
    inv_dy, the last row and column closed. ``tris`` (T, 3) int64 indices into x, y (float64)."""
    nt = tris.shape[0]
    box = np.empty((nt, 4), np.int64)  # rows (y cells) then columns (x cells): cell (i, j) is row j
    for t in range(nt):
        a, b, c = tris[t, 0], tris[t, 1], tris[t, 2]
        xmin = min(x[a], x[b], x[c])
        xmax = max(x[a], x[b], x[c])
        ymin = min(y[a], y[b], y[c])
        ymax = max(y[a], y[b], y[c])
        box[t, 2] = min(max(int(math.floor((xmin - x0) * inv_dx)), 0), nx - 1)
        box[t, 3] = min(max(int(math.floor((xmax - x0) * inv_dx)), 0), nx - 1)
        box[t, 0] = min(max(int(math.floor((ymin - y0) * inv_dy)), 0), ny - 1)
        box[t, 1] = min(max(int(math.floor((ymax - y0) * inv_dy)), 0), ny - 1)
    return csr_from_boxes(box, ny, nx)  # cell (i, j) at j * nx + i, as before


@jit
def locate_points(x, y, tris, start, items, nx, ny, x0, y0, inv_dx, inv_dy, px, py):  # pragma: no cover
    """(N,) int64: the first triangle (in its cell's list) whose closed area holds each point (px, py), -1
    where none does (outside the triangulation, or in a hole). Triangles of zero area hold no point."""
    n = px.shape[0]
    out = np.full(n, -1, np.int64)
    for p in range(n):
        qx = px[p]
        qy = py[p]
        fi = math.floor((qx - x0) * inv_dx)
        fj = math.floor((qy - y0) * inv_dy)
        # a point past the box's far edge by rounding belongs to the last cell, as in bucket_triangles
        if not (fi >= -1 and fj >= -1 and fi <= nx and fj <= ny):
            continue
        i = min(max(int(fi), 0), nx - 1)
        j = min(max(int(fj), 0), ny - 1)
        k = j * nx + i
        for s in range(start[k], start[k + 1]):
            t = items[s]
            a, b, c = tris[t, 0], tris[t, 1], tris[t, 2]
            ax, ay, bx, by, cx, cy = x[a], y[a], x[b], y[b], x[c], y[c]
            d1 = (bx - ax) * (qy - ay) - (by - ay) * (qx - ax)
            d2 = (cx - bx) * (qy - by) - (cy - by) * (qx - bx)
            d3 = (ax - cx) * (qy - cy) - (ay - cy) * (qx - cx)
            area = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
            if area > 0.0:
                if d1 >= 0.0 and d2 >= 0.0 and d3 >= 0.0:
                    out[p] = t
                    break
            elif area < 0.0:
                if d1 <= 0.0 and d2 <= 0.0 and d3 <= 0.0:
                    out[p] = t
                    break
    return out


@jit
def plane_heights(planes, t, px, py):  # pragma: no cover - numba
    """(N,) float64: ``planes[t, 0] * px + planes[t, 1] * py + planes[t, 2]`` at each point whose triangle
    ``t`` (from :func:`locate_points`) is not -1, NaN elsewhere; the operations in that order, without
    fused multiply-adds, so each value has the bits of the numpy expression (matplotlib's
    ``LinearTriInterpolator``)."""
    n = px.shape[0]
    out = np.full(n, np.nan)
    for p in range(n):
        k = t[p]
        if k >= 0:
            out[p] = planes[k, 0] * px[p] + planes[k, 1] * py[p] + planes[k, 2]
    return out
