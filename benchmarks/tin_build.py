"""Detail-increment TIN build (paper 003), end to end, per stage: read, dedup, Delaunay, split, QEM (with
the per-block measured errors), records, save; input points per second per stage and in total, medians of
3, on the Autzen cloud, Autzen tiled 4 × 4 (copies offset in xy) and the Puget Sound 513² crop as
jittered points. Side by side in one run: the build before this work (``--baseline-src``: a ``src``
folder exported from an older commit, run in a subprocess), 1 and 2 threads, and Dask (a LocalCluster of
2 worker processes); pyfqmr on the same TIN as a peer of the QEM stage.

Scale series (``--points 1M,10M``, issue 55): jittered points sampled from a real DEM (the Puget Sound 1k,
mirror-tiled when more samples are needed; :func:`jittered_dem_points`) written as one LAS file of ground
points, then per size one fresh process runs the build end to end the way ``terralod build --method tin``
does (read and ground selection, dedup, Delaunay, split, QEM, records, the ``.terra`` store), with its
process tree's peak RSS sampled by psutil (:func:`run_tree`, killed above ``--max-rss-gib``); in the same
run, each in its own process on the same points: scipy.spatial.Delaunay, Triangle (``triangle``) and
pyfqmr (scipy's Delaunay mesh simplified to the terralod base's triangle count).

    python benchmarks/tin_build.py [--baseline-src /tmp/tlbase/src] [--quick]
    python benchmarks/tin_build.py --points 1M,10M [--baseline-src /tmp/tlbase/src] [--no-peers]

Writes benchmarks/results/tin_build.{json,md} (the scale series: its section and key "scale" there).
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

from _common import SHARED, md_table, tree_peak_rss, write_results  # noqa: E402

STAGES = ("read", "dedup", "delaunay", "split", "qem", "records", "save")
SCALE_STAGES = ("read", "dedup", "delaunay", "split", "qem", "records", "store")
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


# -- scale series (issue 55): one fresh process per size, peak RSS of its process tree ----------------------
def parse_count(text: str) -> int:
    """'10M' -> 10_000_000, '500k' -> 500_000, '2500' -> 2500."""
    t = text.strip().lower()
    mult = {"k": 10**3, "m": 10**6, "g": 10**9}.get(t[-1:], 1)
    return int(float(t[:-1] if mult > 1 else t) * mult)


def jittered_dem_points(n_points: int, seed: int = 0) -> np.ndarray:
    """(about ``n_points``, 3) float64: the samples of a side × side crop of the real Puget Sound 1k DEM
    (160 m; mirror-tiled with :func:`_common.mirror_tile` when the side passes 1025), each moved in xy by up
    to ±20 m (1/8 cell), heights as they are. side = round(sqrt(n_points))."""
    from _common import mirror_tile, puget_sound_1k

    hf = puget_sound_1k()
    if hf is None:
        raise SystemExit("the Puget Sound 1k DEM is missing from ../shared/data/dem")
    side = max(2, int(round(n_points**0.5)))
    z = np.asarray(hf.elevation_m, np.float64)
    reps = max(1, -(-(side - 1) // (z.shape[0] - 1)))
    if reps > 1:
        z = mirror_tile(z, reps)
    z = z[:side, :side]
    rng = np.random.default_rng(seed)
    out = np.empty((side * side, 3), np.float64)
    xx, yy = np.meshgrid(500000.0 + 160.0 * np.arange(side), 5300000.0 - 160.0 * np.arange(side))
    out[:, 0] = xx.ravel() + rng.uniform(-20.0, 20.0, side * side)
    del xx
    out[:, 1] = yy.ravel() + rng.uniform(-20.0, 20.0, side * side)
    del yy
    out[:, 2] = z.ravel()
    return out


def write_ground_las(xyz: np.ndarray, out: Path) -> Path:
    """``xyz`` as a LAS 1.4 file (point format 6, 1 mm steps), every point classified ground (2)."""
    import laspy

    hdr = laspy.LasHeader(point_format=6, version="1.4")
    hdr.scales = np.array([0.001, 0.001, 0.001])
    hdr.offsets = np.floor(xyz.min(axis=0))
    las = laspy.LasData(hdr)
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    las.classification = np.full(xyz.shape[0], 2, np.uint8)
    las.write(str(out))
    return out


def run_tree(
    cmd: list[str], env: dict[str, str] | None = None, max_rss_b: float = float("inf")
) -> dict[str, Any]:
    """``cmd`` in a fresh process: wall seconds, CPU seconds of the tree, peak RSS summed over the process
    tree (psutil, every 50 ms; see benchmarks/region.py), its last stdout line as JSON. Killed (and
    ``killed`` set) when the tree passes ``max_rss_b`` bytes: the machine is shared."""

    t0 = time.perf_counter()
    before = os.times()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    peak, why = tree_peak_rss(proc, max_rss_b=max_rss_b)
    killed = why is not None
    out, err = proc.communicate()
    after = os.times()
    res: dict[str, Any] = {"wall_s": time.perf_counter() - t0, "peak_rss_mib": peak / 2**20, "killed": killed,
                           "cpu_s": (after.children_user - before.children_user)
                           + (after.children_system - before.children_system)}  # fmt: skip
    if proc.returncode != 0 and not killed:
        raise RuntimeError(err[-3000:])
    lines = out.strip().splitlines()
    if lines and not killed:
        res.update(json.loads(lines[-1]))
    return res


_SCALE_BUILD = r"""
import json, sqlite3, sys, time
from terralod.tin import DetailIncrementModel
from terralod.tin.terra import save_model_to_store
t0 = time.perf_counter()
src, out, workers = sys.argv[1], sys.argv[2], int(sys.argv[3])
t = {}
m = DetailIncrementModel.from_las(src, sub_blocks="auto", workers=workers, timings=t)
t1 = time.perf_counter()
summary = save_model_to_store(m, out, overwrite=True, workers=workers)
t["store"] = time.perf_counter() - t1
t["total"] = time.perf_counter() - t0
con = sqlite3.connect(out)
sha = con.execute("SELECT sha256 FROM tin_model").fetchone()[0]
con.close()
print(json.dumps({"s": t, "vertices": int(m.vertices_m.shape[0]), "sub_blocks": m.n_blocks,
                  "base_triangles": summary["base_triangles"], "bytes": summary["size_bytes"],
                  "model_sha256": sha}))
"""

_SCALE_PEER = r"""
import json, sys, time
import numpy as np
import laspy
tool, src = sys.argv[1], sys.argv[2]
las = laspy.read(src)
xyz = np.stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)], axis=1)
del las
xy = xyz[:, :2] - xyz[:, :2].min(axis=0)
res = {}
import pyfqmr, triangle
from scipy.spatial import Delaunay
t0 = time.perf_counter()
if tool == "triangle":
    tri = triangle.triangulate({"vertices": xy}, "Q")["triangles"]
    res["triangles"] = int(tri.shape[0])
else:
    tri = Delaunay(xy).simplices
    res["triangles"] = int(tri.shape[0])
    if tool == "pyfqmr":
        res["delaunay_s"] = time.perf_counter() - t0
        s = pyfqmr.Simplify()
        s.setMesh(xyz - xyz.mean(axis=0), tri.astype(np.int32))
        target = int(sys.argv[3])
        t1 = time.perf_counter()
        s.simplify_mesh(target_count=target, aggressiveness=7, preserve_border=True, verbose=0)
        res["simplify_s"] = time.perf_counter() - t1
        res["target"] = target
        res["kept"] = int(s.getMesh()[1].shape[0])
res["s"] = time.perf_counter() - t0
print(json.dumps(res))
"""


def scale_series(sizes: list[int], baseline_src: str | None, baseline_label: str, peers: bool, workers: int,
                 max_rss_gib: float) -> None:  # fmt: skip
    """The rows of ``--points`` (see the module docstring): per size, the build (and the baseline's, when
    given) in fresh processes, then the peers on the same points."""
    tmp = Path(tempfile.mkdtemp(prefix="tin-build-scale-"))
    here = Path(__file__).resolve().parents[1]
    cap = max_rss_gib * 2**30
    results: list[dict[str, Any]] = []
    rows: list[list[Any]] = []
    peer_rows: list[list[Any]] = []
    # numba's cache loaded (or compiled) once before any timed build
    warm = write_ground_las(jittered_dem_points(20_000), tmp / "warm.las")
    for src_dir in [None] + ([baseline_src] if baseline_src else []):
        env = {**os.environ, "PYTHONPATH": src_dir or str(here / "src")}
        run_tree([sys.executable, "-c", _SCALE_BUILD, str(warm), str(tmp / "warm.terra"), str(workers)], env)
    for n in sizes:
        las = write_ground_las(jittered_dem_points(n), tmp / f"points_{n}.las")
        configs = [("this build", str(here / "src"))]
        if baseline_src:
            configs.insert(0, (baseline_label, baseline_src))
        base_tris = None
        for label, src_dir in configs:
            env = {**os.environ, "PYTHONPATH": src_dir}
            r = run_tree([sys.executable, "-c", _SCALE_BUILD, str(las), str(tmp / "s.terra"), str(workers)], env,
                         cap)  # fmt: skip
            r.update(points=n, build=label, workers=workers)
            results.append(r)
            if r["killed"]:
                rows.append([f"{n:,}", label, "-", "-"] + ["-"] * len(SCALE_STAGES)
                            + ["-", f"> {max_rss_gib:g} GiB (killed)", "-", "-"])  # fmt: skip
                continue
            s, nv = r["s"], r["vertices"]
            base_tris = r["base_triangles"]
            rows.append([f"{n:,}", label, f"{nv:,}", round(s["total"], 1)]
                        + [f"{nv / s[st] / 1e3:,.0f}" if s.get(st, 0) > 0 else "-" for st in SCALE_STAGES]
                        + [f"{nv / s['total'] / 1e3:,.1f}", f"{r['peak_rss_mib']:,.0f}", round(r["cpu_s"], 1),
                           r["model_sha256"][:10]])  # fmt: skip
            print(rows[-1], flush=True)
        if peers:
            for tool in ("scipy", "triangle", "pyfqmr"):
                if tool == "pyfqmr" and base_tris is None:
                    continue
                cmd = [sys.executable, "-c", _SCALE_PEER, tool, str(las), str(base_tris or 0)]
                try:
                    r = run_tree(cmd, None, cap)
                except RuntimeError as exc:
                    print(f"{tool}: failed ({str(exc)[-300:]})", flush=True)
                    continue
                r.update(points=n, build=tool)
                results.append(r)
                what = {"scipy": "scipy.spatial.Delaunay (xy)", "triangle": "Triangle (xy, Delaunay)",
                        "pyfqmr": "scipy Delaunay + pyfqmr to the base's triangle count"}[tool]  # fmt: skip
                if r["killed"]:
                    peer_rows.append([f"{n:,}", what, "-", "-", f"> {max_rss_gib:g} GiB (killed)"])
                else:
                    peer_rows.append([f"{n:,}", what, round(r["s"], 1), f"{n / r['s'] / 1e3:,.1f}",
                                      f"{r['peak_rss_mib']:,.0f}"])  # fmt: skip
                print(peer_rows[-1], flush=True)
        las.unlink()
    head = (["points asked", "build", "vertices", "total s"] + [f"{st} k/s" for st in SCALE_STAGES]
            + ["total k pts/s", "peak RSS MiB", "CPU s", "model sha256"])  # fmt: skip
    md = ("# Detail-increment TIN build at survey scale (issue 55)\n\n"
          "Jittered points sampled from the real Puget Sound 1k DEM (mirror-tiled past 1025²; 160 m cells, xy "
          "moved by up to ±20 m), one LAS file of ground points; per size one fresh process builds the "
          "`.terra` store end to end as `terralod build --method tin` does (sub-blocks auto, "
          f"{workers} threads). Stage rates: TIN vertices per second, thousands (read: LAS read and ground "
          "selection; store: the model's file and the SQLite store). Peak RSS: the process tree, psutil "
          f"every 50 ms. {os.cpu_count()} cores, shared machine (other jobs running): one run each.\n\n"
          + md_table(head, rows))  # fmt: skip
    if peer_rows:
        md += ("\nPeers on the same points, each in its own process (read from the same LAS, outside the time; "
               "seconds of the call alone):\n\n"
               + md_table(["points", "peer", "s", "k pts/s", "peak RSS MiB"], peer_rows))  # fmt: skip
    # beside the per-stage table of the default run: tin_build.{json,md} keep it, this section replaced
    from _common import RESULTS

    marker = "\n## Scale series"
    md = md.replace(
        "# Detail-increment TIN build at survey scale (issue 55)", marker.strip() + " (issue 55)", 1
    )
    old_md = RESULTS / "tin_build.md"
    old_json = RESULTS / "tin_build.json"
    prev_md = old_md.read_text().split(marker)[0].rstrip("\n") + "\n\n" if old_md.exists() else ""
    prev = json.loads(old_json.read_text()) if old_json.exists() else {}
    prev.pop("machine", None)
    prev["scale"] = {"sizes": sizes, "workers": workers, "results": results}
    write_results("tin_build", prev, prev_md + md)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--baseline-src", default=None, help="src folder of the build to compare with")
    ap.add_argument("--baseline-label", default="before", help="its row's name in the table")
    ap.add_argument("--quick", action="store_true", help="1 run each, Autzen only")
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--no-dask", action="store_true")
    ap.add_argument("--points", default=None, help="scale series instead: sizes such as 1M,10M")
    ap.add_argument("--no-peers", action="store_true", help="scale series without scipy, Triangle, pyfqmr")
    ap.add_argument("--workers", type=int, default=2, help="threads of the scale series' builds")
    ap.add_argument("--max-rss-gib", type=float, default=16.0, help="kill a scale-series process above this")
    args = ap.parse_args()
    if args.points:
        sizes = [parse_count(x) for x in args.points.split(",") if x.strip()]
        scale_series(
            sizes, args.baseline_src, args.baseline_label, not args.no_peers, args.workers, args.max_rss_gib
        )
        return
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
