"""``terralod change`` over a region: BEFORE and AFTER read window by window, never whole.

Each side is a window source (:func:`terralod.io.windowed.open_source`: one raster, a mosaic of tiles on
one grid, a VRT; a geographic or Mercator region warped block by block to the in-memory reader's UTM
grid). The pair must share one grid (same CRS, transform and size), as two regions of the same tiles do;
pairs on different grids take the in-memory path (:func:`terralod.change.difference.align`).

The chain, and where it deviates from :func:`terralod.change.volumes.measure_change`:

1. **A bounded sample** (:func:`sample_pair`): at most :data:`SAMPLE_MAX_CELLS` cells of the pair, in
   windows of :data:`SAMPLE_WINDOW`² cells spread evenly over the grid, each read with
   :data:`SAMPLE_MARGIN` cells of margin (valid in AFTER, not in BEFORE: a shifted AFTER is sampled from
   real cells, never from a neighbouring window) and laid side by side on one composite grid. The
   co-registration (:func:`terralod.change.coregister.coregister`), the stable ground, σ, the variogram
   and the resampling error's statistics are those of the sample. A pair of at most
   :data:`SAMPLE_MAX_CELLS` cells is its own sample: then every figure is the in-memory chain's.
   Margins of 32 cells keep adjacent windows' cores 65 cells apart, beyond the variogram's longest lag (64).
2. **The stream** (:func:`stream_change`): windows of :data:`WINDOW`² cells of BEFORE's grid, each with
   its AFTER read over a margin wide enough for the shift and the cubic spline
   (:data:`SPLINE_MARGIN` cells: the spline's prefilter decays by 0.27 a cell, so its window edge is
   1e-18 of the relief away), differenced as the in-memory chain does
   (:func:`terralod.change.difference.dem_of_difference` on the window pair), budgets accumulated
   (:class:`terralod.change.volumes.BudgetSums`, zones rasterized window by window), the extremes kept
   (the first in raster order on ties, as ``nanargmax``), the DoD written to a tiled GeoTIFF, and a
   decimated copy (every s-th cell, at most :data:`REPORT_MAX_CELLS`) kept for the report's figures.
   Without a horizontal shift the DoD is the in-memory chain's bit for bit; volumes equal it up to the
   order of the float64 sums.
3. ``dod.tif`` becomes a Cloud Optimized GeoTIFF (:func:`terralod.change.difference.DodWriter`), and so
   does ``sigma.tif`` beside it: σ of each cell, the error model fitted on the sample
   (:mod:`terralod.change.uncertainty`: σ by slope and curvature, a sum of spherical ranges) applied to
   each window from BEFORE's slope and curvature there (read with 2 cells of margin, so a window's σ is
   the whole grid's); the volumes' ± add up Σσ and Σσ² of each cell set window by window.

Memory: one window pair in flight (about 1200² cells with margins, some tens of float64 arrays), the sample
(at most SAMPLE_MAX_CELLS cells, through the co-registration), the decimated report copy and the sources'
bounded caches — whatever the region's size.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from affine import Affine

from terralod.change.coregister import SLOPE_MIN_DEG, StableGroundFinder, read_stable_mask
from terralod.change.difference import SIGMA_DESCRIPTION, AlignedPair, DodWriter, dem_of_difference, same_crs
from terralod.change.volumes import (
    BudgetSums,
    ChangeResult,
    Uncertainty,
    _lonlat,
    change_summary,
    estimate_uncertainty,
    fit_alignment,
    resampling_error,
    settle_bias_sigma,
)
from terralod.change.zones import outside_message, zone_geometries, zone_mask
from terralod.errors import InputError
from terralod.heightfield import Heightfield

#: Side of a streamed window, cells.
WINDOW = 1024
#: Most cells of the co-registration sample (4 Mi: a 2048² grid is its own sample).
SAMPLE_MAX_CELLS = 1 << 22
#: Side of a sample window's core, and its margin, cells.
SAMPLE_WINDOW = 512
SAMPLE_MARGIN = 32
#: Cells of margin the cubic spline of a shifted AFTER needs around a window (beyond the shift itself).
SPLINE_MARGIN = 32
#: Most cells of the decimated DoD the report draws.
REPORT_MAX_CELLS = 1 << 22


@dataclass
class Sample:
    """The co-registration sample of a pair: its windows' cores (r0, c0, side rows, side cols) on the grid
    and their places on the composite (row, col of the core's first cell)."""

    pair: AlignedPair
    given: np.ndarray | None
    exclude: np.ndarray | None
    whole: bool
    cells: int
    #: BEFORE's valid cells on the composite, margins included (the slope and curvature of a core's edge)
    terrain_valid: np.ndarray | None = None


def same_grid(a: Any, b: Any) -> bool:
    """True when two window sources (or Heightfields) share one grid: CRS, transform and size."""
    return (
        a.shape == b.shape
        and same_crs(a.crs, b.crs)
        and np.allclose(tuple(a.transform)[:6], tuple(b.transform)[:6], rtol=0, atol=1e-6)
    )


def _window_hf(src: Any, r0: int, c0: int, r1: int, c1: int) -> Heightfield:
    z, ok = src.read(r0, c0, r1, c1)
    t = src.transform @ Affine.translation(c0, r0)
    return Heightfield(np.asarray(z, np.float32), np.asarray(ok, bool), t, crs=src.crs, source=src.source)


def _sample_windows(h: int, w: int, max_cells: int) -> list[tuple[int, int]]:
    """Top-left corners of the sample windows' cores: an even k_r x k_c lattice over the grid."""
    s, m = SAMPLE_WINDOW, SAMPLE_MARGIN
    n = max(1, max_cells // (s + 2 * m) ** 2)
    kr = max(1, min(n, round(math.sqrt(n * h / w))))
    kc = max(1, n // kr)
    rows = [min(max(round((i + 0.5) * h / kr - s / 2), 0), max(h - s, 0)) for i in range(kr)]
    cols = [min(max(round((j + 0.5) * w / kc - s / 2), 0), max(w - s, 0)) for j in range(kc)]
    return [(r, c) for r in sorted(set(rows)) for c in sorted(set(cols))]


def sample_pair(
    before: Any, after: Any, *, stable: str | None = None, exclude: str | None = None,
    max_cells: int | None = None,
) -> Sample:  # fmt: skip
    """The bounded, spatially even sample of a pair on one grid (module docstring, step 1), with the
    ``--stable`` / ``--exclude`` masks (file paths) on it."""
    h, w = before.shape
    max_cells = SAMPLE_MAX_CELLS if max_cells is None else max_cells
    if h * w <= max_cells:
        bh, ah = _window_hf(before, 0, 0, h, w), _window_hf(after, 0, 0, h, w)
        pair = AlignedPair(bh, ah, True, [])
        given = read_stable_mask(stable, bh) if stable else None
        excl = read_stable_mask(exclude, bh, what="cell to leave out") if exclude else None
        return Sample(pair, given, excl, True, h * w, bh.valid)
    s, m = SAMPLE_WINDOW, SAMPLE_MARGIN
    side = s + 2 * m
    corners = _sample_windows(h, w, max_cells)
    rows = sorted({r for r, _ in corners})
    cols = sorted({c for _, c in corners})
    H, W = len(rows) * side, len(cols) * side
    zb = np.zeros((H, W), np.float32)
    za = np.zeros((H, W), np.float32)
    okb = np.zeros((H, W), bool)
    okt = np.zeros((H, W), bool)
    oka = np.zeros((H, W), bool)
    given = np.zeros((H, W), bool) if stable else None
    excl = np.zeros((H, W), bool) if exclude else None
    for i, r0 in enumerate(rows):
        for j, c0 in enumerate(cols):
            ra, rb = max(r0 - m, 0), min(r0 + s + m, h)
            ca, cb = max(c0 - m, 0), min(c0 + s + m, w)
            pr, pc = i * side + (ra - (r0 - m)), j * side + (ca - (c0 - m))
            dst = (slice(pr, pr + rb - ra), slice(pc, pc + cb - ca))
            bh, ah = _window_hf(before, ra, ca, rb, cb), _window_hf(after, ra, ca, rb, cb)
            zb[dst], za[dst], oka[dst] = bh.elevation_m, ah.elevation_m, ah.valid
            core = np.zeros(bh.shape, bool)
            core[r0 - ra : min(r0 + s, h) - ra, c0 - ca : min(c0 + s, w) - ca] = True
            okb[dst] = bh.valid & core
            okt[dst] = bh.valid
            for path, out, what in ((stable, given, "stable cell"), (exclude, excl, "cell to leave out")):
                if path and out is not None:
                    try:
                        out[dst] = read_stable_mask(path, bh, what=what)
                    except InputError:
                        if not Path(path).exists():
                            raise
    for path, out, what in ((stable, given, "stable cell"), (exclude, excl, "cell to leave out")):
        if path and out is not None and not out.any():
            raise InputError(f"marks no {what} on the terrain", str(path))
    t = before.transform
    ct = Affine(t.a, 0.0, t.c, 0.0, t.e, t.f)  # a composite: only its spacing means anything
    bh = Heightfield(zb, okb, ct, crs=before.crs, source=before.source)
    ah = Heightfield(za, oka, ct, crs=after.crs, source=after.source)
    return Sample(AlignedPair(bh, ah, True, []), given, excl, False, len(corners) * s * s, okt)


def _report_stride(h: int, w: int) -> int:
    s = 1
    while math.ceil(h / s) * math.ceil(w / s) > REPORT_MAX_CELLS and s < WINDOW:
        s *= 2
    return s


@dataclass
class Streamed:
    """What one pass over the pair gives (module docstring, step 2)."""

    totals: BudgetSums
    zones: list[BudgetSums]
    valid_cells: int
    extremes: dict
    dod_small: np.ndarray
    before_small: Heightfield


@dataclass
class WindowResult:
    """What one window of the stream gives: its budgets, zones, valid cells, extremes candidates ((sign ·
    value, −row, −col), value) and its DoD (float32, as written)."""

    r0: int
    c0: int
    totals: BudgetSums
    zones: list[BudgetSums]
    zones_seen: list[bool]
    valid_cells: int
    best: dict
    dod: np.ndarray
    small: tuple[np.ndarray, np.ndarray, np.ndarray]
    #: σ of each cell of the window (float32, NaN where the DoD is)
    sigma: np.ndarray | None = None


def window_change(
    before: Any, after: Any, shift_m: tuple[float, float, float], lod_m: float, with_error: bool,
    zones: list[tuple[str, dict, float]], stride: int, r0: int, r1: int, c0: int, c1: int,
    unc: Uncertainty | None = None,
) -> WindowResult:  # fmt: skip
    """One window of the stream (rows [r0, r1), cols [c0, c1) of BEFORE's grid): a pure function of the
    sources and its arguments, run here or on a Dask worker (whose allocator gets its adaptive thresholds
    back first: :func:`terralod.pyramid.distributed.tune_worker_malloc`)."""
    from terralod.pyramid.distributed import tune_worker_malloc

    tune_worker_malloc()
    h, w = before.shape
    tx, ty, _ = (float(v) for v in shift_m)
    px = min(before.spacing_m)
    moved = tx != 0.0 or ty != 0.0
    m = SPLINE_MARGIN + math.ceil(math.hypot(tx, ty) / px) if moved else 0
    m = 2 * m if (moved and with_error) else m
    m = max(m, 2) if unc is not None else m  # slope and curvature: central differences of differences
    ra, rb, ca, cb = max(r0 - m, 0), min(r1 + m, h), max(c0 - m, 0), min(c1 + m, w)
    bw, aw = _window_hf(before, ra, ca, rb, cb), _window_hf(after, ra, ca, rb, cb)
    wp = AlignedPair(bw, aw, True, [])
    core = (slice(r0 - ra, r1 - ra), slice(c0 - ca, c1 - ca))
    d = dem_of_difference(wp, shift_m)[core]
    e = resampling_error(wp, aw, shift_m) if with_error else None
    e = None if e is None else e[core]
    sig = sg_model = None
    if unc is not None:
        sig = unc.sigma_grid(bw.elevation_m, bw.valid, before.spacing_m)[core]
        sig = np.where(np.isfinite(d), sig, np.float32(np.nan)).astype(np.float32)
        sg_model = sig if unc.model is not None else None
    totals = BudgetSums(lod_m, None if unc is None else unc.t)
    totals.add(d, e, None, sg_model)
    fin = np.isfinite(d)
    best: dict = {}
    if fin.any():
        for key, fn, sign in (("max_rise", np.nanargmax, 1.0), ("max_drop", np.nanargmin, -1.0)):
            r, c = np.unravel_index(int(fn(d)), d.shape)
            best[key] = ((sign * float(d[r, c]), -(r0 + int(r)), -(c0 + int(c))), float(d[r, c]))
    zsums = [BudgetSums(lod_m, None if unc is None else unc.t) for _ in zones]
    seen = [False] * len(zones)
    if zones:
        wt = before.transform @ Affine.translation(c0, r0)
        bvalid = bw.valid[core]
        for k, (_name, geom, _frac) in enumerate(zones):
            zm = zone_mask(geom, d.shape, wt)
            if zm.any():
                zsums[k].add(d, e, zm, sg_model)
                seen[k] = bool((zm & bvalid).any())
    sr, sc = (-r0) % stride, (-c0) % stride
    small = (d[sr::stride, sc::stride], bw.elevation_m[core][sr::stride, sc::stride],
             bw.valid[core][sr::stride, sc::stride])  # fmt: skip
    return WindowResult(r0, c0, totals, zsums, seen, int(fin.sum()), best, d.astype(np.float32), small, sig)


def stream_change(
    before: Any, after: Any, shift_m: tuple[float, float, float], lod_m: float, *, with_error: bool,
    zones: list[tuple[str, dict, float]] = (), dod: DodWriter | None = None, window: int | None = None,
    client: Any = None, unc: Uncertainty | None = None, sigma: DodWriter | None = None,
) -> Streamed:  # fmt: skip
    """One pass over BEFORE's grid, window by window (:func:`window_change`, on ``client``'s Dask workers
    when given): budgets (``lod_m`` splits them), zones, extremes, the valid cells, the DoD written to ``dod``
    and a decimated copy for the report. Windows are merged in raster order of windows whoever computed
    them, so the figures and ``dod.tif`` are the same bytes with or without Dask."""
    h, w = before.shape
    window = WINDOW if window is None else window
    stride = _report_stride(h, w)
    small = np.full((math.ceil(h / stride), math.ceil(w / stride)), np.nan)
    zsmall = np.zeros(small.shape, np.float32)
    oksmall = np.zeros(small.shape, bool)
    t = None if unc is None else unc.t
    totals = BudgetSums(lod_m, t)
    zsums = [BudgetSums(lod_m, t) for _ in zones]
    zseen = [False] * len(zones)
    valid = 0
    best: dict = {"max_rise": None, "max_drop": None}
    spans = [(r0, min(r0 + window, h), c0, min(c0 + window, w)) for r0 in range(0, h, window)
             for c0 in range(0, w, window)]  # fmt: skip
    args = (shift_m, lod_m, with_error, list(zones), stride)
    kwargs = {"unc": unc}
    for got in _window_results(before, after, args, spans, client, kwargs):
        r0, c0 = got.r0, got.c0
        totals.merge(got.totals)
        for k in range(len(zones)):
            zsums[k].merge(got.zones[k])
            zseen[k] = zseen[k] or got.zones_seen[k]
        valid += got.valid_cells
        for key, cand in got.best.items():
            if best[key] is None or cand[0] > best[key][0]:
                best[key] = cand
        if dod is not None:
            dod.write(got.dod, r0, c0)
        if sigma is not None and got.sigma is not None:
            sigma.write(got.sigma, r0, c0)
        d_s, z_s, ok_s = got.small
        dst = (slice((r0 + stride - 1) // stride, (r0 + stride - 1) // stride + d_s.shape[0]),
               slice((c0 + stride - 1) // stride, (c0 + stride - 1) // stride + d_s.shape[1]))  # fmt: skip
        small[dst], zsmall[dst], oksmall[dst] = d_s, z_s, ok_s
    for k, (name, geom, _frac) in enumerate(zones):
        if not zseen[k]:
            raise InputError(outside_message(name, geom, before.crs, _bounds(before)), "--zones")
    t = before.transform
    st = Affine(t.a * stride, 0.0, t.c, 0.0, t.e * stride, t.f)
    bsmall = Heightfield(zsmall, oksmall, st, crs=before.crs, source=before.source)
    ext = {}
    for key in ("max_rise", "max_drop"):
        if best[key] is None:
            ext[key] = None
            continue
        (_, nr, nc), value = best[key]
        r, c = -nr, -nc
        x, y = t @ (c + 0.5, r + 0.5)
        item = {"value_m": value, "row": r, "col": c, "x_m": float(x), "y_m": float(y)}
        item.update(_lonlat(before.crs, float(x), float(y)))
        ext[key] = item
    return Streamed(totals, zsums, valid, ext, small, bsmall)


#: Windows a Dask run keeps in flight per worker thread (their DoDs come back to be written here).
DASK_WINDOWS_IN_FLIGHT = 2


def _window_results(before: Any, after: Any, args: tuple, spans: list, client: Any, kwargs: dict):  # noqa: ANN202
    """Each window's :class:`WindowResult`, in the order of ``spans``: computed here one at a time, or on
    Dask workers with a bounded number in flight."""
    if client is None:
        for span in spans:
            yield window_change(before, after, *args, *span, **kwargs)
        return
    threads = max(1, sum(client.nthreads().values()))
    limit = DASK_WINDOWS_IN_FLIGHT * threads
    b_f, a_f = client.scatter(before, broadcast=True), client.scatter(after, broadcast=True)
    futures: dict[int, Any] = {}
    nxt = 0
    for i in range(len(spans)):
        while nxt < len(spans) and nxt < i + limit:
            futures[nxt] = client.submit(window_change, b_f, a_f, *args, *spans[nxt], **kwargs, pure=False)
            nxt += 1
        yield futures.pop(i).result()


def _bounds(src: Any) -> tuple[float, float, float, float]:
    t, (h, w) = src.transform, src.shape
    return (t.c, t.f + h * t.e, t.c + w * t.a, t.f)


def measure_change_windowed(
    before: Any, after: Any, *, names: tuple[str, str], dod_path: str | Path | None = None,
    sigma_path: str | Path | None = None,
    stable: str | None = None, exclude: str | None = None, coregistration: bool = True,
    method: str = "xdem", sigma_m: float | None = None, corr_range_m: float | None = None,
    confidence: float = 0.95, zones: str | Path | None = None,
    dates: tuple[str | None, str | None] = (None, None), slope_min_deg: float = SLOPE_MIN_DEG,
    notes: list[str] | None = None, client: Any = None,
) -> ChangeResult:  # fmt: skip
    """:func:`terralod.change.volumes.measure_change` of two window sources on one grid (module
    docstring); ``dod.tif`` is written to ``dod_path`` on the way, ``sigma.tif`` to ``sigma_path`` (beside
    ``dod_path`` when not given). The result's ``dod`` and ``pair`` are the
    decimated copies the report draws; ``summary`` holds the same contract keys, plus ``windowed``."""
    if not same_grid(before, after):
        raise InputError(f"is not on {names[0]}'s grid (CRS, transform and size must match to be read window "
                         "by window); warp it onto that grid first (gdalwarp -te ... -tr ... -tap)", names[1])  # fmt: skip
    geoms = zone_geometries(zones, before.crs, _bounds(before)) if zones is not None else []
    sample = sample_pair(before, after, stable=stable, exclude=exclude)
    sp = sample.pair
    ground = StableGroundFinder(sp, given=sample.given, exclude=sample.exclude, slope_min_deg=slope_min_deg)
    co = fit_alignment(sp, ground, coregistration=coregistration, method=method)
    shift = co.shift_m if co.applied else (0.0, 0.0, 0.0)
    dod_s = dem_of_difference(sp, shift)
    sg = ground(dod_s)
    rerr_s = resampling_error(sp, sp.after, shift)
    dx, dy = before.spacing_m
    unc = estimate_uncertainty(
        dod_s, sg.mask, dx * dy, (dx, dy), sigma_m=sigma_m, corr_range_m=corr_range_m,
        confidence=confidence, resampling_error_m=rerr_s, z_before_m=sp.before.elevation_m,
        valid_before=sample.terrain_valid if sample.terrain_valid is not None else sp.before.valid,
        candidates=sg.base,
    )  # fmt: skip
    settle_bias_sigma(co, unc, dx * dy)
    tags = {"sigma_m": unc.sigma_m, "level_of_detection_m": unc.level_of_detection_m,
            "shift_m": [float(v) for v in shift], "before": Path(names[0]).name, "after": Path(names[1]).name}  # fmt: skip
    writer = DodWriter(dod_path, before, tags) if dod_path is not None else None
    if sigma_path is None and dod_path is not None:
        sigma_path = Path(dod_path).with_name("sigma.tif")
    swriter = (
        DodWriter(sigma_path, before, tags, description=SIGMA_DESCRIPTION) if sigma_path is not None else None
    )
    try:
        got = stream_change(before, after, shift, unc.level_of_detection_m, with_error=rerr_s is not None,
                            zones=geoms, dod=writer, client=client, unc=unc, sigma=swriter)  # fmt: skip
    except BaseException:
        for wr in (writer, swriter):
            if wr is not None:
                wr.abort()
        raise
    for wr in (writer, swriter):
        if wr is not None:
            wr.close()
    zone_budgets = [
        (name, zs.budget(unc), frac) for (name, _g, frac), zs in zip(geoms, got.zones, strict=True)
    ]
    report_pair = AlignedPair(got.before_small, got.before_small, True, list(notes or []))
    summary = change_summary(
        report_pair, co, sg, unc, got.totals.budget(unc), shift=shift, confidence=confidence, dates=dates,
        names=names, valid_cells=got.valid_cells, resampled=False, extremes_=got.extremes,
        zone_budgets=zone_budgets,
    )  # fmt: skip
    h, w = before.shape
    t = before.transform
    summary["grid"]["shape"] = [int(h), int(w)]
    summary["grid"]["bounds_m"] = [float(v) for v in _bounds(before)]
    summary["grid"]["spacing_m"] = [float(dx), float(dy)]
    summary["grid"]["cell_area_m2"] = float(dx * dy)
    summary["windowed"] = {
        "window_cells": WINDOW,
        "sample_cells": int(sample.cells),
        "sample_whole_grid": bool(sample.whole),
        "report_stride": int(round(got.before_small.transform.a / t.a)),
        "statement": (
            "read window by window; the alignment and the survey error were measured on "
            + ("the whole grid" if sample.whole else f"an even sample of {sample.cells:,} cells "
               f"({100.0 * sample.cells / (h * w):.1f} % of the grid)")
        ),
    }  # fmt: skip
    return ChangeResult(report_pair, co, got.dod_small, sg.mask, unc, summary, [])
