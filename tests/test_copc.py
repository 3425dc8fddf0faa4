"""A part of a LiDAR survey (``build --bbox``), and COPC files read through their octree: a COPC file and a
plain LAZ file of the same points give the same cloud, whole or in a box; in a box the COPC read decodes
only the octree nodes that meet it (fewer points than the file holds); the points kept are exactly those
whose longitude and latitude fall in the box, whatever the file's kind; a survey cut into COPC tiles builds
from ``terralod build --bbox`` the TIN the merged file builds in that box. The COPC files are written by
copclib (a maintained COPC writer; laspy writes none) from Autzen's real points."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

laspy = pytest.importorskip("laspy")
copclib = pytest.importorskip("copclib", reason="copclib writes the test's COPC files (pip install copclib)")

from conftest import terralod_cli  # noqa: E402


def write_copc(path: Path, xyz: np.ndarray, cls: np.ndarray, wkt: str, *, depth: int = 3, scale: float = 0.01,
               seed: int = 0) -> Path:  # fmt: skip
    """A COPC file (point format 6) of ``xyz`` (file units) written by copclib: an octree of ``depth``
    levels over the cube [min, min + largest extent] (the cube copclib and laspy both derive), points spread
    over the levels by a fixed shuffle (1/8 of the deeper level's share each level up), every node's parent
    holding a point (readers walk the tree from the root)."""
    n = len(xyz)
    lo, hi = xyz.min(axis=0), xyz.max(axis=0)
    half = float((hi - lo).max() / 2)
    centre = lo + half
    offset = np.floor(lo)
    cfg = copclib.CopcConfigWriter(point_format_id=6, scale=copclib.Vector3(scale, scale, scale),
                                   offset=copclib.Vector3(*offset), wkt=wkt)  # fmt: skip
    cfg.las_header.min = copclib.Vector3(*lo)
    cfg.las_header.max = copclib.Vector3(*hi)
    cfg.copc_info.center_x, cfg.copc_info.center_y, cfg.copc_info.center_z = (float(v) for v in centre)
    cfg.copc_info.halfsize = half
    cfg.copc_info.spacing = 2 * half / 128
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales, header.offsets = np.array([scale] * 3), offset
    level = np.full(n, depth)
    order = np.random.default_rng(seed).permutation(n)
    for d in range(depth - 1, -1, -1):
        level[order[: max(1, n // 8 ** (depth - d))]] = d
    corner = centre - half

    def keys(idx: np.ndarray, d: int) -> np.ndarray:
        return np.clip(((xyz[idx] - corner) // (2 * half / 2**d)).astype(np.int64), 0, 2**d - 1)

    for d in range(depth, 0, -1):  # a node without a parent node is never reached: move a point up
        here, up = np.flatnonzero(level == d), np.flatnonzero(level == d - 1)
        want = keys(here, d - 1)
        have = {tuple(k) for k in keys(up, d - 1).tolist()}
        _, first = np.unique(want, axis=0, return_index=True)
        level[[here[i] for i in first if tuple(want[i].tolist()) not in have]] = d - 1
    w = copclib.FileWriter(str(path), cfg)
    for d in range(depth + 1):
        sel = np.flatnonzero(level == d)
        uniq, inv = np.unique(keys(sel, d), axis=0, return_inverse=True)
        for k, key in enumerate(uniq):
            idx = sel[inv.ravel() == k]
            rec = laspy.ScaleAwarePointRecord.zeros(len(idx), header=header)
            rec.x, rec.y, rec.z = xyz[idx, 0], xyz[idx, 1], xyz[idx, 2]
            rec.classification = cls[idx]
            raw = copclib.VectorChar(np.frombuffer(rec.array.tobytes(), np.int8))
            w.AddNode(copclib.VoxelKey(d, *(int(v) for v in key)), raw)
    w.Close()
    return path


def write_laz(path: Path, xyz: np.ndarray, cls: np.ndarray, wkt: str, scale: float = 0.01) -> Path:
    """The same points as a plain LAZ 1.4 file (laspy, lazrs), no octree."""
    from laspy.vlrs.known import WktCoordinateSystemVlr

    h = laspy.LasHeader(point_format=6, version="1.4")
    h.scales, h.offsets = np.array([scale] * 3), np.floor(xyz.min(axis=0))
    h.vlrs.append(WktCoordinateSystemVlr(wkt))
    las = laspy.LasData(h)
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    las.classification = cls
    las.write(str(path), laz_backend=laspy.LazBackend.Lazrs)
    return path


@pytest.fixture(scope="module")
def autzen(shared_data: Path, tmp_path_factory) -> dict:
    """Autzen's 110,000 real points (feet, Oregon Lambert) as one COPC file, one LAZ file, and four COPC
    quadrant tiles; with the points' lon/lat extent."""
    from pyproj import Transformer

    las = laspy.read(str(shared_data / "lidar" / "autzen_trim.laz"))
    wkt = las.header.parse_crs().to_wkt()
    xyz = np.stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)], axis=1)
    cls = np.asarray(las.classification).astype(np.uint8)
    d = tmp_path_factory.mktemp("copc")
    tiles = d / "tiles"
    tiles.mkdir()
    mx, my = np.median(xyz[:, 0]), np.median(xyz[:, 1])
    for i, sel in enumerate([(xyz[:, 0] < mx) & (xyz[:, 1] < my), (xyz[:, 0] >= mx) & (xyz[:, 1] < my),
                             (xyz[:, 0] < mx) & (xyz[:, 1] >= my), (xyz[:, 0] >= mx) & (xyz[:, 1] >= my)]):  # fmt: skip
        write_copc(tiles / f"q{i}.copc.laz", xyz[sel], cls[sel], wkt)
    lon, lat = Transformer.from_crs(las.header.parse_crs(), "EPSG:4326", always_xy=True).transform(
        xyz[:, 0], xyz[:, 1]
    )
    return {"copc": write_copc(d / "autzen.copc.laz", xyz, cls, wkt), "laz": write_laz(d / "autzen.laz", xyz, cls, wkt),
            "tiles": tiles, "extent": (lon.min(), lat.min(), lon.max(), lat.max()), "dir": d}  # fmt: skip


def _sorted(xyz: np.ndarray) -> np.ndarray:
    return xyz[np.lexsort((xyz[:, 2], xyz[:, 1], xyz[:, 0]))]


def test_a_copc_file_reads_as_its_laz_twin(autzen: dict) -> None:
    """Whole, a COPC file is LAZ: the same ground points, units and CRS as the plain file of its points."""
    from terralod.tin.pointcloud import read_las

    a, b = read_las(autzen["copc"]), read_las(autzen["laz"])
    assert a.classified and b.classified and a.crs == b.crs
    assert a.xyz_m.shape[0] == b.xyz_m.shape[0] > 20_000
    np.testing.assert_array_equal(_sorted(a.xyz_m), _sorted(b.xyz_m))


@settings(max_examples=8, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.tuples(*[st.floats(0.0, 1.0)] * 4))
def test_a_box_keeps_exactly_its_points_and_copc_decodes_only_its_nodes(autzen: dict, f: tuple) -> None:
    """In any box, the COPC read and the chunked LAZ read keep the same points, exactly those of the
    whole cloud whose lon/lat fall in the box; the COPC read decodes the nodes meeting the box only, never
    more than the file and fewer when the box is a small part of it."""
    from pyproj import CRS, Transformer

    from terralod.errors import InputError
    from terralod.tin.pointcloud import read_las

    w0, s0, e0, n0 = autzen["extent"]
    x = sorted([w0 + f[0] * (e0 - w0), w0 + f[1] * (e0 - w0)])
    y = sorted([s0 + f[2] * (n0 - s0), s0 + f[3] * (n0 - s0)])
    box = (x[0], y[0], max(x[1], x[0] + 1e-6), max(y[1], y[0] + 1e-6))
    whole = autzen.get("whole") or autzen.setdefault("whole", read_las(autzen["laz"]))
    lon, lat = Transformer.from_crs(CRS.from_user_input(whole.crs), "EPSG:4326", always_xy=True).transform(
        whole.xyz_m[:, 0], whole.xyz_m[:, 1]
    )
    want = whole.xyz_m[(lon >= box[0]) & (lon <= box[2]) & (lat >= box[1]) & (lat <= box[3])]
    try:
        a = read_las(autzen["copc"], bbox_deg=box)
        b = read_las(autzen["laz"], bbox_deg=box)
    except InputError as exc:  # a box with no point of any class
        assert want.shape[0] == 0, exc
        return
    np.testing.assert_array_equal(_sorted(a.xyz_m), _sorted(want))
    np.testing.assert_array_equal(_sorted(b.xyz_m), _sorted(want))
    decoded = [int(n.split("decoded ")[1].split(" of")[0].replace(",", "")) for n in a.notes if "COPC" in n]
    decoded += [0 for n in a.notes if "header bounds miss" in n]  # not opened: the box is beside the file
    assert len(decoded) == 1 and decoded[0] <= 110_000
    if (box[2] - box[0]) * (box[3] - box[1]) < 0.1 * (e0 - w0) * (n0 - s0):
        assert decoded[0] < 110_000 * 0.75, decoded
    assert not any("COPC" in n for n in b.notes)


def test_build_bbox_of_a_copc_survey_builds_the_merged_files_tin(autzen: dict) -> None:
    """``terralod build TILES/ --bbox`` (four COPC tiles) stores the TIN the merged LAZ file builds in the
    same box: the same vertices; every vertex inside the box; tiles outside it cost nothing."""
    from pyproj import CRS, Transformer

    from terralod.tin import DetailIncrementModel
    from terralod.tin.terra import load_model_from_store

    w0, s0, e0, n0 = autzen["extent"]
    box = (w0 + 0.1 * (e0 - w0), s0 + 0.1 * (n0 - s0), w0 + 0.45 * (e0 - w0), s0 + 0.45 * (n0 - s0))
    out = autzen["dir"] / "part.terra"
    r = terralod_cli(
        "build", str(autzen["tiles"]), "-o", str(out), "--bbox", ",".join(f"{v:.9f}" for v in box)
    )
    assert r.returncode == 0, r.stderr
    got = load_model_from_store(out)[0]
    want = DetailIncrementModel.from_las(autzen["laz"], bbox_deg=box)
    np.testing.assert_array_equal(_sorted(got.vertices_m), _sorted(want.vertices_m))
    lon, lat = Transformer.from_crs(CRS.from_user_input(want.crs), "EPSG:4326", always_xy=True).transform(
        got.vertices_m[:, 0], got.vertices_m[:, 1]
    )
    assert (lon >= box[0]).all() and (lon <= box[2]).all() and (lat >= box[1]).all() and (lat <= box[3]).all()


def test_build_bbox_refusals_are_one_line(autzen: dict, tmp_path: Path) -> None:
    """A box that holds no point, a malformed box, and a box on a DEM build: one line, exit 2, no store."""
    w0, s0, e0, n0 = autzen["extent"]
    far = f"{w0 + 5:.6f},{s0:.6f},{w0 + 5.01:.6f},{s0 + 0.01:.6f}"
    cases = [
        (str(autzen["copc"]), far, "no point inside --bbox"),
        (str(autzen["copc"]), "1,2,3", "--bbox"),
        (str(autzen["copc"]), f"{e0},{s0},{w0},{n0}", "--bbox"),
    ]
    for src, box, words in cases:
        out = tmp_path / "x.terra"
        r = terralod_cli("build", src, "-o", str(out), "--bbox", box)
        assert r.returncode == 2 and words in r.stderr, (box, r.stderr)
        assert len([ln for ln in r.stderr.splitlines() if ln.strip()]) <= 3 and not out.exists()
