"""Build throughput and triangles at equal true error: adaptive vs cohesion vs chunked stores, side by side
with pydelatin and pymartini, in one run on the same real DEMs.

For each terrain (the Pyrenees SRTM3 tile N42E001 as ``read_heightfield`` gives it, 1644 x 1230 at 68.5 m
in UTM 31N; Puget Sound 1k PNG, 1025² at 160 m, elevation = value x 0.1; with ``--big`` also the 4097²
mirror-tiling of Puget Sound) and each tile method (M = 65, all cores):

1. build throughput: the whole ``.terra`` pyramid with measured errors, built ``--reps`` times (default 3)
   in one fresh subprocess after a warm-up build that compiles the kernels; median seconds, source samples
   per second (width x height / seconds), peak RSS, store size;
2. triangles at equal true max vertical error, for each target T in TARGETS_M: the store's uniform cut (the
   coarsest tiles whose stored vertical error is <= T; "unreachable" when a finest tile is above T) against
   a single adaptive mesh of each peer at T: pydelatin (``max_error=T``) and pymartini (its error parameter
   lowered by 0.8x steps until the measured error is <= T: its own bound is not an upper bound). Every
   mesh's true max vertical and Hausdorff error is re-measured at every source sample by
   :func:`terralod.measure_error` (the cut: all its tiles as stored, one mesh). GPU memory per triangle
   is the renderer's layout: 24 bytes a vertex (float32 position + normal) and 12 a triangle (uint32);
   ``adaptive`` is the default (root error from a regular tile's vertex count, halving per level, the
   finest level the lossless grid); ``adaptive_ladder`` the halving ladder down to the finest level too;
   ``adaptive_lossless`` the default ladder with a greedy finest level at 0.5 m instead of the grid;
   ``--methods adaptive_fine`` runs the ladder from a near-lossless finest level (0.5 m) halving upward with
   every tile capped at M^2 vertices, ``--methods adaptive_dense`` the ladder with a root of 4 M^2 vertices
   down to the finest level (``benchmarks/results/build_adaptive_dense.md``, renamed from that run's
   ``build.md``);
3. the 2 px camera path of ``benchmarks/cohesion_vs_chunked.py`` (a circle over the terrain, 20 degrees
   down, 1920 x 1080): triangles drawn per frame, the worst drawn screen error, GPU MiB of the frame.

Writes ``benchmarks/results/build.json`` and ``build.md``.
Run: ``python benchmarks/build.py [--quick] [--big] [--reps N] [--frames N] [--methods a,b] [--terrains a,b]
[--name build]`` (``--name`` writes ``benchmarks/results/<name>.json/.md``).
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from terralod import Engine, Heightfield, build_store, measure_error, open_store  # noqa: E402
from terralod.io.reader import read_heightfield  # noqa: E402
from terralod.pyramid import adaptive  # noqa: E402
from terralod.pyramid.builder import default_tile_size, register_method  # noqa: E402
from terralod.tiles import parent  # noqa: E402

from _common import SHARED, md_table, puget_sound_1k, puget_sound_4k, write_results  # noqa: E402

#: Max vertical error targets, metres, at which triangle counts are compared.
TARGETS_M = (5.0, 10.0, 20.0, 40.0, 80.0)
#: Store methods as ``name@M`` (tile size M; without it the method's default: 33 for adaptive tiles, 65
#: for cohesion and chunked).
METHODS = ("adaptive", "adaptive@65", "adaptive@17", "adaptive_ladder", "adaptive_lossless", "cohesion",
           "chunked", "chunked@33")  # fmt: skip
TILE_SIZE = 65
#: The adaptive ladder from the other end: a near-lossless finest level (0.5 m), halving upward, every tile
#: capped at a regular tile's M^2 vertices (coarse tiles then stop above their target, measured).
register_method("adaptive_fine", adaptive.make_mesher(finest_error_m=0.5, max_tile_vertices=TILE_SIZE**2))
#: The default ladder with a near-lossless greedy finest level (0.5 m) instead of the grid.
register_method("adaptive_lossless", adaptive.make_mesher(finest_level_error_m=0.5))
#: The default ladder with a root of 4 M^2 vertices (every level's target halved).
register_method(
    "adaptive_dense", adaptive.make_mesher(root_vertices=4 * TILE_SIZE**2, finest_level_error_m=None)
)
#: GPU bytes of the renderer (terralod.render.renderer): per vertex, per triangle.
GPU_VERTEX_BYTES = 24
GPU_TRIANGLE_BYTES = 12


def _terrain(name: str) -> Heightfield | None:
    if name == "pyrenees_srtm3_N42E001":
        p = SHARED / "dem" / "srtm3_N42E001.tif"
        return read_heightfield(p) if p.exists() else None
    if name == "puget_sound_1k":
        return puget_sound_1k()
    if name == "puget_sound_4k_mirror":
        return puget_sound_4k()
    raise ValueError(name)


def method_spec(spec: str) -> tuple[str, int]:
    """``(method, tile size)`` of ``name`` or ``name@M`` (the method's default tile size without ``@M``)."""
    name, _, m = spec.partition("@")
    return name, int(m) if m else default_tile_size(name)


def label(spec: str) -> str:
    """``spec`` with its tile size: "adaptive" -> "adaptive M=33"."""
    name, m = method_spec(spec)
    return f"{name} M={m}"


def child_build(name: str, spec: str, out: str, reps: int) -> None:
    """Runs in a subprocess: warm the kernels, build one store ``reps`` times, print JSON."""
    hf = _terrain(name)
    assert hf is not None
    method, tile_size = method_spec(spec)
    warm = np.random.default_rng(0).normal(0.0, 50.0, (140, 140)).astype(np.float32)
    build_store(Heightfield.from_array(warm, 30.0), out + ".warm", tile_size=tile_size, method=method)
    secs, cpu = [], []
    for _ in range(reps):
        adaptive._LADDERS.clear()  # every rep measures its ladder afresh, as a user's one build does
        t = time.perf_counter()
        c = time.process_time()
        build_store(hf, out, tile_size=tile_size, method=method, overwrite=True)
        secs.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
    print(json.dumps({"seconds": secs, "cpu_seconds": cpu, "peak_rss_mib": _own_peak_rss_kib() / 1024}))


def _own_peak_rss_kib() -> int:
    """This process's peak resident set, KiB: the VmHWM of its own address space (getrusage's ru_maxrss is
    not: Linux carries the parent's high-water mark across fork and exec into the child's)."""
    status = Path("/proc/self/status")
    lines = status.read_text().splitlines() if status.exists() else []
    hwm = [int(line.split()[1]) for line in lines if line.startswith("VmHWM:")]
    return hwm[0] if hwm else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss


def uniform_cut(store, target_m: float) -> list[tuple[int, int, int]] | None:
    """The coarsest tiles whose stored vertical error is <= target (None when a finest tile is above it)."""
    errs = store.tile_errors()
    top = store.pyramid.max_level
    if any(v > target_m for (k, _, _), (_e, v) in errs.items() if k == top):
        return None
    return [
        c
        for c, (_e, v) in errs.items()
        if v <= target_m and (parent(c) is None or errs[parent(c)][1] > target_m)
    ]


def cut_mesh(store, codes) -> tuple[np.ndarray, np.ndarray]:
    """All tiles of ``codes`` as stored, one (vertices, triangles) mesh in world metres."""
    vs, ts, n = [], [], 0
    for c in codes:
        t = store.tile(*c)
        vs.append(t.vertices)
        ts.append(t.triangles.astype(np.int64) + n)
        n += len(t.vertices)
    return np.concatenate(vs), np.concatenate(ts)


def _world(hf: Heightfield, cols: np.ndarray, rows: np.ndarray) -> np.ndarray:
    x, y = hf.world_xy(rows, cols)
    return np.c_[x, y, hf.elevation_m[rows.astype(int), cols.astype(int)]]


def run_peers(hf: Heightfield, targets: list[float]) -> list[dict]:
    from pydelatin import Delatin
    from pymartini import Martini

    z = hf.elevation_m
    n = z.shape[0]
    out = []
    martini_ok = z.shape[0] == z.shape[1] and ((n - 1) & (n - 2)) == 0
    for target in targets:
        if martini_ok:
            param = target
            for _ in range(12):
                t = time.perf_counter()
                tile = Martini(n).create_tile(z)
                v, tri = tile.get_mesh(param)
                secs = time.perf_counter() - t
                v = v.reshape(-1, 2).astype(np.float64)
                tri = tri.reshape(-1, 3).astype(np.int64)
                rep = measure_error(_world(hf, v[:, 0], v[:, 1]), tri, hf)
                if rep.max_vertical_m <= target:
                    break
                param *= 0.8
            out.append({"method": f"pymartini (param {param:.3g} m)", "target_m": target, "seconds": secs,
                        "triangles": len(tri), "vertices": len(v), "max_vertical_m": rep.max_vertical_m,
                        "hausdorff_m": rep.hausdorff_m})  # fmt: skip
        t = time.perf_counter()
        d = Delatin(z.astype(np.float64), max_error=target)
        secs = time.perf_counter() - t
        # pydelatin's y axis points north: row = (H - 1) - y
        cols = d.vertices[:, 0].astype(np.float64)
        rows = (z.shape[0] - 1) - d.vertices[:, 1].astype(np.float64)
        rep = measure_error(_world(hf, cols, rows), d.triangles.astype(np.int64), hf)
        out.append({"method": "pydelatin", "target_m": target, "seconds": secs, "triangles": len(d.triangles),
                    "vertices": len(d.vertices), "max_vertical_m": rep.max_vertical_m,
                    "hausdorff_m": rep.hausdorff_m})  # fmt: skip
    return out


def delatin_ladder(hf: Heightfield, ladder_m: list[float], reps: int) -> dict:
    """pydelatin meshing the whole terrain once at each non-zero target of an adaptive store's ladder (what
    the store's greedy levels reach, one mesh a level, without measuring or coding): median of ``reps``
    of the summed seconds (one thread), and the seconds and triangles per target."""
    from pydelatin import Delatin

    z = hf.elevation_m.astype(np.float64)
    targets = [float(t) for t in ladder_m if t > 0]
    per: list[list[float]] = [[] for _ in targets]
    tris = [0] * len(targets)
    for _ in range(reps):
        for i, target in enumerate(targets):
            t = time.perf_counter()
            d = Delatin(z, max_error=target)
            per[i].append(time.perf_counter() - t)
            tris[i] = len(d.triangles)
    sums = [sum(p[r] for p in per) for r in range(reps)]
    return {"targets_m": targets, "seconds_total": sums, "median_s": statistics.median(sums),
            "seconds": [statistics.median(p) for p in per], "triangles": tris}  # fmt: skip


def camera_path(store, frames: int) -> dict:
    """Triangles, worst screen error and GPU bytes along the 2 px circle of cohesion_vs_chunked.py."""
    from cohesion_vs_chunked import path

    eng = Engine(store, 2.0)
    tri, worst, gpu = [], [], []
    for cam in path(store, frames):
        sel = eng.update(cam)
        tri.append(sel.stats.triangles)
        worst.append(sel.stats.max_screen_error_px)
        gpu.append(
            sum(GPU_VERTEX_BYTES * len(v) + GPU_TRIANGLE_BYTES * len(t) for _c, v, t, _n in sel.meshes())
        )
    return {"triangles": tri, "max_screen_error_px": worst, "gpu_bytes": gpu}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--child", nargs=4, metavar=("TERRAIN", "METHOD", "OUT", "REPS"), help=argparse.SUPPRESS)
    ap.add_argument("--quick", action="store_true", help="Puget Sound 1k only, one build each")
    ap.add_argument("--big", action="store_true", help="also the 4097² mirror of Puget Sound")
    ap.add_argument("--reps", type=int, default=3, help="builds per method (median)")
    ap.add_argument("--frames", type=int, default=24, help="frames of the camera path")
    ap.add_argument("--methods", default=",".join(METHODS))
    ap.add_argument("--terrains", default="", help="comma-separated terrain names (default: all of the mode)")
    ap.add_argument("--name", default="build", help="results file name under benchmarks/results/")
    args = ap.parse_args()
    if args.child:
        child_build(args.child[0], args.child[1], args.child[2], int(args.child[3]))
        return
    methods = args.methods.split(",")
    reps = 1 if args.quick else args.reps
    names = ["puget_sound_1k"] if args.quick else ["pyrenees_srtm3_N42E001", "puget_sound_1k"]
    names += ["puget_sound_4k_mirror"] if args.big else []
    if args.terrains:
        names = args.terrains.split(",")
    results: dict = {
        "tile_size": {m: method_spec(m)[1] for m in methods},
        "targets_m": list(TARGETS_M),
        "reps": reps,
        "terrains": {},
    }
    build_rows, cut_rows, path_rows, ratio_rows = [], [], [], []
    with tempfile.TemporaryDirectory() as tmp:
        for name in names:
            hf = _terrain(name)
            if hf is None:
                print(f"skip {name}: ../shared/data not present", flush=True)
                continue
            samples = hf.width * hf.height
            rec: dict = {"size": [hf.width, hf.height], "spacing_m": list(hf.spacing_m), "methods": {}}
            t = time.perf_counter()
            peers = run_peers(hf, list(TARGETS_M))
            rec["peers"] = peers
            rec["peer_seconds_total"] = time.perf_counter() - t
            for method in methods:
                out = str(Path(tmp) / f"{name}_{method}.terra")
                cmd = [sys.executable, __file__, "--child", name, method, out, str(reps)]
                print(f"{name}: building {method} x{reps}", flush=True)
                res = json.loads(subprocess.run(cmd, check=True, capture_output=True, text=True).stdout.strip()
                                 .splitlines()[-1])  # fmt: skip
                med = statistics.median(res["seconds"])
                cpu = statistics.median(res["cpu_seconds"])
                m: dict = {"build_seconds": res["seconds"], "build_median_s": med, "samples_per_s": samples / med,
                           "cpu_seconds": res["cpu_seconds"], "cpu_median_s": cpu,
                           "peak_rss_mib": res["peak_rss_mib"], "cut": {}}  # fmt: skip
                with open_store(out) as s:
                    m["store_mib"] = s.size_bytes() / 2**20
                    m["ladder_m"] = s.meta["build_options"].get("target_error_m")
                    summ = {(r["level"], r["x"], r["y"]): r for r in s.tile_summaries()}
                    m["tiles"] = len(summ)
                    m["triangles_total"] = sum(r["n_triangles"] for r in summ.values())
                    m["bytes_per_triangle"] = s.size_bytes() / max(m["triangles_total"], 1)
                    for target in TARGETS_M:
                        codes = uniform_cut(s, target)
                        if codes is None:
                            m["cut"][str(target)] = None
                            continue
                        v, tr = cut_mesh(s, codes)
                        rep = measure_error(v, tr, hf)
                        m["cut"][str(target)] = {"tiles": len(codes), "triangles": len(tr), "vertices": len(v),
                                                 "max_vertical_m": rep.max_vertical_m, "hausdorff_m": rep.hausdorff_m,
                                                 "gpu_bytes_per_triangle": (GPU_VERTEX_BYTES * len(v)
                                                                            + GPU_TRIANGLE_BYTES * len(tr)) / len(tr)}  # fmt: skip
                    m["path"] = camera_path(s, args.frames)
                rec["methods"][method] = m
                build_rows.append([name, f"{hf.width}x{hf.height}", label(method), m["tiles"], med, samples / med / 1e6,
                                   cpu, m["peak_rss_mib"], m["store_mib"], m["bytes_per_triangle"]])  # fmt: skip
            for p in sorted({p["method"].split(" ")[0] for p in peers}):
                secs = [q["seconds"] for q in peers if q["method"].startswith(p)]
                build_rows.append([name, f"{hf.width}x{hf.height}", f"{p} (one mesh, 5-80 m)", 1,
                                   statistics.median(secs), samples / statistics.median(secs) / 1e6,
                                   statistics.median(secs), "", "", ""])  # fmt: skip
            if rec["methods"].get("adaptive", {}).get("ladder_m"):
                lad = delatin_ladder(hf, rec["methods"]["adaptive"]["ladder_m"], reps)
                rec["pydelatin_ladder"] = lad
                build_rows.append([name, f"{hf.width}x{hf.height}",
                                   f"pydelatin at the {label('adaptive')} ladder's {len(lad['targets_m'])} targets "
                                   f"({lad['targets_m'][-1]:.3g}-{lad['targets_m'][0]:.3g} m, one mesh each)",
                                   len(lad["targets_m"]), lad["median_s"], samples / lad["median_s"] / 1e6,
                                   lad["median_s"], "", "", ""])  # fmt: skip
            for target in TARGETS_M:
                dl = next(p for p in peers if p["method"] == "pydelatin" and p["target_m"] == target)
                row_ratio = [name, target, dl["triangles"]]
                for method in methods:
                    c = rec["methods"][method]["cut"][str(target)]
                    if c is None:
                        cut_rows.append(
                            [name, target, f"{label(method)} (uniform cut)", "unreachable", "", "", ""]
                        )
                        row_ratio.append("")
                        continue
                    cut_rows.append([name, target, f"{label(method)} (uniform cut)", c["triangles"], c["max_vertical_m"],
                                     c["hausdorff_m"], c["gpu_bytes_per_triangle"]])  # fmt: skip
                    row_ratio.append(c["triangles"] / dl["triangles"])
                for p in peers:
                    if p["target_m"] == target:
                        gpb = (GPU_VERTEX_BYTES * p["vertices"] + GPU_TRIANGLE_BYTES * p["triangles"]) / p[
                            "triangles"
                        ]
                        cut_rows.append([name, target, p["method"], p["triangles"], p["max_vertical_m"],
                                         p["hausdorff_m"], gpb])  # fmt: skip
                ca, cc = (
                    rec["methods"].get("adaptive", {}).get("cut", {}),
                    rec["methods"].get("chunked", {}).get("cut", {}),
                )
                a, ch = ca.get(str(target)), cc.get(str(target))
                row_ratio.append(a["triangles"] / ch["triangles"] if a and ch else "")
                ratio_rows.append(row_ratio)
            for method in methods:
                pth = rec["methods"][method]["path"]
                tri = np.asarray(pth["triangles"], float)
                ref = rec["methods"].get("chunked", {}).get("path")
                vs = tri.mean() / np.mean(ref["triangles"]) if ref else ""
                path_rows.append([name, label(method), int(tri.mean()), int(np.median(tri)), vs,
                                  float(max(pth["max_screen_error_px"])), float(np.mean(pth["gpu_bytes"]) / 2**20)])  # fmt: skip
            results["terrains"][name] = rec
    md = f"## Build throughput (whole pyramid with measured errors, median of {reps}; M: tile size)\n\n"
    md += md_table(["terrain", "size", "method", "tiles", "build s", "M samples/s", "CPU s", "peak RSS MiB",
                    "store MiB", "store bytes / triangle"], build_rows)  # fmt: skip
    md += (
        "\nThe stores build on all cores (CPU s: the build's process CPU time, median); peers mesh one error level"
        " per call on one thread (their median over the targets). The last row of each terrain: pydelatin"
        " meshing the whole terrain at each greedy level's target of the default adaptive store, summed (what"
        " the store's ladder levels reach, one mesh a level, without the store's tiles, shared borders,"
        " measured errors, coding or grid level).\n"
    )
    md += "\n## Triangles at equal true max vertical error (every source sample re-measured)\n\n"
    md += md_table(["terrain", "target m", "method", "triangles", "true max vert. m", "Hausdorff m", "GPU B / triangle"],
                   cut_rows)  # fmt: skip
    md += "\nRatios of triangles (uniform cut / pydelatin at the same target; last column adaptive / chunked):\n\n"
    md += md_table(["terrain", "target m", "pydelatin triangles"] + [f"{label(m)} / pydelatin" for m in methods]
                   + [f"{label('adaptive')} / {label('chunked')}"], ratio_rows)  # fmt: skip
    md += "\n## Camera path at 2 px (circle, 20 degrees down, 1920 x 1080)\n\n"
    md += md_table(["terrain", "method", "mean triangles", "median triangles", "mean / chunked M=65", "worst drawn px",
                    "mean GPU MiB"], path_rows)  # fmt: skip
    write_results(args.name, results, md)


if __name__ == "__main__":
    main()
