"""Fractal levels below a store's finest level, generated on demand for the runtime (Hu & Wang §3.1 with
the screen-space rule of DESIGN.md, ``../shared/papers/001_aded52eb792094ea.txt``).

:class:`FractalSource` is a tile source for :class:`terralod.runtime.Engine`: levels 0..L are the store's
tiles; levels L+1..L+E are meshes of :class:`terralod.fractal.FractalDetail` (fBm detail seeded by world
position, so neighbours agree), generated when the selection asks for them and kept in the detail's LRU —
never stored for the whole terrain. The engine refines into them exactly as into stored levels: while
the projected error of a tile exceeds the threshold.

Pyramid: the source sample grid becomes the DEM refined 2^E times ((W-1) 2^E + 1 samples a side), so a
store tile (k, x, y) keeps its code and footprint and its grid coordinates are multiplied by 2^E.

Errors (deviation, stated): a fractal tile's error is the detail's 3-sigma bound ``detail_error_m(e)`` —
how far the e-level surface may depart from the fully refined fractal surface — because that surface
is never built; a store tile's error becomes ``max(stored error, detail_error_m(0))`` so the pyramid stays
monotone. The z-range of a fractal tile is its DEM ancestor's widened by ``detail_error_m(0)``.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import numpy as np

from terralod.pyramid.footprint import footprint_mask
from terralod.tiles import TilePyramid, ancestor


@dataclass(frozen=True, eq=False)
class _SourceTile:
    code: tuple[int, int, int]
    vertices: np.ndarray
    triangles: np.ndarray
    grid_rc: np.ndarray
    error_m: float
    vertical_error_m: float
    measured_error_m: float
    z_min_m: float
    z_max_m: float


class FractalSource:
    """A store extended by ``extra_levels`` fractal levels (see the module docstring).

    Parameters
    ----------
    store : an open TileStore
    detail : a :class:`terralod.fractal.FractalDetail` of the store's source heightfield
    extra_levels : E, fractal levels below the finest stored level (1..6)
    workers : threads generating a frame's new fractal tiles (:meth:`tiles`; the numba kernels release the
        GIL); default: the machine's cores. 1 generates them one after the other.
    """

    def __init__(self, store: Any, detail: Any, extra_levels: int = 2, *, workers: int | None = None) -> None:
        if not 1 <= int(extra_levels) <= 6:
            raise ValueError(f"Expected 1..6 extra levels, got {extra_levels}")
        self.store = store
        self.detail = detail
        self.extra_levels = e = int(extra_levels)
        base = store.pyramid
        self.factor = f = 1 << e
        self.base_level = base.max_level
        self.pyramid = TilePyramid((base.width - 1) * f + 1, (base.height - 1) * f + 1, base.tile_size)
        if self.pyramid.max_level != base.max_level + e:
            raise ValueError("Expected the refined pyramid to add exactly the extra levels")
        self.transform = detail.amplified_transform(f)
        self.path = getattr(store, "path", None)
        self.meta = getattr(store, "meta", {})
        self._floor = [detail.detail_error_m(k) for k in range(e + 1)]
        self._summaries: list[dict[str, Any]] | None = None
        self.workers = max(1, int(workers if workers is not None else (os.cpu_count() or 1)))
        self._pool: ThreadPoolExecutor | None = None

    def tile_summaries(self) -> list[dict[str, Any]]:
        if self._summaries is not None:
            return self._summaries
        rows = [dict(r) for r in self.store.tile_summaries()]
        pad = self._floor[0]
        finest = {}
        for r in rows:
            r["error_m"] = max(r["error_m"], pad)
            r["vertical_error_m"] = max(r["vertical_error_m"], pad)
            r["measured_error_m"] = max(r["measured_error_m"], pad)
            if r["level"] == self.base_level:
                finest[(r["x"], r["y"])] = (r["z_min_m"] - pad, r["z_max_m"] + pad)
        cells = self.pyramid.cells
        for k in range(1, self.extra_levels + 1):
            level = self.base_level + k
            err = self._floor[k]
            for code in self.pyramid.tile_codes(level):
                zlo, zhi = finest[ancestor(code, self.base_level)[1:]]
                rows.append({
                    "level": level, "x": code[1], "y": code[2], "error_m": err, "vertical_error_m": err,
                    "measured_error_m": err, "z_min_m": zlo, "z_max_m": zhi, "n_triangles": 2 * cells * cells,
                    "n_vertices": (cells + 1) ** 2, "rms_error_m": err / 3.0, "n_samples": 0, "bytes": 0,
                    "measured_vertical_error_m": err,
                })  # fmt: skip
        self._summaries = rows
        return rows

    def tiles(self, codes: list[tuple[int, int, int]]) -> list[_SourceTile]:
        """The tiles of ``codes``, in order: store tiles read on this thread (an SQLite connection stays on
        its thread), fractal tiles generated on ``workers`` threads. Same bytes as :meth:`tile` one by one
        (every displacement is a pure function of position, level and seed)."""
        out: list[Any] = [None] * len(codes)
        gen = []
        for i, c in enumerate(codes):
            if c[0] <= self.base_level:
                out[i] = self.tile(*c)
            else:
                gen.append(i)
        if len(gen) > 1 and self.workers > 1:
            if self._pool is None:
                self._pool = ThreadPoolExecutor(self.workers, thread_name_prefix="terralod-fractal")
            for i, t in zip(gen, self._pool.map(lambda i: self.tile(*codes[i]), gen), strict=True):
                out[i] = t
        else:
            for i in gen:
                out[i] = self.tile(*codes[i])
        return out

    def tile(self, level: int, x: int, y: int) -> _SourceTile:
        f = self.factor
        if level <= self.base_level:
            t = self.store.tile(level, x, y)
            pad = self._floor[0]
            return _SourceTile(
                t.code, t.vertices, t.triangles, t.grid_rc * f, max(t.error_m, pad),
                max(t.vertical_error_m, pad), max(t.measured_error_m, pad), t.z_min_m, t.z_max_m,
            )  # fmt: skip
        ft = self.detail.tile((level, x, y), tile_size=self.pyramid.tile_size)
        err = self._floor[level - self.base_level]
        verts, tris, rows, cols = ft.vertices, ft.triangles, ft.rows, ft.cols
        valid = self.detail.hf.valid
        r0, c0 = max(int(rows.min()), 0), max(int(cols.min()), 0)
        if not valid[r0 : int(np.ceil(rows.max())) + 1, c0 : int(np.ceil(cols.max())) + 1].all():
            # no detail over nodata either: the footprint of the stored tiles (terralod.pyramid.footprint)
            keep = footprint_mask(
                rows.astype(np.float64), cols.astype(np.float64), tris.astype(np.int64), valid
            )
            used = np.zeros(len(verts), bool)
            used[tris[keep].ravel()] = True
            remap = np.cumsum(used) - 1
            verts, rows, cols, tris = verts[used], rows[used], cols[used], remap[tris[keep]]
        rc = np.stack([rows * f, cols * f], axis=1)
        z = verts[:, 2]
        zlo, zhi = (float(z.min()), float(z.max())) if len(z) else (0.0, 0.0)
        return _SourceTile(
            (level, x, y), verts, tris.astype(np.uint32), rc, err, err, err, zlo, zhi,
        )  # fmt: skip
