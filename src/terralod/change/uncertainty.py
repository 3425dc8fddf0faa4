"""The error of a DoD that holds where the change is (issue 54): larger on steep and rugged ground, and
correlated over several distances.

The model (Hugonnet et al. 2022, IEEE JSTARS 15, 6456, as xdem 0.2 implements it):

1. **Heteroscedasticity**: σ(slope, curvature) of one cell, the NMAD of the co-registered difference on
   stable ground binned by BEFORE's slope (degrees) and maximum absolute curvature (1/100 m, xdem's unit),
   fitted as :func:`xdem.spatialstats.infer_heteroscedasticity_from_stable` does (bins with at least
   :data:`MIN_BIN_CELLS` cells; empty bins interpolated, beyond the edges the nearest). It is kept as a table
   on the bins' centres and applied cell by cell with the same linear interpolation (:meth:`ErrorModel.sigma`).
   The surveys' resolutions enter through the fit itself (the pair is fitted on its own common grid) and,
   when AFTER was resampled, through the resampling's own error (:func:`terralod.change.volumes.resampling_error`).
2. **Spatial correlation**: the stable difference standardised by σ(slope, curvature), its empirical
   semivariogram along rows and columns (lags of 1 to 64 cells: the bounded sample of
   :mod:`terralod.change.windowed` lays its windows 65 cells apart), fitted as a sum of
   :data:`N_RANGES` spherical models as :func:`xdem.spatialstats.fit_sum_model_variogram` fits it (its steps,
   with the models' sum in a kernel: :func:`fit_sum_spherical`, bit for bit xdem's); the partial sills
   are kept as fractions of the standardised variance.
3. **Propagation** to a volume over a set S of n cells of area a (A = n·a), the circular-area
   approximation of xdem's ``spatial_error_propagation`` for a numeric area (Rolstad et al. 2009
   generalised: ``neff_circular_approx_theoretical``), with σ varying from cell to cell::

       σ_V² = a² Σ_k q_k · max(Σ σ_i², (Σ σ_i)² · g(L_k, A)),
       g(L, A) = 1 − R/L + (R/L)³/5 when R = √(A/π) ≤ L, else (L/R)²/5,

   q_k the fractions of the ranges L_k. The approximation: S is taken as a disc of its area, and the
   mean σ over S (Σσ_i / n) stands for every cell's (xdem's ``mean(SD)``); a range's share never falls
   below the uncorrelated sum Σσ_i². Only Σσ_i, Σσ_i² and n enter, so the volumes of a region are
   accumulated window by window exactly as over the whole grid
   (:class:`terralod.change.volumes.BudgetSums`).

The model is fitted on the bounded sample (:mod:`terralod.change.windowed`) or the whole pair in memory,
and applied to every window. ``--sigma-m`` replaces σ(slope, curvature) by one value, ``--corr-range-m``
the fitted ranges by one range; with both the single-σ model of :mod:`terralod.change.volumes` is used, as
it is (with a note) when the stable ground is too small to fit this one.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from typing import Any

import numpy as np

#: Fewest stable cells the model is fitted on (below: the single-σ model, with a note).
MIN_MODEL_CELLS = 2000
#: Fewest stable cells of one slope × curvature bin.
MIN_BIN_CELLS = 100
#: Spherical ranges summed in the correlation model.
N_RANGES = 2
#: Longest lag of the empirical variogram, cells.
MAX_LAG_CELLS = 64


def terrain_attributes(
    z_m: np.ndarray, valid: np.ndarray, spacing_m: tuple[float, float]
) -> tuple[np.ndarray, np.ndarray]:
    """(slope in degrees, maximum absolute curvature in 1/100 m) of a grid by central differences; cells
    whose stencil meets a gap get 0 (flat)."""
    dx, dy = (float(v) for v in spacing_m)
    z = np.where(valid, z_m, np.nan).astype(np.float64)
    gy, gx = np.gradient(z)
    gx, gy = gx / dx, gy / dy
    slope = np.degrees(np.arctan(np.hypot(gx, gy)))
    gxy, gxx = np.gradient(gx)
    gyy, _ = np.gradient(gy)
    gxx, gyy, gxy = gxx / dx, gyy / dy, gxy / dy
    half = 0.5 * (gxx + gyy)
    root = np.sqrt((0.5 * (gxx - gyy)) ** 2 + gxy**2)
    maxc = 100.0 * np.maximum(np.abs(half + root), np.abs(half - root))
    return np.nan_to_num(slope, nan=0.0), np.nan_to_num(maxc, nan=0.0)


@dataclass
class ErrorModel:
    """σ(slope, curvature) as a table and the correlation as fractions of spherical ranges (module
    docstring). ``sigma_given_m`` / ``range_given_m`` replace the fitted σ / ranges (``--sigma-m`` /
    ``--corr-range-m``)."""

    slope_centres_deg: np.ndarray
    curv_centres: np.ndarray
    table_m: np.ndarray
    ranges_m: tuple[float, ...]
    fractions: tuple[float, ...]
    stable_cells: int
    sigma_given_m: float | None = None
    range_given_m: float | None = None
    #: (slope threshold °, σ above it, σ on flat ground) measured on stable ground, for the plain words
    contrast: tuple[float, float, float] | None = None
    variogram: list[tuple[float, float, int]] = field(default_factory=list)

    def sigma(self, slope_deg: np.ndarray, curv: np.ndarray) -> np.ndarray:
        """σ of each cell, metres (float32)."""
        if self.sigma_given_m is not None:
            return np.full(np.shape(slope_deg), self.sigma_given_m, np.float32)
        return _interp2(self.slope_centres_deg, self.curv_centres, self.table_m, slope_deg, curv)

    def sigma_of_grid(self, z_m: np.ndarray, valid: np.ndarray, spacing_m: tuple[float, float]) -> np.ndarray:
        """σ of each cell of a grid from its own slope and curvature (NaN where not ``valid``)."""
        s, c = terrain_attributes(z_m, valid, spacing_m)
        return np.where(valid, self.sigma(s, c), np.float32(np.nan)).astype(np.float32)

    def correlation(self) -> list[tuple[float, float]]:
        """[(range m, fraction)] of the propagation."""
        if self.range_given_m is not None:
            return [(float(self.range_given_m), 1.0)]
        return [(float(r), float(q)) for r, q in zip(self.ranges_m, self.fractions, strict=True)]

    def volume_sigma_m3(
        self, area_m2: float, cell_area_m2: float, sum_sigma: float, sum_sigma2: float
    ) -> float:
        """1-σ error of a volume over ``area_m2`` whose cells' σ sum to ``sum_sigma`` (σ² to ``sum_sigma2``)."""
        return volume_sigma_m3(area_m2, cell_area_m2, sum_sigma, sum_sigma2, self.correlation())

    def as_dict(self) -> dict:
        return {
            "kind": "sigma by slope and curvature x sum of spherical ranges (xdem 0.2, Hugonnet et al. 2022)",
            "stable_cells": self.stable_cells,
            "slope_centres_deg": [round(float(v), 3) for v in self.slope_centres_deg],
            "curvature_centres_per_100m": [round(float(v), 4) for v in self.curv_centres],
            "sigma_table_m": [[round(float(v), 4) for v in row] for row in self.table_m],
            "sigma_given_m": self.sigma_given_m,
            "ranges_m": [float(r) for r in self.ranges_m],
            "range_fractions": [float(q) for q in self.fractions],
            "range_given_m": self.range_given_m,
            "propagation": "sigma_V^2 = a^2 sum_k q_k max(sum sigma_i^2, (sum sigma_i)^2 g(L_k, A)), g the "
            "spherical disc integral of xdem's neff_circular_approx_theoretical",
            "variogram_empirical": [{"lag_m": h, "gamma": g, "pairs": n} for h, g, n in self.variogram],
        }


def volume_sigma_m3(
    area_m2: float,
    cell_area_m2: float,
    sum_sigma: float,
    sum_sigma2: float,
    ranges: list[tuple[float, float]],
) -> float:
    """σ_V of the module docstring, metres³."""
    if area_m2 <= 0:
        return 0.0
    r_disc = math.sqrt(area_m2 / math.pi)
    var = 0.0
    for rng, q in ranges:
        if rng <= 0:
            g = 0.0
        elif r_disc <= rng:
            x = r_disc / rng
            g = 1.0 - x + x**3 / 5.0
        else:
            g = (rng / r_disc) ** 2 / 5.0
        var += q * max(sum_sigma2, sum_sigma**2 * g)
    return float(cell_area_m2 * math.sqrt(max(var, 0.0)))


def _interp2(xs: np.ndarray, ys: np.ndarray, table: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear interpolation of ``table`` on the centres (xs, ys), the nearest edge beyond (xdem's
    ``interp_nd_binning``), vectorised."""
    x = np.clip(np.asarray(x, np.float64), xs[0], xs[-1])
    y = np.clip(np.asarray(y, np.float64), ys[0], ys[-1])

    def locate(c: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if c.size == 1:
            return np.zeros(v.shape, np.intp), np.zeros(v.shape)
        i = np.clip(np.searchsorted(c, v, side="right") - 1, 0, c.size - 2)
        return i, (v - c[i]) / (c[i + 1] - c[i])

    i, fx = locate(xs, x)
    j, fy = locate(ys, y)
    t = np.asarray(table, np.float64)
    i1 = np.minimum(i + 1, xs.size - 1)
    j1 = np.minimum(j + 1, ys.size - 1)
    out = (t[i, j] * (1 - fx) * (1 - fy) + t[i1, j] * fx * (1 - fy) + t[i, j1] * (1 - fx) * fy
           + t[i1, j1] * fx * fy)  # fmt: skip
    return out.astype(np.float32)


def _edges(v: np.ndarray, quantiles: np.ndarray, min_cells: int) -> np.ndarray:
    """Bin edges at quantiles of ``v``, merged until each bin holds ``min_cells``."""
    e = np.unique(np.quantile(v, quantiles))
    while e.size > 2:
        counts = np.histogram(v, e)[0]
        k = int(np.argmin(counts))
        if counts[k] >= min_cells:
            break
        e = np.delete(e, k + 1 if k + 1 < e.size - 1 else k)
    e[0], e[-1] = min(e[0], float(v.min())), max(e[-1], float(v.max())) + 1e-9
    return e


def empirical_variogram(z: np.ndarray, spacing_m: tuple[float, float]) -> list[tuple[float, float, int]]:
    """[(lag m, semivariance, pairs)] of ``z`` (NaN = no value) along rows and columns, lags 1 to
    :data:`MAX_LAG_CELLS` cells on a geometric ladder."""
    h, w = z.shape
    step = float(np.mean(spacing_m))
    top = max(1, min(MAX_LAG_CELLS, h // 3, w // 3))
    out = []
    for k in sorted({int(v) for v in np.round(np.geomspace(1, top, 16))}):
        v = np.concatenate([(z[:, k:] - z[:, :-k]).ravel(), (z[k:, :] - z[:-k, :]).ravel()])
        v = v[np.isfinite(v)]
        if v.size >= 50:
            out.append((k * step, 0.5 * float(np.mean(v**2)), int(v.size)))
    return out


def stable_by_slope(dod: np.ndarray, base: np.ndarray, slope_deg: np.ndarray, outlier_nmad: float = 3.0,
                    buffer_cells: int = 2) -> np.ndarray:  # fmt: skip
    """Stable cells of ``base`` for the model: the change left out as cells beyond ``outlier_nmad`` NMAD of
    their own slope class's median (8 classes at slope quantiles; re-estimated until it settles), grown by
    ``buffer_cells``. One threshold for all the ground (:func:`terralod.change.coregister.stable_ground`)
    would take a noisy steep side for change and leave the model only its quiet cells."""
    from scipy import ndimage

    from terralod.change.coregister import NMAD_FLOOR_M, median_nmad

    ok = base & np.isfinite(dod)
    if ok.sum() < MIN_MODEL_CELLS:
        return ok
    edges = np.unique(np.quantile(slope_deg[ok], np.linspace(0, 1, 9)))
    cls = np.clip(np.searchsorted(edges, slope_deg, side="right") - 1, 0, max(edges.size - 2, 0))
    stable = ok.copy()
    for _ in range(5):
        med = np.zeros(edges.size, np.float64)
        thr = np.full(edges.size, np.inf)
        for k in range(max(edges.size - 1, 1)):
            v = dod[stable & (cls == k)]
            if v.size >= MIN_BIN_CELLS:
                med[k], s_k = median_nmad(v)
                thr[k] = outlier_nmad * max(s_k, NMAD_FLOOR_M)
        change = ok & (np.abs(dod - med[cls]) > thr[cls])
        if buffer_cells:
            change = ndimage.binary_dilation(change, iterations=buffer_cells)
        new = ok & ~change
        if np.array_equal(new, stable):
            break
        stable = new
    return stable


def binned_nmad_2d(
    values: np.ndarray, x: np.ndarray, y: np.ndarray, x_edges: np.ndarray, y_edges: np.ndarray,
    names: list[str],
) -> Any:  # fmt: skip
    """The 2-D rows of :func:`xdem.spatialstats.nd_binning` (``statistics=[nmad]``, bins given as edges)
    for finite ``values`` at (``x``, ``y``): the same table, row order and numbers, bit for bit, without
    the 1-D rows :func:`xdem.spatialstats.interp_nd_binning` does not read and without scipy's
    per-value Python loop of a callable statistic (``binned_statistic``): the bins are scipy's
    (``binned_statistic_2d``'s counting, its rule for the last edge included), each bin's NMAD the median
    of its absolute deviations from its median, found on the values sorted by bin (a median does not
    depend on the order of the values)."""
    import pandas as pd
    from scipy.stats import binned_statistic_2d

    from terralod.change.coregister import NMAD_FACTOR  # xdem's 1.4826

    v = np.asarray(values, np.float64).ravel()
    count, ex, ey, bins = binned_statistic_2d(x, y, v, statistic="count", bins=[x_edges, y_edges],
                                              expand_binnumbers=True)  # fmt: skip
    nx, ny = ex.size - 1, ey.size - 1
    bx, by = bins[0] - 1, bins[1] - 1  # scipy's numbers count the outlier bins below the first edge
    inside = (bx >= 0) & (bx < nx) & (by >= 0) & (by < ny)
    flat = (bx * ny + by)[inside]
    nmad_bins = np.full(nx * ny, np.nan)
    if flat.size:
        vi = v[inside]
        order = np.lexsort((vi, flat))
        key, vs = flat[order], vi[order]
        med = _group_medians(key, vs, nx * ny)
        dev = np.abs(vi - med[flat])
        order = np.lexsort((dev, flat))
        nmad_bins = NMAD_FACTOR * _group_medians(flat[order], dev[order], nx * ny)
    ix = pd.IntervalIndex.from_breaks(ex, closed="left")
    iy = pd.IntervalIndex.from_breaks(ey, closed="left")
    df = pd.DataFrame()
    df["count"] = count.flatten()
    df["nmad"] = nmad_bins
    df[names[0]] = [i1 for i1 in ix for _ in iy]
    df[names[1]] = [i2 for _ in ix for i2 in iy]
    df.insert(0, "nd", 2)
    return df


def _group_medians(key: np.ndarray, v: np.ndarray, n_groups: int) -> np.ndarray:
    """``np.median`` of each group of ``v`` (sorted by ``key``, then by value), NaN for an empty group."""
    out = np.full(n_groups, np.nan)
    starts = np.searchsorted(key, np.arange(n_groups), side="left")
    ends = np.searchsorted(key, np.arange(n_groups), side="right")
    n = ends - starts
    has = n > 0
    lo = starts + (n - 1) // 2
    hi = starts + n // 2
    odd = has & (n % 2 == 1)
    even = has & (n % 2 == 0)
    out[odd] = v[lo[odd]]
    out[even] = np.mean(np.stack([v[lo[even]], v[hi[even]]]), axis=0)
    return out


def fit_error_model(
    dod: np.ndarray, stable: np.ndarray, z_before_m: np.ndarray, valid_before: np.ndarray,
    spacing_m: tuple[float, float], candidates: np.ndarray | None = None,
) -> ErrorModel | str:  # fmt: skip
    """The model of the module docstring fitted on ``stable`` cells of ``dod``, or why it cannot be; given
    ``candidates`` (the ground that may be stable, before the change was taken out), the stable cells are
    those of :func:`stable_by_slope` instead."""
    import pandas as pd
    import xdem

    slope, curv = terrain_attributes(z_before_m, valid_before, spacing_m)
    ok = stable & np.isfinite(dod)
    if candidates is not None:
        ok = stable_by_slope(dod, candidates, slope) | ok
    n = int(ok.sum())
    if n < MIN_MODEL_CELLS:
        return f"only {n:,} cells of unchanged ground, fewer than the {MIN_MODEL_CELLS:,} needed"
    s_ok, c_ok = slope[ok], curv[ok]
    s_edges = _edges(s_ok, np.linspace(0, 1, 9), 4 * MIN_BIN_CELLS)
    c_edges = _edges(c_ok, np.array([0, 0.5, 0.8, 0.95, 1.0]), 2 * MIN_BIN_CELLS)
    if s_edges.size < 3 and c_edges.size < 3:
        return "too little unchanged ground to tell how the error changes with slope"
    ss_ = xdem.spatialstats
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            # infer_heteroscedasticity_from_stable's own steps (xdem 0.2.3 asks arrays for a ground sampling
            # distance it does not use): N-D binning of the NMAD (its 2-D rows, bit for bit: binned_nmad_2d),
            # its interpolant, the two-step standardisation
            names = ["slope", "maxc"]
            df = binned_nmad_2d(dod[ok], s_ok, c_ok, s_edges, c_edges, names)
            raw = ss_.interp_nd_binning(df, list_var_names=names, statistic="nmad", min_count=MIN_BIN_CELLS)
            fun = ss_.two_step_standardization(dod[ok], [s_ok, c_ok], raw)[1]
        except (ValueError, IndexError) as e:
            return f"the error could not be binned by slope ({e})"
        sc, cc = 0.5 * (s_edges[1:] + s_edges[:-1]), 0.5 * (c_edges[1:] + c_edges[:-1])
        ss, cm = np.meshgrid(sc, cc, indexing="ij")
        table = np.asarray(fun((ss.ravel(), cm.ravel())), np.float64).reshape(ss.shape)
    if not (np.isfinite(table).all() and (table > 0).all()):
        return "the error by slope could not be fitted (empty or zero bins)"
    model = ErrorModel(sc, cc, table, (), (), n)
    sig = model.sigma(slope, curv)
    zs = np.where(ok, dod / np.maximum(sig, 1e-12), np.nan)
    emp = empirical_variogram(zs, spacing_m)
    if len(emp) < 2 * N_RANGES + 1:
        return "too few pairs of unchanged cells at each distance to fit how far errors stay alike"
    lags = np.array([e[0] for e in emp])
    gam = np.array([e[1] for e in emp])
    cnt = np.array([e[2] for e in emp], np.float64)
    df = pd.DataFrame({"lags": lags, "exp": gam, "count": cnt, "err_exp": gam / np.sqrt(cnt) + 1e-6})
    step = float(np.mean(spacing_m))
    top = float(np.max(gam)) * 1.5
    bounds = [(0.1 * step, lags[-1]), (0.0, top)] + [(step, 4 * lags[-1]), (0.0, top)] * (N_RANGES - 1)
    p0 = [step, 0.5 * gam[0]] + [lags[len(lags) // 2], 0.5 * top] * (N_RANGES - 1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            cof = fit_sum_spherical(df, bounds=bounds, p0=p0, maxfev=10000)
        except (RuntimeError, ValueError) as e:
            return f"how far errors stay alike could not be fitted ({e})"
    rng = [float(v) for v in cof[0::2]]
    ps = np.clip(np.asarray(cof[1::2], np.float64), 0, None)
    total = max(float(ps.sum()), float(np.mean(gam[-3:])), 1e-12)
    q = ps / total
    nugget = max(0.0, 1.0 - float(q.sum()))
    # what the model cannot place on any range is uncorrelated: a range of 0 (nugget)
    model.ranges_m = (0.0, *rng)
    model.fractions = (nugget, *(float(v) for v in q))
    model.variogram = [(float(h), float(g), int(c)) for h, g, c in emp]
    model.contrast = _contrast(dod[ok], s_ok)
    return model


def fit_sum_spherical(
    empirical: Any, *, bounds: list[tuple[float, float]], p0: list[float], maxfev: int
) -> np.ndarray:
    """xdem's ``fit_sum_model_variogram(["Sph"] * K, empirical, bounds=..., p0=..., maxfev=...)``, its steps
    (finite values kept, a weighted trust-region fit by ``scipy.optimize.curve_fit`` where the errors are
    given) with the models' sum evaluated by :func:`terralod.kernels.variogram.spherical_sum`: the same
    numbers bit for bit (tests/test_change_uncertainty.py), one kernel call per evaluation instead of one
    Python call per lag and model. Returns (r_0, psill_0, r_1, psill_1, ...)."""
    from scipy.optimize import curve_fit

    from terralod.kernels.variogram import spherical_sum

    def model(h: np.ndarray, *args: float) -> np.ndarray:
        return spherical_sum(np.ascontiguousarray(h, np.float64), np.array(args, np.float64))

    emp = empirical[np.isfinite(empirical.exp.values)]
    final_bounds = np.transpose(np.array(bounds))
    err = emp.err_exp.values
    if np.all(np.isnan(err)) or np.all(err == 0):
        cof, _ = curve_fit(model, emp.lags.values, emp.exp.values, method="trf", p0=p0, bounds=final_bounds,
                           maxfev=maxfev)  # fmt: skip
    else:
        ok = np.isfinite(err)
        cof, _ = curve_fit(model, emp.lags.values[ok], emp.exp.values[ok], method="trf", p0=p0,
                           bounds=final_bounds, sigma=err[ok], maxfev=maxfev)  # fmt: skip
    return np.asarray(cof, np.float64)


def _contrast(d: np.ndarray, slope: np.ndarray) -> tuple[float, float, float] | None:
    """(threshold °, NMAD above it, NMAD on flat ground) on stable ground: the steepest round threshold
    with at least :data:`MIN_BIN_CELLS` cells above, flat = below 5° (or the flattest quarter)."""
    from terralod.change.coregister import nmad

    flat = slope < 5.0
    if flat.sum() < MIN_BIN_CELLS:
        flat = slope <= np.quantile(slope, 0.25)
    for thr in (45.0, 40.0, 35.0, 30.0, 25.0, 20.0, 15.0, 10.0):
        steep = slope > thr
        if steep.sum() >= MIN_BIN_CELLS and (flat & ~steep).sum() >= MIN_BIN_CELLS:
            return thr, nmad(d[steep]), nmad(d[flat & ~steep])
    return None


def where_error_is_larger(model: ErrorModel, t: float) -> str | None:
    """One plain sentence: where the surveys disagree more (± at the confidence's t)."""
    if model.contrast is None or model.sigma_given_m is not None:
        return None
    thr, steep, flat = model.contrast
    if not (flat > 0 and steep > 0):
        return None
    ratio = steep / flat
    if ratio < 1.3:
        return (f"The survey error is about the same on flat and steep ground (±{t * flat:.1f} m on flat "
                f"ground, ±{t * steep:.1f} m on slopes over {thr:.0f}°).")  # fmt: skip
    times = {2: "twice", 3: "three times", 4: "four times", 5: "five times"}.get(round(ratio))
    more = f"{times} as much" if times and abs(ratio - round(ratio)) < 0.25 else f"{ratio:.1f} times as much"
    return (
        f"The survey error is larger where the ground is steep: on slopes over {thr:.0f}° the two surveys "
        f"disagree by ±{t * steep:.1f} m, {more} as on flat ground (±{t * flat:.1f} m), so a change "
        "there must be larger to count."
    )
