"""``terralod serve``'s tile sets in stock CesiumJS with its defaults: the stock page (benchmarks/web/stock_cesium.html,
not terralod's) from a plain static host, pointed at a running ``terralod serve``
(``CesiumTerrainProvider.fromUrl(serve + "/terrain/")``, ``Cesium3DTileset.fromUrl(serve +
"/3dtiles/tileset.json")``, no options): tiles load across origins, no console error, and the heights CesiumJS
samples at source samples lie within the declared errors. The store is the bundled Jacksboro DEM (UTM 16N).
"""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

from test_interop import _stock  # the stock page's driver: one copy

REPO = Path(__file__).resolve().parents[1]
PAGES = REPO / "benchmarks" / "web"  # the stock page, its driver too (benchmarks/web.py uses them)


def _missing() -> str | None:
    from terralod.serve import cesium_dir

    if shutil.which("chromium") is None:
        return "Debian chromium not installed (bash scripts/install.sh installs it)"
    if shutil.which("node") is None or not (REPO / "node_modules" / "puppeteer-core").is_dir():
        return "node or node_modules/puppeteer-core missing (run `npm ci`)"
    if cesium_dir() is None:
        return "CesiumJS not installed with terralod (scripts/vendor_cesium.py)"
    return None


@pytest.fixture(scope="module")
def serve_and_page(tmp_path_factory: pytest.TempPathFactory):
    why = _missing()
    if why:
        pytest.skip(why)
    from terralod.io.reader import sample_heightfield
    from terralod.pyramid.builder import build_store
    from terralod.serve import cesium_dir, make_server
    from terralod.terrain import open_terrain

    root = tmp_path_factory.mktemp("stock")
    hf = sample_heightfield()
    store = root / "jacksboro.terra"
    build_store(hf, store, workers=2)
    (root / "page").mkdir()
    (root / "page" / "cesium").symlink_to(cesium_dir(), target_is_directory=True)
    shutil.copy(PAGES / "stock_cesium.html", root / "page" / "stock_cesium.html")
    page = subprocess.Popen([sys.executable, "-u", "-m", "http.server", "0", "--bind", "127.0.0.1"],
                            cwd=root / "page", stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)  # fmt: skip
    port = re.search(r"port (\d+)", page.stdout.readline()).group(1)
    t = open_terrain(store)
    srv, service = make_server(t, "127.0.0.1", 0)
    th = threading.Thread(target=srv.serve_forever, daemon=True)
    th.start()
    yield {"page": f"http://127.0.0.1:{port}", "serve": f"http://127.0.0.1:{srv.server_address[1]}",
           "service": service, "terrain": t, "hf": hf, "root": root}  # fmt: skip
    srv.shutdown()
    srv.server_close()
    t.close()
    page.terminate()
    page.wait(10)


def _points(hf, service, k: int = 20) -> tuple[list, np.ndarray]:
    rng = np.random.default_rng(5)
    rows = rng.integers(10, hf.height - 10, k)
    cols = rng.integers(10, hf.width - 10, k)
    tr = hf.transform
    x, y = tr.c + (cols + 0.5) * tr.a + (rows + 0.5) * tr.b, tr.f + (cols + 0.5) * tr.d + (rows + 0.5) * tr.e
    from pyproj import Transformer

    lon, lat = Transformer.from_crs(hf.crs, "EPSG:4326", always_xy=True).transform(
        np.asarray(x), np.asarray(y)
    )
    z = np.asarray(hf.elevation_m, np.float64)[rows, cols]
    return np.column_stack([lon, lat]).tolist(), z


def test_stock_cesium_loads_serve_quantized_mesh_and_3dtiles(
    serve_and_page: dict, browser: str, tmp_path: Path
) -> None:
    s = serve_and_page
    pts, z = _points(s["hf"], s["service"])
    w, so, e, n = s["service"].qm().bbox
    views = [{"name": "whole", "rect": [w, so, e, n]}]
    r = _stock(s["page"], f"terrain={s['serve']}/terrain/&hmin={z.min()}&hmax={z.max()}",
             {"kind": "terrain", "views": views, "points": pts}, tmp_path, browser)  # fmt: skip
    assert not r["errors"] and not r["badResponses"] and not r["blocked"], r
    assert r["tileResponses"] > 0
    err = np.abs(np.array(r["heights"], np.float64) - z)
    qm = s["service"].qm()  # the tiles serve encoded for those samples, each measured as it was encoded
    declared = max(v for (zz, _, _), v in qm._errors.items() if zz == qm.max_zoom)
    assert err.max() <= declared + 2e-3, (err.max(), declared)
    r3 = _stock(s["page"], f"tileset={s['serve']}/3dtiles/tileset.json", {"kind": "tileset", "views": views,
              "points": pts}, tmp_path, browser)  # fmt: skip
    assert not r3["errors"] and not r3["badResponses"] and not r3["blocked"], r3
    assert r3["views"][0]["tileResponses"] >= 1
    tree = s["terrain"].lod_tree()
    leaf = max(m.vertical_error_m for m in tree if not any(c.parent == m.code for c in tree))
    h = np.array([np.nan if v is None else v for v in r3["heights"]], np.float64)
    assert np.isfinite(h).all() and np.abs(h - z).max() <= leaf + 0.05, (np.abs(h - z).max(), leaf)
