"""Kill tests: a build (or resume, or --overwrite) killed with SIGKILL at seeded random tile counts and at
every hook between its steps leaves either the old state or a store that opens and that ``--resume``
finishes into tiles identical to an uninterrupted build; a reader racing the writer sees only committed,
checksummed tiles. Kill points are tile counts and hooks (never wall-clock deadlines): the build runs in a
forked child that kills itself at the chosen point.
"""

from __future__ import annotations

import os
import random
import shutil
import signal
import sqlite3
import struct
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import rasterio
from rasterio.transform import from_origin

from terralod import build_store, open_store, read_heightfield
from terralod.integrity import check_store
from terralod.store import TileStore

from conftest import fractal_terrain

pytestmark = pytest.mark.skipif(not hasattr(os, "fork"), reason="kill tests fork the build (POSIX only)")

TILE = 9
METHOD = "chunked"
#: Seed of the random kill points (tile counts).
SEED = 20261201


def _tif(path: Path, seed: int) -> Path:
    z = fractal_terrain(120, 112, seed, relief_m=300.0).astype(np.float32)
    with rasterio.open(path, "w", driver="GTiff", width=z.shape[1], height=z.shape[0], count=1, dtype="float32",
                       crs="EPSG:32610", transform=from_origin(500000, 5200000, 20, 20)) as ds:  # fmt: skip
        ds.write(z, 1)
    return path


def _rows(p: Path) -> list[tuple]:
    con = sqlite3.connect(f"file:{p}?mode=ro", uri=True)
    try:
        return con.execute("SELECT * FROM tiles ORDER BY level, x, y").fetchall()
    finally:
        con.close()


def _die() -> None:
    os.kill(os.getpid(), signal.SIGKILL)


def _killed(fn: Callable[[], None]) -> None:
    """Run ``fn`` in a forked child that must die by SIGKILL (the hook fired)."""
    pid = os.fork()
    if pid == 0:  # child: never return into pytest
        try:
            fn()
        finally:
            os._exit(0)
    _, status = os.waitpid(pid, 0)
    assert os.WIFSIGNALED(status) and os.WTERMSIG(status) == signal.SIGKILL, "the kill point was not reached"


def _build_killed_at_tiles(hf, out: Path, n: int, **kw) -> None:
    def cb(done: int, total: int) -> None:
        if done >= n and done > 0:
            _die()

    _killed(lambda: build_store(hf, out, tile_size=TILE, method=METHOD, workers=1, progress=cb, **kw))


def _build_killed_at_hook(hf, out: Path, hook: str, **kw) -> None:
    import terralod.pyramid.builder as builder
    import terralod.store as store

    def run() -> None:
        if hook == "before_link":  # schema and metadata committed to the temporary, not yet in place
            store._link_into_place = lambda tmp, p: _die()
        elif hook == "after_link":  # in place, no tile yet
            orig = store._link_into_place
            store._link_into_place = lambda tmp, p: (orig(tmp, p), _die())
        elif hook == "complete":  # every tile committed, the complete flag not yet
            orig_set = TileStore.set_meta
            TileStore.set_meta = lambda self, k, v: _die() if k == "complete" else orig_set(self, k, v)
        elif hook == "before_install":  # --overwrite: the new store complete beside the old one
            builder.install_store = lambda new, p: _die()
        build_store(hf, out, tile_size=TILE, method=METHOD, workers=1, **kw)

    _killed(run)


def _no_temporaries(folder: Path) -> bool:
    return not [f for f in folder.iterdir() if f.name.endswith(".tmp")]


@pytest.fixture(scope="module")
def dems(tmp_path_factory: pytest.TempPathFactory):
    d = tmp_path_factory.mktemp("kill")
    src, other = _tif(d / "dem.tif", 5), _tif(d / "other.tif", 6)
    hf, hf_other = read_heightfield(src), read_heightfield(other)
    ref = d / "ref.terra"
    build_store(hf, ref, tile_size=TILE, method=METHOD, workers=1)
    old = d / "old.terra"
    build_store(hf_other, old, tile_size=TILE, method=METHOD, workers=1)
    return hf, hf_other, src, ref, old, _rows(ref), _rows(old)


def test_kill_build_at_random_tile_counts_then_resume(dems, tmp_path: Path) -> None:
    hf, _, _, ref, _, ref_rows, _ = dems
    total = len(ref_rows)
    rng = random.Random(SEED)
    for n in sorted(rng.sample(range(1, total), 3)):
        out = tmp_path / f"k{n}.terra"
        _build_killed_at_tiles(hf, out, n)
        with open_store(out) as s:  # opens: every committed tile, each passing its checksum
            assert not s.complete
            done = len(s.tile_codes())
            assert n <= done < total and s.verify() == []
        rep = check_store(out)
        assert len(rep.problems) == 1 and "incomplete" in rep.problems[0], rep.problems
        # kill the resume too, then finish it
        _build_killed_at_tiles(hf, out, done + 1, resume=True)
        rep = build_store(hf, out, tile_size=TILE, method=METHOD, workers=1, resume=True)
        assert rep.tiles_built + rep.tiles_skipped == total
        assert _rows(out) == ref_rows
        assert check_store(out).sound
        assert not Path(f"{out}-wal").exists() and not Path(f"{out}-shm").exists()


@pytest.mark.parametrize("hook", ["before_link", "after_link", "complete"])
def test_kill_at_each_step_of_creation(dems, tmp_path: Path, hook: str) -> None:
    hf, _, _, _, _, ref_rows, _ = dems
    out = tmp_path / "h.terra"
    _build_killed_at_hook(hf, out, hook)
    if hook == "before_link":  # never a 0-byte or half-made store at the name: nothing, or a whole one
        assert not out.exists()
        build_store(hf, out, tile_size=TILE, method=METHOD, workers=1)
    else:
        with open_store(out) as s:
            assert not s.complete and s.verify() == []
        build_store(hf, out, tile_size=TILE, method=METHOD, workers=1, resume=True)
    assert _rows(out) == ref_rows and check_store(out).sound
    assert _no_temporaries(tmp_path)  # the dead child's temporary was swept


@pytest.mark.parametrize("point", ["tiles", "before_install"])
def test_kill_during_overwrite_keeps_the_old_store(dems, tmp_path: Path, point: str) -> None:
    hf, _, _, _, old, ref_rows, old_rows = dems
    out = tmp_path / "o.terra"
    out.write_bytes(old.read_bytes())
    if point == "tiles":
        _build_killed_at_tiles(hf, out, len(ref_rows) // 2, overwrite=True)
    else:
        _build_killed_at_hook(hf, out, "before_install", overwrite=True)
    assert _rows(out) == old_rows and check_store(out).sound  # the old state, whole
    build_store(hf, out, tile_size=TILE, method=METHOD, workers=1, overwrite=True)
    assert _rows(out) == ref_rows and check_store(out).sound
    assert _no_temporaries(tmp_path)


def test_cli_resume_after_kill(dems, tmp_path: Path) -> None:
    """The command line finishes a killed build (``terralod build --resume``) identically."""
    hf, _, src, _, _, ref_rows, _ = dems
    out = tmp_path / "cli.terra"
    _build_killed_at_tiles(hf, out, len(ref_rows) // 3)
    p = subprocess.run(
        [sys.executable, "-m", "terralod", "build", str(src), "-o", str(out), "--tile-size", str(TILE),
         "--method", METHOD, "--resume"], capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert p.returncode == 0, p.stderr
    assert _rows(out) == ref_rows


class _PausingConnection:
    """Delegates to a connection; before each commit (``with conn:``) it tells the reader how many tiles
    are committed so far and waits until the reader has looked."""

    def __init__(self, conn: sqlite3.Connection, w: int, r: int, committed: int) -> None:
        self._c, self._w, self._r, self._n = conn, w, r, committed

    def __getattr__(self, name: str):
        return getattr(self._c, name)

    def __enter__(self):
        self._c.__enter__()
        return self

    def __exit__(self, *exc):
        if exc[0] is None:
            os.write(self._w, struct.pack("<i", self._n))  # rows written, transaction open
            os.read(self._r, 1)  # the reader has looked
        return self._c.__exit__(*exc)


def test_reader_racing_the_writer_sees_only_committed_tiles(dems, tmp_path: Path) -> None:
    hf, _, _, _, _, ref_rows, _ = dems
    out = tmp_path / "race.terra"
    to_parent_r, to_parent_w = os.pipe()
    to_child_r, to_child_w = os.pipe()
    pid = os.fork()
    if pid == 0:
        try:
            orig = TileStore.write_tiles
            committed = [0]

            def write_tiles(self, tiles):
                real = self._conn
                self._conn = _PausingConnection(real, to_parent_w, to_child_r, committed[0])
                try:
                    orig(self, tiles)
                finally:
                    self._conn = real
                committed[0] += len(tiles)

            TileStore.write_tiles = write_tiles
            build_store(hf, out, tile_size=TILE, method=METHOD, workers=1)
        finally:
            os._exit(0)
    os.close(to_parent_w)
    os.close(to_child_r)
    seen = []
    while len(msg := os.read(to_parent_r, 4)) == 4:  # the writer holds an open transaction with a batch
        (committed,) = struct.unpack("<i", msg)
        with open_store(out) as s:  # metadata checksum verified on open
            assert len(s.tile_codes()) == committed  # the open batch is invisible
            assert s.verify() == []  # every visible tile complete and checksummed
        seen.append(committed)
        os.write(to_child_w, b"g")
    os.waitpid(pid, 0)
    assert len(seen) >= 3 and seen == sorted(seen) and seen[-1] < len(ref_rows), seen
    assert _rows(out) == ref_rows


# -- a killed export ----------------------------------------------------------------------------------------
def _tree(d: Path) -> dict[str, bytes]:
    return {str(f.relative_to(d)): f.read_bytes() for f in sorted(d.rglob("*")) if f.is_file()}


def _export(store: Path, out: Path, fmt: str, overwrite: bool = False, progress=None) -> None:
    from terralod.export import export_3dtiles, export_quantized_mesh
    from terralod.terrain import open_terrain

    fn = export_3dtiles if fmt == "3dtiles" else export_quantized_mesh
    with open_terrain(store) as t:
        fn(t, out, overwrite=overwrite, progress=progress)


def _export_killed_at(store: Path, out: Path, fmt: str, n: int, overwrite: bool) -> None:
    def cb(done: int, total: int) -> None:
        if done >= n:
            _die()

    _killed(lambda: _export(store, out, fmt, overwrite, cb))


def _export_killed_between_renames(store: Path, out: Path, fmt: str) -> None:
    def run() -> None:
        real = os.replace

        def replace(a, b):  # the old output set aside, then killed before the new one is renamed in
            real(a, b)
            if Path(b).name == "old":  # the swap's first rename (terralod.output.Output)
                _die()

        os.replace = replace
        _export(store, out, fmt, True)

    _killed(run)


@pytest.mark.parametrize("fmt", ["3dtiles", "quantized-mesh"])
def test_kill_export_at_random_points(dems, tmp_path: Path, fmt: str) -> None:
    """An export killed at seeded random tiles, fresh or replacing an earlier export, leaves nothing or the
    old output under the output name; running it again gives the uninterrupted export's bytes."""
    from terralod.output import restore_set_aside

    _, _, _, ref, old, _, _ = dems
    want, earlier = tmp_path / "want", tmp_path / "earlier"
    totals: list[int] = []
    _export(ref, want, fmt, progress=lambda d, t: totals.append(t))
    _export(old, earlier, fmt)
    want_tree, earlier_tree = _tree(want), _tree(earlier)
    assert want_tree != earlier_tree and totals
    rng = random.Random(SEED + len(fmt))
    for i, n in enumerate(sorted(rng.sample(range(1, totals[-1]), 2))):
        fresh = tmp_path / f"fresh{i}"
        _export_killed_at(ref, fresh, fmt, n, overwrite=False)
        assert not fresh.exists()  # nothing half-written under the name
        _export(ref, fresh, fmt)
        assert _tree(fresh) == want_tree
        replaced = tmp_path / f"replaced{i}"
        shutil.copytree(earlier, replaced)
        _export_killed_at(ref, replaced, fmt, n, overwrite=True)
        assert _tree(replaced) == earlier_tree  # the old output, whole
        _export(ref, replaced, fmt, overwrite=True)
        assert _tree(replaced) == want_tree
    # killed between setting the old output aside and renaming the new one in: the old one comes back
    between = tmp_path / "between"
    shutil.copytree(earlier, between)
    _export_killed_between_renames(ref, between, fmt)
    assert not between.exists()
    assert restore_set_aside(between)  # what every export does first
    assert _tree(between) == earlier_tree
    _export(ref, between, fmt, overwrite=True)
    assert _tree(between) == want_tree
    assert not [f for f in tmp_path.iterdir() if f.name.endswith((".work", ".tmp"))]  # temporaries swept
