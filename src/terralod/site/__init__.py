"""The change site: one web page that shows a terrain's epochs and the change between them to people who are
not terrain experts — `terralod serve`'s viewer and the folder `terralod export --format site` /
`terralod change --site` write, one code base.

The page (``static/``) is CesiumJS with its default options and no internet: one 3D Tiles tileset per epoch,
all loaded once and toggled with ``show`` (no flash on a switch), a swipe between two epochs, the difference
of a pair draped in the report's colours (blue: the ground rose, red: it dropped, grey: within the level of
detection), a legend in metres, a scale bar and a north arrow, "how much changed here?" on a click and the
volume inside a drawn polygon, both computed in the browser from the difference raster shipped with the page
exactly as ``terralod change --zones`` counts them (cells whose centre lies inside, the same error model).

What the page reads (relative URLs, so a folder on any static host works; ``serve`` answers the same paths):

- ``site.json`` — the manifest (:meth:`terralod.site.plan.SitePlan.manifest`, the plan both the writer and
  ``serve`` read): epochs (name, label, tileset URL),
  pairs (names, the URL of each pair's description), bounds and heights, the rasters' encoding (its step);
- ``pairs/K.json`` — one pair (:func:`terralod.site.data.pair_payload`): the grid (shape, affine transform),
  a lon/lat lattice of grid coordinates (the page maps a point to its cell without a projection library),
  the error model (σ, t, variogram), the legend (with the colour table the page colours the drape with), the
  plain-language summary, and where its rasters' tiles are: the difference and the BEFORE heights as tile
  pyramids ``pairs/KEY-dod/LEVEL/ROW_COL.i32.gz``, KEY a function of the pair's two epochs
  (:func:`terralod.site.data.pair_key`: a site updated with a new survey keeps its pairs' tiles)
  (:mod:`terralod.site.tiles`: 256² tiles of int32 millimetres, gzip'd, which the page inflates itself, so no host configuration is needed; level 0 is the grid, which
  "how much changed here?" and the volume read, coarser levels the block means the drape shows), the page
  fetching only the tiles its view or its answer needs;
- ``epochs/I/tileset.json`` — 3D Tiles of epoch I; ``cesium/`` — CesiumJS's build.
"""

from terralod.site.build import site_from_change, site_from_store
from terralod.site.cesium import cesium_dir

__all__ = ["cesium_dir", "site_from_change", "site_from_store"]
