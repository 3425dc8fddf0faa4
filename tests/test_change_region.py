"""terralod change over a region, window by window (terralod.change.windowed).

A 300² crop of the Kilauea 30 m DEM (UTM 5N) with a planted mound and pit is cut into four GeoTIFFs that
share their edge row and column; BEFORE and AFTER as folders, globs or VRTs give the merged files' volumes,
zones and dod.tif; the windowed chain with tiny windows and a small co-registration sample gives the
in-memory chain's numbers (the shift within 0.02 cell); dod.tif is a tiled COG with overviews; a corrupt
tile is named in one line, exit 2, nothing written.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import rasterio
from affine import Affine

from conftest import terralod_cli

pytest.importorskip("xdem")

N = 300  #: cells a side of the merged crop
K = 150  #: the split: tiles [0, K] and [K, N) share row/column K
REL = 1e-9


def _write(path: Path, a: np.ndarray, transform, crs) -> Path:  # noqa: ANN001
    with rasterio.open(path, "w", driver="GTiff", width=a.shape[1], height=a.shape[0], count=1, dtype="float32",
                       crs=crs, transform=transform, nodata=-9999.0, tiled=True, blockxsize=64, blockysize=64,
                       compress="deflate") as ds:  # fmt: skip
        ds.write(a.astype(np.float32), 1)
    return path


def _quads(a: np.ndarray, t, crs, d: Path) -> Path:  # noqa: ANN001
    d.mkdir(parents=True, exist_ok=True)
    for name, r0, c0 in (("nw", 0, 0), ("ne", 0, K), ("sw", K, 0), ("se", K, K)):
        part = a[r0 : min(r0 + K + 1, N), c0 : min(c0 + K + 1, N)]
        _write(d / f"{name}.tif", part, t @ Affine.translation(c0, r0), crs)
    return d


@pytest.fixture(scope="module")
def pair(tmp_path_factory, shared_data: Path) -> dict:
    """The merged BEFORE/AFTER files and their quads (AFTER: a mound of +20 m and a pit of -12 m)."""
    d = tmp_path_factory.mktemp("region_pair")
    with rasterio.open(shared_data / "dem" / "kilauea_hawaii_30m_utm5.tif") as ds:
        win = rasterio.windows.Window(300, 250, N, N)
        z = ds.read(1, window=win).astype(np.float32)
        t, crs = ds.window_transform(win), ds.crs
    assert (z > 0).all()
    rows, cols = np.indices(z.shape)
    mound = np.clip(20.0 * (1 - np.hypot(rows - 90, cols - 200) / 30.0), 0, None)
    pit = np.clip(12.0 * (1 - np.hypot(rows - 220, cols - 80) / 25.0), 0, None)
    rng = np.random.default_rng(3)
    after = z + mound - pit + rng.normal(0, 0.3, z.shape)
    out = {
        "before": _write(d / "before.tif", z, t, crs),
        "after": _write(d / "after.tif", after, t, crs),
        "before_dir": _quads(z, t, crs, d / "before"),
        "after_dir": _quads(after, t, crs, d / "after"),
    }
    zones = {"type": "FeatureCollection", "crs": {"type": "name", "properties": {"name": "local"}},
             "features": [{"type": "Feature", "properties": {"name": "mound"}, "geometry": {
                 "type": "Polygon", "coordinates": [[list(t @ (c, r)) for r, c in
                                                     ((50, 160), (50, 240), (130, 240), (130, 160), (50, 160))]]}}]}  # fmt: skip
    (d / "zones.geojson").write_text(json.dumps(zones))
    out["zones"] = d / "zones.geojson"
    return out


def _run(before, after, out: Path, *extra: str) -> dict:  # noqa: ANN001
    r = terralod_cli("change", str(before), str(after), "-o", str(out), "--no-views", *extra)
    assert r.returncode == 0, r.stdout + r.stderr
    return json.loads((out / "summary.json").read_text())


def _same(a: dict, b: dict) -> None:
    for k in ("gain_m3", "loss_m3", "net_m3", "net_uncertainty_m3", "gain_m3_above_lod", "loss_m3_above_lod",
              "area_gain_m2", "area_loss_m2", "sigma_m", "level_of_detection_m", "max_rise_m", "max_drop_m"):  # fmt: skip
        assert a[k] == pytest.approx(b[k], rel=REL, abs=1e-9), k
    assert a["shift_m"] == pytest.approx(b["shift_m"], rel=REL, abs=1e-9)
    assert len(a["zones"]) == len(b["zones"])
    for za, zb in zip(a["zones"], b["zones"], strict=True):
        for k in ("gain_m3", "loss_m3", "net_m3", "area_gain_m2"):
            assert za[k] == pytest.approx(zb[k], rel=REL, abs=1e-9), k


def _dod(path: Path) -> np.ndarray:
    with rasterio.open(path) as ds:
        return ds.read(1)


def test_region_forms_equal_the_merged_pair(pair, tmp_path: Path, monkeypatch) -> None:
    import terralod.cli.change as cli_change

    merged = _run(pair["before"], pair["after"], tmp_path / "merged", "--zones", str(pair["zones"]))
    assert "windowed" not in merged  # one small file a side: the in-memory chain
    monkeypatch.setattr(cli_change, "WINDOWED_MIN_CELLS", 0)
    forced = _run(pair["before"], pair["after"], tmp_path / "forced", "--zones", str(pair["zones"]))
    assert forced["windowed"]["sample_whole_grid"]
    _same(forced, merged)
    assert np.array_equal(_dod(tmp_path / "forced" / "dod.tif"), _dod(tmp_path / "merged" / "dod.tif"),
                          equal_nan=True)  # fmt: skip
    monkeypatch.undo()
    for i, (b, a) in enumerate([
        (pair["before_dir"], pair["after_dir"]),
        (f"{pair['before_dir']}/*.tif", f"{pair['after_dir']}/*.tif"),
    ]):  # fmt: skip
        got = _run(b, a, tmp_path / f"region{i}", "--zones", str(pair["zones"]))
        assert "windowed" in got
        _same(got, merged)
        assert np.array_equal(_dod(tmp_path / f"region{i}" / "dod.tif"), _dod(tmp_path / "merged" / "dod.tif"),
                              equal_nan=True)  # fmt: skip
    # the planted change: +20 m cone of radius 30 cells, -12 m of radius 25 (30 m cells), within noise
    z = merged["zones"][0]
    planted = np.pi * 30**2 * 20.0 / 3 * 900.0
    assert z["gain_m3_above_lod"] == pytest.approx(planted, rel=0.05)


def test_tiny_windows_and_a_small_sample_give_the_same_numbers(pair, tmp_path: Path, monkeypatch) -> None:
    """Windows of 64 cells and a co-registration sample of 4 windows of 96² cells give the default's volumes
    (1e-9) and, with AFTER shifted, a shift within 0.02 cell of the whole grid's fit."""
    import terralod.change.windowed as W
    from terralod.io.windowed import RasterSource

    b, a = RasterSource(str(pair["before"])), RasterSource(str(pair["after"]))
    names = ("before.tif", "after.tif")
    ref = W.measure_change_windowed(b, a, names=names, dod_path=tmp_path / "ref.tif")
    monkeypatch.setattr(W, "WINDOW", 64)
    tiny = W.measure_change_windowed(b, a, names=names, dod_path=tmp_path / "tiny.tif")
    _same(tiny.summary, ref.summary)
    assert tiny.summary["extremes"] == ref.summary["extremes"]
    assert np.array_equal(_dod(tmp_path / "tiny.tif"), _dod(tmp_path / "ref.tif"), equal_nan=True)
    # AFTER moved by (0.4, -0.3) cells: the sample's fit against the whole grid's
    with rasterio.open(pair["after"]) as ds:
        z, t, crs = ds.read(1), ds.transform, ds.crs
    moved = _write(tmp_path / "moved.tif", z, t @ Affine.translation(0.4, 0.3), crs)
    am = RasterSource(str(moved))
    # same grid required for the windowed chain: resample onto BEFORE's grid by the in-memory reader
    from terralod import read_heightfield
    from terralod.change.difference import align

    p = align(read_heightfield(pair["before"]), read_heightfield(moved))
    zz, ok = p.after_on_before((0.0, 0.0, 0.0))
    on_grid = _write(tmp_path / "moved_on_grid.tif", np.where(ok, zz, -9999.0), t, crs)
    am = RasterSource(str(on_grid))
    whole = W.measure_change_windowed(b, am, names=names)
    monkeypatch.setattr(W, "SAMPLE_WINDOW", 96)
    monkeypatch.setattr(W, "SAMPLE_MARGIN", 16)
    monkeypatch.setattr(W, "SAMPLE_MAX_CELLS", 4 * 128**2)  # 4 windows of 96² cells: 41 % of the grid
    part = W.measure_change_windowed(b, am, names=names, dod_path=tmp_path / "part.tif")
    assert not part.summary["windowed"]["sample_whole_grid"]
    px = 30.0
    sw, sp = whole.summary["shift_m"], part.summary["shift_m"]
    assert abs(sw[0] + 0.4 * px) < 0.1 * px and abs(sw[1] - 0.3 * px) < 0.1 * px  # AFTER moved east, south
    assert np.hypot(sw[0] - sp[0], sw[1] - sp[1]) / px < 0.02
    # a shifted window stream equals the whole grid's difference (spline margins)
    monkeypatch.setattr(W, "WINDOW", 64)
    part64 = W.measure_change_windowed(b, am, names=names, dod_path=tmp_path / "part64.tif")
    d1, d2 = _dod(tmp_path / "part.tif"), _dod(tmp_path / "part64.tif")
    assert np.nanmax(np.abs(d1 - d2)) < 1e-4
    assert part64.summary["net_m3"] == pytest.approx(part.summary["net_m3"], rel=1e-7)


def test_dod_is_a_cloud_optimized_geotiff(pair, tmp_path: Path, monkeypatch) -> None:
    import terralod.change.windowed as W
    from terralod.io.windowed import RasterSource

    big = np.tile(_dod(pair["before"]), (4, 4))  # 1200²: overviews down to one 512² tile
    with rasterio.open(pair["before"]) as ds:
        t, crs = ds.transform, ds.crs
    bp = _write(tmp_path / "b.tif", big, t, crs)
    ap = _write(tmp_path / "a.tif", big + 1.5, t, crs)
    W.measure_change_windowed(RasterSource(str(bp)), RasterSource(str(ap)), names=("b", "a"),
                              dod_path=tmp_path / "dod.tif", coregistration=False, sigma_m=0.5)  # fmt: skip
    with rasterio.open(tmp_path / "dod.tif") as ds:
        assert ds.profile["tiled"] and ds.block_shapes[0] == (512, 512)
        assert ds.overviews(1) == [2, 4]
        assert ds.compression.name.lower() == "deflate"
        assert ds.tags()["sigma_m"] == "0.5"
        assert np.allclose(ds.read(1), 1.5, atol=1e-4)
    assert not (tmp_path / ".dod.tif.scratch.tif").exists()


def test_a_corrupt_tile_is_named_and_nothing_written(pair, tmp_path: Path) -> None:
    import shutil

    bad = tmp_path / "before"
    shutil.copytree(pair["before_dir"], bad)
    raw = (bad / "se.tif").read_bytes()
    (bad / "se.tif").write_bytes(raw[: len(raw) // 2])  # truncated: its last tiles cannot be decoded
    out = tmp_path / "out"
    r = terralod_cli("change", str(bad), str(pair["after_dir"]), "-o", str(out))
    assert r.returncode == 2
    lines = [ln for ln in r.stderr.strip().splitlines() if ln.strip()]
    assert len(lines) == 1 and "se.tif" in lines[0], r.stderr
    assert not out.exists() and not any(p.name.startswith(".out") for p in tmp_path.iterdir())


def test_dask_gives_the_local_numbers_and_bytes(pair, tmp_path: Path) -> None:
    """``--dask local``: the windows differenced on a worker process; the same summary figures and the same
    dod.tif bytes as the local run."""
    pytest.importorskip("dask.distributed")
    b, a = f"{pair['before_dir']}/*.tif", f"{pair['after_dir']}/*.tif"
    here = _run(b, a, tmp_path / "here", "--zones", str(pair["zones"]))
    there = _run(
        b, a, tmp_path / "there", "--zones", str(pair["zones"]), "--dask", "local", "--dask-workers", "1"
    )
    _same(there, here)
    assert there["extremes"] == here["extremes"]
    assert (tmp_path / "there" / "dod.tif").read_bytes() == (tmp_path / "here" / "dod.tif").read_bytes()


@pytest.fixture(scope="module")
def epoch_store(pair, tmp_path_factory) -> Path:
    """A store of BEFORE (epoch 2000-01-01) updated with AFTER (epoch 2001-01-01): it keeps both grids."""
    d = tmp_path_factory.mktemp("epoch_store")
    store = d / "pair.terra"
    r = terralod_cli("build", str(pair["before"]), "-o", str(store), "--epoch", "2000-01-01")
    assert r.returncode == 0, r.stderr
    r = terralod_cli("update", str(store), str(pair["after"]), "--epoch", "2001-01-01")
    assert r.returncode == 0, r.stderr
    return store


def test_an_epoch_read_a_window_at_a_time_is_the_epoch(epoch_store: Path) -> None:
    """EpochSource.read of any window (block-aligned or not, one cell to the whole grid) is that window of
    epoch_heightfield, values and validity; a pickled copy reads the same; a window outside is refused."""
    import pickle

    from hypothesis import given, settings
    from hypothesis import strategies as st

    from terralod.change.epochs import EpochSource, epoch_heightfield

    dates = ("2000-01-01", "2001-01-01")
    wholes = {d: epoch_heightfield(epoch_store, d) for d in dates}
    sources = {d: EpochSource(epoch_store, d) for d in dates}
    copies = {d: pickle.loads(pickle.dumps(s)) for d, s in sources.items()}
    for d in dates:
        src, whole = sources[d], wholes[d]
        assert (src.height, src.width) == whole.elevation_m.shape
        assert tuple(src.transform) == tuple(whole.transform) and src.crs == whole.crs
        with pytest.raises(ValueError, match="inside"):
            src.read(0, 0, N + 1, 10)

    @settings(max_examples=60, deadline=None, derandomize=True)
    @given(
        st.sampled_from(dates),
        st.integers(0, N - 1),
        st.integers(0, N - 1),
        st.integers(1, N),
        st.integers(1, N),
    )
    def check(date: str, r0: int, c0: int, h: int, w: int) -> None:
        r1, c1 = min(N, r0 + h), min(N, c0 + w)
        for s in (sources[date], copies[date]):
            z, ok = s.read(r0, c0, r1, c1)
            assert np.array_equal(z, wholes[date].elevation_m[r0:r1, c0:c1])
            assert np.array_equal(ok, wholes[date].valid[r0:r1, c0:c1])

    check()
    assert not np.array_equal(sources[dates[0]].read(0, 0, N, N)[0], sources[dates[1]].read(0, 0, N, N)[0])


def _run_epochs(store: Path, out: Path, *extra: str) -> dict:
    r = terralod_cli("change", str(store), "--from", "2000-01-01", "--to", "2001-01-01", "-o", str(out),
                     "--no-views", *extra)  # fmt: skip
    assert r.returncode == 0, r.stdout + r.stderr
    return json.loads((out / "summary.json").read_text())


def test_two_epochs_of_a_store_change_window_by_window_as_two_files(
    pair, epoch_store: Path, tmp_path: Path, monkeypatch
) -> None:
    """``terralod change STORE --from A --to B`` past the windowed size reads both epochs window by window and
    gives the figures and dod.tif cells of the same two grids given as GeoTIFFs; under it, the in-memory chain."""
    import terralod.cli.change as cli_change
    from terralod.change.epochs import epoch_heightfield

    zones = ("--zones", str(pair["zones"]))
    assert "windowed" not in _run_epochs(epoch_store, tmp_path / "small", *zones)
    files = []
    for date in ("2000-01-01", "2001-01-01"):
        hf = epoch_heightfield(epoch_store, date)
        assert hf.valid.all()  # the crop has no nodata: the GeoTIFF is the grid
        files.append(_write(tmp_path / f"{date}.tif", hf.elevation_m, hf.transform, hf.crs))
    monkeypatch.setattr(cli_change, "WINDOWED_MIN_CELLS", 0)
    got = _run_epochs(epoch_store, tmp_path / "epochs", *zones)
    assert got["windowed"]["sample_whole_grid"]
    assert (got["before"]["date"], got["after"]["date"]) == ("2000-01-01", "2001-01-01")
    want = _run(files[0], files[1], tmp_path / "files", *zones)
    _same(got, want)
    # the same cells (the files differ in the tags naming BEFORE and AFTER)
    assert np.array_equal(
        _dod(tmp_path / "epochs" / "dod.tif"), _dod(tmp_path / "files" / "dod.tif"), equal_nan=True
    )
