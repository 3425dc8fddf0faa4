"""Hostile file systems, for real: a full disk (a process file-size limit, and where this machine lets a
test mount one, a small tmpfs) and a read-only file system (a tmpfs remounted read-only). Every command
either works (reading needs no write access) or prints one line naming the file, exits 2 and leaves no
truncated output; a build stopped by a full disk keeps its committed tiles and ``--resume`` finishes it
into the tiles of an uninterrupted build. The commands run as real processes (``python -m terralod``).
"""

from __future__ import annotations

import os
import resource
import shutil
import signal
import sqlite3
import subprocess
import sys
import uuid
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import rasterio
from rasterio.transform import from_origin

from conftest import fractal_terrain, terralod_cli

pytestmark = pytest.mark.skipif(not hasattr(os, "fork"), reason="POSIX resource limits and mounts")

TILE = "17"


def _terralod(*args: str, cwd: Path, fsize: int | None = None) -> subprocess.CompletedProcess:
    """``terralod ARGS`` in ``cwd``: in a process of its own under a file-size limit of ``fsize`` bytes, else
    in this process (tests/conftest.py ``terralod_cli``; a full or read-only file system needs no process)."""
    if fsize is None:
        return terralod_cli(*args, cwd=cwd)

    def limit() -> None:  # a write past fsize bytes fails with EFBIG, as a full disk fails with ENOSPC
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (fsize, fsize))

    return subprocess.run(
        [sys.executable, "-m", "terralod", *args], cwd=cwd, capture_output=True, text=True, timeout=600,
        preexec_fn=limit,
    )  # fmt: skip


def _one_line(p: subprocess.CompletedProcess, *needles: str) -> str:
    assert p.returncode == 2, (p.returncode, p.stdout[-500:], p.stderr[-2000:])
    last = [ln for ln in p.stderr.splitlines() if ln.strip()][-1]
    assert last.startswith("terralod: "), p.stderr
    assert [ln for ln in p.stderr.splitlines() if ln.startswith("terralod: ")] == [last], p.stderr
    assert "Traceback" not in p.stderr, p.stderr
    for n in needles:
        assert n in last, (n, last)
    return last


def _rows(p: Path) -> list[tuple]:
    con = sqlite3.connect(f"file:{p}?mode=ro", uri=True)
    try:
        return con.execute("SELECT * FROM tiles ORDER BY level, x, y").fetchall()
    finally:
        con.close()


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("fs")
    z = fractal_terrain(200, 180, 3, relief_m=300.0).astype(np.float32)
    with rasterio.open(d / "dem.tif", "w", driver="GTiff", width=z.shape[1], height=z.shape[0], count=1,
                       dtype="float32", crs="EPSG:32610", transform=from_origin(500000, 5200000, 20, 20)) as ds:  # fmt: skip
        ds.write(z, 1)
    p = _terralod("build", "dem.tif", "-o", "ref.terra", "--tile-size", TILE, "--workers", "1", cwd=d)
    assert p.returncode == 0, p.stderr
    return d


def test_file_size_limit_build_stops_cleanly_and_resumes(site: Path, tmp_path: Path) -> None:
    shutil.copy(site / "dem.tif", tmp_path / "dem.tif")
    size = (site / "ref.terra").stat().st_size
    for i, limit in enumerate((20_000, size // 2)):  # before any tile is committed, and half-way
        out = f"b{i}.terra"
        p = _terralod(
            "build", "dem.tif", "-o", out, "--tile-size", TILE, "--workers", "1", cwd=tmp_path, fsize=limit
        )
        _one_line(p, out, "cannot write the store", "--resume")
        p = _terralod(
            "build", "dem.tif", "-o", out, "--tile-size", TILE, "--workers", "1", "--resume", cwd=tmp_path
        )
        assert p.returncode == 0, p.stderr
        assert _rows(tmp_path / out) == _rows(site / "ref.terra")
        p = _terralod("check", out, cwd=tmp_path)
        assert p.returncode == 0 and "verdict: sound" in p.stdout, p.stdout


def test_file_size_limit_outputs_leave_nothing_truncated(site: Path, tmp_path: Path) -> None:
    shutil.copy(site / "ref.terra", tmp_path / "s.terra")
    shutil.copy(site / "dem.tif", tmp_path / "dem.tif")
    before = sorted(os.listdir(tmp_path))
    for args, out in (
        (["render", "s.terra", "-o", "r.png", "--size", "320x240"], "r.png"),
        (["amplify", "dem.tif", "-o", "a.tif", "--factor", "2"], "a.tif"),
    ):
        _one_line(_terralod(*args, cwd=tmp_path, fsize=20_000), out)
        assert sorted(os.listdir(tmp_path)) == before, (
            args,
            os.listdir(tmp_path),
        )  # no truncated file, no temporary
    p = _terralod("export", "s.terra", "--format", "3dtiles", "-o", "web", cwd=tmp_path, fsize=2_000)
    _one_line(p)
    assert not (tmp_path / "web").exists() and not [f for f in os.listdir(tmp_path) if ".tmp-" in f]


def _can_mount() -> bool:
    return os.geteuid() == 0 and shutil.which("mount") is not None and shutil.which("umount") is not None


@pytest.fixture
def tmpfs(tmp_path: Path) -> Iterator[Path]:
    """A small tmpfs (1.5 MiB), unmounted after the test; skipped where this process cannot mount."""
    if not _can_mount():
        pytest.skip(
            "mounting a tmpfs needs root (a read-only and a really full file system are mounted for real)"
        )
    m = tmp_path / f"mnt-{uuid.uuid4().hex[:8]}"
    m.mkdir()
    p = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=1536k", "tmpfs", str(m)], capture_output=True, text=True
    )
    if p.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here ({p.stderr.strip() or p.returncode})")
    try:
        yield m
    finally:
        subprocess.run(["umount", "-l", str(m)], capture_output=True)


def test_read_only_file_system(site: Path, tmpfs: Path, tmp_path: Path) -> None:
    shutil.copy(site / "ref.terra", tmpfs / "s.terra")
    shutil.copy(site / "dem.tif", tmpfs / "dem.tif")
    p = subprocess.run(["mount", "-o", "remount,ro", str(tmpfs)], capture_output=True, text=True)
    if p.returncode != 0:
        pytest.skip(f"cannot remount read-only ({p.stderr.strip()})")
    before = sorted(os.listdir(tmpfs))
    # reading needs no write access, and leaves nothing (no -wal/-shm)
    for args in (["info", "s.terra"], ["check", "s.terra"],
                 ["build", "dem.tif", "-o", "s.terra", "--tile-size", TILE, "--resume"],
                 ["render", "s.terra", "-o", str(tmp_path / "r.png"), "--size", "320x240"]):  # fmt: skip
        p = _terralod(*args, cwd=tmpfs)
        assert p.returncode == 0, (args, p.stderr[-2000:])
    assert (tmp_path / "r.png").stat().st_size > 0
    # writing: one line naming the output, exit 2
    for args, needle in (
        (["build", "dem.tif", "-o", "n.terra", "--tile-size", TILE], "n.terra"),
        (["render", "s.terra", "-o", "r.png"], "r.png: Read-only file system"),
        (["amplify", "dem.tif", "-o", "a.tif"], "a.tif"),
        (["export", "s.terra", "--format", "quantized-mesh", "-o", "web"], "web"),
        (["update", "s.terra", "dem.tif", "--epoch", "2021-01-01"], "s.terra"),
    ):
        _one_line(_terralod(*args, cwd=tmpfs), needle)
    assert sorted(os.listdir(tmpfs)) == before


def test_full_file_system(site: Path, tmpfs: Path) -> None:
    """A tmpfs too small for the store: ENOSPC for real; the build says so in one line and resumes once
    there is room (the store moved to a roomier folder)."""
    shutil.copy(site / "dem.tif", tmpfs / "dem.tif")
    filler = tmpfs / "filler"
    free = shutil.disk_usage(tmpfs).free
    filler.write_bytes(b"\0" * max(0, free - (site / "ref.terra").stat().st_size // 2))
    p = _terralod("build", "dem.tif", "-o", "s.terra", "--tile-size", TILE, "--workers", "1", cwd=tmpfs)
    _one_line(p, "s.terra", "cannot write the store")
    p = _terralod("render", str(site / "ref.terra"), "-o", "r.png", "--size", "640x480", cwd=tmpfs)
    _one_line(p, "r.png")
    assert not (tmpfs / "r.png").exists()
    filler.unlink()
    p = _terralod(
        "build", "dem.tif", "-o", "s.terra", "--tile-size", TILE, "--workers", "1", "--resume", cwd=tmpfs
    )
    assert p.returncode == 0, p.stderr[-2000:]
    assert _rows(tmpfs / "s.terra") == _rows(site / "ref.terra")


def test_kernel_cache_write_failure_is_not_an_error(tmp_path: Path) -> None:
    """A cold numba cache on a full disk: the kernel compiles in memory and runs; the failed cache write
    is a logged warning (numba itself raises the OSError into the caller)."""
    code = (
        "import numpy as np\n"
        "from terralod.kernels.codec import undo_zigzag_delta\n"
        "z = np.array([0, 2, 1, 4], np.uint16)\n"
        "print(undo_zigzag_delta(z, 0xFFFF).tolist())\n"
    )

    def limit() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (64, 64))

    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "cold-cache")}
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, env=env,
                       preexec_fn=limit)  # fmt: skip
    assert p.returncode == 0, p.stderr[-2000:]
    assert p.stdout.strip() == "[0, 1, 0, 2]", p.stdout
