"""``terralod bench ...``: the reproducible experiments of ``benchmarks/`` (results in benchmarks/results/)."""

from __future__ import annotations

import runpy
from pathlib import Path

import click


@click.group()
def bench() -> None:
    """Reproducible experiments of benchmarks/ (results in benchmarks/results/)."""


@bench.command("cohesion")
@click.option("--quick", is_flag=True, help="Puget Sound and the bundled sample only.")
@click.option("--frames", default=48, show_default=True, help="Frames of the camera path.")
def bench_cohesion(quick: bool, frames: int) -> None:
    """Vertex cohesion map vs Chunked LOD (benchmarks/cohesion_vs_chunked.py)."""
    script = Path(__file__).resolve().parents[3] / "benchmarks" / "cohesion_vs_chunked.py"
    if not script.exists():
        raise click.ClickException(f"{script}: benchmark script not found (run from a source checkout)")
    runpy.run_path(str(script), run_name="terralod_bench")["main"](
        ["--frames", str(frames)] + (["--quick"] if quick else [])
    )
