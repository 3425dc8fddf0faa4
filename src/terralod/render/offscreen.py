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


def relief_focus(terrain) -> tuple[np.ndarray, float]:
    """(x, y, z) of where the terrain's relief is, and the radius (metres) of that area.

    Roughness is read from the LOD tree: a tile's measured error is the relief its coarse mesh could not
    follow. Over the finest level with at most 256 tiles, the tiles in the top quarter of error are
    averaged (weighted by error); the radius is their spread (at least two tile widths)."""
    t = as_terrain(terrain)
    nodes = t.lod_tree()
    by_level: dict[int, list] = {}
    for n in nodes:
        by_level.setdefault(n.code[0], []).append(n)
    levels = sorted(by_level)
    level = levels[0]
    for k in levels:
        if len(by_level[k]) <= 256:
            level = k
    nodes = [n for n in by_level[level] if n.box_m[5] > n.box_m[2] or n.vertical_error_m > 0]
    lo, hi = store_extent(t)
    if not nodes:
        return (lo + hi) / 2, float(np.linalg.norm(hi[:2] - lo[:2])) / 2
    err = np.array([n.vertical_error_m for n in nodes])
    box = np.array([n.box_m for n in nodes])
    cxy = np.stack([(box[:, 0] + box[:, 3]) / 2, (box[:, 1] + box[:, 4]) / 2], axis=1)
    top = err >= np.quantile(err, 0.75)
    w = err[top] + 1e-9
    c = (cxy[top] * w[:, None]).sum(axis=0) / w.sum()
    width = float(np.median(box[:, 3] - box[:, 0]))
    spread = float(np.sqrt((((cxy[top] - c) ** 2).sum(axis=1) * w).sum() / w.sum()))
    z = float(np.average((box[top, 2] + box[top, 5]) / 2, weights=w))
    return np.array([c[0], c[1], z]), max(spread, 2.0 * width)


def auto_path(terrain, n_frames: int, end: CameraPose | None = None) -> list[CameraPose]:
    """A scripted fly-through: a descending half-orbit from an overview of the whole terrain toward where
    its relief is (:func:`relief_focus`), ending over that relief and looking down across it, so far and
    near tiles of several levels are on screen together. With ``end`` the path eases into that pose."""
    lo, hi = store_extent(terrain)
    c0 = (lo + hi) / 2
    focus, radius = relief_focus(terrain)
    span = float(np.linalg.norm(hi[:2] - lo[:2]))
    relief = float(hi[2] - lo[2])
    out = []
    for i in range(n_frames):
        s = i / max(1, n_frames - 1)
        e = s * s * (3 - 2 * s)  # ease in and out
        c = c0[:2] + (focus[:2] - c0[:2]) * e
        az = math.radians(200.0 + 120.0 * s)
        r = span * 0.9 * (1 - e) + 1.6 * radius * e
        height = hi[2] + relief * 0.2 + span * 0.45 * (1 - e) + (0.8 * radius) * e
        eye = np.array([c[0] + r * math.sin(az), c[1] + r * math.cos(az), height])
        tz = lo[2] + 0.3 * relief + (focus[2] - lo[2] - 0.3 * relief) * e
        back = 0.15 * r * (1 - e)
        tgt = np.array([c[0] - back * math.sin(az), c[1] - back * math.cos(az), tz])
        if end is not None:
            eye = eye + (np.asarray(end.eye) - eye) * e
            tgt = tgt + (np.asarray(end.target) - tgt) * e
        out.append(CameraPose(tuple(map(float, eye)), tuple(map(float, tgt))))
    return out


def lonlat_to_world(terrain, lon_deg: float, lat_deg: float) -> tuple[float, float]:
    """World (x, y) metres in the terrain's CRS of a longitude / latitude (WGS84)."""
    from terralod.errors import InputError

    t = as_terrain(terrain)
    if not t.crs:
        raise InputError("has no CRS (a local metric frame): aim with --eye/--target in metres", str(t.path))
    from rasterio.warp import transform  # rasterio's PROJ: pyproj is an extra

    xs, ys = transform("EPSG:4326", t.crs, [lon_deg], [lat_deg])
    return float(xs[0]), float(ys[0])


def height_at(terrain, x: float, y: float) -> float:
    """Elevation (metres) of the stored vertex nearest (x, y) in the finest LOD node containing it (the
    terrain's middle height when no node holds the point)."""
    t = as_terrain(terrain)
    best = None
    for n in t.lod_tree():
        b = n.box_m
        if b[0] <= x <= b[3] and b[1] <= y <= b[4] and (best is None or n.code[0] >= best.code[0]):
            best = n
    if best is not None:
        v, _ = t.lod_mesh(best.code)
        if len(v):
            k = int(np.argmin((v[:, 0] - x) ** 2 + (v[:, 1] - y) ** 2))
            return float(v[k, 2])
    zlo, zhi = t.elevation_range_m
    return 0.5 * (zlo + zhi)


def aim_pose(
    terrain, look_at_lonlat: tuple[float, float] | None = None,
    from_deg_m: tuple[float, float, float] | None = None,
) -> CameraPose:  # fmt: skip
    """A pose aimed without UTM metres: the target at a longitude / latitude on the terrain (default the
    terrain's centre), the eye at ``(azimuth° clockwise from north, elevation° above the horizon,
    distance m)`` from the target (default 200°, 35°, half the terrain's diagonal)."""
    lo, hi = store_extent(terrain)
    if look_at_lonlat is not None:
        x, y = lonlat_to_world(terrain, *look_at_lonlat)
    else:
        x, y = float((lo[0] + hi[0]) / 2), float((lo[1] + hi[1]) / 2)
    tgt = np.array([x, y, height_at(terrain, x, y)])
    az, el, dist = from_deg_m or (200.0, 35.0, 0.5 * float(np.linalg.norm(hi[:2] - lo[:2])))
    a, e = math.radians(az), math.radians(el)
    eye = tgt + dist * np.array([math.sin(a) * math.cos(e), math.cos(a) * math.cos(e), math.sin(e)])
    return CameraPose(tuple(map(float, eye)), tuple(map(float, tgt)))


#: a sea written as 0 m (SRTM, Copernicus) is drawn as water within this band around 0 m
SEA_TOLERANCE_M = 0.05


def has_sea(terrain) -> bool:
    """True when the terrain has an SRTM-style sea: vertices at 0 m (within :data:`SEA_TOLERANCE_M`)
    forming an area connected to the terrain's border (directly or through the nodata margin), at least
    0.5 % of it. Read from the finest LOD level with at most 64 nodes, rasterised at twice its vertex
    spacing. A flat floor at any other height (a quarry, a dry lake, a fill) is never water."""
    from scipy import ndimage

    t = as_terrain(terrain)
    nodes = t.lod_tree()
    levels = sorted({n.code[0] for n in nodes})
    level = levels[0]
    for k in levels:
        if sum(1 for n in nodes if n.code[0] == k) <= 64:
            level = k
    verts = [t.lod_mesh(n.code)[0] for n in nodes if n.code[0] == level]
    verts = [v for v in verts if len(v)]
    if not verts:
        return False
    v = np.concatenate(verts)
    if not (np.abs(v[:, 2]) <= SEA_TOLERANCE_M).any():
        return False
    w, s_, e, n = t.bounds_m
    cell = 2.0 * math.sqrt(max((e - w) * (n - s_), 1.0) / len(v))
    nx, ny = max(1, int(math.ceil((e - w) / cell))), max(1, int(math.ceil((n - s_) / cell)))
    ix = np.clip(((v[:, 0] - w) / cell).astype(int), 0, nx - 1)
    iy = np.clip(((v[:, 1] - s_) / cell).astype(int), 0, ny - 1)
    land = np.zeros((ny, nx), bool)
    sea = np.zeros((ny, nx), bool)
    zero = np.abs(v[:, 2]) <= SEA_TOLERANCE_M
    sea[iy[zero], ix[zero]] = True
    land[iy[~zero], ix[~zero]] = True
    sea &= ~land  # a cell with any land vertex is coast, not sea
    open_ = sea | ~(sea | land)  # sea or no data
    lab, _ = ndimage.label(open_, structure=np.ones((3, 3)))
    border = np.unique(np.concatenate([lab[0], lab[-1], lab[:, 0], lab[:, -1]]))
    border = border[border > 0]
    connected = sea & np.isin(lab, border)
    return bool(connected.sum() >= 0.005 * (sea | land).sum())


def terrain_colours(terrain, settings: RenderSettings, water_level_m: float | None = None) -> RenderSettings:
    """Fit ``settings`` to a terrain: one colour ramp over its elevation range (the store's metadata where
    it records one, so every epoch of a store shares it), and water: everything at or below
    ``water_level_m`` when given, else the SRTM-style sea at 0 m when :func:`has_sea` finds one."""
    t = as_terrain(terrain)
    meta = getattr(t, "meta", {}) or {}
    rng = meta.get("colour_range_m") or meta.get("elevation_range_m") or _vertex_range(t)
    rng = rng or t.elevation_range_m
    lo, hi = float(rng[0]), float(rng[1])
    if water_level_m is not None:
        settings.water_m = (-1e9, float(water_level_m))
        lo = max(lo, float(water_level_m))
    elif has_sea(t):
        settings.water_m = (-SEA_TOLERANCE_M, SEA_TOLERANCE_M)
        lo = max(lo, 0.0)
    if settings.height_range_m is None:
        settings.height_range_m = (lo, max(hi, lo + 1.0))
    return settings


def _vertex_range(t) -> tuple[float, float] | None:
    """(lowest, highest) stored vertex of a grid store over all its tiles (the root level alone misses the
    peaks its coarse mesh cuts), None for other terrains."""
    summaries = getattr(getattr(t, "store", None), "tile_summaries", None)
    if summaries is None:
        return None
    rows = [r for r in summaries() if r.get("n_vertices", 1) > 0]
    if not rows:
        return None
    return float(min(r["z_min_m"] for r in rows)), float(max(r["z_max_m"] for r in rows))


def legend_image(settings: RenderSettings, height_px: int) -> np.ndarray:
    """The colour legend as an (h, w, 4) uint8 RGBA image: the ramp with heights in metres (and a water
    swatch when water is drawn)."""
    from PIL import Image, ImageDraw, ImageFont

    from terralod.render.renderer import TerrainRenderer

    lo, hi = settings.height_range_m or (0.0, 1.0)
    bar_h = int(min(max(height_px * 0.35, 60), 260))
    size = 11 if height_px < 400 else 14
    font = ImageFont.load_default(size=size)
    ticks = _nice_ticks(lo, hi)
    labels = [f"{v:,.0f} m" if hi - lo >= 20 else f"{v:,.1f} m" for v in ticks]
    text_w = max(int(font.getlength(s)) for s in labels + ["water"]) + 6
    bar_w = 14
    water = settings.water_m is not None
    h = bar_h + 2 * size + (size + 8 if water else 0)
    w = bar_w + text_w + 16
    img = Image.new("RGBA", (w, h), (255, 255, 255, 190))
    d = ImageDraw.Draw(img)
    ramp = TerrainRenderer._ramp_texture()
    y0 = size
    for i in range(bar_h):
        k = int(round((1 - i / max(bar_h - 1, 1)) * 255))
        d.line([(6, y0 + i), (6 + bar_w, y0 + i)], fill=tuple(int(c) for c in ramp[k]) + (255,))
    for v, s in zip(ticks, labels, strict=True):
        y = y0 + (1 - (v - lo) / max(hi - lo, 1e-9)) * (bar_h - 1)
        d.line([(6, y), (6 + bar_w, y)], fill=(0, 0, 0, 160))  # the tick crosses the bar
        d.text((12 + bar_w, y - size / 2 - 1), s, fill=(0, 0, 0, 255), font=font)
    if water:
        yw = y0 + bar_h + size // 2 + 4
        col = tuple(int(255 * c) for c in settings.water_colour) + (255,)
        d.rectangle([(6, yw), (6 + bar_w, yw + size)], fill=col)
        d.text((12 + bar_w, yw - 1), "water", fill=(0, 0, 0, 255), font=font)
    return np.asarray(img)


def _nice_ticks(lo: float, hi: float, n: int = 5) -> list[float]:
    """Round heights between lo and hi (both ends included when no round value is near them)."""
    span = max(hi - lo, 1e-9)
    raw = span / max(n - 1, 1)
    mag = 10 ** math.floor(math.log10(raw))
    step = min((m * mag for m in (1, 2, 2.5, 5, 10) if m * mag >= raw), default=10 * mag)
    first = math.ceil(lo / step) * step
    ticks = [first + i * step for i in range(int((hi - first) / step + 1e-9) + 1)]
    if not ticks or ticks[0] - lo > 0.3 * step:
        ticks.insert(0, lo)
    if hi - ticks[-1] > 0.3 * step:
        ticks.append(hi)
    return ticks


def with_legend(img: np.ndarray, settings: RenderSettings) -> np.ndarray:
    """``img`` with :func:`legend_image` blended into its lower-right corner."""
    leg = legend_image(settings, img.shape[0])
    h, w = leg.shape[:2]
    if h + 8 > img.shape[0] or w + 8 > img.shape[1]:
        return img
    out = img.copy()
    y, x = img.shape[0] - h - 8, img.shape[1] - w - 8
    a = leg[:, :, 3:4].astype(np.float32) / 255.0
    region = out[y : y + h, x : x + w].astype(np.float32)
    out[y : y + h, x : x + w] = (region * (1 - a) + leg[:, :, :3] * a + 0.5).astype(np.uint8)
    return out


def load_path(path: str | Path) -> list[CameraPose]:
    """A camera path file: JSON list of {"eye": [x, y, z], "target": [x, y, z]} in world metres."""
    data = json.loads(Path(path).read_text())
    return [CameraPose(tuple(map(float, p["eye"])), tuple(map(float, p["target"]))) for p in data]


def cull_options(cull: tuple[str, ...] | list[str]) -> dict[str, bool]:
    """Engine options from culling names: "backface" (Hu & Wang §3.2), "region" (§3.1)."""
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
    cull : culling names for grid terrains ("backface", "region"; Hu & Wang)
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
        if self.settings.height_range_m is None:  # one ramp for every frame of this terrain
            self.settings.height_range_m = tuple(map(float, self.terrain.elevation_range_m))  # type: ignore[assignment]
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
        return with_legend(img, self.settings) if self.settings.legend else img

    def close(self) -> None:
        self.renderer.release()
        self.engine.close()


def save_png(img: np.ndarray, path: str | Path) -> None:
    """Write an image (format by suffix) atomically: to a temporary beside it, then renamed, so a full disk
    or a kill leaves no truncated file; errors name the file."""
    from PIL import Image

    from terralod.io.raster import atomic_file

    out = Path(path)
    try:
        with atomic_file(out) as tmp:
            Image.fromarray(img).save(
                tmp, format=Image.registered_extensions().get(out.suffix.lower(), "PNG")
            )
    except OSError as exc:
        raise OSError(exc.errno, exc.strerror or str(exc), str(out)) from exc


def write_video(frames, path: str | Path, fps: int = 24) -> int:
    """Encode (H, W, 3) uint8 frames to MP4 (H.264 through imageio-ffmpeg's bundled ffmpeg)."""
    import imageio.v2 as imageio

    n = 0
    with imageio.get_writer(str(path), fps=fps, codec="libx264", quality=7, macro_block_size=8) as w:
        for f in frames:
            w.append_data(f)
            n += 1
    return n
