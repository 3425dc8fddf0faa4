"""Per-vertex normals of stitched tiles, continuous across tile borders.

Implements ``../shared/papers/002_037d1654b87e3b6a.txt`` §3.4. A vertex normal is the normalised sum of
the area-weighted face normals (cross(b - a, c - a) / 2) of every triangle that contains the vertex's
position — in its own tile *and* in the neighbouring tiles across the border (the paper's "8 directions"
around a boundary vertex). Where the neighbour is coarser and has no vertex at that position (a
T-junction after stitching), the neighbour's triangle whose boundary segment contains the position is
counted whole: the paper's padding by "analogous subdivision" splits that triangle at the position into two
coplanar halves whose area-weighted normals add up to the whole triangle's. Where every tile around a
vertex has the same LoD this is exactly the normal of the merged uniform-LoD mesh (table 2's reference).

Deviations (and why): the paper sums 8 fixed grid directions; we sum the incident triangles, which is the
same stencil on a regular grid and also works for relocated (cohesion-map) vertices and for the fan
triangles the stitcher inserts. Interior normals are computed once per tile geometry and only the
triangles touching the boundary are re-summed after stitching (a patch, not a recomputation).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping

import numpy as np

from terralod.kernels.stitch import (
    add_edge_contributions,
    normal_sums,
    normalize_all,
    normalize_rows,
    triangle_cross,
)

__all__ = [
    "boundary_normals",
    "edge_tables",
    "reference_normals",
    "tile_local_normals",
]


def tile_local_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(N, 3) float32 area-weighted normals from the tile's own triangles only (the "conventional" method)."""
    v = np.ascontiguousarray(vertices, dtype=np.float64)
    t = np.ascontiguousarray(triangles, dtype=np.int64)
    return normalize_all(normal_sums(v, t))


def edge_tables(
    vertices: np.ndarray, triangles: np.ndarray, sums: np.ndarray, edge_vid: np.ndarray, seg_tri: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """What a neighbour needs from one edge of this tile: vertex sums S (m, 3) and segment-triangle terms G (m-1, 3)."""
    s = sums[edge_vid] if edge_vid.size else np.zeros((0, 3))
    g = triangle_cross(vertices, triangles, seg_tri) if seg_tri.size else np.zeros((0, 3))
    return np.ascontiguousarray(s), g


def boundary_normals(
    geometry_normals_: np.ndarray,
    sums: np.ndarray,
    boundary_vid: np.ndarray,
    contributions: Iterable[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]],
    tol: float,
) -> np.ndarray:
    """Final normals: interior from the tile's own triangles, boundary vertices with the neighbours' terms.

    ``contributions`` yields ``(t_tab, S_tab, G_tab, t_query, rows)`` per (edge, neighbour) pair: the
    neighbour's edge table and the positions of this tile's vertices on that edge with their rows in
    ``boundary_vid``. Returns a new (N, 3) float32 array.
    """
    acc = sums[boundary_vid]
    for t_tab, s_tab, g_tab, t_q, rows in contributions:
        add_edge_contributions(t_tab, s_tab, g_tab, t_q, rows, tol, acc)
    out = geometry_normals_.copy()
    tmp = np.empty((boundary_vid.size, 3), np.float32)
    normalize_rows(acc, np.arange(boundary_vid.size), tmp)
    out[boundary_vid] = tmp
    return out


def reference_normals(
    meshes: Mapping[object, tuple[np.ndarray, np.ndarray]], decimals: int = 6
) -> dict[object, np.ndarray]:
    """Normals of the merged mesh: vertices at the same (x, y) (rounded to ``decimals`` metres) are one.

    For tiles that all share one LoD (no T-junctions) this is Li, Liu & Liu table 2's "theoretical value": the
    normals a single uniform-LoD mesh would have. Returns {key: (N, 3) float32} in each tile's vertex order.
    """
    keys = list(meshes)
    verts = [np.asarray(meshes[k][0], dtype=np.float64) for k in keys]
    counts = np.array([len(v) for v in verts])
    allv = np.concatenate(verts) if verts else np.zeros((0, 3))
    xy = np.round(allv[:, :2], decimals)
    _, inv = np.unique(xy, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    acc = np.zeros((inv.max() + 1 if inv.size else 0, 3))
    base = np.concatenate([[0], np.cumsum(counts)[:-1]]) if len(counts) else np.zeros(0, int)
    for k, b in zip(keys, base, strict=True):
        v = np.asarray(meshes[k][0], dtype=np.float64)
        t = np.asarray(meshes[k][1], dtype=np.int64)
        np.add.at(acc, inv[b : b + len(v)], normal_sums(v, t))
    n = normalize_all(acc)
    return {k: n[inv[b : b + c]] for k, b, c in zip(keys, base, counts, strict=True)}
