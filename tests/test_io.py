"""Heightfield readers (terralod.io): every format lands in a metric, north-up frame with the right
elevations, geographic inputs get ground metres, and bad input gets one clear error naming the file."""

from __future__ import annotations

import json
import math
import struct
import warnings
import zlib
from pathlib import Path

import numpy as np
import pytest
import rasterio
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from PIL import Image
from rasterio import Affine
from rasterio.errors import NotGeoreferencedWarning
from rasterio.transform import from_origin
from rasterio.warp import transform as warp_points

from terralod.errors import InputError, InputNotFoundError, TerralodError
from terralod.io.heightmap import decode_terrarium, encode_terrain_rgb, encode_terrarium
from terralod.io.raster import utm_crs
from terralod.io.reader import read_heightfield, read_sidecar, sample_heightfield

R_SPHERE_M = 6371008.8  # mean Earth radius, for independent haversine checks (ellipsoid differs < 0.5 %)
WEB_MERCATOR_R_M = 6378137.0


# -- helpers -------------------------------------------------------------------------------------------
def _tif(path: Path, z: np.ndarray, crs: str | None, transform: Affine | None, nodata=None, **tags) -> Path:
    bands = z[None] if z.ndim == 2 else z
    profile = {"driver": "GTiff", "width": z.shape[-1], "height": z.shape[-2], "count": bands.shape[0],
               "dtype": z.dtype, "crs": crs, "transform": transform, "nodata": nodata}  # fmt: skip
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NotGeoreferencedWarning)  # un-georeferenced test files on purpose
        with rasterio.open(path, "w", **{k: v for k, v in profile.items() if v is not None}) as ds:
            ds.write(bands)
            if "scales" in tags:
                ds.scales, ds.offsets = tags["scales"], tags["offsets"]
    return path


def _haversine_m(lon1: float, lat1: float, lon2: float, lat2: float) -> float:
    p1, p2 = math.radians(lat1), math.radians(lat2)
    dp, dl = p2 - p1, math.radians(lon2 - lon1)
    a = math.sin(dp / 2) ** 2 + math.cos(p1) * math.cos(p2) * math.sin(dl / 2) ** 2
    return 2 * R_SPHERE_M * math.asin(math.sqrt(a))


def _lonlat(hf, rows, cols) -> tuple[np.ndarray, np.ndarray]:
    x, y = hf.world_xy(rows, cols)
    lon, lat = warp_points(hf.crs, "EPSG:4326", np.ravel(x).tolist(), np.ravel(y).tolist())
    return np.asarray(lon), np.asarray(lat)


def _interior(hf, margin: int = 2) -> np.ndarray:
    """Valid cells at least ``margin`` cells away from any invalid cell or the border."""
    from scipy import ndimage

    inner = ndimage.binary_erosion(hf.valid, iterations=margin)
    inner[:margin], inner[-margin:], inner[:, :margin], inner[:, -margin:] = False, False, False, False
    return inner


def _png_header_only(path: Path, width: int, height: int) -> Path:
    """A PNG whose header declares width x height 16-bit grey and whose data is a few bytes."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    ihdr = struct.pack(">IIBBBBB", width, height, 16, 0, 0, 0, 0)
    path.write_bytes(
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", ihdr)
        + chunk(b"IDAT", zlib.compress(b"\0" * 8))
        + chunk(b"IEND", b"")
    )
    return path


# -- GeoTIFF: projected ---------------------------------------------------------------------------------
def test_projected_utm_geotiff_keeps_its_metres_and_masks_nodata(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    z = rng.uniform(100, 900, size=(40, 60)).astype(np.float32)
    z[5:8, 10:14] = -9999
    p = _tif(tmp_path / "utm.tif", z, "EPSG:32610", from_origin(500000.0, 5200000.0, 30.0, 30.0), -9999)
    hf = read_heightfield(p)
    assert hf.shape == (40, 60) and hf.spacing_m == (30.0, 30.0)
    assert "UTM zone 10N" in hf.crs and not any("reprojected" in n for n in hf.notes)
    assert hf.world_xy(0, 0) == (500015.0, 5199985.0)  # pixel centre, in the CRS's own metres
    assert (~hf.valid).sum() == 12 and not hf.valid[6, 12] and hf.valid[4, 9]
    assert np.array_equal(hf.elevation_m[hf.valid], z[hf.valid])  # valid samples untouched
    rim = z[4:9, 9:15][hf.valid[4:9, 9:15]]  # filled cells stay within their rim: no cliff to -9999
    assert (
        rim.min() - 1e-3
        <= hf.elevation_m[5:8, 10:14].min()
        <= hf.elevation_m[5:8, 10:14].max()
        <= rim.max() + 1e-3
    )
    assert hf.fill_method and hf.source == str(p)


@pytest.mark.parametrize(
    "transform, flip, note",
    [
        (Affine(100, 0, 0, 0, 100, 0), (slice(None, None, -1), slice(None)), "south-up"),
        (Affine(-100, 0, 500, 0, -100, 400), (slice(None), slice(None, None, -1)), "east to west"),
    ],
)
def test_south_up_and_east_west_rasters_are_flipped(tmp_path: Path, transform, flip, note) -> None:
    z = np.arange(20, dtype=np.float32).reshape(4, 5)
    north_up = read_heightfield(_tif(tmp_path / "n.tif", z, "EPSG:32610", from_origin(0, 400, 100, 100)))
    flipped = read_heightfield(
        _tif(tmp_path / "f.tif", np.ascontiguousarray(z[flip]), "EPSG:32610", transform)
    )
    assert np.array_equal(north_up.elevation_m, flipped.elevation_m)
    assert tuple(north_up.transform) == tuple(flipped.transform)
    assert any(note in n for n in flipped.notes)


def test_rotated_transform_is_refused(tmp_path: Path) -> None:
    z = np.ones((4, 4), np.float32)
    p = _tif(tmp_path / "rot.tif", z, "EPSG:32610", Affine(10, 2, 0, 2, -10, 100))
    with pytest.raises(InputError, match=r"rot\.tif: has a rotated or sheared geotransform"):
        read_heightfield(p)


def test_scale_offset_tags_and_band(tmp_path: Path) -> None:
    z = np.stack([np.full((3, 4), 10, np.int16), np.arange(12, dtype=np.int16).reshape(3, 4)])
    t = from_origin(0, 30, 10, 10)
    p = _tif(tmp_path / "s.tif", z, "EPSG:32633", t, scales=(0.5, 0.1), offsets=(0.0, 5.0))
    assert np.allclose(read_heightfield(p).elevation_m, 5.0)
    hf = read_heightfield(p, band=2)
    assert np.allclose(hf.elevation_m, z[1] * 0.1 + 5.0, atol=1e-5)
    assert any("* 0.1 + 5" in n for n in hf.notes)
    assert np.allclose(read_heightfield(p, band=2, vertical_scale=2.0).elevation_m, z[1] * 2.0 + 5.0)
    with pytest.raises(InputError, match=r"s\.tif: has 2 band\(s\); band 3 requested"):
        read_heightfield(p, band=3)


def test_foot_crs_is_converted_to_metres(tmp_path: Path) -> None:
    # NAD83 / Oregon GIC Lambert (international feet): coordinates become metres of the same projection
    z = np.linspace(100, 200, 30, dtype=np.float32).reshape(5, 6)
    x0_ft, y0_ft, px_ft = 1_200_000.0, 800_000.0, 100.0
    hf = read_heightfield(_tif(tmp_path / "ft.tif", z, "EPSG:2992", from_origin(x0_ft, y0_ft, px_ft, px_ft)))
    assert hf.spacing_m == pytest.approx((30.48, 30.48))
    assert np.array_equal(hf.elevation_m, z)  # elevations are not touched
    assert any("foot" in n and "metres" in n for n in hf.notes)
    with rasterio.Env():
        assert rasterio.crs.CRS.from_wkt(hf.crs).linear_units_factor[1] == 1.0
    # the same place on the globe, through the foot CRS and through the metric one
    rows, cols = np.array([0, 4, 2]), np.array([0, 5, 3])
    lon_m, lat_m = _lonlat(hf, rows, cols)
    xs_ft, ys_ft = x0_ft + (cols + 0.5) * px_ft, y0_ft - (rows + 0.5) * px_ft
    lon_f, lat_f = warp_points("EPSG:2992", "EPSG:4326", xs_ft.tolist(), ys_ft.tolist())
    assert np.allclose(lon_m, lon_f, atol=1e-8) and np.allclose(lat_m, lat_f, atol=1e-8)


# -- GeoTIFF: geographic and web mercator -> UTM ---------------------------------------------------------
def test_geographic_is_reprojected_to_utm_ground_metres(tmp_path: Path) -> None:
    # 3 arc-second grid at 46.5 N, 7.5 E (UTM 32N): ~64 m east-west and ~93 m north-south on the ground
    d = 3.0 / 3600.0
    west, north, n = 7.45, 46.55, 120
    lon_c = west + (np.arange(n) + 0.5) * d
    lat_c = north - (np.arange(n) + 0.5) * d
    plane = 2000.0 * (lon_c[None, :] - west) + 4000.0 * (north - lat_c[:, None])  # metres, linear in degrees
    z = (500.0 + plane).astype(np.float32)
    z[30:34, 80:84] = np.nan  # a hole at a known place
    hf = read_heightfield(_tif(tmp_path / "geo.tif", z, "EPSG:4326", from_origin(west, north, d, d), np.nan))
    note = next(n for n in hf.notes if "reprojected" in n)
    assert note.startswith("reprojected from EPSG:4326 to EPSG:32632 (UTM 32N) at ") and "bilinear" in note
    assert "UTM zone 32N" in hf.crs
    # square pixels of the ground spacing at the centre: the east-west one (the smaller), never degrees
    dx, dy = hf.spacing_m
    lat0 = north - n / 2 * d
    ground_dx = _haversine_m(7.5, lat0, 7.5 + d, lat0)
    assert dx == dy and abs(dx - ground_dx) / ground_dx < 0.01
    # the UTM box holds the footprint, a little wider for the grid's rotation (meridian convergence ~1.1 deg)
    assert 1.0 < hf.width * dx / (_haversine_m(west, lat0, west + n * d, lat0)) < 1.06
    # every interior cell holds the plane's value at its own lon/lat: the terrain stayed in place
    inner = _interior(hf)
    rows, cols = np.nonzero(inner)
    lon, lat = _lonlat(hf, rows, cols)
    expect = 500.0 + 2000.0 * (lon - west) + 4000.0 * (north - lat)
    assert np.abs(hf.elevation_m[rows, cols] - expect).max() < 0.05  # bilinear is exact on a plane
    # the hole is invalid at its own place (centre 46.55 - 32 d N, 7.45 + 82 d E)
    (hx,), (hy,) = warp_points("EPSG:4326", hf.crs, [west + 82 * d], [north - 32 * d])
    r, c = hf.sample_rc(hx, hy)
    assert not hf.valid[int(round(float(r))), int(round(float(c)))]
    assert hf.nodata_fraction < 0.1


def test_southern_hemisphere_utm_and_mercator_geotiff(tmp_path: Path) -> None:
    d = 1.0 / 3600.0
    z = np.full((50, 50), 42.0, np.float32)
    hf = read_heightfield(_tif(tmp_path / "syd.tif", z, "EPSG:4326", from_origin(151.2, -33.8, d, d)))
    assert "UTM zone 56S" in hf.crs and np.allclose(hf.elevation_m, 42.0)
    # web mercator 'metres' at 50 N are cos(50) ground metres: 100 m mercator pixels -> ~64 m
    x0 = 10.0 / 180.0 * math.pi * WEB_MERCATOR_R_M
    y0 = WEB_MERCATOR_R_M * math.log(math.tan(math.pi / 4 + math.radians(50.0) / 2))
    merc = read_heightfield(_tif(tmp_path / "m.tif", z, "EPSG:3857", from_origin(x0, y0, 100.0, 100.0)))
    assert "UTM zone 32N" in merc.crs and any("from EPSG:3857" in n for n in merc.notes)
    lat_c = math.atan(math.sinh((y0 - 25 * 100.0) / WEB_MERCATOR_R_M))
    expect = 100.0 * math.cos(lat_c)
    assert abs(merc.spacing_m[0] - expect) / expect < 0.01


@pytest.mark.parametrize(
    "lon, lat, epsg",
    [(1.5, 42.5, 32631), (-84.25, 36.6, 32616), (151.2, -33.9, 32756), (179.99, 10, 32660),
     (-180.0, 10, 32601), (180.0, 10, 32601), (0.0, 85.0, 32661), (0.0, -85.0, 32761)],
)  # fmt: skip
def test_utm_zone_choice(lon: float, lat: float, epsg: int) -> None:
    assert utm_crs(lon, lat)[0].to_epsg() == epsg


def test_geographic_misuse_is_refused(tmp_path: Path) -> None:
    z = np.zeros((10, 10), np.float32)
    wide = _tif(tmp_path / "wide.tif", z, "EPSG:4326", from_origin(-20, 10, 4.0, 1.0))
    with pytest.raises(InputError, match=r"wide\.tif: spans 40\.0 degrees of longitude"):
        read_heightfield(wide)
    # UTM metres labelled as degrees: refused, never read as a gigantic lon/lat grid
    bad = _tif(tmp_path / "mislabelled.tif", z, "EPSG:4326", from_origin(500000, 5200000, 30, 30))
    with pytest.raises(InputError, match=r"mislabelled\.tif: .*outside the globe"):
        read_heightfield(bad)


# -- GDAL rasters without georeferencing ---------------------------------------------------------------
def test_raster_without_crs_needs_spacing_or_sidecar(tmp_path: Path) -> None:
    z = np.arange(12, dtype=np.float32).reshape(3, 4)
    p = _tif(tmp_path / "plain.tif", z, None, None)
    with pytest.raises(InputError, match=r"plain\.tif: has no georeferencing and no spacing; .*--spacing"):
        read_heightfield(p)
    hf = read_heightfield(p, spacing_m=(2.0, 3.0))
    assert hf.crs is None and hf.spacing_m == (2.0, 3.0) and hf.bounds_m == (0.0, -9.0, 8.0, 0.0)
    (tmp_path / "plain.json").write_text(json.dumps({"spacing_m": 5}))
    assert read_heightfield(p).spacing_m == (5.0, 5.0)
    # a geotransform without CRS might be degrees: refused unless a CRS or a spacing is given
    q = _tif(tmp_path / "nocrs.tif", z, None, from_origin(7.0, 46.0, 0.001, 0.001))
    with pytest.raises(InputError, match=r"nocrs\.tif: has a geotransform but no CRS"):
        read_heightfield(q)
    (tmp_path / "nocrs.json").write_text(json.dumps({"crs": "EPSG:4326"}))
    assert "UTM zone 32N" in read_heightfield(q).crs


# -- PNG heightmaps ------------------------------------------------------------------------------------
@pytest.mark.parametrize("bits", [8, 16])
def test_png_heightmap_scale_offset_local_frame(tmp_path: Path, bits: int) -> None:
    rng = np.random.default_rng(bits)
    v = rng.integers(0, 2**bits, size=(30, 40)).astype(np.uint8 if bits == 8 else np.uint16)
    p = tmp_path / f"h{bits}.png"
    Image.fromarray(v).save(p)
    hf = read_heightfield(p, vertical_scale=0.5, vertical_offset=-10.0, spacing_m=(2.0, 3.0))
    assert hf.crs is None and hf.spacing_m == (2.0, 3.0)
    assert hf.bounds_m == (0.0, -90.0, 80.0, 0.0)  # origin (0, 0) at the north-west corner
    assert np.array_equal(hf.elevation_m, (v * 0.5 - 10.0).astype(np.float32))  # row 0 = image top = north
    assert hf.valid.all() and hf.fill_method == ""


def test_png_grey_rgb_accepted_colour_refused(tmp_path: Path) -> None:
    v = np.arange(48, dtype=np.uint8).reshape(6, 8)
    Image.fromarray(np.stack([v, v, v], -1)).save(tmp_path / "grey.png")
    assert np.array_equal(read_heightfield(tmp_path / "grey.png", spacing_m=1).elevation_m, v)
    Image.fromarray(np.stack([v, v + 1, v], -1)).save(tmp_path / "colour.png")
    with pytest.raises(InputError, match=r"colour\.png: is a colour RGB image; pass encoding .*--encoding"):
        read_heightfield(tmp_path / "colour.png", spacing_m=1)
    with pytest.raises(InputError, match=r"h\.png: is a greyscale image \(mode L\); encoding terrarium"):
        Image.fromarray(v).save(tmp_path / "h.png")
        read_heightfield(tmp_path / "h.png", spacing_m=1, encoding="terrarium")


def test_png_without_spacing_names_file_and_fix(tmp_path: Path) -> None:
    Image.fromarray(np.zeros((4, 4), np.uint8)).save(tmp_path / "nospacing.png")
    with pytest.raises(InputError) as err:
        read_heightfield(tmp_path / "nospacing.png")
    msg = str(err.value)
    assert msg.startswith(str(tmp_path / "nospacing.png") + ": ") and "--spacing" in msg and "sidecar" in msg


# -- RGB-encoded tiles ---------------------------------------------------------------------------------
def _spec_encode(h: np.ndarray, encoding: str) -> np.ndarray:
    """The encodings written from their definitions, independently of terralod."""
    if encoding == "terrain-rgb":
        code = np.round((h + 10000.0) * 10.0).astype(np.int64)  # h = -10000 + code * 0.1
    else:
        code = np.round((h + 32768.0) * 256.0).astype(np.int64)  # h = R*256 + G + B/256 - 32768
    return np.stack([code // 65536, (code // 256) % 256, code % 256], -1).astype(np.uint8)


@given(
    h=arrays(np.float64, st.tuples(st.integers(2, 12), st.integers(2, 12)), elements=st.floats(-9999, 9000)),
    fmt=st.sampled_from(["png", "webp"]),
    encoding=st.sampled_from(["terrain-rgb", "terrarium"]),
)
@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
def test_encoded_tiles_round_trip(tmp_path_factory, h: np.ndarray, fmt: str, encoding: str) -> None:
    rgb = _spec_encode(h, encoding)
    ours = encode_terrain_rgb(h) if encoding == "terrain-rgb" else encode_terrarium(h)
    assert np.array_equal(ours, rgb)
    p = tmp_path_factory.mktemp("enc") / f"t.{fmt}"
    Image.fromarray(rgb).save(p, **({"lossless": True} if fmt == "webp" else {}))
    hf = read_heightfield(p, encoding=encoding, spacing_m=10.0)
    quantum = 0.1 if encoding == "terrain-rgb" else 1.0 / 256.0
    # quantisation error at most half a step, plus float32 storage of up to ~10 km
    assert np.abs(hf.elevation_m - h).max() <= quantum / 2 + 1e-3
    assert hf.shape == h.shape and hf.valid.all()


def test_encoded_tile_address_georeferences_and_reprojects(tmp_path: Path) -> None:
    z, x, y = 12, 2133, 1445  # near 7.5 E, 46.5 N
    size = 40075016.686 / 2**z
    px = np.zeros((256, 256))
    px[100, 150] = 1000.0  # a peak at a known pixel
    Image.fromarray(encode_terrarium(px)).save(tmp_path / "tile.webp", lossless=True)
    hf = read_heightfield(tmp_path / "tile.webp", encoding="terrarium", tile=(z, x, y))
    assert "UTM zone 32N" in hf.crs and any("tile 12/2133/1445" in n for n in hf.notes)
    mx = -20037508.343 + (x + 150.5 / 256) * size
    my = 20037508.343 - (y + 100.5 / 256) * size
    lon, lat = math.degrees(mx / WEB_MERCATOR_R_M), math.degrees(math.atan(math.sinh(my / WEB_MERCATOR_R_M)))
    ground = size / 256 * math.cos(math.radians(lat))
    assert abs(hf.spacing_m[0] - ground) / ground < 0.01
    r, c = np.unravel_index(np.argmax(hf.elevation_m), hf.shape)
    plon, plat = _lonlat(hf, np.array([r]), np.array([c]))
    assert _haversine_m(lon, lat, float(plon[0]), float(plat[0])) < 1.5 * ground
    with pytest.raises(InputError, match=r"tile\.webp: tile z/x/y = 2/5/0 is not a valid XYZ tile"):
        read_heightfield(tmp_path / "tile.webp", encoding="terrarium", tile=(2, 5, 0))


# -- arrays and sidecars -------------------------------------------------------------------------------
def test_npy_with_flat_sidecar(tmp_path: Path) -> None:
    z = np.arange(20 * 30, dtype=np.int16).reshape(20, 30)
    z[0, 0] = -1
    np.save(tmp_path / "a.npy", z)
    (tmp_path / "a.json").write_text(json.dumps({"spacing_m": [5, 6], "vertical_scale": 2.0, "nodata": -1}))
    hf = read_heightfield(tmp_path / "a.npy")
    assert hf.spacing_m == (5.0, 6.0) and hf.crs is None
    assert not hf.valid[0, 0] and hf.valid.sum() == z.size - 1
    assert np.array_equal(hf.elevation_m[hf.valid], (z * 2.0)[hf.valid])
    # explicit arguments override the sidecar
    hf = read_heightfield(tmp_path / "a.npy", spacing_m=1.0, vertical_scale=1.0, vertical_offset=3.0)
    assert hf.spacing_m == (1.0, 1.0) and hf.elevation_m[1, 1] == z[1, 1] + 3.0


@pytest.mark.parametrize(
    "side",
    [
        {"crs": "EPSG:32633", "transform": [400000, 10, 0, 5000000, 0, -10]},
        {"crs": "EPSG:32633", "transform": [400000, 5000000], "spacing_m": 10},
        {"crs": "EPSG:32633", "origin_m": [400000, 5000000], "spacing_m": [10, 10]},
        {"horizontal": {"crs": "EPSG:32633 (WGS 84 / UTM zone 33N)", "bounds": [400000, 4999800, 400300, 5000000]}},
    ],
)  # fmt: skip
def test_npz_georeferenced_by_sidecar(tmp_path: Path, side: dict) -> None:
    z = np.random.default_rng(0).uniform(0, 50, (20, 30)).astype(np.float32)
    np.savez(tmp_path / "b.npz", other=np.zeros(3), elevation=z)
    (tmp_path / "b.json").write_text(json.dumps(side))
    hf = read_heightfield(tmp_path / "b.npz")
    assert hf.spacing_m == (10.0, 10.0) and hf.bounds_m == (400000.0, 4999800.0, 400300.0, 5000000.0)
    assert "UTM zone 33N" in hf.crs and np.array_equal(hf.elevation_m, z)
    hf = read_heightfield(tmp_path / "b.npz", spacing_m=2.0)
    if "spacing_m" in side:  # an origin takes its spacing from the sidecar or, overriding it, the argument
        assert hf.spacing_m == (2.0, 2.0) and hf.bounds_m[::3] == (400000.0, 5000000.0)
    else:  # a full transform or bounds georeference the grid: the spacing argument is ignored, with a note
        assert hf.spacing_m == (10.0, 10.0) and any("spacing 2 m ignored" in n for n in hf.notes)


def test_origin_with_metre_spacing_in_degrees_is_refused(tmp_path: Path) -> None:
    np.save(tmp_path / "g.npy", np.zeros((4, 4)))
    (tmp_path / "g.json").write_text(json.dumps({"crs": "EPSG:4326", "origin_m": [7, 46], "spacing_m": 30}))
    with pytest.raises(InputError, match=r"g\.npy: origin_m with spacing_m \(metres\) cannot place a grid"):
        read_heightfield(tmp_path / "g.npy")


def test_npz_picks_elevation_or_first_grid_and_own_transform(tmp_path: Path) -> None:
    base = np.full((6, 5), 1500.0, np.float32)
    np.savez(tmp_path / "ts.npz", dates=np.array(["2000-01-01"]), base=base, delta=np.zeros((2, 6, 5)),
             transform=np.array([561195.0, 10, 0, 5119475.0, 0, -10]), crs=np.array("EPSG:26910"))  # fmt: skip
    hf = read_heightfield(tmp_path / "ts.npz")
    assert hf.spacing_m == (10.0, 10.0) and hf.bounds_m[0] == 561195.0 and "UTM zone 10N" in hf.crs
    assert np.all(hf.elevation_m == 1500.0) and any("array 'base'" in n for n in hf.notes)


def test_nested_sidecar_layout(tmp_path: Path) -> None:
    v = np.array([[0, 10], [20, 30]], np.uint16)
    Image.fromarray(v).save(tmp_path / "n.png")
    side = {"nodata": 0, "vertical": {"scale_m_per_unit": 0.1, "offset_m": 5.0},
            "horizontal": {"spacing_m": [160.0, 160.0], "crs": None, "bounds": None}}  # fmt: skip
    (tmp_path / "n.json").write_text(json.dumps(side))
    hf = read_heightfield(tmp_path / "n.png")
    assert hf.spacing_m == (160.0, 160.0) and hf.crs is None and not hf.valid[0, 0]
    assert np.allclose(hf.elevation_m[hf.valid], [6.0, 7.0, 8.0])
    assert read_sidecar(tmp_path / "n.png")["vertical_scale"] == 0.1
    tile_side = {"horizontal": {"tile": {"z": 11, "x": 385, "y": 803, "scheme": "XYZ"}},
                 "encoding": {"name": "Terrarium"}}  # fmt: skip
    (tmp_path / "t.json").write_text(json.dumps(tile_side))
    s = read_sidecar(tmp_path / "t.png")
    assert s["tile"] == (11, 385, 803) and s["encoding"] == "terrarium"


# -- bad input -----------------------------------------------------------------------------------------
def test_missing_file_and_directory(tmp_path: Path) -> None:
    with pytest.raises(InputNotFoundError, match=r"nope\.tif: file not found"):
        read_heightfield(tmp_path / "nope.tif")
    with pytest.raises(InputError, match="is a directory"):
        read_heightfield(tmp_path)


@pytest.mark.parametrize(
    "name, content, match",
    [
        ("x.tif", b"\x00garbage" * 100, r"x\.tif: not a raster GDAL can read"),
        ("y.png", b"not an image", r"y\.png: not a PNG/WebP image"),
        ("y.webp", b"RIFF\x10\x00\x00\x00WEBPVP8 garbage", r"y\.webp: not a PNG/WebP image"),
        ("z.npy", b"\x93NUMPY garbage", r"z\.npy: not a NumPy"),
        ("z.npz", b"PK\x03\x04 garbage", r"z\.npz: not a NumPy"),
    ],
)
def test_undecodable_files(tmp_path: Path, name: str, content: bytes, match: str) -> None:
    (tmp_path / name).write_bytes(content)
    with pytest.raises(InputError, match=match):
        read_heightfield(tmp_path / name, spacing_m=1.0)


def test_truncated_png_and_bad_arrays(tmp_path: Path) -> None:
    Image.fromarray(np.random.default_rng(0).integers(0, 255, (64, 64)).astype(np.uint8)).save(
        tmp_path / "c.png"
    )
    (tmp_path / "c.png").write_bytes((tmp_path / "c.png").read_bytes()[:200])
    with pytest.raises(InputError, match=r"c\.png: not a PNG/WebP image Pillow can decode"):
        read_heightfield(tmp_path / "c.png", spacing_m=1.0)
    np.save(tmp_path / "cube.npy", np.zeros((2, 3, 4)))
    with pytest.raises(InputError, match=r"cube\.npy: expected a 2-D numeric array"):
        read_heightfield(tmp_path / "cube.npy", spacing_m=1.0)
    np.save(tmp_path / "obj.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(InputError, match=r"obj\.npy: expected a 2-D numeric array"):
        read_heightfield(tmp_path / "obj.npy", spacing_m=1.0)
    np.savez(tmp_path / "none.npz", dates=np.array(["2000"]))
    with pytest.raises(InputError, match=r"none\.npz: holds no 2-D numeric array"):
        read_heightfield(tmp_path / "none.npz", spacing_m=1.0)


def test_no_valid_samples_and_tiny(tmp_path: Path) -> None:
    np.save(tmp_path / "nan.npy", np.full((10, 10), np.nan))
    with pytest.raises(InputError, match=r"nan\.npy: every sample is NaN"):
        read_heightfield(tmp_path / "nan.npy", spacing_m=1.0)
    np.save(tmp_path / "tiny.npy", np.ones((1, 5)))
    with pytest.raises(InputError, match=r"tiny\.npy: raster is 5x1 samples; at least 2x2"):
        read_heightfield(tmp_path / "tiny.npy", spacing_m=1.0)
    z = np.full((8, 8), -32768, np.int16)
    p = _tif(tmp_path / "void.tif", z, "EPSG:32610", from_origin(0, 80, 10, 10), -32768)
    with pytest.raises(InputError, match=r"void\.tif: band 1 has no valid samples"):
        read_heightfield(p)
    Image.fromarray(np.zeros((1, 1), np.uint8)).save(tmp_path / "one.png")
    with pytest.raises(InputError, match=r"one\.png: raster is 1x1 samples"):
        read_heightfield(tmp_path / "one.png", spacing_m=1.0)


def test_absurd_dimensions_fail_before_reading_pixels(tmp_path: Path) -> None:
    big = r"raster is 1000000x1000000 samples, beyond the supported"
    (tmp_path / "huge.vrt").write_text(
        '<VRTDataset rasterXSize="1000000" rasterYSize="1000000">'
        '<VRTRasterBand dataType="Float32" band="1"/></VRTDataset>'
    )
    with pytest.raises(InputError, match=r"huge\.vrt: " + big):
        read_heightfield(tmp_path / "huge.vrt")
    with pytest.raises(InputError, match=r"huge\.png: " + big):
        read_heightfield(_png_header_only(tmp_path / "huge.png", 1_000_000, 1_000_000), spacing_m=1.0)
    with open(tmp_path / "huge.npy", "wb") as f:
        np.lib.format.write_array_header_1_0(
            f, {"descr": "<f4", "fortran_order": False, "shape": (1_000_000, 1_000_000)}
        )
    with pytest.raises(InputError, match=r"huge\.npy: " + big):
        read_heightfield(tmp_path / "huge.npy", spacing_m=1.0)


def test_bad_sidecars_and_options_name_the_file(tmp_path: Path) -> None:
    Image.fromarray(np.zeros((4, 4), np.uint8)).save(tmp_path / "s.png")
    (tmp_path / "s.json").write_text("{not json")
    with pytest.raises(InputError, match=r"s\.json: sidecar is not valid JSON"):
        read_heightfield(tmp_path / "s.png")
    (tmp_path / "s.json").write_text(json.dumps({"encoding": {"name": "LERC"}}))
    with pytest.raises(InputError, match=r"s\.json: unknown encoding 'LERC'"):
        read_heightfield(tmp_path / "s.png")
    (tmp_path / "s.json").write_text(json.dumps({"crs": "not a crs", "transform": [0, 1, 0, 4, 0, -1]}))
    with pytest.raises(InputError, match=r"s\.json: crs 'not a crs' is not understood"):
        read_heightfield(tmp_path / "s.png")
    (tmp_path / "s.json").unlink()
    with pytest.raises(InputError, match=r"s\.png: spacing must be positive"):
        read_heightfield(tmp_path / "s.png", spacing_m=-1.0)
    with pytest.raises(InputError, match=r"s\.png: unknown encoding 'rgb'"):
        read_heightfield(tmp_path / "s.png", encoding="rgb")


_MAGIC = {".tif": b"II*\x00", ".png": b"\x89PNG\r\n\x1a\n", ".webp": b"RIFF\x00\x01\x00\x00WEBPVP8L",
          ".npy": b"\x93NUMPY\x01\x00", ".npz": b"PK\x03\x04"}  # fmt: skip


@given(suffix=st.sampled_from(sorted(_MAGIC)), magic=st.booleans(), body=st.binary(max_size=200))
@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
def test_fuzzed_files_give_terralod_errors_only(
    tmp_path_factory, suffix: str, magic: bool, body: bytes
) -> None:
    p = tmp_path_factory.mktemp("fuzz") / f"junk{suffix}"
    p.write_bytes((_MAGIC[suffix] if magic else b"") + body)
    try:
        read_heightfield(p, spacing_m=1.0)
    except TerralodError as exc:
        assert str(exc).startswith(str(p) + ": ")


_JSON = st.recursive(
    st.none() | st.booleans() | st.integers(-10, 10**6) | st.floats(allow_nan=True) | st.text(max_size=12),
    lambda inner: (
        st.lists(inner, max_size=7) | st.dictionaries(st.sampled_from(["z", "x", "y", "name"]), inner)
    ),
    max_leaves=10,
)
_SIDECAR_KEYS = ["spacing_m", "vertical_scale", "vertical_offset", "encoding", "tile", "nodata", "crs",
                 "transform", "origin_m", "bounds", "vertical", "horizontal"]  # fmt: skip


@given(side=st.dictionaries(st.sampled_from(_SIDECAR_KEYS), _JSON, max_size=5))
@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
def test_fuzzed_sidecars_give_terralod_errors_only(tmp_path_factory, side: dict) -> None:
    d = tmp_path_factory.mktemp("side")
    np.save(d / "a.npy", np.arange(16.0).reshape(4, 4))
    (d / "a.json").write_text(json.dumps(side))
    try:
        hf = read_heightfield(d / "a.npy", spacing_m=1.0)
    except TerralodError as exc:
        assert str(exc).startswith((str(d / "a.npy") + ": ", str(d / "a.json") + ": "))
    else:
        assert hf.transform.a > 0 and hf.transform.e < 0 and np.isfinite(hf.elevation_m).all()


# -- real data (../shared/data) ------------------------------------------------------------------------
def test_real_puget_sound_png_via_sidecar(shared_data: Path) -> None:
    hf = read_heightfield(shared_data / "dem/puget_sound_1k_u16.png")
    assert hf.shape == (1025, 1025) and hf.spacing_m == (160.0, 160.0) and hf.crs is None
    lo, hi = hf.valid_range_m()
    assert lo == 0.0 and abs(hi - 4379.8) < 0.01


def test_real_srtm3_geographic_to_utm31n(shared_data: Path) -> None:
    hf = read_heightfield(shared_data / "dem/srtm3_N42E001.tif")
    assert "UTM zone 31N" in hf.crs
    assert any("to EPSG:32631 (UTM 31N)" in n and "92." in n for n in hf.notes)  # dy ~92 m on the ground
    dx, dy = hf.spacing_m
    ground_dx = _haversine_m(1.5, 42.5, 1.5 + 3 / 3600, 42.5)
    assert dx == dy and abs(dx - ground_dx) / ground_dx < 0.01 and 68.0 < dx < 69.0
    lo, hi = hf.valid_range_m()
    assert 340 < lo < 360 and 3000 < hi <= 3100  # Pyrenees, 349..3100 m in the source
    assert np.isfinite(hf.elevation_m).all() and 0.0 < hf.nodata_fraction < 0.1


def test_real_nan_nodata_is_masked_and_filled(shared_data: Path) -> None:
    hf = read_heightfield(shared_data / "dem/srtm1_crop256_coastal_flat_nodata.tif")
    assert np.isfinite(hf.elevation_m).all()
    assert hf.nodata_fraction > 5093 / 65536 * 0.9  # the sea / lake NaNs are in the mask
    lo, hi = hf.valid_range_m()
    assert 1.0 <= lo and hi <= 26.0
    filled = hf.elevation_m[~hf.valid]
    assert filled.min() >= 1.0 - 1e-3 and filled.max() <= 26.0 + 1e-3  # filled within the data's range


def test_real_kilauea_nodata(shared_data: Path) -> None:
    p = shared_data / "dem/kilauea_hawaii_30m_utm5.tif"
    with rasterio.open(p) as ds:
        raw = ds.read(1)
    hf = read_heightfield(p)
    assert hf.spacing_m == (30.0, 30.0) and not hf.notes  # projected metres: used as they are
    assert np.array_equal(~hf.valid, raw == -32768) and (~hf.valid).any()
    assert hf.valid_range_m() == (0.0, 1505.0)


@pytest.mark.parametrize(
    "name, spacing",
    [("tiles/terrarium_grand_canyon_z11_385_803.png", 61.76),
     ("tiles/mapterhorn_terrarium_saxon_switzerland_z10_552_343_512px.webp", 48.26)],
)  # fmt: skip
def test_real_terrarium_tiles(shared_data: Path, name: str, spacing: float) -> None:
    p = shared_data / name
    side = json.loads(p.with_suffix(".json").read_text())
    lo_s, hi_s = side["elevation_range_m"]
    raw = decode_terrarium(np.asarray(Image.open(p).convert("RGB")))
    assert abs(raw.min() - lo_s) < 0.01 and abs(raw.max() - hi_s) < 0.01  # the decoding is exact
    hf = read_heightfield(p)  # encoding and tile come from the sidecar
    assert any("terrarium" in n for n in hf.notes) and any("from EPSG:3857" in n for n in hf.notes)
    assert abs(hf.spacing_m[0] - spacing) / spacing < 0.01
    lo, hi = hf.valid_range_m()  # bilinear reprojection may shave a little off the extremes
    assert lo_s - 0.01 <= lo <= lo_s + 2.0 and hi_s - 2.0 <= hi <= hi_s + 0.01


def test_real_st_helens_npz(shared_data: Path) -> None:
    hf = read_heightfield(shared_data / "change/st_helens_crater_timeseries_2000-2007_10m.npz")
    assert hf.shape == (442, 303) and hf.spacing_m == (10.0, 10.0) and "UTM zone 10N" in hf.crs
    assert hf.bounds_m[0] == pytest.approx(561194.9985) and hf.bounds_m[3] == pytest.approx(5119474.9888)


def test_sample_heightfield() -> None:
    hf = sample_heightfield()
    assert hf.source == "matplotlib sample_data/jacksboro_fault_dem.npz"
    # centre 84.25 W lies in UTM zone 16 (90-84 W), not 17
    assert "UTM zone 16N" in hf.crs and any("EPSG:32616 (UTM 16N)" in n for n in hf.notes)
    dx, dy = hf.spacing_m
    ground_dx = _haversine_m(-84.25, 36.59, -84.25 + 3 / 3600, 36.59)  # ~74 m (dy ~92 m)
    assert dx == dy and abs(dx - ground_dx) / ground_dx < 0.01
    lo, hi = hf.valid_range_m()
    assert 236 <= lo < 250 and 1060 < hi <= 1076  # source 236..1076 m, bilinear smooths the extremes
    assert 0.0 < hf.nodata_fraction < 0.1  # only the corners outside the rotated footprint
