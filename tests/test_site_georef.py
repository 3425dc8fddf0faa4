"""The change site on pairs in other frames: St Helens 2000/2007 resampled into longitude/latitude
(EPSG:4326) and into Washington South state plane in US survey feet with NAVD88 heights in US survey feet
(EPSG:2927+6360), both with rasterio's own warp. ``terralod change --site`` on each: the page's answers (the
change at a clicked point, the volume of a drawn polygon) land on the right cells of the ``dod.tif`` it
wrote, and ``dod.tif`` lies where the metre pair's difference lies (placement and units: metres out).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from tests.test_site import AFTER, BEFORE, _browser_missing, _cells, _cli, _drive, _free_port

A, B = "2000-09-25", "2007-07-05"
RING = [[-122.1975, 46.1935], [-122.1830, 46.1925], [-122.1815, 46.2010], [-122.1960, 46.2030]]
US_FT = 1200.0 / 3937.0


def _warp(src: Path, dst: Path, crs: str, z_scale: float = 1.0) -> Path:
    """``src`` resampled (bilinear) into ``crs`` at about its own ground spacing; heights times z_scale."""
    import rasterio
    from rasterio.warp import Resampling, calculate_default_transform, reproject

    with rasterio.open(src) as ds:
        t, w, h = calculate_default_transform(ds.crs, crs, ds.width, ds.height, *ds.bounds)
        out = np.full((h, w), np.nan, np.float32)
        reproject(ds.read(1).astype(np.float32), out, src_transform=ds.transform, src_crs=ds.crs, dst_transform=t,
                  dst_crs=crs, resampling=Resampling.bilinear, src_nodata=np.nan, dst_nodata=np.nan)  # fmt: skip
    with rasterio.open(dst, "w", driver="GTiff", width=w, height=h, count=1, dtype="float32", crs=crs,
                       transform=t, nodata=np.nan) as o:  # fmt: skip
        o.write(out * np.float32(z_scale), 1)
    return dst


def _dod_at(dod: Path, lonlat: list) -> np.ndarray:
    """dod.tif's value at each (lon, lat): the cell that holds it."""
    import rasterio
    from pyproj import Transformer

    with rasterio.open(dod) as ds:
        d = ds.read(1, masked=True).filled(np.nan)
        x, y = Transformer.from_crs("EPSG:4326", ds.crs, always_xy=True).transform(*np.array(lonlat).T)
        inv = ~ds.transform
        c = np.floor(inv.a * x + inv.b * y + inv.c).astype(int)
        r = np.floor(inv.d * x + inv.e * y + inv.f).astype(int)
    ok = (r >= 0) & (r < d.shape[0]) & (c >= 0) & (c < d.shape[1])
    return np.where(ok, d[np.clip(r, 0, d.shape[0] - 1), np.clip(c, 0, d.shape[1] - 1)], np.nan)


@pytest.fixture(scope="module")
def metre_run(shared_data: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("metre") / "out"
    _cli(["change", str(shared_data / BEFORE), str(shared_data / AFTER), "-o", str(out), "--no-views"])
    return out


@pytest.mark.parametrize(
    ("frame", "crs", "z_scale"), [("lonlat", "EPSG:4326", 1.0), ("feet", "EPSG:2927+6360", 1.0 / US_FT)]
)
def test_site_answers_land_on_the_right_cells(
    shared_data: Path, metre_run: Path, browser: str, tmp_path: Path, frame: str, crs: str, z_scale: float
) -> None:
    why = _browser_missing()
    if why:
        pytest.skip(why)
    import subprocess
    import sys
    import time

    before = _warp(shared_data / BEFORE, tmp_path / f"st_helens_{A}_{frame}.tif", crs, z_scale)
    after = _warp(shared_data / AFTER, tmp_path / f"st_helens_{B}_{frame}.tif", crs, z_scale)
    zones = tmp_path / "zones.geojson"
    zones.write_text(json.dumps({"type": "FeatureCollection", "features": [{"type": "Feature",
        "properties": {"name": "dome"}, "geometry": {"type": "Polygon", "coordinates": [RING + [RING[0]]]}}]}))  # fmt: skip
    out = tmp_path / "out"
    _cli(["change", str(before), str(after), "-o", str(out), "--site", "--zones", str(zones), "--no-views"])
    summary = json.loads((out / "summary.json").read_text())
    # placement and units: where the metre pair rose 100+ m, this pair's dod.tif rose as much (in metres)
    _, _, vals, pts = _cells(out, 40, 5)
    ref = _dod_at(metre_run / "dod.tif", pts)
    both = np.isfinite(ref) & np.isfinite(vals)
    assert both.sum() >= 30
    assert np.median(np.abs(vals[both] - ref[both])) < 1.0, (frame, vals[both] - ref[both])
    zone = summary["zones"][0]
    metre_zone = None  # the dome's volume in metres³ whatever the frame: within the resampling's few %
    _cli(["change", str(shared_data / BEFORE), str(shared_data / AFTER), "-o", str(tmp_path / "m"),
          "--zones", str(zones), "--no-views"])  # fmt: skip
    metre_zone = json.loads((tmp_path / "m" / "summary.json").read_text())["zones"][0]
    assert zone["net_m3"] == pytest.approx(metre_zone["net_m3"], rel=0.03), (zone, metre_zone)
    # the page: changeAt on 20 cells = dod.tif, the polygon's volume = the --zones budget
    port = _free_port()
    proc = subprocess.Popen([sys.executable, "-m", "http.server", str(port), "--bind", "127.0.0.1"],
                            cwd=out / "site", stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # fmt: skip
    try:
        time.sleep(1.0)
        steps = [{"op": "changeAt", "args": [lo, la, A, B]} for lo, la in pts[:20]]
        steps.append({"op": "volume", "args": [RING, A, B]})
        res = _drive(f"http://127.0.0.1:{port}/", steps, tmp_path, browser)
    finally:
        proc.terminate()
        proc.wait(10)
    assert not res["errors"] and not res["failedRequests"], res
    got = res["results"]
    for k in range(20):
        v = got[k]["value"]
        assert v["change_m"] is not None and abs(v["change_m"] - vals[k]) <= 0.01, (frame, k, v, vals[k])
    vol = got[20]["value"]
    assert vol["net_m3"] == pytest.approx(zone["net_m3"], rel=0.005), (frame, vol, zone)
