"""A LiDAR survey pair as two heightfields on one grid, for ``terralod change``.

Each side is a LAS/LAZ file, a folder of them or a quoted glob (:func:`terralod.tin.pointcloud.las_inputs`),
read by :func:`terralod.tin.pointcloud.read_las_survey` with the TIN build's ground rule: the ground points
(class 2) when the survey is classified, else every point. The rule that turns points into cells:

- the points of each survey are joined into a Delaunay triangulation (the TIN's linear surface) and that
  surface is read at the centre of every cell;
- the spacing is ``spacing_m`` when given, else the one the sparser survey's density supports: the
  square root of (its convex hull's area / its points), rounded up to a step of 1, 1.5, 2, 2.5, 3, 4, 5
  or 7.5 × 10^k m, so a cell holds about one point or more;
- both surveys are read on one grid: the intersection of their extents (bounding boxes), snapped to whole
  multiples of the spacing; change is measured only where both surveys are;
- a cell is nodata outside a survey's triangulation, and in a triangle with a side longer than
  :data:`MAX_EDGE_SPACINGS` spacings (a gap in the ground points: a building, water, a tree's shadow),
  which the surface would otherwise bridge with a flat facet.

The two surveys must be in one CRS: a side in another is refused in one line naming its first file.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from terralod.errors import InputError

__all__ = ["MAX_EDGE_SPACINGS", "LidarGrid", "grid_survey_pair", "is_lidar_input", "nice_spacing_m"]

#: A cell in a triangle with a side longer than this many spacings is nodata.
MAX_EDGE_SPACINGS = 3.0
#: Cells sampled per block (bounds the memory of the point location).
_BLOCK_CELLS = 1 << 20
_STEPS = (1.0, 1.5, 2.0, 2.5, 3.0, 4.0, 5.0, 7.5, 10.0)


def is_lidar_input(path: str | os.PathLike[str]) -> bool:
    """A LAS/LAZ file, a folder holding one, or a glob matching one."""
    import glob

    text = str(path)
    p = Path(text)
    suffixes = (".las", ".laz")
    if p.is_dir():
        return any(q.suffix.lower() in suffixes for q in p.iterdir())
    if any(ch in text for ch in "*?[") and not p.exists():
        return any(Path(q).suffix.lower() in suffixes for q in glob.glob(text))
    return p.suffix.lower() in suffixes


def nice_spacing_m(raw_m: float) -> float:
    """``raw_m`` rounded up to 1, 1.5, 2, 2.5, 3, 4, 5 or 7.5 × 10^k."""
    if not (raw_m > 0 and math.isfinite(raw_m)):
        raise ValueError(f"spacing {raw_m!r} is not a positive number")
    k = math.floor(math.log10(raw_m))
    for s in _STEPS:
        v = s * 10.0**k
        if v >= raw_m * (1 - 1e-9):
            return float(f"{v:.6g}")
    return float(f"{10.0 ** (k + 1):.6g}")


@dataclass(frozen=True)
class LidarGrid:
    """The two gridded surveys and the rule that made them (``statement``: one plain sentence)."""

    before: Any  # Heightfield
    after: Any
    spacing_m: float
    spacing_source: str  # "given" or "point density"
    points: tuple[int, int]
    points_per_cell: tuple[float, float]
    statement: str
    #: each survey's LAS/LAZ files (what a continuous-scale TIN of it is built from: the site's 3D Tiles)
    files: tuple[tuple[str, ...], ...] = ()
    crs: Any = None

    def as_dict(self) -> dict[str, Any]:
        return {
            "rule": "ground points (class 2 when classified) -> Delaunay triangulation -> its linear surface "
            "read at cell centres; grid: the intersection of both surveys' extents; nodata outside a "
            f"triangulation or in a triangle with a side over {MAX_EDGE_SPACINGS:g} spacings",
            "spacing_m": self.spacing_m,
            "spacing_source": self.spacing_source,
            "points": list(self.points),
            "points_per_cell": [round(v, 3) for v in self.points_per_cell],
            "max_edge_m": MAX_EDGE_SPACINGS * self.spacing_m,
            "statement": self.statement,
        }


def _hull_area_m2(xy: np.ndarray) -> float:
    from scipy.spatial import ConvexHull

    return float(ConvexHull(xy).volume)  # a 2-D hull's "volume" is its area


def sample_tin(xyz: np.ndarray, xc: np.ndarray, yc: np.ndarray, max_edge_m: float) -> np.ndarray:
    """The Delaunay triangulation of ``xyz``'s linear surface at the grid of cell centres ``xc`` (W,) ×
    ``yc`` (H,): (H, W) float64, NaN outside the triangulation and in triangles with a side over
    ``max_edge_m``."""
    from scipy.spatial import Delaunay

    tri = Delaunay(xyz[:, :2])
    s = tri.simplices
    p = xyz[:, :2]
    edge = np.max(np.stack([np.hypot(*(p[s[:, i]] - p[s[:, (i + 1) % 3]]).T) for i in range(3)]), axis=0)
    ok_tri = edge <= max_edge_m
    h, w = yc.size, xc.size
    out = np.full(h * w, np.nan)
    rows = max(1, _BLOCK_CELLS // max(w, 1))
    for r0 in range(0, h, rows):
        gx, gy = np.meshgrid(xc, yc[r0 : r0 + rows])
        q = np.c_[gx.ravel(), gy.ravel()]
        t = tri.find_simplex(q)
        inside = t >= 0
        inside[inside] = ok_tri[t[inside]]
        ti = t[inside]
        tr = tri.transform[ti]  # (n, 3, 2): inverse affine and the third vertex
        b = np.einsum("nij,nj->ni", tr[:, :2], q[inside] - tr[:, 2])
        bary = np.c_[b, 1.0 - b.sum(axis=1)]
        z = np.einsum("ni,ni->n", bary, xyz[s[ti], 2])
        block = np.full(q.shape[0], np.nan)
        block[inside] = z
        out[r0 * w : r0 * w + q.shape[0]] = block
    return out.reshape(h, w)


def grid_survey_pair(
    before: str, after: str, *, spacing_m: float | None = None, crs: Any = None
) -> LidarGrid:
    """Read the LiDAR surveys ``before`` and ``after`` (a file, folder or glob each) and grid both on one
    grid by the module's rule."""
    from affine import Affine

    from terralod.io.georef import describe_crs, to_crs
    from terralod.io.raster import georeferenced_heightfield
    from terralod.tin.pointcloud import las_inputs, read_las_survey

    files = [las_inputs([before]), las_inputs([after])]
    clouds = [read_las_survey(f, crs=crs) for f in files]
    a, b = clouds
    if (a.crs is None) != (b.crs is None) or (
        a.crs is not None and to_crs(a.crs, str(files[0][0])) != to_crs(b.crs, str(files[1][0]))
    ):

        def label(c: str | None) -> str:
            return "none" if c is None else describe_crs(c)

        raise InputError(
            f"its CRS ({label(b.crs)}) differs from BEFORE's ({label(a.crs)}); the two surveys must share one "
            "CRS (reproject one, or give --crs for both)",
            str(files[1][0]),
        )
    if a.crs is None:
        raise InputError("has no CRS; give --crs so the surveys can be placed and compared", str(files[0][0]))
    n = (a.xyz_m.shape[0], b.xyz_m.shape[0])
    for f, c in zip(files, clouds, strict=True):
        if c.xyz_m.shape[0] < 3:
            raise InputError("has fewer than 3 ground points: nothing to grid", str(f[0]))
    density_m = [math.sqrt(_hull_area_m2(c.xyz_m[:, :2]) / c.xyz_m.shape[0]) for c in clouds]
    if spacing_m is None:
        spacing = nice_spacing_m(max(density_m))
        source = "point density"
    else:
        spacing = float(spacing_m)
        source = "given"
    lo = np.maximum(a.xyz_m[:, :2].min(axis=0), b.xyz_m[:, :2].min(axis=0))
    hi = np.minimum(a.xyz_m[:, :2].max(axis=0), b.xyz_m[:, :2].max(axis=0))
    if not np.all(hi - lo >= spacing):
        raise InputError(
            f"does not overlap BEFORE by one {spacing:g} m cell; the surveys must cover the same area",
            str(files[1][0]),
        )
    x0 = math.floor(lo[0] / spacing) * spacing
    y1 = math.ceil(hi[1] / spacing) * spacing
    w = max(1, math.ceil((hi[0] - x0) / spacing - 1e-9))
    h = max(1, math.ceil((y1 - lo[1]) / spacing - 1e-9))
    xc = x0 + (np.arange(w) + 0.5) * spacing
    yc = y1 - (np.arange(h) + 0.5) * spacing
    t = Affine(spacing, 0.0, x0, 0.0, -spacing, y1)
    max_edge = MAX_EDGE_SPACINGS * spacing
    hfs = []
    for given, f, c, which in zip((before, after), files, clouds, ("BEFORE", "AFTER"), strict=True):
        z = sample_tin(c.xyz_m, xc, yc, max_edge)
        ok = np.isfinite(z)
        if not ok.any():
            raise InputError(f"{which}: no cell of the common grid lies in its ground surface", str(f[0]))
        # a survey of several files by what was given (no slash: the summary names inputs by file name)
        name = (
            str(f[0]) if len(f) == 1 else f"{Path(str(given).rstrip('/')).name} ({len(f)} point-cloud files)"
        )
        hfs.append(georeferenced_heightfield(np.where(ok, z, np.nan), ok, t, a.crs, name, notes=c.notes))
    # points per cell: over each survey's own hull (what the density supports), not the common grid
    ppc = tuple(float((spacing / d) ** 2) for d in density_m)
    kind = (
        "ground points (class 2)"
        if a.classified or b.classified
        else "all points (the surveys are not classified)"
    )
    statement = (
        f"{kind} of each survey ({n[0]:,} and {n[1]:,}), joined into a surface of triangles and read every "
        f"{spacing:g} m ({'the spacing given' if source == 'given' else 'the spacing their density supports'}"
        f": {ppc[0]:.1f} and {ppc[1]:.1f} points per cell) on one grid over the area both cover; cells in a "
        f"triangle with a side over {max_edge:g} m (a gap in the ground points) or outside a survey are left out"
    )
    return LidarGrid(hfs[0], hfs[1], spacing, source, n, ppc, statement,
                     tuple(tuple(str(q) for q in f) for f in files), crs)  # fmt: skip
