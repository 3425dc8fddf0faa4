"""terralod: real-time terrain level of detail with measured geometric error.

Public API (metres everywhere, x east, y north, z up):

- :func:`read_heightfield`, :func:`sample_heightfield` → :class:`Heightfield`
- :func:`measure_error` → :class:`ErrorReport` (max/RMS vertical error, one-sided Hausdorff distance)
- :func:`build_store` → a ``.terra`` :class:`TileStore`, opened again with :func:`open_store`
- :class:`TilePyramid`, tile codes ``(level, x, y)``
- :class:`Camera`, :class:`Engine`: view-dependent selection and crack-free stitching of a store
- :func:`open` → a :class:`Terrain` (any ``.terra`` store: grid tiles or a detail-increment TIN), the one
  interface every consumer (renderer, viewer, CLI, exports, server, change) takes
"""

from terralod.error import ErrorReport, measure_error
from terralod.errors import (
    BuildMismatchError,
    CorruptStoreError,
    InputError,
    InputNotFoundError,
    StoreError,
    TerralodError,
)
from terralod.heightfield import Heightfield
from terralod.io.reader import read_heightfield, sample_heightfield
from terralod.pyramid.builder import BuildReport, build_store
from terralod.runtime import Camera, Engine
from terralod.store import Tile, TileStore, open_store
from terralod.terrain import GridTerrain, LodNode, Terrain, TinTerrain, as_terrain, open_terrain
from terralod.tiles import TilePyramid

__version__ = "0.1.0"

#: ``terralod.open(path)``: any store as a :class:`Terrain` (see :func:`terralod.terrain.open_terrain`).
open = open_terrain  # noqa: A001 - the package-level verb, as in rasterio.open

__all__ = [
    "BuildMismatchError",
    "BuildReport",
    "Camera",
    "CorruptStoreError",
    "Engine",
    "ErrorReport",
    "GridTerrain",
    "Heightfield",
    "InputError",
    "InputNotFoundError",
    "LodNode",
    "StoreError",
    "Terrain",
    "TerralodError",
    "Tile",
    "TilePyramid",
    "TileStore",
    "TinTerrain",
    "__version__",
    "as_terrain",
    "build_store",
    "measure_error",
    "open",
    "open_store",
    "open_terrain",
    "read_heightfield",
    "sample_heightfield",
]
