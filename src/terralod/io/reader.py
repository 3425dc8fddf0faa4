"""Heightfield readers: GeoTIFF/COG and any GDAL raster (rasterio), 8/16-bit PNG heightmaps, Mapbox
Terrain-RGB and Terrarium PNG/WebP tiles, ``.npy``/``.npz`` arrays, and the bundled sample DEM.

World frame (DESIGN.md): metres, x east, y north, sample (row, col) at its pixel centre, row 0 north.

- Projected CRS in metres: its own coordinates. Projected CRS in feet: x/y scaled to metres (the CRS is
  then recorded as WKT with a note, since the coordinates are no longer the CRS's own units).
- Geographic CRS and web-mercator (EPSG:3857, whose metres are not ground metres): reprojected once,
  bilinearly, to the UTM zone of the raster's centre, with square pixels of the ground spacing at the
  centre (the smaller of dx, dy); the nodata mask is reprojected with nearest-neighbour. Degrees are
  never taken for metres.
- Un-georeferenced heightmaps need a spacing in metres (argument or sidecar); their frame is local
  (origin at the north-west pixel corner, no CRS).

Sidecar JSON (``<stem>.json`` beside a PNG/WebP/NPY/NPZ file; explicit arguments win). Flat keys:
``spacing_m`` (number or [dx, dy]), ``vertical_scale``, ``vertical_offset``, ``encoding``
("terrain-rgb" | "terrarium"), ``tile`` ([z, x, y] or {"z", "x", "y"}), ``nodata``, ``crs``,
``transform`` (GDAL geotransform, 6 numbers). The nested layout of ``../shared/data`` sidecars is read
too: ``vertical.scale_m_per_unit``, ``vertical.offset_m``, ``horizontal.spacing_m``,
``horizontal.tile``, ``horizontal.crs``, ``encoding.name``.
"""

from __future__ import annotations

import json
import math
import os
import warnings
from pathlib import Path
from typing import Any

import numpy as np
from affine import Affine

from terralod.errors import InputError, InputNotFoundError
from terralod.heightfield import Heightfield
from terralod.io.fill import check_dimensions, prepare_elevation

_EARTH_CIRCUMFERENCE_M = 40075016.686
_IMAGE_SUFFIXES = {".png", ".webp"}
_ARRAY_SUFFIXES = {".npy", ".npz"}


# -- sidecar -------------------------------------------------------------------------------------------
def read_sidecar(path: Path) -> dict[str, Any]:
    """Normalised keys of ``<stem>.json`` beside ``path`` (empty dict when there is none)."""
    side = path.with_suffix(".json")
    if not side.exists():
        return {}
    try:
        raw = json.loads(side.read_text())
    except (OSError, ValueError) as exc:
        raise InputError(f"sidecar {side.name} is not valid JSON ({exc})", str(path)) from None
    out: dict[str, Any] = {}
    for key in (
        "spacing_m",
        "vertical_scale",
        "vertical_offset",
        "encoding",
        "tile",
        "nodata",
        "crs",
        "transform",
    ):
        if raw.get(key) is not None:
            out[key] = raw[key]
    vert = raw.get("vertical") if isinstance(raw.get("vertical"), dict) else {}
    hor = raw.get("horizontal") if isinstance(raw.get("horizontal"), dict) else {}
    enc = raw.get("encoding")
    if isinstance(enc, dict):
        out["encoding"] = enc.get("name")
    if "scale_m_per_unit" in vert:
        out.setdefault("vertical_scale", vert["scale_m_per_unit"])
    if "offset_m" in vert:
        out.setdefault("vertical_offset", vert["offset_m"])
    if hor.get("spacing_m") is not None:
        out.setdefault("spacing_m", hor["spacing_m"])
    if hor.get("tile") is not None:
        out.setdefault("tile", hor["tile"])
    if hor.get("crs") and "crs" not in out:
        out["crs"] = hor["crs"]
    if isinstance(out.get("encoding"), str):
        e = out["encoding"].lower().replace("_", "-")
        out["encoding"] = {
            "terrarium": "terrarium",
            "terrain-rgb": "terrain-rgb",
            "mapbox": "terrain-rgb",
        }.get(e, e)
    if isinstance(out.get("tile"), dict):
        t = out["tile"]
        out["tile"] = (int(t["z"]), int(t["x"]), int(t["y"]))
    return out


def _spacing_pair(spacing: Any, path: Path) -> tuple[float, float]:
    try:
        if np.isscalar(spacing):
            dx = dy = float(spacing)
        else:
            dx, dy = (float(v) for v in spacing)
    except (TypeError, ValueError):
        raise InputError(
            f"spacing must be a number or (dx, dy) in metres, got {spacing!r}", str(path)
        ) from None
    if not (dx > 0 and dy > 0 and math.isfinite(dx) and math.isfinite(dy)):
        raise InputError(f"spacing must be positive metres, got {spacing!r}", str(path))
    return dx, dy


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
) -> Heightfield:
    """Read a DEM into a :class:`Heightfield` (elevation metres, metric world frame, nodata mask).

    Parameters
    ----------
    path : GeoTIFF/COG (any raster GDAL reads), PNG/WebP heightmap or encoded tile, .npy/.npz
    vertical_scale, vertical_offset : elevation_m = value * scale + offset (heightmaps and arrays)
    spacing_m : ground spacing (dx, dy) in metres for un-georeferenced inputs
    encoding : "terrain-rgb" (Mapbox) or "terrarium" for RGB-encoded tiles
    tile : (z, x, y) XYZ web-map tile address, which georeferences an encoded tile
    band : raster band (1-based)
    """
    p = Path(path)
    if not p.exists():
        raise InputNotFoundError("file not found", str(p))
    if p.is_dir():
        raise InputError("is a directory, not a DEM file", str(p))
    suffix = p.suffix.lower()
    opts = {"vertical_scale": vertical_scale, "vertical_offset": vertical_offset, "spacing_m": spacing_m,
            "encoding": encoding, "tile": tile}  # fmt: skip
    if suffix in _IMAGE_SUFFIXES or suffix in _ARRAY_SUFFIXES:
        side = read_sidecar(p)
        for k, v in side.items():
            if opts.get(k) is None:
                opts[k] = v
        if suffix in _ARRAY_SUFFIXES:
            return _read_array(p, opts, side)
        return _read_image(p, opts, side)
    return _read_raster(p, band, opts)


def sample_heightfield() -> Heightfield:
    """matplotlib's bundled real DEM: the Jacksboro fault, Tennessee (344 x 403 samples, 3 arc-seconds,
    USGS), reprojected to UTM zone 17N (~74 m square pixels)."""
    from matplotlib import cbook

    d = cbook.get_sample_data("jacksboro_fault_dem.npz")
    z = np.asarray(d["elevation"], dtype=np.float64)
    west, east = float(d["xmin"]), float(d["xmax"])
    north = max(float(d["ymin"]), float(d["ymax"]))
    dx_deg, dy_deg = float(d["dx"]), float(d["dy"])
    # pixel-corner transform: the file's extent holds W-1 steps between sample centres
    t = Affine(dx_deg, 0.0, west - 0.5 * dx_deg, 0.0, -dy_deg, north + 0.5 * dy_deg)
    assert abs((east - west) / dx_deg - (z.shape[1] - 1)) < 1.0
    return _georeferenced(
        z, np.ones(z.shape, bool), t, "EPSG:4326", "matplotlib sample_data/jacksboro_fault_dem.npz"
    )


# -- rasters (GDAL) ------------------------------------------------------------------------------------
def _read_raster(p: Path, band: int, opts: dict[str, Any]) -> Heightfield:
    import rasterio
    from rasterio.errors import RasterioIOError

    src = str(p)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ds = rasterio.open(p)
    except RasterioIOError as exc:
        raise InputError(f"not a raster GDAL can read ({str(exc).splitlines()[0][:120]})", src) from None
    with ds:
        check_dimensions(ds.height, ds.width, src)
        if not 1 <= band <= ds.count:
            raise InputError(f"has {ds.count} band(s), band {band} requested", src)
        try:
            z = ds.read(band, masked=True)
        except (RasterioIOError, MemoryError) as exc:
            raise InputError(f"cannot read band {band} ({exc})", src) from None
        valid = ~np.ma.getmaskarray(z)
        values = np.ma.getdata(z).astype(np.float64)
        scale = ds.scales[band - 1] if ds.scales else 1.0
        offset = ds.offsets[band - 1] if ds.offsets else 0.0
        if opts.get("vertical_scale") is not None:
            scale = float(opts["vertical_scale"])
        if opts.get("vertical_offset") is not None:
            offset = float(opts["vertical_offset"])
        values = values * scale + offset
        t = ds.transform
        crs = ds.crs
    if t.b != 0 or t.d != 0:
        raise InputError("has a rotated or sheared geotransform; warp it north-up first (gdalwarp)", src)
    if t.is_identity or crs is None:
        if opts.get("spacing_m") is None:
            raise InputError("has no georeferencing; pass --spacing DX[,DY] in metres", src)
        dx, dy = _spacing_pair(opts["spacing_m"], p)
        return _local(values, valid, dx, dy, src)
    if t.e > 0:  # south-up: flip to row 0 north
        values, valid = values[::-1], valid[::-1]
        t = Affine(t.a, 0.0, t.c, 0.0, -t.e, t.f + t.e * values.shape[0])
    if t.a < 0:
        values, valid = values[:, ::-1], valid[:, ::-1]
        t = Affine(-t.a, 0.0, t.c + t.a * values.shape[1], 0.0, t.e, t.f)
    return _georeferenced(values, valid, t, crs, src)


def _georeferenced(values: np.ndarray, valid: np.ndarray, t: Affine, crs: Any, src: str) -> Heightfield:
    """Build a Heightfield in a metric frame from a georeferenced grid (reprojecting when needed)."""
    from rasterio.crs import CRS

    crs = CRS.from_user_input(crs)
    notes: list[str] = []
    if crs.is_geographic or crs.to_epsg() == 3857:
        values, valid, t, crs, note = _to_utm(values, valid, t, crs, src)
        notes.append(note)
    else:
        unit = (crs.linear_units or "metre").lower()
        factor = (
            crs.linear_units_factor[1] if unit not in ("metre", "meter", "m", "metres", "meters") else 1.0
        )
        if factor != 1.0:
            t = Affine(t.a * factor, 0.0, t.c * factor, 0.0, t.e * factor, t.f * factor)
            notes.append(f"horizontal coordinates converted from {unit} to metres (x {factor})")
    z, ok, how = prepare_elevation(values, valid, src)
    return Heightfield(z, ok, t, crs=crs.to_wkt(), source=src, fill_method=how, notes=tuple(notes))


def _to_utm(values: np.ndarray, valid: np.ndarray, t: Affine, crs: Any, src: str):
    from rasterio.crs import CRS
    from rasterio.warp import Resampling, reproject, transform_bounds

    h, w = values.shape
    west, south, east, north = transform_bounds(crs, "EPSG:4326", t.c, t.f + h * t.e, t.c + w * t.a, t.f)
    lon, lat = (west + east) / 2, (south + north) / 2
    zone = int(min(max((lon + 180.0) // 6 + 1, 1), 60))
    epsg = (32600 if lat >= 0 else 32700) + zone
    dst_crs = CRS.from_epsg(epsg)
    # ground spacing at the centre, from the source pixel's geodesic size
    cx, cy = t.c + (w / 2) * t.a, t.f + (h / 2) * t.e
    from rasterio.warp import transform as warp_pts

    xs, ys = warp_pts(crs, dst_crs, [cx, cx + t.a, cx], [cy, cy, cy + t.e])
    dx_m = math.hypot(xs[1] - xs[0], ys[1] - ys[0])
    dy_m = math.hypot(xs[2] - xs[0], ys[2] - ys[0])
    res = min(dx_m, dy_m)
    bx0, by0, bx1, by1 = transform_bounds(
        crs, dst_crs, t.c, t.f + h * t.e, t.c + w * t.a, t.f, densify_pts=51
    )
    width = max(2, int(math.ceil((bx1 - bx0) / res)))
    height = max(2, int(math.ceil((by1 - by0) / res)))
    check_dimensions(height, width, src)
    dst_t = Affine(res, 0.0, bx0, 0.0, -res, by1)
    src_vals = np.where(valid, values, np.nan).astype(np.float64)
    out = np.full((height, width), np.nan, np.float64)
    reproject(src_vals, out, src_transform=t, src_crs=crs, dst_transform=dst_t, dst_crs=dst_crs,
              resampling=Resampling.bilinear, src_nodata=np.nan, dst_nodata=np.nan)  # fmt: skip
    mask = np.zeros((height, width), np.uint8)
    reproject(valid.astype(np.uint8), mask, src_transform=t, src_crs=crs, dst_transform=dst_t, dst_crs=dst_crs,
              resampling=Resampling.nearest, src_nodata=None, dst_nodata=0)  # fmt: skip
    ok = (mask > 0) & np.isfinite(out)
    name = f"EPSG:{crs.to_epsg()}" if crs.to_epsg() else crs.to_string()
    note = f"reprojected from {name} to EPSG:{epsg} (UTM {zone}{'N' if lat >= 0 else 'S'}) at {res:.2f} m, bilinear"
    return out, ok, dst_t, dst_crs, note


def _local(values: np.ndarray, valid: np.ndarray, dx: float, dy: float, src: str) -> Heightfield:
    z, ok, how = prepare_elevation(values, valid, src)
    t = Affine(dx, 0.0, 0.0, 0.0, -dy, 0.0)
    return Heightfield(
        z, ok, t, crs=None, source=src, fill_method=how, notes=("no georeferencing: local metric frame",)
    )


# -- images and arrays ---------------------------------------------------------------------------------
def _decode_rgb(rgb: np.ndarray, encoding: str, src: str) -> np.ndarray:
    r, g, b = (rgb[..., k].astype(np.float64) for k in range(3))
    if encoding == "terrain-rgb":
        return -10000.0 + (r * 65536.0 + g * 256.0 + b) * 0.1
    if encoding == "terrarium":
        return r * 256.0 + g + b / 256.0 - 32768.0
    raise InputError(f"unknown encoding {encoding!r}; expected terrain-rgb or terrarium", src)


def _read_image(p: Path, opts: dict[str, Any], side: dict[str, Any]) -> Heightfield:
    from PIL import Image, UnidentifiedImageError

    src = str(p)
    try:
        with Image.open(p) as im:
            check_dimensions(im.height, im.width, src)
            mode = im.mode
            enc = opts.get("encoding")
            if enc:
                values = _decode_rgb(np.asarray(im.convert("RGB")), enc, src)
            elif mode in ("I;16", "I;16B", "I;16L", "I", "L", "F"):
                values = np.asarray(im).astype(np.float64)
            elif mode in ("LA", "P"):
                values = np.asarray(im.convert("L")).astype(np.float64)
            else:
                raise InputError(
                    f"is a {mode} image; pass --encoding terrain-rgb|terrarium for RGB elevation tiles", src
                )
    except UnidentifiedImageError:
        raise InputError("not a PNG/WebP image Pillow can decode", src) from None
    except OSError as exc:
        raise InputError(f"cannot decode image ({exc})", src) from None
    if not opts.get("encoding"):
        values = values * float(opts.get("vertical_scale") or 1.0) + float(opts.get("vertical_offset") or 0.0)
    valid = np.isfinite(values)
    if side.get("nodata") is not None and not opts.get("encoding"):
        valid &= values != float(side["nodata"]) * float(opts.get("vertical_scale") or 1.0) + float(
            opts.get("vertical_offset") or 0.0
        )
    tile = opts.get("tile")
    if tile is not None:
        z, x, y = (int(v) for v in tile)
        size = _EARTH_CIRCUMFERENCE_M / 2**z
        h, w = values.shape
        left = -_EARTH_CIRCUMFERENCE_M / 2 + x * size
        top = _EARTH_CIRCUMFERENCE_M / 2 - y * size
        t = Affine(size / w, 0.0, left, 0.0, -size / h, top)
        return _georeferenced(values, valid, t, "EPSG:3857", src)
    if opts.get("spacing_m") is None:
        raise InputError("has no georeferencing; pass --spacing DX[,DY] in metres (or a .json sidecar)", src)
    dx, dy = _spacing_pair(opts["spacing_m"], p)
    return _local(values, valid, dx, dy, src)


def _read_array(p: Path, opts: dict[str, Any], side: dict[str, Any]) -> Heightfield:
    src = str(p)
    try:
        data = np.load(p, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise InputError(f"not a NumPy array file ({exc})", src) from None
    if isinstance(data, np.lib.npyio.NpzFile):
        with data:
            key = "elevation" if "elevation" in data.files else (data.files[0] if data.files else None)
            if key is None:
                raise InputError("holds no arrays", src)
            values = np.asarray(data[key])
    else:
        values = np.asarray(data)
    if values.ndim != 2 or not np.issubdtype(values.dtype, np.number):
        raise InputError(f"expected a 2-D numeric array, got {values.dtype} {values.shape}", src)
    values = values.astype(np.float64) * float(opts.get("vertical_scale") or 1.0) + float(
        opts.get("vertical_offset") or 0.0
    )
    valid = np.isfinite(values)
    if side.get("nodata") is not None:
        valid &= np.asarray(data if not isinstance(data, np.lib.npyio.NpzFile) else values) != float(
            side["nodata"]
        )
    if side.get("transform") is not None and side.get("crs"):
        g = [float(v) for v in side["transform"]]
        return _georeferenced(values, valid, Affine.from_gdal(*g), side["crs"], src)
    if opts.get("spacing_m") is None:
        raise InputError("has no georeferencing; pass --spacing DX[,DY] in metres (or a .json sidecar)", src)
    dx, dy = _spacing_pair(opts["spacing_m"], p)
    return _local(values, valid, dx, dy, src)
