"""Where the test suite's CPU goes: user + system seconds of ``python -m pytest`` (its reaped children
included), by test file and by test, from the per-test account ``tests/conftest.py`` keeps when
``TERRALOD_TEST_CPU`` names a file.

    python benchmarks/suite_cpu.py                       # runs the suite once, writes suite_cpu.{json,md}
    python benchmarks/suite_cpu.py --log cpu.jsonl --total-cpu-s 1219.2   # summarises a run made earlier
    python benchmarks/suite_cpu.py --reference "66b69d2, 535 tests=1035.7" --reference "111de1e=1219.2"

Processes that outlive the test that started them (a shared browser, Dask workers reaped later) are counted
in the test that reaps them or not at all (Chromium's processes are not children pytest waits for); the
whole run's user + system from the OS is recorded beside the sum of the tests'.
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import ROOT, md_table, write_results  # noqa: E402


def run_suite(log: Path) -> tuple[float, float, int]:
    """(user + system s of the run and its children, wall s, exit code) of ``python -m pytest``."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    rc = subprocess.call([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider"], cwd=ROOT,
                         env={**os.environ, "TERRALOD_TEST_CPU": str(log)})  # fmt: skip
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return cpu, time.perf_counter() - t0, rc


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--log", type=Path, help="a per-test account written earlier (TERRALOD_TEST_CPU)")
    ap.add_argument("--total-cpu-s", type=float, help="that run's user + system seconds (GNU time)")
    ap.add_argument("--reference", action="append", default=[], metavar="LABEL=SECONDS",
                    help="another run's whole-suite user + system seconds (e.g. an earlier commit's), for the ratio")  # fmt: skip
    ap.add_argument("--top", type=int, default=25)
    a = ap.parse_args(argv)
    refs = [(lab, float(sec)) for lab, _, sec in (r.rpartition("=") for r in a.reference)]
    if a.log is None:
        log = Path(tempfile.mkdtemp(prefix="terralod-suite-cpu-")) / "cpu.jsonl"
        total, wall, rc = run_suite(log)
    else:
        log, total, wall, rc = a.log, a.total_cpu_s, None, None
    rows = [json.loads(ln) for ln in log.read_text().splitlines() if ln.strip()]
    by_file: dict[str, list[float]] = collections.defaultdict(lambda: [0.0, 0.0, 0])
    for r in rows:
        f = by_file[r["id"].split("::")[0]]
        f[0] += r["cpu_s"]
        f[1] += r["wall_s"]
        f[2] += 1
    tests_cpu = sum(r["cpu_s"] for r in rows)
    files = sorted(by_file.items(), key=lambda kv: -kv[1][0])
    top = sorted(rows, key=lambda r: -r["cpu_s"])[: a.top]
    payload = {
        "tests": len(rows), "tests_cpu_s": round(tests_cpu, 1), "run_cpu_s": total and round(total, 1),
        "run_wall_s": wall and round(wall, 1), "exit_code": rc,
        "references": [{"label": lab, "cpu_s": sec} for lab, sec in refs],
        "files": {k: {"cpu_s": round(v[0], 2), "wall_s": round(v[1], 2), "tests": v[2]} for k, v in files},
        "top_tests": [{"id": r["id"], "cpu_s": round(r["cpu_s"], 2), "wall_s": round(r["wall_s"], 2)} for r in top],
    }  # fmt: skip
    head = [["tests", f"{len(rows)}"], ["sum of the tests' CPU s", f"{tests_cpu:,.1f}"]]
    if total:
        head.append(["the run's user + system s", f"{total:,.1f}"])
    for lab, sec in refs:
        head.append([f"{lab}: user + system s", f"{sec:,.1f}"])
        if total:
            head.append([f"this run / {lab}", f"{total / sec:.2f}"])
    md = "# The test suite's CPU, by file and by test\n\n" + md_table(["", "value"], head) + "\n\n"
    md += f"## The {min(a.top, len(files))} costliest files\n\n" + md_table(
        ["file", "tests", "CPU s", "wall s"],
        [[k, v[2], f"{v[0]:.1f}", f"{v[1]:.1f}"] for k, v in files[: a.top]],
    )
    md += f"\n\n## The {len(top)} costliest tests\n\n" + md_table(
        ["test", "CPU s", "wall s"], [[r["id"], f"{r['cpu_s']:.1f}", f"{r['wall_s']:.1f}"] for r in top]
    )
    write_results("suite_cpu", payload, md + "\n")
    return 0 if rc in (0, None) else int(rc)


if __name__ == "__main__":
    raise SystemExit(main())
