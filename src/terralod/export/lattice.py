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

Where a tile's bytes are decided: this module gives a lattice tile's grid, normals, water mask and
error; :meth:`terralod.export.quantized_mesh.QuantizedMesh.tile` chooses its target and meshes it, and
:mod:`terralod.export.quantized_mesh_format` writes the bytes. The kernels (clipping, the error walk) are in
:mod:`terralod.kernels.lattice` and :mod:`terralod.kernels.error`.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from terralod.kernels.error import lattice_vertical_error

__all__ = ["Lattice", "lattice_error"]

#: Most lattice samples per tile side at the finest zoom (the water mask is 256², Cesium's heightmaps 65²).
MAX_SAMPLES = 256
#: Most samples of a tile's window read at once (a coarse tile's window can be the whole region: it is read
#: in strips of rows this big, about 20 MB, so memory does not grow with the region).
STRIP_SAMPLES = 1 << 22


def _strips(r0: int, r1: int, c0: int, c1: int) -> list[tuple[int, int]]:
    """Row ranges [ra, rb) covering [r0, r1), each at most STRIP_SAMPLES samples of width c1 - c0 (at least
    two rows); one range when the window is small."""
    step = max(STRIP_SAMPLES // max(c1 - c0, 1), 2)
    return [(ra, min(ra + step, r1)) for ra in range(r0, r1, step)]


class Lattice:
    """The lon/lat lattice of a geographic :class:`~terralod.export.source.SourceGrid` (north-up).

    Samples are read through the source's ``window`` / ``gather`` / ``take`` (rows from the north), never
    as one array: a :class:`~terralod.export.source.RegionGrid` answers them from a bounded cache of
    blocks, so a tile touches only the window it covers (plus one sample, and ``stride`` more for its
    normals); at a coarse zoom, only every ``stride``-th row and column of it.
    """

    def __init__(self, ref: Any) -> None:
        t = ref.t
        self.ref = ref
        self.a_deg, self.e_deg = float(t.a), float(t.e)  # e < 0 (north-up)
        self.c_deg, self.f_deg = float(t.c), float(t.f)
        self.h, self.w = ref.shape
        # the same expressions as the source's sample positions (a sample on a tile edge is in both tiles)
        self.lon_c = self.c_deg + (np.arange(self.w) + 0.5) * self.a_deg
        self.lat_r = self.f_deg + (np.arange(self.h) + 0.5) * self.e_deg
        self.any_water = bool(ref.any_water)  # some sample is nodata or sea at exactly 0 m
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
        if stride == 1:  # one window of the samples, its edge rows and columns repeated outside the DEM
            ra, ca = int(rows[0]), int(cols[0])
            win = self.ref.window(ra, int(rows[-1]) + 1, ca, int(cols[-1]) + 1)[0]
            g = win[(rows - ra)[:, None], (cols - ca)[None, :]]
        else:
            g = self.ref.gather(rows, cols)[0]
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
        take = self.ref.take
        top = take(r0, c0)[0] * (1 - tc) + take(r0, c1)[0] * tc
        bot = take(r1, c0)[0] * (1 - tc) + take(r1, c1)[0] * tc
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
        ra, rb, ca, cb = max(r0 - 1, 0), min(r1 + 1, self.h), max(c0 - 1, 0), min(c1 + 1, self.w)
        some, every = self.ref.water_any_all(ra, rb, ca, cb)  # any / all nodata or sea at exactly 0 m
        if not some:
            return 0
        w, s, e, n = rect
        fw, fs, fe, fn = self.footprint
        inside = w >= fw and e <= fe and s >= fs and n <= fn
        if inside and every:
            return 255
        px = w + (np.arange(256) + 0.5) * (e - w) / 256
        py = n - (np.arange(256) + 0.5) * (n - s) / 256
        cc = np.rint((px - self.c_deg) / self.a_deg - 0.5).astype(np.int64)
        rr = np.rint((py - self.f_deg) / self.e_deg - 0.5).astype(np.int64)
        okc = (px >= fw) & (px <= fe)
        okr = (py >= fs) & (py <= fn)
        m = self.ref.water_gather(np.clip(rr, 0, self.h - 1), np.clip(cc, 0, self.w - 1))
        m = m & okr[:, None] & okc[None, :]
        if not m.any():
            return 0
        if m.all():
            return 255
        return m.astype(np.uint8) * np.uint8(255)


def lattice_error(lat: Lattice, tile: dict[str, Any], rect: tuple[float, float, float, float]
                  ) -> tuple[float, float, int]:  # fmt: skip
    """(max, sum of squares, count) of the vertical distance between a decoded tile (:func:`decode_tile`)
    and every valid lattice sample inside ``rect``. Raises RuntimeError when a sample lies in no triangle.

    A window over STRIP_SAMPLES (a coarse tile of a large region) is measured strip by strip of rows: the
    same max and count; the sum of squares added in another order (it feeds only the level's RMS in
    ``layer.json``; the goal zoom's parents, whose RMS sets their children's target, are never that big)."""
    r0, r1, c0, c1 = lat.window(rect)
    if r1 <= r0 or c1 <= c0:
        return 0.0, 0.0, 0
    w, s, e, n = rect
    pu = np.clip((lat.lon_c[c0:c1] - w) / (e - w), 0.0, 1.0) * 32767.0
    pv = np.clip((lat.lat_r[r0:r1] - s) / (n - s), 0.0, 1.0) * 32767.0
    tu, tv = tile["u"].astype(np.float64), tile["v"].astype(np.float64)
    th, tris = np.asarray(tile["height"], np.float64), np.ascontiguousarray(tile["triangles"], np.int64)
    err, sumsq, count, missed = 0.0, 0.0, 0, 0
    for ra, rb in _strips(r0, r1, c0, c1):
        z, ok = lat.ref.window(ra, rb, c0, c1)
        e_, s_, n_, m_ = lattice_vertical_error(tu, tv, th, tris, pu, pv[ra - r0 : rb - r0], z, ok)
        err, sumsq, count, missed = max(err, e_), sumsq + s_, count + n_, missed + m_
    if missed:
        raise RuntimeError(f"{missed} samples fall outside every triangle of the tile (a hole in its mesh)")
    return float(err), float(sumsq), int(count)
