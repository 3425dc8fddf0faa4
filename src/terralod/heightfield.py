"""Heightfield: an elevation raster in metres with its ground frame, the one place where raster
(row, col) indices become world coordinates.

Conventions (DESIGN.md): x east, y north, z up, metres. Row 0 is the north edge. Sample (row, col) sits at
the centre of its pixel: ``x = transform.c + (col + 0.5) * dx`` and ``y = transform.f - (row + 0.5) * dy``.
The transform is always north-up and axis-aligned (readers normalise or refuse anything else).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from affine import Affine

from terralod.fill import prepare_elevation


@dataclass(frozen=True, eq=False)
class Heightfield:
    """An elevation grid with its georeferencing.

    Attributes
    ----------
    elevation_m : (H, W) float32
        Elevation in metres, row 0 north. Cells that were nodata/NaN in the source hold filled values
        (see :attr:`fill_method`) so meshing never sees a hole; ``valid`` remembers which they are.
    valid : (H, W) bool
        True where the source had a real sample.
    transform : affine.Affine
        Maps (col, row) pixel-corner coordinates to world metres; north-up (``b == d == 0``, ``e < 0``).
    crs : str or None
        WKT of the metric CRS of the world coordinates, None for un-georeferenced heightmaps (then the
        world frame is a local metric frame with its origin at the north-west corner).
    source : str
        Path or description of where the data came from.
    fill_method : str
        How nodata cells were filled, one line (empty when nothing was filled).
    notes : tuple of str
        Conversions applied on reading (reprojection, unit scaling), for ``terralod info``.
    source_nodata_fraction, margin_fraction : float
        After a reprojection: nodata of the source itself, and cells outside the source's footprint;
        ``nodata_fraction`` counts both.
    original_grid : terralod.io.raster.OriginalGrid or None
        After a reprojection: the source's own samples (its grid, mask, transform and CRS), which the
        builder measures every tile's error against (:mod:`terralod.pyramid.original`); None when this
        grid holds the source's samples themselves.
    """

    elevation_m: np.ndarray
    valid: np.ndarray
    transform: Affine
    crs: str | None = None
    source: str = "<array>"
    fill_method: str = ""
    notes: tuple[str, ...] = field(default_factory=tuple)
    #: nodata fraction of the source's own samples (set by a reader that resampled it; None: same as
    #: :attr:`nodata_fraction`)
    source_nodata_fraction: float | None = None
    #: fraction of this grid's cells outside the source's footprint (the margin a reprojection leaves)
    margin_fraction: float = 0.0
    #: the source's own samples when this grid resampled them (:class:`terralod.io.raster.OriginalGrid`)
    original_grid: Any = None

    def __post_init__(self) -> None:
        z = np.ascontiguousarray(self.elevation_m, dtype=np.float32)
        v = np.ascontiguousarray(self.valid, dtype=bool)
        if z.ndim != 2 or v.shape != z.shape:
            raise ValueError(f"Expected 2-D elevation and matching mask, got {z.shape} and {v.shape}")
        t = self.transform
        if t.b != 0 or t.d != 0 or t.a <= 0 or t.e >= 0:
            raise ValueError(f"Expected a north-up axis-aligned transform, got {tuple(t)[:6]}")
        object.__setattr__(self, "elevation_m", z)
        object.__setattr__(self, "valid", v)

    # -- shape and frame -------------------------------------------------------------------------------
    @property
    def shape(self) -> tuple[int, int]:
        """(rows, cols) = (height, width) in samples."""
        h, w = self.elevation_m.shape
        return int(h), int(w)

    @property
    def width(self) -> int:
        return int(self.elevation_m.shape[1])

    @property
    def height(self) -> int:
        return int(self.elevation_m.shape[0])

    @property
    def spacing_m(self) -> tuple[float, float]:
        """(dx, dy): ground distance between neighbouring samples east-west and north-south, metres."""
        return float(self.transform.a), float(-self.transform.e)

    @property
    def origin_m(self) -> tuple[float, float]:
        """World (x, y) of sample (row 0, col 0), the north-west sample centre, metres."""
        dx, dy = self.spacing_m
        return float(self.transform.c + 0.5 * dx), float(self.transform.f - 0.5 * dy)

    @property
    def bounds_m(self) -> tuple[float, float, float, float]:
        """(west, south, east, north) of the pixel footprint, metres."""
        t = self.transform
        return (t.c, t.f + self.height * t.e, t.c + self.width * t.a, t.f)

    @property
    def nodata_fraction(self) -> float:
        return float(1.0 - self.valid.mean()) if self.valid.size else 1.0

    def valid_range_m(self) -> tuple[float, float]:
        """(min, max) elevation over valid samples, metres."""
        z = self.elevation_m[self.valid]
        return float(z.min()), float(z.max())

    def world_xy(self, row: np.ndarray | float, col: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        """World (x, y) metres of (fractional) sample indices."""
        x0, y0 = self.origin_m
        dx, dy = self.spacing_m
        return x0 + np.asarray(col, dtype=np.float64) * dx, y0 - np.asarray(row, dtype=np.float64) * dy

    def sample_rc(self, x: np.ndarray | float, y: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        """Fractional (row, col) sample indices of world (x, y) metres; inverse of :meth:`world_xy`."""
        x0, y0 = self.origin_m
        dx, dy = self.spacing_m
        return (y0 - np.asarray(y, dtype=np.float64)) / dy, (np.asarray(x, dtype=np.float64) - x0) / dx

    def digest(self) -> str:
        """sha256 of elevation, mask, transform and CRS: identifies the source of a store for resume."""
        h = hashlib.sha256()
        h.update(np.ascontiguousarray(self.elevation_m).tobytes())
        h.update(np.packbits(self.valid).tobytes())
        h.update(repr(tuple(self.transform)[:6]).encode())
        h.update((self.crs or "").encode())
        return h.hexdigest()

    @classmethod
    def from_array(
        cls,
        elevation_m: np.ndarray,
        spacing_m: float | tuple[float, float] = 1.0,
        *,
        origin_m: tuple[float, float] = (0.0, 0.0),
        crs: str | None = None,
        source: str = "<array>",
        valid: np.ndarray | None = None,
    ) -> Heightfield:
        """Wrap an array (row 0 north) whose north-west pixel corner is at ``origin_m`` (west, north).

        NaN cells are treated as nodata and filled (see :func:`terralod.fill.fill_nodata`).
        """
        if isinstance(spacing_m, tuple | list | np.ndarray):
            dx, dy = spacing_m
        else:  # a scalar (Python or numpy)
            dx = dy = spacing_m
        z, ok, how = prepare_elevation(np.asarray(elevation_m), valid, source)
        t = Affine(float(dx), 0.0, float(origin_m[0]), 0.0, -float(dy), float(origin_m[1]))
        return cls(z, ok, t, crs=crs, source=source, fill_method=how)
