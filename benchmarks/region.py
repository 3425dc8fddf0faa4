"""A region in: ``terralod export FOLDER --format quantized-mesh`` and ``terralod build FOLDER -o
region.terra`` on mosaics of 16 and 64 SRTM3 tiles.

    python benchmarks/region.py [--tiles 16,64] [--source srtm3_N41E001] [--stages export,build]

Each mosaic is the real SRTM3 tile mirror-tiled (``_common.mirror_tile``: reflections sharing their edge
rows, C0-continuous) to (1200 n + 1)² samples and cut back into n x n separate 1° GeoTIFFs in EPSG:4326
(1201² int16 each, deflate, nodata -32768, adjacent bounds sharing their edge row and column as SRTM tiles
do), north-west corner at N(41 + n)E001. The export reads the folder as one region, a window of it at a
time (:class:`terralod.export.source.RegionGrid`), so its peak memory should not grow with the region.

Rows: samples of the region, tiles written, wall and CPU (user + sys) of the ``terralod`` process, its
peak RSS (GNU time's maximum resident set size of the child; psutil's sum over the process tree when GNU
time is absent), tiles per second, µs of wall and of CPU per sample, µs of CPU per sample after the
start-up (the median CPU of the same export of a 121² DEM, reported apart: interpreter, imports, numba's
JIT engine), bytes written. A run of some sizes keeps the earlier rows of the others. Writes
benchmarks/results/region.json and region.md; with 1 among the sizes, the single tile's CPU per sample
after start-up over the largest mosaic's (the issue's ≤ 1.3x, Cesium Terrain Builder's own ratio).

The ``build`` stage: ``terralod build FOLDER -o region.terra`` (out of core: the region warped block by
block to the UTM zone of its centre, every tile also measured against the original samples), wall, CPU
and the peak RSS summed over the process tree (psutil, sampled every 50 ms), tiles in the store, µs of
wall per original sample. Writes benchmarks/results/region_build.json and region_build.md. With
``--store-exports quantized-mesh,3dtiles`` each store just built is exported to those formats (a fresh
process each: wall, CPU, peak RSS of the tree, files and bytes): benchmarks/results/region_store_export.*;
``--stores 16=a.terra,64=b.terra --store-exports 3dtiles`` exports stores built earlier instead.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import SHARED, md_table, mirror_tile, tree_peak_rss, write_results  # noqa: E402


def write_mosaic(src: Path, n: int, folder: Path) -> list[Path]:
    """n x n 1° GeoTIFFs of ``src`` mirror-tiled, sharing edge rows/columns; their paths."""
    import rasterio
    from affine import Affine

    with rasterio.open(src) as ds:
        a = ds.read(1)
        t, nodata = ds.transform, ds.nodata
    side = a.shape[0] - 1  # 1200 samples a degree
    big = mirror_tile(a, n)
    folder.mkdir(parents=True, exist_ok=True)
    out = []
    for i in range(n):  # rows from the north
        for j in range(n):
            lat, lon = 41 + n - 1 - i, 1 + j
            tile = np.ascontiguousarray(big[i * side : i * side + side + 1, j * side : j * side + side + 1])
            tt = Affine(t.a, 0.0, lon - 0.5 * t.a, 0.0, t.e, lat + 1 - 0.5 * t.e)
            p = folder / f"N{lat:02d}E{lon:03d}.tif"
            with rasterio.open(p, "w", driver="GTiff", width=side + 1, height=side + 1, count=1, dtype=a.dtype,
                               crs="EPSG:4326", transform=tt, nodata=nodata, tiled=True, blockxsize=256,
                               blockysize=256, compress="deflate", predictor=2) as ds:  # fmt: skip
                ds.write(tile, 1)
            out.append(p)
    return out


def run_export(folder: Path, out: Path, env: dict[str, str] | None = None) -> dict[str, float]:
    """``terralod export FOLDER --format quantized-mesh -o OUT`` in a fresh process (environment ``env``,
    this one's when None): wall, CPU, peak RSS."""
    cmd = [
        sys.executable,
        "-m",
        "terralod",
        "export",
        str(folder),
        "--format",
        "quantized-mesh",
        "-o",
        str(out),
    ]
    gnu_time = shutil.which("time") or ("/usr/bin/time" if Path("/usr/bin/time").exists() else None)
    t0 = time.perf_counter()
    if gnu_time:
        p = subprocess.run([gnu_time, "-v", *cmd], capture_output=True, text=True, env=env)
        wall = time.perf_counter() - t0
        if p.returncode != 0:
            raise RuntimeError(p.stderr[-2000:])

        def field(name: str) -> float:
            m = re.search(rf"{re.escape(name)}: ([0-9.]+)", p.stderr)
            return float(m.group(1)) if m else float("nan")

        rss_mib = field("Maximum resident set size (kbytes)") / 1024
        cpu = field("User time (seconds)") + field("System time (seconds)")
        return {"wall_s": wall, "cpu_s": cpu, "peak_rss_mib": rss_mib, "stdout": p.stdout.strip()}

    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, env=env)
    peak = _tree_peak_rss(proc)
    wall = time.perf_counter() - t0
    usage = os.times()
    return {"wall_s": wall, "cpu_s": usage.children_user + usage.children_system, "peak_rss_mib": peak / 2**20,
            "stdout": (proc.stdout.read() if proc.stdout else "").strip()}  # fmt: skip


def _tree_peak_rss(proc: subprocess.Popen) -> int:
    """Peak RSS (bytes) summed over ``proc`` and its children (``_common.tree_peak_rss``)."""
    return tree_peak_rss(proc)[0]


def run_tree(cmd: list[str]) -> dict[str, float | str]:
    """``cmd`` in a fresh process: wall, CPU of the process tree (user + sys of the children waited for),
    peak RSS summed over the process tree (psutil, sampled every 50 ms)."""

    t0 = time.perf_counter()
    before = os.times()
    err = tempfile.TemporaryFile("w+")  # not a pipe: a long run's progress would fill it
    got = tempfile.TemporaryFile("w+")  # nor its output (a site's update lists every file: 180 KB)
    proc = subprocess.Popen(cmd, stdout=got, stderr=err, text=True)
    timeline: list[tuple[float, float]] = []
    peak = tree_peak_rss(proc, timeline=timeline)[0]
    proc.wait()
    got.seek(0)
    out = got.read()
    wall = time.perf_counter() - t0
    err.seek(0)
    if proc.returncode != 0:
        raise RuntimeError(err.read()[-2000:])
    after = os.times()
    cpu = (after.children_user - before.children_user) + (after.children_system - before.children_system)
    peak_at = next((t for t, m in timeline if m >= peak / 2**20 - 0.05), wall)
    return {"wall_s": wall, "cpu_s": cpu, "peak_rss_mib": peak / 2**20, "peak_at_s": peak_at,
            "rss_timeline_mib": timeline, "stdout": out.strip()}  # fmt: skip


def run_build(folder: Path, out: Path) -> dict[str, float | str]:
    """``terralod build FOLDER -o OUT`` (out of core) in a fresh process."""
    return run_tree([sys.executable, "-m", "terralod", "build", str(folder), "-o", str(out)])


def store_export_rows(store: Path, count: int, samples: int, formats: list[str]) -> list[dict]:
    """``terralod export STORE --format F -o OUT`` of a region store just built, for each of ``formats``, in
    a fresh process: wall, CPU, peak RSS of the tree, tiles (files) and bytes written."""
    rows = []
    for fmt in formats:
        out = store.parent / f"export-{fmt}"
        r = run_tree(
            [sys.executable, "-m", "terralod", "export", str(store), "--format", fmt, "-o", str(out)]
        )
        files = [f for f in out.rglob("*") if f.is_file() and f.suffix in (".terrain", ".glb")]
        rows.append({"srtm_tiles": count, "format": fmt, "samples": samples, "tiles": len(files),
                     "bytes": sum(f.stat().st_size for f in out.rglob("*") if f.is_file()),
                     "date": time.strftime("%Y-%m-%d %H:%M"), "load_1min": os.getloadavg()[0],
                     **{k: v for k, v in r.items() if k != "stdout"}, "summary": r["stdout"][-2000:]})  # fmt: skip
        print(rows[-1], flush=True)
        shutil.rmtree(out, ignore_errors=True)
    return rows


def write_store_export(src: Path, rows: list[dict]) -> None:
    """benchmarks/results/region_store_export.{json,md}: the rows of this run and the earlier ones of
    other (size, format) pairs."""
    import json

    p = Path(__file__).resolve().parent / "results" / "region_store_export.json"
    try:
        earlier = json.loads(p.read_text())["runs"]
    except (OSError, KeyError, ValueError):
        earlier = []
    mine = {(r["srtm_tiles"], r["format"]) for r in rows}
    runs = sorted([r for r in earlier if (r["srtm_tiles"], r["format"]) not in mine] + rows,
                  key=lambda r: (r["format"], r["srtm_tiles"]))  # fmt: skip
    table = md_table(
        ["store of", "format", "tiles", "wall s", "CPU s", "peak RSS MiB", "µs CPU/sample", "bytes", "run"],
        [[f"{r['srtm_tiles']} SRTM3 tiles", r["format"], r["tiles"], round(float(r["wall_s"]), 1),
          round(float(r["cpu_s"]), 1), round(float(r["peak_rss_mib"]), 1),
          round(float(r["cpu_s"]) / r["samples"] * 1e6, 3), f"{r['bytes'] / 1e6:.1f} MB", r["date"]]
         for r in runs],
    )  # fmt: skip
    note = (
        "\n`terralod export region.terra --format F -o OUT` (a fresh process, start-up included) of the store "
        f"`terralod build` made of SRTM3 {src.stem} mirror-tiled into separate 1° GeoTIFFs (EPSG:4326); peak RSS "
        "summed over the process tree. Reproduce: `python benchmarks/region.py --stages build "
        "--store-exports quantized-mesh,3dtiles`.\n"
    )
    write_results("region_store_export", {"source": src.stem, "runs": runs}, table + note)


def build_stage(src: Path, counts: list[int], store_exports: list[str] | None = None) -> None:
    """The build rows (see the module docstring), and with ``store_exports`` the exports of each store."""
    import sqlite3

    results = _earlier_runs("region_build", counts)  # a 64-tile run adds its row to the 16-tile one
    exported: list[dict] = []
    for count in counts:
        n = int(round(count**0.5))
        with tempfile.TemporaryDirectory(prefix="terralod-region-build-") as d:
            write_mosaic(src, n, Path(d) / "dem")
            samples = (1200 * n + 1) ** 2
            out = Path(d) / "region.terra"
            r = run_build(Path(d) / "dem", out)
            con = sqlite3.connect(out)
            tiles = con.execute("SELECT COUNT(*) FROM tiles").fetchone()[0]
            w, h = (
                int(con.execute("SELECT value FROM meta WHERE key = ?", (k,)).fetchone()[0])
                for k in ("width", "height")
            )
            con.close()
            nbytes = out.stat().st_size
            if store_exports:
                exported += store_export_rows(out, count, samples, store_exports)
                write_store_export(src, exported)
        wall = float(r["wall_s"])
        res = {"srtm_tiles": count, "samples": samples, "grid": [w, h], "tiles": tiles, "bytes": nbytes,
               "us_per_sample": wall / samples * 1e6, "load_1min": os.getloadavg()[0],
               "date": time.strftime("%Y-%m-%d %H:%M"), **{k: v for k, v in r.items() if k != "stdout"},
               "summary": r["stdout"]}  # fmt: skip
        results = sorted(
            [x for x in results if x["srtm_tiles"] != count] + [res], key=lambda x: x["srtm_tiles"]
        )
        print(res, flush=True)
    rows = [[f"{x['srtm_tiles']} SRTM3 tiles ({int(round(x['samples'] ** 0.5))}²)", x["samples"],
             f"{x['grid'][0]} x {x['grid'][1]}", x["tiles"], round(float(x["wall_s"]), 1),
             round(float(x["cpu_s"]), 1), round(float(x["peak_rss_mib"]), 1), round(x["us_per_sample"], 3),
             f"{x['bytes'] / 1e6:.1f} MB", x.get("date", "")] for x in results]  # fmt: skip
    table = md_table(["region", "original samples", "UTM grid", "tiles", "wall s", "CPU s", "peak RSS MiB",
                      "µs/sample", "store", "run"], rows)  # fmt: skip
    note = (
        "\n`terralod build FOLDER -o region.terra` (a fresh process, start-up included; out of core: warped "
        "block by block to UTM, every tile also measured against the original samples) on SRTM3 "
        f"{src.stem} mirror-tiled into separate 1° GeoTIFFs (EPSG:4326); peak RSS summed over the process "
        "tree. Reproduce: `python benchmarks/region.py --stages build`.\n"
    )
    write_results("region_build", {"source": src.stem, "runs": results}, table + note)


def startup_cpu_s(runs: int = 3) -> float:
    """The fixed cost of a run, reported apart: CPU (user + sys) of ``terralod export`` on a 121² DEM (the
    interpreter, the imports, numba's JIT engine and cached kernels loaded, one tiny tile set written),
    the median of ``runs`` fresh processes."""
    import statistics

    import rasterio
    from rasterio.transform import from_origin

    with tempfile.TemporaryDirectory(prefix="terralod-startup-") as d:
        dem = Path(d) / "tiny.tif"
        z = (np.add.outer(np.arange(121), np.arange(121)) % 97).astype(np.int16)
        with rasterio.open(dem, "w", driver="GTiff", width=121, height=121, count=1, dtype="int16",
                           crs="EPSG:4326", transform=from_origin(1.0, 42.0, 1 / 120, 1 / 120)) as ds:  # fmt: skip
            ds.write(z, 1)
        cpu = [run_export(dem, Path(d) / f"out{i}")["cpu_s"] for i in range(runs)]
    return float(statistics.median(cpu))


def _earlier_runs(name: str, counts: list[int]) -> list[dict]:
    """The rows of an earlier run of other mosaic sizes (kept, so a 256-tile run adds its row)."""
    import json

    p = Path(__file__).resolve().parent / "results" / f"{name}.json"
    try:
        return [r for r in json.loads(p.read_text())["runs"] if r["srtm_tiles"] not in counts]
    except (OSError, KeyError, ValueError):
        return []


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument(
        "--tiles", default="1,16,64", help="mosaic sizes in SRTM tiles (squares: 1, 4, 16, 64, ...)"
    )
    ap.add_argument("--source", default="srtm3_N41E001", help="the real SRTM3 tile mirrored")
    ap.add_argument("--stages", default="export,build", help="export, build or both")
    ap.add_argument("--store-exports", default="", help="with build: export each store to these formats "
                    "(quantized-mesh, 3dtiles; comma-separated) into region_store_export")  # fmt: skip
    ap.add_argument("--stores", default="", help="export these stores built earlier instead (COUNT=PATH, "
                    "comma-separated; with --store-exports): no build, no other stage")  # fmt: skip
    args = ap.parse_args()
    src = SHARED / "dem" / f"{args.source}.tif"
    stages = args.stages.split(",")
    if args.stores:
        exported = []
        for item in args.stores.split(","):
            count, path = item.split("=", 1)
            n = int(round(int(count) ** 0.5))
            exported += store_export_rows(Path(path), int(count), (1200 * n + 1) ** 2,
                                          [f for f in args.store_exports.split(",") if f])  # fmt: skip
            write_store_export(src, exported)
        return
    if "build" in stages:
        build_stage(
            src, [int(v) for v in args.tiles.split(",")], [f for f in args.store_exports.split(",") if f]
        )
    if "export" not in stages:
        return
    results = _earlier_runs("region", [int(v) for v in args.tiles.split(",")])
    startup = startup_cpu_s()
    print({"startup_cpu_s": startup}, flush=True)
    for count in [int(v) for v in args.tiles.split(",")]:
        n = int(round(count**0.5))
        assert n * n == count, f"Expected a square number of tiles, got {count}"
        with tempfile.TemporaryDirectory(prefix="terralod-region-") as d:
            files = write_mosaic(src, n, Path(d) / "dem")
            samples = (1200 * n + 1) ** 2
            out = Path(d) / "out"
            r = run_export(Path(d) / "dem", out)
            tiles = sum(1 for _ in out.rglob("*.terrain"))
            nbytes = sum(f.stat().st_size for f in out.rglob("*") if f.is_file())
        res = {"srtm_tiles": count, "files": len(files), "samples": samples, "tiles": tiles, "bytes": nbytes,
               "tiles_per_s": tiles / r["wall_s"], "us_per_sample": r["wall_s"] / samples * 1e6,
               "cpu_us_per_sample": r["cpu_s"] / samples * 1e6, "load_1min": os.getloadavg()[0],
               "startup_cpu_s": startup, "cpu_us_per_sample_after_startup": (r["cpu_s"] - startup) / samples * 1e6,
               "date": time.strftime("%Y-%m-%d %H:%M"),
               **{k: v for k, v in r.items() if k != "stdout"}, "summary": r["stdout"]}  # fmt: skip
        results = sorted(
            [x for x in results if x["srtm_tiles"] != count] + [res], key=lambda x: x["srtm_tiles"]
        )
        print(res, flush=True)
    rows = [[f"{x['srtm_tiles']} SRTM3 tiles ({1200 * round(x['srtm_tiles'] ** 0.5) + 1}²)", x["samples"],
             x["tiles"], round(x["wall_s"], 1), round(x["cpu_s"], 1), round(x["peak_rss_mib"], 1),
             round(x["tiles_per_s"], 2), round(x["us_per_sample"], 3),
             round(x.get("cpu_us_per_sample", x["cpu_s"] / x["samples"] * 1e6), 3),
             round(x["cpu_us_per_sample_after_startup"], 3) if "cpu_us_per_sample_after_startup" in x else "–",
             f"{x['bytes'] / 1e6:.1f} MB", x.get("date", "")] for x in results]  # fmt: skip
    table = md_table(["region", "samples", "tiles", "wall s", "CPU s", "peak RSS MiB", "tiles/s", "wall µs/sample",
                      "CPU µs/sample", "CPU µs/sample after start-up", "bytes", "run"], rows)  # fmt: skip
    per = {x["srtm_tiles"]: x["cpu_us_per_sample_after_startup"] for x in results
           if "cpu_us_per_sample_after_startup" in x}  # fmt: skip
    if 1 in per and len(per) > 1:
        big = max(per)
        table += (f"\nOne tile's CPU per sample after start-up over the {big}-tile mosaic's: "
                  f"**{per[1] / per[big]:.2f}x** (Cesium Terrain Builder's own: 1.3x).\n")  # fmt: skip
    note = (
        "\n`terralod export FOLDER --format quantized-mesh` (a fresh process, start-up included) on SRTM3 "
        f"{args.source} mirror-tiled into separate 1° GeoTIFFs (EPSG:4326); peak RSS of the process. "
        "Reproduce: `python benchmarks/region.py`.\n"
    )
    write_results("region", {"source": args.source, "runs": results}, table + note)


if __name__ == "__main__":
    main()
