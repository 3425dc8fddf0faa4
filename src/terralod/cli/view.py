"""``terralod view PATH``: the real-time window viewer on any terrain (a DEM is built into a cache first)."""

from __future__ import annotations

import json
import os
from typing import Any

import click

from terralod.cli._errors import require_extra
from terralod.cli._inputs import open_terrain_arg
from terralod.cli._options import read_options, size, view_options, water_option


@click.command()
@click.argument("path")
@click.option("--size", "size_text", default="1280x720", show_default=True, help="Window WIDTHxHEIGHT.")
@click.option("--threshold-px", default=2.0, show_default=True)
@click.option("--frames", type=int, default=None, help="Close after this many frames (scripted runs).")
@click.option("--screenshot", help="PNG written after the last frame (with --frames).")
@click.option("--epoch", default=None, metavar="DATE", help="Epoch to start on (default: the latest).")
@water_option
@view_options
@read_options
def view(
    path, size_text, threshold_px, frames, screenshot, epoch, water_level, fractal_levels, cull, **read: Any
) -> None:
    """Open the real-time viewer on a store (or a DEM, built into a cache store first)."""
    require_extra("view", "window")
    from terralod.render.viewer import run_viewer

    w, h = size(size_text)
    from terralod.cli._epochs import at_epoch

    with open_terrain_arg(path, read, fractal_levels) as whole, at_epoch(whole, epoch) as terrain:
        if not os.environ.get("DISPLAY") and not os.environ.get("WAYLAND_DISPLAY"):
            raise click.UsageError(
                "no display (DISPLAY is unset); use `terralod render` or `terralod flythrough`"
            )
        title = "terralod (TIN)" if terrain.kind == "tin" else "terralod"
        out = run_viewer(terrain, width_px=w, height_px=h, threshold_px=threshold_px, max_frames=frames,
                         screenshot=screenshot, cull=cull, title=title, water_level_m=water_level)  # fmt: skip
    if frames:
        click.echo(
            json.dumps({"frames": out["frames"], "hud": out["hud"], "stats": out["stats"]}, default=str)
        )
