"""Build throughput, side by side with an older terralod and with the peers, interleaved round by round.

Absolute rates on this shared 2-core machine move by 1.3-1.7x between hours; ratios measured in one run,
with every configuration hit by the same busy spells, hold. Each round builds, for each terrain and method,
one store with the current ``src`` and one with ``--baseline-src`` (a ``src`` folder exported from an older
commit, e.g. ``git worktree add /tmp/base <commit>``), each in a fresh subprocess after a warm-up build
there (``build.py --child``, all cores), then times the peers in this process: pydelatin at each target of
``build.TARGETS_M`` (its median over them, as in build.md) and, on Puget Sound, pymartini at its first
parameter per target. Medians over the rounds.

    python benchmarks/build_ab.py --baseline-src /tmp/base/src [--baseline-label 50cfeb4] [--rounds 5]
        [--methods adaptive,cohesion,chunked] [--terrains a,b]

Writes ``benchmarks/results/build_ab.{json,md}``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from build import TARGETS_M, _terrain  # noqa: E402

from _common import md_table, write_results  # noqa: E402

BUILD = str(Path(__file__).resolve().parent / "build.py")
SRC = str(Path(__file__).resolve().parents[1] / "src")


def child_seconds(src: str, name: str, method: str, out: str) -> float:
    """One timed build of ``name`` with ``method`` by the terralod in ``src`` (fresh process, warmed up)."""
    env = dict(os.environ, PYTHONPATH=src)
    cmd = [sys.executable, BUILD, "--child", name, method, out, "1"]
    res = subprocess.run(cmd, check=True, capture_output=True, text=True, env=env)
    return float(json.loads(res.stdout.strip().splitlines()[-1])["seconds"][0])


def peer_seconds(z: np.ndarray) -> dict[str, float]:
    """pydelatin's median over the targets (and pymartini's, on a 2^k + 1 square), seconds."""
    from pydelatin import Delatin
    from pymartini import Martini

    out = {}
    secs = []
    for target in TARGETS_M:
        t = time.perf_counter()
        Delatin(z.astype(np.float64), max_error=target)
        secs.append(time.perf_counter() - t)
    out["pydelatin"] = statistics.median(secs)
    n = z.shape[0]
    if z.shape[0] == z.shape[1] and ((n - 1) & (n - 2)) == 0:
        secs = []
        for target in TARGETS_M:
            t = time.perf_counter()
            Martini(n).create_tile(z).get_mesh(target)
            secs.append(time.perf_counter() - t)
        out["pymartini"] = statistics.median(secs)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--baseline-src", required=True, help="src folder of the older terralod")
    ap.add_argument("--baseline-label", default="before")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--methods", default="adaptive,cohesion,chunked")
    ap.add_argument("--terrains", default="pyrenees_srtm3_N42E001,puget_sound_1k")
    args = ap.parse_args()
    methods = args.methods.split(",")
    configs = [(args.baseline_label, str(Path(args.baseline_src).resolve())), ("now", SRC)]
    terrains = {}
    for name in args.terrains.split(","):
        hf = _terrain(name)
        if hf is None:
            print(f"skip {name}: ../shared/data not present", flush=True)
            continue
        terrains[name] = hf
    times: dict = {n: {m: {c: [] for c, _ in configs} for m in methods} for n in terrains}
    peers: dict = {n: {} for n in terrains}
    with tempfile.TemporaryDirectory() as tmp:
        k = 0
        for r in range(args.rounds):
            for name, hf in terrains.items():
                for method in methods:
                    for label, src in configs if r % 2 == 0 else configs[::-1]:
                        k += 1  # a fresh path a build (the child's warm-up store is not overwritten)
                        s = child_seconds(src, name, method, str(Path(tmp) / f"{k}.terra"))
                        times[name][method][label].append(s)
                for p, s in peer_seconds(hf.elevation_m).items():
                    peers[name].setdefault(p, []).append(s)
            print(f"round {r + 1}/{args.rounds} done", flush=True)
    rows = []
    payload: dict = {"rounds": args.rounds, "baseline": args.baseline_label, "terrains": {}}
    for name, hf in terrains.items():
        samples = hf.width * hf.height
        dl = statistics.median(peers[name]["pydelatin"])
        payload["terrains"][name] = {"samples": samples, "times_s": times[name], "peers_s": peers[name]}
        for method in methods:
            med = {label: statistics.median(times[name][method][label]) for label, _ in configs}
            for label, _ in configs:
                rows.append([name, method, label, med[label], samples / med[label] / 1e6,
                             dl / med[label], med[args.baseline_label] / med[label]])  # fmt: skip
        for p, secs in peers[name].items():
            m = statistics.median(secs)
            rows.append([name, f"{p} (one mesh, median over 5-80 m)", "", m, samples / m / 1e6, dl / m, ""])
    md = (
        "# Build throughput, now against an older terralod and the peers, interleaved\n\n"
        f"Medians of {args.rounds} rounds; each round builds every store once with each terralod (fresh "
        "process, warmed up, all cores) and times the peers (one thread), so a busy spell of this shared "
        "machine hits every row. 'x pydelatin' is the store's whole pyramid against pydelatin's one mesh "
        "(time ratio, same run); 'x before' the speed-up over the baseline.\n\n"
    )
    md += md_table(
        ["terrain", "method", "terralod", "build s", "M samples/s", "x pydelatin", "x before"], rows
    )
    write_results("build_ab", payload, md)


if __name__ == "__main__":
    main()
