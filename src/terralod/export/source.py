"""The samples an export is measured against: the DEM as the user gave it, in its own CRS.

A store built from a geographic (EPSG:4326) or Web Mercator DEM holds a grid resampled to UTM; the samples
the user has are the original ones on the geographic lattice. :func:`source_for` gives back those samples
(:class:`SourceGrid`, read again from the store's source file when it is still there and has the store's
digest) or, for a TIN store, the TIN's own vertices (:class:`TinSource`). :func:`source_from_dem` reads a
DEM file directly (``terralod export dem.tif --format quantized-mesh``: no store, no UTM round trip).

Both kinds are a :class:`SampleSource` and answer the same questions in WGS 84 longitude/latitude degrees:
``height_at`` (the surface through the samples: bilinear on the grid, linear on the TIN's triangles; outside
the data the edge values extend outward, so a tile that reaches past the data continues the terrain instead
of dropping to 0 m), ``water_at`` (nodata or sea at exactly 0 m at the nearest sample), ``points_in`` (the
valid samples inside a rectangle: what a tile's error is measured against), ``bbox``, ``spacing_deg`` and
``identity`` (samples on a WGS 84 lon/lat lattice, which the quantized-mesh tiler meshes as they are).

Where a tile's bytes are decided: not here. This module decides the samples every web tile is made from
and measured against (and their nodata fill, :func:`terralod.fill.fill_nodata`, the store's); the tilers
(:mod:`terralod.export.quantized_mesh`, :mod:`terralod.export.lattice`) choose the meshes and
:mod:`terralod.export.quantized_mesh_format` writes them.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from terralod.errors import InputError
from terralod.fill import fill_nodata

__all__ = [
    "RegionGrid",
    "SampleSource",
    "SourceGrid",
    "TinSource",
    "source_for",
    "source_from_dem",
    "source_from_region",
]


def _is_lonlat_wgs84(crs: Any) -> bool:
    try:
        return bool(crs.is_geographic) and crs.to_epsg() == 4326
    except Exception:  # noqa: BLE001 - an unreadable CRS simply goes through pyproj
        return False


class SampleSource:
    """The samples an export is made from and measured against, in WGS 84 longitude/latitude degrees.

    Every source defines ``name`` (the file or store, for messages and layer names), ``bbox`` (west,
    south, east, north of the valid samples, degrees), ``spacing_deg`` (the ground spacing, in degrees
    of latitude) and ``identity`` (True only for samples on a WGS 84 lon/lat lattice, which the
    quantized-mesh tiler meshes on that lattice), and answers :meth:`height_at`, :meth:`water_at` and,
    from the valid samples a subclass gives in ``_flat`` (lon, lat, height), :meth:`points_in`.
    """

    name: str
    bbox: tuple[float, float, float, float]
    spacing_deg: float
    #: True for samples on a WGS 84 longitude/latitude lattice (a geographic DEM read as it is).
    identity: bool = False
    #: How a Dask worker reads these samples again (:mod:`terralod.export.distributed`): ("dem", path) or
    #: ("region", Region); None for samples made in memory.
    origin: tuple[Any, ...] | None = None

    def __init__(self) -> None:
        self._flat: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._buckets: dict[int, tuple[np.ndarray, dict[int, tuple[int, int]]]] = {}

    def _points(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """lon, lat, height of the valid samples, flat."""
        if self._flat is None:
            raise NotImplementedError(f"{type(self).__name__} gives no samples")
        return self._flat

    @property
    def lon(self) -> np.ndarray:
        return self._points()[0]

    @property
    def lat(self) -> np.ndarray:
        return self._points()[1]

    @property
    def zv(self) -> np.ndarray:
        return self._points()[2]

    def height_at(self, lon: np.ndarray, lat: np.ndarray) -> np.ndarray:
        """Height (m) of the surface through the samples at lon/lat; edge values extended outside."""
        raise NotImplementedError

    def water_at(self, lon: np.ndarray, lat: np.ndarray) -> np.ndarray:
        """True where the nearest sample is nodata or sea (exactly 0 m)."""
        raise NotImplementedError

    def points_in(self, z: int, x: int, y: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(lon, lat, height) of the valid samples inside geographic tile z/x/y, its edges included (a
        sample on a shared edge belongs to both tiles: CesiumJS may sample it from either)."""
        from terralod.export.geodesy import tile_rectangle

        order, groups = self._bucketed(z)
        wd, sd, ed, nd = tile_rectangle(z, x, y)
        out = []
        for bx in (x - 1, x, x + 1):
            for by in (y - 1, y, y + 1):
                g = groups.get(bx * (1 << z) + by)
                if g is not None:
                    out.append(order[g[0] : g[1]])
        if not out:
            e = np.zeros(0)
            return e, e, e
        idx = np.concatenate(out)
        lo, la = self.lon[idx], self.lat[idx]
        keep = (lo >= wd) & (lo <= ed) & (la >= sd) & (la <= nd)
        idx = idx[keep]
        return self.lon[idx], self.lat[idx], self.zv[idx]

    def points_strips(self, z: int, x: int, y: int) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """:meth:`points_in` in parts (one here; a windowed source reads a coarse tile's in strips)."""
        yield self.points_in(z, x, y)

    def _bucketed(self, z: int) -> tuple[np.ndarray, dict[int, tuple[int, int]]]:
        """The valid samples sorted by their tile of level z: (order, {bucket key: (start, end)}); one
        level kept at a time (the export walks level by level); safe to call from several threads."""
        got = self._buckets.get(z)
        if got is None:
            d = 180.0 / (1 << z)
            bx = np.floor((self.lon + 180.0) / d).astype(np.int64)
            by = np.floor((self.lat + 90.0) / d).astype(np.int64)
            key = bx * (1 << z) + by
            order = np.argsort(key, kind="stable")
            ks, first, counts = np.unique(key[order], return_index=True, return_counts=True)
            got = (order, {int(k): (int(f), int(f + c)) for k, f, c in zip(ks, first, counts, strict=True)})
            self._buckets = {z: got}
        return got


class SourceGrid(SampleSource):
    """A north-up grid of samples in its own CRS (geographic or projected; pixel-corner ``transform``).

    ``z_m`` holds filled heights (nodata filled, as the store fills it), ``valid`` the real samples.
    """

    def __init__(self, z_m: np.ndarray, valid: np.ndarray, transform: Any, crs: Any, name: str) -> None:
        from pyproj import CRS, Transformer

        super().__init__()
        # float32 stays float32 (an integer DEM read exactly, half the memory); anything else float64
        zt = np.float32 if np.asarray(z_m).dtype == np.float32 else np.float64
        self.z_m = np.ascontiguousarray(z_m, zt)
        self.valid = np.ascontiguousarray(valid, bool)
        self.t = transform
        self.crs = CRS.from_user_input(crs)
        self.name = name
        self._any_water: bool | None = None
        self.identity = _is_lonlat_wgs84(self.crs)
        if not self.identity:
            self._to_crs = Transformer.from_crs("EPSG:4326", self.crs, always_xy=True)
            self._to_ll = Transformer.from_crs(self.crs, "EPSG:4326", always_xy=True)
        h, w = self.z_m.shape
        self.shape = (h, w)
        rows_any, cols_any = self.valid.any(axis=1), self.valid.any(axis=0)
        if not rows_any.any():
            raise InputError("has no valid samples", name)
        r0, r1 = int(np.argmax(rows_any)), int(h - 1 - np.argmax(rows_any[::-1]))
        c0, c1 = int(np.argmax(cols_any)), int(w - 1 - np.argmax(cols_any[::-1]))
        if self.identity:  # the valid samples' bounding box of centres (no per-sample arrays: big DEMs)
            lons = (self.t.c + (c0 + 0.5) * self.t.a, self.t.c + (c1 + 0.5) * self.t.a)
            lats = (self.t.f + (r0 + 0.5) * self.t.e, self.t.f + (r1 + 0.5) * self.t.e)
            self.bbox = (float(min(lons)), float(min(lats)), float(max(lons)), float(max(lats)))
        else:
            # the footprint: corners of the valid samples' bounding box of rows/cols, its edges densified
            k = np.linspace(0.0, 1.0, 33)
            ec = np.concatenate([c0 + (c1 - c0) * k, np.full(33, c1), c0 + (c1 - c0) * k, np.full(33, c0)])
            er = np.concatenate([np.full(33, r0), r0 + (r1 - r0) * k, np.full(33, r1), r0 + (r1 - r0) * k])
            elon, elat = self._lonlat(self.t.c + (ec + 0.5) * self.t.a, self.t.f + (er + 0.5) * self.t.e)
            self.bbox = (float(min(elon.min(), self.lon.min())), float(min(elat.min(), self.lat.min())),
                         float(max(elon.max(), self.lon.max())), float(max(elat.max(), self.lat.max())))  # fmt: skip
        if self.crs.is_geographic:  # the ground spacing, in degrees of latitude (as for projected grids)
            cos_lat = math.cos(math.radians(0.5 * (self.bbox[1] + self.bbox[3])))
            self.spacing_deg = float(min(abs(self.t.a) * cos_lat, abs(self.t.e)))
        else:
            self.spacing_deg = float(min(abs(self.t.a), abs(self.t.e))) / 111320.0

    def _points(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """lon, lat, height of the valid samples (pixel centres), flat; made on first use."""
        if self._flat is None:
            rr, cc = np.nonzero(self.valid)
            x = self.t.c + (cc + 0.5) * self.t.a
            y = self.t.f + (rr + 0.5) * self.t.e
            lon, lat = self._lonlat(x, y)
            self._flat = (lon, lat, self.z_m[rr, cc])
        return self._flat

    def _lonlat(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if self.identity:
            return np.asarray(x, np.float64), np.asarray(y, np.float64)
        lon, lat = self._to_ll.transform(np.asarray(x, np.float64), np.asarray(y, np.float64))
        return np.asarray(lon, np.float64), np.asarray(lat, np.float64)

    def _colrow(self, lon: np.ndarray, lat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Grid coordinates (sample centres at integers) of lon/lat points, clamped to the grid: outside it
        the edge samples extend outward."""
        w, s, e, n = self.bbox
        lon = np.clip(lon, w, e)
        lat = np.clip(lat, s, n)
        if self.identity:
            x, y = lon, lat
        else:
            x, y = self._to_crs.transform(lon, lat)
            x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
        col = (x - self.t.c) / self.t.a - 0.5
        row = (y - self.t.f) / self.t.e - 0.5
        h, wd = self.shape
        return np.clip(col, 0, wd - 1), np.clip(row, 0, h - 1)

    def height_at(self, lon: np.ndarray, lat: np.ndarray) -> np.ndarray:
        """Bilinear height of the filled grid at lon/lat (edge values extended outside the grid)."""
        c, r = self._colrow(lon, lat)
        h, w = self.shape
        c0 = np.minimum(np.floor(c).astype(np.int64), max(w - 2, 0))
        r0 = np.minimum(np.floor(r).astype(np.int64), max(h - 2, 0))
        c1, r1 = np.minimum(c0 + 1, w - 1), np.minimum(r0 + 1, h - 1)
        fc, fr = c - c0, r - r0
        z00, z01 = self.take(r0, c0)[0], self.take(r0, c1)[0]
        z10, z11 = self.take(r1, c0)[0], self.take(r1, c1)[0]
        return z00 * (1 - fc) * (1 - fr) + z01 * fc * (1 - fr) + z10 * (1 - fc) * fr + z11 * fc * fr

    def water_at(self, lon: np.ndarray, lat: np.ndarray) -> np.ndarray:
        """True where the nearest sample is nodata or sea (exactly 0 m); False outside the footprint."""
        w, s, e, n = self.bbox
        inside = (lon >= w) & (lon <= e) & (lat >= s) & (lat <= n)
        c, r = self._colrow(lon, lat)
        z, ok = self.take(np.rint(r).astype(np.int64), np.rint(c).astype(np.int64))
        return inside & (~ok | (z == 0.0))

    # -- the samples by index (row 0 north), the interface the lattice tiler reads through ---------------
    @property
    def any_water(self) -> bool:
        """True when some sample is nodata or sea at exactly 0 m."""
        if self._any_water is None:
            self._any_water = bool((~self.valid).any() or (self.z_m[self.valid] == 0.0).any())
        return self._any_water

    def window(self, r0: int, r1: int, c0: int, c1: int) -> tuple[np.ndarray, np.ndarray]:
        """Filled heights and validity of rows [r0, r1), columns [c0, c1) (inside the grid)."""
        return self.z_m[r0:r1, c0:c1], self.valid[r0:r1, c0:c1]

    def gather(self, rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Filled heights and validity at every (rows[i], cols[j]) (an outer product; indices inside)."""
        return self.z_m[rows[:, None], cols[None, :]], self.valid[rows[:, None], cols[None, :]]

    def take(self, rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Filled heights and validity at the points (rows[k], cols[k]) (indices inside)."""
        return self.z_m[rows, cols], self.valid[rows, cols]

    def water_any_all(self, r0: int, r1: int, c0: int, c1: int) -> tuple[bool, bool]:
        """(some, every): whether any / every sample of rows [r0, r1), cols [c0, c1) (inside the grid, not
        empty) is nodata or sea at exactly 0 m."""
        from terralod.export.lattice import STRIP_SAMPLES

        some, every = False, True
        step = max(STRIP_SAMPLES // max(c1 - c0, 1), 2)
        for ra in range(r0, r1, step):
            wz, wok = self.window(ra, min(ra + step, r1), c0, c1)
            wet = ~wok | (wz == 0.0)
            some, every = some or bool(wet.any()), every and bool(wet.all())
        return some, every

    def water_gather(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """True at every (rows[i], cols[j]) (an outer product; indices inside) whose sample is nodata or
        sea at exactly 0 m."""
        z, ok = self.gather(rows, cols)
        return ~ok | (z == 0.0)


class RegionGrid(SourceGrid):
    """A WGS 84 longitude/latitude region (:class:`terralod.io.region.Region`: one DEM or a mosaic of
    many) read window by window: the samples of :class:`SourceGrid`, bit for bit, without ever holding
    them whole. Heights come from :class:`terralod.io.region.RegionReader` (fixed blocks, nodata filled
    by :func:`terralod.fill.fill_nodata` block by block, equal to the whole grid's fill wherever a hole's
    reach allows; a bounded LRU of blocks), the footprint from one scan of every file
    (:func:`terralod.io.region.scan_region`, which names an unreadable file before anything is written).

    Memory: the reader's block cache (``cache_blocks`` blocks of 512² samples, 1.25 MiB each for integer
    DEMs) and the window of the tile in hand; independent of the region's size.
    """

    def __init__(self, region: Any, *, scan: Any = None, cache_blocks: int | None = None) -> None:
        from pyproj import CRS

        from terralod.io.region import CACHE_BLOCKS, RegionReader, scan_region

        SampleSource.__init__(self)
        if not windowed_crs(region.crs):
            raise InputError("is neither in WGS 84 longitude/latitude (EPSG:4326) nor projected in metres with "
                             "heights in metres", region.name)  # fmt: skip
        self.region = region
        self.reader = RegionReader(
            region, cache_blocks=CACHE_BLOCKS if cache_blocks is None else cache_blocks
        )
        self.reader.open()  # held open from here: the files as they were when the export began
        got = scan_region(region) if scan is None else scan
        self.scan = got
        self.t = region.transform
        self.crs = CRS.from_user_input(region.crs.to_wkt())
        self.identity = _is_lonlat_wgs84(self.crs)
        if not self.identity:
            from pyproj import Transformer

            self._to_crs = Transformer.from_crs("EPSG:4326", self.crs, always_xy=True)
            self._to_ll = Transformer.from_crs(self.crs, "EPSG:4326", always_xy=True)
        self.name = region.footprints[0].shown if len(region.footprints) == 1 else region.name
        self.title = (
            Path(self.name).stem
            if len(region.footprints) == 1
            else f"region of {len(region.footprints)} files"
        )
        self.files = region.files
        self.shape = region.shape
        self._any_water = bool(got.any_water)
        if not self.identity:  # projected: the lon/lat box of the valid samples' rows x cols, from its edges
            self.bbox = self._projected_bbox(got)
            self.spacing_deg = float(min(abs(self.t.a), abs(self.t.e))) / 111320.0
            return
        lons = (self.t.c + (got.c0 + 0.5) * self.t.a, self.t.c + (got.c1 + 0.5) * self.t.a)
        lats = (self.t.f + (got.r0 + 0.5) * self.t.e, self.t.f + (got.r1 + 0.5) * self.t.e)
        self.bbox = (float(min(lons)), float(min(lats)), float(max(lons)), float(max(lats)))
        cos_lat = math.cos(math.radians(0.5 * (self.bbox[1] + self.bbox[3])))
        self.spacing_deg = float(min(abs(self.t.a) * cos_lat, abs(self.t.e)))

    def _projected_bbox(self, got: Any) -> tuple[float, float, float, float]:
        """The lon/lat box of the sample centres of rows r0..r1 x cols c0..c1 (a projection is a smooth
        one-to-one map, so its extremes over that rectangle lie on its edge: every edge sample is taken,
        and the edges densified as :class:`SourceGrid` does, so the box holds every valid sample)."""
        k = np.linspace(0.0, 1.0, 33)
        r0, r1, c0, c1 = got.r0, got.r1, got.c0, got.c1
        rows, cols = np.arange(r0, r1 + 1, dtype=np.float64), np.arange(c0, c1 + 1, dtype=np.float64)
        ec = np.concatenate([c0 + (c1 - c0) * k, np.full(33, c1), c0 + (c1 - c0) * k, np.full(33, c0),
                             cols, cols, np.full(rows.size, c0), np.full(rows.size, c1)])  # fmt: skip
        er = np.concatenate([np.full(33, r0), r0 + (r1 - r0) * k, np.full(33, r1), r0 + (r1 - r0) * k,
                             np.full(cols.size, r0), np.full(cols.size, r1), rows, rows])  # fmt: skip
        lon, lat = self._lonlat(self.t.c + (ec + 0.5) * self.t.a, self.t.f + (er + 0.5) * self.t.e)
        return float(lon.min()), float(lat.min()), float(lon.max()), float(lat.max())

    @property
    def z_m(self) -> np.ndarray:  # type: ignore[override]
        """The whole grid's filled heights, read now (memory of the whole region: for small DEMs and
        checks; the tiler reads windows)."""
        return self.window(0, self.shape[0], 0, self.shape[1])[0]

    @property
    def valid(self) -> np.ndarray:  # type: ignore[override]
        """The whole grid's validity, read now (see :attr:`z_m`)."""
        return self.window(0, self.shape[0], 0, self.shape[1])[1]

    @property
    def samples(self) -> int:
        """Samples of the region's grid (nodata and gaps included)."""
        return int(self.shape[0]) * int(self.shape[1])

    @property
    def any_water(self) -> bool:
        return bool(self._any_water)

    def window(self, r0: int, r1: int, c0: int, c1: int) -> tuple[np.ndarray, np.ndarray]:
        return self.reader.window(r0, r1, c0, c1)

    def gather(self, rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.reader.gather(rows, cols)

    def take(self, rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.reader.take(rows, cols)

    def water_any_all(self, r0: int, r1: int, c0: int, c1: int) -> tuple[bool, bool]:
        return self.reader.water_any_all(r0, r1, c0, c1)

    def water_gather(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        return self.reader.water_gather(rows, cols)

    def _points(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """lon, lat, height of every valid sample, read now (memory of the whole region, as :attr:`z_m`: for
        small DEMs and independent checks; the tiler reads a tile's, :meth:`points_in`, or strips of them)."""
        if self._flat is None:
            z, ok = self.window(0, self.shape[0], 0, self.shape[1])
            rr, cc = np.nonzero(ok)
            lon, lat = self._lonlat(self.t.c + (cc + 0.5) * self.t.a, self.t.f + (rr + 0.5) * self.t.e)
            self._flat = (lon, lat, z[rr, cc])
        return self._flat

    def points_in(self, z: int, x: int, y: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The valid samples inside geographic tile z/x/y, edges included (read from its window)."""
        from terralod.export.geodesy import tile_rectangle

        wd, sd, ed, nd = tile_rectangle(z, x, y)
        h, w = self.shape
        if not self.identity:
            return self._projected_points_in(wd, sd, ed, nd)
        lon_c = self.t.c + (np.arange(w) + 0.5) * self.t.a
        lat_r = self.t.f + (np.arange(h) + 0.5) * self.t.e
        c0, c1 = int(np.searchsorted(lon_c, wd, "left")), int(np.searchsorted(lon_c, ed, "right"))
        r0, r1 = int(np.searchsorted(-lat_r, -nd, "left")), int(np.searchsorted(-lat_r, -sd, "right"))
        if r1 <= r0 or c1 <= c0:
            e = np.zeros(0)
            return e, e, e
        zz, ok = self.window(r0, r1, c0, c1)
        rr, cc = np.nonzero(ok)
        return lon_c[c0 + cc], lat_r[r0 + rr], zz[rr, cc]

    def points_strips(self, z: int, x: int, y: int) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """:meth:`points_in` in strips of rows of at most ``READ_STRIP_SAMPLES`` samples read: a coarse tile
        of a projected region is measured against every sample it covers without holding them at once."""
        if self.identity:
            yield self.points_in(z, x, y)
            return
        from terralod.export.geodesy import tile_rectangle

        rect = tile_rectangle(z, x, y)
        r0, r1, c0, c1 = self._projected_window(*rect)
        step = max(1, READ_STRIP_SAMPLES // max(c1 - c0, 1))
        for ra in range(r0, r1, step):
            yield self._projected_points_in(*rect, window=(ra, min(ra + step, r1), c0, c1))

    def _projected_window(self, wd: float, sd: float, ed: float, nd: float) -> tuple[int, int, int, int]:
        """Rows [r0, r1) and columns [c0, c1) that hold every sample of the lon/lat rectangle: those its
        densified edge covers, plus one sample all round (the whole grid where the edge leaves the
        projection's domain)."""
        k = np.linspace(0.0, 1.0, 65)
        elon = np.concatenate([wd + (ed - wd) * k, np.full(65, ed), wd + (ed - wd) * k, np.full(65, wd)])
        elat = np.concatenate([np.full(65, sd), sd + (nd - sd) * k, np.full(65, nd), sd + (nd - sd) * k])
        x, y = self._to_crs.transform(elon, elat)
        x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
        h, w = self.shape
        if not (np.isfinite(x).all() and np.isfinite(y).all()):
            return 0, h, 0, w
        cf, rf = (x - self.t.c) / self.t.a - 0.5, (y - self.t.f) / self.t.e - 0.5
        c0, c1 = max(int(np.floor(cf.min())) - 1, 0), min(int(np.ceil(cf.max())) + 2, w)
        r0, r1 = max(int(np.floor(rf.min())) - 1, 0), min(int(np.ceil(rf.max())) + 2, h)
        return r0, max(r1, r0), c0, max(c1, c0)

    def _projected_points_in(
        self, wd: float, sd: float, ed: float, nd: float, window: tuple[int, int, int, int] | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The valid samples whose lon/lat lie in [wd, ed] x [sd, nd] (edges included), read from
        ``window`` (rows, columns; default :meth:`_projected_window`)."""
        r0, r1, c0, c1 = window if window is not None else self._projected_window(wd, sd, ed, nd)
        if r1 <= r0 or c1 <= c0:
            e = np.zeros(0)
            return e, e, e
        zz, ok = self.window(r0, r1, c0, c1)
        rr, cc = np.nonzero(ok)
        lon, lat = self._lonlat(self.t.c + (c0 + cc + 0.5) * self.t.a, self.t.f + (r0 + rr + 0.5) * self.t.e)
        keep = (lon >= wd) & (lon <= ed) & (lat >= sd) & (lat <= nd)
        return lon[keep], lat[keep], zz[rr[keep], cc[keep]]

    def close(self) -> None:
        self.reader.close()


def windowed_crs(crs: Any) -> bool:
    """True for a CRS whose regions :class:`RegionGrid` reads window by window: WGS 84 longitude/latitude,
    or a projected CRS whose heights are metres (a vertical axis in feet is scaled by the in-memory reader,
    :func:`terralod.io.reader.read_heightfield`)."""
    if _is_lonlat_wgs84(crs):
        return True
    try:
        from terralod.io.raster import vertical_unit_m

        return bool(crs.is_projected) and vertical_unit_m(crs) is None
    except Exception:  # noqa: BLE001
        return False


class _TriangleLocator:
    """Which triangle of (x, y, tris) holds each query point (-1: none), by a bucket grid of about two
    triangles a cell (:func:`terralod.kernels.tinlocate.bucket_triangles`): built in O(T), queried in
    O(1) a point for a triangulation of even density."""

    def __init__(self, x: np.ndarray, y: np.ndarray, tris: np.ndarray) -> None:
        from terralod.kernels.tinlocate import bucket_triangles

        self.x, self.y = np.ascontiguousarray(x, np.float64), np.ascontiguousarray(y, np.float64)
        self.tris = np.ascontiguousarray(tris, np.int64)
        x0, x1 = float(self.x.min()), float(self.x.max())
        y0, y1 = float(self.y.min()), float(self.y.max())
        cells = max(len(self.tris) // 2, 1)
        wx, wy = max(x1 - x0, 1e-9), max(y1 - y0, 1e-9)
        nx = max(1, min(int(round(math.sqrt(cells * wx / wy))), 1 << 14))
        ny = max(1, min(int(round(cells / nx)), 1 << 14))
        self.grid = (nx, ny, x0, y0, nx / wx, ny / wy)
        self.start, self.items = bucket_triangles(self.x, self.y, self.tris, *self.grid)

    def locate(self, px: np.ndarray, py: np.ndarray) -> np.ndarray:
        from terralod.kernels.tinlocate import locate_points

        return np.asarray(locate_points(self.x, self.y, self.tris, self.start, self.items, *self.grid,
                                        np.ascontiguousarray(px, np.float64),
                                        np.ascontiguousarray(py, np.float64)))  # fmt: skip


def _distinct_xy(xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(group, first): rows of ``xy`` (N, 2) with equal coordinates share a group, numbered in order of first
    appearance (:func:`terralod.kernels.meshtopo.merge_pairs`, -0.0 taken as 0.0), and each group's first
    row."""
    from terralod.kernels.meshtopo import merge_pairs

    bits = np.ascontiguousarray(xy, np.float64) + 0.0  # -0.0 made 0.0: equal positions, equal bits
    group = merge_pairs(bits.view(np.int64))
    first = np.empty(int(group.max()) + 1 if group.size else 0, np.int64)
    first[group[::-1]] = np.arange(group.size - 1, -1, -1)
    return group, first


class TinSource(SampleSource):
    """A TIN store's finest surface: its vertices are the samples, its triangles the surface.

    The leaves' vertices are merged where their positions agree to 0.1 mm (:func:`_distinct_xy` on the
    rounded coordinates, ordered as ``np.unique(..., axis=0)`` orders them); a point is located by a bucket
    grid (:mod:`terralod.kernels.tinlocate`) and its height is matplotlib's: the plane coefficients of
    ``Triangulation.calculate_plane_coefficients`` evaluated as ``LinearTriInterpolator`` does (a x + b y
    + c), so a point in the same triangle gets the same bits. Outside the hull: the nearest vertex."""

    def __init__(self, terrain: Any, geo: Any) -> None:
        import matplotlib.tri as mtri

        super().__init__()
        tree = terrain.lod_tree()
        parents = {n.parent for n in tree}
        vs, ts, base = [], [], 0
        for n in tree:
            if n.code in parents:
                continue
            v, t = terrain.lod_mesh(n.code)
            used = np.unique(t)
            remap = np.full(len(v), -1, np.int64)
            remap[used] = np.arange(used.size)
            vs.append(np.asarray(v, np.float64)[used])
            ts.append(remap[t] + base)
            base += used.size
        allv = np.concatenate(vs)
        key = np.round(allv[:, :2], 4) + 0.0  # -0.0 made 0.0 (np.unique's order, below)
        group, first = _distinct_xy(key)
        ng = first.size
        order = np.lexsort((key[first, 1], key[first, 0]))  # np.unique's order: x, then y
        rank = np.empty(ng, np.int64)
        rank[order] = np.arange(ng)
        xyz = allv[first[order]]
        tri = np.ascontiguousarray(rank[group][np.concatenate(ts)].reshape(-1, 3), np.int64)
        self.geo = geo
        self._planes = np.ascontiguousarray(
            mtri.Triangulation(xyz[:, 0], xyz[:, 1], tri).calculate_plane_coefficients(xyz[:, 2]), np.float64
        )
        self._locator = _TriangleLocator(xyz[:, 0], xyz[:, 1], tri)
        from scipy.spatial import cKDTree

        self._kd = cKDTree(xyz[:, :2])
        self.xyz = xyz
        self.name = str(terrain.path)
        #: what every tile made from this TIN depends on (None: encoded every time, see incremental)
        self.model_digest: str | None = getattr(terrain, "model_digest", None)
        lon, lat = geo.lonlat(xyz[:, 0], xyz[:, 1])
        self._flat = (np.asarray(lon, np.float64), np.asarray(lat, np.float64), xyz[:, 2])
        self.bbox = (
            float(self.lon.min()),
            float(self.lat.min()),
            float(self.lon.max()),
            float(self.lat.max()),
        )
        w, s, e, n = terrain.bounds_m
        self.spacing_deg = math.sqrt((e - w) * (n - s) / max(len(xyz), 1)) / 111320.0

    def height_at(self, lon: np.ndarray, lat: np.ndarray) -> np.ndarray:
        from terralod.kernels.tinlocate import plane_heights

        w, s, e, n = self.bbox
        # most of a coarse tile's points lie outside the data and are clipped onto the bounding box's edges:
        # each distinct position is projected and looked up once (the same answers, a fraction of the work)
        ll = np.column_stack([np.clip(np.ravel(lon), w, e), np.clip(np.ravel(lat), s, n)])
        group, first = _distinct_xy(ll)
        x, y = self.geo.xy(ll[first, 0], ll[first, 1])
        x = np.ascontiguousarray(np.ravel(np.asarray(x, np.float64)))
        y = np.ascontiguousarray(np.ravel(np.asarray(y, np.float64)))
        z = plane_heights(self._planes, self._locator.locate(x, y), x, y)
        bad = ~np.isfinite(z)
        if bad.any():  # outside the TIN's hull: the nearest vertex (its edge extended outward)
            _, j = self._kd.query(np.column_stack([x[bad], y[bad]]))
            z[bad] = self.xyz[j, 2]
        return z[group].reshape(np.shape(lon))

    def water_at(self, lon: np.ndarray, lat: np.ndarray) -> np.ndarray:
        return np.zeros(np.shape(lon), bool)


#: Samples per strip when a DEM is read (a few MB at a time beside the one array of heights).
READ_STRIP_SAMPLES = 1 << 22


def _native_grid(path: Path) -> SourceGrid | None:
    """The samples of a geographic or Web Mercator GeoTIFF on its own lattice (the store holds them
    resampled to UTM); None for other inputs (their metric heightfield already is the user's grid).

    Read in strips of rows straight into one array of heights (float32 for integer and float32 DEMs
    without scale/offset: exact, 4 bytes a sample; float64 otherwise) and one of validity; nodata filled
    as a store fills it (:func:`terralod.fill.fill_nodata`: while it runs, about 24 bytes a sample more)."""
    import rasterio
    from rasterio.windows import Window

    from terralod.io.raster import _is_mercator, north_up

    try:
        with rasterio.open(path) as ds:
            crs, t = ds.crs, ds.transform
            if crs is None or t.is_identity or not (crs.is_geographic or _is_mercator(crs)):
                return None
            scale = float((ds.scales or (1.0,))[0] or 1.0)
            offset = float((ds.offsets or (0.0,))[0] or 0.0)
            exact32 = ds.dtypes[0] in ("int8", "uint8", "int16", "uint16", "float32")
            dt = np.float32 if exact32 and scale == 1.0 and offset == 0.0 else np.float64
            h, w = ds.height, ds.width
            values = np.empty((h, w), dt)
            valid = np.empty((h, w), bool)
            step = max(1, READ_STRIP_SAMPLES // max(w, 1))
            for r0 in range(0, h, step):
                n = min(step, h - r0)
                a = ds.read(1, window=Window(0, r0, w, n), masked=True)
                zz, vv = values[r0 : r0 + n], valid[r0 : r0 + n]
                zz[...] = np.ma.getdata(a)
                if scale != 1.0:
                    zz *= scale
                if offset != 0.0:
                    zz += offset
                vv[...] = ~np.ma.getmaskarray(a)
                vv &= np.isfinite(zz)
            wkt = crs.to_wkt()
    except Exception:  # noqa: BLE001 - not a GDAL raster: the caller uses the metric heightfield
        return None
    values, valid, t, _ = north_up(values, valid, t, str(path))
    if not valid.any():
        raise InputError("has no valid samples", str(path))
    if not valid.all():  # the store's fill, so a DEM exported directly has a store's filled surface
        valid = np.ascontiguousarray(valid)
        values = fill_nodata(values, valid).astype(values.dtype)
    return SourceGrid(values, valid, t, wkt, str(path))


def _from_heightfield(hf: Any) -> SourceGrid:
    return SourceGrid(np.asarray(hf.elevation_m, np.float64), np.asarray(hf.valid), hf.transform, hf.crs,
                      str(hf.source))  # fmt: skip


def source_from_dem(path: str | Path) -> SourceGrid:
    """A DEM file's samples in its own CRS (geographic and Web Mercator GeoTIFFs on their own lattice,
    EPSG:4326 ones read window by window (:class:`RegionGrid`); anything else as
    :func:`terralod.io.reader.read_heightfield` reads it). Raises InputError."""
    from terralod.io.reader import read_heightfield

    p = Path(path)
    if p.is_file():
        windowed = _region_grid(p)
        if windowed is not None:
            return windowed
    native = _native_grid(p) if p.is_file() else None
    if native is None:
        hf = read_heightfield(p)
        if not hf.crs:
            raise InputError(
                "has no CRS (a local metric frame); the web exports need a georeferenced DEM", str(p)
            )
        native = _from_heightfield(hf)
    native.origin = ("dem", str(p))
    return native


def _region_grid(path: Path) -> RegionGrid | None:
    """A north-up EPSG:4326 or metric projected raster as a :class:`RegionGrid` (:func:`windowed_crs`); None
    for anything else (or a file GDAL cannot open: the in-memory readers name the problem)."""
    from terralod.io.region import resolve_region

    try:
        region = resolve_region([path])
    except InputError:
        return None
    if not windowed_crs(region.crs):
        return None
    return RegionGrid(region)


def source_from_region(inputs: Any, crs: Any = None) -> SourceGrid:
    """The samples of a region (a :class:`terralod.io.region.Region`, or what
    :func:`terralod.io.region.resolve_region` resolves: files, globs, folders, VRTs,
    ``.hgt``, ``.hgt.zip``; ``crs`` assigns one to every file). WGS 84 longitude/latitude and metric projected
    regions are read window by window (:class:`RegionGrid`, :func:`windowed_crs`); other CRSs through the
    VRT, in memory, as
    :func:`source_from_dem` reads one file. Every file is read once first (a file GDAL cannot decode is
    named in one line, InputError). Where files overlap the last one listed wins."""
    import tempfile

    from terralod.io.reader import read_heightfield
    from terralod.io.region import Region, resolve_region

    region = inputs if isinstance(inputs, Region) else resolve_region(inputs, crs)
    if windowed_crs(region.crs):
        return RegionGrid(region)
    if len(region.footprints) == 1 and region.vrt is None:
        return source_from_dem(region.footprints[0].path)
    from terralod.io.region import scan_region

    scan_region(region)  # an unreadable file named before anything is read into memory
    with tempfile.TemporaryDirectory(prefix="terralod-region-") as d:
        vrt = region.write_vrt(Path(d) / "region.vrt")
        grid = _native_grid(vrt)
        if grid is None:
            hf = read_heightfield(vrt)
            if not hf.crs:
                raise InputError("has no CRS; the web exports need a georeferenced DEM", region.name)
            grid = _from_heightfield(hf)
    grid.name = region.name
    grid.files = region.files  # type: ignore[attr-defined]
    grid.origin = ("region", region)
    return grid


def _windowed_source(terrain: Any) -> RegionGrid | None:
    """The WGS 84 longitude/latitude or metric projected samples a store was built from (one file or a region: a folder, glob,
    VRT), read window by window (:class:`RegionGrid`), when they are still there and give the store's
    digest; None otherwise (a projected source, a store of epochs, a moved or changed source).

    The digest is the one the build recorded, of the grid it resampled to UTM: checked by building that
    grid again strip by strip (:func:`terralod.io.windowed.open_source`,
    :func:`terralod.export.common.streamed_digest`), never whole, so memory stays one strip and one
    block cache however large the region is."""
    from terralod.export.common import streamed_digest
    from terralod.io.region import resolve_region
    from terralod.io.windowed import open_source

    meta = getattr(terrain, "meta", {}) or {}
    src, digest = meta.get("source"), meta.get("source_digest")
    files = [str(f) for f in meta.get("source_files") or ([src] if src else [])]  # a mosaic: its files
    if (
        getattr(terrain, "epochs", None)
        or not files
        or not digest
        or not all(Path(f).exists() for f in files)
    ):
        return None
    try:
        region = resolve_region(files)
        if not windowed_crs(region.crs):
            return None
        warped = open_source(files if len(files) > 1 else files[0])
        if streamed_digest(warped) != digest:
            return None
        return RegionGrid(region)
    except Exception:  # noqa: BLE001 - a source that no longer reads as it did is simply not used
        return None


def source_for(terrain: Any, geo: Any) -> SampleSource:
    """The samples behind a store: its source DEM on its own lattice when it can be read again and is the
    one the store was built from (a WGS 84 longitude/latitude one window by window, :func:`_windowed_source`);
    the store's grid when only that is known; a TIN store's vertices."""
    from terralod.export.common import source_heightfield

    windowed = _windowed_source(terrain)
    if windowed is not None:
        return windowed
    hf = source_heightfield(terrain)
    if hf is not None:
        meta = getattr(terrain, "meta", {}) or {}
        src = meta.get("source")
        if src and Path(src).is_file() and not getattr(terrain, "epochs", None):
            native = _native_grid(Path(src))
            if native is not None:
                return native
        return _from_heightfield(hf)
    if hasattr(terrain, "heightfield") and not getattr(terrain, "epochs", None):
        from terralod.errors import StoreError

        try:
            return _from_heightfield(terrain.heightfield())
        except StoreError:  # keeps no samples and its source is gone or changed: its finest meshes below
            pass
    return TinSource(terrain, geo)
