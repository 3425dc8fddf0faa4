"""The complex base TIN and its sub-blocks.

Paper: ``../shared/papers/003_2a2cfcda929de24c.txt`` §2.1: the points are split into four sub-blocks at
the midpoints of the bounding box, each is triangulated inside its own convex hull, the gaps between them
are filled from the hulls, and the sub-blocks' boundaries (external and internal) are kept out of the
simplification so that sub-blocks change scale independently without gaps.

Deviations, and why:

- **One global Delaunay, split afterwards.** Triangulating each sub-block alone and stitching the hulls
  (the paper) gives long thin gap triangles along the seams. Here the whole cloud gets one Delaunay
  triangulation (Triangle, or Qhull; see below) and each triangle goes to the sub-block holding its
  centroid. The sub-blocks then join exactly along shared edges (a polyline of the TIN, not a straight
  line) and the seam vertices, those used by triangles of two or more sub-blocks, are locked. Same
  guarantee, better triangles, no special seam code. A big cloud's one triangulation is itself computed
  in blocks, in parallel (threads or Dask workers), and joined exactly: :mod:`terralod.tin.delaunay_blocks`.
- **Triangulator.** Shewchuk's Triangle (the ``triangle`` package: divide and conquer, exact predicates)
  when it is installed, as the default set-up does; scipy's Qhull otherwise. The two give the same
  triangles for points in general position (tested); Triangle is about 10x faster (1 M points in 0.9 s
  against 8.4 s here), and Qhull was most of a cloud's build time. Triangle's licence forbids selling it
  or putting it in a commercial product without the author's permission: ``pip uninstall triangle`` (or
  :data:`ENGINE` = "qhull") gives the same TINs through Qhull alone.
- **k × k sub-blocks.** The paper uses 2 × 2; big clouds want more (each sub-block then holds fewer
  triangles, so a scale change rebuilds less). ``sub_blocks`` must be a square number. Block index
  ``row * k + col``, row 0 at the north edge, col 0 at the west edge (raster order, DESIGN.md).
- **Heightfields** are triangulated as their grid (two triangles a cell of four valid samples, the
  diagonal joining the pair of corners with the smaller height difference), not through Qhull: a grid is
  full of co-circular quadruples, where Delaunay is ambiguous and Qhull slow.

Every triangle comes out counter-clockwise in xy (x east, y north) with a positive area; zero-area
triangles (collinear hull points) are dropped and unused points (coincident duplicates Qhull skipped)
removed.
"""

from __future__ import annotations

import math
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import numpy as np

from terralod.errors import InputError
from terralod.kernels.qem import FREE, LOCKED, block_corner_bounds, edge_topology

__all__ = ["SubBlocks", "delaunay_tin", "grid_tin", "mesh_boundary_vertices", "split_sub_blocks"]

#: The triangulator of :func:`delaunay_tin`: "triangle" (Shewchuk's Triangle, when installed) or "qhull".
ENGINE = "triangle"


def _triangle_available() -> bool:
    try:
        import triangle  # noqa: F401
    except ImportError:
        return False
    return True


def _simplices(local: np.ndarray) -> np.ndarray:
    """Delaunay triangles (M, 3) int64 of distinct-enough xy points (centred), any orientation; empty when
    they are collinear."""
    if ENGINE == "triangle" and _triangle_available():
        import triangle

        out = triangle.triangulate({"vertices": local}, "Q")  # Q: quiet
        tris = out.get("triangles")
        return np.zeros((0, 3), np.int64) if tris is None else np.asarray(tris, np.int64)
    from scipy.spatial import Delaunay, QhullError

    try:
        return Delaunay(local).simplices.astype(np.int64)
    except QhullError:
        return np.zeros((0, 3), np.int64)


def _orient_ccw(xy: np.ndarray, tris: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Triangles made counter-clockwise; returns (tris, twice the xy area) with area > 0 kept
    (:func:`terralod.kernels.delaunay.orient_ccw`)."""
    from terralod.kernels.delaunay import orient_ccw

    return orient_ccw(np.ascontiguousarray(xy, np.float64), np.ascontiguousarray(tris, np.int64))


def _compact(vertices: np.ndarray, tris: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Drop unused vertices; returns (vertices, tris renumbered, kept old indices ascending)."""
    used = np.flatnonzero(np.bincount(tris.ravel(), minlength=vertices.shape[0]))
    remap = np.full(vertices.shape[0], -1, np.int64)
    remap[used] = np.arange(used.size)
    return vertices[used], remap[tris].astype(np.int32), used


def _check_manifold(tris: np.ndarray, source: str | None) -> None:
    """InputError unless every edge is used by one triangle, or by two with opposite directions (every
    directed edge once: then no edge has three triangles). One linear pass
    (:func:`terralod.kernels.qem.edge_topology`), no sort."""
    repeated, _ = edge_topology(np.ascontiguousarray(tris, np.int64), int(tris.max()) + 1)
    if repeated:
        raise InputError(
            "the triangulation has a repeated directed edge (inconsistent or non-manifold)", source
        )


def _block_simplices(local: np.ndarray, workers: int | None, executor: Any) -> np.ndarray | None:
    """The triangulation computed block by block (:mod:`terralod.tin.delaunay_blocks`) when the cloud is
    big enough for more than one block and Triangle is in use; None otherwise (one call)."""
    if not (ENGINE == "triangle" and _triangle_available()):
        return None
    from terralod.tin.delaunay_blocks import block_jobs, block_layout, block_triangles, fill_holes

    layout = block_layout(local)
    if layout.m == 1:
        return None
    jobs = block_jobs(local, layout)
    if executor is not None:
        results = list(executor(jobs, block_triangles))
    else:
        n_threads = max(1, min(workers or os.cpu_count() or 1, len(jobs)))
        with ThreadPoolExecutor(n_threads) as pool:  # Triangle runs without the GIL (ctypes)
            results = list(pool.map(block_triangles, jobs))
    return fill_holes(local, results)


def delaunay_tin(
    points_m: np.ndarray, *, source: str | None = None, workers: int | None = None, executor: Any = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Delaunay TIN of points (x, y, z metres) in xy.

    A cloud of 150 k points or more is triangulated (with Triangle) block by block on ``workers``
    threads, or on ``executor(jobs, fn)`` (Dask: :func:`terralod.tin.distributed.dask_executor`), and the
    blocks' pieces joined into the one Delaunay triangulation (:mod:`terralod.tin.delaunay_blocks`); the
    triangles do not depend on ``workers`` or ``executor``.

    Parameters
    ----------
    points_m : (N, 3) float64
        Finite points, metres, already thinned of duplicates (remaining coincident points are skipped).
    source : str, optional
        Named in error messages.
    workers : int, optional
        Threads for the blocks (default: the cores).
    executor : callable, optional
        ``executor(jobs, fn)`` returns ``[fn(job) for job in jobs]``, computed elsewhere.

    Returns
    -------
    vertices : (V, 3) float64
        The points used by the TIN, metres (a subset of ``points_m``, in input order).
    triangles : (M, 3) int32
        Counter-clockwise vertex triples, positive xy area, each starting at its smallest vertex, sorted
        (:func:`terralod.kernels.delaunay.canonical_order`): the same array for the same triangles,
        whichever way they were found.
    index : (V,) int64
        Row of ``points_m`` of each vertex.

    Raises
    ------
    InputError
        Fewer than 3 distinct points, or all points collinear.
    """
    n = points_m.shape[0]
    if n < 3:
        raise InputError(f"Expected at least 3 points with distinct xy to triangulate, got {n}", source)
    xy = points_m[:, :2]
    centre = 0.5 * (xy.min(axis=0) + xy.max(axis=0))
    local = xy - centre
    # at least 3 distinct xy: a point unlike the first, then one unlike both (no sort of the cloud)
    other = np.flatnonzero((local != local[0]).any(axis=1))
    third = other[(local[other] != local[other[0]]).any(axis=1)] if other.size else other
    if third.size == 0:
        raise InputError(
            f"Expected at least 3 points with distinct xy to triangulate, got {1 + min(other.size, 1)}",
            source,
        )
    local = np.ascontiguousarray(local)
    simplices = _block_simplices(local, workers, executor)
    if simplices is None:
        simplices = _simplices(local)
    if simplices.shape[0] == 0:
        raise InputError(
            "the points are collinear (or nearly so) in xy: a TIN needs points spanning an area", source
        )
    tris, _ = _orient_ccw(local, simplices)
    if tris.shape[0] == 0:
        raise InputError("the points are collinear in xy: a TIN needs points spanning an area", source)
    vertices, tris, used = _compact(points_m, tris)
    _check_manifold(tris, source)
    # one order for one set of triangles, whichever way they were found (one call, blocks, Qhull)
    from terralod.kernels.delaunay import canonical_order

    tris = canonical_order(tris, vertices.shape[0])
    return np.ascontiguousarray(vertices), tris, used


def grid_tin(
    elevation_m: np.ndarray, valid: np.ndarray, x_m: np.ndarray, y_m: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Grid TIN of a raster: two triangles per cell whose four samples are valid.

    Parameters
    ----------
    elevation_m : (H, W) float
        Elevations, metres, row 0 north.
    valid : (H, W) bool
        Samples to use.
    x_m : (W,) float64
        World x (east) of each column, metres.
    y_m : (H,) float64
        World y (north) of each row, metres (decreasing: row 0 is north).

    Returns
    -------
    vertices (V, 3) float64 metres, triangles (M, 3) int32 counter-clockwise, sample index (V,) int64
    (row * W + col) of each vertex.

    Raises
    ------
    InputError
        No cell has four valid samples.
    """
    h, w = elevation_m.shape
    if h < 2 or w < 2:
        raise InputError(f"Expected a heightfield of at least 2 x 2 samples, got {h} x {w}")
    z = np.asarray(elevation_m, np.float64)
    ok = np.asarray(valid, bool) & np.isfinite(z)
    cell = ok[:-1, :-1] & ok[:-1, 1:] & ok[1:, :-1] & ok[1:, 1:]
    r, c = np.nonzero(cell)
    if r.size == 0:
        raise InputError("the heightfield has no cell with four valid samples to triangulate")
    nw = r * w + c
    ne = nw + 1
    sw = nw + w
    se = sw + 1
    zf = z.ravel()
    # Diagonal joining the corner pair with the smaller height difference.
    main = np.abs(zf[nw] - zf[se]) <= np.abs(zf[ne] - zf[sw])
    t1 = np.where(main[:, None], np.stack([nw, sw, se], 1), np.stack([nw, sw, ne], 1))
    t2 = np.where(main[:, None], np.stack([nw, se, ne], 1), np.stack([sw, se, ne], 1))
    tris = np.concatenate([t1, t2]).astype(np.int64)
    # Cell order (row-major), first then second triangle of each cell: deterministic and cache-friendly.
    tris = tris.reshape(2, -1, 3).transpose(1, 0, 2).reshape(-1, 3)
    xx, yy = np.meshgrid(np.asarray(x_m, np.float64), np.asarray(y_m, np.float64))
    pts = np.stack([xx.ravel(), yy.ravel(), zf], 1)
    vertices, tris32, used = _compact(pts, tris)
    return np.ascontiguousarray(vertices), tris32, used


def mesh_boundary_vertices(triangles: np.ndarray, n_vertices: int) -> np.ndarray:
    """(V,) bool: vertices on an edge used by a single triangle (the TIN's outline, holes included)."""
    if len(triangles) == 0:
        return np.zeros(n_vertices, bool)
    _, out = edge_topology(np.ascontiguousarray(triangles, np.int64), int(n_vertices))
    return out


@dataclass(frozen=True)
class SubBlocks:
    """A k × k split of a TIN's triangles, with the locked vertices.

    Attributes
    ----------
    k : int
        Sub-blocks per side; ``k * k`` blocks, index ``row * k + col`` (row 0 north, col 0 west).
    tri_block : (M,) int32
        Block of each triangle (the cell holding its xy centroid).
    vert_block : (V,) int32
        Block of each FREE vertex; -1 for LOCKED vertices (they may touch several blocks).
    kind : (V,) uint8
        FREE (interior of one block and of the TIN) or LOCKED (TIN outline or block seam).
    bounds_m : (k * k, 4) float64
        (west, south, east, north) of each block's cell, metres.
    centre_m : (k * k, 3) float64
        Centre of each block's triangles: the middle of their xy bounding box and the mean height of
        their corners (the paper's "centre of the terrain mesh" for the SVO segment), metres.
    """

    k: int
    tri_block: np.ndarray
    vert_block: np.ndarray
    kind: np.ndarray
    bounds_m: np.ndarray
    centre_m: np.ndarray

    @property
    def n_blocks(self) -> int:
        return self.k * self.k


def blocks_per_side(sub_blocks: int) -> int:
    """k for ``sub_blocks = k * k``; InputError otherwise."""
    if isinstance(sub_blocks, bool) or not isinstance(sub_blocks, int | np.integer) or sub_blocks < 1:
        raise InputError(f"Expected sub_blocks a square number >= 1 (1, 4, 9, 16, …), got {sub_blocks!r}")
    k = math.isqrt(int(sub_blocks))
    if k * k != sub_blocks:
        raise InputError(f"Expected sub_blocks a square number (1, 4, 9, 16, …), got {sub_blocks}")
    if k > 255:
        raise InputError(f"Expected at most 255 x 255 sub-blocks, got {k} x {k}")
    return k


def split_sub_blocks(vertices: np.ndarray, triangles: np.ndarray, k: int) -> SubBlocks:
    """Assign triangles to a k × k grid of sub-blocks by centroid and lock outline and seam vertices.

    Parameters
    ----------
    vertices : (V, 3) float64
        Metres.
    triangles : (M, 3) int
        Counter-clockwise triples.
    k : int
        Blocks per side.
    """
    n = vertices.shape[0]
    xy = vertices[:, :2]
    lo = xy.min(axis=0)
    hi = xy.max(axis=0)
    span = np.maximum(hi - lo, np.finfo(np.float64).tiny)
    cen = xy[triangles].mean(axis=1)
    col = np.clip(((cen[:, 0] - lo[0]) / span[0] * k).astype(np.int64), 0, k - 1)
    row = np.clip(((hi[1] - cen[:, 1]) / span[1] * k).astype(np.int64), 0, k - 1)
    tri_block = (row * k + col).astype(np.int32)

    t = triangles.astype(np.int64).ravel()
    tb = np.repeat(tri_block, 3)
    nb = k * k
    plo, phi, bmin, bmax = block_corner_bounds(np.ascontiguousarray(vertices, np.float64),
                                               np.ascontiguousarray(triangles, np.int64), tri_block, nb)  # fmt: skip
    locked = (bmin != bmax) | mesh_boundary_vertices(triangles, n) | (bmax < 0)
    kind = np.where(locked, LOCKED, FREE).astype(np.uint8)
    vert_block = np.where(locked, -1, bmin).astype(np.int32)

    r, c = np.divmod(np.arange(nb), k)
    bounds = np.stack(
        [
            lo[0] + span[0] * c / k,
            hi[1] - span[1] * (r + 1) / k,
            lo[0] + span[0] * (c + 1) / k,
            hi[1] - span[1] * r / k,
        ],
        axis=1,
    )
    # Centres from the triangle corners of each block (a vertex counts once per triangle using it).
    pmin, pmax = plo[:, :2], phi[:, :2]
    cnt = np.bincount(tb, minlength=nb)
    zsum = np.bincount(tb, weights=vertices[t, 2], minlength=nb)
    centre = np.empty((nb, 3), np.float64)
    has = cnt > 0
    centre[has, :2] = 0.5 * (pmin[has] + pmax[has])
    centre[has, 2] = zsum[has] / cnt[has]
    centre[~has, :2] = 0.5 * (bounds[~has, :2] + bounds[~has, 2:])
    centre[~has, 2] = vertices[:, 2].mean()
    return SubBlocks(k, tri_block, vert_block, kind, bounds, centre)
