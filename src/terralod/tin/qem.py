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
- **One heap per sub-block, in parallel** (as the paper's threads), each sub-block stopping at its own
  target (``base_fraction`` of its triangles). A sub-block is simplified as a mesh of its own triangles,
  its seam and outline vertices LOCKED, starting from the quadrics of the whole TIN (a seam vertex holds
  the planes of its triangles in every sub-block around it). What a collapse merges into a seam vertex's
  quadric stays in its own sub-block's copy: with one heap for all sub-blocks (this module until 2026-12)
  a collapse onto a seam vertex v in one block raised the cost of every later collapse onto v in the
  neighbouring block, so the per-block sequences depended on how the blocks interleaved, and collapses in
  different blocks did not commute. Now they do: each block's sequence is a function of that block's
  triangles and the initial quadrics, the same on 1 or N threads, on Dask workers, or one block after
  another (``workers=1``). The link condition is tested on the block's mesh: a collapse that it accepts and
  the whole TIN's link condition refuses would need an edge of another block inside this block's outline,
  which the orientation test rejects (the block's outline is fixed and its triangles stay
  counter-clockwise, so they tile the same region). The log is block-major; the global order of scales
  comes from the MMQE ranks of the records (:class:`terralod.tin.records.Increments`).
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
import os
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from terralod.errors import InputError
from terralod.kernels.qem import FREE, LOCKED, collapse_vertical_errors, plane_quadrics, qem_simplify

__all__ = [
    "BlockJob",
    "BlockResult",
    "CollapseLog",
    "block_jobs",
    "measured_errors",
    "merge_blocks",
    "run_block",
    "simplify",
    "simplify_blocks",
    "simplify_mesh",
]

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


@dataclass(frozen=True)
class BlockJob:
    """What simplifying one sub-block needs, in the block's own (local) vertex and slot numbering.

    Local vertex i is ``verts[i]`` of the TIN, local slot j is ``slots[j]``; both ascending, so every
    tie the kernel breaks by index goes the same way as in the whole TIN. Plain arrays: a job pickles to a
    Dask worker (:mod:`terralod.tin.distributed`).
    """

    block: int
    verts: np.ndarray  #: (n,) int64 TIN vertex of each local vertex, ascending
    slots: np.ndarray  #: (m,) int64 TIN slot of each local triangle, ascending
    p: np.ndarray  #: (n, 3) float64 positions in the TIN's centred frame, metres
    world_m: np.ndarray  #: (n, 3) float64 world positions (measured errors), metres
    tris: np.ndarray  #: (m, 3) int32 local triples, counter-clockwise
    kind: np.ndarray  #: (n,) uint8 FREE / LOCKED
    q: np.ndarray  #: (n, 10) float64 initial quadrics of the whole TIN
    w: np.ndarray  #: (n,) float64 their areas, m²
    target: int  #: stop at this many live triangles
    shape_eps: float
    vertical_weight: float


@dataclass(frozen=True)
class BlockResult:
    """One sub-block's collapses (local numbering, see :class:`BlockJob`) and measured errors."""

    block: int
    out: tuple  #: the kernel's return tuple (:func:`terralod.kernels.qem.qem_simplify`)
    tris: np.ndarray  #: (m, 3) int32 local triples at the base
    alive: np.ndarray  #: (m,) bool
    error_m: np.ndarray  #: (C_b,) float64 running max of the measured vertical error, metres


def _targets(tri_block: np.ndarray, nb: int, base_fraction: float) -> np.ndarray:
    count = np.bincount(tri_block, minlength=nb)
    return np.ceil(count * float(base_fraction)).astype(np.int64)


def _check(base_fraction: float, vertical_weight: float | None) -> float:
    if not (0.0 < base_fraction <= 1.0):
        raise InputError(f"Expected base_fraction in (0, 1], got {base_fraction}")
    if vertical_weight is not None and not (vertical_weight >= 0.0 and math.isfinite(vertical_weight)):
        raise InputError(f"Expected vertical_weight >= 0, got {vertical_weight}")
    return VERTICAL_WEIGHT if vertical_weight is None else float(vertical_weight)


def block_vertices(t: np.ndarray, n_vertices: int) -> np.ndarray:
    """The vertices that triangles ``t`` use, ascending (int64): from a mask over all ``n_vertices`` while
    the TIN has at most 25 vertices per index of ``t``, else from a sort of ``t``'s own indices (a pass
    over V bytes per block made cutting every block of a large cloud cost blocks x V; measured with
    393 k indices: mask 2 / 11 / 27 ms, sort 11-12 ms, for V = 1 M / 10 M / 100 M)."""
    flat = t.ravel()
    if n_vertices <= 25 * flat.size:
        used = np.zeros(n_vertices, np.bool_)
        used[flat] = True
        return np.flatnonzero(used)
    s = np.sort(flat)
    keep = np.ones(s.size, np.bool_)
    keep[1:] = s[1:] != s[:-1]
    return s[keep].astype(np.int64)


def block_jobs(
    vertices_m: np.ndarray,
    triangles: np.ndarray,
    kind: np.ndarray,
    tri_block: np.ndarray,
    *,
    base_fraction: float = 0.2,
    shape_eps: float = SHAPE_EPS,
    n_blocks: int | None = None,
    vertical_weight: float | None = None,
) -> tuple[int, Callable[[int], BlockJob | None]]:
    """(number of blocks, make(b)): ``make(b)`` cuts sub-block b's job out of the TIN (None: no triangle).

    The quadrics are computed once over the whole TIN (so a seam vertex has the planes of every block
    around it); cutting a job is numpy work on the block's own triangles (:func:`block_vertices`) that
    releases the GIL, so threads may cut their own.
    """
    vw = _check(base_fraction, vertical_weight)
    v = np.asarray(vertices_m, np.float64)
    centre = 0.5 * (v.min(axis=0) + v.max(axis=0))
    p = np.ascontiguousarray(v - centre)
    tris = np.ascontiguousarray(triangles, np.int32)
    tb = np.ascontiguousarray(tri_block, np.int32)
    nb = max(int(tb.max()) + 1 if tb.size else 1, int(n_blocks or 0))
    target = _targets(tb, nb, base_fraction)
    q, w = plane_quadrics(p, tris, np.ones(tris.shape[0], np.bool_))
    kind8 = np.ascontiguousarray(kind, np.uint8)
    order = np.argsort(tb, kind="stable")
    ptr = np.searchsorted(tb[order], np.arange(nb + 1))

    def make(b: int) -> BlockJob | None:
        slots = order[ptr[b] : ptr[b + 1]].astype(np.int64)
        if slots.size == 0:
            return None
        t = tris[slots]
        verts = block_vertices(t, v.shape[0])
        local = np.searchsorted(verts, t).astype(np.int32)
        return BlockJob(int(b), verts, slots, p[verts], v[verts], local, kind8[verts], q[verts], w[verts],
                        int(target[b]), float(shape_eps), vw)  # fmt: skip

    return nb, make


def run_block(job: BlockJob) -> BlockResult:
    """Simplify one sub-block (its own heap, its seam LOCKED) and measure each collapse's error.

    A pure function of the job (the numba kernels release the GIL: threads run blocks in parallel)."""
    tris = job.tris.copy()
    alive = np.ones(tris.shape[0], np.bool_)
    n = job.p.shape[0]
    out = qem_simplify(job.p, tris, alive, job.kind, np.zeros(tris.shape[0], np.int32), np.zeros(n, np.int32),
                       np.array([job.target], np.int64), job.shape_eps, job.vertical_weight, job.q, job.w)  # fmt: skip
    _, cu, _, _, _, _, _, del_slot, _, rep_ptr, rep_slot, _, rep_new = out
    e = collapse_vertical_errors(job.world_m, job.tris, cu, del_slot, rep_ptr, rep_slot, rep_new)
    np.maximum.accumulate(e, out=e)
    return BlockResult(job.block, out, tris, alive, e)


#: The log's fields a model's records are made of (:meth:`terralod.tin.records.Increments.from_log`); the
#: others (costs, deleted and rewritten slots, rewritten triples: about 150 bytes a collapse) only serve
#: checks and the single-heap path, and are left empty when a build asks for the records' alone.
REWRITE_FIELDS = ("c", "ds", "rs", "ro", "rn")


def block_part(job: BlockJob, res: BlockResult, keep_rewrites: bool = True) -> dict[str, np.ndarray]:
    """One block's share of the merged log, in the TIN's numbering (what :func:`merge_blocks` joins): made
    as soon as the block is done, so the block's own result (local numbering, every kernel output) goes
    then, not at the merge."""
    (_, cu, cv, _, cmmqe, ccost, m0, del_slot, del_tri, rep_ptr, rep_slot, rep_old, rep_new) = res.out
    vi, si = job.verts.astype(np.int32), job.slots.astype(np.int32)
    part = {
        "u": vi[cu],
        "v": vi[cv],
        "b": np.full(cu.size, job.block, np.int32),
        "mm": cmmqe,
        "m0": m0[:1],
        "dt": vi[del_tri],
        "rc": np.diff(rep_ptr),  # slots rewritten by each collapse
        "e": res.error_m,
        "si": si,
        "tris": vi[res.tris],
        "alive": res.alive,
    }
    if keep_rewrites:
        part.update(c=ccost, ds=si[del_slot], rs=si[rep_slot], ro=vi[rep_old], rn=vi[rep_new])
    return part


def merge_blocks(
    triangles: np.ndarray, nb: int, parts: Sequence[dict[str, np.ndarray] | None]
) -> tuple[CollapseLog, np.ndarray]:
    """One log (block-major, each block's collapses in its order) and its measured errors, from each
    block's :func:`block_part` (None for an empty block); the parts are emptied as they are joined (each
    field's blocks go once it is one array), so the merge holds the log about once, not three times. The
    fields of :data:`REWRITE_FIELDS` are empty unless every part has them."""
    tris = np.ascontiguousarray(triangles, np.int32).copy()
    alive = np.ones(tris.shape[0], np.bool_)
    mmqe0 = np.zeros(nb, np.float64)
    have = [p for p in parts if p is not None]
    for b, p in enumerate(parts):
        if p is not None:
            mmqe0[b] = p["m0"][0]
            tris[p["si"]] = p["tris"]
            alive[p["si"]] = p["alive"]
            for k in ("m0", "si", "tris", "alive"):
                del p[k]
    rewrites = bool(have) and all("c" in p for p in have)

    def cat(key: str, dtype: type, shape: tuple[int, ...] = (0,)) -> np.ndarray:
        a = [p.pop(key) for p in have if key in p]
        return (
            np.concatenate(a).astype(dtype, copy=False)
            if a and (rewrites or key not in REWRITE_FIELDS)
            else np.zeros(shape, dtype)
        )

    u, v, blk, mm = cat("u", np.int32), cat("v", np.int32), cat("b", np.int32), cat("mm", np.float64)
    cost, ds, dt = cat("c", np.float64), cat("ds", np.int32), cat("dt", np.int32, (0, 3))
    rep_ptr = np.concatenate([[0], np.cumsum(cat("rc", np.int64))]).astype(np.int64)
    rs, ro, rn = cat("rs", np.int32), cat("ro", np.int32, (0, 3)), cat("rn", np.int32, (0, 3))
    log = CollapseLog(u, v, blk, mm, cost, mmqe0, ds, dt, rep_ptr, rs, ro, rn, tris, alive)
    return log, cat("e", np.float64)


def _workers(workers: int | None) -> int:
    if workers is None:
        return max(1, min(os.cpu_count() or 1, 8))
    if isinstance(workers, bool) or int(workers) < 1:
        raise InputError(f"Expected workers >= 1, got {workers!r}")
    return int(workers)


def simplify_blocks(
    vertices_m: np.ndarray,
    triangles: np.ndarray,
    kind: np.ndarray,
    tri_block: np.ndarray,
    *,
    base_fraction: float = 0.2,
    shape_eps: float = SHAPE_EPS,
    n_blocks: int | None = None,
    vertical_weight: float | None = None,
    workers: int | None = None,
    executor: Callable[[Iterable[BlockJob], Callable[[BlockJob], BlockResult]], list[BlockResult]]
    | None = None,
    keep_rewrites: bool = True,
) -> tuple[CollapseLog, np.ndarray]:
    """Each sub-block simplified on its own (its seam LOCKED), ``workers`` threads, and merged: (log,
    measured errors (C,), the per-block running max of :func:`measured_errors`). Without
    ``keep_rewrites`` the log's fields a model's records do not read (:data:`REWRITE_FIELDS`) are empty.

    The result does not depend on ``workers`` (each block's collapses are a function of its job);
    ``executor(jobs, run_block)`` may replace the thread pool: it takes the jobs as they are cut (an
    iterable) and returns :func:`run_block` of each job, in order
    (Dask workers, :func:`terralod.tin.distributed.dask_executor`).
    """
    nb, make = block_jobs(vertices_m, triangles, kind, tri_block, base_fraction=base_fraction,
                          shape_eps=shape_eps, n_blocks=n_blocks, vertical_weight=vertical_weight)  # fmt: skip
    jobs: list[BlockJob | None] = [None] * nb

    def one(b: int) -> dict[str, np.ndarray] | None:
        job = make(b)
        if job is None:
            return None
        # in the TIN's numbering at once: the job's inputs (~160 bytes a vertex) and the block's own
        # result go now
        return block_part(job, run_block(job), keep_rewrites)

    # biggest blocks first: the pool ends together
    size = np.bincount(np.asarray(tri_block, np.int64), minlength=nb)
    blocks = [int(b) for b in np.argsort(-size, kind="stable")]
    n_threads = _workers(workers)
    if executor is not None:

        def cut() -> Iterator[BlockJob]:  # each job handed over as soon as it is cut: the first ones run
            for b in blocks:  # while the client cuts the rest
                jobs[b] = make(b)
                if jobs[b] is not None:
                    yield jobs[b]

        ran = iter(executor(cut(), run_block))
        got = []
        for b in blocks:
            job = jobs[b]
            got.append(None if job is None else block_part(job, next(ran), keep_rewrites))
            jobs[b] = None
    elif n_threads == 1 or nb == 1:
        got = [one(b) for b in blocks]
    else:
        with ThreadPoolExecutor(min(n_threads, nb)) as pool:
            got = list(pool.map(one, blocks))
    parts: list[dict[str, np.ndarray] | None] = [None] * nb
    for b, r in zip(blocks, got, strict=True):
        parts[b] = r
    del got
    return merge_blocks(triangles, nb, parts)


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
    workers: int | None = None,
    single_heap: bool = False,
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
    workers : int, optional
        Threads simplifying sub-blocks (default: the cores, at most 8); the log is the same for any number.
    single_heap : bool
        The former build (one heap for all sub-blocks, seam quadrics shared across blocks, the log in
        global cost order), kept for comparisons; its per-block sequences may differ near the seams.

    Returns
    -------
    CollapseLog
    """
    if not single_heap:
        return simplify_blocks(vertices_m, triangles, kind, tri_block, base_fraction=base_fraction,
                               shape_eps=shape_eps, n_blocks=n_blocks, vertical_weight=vertical_weight,
                               workers=workers)[0]  # fmt: skip
    vw = _check(base_fraction, vertical_weight)
    v = np.asarray(vertices_m, np.float64)
    centre = 0.5 * (v.min(axis=0) + v.max(axis=0))
    p = np.ascontiguousarray(v - centre)
    tris = np.ascontiguousarray(triangles, np.int32).copy()
    alive = np.ones(tris.shape[0], np.bool_)
    tb = np.ascontiguousarray(tri_block, np.int32)
    nb = max(int(tb.max()) + 1 if tb.size else 1, int(n_blocks or 0))
    target = _targets(tb, nb, base_fraction)
    out = qem_simplify(p, tris, alive, np.ascontiguousarray(kind, np.uint8), tb,
                       np.ascontiguousarray(vert_block, np.int32), target, float(shape_eps), vw,
                       np.zeros((0, 10)), np.zeros(0))  # fmt: skip
    (_, cu, cv, cblock, cmmqe, ccost, mmqe0, del_slot, del_tri, rep_ptr, rep_slot, rep_old, rep_new) = out
    return CollapseLog(cu, cv, cblock, cmmqe, ccost, mmqe0, del_slot, del_tri, rep_ptr, rep_slot, rep_old,
                       rep_new, tris, alive)  # fmt: skip


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
