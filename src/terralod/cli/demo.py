"""``terralod demo``: build the bundled real DEM, then open the viewer (or, with no display, render a
fly-through video and a still) and print the statistics."""

from __future__ import annotations

import os
from pathlib import Path

import click

from terralod.cli._console import console, crs_name, heightfield_info, print_store_summary
from terralod.cli._errors import missing_modules
from terralod.cli._inputs import run_build


@click.command()
@click.option("-o", "--output", default="demo.terra", show_default=True, help="Store to build.")
@click.option("--tile-size", default=33, show_default=True, help="Vertices per tile side.")
@click.option("--frames", default=96, show_default=True, help="Fly-through frames when there is no display.")
@click.option("--no-window", is_flag=True, help="Render demo.mp4 + demo.png even when a display is present.")
def demo(output: str, tile_size: int, frames: int, no_window: bool) -> None:
    """Build the bundled real DEM (matplotlib's Jacksboro fault, Tennessee), then open the viewer, or with
    no display render a fly-through to demo.mp4 plus demo.png and print the statistics."""
    from terralod.cli.flythrough import flythrough_table, render_flythrough
    from terralod.io.reader import sample_heightfield
    from terralod.pyramid.builder import DEFAULT_METHOD, store_summary
    from terralod.store import open_store
    from terralod.terrain import GridTerrain

    hf = sample_heightfield()
    d = heightfield_info(hf)
    console.print(
        f"[bold]{d['source']}[/bold]: {d['size'][0]}x{d['size'][1]} samples at {d['spacing_m'][0]:.1f} m, "
        f"{d['elevation_range_m'][0]:.0f}..{d['elevation_range_m'][1]:.0f} m, CRS {crs_name(d['crs'])}"
    )
    rep = run_build(
        hf, output, tile_size=tile_size, method=DEFAULT_METHOD, workers=None, resume=False, overwrite=True
    )
    console.print(f"built {rep.tiles_built} tiles in {rep.seconds:.2f} s")
    with open_store(output) as s:
        print_store_summary(store_summary(s))
        terrain = GridTerrain(s)
        display = os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")
        if display and not no_window and missing_modules("window"):
            console.print(
                "no window without the window extra (pip install 'terralod[window]'): rendering instead"
            )
        elif display and not no_window:
            from terralod.render.viewer import run_viewer

            run_viewer(terrain)
            return
        stem = Path(output).with_suffix("")
        summary = render_flythrough(
            terrain, f"{stem}.mp4", frames=frames, size=(1024, 576), png=f"{stem}.png"
        )
    flythrough_table(summary)
    console.print(f"wrote {stem}.mp4 and {stem}.png")
