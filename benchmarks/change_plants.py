"""Planted change on real terrain, shared by ``tests/test_change_pairs.py`` (its proofs) and
``benchmarks/change.py`` (terralod against xdem on the same plants): the windows of ../shared/data, a
landslide's scarp and deposit, a lake whose level changed, and AFTER as the truth resampled with a shift, a
bias, noise and a coarser grid.
"""

from __future__ import annotations

import math
from functools import cache
from pathlib import Path

import numpy as np
from affine import Affine
from scipy import ndimage

from terralod import read_heightfield
from terralod.heightfield import Heightfield

from _common import SHARED

#: name: (file, row, col, size, what the fit can do there); lakes are planted where there is flat land
TERRAINS = {
    "coast_tarragona": ("srtm3_N41E001.tif", 1000, 500, 320, "shift"),  # 17 % sea at 0 m
    "coast_kattegat": ("srtm3_N57E011.tif", 448, 640, 320, "shift"),  # skerries, 64 % sea
    "mountains_pyrenees": ("srtm3_N42E001.tif", 600, 500, 256, "shift"),
    "geographic_alpine": ("srtm1_crop256_alpine.tif", 0, 60, 200, "shift"),  # lon/lat file
    # 1 m cells on gentle slopes under 1-1.5 m of noise: a shift is fitted only when it can be trusted
    "prairie_lidar_1m": ("lidar_1m_prairie_depressions_utm15.tif", 0, 0, 320, "either"),
}
#: the flattest: a Kattegat window 93 % sea, its land low skerries and shore (South Florida's suburbs and
#: the North German Plain carry enough 3° slopes to fit a sub-cell shift, and do)
FLATTEST = ("srtm3_N57E011.tif", 1024, 768, 320, "bias")


@cache
def _read(path: Path) -> Heightfield:
    return read_heightfield(path)


def crop(name: str, r0: int, c0: int, n: int, dem: Path = SHARED / "dem") -> Heightfield:
    """The n x n window at (r0, c0) of the DEM ``dem / name`` (read once per process)."""
    hf = _read(dem / name)
    z = hf.elevation_m[r0 : r0 + n, c0 : c0 + n].astype(np.float32)
    ok = hf.valid[r0 : r0 + n, c0 : c0 + n]
    return Heightfield(z, ok, hf.transform * Affine.translation(c0, r0), crs=hf.crs, source=name)


def bowl(shape, r: float, c: float, radius: float) -> np.ndarray:
    """A smooth cosine bowl of height 1 at (r, c), 0 beyond ``radius`` cells."""
    rr, cc = np.indices(shape)
    d = np.hypot(rr - r, cc - c) / radius
    return np.where(d < 1, 0.5 * (1 + np.cos(np.pi * d)), 0.0)


def landslide(hf: Heightfield, rng: np.random.Generator, depth_m: float, radius: float, avoid=None) -> tuple:
    """A scarp of ``depth_m`` on a slope and its deposit (the same volume) 3 radii downhill, both at least
    8 cells clear of each other and of ``avoid`` (another change)."""
    z = ndimage.gaussian_filter(hf.elevation_m.astype(np.float64), radius / 2)
    gy, gx = np.gradient(z)
    slope = np.hypot(gx, gy) / hf.spacing_m[0]
    h, w = hf.shape
    m = int(4.5 * radius)
    inner = np.zeros(hf.shape, bool)
    inner[m : h - m, m : w - m] = True
    # away from data gaps (the sea, voids): a change is measured where both surveys have data
    far = ndimage.distance_transform_edt(hf.valid)
    inner &= far >= min(3.5 * radius, float(np.percentile(far[inner], 90)))
    cand = np.argwhere(inner & (slope >= np.percentile(slope[inner], 60)))
    keep_off = np.zeros(hf.shape, bool) if avoid is None else ndimage.binary_dilation(avoid, iterations=10)
    for _ in range(100):
        r, c = cand[rng.integers(len(cand))]
        g = np.array([gy[r, c], gx[r, c]])
        g = g / (np.hypot(*g) + 1e-12)
        r2 = float(np.clip(r - g[0] * 3 * radius, radius, h - radius))
        c2 = float(np.clip(c - g[1] * 3 * radius, radius, w - radius))
        scarp = -depth_m * bowl(hf.shape, r, c, radius)
        dep = bowl(hf.shape, r2, c2, radius)
        if not (keep_off & ((scarp != 0) | (dep != 0))).any() and math.hypot(r - r2, c - c2) >= 2.9 * radius:
            break
    dep *= -scarp.sum() / dep.sum()
    return scarp, dep


def lake(hf: Heightfield, rng: np.random.Generator, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """A lake on the flattest land: BEFORE's surface set level within a disc (returned as the new BEFORE
    elevation), and its level change in AFTER (returned as a change of known volume)."""
    z = hf.elevation_m.astype(np.float64)
    h, w = hf.shape
    rr, cc = np.indices(hf.shape)
    m = int(2 * radius)
    rough = ndimage.generic_filter(z[::4, ::4], np.ptp, size=5)
    ok = np.zeros_like(rough, bool)
    ok[m // 4 : (h - m) // 4, m // 4 : (w - m) // 4] = True
    ok &= hf.valid[::4, ::4] & (z[::4, ::4] > 1)
    idx = np.argwhere(ok & (rough <= np.percentile(rough[ok], 20)))
    r, c = idx[rng.integers(len(idx))] * 4
    disc = np.hypot(rr - r, cc - c) <= radius
    level = float(np.min(z[disc]))
    z2 = np.where(disc, level, z)
    rise = float(rng.uniform(5.0, 10.0)) * (1 if rng.random() < 0.5 else -1)
    return z2.astype(np.float32), np.where(disc, rise, 0.0)


def make_after(hf: Heightfield, truth: np.ndarray, shift_px, bias_m, noise_m, factor, seed):
    """AFTER(p) = T(p + s) + bias + noise on a grid ``factor`` times coarser (T: cubic spline of ``truth``).
    Returns AFTER and the shift (dx, dy, dz) that undoes it."""
    rng = np.random.default_rng(seed)
    px, py = hf.spacing_m
    s = (shift_px[0] * px, shift_px[1] * py)
    t = hf.transform * Affine.scale(factor)
    h, w = int(hf.shape[0] / factor), int(hf.shape[1] / factor)
    rows, cols = np.indices((h, w), dtype=np.float64)
    x, y = t.c + (cols + 0.5) * t.a, t.f + (rows + 0.5) * t.e
    r, c = hf.sample_rc(x + s[0], y + s[1])
    # the heightfield's own fill of its gaps (not a constant, which would ring through the spline)
    z = ndimage.map_coordinates(ndimage.spline_filter(truth.astype(np.float64)), [r, c], order=3,
                                prefilter=False, mode="nearest")  # fmt: skip
    inside = (r >= 0) & (r <= hf.shape[0] - 1) & (c >= 0) & (c <= hf.shape[1] - 1)
    ok = inside & (ndimage.map_coordinates(hf.valid.astype(float), [r, c], order=1, cval=0) >= 0.999)
    z = z + bias_m + rng.normal(0.0, noise_m, z.shape)
    after = Heightfield(z.astype(np.float32), ok, t, crs=hf.crs, source="after.tif")
    return after, (s[0], s[1], -bias_m)
