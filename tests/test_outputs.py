"""The one way outputs are written (terralod.output): the input guard, the work folder and its lock, resume,
update, the swap; and an export killed mid-way then resumed gives the uninterrupted export's bytes."""

from __future__ import annotations

import hashlib
import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from terralod.errors import InputError, OutputBusyError
from terralod.output import Lock, Output, check_target, refuse_inputs, restore_set_aside, work_path

from conftest import terralod_cli

posix = pytest.mark.skipif(os.name != "posix", reason="process ids and SIGKILL")


def _tree(d: Path) -> dict[str, str]:
    """Every file of ``d`` (relative path → SHA-256)."""
    return {f.relative_to(d).as_posix(): hashlib.sha256(f.read_bytes()).hexdigest()
            for f in sorted(d.rglob("*")) if f.is_file()}  # fmt: skip


def _dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def _plant(target: Path, pid: int, files: dict[str, bytes], key: object = None, records: bool = True) -> Path:
    """A work folder as a run of ``pid`` would leave it: lock, finished files, their journal."""
    work = work_path(target)
    (work / "out").mkdir(parents=True)
    k = None if key is None else json.dumps(key, sort_keys=True, separators=(",", ":"))
    Lock(pid, socket.gethostname(), "2024-01-01T00:00:00+00:00", "terralod export", None, k).write(work)
    with open(work / "journal.jsonl", "w") as fh:
        for rel, data in files.items():
            (work / "out" / rel).parent.mkdir(parents=True, exist_ok=True)
            (work / "out" / rel).write_bytes(data)
            if records:
                fh.write(json.dumps({"path": rel, "record": {"n": len(data)}, "changed": True}) + "\n")
        fh.write('{"path": "half')  # a kill in the middle of a line
    return work


# -- the input guard ---------------------------------------------------------------------------------------
def test_input_guard_refuses_an_output_on_in_or_around_an_input(tmp_path: Path) -> None:
    site = tmp_path / "site"
    (site / "deep").mkdir(parents=True)
    store = site / "deep" / "s.terra"
    store.write_bytes(b"x")
    link = tmp_path / "link.terra"
    os.link(store, link)
    for out, words in ((store, "is (or holds) the input"), (site, "is (or holds) the input"),
                       (link, "is (or holds) the input"), (store / "web", "lies inside the input"),
                       (site / "deep" / "s.json", "sidecar")):  # fmt: skip
        with pytest.raises(InputError, match=r"\(or holds\)|inside|sidecar") as exc:
            refuse_inputs(out, [store])
        assert words in str(exc.value) and str(out) in str(exc.value) and "\n" not in str(exc.value)
        with pytest.raises(InputError):  # whatever overwrite says
            with Output(out, inputs=[store], overwrite=True):
                pass
    refuse_inputs(tmp_path / "web", [store])  # beside it: fine
    assert sorted(p.name for p in tmp_path.iterdir()) == ["link.terra", "site"]  # nothing written


def test_file_target_rule(tmp_path: Path) -> None:
    src = tmp_path / "dem.tif"
    src.write_bytes(b"x")
    with pytest.raises(InputError, match="must end in .png"):
        check_target(tmp_path / "a.jpg", [src], suffixes=(".png",), what="image")
    with pytest.raises(InputError, match="is \\(or holds\\) the input"):
        check_target(src, [src], overwrite=True)
    (tmp_path / "a.png").write_bytes(b"old")
    with pytest.raises(InputError, match="--overwrite"):
        check_target(tmp_path / "a.png", [src])
    assert check_target(tmp_path / "a.png", [src], overwrite=True) == tmp_path / "a.png"
    with pytest.raises(InputError, match="does not exist"):
        check_target(tmp_path / "no" / "a.png", [src])


# -- the work folder, the lock, the swap ------------------------------------------------------------------
def test_swap_writes_whole_and_replaces_only_with_overwrite(tmp_path: Path) -> None:
    out = tmp_path / "web"
    with Output(out) as o:
        assert o.write("a/1.bin", b"one") and not out.exists()
        (o.folder / "layer.json").write_text("{}")
    assert _tree(out) == _tree(out) and (out / "a" / "1.bin").read_bytes() == b"one"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["web"]  # no work folder, no temporary
    with pytest.raises(InputError, match="--overwrite"):
        with Output(out):
            pass
    with pytest.raises(RuntimeError, match="boom"):
        with Output(out, overwrite=True) as o:
            o.write("b", b"two")
            raise RuntimeError("boom")
    assert (out / "a" / "1.bin").read_bytes() == b"one" and not work_path(out).exists()
    with Output(out, overwrite=True) as o:
        o.write("b", b"two")
    assert _tree(out) == {"b": hashlib.sha256(b"two").hexdigest()}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["web"]


@posix
def test_a_live_lock_is_never_touched(tmp_path: Path) -> None:
    out = tmp_path / "web"
    live = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        work = _plant(out, live.pid, {"0/0/0.terrain": b"tile"})
        before = _tree(work)
        for resume in (False, True):
            with pytest.raises(OutputBusyError) as exc:
                with Output(out, resume=resume, overwrite=True):
                    pass
            msg = str(exc.value)
            assert f"pid {live.pid}" in msg and str(out) in msg and "\n" not in msg
        assert _tree(work) == before and not out.exists()
    finally:
        live.kill()
        live.wait()
    # the same process id reused by a later process (another start time) is not the writer
    Lock(os.getpid(), socket.gethostname(), "x", "y", "not-my-start").write(work)
    with Output(out) as o:
        o.write("x", b"x")
    assert _tree(out) == {"x": hashlib.sha256(b"x").hexdigest()}


@posix
def test_a_dead_lock_is_adopted_with_resume_and_replaced_without(tmp_path: Path) -> None:
    out = tmp_path / "web"
    key = {"format": "quantized-mesh", "gzip": False}
    _plant(out, _dead_pid(), {"0/0/0.terrain": b"done", "0/1/0.terrain": b"also"}, key=key)
    (work_path(out) / "out" / "0" / f".2.terrain.{_dead_pid()}.tmp").write_bytes(b"half")
    (work_path(out) / "out" / "0" / "1" / "1.terrain").write_bytes(b"no journal line: not done")
    with Output(out, resume=True, key=key) as o:
        assert o.adopted is not None and o.adopted.command == "terralod export"
        assert o.done("0/0/0.terrain") and o.record("0/0/0.terrain") == {"n": 4}
        assert not o.done("0/1/1.terrain") and not o.done("half") and o.record("9/9/9.terrain") is None
        o.write("0/1/1.terrain", b"new")
        assert Lock.read(work_path(out)).pid == os.getpid()  # type: ignore[union-attr]
    assert sorted(_tree(out)) == ["0/0/0.terrain", "0/1/0.terrain", "0/1/1.terrain"]  # temporaries gone
    assert (out / "0" / "0" / "0.terrain").read_bytes() == b"done"
    # without resume: replaced, nothing of the dead run's kept
    other = tmp_path / "other"
    _plant(other, _dead_pid(), {"0/0/0.terrain": b"done"}, key=key)
    with Output(other, key=key) as o:
        assert o.adopted is None and not o.done("0/0/0.terrain")
        o.write("z", b"z")
    assert sorted(_tree(other)) == ["z"]
    # resume of another key (options, input): refused, the work folder left as it was
    third = tmp_path / "third"
    work = _plant(third, _dead_pid(), {"0/0/0.terrain": b"done"}, key=key)
    before = _tree(work)
    with pytest.raises(InputError, match="without --resume"):
        with Output(third, resume=True, key={**key, "gzip": True}):
            pass
    assert _tree(work) == before


def test_an_error_keeps_a_resumable_work_folder_released(tmp_path: Path) -> None:
    out = tmp_path / "web"
    with pytest.raises(KeyboardInterrupt):
        with Output(out, key="k") as o:
            o.write("a", b"a", {"e": 0.1})
            raise KeyboardInterrupt
    lock = Lock.read(work_path(out))
    assert lock is not None and lock.released and not lock.alive() and not out.exists()
    with Output(out, key="k", resume=True) as o:  # the same process resumes it
        assert o.done("a") and o.record("a") == {"e": 0.1}
        o.write("b", b"b")
    assert sorted(_tree(out)) == ["a", "b"]


@posix
def test_a_kill_between_the_swaps_renames_puts_the_old_output_back(tmp_path: Path) -> None:
    out = tmp_path / "web"
    out.mkdir()
    (out / "old.txt").write_text("old")
    work = _plant(out, _dead_pid(), {"new.txt": b"new"})
    os.replace(out, work / "old")  # what the swap's first rename did before the kill
    assert restore_set_aside(out) and (out / "old.txt").read_text() == "old"
    assert not restore_set_aside(out)  # once
    with Output(out, overwrite=True) as o:  # the next run replaces the dead work folder
        o.write("n", b"n")
    assert sorted(_tree(out)) == ["n"] and not work.exists()


# -- update ------------------------------------------------------------------------------------------------
def test_update_rewrites_only_changed_files_and_leaves_the_others_untouched(tmp_path: Path) -> None:
    out = tmp_path / "web"
    with Output(out) as o:
        for i in range(5):
            o.write(f"t/{i}.bin", bytes([i]) * 100)
        o.write("layer.json", b"{}")
    past = time.time() - 3600
    for f in out.rglob("*.bin"):
        os.utime(f, (past, past))
    seen = {
        f.relative_to(out).as_posix(): (f.stat().st_ino, f.stat().st_mtime_ns) for f in out.rglob("*.bin")
    }
    with Output(out, update=True) as o:
        assert not o.done("t/0.bin")  # a file of the old output is not one this run finished
        for i in range(5):
            o.write(f"t/{i}.bin", bytes([i]) * (101 if i == 3 else 100))
        o.write("t/new.bin", b"new")
        assert o.prune() == ["layer.json"]  # what the new output no longer has
        rewritten = list(o.rewritten)
    assert rewritten == ["t/3.bin", "t/new.bin"]
    now = {f.relative_to(out).as_posix(): (f.stat().st_ino, f.stat().st_mtime_ns) for f in out.rglob("*.bin")}
    for rel, was in seen.items():
        assert (now[rel] == was) == (rel != "t/3.bin"), rel  # same inode and mtime unless rewritten
    assert (out / "t" / "3.bin").read_bytes() == bytes([3]) * 101 and not (out / "layer.json").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["web"]
    with pytest.raises(InputError, match="nothing to update"):
        with Output(tmp_path / "missing", update=True):
            pass


@posix
def test_a_resumed_update_keeps_what_the_dead_run_wrote(tmp_path: Path) -> None:
    out = tmp_path / "web"
    with Output(out) as o:
        o.write("a", b"a")
        o.write("b", b"b")
        o.write("gone", b"x")
    work = _plant(tmp_path / "web", _dead_pid(), {"a": b"A"}, key="k")  # an update run killed after "a"
    for f in ("b", "gone"):
        os.link(out / f, work / "out" / f)
    with Output(out, update=True, resume=True, key="k") as o:
        assert o.done("a") and not o.done("b")
        o.write("b", b"b")
        assert o.prune() == ["gone"] and o.rewritten == ["a"]
    assert _tree(out) == {"a": hashlib.sha256(b"A").hexdigest(), "b": hashlib.sha256(b"b").hexdigest()}


# -- an export killed, then resumed --------------------------------------------------------------------------
def _small_dem(path: Path) -> Path:
    """A 200 x 200 georeferenced GeoTIFF (UTM 31N, 30 m): a smooth hill, no file of /work/shared needed."""
    import rasterio
    from affine import Affine

    y, x = np.mgrid[0:200, 0:200].astype(np.float32)
    z = (
        400.0
        + 150.0 * np.exp(-((x - 90) ** 2 + (y - 110) ** 2) / 3000.0)
        + 5.0 * np.sin(x / 7.0) * np.cos(y / 9.0)
    )
    with rasterio.open(path, "w", driver="GTiff", width=200, height=200, count=1, dtype="float32",
                       crs="EPSG:32631", transform=Affine(30.0, 0, 400000.0, 0, -30.0, 4600000.0)) as dst:  # fmt: skip
        dst.write(z.astype(np.float32), 1)
    return path


def _terralod(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    """``terralod ARGS`` in this process (tests/conftest.py ``terralod_cli``); the kill below runs a real one."""
    return terralod_cli(*args, cwd=cwd)


@posix
@pytest.mark.parametrize("fmt", ["quantized-mesh", "3dtiles"])
def test_export_killed_then_resumed_gives_the_uninterrupted_bytes(tmp_path: Path, fmt: str) -> None:
    pytest.importorskip("pydelatin")
    pytest.importorskip("pyproj")
    dem = _small_dem(tmp_path / "small.tif")
    src = str(dem)
    if fmt == "3dtiles":
        p = _terralod("build", src, "-o", "s.terra", cwd=tmp_path)
        assert p.returncode == 0, p.stderr
        src = "s.terra"
    p = _terralod("export", src, "--format", fmt, "-o", "want", cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    want = _tree(tmp_path / "want")
    tiles = [f for f in want if f.endswith((".terrain", ".glb"))]
    assert len(tiles) > 8
    # killed (SIGKILL) once a few tiles are in the work folder
    work = tmp_path / ".out.work" / "out"
    proc = subprocess.Popen([sys.executable, "-m", "terralod", "export", src, "--format", fmt, "-o", "out"],
                            cwd=tmp_path, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # fmt: skip
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline and proc.poll() is None:
        if work.is_dir() and sum(1 for f in work.rglob("*") if f.suffix in (".terrain", ".glb")) >= 4:
            break
        time.sleep(0.005)
    if proc.poll() is not None:
        pytest.skip("the export finished before it could be killed")
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert not (tmp_path / "out").exists()
    finished = sum(1 for f in work.rglob("*") if f.suffix in (".terrain", ".glb"))
    assert 4 <= finished < len(tiles)
    kept = {f: f.stat().st_ino for f in work.rglob("*") if f.suffix in (".terrain", ".glb")}
    p = _terralod("export", src, "--format", fmt, "-o", "out", "--resume", cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    assert "resum" in p.stdout + p.stderr
    assert _tree(tmp_path / "out") == want  # byte for byte the uninterrupted export
    assert not (tmp_path / ".out.work").exists()
    out = tmp_path / "out"
    reused = [f for f, ino in kept.items() if (out / f.relative_to(work)).stat().st_ino == ino]
    assert len(reused) >= len(kept) - 1  # the finished tiles were kept, not encoded again


# -- export --update after terralod update ---------------------------------------------------------------
def _dem_with_bump(src: Path, dst: Path) -> Path:
    """``src`` with a 20 m mound in one corner (the rest byte for byte the same)."""
    import rasterio

    with rasterio.open(src) as s:
        profile, z = s.profile, s.read(1)
    y, x = np.mgrid[0 : z.shape[0], 0 : z.shape[1]]
    z = z + (20.0 * np.exp(-((x - 30) ** 2 + (y - 30) ** 2) / 80.0)).astype(np.float32)
    with rasterio.open(dst, "w", **profile) as d:
        d.write(z, 1)
    return dst


@pytest.mark.parametrize("fmt", ["quantized-mesh", "3dtiles"])
def test_export_update_rewrites_only_the_changed_tiles(tmp_path: Path, fmt: str) -> None:
    pytest.importorskip("pydelatin")
    pytest.importorskip("pyproj")
    dem = _small_dem(tmp_path / "small.tif")
    _dem_with_bump(dem, tmp_path / "later.tif")
    for args in (["build", "small.tif", "-o", "s.terra", "--epoch", "2000-01-01"],
                 ["export", "s.terra", "--format", fmt, "-o", "web"],
                 ["update", "s.terra", "later.tif", "--epoch", "2001-01-01"],
                 ["export", "s.terra", "--format", fmt, "-o", "want"]):  # fmt: skip
        p = _terralod(*args, cwd=tmp_path)
        assert p.returncode == 0, (args, p.stderr)
    web = tmp_path / "web"
    old = _tree(web)
    want = _tree(tmp_path / "want")
    changed = sorted(f for f in want if old.get(f) != want[f])
    assert 0 < len(changed) < len(want) // 2  # a local change: most tiles are the same
    past = time.time() - 3600
    for f in web.rglob("*"):
        if f.is_file():
            os.utime(f, (past, past))
    seen = {f: (p.stat().st_ino, p.stat().st_mtime_ns) for f in old if (p := web / f).is_file()}
    p = _terralod("export", "s.terra", "--format", fmt, "-o", "web", "--update", cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    assert _tree(web) == want  # the updated output is the fresh export, byte for byte
    printed = sorted(
        line.split()[-1] for line in p.stdout.splitlines() if line.strip().startswith("rewritten ")
    )
    assert printed == changed, p.stdout
    assert f"{len(changed)} file(s) rewritten, 0 removed" in p.stdout
    for f, was in seen.items():
        now = ((web / f).stat().st_ino, (web / f).stat().st_mtime_ns)
        assert (now == was) == (f not in changed), f  # unchanged files: same inode, same mtime
    assert sorted(x.name for x in tmp_path.iterdir() if x.name.startswith(".")) == []  # no work folder left
