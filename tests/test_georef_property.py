"""Every sample where it is, for many CRSs: the world position terralod gives each input sample agrees with
pyproj's own transform of the input coordinates (within 0.01 m on the ground), whatever the CRS and unit,
and ``--crs`` assigns or overrides a CRS.

CRSs: UTM north and south, state planes in international and US survey feet, Lambert conformal, polar
stereographic north and south, a compound CRS, and the two that are reprojected (EPSG:4326, EPSG:3857):
for those the store's grid is not the input's, so each input sample must lie inside the store's footprint
where pyproj puts it and its height must be reproduced by the resampled grid's neighbourhood.
"""

from __future__ import annotations

import subprocess
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

pyproj = pytest.importorskip("pyproj")

from tests.test_georef import cloud, wkt_of, write_las, write_tif  # noqa: E402

from conftest import terralod_cli  # noqa: E402

#: (CRS, pixel size in the CRS's unit): projected CRSs keep the input's grid.
PROJECTED = [
    ("EPSG:32633", 30.0),  # UTM 33N, metres
    ("EPSG:32733", 30.0),  # UTM 33S
    ("EPSG:2992", 100.0),  # Oregon Lambert, international feet
    ("EPSG:2227", 100.0),  # California zone 3, US survey feet
    ("EPSG:2154", 30.0),  # Lambert-93 (France)
    ("EPSG:3031", 30.0),  # Antarctic polar stereographic
    ("EPSG:3413", 30.0),  # NSIDC sea-ice polar stereographic north
    ("EPSG:32610+5703", 30.0),  # UTM 10N + NAVD88 height: a compound CRS
]
#: CRSs a build reprojects to the UTM zone of the raster's centre.
REPROJECTED = [("EPSG:4326", 0.0005), ("EPSG:3857", 40.0)]

_GEOD = pyproj.Geod(ellps="WGS84")


def _inside_area(code: str, u: float, v: float) -> tuple[float, float]:
    """A point of the CRS's area of use (fractions u, v of its lon/lat box, kept off its edges), in the
    CRS's own coordinates."""
    crs = pyproj.CRS.from_user_input(code)
    a = crs.area_of_use or crs.sub_crs_list[0].area_of_use  # a compound CRS: its horizontal part's
    lon = a.west + (0.3 + 0.4 * u) * (a.east - a.west)
    lat = a.south + (0.3 + 0.4 * v) * (a.north - a.south)
    lat = max(min(lat, 84.0), -80.0) if code not in ("EPSG:3031", "EPSG:3413") else lat
    t = pyproj.Transformer.from_crs(
        "EPSG:4326", crs.sub_crs_list[0] if crs.is_compound else crs, always_xy=True
    )
    x, y = t.transform(lon, lat)
    return float(x), float(y)


def _ground_distance_m(lon1, lat1, lon2, lat2) -> np.ndarray:
    _, _, d = _GEOD.inv(lon1, lat1, lon2, lat2)
    return np.abs(np.asarray(d))


def _to_lonlat(crs, x, y) -> tuple[np.ndarray, np.ndarray]:
    t = pyproj.Transformer.from_crs(pyproj.CRS.from_user_input(crs), "EPSG:4326", always_xy=True)
    lon, lat = t.transform(np.asarray(x, float), np.asarray(y, float))
    return np.asarray(lon), np.asarray(lat)


def _raster(tmp: Path, code: str, px: float, u: float, v: float, name: str = "dem.tif", crs=None) -> tuple:
    from rasterio.transform import from_origin

    x0, y0 = _inside_area(code, u, v)
    rows, cols = 20, 24
    z = (200.0 + np.add.outer(np.arange(rows) * 3.0, np.sin(np.arange(cols)) * 5.0)).astype("float32")
    t = from_origin(x0, y0, px, px)
    path = write_tif(tmp / name, crs=code if crs is None else crs, transform=t, z=z)
    r, c = np.mgrid[0:rows, 0:cols]
    xs, ys = t * (c.ravel() + 0.5, r.ravel() + 0.5)  # sample centres (pixel-is-area)
    return path, np.asarray(xs), np.asarray(ys), z.ravel()


@settings(max_examples=24, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(i=st.integers(0, len(PROJECTED) - 1), u=st.floats(0, 1), v=st.floats(0, 1))
def test_projected_samples_land_where_pyproj_puts_them(tmp_path: Path, i: int, u: float, v: float) -> None:
    from terralod.io.reader import read_heightfield

    code, px = PROJECTED[i]
    path, xs, ys, _ = _raster(tmp_path, code, px, u, v)
    hf = read_heightfield(path)
    rows, cols = hf.elevation_m.shape
    r, c = np.mgrid[0:rows, 0:cols]
    t = hf.transform
    hx, hy = t * (c.ravel() + 0.5, r.ravel() + 0.5)
    lon_t, lat_t = _to_lonlat(hf.crs, hx, hy)
    lon_p, lat_p = _to_lonlat(code, xs, ys)
    d = _ground_distance_m(lon_t, lat_t, lon_p, lat_p)
    assert d.max() <= 0.01, (code, float(d.max()))


@settings(max_examples=6, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(i=st.integers(0, len(REPROJECTED) - 1), u=st.floats(0, 1), v=st.floats(0, 1))
def test_reprojected_samples_lie_in_the_store_grid(tmp_path: Path, i: int, u: float, v: float) -> None:
    """A geographic or Mercator input: every sample, placed by pyproj in the grid's CRS, lies inside the
    resampled grid (how far the grid's heights are from the samples is the store's measured error, checked
    against the original samples in tests/test_honest_errors.py)."""
    from terralod.io.reader import read_heightfield

    code, px = REPROJECTED[i]
    path, xs, ys, _ = _raster(tmp_path, code, px, u, v)
    hf = read_heightfield(path)
    to_grid = pyproj.Transformer.from_crs(pyproj.CRS.from_user_input(code), pyproj.CRS.from_user_input(hf.crs),
                                          always_xy=True)  # fmt: skip
    gx, gy = to_grid.transform(xs, ys)
    col, row = ~hf.transform * (np.asarray(gx), np.asarray(gy))
    rows, cols = hf.elevation_m.shape
    assert (col >= 0).all() and (col <= cols).all() and (row >= 0).all() and (row <= rows).all()


@settings(max_examples=10, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(code=st.sampled_from(["EPSG:2992", "EPSG:2227", "EPSG:32610", "EPSG:3031"]), u=st.floats(0, 1),
       v=st.floats(0, 1))  # fmt: skip
def test_las_points_land_where_pyproj_puts_them(tmp_path: Path, code: str, u: float, v: float) -> None:
    from terralod.tin.pointcloud import read_las

    x0, y0 = _inside_area(code, u, v)
    xyz = cloud(x0, y0, 300.0, n=200)
    path = write_las(tmp_path / "c.las", xyz, wkt=wkt_of(code))
    pc = read_las(path, ground_only=False)
    lon_t, lat_t = _to_lonlat(pc.crs, pc.xyz_m[:, 0], pc.xyz_m[:, 1])
    # points are rounded to the file's 0.001 unit scale: compare with the coordinates as stored
    import laspy

    las = laspy.read(str(path))
    lon_p, lat_p = _to_lonlat(code, np.asarray(las.x), np.asarray(las.y))
    d = _ground_distance_m(lon_t, lat_t, lon_p, lat_p)
    assert d.max() <= 0.01, (code, float(d.max()))


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    """``terralod ARGS`` in this process (tests/conftest.py ``terralod_cli``)."""
    return terralod_cli(*args)


def test_crs_option_assigns_a_crs_to_a_file_without(tmp_path: Path) -> None:
    from terralod.io.reader import read_heightfield

    path, xs, ys, _ = _raster(tmp_path, "EPSG:2992", 100.0, 0.5, 0.5, crs=None)
    bare, *_ = _raster(tmp_path, "EPSG:2992", 100.0, 0.5, 0.5, name="bare.tif", crs=None)
    import rasterio

    with rasterio.open(path) as ds:  # the same grid, its CRS stripped
        z, t = ds.read(1), ds.transform
    write_tif(bare, crs=None, transform=t, z=z)
    hf = read_heightfield(bare, crs="EPSG:2992")
    ref = read_heightfield(path)
    assert tuple(hf.transform) == tuple(ref.transform)
    corners = ([0.0, 24.0 * hf.spacing_m[0]], [0.0, -20.0 * hf.spacing_m[1]])
    x = np.array(corners[0]) + hf.transform.c
    y = np.array(corners[1]) + hf.transform.f
    d = _ground_distance_m(*_to_lonlat(hf.crs, x, y), *_to_lonlat(ref.crs, x, y))
    assert d.max() <= 0.01, d  # the same place, whether the CRS came from the file or from --crs
    assert np.array_equal(hf.elevation_m, ref.elevation_m)
    assert any("--crs" in n and "has none" in n for n in hf.notes), hf.notes
    r = _cli("info", str(bare), "--crs", "EPSG:2992")
    assert r.returncode == 0, r.stderr
    assert "2992" in r.stdout or "Oregon" in r.stdout, r.stdout


def test_crs_option_overrides_and_says_so(tmp_path: Path) -> None:
    from terralod.io.reader import read_heightfield

    path, *_ = _raster(tmp_path, "EPSG:32633", 30.0, 0.5, 0.5)
    hf = read_heightfield(path, crs="EPSG:32634")
    assert "32634" in (pyproj.CRS.from_user_input(hf.crs).to_string() + str(pyproj.CRS.from_user_input(hf.crs)
                                                                            .to_epsg()))  # fmt: skip
    assert any("overriding" in n for n in hf.notes), hf.notes


def test_a_bad_crs_option_is_one_line(tmp_path: Path) -> None:
    path, *_ = _raster(tmp_path, "EPSG:32633", 30.0, 0.5, 0.5)
    r = _cli("info", str(path), "--crs", "EPSG:999999")
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "EPSG:999999" in lines[0] and str(path) in lines[0], r.stderr


def test_crs_option_on_a_point_cloud(tmp_path: Path) -> None:
    from terralod.tin.pointcloud import read_las

    x0, y0 = _inside_area("EPSG:2992", 0.5, 0.5)
    path = write_las(tmp_path / "bare.las", cloud(x0, y0, 300.0, n=100))  # no CRS records
    pc = read_las(path, ground_only=False, crs="EPSG:2992")
    lon, lat = _to_lonlat(pc.crs, pc.xyz_m[:, 0], pc.xyz_m[:, 1])
    a = pyproj.CRS.from_user_input("EPSG:2992").area_of_use
    assert (
        (a.west <= lon).all() and (lon <= a.east).all() and (a.south <= lat).all() and (lat <= a.north).all()
    )
