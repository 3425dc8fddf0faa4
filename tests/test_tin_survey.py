"""A LiDAR survey delivered as tiles builds one TIN: tiles cut from one cloud (quadrants, with a shared
border point copied into two tiles) give the same vertices and triangles, at every scale, as the merged
file; a tile in another CRS is named in one line; a tile without ground points among classified tiles
contributes none, and says so."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("laspy")

from tests.test_georef import wkt_of  # noqa: E402

from conftest import terralod_cli

#: One survey's header: every tile shares its scale and offset (as tiles cut from one cloud do).
OFFSET = np.array([500000.0, 4880000.0, 0.0])


def write_las(path: Path, xyz: np.ndarray, *, wkt: str) -> Path:
    """A LAS 1.2 file on the survey's integer grid (0.001 m steps from :data:`OFFSET`), CRS as WKT."""
    import laspy
    from laspy.vlrs.known import WktCoordinateSystemVlr

    h = laspy.LasHeader(version="1.2", point_format=3)
    h.offsets = OFFSET
    h.scales = np.array([0.001, 0.001, 0.001])
    h.vlrs.append(WktCoordinateSystemVlr(wkt))
    las = laspy.LasData(h)
    ints = np.round((xyz - OFFSET) / 0.001).astype(np.int32)  # the survey's integer grid, set as is
    las.X, las.Y, las.Z = ints[:, 0], ints[:, 1], ints[:, 2]
    las.write(str(path))
    return path


def _cloud(n: int = 3000, seed: int = 4) -> np.ndarray:
    """Ground-like points over a 400 m square in UTM 10N (file units: metres), a hill and some texture."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0.0, 400.0, (n, 2))
    z = (
        120.0
        + 30.0 * np.exp(-((xy[:, 0] - 200) ** 2 + (xy[:, 1] - 180) ** 2) / 8000.0)
        + 2.0 * np.sin(xy[:, 0] / 13)
    )
    return np.c_[xy + np.array([500000.0, 4880000.0]), z]


def _quadrants(xyz: np.ndarray, folder: Path, wkt: str, order_seed: int = 1) -> list[Path]:
    """Four tiles by quadrant, each in its own shuffled order; one border point copied into two tiles."""
    folder.mkdir()
    cx, cy = 500200.0, 4880200.0
    rng = np.random.default_rng(order_seed)
    paths = []
    for i, (east, north) in enumerate([(False, False), (True, False), (False, True), (True, True)]):
        m = ((xyz[:, 0] >= cx) == east) & ((xyz[:, 1] >= cy) == north)
        part = xyz[m]
        if i == 1:
            part = np.concatenate([part, xyz[np.flatnonzero(~m)[:1]]])  # the same point in two tiles
        paths.append(write_las(folder / f"t{i}.las", part[rng.permutation(len(part))], wkt=wkt))
    return paths


def test_tiles_build_the_merged_files_tin(tmp_path: Path) -> None:
    from terralod.tin import DetailIncrementModel

    wkt = wkt_of("EPSG:32610")
    xyz = _cloud()
    merged = write_las(tmp_path / "merged.las", xyz, wkt=wkt)
    tiles = _quadrants(xyz, tmp_path / "tiles", wkt)
    a = DetailIncrementModel.from_las(merged, sub_blocks=4)
    b = DetailIncrementModel.from_las(tiles[::-1], sub_blocks=4)  # listed in another order too
    assert np.array_equal(a.vertices_m, b.vertices_m)
    for scale in (0, a.n_scales // 2, a.n_scales - 1):
        va, ta = a.mesh_at(scale)
        vb, tb = b.mesh_at(scale)
        assert np.array_equal(va, vb) and np.array_equal(ta, tb), scale
    # no duplicate point: the point copied into two tiles is one vertex
    assert len(np.unique(b.vertices_m[:, :2], axis=0)) == len(b.vertices_m)


def test_cli_builds_a_folder_of_tiles(tmp_path: Path) -> None:
    wkt = wkt_of("EPSG:32610")
    _quadrants(_cloud(1500), tmp_path / "tiles", wkt)
    out = tmp_path / "survey.terra"
    r = terralod_cli("build", str(tmp_path / "tiles"), "-o", str(out))
    assert r.returncode == 0, r.stderr
    assert out.is_file() and "detail-increment TIN" in r.stdout


def test_a_tile_in_another_crs_is_named_in_one_line(tmp_path: Path) -> None:
    xyz = _cloud(800)
    tiles = _quadrants(xyz, tmp_path / "tiles", wkt_of("EPSG:32610"))
    odd = write_las(tiles[2], xyz[:50], wkt=wkt_of("EPSG:26910"))  # NAD83 / UTM 10N: another datum
    r = terralod_cli("build", str(tmp_path / "tiles"), "-o", str(tmp_path / "s.terra"))
    lines = [ln for ln in r.stderr.strip().splitlines() if ln.startswith("terralod")]
    assert r.returncode == 2 and len(lines) == 1, r.stderr
    assert str(odd) in lines[0] and "CRS" in lines[0] and "t0.las" in lines[0], lines[0]
    assert not (tmp_path / "s.terra").exists()


def test_an_unclassified_tile_among_classified_ones_contributes_no_points(tmp_path: Path) -> None:
    import laspy

    from terralod.tin.pointcloud import read_las_survey

    wkt = wkt_of("EPSG:32610")
    tiles = _quadrants(_cloud(1200), tmp_path / "tiles", wkt)
    for t in tiles[:3]:  # three tiles classified as ground, the last not classified
        las = laspy.read(str(t))
        las.classification = np.full(len(las.x), 2, np.uint8)
        las.write(str(t))
    pc = read_las_survey(tiles)
    n_last = len(laspy.read(str(tiles[3])).x)
    assert pc.classified and pc.xyz_m.shape[0] == pc.n_read - n_last
    assert any("t3.las" in n and "no ground" in n for n in pc.notes), pc.notes
