"""The error of the change that holds where the change is (issue 54, terralod.change.uncertainty).

A synthetic valley (a flat floor and a 35° side) whose AFTER carries noise growing with slope and a mound
on the floor: sigma.tif is written beside dod.tif on its grid and is larger on the steep side; --sigma-m
replaces it by one value; a pair with almost no stable ground falls back to the single σ with a note; the
windowed path gives the in-memory totals and their ± on the same pair.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import rasterio
from hypothesis import given, settings
from hypothesis import strategies as st
from rasterio.transform import from_origin

from terralod.change.uncertainty import terrain_attributes, volume_sigma_m3
from terralod.change.volumes import measure_change
from terralod.heightfield import Heightfield
from test_change import run as _run  # the CLI in this process: (exit code, stdout, stderr)

pytest.importorskip("xdem")
pytest.importorskip("skgstat")

N = 160
DX = 10.0
CRS = "EPSG:32633"


def _valley(noise_seed: int = 1) -> tuple[Heightfield, Heightfield]:
    t = from_origin(500_000.0, 5_000_000.0, DX, DX)
    rows, cols = np.indices((N, N), dtype=np.float64)
    z = np.where(cols < 80, 100.0 + 0.002 * rows * DX, 100.0 + (cols - 80) * DX * np.tan(np.radians(35)))
    z = z + 2.0 * np.sin(rows / 7.0) * np.cos(cols / 9.0)
    ok = np.ones((N, N), bool)
    before = Heightfield(z.astype(np.float32), ok, t, crs=CRS, source="before.tif")
    slope, _ = terrain_attributes(z, ok, (DX, DX))
    rng = np.random.default_rng(noise_seed)
    mound = np.clip(6.0 * (1 - np.hypot(rows - 80, cols - 35) / 15.0), 0, None)
    after = z + mound + (0.2 + 0.04 * slope) * rng.normal(size=z.shape)
    return before, Heightfield(after.astype(np.float32), ok, t, crs=CRS, source="after.tif")


def _tif(path: Path, hf: Heightfield) -> Path:
    with rasterio.open(path, "w", driver="GTiff", width=N, height=N, count=1, dtype="float32", crs=hf.crs,
                       transform=hf.transform, nodata=np.nan) as ds:  # fmt: skip
        ds.write(hf.elevation_m.astype(np.float32), 1)
    return path


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> tuple[Path, Path]:
    d = tmp_path_factory.mktemp("valley")
    b, a = _valley()
    return _tif(d / "before.tif", b), _tif(d / "after.tif", a)


def test_sigma_raster_is_written_and_larger_on_steep_ground(files, tmp_path: Path, capsys) -> None:
    out = tmp_path / "o"
    code, so, se = _run(capsys, "change", *files, "-o", out, "--no-views", "--no-coregister")
    assert code == 0, se
    with rasterio.open(out / "sigma.tif") as ds, rasterio.open(out / "dod.tif") as dd:
        sig = ds.read(1)
        assert ds.transform == dd.transform and ds.shape == dd.shape and ds.crs == dd.crs
        assert ds.profile["tiled"] and "1-sigma" in ds.descriptions[0]
    flat, steep = np.nanmedian(sig[10:-10, 10:70]), np.nanmedian(sig[10:-10, 90:-10])
    # truth: 0.2 + 0.04 · 2° ≈ 0.28 m on the floor against 0.2 + 0.04 · 35° = 1.6 m on the side
    assert steep > 2.0 * flat, (flat, steep)
    assert 0.15 < flat < 0.5 and 0.9 < steep < 2.5
    s = json.loads((out / "summary.json").read_text())
    u = s["uncertainty"]
    assert u["model"] is not None and u["model_note"] is None
    assert len(u["model"]["ranges_m"]) >= 2
    words = [x for x in u["statements"] if "steep" in x]
    assert words and "flat ground" in words[0]
    assert "steep" in (out / "report.html").read_text()
    # the planted mound (on the flat floor) inside its ±
    planted = np.pi * 15**2 * 6.0 / 3 * DX * DX
    assert abs(s["net_m3"] - planted) <= s["net_uncertainty_m3"]


def test_sigma_m_overrides_the_model(files, tmp_path: Path, capsys) -> None:
    out = tmp_path / "o"
    code, _so, se = _run(
        capsys, "change", *files, "-o", out, "--no-views", "--no-coregister", "--sigma-m", "0.7"
    )
    assert code == 0, se
    with rasterio.open(out / "sigma.tif") as ds:
        sig = ds.read(1)
    assert np.allclose(sig[np.isfinite(sig)], 0.7)
    s = json.loads((out / "summary.json").read_text())
    assert s["sigma_m"] == 0.7 and s["sigma_source"].startswith("given")
    assert s["uncertainty"]["model"]["sigma_given_m"] == 0.7
    assert not any("steep" in x for x in s["uncertainty"]["statements"])
    # both given: the single-σ model exactly (Rolstad et al. with one range)
    before, after = _valley()
    r = measure_change(before, after, coregistration=False, sigma_m=0.7, corr_range_m=300.0)
    assert r.uncertainty.model is None and np.allclose(r.sigma[np.isfinite(r.sigma)], 0.7)


def test_fallback_note_when_stable_ground_is_tiny() -> None:
    before, after = _valley()
    stable = np.zeros((N, N), bool)
    stable[:30, :30] = True  # 900 cells: enough for σ, too few for the model
    r = measure_change(before, after, coregistration=False, stable=stable)
    u = r.uncertainty
    assert u.model is None and u.model_note and "900" in u.model_note
    assert any("the same everywhere" in x for x in r.summary["uncertainty"]["statements"])
    assert u.sigma_source.startswith("NMAD")
    assert np.allclose(r.sigma[np.isfinite(r.sigma)], u.sigma_m)


def test_windowed_path_gives_the_in_memory_totals(tmp_path: Path, monkeypatch) -> None:
    import terralod.change.windowed as W
    from terralod.io.windowed import RasterSource

    before, after = _valley(noise_seed=2)
    pb, pa = _tif(tmp_path / "b.tif", before), _tif(tmp_path / "a.tif", after)
    mem = measure_change(before, after, coregistration=False)
    assert mem.uncertainty.model is not None
    monkeypatch.setattr(W, "WINDOW", 48)  # windows of 48 cells: σ from slope and curvature at their edges
    win = W.measure_change_windowed(RasterSource(str(pb)), RasterSource(str(pa)), names=("b.tif", "a.tif"),
                                    dod_path=tmp_path / "dod.tif", coregistration=False)  # fmt: skip
    for k in ("net_m3", "gain_m3", "net_uncertainty_m3", "gain_uncertainty_m3", "loss_uncertainty_m3",
              "gain_m3_above_lod", "area_gain_m2", "net_above_lod_uncertainty_m3", "sigma_m"):  # fmt: skip
        assert win.summary[k] == pytest.approx(mem.summary[k], rel=1e-9, abs=1e-9), k
    with rasterio.open(tmp_path / "sigma.tif") as ds:
        assert np.allclose(ds.read(1), mem.sigma, equal_nan=True, rtol=0, atol=1e-6)


def test_propagation_matches_xdem_for_a_constant_sigma() -> None:
    """One spherical range, constant σ: σ_V / A = σ / sqrt(Neff) of xdem's circular approximation."""
    import pandas as pd
    import xdem

    params = pd.DataFrame({"model": ["spherical"], "range": [300.0], "psill": [1.0]})
    a, n = 100.0, 40_000
    area = a * n
    neff = xdem.spatialstats.neff_circular_approx_theoretical(area, params)
    got = volume_sigma_m3(area, a, n * 1.5, n * 1.5**2, [(300.0, 1.0)]) / area
    assert got == pytest.approx(1.5 / np.sqrt(neff), rel=1e-6)


@settings(max_examples=12, deadline=None)
@given(st.integers(0, 2**31))
def test_the_variogram_fit_is_xdems_bit_for_bit(seed: int) -> None:
    """fit_sum_spherical (the models' sum in one kernel call) gives xdem's fit_sum_model_variogram numbers
    exactly, on noisy two-range variograms, or fails where it fails."""
    import warnings

    import pandas as pd
    import xdem

    from terralod.change.uncertainty import fit_sum_spherical

    rng = np.random.default_rng(seed)
    lags = np.arange(1, 65, dtype=float) * rng.uniform(1, 30)
    r1, r2 = rng.uniform(1, 10) * lags[0], rng.uniform(10, 60) * lags[0]
    s1, s2 = rng.uniform(0.1, 1), rng.uniform(0.1, 1)
    sph = lambda h, r, c: np.where(h <= r, c * (1.5 * h / r - 0.5 * (h / r) ** 3), c)  # noqa: E731
    gam = np.abs(sph(lags, r1, s1) + sph(lags, r2, s2) + rng.normal(0, 0.05, lags.size) + rng.uniform(0, 0.3))
    cnt = rng.integers(100, 100_000, lags.size).astype(float)
    df = pd.DataFrame({"lags": lags, "exp": gam, "count": cnt, "err_exp": gam / np.sqrt(cnt) + 1e-6})
    top = gam.max() * 1.5
    bounds = [(0.1 * lags[0], lags[-1]), (0.0, top), (lags[0], 4 * lags[-1]), (0.0, top)]
    p0 = [lags[0], 0.5 * gam[0], lags[32], 0.5 * top]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            _f, params = xdem.spatialstats.fit_sum_model_variogram(["Sph"] * 2, df, bounds=bounds, p0=p0,
                                                                   maxfev=10000)  # fmt: skip
        except RuntimeError:
            with pytest.raises(RuntimeError):
                fit_sum_spherical(df, bounds=bounds, p0=p0, maxfev=10000)
            return
        got = fit_sum_spherical(df, bounds=bounds, p0=p0, maxfev=10000)
    want = np.ravel(np.c_[params["range"].values, params["psill"].values])
    assert np.array_equal(got, want), (got, want)


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**31), st.integers(300, 30_000), st.booleans())
def test_the_slope_binning_is_xdems_bit_for_bit(seed: int, n: int, ties: bool) -> None:
    """binned_nmad_2d gives the 2-D rows of xdem's nd_binning (NMAD by slope x curvature bins, the edges
    the model uses) exactly: the same columns, row order, counts, NMADs (empty bins NaN) and intervals,
    with heavy-tailed errors and, when ``ties``, slopes on a 0.5-degree lattice (values on the edges)."""
    import warnings

    import xdem

    from terralod.change.uncertainty import _edges, binned_nmad_2d

    rng = np.random.default_rng(seed)
    v = rng.standard_t(3, n) * rng.uniform(0.1, 5.0)
    s, c = rng.gamma(2.0, 8.0, n), rng.exponential(1.0, n)
    if ties:
        s = np.round(2 * s) / 2
    se = _edges(s, np.linspace(0, 1, 9), 400)
    ce = _edges(c, np.array([0, 0.5, 0.8, 0.95, 1.0]), 200)
    if se.size < 2 or ce.size < 2:
        return
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        want = xdem.spatialstats.nd_binning(v, [s, c], ["slope", "maxc"], statistics=[xdem.spatialstats.nmad],
                                            list_var_bins=(se, ce))  # fmt: skip
    want = want[want.nd == 2].reset_index(drop=True)
    got = binned_nmad_2d(v, s, c, se, ce, ["slope", "maxc"])
    assert list(got.columns) == list(want.columns)
    for k in ("nd", "count", "nmad"):
        assert np.array_equal(got[k].to_numpy(), want[k].to_numpy(), equal_nan=True), k
    assert list(got["slope"]) == list(want["slope"]) and list(got["maxc"]) == list(want["maxc"])


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**31), st.integers(1, 20_000), st.booleans(), st.booleans())
def test_nuth_kaab_binned_by_np_median_is_its_default_bit_for_bit(seed: int, n: int, ties: bool,
                                                                  single: bool) -> None:  # fmt: skip
    """The co-registration gives xdem's NuthKaab ``np.median`` as its bin statistic instead of the default
    ``np.nanmedian`` (scipy sorts once for np.median, where it gathers a Python list per bin for any other
    callable): on the finite values xdem bins, the medians and counts of its aspect bins are the same bits,
    with heavy tails, ties (values on a lattice), float32 or float64, and bins with 0, 1 or 2 values."""
    import warnings

    import xdem

    rng = np.random.default_rng(seed)
    dh = rng.standard_t(2, n) * rng.uniform(0.01, 50.0)
    if ties:
        dh = np.round(dh * 4) / 4
    dh = dh.astype(np.float32 if single else np.float64)
    aspect = rng.uniform(0.0, 2 * np.pi, n)
    dh[rng.uniform(size=n) < 0.05] = np.nan  # xdem drops them before binning
    tables = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for stat in (np.nanmedian, np.median):
            tables.append(
                xdem.spatialstats.nd_binning(dh, [aspect], ["aspect"], 72, statistics=(stat, "count"))
            )
    a, b = tables
    assert np.array_equal(a["nanmedian"].to_numpy(), b["median"].to_numpy(), equal_nan=True)
    assert np.array_equal(a["count"].to_numpy(), b["count"].to_numpy(), equal_nan=True)
    assert list(a["aspect"]) == list(b["aspect"])
