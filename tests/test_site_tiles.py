"""The change site's rasters as tile pyramids (terralod.site.tiles, issue 54): the tiles decode (as the page
decodes them) to dod.tif within the step site.json states, every tile the manifest names is there and no other,
coarser levels are the block means, the pyramid read window by window from dod.tif is the site's byte for byte,
and no file of the site is over 8 MB. The browser side (changeAt, volume, the drape) is tests/test_site.py."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from terralod.cli import main
from terralod.site.tiles import (
    NODATA_Q,
    STEP_M,
    TILE_PX,
    array_rows,
    decode_tile,
    encode_tile,
    raster_rows,
    read_level,
    write_pyramid,
)

BEFORE = "change/st_helens_crater_2000-09-25_10m.tif"
AFTER = "change/st_helens_crater_2007-07-05_10m.tif"


@pytest.fixture(scope="module")
def run(shared_data: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("tiles") / "out"
    try:
        main(
            [
                "change",
                str(shared_data / BEFORE),
                str(shared_data / AFTER),
                "-o",
                str(out),
                "--site",
                "--no-views",
            ]
        )
    except SystemExit as exc:
        assert exc.code in (0, None)
    return out


def _block_means(a: np.ndarray, f: int) -> np.ndarray:
    h, w = a.shape
    H, W = -(-h // f), -(-w // f)
    p = np.full((H * f, W * f), np.nan)
    p[:h, :w] = a
    b = p.reshape(H, f, W, f)
    n = np.isfinite(b).sum(axis=(1, 3))
    s = np.nansum(b, axis=(1, 3))
    with np.errstate(invalid="ignore"):
        return np.where(n > 0, s / np.maximum(n, 1), np.nan)


def test_site_tiles_decode_to_dod_tif_within_the_step(run: Path, shared_data: Path) -> None:
    import rasterio

    site = run / "site"
    manifest = json.loads((site / "site.json").read_text())
    enc = manifest["rasters"]
    assert enc["step_m"] == STEP_M <= 0.001 and enc["nodata"] == NODATA_Q and enc["tile_px"] == TILE_PX
    pair = json.loads((site / "pairs/0.json").read_text())
    with rasterio.open(run / "dod.tif") as ds:
        dod = ds.read(1, masked=True).astype(np.float64).filled(np.nan)
    desc = pair["rasters"]["dod"]

    def get(name: str) -> bytes | None:
        f = site / name
        return f.read_bytes() if f.is_file() else None

    level0 = read_level(desc, get, 0)
    assert np.array_equal(np.isfinite(level0), np.isfinite(dod))  # no data flagged where dod.tif has none
    assert np.nanmax(np.abs(level0 - dod)) <= STEP_M / 2 + 1e-9
    for k in range(1, len(desc["levels"])):  # each level: the means of level 0's 2^k blocks, within the step
        got = read_level(desc, get, k)
        want = _block_means(dod, 2**k)
        assert got.shape == want.shape and np.array_equal(np.isfinite(got), np.isfinite(want))
        assert np.nanmax(np.abs(got - want)) <= STEP_M / 2 + 1e-9, k
    assert max(desc["levels"][-1]["shape"]) <= TILE_PX  # the last level is one tile
    # every tile the manifests name is there, and no other
    named = set()
    for role, d in pair["rasters"].items():
        for k, lv in enumerate(d["levels"]):
            nc = -(-lv["shape"][1] // TILE_PX)
            assert len(lv["tiles"]) == nc * -(-lv["shape"][0] // TILE_PX), role
            named |= {
                f"{d['url']}/{k}/{i // nc}_{i % nc}.i32.gz" for i, f in enumerate(lv["tiles"]) if f == "1"
            }
    on_disk = {p.relative_to(site).as_posix() for p in (site / "pairs").rglob("*.i32.gz")}
    assert named == on_disk
    # BEFORE heights: the first epoch's DEM
    before = read_level(pair["rasters"]["before"], get, 0)
    with rasterio.open(shared_data / BEFORE) as ds:
        z = ds.read(1, masked=True).astype(np.float64).filled(np.nan)
    assert np.nanmax(np.abs(before - z)) <= STEP_M / 2 + 1e-6
    # no file of the site over 8 MB
    biggest = max(site.rglob("*"), key=lambda p: p.stat().st_size if p.is_file() else 0)
    assert biggest.stat().st_size <= 8 << 20, biggest


def test_pyramid_from_dod_tif_window_by_window_is_the_sites(run: Path) -> None:
    """raster_rows reads dod.tif in strips (here 100 rows: not a multiple of the tile) and the pyramid is the
    site's, tile for tile."""
    site = run / "site"
    desc = json.loads((site / "pairs/0.json").read_text())["rasters"]["dod"]
    read, shape, close = raster_rows(run / "dod.tif")
    try:
        got, files = write_pyramid(read, shape, desc["url"], strip_rows=100)
    finally:
        close()
    assert got == desc
    for name, data in files.items():
        assert (site / name).read_bytes() == data, name


@settings(max_examples=25, deadline=None)
@given(
    h=st.integers(1, 700),
    w=st.integers(1, 600),
    strip=st.integers(1, 600),
    seed=st.integers(0, 2**16),
)
def test_pyramid_of_any_shape_and_strip(h: int, w: int, strip: int, seed: int) -> None:
    """Any shape, any strip height: level 0 is the grid within the step (NaN where it has no data, extreme
    and alternating values wrap through the int32 deltas), level k the block means, the same tiles whatever
    the strip."""
    rng = np.random.default_rng(seed)
    a = rng.normal(0, 300, (h, w))
    a[rng.random((h, w)) < 0.2] = np.nan
    a[rng.random((h, w)) < 0.01] = 2_000_000.0 * rng.choice([-1, 1])  # deltas near int32's ends
    desc, files = write_pyramid(array_rows(a), (h, w), "p", strip_rows=strip)
    ref, ref_files = write_pyramid(array_rows(a), (h, w), "p")
    assert desc == ref and files == ref_files
    for k in range(len(desc["levels"])):
        got = read_level(desc, files.get, k)
        want = _block_means(a, 2**k) if k else a
        assert np.array_equal(np.isfinite(got), np.isfinite(want)), k
        if np.isfinite(want).any():
            assert np.nanmax(np.abs(got - want)) <= STEP_M / 2 + 1e-6, k


def test_tile_encoding_round_trip_and_refusal() -> None:
    t = np.array([[0.0, np.nan, -0.0004, 0.0006], [2147.4, -2147.4, np.nan, np.nan]])
    got = decode_tile(encode_tile(t), t.shape)
    assert np.array_equal(np.isnan(got), np.isnan(t))
    assert np.nanmax(np.abs(got - t)) <= STEP_M / 2 + 1e-12
    with pytest.raises(ValueError, match="int32"):
        encode_tile(np.array([[3e6]]))
