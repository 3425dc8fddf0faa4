"""Headless frames and fly-through videos of any :class:`terralod.terrain.Terrain` (grid store or TIN):
selection by the terrain's engine, drawing by :class:`TerrainRenderer` on an EGL context (Mesa llvmpipe
where there is no GPU). Functions also take an open tile store, a fractal source or a TIN model, wrapped
by :func:`terralod.terrain.as_terrain`."""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from terralod.render.renderer import RenderSettings, TerrainRenderer
from terralod.terrain import as_terrain, frame_stats


@dataclass(frozen=True)
class CameraPose:
    """Eye and target in world metres."""

    eye: tuple[float, float, float]
    target: tuple[float, float, float]


def store_extent(terrain) -> tuple[np.ndarray, np.ndarray]:
    """(min xyz, max xyz) of a terrain, metres (xy from its bounds, z from its elevation range)."""
    t = as_terrain(terrain)
    w, s_, e, n = t.bounds_m
    zlo, zhi = t.elevation_range_m
    return np.array([w, s_, zlo], np.float64), np.array([e, n, zhi], np.float64)


def overview_pose(
    terrain, elevation_deg: float = 35.0, azimuth_deg: float = 200.0, distance: float = 1.1
) -> CameraPose:
    """A pose seeing the whole terrain from the south-south-west at ``elevation_deg`` above the horizon."""
    lo, hi = store_extent(terrain)
    c = (lo + hi) / 2
    c[2] = lo[2] + 0.3 * (hi[2] - lo[2])
    r = distance * float(np.linalg.norm(hi[:2] - lo[:2]))
    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    eye = c + r * np.array([math.sin(az) * math.cos(el), math.cos(az) * math.cos(el), math.sin(el)])
    return CameraPose(tuple(map(float, eye)), tuple(map(float, c)))


def auto_path(terrain, n_frames: int) -> list[CameraPose]:
    """A scripted fly-through: a descending half-orbit that ends low over the terrain, looking across it,
    so far and near tiles of several levels are on screen together."""
    lo, hi = store_extent(terrain)
    c = (lo + hi) / 2
    span = float(np.linalg.norm(hi[:2] - lo[:2]))
    relief = float(hi[2] - lo[2])
    out = []
    for i in range(n_frames):
        s = i / max(1, n_frames - 1)
        az = math.radians(200.0 + 120.0 * s)
        r = span * (0.9 - 0.55 * s)
        height = hi[2] + relief * 0.2 + span * (0.45 - 0.35 * s)
        eye = np.array([c[0] + r * math.sin(az), c[1] + r * math.cos(az), height])
        tgt = np.array([c[0] - 0.15 * r * math.sin(az), c[1] - 0.15 * r * math.cos(az), lo[2] + 0.3 * relief])
        out.append(CameraPose(tuple(eye), tuple(tgt)))
    return out


def load_path(path: str | Path) -> list[CameraPose]:
    """A camera path file: JSON list of {"eye": [x, y, z], "target": [x, y, z]} in world metres."""
    data = json.loads(Path(path).read_text())
    return [CameraPose(tuple(map(float, p["eye"])), tuple(map(float, p["target"]))) for p in data]


def cull_options(cull: tuple[str, ...] | list[str]) -> dict[str, bool]:
    """Engine options from culling names: "backface" (paper 001 §3.2), "region" (§3.1)."""
    bad = set(cull) - {"backface", "region"}
    if bad:
        raise ValueError(f"Expected culling among backface, region; got {sorted(bad)}")
    return {"cull_backfacing": "backface" in cull, "cull_region": "region" in cull}


class FrameRenderer:
    """A terrain's engine + the renderer at one viewport size.

    Parameters
    ----------
    terrain : a :class:`terralod.terrain.Terrain` (or what :func:`terralod.terrain.as_terrain` wraps)
    width_px, height_px : viewport
    threshold_px : screen-space error threshold, pixels
    cull : culling names for grid terrains ("backface", "region"; paper 001)
    """

    def __init__(
        self, terrain, width_px: int, height_px: int, *, threshold_px: float = 2.0, fov_y_deg: float = 45.0,
        settings: RenderSettings | None = None, ctx=None, draw_mode: str = "auto", cull: tuple[str, ...] = (),
    ) -> None:  # fmt: skip
        self.store = terrain
        self.terrain = as_terrain(terrain)
        cull_options(cull)
        self.engine = self.terrain.engine(threshold_px=threshold_px, cull=cull)
        self.renderer = TerrainRenderer(width_px, height_px, ctx=ctx, draw_mode=draw_mode)
        self.settings = settings or RenderSettings()
        self.fov_y_deg = fov_y_deg
        self.width_px, self.height_px = width_px, height_px
        self.last_stats: dict = {}

    def camera(self, pose: CameraPose):
        from terralod.runtime import Camera

        d = float(np.linalg.norm(np.asarray(pose.eye) - np.asarray(pose.target)))
        return Camera(pose.eye, pose.target, (0.0, 0.0, 1.0), self.fov_y_deg, self.width_px, self.height_px,
                      near_m=max(0.1, d * 1e-4))  # fmt: skip

    def frame(self, pose: CameraPose) -> np.ndarray:
        cam = self.camera(pose)
        sel = self.engine.update(cam)
        meshes = list(sel.meshes())
        t = time.perf_counter()
        img = self.renderer.render(
            meshes, pose.eye, pose.target, fov_y_deg=self.fov_y_deg, settings=self.settings
        )
        stats = frame_stats(sel)
        stats["draw_ms"] = (time.perf_counter() - t) * 1e3
        self.last_stats = stats
        return img

    def close(self) -> None:
        self.renderer.release()
        self.engine.close()


def save_png(img: np.ndarray, path: str | Path) -> None:
    """Write an image (format by suffix) atomically: to a temporary beside it, then renamed, so a full disk
    or a kill leaves no truncated file; errors name the file."""
    import os

    from PIL import Image

    out = Path(path)
    tmp = out.with_name(f".{out.name}.{os.getpid()}.tmp")
    try:
        Image.fromarray(img).save(tmp, format=Image.registered_extensions().get(out.suffix.lower(), "PNG"))
        os.replace(tmp, out)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise OSError(exc.errno, exc.strerror or str(exc), str(out)) from exc
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_video(frames, path: str | Path, fps: int = 24) -> int:
    """Encode (H, W, 3) uint8 frames to MP4 (H.264 through imageio-ffmpeg's bundled ffmpeg)."""
    import imageio.v2 as imageio

    n = 0
    with imageio.get_writer(str(path), fps=fps, codec="libx264", quality=7, macro_block_size=8) as w:
        for f in frames:
            w.append_data(f)
            n += 1
    return n
