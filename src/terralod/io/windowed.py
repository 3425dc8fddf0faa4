"""Window sources: a DEM read a window at a time, so a build never holds the whole raster.

A window source has the frame of a :class:`~terralod.heightfield.Heightfield` (``width``, ``height``,
``transform``, ``crs``, ``spacing_m``, ``source``, ``notes``) and one verb::

    read(r0, c0, r1, c1) -> (elevation_m (r1 - r0, c1 - c0) float32, valid (same) bool)

rows ``r0 <= r < r1``, columns ``c0 <= c < c1`` of the north-up sample grid (row 0 north), nodata cells
filled (``valid`` False there). Three kinds:

- :class:`ArraySource`: an in-memory Heightfield, sliced (its global fill is kept);
- :class:`RasterSource`: one raster GDAL opens (GeoTIFF, COG, VRT) or a mosaic of many (written as a
  VRT, hand-made XML, in memory), read by rasterio windowed reads — a COG's internal tiles are the only
  part of the file touched. Picklable (the dataset is re-opened per process and per thread), so Dask
  workers read their own windows;
- :class:`WarpedSource`: a geographic or Mercator region on a metric grid, warped block by block
  (picklable likewise).

Values are the in-memory reader's, bit for bit: ``float64(stored) * scale + offset``, then float32
(:func:`terralod.io.raster.read_raster` and :func:`terralod.fill.prepare_elevation`), so a build from a
window source of a raster without nodata has the same tiles as a build from ``read_heightfield``.

Deviations from the in-memory reader, and why:

1. Nodata fill. The in-memory fill (:func:`terralod.fill.fill_nodata`) is global (nearest valid sample,
   then Laplace relaxation). A window cannot see the whole raster, so each fixed block of
   ``FILL_BLOCK`` x ``FILL_BLOCK`` samples is filled on itself plus a halo of ``FILL_HALO`` samples
   (doubled until the halo holds a valid sample) and only its own cells are kept: a cell's value depends
   on its block alone, whichever window reads it, so neighbouring tiles agree on shared vertices (no
   cracks). Filled values differ from the global fill near block edges; valid samples never change, and
   errors are never measured on filled cells. A block with no valid sample within
   ``FILL_HALO_EXACT_MAX`` samples of it (the corners of a geographic region warped to UTM, open sea
   stored as nodata) takes one value, the valid sample nearest its centre found block by block
   (:meth:`_BlockFilled._far_value`), instead of a window grown until it reaches the data: that window's
   fill cost time and memory that grew with the region.
2. Georeferencing. :class:`RasterSource` reads rasters already in a metric frame: a projected CRS in
   metres (or in feet, re-expressed in metres as the in-memory reader does), or no CRS with
   ``spacing_m``. A geographic or Mercator raster or region (every global DEM product: SRTM, Copernicus
   GLO-30, ALOS come as EPSG:4326 1° tiles) is a :class:`WarpedSource`: the region (one grid of many
   files, :func:`terralod.io.region.resolve_region`) warped block by block to the in-memory reader's
   metric grid (the UTM zone of its centre), or to a Transverse Mercator on its central meridian when
   it spans more longitude than one UTM zone takes. Its ``original_grid`` is the region's own samples,
   against which every tile is also measured.
3. Mosaics must share one CRS, one pixel size and one grid (integer pixel offsets); anything else is
   refused in one line, never resampled silently. Cells no file covers are nodata.
"""

from __future__ import annotations

import math
import os
import threading
import warnings
from collections import OrderedDict
from collections.abc import Sequence
from pathlib import Path
from typing import Any
from xml.sax.saxutils import escape

import numpy as np
from affine import Affine

from terralod.errors import InputError, InputNotFoundError
from terralod.fill import MIN_SIDE, fill_nodata, nearest_valid_value
from terralod.heightfield import Heightfield
from terralod.io.georef import to_crs
from terralod.io.raster import crs_text, vertical_unit_m
from terralod.io.region import FILL_HALO_EXACT_MAX, _exact
from terralod.output import SpillFile, pack_block, unpack_block

__all__ = [
    "ArraySource",
    "RasterSource",
    "RegionSamples",
    "WarpedSource",
    "WindowSource",
    "open_source",
    "warp_frame",
]

#: Side of the fixed nodata-fill blocks, samples, and the halo each is filled with (see deviation 1).
FILL_BLOCK = 512
FILL_HALO = 64
#: GDAL's block cache of a process reading windows, bytes (GDAL's default, 5 % of the RAM, would hold
#: decompressed blocks up to GiBs on a large machine); left alone when GDAL_CACHEMAX is set. A work unit's
#: window (about 1024² samples of the store's grid) needs a few MiB of decompressed source blocks.
GDAL_CACHE_BYTES = 64 << 20
#: Filled blocks kept per source and process (each a (FILL_BLOCK)^2 float32 copy, 1 MiB, not a view of the
#: haloed array it was cut from): the 3 x 3 blocks of a work unit's window for each of two units in flight,
#: and their neighbours. A block is a pure function of its index, so the count changes time, not values.
FILL_CACHE_BLOCKS = 24
#: A geographic or Mercator region is warped in fixed blocks of WARP_ROWS rows by the grid's whole width
#: (cut into equal bands of at most WARP_MAX_COLS columns): GDAL's approximate transformer interpolates
#: the source position along each destination row of a chunk, so a block as wide as the grid samples where
#: a whole-grid warp does (the in-memory reader's). WARP_MARGIN_PX source pixels are read around a block's
#: transformed footprint (bilinear reads one); WARP_CACHE_SAMPLES warped samples (9 bytes each: float64 +
#: mask, 75 MB) are kept per source and process: the three block rows a row of work units reads (a unit's
#: window is about 1024 rows) on a grid 5,400 samples wide, fewer on wider grids (a block is a pure function
#: of its index, so the count changes time, not values).
WARP_ROWS = 512
WARP_MAX_COLS = 8192
WARP_MARGIN_PX = 4
WARP_CACHE_SAMPLES = 1 << 23
#: Sources whose open datasets and fill caches a process keeps for the copies that unpickle into it.
SHARED_SOURCES = 4

# One (thread-local datasets, fill cache, lock) per source and process, keyed by the source's files (their
# identities included) and read options: every copy of a source a Dask worker unpickles (one per task)
# reads through the same open datasets, so GDAL's block cache stays warm across a worker's tasks instead
# of a re-open and cold blocks per task (7 ms a work unit on the 4097² COG of benchmarks/scale.py).
_shared: OrderedDict[tuple, tuple[threading.local, OrderedDict, threading.Lock]] = OrderedDict()
_shared_lock = threading.Lock()


def _process_state(key: tuple) -> tuple[threading.local, OrderedDict, threading.Lock]:
    """This process's (datasets, fill cache, lock) of the source ``key``, the most recent few kept."""
    with _shared_lock:
        state = _shared.get(key)
        if state is None:
            state = _shared[key] = (threading.local(), OrderedDict(), threading.Lock())
            while len(_shared) > SHARED_SOURCES:
                _shared.popitem(last=False)
        _shared.move_to_end(key)
        return state


class WindowSource:
    """Base of the window sources: the frame attributes and :meth:`read` (see the module docstring)."""

    width: int
    height: int
    transform: Affine
    crs: str | None
    source: str
    notes: tuple[str, ...]
    fill_method: str = ""
    #: How a streamed build says the nodata was filled ("" for a source that fills as the in-memory reader).
    fill_note: str = ""
    #: A reprojected source's own nodata fraction, and the fraction of the grid outside its footprint.
    source_nodata_fraction: float | None = None
    margin_fraction: float = 0.0

    @property
    def shape(self) -> tuple[int, int]:
        return self.height, self.width

    @property
    def original_grid(self) -> Any:
        """The samples the user gave, when the grid is a resampling of them (anything with ``crs``,
        ``transform``, ``shape``, ``source``, ``n_valid`` and ``window(r0, r1, c0, c1)``); None when the
        grid is the source's own samples."""
        return None

    @property
    def spacing_m(self) -> tuple[float, float]:
        """(dx, dy) metres between neighbouring samples east-west and north-south."""
        return float(self.transform.a), float(-self.transform.e)

    def read(self, r0: int, c0: int, r1: int, c1: int) -> tuple[np.ndarray, np.ndarray]:
        """Elevations (float32 metres, nodata filled) and the valid mask of rows [r0, r1), cols [c0, c1)."""
        raise NotImplementedError

    def window_heightfield(self, r0: int, c0: int, r1: int, c1: int) -> Heightfield:
        """The window as a Heightfield whose transform places it in the full terrain's frame."""
        z, ok = self.read(r0, c0, r1, c1)
        t = self.transform @ Affine.translation(c0, r0)
        return Heightfield(z, ok, t, crs=self.crs, source=self.source, original_grid=self.original_grid)

    def _check_window(self, r0: int, c0: int, r1: int, c1: int) -> None:
        if not (0 <= r0 < r1 <= self.height and 0 <= c0 < c1 <= self.width):
            raise ValueError(
                f"Expected a window inside {self.height}x{self.width}, got rows [{r0}, {r1}) cols [{c0}, {c1})"
            )


class ArraySource(WindowSource):
    """An in-memory :class:`Heightfield` behind the window interface (slices; its global fill kept)."""

    def __init__(self, hf: Heightfield) -> None:
        self.hf = hf
        self.width, self.height = hf.width, hf.height
        self.transform, self.crs, self.source = hf.transform, hf.crs, hf.source
        self.notes, self.fill_method = tuple(hf.notes), hf.fill_method
        self.source_nodata_fraction = hf.source_nodata_fraction
        self.margin_fraction = hf.margin_fraction

    @property
    def original_grid(self) -> Any:
        return self.hf.original_grid

    def read(self, r0: int, c0: int, r1: int, c1: int) -> tuple[np.ndarray, np.ndarray]:
        self._check_window(r0, c0, r1, c1)
        return self.hf.elevation_m[r0:r1, c0:c1], self.hf.valid[r0:r1, c0:c1]


class _BlockFilled(WindowSource):
    """A window source whose nodata is filled per fixed block of ``FILL_BLOCK`` samples (deviation 1):
    subclasses give ``read_raw(r0, c0, r1, c1)`` (unfilled values, valid mask) and hold ``_cache`` (filled
    blocks, an LRU) and ``_lock``. With ``exact_fill`` the halo grows (64, 128, 256 samples) until the
    block's fill provably equals the whole grid's (:func:`terralod.io.region._exact`, the region reader's
    test), so a block away from large holes is filled as the in-memory reader fills it."""

    exact_fill = False
    _cache: OrderedDict[tuple[int, int], np.ndarray]
    _lock: threading.Lock

    def read_raw(self, r0: int, c0: int, r1: int, c1: int) -> tuple[np.ndarray, np.ndarray]:
        raise NotImplementedError

    def read(self, r0: int, c0: int, r1: int, c1: int) -> tuple[np.ndarray, np.ndarray]:
        values, ok = self.read_raw(r0, c0, r1, c1)
        return self._filled(values.astype(np.float32, copy=False), ok, r0, c0, r1, c1)

    def _filled(
        self, z: np.ndarray, ok: np.ndarray, r0: int, c0: int, r1: int, c1: int
    ) -> tuple[np.ndarray, np.ndarray]:
        """The window's float32 heights ``z`` with its invalid cells set from the filled blocks."""
        if ok.all():
            return z, ok
        b = FILL_BLOCK
        for br in range(r0 // b, (r1 - 1) // b + 1):
            for bc in range(c0 // b, (c1 - 1) // b + 1):
                ra, ca = max(br * b, r0), max(bc * b, c0)
                rb, cb = min((br + 1) * b, r1), min((bc + 1) * b, c1)
                if ok[ra - r0 : rb - r0, ca - c0 : cb - c0].all():
                    continue
                fz = self._filled_block(br, bc)
                z[ra - r0 : rb - r0, ca - c0 : cb - c0] = fz[
                    ra - br * b : rb - br * b, ca - bc * b : cb - bc * b
                ]
        return z, ok

    def _filled_block(self, br: int, bc: int) -> np.ndarray:
        """Fill block (br, bc) on itself plus a halo that holds a valid sample (deviation 1), cached."""
        key = (br, bc)
        with self._lock:
            if key in self._cache:
                self._cache.move_to_end(key)
                return self._cache[key]
        b = FILL_BLOCK
        r0, c0 = br * b, bc * b
        r1, c1 = min(r0 + b, self.height), min(c0 + b, self.width)
        halo = FILL_HALO
        while True:
            ra, ca = max(r0 - halo, 0), max(c0 - halo, 0)
            rb, cb = min(r1 + halo, self.height), min(c1 + halo, self.width)
            values, ok = self.read_raw(ra, ca, rb, cb)
            whole = ra == 0 and ca == 0 and rb == self.height and cb == self.width
            if ok.any() and (not self.exact_fill or whole or halo >= FILL_HALO_EXACT_MAX
                             or _exact(ok, (ra, rb, ca, cb), (r0, r1, c0, c1), self.shape)):  # fmt: skip
                break
            if whole:
                break
            if halo >= FILL_HALO_EXACT_MAX:  # far from every valid sample: one value, found block by block
                break
            halo *= 2
        if ok.any():
            # a copy: a view would keep the haloed array (up to (FILL_BLOCK + 2 FILL_HALO_EXACT_MAX)^2) alive
            filled = np.array(fill_nodata(values, ok)[r0 - ra : r1 - ra, c0 - ca : c1 - ca], np.float32)
        else:
            filled = np.full((r1 - r0, c1 - c0), self._far_value(br, bc), np.float32)
        del values, ok
        with self._lock:
            self._cache[key] = filled
            while len(self._cache) > FILL_CACHE_BLOCKS:
                self._cache.popitem(last=False)
        return filled

    def _far_value(self, br: int, bc: int) -> float:
        """The one value of a block with no valid sample within ``FILL_HALO_EXACT_MAX`` of it (deviation
        1): :func:`terralod.fill.nearest_valid_value`, blocks read one at a time, each read for its
        validity once per source, so memory stays one block whatever the distance (a haloed window grown to
        reach the data held up to (FILL_BLOCK + 2 x distance)² samples: the exterior wedges of a 64-tile
        SRTM3 region warped to UTM are thousands of samples wide)."""
        b = FILL_BLOCK

        def block(i: int, j: int) -> tuple[np.ndarray, np.ndarray, int, int]:
            values, ok = self.read_raw(i * b, j * b, min(i * b + b, self.height), min(j * b + b, self.width))
            return values, ok, i * b, j * b

        centre = (
            (br * b + min((br + 1) * b, self.height) - 1) / 2.0,
            (bc * b + min((bc + 1) * b, self.width) - 1) / 2.0,
        )
        got = nearest_valid_value((br, bc), (-(-self.height // b), -(-self.width // b)), centre,
                                  self._block_has_valid, block)  # fmt: skip
        if got is None:
            raise InputError("band has no valid samples (all nodata)", self.source)
        return got

    def _block_has_valid(self, i: int, j: int) -> bool:
        """Whether fill block (i, j) holds a valid sample (one bool a block, kept for the source)."""
        flags = self.__dict__.setdefault("_has_valid", {})
        got = flags.get((i, j))
        if got is None:
            b = FILL_BLOCK
            _, ok = self.read_raw(i * b, j * b, min(i * b + b, self.height), min(j * b + b, self.width))
            got = flags[(i, j)] = bool(ok.any())
        return got


class RasterSource(_BlockFilled):
    """One band of a raster (or a mosaic of rasters) read window by window with rasterio.

    Parameters
    ----------
    paths : one path, or several (a mosaic on one grid, see deviation 3 of the module docstring).
    band : 1-based band index.
    vertical_scale, vertical_offset : elevation_m = value * scale + offset; default to the band's tags.
    nodata : stored value marking missing samples, used only when the band has no nodata of its own.
    spacing_m : (dx, dy) metres for a raster without CRS (local frame, origin at its north-west corner).
    """

    def __init__(
        self,
        paths: str | Path | Sequence[str | Path],
        *,
        band: int = 1,
        vertical_scale: float | None = None,
        vertical_offset: float | None = None,
        nodata: float | None = None,
        spacing_m: float | tuple[float, float] | None = None,
        crs: Any = None,
    ) -> None:
        plist = [Path(paths)] if isinstance(paths, str | Path) else [Path(p) for p in paths]
        if not plist:
            raise InputError("no input files given")
        for p in plist:
            if not p.exists():
                raise InputNotFoundError("file not found", str(p))
        self.paths = [str(p) for p in plist]
        self.band = int(band)
        self.source = (
            self.paths[0] if len(plist) == 1 else f"mosaic of {len(plist)} files ({self.paths[0]}, ...)"
        )
        self._vrt = _mosaic_vrt(self.paths, self.band) if len(plist) > 1 else None
        # the files as they are now: a file replaced or rewritten later is another source
        self._files = tuple((st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns) for st in map(os.stat, plist))
        self._local = threading.local()
        self._cache: OrderedDict[tuple[int, int], np.ndarray] = OrderedDict()
        self._lock = threading.Lock()
        ds = self._dataset()
        src = self.paths[0] if self._vrt is None else self.source
        if ds.height < MIN_SIDE or ds.width < MIN_SIDE:  # no upper bound: nothing is held whole
            raise InputError(
                f"raster is {ds.width}x{ds.height} samples; at least {MIN_SIDE}x{MIN_SIDE} needed", src
            )
        if self.band > ds.count:
            raise InputError(f"has {ds.count} band(s); band {band} requested", src)
        scale_tag = (ds.scales or (1.0,) * ds.count)[self.band - 1]
        offset_tag = (ds.offsets or (0.0,) * ds.count)[self.band - 1]
        self.scale = float(vertical_scale) if vertical_scale is not None else float(scale_tag or 1.0)
        self.offset = float(vertical_offset) if vertical_offset is not None else float(offset_tag or 0.0)
        if not (math.isfinite(self.scale) and math.isfinite(self.offset)) or self.scale == 0.0:
            raise InputError(f"vertical scale and offset must be finite and the scale non-zero, got "
                             f"{self.scale:g}, {self.offset:g}", src)  # fmt: skip
        self.nodata_hint = None
        if ds.nodatavals[self.band - 1] is None and nodata is not None and not math.isnan(nodata):
            self.nodata_hint = float(nodata)
        self.fill_note = f"filled per {FILL_BLOCK}-sample block (halo {FILL_HALO}) with the nearest valid sample, then relaxed"
        self.file_height, self.file_width = ds.height, ds.width
        self.width, self.height = ds.width, ds.height
        self.transform, self.crs, self.notes, self.flip_rows, self.flip_cols = _metric_frame(
            ds, spacing_m, src, crs
        )
        vunit = vertical_unit_m(ds.crs if crs is None else to_crs(crs, src)) if self.crs is not None else None
        if vunit is not None and vertical_scale is None and self.scale == 1.0:
            self.scale = vunit[1]  # heights in the unit the CRS's vertical axis names
            self.notes = (
                *self.notes,
                f"heights in {vunit[0]} (the CRS's vertical axis): x {vunit[1]:.10g} to metres",
            )
        if self.scale != 1.0 or self.offset != 0.0:
            self.notes = (*self.notes, f"elevation_m = stored value * {self.scale:g} + {self.offset:g}")

    # -- pickling: the dataset and the fill cache stay in their process ---------------------------------
    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        for key in ("_local", "_cache", "_lock"):
            state.pop(key)
        state.pop("_has_valid", None)
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        """A copy shares the datasets and fill cache of this process's earlier copies of the same source."""
        self.__dict__.update(state)
        key = (tuple(self.paths), self.band, self._files, self.scale, self.offset, self.nodata_hint,
               self.flip_rows, self.flip_cols, self.transform)  # fmt: skip
        self._local, self._cache, self._lock = _process_state(key)

    def _dataset(self):
        """This thread's open dataset (rasterio datasets are not shared between threads)."""
        import rasterio
        from rasterio.errors import NotGeoreferencedWarning

        ds = getattr(self._local, "ds", None)
        if ds is None:
            if "GDAL_CACHEMAX" not in os.environ:
                from rasterio._env import set_gdal_config

                set_gdal_config("GDAL_CACHEMAX", GDAL_CACHE_BYTES)
            target = self._vrt if self._vrt is not None else self.paths[0]
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", NotGeoreferencedWarning)
                    ds = rasterio.open(target)
            except Exception as exc:
                from terralod.io.raster import error_line

                raise InputError(f"not a raster GDAL can read ({error_line(exc)})", self.paths[0]) from None
            self._local.ds = ds
        return ds

    def close(self) -> None:
        ds = getattr(self._local, "ds", None)
        if ds is not None:
            ds.close()
            self._local.ds = None

    # -- reading -----------------------------------------------------------------------------------------
    def read_raw(self, r0: int, c0: int, r1: int, c1: int) -> tuple[np.ndarray, np.ndarray]:
        """Unfilled elevations (metres, float64 when scaled, else float32; arbitrary where invalid) and the valid
        mask of the window."""
        from rasterio.windows import Window

        self._check_window(r0, c0, r1, c1)
        fr0, fr1 = (self.height - r1, self.height - r0) if self.flip_rows else (r0, r1)
        fc0, fc1 = (self.width - c1, self.width - c0) if self.flip_cols else (c0, c1)
        try:
            data = self._dataset().read(self.band, window=Window(fc0, fr0, fc1 - fc0, fr1 - fr0), masked=True)
        except InputError:
            raise
        except Exception as exc:
            from terralod.io.raster import error_line

            raise InputError(f"cannot read rows {r0}-{r1} ({error_line(exc)})", self.source) from None
        raw = np.ma.getdata(data)
        ok = ~np.ma.getmaskarray(data)
        if self.flip_rows:
            raw, ok = raw[::-1], ok[::-1]
        if self.flip_cols:
            raw, ok = raw[:, ::-1], ok[:, ::-1]
        if self.nodata_hint is not None:
            ok &= raw != self.nodata_hint
        if self.scale != 1.0 or self.offset != 0.0:
            values = raw.astype(np.float64)
            values *= self.scale
            values += self.offset
        else:  # float64 then float32 (the in-memory reader) rounds as float32 directly does
            values = raw.astype(np.float32)
        ok &= np.isfinite(values)
        return values, np.ascontiguousarray(ok)


class RegionSamples:
    """A region's own samples, read window by window: the original grid a reprojected source's tiles are
    measured against (:mod:`terralod.pyramid.original`; the windowed twin of
    :class:`terralod.io.raster.OriginalGrid`).

    Attributes
    ----------
    crs : WKT of the region's CRS (geographic or Mercator); transform : its north-up pixel-corner transform;
    shape : (rows, cols); source : the region's name; n_valid : its valid samples (counted by one scan).
    """

    def __init__(self, region: Any, n_valid: int) -> None:
        from terralod.io.region import RegionReader

        self.region = region
        self.crs: str = region.crs.to_wkt()
        self.transform: Affine = region.transform
        self.source: str = region.name
        self.n_valid = int(n_valid)
        self.reader = RegionReader(region, cache_blocks=0)

    @property
    def shape(self) -> tuple[int, int]:
        return int(self.region.height), int(self.region.width)

    def window(self, r0: int, r1: int, c0: int, c1: int) -> tuple[np.ndarray, np.ndarray]:
        """(values, valid) of rows ``r0 <= r < r1``, columns ``c0 <= c < c1`` (clipped to the grid); values
        as the single-file reader reads them (scale and offset applied), arbitrary where invalid."""
        h, w = self.shape
        r0, r1, c0, c1 = max(0, r0), min(h, r1), max(0, c0), min(w, c1)
        if r1 <= r0 or c1 <= c0:
            return np.zeros((max(r1 - r0, 0), max(c1 - c0, 0))), np.zeros(
                (max(r1 - r0, 0), max(c1 - c0, 0)), bool
            )
        return self.reader.read_raw(r0, r1, c0, c1)


class _WarpState:
    """What a process keeps of a warped source (shared by the copies Dask unpickles into it): the region's
    samples (one object, so the position cache of :mod:`terralod.pyramid.original` stays warm), the
    warped blocks and the filled blocks (LRUs), one lock."""

    def __init__(self, region: Any, n_valid: int) -> None:
        self.original = RegionSamples(region, n_valid)
        self.warped: OrderedDict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = OrderedDict()
        self.filled: OrderedDict[tuple[int, int], np.ndarray] = OrderedDict()
        self.lock = threading.Lock()
        #: warped blocks the LRU dropped (float64 heights and a bit a sample), read back instead of warped
        #: again: a build's finer levels sweep the grid in units whose windows cut across the block rows
        self.spill = SpillFile("terralod-warped-")
        self.spilled: set[tuple[int, int]] = set()
        self.blocks_warped = 0  #: blocks warped from the source (cache and spill misses), for benchmarks


_warp_states: OrderedDict[tuple, _WarpState] = OrderedDict()


def _warp_state(key: tuple, region: Any, n_valid: int) -> _WarpState:
    """This process's :class:`_WarpState` of the warped source ``key``, the most recent few kept."""
    with _shared_lock:
        state = _warp_states.get(key)
        if state is None:
            state = _warp_states[key] = _WarpState(region, n_valid)
            while len(_warp_states) > SHARED_SOURCES:
                _warp_states.popitem(last=False)
        _warp_states.move_to_end(key)
        return state


class WarpedSource(_BlockFilled):
    """A geographic (or Mercator) region presented on a metric grid, warped block by block.

    The region is what :func:`terralod.io.region.resolve_region` makes of the inputs (files, globs,
    folders, VRTs, ``.hgt``/``.hgt.zip``: one grid, the last file wins, gaps nodata). The metric grid is
    the in-memory reader's (:func:`terralod.io.raster.reproject_to_utm`): the UTM zone (UPS beyond 84 N /
    80 S) of the region's centre, square pixels of the ground spacing at the centre (the smaller of dx,
    dy, millimetre-rounded), snapped to multiples of it over the transformed bounds. A region wider than
    ``MAX_UTM_SPAN_DEG`` degrees of longitude, which that reader refuses, gets a Transverse Mercator on
    the WGS 84 ellipsoid centred on its central meridian (scale 1 there, false origin 0, 0) instead.

    The grid is warped in fixed blocks of ``WARP_ROWS`` rows by its whole width (equal bands of at most
    ``WARP_MAX_COLS`` columns), each from the source window its footprint needs plus ``WARP_MARGIN_PX``
    pixels (``rasterio.warp.reproject``): elevations bilinear over the valid samples (NaN nodata), the valid
    mask nearest, cells outside the region invalid — the in-memory reader's calls, with GDAL's kernel
    scale fixed to the whole grid's ratio. A block is a pure function of its index, whichever window reads
    it. Then nodata is filled per ``FILL_BLOCK`` block with the exact halo of :class:`_BlockFilled`.

    Against the in-memory reader (one SRTM3 tile, N42E001, 1230 x 1644 samples in UTM 31N): the same
    frame and valid mask, the same filled cells, and 2 of its 1.94 M valid samples one float32 step apart
    (0.00024 m: GDAL's source coordinates relative to a block's window, not the whole file's). A grid
    wider than ``WARP_MAX_COLS``, or one GDAL's in-memory warp cuts into several chunks (over its 64 MB
    working memory), resamples where the approximate transformer puts each chunk's rows (within 0.125
    source pixels of the exact position) and may differ further. Memory: ``WARP_CACHE_SAMPLES`` warped
    samples and ``FILL_CACHE_BLOCKS`` filled blocks, whatever the region's size. A warped block the LRU
    drops goes to a spill file (:class:`terralod.output.SpillFile`, beside the output: 8.1 bytes a sample)
    and comes back from it as the same bytes: the units of a build's finer levels cut across the block
    rows, and without it a 16-tile SRTM3 build warped its blocks again and again (reproject 40 % of its
    CPU; with it, 272 -> 180 CPU s, the same store).

    ``original_grid`` (:class:`RegionSamples`) is the region's own samples, against which every stored
    error is also measured (:mod:`terralod.pyramid.original`).
    """

    exact_fill = True

    def __init__(
        self,
        inputs: str | Path | Sequence[str | Path],
        *,
        vertical_scale: float | None = None,
        vertical_offset: float | None = None,
        crs: Any = None,
    ) -> None:
        import dataclasses

        from terralod.io.georef import assign_crs, check_area_of_use
        from terralod.io.region import resolve_region, scan_region

        region = resolve_region(inputs, crs=crs)
        src = region.name
        notes: list[str] = []
        if crs is not None:
            _, note = assign_crs(crs, _file_crs(region.footprints[0].path), src)
            notes.append(note)
        scale = float(vertical_scale) if vertical_scale is not None else region.scale
        offset = float(vertical_offset) if vertical_offset is not None else region.offset
        vunit = vertical_unit_m(region.crs)
        if vunit is not None and vertical_scale is None and scale == 1.0:
            scale = vunit[1]
            notes.append(f"heights in {vunit[0]} (the CRS's vertical axis): x {vunit[1]:.10g} to metres")
        if not (math.isfinite(scale) and math.isfinite(offset)) or scale == 0.0:
            raise InputError(f"vertical scale and offset must be finite and the scale non-zero, got "
                             f"{scale:g}, {offset:g}", src)  # fmt: skip
        if (scale, offset) != (region.scale, region.offset):
            region = dataclasses.replace(region, scale=scale, offset=offset)
        if scale != 1.0 or offset != 0.0:
            notes.append(f"elevation_m = stored value * {scale:g} + {offset:g}")
        scan_region(region)  # every file decoded once, a bad one named, before anything is written
        n_valid = _count_valid(region)  # on the grid: cells files share (SRTM's edges) count once
        h, w = region.shape
        if h < MIN_SIDE or w < MIN_SIDE:
            raise InputError(f"raster is {w}x{h} samples; at least {MIN_SIDE}x{MIN_SIDE} needed", src)
        notes += check_area_of_use(region.crs, region.bounds, src)
        dst_crs, t, width, height, note, margin = warp_frame(region.crs, region.transform, (h, w), src)
        self.region, self.n_valid = region, n_valid
        self.source = src
        self.paths = [f.shown for f in region.footprints]
        self._files = tuple(_identity(f.shown) for f in region.footprints)
        self.src_crs = region.crs
        self.dst_crs = dst_crs
        self.crs = crs_text(dst_crs)
        self.transform, self.width, self.height = t, width, height
        self.notes = (*notes, note)
        self.source_nodata_fraction = 1.0 - n_valid / float(h * w)
        self.margin_fraction = margin
        self.fill_note = (
            f"filled per {FILL_BLOCK}-sample block on a halo grown ({FILL_HALO} to {FILL_HALO_EXACT_MAX} "
            "samples) until it equals the whole grid's fill, with the nearest valid sample, then relaxed"
        )
        self._attach()

    # -- process state: shared by every copy of this source in a process ------------------------------------
    def _key(self) -> tuple:
        return (tuple(self.paths), self._files, self.region.scale, self.region.offset, self.transform,
                self.width, self.height, self.crs)  # fmt: skip

    def _attach(self) -> None:
        self._state = _warp_state(self._key(), self.region, self.n_valid)
        self._cache, self._lock = self._state.filled, self._state.lock

    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        for key in ("_state", "_cache", "_lock"):
            state.pop(key)
        state.pop("_has_valid", None)
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self._attach()

    @property
    def original_grid(self) -> RegionSamples:
        """The region's own samples (this process's one object for this source)."""
        return self._state.original

    def close(self) -> None:
        self._state.original.reader.close()

    # -- reading -------------------------------------------------------------------------------------------
    def read(self, r0: int, c0: int, r1: int, c1: int) -> tuple[np.ndarray, np.ndarray]:
        z, ok = self._assembled(r0, c0, r1, c1, np.float32)  # float32 at once: no float64 copy of the window
        return self._filled(z, ok, r0, c0, r1, c1)

    def read_raw(self, r0: int, c0: int, r1: int, c1: int) -> tuple[np.ndarray, np.ndarray]:
        """Warped elevations (float64 metres, NaN where invalid) and the valid mask of the window,
        assembled from the warped blocks."""
        return self._assembled(r0, c0, r1, c1, np.float64)

    def _assembled(self, r0: int, c0: int, r1: int, c1: int, dtype: Any) -> tuple[np.ndarray, np.ndarray]:
        self._check_window(r0, c0, r1, c1)
        b = WARP_ROWS
        edges = self._bands
        z = np.empty((r1 - r0, c1 - c0), dtype)
        ok = np.empty((r1 - r0, c1 - c0), bool)
        for br in range(r0 // b, (r1 - 1) // b + 1):
            for bc in range(len(edges) - 1):
                ba, bb = edges[bc], edges[bc + 1]
                if bb <= c0 or ba >= c1:
                    continue
                bz, bok = self._warped_block(br, bc)
                ra, rb = max(br * b, r0), min((br + 1) * b, r1)
                ca, cb = max(ba, c0), min(bb, c1)
                z[ra - r0 : rb - r0, ca - c0 : cb - c0] = bz[ra - br * b : rb - br * b, ca - ba : cb - ba]
                ok[ra - r0 : rb - r0, ca - c0 : cb - c0] = bok[ra - br * b : rb - br * b, ca - ba : cb - ba]
        return z, ok

    @property
    def _bands(self) -> list[int]:
        """Column edges of the warped blocks: the width cut into equal bands of at most WARP_MAX_COLS."""
        n = -(-self.width // WARP_MAX_COLS)
        return [round(k * self.width / n) for k in range(n + 1)]

    def _warped_block(self, br: int, bc: int) -> tuple[np.ndarray, np.ndarray]:
        st = self._state
        key = (br, bc)
        with st.lock:
            hit = st.warped.get(key)
            if hit is not None:
                st.warped.move_to_end(key)
                return hit
        got = self._unspilled(br, bc)
        warped = got is None
        if got is None:
            got = self._warp_block(br, bc)
        with st.lock:
            st.blocks_warped += warped
            st.warped[key] = got
            kept = sum(v[0].size for v in st.warped.values())
            while kept > WARP_CACHE_SAMPLES and len(st.warped) > 1:
                old, block = st.warped.popitem(last=False)
                kept -= block[0].size
                self._spill(old, block)
        return got

    def _spill_slot(self, br: int, bc: int) -> tuple[int, int]:
        """(offset, samples) of warped block (br, bc)'s slot in the spill file: the heights as float64,
        then the validity bits; every slot is the widest band's size."""
        edges = self._bands
        widest = max(b - a for a, b in zip(edges[:-1], edges[1:], strict=False))
        n = WARP_ROWS * widest
        slot = 8 * n + (n + 7) // 8
        return (br * (len(edges) - 1) + bc) * slot, (min(WARP_ROWS, self.height - br * WARP_ROWS)
                                                      * (edges[bc + 1] - edges[bc]))  # fmt: skip

    def _spill(self, key: tuple[int, int], block: tuple[np.ndarray, np.ndarray]) -> None:
        """Keep a warped block the LRU drops in the spill file (the caller holds the lock); one the file
        declines (its disk's reserve reached) is warped again when asked."""
        st = self._state
        if key in st.spilled:
            return
        z, ok = block
        if st.spill.put(self._spill_slot(*key)[0], pack_block(z, ok, np.float64)):
            st.spilled.add(key)

    def _unspilled(self, br: int, bc: int) -> tuple[np.ndarray, np.ndarray] | None:
        """Warped block (br, bc) read back from the spill file (the same bytes), or None."""
        st = self._state
        with st.lock:
            if (br, bc) not in st.spilled:
                return None
        offset, n = self._spill_slot(br, bc)
        edges = self._bands
        shape = (n // (edges[bc + 1] - edges[bc]), edges[bc + 1] - edges[bc])
        return unpack_block(st.spill.get(offset, 8 * n + (n + 7) // 8), np.float64, shape)  # read-only

    def _warp_block(self, br: int, bc: int) -> tuple[np.ndarray, np.ndarray]:
        """Block (br, bc) warped from its source window (see the class docstring)."""
        from rasterio.warp import Resampling, reproject, transform_bounds

        edges = self._bands
        r0, c0 = br * WARP_ROWS, edges[bc]
        r1, c1 = min(r0 + WARP_ROWS, self.height), edges[bc + 1]
        bt = self.transform @ Affine.translation(c0, r0)
        out = np.full((r1 - r0, c1 - c0), np.nan, np.float64)
        mask = np.zeros((r1 - r0, c1 - c0), np.uint8)
        west, north = bt @ (0, 0)
        east, south = bt @ (c1 - c0, r1 - r0)
        st = self.region.transform
        h, w = self.region.shape
        try:
            sw, ss, se, sn = transform_bounds(
                self.dst_crs, self.src_crs, west, south, east, north, densify_pts=21
            )
        except Exception:  # noqa: BLE001 - a block PROJ cannot place in the source's CRS: the whole source
            sw, ss, se, sn = self.region.bounds
        if self.src_crs.is_geographic and se < sw:  # across the antimeridian: the whole width
            sw, se = st.c, st.c + w * st.a
        m = WARP_MARGIN_PX
        ca = max(int(math.floor((sw - st.c) / st.a)) - m, 0)
        cb = min(int(math.ceil((se - st.c) / st.a)) + m, w)
        ra = max(int(math.floor((sn - st.f) / st.e)) - m, 0)
        rb = min(int(math.ceil((ss - st.f) / st.e)) + m, h)
        if cb <= ca or rb <= ra:
            return out, mask.astype(bool)
        values, valid = self._state.original.reader.read_raw(ra, rb, ca, cb)
        src = np.where(valid, values.astype(np.float64), np.nan)
        # GDAL sizes its resampling kernel by the destination/source pixel ratio of each chunk it warps;
        # the whole grid's ratio is given, so every block resamples as one whole-grid warp does
        kw = {"src_transform": st @ Affine.translation(ca, ra), "src_crs": self.src_crs, "dst_transform": bt,
              "dst_crs": self.dst_crs, "XSCALE": repr(self.width / w), "YSCALE": repr(self.height / h)}  # fmt: skip
        reproject(src, out, resampling=Resampling.bilinear, src_nodata=np.nan, dst_nodata=np.nan, **kw)
        reproject(np.ascontiguousarray(valid, dtype=np.uint8), mask, resampling=Resampling.nearest,
                  src_nodata=None, dst_nodata=0, **kw)  # fmt: skip
        return out, (mask > 0) & np.isfinite(out)


def warp_frame(
    crs: Any, t: Affine, shape: tuple[int, int], source: str
) -> tuple[Any, Affine, int, int, str, float]:
    """The metric grid a geographic or Mercator grid is warped to (:class:`WarpedSource`'s rule, the
    in-memory reader's for a region one UTM zone takes): (CRS, north-up transform, width, height, note,
    fraction of the grid outside the source's footprint). Refuses, in one line, bounds off the globe and a
    grid that would grow over ``MAX_REPROJECT_GROWTH`` times."""
    from rasterio.warp import transform as warp_points

    from terralod.io.raster import _crs_name, metric_grid

    h, w = shape
    west, south, east, north = t.c, t.f + h * t.e, t.c + w * t.a, t.f
    dst_crs, label, dst_t, width, height, res, dx_m, dy_m, wide = metric_grid(
        crs, t, shape, source, wide_ok=True
    )
    # the footprint's area in the target CRS (its edges densified), for the margin fraction
    f = np.linspace(0.0, 1.0, 257)[:-1]
    ex = np.concatenate(
        [west + f * (east - west), np.full(f.size, east), east - f * (east - west), np.full(f.size, west)]
    )
    ey = np.concatenate(
        [
            np.full(f.size, north),
            north - f * (north - south),
            np.full(f.size, south),
            south + f * (north - south),
        ]
    )
    try:
        px, py = (np.asarray(v, np.float64) for v in warp_points(crs, dst_crs, ex, ey))
        area = 0.5 * abs(float(np.dot(px, np.roll(py, -1)) - np.dot(py, np.roll(px, -1))))
        margin = min(max(1.0 - area / (width * height * res * res), 0.0), 1.0)
    except Exception:  # noqa: BLE001 - a statistic only
        margin = 0.0
    note = (
        f"reprojected from {_crs_name(crs)} to {_crs_name(dst_crs)} ({label}) at {res:g} m, bilinear "
        f"(ground spacing at the centre {dx_m:.1f} x {dy_m:.1f} m), block by block out of core{wide}"
    )
    return dst_crs, dst_t, width, height, note, margin


def _count_valid(region: Any) -> int:
    """Valid samples of the region's grid, read in strips of rows (each cell once, whichever files
    cover it)."""
    from terralod.io.region import SCAN_STRIP_SAMPLES, RegionReader

    reader = RegionReader(region, cache_blocks=0)
    h, w = region.shape
    step = max(1, SCAN_STRIP_SAMPLES // w)
    try:
        return sum(
            int(np.count_nonzero(reader.read_raw(a, min(a + step, h), 0, w)[1])) for a in range(0, h, step)
        )
    finally:
        reader.close()


def _file_crs(name: str) -> Any:
    """A file's own CRS (None when it has none or cannot be opened: the reader reports that)."""
    import rasterio

    try:
        with rasterio.open(name) as ds:
            return ds.crs
    except Exception:  # noqa: BLE001
        return None


def _identity(path: str) -> tuple[int, int, int, int]:
    st = os.stat(path)
    return (st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns)


def needs_warp(inputs: str | Path | Sequence[str | Path], crs: Any = None) -> bool:
    """True when the inputs (files, globs, folders, as :func:`terralod.io.region.resolve_region` takes
    them) are in a geographic or Mercator CRS (``crs``: ``--crs``, assigned or overriding): they build
    through :class:`WarpedSource`. False when the first file cannot be placed (its reader says why)."""
    from terralod.io.raster import _is_mercator
    from terralod.io.region import expand_inputs

    try:
        name = expand_inputs([inputs] if isinstance(inputs, str | Path) else list(inputs))[0][0]
        own = to_crs(crs, name) if crs is not None else _file_crs(name)
    except Exception:  # noqa: BLE001 - the reader reports it
        return False
    return own is not None and (bool(own.is_geographic) or _is_mercator(own))


def open_source(paths: str | Path | Sequence[str | Path], **options: Any) -> RasterSource | WarpedSource:
    """The window source of one raster or a mosaic: a :class:`WarpedSource` for a geographic or Mercator
    one, else a :class:`RasterSource` (see :class:`RasterSource` for ``options``)."""
    if needs_warp(paths, options.get("crs")):
        return WarpedSource(paths, vertical_scale=options.get("vertical_scale"),
                            vertical_offset=options.get("vertical_offset"), crs=options.get("crs"))  # fmt: skip
    return RasterSource(paths, **options)


# -- frame ---------------------------------------------------------------------------------------------
def _metric_frame(
    ds, spacing_m, src: str, given_crs: Any = None
) -> tuple[Affine, str | None, tuple[str, ...], bool, bool]:
    """(north-up metric transform, CRS WKT or None, notes, flip rows, flip cols) of a dataset, as
    :func:`terralod.io.raster.read_raster` places it (``given_crs``: ``--crs``, assigned or overriding);
    geographic and Mercator CRSs are refused."""
    from terralod.io.georef import assign_crs, check_area_of_use
    from terralod.io.raster import _is_mercator, _metric_units, _scale_note, crs_text

    t, crs = ds.transform, ds.crs
    notes: list[str] = []
    if given_crs is not None:
        crs, note = assign_crs(given_crs, crs, src)
        notes.append(note)
    has_transform = not t.is_identity
    if has_transform and (t.b != 0 or t.d != 0):
        raise InputError(f"has a rotated or sheared geotransform {tuple(t)[:6]}; warp it north-up first "
                         "(gdalwarp -t_srs <its CRS>)", src)  # fmt: skip
    h, w = ds.height, ds.width
    if crs is None or not has_transform:
        if spacing_m is None:
            raise InputError("has no CRS; pass spacing_m (CLI --spacing DX[,DY]) in metres for a local frame",
                             src)  # fmt: skip
        dx, dy = (spacing_m, spacing_m) if np.isscalar(spacing_m) else spacing_m
        if has_transform:
            notes.append("geotransform ignored: the file has no CRS")
        notes.append(f"local metric frame at {dx:g} m (no CRS)" if dx == dy else
                     f"local metric frame at {dx:g} x {dy:g} m (no CRS)")  # fmt: skip
        return Affine(float(dx), 0.0, 0.0, 0.0, -float(dy), 0.0), None, tuple(notes), False, False
    if crs.is_geographic or _is_mercator(crs):
        raise InputError(
            f"is in {'a geographic' if crs.is_geographic else 'a Mercator'} CRS; RasterSource reads metric grids "
            "only: open it with open_source (a WarpedSource, warped block by block), or reproject it first "
            "(gdalwarp -t_srs EPSG:<UTM zone>)",
            src,
        )
    flip_rows, flip_cols = t.e > 0, t.a < 0
    if flip_rows:
        t = Affine(t.a, 0.0, t.c, 0.0, -t.e, t.f + t.e * h)
        notes.append("rows flipped: the source is south-up")
    if flip_cols:
        t = Affine(-t.a, 0.0, t.c + t.a * w, 0.0, t.e, t.f)
        notes.append("columns flipped: the source runs east to west")
    notes += check_area_of_use(crs, (t.c, t.f + h * t.e, t.c + w * t.a, t.f), src)
    crs_m, t, unit_notes = _metric_units(crs, t, src)
    notes += [*unit_notes, *_scale_note(t, crs_m, (h, w))]
    return t, crs_text(crs_m), tuple(notes), flip_rows, flip_cols


# -- mosaics -------------------------------------------------------------------------------------------
def _mosaic_vrt(paths: list[str], band: int) -> str:
    """VRT XML of a mosaic of rasters on one grid (same CRS and pixel size, integer offsets); refuses
    anything else in one line. Cells no file covers are nodata (NaN)."""
    import rasterio

    infos = []
    for p in paths:
        try:
            with rasterio.open(p) as ds:
                if band > ds.count:
                    raise InputError(f"has {ds.count} band(s); band {band} requested", p)
                infos.append((p, ds.crs, ds.transform, ds.width, ds.height, ds.nodatavals[band - 1],
                              ds.dtypes[band - 1], (ds.scales or (1.0,))[band - 1],
                              (ds.offsets or (0.0,))[band - 1]))  # fmt: skip
        except InputError:
            raise
        except Exception as exc:
            from terralod.io.raster import error_line

            raise InputError(f"not a raster GDAL can read ({error_line(exc)})", p) from None
    p0, crs0, t0 = infos[0][0], infos[0][1], infos[0][2]
    for p, crs, t, *_rest in infos[1:]:
        if crs != crs0:
            raise InputError(f"mosaic: its CRS differs from {p0}'s; reproject the tiles to one CRS first "
                             "(gdalwarp -t_srs ...)", p)  # fmt: skip
        if not (math.isclose(t.a, t0.a, rel_tol=1e-9) and math.isclose(t.e, t0.e, rel_tol=1e-9)):
            raise InputError(f"mosaic: its pixel size {t.a:g} x {-t.e:g} differs from {p0}'s {t0.a:g} x "
                             f"{-t0.e:g}; resample the tiles to one resolution first (gdalwarp -tr ...)", p)  # fmt: skip
        if t.b or t.d or t.a <= 0 or t.e >= 0:
            raise InputError("mosaic: tiles must be north-up; warp it first (gdalwarp)", p)
    if t0.b or t0.d or t0.a <= 0 or t0.e >= 0:
        raise InputError("mosaic: tiles must be north-up; warp it first (gdalwarp)", p0)
    if len({(i[7], i[8]) for i in infos}) > 1:
        raise InputError("mosaic: the tiles' vertical scale/offset tags differ", p0)
    west = min(t.c for _, _, t, *_ in infos)
    north = max(t.f for _, _, t, *_ in infos)
    offs = []
    for p, _, t, *_ in infos:
        fx, fy = (t.c - west) / t0.a, (north - t.f) / -t0.e
        if abs(fx - round(fx)) > 1e-6 or abs(fy - round(fy)) > 1e-6:
            raise InputError(f"mosaic: not on {p0}'s grid (offset {fx:.3f}, {fy:.3f} pixels); resample it "
                             "onto one grid first (gdalwarp -tap)", p)  # fmt: skip
        offs.append((round(fx), round(fy)))
    width = max(ox + i[3] for (ox, _), i in zip(offs, infos, strict=True))
    height = max(oy + i[4] for (_, oy), i in zip(offs, infos, strict=True))
    scale, offset = infos[0][7] or 1.0, infos[0][8] or 0.0
    srcs = []
    for (ox, oy), (p, _, _, w, h, nd, *_r) in zip(offs, infos, strict=True):
        nd_xml = f"<NODATA>{nd!r}</NODATA>" if nd is not None else ""
        srcs.append(
            f'<ComplexSource><SourceFilename relativeToVRT="0">{escape(str(Path(p).resolve()))}</SourceFilename>'
            f'<SourceBand>{band}</SourceBand><SrcRect xOff="0" yOff="0" xSize="{w}" ySize="{h}"/>'
            f'<DstRect xOff="{ox}" yOff="{oy}" xSize="{w}" ySize="{h}"/>{nd_xml}</ComplexSource>'
        )
    gt = f"{west!r}, {t0.a!r}, 0.0, {north!r}, 0.0, {t0.e!r}"
    return (
        f'<VRTDataset rasterXSize="{width}" rasterYSize="{height}">'
        f"<SRS>{escape(crs0.to_wkt()) if crs0 else ''}</SRS><GeoTransform>{gt}</GeoTransform>"
        f'<VRTRasterBand dataType="Float64" band="1"><NoDataValue>nan</NoDataValue>'
        f"<Offset>{offset!r}</Offset><Scale>{scale!r}</Scale>{''.join(srcs)}</VRTRasterBand></VRTDataset>"
    )
