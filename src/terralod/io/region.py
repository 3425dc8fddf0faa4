"""A region of elevation: many DEM files read as one grid, a window at a time.

:func:`resolve_region` turns what a user points at — files, a quoted glob, a folder (its rasters), a GDAL
VRT, SRTM ``.hgt`` and ``.hgt.zip`` as downloaded (read through GDAL's ``/vsizip/``) — into one
:class:`Region`: its files, CRS, pixel size, bounds, every file's footprint and, for several files, a VRT
(hand-written XML: rasterio writes none) that places them on one grid. :class:`RegionReader` reads that
grid block by block with rasterio windowed reads, nodata filled, through a bounded LRU of blocks: nothing
ever holds the whole region, and a block is a pure function of the files and its index.

The rules, and why:

- One grid. Every file must share the first one's CRS and pixel size and sit on its grid (integer pixel
  offsets; SRTM tiles do: 1° is 1200 samples at 3", and adjacent tiles share their edge row or column).
  Anything else is refused in one line naming the two files (resampling would move every sample the
  tiles are measured against; ``gdalwarp -tr ... -tap`` does it once, visibly).
- Overlaps: the last file listed wins, as in a GDAL VRT (its sources are drawn in order), except where it
  has nodata: there the files below show through. A glob or a folder lists its files sorted by name.
  SRTM's shared edge rows are identical in both tiles, so there the rule changes nothing.
- Gaps (cells no file covers) are nodata: filled like any hole, flagged in the water mask of a
  quantized-mesh tile, never counted in a declared error.
- Values are the single-file reader's, bit for bit (``stored * scale + offset``; float32 for 8/16-bit
  integers and float32 without scale/offset, float64 otherwise): a region of one file reads as that file.
- Nodata fill (:func:`terralod.fill.fill_nodata`, the package's one fill), block by block: each fixed block
  of ``FILL_BLOCK`` x ``FILL_BLOCK`` samples is filled on itself plus a halo and keeps its own cells. The
  halo grows (64, 128, 256 samples) until the fill of the block provably equals the fill of the whole
  grid: every hole cell within the relaxation's reach (``FILL_SMOOTH_ITERATIONS`` samples) of the block
  has its nearest valid sample strictly closer than the halo's open edges, and those edges are further
  than that reach from the block (the relaxation is edge-clamped). Holes larger than that (a missing tile,
  an ocean of nodata) are filled on the largest halo when it holds a valid sample: there the values are
  the block's own fill, still a pure function of the block, so neighbouring tiles agree on every shared
  vertex. A block with no valid sample within the largest halo takes one value, the valid sample nearest
  its centre found block by block (:func:`terralod.fill.nearest_valid_value`, the window sources' rule),
  instead of a window grown until it reaches the data: from the open sea of a coastal region that window
  grew with the distance to the coast (up to the whole region).
"""

from __future__ import annotations

import glob as _glob
import math
import os
import threading
import warnings
import zipfile
from collections import OrderedDict
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from xml.sax.saxutils import escape

import numpy as np
from affine import Affine

from terralod.errors import InputError, InputNotFoundError
from terralod.fill import FILL_SMOOTH_ITERATIONS, fill_nodata, nearest_valid_value
from terralod.output import SpillFile, pack_block, unpack_block

__all__ = [
    "FILL_BLOCK",
    "Footprint",
    "Region",
    "RegionReader",
    "RegionCheck",
    "RegionScan",
    "check_region",
    "resolve_region",
    "scan_region",
]

#: Side of the fixed nodata-fill blocks (samples): the blocks of :mod:`terralod.io.windowed`'s scheme.
FILL_BLOCK = 512
#: First halo of a block's fill, and the largest one the exactness test grows it to (samples).
FILL_HALO = 64
FILL_HALO_EXACT_MAX = 256
#: Blocks a reader keeps (each FILL_BLOCK² samples: 1.25 MiB as float32 + mask, 2.25 MiB as float64).
CACHE_BLOCKS = 48
#: Bytes a reader keeps of what a block's nodata fill gave (its filled cells, or the whole filled block
#: where most of it is fill): a block evicted from the LRU is read again from the files, never filled again.
FILL_CACHE_BYTES = 64 << 20
#: GDAL's own block cache while a reader reads (unless GDAL_CACHEMAX is set): the reader keeps decoded
#: blocks itself (the LRU above), so GDAL's cache only spares re-decoding a file's tiles that straddle two
#: reader blocks; 16 MiB holds those (the export of 4 SRTM3 tiles took the same CPU as with 64 MiB), the
#: other 48 MiB were resident for nothing once a region is larger than the cache.
GDAL_CACHE_BYTES = 16 << 20
#: Thinned copies of every block made (every s-th row and column, s = THIN_MIN, 2 THIN_MIN, ... FILL_BLOCK;
#: 1/48 of the block for s >= 8) are kept within THIN_CACHE_BYTES: a coarse zoom's grid reads them instead
#: of every block of its window at full resolution (a region of 1e9 samples holds 100 MB of them).
THIN_MIN = 8
THIN_CACHE_BYTES = 32 << 20
#: Bytes a reader keeps of packed water bits (nodata or 0 m) of blocks that hold some water and some land.
WATER_CACHE_BYTES = 16 << 20
#: Samples per strip of the scan (a few MB at a time).
SCAN_STRIP_SAMPLES = 1 << 22
#: File names a folder contributes (lower case).
RASTER_SUFFIXES = (".tif", ".tiff", ".hgt", ".hgt.zip", ".vrt", ".img", ".dem", ".asc", ".bil", ".nc")
#: Data types read exactly as float32 (4 bytes a sample); anything else is read as float64.
EXACT32 = ("int8", "uint8", "int16", "uint16", "float32")
#: The reach of the relaxation of the fill (a cell's filled value depends on the nearest-sample values
#: within this many samples of it) plus one.
_REACH = FILL_SMOOTH_ITERATIONS + 1


@dataclass(frozen=True)
class Footprint:
    """One file of a region: where it sits on the region's grid."""

    path: str  #: the name GDAL opens (``/vsizip/...`` inside a zip)
    shown: str  #: the name given in messages (the file the user has)
    row: int  #: row offset of its first row in the region's grid
    col: int  #: column offset of its first column
    height: int
    width: int
    bounds: tuple[float, float, float, float]  #: west, south, east, north (CRS units, pixel edges)
    nodata: float | None
    dtype: str


@dataclass
class Region:
    """Files on one north-up grid (see the module docstring for the rules).

    ``transform`` maps (col, row) pixel corners of the whole grid to CRS coordinates; ``bounds`` are its
    outer pixel edges (west, south, east, north); ``resolution`` (x, y) in CRS units (degrees for a
    geographic CRS); ``vrt`` the VRT XML placing several files (None for one file, read as it is).
    """

    footprints: tuple[Footprint, ...]
    crs: Any  #: rasterio CRS
    transform: Affine
    width: int
    height: int
    scale: float = 1.0
    offset: float = 0.0
    vrt: str | None = None
    notes: tuple[str, ...] = field(default_factory=tuple)

    @property
    def paths(self) -> list[str]:
        return [f.path for f in self.footprints]

    @property
    def files(self) -> list[Path]:
        """The files on disk behind the region (a zip, not its member)."""
        return [Path(f.shown) for f in self.footprints]

    @property
    def shape(self) -> tuple[int, int]:
        return self.height, self.width

    @property
    def resolution(self) -> tuple[float, float]:
        return float(self.transform.a), float(-self.transform.e)

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        t = self.transform
        return (t.c, t.f + self.height * t.e, t.c + self.width * t.a, t.f)

    @property
    def dtype(self) -> type:
        """float32 where every file's values are exact in it and unscaled, float64 otherwise."""
        exact = all(f.dtype in EXACT32 for f in self.footprints)
        return np.float32 if exact and self.scale == 1.0 and self.offset == 0.0 else np.float64

    @property
    def name(self) -> str:
        """The region in messages: its one file, or ``N files (first, ...)``."""
        if len(self.footprints) == 1:
            return self.footprints[0].shown
        return f"{len(self.footprints)} files ({self.footprints[0].shown}, ...)"

    @property
    def target(self) -> str:
        """What GDAL opens: the one file, or the VRT XML itself."""
        return self.vrt if self.vrt is not None else self.footprints[0].path

    def write_vrt(self, path: str | Path) -> Path:
        """Write the region as a VRT file (for GDAL tools); a one-file region gets a VRT of that file."""
        p = Path(path)
        p.write_text(self.vrt if self.vrt is not None else _vrt_xml(self, self.footprints))
        return p


# -- resolving what the user gave -----------------------------------------------------------------------
def _is_glob(text: str) -> bool:
    return any(ch in text for ch in "*?[")


def _is_raster_name(p: Path) -> bool:
    low = p.name.lower()
    return any(low.endswith(s) for s in RASTER_SUFFIXES)


def _gdal_name(p: Path) -> str:
    """The name GDAL opens for a file: a zip's one raster through /vsizip/, anything else as it is."""
    if p.name.lower().endswith(".zip"):
        try:
            with zipfile.ZipFile(p) as zf:
                members = [n for n in zf.namelist() if _is_raster_name(Path(n)) and not n.endswith("/")]
        except (zipfile.BadZipFile, OSError) as exc:
            raise InputError(f"not a zip file GDAL can read ({exc})", str(p)) from None
        if len(members) != 1:
            raise InputError(
                f"holds {len(members)} rasters; expected one (an SRTM .hgt.zip holds one)", str(p)
            )
        return f"/vsizip/{p.resolve()}/{members[0]}"
    return str(p)


def expand_inputs(inputs: Iterable[str | Path]) -> list[tuple[str, str]]:
    """(GDAL name, name shown) of every file the inputs stand for, in the order given (a glob's and a
    folder's files sorted by name); InputNotFoundError naming an input that stands for nothing."""
    out: list[tuple[str, str]] = []
    for item in inputs:
        text = str(item)
        p = Path(text)
        if p.is_dir():
            found = sorted(q for q in p.iterdir() if q.is_file() and _is_raster_name(q))
            if not found:
                raise InputNotFoundError(f"holds no raster ({', '.join(RASTER_SUFFIXES)})", text)
            paths = found
        elif not p.exists() and _is_glob(text):
            paths = [Path(q) for q in sorted(_glob.glob(text)) if Path(q).is_file()]
            if not paths:
                raise InputNotFoundError("no file matches this pattern", text)
        elif not p.exists():
            raise InputNotFoundError("file not found", text)
        else:
            paths = [p]
        out += [(_gdal_name(q), str(q)) for q in paths]
    if not out:
        raise InputError("no input files given")
    seen: dict[str, str] = {}
    for _name, shown in out:
        key = os.path.realpath(shown)
        if key in seen:
            raise InputError(f"is given twice (also as {seen[key]})", shown)
        seen[key] = shown
    return out


def _same_crs(a: Any, b: Any) -> bool:
    if a == b:
        return True
    try:
        ea, eb = a.to_epsg(), b.to_epsg()
        if ea is not None and ea == eb:
            return True
        from pyproj import CRS

        return bool(
            CRS.from_user_input(a.to_wkt()).equals(CRS.from_user_input(b.to_wkt()), ignore_axis_order=True)
        )
    except Exception:  # noqa: BLE001 - a CRS pyproj cannot compare is a different one
        return False


def _header(name: str, shown: str, crs_given: Any) -> dict[str, Any]:
    import rasterio
    from rasterio.errors import NotGeoreferencedWarning

    from terralod.io.raster import error_line

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", NotGeoreferencedWarning)
            with rasterio.open(name) as ds:
                return {
                    "crs": crs_given if crs_given is not None else ds.crs,
                    "t": ds.transform,
                    "w": ds.width,
                    "h": ds.height,
                    "nodata": ds.nodatavals[0],
                    "dtype": ds.dtypes[0],
                    "scale": float((ds.scales or (1.0,))[0] or 1.0),
                    "offset": float((ds.offsets or (0.0,))[0] or 0.0),
                }
    except Exception as exc:  # noqa: BLE001 - any failure to open is the file's problem, said in one line
        raise InputError(f"not a raster GDAL can read ({error_line(exc)})", shown) from None


def resolve_region(inputs: str | Path | Sequence[str | Path], crs: Any = None) -> Region:
    """One :class:`Region` of every file ``inputs`` stand for (files, globs, folders, VRTs, ``.hgt``,
    ``.hgt.zip``); ``crs`` assigns (or overrides) the CRS of every file. Raises InputError (one line naming
    the file) for an unreadable file, a different CRS, pixel size or grid, or a raster that is not north-up.
    Where files overlap, the last one listed wins (its nodata cells show the files below)."""
    from terralod.io.georef import to_crs

    items = [inputs] if isinstance(inputs, str | Path) else list(inputs)
    files = expand_inputs(items)
    given = to_crs(crs) if crs is not None else None
    heads = [_header(name, shown, given) for name, shown in files]
    (_, shown0), h0 = files[0], heads[0]
    t0 = h0["t"]
    for (_, shown), h in zip(files, heads, strict=True):
        t = h["t"]
        if h["crs"] is None or t.is_identity:
            raise InputError("has no georeferencing (a CRS and a geotransform); give --crs, or use one file",
                             shown) if len(files) > 1 else InputError("has no CRS", shown)  # fmt: skip
        if t.b or t.d or t.a <= 0 or t.e >= 0:
            raise InputError(
                f"is not north-up (geotransform {tuple(t)[:6]}); warp it first (gdalwarp)", shown
            )
    for (_, shown), h in zip(files[1:], heads[1:], strict=True):
        t = h["t"]
        if not _same_crs(h["crs"], h0["crs"]):
            raise InputError(f"its CRS differs from {shown0}'s; reproject the files to one CRS first "
                             "(gdalwarp -t_srs ...)", shown)  # fmt: skip
        if not (math.isclose(t.a, t0.a, rel_tol=1e-9) and math.isclose(t.e, t0.e, rel_tol=1e-9)):
            raise InputError(f"its resolution {t.a:.10g} x {-t.e:.10g} differs from {shown0}'s {t0.a:.10g} x "
                             f"{-t0.e:.10g}; resample to one resolution first (gdalwarp -tr ... -tap)", shown)  # fmt: skip
        if (h["scale"], h["offset"]) != (h0["scale"], h0["offset"]):
            raise InputError(f"its vertical scale/offset ({h['scale']:g}, {h['offset']:g}) differ from "
                             f"{shown0}'s ({h0['scale']:g}, {h0['offset']:g})", shown)  # fmt: skip
    west = min(h["t"].c for h in heads)
    north = max(h["t"].f for h in heads)
    fps = []
    for (name, shown), h in zip(files, heads, strict=True):
        t = h["t"]
        fx, fy = (t.c - west) / t0.a, (north - t.f) / -t0.e
        if abs(fx - round(fx)) > 1e-6 or abs(fy - round(fy)) > 1e-6:
            raise InputError(f"is not on {shown0}'s grid (offset {fx:.3f}, {fy:.3f} samples); resample it "
                             "onto one grid first (gdalwarp -tap)", shown)  # fmt: skip
        bounds = (t.c, t.f + h["h"] * t.e, t.c + h["w"] * t.a, t.f)
        fps.append(
            Footprint(name, shown, round(fy), round(fx), h["h"], h["w"], bounds, h["nodata"], h["dtype"])
        )
    width = max(f.col + f.width for f in fps)
    height = max(f.row + f.height for f in fps)
    transform = Affine(t0.a, 0.0, west, 0.0, t0.e, north) if len(fps) > 1 else t0
    region = Region(tuple(fps), h0["crs"], transform, width, height, h0["scale"], h0["offset"])
    if len(fps) > 1 or given is not None:
        region.vrt = _vrt_xml(region, fps)
    return region


def _vrt_xml(region: Region, fps: Sequence[Footprint]) -> str:
    """VRT XML of the files on the region's grid: sources in the order given (the last one wins), nodata
    (NaN) where none covers a cell. Float32 when that holds every file exactly, else Float64."""
    dt = "Float32" if all(f.dtype in EXACT32 for f in fps) else "Float64"
    srcs = []
    for f in fps:
        nd = f"<NODATA>{f.nodata!r}</NODATA>" if f.nodata is not None else ""
        name = f.path if f.path.startswith("/vsi") else str(Path(f.path).resolve())
        srcs.append(
            f'<ComplexSource><SourceFilename relativeToVRT="0">{escape(name)}</SourceFilename>'
            f'<SourceBand>1</SourceBand><SrcRect xOff="0" yOff="0" xSize="{f.width}" ySize="{f.height}"/>'
            f'<DstRect xOff="{f.col}" yOff="{f.row}" xSize="{f.width}" ySize="{f.height}"/>{nd}</ComplexSource>'
        )
    t = region.transform
    gt = f"{t.c!r}, {t.a!r}, 0.0, {t.f!r}, 0.0, {t.e!r}"
    return (
        f'<VRTDataset rasterXSize="{region.width}" rasterYSize="{region.height}">'
        f"<SRS>{escape(region.crs.to_wkt())}</SRS><GeoTransform>{gt}</GeoTransform>"
        f'<VRTRasterBand dataType="{dt}" band="1"><NoDataValue>nan</NoDataValue>'
        f"{''.join(srcs)}</VRTRasterBand></VRTDataset>"
    )


# -- the scan: every sample read once, before anything is written -------------------------------------
@dataclass
class RegionScan:
    """What one pass over every file finds: the valid samples' bounding box in the region's grid (rows
    r0..r1, cols c0..c1, inclusive), how many there are, and whether any cell is nodata or sea (0 m)."""

    r0: int
    r1: int
    c0: int
    c1: int
    valid_samples: int
    any_water: bool


def scan_region(region: Region) -> RegionScan:
    """Read every file of the region once, strip by strip: a file GDAL cannot decode is named in one line
    (InputError) before anything is written; also the valid samples' extent and whether there is water."""
    import rasterio
    from rasterio.windows import Window

    from terralod.io.raster import error_line

    r0 = c0 = 1 << 62
    r1 = c1 = -1
    count = 0
    water = False
    covered = 0
    for f in region.footprints:
        covered += f.width * f.height
        try:
            with rasterio.open(f.path) as ds:
                step = max(1, SCAN_STRIP_SAMPLES // max(ds.width, 1))
                for s0 in range(0, ds.height, step):
                    n = min(step, ds.height - s0)
                    a = ds.read(1, window=Window(0, s0, ds.width, n), masked=True)
                    ok = ~np.ma.getmaskarray(a)
                    vals = np.ma.getdata(a)
                    if vals.dtype.kind == "f":
                        ok &= np.isfinite(vals)
                    if not ok.all() or bool((vals[ok] * region.scale + region.offset == 0.0).any()):
                        water = True
                    rows = np.flatnonzero(ok.any(axis=1))
                    if rows.size:
                        cols = np.flatnonzero(ok.any(axis=0))
                        r0, r1 = min(r0, f.row + s0 + int(rows[0])), max(r1, f.row + s0 + int(rows[-1]))
                        c0, c1 = min(c0, f.col + int(cols[0])), max(c1, f.col + int(cols[-1]))
                        count += int(ok.sum())
        except Exception as exc:  # noqa: BLE001 - a corrupt block, a truncated file: the file, in one line
            raise InputError(f"cannot be read ({error_line(exc)})", f.shown) from None
    if count == 0:
        raise InputError("has no valid samples", region.name)
    if covered < region.width * region.height:  # maybe a gap (files may also overlap): check exactly
        water = water or _has_gap(region)
    return RegionScan(r0, r1, c0, c1, count, water)


@dataclass
class RegionCheck:
    """What ``terralod check`` finds in a region of DEM files: every file read whole, block by block."""

    name: str
    files: int = 0
    grid: str = ""
    samples: int = 0
    valid_in_files: int = 0  #: valid samples summed over the files (a shared edge row counts in each)
    checked: list[str] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)

    @property
    def sound(self) -> bool:
        return not self.problems

    def as_dict(self) -> dict[str, Any]:
        return {"kind": "region of DEM files", "name": self.name, "files": self.files, "grid": self.grid,
                "samples": self.samples, "valid_in_files": self.valid_in_files, "checked": self.checked,
                "problems": self.problems, "sound": self.sound}  # fmt: skip


def check_region(inputs: str | Path | Sequence[str | Path], crs: Any = None) -> RegionCheck:
    """Check a region of DEM files as an export would read it, reporting every problem (not only the first):
    the files make one grid (:func:`resolve_region`'s rules), every block of every file decodes, every file
    holds valid samples; gaps and overlaps are said (they follow the region's rules, so they are no
    problem). Memory: one strip of one file at a time."""
    import rasterio
    from rasterio.windows import Window

    from terralod.io.raster import error_line

    shown = ", ".join(map(str, [inputs] if isinstance(inputs, (str, Path)) else inputs))
    rep = RegionCheck(shown)
    try:
        region = resolve_region(inputs, crs)
    except InputError as exc:
        rep.problems.append(str(exc))
        return rep
    rep.name, rep.files = region.name, len(region.footprints)
    rep.grid = f"{region.width} x {region.height} samples, {describe_pixel(region)}"
    rep.samples = region.width * region.height
    covered = 0
    for f in region.footprints:
        covered += f.width * f.height
        valid = 0
        try:
            with rasterio.open(f.path) as ds:
                step = max(1, SCAN_STRIP_SAMPLES // max(ds.width, 1))
                for s0 in range(0, ds.height, step):
                    a = ds.read(1, window=Window(0, s0, ds.width, min(step, ds.height - s0)), masked=True)
                    ok = ~np.ma.getmaskarray(a)
                    vals = np.ma.getdata(a)
                    if vals.dtype.kind == "f":
                        ok &= np.isfinite(vals)
                    valid += int(ok.sum())
        except Exception as exc:  # noqa: BLE001 - a corrupt block, a truncated file: the file, in one line
            rep.problems.append(f"{f.shown}: cannot be read ({error_line(exc)})")
            continue
        if valid == 0:
            rep.problems.append(f"{f.shown}: has no valid samples (all nodata)")
        rep.valid_in_files += valid
    readable = rep.files - sum(1 for p in rep.problems if "cannot be read" in p)
    rep.checked.append(f"{readable} of {rep.files} file(s) read whole, every block decoded")
    rep.checked.append(f"one grid: {rep.grid}")
    if covered > rep.samples:
        rep.checked.append("files overlap: the last one listed wins where it has data")
    if covered < rep.samples and _has_gap(region):
        rep.checked.append("gaps (cells no file covers) are nodata: filled, flagged as water, in no error")
    return rep


def describe_pixel(region: Region) -> str:
    """The region's pixel size and CRS in a few words."""
    from terralod.io.georef import describe_crs

    a, e = region.transform.a, -region.transform.e
    unit = "°" if region.crs is not None and region.crs.is_geographic else " m"
    size = f'{a * 3600:.4g}" x {e * 3600:.4g}"' if unit == "°" else f"{a:.6g} x {e:.6g}{unit}"
    return f"pixels {size}, {describe_crs(region.crs)}"


def _has_gap(region: Region) -> bool:
    """True when some cell of the region's grid is covered by no file (on the grid of file edges)."""
    rows = sorted({0, region.height, *(f.row for f in region.footprints),
                   *(f.row + f.height for f in region.footprints)})  # fmt: skip
    cols = sorted({0, region.width, *(f.col for f in region.footprints),
                   *(f.col + f.width for f in region.footprints)})  # fmt: skip
    cover = np.zeros((len(rows) - 1, len(cols) - 1), bool)
    for f in region.footprints:
        i0, i1 = rows.index(f.row), rows.index(f.row + f.height)
        j0, j1 = cols.index(f.col), cols.index(f.col + f.width)
        cover[i0:i1, j0:j1] = True
    return not bool(cover.all())


# -- reading blocks ------------------------------------------------------------------------------------
class _BytesLRU:
    """A least-recently-used map bounded by the bytes of its values (tuples of arrays); thread-safe."""

    def __init__(self, budget: int) -> None:
        self.budget = int(budget)
        self.used = 0
        self._d: OrderedDict[Any, tuple[Any, int]] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, key: Any) -> Any:
        with self._lock:
            got = self._d.get(key)
            if got is None:
                return None
            self._d.move_to_end(key)
            return got[0]

    def put(self, key: Any, value: Any, nbytes: int) -> None:
        if nbytes > self.budget:
            return
        with self._lock:
            old = self._d.pop(key, None)
            if old is not None:
                self.used -= old[1]
            self._d[key] = (value, nbytes)
            self.used += nbytes
            while self.used > self.budget:
                _, (_, n) = self._d.popitem(last=False)
                self.used -= n


class RegionReader:
    """The region's samples, nodata filled, block by block (see the module docstring), through a bounded
    LRU of ``cache_blocks`` blocks; thread-safe (one open dataset per thread).

    What each block costs is paid once, whatever the order of the windows asked for:

    - its fill: the filled cells (or the whole filled block, where fill is most of it) are kept within
      FILL_CACHE_BYTES, so a block evicted from the LRU is read again (a few ms) but never filled again;
    - its water (nodata or exactly 0 m, on the unfilled values): whether it holds none, some or only
      water, for every block made (two flags), and the packed bits of the blocks with some of each within
      WATER_CACHE_BYTES: :meth:`water_any_all` and :meth:`water_gather` answer from them;
    - a coarse grid (every s-th row and column, s >= THIN_MIN a power of two): :meth:`gather` reads the
      thinned copies made with each block (kept within THIN_CACHE_BYTES) and the region's last row and
      column (kept: the grids clamp to them), not every block at full resolution.

    A block the LRU drops goes to a spill file (:class:`terralod.output.SpillFile`: the region's dtype and
    one bit a sample, about 4.1 bytes a sample of the blocks dropped) and comes back from it as the same bytes, a
    copy instead of a GDAL read and decode: the finer zooms of an export sweep the region again and again.

    Memory: ``cache_blocks`` blocks plus those three budgets, whatever the region's size.
    """

    def __init__(self, region: Region, *, cache_blocks: int = CACHE_BLOCKS) -> None:
        self.region = region
        self.height, self.width = region.shape
        self.dtype: type = region.dtype
        self.cache_blocks = int(cache_blocks)
        self._local = threading.local()
        self._cache: OrderedDict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = OrderedDict()
        self._lock = threading.Lock()
        self._fills = _BytesLRU(FILL_CACHE_BYTES)
        #: the halo each block (br, bc) filled so far needed: over FILL_HALO_EXACT_MAX (a hole that wide),
        #: its values may depend on samples further away (what an export's update asks)
        self.fill_halos: dict[tuple[int, int], int] = {}
        self._thin = _BytesLRU(THIN_CACHE_BYTES)
        self._water_bits = _BytesLRU(WATER_CACHE_BYTES)
        #: (some, every) water of each block made: (False, False) land only, (True, True) water only
        self._water: dict[tuple[int, int], tuple[bool, bool]] = {}
        self._edges: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        #: blocks the LRU dropped, kept in an unlinked temporary file (the region's dtype and a bit a
        #: sample: 4.1 bytes a sample for float32) and read back from it instead of from the files
        self._spill_file = SpillFile("terralod-blocks-")
        self._spilled: set[tuple[int, int]] = set()
        self.blocks_read = 0  #: blocks read from the files (cache misses), for benchmarks
        self.blocks_filled = 0  #: blocks whose nodata fill was computed, for benchmarks

    def _dataset(self) -> Any:
        import rasterio

        ds = getattr(self._local, "ds", None)
        if ds is None:
            if "GDAL_CACHEMAX" not in os.environ:
                from rasterio._env import set_gdal_config

                set_gdal_config("GDAL_CACHEMAX", GDAL_CACHE_BYTES)
            ds = self._local.ds = rasterio.open(self.region.target)
        return ds

    def open(self) -> None:
        """Open the dataset for this thread now (reads then go on even if a file is unlinked)."""
        self._dataset()

    def close(self) -> None:
        ds = getattr(self._local, "ds", None)
        if ds is not None:
            ds.close()
            self._local.ds = None

    def read_raw(self, r0: int, r1: int, c0: int, c1: int) -> tuple[np.ndarray, np.ndarray]:
        """Unfilled values (metres, the region's dtype; arbitrary where invalid) and validity of rows
        [r0, r1), cols [c0, c1) (inside the grid)."""
        from rasterio.windows import Window

        from terralod.io.raster import error_line

        ds = self._dataset()
        nodata = self._plain_nodata(ds)
        try:
            a = ds.read(1, window=Window(c0, r0, c1 - c0, r1 - r0), masked=nodata is None)
        except Exception as exc:  # noqa: BLE001 - a file that went bad after the scan
            raise InputError(f"cannot read rows {r0}-{r1} ({error_line(exc)})", self.region.name) from None
        if nodata is None:
            ok = ~np.ma.getmaskarray(a)
            raw = np.ma.getdata(a)
        elif isinstance(nodata, bool):  # every sample valid (NaN aside, below)
            raw, ok = a, np.ones(a.shape, bool)
        else:  # the samples equal to the nodata value, as GDAL's mask has them (NaN: isfinite, below)
            raw, ok = a, a != nodata
        if self.region.scale != 1.0 or self.region.offset != 0.0:
            values = raw.astype(np.float64)
            values *= self.region.scale
            values += self.region.offset
        else:
            values = raw.astype(self.dtype)
        ok &= np.isfinite(values)
        return values, np.ascontiguousarray(ok)

    def _plain_nodata(self, ds: Any) -> Any:
        """How validity can be had without GDAL's mask band (which reads a VRT's window a second time):
        True when every sample is valid, the nodata value of an integer band or a NaN one (compared
        exactly, as GDAL does), or None: a mask band, an alpha band or a float nodata that is not NaN (GDAL
        compares those with a tolerance), read through ``masked=True``."""
        got = getattr(self._local, "nodata", ())
        if got != ():
            return got
        from rasterio.enums import MaskFlags

        flags, nodata, dtype = ds.mask_flag_enums[0], ds.nodata, np.dtype(ds.dtypes[0])
        if flags == [MaskFlags.all_valid]:
            got = True
        elif flags == [MaskFlags.nodata] and nodata is not None:
            if np.issubdtype(dtype, np.integer) and float(nodata).is_integer():
                got = dtype.type(nodata) if np.can_cast(np.min_scalar_type(nodata), dtype) else None
            elif np.issubdtype(dtype, np.floating) and math.isnan(nodata):
                got = True  # NaN is never equal: isfinite below drops it
            else:
                got = None
        else:
            got = None
        self._local.nodata = got
        return got

    def block(self, br: int, bc: int) -> tuple[np.ndarray, np.ndarray]:
        """Block (br, bc): filled heights (the region's dtype) and validity, FILL_BLOCK² or less at the
        south and east edges; cached."""
        key = (br, bc)
        with self._lock:
            got = self._cache.get(key)
            if got is not None:
                self._cache.move_to_end(key)
                return got
        got = self._spilled_block(br, bc)
        read = got is None
        if got is None:
            got = self._make_block(br, bc)
        elif self._thin.get(key) is None:
            self._note_thinned(br, bc, *got)
        with self._lock:
            self.blocks_read += read
            self._cache[key] = got
            while len(self._cache) > self.cache_blocks:
                self._spill(*self._cache.popitem(last=False))
        return got

    def _spill_offset(self, br: int, bc: int) -> int:
        """Offset of block (br, bc)'s slot in the spill file (heights, then validity bits)."""
        b = FILL_BLOCK
        slot = b * b * np.dtype(self.dtype).itemsize + b * b // 8
        return (br * -(-self.width // b) + bc) * slot

    def _spill(self, key: tuple[int, int], got: tuple[np.ndarray, np.ndarray]) -> None:
        """Keep a block the LRU drops in the spill file (caller holds the lock): read back, it costs a
        copy instead of a GDAL read (decode, VRT) and its fill. A block the file declines (its disk's
        reserve reached) is read from the files again when asked."""
        if key in self._spilled or self.cache_blocks <= 0:
            return
        z, ok = got
        if self._spill_file.put(self._spill_offset(*key), pack_block(z, ok, self.dtype)):
            self._spilled.add(key)

    def _spilled_block(self, br: int, bc: int) -> tuple[np.ndarray, np.ndarray] | None:
        """Block (br, bc) read back from the spill file, or None if it was never dropped there."""
        with self._lock:
            if (br, bc) not in self._spilled:
                return None
        r0, r1, c0, c1 = self._bounds(br, bc)
        shape = (r1 - r0, c1 - c0)
        n = shape[0] * shape[1]
        width = n * np.dtype(self.dtype).itemsize
        z, ok = unpack_block(
            self._spill_file.get(self._spill_offset(br, bc), width + (n + 7) // 8), self.dtype, shape
        )
        return z.copy(), ok  # a writable copy, as a block read from the files is

    def _bounds(self, br: int, bc: int) -> tuple[int, int, int, int]:
        b = FILL_BLOCK
        r0, c0 = br * b, bc * b
        return r0, min(r0 + b, self.height), c0, min(c0 + b, self.width)

    def _make_block(self, br: int, bc: int) -> tuple[np.ndarray, np.ndarray]:
        got = self._read_filled(br, bc)
        if self._thin.get((br, bc)) is None:
            self._note_thinned(br, bc, *got)
        return got

    def _read_filled(self, br: int, bc: int) -> tuple[np.ndarray, np.ndarray]:
        r0, r1, c0, c1 = self._bounds(br, bc)
        values, ok = self.read_raw(r0, r1, c0, c1)
        if (br, bc) not in self._water:
            self._note_water(br, bc, values, ok)
        if ok.all():
            self.fill_halos[(br, bc)] = 0
            return values, ok
        kept = self._fills.get((br, bc))
        if kept is not None:  # the fill made before: its cells, or the whole filled block
            idx, fv = kept
            if idx is None:
                return fv, ok
            values.reshape(-1)[idx] = fv
            return values, ok
        filled = self._fill(r0, r1, c0, c1)
        holes = np.flatnonzero(~ok.reshape(-1))
        if 2 * holes.size <= ok.size:
            fv = filled.reshape(-1)[holes]
            self._fills.put((br, bc), (holes.astype(np.int32), fv), holes.size * 4 + fv.nbytes)
        else:
            self._fills.put((br, bc), (None, filled), filled.nbytes)
        return filled, ok

    def _fill(self, r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
        """The filled heights of the block [r0, r1) x [c0, c1) (see the module docstring: the halo grown
        until the block's fill is the whole grid's)."""
        self.blocks_filled += 1
        halo = FILL_HALO
        while True:
            ra, ca = max(r0 - halo, 0), max(c0 - halo, 0)
            rb, cb = min(r1 + halo, self.height), min(c1 + halo, self.width)
            wv, wok = self.read_raw(ra, rb, ca, cb)
            whole = ra == 0 and ca == 0 and rb == self.height and cb == self.width
            if wok.any() and (whole or halo >= FILL_HALO_EXACT_MAX or _exact(wok, (ra, rb, ca, cb),
                                                                              (r0, r1, c0, c1), self.shape)):  # fmt: skip
                break
            if whole:
                raise InputError("has no valid samples", self.region.name)
            if halo >= FILL_HALO_EXACT_MAX:  # far from every valid sample: one value, found block by block
                del wv, wok
                self.fill_halos[(r0 // FILL_BLOCK, c0 // FILL_BLOCK)] = max(self.height, self.width)
                return np.full((r1 - r0, c1 - c0), self._far_value(r0, r1, c0, c1), self.dtype)
            halo *= 2
        self.fill_halos[(r0 // FILL_BLOCK, c0 // FILL_BLOCK)] = halo
        filled: np.ndarray = fill_nodata(wv, wok).astype(self.dtype)
        return np.ascontiguousarray(filled[r0 - ra : r1 - ra, c0 - ca : c1 - ca])

    def _far_value(self, r0: int, r1: int, c0: int, c1: int) -> float:
        """The one value of the block [r0, r1) x [c0, c1) with no valid sample within FILL_HALO_EXACT_MAX
        (:func:`terralod.fill.nearest_valid_value`; a flag a block says which hold valid samples)."""
        b = FILL_BLOCK
        flags = self.__dict__.setdefault("_has_valid", {})

        def block(i: int, j: int) -> tuple[np.ndarray, np.ndarray, int, int]:
            values, ok = self.read_raw(i * b, min(i * b + b, self.height), j * b, min(j * b + b, self.width))
            return values, ok, i * b, j * b

        def has_valid(i: int, j: int) -> bool:
            got = flags.get((i, j))
            if got is None:
                got = flags[(i, j)] = bool(block(i, j)[1].any())
            return got

        got = nearest_valid_value((r0 // b, c0 // b), (-(-self.height // b), -(-self.width // b)),
                                  ((r0 + r1 - 1) / 2.0, (c0 + c1 - 1) / 2.0), has_valid, block)  # fmt: skip
        if got is None:
            raise InputError("has no valid samples", self.region.name)
        return got

    def _note_water(self, br: int, bc: int, values: np.ndarray, ok: np.ndarray) -> None:
        """Record the block's water flags (and its packed bits where it holds some water and some land)."""
        wet = ~ok
        wet |= values == 0.0
        some, every = bool(wet.any()), bool(wet.all())
        if some and not every:
            bits = np.packbits(wet, axis=None)
            self._water_bits.put((br, bc), bits, bits.nbytes)
        self._water[(br, bc)] = (some, every)

    def _block_water(self, br: int, bc: int) -> tuple[bool, bool, np.ndarray | None]:
        """(some, every, bits): the block's water flags and, where it holds both, its water as a bool
        array (None otherwise)."""
        flags = self._water.get((br, bc))
        if flags is None:
            z, ok = self.block(br, bc)
            flags = self._water[(br, bc)]
        some, every = flags
        if not some or every:
            return some, every, None
        bits = self._water_bits.get((br, bc))
        r0, r1, c0, c1 = self._bounds(br, bc)
        if bits is None:
            z, ok = self.block(br, bc)  # valid samples keep their values: the water of the unfilled ones
            wet = ~ok | (z == 0.0)
            bits = np.packbits(wet, axis=None)
            self._water_bits.put((br, bc), bits, bits.nbytes)
            return some, every, wet
        n = (r1 - r0) * (c1 - c0)
        return some, every, np.unpackbits(bits, count=n).view(bool).reshape(r1 - r0, c1 - c0)

    @property
    def shape(self) -> tuple[int, int]:
        return self.height, self.width

    # -- windows and gathers, assembled from blocks -------------------------------------------------------
    def window(self, r0: int, r1: int, c0: int, c1: int) -> tuple[np.ndarray, np.ndarray]:
        """Filled heights and validity of rows [r0, r1), cols [c0, c1) (inside the grid)."""
        b = FILL_BLOCK
        z: np.ndarray = np.empty((r1 - r0, c1 - c0), self.dtype)
        ok = np.empty((r1 - r0, c1 - c0), bool)
        for br in range(r0 // b, (r1 - 1) // b + 1):
            for bc in range(c0 // b, (c1 - 1) // b + 1):
                bz, bok = self.block(br, bc)
                ra, rb = max(br * b, r0), min((br + 1) * b, r1)
                ca, cb = max(bc * b, c0), min((bc + 1) * b, c1)
                z[ra - r0 : rb - r0, ca - c0 : cb - c0] = bz[
                    ra - br * b : rb - br * b, ca - bc * b : cb - bc * b
                ]
                ok[ra - r0 : rb - r0, ca - c0 : cb - c0] = bok[
                    ra - br * b : rb - br * b, ca - bc * b : cb - bc * b
                ]
        return z, ok

    def water_any_all(self, r0: int, r1: int, c0: int, c1: int) -> tuple[bool, bool]:
        """(some, every): whether any / every sample of rows [r0, r1), cols [c0, c1) (inside the grid, not
        empty) is nodata or exactly 0 m; from the blocks' flags where a block is all land or all water."""
        b = FILL_BLOCK
        some, every = False, True
        for br in range(r0 // b, (r1 - 1) // b + 1):
            for bc in range(c0 // b, (c1 - 1) // b + 1):
                s_, e_, wet = self._block_water(br, bc)
                if wet is not None:
                    ra, rb = max(br * b, r0) - br * b, min((br + 1) * b, r1) - br * b
                    ca, cb = max(bc * b, c0) - bc * b, min((bc + 1) * b, c1) - bc * b
                    part = wet[ra:rb, ca:cb]
                    s_, e_ = bool(part.any()), bool(part.all())
                some, every = some or s_, every and e_
        return some, every

    def water_gather(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Water (nodata or exactly 0 m) at every (rows[i], cols[j]) (an outer product; indices inside)."""
        b = FILL_BLOCK
        rows, cols = np.asarray(rows, np.int64), np.asarray(cols, np.int64)
        out = np.zeros((rows.size, cols.size), bool)
        rb_, cb_ = rows // b, cols // b
        for br in np.unique(rb_):
            i = np.flatnonzero(rb_ == br)
            for bc in np.unique(cb_):
                j = np.flatnonzero(cb_ == bc)
                some, every, wet = self._block_water(int(br), int(bc))
                if not some:
                    continue
                if every:
                    out[i[:, None], j[None, :]] = True
                elif wet is not None:
                    out[i[:, None], j[None, :]] = wet[rows[i, None] - br * b, cols[None, j] - bc * b]
        return out

    def _edge(self, which: str) -> tuple[np.ndarray, np.ndarray]:
        """The region's last row ("row") or last column ("col"): filled heights and validity (kept)."""
        got = self._edges.get(which)
        if got is None:
            h, w = self.shape
            got = self.window(h - 1, h, 0, w) if which == "row" else self.window(0, h, w - 1, w)
            got = (got[0].reshape(-1).copy(), got[1].reshape(-1).copy())
            self._edges[which] = got
        return got

    def _note_thinned(self, br: int, bc: int, z: np.ndarray, ok: np.ndarray) -> None:
        """Keep every s-th row and column of a block just made, for s = THIN_MIN ... FILL_BLOCK (one buffer
        of heights and one of validity per block: few, long-lived allocations)."""
        parts = [(z[::s, ::s], ok[::s, ::s]) for s in _thin_strides()]
        zs = np.concatenate([a.reshape(-1) for a, _ in parts])
        oks = np.concatenate([b.reshape(-1) for _, b in parts])
        views, at = {}, 0
        for s, (a, _) in zip(_thin_strides(), parts, strict=True):
            views[s] = (zs[at : at + a.size].reshape(a.shape), oks[at : at + a.size].reshape(a.shape))
            at += a.size
        self._thin.put((br, bc), views, zs.nbytes + oks.nbytes)

    def _thinned(self, br: int, bc: int, s: int) -> tuple[np.ndarray, np.ndarray]:
        """Every s-th row and column of block (br, bc) from its first (s a power of two)."""
        if s >= THIN_MIN:
            views = self._thin.get((br, bc))
            if views is None:
                self.block(br, bc)  # makes and keeps them (unless the block was in the LRU: then now)
                views = self._thin.get((br, bc))
                if views is None:
                    self._note_thinned(br, bc, *self.block(br, bc))
                    views = self._thin.get((br, bc))
            if views is not None:
                got: tuple[np.ndarray, np.ndarray] = views[s]
                return got
        z, ok = self.block(br, bc)
        return z[::s, ::s], ok[::s, ::s]

    def gather(self, rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Filled heights and validity at every (rows[i], cols[j]) (an outer product; indices inside).

        Indices that are all multiples of a power of two s >= 2 (but for the region's last row and column)
        are read from thinned blocks (s up to FILL_BLOCK) and the kept last row and column."""
        b = FILL_BLOCK
        rows, cols = np.asarray(rows, np.int64), np.asarray(cols, np.int64)
        h, w = self.shape
        s = _stride_of(rows, h - 1, cols, w - 1)
        z: np.ndarray = np.empty((rows.size, cols.size), self.dtype)
        ok = np.empty((rows.size, cols.size), bool)
        if s > 1:
            lr, lc = rows == h - 1, cols == w - 1
            if lr.any():
                ez, eok = self._edge("row")
                z[lr, :], ok[lr, :] = ez[cols], eok[cols]
            if lc.any():
                ez, eok = self._edge("col")
                z[:, lc], ok[:, lc] = ez[rows][:, None], eok[rows][:, None]
            ri, ci = np.flatnonzero(~lr), np.flatnonzero(~lc)
            rows_in, cols_in = rows[ri], cols[ci]
        else:
            ri, ci = np.arange(rows.size), np.arange(cols.size)
            rows_in, cols_in = rows, cols
        rb_, cb_ = rows_in // b, cols_in // b
        for br in np.unique(rb_):
            i = np.flatnonzero(rb_ == br)
            for bc in np.unique(cb_):
                j = np.flatnonzero(cb_ == bc)
                ii, jj = rows_in[i, None] - br * b, cols_in[None, j] - bc * b
                if s > 1:
                    bz, bok = self._thinned(int(br), int(bc), s)
                    ii, jj = ii // s, jj // s
                else:
                    bz, bok = self.block(int(br), int(bc))
                dst = (ri[i][:, None], ci[j][None, :])
                z[dst] = bz[ii, jj]
                ok[dst] = bok[ii, jj]
        return z, ok

    def take(self, rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Filled heights and validity at the points (rows[k], cols[k]) (any shape; indices inside)."""
        b = FILL_BLOCK
        rows, cols = np.asarray(rows, np.int64), np.asarray(cols, np.int64)
        shape = np.broadcast_shapes(rows.shape, cols.shape)
        rf, cf = np.broadcast_to(rows, shape).ravel(), np.broadcast_to(cols, shape).ravel()
        z: np.ndarray = np.empty(rf.size, self.dtype)
        ok = np.empty(rf.size, bool)
        nb = (self.width + b - 1) // b
        key = (rf // b) * nb + cf // b
        order = np.argsort(key, kind="stable")
        ks, first = np.unique(key[order], return_index=True)
        bounds = [*first.tolist(), rf.size]
        for n, k in enumerate(ks.tolist()):
            sel = order[bounds[n] : bounds[n + 1]]
            br, bc = divmod(int(k), nb)
            bz, bok = self.block(br, bc)
            z[sel] = bz[rf[sel] - br * b, cf[sel] - bc * b]
            ok[sel] = bok[rf[sel] - br * b, cf[sel] - bc * b]
        return z.reshape(shape), ok.reshape(shape)


def _thin_strides() -> list[int]:
    """The strides whose thinned copies a reader keeps: THIN_MIN, 2 THIN_MIN, ... FILL_BLOCK."""
    out, s = [], THIN_MIN
    while s <= FILL_BLOCK:
        out.append(s)
        s *= 2
    return out


def _stride_of(rows: np.ndarray, last_row: int, cols: np.ndarray, last_col: int) -> int:
    """The largest power of two s <= FILL_BLOCK that divides every row and column index but the grid's last
    row and column (1 when there is none, or when an index is odd)."""
    r = rows[rows != last_row]
    c = cols[cols != last_col]
    both = np.concatenate([r, c])
    if both.size == 0:
        return 1
    low = both & -both  # each index's lowest set bit (0 for index 0: a multiple of any s)
    low = low[low > 0]
    return int(min(low.min(), FILL_BLOCK)) if low.size else FILL_BLOCK


def _exact(ok: np.ndarray, win: tuple[int, int, int, int], core: tuple[int, int, int, int],
           shape: tuple[int, int]) -> bool:  # fmt: skip
    """True when filling the window ``win`` gives, on ``core``, the fill of the whole grid: its open edges
    (those not on the grid's edge) lie beyond the relaxation's reach of the core, and every hole cell
    within that reach has its nearest valid sample strictly closer than any cell beyond an open edge."""
    from scipy import ndimage

    ra, rb, ca, cb = win
    r0, r1, c0, c1 = core
    h, w = shape
    open_n, open_s, open_w, open_e = ra > 0, rb < h, ca > 0, cb < w
    if (
        (open_n and r0 - ra < _REACH)
        or (open_s and rb - r1 < _REACH)
        or (open_w and c0 - ca < _REACH)
        or (open_e and cb - c1 < _REACH)
    ):
        return False
    # the cells whose nearest-sample value reaches the core through the relaxation
    za, zb = max(r0 - _REACH, ra) - ra, min(r1 + _REACH, rb) - ra
    xa, xb = max(c0 - _REACH, ca) - ca, min(c1 + _REACH, cb) - ca
    zone = ~ok[za:zb, xa:xb]
    if not zone.any():
        return True
    dist = ndimage.distance_transform_edt(~ok)[za:zb, xa:xb]
    rr, cc = np.nonzero(zone)
    rr, cc = rr + za, cc + xa  # window coordinates
    d = dist[zone]
    big = np.inf
    room = np.full(d.shape, big)
    if open_n:
        room = np.minimum(room, rr + 1)
    if open_s:
        room = np.minimum(room, (rb - ra) - rr)
    if open_w:
        room = np.minimum(room, cc + 1)
    if open_e:
        room = np.minimum(room, (cb - ca) - cc)
    return bool((d < room).all())
