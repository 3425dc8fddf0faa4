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
  pairs (names, the URL of each pair's description), bounds and heights;
- ``pairs/K.json`` — one pair (:func:`terralod.site.data.pair_payload`): the grid (shape, affine transform),
  a lon/lat lattice of grid coordinates (the page maps a point to its cell without a projection library),
  the error model (σ, t, variogram), the legend, the plain-language summary; and its rasters
  ``pairs/K-dod.f32.gz`` / ``pairs/K-before.f32.gz`` (little-endian float32, NaN = no data, gzip'd: the page
  inflates them itself, so no host configuration is needed) and
  ``pairs/K-overlay.png`` (the drape);
- ``epochs/I/tileset.json`` — 3D Tiles of epoch I; ``cesium/`` — CesiumJS's build.
"""

from terralod.site.build import site_from_change, site_from_store
from terralod.site.cesium import cesium_dir

__all__ = ["cesium_dir", "site_from_change", "site_from_store"]
