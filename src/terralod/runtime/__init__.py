"""Runtime LOD: camera → view-dependent selection → crack-free stitching → continuous normals.

Papers: ``../shared/papers/000_0f8c6950ace8a2d1.txt`` (screen-space error selection, parent fallback,
quadtree parser) and ``../shared/papers/002_037d1654b87e3b6a.txt`` (edge/corner adjacency with Dirty flags,
stitching for any LoD difference, boundary normals). The runtime is a pure query and never imports a GPU
backend: a renderer consumes :meth:`Selection.meshes`.

>>> with open_store("dem.terra") as store:  # doctest: +SKIP
...     engine = Engine(store, threshold_px=2.0)
...     sel = engine.update(Camera(eye=(0, 0, 3000), target=(5000, 5000, 0), fov_y_deg=60,
...                                width_px=1920, height_px=1080))
...     for code, vertices, triangles, normals in sel.meshes():
...         ...
"""

from terralod.runtime.adjacency import Adjacency, QuadIndex, TileNeighbours
from terralod.runtime.camera import Camera
from terralod.runtime.normals import reference_normals, tile_local_normals
from terralod.runtime.select import Engine, FrameStats, Selection, TileTable
from terralod.runtime.stitch import CrackReport, Stitcher, TileCache, find_cracks, stitch_leaves

__all__ = [
    "Adjacency",
    "Camera",
    "CrackReport",
    "Engine",
    "FrameStats",
    "QuadIndex",
    "Selection",
    "Stitcher",
    "TileCache",
    "TileNeighbours",
    "TileTable",
    "find_cracks",
    "reference_normals",
    "stitch_leaves",
    "tile_local_normals",
]
