"""Build throughput of the Chunked-LOD tile store, side by side with pydelatin and pymartini.

For each terrain (Puget Sound 1k, real; and a 4097² terrain mirror-tiled from it) this script, in one run
on the same data:

1. builds the whole ``.terra`` pyramid (M = 65, all cores) in a fresh subprocess and records wall time,
   source samples per second (width x height / build seconds, error measurement included), peak RSS
   and store size;
2. for three error targets (TARGETS_M: 5, 20 and 80 m of vertical error), counts the
   triangles the Chunked-LOD store needs to meet the target everywhere (the coarsest tile cut whose
   vertical error is within it), and meshes the same grid with pymartini and pydelatin at the same max
   error, recording their time, triangles and their *measured* max vertical / Hausdorff error
   (terralod.measure_error on their output, not their own estimate).

Writes ``benchmarks/results/build.json`` and ``build.md``. Run: ``python benchmarks/build.py [--quick]``.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from terralod import Heightfield, build_store, measure_error, open_store  # noqa: E402
from terralod.tiles import parent  # noqa: E402

from _common import md_table, puget_sound_1k, puget_sound_4k, write_results  # noqa: E402

#: Max vertical error targets, metres, at which triangle counts are compared.
TARGETS_M = (5.0, 20.0, 80.0)


def _terrain(name: str) -> Heightfield | None:
    if name == "puget_sound_1k":
        return puget_sound_1k()
    if name == "puget_sound_4k_mirror":
        return puget_sound_4k()
    raise ValueError(name)


def child_build(name: str, out: str, workers: int | None) -> None:
    """Runs in a subprocess: build one store, print JSON with timing and peak memory."""
    hf = _terrain(name)
    assert hf is not None
    # warm the numba caches on a tiny input so compile time is not counted as build time
    build_store(Heightfield.from_array(np.zeros((70, 70), np.float32), 1.0), out + ".warm", tile_size=65)
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t = time.perf_counter()
    rep = build_store(hf, out, tile_size=65, workers=workers, overwrite=True)
    secs = time.perf_counter() - t
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    print(
        json.dumps(
            {
                "seconds": secs,
                "tiles": rep.tiles_built,
                "peak_rss_mib": rss / 1024,
                "rss_before_mib": rss0 / 1024,
            }
        )
    )


def chunked_triangles_at(store, target_m: float) -> tuple[int, float]:
    """Triangles of the coarsest tile cut whose every tile has vertical error <= target, and that cut's max error."""
    errs = store.tile_errors()
    summ = {(r["level"], r["x"], r["y"]): r for r in store.tile_summaries()}
    cut = [
        c
        for c, (e, v) in errs.items()
        if v <= target_m and (parent(c) is None or errs[parent(c)][1] > target_m)
    ]
    return sum(summ[c]["n_triangles"] for c in cut), max(errs[c][1] for c in cut)


def run_peers(hf: Heightfield, targets: list[float]) -> list[dict]:
    from pydelatin import Delatin
    from pymartini import Martini

    z = hf.elevation_m
    n = z.shape[0]
    rows_out = []
    x0, y0 = hf.origin_m
    dx, dy = hf.spacing_m
    martini_ok = z.shape[0] == z.shape[1] and ((n - 1) & (n - 2)) == 0
    for target in targets:
        if martini_ok:
            t = time.perf_counter()
            m = Martini(n)
            tile = m.create_tile(z)
            v, tri = tile.get_mesh(target)
            tri = tri.reshape(-1, 3)
            secs = time.perf_counter() - t
            cols, rows = v.reshape(-1, 2)[:, 0].astype(np.float64), v.reshape(-1, 2)[:, 1].astype(np.float64)
            verts = np.c_[x0 + cols * dx, y0 - rows * dy, z[rows.astype(int), cols.astype(int)]]
            rep = measure_error(verts, tri.astype(np.int64), hf)
            rows_out.append({"method": "pymartini", "target_m": target, "seconds": secs, "triangles": len(tri),
                             "max_vertical_m": rep.max_vertical_m, "hausdorff_m": rep.hausdorff_m})  # fmt: skip
        t = time.perf_counter()
        d = Delatin(z.astype(np.float64), max_error=target)
        secs = time.perf_counter() - t
        # pydelatin's y axis points north: row = (H - 1) - y
        cols, rows = (
            d.vertices[:, 0].astype(np.float64),
            (z.shape[0] - 1) - d.vertices[:, 1].astype(np.float64),
        )
        verts = np.c_[x0 + cols * dx, y0 - rows * dy, z[rows.astype(int), cols.astype(int)]]
        rep = measure_error(verts, d.triangles.astype(np.int64), hf)
        rows_out.append({"method": "pydelatin", "target_m": target, "seconds": secs, "triangles": len(d.triangles),
                         "max_vertical_m": rep.max_vertical_m, "hausdorff_m": rep.hausdorff_m})  # fmt: skip
    return rows_out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--child", nargs=2, metavar=("TERRAIN", "OUT"), help=argparse.SUPPRESS)
    ap.add_argument("--workers", type=int, default=None)
    ap.add_argument("--quick", action="store_true", help="Puget Sound 1k only")
    args = ap.parse_args()
    if args.child:
        child_build(args.child[0], args.child[1], args.workers)
        return
    names = ["puget_sound_1k"] + ([] if args.quick else ["puget_sound_4k_mirror"])
    results = {"terrains": {}}
    build_rows, peer_rows = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for name in names:
            hf = _terrain(name)
            if hf is None:
                print(f"skip {name}: ../shared/data not present")
                continue
            out = str(Path(tmp) / f"{name}.terra")
            cmd = [sys.executable, __file__, "--child", name, out] + (
                ["--workers", str(args.workers)] if args.workers else []
            )
            res = json.loads(
                subprocess.run(cmd, check=True, capture_output=True, text=True)
                .stdout.strip()
                .splitlines()[-1]
            )
            samples = hf.width * hf.height
            with open_store(out) as s:
                size = s.size_bytes()
                per_level = {}
                errs = s.tile_errors()
                for (k, _, _), (_e, v) in errs.items():
                    per_level[k] = max(per_level.get(k, 0.0), v)
                targets = list(TARGETS_M)
                cut = {t: chunked_triangles_at(s, t) for t in targets}
            build = {
                "samples": samples, "seconds": res["seconds"], "samples_per_s": samples / res["seconds"],
                "tiles": res["tiles"], "peak_rss_mib": res["peak_rss_mib"], "store_mib": size / 2**20,
            }  # fmt: skip
            build_rows.append([name, f"{hf.width}x{hf.height}", res["tiles"], res["seconds"],
                               samples / res["seconds"] / 1e6, res["peak_rss_mib"], size / 2**20])  # fmt: skip
            t = time.perf_counter()
            peers = run_peers(hf, targets)
            for target in targets:
                tri, err = cut[target]
                peer_rows.append([name, target, "terralod chunked (tile cut)", tri, err, "", ""])
                for p in peers:
                    if p["target_m"] == target:
                        peer_rows.append([name, target, p["method"], p["triangles"], p["max_vertical_m"],
                                          p["hausdorff_m"], p["seconds"]])  # fmt: skip
            results["terrains"][name] = {"build": build, "level_max_vertical_m": per_level,
                                         "chunked_cut": {str(k): v for k, v in cut.items()},
                                         "peers": peers, "peer_seconds": time.perf_counter() - t}  # fmt: skip
    md = "## Build throughput (Chunked LOD, M = 65, error measurement included)\n\n"
    md += md_table(
        ["terrain", "size", "tiles", "build s", "M samples/s", "peak RSS MiB", "store MiB"], build_rows
    )
    md += "\n## Triangles at the same max vertical error (peers' error measured by terralod)\n\n"
    md += md_table(["terrain", "target m", "method", "triangles", "measured max vert. m", "Hausdorff m", "seconds"],
                   peer_rows)  # fmt: skip
    md += "\nThe Chunked-LOD build produces every level of the pyramid; pymartini/pydelatin mesh one error level.\n"
    write_results("build", results, md)


if __name__ == "__main__":
    main()
