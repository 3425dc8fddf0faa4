"""Detail increments ΔT as reversible records: the record model, merging with compression, MMQE codes.

Paper: ``../shared/papers/003_2a2cfcda929de24c.txt``

- eq. 1–2: f(S_i) = f(S_0) + ΔT_0 + … + ΔT_{i-1}; moving between scales adds or subtracts increments;
- §2.2.1, table 1: one record per collapse with ``levelIndex``, ``mmqeValue``, the deleted triangles'
  indices and vertex triples, the replaced triangles' indices with original and new vertex triples
  (:class:`DeltaT`; all records of a model as flat arrays: :class:`Increments`);
- §2.2.2: merging k consecutive records, where a triangle changed several times keeps only its first
  original and its last state, or only its first original as "deleted" when it ends deleted
  (:meth:`Increments.merged`).

The file formats (the paper's text scheme, the binary container) are in :mod:`terralod.tin.fileformat`;
the model that applies the records (§2.3.1) is :class:`terralod.tin.increments.DetailIncrementModel`.

Deviations, and why:

- **Stable triangle slots.** A triangle keeps its slot (row of the triangle array) for ever; a deleted
  triangle leaves its slot empty instead of shifting later triangles down. The paper's index
  recalculation (§2.2.1, steps 1–4) is then unnecessary, and applying a record is O(its size). The
  base triangles take slots 0 … n_base - 1 (in canonical order, :func:`canonical_rows`), record r's two
  re-created triangles n_base + 2r and n_base + 2r + 1: the full scale holds the input triangles as a
  set, in other slots (a triple may start at another of its vertices, same orientation).
- **Per-sub-block sequences.** Every collapse touches one sub-block, so each sub-block has its own scale
  S_0 … S_{n_b} and its own records, and the current scale is a vector, one entry per sub-block; an
  integer scale is a position in a global order of all records that refines, one record at a time, the
  sub-block whose current MMQE is the largest (:func:`mmqe_rank`; derived, so files need not store it).
- **MMQE quantised** to 1/256 octave (0.14 % of the SVO length sqrt(MMQE)); monotone stays monotone.
- **Raw records are vertex splits.** A raw record is one vertex split (removed vertex u, kept vertex v,
  the wing x1 where the fan of m moved triangles starts, see :func:`terralod.kernels.qem_replay.replay_splits`);
  :meth:`Increments.from_compact` replays the splits from the base once, deriving every field of table 1
  (slots, deleted triples, original and new triples) exactly. Merged records (§2.2.2) are derived in
  memory from the raw ones.
- **Measured error per scale** (not in the paper): besides the MMQE, each scale of a sub-block stores an
  upper bound of its max vertical distance to the input points (:func:`terralod.tin.qem.measured_errors`,
  quantised rounding up by :func:`quantise_error`); scale selection uses them by default (see
  :mod:`terralod.tin.svo` for why; ``error="mmqe"`` is the paper's rule).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from terralod.errors import CorruptStoreError, InputError
from terralod.kernels.qem_replay import replay_splits
from terralod.tin.svo import monotone_mmqe

__all__ = [
    "DeltaT",
    "Increments",
    "canonical_rows",
    "dequantise_mmqe",
    "mmqe_rank",
    "quantise_error",
    "quantise_mmqe",
]


# -- records ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class DeltaT:
    """One detail increment ΔT_s of one sub-block: what takes scale S_s to S_{s+1} (Ai et al. (2019) table 1).

    Refining (vertex split) brings the deleted triangles back and gives the replaced ones their original
    triples; coarsening (edge collapse) does the opposite.

    Attributes
    ----------
    level_index : int
        s (``levelIndex``).
    mmqe_value : float
        Monotone MMQE of scale S_s, m² (``mmqeValue``).
    deleted_tri : (d,) int32
        Slots of the triangles S_{s+1} has and S_s has not (``deletedTriInfo``).
    deleted_tri_vex : (d, 3) int32
        Their vertex triples in S_{s+1} (``deletedTriVexInfo``).
    replaced_tri : (r,) int32
        Slots present in both with different triples (``replacedTriInfo``).
    replaced_tri_vex_ori : (r, 3) int32
        Their triples in S_{s+1}, the finer scale (``replacedTriVexOriInfo``).
    replaced_tri_vex_new : (r, 3) int32
        Their triples in S_s, after the collapse (``replacedTriVexNewInfo``).
    block : int
        Sub-block.
    """

    level_index: int
    mmqe_value: float
    deleted_tri: np.ndarray
    deleted_tri_vex: np.ndarray
    replaced_tri: np.ndarray
    replaced_tri_vex_ori: np.ndarray
    replaced_tri_vex_new: np.ndarray
    block: int = 0


def _csr_take(ptr: np.ndarray, order: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows ``order`` of a CSR layout: (new ptr, item indices into the old item arrays)."""
    lens = (ptr[1:] - ptr[:-1])[order]
    new_ptr = np.zeros(order.size + 1, np.int64)
    np.cumsum(lens, out=new_ptr[1:])
    starts = np.repeat(ptr[:-1][order] - new_ptr[:-1], lens)
    return new_ptr, np.arange(new_ptr[-1], dtype=np.int64) + starts


# -- MMQE quantisation -----------------------------------------------------------------------------------
#: MMQE codes per octave: a code is round(256 · log2(MMQE / m²)), a relative step of 0.27 % in MMQE and
#: 0.14 % in the SVO length sqrt(MMQE); monotone, so a monotone MMQE stays monotone.
MMQE_STEPS_PER_OCTAVE = 256
#: Code of MMQE 0 (and of anything below 2^-40 m², about 1e-12 m²).
MMQE_ZERO_CODE = -40 * MMQE_STEPS_PER_OCTAVE


def quantise_mmqe(mmqe_m2: np.ndarray) -> np.ndarray:
    """(n,) int64 codes of MMQE values, m² (see :data:`MMQE_STEPS_PER_OCTAVE`)."""
    mm = np.asarray(mmqe_m2, np.float64)
    with np.errstate(divide="ignore"):
        c = np.round(np.log2(np.maximum(mm, 0.0)) * MMQE_STEPS_PER_OCTAVE)
    return np.maximum(np.nan_to_num(c, nan=MMQE_ZERO_CODE, neginf=MMQE_ZERO_CODE), MMQE_ZERO_CODE).astype(
        np.int64
    )


def quantise_error(error_m: np.ndarray) -> np.ndarray:
    """(n,) int64 codes of measured errors, metres, rounded *up* (1/256 octave, 0.27 %), so the stored
    error never falls below the measured one; 0 gets the zero code."""
    e = np.asarray(error_m, np.float64)
    with np.errstate(divide="ignore"):
        c = np.ceil(np.log2(np.maximum(e, 0.0)) * MMQE_STEPS_PER_OCTAVE)
    c = np.nan_to_num(c, nan=MMQE_ZERO_CODE, neginf=MMQE_ZERO_CODE)
    return np.where(e > 0.0, np.maximum(c, MMQE_ZERO_CODE + 1), MMQE_ZERO_CODE).astype(np.int64)


def dequantise_mmqe(code: np.ndarray) -> np.ndarray:
    """(n,) float64 MMQE, m², of codes from :func:`quantise_mmqe` (the zero code gives 0)."""
    c = np.asarray(code, np.int64)
    return np.where(c <= MMQE_ZERO_CODE, 0.0, np.exp2(c / MMQE_STEPS_PER_OCTAVE))


def mmqe_rank(block_ptr: np.ndarray, mmqe_code: np.ndarray) -> np.ndarray:
    """(R,) int64: each (block-major) record's position in the global refinement order.

    Record s of block b (S_s -> S_{s+1}) ranks by the MMQE of S_s, largest first, then by block, then
    by s: the global scale j refines, j times, the sub-block whose current MMQE is the largest. Each
    block's MMQE never grows with s, so every block keeps its own order.
    """
    bp = np.asarray(block_ptr, np.int64)
    nb = bp.size - 1
    n = int(bp[-1])
    blk = np.repeat(np.arange(nb, dtype=np.int64), np.diff(bp))
    s = np.arange(n, dtype=np.int64) - bp[blk]
    key = np.asarray(mmqe_code, np.int64)[bp[blk] + blk + s]  # code of S_s (mmqe_ptr = block_ptr + b)
    order = np.lexsort((s, blk, -key))
    rank = np.empty(n, np.int64)
    rank[order] = np.arange(n, dtype=np.int64)
    return rank


class Increments:
    """The records of every sub-block, as flat arrays (records in block-major refinement order).

    Block b owns records ``block_ptr[b] … block_ptr[b+1]-1``; record ``block_ptr[b] + s`` is ΔT_s of
    block b. Record r deletes ``del_slot[del_ptr[r]:del_ptr[r+1]]`` (triples ``del_tri``) and replaces
    ``rep_slot[rep_ptr[r]:rep_ptr[r+1]]`` (``rep_old`` in the finer scale, ``rep_new`` in the coarser).
    ``mmqe_m2[mmqe_ptr[b] + s]`` is the monotone MMQE of block b's scale S_s (s = 0 … n_b).
    ``rank[r]`` orders the records globally (refinement order; consistent with each block's order).
    ``step`` is the number of collapses merged into one record (1 for raw records).
    """

    def __init__(
        self,
        block_ptr: np.ndarray,
        del_ptr: np.ndarray,
        del_slot: np.ndarray,
        del_tri: np.ndarray,
        rep_ptr: np.ndarray,
        rep_slot: np.ndarray,
        rep_old: np.ndarray,
        rep_new: np.ndarray,
        mmqe_m2: np.ndarray,
        rank: np.ndarray,
        step: int = 1,
        rec_u: np.ndarray | None = None,
        rec_v: np.ndarray | None = None,
        rec_w: np.ndarray | None = None,
        mmqe_code: np.ndarray | None = None,
        raw: Increments | None = None,
        error_m: np.ndarray | None = None,
        error_code: np.ndarray | None = None,
    ) -> None:
        self.block_ptr = np.ascontiguousarray(block_ptr, np.int64)
        self.del_ptr = np.ascontiguousarray(del_ptr, np.int64)
        self.del_slot = np.ascontiguousarray(del_slot, np.int32)
        self.del_tri = np.ascontiguousarray(del_tri, np.int32).reshape(-1, 3)
        self.rep_ptr = np.ascontiguousarray(rep_ptr, np.int64)
        self.rep_slot = np.ascontiguousarray(rep_slot, np.int32)
        self.rep_old = np.ascontiguousarray(rep_old, np.int32).reshape(-1, 3)
        self.rep_new = np.ascontiguousarray(rep_new, np.int32).reshape(-1, 3)
        self.mmqe_m2 = np.ascontiguousarray(mmqe_m2, np.float64)
        self.rank = np.ascontiguousarray(rank, np.int64)
        self.step = int(step)
        #: raw records only: the split each makes (v into v and u; wing rank w among v's neighbours)
        self.rec_u = None if rec_u is None else np.ascontiguousarray(rec_u, np.int32)
        self.rec_v = None if rec_v is None else np.ascontiguousarray(rec_v, np.int32)
        self.rec_w = None if rec_w is None else np.ascontiguousarray(rec_w, np.int32)
        #: raw records only: the quantised MMQE codes (mmqe_m2 = dequantise_mmqe(mmqe_code))
        self.mmqe_code = None if mmqe_code is None else np.ascontiguousarray(mmqe_code, np.int64)
        #: merged records only: the raw records they were merged from (what a file stores)
        self.raw = raw
        #: measured max vertical error of every block's scales, metres, laid out like ``mmqe_m2`` (monotone,
        #: an upper bound; 0 at full resolution); raw records also keep its codes (what a file stores)
        self.error_m = (np.full(self.mmqe_m2.shape, np.inf) if error_m is None
                        else np.ascontiguousarray(error_m, np.float64))  # fmt: skip
        self.error_code = None if error_code is None else np.ascontiguousarray(error_code, np.int64)
        nb = self.block_ptr.size - 1
        self.mmqe_ptr = self.block_ptr + np.arange(nb + 1)
        self.record_block = np.repeat(np.arange(nb, dtype=np.int32), np.diff(self.block_ptr))
        self.order = np.argsort(self.rank, kind="stable")

    # -- sizes ------------------------------------------------------------------------------------------
    @property
    def n_blocks(self) -> int:
        return int(self.block_ptr.size - 1)

    @property
    def n_records(self) -> int:
        return int(self.block_ptr[-1])

    def block_n_records(self) -> np.ndarray:
        """(B,) int64: records of each block, n_b (its scales are S_0 … S_{n_b})."""
        return np.diff(self.block_ptr)

    def mmqe_of(self, block: int) -> np.ndarray:
        """Monotone MMQE of block ``block``'s scales S_0 … S_{n_b}, m²."""
        return self.mmqe_m2[self.mmqe_ptr[block] : self.mmqe_ptr[block + 1]]

    def error_of(self, block: int) -> np.ndarray:
        """Measured max vertical error of block ``block``'s scales S_0 … S_{n_b}, metres (monotone)."""
        return self.error_m[self.mmqe_ptr[block] : self.mmqe_ptr[block + 1]]

    def record(self, block: int, s: int) -> DeltaT:
        """ΔT_s of block ``block`` as the paper's record (copies)."""
        n = int(self.block_ptr[block + 1] - self.block_ptr[block])
        if not 0 <= s < n:
            raise IndexError(f"Expected a level index in [0, {n}) for block {block}, got {s}")
        r = int(self.block_ptr[block]) + s
        d0, d1 = self.del_ptr[r], self.del_ptr[r + 1]
        r0, r1 = self.rep_ptr[r], self.rep_ptr[r + 1]
        return DeltaT(
            s,
            float(self.mmqe_m2[self.mmqe_ptr[block] + s]),
            self.del_slot[d0:d1].copy(),
            self.del_tri[d0:d1].copy(),
            self.rep_slot[r0:r1].copy(),
            self.rep_old[r0:r1].copy(),
            self.rep_new[r0:r1].copy(),
            block,
        )

    def records(self, block: int) -> Iterator[DeltaT]:
        """ΔT_0, ΔT_1, … of block ``block``."""
        for s in range(int(self.block_ptr[block + 1] - self.block_ptr[block])):
            yield self.record(block, s)

    # -- construction ----------------------------------------------------------------------------------
    @classmethod
    def from_log(
        cls,
        log: Any,
        n_blocks: int,
        n_vertices: int,
        error_m: np.ndarray,
        on_compact: Callable[..., None] | None = None,
    ) -> tuple[Increments, np.ndarray, np.ndarray]:
        """Records from a :class:`terralod.tin.qem.CollapseLog` (collapse order → refinement order).

        ``error_m`` (C,): the measured error of each collapse (:func:`terralod.tin.qem.measured_errors`).

        The log is encoded to the compact vertex splits a file stores and decoded back
        (:meth:`from_compact`), so a model built here is exactly the model its file loads (slots
        included). Returns (increments, base triples (S, 3), base alive (S,)) in the decoded slot order:
        the base triangles first, in their input order. ``on_compact(base_tri, block_records, u, v, x1, m)``
        is called with the compact records before they are replayed (what a file's coder needs).
        """
        c = log.n_collapses
        block = log.block.astype(np.int64)
        # Block-major, and within a block the last collapse first (ΔT_0 undoes the last collapse).
        perm = np.lexsort((-np.arange(c), block))
        block_records = np.bincount(block, minlength=n_blocks).astype(np.int64)
        u = log.u[perm].astype(np.int64)
        v = log.v[perm].astype(np.int64)
        m = np.diff(log.rep_ptr)[perm].astype(np.int64)
        # x1: the third vertex of the deleted triangle holding the directed edge u -> v
        d = log.del_tri.reshape(c, 2, 3)[perm].astype(np.int64)
        uu, vv = u[:, None], v[:, None]
        has_uv = (
            ((d[..., 0] == uu) & (d[..., 1] == vv))
            | ((d[..., 1] == uu) & (d[..., 2] == vv))
            | ((d[..., 2] == uu) & (d[..., 0] == vv))
        )
        third = d.sum(axis=2) - uu - vv
        x1 = np.where(has_uv[:, 0], third[:, 0], third[:, 1])
        del d, uu, vv, has_uv, third  # (about 80 bytes a collapse, gone before the replay's arrays come)
        # the base in canonical order (each triple from its smallest vertex, rows sorted): the file codes
        # its rows as deltas (:func:`encode_mesh_rows`)
        base_tri = canonical_rows(log.base_tris[log.base_alive])
        mm = np.empty(c + n_blocks, np.float64)
        ee = np.empty(c + n_blocks, np.float64)
        err = np.asarray(error_m, np.float64)
        block_ptr = np.concatenate([[0], np.cumsum(block_records)])
        for b in range(n_blocks):
            lo, hi = block_ptr[b], block_ptr[b + 1]
            mm[lo + b : hi + b + 1] = monotone_mmqe(
                np.concatenate([log.mmqe_m2[perm[lo:hi]], [log.mmqe0_m2[b]]])
            )
            ee[lo + b : hi + b + 1] = monotone_mmqe(np.concatenate([err[perm[lo:hi]], [0.0]]))
        mmqe_code, error_code = quantise_mmqe(mm), quantise_error(ee)
        del mm, ee, perm, block
        if on_compact is not None:
            on_compact(base_tri, block_records, u, v, x1, m)
        return cls.from_compact(
            n_vertices,
            base_tri,
            block_records,
            u,
            v,
            x1,
            m,
            mmqe_code,
            error_code,
            source="collapse log",
        )

    @classmethod
    def from_compact(
        cls,
        n_vertices: int,
        base_tri: np.ndarray,
        block_records: np.ndarray,
        rec_u: np.ndarray,
        rec_v: np.ndarray,
        rec_x1: np.ndarray,
        rec_m: np.ndarray,
        mmqe_code: np.ndarray,
        error_code: np.ndarray,
        *,
        source: str | None = None,
        moves: tuple[np.ndarray, ...] | None = None,
    ) -> tuple[Increments, np.ndarray, np.ndarray]:
        """Raw records from the compact vertex splits (what a file decodes to), by replaying them from the base.

        Parameters
        ----------
        n_vertices : int
        base_tri : (n_base, 3) int, the base triangles (they take slots 0 … n_base - 1).
        block_records : (B,) int, n_b; records are block-major, each block's in refinement order.
        rec_u, rec_v, rec_x1, rec_m : (R,) int, the splits: v splits into v and u, the fan of m triangles
            from the wing vertex x1 moves to u (see :func:`terralod.kernels.qem_replay.replay_splits`).
        mmqe_code : (R + B,) int, quantised monotone MMQE of every block's scales S_0 … S_{n_b}.
        error_code : (R + B,) int, quantised measured error of the same scales (:func:`quantise_error`).
        moves : (del_tri, rep_ptr, rep_slot, rep_old, rep_new) of these splits when known (the file's decoder,
            :func:`terralod.kernels.tincodec.split_codes`, writes them as it replays): not replayed again,
            and the x1 ranks (``rec_w``, which nothing reads) are not derived.

        Returns (increments, base triples (S, 3), base alive (S,)); CorruptStoreError (naming ``source``)
        when the splits do not fit together.
        """
        rec_u, rec_v, rec_x1, rec_m = (
            np.ascontiguousarray(a, np.int64) for a in (rec_u, rec_v, rec_x1, rec_m)
        )
        base_tri = np.ascontiguousarray(base_tri, np.int32).reshape(-1, 3)
        rec_w: np.ndarray | None = None
        if moves is not None:
            status = 0
            del_tri, rep_ptr, rep_slot, rep_old, rep_new = moves
        else:
            rec_w = np.zeros(rec_u.size, np.int64)
            status, _, del_tri, rep_ptr, rep_slot, rep_old, rep_new = replay_splits(
                int(n_vertices), base_tri, rec_u, rec_v, rec_x1, rec_w, rec_m, True
            )
        if status != 0:
            where = "base triangles" if status < 0 else f"record {status - 1}"
            raise CorruptStoreError(
                f"inconsistent detail-increment records: {where} does not fit the mesh", source
            )
        c = rec_u.size
        n_base = base_tri.shape[0]
        block_ptr = np.concatenate([[0], np.cumsum(block_records)]).astype(np.int64)
        rank = mmqe_rank(block_ptr, mmqe_code)
        base_tris = np.zeros((n_base + 2 * c, 3), np.int32)
        base_tris[:n_base] = base_tri
        base_alive = np.zeros(n_base + 2 * c, np.bool_)
        base_alive[:n_base] = True
        inc = cls(
            block_ptr,
            np.arange(0, 2 * c + 1, 2, dtype=np.int64),
            np.arange(n_base, n_base + 2 * c, dtype=np.int32),
            del_tri,
            rep_ptr,
            rep_slot,
            rep_old,
            rep_new,
            dequantise_mmqe(mmqe_code),
            rank,
            1,
            rec_u,
            rec_v,
            rec_w,
            mmqe_code,
            None,
            dequantise_mmqe(error_code),
            error_code,
        )
        return inc, base_tris, base_alive

    def merged(self, k: int) -> Increments:
        """Merge every k consecutive records of each block into one, compressed (Ai et al. (2019) §2.2.2).

        Block b's scales become S_0, S_k, S_2k, …, S_{n_b} (the last record may hold fewer than k).
        Within a merged record a triangle appears once: changed once, it stays as it is (principle 1);
        changed several times and finally replaced, it keeps its first original and its last new triple
        (principle 2); finally deleted, it keeps only its first original, as a deleted triangle
        (principle 3). Vectorised over all records at once.
        """
        if isinstance(k, bool) or not isinstance(k, int | np.integer) or k < 1:
            raise InputError(f"Expected a merge factor k >= 1, got {k!r}")
        if k == 1:
            return self
        if self.raw is not None:  # merging merged records = merging the raw ones by the product
            return self.raw.merged(self.step * k)
        nb = self.n_blocks
        n_b = self.block_n_records()
        g_b = -(-n_b // k)  # groups (merged records) per block
        gptr = np.zeros(nb + 1, np.int64)
        np.cumsum(g_b, out=gptr[1:])
        rec_local = np.arange(self.n_records) - self.block_ptr[self.record_block]
        rec_group = gptr[self.record_block] + rec_local // k

        # Every change as an event (group, slot, record, original triple, new triple; new = -1: deleted).
        nd = self.del_slot.size
        ev_rec = np.concatenate(
            [
                np.repeat(np.arange(self.n_records), np.diff(self.del_ptr)),
                np.repeat(np.arange(self.n_records), np.diff(self.rep_ptr)),
            ]
        )
        ev_slot = np.concatenate([self.del_slot, self.rep_slot])
        ev_old = np.concatenate([self.del_tri, self.rep_old])
        ev_new = np.concatenate([np.full((nd, 3), -1, np.int32), self.rep_new])
        ev_group = rec_group[ev_rec]
        # Within a group the collapse order is decreasing record index: sort so each (group, slot) run
        # starts with its first collapse (its original triple) and ends with its last (its final state).
        o = np.lexsort((-ev_rec, ev_slot, ev_group))
        g, s = ev_group[o], ev_slot[o]
        start = np.ones(o.size, bool)
        start[1:] = (g[1:] != g[:-1]) | (s[1:] != s[:-1])
        first = o[start]
        last = o[np.append(np.flatnonzero(start)[1:] - 1, o.size - 1)] if o.size else o
        grp = ev_group[first]
        slot = ev_slot[first]
        old = ev_old[first]
        new = ev_new[last]
        dead = new[:, 0] < 0
        n_groups = int(gptr[-1])
        del_ptr = np.zeros(n_groups + 1, np.int64)
        np.cumsum(np.bincount(grp[dead], minlength=n_groups), out=del_ptr[1:])
        rep_ptr = np.zeros(n_groups + 1, np.int64)
        np.cumsum(np.bincount(grp[~dead], minlength=n_groups), out=rep_ptr[1:])

        # Scales S_0, S_k, …, S_{n_b}: the monotone MMQE sampled there (still monotone).
        mm = np.empty(n_groups + nb, np.float64)
        ee = np.empty(n_groups + nb, np.float64)
        for b in range(nb):
            scales = np.minimum(np.arange(g_b[b] + 1) * k, n_b[b])
            mm[gptr[b] + b : gptr[b + 1] + b + 1] = self.mmqe_of(b)[scales]
            ee[gptr[b] + b : gptr[b + 1] + b + 1] = self.error_of(b)[scales]
        # A merged record ranks where its first member does (keeps each block's order).
        rank = np.zeros(n_groups, np.int64)
        if self.n_records:
            rank = np.full(n_groups, np.iinfo(np.int64).max, np.int64)
            np.minimum.at(rank, rec_group, self.rank)
        return Increments(
            gptr,
            del_ptr,
            slot[dead],
            old[dead],
            rep_ptr,
            slot[~dead],
            old[~dead],
            new[~dead],
            mm,
            rank,
            self.step * k,
            raw=self if self.rec_u is not None else None,
            error_m=ee,
        )


# -- base mesh order -------------------------------------------------------------------------------------
def canonical_rows(tris: np.ndarray) -> np.ndarray:
    """(K, 3) int32: each triple turned to start at its smallest vertex (orientation kept), rows sorted."""
    t = np.asarray(tris, np.int64).reshape(-1, 3)
    t = np.take_along_axis(t, (np.argmin(t, axis=1)[:, None] + np.arange(3)) % 3, axis=1)
    return np.ascontiguousarray(t[np.lexsort((t[:, 2], t[:, 1], t[:, 0]))], np.int32)
