"""Runtime of a detail-increment TIN (Ai et al., 2019): per-frame sub-block scales from the SVO rule, meshes out.

Paper: ``../shared/papers/003_2a2cfcda929de24c.txt`` §2.3 (reconstruction of any scale by applying or
reverting ΔT records; each sub-block takes the coarsest scale whose error projects to at most N pixels,
N = 2 px; sub-blocks change scale independently). By default the error is the scale's measured max
vertical error at the nearest point of the sub-block's box (the paper's sqrt(MMQE) at the centre, a mean,
never refines a large terrain: ``error="mmqe"`` keeps it). The scale query is
:meth:`terralod.tin.DetailIncrementModel.scales_for_camera`; this module keeps a model at the scales of
the last camera, moves only the sub-blocks whose scale changed, and hands a renderer one mesh per
sub-block (a pure producer: it never imports the GPU backend).

Deviations, and why:

- **Normals from the whole current TIN**, then cut per sub-block, so shading is continuous across the
  seams (a sub-block's own triangles alone would give its seam vertices one-sided normals). The
  per-vertex sums are updated by the changed sub-blocks only (subtract the old cut, add the new).
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

__all__ = ["TinEngine", "TinFrame", "TinRuntime", "slot_blocks"]


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
    max_svo_px : the largest projected error over the sub-blocks at their scales, pixels (the measured
        error at the nearest point of each sub-block's box, or the sqrt(MMQE) segment at its centre, by the
        runtime's ``error`` rule)
    """

    scales: np.ndarray
    changed: np.ndarray
    triangles: int
    select_ms: float
    apply_ms: float
    mesh_ms: float
    records_applied: int
    max_svo_px: float = 0.0
    _meshes: list[tuple] = field(default_factory=list, repr=False)

    @property
    def stats(self) -> dict[str, float]:
        """The tile engine's statistics keys (for HUDs and tables): sub-blocks count as tiles, the SVO
        length as the screen error, records + meshes as the stitch step."""
        return {"tiles": int(self.scales.size), "triangles": self.triangles, "max_screen_error_px": self.max_svo_px,
                "select_ms": self.select_ms, "stitch_ms": self.apply_ms + self.mesh_ms,
                "records_applied": self.records_applied, "changed": int(self.changed.size),
                "sub_blocks": int(self.scales.size), "apply_ms": self.apply_ms, "mesh_ms": self.mesh_ms}  # fmt: skip

    @property
    def frame_ms(self) -> float:
        return self.select_ms + self.apply_ms + self.mesh_ms

    def meshes(self) -> Iterator[tuple]:
        """(code, vertices (n, 3) float64 metres, triangles (m, 3) int32, normals (n, 3) float32) per
        non-empty sub-block; ``code = (scale band 0..7, block, 0)`` (the band colours "lod" mode)."""
        return iter(self._meshes)


class TinRuntime:
    """A detail-increment model kept at the SVO scales of the latest camera.

    Per frame: the SVO query, the records of the sub-blocks whose scale changed (eq. 2), a new mesh for
    each of those sub-blocks, and fresh normals for them and for the sub-blocks sharing a vertex with
    them. Normals come from per-vertex sums of face normals kept for the whole TIN and updated by the
    changed sub-blocks only, so a frame costs what changed, not the size of the TIN.

    Parameters
    ----------
    model : terralod.tin.DetailIncrementModel (moved in place; start it anywhere)
    threshold_px : N, the largest projected error of a sub-block, pixels
    error : "measured" (default: the scale's measured max vertical error) or "mmqe" (the paper's SVO
        segment, sqrt(MMQE)); see :meth:`terralod.tin.DetailIncrementModel.scales_for_camera`
    """

    def __init__(self, model: Any, *, threshold_px: float = 2.0, error: str = "measured") -> None:
        if not threshold_px > 0:
            raise ValueError(f"Expected threshold_px > 0, got {threshold_px}")
        if error not in ("measured", "mmqe"):
            raise ValueError(f"Expected error 'measured' or 'mmqe', got {error!r}")
        self.model = model
        self.threshold_px = float(threshold_px)
        self.error = error
        self.slot_block = slot_blocks(model)
        nb = model.n_blocks
        order = np.argsort(self.slot_block, kind="stable")
        ptr = np.searchsorted(self.slot_block[order], np.arange(nb + 1))
        self._block_slots = [order[ptr[b] : ptr[b + 1]] for b in range(nb)]
        nv = model.vertices_m.shape[0]
        self._nsum = np.zeros((nv, 3), np.float64)  # Σ area-weighted face normals of the cut triangles
        self._mask = np.zeros(nv, np.int64) if nb <= 63 else None  # bit b: sub-block b uses the vertex
        self._cut: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}  # b -> (used, local tris, sums)
        self._cache: dict[int, tuple] = {}
        self._first = True

    def update(self, camera: Any) -> TinFrame:
        """Move every sub-block to its SVO scale for ``camera`` (a :class:`terralod.runtime.Camera`)."""
        m = self.model
        t0 = time.perf_counter()
        scales = m.scales_for_camera(
            camera.eye, camera.fov_y_deg, camera.height_px, self.threshold_px, error=self.error
        )
        t1 = time.perf_counter()
        before = m.block_scales
        m.set_block_scales(scales)
        changed = np.arange(m.n_blocks) if self._first else np.flatnonzero(scales != before)
        t2 = time.perf_counter()
        if changed.size:
            self._rebuild(changed)
        t3 = time.perf_counter()
        self._first = False
        svo = m.projected_error_px(camera.eye, camera.fov_y_deg, camera.height_px, scales, error=self.error)
        return TinFrame(
            scales, changed, int(m._alive.sum()), (t1 - t0) * 1e3, (t2 - t1) * 1e3, (t3 - t2) * 1e3,
            int(np.abs(scales - before).sum()), float(svo.max()) if svo.size else 0.0,
            [self._cache[b] for b in sorted(self._cache)],
        )  # fmt: skip

    def _rebuild(self, changed: np.ndarray) -> None:
        m = self.model
        v = m.vertices_m
        touched = 0
        for b in changed.tolist():
            bit = np.int64(1) << np.int64(b) if self._mask is not None else 0
            old = self._cut.pop(b, None)
            if old is not None:
                self._nsum[old[0]] -= old[2]
                if self._mask is not None:
                    touched |= int(np.bitwise_or.reduce(self._mask[old[0]])) if old[0].size else 0
                    self._mask[old[0]] &= ~bit
            slots = self._block_slots[b]
            t = m._tris[slots[m._alive[slots]]].astype(np.int64)
            if t.shape[0] == 0:
                self._cache.pop(b, None)
                continue
            used, tloc = np.unique(t, return_inverse=True)
            tloc = tloc.reshape(t.shape)
            fn = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
            flat = tloc.ravel()
            sums = np.stack([np.bincount(flat, weights=np.repeat(fn[:, a], 3), minlength=used.size)
                             for a in range(3)], axis=1)  # fmt: skip
            self._nsum[used] += sums
            self._cut[b] = (used, tloc.astype(np.int32), sums)
            if self._mask is not None:
                self._mask[used] |= bit
                touched |= int(np.bitwise_or.reduce(self._mask[used]))
        # Sub-blocks sharing a vertex with a changed one get fresh normals too (seams stay continuous).
        if self._mask is None:
            refresh = list(self._cut)
        else:
            refresh = [b for b in self._cut if (touched >> b) & 1 or b in set(changed.tolist())]
        nmax = np.maximum(m.increments.block_n_records(), 1)
        scales = m.block_scales
        for b in refresh:
            used, tloc, _ = self._cut[b]
            n = self._nsum[used]
            ln = np.linalg.norm(n, axis=1, keepdims=True)
            n = np.where(ln > 0, n / np.maximum(ln, 1e-300), np.array([0.0, 0.0, 1.0])).astype(np.float32)
            band = int(round(7 * scales[b] / nmax[b]))
            self._cache[b] = ((band, b, 0), v[used], tloc, n)


class TinEngine:
    """The tile :class:`terralod.runtime.Engine`'s interface (``request`` / ``latest`` / ``update`` /
    ``close``, ``threshold_px``) over a :class:`TinRuntime`, so the window viewer drives a TIN. Updates run
    on the caller's thread: a TIN frame costs milliseconds (``benchmarks/results/tin_zoom.md``)."""

    def __init__(self, model: Any, *, threshold_px: float = 2.0, error: str = "measured") -> None:
        self.runtime = TinRuntime(model, threshold_px=threshold_px, error=error)
        self._camera: Any = None

    @property
    def threshold_px(self) -> float:
        return self.runtime.threshold_px

    @threshold_px.setter
    def threshold_px(self, px: float) -> None:
        if not px > 0:
            raise ValueError(f"Expected threshold_px > 0, got {px}")
        self.runtime.threshold_px = float(px)

    def update(self, camera: Any) -> TinFrame:
        return self.runtime.update(camera)

    def request(self, camera: Any) -> None:
        self._camera = camera

    def latest(self) -> TinFrame | None:
        """The frame of the last requested camera (None when nothing was requested since)."""
        cam, self._camera = self._camera, None
        return None if cam is None else self.runtime.update(cam)

    def close(self) -> None:
        self._camera = None
