"""The detail-increment model of Ai et al. (2019): base mesh + ΔT records + the current scale of each sub-block.

Paper: ``../shared/papers/003_2a2cfcda929de24c.txt``

- eq. 1–2: f(S_i) = f(S_0) + ΔT_0 + … + ΔT_{i-1}; moving between scales adds or subtracts increments
  (:meth:`DetailIncrementModel.set_block_scales`);
- §2.3.1: reconstruction by applying records forwards (vertex split) or backwards (edge collapse);
- §4: storage of base + increments against a static pyramid (``benchmarks/tin.py``).

The records themselves (table 1, merging §2.2.2, MMQE codes) are in :mod:`terralod.tin.records`; the
file formats (the paper's text scheme, the binary container, format 5) in :mod:`terralod.tin.fileformat`.
This module builds the model (Delaunay TIN, sub-blocks, QEM collapses, records), selects scales
(:mod:`terralod.tin.svo`), and turns the model into the container's arrays and back (the split coding of
:mod:`terralod.kernels.tincodec`: per-vertex sub-block labels, insertion order, exact integer xy).
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import numpy as np

from terralod.errors import CorruptStoreError, InputError
from terralod.kernels.qem import block_corner_bounds
from terralod.kernels.qem_replay import coarsen_records, refine_records
from terralod.kernels.tincodec import V_ESCAPE, split_codes
from terralod.tin.fileformat import (
    decode_mesh_rows,
    encode_mesh_rows,
    read_container,
    write_container_stream,
    write_text,
)
from terralod.tin.records import DeltaT, Increments
from terralod.tin.svo import (
    box_distance_m,
    projected_px,
    select_scales,
    select_scales_measured,
)

__all__ = ["DetailIncrementModel"]


def _grid_xy(vertices_m: np.ndarray) -> np.ndarray:
    """(V, 2) int64: vertex xy on an integer grid of 2^26 steps over the larger side, so the split coder's
    orientation tests are exact and its walks the same on every machine (numpy's elementwise arithmetic is
    correctly rounded)."""
    xy = np.asarray(vertices_m, np.float64)[:, :2]
    if not xy.size:
        return np.zeros((0, 2), np.int64)
    lo = xy.min(axis=0)
    span = float((xy.max(axis=0) - lo).max())
    if not span > 0.0:
        return np.zeros(xy.shape, np.int64)
    return np.floor((xy - lo) * (2.0**26 / span)).astype(np.int64)


def _block_cells(vertices_m: np.ndarray, k: int) -> np.ndarray:
    """(V,) int64: the k × k sub-block cell holding each vertex's xy (row-major from the north-west, the
    rule :func:`terralod.tin.delaunay.split_sub_blocks` applies to triangle centroids)."""
    xy = np.asarray(vertices_m, np.float64)[:, :2]
    if not xy.size:
        return np.zeros(0, np.int64)
    lo = xy.min(axis=0)
    hi = xy.max(axis=0)
    span = np.maximum(hi - lo, np.finfo(np.float64).tiny)
    col = np.clip(((xy[:, 0] - lo[0]) / span[0] * k).astype(np.int64), 0, k - 1)
    row = np.clip(((hi[1] - xy[:, 1]) / span[1] * k).astype(np.int64), 0, k - 1)
    return row * k + col


def _insert_order(label: np.ndarray, n_blocks: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Vertices by (sub-block that inserts them, index): (position of each vertex, vertex at each position,
    first and end position of each block's segment); label ``n_blocks``: never inserted (base or unused)."""
    vat = np.argsort(label, kind="stable").astype(np.int64)
    vpos = np.empty_like(vat)
    vpos[vat] = np.arange(vat.size, dtype=np.int64)
    seg = np.searchsorted(label[vat], np.arange(n_blocks + 1)).astype(np.int64)
    return vpos, vat, seg[:-1], seg[1:]


class _Clock:
    """Stage timer: ``clock(name)`` adds the seconds since the last call to ``timings[name]``."""

    def __init__(self, timings: dict[str, float] | None) -> None:
        self.timings = timings
        self.t = time.perf_counter()

    def __call__(self, name: str) -> None:
        now = time.perf_counter()
        if self.timings is not None:
            self.timings[name] = self.timings.get(name, 0.0) + now - self.t
        self.t = now


# -- the model -------------------------------------------------------------------------------------------
def _split_arrays(qxy, z, label, base, block_ptr, vpos, vat, lo, hi, rec_u, rec_v, wing, rec_m) -> dict[str, np.ndarray]:  # fmt: skip
    """The file's arrays of the vertex splits: :func:`terralod.kernels.tincodec.split_codes` (one sequential
    pass, without the GIL) of records ``rec_u, rec_v`` (int64), wings ``wing`` (x1) and fan sizes ``rec_m``
    over the base ``base`` and each vertex's inserting block ``label``."""
    sym = [np.zeros(rec_u.shape[0], np.int64) for _ in range(6)]
    status, n_esc, *_ = split_codes(True, qxy, z, label, base, block_ptr, vpos, vat, lo, hi, rec_u, rec_v, wing,
                                    rec_m, *sym, False, np.zeros((0, 3), np.int32), np.zeros(0, np.int64))  # fmt: skip
    if status == -2:
        raise InputError(f"a TIN of {base.shape[0] + 2 * rec_u.shape[0]:,} triangle slots is more than one model "
                         "codes (about 715 M): build it in parts (--bbox)")  # fmt: skip
    if status != 0:
        raise RuntimeError(f"vertex splits do not code (record {status - 1})")
    sym_u, sym_v, sym_j, after, esc_v, esc_x = sym
    return {
        "split_u": sym_u,
        "split_v": sym_v,
        "split_j": sym_j,
        "split_after": after,
        "escape_v": esc_v[:n_esc],
        "escape_x1": esc_x[:n_esc],
    }


def _vertex_labels(n_vertices: int, n_blocks: int, rec_u: np.ndarray, block_ptr: np.ndarray) -> np.ndarray:
    """(V,) int64: the sub-block whose records insert each vertex (``n_blocks`` for the base's)."""
    label = np.full(n_vertices, n_blocks, np.int64)
    label[rec_u] = np.repeat(np.arange(n_blocks, dtype=np.int64), np.diff(block_ptr))
    return label


def _split_args(vertices_m, label, n_blocks, base, block_ptr, rec_u, rec_v, wing, rec_m) -> tuple:  # fmt: skip
    """The arguments of :func:`_split_arrays` for compact records (block-major, refinement order)."""
    vpos, vat, lo, hi = _insert_order(label, n_blocks)
    i64 = [np.ascontiguousarray(a, np.int64) for a in (block_ptr, rec_u, rec_v, wing, rec_m)]
    return (_grid_xy(vertices_m), vertices_m[:, 2].copy(), label, base, i64[0], vpos, vat, lo, hi, *i64[1:])


def _splits_beside(vertices_m: np.ndarray, n_blocks: int) -> tuple[Callable[..., None], list]:
    """An ``on_compact`` hook for :meth:`Increments.from_log` that starts :func:`_split_arrays` on a thread
    of its own with the compact records (they are all it needs), and the list it puts the future in: the
    file's sequential split coder then runs beside the records' sequential replay instead of after it."""
    box: list = []

    def hook(base_tri, block_records, u, v, x1, m) -> None:
        from concurrent.futures import ThreadPoolExecutor

        block_ptr = np.concatenate([[0], np.cumsum(block_records)])
        label = _vertex_labels(vertices_m.shape[0], n_blocks, u, block_ptr)
        args = _split_args(vertices_m, label, n_blocks, np.ascontiguousarray(base_tri, np.int32), block_ptr, u,
                           v, x1, m)  # fmt: skip
        pool = ThreadPoolExecutor(1)
        box.append(pool.submit(_split_arrays, *args))
        pool.shutdown(wait=False)  # the thread ends with its one task

    return hook, box


def _auto_sub_blocks(n_points: int) -> int:
    """k * k sub-blocks for a cloud of ``n_points``: about 32 k points (64 k triangles) a block, k >= 2."""
    k = max(2, math.ceil(math.sqrt(n_points / 32768)))
    return k * k


class DetailIncrementModel:
    """A continuous-scale TIN: the base mesh, the detail increments and the current scale of each sub-block.

    Build with :meth:`from_points`, :meth:`from_las` or :meth:`from_heightfield`; read with :meth:`load`.
    Coordinates are world metres (x east, y north, z up). Scales follow the paper: per sub-block, S_0 is
    the base (``base_fraction`` of its triangles) and S_{n_b} the full-resolution TIN. The model keeps one
    current state and moves it by applying increments (eq. 2), so nearby scale changes are cheap.

    Attributes
    ----------
    vertices_m : (V, 3) float64
        Every vertex of the full-resolution TIN, world metres (read-only).
    increments : Increments
        The records.
    k : int
        Sub-blocks per side (``n_blocks = k * k``).
    block_centres_m : (B, 3) float64
        Centre of each sub-block (the SVO segment's position), metres.
    block_bounds_m : (B, 4) float64
        (west, south, east, north) of each sub-block's cell, metres.
    source, crs, notes
        Provenance: input name, CRS WKT (or None), conversions applied.
    """

    def __init__(
        self,
        vertices_m: np.ndarray,
        base_tris: np.ndarray,
        base_alive: np.ndarray,
        increments: Increments,
        k: int,
        block_centres_m: np.ndarray,
        block_bounds_m: np.ndarray,
        *,
        source: str = "<points>",
        crs: str | None = None,
        notes: Sequence[str] = (),
        block_boxes_m: np.ndarray | None = None,
    ) -> None:
        self.vertices_m = np.ascontiguousarray(vertices_m, np.float64)
        self.vertices_m.setflags(write=False)
        self._base_tris = np.ascontiguousarray(base_tris, np.int32)
        self._base_alive = np.ascontiguousarray(base_alive, np.bool_)
        self.increments = increments
        self.k = int(k)
        self.block_centres_m = np.ascontiguousarray(block_centres_m, np.float64)
        self.block_bounds_m = np.ascontiguousarray(block_bounds_m, np.float64)
        if block_boxes_m is None:  # the cells, all heights (a box around each block's triangles is tighter)
            z = self.vertices_m[:, 2]
            nb = self.block_bounds_m.shape[0]
            zlo = np.full(nb, z.min() if z.size else 0.0)
            zhi = np.full(nb, z.max() if z.size else 0.0)
            bb = self.block_bounds_m
            block_boxes_m = np.stack([bb[:, 0], bb[:, 1], zlo, bb[:, 2], bb[:, 3], zhi], axis=1)
        #: (B, 6) float64: (west, south, low, east, north, high) around each sub-block's triangles, metres
        self.block_boxes_m = np.ascontiguousarray(block_boxes_m, np.float64)
        self.source = source
        self.crs = crs
        self.notes = tuple(notes)
        self._tris = self._base_tris.copy()
        self._alive = self._base_alive.copy()
        self._scales = np.zeros(increments.n_blocks, np.int64)
        self._full_tris: np.ndarray | None = None  # the input TIN when built here (for checks)
        # (the raw increments, the future of their split arrays) when built here (see _splits_beside)
        self._splits_ahead: tuple[Any, Any] | None = None

    # -- builders ----------------------------------------------------------------------------------------
    @classmethod
    def from_points(
        cls,
        xyz_m: np.ndarray,
        *,
        sub_blocks: int | str = 4,
        base_fraction: float = 0.2,
        dedup_tol_m: float = 0.01,
        source: str = "<points>",
        crs: str | None = None,
        notes: Sequence[str] = (),
        workers: int | None = None,
        timings: dict[str, float] | None = None,
        executor: Any = None,
    ) -> DetailIncrementModel:
        """Delaunay TIN of points, split into sub-blocks, simplified to its base, with its increments.

        Parameters
        ----------
        xyz_m : (N, 3) float
            Points, world metres (x east, y north, z up).
        sub_blocks : int or "auto"
            Number of sub-blocks, a square number (4 = the paper's 2 × 2); "auto" takes about 32 k points
            a block (at least 4).
        base_fraction : float in (0, 1]
            Fraction of each sub-block's triangles in the base mesh S_0 (the paper's 20 %).
        dedup_tol_m : float
            Points sharing a ``dedup_tol_m`` xy cell are one (the lowest is kept); see
            :func:`terralod.tin.pointcloud.thin_duplicates`.
        source, crs, notes
            Provenance, kept with the model.
        workers : int, optional
            Threads triangulating the cloud's blocks and simplifying the sub-blocks in parallel (default:
            the cores, at most 8); the model is the same for any number.
        timings : dict, optional
            Filled with the seconds of each stage (dedup, delaunay, split, qem, records).
        executor : callable, optional
            ``executor(jobs, fn)`` returns ``[fn(job) for job in jobs]`` computed elsewhere, instead of the
            thread pools: the Delaunay blocks and the sub-blocks' simplification (Dask:
            :func:`terralod.tin.distributed.dask_executor`).

        Raises
        ------
        InputError
            Bad shape, NaN/inf coordinates, fewer than 3 distinct points, collinear points, bad options.
        """
        from terralod.tin.delaunay import blocks_per_side, delaunay_tin
        from terralod.tin.pointcloud import check_points, thin_duplicates

        clock = _Clock(timings)
        pts = check_points(xyz_m, source if source != "<points>" else None)
        keep = thin_duplicates(pts, dedup_tol_m)
        extra = []
        if keep.size < pts.shape[0]:
            extra.append(f"thinned {pts.shape[0] - keep.size} duplicate point(s) within {dedup_tol_m} m")
        src = None if source == "<points>" else source
        k = blocks_per_side(_auto_sub_blocks(keep.size) if sub_blocks == "auto" else sub_blocks)  # type: ignore[arg-type]
        pts = pts[keep]
        clock("dedup")
        vertices, tris, _ = delaunay_tin(pts, source=src, workers=workers, executor=executor)
        clock("delaunay")
        return cls._build(vertices, tris, k, base_fraction, source, crs, (*notes, *extra),
                          workers=workers, clock=clock, executor=executor)  # fmt: skip

    @classmethod
    def from_las(
        cls,
        path: str | os.PathLike[str] | Sequence[str | os.PathLike[str]],
        *,
        sub_blocks: int | str = 4,
        base_fraction: float = 0.2,
        dedup_tol_m: float = 0.01,
        ground_only: bool | None = None,
        units: str | float | None = None,
        workers: int | None = None,
        timings: dict[str, float] | None = None,
        executor: Any = None,
        crs: Any = None,
        bbox_deg: tuple[float, float, float, float] | None = None,
    ) -> DetailIncrementModel:
        """:meth:`from_points` of a LAS/LAZ survey's points (ground only when classified, metres): one file
        or several tiles of one survey (``path`` a sequence), read as one cloud in a canonical order, so
        tiles cut from one cloud build the same TIN as the merged file.

        See :func:`terralod.tin.pointcloud.read_las_survey` for ``ground_only``, ``units``, ``crs`` and
        ``bbox_deg`` (a part: the points inside a box in degrees, COPC files read through their octree),
        :meth:`from_points` for ``workers``, ``timings`` (plus "read") and ``executor``.
        """
        from terralod.tin.pointcloud import read_las_survey

        clock = _Clock(timings)
        paths = [path] if isinstance(path, str | os.PathLike) else list(path)
        pc = read_las_survey(paths, ground_only=ground_only, units=units, crs=crs, bbox_deg=bbox_deg)
        clock("read")
        return cls.from_points(
            pc.xyz_m,
            sub_blocks=sub_blocks,
            base_fraction=base_fraction,
            dedup_tol_m=dedup_tol_m,
            source=pc.source,
            crs=pc.crs,
            notes=pc.notes,
            workers=workers,
            timings=timings,
            executor=executor,
        )

    @classmethod
    def from_heightfield(
        cls,
        hf: Any,
        *,
        sub_blocks: int | str = 4,
        base_fraction: float = 0.2,
        workers: int | None = None,
        executor: Any = None,
    ) -> DetailIncrementModel:
        """The grid TIN of a :class:`terralod.Heightfield`'s valid samples (world metres), as a model
        (``workers``, ``executor``: see :meth:`from_points`)."""
        from terralod.tin.delaunay import blocks_per_side, grid_tin

        h, w = hf.shape
        xs, _ = hf.world_xy(np.zeros(w), np.arange(w))
        _, ys = hf.world_xy(np.arange(h), np.zeros(h))
        vertices, tris, _ = grid_tin(hf.elevation_m, hf.valid, xs, ys)
        k = blocks_per_side(_auto_sub_blocks(vertices.shape[0]) if sub_blocks == "auto" else sub_blocks)  # type: ignore[arg-type]
        return cls._build(vertices, tris, k, base_fraction, hf.source, hf.crs, tuple(getattr(hf, "notes", ())),
                          workers=workers, executor=executor)  # fmt: skip

    @classmethod
    def _build(cls, vertices, tris, k, base_fraction, source, crs, notes, *, workers=None, clock=None,
               executor=None) -> DetailIncrementModel:  # fmt: skip
        from terralod.tin.delaunay import split_sub_blocks
        from terralod.tin.qem import simplify_blocks

        clock = clock or _Clock(None)
        sb = split_sub_blocks(vertices, tris, k)
        clock("split")
        # each sub-block on its own heap, in parallel; measured errors per block with it
        # the records are replayed from the compact splits: the log's rewritten slots and costs are never
        # read, and go as each block finishes (about 150 bytes a collapse)
        log, err = simplify_blocks(vertices, tris, sb.kind, sb.tri_block, base_fraction=base_fraction,
                                   n_blocks=sb.n_blocks, workers=workers, executor=executor,
                                   keep_rewrites=False)  # fmt: skip
        clock("qem")
        # the file's split codes are computed beside the replay (kept for save; a model never saved
        # wastes one thread's second)
        hook, ahead = _splits_beside(np.asarray(vertices, np.float64), sb.n_blocks)
        inc, base_tris, base_alive = Increments.from_log(log, sb.n_blocks, vertices.shape[0], err, hook)
        del log, err
        # a box around each block's triangles: every scale's surface lies inside it
        t = np.asarray(tris, np.int64)
        lo = (
            np.repeat(vertices.min(axis=0)[None, :], sb.n_blocks, axis=0)
            if t.size
            else np.zeros((sb.n_blocks, 3))
        )
        hi = lo.copy()
        has = np.bincount(sb.tri_block, minlength=sb.n_blocks) > 0
        blo, bhi, _, _ = block_corner_bounds(np.ascontiguousarray(vertices, np.float64), t, sb.tri_block,
                                             sb.n_blocks)  # fmt: skip
        lo[has], hi[has] = blo[has], bhi[has]
        model = cls(
            vertices,
            base_tris,
            base_alive,
            inc,
            k,
            sb.centre_m,
            sb.bounds_m,
            source=str(source),
            crs=crs,
            notes=notes,
            block_boxes_m=np.concatenate([lo, hi], axis=1),
        )
        # the input TIN, kept for checks: the full scale holds the same triangles (in other slots, a
        # triple possibly rotated)
        model._full_tris = np.ascontiguousarray(tris, np.int32)
        if ahead:
            model._splits_ahead = (inc.raw if inc.raw is not None else inc, ahead[0])
        clock("records")
        return model

    # -- sizes and scales -------------------------------------------------------------------------------
    @property
    def n_blocks(self) -> int:
        return self.increments.n_blocks

    @property
    def n_slots(self) -> int:
        """Triangles of the full-resolution TIN (every slot)."""
        return int(self._base_tris.shape[0])

    @property
    def n_scales(self) -> int:
        """Global scales 0 … n_scales - 1: scale j applies the first j records in global order."""
        return self.increments.n_records + 1

    @property
    def block_n_scales(self) -> np.ndarray:
        """(B,) int64: scales of each sub-block (n_b + 1)."""
        return self.increments.block_n_records() + 1

    @property
    def block_scales(self) -> np.ndarray:
        """(B,) int64: the current scale of each sub-block (a copy)."""
        return self._scales.copy()

    def block_scales_of(self, scale: int) -> np.ndarray:
        """(B,) per-block scales of global scale ``scale``."""
        if (
            isinstance(scale, bool)
            or not isinstance(scale, int | np.integer)
            or not 0 <= scale < self.n_scales
        ):
            raise ValueError(f"Expected a scale in [0, {self.n_scales}), got {scale!r}")
        inc = self.increments
        return np.bincount(inc.record_block[inc.order[: int(scale)]], minlength=self.n_blocks).astype(
            np.int64
        )

    def set_block_scales(self, scales: Sequence[int] | np.ndarray) -> None:
        """Move each sub-block to its scale by applying (or reverting) its increments (eq. 2)."""
        s = np.asarray(scales, np.int64)
        nmax = self.increments.block_n_records()
        if s.shape != (self.n_blocks,):
            raise ValueError(f"Expected {self.n_blocks} per-block scales, got shape {s.shape}")
        if (s < 0).any() or (s > nmax).any():
            raise ValueError(
                f"Expected per-block scales in [0, n_b], n_b = {nmax.tolist()}, got {s.tolist()}"
            )
        inc = self.increments
        for b in np.flatnonzero(s != self._scales):
            cur, tgt, base = int(self._scales[b]), int(s[b]), int(inc.block_ptr[b])
            if tgt > cur:
                refine_records(
                    self._tris,
                    self._alive,
                    base + cur,
                    base + tgt,
                    inc.del_ptr,
                    inc.del_slot,
                    inc.del_tri,
                    inc.rep_ptr,
                    inc.rep_slot,
                    inc.rep_old,
                )
            else:
                coarsen_records(
                    self._tris,
                    self._alive,
                    base + tgt,
                    base + cur,
                    inc.del_ptr,
                    inc.del_slot,
                    inc.rep_ptr,
                    inc.rep_slot,
                    inc.rep_new,
                )
            self._scales[b] = tgt

    def triangles(self) -> np.ndarray:
        """(K, 3) int32: the live triangles of the current state (counter-clockwise, indices into
        :attr:`vertices_m`), in slot order."""
        return self._tris[self._alive]

    def _mesh(self, compact: bool) -> tuple[np.ndarray, np.ndarray]:
        t = self.triangles()
        if not compact:
            return self.vertices_m, t
        used, inv = np.unique(t, return_inverse=True)
        return self.vertices_m[used], inv.reshape(t.shape).astype(np.int32)

    def mesh_at(
        self, scale: int | Sequence[int] | np.ndarray, *, compact: bool = False
    ) -> tuple[np.ndarray, np.ndarray]:
        """The TIN at a scale.

        Parameters
        ----------
        scale : int or (B,) ints
            A global scale in [0, n_scales) (0: every sub-block at its base; n_scales - 1: the full
            TIN), or one scale per sub-block.
        compact : bool
            False (default): all vertices, triangles index them (unused vertices stay, the paper's
            shared point array); True: only the used vertices, renumbered.

        Returns
        -------
        vertices (N, 3) float64 world metres, triangles (K, 3) int32 counter-clockwise.
        """
        if np.ndim(scale) == 0:
            self.set_block_scales(self.block_scales_of(scale))  # type: ignore[arg-type]
        else:
            self.set_block_scales(scale)  # type: ignore[arg-type]
        return self._mesh(compact)

    def _camera(
        self,
        eye_m: Sequence[float] | np.ndarray,
        fov_y_deg: float,
        height_px: float,
        threshold_px: float,
        error: str,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Checked camera: (eye (3,), distance of every sub-block (B,), metres, for ``error``'s rule)."""
        eye = np.asarray(eye_m, np.float64)
        if eye.shape != (3,) or not np.isfinite(eye).all():
            raise ValueError(f"Expected a finite eye position (x, y, z) in metres, got {eye_m!r}")
        if not (0.0 < fov_y_deg < 180.0):
            raise ValueError(f"Expected fov_y_deg in (0, 180) degrees, got {fov_y_deg}")
        if not (height_px > 0 and threshold_px > 0):
            raise ValueError(f"Expected positive height_px and threshold_px, got {height_px}, {threshold_px}")
        if error == "measured":
            return eye, box_distance_m(self.block_boxes_m, eye)
        if error == "mmqe":
            return eye, np.linalg.norm(self.block_centres_m - eye[None, :], axis=1)
        raise ValueError(f"Expected error 'measured' or 'mmqe', got {error!r}")

    def scales_for_camera(
        self,
        eye_m: Sequence[float] | np.ndarray,
        fov_y_deg: float,
        height_px: float,
        threshold_px: float = 2.0,
        *,
        error: str = "measured",
    ) -> np.ndarray:
        """(B,) per-sub-block scales for a perspective camera: the coarsest scale whose error projects to at
        most ``threshold_px`` pixels. A pure query: the state is not touched.

        Parameters
        ----------
        eye_m : (3,) world metres. fov_y_deg : vertical field of view, degrees, in (0, 180).
        height_px : viewport height, pixels. threshold_px : N, pixels (the paper's 2).
        error : "measured" (default) or "mmqe"
            "measured": the scale's measured max vertical error (metres, an upper bound over the input
            points) at the nearest point of the sub-block's box, so no point of the drawn surface is
            more than N pixels off. "mmqe": the paper's SVO rule (§2.3.2), a segment of sqrt(monotone
            MMQE) metres at the sub-block's centre; a mean error, so it keeps far coarser scales.
        """
        _, d = self._camera(eye_m, fov_y_deg, height_px, threshold_px, error)
        inc = self.increments
        if error == "measured":
            return select_scales_measured(inc.error_m, inc.mmqe_ptr, d, math.radians(fov_y_deg), float(height_px),
                                          float(threshold_px))  # fmt: skip
        return select_scales(inc.mmqe_m2, inc.mmqe_ptr, self.block_centres_m, np.asarray(eye_m, np.float64),
                             math.radians(fov_y_deg), float(height_px), float(threshold_px))  # fmt: skip

    def projected_error_px(
        self,
        eye_m: Sequence[float] | np.ndarray,
        fov_y_deg: float,
        height_px: float,
        scales: np.ndarray | None = None,
        *,
        error: str = "measured",
    ) -> np.ndarray:
        """(B,) each sub-block's error at ``scales`` (default: its current scale) projected to the screen,
        pixels, by the rule of ``error`` (see :meth:`scales_for_camera`)."""
        _, d = self._camera(eye_m, fov_y_deg, height_px, 1.0, error)
        inc = self.increments
        s = self._scales if scales is None else np.asarray(scales, np.int64)
        if error == "measured":
            return projected_px(
                inc.error_m[inc.mmqe_ptr[:-1] + s], d, math.radians(fov_y_deg), float(height_px)
            )
        return projected_px(np.sqrt(inc.mmqe_m2[inc.mmqe_ptr[:-1] + s]), d, math.radians(fov_y_deg),
                            float(height_px))  # fmt: skip

    def mesh_for_camera(
        self,
        eye_m: Sequence[float] | np.ndarray,
        fov_y_deg: float,
        height_px: float,
        threshold_px: float = 2.0,
        *,
        compact: bool = False,
        error: str = "measured",
    ) -> tuple[np.ndarray, np.ndarray]:
        """The TIN with each sub-block at its scale for this camera (see :meth:`scales_for_camera`)."""
        self.set_block_scales(self.scales_for_camera(eye_m, fov_y_deg, height_px, threshold_px, error=error))
        return self._mesh(compact)

    def error_m(self, block: int) -> np.ndarray:
        """Measured max vertical error of sub-block ``block``'s scales S_0 … S_{n_b}, metres (monotone, an
        upper bound of the distance from every input point of the block to the scale's surface)."""
        return self.increments.error_of(block).copy()

    def mmqe_m2(self, block: int) -> np.ndarray:
        """Monotone MMQE of sub-block ``block``'s scales S_0 … S_{n_b}, m²."""
        return self.increments.mmqe_of(block).copy()

    def records(self, block: int) -> Iterator[DeltaT]:
        """ΔT_0, ΔT_1, … of a sub-block (Ai et al. (2019) table 1)."""
        return self.increments.records(block)

    # -- compression -------------------------------------------------------------------------------------
    def compressed(self, k: int) -> DetailIncrementModel:
        """A model whose records each merge k consecutive records (Ai et al. (2019) §2.2.2), starting at the base.

        Its sub-block scales are this model's S_0, S_k, S_2k, …, S_{n_b}.
        """
        m = DetailIncrementModel(
            self.vertices_m,
            self._base_tris,
            self._base_alive,
            self.increments.merged(k),
            self.k,
            self.block_centres_m,
            self.block_bounds_m,
            source=self.source,
            crs=self.crs,
            notes=self.notes,
            block_boxes_m=self.block_boxes_m,
        )
        m._full_tris = self._full_tris
        return m

    # -- files -------------------------------------------------------------------------------------------
    def _payload(self) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
        """The file's metadata and named arrays, in the file's order (what :meth:`save` writes)."""
        meta, head, splits, tail = self._payload_parts()
        return meta, {**head, **splits(), **tail}

    def _payload_parts(
        self,
    ) -> tuple[
        dict[str, Any], dict[str, np.ndarray], Callable[[], dict[str, np.ndarray]], dict[str, np.ndarray]
    ]:
        """(meta, the arrays before the splits, a function computing the splits' arrays, the arrays after):
        the splits' codes are one sequential pass (:func:`terralod.kernels.tincodec.split_codes`), which
        :meth:`save` runs beside the compression of the arrays before them."""
        inc = self.increments
        raw = inc.raw if inc.raw is not None else inc
        if raw.rec_u is None or raw.rec_v is None or raw.mmqe_code is None or raw.error_code is None:
            raise InputError("these records carry no vertex splits to store (build the model, then save it)")
        n_base = int(self._base_alive.sum())
        nb = raw.n_blocks
        code = raw.mmqe_code
        first = code[raw.mmqe_ptr[:-1]]
        # each block's codes fall from S_0 to S_{n_b}: store the first and the drops (mostly 0, 1 byte)
        drop = -np.diff(code)
        drop = np.delete(drop, raw.mmqe_ptr[1:-1] - 1)
        ecode = raw.error_code
        edrop = np.delete(-np.diff(ecode), raw.mmqe_ptr[1:-1] - 1)
        # the splits as symbols predicted from geometry (terralod.kernels.tincodec)
        label = _vertex_labels(self.vertices_m.shape[0], nb, raw.rec_u, raw.block_ptr)
        # a vertex out of the base is mostly inserted by the sub-block whose cell holds it: 0, else label + 1
        out = np.ones(label.size, np.bool_)
        out[self._base_tris[:n_base].ravel()] = False
        cell = _block_cells(self.vertices_m, self.k)[out]
        label_escape = np.where(label[out] == cell, 0, label[out] + 1)
        base = self._base_tris[:n_base]
        pre = self._splits_ahead
        if pre is not None and pre[0] is raw:  # coded beside the build's replay (same inputs)
            splits = pre[1].result
        else:
            args = _split_args(self.vertices_m, label, nb, base, raw.block_ptr, raw.rec_u, raw.rec_v,
                               raw.del_tri[0::2, 2], np.diff(raw.rep_ptr))  # fmt: skip

            def splits() -> dict[str, np.ndarray]:
                return _split_arrays(*args)

        meta = {
            "format": "terralod detail-increment model (Ai et al., 2019)",
            "k": self.k,
            "n_slots": self.n_slots,
            "step": inc.step,
            "source": self.source,
            "crs": self.crs,
            "notes": list(self.notes),
            "units": "metres; x east, y north, z up",
        }
        head = {
            "vertices_m": self.vertices_m,
            "base_rows": encode_mesh_rows(base),
            "block_centres_m": self.block_centres_m,
            "block_bounds_m": self.block_bounds_m,
            "block_boxes_m": self.block_boxes_m,
            "block_records": np.diff(raw.block_ptr),
            "vertex_block_escape": label_escape,
        }
        tail = {
            "mmqe_first": first,
            "mmqe_drop": drop,
            "error_first": ecode[raw.mmqe_ptr[:-1]],
            "error_drop": edrop,
        }
        return meta, head, splits, tail

    def save(self, path: str | os.PathLike[str], *, compress: bool = True, workers: int | None = None) -> int:
        """Write the model (base mesh + increments + MMQE) to one checksummed file; returns its size, bytes
        (``workers`` threads compress it; the bytes are the same for any number). The splits are coded on
        a thread of their own while the arrays before them (the vertices, most of the file) are compressed."""
        from concurrent.futures import ThreadPoolExecutor

        meta, head, splits, tail = self._payload_parts()
        with ThreadPoolExecutor(1) as pool:
            coded = pool.submit(splits)  # split_codes releases the GIL

            def arrays() -> Iterator[tuple[str, np.ndarray]]:
                yield from head.items()
                yield from coded.result().items()
                yield from tail.items()

            return write_container_stream(path, meta, len(head) + 6 + len(tail), arrays(), compress=compress,
                                          workers=workers)  # fmt: skip

    def export_text(self, path: str | os.PathLike[str]) -> None:
        """Write the increments in the paper's text scheme (:func:`write_text`)."""
        write_text(self.increments, path)

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> DetailIncrementModel:
        """Read a file written by :meth:`save`; the model starts at its base scale.

        Raises
        ------
        InputNotFoundError : no such file.
        CorruptStoreError : not such a file, older or newer format, checksum mismatch, or inconsistent content.
        """
        src = str(path)
        meta, a = read_container(path)
        try:
            k = int(meta["k"])
            n_slots = int(meta["n_slots"])
            step = int(meta.get("step", 1))
            v = a["vertices_m"]
            nb = k * k
            br = a["block_records"].astype(np.int64)
            n_rec = int(br.sum()) if br.size else 0
            rows = a["base_rows"]
            lab_esc = a["vertex_block_escape"].astype(np.int64)
            n_esc = int((a["split_v"] == V_ESCAPE).sum())
            per_rec = ("split_u", "split_v", "split_j", "split_after", "mmqe_drop", "error_drop")
            checks = [
                (v.ndim == 2 and v.shape[1] == 3, "vertices"),
                (br.shape == (nb,) and (br >= 0).all(), "block count"),
                (all(a[n].shape == (n_rec,) for n in per_rec), "record count"),
                (rows.ndim == 2 and rows.shape[1] == 3, "base triangles"),
                (n_slots == rows.shape[0] + 2 * n_rec, "triangle count"),
                (lab_esc.ndim == 1 and ((lab_esc >= 0) & (lab_esc <= nb + 1)).all(), "vertex blocks"),
                (a["escape_v"].shape == a["escape_x1"].shape == (n_esc,), "escapes"),
                (a["mmqe_first"].shape == (nb,) and (a["mmqe_drop"] >= 0).all(), "MMQE"),
                (a["error_first"].shape == (nb,) and (a["error_drop"] >= 0).all(), "measured error"),
                (step >= 1, "merge factor"),
                (a["block_boxes_m"].shape == (nb, 6), "block boxes"),
            ]
        except (KeyError, ValueError, TypeError) as exc:
            raise CorruptStoreError(f"incomplete detail-increment file ({exc})", src) from exc
        for ok, what in checks:
            if not ok:
                raise CorruptStoreError(f"inconsistent detail-increment file: {what}", src)
        # MMQE and error codes of every block's scales S_0 … S_{n_b}: the first, then the running drops
        bptr = np.concatenate([[0], np.cumsum(br)])

        def codes(first: np.ndarray, drop: np.ndarray) -> np.ndarray:
            code = np.empty(n_rec + nb, np.int64)
            drops = drop.astype(np.int64)
            for b in range(nb):
                seg = drops[bptr[b] : bptr[b + 1]]
                code[bptr[b] + b] = int(first[b])
                code[bptr[b] + b + 1 : bptr[b + 1] + b + 1] = int(first[b]) - np.cumsum(seg)
            return code

        # the splits from their symbols, replaying them over the base (terralod.kernels.tincodec)
        base_tri = decode_mesh_rows(rows)
        if base_tri.size and (base_tri.min() < 0 or base_tri.max() >= v.shape[0]):
            raise CorruptStoreError(
                "inconsistent detail-increment records: base triangles do not fit the mesh", src
            )
        out = np.ones(v.shape[0], np.bool_)
        out[base_tri.ravel()] = False
        label = np.full(v.shape[0], nb, np.int64)
        if lab_esc.size != int(out.sum()):
            raise CorruptStoreError("inconsistent detail-increment file: vertex blocks", src)
        label[out] = np.where(lab_esc == 0, _block_cells(v, k)[out], lab_esc - 1)
        if not np.array_equal(np.bincount(label, minlength=nb + 1)[:nb], br):
            raise CorruptStoreError("inconsistent detail-increment file: vertex blocks", src)
        sym_u, sym_v, sym_j, after = (
            a[n].astype(np.int64) for n in ("split_u", "split_v", "split_j", "split_after")
        )
        rec_u, rec_v, rec_x, rec_m = (np.zeros(n_rec, np.int64) for _ in range(4))
        vpos, vat, lo, hi = _insert_order(label, nb)
        # the decoder also writes what each split does to the mesh (no second replay of the same splits)
        del_tri = np.zeros((2 * n_rec, 3), np.int32)
        rep_ptr = np.zeros(n_rec + 1, np.int64)
        status, _, rep_slot, rep_old, rep_new = split_codes(
            False, _grid_xy(v), v[:, 2].copy(), label, base_tri.astype(np.int32), bptr, vpos, vat, lo, hi, rec_u,
            rec_v, rec_x, rec_m, sym_u, sym_v, sym_j, after, a["escape_v"].astype(np.int64),
            a["escape_x1"].astype(np.int64), True, del_tri, rep_ptr,
        )  # fmt: skip
        if status != 0:
            where = ("more triangle slots than a model codes" if status == -2 else "base triangles" if status < 0
                     else f"record {max(status, 1) - 1}")  # fmt: skip
            raise CorruptStoreError(
                f"inconsistent detail-increment records: {where} does not fit the mesh", src
            )
        inc, base_tris, base_alive = Increments.from_compact(
            v.shape[0],
            base_tri,
            br,
            rec_u,
            rec_v,
            rec_x,
            rec_m,
            codes(a["mmqe_first"], a["mmqe_drop"]),
            codes(a["error_first"], a["error_drop"]),
            source=src,
            moves=(del_tri, rep_ptr, *(r[: rep_ptr[-1]].copy() for r in (rep_slot, rep_old, rep_new))),
        )
        if step > 1:
            inc = inc.merged(step)
        m = cls(
            v,
            base_tris,
            base_alive,
            inc,
            k,
            a["block_centres_m"],
            a["block_bounds_m"],
            source=str(meta.get("source", src)),
            crs=meta.get("crs"),
            notes=meta.get("notes", ()),
            block_boxes_m=a["block_boxes_m"],
        )
        return m
