"""Window sources: a DEM read a window at a time, so a build never holds the whole raster.

A window source has the frame of a :class:`~terralod.heightfield.Heightfield` (``width``, ``height``,
``transform``, ``crs``, ``spacing_m``, ``source``, ``notes``) and one verb::

    read(r0, c0, r1, c1) -> (elevation_m (r1 - r0, c1 - c0) float32, valid (same) bool)

rows ``r0 <= r < r1``, columns ``c0 <= c < c1`` of the north-up sample grid (row 0 north), nodata cells
filled (``valid`` False there). Two kinds:

- :class:`ArraySource`: an in-memory Heightfield, sliced (its global fill is kept);
- :class:`RasterSource`: one raster GDAL opens (GeoTIFF, COG, VRT) or a mosaic of many (written as a
  VRT, hand-made XML, in memory), read by rasterio windowed reads — a COG's internal tiles are the only
  part of the file touched. Picklable (the dataset is re-opened per process and per thread), so Dask
  workers read their own windows.

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
   errors are never measured on filled cells.
2. Georeferencing. Only rasters already in a metric frame stream: a projected CRS in metres (or in feet,
   re-expressed in metres as the in-memory reader does), or no CRS with ``spacing_m``. A geographic or
   Mercator raster is refused in one line (the in-memory reader reprojects the whole array once;
   ``gdalwarp -t_srs EPSG:<UTM zone>`` does it out of core).
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
from terralod.fill import MIN_SIDE, fill_nodata
from terralod.heightfield import Heightfield
from terralod.io.georef import to_crs
from terralod.io.raster import vertical_unit_m

__all__ = ["ArraySource", "RasterSource", "WindowSource", "open_source"]

#: Side of the fixed nodata-fill blocks, samples, and the halo each is filled with (see deviation 1).
FILL_BLOCK = 512
FILL_HALO = 64
#: GDAL's block cache of a process reading windows, bytes (GDAL's default, 5 % of the RAM, would hold
#: decompressed blocks up to GiBs on a large machine); left alone when GDAL_CACHEMAX is set.
GDAL_CACHE_BYTES = 128 << 20
#: Filled blocks kept per source and process (each (FILL_BLOCK)^2 float32 + bool, 1.25 MiB).
FILL_CACHE_BLOCKS = 64
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

    @property
    def shape(self) -> tuple[int, int]:
        return self.height, self.width

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
        return Heightfield(z, ok, t, crs=self.crs, source=self.source)

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

    def read(self, r0: int, c0: int, r1: int, c1: int) -> tuple[np.ndarray, np.ndarray]:
        self._check_window(r0, c0, r1, c1)
        return self.hf.elevation_m[r0:r1, c0:c1], self.hf.valid[r0:r1, c0:c1]


class RasterSource(WindowSource):
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
        self._cache: OrderedDict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = OrderedDict()
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

    def read(self, r0: int, c0: int, r1: int, c1: int) -> tuple[np.ndarray, np.ndarray]:
        values, ok = self.read_raw(r0, c0, r1, c1)
        z = values.astype(np.float32, copy=False)
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
                return self._cache[key][0]
        b = FILL_BLOCK
        r0, c0 = br * b, bc * b
        r1, c1 = min(r0 + b, self.height), min(c0 + b, self.width)
        halo = FILL_HALO
        while True:
            ra, ca = max(r0 - halo, 0), max(c0 - halo, 0)
            rb, cb = min(r1 + halo, self.height), min(c1 + halo, self.width)
            values, ok = self.read_raw(ra, ca, rb, cb)
            whole = ra == 0 and ca == 0 and rb == self.height and cb == self.width
            if ok.any() or whole:
                break
            halo *= 2
        if not ok.any():
            raise InputError("band has no valid samples (all nodata)", self.source)
        filled = fill_nodata(values, ok).astype(np.float32)[r0 - ra : r1 - ra, c0 - ca : c1 - ca]
        with self._lock:
            self._cache[key] = (filled, ok)
            while len(self._cache) > FILL_CACHE_BLOCKS:
                self._cache.popitem(last=False)
        return filled


def open_source(paths: str | Path | Sequence[str | Path], **options: Any) -> RasterSource:
    """A :class:`RasterSource` of one raster or a mosaic (see :class:`RasterSource` for ``options``)."""
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
            f"is in {'a geographic' if crs.is_geographic else 'a Mercator'} CRS; out-of-core builds read "
            "metric grids only: reproject it first (gdalwarp -t_srs EPSG:<UTM zone>), or build it in memory",
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
