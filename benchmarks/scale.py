"""Scaling of out-of-core and Dask builds (issue 20): throughput, peak memory, the writer's ceiling, and a
projection to a national DEM.

Terrain: srtm3_N42E001 (Pyrenees, ../shared/data), read and reprojected to UTM in memory once, a 1025²
crop mirror-tiled 4 x 4 (4097², ``_common.mirror_tile``), written as a COG (DEFLATE, 256² blocks) into a
temporary folder (never the repository); ``--big`` also writes the 16385² mirror (16 x 16, 1 GiB as
float32) as a tiled GeoTIFF written window by window and builds it once.

Configurations, each in a fresh subprocess whose whole process tree (client + Dask workers) is sampled
for RSS every 0.1 s:

- ``memory-tN``: :func:`terralod.pyramid.builder.build_store` on the whole raster, N threads;
- ``window-tN``: :func:`terralod.pyramid.distributed.build_store_windowed` on the COG, N threads;
- ``dask-pN``: the same on a LocalCluster of N worker processes x 1 thread (cluster start not counted);
- ``dask-p2-kill``: dask-p2 with one worker killed (SIGKILL) after 30 % of the tiles: its units are
  rebuilt by the scheduler on the other (then restarted) worker; tiles compared with ``window-t1``.

``--tin``: the detail-increment TIN build (paper 003) of Autzen's ground points tiled ``--tin-tiles`` ×
``--tin-tiles`` (copies offset in xy, ``benchmarks/tin_build.py``), ``terralod build cloud.las`` as the
command runs it (read, thin, Delaunay blocks, sub-blocks simplified, records, file written): ``tin-tN``
on N threads, ``tin-pN`` on a LocalCluster of N worker processes x 1 thread (cluster start and warm-up not
counted); points/s, peak RSS of the process tree, the file's sha256 against ``tin-t1``. Writes
``scale_tin.{json,md}``.

Samples/s = source samples / build seconds (the streamed plan and the error measurement included). The
writer's ceiling: every tile of the built store re-committed into a new store by ``TileStore.write_tiles``
in the builder's batches of 64, tiles/s. Medians of ``--repeat`` runs, interleaved across the configurations.
Writes ``benchmarks/results/scale.json`` and ``scale.md``. Run: ``python benchmarks/scale.py [--big] [--repeat N]``.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import sqlite3
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import RESULTS, SHARED, md_table, mirror_tile, tree_peak_rss, write_results  # noqa: E402

DEM = SHARED / "dem" / "srtm3_N42E001.tif"
CROP = 1025
METHOD = "chunked"
#: Tile size of every build here (the recorded scale*.md runs, adaptive included, used 65² tiles; adaptive
#: builds default to 33² since).
TILE_SIZE = 65
RESULTS_JSON = RESULTS / "scale.json"


# -- terrains ------------------------------------------------------------------------------------------
def write_terrains(folder: Path, big: bool) -> dict[str, Path]:
    """The 4097² COG (and the 16385² tiled GeoTIFF) of the mirror-tiled Pyrenees, in ``folder``."""
    import rasterio
    from rasterio.shutil import copy as rio_copy
    from rasterio.windows import Window

    from terralod.io.reader import read_heightfield

    hf = read_heightfield(DEM)
    h, w = hf.shape
    r0, c0 = (h - CROP) // 2, (w - CROP) // 2
    crop = np.ascontiguousarray(hf.elevation_m[r0 : r0 + CROP, c0 : c0 + CROP])
    t = hf.transform
    out = {}
    z4 = mirror_tile(crop, 4)
    profile = {"driver": "GTiff", "dtype": "float32", "count": 1, "crs": hf.crs, "transform": t,
               "tiled": True, "blockxsize": 256, "blockysize": 256, "compress": "deflate"}  # fmt: skip
    tmp = folder / "dem4k_tiled.tif"
    with rasterio.open(tmp, "w", width=z4.shape[1], height=z4.shape[0], **profile) as ds:
        ds.write(z4, 1)
    out["4097"] = folder / "dem4k_cog.tif"
    rio_copy(tmp, out["4097"], driver="COG", compress="deflate", blocksize=256)
    tmp.unlink()
    if big:
        n = (CROP - 1) * 16 + 1
        out["16385"] = folder / "dem16k_tiled.tif"
        # rows of mirror copies: copy i is the crop (even i) or its flip (odd i), sharing edge rows
        base = [crop if i % 2 == 0 else crop[::-1] for i in range(2)]
        with rasterio.open(out["16385"], "w", width=n, height=n, **profile) as ds:
            for i in range(16):
                band = base[i % 2]
                cols = [band, band[:, ::-1]]
                strip = np.concatenate([cols[0]] + [cols[j % 2][:, 1:] for j in range(1, 16)], axis=1)
                first = 0 if i == 0 else 1
                ds.write(strip[first:], 1, window=Window(0, i * (CROP - 1) + first, n, CROP - first))
    return out


# -- one configuration, in its own process ---------------------------------------------------------------
def child_tin(config: str, cloud: str, out: str) -> None:
    """Build the TIN of ``cloud`` (LAS) into ``out`` with ``config`` (tin-tN, tin-pN); print one JSON line."""
    import hashlib

    from terralod.tin import DetailIncrementModel
    from terralod.tin.distributed import close_client, dask_executor, open_client
    from tin_build import AUTZEN

    n = config_cores(config)
    procs = config.split("-")[1].startswith("p")
    client = open_client("local", n) if procs else None
    executor = dask_executor(client) if client is not None else None
    opts = {"workers": None if procs else n, "executor": executor, "sub_blocks": "auto"}
    DetailIncrementModel.from_las(AUTZEN, **opts).save(out + ".warm", workers=n)  # numba caches, workers up
    t = time.perf_counter()
    model = DetailIncrementModel.from_las(cloud, **opts)
    model.save(out, workers=n)
    secs = time.perf_counter() - t
    if client is not None:
        close_client(client)
    print(json.dumps({"seconds": secs, "points": int(model.vertices_m.shape[0]),
                      "sha256": hashlib.sha256(Path(out).read_bytes()).hexdigest()}))  # fmt: skip


def child(config: str, dem: str, out: str) -> None:
    """Build ``dem`` into ``out`` with ``config``; print one JSON line."""
    if config.startswith("tin-"):
        child_tin(config, dem, out)
        return
    from terralod.heightfield import Heightfield
    from terralod.io.windowed import RasterSource
    from terralod.pyramid.builder import build_store
    from terralod.pyramid.distributed import build_store_windowed, dask_client

    config, _, method = config.partition("@")
    method = method or METHOD
    # warm the numba caches (compile time is not build time)
    build_store(
        Heightfield.from_array(np.zeros((70, 70), np.float32), 1.0),
        out + ".warm",
        method=method,
        tile_size=TILE_SIZE,
    )
    kind, _, rest = config.partition("-")
    n = int(rest.split("-")[0][1:])
    info: dict = {}
    if kind == "memory":
        from terralod.io.reader import read_heightfield

        t = time.perf_counter()
        hf = read_heightfield(dem)
        info["read_s"] = time.perf_counter() - t
        t = time.perf_counter()
        rep = build_store(hf, out, method=method, workers=n, overwrite=True, tile_size=TILE_SIZE)
    elif kind == "window":
        t = time.perf_counter()
        rep = build_store_windowed(
            RasterSource(dem), out, method=method, workers=n, overwrite=True, tile_size=TILE_SIZE
        )
    else:
        client = dask_client("local", n_workers=n, threads=1)
        client.run(lambda: build_store(Heightfield.from_array(np.zeros((70, 70), np.float32), 1.0),
                                       out + f".warm{os.getpid()}", method=method, tile_size=TILE_SIZE))  # fmt: skip
        if config.endswith("kill"):
            _kill_later(client, out)
        t = time.perf_counter()
        rep = build_store_windowed(
            RasterSource(dem), out, method=method, client=client, overwrite=True, tile_size=TILE_SIZE
        )
        info["workers_at_end"] = len(client.scheduler_info()["workers"])
        client.close()
    secs = time.perf_counter() - t
    print(json.dumps({"seconds": secs, "tiles": rep.tiles_built, "samples": rep.source_samples, **info}))


def _kill_later(client, out: str) -> None:
    """SIGKILL one worker process once 30 % of the tiles are committed (a thread polling the store)."""
    pids = list(client.run(os.getpid).values())

    def watch() -> None:
        while True:
            time.sleep(0.2)
            try:
                conn = sqlite3.connect(f"file:{out}?mode=ro", uri=True)
                done = conn.execute("SELECT COUNT(*) FROM tiles").fetchone()[0]
                conn.close()
            except sqlite3.Error:
                continue
            if done >= 0.3 * 5461:
                os.kill(pids[0], signal.SIGKILL)
                print(json.dumps({"killed_pid": pids[0], "after_tiles": done}), file=sys.stderr)
                return

    threading.Thread(target=watch, daemon=True).start()


def config_cores(config: str) -> int:
    """The workers of a configuration (threads or processes): ``window-t2`` 2, ``dask-p1`` 1."""
    return int(config.partition("@")[0].split("-")[1][1:])


def run_config(config: str, dem: Path, folder: Path, timeout_s: float, pin: bool = False) -> dict:
    """Run one configuration in a subprocess; sample the RSS of its whole process tree. With ``pin`` the
    subprocess and everything it starts (Dask's scheduler and workers included) run on as many CPUs as the
    configuration has workers (``os.sched_setaffinity``, inherited by children)."""
    out = folder / f"{config}.terra"
    for p in folder.glob(f"{config}.terra*"):
        p.unlink()
    cpus = sorted(os.sched_getaffinity(0))[: config_cores(config)] if pin else None
    proc = subprocess.Popen([sys.executable, __file__, "--child", config, str(dem), str(out)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=(lambda: os.sched_setaffinity(0, cpus)) if cpus else None)  # fmt: skip
    peak, why = tree_peak_rss(proc, timeout_s=timeout_s, interval_s=0.1)
    if why is not None:
        return {"config": config, "error": f"timed out after {timeout_s:.0f} s"}
    stdout, stderr = proc.communicate()
    if proc.returncode != 0:
        return {"config": config, "error": stderr.strip().splitlines()[-1] if stderr.strip() else "failed"}
    res = json.loads(stdout.strip().splitlines()[-1])
    res.update(config=config, peak_rss_mib=peak / 2**20, store=str(out))
    for line in stderr.splitlines():
        if line.startswith("{") and "killed_pid" in line:
            res.update(json.loads(line))
    return res


def tiles_of(path: str) -> list[tuple]:
    conn = sqlite3.connect(path)
    try:
        return conn.execute("SELECT * FROM tiles ORDER BY level, x, y").fetchall()
    finally:
        conn.close()


def writer_ceiling(store_path: str, folder: Path, repeat: int) -> dict:
    """Tiles/s of TileStore.write_tiles re-committing every tile of a built store in batches of 64."""
    from terralod.pyramid.builder import _BATCH_TILES
    from terralod.store import TileStore

    with TileStore.open(store_path) as s:
        meta = {
            k: v for k, v in s.meta.items() if k not in ("format", "version", "complete", "meta_checksum")
        }
        tiles = [s.raw_tile(*c) for c in s.tile_codes()]
    rates = []
    for i in range(repeat):
        p = folder / f"writer{i}.terra"
        with TileStore.create(p, meta) as dst:
            t = time.perf_counter()
            for k in range(0, len(tiles), _BATCH_TILES):
                dst.write_tiles(tiles[k : k + _BATCH_TILES])
            rates.append(len(tiles) / (time.perf_counter() - t))
        p.unlink()
    mib = sum(len(t.vertices) + len(t.triangles) for t in tiles) / 2**20
    return {"tiles": len(tiles), "tiles_per_s": statistics.median(rates), "payload_mib": mib,
            "mib_per_s": statistics.median(rates) * mib / len(tiles)}  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument(
        "--big", action="store_true", help="also build the 16385² terrain once (window, 2 workers)"
    )
    ap.add_argument("--big-only", action="store_true",
                    help="only the 16385² build, the 4097² figures kept from the last run's JSON")  # fmt: skip
    ap.add_argument("--big-method", default=METHOD, help="method of the --big-only build (chunked)")
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--method", default=METHOD, help="method of the 4097² builds (chunked)")
    ap.add_argument("--name", default="scale", help="results file name under benchmarks/results/")
    ap.add_argument("--pin", action="store_true",
                    help="run each configuration on as many CPUs as it has workers (client included)")  # fmt: skip
    ap.add_argument("--child", nargs=3, metavar=("CONFIG", "DEM", "OUT"))
    ap.add_argument("--tin", action="store_true", help="the TIN build of a tiled Autzen cloud (scale_tin)")
    ap.add_argument("--tin-tiles", type=int, default=8, help="Autzen copies per side for --tin (8)")
    ap.add_argument(
        "--configs", default="memory-t1,memory-t2,window-t1,window-t2,dask-p1,dask-p2,dask-p2-kill"
    )
    args = ap.parse_args()
    if args.pin and args.name == "scale":
        ap.error("--pin needs --name (a side table): scale.md keeps the unpinned figures")
    if args.child:
        child(*args.child)
        return
    if not DEM.exists():
        print(f"skipped: {DEM} not present (../shared/data beside the repository)")
        return
    if args.big_only:
        big_only(args.big_method)
        return
    if args.tin:
        tin_scaling(args.tin_tiles, args.repeat, args.pin, args.name if args.name != "scale" else "scale_tin")
        return
    with tempfile.TemporaryDirectory(prefix="terralod-scale-") as tmp:
        folder = Path(tmp)
        t = time.perf_counter()
        dems = write_terrains(folder, args.big)
        print(
            f"terrains written in {time.perf_counter() - t:.1f} s: {', '.join(str(p) for p in dems.values())}"
        )
        results: dict[str, list[dict]] = {}
        # repeats interleaved (every configuration once, then again): a spell of load from the machine's
        # other users slows one run of each configuration, not every run of one of them
        for rep in range(args.repeat):
            for config in args.configs.split(","):
                if rep and config.endswith("kill"):
                    continue  # once
                run = config if args.method == METHOD else f"{config}@{args.method}"
                r = run_config(run, dems["4097"], folder, 1200, pin=args.pin)
                print(json.dumps(r))
                results.setdefault(config, []).append(r)
        rows, payload = summarise(results, folder)
        payload["method"] = args.method
        payload["pinned"] = args.pin
        if args.name != "scale":  # a side run (another method, pinned CPUs): its table alone
            write_results(args.name, payload, report(rows, payload))
            return
        big = None
        if args.big:
            big = run_config("window-t2", dems["16385"], folder, 3000)
            big["samples_per_s"] = big.get("samples", 0) / big["seconds"] if "seconds" in big else None
            print(json.dumps(big))
        elif (RESULTS_JSON).exists():  # the 16385² build runs once: keep its figures from the last --big run
            big = json.loads(RESULTS_JSON.read_text()).get("big_16385")
            if big:
                big["note"] = "from an earlier --big run of this script (busier machine)"
        payload["big_16385"] = big
        if RESULTS_JSON.exists():  # and the other methods' 16385² builds (--big-only --big-method)
            last = json.loads(RESULTS_JSON.read_text())
            payload.update({k: v for k, v in last.items() if k.startswith("big_16385_")})
        write_results("scale", payload, report(rows, payload))


def tin_scaling(tiles: int, repeat: int, pin: bool, name: str) -> None:
    """The TIN configurations (tin-t1, tin-t2, tin-p1, tin-p2), interleaved ``repeat`` times."""
    from tin_build import AUTZEN, autzen_tiled

    if not AUTZEN.exists():
        print(f"skipped: {AUTZEN} not present (../shared/data beside the repository)")
        return
    configs = ["tin-t1", "tin-t2", "tin-p1", "tin-p2"]
    with tempfile.TemporaryDirectory(prefix="terralod-scale-tin-") as tmp:
        folder = Path(tmp)
        cloud = autzen_tiled(tiles, folder / f"autzen{tiles}x{tiles}.las")
        results: dict[str, list[dict]] = {c: [] for c in configs}
        for _ in range(repeat):
            for config in configs:
                r = run_config(config, cloud, folder, 1800, pin=pin)
                print(json.dumps(r))
                results[config].append(r)
    rows, per = [], {}
    ref = next((r["sha256"] for r in results["tin-t1"] if "sha256" in r), None)
    for config, runs in results.items():
        ok = _completed(config, runs, rows)
        if not ok:
            continue
        secs = statistics.median(r["seconds"] for r in ok)
        same = all(r["sha256"] == ref for r in ok)
        per[config] = {"seconds": secs, "points_per_s": ok[0]["points"] / secs, "points": ok[0]["points"],
                       "peak_rss_mib": max(r["peak_rss_mib"] for r in ok), "same_file_as_tin_t1": same,
                       "runs": ok}  # fmt: skip
        rows.append([config, secs, f"{ok[0]['points'] / secs / 1e3:,.1f}", per[config]["peak_rss_mib"],
                     "yes" if same else "NO", f"{len(ok)} runs"])  # fmt: skip
    md = ["# Detail-increment TIN builds: threads and Dask processes (issue 20)\n",
          f"Autzen's ground points tiled {tiles} x {tiles} (copies offset in xy; "
          f"{next(iter(per.values()))['points'] if per else 0:,} points after thinning), sub-blocks 'auto', the "
          "whole build (read, thin, Delaunay blocks, simplification with measured errors, records, file). One "
          "subprocess per configuration, peak RSS of its whole process tree (Dask workers included), medians "
          f"of {repeat} interleaved runs. "
          + ("**Pinned:** each configuration's process tree on as many CPUs as it has workers. " if pin else "")
          + "Machine: 2 cores shared with other users.\n",
          md_table(["config", "build s", "k points/s", "peak RSS MiB", "same file as tin-t1", "note"], rows)]  # fmt: skip
    for a, b, what in (("tin-t1", "tin-t2", "threads"), ("tin-p1", "tin-p2", "processes")):
        if a in per and b in per:
            md.append(
                f"- scaling {b} / {a} ({what}): **{per[b]['points_per_s'] / per[a]['points_per_s']:.2f}x**"
            )
    write_results(name, {"tiles": tiles, "pinned": pin, "configs": per}, "\n".join(md) + "\n")


def big_only(method: str = METHOD) -> None:
    """The 16385² build alone (``method``); the 4097² rows, ratios, writer ceiling and the other methods'
    16385² builds re-rendered from the last JSON."""
    payload = json.loads(RESULTS_JSON.read_text())
    rows = [[c, d["seconds"], d["samples_per_s"] / 1e6, d["peak_rss_mib"], d["same_tiles_as_window_t1"],
             f"killed worker after {d['runs'][0]['after_tiles']} tiles" if "killed_pid" in d["runs"][0] else ""]
            for c, d in payload["configs"].items()]  # fmt: skip
    with tempfile.TemporaryDirectory(prefix="terralod-scale-") as tmp:
        dems = write_terrains(Path(tmp), True)
        config = "window-t2" if method == METHOD else f"window-t2@{method}"
        big = run_config(config, dems["16385"], Path(tmp), 3000)
    big["samples_per_s"] = big.get("samples", 0) / big["seconds"] if "seconds" in big else None
    big["method"] = method
    print(json.dumps(big))
    payload["big_16385" if method == METHOD else f"big_16385_{method}"] = big
    write_results("scale", payload, report(rows, payload))


def _completed(config: str, runs: list[dict], rows: list[list]) -> list[dict]:
    """The runs of ``config`` that finished; none: an error row is added to ``rows``."""
    ok = [r for r in runs if "seconds" in r]
    if not ok:
        rows.append([config, "-", "-", "-", "-", runs[0].get("error", "")])
    return ok


def summarise(results: dict[str, list[dict]], folder: Path) -> tuple[list[list], dict]:
    rows = []
    per = {}
    ref = results.get("window-t1", [{}])[0].get("store")
    for config, runs in results.items():
        ok = _completed(config, runs, rows)
        if not ok:
            continue
        secs = statistics.median(r["seconds"] for r in ok)
        rss = max(r["peak_rss_mib"] for r in ok)
        same = "-"
        if ref and config != "window-t1":
            same = "yes" if tiles_of(ok[0]["store"]) == tiles_of(ref) else "NO"
        note = f"killed worker after {ok[0]['after_tiles']} tiles" if "killed_pid" in ok[0] else ""
        per[config] = {"seconds": secs, "samples_per_s": ok[0]["samples"] / secs, "tiles": ok[0]["tiles"],
                       "peak_rss_mib": rss, "same_tiles_as_window_t1": same, "runs": ok}  # fmt: skip
        rows.append([config, secs, ok[0]["samples"] / secs / 1e6, rss, same, note])
    writer = writer_ceiling(ref, folder, 3) if ref else None
    return rows, {"configs": per, "writer": writer, "method": METHOD}


def ratio(per: dict, a: str, b: str) -> float | None:
    return per[b]["samples_per_s"] / per[a]["samples_per_s"] if a in per and b in per else None


def report(rows: list[list], payload: dict) -> str:
    per = payload["configs"]
    md = ["# Out-of-core and Dask builds (issue 20)\n",
          f"4097² mirror-tiled Pyrenees (srtm3_N42E001, UTM), COG, method {payload.get('method', METHOD)}, tile "
          "size 65 (5461 tiles); "
          "one subprocess per configuration, peak RSS of its whole process tree. "
          + ("**Pinned:** each configuration's process tree (client, Dask scheduler and workers) ran on as many "
             "CPUs as it has workers (`--pin`), so 1 worker had 1 core for everything and 2 workers 2. "
             if payload.get("pinned") else "")
          + "Machine: 2 cores shared with "
          "other users (load varies between runs).\n",
          md_table(["config", "build s", "M samples/s", "peak RSS MiB", "same tiles as window-t1", "note"], rows)]  # fmt: skip
    for a, b, what in (("window-t1", "window-t2", "threads"), ("dask-p1", "dask-p2", "processes"),
                       ("memory-t1", "memory-t2", "threads, in memory")):  # fmt: skip
        r = ratio(per, a, b)
        if r:
            md.append(f"- scaling {b} / {a} ({what}): **{r:.2f}x**")
    w = payload.get("writer")
    if w:
        md.append(f"- writer ceiling: **{w['tiles_per_s']:,.0f} tiles/s** ({w['mib_per_s']:.1f} MiB/s of tile "
                  f"payload, batches of 64, one SQLite writer)")  # fmt: skip
    big = payload.get("big_16385")
    if big and "seconds" in big:
        md.append(
            f"- 16385² (tiled GeoTIFF, window-t2, once): {big['seconds']:.0f} s, "
            f"{big['samples_per_s'] / 1e6:.2f} M samples/s, peak RSS {big['peak_rss_mib']:.0f} MiB"
        )
    elif big:
        md.append(f"- 16385²: {big.get('error')}")
    for key in sorted(k for k in payload if k.startswith("big_16385_")):
        b = payload[key]
        if "seconds" in b:
            md.append(
                f"- 16385², method {b['method']} (tiled GeoTIFF, window-t2, once, `--big-only --big-method "
                f"{b['method']}`): {b['seconds']:.0f} s, {b['samples_per_s'] / 1e6:.2f} M samples/s, "
                f"peak RSS {b['peak_rss_mib']:.0f} MiB"
            )
        else:
            md.append(f"- 16385², method {b.get('method')}: {b.get('error')}")
    md.append(projection(payload))
    return "\n".join(md) + "\n"


def projection(payload: dict) -> str:
    """A 10^12-sample DEM on N machines, from the measured per-core cost and the writer's ceiling."""
    per = payload["configs"]
    base = per.get("dask-p1") or per.get("window-t1")
    w = payload.get("writer")
    if not base or not w:
        return ""
    core_rate = base["samples_per_s"]  # samples/s of one worker process, one thread
    n_samples = 1e12
    tiles = n_samples / 64**2 * 4 / 3
    writer_s = tiles / w["tiles_per_s"]
    lines = ["\n## Projection: a 10^12-sample national DEM (1 m over 10^6 km²)\n",
             f"Measured here: one worker process builds {core_rate / 1e6:.2f} M samples/s ({payload.get('method', METHOD)}, one thread, "
             f"plan and measurement included); the writer commits {w['tiles_per_s']:,.0f} tiles/s. The store "
             f"would hold about {tiles:.2e} tiles (M = 65).\n",
             md_table(["machines (16 cores each)", "build hours (compute)", "writer hours", "bound by"],
                      [[n, n_samples / (core_rate * 16 * n) / 3600, writer_s / 3600,
                        "writer" if writer_s > n_samples / (core_rate * 16 * n) else "compute"]
                       for n in (1, 4, 16, 64, 256)]),  # fmt: skip
             "What limits it, in order: (1) the single SQLite writer above a few dozen machines — per-worker "
             "shard stores merged by bulk `INSERT ... SELECT` (or a store split by quadtree prefix) remove it, "
             "see the docstring of `terralod.pyramid.distributed`; (2) the streamed plan reads the whole DEM "
             "once on the client (digest and lattices; about 4 TB at a disk's 0.2-1 GB/s is 1-6 hours), which "
             "a per-strip plan on the workers with a tree of digests would spread; (3) the level barrier: "
             "coarse levels have few tiles (the root is one task reading a decimated copy), so the last levels "
             "run on few cores; (4) shared storage bandwidth: every sample is read about twice (plan, tiles), "
             "4 bytes each, so 256 machines at the compute rate above need "
             f"{2 * 4 * core_rate * 16 * 256 / 1e9:.0f} GB/s in aggregate. Cohesion costs more per tile than "
             "Chunked LOD (see benchmarks/results/cohesion_vs_chunked.md), which moves the balance toward compute."]  # fmt: skip
    return "\n".join(lines)


if __name__ == "__main__":
    main()
