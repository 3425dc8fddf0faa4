"""``terralod flythrough PATH -o video.mp4``: a fly-through video of any terrain, headless."""

from __future__ import annotations

from typing import Any

import click
import numpy as np

from terralod.cli._console import console
from terralod.cli._epochs import at_epoch, caption, epoch_options, overlay_for
from terralod.cli._inputs import open_terrain_arg
from terralod.cli._options import aim_options, aimed_pose, check_output, read_options, size, view_options


def timelapse_video(terrain, output: str, epochs_text: str, **kw: Any) -> dict[str, Any]:
    """``--epochs all|D1,D2,...``: :func:`terralod.render.timelapse.timelapse` over those epochs."""
    from terralod.errors import InputError
    from terralod.render.offscreen import terrain_colours
    from terralod.render.overlay import DEFAULT_LOD_M
    from terralod.render.timelapse import timelapse

    have = list(getattr(terrain, "epochs", []))
    eps = have if epochs_text.strip() == "all" else [e.strip() for e in epochs_text.split(",") if e.strip()]
    missing = [e for e in eps if e not in have]
    if missing or not eps:
        raise InputError(f"has no epoch {missing[0] if missing else epochs_text!r} (epochs: {', '.join(have) or 'none'})",
                         str(terrain.path))  # fmt: skip
    from terralod.render import RenderSettings

    st = terrain_colours(terrain, RenderSettings(legend=kw.get("overlay") != "change"))
    if not (getattr(terrain, "meta", {}) or {}).get("colour_range_m"):
        st.height_range_m = None  # no range recorded for all epochs: the union of theirs (timelapse)
    lod = kw.pop("lod_m", None)
    overlay = kw.pop("overlay", "none")
    return timelapse(terrain, output, epochs=eps, settings=st, overlay=None if overlay == "none" else overlay,
                     lod_m=DEFAULT_LOD_M if lod is None else lod, **kw)  # fmt: skip


#: Video files ``flythrough -o`` writes (H.264 through ffmpeg).
VIDEO_SUFFIXES = (".mp4", ".mkv", ".mov")


def render_flythrough(terrain, output: str, *, cam_path: str = "auto", frames: int = 120, fps: int = 24,
                      size=(1280, 720), threshold_px: float = 2.0, png: str | None = None,
                      cull: tuple[str, ...] = (), water_level_m: float | None = None, legend: bool = True,
                      end_pose=None, overlay: tuple | None = None) -> dict[str, Any]:  # fmt: skip
    """Render a camera path to MP4; returns the per-frame statistics summarised (medians, worst error).
    The auto path ends on the terrain's relief, or at ``end_pose`` (--look-at / --from) when given.
    ``overlay`` = (kind, from_epoch, lod_m) draws the change overlay (cli/_epochs.py) and the date."""
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
    ov = overlay_for(terrain, *overlay, st) if overlay else None
    fr = FrameRenderer(terrain, size[0], size[1], threshold_px=threshold_px, cull=cull, settings=st)
    per_frame: list[dict[str, Any]] = []

    def gen():
        for i, pose in enumerate(poses):
            img = caption(fr.frame(pose), terrain, ov)
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
@click.option(
    "--epochs", "epochs_text", default=None, metavar="all|D1,D2,...",
    help="A time-lapse of the store's epochs (all, or a list): each shown in turn with its date, one colour "
    "scale for all, the camera turning slowly (--orbit-deg).",
)  # fmt: skip
@click.option("--seconds-per-epoch", type=click.FloatRange(min=0.04), default=0.5, show_default=True)
@click.option(
    "--orbit-deg", type=float, default=30.0, show_default=True, help="Time-lapse camera turn (0: fixed)."
)
@epoch_options
@aim_options
@view_options
@read_options
def flythrough(
    path, output, cam_path, frames, fps, size_text, threshold_px, overwrite, look_at, from_text, water_level,
    fractal_levels, cull, epochs_text, seconds_per_epoch, orbit_deg, epoch, overlay, from_epoch, lod_m, **read: Any
) -> None:  # fmt: skip
    """Render a fly-through video of a store (or a DEM, built first), headless. The auto path descends
    from an overview onto the terrain's relief (or onto --look-at / --from)."""
    inputs = [path] + ([cam_path] if cam_path != "auto" else [])
    check_output(output, inputs, overwrite=overwrite, suffixes=VIDEO_SUFFIXES, what="video")
    w, h = size(size_text)
    if epochs_text is not None:
        with open_terrain_arg(path, read, fractal_levels) as terrain:
            summary = timelapse_video(terrain, output, epochs_text, fps=fps, size=(w, h), threshold_px=threshold_px,
                                      overlay=overlay, from_epoch=from_epoch, lod_m=lod_m,
                                      seconds_per_epoch=seconds_per_epoch, orbit_deg=orbit_deg)  # fmt: skip
        flythrough_table(summary)
        console.print(
            f"time-lapse of {len(summary['epochs'])} epochs, {summary['first']} to {summary['last']}"
        )
        return
    with open_terrain_arg(path, read, fractal_levels) as whole, at_epoch(whole, epoch) as terrain:
        end = aimed_pose(terrain, look_at, from_text)
        summary = render_flythrough(terrain, output, cam_path=cam_path, frames=frames, fps=fps, size=(w, h),
                                    threshold_px=threshold_px, cull=cull, water_level_m=water_level,
                                    end_pose=end, overlay=(overlay, from_epoch, lod_m))  # fmt: skip
    flythrough_table(summary)
