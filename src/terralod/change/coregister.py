"""Co-registration of AFTER onto BEFORE: the horizontal and vertical shift that makes stable ground agree.

Paper: Nuth, C. and Kääb, A. (2011), "Co-registration and bias corrections of satellite elevation data
sets for quantifying glacier thickness change", The Cryosphere 5, 271-290 (not in ../shared/papers; the
field's standard, implemented by xdem as ``xdem.coreg.NuthKaab``). Their model: on stable ground a
horizontal misregistration (a, b) leaves ``dh = a·cos(b − ψ)·tan(α) + dz`` (ψ aspect, α slope).

Two estimators, same inputs (an :class:`~terralod.change.difference.AlignedPair` and a stable mask on
BEFORE's grid), same output (the translation applied to AFTER, metres):

- ``"xdem"`` (default): ``xdem.coreg.NuthKaab`` fitted on BEFORE's grid. xdem needs both DEMs on one grid;
  :func:`~terralod.change.difference.align` puts them there first, which is what lets it take unequal
  grids and any CRS (geographic inputs are in UTM after reading).
- ``"terralod"``: the same model written in gradient form, ``dh ≈ −∇z·(dx, dy) + dz`` (Nuth & Kääb's
  cosine is the projection of the shift on the gradient, ``tan α·cos(b − ψ)``), solved by Gauss-Newton
  with iteratively re-weighted least squares (cells beyond 3 NMAD of the residual dropped each step; the
  gradient is BEFORE's, fixed, as in inverse-compositional image alignment)
  instead of their binned curve fit of ``dh / tan α`` against aspect, on a coarse-to-fine pair of
  Gaussian-smoothed surfaces (4, 2, 1 px, then unsmoothed) so that shifts of several pixels converge.
  AFTER is sampled from its own grid at the shifted positions (cubic spline), never resampled twice.
  ``benchmarks/change.py`` measures both on known shifts of real DEMs (accuracy, time, memory).

"Stable ground" is a mask given by the caller (``--stable``), else every valid cell outside the change:
the change is where the residual lies beyond 3 NMAD of its median, grown by 2 cells, re-estimated after
each fit (:func:`stable_ground`).
"""

from __future__ import annotations

import logging
import time
import warnings
from dataclasses import dataclass, field

import numpy as np

from terralod.change.difference import AlignedPair, dem_of_difference, sample_surface

log = logging.getLogger(__name__)

#: NMAD = 1.4826 · median absolute deviation: the standard deviation of a normal distribution.
NMAD_FACTOR = 1.4826
#: Residuals beyond this many NMAD are not stable ground (and not used in a fit).
OUTLIER_NMAD = 3.0
#: Cells added around the change before taking the rest as stable ground.
CHANGE_BUFFER_CELLS = 2
#: Fewest stable cells a fit (and an NMAD) is made from.
MIN_STABLE_CELLS = 100
#: Most stable cells used by a fit (a seeded random subsample beyond it, as xdem does).
MAX_FIT_CELLS = 500_000
METHODS = ("xdem", "terralod")


@dataclass
class Coregistration:
    """A fitted translation. ``shift_m`` = (dx, dy, dz) metres applied to AFTER to align it with BEFORE:
    the aligned surface is ``after(x − dx, y − dy) + dz``."""

    shift_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    method: str = "none"
    applied: bool = False
    stable_cells: int = 0
    nmad_before_m: float = float("nan")
    nmad_after_m: float = float("nan")
    iterations: int = 0
    seconds: float = 0.0
    notes: list[str] = field(default_factory=list)

    def as_dict(self) -> dict:
        return {
            "method": self.method,
            "applied": self.applied,
            "shift_m": [float(v) for v in self.shift_m],
            "stable_cells": int(self.stable_cells),
            "nmad_before_m": _num(self.nmad_before_m),
            "nmad_after_m": _num(self.nmad_after_m),
            "iterations": int(self.iterations),
            "seconds": round(float(self.seconds), 4),
            "notes": list(self.notes),
        }


def nmad(values: np.ndarray) -> float:
    """Normalised median absolute deviation of the finite values (NaN when there are none)."""
    v = np.asarray(values, np.float64)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return float("nan")
    return float(NMAD_FACTOR * np.median(np.abs(v - np.median(v))))


def stable_ground(dod: np.ndarray, given: np.ndarray | None = None) -> np.ndarray:
    """Stable cells of a DoD: ``given`` (or every finite cell) minus the change, the cells beyond
    ``OUTLIER_NMAD`` NMAD of the median (re-estimated until it settles), grown by ``CHANGE_BUFFER_CELLS``."""
    from scipy import ndimage

    ok = np.isfinite(dod) if given is None else (np.isfinite(dod) & given)
    stable = ok.copy()
    for _ in range(5):
        v = dod[stable]
        if v.size < MIN_STABLE_CELLS:
            return stable
        med, s = float(np.median(v)), nmad(v)
        change = ok & (np.abs(dod - med) > OUTLIER_NMAD * s)
        if CHANGE_BUFFER_CELLS:
            change = ndimage.binary_dilation(change, iterations=CHANGE_BUFFER_CELLS)
        new = ok & ~change
        if np.array_equal(new, stable):
            break
        stable = new
    return stable


def coregister(
    pair: AlignedPair, *, stable: np.ndarray | None = None, method: str = "xdem", seed: int = 0
) -> Coregistration:
    """Fit the translation of AFTER onto BEFORE on stable ground (``stable``: a mask on BEFORE's grid, or
    None for "outside the change"). Returns a :class:`Coregistration` (not yet applied)."""
    if method not in METHODS:
        raise ValueError(f"Expected a co-registration method in {METHODS}, got {method!r}")
    t0 = time.perf_counter()
    dod0 = dem_of_difference(pair)
    mask = stable_ground(dod0, stable)
    res = Coregistration(method=method, stable_cells=int(mask.sum()), nmad_before_m=nmad(dod0[mask]))
    if res.stable_cells < MIN_STABLE_CELLS:
        res.notes.append(f"co-registration skipped: {res.stable_cells} stable cells (< {MIN_STABLE_CELLS})")
        res.method = "none"
        return res
    if res.nmad_before_m == 0.0:
        res.notes.append(
            "stable ground is identical in both DEMs (difference exactly 0): shift 0, nothing to fit"
        )
        res.nmad_after_m = 0.0
        res.method = "none"
        res.seconds = time.perf_counter() - t0
        return res
    if method == "xdem":
        shift, iters = _fit_xdem(pair, mask, seed)
    else:
        shift, iters = _fit_terralod(pair, mask, seed)
    res.shift_m, res.iterations = shift, iters
    dod1 = dem_of_difference(pair, shift)
    mask1 = stable_ground(dod1, stable)
    res.stable_cells = int(mask1.sum())
    res.nmad_after_m = nmad(dod1[mask1])
    res.seconds = time.perf_counter() - t0
    return res


# -- xdem ----------------------------------------------------------------------------------------------
def _fit_xdem(pair: AlignedPair, mask: np.ndarray, seed: int) -> tuple[tuple[float, float, float], int]:
    import xdem
    from rasterio.crs import CRS

    before = pair.before
    ref = np.where(before.valid, before.elevation_m, np.nan).astype(np.float32)
    tba, _ = pair.after_on_before()
    crs = (
        CRS.from_user_input(before.crs) if before.crs else CRS.from_epsg(32631)
    )  # local frame: any metric CRS
    nk = xdem.coreg.NuthKaab(subsample=MAX_FIT_CELLS)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        nk.fit(ref, tba.astype(np.float32), inlier_mask=mask, transform=before.transform, crs=crs,
               random_state=seed)  # fmt: skip
    out = nk.meta["outputs"]["affine"]
    shift = (float(out["shift_x"]), float(out["shift_y"]), float(out["shift_z"]))
    if not pair.same_grid:
        # xdem fitted the resampled AFTER; refine dz on AFTER sampled once at the shift (the horizontal
        # part does not depend on that resampling to first order)
        d = dem_of_difference(pair, shift)
        shift = (shift[0], shift[1], shift[2] - float(np.median(d[mask & np.isfinite(d)])))
    return shift, 1


# -- own estimator -------------------------------------------------------------------------------------
def _fit_terralod(
    pair: AlignedPair, mask: np.ndarray, seed: int, *, tol_px: float = 1e-3, max_iter: int = 30
) -> tuple[tuple[float, float, float], int]:
    """Gauss-Newton on ``r(t) = A(x − t_xy) + t_z − B(x)`` over stable cells, coarse to fine."""
    from scipy import ndimage

    before, after = pair.before, pair.after
    rows, cols = np.nonzero(mask)
    if rows.size > MAX_FIT_CELLS:
        pick = np.random.default_rng(seed).choice(rows.size, MAX_FIT_CELLS, replace=False)
        rows, cols = rows[pick], cols[pick]
    x, y = before.world_xy(rows, cols)
    dxa, dya = after.spacing_m
    t = np.zeros(3)
    iters = 0
    b_full = before.elevation_m.astype(np.float64)
    a_full = after.elevation_m.astype(np.float64)
    px = float(min(before.spacing_m))
    for sigma_px in (4.0, 2.0, 1.0, 0.0):
        b_s = ndimage.gaussian_filter(b_full, sigma_px) if sigma_px else b_full
        a_s = ndimage.gaussian_filter(a_full, sigma_px * px / min(dxa, dya)) if sigma_px else a_full
        b = b_s[rows, cols]
        a_coef = ndimage.spline_filter(a_s, order=3)
        # the gradient of BEFORE at its own cells (central differences leave the cell's own sample out, so
        # white noise in the residual is uncorrelated with it; AFTER's gradient would share AFTER's noise)
        gy_b, gx_b = np.gradient(b_s)
        gx = gx_b[rows, cols] / before.spacing_m[0]  # d/dx east
        gy = -gy_b[rows, cols] / before.spacing_m[1]  # d/dy north (row 0 north)
        for _ in range(max_iter):
            iters += 1
            r, c = after.sample_rc(x - t[0], y - t[1])
            coords = np.stack([r, c])
            a = ndimage.map_coordinates(a_coef, coords, order=3, mode="nearest", prefilter=False)
            _, ok = sample_surface(after, r, c, order=1)
            res = a + t[2] - b
            med = np.median(res[ok])
            s = max(nmad(res[ok]), 1e-9)
            use = ok & (np.abs(res - med) <= OUTLIER_NMAD * s)
            if use.sum() < MIN_STABLE_CELLS:
                break
            # r(t + δ) ≈ r(t) − ∇A(x − t)·δ + δz, and ∇A(x − t) ≈ ∇B(x) near the solution
            m = np.column_stack([gx[use], gy[use], -np.ones(int(use.sum()))])
            delta, *_ = np.linalg.lstsq(m, res[use], rcond=None)
            t += delta
            if np.hypot(delta[0], delta[1]) < tol_px * px and abs(delta[2]) < 1e-4:
                break
    # final vertical offset: the median residual of the unsmoothed surfaces on the inliers
    d = dem_of_difference(pair, tuple(t))
    st = stable_ground(d, mask)
    if st.sum() >= MIN_STABLE_CELLS:
        t[2] -= float(np.median(d[st]))
    return (float(t[0]), float(t[1]), float(t[2])), iters


def _num(v: float):
    return None if v is None or not np.isfinite(v) else float(v)


def read_stable_mask(path, hf) -> np.ndarray:
    """A stable-ground mask on ``hf``'s grid from a raster (non-zero, finite = stable; nearest-neighbour
    onto the grid, in its own CRS) or from GeoJSON polygons (inside = stable; see
    :func:`terralod.change.zones.read_zones` for their CRS)."""
    from pathlib import Path

    from terralod.errors import InputError, InputNotFoundError

    p = Path(path)
    if not p.exists():
        raise InputNotFoundError("file not found", str(p))
    if p.suffix.lower() in (".geojson", ".json"):
        from terralod.change.zones import read_zones

        masks = [m for _, m, _, _ in read_zones(p, hf)]
        return np.logical_or.reduce(masks)
    import rasterio
    from rasterio.warp import Resampling, reproject

    try:
        with rasterio.open(p) as ds:
            src = ds.read(1).astype(np.float32)
            if ds.nodata is not None:
                src[src == ds.nodata] = 0
            out = np.zeros(hf.shape, np.float32)
            crs = ds.crs or hf.crs
            if crs is None or hf.crs is None:
                if src.shape != hf.shape:
                    raise InputError(
                        f"has no CRS and its shape {src.shape} is not the DEM's {hf.shape}", str(p)
                    )
                out = src
            else:
                reproject(src, out, src_transform=ds.transform, src_crs=crs, dst_transform=hf.transform,
                          dst_crs=hf.crs, resampling=Resampling.nearest)  # fmt: skip
    except rasterio.errors.RasterioIOError as exc:
        raise InputError(f"is not a raster mask or GeoJSON ({exc})", str(p)) from None
    mask = np.isfinite(out) & (out != 0)
    if not mask.any():
        raise InputError("marks no stable cell on the terrain", str(p))
    return mask
