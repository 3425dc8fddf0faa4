"""Every web export works in clients terralod did not write, with their defaults.

- stock CesiumJS: a minimal page that is not terralod's viewer (benchmarks/web/stock_cesium.html:
  ``CesiumTerrainProvider.fromUrl(url)`` / ``Cesium3DTileset.fromUrl(url)`` with no options), served from the
  export folder by a plain ``python -m http.server`` (no headers configured), driven in Debian's headless
  Chromium by puppeteer-core (benchmarks/web/stock_check.mjs) from three views: the whole terrain, 2 km above a
  ridge, an oblique view to the horizon. Tiles load, no console error, CesiumJS's own most-detailed height
  samplers agree with the source samples within the declared error, the screenshots show terrain.
- loaders.gl's quantized-mesh loader (tests/web/qm_decode.mjs) decodes every ``.terrain`` tile: header
  fields, edge lists and extensions as the specification says, heights within each tile's declared error of
  every source sample inside it (measured here again with matplotlib's triangle interpolator).
- 3DTilesRendererJS (tests/web/tiles_renderer_check.mjs) loads the tilesets and refines them.
- the Khronos glTF validator reports 0 errors.

Real data (small crops of ../shared/data, made here): SRTM3 N41E001 (EPSG:4326, the Tarragona coast with
sea at 0 m, exported straight from the DEM), Big Tujunga (UTM, steep mountains, a store), the South Florida
coastal flat with nodata as a TIN store. One export per kind and one browser per format.
"""

from __future__ import annotations

import json
import math
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import read_tileset

REPO = Path(__file__).resolve().parents[1]
NODE_MODULES = REPO / "node_modules"
WEB = REPO / "tests" / "web"
PAGES = REPO / "benchmarks" / "web"  # the page drivers the benchmarks use too
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


def _node_missing(*pkgs: str) -> str | None:
    if shutil.which("node") is None:
        return "node not installed"
    for pkg in pkgs:
        if not (NODE_MODULES / pkg).is_dir():
            return f"node_modules/{pkg} missing (run `npm ci` in the repository)"
    return None


def _cesium_build() -> Path | None:
    try:
        from terralod.serve import cesium_dir

        d = cesium_dir()
        if d is not None and (Path(d) / "Cesium.js").is_file():
            return Path(d)
    except ImportError:
        pass
    d = NODE_MODULES / "cesium" / "Build" / "Cesium"
    return d if (d / "Cesium.js").is_file() else None


def _browser_missing() -> str | None:
    if CHROMIUM is None:
        return "Debian chromium not installed (bash scripts/install.sh installs it)"
    if _cesium_build() is None:
        return "no CesiumJS build (package data or node_modules/cesium)"
    return _node_missing("puppeteer-core")


def _crop(src: Path, dst: Path, row: int, col: int, h: int, w: int) -> Path:
    import rasterio
    from rasterio.windows import Window

    with rasterio.open(src) as d:
        win = Window(col, row, w, h)
        prof = d.profile.copy()
        prof.update(width=w, height=h, transform=d.window_transform(win), tiled=False)
        prof.pop("blockxsize", None)
        prof.pop("blockysize", None)
        data = d.read(1, window=win)
    with rasterio.open(dst, "w", **prof) as o:
        o.write(data, 1)
    return dst


@pytest.fixture(scope="module")
def site(shared_data: Path, tmp_path_factory: pytest.TempPathFactory) -> dict:
    """One folder a static server serves: the stock page, CesiumJS, and the exports of each kind."""
    from terralod.export import export_3dtiles, export_quantized_mesh
    from terralod.export.source import source_from_dem
    from terralod.heightfield import Heightfield
    from terralod.io.reader import read_heightfield
    from terralod.pyramid.builder import build_store
    from terralod.terrain import open_terrain
    from terralod.tin import DetailIncrementModel
    from terralod.tin.terra import save_model_to_store

    root = tmp_path_factory.mktemp("interop")
    dem = shared_data / "dem"
    geo = _crop(dem / "srtm3_N41E001.tif", root / "tarragona.tif", 1000, 250, 160, 160)
    utm = _crop(dem / "big_tujunga_srtm30m_utm11.tif", root / "tujunga.tif", 200, 300, 200, 200)
    out: dict = {"root": root, "geo_dem": geo, "utm_dem": utm, "reports": {}}
    out["reports"]["qm_geo"] = export_quantized_mesh(source_from_dem(geo), root / "qm_geo")
    store = root / "tujunga.terra"
    build_store(read_heightfield(utm), store, workers=2)
    with open_terrain(store) as t:
        out["reports"]["qm_utm"] = export_quantized_mesh(t, root / "qm_utm")
        out["reports"]["t3_utm"] = export_3dtiles(t, root / "t3_utm")
        out["reports"]["t3_split"] = export_3dtiles(t, root / "t3_split", split_levels=1)  # a file a level
    try:  # heights above EGM96 made ellipsoidal (needs PROJ's EGM96 grid: Debian's proj-data)
        out["reports"]["qm_geo_egm96"] = export_quantized_mesh(source_from_dem(geo), root / "qm_geo_egm96",
                                                               vertical_datum="egm96")  # fmt: skip
    except Exception as exc:  # noqa: BLE001 - the test that needs it skips with the reason
        out["egm96_missing"] = str(exc)
    geo_store = root / "tarragona.terra"  # a geographic DEM's store: errors against its own samples
    build_store(read_heightfield(geo), geo_store, workers=2)
    with open_terrain(geo_store) as t:
        out["reports"]["t3_geo"] = export_3dtiles(t, root / "t3_geo")
    hf = read_heightfield(dem / "srtm1_crop256_coastal_flat_nodata.tif")
    crop = Heightfield(hf.elevation_m[:96, :96].copy(), hf.valid[:96, :96].copy(), hf.transform, hf.crs)
    tin = root / "tin.terra"
    save_model_to_store(DetailIncrementModel.from_heightfield(crop, sub_blocks=4), tin)
    with open_terrain(tin) as t:
        out["reports"]["qm_tin"] = export_quantized_mesh(t, root / "qm_tin", normals=True)
        out["reports"]["t3_tin"] = export_3dtiles(t, root / "t3_tin")
    cesium = _cesium_build()
    if cesium is not None:
        (root / "cesium").symlink_to(cesium, target_is_directory=True)
    shutil.copy(PAGES / "stock_cesium.html", root / "stock_cesium.html")
    return out


@pytest.fixture(scope="module")
def static_server(site: dict):
    """``python -m http.server`` on a random loopback port, serving the site folder as it is."""
    proc = subprocess.Popen(
        [sys.executable, "-u", "-m", "http.server", "0", "--bind", "127.0.0.1"],
        cwd=site["root"], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
    )  # fmt: skip
    line = proc.stdout.readline()
    m = re.search(r"port (\d+)", line)
    assert m, line
    yield f"http://127.0.0.1:{m.group(1)}"
    proc.terminate()
    proc.wait(timeout=10)


def _source_points(dem: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """lon, lat (WGS 84 degrees) and height of every valid sample of a DEM crop, read with rasterio itself
    and placed by pyproj: the check does not take the samples from the exporter it checks."""
    import rasterio
    from pyproj import Transformer

    with rasterio.open(dem) as ds:
        band = ds.read(1, masked=True)
        t, crs = ds.transform, ds.crs
    z = np.ma.getdata(band).astype(np.float64)
    ok = ~np.ma.getmaskarray(band) & np.isfinite(z)
    r, c = np.nonzero(ok)
    x = t.c + (c + 0.5) * t.a  # sample centres: pixel-is-area, north-up
    y = t.f + (r + 0.5) * t.e
    if crs.to_epsg() != 4326:
        x, y = Transformer.from_crs(crs, "EPSG:4326", always_xy=True).transform(x, y)
    return np.asarray(x), np.asarray(y), z[ok]


# -- quantized-mesh: loaders.gl decodes every tile -------------------------------------------------
@pytest.mark.parametrize("name", ["qm_geo", "qm_utm", "qm_tin"])
def test_loaders_gl_decodes_every_tile_within_declared_error(site: dict, name: str) -> None:
    """Every tile decodes in loaders.gl; the header (heights, bounding sphere, horizon point), the edge
    lists and the extensions are as the specification says; the surface loaders.gl decodes is within each
    tile's declared error of every source sample inside it, and each level's declared error bounds its
    tiles'."""
    import matplotlib.tri as mtri

    from terralod.export.geodesy import ecef_lonlat
    from terralod.export.quantized_mesh import tile_rectangle
    from terralod.export.source import source_for
    from terralod.terrain import open_terrain

    if (why := _node_missing("@loaders.gl/terrain", "@loaders.gl/core")) is not None:
        pytest.skip(why)
    out = site["root"] / name
    res = subprocess.run(["node", str(WEB / "qm_decode.mjs"), str(out), str(out.parent / f"{name}.json")],
                         capture_output=True, text=True, timeout=300, cwd=REPO)  # fmt: skip
    assert res.returncode == 0, res.stderr[-2000:]
    dec = json.loads((out.parent / f"{name}.json").read_text())
    layer = json.loads((out / "layer.json").read_text())
    declared = json.loads((out / "errors.json").read_text())["tiles"]
    assert not dec["errors"] and set(dec["tiles"]) == set(declared)
    assert "metadata" not in layer["extensions"]  # stock CesiumJS requests metadata by default
    if name == "qm_geo":
        lon, lat, zs = _source_points(site["geo_dem"])
    else:
        store = {"qm_utm": "tujunga.terra", "qm_tin": "tin.terra"}[name]
        with open_terrain(site["root"] / store) as t:
            from terralod.export.geodesy import Geodesy

            src = source_for(t, Geodesy(t.crs))
            lon, lat, zs = src.lon, src.lat, src.zv
    worst: dict[int, float] = {}
    for key, tile in dec["tiles"].items():
        z, x, y = (int(a) for a in key.split("/"))
        w, s, e, n = tile_rectangle(z, x, y)
        u, v = np.array(tile["u"], np.float64), np.array(tile["v"], np.float64)
        h = np.array(tile["height"], np.float64)
        tri = np.array(tile["indices"], np.int64).reshape(-1, 3)
        hd = tile["header"]
        assert abs(h.min() - hd["minHeight"]) < 1e-3 and abs(h.max() - hd["maxHeight"]) < 1e-3
        assert len(tri) and tri.max() < len(u) and u.max() <= 32767 and v.max() <= 32767
        for side, sel in (("west", u == 0), ("south", v == 0), ("east", u == 32767), ("north", v == 32767)):
            assert sorted(tile[side]) == sorted(np.flatnonzero(sel).tolist()), (key, side)
            assert len(tile[side]) >= 2, (key, side)  # each edge has its two corners at least
        ecef = ecef_lonlat(w + u / 32767 * (e - w), s + v / 32767 * (n - s), h)
        c = np.array([hd["boundingSphereCenterX"], hd["boundingSphereCenterY"], hd["boundingSphereCenterZ"]])
        assert np.linalg.norm(ecef - c, axis=1).max() <= hd["boundingSphereRadius"] * (1 + 1e-9) + 1e-6
        occ = np.array(
            [hd["horizonOcclusionPointX"], hd["horizonOcclusionPointY"], hd["horizonOcclusionPointZ"]]
        )
        # the point lies outside the ellipsoid, on the side of the tile's centre
        assert np.linalg.norm(occ) >= 1.0 and occ @ (c / np.linalg.norm(c)) > 0
        # normals only where the layer declares them (``normals=True``: the TIN export here)
        want = 2 * len(u) if "octvertexnormals" in layer["extensions"] else 0
        assert tile["normals"] == want and tile["watermask"] in (1, 65536)
        # heights: matplotlib's interpolation of loaders.gl's surface at every source sample inside the tile
        inside = (lon >= w) & (lon <= e) & (lat >= s) & (lat <= n)
        if inside.any():
            interp = mtri.LinearTriInterpolator(mtri.Triangulation(u, v, tri), h)
            pu = np.clip((lon[inside] - w) / (e - w) * 32767, 0, 32767)
            pv = np.clip((lat[inside] - s) / (n - s) * 32767, 0, 32767)
            zt = np.asarray(interp(pu, pv).filled(np.nan))
            ok = np.isfinite(zt)
            assert ok.mean() > 0.99, key  # a point exactly on the hull may miss matplotlib's finder
            err = float(np.abs(zt[ok] - zs[inside][ok]).max())
            assert err <= declared[key] + 2e-3, (key, err, declared[key])
            worst[z] = max(worst.get(z, 0.0), err)
    for z, err in worst.items():
        assert err <= layer["terralod"]["error_m"][z] + 2e-3
    assert worst, "no source sample fell inside any tile"


def test_quantized_mesh_water_and_edges(site: dict) -> None:
    """Tarragona: the sea at 0 m gets a water mask where the tile holds water, one byte elsewhere; outside
    the data the tiles continue its edge heights (no drop to 0 m: no slope steeper than the data's own)."""
    from terralod.export.quantized_mesh import QuantizedMesh, decode_tile, tile_rectangle
    from terralod.export.source import source_from_dem

    rep = site["reports"]["qm_geo"]
    assert rep.extra["water_masks"]["some"] >= 1 and rep.extra["water_masks"]["none"] >= 1
    src = source_from_dem(site["geo_dem"])
    _, _, zs = _source_points(site["geo_dem"])
    qm = QuantizedMesh(src)
    z = qm.max_zoom
    x0, y0, x1, y1 = qm.level_range(z)
    w, s, e, n = src.bbox
    ref_slope = 0.0
    for x in range(x0, x1 + 1):
        for y in range(y0, y1 + 1):
            rect = tile_rectangle(z, x, y)
            d = decode_tile((site["root"] / "qm_geo" / str(z) / str(x) / f"{y}.terrain").read_bytes(), rect)
            outside = (d["lon"] < w) | (d["lon"] > e) | (d["lat"] < s) | (d["lat"] > n)
            if outside.any():  # the fill is the nearest edge value: never below the data's lowest edge
                assert d["height"][outside].min() >= zs.min() - 1e-3
                assert d["height"][outside].max() <= zs.max() + 1e-3
            ref_slope = max(ref_slope, float(np.ptp(d["height"])))
    # at 1 m south of the data the surface continues the southern edge's heights
    lon = np.linspace(w, e, 50)
    h_in = src.height_at(lon, np.full(50, s))
    h_out = src.height_at(lon, np.full(50, s - 0.01))
    assert np.abs(h_out - h_in).max() < 1e-9


# -- 3D Tiles geometric error -------------------------------------------------------------------------
def test_3dtiles_geometric_error_as_specified(site: dict) -> None:
    """The tileset's geometricError (drawing nothing) is at least the terrain's horizontal diagonal; each
    tile's is at least its children's; a TIN's content-less root carries the tileset's."""
    for name in ("t3_utm", "t3_tin"):
        ts = read_tileset(site["root"] / name)
        reg = ts["root"]["boundingVolume"]["region"]
        lat = 0.5 * (reg[1] + reg[3])
        diag = math.hypot((reg[2] - reg[0]) * 6378137 * math.cos(lat), (reg[3] - reg[1]) * 6378137)
        assert ts["geometricError"] >= 0.9 * diag, (name, ts["geometricError"], diag)

        def walk(t: dict) -> None:
            for k in t.get("children", []):
                assert k["geometricError"] <= t["geometricError"] + 1e-12
                walk(k)

        walk(ts["root"])
        if "content" not in ts["root"]:
            assert ts["root"]["geometricError"] == ts["geometricError"]


def test_gltf_validator_zero_errors(site: dict) -> None:
    if (why := _node_missing("gltf-validator")) is not None:
        pytest.skip(why)
    for name in ("t3_utm", "t3_tin"):
        res = subprocess.run(["node", str(WEB / "validate_glb.mjs"), str(site["root"] / name)],
                             capture_output=True, text=True, timeout=300, cwd=REPO)  # fmt: skip
        r = json.loads(res.stdout.strip().splitlines()[-1])
        assert r["files"] > 0 and r["errors"] == 0, r


def test_3d_tiles_renderer_loads_and_refines(site: dict, static_server: str) -> None:
    """3DTilesRendererJS with its defaults loads the root from an overview, and its children close up."""
    if (why := _node_missing("3d-tiles-renderer", "three")) is not None:
        pytest.skip(why)
    for name in ("t3_utm", "t3_tin", "t3_split"):
        res = subprocess.run(["node", str(WEB / "tiles_renderer_check.mjs"), f"{static_server}/{name}/tileset.json",
                              "60000"], capture_output=True, text=True, timeout=200, cwd=REPO)  # fmt: skip
        r = json.loads(res.stdout.strip().splitlines()[-1])
        assert not r["errors"] and r["failed"] == 0, r
        whole, close = r["views"]
        assert whole["visible"] >= 1 and close["loaded"] > whole["loaded"], r


# -- stock CesiumJS -----------------------------------------------------------------------------------
def _stock(static_server: str, query: str, cfg: dict, tmp: Path, browser: str) -> dict:
    """benchmarks/web/stock_check.mjs on the page, in a fresh context of the session's ``browser``."""
    (tmp / "cfg.json").write_text(json.dumps(cfg))
    res = subprocess.run(["node", str(PAGES / "stock_check.mjs"), f"{static_server}/stock_cesium.html?{query}",
                          str(tmp / "cfg.json"), str(tmp / "shot_"), "90000"], capture_output=True, text=True,
                         timeout=400, cwd=REPO, env={**os.environ, "TERRALOD_BROWSER_WS": browser})  # fmt: skip
    assert res.returncode == 0, res.stderr[-2000:]
    return json.loads(res.stdout.strip().splitlines()[-1])


def _views(bbox: tuple[float, float, float, float], ridge: tuple[float, float]) -> list[dict]:
    w, s, e, n = bbox
    return [
        {"name": "whole", "rect": [w, s, e, n]},
        {"name": "ridge", "lon": ridge[0], "lat": ridge[1], "height": 2000, "pitch": -90},
        {"name": "oblique", "lon": 0.5 * (w + e), "lat": s - 0.3 * (n - s), "height": 1500, "pitch": -5},
    ]


def _shows_terrain(png: Path) -> float:
    """Spread of the screenshot's grey levels in its middle (a uniform globe or a blank page has none)."""
    from PIL import Image

    a = np.asarray(Image.open(png).convert("L"), np.float64)
    return float(a[100:300, 100:540].std())


def _shows_tiles(png: Path) -> float:
    """Fraction of the screenshot's middle that is not the bare globe's blue (the tileset's grey mesh)."""
    from PIL import Image

    a = np.asarray(Image.open(png).convert("RGB"), np.float64)[100:300, 100:540]
    return float((a[..., 2] < a[..., 0] + 25).mean())


def _sample_points(lon: np.ndarray, lat: np.ndarray, z: np.ndarray, k: int = 25) -> tuple[np.ndarray, ...]:
    rng = np.random.default_rng(42)
    i = rng.choice(lon.size, size=min(k, lon.size), replace=False)
    i = np.concatenate([i, [int(np.argmax(z))]])  # the highest sample: the ridge
    return lon[i], lat[i], z[i]


@pytest.mark.skipif(_browser_missing() is not None, reason=str(_browser_missing()))
def test_stock_cesium_quantized_mesh(site: dict, static_server: str, browser: str, tmp_path: Path) -> None:
    """CesiumTerrainProvider.fromUrl(folder) with no options, from a plain static server: every tile
    loads in three views, no console error, sampleTerrainMostDetailed at the source samples within the
    finest level's declared error, screenshots that show terrain."""
    lon, lat, z = _source_points(site["geo_dem"])
    plon, plat, pz = _sample_points(lon, lat, z)
    layer = json.loads((site["root"] / "qm_geo" / "layer.json").read_text())
    cfg = {"kind": "terrain", "views": _views(tuple(layer["bounds"]), (plon[-1], plat[-1])),
           "points": np.column_stack([plon, plat]).tolist()}  # fmt: skip
    r = _stock(static_server, f"terrain=qm_geo/&hmin={z.min()}&hmax={z.max()}", cfg, tmp_path, browser)
    assert not r["errors"] and not r["badResponses"] and not r["blocked"], r
    assert r["views"][0]["tileResponses"] > 0 and r["tileResponses"] >= 3, str(
        {k: v for k, v in r.items() if k != "heights"}
    )
    err = np.abs(np.array(r["heights"], np.float64) - pz)
    assert err.max() <= layer["terralod"]["error_m"][layer["maxzoom"]] + 2e-3, err
    for v in ("whole", "ridge", "oblique"):
        assert _shows_terrain(tmp_path / f"shot_{v}.png") > 3.0, v


@pytest.mark.skipif(_browser_missing() is not None, reason=str(_browser_missing()))
@pytest.mark.parametrize("name", ["t3_utm", "t3_split"])
def test_stock_cesium_3dtiles(
    site: dict, static_server: str, browser: str, tmp_path: Path, name: str
) -> None:
    """Cesium3DTileset.fromUrl(url) with no options: the root draws from the whole-terrain view (the
    tileset's error is the error of drawing nothing), tiles refine close up, no console error, and
    scene.sampleHeightMostDetailed at the source samples lies within the finest tiles' error; the same
    through external tilesets (``t3_split``: a tileset file per level)."""
    from terralod.terrain import open_terrain

    lon, lat, z = _source_points(site["utm_dem"])
    plon, plat, pz = _sample_points(lon, lat, z)
    ts = read_tileset(site["root"] / name)
    reg = np.degrees(ts["root"]["boundingVolume"]["region"][:4])
    with open_terrain(site["root"] / "tujunga.terra") as t:
        leaf_err = max(
            n.vertical_error_m for n in t.lod_tree() if not any(m.parent == n.code for m in t.lod_tree())
        )
    cfg = {"kind": "tileset", "views": _views(tuple(reg), (plon[-1], plat[-1])),
           "points": np.column_stack([plon, plat]).tolist()}  # fmt: skip
    r = _stock(static_server, f"tileset={name}/tileset.json", cfg, tmp_path, browser)
    assert not r["errors"] and not r["badResponses"] and not r["blocked"], r
    assert r["views"][0]["tileResponses"] >= 1, r  # the overview draws the root
    h = np.array([np.nan if v is None else v for v in r["heights"]], np.float64)
    assert np.isfinite(h).all(), r["heights"]
    assert np.abs(h - pz).max() <= leaf_err + 0.05, (np.abs(h - pz).max(), leaf_err)
    for v in ("whole", "ridge", "oblique"):
        assert _shows_tiles(tmp_path / f"shot_{v}.png") > 0.3, v


# -- the CLI --------------------------------------------------------------------------------------------
def test_export_straight_from_a_dem_cli(site: dict, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """``terralod export dem.tif --format quantized-mesh -o DIR``: uncompressed tiles by default, gzip'd
    with --gzip; 3D Tiles from a DEM is refused in one line with exit code 2 and nothing written."""
    from click.testing import CliRunner

    from terralod.cli import cli as main

    dem = str(site["geo_dem"])
    r = CliRunner().invoke(main, ["export", dem, "--format", "quantized-mesh", "-o", str(tmp_path / "a")])
    assert r.exit_code == 0, r.output
    r = CliRunner().invoke(
        main, ["export", dem, "--format", "quantized-mesh", "--gzip", "-o", str(tmp_path / "b")]
    )
    assert r.exit_code == 0, r.output
    a, b = (
        (tmp_path / "a" / "0" / "0" / "0.terrain").read_bytes(),
        (tmp_path / "b" / "0" / "0" / "0.terrain").read_bytes(),
    )
    assert a[:2] != b"\x1f\x8b" and b[:2] == b"\x1f\x8b"
    import gzip

    assert gzip.decompress(b) == a
    from terralod.cli import main as entry  # the entry point: one line, exit code 2

    with pytest.raises(SystemExit) as ex:
        entry(["export", dem, "--format", "3dtiles", "-o", str(tmp_path / "c")])
    err = capsys.readouterr().err
    assert ex.value.code == 2 and "DEM" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "c").exists()


def _scaled_point_visible(camera_ecef: np.ndarray, occludee_scaled: np.ndarray) -> bool:
    """CesiumJS's EllipsoidalOccluder.isScaledSpacePointVisible, on the WGS 84 ellipsoid."""
    radii = np.array([6378137.0, 6378137.0, 6356752.314245179])
    cv = camera_ecef / radii
    vh2 = float(cv @ cv) - 1.0
    vt = occludee_scaled - cv
    vt_dot_vc = -float(vt @ cv)
    if vh2 < 0:
        return not vt_dot_vc > 0
    return not (vt_dot_vc > vh2 and vt_dot_vc * vt_dot_vc / float(vt @ vt) > vh2)


@pytest.mark.parametrize("name", ["qm_geo", "qm_utm"])
def test_horizon_occlusion_point_never_hides_a_tile_seen_from_above(site: dict, name: str) -> None:
    """Every tile's horizon-occlusion point is visible from 10 km above the terrain inside the tile (CesiumJS
    culls a tile whose point is below the horizon: a wrong point at zoom 0 hid the whole terrain from a
    camera above it), and its bounding sphere holds every decoded vertex."""
    from terralod.export.geodesy import ecef_lonlat
    from terralod.export.quantized_mesh import decode_tile, tile_rectangle

    root = site["root"] / name
    bw, bs, be, bn = json.loads((root / "layer.json").read_text())["bounds"]
    n = 0
    for f in sorted(root.rglob("*.terrain")):
        z, x, y = int(f.parent.parent.name), int(f.parent.name), int(f.stem)
        d = decode_tile(f.read_bytes())
        w, s, e, nn = tile_rectangle(z, x, y)
        if max(w, bw) > min(e, be) or max(s, bs) > min(nn, bn):
            continue  # a zoom-0 tile beside the data (both are always there)
        # above the part of the tile that holds data (a camera over the terrain must see its tiles)
        lon_c = 0.5 * (max(w, bw) + min(e, be))
        lat_c = 0.5 * (max(s, bs) + min(nn, bn))
        cam = ecef_lonlat(np.array([lon_c]), np.array([lat_c]), np.array([10_000.0]))[0]
        assert _scaled_point_visible(cam, np.asarray(d["occlusion"], np.float64)), (
            name,
            z,
            x,
            y,
            d["occlusion"],
        )
        lon = w + np.asarray(d["u"]) / 32767.0 * (e - w)
        lat = s + np.asarray(d["v"]) / 32767.0 * (nn - s)
        h = d["min_height"] + np.asarray(d["hq"]) / 32767.0 * (d["max_height"] - d["min_height"])
        p = ecef_lonlat(lon, lat, h)
        c = np.asarray(d["sphere"][:3])
        assert np.sqrt(((p - c) ** 2).sum(axis=1)).max() <= d["sphere"][3] + 1e-3
        n += 1
    assert n > 10


@pytest.mark.skipif(_browser_missing() is not None, reason=str(_browser_missing()))
def test_stock_cesium_heights_above_the_ellipsoid(
    site: dict, static_server: str, browser: str, tmp_path: Path
) -> None:
    """The geographic crop exported with ``vertical_datum="egm96"``: stock CesiumJS samples the DEM's height
    + the EGM96 undulation (PROJ's grid, checked on NGA's values in test_vertical.py) at the DEM's own
    samples, within the finest level's declared error + 0.5 m; the undulation there is not zero."""
    if "egm96_missing" in site:
        pytest.skip(f"PROJ has no EGM96 grid here: {site['egm96_missing']}")
    from terralod.export.vertical import resolve_vertical_datum

    lon, lat, z = _source_points(site["geo_dem"])
    plon, plat, pz = _sample_points(lon, lat, z)
    n = resolve_vertical_datum("egm96").converter().undulation_m(plon, plat)
    assert np.all(np.abs(n) > 10.0)  # Catalonia: about +49 m
    layer = json.loads((site["root"] / "qm_geo_egm96" / "layer.json").read_text())
    assert layer["terralod"]["heights"]["datum"] == "egm96"
    cfg = {"kind": "terrain", "views": _views(tuple(layer["bounds"]), (plon[-1], plat[-1])),
           "points": np.column_stack([plon, plat]).tolist()}  # fmt: skip
    r = _stock(
        static_server, f"terrain=qm_geo_egm96/&hmin={z.min()}&hmax={z.max() + 100}", cfg, tmp_path, browser
    )
    assert not r["errors"] and not r["badResponses"] and not r["blocked"], r
    err = np.abs(np.array(r["heights"], np.float64) - (pz + n))
    assert err.max() <= layer["terralod"]["error_m"][layer["maxzoom"]] + 0.5, err


@pytest.mark.skipif(_browser_missing() is not None, reason=str(_browser_missing()))
def test_stock_cesium_3dtiles_of_a_geographic_store(
    site: dict, static_server: str, browser: str, tmp_path: Path
) -> None:
    """A store built from a lon/lat DEM (meshed on a metric grid): stock CesiumJS samples its 3D Tiles at the
    DEM's own sample positions within the finest tiles' declared error (which counts what resampling moved)."""
    from terralod.terrain import open_terrain

    lon, lat, z = _source_points(site["geo_dem"])
    plon, plat, pz = _sample_points(lon, lat, z)
    ts = read_tileset(site["root"] / "t3_geo")
    reg = np.degrees(ts["root"]["boundingVolume"]["region"][:4])
    with open_terrain(site["root"] / "tarragona.terra") as t:
        tree = t.lod_tree()
        leaf_err = max(n.vertical_error_m for n in tree if not any(m.parent == n.code for m in tree))
    cfg = {"kind": "tileset", "views": _views(tuple(reg), (plon[-1], plat[-1])),
           "points": np.column_stack([plon, plat]).tolist()}  # fmt: skip
    r = _stock(static_server, "tileset=t3_geo/tileset.json", cfg, tmp_path, browser)
    assert not r["errors"] and not r["badResponses"] and not r["blocked"], r
    h = np.array([np.nan if v is None else v for v in r["heights"]], np.float64)
    ok = np.isfinite(h)
    assert ok.sum() >= len(h) - 2, r["heights"]  # a sample on the crop's very edge may fall off the mesh
    assert np.abs(h[ok] - pz[ok]).max() <= leaf_err + 0.05, (np.abs(h[ok] - pz[ok]).max(), leaf_err)
