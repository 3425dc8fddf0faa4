"""Measured geometric error of a triangle mesh against the heightfield samples it covers (numba kernels).

Source: DESIGN.md's rule "every stored tile error is the maximum distance between the tile's surface and
every source sample it covers" (no paper of ../shared/papers defines the measurement; they assume it);
the point-triangle distance is Ericson's, *Real-Time Collision Detection* 5.1.5, unchanged.

Frame (window-local, metres): sample (r, c) of the window sits at ``(c * dx, r * dy, z[r, c])``; X grows
east, Y grows south (the frame is mirrored, distances are not). Vertices come in the same frame.

Definitions. A sample is *covered* when it is valid and lies inside or on the boundary of at least one
triangle's XY projection.

- vertical error of a covered sample: ``|z - z_surface|``, z_surface interpolated on a covering triangle;
  where triangles overlap (folded meshes, triangle soups) the smallest over the covering triangles is
  taken. On a vertex, z_surface is the vertex height exactly (so a mesh through the samples measures 0);
- Hausdorff distance: max over covered samples of the 3D distance from the sample to the closest point of
  the mesh (every triangle, exact point-triangle distance, Ericson, *Real-Time Collision Detection*
  5.1.5). It never exceeds the max vertical error.

Coverage is decided in sample units (u = X / dx, v = Y / dy; a vertex within 1e-7 samples of a lattice
point is put on it, ``_SNAP``) by one orientation predicate per edge, with the edge taken in a canonical
direction (lexicographically smaller endpoint first). So the two triangles sharing an edge compute
bit-identical numbers for it and a sample on a shared edge is never lost between them; and for vertices
on the sample lattice (every mesh made from the raster) the predicate is exact integer arithmetic, so a
sample on an outer edge is covered whatever dx, dy and the window origin.

Algorithm (the recipe in :func:`tile_error_with`):

1. Buckets: a uniform grid of square buckets of ``bs`` samples over the window.
2. ``_vertical_pass``: the vertical error of every covered sample, by ``_rasterise_bucket`` (per row the
   covered run is found by the exact test at its two ends, and its interior is a branch-free loop that
   vectorises). Windows up to ``_KEEP_SAMPLES`` samples (every tile at stride <= 16) are rasterised
   triangle by triangle straight into a per-sample array; larger ones bucket by bucket through a bucket
   of scratch, each bucket with the triangles whose box touches it (``_bin_triangles``: count first,
   allocate exactly, then fill — the martini habit). Out: count, sum of squares, max, and per bucket the
   max and where it is.
3. ``_hausdorff_pass``: a sample's distance is at most its vertical error v, so it is searched only while
   v exceeds the running max (RMS is vertical-only, nothing else needs its exact distance). Seed: the
   worst sample of each of the worst buckets, which lifts the running max close to its final value.
   Sweep: buckets by decreasing max vertical error, stopping at the first whose max is not above the
   running max. A search (``_sample_dist2``) descends a pyramid of the buckets' 3D boxes best first and
   stops as soon as the distance cannot raise the running max, so it stays local however large v is.
   On terrain tiles pass 2 costs a few percent of pass 1.

Several meshes of one window that differ in a few triangles (a mesher's candidates):
:func:`tile_error_rows` keeps the per-sample array between calls and rasterises again only the rows that
a changed triangle reaches (rows are independent in pass 1, so this is bit-identical); the statistics and
pass 2 run on the whole window as always.

Web-export tiles (:func:`points_vertical_error`, :func:`lattice_vertical_error`): the vertical distance
between a decoded quantized-mesh tile (u/v units, linear in u/v as a client interpolates it) and the source
samples inside it, scattered points (bucketed) or a lattice window (each triangle's row spans), through the
one barycentric test :func:`triangle_gap`; a valid sample that no triangle covers is counted (a hole is
reported by the caller, never skipped).

Memory: the per-sample array (8 bytes a sample, at most 16 MiB) or one bucket of scratch; the bucket
index (1 to 4 int64 a triangle) and, in pass 2, per-triangle boxes (6 float64 a triangle).
"""

from __future__ import annotations

import math

import numpy as np

from terralod.kernels import jit, leaf

#: Vertices within this many samples of a lattice point are put on it for the coverage test (their
#: metric coordinates, used for every distance, are left alone): X / dx rounds, and a vertex made as
#: ``col * dx`` must come back as exactly ``col``.
_SNAP = 1e-7

#: Slack, in samples, added to every triangle box before binning (binning too much only costs a test).
_BIN_SLACK = 1e-6

#: The box lower bound of a point-triangle distance is shrunk by this factor before pruning, so rounding
#: in the bound can never prune the closest triangle.
_LB_SHRINK = 1.0 - 1e-9

#: Bucket side, samples: about _BUCKET_SCALE * sqrt(window samples per triangle) (a regular grid at
#: stride s gets about 3 s, some 20 triangles a bucket), within [_MIN_BUCKET, _MAX_BUCKET] (lower
#: bound _MIN_BUCKET_KEEP when pass 1 does not go through buckets).
_BUCKET_SCALE = 4.0
_MIN_BUCKET = 16
_MIN_BUCKET_KEEP = 4
_MAX_BUCKET = 128

#: Windows of at most this many samples are rasterised triangle by triangle straight into one array of
#: vertical errors (8 bytes a sample, 16 MiB at most), which pass 2 reads; larger windows (coarse
#: tiles) go bucket by bucket through a bucket of scratch and pass 2 rasterises its buckets again.
_KEEP_SAMPLES = 1 << 21

#: Pass 2 first measures the worst sample of this many of the worst buckets, which lifts the running
#: maximum close to its final value before the sweep (most samples then need no search).
_SEED_BUCKETS = 16


@leaf
def triangle_gap(ua, va, ub, vb, uc, vc, det, ha, hb, hc, x, y, z, tol):  # pragma: no cover - numba
    """|z - surface| at (x, y) of the triangle (ua, va, ha), (ub, vb, hb), (uc, vc, hc), linear in u/v as
    a quantized-mesh client interpolates it; -1.0 when (x, y) is outside (edges within ``tol`` count as
    inside). ``det`` = (vb - vc)(ua - uc) + (uc - ub)(va - vc), non-zero: the caller skips flat ones. The
    one barycentric test of both web-export error kernels (scattered points and lattice rows)."""
    la = ((vb - vc) * (x - uc) + (uc - ub) * (y - vc)) / det
    lb = ((vc - va) * (x - uc) + (ua - uc) * (y - vc)) / det
    lc = 1.0 - la - lb
    if la < -tol or lb < -tol or lc < -tol:
        return -1.0
    return abs(la * ha + lb * hb + lc * hc - z)


@leaf
def _canonical_edge(ax, ay, bx, by):
    """Start point and direction of segment a-b, lexicographically smaller endpoint first."""
    if ax < bx or (ax == bx and ay <= by):
        return ax, ay, bx - ax, by - ay
    return bx, by, ax - bx, ay - by


@leaf
def _side(px, py, ex, ey, ox, oy):
    """+1 / -1: side of point o of the canonical edge (p, e); 0 when o is on its line."""
    s = ex * (oy - py) - ey * (ox - px)
    return 1.0 if s > 0.0 else (-1.0 if s < 0.0 else 0.0)


@jit
def _sample_units(verts, dx, dy):
    """(N, 2) vertex (u, v) = (X / dx, Y / dy) in samples, snapped to the lattice within _SNAP."""
    n = verts.shape[0]
    uv = np.empty((n, 2), np.float64)
    for i in range(n):
        u = verts[i, 0] / dx
        v = verts[i, 1] / dy
        ru = math.floor(u + 0.5)
        rv = math.floor(v + 0.5)
        uv[i, 0] = ru if abs(u - ru) <= _SNAP else u
        uv[i, 1] = rv if abs(v - rv) <= _SNAP else v
    return uv


@leaf
def _bucket_span(lo, hi, nb, ibs):
    """Bucket indices [b0, b1] covering the closed interval [lo, hi] samples, clamped to [0, nb - 1].

    ibs is 1 / bucket side (inexact for most sides: the slack keeps that rounding from dropping a bucket).
    """
    a = min(max((lo - _BIN_SLACK) * ibs, 0.0), nb - 1.0)
    b = min(max((hi + _BIN_SLACK) * ibs, 0.0), nb - 1.0)
    return int(a), int(b)


@jit
def csr_from_boxes(box, nrow, ncol):  # pragma: no cover - numba
    """CSR index of items over a nrow x ncol grid of cells: item t goes to every cell (i, j) with
    ``box[t, 0] <= i <= box[t, 1]`` and ``box[t, 2] <= j <= box[t, 3]`` (inclusive, inside the grid); the
    items of cell (i, j) are ``items[start[i*ncol+j]:start[i*ncol+j+1]]``, ascending. Count first, then
    fill: two passes, no resizing."""
    k = box.shape[0]
    nb = nrow * ncol
    count = np.zeros(nb + 1, np.int64)
    for t in range(k):
        for i in range(box[t, 0], box[t, 1] + 1):
            for j in range(box[t, 2], box[t, 3] + 1):
                count[i * ncol + j + 1] += 1
    for b in range(nb):
        count[b + 1] += count[b]
    start = count.copy()
    items = np.empty(count[nb], np.int64)
    for t in range(k):
        for i in range(box[t, 0], box[t, 1] + 1):
            for j in range(box[t, 2], box[t, 3] + 1):
                b = i * ncol + j
                items[count[b]] = t
                count[b] += 1
    return start, items


@jit
def _bin_triangles(uv, tris, nbr, nbc, bs):
    """CSR bucket index: triangles of bucket (i, j) are ``items[start[i*nbc+j]:start[i*nbc+j+1]]``.

    A triangle goes to every bucket its bounding box (in samples) touches.
    """
    k = tris.shape[0]
    ibs = 1.0 / bs
    span = np.empty((k, 4), np.int64)
    for t in range(k):
        a, b, c = tris[t, 0], tris[t, 1], tris[t, 2]
        ua, ub, uc = uv[a, 0], uv[b, 0], uv[c, 0]
        va, vb, vc = uv[a, 1], uv[b, 1], uv[c, 1]
        i0, i1 = _bucket_span(min(va, vb, vc), max(va, vb, vc), nbr, ibs)
        j0, j1 = _bucket_span(min(ua, ub, uc), max(ua, ub, uc), nbc, ibs)
        span[t, 0], span[t, 1], span[t, 2], span[t, 3] = i0, i1, j0, j1
    return csr_from_boxes(span, nbr, nbc)


@jit
def _bin_centroids(uv, tris, nbr, nbc, bs):
    """CSR bucket index with each triangle in the one bucket holding its centroid (clamped to the grid).

    Enough for the distance search, whose bucket boxes are the union of their triangles' boxes.
    """
    k = tris.shape[0]
    nb = nbr * nbc
    key = np.empty(k, np.int64)
    count = np.zeros(nb + 1, np.int64)
    for t in range(k):
        a, b, c = tris[t, 0], tris[t, 1], tris[t, 2]
        i = (uv[a, 1] + uv[b, 1] + uv[c, 1]) / (3.0 * bs)
        j = (uv[a, 0] + uv[b, 0] + uv[c, 0]) / (3.0 * bs)
        key[t] = int(min(max(i, 0.0), nbr - 1.0)) * nbc + int(min(max(j, 0.0), nbc - 1.0))
        count[key[t] + 1] += 1
    for b in range(nb):
        count[b + 1] += count[b]
    start = count.copy()
    items = np.empty(k, np.int64)
    for t in range(k):
        items[count[key[t]]] = t
        count[key[t]] += 1
    return start, items


@leaf
def _sample_range(lo, hi, first, last):
    """Integer samples [a, b] (possibly empty, one wider than needed) around [lo, hi], within [first, last]."""
    a = min(max(math.floor(lo), first - 1.0), last + 1.0)
    b = min(max(math.ceil(hi), first - 1.0), last + 1.0)
    return max(int(a), first), min(int(b), last)


@leaf
def _row_span(a, px, ey, m, lo, hi):
    """Narrow the column interval [lo, hi] (samples, float) to where one edge may hold in this row.

    The edge value along the row is ``a - ey * (c - px)`` (times m it must be >= 0), zero near
    ``c = px + a / ey``; the caller keeps one sample of margin and decides with the exact test.
    """
    if ey == 0.0:
        return (lo, hi) if a * m >= 0.0 else (np.inf, -np.inf)
    c = px + a / ey
    if m * ey > 0.0:
        return lo, min(hi, c)
    return max(lo, c), hi


@leaf
def _end_height(l0, l1, l2, za, zb, zc):
    """Surface height at a row's first or last covered sample from its edge values l_i (>= 0).

    Exactly the vertex height on a vertex: a vertex is an extreme point of its triangle, so it is always
    an end of its row's run, and the run's interior can use the plain plane formula.
    """
    zi = (l0 * za + l1 * zb + l2 * zc) / (l0 + l1 + l2)
    zi = za if (l1 == 0.0 and l2 == 0.0) else zi
    zi = zb if (l0 == 0.0 and l2 == 0.0) else zi
    return zc if (l0 == 0.0 and l1 == 0.0) else zi


@leaf
def _unit_lattice(ax, ay, bx, by, cx, cy):
    """True for a triangle with its vertices on the sample lattice, a box of 1 x 1 samples and an XY area:
    a half of a unit cell, which holds no lattice point but its 3 vertices."""
    if not (ax == math.floor(ax) and ay == math.floor(ay) and bx == math.floor(bx) and by == math.floor(by)
            and cx == math.floor(cx) and cy == math.floor(cy)):  # fmt: skip
        return False
    if max(ax, bx, cx) - min(ax, bx, cx) != 1.0 or max(ay, by, cy) - min(ay, by, cy) != 1.0:
        return False
    return (bx - ax) * (cy - ay) - (by - ay) * (cx - ax) != 0.0


@leaf
def _rasterise_bucket(uv, verts, tris, items, s0, s1, z, valid, r0, r1, c0, c1, vbuf):
    """Vertical error of the samples rows r0..r1, cols c0..c1 (min over covering triangles), into vbuf.

    vbuf[(r - r0) * (c1 - c0 + 1) + (c - c0)] is inf where the sample is not covered (or not valid).
    Coverage and weights are computed in samples (uv), heights in metres (verts[:, 2]). Triangles whose
    box spans under 4 columns test every sample of it; larger ones, per row, narrow the columns by where
    the edges cross the row, find the run of covered columns with the exact test at both ends (each edge
    value is monotone along a row, so the run is contiguous) and fill the run's interior branch-free.
    """
    bw = c1 - c0 + 1
    for q in range((r1 - r0 + 1) * bw):
        vbuf[q] = np.inf
    for it in range(s0, s1):
        t = items[it]
        a, b, c = tris[t, 0], tris[t, 1], tris[t, 2]
        ax, ay, za = uv[a, 0], uv[a, 1], verts[a, 2]
        bx, by, zb = uv[b, 0], uv[b, 1], verts[b, 2]
        cx, cy, zc = uv[c, 0], uv[c, 1], verts[c, 2]
        if _unit_lattice(ax, ay, bx, by, cx, cy):
            # Its covered samples are its 3 vertices, each at its own height: what the general path below
            # computes for them (two edge values exactly 0 there), without the edge set-up (the triangles of
            # a full-resolution grid, every tile of stride 1).
            # (inline: a kernel called with arrays pays their reference counts, which costs more here)
            for k in range(3):
                vx, vy, zv = (ax, ay, za) if k == 0 else ((bx, by, zb) if k == 1 else (cx, cy, zc))
                r = int(vy)
                cc = int(vx)
                if r0 <= r <= r1 and c0 <= cc <= c1 and valid[r, cc]:
                    v = abs(z[r, cc] - zv)
                    q = (r - r0) * bw + (cc - c0)
                    if v < vbuf[q]:  # NaN (no sample) never replaces
                        vbuf[q] = v
            continue
        ra, rb = _sample_range(min(ay, by, cy), max(ay, by, cy), r0, r1)
        ca, cb = _sample_range(min(ax, bx, cx), max(ax, bx, cx), c0, c1)
        if ra > rb or ca > cb:
            continue
        # Edge i is opposite vertex i; m_i is the side of vertex i, so l_i = m_i * value >= 0 inside.
        px0, py0, ex0, ey0 = _canonical_edge(bx, by, cx, cy)
        px1, py1, ex1, ey1 = _canonical_edge(cx, cy, ax, ay)
        px2, py2, ex2, ey2 = _canonical_edge(ax, ay, bx, by)
        m0 = _side(px0, py0, ex0, ey0, ax, ay)
        m1 = _side(px1, py1, ex1, ey1, bx, by)
        m2 = _side(px2, py2, ex2, ey2, cx, cy)
        if m0 == 0.0 or m1 == 0.0 or m2 == 0.0:
            continue  # zero XY area: covers no sample
        # Interior samples: the plane through a, with weights l1, l2 over twice the area.
        inv = 1.0 / abs(ex2 * (cy - py2) - ey2 * (cx - px2))
        dzb = zb - za
        dzc = zc - za
        if cb - ca < 4:
            # Small box: every sample of it, branch-free (stores the old value back when not covered).
            for r in range(ra, rb + 1):
                sy = float(r)
                a0 = ex0 * (sy - py0)
                a1 = ex1 * (sy - py1)
                a2 = ex2 * (sy - py2)
                base = (r - r0) * bw - c0
                for cc in range(ca, cb + 1):
                    sx = float(cc)
                    l0 = (a0 - ey0 * (sx - px0)) * m0
                    l1 = (a1 - ey1 * (sx - px1)) * m1
                    l2 = (a2 - ey2 * (sx - px2)) * m2
                    zi = _end_height(l0, l1, l2, za, zb, zc)
                    v = abs(z[r, cc] - zi)
                    old = vbuf[base + cc]
                    take = l0 >= 0.0 and l1 >= 0.0 and l2 >= 0.0 and valid[r, cc] and v < old
                    vbuf[base + cc] = v if take else old
            continue
        for r in range(ra, rb + 1):
            sy = float(r)
            a0 = ex0 * (sy - py0)
            a1 = ex1 * (sy - py1)
            a2 = ex2 * (sy - py2)
            # Columns the edges leave open, with one sample of margin for the rounding of the estimate.
            cl, ch = ca, cb
            lo, hi = _row_span(a0, px0, ey0, m0, float(ca), float(cb))
            lo, hi = _row_span(a1, px1, ey1, m1, lo, hi)
            lo, hi = _row_span(a2, px2, ey2, m2, lo, hi)
            if lo == lo and hi == hi:  # not NaN; clamped before the int conversion
                cl = max(ca, int(math.floor(min(lo, cb + 1.0))) - 1)
                ch = min(cb, int(math.ceil(max(hi, ca - 1.0))) + 1)
            # First and last covered column of the row, with their edge values.
            first = -1
            f0 = f1 = f2 = 0.0
            for cc in range(cl, ch + 1):
                sx = float(cc)
                f0 = (a0 - ey0 * (sx - px0)) * m0
                f1 = (a1 - ey1 * (sx - px1)) * m1
                f2 = (a2 - ey2 * (sx - px2)) * m2
                if f0 >= 0.0 and f1 >= 0.0 and f2 >= 0.0:
                    first = cc
                    break
            if first < 0:
                continue
            last = first
            g0, g1, g2 = f0, f1, f2
            for cc in range(ch, first, -1):
                sx = float(cc)
                g0 = (a0 - ey0 * (sx - px0)) * m0
                g1 = (a1 - ey1 * (sx - px1)) * m1
                g2 = (a2 - ey2 * (sx - px2)) * m2
                if g0 >= 0.0 and g1 >= 0.0 and g2 >= 0.0:
                    last = cc
                    break
            base = (r - r0) * bw - c0
            if valid[r, first]:
                v = abs(z[r, first] - _end_height(f0, f1, f2, za, zb, zc))
                if v < vbuf[base + first]:  # NaN (no sample) never replaces
                    vbuf[base + first] = v
            if last != first and valid[r, last]:
                v = abs(z[r, last] - _end_height(g0, g1, g2, za, zb, zc))
                if v < vbuf[base + last]:
                    vbuf[base + last] = v
            # Run interior, branch-free with unsigned indices (no wraparound checks) so that it vectorises.
            ru = np.uint64(r)
            cu = np.uint64(first + 1)
            qu = np.uint64(base + first + 1)
            for i in range(np.uint64(max(last - first - 1, 0))):
                sx = first + 1.0 + np.float64(i)
                l1 = (a1 - ey1 * (sx - px1)) * m1
                l2 = (a2 - ey2 * (sx - px2)) * m2
                v = abs(z[ru, cu + i] - (za + (l1 * dzb + l2 * dzc) * inv))
                v = v if valid[ru, cu + i] else np.inf
                old = vbuf[qu + i]
                vbuf[qu + i] = v if v < old else old  # NaN (no sample) never replaces


@leaf
def _segment_dist2(px, py, pz, ax, ay, az, bx, by, bz):
    """Squared distance from p to segment a-b (a point when a == b)."""
    ux, uy, uz = bx - ax, by - ay, bz - az
    wx, wy, wz = px - ax, py - ay, pz - az
    uu = ux * ux + uy * uy + uz * uz
    t = 0.0
    if uu > 0.0:
        t = min(max((wx * ux + wy * uy + wz * uz) / uu, 0.0), 1.0)
    dx, dy, dz = wx - t * ux, wy - t * uy, wz - t * uz
    return dx * dx + dy * dy + dz * dz


@leaf
def _point_triangle_dist2(px, py, pz, ax, ay, az, bx, by, bz, cx, cy, cz):
    """Squared distance from p to triangle abc, Ericson's Voronoi-region walk (RTCD 5.1.5).

    Collinear (zero-area) triangles, where the face region's denominator vanishes, fall back to the
    distance to their three edges.
    """
    abx, aby, abz = bx - ax, by - ay, bz - az
    acx, acy, acz = cx - ax, cy - ay, cz - az
    apx, apy, apz = px - ax, py - ay, pz - az
    d1 = abx * apx + aby * apy + abz * apz
    d2 = acx * apx + acy * apy + acz * apz
    if d1 <= 0.0 and d2 <= 0.0:  # vertex region a
        return apx * apx + apy * apy + apz * apz
    bpx, bpy, bpz = px - bx, py - by, pz - bz
    d3 = abx * bpx + aby * bpy + abz * bpz
    d4 = acx * bpx + acy * bpy + acz * bpz
    if d3 >= 0.0 and d4 <= d3:  # vertex region b
        return bpx * bpx + bpy * bpy + bpz * bpz
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:  # edge region ab
        v = d1 / (d1 - d3)
        qx, qy, qz = apx - v * abx, apy - v * aby, apz - v * abz
        return qx * qx + qy * qy + qz * qz
    cpx, cpy, cpz = px - cx, py - cy, pz - cz
    d5 = abx * cpx + aby * cpy + abz * cpz
    d6 = acx * cpx + acy * cpy + acz * cpz
    if d6 >= 0.0 and d5 <= d6:  # vertex region c
        return cpx * cpx + cpy * cpy + cpz * cpz
    vb = d5 * d2 - d1 * d6
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:  # edge region ac
        w = d2 / (d2 - d6)
        qx, qy, qz = apx - w * acx, apy - w * acy, apz - w * acz
        return qx * qx + qy * qy + qz * qz
    va = d3 * d6 - d5 * d4
    if va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:  # edge region bc
        w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        qx, qy, qz = bpx - w * (cx - bx), bpy - w * (cy - by), bpz - w * (cz - bz)
        return qx * qx + qy * qy + qz * qz
    denom = va + vb + vc
    if not denom > 0.0:  # collinear: the triangle is its edges
        return min(
            _segment_dist2(px, py, pz, ax, ay, az, bx, by, bz),
            _segment_dist2(px, py, pz, bx, by, bz, cx, cy, cz),
            _segment_dist2(px, py, pz, cx, cy, cz, ax, ay, az),
        )
    v = vb / denom  # face region: p projects inside
    w = vc / denom
    qx = apx - v * abx - w * acx
    qy = apy - v * aby - w * acy
    qz = apz - v * abz - w * acz
    return qx * qx + qy * qy + qz * qz


@jit
def _triangle_boxes(verts, tris):
    """(K, 6) bounding boxes, metres: x min, x max, y min, y max, z min, z max."""
    k = tris.shape[0]
    box = np.empty((k, 6), np.float64)
    for t in range(k):
        a, b, c = tris[t, 0], tris[t, 1], tris[t, 2]
        for j in range(3):
            box[t, 2 * j] = min(verts[a, j], verts[b, j], verts[c, j])
            box[t, 2 * j + 1] = max(verts[a, j], verts[b, j], verts[c, j])
    return box


@leaf
def _search_bucket(b, start, items, verts, tris, box, px, py, pz, best2, stop2, stamp, sid):
    """Lower best2 with the triangles of bucket b not yet seen by search sid; stops early at stop2."""
    for it in range(start[b], start[b + 1]):
        t = items[it]
        if stamp[t] == sid:
            continue
        stamp[t] = sid
        # Box lower bound first: most candidates end here.
        gx = max(box[t, 0] - px, 0.0, px - box[t, 1])
        gy = max(box[t, 2] - py, 0.0, py - box[t, 3])
        gz = max(box[t, 4] - pz, 0.0, pz - box[t, 5])
        if (gx * gx + gy * gy + gz * gz) * _LB_SHRINK >= best2:
            continue
        a, bb, c = tris[t, 0], tris[t, 1], tris[t, 2]
        d2 = _point_triangle_dist2(
            px, py, pz,
            verts[a, 0], verts[a, 1], verts[a, 2],
            verts[bb, 0], verts[bb, 1], verts[bb, 2],
            verts[c, 0], verts[c, 1], verts[c, 2],
        )  # fmt: skip
        if d2 < best2:
            best2 = d2
            if best2 <= stop2:
                break
    return best2


@jit
def _bucket_pyramid(box, start, items, nbr, nbc):
    """Bounding boxes of the buckets' triangles (metres), and of 2 x 2 groups of them up to one root.

    Returns (nodes (M, 6), level_offset, level_rows, level_cols): level 0 is the bucket grid (row-major),
    level l + 1 merges 2 x 2 cells of level l. An empty cell keeps an inverted (+inf, -inf) box, whose
    distance is inf, so it is never opened.
    """
    nlev = 1
    r, c = nbr, nbc
    total = r * c
    while r > 1 or c > 1:
        r = (r + 1) // 2
        c = (c + 1) // 2
        total += r * c
        nlev += 1
    off = np.empty(nlev + 1, np.int64)
    rows = np.empty(nlev, np.int64)
    cols = np.empty(nlev, np.int64)
    nodes = np.empty((total, 6), np.float64)
    for i in range(total):
        for j in range(0, 6, 2):
            nodes[i, j] = np.inf
            nodes[i, j + 1] = -np.inf
    r, c = nbr, nbc
    off[0] = 0
    for lev in range(nlev):
        rows[lev] = r
        cols[lev] = c
        off[lev + 1] = off[lev] + r * c
        r = (r + 1) // 2
        c = (c + 1) // 2
    for b in range(nbr * nbc):
        for it in range(start[b], start[b + 1]):
            t = items[it]
            for j in range(0, 6, 2):
                nodes[b, j] = min(nodes[b, j], box[t, j])
                nodes[b, j + 1] = max(nodes[b, j + 1], box[t, j + 1])
    for lev in range(1, nlev):
        for i in range(rows[lev - 1]):
            for j in range(cols[lev - 1]):
                src = off[lev - 1] + i * cols[lev - 1] + j
                dst = off[lev] + (i // 2) * cols[lev] + j // 2
                for q in range(0, 6, 2):
                    nodes[dst, q] = min(nodes[dst, q], nodes[src, q])
                    nodes[dst, q + 1] = max(nodes[dst, q + 1], nodes[src, q + 1])
    return nodes, off, rows, cols


@leaf
def _box_dist2(nodes, i, px, py, pz):
    """Squared distance from p to box i of nodes (inf for an empty box)."""
    gx = max(nodes[i, 0] - px, 0.0, px - nodes[i, 1])
    gy = max(nodes[i, 2] - py, 0.0, py - nodes[i, 3])
    gz = max(nodes[i, 4] - pz, 0.0, pz - nodes[i, 5])
    return gx * gx + gy * gy + gz * gz


@leaf
def _sample_dist2(px, py, pz, v, pyramid, start, items, verts, tris, box, stop2, stamp, sid, stack):
    """Squared distance from p to the mesh, or any value <= stop2 once it cannot exceed it.

    v is the sample's vertical error, an upper bound. Best-first descent of the bucket pyramid (see
    ``_bucket_pyramid``): a cell is opened only while the distance to its box is below the best distance
    found so far, nearest child first, so the search stays local however large v is. sid is a number no
    earlier search used (it marks the triangles already tested); stack is scratch of at least
    3 * levels + 1 entries.
    """
    nodes, off, rows, cols = pyramid
    best2 = v * v
    stack[0] = off[len(rows) - 1]  # the root
    sp = 1
    while sp > 0:
        sp -= 1
        node = stack[sp]
        if _box_dist2(nodes, node, px, py, pz) * _LB_SHRINK >= best2:
            continue
        if node < off[1]:  # a bucket
            best2 = _search_bucket(node, start, items, verts, tris, box, px, py, pz, best2, stop2, stamp, sid)
            if best2 <= stop2:
                return best2
            continue
        lev = 1
        while node >= off[lev + 1]:
            lev += 1
        # Open children worth opening, pushed farthest first so that the nearest is opened next.
        i = (node - off[lev]) // cols[lev]
        j = (node - off[lev]) % cols[lev]
        first = sp
        for ci in range(2 * i, min(2 * i + 2, rows[lev - 1])):
            for cj in range(2 * j, min(2 * j + 2, cols[lev - 1])):
                child = off[lev - 1] + ci * cols[lev - 1] + cj
                d = _box_dist2(nodes, child, px, py, pz)
                if d * _LB_SHRINK >= best2:
                    continue
                q = sp
                while q > first and _box_dist2(nodes, stack[q - 1], px, py, pz) < d:
                    stack[q] = stack[q - 1]
                    q -= 1
                stack[q] = child
                sp += 1
    return best2


@leaf
def _bucket_stats(vbuf, r0, r1, c0, c1, w):
    """Count, sum of squares, max and where (window index r * w + c) of the finite entries of one bucket."""
    bw = c1 - c0 + 1
    n = 0
    sumsq = 0.0
    vmax = -1.0
    arg = -1
    for q in range((r1 - r0 + 1) * bw):
        v = vbuf[q]
        if v == np.inf:
            continue
        n += 1
        sumsq += v * v
        if v > vmax:
            vmax = v
            arg = (r0 + q // bw) * w + c0 + q % bw
    return n, sumsq, vmax, arg


@jit
def _rasterise_rows(uv, verts, tris, z, valid, dirty, vall):
    """Rasterise into vall (h * w) the rows r with dirty[r] only, run of rows by run of rows, each with
    the triangles whose row span meets it. Rows are independent (a triangle's row is computed from the
    row alone, its columns clipped to the whole window as always), so each row gets the values a whole
    window's rasterisation gives it, bit for bit."""
    h, w = z.shape
    k = tris.shape[0]
    tlo = np.empty(k, np.int64)
    thi = np.empty(k, np.int64)
    for t in range(k):
        a, b, c = tris[t, 0], tris[t, 1], tris[t, 2]
        tlo[t] = int(math.floor(min(uv[a, 1], uv[b, 1], uv[c, 1]))) - 1
        thi[t] = int(math.ceil(max(uv[a, 1], uv[b, 1], uv[c, 1]))) + 1
    items = np.empty(k, np.int64)
    r = 0
    while r < h:
        if not dirty[r]:
            r += 1
            continue
        e = r
        while e + 1 < h and dirty[e + 1]:
            e += 1
        n = 0
        for t in range(k):
            if thi[t] >= r and tlo[t] <= e:
                items[n] = t
                n += 1
        _rasterise_bucket(uv, verts, tris, items, 0, n, z, valid, r, e, 0, w - 1, vall[r * w : (e + 1) * w])
        r = e + 1


@jit
def _vertical_pass(uv, verts, tris, z, valid, bs, nbr, nbc, start, items, vall, dirty):
    """Pass 1: vertical error of every covered sample.

    Returns (max_v, sumsq, n, worst, bmax, barg): worst is the window index r * w + c of a sample
    attaining max_v; per bucket, bmax is the max vertical error (-1 when the bucket covers nothing) and
    barg where it is. With vall of h * w entries, every triangle is rasterised straight into it (inf
    where not covered) and start/items are not used; a ``dirty`` mask of h rows limits that to its rows
    (the other rows of vall are taken as they are: see :func:`tile_error_rows`), an empty one means
    every row. Else bucket by bucket through a bucket of scratch, with start/items the buckets'
    triangles (dirty unused).
    """
    h, w = z.shape
    keep = vall.shape[0] == h * w
    if keep and dirty.shape[0] == 0:
        k = tris.shape[0]
        _rasterise_bucket(uv, verts, tris, np.arange(k), 0, k, z, valid, 0, h - 1, 0, w - 1, vall)
    elif keep:
        _rasterise_rows(uv, verts, tris, z, valid, dirty, vall)
    vbuf = np.empty(0 if keep else bs * bs, np.float64)
    bmax = np.full(nbr * nbc, -1.0)
    barg = np.full(nbr * nbc, -1, np.int64)
    sumsq = 0.0
    n = 0
    for bi in range(nbr):
        r0 = bi * bs
        r1 = min(r0 + bs, h) - 1
        for bj in range(nbc):
            c0 = bj * bs
            c1 = min(c0 + bs, w) - 1
            b = bi * nbc + bj
            if keep:
                for r in range(r0, r1 + 1):  # bucket stats straight from vall
                    for c in range(c0, c1 + 1):
                        v = vall[r * w + c]
                        if v == np.inf:
                            continue
                        n += 1
                        sumsq += v * v
                        if v > bmax[b]:
                            bmax[b] = v
                            barg[b] = r * w + c
                continue
            if start[b] == start[b + 1]:
                continue
            _rasterise_bucket(uv, verts, tris, items, start[b], start[b + 1], z, valid, r0, r1, c0, c1, vbuf)
            nb_, sq, bmax[b], barg[b] = _bucket_stats(vbuf, r0, r1, c0, c1, w)
            n += nb_
            sumsq += sq
    max_v = -1.0
    worst = -1
    for b in range(nbr * nbc):
        if bmax[b] > max_v:
            max_v = bmax[b]
            worst = barg[b]
    return max_v, sumsq, n, worst, bmax, barg


@jit
def _hausdorff_pass(uv, verts, tris, z, valid, dx, dy, bs, nbr, nbc, start, items, vall, bmax, barg):
    """Pass 2: max over covered samples of the exact distance to the mesh (squared), and its sample.

    A sample is searched only while its vertical error (an upper bound of its distance) exceeds the
    running max. Seed: the worst sample of each of the worst buckets, which lifts the running max close
    to its final value. Sweep: buckets by decreasing max vertical error, stopping at the first whose max
    does not exceed the running max.
    """
    h, w = z.shape
    keep = vall.shape[0] == h * w
    box = _triangle_boxes(verts, tris)
    pyramid = _bucket_pyramid(box, start, items, nbr, nbc)
    stack = np.empty(3 * len(pyramid[2]) + 4, np.int64)
    stamp = np.full(tris.shape[0], -1, np.int64)
    sid = 0
    order = np.argsort(-bmax, kind="mergesort")
    hd2 = 0.0
    worst = barg[order[0]]
    for ob in range(min(nbr * nbc, _SEED_BUCKETS)):
        b = order[ob]
        if bmax[b] <= 0.0 or bmax[b] * bmax[b] <= hd2:
            break  # (bmax is -1 for buckets that cover nothing)
        r = barg[b] // w
        c = barg[b] % w
        zs = np.float64(z[r, c])
        d2 = _sample_dist2(
            c * dx, r * dy, zs, bmax[b], pyramid, start, items, verts, tris, box, hd2, stamp, sid, stack
        )
        sid += 1
        if d2 > hd2:
            hd2 = d2
            worst = barg[b]
    vbuf = np.empty(bs * bs, np.float64)
    for ob in range(nbr * nbc):
        b = order[ob]
        if bmax[b] <= 0.0 or bmax[b] * bmax[b] <= hd2:
            break  # this bucket and every later one: no sample's bound exceeds the running max
        r0 = (b // nbc) * bs
        r1 = min(r0 + bs, h) - 1
        c0 = (b % nbc) * bs
        c1 = min(c0 + bs, w) - 1
        bw = c1 - c0 + 1
        if keep:
            for q in range((r1 - r0 + 1) * bw):
                vbuf[q] = vall[(r0 + q // bw) * w + c0 + q % bw]
        else:
            _rasterise_bucket(uv, verts, tris, items, start[b], start[b + 1], z, valid, r0, r1, c0, c1, vbuf)
        for q in range((r1 - r0 + 1) * bw):
            v = vbuf[q]
            if v == np.inf or v * v <= hd2:
                continue
            r = r0 + q // bw
            c = c0 + q % bw
            zs = np.float64(z[r, c])
            d2 = _sample_dist2(
                c * dx, r * dy, zs, v, pyramid, start, items, verts, tris, box, hd2, stamp, sid, stack
            )
            sid += 1
            if d2 > hd2:
                hd2 = d2
                worst = r * w + c
    return hd2, worst


@jit
def tile_error(verts, tris, z, valid, dx, dy):
    """Vertical and Hausdorff error of a mesh against the window's samples it covers.

    Parameters
    ----------
    verts : (N, 3) float64
        Vertices in the window-local frame, metres: X = col * dx (east), Y = row * dy (south), Z up.
        Finite (not checked here).
    tris : (K, 3) integer
        Vertex indices, each in [0, N) (not checked here), either winding.
    z : (h, w) float32
        Window elevations, metres, row 0 north. NaN samples count as invalid.
    valid : (h, w) bool
        Samples to measure.
    dx, dy : float
        Sample spacing east-west and north-south, metres (> 0).

    Returns
    -------
    max_v : float
        Max vertical error over covered samples, metres (0 when none).
    sumsq_v : float
        Sum of squared vertical errors, m^2.
    n : int
        Number of covered samples.
    hausdorff : float
        One-sided Hausdorff distance from covered samples to the mesh, metres (0 when none).
    worst_v_r, worst_v_c, worst_h_r, worst_h_c : int
        Window (row, col) of the sample attaining each max (-1 when no sample is covered).
    """
    return tile_error_with(verts, tris, z, valid, dx, dy, 0, _KEEP_SAMPLES)


@jit
def tile_error_with(verts, tris, z, valid, dx, dy, bucket_size, keep_samples):
    """:func:`tile_error` with its two speed settings given (all arguments positional).

    bucket_size is the bucket side in samples (0: from the triangle density); windows of at most
    keep_samples samples are rasterised once into a per-sample array (8 bytes a sample) that pass 2
    reads, larger ones bucket by bucket, twice. Only speed and memory depend on them; tests vary them to
    exercise every path.
    """
    h, w = z.shape
    vall = np.empty(h * w if h * w <= keep_samples else 0, np.float64)
    return _tile_error(verts, tris, z, valid, dx, dy, bucket_size, vall, np.empty(0, np.bool_))


@jit
def changed_rows(pv, pt, v, t, dy, h):
    """(h,) bool: the window rows that the triangles differing between two meshes of the same counts reach
    in either mesh, with a row of margin (what :func:`tile_error_rows` must rasterise again).

    A triangle differs when an index differs or one of its vertices (in either mesh) moved; it reaches
    rows ``floor(min y / dy) - 1`` to ``ceil(max y / dy) + 1`` of each mesh, clipped to the window.
    pv, v : (N, 3) float64 vertices (window frame, metres); pt, t : (K, 3) integer triangles.
    """
    n = v.shape[0]
    moved = np.zeros(n, np.bool_)
    for i in range(n):
        moved[i] = pv[i, 0] != v[i, 0] or pv[i, 1] != v[i, 1] or pv[i, 2] != v[i, 2]
    edges = np.zeros(h + 1, np.int64)
    for k in range(t.shape[0]):
        a0, a1, a2 = pt[k, 0], pt[k, 1], pt[k, 2]
        b0, b1, b2 = t[k, 0], t[k, 1], t[k, 2]
        if not (a0 != b0 or a1 != b1 or a2 != b2 or moved[a0] or moved[a1] or moved[a2] or moved[b0]
                or moved[b1] or moved[b2]):  # fmt: skip
            continue
        for m in range(2):
            if m == 0:
                y0, y1, y2 = pv[a0, 1] / dy, pv[a1, 1] / dy, pv[a2, 1] / dy
            else:
                y0, y1, y2 = v[b0, 1] / dy, v[b1, 1] / dy, v[b2, 1] / dy
            lo = min(max(np.int64(math.floor(min(y0, y1, y2))) - 1, 0), h)
            hi = min(max(np.int64(math.ceil(max(y0, y1, y2))) + 2, 0), h)  # one past the last row
            edges[lo] += 1
            edges[hi] -= 1
    out = np.empty(h, np.bool_)
    run = 0
    for r in range(h):
        run += edges[r]
        out[r] = run > 0
    return out


@jit
def tile_error_rows(verts, tris, z, valid, dx, dy, vall, dirty):
    """:func:`tile_error` of a mesh that differs from a previously measured one only on some rows.

    ``vall`` ((h * w,) float64, h * w <= ``_KEEP_SAMPLES``) holds the per-sample vertical errors: on
    entry those of the previous mesh (left there by the previous call; an all-True ``dirty`` measures
    from scratch), on return those of this mesh. ``dirty`` ((h,) bool): the caller guarantees that every
    triangle covering a sample of a row that is not dirty is, in both meshes, the same triangle (same
    index, same vertex coordinates). Only the dirty rows are rasterised again; everything else (the
    bucket statistics, the Hausdorff pass) runs on the whole window as in :func:`tile_error`, so the
    result is :func:`tile_error`'s bit for bit.
    """
    return _tile_error(verts, tris, z, valid, dx, dy, 0, vall, dirty)


@jit
def _tile_error(verts, tris, z, valid, dx, dy, bucket_size, vall, dirty):
    """Body of :func:`tile_error_with` and :func:`tile_error_rows`: vall of h * w entries selects the
    per-sample path (only the dirty rows rasterised, every row when dirty is empty), of 0 entries the
    bucket path."""
    h, w = z.shape
    k = tris.shape[0]
    keep = vall.shape[0] == h * w
    if k == 0 or h == 0 or w == 0:
        if keep:
            vall[:] = np.inf  # nothing covered (a later tile_error_rows call starts from here)
        return 0.0, 0.0, 0, 0.0, -1, -1, -1, -1
    bs = bucket_size
    if bs <= 0:
        lo = _MIN_BUCKET_KEEP if keep else _MIN_BUCKET
        bs = int(min(max(_BUCKET_SCALE * math.sqrt(h * w / k), lo), _MAX_BUCKET))
    nbr = (h + bs - 1) // bs
    nbc = (w + bs - 1) // bs
    uv = _sample_units(verts, dx, dy)
    if keep:  # pass 1 rasterises into vall; pass 2 needs each triangle in one bucket only
        start = items = np.empty(0, np.int64)
    else:
        start, items = _bin_triangles(uv, tris, nbr, nbc, bs)
    max_v, sumsq, n, wv, bmax, barg = _vertical_pass(
        uv, verts, tris, z, valid, bs, nbr, nbc, start, items, vall, dirty
    )
    if n == 0:
        return 0.0, 0.0, 0, 0.0, -1, -1, -1, -1
    if max_v == 0.0:  # the mesh passes through every covered sample
        return 0.0, sumsq, n, 0.0, wv // w, wv % w, wv // w, wv % w
    if keep:
        start, items = _bin_centroids(uv, tris, nbr, nbc, bs)
    hd2, wh = _hausdorff_pass(uv, verts, tris, z, valid, dx, dy, bs, nbr, nbc, start, items, vall, bmax, barg)
    return max_v, sumsq, n, math.sqrt(hd2), wv // w, wv % w, wh // w, wh % w


# -- scattered points in square buckets ------------------------------------------------------------------
@jit
def bucket_points(px, py, x0, y0, inv_x, inv_y, nb):  # pragma: no cover - numba
    """Points (px, py) counted into nb x nb square buckets from (x0, y0), ``inv_*`` buckets per unit:
    (start (nb * nb + 1,), order (n,)): bucket k holds points order[start[k]:start[k + 1]], in input order.
    Points off the grid go to its edge buckets."""
    n = px.size
    cell = np.empty(n, np.int64)
    start = np.zeros(nb * nb + 1, np.int64)
    for i in range(n):
        cx = min(max(int((px[i] - x0) * inv_x), 0), nb - 1)
        cy = min(max(int((py[i] - y0) * inv_y), 0), nb - 1)
        cell[i] = cy * nb + cx
        start[cell[i] + 1] += 1
    for k in range(nb * nb):
        start[k + 1] += start[k]
    fill = start[:-1].copy()
    order = np.empty(n, np.int64)
    for i in range(n):
        order[fill[cell[i]]] = i
        fill[cell[i]] += 1
    return start, order


# -- web-export tiles (u/v units, vertical distance only) ------------------------------------------------
@jit
def points_vertical_error(tu, tv, th, tris, pu, pv, pz):  # pragma: no cover - numba
    """Max |surface - z| over points (pu, pv, pz) of the triangles (tu, tv, th) in u/v units, and how many
    points no triangle covered (the points are bucketed on a square grid; each triangle visits the
    buckets of its bounding box; a point on a shared edge is tested by both triangles)."""
    n = pu.size
    nb = max(1, min(256, int(math.sqrt(n / 4.0)) + 1))
    scale = nb / 32768.0
    start, order = bucket_points(pu, pv, 0.0, 0.0, scale, scale, nb)
    covered = np.zeros(n, np.bool_)
    err = 0.0
    for t in range(tris.shape[0]):
        a, b, c = tris[t, 0], tris[t, 1], tris[t, 2]
        ua, va, ub, vb, uc, vc = tu[a], tv[a], tu[b], tv[b], tu[c], tv[c]
        det = (vb - vc) * (ua - uc) + (uc - ub) * (va - vc)
        if det == 0.0:
            continue
        x0 = min(max(int(min(ua, ub, uc) * scale), 0), nb - 1)
        x1 = min(max(int(max(ua, ub, uc) * scale), 0), nb - 1)
        y0 = min(max(int(min(va, vb, vc) * scale), 0), nb - 1)
        y1 = min(max(int(max(va, vb, vc) * scale), 0), nb - 1)
        tol = 1e-9
        for cy in range(y0, y1 + 1):
            for cx in range(x0, x1 + 1):
                k = cy * nb + cx
                for j in range(start[k], start[k + 1]):
                    i = order[j]
                    d = triangle_gap(
                        ua, va, ub, vb, uc, vc, det, th[a], th[b], th[c], pu[i], pv[i], pz[i], tol
                    )
                    if d >= 0.0:
                        if d > err:
                            err = d
                        covered[i] = True
    missed = 0
    for i in range(n):
        if not covered[i]:
            missed += 1
    return err, missed


@jit
def lattice_vertical_error(tu, tv, th, tris, pu, pv, zwin, vwin):  # pragma: no cover - numba
    """Vertical distance between triangles (tu, tv, th; u/v units) and the lattice points (pu[k], pv[j])
    of heights zwin[j, k] where vwin[j, k] (a valid sample). Returns (max over every test, sum of squares
    and count over the samples, each once: at the first triangle that covers it, valid samples that no
    triangle covers). pu increases, pv decreases (north row first). Each triangle tests the points of its
    rows between its edges (a small margin, then the same barycentric test as the scattered-point kernel:
    edges included). Only a (rows, cols) byte array besides the inputs: a tile that spans the whole DEM
    needs one byte per sample."""
    nj, nk = zwin.shape
    if nj == 0 or nk == 0:
        return 0.0, 0.0, 0, 0
    seen = np.zeros((nj, nk), np.uint8)
    sumsq = 0.0
    count = 0
    pu0 = pu[0]
    du = (pu[nk - 1] - pu[0]) / (nk - 1) if nk > 1 else 1.0
    pv0 = pv[0]
    dv = (pv[0] - pv[nj - 1]) / (nj - 1) if nj > 1 else 1.0
    if du <= 0.0:
        du = 1.0
    if dv <= 0.0:
        dv = 1.0
    err = 0.0
    tol = 1e-9
    for t in range(tris.shape[0]):
        a, b, c = tris[t, 0], tris[t, 1], tris[t, 2]
        ua, va, ub, vb, uc, vc = tu[a], tv[a], tu[b], tv[b], tu[c], tv[c]
        det = (vb - vc) * (ua - uc) + (uc - ub) * (va - vc)
        if det == 0.0:
            continue
        vmin = min(va, vb, vc)
        vmax = max(va, vb, vc)
        j0 = max(int(math.floor((pv0 - vmax) / dv)) - 1, 0)
        j1 = min(int(math.ceil((pv0 - vmin) / dv)) + 1, nj - 1)
        for j in range(j0, j1 + 1):
            y = pv[j]
            if y < vmin - 1e-6 or y > vmax + 1e-6:
                continue
            lo = 1e300
            hi = -1e300
            for q in range(3):
                if q == 0:
                    u1, v1, u2, v2 = ua, va, ub, vb
                elif q == 1:
                    u1, v1, u2, v2 = ub, vb, uc, vc
                else:
                    u1, v1, u2, v2 = uc, vc, ua, va
                if v1 == v2:
                    if abs(y - v1) <= 1e-6:
                        lo = min(lo, u1, u2)
                        hi = max(hi, u1, u2)
                elif min(v1, v2) - 1e-6 <= y <= max(v1, v2) + 1e-6:
                    x = u1 + (y - v1) * (u2 - u1) / (v2 - v1)
                    lo = min(lo, x)
                    hi = max(hi, x)
            if hi < lo:
                continue
            k0 = max(int(math.floor((lo - pu0) / du)) - 1, 0)
            k1 = min(int(math.ceil((hi - pu0) / du)) + 1, nk - 1)
            for k in range(k0, k1 + 1):
                if not vwin[j, k]:
                    continue
                x = pu[k]
                d = triangle_gap(ua, va, ub, vb, uc, vc, det, th[a], th[b], th[c], x, y, zwin[j, k], tol)
                if d >= 0.0:
                    if d > err:
                        err = d
                    if seen[j, k] == 0:
                        seen[j, k] = 1
                        sumsq += d * d
                        count += 1
    missed = 0
    for j in range(nj):
        for k in range(nk):
            if vwin[j, k] and seen[j, k] == 0:
                missed += 1
    return err, sumsq, count, missed
