"""Continuous-scale TIN from LiDAR: the detail-increment model of Ai et al. (2019).

Paper: ``../shared/papers/003_2a2cfcda929de24c.txt`` (Ai et al. 2019). Pipeline::

    LAS/LAZ points ─ pointcloud ─▶ metres, ground class, duplicates thinned
                   ─ delaunay   ─▶ one Delaunay TIN, k × k sub-blocks, seam and outline vertices locked
                   ─ qem        ─▶ QEM half-edge collapses (endpoint placement) down to the base mesh
                   ─ increments ─▶ one ΔT record per collapse; merging with compression; files
                   ─ svo        ─▶ per-sub-block scale from the smallest-visible-object pixel rule

Public API: :class:`DetailIncrementModel` (``from_points``, ``from_las``, ``from_heightfield``,
``mesh_at``, ``mesh_for_camera``, ``compressed``, ``save``, ``load``), :class:`DeltaT`,
:func:`read_las`.
"""

from terralod.tin.fileformat import read_text, write_text
from terralod.tin.increments import DetailIncrementModel
from terralod.tin.pointcloud import PointCloud, read_las
from terralod.tin.records import DeltaT, Increments

__all__ = [
    "DeltaT",
    "DetailIncrementModel",
    "Increments",
    "PointCloud",
    "read_las",
    "read_text",
    "write_text",
]
