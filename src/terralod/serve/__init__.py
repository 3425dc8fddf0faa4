"""``terralod serve``: the web formats from a store on request, and the CesiumJS viewer page."""

from terralod.serve.server import CESIUM_HINT, TileService, cesium_dir, make_server

__all__ = ["CESIUM_HINT", "TileService", "cesium_dir", "make_server"]
