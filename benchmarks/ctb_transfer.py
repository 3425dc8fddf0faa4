"""terralod's DEM → quantized-mesh export against Cesium Terrain Builder, carried over through a transfer run.

    python benchmarks/ctb_transfer.py [--tiles 16,64] [--rounds 3] [--baseline-rev 66b69d2]

ctb cannot be installed on this machine (no package, no GDAL headers to build it), and absolute µs per
sample move 1.5-2x between machines and sessions. The region issue's table measured ctb and terralod in one
session on one machine (ctb ``-f Mesh -C -c 1``; terralod's direct export of a single-file mosaic, in
memory):

    16-tile mosaic: ctb 2.34 µs/sample, terralod 1.14 (0.49 x ctb)
    64-tile mosaic: ctb 2.32 µs/sample, terralod 0.98 (0.42 x ctb)

That terralod is still here (``--baseline-rev``, the commit the issue measured, checked out as a git
worktree). This script runs it and today's terralod alternately, round by round, on the same mosaics
(``benchmarks/region.py``'s SRTM3 tile mirror-tiled: the baseline reads one GeoTIFF of the whole mosaic,
which it holds in memory; today's reads the folder of 1° GeoTIFFs window by window, as a user's region,
and also the single file), each in a fresh process (CPU = user + sys, start-up included; peak RSS), and
gives

    terralod / ctb  =  (today / baseline, medians, this machine)  x  (baseline / ctb, the issue's session)

which assumes that ctb and the baseline, both single-threaded CPU-bound C++ and numba code, move together
between machines (the transfer run's own spread is reported beside it).

Writes benchmarks/results/ctb_transfer.json and ctb_transfer.md.
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from region import _earlier_runs, run_export, write_mosaic  # noqa: E402

from _common import ROOT, SHARED, md_table, mirror_tile, write_results  # noqa: E402

#: The region issue's table (one session, one machine): µs per source sample and peak RSS (MiB).
ISSUE = {
    16: {"samples": 23_049_601, "ctb_us": 2.34, "ctb_mib": 146, "terralod_us": 1.14, "terralod_mib": 428},
    64: {"samples": 92_179_201, "ctb_us": 2.32, "ctb_mib": 437, "terralod_us": 0.98, "terralod_mib": 911},
}


def write_single(src: Path, n: int, dest: Path) -> Path:
    """The n x n mosaic as one GeoTIFF (the baseline reads one file)."""
    import rasterio
    from affine import Affine

    with rasterio.open(src) as ds:
        a, t, nodata = ds.read(1), ds.transform, ds.nodata
    big = mirror_tile(a, n)
    tt = Affine(t.a, 0.0, 1 - 0.5 * t.a, 0.0, t.e, 41 + n - 0.5 * t.e)
    with rasterio.open(dest, "w", driver="GTiff", width=big.shape[1], height=big.shape[0], count=1,
                       dtype=big.dtype, crs="EPSG:4326", transform=tt, nodata=nodata, tiled=True,
                       blockxsize=256, blockysize=256, compress="deflate", predictor=2) as ds:  # fmt: skip
        ds.write(big, 1)
    return dest


def baseline_tree(rev: str, where: Path) -> Path:
    """A git worktree of ``rev`` (its src/ is put first on PYTHONPATH for the baseline runs)."""
    subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "-f", "--detach", str(where), rev], check=True,
                   capture_output=True)  # fmt: skip
    return where / "src"


def run(inp: Path, out: Path, pythonpath: Path | None) -> dict:
    """One export in a fresh process: the baseline's (its src/ first on PYTHONPATH) or today's."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    if pythonpath is not None:
        env["PYTHONPATH"] = str(pythonpath)
    shutil.rmtree(out, ignore_errors=True)
    try:
        return run_export(inp, out, env)
    finally:
        shutil.rmtree(out, ignore_errors=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tiles", default="16,64")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--baseline-rev", default="66b69d2", help="the terralod the region issue measured")
    args = ap.parse_args()
    src = SHARED / "dem" / "srtm3_N41E001.tif"
    counts = [int(v) for v in args.tiles.split(",")]
    results, rows = _earlier_runs("ctb_transfer", counts), []
    with tempfile.TemporaryDirectory(prefix="terralod-ctb-transfer-") as d:
        tmp = Path(d)
        base_src = baseline_tree(args.baseline_rev, tmp / "baseline")
        try:
            # a warm-up of each (numba's on-disk caches of both trees), outside the figures
            run(src, tmp / "warm", base_src)
            run(src, tmp / "warm", None)
            for count in counts:
                n = int(round(count**0.5))
                single = write_single(src, n, tmp / f"mosaic{count}.tif")
                folder = tmp / f"mosaic{count}"
                write_mosaic(src, n, folder)
                runs: dict[str, list[dict]] = {"baseline (one file)": [], "today (folder)": [],
                                               "today (one file)": []}  # fmt: skip
                for _ in range(args.rounds):
                    for name, inp, pp in (("baseline (one file)", single, base_src), ("today (folder)", folder, None),
                                          ("today (one file)", single, None)):  # fmt: skip
                        r = run(inp, tmp / "out", pp)
                        r["load_1min"] = os.getloadavg()[0]
                        runs[name].append(r)
                        print(count, name, {k: v for k, v in r.items() if k != "stdout"}, flush=True)
                iss = ISSUE.get(count)
                med = {k: statistics.median(x["cpu_s"] for x in v) for k, v in runs.items()}
                samples = (1200 * n + 1) ** 2
                base = med["baseline (one file)"]
                for name, v in runs.items():
                    cpu = [x["cpu_s"] for x in v]
                    ratio_base = med[name] / base
                    vs_ctb = ratio_base * iss["terralod_us"] / iss["ctb_us"] if iss else None
                    res = {"srtm_tiles": count, "samples": samples, "run": name, "cpu_s": cpu,
                           "median_cpu_s": med[name], "us_per_sample": med[name] / samples * 1e6,
                           "peak_rss_mib": max(x["peak_rss_mib"] for x in v), "over_baseline": ratio_base,
                           "spread": (max(cpu) - min(cpu)) / med[name], "vs_ctb": vs_ctb,
                           "loads": [x["load_1min"] for x in v]}  # fmt: skip
                    results.append(res)
        finally:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(tmp / "baseline")],
                           capture_output=True)  # fmt: skip
    results.sort(key=lambda r: r["srtm_tiles"])
    for r in results:
        iss = ISSUE.get(r["srtm_tiles"])
        rows.append([f"{r['srtm_tiles']} SRTM3 tiles", r["run"], " / ".join(f"{c:.1f}" for c in r["cpu_s"]),
                     round(r["us_per_sample"], 3), round(r["peak_rss_mib"]), round(r["over_baseline"], 3),
                     f"{r['vs_ctb']:.2f}" if r["vs_ctb"] is not None else "–",
                     f"{iss['ctb_us']} µs, {iss['ctb_mib']} MiB" if iss else "–"])  # fmt: skip
    table = md_table(["mosaic", "run", "CPU s, each round", "µs/sample (median)", "peak RSS MiB",
                      "/ baseline", "terralod / ctb", "ctb (issue's session)"], rows)  # fmt: skip
    note = (
        f"\nBaseline: terralod at {args.baseline_rev}, the export the region issue measured beside ctb "
        "(its table: 16 tiles 1.14 µs/sample = 0.49 x ctb's 2.34; 64 tiles 0.98 = 0.42 x ctb's 2.32). "
        "terralod / ctb = (median CPU / the baseline's median CPU, here) x (the baseline's µs / ctb's, "
        f"there). {args.rounds} rounds, the runs alternating; a fresh process each (start-up included). "
        "Machine: 2 shared CPUs (1-minute loads in the JSON). Reproduce: `python benchmarks/ctb_transfer.py "
        f"--tiles 16,64 --rounds 3` (this run: --tiles {args.tiles} --rounds {args.rounds}, "
        f"{time.strftime('%Y-%m-%d %H:%M')}).\n"
    )
    write_results("ctb_transfer", {"issue": ISSUE, "baseline_rev": args.baseline_rev, "runs": results},
                  table + note)  # fmt: skip


if __name__ == "__main__":
    main()
