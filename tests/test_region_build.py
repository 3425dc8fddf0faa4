"""A geographic region builds out of core: SRTM-like 1° tiles warped block by block to a metric grid.

Four small EPSG:4326 GeoTIFFs cut from one raster (adjacent tiles sharing their edge row and column, as
SRTM's do) build into the store of the merged single file, tile for tile; every stored error holds against
every original sample at every level (the independent check of tests/test_honest_errors.py); a Dask
build gives the same bytes; a killed build resumes; the warped grid is the in-memory reader's.
"""

from __future__ import annotations

import os
import sqlite3
from pathlib import Path

import numpy as np
import pytest
from affine import Affine

from terralod.errors import InputError
from terralod.io.reader import read_heightfield
from terralod.io.windowed import RasterSource, WarpedSource, open_source, warp_frame
from terralod.pyramid.distributed import build_store_windowed, dask_client
from terralod.store import TileStore
from test_honest_errors import _assert_monotone, _sharp_relief, _write, check_against_original
from test_kill import _killed

rasterio = pytest.importorskip("rasterio")
pytest.importorskip("pyproj")

#: 3 arc-seconds (SRTM3), the tiles' pixel size in degrees.
D = 3.0 / 3600.0
#: Samples a side of the merged raster and of each quarter (sharing the middle row and column).
N = 121
Q = (N + 1) // 2


def _merged(path: Path) -> Path:
    """N x N samples of sharp relief near 43 N 1 E (pixel-is-area, like a GeoTIFF written from SRTM), a
    small nodata void."""
    z = _sharp_relief(N, 5)
    z[30:33, 80:84] = -32768.0
    return _write(path, z.astype(np.float32), Affine(D, 0.0, 1.0 - D / 2, 0.0, -D, 43.1 + D / 2), "EPSG:4326",
                  nodata=-32768.0)  # fmt: skip


def _quarters(merged: Path, folder: Path) -> list[Path]:
    """The merged raster cut into 2 x 2 tiles of Q x Q samples sharing the middle row and column."""
    folder.mkdir()
    out = []
    with rasterio.open(merged) as ds:
        z, t = ds.read(1), ds.transform
    for i in range(2):
        for j in range(2):
            r0, c0 = i * (Q - 1), j * (Q - 1)
            out.append(_write(folder / f"q{i}{j}.tif", np.ascontiguousarray(z[r0 : r0 + Q, c0 : c0 + Q]),
                              t @ Affine.translation(c0, r0), "EPSG:4326", nodata=-32768.0))  # fmt: skip
    return out


def _rows(path: Path) -> list[tuple]:
    conn = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
    try:
        return conn.execute("SELECT * FROM tiles ORDER BY level, x, y").fetchall()
    finally:
        conn.close()


@pytest.fixture(scope="module")
def region(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[Path]]:
    d = tmp_path_factory.mktemp("region")
    merged = _merged(d / "merged.tif")
    return merged, _quarters(merged, d / "tiles")


BUILD = {"tile_size": 17, "method": "adaptive", "workers": 2, "unit_span_samples": 64}


def test_warped_grid_is_the_in_memory_readers(region) -> None:
    """One file: the frame, the valid mask and the filled heights of the in-memory reader's reprojection
    (up to one float32 step, see WarpedSource); the quarters read as the merged file, whichever window."""
    merged, tiles = region
    hf = read_heightfield(merged)
    one = open_source([merged])
    assert isinstance(one, WarpedSource) and one.original_grid.n_valid == hf.original_grid.n_valid
    assert (one.width, one.height, one.transform, one.crs) == (hf.width, hf.height, hf.transform, hf.crs)
    z, ok = one.read(0, 0, one.height, one.width)
    np.testing.assert_array_equal(ok, hf.valid)
    np.testing.assert_allclose(z, hf.elevation_m, rtol=0, atol=1e-3)
    four = open_source(tiles)
    assert four.original_grid.n_valid == hf.original_grid.n_valid
    z4, ok4 = four.read(0, 0, four.height, four.width)
    np.testing.assert_array_equal(z4, z)
    np.testing.assert_array_equal(ok4, ok)
    zw, okw = four.read(37, 11, 90, 70)
    np.testing.assert_array_equal(zw, z[37:90, 11:70])
    np.testing.assert_array_equal(okw, ok[37:90, 11:70])
    with pytest.raises(InputError, match="gdalwarp"):
        RasterSource(merged)


def test_region_builds_the_merged_files_store_with_honest_errors(region, tmp_path: Path) -> None:
    """The four tiles build the merged file's tiles byte for byte (coarse tiles meshed from a decimated
    copy too), and every stored error bounds every original sample's gap at every level."""
    merged, tiles = region
    one, four = tmp_path / "one.terra", tmp_path / "four.terra"
    build_store_windowed(open_source([merged]), one, max_window_samples=65**2, **BUILD)
    build_store_windowed(open_source(tiles), four, max_window_samples=65**2, **BUILD)
    assert _rows(four) == _rows(one)
    with TileStore.open(four) as s:
        ref = s.meta["errors_measured_against"]
        assert (
            ref["samples"] == "original" and ref["valid_samples"] == open_source(tiles).original_grid.n_valid
        )
        assert s.meta["notes"][-1].startswith("reprojected from EPSG:4326 to EPSG:32631")
    res = check_against_original(merged, four)
    n_valid = ref["valid_samples"]
    for level, (checked, _) in res.items():
        assert checked >= 0.97 * n_valid, (level, checked, n_valid)
    assert max(worst for _, worst in res.values()) > 1.0  # resampling moved samples: the check has teeth
    _assert_monotone(four)


def test_grid_only_errors_fail_the_check(region, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Without the original samples (the grid alone, as before) the same independent check fails."""
    merged, tiles = region
    monkeypatch.setattr(WarpedSource, "original_grid", property(lambda self: None))
    out = tmp_path / "grid_only.terra"
    build_store_windowed(open_source(tiles), out, **BUILD)
    with pytest.raises(AssertionError):
        check_against_original(merged, out)


def test_dask_gives_the_local_bytes(region, tmp_path: Path) -> None:
    pytest.importorskip("dask.distributed", reason="dask[distributed] is not installed")
    _, tiles = region
    local = tmp_path / "local.terra"
    build_store_windowed(open_source(tiles), local, **BUILD)
    client = dask_client("local", n_workers=2, threads=1)
    try:
        out = tmp_path / "dask.terra"
        build_store_windowed(open_source(tiles), out, client=client,
                             **{k: v for k, v in BUILD.items() if k != "workers"})  # fmt: skip
    finally:
        cluster = client.cluster
        client.close()
        cluster.close()
    assert _rows(out) == _rows(local)


@pytest.mark.skipif(not hasattr(os, "fork"), reason="kill tests fork the build (POSIX only)")
def test_killed_region_build_resumes(region, tmp_path: Path) -> None:
    _, tiles = region
    ref = tmp_path / "ref.terra"
    build_store_windowed(open_source(tiles), ref, **BUILD)
    out = tmp_path / "killed.terra"
    total = len(_rows(ref))

    def cb(done: int, _total: int) -> None:
        if done >= total // 2:
            os.kill(os.getpid(), 9)

    _killed(lambda: build_store_windowed(open_source(tiles), out, progress=cb, **BUILD))
    partial = len(_rows(out)) if out.exists() else 0
    assert partial < total
    rep = build_store_windowed(open_source(tiles), out, resume=True, **BUILD)
    assert rep.tiles_skipped == partial
    assert _rows(out) == _rows(ref)


def test_wide_region_gets_a_transverse_mercator() -> None:
    """Wider than one UTM zone takes: a Transverse Mercator on the central meridian, said in the note."""
    from rasterio.crs import CRS

    t = Affine(0.05, 0.0, -10.0, 0.0, -0.05, 46.0)
    crs, dst_t, w, h, note, margin = warp_frame(CRS.from_epsg(4326), t, (100, 500), "wide")
    assert "tmerc" in crs.to_proj4() and "+lon_0=2.5" in crs.to_proj4()
    assert "Transverse Mercator" in note and "too wide for one UTM zone" in note
    assert 0.0 < margin < 0.5 and w > 0 and h > 0 and dst_t.a == -dst_t.e


def test_cli_builds_a_folder_of_geographic_tiles(region, tmp_path: Path) -> None:
    from click.testing import CliRunner

    from terralod.cli import cli

    _, tiles = region
    out = tmp_path / "cli.terra"
    res = CliRunner().invoke(cli, ["build", str(tiles[0].parent), "-o", str(out), "--tile-size", "17"])
    assert res.exit_code == 0, res.output
    assert "original samples" in res.output
    with TileStore.open(out) as s:
        assert s.meta["errors_measured_against"]["samples"] == "original"


def test_a_build_the_disk_cannot_hold_is_refused_before_anything_is_written(
    region, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The free-disk check of an out-of-core build: a store estimated beyond the disk's free space is one
    line naming the output, exit 2, no file written (with the default estimate the build above runs)."""
    import terralod.cli._windowed as windowed

    from conftest import terralod_cli

    _, tiles = region
    out = tmp_path / "big.terra"
    monkeypatch.setattr(windowed, "STORE_BYTES_PER_SAMPLE", 1e12)  # a petabyte a sample: no disk has it
    res = terralod_cli("build", tiles[0].parent, "-o", out, "--tile-size", "17")
    assert res.returncode == 2, res.stderr
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and str(out) in lines[0] and "free" in lines[0], res.stderr
    assert list(tmp_path.iterdir()) == []


def test_large_tiles_measure_original_samples_in_strips(
    region, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Tiles over MEASURE_STRIP_SAMPLES take their original samples in blocks of rows and columns: the same
    geometry and sample counts as one window of the whole footprint, errors up to rounding (each block's
    samples are placed from its own north-west corner), and no block takes more than a few times
    MEASURE_STRIP_SAMPLES samples, however wide the tile (strips of a tile's whole width took its width)."""
    import terralod.pyramid.distributed as dist
    import terralod.pyramid.original as original

    merged, tiles = region
    whole = tmp_path / "whole.terra"
    build_store_windowed(open_source(tiles), whole, **BUILD)
    monkeypatch.setattr(dist, "MEASURE_STRIP_SAMPLES", 16)
    taken: list[int] = []
    tile_samples = original.tile_samples

    def counted(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        got = tile_samples(*args, **kwargs)
        taken.append(got[0].size)
        return got

    monkeypatch.setattr(original, "tile_samples", counted)
    strips = tmp_path / "strips.terra"
    build_store_windowed(open_source(tiles), strips, **BUILD)
    assert taken and max(taken) <= 4 * 16, max(taken)
    with rasterio.open(merged) as ds:
        assert ds.width > 4 * 16  # a full-width strip of the coarsest tile takes more
    a, b = _rows(whole), _rows(strips)
    # code, sample count, heights, geometry exactly; the five error columns to rounding
    assert [r[:3] + r[8:-1] for r in a] == [r[:3] + r[8:-1] for r in b]
    np.testing.assert_allclose([r[3:8] for r in a], [r[3:8] for r in b], rtol=0, atol=1e-6)
    check_against_original(merged, strips)


def test_a_region_stores_export_reads_its_tiles_again(region, tmp_path: Path) -> None:
    """A store built from a folder of geographic tiles records its files; its quantized-mesh export reads
    them again window by window (no merge of the store's meshes) and gives the direct export's tiles."""
    from click.testing import CliRunner

    from terralod.cli import cli
    from terralod.export.source import RegionGrid, source_for
    from terralod.terrain import open_terrain

    _, tiles = region
    store = tmp_path / "r.terra"
    res = CliRunner().invoke(cli, ["build", str(tiles[0].parent), "-o", str(store), "--tile-size", "17"])
    assert res.exit_code == 0, res.output
    with TileStore.open(store) as s:
        assert sorted(s.meta["source_files"]) == sorted(str(t.resolve()) for t in tiles)
    with open_terrain(store) as t:
        assert isinstance(source_for(t, None), RegionGrid)
    for args, out in (([str(store)], tmp_path / "from_store"), ([str(tiles[0].parent)], tmp_path / "direct")):
        res = CliRunner().invoke(cli, ["export", *args, "--format", "quantized-mesh", "-o", str(out)])
        assert res.exit_code == 0, res.output
    a = {
        p.relative_to(tmp_path / "from_store"): p.read_bytes()
        for p in (tmp_path / "from_store").rglob("*.terrain")
    }
    b = {p.relative_to(tmp_path / "direct"): p.read_bytes() for p in (tmp_path / "direct").rglob("*.terrain")}
    assert a and a == b
