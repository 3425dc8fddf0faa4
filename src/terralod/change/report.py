"""One self-contained HTML report of a terrain change, for people who are not terrain experts.

Contents, top to bottom: a plain-language summary (every figure with its ± at the confidence level),
the difference map (diverging colours, blue = the ground rose, red = it dropped, grey = within the level
of detection, a legend in metres, the largest rise and drop marked), the before/after 3D views (rendered
by :class:`terralod.render.offscreen.FrameRenderer` from small tile stores of the two DEMs), a profile
across the largest change, the histogram of the difference, the volume against time (for a series), the
zone budgets, and the technical table (σ and where it came from, the co-registration, the error model).

The figures are matplotlib PNGs embedded as base64 data URIs; the page loads nothing from anywhere, so it
opens offline. :func:`figures` returns the PNG bytes too (the CLI writes them beside the report).
"""

from __future__ import annotations

import base64
import datetime as _dt
import html
import io
import logging
import math
import tempfile
from pathlib import Path

import numpy as np

from terralod.change.volumes import ChangeResult
from terralod.heightfield import Heightfield

log = logging.getLogger(__name__)

#: An Olympic swimming pool, 50 m x 25 m x 2 m, cubic metres.
OLYMPIC_POOL_M3 = 2500.0
#: A football (soccer) pitch, 105 m x 68 m, square metres.
FOOTBALL_PITCH_M2 = 7140.0
#: One storey of a building, metres.
STOREY_M = 3.0
GAIN_COLOUR, LOSS_COLOUR = "#2166ac", "#b2182b"


# -- words ---------------------------------------------------------------------------------------------
def nice_date(iso: str | None) -> str | None:
    if not iso:
        return None
    try:
        d = _dt.date.fromisoformat(str(iso)[:10])
    except ValueError:
        return str(iso)
    return f"{d.day} {d.strftime('%b')} {d.year}"


def volume_words(v_m3: float) -> str:
    """'99.0 million m³', '350,000 m³', '1.2 billion m³'."""
    a = abs(v_m3)
    if a >= 1e9:
        return f"{v_m3 / 1e9:.2f} billion m³"
    if a >= 1e6:
        return f"{v_m3 / 1e6:.1f} million m³"
    if a >= 1e4:
        return f"{v_m3:,.0f} m³"
    return f"{v_m3:,.1f} m³"


def pm_volume(v_m3: float, u_m3: float) -> str:
    """'99.0 ± 2.8 million m³' in one unit."""
    a = max(abs(v_m3), abs(u_m3))
    for scale, word, nd, at in (
        (1e9, "billion m³", 2, 1e9),
        (1e6, "million m³", 1, 1e6),
        (1e6, "million m³", 2, 1e5),
    ):
        if a >= at:
            return f"{v_m3 / scale:.{nd}f} ± {u_m3 / scale:.{nd}f} {word}"
    return f"{v_m3:,.0f} ± {u_m3:,.0f} m³"


def area_words(a_m2: float) -> str:
    return f"{a_m2 / 1e6:.2f} km²" if a_m2 >= 1e5 else f"{a_m2:,.0f} m²"


def _count(n: float) -> str:
    if n >= 100:
        return f"{round(n, -int(math.floor(math.log10(n))) + 1):,.0f}"
    return f"{n:.1f}" if n < 10 else f"{n:.0f}"


def plain_summary(result: ChangeResult, dates: tuple[str | None, str | None]) -> list[str]:
    """Sentences a layperson understands, each figure with its ± (the confidence level's)."""
    s = result.summary
    unc = result.uncertainty
    d0, d1 = nice_date(dates[0]), nice_date(dates[1])
    when = f"Between {d0} and {d1}" if d0 and d1 else "Between the two surveys"
    conf = f"{100 * unc.confidence:.0f} %"
    lod = unc.level_of_detection_m
    net, net_u = s["net_m3"], s["net_uncertainty_m3"]
    gain, gain_u = s["gain_m3_above_lod"], s["gain_above_lod_uncertainty_m3"]
    loss, loss_u = s["loss_m3_above_lod"], s["loss_above_lod_uncertainty_m3"]
    out = []
    if s["area_gain_m2"] == 0 and s["area_loss_m2"] == 0:
        out.append(
            f"{when} the ground did not change measurably: no part of the map rose or dropped by more than "
            f"{lod:.1f} m (the largest differences are +{s['max_rise_m']:.1f} m and -{s['max_drop_m']:.1f} m)."
        )
    elif gain >= loss:
        out.append(
            f"{when} about {pm_volume(gain, gain_u)} of material (rock, ice, soil) was added to the ground "
            f"surface — as much as {_count(gain / OLYMPIC_POOL_M3)} Olympic swimming pools — over "
            f"{area_words(s['area_gain_m2'])} (about {_count(s['area_gain_m2'] / FOOTBALL_PITCH_M2)} football "
            f"pitches); the ground rose by up to {s['max_rise_m']:.1f} ± {lod:.1f} m, the height of a "
            f"{max(1, round(s['max_rise_m'] / STOREY_M))}-storey building."
        )
        if loss > 0:
            out.append(
                f"Elsewhere about {pm_volume(loss, loss_u)} was removed, over {area_words(s['area_loss_m2'])}; "
                f"the ground dropped by up to {s['max_drop_m']:.1f} ± {lod:.1f} m."
            )
    else:
        out.append(
            f"{when} about {pm_volume(loss, loss_u)} of material (rock, ice, soil) was removed from the ground "
            f"surface — as much as {_count(loss / OLYMPIC_POOL_M3)} Olympic swimming pools — over "
            f"{area_words(s['area_loss_m2'])}; the ground dropped by up to {s['max_drop_m']:.1f} ± {lod:.1f} m."
        )
        if gain > 0:
            out.append(
                f"Elsewhere about {pm_volume(gain, gain_u)} was added, over {area_words(s['area_gain_m2'])}; "
                f"the ground rose by up to {s['max_rise_m']:.1f} ± {lod:.1f} m."
            )
    out.append(
        f"Counting every part of the map, the net change is {pm_volume(net, net_u)} "
        + (
            "(too small to tell from zero)."
            if abs(net) <= net_u
            else f"({'more' if net > 0 else 'less'} material than before)."
        )
    )
    steeper, lod_flat = "", lod
    if unc.model is not None and unc.model.sigma_given_m is None and unc.model.contrast is not None:
        thr, st, fl = unc.model.contrast
        if st > 1.3 * fl:
            steeper = f" on flat ground (about {unc.t * st:.1f} m on slopes over {thr:.0f}°)"
            lod_flat = unc.t * fl
    out.append(
        f"Changes smaller than {lod_flat:.1f} m up or down{steeper} cannot be told apart from survey error and are "
        f"shown in grey; each ± is the range that holds the true value with {conf} confidence."
    )
    src = unc.sigma_source
    if src.startswith("assumed"):
        out.append(
            f"Caution: the survey error could not be measured from these files, so {unc.sigma_m:g} m was "
            "assumed; give the surveys' own accuracy with --sigma-m for a firmer figure."
        )
    elif src.startswith("given"):
        out.append(f"The survey error ({unc.sigma_m:g} m per point) was given by the user.")
    else:
        out.append(
            f"The survey error ({unc.sigma_m:.2f} m per point) was measured on ground that did not change."
        )
    sh = s["shift_m"]
    co = s.get("coregistration", {})
    if co.get("mode") == "bias only":
        out.append(co.get("statement", ""))
    elif any(abs(v) > 0 for v in sh):
        out.append(
            f"The later survey was first lined up with the earlier one on unchanged ground: moved "
            f"{abs(sh[0]):.2f} m {'east' if sh[0] >= 0 else 'west'}, {abs(sh[1]):.2f} m "
            f"{'north' if sh[1] >= 0 else 'south'} and {abs(sh[2]):.2f} m {'up' if sh[2] >= 0 else 'down'}."
        )
    desc = s.get("stable_ground", {}).get("description")
    if desc and co.get("mode") == "bias only":
        out.append(f"The height difference was {desc}.")
    elif desc and co.get("mode") == "shift and bias":
        out.append(f"The alignment was {desc}.")
    elif co.get("statement"):
        out.append(co["statement"])
    for st in s.get("uncertainty", {}).get("statements", []):
        if not src.startswith("assumed") or "could not be measured from these files" not in st:
            out.append(st[0].upper() + st[1:] + ("" if st.endswith(".") else "."))
    return [o for o in out if o]


# -- figures -------------------------------------------------------------------------------------------
def _png(fig) -> bytes:
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    # zlib level 3, not PIL's 6: the same pixels, files some 13 % larger, written in about half the time
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight", pil_kwargs={"compress_level": 3})
    plt.close(fig)
    return buf.getvalue()


def _km_extent(hf: Heightfield):
    w, s, e, n = hf.bounds_m
    return (0.0, (e - w) / 1e3, 0.0, (n - s) / 1e3)


def _to_km(hf: Heightfield, row: float, col: float) -> tuple[float, float]:
    x, y = hf.world_xy(row, col)
    w, s, _, _ = hf.bounds_m
    return (float(x) - w) / 1e3, (float(y) - s) / 1e3


def profile_line(result: ChangeResult) -> tuple[np.ndarray, np.ndarray]:
    """(rows, cols) of a straight line across the largest change: through the cell of largest |change|,
    along the long axis of the connected change (beyond the LoD) that holds it, extended by a third of its
    length on both sides and clipped to the grid; 400 samples."""
    from scipy import ndimage

    dod = result.dod
    lod = result.uncertainty.level_of_detection_m
    h, w = dod.shape
    a = np.abs(np.nan_to_num(dod))
    r0, c0 = np.unravel_index(int(np.argmax(a)), a.shape)
    lab, _ = ndimage.label(a > lod)
    comp = lab == lab[r0, c0] if lab[r0, c0] else np.zeros_like(lab, bool)
    rr, cc = np.nonzero(comp)
    if rr.size >= 3:
        cov = np.cov(np.vstack([rr, cc]).astype(np.float64))
        evals, evecs = np.linalg.eigh(cov)
        v = evecs[:, int(np.argmax(evals))]
        proj = (rr - r0) * v[0] + (cc - c0) * v[1]
        lo, hi = float(proj.min()), float(proj.max())
    else:
        v, lo, hi = np.array([0.0, 1.0]), -10.0, 10.0
    ext = max(hi - lo, 10.0) / 3.0
    t = np.linspace(lo - ext, hi + ext, 400)
    rows, cols = r0 + t * v[0], c0 + t * v[1]
    keep = (rows >= 0) & (rows <= h - 1) & (cols >= 0) & (cols <= w - 1)
    return rows[keep], cols[keep]


def figure_map(result: ChangeResult, line=None) -> bytes:
    import matplotlib.pyplot as plt
    from matplotlib.colors import LightSource, TwoSlopeNorm

    hf = result.pair.before
    dod = result.dod
    lod = result.uncertainty.level_of_detection_m
    ext = _km_extent(hf)
    dx, dy = hf.spacing_m
    shade = LightSource(azdeg=315, altdeg=45).hillshade(hf.elevation_m.astype(np.float64), dx=dx, dy=dy)
    fin = dod[np.isfinite(dod)]
    hi = max(float(np.percentile(fin[fin > 0], 99.5)) if (fin > 0).any() else 0.0, 2 * lod, 0.1)
    lo = max(float(-np.percentile(fin[fin < 0], 0.5)) if (fin < 0).any() else 0.0, 2 * lod, 0.1)
    norm = TwoSlopeNorm(vmin=-lo, vcenter=0.0, vmax=hi)
    shown = np.ma.masked_where(~np.isfinite(dod) | (np.abs(dod) <= lod), dod)
    aspect = hf.width / hf.height
    fig, ax = plt.subplots(figsize=(min(11, 3 + 6.5 * aspect), 7.5))
    ax.imshow(shade, cmap="gray", vmin=-0.3, vmax=1.3, extent=ext, origin="upper", interpolation="nearest")
    nodata = np.ma.masked_where(np.isfinite(dod), np.ones_like(dod))
    ax.imshow(nodata, cmap="Greys", vmin=0, vmax=1, extent=ext, origin="upper", interpolation="nearest")
    grey = np.ma.masked_where(~(np.isfinite(dod) & (np.abs(dod) <= lod)), np.ones_like(dod))
    ax.imshow(grey, cmap="Greys", vmin=0, vmax=3, alpha=0.35, extent=ext, origin="upper")
    im = ax.imshow(
        shown, cmap="RdBu", norm=norm, extent=ext, origin="upper", interpolation="nearest", alpha=0.9
    )
    # the scale tops out at the 99.5th percentiles: beyond them the colour stays full, and the bar says so
    beyond_hi = bool(fin.size) and float(fin.max()) > hi
    beyond_lo = bool(fin.size) and float(fin.min()) < -lo
    extend = {(True, True): "both", (True, False): "max", (False, True): "min"}.get(
        (beyond_hi, beyond_lo), "neither"
    )
    cb = fig.colorbar(im, ax=ax, shrink=0.85, pad=0.02, extend=extend)
    cb.set_label("change in ground height (m)\nblue: the ground rose · red: it dropped")
    ticks = [-lo, -lo / 2, 0.0, hi / 4, hi / 2, 3 * hi / 4, hi]
    cb.set_ticks(ticks)
    labels = ["0" if v == 0 else (f"{v:+.0f}" if max(hi, lo) >= 20 else f"{v:+.1f}") for v in ticks]
    if beyond_hi:
        labels[-1] += " or more"
    if beyond_lo:
        labels[0] += " or less"
    cb.set_ticklabels(labels)
    cb.ax.axhspan(-lod, lod, color="0.6")
    from matplotlib.patches import Patch

    handles = [Patch(facecolor="0.75", edgecolor="0.5", label=f"within ±{lod:.1f} m: no measurable change")]
    if not np.isfinite(dod).all():
        handles.append(Patch(facecolor="black", label="no data in one of the surveys"))
    ext_d = result.summary["extremes"]
    for key, mark, _col, label in (("max_rise", "^", GAIN_COLOUR, "largest rise"),
                                  ("max_drop", "v", LOSS_COLOUR, "largest drop")):  # fmt: skip
        e = ext_d.get(key)
        if e and abs(e["value_m"]) > 0:
            w_m, s_m, _, _ = hf.bounds_m  # the position in metres: the map may be a decimated copy
            x, y = (e["x_m"] - w_m) / 1e3, (e["y_m"] - s_m) / 1e3
            ax.plot(x, y, mark, ms=11, mfc="yellow", mec="k", mew=1.2)
            handles.append(
                plt.Line2D(
                    [],
                    [],
                    ls="",
                    marker=mark,
                    ms=9,
                    mfc="yellow",
                    mec="k",
                    label=f"{label} ({e['value_m']:+.1f} m)",
                )
            )
            ax.annotate(f"{label}\n{e['value_m']:+.1f} m", (x, y), xytext=(8, 8), textcoords="offset points",
                        fontsize=9, bbox={"boxstyle": "round", "fc": "white", "alpha": 0.8})  # fmt: skip
    if line is not None and len(line[0]) > 1:
        xs, ys = zip(
            *(_to_km(hf, r, c) for r, c in zip(line[0][[0, -1]], line[1][[0, -1]], strict=True)), strict=True
        )
        ax.plot(xs, ys, "k--", lw=1.5)
        ax.text(xs[0], ys[0], " A", fontsize=11, weight="bold")
        ax.text(xs[1], ys[1], " B", fontsize=11, weight="bold")
    ax.legend(handles=handles, loc="upper right", fontsize=8, framealpha=0.9)
    ax.set_xlabel("km east")
    ax.set_ylabel("km north")
    ax.set_title("Where the ground changed")
    ax.annotate("N ↑", xy=(0.02, 0.96), xycoords="axes fraction", fontsize=11, weight="bold",
                bbox={"fc": "white", "alpha": 0.7})  # fmt: skip
    return _png(fig)


def figure_histogram(result: ChangeResult) -> bytes:
    import matplotlib.pyplot as plt

    d = result.dod[np.isfinite(result.dod)]
    lod = result.uncertainty.level_of_detection_m
    fig, ax = plt.subplots(figsize=(8, 3.6))
    bins = np.linspace(float(d.min()), float(d.max()) + 1e-9, 120)
    n, edges, patches = ax.hist(d, bins=bins, color="0.5", log=True)
    for p, left in zip(patches, edges[:-1], strict=True):
        if left >= lod:
            p.set_facecolor(GAIN_COLOUR)
        elif left + (edges[1] - edges[0]) <= -lod:
            p.set_facecolor(LOSS_COLOUR)
    ax.axvspan(-lod, lod, color="0.85", zorder=0, label=f"within ±{lod:.1f} m (no measurable change)")
    ax.set_xlabel("change in ground height (m)")
    ax.set_ylabel("number of map cells (log scale)")
    ax.set_title("How much the ground changed, cell by cell")
    ax.legend(loc="upper right", fontsize=8)
    return _png(fig)


def figure_profile(result: ChangeResult, line) -> bytes:
    import matplotlib.pyplot as plt
    from scipy import ndimage

    hf = result.pair.before
    rows, cols = line
    coords = np.stack([rows, cols])
    zb = ndimage.map_coordinates(hf.elevation_m.astype(np.float64), coords, order=1)
    after = result.dod + hf.elevation_m
    za = ndimage.map_coordinates(np.nan_to_num(after, nan=np.nan), coords, order=1, cval=np.nan)
    dx, dy = hf.spacing_m
    dist = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(rows) * dy, np.diff(cols) * dx))])
    lod = result.uncertainty.level_of_detection_m
    fig, ax = plt.subplots(figsize=(8, 3.8))
    ax.plot(
        dist,
        zb,
        color="0.35",
        lw=1.5,
        label=f"before ({nice_date(result.summary['before'].get('date')) or 'BEFORE'})",
    )
    ax.plot(
        dist,
        za,
        color="k",
        lw=1.5,
        label=f"after ({nice_date(result.summary['after'].get('date')) or 'AFTER'})",
    )
    ax.fill_between(dist, zb, za, where=(za - zb) > lod, color=GAIN_COLOUR, alpha=0.5, label="ground rose")
    ax.fill_between(
        dist, zb, za, where=(za - zb) < -lod, color=LOSS_COLOUR, alpha=0.5, label="ground dropped"
    )
    ax.set_xlabel("distance along the line A → B on the map (m)")
    ax.set_ylabel("elevation (m)")
    ax.set_title("Profile across the largest change (same scale for both surveys)")
    ax.text(0, 0.02, "A", transform=ax.transAxes, weight="bold")
    ax.text(0.98, 0.02, "B", transform=ax.transAxes, weight="bold")
    ax.legend(fontsize=8, loc="best")
    return _png(fig)


def figure_series(series: list[dict]) -> bytes:
    import matplotlib.dates as mdates
    import matplotlib.pyplot as plt

    t = [_dt.date.fromisoformat(str(r["date"])[:10]) for r in series]
    net = np.array([r["net_m3"] for r in series]) / 1e6
    net_u = np.array([r["net_uncertainty_m3"] for r in series]) / 1e6
    gain = np.array([r["gain_m3_above_lod"] for r in series]) / 1e6
    loss = np.array([r["loss_m3_above_lod"] for r in series]) / 1e6
    fig, ax = plt.subplots(figsize=(8, 3.8))
    # surveys far apart (> 4x the median interval) are joined by a dotted line: nothing is known between
    days = np.array([(b - a).days for a, b in zip(t, t[1:], strict=False)], np.float64)
    gap = days > 4 * np.median(days) if days.size > 2 else np.zeros(days.size, bool)
    runs, start = [], 0
    for i, g in enumerate(gap):
        if g:
            runs.append((start, i + 1))
            start = i + 1
    runs.append((start, len(t)))
    for k, (a, b) in enumerate(runs):
        sl = slice(a, b)
        first = k == 0
        ax.fill_between(
            t[sl], (net - net_u)[sl], (net + net_u)[sl], color="0.8", label="net, ± range" if first else None
        )
        ax.plot(t[sl], net[sl], "k-o", ms=3, label="net change" if first else None)
        ax.plot(t[sl], gain[sl], "-", color=GAIN_COLOUR, label="added" if first else None)
        ax.plot(
            t[sl], -loss[sl], "-", color=LOSS_COLOUR, label="removed (shown below zero)" if first else None
        )
    for i in np.nonzero(gap)[0]:
        ax.plot(
            t[i : i + 2],
            net[i : i + 2],
            ":",
            color="0.4",
            label="no survey in between" if i == np.nonzero(gap)[0][0] else None,
        )
    ax.axhline(0, color="0.5", lw=0.8)
    ax.set_ylabel("volume since the first survey\n(million m³)")
    ax.set_title("Volume against time")
    ax.xaxis.set_major_formatter(mdates.DateFormatter("%b %Y"))
    ax.legend(fontsize=8, loc="upper left")
    fig.autofmt_xdate()
    return _png(fig)


def render_views(result: ChangeResult, width_px: int = 560, height_px: int = 380) -> list[tuple[str, bytes]]:
    """Before/after 3D views of small tile stores built from the two DEMs (AFTER co-registered, on BEFORE's
    grid), one camera aimed at the largest change. Raises when no OpenGL context can be made."""
    from PIL import Image

    import terralod
    from terralod.pyramid.builder import build_store
    from terralod.render import RenderSettings
    from terralod.render.offscreen import FrameRenderer

    hf = result.pair.before
    after = result.dod + hf.elevation_m
    ok = np.isfinite(after)
    a_hf = Heightfield(np.where(ok, after, hf.elevation_m).astype(np.float32), ok & hf.valid, hf.transform,
                       crs=hf.crs, source="after (co-registered)")  # fmt: skip
    zlo = float(min(np.nanmin(hf.elevation_m), np.nanmin(after)))
    zhi = float(max(np.nanmax(hf.elevation_m), np.nanmax(after)))
    pose = _view_pose(result, zlo, zhi)
    out = []
    with tempfile.TemporaryDirectory(prefix="terralod-change-") as tmp:
        for label, h in (("before", hf), ("after", a_hf)):
            path = Path(tmp) / f"{label}.terra"
            build_store(h, path, method="chunked", tile_size=33, workers=1)
            ter = terralod.open(path)
            try:
                fr = FrameRenderer(ter, width_px, height_px, threshold_px=1.0,
                                   settings=RenderSettings(height_range_m=(zlo, zhi), fog=False))  # fmt: skip
            except BaseException:
                ter.close()
                raise
            img = fr.frame(pose)
            fr.close()
            ter.close()
            buf = io.BytesIO()
            Image.fromarray(img).save(buf, format="PNG")
            out.append((label, buf.getvalue()))
    return out


def _view_pose(result: ChangeResult, zlo: float, zhi: float):
    """Camera looking at the largest change from the terrain's low side, 45° above the horizon."""
    from terralod.render.offscreen import CameraPose

    hf = result.pair.before
    h, w = hf.shape
    a = np.abs(np.nan_to_num(result.dod))
    r0, c0 = np.unravel_index(int(np.argmax(a)), a.shape)
    edge = np.zeros(hf.shape, bool)
    edge[0, :] = edge[-1, :] = edge[:, 0] = edge[:, -1] = True
    z = hf.elevation_m
    thr = np.percentile(z[edge], 20)
    er, ec = np.nonzero(edge & (z <= thr))
    vr, vc = er.mean() - r0, ec.mean() - c0
    dx, dy = hf.spacing_m
    vx, vy = vc * dx, -vr * dy
    nrm = math.hypot(vx, vy) or 1.0
    vx, vy = vx / nrm, vy / nrm
    tx, ty = hf.world_xy(r0, c0)
    tz = float(z[r0, c0])
    span = math.hypot(w * dx, h * dy)
    r = 0.75 * span
    el = math.radians(45.0)
    eye = (float(tx) + r * vx * math.cos(el), float(ty) + r * vy * math.cos(el), tz + r * math.sin(el))
    return CameraPose(eye, (float(tx), float(ty), tz))


def figures(result: ChangeResult, series: list[dict] | None = None, views: bool = True) -> dict[str, bytes]:
    """Every figure of the report as PNG bytes, by name."""
    lod = result.uncertainty.level_of_detection_m
    changed = bool(np.any(np.abs(np.nan_to_num(result.dod)) > lod))
    line = profile_line(result) if changed else None
    out = {"map": figure_map(result, line), "histogram": figure_histogram(result)}
    if line is not None and len(line[0]) > 1:
        out["profile"] = figure_profile(result, line)
    if series:
        out["series"] = figure_series(series)
    if views:
        try:
            for label, png in render_views(result):
                out[f"view_{label}"] = png
        except Exception as exc:  # noqa: BLE001 - no OpenGL context here: the report goes on without views
            note = f"3D views left out: {type(exc).__name__}: {exc}"
            log.warning(note)
            result.summary.setdefault("report_notes", []).append(note)
    return out


# -- page ----------------------------------------------------------------------------------------------
_CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,Roboto,sans-serif;max-width:1100px;margin:2em auto;padding:0 1em;
color:#222;line-height:1.45}
h1{font-size:1.6em;margin-bottom:.2em} h2{font-size:1.2em;margin-top:1.8em;border-bottom:1px solid #ddd}
.summary{background:#f4f7fb;border-left:5px solid #2166ac;padding:.8em 1.2em;font-size:1.08em}
.summary p{margin:.5em 0} img{max-width:100%} .views{display:flex;gap:1em;flex-wrap:wrap}
.views figure{margin:0;flex:1 1 300px} figcaption{font-size:.9em;color:#555}
table{border-collapse:collapse;font-size:.9em} td,th{border:1px solid #ccc;padding:.25em .6em;text-align:right}
td:first-child,th:first-child{text-align:left} .small{font-size:.85em;color:#555} code{font-size:.95em}
"""


def _img(png: bytes, alt: str) -> str:
    return f'<img alt="{html.escape(alt)}" src="data:image/png;base64,{base64.b64encode(png).decode()}">'


def _fmt(v) -> str:
    if isinstance(v, float):
        return f"{v:,.3f}" if abs(v) < 1e4 else f"{v:,.0f}"
    return html.escape(str(v))


def build_html(result: ChangeResult, figs: dict[str, bytes], series: list[dict] | None = None,
               title: str | None = None) -> str:  # fmt: skip
    s = result.summary
    dates = (s["before"].get("date"), s["after"].get("date"))
    d0, d1 = nice_date(dates[0]), nice_date(dates[1])
    title = title or (f"Terrain change {d0} → {d1}" if d0 and d1 else "Terrain change")
    parts = [
        "<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'>",
        f"<title>{html.escape(title)}</title><style>{_CSS}</style></head><body>",
        f"<h1>{html.escape(title)}</h1>",
        f"<p class='small'>BEFORE: <code>{html.escape(str(s['before']['source']))}</code> · AFTER: "
        f"<code>{html.escape(str(s['after']['source']))}</code></p>",
        "<div class='summary'>"
        + "".join(f"<p>{html.escape(t)}</p>" for t in plain_summary(result, dates))
        + "</div>",
        "<h2>Where the ground changed</h2>",
        _img(figs["map"], "map of the change in ground height"),
        "<p class='small'>Coloured cells changed by more than the level of detection; grey-shaded cells did "
        "not change measurably. The dashed line A–B is the profile below.</p>",
    ]
    if "view_before" in figs and "view_after" in figs:
        parts += [
            "<h2>Before and after in 3D</h2><div class='views'>",
            f"<figure>{_img(figs['view_before'], 'before')}<figcaption>Before ({html.escape(d0 or 'BEFORE')})"
            "</figcaption></figure>",
            f"<figure>{_img(figs['view_after'], 'after')}<figcaption>After ({html.escape(d1 or 'AFTER')}), "
            "same camera, same colours for the same heights</figcaption></figure></div>",
        ]
    if "profile" in figs:
        parts += ["<h2>Profile across the largest change</h2>", _img(figs["profile"], "profile")]
    parts += ["<h2>How much the ground changed, cell by cell</h2>", _img(figs["histogram"], "histogram")]
    if "series" in figs and series:
        parts += [
            "<h2>Volume against time</h2>",
            _img(figs["series"], "volume against time"),
            _series_table(series),
        ]
    if s.get("zones"):
        parts += ["<h2>Zones</h2>", _zones_table(s["zones"])]
    parts += ["<h2>Technical details</h2>", _tech_table(result)]
    parts += ["</body></html>"]
    return "\n".join(parts)


def _series_table(series: list[dict]) -> str:
    rows = "".join(
        f"<tr><td>{html.escape(nice_date(r['date']) or '')}</td><td>{r['gain_m3_above_lod'] / 1e6:.2f}</td>"
        f"<td>{r['loss_m3_above_lod'] / 1e6:.2f}</td><td>{r['net_m3'] / 1e6:.2f} ± "
        f"{r['net_uncertainty_m3'] / 1e6:.2f}</td><td>{r['max_rise_m']:.1f}</td></tr>"
        for r in series
    )
    return (
        "<table><tr><th>survey</th><th>added, million m³</th><th>removed, million m³</th>"
        f"<th>net, million m³</th><th>largest rise, m</th></tr>{rows}</table>"
    )


def _zones_table(zones: list[dict]) -> str:
    rows = "".join(
        f"<tr><td>{html.escape(z['name'])}</td><td>{pm_volume(z['gain_m3_above_lod'], z['gain_above_lod_uncertainty_m3'])}</td>"
        f"<td>{pm_volume(z['loss_m3_above_lod'], z['loss_above_lod_uncertainty_m3'])}</td>"
        f"<td>{pm_volume(z['net_m3'], z['net_uncertainty_m3'])}</td><td>{area_words(z['area_m2'])}</td>"
        f"<td>{html.escape(z.get('note', ''))}</td></tr>"
        for z in zones
    )
    return (
        "<table><tr><th>zone</th><th>added</th><th>removed</th><th>net</th><th>area</th><th>note</th></tr>"
        f"{rows}</table>"
    )


def _tech_table(result: ChangeResult) -> str:
    s = result.summary
    u = s["uncertainty"]
    c = s["coregistration"]
    items = [
        ("σ of the difference (m)", s["sigma_m"]),
        ("σ from", s["sigma_source"]),
        ("level of detection (m)", f"{s['level_of_detection_m']:.3f} (t = {u['t']:.3f}, {100 * u['confidence']:.0f} %)"),
        ("gain / loss / net, all cells (m³)", f"{s['gain_m3']:,.0f} / {s['loss_m3']:,.0f} / {s['net_m3']:,.0f}"),
        ("gain / loss / net beyond the LoD (m³)",
         f"{s['gain_m3_above_lod']:,.0f} / {s['loss_m3_above_lod']:,.0f} / {s['net_m3_above_lod']:,.0f}"),
        ("± net, all cells (m³)", s["net_uncertainty_m3"]),
        ("area beyond the LoD, gain / loss (m²)", f"{s['area_gain_m2']:,.0f} / {s['area_loss_m2']:,.0f}"),
        ("error model", u["propagation"]),
        ("correlation range (m)", f"{u['variogram']['range_m']:.1f} ({u['variogram']['range_source']})"),
        ("co-registration", f"{c['method']} ({c.get('mode', '')}); shift applied to AFTER [dx, dy, dz] = "
         + ", ".join(f"{v:.3f}" for v in s["shift_m"]) + " m"),
        ("what the fit used", s.get("fit_description", "")),
        ("stable ground (cells; sloping part used for the shift)",
         f"{s.get('stable_ground', {}).get('cells', 0):,}; {s.get('stable_ground', {}).get('fit_cells', 0):,} "
         f"above {s.get('stable_ground', {}).get('slope_min_deg', 0):g}°"),
        ("shift standard error (cells) / vertical bias σ (m)",
         f"{c.get('shift_se_cells')} / {c.get('bias_sigma_m')}"),
        ("resampling's own error, NMAD (m)", u.get("resampling_nmad_m")),
        ("NMAD on stable ground before / after co-registration (m)", f"{c['nmad_before_m']} / {c['nmad_after_m']}"),
        ("grid", f"{s['grid']['crs']}, {s['grid']['spacing_m'][0]:g} × {s['grid']['spacing_m'][1]:g} m, "
         f"{s['grid']['shape'][1]} × {s['grid']['shape'][0]} cells"),
    ]  # fmt: skip
    items += [("alignment", n) for n in s["alignment_notes"]]
    items += [("co-registration note", n) for n in c["notes"]]
    items += [("warning", w) for w in u["warnings"]]
    items += [("report note", n) for n in s.get("report_notes", [])]
    rows = "".join(
        f"<tr><td>{html.escape(k)}</td><td style='text-align:left'>{_fmt(v)}</td></tr>" for k, v in items
    )
    return f"<table>{rows}</table>"


def write_report(result: ChangeResult, path: str | Path, *, series: list[dict] | None = None,
                 views: bool = True, figures_dir: str | Path | None = None) -> dict[str, bytes]:  # fmt: skip
    """Write the self-contained HTML report to ``path`` (and each PNG to ``figures_dir`` when given)."""
    figs = figures(result, series, views=views)
    Path(path).write_text(build_html(result, figs, series), encoding="utf-8")
    if figures_dir is not None:
        d = Path(figures_dir)
        d.mkdir(parents=True, exist_ok=True)
        for name, png in figs.items():
            (d / f"{name}.png").write_bytes(png)
    return figs
