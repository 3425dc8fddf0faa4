"""``terralod render PATH -o frame.png``: one frame of any terrain (grid store, TIN store, or a DEM built
into a cache store first), headless on EGL."""

from __future__ import annotations

from typing import Any

import click

from terralod.cli._console import console, frame_table
from terralod.cli._epochs import at_epoch, caption, epoch_options, overlay_for
from terralod.cli._inputs import open_terrain_arg
from terralod.cli._options import (
    aim_options,
    aimed_pose,
    check_output,
    read_options,
    render_settings,
    size,
    triple,
    view_options,
)

#: Image files ``render -o`` writes (Pillow picks the format by suffix).
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".webp", ".tif", ".tiff", ".bmp")


def describe_frame(output: str, stats: dict[str, Any]) -> None:
    """The frame table, plus what a terrain's engine reports beyond the shared keys."""
    frame_table(stats, output)
    if "records_applied" in stats:
        console.print(
            f"{output}: {int(stats['triangles']):,} triangles, {int(stats['tiles'])} sub-blocks at their SVO "
            f"scales ({int(stats['records_applied']):,} ΔT records applied)"
        )


@click.command()
@click.argument("path")
@click.option("-o", "--output", required=True, help="PNG to write.")
@click.option("--eye", help="Eye X,Y,Z in world metres (default: an overview).")
@click.option("--target", help="Target X,Y,Z in world metres.")
@click.option("--size", "size_text", default="1920x1080", show_default=True, help="WIDTHxHEIGHT pixels.")
@click.option("--threshold-px", default=2.0, show_default=True, help="Screen-space error threshold, pixels.")
@click.option("--background", help="Sky colour R,G,B (0..1 or 0..255).")
@click.option(
    "--mode", type=click.Choice(["elevation", "lod", "error"]), default="elevation", show_default=True
)
@click.option("--wireframe", is_flag=True)
@click.option("--overwrite", is_flag=True, help="Replace an existing image.")
@epoch_options
@aim_options
@view_options
@read_options
def render(
    path, output, eye, target, size_text, threshold_px, background, mode, wireframe, overwrite, look_at,
    from_text, water_level, fractal_levels, cull, epoch, overlay, from_epoch, lod_m, **read: Any,
) -> None:  # fmt: skip
    """Render one frame of a store (or a DEM, built first) to a PNG, headless (EGL)."""
    from terralod.render.offscreen import CameraPose, FrameRenderer, overview_pose, save_png, terrain_colours

    check_output(output, [path], overwrite=overwrite, suffixes=IMAGE_SUFFIXES, what="image")
    w, h = size(size_text)
    if eye and not target or target and not eye:
        raise click.BadParameter("give both --eye and --target", param_hint="--eye")
    if eye and (look_at or from_text):
        raise click.BadParameter("give --eye/--target or --look-at/--from, not both", param_hint="--eye")
    with open_terrain_arg(path, read, fractal_levels) as whole, at_epoch(whole, epoch) as terrain:
        pose = aimed_pose(terrain, look_at, from_text) or overview_pose(terrain)
        if eye and target:
            pose = CameraPose(triple(eye, "--eye"), triple(target, "--target"))
        st = terrain_colours(terrain, render_settings(background, mode, wireframe), water_level)
        ov = overlay_for(terrain, overlay, from_epoch, lod_m, st)
        fr = FrameRenderer(terrain, w, h, threshold_px=threshold_px, settings=st, cull=cull)
        try:
            save_png(caption(fr.frame(pose), terrain, ov), output)
        finally:
            fr.close()
    describe_frame(output, fr.last_stats)
