"""terralod change: known volumes (a cone, a trench) measured within 0.5 %, known horizontal shifts of a real
DEM recovered within 0.1 px (both estimators, sub-pixel and several pixels, equal and unequal grids), the
net change across two CRSs equal to the change on one grid within 1 %, zone budgets, the St Helens pair's
golden figures, the CLI contract (keys, files, exit codes) and bad inputs (one line, nothing written)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import rasterio
from affine import Affine
from hypothesis import given, settings
from hypothesis import strategies as st
from rasterio.transform import from_origin

from terralod import read_heightfield
from terralod.change.coregister import coregister, nmad
from terralod.change.difference import align, dem_of_difference
from terralod.change.volumes import measure_change, series_volumes
from terralod.cli import main
from terralod.heightfield import Heightfield

from conftest import SHARED_DATA

CONTRACT_KEYS = (
    "gain_m3", "loss_m3", "net_m3", "gain_m3_above_lod", "loss_m3_above_lod", "net_m3_above_lod",
    "net_uncertainty_m3", "area_gain_m2", "area_loss_m2", "sigma_m", "level_of_detection_m", "max_rise_m",
    "max_drop_m", "shift_m", "zones",
)  # fmt: skip
CRS = "EPSG:32611"


def real_crop(n: int = 160) -> Heightfield:
    """A crop of the Big Tujunga SRTM DEM (30 m, UTM 11N): steep real relief, in every aspect."""
    p = SHARED_DATA / "dem" / "big_tujunga_srtm30m_utm11.tif"
    if not p.is_file():
        pytest.skip(f"real terrain data not present at {SHARED_DATA} (../shared/data beside the repository)")
    hf = read_heightfield(p)
    r0, c0 = 200, 420
    z = hf.elevation_m[r0 : r0 + n, c0 : c0 + n]
    return Heightfield(z, np.ones(z.shape, bool), hf.transform * Affine.translation(c0, r0), crs=hf.crs)


def synthetic_base(n: int = 200, spacing: float = 2.0) -> Heightfield:
    """A rough, non-planar synthetic surface (sum of sines) in UTM 11N, for exact-volume tests."""
    yy, xx = np.mgrid[0:n, 0:n].astype(np.float64)
    z = 500 + 8 * np.sin(xx / 13.0) * np.cos(yy / 17.0) + 0.05 * xx + 3 * np.sin((xx + 2 * yy) / 29.0)
    return Heightfield(z, np.ones(z.shape, bool), from_origin(400000.0, 3800000.0, spacing, spacing), crs=CRS)


def cone(hf: Heightfield, cx: float, cy: float, radius_m: float, height_m: float) -> np.ndarray:
    rows, cols = np.indices(hf.shape)
    x, y = hf.world_xy(rows, cols)
    r = np.hypot(x - cx, y - cy)
    return np.clip(height_m * (1 - r / radius_m), 0, None)


def trench(hf, cx, cy, length_m, top_w_m, bottom_w_m, depth_m, angle_deg, ramp_m=10.0) -> np.ndarray:
    """A straight trench with a trapezoidal cross-section, ends ramped over ``ramp_m``, rotated; its volume
    is the cross-section's area times (length + ramp)."""
    rows, cols = np.indices(hf.shape)
    x, y = hf.world_xy(rows, cols)
    a = math.radians(angle_deg)
    u = (x - cx) * math.cos(a) + (y - cy) * math.sin(a)  # along
    v = -(x - cx) * math.sin(a) + (y - cy) * math.cos(a)  # across
    half_top, half_bot = top_w_m / 2, bottom_w_m / 2
    d = np.where(np.abs(v) <= half_bot, depth_m, depth_m * (half_top - np.abs(v)) / (half_top - half_bot))
    d = np.clip(d, 0, None) * np.clip((length_m / 2 + ramp_m - np.abs(u)) / ramp_m, 0, 1)
    return -d


def with_change(hf: Heightfield, dz: np.ndarray) -> Heightfield:
    return Heightfield(hf.elevation_m + dz, hf.valid, hf.transform, crs=hf.crs)


def write_tif(path: Path, hf: Heightfield, unit: str | None = None) -> Path:
    with rasterio.open(
        path, "w", driver="GTiff", width=hf.width, height=hf.height, count=1, dtype="float32", crs=hf.crs,
        transform=hf.transform, nodata=np.nan,
    ) as ds:  # fmt: skip
        ds.write(hf.elevation_m.astype(np.float32), 1)
        if unit:
            ds.set_band_unit(1, unit)
    return path


def run(capsys, *args) -> tuple[int, str, str]:
    try:
        main([str(a) for a in args])
        code = 0
    except SystemExit as exc:
        code = int(exc.code or 0)
    out = capsys.readouterr()
    return code, out.out, out.err


# -- analytic volumes ----------------------------------------------------------------------------------
@settings(max_examples=6, deadline=None)
@given(
    radius=st.floats(50, 110), height=st.floats(5, 40), length=st.floats(60, 120), depth=st.floats(1, 6),
    angle=st.floats(0, 180),
)  # fmt: skip
def test_cone_and_trench_volumes_within_half_percent(radius, height, length, depth, angle) -> None:
    base = synthetic_base(220)
    w, s, e, n = base.bounds_m
    cone_v = math.pi * radius**2 * height / 3
    top, bot = 24.0, 8.0
    trench_v = (length + 10.0) * depth * (top + bot) / 2
    # the cone's apex on a cell centre (centres at w + 1 + 2k); cone and trench apart, both inside
    dz = cone(base, w + 131, s + 201, radius, height) + trench(
        base, w + 330, s + 220, length, top, bot, depth, angle
    )
    r = measure_change(base, with_change(base, dz), sigma_m=0.05)
    s_ = r.summary
    assert s_["shift_m"] == [0.0, 0.0, 0.0]  # stable ground identical: nothing to fit
    assert s_["gain_m3"] == pytest.approx(cone_v, rel=5e-3)
    assert s_["loss_m3"] == pytest.approx(trench_v, rel=5e-3)
    assert s_["net_m3"] == pytest.approx(cone_v - trench_v, abs=5e-3 * (cone_v + trench_v))
    assert s_["max_rise_m"] == pytest.approx(height, abs=1e-3)
    assert s_["max_drop_m"] == pytest.approx(depth, abs=1e-3)
    # thresholded figures never exceed the unthresholded ones, and uncertainties are positive
    assert 0 < s_["gain_m3_above_lod"] <= s_["gain_m3"]
    assert 0 < s_["loss_m3_above_lod"] <= s_["loss_m3"]
    assert s_["net_uncertainty_m3"] > 0 and s_["level_of_detection_m"] == pytest.approx(1.96 * 0.05, rel=1e-3)


# -- co-registration -----------------------------------------------------------------------------------
@pytest.mark.parametrize("method", ["xdem", "terralod"])
@pytest.mark.parametrize("shift_px", [(0.37, -0.21), (2.6, 3.3)])
def test_shift_of_a_real_dem_recovered_within_a_tenth_of_a_pixel(method, shift_px) -> None:
    """AFTER is BEFORE's own samples on a grid moved by (sx, sy) px (no resampling: an exact shift), plus
    a vertical offset and a cone of real change; the fit must undo the move."""
    before = real_crop()
    px = before.spacing_m[0]
    sx, sy = shift_px
    bump = cone(before, before.origin_m[0] + 1500, before.origin_m[1] - 1500, 600, 60)
    z = before.elevation_m + 4.0 + bump
    after = Heightfield(z, before.valid, before.transform * Affine.translation(sx, -sy), crs=before.crs)
    pair = align(before, after)
    assert not pair.same_grid
    co = coregister(pair, method=method)
    dx, dy, dz = co.shift_m
    assert math.hypot(dx / px + sx, dy / px + sy) < 0.1, co.shift_m
    assert dz == pytest.approx(-4.0, abs=0.5)
    assert co.nmad_after_m < co.nmad_before_m


def test_subpixel_resampled_shift_recovered() -> None:
    """A shift made by resampling (cubic spline) instead of moving the grid."""
    from scipy import ndimage

    before = real_crop()
    z = ndimage.shift(before.elevation_m.astype(np.float64), (0.45, -0.3), order=3, mode="nearest")
    after = Heightfield(z, before.valid, before.transform, crs=before.crs)
    co = coregister(align(before, after), method="terralod")
    px = before.spacing_m[0]
    # the surface moved 0.3 px west and 0.45 px south: the fix moves it back east and north
    assert math.hypot(co.shift_m[0] / px - 0.3, co.shift_m[1] / px - 0.45) < 0.1, co.shift_m


def test_measure_change_applies_the_shift() -> None:
    before = real_crop()
    bump = cone(before, before.origin_m[0] + 2400, before.origin_m[1] - 2400, 900, 80)
    noise = np.random.default_rng(3).normal(0.0, 0.5, before.shape)  # survey noise of AFTER, 0.5 m
    after = Heightfield(before.elevation_m + bump + noise, before.valid,
                        before.transform * Affine.translation(1.3, 0.0), crs=before.crs)  # fmt: skip
    r = measure_change(before, after, method="terralod")
    px = before.spacing_m[0]
    assert r.summary["shift_m"][0] / px == pytest.approx(-1.3, abs=0.1)
    truth = math.pi * 900**2 * 80 / 3
    assert r.summary["net_m3"] == pytest.approx(truth, rel=0.02)
    no = measure_change(before, after, coregistration=False)
    assert no.summary["shift_m"] == [0.0, 0.0, 0.0]
    assert no.summary["sigma_m"] > 3 * r.summary["sigma_m"]  # misregistration inflates the stable NMAD
    assert r.summary["sigma_source"].startswith("NMAD")
    assert r.summary["sigma_m"] == pytest.approx(0.5, rel=0.25)  # bilinear resampling averages some noise


# -- different CRS -------------------------------------------------------------------------------------
@pytest.mark.parametrize("dst_crs", ["EPSG:32610", "EPSG:4326"])
def test_net_change_across_crs_equals_one_grid(tmp_path: Path, dst_crs: str) -> None:
    """AFTER in the neighbouring UTM zone at 25 m, or in lon/lat degrees (the reader takes it to UTM on
    its own grid): resampled onto BEFORE's grid, the net change is the one-grid figure within 1 %."""
    from rasterio.warp import Resampling, calculate_default_transform, reproject

    before = real_crop()
    c = before.origin_m[0] + 2400, before.origin_m[1] - 2400
    bump = cone(before, *c, 1200, 100)
    after = with_change(before, bump)
    one_grid = measure_change(before, after, coregistration=False, sigma_m=0.5).summary["net_m3"]
    res = {"resolution": 25.0} if dst_crs != "EPSG:4326" else {}
    t, w, h = calculate_default_transform(before.crs, dst_crs, before.width, before.height, *before.bounds_m,
                                          **res)  # fmt: skip
    out = np.full((h, w), np.nan, np.float32)
    reproject(after.elevation_m, out, src_transform=after.transform, src_crs=after.crs, dst_transform=t,
              dst_crs=dst_crs, dst_nodata=np.nan, resampling=Resampling.cubic)  # fmt: skip
    path = tmp_path / "after_other_crs.tif"
    with rasterio.open(path, "w", driver="GTiff", width=w, height=h, count=1, dtype="float32", crs=dst_crs,
                       transform=t, nodata=np.nan) as ds:  # fmt: skip
        ds.write(out, 1)
    after2 = read_heightfield(path)
    plain = measure_change(before, after2, sigma_m=0.5, coregistration=False)
    assert any("reprojected" in n or "resampled" in n for n in plain.summary["alignment_notes"])
    assert plain.summary["grid"]["resampled"]
    assert plain.summary["net_m3"] == pytest.approx(one_grid, rel=0.01)
    # co-registered: the two resamplings' own bias (a few cm on this steep 30 m DEM) is fitted as a vertical
    # shift, the horizontal shift stays within a fifth of a pixel
    r = measure_change(before, after2, sigma_m=0.5, method="terralod").summary
    assert r["net_m3"] == pytest.approx(one_grid, rel=0.01)
    assert math.hypot(*r["shift_m"][:2]) < 0.2 * before.spacing_m[0] and abs(r["shift_m"][2]) < 0.2


def test_stable_mask_raster(tmp_path: Path) -> None:
    """--stable: a raster mask (non-zero = stable) on its own grid; the fit uses only those cells."""
    from terralod.change.coregister import read_stable_mask

    before = real_crop()
    bump = cone(before, before.origin_m[0] + 2400, before.origin_m[1] - 2400, 900, 80)
    after = Heightfield(before.elevation_m + bump, before.valid, before.transform * Affine.translation(0.6, -0.4),
                        crs=before.crs)  # fmt: skip
    m = np.ones(before.shape, np.uint8)
    m[:, : before.width // 2] = 0  # only the east half is declared stable
    p = tmp_path / "stable.tif"
    with rasterio.open(p, "w", driver="GTiff", width=before.width, height=before.height, count=1, dtype="uint8",
                       crs=before.crs, transform=before.transform) as ds:  # fmt: skip
        ds.write(m, 1)
    mask = read_stable_mask(p, before)
    assert mask[:, before.width // 2 + 1 :].all() and not mask[:, : before.width // 2].any()
    r = measure_change(before, after, stable=mask, method="terralod")
    px = before.spacing_m[0]
    assert math.hypot(r.summary["shift_m"][0] / px + 0.6, r.summary["shift_m"][1] / px + 0.4) < 0.1
    assert r.stable[:, : before.width // 2].sum() == 0


# -- zones and series ----------------------------------------------------------------------------------
def test_zone_budgets_in_a_named_crs_and_lonlat(tmp_path: Path) -> None:
    from pyproj import Transformer

    base = synthetic_base()
    w, s, e, n = base.bounds_m
    dz = cone(base, w + 100, s + 200, 80, 20) + trench(base, w + 290, s + 200, 120, 24, 8, 3, 90)
    after = with_change(base, dz)
    west = [[w, s], [w + 200, s], [w + 200, n], [w, n], [w, s]]
    east = [[w + 200, s], [e, s], [e, n], [w + 200, n], [w + 200, s]]
    zones = tmp_path / "zones.geojson"
    zones.write_text(json.dumps({
        "type": "FeatureCollection", "crs": {"type": "name", "properties": {"name": "urn:ogc:def:crs:EPSG::32611"}},
        "features": [{"type": "Feature", "properties": {"name": n_}, "geometry": {"type": "Polygon", "coordinates": [ring]}}
                     for n_, ring in (("cone side", west), ("trench side", east))],
    }))  # fmt: skip
    r = measure_change(base, after, sigma_m=0.05, zones=zones).summary
    a, b = r["zones"]
    assert (a["name"], b["name"]) == ("cone side", "trench side")
    assert a["gain_m3"] == pytest.approx(r["gain_m3"], rel=1e-9) and a["loss_m3"] == 0
    assert b["loss_m3"] == pytest.approx(r["loss_m3"], rel=1e-9) and b["gain_m3"] == 0
    assert a["net_m3"] + b["net_m3"] == pytest.approx(r["net_m3"], rel=1e-9)
    # the same west zone in lon/lat (RFC 7946 default, no crs member)
    tr = Transformer.from_crs(CRS, "EPSG:4326", always_xy=True)
    ll = [list(tr.transform(x, y)) for x, y in west]
    zones2 = tmp_path / "ll.geojson"
    zones2.write_text(json.dumps({"type": "Feature", "properties": {"name": "ll"},
                                  "geometry": {"type": "Polygon", "coordinates": [ll]}}))  # fmt: skip
    z2 = measure_change(base, after, sigma_m=0.05, zones=zones2).summary["zones"][0]
    assert z2["gain_m3"] == pytest.approx(a["gain_m3"], rel=0.02)


def test_series_volume_grows_with_the_dome() -> None:
    base = synthetic_base(120)
    w, s, e, n = base.bounds_m
    heights = [0.0, 5.0, 12.0, 20.0]
    epochs = [with_change(base, cone(base, (w + e) / 2, (s + n) / 2, 70, h)) for h in heights]
    rows = series_volumes(epochs, ["2000-01-01", "2001-01-01", "2002-01-01", "2003-01-01"], sigma_m=0.1)
    nets = [r["net_m3"] for r in rows]
    assert nets[0] == 0 and all(b > a for a, b in zip(nets, nets[1:], strict=False))
    assert nets[-1] == pytest.approx(math.pi * 70**2 * 20 / 3, rel=0.01)


def test_nmad_of_normal_noise() -> None:
    v = np.random.default_rng(1).normal(0, 2.0, 200_000)
    assert nmad(v) == pytest.approx(2.0, rel=0.02)


# -- St Helens golden ----------------------------------------------------------------------------------
def test_st_helens_pair_golden(tmp_path: Path, capsys) -> None:
    d = SHARED_DATA / "change"
    before, after = d / "st_helens_crater_2000-09-25_10m.tif", d / "st_helens_crater_2007-07-05_10m.tif"
    if not before.is_file():
        pytest.skip(f"St Helens pair not present at {d} (../shared/data beside the repository)")
    out = tmp_path / "sth"
    code, so, se = run(capsys, "change", before, after, "-o", out, "--no-views")
    assert code == 0, se
    s = json.loads((out / "summary.json").read_text())
    # golden figures (this command on the shared files); no threshold: exact sums over the 10 m cells
    assert s["gain_m3"] == pytest.approx(99_773_975, rel=1e-4)
    assert s["loss_m3"] == pytest.approx(728_477, rel=1e-3)
    assert s["net_m3"] == pytest.approx(99_045_498, rel=1e-4)
    assert s["max_rise_m"] == pytest.approx(205.517, abs=0.01)
    assert s["max_drop_m"] == pytest.approx(25.130, abs=0.01)
    assert s["shift_m"] == [0.0, 0.0, 0.0]  # stable ground copied: no shift to fit
    # sigma cannot be measured (difference exactly 0 outside the surveys): the assumed 1 m, said so
    assert s["sigma_m"] == 1.0 and s["sigma_source"].startswith("assumed")
    assert "sigma cannot be measured" in se
    assert s["area_gain_m2"] == pytest.approx(1_787_300, rel=1e-3)
    assert 1e6 < s["net_uncertainty_m3"] < 5e6
    assert "25 Sep 2000 and 5 Jul 2007" in so and "million m³" in so
    # with a stated sigma: the area beyond the 0.98 m LoD is the "1.9 km²"
    s2 = measure_change(read_heightfield(before), read_heightfield(after), sigma_m=0.5).summary
    assert s2["sigma_source"].startswith("given") and s2["area_gain_m2"] == pytest.approx(1.88e6, rel=0.01)
    assert s2["gain_m3_above_lod"] == pytest.approx(99.7e6, rel=0.002)


# -- CLI contract and bad inputs -----------------------------------------------------------------------
@pytest.fixture(scope="module")
def pair_files(tmp_path_factory) -> tuple[Path, Path, Heightfield]:
    tmp = tmp_path_factory.mktemp("change")
    base = synthetic_base(100, 4.0)
    w, s, e, n = base.bounds_m
    dz = cone(base, w + 120, s + 200, 60, 15) + trench(base, w + 280, s + 200, 100, 24, 8, 3, 30)
    return (write_tif(tmp / "before_2001-02-03.tif", base), write_tif(tmp / "after_2004-05-06.tif", with_change(base, dz)),
            base)  # fmt: skip


def test_cli_contract(pair_files, tmp_path: Path, capsys) -> None:
    before, after, base = pair_files
    w, s, e, n = base.bounds_m
    zones = tmp_path / "z.geojson"
    ring = [[w, s], [w + 200, s], [w + 200, n], [w, n], [w, s]]
    zones.write_text(json.dumps({"type": "FeatureCollection", "crs": {"type": "name", "properties": {"name": CRS}},
        "features": [{"type": "Feature", "properties": {"name": "west"}, "geometry": {"type": "Polygon", "coordinates": [ring]}}]}))  # fmt: skip
    out = tmp_path / "out"
    code, so, se = run(capsys, "change", before, after, "-o", out, "--zones", zones, "--sigma-m", "0.1")
    assert code == 0, se
    s_ = json.loads((out / "summary.json").read_text())
    for k in CONTRACT_KEYS:
        assert k in s_, k
    assert s_["gain_m3"] > 0 and s_["loss_m3"] > 0 and s_["max_drop_m"] > 0
    assert len(s_["shift_m"]) == 3
    assert [z["name"] for z in s_["zones"]] == ["west"]
    for k in ("gain_m3", "loss_m3", "net_m3", "gain_m3_above_lod", "net_uncertainty_m3", "area_gain_m2"):
        assert k in s_["zones"][0]
    assert s_["before"]["date"] == "2001-02-03" and s_["after"]["date"] == "2004-05-06"
    with rasterio.open(out / "dod.tif") as ds:
        dod = ds.read(1)
        assert ds.crs.to_epsg() == 32611 and dod.shape == base.shape
    assert np.nansum(dod) * 16 == pytest.approx(s_["net_m3"], rel=1e-5)
    page = (out / "report.html").read_text()
    assert page.count("data:image/png;base64,") >= 3
    assert "http://" not in page and "https://" not in page  # opens offline: nothing fetched
    assert "3 Feb 2001" in page and "±" in page
    # without --zones: an empty list; an existing output needs --overwrite
    code, _, se = run(capsys, "change", before, after, "-o", out, "--no-views")
    assert code == 2 and "--overwrite" in se
    code, _, se = run(capsys, "change", before, after, "-o", out, "--no-views", "--overwrite")
    assert code == 0, se
    assert json.loads((out / "summary.json").read_text())["zones"] == []


def _one_line(err: str, *needles: str) -> None:
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("terralod: "), err
    for nd in needles:
        assert nd in lines[0], (nd, lines[0])


def test_bad_inputs(pair_files, tmp_path: Path, capsys) -> None:
    before, after, base = pair_files
    out = tmp_path / "out"
    far = Heightfield(
        base.elevation_m, base.valid, base.transform * Affine.translation(5000, 0), crs=base.crs
    )
    far_p = write_tif(tmp_path / "far.tif", far)
    code, _, se = run(capsys, "change", before, far_p, "-o", out)
    assert code == 2
    _one_line(se, "far.tif", "does not overlap")
    feet = write_tif(tmp_path / "feet.tif", base, unit="ft")
    metres = write_tif(tmp_path / "metres.tif", base, unit="metre")
    code, _, se = run(capsys, "change", metres, feet, "-o", out)
    assert code == 2
    _one_line(se, "feet.tif", "vertical unit")
    outside = tmp_path / "outside.geojson"
    outside.write_text(
        json.dumps({"type": "Polygon", "coordinates": [[[2, 48], [2.1, 48], [2.1, 48.1], [2, 48]]]})
    )
    code, _, se = run(capsys, "change", before, after, "-o", out, "--zones", outside)
    assert code == 2
    _one_line(se, "outside.geojson", "outside the terrain")
    code, _, se = run(capsys, "change", before, after, "-o", before)
    assert code == 2
    _one_line(se, "is (or holds) the input")
    code, _, se = run(capsys, "change", before, after, "-o", before.parent)
    assert code == 2
    _one_line(se, "is (or holds) the input")
    code, _, se = run(capsys, "change", before, "-o", out)
    assert code == 2
    _one_line(se, "second DEM")
    # nothing half-written: no output and no temporary folder left behind
    assert not out.exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".out")]
    assert before.is_file() and after.is_file()


def test_store_epochs_form(tmp_path: Path, pair_files, capsys) -> None:
    epochs = pytest.importorskip("terralod.change.epochs", reason="terralod.change.epochs not built yet")
    before, after, _ = pair_files
    store = tmp_path / "site.terra"
    code, _, se = run(capsys, "build", before, "-o", store, "--epoch", "2001-02-03", "--method", "chunked",
                      "--tile-size", "33")  # fmt: skip
    assert code == 0, se
    code, _, se = run(capsys, "update", store, after, "--epoch", "2004-05-06")
    assert code == 0, se
    assert hasattr(epochs, "epoch_heightfield")
    out = tmp_path / "o"
    code, so, se = run(capsys, "change", store, "--from", "2001-02-03", "--to", "2004-05-06", "-o", out, "--no-views",
                       "--sigma-m", "0.1")  # fmt: skip
    assert code == 0, se
    s_ = json.loads((out / "summary.json").read_text())
    s2 = measure_change(read_heightfield(before), read_heightfield(after), sigma_m=0.1).summary
    assert s_["net_m3"] == pytest.approx(s2["net_m3"], rel=1e-4)


def test_dem_of_difference_is_nan_outside_overlap() -> None:
    base = synthetic_base(80)
    after = Heightfield(
        base.elevation_m, base.valid, base.transform * Affine.translation(30, 0), crs=base.crs
    )
    d = dem_of_difference(align(base, after))
    assert np.isnan(d[:, :29]).all() and np.isfinite(d[:, 31:]).all()
