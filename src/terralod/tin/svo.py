"""Scale selection by the smallest visible object (SVO): monotone MMQE and its projected length, or the
measured error of each scale.

Paper: ``../shared/papers/003_2a2cfcda929de24c.txt`` §2.3.2. Each scale S_s of a sub-block has an MMQE
(mean over its vertices of their minimum quadric error); made monotone, it falls as the scale gets finer.
A segment of length sqrt(MMQE) metres, parallel to the screen at the sub-block's centre, projects to

    L_px = sqrt(MMQE) · H / (2 · d · tan(fov_y / 2))

pixels (H viewport height in pixels, d the eye-to-centre distance in metres, fov_y the vertical field of
view). The sub-block is drawn at the coarsest scale with L_px ≤ N (N = 2 px in the paper's experiment);
the same screen-space rule as every other stage of terralod (DESIGN.md, "Screen-space error ρ").

Scale numbering (the paper's): S_0 is the most simplified version (the base mesh), S_n the full
resolution; ΔT_s takes S_s to S_{s+1}.

Deviations, and why:

- **Monotone by running maximum from fine to coarse.** §2.3.2 lifts any MMQE lower than the previous
  one (in collapse order) to that value; in scale order this is ``mono[s] = max(mmqe[s:])``.
- **Perspective only**, as the paper says; an orthographic camera has no distance to divide by.
- **A sub-block whose finest scale still projects above N** is drawn at its finest scale.
- **Measured error by default** (:func:`select_scales_measured`; ``error="measured"`` in
  :meth:`terralod.tin.DetailIncrementModel.scales_for_camera`). sqrt(MMQE) is an area-weighted *mean*
  squared distance over a sub-block's vertices: on the 513² Puget Sound crop (160 m spacing) it is 5–7 m
  at the base scale while the base is up to ~90 m off vertically, and a segment of it at a sub-block's
  centre (14 km away for an eye 300 m above the middle of the 82 km crop) never reaches 2 px, so a user
  zooming in saw no added detail. The default rule uses, per scale, the measured max vertical distance from
  the input points to that scale's surface (an upper bound, made monotone by the same running maximum;
  :func:`terralod.tin.qem.measured_errors`), seen from the nearest point of the sub-block's bounding
  box, as every other terralod stage does (DESIGN.md, "Screen-space error"): no drawn point is then more
  than N pixels off. The paper's rule stays available (``error="mmqe"``).
"""

from __future__ import annotations

import math

import numpy as np

__all__ = [
    "box_distance_m",
    "monotone_mmqe",
    "projected_px",
    "select_scale",
    "select_scales",
    "select_scales_measured",
    "svo_length_px",
]


def monotone_mmqe(mmqe_m2: np.ndarray) -> np.ndarray:
    """MMQE per scale made non-increasing from S_0 (coarsest) to S_n (finest).

    Parameters
    ----------
    mmqe_m2 : (n + 1,) float
        MMQE of scales S_0 … S_n, m².

    Returns
    -------
    (n + 1,) float64
        ``mono[s] = max(mmqe_m2[s:])``.
    """
    m = np.asarray(mmqe_m2, np.float64)
    return np.maximum.accumulate(m[::-1])[::-1].copy()


def projected_px(
    length_m: float | np.ndarray, distance_m: float | np.ndarray, fov_y_rad: float, height_px: float
) -> np.ndarray:
    """Projected length, pixels, of a screen-parallel segment of ``length_m`` metres at ``distance_m``."""
    d = np.asarray(distance_m, np.float64)
    length = np.asarray(length_m, np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):  # the eye on the segment: inf (0 for length 0)
        px = length * height_px / (2.0 * d * math.tan(0.5 * fov_y_rad))
    return np.where(length == 0.0, 0.0, px)


def box_distance_m(boxes_m: np.ndarray, eye_m: np.ndarray) -> np.ndarray:
    """(B,) distance, metres, from the eye to each box (west, south, low, east, north, high); 0 inside."""
    b = np.asarray(boxes_m, np.float64)
    e = np.asarray(eye_m, np.float64)[None, :]
    gap = np.maximum(np.maximum(b[:, :3] - e, e - b[:, 3:]), 0.0)
    return np.sqrt((gap * gap).sum(axis=1))


def select_scales_measured(
    error_m: np.ndarray,
    error_ptr: np.ndarray,
    distance_m: np.ndarray,
    fov_y_rad: float,
    height_px: float,
    threshold_px: float = 2.0,
) -> np.ndarray:
    """(B,) per sub-block, the coarsest scale whose measured error projects to at most ``threshold_px``.

    ``error_m[error_ptr[b] : error_ptr[b + 1]]`` is block b's non-increasing max vertical error of its
    scales S_0 … S_{n_b}, metres (0 at S_{n_b}); ``distance_m`` (B,) the eye's distance to each block,
    metres (the nearest point of its bounding box, so the bound holds over the whole block).
    """
    d = np.asarray(distance_m, np.float64)
    lim = threshold_px * 2.0 * np.maximum(d, 0.0) * math.tan(0.5 * fov_y_rad) / height_px
    out = np.empty(d.shape[0], np.int64)
    for b in range(d.shape[0]):
        e = error_m[error_ptr[b] : error_ptr[b + 1]]
        out[b] = min(int(np.searchsorted(-e, -lim[b], side="left")), e.size - 1)
    return out


def svo_length_px(
    mmqe_m2: float | np.ndarray, distance_m: float | np.ndarray, fov_y_rad: float, height_px: float
) -> np.ndarray:
    """Projected length, pixels, of a screen-parallel segment of sqrt(MMQE) metres at ``distance_m``."""
    d = np.maximum(np.asarray(distance_m, np.float64), np.finfo(np.float64).tiny)
    return np.sqrt(np.asarray(mmqe_m2, np.float64)) * height_px / (2.0 * d * math.tan(0.5 * fov_y_rad))


def select_scale(
    mono_m2: np.ndarray, distance_m: float, fov_y_rad: float, height_px: float, threshold_px: float = 2.0
) -> int:
    """Coarsest scale s with ``svo_length_px(mono_m2[s], …) <= threshold_px`` (the finest if none).

    ``mono_m2`` must be non-increasing (:func:`monotone_mmqe`).
    """
    # L_px <= N  <=>  MMQE <= (N · 2 d tan(fov/2) / H)²
    lim = threshold_px * 2.0 * max(float(distance_m), 0.0) * math.tan(0.5 * fov_y_rad) / height_px
    s = int(np.searchsorted(-np.asarray(mono_m2), -(lim * lim), side="left"))
    return min(s, len(mono_m2) - 1)


def select_scales(
    mono_m2: np.ndarray,
    mono_ptr: np.ndarray,
    centres_m: np.ndarray,
    eye_m: np.ndarray,
    fov_y_rad: float,
    height_px: float,
    threshold_px: float = 2.0,
) -> np.ndarray:
    """Per sub-block scales for a perspective camera (a pure query: no state is touched).

    Parameters
    ----------
    mono_m2 : (S,) float64
        Monotone MMQE of every sub-block's scales, concatenated; block b's are
        ``mono_m2[mono_ptr[b] : mono_ptr[b + 1]]`` (S_0 first), m².
    mono_ptr : (B + 1,) int64
        Offsets into ``mono_m2``.
    centres_m : (B, 3) float64
        Sub-block centres, world metres.
    eye_m : (3,) float
        Eye position, world metres.
    fov_y_rad : float
        Vertical field of view, radians, in (0, π).
    height_px : float
        Viewport height, pixels.
    threshold_px : float
        N, the largest allowed projected length of the SVO segment, pixels.

    Returns
    -------
    (B,) int64
        Scale index of each sub-block, 0 (base) … n_b (full resolution).
    """
    d = np.linalg.norm(np.asarray(centres_m, np.float64) - np.asarray(eye_m, np.float64)[None, :], axis=1)
    out = np.empty(d.shape[0], np.int64)
    for b in range(d.shape[0]):
        out[b] = select_scale(
            mono_m2[mono_ptr[b] : mono_ptr[b + 1]], float(d[b]), fov_y_rad, height_px, threshold_px
        )
    return out
