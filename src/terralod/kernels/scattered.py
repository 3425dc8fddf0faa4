"""Vertical error of a triangle mesh at scattered points (numba kernels): a tile's surface against the
original samples of a source that was resampled before meshing.

Source: DESIGN.md's rule "every stored tile error is the maximum distance between the tile's surface and
every source sample it covers" (no paper of ../shared/papers defines the measurement), applied to samples
that do not sit on the tile's lattice: a geographic or Mercator DEM reprojected once to UTM
(:func:`terralod.io.raster.reproject_to_utm`) puts its own samples anywhere between the grid's.

Definitions (any planar frame, e.g. window-local metres; the kernel never looks at units): a point is
*covered* when its (x, y) lies inside or on an edge of at least one non-degenerate triangle (barycentric
coordinates >= -1e-9, the one test :func:`terralod.kernels.error.triangle_gap`); its gap is
``|z - surface(x, y)|``, the surface linear on the triangle. Where several triangles cover a point (a shared
edge or vertex, a fold) the largest of their gaps is taken, so the result bounds the gap whichever covering
triangle a consumer interpolates on. Uncovered points are counted, never measured (a hole in the mesh is the
caller's to judge).

Algorithm: the points are bucketed on a square grid over their bounding box (counting sort: count, allocate
exactly, fill — the martini habit); each triangle tests the points of the buckets its bounding box touches.
Memory: one float64 gap and one int64 bucket index a point, and the bucket offsets.
"""

from __future__ import annotations

import math

import numpy as np

from terralod.kernels import jit
from terralod.kernels.error import bucket_points, triangle_gap

#: Barycentric slack of the coverage test: points on an edge (up to rounding) count as inside.
_EDGE_TOL = 1e-9
#: A triangle visits the buckets of its box widened by this fraction of its size (>> _EDGE_TOL).
_BOX_PAD = 1e-6
#: Points a bucket holds on average, and the most buckets a side.
_POINTS_PER_BUCKET = 4.0
_MAX_BUCKETS = 1024


@jit
def scattered_vertical_error(verts, tris, px, py, pz):  # pragma: no cover - numba
    """Gaps between the triangles ``tris`` (K, 3) of ``verts`` (N, 3) (x, y, z) and the points
    (``px``, ``py``, ``pz``) (M,) in the same frame.

    Returns (largest gap, sum of squared gaps, covered points, uncovered points); each covered point counted
    once, with the largest gap of the triangles covering it."""
    n = px.size
    if n == 0:
        return 0.0, 0.0, 0, 0
    gap = np.full(n, -1.0)
    xmin = px.min()
    xmax = px.max()
    ymin = py.min()
    ymax = py.max()
    nb = max(1, min(_MAX_BUCKETS, int(math.sqrt(n / _POINTS_PER_BUCKET)) + 1))
    ix = nb / (xmax - xmin) if xmax > xmin else 0.0
    iy = nb / (ymax - ymin) if ymax > ymin else 0.0
    start, order = bucket_points(px, py, xmin, ymin, ix, iy, nb)  # counting sort into nb x nb buckets
    for t in range(tris.shape[0]):
        a, b, c = tris[t, 0], tris[t, 1], tris[t, 2]
        ua, va, ub, vb, uc, vc = verts[a, 0], verts[a, 1], verts[b, 0], verts[b, 1], verts[c, 0], verts[c, 1]
        det = (vb - vc) * (ua - uc) + (uc - ub) * (va - vc)
        if det == 0.0:
            continue
        # the box widened by far more than the edge slack reaches, so a point the test may take is visited
        pad = _BOX_PAD * (max(ua, ub, uc) - min(ua, ub, uc) + max(va, vb, vc) - min(va, vb, vc))
        tx0 = min(ua, ub, uc) - pad
        tx1 = max(ua, ub, uc) + pad
        ty0 = min(va, vb, vc) - pad
        ty1 = max(va, vb, vc) + pad
        if tx1 < xmin or tx0 > xmax or ty1 < ymin or ty0 > ymax:
            continue
        # the points' own bucket formula (monotone in x, y), so a point on the box's edge is never missed
        x0 = max(int((tx0 - xmin) * ix), 0)
        x1 = min(int((tx1 - xmin) * ix), nb - 1)
        y0 = max(int((ty0 - ymin) * iy), 0)
        y1 = min(int((ty1 - ymin) * iy), nb - 1)
        ha, hb, hc = verts[a, 2], verts[b, 2], verts[c, 2]
        for cy in range(y0, y1 + 1):
            for cx in range(x0, x1 + 1):
                k = cy * nb + cx
                for j in range(start[k], start[k + 1]):
                    i = order[j]
                    d = triangle_gap(ua, va, ub, vb, uc, vc, det, ha, hb, hc, px[i], py[i], pz[i], _EDGE_TOL)
                    if d > gap[i]:
                        gap[i] = d
    err = 0.0
    sumsq = 0.0
    covered = 0
    for i in range(n):
        d = gap[i]
        if d >= 0.0:
            covered += 1
            sumsq += d * d
            if d > err:
                err = d
    return err, sumsq, covered, n - covered
