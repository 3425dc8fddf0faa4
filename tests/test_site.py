"""The change site (terralod.site): the folder ``terralod change --site`` and ``terralod export --format site``
write, and ``terralod serve``'s page, checked in a real headless Chromium through the page's contract
``window.terralodSite`` against what ``terralod change`` wrote in the same run (dod.tif, the --zones budget).

The St Helens pair (../shared/data/change, 2000-09-25 and 2007-07-05, 10 m): the dome rose up to 205 m.
Python-side invariants (the lattice the page maps lon/lat with, the drape's affine map, the pairs a site
carries) run without a browser; the browser tests skip with the reason when chromium or node_modules are
missing.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from terralod.cli import main

from conftest import read_tileset

REPO = Path(__file__).resolve().parents[1]
BEFORE = "change/st_helens_crater_2000-09-25_10m.tif"
AFTER = "change/st_helens_crater_2007-07-05_10m.tif"
A, B = "2000-09-25", "2007-07-05"


def _browser_missing() -> str | None:
    if shutil.which("chromium") is None:
        return "Debian chromium not installed (bash scripts/install.sh installs it)"
    if shutil.which("node") is None:
        return "node not installed"
    if not (REPO / "node_modules" / "puppeteer-core").is_dir():
        return "node_modules/puppeteer-core missing (run `npm ci` in the repository)"
    from terralod.serve import cesium_dir

    if cesium_dir() is None:
        return "CesiumJS not installed with terralod (scripts/vendor_cesium.py)"
    return None


def _drive(url: str, steps: list[dict], shots: Path, browser: str, timeout_s: int = 240) -> dict:
    """benchmarks/web/site_check.mjs on the site at ``url``, in a fresh context of the session's ``browser``."""
    job = {
        "url": url,
        "shots": str(shots) + "/",
        "steps": steps,
        "timeoutMs": 150000,
        "width": 900,
        "height": 600,
    }
    run = subprocess.run(["node", str(REPO / "benchmarks" / "web" / "site_check.mjs")], input=json.dumps(job),
                         capture_output=True, text=True, timeout=timeout_s, cwd=REPO,
                         env={**os.environ, "TERRALOD_BROWSER_WS": browser})  # fmt: skip
    assert run.stdout.strip(), run.stderr[-2000:]
    return json.loads(run.stdout.strip().splitlines()[-1])


def _cli(args: list[str]) -> None:
    """Run a terralod command in this process; it must succeed."""
    try:
        main(args)
    except SystemExit as exc:
        assert exc.code in (0, None), args


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def change_run(shared_data: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``terralod change BEFORE AFTER -o OUT --site --zones Z``: dod.tif, the zone budget and the site."""
    tmp = tmp_path_factory.mktemp("site")
    zones = tmp / "zones.geojson"
    ring = [[-122.1975, 46.1935], [-122.1830, 46.1925], [-122.1815, 46.2010], [-122.1960, 46.2030]]
    zones.write_text(json.dumps({"type": "FeatureCollection", "features": [{"type": "Feature",
        "properties": {"name": "dome"}, "geometry": {"type": "Polygon", "coordinates": [ring + [ring[0]]]}}]}))  # fmt: skip
    out = tmp / "out"
    _cli(["change", str(shared_data / BEFORE), str(shared_data / AFTER), "-o", str(out), "--site",
          "--zones", str(zones), "--no-views"])  # fmt: skip
    (out / "ring.json").write_text(json.dumps(ring))
    return out


@pytest.fixture(scope="module")
def static_host(change_run: Path):
    """``python -m http.server`` in the site folder, as any host would serve it (no terralod)."""
    port = _free_port()
    proc = subprocess.Popen([sys.executable, "-m", "http.server", str(port), "--bind", "127.0.0.1"],
                            cwd=change_run / "site", stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # fmt: skip
    for _ in range(100):
        try:
            socket.create_connection(("127.0.0.1", port), timeout=1).close()
            break
        except OSError:
            time.sleep(0.1)
    yield f"http://127.0.0.1:{port}/"
    proc.terminate()
    proc.wait(10)


# -- without a browser ----------------------------------------------------------------------------------
def test_pairs_first_last_and_consecutive() -> None:
    from terralod.site.data import pairs_of

    assert pairs_of(["a"]) == []
    assert pairs_of(["a", "b"]) == [("a", "b")]
    names = [f"e{i}" for i in range(6)]
    p = pairs_of(names)
    assert p[0] == ("e0", "e5") and len(p) == len(set(p)) == 9
    assert all((a, b) in p for a, b in zip(names, names[1:], strict=False))  # consecutive
    assert all(("e0", b) in p for b in names[1:])  # the change since the first date, on every date


@settings(max_examples=25, deadline=None)
@given(st.floats(0.02, 0.98), st.floats(0.02, 0.98), st.sampled_from(["EPSG:26910", "EPSG:32633", "EPSG:3857",
                                                                        "EPSG:4326"]))  # fmt: skip
def test_lattice_maps_lonlat_to_the_grid_within_a_centimetre(fx: float, fy: float, crs: str) -> None:
    """The page's bilinear lattice (reimplemented here as site.js does it) against pyproj, anywhere on a
    20 km terrain (0.2° in a geographic CRS) in several projections."""
    from affine import Affine
    from pyproj import Transformer

    from terralod.heightfield import Heightfield
    from terralod.site.data import lattice

    origin = {"EPSG:26910": (560000, 5120000, 10.0), "EPSG:32633": (400000, 5000000, 10.0),
              "EPSG:3857": (1500000, 6000000, 10.0), "EPSG:4326": (14.0, 47.0, 0.0001)}[crs]  # fmt: skip
    x0, y0, step = origin
    z = np.zeros((2000, 2000), np.float32)
    hf = Heightfield(z, np.ones(z.shape, bool), Affine(step, 0, x0, 0, -step, y0), crs=crs)
    L = lattice(hf)
    w, s, e, n = hf.bounds_m
    x, y = w + fx * (e - w), s + fy * (n - s)
    lon, lat = Transformer.from_crs(crs, "EPSG:4326", always_xy=True).transform(x, y)
    k = L["nodes"]
    fi, fj = (lon - L["lon0_deg"]) / L["dlon_deg"], (lat - L["lat0_deg"]) / L["dlat_deg"]
    i, j = int(fi), int(fj)
    ti, tj = fi - i, fj - j
    X, Y = np.reshape(L["x_m"], (k, k)), np.reshape(L["y_m"], (k, k))

    def at(a: np.ndarray) -> float:
        return (a[j, i] * (1 - ti) + a[j, i + 1] * ti) * (1 - tj) + (
            a[j + 1, i] * (1 - ti) + a[j + 1, i + 1] * ti
        ) * tj

    tol = 0.01 if crs != "EPSG:4326" else 1e-7
    assert abs(at(X) - x) < tol and abs(at(Y) - y) < tol


@settings(max_examples=12, deadline=None)
@given(st.sampled_from(["EPSG:26910", "EPSG:32633", "EPSG:3857"]), st.integers(40, 900), st.integers(40, 900),
       st.floats(1.0, 30.0), st.integers(0, 2**16))  # fmt: skip
def test_the_drape_puts_each_cell_centre_on_its_texel_centre(
    crs: str, h: int, w: int, step: float, seed: int
) -> None:
    """The page maps a point's local east/north metres to the overlay's texture coordinates with the drape's
    affine map; a cell's centre, at its own height, must land on ((c + 0.5) / w, (r + 0.5) / h) within the
    fit's stated residual (half a cell off would put the whole drape beside the ground it measures)."""
    from affine import Affine

    from terralod.export.geodesy import Geodesy, ecef_lonlat
    from terralod.heightfield import Heightfield
    from terralod.site.data import drape_map

    origin = {
        "EPSG:26910": (560000, 5120000),
        "EPSG:32633": (400000, 5000000),
        "EPSG:3857": (1500000, 6000000),
    }
    rng = np.random.default_rng(seed)
    z = (500 + 300 * rng.random((h, w))).astype(np.float32)
    hf = Heightfield(
        z, np.ones(z.shape, bool), Affine(step, 0, origin[crs][0], 0, -step, origin[crs][1]), crs=crs
    )
    d = drape_map(hf)
    r, c = rng.integers(0, h, 50), rng.integers(0, w, 50)
    x, y = hf.transform @ (c + 0.5, r + 0.5)
    lon, lat = Geodesy(crs, geographic=True).lonlat(x, y)
    p = ecef_lonlat(lon, lat, z[r, c].astype(np.float64)) - np.asarray(d["centre_ecef"])
    A = np.stack([np.ones(len(p)), p @ np.asarray(d["east"]), p @ np.asarray(d["north"])], axis=1)
    u, v = A @ np.asarray(d["u"]), A @ np.asarray(d["v"])
    assert np.abs(u * w - (c + 0.5)).max() <= d["residual_cells"] + 0.05
    assert np.abs(v * h - (r + 0.5)).max() <= d["residual_cells"] + 0.05


def test_site_folder_is_whole_and_names_no_machine(change_run: Path) -> None:
    site = change_run / "site"
    for f in ("index.html", "site.js", "site.css", "site.json", "README.txt", "cesium/Cesium.js",
              "cesium/LICENSE.md", "epochs/0/tileset.json", "epochs/1/tileset.json", "pairs/0.json"):  # fmt: skip
        assert (site / f).is_file(), f
    m = json.loads((site / "site.json").read_text())
    assert [e["name"] for e in m["epochs"]] == [A, B] and m["pairs"] == [
        {"from": A, "to": B, "url": "pairs/0.json"}
    ]
    # St Helens (EPSG:26910, no vertical CRS in the files): nobody said above what, so no "sea level"
    assert m["heights"]["datum"] == "unknown"
    assert m["heights"]["words"] == "as surveyed (the survey does not say above what)"
    assert m["heights"]["conversion"]["converted_to"].startswith("none: heights written as read")
    pair = json.loads((site / "pairs/0.json").read_text())
    assert pair["drape"]["residual_cells"] < 0.5
    lod = pair["error_model"]["lod_m"]
    for i in (0, 1):  # levels finer than the level of detection are left out; every tile referenced is there
        ts = read_tileset(site / "epochs" / str(i))
        leaves = _leaves(ts["root"])
        assert all(n["geometricError"] <= lod for n in leaves)
        stack = [ts["root"]]
        while stack:
            n = stack.pop()
            stack += n.get("children", [])
            if "content" in n:
                assert (site / "epochs" / str(i) / n["content"]["uri"]).resolve().is_file()
    h, w = pair["grid"]["shape"]
    assert pair["rasters"]["dod"]["levels"][0]["shape"] == [h, w]  # the tiles: tests/test_site_tiles.py
    assert not [p for p in site.rglob(".*")]  # nothing hidden is published (an export's journal, a temporary)
    assert m["rasters"]["step_m"] <= 0.001
    home = str(Path.home())
    for f in [*site.glob("*.json"), *site.glob("pairs/*.json"), site / "README.txt", change_run / "report.html",
              change_run / "summary.json"]:  # fmt: skip
        text = f.read_text(errors="replace")
        assert str(change_run.parent) not in text and home + "/" not in text, f


@pytest.mark.parametrize(
    ("crs", "words"),
    [
        ("EPSG:26910+5703", "above sea level"),
        ("EPSG:26910", "as surveyed"),
        ("EPSG:4979", "above the WGS 84"),
    ],
)
def test_the_page_says_above_sea_level_only_for_a_geoid(crs: str, words: str) -> None:
    from terralod.export.vertical import resolve_vertical_datum
    from terralod.site.plan import height_words

    assert height_words(resolve_vertical_datum(None, crs))["words"].startswith(words)


def test_site_refuses_to_write_over_its_input(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    from terralod.io.reader import sample_heightfield
    from terralod.pyramid.builder import build_store

    store = tmp_path / "in" / "s.terra"
    store.parent.mkdir()
    build_store(sample_heightfield(), store, workers=1)
    with pytest.raises(SystemExit) as exc:
        main(["export", str(store), "--format", "site", "-o", str(tmp_path / "in"), "--overwrite"])
    err = capsys.readouterr().err.strip()
    assert exc.value.code == 2 and len(err.splitlines()) == 1 and store.is_file()


# -- in the browser -----------------------------------------------------------------------------------
def _cells(change_run: Path, n: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, list]:
    """n random valid cells of dod.tif: rows, cols, values, and their centres in lon/lat."""
    import rasterio
    from pyproj import Transformer

    with rasterio.open(change_run / "dod.tif") as ds:
        d = ds.read(1, masked=True).filled(np.nan)
        tr, crs = ds.transform, ds.crs
    rng = np.random.default_rng(seed)
    ok = np.argwhere(np.isfinite(d))
    pick = ok[rng.choice(len(ok), n, replace=False)]
    r, c = pick[:, 0], pick[:, 1]
    x, y = tr.c + (c + 0.5) * tr.a + (r + 0.5) * tr.b, tr.f + (c + 0.5) * tr.d + (r + 0.5) * tr.e
    lon, lat = Transformer.from_crs(crs, "EPSG:4326", always_xy=True).transform(x, y)
    return r, c, d[r, c], [[float(a), float(b)] for a, b in zip(lon, lat, strict=True)]


def test_static_site_answers_like_terralod_change(
    change_run: Path, static_host: str, browser: str, tmp_path: Path
) -> None:
    """From a plain static host: changeAt = dod.tif at 20 cells within the tiles' step; volume of the zone polygon =
    `terralod change --zones` within 0.5 %; the heights CesiumJS samples follow each epoch's DEM within the
    tiles' stored error; the drape is blue on the dome's top and red where dod.tif says the ground dropped;
    the legend is shown; no request leaves loopback, no console error."""
    why = _browser_missing()
    if why:
        pytest.skip(why)
    import rasterio
    from PIL import Image
    from scipy.ndimage import maximum_filter

    rows, cols, vals, pts = _cells(change_run, 20, 3)
    ring = json.loads((change_run / "ring.json").read_text())
    summary = json.loads((change_run / "summary.json").read_text())
    zone = summary["zones"][0]
    with rasterio.open(change_run / "dod.tif") as ds:
        d = ds.read(1, masked=True).filled(np.nan)
    lod = summary["level_of_detection_m"]
    step = json.loads((change_run / "site" / "site.json").read_text())["rasters"]["step_m"] / 2 + 1e-6
    ext = summary["extremes"]["max_rise"]
    drop = maximum_filter(np.nan_to_num(d, nan=0.0), size=3) < -2 * lod  # a 3x3 patch that dropped
    rr, cc = np.unravel_index(int(np.argmin(np.where(drop, d, 0.0))), d.shape)
    assert drop.any()
    (_, _, _, drop_ll) = _cells_at(change_run, [rr], [cc])
    steps = [{"op": "changeAt", "args": [lo, la, A, B]} for lo, la in pts]
    steps.append({"op": "volume", "args": [ring, A, B]})
    hpts = pts[:8]
    steps += [{"op": "setEpoch", "args": [A]}, {"op": "heights", "args": [hpts]},
              {"op": "setEpoch", "args": [B]}, {"op": "heights", "args": [hpts]}]  # fmt: skip
    for name, (lo, la), z in (
        ("rise", (ext["lon_deg"], ext["lat_deg"]), 3800.0),
        ("drop", drop_ll[0], 3800.0),
    ):
        steps += [{"op": "camera", "args": [lo, la, z, 0, -90]}, {"op": "describeChange", "args": [lo, la],
                   "shot": name, "settleMs": 800}]  # fmt: skip
    res = _drive(static_host, steps, tmp_path, browser)
    assert not res["errors"] and not res["blocked"] and not res["failedRequests"], res
    got = res["results"]
    for k in range(20):
        v = got[k]["value"]
        assert v["change_m"] is not None and abs(v["change_m"] - vals[k]) <= step, (k, v, vals[k])
        assert abs(v["after_m"] - v["before_m"] - v["change_m"]) < 0.01
        assert v["lod_m"] == pytest.approx(lod, rel=1e-6)
    vol = got[20]["value"]
    assert vol["net_m3"] == pytest.approx(zone["net_m3"], rel=0.005), (vol, zone)
    assert vol["gain_m3"] == pytest.approx(zone["gain_m3"], rel=0.005)
    assert vol["net_uncertainty_m3"] == pytest.approx(zone["net_uncertainty_m3"], rel=0.01)
    # heights: each epoch's DEM at the sampled cell centres (the leaf tiles are the lossless grid)
    heights = {A: np.array(got[22]["value"], float), B: np.array(got[24]["value"], float)}
    for i, (epoch, dem) in enumerate(((A, BEFORE), (B, AFTER))):
        src = _dem_values(dem, hpts)
        h = heights[epoch]
        ts = read_tileset(change_run / "site" / "epochs" / str(i))
        stored = max(n["geometricError"] for n in _leaves(ts["root"]))
        assert np.isfinite(h).sum() >= 6
        assert np.nanmax(np.abs(h - src)) <= stored + 0.5, (epoch, h - src, stored)  # + picking precision
    # the drape's colours at the dome's top (rose: blue) and at the patch that dropped (red)
    for name, sign in (("rise", +1), ("drop", -1)):
        img = np.asarray(Image.open(tmp_path / f"{name}.png").convert("RGB"), np.float64)
        px = np.median(img[295:306, 445:456].reshape(-1, 3), axis=0)
        if sign > 0:
            assert px[2] > px[0] + 40, (name, px)
        else:
            assert px[0] > px[2] + 40, (name, px)
    assert "rose" in got[-3]["value"] and "dropped" in got[-1]["value"]
    assert res["readyMs"] > 0


def _leaves(node: dict) -> list[dict]:
    kids = node.get("children", [])
    return [node] if not kids else [leaf for k in kids for leaf in _leaves(k)]


def _cells_at(change_run: Path, rows: list, cols: list):
    import rasterio
    from pyproj import Transformer

    with rasterio.open(change_run / "dod.tif") as ds:
        tr, crs = ds.transform, ds.crs
    cc, rr = np.asarray(cols) + 0.5, np.asarray(rows) + 0.5
    x, y = tr.c + cc * tr.a + rr * tr.b, tr.f + cc * tr.d + rr * tr.e
    lon, lat = Transformer.from_crs(crs, "EPSG:4326", always_xy=True).transform(x, y)
    return (
        rows,
        cols,
        None,
        [[float(a), float(b)] for a, b in zip(np.atleast_1d(lon), np.atleast_1d(lat), strict=True)],
    )


def _dem_values(dem: str, pts: list) -> np.ndarray:
    import rasterio
    from pyproj import Transformer

    from conftest import SHARED_DATA as SHARED

    with rasterio.open(SHARED / dem) as ds:
        z = ds.read(1).astype(np.float64)
        x, y = Transformer.from_crs("EPSG:4326", ds.crs, always_xy=True).transform(*np.array(pts).T)
        inv = ~ds.transform
        c = np.floor(inv.a * x + inv.b * y + inv.c).astype(int)
        r = np.floor(inv.d * x + inv.e * y + inv.f).astype(int)
    return z[r, c]


def test_serve_shows_the_same_page(shared_data: Path, browser: str, tmp_path: Path) -> None:
    """`terralod serve` on a store with two epochs serves the same page and contract: the same epochs and
    pair, changeAt at the dome's top as the exported site says."""
    why = _browser_missing()
    if why:
        pytest.skip(why)
    from terralod.serve import make_server
    from terralod.terrain import open_terrain

    store = tmp_path / "sh.terra"
    _cli(["build", str(shared_data / BEFORE), "-o", str(store), "--epoch", A])
    _cli(["update", str(store), str(shared_data / AFTER), "--epoch", B])
    t = open_terrain(store)
    srv, service = make_server(t, "127.0.0.1", 0)
    th = threading.Thread(target=srv.serve_forever, daemon=True)
    th.start()
    try:
        pair = service.site_pair(0)
        assert pair is not None
        big = pair[0]["largest"]
        res = _drive(f"http://127.0.0.1:{srv.server_address[1]}/", [
            {"op": "setSwipe", "args": [A, B, 0.5], "shot": "swipe"},
            {"op": "changeAt", "args": [big["lon_deg"], big["lat_deg"], A, B]}], tmp_path, browser)  # fmt: skip
    finally:
        srv.shutdown()
        srv.server_close()
        t.close()
    assert not res["errors"] and not res["blocked"] and not res["failedRequests"], res
    assert res["epochs"] == [A, B] and res["pairs"] == [[A, B]]
    assert res["results"][1]["value"]["change_m"] == pytest.approx(big["value_m"], abs=0.01)


def _plant_series(src: Path, out: Path) -> tuple[list[Path], dict]:
    """Three epochs of a real SRTM crop (EPSG:4326): a deposit growing to +30 m (a Gaussian mound) and a
    scarp deepening to -20 m, on the same grid; their true volumes at the last epoch (cell areas on the
    ellipsoid's sphere of the latitude)."""
    import rasterio

    with rasterio.open(src) as ds:
        z = ds.read(1).astype(np.float32)
        prof = ds.profile
        tr = ds.transform
    h, w = z.shape
    rr, cc = np.mgrid[0:h, 0:w]
    mound = np.exp(-(((rr - 90) / 14.0) ** 2 + ((cc - 160) / 14.0) ** 2))
    scarp = np.exp(-(((rr - 180) / 12.0) ** 2 + ((cc - 80) / 12.0) ** 2))
    lat = tr.f + (rr + 0.5) * tr.e
    cell_m2 = (np.radians(tr.a) * 6371008.8 * np.cos(np.radians(lat))) * (np.radians(-tr.e) * 6371008.8)
    paths = []
    for i, f in enumerate((0.0, 0.5, 1.0)):
        e = z + f * (30.0 * mound - 20.0 * scarp)
        p = out / f"epoch{i}.tif"
        with rasterio.open(p, "w", **prof) as dst:
            dst.write(e.astype(prof["dtype"]), 1)
        paths.append(p)
    truth = {"mound_m3": float((30.0 * mound * cell_m2)[mound > 0.01].sum()),
             "mound_lonlat": (tr.c + 160.5 * tr.a, tr.f + 90.5 * tr.e),
             "scarp_lonlat": (tr.c + 80.5 * tr.a, tr.f + 180.5 * tr.e),
             "mound_ring": [[tr.c + (160.5 + 40 * np.cos(t)) * tr.a, tr.f + (90.5 + 40 * np.sin(t)) * tr.e]
                            for t in np.linspace(0, 2 * np.pi, 24, endpoint=False)]}  # fmt: skip
    return paths, truth


def test_planted_series_site(shared_data: Path, browser: str, tmp_path: Path) -> None:
    """A three-epoch series planted on a geographic SRTM crop (another DEM than St Helens): the site carries
    first -> last and both consecutive pairs; in the browser the change at the deposit's top and the scarp's
    bottom is the planted +30 / -20 m, the volume inside a ring around the deposit is the planted volume
    within 3 %, the drape is blue on the deposit and red in the scarp, and the series has its play button
    and volume-against-time chart."""
    why = _browser_missing()
    if why:
        pytest.skip(why)
    from PIL import Image

    paths, truth = _plant_series(shared_data / "dem" / "srtm1_crop256_alpine.tif", tmp_path)
    out = tmp_path / "out"
    dates = ["2019-06-01", "2020-06-01", "2021-06-01"]
    _cli(["change", *map(str, paths), "-o", str(out), "--site", "--no-views", "--dates", ",".join(dates)])
    m = json.loads((out / "site" / "site.json").read_text())
    assert [e["name"] for e in m["epochs"]] == dates
    assert [(p["from"], p["to"]) for p in m["pairs"]] == [
        (dates[0], dates[2]),
        (dates[0], dates[1]),
        (dates[1], dates[2]),
    ]
    port = _free_port()
    proc = subprocess.Popen([sys.executable, "-m", "http.server", str(port), "--bind", "127.0.0.1"],
                            cwd=out / "site", stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # fmt: skip
    try:
        time.sleep(0.5)
        (mlo, mla), (slo, sla) = truth["mound_lonlat"], truth["scarp_lonlat"]
        steps = [
            {"op": "changeAt", "args": [mlo, mla, dates[0], dates[2]]},
            {"op": "changeAt", "args": [slo, sla, dates[0], dates[2]]},
            {"op": "changeAt", "args": [mlo, mla, dates[1], dates[2]]},
            {"op": "volume", "args": [truth["mound_ring"], dates[0], dates[2]]},
            {"op": "setEpoch", "args": [dates[2]]},
            {"op": "camera", "args": [mlo, mla, 9000.0, 0, -90]},
            {"op": "describeChange", "args": [mlo, mla], "shot": "mound", "settleMs": 800},
            {"op": "click", "args": [450, 300]},  # a visitor clicks the deposit's top
            {"op": "press", "args": ["measure"]},  # ... then draws a square around it
            {"op": "click", "args": [390, 220]},  # (the panel ends at x = 374)
            {"op": "click", "args": [510, 220]},
            {"op": "click", "args": [510, 380]},
            {"op": "click", "args": [390, 380]},
            {"op": "press", "args": ["measure"]},
            {"op": "camera", "args": [slo, sla, 9000.0, 0, -90]},
            {"op": "describeChange", "args": [slo, sla], "shot": "scarp", "settleMs": 800},
            {"op": "dom"},
        ]
        res = _drive(f"http://127.0.0.1:{port}/", steps, tmp_path, browser)
    finally:
        proc.terminate()
        proc.wait(10)
    assert not res["errors"] and not res["blocked"] and not res["failedRequests"], res
    got = [r.get("value") for r in res["results"]]
    assert got[0]["change_m"] == pytest.approx(30.0, abs=1.5)  # resampled onto the UTM grid: the top's cell
    assert got[1]["change_m"] == pytest.approx(-20.0, abs=1.5)
    assert got[2]["change_m"] == pytest.approx(15.0, abs=1.0)
    assert got[3]["net_m3"] == pytest.approx(truth["mound_m3"], rel=0.03), (got[3], truth)
    for name, sign in (("mound", 1), ("scarp", -1)):
        img = np.asarray(Image.open(tmp_path / f"{name}.png").convert("RGB"), np.float64)
        px = np.median(img[295:306, 445:456].reshape(-1, 3), axis=0)
        assert (px[2] - px[0]) * sign > 40, (name, px)
    clicked, drawn = got[7], got[13]
    assert clicked.startswith("Here the ground rose") and "between 1 Jun 2019 and 1 Jun 2021" in clicked, (
        clicked
    )
    assert "net gain" in drawn and "Olympic swimming pools" in drawn, drawn
    dom = got[-1]
    assert dom["play"] and dom["legend"] and dom["chartPoints"] == 3 and dom["north"], dom
    assert (
        re.fullmatch(r"\d+ k?m", dom["scale"]) and "rose" in dom["legendText"] and "Between" in dom["summary"]
    )


def test_a_series_site_updates_only_what_a_new_survey_changed(shared_data: Path, tmp_path: Path) -> None:
    """`terralod update` of a store with a third survey, then `export --format site --update`: the site is a
    fresh export's bytes, the files that did not change are the same inodes (not rewritten), and the
    rewritten ones are listed; an update with nothing new rewrites nothing."""
    paths, _ = _plant_series(shared_data / "dem" / "srtm1_crop256_alpine.tif", tmp_path)
    store = tmp_path / "series.terra"
    dates = ["2019-06-01", "2020-06-01", "2021-06-01"]
    _cli(["build", str(paths[0]), "-o", str(store), "--epoch", dates[0]])
    _cli(["update", str(store), str(paths[1]), "--epoch", dates[1]])
    site = tmp_path / "site"
    _cli(["export", str(store), "--format", "site", "-o", str(site)])
    files = {f.relative_to(site).as_posix(): f.stat().st_ino for f in site.rglob("*") if f.is_file()}
    _cli(["update", str(store), str(paths[2]), "--epoch", dates[2]])
    _cli(["export", str(store), "--format", "site", "-o", str(tmp_path / "fresh")])
    _cli(["export", str(store), "--format", "site", "-o", str(site), "--update"])
    got = {f.relative_to(site).as_posix(): f for f in site.rglob("*") if f.is_file()}
    fresh = {
        f.relative_to(tmp_path / "fresh").as_posix(): f
        for f in (tmp_path / "fresh").rglob("*")
        if f.is_file()
    }
    assert sorted(got) == sorted(fresh)
    assert all(got[k].read_bytes() == fresh[k].read_bytes() for k in got)
    kept = [k for k in got if files.get(k) == got[k].stat().st_ino]
    assert "site.json" not in kept  # the manifest names the new epoch and its pairs
    assert len(kept) > len(got) // 2  # CesiumJS, the page and the earlier epochs' tiles were not rewritten
    assert any(k.startswith("epochs/2/") for k in got) and not any(k.startswith("epochs/2/") for k in kept)
    inodes = {k: f.stat().st_ino for k, f in got.items()}
    _cli(["export", str(store), "--format", "site", "-o", str(site), "--update"])
    assert {f.relative_to(site).as_posix(): f.stat().st_ino for f in site.rglob("*") if f.is_file()} == inodes
