"""Numba kernels of the runtime stitcher and boundary normals (``../shared/papers/002_037d1654b87e3b6a.txt``
§3.3–3.4). Pure functions on arrays: no I/O, no exceptions; validation lives in
:mod:`terralod.runtime.stitch` and :mod:`terralod.runtime.normals`.

Vocabulary: an *edge polyline* is the ordered list of a tile's vertices on one side of its square, given
by their position ``t`` along the side (source rows for the west/east sides, source columns for the
north/south sides; fractional for relocated boundary vertices) and their heights ``h`` in metres.
"""

from __future__ import annotations

import numpy as np

from terralod.kernels import jit


@jit
def polyline_at(t, h, q):
    """Heights of the polyline (t ascending, h) at positions q, clamped at its ends; exact at nodes."""
    n = t.shape[0]
    out = np.empty(q.shape[0], np.float64)
    for i in range(q.shape[0]):
        x = q[i]
        if x <= t[0]:
            out[i] = h[0]
        elif x >= t[n - 1]:
            out[i] = h[n - 1]
        else:
            j = np.searchsorted(t, x, side="right") - 1  # t[j] <= x < t[j + 1]
            if x == t[j]:
                out[i] = h[j]
            else:
                w = (x - t[j]) / (t[j + 1] - t[j])
                out[i] = h[j] + w * (h[j + 1] - h[j])
    return out


@jit
def stitch_edge(t_f, t_c, h_c, tol):
    """Paper 002 §3.3 step 2 for one edge and any LoD difference.

    Parameters: fine edge positions ``t_f`` (ascending), the coarse neighbour's final edge polyline
    (``t_c`` ascending, ``h_c`` metres) and a position tolerance (samples).

    Returns ``(h_f, ins_seg, ins_t, ins_h)``: the fine vertices' heights on the coarse polyline, and the
    coarse nodes lying strictly inside a fine segment (``ins_seg[i]`` = index j of segment (j, j + 1);
    ascending), which the caller inserts into the fine mesh so its edge follows every bend of the coarse
    edge (only needed when boundary vertices were relocated; grid tiles never need it).
    """
    h_f = polyline_at(t_c, h_c, t_f)
    nf = t_f.shape[0]
    lo = t_f[0]
    hi = t_f[nf - 1]
    cnt = 0
    for k in range(t_c.shape[0]):
        x = t_c[k]
        if x <= lo + tol or x >= hi - tol:
            continue
        j = np.searchsorted(t_f, x, side="right") - 1
        if abs(x - t_f[j]) <= tol or (j + 1 < nf and abs(t_f[j + 1] - x) <= tol):
            continue
        cnt += 1
    ins_seg = np.empty(cnt, np.int64)
    ins_t = np.empty(cnt, np.float64)
    ins_h = np.empty(cnt, np.float64)
    m = 0
    for k in range(t_c.shape[0]):
        x = t_c[k]
        if x <= lo + tol or x >= hi - tol:
            continue
        j = np.searchsorted(t_f, x, side="right") - 1
        if abs(x - t_f[j]) <= tol or (j + 1 < nf and abs(t_f[j + 1] - x) <= tol):
            continue
        ins_seg[m] = j
        ins_t[m] = x
        ins_h[m] = h_c[k]
        m += 1
    return h_f, ins_seg, ins_t, ins_h


@jit
def split_boundary_triangles(tris, seg_tri, seg_rot, seg_lo, ins_seg, ins_vid):
    """Fan-split the boundary triangle of each fine segment that receives inserted vertices.

    ``seg_tri[j]`` is the triangle holding boundary segment j, ``seg_rot[j]`` the corner r of that triangle
    where the segment starts (its endpoints are corners r and r + 1, counter-clockwise) and ``seg_lo[j]``
    the vertex index of the segment's lower-``t`` end; ``ins_seg`` (ascending) / ``ins_vid`` give the
    inserted vertex indices in ascending ``t``. A triangle (a, b, o) with a-b on the boundary becomes
    (a, q1, o), (q1, q2, o), ..., (qk, b, o): same orientation, same plane, no new interior vertex.
    Returns the new (K', 3) uint32 triangle array.
    """
    k = tris.shape[0]
    out = np.empty((k + ins_seg.shape[0], 3), np.uint32)
    out[:k] = tris
    nxt = k
    i = 0
    n = ins_seg.shape[0]
    while i < n:
        j = ins_seg[i]
        e = i
        while e < n and ins_seg[e] == j:
            e += 1
        ti = seg_tri[j]
        if ti < 0:
            i = e
            continue
        r = seg_rot[j]
        a = tris[ti, r]
        b = tris[ti, (r + 1) % 3]
        o = tris[ti, (r + 2) % 3]
        forward = a == seg_lo[j]  # then the inserted vertices run from a to b in ascending t
        prev = a
        for m in range(e - i):
            q = ins_vid[i + m] if forward else ins_vid[e - 1 - m]
            row = ti if m == 0 else nxt
            out[row, 0] = prev
            out[row, 1] = q
            out[row, 2] = o
            if m > 0:
                nxt += 1
            prev = q
        out[nxt, 0] = prev
        out[nxt, 1] = b
        out[nxt, 2] = o
        nxt += 1
        i = e
    return out[:nxt]


@jit
def normal_sums(v, tris):
    """(N, 3) float64: per vertex, the sum of cross(b - a, c - a) / 2 of its triangles (area-weighted)."""
    out = np.zeros((v.shape[0], 3), np.float64)
    for t in range(tris.shape[0]):
        a = tris[t, 0]
        b = tris[t, 1]
        c = tris[t, 2]
        ux = v[b, 0] - v[a, 0]
        uy = v[b, 1] - v[a, 1]
        uz = v[b, 2] - v[a, 2]
        wx = v[c, 0] - v[a, 0]
        wy = v[c, 1] - v[a, 1]
        wz = v[c, 2] - v[a, 2]
        nx = 0.5 * (uy * wz - uz * wy)
        ny = 0.5 * (uz * wx - ux * wz)
        nz = 0.5 * (ux * wy - uy * wx)
        for p in (a, b, c):
            out[p, 0] += nx
            out[p, 1] += ny
            out[p, 2] += nz
    return out


@jit
def triangle_cross(v, tris, ids):
    """(len(ids), 3) float64 cross(b - a, c - a) / 2 of the triangles ``ids`` (zeros where id < 0)."""
    out = np.zeros((ids.shape[0], 3), np.float64)
    for i in range(ids.shape[0]):
        t = ids[i]
        if t < 0:
            continue
        a = tris[t, 0]
        b = tris[t, 1]
        c = tris[t, 2]
        ux = v[b, 0] - v[a, 0]
        uy = v[b, 1] - v[a, 1]
        uz = v[b, 2] - v[a, 2]
        wx = v[c, 0] - v[a, 0]
        wy = v[c, 1] - v[a, 1]
        wz = v[c, 2] - v[a, 2]
        out[i, 0] = 0.5 * (uy * wz - uz * wy)
        out[i, 1] = 0.5 * (uz * wx - ux * wz)
        out[i, 2] = 0.5 * (ux * wy - uy * wx)
    return out


@jit
def patch_normal_sums(sums, v_old, v_new, tris, ids):
    """In place: replace the contribution of triangles ``ids`` computed on ``v_old`` by that on ``v_new``."""
    old = triangle_cross(v_old, tris, ids)
    new = triangle_cross(v_new, tris, ids)
    for i in range(ids.shape[0]):
        t = ids[i]
        for r in range(3):
            p = tris[t, r]
            for a in range(3):
                sums[p, a] += new[i, a] - old[i, a]


@jit
def normalize_rows(sums, rows, out):
    """In place: ``out[rows] = sums[rows] / |sums[rows]|`` as float32 (+z where the sum vanishes)."""
    for i in range(rows.shape[0]):
        r = rows[i]
        x = sums[r, 0]
        y = sums[r, 1]
        z = sums[r, 2]
        n = np.sqrt(x * x + y * y + z * z)
        if n > 0.0:
            out[r, 0] = x / n
            out[r, 1] = y / n
            out[r, 2] = z / n
        else:
            out[r, 0] = 0.0
            out[r, 1] = 0.0
            out[r, 2] = 1.0


@jit
def normalize_all(sums):
    """(N, 3) float32 unit normals of area-weighted sums (+z where a sum vanishes)."""
    out = np.empty((sums.shape[0], 3), np.float32)
    normalize_rows(sums, np.arange(sums.shape[0]), out)
    return out


@jit
def add_edge_contributions(t_tab, s_tab, g_tab, t_q, rows, tol, acc):
    """Paper 002 §3.4 steps 2–3 for the vertices of one tile edge against one neighbour edge.

    For each query position ``t_q[i]`` (a boundary vertex of the current tile) that lies on the
    neighbour's edge polyline ``t_tab``: add the neighbour's vertex sum ``s_tab[j]`` when a neighbour
    vertex sits there, else the area-weighted normal ``g_tab[j]`` of the neighbour triangle whose
    boundary segment j contains it — the padding by "analogous subdivision": splitting that triangle at the
    query point gives two coplanar halves whose area-weighted normals add up to the whole triangle's.
    ``acc[rows[i]]`` accumulates (float64).
    """
    n = t_tab.shape[0]
    if n == 0:
        return
    for i in range(t_q.shape[0]):
        x = t_q[i]
        if x < t_tab[0] - tol or x > t_tab[n - 1] + tol:
            continue
        j = np.searchsorted(t_tab, x - tol, side="left")
        r = rows[i]
        if j < n and abs(t_tab[j] - x) <= tol:
            for a in range(3):
                acc[r, a] += s_tab[j, a]
        elif 0 < j < n:
            for a in range(3):
                acc[r, a] += g_tab[j - 1, a]


@jit
def segment_triangles(tris, edge_vid, n_vertices):
    """For each boundary segment (edge_vid[j], edge_vid[j + 1]) of one side: the triangle holding it and the
    corner r of that triangle where the directed edge (r, r + 1) starts; -1 / 0 where none holds it."""
    m = edge_vid.shape[0]
    seg_tri = np.full(max(m - 1, 0), -1, np.int64)
    seg_rot = np.zeros(max(m - 1, 0), np.int64)
    if m < 2:
        return seg_tri, seg_rot
    rank = np.full(n_vertices, -1, np.int64)
    for j in range(m):
        rank[edge_vid[j]] = j
    for t in range(tris.shape[0]):
        for r in range(3):
            ra = rank[tris[t, r]]
            if ra < 0:
                continue
            rb = rank[tris[t, (r + 1) % 3]]
            if rb < 0:
                continue
            if ra - rb == 1 or rb - ra == 1:
                j = min(ra, rb)
                seg_tri[j] = t
                seg_rot[j] = r
    return seg_tri, seg_rot
