"""Numba kernels of the fractal detail (``../shared/papers/001_aded52eb792094ea.txt`` §2, §3.2): position-
hashed Gaussian noise, one diamond-square refinement level, the per-block variogram of a DEM, and the
per-quad errors of both diagonals. Pure functions on arrays: no I/O, no exceptions; validation lives in
:mod:`terralod.fractal`.

Vocabulary
----------
*Level-k lattice*: the DEM's sample grid refined k times; level-k index ``g`` is DEM sample ``g / 2^k``
(level 0 is the DEM itself). *World lattice*: the same index shifted by the DEM's offset on the world grid
of its spacing (``row_off * 2^k``, ``col_off * 2^k``), so that two DEMs on one grid hash alike.

fBm model: ``E[(z(p) - z(q))^2] = sigma^2 * |p - q|^(2H)`` with |p - q| in DEM samples. A new point is
a 4 x 4 stencil of its parents (weights from a table indexed by H, see
:func:`terralod.fractal.stencil_table`) plus a Gaussian of variance ``sigma^2 s^2H kappa2(H)`` for a parent
spacing s (times 2^-H in the square step, whose parent lattice is the diamond's scaled by 1/sqrt(2)).
"""

from __future__ import annotations

import math

import numpy as np

from terralod.kernels import jit

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_S30 = np.uint64(30)
_S27 = np.uint64(27)
_S31 = np.uint64(31)
_S11 = np.uint64(11)
_INV53 = 1.0 / 9007199254740992.0  # 2^-53
_TWO_PI = 2.0 * math.pi


@jit
def mix64(x):
    """splitmix64 finaliser: a bijective avalanche of a uint64."""
    x = (x ^ (x >> _S30)) * _M1
    x = (x ^ (x >> _S27)) * _M2
    return x ^ (x >> _S31)


@jit
def hash_key(seed, level, gi, gj):
    """uint64 hash of (seed uint64, level, world lattice row gi, col gi) — order of the tuple matters."""
    h = mix64(seed + _GOLDEN * np.uint64(level + 1))
    h = mix64(h ^ np.uint64(gi))
    return mix64(h ^ (np.uint64(gj) * _GOLDEN))


@jit
def gauss_at(seed, level, gi, gj):
    """Standard normal value of lattice point (gi, gj) at ``level`` (Box–Muller on two hashed uniforms)."""
    h1 = hash_key(seed, level, gi, gj)
    h2 = mix64(h1 + _GOLDEN)
    u1 = (float(h1 >> _S11) + 1.0) * _INV53  # (0, 1]
    u2 = float(h2 >> _S11) * _INV53  # [0, 1)
    return math.sqrt(-2.0 * math.log(u1)) * math.cos(_TWO_PI * u2)


@jit
def gauss_grid(seed, level, gi0, gj0, rows, cols):
    """(rows, cols) float64 standard normals of lattice points gi0 + i, gj0 + j (for tests)."""
    out = np.empty((rows, cols), np.float64)
    for i in range(rows):
        for j in range(cols):
            out[i, j] = gauss_at(seed, level, gi0 + i, gj0 + j)
    return out


@jit
def interp_blocks(blocks, block, r, c):
    """Bilinear value of a per-block map at fractional DEM sample (r, c); block centres at (b + 0.5) B - 0.5.

    Clamped at the outer block centres, so the value is a continuous function of position.
    """
    nby, nbx = blocks.shape
    v = (r + 0.5) / block - 0.5
    u = (c + 0.5) / block - 0.5
    v = min(max(v, 0.0), nby - 1.0)
    u = min(max(u, 0.0), nbx - 1.0)
    i0 = min(int(v), nby - 2) if nby > 1 else 0
    j0 = min(int(u), nbx - 2) if nbx > 1 else 0
    i1 = min(i0 + 1, nby - 1)
    j1 = min(j0 + 1, nbx - 1)
    fv = v - i0
    fu = u - j0
    top = blocks[i0, j0] + fu * (blocks[i0, j1] - blocks[i0, j0])
    bot = blocks[i1, j0] + fu * (blocks[i1, j1] - blocks[i1, j0])
    return top + fv * (bot - top)


@jit
def sample_blocks(blocks, block, rows, cols, scale):
    """(rows, cols) map of :func:`interp_blocks` at DEM samples (i * scale, j * scale)."""
    out = np.empty((rows, cols), np.float64)
    for i in range(rows):
        for j in range(cols):
            out[i, j] = interp_blocks(blocks, block, i * scale, j * scale)
    return out


@jit
def _stencil_at(table, hurst):
    """Linear interpolation of the stencil table row at ``hurst``: (w_inner, w_ring, w_corner, kappa2)."""
    n = table.shape[0] - 1
    x = min(max(hurst, 0.0), 1.0) * n
    i = min(int(x), n - 1)
    f = x - i
    return (
        table[i, 0] + f * (table[i + 1, 0] - table[i, 0]),
        table[i, 1] + f * (table[i + 1, 1] - table[i, 1]),
        table[i, 2] + f * (table[i + 1, 2] - table[i, 2]),
        table[i, 3] + f * (table[i + 1, 3] - table[i, 3]),
    )


@jit
def _local_model(h_blocks, s_blocks, block, gi, gj, level):
    """(H, sigma_m) at level-``level`` lattice point (gi, gj) (DEM-relative indices)."""
    inv = 1.0 / (1 << level)
    return interp_blocks(h_blocks, block, gi * inv, gj * inv), interp_blocks(
        s_blocks, block, gi * inv, gj * inv
    )


@jit
def refine_level(
    coarse, r_lo, c_lo, level, n_rows, n_cols, h_blocks, s_blocks, block, table, row_off, col_off, seed
):
    """One diamond-square iteration (Hu & Wang §2) of a rectangle of the level-(k-1) lattice.

    Parameters
    ----------
    coarse : (cr, cc) float64, metres: level-(k-1) values of lattice rows r_lo..r_lo+cr-1, cols c_lo..
    level : k >= 1
    n_rows, n_cols : last level-k index of the whole DEM ((H - 1) 2^k, (W - 1) 2^k)
    h_blocks, s_blocks, block : Hurst exponent and sigma (metres) per block of ``block`` DEM samples
    table : (n + 1, 4) stencil weights and variance factor at H = i / n (see :mod:`terralod.fractal`)
    row_off, col_off : the DEM's offset on the world lattice (DEM samples); seed : uint64

    Returns
    -------
    (2 cr - 1, 2 cc - 1) float64: level-k rows 2 r_lo.., cols 2 c_lo... Old points are copied unchanged.
    Each new point is a 4 x 4 stencil of its parents plus Gaussian noise: the diamond step predicts square
    centres from the 4 x 4 corners around them, the square step predicts edge midpoints from the 4 x 4
    stencil of the 45°-rotated lattice of corners and centres (the same weights: the square step is the
    diamond step rotated and scaled by 1/sqrt(2)). Where the stencil leaves the DEM, the plain mean of the
    nearest 4 parents (3 on the DEM's edge) is used. Points within 6 level-k units of this array's edge
    may lack parents and are wrong; the caller crops them. Every value is a pure function of its lattice
    position and its parents' values.
    """
    cr, cc = coarse.shape
    fr = 2 * cr - 1
    fc = 2 * cc - 1
    fine = np.empty((fr, fc), np.float64)
    gr0 = 2 * r_lo
    gc0 = 2 * c_lo
    wr = row_off << level
    wc = col_off << level
    scale = 2.0 ** (-(level - 1))  # parent spacing, DEM samples
    for i in range(cr):
        for j in range(cc):
            fine[2 * i, 2 * j] = coarse[i, j]
    # diamond step: square centres
    for i in range(cr - 1):
        for j in range(cc - 1):
            gi = gr0 + 2 * i + 1
            gj = gc0 + 2 * j + 1
            hurst, sigma = _local_model(h_blocks, s_blocks, block, gi, gj, level)
            near = coarse[i, j] + coarse[i, j + 1] + coarse[i + 1, j] + coarse[i + 1, j + 1]
            full = gi - 3 >= 0 and gj - 3 >= 0 and gi + 3 <= n_rows and gj + 3 <= n_cols
            if full and i >= 1 and j >= 1 and i + 2 < cr and j + 2 < cc:
                wa, wb, wcn, k2 = _stencil_at(table, hurst)
                ring = (
                    coarse[i - 1, j]
                    + coarse[i - 1, j + 1]
                    + coarse[i, j - 1]
                    + coarse[i + 1, j - 1]
                    + coarse[i, j + 2]
                    + coarse[i + 1, j + 2]
                    + coarse[i + 2, j]
                    + coarse[i + 2, j + 1]
                )
                corner = (
                    coarse[i - 1, j - 1] + coarse[i - 1, j + 2] + coarse[i + 2, j - 1] + coarse[i + 2, j + 2]
                )
                pred = wa * near + wb * ring + wcn * corner
            else:
                k2 = 2.0 ** (-hurst) - 0.25 - 0.125 * 2.0**hurst
                pred = near * 0.25
            amp = sigma * scale**hurst * math.sqrt(max(k2, 0.0))
            fine[2 * i + 1, 2 * j + 1] = pred + amp * gauss_at(seed, level, wr + gi, wc + gj)
    # square step: edge midpoints; stencil offsets (m + n, m - n) for m, n in {-3/2, -1/2, 1/2, 3/2}
    for fi in range(fr):
        gi = gr0 + fi
        for fj in range((fi + 1) % 2, fc, 2):
            gj = gc0 + fj
            hurst, sigma = _local_model(h_blocks, s_blocks, block, gi, gj, level)
            full = gi - 3 >= 0 and gj - 3 >= 0 and gi + 3 <= n_rows and gj + 3 <= n_cols
            if full and fi >= 3 and fj >= 3 and fi + 3 < fr and fj + 3 < fc:
                wa, wb, wcn, k2 = _stencil_at(table, hurst)
                near = fine[fi - 1, fj] + fine[fi, fj - 1] + fine[fi, fj + 1] + fine[fi + 1, fj]
                ring = (
                    fine[fi - 2, fj - 1]
                    + fine[fi - 2, fj + 1]
                    + fine[fi - 1, fj - 2]
                    + fine[fi - 1, fj + 2]
                    + fine[fi + 1, fj - 2]
                    + fine[fi + 1, fj + 2]
                    + fine[fi + 2, fj - 1]
                    + fine[fi + 2, fj + 1]
                )
                corner = fine[fi - 3, fj] + fine[fi, fj - 3] + fine[fi, fj + 3] + fine[fi + 3, fj]
                pred = wa * near + wb * ring + wcn * corner
                k2 = k2 * 2.0 ** (-hurst)
            else:
                acc = 0.0
                n = 0
                if gi >= 1 and fi >= 1:
                    acc += fine[fi - 1, fj]
                    n += 1
                if gj >= 1 and fj >= 1:
                    acc += fine[fi, fj - 1]
                    n += 1
                if gj + 1 <= n_cols and fj + 1 < fc:
                    acc += fine[fi, fj + 1]
                    n += 1
                if gi + 1 <= n_rows and fi + 1 < fr:
                    acc += fine[fi + 1, fj]
                    n += 1
                pred = acc / n
                k2 = 2.0 ** (-2.0 * hurst) - 0.125 - 0.25 * 2.0 ** (-hurst)
            amp = sigma * scale**hurst * math.sqrt(max(k2, 0.0))
            fine[fi, fj] = pred + amp * gauss_at(seed, level, wr + gi, wc + gj)
    return fine


@jit
def block_variogram(z, valid, block, max_lag):
    """Sums and counts of squared increments at lags 1..max_lag along rows and columns, per block.

    Returns
    -------
    sums, counts : (nby, nbx, max_lag) float64; a pair is counted in the block of its first sample and
    only when both samples are valid.
    """
    h, w = z.shape
    nby = -(-h // block)
    nbx = -(-w // block)
    sums = np.zeros((nby, nbx, max_lag), np.float64)
    counts = np.zeros((nby, nbx, max_lag), np.float64)
    for r in range(h):
        by = r // block
        for c in range(w):
            if not valid[r, c]:
                continue
            bx = c // block
            z0 = np.float64(z[r, c])
            for lag in range(1, max_lag + 1):
                if c + lag < w and valid[r, c + lag]:
                    d = np.float64(z[r, c + lag]) - z0
                    sums[by, bx, lag - 1] += d * d
                    counts[by, bx, lag - 1] += 1.0
                if r + lag < h and valid[r + lag, c]:
                    d = np.float64(z[r + lag, c]) - z0
                    sums[by, bx, lag - 1] += d * d
                    counts[by, bx, lag - 1] += 1.0
    return sums, counts


@jit
def axis_variogram(z, max_lag):
    """Mean squared increment at lags 1..max_lag along rows and columns of a full grid, (max_lag,)."""
    h, w = z.shape
    out = np.zeros(max_lag, np.float64)
    for lag in range(1, max_lag + 1):
        s = 0.0
        n = 0
        for r in range(h):
            for c in range(w - lag):
                d = z[r, c + lag] - z[r, c]
                s += d * d
                n += 1
        for r in range(h - lag):
            for c in range(w):
                d = z[r + lag, c] - z[r, c]
                s += d * d
                n += 1
        out[lag - 1] = s / max(n, 1)
    return out


@jit
def quad_diagonal_errors(zg, ref, sub, nq_r, nq_c):
    """Vertical error of both diagonals of every quad of a grid against a finer reference surface.

    Parameters
    ----------
    zg : (>= nq_r + 1, >= nq_c + 1) float64 grid heights, metres
    ref : ((nq_r * sub) + 1, (nq_c * sub) + 1) float64 reference heights on the grid refined ``sub`` times
    nq_r, nq_c : quads per column / row

    Returns
    -------
    max0, ss0, max1, ss1 : (nq_r, nq_c) float64 — max |error| and sum of squared errors over the
    reference samples of each quad (borders included), for diagonal 0 (north-west to south-east, a-d)
    and diagonal 1 (north-east to south-west, b-c).
    """
    max0 = np.zeros((nq_r, nq_c), np.float64)
    ss0 = np.zeros((nq_r, nq_c), np.float64)
    max1 = np.zeros((nq_r, nq_c), np.float64)
    ss1 = np.zeros((nq_r, nq_c), np.float64)
    inv = 1.0 / sub
    for i in range(nq_r):
        for j in range(nq_c):
            za = zg[i, j]
            zb = zg[i, j + 1]
            zc = zg[i + 1, j]
            zd = zg[i + 1, j + 1]
            m0 = 0.0
            s0 = 0.0
            m1 = 0.0
            s1 = 0.0
            for a in range(sub + 1):
                v = a * inv
                for b in range(sub + 1):
                    u = b * inv
                    zs = ref[i * sub + a, j * sub + b]
                    if u >= v:
                        p0 = za + u * (zb - za) + v * (zd - zb)
                    else:
                        p0 = za + v * (zc - za) + u * (zd - zc)
                    if u + v <= 1.0:
                        p1 = za + u * (zb - za) + v * (zc - za)
                    else:
                        p1 = zd + (1.0 - u) * (zc - zd) + (1.0 - v) * (zb - zd)
                    e0 = abs(zs - p0)
                    e1 = abs(zs - p1)
                    s0 += e0 * e0
                    s1 += e1 * e1
                    m0 = max(m0, e0)
                    m1 = max(m1, e1)
            max0[i, j] = m0
            ss0[i, j] = s0
            max1[i, j] = m1
            ss1[i, j] = s1
    return max0, ss0, max1, ss1
