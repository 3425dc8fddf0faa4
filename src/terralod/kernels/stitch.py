"""Numba kernels of the runtime stitcher and boundary normals (``../shared/papers/002_037d1654b87e3b6a.txt``
§3.3–3.4). Pure functions on arrays: no I/O, no exceptions; validation lives in
:mod:`terralod.runtime.stitch` and :mod:`terralod.runtime.normals`.

Vocabulary: an *edge polyline* is the ordered list of a tile's vertices on one side of its square, given
by their position ``t`` along the side (source rows for the west/east sides, source columns for the
north/south sides; fractional for relocated boundary vertices) and their heights ``h`` in metres.
"""

from __future__ import annotations

import numpy as np

from terralod.kernels import jit, leaf


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
    """Li, Liu & Liu §3.3 step 2 for one edge and any LoD difference.

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
def split_boundary_triangles(tris, n_t, seg_tri, seg_rot, seg_lo, ins_seg, ins_vid):
    """In place: fan-split the boundary triangle of each fine segment that receives inserted vertices.

    ``tris`` holds ``n_t`` triangles and room for ``len(ins_seg)`` more; ``seg_tri[j]`` is the triangle
    holding boundary segment j, ``seg_rot[j]`` the corner r of that triangle where the segment starts (its
    endpoints are corners r and r + 1, counter-clockwise) and ``seg_lo[j]`` the vertex index of the
    segment's lower-``t`` end; ``ins_seg`` (ascending) / ``ins_vid`` give the inserted vertex indices in
    ascending ``t``. A triangle (a, b, o) with a-b on the boundary becomes (a, q1, o) in its row and
    (q1, q2, o), ..., (qk, b, o) appended: same orientation, same plane, no new interior vertex.
    Returns the new triangle count.
    """
    nxt = n_t
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
            tris[row, 0] = prev
            tris[row, 1] = q
            tris[row, 2] = o
            if m > 0:
                nxt += 1
            prev = q
        tris[nxt, 0] = prev
        tris[nxt, 1] = b
        tris[nxt, 2] = o
        nxt += 1
        i = e
    return nxt


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
def add_triangle_sums(sums, v, tris, ids, sign):
    """In place: add ``sign`` x cross(b - a, c - a) / 2 of the triangles ``ids`` to their vertices' sums."""
    c = triangle_cross(v, tris, ids)
    for i in range(ids.shape[0]):
        for r in range(3):
            p = tris[ids[i], r]
            for a in range(3):
                sums[p, a] += sign * c[i, a]


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
    """Li, Liu & Liu §3.4 steps 2–3 for the vertices of one tile edge against one neighbour edge.

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
def segment_triangles_among(tris, ids, edge_vid, rank):
    """For each boundary segment (edge_vid[j], edge_vid[j + 1]) of one side: the triangle holding it and the
    corner r of that triangle where the directed edge (r, r + 1) starts (-1 / 0 where none holds it),
    looking only at the triangles ``ids`` (ascending; they must include every triangle holding a segment of
    the side, e.g. those touching the tile boundary). ``rank`` is a work
    array of -1 with a row per vertex; it is -1 again on return."""
    m = edge_vid.shape[0]
    seg_tri = np.full(max(m - 1, 0), -1, np.int64)
    seg_rot = np.zeros(max(m - 1, 0), np.int64)
    if m < 2:
        return seg_tri, seg_rot
    for j in range(m):
        rank[edge_vid[j]] = j
    for i in range(ids.shape[0]):
        t = ids[i]
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
    for j in range(m):
        rank[edge_vid[j]] = -1
    return seg_tri, seg_rot


@jit
def _boundary_ids(btris, k0, k):
    """The triangles that may hold a boundary segment after insertions: the stored ones touching the
    boundary, then the rows k0..k-1 that insertions appended."""
    return np.concatenate((btris, np.arange(k0, k).astype(np.int64)))


@jit
def _insert_on_side(verts, n_v, tris, n_t, vid, t, ins_seg, ins_t, ins_h, side, geo, btris, k0, rank):
    """Add the positions ``ins_t`` (heights ``ins_h``) inside segments ``ins_seg`` of side ``side`` as new
    vertices, fan-splitting the boundary triangles that hold those segments, in place: ``verts`` holds
    ``n_v`` vertices and ``tris`` ``n_t`` triangles, both with room for ``len(ins_t)`` more. ``geo`` = (x0,
    y0, dx, dy, c0, c1, r0, r1): the world position of sample (0, 0), the sample spacing and the tile
    square; ``btris`` the stored triangles touching the boundary and ``k0`` the stored triangle count;
    ``rank`` as in :func:`segment_triangles_among`. Returns ``(n_v, n_t, vid, t)`` with the side's vertices
    still ascending along it."""
    k = ins_t.shape[0]
    x0, y0, dx, dy = geo[0], geo[1], geo[2], geo[3]
    for i in range(k):
        if side == 0 or side == 2:
            verts[n_v + i, 0] = x0 + (geo[4] if side == 0 else geo[5]) * dx
            verts[n_v + i, 1] = y0 + ins_t[i] * dy
        else:
            verts[n_v + i, 0] = x0 + ins_t[i] * dx
            verts[n_v + i, 1] = y0 + (geo[6] if side == 1 else geo[7]) * dy
        verts[n_v + i, 2] = ins_h[i]
    new_vid = np.arange(n_v, n_v + k).astype(np.int64)
    seg_tri, seg_rot = segment_triangles_among(tris, _boundary_ids(btris, k0, n_t), vid, rank)
    n_t = split_boundary_triangles(tris, n_t, seg_tri, seg_rot, vid[:-1], ins_seg, new_vid)
    all_t = np.concatenate((t, ins_t))
    order = np.argsort(all_t, kind="mergesort")
    return n_v + k, n_t, np.concatenate((vid, new_vid))[order], all_t[order]


@jit
def stitch_tile(
    verts0, tris0, base_sums, base_normals, btris, btouched, ev, et, eoff, seg0, segoff, corner_vid,
    fit_t, fit_h, fitoff, fit_on, corner_h, corner_on, fine_t, fineoff, fine_on, geo, tol,
):  # fmt: skip
    """Li, Liu & Liu §3.3 for one tile in one call: fit its sides and corners to coarser visible neighbours,
    insert their bend points and the finer neighbours' boundary positions (no T-junction remains), and
    recompute its own-triangle normals and the edge tables its neighbours read (§3.4).

    Inputs: the prepared tile (vertices (N, 3), triangles (K, 3) uint32, own normal sums / normals, the
    triangles touching the boundary and their vertices), its sides' vertex ids ``ev`` and positions ``et``
    concatenated side after side (side e is ``eoff[e]:eoff[e + 1]``) and the triangles holding its side
    segments (:func:`segment_triangles_among`, at ``segoff``), its corner vertex ids (-1: none); per side, the
    coarse polyline to fit to (``fit_t``/``fit_h`` at ``fitoff``, used where ``fit_on``) and the finer
    neighbours' boundary positions (``fine_t`` at ``fineoff``, used where ``fine_on``); per corner the
    height it takes (where ``corner_on``); ``geo`` as in :func:`_insert_on_side`; a position tolerance.

    Returns ``(changed, verts, tris, sums, normals, vid, t, h, off, S, G, goff, boundary_vid, rows)``.
    With ``changed`` false the tile keeps its stored geometry and the other outputs are empty; ``tris`` is
    empty also where no vertex was inserted (the stored triangles stand). Otherwise the side arrays are
    concatenated side after side at ``off`` (``vid``, positions ``t``, heights ``h``, the vertex sums
    ``S``) and at ``goff`` (the segment-triangle terms ``G`` of :func:`add_edge_contributions`);
    ``boundary_vid`` the sorted boundary vertex ids and ``rows`` each side vertex's row in it.
    Normal sums are patched, not recomputed: the stored triangles touching the boundary are taken out as
    stored and put back as they are now (fan pieces and appended rows included); interior sums and
    normals stay the stored ones.
    """
    n0 = verts0.shape[0]
    k0 = tris0.shape[0]
    zs = verts0[:, 2]
    changed = False
    room = 0
    h_fit = []
    i_seg = []
    i_t = []
    i_h = []
    for e in range(4):
        vid = ev[eoff[e] : eoff[e + 1]]
        if fit_on[e]:
            h_f, ins_seg, ins_t, ins_h = stitch_edge(
                et[eoff[e] : eoff[e + 1]],
                fit_t[fitoff[e] : fitoff[e + 1]],
                fit_h[fitoff[e] : fitoff[e + 1]],
                tol,
            )
            for i in range(vid.shape[0]):
                if not zs[vid[i]] == h_f[i]:
                    changed = True
        else:
            h_f = np.empty(0, np.float64)
            ins_seg = np.empty(0, np.int64)
            ins_t = np.empty(0, np.float64)
            ins_h = np.empty(0, np.float64)
        room += ins_t.shape[0]
        if fine_on[e]:
            room += fineoff[e + 1] - fineoff[e]
        h_fit.append(h_f)
        i_seg.append(ins_seg)
        i_t.append(ins_t)
        i_h.append(ins_h)
    for c in range(4):
        if corner_on[c] and not zs[corner_vid[c]] == corner_h[c]:
            changed = True
    e0 = np.empty(0, np.int64)
    f0 = np.empty(0, np.float64)
    g0 = np.empty((0, 3), np.float64)
    no_fine = not (fine_on[0] or fine_on[1] or fine_on[2] or fine_on[3])
    if not changed and no_fine and i_seg[0].size + i_seg[1].size + i_seg[2].size + i_seg[3].size == 0:
        return (
            False,
            g0,
            np.empty((0, 3), np.uint32),
            g0,
            np.empty((0, 3), np.float32),
            e0,
            f0,
            f0,
            e0,
            g0,
            g0,
            e0,
            e0,
            e0,
        )
    verts = np.empty((n0 + room, 3), np.float64)
    verts[:n0] = verts0
    for e in range(4):
        if fit_on[e]:
            vid = ev[eoff[e] : eoff[e + 1]]
            for i in range(vid.shape[0]):
                verts[vid[i], 2] = h_fit[e][i]
    for c in range(4):
        if corner_on[c]:
            verts[corner_vid[c], 2] = corner_h[c]
    n_v = n0
    # the stored (read-only) triangles stand until a vertex is inserted: copied once into tris then
    tris = np.empty((0, 3), np.uint32)
    n_t = k0
    rank = np.full(n0 + room, -1, np.int64)
    fvid = [ev[eoff[e] : eoff[e + 1]].copy() for e in range(4)]
    ft = [et[eoff[e] : eoff[e + 1]].copy() for e in range(4)]
    for e in range(4):
        if i_seg[e].shape[0] > 0:
            if tris.shape[0] == 0:
                tris = np.empty((k0 + room, 3), np.uint32)
                tris[:k0] = tris0
            n_v, n_t, fvid[e], ft[e] = _insert_on_side(
                verts, n_v, tris, n_t, fvid[e], ft[e], i_seg[e], i_t[e], i_h[e], e, geo, btris, k0, rank
            )
    for e in range(4):
        if not fine_on[e] or ft[e].shape[0] < 2:
            continue
        t = ft[e]
        cand = np.unique(fine_t[fineoff[e] : fineoff[e + 1]])
        keep = (cand > t[0] + tol) & (cand < t[-1] - tol)
        cand = cand[keep]
        j = np.searchsorted(t, cand, side="right") - 1
        far = np.ones(cand.shape[0], np.bool_)
        for i in range(cand.shape[0]):
            jn = min(j[i] + 1, t.shape[0] - 1)
            if abs(cand[i] - t[j[i]]) <= tol or abs(t[jn] - cand[i]) <= tol:
                far[i] = False
        cand = cand[far]
        j = j[far]
        if cand.shape[0] > 0:
            hz = np.empty(fvid[e].shape[0], np.float64)
            for i in range(hz.shape[0]):
                hz[i] = verts[fvid[e][i], 2]
            h = polyline_at(t, hz, cand)  # on the edge: the geometry does not change
            if tris.shape[0] == 0:
                tris = np.empty((k0 + room, 3), np.uint32)
                tris[:k0] = tris0
            n_v, n_t, fvid[e], ft[e] = _insert_on_side(
                verts, n_v, tris, n_t, fvid[e], ft[e], j, cand, h, e, geo, btris, k0, rank
            )
    topo = tris.shape[0] > 0
    verts = verts[:n_v]
    sums = np.zeros((n_v, 3), np.float64)
    sums[:n0] = base_sums
    normals = np.empty((n_v, 3), np.float32)
    normals[:n0] = base_normals
    if topo:
        tris = tris[:n_t]
        ids = _boundary_ids(btris, k0, n_t)
        add_triangle_sums(sums, verts0, tris0, btris, -1.0)  # out as stored
        add_triangle_sums(sums, verts, tris, ids, 1.0)  # back as they are now
        normalize_rows(sums, np.concatenate((btouched, np.arange(n0, n_v).astype(np.int64))), normals)
    else:
        patch_normal_sums(sums, verts0, verts, tris0, btris)
        normalize_rows(sums, btouched, normals)
        ids = btris
    off = np.zeros(5, np.int64)
    goff = np.zeros(5, np.int64)
    for e in range(4):
        off[e + 1] = off[e] + fvid[e].shape[0]
        goff[e + 1] = goff[e] + max(fvid[e].shape[0] - 1, 0)
    n_b = off[4]
    vid_all = np.empty(n_b, np.int64)
    t_all = np.empty(n_b, np.float64)
    h_all = np.empty(n_b, np.float64)
    s_all = np.empty((n_b, 3), np.float64)
    g_all = np.empty((goff[4], 3), np.float64)
    for e in range(4):
        m = fvid[e].shape[0]
        if m >= 2:
            if topo:
                seg_tri = segment_triangles_among(tris, ids, fvid[e], rank)[0]
                g_all[goff[e] : goff[e + 1]] = triangle_cross(verts, tris, seg_tri)
            else:
                g_all[goff[e] : goff[e + 1]] = triangle_cross(verts, tris0, seg0[segoff[e] : segoff[e + 1]])
        for i in range(m):
            p = fvid[e][i]
            vid_all[off[e] + i] = p
            t_all[off[e] + i] = ft[e][i]
            h_all[off[e] + i] = verts[p, 2]
            for a in range(3):
                s_all[off[e] + i, a] = sums[p, a]
    bvid = np.unique(vid_all)
    rows = np.searchsorted(bvid, vid_all)
    return True, verts, tris, sums, normals, vid_all, t_all, h_all, off, s_all, g_all, goff, bvid, rows


# -- the crack detector (terralod.runtime.stitch.find_cracks) -----------------------------------------------
@jit
def border_segments(tris, along, on, z):
    """The triangle edges with both ends on a line (``on[v]``) as rows (t_a, z_a, t_b, z_b) with
    t_a <= t_b (``along``: position along the line, ``z``: height), duplicates removed, in lexicographic
    order of the rows (numpy's ``unique(axis=0)`` order)."""
    k = tris.shape[0]
    buf = np.empty((3 * k, 4), np.float64)
    n = 0
    for i in range(k):
        for e in range(3):
            a = tris[i, e]
            b = tris[i, (e + 1) % 3]
            if on[a] and on[b]:
                if along[a] > along[b]:
                    a, b = b, a
                buf[n, 0] = along[a]
                buf[n, 1] = z[a]
                buf[n, 2] = along[b]
                buf[n, 3] = z[b]
                n += 1
    order = np.argsort(buf[:n, 0], kind="mergesort")
    rows = np.empty((n, 4), np.float64)
    for i in range(n):
        rows[i] = buf[order[i]]
    # rows sharing t_a: insertion sort on the remaining columns (runs are a few rows long)
    i = 0
    while i < n:
        j = i + 1
        while j < n and rows[j, 0] == rows[i, 0]:
            j += 1
        for p in range(i + 1, j):
            q = p
            while q > i and _row_less(rows, q, q - 1):
                for c in range(4):
                    rows[q, c], rows[q - 1, c] = rows[q - 1, c], rows[q, c]
                q -= 1
        i = j
    m = 0
    for i in range(n):
        if m == 0 or not (
            rows[i, 0] == rows[m - 1, 0]
            and rows[i, 1] == rows[m - 1, 1]
            and rows[i, 2] == rows[m - 1, 2]
            and rows[i, 3] == rows[m - 1, 3]
        ):
            for c in range(4):
                rows[m, c] = rows[i, c]
            m += 1
    return rows[:m].copy()


@leaf
def _row_less(rows, p, q):
    for c in range(4):
        if rows[p, c] < rows[q, c]:
            return True
        if rows[p, c] > rows[q, c]:
            return False
    return False


@jit
def line_pair_gaps(segs, start, lo_t, hi_t, sign, code, frac, tol):
    """Gaps between the tiles that share one line, for every ordered pair (a, b) of its border polylines
    on opposite sides (``sign``) of different tiles (``code``) whose spans [lo_t, hi_t] meet.

    ``segs[start[i]:start[i + 1]]`` are polyline i's segments (t_a, z_a, t_b, z_b), sorted by t_a. Points
    at fractions ``frac`` along each segment of a are compared with b's height there: a point inside b's
    span that no segment of b covers (within ``tol``) is a hole (gap inf). Returns, for the pairs with a
    point checked: a, b, overlap of the spans, largest gap, points checked."""
    n = start.shape[0] - 1
    out_a, out_b, out_n = [0], [0], [0]
    out_overlap, out_gap = [0.0], [0.0]
    for ia in range(n):
        for ib in range(n):
            if sign[ib] == sign[ia] or code[ib] == code[ia]:
                continue
            if lo_t[ib] > hi_t[ia] + 1e-9 or lo_t[ia] > hi_t[ib] + 1e-9:
                continue
            b0, b1 = start[ib], start[ib + 1]
            checked = 0
            worst = 0.0
            for s in range(start[ia], start[ia + 1]):
                ta, za, tb, zb = segs[s, 0], segs[s, 1], segs[s, 2], segs[s, 3]
                for f in frac:
                    t = ta + f * (tb - ta)
                    if t < lo_t[ib] - tol or t > hi_t[ib] + tol:
                        continue
                    pz = za + f * (zb - za)
                    j = b0 + np.searchsorted(segs[b0:b1, 0], t + tol, side="right") - 1
                    j = min(max(j, b0), b1 - 1)
                    sa, sza, sb, szb = segs[j, 0], segs[j, 1], segs[j, 2], segs[j, 3]
                    if t >= sa - tol and t <= sb + tol:
                        w = (t - sa) / ((sb - sa) if sb > sa else 1.0)
                        w = min(max(w, 0.0), 1.0)
                        h = sza + w * (szb - sza)
                        if np.isnan(h):
                            continue
                        gap = abs(pz - h)
                    else:
                        gap = np.inf
                    checked += 1
                    if gap > worst:
                        worst = gap
            if checked:
                out_a.append(ia)
                out_b.append(ib)
                out_n.append(checked)
                out_overlap.append(min(hi_t[ia], hi_t[ib]) - max(lo_t[ia], lo_t[ib]))
                out_gap.append(worst)
    return (
        np.array(out_a[1:]),
        np.array(out_b[1:]),
        np.array(out_overlap[1:]),
        np.array(out_gap[1:]),
        np.array(out_n[1:]),
    )


@jit
def tile_edges(rc, tris, r0, c0, r1, c1, tol):
    """A tile's boundary bookkeeping in one pass (:meth:`terralod.runtime.stitch.TilePrep.from_tile`).

    ``rc`` (N, 2) the vertices' (row, col) in source samples, ``tris`` (K, 3); the tile square's rows r0, r1
    and columns c0, c1; a vertex is on a side within ``tol``. Returns the sides L, U, R, D concatenated:
    vertex ids ascending along each side (ties in id order) and their positions t (row on L/R, col on U/D)
    with offsets (5,); each side's segment triangles and start corners (:func:`segment_triangles_among`) with
    offsets (5,); the corner vertices LU, RU, RD, LD (lowest id, -1 where none); the triangles touching the
    boundary and their vertices, both ascending."""
    n = rc.shape[0]
    on = np.zeros((4, n), np.bool_)
    count = np.zeros(4, np.int64)
    for v in range(n):
        on[0, v] = abs(rc[v, 1] - c0) <= tol
        on[1, v] = abs(rc[v, 0] - r0) <= tol
        on[2, v] = abs(rc[v, 1] - c1) <= tol
        on[3, v] = abs(rc[v, 0] - r1) <= tol
        for e in range(4):
            if on[e, v]:
                count[e] += 1
    eoff = np.zeros(5, np.int64)
    for e in range(4):
        eoff[e + 1] = eoff[e] + count[e]
    ev = np.empty(eoff[4], np.int64)
    et = np.empty(eoff[4], np.float64)
    for e in range(4):
        col = 0 if e == 0 or e == 2 else 1
        idx = np.empty(count[e], np.int64)
        t = np.empty(count[e], np.float64)
        k = 0
        for v in range(n):
            if on[e, v]:
                idx[k] = v
                t[k] = rc[v, col]
                k += 1
        order = np.argsort(t, kind="mergesort")
        for j in range(count[e]):
            ev[eoff[e] + j] = idx[order[j]]
            et[eoff[e] + j] = t[order[j]]
    corners = np.full(4, -1, np.int64)
    for c in range(4):
        a, b = c, (c + 1) % 4  # LU = L & U, RU = U & R, RD = R & D, LD = D & L
        for v in range(n):
            if on[a, v] and on[b, v]:
                corners[c] = v
                break
    nb = 0
    bt = np.empty(tris.shape[0], np.int64)
    nv = n
    for i in range(tris.shape[0]):
        hit = False
        for r in range(3):
            w = tris[i, r]
            if w + 1 > nv:
                nv = w + 1
            if w < n and (on[0, w] or on[1, w] or on[2, w] or on[3, w]):
                hit = True
        if hit:
            bt[nb] = i
            nb += 1
    btris = bt[:nb].copy()
    mark = np.zeros(nv, np.bool_)
    for i in range(nb):
        for r in range(3):
            mark[tris[btris[i], r]] = True
    touched = np.flatnonzero(mark).astype(np.int64)
    rank = np.full(nv, -1, np.int64)
    soff = np.zeros(5, np.int64)
    for e in range(4):
        soff[e + 1] = soff[e] + max(count[e] - 1, 0)
    seg_tri = np.empty(soff[4], np.int64)
    seg_rot = np.empty(soff[4], np.int64)
    for e in range(4):
        st, sr = segment_triangles_among(tris, btris, ev[eoff[e] : eoff[e + 1]], rank)
        seg_tri[soff[e] : soff[e + 1]] = st
        seg_rot[soff[e] : soff[e + 1]] = sr
    return ev, et, eoff, seg_tri, seg_rot, soff, corners, btris, touched
