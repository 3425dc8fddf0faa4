"""Every sample where it is: a cloud in feet lands where the file says (Autzen Stadium, Eugene), ``info``
names CRSs instead of printing WKT, and bad georeferencing gets one line naming the file and the problem
(exit 2): rotated or sheared grids, CRSs PROJ cannot place, LAS CRS records that disagree, coordinates far
outside the CRS's area of use."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
import pytest

from terralod.errors import InputError

from conftest import terralod_cli

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
AUTZEN = SHARED / "lidar" / "autzen_trim.laz"
needs_autzen = pytest.mark.skipif(
    not AUTZEN.exists(), reason="../shared/data/lidar/autzen_trim.laz is absent"
)
FT = 0.3048
US_FT = 1200.0 / 3937.0


def terralod(*args: str) -> subprocess.CompletedProcess[str]:
    """``terralod ARGS`` in this process (tests/conftest.py ``terralod_cli``)."""
    return terralod_cli(*args)


def one_line_error(r: subprocess.CompletedProcess[str], path: Path, *words: str) -> str:
    """The single stderr line of a refused command (exit 2), which names ``path`` and every word."""
    assert r.returncode == 2, r.stdout + r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1, r.stderr
    line = lines[0]
    assert line.startswith("terralod: ") and str(path) in line, line
    for w in words:
        assert w in line, line
    return line


def write_tif(path: Path, *, crs, transform, z: np.ndarray | None = None) -> Path:
    import rasterio

    z = np.add.outer(np.arange(20.0), np.arange(24.0)).astype("float32") if z is None else z
    with rasterio.open(path, "w", driver="GTiff", width=z.shape[1], height=z.shape[0], count=1,
                       dtype="float32", crs=crs, transform=transform) as ds:  # fmt: skip
        ds.write(z, 1)
    return path


def write_las(
    path: Path, xyz: np.ndarray, *, wkt: str | None = None, geokeys_epsg: int | None = None
) -> Path:
    """A LAS 1.2 file (point format 3) with a WKT record and/or GeoTIFF keys (ProjectedCSTypeGeoKey)."""
    import laspy
    from laspy.vlrs.geotiff import GeoKeyEntryStruct
    from laspy.vlrs.known import GeoKeyDirectoryVlr, WktCoordinateSystemVlr

    h = laspy.LasHeader(version="1.2", point_format=3)
    h.offsets = xyz.min(axis=0)
    h.scales = np.array([0.001, 0.001, 0.001])
    if wkt is not None:
        h.vlrs.append(WktCoordinateSystemVlr(wkt))
    if geokeys_epsg is not None:
        d = GeoKeyDirectoryVlr()
        d.geo_keys_header.number_of_keys = 2
        d.geo_keys = [GeoKeyEntryStruct(1024, 0, 1, 1), GeoKeyEntryStruct(3072, 0, 1, geokeys_epsg)]
        h.vlrs.append(d)
    las = laspy.LasData(h)
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    las.write(str(path))
    return path


def cloud(x0: float, y0: float, span: float, n: int = 400, seed: int = 0, z0: float = 100.0) -> np.ndarray:
    """Random points over a ``span`` square from (x0, y0), a gentle surface around z0 (file units)."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0.0, span, (n, 2))
    z = z0 + 0.05 * xy[:, 0] + 3.0 * np.sin(xy[:, 1] / span * 6.0)
    corners = np.array([[0.0, 0.0], [span, 0.0], [0.0, span], [span, span]])
    xy[:4] = corners  # the corners are points: the footprint is the square
    return np.c_[xy + np.array([x0, y0]), z[: len(xy)]]


def wkt_of(code: str) -> str:
    from rasterio.crs import CRS

    return CRS.from_user_input(code).to_wkt()


# -- 1. a cloud in feet lands where it is -----------------------------------------------------------------


@needs_autzen
def test_autzen_store_lies_on_autzen_stadium(tmp_path: Path) -> None:
    """NAD83(HARN) Oregon Lambert in international feet: the store's metres and its CRS agree, so its
    lon/lat bounds hold the stadium (about 123.07 W, 44.05 N; the feet-as-CRS-units bug put it at
    124.64 W, 42.38 N)."""
    out = tmp_path / "a.terra"
    r = terralod("build", str(AUTZEN), "-o", str(out))
    assert r.returncode == 0, r.stderr
    r = terralod("info", str(out), "--json")
    assert r.returncode == 0, r.stderr
    d = json.loads(r.stdout)
    w, s, e, n = d["bounds_lonlat"]
    assert w < -123.07 < e and s < 44.05 < n, d["bounds_lonlat"]
    assert "unit metre" in d["crs_name"] and "were foot" in d["crs_name"] and "PROJCS" not in d["crs_name"]
    text = terralod("info", str(out)).stdout
    assert "W -123.07" in text and "PROJCS" not in text and "PROJCRS" not in text


@needs_autzen
def test_autzen_info_names_the_crs_and_places_the_cloud() -> None:
    r = terralod("info", str(AUTZEN))
    assert r.returncode == 0, r.stderr
    crs_line = next(ln for ln in r.stdout.splitlines() if ln.strip().startswith("CRS"))
    assert "NAD_1983_HARN_Lambert_Conformal_Conic, unit foot" in crs_line and "[" not in crs_line
    assert "W -123.07" in r.stdout and "N 44.05" in r.stdout


def test_las_in_us_survey_feet_with_a_metre_vertical_axis(tmp_path: Path) -> None:
    """California zone 3 in US survey feet + NAVD88 height in metres: x/y scale by 1200/3937, z not at all,
    and the store's CRS places the points where pyproj places the file's coordinates."""
    from rasterio.warp import transform

    from terralod.tin.pointcloud import read_las

    xyz = cloud(6_000_000.0, 2_100_000.0, 1500.0)
    p = write_las(tmp_path / "ca.las", xyz, wkt=wkt_of("EPSG:2227+5703"))
    pc = read_las(p, ground_only=False)
    assert np.allclose(pc.xyz_m[:, 2], xyz[:, 2], atol=1e-3)  # heights already metres
    assert np.allclose(pc.xyz_m[:, :2], xyz[:, :2] * US_FT, atol=1e-3)
    lon_m, lat_m = transform(pc.crs, "EPSG:4326", pc.xyz_m[:4, 0].tolist(), pc.xyz_m[:4, 1].tolist())
    lon_f, lat_f = transform("EPSG:2227", "EPSG:4326", xyz[:4, 0].tolist(), xyz[:4, 1].tolist())
    # 1e-7 degrees is about a centimetre on the ground
    assert np.allclose(lon_m, lon_f, atol=1e-7) and np.allclose(lat_m, lat_f, atol=1e-7)
    from terralod.io.georef import crs_summary

    s = crs_summary(pc.crs)
    assert s.unit_m == 1.0 and s.vertical_name == "NAVD88 height" and s.vertical_unit_m == 1.0


def test_las_without_crs_is_a_local_frame_and_says_so(tmp_path: Path) -> None:
    p = write_las(tmp_path / "local.las", cloud(0.0, 0.0, 100.0))
    r = terralod("info", str(p))
    assert r.returncode == 0, r.stderr
    assert "CRS          none (local metric frame, not placed on the globe)" in r.stdout
    assert "lon/lat" not in r.stdout


# -- 3. info names CRSs ------------------------------------------------------------------------------------


def test_info_names_a_compound_crs_and_a_foot_crs(tmp_path: Path) -> None:
    """A DEM in UTM 10N + NAVD88 height: name, EPSG code and unit of both parts; a DEM in Oregon Lambert
    (ft): its name and unit, and what the store holds (metre axes)."""
    from affine import Affine

    dem = write_tif(
        tmp_path / "c.tif", crs="EPSG:32610+5703", transform=Affine(10, 0, 500000, 0, -10, 5000000)
    )
    r = terralod("info", str(dem))
    assert r.returncode == 0, r.stderr
    assert (
        "CRS          WGS 84 / UTM zone 10N (EPSG:32610), unit metre; vertical NAVD88 height (EPSG:5703), "
        "unit metre" in r.stdout
    ), r.stdout
    ft = write_tif(tmp_path / "f.tif", crs="EPSG:2994", transform=Affine(30, 0, 1_300_000, 0, -30, 500_000))
    out = tmp_path / "f.terra"
    assert terralod("build", str(ft), "-o", str(out), "--tile-size", "9").returncode == 0
    r = terralod("info", str(out))
    assert r.returncode == 0, r.stderr
    assert "CRS NAD83(HARN) / Oregon GIC Lambert (ft), unit metre (axes re-expressed in metres, were foot in " \
           "EPSG:2994)" in " ".join(r.stdout.split()), r.stdout  # fmt: skip
    assert "PROJCS" not in r.stdout and "PROJCRS" not in r.stdout


def test_foot_raster_store_corners_agree_with_pyproj(tmp_path: Path) -> None:
    """The store of a DEM in international feet: its lon/lat bounds are pyproj's of the DEM's corners."""
    import pyproj
    from affine import Affine

    from terralod.io.reader import read_heightfield

    t = Affine(30, 0, 1_300_000, 0, -30, 500_000)
    hf = read_heightfield(write_tif(tmp_path / "f.tif", crs="EPSG:2994", transform=t))
    w, s, e, n = hf.bounds_m
    to_ll = pyproj.Transformer.from_crs(pyproj.CRS.from_wkt(hf.crs), 4326, always_xy=True)
    ref = pyproj.Transformer.from_crs(2994, 4326, always_xy=True)
    for (xm, ym), (xf, yf) in zip(
        [(w, n), (e, s)], [(t.c, t.f), (t.c + 24 * 30, t.f - 20 * 30)], strict=True
    ):
        assert np.allclose(to_ll.transform(xm, ym), ref.transform(xf, yf), atol=1e-7)


# -- 4. bad georeferencing: one line, exit 2 ---------------------------------------------------------------


def test_rotated_raster_is_refused_in_one_line(tmp_path: Path) -> None:
    from affine import Affine

    p = write_tif(tmp_path / "rot.tif", crs="EPSG:32610", transform=Affine(10, 2, 500000, 1, -10, 5000000))
    one_line_error(terralod("info", str(p)), p, "rotated or sheared")
    one_line_error(terralod("build", str(p), "-o", str(tmp_path / "r.terra")), p, "rotated or sheared")
    assert not (tmp_path / "r.terra").exists()


def test_crs_proj_cannot_place_is_refused_in_one_line(tmp_path: Path) -> None:
    """An engineering (local) CRS: GDAL reads it, but there is no way to WGS 84 lon/lat."""
    from affine import Affine
    from rasterio.crs import CRS

    crs = CRS.from_wkt(
        'LOCAL_CS["mine site grid",UNIT["metre",1],AXIS["Easting",EAST],AXIS["Northing",NORTH]]'
    )
    p = write_tif(tmp_path / "eng.tif", crs=crs, transform=Affine(1, 0, 1000, 0, -1, 2000))
    one_line_error(terralod("info", str(p)), p, "cannot place", "mine site grid")


def test_unreadable_las_wkt_is_refused_in_one_line(tmp_path: Path) -> None:
    p = write_las(tmp_path / "bad.las", cloud(500000.0, 5000000.0, 100.0), wkt='PROJCS["broken",GEOGCS[')
    one_line_error(terralod("info", str(p)), p, "not one PROJ can use")
    one_line_error(terralod("build", str(p), "-o", str(tmp_path / "b.terra")), p, "not one PROJ can use")


def test_feet_in_a_metre_crs_are_refused_with_the_likely_cause(tmp_path: Path) -> None:
    """UTM 10N eastings/northings written in feet: ~1,100 km east of the zone; the line says they look
    like feet read as metres, for rasters and clouds alike."""
    from affine import Affine

    t = Affine(30, 0, 500000 / FT, 0, -30, 5000000 / FT)
    p = write_tif(tmp_path / "ft.tif", crs="EPSG:32610", transform=t)
    one_line_error(terralod("info", str(p)), p, "far outside the area of use", "look like international feet")
    q = write_las(tmp_path / "ft.las", cloud(500000 / FT, 5000000 / FT, 300.0), wkt=wkt_of("EPSG:32610"))
    one_line_error(terralod("build", str(q), "-o", str(tmp_path / "q.terra")), q, "far outside the area of use",
                   "look like international feet")  # fmt: skip


def test_points_a_little_outside_the_area_of_use_get_a_note(tmp_path: Path) -> None:
    """UTM 10N coordinates about one degree east of the zone (a common spill-over) are kept, with a note."""
    from terralod.tin.pointcloud import read_las

    p = write_las(tmp_path / "spill.las", cloud(800000.0, 5000000.0, 200.0), wkt=wkt_of("EPSG:32610"))
    pc = read_las(p, ground_only=False)
    assert any("partly outside the area of use" in n for n in pc.notes), pc.notes


def test_las_crs_records_that_disagree_warn_which_was_taken(tmp_path: Path) -> None:
    """WKT says UTM 10N (metres), GeoTIFF keys say Oregon Lambert (ft): only UTM 10N's area holds the
    points, so it is taken, with a note naming both."""
    from terralod.tin.pointcloud import read_las

    xyz = cloud(500000.0, 5000000.0, 200.0)
    p = write_las(tmp_path / "two.las", xyz, wkt=wkt_of("EPSG:32610"), geokeys_epsg=2992)
    pc = read_las(p, ground_only=False)
    note = next(n for n in pc.notes if "disagree" in n)
    assert "UTM zone 10N" in note and "Oregon GIC Lambert" in note and "took the WKT record" in note
    assert np.allclose(pc.xyz_m[:, 0], xyz[:, 0], atol=1e-3)  # metres, not feet


def test_las_crs_records_that_disagree_ambiguously_are_refused(tmp_path: Path) -> None:
    """WKT says UTM 10N, GeoTIFF keys say UTM 11N, and the points fit both zones: refused in one line."""
    p = write_las(tmp_path / "amb.las", cloud(700000.0, 5000000.0, 200.0), wkt=wkt_of("EPSG:32610"),
                  geokeys_epsg=32611)  # fmt: skip
    line = one_line_error(terralod("build", str(p), "-o", str(tmp_path / "amb.terra")), p, "disagree")
    assert "UTM zone 10N" in line and "UTM zone 11N" in line and "cannot tell" in line
    from terralod.tin.pointcloud import read_las

    with pytest.raises(InputError, match="disagree"):
        read_las(p)


def test_las_crs_records_that_agree_are_quiet(tmp_path: Path) -> None:
    from terralod.tin.pointcloud import read_las

    p = write_las(tmp_path / "same.las", cloud(500000.0, 5000000.0, 200.0), wkt=wkt_of("EPSG:32610"),
                  geokeys_epsg=32610)  # fmt: skip
    pc = read_las(p, ground_only=False)
    assert not any("disagree" in n for n in pc.notes) and any("GeoTIFF keys agree" in n for n in pc.notes)


def test_raster_heights_follow_the_vertical_axis_of_a_compound_crs(tmp_path: Path) -> None:
    """Oregon Lambert (international ft) + NAVD88 height (US survey ft): x/y scale by 0.3048, heights by
    1200/3937; a horizontal-only foot CRS leaves heights as stored (it says nothing of them)."""
    from affine import Affine

    from terralod.io.georef import crs_summary
    from terralod.io.reader import read_heightfield

    t = Affine(30, 0, 1_300_000, 0, -30, 500_000)
    z = np.full((20, 24), 1000.0, np.float32)
    hf = read_heightfield(write_tif(tmp_path / "c.tif", crs="EPSG:2992+6360", transform=t, z=z))
    assert np.allclose(hf.elevation_m, 1000.0 * US_FT, atol=1e-3)
    assert np.allclose(
        hf.bounds_m, (1_300_000 * FT, (500_000 - 600) * FT, (1_300_000 + 720) * FT, 500_000 * FT)
    )
    s = crs_summary(hf.crs)
    assert s.unit_m == 1.0 and s.vertical_unit_m == 1.0 and s.vertical_name == "NAVD88 height (ftUS)"
    plain = read_heightfield(write_tif(tmp_path / "h.tif", crs="EPSG:2992", transform=t, z=z))
    assert np.allclose(plain.elevation_m, 1000.0)
