"""Hole-filling relaxation kernel (see terralod.fill): Jacobi averaging over hole cells only."""

from __future__ import annotations

import numpy as np

from terralod.kernels import jit


@jit
def relax_holes(z, hole_r, hole_c, iterations):
    """``iterations`` Jacobi sweeps of 4-neighbour averaging over the listed hole cells (edge-clamped);
    every other cell is held fixed. Works in place on ``z`` (float64, (H, W)) and returns it."""
    h, w = z.shape
    n = hole_r.size
    tmp = np.empty(n, np.float64)
    for _ in range(iterations):
        for k in range(n):
            r = hole_r[k]
            c = hole_c[k]
            up = z[r - 1, c] if r > 0 else z[r, c]
            dn = z[r + 1, c] if r < h - 1 else z[r, c]
            lf = z[r, c - 1] if c > 0 else z[r, c]
            rt = z[r, c + 1] if c < w - 1 else z[r, c]
            tmp[k] = 0.25 * (up + dn + lf + rt)
        for k in range(n):
            z[hole_r[k], hole_c[k]] = tmp[k]
    return z
