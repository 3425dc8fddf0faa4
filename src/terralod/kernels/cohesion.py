"""Numba kernels of the vertex cohesion map, relocation (``../shared/papers/000_0f8c6950ace8a2d1.txt`` §3.1).

The moves of the grid vertices: the Hooke relaxation of one tile side (:func:`relax_edge`) and of the
interior (:func:`relax_interior`, eq. 6-9 with :func:`stiffness` and :func:`diamond_centroid`), the
error-driven refinement (:func:`refine_max_error`, with its pair search :func:`_pair_search` over
:data:`PAIRS` and lattice/star search :func:`_star_search`; :func:`refine_edge_max_error` on a side), and
the fold-over checks every move passes (:func:`_around_ok`). Everything they measure comes from
:mod:`terralod.kernels.cohesion_measure` (frame, quad corners and diagonals, and the cost of the error scans
are described there); this module imports it, never the other way round.

Pure functions on arrays, no I/O, no exceptions; validation and the paper's reading live in
:mod:`terralod.pyramid.cohesion`.
"""

from __future__ import annotations

import numpy as np

from terralod.kernels import jit, leaf
from terralod.kernels.cohesion_measure import (
    ERR_EPS_M,
    WEIGHT_ERROR,
    _best_quad,
    _line_height,
    _min_area2,
    _seg_max,
    _seg_worst,
    choose_diagonals_moved,
    diagonal_ok,
    height_at,
)

#: Fractions of the way to a quad's worst sample tried by the error-driven refinement.
FRACS = (1.0, 0.5)


@leaf
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


@leaf
def _snapped(v, u, snap):
    """(v, u) rounded to the nearest sample when ``snap``, else unchanged."""
    if snap:
        return np.floor(v + 0.5), np.floor(u + 0.5)
    return v, u


@leaf
def _try_at(pv, pu, i, j, v, u, cells, min_turn):
    """Put vertex (i, j) at (v, u) (height not updated) and say whether its 4 quads pass :func:`_around_ok`."""
    pv[i, j] = v
    pu[i, j] = u
    return _around_ok(pv, pu, i, j, cells, min_turn)


@jit
def stiffness(a, tau_low, tau_up):
    """Adaptive modulus K of the area ratio a (Sung, Lee & Shin (2021) eq. 6-8; eq. 8 read as (a - 1) / (tau_up - 1) so
    that K is continuous and 0 at a = 1, like eq. 7)."""
    if a < tau_low or a > tau_up:
        return 1.0
    if a < 1.0:
        return (1.0 - a) / (1.0 - tau_low)
    if tau_up <= 1.0:
        return 0.0
    return (a - 1.0) / (tau_up - 1.0)


@leaf
def diamond_centroid(pv, pu, i, j):
    """Shoelace centroid (v, u) and area (samples^2) of the quad of the 4 edge neighbours of (i, j),
    in the order north, west, south, east (counter-clockwise seen from above)."""
    # scalars, not 4-element arrays (an allocation a call, in the relaxation's inner loop); the same sums in
    # the same order (k = 0..3, k + 1 mod 4)
    x0, y0 = pu[i - 1, j], -pv[i - 1, j]
    x1, y1 = pu[i, j - 1], -pv[i, j - 1]
    x2, y2 = pu[i + 1, j], -pv[i + 1, j]
    x3, y3 = pu[i, j + 1], -pv[i, j + 1]
    a2 = 0.0
    cx = 0.0
    cy = 0.0
    cr = x0 * y1 - x1 * y0
    a2 += cr
    cx += (x0 + x1) * cr
    cy += (y0 + y1) * cr
    cr = x1 * y2 - x2 * y1
    a2 += cr
    cx += (x1 + x2) * cr
    cy += (y1 + y2) * cr
    cr = x2 * y3 - x3 * y2
    a2 += cr
    cx += (x2 + x3) * cr
    cy += (y2 + y3) * cr
    cr = x3 * y0 - x0 * y3
    a2 += cr
    cx += (x3 + x0) * cr
    cy += (y3 + y0) * cr
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


@leaf
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
def relax_interior(zw, vw, feat, mode, pv, pu, movable, keep, s, snap, n_iter, alpha, tau_low, tau_up, sxy,
                   vmax, umax):  # fmt: skip
    """2-D cohesion relocation of the movable interior vertices, in place (Sung, Lee & Shin (2021) eq. 9).

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


@leaf
def _put(pv, pu, hz, i, j, v, u, h):
    """Set vertex (i, j) to position (v, u) with height h (restores a saved vertex)."""
    pv[i, j] = v
    pu[i, j] = u
    hz[i, j] = h


@leaf
def _move(zw, pv, pu, hz, i, j, v, u, snap):
    """Move vertex (i, j) to (v, u) and give it the source height there."""
    _put(pv, pu, hz, i, j, v, u, height_at(zw, v, u, snap))


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


@leaf
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


@leaf
def _has(qi, qj, vi, vj):
    """Quad (qi, qj) has vertex (vi, vj) as a corner."""
    return vi - 1 <= qi <= vi and vj - 1 <= qj <= vj


@leaf
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


@leaf
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


@leaf
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


@leaf
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


@leaf
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


@leaf
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
