"""The drawn footprint of a tile: triangles over nodata are not stored.

Nodata (the source's own holes and the margin a reprojection leaves around a geographic tile) is filled
before meshing (:mod:`terralod.fill`) so that every mesher sees a continuous surface; the fill is for
meshing only, never for display. After a tile is meshed, :func:`footprint_mask` keeps a triangle when at
least half of the source samples its closed XY projection covers are valid (a triangle covering no sample,
a sliver between samples, takes the sample nearest its centroid). At the finest level (stride 1) a
triangle covers its three vertex samples, so a triangle with two nodata corners is dropped; at a coarse
level the drawn footprint follows the valid region to within a triangle's size. :func:`drop_nodata`
removes the dropped triangles and the vertices no kept triangle uses, in order, so a tile that lies
wholly in nodata is stored with no vertex and no triangle.

Same-level neighbours still share bit-identical boundary vertices where both keep triangles; where one
side dropped its triangles the stitcher (Li, Liu & Liu) sees a partial side, as at the data edge.
"""

from __future__ import annotations

import math

import numpy as np

from terralod.kernels import jit, leaf


@leaf
def _box_verdict(sat, r0, r1, c0, c1, g_r0, g_c0):
    """1 when samples rows r0..r1 x cols c0..c1 are all valid, 0 when all nodata, -1 when mixed (from the
    summed-area table ``sat`` whose origin is sample (g_r0, g_c0))."""
    y0, y1, x0, x1 = r0 - g_r0, r1 - g_r0 + 1, c0 - g_c0, c1 - g_c0 + 1
    nv = sat[y1, x1] - sat[y0, x1] - sat[y1, x0] + sat[y0, x0]
    if nv == (y1 - y0) * (x1 - x0):
        return 1
    return 0 if nv == 0 else -1


@jit
def footprint_mask(rows, cols, tris, valid):
    """(K,) bool: True for triangles whose covered samples are at least half valid.

    rows, cols : (N,) float64 source sample coordinates of the vertices (row south, col east)
    tris : (K, 3) integer vertex indices
    valid : (H, W) bool over the whole source (samples outside it are not counted)

    A triangle whose box of samples widened to whole samples (floor of its least row and column to ceil
    of its largest, clipped to the grid) is all valid or all nodata is decided from a summed-area table of
    the mask without visiting its samples: that box holds every sample it covers and the sample nearest
    its centroid, so the count would say the same. So is a triangle inside the grid whose own box of
    samples is all valid or all nodata and whose inscribed circle has a radius of at least sqrt(2)/2
    samples (so it covers a sample). The others are counted.
    """
    h, w = valid.shape
    k = tris.shape[0]
    keep = np.zeros(k, np.bool_)
    eps = 1e-9
    # summed-area table of valid over the vertices' box of samples (clipped to the grid)
    n_v = rows.shape[0]
    g_r0, g_r1, g_c0, g_c1 = h, -1, w, -1
    for i in range(n_v):
        g_r0 = min(g_r0, max(0, int(math.floor(rows[i]))))
        g_r1 = max(g_r1, min(h - 1, int(math.ceil(rows[i]))))
        g_c0 = min(g_c0, max(0, int(math.floor(cols[i]))))
        g_c1 = max(g_c1, min(w - 1, int(math.ceil(cols[i]))))
    sh = max(g_r1 - g_r0 + 2, 1)
    sw = max(g_c1 - g_c0 + 2, 1)
    sat = np.zeros((sh, sw), np.int64)
    for r in range(1, sh):
        run = 0
        for col in range(1, sw):
            run += 1 if valid[g_r0 + r - 1, g_c0 + col - 1] else 0
            sat[r, col] = sat[r - 1, col] + run
    for t in range(k):
        a, b, c = tris[t, 0], tris[t, 1], tris[t, 2]
        ra, rb, rc = rows[a], rows[b], rows[c]
        ca, cb, cc = cols[a], cols[b], cols[c]
        area = (cb - ca) * (rc - ra) - (rb - ra) * (cc - ca)
        sgn = 1.0 if area >= 0.0 else -1.0
        tol = eps * max(abs(area), 1.0)
        r_lo = max(0, int(math.ceil(min(ra, rb, rc) - eps)))
        r_hi = min(h - 1, int(math.floor(max(ra, rb, rc) + eps)))
        c_lo = max(0, int(math.ceil(min(ca, cb, cc) - eps)))
        c_hi = min(w - 1, int(math.floor(max(ca, cb, cc) + eps)))
        # the widened box: every covered sample and the centroid's nearest (clamped) sample lie in it
        wr0 = max(0, int(math.floor(min(ra, rb, rc))))
        wr1 = min(h - 1, int(math.ceil(max(ra, rb, rc))))
        wc0 = max(0, int(math.floor(min(ca, cb, cc))))
        wc1 = min(w - 1, int(math.ceil(max(ca, cb, cc))))
        if wr0 <= wr1 and wc0 <= wc1:
            verdict = _box_verdict(sat, wr0, wr1, wc0, wc1, g_r0, g_c0)
            if verdict >= 0:
                keep[t] = verdict == 1
                continue
        inside = (
            min(ra, rb, rc) >= 0.0
            and max(ra, rb, rc) <= h - 1
            and min(ca, cb, cc) >= 0.0
            and max(ca, cb, cc) <= w - 1
        )
        if inside and r_lo <= r_hi and c_lo <= c_hi:
            perim = math.hypot(rb - ra, cb - ca) + math.hypot(rc - rb, cc - cb) + math.hypot(ra - rc, ca - cc)
            if abs(area) >= 0.7072 * perim:  # inradius = |area2| / perimeter >= sqrt(2) / 2
                verdict = _box_verdict(sat, r_lo, r_hi, c_lo, c_hi, g_r0, g_c0)
                if verdict >= 0:
                    keep[t] = verdict == 1
                    continue
        n = 0
        nv = 0
        for r in range(r_lo, r_hi + 1):
            for col in range(c_lo, c_hi + 1):
                e0 = sgn * ((cb - ca) * (r - ra) - (rb - ra) * (col - ca))
                e1 = sgn * ((cc - cb) * (r - rb) - (rc - rb) * (col - cb))
                e2 = sgn * ((ca - cc) * (r - rc) - (ra - rc) * (col - cc))
                if e0 >= -tol and e1 >= -tol and e2 >= -tol:
                    n += 1
                    if valid[r, col]:
                        nv += 1
        if n == 0:
            r = min(max(int(round((ra + rb + rc) / 3.0)), 0), h - 1)
            col = min(max(int(round((ca + cb + cc) / 3.0)), 0), w - 1)
            keep[t] = valid[r, col]
        else:
            keep[t] = 2 * nv >= n
    return keep


@jit
def _all_true(mask):
    """``mask.all()`` of a 2-D bool array (a strided window of the source's mask), without the GIL (a
    coarse tile's window holds millions of samples) and stopping at the first False."""
    h, w = mask.shape
    for r in range(h):
        for c in range(w):
            if not mask[r, c]:
                return False
    return True


@jit
def compact_mesh(rows, cols, heights_m, tris, keep):
    """The mesh of the triangles where ``keep`` is True, without the vertices they leave unused (vertex and
    triangle order kept, indices renumbered, triangles in ``tris``' dtype)."""
    n = rows.shape[0]
    used = np.zeros(n, np.bool_)
    nk = 0
    for t in range(tris.shape[0]):
        if keep[t]:
            nk += 1
            used[tris[t, 0]] = True
            used[tris[t, 1]] = True
            used[tris[t, 2]] = True
    remap = np.empty(n, np.int64)
    m = 0
    for i in range(n):
        remap[i] = m
        if used[i]:
            m += 1
    r_out = np.empty(m, rows.dtype)
    c_out = np.empty(m, cols.dtype)
    h_out = np.empty(m, heights_m.dtype)
    for i in range(n):
        if used[i]:
            r_out[remap[i]] = rows[i]
            c_out[remap[i]] = cols[i]
            h_out[remap[i]] = heights_m[i]
    t_out = np.empty((nk, 3), tris.dtype)
    k = 0
    for t in range(tris.shape[0]):
        if keep[t]:
            t_out[k, 0] = remap[tris[t, 0]]
            t_out[k, 1] = remap[tris[t, 1]]
            t_out[k, 2] = remap[tris[t, 2]]
            k += 1
    return r_out, c_out, h_out, t_out


def drop_nodata(
    rows: np.ndarray, cols: np.ndarray, heights_m: np.ndarray, tris: np.ndarray, valid: np.ndarray,
    window_valid: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """A mesher's tile without the triangles over nodata and the vertices left unused (order kept).

    ``window_valid`` is the source's mask over the tile's window: when it is all True nothing can be
    dropped and the arrays are returned as they are (the tile is bit-identical to an unfiltered build).
    """
    if tris.shape[0] == 0 or _all_true(window_valid):
        return rows, cols, heights_m, tris
    tt = np.ascontiguousarray(tris if tris.dtype in (np.int32, np.int64) else tris.astype(np.int64))
    keep = footprint_mask(
        np.ascontiguousarray(rows, np.float64), np.ascontiguousarray(cols, np.float64), tt,
        np.ascontiguousarray(valid, np.bool_),
    )  # fmt: skip
    if keep.all():
        return rows, cols, heights_m, tris
    r, c, hz, t = compact_mesh(rows, cols, heights_m, tt, keep)
    return r, c, hz, t.astype(tris.dtype, copy=False)
