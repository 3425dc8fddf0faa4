"""QEM edge-collapse simplification of a TIN down to its most simplified version (the base mesh).

Paper: ``../shared/papers/003_2a2cfcda929de24c.txt`` §2.1: Garland–Heckbert quadrics (eq. 3–6), the
collapsed vertex placed at the endpoint with the smaller quadric error, collapses in increasing cost,
never on sub-block boundaries, down to 20 % of the triangles; the MMQE (mean of the vertices' minimum
quadric errors) recorded after each collapse, per sub-block. The kernel is
:func:`terralod.kernels.qem.qem_simplify` (numba; its docstring has the collapse rules).

Deviations, and why:

- **Half-edge collapses.** "Endpoint placement" is read as: the edge (u, v) collapses onto v, the
  endpoint where the merged quadric Q_u + Q_v is smaller, and u disappears. Only FREE vertices (inside one
  sub-block and inside the TIN) may disappear; a LOCKED vertex (TIN outline, sub-block seam) may still be
  the endpoint kept. So the seams and the outline never change and each collapse touches the triangles of
  one sub-block only, which is what makes the sub-blocks' scales independent.
- **Area-weighted quadrics, normalised MMQE.** Planes are weighted by triangle area (Garland–Heckbert's
  recommendation; the paper's eq. 3 is unweighted) so big flat triangles cost what they cover. The heap
  orders by the weighted cost (m⁴); the MMQE uses the cost divided by the summed area of the planes, an
  area-weighted mean squared distance (m²), so that sqrt(MMQE) is the length in metres §2.3.2 projects
  to the screen. The paper's unweighted sum grows with the number of merged planes instead.
- **One heap for all sub-blocks**, each sub-block stopping at its own target (``base_fraction`` of its
  triangles): the paper runs the sub-blocks in parallel threads; one heap gives the same per-block
  sequences (collapses in different blocks commute) with a global order that ``mesh_at(scale)`` uses.
- **A vertical term in the cost** (``vertical_weight``, default :data:`VERTICAL_WEIGHT`; 0 is the
  paper's cost). The quadric measures the distance to the planes of the triangles around u, not to the
  points removed before, so QEM alone let the surface drift far from them: on the 513² Puget Sound crop
  its max vertical error at 20 % of the triangles was 87 m against 42 m for pyfqmr. The term adds the
  squared largest vertical distance from u and the removed vertices under star(u) to the surface after
  the collapse (the error a user sees), weighted by u's quadric area; placement stays at an endpoint.
  Plane-only variants (unweighted or vertical-distance planes, the kept endpoint's quadric dropped or
  halved, costs normalised by area, the distance of u alone) gave no consistent gain and were dropped
  (figures in the commit "QEM cost variants measured beside the peers").
- **Validity.** Collapses that break the link condition or turn a rewritten triangle clockwise (or into a
  near-zero-area sliver) in xy are rejected; for a TIN a clockwise triangle is a flipped normal.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from terralod.errors import InputError
from terralod.kernels.qem import FREE, LOCKED, collapse_vertical_errors, qem_simplify

__all__ = ["CollapseLog", "measured_errors", "simplify", "simplify_mesh"]

#: Default orientation tolerance of rewritten triangles: twice the area must exceed this times the sum
#: of the squared xy edge lengths (an equilateral triangle has ~0.58; 1e-9 only rejects slivers whose
#: orientation float rounding could decide).
SHAPE_EPS = 1e-9

#: Default weight of the vertical term (cost + w · W_u · g², g the largest vertical distance from u and the
#: removed vertices its star carries to the surface after the collapse). 10 on the 513² Puget Sound crop
#: (benchmarks/results/tin.md): max vertical error 25.4 m at 20 % of the triangles against 87.3 m with the
#: quadric alone; 3 and 30 give about the same (28.4 and 23.5 m), at 2.5-4x the time of the quadric alone.
VERTICAL_WEIGHT = 10.0


@dataclass(frozen=True)
class CollapseLog:
    """Every collapse performed, in order, and the base mesh it left.

    Attributes
    ----------
    u, v : (C,) int32
        Collapse i removed vertex ``u[i]`` onto vertex ``v[i]``.
    block : (C,) int32
        Sub-block of collapse i.
    mmqe_m2 : (C,) float64
        MMQE of that sub-block just after collapse i, m².
    cost : (C,) float64
        Area-weighted quadric cost of collapse i, m⁴.
    mmqe0_m2 : (B,) float64
        MMQE of each sub-block before any collapse (full resolution), m².
    del_slot, del_tri : (2C,), (2C, 3) int32
        The two slots collapse i deleted (``2i``, ``2i+1``) and their vertex triples then.
    rep_ptr : (C+1,) int64; rep_slot (R,), rep_old (R, 3), rep_new (R, 3) int32
        Slots collapse i rewrote (``rep_ptr[i]:rep_ptr[i+1]``), with triples before and after.
    base_tris : (M, 3) int32, base_alive : (M,) bool
        Triangle slots at the end (the most simplified version); dead slots keep their last triple.
    """

    u: np.ndarray
    v: np.ndarray
    block: np.ndarray
    mmqe_m2: np.ndarray
    cost: np.ndarray
    mmqe0_m2: np.ndarray
    del_slot: np.ndarray
    del_tri: np.ndarray
    rep_ptr: np.ndarray
    rep_slot: np.ndarray
    rep_old: np.ndarray
    rep_new: np.ndarray
    base_tris: np.ndarray
    base_alive: np.ndarray

    @property
    def n_collapses(self) -> int:
        return int(self.u.shape[0])


def simplify(
    vertices_m: np.ndarray,
    triangles: np.ndarray,
    kind: np.ndarray,
    tri_block: np.ndarray,
    vert_block: np.ndarray,
    *,
    base_fraction: float = 0.2,
    shape_eps: float = SHAPE_EPS,
    n_blocks: int | None = None,
    vertical_weight: float | None = None,
) -> CollapseLog:
    """Collapse edges by increasing QEM cost until each sub-block keeps ``base_fraction`` of its triangles.

    Parameters
    ----------
    vertices_m : (V, 3) float64
        Vertex positions, metres (any frame; they are centred internally for the quadrics).
    triangles : (M, 3) int
        Counter-clockwise triples (see :func:`terralod.tin.delaunay.delaunay_tin`).
    kind : (V,) uint8
        FREE or LOCKED (:class:`terralod.tin.delaunay.SubBlocks`).
    tri_block, vert_block : (M,), (V,) int
        Sub-block of each triangle and of each FREE vertex.
    base_fraction : float in (0, 1]
        Fraction of each sub-block's triangles kept in the base mesh (the paper's 20 %). Sub-blocks with
        few FREE vertices may stop above it (nothing left to collapse).
    shape_eps : float
        Orientation tolerance of rewritten triangles (dimensionless, see :data:`SHAPE_EPS`).
    n_blocks : int, optional
        Number of sub-blocks (default: the largest block index + 1); blocks may hold no triangle.
    vertical_weight : float, optional
        Weight of the vertical term added to the quadric cost (default :data:`VERTICAL_WEIGHT`); 0 gives the
        paper's cost, the quadric alone (faster, larger max error).

    Returns
    -------
    CollapseLog
    """
    if not (0.0 < base_fraction <= 1.0):
        raise InputError(f"Expected base_fraction in (0, 1], got {base_fraction}")
    if vertical_weight is not None and not (vertical_weight >= 0.0 and math.isfinite(vertical_weight)):
        raise InputError(f"Expected vertical_weight >= 0, got {vertical_weight}")
    v = np.asarray(vertices_m, np.float64)
    centre = 0.5 * (v.min(axis=0) + v.max(axis=0))
    p = np.ascontiguousarray(v - centre)
    tris = np.ascontiguousarray(triangles, np.int32).copy()
    alive = np.ones(tris.shape[0], np.bool_)
    tb = np.ascontiguousarray(tri_block, np.int32)
    nb = max(int(tb.max()) + 1 if tb.size else 1, int(n_blocks or 0))
    count = np.bincount(tb, minlength=nb)
    target = np.ceil(count * float(base_fraction)).astype(np.int64)
    out = qem_simplify(
        p,
        tris,
        alive,
        np.ascontiguousarray(kind, np.uint8),
        tb,
        np.ascontiguousarray(vert_block, np.int32),
        target,
        float(shape_eps),
        VERTICAL_WEIGHT if vertical_weight is None else float(vertical_weight),
    )
    (_, cu, cv, cblock, cmmqe, ccost, mmqe0, del_slot, del_tri, rep_ptr, rep_slot, rep_old, rep_new) = out
    return CollapseLog(
        cu,
        cv,
        cblock,
        cmmqe,
        ccost,
        mmqe0,
        del_slot,
        del_tri,
        rep_ptr,
        rep_slot,
        rep_old,
        rep_new,
        tris,
        alive,
    )


def measured_errors(vertices_m: np.ndarray, triangles: np.ndarray, log: CollapseLog) -> np.ndarray:
    """(C,) float64: an upper bound, metres, of the max vertical error of each sub-block's mesh just after
    each collapse, against the input vertices (the TIN's own points).

    Collapse i measures the vertical distance from the vertices it removed or displaced (the removed vertex
    and every removed vertex under a triangle it changed) to the surface it left
    (:func:`terralod.kernels.qem.collapse_vertical_errors`); the running maximum over the collapses of the
    same sub-block, in collapse order, makes it monotone (like the MMQE, §2.3.2) and an upper bound of the
    true max (a vertex no collapse since touched keeps its distance).
    """
    e = collapse_vertical_errors(
        np.ascontiguousarray(vertices_m, np.float64),
        np.ascontiguousarray(triangles, np.int32),
        log.u,
        log.del_slot,
        log.rep_ptr,
        log.rep_slot,
        log.rep_new,
    )
    if e.size == 0:
        return e
    blk = log.block.astype(np.int64)
    o = np.argsort(blk, kind="stable")  # block-major, collapse order kept
    es = e[o]
    starts = np.flatnonzero(np.r_[True, blk[o][1:] != blk[o][:-1]])
    for a, b in zip(starts, np.r_[starts[1:], es.size], strict=True):  # one running max per sub-block
        np.maximum.accumulate(es[a:b], out=es[a:b])
    out = np.empty_like(e)
    out[o] = es
    return out


def simplify_mesh(
    vertices_m: np.ndarray,
    triangles: np.ndarray,
    *,
    target_triangles: int,
    shape_eps: float = SHAPE_EPS,
    vertical_weight: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Simplify one TIN (a single block, its outline locked) to about ``target_triangles`` triangles.

    A convenience for comparisons with other simplifiers: returns (vertices_m unchanged, triangles (K, 3)
    int32 counter-clockwise), K >= target_triangles (the outline vertices cannot go).
    """
    from terralod.tin.delaunay import mesh_boundary_vertices

    tris = np.ascontiguousarray(triangles, np.int64)
    n = vertices_m.shape[0]
    locked = mesh_boundary_vertices(tris, n)
    kind = np.where(locked, LOCKED, FREE).astype(np.uint8)
    vb = np.where(locked, -1, 0).astype(np.int32)
    frac = min(max(target_triangles / max(tris.shape[0], 1), math.ulp(1.0)), 1.0)
    log = simplify(
        vertices_m,
        tris,
        kind,
        np.zeros(tris.shape[0], np.int32),
        vb,
        base_fraction=frac,
        shape_eps=shape_eps,
        vertical_weight=vertical_weight,
    )
    return vertices_m, log.base_tris[log.base_alive]
