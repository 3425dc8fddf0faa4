"""Clipping of a triangulation to a rectangle (the web export's lattice tiles, :mod:`terralod.export.lattice`).

A tile's grid of lattice samples reaches past the tile's edges (its first and last rows and columns are the
samples at or beyond them); the mesh made on it is cut back to the tile's rectangle here. Pure functions on
arrays.
"""

from __future__ import annotations

import numpy as np

from terralod.kernels import jit


@jit
def clip_mesh(px, py, ph, tris, x0, x1, y0, y1):  # pragma: no cover - numba
    """Clip a triangulation (vertices px, py, heights ph) to the rectangle [x0, x1] x [y0, y1]
    (Sutherland-Hodgman per triangle, each clipped polygon fanned): the surface inside is unchanged, new
    vertices lie on the triangles' edges with heights interpolated along them. Returns (x, y, h, tris);
    vertices outside the rectangle stay in the arrays, unreferenced."""
    nv = px.size
    nt = tris.shape[0]
    cap = nv + 12 * nt + 8
    vx = np.empty(cap)
    vy = np.empty(cap)
    vh = np.empty(cap)
    vx[:nv] = px
    vy[:nv] = py
    vh[:nv] = ph
    m = nv
    out = np.empty((5 * nt + 1, 3), np.int64)
    no = 0
    eps = 1e-9
    ax = np.empty(12)
    ay = np.empty(12)
    ah = np.empty(12)
    ai = np.empty(12, np.int64)
    bx = np.empty(12)
    by = np.empty(12)
    bh = np.empty(12)
    bi = np.empty(12, np.int64)
    for t in range(nt):
        ins = 0
        for q in range(3):
            i = tris[t, q]
            if x0 - eps <= px[i] <= x1 + eps and y0 - eps <= py[i] <= y1 + eps:
                ins += 1
        if ins == 3:
            out[no, 0] = tris[t, 0]
            out[no, 1] = tris[t, 1]
            out[no, 2] = tris[t, 2]
            no += 1
            continue
        n = 3
        for q in range(3):
            i = tris[t, q]
            ax[q] = px[i]
            ay[q] = py[i]
            ah[q] = ph[i]
            ai[q] = i
        for plane in range(4):
            k = 0
            for q in range(n):
                r = (q + 1) % n
                if plane == 0:
                    dp, dq = ax[q] - x0, ax[r] - x0
                elif plane == 1:
                    dp, dq = x1 - ax[q], x1 - ax[r]
                elif plane == 2:
                    dp, dq = ay[q] - y0, ay[r] - y0
                else:
                    dp, dq = y1 - ay[q], y1 - ay[r]
                if dp >= -eps:
                    bx[k], by[k], bh[k], bi[k] = ax[q], ay[q], ah[q], ai[q]
                    k += 1
                if (dp > eps and dq < -eps) or (dp < -eps and dq > eps):
                    f = dp / (dp - dq)
                    bx[k] = ax[q] + f * (ax[r] - ax[q])
                    by[k] = ay[q] + f * (ay[r] - ay[q])
                    bh[k] = ah[q] + f * (ah[r] - ah[q])
                    if plane == 0:
                        bx[k] = x0
                    elif plane == 1:
                        bx[k] = x1
                    elif plane == 2:
                        by[k] = y0
                    else:
                        by[k] = y1
                    bi[k] = -1
                    k += 1
            n = k
            for q in range(n):
                ax[q], ay[q], ah[q], ai[q] = bx[q], by[q], bh[q], bi[q]
            if n < 3:
                break
        if n < 3:
            continue
        for q in range(n):
            if ai[q] < 0:
                vx[m], vy[m], vh[m] = ax[q], ay[q], ah[q]
                ai[q] = m
                m += 1
        for q in range(1, n - 1):
            out[no, 0] = ai[0]
            out[no, 1] = ai[q]
            out[no, 2] = ai[q + 1]
            no += 1
    return vx[:m], vy[:m], vh[:m], out[:no]
