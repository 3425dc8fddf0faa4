"""Cesium quantized-mesh 1.0 export of any terrain, the tiler: which tiles, which mesh in each, which error.

Where a tile's bytes are decided: the mesh of each tile (its samples, the greedy-insertion target, the
vertices and triangles kept) here and, for a geographic DEM, in :mod:`terralod.export.lattice`; the bytes
of that mesh in :mod:`terralod.export.quantized_mesh_format`; the samples themselves in
:mod:`terralod.export.source`. Output: ``layer.json``, ``errors.json`` and ``Z/X/Y.terrain`` tiles.

A tile is a function of (source, options, z, x, y) alone: the same bytes whichever tiles were made before
it, in an export (level by level) or on request (``terralod serve``, in the clients' order), in any
process. The one statistic a tile takes from elsewhere comes from its parent, itself such a function
(:meth:`QuantizedMesh.rms_ratio`, memoised).

The tiling. Quantized-mesh lives on Cesium's *geographic* tiling scheme (EPSG:4326, two 180° roots at
level 0, 2^(z+1) x 2^z tiles at level z, TMS rows: y grows north). That is a second tiling beside the
store's own quadtree, and it exists only here at the export boundary: each tile's rectangle is converted
to the store's CRS with pyproj and the terrain is re-tiled into it from the *source samples* (the store's
source DEM when it can be read again and has the store's digest; otherwise the store's finest meshes, i.e.
the full-resolution TIN of a TIN store or the finest tiles of a grid store, interpolated on their own
triangles). Levels run from 0 to the first level whose tiles, sampled at 257², are as fine as the source.

The meshing is adaptive greedy insertion (pydelatin, Garland & Heckbert's scheme as in Delatin) on the
257² samples of each tile with a target error of a quarter of CesiumJS's level maximum geometric error
(the error CesiumJS assumes for the level when it computes screen-space error); the error written with
each tile is then *measured*: max vertical distance between the tile surface and every source sample inside
the tile (metadata extension ``terralod.error_m``, and ``error_m`` per level in ``layer.json``). The store's
own cohesion mesher needs the store's quantised lattice, which does not exist in the geographic tiling;
greedy insertion is the closest method that meshes an arbitrary sample grid to an error target (deviation
from the store's own method, and why).

A geographic DEM (``terralod export dem.tif``, or a store whose source DEM is one) is meshed on its own
lattice instead (:mod:`terralod.export.lattice`): every sample at the two finest zooms, every 2nd, 4th...
below; the finest zoom at FINEST_ERROR_M, the one below it at its level target lowered by its parent's RMS
per metre of target (:meth:`QuantizedMesh.rms_ratio`), tiles whose RMS is then still above RMS_GOAL_M
meshed again at a target scaled to it.

Nodata: outside the source footprint the surface continues the data's edge values; inside, nodata samples
keep the fill (the store's, :func:`terralod.fill.fill_nodata`, also for a DEM read on its lattice). The
water-mask extension marks nodata and sea at 0 m where a tile holds any (one byte elsewhere). Normals
(oct-encoded extension, only with ``normals=True``: about 0.7 B a triangle gzip'd, and CesiumJS asks for
them only with ``requestVertexNormals``) are the normals of the continuous sampled surface at each vertex
(central differences on the samples, ENU → ECEF), so the tiles of one level have identical normals at their
shared borders. CesiumJS adds its own skirts from the edge indices.
"""

from __future__ import annotations

import gzip
import json
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from terralod.export.common import check_exportable, export_inputs, export_key
from terralod.export.geodesy import WGS84_A_M, Geodesy, enu_frame, tile_rectangle
from terralod.export.quantized_mesh_format import decode_tile, encode_tile, oct_decode, oct_encode
from terralod.export.tiles3d import ExportReport
from terralod.kernels.error import points_vertical_error
from terralod.kernels.qmesh import merge_uv

__all__ = [
    "Part",
    "QmTile",
    "QuantizedMesh",
    "decode_tile",
    "encode_tile",
    "export_quantized_mesh",
    "level_max_error_m",
    "oct_decode",
    "oct_encode",
    "tile_rectangle",
    "true_error_m",
]

#: Samples per tile side of the re-tiling (the water mask is 256², so this is one more).
SAMPLES = 257
#: Target error of the greedy insertion, as a fraction of CesiumJS's level maximum geometric error.
TARGET_FRACTION = 0.25
#: Greedy-insertion target at the finest zoom of a lattice export at most this (m): the zoom CesiumJS
#: shows up close and never refines, holding the DEM's detail (SRTM heights are whole metres).
FINEST_ERROR_M = 3.0
#: RMS error (m) the zoom below the finest aims at on a lattice export: a tile whose RMS at the level's
#: target is above it is meshed again at a target scaled down to it (once; the measured errors are what
#: the tile declares either way). It puts one zoom of the pyramid at the RMS of the finest tiles other
#: tools serve (Cesium Terrain Builder's z12 on SRTM3: 6-9 m), between the level's quarter of CesiumJS's
#: error and the finest zoom's full detail.
RMS_GOAL_M = 8.0


def _undulation_spread_m(geoid: Any, rect: tuple[float, float, float, float], n: int = 9) -> float:
    """max − min of the geoid undulation over a tile rectangle (degrees), on an n × n lattice."""
    w, s, e, nn = rect
    lon, lat = np.meshgrid(np.linspace(w, e, n), np.linspace(s, nn, n))
    und = geoid.undulation_m(lon.ravel(), lat.ravel())
    return float(np.nanmax(und) - np.nanmin(und)) if np.isfinite(und).any() else 0.0


def level_max_error_m(z: int) -> float:
    """CesiumJS's level maximum geometric error of the geographic scheme (a 65² heightmap's, 0.25 quality)."""
    return WGS84_A_M * 2.0 * math.pi * 0.25 / (65 * 2) / (1 << z)


# -- the true error of a decoded tile --------------------------------------------------------------------
def true_error_m(tile: dict[str, Any], rect: tuple[float, float, float, float], lon: np.ndarray,
                 lat: np.ndarray, z_m: np.ndarray) -> float:  # fmt: skip
    """Max vertical distance (m) between a *decoded* tile (:func:`decode_tile`: u/v/h after quantisation,
    the surface CesiumJS interpolates, linear in u/v) and sample points (lon, lat, z) inside ``rect``."""
    if lon.size == 0:
        return 0.0
    w, s, e, n = rect
    pu = np.clip((lon - w) / (e - w), 0.0, 1.0) * 32767.0
    pv = np.clip((lat - s) / (n - s), 0.0, 1.0) * 32767.0
    err, missed = points_vertical_error(
        tile["u"].astype(np.float64), tile["v"].astype(np.float64), np.asarray(tile["height"], np.float64),
        np.ascontiguousarray(tile["triangles"], np.int64), pu, pv, np.asarray(z_m, np.float64),
    )  # fmt: skip
    if missed:
        raise RuntimeError(f"{missed} samples fall outside every triangle of the tile (a hole in its mesh)")
    return float(err)


def _rms_per_target(t: QmTile, target_m: float) -> float | None:
    """A tile's RMS vertical error over its valid samples per metre of its target (None without samples)."""
    if not t.samples or target_m <= 0:
        return None
    return math.sqrt(t.sumsq_m2 / t.samples) / target_m


def _ceil4(x: float) -> float:
    """Round up to 0.1 mm (a declared error is never below the measured one)."""
    return math.ceil(x * 1e4) / 1e4


# -- the tiles -----------------------------------------------------------------------------------------
@dataclass
class QmTile:
    raw: bytes  # uncompressed (what the export writes by default)
    error_m: float
    triangles: int
    vertices: int
    nodata_fraction: float
    water: str  # "none", "all" or "some": the water mask the tile carries
    sumsq_m2: float = 0.0  # sum of squared vertical errors over the source samples measured ...
    samples: int = 0  # ... and how many (the level's RMS error; lattice tiles only)
    _gz: bytes | None = None

    @property
    def data(self) -> bytes:
        """gzip'd (what ``terralod serve`` sends with Content-Encoding: gzip); made on first use."""
        if self._gz is None:
            self._gz = gzip.compress(self.raw, 6, mtime=0)
        return self._gz


@dataclass(frozen=True)
class Part:
    """A part of an export: levels ``min_zoom``..``max_zoom`` (None: the terrain's finest) and the tiles
    that meet ``bbox`` (west, south, east, north, degrees; None: all). A part's tiles are the whole
    export's, byte for byte: the part chooses which tiles are written, never what is in them."""

    bbox: tuple[float, float, float, float] | None = None
    min_zoom: int = 0
    max_zoom: int | None = None

    def __post_init__(self) -> None:
        if self.bbox is not None:
            w, s, e, n = self.bbox
            if not (-180.0 <= w < e <= 180.0 and -90.0 <= s < n <= 90.0):
                raise ValueError(
                    f"Expected a box west < east within ±180, south < north within ±90, got {self.bbox}"
                )
        if self.min_zoom < 0 or (self.max_zoom is not None and self.max_zoom < self.min_zoom):
            raise ValueError(f"Expected 0 <= min zoom <= max zoom, got {self.min_zoom}, {self.max_zoom}")

    @property
    def whole(self) -> bool:
        return self.bbox is None and self.min_zoom == 0 and self.max_zoom is None

    def top(self, qm: QuantizedMesh) -> int:
        return qm.max_zoom if self.max_zoom is None else min(self.max_zoom, qm.max_zoom)

    def level_range(self, qm: QuantizedMesh, z: int) -> tuple[int, int, int, int] | None:
        """(x0, y0, x1, y1) inclusive of the part's tiles of level z; None when it has none there."""
        if z < self.min_zoom or z > self.top(qm):
            return None
        x0, y0, x1, y1 = qm.level_range(z)
        if self.bbox is not None:
            d = 180.0 / (1 << z)
            w, s, e, n = self.bbox
            x0, x1 = max(x0, int((w + 180.0) // d)), min(x1, int((e + 180.0) // d))
            y0, y1 = max(y0, int((s + 90.0) // d)), min(y1, int((n + 90.0) // d))
        return (x0, y0, x1, y1) if x0 <= x1 and y0 <= y1 else None

    def key(self) -> dict[str, Any]:
        return {
            "bbox": list(self.bbox) if self.bbox else None,
            "min_zoom": self.min_zoom,
            "max_zoom": self.max_zoom,
        }


class QuantizedMesh:
    """The quantized-mesh view of one terrain: :meth:`layer` (layer.json dict) and :meth:`tile`.

    ``terrain`` is a store (:func:`terralod.terrain.open_terrain`) or a DEM's samples
    (:func:`terralod.export.source.source_from_dem`). A tile depends on the terrain, the options and its
    code only: what the object keeps between tiles is the memo of a pure function (:meth:`rms_ratio`)
    and a record of the errors declared (``_errors``), never an input of another tile.
    """

    #: Samples a side of a resampled tile's grid, and the constants every tile's bytes depend on (recorded
    #: in each tile's dependency digest, :mod:`terralod.export.incremental`).
    grid_side = SAMPLES
    digest_constants = (SAMPLES, FINEST_ERROR_M, RMS_GOAL_M)

    def __init__(
        self, terrain: Any, *, target_fraction: float = TARGET_FRACTION, normals: bool = False,
        vertical_datum: str | None = None,
    ) -> None:  # fmt: skip
        from terralod.export.lattice import Lattice
        from terralod.export.source import SampleSource, source_for

        self.ref: SampleSource
        if isinstance(terrain, SampleSource):
            self.terrain = None
            self.ref = terrain
            self.name = getattr(terrain, "title", None) or Path(terrain.name).stem
            geo = Geodesy(getattr(terrain, "crs", None) or "EPSG:4326", None, geographic=True,
                          vertical_datum=vertical_datum)  # fmt: skip
        else:
            self.terrain = terrain
            where = str(terrain.path) if terrain.path is not None else None
            geo = Geodesy(terrain.crs, where, vertical_datum=vertical_datum)
            self.ref = source_for(terrain, geo)
            self.name = Path(str(terrain.path)).stem if terrain.path is not None else "terrain"
        #: stored heights → heights above the WGS 84 ellipsoid (None: as read), and what the outputs say
        self.geoid = geo.geoid
        self.heights = geo.vertical_record()
        self.target_fraction = target_fraction
        self.normals = bool(normals)
        self.bbox = self.ref.bbox
        # a geographic DEM is meshed on its own lattice (no resampling); anything else on 257² tile grids
        self.lattice = Lattice(self.ref) if self.ref.identity else None
        self.max_zoom = 0
        if self.lattice is not None:
            self.max_zoom = self.lattice.finest_zoom()
        else:
            while 180.0 / (1 << self.max_zoom) / (SAMPLES - 1) > self.ref.spacing_deg and self.max_zoom < 22:
                self.max_zoom += 1
        self._errors: dict[tuple[int, int, int], float] = {}  # declared error of each tile made (a record)
        self._rms_ratio: dict[tuple[int, int, int], float | None] = {}  # memo of rms_ratio (pure)

    def target_error_m(self, z: int) -> float:
        """Greedy-insertion target of level z: a fraction of CesiumJS's level error; 2x finer at the last
        level (nothing refines it, so it carries the detail of the source)."""
        f = self.target_fraction / (2.0 if z >= self.max_zoom else 1.0)
        if self.lattice is not None and z >= self.max_zoom:
            return min(f * level_max_error_m(z), FINEST_ERROR_M)
        return f * level_max_error_m(z)

    def level_range(self, z: int) -> tuple[int, int, int, int]:
        """(x0, y0, x1, y1) inclusive of the tiles of level z that meet the terrain (both roots at 0)."""
        if z == 0:
            return (0, 0, 1, 0)
        d = 180.0 / (1 << z)
        w, s, e, n = self.bbox
        x0, x1 = int((w + 180.0) // d), int((e + 180.0) // d)
        y0, y1 = int((s + 90.0) // d), int((n + 90.0) // d)
        return (x0, y0, min(x1, (2 << z) - 1), min(y1, (1 << z) - 1))

    def available(self, z: int, x: int, y: int) -> bool:
        if not 0 <= z <= self.max_zoom:
            return False
        x0, y0, x1, y1 = self.level_range(z)
        return x0 <= x <= x1 and y0 <= y <= y1

    def tile_codes(self, part: Part | None = None) -> list[tuple[int, int, int]]:
        """Every tile of the export, level by level (rows, then columns); with ``part`` only its levels and
        the tiles that meet its box (each the same tile as in the whole export)."""
        out = []
        for z in range(self.max_zoom + 1):
            r = self.level_range(z) if part is None else part.level_range(self, z)
            if r is None:
                continue
            x0, y0, x1, y1 = r
            out += [(z, x, y) for y in range(y0, y1 + 1) for x in range(x0, x1 + 1)]
        return out

    def layer(self, part: Part | None = None) -> dict[str, Any]:
        """layer.json: ``available`` per level, no per-tile metadata extension (CesiumJS parses that
        extension by default and then expects tile availability inside it); the measured errors are in
        ``terralod.error_m`` (per level) and ``errors.json`` (per tile) beside it. With a ``part``: its
        levels and tiles only, its box as the bounds."""
        top, bounds = self.max_zoom, list(self.bbox)
        available = [self.level_range(z) for z in range(self.max_zoom + 1)]
        if part is not None and not part.whole:
            top = part.top(self)
            available = [part.level_range(self, z) for z in range(top + 1)]
            if part.bbox is not None:
                w, s, e, n = self.bbox
                pw, ps, pe, pn = part.bbox
                bounds = [max(w, pw), max(s, ps), min(e, pe), min(n, pn)]
        return {
            "tilejson": "2.1.0",
            "name": self.name,
            "description": "terralod export: measured max vertical error per level in terralod.error_m, "
                           "per tile in errors.json",
            "version": "1.0.0",
            "format": "quantized-mesh-1.0",
            "scheme": "tms",
            "projection": "EPSG:4326",
            "tiles": ["{z}/{x}/{y}.terrain?v={version}"],
            "bounds": bounds,
            "minzoom": 0,
            "maxzoom": top,
            "extensions": (["octvertexnormals"] if self.normals else []) + ["watermask"],
            "available": [[dict(zip(("startX", "startY", "endX", "endY"), r, strict=True))] if r else []
                          for r in available],
            "terralod": {"heights": self.heights,
                         "error": "max vertical distance (m) between each tile as decoded (after quantisation) "
                                  "and every valid source sample inside it, in the source's own samples",
                         "outside": "the data's edge values extended outward (no cliff); watermask 255 marks "
                                    "nodata and sea at 0 m",
                         "target_error_m": [round(self.target_error_m(z), 4) for z in range(top + 1)]},
        }  # fmt: skip

    def rms_ratio(self, z: int, x: int, y: int) -> float | None:
        """RMS vertical error per metre of target of lattice tile z/x/y meshed at its level's target (None
        where it holds no valid sample): a goal-zoom tile's parent gives it, and the child's target is
        lowered by it (same terrain, so about the same ratio). A function of the code alone, memoised:
        the export makes each parent before its children and keeps the figure, so nothing is meshed twice
        there; a child asked for first (``terralod serve``) meshes its parent once, for its three siblings
        too."""
        key = (z, x, y)
        if key not in self._rms_ratio:
            target = self.target_error_m(z)
            self._rms_ratio[key] = _rms_per_target(self._lattice_tile(z, x, y, tile_rectangle(z, x, y), target),
                                                   target)  # fmt: skip
        return self._rms_ratio[key]

    def samples(self, z: int, x: int, y: int, n: int = SAMPLES) -> tuple[np.ndarray, ...]:
        """(lon, lat, heights, water) on the tile's n² lattice plus a one-sample margin ((n+2)², north row
        first); outside the data the heights continue its edge values."""
        w, s, e, nn = tile_rectangle(z, x, y)
        du, dv = (e - w) / (n - 1), (nn - s) / (n - 1)
        lon = w + du * np.arange(-1, n + 1)
        lat = nn - dv * np.arange(-1, n + 1)
        LON, LAT = np.meshgrid(lon, lat)
        hgt = self.ref.height_at(LON.ravel(), LAT.ravel()).reshape(LON.shape)
        water = self.ref.water_at(LON.ravel(), LAT.ravel()).reshape(LON.shape)
        return LON, LAT, hgt, water

    def tile(
        self, z: int, x: int, y: int, *, regular: int | None = None, target_m: float | None = None
    ) -> QmTile:
        """Tile z/x/y: greedy-insertion mesh (or, with ``regular=k``, the k² regular grid), its error
        measured on the decoded tile against the source samples inside it."""
        from pydelatin import Delatin

        rect = tile_rectangle(z, x, y)
        target = self.target_error_m(z) if target_m is None else float(target_m)
        if self.lattice is not None and not regular:
            goal_zoom = target_m is None and z == self.max_zoom - 1
            floor_m = self.target_error_m(self.max_zoom)
            ratio = self.rms_ratio(z - 1, x // 2, y // 2) if goal_zoom and z > 0 else None
            if ratio:  # the parent's RMS per metre of target predicts this tile's (same terrain)
                target = min(target, max(RMS_GOAL_M / ratio, floor_m))
            t = self._lattice_tile(z, x, y, rect, target)
            if target_m is None and z == self.max_zoom - 2:  # a goal-zoom tile's parent: its figure, kept
                self._rms_ratio[(z, x, y)] = _rms_per_target(t, target)
            if t.samples and target > 0:
                rms = math.sqrt(t.sumsq_m2 / t.samples)
                # RMS is about proportional to the target: scale it down once where still above the goal
                if goal_zoom and rms > 1.05 * RMS_GOAL_M and target > floor_m:
                    t = self._lattice_tile(z, x, y, rect, max(target * RMS_GOAL_M / rms, floor_m))
            if target_m is None:
                self._errors[(z, x, y)] = t.error_m
            return t
        LON, LAT, filled, water = self.samples(z, x, y)
        core = filled[1:-1, 1:-1]
        n = SAMPLES
        if regular:
            step = (n - 1) // (regular - 1)
            ii = np.arange(0, n, step)
            C, R = np.meshgrid(ii, ii)
            cols, rows = C.ravel(), R.ravel()
            k = len(ii)
            a = (np.arange(k - 1)[None, :] + k * np.arange(k - 1)[:, None]).ravel()
            tris = np.concatenate([np.stack([a, a + k, a + 1], 1), np.stack([a + 1, a + k, a + k + 1], 1)])
        else:
            d = Delatin(core.astype(np.float32), width=n, height=n, max_error=target)
            cols = np.rint(d.vertices[:, 0]).astype(np.int64)
            rows = (n - 1) - np.rint(d.vertices[:, 1]).astype(np.int64)  # Delatin's y grows north
            tris = np.asarray(d.triangles, np.int64)
        hv = core[rows, cols]
        w, s, e, nn = rect
        lon = w + cols * (e - w) / (n - 1)
        lat = nn - rows * (nn - s) / (n - 1)
        # counter-clockwise seen from above (east, north)
        a, b = np.column_stack([lon, lat])[tris[:, 1]], np.column_stack([lon, lat])[tris[:, 2]]
        o = np.column_stack([lon, lat])[tris[:, 0]]
        cr = (a[:, 0] - o[:, 0]) * (b[:, 1] - o[:, 1]) - (a[:, 1] - o[:, 1]) * (b[:, 0] - o[:, 0])
        tris[cr < 0] = tris[cr < 0][:, ::-1]
        normals = self._normals(filled, rows, cols, rect, lon, lat) if self.normals else None
        wmask = water[1:-1, 1:-1][:256, :256]
        if not wmask.any():
            wm: np.ndarray | int = 0
            kind = "none"
        elif wmask.all():
            wm, kind = 255, "all"
        else:
            wm, kind = (wmask * 255).astype(np.uint8), "some"
        if self.geoid is not None:  # vertices and samples alike ellipsoidal: the error is measured on them
            hv = hv + self.geoid.undulation_m(lon, lat)
        raw = encode_tile(lon, lat, hv, tris, rect, normals=normals, watermask=wm)
        dec = decode_tile(raw, rect, gzipped=False)
        err = 0.0
        for plon, plat, pz in self.ref.points_strips(z, x, y):  # a coarse tile of a region: strip by strip
            if self.geoid is not None:
                pz = pz + self.geoid.undulation_m(plon, plat)
            err = max(err, true_error_m(dec, rect, plon, plat, pz))
        err = _ceil4(err)
        nodata = float(water[1:-1, 1:-1].mean()) if kind != "none" else 0.0
        if regular is None and target_m is None:
            self._errors[(z, x, y)] = err
        return QmTile(raw, err, len(tris), len(lon), nodata, kind)

    def _lattice_tile(self, z: int, x: int, y: int, rect: tuple[float, float, float, float],
                      target: float) -> QmTile:  # fmt: skip
        """Greedy insertion on the tile's window of the source lattice (:mod:`terralod.export.lattice`);
        its error measured on the decoded tile against every valid source sample inside it."""
        from pydelatin import Delatin

        from terralod.export.lattice import lattice_error
        from terralod.kernels.lattice import clip_mesh

        lat_ = self.lattice
        stride = lat_.stride(z, self.max_zoom)
        r0, c0, g, (xw, xe, yn, ys) = lat_.grid(rect, stride)
        nr, nc = g.shape
        d = Delatin(g.astype(np.float32), width=nc, height=nr, max_error=target)
        vx = d.vertices
        gx, gy = vx[:, 0].copy(), (nr - 1) - vx[:, 1]  # Delatin's y grows north
        hx = g[np.rint(gy).astype(np.int64), np.rint(gx).astype(np.int64)]
        px, py, ph, tris = clip_mesh(gx, gy, hx, np.asarray(d.triangles, np.int64), xw, xe, yn, ys)
        fc, fr = c0 + px * stride, r0 + py * stride  # fractional lattice indices
        w, s, e, n = rect
        # one vertex per quantised u/v (clipping makes the same edge crossing in both neighbours)
        u = np.rint(np.clip((fc - (c0 + xw * stride)) / ((xe - xw) * stride), 0, 1) * 32767).astype(np.int64)
        v = np.rint(np.clip(((r0 + ys * stride) - fr) / ((ys - yn) * stride), 0, 1) * 32767).astype(np.int64)
        keep, tris = merge_uv(np.ascontiguousarray(tris, np.int64), u, v)
        fc, fr, hv, u, v = fc[keep], fr[keep], ph[keep], u[keep], v[keep]
        area = (u[tris[:, 1]] - u[tris[:, 0]]) * (v[tris[:, 2]] - v[tris[:, 0]]) - (
            v[tris[:, 1]] - v[tris[:, 0]]
        ) * (u[tris[:, 2]] - u[tris[:, 0]])
        tris = tris[area != 0]
        tris[area[area != 0] < 0] = tris[area[area != 0] < 0][:, ::-1]  # counter-clockwise (east, north)
        lon = w + u / 32767.0 * (e - w)
        lat = s + v / 32767.0 * (n - s)
        normals = None
        if self.normals:
            enu = lat_.normals_enu(fr, fc, lat, stride)
            ea, no, up = enu_frame(lon, lat)
            normals = ea * enu[:, :1] + no * enu[:, 1:2] + up * enu[:, 2:3]
            normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        wm = lat_.water_mask(rect)
        kind = "some" if isinstance(wm, np.ndarray) else ("all" if wm == 255 else "none")
        spread = 0.0
        if self.geoid is not None:
            # each vertex moves by its own undulation N; the decoded tile less N at its vertices is measured
            # against the lattice, and N's spread over the tile bounds what N does between vertices
            hv = hv + self.geoid.undulation_m(lon, lat)
        raw = encode_tile(lon, lat, hv, tris, rect, normals=normals, watermask=wm)
        dec = decode_tile(raw, rect, gzipped=False)
        if self.geoid is not None:
            dec = {**dec, "height": dec["height"] - self.geoid.undulation_m(dec["lon"], dec["lat"])}
            spread = _undulation_spread_m(self.geoid, rect)
        err, sumsq, count = lattice_error(lat_, dec, rect)
        err += spread
        nodata = float(np.mean(wm) / 255.0) if kind != "none" else 0.0
        return QmTile(raw, _ceil4(err), len(tris), len(lon), nodata, kind, sumsq, count)

    def _normals(self, filled: np.ndarray, rows: np.ndarray, cols: np.ndarray, rect: tuple[float, ...],
                 lon: np.ndarray, lat: np.ndarray) -> np.ndarray:  # fmt: skip
        """ECEF unit normals of the sampled surface at the vertices (central differences, metres)."""
        w, s, e, n = rect
        du_m = (e - w) / (SAMPLES - 1) * 111320.0 * np.cos(np.radians(np.clip(lat, -89.9, 89.9)))
        dv_m = (n - s) / (SAMPLES - 1) * 111320.0
        r, c = rows + 1, cols + 1
        dzdx = (filled[r, c + 1] - filled[r, c - 1]) / (2 * np.maximum(du_m, 1e-6))
        dzdy = (filled[r - 1, c] - filled[r + 1, c]) / (2 * dv_m)
        enu = np.column_stack([-dzdx, -dzdy, np.ones_like(dzdx)])
        enu /= np.linalg.norm(enu, axis=1, keepdims=True)
        ea, no, up = enu_frame(lon, lat)
        out = ea * enu[:, :1] + no * enu[:, 1:2] + up * enu[:, 2:3]
        return out / np.linalg.norm(out, axis=1, keepdims=True)


#: Bytes an uncompressed lattice tile takes per lattice sample of its grid (header, vertices, indices, edge
#: lists), the water mask a tile of a source with water adds on average (65,536 B where the tile holds
#: both), and a 257² tile's bytes: the estimates of SRTM3 N42E001 (voids), a 300² crop of N41E001 and
#: Kilauea (UTM, 257² tiles) are within 15 % of what they write.
BYTES_PER_SAMPLE = 7.0
WATERMASK_BYTES = 16384
GRID_TILE_BYTES = 48_000


def estimate_bytes(qm: QuantizedMesh, codes: list[tuple[int, int, int]], *, gzip_tiles: bool = False) -> int:
    """Bytes the tiles ``codes`` will take on disk (an estimate, for a free-space check before a long run):
    per lattice tile BYTES_PER_SAMPLE for each lattice sample of its grid (plus a water mask where the
    source has water), GRID_TILE_BYTES per 257² tile; gzip'd tiles about half."""
    total = 0.0
    if qm.lattice is None:
        total = GRID_TILE_BYTES * len(codes)
    else:
        lat_ = qm.lattice
        w0, s0, e0, n0 = qm.bbox
        for z, x, y in codes:
            w, s, e, n = tile_rectangle(z, x, y)
            stride = lat_.stride(z, qm.max_zoom)
            cols = max(min(e, e0) - max(w, w0), 0.0) / abs(lat_.a_deg) / stride + 2
            rows = max(min(n, n0) - max(s, s0), 0.0) / abs(lat_.e_deg) / stride + 2
            total += 1024 + BYTES_PER_SAMPLE * cols * rows + (WATERMASK_BYTES if lat_.any_water else 0)
    return int(total * (0.5 if gzip_tiles else 1.0))


def check_free_space(out: str | Path, need: int) -> None:
    """Refuse (InputError, one line) when the disk of ``out`` has less free space than ``need`` bytes."""
    import shutil

    from terralod.errors import InputError

    p = Path(out).resolve()
    while not p.exists() and p != p.parent:
        p = p.parent
    free = shutil.disk_usage(p).free
    if free < need:
        raise InputError(f"needs about {_size(need)} for its tiles and the disk has {_size(free)} free; free "
                         "some space, or export a part (--bbox, --max-zoom)", str(out))  # fmt: skip


def _size(n: float) -> str:
    return f"{n / 1e9:.2f} GB" if n >= 1e9 else f"{n / 1e6:.1f} MB"


def _inputs_and_key(terrain: Any, fmt: str, **options: Any) -> tuple[list[Path], dict[str, Any]]:
    """The files an export reads (every file of a region) and its resume key (each file's identity)."""
    files = getattr(terrain, "files", None)
    if not files:
        return export_inputs(terrain), export_key(terrain, fmt, **options)
    ident = []
    for f in files:
        st = Path(f).stat()
        ident.append([str(Path(f).resolve()), st.st_size, st.st_mtime_ns])
    return [Path(f) for f in files], {"format": fmt, "epoch": None, "input": ident, **options}


class _Deps:
    """Each tile's dependency digest (:mod:`terralod.export.incremental`), recorded with it."""

    def __init__(self, qm: QuantizedMesh, options: dict[str, Any]) -> None:
        from terralod.export.incremental import qm_global

        self.qm = qm
        self.glob = qm_global(qm, options)

    def unchanged(self, code: tuple[int, int, int], record: dict[str, Any]) -> bool:
        from terralod.export.incremental import qm_unchanged

        return qm_unchanged(self.qm, *code, self.glob, record)

    def add(self, record: dict[str, Any], code: tuple[int, int, int]) -> dict[str, Any]:
        from terralod.export.incremental import qm_digest

        got, halo = qm_digest(self.qm, *code, self.glob)
        return {**record, "deps": got, "halo": halo} if got is not None else record


def export_quantized_mesh(
    terrain: Any,
    out: str | Path,
    *,
    epoch: str | None = None,
    overwrite: bool = False,
    gzip_tiles: bool = False,
    normals: bool = False,
    resume: bool = False,
    update: bool = False,
    part: Part | None = None,
    check_space: bool = True,
    progress: Callable[[int, int], None] | None = None,
    vertical_datum: str | None = None,
    client: Any = None,
) -> ExportReport:
    """Write ``out/layer.json``, ``out/errors.json`` (measured error per tile) and ``out/Z/X/Y.terrain``.

    ``vertical_datum``: what the heights are above when the source's CRS does not say (see
    :mod:`terralod.export.vertical`); with a known datum the tiles carry heights above the WGS 84
    ellipsoid, as CesiumJS expects.

    ``terrain`` is a store or a DEM's or region's samples (:func:`terralod.export.source.source_from_dem`,
    :func:`terralod.export.source.source_from_region`). Tiles are uncompressed (any static host serves them
    as they are); ``gzip_tiles`` writes them gzip'd, for a host that sends ``Content-Encoding: gzip`` with
    them (CesiumJS cannot read gzip'd tiles without it). ``part`` (:class:`Part`) writes only some levels
    and the tiles meeting a box, each byte for byte the whole export's (``layer.json`` lists only them).
    ``resume``: the tiles an interrupted export of the same terrain and options finished are not encoded
    again; ``update``: only the files whose bytes change are rewritten (``extra["rewritten"]``). With
    ``check_space`` the free disk is checked against :func:`estimate_bytes` before the first tile. The
    output is written through :class:`terralod.output.Output`. ``client`` (a ``dask.distributed`` Client):
    the tiles are encoded on its workers (:mod:`terralod.export.distributed`), the same bytes.
    """
    from terralod.export.distributed import encode_quantized_mesh, recipe_of
    from terralod.export.source import SampleSource
    from terralod.output import Output

    t0 = time.perf_counter()
    part = part or Part()
    if not isinstance(terrain, SampleSource):
        check_exportable(terrain, epoch)
        if epoch is not None and epoch != getattr(terrain, "epoch", None):
            terrain = terrain.with_epoch(epoch)
    options: dict[str, Any] = {"gzip": bool(gzip_tiles), "normals": bool(normals)}
    if vertical_datum is not None:
        options["vertical_datum"] = vertical_datum
    if not part.whole:
        options["part"] = part.key()
    inputs, key = _inputs_and_key(terrain, "quantized-mesh", **options)
    output = Output(out, inputs=inputs, overwrite=overwrite, resume=resume, update=update, key=key,
                    keep_records=True)  # fmt: skip
    output.check()  # refusals first, before the tiler's set-up
    qm = QuantizedMesh(terrain, normals=normals, vertical_datum=vertical_datum)
    codes = qm.tile_codes(part)
    recipe = None
    if client is not None:
        recipe = recipe_of(terrain, QuantizedMesh, epoch, normals=normals, vertical_datum=vertical_datum)
    if check_space:
        check_free_space(out, estimate_bytes(qm, codes, gzip_tiles=gzip_tiles))
    rep = ExportReport(Path(out))
    per_level: dict[int, float] = {}
    per_tile: dict[str, float] = {}
    raw_bytes = gz_bytes = 0
    water = {"none": 0, "all": 0, "some": 0}
    level_sq: dict[int, list] = {}
    with output as o:
        deps = _Deps(qm, options)
        if update:  # a tile made from what it was made of last time is kept as it is, not encoded
            for c in codes:
                rel_ = "{}/{}/{}.terrain".format(*c)
                prev = o.previous(rel_) if o.record(rel_) is None else None
                if prev is not None and deps.unchanged(c, prev):
                    o.keep(rel_, prev)
        todo = [c for c in codes if o.record("{}/{}/{}.terrain".format(*c)) is None]  # the rest: resumed
        made = encode_quantized_mesh(qm, todo, gzip_tiles=gzip_tiles, client=client, recipe=recipe)
        for i, (z, x, y) in enumerate(codes):
            rel = f"{z}/{x}/{y}.terrain"
            r = o.record(rel)  # finished by the interrupted export this one resumes
            if r is None:
                _, data, r = next(made)  # here or on the Dask workers (terralod.export.distributed)
                r = deps.add(r, (z, x, y))
                o.write(rel, data, r)
            rep.tiles += 1
            rep.bytes += r["bytes"]
            raw_bytes += r["raw"]
            gz_bytes += r["gz"]
            rep.triangles += r["triangles"]
            sq = level_sq.setdefault(z, [0.0, 0])
            sq[0] += r["sumsq_m2"]
            sq[1] += r["samples"]
            water[r["water"]] += 1
            per_level[z] = max(per_level.get(z, 0.0), r["error_m"])
            per_tile[f"{z}/{x}/{y}"] = r["error_m"]
            if progress is not None:
                progress(i + 1, len(codes))
        layer = qm.layer(part)
        top = layer["maxzoom"]
        layer["terralod"]["error_m"] = [_ceil4(per_level.get(z, 0.0)) for z in range(top + 1)]
        if qm.lattice is not None:  # RMS over every valid source sample of the level (edge samples twice)
            layer["terralod"]["rms_m"] = [
                round(math.sqrt(level_sq[z][0] / level_sq[z][1]), 4) if level_sq.get(z, [0, 0])[1] else 0.0
                for z in range(top + 1)
            ]
        layer["terralod"]["gzip"] = bool(gzip_tiles)
        js = json.dumps(layer, indent=1)
        o.write("layer.json", js.encode())
        o.write("errors.json", json.dumps({"unit": "m", "tiles": per_tile}, separators=(",", ":")).encode())
        rep.bytes += len(js)
        o.seal()
        changes = {"rewritten": list(o.rewritten), "removed": o.prune()} if update else {}
    rep.seconds = time.perf_counter() - t0
    rep.extra = {
        "format": "quantized-mesh",
        "max_zoom": qm.max_zoom,
        "gzip": bool(gzip_tiles),
        "tile_bytes_raw": raw_bytes,
        "tile_bytes_gzip": gz_bytes if gzip_tiles else None,
        "water_masks": water,
        "error_m_per_level": layer["terralod"]["error_m"],
        "worst_error_m": max(per_tile.values(), default=0.0),
        "resumed": o.adopted is not None,
        "encoded": len(todo),
        **changes,
    }
    return rep
