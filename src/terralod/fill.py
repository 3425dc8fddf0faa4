"""Validation of elevation arrays and filling of nodata cells for meshing.

Fill method (documented, deterministic): every nodata cell first takes the elevation of its nearest valid
sample (Euclidean distance in pixels, ``scipy.ndimage.distance_transform_edt``), then the filled cells
alone are relaxed by 4-neighbour averaging (Jacobi iterations with the valid samples held fixed) so a
hole becomes a smooth membrane spanning its rim — never a cliff down to a nodata value, never a step
between Voronoi cells. Valid samples are never changed, and the mask of filled cells is kept so error
measurement ignores them. It is the one fill of the package: a store's heightfield, the window sources'
blocks (:mod:`terralod.io.windowed`) and a DEM read on its own lattice for a web export
(:mod:`terralod.export.source`) all fill holes with :func:`fill_nodata`.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy import ndimage

from terralod.errors import InputError
from terralod.kernels.fill import relax_holes

#: Largest accepted raster side in samples (a 1 m DEM of a 262 km square); beyond it, tile the input.
MAX_SIDE = 262_145
#: Largest accepted sample count (4 bytes each as float32, plus mask and pyramid bookkeeping).
MAX_SAMPLES = 2_000_000_000
#: Smallest raster that spans a surface.
MIN_SIDE = 2
#: Smallest fraction of valid samples accepted: below it the raster is mostly fill, and its mesh would be
#: invented surface (e.g. 1 valid sample in 10,000); crop it to the data or check the nodata value.
MIN_VALID_FRACTION = 0.001
#: Jacobi iterations that smooth the nearest-sample fill of holes.
FILL_SMOOTH_ITERATIONS = 32


def check_dimensions(height: int, width: int, source: str) -> None:
    """Refuse rasters too small to mesh or too large to hold, before reading them."""
    if height < MIN_SIDE or width < MIN_SIDE:
        raise InputError(f"raster is {width}x{height} samples; at least {MIN_SIDE}x{MIN_SIDE} needed", source)
    if height > MAX_SIDE or width > MAX_SIDE or height * width > MAX_SAMPLES:
        raise InputError(
            f"raster is {width}x{height} samples, beyond the supported {MAX_SIDE} per side / "
            f"{MAX_SAMPLES:,} samples; split it into tiles first",
            source,
        )


def prepare_elevation(
    values: np.ndarray, valid: np.ndarray | None, source: str
) -> tuple[np.ndarray, np.ndarray, str]:
    """Validate an elevation array and fill its nodata cells.

    Parameters
    ----------
    values : (H, W) array, metres; NaN/inf are nodata.
    valid : (H, W) bool or None; False marks nodata in addition to non-finite values.
    source : file name used in error messages.

    Returns
    -------
    elevation_m : (H, W) float32 filled, valid : (H, W) bool, fill_method : str ("" if nothing filled)
    """
    if values.ndim != 2:
        raise InputError(f"expected a 2-D elevation grid, got shape {values.shape}", source)
    check_dimensions(values.shape[0], values.shape[1], source)
    z = np.asarray(values, dtype=np.float64)
    ok = np.isfinite(z)
    if valid is not None:
        ok &= np.asarray(valid, dtype=bool)
    if not ok.any():
        if not np.isfinite(z).any():
            raise InputError("every sample is NaN or infinite", source)
        raise InputError("band 1 has no valid samples (all nodata)", source)
    n_ok = int(ok.sum())
    if n_ok < MIN_VALID_FRACTION * ok.size:
        raise InputError(
            f"only {n_ok} of {ok.size} samples are valid ({100.0 * n_ok / ok.size:.3g} %, below the "
            f"{100 * MIN_VALID_FRACTION:g} % terralod meshes); crop it to the data or check the nodata value",
            source,
        )
    zv = z[ok]
    if np.abs(zv).max() > 1e5:
        raise InputError(
            f"elevations reach {zv.min():.6g}..{zv.max():.6g} m, beyond any terrain; "
            "check the vertical scale or nodata value",
            source,
        )
    if ok.all():
        return z.astype(np.float32), ok, ""
    filled = fill_nodata(z, ok)
    n = int((~ok).sum())
    how = (
        f"{n} nodata cells ({100.0 * n / ok.size:.2f} %) filled with the nearest valid sample, "
        f"then relaxed by {FILL_SMOOTH_ITERATIONS} Laplace iterations"
    )
    return filled.astype(np.float32), ok, how


def fill_nodata(z: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Fill ``~valid`` cells of ``z`` (float64, (H, W)); valid cells are returned unchanged."""
    idx = ndimage.distance_transform_edt(~valid, return_distances=False, return_indices=True)
    out = z[idx[0], idx[1]].astype(np.float64)
    # Relax only inside holes; the valid rim stays fixed, so the membrane meets the data without a step.
    hr, hc = np.nonzero(~valid)
    return relax_holes(out, hr.astype(np.int64), hc.astype(np.int64), FILL_SMOOTH_ITERATIONS)


def nearest_valid_value(
    block_rc: tuple[int, int],
    n_blocks: tuple[int, int],
    centre_rc: tuple[float, float],
    has_valid: Callable[[int, int], bool],
    block: Callable[[int, int], tuple[np.ndarray, np.ndarray, int, int]],
) -> float | None:
    """The one value a window source gives a fill block far from every valid sample: the height of the
    valid sample nearest the block's centre ``centre_rc`` (row, column of the whole grid) among the blocks
    of the nearest ring of blocks around ``block_rc`` that holds one (ties: the lowest row, then column).
    ``has_valid(i, j)`` says whether block (i, j) holds a valid sample (the caller keeps a flag a block);
    ``block(i, j)`` reads it as (values, valid, first row, first column). Only a ring's perimeter is
    visited, a block at a time, so memory is one block whatever the distance. None: no block holds one."""
    br, bc = block_rc
    nbr, nbc = n_blocks
    cr, cc = centre_rc
    for k in range(1, max(nbr, nbc) + 1):
        best: tuple[float, int, int, float] | None = None
        ring = [(br - k, j) for j in range(bc - k, bc + k + 1)] + [
            (br + k, j) for j in range(bc - k, bc + k + 1)
        ]
        ring += [(i, bc - k) for i in range(br - k + 1, br + k)] + [
            (i, bc + k) for i in range(br - k + 1, br + k)
        ]
        for i, j in ring:
            if not (0 <= i < nbr and 0 <= j < nbc) or not has_valid(i, j):
                continue
            values, ok, ra, ca = block(i, j)
            rr, cc_ = np.nonzero(ok)
            d2 = (rr + ra - cr) ** 2 + (cc_ + ca - cc) ** 2
            m = int(np.lexsort((cc_ + ca, rr + ra, d2))[0])
            cand = (float(d2[m]), int(rr[m]) + ra, int(cc_[m]) + ca, float(values[rr[m], cc_[m]]))
            if best is None or cand[:3] < best[:3]:
                best = cand
        if best is not None:
            return best[3]
    return None
