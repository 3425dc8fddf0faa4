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

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # the names below are loaded on first use (PEP 562): `import terralod` stays cheap
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

#: Where each public name lives: the package imports numba, scipy and GDAL only when one is used, so the
#: command line (``terralod --help``, a one-line refusal) and a process that needs one module start fast.
_LAZY = {
    "ErrorReport": "terralod.error", "measure_error": "terralod.error",
    "BuildMismatchError": "terralod.errors", "CorruptStoreError": "terralod.errors",
    "InputError": "terralod.errors", "InputNotFoundError": "terralod.errors", "StoreError": "terralod.errors",
    "TerralodError": "terralod.errors", "Heightfield": "terralod.heightfield",
    "read_heightfield": "terralod.io.reader", "sample_heightfield": "terralod.io.reader",
    "BuildReport": "terralod.pyramid.builder", "build_store": "terralod.pyramid.builder",
    "Camera": "terralod.runtime", "Engine": "terralod.runtime", "Tile": "terralod.store",
    "TileStore": "terralod.store", "open_store": "terralod.store", "GridTerrain": "terralod.terrain",
    "LodNode": "terralod.terrain", "Terrain": "terralod.terrain", "TinTerrain": "terralod.terrain",
    "as_terrain": "terralod.terrain", "open_terrain": "terralod.terrain", "TilePyramid": "terralod.tiles",
}  # fmt: skip


def __getattr__(name: str) -> Any:
    """A public name, imported from its module on first use (``terralod.open`` is ``open_terrain``)."""
    target = "open_terrain" if name == "open" else name
    if target not in _LAZY:
        raise AttributeError(f"module 'terralod' has no attribute {name!r}")
    value = getattr(importlib.import_module(_LAZY[target]), target)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))


__version__ = "0.1.0"

#: ``terralod.open(path)``: any store as a :class:`Terrain` (see :func:`terralod.terrain.open_terrain`), the
#: package-level verb, as in rasterio.open (loaded on first use, by :func:`__getattr__`).

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
