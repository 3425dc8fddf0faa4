"""A series over a region (issue 54 #5): ``terralod build --epoch`` and ``terralod update`` of a mosaic read
window by window (:func:`terralod.pyramid.update.update_store_windowed`), against the in-memory update of the
same grids."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from terralod.heightfield import Heightfield
from terralod.io.windowed import RasterSource
from terralod.pyramid.builder import build_store
from terralod.pyramid.distributed import build_store_windowed
from terralod.pyramid.update import (
    DirtyTiles,
    dirty_tiles,
    update_store,
    update_store_windowed,
)
from terralod.store import TileStore
from terralod.tiles import TilePyramid

from conftest import fractal_terrain

CRS = "EPSG:32611"
RES = 30.0


def _write_tif(path: Path, z: np.ndarray, r: int = 0, c: int = 0) -> Path:
    import rasterio
    from rasterio.transform import from_origin

    h, w = z.shape
    with rasterio.open(path, "w", driver="GTiff", width=w, height=h, count=1, dtype="float32", crs=CRS,
                       transform=from_origin(380000.0 + RES * c, 3800000.0 - RES * r, RES, RES), tiled=True,
                       blockxsize=64, blockysize=64) as ds:  # fmt: skip
        ds.write(z.astype(np.float32), 1)
    return path


def _mosaic(folder: Path, z: np.ndarray) -> Path:
    """``z`` as 2 x 2 GeoTIFF tiles sharing their edge samples, in ``folder``."""
    folder.mkdir()
    h, w = z.shape
    hr, hc = h // 2, w // 2
    for i, (r, c) in enumerate([(0, 0), (0, hc), (hr, 0), (hr, hc)]):
        _write_tif(folder / f"t{i}.tif", z[r : r + hr + 1, c : c + hc + 1], r, c)
    return folder


def _epoch_rows(path: Path, epoch: str) -> list[tuple]:
    """The tile rows of ``epoch`` (its map: shared rows and its own), without the rev column."""
    conn = sqlite3.connect(path)
    try:
        eid = conn.execute("SELECT id FROM epochs WHERE name = ?", (epoch,)).fetchone()[0]
        cols = "t.level, t.x, t.y, t.error_m, t.vertical_error_m, t.n_vertices, t.n_triangles, t.vertices, t.triangles"
        a = conn.execute(f"SELECT {cols} FROM epoch_tiles e JOIN tiles t USING (level, x, y) "
                         "WHERE e.epoch = ? AND e.rev = 0", (eid,)).fetchall()  # fmt: skip
        b = conn.execute(f"SELECT {cols} FROM epoch_tiles e JOIN tile_revs t ON t.level = e.level AND "
                         "t.x = e.x AND t.y = e.y AND t.rev = e.rev WHERE e.epoch = ? AND e.rev > 0",
                         (eid,)).fetchall()  # fmt: skip
        return sorted(a + b)
    finally:
        conn.close()


def _planted(z: np.ndarray, r: int, c: int, radius: int, depth_m: float) -> np.ndarray:
    yy, xx = np.mgrid[: z.shape[0], : z.shape[1]]
    bowl = np.clip(1.0 - ((yy - r) ** 2 + (xx - c) ** 2) / radius**2, 0.0, None)
    return (z - depth_m * bowl).astype(np.float32)


@pytest.mark.parametrize("method", ["chunked", "cohesion"])
def test_windowed_series_is_the_in_memory_series(tmp_path: Path, method: str) -> None:
    """A mosaic built with an epoch out of core, then updated with a second mosaic read window by window:
    the same epochs, tiles (bytes and errors), dirty counts and kept samples as the in-memory build and
    update of the same grids; the second epoch shares every clean tile with the first."""
    z0 = fractal_terrain(257, 289, seed=5, relief_m=600.0)
    z1 = _planted(z0, 150, 60, 25, 12.0)
    before, after = _mosaic(tmp_path / "2000", z0), _mosaic(tmp_path / "2007", z1)
    src0, src1 = (
        RasterSource([str(p) for p in sorted(before.glob("*.tif"))]),
        RasterSource([str(p) for p in sorted(after.glob("*.tif"))]),
    )
    hf0 = Heightfield(*src0.read(0, 0, src0.height, src0.width), src0.transform, src0.crs, src0.source)
    hf1 = Heightfield(*src1.read(0, 0, src1.height, src1.width), src1.transform, src1.crs, src1.source)
    win, mem = tmp_path / "win.terra", tmp_path / "mem.terra"
    build_store_windowed(src0, win, method=method, workers=2, unit_span_samples=128, epoch="2000")
    build_store(hf0, mem, method=method, workers=1, epoch="2000")
    assert _epoch_rows(win, "2000") == _epoch_rows(mem, "2000")
    rw = update_store_windowed(src1, win, "2007", workers=2)
    rm = update_store(hf1, mem, "2007", workers=1)
    assert (rw.tiles_dirty, rw.changed_samples, rw.complete) == (rm.tiles_dirty, rm.changed_samples, True)
    assert 0 < rw.tiles_dirty < rw.tiles_total
    assert _epoch_rows(win, "2007") == _epoch_rows(mem, "2007")
    with TileStore.open(win, epoch="2007") as s, TileStore.open(mem, epoch="2007") as m:
        assert s.epochs == m.epochs == ["2000", "2007"]
        for a, b in zip(s.epoch_source("2007"), (hf1.elevation_m, hf1.valid), strict=True):
            np.testing.assert_array_equal(a, b)
        assert s.meta["colour_range_m"] == m.meta["colour_range_m"]
        assert s.epoch_info("2007")["tiles_shared"] == rw.tiles_shared
        assert not s.verify_epochs()


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    h=st.integers(40, 200), w=st.integers(40, 200), m=st.sampled_from([9, 17, 33]),
    method=st.sampled_from(["chunked", "cohesion", "adaptive"]), strip=st.sampled_from([1, 7, 64]),
    seed=st.integers(0, 2**31 - 1),
)  # fmt: skip
def test_dirty_tiles_found_strip_by_strip_are_the_whole_masks(h, w, m, method, strip, seed) -> None:
    """:class:`DirtyTiles` fed strips of any height finds :func:`dirty_tiles`' tiles, for sparse changes
    anywhere (edges, corners, single samples) and every mesher's margin."""
    rng = np.random.default_rng(seed)
    changed = rng.random((h, w)) < rng.choice([0.0, 1e-4, 1e-3, 0.02])
    pyr = TilePyramid(w, h, m)
    d = DirtyTiles(pyr, method)
    for r0 in range(0, h, strip):
        d.add(r0, changed[r0 : r0 + strip])
    assert set(d.codes()) == dirty_tiles(pyr, changed, method)
    assert d.changed_samples == int(changed.sum())
    codes = d.codes()
    assert [c[0] for c in codes] == sorted((c[0] for c in codes), reverse=True)


def test_windowed_update_refuses_in_one_line_and_writes_nothing(tmp_path: Path) -> None:
    """A survey on another grid, a store that keeps no samples, and an epoch that exists: one line naming
    the file, the store unchanged."""
    from terralod.errors import InputError, StoreError

    z0 = fractal_terrain(129, 129, seed=2, relief_m=300.0)
    src0 = RasterSource(str(_write_tif(tmp_path / "a.tif", z0)))
    store = tmp_path / "s.terra"
    build_store_windowed(src0, store, method="chunked", workers=1, epoch="2000")
    bytes_before = store.read_bytes()
    other = RasterSource(str(_write_tif(tmp_path / "b.tif", z0[:100, :100])))
    with pytest.raises(InputError, match="store's grid") as e:
        update_store_windowed(other, store, "2001")
    assert "\n" not in str(e.value)
    with pytest.raises(InputError, match="exists already"):
        update_store_windowed(src0, store, "2000")
    plain = tmp_path / "plain.terra"
    build_store_windowed(src0, plain, method="chunked", workers=1)
    with pytest.raises(StoreError, match="keeps no samples"):
        update_store_windowed(src0, plain, "2001")
    assert store.read_bytes() == bytes_before
    with TileStore.open(store) as s:
        assert s.epochs == ["2000"]


BEFORE = "change/st_helens_crater_2000-09-25_10m.tif"
AFTER = "change/st_helens_crater_2007-07-05_10m.tif"


def _stamp(site: Path) -> dict[str, tuple[int, int]]:
    return {p.relative_to(site).as_posix(): (p.stat().st_ino, p.stat().st_mtime_ns)
            for p in site.rglob("*") if p.is_file()}  # fmt: skip


def test_a_series_site_window_by_window_and_its_update(
    shared_data: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """St Helens as a store of epochs built and updated window by window; its site made window by window
    (each pair from the kept samples, its rasters from its dod.tif in strips) is the in-memory site's pair
    for pair; a third survey added, ``--update`` rewrites the files that change and leaves the first epoch's
    tiles as they were."""
    import json

    import rasterio

    import terralod.change.windowed as windowed
    import terralod.export.common as common
    from terralod.site.build import site_from_store

    monkeypatch.setattr(common, "WHOLE_VALIDITY_SAMPLES", 0)  # each epoch's validity read block by block too
    measured: list[Path] = []
    real = windowed.measure_change_windowed
    monkeypatch.setattr(
        windowed, "measure_change_windowed", lambda *a, **k: measured.append(k["dod_path"]) or real(*a, **k)
    )

    store = tmp_path / "helens.terra"
    build_store_windowed(RasterSource(str(shared_data / BEFORE)), store, workers=2, epoch="2000-09-25")
    update_store_windowed(RasterSource(str(shared_data / AFTER)), store, "2007-07-05", workers=2)
    site, mem = tmp_path / "site", tmp_path / "mem"
    site_from_store(store, site, windowed=True)
    assert len(measured) == 1  # the windowed path, one pair
    site_from_store(store, mem, windowed=False)
    assert len(measured) == 1
    got, want = (json.loads((s / "pairs/0.json").read_text()) for s in (site, mem))
    for key in ("from", "to", "dates", "grid", "lattice", "legend"):
        assert got[key] == want[key], key
    for role in ("dod", "before"):
        assert got["rasters"][role]["levels"] == want["rasters"][role]["levels"], role
    for key, v in want["totals"].items():
        assert got["totals"][key] == pytest.approx(v, rel=1e-6, abs=1e-6), key
    assert (
        json.loads((site / "site.json").read_text())["epochs"]
        == json.loads((mem / "site.json").read_text())["epochs"]
    )

    with rasterio.open(shared_data / AFTER) as ds:  # a third survey: a pit dug into the 2007 dome
        z, profile = ds.read(1), ds.profile
    third = tmp_path / "2010.tif"
    with rasterio.open(third, "w", **profile) as ds:
        ds.write(_planted(z, z.shape[0] // 2, z.shape[1] // 2, 20, 15.0).astype(z.dtype), 1)
    rep = update_store_windowed(RasterSource(str(third)), store, "2010-01-01", workers=2)
    assert 0 < rep.tiles_dirty < rep.tiles_total
    before = _stamp(site)
    upd = site_from_store(store, site, windowed=True, update=True)
    after = _stamp(site)
    assert len(measured) == 4  # three pairs now (first → last, then each consecutive pair)
    manifest = json.loads((site / "site.json").read_text())
    assert [e["name"] for e in manifest["epochs"]] == ["2000-09-25", "2007-07-05", "2010-01-01"]
    assert len(manifest["pairs"]) == 3 and "site.json" in upd.rewritten
    kept = [f for f in before if f.startswith("epochs/0/") and after.get(f) == before[f]]
    assert kept and all(f not in upd.rewritten for f in kept)  # the first epoch's tiles untouched
    assert set(upd.rewritten) == {f for f in after if after[f] != before.get(f)}
    assert any(f.startswith("epochs/2/") for f in upd.rewritten)
    # the pair the site had (2000 → 2007) keeps its tiles under the same names, untouched
    first = [f for f in before if f.startswith(got["rasters"]["dod"]["url"] + "/")]
    assert first and all(after.get(f) == before[f] for f in first)


@settings(max_examples=10, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(0, 3000))
def test_kept_validity_read_block_by_block_is_the_grid(tmp_path_factory, seed: int, n: int) -> None:
    """:class:`terralod.export.common.KeptValidity` (what a regional store's 3D Tiles drop nodata triangles
    against) answers the kept mask's value for any samples, in any order, repeated or not, after pickling."""
    import pickle

    from terralod.export.common import KeptValidity

    rng = np.random.default_rng(seed)
    z = fractal_terrain(150, 170, seed=seed % 1000, relief_m=200.0)
    valid = rng.random(z.shape) > 0.2
    hf = Heightfield(z.astype(np.float32), valid, Heightfield.from_array(z, 10.0).transform, None, "t")
    path = tmp_path_factory.mktemp("kept") / "s.terra"
    build_store(hf, path, method="chunked", workers=1, epoch="e1")
    with TileStore.open(path) as s:
        kv = pickle.loads(
            pickle.dumps(KeptValidity(path, s.epoch_source_id("e1"), 170, 150, s.meta["transform"]))
        )
        r, c = rng.integers(0, 150, n), rng.integers(0, 170, n)
        np.testing.assert_array_equal(kv.valid[r, c], s.epoch_source("e1")[1][r, c])


def test_cli_series_of_geographic_regions(tmp_path: Path) -> None:
    """``terralod build REGION/ --epoch`` then ``terralod update STORE REGION2/ --epoch`` on EPSG:4326 tiles
    (warped block by block): both out of core, the second survey's tiles measured against its own lon/lat
    samples (every stored error holds against every original sample), the clean tiles shared."""
    import rasterio

    from terralod.cli import main
    from test_honest_errors import _write, check_against_original
    from test_region_build import _merged, _quarters

    merged = _merged(tmp_path / "2000.tif")
    with rasterio.open(merged) as ds:
        z, t, nodata = ds.read(1), ds.transform, ds.nodata
    pit = _planted(z, 90, 30, 8, 40.0)
    pit[z == nodata] = nodata
    merged2 = _write(tmp_path / "2007.tif", pit, t, "EPSG:4326", nodata=nodata)
    _quarters(merged, tmp_path / "r2000")
    _quarters(merged2, tmp_path / "r2007")
    store = tmp_path / "s.terra"
    for args in (["build", str(tmp_path / "r2000"), "-o", str(store), "--epoch", "2000"],
                 ["update", str(store), str(tmp_path / "r2007"), "--epoch", "2007"]):  # fmt: skip
        try:
            main(args)
        except SystemExit as exc:
            assert exc.code in (0, None), args
    with TileStore.open(store) as s:
        assert s.epochs == ["2000", "2007"]
        info = s.epoch_info("2007")
        assert info["kind"] == "update" and 0 < info["tiles_rebuilt"] and info["tiles_shared"] > 0
        assert "32631" in str(s.meta["crs"])  # the metric frame of the region (UTM 31N)
    checked = check_against_original(merged2, store)  # asserts |mesh - sample| <= each tile's errors
    assert len(checked) == 4 and all(n > 0 for n, _ in checked.values())


def test_an_interrupted_windowed_update_resumes_to_the_same_epoch(tmp_path: Path) -> None:
    """An update stopped after a few tiles leaves the earlier epoch as it was and no new complete epoch;
    ``resume=True`` finishes it with the tiles already written kept: the epoch of an uninterrupted update."""
    z0 = fractal_terrain(193, 225, seed=9, relief_m=400.0)
    src0 = RasterSource(str(_write_tif(tmp_path / "a.tif", z0)))
    src1 = RasterSource(str(_write_tif(tmp_path / "b.tif", _planted(z0, 100, 120, 30, 8.0))))
    whole, cut = tmp_path / "whole.terra", tmp_path / "cut.terra"
    for p in (whole, cut):
        build_store_windowed(src0, p, method="cohesion", workers=1, epoch="2000")
    update_store_windowed(src1, whole, "2007", workers=2)
    part = update_store_windowed(src1, cut, "2007", workers=2, stop_after=3)
    assert not part.complete and part.tiles_built == 3
    with TileStore.open(cut) as s:
        assert s.epochs == ["2000"]
    rest = update_store_windowed(src1, cut, "2007", workers=2, resume=True)
    assert rest.complete and rest.tiles_skipped == 3 and rest.tiles_built == rest.tiles_dirty - 3
    assert _epoch_rows(cut, "2007") == _epoch_rows(whole, "2007")


def test_3d_tiles_of_a_regional_epoch_read_its_validity_block_by_block(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """An epoch past the size read whole (the threshold lowered) is exported with its validity read block by
    block: the same files, byte for byte, as with the grid read whole (the nodata triangles dropped alike),
    and ``--update`` after a new epoch works on it (its digest from the kept blocks' digests)."""
    import terralod.export.common as common
    from terralod.export.tiles3d import export_3dtiles
    from terralod.terrain import open_terrain

    z = fractal_terrain(161, 177, seed=4, relief_m=500.0)
    valid = np.ones(z.shape, bool)
    valid[40:70, 20:90] = False  # a void: its triangles are dropped
    hf = Heightfield(
        z.astype(np.float32), valid, Heightfield.from_array(z, 30.0).transform, "EPSG:32611", "v"
    )
    store = tmp_path / "s.terra"
    build_store(hf, store, method="chunked", workers=1, epoch="2000")
    hf2 = Heightfield(_planted(hf.elevation_m, 120, 120, 15, 9.0), valid, hf.transform, hf.crs, "v2")
    update_store(hf2, store, "2007", workers=1)

    def files(d: Path) -> dict[str, bytes]:
        return {q.relative_to(d).as_posix(): q.read_bytes() for q in d.rglob("*") if q.is_file() and
                not q.name.startswith(".")}  # fmt: skip

    with open_terrain(store) as t:
        export_3dtiles(t.with_epoch("2007"), tmp_path / "whole")
        monkeypatch.setattr(common, "WHOLE_VALIDITY_SAMPLES", 0)
        asked: list[int] = []
        real = common.KeptValidity.__getitem__
        monkeypatch.setattr(
            common.KeptValidity, "__getitem__", lambda kv, i: asked.append(len(i[0])) or real(kv, i)
        )
        export_3dtiles(t.with_epoch("2007"), tmp_path / "blocks")
        assert sum(asked) > 1000  # the triangles were checked against the kept blocks
        assert files(tmp_path / "blocks") == files(tmp_path / "whole")
        export_3dtiles(t.with_epoch("2000"), tmp_path / "blocks", update=True)
        export_3dtiles(t.with_epoch("2000"), tmp_path / "ref")
        assert files(tmp_path / "blocks") == files(tmp_path / "ref")


def test_a_dask_update_is_the_local_update(tmp_path: Path) -> None:
    """``update --dask``: the dirty tiles rebuilt on a LocalCluster of 2 worker processes are the local
    update's, byte for byte."""
    pytest.importorskip("dask.distributed", reason="dask[distributed] is not installed")
    from terralod.pyramid.distributed import dask_client

    z0 = fractal_terrain(161, 193, seed=12, relief_m=300.0)
    src0 = RasterSource(str(_write_tif(tmp_path / "a.tif", z0)))
    src1 = RasterSource(str(_write_tif(tmp_path / "b.tif", _planted(z0, 60, 140, 20, 6.0))))
    local, remote = tmp_path / "local.terra", tmp_path / "dask.terra"
    for p in (local, remote):
        build_store_windowed(src0, p, method="chunked", tile_size=33, workers=1, epoch="2000")
    update_store_windowed(src1, local, "2007", workers=1)
    client = dask_client("local", n_workers=2, threads=1)
    try:
        rep = update_store_windowed(src1, remote, "2007", client=client)
    finally:
        cluster = client.cluster
        client.close()
        cluster.close()
    assert rep.complete and rep.tiles_dirty > 0
    assert _epoch_rows(remote, "2007") == _epoch_rows(local, "2007")
