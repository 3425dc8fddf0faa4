"""The window viewer's epoch controls: an epoch slider (keys and an on-screen control), the change
overlay toggle, the date on screen, and the elevation and change under the cursor in the HUD.

Keys: ``[`` / ``]`` or PageUp / PageDown previous / next epoch, Home / End first / last, C change overlay
(gain blue, loss red since the first epoch, greyed below the level of detection; one colour scale for all
epochs). Mouse: a click on the slider at the bottom of the window picks that epoch.

The parts that need no window are plain functions (:func:`slider_geometry`, :func:`slider_hit`,
:func:`slider_image`, :func:`pick_ground`), so they are tested headless; :class:`EpochControl` ties them to
a :class:`terralod.render.viewer.Viewer`.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from terralod.render.overlay import DEFAULT_LOD_M, format_date, legend_image

#: Key names of :meth:`EpochControl.on_key` (glfw key constants are looked up by these names).
KEYS_PREVIOUS = ("KEY_LEFT_BRACKET", "KEY_PAGE_UP")
KEYS_NEXT = ("KEY_RIGHT_BRACKET", "KEY_PAGE_DOWN")


def slider_geometry(width_px: int, height_px: int) -> tuple[int, int, int, int]:
    """(x0, y0, w, h) of the slider panel, pixels from the window's top-left (bottom centre)."""
    w = int(min(640, width_px - 40))
    h = 52
    return (width_px - w) // 2, height_px - h - 10, w, h


def _track(w: int) -> tuple[int, int]:
    return 18, w - 18


def slider_hit(x_px: float, y_px: float, n: int, width_px: int, height_px: int) -> int | None:
    """The epoch index under a click at (x, y) pixels, None when it misses the slider."""
    x0, y0, w, h = slider_geometry(width_px, height_px)
    if n < 1 or not (x0 <= x_px <= x0 + w and y0 <= y_px <= y0 + h):
        return None
    a, b = _track(w)
    f = (x_px - x0 - a) / max(b - a, 1)
    return int(min(max(round(f * (n - 1)), 0), n - 1))


def slider_image(names: list[str], index: int, width_px: int, height_px: int, overlay_on: bool) -> np.ndarray:
    """The slider panel as (h, w, 4) uint8 RGBA: a tick per epoch, the knob on the current one, its date."""
    from PIL import Image, ImageDraw

    from terralod.render.overlay import _font

    _, _, w, h = slider_geometry(width_px, height_px)
    img = Image.new("RGBA", (w, h), (0, 0, 0, 150))
    d = ImageDraw.Draw(img)
    a, b = _track(w)
    y = 14
    d.line([(a, y), (b, y)], fill=(200, 200, 200, 255), width=3)
    n = len(names)
    for i in range(n):
        x = a + (b - a) * (i / max(n - 1, 1))
        d.line([(x, y - 5), (x, y + 5)], fill=(230, 230, 230, 255), width=1)
    xk = a + (b - a) * (index / max(n - 1, 1))
    d.ellipse([xk - 7, y - 7, xk + 7, y + 7], fill=(255, 200, 40, 255), outline=(40, 40, 40, 255))
    f = _font(14)
    fs = _font(11)
    label = f"{format_date(names[index])}   ({index + 1} of {n})"
    d.text((a, y + 12), label, fill=(255, 255, 255, 255), font=f)
    hint = "[ ] or PgUp/PgDn: epoch   C: change " + ("off" if overlay_on else "on")
    tw = d.textlength(hint, font=fs)
    d.text((b - tw, y + 15), hint, fill=(210, 210, 210, 255), font=fs)
    return np.asarray(img)


def pick_ground(eye: np.ndarray, target: np.ndarray, fov_y_deg: float, width_px: int, height_px: int,
                x_px: float, y_px: float, hf: Any, z_exaggeration: float = 1.0,
                steps: int = 2048) -> tuple[float, float, float] | None:  # fmt: skip
    """World (x, y, z) where the ray through pixel (x, y) first meets the heightfield ``hf`` (nearest
    sample), or None when it meets no ground. The ray is marched in ``steps`` steps to the far side of the
    terrain, then refined by bisection."""
    eye = np.asarray(eye, np.float64)
    f = np.asarray(target, np.float64) - eye
    f /= np.linalg.norm(f)
    s = np.cross(f, [0.0, 0.0, 1.0])
    if np.linalg.norm(s) < 1e-9:
        s = np.cross(f, [0.0, 1.0, 0.0])
    s /= np.linalg.norm(s)
    u = np.cross(s, f)
    t = math.tan(math.radians(fov_y_deg) / 2)
    nx = (2.0 * (x_px + 0.5) / width_px - 1.0) * t * width_px / height_px
    ny = (1.0 - 2.0 * (y_px + 0.5) / height_px) * t
    ray = f + nx * s + ny * u
    ray /= np.linalg.norm(ray)
    z = hf.elevation_m
    w, s_, e, n = hf.bounds_m
    reach = float(np.linalg.norm([e - w, n - s_])) + float(
        np.linalg.norm(eye[:2] - [(w + e) / 2, (s_ + n) / 2])
    )
    reach += abs(float(eye[2])) + float(np.nanmax(z)) * z_exaggeration

    def above(p: np.ndarray) -> np.ndarray:
        """Height of the points above the ground (NaN off the grid)."""
        r, c = hf.sample_rc(p[:, 0], p[:, 1])
        ri, ci = np.rint(r).astype(np.int64), np.rint(c).astype(np.int64)
        ok = (ri >= 0) & (ri < hf.height) & (ci >= 0) & (ci < hf.width)
        g = np.full(len(p), np.nan)
        g[ok] = z[ri[ok], ci[ok]] * z_exaggeration
        return p[:, 2] - g

    ts = np.linspace(0.0, reach, steps)
    pts = eye[None, :] + ts[:, None] * ray[None, :]
    h = above(pts)
    below = np.flatnonzero(h <= 0)
    if below.size == 0:
        return None
    k = int(below[0])
    lo, hi = (ts[k - 1], ts[k]) if k > 0 else (0.0, ts[0])
    for _ in range(30):
        mid = 0.5 * (lo + hi)
        hm = above((eye + mid * ray)[None, :])[0]
        if np.isfinite(hm) and hm <= 0:
            hi = mid
        else:
            lo = mid
    p = eye + hi * ray
    r, c = hf.sample_rc(p[0], p[1])
    ri, ci = int(round(float(r))), int(round(float(c)))
    if not (0 <= ri < hf.height and 0 <= ci < hf.width):
        return None
    return float(p[0]), float(p[1]), float(z[ri, ci])


class EpochControl:
    """Epochs in a :class:`terralod.render.viewer.Viewer`: which one is drawn, the change overlay, the pick
    under the cursor. Inert (no slider, no lines) for a terrain with fewer than two epochs, except the
    elevation under the cursor."""

    def __init__(
        self, viewer: Any, terrain: Any, cull: tuple[str, ...] = (), lod_m: float = DEFAULT_LOD_M
    ) -> None:
        self.viewer = viewer
        self.base = terrain
        self.cull = cull
        self.lod_m = lod_m
        self.names: list[str] = list(getattr(terrain, "epochs", []) or [])
        current = getattr(terrain, "epoch", None)
        self.index = self.names.index(current) if current in self.names else max(len(self.names) - 1, 0)
        self.overlay_on = False
        self._overlays: dict[str, Any] | None = None
        self._views: list[Any] = []
        self._grids: dict[str | None, Any] = {}
        self.cursor: tuple[float, float] | None = None
        self.picked: tuple[float, float, float] | None = None
        self.change_m: float | None = None
        self._legend_settings = None

    @property
    def active(self) -> bool:
        return len(self.names) >= 2

    @property
    def epoch(self) -> str | None:
        return self.names[self.index] if self.names else None

    # -- input ---------------------------------------------------------------------------------------
    def on_key(self, key: int) -> bool:
        """Handle a key press; True when it was an epoch key."""
        g = self.viewer.glfw
        if not self.active:
            return False
        if key in [getattr(g, k) for k in KEYS_PREVIOUS]:
            self.set_index(self.index - 1)
        elif key in [getattr(g, k) for k in KEYS_NEXT]:
            self.set_index(self.index + 1)
        elif key == g.KEY_HOME:
            self.set_index(0)
        elif key == g.KEY_END:
            self.set_index(len(self.names) - 1)
        elif key == g.KEY_C:
            self.toggle_overlay()
        else:
            return False
        return True

    def on_click(self, x_px: float, y_px: float) -> bool:
        """A left click: True when it hit the slider (which then moved)."""
        if not self.active:
            return False
        i = slider_hit(x_px, y_px, len(self.names), self.viewer.width_px, self.viewer.height_px)
        if i is None:
            return False
        self.set_index(i)
        return True

    # -- state ---------------------------------------------------------------------------------------
    def set_index(self, i: int) -> None:
        i = int(min(max(i, 0), len(self.names) - 1))
        if i == self.index:
            return
        self.index = i
        v = self.viewer
        view = self.base.with_epoch(self.names[i])
        old = v.engine
        try:
            v.engine = view.engine(
                threshold_px=v.threshold_px, background=True, cull=self.cull, async_loads=True
            )
        except TypeError:  # an engine without asynchronous loads
            v.engine = view.engine(threshold_px=v.threshold_px, background=True, cull=self.cull)
        if hasattr(old, "close"):
            old.close()
        self._views.append(view)
        while len(self._views) > 2:  # the frame on screen may still draw from the previous epoch's store
            self._views.pop(0).close()
        self._apply_overlay()

    def toggle_overlay(self) -> None:
        self.overlay_on = not self.overlay_on
        if self.overlay_on and self._overlays is None:
            from terralod.render.timelapse import series_overlays

            self._overlays = series_overlays(self.base, self.names, self.names[0], self.lod_m)
        self._apply_overlay()

    def _apply_overlay(self) -> None:
        st = self.viewer.settings
        if self._legend_settings is None:
            self._legend_settings = st.legend
        if self.overlay_on and self._overlays is not None:
            st.overlay = self._overlays[self.names[self.index]]
            st.legend = False
        else:
            st.overlay = None
            st.legend = self._legend_settings

    def grid(self, epoch: str | None) -> Any:
        """The elevation grid of ``epoch`` (cached; None when the store keeps none and its source is gone)."""
        if epoch not in self._grids:
            try:
                self._grids[epoch] = (
                    self.base.heightfield(epoch) if hasattr(self.base, "heightfield") else None
                )
            except Exception:  # noqa: BLE001 - no grid: the HUD simply shows no pick
                self._grids[epoch] = None
        return self._grids[epoch]

    def update_pick(self) -> None:
        """The ground under the cursor and the change there (since the first epoch)."""
        v = self.viewer
        self.picked, self.change_m = None, None
        if v._mouse is None:
            return
        hf = self.grid(self.epoch)
        if hf is None:
            return
        st = v.settings
        self.picked = pick_ground(v.eye, v.target, v.fov_y_deg, v.width_px, v.height_px, v._mouse[0],
                                  v._mouse[1], hf, st.z_exaggeration)  # fmt: skip
        if self.picked is not None and self.active:
            first = self.grid(self.names[0])
            if first is not None:
                r, c = hf.sample_rc(self.picked[0], self.picked[1])
                ri, ci = int(round(float(r))), int(round(float(c)))
                self.change_m = float(hf.elevation_m[ri, ci]) - float(first.elevation_m[ri, ci])

    # -- drawing -------------------------------------------------------------------------------------
    def hud_lines(self) -> list[str]:
        out = []
        if self.active:
            out.append(f"epoch {format_date(self.epoch)}  ({self.index + 1} of {len(self.names)})"
                       f"   change overlay {'on' if self.overlay_on else 'off'} (C)")  # fmt: skip
        if self.picked is not None:
            line = f"under cursor: elevation {self.picked[2]:,.1f} m"
            if self.change_m is not None:
                line += f", change {self.change_m:+,.1f} m since {format_date(self.names[0])}"
            out.append(line)
        return out

    def draw(self, hud: Any, legend_hud: Any) -> None:
        """The slider and (overlay on) the change legend, through two of the viewer's HUD blitters."""
        v = self.viewer
        if not self.active:
            return
        x0, y0, _, _ = slider_geometry(v.width_px, v.height_px)
        hud.blit(slider_image(self.names, self.index, v.width_px, v.height_px, self.overlay_on), x0, y0,
                 v.width_px, v.height_px)  # fmt: skip
        ov = v.settings.overlay
        if ov is not None:
            leg = np.asarray(legend_image(ov, 0.9))
            lh, lw = leg.shape[:2]
            legend_hud.blit(leg, v.width_px - lw - 8, 8, v.width_px, v.height_px)

    def close(self) -> None:
        for t in self._views:
            t.close()
        self._views = []
