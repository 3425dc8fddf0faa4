"""Numba kernels of the vertex cohesion map (``../shared/papers/000_0f8c6950ace8a2d1.txt`` §3.1).

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
search splits the quads by the vertex they depend on (:func:`_pair_search`), and the per-quad state of
:func:`measure_quads` is carried through :func:`refine_max_error` to :func:`assemble_diagonals`.
"""

from __future__ import annotations

import numpy as np

from terralod.kernels import jit

#: Errors up to this many metres count as exact: no attraction, nothing to refine (rounding noise of a
#: plane through float samples must not pull vertices).
ERR_EPS_M = 1e-6

#: Quads of lattice corners whose bounding box spans at least this many columns are scanned by row intervals
#: (:func:`_quad_eval2`); narrower ones test every sample of the box (the same samples either way). Since
#: the row scan does both diagonals in one pass over the row, it is the cheaper one at every size (stride-4
#: levels 5-8 % faster than with 12): 0.
SCAN_MIN_COLS = 0

#: Fractions of the way to a quad's worst sample tried by the error-driven refinement.
FRACS = (1.0, 0.5)

#: Attraction weights: the vertical error of the current mesh squared (default), or a static feature map.
WEIGHT_ERROR = 0
WEIGHT_FEATURE = 1
#: No attraction moments (errors only: the refinement and the measures, which never read them).
WEIGHT_NONE = 2


@jit
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


@jit
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


@jit
def _side(va, ua, vb, ub, r, c):
    """Orientation of sample (r, c) against the directed line a -> b in the (u, v) frame."""
    return (ub - ua) * (r - va) - (vb - va) * (c - ua)


@jit
def _tri_area2(pv, pu, i0, j0, i1, j1, i2, j2):
    """Twice the signed area of a triangle seen from above (x = u east, y = -v north): > 0 counter-clockwise."""
    x0, y0 = pu[i0, j0], -pv[i0, j0]
    return (pu[i1, j1] - x0) * (-pv[i2, j2] - y0) - (-pv[i1, j1] - y0) * (pu[i2, j2] - x0)


@jit
def diagonal_ok(pv, pu, i, j, diag, min_area2):
    """True when both triangles of quad (i, j) along ``diag`` are counter-clockwise with twice their area
    above ``min_area2`` (diagonal 0: a-c-d, a-d-b; diagonal 1: a-c-b, b-c-d)."""
    if diag == 0:
        return (_tri_area2(pv, pu, i, j, i + 1, j, i + 1, j + 1) > min_area2
                and _tri_area2(pv, pu, i, j, i + 1, j + 1, i, j + 1) > min_area2)  # fmt: skip
    return (_tri_area2(pv, pu, i, j, i + 1, j, i, j + 1) > min_area2
            and _tri_area2(pv, pu, i, j + 1, i + 1, j, i + 1, j + 1) > min_area2)  # fmt: skip


@jit
def _integral(va, ua, vb, ub, vc, uc, vd, ud):
    """All four corners on the sample lattice."""
    return (va == np.floor(va) and ua == np.floor(ua) and vb == np.floor(vb) and ub == np.floor(ub)
            and vc == np.floor(vc) and uc == np.floor(uc) and vd == np.floor(vd) and ud == np.floor(ud))  # fmt: skip


@jit
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


@jit
def _edge_next(E, k):
    """Step the row state of edge k to the next row (exact integer arithmetic, no division)."""
    E[k, 3] += E[k, 5]
    if E[k, 0] == 0:
        return
    E[k, 4] += E[k, 6]
    if E[k, 4] >= E[k, 0]:
        E[k, 3] += 1
        E[k, 4] -= E[k, 0]


@jit
def _edge_clip(E, k, g, lo, hi):
    """Columns of [lo, hi] where g * _side of edge k <= 0 on the current row: an interval (lo > hi: none)."""
    if E[k, 0] == 0:
        return (lo, hi) if g * E[k, 3] <= 0 else (lo, lo - 1)
    if g * E[k, 1] > 0:  # dv (c - up) >= a: c >= up + ceil(a / dv)
        return max(lo, E[k, 2] + E[k, 3] + (1 if E[k, 4] > 0 else 0)), hi
    return lo, min(hi, E[k, 2] + E[k, 3])  # c <= up + floor(a / dv)


@jit
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


@jit
def _min_area2(pv):
    """Smallest accepted doubled triangle area, samples^2 (a scale-aware epsilon; lattice triangles have >= 1)."""
    return 1e-6 * (pv[pv.shape[0] - 1, 0] - pv[0, 0] + 1.0) ** 2 / (pv.shape[0] * pv.shape[0])


@jit
def _around_ok(pv, pu, i, j, cells, min_turn):
    """Every quad around vertex (i, j) keeps a valid diagonal (both triangles counter-clockwise, area above
    the epsilon). Then the final mesh, which only uses valid diagonals, has no fold-over: a triangulated
    disc whose triangles are all positively oriented and whose boundary stays in order is embedded."""
    min_area2 = _min_area2(pv)
    for di in (-1, 0):
        for dj in (-1, 0):
            qi = i + di
            qj = j + dj
            if 0 <= qi < cells and 0 <= qj < cells:
                if not (
                    diagonal_ok(pv, pu, qi, qj, 0, min_area2) or diagonal_ok(pv, pu, qi, qj, 1, min_area2)
                ):
                    return False
    return True


@jit
def _snapped(v, u, snap):
    """(v, u) rounded to the nearest sample when ``snap``, else unchanged."""
    if snap:
        return np.floor(v + 0.5), np.floor(u + 0.5)
    return v, u


@jit
def _try_at(pv, pu, i, j, v, u, cells, min_turn):
    """Put vertex (i, j) at (v, u) (height not updated) and say whether its 4 quads pass :func:`_around_ok`."""
    pv[i, j] = v
    pu[i, j] = u
    return _around_ok(pv, pu, i, j, cells, min_turn)


@jit
def stiffness(a, tau_low, tau_up):
    """Adaptive modulus K of the area ratio a (paper 000 eq. 6-8; eq. 8 read as (a - 1) / (tau_up - 1) so
    that K is continuous and 0 at a = 1, like eq. 7)."""
    if a < tau_low or a > tau_up:
        return 1.0
    if a < 1.0:
        return (1.0 - a) / (1.0 - tau_low)
    if tau_up <= 1.0:
        return 0.0
    return (a - 1.0) / (tau_up - 1.0)


@jit
def diamond_centroid(pv, pu, i, j):
    """Shoelace centroid (v, u) and area (samples^2) of the quad of the 4 edge neighbours of (i, j),
    in the order north, west, south, east (counter-clockwise seen from above)."""
    xs = np.empty(4, np.float64)
    ys = np.empty(4, np.float64)
    xs[0], ys[0] = pu[i - 1, j], -pv[i - 1, j]
    xs[1], ys[1] = pu[i, j - 1], -pv[i, j - 1]
    xs[2], ys[2] = pu[i + 1, j], -pv[i + 1, j]
    xs[3], ys[3] = pu[i, j + 1], -pv[i, j + 1]
    a2 = 0.0
    cx = 0.0
    cy = 0.0
    for k in range(4):
        k1 = (k + 1) % 4
        cr = xs[k] * ys[k1] - xs[k1] * ys[k]
        a2 += cr
        cx += (xs[k] + xs[k1]) * cr
        cy += (ys[k] + ys[k1]) * cr
    if a2 <= 0.0:
        return pv[i, j], pu[i, j], 0.0
    return -cy / (3.0 * a2), cx / (3.0 * a2), 0.5 * a2


@jit
def relax_edge(line_z, line_ok, feat, mode, s, m, limit, snap, n_iter, alpha, tau_low, tau_up):
    """1-D cohesion relocation of the m vertices of one tile side (positions 0..(m-1)*s along it).

    Only the samples of the side's own line are read, so the two tiles sharing a side compute bit-identical
    positions. Vertex j (1..m-2) moves when (j + 1) * s <= ``limit`` (the last data sample of the line);
    the ends stay. Each step: attraction toward the weighted centroid of the samples between its
    neighbours (W = err^2 of the current polyline or ``feat``), elastic pull toward the neighbours' midpoint
    with K from the length ratio (eq. 6-8); order kept with a gap of 1 sample (``snap``) or s / 8.
    Returns (m,) float64 positions.
    """
    t = np.empty(m, np.float64)
    for j in range(m):
        t[j] = j * s
    if s < 2:
        return t
    gap = 1.0 if snap else s / 8.0
    n = line_z.shape[0]
    hz = np.empty(m, np.float64)
    for _ in range(n_iter):
        for j in range(m):
            hz[j] = _line_height(line_z, t[j], snap)
        for j in range(1, m - 1):
            if (j + 1) * s > limit:
                break
            lo = t[j - 1]
            hi = t[j + 1]
            wsum = 0.0
            wpos = 0.0
            k0 = max(int(np.ceil(lo)), 0)
            k1 = min(int(np.floor(hi)), n - 1)
            for k in range(k0, k1 + 1):
                if not line_ok[k]:
                    continue
                if k <= t[j]:
                    a, b, za, zb = lo, t[j], hz[j - 1], hz[j]
                else:
                    a, b, za, zb = t[j], hi, hz[j], hz[j + 1]
                f = (k - a) / (b - a) if b > a else 0.0
                e = abs(line_z[k] - (za + f * (zb - za)))
                wt = (e * e if e > ERR_EPS_M else 0.0) if mode == WEIGHT_ERROR else feat[k]
                wsum += wt
                wpos += wt * k
            att = (wpos / wsum - t[j]) if wsum > 0.0 else 0.0
            ratio = (2.0 * s) / (hi - lo)
            kk = stiffness(ratio, tau_low, tau_up)
            mv = kk * (0.5 * (lo + hi) - t[j]) + alpha * att
            mv = min(max(mv, -0.5 * s), 0.5 * s)
            x = t[j] + mv
            if snap:
                x = np.floor(x + 0.5)
            lo_ok, hi_ok = _side_bounds(t, j, m, s, gap)
            x = min(max(x, lo_ok), hi_ok)
            if snap:
                x = np.floor(x + 0.5)
            if lo_ok <= x <= hi_ok:
                t[j] = x
                hz[j] = _line_height(line_z, x, snap)
    return t


@jit
def _side_bounds(t, j, m, s, gap):
    """Allowed range of side vertex j: ``gap`` from its neighbours, and for the vertices next to a corner
    less than 2 s from that corner. The corner quad (corner, two side vertices at a, b <= 2 s - gap from
    it, interior vertex at its grid position (s, s)) is then strictly convex whatever both sides do:
    its only possibly reflex turn needs (a - s)(b - s) >= s^2."""
    lo = t[j - 1] + gap
    hi = t[j + 1] - gap
    if j == 1:
        hi = min(hi, 2.0 * s - gap)
    if j == m - 2:
        lo = max(lo, (m - 3) * s + gap)
    return lo, hi


@jit
def _line_height(line_z, x, snap):
    """Height of the side's line at position x: the sample when ``snap``, else linear (see height_at)."""
    k = int(np.floor(x))
    if snap or x == k:
        return line_z[k]
    return line_z[k] + (x - k) * (line_z[k + 1] - line_z[k])


@jit
def relax_interior(zw, vw, feat, mode, pv, pu, movable, keep, s, snap, n_iter, alpha, tau_low, tau_up, sxy,
                   vmax, umax):  # fmt: skip
    """2-D cohesion relocation of the movable interior vertices, in place (paper 000 eq. 9).

    Per iteration: heights at the current positions, per-quad diagonals and attraction moments
    (:func:`choose_diagonals`), then a Gauss-Seidel sweep in raster order: V = K (T - P) + alpha * A with
    T the shoelace centroid of the 4 edge neighbours, K from the area ratio (eq. 6-8) and A the pull toward
    the weighted centroid of the 4 quads around P; |V| <= s / 2 per axis; positions stay in
    [0, vmax] x [0, umax], are rounded to samples when ``snap``, and a move that would make any of the 4
    quads around P non-convex is halved twice, then dropped (no fold-over, ever).
    """
    m = pv.shape[0]
    cells = m - 1
    hz = np.empty((m, m), np.float64)
    diag = np.zeros((cells, cells), np.int8)
    qmax = np.zeros((cells, cells), np.float64)
    mom = np.zeros((cells, cells, 3), np.float64)
    min_turn = 1e-6 * s * s
    # vertices moved by the last sweep: only the quads around them are measured again (all at first)
    changed = np.ones((m, m), np.bool_)
    for _ in range(n_iter):
        for i in range(m):
            for j in range(m):
                if changed[i, j]:
                    hz[i, j] = height_at(zw, pv[i, j], pu[i, j], snap)
        choose_diagonals_moved(zw, vw, feat, mode, pv, pu, hz, keep, diag, qmax, mom, sxy, changed)
        changed[:, :] = False
        moved = 0
        for i in range(1, m - 1):
            for j in range(1, m - 1):
                if not movable[i, j]:
                    continue
                p_v = pv[i, j]
                p_u = pu[i, j]
                wsum = 0.0
                wv = 0.0
                wu = 0.0
                for di in (-1, 0):
                    for dj in (-1, 0):
                        wsum += mom[i + di, j + dj, 0]
                        wv += mom[i + di, j + dj, 1]
                        wu += mom[i + di, j + dj, 2]
                av = (wv / wsum - p_v) if wsum > 0.0 else 0.0
                au = (wu / wsum - p_u) if wsum > 0.0 else 0.0
                tv, tu, area = diamond_centroid(pv, pu, i, j)
                kk = 1.0 if area <= 0.0 else stiffness(2.0 * s * s / area, tau_low, tau_up)
                mv = kk * (tv - p_v) + alpha * av
                mu = kk * (tu - p_u) + alpha * au
                half = 0.5 * s
                mv = min(max(mv, -half), half)
                mu = min(max(mu, -half), half)
                for _try in range(3):
                    nv = min(max(p_v + mv, 0.0), vmax)
                    nu = min(max(p_u + mu, 0.0), umax)
                    nv, nu = _snapped(nv, nu, snap)
                    if nv == p_v and nu == p_u:
                        break
                    if _try_at(pv, pu, i, j, nv, nu, cells, min_turn):
                        moved += 1
                        changed[i, j] = True
                        break
                    pv[i, j] = p_v
                    pu[i, j] = p_u
                    mv *= 0.5
                    mu *= 0.5
        if moved == 0:
            break


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


@jit
def _put(pv, pu, hz, i, j, v, u, h):
    """Set vertex (i, j) to position (v, u) with height h (restores a saved vertex)."""
    pv[i, j] = v
    pu[i, j] = u
    hz[i, j] = h


@jit
def _move(zw, pv, pu, hz, i, j, v, u, snap):
    """Move vertex (i, j) to (v, u) and give it the source height there."""
    _put(pv, pu, hz, i, j, v, u, height_at(zw, v, u, snap))


@jit
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


@jit
def refine_max_error(
    zw, vw, pv, pu, movable, keep, s, snap, budget, sxy, escape, focus, pairs, qmax, wr, wc, diag
):
    """Error-driven relocation (our improvement of the attraction term), in place.

    Repeatedly take the kept quad of largest max error that is not marked stuck and try to move one of its
    movable corners onto that quad's worst sample, half-way there, or onto one of the worst sample's 4
    neighbours (the worst itself may be out of reach or fold a triangle); a candidate is valid when
    the 4 quads around the vertex stay strictly convex. The candidate of the smallest max error over those 4
    quads is taken when that is below the worst quad's error (so the tile's max error never grows), and the
    4 quads are re-measured and un-stuck; otherwise the quad is marked stuck. Stops after ``budget`` tries
    or when every quad is stuck or exact. Returns the number of moves made.

    ``qmax``, ``wr``, ``wc``, ``diag`` hold the per-quad state of :func:`measure_quads` for the current
    positions on entry (computed by the caller, or left by a previous call) and are kept up to date, so a
    later call or :func:`assemble_diagonals` needs no new pass over the samples (snapped positions only).
    """
    m = pv.shape[0]
    cells = m - 1
    feat = np.zeros((1, 1), np.float64)
    hz = np.empty((m, m), np.float64)
    for i in range(m):
        for j in range(m):
            hz[i, j] = height_at(zw, pv[i, j], pu[i, j], snap)
    stuck = np.zeros((cells, cells), np.bool_)
    a0 = np.zeros(8, np.float64)
    a1 = np.zeros(8, np.float64)
    pl = np.empty((4, 3), np.float64)
    min_area2 = _min_area2(pv)
    # per row of quads: the largest error of a quad not stuck and where it is (a 2-level max search)
    rowbest = np.zeros(cells, np.float64)
    rowarg = np.zeros(cells, np.int64)
    for i in range(cells):
        _row_max(qmax, stuck, i, rowbest, rowarg)
    min_turn = 1e-6 * s * s
    moves = 0
    stuck_max = 0.0
    for _ in range(budget):
        bi = -1
        best = 0.0
        for i in range(cells):
            if rowbest[i] > max(best, ERR_EPS_M):
                best = rowbest[i]
                bi = i
        if bi < 0:
            break
        if best < focus * stuck_max:  # every quad left is well below a quad that cannot improve
            stuck_max = 0.0
            for i in range(cells):
                for j in range(cells):
                    if stuck[i, j] and qmax[i, j] > stuck_max:
                        stuck_max = qmax[i, j]
            if best < focus * stuck_max:
                break
        bj = rowarg[bi]
        tv = wr[bi, bj]
        tu = wc[bi, bj]
        cand_err = best
        cand_i = -1
        cand_j = -1
        cand_v = 0.0
        cand_u = 0.0
        for di in (0, 1):
            for dj in (0, 1):
                vi = bi + di
                vj = bj + dj
                if not movable[vi, vj]:
                    continue
                p_v = pv[vi, vj]
                p_u = pu[vi, vj]
                p_h = hz[vi, vj]
                for cand in range(len(FRACS) + 4):
                    if cand < len(FRACS):
                        nv = p_v + FRACS[cand] * (tv - p_v)
                        nu = p_u + FRACS[cand] * (tu - p_u)
                    else:  # a sample next to the worst one (when the worst itself cannot be reached)
                        k = cand - len(FRACS)
                        nv = tv + (1.0 if k == 0 else (-1.0 if k == 1 else 0.0))
                        nu = tu + (1.0 if k == 2 else (-1.0 if k == 3 else 0.0))
                    nv, nu = _snapped(nv, nu, snap)
                    if nv == p_v and nu == p_u:
                        continue
                    if _try_at(pv, pu, vi, vj, nv, nu, cells, min_turn):
                        hz[vi, vj] = height_at(zw, nv, nu, snap)
                        # the worst quad first: most candidates fail there, and the rest is skipped
                        loc = _local_max(zw, vw, feat, pv, pu, hz, keep, vi, vj, bi, bj, cand_err, a0, a1, pl,
                                         min_area2, sxy)  # fmt: skip
                        if loc < cand_err:
                            cand_err = loc
                            cand_i = vi
                            cand_j = vj
                            cand_v = nv
                            cand_u = nu
                    _put(pv, pu, hz, vi, vj, p_v, p_u, p_h)
        if cand_i < 0 and escape > 0:  # no short move helps: search every lattice point of the corners' stars
            for di in (0, 1):
                for dj in (0, 1):
                    vi = bi + di
                    vj = bj + dj
                    if not movable[vi, vj]:
                        continue
                    e, nv, nu = _star_search(zw, vw, feat, pv, pu, hz, keep, vi, vj, bi, bj, cand_err, escape,
                                             snap, a0, a1, pl, min_area2, min_turn, sxy)  # fmt: skip
                    if e < cand_err:
                        cand_err = e
                        cand_i = vi
                        cand_j = vj
                        cand_v = nv
                        cand_u = nu
        pair_i = -1
        pair_j = -1
        pair_v = 0.0
        pair_u = 0.0
        if cand_i < 0 and pairs > 0 and best >= stuck_max:  # the tile's worst quad is stuck: move 2 corners
            for k in range(PAIRS.shape[0]):
                if k == 6 and cand_i >= 0:  # a pair of the quad's own corners helped
                    break
                ai = bi + PAIRS[k, 0]
                aj = bj + PAIRS[k, 1]
                ci = bi + PAIRS[k, 2]
                cj = bj + PAIRS[k, 3]
                if not (0 <= ci < m and 0 <= cj < m and movable[ai, aj] and movable[ci, cj]):
                    continue
                e, av, au, cv, cu = _pair_search(zw, vw, feat, pv, pu, hz, keep, bi, bj, ai, aj, ci, cj, cand_err,
                                                 pairs, snap, a0, a1, pl, min_area2, min_turn, sxy)  # fmt: skip
                if e < cand_err:
                    cand_err = e
                    cand_i, cand_j, cand_v, cand_u = ai, aj, av, au
                    pair_i, pair_j, pair_v, pair_u = ci, cj, cv, cu
        if cand_i < 0:
            stuck[bi, bj] = True
            stuck_max = max(stuck_max, best)
            _row_max(qmax, stuck, bi, rowbest, rowarg)
            continue
        _move(zw, pv, pu, hz, cand_i, cand_j, cand_v, cand_u, snap)
        if pair_i >= 0:
            _move(zw, pv, pu, hz, pair_i, pair_j, pair_v, pair_u, snap)
        moves += 1
        for t in range(2):
            vi = cand_i if t == 0 else pair_i
            vj = cand_j if t == 0 else pair_j
            if vi < 0:
                continue
            for ei in (-1, 0):
                for ej in (-1, 0):
                    qi = vi + ei
                    qj = vj + ej
                    if 0 <= qi < cells and 0 <= qj < cells and keep[qi, qj]:
                        e, r, c, d = _best_quad(
                            zw, vw, feat, pv, pu, hz, qi, qj, a0, a1, pl, min_area2, sxy, np.inf
                        )
                        qmax[qi, qj] = e
                        wr[qi, qj] = r
                        wc[qi, qj] = c
                        diag[qi, qj] = d
                        stuck[qi, qj] = False
            for qi in (vi - 1, vi):
                if 0 <= qi < cells:
                    _row_max(qmax, stuck, qi, rowbest, rowarg)
    return moves


#: Vertex pairs moved together by the pair search for quad (i, j): (di_a, dj_a, di_b, dj_b) from (i, j); the
#: quad's 4 sides and 2 diagonals, then (tried only when none of those helps) a corner with one of its 5
#: neighbours outside the quad, which can make room for the corner.
def _make_pairs():
    own = [[0, 0, 0, 1], [0, 1, 1, 1], [1, 1, 1, 0], [1, 0, 0, 0], [0, 0, 1, 1], [0, 1, 1, 0]]
    ring = []
    for ai in (0, 1):
        for aj in (0, 1):
            for ei in (-1, 0, 1):
                for ej in (-1, 0, 1):
                    ni, nj = ai + ei, aj + ej
                    if (ei, ej) != (0, 0) and not (0 <= ni <= 1 and 0 <= nj <= 1):
                        ring.append([ai, aj, ni, nj])
    return np.array(own + ring, np.int64)


PAIRS = _make_pairs()


@jit
def _lattice(pv, pu, vi, vj, n_side):
    """(v0, u0, nv, nu, step_v, step_u): a lattice of at most (2 n_side + 1)^2 sample points over the box of
    vertex (vi, vj)'s 8 neighbours (step 1 sample when the box is small)."""
    vlo = pv[vi, vj]
    vhi = vlo
    ulo = pu[vi, vj]
    uhi = ulo
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            vlo = min(vlo, pv[vi + di, vj + dj])
            vhi = max(vhi, pv[vi + di, vj + dj])
            ulo = min(ulo, pu[vi + di, vj + dj])
            uhi = max(uhi, pu[vi + di, vj + dj])
    v0 = int(np.ceil(vlo))
    u0 = int(np.ceil(ulo))
    nvv = int(np.floor(vhi)) - v0
    nuu = int(np.floor(uhi)) - u0
    step_v = max(1, (nvv + 2 * n_side - 1) // (2 * n_side))
    step_u = max(1, (nuu + 2 * n_side - 1) // (2 * n_side))
    return v0, u0, nvv, nuu, step_v, step_u


@jit
def _has(qi, qj, vi, vj):
    """Quad (qi, qj) has vertex (vi, vj) as a corner."""
    return vi - 1 <= qi <= vi and vj - 1 <= qj <= vj


@jit
def _part_max(
    zw, vw, feat, pv, pu, hz, keep, ai, aj, ci, cj, with_a, with_c, bound, a0, a1, pl, min_area2, sxy
):
    """Max error of the kept quads around A = (ai, aj) or C = (ci, cj) (8-neighbours) that have A as a corner
    iff ``with_a`` and C iff ``with_c`` (both False: the block's quads around neither); stops at ``bound``."""
    cells = keep.shape[0]
    loc = 0.0
    for qi in range(max(min(ai, ci) - 1, 0), min(max(ai, ci), cells - 1) + 1):
        for qj in range(max(min(aj, cj) - 1, 0), min(max(aj, cj), cells - 1) + 1):
            if keep[qi, qj] and _has(qi, qj, ai, aj) == with_a and _has(qi, qj, ci, cj) == with_c:
                e, _r, _c, _d = _best_quad(
                    zw, vw, feat, pv, pu, hz, qi, qj, a0, a1, pl, min_area2, sxy, bound
                )
                if e > loc:
                    loc = e
                    if loc >= bound:
                        return loc
    return loc


@jit
def _part_ok(pv, pu, ai, aj, ci, cj, with_a, with_c, cells, min_area2):
    """The quads (kept or not) with corner A iff ``with_a`` and corner C iff ``with_c`` (not both False) keep
    a valid diagonal (the test of :func:`_around_ok`, split by the vertices a quad depends on)."""
    for qi in range(max(min(ai, ci) - 1, 0), min(max(ai, ci), cells - 1) + 1):
        for qj in range(max(min(aj, cj) - 1, 0), min(max(aj, cj), cells - 1) + 1):
            if _has(qi, qj, ai, aj) == with_a and _has(qi, qj, ci, cj) == with_c:
                if not (
                    diagonal_ok(pv, pu, qi, qj, 0, min_area2) or diagonal_ok(pv, pu, qi, qj, 1, min_area2)
                ):
                    return False
    return True


@jit
def _pair_search(zw, vw, feat, pv, pu, hz, keep, bi, bj, ai, aj, ci, cj, bound, n_side, snap, a0, a1, pl, min_area2,
                 min_turn, sxy):  # fmt: skip
    """Best joint position of vertices A = (ai, aj) and C = (ci, cj) (8-neighbours, A a corner of quad
    (bi, bj)) over a lattice of each one's star (:func:`_lattice`): (max error of the quads around both, A's
    v, u, C's v, u), the error ``bound`` when no valid pair is below it. Positions restored on return.

    The max splits by what each quad depends on: the quads with corner A only are measured (and checked for
    a valid diagonal) once per position of A, those with C only once per position of C, so a pair costs
    only the 1-2 quads sharing both, and none when either part is already at the bound."""
    cells = keep.shape[0]
    h, w = zw.shape
    pav = pv[ai, aj]
    pau = pu[ai, aj]
    pah = hz[ai, aj]
    pcv = pv[ci, cj]
    pcu = pu[ci, cj]
    pch = hz[ci, cj]
    av0, au0, anv, anu, asv, asu = _lattice(pv, pu, ai, aj, n_side)
    cv0, cu0, cnv, cnu, csv, csu = _lattice(pv, pu, ci, cj, n_side)
    # the quads around neither (diagonal neighbours) do not change
    fixed = _part_max(
        zw, vw, feat, pv, pu, hz, keep, ai, aj, ci, cj, False, False, bound, a0, a1, pl, min_area2, sxy
    )
    if fixed >= bound:
        return bound, pav, pau, pcv, pcu
    # per position of C: the quads with corner C only (bound when invalid, moved nowhere or past the data)
    ncu = cnu // csu + 1
    err_c = np.empty((cnv // csv + 1) * ncu, np.float64)
    for c in range(0, cnv + 1, csv):
        for d in range(0, cnu + 1, csu):
            k = (c // csv) * ncu + d // csu
            ncv = float(cv0 + c)
            nc_u = float(cu0 + d)
            err_c[k] = bound
            if ncv > h - 1 or nc_u > w - 1 or (ncv == pcv and nc_u == pcu):
                continue
            _move(zw, pv, pu, hz, ci, cj, ncv, nc_u, snap)
            if _part_ok(pv, pu, ai, aj, ci, cj, False, True, cells, min_area2):
                err_c[k] = _part_max(zw, vw, feat, pv, pu, hz, keep, ai, aj, ci, cj, False, True, bound, a0, a1, pl,
                                     min_area2, sxy)  # fmt: skip
            _put(pv, pu, hz, ci, cj, pcv, pcu, pch)
    best = bound
    bav = pav
    bau = pau
    bcv = pcv
    bcu = pcu
    for a in range(0, anv + 1, asv):
        for b in range(0, anu + 1, asu):
            nav = float(av0 + a)
            nau = float(au0 + b)
            if nav > h - 1 or nau > w - 1 or (nav == pav and nau == pau):
                continue
            _move(zw, pv, pu, hz, ai, aj, nav, nau, snap)
            if _part_ok(pv, pu, ai, aj, ci, cj, True, False, cells, min_area2):
                ea = _part_max(zw, vw, feat, pv, pu, hz, keep, ai, aj, ci, cj, True, False, best, a0, a1, pl,
                               min_area2, sxy)  # fmt: skip
                if max(ea, fixed) < best:
                    for c in range(0, cnv + 1, csv):
                        for d in range(0, cnu + 1, csu):
                            ec = err_c[(c // csv) * ncu + d // csu]
                            part = max(max(ea, fixed), ec)
                            if part >= best:
                                continue
                            ncv = float(cv0 + c)
                            nc_u = float(cu0 + d)
                            _move(zw, pv, pu, hz, ci, cj, ncv, nc_u, snap)
                            if _part_ok(pv, pu, ai, aj, ci, cj, True, True, cells, min_area2):
                                eb = _part_max(zw, vw, feat, pv, pu, hz, keep, ai, aj, ci, cj, True, True, best,
                                               a0, a1, pl, min_area2, sxy)  # fmt: skip
                                loc = max(part, eb)
                                if loc < best:
                                    best = loc
                                    bav = nav
                                    bau = nau
                                    bcv = ncv
                                    bcu = nc_u
                            _put(pv, pu, hz, ci, cj, pcv, pcu, pch)
            _put(pv, pu, hz, ai, aj, pav, pau, pah)
    return best, bav, bau, bcv, bcu


@jit
def _local_max(zw, vw, feat, pv, pu, hz, keep, vi, vj, bi, bj, bound, a0, a1, pl, min_area2, sxy):
    """Max error of the (kept) quads around vertex (vi, vj), quad (bi, bj) first; stops at ``bound``."""
    cells = keep.shape[0]
    loc = 0.0
    for k in range(4):
        qi, qj = bi, bj
        if k > 0:
            qi, qj = _kth_other_quad(vi, vj, bi, bj, k)
        if loc >= bound:
            break
        if 0 <= qi < cells and 0 <= qj < cells and keep[qi, qj]:
            e, _r, _c, _d = _best_quad(zw, vw, feat, pv, pu, hz, qi, qj, a0, a1, pl, min_area2, sxy, bound)
            if e > loc:
                loc = e
    return loc


@jit
def _star_search(zw, vw, feat, pv, pu, hz, keep, vi, vj, bi, bj, bound, n_side, snap, a0, a1, pl, min_area2,
                 min_turn, sxy):  # fmt: skip
    """Best position of vertex (vi, vj) over a lattice of at most (2 n_side + 1)^2 sample points covering the
    box of its 8 neighbours (:func:`_lattice`): (max error of its 4 quads, v, u), the
    error ``bound`` when no valid point is below it. Positions restored on return."""
    cells = keep.shape[0]
    p_v = pv[vi, vj]
    p_u = pu[vi, vj]
    p_h = hz[vi, vj]
    v0, u0, nvv, nuu, step_v, step_u = _lattice(pv, pu, vi, vj, n_side)
    best = bound
    bv = p_v
    bu = p_u
    h, w = zw.shape
    for a in range(0, nvv + 1, step_v):
        for b in range(0, nuu + 1, step_u):
            nv = float(v0 + a)
            nu = float(u0 + b)
            if (nv == p_v and nu == p_u) or nv > h - 1 or nu > w - 1:
                continue
            if _try_at(pv, pu, vi, vj, nv, nu, cells, min_turn):
                hz[vi, vj] = height_at(zw, nv, nu, snap)
                loc = _local_max(
                    zw, vw, feat, pv, pu, hz, keep, vi, vj, bi, bj, best, a0, a1, pl, min_area2, sxy
                )
                if loc < best:
                    best = loc
                    bv = nv
                    bu = nu
            _put(pv, pu, hz, vi, vj, p_v, p_u, p_h)
    return best, bv, bu


@jit
def _kth_other_quad(vi, vj, bi, bj, k):
    """The k-th (1..3) of the 4 quads around vertex (vi, vj) other than quad (bi, bj)."""
    n = 0
    for ei in (-1, 0):
        for ej in (-1, 0):
            qi = vi + ei
            qj = vj + ej
            if qi == bi and qj == bj:
                continue
            n += 1
            if n == k:
                return qi, qj
    return -1, -1


@jit
def _row_max(qmax, stuck, i, rowbest, rowarg):
    """Largest error of a quad of row i that is not stuck (0 if none) and its column."""
    best = 0.0
    arg = 0
    for j in range(qmax.shape[1]):
        if not stuck[i, j] and qmax[i, j] > best:
            best = qmax[i, j]
            arg = j
    rowbest[i] = best
    rowarg[i] = arg


@jit
def _seg_max(line_z, line_ok, t, hz, j0, j1):
    """Max |error| of the line samples between vertices j0 and j1 (> j0) of the polyline (t, hz)."""
    worst = 0.0
    for j in range(j0, j1):
        e, _at = _seg_worst(line_z, line_ok, t, hz, j)
        if e > worst:
            worst = e
    return worst


@jit
def refine_edge_max_error(line_z, line_ok, t, s, limit, snap, budget):
    """1-D :func:`refine_max_error` on one tile side (positions ``t`` in place; reads only the line).

    The segment of largest error that is not stuck moves one of its movable ends onto its worst sample (or
    half-way), keeping an order gap of 1 sample (``snap``) or s / 8, when that lowers the max error of the
    two segments around the end. Returns the number of moves."""
    m = t.shape[0]
    n = line_z.shape[0]
    gap = 1.0 if snap else s / 8.0
    hz = np.empty(m, np.float64)
    for j in range(m):
        hz[j] = _line_height(line_z, t[j], snap)
    seg = np.zeros(m - 1, np.float64)
    pos = np.zeros(m - 1, np.float64)
    stuck = np.zeros(m - 1, np.bool_)
    for j in range(m - 1):
        seg[j], pos[j] = _seg_worst(line_z, line_ok, t, hz, j)
    moves = 0
    for _ in range(budget):
        bj = -1
        best = 0.0
        for j in range(m - 1):
            if not stuck[j] and seg[j] > max(best, ERR_EPS_M):
                best = seg[j]
                bj = j
        if bj < 0:
            break
        cand_err = best
        cand_j = -1
        cand_t = 0.0
        for vj in (bj, bj + 1):
            if vj < 1 or vj > m - 2 or (vj + 1) * s > limit:
                continue
            old = t[vj]
            old_h = hz[vj]
            for frac in (1.0, 0.5):
                x = old + frac * (pos[bj] - old)
                if snap:
                    x = np.floor(x + 0.5)
                lo_ok, hi_ok = _side_bounds(t, vj, m, s, gap)
                if x == old or x < lo_ok or x > hi_ok or x > n - 1:
                    continue
                t[vj] = x
                hz[vj] = _line_height(line_z, x, snap)
                loc = _seg_max(line_z, line_ok, t, hz, vj - 1, vj + 1)
                if loc < cand_err:
                    cand_err = loc
                    cand_j = vj
                    cand_t = x
                t[vj] = old
                hz[vj] = old_h
        if cand_j < 0:
            stuck[bj] = True
            continue
        t[cand_j] = cand_t
        hz[cand_j] = _line_height(line_z, cand_t, snap)
        moves += 1
        for j in (cand_j - 1, cand_j):
            seg[j], pos[j] = _seg_worst(line_z, line_ok, t, hz, j)
            stuck[j] = False
    return moves


@jit
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
