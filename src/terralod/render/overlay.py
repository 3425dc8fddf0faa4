"""The change overlay and the captions drawn on frames for non-experts.

:class:`ChangeOverlay` is the elevation change of one epoch relative to another on the store's grid
(metres, ``after - before``). The renderer samples it per fragment from a float texture laid over the
terrain (``shaders/terrain.frag``, ``u_overlay``): gain (material added, ground rose) in blues, loss
(material removed, ground dropped) in reds, stronger with the size of the change up to ``max_m``, and every
cell whose change is below the level of detection ``lod_m`` drawn in the terrain's grey (no significant
change) — the geomorphic change detection convention (GCD: blue deposition, red erosion, the minimum
level of detection masked). The colours are defined once here and passed to the shader as uniforms, so
the legend drawn by :func:`legend_image` shows exactly the colours on screen.

:func:`annotate` burns the date (e.g. "25 Sep 2000") and the legend into a frame (offscreen renders and
the time-lapse); the window viewer draws the same legend image as an overlay quad.
"""

from __future__ import annotations

import datetime
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

#: Colours at the level of detection (light) and at ``max_m`` (dark), RGB 0..1.
GAIN_LIGHT = (0.66, 0.82, 0.96)
GAIN_DARK = (0.03, 0.19, 0.55)
LOSS_LIGHT = (0.99, 0.75, 0.62)
LOSS_DARK = (0.62, 0.02, 0.06)
#: Default level of detection, metres, when the change analysis gives none.
DEFAULT_LOD_M = 1.0


@dataclass(eq=False)
class ChangeOverlay:
    """Elevation change on a grid, drawn over the terrain.

    Attributes
    ----------
    change_m : (H, W) float32, ``after - before`` metres, NaN where either epoch has no data
    transform : affine.Affine of the grid (pixel corners; north-up)
    lod_m : level of detection: |change| below it is greyed out
    max_m : change (either sign) at which the colours saturate
    before, after : names of the epochs compared (for the legend)
    """

    change_m: np.ndarray
    transform: Any
    lod_m: float = DEFAULT_LOD_M
    max_m: float = 10.0
    before: str = ""
    after: str = ""
    key: int = field(default=0)

    def __post_init__(self) -> None:
        self.change_m = np.ascontiguousarray(self.change_m, np.float32)
        self.key = id(self.change_m)

    def at(self, x_m: float, y_m: float) -> float:
        """Change at world (x, y), metres (nearest sample; NaN outside the grid or without data)."""
        t = self.transform
        col = math.floor((x_m - t.c) / t.a)
        row = math.floor((y_m - t.f) / t.e)
        h, w = self.change_m.shape
        if 0 <= row < h and 0 <= col < w:
            return float(self.change_m[row, col])
        return math.nan


def nice_max_m(values: list[float] | np.ndarray, lod_m: float) -> float:
    """A round colour-scale end (1, 1.5, 2, 2.5, 3, 4, 5, 6, 8 x 10^k metres) at or above the 99.5th
    percentile of |change|: the largest changes take the darkest colours."""
    v = np.abs(np.asarray(values, np.float64))
    v = v[np.isfinite(v)]
    top = float(np.percentile(v, 99.5)) if v.size else 0.0
    top = max(top, 2.0 * lod_m, 1e-3)
    k = 10 ** math.floor(math.log10(top))
    for m in (1, 1.5, 2, 2.5, 3, 4, 5, 6, 8, 10):
        if m * k >= top:
            return float(m * k)
    return float(10 * k)


def change_overlay(terrain: Any, after: str | None = None, before: str | None = None, *,
                   lod_m: float = DEFAULT_LOD_M, max_m: float | None = None) -> ChangeOverlay:  # fmt: skip
    """The change of epoch ``after`` (default: the terrain's) relative to ``before`` (default: the first
    epoch) of a grid terrain with epochs, from the elevation grids the store keeps."""
    from terralod.errors import InputError

    eps = list(getattr(terrain, "epochs", []))
    if len(eps) < 1 or not hasattr(terrain, "heightfield"):
        raise InputError(
            "has no epochs to compare (build with --epoch, then terralod update)", str(terrain.path)
        )
    after = after or terrain.epoch or eps[-1]
    before = before or eps[0]
    for e in (after, before):
        if e not in eps:
            raise InputError(f"has no epoch {e!r} (epochs: {', '.join(eps)})", str(terrain.path))
    a = terrain.heightfield(before)
    b = terrain.heightfield(after)
    d = b.elevation_m.astype(np.float32) - a.elevation_m.astype(np.float32)
    d[~(a.valid & b.valid)] = np.nan
    if max_m is None:
        sig = d[np.abs(d) >= lod_m]
        max_m = nice_max_m(sig, lod_m) if sig.size else nice_max_m([2 * lod_m], lod_m)
    return ChangeOverlay(d, a.transform, float(lod_m), float(max_m), before, after)


def change_colour(d_m: np.ndarray, lod_m: float, max_m: float) -> np.ndarray:
    """(..., 3) RGB 0..1 of changes ``d_m`` as the shader colours them (NaN where below the LoD: grey)."""
    d = np.asarray(d_m, np.float64)
    t = np.clip((np.abs(d) - lod_m) / max(max_m - lod_m, 1e-6), 0.0, 1.0)[..., None]
    gain = np.array(GAIN_LIGHT) * (1 - t) + np.array(GAIN_DARK) * t
    loss = np.array(LOSS_LIGHT) * (1 - t) + np.array(LOSS_DARK) * t
    out = np.where((d >= 0)[..., None], gain, loss)
    out[np.abs(d) < lod_m] = np.nan
    return out


def format_date(name: str | None) -> str:
    """ "2000-09-25" → "25 Sep 2000"; other epoch names as they are."""
    if not name:
        return ""
    try:
        d = datetime.date.fromisoformat(str(name)[:10])
    except ValueError:
        return str(name)
    return f"{d.day} {d.strftime('%b')} {d.year}"


def _font(size_px: int) -> Any:
    from PIL import ImageFont

    for name in ("DejaVuSans-Bold.ttf", "DejaVuSans.ttf", "LiberationSans-Bold.ttf"):
        try:
            return ImageFont.truetype(name, size_px)
        except OSError:
            continue
    try:
        return ImageFont.load_default(size=size_px)
    except TypeError:  # Pillow < 10.1
        return ImageFont.load_default()


def legend_image(overlay: ChangeOverlay, scale: float = 1.0) -> Any:
    """An RGBA legend (PIL image): the colour bar from -max to +max metres with the greyed LoD band,
    labelled in metres, with a one-line meaning for each colour."""
    from PIL import Image, ImageDraw

    s = max(scale, 0.5)
    w, bar_h = int(330 * s), int(14 * s)
    f = _font(int(12 * s))
    fb = _font(int(13 * s))
    h = int(106 * s)
    img = Image.new("RGBA", (w, h), (255, 255, 255, 215))
    dr = ImageDraw.Draw(img)
    title = "Ground change" + (f" since {format_date(overlay.before)}" if overlay.before else "")
    dr.text((int(8 * s), int(4 * s)), title, fill=(20, 20, 20, 255), font=fb)
    x0, x1, y0 = int(24 * s), w - int(24 * s), int(24 * s)
    vals = np.linspace(-overlay.max_m, overlay.max_m, x1 - x0)
    cols = change_colour(vals, overlay.lod_m, overlay.max_m)
    for i, c in enumerate(cols):
        rgb = (150, 150, 150) if np.isnan(c[0]) else tuple(int(255 * v) for v in c)
        dr.line([(x0 + i, y0), (x0 + i, y0 + bar_h)], fill=(*rgb, 255))
    dr.rectangle([x0, y0, x1, y0 + bar_h], outline=(60, 60, 60, 255))
    m = overlay.max_m
    ticks = [-m, -m / 2, 0.0, m / 2, m]
    for v in ticks:
        x = x0 + (v + m) / (2 * m) * (x1 - x0)
        dr.line([(x, y0 + bar_h), (x, y0 + bar_h + int(4 * s))], fill=(40, 40, 40, 255))
        label = f"{v:+.0f} m" if abs(v) >= 10 or v == 0 else f"{v:+.1f} m"
        if v == 0:
            label = "0"
        tw = dr.textlength(label, font=f)
        dr.text(
            (min(max(x - tw / 2, 1), w - tw - 1), y0 + bar_h + int(5 * s)),
            label,
            fill=(30, 30, 30, 255),
            font=f,
        )
    y = y0 + bar_h + int(22 * s)
    dr.text(
        (x0, y), "blue: ground rose / material added", fill=(*[int(255 * c) for c in GAIN_DARK], 255), font=f
    )
    dr.text((x0, y + int(13 * s)), "red: ground dropped / removed", fill=(*[int(255 * c) for c in LOSS_DARK], 255),
            font=f)  # fmt: skip
    dr.text((x0, y + int(26 * s)), f"grey: less than {overlay.lod_m:g} m (no clear change)", fill=(90, 90, 90, 255),
            font=f)  # fmt: skip
    return img


def annotate(img: np.ndarray, *, date: str | None = None, overlay: ChangeOverlay | None = None,
             subtitle: str | None = None) -> np.ndarray:  # fmt: skip
    """The frame with the date (top left, large) and the change legend (bottom right) burnt in."""
    from PIL import Image, ImageDraw

    h, w = img.shape[:2]
    im = Image.fromarray(img).convert("RGBA")
    s = max(min(w / 640.0, h / 360.0), 0.45)
    if date:
        f = _font(int(30 * s))
        fs = _font(int(14 * s))
        dr = ImageDraw.Draw(im)
        text = format_date(date)
        tw = dr.textlength(text, font=f)
        sub_w = dr.textlength(subtitle, font=fs) if subtitle else 0
        box = Image.new(
            "RGBA", (int(max(tw, sub_w) + 20 * s), int((46 + (18 if subtitle else 0)) * s)), (0, 0, 0, 140)
        )
        im.alpha_composite(box, (int(8 * s), int(8 * s)))
        dr = ImageDraw.Draw(im)
        dr.text((int(18 * s), int(12 * s)), text, fill=(255, 255, 255, 255), font=f)
        if subtitle:
            dr.text((int(18 * s), int(50 * s)), subtitle, fill=(230, 230, 230, 255), font=fs)
    if overlay is not None:
        leg = legend_image(overlay, 0.8 * s)
        if leg.width < w and leg.height < h:
            im.alpha_composite(leg, (w - leg.width - int(8 * s), h - leg.height - int(8 * s)))
    return np.asarray(im.convert("RGB")).copy()
