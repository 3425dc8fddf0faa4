"""End-to-end CLI: info/build/demo, bad input gets one line naming the file and exit code 2, and a build
killed at a random moment leaves an openable store that --resume finishes identically."""

from __future__ import annotations

import os
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import rasterio
from rasterio.transform import from_origin

from terralod import build_store, open_store, read_heightfield

from conftest import fractal_terrain


def run_cli(*args: str, cwd: Path | None = None, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "terralod", *args], capture_output=True, text=True, cwd=cwd, timeout=timeout
    )


def write_tif(
    path: Path, z: np.ndarray, nodata: float | None = None, crs: str = "EPSG:32610", res: float = 30.0
) -> Path:
    with rasterio.open(
        path, "w", driver="GTiff", width=z.shape[1], height=z.shape[0], count=1, dtype=z.dtype,
        crs=crs, transform=from_origin(500000, 5200000, res, res), nodata=nodata,
    ) as ds:  # fmt: skip
        ds.write(z, 1)
    return path


def assert_one_line_error(proc: subprocess.CompletedProcess, *needles: str) -> None:
    assert proc.returncode == 2, (proc.returncode, proc.stdout, proc.stderr)
    lines = [ln for ln in proc.stderr.strip().splitlines() if ln.strip()]
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("terralod: ")
    assert "Traceback" not in proc.stderr
    for n in needles:
        assert n in lines[0], (n, lines[0])


def test_bad_inputs(tmp_path: Path) -> None:
    out = str(tmp_path / "o.terra")
    missing = tmp_path / "missing.tif"
    assert_one_line_error(run_cli("build", str(missing), "-o", out), "missing.tif", "not found")
    txt = tmp_path / "notes.tif"
    txt.write_text("not a raster\n" * 50)
    assert_one_line_error(run_cli("build", str(txt), "-o", out), "notes.tif")
    allnd = write_tif(tmp_path / "allnodata.tif", np.full((50, 50), -9999, np.int16), nodata=-9999)
    assert_one_line_error(run_cli("build", str(allnd), "-o", out), "allnodata.tif", "no valid samples")
    nan = write_tif(tmp_path / "nan.tif", np.full((50, 50), np.nan, np.float32))
    assert_one_line_error(run_cli("info", str(nan)), "nan.tif", "NaN")
    one = write_tif(tmp_path / "one.tif", np.ones((1, 1), np.float32))
    assert_one_line_error(run_cli("build", str(one), "-o", out), "one.tif", "1x1")
    # an absurd raster: a sparse GeoTIFF header claiming 400 000 x 400 000 samples
    with rasterio.open(
        tmp_path / "huge.tif", "w", driver="GTiff", width=400_000, height=400_000, count=1, dtype="int16",
        crs="EPSG:32610", transform=from_origin(0, 0, 1, 1), tiled=True, sparse_ok=True, compress="deflate",
        BIGTIFF="YES",
    ):  # fmt: skip
        pass
    assert_one_line_error(run_cli("info", str(tmp_path / "huge.tif")), "huge.tif", "400000x400000")
    good = write_tif(tmp_path / "good.tif", fractal_terrain(40, 40, 1))
    assert_one_line_error(run_cli("build", str(good), "-o", "/dev/null/x.terra"), "x.terra")
    assert_one_line_error(
        run_cli("build", str(good), "-o", str(tmp_path / "nodir" / "x.terra")), "does not exist"
    )
    png = tmp_path / "h.png"
    from PIL import Image

    Image.fromarray(np.zeros((20, 20), np.uint16)).save(png)
    assert_one_line_error(run_cli("info", str(png)), "h.png", "spacing")
    # a corrupt store
    bad = tmp_path / "bad.terra"
    bad.write_bytes(b"SQLite format 3\x00" + b"\x00" * 200)
    assert_one_line_error(run_cli("info", str(bad)), "bad.terra")


def test_info_and_build(tmp_path: Path) -> None:
    src = write_tif(tmp_path / "dem.tif", fractal_terrain(200, 150, 5), crs="EPSG:32610", res=30.0)
    p = run_cli("info", str(src))
    assert p.returncode == 0, p.stderr
    assert "150 x 200" in p.stdout and "EPSG:32610" in p.stdout and "30.000 x 30.000 m" in p.stdout
    p = run_cli("build", str(src), "-o", str(tmp_path / "dem.terra"), "--tile-size", "33", "--workers", "2")
    assert p.returncode == 0, p.stderr
    p = run_cli("info", str(tmp_path / "dem.terra"))
    assert p.returncode == 0 and "complete" in p.stdout and "max error m" in p.stdout
    with open_store(tmp_path / "dem.terra") as s:
        assert s.meta["method"] == "cohesion"  # the default mesher: the vertex cohesion map (paper 000)


def test_demo_runs(tmp_path: Path) -> None:
    p = run_cli("demo", cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    assert "jacksboro" in p.stdout and (tmp_path / "demo.terra").exists()
    with open_store(tmp_path / "demo.terra") as s:
        assert s.complete and len(s.tile_codes()) == len(s.pyramid.all_codes())
        assert "UTM zone 16N" in (s.crs or "")
        assert s.meta["method"] == "cohesion"


def test_kill_during_build_then_resume(tmp_path: Path) -> None:
    z = fractal_terrain(1500, 1400, 11, relief_m=2000.0)
    src = write_tif(tmp_path / "big.tif", z)
    out = tmp_path / "big.terra"
    proc = subprocess.Popen(
        [sys.executable, "-m", "terralod", "build", str(src), "-o", str(out), "--tile-size", "9", "--workers", "2"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    n = 0
    deadline = time.time() + 240
    while time.time() < deadline and proc.poll() is None:
        time.sleep(0.05)
        if out.exists():
            try:
                con = sqlite3.connect(f"file:{out}?mode=ro", uri=True, timeout=0.1)
                n = con.execute("SELECT count(*) FROM tiles").fetchone()[0]
                con.close()
            except sqlite3.Error:
                n = 0
            if n > 200:
                break
    assert proc.poll() is None, "build finished before it could be killed; make the input larger"
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    with open_store(out) as s:
        assert not s.complete
        done = len(s.tile_codes())
        assert 0 < done < len(s.pyramid.all_codes())
        assert s.verify() == []
    p = run_cli("build", str(src), "-o", str(out), "--tile-size", "9", "--resume")
    assert p.returncode == 0, p.stderr
    ref = tmp_path / "ref.terra"
    build_store(read_heightfield(src), ref, tile_size=9)
    rows = []
    for path in (out, ref):
        con = sqlite3.connect(path)
        rows.append(con.execute("SELECT * FROM tiles ORDER BY level, x, y").fetchall())
        con.close()
    assert rows[0] == rows[1]
    with open_store(out) as s:
        assert s.complete


@pytest.mark.parametrize("name", ["dem/srtm3_N42E001.tif", "dem/kilauea_hawaii_30m_utm5.tif"])
def test_real_dem_cli_info(shared_data: Path, name: str) -> None:
    p = run_cli("info", str(shared_data / name))
    assert p.returncode == 0, p.stderr
    assert "none (local metric frame)" not in p.stdout
    crs = read_heightfield(shared_data / name).crs or ""
    assert "UTM" in crs or "Transverse_Mercator" in crs
