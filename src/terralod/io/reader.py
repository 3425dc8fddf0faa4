"""Read any supported DEM into a :class:`~terralod.heightfield.Heightfield`: the one entry point of io/.

Formats, chosen by file suffix:

- ``.png``, ``.webp``: greyscale heightmaps and RGB-encoded elevation tiles
  (:mod:`terralod.io.heightmap`, Pillow);
- ``.npy``, ``.npz``: NumPy grids (:mod:`terralod.io.heightmap`);
- anything else: a raster GDAL reads, GeoTIFF/COG first (:mod:`terralod.io.raster`, rasterio).

World frame: metres, x east, y north, row 0 north, north-up transform; geographic and web-mercator
inputs are reprojected once to UTM, foot CRSs converted to metres (details in :mod:`terralod.io.raster`).

Sidecar
-------
A file ``<stem>.json`` beside the input supplies defaults; explicit keyword arguments override it. For
PNG/WebP/NPY/NPZ every key applies; for GDAL rasters the file's own metadata wins, and the sidecar only
fills what the file lacks (georeferencing when the file has no CRS, nodata when the band has none).
Two layouts are read, the flat one first:

===================== ================================== ===================================================
flat key              nested key (``../shared/data``)    meaning
===================== ================================== ===================================================
``spacing_m``         ``horizontal.spacing_m``           ground spacing, metres: number or [dx, dy]
``vertical_scale``    ``vertical.scale_m_per_unit``      metres per stored unit
``vertical_offset``   ``vertical.offset_m``              metres added after scaling
``encoding``          ``encoding.name``                  "terrain-rgb" (also "Terrain-RGB", "mapbox") or
                                                         "terrarium" (any case)
``tile``              ``horizontal.tile``                XYZ tile: [z, x, y], "z/x/y" or {"z", "x", "y"}
``nodata``            ``nodata``                         stored value of missing samples (number, "NaN",
                                                         null)
``crs``               ``horizontal.crs``                 "EPSG:32610", WKT, PROJ; a text containing
                                                         "EPSG:<code>" is read as that code
``transform``         ``horizontal.transform``           GDAL geotransform [x0, dx, 0, y0, 0, -dy], or
                                                         [west, north] origin used with ``spacing_m``
``origin_m``          ``horizontal.origin_m``            [west, north] pixel corner of sample (0, 0)
``bounds``            ``horizontal.bounds``              [west, south, east, north] of the pixel footprint
===================== ================================== ===================================================

Georeferencing precedence: a tile, then transform / bounds / origin (with ``crs``: georeferenced; without:
a local metric frame), then ``spacing_m`` alone (local frame, origin at the north-west corner). A spacing
is ignored (with a note) for a georeferenced input. Without any, PNG/NPY inputs are refused with an error
that asks for ``--spacing`` or a sidecar. An ``.npz`` may hold its own ``transform`` (geotransform) and
``crs`` arrays, used when the sidecar gives none. ``nodata`` is a stored value (before scaling), except
for encoded tiles, where it is in decoded metres.
"""

from __future__ import annotations

import json
import math
import os
import re
from pathlib import Path
from typing import Any

import numpy as np
from affine import Affine

from terralod.errors import InputError, InputNotFoundError
from terralod.heightfield import Heightfield
from terralod.io.encodings import ENCODINGS
from terralod.io.heightmap import read_array, read_image
from terralod.io.raster import FrameHints, georeferenced_heightfield, read_raster

IMAGE_SUFFIXES = frozenset({".png", ".webp"})
ARRAY_SUFFIXES = frozenset({".npy", ".npz"})
SAMPLE_SOURCE = "matplotlib sample_data/jacksboro_fault_dem.npz"

_ENCODING_ALIASES = {
    "terrain-rgb": "terrain-rgb",
    "terrainrgb": "terrain-rgb",
    "mapbox": "terrain-rgb",
    "mapbox-terrain-rgb": "terrain-rgb",
    "terrarium": "terrarium",
    "mapzen": "terrarium",
    "mapzen-terrarium": "terrarium",
}


# -- public --------------------------------------------------------------------------------------------
def read_heightfield(
    path: str | os.PathLike[str],
    *,
    vertical_scale: float | None = None,
    vertical_offset: float | None = None,
    spacing_m: float | tuple[float, float] | None = None,
    encoding: str | None = None,
    tile: tuple[int, int, int] | None = None,
    band: int = 1,
    crs: Any = None,
    vertical_datum: str | None = None,
) -> Heightfield:
    """Read a DEM into a :class:`Heightfield` (elevation metres, metric world frame, nodata mask).

    Parameters
    ----------
    path : GeoTIFF/COG (any raster GDAL reads), PNG/WebP heightmap or encoded tile, .npy/.npz.
    vertical_scale : metres per stored unit. Default: the sidecar's for PNG/WebP/NPY/NPZ, the band's scale
        tag for GDAL rasters; else 1.
    vertical_offset : metres added after scaling. Default: the sidecar's, or the band's offset tag; else 0.
    spacing_m : ground spacing in metres, a number or (dx, dy), for inputs without georeferencing.
    encoding : "terrain-rgb" (Mapbox) or "terrarium" for RGB-encoded elevation tiles.
    tile : (z, x, y) XYZ web-map tile address (y down from the north), which georeferences a tile in
        EPSG:3857; the tile is then reprojected to UTM like any geographic raster.
    band : 1-based raster band (GDAL rasters).
    crs : a CRS (EPSG code, WKT, PROJ string) that assigns or overrides the input's own (CLI ``--crs``);
        for a heightmap without georeferencing it is the CRS of the sidecar's transform / origin / bounds.
    vertical_datum : what the heights are measured from when the file does not say (CLI
        ``--vertical-datum``): ``egm96``, ``egm2008``, ``navd88``, ``ellipsoid`` or a vertical CRS
        (``EPSG:5773``); carried in the Heightfield's CRS (compound, or 3D for the ellipsoid), so a store and
        its web exports know it.

    Returns
    -------
    Heightfield with ``elevation_m`` filled where the source had nodata and ``valid`` marking real samples.

    Raises
    ------
    InputNotFoundError : the file does not exist.
    InputError : the file cannot be decoded, is not georeferenced and no spacing is known, has no valid
        samples, or is too small or too large; the message names the file.
    """
    if vertical_datum is not None:
        hf = read_heightfield(path, vertical_scale=vertical_scale, vertical_offset=vertical_offset,
                              spacing_m=spacing_m, encoding=encoding, tile=tile, band=band, crs=crs)  # fmt: skip
        return with_vertical_datum(hf, vertical_datum)
    p = Path(path)
    src = str(p)
    if not p.exists():
        raise InputNotFoundError("file not found", src)
    if p.is_dir():
        raise InputError("is a directory, not a DEM file", src)
    if isinstance(band, bool) or not isinstance(band, int | np.integer) or band < 1:
        raise InputError(f"band must be a 1-based integer, got {band!r}", src)
    side = read_sidecar(p)
    explicit: dict[str, Any] = {
        "vertical_scale": _opt_float(vertical_scale, "vertical_scale", src),
        "vertical_offset": _opt_float(vertical_offset, "vertical_offset", src),
        "spacing_m": None if spacing_m is None else spacing_pair(spacing_m, src),
        "encoding": None if encoding is None else normalise_encoding(encoding, src),
        "tile": None if tile is None else _tile(tile, src),
    }
    opts = {**side, **{k: v for k, v in explicit.items() if v is not None}}
    if crs is not None:
        from terralod.io.georef import to_crs

        opts["crs"] = to_crs(crs, src).to_wkt()
    hints = _hints(opts, src)
    suffix = p.suffix.lower()
    if suffix in IMAGE_SUFFIXES or suffix in ARRAY_SUFFIXES:
        notes = (f"sidecar {p.with_suffix('.json').name} read",) if side else ()
        common: dict[str, Any] = {
            "vertical_scale": opts.get("vertical_scale"),
            "vertical_offset": opts.get("vertical_offset"),
            "nodata": opts.get("nodata"),
            "hints": hints,
            "notes": notes,
        }
        if suffix in IMAGE_SUFFIXES:
            return read_image(p, encoding=opts.get("encoding"), **common)
        if opts.get("encoding"):
            raise InputError("an encoding applies to RGB images, not to arrays", src)
        return read_array(p, **common)
    return read_raster(
        p,
        band=int(band),
        vertical_scale=explicit["vertical_scale"],
        vertical_offset=explicit["vertical_offset"],
        encoding=opts.get("encoding"),
        nodata=opts.get("nodata"),
        hints=hints,
        crs=crs,
    )


#: ``--vertical-datum`` names and their vertical CRS (``ellipsoid``: the CRS made 3D, ellipsoidal height).
VERTICAL_DATUMS = {"egm96": "EPSG:5773", "egm2008": "EPSG:3855", "navd88": "EPSG:5703", "ellipsoid": None}


def with_vertical_datum(hf: Heightfield, vertical_datum: str) -> Heightfield:
    """``hf`` with its heights declared above ``vertical_datum`` (see :func:`crs_with_vertical_datum`).
    Heights are not changed; the web exports convert them."""
    import dataclasses

    crs, note = crs_with_vertical_datum(hf.crs, vertical_datum, hf.source)
    return dataclasses.replace(hf, crs=crs, notes=(*hf.notes, note))


def crs_with_vertical_datum(crs_text: str | None, vertical_datum: str, source: str) -> tuple[str, str]:
    """(WKT, note): ``crs_text`` with heights above ``vertical_datum`` (a name of :data:`VERTICAL_DATUMS` or
    a vertical CRS such as ``EPSG:5773``): compound (horizontal + vertical), or 3D with an ellipsoidal height
    axis for ``ellipsoid``."""
    if crs_text is None:
        raise InputError("has no CRS, so no vertical datum can be attached to it (give --crs too)", source)
    try:
        import pyproj
        from pyproj.crs import CompoundCRS
    except ImportError:
        raise InputError("--vertical-datum needs pyproj: pip install 'terralod[web]'", source) from None
    key = vertical_datum.strip().lower()
    horizontal = pyproj.CRS.from_user_input(crs_text)
    if horizontal.is_compound:
        horizontal = horizontal.sub_crs_list[0]
    if key == "ellipsoid":
        return horizontal.to_3d().to_wkt(), "heights above the WGS 84 ellipsoid (--vertical-datum)"
    code = VERTICAL_DATUMS.get(key, vertical_datum.strip())
    try:
        vertical = pyproj.CRS.from_user_input(code)
    except Exception:  # noqa: BLE001 - pyproj raises CRSError and others
        vertical = None
    if vertical is None or not vertical.is_vertical:
        names = ", ".join(VERTICAL_DATUMS)
        raise InputError(
            f"--vertical-datum: expected one of {names} or a vertical CRS (EPSG:5773), got {vertical_datum!r}",
            source,
        )
    crs = CompoundCRS(f"{horizontal.name} + {vertical.name}", [horizontal, vertical])
    return crs.to_wkt(), f"heights above {vertical.name} (--vertical-datum)"


def sample_heightfield() -> Heightfield:
    """matplotlib's bundled real DEM: the Jacksboro fault, Tennessee (USGS, 344 x 403 samples at 3
    arc-seconds, 236..1076 m), reprojected from WGS84 lon/lat to UTM zone 16N (its centre, 84.25 W, lies
    west of 84 W) on ~74 m square pixels.

    ``xmin``/``xmax`` and ``ymin``/``ymax`` in the file are pixel-footprint edges (their span is
    W * dx), with ``ymin`` and ``ymax`` swapped: the larger is the north edge, which row 0 sits on.
    """
    from matplotlib import cbook

    sample: Any = cbook.get_sample_data("jacksboro_fault_dem.npz")
    with sample as d:
        z = np.asarray(d["elevation"], dtype=np.float64)
        west, east = float(d["xmin"]), float(d["xmax"])
        south, north = sorted((float(d["ymin"]), float(d["ymax"])))
        dx_deg, dy_deg = float(d["dx"]), float(d["dy"])
    h, w = z.shape
    # edges when the span is W steps, sample centres when it is W - 1 steps (then extend by half a step)
    half_x = 0.0 if abs((east - west) - w * dx_deg) <= abs((east - west) - (w - 1) * dx_deg) else 0.5
    half_y = 0.0 if abs((north - south) - h * dy_deg) <= abs((north - south) - (h - 1) * dy_deg) else 0.5
    t = Affine(dx_deg, 0.0, west - half_x * dx_deg, 0.0, -dy_deg, north + half_y * dy_deg)
    return georeferenced_heightfield(
        z,
        np.ones(z.shape, bool),
        t,
        "EPSG:4326",
        SAMPLE_SOURCE,
        notes=("USGS 3 arc-second DEM of the Jacksboro fault, Tennessee (matplotlib sample data)",),
    )


# -- sidecar -------------------------------------------------------------------------------------------
def read_sidecar(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Normalised defaults from ``<stem>.json`` beside ``path`` (empty dict when there is none).

    Keys of the result (all optional): ``spacing_m`` (dx, dy), ``vertical_scale``, ``vertical_offset``,
    ``encoding`` (canonical name), ``tile`` (z, x, y), ``nodata`` (float, NaN allowed), ``crs`` (str),
    ``transform`` (6 numbers), ``origin_m`` (west, north), ``bounds`` (west, south, east, north), and
    ``_sidecar`` (the sidecar's path, for messages).
    """
    side = Path(path).with_suffix(".json")
    if not side.is_file() or side == Path(path):
        return {}
    name = str(side)
    try:
        raw = json.loads(side.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise InputError(f"sidecar is not valid JSON ({exc})", name) from None
    if not isinstance(raw, dict):
        raise InputError(f"sidecar must hold a JSON object, got {type(raw).__name__}", name)
    vert: dict[str, Any] = raw["vertical"] if isinstance(raw.get("vertical"), dict) else {}
    hor: dict[str, Any] = raw["horizontal"] if isinstance(raw.get("horizontal"), dict) else {}

    def pick(flat: str, nested: dict[str, Any], key: str) -> Any:
        return raw[flat] if raw.get(flat) is not None else nested.get(key)

    out: dict[str, Any] = {}
    if (v := pick("spacing_m", hor, "spacing_m")) is not None:
        out["spacing_m"] = spacing_pair(v, name)
    if (v := pick("vertical_scale", vert, "scale_m_per_unit")) is not None:
        out["vertical_scale"] = _opt_float(v, "vertical_scale", name)
    if (v := pick("vertical_offset", vert, "offset_m")) is not None:
        out["vertical_offset"] = _opt_float(v, "vertical_offset", name)
    enc = raw.get("encoding")
    if isinstance(enc, dict):
        enc = enc.get("name")
    if enc is not None:
        out["encoding"] = normalise_encoding(enc, name)
    if (v := pick("tile", hor, "tile")) is not None:
        out["tile"] = _tile(v, name)
    if raw.get("nodata") is not None:
        try:
            out["nodata"] = float(raw["nodata"])
        except (TypeError, ValueError):
            raise InputError(
                f'sidecar nodata must be a number or "NaN", got {raw["nodata"]!r}', name
            ) from None
    if (v := pick("crs", hor, "crs")) is not None:
        if not isinstance(v, str):
            raise InputError(f'sidecar crs must be a string such as "EPSG:32610", got {v!r}', name)
        out["crs"] = v
    for key in ("transform", "origin_m", "bounds"):
        if (v := pick(key, hor, key)) is not None:
            out[key] = _numbers(v, key, name)
    t = out.get("transform")
    if t is not None and len(t) == 2:  # an origin given under "transform"
        out["origin_m"] = out.pop("transform")
    for key, n in (("transform", 6), ("origin_m", 2), ("bounds", 4)):
        if key in out and len(out[key]) != n:
            raise InputError(f"sidecar {key} must hold {n} numbers, got {len(out[key])}", name)
    out["_sidecar"] = name
    return out


def normalise_encoding(encoding: str, source: str | None = None) -> str:
    """Canonical encoding name ("terrain-rgb" or "terrarium") of a user-written one."""
    key = str(encoding).strip().lower().replace("_", "-").replace(" ", "-")
    if key not in _ENCODING_ALIASES:
        raise InputError(f"unknown encoding {encoding!r}; expected one of {', '.join(ENCODINGS)}", source)
    return _ENCODING_ALIASES[key]


def spacing_pair(spacing: Any, source: str | None = None) -> tuple[float, float]:
    """(dx, dy) metres from a number or a pair; refuses non-positive or non-finite values."""
    try:
        if isinstance(spacing, str):
            spacing = [float(s) for s in spacing.replace(",", " ").split()]
        if np.ndim(spacing) == 0:
            dx = dy = float(spacing)
        else:
            dx, dy = (float(v) for v in spacing)
    except (TypeError, ValueError):
        raise InputError(f"spacing must be a number or (dx, dy) in metres, got {spacing!r}", source) from None
    if not (dx > 0 and dy > 0 and math.isfinite(dx) and math.isfinite(dy)):
        raise InputError(f"spacing must be positive, finite metres, got {spacing!r}", source)
    return dx, dy


# -- helpers -------------------------------------------------------------------------------------------
def _hints(opts: dict[str, Any], src: str) -> FrameHints:
    crs = opts.get("crs")
    if crs is not None:
        placed = any(opts.get(k) is not None for k in ("transform", "origin_m", "bounds"))
        try:
            crs = _crs_text(crs, opts.get("_sidecar", src))
        except InputError:
            if placed:
                raise
            crs = None  # unused unless a raster without CRS brings its own transform: then unknown
    t = opts.get("transform")
    return FrameHints(
        spacing_m=opts.get("spacing_m"),
        crs=crs,
        transform=None if t is None else Affine.from_gdal(*t),
        origin_m=None if opts.get("origin_m") is None else tuple(opts["origin_m"]),
        bounds=None if opts.get("bounds") is None else tuple(opts["bounds"]),
        tile=opts.get("tile"),
    )


def _crs_text(crs: str, where: str) -> str:
    """A CRS string rasterio understands: as given, or the "EPSG:<code>" it mentions."""
    from rasterio.crs import CRS

    try:
        CRS.from_user_input(crs)
        return crs
    except Exception:  # rasterio raises CRSError, ValueError or TypeError on malformed text
        m = re.search(r"EPSG\s*:\s*(\d+)", crs, re.IGNORECASE)
        if m:
            return f"EPSG:{m.group(1)}"
    raise InputError(f'crs {crs[:80]!r} is not understood (expected e.g. "EPSG:32610" or WKT)', where)


def _tile(tile: Any, source: str) -> tuple[int, int, int]:
    try:
        if isinstance(tile, dict):
            vals = [tile["z"], tile["x"], tile["y"]]
        elif isinstance(tile, str):
            vals = tile.replace(",", "/").split("/")
        else:
            vals = list(tile)
        if len(vals) != 3:
            raise ValueError
        z, x, y = (int(v) for v in vals)
    except (TypeError, ValueError, KeyError):
        raise InputError(f"tile must be (z, x, y) integers, got {tile!r}", source) from None
    if not (0 <= z <= 30 and 0 <= x < 2**z and 0 <= y < 2**z):
        raise InputError(
            f"tile z/x/y = {z}/{x}/{y} is not a valid XYZ tile (expected 0 <= x, y < 2**z)", source
        )
    return z, x, y


def _opt_float(value: Any, name: str, source: str) -> float | None:
    if value is None:
        return None
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a number, got {value!r}", source) from None
    if not math.isfinite(v):
        raise InputError(f"{name} must be finite, got {value!r}", source)
    return v


def _numbers(value: Any, key: str, source: str) -> list[float]:
    try:
        out = [float(v) for v in value]
    except (TypeError, ValueError):
        raise InputError(f"sidecar {key} must be a list of numbers, got {value!r}", source) from None
    if not all(math.isfinite(v) for v in out):
        raise InputError(f"sidecar {key} must hold finite numbers, got {value!r}", source)
    return out
