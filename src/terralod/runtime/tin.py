"""Runtime of a detail-increment TIN (paper 003): per-frame sub-block scales from the SVO rule, meshes out.

Paper: ``../shared/papers/003_2a2cfcda929de24c.txt`` §2.3 (reconstruction of any scale by applying or
reverting ΔT records; each sub-block takes the coarsest scale whose sqrt(MMQE) segment at its centre
projects to at most N pixels, N = 2 px; sub-blocks change scale independently). The scale query is
:meth:`terralod.tin.DetailIncrementModel.scales_for_camera`; this module keeps a model at the scales of
the last camera, moves only the sub-blocks whose scale changed, and hands a renderer one mesh per
sub-block (a pure producer: it never imports the GPU backend).

Deviations, and why:

- **Normals from the whole current TIN**, then cut per sub-block, so shading is continuous across the
  seams (a sub-block's own triangles alone would give its seam vertices one-sided normals).
- **Sub-block of a triangle slot.** The model does not store it: a slot touched by a record belongs to
  that record's sub-block (collapses never cross a seam); an untouched slot keeps its full-resolution
  triangle, whose centroid cell is how :func:`terralod.tin.delaunay.split_sub_blocks` assigned it.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = ["TinFrame", "TinRuntime", "slot_blocks"]


def slot_blocks(model: Any) -> np.ndarray:
    """(n_slots,) int32: the sub-block of every triangle slot of ``model`` (see the module docstring)."""
    inc = model.increments
    k = model.k
    v = model.vertices_m
    lo = v[:, :2].min(axis=0)
    hi = v[:, :2].max(axis=0)
    span = np.maximum(hi - lo, np.finfo(np.float64).tiny)
    tris = model._base_tris  # untouched slots hold their full-resolution triangle here
    cen = v[tris.astype(np.int64)][:, :, :2].mean(axis=1)
    col = np.clip(((cen[:, 0] - lo[0]) / span[0] * k).astype(np.int64), 0, k - 1)
    row = np.clip(((hi[1] - cen[:, 1]) / span[1] * k).astype(np.int64), 0, k - 1)
    out = (row * k + col).astype(np.int32)
    rec_block = inc.record_block
    out[inc.del_slot] = np.repeat(rec_block, np.diff(inc.del_ptr))
    out[inc.rep_slot] = np.repeat(rec_block, np.diff(inc.rep_ptr))
    return out


def _vertex_normals(v: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(N, 3) float32 area-weighted unit normals of the vertices used by triangles ``t`` (z up)."""
    ti = t.astype(np.int64)
    fn = np.cross(v[ti[:, 1]] - v[ti[:, 0]], v[ti[:, 2]] - v[ti[:, 0]])
    nv = v.shape[0]
    flat = ti.ravel()
    n = np.stack([np.bincount(flat, weights=np.repeat(fn[:, a], 3), minlength=nv) for a in range(3)], axis=1)
    ln = np.linalg.norm(n, axis=1, keepdims=True)
    n = np.where(ln > 0, n / np.maximum(ln, 1e-300), np.array([0.0, 0.0, 1.0]))
    return n.astype(np.float32)


@dataclass
class TinFrame:
    """What one camera update produced.

    Attributes
    ----------
    scales : (B,) int64, each sub-block's scale (0 = base … n_b = full resolution)
    changed : (C,) int64, sub-blocks whose scale changed this frame
    triangles : live triangles drawn
    select_ms, apply_ms, mesh_ms : time of the SVO query, of applying/reverting records, of cutting meshes
    records_applied : ΔT records applied or reverted this frame
    """

    scales: np.ndarray
    changed: np.ndarray
    triangles: int
    select_ms: float
    apply_ms: float
    mesh_ms: float
    records_applied: int
    _meshes: list[tuple] = field(default_factory=list, repr=False)

    @property
    def frame_ms(self) -> float:
        return self.select_ms + self.apply_ms + self.mesh_ms

    def meshes(self) -> Iterator[tuple]:
        """(code, vertices (n, 3) float64 metres, triangles (m, 3) int32, normals (n, 3) float32) per
        non-empty sub-block; ``code = (scale band 0..7, block, 0)`` (the band colours "lod" mode)."""
        return iter(self._meshes)


class TinRuntime:
    """A detail-increment model kept at the SVO scales of the latest camera.

    Parameters
    ----------
    model : terralod.tin.DetailIncrementModel (moved in place; start it anywhere)
    threshold_px : N, the largest projected length of a sub-block's sqrt(MMQE) segment, pixels
    """

    def __init__(self, model: Any, *, threshold_px: float = 2.0) -> None:
        if not threshold_px > 0:
            raise ValueError(f"Expected threshold_px > 0, got {threshold_px}")
        self.model = model
        self.threshold_px = float(threshold_px)
        self.slot_block = slot_blocks(model)
        self._cache: dict[int, tuple] = {}
        self._normals: np.ndarray | None = None
        self._first = True

    def update(self, camera: Any) -> TinFrame:
        """Move every sub-block to its SVO scale for ``camera`` (a :class:`terralod.runtime.Camera`)."""
        m = self.model
        t0 = time.perf_counter()
        scales = m.scales_for_camera(camera.eye, camera.fov_y_deg, camera.height_px, self.threshold_px)
        t1 = time.perf_counter()
        before = m.block_scales
        changed = np.flatnonzero(scales != before) if not self._first else np.arange(m.n_blocks)
        m.set_block_scales(scales)
        t2 = time.perf_counter()
        if changed.size:
            self._rebuild()
        t3 = time.perf_counter()
        self._first = False
        return TinFrame(
            scales, changed, int(m._alive.sum()), (t1 - t0) * 1e3, (t2 - t1) * 1e3, (t3 - t2) * 1e3,
            int(np.abs(scales - before).sum()), [self._cache[b] for b in sorted(self._cache)],
        )  # fmt: skip

    def _rebuild(self) -> None:
        m = self.model
        v = m.vertices_m
        live = np.flatnonzero(m._alive)
        tris = m._tris[live]
        normals = _vertex_normals(v, tris)  # whole TIN: continuous across seams
        blk = self.slot_block[live]
        nmax = np.maximum(m.increments.block_n_records(), 1)
        scales = m.block_scales
        # Seam vertices are shared, so a scale change next door can change a block's normals: redo all
        # blocks when any changed (the cut is cheap next to the records and the upload skips unchanged).
        order = np.argsort(blk, kind="stable")
        ptr = np.searchsorted(blk[order], np.arange(m.n_blocks + 1))
        remap = np.full(v.shape[0], -1, np.int64)
        for b in range(m.n_blocks):
            t = tris[order[ptr[b] : ptr[b + 1]]]
            if t.shape[0] == 0:
                self._cache.pop(b, None)
                continue
            used = np.flatnonzero(np.bincount(t.ravel(), minlength=v.shape[0]))
            remap[used] = np.arange(used.size)
            band = int(round(7 * scales[b] / nmax[b]))
            self._cache[b] = ((band, b, 0), v[used], remap[t].astype(np.int32), normals[used])
