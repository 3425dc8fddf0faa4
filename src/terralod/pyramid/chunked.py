"""Chunked LOD tiles (Ulrich 2002), the baseline that Sung, Lee & Shin (2021) (``../shared/papers/000_0f8c6950ace8a2d1.txt``,
§2 and §4) measures the vertex cohesion map against.

Each tile is the regular M x M grid of the source at its level's stride; every quad is split along the
diagonal that gives the smaller maximum vertical error over the source samples inside the quad (ties:
smaller summed error, then the north-west/south-east diagonal), so the baseline is the best regular grid,
not a strawman. Quads whose north-west corner lies outside the source's sample rectangle are dropped (see
``terralod.tiles``); vertices past the source edge take the edge-replicated height.

Deviation from Ulrich: no skirts — cracks are closed by the runtime's stitching (Li, Liu & Liu), and the tile
error is measured (one-sided Hausdorff over every covered sample) instead of estimated.
"""

from __future__ import annotations

import numpy as np

from terralod.kernels import jit, leaf
from terralod.tiles import TileCode, TilePyramid


@leaf
def _quad_errors(z, valid, r0, c0, s, zq, ra, ca):
    """Max and summed |vertical error| of both diagonals of the quad with corner heights zq (a, b, c, d).

    a = north-west, b = north-east, c = south-west, d = south-east; samples (r0..r0+s, c0..c0+s)
    clipped to the source; invalid samples ignored. Returns (max0, sum0, max1, sum1) where diagonal 0
    joins a-d and diagonal 1 joins b-c.
    """
    h, w = z.shape
    za, zb, zc, zd = zq[0], zq[1], zq[2], zq[3]
    m0 = 0.0
    s0 = 0.0
    m1 = 0.0
    s1 = 0.0
    inv = 1.0 / s
    for dr in range(s + 1):
        r = r0 + dr
        if r >= h:
            break
        v = dr * inv
        for dc in range(s + 1):
            c = c0 + dc
            if c >= w:
                break
            if not valid[r, c]:
                continue
            u = dc * inv
            zs = z[r, c]
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
            s0 += e0
            s1 += e1
            if e0 > m0:
                m0 = e0
            if e1 > m1:
                m1 = e1
    return m0, s0, m1, s1


@jit
def _chunked_tile(z, valid, r0, c0, s, m):
    """Regular-grid tile mesh. Returns (rows (N,), cols (N,), heights (N,), triangles (K, 3) int32).

    rows/cols are integer source sample indices (may exceed the source in the padding), heights the
    edge-replicated source elevations there. Unused grid vertices are dropped; vertex order is raster.
    """
    h, w = z.shape
    cells = m - 1
    zg = np.empty((m, m), np.float64)
    for i in range(m):
        r = min(r0 + i * s, h - 1)
        for j in range(m):
            c = min(c0 + j * s, w - 1)
            zg[i, j] = z[r, c]
    keep = np.zeros((cells, cells), np.bool_)
    used = np.zeros((m, m), np.bool_)
    nq = 0
    for i in range(cells):
        if r0 + i * s >= h - 1:
            break
        for j in range(cells):
            if c0 + j * s >= w - 1:
                break
            keep[i, j] = True
            used[i, j] = True
            used[i, j + 1] = True
            used[i + 1, j] = True
            used[i + 1, j + 1] = True
            nq += 1
    # Count first, allocate exactly, then fill.
    index = np.full((m, m), -1, np.int64)
    n = 0
    for i in range(m):
        for j in range(m):
            if used[i, j]:
                index[i, j] = n
                n += 1
    rows = np.empty(n, np.int64)
    cols = np.empty(n, np.int64)
    hz = np.empty(n, np.float64)
    for i in range(m):
        for j in range(m):
            k = index[i, j]
            if k >= 0:
                rows[k] = r0 + i * s
                cols[k] = c0 + j * s
                hz[k] = zg[i, j]
    tris = np.empty((2 * nq, 3), np.int32)
    zq = np.empty(4, np.float64)
    t = 0
    for i in range(cells):
        for j in range(cells):
            if not keep[i, j]:
                continue
            a = index[i, j]
            b = index[i, j + 1]
            c = index[i + 1, j]
            d = index[i + 1, j + 1]
            zq[0] = zg[i, j]
            zq[1] = zg[i, j + 1]
            zq[2] = zg[i + 1, j]
            zq[3] = zg[i + 1, j + 1]
            diag1 = False
            if s > 1:
                m0, s0, m1, s1 = _quad_errors(z, valid, r0 + i * s, c0 + j * s, s, zq, 0, 0)
                diag1 = m1 < m0 or (m1 == m0 and s1 < s0)
            # Counter-clockwise seen from above (x east, y north): rows grow south.
            if diag1:
                tris[t, 0] = a
                tris[t, 1] = c
                tris[t, 2] = b
                tris[t + 1, 0] = b
                tris[t + 1, 1] = c
                tris[t + 1, 2] = d
            else:
                tris[t, 0] = a
                tris[t, 1] = c
                tris[t, 2] = d
                tris[t + 1, 0] = a
                tris[t + 1, 1] = d
                tris[t + 1, 2] = b
            t += 2
    return rows, cols, hz, tris


def mesh_tile(
    z: np.ndarray, valid: np.ndarray, pyramid: TilePyramid, code: TileCode
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Chunked-LOD mesh of tile ``code``.

    Returns
    -------
    rows, cols : (N,) float64 source sample coordinates (row south, col east) of the vertices
    heights_m : (N,) float64 elevation, metres
    triangles : (K, 3) int32, counter-clockwise seen from above
    """
    r0, c0 = pyramid.origin_rc(code)
    rows, cols, hz, tris = _chunked_tile(z, valid, r0, c0, pyramid.stride(code[0]), pyramid.tile_size)
    return rows.astype(np.float64), cols.astype(np.float64), hz, tris
