"""Surface-vs-heightfield error: the measured number every tile of the store carries.

For a triangle mesh and the source heightfield, over every *covered* source sample (valid, and inside or
on the boundary of at least one triangle's XY projection):

- vertical error ``|z_sample - z_surface(x, y)|``; where the mesh overlaps itself (folds, triangle soups)
  the covering triangle with the smallest vertical distance is used; on a shared edge every covering
  triangle gives the same value up to rounding;
- one-sided Hausdorff distance: the max over covered samples of the 3D distance from the sample point to
  the closest point of the mesh (all triangles, exact point-triangle distance). It never exceeds the max
  vertical error.

The kernels are in :mod:`terralod.kernels.error` (pure, numba, GIL-free); this module validates input
and converts frames. See DESIGN.md, "Errors are measured, never assumed".
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from terralod.heightfield import Heightfield
from terralod.kernels.error import _KEEP_SAMPLES, changed_rows, tile_error, tile_error_rows

__all__ = ["ErrorReport", "measure_error", "measure_error_window", "measure_error_window_series"]


@dataclass(frozen=True)
class ErrorReport:
    """Measured error of a mesh against the source samples it covers.

    Attributes
    ----------
    max_vertical_m : float
        Largest vertical distance between a covered sample and the surface above/below it, metres.
    rms_vertical_m : float
        Root mean square of the vertical distances over covered samples, metres.
    hausdorff_m : float
        One-sided Hausdorff distance, samples to surface (3D, exact), metres; ``<= max_vertical_m``.
    n_samples : int
        Number of covered samples measured (0 when the mesh covers none; then every error is 0).
    worst_vertical_rc : (int, int) or None
        (row, col) of a sample attaining ``max_vertical_m`` (heightfield or window indices), None if
        ``n_samples == 0``.
    worst_hausdorff_rc : (int, int) or None
        (row, col) of a sample attaining ``hausdorff_m``, None if ``n_samples == 0``.
    """

    max_vertical_m: float
    rms_vertical_m: float
    hausdorff_m: float
    n_samples: int
    worst_vertical_rc: tuple[int, int] | None = None
    worst_hausdorff_rc: tuple[int, int] | None = None


def _check_mesh(vertices: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) float64 and (K, 3) int64 C-contiguous copies/views; ValueError on bad shapes or values."""
    v = np.asarray(vertices)
    t = np.asarray(triangles)
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"Expected vertices of shape (N, 3), got {v.shape}")
    if not (np.issubdtype(v.dtype, np.floating) or np.issubdtype(v.dtype, np.integer)):
        raise ValueError(f"Expected numeric vertices, got dtype {v.dtype}")
    if t.ndim != 2 or t.shape[1] != 3:
        raise ValueError(f"Expected triangles of shape (K, 3), got {t.shape}")
    if t.size and not np.issubdtype(t.dtype, np.integer):
        raise ValueError(f"Expected integer triangle indices, got dtype {t.dtype}")
    v = np.ascontiguousarray(v, dtype=np.float64)
    t = np.ascontiguousarray(t, dtype=np.int64)
    if not np.isfinite(v).all():
        bad = int(np.flatnonzero(~np.isfinite(v).all(axis=1))[0])
        raise ValueError(f"Expected finite vertex coordinates, got {v[bad].tolist()} at vertex {bad}")
    if t.size:
        lo, hi = int(t.min()), int(t.max())
        if lo < 0 or hi >= v.shape[0]:
            raise ValueError(f"Expected triangle indices in [0, {v.shape[0]}), got range [{lo}, {hi}]")
    return v, t


def _report(out: tuple[float, ...], r0: int = 0, c0: int = 0) -> ErrorReport:
    max_v, sumsq, n, hd, wvr, wvc, whr, whc = out
    n = int(n)
    if n == 0:
        return ErrorReport(0.0, 0.0, 0.0, 0)
    return ErrorReport(
        max_vertical_m=float(max_v),
        rms_vertical_m=math.sqrt(float(sumsq) / n),
        hausdorff_m=float(hd),
        n_samples=n,
        worst_vertical_rc=(int(wvr) + r0, int(wvc) + c0),
        worst_hausdorff_rc=(int(whr) + r0, int(whc) + c0),
    )


def measure_error_window(
    verts_local: np.ndarray,
    tris: np.ndarray,
    z: np.ndarray,
    valid: np.ndarray,
    dx: float,
    dy: float,
    *,
    check: bool = True,
) -> ErrorReport:
    """Error of a mesh in a window's local frame against the window's samples (the tile builder's call).

    Parameters
    ----------
    verts_local : (N, 3) float
        Vertices, metres, in the window frame: X = col * dx (east), Y = row * dy (south-positive; the
        frame is mirrored, distances are not), Z = elevation. Sample (r, c) sits at (c*dx, r*dy, z[r, c]).
    tris : (K, 3) integer
        Vertex indices in [0, N); either winding.
    z : (h, w) float
        Window elevations, metres, row 0 north (converted to float32; NaN samples are ignored).
    valid : (h, w) bool
        Samples to measure; False samples are ignored.
    dx, dy : float
        Sample spacing east-west and north-south, metres.
    check : bool
        False skips the checks of the mesh, for a caller that made it (the builder, per tile: the checks
        and an int64 copy of the triangles cost about a fifth of a 65² tile's measure, held under the GIL):
        then ``verts_local`` must be C-contiguous finite float64 and ``tris`` C-contiguous integers in
        range.

    Returns
    -------
    ErrorReport
        With worst-sample indices in window (row, col).

    Raises
    ------
    ValueError
        On bad shapes, non-finite vertices, indices out of range or non-positive spacing.
    """
    v, t = _check_mesh(verts_local, tris) if check else (verts_local, tris)
    zz, ok = _check_window(z, valid, dx, dy)
    return _report(tile_error(v, t, zz, ok, float(dx), float(dy)))


def _check_window(z: np.ndarray, valid: np.ndarray, dx: float, dy: float) -> tuple[np.ndarray, np.ndarray]:
    """(float32 elevations, bool mask), contiguous; ValueError on mismatched shapes or a bad spacing."""
    zz = np.ascontiguousarray(z, dtype=np.float32)
    ok = np.ascontiguousarray(valid, dtype=np.bool_)
    if zz.ndim != 2 or ok.shape != zz.shape:
        raise ValueError(
            f"Expected 2-D elevations and a mask of the same shape, got {zz.shape} and {ok.shape}"
        )
    if not (dx > 0 and dy > 0 and math.isfinite(dx) and math.isfinite(dy)):
        raise ValueError(f"Expected positive finite spacing (dx, dy) in metres, got ({dx}, {dy})")
    return zz, ok


def measure_error_window_series(
    meshes: list[tuple[np.ndarray, np.ndarray]],
    z: np.ndarray,
    valid: np.ndarray,
    dx: float,
    dy: float,
) -> list[ErrorReport]:
    """:func:`measure_error_window` of each (verts_local, tris) of ``meshes`` on one window, bit for bit,
    cheaper when consecutive meshes differ in a few triangles (the candidates of a tile mesher).

    Each mesh is measured over every covered sample as :func:`measure_error_window` does; only the
    per-sample vertical errors are carried from one mesh to the next: where a mesh has the previous one's
    vertex and triangle counts, the rows that a triangle differing between the two (its indices or a
    vertex's coordinates) reaches in either mesh are rasterised again (with a row of margin), and the
    rest of the measure (statistics, Hausdorff distances) runs on the whole window (see
    :func:`terralod.kernels.error.tile_error_rows`). Windows of over 2^21 samples are measured one by one.
    """
    zz, ok = _check_window(z, valid, dx, dy)
    h, w = zz.shape
    if h * w > _KEEP_SAMPLES:
        return [measure_error_window(v, t, zz, ok, dx, dy) for v, t in meshes]
    vall = np.empty(h * w, np.float64)
    out = []
    prev: tuple[np.ndarray, np.ndarray] | None = None
    for verts, tris in meshes:
        v, t = _check_mesh(verts, tris)
        dirty = _changed_rows(prev, v, t, float(dy), h)
        out.append(_report(tile_error_rows(v, t, zz, ok, float(dx), float(dy), vall, dirty)))
        prev = (v, t)
    return out


def _changed_rows(
    prev: tuple[np.ndarray, np.ndarray] | None, v: np.ndarray, t: np.ndarray, dy: float, h: int
) -> np.ndarray:
    """(h,) bool: the window rows that the triangles differing between ``prev`` and (v, t) reach in either
    mesh, with a row of margin; every row when the counts differ or there is no ``prev``."""
    if prev is None or prev[0].shape != v.shape or prev[1].shape != t.shape:
        return np.ones(h, np.bool_)
    pv, pt = prev
    rows: np.ndarray = changed_rows(pv, pt, v, t, float(dy), int(h))
    return rows


def measure_error(
    vertices: np.ndarray,
    triangles: np.ndarray,
    heightfield: Heightfield,
    *,
    mask: np.ndarray | None = None,
) -> ErrorReport:
    """Error of a mesh in world coordinates against the heightfield samples it covers.

    Parameters
    ----------
    vertices : (N, 3) float
        World metres: x east, y north, z up (the frame of :meth:`Heightfield.world_xy`).
    triangles : (K, 3) integer
        Vertex indices in [0, N); either winding.
    heightfield : Heightfield
        The source; only its valid samples are measured.
    mask : (H, W) bool, optional
        Further restricts the measured samples (True = measure), e.g. to one tile's footprint.

    Returns
    -------
    ErrorReport
        With worst-sample indices in heightfield (row, col).

    Raises
    ------
    ValueError
        On bad shapes, non-finite vertices, indices out of range, or a mask of the wrong shape.

    Notes
    -----
    Vertices are converted to fractional sample indices with :meth:`Heightfield.sample_rc`; the coverage
    test puts a vertex within 1e-7 samples of a sample on it, so a mesh whose vertices sit on samples
    (made with :meth:`Heightfield.world_xy`) covers exactly the samples on its outline, whatever the
    georeferencing. For vertices off the sample lattice, a sample lying exactly on an outer edge is
    decided by the rounded coordinates (world coordinates of 1e6 m carry about 1e-10 m of rounding).
    The source is cropped to the mesh's bounding box plus one sample before measuring.
    """
    v, t = _check_mesh(vertices, triangles)
    ok = heightfield.valid
    if mask is not None:
        m = np.asarray(mask)
        if m.shape != heightfield.shape:
            raise ValueError(f"Expected a mask of shape {heightfield.shape}, got {m.shape}")
        ok = ok & m.astype(bool)
    used = np.unique(t) if t.size else np.empty(0, np.int64)
    if used.size == 0:
        return ErrorReport(0.0, 0.0, 0.0, 0)
    rows, cols = heightfield.sample_rc(v[:, 0], v[:, 1])
    # Crop to the used vertices' bounding box, one sample wider for rounding.
    h, w = heightfield.shape
    r0 = max(int(math.floor(rows[used].min())) - 1, 0)
    r1 = min(int(math.ceil(rows[used].max())) + 1, h - 1)
    c0 = max(int(math.floor(cols[used].min())) - 1, 0)
    c1 = min(int(math.ceil(cols[used].max())) + 1, w - 1)
    if r0 > r1 or c0 > c1:
        return ErrorReport(0.0, 0.0, 0.0, 0)
    dx, dy = heightfield.spacing_m
    local = np.empty_like(v)
    local[:, 0] = (cols - c0) * dx
    local[:, 1] = (rows - r0) * dy
    local[:, 2] = v[:, 2]
    # C-contiguous copies: the kernel's C-layout build is faster than a strided view, copy included.
    z = np.ascontiguousarray(heightfield.elevation_m[r0 : r1 + 1, c0 : c1 + 1])
    out = tile_error(local, t, z, np.ascontiguousarray(ok[r0 : r1 + 1, c0 : c1 + 1]), float(dx), float(dy))
    return _report(out, r0, c0)
