"""Real-time window viewer (glfw + moderngl): orbit/pan/zoom with the mouse, fly with WASD, a HUD with
fps, frame ms, triangles, tiles, max screen error and select/stitch ms.

Selection runs on the engine's background thread; each frame draws the latest finished selection and
never waits for the next one.

Keys: W/A/S/D fly, Q/E down/up, +/- threshold x/÷ 1.25, F wireframe, L level-of-detail colours,
H error heat-map, P screenshot (PNG beside the store), Esc quit. A store with epochs: [ ] or PageUp/PageDown
previous/next epoch (the slider at the bottom; click it), Home/End first/last, C change overlay; the HUD shows
the date and the elevation and change under the cursor (terralod.render.viewer_epochs).
Mouse: left drag orbit, right drag pan, wheel zoom.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np

from terralod.render.offscreen import (
    CameraPose,
    cull_options,
    legend_image,
    overview_pose,
    store_extent,
    terrain_colours,
)
from terralod.render.renderer import _SHADERS, RenderSettings, TerrainRenderer
from terralod.render.viewer_epochs import EpochControl
from terralod.terrain import as_terrain, frame_stats


def hud_lines(
    stats: dict, fps: float, frame_ms: float, threshold_px: float, settings: RenderSettings
) -> list[str]:
    """The HUD text: the engine's own numbers, unrounded beyond display precision."""
    return [
        f"fps {fps:6.1f}   frame {frame_ms:6.2f} ms",
        f"tiles {int(stats.get('tiles', 0))}   triangles {int(stats.get('triangles', 0)):,}",
        f"max screen error {float(stats.get('max_screen_error_px', 0.0)):.2f} px   threshold {threshold_px:.2f} px",
        f"select {float(stats.get('select_ms', 0.0)):.2f} ms   stitch {float(stats.get('stitch_ms', 0.0)):.2f} ms",
        f"mode {settings.mode}{'  wireframe' if settings.wireframe else ''}",
    ]


class _Hud:
    def __init__(self, ctx) -> None:
        import moderngl

        self.ctx = ctx
        self.prog = ctx.program(
            vertex_shader=(_SHADERS / "hud.vert").read_text(),
            fragment_shader=(_SHADERS / "hud.frag").read_text(),
        )
        self.tex = None
        self.vao = None
        self._moderngl = moderngl

    def draw(self, lines: list[str], width_px: int, height_px: int) -> None:
        from PIL import Image, ImageDraw, ImageFont

        font = ImageFont.load_default()
        w, h = 460, 16 * len(lines) + 10
        img = Image.new("RGBA", (w, h), (0, 0, 0, 150))
        d = ImageDraw.Draw(img)
        for i, line in enumerate(lines):
            d.text((6, 4 + 16 * i), line, fill=(255, 255, 255, 255), font=font)
        self.blit(np.asarray(img), 8, 8, width_px, height_px)

    def blit(self, rgba: np.ndarray, x_px: int, y_px: int, width_px: int, height_px: int) -> None:
        """Draw an (h, w, 4) uint8 image with its top-left corner ``(x_px, y_px)`` from the window's
        top-left (alpha blended, over everything)."""
        h, w = rgba.shape[:2]
        data = np.ascontiguousarray(rgba[::-1])
        if self.tex is None or self.tex.size != (w, h):
            if self.tex is not None:
                self.tex.release()
            self.tex = self.ctx.texture((w, h), 4, data.tobytes())
        else:
            self.tex.write(data.tobytes())
        x0, y1 = -1.0 + x_px * 2.0 / width_px, 1.0 - y_px * 2.0 / height_px
        x1, y0 = x0 + 2.0 * w / width_px, y1 - 2.0 * h / height_px
        quad = np.array([x0, y0, 0, 0, x1, y0, 1, 0, x0, y1, 0, 1, x1, y1, 1, 1], np.float32)
        vbo = self.ctx.buffer(quad.tobytes())
        vao = self.ctx.vertex_array(self.prog, [(vbo, "2f 2f", "in_pos", "in_uv")])
        self.ctx.enable(self._moderngl.BLEND)
        self.ctx.disable(self._moderngl.DEPTH_TEST)
        self.tex.use(0)
        vao.render(self._moderngl.TRIANGLE_STRIP)
        self.ctx.disable(self._moderngl.BLEND)
        vao.release()
        vbo.release()


class Viewer:
    """The window. ``run(max_frames=None)`` loops until closed (or for ``max_frames`` frames)."""

    def __init__(self, terrain, *, width_px: int = 1280, height_px: int = 720, threshold_px: float = 2.0,
                 fov_y_deg: float = 45.0, title: str = "terralod", cull: tuple[str, ...] = (),
                 pose: CameraPose | None = None, water_level_m: float | None = None) -> None:  # fmt: skip
        import glfw
        import moderngl

        from terralod.errors import DisplayError

        terrain = as_terrain(terrain)
        cull_options(cull)

        if not glfw.init():
            raise DisplayError("glfw could not initialise (no display?)")
        glfw.window_hint(glfw.CONTEXT_VERSION_MAJOR, 3)
        glfw.window_hint(glfw.CONTEXT_VERSION_MINOR, 3)
        glfw.window_hint(glfw.OPENGL_PROFILE, glfw.OPENGL_CORE_PROFILE)
        glfw.window_hint(glfw.OPENGL_FORWARD_COMPAT, True)
        self.window = glfw.create_window(width_px, height_px, title, None, None)
        if not self.window:
            glfw.terminate()
            raise DisplayError("glfw could not open a window")
        glfw.make_context_current(self.window)
        glfw.swap_interval(0)
        self.glfw = glfw
        self.ctx = moderngl.create_context()
        self.terrain = terrain
        self.store = terrain
        self.width_px, self.height_px = width_px, height_px
        self.fov_y_deg = fov_y_deg
        self.threshold_px = threshold_px
        # the terrain's own engine (selection on a worker thread where the kind has one)
        self.engine = terrain.engine(threshold_px=threshold_px, background=True, cull=cull, async_loads=True)
        self.renderer = TerrainRenderer(width_px, height_px, ctx=self.ctx)
        # one colour ramp (with its legend) over the terrain's range, water where the source marks it
        self.settings = terrain_colours(terrain, RenderSettings(legend=True), water_level_m)
        self._legend = legend_image(self.settings, height_px)
        self.hud = _Hud(self.ctx)
        self.legend_hud = _Hud(self.ctx)
        # epochs: slider, change overlay, pick under the cursor (terralod.render.viewer_epochs)
        self.epochs = EpochControl(self, terrain, cull)
        self.epoch_huds = (_Hud(self.ctx), _Hud(self.ctx))
        pose = pose or overview_pose(terrain)
        self.eye = np.array(pose.eye, np.float64)
        self.target = np.array(pose.target, np.float64)
        lo, hi = store_extent(terrain)
        self.scale = float(np.linalg.norm(hi - lo))
        self._mouse = None
        self._buttons = set()
        self.last_stats: dict = {}
        self.last_hud: list[str] = []
        self.screenshots: list[Path] = []
        glfw.set_key_callback(self.window, self._on_key)
        glfw.set_mouse_button_callback(self.window, self._on_button)
        glfw.set_cursor_pos_callback(self.window, self._on_cursor)
        glfw.set_scroll_callback(self.window, self._on_scroll)

    # -- input -----------------------------------------------------------------------------------------
    def _on_key(self, win, key, sc, action, mods) -> None:
        g = self.glfw
        if action != g.PRESS:
            return
        if self.epochs.on_key(key):
            return
        if key == g.KEY_ESCAPE:
            g.set_window_should_close(win, True)
        elif key in (g.KEY_EQUAL, g.KEY_KP_ADD):
            self.set_threshold(self.threshold_px * 1.25)
        elif key in (g.KEY_MINUS, g.KEY_KP_SUBTRACT):
            self.set_threshold(self.threshold_px / 1.25)
        elif key == g.KEY_F:
            self.settings.wireframe = not self.settings.wireframe
        elif key == g.KEY_L:
            self.settings.mode = "elevation" if self.settings.mode == "lod" else "lod"
        elif key == g.KEY_H:
            self.settings.mode = "elevation" if self.settings.mode == "error" else "error"
        elif key == g.KEY_P:
            self.screenshot()

    def set_threshold(self, px: float) -> None:
        self.threshold_px = float(min(max(px, 0.25), 64.0))
        self.engine.threshold_px = self.threshold_px

    def _on_button(self, win, button, action, mods) -> None:
        if action == self.glfw.PRESS:
            if button == self.glfw.MOUSE_BUTTON_LEFT and self._mouse and self.epochs.on_click(*self._mouse):
                return  # a click on the epoch slider
            self._buttons.add(button)
        else:
            self._buttons.discard(button)

    def _on_cursor(self, win, x, y) -> None:
        if self._mouse is None:
            self._mouse = (x, y)
            return
        dx, dy = x - self._mouse[0], y - self._mouse[1]
        self._mouse = (x, y)
        if self.glfw.MOUSE_BUTTON_LEFT in self._buttons:
            self.orbit(-dx * 0.005, -dy * 0.005)
        elif self.glfw.MOUSE_BUTTON_RIGHT in self._buttons:
            self.pan(dx, dy)

    def _on_scroll(self, win, sx, sy) -> None:
        self.zoom(0.85**sy)

    def orbit(self, d_az: float, d_el: float) -> None:
        v = self.eye - self.target
        r = float(np.linalg.norm(v))
        az = math.atan2(v[0], v[1]) + d_az
        el = min(max(math.asin(v[2] / r) + d_el, math.radians(2)), math.radians(89))
        self.eye = self.target + r * np.array(
            [math.sin(az) * math.cos(el), math.cos(az) * math.cos(el), math.sin(el)]
        )

    def pan(self, dx_px: float, dy_px: float) -> None:
        f = self.target - self.eye
        d = float(np.linalg.norm(f))
        right = np.cross(f / d, [0, 0, 1.0])
        right /= max(np.linalg.norm(right), 1e-9)
        fwd = np.cross([0, 0, 1.0], right)
        k = d * 2 * math.tan(math.radians(self.fov_y_deg) / 2) / self.height_px
        move = (-dx_px * right + dy_px * fwd) * k
        self.eye += move
        self.target += move

    def zoom(self, factor: float) -> None:
        self.eye = self.target + (self.eye - self.target) * factor

    def fly(self, dt: float) -> None:
        g = self.glfw
        f = self.target - self.eye
        f[2] = 0
        n = np.linalg.norm(f)
        if n < 1e-9:
            return
        f /= n
        r = np.cross(f, [0, 0, 1.0])
        step = 0.15 * self.scale * dt
        mv = np.zeros(3)
        for key, vec in ((g.KEY_W, f), (g.KEY_S, -f), (g.KEY_D, r), (g.KEY_A, -r),
                         (g.KEY_E, np.array([0, 0, 1.0])), (g.KEY_Q, np.array([0, 0, -1.0]))):  # fmt: skip
            if g.get_key(self.window, key) == g.PRESS:
                mv += vec
        if mv.any():
            self.eye += mv * step
            self.target += mv * step

    # -- loop ------------------------------------------------------------------------------------------
    def camera(self):
        from terralod.runtime import Camera

        d = float(np.linalg.norm(self.eye - self.target))
        return Camera(tuple(self.eye), tuple(self.target), (0, 0, 1.0), self.fov_y_deg, self.width_px,
                      self.height_px, near_m=max(0.1, d * 1e-4))  # fmt: skip

    def screenshot(self, path: str | Path | None = None) -> Path:
        from PIL import Image

        raw = self.ctx.screen.read(components=3, alignment=1)
        img = np.frombuffer(raw, np.uint8).reshape(self.height_px, self.width_px, 3)[::-1]
        base = self.terrain.path or Path("terralod.terra")
        p = Path(path) if path else base.with_name(f"{base.stem}-{len(self.screenshots):03d}.png")
        Image.fromarray(img).save(p)
        self.screenshots.append(p)
        return p

    def run(self, max_frames: int | None = None, screenshot: str | Path | None = None) -> dict:
        g = self.glfw
        frames = 0
        t_prev = time.perf_counter()
        fps = 0.0
        sel = None
        while not g.window_should_close(self.window):
            t0 = time.perf_counter()
            g.poll_events()
            self.fly(t0 - t_prev)
            t_prev = t0
            self.engine.request(self.camera())
            latest = self.engine.latest()
            if latest is None and sel is None:
                latest = self.engine.update(self.camera())  # the very first frame has nothing to draw yet
            sel = latest or sel
            meshes = list(sel.meshes())
            self.renderer.render(meshes, self.eye, self.target, fov_y_deg=self.fov_y_deg, settings=self.settings,
                                 read=False)  # fmt: skip
            frame_ms = (time.perf_counter() - t0) * 1e3
            fps = 0.9 * fps + 0.1 * (1000.0 / max(frame_ms, 1e-3)) if frames else 1000.0 / max(frame_ms, 1e-3)
            stats = frame_stats(sel)
            self.last_stats = stats
            self.last_hud = hud_lines(stats, fps, frame_ms, self.threshold_px, self.settings)
            if frames % 4 == 0:
                self.epochs.update_pick()
            self.last_hud += self.epochs.hud_lines()
            self.hud.draw(self.last_hud, self.width_px, self.height_px)
            if self.settings.legend and self.settings.mode == "elevation":
                lh, lw = self._legend.shape[:2]
                self.legend_hud.blit(self._legend, self.width_px - lw - 8, self.height_px - lh - 8, self.width_px,
                              self.height_px)  # fmt: skip
            self.epochs.draw(*self.epoch_huds)
            frames += 1
            if max_frames is not None and frames >= max_frames:
                if screenshot:
                    self.screenshot(screenshot)
                g.swap_buffers(self.window)
                break
            g.swap_buffers(self.window)
        return {"frames": frames, "stats": self.last_stats, "hud": self.last_hud}

    def close(self) -> None:
        self.engine.close() if hasattr(self.engine, "close") else None
        self.epochs.close()
        self.renderer.release()
        self.glfw.destroy_window(self.window)
        self.glfw.terminate()


def run_viewer(terrain, **kw) -> dict:
    """Open the window on any terrain (grid store or TIN) and run it; returns the last frame's numbers."""
    keys = ("width_px", "height_px", "threshold_px", "cull", "title", "pose", "water_level_m")
    v = Viewer(terrain, **{k: kw[k] for k in keys if k in kw})
    try:
        return v.run(kw.get("max_frames"), kw.get("screenshot"))
    finally:
        v.close()


__all__ = ["CameraPose", "Viewer", "hud_lines", "run_viewer"]
