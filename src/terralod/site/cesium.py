"""Where CesiumJS's browser build is: the copy the package carries (``terralod/site/cesium``, put there by
``scripts/vendor_cesium.py`` and shipped in the wheel), for the site's page and ``terralod serve``."""

from __future__ import annotations

import os
from pathlib import Path

CESIUM_HINT = (
    "CesiumJS not found (terralod/site/cesium is missing): in a source checkout run "
    "`bash scripts/install.sh` (npm ci, then python scripts/vendor_cesium.py)"
)


def cesium_dir() -> Path | None:
    """The folder of CesiumJS's browser build (``Cesium.js``, ``Workers``, ``Assets``, ``Widgets``), or None.

    In order: ``$TERRALOD_CESIUM_DIR``; the copy the package carries; in a source checkout,
    ``node_modules/cesium/Build/Cesium`` under the working directory or the repository.
    """
    here = Path(__file__).resolve().parent
    cands = []
    if os.environ.get("TERRALOD_CESIUM_DIR"):
        cands.append(Path(os.environ["TERRALOD_CESIUM_DIR"]))
    cands.append(here / "cesium")
    cands.append(Path.cwd() / "node_modules" / "cesium" / "Build" / "Cesium")
    cands.append(here.parents[2] / "node_modules" / "cesium" / "Build" / "Cesium")
    for c in cands:
        if (c / "Cesium.js").is_file():
            return c.resolve()
    return None
