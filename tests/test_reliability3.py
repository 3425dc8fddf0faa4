"""Nothing lost, nothing silently wrong, round three (issue 48, the rest of items 2 and 5): what a killed
``change`` leaves beside its output, the exact command ``check`` gives for an interrupted update or edit, an
edit rerun after it committed, rasters wider than the 16-bit lattice of a tile at the coarse levels, a
DEM too large for memory, and ``export`` straight from a DEM under the one size limit. Every kill is real
(SIGKILL or ``os._exit`` in a child process, no clean-up), at a point reached by the code, never by a clock.
"""

from __future__ import annotations

import collections
import json
import os
import shlex
import shutil
import signal
import sqlite3
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import rasterio
from affine import Affine

from terralod import build_store, open_store
from terralod.heightfield import Heightfield
from terralod.integrity import check_store

from conftest import fractal_terrain, terralod_cli

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "change"
BEFORE = DATA / "st_helens_crater_2000-09-25_10m.tif"
AFTER = DATA / "st_helens_crater_2007-07-05_10m.tif"
needs_data = pytest.mark.skipif(not BEFORE.exists(), reason="../shared/data (St Helens pair) is absent")
posix = pytest.mark.skipif(not hasattr(os, "fork"), reason="kills and memory limits are POSIX only")

CRS = "EPSG:32610"
ORIGIN = (500000.0, 5200000.0)


def terralod(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    """``terralod ARGS`` in this process (tests/conftest.py ``terralod_cli``)."""
    return terralod_cli(*args, cwd=cwd)


def terralod_process(*args: str, **kw) -> subprocess.CompletedProcess[str]:
    """``terralod ARGS`` in a process of its own (a memory limit, a pid that is not this one)."""
    return subprocess.run([sys.executable, "-m", "terralod", *args], capture_output=True, text=True,
                          timeout=600, **kw)  # fmt: skip


def python(code: str) -> subprocess.CompletedProcess[str]:
    """``code`` in a fresh interpreter (where the kill happens)."""
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600)


def _errors(p: subprocess.CompletedProcess) -> list[str]:
    """stderr lines that are not a progress bar."""
    return [ln for ln in p.stderr.strip().splitlines() if ln.startswith("terralod")]


def _hf(z: np.ndarray, spacing: float = 10.0) -> Heightfield:
    t = Affine(spacing, 0, ORIGIN[0], 0, -spacing, ORIGIN[1])
    return Heightfield(z.astype(np.float32), np.ones(z.shape, bool), t, CRS, "<array>")


def _tif(path: Path, z: np.ndarray, crs: str = CRS, transform: Affine | None = None) -> Path:
    t = transform or Affine(10.0, 0, ORIGIN[0], 0, -10.0, ORIGIN[1])
    with rasterio.open(path, "w", driver="GTiff", width=z.shape[1], height=z.shape[0], count=1, dtype="float32",
                       crs=crs, transform=t) as ds:  # fmt: skip
        ds.write(z.astype(np.float32), 1)
    return path


def _square(path: Path, x0: float, y0: float, side: float) -> Path:
    ring = [[x0, y0], [x0 + side, y0], [x0 + side, y0 + side], [x0, y0 + side], [x0, y0]]
    path.write_text(json.dumps({
        "type": "FeatureCollection", "crs": {"type": "name", "properties": {"name": CRS}},
        "features": [{"type": "Feature", "properties": {"name": "pit"},
                      "geometry": {"type": "Polygon", "coordinates": [ring]}}]}))  # fmt: skip
    return path


def _epochs(store: Path) -> list[tuple[str, str]]:
    con = sqlite3.connect(f"file:{store}?mode=ro", uri=True)
    try:
        return [(str(n), str(s)) for n, s in con.execute("SELECT name, state FROM epochs ORDER BY id")]
    finally:
        con.close()


def _tiles(store: Path, epoch: str | None = None) -> dict:
    with open_store(store, epoch=epoch) as s:
        return {c: s.raw_tile(*c) for c in s.tile_codes()}


@pytest.fixture(scope="module")
def base_store(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, np.ndarray]:
    out = tmp_path_factory.mktemp("r3") / "base.terra"
    z = fractal_terrain(97, 113, 5, relief_m=300.0) + 1000.0
    build_store(_hf(z), out, tile_size=17, epoch="2000-01-01", workers=2)
    return out, z


# -- 48.5: a killed change leaves no temporary folder for ever ------------------------------------------------
@needs_data
@posix
def test_killed_change_temporaries_are_cleaned_and_live_ones_kept(tmp_path: Path) -> None:
    from terralod.output import Lock, work_path

    out = tmp_path / "c"
    # a real kill (SIGKILL) while the output is being written into its work folder
    code = (
        "import os, signal\n"
        "import terralod.change.report as report\n"
        "def die(*a, **k): os.kill(os.getpid(), signal.SIGKILL)\n"
        "report.write_report = die\n"
        "from terralod.cli import main\n"
        f"main(['change', {str(BEFORE)!r}, {str(AFTER)!r}, '-o', {str(out)!r}, '--no-views'])\n"
    )
    p = python(code)
    assert p.returncode == -signal.SIGKILL, p.stderr[-2000:]
    work = work_path(out)
    assert (work / "out" / "dod.tif").is_file()  # what the kill left
    other = tmp_path / ".c.tmp-notapid"  # a folder that is no one's temporary
    other.mkdir()
    p = terralod("change", str(BEFORE), str(AFTER), "-o", str(out), "--no-views")
    assert p.returncode == 0, p.stderr
    assert not work.exists()  # the dead run's work folder is gone
    assert json.loads((out / "summary.json").read_text())["net_m3"] != 0
    assert sorted(x.name for x in tmp_path.iterdir()) == sorted(["c", other.name])
    # a run in progress (this very process is alive): its work folder is never touched, the run refused
    live = tmp_path / "d"
    (work_path(live) / "out").mkdir(parents=True)
    (work_path(live) / "out" / "summary.json").write_text("{}")
    Lock.mine(None, "terralod change (live)").write(work_path(live))
    p = terralod_process("change", str(BEFORE), str(AFTER), "-o", str(live), "--no-views")
    assert p.returncode == 2 and len(p.stderr.strip().splitlines()) == 1, p.stderr
    assert f"pid {os.getpid()}" in p.stderr and "being written" in p.stderr
    assert (work_path(live) / "out" / "summary.json").read_text() == "{}" and not live.exists()


# -- 48.5: check names the exact command that finishes an interrupted update or edit -----------------------
def _advice(store: Path) -> list[str]:
    """The commands ``terralod check`` gives for the store's unfinished epochs (it exits 2)."""
    p = terralod("check", str(store))
    assert p.returncode == 2, p.stdout + p.stderr
    lines = [ln for ln in p.stdout.splitlines() if "unfinished" in ln]
    assert lines, p.stdout
    cmds = []
    for ln in lines:
        assert "`" in ln, f"no command in {ln!r}"
        cmds.append(ln.split("`")[1])
    return cmds


def _run_advice(cmd: str) -> subprocess.CompletedProcess[str]:
    argv = shlex.split(cmd)
    assert argv[0] == "terralod", cmd
    return terralod(*argv[1:])


@posix
def test_check_gives_the_command_that_finishes_a_killed_update(base_store, tmp_path: Path) -> None:
    src, z = base_store
    store, ref = tmp_path / "k.terra", tmp_path / "ref.terra"
    shutil.copy(src, store)
    shutil.copy(src, ref)
    z2 = z.copy()
    z2[10:60, 10:80] += 25.0
    dem = _tif(tmp_path / "after 2002.tif", z2)  # a space in the name: the command quotes it
    p = python(
        "import os\n"
        "from terralod.io.reader import read_heightfield\n"
        "from terralod.pyramid.update import update_store\n"
        "def cb(done, total):\n"
        "    if done >= 16: os._exit(9)\n"
        f"update_store(read_heightfield({str(dem)!r}), {str(store)!r}, '2002-02-02', progress=cb, workers=2)\n"
    )
    assert p.returncode == 9, p.stderr[-2000:]
    assert _epochs(store) == [("2000-01-01", "complete"), ("2002-02-02", "building")]
    # a plain rerun refuses, so the advice cannot be "rerun the update": it is the command that works
    (cmd,) = _advice(store)
    assert cmd.startswith("terralod update ") and "--resume" in cmd and "2002-02-02" in cmd
    plain = terralod("update", str(store), str(dem), "--epoch", "2002-02-02")  # refused, with the same advice
    assert plain.returncode == 2 and len(_errors(plain)) == 1 and f"`{cmd}`" in _errors(plain)[0], (
        plain.stderr
    )
    r = _run_advice(cmd)
    assert r.returncode == 0, r.stderr
    assert terralod("check", str(store)).returncode == 0
    from terralod.io.reader import read_heightfield
    from terralod.pyramid.update import update_store

    update_store(read_heightfield(str(dem)), ref, "2002-02-02", workers=1)
    assert _tiles(store, "2002-02-02") == _tiles(ref, "2002-02-02")


@posix
def test_check_gives_the_command_that_finishes_a_killed_edit(base_store, tmp_path: Path) -> None:
    src, _ = base_store
    store, ref = tmp_path / "e.terra", tmp_path / "ref.terra"
    shutil.copy(src, store)
    shutil.copy(src, ref)
    cut = _square(tmp_path / "cut.geojson", ORIGIN[0] + 103.0, ORIGIN[1] - 620.0, 412.0)
    p = python(
        "import os\n"
        "from terralod.change.epochs import edit_store\n"
        "def cb(done, total):\n"
        "    if done >= 8: os._exit(9)\n"
        f"edit_store({str(store)!r}, polygon={str(cut)!r}, depth_m=12.0, progress=cb, workers=2)\n"
    )
    assert p.returncode == 9, p.stderr[-2000:]
    assert _epochs(store)[-1] == ("edit-1", "building")
    (cmd,) = _advice(store)
    assert cmd.startswith("terralod edit ") and "--resume" in cmd and "edit-1" in cmd
    r = _run_advice(cmd)
    assert r.returncode == 0, r.stderr
    assert terralod("check", str(store)).returncode == 0
    from terralod.change.epochs import edit_store

    edit_store(ref, polygon=cut, depth_m=12.0, workers=1)
    assert _tiles(store, "edit-1") == _tiles(ref, "edit-1")


# -- 48.5: an edit killed after it committed does not dig a second time -------------------------------------
def _edit_killed_after_commit(store: Path, *args: str) -> None:
    """``terralod edit STORE ARGS`` killed (os._exit) once the epoch is committed, before it says so."""
    p = python(
        "import os\n"
        "import terralod.cli.update as u\n"
        "u.print_update = lambda rep: os._exit(9)\n"
        "from terralod.cli import main\n"
        f"main(['edit', {str(store)!r}, *{list(args)!r}])\n"
    )
    assert p.returncode == 9, p.stderr[-2000:]


@posix
def test_edit_rerun_after_a_kill_past_its_commit_does_not_dig_twice(base_store, tmp_path: Path) -> None:
    from terralod.change.epochs import epoch_heightfield

    src, z = base_store
    store = tmp_path / "e.terra"
    shutil.copy(src, store)
    cut = _square(tmp_path / "cut.geojson", ORIGIN[0] + 103.0, ORIGIN[1] - 420.0, 212.0)
    args = ["--polygon", str(cut), "--depth-m", "12"]
    _edit_killed_after_commit(store, *args)
    assert _epochs(store) == [("2000-01-01", "complete"), ("edit-1", "complete")]
    dug = epoch_heightfield(store, "edit-1").elevation_m
    assert np.allclose((z - dug)[dug != z], 12.0, atol=1e-3)
    # the same command again: says what happened, digs nothing
    p = terralod("edit", str(store), *args)
    assert p.returncode == 0, p.stderr
    assert "edit-1" in p.stdout and "already" in p.stdout, p.stdout
    assert _epochs(store) == [("2000-01-01", "complete"), ("edit-1", "complete")]
    # named epoch: the same
    _edit_killed_after_commit(store, *args, "--from", "2000-01-01", "--epoch", "pit")
    p = terralod("edit", str(store), *args, "--from", "2000-01-01", "--epoch", "pit")
    assert p.returncode == 0 and "already" in p.stdout, p.stdout + p.stderr
    assert [n for n, _ in _epochs(store)] == ["2000-01-01", "edit-1", "pit"]
    assert np.array_equal(epoch_heightfield(store, "pit").elevation_m, dug)
    # another edit (other depth), and digging again on purpose (a new epoch named), still go ahead
    p = terralod("edit", str(store), "--polygon", str(cut), "--depth-m", "3")
    assert p.returncode == 0, p.stderr
    p = terralod("edit", str(store), *args, "--epoch", "deeper")
    assert p.returncode == 0 and "already" not in p.stdout, p.stdout + p.stderr
    deeper = epoch_heightfield(store, "deeper").elevation_m
    assert np.allclose((z - deeper)[deeper != z].max(), 27.0, atol=1e-3)


# -- 48.2: rasters wider than a 16-bit tile lattice at level 0 ----------------------------------------------
@pytest.mark.parametrize("side", [32_770, 40_000, 50_000, 262_145])
def test_quantisation_of_coarse_levels_wider_than_65535_samples(side: int) -> None:
    """The lattice a raster of ``side`` samples gives: level 0 spans more than 65,535 samples, so its
    fractional bits are negative; grid vertices still quantise exactly and within 16 bits."""
    from terralod.kernels.codec import quantise_tile
    from terralod.pyramid.builder import _quantise
    from terralod.store import LevelQuantisation
    from terralod.tiles import TilePyramid

    pyr = TilePyramid(side, side, 65)
    assert pyr.span(0) > 65535
    rng = np.random.default_rng(side)
    for k in pyr.levels[:3]:
        q = LevelQuantisation(pyr.xy_frac_bits(k), 0.01)
        s = pyr.stride(k)
        g = np.arange(0, pyr.cells + 1) * s
        rows, cols = (a.ravel().astype(np.float64) for a in np.meshgrid(g, g, indexing="ij"))
        hz = rng.uniform(0.0, 300.0, rows.size)
        r0, c0 = pyr.origin_rc((k, 0, 0))
        qv, z0 = _quantise(rows, cols, hz, r0, c0, q)
        assert qv.dtype == np.uint16
        step = 2.0**-q.xy_frac_bits  # samples per lattice unit
        assert np.array_equal(qv[:, 0] * step, cols - c0) and np.array_equal(qv[:, 1] * step, rows - r0)
        assert q.xy_bound_samples == 0.5 * step
        qk, z0k, local, ok = quantise_tile(rows, cols, hz, r0, c0, q.xy_frac_bits, q.z_step_m, 2.0, 3.0)
        assert ok and np.array_equal(qk, qv) and z0k == z0
        assert np.array_equal(local[:, 0], (cols - c0) * 2.0) and np.array_equal(
            local[:, 1], (rows - r0) * 3.0
        )


def _strip(width: int, height: int) -> np.ndarray:
    """A cheap rolling terrain of ``height`` x ``width`` samples (no FFT of width²)."""
    c = np.arange(width, dtype=np.float64)[None, :]
    r = np.arange(height, dtype=np.float64)[:, None]
    z = 200 + 80 * np.sin(c / 900.0) + 30 * np.sin(c / 97.0 + r / 7.0) + 5 * np.cos(c / 13.0 - r / 3.0)
    return z.astype(np.float32)


@pytest.mark.parametrize("windowed", [False, True])
def test_a_raster_40001_samples_wide_builds_and_checks_sound(tmp_path: Path, windowed: bool) -> None:
    """A 40,001 x 33 strip has the coarse levels of a 40,000² raster (level 0 spans 65,536 samples): built in
    memory and out of core (coarse tiles meshed from decimated windows, ``_build_decimated``), the store is
    sound and level 0 stands on the source's samples."""
    from terralod.pyramid.distributed import build_store_windowed

    z = _strip(40_001, 33)
    out = tmp_path / "wide.terra"
    if windowed:
        build_store_windowed(
            _hf(z), out, tile_size=65, method="chunked", workers=2, max_window_samples=20_000
        )
    else:
        build_store(_hf(z), out, tile_size=65, method="chunked", workers=2)
    rep = check_store(out)
    assert rep.sound, rep.problems[:5]
    with open_store(out) as s:
        assert s.quantisation[0].xy_frac_bits == -1
        t = s.tile(0, 0, 0)
        rows, cols = t.grid_rc[:, 0], t.grid_rc[:, 1]
        assert t.vertices.shape[0] > 3 and cols.max() >= 40_000
        assert np.array_equal(rows, np.round(rows)) and np.array_equal(cols, np.round(cols))
        # vertices on source samples: heights within the vertical quantisation step of the source's
        on = (rows < z.shape[0]) & (cols < z.shape[1])
        zs = z[rows[on].astype(int), cols[on].astype(int)]
        assert np.abs(t.vertices[on, 2] - zs).max() <= s.quantisation[0].z_step_m


# -- 48.2: a DEM too large for this machine's memory is named -----------------------------------------------
def _vrt(folder: Path, side: int, srs: str | None = None) -> Path:
    """A VRT claiming side x side float32 samples over a small real raster: nothing is allocated."""
    vrt = folder / f"big_{side}.vrt"
    geo = ""
    if srs:
        geo = f"<SRS>{srs}</SRS><GeoTransform>-122.3, 0.0001, 0, 46.3, 0, -0.0001</GeoTransform>"
    vrt.write_text(f"""<VRTDataset rasterXSize="{side}" rasterYSize="{side}">{geo}
  <VRTRasterBand dataType="Float32" band="1">
    <SimpleSource><SourceFilename relativeToVRT="0">{BEFORE}</SourceFilename><SourceBand>1</SourceBand>
    </SimpleSource>
  </VRTRasterBand>
</VRTDataset>""")
    return vrt


def _limit_memory(n_bytes: int):
    def apply() -> None:
        import resource

        resource.setrlimit(resource.RLIMIT_AS, (n_bytes, n_bytes))

    return apply


@needs_data
@posix
def test_info_out_of_memory_names_the_file(tmp_path: Path) -> None:
    """A 20,000² DEM within the size limit on a machine without the memory to read it (the address space
    capped at 2.5 GB): one line naming the file, exit 2, never a bare "out of memory"."""
    vrt = _vrt(tmp_path, 20_000)
    p = terralod_process("info", str(vrt), preexec_fn=_limit_memory(2_500 << 20))
    lines = p.stderr.strip().splitlines()
    assert p.returncode == 2, p.stdout + p.stderr
    assert len(lines) == 1 and str(vrt) in lines[0] and "memory" in lines[0], p.stderr
    assert "internal error" not in lines[0]


# -- 48.2: export straight from a DEM applies the one size limit up front ------------------------------------
@needs_data
def test_export_of_a_region_larger_than_memory_is_refused_only_for_want_of_disk(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A geographic DEM of 20,000² samples (a VRT over a small raster: nothing allocated) is not held in
    memory, so no in-memory size limit refuses it; what it would write is checked against the free disk
    (made small here, so the refusal is the same on any machine) in one line, before anything is written."""
    vrt = _vrt(tmp_path, 20_000, srs="EPSG:4326")
    out = tmp_path / "qm"
    usage = collections.namedtuple("usage", "total used free")
    monkeypatch.setattr(shutil, "disk_usage", lambda p: usage(10**9, 10**9 - 10**6, 10**6))
    p = terralod("export", str(vrt), "--format", "quantized-mesh", "-o", str(out))
    lines = _errors(p)
    assert p.returncode == 2, p.stdout + p.stderr
    assert len(lines) == 1 and str(out) in lines[0] and "needs about" in lines[0] and "free" in lines[0], (
        p.stderr
    )
    assert not out.exists() and not list(tmp_path.glob(".qm*"))


def test_export_from_a_geographic_dem_beyond_the_in_memory_limit_reads_it_by_windows(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """With the in-memory limit lowered to 10,000 samples in the process, a real 120 x 100 geographic GeoTIFF
    still exports (its lattice is read window by window, never whole), to the same bytes as without."""
    z = fractal_terrain(100, 120, 3, relief_m=200.0) + 500.0
    dem = _tif(tmp_path / "geo.tif", z, crs="EPSG:4326", transform=Affine(0.001, 0, -122.3, 0, -0.001, 46.3))
    outs = []
    import terralod.fill as f

    for limit in (10_000, f.MAX_SAMPLES):
        out = tmp_path / f"qm-{limit}"
        with monkeypatch.context() as m:
            m.setattr(f, "MAX_SAMPLES", limit)
            p = terralod("export", str(dem), "--format", "quantized-mesh", "-o", str(out))
        assert p.returncode == 0, p.stdout + p.stderr
        outs.append({f.relative_to(out): f.read_bytes() for f in out.rglob("*") if f.is_file()})
    assert outs[0] == outs[1] and len(outs[0]) > 3


@needs_data
def test_a_geographic_build_counts_its_spill_files_against_the_free_disk(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """An out-of-core build of a geographic DEM writes spill files (warped blocks) beside its store while it
    runs: a disk that would hold the store alone but not the store and the spill is refused in one line that
    says so, before anything is written."""
    from terralod.cli._windowed import (
        POSITION_SPILL_BYTES_PER_SAMPLE,
        SPILL_BYTES_PER_SAMPLE,
        STORE_BYTES_PER_SAMPLE,
    )
    from terralod.io.windowed import open_source

    vrt = _vrt(tmp_path, 20_000, srs="EPSG:4326")
    src = open_source([str(vrt)])
    samples = src.width * src.height  # the UTM grid the warp makes
    out = tmp_path / "region.terra"
    seen: list[str] = []
    usage = collections.namedtuple("usage", "total used free")

    spill = (
        SPILL_BYTES_PER_SAMPLE * samples + POSITION_SPILL_BYTES_PER_SAMPLE * 20_000**2
    )  # warped, positions

    def disk(p):  # room for the store, and half its spill
        seen.append(str(p))
        return usage(10**13, 0, int(STORE_BYTES_PER_SAMPLE * samples + spill / 2))

    def no_build(*a, **k):  # a check that let it through fails here, not after an hour of building
        raise AssertionError("the build started")

    monkeypatch.setattr(shutil, "disk_usage", disk)
    monkeypatch.setattr("terralod.pyramid.distributed.build_store_windowed", no_build)
    p = terralod("build", str(vrt), "-o", str(out))
    lines = _errors(p)
    assert p.returncode == 2 and seen, p.stdout + p.stderr
    assert len(lines) == 1 and str(out) in lines[0] and "spill files" in lines[0], p.stderr
    assert SPILL_BYTES_PER_SAMPLE > 8 and not out.exists()
