"""A command's memory budget: ``--memory SIZE``, the peak resident set its whole process tree plans for.

Out-of-core work holds the work in flight, never the input: what a command needs is a fixed part per
process (the interpreter, numba's kernels, GDAL, the region readers' caches of a fixed size) plus one part
per work unit it runs at once. The budget decides how many units run at once (threads, Dask worker
processes) and is refused in one line when it cannot hold one; it never changes a tile (tiles are pure
functions of their code, so the same store and the same files come out whatever the budget).

The two parts are measured, not guessed (``benchmarks/region.py``, ``benchmarks/results/region*.md``):
``terralod export`` of a region of 16 and 256 SRTM3 tiles peaked at 360 and 425 MiB (one process, no unit
beyond the tile being encoded), and the out-of-core ``terralod build`` of 16 SRTM3 tiles at 870 MiB with
two threads (the process plus two units; a coarse tile's window is at most 4097² samples, and its
measurement goes in strips of 2^20 samples). The per-unit figure below is kept from before the strips
were made smaller (1,211 MiB then): a budget it admits holds.
"""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass

__all__ = [
    "BUILD_UNIT_BYTES",
    "DEFAULT_MEMORY_BYTES",
    "EXPORT_UNIT_BYTES",
    "IN_MEMORY_BYTES_PER_SAMPLE",
    "PROCESS_BYTES",
    "WORKER_PROCESS_BYTES",
    "MemoryPlan",
    "format_size",
    "in_memory_samples",
    "parse_size",
    "plan_memory",
]

#: The budget a command plans for unless told (``--memory``).
DEFAULT_MEMORY_BYTES = 2 << 30
#: One terralod process at work with its libraries and the region readers' fixed caches.
PROCESS_BYTES = 448 << 20
#: Bytes a sample costs an in-memory build (a 4097² build in one process peaked at 701 MiB:
#: ``benchmarks/results/scale_pinned.md``); a raster that needs more than a budget builds out of core.
IN_MEMORY_BYTES_PER_SAMPLE = 27
#: One export batch in flight (a few dozen tiles' windows and meshes; the export of 64 SRTM3 tiles in one
#: process peaked at 444 MiB, PROCESS_BYTES holding it).
EXPORT_UNIT_BYTES = 128 << 20
#: One Dask worker process's libraries, without a unit (the tree of client, scheduler and two workers of a
#: 4097² out-of-core build peaked at 1,149 MiB: ``benchmarks/results/scale_pinned.md``).
WORKER_PROCESS_BYTES = 256 << 20
#: One out-of-core build unit in flight (a coarse tile's window and its mesher's arrays).
BUILD_UNIT_BYTES = 384 << 20

_UNITS = {"": 1, "b": 1, "k": 1 << 10, "m": 1 << 20, "g": 1 << 30, "t": 1 << 40}
_SIZE = re.compile(r"^\s*(\d+(?:\.\d+)?)\s*([kmgt]?)(?:i?b)?\s*$", re.IGNORECASE)


def parse_size(text: str) -> int:
    """Bytes of a size as people write it: ``2GiB``, ``2G``, ``1.5 GB``, ``512MiB``, ``800m``, ``1073741824``
    (K, M, G, T are powers of 1024: what ``free`` and ``top`` show). ValueError for anything else."""
    m = _SIZE.match(str(text))
    if m is None:
        raise ValueError(f"expected a size such as 2GiB, 1500MiB or 800M, got {text!r}")
    value = float(m.group(1)) * _UNITS[m.group(2).lower()]
    if not math.isfinite(value) or value < 1:
        raise ValueError(f"expected a size of at least one byte, got {text!r}")
    return int(value)


def format_size(n: float) -> str:
    """``n`` bytes as MiB or GiB (one decimal)."""
    return f"{n / (1 << 30):.1f} GiB" if n >= 1 << 30 else f"{n / (1 << 20):.0f} MiB"


@dataclass(frozen=True)
class MemoryPlan:
    """How a budget is spent: ``threads`` units at once in this process, or ``dask_workers`` local worker
    processes of ``threads`` units each, each process allowed ``worker_bytes`` (Dask's memory limit)."""

    budget_bytes: int
    threads: int
    dask_workers: int | None
    worker_bytes: int | None

    def describe(self) -> str:
        if self.dask_workers is None:
            return f"{format_size(self.budget_bytes)}: {self.threads} unit(s) at once"
        return (f"{format_size(self.budget_bytes)}: {self.dask_workers} Dask worker(s) of {self.threads} "
                f"thread(s), {format_size(self.worker_bytes or 0)} each")  # fmt: skip


def in_memory_samples(budget_bytes: int | None = None) -> int:
    """The most samples an in-memory build of one raster holds within the budget."""
    budget = DEFAULT_MEMORY_BYTES if budget_bytes is None else int(budget_bytes)
    return max(0, budget - PROCESS_BYTES) // IN_MEMORY_BYTES_PER_SAMPLE


def plan_memory(
    budget_bytes: int | None = None, *, threads: int | None = None, dask_workers: int | None = None,
    dask_local: bool = False, unit_bytes: int = BUILD_UNIT_BYTES, what: str = "--memory",
) -> MemoryPlan:  # fmt: skip
    """The units a budget holds at once. ``threads`` / ``dask_workers`` asked for are upper bounds (default:
    the cores, 2 local workers); fewer run when the budget holds fewer. ValueError (one line, naming the
    least that works) when it cannot hold one process with one unit."""
    budget = DEFAULT_MEMORY_BYTES if budget_bytes is None else int(budget_bytes)
    least = PROCESS_BYTES + unit_bytes
    if budget < least:
        raise ValueError(
            f"{format_size(budget)} cannot hold one process with one work unit: give at least {format_size(least)}"
        )
    want_threads = max(1, threads or os.cpu_count() or 1)
    if not dask_local:
        fit = (budget - PROCESS_BYTES) // unit_bytes
        return MemoryPlan(budget, int(max(1, min(want_threads, fit))), None, None)
    # the client's process (the writer) keeps PROCESS_BYTES; the local workers share the rest
    want_threads = max(1, threads or 1)
    workers = max(1, dask_workers or 2)
    rest = budget - PROCESS_BYTES
    if rest < WORKER_PROCESS_BYTES + unit_bytes:
        least = PROCESS_BYTES + WORKER_PROCESS_BYTES + unit_bytes
        raise ValueError(f"{format_size(budget)} cannot hold the client and one Dask worker with one work unit: "
                         f"give at least {format_size(least)}")  # fmt: skip
    while workers > 1 and rest // workers < WORKER_PROCESS_BYTES + unit_bytes:
        workers -= 1
    per_worker = max(rest // workers, WORKER_PROCESS_BYTES + unit_bytes)
    fit = (per_worker - WORKER_PROCESS_BYTES) // unit_bytes
    return MemoryPlan(budget, int(max(1, min(want_threads, fit))), workers, int(per_worker))
