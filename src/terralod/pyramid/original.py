"""Tile errors against the samples the user gave, whatever grid the tiles were meshed on.

A geographic or Mercator DEM is reprojected once to the UTM zone of its centre before meshing
(:func:`terralod.io.raster.reproject_to_utm`, bilinear): the store's grid is then a resampling, and an
error measured on it alone says nothing of what the resampling moved (on SRTM3 N42E001 every finest
tile, "the lossless grid", measured 0.0 m on the grid and up to 107 m against the original samples).
So for such a source every tile is also measured against the original samples in its footprint, and its
stored errors are the larger of the two (DESIGN.md: "every stored tile error is the maximum distance
between the tile's surface and every source sample it covers").

Per tile, a pure function of the tile's mesh and one window of the source (:func:`tile_samples` then
:func:`original_error`), so a build that reads the source by windows (out of core, on Dask workers) can
measure the same way:

1. the tile's footprint (the rectangle of its grid's sample centres, store CRS) is densified and
   transformed to the source's CRS; its bounding box, widened by :data:`WINDOW_MARGIN_PX` source pixels,
   is the window read (``OriginalGrid.window``);
2. the window's valid samples (pixel centres) are transformed to the store's CRS (rasterio's PROJ, the
   core's one CRS library) and those inside the footprint (edges included) are kept, in the tile's
   window-local frame (X east, Y south, metres from the tile's north-west sample);
3. :func:`terralod.kernels.scattered.scattered_vertical_error` measures ``|surface - z|`` at each, on the
   stored (quantised) geometry.

What is measured: the vertical gap (an upper bound of the 3D distance), so a tile's ``error_m`` bounds
every original sample's vertical gap and its grid Hausdorff distance at once. A sample no triangle covers
(the store dropped the triangles over nodata) is not measured, as on the grid. A sample on a tile's edge
belongs to every tile that shares the edge. Heights are compared as read (the source's vertical datum).
"""

from __future__ import annotations

import collections
import functools
import math
import threading
import weakref
from dataclasses import dataclass
from typing import Any

import numpy as np

from terralod.kernels.scattered import scattered_vertical_error

__all__ = ["OriginalError", "error_reference", "original_error", "tile_samples"]

#: Source pixels added around the transformed footprint's bounding box before the window is read (the
#: footprint's edges are transformed at :data:`DENSIFY` points each; the exact filter is in the store CRS).
WINDOW_MARGIN_PX = 2
#: Points per edge of the footprint transformed to the source's CRS to find its window.
DENSIFY = 33


@dataclass(frozen=True)
class OriginalError:
    """A tile measured against the original samples of its footprint.

    Attributes
    ----------
    max_vertical_m : largest |surface - z| over the covered samples, metres (0 when none)
    sumsq_m2 : sum of the squared gaps, m²
    n_samples : covered samples; n_uncovered : samples of the footprint no triangle covers
    """

    max_vertical_m: float
    sumsq_m2: float
    n_samples: int
    n_uncovered: int

    @property
    def rms_m(self) -> float:
        return math.sqrt(self.sumsq_m2 / self.n_samples) if self.n_samples else 0.0


@functools.lru_cache(maxsize=16)
def _horizontal(wkt: str) -> Any:
    """The horizontal part of a CRS (a compound or 3D CRS's 2D CRS) as rasterio's CRS."""
    from rasterio.crs import CRS

    crs = CRS.from_user_input(wkt)
    try:
        from pyproj import CRS as ProjCRS  # optional: only to drop a vertical part the store's CRS carries

        p = ProjCRS.from_wkt(wkt)
        if p.is_compound or len(p.axis_info) > 2:
            return CRS.from_wkt(p.to_2d().to_wkt())
    except ImportError:
        pass
    return crs


def tile_samples(
    grid: Any,
    store_crs: str,
    origin_m: tuple[float, float],
    spacing_m: tuple[float, float],
    rc0: tuple[int, int],
    rc1: tuple[int, int],
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The original valid samples inside a tile's footprint, in the tile's window-local frame.

    Parameters
    ----------
    grid : the source's own samples (:class:`terralod.io.raster.OriginalGrid`, or anything with its ``crs``
        (WKT), ``transform``, ``shape`` and ``window(r0, r1, c0, c1)``)
    store_crs : WKT of the store's CRS
    origin_m : world (x, y) of the store grid's sample (0, 0), metres; spacing_m : its (dx, dy), metres
    rc0, rc1 : (row, col) of the tile's north-west and south-east grid samples (inclusive)

    Returns
    -------
    x, y : (M,) float64 metres east and south of the tile's north-west sample; z : (M,) float64 heights
    """
    from rasterio.warp import transform as warp_points

    x0, y0 = origin_m
    dx, dy = spacing_m
    (r0, c0), (r1, c1) = rc0, rc1
    west, east = x0 + c0 * dx, x0 + c1 * dx
    north, south = y0 - r0 * dy, y0 - r1 * dy
    src_crs, dst_crs = _horizontal(grid.crs), _horizontal(store_crs)
    # 1. the window: the densified footprint in the source's CRS, widened by a margin
    f = np.linspace(0.0, 1.0, DENSIFY)
    ex = np.concatenate(
        [west + f * (east - west), np.full(DENSIFY, east), east - f * (east - west), np.full(DENSIFY, west)]
    )
    ey = np.concatenate(
        [
            np.full(DENSIFY, north),
            north - f * (north - south),
            np.full(DENSIFY, south),
            south + f * (north - south),
        ]
    )
    sx, sy = (np.asarray(v, np.float64) for v in warp_points(dst_crs, src_crs, ex, ey))
    t = grid.transform
    h, w = grid.shape
    if src_crs.is_geographic:  # longitudes near the source's own (across the antimeridian too)
        centre = t.c + t.a * w / 2.0
        sx = centre + (sx - centre + 180.0) % 360.0 - 180.0
    cols = (sx - t.c) / t.a - 0.5
    rows = (sy - t.f) / t.e - 0.5
    if not (np.isfinite(cols).all() and np.isfinite(rows).all()):
        wr0, wc0, wr1, wc1 = 0, 0, h, w  # a footprint PROJ cannot place in the source's CRS: all of it
    else:
        wr0 = int(math.floor(rows.min())) - WINDOW_MARGIN_PX
        wr1 = int(math.ceil(rows.max())) + WINDOW_MARGIN_PX + 1
        wc0 = int(math.floor(cols.min())) - WINDOW_MARGIN_PX
        wc1 = int(math.ceil(cols.max())) + WINDOW_MARGIN_PX + 1
    wr0, wr1, wc0, wc1 = max(wr0, 0), min(wr1, h), max(wc0, 0), min(wc1, w)
    empty = np.zeros(0, np.float64)
    if wr1 <= wr0 or wc1 <= wc0:
        return empty, empty, empty
    values, valid = grid.window(wr0, wr1, wc0, wc1)
    if not valid.any():
        return empty, empty, empty
    # 2. the valid samples' centres in the store's CRS, those inside the footprint kept
    qx, qy = _positions(grid, store_crs).window(wr0, wr1, wc0, wc1)
    keep = valid & (qx >= west) & (qx <= east) & (qy >= south) & (qy <= north)
    z = np.asarray(values, np.float64)[keep]
    return qx[keep] - west, north - qy[keep], z


#: Side of the blocks of source samples whose store-CRS positions are transformed together (16 bytes a
#: sample: 1 MiB a block), and the blocks kept in memory per source (LRU, 96 MiB). PROJ through GDAL costs
#: about 0.7 us a point, and the levels sweep the region again and again (a unit's window, about 1024²
#: store samples, covers some 5 x 5 blocks of a 3" source): so a block is transformed once per source
#: and process, and a block the LRU drops goes to a spill file (:class:`terralod.output.SpillFile`, 16 bytes a
#: sample of the blocks dropped) from which it is read back instead of transformed again. Memory stays at the blocks
#: kept whatever the region; disk grows with it (a 16-tile SRTM3 region: 352 blocks, 352 MiB). A block is
#: the same numbers whether transformed or read back: the count changes time, not values.
POSITION_BLOCK = 256
POSITION_BLOCKS_KEPT = 96


class _Positions:
    """Store-CRS positions (x, y) of every sample centre of a source grid, transformed once per block of
    :data:`POSITION_BLOCK` rows and columns on first use (each point transformed alone by PROJ, so a
    block's numbers are those a window's own transform would give); blocks the memory LRU drops are kept
    in a spill file and read back from it."""

    def __init__(self, grid: Any, store_crs: str) -> None:
        from terralod.output import SpillFile

        self.grid, self.store_crs = grid, store_crs
        self.blocks: collections.OrderedDict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = (
            collections.OrderedDict()
        )
        self.lock = threading.Lock()
        self.spill = SpillFile("terralod-positions-")
        self.spilled: set[tuple[int, int]] = set()

    def _offset(self, br: int, bc: int) -> int:
        w = self.grid.shape[1]
        return (br * -(-w // POSITION_BLOCK) + bc) * POSITION_BLOCK * POSITION_BLOCK * 16

    def _block_shape(self, br: int, bc: int) -> tuple[int, int]:
        h, w = self.grid.shape
        r0, c0 = br * POSITION_BLOCK, bc * POSITION_BLOCK
        return min(r0 + POSITION_BLOCK, h) - r0, min(c0 + POSITION_BLOCK, w) - c0

    def _drop(self) -> None:
        """Drop the least recently used blocks beyond :data:`POSITION_BLOCKS_KEPT` to the spill file
        (caller holds the lock; a block the spill file declines is transformed again when asked)."""
        while len(self.blocks) > POSITION_BLOCKS_KEPT:
            key, (qx, qy) = self.blocks.popitem(last=False)
            if key not in self.spilled and self.spill.put(
                self._offset(*key), np.concatenate([qx.ravel(), qy.ravel()]).tobytes()
            ):
                self.spilled.add(key)

    def _block(self, br: int, bc: int) -> tuple[np.ndarray, np.ndarray]:
        with self.lock:
            hit = self.blocks.get((br, bc))
            if hit is not None:
                self.blocks.move_to_end((br, bc))
                return hit
            spilled = (br, bc) in self.spilled
        shape = self._block_shape(br, bc)
        if spilled:
            n = shape[0] * shape[1]
            both = np.frombuffer(self.spill.get(self._offset(br, bc), 16 * n), np.float64)
            qx, qy = both[:n].reshape(shape), both[n:].reshape(shape)
        else:
            qx, qy = self._transform(br, bc, shape)
        with self.lock:
            self.blocks[(br, bc)] = (qx, qy)
            self._drop()
        return qx, qy

    def _transform(self, br: int, bc: int, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        from rasterio.warp import transform as warp_points

        t = self.grid.transform
        r0, c0 = br * POSITION_BLOCK, bc * POSITION_BLOCK
        cc, rr = np.meshgrid(
            np.arange(c0, c0 + shape[1], dtype=np.float64), np.arange(r0, r0 + shape[0], dtype=np.float64)
        )
        px = t.c + (cc.ravel() + 0.5) * t.a
        py = t.f + (rr.ravel() + 0.5) * t.e
        src, dst = _horizontal(self.grid.crs), _horizontal(self.store_crs)
        qx, qy = (np.asarray(v, np.float64).reshape(shape) for v in warp_points(src, dst, px, py))
        return qx, qy

    def window(self, r0: int, r1: int, c0: int, c1: int) -> tuple[np.ndarray, np.ndarray]:
        """(x, y) store-CRS metres of the sample centres of rows r0..r1-1, columns c0..c1-1."""
        qx = np.empty((r1 - r0, c1 - c0), np.float64)
        qy = np.empty_like(qx)
        b = POSITION_BLOCK
        for br in range(r0 // b, (r1 - 1) // b + 1):
            for bc in range(c0 // b, (c1 - 1) // b + 1):
                bx, by = self._block(br, bc)
                a0, a1 = max(r0, br * b), min(r1, br * b + b)
                d0, d1 = max(c0, bc * b), min(c1, bc * b + b)
                qx[a0 - r0 : a1 - r0, d0 - c0 : d1 - c0] = bx[
                    a0 - br * b : a1 - br * b, d0 - bc * b : d1 - bc * b
                ]
                qy[a0 - r0 : a1 - r0, d0 - c0 : d1 - c0] = by[
                    a0 - br * b : a1 - br * b, d0 - bc * b : d1 - bc * b
                ]
        return qx, qy


_POSITIONS: weakref.WeakKeyDictionary[Any, dict[str, _Positions]] = weakref.WeakKeyDictionary()
_POSITIONS_LOCK = threading.Lock()


def _positions(grid: Any, store_crs: str) -> _Positions:
    """The position cache of ``grid`` in ``store_crs`` (one per source grid object and store CRS)."""
    with _POSITIONS_LOCK:
        per = _POSITIONS.setdefault(grid, {})
        if store_crs not in per:
            per[store_crs] = _Positions(grid, store_crs)
        return per[store_crs]


def original_error(
    local: np.ndarray, triangles: np.ndarray, x: np.ndarray, y: np.ndarray, z: np.ndarray
) -> OriginalError:
    """Vertical gaps between a tile's stored geometry and samples in its window-local frame.

    Parameters
    ----------
    local : (N, 3) float64 vertices, metres east and south of the tile's north-west sample, heights metres
        (the builder's dequantised geometry)
    triangles : (K, 3) int triangles of ``local``
    x, y, z : (M,) float64 samples in the same frame (:func:`tile_samples`)
    """
    if x.size == 0 or triangles.shape[0] == 0:
        return OriginalError(0.0, 0.0, 0, int(x.size))
    err, sumsq, n, missed = scattered_vertical_error(
        np.ascontiguousarray(local, np.float64), np.ascontiguousarray(triangles, np.int64),
        np.ascontiguousarray(x, np.float64), np.ascontiguousarray(y, np.float64),
        np.ascontiguousarray(z, np.float64),
    )  # fmt: skip
    return OriginalError(float(err), float(sumsq), int(n), int(missed))


def _crs_label(wkt: str | None) -> str:
    from rasterio.crs import CRS

    try:
        epsg = CRS.from_user_input(wkt).to_epsg() if wkt else None
    except Exception:  # noqa: BLE001 - an unreadable CRS is named as such
        epsg = None
    return f"EPSG:{epsg}" if epsg else "its own CRS"


def error_reference(grid: Any) -> dict[str, Any]:
    """The store's record (meta ``errors_measured_against``) that its errors include the original samples."""
    return {
        "samples": "original",
        "source": str(grid.source),
        "crs": _crs_label(grid.crs),
        "valid_samples": int(grid.n_valid),
    }


def error_reference_line(meta: dict[str, Any]) -> str:
    """One line saying what a store's errors are measured against (``terralod info``, the build summary)."""
    ref = meta.get("errors_measured_against")
    if isinstance(ref, dict) and ref.get("samples") == "original":
        name = str(ref.get("source", "the source")).replace("\\", "/").rsplit("/", 1)[-1]
        return (
            f"errors measured against the {int(ref.get('valid_samples', 0)):,} original samples of {name} "
            f"({ref.get('crs')}), not only the resampled grid"
        )
    if any(str(n).startswith("reprojected from") for n in meta.get("notes") or []):
        return (
            "errors measured on the resampled grid only, not the source's own samples: they understate; "
            "rebuild with this terralod (build --overwrite)"
        )
    return "errors measured against the source's own samples (no resampling)"
