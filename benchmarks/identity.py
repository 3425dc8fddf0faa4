"""Same behaviour before and after a refactor: every tile, triangle count, error and frame compared.

Builds the same stores with two source trees of terralod (``--baseline`` and ``--candidate``, each a
``src`` folder; e.g. a ``git worktree`` of the commit before the change) in fresh processes, one after the
other, and compares byte for byte: every tile row (quantised vertices, triangles, the stored and measured
errors, counts), the per-level table of ``terralod info``, the detail-increment TIN payload, and a rendered
frame (EGL, llvmpipe: bit-identical run to run). Build times of the two trees are interleaved, medians of
``--repeats`` runs, and reported as ratios (this machine is shared; absolute times are noise).

    git worktree add /tmp/base <commit-before>
    python benchmarks/identity.py --baseline /tmp/base/src --candidate src

Writes ``benchmarks/results/identity.json`` and ``identity.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
DATA = HERE.parent.parent / "shared" / "data"

#: Work run in a fresh interpreter with one tree on sys.path; only API present before and after.
_WORKER = r"""
import hashlib, json, sys, time
from pathlib import Path
import numpy as np
case, out = json.loads(sys.argv[1]), Path(sys.argv[2])
import terralod
from terralod.io.reader import read_heightfield, sample_heightfield
res = {"case": case["name"], "terralod": terralod.__file__}
if case["kind"] == "tin":
    from terralod.tin import DetailIncrementModel
    t0 = time.perf_counter()
    if case["input"].endswith((".las", ".laz")):
        m = DetailIncrementModel.from_las(case["input"], sub_blocks=case["sub_blocks"])
    else:
        m = DetailIncrementModel.from_heightfield(sample_heightfield(), sub_blocks=case["sub_blocks"])
    res["seconds"] = time.perf_counter() - t0
    m.save(out / "m.tdim")
    res["payload_sha256"] = hashlib.sha256((out / "m.tdim").read_bytes()).hexdigest()
    res["errors"] = [m.error_m(b).tolist() for b in range(m.n_blocks)]
    v, t = m.mesh_at(0)
    res["base_triangles"] = int(t.shape[0])
else:
    hf = sample_heightfield() if case["input"] == "sample" else read_heightfield(
        case["input"], spacing_m=case.get("spacing"), vertical_scale=case.get("vscale"))
    t0 = time.perf_counter()
    terralod.build_store(hf, out / "s.terra", tile_size=case["tile_size"], method=case["method"], workers=1)
    res["seconds"] = time.perf_counter() - t0
    with terralod.open_store(out / "s.terra") as s:
        rows = s._conn.execute(
            "SELECT level, x, y, error_m, vertical_error_m, measured_error_m, measured_vertical_error_m, "
            "rms_error_m, n_samples, z_min_m, z_max_m, n_vertices, n_triangles, z0_index, vertices, triangles "
            "FROM tiles ORDER BY level, y, x").fetchall()
        res["tiles"] = len(rows)
        res["tile_sha256"] = {f"{r[0]}/{r[1]}/{r[2]}": hashlib.sha256(repr(r[3:14]).encode() + r[14] + r[15]).hexdigest()
                              for r in rows}
        lv = {}
        for r in rows:
            d = lv.setdefault(str(r[0]), {"tiles": 0, "triangles": 0, "max_error_m": 0.0, "max_vertical_error_m": 0.0})
            d["tiles"] += 1; d["triangles"] += r[12]
            d["max_error_m"] = max(d["max_error_m"], r[3]); d["max_vertical_error_m"] = max(d["max_vertical_error_m"], r[4])
        res["levels"] = lv
        if case.get("frame"):
            from terralod.render.offscreen import FrameRenderer, overview_pose
            fr = FrameRenderer(s, 320, 180, threshold_px=2.0)
            img = fr.frame(overview_pose(s))
            res["frame_sha256"] = hashlib.sha256(np.ascontiguousarray(img).tobytes()).hexdigest()
            res["frame_triangles"] = int(fr.last_stats["triangles"])
            fr.close()
print(json.dumps(res))
"""


def cases() -> list[dict]:
    out = [
        {"name": "sample chunked 33", "kind": "grid", "input": "sample", "method": "chunked", "tile_size": 33,
         "frame": True},
        {"name": "sample cohesion 33", "kind": "grid", "input": "sample", "method": "cohesion", "tile_size": 33,
         "frame": True},
        {"name": "sample cohesion 65", "kind": "grid", "input": "sample", "method": "cohesion", "tile_size": 65},
        {"name": "sample TIN 16 blocks", "kind": "tin", "input": "sample", "sub_blocks": 16},
    ]  # fmt: skip
    if DATA.exists():
        alpine = str(DATA / "dem" / "srtm1_crop256_alpine.tif")
        puget = str(DATA / "dem" / "puget_sound_1k_u16.png")
        out += [
            {"name": "Rainier 256 chunked", "kind": "grid", "input": alpine, "method": "chunked", "tile_size": 65},
            {"name": "Rainier 256 cohesion", "kind": "grid", "input": alpine, "method": "cohesion", "tile_size": 65},
            {"name": "Puget 1k chunked", "kind": "grid", "input": puget, "method": "chunked", "tile_size": 65,
             "spacing": [160.0, 160.0], "vscale": 0.1},
            {"name": "Puget 1k cohesion", "kind": "grid", "input": puget, "method": "cohesion", "tile_size": 65,
             "spacing": [160.0, 160.0], "vscale": 0.1},
            {"name": "Autzen TIN 4 blocks", "kind": "tin", "input": str(DATA / "lidar" / "autzen_trim.laz"),
             "sub_blocks": 4},
        ]  # fmt: skip
    return out


def run_case(src: str, case: dict) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        env = dict(os.environ, PYTHONPATH=str(Path(src).resolve()))
        p = subprocess.run([sys.executable, "-c", _WORKER, json.dumps(case), tmp], capture_output=True, text=True,
                           env=env, cwd=tmp)  # fmt: skip
        if p.returncode != 0:
            raise RuntimeError(f"{case['name']} with {src}: {p.stderr[-2000:]}")
        return json.loads(p.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--baseline", required=True, help="src folder of the tree before the change")
    ap.add_argument("--candidate", default=str(HERE.parent / "src"), help="src folder after (default: this)")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args(argv)
    rows = []
    for case in cases():
        base, cand = [], []
        for _ in range(args.repeats):  # interleaved: both trees see the same machine load
            base.append(run_case(args.baseline, case))
            cand.append(run_case(args.candidate, case))
        b, c = base[0], cand[0]
        assert b["terralod"].startswith(str(Path(args.baseline).resolve())), b["terralod"]
        keys = [k for k in b if k not in ("seconds", "terralod", "case")]
        same = {k: b[k] == c.get(k) for k in keys}
        stable = all(r == {**b, "seconds": r["seconds"]} for r in base)
        ratio = statistics.median(r["seconds"] for r in cand) / statistics.median(r["seconds"] for r in base)
        rows.append({"case": case["name"], "identical": all(same.values()), "compared": same,
                     "deterministic_baseline": stable, "tiles": b.get("tiles"),
                     "triangles": sum(d["triangles"] for d in b.get("levels", {}).values()) or b.get("base_triangles"),
                     "time_ratio_candidate_over_baseline": ratio,
                     "baseline_s_median": statistics.median(r["seconds"] for r in base),
                     "candidate_s_median": statistics.median(r["seconds"] for r in cand)})  # fmt: skip
        print(f"{case['name']}: identical={rows[-1]['identical']} ratio={ratio:.3f}", flush=True)
    res_dir = HERE / "results"
    res_dir.mkdir(exist_ok=True)
    (res_dir / "identity.json").write_text(json.dumps({"baseline": args.baseline, "candidate": args.candidate,
                                                       "repeats": args.repeats, "rows": rows}, indent=2))  # fmt: skip
    lines = ["| case | tiles | triangles | identical (tiles, errors, counts, payload, frame) | time after / before |",
             "|---|---|---|---|---|"]  # fmt: skip
    for r in rows:
        what = ", ".join(k for k, v in r["compared"].items() if v)
        lines.append(f"| {r['case']} | {r['tiles'] or '-'} | {r['triangles']:,} | "
                     f"{'yes' if r['identical'] else 'NO'} ({what}) | {r['time_ratio_candidate_over_baseline']:.2f} |")  # fmt: skip
    (res_dir / "identity.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    if not all(r["identical"] for r in rows):
        sys.exit(1)


if __name__ == "__main__":
    main()
