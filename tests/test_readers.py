"""Heightfield readers: every format round-trips, geographic inputs get a metric frame, bad input gets a
clear error naming the file."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import rasterio
from hypothesis import given, settings
from hypothesis import strategies as st
from PIL import Image
from rasterio.transform import from_origin

from terralod import Heightfield, InputError, InputNotFoundError, read_heightfield, sample_heightfield

from conftest import fractal_terrain


def _tif(path: Path, z: np.ndarray, crs: str, transform, nodata=None) -> Path:
    with rasterio.open(path, "w", driver="GTiff", width=z.shape[1], height=z.shape[0], count=1, dtype=z.dtype,
                       crs=crs, transform=transform, nodata=nodata) as ds:  # fmt: skip
        ds.write(z, 1)
    return path


def test_projected_geotiff_frame_and_nodata(tmp_path: Path) -> None:
    z = fractal_terrain(40, 60, 1, 300).astype(np.float32)
    z[5:8, 10:14] = -9999
    p = _tif(
        tmp_path / "utm.tif", z, "EPSG:32610", from_origin(500000.0, 5200000.0, 30.0, 30.0), nodata=-9999
    )
    hf = read_heightfield(p)
    assert hf.shape == (40, 60) and hf.spacing_m == (30.0, 30.0)
    assert "32610" in hf.crs or "UTM zone 10N" in hf.crs
    # sample (row, col) at its pixel centre in the CRS's own metres
    x, y = hf.world_xy(0, 0)
    assert (float(x), float(y)) == (500015.0, 5199985.0)
    assert (~hf.valid).sum() == 12 and not hf.valid[6, 12]
    # filled cells lie within the range of their rim: no cliff down to -9999
    rim = z[4:9, 9:15][hf.valid[4:9, 9:15]]
    assert (
        rim.min() - 1e-3 <= hf.elevation_m[5:8, 10:14].min()
        and hf.elevation_m[5:8, 10:14].max() <= rim.max() + 1e-3
    )
    assert np.array_equal(hf.elevation_m[hf.valid], z[hf.valid])


def test_south_up_raster_is_flipped(tmp_path: Path) -> None:
    z = np.arange(20, dtype=np.float32).reshape(4, 5)
    north_up = read_heightfield(_tif(tmp_path / "n.tif", z, "EPSG:32610", from_origin(0, 400, 100, 100)))
    south_up = read_heightfield(
        _tif(tmp_path / "s.tif", z[::-1].copy(), "EPSG:32610", rasterio.Affine(100, 0, 0, 0, 100, 0))
    )
    assert np.array_equal(north_up.elevation_m, south_up.elevation_m)
    assert tuple(north_up.transform) == tuple(south_up.transform)


def test_geographic_reprojected_to_utm_ground_metres(tmp_path: Path) -> None:
    # 3 arc-second grid at 46.5 N, 7.5 E (UTM 32N): ~64 m east-west, ~93 m north-south on the ground
    d = 3.0 / 3600.0
    z = np.zeros((120, 120), np.float32)
    z[60, 60] = 500.0  # a spike marks a known place
    p = _tif(tmp_path / "geo.tif", z, "EPSG:4326", from_origin(7.45, 46.55, d, d))
    hf = read_heightfield(p)
    assert "UTM zone 32N" in hf.crs and any("reprojected" in n for n in hf.notes)
    dx, dy = hf.spacing_m
    lat = math.radians(46.55 - 60.5 * d)
    expect_dx = d * math.pi / 180 * 6378137.0 * math.cos(lat) / math.sqrt(1 - 0.00669438 * math.sin(lat) ** 2)
    assert dx == dy and abs(dx - expect_dx) / expect_dx < 0.01
    # the spike stays at its place: 7.45 + 60.5 d E, 46.55 - 60.5 d N
    from rasterio.warp import transform as warp

    (ex,), (ey,) = warp("EPSG:4326", hf.crs, [7.45 + 60.5 * d], [46.55 - 60.5 * d])
    r, c = np.unravel_index(np.argmax(hf.elevation_m), hf.shape)
    x, y = hf.world_xy(r, c)
    assert math.hypot(float(x) - ex, float(y) - ey) < 1.5 * max(dx, 93.0)


@pytest.mark.parametrize("bits", [8, 16])
def test_png_heightmap_scale_offset(tmp_path: Path, bits: int) -> None:
    rng = np.random.default_rng(bits)
    dtype = np.uint8 if bits == 8 else np.uint16
    v = rng.integers(0, 2**bits, size=(30, 40)).astype(dtype)
    p = tmp_path / f"h{bits}.png"
    Image.fromarray(v).save(p)
    hf = read_heightfield(p, vertical_scale=0.5, vertical_offset=-10.0, spacing_m=(2.0, 3.0))
    assert hf.spacing_m == (2.0, 3.0) and hf.crs is None
    assert np.allclose(hf.elevation_m, v * 0.5 - 10.0)


@given(
    z=st.lists(st.floats(-500, 8000, allow_nan=False), min_size=64, max_size=64),
    fmt=st.sampled_from(["png", "webp"]),
)
@settings(max_examples=20, deadline=None)
def test_encoded_tiles_round_trip(tmp_path_factory, z: list[float], fmt: str) -> None:
    tmp = tmp_path_factory.mktemp("enc")
    h = np.array(z).reshape(8, 8)
    for enc in ("terrain-rgb", "terrarium"):
        if enc == "terrain-rgb":
            code = np.round((h + 10000.0) * 10).astype(np.int64)
            rgb = np.stack([(code >> 16) & 255, (code >> 8) & 255, code & 255], -1).astype(np.uint8)
            expect, tol = code * 0.1 - 10000.0, 1e-6
        else:
            code = np.round((h + 32768.0) * 256).astype(np.int64)
            rgb = np.stack([(code >> 16) & 255, (code >> 8) & 255, code & 255], -1).astype(np.uint8)
            expect, tol = code / 256.0 - 32768.0, 1e-6
        p = tmp / f"t.{fmt}"
        Image.fromarray(rgb).save(p, **({"lossless": True} if fmt == "webp" else {}))
        hf = read_heightfield(p, encoding=enc, spacing_m=10.0)
        assert np.allclose(hf.elevation_m, expect, atol=max(tol, 1e-3 * np.abs(expect).max() * 1e-3))


def test_npy_npz_with_sidecar(tmp_path: Path) -> None:
    z = fractal_terrain(20, 30, 2)
    np.save(tmp_path / "a.npy", z)
    (tmp_path / "a.json").write_text(json.dumps({"spacing_m": [5, 6], "vertical_scale": 2.0}))
    hf = read_heightfield(tmp_path / "a.npy")
    assert hf.spacing_m == (5.0, 6.0) and np.allclose(hf.elevation_m, z * 2.0)
    np.savez(tmp_path / "b.npz", elevation=z)
    (tmp_path / "b.json").write_text(
        json.dumps({"crs": "EPSG:32633", "transform": [400000, 10, 0, 5000000, 0, -10]})
    )
    hf = read_heightfield(tmp_path / "b.npz")
    assert hf.spacing_m == (10.0, 10.0) and tuple(hf.bounds_m)[0] == 400000.0
    assert read_heightfield(tmp_path / "b.npz", spacing_m=1.0).spacing_m == (10.0, 10.0)


def test_bad_inputs_name_the_file(tmp_path: Path) -> None:
    with pytest.raises(InputNotFoundError, match="nope.tif: file not found"):
        read_heightfield(tmp_path / "nope.tif")
    (tmp_path / "x.tif").write_bytes(b"\x00garbage" * 100)
    with pytest.raises(InputError, match=r"x\.tif: not a raster"):
        read_heightfield(tmp_path / "x.tif")
    (tmp_path / "y.png").write_bytes(b"not an image")
    with pytest.raises(InputError, match=r"y\.png: not a PNG/WebP"):
        read_heightfield(tmp_path / "y.png", spacing_m=1.0)
    np.save(tmp_path / "nan.npy", np.full((10, 10), np.nan))
    with pytest.raises(InputError, match="every sample is NaN"):
        read_heightfield(tmp_path / "nan.npy", spacing_m=1.0)
    np.save(tmp_path / "tiny.npy", np.ones((1, 5)))
    with pytest.raises(InputError, match="5x1 samples"):
        read_heightfield(tmp_path / "tiny.npy", spacing_m=1.0)
    rgb = np.zeros((10, 10, 3), np.uint8)
    rgb[..., 0] = 255  # a coloured image (equal channels would be read as greyscale)
    Image.fromarray(rgb).save(tmp_path / "rgb.png")
    with pytest.raises(InputError, match="--encoding"):
        read_heightfield(tmp_path / "rgb.png", spacing_m=1.0)
    with pytest.raises(InputError, match="elevations reach"):
        Heightfield.from_array(np.full((5, 5), 3e7), 1.0)


def test_sample_heightfield() -> None:
    hf = sample_heightfield()
    assert "UTM zone 16N" in hf.crs
    lo, hi = hf.valid_range_m()
    assert 200 < lo < 300 and 1000 < hi < 1100  # Jacksboro fault: 236..1072 m in the source grid
    assert hf.spacing_m[0] == hf.spacing_m[1] and 70 < hf.spacing_m[0] < 80


@pytest.mark.parametrize(
    "name, expect_range, spacing",
    [
        ("dem/puget_sound_1k_u16.png", (0.0, 4379.8), 160.0),
        ("dem/grand_canyon_hoppe_1200_u8.png", (641.0, 2763.0), 60.0),  # sidecar range (14 m steps)
        ("dem/kilauea_hawaii_30m_utm5.tif", (0.0, 1505.0), 30.0),
        ("tiles/terrarium_grand_canyon_z11_385_803.png", (715.17, 2488.95), 61.8),
        ("tiles/mapterhorn_terrarium_saxon_switzerland_z10_552_343_512px.webp", (113.0, 723.0), 48.3),
        ("dem/srtm3_N42E001.tif", (349.0, 3100.0), 68.4),
        ("dem/srtm1_crop256_coastal_flat_nodata.tif", (1.0, 26.0), 27.9),
    ],
)
def test_real_files(shared_data: Path, name: str, expect_range: tuple[float, float], spacing: float) -> None:
    hf = read_heightfield(shared_data / name)
    lo, hi = hf.valid_range_m()
    relief = expect_range[1] - expect_range[0]
    # bilinear reprojection smooths extremes a little; encoded tiles are exact
    assert expect_range[0] - 0.02 * relief <= lo and hi <= expect_range[1] + 0.02 * relief
    assert hi - lo > 0.9 * relief
    assert abs(hf.spacing_m[0] - spacing) / spacing < 0.02
    assert np.isfinite(hf.elevation_m).all()
