"""One interface for every terrain with levels of detail: grid tile stores and detail-increment TINs.

Every consumer — the renderer, the window viewer, the CLI, the exports, the server and the change code —
takes a :class:`Terrain` and never asks which kind it holds. :func:`open_terrain` (``terralod.open``)
opens any ``.terra`` store; :class:`GridTerrain` and :class:`TinTerrain` wrap objects already open.

What a terrain offers (metres everywhere, x east, y north, z up):

- ``crs``, ``bounds_m`` (west, south, east, north in the CRS), ``elevation_range_m``, ``epochs``;
- ``engine(threshold_px=..., background=..., cull=...)`` → a :class:`TerrainEngine`: ``update(camera)`` →
  a :class:`Frame` whose ``meshes()`` yields ``(code, vertices (N, 3) float64 world metres, triangles
  (K, 3) uint32/int32 counter-clockwise, normals (N, 3) float32)`` — stitched and crack-free for grid
  stores, one mesh per sub-block at its scale for TINs — and ``stats`` (``FrameStats``/dict with at least
  tiles, triangles, max_screen_error_px, select_ms, stitch_ms);
- ``select(camera)``: the same through one engine kept by the terrain (incremental between calls);
- ``lod_tree()`` → the static LOD tree for exports: :class:`LodNode` (code, parent, measured errors,
  bounding box), parents before children, coarser nodes replaced by their children; ``lod_mesh(code)``
  the geometry of one node exactly as stored.

Layering: this module sits above the store, the runtime and the TIN model and below every consumer; it
never imports the renderer.
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np

from terralod.errors import InputError, StoreError

__all__ = [
    "Frame",
    "GridTerrain",
    "LodNode",
    "Terrain",
    "TerrainEngine",
    "TinTerrain",
    "as_terrain",
    "frame_stats",
    "open_terrain",
]

#: A node code of :meth:`Terrain.lod_tree`: a tile ``(level, x, y)`` of a grid store, or
#: ``(rung, sub_block, scale)`` of a TIN (rung 0 = the sub-block's base mesh).
NodeCode = tuple[int, int, int]


@dataclass(frozen=True, slots=True)
class LodNode:
    """One node of a terrain's static LOD tree (what the 3D Tiles / quantized-mesh exports walk).

    Attributes
    ----------
    code : node code (see :data:`NodeCode`)
    parent : the node this one refines, or None for a root
    error_m : measured one-sided Hausdorff distance from the source samples to this node's surface, metres
        (for TINs the measured max vertical error, an upper bound of it)
    vertical_error_m : measured max vertical distance, metres
    box_m : (west, south, z_min, east, north, z_max) of the node's geometry, world metres
    """

    code: NodeCode
    parent: NodeCode | None
    error_m: float
    vertical_error_m: float
    box_m: tuple[float, float, float, float, float, float]


@runtime_checkable
class Frame(Protocol):
    """What one camera update produced: meshes to draw and their statistics."""

    @property
    def stats(self) -> Any: ...

    def meshes(self) -> Iterator[tuple[Any, np.ndarray, np.ndarray, np.ndarray]]: ...


@runtime_checkable
class TerrainEngine(Protocol):
    """Per-frame selection over a terrain: synchronous ``update`` or ``request`` + ``latest``."""

    threshold_px: float

    def update(self, camera: Any) -> Frame: ...

    def request(self, camera: Any) -> None: ...

    def latest(self) -> Frame | None: ...

    def close(self) -> None: ...


@runtime_checkable
class Terrain(Protocol):
    """A terrain with levels of detail (see the module docstring)."""

    kind: str
    path: Path | None

    @property
    def crs(self) -> str | None: ...

    @property
    def bounds_m(self) -> tuple[float, float, float, float]: ...

    @property
    def elevation_range_m(self) -> tuple[float, float]: ...

    @property
    def epochs(self) -> list[str]: ...

    def engine(self, *, threshold_px: float = 2.0, background: bool = False, cull: Sequence[str] = (),
               async_loads: bool = False) -> TerrainEngine: ...  # fmt: skip

    def select(self, camera: Any) -> Frame: ...

    def lod_tree(self) -> list[LodNode]: ...

    def lod_mesh(self, code: NodeCode) -> tuple[np.ndarray, np.ndarray]: ...

    def lod_vertices(self, level: int) -> dict[NodeCode, int] | None: ...

    def close(self) -> None: ...


def frame_stats(frame: Frame) -> dict[str, Any]:
    """A frame's statistics as a plain dict (grid selections carry a ``FrameStats``, TIN frames a dict)."""
    st = frame.stats
    if isinstance(st, dict):
        return dict(st)
    if hasattr(st, "as_dict"):
        return dict(st.as_dict())
    return dict(vars(st))


def _cull_options(cull: Sequence[str]) -> dict[str, bool]:
    bad = set(cull) - {"backface", "region"}
    if bad:
        raise ValueError(f"Expected culling among backface, region; got {sorted(bad)}")
    return {"cull_backfacing": "backface" in cull, "cull_region": "region" in cull}


class _TerrainBase:
    """Shared lifetime and the lazily created engine of :meth:`select`."""

    kind = "?"
    path: Path | None = None

    def __init__(self) -> None:
        self._engine: Any = None

    def select(self, camera: Any) -> Frame:
        """Select for ``camera`` through one engine kept by the terrain (2 px; incremental between calls)."""
        if self._engine is None:
            self._engine = self.engine()
        frame: Frame = self._engine.update(camera)
        return frame

    def engine(self, *, threshold_px: float = 2.0, background: bool = False, cull: Sequence[str] = (),
               async_loads: bool = False) -> Any:  # fmt: skip
        raise NotImplementedError

    def close(self) -> None:
        if self._engine is not None:
            self._engine.close()
            self._engine = None

    def __enter__(self) -> Any:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class GridTerrain(_TerrainBase):
    """A grid tile store (chunked / cohesion / any pyramid method), optionally with fractal levels below it.

    Parameters
    ----------
    store : an open :class:`terralod.store.TileStore`
    epoch : the epoch to read (a name of ``epochs``; default: the store's, i.e. the latest). Another epoch
        than the store's opens the file again at that epoch (closed with the terrain).
    source : what the engine selects from: the store itself (default) or a
        :class:`terralod.runtime.fractal_source.FractalSource` over it (Hu & Wang)
    own : close the store with the terrain
    """

    kind = "grid"

    def __init__(
        self, store: Any, source: Any = None, *, own: bool = False, epoch: str | None = None
    ) -> None:
        super().__init__()
        if epoch is not None and getattr(store, "epoch", None) != epoch:
            from terralod.store import open_store

            if own:
                store.close()
            store, source, own = open_store(store.path, epoch=epoch), None, True
        self.store = store
        self.source = store if source is None else source
        self.path = Path(store.path) if getattr(store, "path", None) is not None else None
        self._own = own

    @property
    def meta(self) -> dict[str, Any]:
        return dict(self.store.meta)

    @property
    def crs(self) -> str | None:
        crs: str | None = self.store.crs
        return crs

    @property
    def bounds_m(self) -> tuple[float, float, float, float]:
        """(west, south, east, north) of the sample centres, metres in the store's CRS."""
        t = self.source.transform
        w, h = self.source.pyramid.width, self.source.pyramid.height
        x0, y0 = t.c + 0.5 * t.a, t.f + 0.5 * t.e
        x1, y1 = x0 + (w - 1) * t.a, y0 + (h - 1) * t.e
        return (min(x0, x1), min(y0, y1), max(x0, x1), max(y0, y1))

    @property
    def elevation_range_m(self) -> tuple[float, float]:
        """(lowest, highest) vertex height of the root tile's level (the whole terrain), metres."""
        rows = [r for r in self.store.tile_summaries() if r["level"] == 0]
        if not rows:
            return (0.0, 1.0)
        return (float(min(r["z_min_m"] for r in rows)), float(max(r["z_max_m"] for r in rows)))

    @property
    def epochs(self) -> list[str]:
        """Names of the store's epochs, in the order they were added ([] for a store without epochs)."""
        return list(getattr(self.store, "epochs", []))

    @property
    def epoch(self) -> str | None:
        """The epoch whose tiles this terrain reads (None for a store without epochs)."""
        return getattr(self.store, "epoch", None)

    def with_epoch(self, epoch: str) -> GridTerrain:
        """The same store at another epoch (a new terrain that owns its own connection)."""
        from terralod.store import open_store

        return GridTerrain(open_store(self.store.path, epoch=epoch), own=True)

    def heightfield(self, epoch: str | None = None) -> Any:
        """The source elevation grid of ``epoch`` (default: this terrain's) exactly as built
        (:func:`terralod.pyramid.update.stored_heightfield`)."""
        from terralod.pyramid.update import stored_heightfield

        return stored_heightfield(self.store, epoch if epoch is not None else self.epoch)

    def engine(self, *, threshold_px: float = 2.0, background: bool = False, cull: Sequence[str] = (),
               async_loads: bool = False) -> Any:  # fmt: skip
        """The runtime :class:`terralod.runtime.Engine` over this store; ``async_loads`` reads tiles on a
        worker thread (interactive viewers), never on the frame path."""
        from terralod.runtime import Engine

        opts = _cull_options(cull)
        return Engine(self.source, threshold_px=threshold_px, background=background, async_loads=async_loads,
                      cull_backfacing=opts["cull_backfacing"], cull_region=opts["cull_region"])  # fmt: skip

    def lod_tree(self) -> list[LodNode]:
        """Every stored tile, by level: the quadtree as stored, with its measured (monotone) errors."""
        b = self.store.pyramid
        out = []
        # the rows streamed in the tree's order (level, then rows, then columns): no list of every tile's
        # summary beside the tree (1.2 KB a node at the peak, where the tree keeps about 0.9)
        for level, x, y, error_m, vertical_error_m, z_min_m, z_max_m in self.store.each_tile_extent():
            code = (int(level), int(x), int(y))
            x0, y0, x1, y1 = self._tile_xy(b, code)
            parent = None if code[0] == 0 else (code[0] - 1, code[1] // 2, code[2] // 2)
            out.append(LodNode(code, parent, float(error_m), float(vertical_error_m),
                               (x0, y0, float(z_min_m), x1, y1, float(z_max_m))))  # fmt: skip
        return out

    def _tile_xy(self, pyramid: Any, code: NodeCode) -> tuple[float, float, float, float]:
        t = self.store.transform
        r0, c0 = pyramid.origin_rc(code)
        span = pyramid.span(code[0])
        r1 = min(r0 + span, pyramid.height - 1)
        c1 = min(c0 + span, pyramid.width - 1)
        xa, xb = t.c + (c0 + 0.5) * t.a, t.c + (c1 + 0.5) * t.a
        ya, yb = t.f + (r0 + 0.5) * t.e, t.f + (r1 + 0.5) * t.e
        return (min(xa, xb), min(ya, yb), max(xa, xb), max(ya, yb))

    def lod_vertices(self, level: int) -> dict[NodeCode, int] | None:
        """{code: vertices} of level ``level``'s tiles, from the store's counts (no mesh read): what an
        export sizes its blocks of meshes in flight by."""
        counts: dict[NodeCode, int] = self.store.tile_vertex_counts(level)
        return counts

    def lod_mesh(self, code: NodeCode) -> tuple[np.ndarray, np.ndarray]:
        """(vertices (N, 3) float64 world metres, triangles (K, 3) uint32) of tile ``code`` as stored."""
        tile = self.store.tile(*code)
        return tile.vertices, tile.triangles

    def close(self) -> None:
        super().close()
        if self._own:
            self.store.close()


class TinTerrain(_TerrainBase):
    """A detail-increment TIN (Ai et al., 2019): one mesh per sub-block, each at its own scale.

    ``lod_tree`` gives each sub-block a ladder of scales whose measured max vertical errors halve from its
    base mesh (rung 0) to full resolution (the input TIN, error 0): ``code = (rung, sub_block, scale)``.
    """

    kind = "tin"

    def __init__(self, model: Any, meta: dict[str, Any] | None = None, path: str | os.PathLike[str] | None = None
                 ) -> None:  # fmt: skip
        super().__init__()
        self.model = model
        self._meta = dict(meta or {})
        self.path = Path(path) if path is not None else None
        self._tree: list[LodNode] | None = None
        self._block_slots: list[np.ndarray] | None = None

    @property
    def meta(self) -> dict[str, Any]:
        return dict(self._meta)

    @property
    def crs(self) -> str | None:
        return getattr(self.model, "crs", None) or self._meta.get("crs")

    @property
    def model_digest(self) -> str | None:
        """The stored model's SHA-256 (its store's checksum, verified when it was opened), or None for a
        model held only in memory: what every web tile of this TIN depends on, with the export's options."""
        if self.path is None:
            return None
        from terralod.store import tin_model_sha256

        return tin_model_sha256(self.path)

    @property
    def bounds_m(self) -> tuple[float, float, float, float]:
        v = self.model.vertices_m
        lo, hi = v.min(axis=0), v.max(axis=0)
        return (float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]))

    @property
    def elevation_range_m(self) -> tuple[float, float]:
        z = self.model.vertices_m[:, 2]
        return (float(z.min()), float(z.max()))

    @property
    def epochs(self) -> list[str]:
        return []

    def engine(self, *, threshold_px: float = 2.0, background: bool = False, cull: Sequence[str] = (),
               async_loads: bool = False) -> Any:  # fmt: skip
        """A :class:`terralod.runtime.tin.TinEngine` (the model is in memory: nothing to load)."""
        from terralod.runtime.tin import TinEngine

        return TinEngine(self.model, threshold_px=threshold_px)

    def ladder(self, block: int) -> list[int]:
        """Scales of sub-block ``block`` whose measured errors halve: base, then each first scale at or
        below half the previous rung's error, ending at full resolution. After the first rung of error 0
        only full resolution follows: a scale of error 0 halves nothing (every later scale is exact too,
        and a client never refines a tile whose error is 0)."""
        from terralod.kernels.qem_replay import halving_rungs

        return [int(s) for s in halving_rungs(np.ascontiguousarray(self.model.error_m(block), np.float64))]

    def lod_tree(self) -> list[LodNode]:
        if self._tree is not None:
            return self._tree
        from terralod.kernels.meshtopo import used_bounds

        out: list[LodNode] = []
        saved = self.model.block_scales
        try:
            for b in range(self.model.n_blocks):
                err = self.model.error_m(b)
                parent = None
                for i, s in enumerate(self.ladder(b)):
                    v, t = self.lod_mesh((i, b, s))
                    lo, hi = used_bounds(v, np.ascontiguousarray(t, np.int64))  # zeros without triangles
                    e = float(err[s])
                    out.append(LodNode((i, b, s), parent, e, e, (float(lo[0]), float(lo[1]), float(lo[2]),
                                                             float(hi[0]), float(hi[1]), float(hi[2]))))  # fmt: skip
                    parent = (i, b, s)
        finally:
            self.model.set_block_scales(saved)
        self._tree = out
        return out

    def lod_vertices(self, level: int) -> dict[NodeCode, int] | None:
        """None: a TIN's nodes share the model's one point array (its meshes in flight are its triangles)."""
        return None

    def lod_mesh(self, code: NodeCode) -> tuple[np.ndarray, np.ndarray]:
        """(vertices (N, 3) float64 world metres, triangles (K, 3) int32) of sub-block ``code[1]`` at scale
        ``code[2]`` (only that sub-block's triangles; vertices are the model's shared point array)."""
        _, b, s = code
        scales = self.model.block_scales
        scales[b] = s
        self.model.set_block_scales(scales)
        slots = self._slots()[b]
        tris = self.model._tris[slots[self.model._alive[slots]]]
        return self.model.vertices_m, tris

    def _slots(self) -> list[np.ndarray]:
        """The triangle slots of each sub-block, ascending (:func:`terralod.runtime.tin.slot_blocks`)."""
        if self._block_slots is None:
            from terralod.runtime.tin import slot_blocks

            sb = slot_blocks(self.model)
            order = np.argsort(sb, kind="stable")
            ptr = np.searchsorted(sb[order], np.arange(self.model.n_blocks + 1))
            self._block_slots = [order[ptr[b] : ptr[b + 1]] for b in range(self.model.n_blocks)]
        return self._block_slots


def as_terrain(obj: Any) -> Any:
    """``obj`` as a :class:`Terrain`: a terrain as is; an open tile store, a fractal source over one, or a
    detail-increment model wrapped (the one place that tells the kinds apart)."""
    if isinstance(obj, _TerrainBase):
        return obj
    if hasattr(obj, "increments") and hasattr(obj, "set_block_scales"):
        return TinTerrain(obj)
    if hasattr(obj, "pyramid") and hasattr(obj, "tile"):
        store = getattr(obj, "store", None)
        if store is not None and hasattr(store, "tile_summaries") and obj is not store:
            return GridTerrain(store, obj)
        return GridTerrain(obj)
    raise TypeError(f"Expected a terrain, tile store or TIN model, got {type(obj).__name__}")


def _is_sqlite(p: Path) -> bool:
    try:
        with open(p, "rb") as fh:
            return fh.read(16) == b"SQLite format 3\x00"
    except OSError:
        return False


def open_terrain(path: str | os.PathLike[str], epoch: str | None = None) -> GridTerrain | TinTerrain:
    """Open any ``.terra`` store as a :class:`Terrain` (read-only): a grid tile store or a TIN store;
    ``epoch`` selects one epoch of a store of epochs (default: the latest).

    Raises
    ------
    InputNotFoundError, CorruptStoreError, StoreError : a missing, damaged or foreign file (one clear line).
    """
    from terralod.errors import InputNotFoundError
    from terralod.store import TIN_METHOD, open_store, store_method

    p = Path(path)
    if not p.exists():
        raise InputNotFoundError("no such file", str(p))
    if p.is_dir():
        raise InputError("is a folder, not a .terra store", str(p))
    if not _is_sqlite(p):
        raise StoreError("not a terralod store (expected a .terra SQLite file)", str(p))
    if store_method(p) == TIN_METHOD:
        from terralod.tin.terra import load_model_from_store

        model, meta = load_model_from_store(p)
        return TinTerrain(model, meta, p)
    return GridTerrain(open_store(p, epoch=epoch), own=True)


def overview_distance_m(terrain: Terrain) -> float:
    """Horizontal diagonal of a terrain's bounds, metres (the scale of its overview camera)."""
    w, s, e, n = terrain.bounds_m
    return float(math.hypot(e - w, n - s))
