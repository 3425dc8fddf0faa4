"""The long fuzzing campaign of every reader: ``python benchmarks/fuzz.py --minutes N``.

Hypothesis mutations (``benchmarks/fuzzing.py``: bit flips, truncation, splices, absurd header integers) of a
valid seed of each reader, rounds of random cases per target in memory-limited child processes until the
time is up; then, when atheris installs (``pip install atheris``), libFuzzer-driven mutation of the same
seeds with the terralod readers instrumented for coverage, one child per target. The contract: a result or
a one-line ``TerralodError`` naming the file, never another exception, hang or crash.

Writes ``benchmarks/results/fuzz.json`` and ``fuzz.md`` (cases and failures per reader and engine).
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

import fuzzing  # noqa: E402

from _common import write_results  # noqa: E402


def hypothesis_rounds(seeds: dict[str, Path], folder: Path, seconds: float, per_round: int) -> dict[str, Any]:
    """Rounds of ``per_round`` random cases per target until ``seconds`` are spent; one child process per
    target and round (a crash by signal loses only that target's round, and is counted)."""
    total: dict[str, Any] = {t: {"cases": 0, "failures": []} for t in seeds}
    crashes: list[str] = []
    t_end = time.monotonic() + seconds
    rounds = 0
    while time.monotonic() < t_end:
        order = list(seeds)[rounds % len(seeds) :] + list(seeds)[: rounds % len(seeds)]  # rotate the start
        rounds += 1
        for k, t in enumerate(order):
            share = max(1.0, (t_end - time.monotonic()) / (len(order) - k))
            res = fuzzing.run_campaign({t: seeds[t]}, folder, per_round, derandomize=False, seconds=share,
                                       timeout_s=share + 300)  # fmt: skip
            if "_crash" in res:
                crashes.append(f"{t}: {res.pop('_crash')[-400:]}")
            for name, r in res.items():
                total[name]["cases"] += r["cases"]
                total[name]["failures"] += r["failures"][: max(0, 5 - len(total[name]["failures"]))]
            if time.monotonic() >= t_end:
                break
    return {"targets": total, "rounds": rounds, "crashes": crashes}


ATHERIS_CHILD = r"""
import sys, atheris
sys.path.insert(0, {benchmarks!r})
target, seed_dir, work, seconds = sys.argv[1], sys.argv[2], sys.argv[3], int(sys.argv[4])
import resource, logging, warnings
resource.setrlimit(resource.RLIMIT_AS, (3 << 30, 3 << 30))
warnings.simplefilter("ignore"); logging.disable(logging.CRITICAL)
# numba-compiled code cannot be instrumented: every module that uses numba is left out (by full name)
import pathlib
src = pathlib.Path({src!r})
skip = [".".join(f.relative_to(src.parent).with_suffix("").parts) for f in src.rglob("*.py")
        if "kernels" in f.parts or "numba" in f.read_text() or "@jit" in f.read_text() or "cli" in f.parts]
skip = [m[: -len(".__init__")] if m.endswith(".__init__") else m for m in skip]
with atheris.instrument_imports(include=["terralod"], exclude=skip):
    import terralod.io.reader, terralod.io.raster, terralod.io.heightmap, terralod.store, terralod.integrity
    import terralod.tin.pointcloud, terralod.tin.fileformat, terralod.tin.increments, terralod.tin.terra
import fuzzing
from pathlib import Path
suffix = {suffix!r}
def one(data):
    bad = fuzzing.run_case(target, bytes(data), Path(work), suffix)
    if bad:
        Path(work, "failure.txt").write_text(bad)  # what happened (libFuzzer only says "target exited")
        raise RuntimeError(bad)
atheris.Setup([sys.argv[0], f"-max_total_time={{seconds}}", "-rss_limit_mb=3072", "-timeout=60",
               "-print_final_stats=1", "-artifact_prefix=" + work + "/", seed_dir], one)
atheris.Fuzz()
"""


def atheris_runs(seeds: dict[str, Path], folder: Path, seconds: float) -> dict[str, Any] | None:
    try:
        import atheris  # noqa: F401
    except ImportError:
        return None
    per = max(5, int(seconds / max(1, len(seeds))))
    out: dict[str, Any] = {}
    for target, seed in seeds.items():
        corpus = Path(tempfile.mkdtemp(prefix=f"corpus-{target}-", dir=folder))
        (corpus / f"seed{seed.suffix}").write_bytes(seed.read_bytes())
        work = Path(tempfile.mkdtemp(prefix=f"atheris-{target}-", dir=folder))
        code = ATHERIS_CHILD.format(
            benchmarks=str(ROOT / "benchmarks"), suffix=seed.suffix, src=str(ROOT / "src" / "terralod")
        )
        try:
            p = subprocess.run([sys.executable, "-c", code, target, str(corpus), str(work), str(per)],
                               capture_output=True, text=True, timeout=per * 3 + 120)  # fmt: skip
            log = p.stderr
            rc = p.returncode
        except subprocess.TimeoutExpired as exc:
            log, rc = str(exc.stderr or ""), "timeout"
        m = re.search(r"stat::number_of_executed_units:\s*(\d+)", log) or re.search(r"Done (\d+) runs", log)
        runs = int(m.group(1)) if m else 0
        failure = None
        if (work / "failure.txt").exists():
            failure = (work / "failure.txt").read_text()[:600]
        elif rc not in (0,):
            lines = [ln for ln in log.splitlines() if "RuntimeError" in ln or "Uncaught" in ln]
            lines = lines or [ln for ln in log.splitlines() if "ERROR" in ln or "crash" in ln]
            failure = (lines[-1] if lines else log[-400:])[:600]
        out[target] = {"cases": runs, "failures": [failure] if failure else [], "seconds": per}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=2.0, help="Total time, minutes (split between engines).")
    ap.add_argument("--per-round", type=int, default=100, help="Hypothesis cases per target per round.")
    ap.add_argument("--no-atheris", action="store_true")
    ap.add_argument("--name", default="fuzz", help="Results file stem under benchmarks/results/.")
    args = ap.parse_args()
    seconds = args.minutes * 60.0
    with tempfile.TemporaryDirectory(prefix="terralod-fuzz-") as tmp:
        folder = Path(tmp)
        seeds = fuzzing.make_seeds(folder / "seeds")
        try:
            import atheris  # noqa: F401

            has_atheris = not args.no_atheris
        except ImportError:
            has_atheris = False
        t0 = time.monotonic()
        hyp = hypothesis_rounds(seeds, folder, seconds / 2 if has_atheris else seconds, args.per_round)
        t_hyp = time.monotonic() - t0
        ath = atheris_runs(seeds, folder, seconds / 2) if has_atheris else None
        t_all = time.monotonic() - t0
    rows = []
    for t in seeds:
        h = hyp["targets"][t]
        a = (ath or {}).get(t, {"cases": 0, "failures": []})
        rows.append({"reader": t, "hypothesis_cases": h["cases"], "hypothesis_failures": len(h["failures"]),
                     "atheris_cases": a["cases"], "atheris_failures": len(a["failures"]),
                     "examples": h["failures"][:2] + a["failures"][:2]})  # fmt: skip
    payload = {"minutes": args.minutes, "seconds_hypothesis": t_hyp, "seconds_total": t_all,
               "rounds": hyp["rounds"], "crashes": hyp["crashes"], "atheris": ath is not None, "readers": rows}  # fmt: skip
    md = [f"# Fuzzed readers ({args.minutes:g} min: hypothesis{' + atheris' if ath is not None else ''})", "",
          "| reader | hypothesis cases | failures | atheris runs | failures |", "|---|---:|---:|---:|---:|"]  # fmt: skip
    for r in rows:
        md.append(f"| {r['reader']} | {r['hypothesis_cases']:,} | {r['hypothesis_failures']} | "
                  f"{r['atheris_cases']:,} | {r['atheris_failures']} |")  # fmt: skip
    tot_h = sum(r["hypothesis_cases"] for r in rows)
    tot_a = sum(r["atheris_cases"] for r in rows)
    fails = sum(r["hypothesis_failures"] + r["atheris_failures"] for r in rows)
    md.append(f"| **all** | **{tot_h:,}** | **{fails}** | **{tot_a:,}** | |")
    md += ["", f"Child crashes or hangs: {len(hyp['crashes'])}. A failure is any exception other than a one-line "
           "TerralodError naming the file."]  # fmt: skip
    for r in rows:
        for e in r["examples"]:
            md.append(f"- {r['reader']}: `{e[:300]}`")
    write_results(args.name, payload, "\n".join(md) + "\n")
    if fails or hyp["crashes"]:
        sys.exit(1)


if __name__ == "__main__":
    os.environ.setdefault("PYTHONHASHSEED", "0")
    main()
