"""Out-of-core and Dask builds (terralod.io.windowed, terralod.pyramid.distributed): the same tiles as the
in-memory build, a streamed plan equal to the in-memory one, coarse tiles measured on every sample."""

from __future__ import annotations

import os
import signal
import sqlite3
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from terralod.error import measure_error_window
from terralod.errors import InputError
from terralod.heightfield import Heightfield
from terralod.io.reader import read_heightfield
from terralod.io.windowed import FILL_BLOCK, ArraySource, RasterSource
from terralod.pyramid.builder import build_store, plan_quantisation
from terralod.pyramid.distributed import build_store_windowed, dask_client, scan_source
from terralod.store import TileStore
from terralod.tiles import TilePyramid

from conftest import fractal_terrain, terralod_cli

CRS = "EPSG:32611"


def _write_tif(path: Path, z: np.ndarray, *, x0: float = 380000.0, y0: float = 3800000.0, res: float = 30.0,
               crs: str = CRS, nodata: float | None = None) -> Path:  # fmt: skip
    import rasterio
    from rasterio.transform import from_origin

    h, w = z.shape
    with rasterio.open(path, "w", driver="GTiff", width=w, height=h, count=1, dtype="float32", crs=crs,
                       transform=from_origin(x0, y0, res, res), tiled=True, blockxsize=64, blockysize=64,
                       nodata=nodata) as ds:  # fmt: skip
        ds.write(z.astype(np.float32), 1)
    return path


def _rows(path: Path) -> list[tuple]:
    conn = sqlite3.connect(path)
    try:
        return conn.execute("SELECT * FROM tiles ORDER BY level, x, y").fetchall()
    finally:
        conn.close()


def _meta(path: Path) -> dict:
    with TileStore.open(path) as s:
        return dict(s.meta)


@pytest.mark.parametrize(
    ("method", "shape"), [("chunked", (257, 301)), ("cohesion", (161, 201)), ("adaptive", (257, 301))]
)
def test_windowed_build_is_the_in_memory_build(tmp_path: Path, method: str, shape: tuple[int, int]) -> None:
    """A tiled GeoTIFF read window by window (units of 2 x 2 and more tiles, data edges that cut tiles)
    gives the in-memory build's tiles and metadata byte for byte."""
    tif = _write_tif(tmp_path / "dem.tif", fractal_terrain(*shape, seed=3, relief_m=800.0))
    hf = read_heightfield(tif)
    build_store(hf, tmp_path / "mem.terra", method=method, workers=1)
    rep = build_store_windowed(RasterSource(tif), tmp_path / "win.terra", method=method, workers=2,
                               unit_span_samples=128)  # fmt: skip
    assert rep.tiles_built == rep.tiles_total == len(_rows(tmp_path / "mem.terra"))
    assert _rows(tmp_path / "win.terra") == _rows(tmp_path / "mem.terra")
    assert _meta(tmp_path / "win.terra") == _meta(tmp_path / "mem.terra")


def test_adaptive_ladder_from_a_decimated_root_window_is_the_same_in_and_out_of_core(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Adaptive's default ladder comes from the root's window decimated to LADDER_MAX_SIDE a side (a
    terrain over 4097² in practice; 100 here): the out-of-core build reads that decimated window and gets
    the in-memory build's ladder and tiles."""
    from terralod.pyramid import adaptive

    tif = _write_tif(tmp_path / "dem.tif", fractal_terrain(257, 301, seed=5, relief_m=600.0))
    hf = read_heightfield(tif)
    build_store(hf, tmp_path / "full.terra", method="adaptive", workers=1)
    monkeypatch.setattr(adaptive, "LADDER_MAX_SIDE", 100)
    assert adaptive.ladder_window(257, 301, TilePyramid(301, 257, 65))[2] == 4
    build_store(hf, tmp_path / "mem.terra", method="adaptive", workers=1)
    build_store_windowed(RasterSource(tif), tmp_path / "win.terra", method="adaptive", workers=2,
                         unit_span_samples=128)  # fmt: skip
    ladder = _meta(tmp_path / "mem.terra")["build_options"]["target_error_m"]
    assert ladder != _meta(tmp_path / "full.terra")["build_options"]["target_error_m"]  # decimated: another
    assert _meta(tmp_path / "win.terra") == _meta(tmp_path / "mem.terra")
    assert _rows(tmp_path / "win.terra") == _rows(tmp_path / "mem.terra")


@settings(max_examples=12, deadline=None)
@given(
    h=st.integers(3, 300), w=st.integers(3, 300), m=st.sampled_from([3, 5, 17, 33]),
    strip=st.sampled_from([64, 4096, 1 << 25]), seed=st.integers(0, 99),
)  # fmt: skip
def test_streamed_plan_is_the_in_memory_plan(h: int, w: int, m: int, strip: int, seed: int) -> None:
    """The streamed scan (strips of any height, merged up the quadtree) gives plan_quantisation's lattices for
    both kinds of mesher, with and without
    an epoch store's headroom, Heightfield.digest's digest and the elevation range."""
    z = fractal_terrain(h, w, seed=seed, relief_m=300.0)
    hf = Heightfield.from_array(z, 10.0)
    pyr = TilePyramid(w, h, m)
    plan = scan_source(ArraySource(hf), pyr, strip_samples=strip)
    assert plan.digest == hf.digest()
    for grid in (True, False):
        for headroom in (False, True):  # a store of epochs plans its lattice with headroom
            assert plan.quant(grid, headroom) == plan_quantisation(
                hf, pyr, grid_vertices=grid, headroom=headroom
            )
    assert plan.z_range_m == hf.valid_range_m()


@pytest.mark.parametrize("method", ["chunked", "cohesion"])
def test_decimated_coarse_tiles_are_measured_on_every_sample(tmp_path: Path, method: str) -> None:
    """Tiles whose window exceeds the budget are meshed from a decimated copy; their stored errors are
    those of their mesh against every full-resolution sample it covers (vertical exactly, Hausdorff an
    upper bound), and the other tiles are the in-memory build's."""
    hf = Heightfield.from_array(fractal_terrain(193, 177, seed=5, relief_m=600.0), 20.0)
    build_store(hf, tmp_path / "mem.terra", method=method, workers=1)
    build_store_windowed(hf, tmp_path / "win.terra", method=method, workers=1, max_window_samples=65 * 65)
    dx, dy = hf.spacing_m
    with TileStore.open(tmp_path / "win.terra") as win, TileStore.open(tmp_path / "mem.terra") as mem:
        pyr = win.pyramid
        assert win.complete and not win.verify()
        for code in pyr.all_codes():
            a, b = win.raw_tile(*code), mem.raw_tile(*code)
            if pyr.span(code[0]) <= 64:
                assert (a.vertices, a.triangles, a.error_m) == (b.vertices, b.triangles, b.error_m)
                continue
            tile = win.tile(*code)
            r0, c0 = pyr.origin_rc(code)
            r1, c1 = min(r0 + pyr.span(code[0]), hf.height - 1), min(c0 + pyr.span(code[0]), hf.width - 1)
            rc = tile.grid_rc - np.array([r0, c0])
            local = np.stack([rc[:, 1] * dx, rc[:, 0] * dy, tile.vertices[:, 2]], axis=1)
            rep = measure_error_window(local, tile.triangles, hf.elevation_m[r0 : r1 + 1, c0 : c1 + 1],
                                       hf.valid[r0 : r1 + 1, c0 : c1 + 1], dx, dy)  # fmt: skip
            assert a.n_samples == rep.n_samples
            assert a.measured_vertical_error_m == pytest.approx(rep.max_vertical_m, rel=1e-12, abs=1e-9)
            assert rep.hausdorff_m - 1e-9 <= a.measured_error_m <= a.measured_vertical_error_m + 1e-9


def test_mosaic_is_the_whole_raster_and_mixed_grids_are_refused(tmp_path: Path) -> None:
    """Four GeoTIFF tiles on one grid (shared edges) read as one VRT mosaic give the whole raster's samples;
    another CRS or pixel size is refused in one line naming the file."""
    z = fractal_terrain(193, 161, seed=11)
    whole = RasterSource(_write_tif(tmp_path / "whole.tif", z))
    parts = []
    for i, (r, c) in enumerate([(0, 0), (0, 80), (96, 0), (96, 80)]):
        sub = z[r : r + 97, c : c + 81]
        parts.append(_write_tif(tmp_path / f"t{i}.tif", sub, x0=380000.0 + 30.0 * c, y0=3800000.0 - 30.0 * r))
    mosaic = RasterSource(parts)
    assert (mosaic.width, mosaic.height) == (161, 193) and mosaic.transform == whole.transform
    for a, b in zip(mosaic.read(0, 0, 193, 161), whole.read(0, 0, 193, 161), strict=True):
        np.testing.assert_array_equal(a, b)
    other_crs = _write_tif(tmp_path / "utm10.tif", z[:50, :50], crs="EPSG:32610")
    other_res = _write_tif(tmp_path / "res.tif", z[:50, :50], res=10.0)
    with pytest.raises(InputError, match="CRS differs") as e1:
        RasterSource([parts[0], other_crs])
    with pytest.raises(InputError, match="pixel size") as e2:
        RasterSource([parts[0], other_res])
    assert "\n" not in str(e1.value) + str(e2.value) and str(other_crs) in str(e1.value)


def test_block_fill_is_the_same_whichever_window_reads_it(tmp_path: Path) -> None:
    """Nodata cells are filled per fixed block: two windows that overlap read identical values there, valid
    samples are never changed, and a build from it completes with valid errors."""
    z = fractal_terrain(FILL_BLOCK + 90, 300, seed=2)
    z[100:160, 40:90] = -9999.0
    z[FILL_BLOCK - 20 : FILL_BLOCK + 30, 200:260] = -9999.0  # a hole across a block edge
    src = RasterSource(_write_tif(tmp_path / "holes.tif", z, nodata=-9999.0))
    a, va = src.read(0, 0, FILL_BLOCK + 90, 300)
    b, vb = src.read(FILL_BLOCK - 60, 150, FILL_BLOCK + 50, 280)
    np.testing.assert_array_equal(a[FILL_BLOCK - 60 : FILL_BLOCK + 50, 150:280], b)
    np.testing.assert_array_equal(va, z != -9999.0)
    np.testing.assert_array_equal(a[va], z[va])
    assert np.isfinite(a).all() and a[~va].min() > 0.0


def test_unpickled_copies_share_the_process_datasets_until_the_file_changes(tmp_path: Path) -> None:
    """Every copy of a source a process unpickles (one per Dask task) reads through the same open dataset
    and fill cache; a file rewritten at the same path is another source, read afresh."""
    import pickle

    z = fractal_terrain(200, 180, seed=4)
    path = _write_tif(tmp_path / "a.tif", z)
    src = RasterSource(path)
    blob = pickle.dumps(src)
    a, b = pickle.loads(blob), pickle.loads(blob)
    np.testing.assert_array_equal(a.read(0, 0, 50, 60)[0], z[:50, :60])
    assert b._dataset() is a._dataset() and b._cache is a._cache
    assert src._local is not a._local  # the original keeps its own
    _write_tif(path, z + 100.0)  # rewritten in place: new size or mtime, new identity
    fresh = pickle.loads(pickle.dumps(RasterSource(path)))
    assert fresh._dataset() is not a._dataset()
    np.testing.assert_array_equal(fresh.read(0, 0, 50, 60)[0], (z + 100.0)[:50, :60].astype(np.float32))


def test_geographic_rasters_are_refused_in_one_line(tmp_path: Path) -> None:
    tif = _write_tif(tmp_path / "geo.tif", fractal_terrain(20, 20, seed=1), x0=1.0, y0=43.0, res=0.001,
                     crs="EPSG:4326")  # fmt: skip
    with pytest.raises(InputError, match="gdalwarp") as exc:
        RasterSource(tif)
    assert "\n" not in str(exc.value)


def test_dask_build_is_the_local_build_and_resumes(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A LocalCluster of 2 worker processes builds the in-memory build's tiles; an interrupted Dask build
    (stopped after some tiles, as a dead client leaves it) finishes with resume; a build during which a
    worker is killed gives the same tiles; an unreachable scheduler is refused."""
    pytest.importorskip("dask.distributed", reason="dask[distributed] is not installed")
    tif = _write_tif(tmp_path / "dem.tif", fractal_terrain(129, 193, seed=7, relief_m=400.0))
    build_store(read_heightfield(tif), tmp_path / "mem.terra", tile_size=33, method="chunked", workers=1)
    client = dask_client("local", n_workers=2, threads=1)
    try:
        out = tmp_path / "dask.terra"
        first = build_store_windowed(RasterSource(tif), out, tile_size=33, method="chunked", client=client,
                                     stop_after=10, unit_span_samples=64)  # fmt: skip
        assert 0 < first.tiles_built < first.tiles_total and not TileStore.open(out).complete
        rest = build_store_windowed(RasterSource(tif), out, tile_size=33, method="chunked", client=client,
                                    resume=True)  # fmt: skip
        assert rest.tiles_skipped == first.tiles_built

        def malloc_state() -> tuple[bool, bool | None]:
            import terralod.pyramid.distributed as d

            return "MALLOC_TRIM_THRESHOLD_" in os.environ, d._malloc_tuned

        # a worker that built units has glibc's adaptive thresholds back where its nanny fixed one
        for has_env, tuned in client.run(malloc_state).values():
            assert tuned is (has_env and sys.platform.startswith("linux"))
        # a worker killed (SIGKILL) once the first tiles are committed: its units are rebuilt elsewhere
        pids = list(client.run(os.getpid).values())
        killed = []

        def kill_once(done: int, total: int) -> None:
            if done and not killed:
                os.kill(pids[0], signal.SIGKILL)
                killed.append(done)

        # tile size 9 on 65 x 97: the first commit (64 tiles or 0.5 s) is mid-level, units in flight
        small = _write_tif(tmp_path / "small.tif", fractal_terrain(65, 97, seed=8, relief_m=300.0))
        hit = tmp_path / "killed.terra"
        rep = build_store_windowed(RasterSource(small), hit, tile_size=9, method="chunked", client=client,
                                   unit_span_samples=8, progress=kill_once)  # fmt: skip
        assert killed and killed[0] < 8 * 12 and rep.tiles_total == rep.tiles_built
        # units whose futures the scheduler cancels (a lost scattered copy, a reconnect) are resubmitted:
        # here the first unit's future is cancelled as soon as it is submitted
        import terralod.pyramid.distributed as d

        cancelled: list[str] = []
        submit = d._DaskRunner.submit

        def submit_then_cancel(self, *args):
            fut = submit(self, *args)
            if not cancelled:
                cancelled.append(fut.key)
                self.client.cancel([fut])
            return fut

        monkeypatch.setattr(d._DaskRunner, "submit", submit_then_cancel)
        again = tmp_path / "cancelled.terra"
        rep = build_store_windowed(RasterSource(small), again, tile_size=9, method="chunked", client=client,
                                   unit_span_samples=8)  # fmt: skip
        monkeypatch.undo()
        assert cancelled and rep.tiles_total == rep.tiles_built
    finally:
        cluster = client.cluster
        client.close()
        cluster.close()
    assert _rows(out) == _rows(tmp_path / "mem.terra")
    build_store(read_heightfield(small), tmp_path / "mem9.terra", tile_size=9, method="chunked", workers=1)
    assert _rows(hit) == _rows(tmp_path / "mem9.terra")
    assert _rows(again) == _rows(tmp_path / "mem9.terra")
    with pytest.raises(InputError, match="cannot reach the Dask scheduler"):
        dask_client("tcp://127.0.0.1:9", timeout_s=1.0)


_FAULTS = """
import resource, sys
import numpy as np
from terralod.pyramid.distributed import tune_worker_malloc
tuned = tune_worker_malloc() if sys.argv[1] == "tune" else False
a = np.ones(1 << 18); del a
f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(50):
    a = np.ones(1 << 18); del a  # 2 MiB allocated, touched and freed
print(tuned, resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc malloc thresholds: Linux only")
def test_fixed_malloc_threshold_is_undone_where_set() -> None:
    """With MALLOC_TRIM_THRESHOLD_ set (as Dask's nanny sets it) every freed 2 MiB array goes back to the
    kernel and the next one faults its 512 pages in again; tune_worker_malloc stops that, and does nothing
    in a process started without the variable."""

    def run(mode: str, env_set: bool) -> tuple[str, int]:
        env = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_")}
        if env_set:
            env["MALLOC_TRIM_THRESHOLD_"] = "65536"
        out = subprocess.run([sys.executable, "-c", _FAULTS, mode], env=env, capture_output=True, text=True,
                             check=True).stdout.split()  # fmt: skip
        return out[0], int(out[1])

    fixed_flag, fixed = run("none", True)
    tuned_flag, tuned = run("tune", True)
    plain_flag, plain = run("tune", False)
    assert (fixed_flag, tuned_flag, plain_flag) == ("False", "True", "False")
    assert fixed >= 50 * 256  # about 512 page faults per array
    assert tuned < fixed / 20 and plain < fixed / 20


def _die_on_every_unit():
    """A Dask worker plugin (installed on every worker, restarted ones too) whose workers die in every
    work unit, as a worker killed by the out-of-memory guard does."""
    from distributed import WorkerPlugin

    class DieOnEveryUnit(WorkerPlugin):
        name = "terralod-test-die"

        def setup(self, worker) -> None:
            import terralod.pyramid.distributed as d

            def die(*args, **kwargs):
                os._exit(1)

            d.build_unit = die

    return DieOnEveryUnit()


def test_dask_workers_lost_on_every_try_is_one_clear_line(tmp_path: Path) -> None:
    """A unit whose workers keep dying (out of memory) ends the build with one line saying so and how to
    go on; the store keeps what was committed and resumes locally into the in-memory build's tiles."""
    pytest.importorskip("dask.distributed", reason="dask[distributed] is not installed")
    import dask

    from terralod.errors import WorkerLostError

    tif = _write_tif(tmp_path / "dem.tif", fractal_terrain(65, 97, seed=9, relief_m=300.0))
    with dask.config.set({"distributed.scheduler.allowed-failures": 0}):
        client = dask_client("local", n_workers=1, threads=1)
    try:
        client.register_plugin(_die_on_every_unit())
        out = tmp_path / "lost.terra"
        with pytest.raises(WorkerLostError, match="out of memory.*--resume"):
            build_store_windowed(
                RasterSource(tif), out, tile_size=9, method="chunked", client=client, retries=0
            )
    finally:
        cluster = client.cluster
        client.close()
        cluster.close()
    # the store holds what was committed (sound, incomplete); when the workers died before the store's
    # metadata was ready there is none at all, never a half-written one: --resume finishes either way
    if out.exists():
        with TileStore.open(out) as s:
            assert not s.complete and s.verify() == []
    assert not [f for f in tmp_path.iterdir() if f.name.startswith(".lost.terra")]
    build_store_windowed(RasterSource(tif), out, tile_size=9, method="chunked", workers=1, resume=True)
    build_store(read_heightfield(tif), tmp_path / "mem.terra", tile_size=9, method="chunked", workers=1)
    assert _rows(out) == _rows(tmp_path / "mem.terra")


def test_tin_tasks_whose_workers_die_end_in_one_clear_line() -> None:
    """A TIN task (a Delaunay block, a sub-block's simplification) whose worker dies on every try ends the
    build with WorkerLostError, one line naming the likely cause and what to change, not a traceback."""
    pytest.importorskip("dask.distributed", reason="dask[distributed] is not installed")
    import dask

    from terralod.errors import WorkerLostError
    from terralod.tin.distributed import close_client, dask_executor

    with dask.config.set({"distributed.scheduler.allowed-failures": 0}):
        client = dask_client("local", n_workers=1, threads=1)
    try:
        with pytest.raises(WorkerLostError, match="out of memory.*--sub-blocks"):
            dask_executor(client, retries=0)([1], os._exit)  # the task kills its worker process
    finally:
        close_client(client)


def test_windowed_overwrite_keeps_the_old_store_until_complete(tmp_path: Path) -> None:
    """``overwrite`` of an out-of-core build builds beside the old store: stopped early (or killed) it
    leaves the old store whole; complete, it replaces it."""
    tif = _write_tif(tmp_path / "dem.tif", fractal_terrain(65, 97, seed=10, relief_m=300.0))
    other = _write_tif(tmp_path / "other.tif", fractal_terrain(65, 97, seed=11, relief_m=300.0))
    out = tmp_path / "s.terra"
    build_store_windowed(RasterSource(other), out, tile_size=9, method="chunked", workers=1)
    old = _rows(out)
    part = build_store_windowed(RasterSource(tif), out, tile_size=9, method="chunked", workers=1, overwrite=True,
                                stop_after=5)  # fmt: skip
    assert part.tiles_built == 5 and _rows(out) == old
    with pytest.raises(RuntimeError, match="stop"):

        def boom(done: int, total: int) -> None:
            if done > 3:
                raise RuntimeError("stop")

        build_store_windowed(RasterSource(tif), out, tile_size=9, method="chunked", workers=1, overwrite=True,
                             progress=boom)  # fmt: skip
    assert _rows(out) == old and not [f for f in tmp_path.iterdir() if f.name.endswith(".tmp")]
    build_store_windowed(RasterSource(tif), out, tile_size=9, method="chunked", workers=1, overwrite=True)
    build_store(read_heightfield(tif), tmp_path / "mem.terra", tile_size=9, method="chunked", workers=1)
    assert _rows(out) == _rows(tmp_path / "mem.terra") != old


def test_tcp_scheduler_builds_dem_and_tin_as_the_local_build(tmp_path: Path) -> None:
    """The contract scripts rely on, with a real cluster: ``dask scheduler`` and ``dask worker`` started as
    their own processes (as on a cluster), then ``terralod build ... --dask tcp://HOST:PORT`` for a DEM and
    for a LiDAR cloud: the DEM store's tile rows and the TIN store's model bytes are the local build's."""
    pytest.importorskip("dask.distributed", reason="dask[distributed] is not installed")
    import json
    import shutil
    import subprocess
    import time

    from terralod.store import read_tin_store
    from test_tin_cli import write_las

    dask_cli = shutil.which("dask")
    if dask_cli is None:
        pytest.skip("the dask command (dask[distributed]) is not on PATH")
    sf = tmp_path / "scheduler.json"
    env = {**os.environ, "DASK_DISTRIBUTED__WORKER__DAEMON": "False"}
    procs = [subprocess.Popen([dask_cli, "scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
                               "--scheduler-file", str(sf)], env=env, cwd=tmp_path,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]  # fmt: skip
    try:
        for _ in range(600):
            if sf.exists() and sf.stat().st_size:
                break
            time.sleep(0.1)
        address = json.loads(sf.read_text())["address"]
        assert address.startswith("tcp://127.0.0.1:")
        procs.append(subprocess.Popen([dask_cli, "worker", "--scheduler-file", str(sf), "--nworkers", "2",
                                       "--nthreads", "1", "--no-dashboard"], env=env, cwd=tmp_path,
                                      stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))  # fmt: skip
        from distributed import Client

        with Client(address, timeout=60) as c:
            c.wait_for_workers(2, timeout=120)

        def build(src: Path, out: Path, *extra: str) -> None:
            # the command in this process: only the cluster runs apart
            r = terralod_cli("build", str(src), "-o", str(out), *extra)
            assert r.returncode == 0, r.stdout + r.stderr

        tif = _write_tif(tmp_path / "dem.tif", fractal_terrain(129, 193, seed=11, relief_m=350.0))
        common = ["--tile-size", "33", "--method", "chunked"]
        build(tif, tmp_path / "local.terra", *common, "--workers", "1")
        build(tif, tmp_path / "tcp.terra", *common, "--dask", address)
        assert _rows(tmp_path / "tcp.terra") == _rows(tmp_path / "local.terra")
        rng = np.random.default_rng(5)
        xy = rng.uniform(0.0, 300.0, (3000, 2))
        z = 40.0 * np.sin(xy[:, 0] / 37.0) * np.cos(xy[:, 1] / 53.0) + rng.normal(0.0, 0.3, 3000)
        las = write_las(tmp_path / "c.las", np.column_stack([xy, z]))
        build(las, tmp_path / "local_tin.terra", "--sub-blocks", "9", "--workers", "1")
        build(las, tmp_path / "tcp_tin.terra", "--sub-blocks", "9", "--dask", address)
        assert (
            read_tin_store(tmp_path / "tcp_tin.terra")[1] == read_tin_store(tmp_path / "local_tin.terra")[1]
        )
        # and the work really ran on the cluster's workers: the scheduler has seen their tasks
        with Client(address, timeout=60) as c:
            done = c.run_on_scheduler(lambda dask_scheduler: dask_scheduler.transition_counter)
        assert done >= 3 * (9 + 2), done  # >= 3 transitions per task
    finally:
        for p in reversed(procs):
            p.terminate()
        for p in reversed(procs):
            try:
                p.wait(timeout=30)
            except subprocess.TimeoutExpired:
                p.kill()


@settings(max_examples=40, deadline=None)
@given(st.integers(40, 2000), st.integers(40, 2000), st.sampled_from([9, 17, 33, 65]),
       st.lists(st.tuples(st.integers(0, 10**6), st.floats(0, 1e4), st.floats(0, 1e4)), max_size=300))  # fmt: skip
def test_tile_errors_hold_what_a_dict_holds(w: int, h: int, tile: int, puts: list) -> None:
    """The build's per-level arrays of tile errors answer as the dict of tuples they replace: the same
    keys, the same floats bit for bit, the same membership for tiles never put."""
    from terralod.pyramid.distributed import TileErrors
    from terralod.tiles import TilePyramid

    p = TilePyramid(w, h, tile)
    codes = p.all_codes()
    got, want = TileErrors(p), {}
    for i, e, v in puts:
        c = codes[i % len(codes)]
        got[c] = (e, v)
        want[c] = (e, v)
    assert len(got) == len(want) and sorted(got) == sorted(want)
    assert all(got[c] == want[c] for c in want)
    assert all((c in got) == (c in want) for c in codes[:: max(1, len(codes) // 200)])
    assert (p.max_level + 1, 0, 0) not in got


@settings(max_examples=40, deadline=None)
@given(st.integers(40, 3000), st.integers(40, 3000), st.sampled_from([9, 17, 33, 65]),
       st.sampled_from([64, 512, 2048]), st.sets(st.integers(0, 10**6), max_size=200),
       st.one_of(st.none(), st.integers(0, 3000)), st.integers(0, 6))  # fmt: skip
def test_units_made_as_taken_cover_the_plan(w: int, h: int, tile: int, unit_span: int, done: set,
                                            stop_after: int | None, early: int) -> None:  # fmt: skip
    """The work units a build makes as it goes (from a byte per tile, not a list of codes) are the plan:
    every tile not done, and of those only the first ``stop_after`` in finest-first raster order, each in
    exactly one unit; a unit is one level's tiles in one aligned g x g block, in raster order; the early
    levels (few units) coarsest first, then the others finest first."""
    from terralod.pyramid.distributed import TileErrors, _todo, _unit_order, _unit_side

    p = TilePyramid(w, h, tile)
    codes = p.all_codes(finest_first=True)
    errors = TileErrors(p)
    for i in done:
        errors[codes[i % len(codes)]] = (1.0, 1.0)
    want = [c for c in codes if c not in errors]
    if stop_after is not None:
        want = want[:stop_after]
    first, rest = _unit_order(p, _todo(p, errors, stop_after), unit_span, early)
    units = first + list(rest)
    got = [c for u in units for c in u]
    assert sorted(got) == sorted(want) and len(got) == len(set(got))
    levels = [u[0][0] for u in units]
    for u in units:
        level, g = u[0][0], _unit_side(p, u[0][0], unit_span)
        assert {c[0] for c in u} == {level} and len({(c[1] // g, c[2] // g) for c in u}) == 1
        assert u == sorted(u, key=lambda c: (c[2], c[1]))
    n_first = len(first)
    assert levels[:n_first] == sorted(levels[:n_first])
    assert levels[n_first:] == sorted(levels[n_first:], reverse=True)
