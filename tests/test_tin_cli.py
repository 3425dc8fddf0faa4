"""TIN models (paper 003) in ``.terra`` stores and on the command line: ``terralod build cloud.las`` stores the
detail-increment model (one transaction, checksummed), ``terralod info`` describes it, the stored model gives
back exactly the model built, a damaged blob is caught, tile readers refuse a TIN store clearly, and bad
LAS/LAZ input gets one line naming the file and exit code 2."""

from __future__ import annotations

import json
import sqlite3
import subprocess
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from terralod.errors import CorruptStoreError, InputError, StoreError
from terralod.store import TIN_METHOD, open_store, read_tin_store, store_method
from terralod.tin import DetailIncrementModel, read_las
from terralod.tin.terra import load_model_from_store, model_summary, save_model_to_store

from conftest import terralod_cli

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data"
FOOT_M = 0.3048


def run_cli(*args: str) -> subprocess.CompletedProcess:
    """``terralod ARGS`` in this process (tests/conftest.py ``terralod_cli``)."""
    return terralod_cli(*args)


def _points(seed: int, n: int) -> np.ndarray:
    """Random xy over 500 m² with a smooth surface, metres (projected frame)."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0.0, 500.0, (n, 2)) + np.array([400000.0, 5000000.0])
    z = 100.0 + 15.0 * np.sin((xy[:, 0] - 400000.0) / 60.0) * np.cos((xy[:, 1] - 5000000.0) / 90.0)
    return np.c_[xy, z]


def write_las(path: Path, xyz: np.ndarray, classification: np.ndarray | None = None) -> Path:
    """A LAS 1.2 point format 3 file without CRS (coordinates taken as metres), 1 mm resolution."""
    import laspy

    header = laspy.LasHeader(point_format=3, version="1.2")
    header.scales = np.array([0.001, 0.001, 0.001])
    header.offsets = np.floor(xyz.min(axis=0))
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    if classification is not None:
        las.classification = classification
    las.write(str(path))
    return path


def test_store_roundtrip_is_exact_and_tile_readers_refuse_it(tmp_path: Path) -> None:
    m = DetailIncrementModel.from_points(_points(1, 1500), sub_blocks=4, source="cloud.las")
    out = tmp_path / "m.terra"
    summary = save_model_to_store(m, out)
    assert summary["size_bytes"] == out.stat().st_size
    assert summary["triangles"] == m.n_slots and summary["scales"] == m.n_scales
    assert store_method(out) == TIN_METHOD
    r, meta = load_model_from_store(out)
    assert meta["source"] == "cloud.las" and meta["base_triangles"] == summary["base_triangles"]
    # the stored model reaches exactly the same triangulations at every scale probed, forwards and back
    for s in (m.n_scales - 1, 0, m.n_scales // 2, 1, m.n_scales - 1):
        assert np.array_equal(r.mesh_at(s)[1], m.mesh_at(s)[1])
        assert np.array_equal(r.mesh_at(s)[0], m.mesh_at(s)[0])
    assert r.mesh_at(0)[1].shape[0] == summary["base_triangles"]
    # refining the stored base fully gives the input Delaunay TIN
    t, f = r.mesh_at(r.n_scales - 1)[1].astype(np.int64), m._full_tris.astype(np.int64)
    canon = [
        np.sort(np.take_along_axis(x, (np.argmin(x, 1)[:, None] + np.arange(3)) % 3, 1).view("i8,i8,i8"), 0)
        for x in (t, f)
    ]
    assert np.array_equal(*canon)
    with pytest.raises(StoreError, match="TIN detail-increment model"):
        open_store(out)
    with pytest.raises(StoreError, match="already exists"):
        save_model_to_store(m, out)
    save_model_to_store(m.compressed(4), out, overwrite=True)
    c, meta = load_model_from_store(out)
    assert meta["collapses_per_record"] == 4 and c.n_scales < m.n_scales
    assert np.array_equal(c.mesh_at(c.n_scales - 1)[1], m.mesh_at(m.n_scales - 1)[1])


def test_damaged_model_blob_is_detected(tmp_path: Path) -> None:
    m = DetailIncrementModel.from_points(_points(2, 800), sub_blocks=4)
    out = tmp_path / "m.terra"
    save_model_to_store(m, out)
    with sqlite3.connect(out) as conn:
        blob = bytearray(conn.execute("SELECT model FROM tin_model").fetchone()[0])
        blob[len(blob) // 2] ^= 0x01
        conn.execute("UPDATE tin_model SET model = ?", (bytes(blob),))
    conn.close()
    with pytest.raises(CorruptStoreError, match="checksum") as e:
        load_model_from_store(out)
    assert str(out) in str(e.value)
    # the checksum column agreeing with a damaged payload: the model's own sha256 still catches it
    with sqlite3.connect(out) as conn:
        import hashlib

        conn.execute("UPDATE tin_model SET sha256 = ?", (hashlib.sha256(bytes(blob)).hexdigest(),))
    conn.close()
    with pytest.raises(CorruptStoreError, match="checksum") as e:
        load_model_from_store(out)
    assert str(out) in str(e.value)
    (tmp_path / "foreign.terra").write_bytes(b"not a store" * 20)
    with pytest.raises(CorruptStoreError):
        read_tin_store(tmp_path / "foreign.terra")


def test_read_las_keeps_ground_and_refuses_bad_points(tmp_path: Path) -> None:
    xyz = _points(3, 400)
    cls = np.where(np.arange(400) % 4 == 0, 1, 2).astype(np.uint8)  # a quarter is not ground
    pc = read_las(write_las(tmp_path / "c.las", xyz, cls))
    assert pc.xyz_m.shape == (300, 3) and pc.classified
    assert np.allclose(np.sort(pc.xyz_m[:, 2]), np.sort(xyz[cls == 2, 2]), atol=1e-3)
    assert any("metres" in n for n in pc.notes)  # no CRS in the file: said so
    pc = read_las(tmp_path / "c.las", ground_only=False, units="ft")
    assert pc.xyz_m.shape == (400, 3)
    assert np.allclose(np.sort(pc.xyz_m[:, 2]), np.sort(xyz[:, 2]) * FOOT_M, atol=1e-3)
    with pytest.raises(InputError, match="collinear") as e:
        DetailIncrementModel.from_las(write_las(tmp_path / "line.las", np.c_[np.arange(50.0), np.arange(50.0),
                                                                            np.ones(50)]))  # fmt: skip
    assert "line.las" in str(e.value)
    with pytest.raises(InputError, match="at least 3") as e:
        DetailIncrementModel.from_las(write_las(tmp_path / "two.las", xyz[:2]))
    assert "two.las" in str(e.value)
    with pytest.raises(InputError, match="no ground points"):
        read_las(write_las(tmp_path / "unc.las", xyz[:10], np.ones(10, np.uint8)), ground_only=True)


@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    n=st.integers(1, 300),
    chunk=st.integers(1, 64),
    first_ground=st.integers(0, 320),  # the first class-2 point (past n: none)
    ground_only=st.sampled_from([None, True, False]),
    laz=st.booleans(),
)
def test_chunked_las_read_keeps_what_a_whole_read_keeps(
    tmp_path: Path, monkeypatch, n, chunk, first_ground, ground_only, laz
) -> None:
    """read_las streams the file in chunks (laspy's chunk iterator): the points kept, their order and
    coordinates are those of the whole file read at once, wherever the first ground point falls."""
    import laspy

    import terralod.tin.pointcloud as pc_mod

    xyz = _points(n, n)
    rng = np.random.default_rng(n)
    cls = np.where(rng.random(n) < 0.6, 2, 1).astype(np.uint8)
    cls[: min(first_ground, n)] = 1
    p = write_las(tmp_path / f"c{n}_{chunk}.{'laz' if laz else 'las'}", xyz, cls)
    whole = laspy.read(str(p))
    wx = np.c_[np.asarray(whole.x), np.asarray(whole.y), np.asarray(whole.z)]
    ground = np.asarray(whole.classification) == 2
    monkeypatch.setattr(pc_mod, "LAS_CHUNK_POINTS", chunk)
    if ground_only is True and not ground.any():
        with pytest.raises(InputError, match="no ground points"):
            read_las(p, ground_only=True)
        return
    got = read_las(p, ground_only=ground_only)
    want = wx[ground] if ground.any() and ground_only is not False else wx
    assert np.array_equal(got.xyz_m, want) and got.n_read == n and got.classified == bool(ground.any())


def test_cli_build_and_info_of_a_cloud(tmp_path: Path) -> None:
    las = write_las(tmp_path / "cloud.las", _points(4, 3000))
    out = tmp_path / "cloud.terra"
    r = run_cli("build", str(las), "-o", str(out), "--sub-blocks", "9")
    assert r.returncode == 0, r.stderr
    assert "detail-increment TIN" in r.stdout and "9 sub-blocks" in r.stdout
    # the points/s of the whole command and the seconds of each stage, read to save
    stages = next(line for line in r.stdout.splitlines() if line.strip().startswith("stages"))
    assert "k points/s" in r.stdout
    assert [part.split()[0] for part in stages.split(None, 1)[1].split(", ")] == [
        "read", "dedup", "delaunay", "split", "qem", "records", "save"
    ]  # fmt: skip
    r = run_cli("info", str(out), "--json")
    assert r.returncode == 0, r.stderr
    d = json.loads(r.stdout)
    m, _ = load_model_from_store(out)
    assert d["method"] == "tin" and d["sub_blocks"] == 9 and d["size_bytes"] == out.stat().st_size
    assert {k: d[k] for k in ("vertices", "triangles", "scales", "records")} == {
        k: model_summary(m)[k] for k in ("vertices", "triangles", "scales", "records")
    }
    r = run_cli("info", str(out))
    assert r.returncode == 0 and "method tin" in r.stdout and "base" in r.stdout
    # existing output without --overwrite: one line, exit 2, store untouched
    before = out.read_bytes()
    r = run_cli("build", str(las), "-o", str(out))
    assert r.returncode == 2 and "already exists" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    assert out.read_bytes() == before
    r = run_cli("build", str(las), "-o", str(out), "--overwrite", "--base-fraction", "0.5")
    assert r.returncode == 0, r.stderr
    # every command takes the TIN store through the one Terrain interface: a fly-through renders it
    r = run_cli("flythrough", str(out), "-o", str(tmp_path / "x.mp4"), "--frames", "2", "--size", "160x96")
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "x.mp4").stat().st_size > 0 and "frames" in r.stdout


def test_cli_build_tin_from_a_dem(tmp_path: Path) -> None:
    """``--method tin`` on a DEM: the grid TIN of its samples (world metres) as a detail-increment model."""
    import rasterio
    from rasterio.transform import from_origin

    z = (200.0 + 30.0 * np.sin(np.arange(40)[:, None] / 6.0) * np.cos(np.arange(50)[None, :] / 8.0)).astype(
        "f4"
    )
    tif = tmp_path / "dem.tif"
    with rasterio.open(tif, "w", driver="GTiff", width=50, height=40, count=1, dtype="float32", crs="EPSG:32610",
                       transform=from_origin(500000, 5200000, 30.0, 30.0)) as ds:  # fmt: skip
        ds.write(z, 1)
    out = tmp_path / "dem.terra"
    r = run_cli("build", str(tif), "-o", str(out), "--method", "tin")
    assert r.returncode == 0, r.stderr
    m, meta = load_model_from_store(out)
    v, t = m.mesh_at(m.n_scales - 1)
    assert t.shape[0] == 2 * 39 * 49 == meta["triangles"] and v.shape[0] == 40 * 50
    assert np.allclose(np.sort(v[:, 2]), np.sort(z.ravel().astype(np.float64)))
    assert v[:, 0].min() == pytest.approx(500015.0) and v[:, 1].max() == pytest.approx(5199985.0)  # centres


@pytest.mark.parametrize(
    ("name", "content", "message"),
    [
        ("garbage.laz", b"this is not a point cloud\n" * 8, "cannot read as LAS/LAZ"),
        ("empty.las", b"", "cannot read as LAS/LAZ"),
        ("missing.laz", None, "not found"),
    ],
)
def test_cli_bad_cloud_gets_one_line(tmp_path: Path, name: str, content: bytes | None, message: str) -> None:
    src = tmp_path / name
    if content is not None:
        src.write_bytes(content)
    out = tmp_path / "o.terra"
    r = run_cli("build", str(src), "-o", str(out))
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and name in lines[0] and message in lines[0], r.stderr
    assert not out.exists()


def test_cli_bad_tin_options(tmp_path: Path) -> None:
    las = write_las(tmp_path / "c.las", _points(5, 200))
    for opts, hint in ((["--sub-blocks", "5"], "square"), (["--sub-blocks", "x"], "sub-blocks"),
                       (["--base-fraction", "0"], "base-fraction")):  # fmt: skip
        r = run_cli("build", str(las), "-o", str(tmp_path / "o.terra"), *opts)
        assert r.returncode == 2 and hint in r.stderr and "Traceback" not in r.stderr, r.stderr


@pytest.mark.skipif(not (SHARED / "lidar" / "autzen_trim.laz").exists(),
                    reason=f"real LiDAR not present at {SHARED} (../shared/data beside the repository)")  # fmt: skip
def test_cli_real_laz(tmp_path: Path) -> None:
    """Autzen (LAZ, international feet, classified): the store holds the ground-only model in metres."""
    out = tmp_path / "autzen.terra"
    r = run_cli("build", str(SHARED / "lidar" / "autzen_trim.laz"), "-o", str(out))
    assert r.returncode == 0, r.stderr
    m, meta = load_model_from_store(out)
    assert meta["vertices"] == m.vertices_m.shape[0] and 20_000 < meta["vertices"] <= 26_107
    assert 123.0 < meta["elevation_range_m"][0] and meta["elevation_range_m"][1] < 133.0
    assert any("foot" in n for n in meta["notes"])
    assert meta["base_triangles"] <= 0.21 * meta["triangles"]
