"""``terralod warmup``: compile and cache every numba kernel now (``scripts/install.sh`` runs it), so the
first build, render or demo starts at once."""

from __future__ import annotations

import time

import click

from terralod.cli._console import err_console


@click.command()
def warmup() -> None:
    """Compile and cache every numba kernel ahead of first use (about 3 minutes once, on one core)."""
    from terralod.warmup import COLD_COMPILE_S, kernels_cold, warm_up

    cold = kernels_cold()
    if cold:
        err_console.print(f"compiling kernels once, about {COLD_COMPILE_S} s ...")
    t0 = time.perf_counter()
    warm_up(report=lambda line: err_console.print(line))
    err_console.print(f"kernels compiled and cached in {time.perf_counter() - t0:.1f} s")
