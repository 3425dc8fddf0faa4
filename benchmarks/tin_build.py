"""Detail-increment TIN build (paper 003), end to end, per stage: read, dedup, Delaunay, split, QEM (with
the per-block measured errors), records, save; input points per second per stage and in total, medians of
3, on the Autzen cloud, Autzen tiled 4 × 4 (copies offset in xy) and the Puget Sound 513² crop as
jittered points. Side by side in one run: the build before this work (``--baseline-src``: a ``src``
folder exported from an older commit, run in a subprocess), 1 and 2 threads, and Dask (a LocalCluster of
2 worker processes); pyfqmr on the same TIN as a peer of the QEM stage.

    python benchmarks/tin_build.py [--baseline-src /tmp/tlbase/src] [--quick]

Writes benchmarks/results/tin_build.{json,md}.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import SHARED, md_table, write_results  # noqa: E402

STAGES = ("read", "dedup", "delaunay", "split", "qem", "records", "save")
AUTZEN = SHARED / "lidar" / "autzen_trim.laz"


# -- inputs -------------------------------------------------------------------------------------------------
def autzen_tiled(reps: int, out: Path) -> Path:
    """A LAS file of ``reps`` × ``reps`` copies of Autzen's points, offset in xy by the cloud's extent."""
    import laspy

    las = laspy.read(str(AUTZEN))
    x, y = np.asarray(las.x), np.asarray(las.y)
    sx, sy = float(las.header.scales[0]), float(las.header.scales[1])
    dx = int(round((float(x.max() - x.min()) + 1.0) / sx))  # offsets in the file's integer units
    dy = int(round((float(y.max() - y.min()) + 1.0) / sy))
    hdr = laspy.LasHeader(point_format=las.header.point_format, version=las.header.version)
    hdr.offsets = las.header.offsets
    hdr.scales = las.header.scales
    for vlr in las.header.vlrs:
        hdr.vlrs.append(vlr)
    big = laspy.LasData(hdr)
    pts = []
    for i in range(reps):
        for j in range(reps):
            a = las.points.array.copy()
            a["X"] += i * dx
            a["Y"] += j * dy
            pts.append(a)
    big.points = laspy.ScaleAwarePointRecord(np.concatenate(pts), hdr.point_format, hdr.scales, hdr.offsets)
    big.update_header()
    big.write(str(out))
    return out


def puget_points() -> np.ndarray:
    """The 513² Puget Sound crop of benchmarks/tin.py as points, xy jittered by up to ±20 m (1/8 cell)."""
    from tin import dem_crop

    _, hf = dem_crop()
    h, w = hf.shape
    xs, _ = hf.world_xy(np.zeros(w), np.arange(w))
    _, ys = hf.world_xy(np.arange(h), np.zeros(h))
    xx, yy = np.meshgrid(xs, ys)
    rng = np.random.default_rng(0)
    return np.stack([xx.ravel() + rng.uniform(-20, 20, xx.size), yy.ravel() + rng.uniform(-20, 20, xx.size),
                     np.asarray(hf.elevation_m, np.float64).ravel()], axis=1)  # fmt: skip


# -- one build ------------------------------------------------------------------------------------------
def build_once(src: str, k: int, workers: int | None, executor: Any, out: Path) -> dict[str, Any]:
    """Time one build of ``src`` (a .las/.laz path or a .npy of points) with the current terralod
    (``executor``: a Dask executor, its cluster started and warm, outside the time)."""
    from terralod.tin import DetailIncrementModel

    t: dict[str, float] = {}
    t0 = time.perf_counter()
    if src.endswith(".npy"):
        xyz = np.load(src)
        t["read"] = time.perf_counter() - t0
        m = DetailIncrementModel.from_points(xyz, sub_blocks=k * k, workers=workers, timings=t,
                                             executor=executor)  # fmt: skip
    else:
        m = DetailIncrementModel.from_las(
            src, sub_blocks=k * k, workers=workers, timings=t, executor=executor
        )
    t1 = time.perf_counter()
    size = m.save(out, workers=workers)
    t["save"] = time.perf_counter() - t1
    t["total"] = time.perf_counter() - t0
    import hashlib

    return {"s": t, "bytes": size, "sha256": hashlib.sha256(out.read_bytes()).hexdigest(),
            "vertices": int(m.vertices_m.shape[0]), "records": int(m.increments.n_records)}  # fmt: skip


_BASELINE = r"""
import json, sys
from pathlib import Path
sys.path.insert(0, sys.argv[5])
import tin_build as B
src, k, out, workers = sys.argv[1], int(sys.argv[2]), Path(sys.argv[3]), int(sys.argv[4])
B.build_once(str(B.AUTZEN), 2, workers, None, out)  # warm up: numba's cache loaded outside the time
print(json.dumps(B.build_once(src, k, workers, None, out)))
"""


def build_baseline(baseline_src: str, src: str, k: int, out: Path, workers: int = 2) -> dict[str, Any]:
    """:func:`build_once` with the terralod of ``baseline_src`` (a subprocess that warms up first, so the
    timed build is as warm as this process's), ``workers`` threads."""
    env = {**os.environ, "PYTHONPATH": baseline_src}
    here = str(Path(__file__).resolve().parent)
    r = subprocess.run([sys.executable, "-c", _BASELINE, src, str(k), str(out), str(workers), here], env=env,
                       capture_output=True, text=True, check=True)  # fmt: skip
    return json.loads(r.stdout.strip().splitlines()[-1])


def pyfqmr_s(src: str, k: int) -> float | None:
    """pyfqmr on the same Delaunay TIN down to 20 % of its triangles (the QEM stage's peer), seconds."""
    try:
        import pyfqmr
    except ImportError:
        return None
    from terralod.tin.delaunay import delaunay_tin
    from terralod.tin.pointcloud import check_points, read_las, thin_duplicates

    xyz = np.load(src) if src.endswith(".npy") else read_las(src).xyz_m
    p = check_points(xyz)
    v, t, _ = delaunay_tin(p[thin_duplicates(p, 0.01)])
    s = pyfqmr.Simplify()
    s.setMesh(v - v.mean(axis=0), t)
    a = time.perf_counter()
    s.simplify_mesh(target_count=int(0.2 * t.shape[0]), aggressiveness=7, preserve_border=True, verbose=0)
    return time.perf_counter() - a


def median_of(runs: list[dict[str, Any]]) -> dict[str, Any]:
    keys = sorted({k for r in runs for k in r["s"]})
    med = {k: float(np.median([r["s"].get(k, 0.0) for r in runs])) for k in keys}
    return {
        **runs[0],
        "s": med,
        "runs": [r["s"] for r in runs],
        "same_bytes": len({r["sha256"] for r in runs}) == 1,
    }


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--baseline-src", default=None, help="src folder of the build to compare with")
    ap.add_argument("--baseline-label", default="before", help="its row's name in the table")
    ap.add_argument("--quick", action="store_true", help="1 run each, Autzen only")
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--no-dask", action="store_true")
    args = ap.parse_args()
    reps = 1 if args.quick else args.reps
    tmp = Path(tempfile.mkdtemp(prefix="tin-build-"))
    cases: list[tuple[str, str, int]] = [("autzen (ground)", str(AUTZEN), 2)]
    if not args.quick:
        cases.append(("autzen 4x4 tiled (ground)", str(autzen_tiled(4, tmp / "autzen4x4.las")), 4))
        np.save(tmp / "puget.npy", puget_points())
        cases.append(("puget 513² jittered points", str(tmp / "puget.npy"), 3))
    # warm up (numba compiles or loads its cache; Dask starts once)
    build_once(str(AUTZEN), 2, 1, None, tmp / "w.tin")
    client = executor = None
    if not args.no_dask:
        from terralod.tin.distributed import close_client, dask_executor, open_client

        client = open_client("local", 2)
        executor = dask_executor(client)
        build_once(str(AUTZEN), 2, 2, executor, tmp / "wd.tin")
    if args.baseline_src:
        build_baseline(args.baseline_src, str(AUTZEN), 2, tmp / "wb.tin")
    results: list[dict[str, Any]] = []
    rows = []
    for name, src, k in cases:
        configs: list[tuple[str, Any]] = []
        if args.baseline_src:
            configs.append(
                (
                    args.baseline_label,
                    lambda s=src, k=k: build_baseline(args.baseline_src, s, k, tmp / "b.tin"),
                )
            )
        configs.append(("1 thread", lambda s=src, k=k: build_once(s, k, 1, None, tmp / "t1.tin")))
        configs.append(("2 threads", lambda s=src, k=k: build_once(s, k, 2, None, tmp / "t2.tin")))
        if not args.no_dask:
            configs.append(
                ("dask local, 2 workers", lambda s=src, k=k: build_once(s, k, 2, executor, tmp / "d2.tin"))
            )
        # the configurations interleaved, run by run: a busy spell of this shared machine hits them all
        runs: dict[str, list[dict[str, Any]]] = {label: [] for label, _ in configs}
        peer_runs = []
        for _ in range(reps):
            for label, fn in configs:
                runs[label].append(fn())
            peer_runs.append(pyfqmr_s(src, k))
        peer = None if peer_runs[0] is None else float(np.median(peer_runs))
        for label, _ in configs:
            r = median_of(runs[label])
            n_in = r["vertices"]
            r.update(case=name, config=label, k=k, pyfqmr_s=peer)
            results.append(r)
            s = r["s"]
            rows.append([name, label, n_in, round(s["total"], 2)]
                        + [f"{n_in / s[st] / 1e3:,.0f}" if s.get(st, 0) > 0 else "-" for st in STAGES]
                        + [f"{n_in / s['total'] / 1e3:,.1f}", r["bytes"], r["sha256"][:10]])  # fmt: skip
            print(rows[-1], flush=True)
    head = (
        ["cloud", "build", "points", "total s"]
        + [f"{st} k/s" for st in STAGES]
        + ["total k pts/s", "bytes", "sha256"]
    )
    md = ("# Detail-increment TIN build, end to end (paper 003)\n\n"
          f"Input points (TIN vertices) per second per stage, thousands; medians of {reps} runs, the "
          f"configurations interleaved run by run; {os.cpu_count()} cores, shared machine. QEM includes the "
          f"per-block measured errors. {args.baseline_label!r}, where present: the same timed build with "
          f"the terralod of ``--baseline-src``, 2 threads (in a subprocess, after a warm-up build there). Same sha256: the same file "
          "(the file names its source, so it differs between runs of this script).\n\n") + md_table(head, rows)  # fmt: skip
    peers = {r["case"]: r["pyfqmr_s"] for r in results}
    md += "\npyfqmr (same TIN, to 20 % of its triangles, 1 thread, median), seconds: " + ", ".join(
        f"{c}: {s:.2f}" for c, s in peers.items() if s is not None) + "\n"  # fmt: skip
    if client is not None:
        close_client(client)
    write_results("tin_build", {"reps": reps, "results": results}, md)


if __name__ == "__main__":
    main()
