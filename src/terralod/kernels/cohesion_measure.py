"""Numba kernels of the vertex cohesion map, measurement (``../shared/papers/000_0f8c6950ace8a2d1.txt`` §3.1).

The error scans of a mesh of given vertex positions, which never move a vertex: heights at positions, the
errors of one quad with both diagonals (:func:`_quad_eval2`), the diagonal choice and attraction moments
per quad (:func:`choose_diagonals`), the per-quad state of :func:`measure_quads`, the lower bound of the
Hausdorff error (:func:`grid_error_bound`), the errors of one tile side's segments (:func:`_seg_worst`), and
the final mesh of the positions (:func:`assemble`, :func:`assemble_diagonals`). The relocation that moves
the vertices (Hooke relaxation, error-driven moves, pair and lattice search) is in
:mod:`terralod.kernels.cohesion`, which imports this module (never the other way round).

Pure functions on arrays, no I/O, no exceptions; validation and the paper's reading live in
:mod:`terralod.pyramid.cohesion`.

Frame: tile-local source samples, ``u`` = column offset (east), ``v`` = row offset (south) from the tile's
north-west vertex; the window ``zw`` holds the source over the tile square (edge-replicated past the data,
``vw`` False there). Grid vertex (i, j) starts at (v, u) = (i * s, j * s). A quad (i, j) has the corners
a = (i, j) north-west, b = (i, j + 1) north-east, c = (i + 1, j) south-west, d = (i + 1, j + 1) south-east;
diagonal 0 joins a-d (triangles a-c-d, a-d-b), diagonal 1 joins b-c (a-c-b, b-c-d), both counter-clockwise
seen from above (x east, y north) while the quad is convex; every accepted move keeps at least one valid
diagonal per quad (:func:`diagonal_ok`) and only valid diagonals are ever used.

Cost. Nearly all the time goes into :func:`_quad_eval2` (the errors of one quad, both diagonals, over its
samples). It is kept exact while made cheap: quads of lattice corners wide enough are scanned by row
intervals found with integer arithmetic (:func:`_edge_start`; the same samples as the per-sample tests),
a scan stops at the first row where both diagonals already reach the error to beat (``bound``), the
relaxation re-measures only the quads around moved vertices (:func:`choose_diagonals_moved`), the pair
search splits the quads by the vertex they depend on (:func:`terralod.kernels.cohesion._pair_search`), and
the per-quad state of :func:`measure_quads` is carried through
:func:`terralod.kernels.cohesion.refine_max_error` to :func:`assemble_diagonals`.
"""

from __future__ import annotations

import numpy as np

from terralod.kernels import jit, leaf

#: Errors up to this many metres count as exact: no attraction, nothing to refine (rounding noise of a
#: plane through float samples must not pull vertices).
ERR_EPS_M = 1e-6

#: Quads of lattice corners whose bounding box spans at least this many columns are scanned by row intervals
#: (:func:`_quad_eval2`); narrower ones test every sample of the box (the same samples either way). Since
#: the row scan does both diagonals in one pass over the row, it is the cheaper one at every size (stride-4
#: levels 5-8 % faster than with 12): 0.
SCAN_MIN_COLS = 0

#: Attraction weights: the vertical error of the current mesh squared (default), or a static feature map.
WEIGHT_ERROR = 0
WEIGHT_FEATURE = 1
#: No attraction moments (errors only: the refinement and the measures, which never read them).
WEIGHT_NONE = 2


@leaf
def height_at(zw, v, u, snap):
    """Source height at (v, u): the sample itself when ``snap`` (integer positions), else bilinear; the
    window is taken as edge-replicated past its last row and column (it may end at the data's edge).

    On a sample row (or column) the value is the linear interpolation along it, computed exactly as
    :func:`_line_height` does, so side vertices get bit-identical heights in both tiles sharing the side.
    """
    h, w = zw.shape
    v = min(v, h - 1.0)  # past the window's last row or column the source is edge-replicated
    u = min(u, w - 1.0)
    if snap:
        return zw[int(v), int(u)]
    r0 = int(np.floor(v))
    c0 = int(np.floor(u))
    fr = v - r0
    fc = u - c0
    if fr == 0.0 and fc == 0.0:
        return zw[r0, c0]
    if fr == 0.0:
        return zw[r0, c0] + fc * (zw[r0, c0 + 1] - zw[r0, c0])
    if fc == 0.0:
        return zw[r0, c0] + fr * (zw[r0 + 1, c0] - zw[r0, c0])
    r1 = min(r0 + 1, h - 1)
    c1 = min(c0 + 1, w - 1)
    top = zw[r0, c0] + fc * (zw[r0, c1] - zw[r0, c0])
    bot = zw[r1, c0] + fc * (zw[r1, c1] - zw[r1, c0])
    return top + fr * (bot - top)


@leaf
def _plane(v0, u0, z0, v1, u1, z1, v2, u2, z2, out, k):
    """z = out[k, 0] + out[k, 1] * u + out[k, 2] * v through three points (zeros if degenerate)."""
    den = (u1 - u0) * (v2 - v0) - (u2 - u0) * (v1 - v0)
    if den == 0.0:
        out[k, 0] = z0
        out[k, 1] = 0.0
        out[k, 2] = 0.0
        return
    gu = ((z1 - z0) * (v2 - v0) - (z2 - z0) * (v1 - v0)) / den
    gv = ((u1 - u0) * (z2 - z0) - (u2 - u0) * (z1 - z0)) / den
    out[k, 0] = z0 - gu * u0 - gv * v0
    out[k, 1] = gu
    out[k, 2] = gv


@leaf
def _side(va, ua, vb, ub, r, c):
    """Orientation of sample (r, c) against the directed line a -> b in the (u, v) frame."""
    return (ub - ua) * (r - va) - (vb - va) * (c - ua)


@leaf
def _tri_area2(pv, pu, i0, j0, i1, j1, i2, j2):
    """Twice the signed area of a triangle seen from above (x = u east, y = -v north): > 0 counter-clockwise."""
    x0, y0 = pu[i0, j0], -pv[i0, j0]
    return (pu[i1, j1] - x0) * (-pv[i2, j2] - y0) - (-pv[i1, j1] - y0) * (pu[i2, j2] - x0)


@leaf
def diagonal_ok(pv, pu, i, j, diag, min_area2):
    """True when both triangles of quad (i, j) along ``diag`` are counter-clockwise with twice their area
    above ``min_area2`` (diagonal 0: a-c-d, a-d-b; diagonal 1: a-c-b, b-c-d)."""
    if diag == 0:
        return (_tri_area2(pv, pu, i, j, i + 1, j, i + 1, j + 1) > min_area2
                and _tri_area2(pv, pu, i, j, i + 1, j + 1, i, j + 1) > min_area2)  # fmt: skip
    return (_tri_area2(pv, pu, i, j, i + 1, j, i, j + 1) > min_area2
            and _tri_area2(pv, pu, i, j + 1, i + 1, j, i + 1, j + 1) > min_area2)  # fmt: skip


@leaf
def _integral(va, ua, vb, ub, vc, uc, vd, ud):
    """All four corners on the sample lattice."""
    return (va == np.floor(va) and ua == np.floor(ua) and vb == np.floor(vb) and ub == np.floor(ub)
            and vc == np.floor(vc) and uc == np.floor(uc) and vd == np.floor(vd) and ud == np.floor(ud))  # fmt: skip


@leaf
def _edge_start(E, k, vp, up, vq, uq, r):
    """Row state of edge k (p -> q, integer corners) in ``E[k]`` for row r: _side(p, q, r, c) is
    a - dv (c - up) with a = du (r - vp), kept as D = |dv|, sg = sign(dv), q = floor(sg a / D),
    rem = sg a - q D, and the per-row steps of q and rem (D = 0: q holds a, stepped by du)."""
    dv = int(vq - vp)
    du = int(uq - up)
    a = du * (r - int(vp))
    E[k, 2] = int(up)
    if dv == 0:
        E[k, 0], E[k, 1], E[k, 3], E[k, 4], E[k, 5], E[k, 6] = 0, 0, a, 0, du, 0
        return
    sg = 1 if dv > 0 else -1
    d = dv * sg
    q = (a * sg) // d
    qs = (du * sg) // d
    E[k, 0], E[k, 1], E[k, 3], E[k, 4], E[k, 5], E[k, 6] = d, sg, q, a * sg - q * d, qs, du * sg - qs * d


@leaf
def _edge_next(E, k):
    """Step the row state of edge k to the next row (exact integer arithmetic, no division)."""
    E[k, 3] += E[k, 5]
    if E[k, 0] == 0:
        return
    E[k, 4] += E[k, 6]
    if E[k, 4] >= E[k, 0]:
        E[k, 3] += 1
        E[k, 4] -= E[k, 0]


@leaf
def _edge_clip(E, k, g, lo, hi):
    """Columns of [lo, hi] where g * _side of edge k <= 0 on the current row: an interval (lo > hi: none)."""
    if E[k, 0] == 0:
        return (lo, hi) if g * E[k, 3] <= 0 else (lo, lo - 1)
    if g * E[k, 1] > 0:  # dv (c - up) >= a: c >= up + ceil(a / dv)
        return max(lo, E[k, 2] + E[k, 3] + (1 if E[k, 4] > 0 else 0)), hi
    return lo, min(hi, E[k, 2] + E[k, 3])  # c <= up + floor(a / dv)


@leaf
def _tri_cols(E, e0, g0, e1, g1, e2, g2, lo, hi, ok):
    """Columns of the current row in [lo, hi] inside one triangle of :func:`_quad_eval2`: its three edges
    (row states in E) with their test signs g (+1: _side <= 0, -1: _side >= 0); (lo, lo - 1) when none or
    ``ok`` is False."""
    if not ok:
        return lo, lo - 1
    lo, hi = _edge_clip(E, e0, g0, lo, hi)
    lo, hi = _edge_clip(E, e1, g1, lo, hi)
    lo, hi = _edge_clip(E, e2, g2, lo, hi)
    if lo > hi:
        return lo, lo - 1
    return lo, hi


@jit
def _quad_eval2(zw, vw, feat, mode, pv, pu, hz, i, j, acc0, acc1, min_area2, pl, sxy, bound):
    """Errors and attraction moments of quad (i, j) for both diagonals in one pass over its samples.

    ``acc0`` (diagonal a-d) and ``acc1`` (diagonal b-c) get [max |err|, sum |err|, W, W*v, W*u, row of max,
    col of max, valid] with W = err^2 (mode WEIGHT_ERROR), feat (WEIGHT_FEATURE) or 0 (WEIGHT_NONE), over
    the samples of the diagonal's two (closed) triangles; a diagonal whose triangles are not both
    counter-clockwise (the quad is not convex) is marked invalid (acc[7] = 0) and gets max = inf. ``pl`` is
    (4, 3) scratch for the planes.
    The scan stops after a row where both diagonals' max already reach ``bound`` (the sums and moments are
    then partial: callers give a finite bound only to reject the quad; np.inf for the full measure).
    """
    for k in range(8):
        acc0[k] = 0.0
        acc1[k] = 0.0
    ok0 = diagonal_ok(pv, pu, i, j, 0, min_area2)
    ok1 = diagonal_ok(pv, pu, i, j, 1, min_area2)
    acc0[7] = 1.0 if ok0 else 0.0
    acc1[7] = 1.0 if ok1 else 0.0
    h, w = zw.shape
    va, ua, za = pv[i, j], pu[i, j], hz[i, j]
    vb, ub, zb = pv[i, j + 1], pu[i, j + 1], hz[i, j + 1]
    vc, uc, zc = pv[i + 1, j], pu[i + 1, j], hz[i + 1, j]
    vd, ud, zd = pv[i + 1, j + 1], pu[i + 1, j + 1], hz[i + 1, j + 1]
    _plane(va, ua, za, vc, uc, zc, vd, ud, zd, pl, 0)  # diag 0: a, c, d
    _plane(va, ua, za, vd, ud, zd, vb, ub, zb, pl, 1)  # diag 0: a, d, b
    _plane(va, ua, za, vc, uc, zc, vb, ub, zb, pl, 2)  # diag 1: a, c, b
    _plane(vb, ub, zb, vc, uc, zc, vd, ud, zd, pl, 3)  # diag 1: b, c, d
    # error metric: vertical (sxy = 0) or distance to the triangle's plane, |dz| / sqrt(1 + |grad z|^2)
    # with the gradient in metres per metre (sxy = 1 / dx, 1 / dy)
    n0 = 1.0 / np.sqrt(1.0 + (pl[0, 1] * sxy[0]) ** 2 + (pl[0, 2] * sxy[1]) ** 2)
    n1 = 1.0 / np.sqrt(1.0 + (pl[1, 1] * sxy[0]) ** 2 + (pl[1, 2] * sxy[1]) ** 2)
    n2 = 1.0 / np.sqrt(1.0 + (pl[2, 1] * sxy[0]) ** 2 + (pl[2, 2] * sxy[1]) ** 2)
    n3 = 1.0 / np.sqrt(1.0 + (pl[3, 1] * sxy[0]) ** 2 + (pl[3, 2] * sxy[1]) ** 2)
    eps = 1e-9
    rlo = max(int(np.ceil(min(min(va, vb), min(vc, vd)) - eps)), 0)
    rhi = min(int(np.floor(max(max(va, vb), max(vc, vd)) + eps)), h - 1)
    clo = max(int(np.ceil(min(min(ua, ub), min(uc, ud)) - eps)), 0)
    chi = min(int(np.floor(max(max(ua, ub), max(uc, ud)) + eps)), w - 1)
    # in the (u, v) frame (v south) a point inside a counter-clockwise triangle has every _side <= 0
    sc = 1e-9 * (1.0 + (ud - ua) * (ud - ua) + (vd - va) * (vd - va))
    # accumulators as locals (x0 for diagonal a-d, x1 for b-c): max, sum, W, W*v, W*u, row and col of max
    mx0 = 0.0
    sm0 = 0.0
    w0 = 0.0
    wv0 = 0.0
    wu0 = 0.0
    ar0 = 0.0
    ac0 = 0.0
    mx1 = 0.0
    sm1 = 0.0
    w1 = 0.0
    wv1 = 0.0
    wu1 = 0.0
    ar1 = 0.0
    ac1 = 0.0
    p00, p01, p02 = pl[0, 0], pl[0, 1], pl[0, 2]
    p10, p11, p12 = pl[1, 0], pl[1, 1], pl[1, 2]
    p20, p21, p22 = pl[2, 0], pl[2, 1], pl[2, 2]
    p30, p31, p32 = pl[3, 0], pl[3, 1], pl[3, 2]
    if chi - clo >= SCAN_MIN_COLS and sc < 0.5 and _integral(va, ua, vb, ub, vc, uc, vd, ud):
        # lattice corners (snapped positions): every _side is an exact integer, so each triangle's samples
        # on a row are one interval found by integer division, and the loops below visit exactly the samples
        # the tests further down accept, in the same order (bit-identical results, without the 6 tests)
        # the 6 edges, as the tests below orient them: 0 a->c, 1 c->d, 2 d->b, 3 b->a, 4 a->d, 5 b->c
        E = np.empty((6, 7), np.int64)
        _edge_start(E, 0, va, ua, vc, uc, rlo)
        _edge_start(E, 1, vc, uc, vd, ud, rlo)
        _edge_start(E, 2, vd, ud, vb, ub, rlo)
        _edge_start(E, 3, vb, ub, va, ua, rlo)
        _edge_start(E, 4, va, ua, vd, ud, rlo)
        _edge_start(E, 5, vb, ub, vc, uc, rlo)
        for r in range(rlo, rhi + 1):
            if r > rlo:
                for k in range(6):
                    _edge_next(E, k)
            # triangle a-c-d: s_ac <= 0, s_cd <= 0, s_ad >= 0; a-d-b: s_ad, s_db, s_ba <= 0
            l0, h0 = _tri_cols(E, 0, 1, 1, 1, 4, -1, clo, chi, ok0)
            l1, h1 = _tri_cols(E, 4, 1, 2, 1, 3, 1, clo, chi, ok0)
            # triangle a-c-b: s_ac <= 0, s_bc >= 0, s_ba <= 0; b-c-d: s_bc, s_cd, s_db <= 0
            l2, h2 = _tri_cols(E, 0, 1, 5, -1, 3, 1, clo, chi, ok1)
            l3, h3 = _tri_cols(E, 5, 1, 1, 1, 2, 1, clo, chi, ok1)
            # One pass over the row's columns for both diagonals, in increasing column order (each
            # diagonal's sums and first maximum as a run per triangle would give them, bit for bit); on
            # diagonal a-d the first triangle wins a shared sample, on b-c the third.
            lo = chi + 1
            hi = clo - 1
            if l0 <= h0:
                lo, hi = min(lo, l0), max(hi, h0)
            if l1 <= h1:
                lo, hi = min(lo, l1), max(hi, h1)
            if l2 <= h2:
                lo, hi = min(lo, l2), max(hi, h2)
            if l3 <= h3:
                lo, hi = min(lo, l3), max(hi, h3)
            for c in range(lo, hi + 1):
                if not vw[r, c]:
                    continue
                zs = zw[r, c]
                in0 = l0 <= c and c <= h0
                if in0 or (l1 <= c and c <= h1):
                    if in0:
                        e = abs(zs - (p00 + p01 * c + p02 * r)) * n0
                    else:
                        e = abs(zs - (p10 + p11 * c + p12 * r)) * n1
                    if e > mx0:
                        mx0 = e
                        ar0 = r
                        ac0 = c
                    sm0 += e
                    if mode != WEIGHT_NONE:
                        wk = (e * e if e > ERR_EPS_M else 0.0) if mode == WEIGHT_ERROR else feat[r, c]
                        w0 += wk
                        wv0 += wk * r
                        wu0 += wk * c
                in2 = l2 <= c and c <= h2
                if in2 or (l3 <= c and c <= h3):
                    if in2:
                        e = abs(zs - (p20 + p21 * c + p22 * r)) * n2
                    else:
                        e = abs(zs - (p30 + p31 * c + p32 * r)) * n3
                    if e > mx1:
                        mx1 = e
                        ar1 = r
                        ac1 = c
                    sm1 += e
                    if mode != WEIGHT_NONE:
                        wk = (e * e if e > ERR_EPS_M else 0.0) if mode == WEIGHT_ERROR else feat[r, c]
                        w1 += wk
                        wv1 += wk * r
                        wu1 += wk * c
            if (mx0 >= bound or not ok0) and (mx1 >= bound or not ok1):
                break  # both diagonals already at the bound: the caller rejects the quad
        rlo = rhi + 1  # done: skip the per-sample tests
    for r in range(rlo, rhi + 1):
        for c in range(clo, chi + 1):
            if not vw[r, c]:
                continue
            s_ac = _side(va, ua, vc, uc, r, c)
            s_cd = _side(vc, uc, vd, ud, r, c)
            s_db = _side(vd, ud, vb, ub, r, c)
            s_ba = _side(vb, ub, va, ua, r, c)
            s_ad = _side(va, ua, vd, ud, r, c)
            s_bc = _side(vb, ub, vc, uc, r, c)
            k0 = -1
            if ok0:
                if s_ac <= sc and s_cd <= sc and s_ad >= -sc:
                    k0 = 0
                elif s_ad <= sc and s_db <= sc and s_ba <= sc:
                    k0 = 1
            k1 = -1
            if ok1:
                if s_ac <= sc and s_bc >= -sc and s_ba <= sc:
                    k1 = 2
                elif s_bc <= sc and s_cd <= sc and s_db <= sc:
                    k1 = 3
            if k0 < 0 and k1 < 0:
                continue
            zs = zw[r, c]
            if k0 >= 0:
                if k0 == 0:
                    e = abs(zs - (p00 + p01 * c + p02 * r)) * n0
                else:
                    e = abs(zs - (p10 + p11 * c + p12 * r)) * n1
                if e > mx0:
                    mx0 = e
                    ar0 = r
                    ac0 = c
                sm0 += e
                if mode != WEIGHT_NONE:
                    wk = (e * e if e > ERR_EPS_M else 0.0) if mode == WEIGHT_ERROR else feat[r, c]
                    w0 += wk
                    wv0 += wk * r
                    wu0 += wk * c
            if k1 >= 0:
                if k1 == 2:
                    e = abs(zs - (p20 + p21 * c + p22 * r)) * n2
                else:
                    e = abs(zs - (p30 + p31 * c + p32 * r)) * n3
                if e > mx1:
                    mx1 = e
                    ar1 = r
                    ac1 = c
                sm1 += e
                if mode != WEIGHT_NONE:
                    wk = (e * e if e > ERR_EPS_M else 0.0) if mode == WEIGHT_ERROR else feat[r, c]
                    w1 += wk
                    wv1 += wk * r
                    wu1 += wk * c
        if (mx0 >= bound or not ok0) and (mx1 >= bound or not ok1):
            break
    acc0[0], acc0[1], acc0[2], acc0[3], acc0[4], acc0[5], acc0[6] = mx0, sm0, w0, wv0, wu0, ar0, ac0
    acc1[0], acc1[1], acc1[2], acc1[3], acc1[4], acc1[5], acc1[6] = mx1, sm1, w1, wv1, wu1, ar1, ac1
    if not ok0:
        acc0[0] = np.inf
    if not ok1:
        acc1[0] = np.inf


@jit
def choose_diagonals(zw, vw, feat, mode, pv, pu, hz, keep, diag, qmax, moments, sxy):
    """Per kept quad: the valid diagonal (both triangles counter-clockwise) of smaller max |vertical error|
    (ties: smaller sum, then diagonal 0), its max error ``qmax`` and its attraction moments
    ``moments[i, j] = (W, W*v, W*u)``. Returns the tile max."""
    m = pv.shape[0]
    return choose_diagonals_moved(zw, vw, feat, mode, pv, pu, hz, keep, diag, qmax, moments, sxy,
                                  np.ones((m, m), np.bool_))  # fmt: skip


@jit
def choose_diagonals_moved(zw, vw, feat, mode, pv, pu, hz, keep, diag, qmax, moments, sxy, moved):
    """:func:`choose_diagonals` for the kept quads with a corner marked in ``moved`` (m, m) only; the others
    keep their entries (a quad depends on its 4 corners alone). Returns the max over the quads redone."""
    cells = keep.shape[0]
    a0 = np.zeros(8, np.float64)
    a1 = np.zeros(8, np.float64)
    worst = 0.0
    min_area2 = _min_area2(pv)
    pl = np.empty((4, 3), np.float64)
    for i in range(cells):
        for j in range(cells):
            if not keep[i, j] or not (
                moved[i, j] or moved[i, j + 1] or moved[i + 1, j] or moved[i + 1, j + 1]
            ):
                continue
            _quad_eval2(zw, vw, feat, mode, pv, pu, hz, i, j, a0, a1, min_area2, pl, sxy, np.inf)
            use1 = a1[0] < a0[0] or (a1[0] == a0[0] and a1[1] < a0[1])
            best = a1 if use1 else a0
            diag[i, j] = 1 if use1 else 0
            qmax[i, j] = best[0]
            moments[i, j, 0] = best[2]
            moments[i, j, 1] = best[3]
            moments[i, j, 2] = best[4]
            if best[0] > worst:
                worst = best[0]
    return worst


@leaf
def _min_area2(pv):
    """Smallest accepted doubled triangle area, samples^2 (a scale-aware epsilon; lattice triangles have >= 1)."""
    return 1e-6 * (pv[pv.shape[0] - 1, 0] - pv[0, 0] + 1.0) ** 2 / (pv.shape[0] * pv.shape[0])


@leaf
def _line_height(line_z, x, snap):
    """Height of the side's line at position x: the sample when ``snap``, else linear (see height_at)."""
    k = int(np.floor(x))
    if snap or x == k:
        return line_z[k]
    return line_z[k] + (x - k) * (line_z[k + 1] - line_z[k])


@jit
def assemble(zw, vw, feat, pv, pu, keep, r0, c0, snap, sxy):
    """Final mesh of relocated positions: (rows (N,), cols (N,), heights (N,), triangles (K, 3) int32, max
    |vertical error| over the window's samples). Diagonals by smaller max error; vertex order raster; vertices
    of no kept quad dropped; rows/cols are global source coordinates (r0 + v, c0 + u)."""
    m = pv.shape[0]
    cells = m - 1
    hz = np.empty((m, m), np.float64)
    for i in range(m):
        for j in range(m):
            hz[i, j] = height_at(zw, pv[i, j], pu[i, j], snap)
    diag = np.zeros((cells, cells), np.int8)
    qmax = np.zeros((cells, cells), np.float64)
    mom = np.zeros((cells, cells, 3), np.float64)
    worst = choose_diagonals(zw, vw, feat, WEIGHT_NONE, pv, pu, hz, keep, diag, qmax, mom, sxy)
    rows, cols, heights, tris = assemble_diagonals(zw, pv, pu, keep, diag, r0, c0, snap)
    return rows, cols, heights, tris, worst


@jit
def assemble_diagonals(zw, pv, pu, keep, diag, r0, c0, snap):
    """The mesh of :func:`assemble` with the diagonals already chosen (``diag``: 0 a-d, 1 b-c per quad):
    (rows (N,), cols (N,), heights (N,), triangles (K, 3) int32)."""
    m = pv.shape[0]
    cells = m - 1
    used = np.zeros((m, m), np.bool_)
    nq = 0
    for i in range(cells):
        for j in range(cells):
            if keep[i, j]:
                used[i, j] = True
                used[i, j + 1] = True
                used[i + 1, j] = True
                used[i + 1, j + 1] = True
                nq += 1
    index = np.full((m, m), -1, np.int64)
    n = 0
    for i in range(m):
        for j in range(m):
            if used[i, j]:
                index[i, j] = n
                n += 1
    rows = np.empty(n, np.float64)
    cols = np.empty(n, np.float64)
    heights = np.empty(n, np.float64)
    for i in range(m):
        for j in range(m):
            k = index[i, j]
            if k >= 0:
                rows[k] = r0 + pv[i, j]
                cols[k] = c0 + pu[i, j]
                heights[k] = height_at(zw, pv[i, j], pu[i, j], snap)
    tris = np.empty((2 * nq, 3), np.int32)
    t = 0
    for i in range(cells):
        for j in range(cells):
            if not keep[i, j]:
                continue
            a = index[i, j]
            b = index[i, j + 1]
            c = index[i + 1, j]
            d = index[i + 1, j + 1]
            if diag[i, j] == 1:
                tris[t, 0], tris[t, 1], tris[t, 2] = a, c, b
                tris[t + 1, 0], tris[t + 1, 1], tris[t + 1, 2] = b, c, d
            else:
                tris[t, 0], tris[t, 1], tris[t, 2] = a, c, d
                tris[t + 1, 0], tris[t + 1, 1], tris[t + 1, 2] = a, d, b
            t += 2
    return rows, cols, heights, tris


@leaf
def _best_quad(zw, vw, feat, pv, pu, hz, i, j, a0, a1, pl, min_area2, sxy, bound):
    """(max |err|, worst row, worst col, diagonal) of quad (i, j) with its better diagonal."""
    _quad_eval2(zw, vw, feat, WEIGHT_NONE, pv, pu, hz, i, j, a0, a1, min_area2, pl, sxy, bound)
    if a1[0] < a0[0] or (a1[0] == a0[0] and a1[1] < a0[1]):
        return a1[0], a1[5], a1[6], 1
    return a0[0], a0[5], a0[6], 0


@jit
def measure_quads(zw, vw, pv, pu, keep, snap, sxy, qmax, wr, wc, diag):
    """Per kept quad: max error with its better diagonal (:func:`_best_quad`) into ``qmax``, the worst
    sample's row and col into ``wr``, ``wc`` and the diagonal into ``diag`` (the state that
    :func:`refine_max_error` keeps up to date and :func:`assemble_diagonals` triangulates); -1 elsewhere."""
    m = pv.shape[0]
    cells = m - 1
    feat = np.zeros((1, 1), np.float64)
    hz = np.empty((m, m), np.float64)
    for i in range(m):
        for j in range(m):
            hz[i, j] = height_at(zw, pv[i, j], pu[i, j], snap)
    a0 = np.zeros(8, np.float64)
    a1 = np.zeros(8, np.float64)
    pl = np.empty((4, 3), np.float64)
    min_area2 = _min_area2(pv)
    for i in range(cells):
        for j in range(cells):
            qmax[i, j] = -1.0
            wr[i, j] = 0.0
            wc[i, j] = 0.0
            diag[i, j] = 0
            if keep[i, j]:
                e, r, c, d = _best_quad(zw, vw, feat, pv, pu, hz, i, j, a0, a1, pl, min_area2, sxy, np.inf)
                qmax[i, j] = e
                wr[i, j] = r
                wc[i, j] = c
                diag[i, j] = d


@jit
def grid_error_bound(zw, vw, pv, pu, keep, grad_scale, side_m):
    """A lower bound (metres) of the Hausdorff error of the mesh of positions (pv, pu), whatever its
    diagonals, from the window's samples (a window of every f-th source sample bounds the full source).

    Per kept quad, v = the smaller of its two diagonals' max vertical error is a lower bound of |dz| at
    some sample; a sample dz off a surface z = f(x, y) with |grad f| <= L within horizontal distance r is at
    least min(r, |dz| / sqrt(1 + L^2)) from it (r'^2 + (|dz| - L r')^2 >= dz^2 / (1 + L^2)). L is taken over
    every triangle of both diagonals, for the whole tile and, for quads whose 3 x 3 neighbourhood lies on
    the regular lattice (interior vertices of the grid: i, j in 2..m-4), over that neighbourhood, with r =
    ``side_m`` (the quad side, metres). ``grad_scale``: 1 / metres per window sample on each axis.
    """
    m = pv.shape[0]
    cells = m - 1
    feat = np.zeros((1, 1), np.float64)
    hz = np.empty((m, m), np.float64)
    for i in range(m):
        for j in range(m):
            hz[i, j] = height_at(zw, pv[i, j], pu[i, j], True)
    a0 = np.zeros(8, np.float64)
    a1 = np.zeros(8, np.float64)
    pl = np.empty((4, 3), np.float64)
    min_area2 = _min_area2(pv)
    vq = np.zeros((cells, cells), np.float64)
    sq = np.zeros((cells, cells), np.float64)
    for i in range(cells):
        for j in range(cells):
            _quad_eval2(
                zw, vw, feat, WEIGHT_NONE, pv, pu, hz, i, j, a0, a1, min_area2, pl, np.zeros(2), np.inf
            )
            if keep[i, j]:
                vq[i, j] = min(a0[0], a1[0])
            for k in range(4):
                sq[i, j] = max(sq[i, j], (pl[k, 1] * grad_scale[0]) ** 2 + (pl[k, 2] * grad_scale[1]) ** 2)
    slope2 = 0.0
    v_all = 0.0
    for i in range(cells):
        for j in range(cells):
            slope2 = max(slope2, sq[i, j])
            v_all = max(v_all, vq[i, j])
    lb = v_all / np.sqrt(1.0 + slope2)
    for i in range(2, cells - 2):
        for j in range(2, cells - 2):
            if vq[i, j] <= lb:
                continue
            local = 0.0
            for di in range(-1, 2):
                for dj in range(-1, 2):
                    local = max(local, sq[i + di, j + dj])
            lb = max(lb, min(side_m, vq[i, j] / np.sqrt(1.0 + local)))
    return lb


@leaf
def _seg_max(line_z, line_ok, t, hz, j0, j1):
    """Max |error| of the line samples between vertices j0 and j1 (> j0) of the polyline (t, hz)."""
    worst = 0.0
    for j in range(j0, j1):
        e, _at = _seg_worst(line_z, line_ok, t, hz, j)
        if e > worst:
            worst = e
    return worst


@leaf
def _seg_worst(line_z, line_ok, t, hz, j):
    """(max |error|, position of the worst sample) of segment j of the polyline (t, hz)."""
    n = line_z.shape[0]
    a = t[j]
    b = t[j + 1]
    worst = 0.0
    at = a
    k0 = max(int(np.ceil(a)), 0)
    k1 = min(int(np.floor(b)), n - 1)
    for k in range(k0, k1 + 1):
        if not line_ok[k]:
            continue
        f = (k - a) / (b - a)
        e = abs(line_z[k] - (hz[j] + f * (hz[j + 1] - hz[j])))
        if e > worst:
            worst = e
            at = k
    return worst, at
