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
  When AFTER's cells are coarser, the fit runs on AFTER's own samples against BEFORE's spline instead
  (:func:`_fit_on_after_grid`, like with like).
  ``benchmarks/change.py`` measures both on known shifts of real DEMs (accuracy, time, memory).

"Stable ground" (:class:`StableGroundFinder`) is where the fit and σ may look: cells valid in both DEMs,
inside ``--stable`` when given, outside ``--exclude`` (glaciers, lakes, the known change), off *level
surfaces* (connected patches of BEFORE — or AFTER on the same grid — whose elevation is exactly constant:
the sea at 0 m, lakes, reservoirs; a water surface says nothing about survey error and can change level
between surveys) and outside the change (cells beyond 3 NMAD of the median difference, grown by 2 cells,
re-estimated after the fit). The horizontal fit uses only its cells on slopes of at least
``slope_min_deg`` (3° by default; flat cells carry no information on a horizontal shift, as in Nuth &
Kääb 2011 and xdem). When those cannot constrain a shift (fewer than :data:`MIN_FIT_CELLS`, or the
least-squares standard error of the shift above :data:`MAX_SHIFT_SE_CELLS` of a cell) only the vertical
bias is fitted, on all of the stable ground, and :attr:`Coregistration.statement` says so. A shift of a
cell or more that slopes cannot fit still moves the flat land's heights (a moved shore leaves land over the
sea): a direct search on the land left (:func:`_search_shift`, polished by least squares) finds it well
enough to measure the bias through it (a trimmed mean), but it is not applied or reported as fitted.
"Identical" is concluded only when the difference on stable ground is exactly 0, never from an NMAD of 0.
"""

from __future__ import annotations

import logging
import math
import time
import warnings
from dataclasses import dataclass, field

import numpy as np

from terralod.change.difference import AlignedPair, dem_of_difference, valid_at

log = logging.getLogger(__name__)

#: NMAD = 1.4826 · median absolute deviation: the standard deviation of a normal distribution.
NMAD_FACTOR = 1.4826
#: Residuals beyond this many NMAD are not stable ground (and not used in a fit).
OUTLIER_NMAD = 3.0
#: Cells added around the change before taking the rest as stable ground.
CHANGE_BUFFER_CELLS = 2
#: Fewest stable cells a fit (and an NMAD) is made from.
MIN_STABLE_CELLS = 100
#: Fewest sloping stable cells a horizontal fit is made from.
MIN_FIT_CELLS = 200
#: Slope below which a cell carries no information on a horizontal shift, degrees (xdem / Nuth & Kääb).
SLOPE_MIN_DEG = 3.0
#: A horizontal shift is fitted only when its least-squares standard error is below this, cells.
MAX_SHIFT_SE_CELLS = 0.05
#: A level surface (water) is a connected patch of exactly constant elevation of at least this many cells.
LEVEL_MIN_CELLS = 16
#: Most stable cells used by a fit (a seeded random subsample beyond it, as xdem does).
MAX_FIT_CELLS = 500_000
#: Smallest difference (m) under which a change threshold is never set (an NMAD of 0 is no licence to
#: call every non-zero cell a change).
NMAD_FLOOR_M = 0.01
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
    #: "shift and bias", "bias only", "identical" or "none"
    mode: str = "none"
    fit_cells: int = 0
    #: least-squares standard error of the horizontal shift, cells (NaN when none was fitted)
    shift_se_cells: float = float("nan")
    #: 1-σ uncertainty of the fitted vertical bias, metres
    bias_sigma_m: float = float("nan")
    #: one plain sentence on what was fitted and why
    statement: str = ""

    def as_dict(self) -> dict:
        return {
            "method": self.method,
            "applied": self.applied,
            "mode": self.mode,
            "statement": self.statement,
            "shift_m": [float(v) for v in self.shift_m],
            "stable_cells": int(self.stable_cells),
            "fit_cells": int(self.fit_cells),
            "shift_se_cells": _num(self.shift_se_cells),
            "bias_sigma_m": _num(self.bias_sigma_m),
            "nmad_before_m": _num(self.nmad_before_m),
            "nmad_after_m": _num(self.nmad_after_m),
            "iterations": int(self.iterations),
            "seconds": round(float(self.seconds), 4),
            "notes": list(self.notes),
        }


@dataclass
class StableGround:
    """Where the fit and σ look, and why the rest was left out (cell counts on BEFORE's grid)."""

    mask: np.ndarray  # stable ground (σ, the vertical bias)
    fit: np.ndarray  # its cells on slopes >= slope_min_deg (the horizontal fit)
    slope_min_deg: float
    valid_cells: int
    user_mask_cells: int | None
    excluded_cells: int
    level_cells: int
    level_patches: int
    change_cells: int
    flat_cells: int
    #: every sloping cell that could be stable (the change not yet taken out): the first fit's cells when a
    #: misregistration makes too much sloping ground look changed
    candidates: np.ndarray | None = None
    #: every cell that could be stable (valid, off water, inside --stable, outside --exclude)
    base: np.ndarray | None = None

    @property
    def cells(self) -> int:
        return int(self.mask.sum())

    @property
    def fit_cells(self) -> int:
        return int(self.fit.sum())

    def describe(self, bias_only: bool) -> str:
        """'fitted on 41 % of the area: land outside the change with slopes above 3°; the sea and 2 lakes
        were left out' — for a council member."""
        total = self.mask.size
        used = self.cells if bias_only else self.fit_cells
        pct = 100.0 * used / max(total, 1)
        what = "ground outside the change" if self.user_mask_cells is None else "the stable ground you marked"
        if not bias_only:
            what += f" with slopes above {self.slope_min_deg:g}°"
        left = []
        if self.level_patches:
            n = self.level_patches
            left.append(
                f"{n} flat water surface{'s' if n > 1 else ''} (sea, lakes: "
                f"{100.0 * self.level_cells / total:.0f} % of the area)"
            )
        if self.excluded_cells:
            left.append(f"the areas you excluded ({100.0 * self.excluded_cells / total:.0f} %)")
        if self.change_cells:
            left.append(f"the changed ground ({100.0 * self.change_cells / total:.0f} %)")
        if total - self.valid_cells:
            left.append(
                f"cells without data in one survey ({100.0 * (total - self.valid_cells) / total:.0f} %)"
            )
        if not bias_only and self.flat_cells:
            left.append(f"flatter ground ({100.0 * self.flat_cells / total:.0f} %)")
        s = f"fitted on {pct:.0f} % of the area: {what}"
        if left:
            s += "; left out: " + ", ".join(left)
        return s

    def as_dict(self, bias_only: bool) -> dict:
        total = self.mask.size
        return {
            "cells": self.cells,
            "fit_cells": self.fit_cells,
            "fraction_of_area": self.cells / max(total, 1),
            "fit_fraction_of_area": (self.cells if bias_only else self.fit_cells) / max(total, 1),
            "slope_min_deg": self.slope_min_deg,
            "valid_cells": self.valid_cells,
            "user_mask_cells": self.user_mask_cells,
            "excluded_cells": self.excluded_cells,
            "level_surface_cells": self.level_cells,
            "level_surfaces": self.level_patches,
            "change_cells": self.change_cells,
            "flat_cells": self.flat_cells,
            "description": self.describe(bias_only),
        }


def nmad(values: np.ndarray) -> float:
    """Normalised median absolute deviation of the finite values (NaN when there are none)."""
    v = np.asarray(values, np.float64)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return float("nan")
    return float(NMAD_FACTOR * np.median(np.abs(v - np.median(v))))


def median_nmad(values: np.ndarray) -> tuple[float, float]:
    """(``np.median(values)``, :func:`nmad` of them), the median found once when the values are finite
    float64 (the same two numbers as computing each on its own)."""
    v = np.asarray(values)
    med = float(np.median(v))
    if v.dtype != np.float64 or v.size == 0 or not np.isfinite(med) or not np.isfinite(v).all():
        return med, nmad(v)
    return med, float(NMAD_FACTOR * np.median(np.abs(v - med)))


def stable_ground(dod: np.ndarray, given: np.ndarray | None = None) -> np.ndarray:
    """Stable cells of a DoD: ``given`` (or every finite cell) minus the change, the cells beyond
    ``OUTLIER_NMAD`` NMAD of the median (re-estimated until it settles; the threshold never below
    :data:`NMAD_FLOOR_M`), grown by ``CHANGE_BUFFER_CELLS``."""
    from scipy import ndimage

    ok = np.isfinite(dod) if given is None else (np.isfinite(dod) & given)
    stable = ok.copy()
    for _ in range(5):
        v = dod[stable]
        if v.size < MIN_STABLE_CELLS:
            return stable
        med, s = median_nmad(v)
        s = max(s, NMAD_FLOOR_M)
        change = ok & (np.abs(dod - med) > OUTLIER_NMAD * s)
        if CHANGE_BUFFER_CELLS:
            change = ndimage.binary_dilation(change, iterations=CHANGE_BUFFER_CELLS)
        new = ok & ~change
        if np.array_equal(new, stable):
            break
        stable = new
    return stable


def level_surfaces(
    z: np.ndarray, valid: np.ndarray, min_cells: int = LEVEL_MIN_CELLS
) -> tuple[np.ndarray, int]:
    """Cells of connected patches whose elevation is exactly constant (every 3×3 neighbourhood of equal
    height), of at least ``min_cells``, with their shore cells: the sea, lakes, reservoirs. Returns (mask,
    number of patches)."""
    from scipy import ndimage

    zz = z.astype(np.float64)
    hi = ndimage.maximum_filter(np.where(valid, zz, np.inf), size=3, mode="nearest")
    lo = ndimage.minimum_filter(np.where(valid, zz, -np.inf), size=3, mode="nearest")
    flat = valid & (hi == lo)
    if not flat.any():
        return flat, 0
    lab, n = ndimage.label(flat, structure=np.ones((3, 3), bool))
    sizes = np.bincount(lab.ravel(), minlength=n + 1)
    big = sizes >= min_cells
    big[0] = False
    core = big[lab]
    return ndimage.binary_dilation(core) & valid, int(big.sum())


def slope_deg(hf) -> np.ndarray:
    """Slope of a heightfield, degrees (central differences, metres)."""
    gy, gx = np.gradient(hf.elevation_m.astype(np.float64))
    dx, dy = hf.spacing_m
    return np.degrees(np.arctan(np.hypot(gx / dx, gy / dy)))


class StableGroundFinder:
    """The stable ground of one pair for any DoD of it (module docstring).

    What depends only on the pair and the user's masks is computed once, here: the level surfaces (of
    BEFORE, and of AFTER on the same grid), BEFORE's slopes and so its sloping cells. Each call takes a DoD
    (its valid cells and its change) and returns a :class:`StableGround`; the result is the same as
    recomputing everything for that DoD."""

    def __init__(
        self,
        pair: AlignedPair,
        *,
        given: np.ndarray | None = None,
        exclude: np.ndarray | None = None,
        slope_min_deg: float = SLOPE_MIN_DEG,
    ) -> None:
        before = pair.before
        level, n_level = level_surfaces(before.elevation_m, before.valid)
        if pair.same_grid:
            lv2, _ = level_surfaces(pair.after.elevation_m, pair.after.valid)
            if (lv2 & ~level).any():
                from scipy import ndimage

                level |= lv2
                n_level = int(ndimage.label(level, structure=np.ones((3, 3), bool))[1])
        self.given = given
        self.exclude = exclude
        self.slope_min_deg = slope_min_deg
        self.level = level
        self.level_patches = n_level
        self.sloping = slope_deg(before) >= slope_min_deg

    def __call__(self, dod: np.ndarray) -> StableGround:
        valid = np.isfinite(dod)
        base = valid & ~self.level
        user = None
        if self.given is not None:
            user = int((self.given & valid).sum())
            base &= self.given
        n_excl = 0
        if self.exclude is not None:
            n_excl = int((self.exclude & valid & ~self.level).sum())
            base &= ~self.exclude
        mask = stable_ground(dod, base)
        fit = mask & self.sloping
        return StableGround(
            mask=mask, fit=fit, slope_min_deg=self.slope_min_deg, valid_cells=int(valid.sum()),
            user_mask_cells=user, excluded_cells=n_excl, level_cells=int((self.level & valid).sum()),
            level_patches=self.level_patches, change_cells=int((base & ~mask).sum()),
            flat_cells=int((mask & ~fit).sum()), candidates=base & self.sloping, base=base,
        )  # fmt: skip


def shift_standard_error_cells(
    pair: AlignedPair,
    fit: np.ndarray,
    residual: np.ndarray,
    shift_m: tuple[float, float, float] | None = None,
) -> float:
    """Least-squares standard error of a horizontal shift fitted on ``fit`` cells (largest direction),
    cells: σ_r · sqrt(λmax((GᵀG)⁻¹)) with G the slope vectors of BEFORE and σ_r the residual's NMAD.
    With a coarser AFTER and ``shift_m`` given, on AFTER's own samples (as :func:`_fit_on_after_grid`
    fits): AFTER's spline on BEFORE's grid averages its noise, and its NMAD there understates σ_r."""
    before = pair.before
    if shift_m is not None and _coarser_after(pair):
        return _after_grid_standard_error_cells(pair, fit, shift_m)
    gy, gx = np.gradient(before.elevation_m.astype(np.float64))
    dx, dy = before.spacing_m
    gx, gy = gx[fit] / dx, -gy[fit] / dy
    r = residual[fit]
    ok = np.isfinite(r)
    if ok.sum() < MIN_FIT_CELLS:
        return float("inf")
    g = np.column_stack([gx[ok], gy[ok]])
    m = g.T @ g
    try:
        lam = float(np.linalg.eigvalsh(np.linalg.inv(m)).max())
    except np.linalg.LinAlgError:
        return float("inf")
    s = max(nmad(r[ok]), NMAD_FLOOR_M)
    # AFTER's own samples are the independent ones: fewer of them when its grid is coarser
    coarser = max(1.0, (pair.after.spacing_m[0] * pair.after.spacing_m[1]) / (dx * dy))
    return float(s * math.sqrt(max(lam, 0.0) * coarser) / min(before.spacing_m))


def coregister(
    pair: AlignedPair,
    *,
    stable: np.ndarray | None = None,
    exclude: np.ndarray | None = None,
    method: str = "xdem",
    seed: int = 0,
    slope_min_deg: float = SLOPE_MIN_DEG,
    ground: StableGroundFinder | None = None,
) -> Coregistration:
    """Fit the translation of AFTER onto BEFORE on stable ground (``stable``: a mask on BEFORE's grid, or
    None for "outside the change"; ``exclude``: cells never stable; ``ground``: the pair's
    :class:`StableGroundFinder` when the caller has one, which then stands for those three). Returns a
    :class:`Coregistration` (not yet applied) with :attr:`~Coregistration.statement` saying what was fitted.

    The recipe: find the stable ground of the raw difference; stop if it is too small or identical; fit a
    horizontal shift in rounds on its sloping part; keep the shift only if its standard error allows; without
    one, look for the bias through a searched shift; settle the vertical bias; say what was done."""
    if method not in METHODS:
        raise ValueError(f"Expected a co-registration method in {METHODS}, got {method!r}")
    t0 = time.perf_counter()
    if ground is None:
        ground = StableGroundFinder(pair, given=stable, exclude=exclude, slope_min_deg=slope_min_deg)
    dod0 = dem_of_difference(pair)
    sg = ground(dod0)
    res = Coregistration(method=method, stable_cells=sg.cells, nmad_before_m=nmad(dod0[sg.mask]))
    if _nothing_to_fit(res, sg, dod0):
        res.seconds = time.perf_counter() - t0
        return res
    cand, sg, why = _fit_shift_rounds(pair, ground, sg, dod0, method, seed, res)
    shift, why = _accepted_shift(pair, sg, cand, why, res, ground.slope_min_deg)
    bias_only = shift is None
    searched = None
    if shift is None:
        shift, sg, searched = _bias_ground_without_a_shift(pair, ground, sg, dod0, seed, res)
    if searched is None:
        shift, sg, d = _settle_bias(pair, ground, sg, shift, bias_only)
    else:
        d = dem_of_difference(pair, shift)
    _conclude(res, sg, shift, d, bias_only, why, method)
    res.seconds = time.perf_counter() - t0
    return res


def _nothing_to_fit(res: Coregistration, sg: StableGround, dod0: np.ndarray) -> bool:
    """Whether there is nothing to fit: too little stable ground, or a difference exactly 0 on it (never
    concluded from an NMAD of 0). Fills ``res`` when so."""
    if sg.cells < MIN_STABLE_CELLS:
        res.notes.append(f"co-registration skipped: {sg.cells} stable cells (< {MIN_STABLE_CELLS})")
        res.statement = (
            f"The surveys were not lined up: only {sg.cells} cells of stable ground were left to do it on."
        )
        res.method = "none"
        return True
    if bool(np.all(dod0[sg.mask] == 0.0)):
        res.notes.append(
            "stable ground is identical in both DEMs (difference exactly 0): shift 0, nothing to fit"
        )
        res.statement = "The two surveys are identical on unchanged ground, so no alignment was needed."
        res.nmad_after_m = 0.0
        res.method, res.mode = "none", "identical"
        return True
    return False


def _fit_once(
    pair: AlignedPair, cells: np.ndarray, method: str, seed: int
) -> tuple[tuple[float, float, float], int]:
    """One horizontal fit on ``cells`` with ``method`` (xdem's binned fit is polished by least squares on the
    unsmoothed surfaces: on gentle or noisy ground its bins leave a tenth of a cell that the cells themselves
    can resolve)."""
    if method == "xdem":
        s1, iters = _fit_xdem(pair, cells, seed)
        s1, more = _fit_terralod(pair, cells, seed, start=s1)
        return s1, iters + more
    return _fit_terralod(pair, cells, seed)


#: Most fit rounds (stable ground re-found on each round's difference) before the shift is taken as is.
MAX_FIT_ROUNDS = 6
#: A round that moves the shift by less than this (cells) has reached the fixed point.
ROUND_SETTLED_CELLS = 0.002
#: A round is refused when it makes the NMAD on the sloping stable ground worse by more than this factor.
ROUND_NMAD_SLACK = 1.01


def _fit_shift_rounds(
    pair: AlignedPair,
    ground: StableGroundFinder,
    sg: StableGround,
    dod0: np.ndarray,
    method: str,
    seed: int,
    res: Coregistration,
) -> tuple[tuple[float, float, float] | None, StableGround, str]:
    """Rounds to a fixed point: fit on the sloping stable ground, re-find the stable ground on the improved
    difference (a misregistered survey makes sloping ground look changed), fit again, until the stable ground
    or the shift (within :data:`ROUND_SETTLED_CELLS`) settles, at most :data:`MAX_FIT_ROUNDS` rounds.

    The stable ground is chosen by thresholding the noisy difference, so a round's cells are those where the
    noise happened to cancel what the previous shift left: each fit is pulled towards the previous one
    (attenuation), and only at the fixed point is the pull gone. On the 1 m prairie LiDAR against a 1.5x
    coarser AFTER under 1.2 m of noise, stopping after the first round whose NMAD did not drop left the
    shift up to 0.27 cell off (seeds 0-9); to the fixed point it is within 0.11. A later round is refused
    only when it makes the NMAD on the sloping ground worse by more than :data:`ROUND_NMAD_SLACK` (a
    diverging fit; noise moves that NMAD by a fraction of a percent either way). Returns (the shift or None,
    the stable ground, why no shift could be fitted)."""
    cand: tuple[float, float, float] | None = None
    dod = dod0
    why = ""
    px = float(min(pair.before.spacing_m))
    for _round in range(MAX_FIT_ROUNDS):
        cells = sg.fit
        if sg.fit_cells < MIN_FIT_CELLS:
            if _round == 0 and sg.candidates is not None and sg.candidates.sum() >= MIN_FIT_CELLS:
                cells = sg.candidates  # the fit's own outlier rejection takes the change out
            else:
                why = (
                    f"only {sg.fit_cells:,} stable cells have slopes above {ground.slope_min_deg:g}° "
                    f"(< {MIN_FIT_CELLS})"
                )
                break
        try:
            s1, iters = _fit_once(pair, cells, method, seed)
            res.iterations += iters
        except Exception as exc:  # noqa: BLE001 - an estimator's failure is a note and a fall-back
            msg = str(exc).splitlines()[0][:160] if str(exc) else type(exc).__name__
            res.notes.append(f"{method}'s Nuth & Kääb fit failed ({msg}); vertical bias fitted alone")
            why = f"the horizontal fit failed ({msg})"
            break
        d1 = dem_of_difference(pair, s1)
        if cand is not None and not nmad(d1[sg.fit]) <= ROUND_NMAD_SLACK * nmad(dod[sg.fit]):
            break
        moved_cells = None if cand is None else math.hypot(s1[0] - cand[0], s1[1] - cand[1]) / px
        cand, dod = s1, d1 - float(np.nanmedian(d1[sg.mask]))
        if moved_cells is not None and moved_cells < ROUND_SETTLED_CELLS:
            break
        sg2 = ground(dod)
        if sg2.cells < MIN_STABLE_CELLS or np.array_equal(sg2.mask, sg.mask):
            break
        sg = sg2
    return cand, sg, why


def _accepted_shift(
    pair: AlignedPair,
    sg: StableGround,
    cand: tuple[float, float, float] | None,
    why: str,
    res: Coregistration,
    slope_min_deg: float,
) -> tuple[tuple[float, float, float] | None, str]:
    """The fitted shift when its standard error is at most :data:`MAX_SHIFT_SE_CELLS` (recorded in
    ``res``), else None and why not."""
    if cand is None:
        return None, why
    d1 = dem_of_difference(pair, cand)
    se = shift_standard_error_cells(pair, sg.fit, d1, cand)
    res.shift_se_cells = se
    if se <= MAX_SHIFT_SE_CELLS:
        return cand, why
    return None, (
        f"the sloping stable ground ({sg.fit_cells:,} cells above {slope_min_deg:g}°) leaves the "
        f"shift uncertain by ±{se:.2f} cells"
    )


def _bias_ground_without_a_shift(
    pair: AlignedPair,
    ground: StableGroundFinder,
    sg: StableGround,
    dod0: np.ndarray,
    seed: int,
    res: Coregistration,
) -> tuple[tuple[float, float, float], StableGround, tuple[float, float] | None]:
    """No horizontal shift could be fitted: the stable ground the vertical bias is measured on. A shift of a
    cell or more found by :func:`_search_shift` (polished by least squares when that stays within a cell) is
    looked through, not applied: the bias is the trimmed mean on the stable ground it leaves, so that an
    unfitted shift of several cells does not pollute it. Returns (the shift: (0, 0, dz) through a searched
    shift, else zero; the stable ground the bias is measured on; the searched shift or None)."""
    shift = (0.0, 0.0, 0.0)
    searched = _search_shift(pair, sg.base if sg.base is not None else sg.mask)
    px = min(pair.before.spacing_m)
    if searched is not None and math.hypot(*searched) < SEARCH_USE_CELLS * px:
        searched = None  # under a cell the flatter ground's median is barely moved by the shift
    if searched is not None:
        ds = dem_of_difference(pair, (searched[0], searched[1], 0.0))
        sgs = ground(ds - float(np.nanmedian(ds[sg.base])))
        if sgs.cells >= MIN_STABLE_CELLS:
            # polished by least squares on that ground (slopes of any size), for the bias only
            pol, _ = _fit_terralod(pair, sgs.mask, seed, start=(searched[0], searched[1], 0.0))
            if math.hypot(pol[0] - searched[0], pol[1] - searched[1]) <= px:
                searched = (pol[0], pol[1])
                ds = dem_of_difference(pair, (searched[0], searched[1], 0.0))
            for _ in range(2):
                sgs2 = ground(ds - _trimmed_mean(ds[sgs.mask]))
                if sgs2.cells < MIN_STABLE_CELLS:
                    break
                sgs = sgs2
            shift = (0.0, 0.0, -_trimmed_mean(ds[sgs.mask]))
            res.notes.append(
                f"vertical bias measured with AFTER moved by ({searched[0]:+.1f}, {searched[1]:+.1f}) m, "
                "found by a direct search on the land left (not applied: too imprecise to report)"
            )
        else:
            searched = None
    base_bias = -shift[2] if searched is not None else float(np.nanmedian(dod0[_bias_cells(sg, True)]))
    return shift, ground(dod0 - base_bias), searched


def _settle_bias(
    pair: AlignedPair,
    ground: StableGroundFinder,
    sg: StableGround,
    shift: tuple[float, float, float],
    bias_only: bool,
) -> tuple[tuple[float, float, float], StableGround, np.ndarray]:
    """The vertical bias: the median difference on the stable ground (its flatter part when no horizontal
    shift could be fitted: an unknown shift moves sloping cells' differences most), twice, the stable ground
    re-found on each. Returns (the shift with its bias, the stable ground, the difference through it)."""
    for _ in range(2):
        d = dem_of_difference(pair, shift)
        med = float(np.nanmedian(d[_bias_cells(sg, bias_only)]))
        shift = (shift[0], shift[1], shift[2] - med)
        d = d - med
        sg2 = ground(d)
        if sg2.cells < MIN_STABLE_CELLS:
            break
        sg = sg2
    return shift, sg, d


def _conclude(
    res: Coregistration,
    sg: StableGround,
    shift: tuple[float, float, float],
    d: np.ndarray,
    bias_only: bool,
    why: str,
    method: str,
) -> None:
    """Fill ``res`` with the shift, the cells it was fitted on and a plain statement of what was fitted."""
    res.shift_m = (float(shift[0]), float(shift[1]), float(shift[2]))
    res.fit_cells = sg.cells if bias_only else sg.fit_cells
    res.stable_cells = sg.cells
    res.nmad_after_m = nmad(d[sg.mask])
    res.mode = "bias only" if bias_only else "shift and bias"
    if bias_only:
        res.method = f"{method} (vertical bias only)" if not res.notes else "median (vertical bias only)"
        res.statement = (
            f"Only the height difference between the surveys ({abs(shift[2]):.2f} m) could be corrected: "
            f"{why or 'the horizontal alignment could not be measured'}, so a sideways misalignment "
            "cannot be ruled out and the uncertainty was widened."
        )
        res.notes.append(f"vertical bias only: {why}")
    else:
        res.statement = (
            f"The later survey was lined up with the earlier one on {sg.describe(False).split(': ', 1)[1]}."
        )


#: Largest horizontal shift the direct search looks for, cells
SEARCH_MAX_CELLS = 6
#: The searched shift is used for the bias only when it is at least this long, cells
SEARCH_USE_CELLS = 1.0
#: The search's best shift is used only when it lowers the NMAD on the land by at least this fraction
SEARCH_MIN_GAIN = 0.1


def _search_shift(pair: AlignedPair, land: np.ndarray) -> tuple[float, float] | None:
    """A horizontal shift (dx, dy) metres found by direct search where slopes cannot fit one: the NMAD of
    AFTER − BEFORE on ``land`` (every candidate stable cell: the change is a minority that the NMAD
    ignores) over whole cells within ±:data:`SEARCH_MAX_CELLS`, then quarter cells around the best. Its
    steps are where the land's low relief and its shore (a moved coast leaves land over sea) do show a
    shift of a cell or more. None when it does not lower the NMAD by :data:`SEARCH_MIN_GAIN`."""
    from scipy import ndimage

    rows, cols = np.nonzero(land)
    if rows.size < MIN_STABLE_CELLS:
        return None
    x, y = pair.before.world_xy(rows, cols)
    b = pair.before.elevation_m[rows, cols].astype(np.float64)
    after = pair.after
    a_full = after.elevation_m.astype(np.float64)
    dx, dy = pair.before.spacing_m

    def cost(tx: float, ty: float) -> float:
        r, c = after.sample_rc(x - tx, y - ty)
        z = ndimage.map_coordinates(a_full, [r, c], order=1, mode="nearest")
        ok = valid_at(after, r, c)
        if ok.sum() < MIN_STABLE_CELLS:
            return float("inf")
        return nmad(z[ok] - b[ok])

    zero = cost(0.0, 0.0)
    n = SEARCH_MAX_CELLS
    best = min((cost(i * dx, j * dy), i, j) for i in range(-n, n + 1) for j in range(-n, n + 1))
    steps = np.arange(-1.0, 1.01, 0.25)
    best = min((cost((best[1] + u) * dx, (best[2] + v) * dy), best[1] + u, best[2] + v)
                for u in steps for v in steps)  # fmt: skip
    if not best[0] <= (1.0 - SEARCH_MIN_GAIN) * zero:
        return None
    return float(best[1] * dx), float(best[2] * dy)


def _trimmed_mean(v: np.ndarray) -> float:
    """Mean of the finite values (on stable ground, already cut at 3 NMAD: a trimmed mean, which on a few
    hundred cells of land scatters 1.25 times less than their median)."""
    v = v[np.isfinite(v)]
    return float(v.mean()) if v.size else float("nan")


def _bias_cells(sg: StableGround, bias_only: bool) -> np.ndarray:
    """Cells the vertical bias is the median of: all the stable ground after a horizontal fit; without one,
    its flatter part (an unknown shift moves sloping cells' differences most)."""
    flat = sg.mask & ~sg.fit
    return flat if bias_only and flat.sum() >= MIN_STABLE_CELLS else sg.mask


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
    # np.median, not xdem's default np.nanmedian: xdem bins only finite values, where the two agree bit for
    # bit, and scipy's binned_statistic computes np.median by sorting once instead of per-bin Python lists
    # (the binning, most of the fit, at half the CPU; tests/test_change_uncertainty.py checks the same bits)
    nk = xdem.coreg.NuthKaab(subsample=MAX_FIT_CELLS, bin_statistic=np.median)
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
    pair: AlignedPair,
    mask: np.ndarray,
    seed: int,
    *,
    tol_px: float = 1e-3,
    max_iter: int = 30,
    start: tuple[float, float, float] | None = None,
) -> tuple[tuple[float, float, float], int]:
    """Gauss-Newton on ``r(t) = A(x − t_xy) + t_z − B(x)`` over stable cells, coarse to fine (only on the
    unsmoothed surfaces when starting from ``start``, another estimator's answer)."""
    from scipy import ndimage

    before, after = pair.before, pair.after
    if _coarser_after(pair):
        return _fit_on_after_grid(pair, mask, seed, tol_px=tol_px, max_iter=max_iter, start=start)
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
    if start is not None:
        t[:] = start
    for sigma_px in (4.0, 2.0, 1.0, 0.0) if start is None else (0.0,):
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
            ok = valid_at(after, r, c)
            res = a + t[2] - b
            # r(t + δ) ≈ r(t) − ∇A(x − t)·δ + δz, and ∇A(x − t) ≈ ∇B(x) near the solution
            delta = _robust_step(res, ok, gx, gy)
            if delta is None:
                break
            t += delta
            if np.hypot(delta[0], delta[1]) < tol_px * px and abs(delta[2]) < 1e-4:
                break
    return _with_final_offset(pair, mask, t), iters


def _robust_step(res: np.ndarray, ok: np.ndarray, gx: np.ndarray, gy: np.ndarray) -> np.ndarray | None:
    """One Gauss-Newton step (δx, δy, δz) of the residuals ``res`` against the gradient (gx, gy), on the
    valid cells within ``OUTLIER_NMAD`` NMAD of their median; None when too few are left."""
    if ok.sum() < MIN_STABLE_CELLS:
        return None
    med, s = median_nmad(res[ok])
    s = max(s, 1e-9)
    use = ok & (np.abs(res - med) <= OUTLIER_NMAD * s)
    if use.sum() < MIN_STABLE_CELLS:
        return None
    m = np.column_stack([gx[use], gy[use], -np.ones(int(use.sum()))])
    delta, *_ = np.linalg.lstsq(m, res[use], rcond=None)
    return delta


def _with_final_offset(pair: AlignedPair, mask: np.ndarray, t: np.ndarray) -> tuple[float, float, float]:
    """The fitted shift with its vertical offset taken from the median difference of the unsmoothed
    surfaces on the stable ground it leaves."""
    d = dem_of_difference(pair, tuple(t))
    st = stable_ground(d, mask)
    if st.sum() >= MIN_STABLE_CELLS:
        t[2] -= float(np.median(d[st]))
    return (float(t[0]), float(t[1]), float(t[2]))


#: AFTER is fitted on its own grid when its cells are at least this much larger (area) than BEFORE's
COARSER_AREA_RATIO = 1.2


def _coarser_after(pair: AlignedPair) -> bool:
    (bx, by), (ax, ay) = pair.before.spacing_m, pair.after.spacing_m
    return not pair.same_grid and ax * ay >= COARSER_AREA_RATIO * bx * by


def _after_grid_samples(pair: AlignedPair, mask: np.ndarray, seed: int):
    """AFTER's valid samples whose nearest BEFORE cell is in ``mask``: (rows, cols, x, y), at most
    :data:`MAX_FIT_CELLS` (a seeded subsample)."""
    before, after = pair.before, pair.after
    ra, ca = np.nonzero(after.valid)
    x, y = after.world_xy(ra, ca)
    rb, cb = before.sample_rc(x, y)
    ri, ci = np.rint(rb).astype(np.int64), np.rint(cb).astype(np.int64)
    h, w = before.shape
    inside = (ri >= 0) & (ri < h) & (ci >= 0) & (ci < w)
    keep = np.zeros(ra.size, bool)
    keep[inside] = mask[ri[inside], ci[inside]]
    ra, ca, x, y = ra[keep], ca[keep], x[keep], y[keep]
    if ra.size > MAX_FIT_CELLS:
        pick = np.random.default_rng(seed).choice(ra.size, MAX_FIT_CELLS, replace=False)
        ra, ca, x, y = ra[pick], ca[pick], x[pick], y[pick]
    return ra, ca, x, y


def _after_grid_residual(pair: AlignedPair, b_coef, gx_b, gy_b, a, x, y, t):
    """``A(p) + t_z − B(p + t_xy)`` at AFTER's samples, BEFORE's gradient there and whether B is valid."""
    from scipy import ndimage

    r, c = pair.before.sample_rc(x + t[0], y + t[1])
    coords = np.stack([r, c])
    b = ndimage.map_coordinates(b_coef, coords, order=3, mode="nearest", prefilter=False)
    gx = ndimage.map_coordinates(gx_b, coords, order=1, mode="nearest")
    gy = ndimage.map_coordinates(gy_b, coords, order=1, mode="nearest")
    return a + t[2] - b, gx, gy, valid_at(pair.before, r, c)


def _before_spline(before, sigma_px: float = 0.0):
    """BEFORE (Gaussian-smoothed by ``sigma_px`` cells) as cubic-spline coefficients, and its gradient
    (east, north) per metre."""
    from scipy import ndimage

    b = before.elevation_m.astype(np.float64)
    if sigma_px:
        b = ndimage.gaussian_filter(b, sigma_px)
    gy_b, gx_b = np.gradient(b)
    return ndimage.spline_filter(b, order=3), gx_b / before.spacing_m[0], -gy_b / before.spacing_m[1]


def _after_grid_standard_error_cells(pair: AlignedPair, fit: np.ndarray, shift_m) -> float:
    """:func:`shift_standard_error_cells` on AFTER's own samples (a coarser AFTER)."""
    ra, ca, x, y = _after_grid_samples(pair, fit, 0)
    if ra.size < MIN_FIT_CELLS:
        return float("inf")
    b_coef, gx_b, gy_b = _before_spline(pair.before)
    a = pair.after.elevation_m[ra, ca].astype(np.float64)
    res, gx, gy, ok = _after_grid_residual(pair, b_coef, gx_b, gy_b, a, x, y, shift_m)
    if ok.sum() < MIN_FIT_CELLS:
        return float("inf")
    med, s = median_nmad(res[ok])
    s = max(s, NMAD_FLOOR_M)
    use = ok & (np.abs(res - med) <= OUTLIER_NMAD * s)
    if use.sum() < MIN_FIT_CELLS:
        return float("inf")
    g = np.column_stack([gx[use], gy[use]])
    try:
        lam = float(np.linalg.eigvalsh(np.linalg.inv(g.T @ g)).max())
    except np.linalg.LinAlgError:
        return float("inf")
    return float(s * math.sqrt(max(lam, 0.0)) / min(pair.before.spacing_m))


def _fit_on_after_grid(
    pair: AlignedPair,
    mask: np.ndarray,
    seed: int,
    *,
    tol_px: float,
    max_iter: int,
    start: tuple[float, float, float] | None,
) -> tuple[tuple[float, float, float], int]:
    """The Gauss-Newton fit of :func:`_fit_terralod` on AFTER's coarser grid, like with like: each AFTER
    sample against BEFORE (the finer, cubic spline) at that sample's shifted position,
    ``r(t) = A(p) + t_z − B(p + t_xy)``, with BEFORE's gradient taken there. Fitting on BEFORE's grid
    instead uses AFTER's spline, which spreads each noisy AFTER sample over several BEFORE cells (whose
    residuals also chose the stable ground): on the 1 m prairie LiDAR with a 1.5x coarser AFTER under 1.2 m
    of noise that fit was 0.07 cell off where this one is 0.008 (without noise both are exact), and the
    NMAD of those spread residuals understated the shift's standard error."""
    from scipy import ndimage

    before, after = pair.before, pair.after
    ra, ca, x, y = _after_grid_samples(pair, mask, seed)
    t = np.zeros(3) if start is None else np.array(start, np.float64)
    iters = 0
    a_full = after.elevation_m.astype(np.float64)
    px = float(min(before.spacing_m))
    dxa, dya = after.spacing_m
    for sigma_m in (4.0 * px, 2.0 * px, 1.0 * px, 0.0) if start is None else (0.0,):
        a_s = ndimage.gaussian_filter(a_full, sigma_m / min(dxa, dya)) if sigma_m else a_full
        a = a_s[ra, ca]
        b_coef, gx_b, gy_b = _before_spline(before, sigma_m / px)
        for _ in range(max_iter):
            iters += 1
            res, gx, gy, ok = _after_grid_residual(pair, b_coef, gx_b, gy_b, a, x, y, t)
            delta = _robust_step(res, ok, gx, gy)
            if delta is None:
                break
            t += delta
            if np.hypot(delta[0], delta[1]) < tol_px * px and abs(delta[2]) < 1e-4:
                break
    return _with_final_offset(pair, mask, t), iters


def _num(v: float):
    return None if v is None or not np.isfinite(v) else float(v)


def read_stable_mask(path, hf, what: str = "stable cell") -> np.ndarray:
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
        raise InputError(f"marks no {what} on the terrain", str(p))
    return mask
