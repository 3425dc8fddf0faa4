"""Quantized-mesh tiles meshed on a geographic DEM's own lattice (no resampling of the source).

A WGS 84 longitude/latitude DEM (SRTM and most global DEMs) has its samples on a regular lon/lat lattice,
and Cesium's geographic tiles are lon/lat rectangles. So a tile's grid is the source lattice itself: the
lattice columns and rows strictly inside the tile (every ``stride``-th one, counted from the DEM's first
sample so that a tile's grid points are also its children's) plus the tile's four edges, whose heights are
the bilinear surface of the samples there. At the finest zoom the stride is 1: every source sample is a
grid point, so the mesh can reach a true error of zero; coarser zooms take every 2nd, 4th... sample (the
samples themselves, never an average that moves a peak). Outside the DEM the lattice is not extended
(heights there continue the edge values, which the tile's edges and the DEM's first and last rows and
columns already carry), so a coarse tile that spans far beyond the DEM holds no empty grid.

The error of a decoded tile against the source (:func:`lattice_error`) walks each triangle's rows of the
lattice window inside the tile, testing only the samples between its edges, and accumulates the max
and the sum of squares of the vertical distance over every valid sample (a valid sample no triangle
covers is counted: a hole is detected, not skipped).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numba import njit

from terralod.kernels.error import triangle_gap

__all__ = ["Lattice", "lattice_error"]

#: Most lattice samples per tile side at the finest zoom (the water mask is 256², Cesium's heightmaps 65²).
MAX_SAMPLES = 256


class Lattice:
    """The lon/lat lattice of a geographic :class:`~terralod.export.source.SourceGrid` (north-up)."""

    def __init__(self, ref: Any) -> None:
        t = ref.t
        self.ref = ref
        self.a_deg, self.e_deg = float(t.a), float(t.e)  # e < 0 (north-up)
        self.c_deg, self.f_deg = float(t.c), float(t.f)
        self.z = ref.z_m
        self.valid = ref.valid
        self.h, self.w = self.z.shape
        # the same expressions as the source's sample positions (a sample on a tile edge is in both tiles)
        self.lon_c = self.c_deg + (np.arange(self.w) + 0.5) * self.a_deg
        self.lat_r = self.f_deg + (np.arange(self.h) + 0.5) * self.e_deg
        self.water = ~self.valid | (self.z == 0.0)  # nodata and sea at exactly 0 m
        self.any_water = bool(self.water.any())
        w, s, e, n = ref.bbox
        self.footprint = (w, s, e, n)

    def finest_zoom(self) -> int:
        """The first zoom whose tiles hold at most MAX_SAMPLES lattice samples per side."""
        z = 0
        while 180.0 / (1 << z) > MAX_SAMPLES * min(abs(self.a_deg), abs(self.e_deg)) and z < 22:
            z += 1
        return z

    def stride(self, z: int, finest: int) -> int:
        """Every stride-th lattice sample at zoom z: 1 at the two finest zooms (the one below the finest
        meshes every sample too, up to 2 MAX_SAMPLES + 2 a side: no peak lost where the error is still
        small), then 2, 4, ... (grids of at most 2 MAX_SAMPLES + 2 a side)."""
        return 1 << max(finest - 1 - z, 0)

    # -- one tile's grid ----------------------------------------------------------------------------------
    def window(self, rect: tuple[float, float, float, float]) -> tuple[int, int, int, int]:
        """(r0, r1, c0, c1), half-open: the lattice samples inside the tile, its edges included."""
        w, s, e, n = rect
        c0 = int(np.searchsorted(self.lon_c, w, "left"))
        c1 = int(np.searchsorted(self.lon_c, e, "right"))
        neg = -self.lat_r  # increasing
        r0 = int(np.searchsorted(neg, -n, "left"))
        r1 = int(np.searchsorted(neg, -s, "right"))
        return r0, r1, c0, c1

    def grid(self, rect: tuple[float, float, float, float], stride: int) -> tuple[Any, ...]:
        """The tile's uniform grid: every stride-th lattice row/column (counted from the DEM's first sample)
        from the last one at or before the tile's west/north edge to the first at or after its east/south
        edge (heights clamped outside the DEM: its edge values continue), and the tile's rectangle in
        grid units. Returns (r0, c0, heights (north row first), (x_w, x_e, y_n, y_s))."""
        w, s, e, n = rect
        fc_w = (w - self.c_deg) / self.a_deg - 0.5
        fc_e = (e - self.c_deg) / self.a_deg - 0.5
        fr_n = (n - self.f_deg) / self.e_deg - 0.5
        fr_s = (s - self.f_deg) / self.e_deg - 0.5
        c0 = int(math.floor(fc_w / stride + 1e-9)) * stride
        c1 = int(math.ceil(fc_e / stride - 1e-9)) * stride
        r0 = int(math.floor(fr_n / stride + 1e-9)) * stride
        r1 = int(math.ceil(fr_s / stride - 1e-9)) * stride
        rows = np.clip(np.arange(r0, r1 + 1, stride), 0, self.h - 1)
        cols = np.clip(np.arange(c0, c1 + 1, stride), 0, self.w - 1)
        g = self.z[rows[:, None], cols[None, :]]
        box = ((fc_w - c0) / stride, (fc_e - c0) / stride, (fr_n - r0) / stride, (fr_s - r0) / stride)
        return r0, c0, g, box

    def bilinear(self, fr: np.ndarray, fc: np.ndarray) -> np.ndarray:
        """Heights at fractional lattice indices (broadcast), clamped to the grid: outside it the edge
        values continue outward."""
        fr = np.clip(fr, 0.0, self.h - 1)
        fc = np.clip(fc, 0.0, self.w - 1)
        r0 = np.minimum(np.floor(fr).astype(np.int64), max(self.h - 2, 0))
        c0 = np.minimum(np.floor(fc).astype(np.int64), max(self.w - 2, 0))
        r1, c1 = np.minimum(r0 + 1, self.h - 1), np.minimum(c0 + 1, self.w - 1)
        tr, tc = fr - r0, fc - c0
        z = self.z
        top = z[r0, c0] * (1 - tc) + z[r0, c1] * tc
        bot = z[r1, c0] * (1 - tc) + z[r1, c1] * tc
        return top * (1 - tr) + bot * tr

    def normals_enu(self, fr: np.ndarray, fc: np.ndarray, lat: np.ndarray, stride: int) -> np.ndarray:
        """(N, 3) east/north/up unit normals of the sampled surface at fractional lattice indices (central
        differences over ``stride`` samples; the same at a point any tile of the zoom shares)."""
        d = float(stride)
        dx_m = 2 * d * abs(self.a_deg) * 111320.0 * np.cos(np.radians(np.clip(lat, -89.9, 89.9)))
        dy_m = 2 * d * abs(self.e_deg) * 111320.0
        dzdx = (self.bilinear(fr, fc + d) - self.bilinear(fr, fc - d)) / np.maximum(dx_m, 1e-6)
        dzdy = (self.bilinear(fr - d, fc) - self.bilinear(fr + d, fc)) / dy_m
        enu = np.column_stack([-dzdx, -dzdy, np.ones_like(dzdx)])
        return enu / np.linalg.norm(enu, axis=1, keepdims=True)

    def water_mask(self, rect: tuple[float, float, float, float]) -> np.ndarray | int:
        """The tile's water mask: 0 (no water), 255 (all water) or a 256² grid (north row first) of the
        nearest sample's water (nodata or 0 m) at the mask's pixel centres; nothing outside the DEM."""
        if not self.any_water:
            return 0
        r0, r1, c0, c1 = self.window(rect)
        if r1 <= r0 or c1 <= c0:
            return 0
        win = self.water[max(r0 - 1, 0) : r1 + 1, max(c0 - 1, 0) : c1 + 1]
        if not win.any():
            return 0
        w, s, e, n = rect
        fw, fs, fe, fn = self.footprint
        inside = w >= fw and e <= fe and s >= fs and n <= fn
        if inside and win.all():
            return 255
        px = w + (np.arange(256) + 0.5) * (e - w) / 256
        py = n - (np.arange(256) + 0.5) * (n - s) / 256
        cc = np.rint((px - self.c_deg) / self.a_deg - 0.5).astype(np.int64)
        rr = np.rint((py - self.f_deg) / self.e_deg - 0.5).astype(np.int64)
        okc = (px >= fw) & (px <= fe)
        okr = (py >= fs) & (py <= fn)
        m = self.water[np.clip(rr, 0, self.h - 1)[:, None], np.clip(cc, 0, self.w - 1)[None, :]]
        m = m & okr[:, None] & okc[None, :]
        if not m.any():
            return 0
        if m.all():
            return 255
        return m.astype(np.uint8) * np.uint8(255)


@njit(cache=True)
def _lattice_error_kernel(tu, tv, th, tris, pu, pv, zwin, vwin):  # pragma: no cover - numba
    """Vertical distance between triangles (tu, tv, th; u/v units) and the lattice points (pu[k], pv[j])
    of heights zwin[j, k] where vwin[j, k] (a valid sample). Returns (max over every test, sum of squares
    and count over the samples, each once: at the first triangle that covers it, valid samples that no
    triangle covers). pu increases, pv decreases (north row first). Each triangle tests the points of its
    rows between its edges (a small margin, then the same barycentric test as the scattered-point kernel:
    edges included). Only a (rows, cols) byte array besides the inputs: a tile that spans the whole DEM
    needs one byte per sample."""
    nj, nk = zwin.shape
    if nj == 0 or nk == 0:
        return 0.0, 0.0, 0, 0
    seen = np.zeros((nj, nk), np.uint8)
    sumsq = 0.0
    count = 0
    pu0 = pu[0]
    du = (pu[nk - 1] - pu[0]) / (nk - 1) if nk > 1 else 1.0
    pv0 = pv[0]
    dv = (pv[0] - pv[nj - 1]) / (nj - 1) if nj > 1 else 1.0
    if du <= 0.0:
        du = 1.0
    if dv <= 0.0:
        dv = 1.0
    err = 0.0
    tol = 1e-9
    for t in range(tris.shape[0]):
        a, b, c = tris[t, 0], tris[t, 1], tris[t, 2]
        ua, va, ub, vb, uc, vc = tu[a], tv[a], tu[b], tv[b], tu[c], tv[c]
        det = (vb - vc) * (ua - uc) + (uc - ub) * (va - vc)
        if det == 0.0:
            continue
        vmin = min(va, vb, vc)
        vmax = max(va, vb, vc)
        j0 = max(int(math.floor((pv0 - vmax) / dv)) - 1, 0)
        j1 = min(int(math.ceil((pv0 - vmin) / dv)) + 1, nj - 1)
        for j in range(j0, j1 + 1):
            y = pv[j]
            if y < vmin - 1e-6 or y > vmax + 1e-6:
                continue
            lo = 1e300
            hi = -1e300
            for q in range(3):
                if q == 0:
                    u1, v1, u2, v2 = ua, va, ub, vb
                elif q == 1:
                    u1, v1, u2, v2 = ub, vb, uc, vc
                else:
                    u1, v1, u2, v2 = uc, vc, ua, va
                if v1 == v2:
                    if abs(y - v1) <= 1e-6:
                        lo = min(lo, u1, u2)
                        hi = max(hi, u1, u2)
                elif min(v1, v2) - 1e-6 <= y <= max(v1, v2) + 1e-6:
                    x = u1 + (y - v1) * (u2 - u1) / (v2 - v1)
                    lo = min(lo, x)
                    hi = max(hi, x)
            if hi < lo:
                continue
            k0 = max(int(math.floor((lo - pu0) / du)) - 1, 0)
            k1 = min(int(math.ceil((hi - pu0) / du)) + 1, nk - 1)
            for k in range(k0, k1 + 1):
                if not vwin[j, k]:
                    continue
                x = pu[k]
                d = triangle_gap(ua, va, ub, vb, uc, vc, det, th[a], th[b], th[c], x, y, zwin[j, k], tol)
                if d >= 0.0:
                    if d > err:
                        err = d
                    if seen[j, k] == 0:
                        seen[j, k] = 1
                        sumsq += d * d
                        count += 1
    missed = 0
    for j in range(nj):
        for k in range(nk):
            if vwin[j, k] and seen[j, k] == 0:
                missed += 1
    return err, sumsq, count, missed


@njit(cache=True)
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


def lattice_error(lat: Lattice, tile: dict[str, Any], rect: tuple[float, float, float, float]
                  ) -> tuple[float, float, int]:  # fmt: skip
    """(max, sum of squares, count) of the vertical distance between a decoded tile (:func:`decode_tile`)
    and every valid lattice sample inside ``rect``. Raises RuntimeError when a sample lies in no triangle."""
    r0, r1, c0, c1 = lat.window(rect)
    if r1 <= r0 or c1 <= c0:
        return 0.0, 0.0, 0
    w, s, e, n = rect
    pu = np.clip((lat.lon_c[c0:c1] - w) / (e - w), 0.0, 1.0) * 32767.0
    pv = np.clip((lat.lat_r[r0:r1] - s) / (n - s), 0.0, 1.0) * 32767.0
    err, sumsq, count, missed = _lattice_error_kernel(
        tile["u"].astype(np.float64), tile["v"].astype(np.float64), np.asarray(tile["height"], np.float64),
        np.ascontiguousarray(tile["triangles"], np.int64), pu, pv, lat.z[r0:r1, c0:c1], lat.valid[r0:r1, c0:c1],
    )  # fmt: skip
    if missed:
        raise RuntimeError(f"{missed} samples fall outside every triangle of the tile (a hole in its mesh)")
    return float(err), float(sumsq), int(count)
