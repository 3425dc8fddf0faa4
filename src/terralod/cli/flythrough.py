"""``terralod flythrough PATH -o video.mp4``: a fly-through video of any terrain, headless."""

from __future__ import annotations

from typing import Any

import click
import numpy as np

from terralod.cli._common import (
    aim_options,
    aimed_pose,
    check_output,
    console,
    open_terrain_arg,
    read_options,
    size,
    view_options,
)

#: Video files ``flythrough -o`` writes (H.264 through ffmpeg).
VIDEO_SUFFIXES = (".mp4", ".mkv", ".mov")


def render_flythrough(terrain, output: str, *, cam_path: str = "auto", frames: int = 120, fps: int = 24,
                      size=(1280, 720), threshold_px: float = 2.0, png: str | None = None,
                      cull: tuple[str, ...] = (), water_level_m: float | None = None, legend: bool = True,
                      end_pose=None) -> dict[str, Any]:  # fmt: skip
    """Render a camera path to MP4; returns the per-frame statistics summarised (medians, worst error).
    The auto path ends on the terrain's relief, or at ``end_pose`` (--look-at / --from) when given."""
    from terralod.render import RenderSettings
    from terralod.render.offscreen import (
        FrameRenderer,
        auto_path,
        load_path,
        save_png,
        terrain_colours,
        write_video,
    )

    poses = auto_path(terrain, frames, end=end_pose) if cam_path == "auto" else load_path(cam_path)
    st = terrain_colours(terrain, RenderSettings(legend=legend), water_level_m)
    fr = FrameRenderer(terrain, size[0], size[1], threshold_px=threshold_px, cull=cull, settings=st)
    per_frame: list[dict[str, Any]] = []

    def gen():
        for i, pose in enumerate(poses):
            img = fr.frame(pose)
            per_frame.append(fr.last_stats)
            if png and i == len(poses) // 2:
                save_png(img, png)
            yield img

    try:
        n = write_video(gen(), output, fps=fps)
    finally:
        fr.close()
    keys = ("tiles", "triangles", "max_screen_error_px", "select_ms", "stitch_ms", "draw_ms")
    return {"output": output, "frames": n, **{k: float(np.median([f.get(k, 0.0) for f in per_frame])) for k in keys},
            "max_screen_error_px_max": float(max(f.get("max_screen_error_px", 0.0) for f in per_frame))}  # fmt: skip


def flythrough_table(summary: dict[str, Any]) -> None:
    from rich.table import Table

    t = Table(title=f"{summary['output']}: {summary['frames']} frames (medians)")
    for col in ("tiles", "triangles", "max screen error px", "select ms", "stitch ms", "draw ms"):
        t.add_column(col, justify="right")
    t.add_row(
        f"{summary['tiles']:.0f}", f"{summary['triangles']:,.0f}", f"{summary['max_screen_error_px']:.2f}",
        f"{summary['select_ms']:.2f}", f"{summary['stitch_ms']:.2f}", f"{summary['draw_ms']:.2f}",
    )  # fmt: skip
    console.print(t)


@click.command()
@click.argument("path")
@click.option("-o", "--output", required=True, help="MP4 to write.")
@click.option(
    "--path", "cam_path", default="auto", show_default=True, help="auto, or a JSON camera path file."
)
@click.option("--frames", default=120, show_default=True, help="Frames of the auto path.")
@click.option("--fps", default=24, show_default=True)
@click.option("--size", "size_text", default="1280x720", show_default=True, help="WIDTHxHEIGHT pixels.")
@click.option("--threshold-px", default=2.0, show_default=True)
@click.option("--overwrite", is_flag=True, help="Replace an existing video.")
@aim_options
@view_options
@read_options
def flythrough(
    path, output, cam_path, frames, fps, size_text, threshold_px, overwrite, look_at, from_text, water_level,
    fractal_levels, cull, **read: Any
) -> None:  # fmt: skip
    """Render a fly-through video of a store (or a DEM, built first), headless. The auto path descends
    from an overview onto the terrain's relief (or onto --look-at / --from)."""
    inputs = [path] + ([cam_path] if cam_path != "auto" else [])
    check_output(output, inputs, overwrite=overwrite, suffixes=VIDEO_SUFFIXES, what="video")
    w, h = size(size_text)
    with open_terrain_arg(path, read, fractal_levels) as terrain:
        end = aimed_pose(terrain, look_at, from_text)
        summary = render_flythrough(terrain, output, cam_path=cam_path, frames=frames, fps=fps, size=(w, h),
                                    threshold_px=threshold_px, cull=cull, water_level_m=water_level,
                                    end_pose=end)  # fmt: skip
    flythrough_table(summary)
