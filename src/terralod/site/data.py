"""What the change site's page reads: the manifest and, per pair of epochs, the difference raster (as tile
pyramids, :mod:`terralod.site.tiles`) with everything needed to answer "how much changed here?" in the
browser (see :mod:`terralod.site`).

The page has no projection library. It maps a longitude/latitude to the difference raster's cell through a
lattice of the grid CRS's coordinates at regular longitudes and latitudes (bilinear between nodes: over a
lattice step of a few hundred metres a projection bends by millimetres), and drapes the difference (coloured in
the page with the legend's table) on the 3D Tiles through an affine map from local east/north metres to
texture coordinates, fitted here on the grid's cells at their own heights (its worst residual is stored and
tested). Every coordinate transform is
:mod:`terralod.export.geodesy`'s.
"""

from __future__ import annotations

import math
from collections.abc import MutableMapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from terralod.site.tiles import RowReader, array_rows, write_pyramid

#: Lattice nodes per side (lon/lat → grid CRS coordinates).
LATTICE_NODES = 33
#: One Olympic swimming pool (50 m × 25 m × 2 m), the page's familiar comparison for a volume.
OLYMPIC_POOL_M3 = 2500.0
#: Grey of "no measurable change" (inside the level of detection) and its opacity.
LOD_GREY_RGBA = (150, 150, 150, 110)


def lattice(hf: Any, nodes: int = LATTICE_NODES) -> dict[str, Any]:
    """Grid-CRS x, y (metres) at ``nodes``² regular lon/lat points covering ``hf`` (row-major, south first)."""
    from terralod.export.geodesy import Geodesy

    g = Geodesy(hf.crs, geographic=True)
    w, s, e, n = g.lonlat_bounds(hf.bounds_m)
    pad_lon, pad_lat = 0.02 * (e - w), 0.02 * (n - s)
    w, e, s, n = w - pad_lon, e + pad_lon, s - pad_lat, n + pad_lat
    lon = np.linspace(w, e, nodes)
    lat = np.linspace(s, n, nodes)
    LON, LAT = np.meshgrid(lon, lat)
    x, y = g.xy(LON.ravel(), LAT.ravel())
    return {"lon0_deg": w, "lat0_deg": s, "dlon_deg": (e - w) / (nodes - 1), "dlat_deg": (n - s) / (nodes - 1),
            "nodes": nodes, "x_m": [round(float(v), 4) for v in x], "y_m": [round(float(v), 4) for v in y]}  # fmt: skip


def drape_map(hf: Any, grid: tuple[Any, tuple[int, int]] | None = None) -> dict[str, Any]:
    """The affine map from local east/north metres (about the grid's centre, Earth-fixed) to the overlay's
    texture coordinates (u = column / width, v = row / height: a cell's centre at ((c + 0.5) / w, (r + 0.5)
    / h)), least-squares on a 17² sample of cell centres at their own heights; ``residual_cells`` is its worst
    error in cells. ``grid``: (transform, shape) of the overlay's grid when it is not ``hf``'s (a region
    measured window by window: ``hf`` is then the report's decimated copy, each sampled centre's height taken
    from the copy's cell holding it)."""
    from terralod.export.geodesy import Geodesy, ecef_lonlat

    t, (h, w) = grid if grid is not None else (hf.transform, hf.shape)
    R, C = np.meshgrid(np.linspace(0, h - 1, 17).round(), np.linspace(0, w - 1, 17).round(), indexing="ij")
    x, y = t @ (C + 0.5, R + 0.5)  # the sampled cells' centres
    hr, hc = hf.sample_rc(x, y)
    r_i = np.clip(np.round(hr), 0, hf.height - 1).astype(int)
    c_i = np.clip(np.round(hc), 0, hf.width - 1).astype(int)
    z = np.asarray(hf.elevation_m, np.float64)
    valid = np.asarray(hf.valid, bool)
    zmed = float(np.median(z[valid])) if valid.any() else 0.0
    zz = np.where(valid[r_i, c_i], z[r_i, c_i], zmed)
    lon, lat = Geodesy(hf.crs, geographic=True).lonlat(np.ravel(x), np.ravel(y))
    p = ecef_lonlat(lon, lat, zz.ravel())
    lon_c, lat_c = float(np.mean(lon)), float(np.mean(lat))
    centre = ecef_lonlat(np.array([lon_c]), np.array([lat_c]), np.array([zmed]))[0]
    lo, la = math.radians(lon_c), math.radians(lat_c)
    east = np.array([-math.sin(lo), math.cos(lo), 0.0])
    north = np.array([-math.sin(la) * math.cos(lo), -math.sin(la) * math.sin(lo), math.cos(la)])
    d = p - centre
    A = np.stack([np.ones(len(d)), d @ east, d @ north], axis=1)
    u = (C.ravel() + 0.5) / w
    v = (R.ravel() + 0.5) / h
    cu, *_ = np.linalg.lstsq(A, u, rcond=None)
    cv, *_ = np.linalg.lstsq(A, v, rcond=None)
    res = max(float(np.max(np.abs(A @ cu - u))) * w, float(np.max(np.abs(A @ cv - v))) * h)
    return {"centre_ecef": centre.tolist(), "east": east.tolist(), "north": north.tolist(),
            "u": cu.tolist(), "v": cv.tolist(), "residual_cells": res}  # fmt: skip


def colour_scale(dod: np.ndarray, lod_m: float) -> tuple[float, float]:
    """(largest drop, largest rise) metres at full colour: the report's map's scale (99.5th percentiles)."""
    fin = dod[np.isfinite(dod)]
    hi = max(float(np.percentile(fin[fin > 0], 99.5)) if (fin > 0).any() else 0.0, 2 * lod_m, 0.1)
    lo = max(float(-np.percentile(fin[fin < 0], 0.5)) if (fin < 0).any() else 0.0, 2 * lod_m, 0.1)
    return lo, hi


#: Colours in the legend's look-up table the page colours the drape with (matplotlib's RdBu, evenly in the
#: two-slope normalised value: 0 = the largest drop, 0.5 = no change, 1 = the largest rise).
LUT_SIZE = 256


def legend_of(dod: np.ndarray, lod_m: float) -> dict[str, Any]:
    """The drape's legend: matplotlib's RdBu (colour-blind safe; blue = rose, red = dropped) on the report's
    scale (:func:`colour_scale`), grey inside the level of detection, and the look-up table the page colours
    the difference's tiles with (``lut_rgb``: LUT_SIZE RGB triples over the two-slope normalised value; the
    page draws no data transparent, inside the level of detection :data:`LOD_GREY_RGBA`, else the table's
    colour at opacity ``alpha``)."""
    from matplotlib import colormaps
    from matplotlib.colors import TwoSlopeNorm

    lo, hi = colour_scale(dod, lod_m)
    norm = TwoSlopeNorm(vmin=-lo, vcenter=0.0, vmax=hi)
    cmap = colormaps["RdBu"]
    values = [-lo, -lo / 2, -lod_m, lod_m, hi / 4, hi / 2, 3 * hi / 4, hi]
    stops = []
    for v in values:
        r, g, b, _ = cmap(norm(v))
        stops.append({"value_m": v, "css": f"rgb({round(255 * r)},{round(255 * g)},{round(255 * b)})"})
    lut = (cmap(np.linspace(0.0, 1.0, LUT_SIZE))[:, :3] * 255).round().astype(int)
    return {"min_m": -lo, "max_m": hi, "lod_m": lod_m, "stops": stops, "lod_css": "rgb(150,150,150)",
            "rose": "blue", "dropped": "red", "lut_rgb": lut.ravel().tolist(), "alpha": 235,
            "lod_rgba": list(LOD_GREY_RGBA)}  # fmt: skip


@dataclass(frozen=True)
class PairRasters:
    """A pair's rasters on the full grid, read in strips of rows (:data:`terralod.site.tiles.RowReader`): the
    difference and BEFORE's heights (float metres, NaN = no data), the grid's shape and affine transform. A
    pair measured window by window gives these, its result's arrays being the report's decimated copies."""

    dod: RowReader
    before: RowReader
    shape: tuple[int, int]
    transform: Any


def pair_key(before: str, after: str) -> str:
    """The name a pair's raster pyramids go under (``pairs/KEY-dod/``, ``pairs/KEY-before/``): a function of
    its two epochs only, so that a site updated with a new survey keeps the pairs it had under the same names
    (``--update`` leaves their tiles as they are) whatever place the new pairs take in the list."""
    import hashlib

    return hashlib.sha256(f"{before}\n{after}".encode()).hexdigest()[:12]


def epoch_key(epoch: str) -> str:
    """The name an epoch's heights pyramid goes under (``pairs/KEY-before/``): every pair from that epoch
    shows the same heights, kept once under one name whatever pairs a site has."""
    import hashlib

    return hashlib.sha256(f"{epoch}\n".encode()).hexdigest()[:12]


def pair_payload(result: Any, dates: tuple[str | None, str | None], labels: tuple[str, str], key: str,
                 *, summary_lines: list[str] | None = None, rasters: PairRasters | None = None,
                 files: MutableMapping[str, bytes] | None = None,
                 before_key: str | None = None) -> tuple[dict[str, Any], MutableMapping[str, bytes]]:  # fmt: skip
    """(description, files) of one pair for the page: ``pairs/KEY.json``'s content and the rasters' tiles
    (put in ``files`` when given: a :class:`terralod.site.tiles.FolderFiles` keeps them on disk).

    ``rasters``: the full grid's rasters when ``result`` holds decimated copies (a pair measured window by
    window): the tiles, the grid and the drape come from them; the legend's colour scale from the copy (as
    the report's map)."""
    from terralod.change.report import plain_summary

    hf = result.pair.before
    dod = np.asarray(result.dod, np.float32)
    unc = result.uncertainty
    legend = legend_of(dod, unc.level_of_detection_m)
    if rasters is None:
        before = np.where(np.asarray(hf.valid, bool), np.asarray(hf.elevation_m, np.float32), np.nan)
        rasters = PairRasters(array_rows(dod), array_rows(before.astype("<f4")), dod.shape, hf.transform)
    files = {} if files is None else files
    dod_desc, _ = write_pyramid(rasters.dod, rasters.shape, f"pairs/{key}-dod", files=files)
    before_desc, _ = write_pyramid(
        rasters.before, rasters.shape, f"pairs/{before_key or key}-before", files=files
    )
    s = result.summary
    ext = {}
    for k in ("max_rise", "max_drop"):
        e = (s.get("extremes") or {}).get(k)
        if e and "lon_deg" in e:
            ext[k] = {"lon_deg": e["lon_deg"], "lat_deg": e["lat_deg"], "value_m": e["value_m"]}
    big = max(ext.values(), key=lambda e: abs(e["value_m"]), default=None)
    tr = rasters.transform
    meta = {
        "key": key,
        "from": labels[0],
        "to": labels[1],
        "dates": list(dates),
        "grid": {
            "shape": list(rasters.shape),
            "transform": [tr.a, tr.b, tr.c, tr.d, tr.e, tr.f],
            "cell_area_m2": float(unc.cell_area_m2),
        },  # fmt: skip
        "lattice": lattice(hf),
        "drape": drape_map(hf, (rasters.transform, rasters.shape)),
        "error_model": {
            "sigma_m": unc.sigma_m,
            "t": unc.t,
            "confidence": unc.confidence,
            "nugget_m2": unc.nugget_m2,
            "sill_m2": unc.sill_m2,
            "range_m": unc.range_m,
            "lod_m": unc.level_of_detection_m,
            "sigma_source": unc.sigma_source,
        },  # fmt: skip
        "legend": legend,
        "summary": summary_lines if summary_lines is not None else plain_summary(result, dates),
        "totals": {
            k: s[k]
            for k in (
                "net_m3",
                "net_uncertainty_m3",
                "gain_m3_above_lod",
                "loss_m3_above_lod",
                "area_gain_m2",
                "area_loss_m2",
            )  # fmt: skip
        },
        "largest": big,
        "rasters": {"dod": dod_desc, "before": before_desc},
        "olympic_pool_m3": OLYMPIC_POOL_M3,
    }
    return meta, files


def pairs_of(epochs: list[str]) -> list[tuple[str, str]]:
    """The pairs a site carries: first → last, each consecutive pair, then first → every other epoch (the
    page drapes "the change since the first date" on each date of a series), no repeats."""
    out: list[tuple[str, str]] = []
    if len(epochs) >= 2:
        out.append((epochs[0], epochs[-1]))
    for a, b in zip(epochs[:-1], epochs[1:], strict=True):
        if (a, b) not in out:
            out.append((a, b))
    for b in epochs[2:-1]:
        out.append((epochs[0], b))
    return out


def epoch_label(name: str) -> str:
    """'25 Sep 2000' for an ISO date name, the name otherwise."""
    from terralod.change.report import nice_date

    return nice_date(name) or name if len(name) >= 10 and name[4] == "-" else name
