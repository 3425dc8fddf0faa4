"""``terralod serve``: the web formats from a store on request, and the CesiumJS viewer page."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

__all__ = ["CESIUM_HINT", "TileService", "cesium_dir", "make_server"]

CESIUM_HINT = (
    "CesiumJS not found (terralod/serve/static/cesium is missing): in a source checkout run "
    "`bash scripts/install.sh` (npm ci, then python scripts/vendor_cesium.py)"
)


def cesium_dir() -> Path | None:
    """The folder of CesiumJS's browser build (``Cesium.js``, ``Workers``, ``Assets``, ``Widgets``), or None.

    In order: ``$TERRALOD_CESIUM_DIR``; the copy the package carries (``serve/static/cesium``, put there by
    ``scripts/vendor_cesium.py`` and shipped in the wheel); in a source checkout, ``node_modules/cesium/
    Build/Cesium`` under the working directory or the repository.
    """
    here = Path(__file__).resolve().parent
    cands = []
    if os.environ.get("TERRALOD_CESIUM_DIR"):
        cands.append(Path(os.environ["TERRALOD_CESIUM_DIR"]))
    cands.append(here / "static" / "cesium")
    cands.append(Path.cwd() / "node_modules" / "cesium" / "Build" / "Cesium")
    cands.append(here.parents[2] / "node_modules" / "cesium" / "Build" / "Cesium")
    for c in cands:
        if (c / "Cesium.js").is_file():
            return c.resolve()
    return None


def __getattr__(name: str) -> Any:
    # the server (and numpy behind it) loads on first use, not on ``import terralod.serve``
    if name in ("TileService", "make_server"):
        from terralod.serve import server

        return getattr(server, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
