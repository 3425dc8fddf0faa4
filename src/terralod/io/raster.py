"""GDAL rasters (GeoTIFF, COG, .hgt, VRT, anything rasterio opens) and the one place where a
georeferenced grid becomes the metric world frame of a :class:`~terralod.heightfield.Heightfield`.

World frame (DESIGN.md): metres, x east, y north, z up; row 0 is the north edge; the transform is
north-up and axis-aligned. How each kind of georeferencing gets there:

- **Projected CRS in metres**: the CRS's own coordinates, unchanged (no resampling).
- **Projected CRS in feet** (international or US survey foot, any non-metre linear unit): x/y are
  multiplied by the unit's size in metres and the CRS is re-expressed as the same projection with metre
  axes (:func:`terralod.io.georef.metric_crs`: datum and parameters kept, checked by transforming a point
  through both; refused when that check fails). Elevations follow the CRS's *vertical* axis only: a
  compound CRS whose vertical part is in feet scales them (unless ``vertical_scale`` or a band scale tag is
  given); a horizontal CRS in feet says nothing of heights, so pass ``vertical_scale=0.3048`` for foot
  elevations there.
- **Area of use**: coordinates far outside the CRS's area of use (a unit mix-up, usually) are refused
  (:func:`terralod.io.georef.check_area_of_use`), a CRS with no transformation to WGS 84 too.
- **Geographic CRS** (degrees) and **Mercator** projections (EPSG:3857 web mercator, EPSG:3395), whose
  'metres' are not ground metres away from the equator: reprojected *once* with
  :func:`rasterio.warp.reproject` to the UTM zone of the raster's centre (north/south by latitude; UPS
  beyond 84 N / 80 S), bilinear, on square pixels whose size is the ground spacing at the centre (the
  smaller of dx, dy, on the WGS84 ellipsoid, rounded to the millimetre), on a grid snapped to multiples of
  that size. The nodata mask is reprojected with nearest neighbour; cells outside the source footprint
  are nodata. Rasters wider than 20 degrees of longitude are refused (one UTM zone would distort them by
  more than ~1.5 %). Degrees are never taken for metres.
- **No CRS**: the grid needs a spacing (argument or sidecar) and lives in a local frame with its origin at
  the north-west pixel corner; a geotransform without a CRS is not trusted (it might be in degrees).

Rotated or sheared geotransforms are refused; south-up (and east-to-west) grids are flipped to row 0
north. Every conversion is recorded in ``Heightfield.notes``.
"""

from __future__ import annotations

import logging
import math
import os
import sys
import tempfile
import warnings
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from affine import Affine

from terralod.errors import InputError
from terralod.fill import check_dimensions, prepare_elevation
from terralod.heightfield import Heightfield
from terralod.io.encodings import decode_rgb
from terralod.io.georef import assign_crs, check_area_of_use, crs_summary, metric_crs

#: Web-mercator (EPSG:3857) world width, metres: one XYZ tile at zoom z spans this / 2**z.
EARTH_CIRCUMFERENCE_M = 40075016.686
#: WGS84 semi-major axis (m) and first eccentricity squared, for ground spacings on the ellipsoid.
WGS84_A_M = 6378137.0
WGS84_E2 = 0.00669437999014
#: Largest growth of the sample count the one reprojection to UTM may cause (square pixels of the smaller
#: ground spacing): beyond it the raster is refused (e.g. 50x50 degrees-pixels at 89.5 N became 23 M).
MAX_REPROJECT_GROWTH = 16.0
#: Widest raster (degrees of longitude) reprojected into a single UTM zone.
MAX_UTM_SPAN_DEG = 20.0
#: A projected CRS whose grid metres differ from ground metres by more than this gets a note.
SCALE_NOTE_TOLERANCE = 0.01
#: Resampling names recorded in notes.
_RESAMPLING = "bilinear"


@dataclass(frozen=True)
class FrameHints:
    """Georeferencing given from outside the data file (arguments, sidecar), used when the file has none.

    Attributes
    ----------
    spacing_m : (dx, dy) ground spacing in metres, or None.
    crs : CRS of ``transform`` / ``origin_m`` / ``bounds`` (anything ``rasterio.crs.CRS.from_user_input``
        reads), or None for a local metric frame.
    transform : pixel-corner affine transform (may be south-up), in ``crs`` units or local metres.
    origin_m : (west, north) pixel corner of sample (0, 0); used with ``spacing_m``.
    bounds : (west, south, east, north) of the pixel footprint in ``crs`` units.
    tile : (z, x, y) XYZ web-map tile (y down from the north), georeferencing in EPSG:3857.
    """

    spacing_m: tuple[float, float] | None = None
    crs: str | None = None
    transform: Affine | None = None
    origin_m: tuple[float, float] | None = None
    bounds: tuple[float, float, float, float] | None = None
    tile: tuple[int, int, int] | None = None


@dataclass(frozen=True, eq=False)
class OriginalGrid:
    """A source's own samples, kept beside the grid they were resampled to (``Heightfield.original_grid``):
    what every stored error of a store built from a reprojected DEM is measured against
    (:mod:`terralod.pyramid.original`), never the resampled grid alone.

    Attributes
    ----------
    values : (H, W) float64 elevations, metres, as read (scale and offset applied; nodata cells arbitrary).
    valid : (H, W) bool, False at the source's nodata.
    transform : north-up pixel-corner affine transform, in ``crs`` units (row 0 north).
    crs : WKT of the source's CRS (geographic, or a Mercator projection).
    source : the file the samples were read from.
    """

    values: np.ndarray
    valid: np.ndarray
    transform: Affine
    crs: str
    source: str

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, cols) of the source grid."""
        h, w = self.values.shape
        return int(h), int(w)

    @property
    def n_valid(self) -> int:
        """Valid samples of the source."""
        return int(np.count_nonzero(self.valid))

    def window(self, r0: int, r1: int, c0: int, c1: int) -> tuple[np.ndarray, np.ndarray]:
        """(values, valid) of rows ``r0 <= r < r1``, columns ``c0 <= c < c1`` (clipped to the grid): the
        one read verb (a windowed reader of the file, e.g. :class:`terralod.io.region.RegionReader`, has
        the same)."""
        h, w = self.values.shape
        r0, r1 = max(0, r0), min(h, r1)
        c0, c1 = max(0, c0), min(w, c1)
        return self.values[r0:r1, c0:c1], self.valid[r0:r1, c0:c1]


# -- GDAL rasters --------------------------------------------------------------------------------------
def read_raster(
    path: str | Path,
    *,
    band: int = 1,
    vertical_scale: float | None = None,
    vertical_offset: float | None = None,
    encoding: str | None = None,
    nodata: float | None = None,
    hints: FrameHints | None = None,
    notes: tuple[str, ...] = (),
    crs: Any = None,
) -> Heightfield:
    """Read one band of a raster GDAL can open into a metric :class:`Heightfield`.

    Parameters
    ----------
    path : raster file (GeoTIFF, COG, .hgt, VRT, ...).
    band : 1-based band index.
    vertical_scale, vertical_offset : elevation_m = value * scale + offset; default to the band's scale
        and offset tags (1 and 0 when absent).
    encoding : "terrain-rgb" or "terrarium" to decode bands 1-3 as an RGB-encoded elevation raster.
    nodata : stored value that marks missing samples, used only when the band has no nodata of its own.
    hints : georeferencing used only when the file has no CRS (see :class:`FrameHints`).
    notes : notes carried into the Heightfield (e.g. which sidecar was read).
    crs : a CRS (EPSG code, WKT, PROJ string) that assigns or overrides the file's own (CLI ``--crs``).

    Returns
    -------
    Heightfield, elevations in metres, row 0 north, nodata cells filled and marked in ``valid``.
    """
    import rasterio
    from rasterio.errors import NotGeoreferencedWarning

    src = str(path)
    hints = hints or FrameHints()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", NotGeoreferencedWarning)
            ds = rasterio.open(path)
    except Exception as exc:  # GDAL raises several unrelated classes; all mean "cannot read this file"
        raise InputError(f"not a raster GDAL can read ({error_line(exc)})", src) from None
    given = crs
    with ds:
        check_dimensions(ds.height, ds.width, src)
        t, crs = ds.transform, ds.crs
        if given is not None:
            crs, given_note = assign_crs(given, crs, src)
            notes = (*notes, given_note)
        has_transform = not t.is_identity
        if has_transform and (t.b != 0 or t.d != 0):
            raise InputError(
                f"has a rotated or sheared geotransform {tuple(t)[:6]}; warp it north-up first "
                "(gdalwarp -t_srs <its CRS>)",
                src,
            )
        if not has_transform and ds.gcps[0]:
            raise InputError(
                "is georeferenced by ground control points only; warp it to a grid first (gdalwarp)", src
            )
        bands = [1, 2, 3] if encoding else [band]
        if max(bands) > ds.count or min(bands) < 1:
            want = "3 bands (R, G, B) for an encoded raster" if encoding else f"band {band}"
            raise InputError(f"has {ds.count} band(s); {want} requested", src)
        kind = np.dtype(ds.dtypes[bands[0] - 1]).kind
        if kind not in "iuf":
            raise InputError(
                f"band {bands[0]} holds {ds.dtypes[bands[0] - 1]} values; elevations must be real numbers",
                src,
            )
        file_nodata = ds.nodatavals[bands[0] - 1]
        scale_tag = (ds.scales or (1.0,) * ds.count)[bands[0] - 1]
        offset_tag = (ds.offsets or (0.0,) * ds.count)[bands[0] - 1]
        try:
            data = ds.read(bands if encoding else band, masked=True)
        except MemoryError:
            raise InputError(f"{ds.width}x{ds.height} samples do not fit in memory", src) from None
        except Exception as exc:
            raise InputError(f"cannot read band {band} ({error_line(exc)})", src) from None
    mask = np.ma.getmaskarray(data)
    raw = np.ma.getdata(data)
    if encoding:
        values = decode_rgb(np.moveaxis(raw, 0, -1), encoding, src)
        valid = ~mask.any(axis=0)
        notes = (*notes, f"decoded {encoding} RGB bands 1-3")
    else:
        values = raw.astype(np.float64)
        valid = ~mask
        if file_nodata is None and nodata is not None and not math.isnan(nodata):
            valid &= raw != nodata
    scale = float(vertical_scale) if vertical_scale is not None else float(scale_tag or 1.0)
    offset = float(vertical_offset) if vertical_offset is not None else float(offset_tag or 0.0)
    vunit = vertical_unit_m(crs) if has_transform else None
    if vunit is not None and vertical_scale is None and scale == 1.0:
        scale = vunit[1]  # heights in the unit the CRS's vertical axis names
        notes = (*notes, f"heights in {vunit[0]} (the CRS's vertical axis): x {vunit[1]:.10g} to metres")
    values, note = apply_vertical(values, scale, offset, src)
    notes = (*notes, *note)

    if crs is not None and has_transform:
        return georeferenced_heightfield(values, valid, t, crs, src, notes=notes)
    # no CRS (or no transform): only the caller's hints can place it
    if hints.crs is not None and hints.transform is None and has_transform:
        hints = replace(hints, transform=t)
    elif has_transform and hints.crs is None and hints.transform is None:
        if hints.spacing_m is None:
            raise InputError(
                "has a geotransform but no CRS, so its units (metres? degrees?) are unknown; give it a "
                "CRS, or pass spacing_m (CLI --spacing DX[,DY]) in metres for a local frame",
                src,
            )
        notes = (*notes, "geotransform ignored: the file has no CRS")
    return place_heightfield(values, valid, src, hints, notes=notes)


@contextmanager
def atomic_file(out: Path) -> Iterator[Path]:
    """A temporary path beside ``out`` (``.NAME.PID.tmp``), renamed over ``out`` when the block ends and
    removed when it raises: a full disk or a kill never leaves a truncated output. The removal never
    raises (on a read-only file system even unlinking a missing file fails; the write's error matters)."""
    tmp = out.with_name(f".{out.name}.{os.getpid()}.tmp")
    try:
        yield tmp
        os.replace(tmp, out)
    except BaseException:
        with suppress(OSError):  # the error that propagates is the write's
            tmp.unlink(missing_ok=True)
        raise


@contextmanager
def c_stderr_captured() -> Iterator[list[str]]:
    """Collect what C libraries write straight to file descriptor 2 (libtiff prints some errors itself,
    before any ``terralod:`` line could): yields a list filled with those lines on exit; they are logged at
    INFO (shown with ``-v``) and callers may add the first one to their message."""
    lines: list[str] = []
    try:
        buf = tempfile.TemporaryFile()
        saved = os.dup(2)
    except OSError:
        yield lines
        return
    sys.stderr.flush()
    os.dup2(buf.fileno(), 2)
    try:
        yield lines
    finally:
        sys.stderr.flush()
        os.dup2(saved, 2)
        os.close(saved)
        buf.seek(0)
        lines.extend(ln for ln in buf.read().decode("utf-8", "replace").splitlines() if ln.strip())
        buf.close()
        for ln in lines:
            logging.getLogger("terralod.io.gdal").info("%s", ln)


def error_line(exc: BaseException) -> str:
    """First line of an exception's message (at most 160 characters), for wrapping library errors.

    rasterio's "Read failed. See previous exception for details." carries the real cause (GDAL's message)
    as ``__cause__``/``__context__``: that one is given instead."""
    seen = 0
    while "previous exception" in str(exc) and seen < 8:
        nxt = exc.__cause__ or exc.__context__
        if nxt is None:
            break
        exc, seen = nxt, seen + 1
    text = str(exc).strip().splitlines()
    return (text[0] if text else type(exc).__name__)[:160]


def apply_vertical(
    values: np.ndarray, scale: float, offset: float, source: str
) -> tuple[np.ndarray, tuple[str, ...]]:
    """``values * scale + offset`` (metres) in place on a float64 array; returns it and a note unless
    the scale is 1 and the offset 0."""
    if not (math.isfinite(scale) and math.isfinite(offset)) or scale == 0.0:
        raise InputError(
            f"vertical scale and offset must be finite and the scale non-zero, got {scale:g}, {offset:g}",
            source,
        )
    if scale == 1.0 and offset == 0.0:
        return values, ()
    values *= scale
    values += offset
    return values, (f"elevation_m = stored value * {scale:g} + {offset:g}",)


# -- placing a grid in the metric frame ----------------------------------------------------------------
def place_heightfield(
    values: np.ndarray,
    valid: np.ndarray,
    source: str,
    hints: FrameHints,
    *,
    notes: tuple[str, ...] = (),
) -> Heightfield:
    """Build a Heightfield from a grid whose georeferencing comes from ``hints``.

    Precedence: ``tile`` (EPSG:3857), then ``transform`` / ``bounds`` / ``origin_m`` with ``crs``, then a
    transform or origin without CRS (local metres), then ``spacing_m`` alone (local frame, origin at the
    north-west pixel corner). ``spacing_m`` is ignored (with a note) when the grid is georeferenced.
    """
    h, w = values.shape
    check_dimensions(h, w, source)
    t: Affine | None = None
    crs: Any = hints.crs
    if hints.tile is not None:
        t, crs = tile_transform_3857(*hints.tile, width=w, height=h, source=source), "EPSG:3857"
        notes = (*notes, "georeferenced as XYZ tile {}/{}/{} in EPSG:3857".format(*hints.tile))
    elif hints.transform is not None:
        t = hints.transform
    elif hints.bounds is not None:
        west, south, east, north = hints.bounds
        if not (east > west and north > south):
            raise InputError(f"bounds must be (west, south, east, north), got {hints.bounds}", source)
        t = Affine((east - west) / w, 0.0, west, 0.0, -(north - south) / h, north)
    elif hints.origin_m is not None and hints.spacing_m is not None:
        if crs is not None and _is_geographic(crs):
            raise InputError(
                "origin_m with spacing_m (metres) cannot place a grid in a geographic CRS; give a "
                "transform or bounds in degrees instead",
                source,
            )
        dx, dy = hints.spacing_m
        t = Affine(dx, 0.0, hints.origin_m[0], 0.0, -dy, hints.origin_m[1])
    if t is not None and crs is not None:
        hf = georeferenced_heightfield(values, valid, t, crs, source, notes=notes)
        if hints.spacing_m is not None and not np.allclose(hf.spacing_m, hints.spacing_m, rtol=0.01):
            hf = _with_notes(
                hf, f"spacing {_fmt_pair(hints.spacing_m)} m ignored: the input is georeferenced"
            )
        return hf
    if t is not None:  # our own sidecar transform without CRS: local metres by definition
        if t.b != 0 or t.d != 0:
            raise InputError(f"transform {tuple(t)[:6]} is rotated; expected north-up", source)
        values, valid, t, flips = north_up(values, valid, t, source)
        return _metric(values, valid, t, None, source, (*notes, *flips, "local metric frame (no CRS)"))
    if hints.crs is not None:
        notes = (*notes, "crs ignored: no transform, origin or bounds to place the grid with")
    if hints.spacing_m is None:
        raise InputError(
            "has no georeferencing and no spacing; pass spacing_m (CLI option --spacing DX[,DY], metres) "
            "or put a sidecar <stem>.json with spacing_m beside it",
            source,
        )
    dx, dy = hints.spacing_m
    t = Affine(dx, 0.0, 0.0, 0.0, -dy, 0.0)
    return _metric(
        values, valid, t, None, source, (*notes, f"local metric frame at {_fmt_pair((dx, dy))} m (no CRS)")
    )


def georeferenced_heightfield(
    values: np.ndarray,
    valid: np.ndarray,
    transform: Affine,
    crs: Any,
    source: str,
    *,
    notes: tuple[str, ...] = (),
) -> Heightfield:
    """Put a georeferenced grid in a metric frame (see the module docstring) and fill its nodata.

    Parameters
    ----------
    values : (H, W) float64 elevations, metres (nodata cells arbitrary).
    valid : (H, W) bool, False at nodata.
    transform : pixel-corner affine transform in ``crs`` units; south-up is flipped, rotation refused.
    crs : anything ``rasterio.crs.CRS.from_user_input`` accepts.
    source : file name for messages and ``Heightfield.source``.
    notes : notes carried into the Heightfield.
    """
    from rasterio.crs import CRS

    try:
        crs = CRS.from_user_input(crs)
    except Exception as exc:  # noqa: BLE001 - CRSError, and a SystemError on text PROJ's decoder chokes on (fuzzing)
        raise InputError(f"CRS {str(crs)[:80]!r} is not understood ({error_line(exc)})", source) from None
    t = transform
    if t.b != 0 or t.d != 0:
        raise InputError(
            f"has a rotated or sheared geotransform {tuple(t)[:6]}; warp it north-up first", source
        )
    values, valid, t, flips = north_up(values, valid, t, source)
    h, w = values.shape
    notes = (*notes, *flips, *check_area_of_use(crs, (t.c, t.f + h * t.e, t.c + w * t.a, t.f), source))
    if crs.is_geographic or _is_mercator(crs):
        original = OriginalGrid(values, valid, t, crs.to_wkt(), source)
        values, valid, t, crs, note, src_nodata, margin = reproject_to_utm(values, valid, t, crs, source)
        hf = _metric(values, valid, t, crs, source, (*notes, note))
        return replace(hf, source_nodata_fraction=src_nodata, margin_fraction=margin, original_grid=original)
    crs, t, unit_notes = _metric_units(crs, t, source)
    notes = (*notes, *unit_notes, *_scale_note(t, crs, values.shape))
    return _metric(values, valid, t, crs, source, notes)


def north_up(
    values: np.ndarray, valid: np.ndarray, t: Affine, source: str
) -> tuple[np.ndarray, np.ndarray, Affine, tuple[str, ...]]:
    """Flip a south-up (``e > 0``) or east-to-west (``a < 0``) grid so row 0 is north, column 0 west."""
    h, w = values.shape
    if not (t.a != 0 and t.e != 0 and math.isfinite(t.a) and math.isfinite(t.e)):
        raise InputError(f"geotransform {tuple(t)[:6]} has a zero or non-finite pixel size", source)
    notes: list[str] = []
    if t.e > 0:
        values, valid = values[::-1], valid[::-1]
        t = Affine(t.a, 0.0, t.c, 0.0, -t.e, t.f + t.e * h)
        notes.append("rows flipped: the source is south-up")
    if t.a < 0:
        values, valid = values[:, ::-1], valid[:, ::-1]
        t = Affine(-t.a, 0.0, t.c + t.a * w, 0.0, t.e, t.f)
        notes.append("columns flipped: the source runs east to west")
    return values, valid, t, tuple(notes)


def tile_transform_3857(
    z: int, x: int, y: int, *, width: int, height: int, source: str | None = None
) -> Affine:
    """Pixel-corner EPSG:3857 transform of XYZ tile (z, x, y), y counted down from the north, of
    ``width`` x ``height`` pixels. One tile spans ``EARTH_CIRCUMFERENCE_M / 2**z`` mercator metres."""
    if not (0 <= z <= 30 and 0 <= x < 2**z and 0 <= y < 2**z):
        raise InputError(
            f"tile z/x/y = {z}/{x}/{y} is not a valid XYZ tile (expected 0 <= x, y < 2**z, z <= 30)", source
        )
    size = EARTH_CIRCUMFERENCE_M / 2**z
    left = -EARTH_CIRCUMFERENCE_M / 2 + x * size
    top = EARTH_CIRCUMFERENCE_M / 2 - y * size
    return Affine(size / width, 0.0, left, 0.0, -size / height, top)


# -- CRS handling --------------------------------------------------------------------------------------
def _is_geographic(crs: Any) -> bool:
    from rasterio.crs import CRS

    try:
        return bool(CRS.from_user_input(crs).is_geographic)
    except Exception:
        return False  # an unreadable CRS is reported by georeferenced_heightfield


def _is_mercator(crs: Any) -> bool:
    try:
        return crs.is_projected and crs.to_dict().get("proj") == "merc"
    except Exception:
        return False


def _crs_name(crs: Any) -> str:
    """The CRS as "EPSG:<code>" when it has one, else the name in its WKT."""
    epsg = crs.to_epsg()
    if epsg:
        return f"EPSG:{epsg}"
    wkt = crs.to_wkt()
    return f"'{wkt.split(chr(34))[1]}'" if wkt.count(chr(34)) >= 2 else "an unnamed CRS"


def utm_crs(lon_deg: float, lat_deg: float) -> tuple[Any, str]:
    """The UTM zone (WGS84, EPSG:326zz north / 327zz south) containing (lon, lat), or UPS beyond
    84 N / 80 S; returns (CRS, label like "UTM 31N"). Norway/Svalbard zone exceptions are not applied."""
    from rasterio.crs import CRS

    if lat_deg > 84.0:
        return CRS.from_epsg(32661), "UPS North"
    if lat_deg < -80.0:
        return CRS.from_epsg(32761), "UPS South"
    lon = (lon_deg + 180.0) % 360.0 - 180.0
    zone = min(int((lon + 180.0) // 6.0) + 1, 60)
    north = lat_deg >= 0.0
    return CRS.from_epsg((32600 if north else 32700) + zone), f"UTM {zone}{'N' if north else 'S'}"


def ground_spacing_m(t: Affine, crs: Any, shape: tuple[int, int]) -> tuple[float, float]:
    """Ground distance (metres, WGS84 ellipsoid) between the central sample and its east and south
    neighbours: the true (dx, dy) of a grid at its centre, whatever its CRS units."""
    from rasterio.warp import transform as warp_points

    h, w = shape
    cx, cy = t @ (w / 2.0, h / 2.0)
    ex, ey = t @ (w / 2.0 + 1.0, h / 2.0)
    sx, sy = t @ (w / 2.0, h / 2.0 + 1.0)
    lon, lat = warp_points(crs, "EPSG:4326", [cx, ex, sx], [cy, ey, sy])
    phi = math.radians(lat[0])
    s2 = math.sin(phi) ** 2
    n_radius = WGS84_A_M / math.sqrt(1.0 - WGS84_E2 * s2)  # prime vertical radius of curvature
    m_radius = WGS84_A_M * (1.0 - WGS84_E2) / (1.0 - WGS84_E2 * s2) ** 1.5  # meridional radius

    def dist(k: int) -> float:
        dlon = (lon[k] - lon[0] + 180.0) % 360.0 - 180.0
        return math.hypot(
            n_radius * math.cos(phi) * math.radians(dlon), m_radius * math.radians(lat[k] - lat[0])
        )

    return dist(1), dist(2)


def metric_grid(
    crs: Any, t: Affine, shape: tuple[int, int], source: str, *, wide_ok: bool
) -> tuple[Any, str, Affine, int, int, float, float, float, str]:
    """The metric grid a north-up geographic or Mercator grid is resampled to, one rule for the in-memory
    reader and the out-of-core warp: the UTM zone of its centre (UPS near the poles), square pixels of the
    ground spacing at the centre (min of dx, dy, millimetre-rounded), the grid snapped to multiples of it.
    A region wider than ``MAX_UTM_SPAN_DEG`` of longitude is refused unless ``wide_ok``, which takes a
    Transverse Mercator on its central meridian instead.

    Returns (CRS, label, north-up transform, width, height, resolution m, ground dx m, dy m, note on a wide
    region). Refuses, in one line, bounds off the globe and a grid that would grow over
    ``MAX_REPROJECT_GROWTH`` times.
    """
    from rasterio.crs import CRS
    from rasterio.warp import transform as warp_points
    from rasterio.warp import transform_bounds

    h, w = shape
    west, south, east, north = t.c, t.f + h * t.e, t.c + w * t.a, t.f
    if crs.is_geographic and (
        max(abs(south), abs(north)) > 90.0 + abs(t.e) or max(abs(west), abs(east)) > 540.0
    ):
        raise InputError(
            f"bounds {west:.6g}, {south:.6g}, {east:.6g}, {north:.6g} lie outside the globe for the "
            f"geographic CRS {_crs_name(crs)}; the CRS is probably wrong",
            source,
        )
    try:
        lon_w, _, lon_e, _ = transform_bounds(crs, "EPSG:4326", west, south, east, north, densify_pts=21)
        (clon,), (clat,) = warp_points(crs, "EPSG:4326", [t.c + t.a * w / 2], [t.f + t.e * h / 2])
        dx_m, dy_m = ground_spacing_m(t, crs, (h, w))
    except Exception as exc:  # noqa: BLE001 - PROJ's failures, said in one line
        raise InputError(f"cannot locate the raster on the globe ({error_line(exc)})", source) from None
    span = lon_e - lon_w if lon_e >= lon_w else lon_e - lon_w + 360.0  # across the antimeridian too
    dst_crs, label = utm_crs(clon, clat)
    wide = ""
    if label.startswith("UTM") and span > MAX_UTM_SPAN_DEG:
        if not wide_ok:
            raise InputError(
                f"spans {span:.1f} degrees of longitude, too wide for one UTM zone (at most "
                f"{MAX_UTM_SPAN_DEG:g}); reproject it to a suitable metric CRS first (gdalwarp -t_srs ...)",
                source,
            )
        lon0 = (clon + 180.0) % 360.0 - 180.0
        dst_crs = CRS.from_proj4(f"+proj=tmerc +lat_0=0 +lon_0={lon0:.6f} +k=1 +x_0=0 +y_0=0 +datum=WGS84 "
                                 "+units=m +no_defs")  # fmt: skip
        label = f"Transverse Mercator on {lon0:.6f} E"
        wide = (
            f"; {span:.1f} degrees of longitude are too wide for one UTM zone (at most {MAX_UTM_SPAN_DEG:g})"
        )
    res = round(min(dx_m, dy_m), 3)
    if not (res > 0 and math.isfinite(res)):
        raise InputError(f"ground spacing at the centre is {res} m; check the georeferencing", source)
    bx0, by0, bx1, by1 = transform_bounds(crs, dst_crs, west, south, east, north, densify_pts=51)
    bx0, by1 = math.floor(bx0 / res) * res, math.ceil(by1 / res) * res
    width = max(2, math.ceil((bx1 - bx0) / res - 1e-9))
    height = max(2, math.ceil((by1 - by0) / res - 1e-9))
    growth = (width * height) / float(w * h)
    if growth > MAX_REPROJECT_GROWTH:
        raise InputError(
            f"reprojecting to {label} at the {res:g} m ground spacing of its centre would turn {w}x{h} samples "
            f"into {width}x{height} ({growth:,.0f}x, beyond {MAX_REPROJECT_GROWTH:g}x): its pixels are "
            f"{dx_m:.1f} x {dy_m:.1f} m on the ground (near a pole?); reproject it first with a suitable "
            "CRS and resolution (gdalwarp -t_srs ... -tr ...)",
            source,
        )
    return dst_crs, label, Affine(res, 0.0, bx0, 0.0, -res, by1), width, height, res, dx_m, dy_m, wide


def reproject_to_utm(
    values: np.ndarray, valid: np.ndarray, t: Affine, crs: Any, source: str
) -> tuple[np.ndarray, np.ndarray, Affine, Any, str]:
    """Reproject a north-up geographic or Mercator grid once to the UTM zone of its centre.

    Square pixels of the ground spacing at the centre (min of dx, dy, millimetre-rounded), grid snapped to
    multiples of it; elevations bilinear, the valid mask nearest-neighbour; cells outside the source
    footprint are invalid. Returns (values, valid, transform, crs, note, the source's own nodata
    fraction, the fraction of output cells outside the source's footprint).
    """
    from rasterio.warp import Resampling, reproject

    h, w = values.shape
    dst_crs, label, dst_t, width, height, res, dx_m, dy_m, _ = metric_grid(
        crs, t, (h, w), source, wide_ok=False
    )
    check_dimensions(height, width, source)
    out = np.full((height, width), np.nan, np.float64)
    kw = {"src_transform": t, "src_crs": crs, "dst_transform": dst_t, "dst_crs": dst_crs}
    reproject(np.where(valid, values, np.nan), out, resampling=Resampling.bilinear,
              src_nodata=np.nan, dst_nodata=np.nan, **kw)  # fmt: skip
    mask = np.zeros((height, width), np.uint8)
    reproject(np.ascontiguousarray(valid, dtype=np.uint8), mask, resampling=Resampling.nearest,
              src_nodata=None, dst_nodata=0, **kw)  # fmt: skip
    ok = (mask > 0) & np.isfinite(out)
    inside = np.zeros((height, width), np.uint8)
    reproject(np.ones(valid.shape, np.uint8), inside, resampling=Resampling.nearest,
              src_nodata=None, dst_nodata=0, **kw)  # fmt: skip
    src_nodata = float(1.0 - valid.mean()) if valid.size else 1.0
    margin = float((inside == 0).mean())
    note = (
        f"reprojected from {_crs_name(crs)} to {_crs_name(dst_crs)} ({label}) at {res:g} m, {_RESAMPLING} "
        f"(ground spacing at the centre {dx_m:.1f} x {dy_m:.1f} m)"
    )
    return out, ok, dst_t, dst_crs, note, src_nodata, margin


def _metric_units(crs: Any, t: Affine, source: str) -> tuple[Any, Affine, tuple[str, ...]]:
    """Convert a projected CRS in feet (or any non-metre unit) to the same projection in metres."""
    crs, t, _, notes = metric_frame(crs, t, source)
    return crs, t, notes


def metric_frame(crs: Any, t: Affine, source: str) -> tuple[Any, Affine, float | None, tuple[str, ...]]:
    """(the CRS with metre axes, the transform in metres, metres per unit of the CRS's vertical axis or
    None, notes) of a north-up projected grid (:func:`terralod.io.georef.metric_crs`); elevations are the
    caller's (see :func:`vertical_unit_m`)."""
    metric, factor, fv, notes = metric_crs(crs, t @ (0.5, 0.5), source)
    if factor != 1.0:
        t = Affine(t.a * factor, 0.0, t.c * factor, 0.0, t.e * factor, t.f * factor)
    return metric, t, fv, notes


def vertical_unit_m(crs: Any) -> tuple[str, float] | None:
    """(unit, metres per unit) of a CRS's vertical axis when it has one in another unit than metres
    (a compound CRS with a vertical part in feet), else None (also for an unreadable CRS: reported later)."""
    if crs is None:
        return None
    try:
        s = crs_summary(crs)
    except InputError:
        return None
    if s.vertical_unit_m is None or s.vertical_unit_m == 1.0:
        return None
    return s.vertical_unit or "?", s.vertical_unit_m


def _scale_note(t: Affine, crs: Any, shape: tuple[int, int]) -> tuple[str, ...]:
    """A note when the projection's grid metres differ from ground metres at the centre by > 1 %."""
    try:
        gx, gy = ground_spacing_m(t, crs, shape)
    except Exception:
        return ()
    kx, ky = gx / t.a, gy / -t.e  # ground metres per grid metre
    k = kx if abs(kx - 1.0) >= abs(ky - 1.0) else ky
    if abs(k - 1.0) <= SCALE_NOTE_TOLERANCE:
        return ()
    return (f"projection scale: one grid metre is {k:.3f} ground metres at the centre",)


def _metric(
    values: np.ndarray, valid: np.ndarray, t: Affine, crs: Any, source: str, notes: tuple[str, ...]
) -> Heightfield:
    z, ok, how = prepare_elevation(values, valid, source)
    wkt = None if crs is None else crs_text(crs)
    return Heightfield(z, ok, t, crs=wkt, source=source, fill_method=how, notes=tuple(notes))


def crs_text(crs: Any) -> str:
    """The WKT stored for a CRS: GDAL's WKT1, or WKT2 for a CRS terralod re-expressed in metres (whose
    REMARK saying so WKT1 cannot hold)."""
    wkt2 = crs.to_wkt(version="WKT2_2019")
    return wkt2 if "REMARK[" in wkt2 else crs.to_wkt()


def _with_notes(hf: Heightfield, *notes: str) -> Heightfield:
    return replace(hf, notes=(*hf.notes, *notes))  # a reprojection's fractions and original grid kept


def _fmt_pair(p: tuple[float, float]) -> str:
    return f"{p[0]:g}" if p[0] == p[1] else f"{p[0]:g} x {p[1]:g}"
