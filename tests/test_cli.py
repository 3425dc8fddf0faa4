"""End-to-end CLI: info/build/demo, bad input gets one line naming the file and exit code 2 (kills and
resumes: tests/test_kill.py)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import rasterio
from rasterio.transform import from_origin

from terralod import open_store, read_heightfield

from conftest import fractal_terrain, terralod_cli


def real_cli(*args: str, cwd: Path | None = None, timeout: float = 300) -> subprocess.CompletedProcess:
    """``python -m terralod ARGS`` in a fresh process: the whole stderr of a real run."""
    return subprocess.run(
        [sys.executable, "-m", "terralod", *args], capture_output=True, text=True, cwd=cwd, timeout=timeout
    )


def run_cli(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    """The same command in this process (tests/conftest.py ``terralod_cli``): a process start saved."""
    return terralod_cli(*args, cwd=cwd)


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
    # a real process: its whole stderr is the one line (no warning, no log line at start-up or exit)
    assert_one_line_error(real_cli("build", str(missing), "-o", out), "missing.tif", "not found")
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
        assert s.meta["method"] == "adaptive"  # the default mesher (benchmarks/results/build.md)
        ladder = s.meta["build_options"]["target_error_m"]
        assert ladder[-1] == 0.0  # the lossless grid finest level
    # info states the ladder, the finest level as the grid
    line = next(x for x in p.stdout.splitlines() if x.startswith("target max vertical error per level"))
    assert line.endswith("0 (grid)") and line.split(": ", 1)[1].count(", ") == len(ladder) - 1


def test_demo_runs(tmp_path: Path) -> None:
    p = run_cli("demo", "--frames", "8", "--no-window", cwd=tmp_path)  # 8 frames: the video is not the point
    assert p.returncode == 0, p.stderr
    assert (tmp_path / "demo.mp4").stat().st_size > 0 and (tmp_path / "demo.png").exists()
    assert "jacksboro" in p.stdout and (tmp_path / "demo.terra").exists()
    with open_store(tmp_path / "demo.terra") as s:
        assert s.complete and len(s.tile_codes()) == len(s.pyramid.all_codes())
        assert "UTM zone 16N" in (s.crs or "")
        assert s.meta["method"] == "adaptive"


# The kill-and-resume test that lived here (a 1500x1400 build killed by polling wall-clock deadlines,
# ~100 s) is replaced by tests/test_kill.py: deterministic kill points (tile counts, hooks), seconds.


@pytest.mark.parametrize("name", ["dem/srtm3_N42E001.tif", "dem/kilauea_hawaii_30m_utm5.tif"])
def test_real_dem_cli_info(shared_data: Path, name: str) -> None:
    p = run_cli("info", str(shared_data / name))
    assert p.returncode == 0, p.stderr
    assert "none (local metric frame)" not in p.stdout
    crs = read_heightfield(shared_data / name).crs or ""
    assert "UTM" in crs or "Transverse_Mercator" in crs


def test_commands_registered_once_and_help_ends_with_an_example() -> None:
    """Issue 46: each command once in COMMANDS; every --help's last line is an example that runs terralod
    with that command; no help says "paper 00N"."""
    import re

    from click.testing import CliRunner

    from terralod.cli import COMMANDS, cli

    names = [name for _module, name in COMMANDS]
    assert len(names) == len(set(names)), names
    assert sorted(names) == sorted(cli.commands)
    for name in names:
        r = CliRunner().invoke(cli, [name, "--help"], terminal_width=200)
        assert r.exit_code == 0, (name, r.output)
        last = r.output.strip().splitlines()[-1].strip()
        assert last.startswith(f"Example: terralod {name}"), (name, last)
        assert not re.search(r"paper\s+00\d", r.output, re.IGNORECASE), name
