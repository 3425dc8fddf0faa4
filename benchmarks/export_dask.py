"""``terralod export FOLDER --format quantized-mesh`` here vs ``--dask local`` with 1 and 2 workers.

    python benchmarks/export_dask.py [--tiles 16] [--source srtm3_N41E001]   (--tiles 64: the issue's target)

The mosaic is benchmarks/region.py's (the real SRTM3 tile mirror-tiled into n x n separate 1° EPSG:4326
GeoTIFFs). Three runs of the export in a fresh process each: local (the tiles encoded in the process),
``--dask local --dask-workers 1`` and ``--dask-workers 2`` (one thread a worker; NUMBA/OMP/MKL threads
pinned to 1 in every run). Rows: wall, CPU (user + sys) of the whole process tree (the workers included:
each process waits for its children), peak RSS summed over the process tree (psutil, every 50 ms), tiles
per second, and whether the output is byte for byte the local run's (every file, layer.json included).
Speed-up: the 1-worker run's wall over the 2-worker run's (target on the 64-tile mosaic: >= 1.5).
Writes benchmarks/results/export_dask.json and export_dask.md.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from region import run_tree, write_mosaic  # noqa: E402

from _common import SHARED, md_table, write_results  # noqa: E402

PINNED = {
    "NUMBA_NUM_THREADS": "1",
    "OMP_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
}
RUNS = {"local": [], "dask 1 worker": ["--dask", "local", "--dask-workers", "1"],
        "dask 2 workers": ["--dask", "local", "--dask-workers", "2"]}  # fmt: skip


def digest(out: Path) -> str:
    """One sha256 over every file of an output (relative path and bytes, in path order)."""
    h = hashlib.sha256()
    for f in sorted(p for p in out.rglob("*") if p.is_file()):
        h.update(str(f.relative_to(out)).encode() + b"\0" + f.read_bytes())
    return h.hexdigest()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tiles", type=int, default=16, help="mosaic size in SRTM tiles (a square: 16, 64)")
    ap.add_argument("--source", default="srtm3_N41E001", help="the real SRTM3 tile mirrored")
    args = ap.parse_args()
    n = int(round(args.tiles**0.5))
    assert n * n == args.tiles, f"Expected a square number of tiles, got {args.tiles}"
    os.environ.update(PINNED)
    rows, runs = [], []
    with tempfile.TemporaryDirectory(prefix="terralod-export-dask-") as d:
        folder = Path(d) / "dem"
        write_mosaic(SHARED / "dem" / f"{args.source}.tif", n, folder)
        want = None
        for name, extra in RUNS.items():
            out = Path(d) / name.replace(" ", "-")
            load = os.getloadavg()[0]
            r = run_tree([sys.executable, "-m", "terralod", "export", str(folder), "--format", "quantized-mesh",
                          "-o", str(out), *extra])  # fmt: skip
            tiles = sum(1 for _ in out.rglob("*.terrain"))
            got = digest(out)
            want = want or got
            res = {"run": name, "tiles": tiles, "wall_s": r["wall_s"], "cpu_s": r["cpu_s"],
                   "peak_rss_mib": r["peak_rss_mib"], "tiles_per_s": tiles / float(r["wall_s"]),
                   "identical": got == want, "sha256": got, "load_1min_before": load}  # fmt: skip
            runs.append(res)
            print(res, flush=True)
    one, two = runs[1]["wall_s"], runs[2]["wall_s"]
    speedup = float(one) / float(two)
    for x in runs:
        rows.append([x["run"], x["tiles"], round(x["wall_s"], 1), round(x["cpu_s"], 1),
                     round(x["peak_rss_mib"], 1), round(x["tiles_per_s"], 2), "yes" if x["identical"] else "NO",
                     round(x["load_1min_before"], 2)])  # fmt: skip
    table = md_table(["run", "tiles", "wall s", "CPU s (tree)", "peak RSS MiB (tree)", "tiles/s",
                      "bytes = local", "load before"], rows)  # fmt: skip
    note = (
        f"\n{args.tiles} SRTM3 tiles ({1200 * n + 1}² samples, {args.source} mirror-tiled, EPSG:4326 GeoTIFFs): "
        f"2 workers over 1: {speedup:.2f}x. A fresh process each (start-up and the local cluster's included), "
        "one thread a worker, NUMBA/OMP threads 1. Machine: "
        f"{os.cpu_count()} CPUs, shared with other work (the 1-minute load before each run is listed). "
        f"Reproduce: `python benchmarks/export_dask.py --tiles {args.tiles}` ({time.strftime('%Y-%m-%d %H:%M')}).\n"
    )
    write_results("export_dask", {"source": args.source, "srtm_tiles": args.tiles, "speedup_2_over_1": speedup,
                                  "runs": runs}, table + note)  # fmt: skip


if __name__ == "__main__":
    main()
