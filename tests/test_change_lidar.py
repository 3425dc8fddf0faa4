"""``terralod change BEFORE.laz AFTER.las``: a LiDAR survey pair gridded by the TIN's linear surface
(:mod:`terralod.change.lidar`), on Autzen with a planted mound of known volume."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from test_change import run as _run  # the CLI in this process: (exit code, stdout, stderr)

laspy = pytest.importorskip("laspy")


AUTZEN = Path("/work/shared/data/lidar/autzen_trim.laz")
FT_M = 0.3048  # Autzen's x, y and z are international feet
RADIUS_M = 25.0
HEIGHT_M = 2.0
#: cos² bump: ∫ H cos²(πr / 2R) dA = π R² H (1/2 − 2/π²)
PLANTED_M3 = math.pi * RADIUS_M**2 * HEIGHT_M * (0.5 - 2.0 / math.pi**2)

pytestmark = pytest.mark.skipif(not AUTZEN.exists(), reason="the Autzen sample is not here")


@pytest.fixture(scope="module")
def pair(tmp_path_factory) -> tuple[Path, Path, Path]:
    """(BEFORE = the Autzen LAZ, AFTER = a copy with a mound on its ground points, AFTER in another CRS)."""
    from scipy import ndimage

    from terralod.change.lidar import grid_survey_pair

    d = tmp_path_factory.mktemp("lidar_pair")
    # the mound's centre: the point of Autzen's gridded ground farthest from any gap
    g = grid_survey_pair(str(AUTZEN), str(AUTZEN))
    dist = ndimage.distance_transform_edt(g.before.valid) * g.spacing_m
    assert dist.max() > RADIUS_M + 5 * g.spacing_m
    r, c = np.unravel_index(np.argmax(dist), dist.shape)
    cx_m, cy_m = g.before.transform @ (c + 0.5, r + 0.5)
    las = laspy.read(str(AUTZEN))
    x_m, y_m = np.asarray(las.x) * FT_M, np.asarray(las.y) * FT_M
    rr = np.hypot(x_m - cx_m, y_m - cy_m)
    bump_m = np.where(rr < RADIUS_M, HEIGHT_M * np.cos(np.pi * rr / (2 * RADIUS_M)) ** 2, 0.0)
    ground = np.asarray(las.classification) == 2
    las.z = np.asarray(las.z) + np.where(ground, bump_m, 0.0) / FT_M
    after = d / "autzen_after.las"
    las.write(str(after))
    # the same points in Oregon Lambert feet on NAD83 (not HARN): another CRS
    from laspy.vlrs.known import WktCoordinateSystemVlr
    from pyproj import CRS

    other = laspy.read(str(AUTZEN))
    other.vlrs = [WktCoordinateSystemVlr(CRS.from_epsg(2992).to_wkt(version="WKT1_GDAL"))]
    other.header.global_encoding.wkt = True
    other_crs = d / "autzen_other_crs.las"
    other.write(str(other_crs))
    return AUTZEN, after, other_crs


def test_planted_mound_volume(pair, tmp_path: Path, capsys) -> None:
    before, after, _ = pair
    out = tmp_path / "out"
    code, so, se = _run(capsys, "change", before, after, "-o", out, "--no-views")
    assert code == 0, se
    s = json.loads((out / "summary.json").read_text())
    # the gained volume within 5 % of the planted one (every valid cell, no threshold)
    assert s["gain_m3"] == pytest.approx(PLANTED_M3, rel=0.05), (s["gain_m3"], PLANTED_M3)
    assert s["net_m3"] == pytest.approx(PLANTED_M3, rel=0.05)
    g = s["gridding"]
    assert g["spacing_m"] == 1.5 and g["spacing_source"] == "point density"
    assert "ground points (class 2)" in g["statement"] and "every 1.5 m" in g["statement"]
    assert any("surface of triangles" in n for n in s["alignment_notes"])
    assert "surface of triangles" in (out / "report.html").read_text()
    assert str(tmp_path) not in json.dumps(s)


def test_given_spacing(pair, tmp_path: Path, capsys) -> None:
    before, after, _ = pair
    out = tmp_path / "out"
    code, _, se = _run(capsys, "change", before, after, "-o", out, "--no-views", "--spacing", "3",
                       "--no-coregister")  # fmt: skip
    assert code == 0, se
    s = json.loads((out / "summary.json").read_text())
    assert s["gridding"]["spacing_m"] == 3.0 and s["gridding"]["spacing_source"] == "given"
    assert s["grid"]["spacing_m"] == [3.0, 3.0]
    assert s["gain_m3"] == pytest.approx(PLANTED_M3, rel=0.08)


def test_other_crs_refused_in_one_line(pair, tmp_path: Path, capsys) -> None:
    before, _, other = pair
    code, _, se = _run(capsys, "change", before, other, "-o", tmp_path / "out")
    assert code == 2
    lines = [ln for ln in se.strip().splitlines() if ln.strip()]
    assert len(lines) == 1 and other.name in lines[0] and "CRS" in lines[0], se
    assert not (tmp_path / "out").exists()


def test_lidar_with_a_dem_refused(pair, tmp_path: Path, capsys) -> None:
    before, _, _ = pair
    dem = tmp_path / "dem.tif"
    dem.write_bytes(b"")
    code, _, se = _run(capsys, "change", before, dem, "-o", tmp_path / "out")
    assert code == 2 and before.name in se and len(se.strip().splitlines()) == 1, se


def test_nice_spacing() -> None:
    from terralod.change.lidar import nice_spacing_m

    assert [nice_spacing_m(v) for v in (0.4, 1.0, 1.2, 1.53, 2.7, 3.1, 6.0, 8.0)] == [
        0.4, 1.0, 1.5, 2.0, 3.0, 4.0, 7.5, 10.0,
    ]  # fmt: skip


def test_folder_of_tiles_and_site(pair, tmp_path: Path, capsys) -> None:
    """AFTER as a folder of LAS tiles (the survey resolver, las_inputs) and --site: both epochs as their
    surveys' continuous-scale TINs (issue 55 #4): the site's epoch 0 is the 3D Tiles of ``terralod build
    BEFORE.laz`` (a TIN store) at its root, not the gridded surface's."""
    pytest.importorskip("terralod.site")
    before, after, _ = pair
    las = laspy.read(str(after))
    tiles = tmp_path / "after_tiles"
    tiles.mkdir()
    mid = float(np.median(las.x))
    for i, m in enumerate((np.asarray(las.x) < mid, np.asarray(las.x) >= mid)):
        sub = laspy.LasData(las.header)
        sub.points = las.points[m]
        sub.write(str(tiles / f"t{i}.las"))
    out = tmp_path / "out"
    code, _, se = _run(capsys, "change", before, tiles, "-o", out, "--no-views", "--site")
    assert code == 0, se
    s = json.loads((out / "summary.json").read_text())
    assert s["gain_m3"] == pytest.approx(PLANTED_M3, rel=0.05)
    assert s["after"]["source"] == "after_tiles (2 point-cloud files)"
    site = json.loads((out / "site" / "site.json").read_text())
    assert len(site["epochs"]) == 2
    for e in site["epochs"]:
        assert (out / "site" / e["tileset"]).is_file()
    from terralod.export.tiles3d import export_3dtiles
    from terralod.terrain import open_terrain

    assert _run(capsys, "build", before, "-o", tmp_path / "tin.terra")[0] == 0
    with open_terrain(tmp_path / "tin.terra") as t:
        assert t.kind == "tin"
        export_3dtiles(t, tmp_path / "tin3d")
    want = json.loads((tmp_path / "tin3d" / "tileset.json").read_text())["root"]
    got = json.loads((out / "site" / site["epochs"][0]["tileset"]).read_text())["root"]
    assert got["boundingVolume"] == want["boundingVolume"]
    assert got["geometricError"] == want["geometricError"]
