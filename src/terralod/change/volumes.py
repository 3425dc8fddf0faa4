"""Volumes of change with their uncertainty, areas beyond the level of detection, extremes, zone budgets
and a series' volume against time; :func:`measure_change` runs the whole chain on two heightfields.

Uncertainty (what a geoscientist signs)
---------------------------------------
- σ, the vertical uncertainty of one DoD cell: the NMAD of the co-registered DoD on stable ground
  (:class:`terralod.change.coregister.StableGroundFinder`: valid in both, outside the change, off water
  surfaces and ``--exclude``), or the given ``sigma_m`` (``--sigma-m``). The given value wins when there is
  one. σ is refused — a stated default (:data:`ASSUMED_SIGMA_M`) is used, with a warning and a plain
  statement — when the stable ground cannot give it: fewer than 100 cells, a difference exactly 0 or
  constant (copied, not surveyed twice), or a difference no larger than the resampling's own error (or
  explained by it cell by cell): a copy of one survey, resampled. Cells whose difference is exactly 0
  among others that are not (a copied patch) are left out of σ, said so. ``sigma_source`` says which.
- Level of detection: LoD = t·σ with t the two-sided normal quantile of the confidence (1.96 at 95 %),
  the minimum level of detection of GCD (Wheaton et al. 2010, ESPL 35).
- Volume uncertainty, spatially correlated errors (Rolstad, Haug and Denby 2009, J. Glaciol. 55(192),
  eq. 8 and the nugget term of Hugonnet et al. 2022): the DoD error is modelled as a nugget ``c0`` plus
  a spherical variogram of sill ``c1`` and range ``L`` (``c0 + c1 = σ²``), fitted to the empirical
  semivariogram of the stable DoD along rows and columns (:func:`correlation_model`). The standard error of
  the mean over an area A is

      σ_mean² = c0 · a / A + c1 · min(1, π L² / (5 A)),     a = one cell's area,

  and of the volume σ_V = A · σ_mean. Without a fitted variogram ``L`` is the given ``corr_range_m`` or
  :data:`ASSUMED_RANGE_M`, all of σ² in the spherical part, said so in a plain statement. Each volume takes
  the area it sums over: every valid cell for ``net_m3``, the gain (loss) cells for ``gain_m3``
  (``loss_m3``), the cells beyond the LoD for the ``_above_lod`` figures. Two more terms, in quadrature:

  - the fitted vertical bias's own uncertainty, a fully correlated error of every cell: 1.2533 · σ_mean over
    the stable area (the standard error of a median), doubled when only the bias could be fitted (the
    horizontal alignment could not be checked); A · σ_bias per volume;
  - the resampling's own error when AFTER was resampled or reprojected onto BEFORE's grid
    (:func:`resampling_error`: BEFORE taken through AFTER's grid and back by the same path, halved), summed
    over the volume's cells: interpolation smooths peaks and pits, an error that does not average out.

  The ± figures are t · sqrt(σ_V² + (A σ_bias)² + (Σ e · a)²).

- The error that holds where the change is (issue 54, :mod:`terralod.change.uncertainty`): when the stable
  ground allows it (at least :data:`terralod.change.uncertainty.MIN_MODEL_CELLS` cells), σ of each cell is
  a function of BEFORE's slope and curvature and the correlation a sum of spherical ranges, both fitted on
  the stable ground (the bounded sample of a region); σ_V above is then that module's propagation of a
  sum with per-cell σ, the level of detection of each cell t · σ(cell), and ``sigma.tif`` holds σ(cell).
  ``sigma_m`` / ``level_of_detection_m`` stay the NMAD of all the stable ground and its t · σ.
  ``--sigma-m`` overrides σ(slope, curvature) with one value, ``--corr-range-m`` the fitted ranges with
  one range; given both, or when the stable ground is too small to fit the model (said so in a
  statement), the single-σ model above is used.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from terralod.change.coregister import (
    SLOPE_MIN_DEG,
    Coregistration,
    StableGround,
    StableGroundFinder,
    coregister,
    nmad,
)
from terralod.change.difference import (
    AlignedPair,
    align,
    crs_label,
    dem_of_difference,
    reproject_onto,
    sample_surface,
)
from terralod.change.uncertainty import (
    ErrorModel,
    fit_error_model,
    stable_by_slope,
    terrain_attributes,
    where_error_is_larger,
)
from terralod.change.zones import read_zones
from terralod.heightfield import Heightfield

log = logging.getLogger(__name__)

#: σ used (with a warning) when neither stable ground nor ``sigma_m`` gives one, metres.
ASSUMED_SIGMA_M = 1.0
#: Correlation range used when the stable ground cannot be fitted and none is given, metres.
ASSUMED_RANGE_M = 500.0
#: Fewest stable cells σ is estimated from.
MIN_STABLE_CELLS = 100
#: Volume keys of every budget (summary and zones).
VOLUME_KEYS = (
    "gain_m3", "loss_m3", "net_m3", "gain_m3_above_lod", "loss_m3_above_lod", "net_m3_above_lod",
    "net_uncertainty_m3", "gain_uncertainty_m3", "loss_uncertainty_m3", "net_above_lod_uncertainty_m3",
    "gain_above_lod_uncertainty_m3", "loss_above_lod_uncertainty_m3", "area_gain_m2", "area_loss_m2",
    "area_m2", "max_rise_m", "max_drop_m",
)  # fmt: skip


@dataclass
class Uncertainty:
    """The error model of one DoD."""

    sigma_m: float
    sigma_source: str
    confidence: float
    t: float
    nugget_m2: float
    sill_m2: float
    range_m: float
    range_source: str
    stable_cells: int
    stable_nmad_m: float | None
    cell_area_m2: float
    warnings: list[str] = field(default_factory=list)
    #: 1-σ uncertainty of the fitted vertical bias (a fully correlated error of every cell), metres
    bias_sigma_m: float = 0.0
    #: the resampling's own error on BEFORE's grid (one interpolation, simulated), metres; None: no resampling
    resampling_error_m: np.ndarray | None = None
    #: plain statements on what the data could not support
    statements: list[str] = field(default_factory=list)
    #: σ(slope, curvature) x multi-range correlation (:mod:`terralod.change.uncertainty`); None: single σ
    model: ErrorModel | None = None
    #: why the model was not fitted (None: fitted, or not asked for)
    model_note: str | None = None
    #: (cells, Σσ, Σσ²) of the stable ground under the model
    stable_sums: tuple[int, float, float] | None = None

    @property
    def resampling_nmad_m(self) -> float | None:
        if self.resampling_error_m is None:
            return None
        return nmad(self.resampling_error_m)

    @property
    def level_of_detection_m(self) -> float:
        return self.t * self.sigma_m

    def volume_sigma_m3(
        self, area_m2: float, sum_sigma: float | None = None, sum_sigma2: float | None = None
    ) -> float:
        """1-σ uncertainty of a volume summed over ``area_m2`` (Rolstad et al. 2009 + nugget); under the
        model, of cells whose σ sum to ``sum_sigma`` (σ² to ``sum_sigma2``; constant σ when not given)."""
        if area_m2 <= 0:
            return 0.0
        if self.model is not None:
            n = area_m2 / self.cell_area_m2
            s1 = n * self.sigma_m if sum_sigma is None else sum_sigma
            s2 = n * self.sigma_m**2 if sum_sigma2 is None else sum_sigma2
            return self.model.volume_sigma_m3(area_m2, self.cell_area_m2, s1, s2)
        corr = min(1.0, math.pi * self.range_m**2 / (5.0 * area_m2)) if self.range_m > 0 else 0.0
        var_mean = self.nugget_m2 * min(1.0, self.cell_area_m2 / area_m2) + self.sill_m2 * corr
        return float(area_m2 * math.sqrt(max(var_mean, 0.0)))

    def volume_uncertainty_m3(self, area_m2: float) -> float:
        """± at the confidence level (t · σ_V)."""
        return self.t * self.volume_sigma_m3(area_m2)

    def sigma_grid(self, z_m: np.ndarray, valid: np.ndarray, spacing_m: tuple[float, float]) -> np.ndarray:
        """σ of each cell of a grid (float32, NaN where not ``valid``): the model's, or the one σ."""
        if self.model is not None:
            return self.model.sigma_of_grid(z_m, valid, spacing_m)
        return np.where(valid, np.float32(self.sigma_m), np.float32(np.nan)).astype(np.float32)

    def as_dict(self) -> dict:
        model = self.model.as_dict() if self.model is not None else None
        return {
            "model": model,
            "model_note": self.model_note,
            "sigma_m": self.sigma_m,
            "sigma_source": self.sigma_source,
            "confidence": self.confidence,
            "t": self.t,
            "level_of_detection_m": self.level_of_detection_m,
            "stable_cells": self.stable_cells,
            "stable_nmad_m": self.stable_nmad_m,
            "variogram": {
                "nugget_m2": self.nugget_m2,
                "spherical_sill_m2": self.sill_m2,
                "range_m": self.range_m,
                "range_source": self.range_source,
            },
            "propagation": (
                model["propagation"]
                if model
                else "Rolstad et al. 2009 spherical-correlation "
                "area average plus nugget; sigma_V = A * sqrt(c0 * a / A + c1 * min(1, pi L^2 / (5 A)))"
            )
            + "; +- = t * sqrt(sigma_V^2 + (A * sigma_bias)^2 + (sum of the resampling error * a)^2)",
            "bias_sigma_m": self.bias_sigma_m,
            "resampling_nmad_m": self.resampling_nmad_m,
            "statements": list(self.statements),
            "warnings": list(self.warnings),
        }


def z_quantile(confidence: float) -> float:
    """Two-sided normal quantile: 1.96 for 0.95."""
    from statistics import NormalDist

    if not 0.0 < confidence < 1.0:
        raise ValueError(f"Expected a confidence in (0, 1), got {confidence}")
    return float(NormalDist().inv_cdf(0.5 + confidence / 2.0))


def correlation_model(
    dod: np.ndarray, stable: np.ndarray, spacing_m: tuple[float, float], max_lag_cells: int = 64
) -> tuple[float, float, float] | None:
    """(nugget m², spherical sill m², range m) fitted to the empirical semivariogram of ``dod`` on
    ``stable`` cells, lags along rows and columns; None when there are too few pairs."""
    from scipy.optimize import curve_fit

    d = np.where(stable & np.isfinite(dod), dod, np.nan)
    h, w = d.shape
    step = float(np.mean(spacing_m))
    lags = sorted(
        {int(v) for v in np.unique(np.round(np.geomspace(1, max(1, min(max_lag_cells, h // 3, w // 3)), 14)))}
    )
    hs, gs = [], []
    for k in lags:
        parts = [(d[:, k:] - d[:, :-k]).ravel(), (d[k:, :] - d[:-k, :]).ravel()]
        v = np.concatenate(parts)
        v = v[np.isfinite(v)]
        if v.size < 50:
            continue
        hs.append(k * step)
        gs.append(0.5 * float(np.mean(v**2)))
    if len(hs) < 4:
        return None
    hs_a, gs_a = np.asarray(hs), np.asarray(gs)
    var = float(np.nanvar(d))

    def spherical(x, c0, c1, a):
        r = np.clip(x / a, 0, 1)
        return c0 + c1 * (1.5 * r - 0.5 * r**3)

    try:
        (c0, c1, a), _ = curve_fit(
            spherical, hs_a, gs_a, p0=(0.1 * var, 0.9 * var, hs_a[len(hs_a) // 2]),
            bounds=([0, 0, step], [np.inf, np.inf, 100.0 * hs_a[-1]]), maxfev=5000,
        )  # fmt: skip
    except (RuntimeError, ValueError):
        return None
    return float(c0), float(c1), float(a)


def estimate_uncertainty(
    dod: np.ndarray,
    stable: np.ndarray,
    cell_area_m2: float,
    spacing_m: tuple[float, float],
    *,
    sigma_m: float | None = None,
    corr_range_m: float | None = None,
    confidence: float = 0.95,
    resampling_error_m: np.ndarray | None = None,
    z_before_m: np.ndarray | None = None,
    valid_before: np.ndarray | None = None,
    candidates: np.ndarray | None = None,
) -> Uncertainty:
    """σ, LoD and the correlation model of a co-registered DoD (module docstring); given BEFORE's
    elevations (``z_before_m``, ``valid_before``) on the DoD's grid, σ by slope and curvature with a
    multi-range correlation (:mod:`terralod.change.uncertainty`) unless both ``sigma_m`` and
    ``corr_range_m`` are given; ``candidates`` (the finder's ground before the change was taken out) lets
    the model take the change out slope class by slope class
    (:func:`terralod.change.uncertainty.stable_by_slope`).

    σ is refused (a stated default is used, with a warning) when the stable ground cannot give it: too
    few cells, a difference exactly 0 (copied, not surveyed twice), or a difference no larger than the
    resampling's own error (``resampling_error_m``, simulated): stable ground that only differs by the
    interpolation of a copy. Cells whose difference is exactly 0 while others are not (a copied patch)
    are left out of σ, said so.
    """
    t = z_quantile(confidence)
    ok = stable & np.isfinite(dod)
    n = int(ok.sum())
    warns: list[str] = []
    statements: list[str] = []
    zero = ok & (dod == 0.0)
    n_zero = int(zero.sum())
    if n and 0 < n_zero < n and n_zero >= 0.05 * n:
        statements.append(
            f"{100 * n_zero / n:.0f} % of the stable ground is identical in both files (copied from one "
            "survey into the other); the survey error was measured on the rest"
        )
        ok = ok & ~zero
        n = int(ok.sum())
    s_nmad = nmad(dod[ok]) if n else float("nan")
    r_nmad, r_corr = 0.0, 0.0
    if resampling_error_m is not None and n:
        # the resampling's own error over every valid cell, and how much of the stable difference it
        # explains cell by cell: a copy of the same survey, resampled, differs by just that
        r_nmad = nmad(resampling_error_m[np.isfinite(dod)])
        both = ok & np.isfinite(resampling_error_m)
        if both.sum() >= MIN_STABLE_CELLS and np.std(resampling_error_m[both]) > 0 and np.std(dod[both]) > 0:
            r_corr = float(np.corrcoef(dod[both], resampling_error_m[both])[0, 1])
    why = None
    if n < MIN_STABLE_CELLS:
        why = f"only {n} stable cells"
    elif not s_nmad > 0:
        why = (
            f"the difference on its {n:,} stable cells is exactly 0 (copied, not surveyed twice)"
            if bool(np.all(dod[ok] == 0))
            else f"the difference on its {n:,} stable cells is constant (NMAD 0)"
        )
    elif s_nmad <= max(r_nmad, 1e-3) or r_corr >= 0.7:
        why = (
            f"the difference on its {n:,} stable cells ({s_nmad:.3f} m) is no more than the resampling's "
            f"own error ({r_nmad:.3f} m, correlation {r_corr:.2f}): that ground looks copied from one survey "
            "into the other"
        )
    if sigma_m is not None:
        if not (math.isfinite(sigma_m) and sigma_m >= 0):
            raise ValueError(f"Expected sigma_m >= 0, got {sigma_m}")
        sigma, source = float(sigma_m), "given (--sigma-m)"
    elif why is None:
        sigma, source = s_nmad, f"NMAD of the difference on {n:,} stable cells"
    else:
        sigma, source = ASSUMED_SIGMA_M, f"assumed {ASSUMED_SIGMA_M:g} m: {why}; give --sigma-m"
        warns.append(f"sigma cannot be measured ({why}); assumed {ASSUMED_SIGMA_M:g} m, give --sigma-m")
        statements.append(
            f"The survey error could not be measured from these files ({why}); {ASSUMED_SIGMA_M:g} m was assumed."
        )
    model = correlation_model(dod, ok, spacing_m) if why is None else None
    if corr_range_m is not None:
        rng, rsrc = float(corr_range_m), "given (--corr-range-m)"
        c0, c1 = 0.0, sigma**2
    elif model is not None:
        c0m, c1m, rng = model
        frac = c0m / max(c0m + c1m, 1e-30)
        c0, c1 = frac * sigma**2, (1 - frac) * sigma**2
        rsrc = f"spherical variogram fitted on {n:,} stable cells"
    else:
        reason = why or "too few pairs of stable cells at each distance to fit a variogram"
        rng, rsrc = ASSUMED_RANGE_M, f"assumed {ASSUMED_RANGE_M:g} m ({reason})"
        c0, c1 = 0.0, sigma**2
        statements.append(
            f"How far survey errors stay alike could not be measured ({reason}); {ASSUMED_RANGE_M:g} m "
            "was assumed."
        )
    unc = Uncertainty(
        sigma_m=sigma, sigma_source=source, confidence=confidence, t=t, nugget_m2=c0, sill_m2=c1, range_m=rng,
        range_source=rsrc, stable_cells=n, stable_nmad_m=None if not math.isfinite(s_nmad) else s_nmad,
        cell_area_m2=cell_area_m2, warnings=warns, resampling_error_m=resampling_error_m,
        statements=statements,
    )  # fmt: skip
    if z_before_m is not None and valid_before is not None and why is None:
        if sigma_m is not None and corr_range_m is not None:
            return unc  # both given: the single-σ model, as asked
        cand = None if candidates is None else candidates & ~zero
        got = fit_error_model(dod, ok, z_before_m, valid_before, spacing_m, cand)
        if isinstance(got, str):
            unc.model_note = got
            statements.append(
                f"The survey error was taken as the same everywhere: {got} to tell how it changes with slope."
            )
            return unc
        got.sigma_given_m = None if sigma_m is None else float(sigma_m)
        got.range_given_m = None if corr_range_m is None else float(corr_range_m)
        unc.model = got
        ok = (
            ok
            if cand is None
            else (ok | stable_by_slope(dod, cand, terrain_attributes(z_before_m, valid_before, spacing_m)[0]))
        )
        sig = got.sigma_of_grid(z_before_m, valid_before, spacing_m)[ok]
        sig = sig[np.isfinite(sig)]
        unc.stable_sums = (int(sig.size), float(np.sum(sig, dtype=np.float64)),
                           float(np.sum(sig.astype(np.float64) ** 2)))  # fmt: skip
        if corr_range_m is None:
            q = dict(zip(got.ranges_m, got.fractions, strict=True))
            unc.range_m = float(max(got.ranges_m))
            unc.nugget_m2 = float(q.get(0.0, 0.0)) * sigma**2
            unc.sill_m2 = sigma**2 - unc.nugget_m2
            unc.range_source = (f"{len(got.ranges_m) - 1} spherical ranges fitted on {n:,} stable cells: "
                                + ", ".join(f"{r:,.0f} m ({100 * f:.0f} %)" for r, f in got.correlation() if r > 0))  # fmt: skip
            unc.statements[:] = [x for x in unc.statements if not x.startswith("How far survey errors")]
        words = where_error_is_larger(got, t)
        if words:
            statements.append(words)
    return unc


def resampling_error(pair: AlignedPair, after: Heightfield, shift_m=(0.0, 0.0, 0.0)) -> np.ndarray | None:
    """The error resampling AFTER onto BEFORE's grid adds by itself, on BEFORE's grid (metres; None when
    AFTER is on BEFORE's grid and not shifted). Simulated on BEFORE: its surface taken to AFTER's grid and
    back by the same path (a round trip: two interpolations, halved for one)."""
    before = pair.before
    tx, ty, _ = (float(v) for v in shift_m)
    if pair.after is not after:  # reprojected in align(): the round trip through AFTER's own grid and CRS
        there = reproject_onto(before, after)
        back = reproject_onto(there, before)
        e = np.where(back.valid & before.valid, back.elevation_m - before.elevation_m, np.nan)
        return (0.5 * e).astype(np.float64)
    if pair.same_grid and tx == 0.0 and ty == 0.0:
        return None
    rows, cols = np.indices(after.shape, dtype=np.float64)
    x, y = after.world_xy(rows, cols)
    r, c = before.sample_rc(x + tx, y + ty)
    z, ok = sample_surface(before, r, c, order=3)
    # on one grid the fill is the nearest valid cell's (local: a window with a margin fills as the whole grid
    # does, :mod:`terralod.change.windowed`); on another grid the median, as it always was
    fill = (
        _nearest_filled(z, ok)
        if pair.same_grid
        else np.where(ok, z, np.nanmedian(z[ok]) if ok.any() else 0.0)
    )
    sim = Heightfield(
        fill.astype(np.float32), ok & after.valid, after.transform, crs=after.crs, source="simulated"
    )
    d = dem_of_difference(AlignedPair(before, sim, pair.same_grid), (tx, ty, 0.0))
    return 0.5 * d


def _nearest_filled(z: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """``z`` with its invalid cells set to the nearest valid cell's value: the fill a cubic spline rings on
    least, and a local one (a window with a margin fills as the whole grid does)."""
    from scipy import ndimage

    if ok.all() or not ok.any():
        return np.where(ok, z, 0.0) if not ok.any() else z
    idx = ndimage.distance_transform_edt(~ok, return_distances=False, return_indices=True)
    return z[tuple(idx)]


def budget(
    dod: np.ndarray, unc: Uncertainty, mask: np.ndarray | None = None, sigma: np.ndarray | None = None
) -> dict:
    """Gain/loss/net volumes (all cells, and beyond the LoD) with ± uncertainty, areas beyond the LoD, the
    largest rise and drop, over the finite cells of ``dod`` (inside ``mask`` when given); ``sigma``: σ of
    each cell under the model (:meth:`Uncertainty.sigma_grid`)."""
    sums = BudgetSums(unc.level_of_detection_m, unc.t)
    sums.add(dod, unc.resampling_error_m, mask, sigma if unc.model is not None else None)
    return sums.budget(unc)


#: The cell sets a budget sums over: every valid cell, gain, loss, beyond the LoD up, down, either.
_SETS = ("all", "pos", "neg", "up", "down", "beyond")


class BudgetSums:
    """What :func:`budget` needs of a DoD, accumulated window by window: per cell set (:data:`_SETS`) the
    sum of the difference (float64), the cell count and the sum of the resampling error, and under the error
    model the sums of σ and σ² (each cell's LoD is then t · σ); the largest rise and drop. ``budget(unc)``
    gives :func:`budget`'s dict; the volumes equal a whole-grid sum up to the order of the float64 additions
    (1e-15 relative)."""

    def __init__(self, lod_m: float, t: float | None = None) -> None:
        self.lod_m = float(lod_m)
        self.t = t
        self.s1 = dict.fromkeys(_SETS, 0.0)
        self.s2 = dict.fromkeys(_SETS, 0.0)
        self.has_sigma = False
        self.vol = dict.fromkeys(_SETS, 0.0)
        self.count = dict.fromkeys(_SETS, 0)
        self.err = dict.fromkeys(_SETS, 0.0)
        self.has_err = False
        self.d_max = -math.inf
        self.d_min = math.inf

    def add(
        self, dod: np.ndarray, err: np.ndarray | None = None, mask: np.ndarray | None = None,
        sigma: np.ndarray | None = None,
    ) -> None:  # fmt: skip
        """Add a window of the DoD (metres; NaN = no data), its resampling error (or None), a mask and σ of
        each cell under the error model (or None)."""
        ok = np.isfinite(dod) if mask is None else (np.isfinite(dod) & mask)
        d = dod[ok]
        if d.size == 0:
            return
        sg = None
        if sigma is not None:
            if self.t is None:
                raise ValueError("BudgetSums needs t for a per-cell sigma")
            sg = sigma[ok].astype(np.float64)
            self.has_sigma = True
        lod = self.lod_m if sg is None else self.t * sg
        pos, neg = d > 0, d < 0
        up, down = d > lod, d < -lod
        sel = {"all": None, "pos": pos, "neg": neg, "up": up, "down": down, "beyond": up | down}
        e = None if err is None else err[ok]
        self.has_err = self.has_err or e is not None
        for k, m in sel.items():
            v = d if m is None else d[m]
            self.vol[k] += float(np.sum(v, dtype=np.float64))
            self.count[k] += int(v.size)
            if e is not None:
                self.err[k] += float(np.nansum(e if m is None else e[m], dtype=np.float64))
            if sg is not None:
                g = sg if m is None else sg[m]
                self.s1[k] += float(np.sum(g))
                self.s2[k] += float(np.sum(g * g))
        self.d_max = max(self.d_max, float(d.max()))
        self.d_min = min(self.d_min, float(d.min()))

    def merge(self, other: BudgetSums) -> None:
        """Add another accumulator's sums (a window done elsewhere)."""
        for k in _SETS:
            self.vol[k] += other.vol[k]
            self.count[k] += other.count[k]
            self.err[k] += other.err[k]
            self.s1[k] += other.s1[k]
            self.s2[k] += other.s2[k]
        self.has_err = self.has_err or other.has_err
        self.has_sigma = self.has_sigma or other.has_sigma
        self.d_max, self.d_min = max(self.d_max, other.d_max), min(self.d_min, other.d_min)

    def budget(self, unc: Uncertainty) -> dict:
        a = unc.cell_area_m2
        vol = lambda k: self.vol[k] * a  # noqa: E731
        area = lambda k: float(self.count[k] * a)  # noqa: E731

        def pm(k: str) -> float:
            sums = (self.s1[k], self.s2[k]) if self.has_sigma else (None, None)
            u = unc.volume_sigma_m3(area(k), *sums) ** 2 + (area(k) * unc.bias_sigma_m) ** 2
            if self.has_err:
                u += (self.err[k] * a) ** 2
            return float(unc.t * math.sqrt(u)) if area(k) > 0 else 0.0

        n = self.count["all"]
        return {
            "gain_m3": vol("pos"),
            "loss_m3": -vol("neg"),
            "net_m3": vol("all"),
            "gain_m3_above_lod": vol("up"),
            "loss_m3_above_lod": -vol("down"),
            "net_m3_above_lod": vol("beyond"),
            "net_uncertainty_m3": pm("all"),
            "gain_uncertainty_m3": pm("pos"),
            "loss_uncertainty_m3": pm("neg"),
            "net_above_lod_uncertainty_m3": pm("beyond"),
            "gain_above_lod_uncertainty_m3": pm("up"),
            "loss_above_lod_uncertainty_m3": pm("down"),
            "area_gain_m2": area("up"),
            "area_loss_m2": area("down"),
            "area_m2": area("all"),
            "max_rise_m": max(0.0, self.d_max) if n else 0.0,
            "max_drop_m": max(0.0, -self.d_min) if n else 0.0,
        }


def extremes(dod: np.ndarray, hf: Heightfield) -> dict:
    """Position (x, y in the grid CRS, lon/lat, row/col) and value of the largest rise and drop."""
    out = {}
    for key, fn in (("max_rise", np.nanargmax), ("max_drop", np.nanargmin)):
        if not np.isfinite(dod).any():
            out[key] = None
            continue
        r, c = np.unravel_index(int(fn(dod)), dod.shape)
        x, y = hf.world_xy(r, c)
        item = {"value_m": float(dod[r, c]), "row": int(r), "col": int(c), "x_m": float(x), "y_m": float(y)}
        item.update(_lonlat(hf.crs, float(x), float(y)))
        out[key] = item
    return out


def _lonlat(crs: str | None, x: float, y: float) -> dict:
    if not crs:
        return {}
    try:
        from pyproj import Transformer

        lon, lat = Transformer.from_crs(crs, "EPSG:4326", always_xy=True).transform(x, y)
        return {"lon_deg": float(lon), "lat_deg": float(lat)}
    except Exception:  # noqa: BLE001 - positions in the grid CRS are given anyway
        return {}


@dataclass
class ChangeResult:
    """Everything a change summary and report are made of."""

    pair: AlignedPair
    coreg: Coregistration
    dod: np.ndarray
    stable: np.ndarray
    uncertainty: Uncertainty
    summary: dict
    zone_masks: list = field(default_factory=list)
    #: σ of each DoD cell (``sigma.tif``; the decimated copy on a region), metres
    sigma: np.ndarray | None = None


def measure_change(
    before: Heightfield,
    after: Heightfield,
    *,
    stable: np.ndarray | None = None,
    exclude: np.ndarray | None = None,
    coregistration: bool = True,
    method: str = "xdem",
    sigma_m: float | None = None,
    corr_range_m: float | None = None,
    confidence: float = 0.95,
    zones: str | Path | None = None,
    dates: tuple[str | None, str | None] = (None, None),
    pair: AlignedPair | None = None,
    slope_min_deg: float = SLOPE_MIN_DEG,
) -> ChangeResult:
    """Align, co-register (unless ``coregistration`` is False), difference and budget two DEMs.

    ``stable`` is a mask on BEFORE's grid (True = stable ground) or None ("outside the change");
    ``exclude`` a mask of cells never taken as stable (glaciers, lakes, the known change).
    The result's ``summary`` holds the contract keys of ``terralod change`` (see :mod:`terralod.cli.change`).
    """
    pair = pair or align(before, after)
    ground = StableGroundFinder(pair, given=stable, exclude=exclude, slope_min_deg=slope_min_deg)
    co = fit_alignment(pair, ground, coregistration=coregistration, method=method)
    shift = co.shift_m if co.applied else (0.0, 0.0, 0.0)
    dod = dem_of_difference(pair, shift)
    sg = ground(dod)
    st = sg.mask
    rerr = resampling_error(pair, after, shift)
    unc = estimate_uncertainty(
        dod, st, pair.cell_area_m2, before.spacing_m, sigma_m=sigma_m, corr_range_m=corr_range_m,
        confidence=confidence, resampling_error_m=rerr, z_before_m=before.elevation_m,
        valid_before=before.valid, candidates=sg.base,
    )  # fmt: skip
    settle_bias_sigma(co, unc, pair.cell_area_m2)
    sigma = np.where(
        np.isfinite(dod), unc.sigma_grid(before.elevation_m, before.valid, before.spacing_m), np.nan
    )
    zone_masks = read_zones(zones, before) if zones is not None else []
    zone_budgets = [(name, budget(dod, unc, mask, sigma), frac) for name, mask, frac, _geom in zone_masks]
    summary = change_summary(
        pair, co, sg, unc, budget(dod, unc, sigma=sigma), shift=shift, confidence=confidence, dates=dates,
        names=(before.source, after.source), valid_cells=int(np.isfinite(dod).sum()),
        resampled=not (pair.same_grid and pair.after is after), extremes_=extremes(dod, before),
        zone_budgets=zone_budgets,
    )  # fmt: skip
    return ChangeResult(pair, co, dod, st, unc, summary, zone_masks, sigma.astype(np.float32))


def fit_alignment(
    pair: AlignedPair, ground: StableGroundFinder, *, coregistration: bool, method: str
) -> Coregistration:
    """The co-registration of a pair (:func:`coregister`), or the note that it was skipped."""
    if coregistration:
        co = coregister(pair, method=method, ground=ground)
        co.applied = co.method != "none"
    else:
        co = Coregistration(method="none", notes=["co-registration skipped (--no-coregister)"])
        co.statement = "The surveys were compared as they are, without lining them up (--no-coregister)."
    return co


def settle_bias_sigma(co: Coregistration, unc: Uncertainty, cell_area_m2: float) -> None:
    """The fitted vertical bias is itself uncertain: the standard error of a median over the stable area
    (set on ``unc`` and ``co``)."""
    if co.applied and unc.stable_cells >= MIN_STABLE_CELLS:
        area_st = unc.stable_cells * cell_area_m2
        if unc.stable_sums is not None:
            n, s1, s2 = unc.stable_sums
            area_st = n * cell_area_m2
            unc.bias_sigma_m = 1.2533 * unc.volume_sigma_m3(area_st, s1, s2) / area_st
        else:
            unc.bias_sigma_m = 1.2533 * unc.volume_sigma_m3(area_st) / area_st
        if unc.sigma_source.startswith("assumed") and unc.stable_nmad_m is not None:
            # an assumed σ is no measure of how well the bias was fitted: the stable ground's own spread is
            unc.bias_sigma_m *= unc.stable_nmad_m / unc.sigma_m
        if co.mode == "bias only":
            unc.bias_sigma_m *= 2.0  # the horizontal alignment could not be checked: widened
        co.bias_sigma_m = unc.bias_sigma_m


def change_summary(
    pair: AlignedPair, co: Coregistration, sg: StableGround, unc: Uncertainty, totals: dict, *,
    shift: tuple[float, float, float], confidence: float, dates: tuple[str | None, str | None],
    names: tuple[str, str], valid_cells: int, resampled: bool, extremes_: dict,
    zone_budgets: list[tuple[str, dict, float]],
) -> dict:  # fmt: skip
    """The contract summary of ``terralod change`` (:mod:`terralod.cli.change`) from its parts; BEFORE's
    grid is ``pair.before``'s frame (a window source or a Heightfield)."""
    before = pair.before
    bias_only = co.mode == "bias only"
    dx, dy = before.spacing_m
    h, w = before.shape
    t = before.transform
    summary: dict = dict(totals)
    summary.update(
        {
            "sigma_m": unc.sigma_m,
            "sigma_source": unc.sigma_source,
            "level_of_detection_m": unc.level_of_detection_m,
            "confidence": confidence,
            "shift_m": [float(v) for v in shift],
            "before": {"source": Path(str(names[0])).name, "date": dates[0]},
            "after": {"source": Path(str(names[1])).name, "date": dates[1]},
            "grid": {
                "crs": crs_label(before.crs),
                "shape": [int(h), int(w)],
                "spacing_m": [float(dx), float(dy)],
                "bounds_m": [float(t.c), float(t.f + h * t.e), float(t.c + w * t.a), float(t.f)],
                "cell_area_m2": float(dx * dy),
                "valid_cells": int(valid_cells),
                "resampled": bool(resampled),
            },
            "alignment_notes": list(pair.notes),
            "coregistration": co.as_dict(),
            "stable_ground": sg.as_dict(bias_only),
            "fit_description": _fit_words(co, sg, bias_only),
            "uncertainty": unc.as_dict(),
            "extremes": extremes_,
        }
    )
    summary["zones"] = []
    for name, b, frac in zone_budgets:
        z = {"name": name, **b, "fraction_on_terrain": frac}
        if frac < 0.999:
            z["note"] = f"{100 * (1 - frac):.1f} % of the polygon lies outside the terrain and is not counted"
        summary["zones"].append(z)
    return summary


def _fit_words(co: Coregistration, sg: StableGround, bias_only: bool) -> str:
    """What the alignment used, in words a council member reads."""
    if co.mode == "identical":
        return co.statement
    if not co.applied:
        return co.statement
    if bias_only:
        return f"{co.statement} The height difference was {sg.describe(True)}."
    return f"The alignment was {sg.describe(False)}."


def series_volumes(
    epochs: list[Heightfield], dates: list[str], *, sigma_m: float | None = None,
    corr_range_m: float | None = None, confidence: float = 0.95, coregistration: bool = False,
    method: str = "xdem",
) -> list[dict]:  # fmt: skip
    """Volume against time: the budget of each epoch against the first (cumulative change), on the first
    epoch's grid. Returns one dict per epoch (the first has zero change) with ``date`` and the budget keys."""
    base = epochs[0]
    rows = []
    for hf, date in zip(epochs, dates, strict=True):
        if hf is base:
            rows.append(
                {**{k: 0.0 for k in VOLUME_KEYS}, "date": date, "sigma_m": sigma_m, "shift_m": [0.0] * 3}
            )
            continue
        r = measure_change(base, hf, coregistration=coregistration, method=method, sigma_m=sigma_m,
                           corr_range_m=corr_range_m, confidence=confidence)  # fmt: skip
        row = {k: r.summary[k] for k in VOLUME_KEYS}
        row.update({"date": date, "sigma_m": r.summary["sigma_m"], "sigma_source": r.summary["sigma_source"],
                    "shift_m": r.summary["shift_m"]})  # fmt: skip
        rows.append(row)
    return rows
