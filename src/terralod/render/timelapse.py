"""Frames and time-lapse videos of a terrain's epochs, for people who are not terrain experts.

- :func:`epoch_frame`: one frame of one epoch, optionally with the change overlay (gain / loss relative to
  another epoch, :mod:`terralod.render.overlay`) and the date and legend burnt in.
- :func:`timelapse`: every epoch in turn (``terralod flythrough STORE --epochs all``), a slow camera orbit or
  a fixed view, the date on every frame, and the *same* colours for every epoch: the elevation ramp spans
  the union of the epochs' height ranges and the change scale the largest change of any epoch, so a colour
  means the same height or the same change all through the video.

The renderer and the frame pipeline are the shared ones (:class:`terralod.render.offscreen.FrameRenderer`);
an epoch is drawn by swapping the frame renderer's engine for one over that epoch's tiles (tiles whose
geometry did not change are not uploaded again: the renderer compares their checksums).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from terralod.render.overlay import (
    DEFAULT_LOD_M,
    ChangeOverlay,
    annotate,
    change_overlay,
    format_date,
    nice_max_m,
)


def epoch_height_range(terrain: Any, epochs: Sequence[str]) -> tuple[float, float]:
    """(lowest, highest) vertex height over ``epochs`` (one colour ramp for all of them), metres."""
    lo, hi = math.inf, -math.inf
    for e in epochs:
        with terrain.with_epoch(e) as t:
            a, b = t.elevation_range_m
        lo, hi = min(lo, a), max(hi, b)
    return float(lo), float(hi)


def series_overlays(terrain: Any, epochs: Sequence[str], before: str | None = None,
                    lod_m: float = DEFAULT_LOD_M) -> dict[str, ChangeOverlay]:  # fmt: skip
    """The change overlay of each epoch relative to ``before`` (default: the first), on one colour scale
    (the largest change of the series, rounded)."""
    ovs = {e: change_overlay(terrain, e, before, lod_m=lod_m, max_m=1.0) for e in epochs}
    vals = np.concatenate([o.change_m[np.abs(o.change_m) >= lod_m] for o in ovs.values()] + [np.zeros(0)])
    top = nice_max_m(vals, lod_m) if vals.size else 2.0 * lod_m
    for o in ovs.values():
        o.max_m = top
    return ovs


def orbit_pose(terrain: Any, azimuth_deg: float, elevation_deg: float = 38.0, distance: float = 0.95) -> Any:
    """The overview pose of :func:`terralod.render.offscreen.overview_pose` from ``azimuth_deg``."""
    from terralod.render.offscreen import overview_pose

    return overview_pose(terrain, elevation_deg=elevation_deg, azimuth_deg=azimuth_deg, distance=distance)


class EpochFrames:
    """One frame renderer drawing any epoch of a grid terrain with epochs."""

    def __init__(self, terrain: Any, width_px: int, height_px: int, *, threshold_px: float = 2.0,
                 settings: Any = None) -> None:  # fmt: skip
        from terralod.render import RenderSettings
        from terralod.render.offscreen import FrameRenderer

        self.terrain = terrain
        self.fr = FrameRenderer(terrain, width_px, height_px, threshold_px=threshold_px,
                                settings=settings or RenderSettings())  # fmt: skip
        self.threshold_px = threshold_px
        self._epoch = getattr(terrain, "epoch", None)
        self._view: Any = None

    def use_epoch(self, epoch: str) -> None:
        if epoch == self._epoch:
            return
        view = self.terrain.with_epoch(epoch)
        self.fr.engine.close()
        self.fr.engine = view.engine(threshold_px=self.threshold_px)
        if self._view is not None:
            self._view.close()
        self._view, self._epoch = view, epoch

    def frame(self, epoch: str, pose: Any, *, overlay: ChangeOverlay | None = None, caption: bool = True,
              subtitle: str | None = None) -> np.ndarray:  # fmt: skip
        self.use_epoch(epoch)
        base = self.fr.settings
        self.fr.settings = replace(base, overlay=overlay)
        try:
            img = self.fr.frame(pose)
        finally:
            self.fr.settings = base
        if caption:
            img = annotate(img, date=epoch, overlay=overlay, subtitle=subtitle)
        return img

    @property
    def last_stats(self) -> dict:
        return self.fr.last_stats

    def close(self) -> None:
        self.fr.close()
        if self._view is not None:
            self._view.close()


def epoch_frame(terrain: Any, epoch: str | None, pose: Any, width_px: int, height_px: int, *,
                overlay: str | None = None, from_epoch: str | None = None, lod_m: float = DEFAULT_LOD_M,
                threshold_px: float = 2.0, settings: Any = None, caption: bool = True) -> np.ndarray:  # fmt: skip
    """One frame of ``epoch`` (default: the terrain's); ``overlay="change"`` colours the change since
    ``from_epoch`` (default: the first epoch)."""
    epoch = epoch or terrain.epoch or terrain.epochs[-1]
    ov = change_overlay(terrain, epoch, from_epoch, lod_m=lod_m) if overlay == "change" else None
    ef = EpochFrames(terrain, width_px, height_px, threshold_px=threshold_px, settings=settings)
    try:
        return ef.frame(epoch, pose, overlay=ov, caption=caption)
    finally:
        ef.close()


def timelapse(
    terrain: Any,
    output: str | Path,
    *,
    epochs: Sequence[str] | None = None,
    fps: int = 24,
    seconds_per_epoch: float = 0.5,
    size: tuple[int, int] = (1280, 720),
    threshold_px: float = 2.0,
    overlay: str | None = None,
    from_epoch: str | None = None,
    lod_m: float = DEFAULT_LOD_M,
    orbit_deg: float = 30.0,
    azimuth_deg: float = 200.0,
    settings: Any = None,
    png_dir: str | Path | None = None,
) -> dict[str, Any]:
    """Render every epoch in turn to a video; returns a summary (frames, epochs, medians of frame stats).

    The camera turns ``orbit_deg`` about the terrain over the whole video (0: a fixed view from
    ``azimuth_deg``); each epoch is held ``seconds_per_epoch``; ``png_dir`` keeps one PNG per epoch.
    """
    from terralod.render import RenderSettings
    from terralod.render.offscreen import write_video

    eps = list(epochs or terrain.epochs)
    if not eps:
        from terralod.errors import InputError

        raise InputError("has no epochs (build with --epoch, then terralod update)", str(terrain.path))
    st = settings or RenderSettings()
    st = replace(st, height_range_m=st.height_range_m or epoch_height_range(terrain, eps))
    ovs = series_overlays(terrain, eps, from_epoch, lod_m) if overlay == "change" else {}
    per_epoch = max(1, round(fps * seconds_per_epoch))
    n_frames = per_epoch * len(eps)
    ef = EpochFrames(terrain, size[0], size[1], threshold_px=threshold_px, settings=st)
    stats: list[dict] = []
    if png_dir is not None:
        Path(png_dir).mkdir(parents=True, exist_ok=True)

    def gen():
        k = 0
        for i, e in enumerate(eps):
            for j in range(per_epoch):
                s = k / max(1, n_frames - 1)
                pose = orbit_pose(terrain, azimuth_deg - orbit_deg / 2 + orbit_deg * s)
                img = ef.frame(e, pose, overlay=ovs.get(e), subtitle=f"survey {i + 1} of {len(eps)}")
                stats.append(ef.last_stats)
                if png_dir is not None and j == per_epoch // 2:
                    from terralod.render.offscreen import save_png

                    save_png(img, Path(png_dir) / f"epoch_{i:02d}_{e}.png")
                k += 1
                yield img

    try:
        n = write_video(gen(), output, fps=fps)
    finally:
        ef.close()
    keys = ("tiles", "triangles", "max_screen_error_px", "select_ms", "stitch_ms", "draw_ms")
    out: dict[str, Any] = {"output": str(output), "frames": n, "epochs": eps,
                           "first": format_date(eps[0]), "last": format_date(eps[-1])}  # fmt: skip
    out.update({k: float(np.median([f.get(k, 0.0) for f in stats])) for k in keys})
    out["max_screen_error_px_max"] = float(max(f.get("max_screen_error_px", 0.0) for f in stats))
    if ovs:
        out["change_scale_m"] = next(iter(ovs.values())).max_m
    return out
