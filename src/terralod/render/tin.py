"""Headless frames of a detail-increment TIN (paper 003): :class:`terralod.runtime.tin.TinRuntime` picks each
sub-block's scale per frame, :class:`TerrainRenderer` draws one mesh per sub-block."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from terralod.render.offscreen import CameraPose
from terralod.render.renderer import RenderSettings, TerrainRenderer

__all__ = ["TinFrameRenderer", "run_tin_viewer", "tin_overview_pose"]


def tin_overview_pose(model: Any, elevation_deg: float = 35.0, azimuth_deg: float = 200.0,
                      distance: float = 1.1) -> CameraPose:  # fmt: skip
    """A pose seeing the whole TIN from the south-south-west at ``elevation_deg`` above the horizon."""
    v = model.vertices_m
    lo, hi = v.min(axis=0), v.max(axis=0)
    c = (lo + hi) / 2
    c[2] = lo[2] + 0.3 * (hi[2] - lo[2])
    r = distance * float(np.linalg.norm(hi[:2] - lo[:2]))
    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    eye = c + r * np.array([math.sin(az) * math.cos(el), math.cos(az) * math.cos(el), math.sin(el)])
    return CameraPose(tuple(map(float, eye)), tuple(map(float, c)))


class TinFrameRenderer:
    """Runtime + renderer for one TIN model at one viewport size (mirrors ``FrameRenderer`` for tiles)."""

    def __init__(self, model: Any, width_px: int, height_px: int, *, threshold_px: float = 2.0,
                 fov_y_deg: float = 45.0, settings: RenderSettings | None = None, ctx=None) -> None:  # fmt: skip
        from terralod.runtime.tin import TinRuntime

        self.runtime = TinRuntime(model, threshold_px=threshold_px)
        self.renderer = TerrainRenderer(width_px, height_px, ctx=ctx)
        self.settings = settings or RenderSettings()
        self.fov_y_deg = fov_y_deg
        self.width_px, self.height_px = width_px, height_px
        self.last_stats: dict = {}

    def frame(self, pose: CameraPose) -> np.ndarray:
        import time

        from terralod.runtime import Camera

        d = float(np.linalg.norm(np.asarray(pose.eye) - np.asarray(pose.target)))
        cam = Camera(pose.eye, pose.target, (0.0, 0.0, 1.0), self.fov_y_deg, self.width_px, self.height_px,
                     near_m=max(0.1, d * 1e-4))  # fmt: skip
        f = self.runtime.update(cam)
        t = time.perf_counter()
        img = self.renderer.render(list(f.meshes()), pose.eye, pose.target, fov_y_deg=self.fov_y_deg,
                                   settings=self.settings)  # fmt: skip
        self.last_stats = {
            "sub_blocks": int(f.scales.size), "changed": int(f.changed.size), "triangles": f.triangles,
            "records_applied": f.records_applied, "select_ms": f.select_ms, "apply_ms": f.apply_ms,
            "mesh_ms": f.mesh_ms, "draw_ms": (time.perf_counter() - t) * 1e3,
        }  # fmt: skip
        return img

    def close(self) -> None:
        self.renderer.release()


def run_tin_viewer(model: Any, store_path: str, *, width_px: int = 1280, height_px: int = 720,
                   threshold_px: float = 2.0, max_frames: int | None = None, screenshot: str | None = None) -> dict:
    """The window viewer on a TIN: every frame moves each sub-block to its SVO scale (``TinEngine``)."""
    from pathlib import Path
    from types import SimpleNamespace

    from terralod.render.viewer import Viewer
    from terralod.runtime.tin import TinEngine

    v = model.vertices_m
    viewer = Viewer(SimpleNamespace(path=Path(store_path)), width_px=width_px, height_px=height_px,
                    threshold_px=threshold_px, title="terralod (TIN)", engine=TinEngine(model, threshold_px=threshold_px),
                    pose=tin_overview_pose(model), extent=(v.min(axis=0), v.max(axis=0)))  # fmt: skip
    try:
        return viewer.run(max_frames, screenshot)
    finally:
        viewer.close()
