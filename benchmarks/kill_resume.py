"""Random SIGKILLs on a region's commands, then ``--resume``: the uninterrupted bytes, finished work kept.

    python benchmarks/kill_resume.py [--tiles 16] [--kills 5] [--seed 7] [--stages export,build]

For each stage, on a mosaic of n SRTM3 tiles (``benchmarks/region.py``'s ``write_mosaic``: the real tile
mirror-tiled into separate 1° GeoTIFFs, EPSG:4326):

1. the command runs uninterrupted once (the reference, its wall time T);
2. the same command, into another output, is killed with SIGKILL ``--kills`` times at seeded random moments
   (once a share of the work drawn uniformly in (0.05, 0.9) is done, polled at random intervals, or at that
   share of T at the latest, so a kill can fall on the start-up, a tile, a commit or the final swap), each
   time started again with ``--resume``; then it runs to the end with ``--resume``;
3. the result is compared with the reference: every file's bytes (export: the output folder; build: every
   tile row of the store, which names its own path and build time in its metadata, so rows only), and
   the finished work counted before each kill is checked to be there after it (export: tiles in the work
   folder whose inode survives into the output; build: tile rows committed).

Writes benchmarks/results/kill_resume.json and kill_resume.md.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import random
import signal
import sqlite3
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from region import write_mosaic  # noqa: E402

from _common import SHARED, md_table, write_results  # noqa: E402


def _cmd(stage: str, dem: Path, out: Path) -> list[str]:
    if stage == "export":
        return [
            sys.executable,
            "-m",
            "terralod",
            "export",
            str(dem),
            "--format",
            "quantized-mesh",
            "-o",
            str(out),
        ]
    return [sys.executable, "-m", "terralod", "build", str(dem), "-o", str(out)]


def _tree(out: Path) -> dict[str, str]:
    return {str(f.relative_to(out)): hashlib.sha256(f.read_bytes()).hexdigest()
            for f in sorted(out.rglob("*")) if f.is_file()}  # fmt: skip


def _rows(store: Path) -> str:
    h = hashlib.sha256()
    with sqlite3.connect(store) as db:
        for row in db.execute("SELECT * FROM tiles ORDER BY 1, 2, 3"):
            h.update(repr(row).encode())
    return h.hexdigest()


def _done(stage: str, out: Path) -> dict[str, int]:
    """What is finished at this moment: export: {tile: inode} in the work folder; build: committed rows."""
    if stage == "export":
        work = out.parent / f".{out.name}.work" / "out"
        return (
            {str(f.relative_to(work)): f.stat().st_ino for f in work.rglob("*.terrain")}
            if work.is_dir()
            else {}
        )
    if not out.exists():
        return {}
    try:
        with sqlite3.connect(f"file:{out}?mode=ro", uri=True) as db:
            return {"rows": int(db.execute("SELECT count(*) FROM tiles").fetchone()[0])}
    except sqlite3.Error:
        return {}


def run_stage(stage: str, dem: Path, d: Path, kills: int, rng: random.Random) -> dict:
    ref = d / f"{stage}-ref" if stage == "export" else d / f"{stage}-ref.terra"
    t0 = time.perf_counter()
    subprocess.run(_cmd(stage, dem, ref), check=True, capture_output=True)
    ref_s = time.perf_counter() - t0
    out = d / f"{stage}-killed" if stage == "export" else d / f"{stage}-killed.terra"
    total = len(_tree(ref)) if stage == "export" else _done(stage, ref).get("rows", 0)
    lost = 0
    moments = []
    for k in range(kills):
        cmd = _cmd(stage, dem, out) + (["--resume"] if k else [])
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        # killed once a drawn share of the work is done (a moment drawn in seconds misses when the load
        # changes between runs), at a drawn instant within the next poll, or at the drawn time at the latest
        share = rng.uniform(0.05, 0.9)
        wait = share * ref_s
        t = time.perf_counter()
        while proc.poll() is None and time.perf_counter() - t < wait:
            got = _done(stage, out)
            n = len(got) if stage == "export" else got.get("rows", 0)
            if n >= share * total:
                break
            time.sleep(rng.uniform(0.05, 0.5))
        if proc.poll() is not None:
            moments.append(f"finished before the kill ({share:.0%})")
            continue
        before = _done(stage, out)
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        after = _done(stage, out)
        if stage == "export":
            lost += sum(1 for rel, ino in before.items() if after.get(rel) != ino)
        else:
            lost += max(0, before.get("rows", 0) - after.get("rows", 0))
        moments.append(f"{wait:.1f} s ({len(before) if stage == 'export' else before.get('rows', 0)} done)")
    kept = _done(stage, out)
    t0 = time.perf_counter()
    subprocess.run(_cmd(stage, dem, out) + ["--resume"], check=True, capture_output=True)
    last_s = time.perf_counter() - t0
    if stage == "export":
        same = _tree(out) == _tree(ref)
        reused = sum(
            1 for rel, ino in kept.items() if (out / rel).exists() and (out / rel).stat().st_ino == ino
        )
        kept_n = len(kept)
    else:
        same = _rows(out) == _rows(ref)
        reused = kept_n = kept.get("rows", 0)
    return {"stage": stage, "reference_s": ref_s, "kills": kills, "kill_moments": moments, "lost_at_kills": lost,
            "done_before_last_run": kept_n, "kept_by_last_run": reused, "last_run_s": last_s, "identical": same}  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tiles", type=int, default=16, help="SRTM3 tiles of the mosaic (a square number)")
    ap.add_argument("--kills", type=int, default=5)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--stages", default="export,build")
    ap.add_argument("--source", default="srtm3_N41E001")
    args = ap.parse_args()
    n = round(args.tiles**0.5)
    rng = random.Random(args.seed)
    stages = args.stages.split(",")
    # rows of earlier runs of other (stage, size) pairs are kept, so one size's run adds its rows
    runs = [
        r for r in _earlier_runs() if (r["stage"], r.get("tiles")) not in {(s, args.tiles) for s in stages}
    ]
    with tempfile.TemporaryDirectory(prefix="terralod-kill-") as tmp:
        d = Path(tmp)
        write_mosaic(SHARED / "dem" / f"{args.source}.tif", n, d / "dem")
        for stage in stages:
            r = run_stage(stage, d / "dem", d, args.kills, rng)
            r.update(tiles=args.tiles, seed=args.seed, load_1min=os.getloadavg()[0],
                     date=time.strftime("%Y-%m-%d %H:%M"))  # fmt: skip
            runs.append(r)
            print(r, flush=True)
    runs.sort(key=lambda r: (r["stage"], r.get("tiles", 0)))
    rows = [[f"{r['stage']} ({r.get('tiles', '?')} SRTM3 tiles)", round(r["reference_s"], 1), r["kills"],
             "; ".join(r["kill_moments"]), r["lost_at_kills"], r["done_before_last_run"], r["kept_by_last_run"],
             round(r["last_run_s"], 1), "yes" if r["identical"] else "**NO**", r.get("date", "")] for r in runs]  # fmt: skip
    table = md_table(["command", "uninterrupted s", "SIGKILLs", "killed at (finished so far)", "finished work lost",
                      "finished before the last run", "kept by it", "last run s", "identical to uninterrupted",
                      "run"], rows)  # fmt: skip
    note = ("\nOne run per row (seed 7 unless the JSON says otherwise), on a shared 2-core machine. Export: "
            "every file of the output compared; build: every tile row. 'Kept by it': finished tiles whose "
            "file (inode) the last run kept, or committed rows it did not build again. A run of some sizes "
            "and stages keeps the rows of the others.\n")  # fmt: skip
    write_results("kill_resume", {"runs": runs}, table + note)


def _earlier_runs() -> list[dict]:
    """The runs of the results file (each with its stage and mosaic size), if any."""
    import json

    p = Path(__file__).resolve().parent / "results" / "kill_resume.json"
    try:
        return list(json.loads(p.read_text())["runs"])
    except (OSError, KeyError, ValueError):
        return []


if __name__ == "__main__":
    main()
