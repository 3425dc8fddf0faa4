"""Detail increments ΔT: records, merging with compression, reconstruction, file formats; the model.

Paper: ``../shared/papers/003_2a2cfcda929de24c.txt``

- eq. 1–2: f(S_i) = f(S_0) + ΔT_0 + … + ΔT_{i-1}; moving between scales adds or subtracts increments;
- §2.2.1, table 1: one record per collapse with ``levelIndex``, ``mmqeValue``, the deleted triangles'
  indices and vertex triples, the replaced triangles' indices with original and new vertex triples
  (:class:`DeltaT`);
- §2.2.2: merging k consecutive records, where a triangle changed several times keeps only its first
  original and its last state, or only its first original as "deleted" when it ends deleted
  (:meth:`Increments.merged`); and the external text scheme (:func:`write_text`);
- §2.3.1: reconstruction by applying records forwards (vertex split) or backwards (edge collapse);
- §4: storage of base + increments against a static pyramid (``benchmarks/tin.py``).

Deviations, and why:

- **Stable triangle slots.** A triangle keeps its slot (row of the triangle array) for ever; a deleted
  triangle leaves its slot empty instead of shifting later triangles down. The paper's index
  recalculation (§2.2.1, steps 1–4) is then unnecessary, and applying a record is O(its size). The
  base triangles take slots 0 … n_base - 1 (in input order), record r's two re-created triangles
  n_base + 2r and n_base + 2r + 1: the full scale holds the input triangles as a set, in other slots
  (a triple may start at another of its vertices, same orientation).
- **Per-sub-block sequences.** Every collapse touches one sub-block, so each sub-block has its own scale
  S_0 … S_{n_b} and its own records, and the current scale is a vector, one entry per sub-block; an
  integer scale is a position in a global order of all records that refines, one record at a time, the
  sub-block whose current MMQE is the largest (:func:`mmqe_rank`; derived, so files need not store it).
- **MMQE quantised** to 1/256 octave (0.14 % of the SVO length sqrt(MMQE)); monotone stays monotone.
- **Binary format, version 5** (the paper's text scheme stays as an export): a header (magic, version,
  payload length, sha256 of the payload) and one raw LZMA2 stream holding the metadata (JSON) and numpy
  arrays (integers in the narrowest type, byte-shuffled; float arrays column by column as their distinct
  values and the rank changes from one element to the next when that is smaller, the same container as
  the static pyramid of ``benchmarks/tin.py``). Table 1's fields are not stored: a raw record is one vertex
  split (removed vertex u, kept vertex v, the wing x1 where the fan of m moved triangles starts, see
  :func:`terralod.kernels.qem.replay_splits`), coded from geometry by :mod:`terralod.kernels.tincodec`: u
  as its rank among the vertices its sub-block has still to insert, largest vertical distance to the
  current surface first (a per-vertex sub-block label, stored as "the cell holding the vertex" or an
  exception, says which sub-block inserts a vertex), v as a corner (0-2, nearest first) of the current
  triangle holding u's xy, the fan as its triangles before and after that triangle (escape: v and x1 as
  they are), v and the fan's counts ranked by frequency within a geometric context; the base mesh in
  canonical order (each triple from its smallest vertex, rows sorted) as delta rows
  (:func:`encode_mesh_rows`); each block's MMQE and measured-error codes as the first and the drops.
  Loading decodes the splits and replays them from the base once, deriving every field of table 1
  (slots, deleted triples, original and new triples) exactly. Merged records (§2.2.2) are derived in
  memory from the raw ones; a file of a merged model stores the raw splits and the merge factor.
  Versions 1 (slots and triples), 2 (no measured error), 3 (floats not coded by column) and 4 (splits as
  plain indices, deflated per array) are refused with one line naming the file.
- **Measured error per scale** (not in the paper): besides the MMQE, each scale of a sub-block stores an
  upper bound of its max vertical distance to the input points (:func:`terralod.tin.qem.measured_errors`,
  quantised rounding up, stored like the MMQE codes: first + drops), and each sub-block a bounding box;
  scale selection uses them by default (see :mod:`terralod.tin.svo` for why; ``error="mmqe"`` is the
  paper's rule).
"""

from __future__ import annotations

import hashlib
import io
import json
import lzma
import math
import os
import struct
import zlib
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from terralod.errors import CorruptStoreError, InputError, InputNotFoundError
from terralod.kernels.qem import coarsen_records, refine_records, replay_splits
from terralod.kernels.tincodec import V_ESCAPE, split_codes
from terralod.tin.svo import (
    box_distance_m,
    monotone_mmqe,
    projected_px,
    select_scales,
    select_scales_measured,
)

__all__ = [
    "DeltaT",
    "DetailIncrementModel",
    "Increments",
    "read_text",
    "write_text",
]

MAGIC = b"TLODDIM\x00"
#: 5: splits coded from geometry (u's rank in its sub-block, v a corner of the triangle holding u, the
#: fan's offset), base rows delta-coded, one LZMA2 stream; 4: float arrays coded by column (distinct values
#: + rank changes); 3: + measured error per scale; 2: compact vertex-split records; 1: slots and triples
#: (1 to 4 no longer read)
FORMAT_VERSION = 5
_HEADER = struct.Struct("<8sHHIQ32s8x")  # magic, version, flags, reserved, payload length, sha256
_FLAG_LZMA = 2  #: the payload is one raw LZMA2 stream


# -- records ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class DeltaT:
    """One detail increment ΔT_s of one sub-block: what takes scale S_s to S_{s+1} (paper 003 table 1).

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
    return np.maximum(np.nan_to_num(c, nan=MMQE_ZERO_CODE, neginf=MMQE_ZERO_CODE), MMQE_ZERO_CODE).astype(np.int64)


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
    def from_log(cls, log: Any, n_blocks: int, n_vertices: int, error_m: np.ndarray
                 ) -> tuple[Increments, np.ndarray, np.ndarray]:
        """Records from a :class:`terralod.tin.qem.CollapseLog` (collapse order → refinement order).

        ``error_m`` (C,): the measured error of each collapse (:func:`terralod.tin.qem.measured_errors`).

        The log is encoded to the compact vertex splits a file stores and decoded back
        (:meth:`from_compact`), so a model built here is exactly the model its file loads (slots
        included). Returns (increments, base triples (S, 3), base alive (S,)) in the decoded slot order:
        the base triangles first, in their input order.
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
        has_uv = ((d[..., 0] == uu) & (d[..., 1] == vv)) | ((d[..., 1] == uu) & (d[..., 2] == vv)) | (
            (d[..., 2] == uu) & (d[..., 0] == vv)
        )
        third = d.sum(axis=2) - uu - vv
        x1 = np.where(has_uv[:, 0], third[:, 0], third[:, 1])
        # the base in canonical order (each triple from its smallest vertex, rows sorted): the file codes
        # its rows as deltas (:func:`encode_mesh_rows`)
        base_tri = canonical_rows(log.base_tris[log.base_alive])
        mm = np.empty(c + n_blocks, np.float64)
        ee = np.empty(c + n_blocks, np.float64)
        err = np.asarray(error_m, np.float64)
        block_ptr = np.concatenate([[0], np.cumsum(block_records)])
        for b in range(n_blocks):
            lo, hi = block_ptr[b], block_ptr[b + 1]
            mm[lo + b : hi + b + 1] = monotone_mmqe(np.concatenate([log.mmqe_m2[perm[lo:hi]], [log.mmqe0_m2[b]]]))
            ee[lo + b : hi + b + 1] = monotone_mmqe(np.concatenate([err[perm[lo:hi]], [0.0]]))
        return cls.from_compact(n_vertices, base_tri, block_records, u, v, x1, m, quantise_mmqe(mm),
                                quantise_error(ee), source="collapse log")

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
    ) -> tuple[Increments, np.ndarray, np.ndarray]:
        """Raw records from the compact vertex splits (what a file decodes to), by replaying them from the base.

        Parameters
        ----------
        n_vertices : int
        base_tri : (n_base, 3) int, the base triangles (they take slots 0 … n_base - 1).
        block_records : (B,) int, n_b; records are block-major, each block's in refinement order.
        rec_u, rec_v, rec_x1, rec_m : (R,) int, the splits: v splits into v and u, the fan of m triangles
            from the wing vertex x1 moves to u (see :func:`terralod.kernels.qem.replay_splits`).
        mmqe_code : (R + B,) int, quantised monotone MMQE of every block's scales S_0 … S_{n_b}.
        error_code : (R + B,) int, quantised measured error of the same scales (:func:`quantise_error`).

        Returns (increments, base triples (S, 3), base alive (S,)); CorruptStoreError (naming ``source``)
        when the splits do not fit together.
        """
        rec_u, rec_v, rec_x1, rec_m = (np.ascontiguousarray(a, np.int64) for a in (rec_u, rec_v, rec_x1, rec_m))
        rec_w = np.zeros(rec_u.size, np.int64)
        base_tri = np.ascontiguousarray(base_tri, np.int32).reshape(-1, 3)
        status, _, del_tri, rep_ptr, rep_slot, rep_old, rep_new = replay_splits(
            int(n_vertices), base_tri, rec_u, rec_v, rec_x1, rec_w, rec_m, True
        )
        if status != 0:
            where = "base triangles" if status < 0 else f"record {status - 1}"
            raise CorruptStoreError(f"inconsistent detail-increment records: {where} does not fit the mesh", source)
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
        """Merge every k consecutive records of each block into one, compressed (paper 003 §2.2.2).

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
            [np.repeat(np.arange(self.n_records), np.diff(self.del_ptr)),
             np.repeat(np.arange(self.n_records), np.diff(self.rep_ptr))]
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
            gptr, del_ptr, slot[dead], old[dead], rep_ptr, slot[~dead], old[~dead], new[~dead], mm, rank,
            self.step * k, raw=self if self.rec_u is not None else None, error_m=ee,
        )


# -- text export (paper 003 §2.2.2, "external storage scheme") -------------------------------------------
def write_text(inc: Increments, path: str | os.PathLike[str]) -> None:
    """Write the increments in the paper's text scheme.

    Line 1: the number of collapses merged per record (element 1, stored once). Then, per sub-block, a
    comment line ``# block <b> records <n_b>`` and one row per record ΔT_0, ΔT_1, … with, separated by
    spaces: (2) the number of changed triangles d + r; (3) the d deleted slots; (4) the r replaced
    slots; (5) 3·d vertex indices of the deleted triangles; (6) 3·r original and (7) 3·r new vertex
    indices of the replaced triangles. d follows from the row length (4 (d + r) + 3 r numbers).
    """
    with open(path, "w", encoding="ascii") as f:
        f.write(f"{inc.step}\n")
        for b in range(inc.n_blocks):
            f.write(f"# block {b} records {int(inc.block_ptr[b + 1] - inc.block_ptr[b])}\n")
            for r in range(int(inc.block_ptr[b]), int(inc.block_ptr[b + 1])):
                d0, d1 = inc.del_ptr[r], inc.del_ptr[r + 1]
                r0, r1 = inc.rep_ptr[r], inc.rep_ptr[r + 1]
                parts = [
                    np.array([d1 - d0 + r1 - r0]),
                    inc.del_slot[d0:d1],
                    inc.rep_slot[r0:r1],
                    inc.del_tri[d0:d1].ravel(),
                    inc.rep_old[r0:r1].ravel(),
                    inc.rep_new[r0:r1].ravel(),
                ]
                f.write(" ".join(map(str, np.concatenate(parts).tolist())) + "\n")


def read_text(path: str | os.PathLike[str]) -> tuple[int, list[list[DeltaT]]]:
    """Parse :func:`write_text` output: (step, records per block; MMQE is not part of the scheme: NaN)."""
    blocks: list[list[DeltaT]] = []
    with open(path, encoding="ascii") as f:
        step = int(f.readline())
        for line in f:
            if line.startswith("#"):
                blocks.append([])
                continue
            a = np.array(line.split(), np.int64)
            n = int(a[0])
            r = (a.size - 1 - 4 * n) // 3
            d = n - r
            if d < 0 or r < 0 or a.size != 1 + 4 * n + 3 * r:
                raise InputError(f"malformed record row of {a.size} numbers", str(path))
            p = 1
            ds = a[p : p + d]
            p += d
            rs = a[p : p + r]
            p += r
            dv = a[p : p + 3 * d].reshape(-1, 3)
            p += 3 * d
            ro = a[p : p + 3 * r].reshape(-1, 3)
            p += 3 * r
            rn = a[p : p + 3 * r].reshape(-1, 3)
            blk = blocks[-1]
            blk.append(DeltaT(len(blk), math.nan, ds, dv, rs, ro, rn, len(blocks) - 1))
    return step, blocks


# -- binary container ------------------------------------------------------------------------------------
#: The generic entropy coder of format 5: the whole payload after the header is one raw LZMA2 stream (no
#: per-section stream overheads; the static pyramid of ``benchmarks/tin.py`` is coded by the same function).
_LZMA_FILTERS = [{"id": lzma.FILTER_LZMA2, "preset": 9}]


def _pack(raw: bytes) -> bytes:
    return lzma.compress(raw, format=lzma.FORMAT_RAW, filters=_LZMA_FILTERS)


def _unpack(buf: bytes, src: str) -> bytes:
    try:
        return lzma.decompress(buf, format=lzma.FORMAT_RAW, filters=_LZMA_FILTERS)
    except lzma.LZMAError as exc:
        raise CorruptStoreError(f"damaged compressed payload ({exc})", src) from exc


def _narrow(a: np.ndarray) -> np.ndarray:
    """Integers in the narrowest little-endian type holding them."""
    if a.dtype.kind not in "iu" or a.size == 0:
        return a.astype(a.dtype.newbyteorder("<"))
    lo, hi = int(a.min()), int(a.max())
    for t in (np.uint8, np.uint16, np.uint32, np.uint64) if lo >= 0 else (np.int8, np.int16, np.int32, np.int64):
        info = np.iinfo(t)
        if info.min <= lo and hi <= info.max:
            return a.astype(np.dtype(t).newbyteorder("<"))
    return a


_FLOAT_CODED = "coded"  #: stored-dtype tag of a float64 array coded column by column (:func:`_encode_floats`)


def _shuffle(a: np.ndarray) -> bytes:
    """Bytes of ``a`` regrouped by byte position (all first bytes, then all second bytes, …)."""
    raw = a.tobytes()
    if a.dtype.itemsize > 1 and a.size:
        raw = np.frombuffer(raw, np.uint8).reshape(-1, a.dtype.itemsize).T.tobytes()
    return raw


def _unshuffle(raw: bytes, dtype: np.dtype, n: int) -> np.ndarray:
    if dtype.itemsize > 1 and n:
        raw = np.frombuffer(raw, np.uint8).reshape(dtype.itemsize, -1).T.tobytes()
    return np.frombuffer(raw, dtype)


def _zigzag(d: np.ndarray) -> np.ndarray:
    d = np.asarray(d, np.int64)
    return ((d << 1) ^ (d >> 63)).view(np.uint64)


def _unzigzag(z: np.ndarray) -> np.ndarray:
    z = np.asarray(z).astype(np.uint64)
    return (z >> np.uint64(1)).view(np.int64) ^ -(z & np.uint64(1)).view(np.int64)


def encode_mesh_rows(tris: np.ndarray) -> np.ndarray:
    """(K, 3) uint64: triangle rows as (first vertex - previous row's first, second - first, third - first),
    zigzag: a mesh coding for any row order, compact when rows are sorted by their first vertex and
    neighbouring vertices have near indices. The model's base mesh and every mesh of the static pyramid
    (``benchmarks/tin.py``) use it; :func:`decode_mesh_rows` inverts it."""
    t = np.asarray(tris, np.int64).reshape(-1, 3)
    a = t[:, 0]
    return np.ascontiguousarray(np.stack([_zigzag(np.diff(a, prepend=0)), _zigzag(t[:, 1] - a),
                                          _zigzag(t[:, 2] - a)], axis=1))  # fmt: skip


def decode_mesh_rows(rows: np.ndarray) -> np.ndarray:
    """(K, 3) int64 triangles of :func:`encode_mesh_rows` output."""
    d = _unzigzag(np.asarray(rows).reshape(-1, 3))
    a = np.cumsum(d[:, 0])
    return np.stack([a, a + d[:, 1], a + d[:, 2]], axis=1)


def canonical_rows(tris: np.ndarray) -> np.ndarray:
    """(K, 3) int32: each triple turned to start at its smallest vertex (orientation kept), rows sorted."""
    t = np.asarray(tris, np.int64).reshape(-1, 3)
    t = np.take_along_axis(t, (np.argmin(t, axis=1)[:, None] + np.arange(3)) % 3, axis=1)
    return np.ascontiguousarray(t[np.lexsort((t[:, 2], t[:, 1], t[:, 0]))], np.int32)


def _estimate(raw: bytes) -> int:
    """Cheap stand-in for the coded size, to choose between two codings of a float column."""
    return len(zlib.compress(raw, 6))


def _encode_floats(a: np.ndarray) -> bytes:
    """A float64 array (1-D, or 2-D coded column by column) losslessly, each column the smaller of:
    0, its values, shuffled; 1, its sorted distinct values (bit patterns made monotone, then differences)
    and, per element, the change of its rank from the previous element (zigzag), each narrowed and
    shuffled. A grid's heights take few distinct values and change little from one vertex to the next: 1
    halves them; scattered LiDAR coordinates keep 0. The bytes go to the payload's one compressed stream."""
    cols = a.reshape(a.shape[0], -1) if a.ndim else a.reshape(1, 1)
    out = io.BytesIO()
    for j in range(cols.shape[1]):
        c = np.ascontiguousarray(cols[:, j], np.float64)
        plain = _shuffle(c.astype("<f8"))
        best: tuple = (0, [plain])
        if c.size > 64:
            bits = c.view(np.int64)
            mono = bits ^ ((bits >> 63) & np.int64(0x7FFFFFFFFFFFFFFF))  # order of the floats, as integers
            uniq, rank = np.unique(mono, return_inverse=True)
            du = _narrow(_zigzag(np.diff(uniq, prepend=np.int64(0)) if uniq.size else uniq))
            dr = _narrow(_zigzag(np.diff(rank.astype(np.int64).ravel(), prepend=0)))
            parts = [_shuffle(du), _shuffle(dr)]
            if sum(map(_estimate, parts)) + 16 < _estimate(plain):
                best = (1, parts, du.dtype.str, dr.dtype.str, uniq.size)
        out.write(struct.pack("<B", best[0]))
        if best[0] == 1:
            out.write(struct.pack("<Q", best[4]))
            for dt in (best[2], best[3]):
                out.write(struct.pack("<B", len(dt)) + dt.encode())
        for part in best[1]:
            out.write(part)
    return out.getvalue()


def _decode_floats(buf: bytes, shape: tuple[int, ...], src: str) -> np.ndarray:
    n = shape[0] if shape else 1
    k = int(np.prod(shape[1:])) if len(shape) > 1 else 1
    cols = np.empty((n, k), np.float64)
    pos = 0

    def take(m: int) -> bytes:
        nonlocal pos
        if m < 0 or pos + m > len(buf):
            raise CorruptStoreError("truncated float array", src)
        pos += m
        return buf[pos - m : pos]

    for j in range(k):
        (mode,) = struct.unpack("<B", take(1))
        if mode == 0:
            cols[:, j] = _unshuffle(take(8 * n), np.dtype("<f8"), n)
        elif mode == 1:
            (nu,) = struct.unpack("<Q", take(8))
            dts = []
            for _ in range(2):
                (ld,) = struct.unpack("<B", take(1))
                dts.append(np.dtype(take(ld).decode()))
            uniq = np.cumsum(_unzigzag(_unshuffle(take(nu * dts[0].itemsize), dts[0], nu)))
            rank = np.cumsum(_unzigzag(_unshuffle(take(n * dts[1].itemsize), dts[1], n)))
            if n and (rank.min() < 0 or rank.max() >= nu):
                raise CorruptStoreError("inconsistent float array", src)
            mono = uniq[rank]
            cols[:, j] = (mono ^ ((mono >> 63) & np.int64(0x7FFFFFFFFFFFFFFF))).view(np.float64)
        else:
            raise CorruptStoreError(f"unknown float coding {mode}", src)
    if pos != len(buf):
        raise CorruptStoreError("inconsistent float array", src)
    return cols.reshape(shape)


def _array_section(arrays: dict[str, np.ndarray]) -> bytes:
    """Named arrays, uncoded: per array its name, dtype, stored dtype, shape, byte length and bytes
    (integers narrowed and shuffled; large float arrays by :func:`_encode_floats`)."""
    out = io.BytesIO()
    out.write(struct.pack("<I", len(arrays)))
    for name, arr in arrays.items():
        a = np.ascontiguousarray(arr)
        if a.dtype == np.float64 and a.ndim in (1, 2) and a.size > 256:  # small ones: as they are
            stored_str = _FLOAT_CODED
            raw = _encode_floats(a)
        else:
            stored = _narrow(a)
            stored_str = stored.dtype.str
            raw = _shuffle(stored)
        nm = name.encode()
        out.write(struct.pack("<B", len(nm)) + nm)
        for dt in (a.dtype.newbyteorder("<").str, stored_str):
            out.write(struct.pack("<B", len(dt)) + dt.encode())
        out.write(struct.pack("<B", a.ndim) + b"".join(_uvarint(s) for s in a.shape))
        out.write(_uvarint(len(raw)) + raw)
    return out.getvalue()


def _uvarint(x: int) -> bytes:
    """LEB128: 7 bits a byte, low first (array shapes and lengths: mostly 1 to 3 bytes)."""
    out = bytearray()
    x = int(x)
    while True:
        b = x & 0x7F
        x >>= 7
        if x:
            out.append(b | 0x80)
        else:
            out.append(b)
            return bytes(out)


def _encode_arrays(arrays: dict[str, np.ndarray], compress: bool = True) -> bytes:
    """Named arrays as one stream, compressed by the file's entropy coder when ``compress``."""
    raw = _array_section(arrays)
    return _pack(raw) if compress else raw


def _decode_arrays(buf: bytes, compress: bool, src: str) -> dict[str, np.ndarray]:
    return _parse_arrays(_unpack(buf, src) if compress else buf, src)


def _parse_arrays(buf: bytes, src: str) -> dict[str, np.ndarray]:
    view = memoryview(buf)
    pos = 0

    def take(n: int) -> memoryview:
        nonlocal pos
        if n < 0 or pos + n > len(view):
            raise CorruptStoreError("truncated array section", src)
        out = view[pos : pos + n]
        pos += n
        return out

    def varint() -> int:
        x, shift = 0, 0
        while True:
            (b,) = take(1)
            x |= (b & 0x7F) << shift
            if b < 0x80:
                return x
            shift += 7
            if shift > 63:
                raise CorruptStoreError("malformed length", src)

    (count,) = struct.unpack("<I", take(4))
    arrays = {}
    for _ in range(count):
        (ln,) = take(1)
        name = bytes(take(ln)).decode()
        dts = []
        for _ in range(2):
            (ld,) = take(1)
            dts.append(bytes(take(ld)).decode())
        (ndim,) = take(1)
        shape = tuple(varint() for _ in range(ndim))
        raw = bytes(take(varint()))
        if dts[1] == _FLOAT_CODED:
            arrays[name] = _decode_floats(raw, shape, src).astype(np.dtype(dts[0]).newbyteorder("="))
            continue
        stored = np.dtype(dts[1])
        n = int(np.prod(shape))
        if len(raw) != n * stored.itemsize:
            raise CorruptStoreError(f"array {name}: {len(raw)} bytes for shape {shape}", src)
        arrays[name] = _unshuffle(raw, stored, n).reshape(shape).astype(np.dtype(dts[0]).newbyteorder("="))
    return arrays


def write_container(path: str | os.PathLike[str], meta: dict[str, Any], arrays: dict[str, np.ndarray],
                    *, compress: bool = True) -> int:
    """Write ``meta`` (JSON) and named arrays with the checksummed header; returns the file size, bytes.

    The payload (meta + arrays) is one stream, compressed once (:func:`_pack`) when ``compress``. Written
    to ``path + '.tmp'`` then renamed, so an interrupted write never leaves a half file.
    """
    body = json.dumps(meta, sort_keys=True, separators=(",", ":")).encode()
    plain = _uvarint(len(body)) + body + _array_section(arrays)
    payload = _pack(plain) if compress else plain
    head = _HEADER.pack(MAGIC, FORMAT_VERSION, _FLAG_LZMA if compress else 0, 0, len(payload),
                        hashlib.sha256(payload).digest())
    p = Path(path)
    tmp = p.with_name(p.name + ".tmp")
    with open(tmp, "wb") as f:
        f.write(head)
        f.write(payload)
    os.replace(tmp, p)
    return len(head) + len(payload)


def read_container(path: str | os.PathLike[str]) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """Read :func:`write_container` output; CorruptStoreError on a foreign, damaged, older or newer file."""
    p = Path(path)
    src = str(p)
    if not p.exists():
        raise InputNotFoundError("file not found", src)
    data = p.read_bytes()
    if len(data) < _HEADER.size or data[:8] != MAGIC:
        raise CorruptStoreError("not a terralod detail-increment file (bad magic)", src)
    magic, version, flags, _, length, digest = _HEADER.unpack_from(data)
    if version > FORMAT_VERSION:
        raise CorruptStoreError(f"format version {version} is newer than this terralod's ({FORMAT_VERSION})", src)
    if version < FORMAT_VERSION:
        raise CorruptStoreError(
            f"format version {version} is no longer read (this terralod reads {FORMAT_VERSION}): rebuild the model "
            "from its source", src)
    payload = data[_HEADER.size :]
    if len(payload) != length:
        raise CorruptStoreError(f"truncated or padded: payload of {len(payload)} bytes, header says {length}", src)
    if hashlib.sha256(payload).digest() != digest:
        raise CorruptStoreError("checksum mismatch: the file is corrupted", src)
    plain = _unpack(payload, src) if flags & _FLAG_LZMA else payload
    view = memoryview(plain)
    lm, shift, pos = 0, 0, 0
    while pos < len(view):
        b = view[pos]
        pos += 1
        lm |= (b & 0x7F) << shift
        shift += 7
        if b < 0x80:
            break
    try:
        meta = json.loads(bytes(view[pos : pos + lm]).decode())
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CorruptStoreError(f"unreadable metadata ({exc})", src) from exc
    arrays = _parse_arrays(bytes(view[pos + lm :]), src)
    return meta, arrays


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


# -- the model -------------------------------------------------------------------------------------------
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

        Raises
        ------
        InputError
            Bad shape, NaN/inf coordinates, fewer than 3 distinct points, collinear points, bad options.
        """
        from terralod.tin.delaunay import blocks_per_side, delaunay_tin
        from terralod.tin.pointcloud import check_points, thin_duplicates

        pts = check_points(xyz_m, source if source != "<points>" else None)
        keep = thin_duplicates(pts, dedup_tol_m)
        extra = []
        if keep.size < pts.shape[0]:
            extra.append(f"thinned {pts.shape[0] - keep.size} duplicate point(s) within {dedup_tol_m} m")
        src = None if source == "<points>" else source
        k = blocks_per_side(_auto_sub_blocks(keep.size) if sub_blocks == "auto" else sub_blocks)  # type: ignore[arg-type]
        vertices, tris, _ = delaunay_tin(pts[keep], source=src)
        return cls._build(vertices, tris, k, base_fraction, source, crs, (*notes, *extra))

    @classmethod
    def from_las(
        cls,
        path: str | os.PathLike[str],
        *,
        sub_blocks: int | str = 4,
        base_fraction: float = 0.2,
        dedup_tol_m: float = 0.01,
        ground_only: bool | None = None,
        units: str | float | None = None,
    ) -> DetailIncrementModel:
        """:meth:`from_points` of a LAS/LAZ file's points (ground only when classified, metres).

        See :func:`terralod.tin.pointcloud.read_las` for ``ground_only`` and ``units``.
        """
        from terralod.tin.pointcloud import read_las

        pc = read_las(path, ground_only=ground_only, units=units)
        return cls.from_points(
            pc.xyz_m, sub_blocks=sub_blocks, base_fraction=base_fraction, dedup_tol_m=dedup_tol_m,
            source=pc.source, crs=pc.crs, notes=pc.notes,
        )

    @classmethod
    def from_heightfield(
        cls, hf: Any, *, sub_blocks: int | str = 4, base_fraction: float = 0.2
    ) -> DetailIncrementModel:
        """The grid TIN of a :class:`terralod.Heightfield`'s valid samples (world metres), as a model."""
        from terralod.tin.delaunay import blocks_per_side, grid_tin

        h, w = hf.shape
        xs, _ = hf.world_xy(np.zeros(w), np.arange(w))
        _, ys = hf.world_xy(np.arange(h), np.zeros(h))
        vertices, tris, _ = grid_tin(hf.elevation_m, hf.valid, xs, ys)
        k = blocks_per_side(_auto_sub_blocks(vertices.shape[0]) if sub_blocks == "auto" else sub_blocks)  # type: ignore[arg-type]
        return cls._build(vertices, tris, k, base_fraction, hf.source, hf.crs, tuple(getattr(hf, "notes", ())))

    @classmethod
    def _build(cls, vertices, tris, k, base_fraction, source, crs, notes) -> DetailIncrementModel:
        from terralod.tin.delaunay import split_sub_blocks
        from terralod.tin.qem import measured_errors, simplify

        sb = split_sub_blocks(vertices, tris, k)
        log = simplify(vertices, tris, sb.kind, sb.tri_block, sb.vert_block, base_fraction=base_fraction,
                       n_blocks=sb.n_blocks)
        err = measured_errors(vertices, tris, log)
        inc, base_tris, base_alive = Increments.from_log(log, sb.n_blocks, vertices.shape[0], err)
        # a box around each block's triangles: every scale's surface lies inside it
        t = np.asarray(tris, np.int64).ravel()
        tb = np.repeat(sb.tri_block.astype(np.int64), 3)
        lo = np.repeat(vertices.min(axis=0)[None, :], sb.n_blocks, axis=0) if t.size else np.zeros((sb.n_blocks, 3))
        hi = lo.copy()
        has = np.bincount(tb, minlength=sb.n_blocks) > 0
        lo[has], hi[has] = np.inf, -np.inf
        np.minimum.at(lo, tb, vertices[t])
        np.maximum.at(hi, tb, vertices[t])
        model = cls(vertices, base_tris, base_alive, inc, k, sb.centre_m, sb.bounds_m,
                    source=str(source), crs=crs, notes=notes, block_boxes_m=np.concatenate([lo, hi], axis=1))
        # the input TIN, kept for checks: the full scale holds the same triangles (in other slots, a
        # triple possibly rotated)
        model._full_tris = np.ascontiguousarray(tris, np.int32)
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
        if isinstance(scale, bool) or not isinstance(scale, int | np.integer) or not 0 <= scale < self.n_scales:
            raise ValueError(f"Expected a scale in [0, {self.n_scales}), got {scale!r}")
        inc = self.increments
        return np.bincount(inc.record_block[inc.order[: int(scale)]], minlength=self.n_blocks).astype(np.int64)

    def set_block_scales(self, scales: Sequence[int] | np.ndarray) -> None:
        """Move each sub-block to its scale by applying (or reverting) its increments (eq. 2)."""
        s = np.asarray(scales, np.int64)
        nmax = self.increments.block_n_records()
        if s.shape != (self.n_blocks,):
            raise ValueError(f"Expected {self.n_blocks} per-block scales, got shape {s.shape}")
        if (s < 0).any() or (s > nmax).any():
            raise ValueError(f"Expected per-block scales in [0, n_b], n_b = {nmax.tolist()}, got {s.tolist()}")
        inc = self.increments
        for b in np.flatnonzero(s != self._scales):
            cur, tgt, base = int(self._scales[b]), int(s[b]), int(inc.block_ptr[b])
            if tgt > cur:
                refine_records(self._tris, self._alive, base + cur, base + tgt, inc.del_ptr, inc.del_slot,
                               inc.del_tri, inc.rep_ptr, inc.rep_slot, inc.rep_old)
            else:
                coarsen_records(self._tris, self._alive, base + tgt, base + cur, inc.del_ptr, inc.del_slot,
                                inc.rep_ptr, inc.rep_slot, inc.rep_new)
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

    def mesh_at(self, scale: int | Sequence[int] | np.ndarray, *, compact: bool = False
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

    def _camera(self, eye_m: Sequence[float] | np.ndarray, fov_y_deg: float, height_px: float,
                threshold_px: float, error: str) -> tuple[np.ndarray, np.ndarray]:
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

    def scales_for_camera(self, eye_m: Sequence[float] | np.ndarray, fov_y_deg: float, height_px: float,
                          threshold_px: float = 2.0, *, error: str = "measured") -> np.ndarray:
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

    def projected_error_px(self, eye_m: Sequence[float] | np.ndarray, fov_y_deg: float, height_px: float,
                           scales: np.ndarray | None = None, *, error: str = "measured") -> np.ndarray:
        """(B,) each sub-block's error at ``scales`` (default: its current scale) projected to the screen,
        pixels, by the rule of ``error`` (see :meth:`scales_for_camera`)."""
        _, d = self._camera(eye_m, fov_y_deg, height_px, 1.0, error)
        inc = self.increments
        s = self._scales if scales is None else np.asarray(scales, np.int64)
        if error == "measured":
            return projected_px(inc.error_m[inc.mmqe_ptr[:-1] + s], d, math.radians(fov_y_deg), float(height_px))
        return projected_px(np.sqrt(inc.mmqe_m2[inc.mmqe_ptr[:-1] + s]), d, math.radians(fov_y_deg),
                            float(height_px))  # fmt: skip

    def mesh_for_camera(self, eye_m: Sequence[float] | np.ndarray, fov_y_deg: float, height_px: float,
                        threshold_px: float = 2.0, *, compact: bool = False, error: str = "measured"
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
        """ΔT_0, ΔT_1, … of a sub-block (paper 003 table 1)."""
        return self.increments.records(block)

    # -- compression -------------------------------------------------------------------------------------
    def compressed(self, k: int) -> DetailIncrementModel:
        """A model whose records each merge k consecutive records (paper 003 §2.2.2), starting at the base.

        Its sub-block scales are this model's S_0, S_k, S_2k, …, S_{n_b}.
        """
        m = DetailIncrementModel(self.vertices_m, self._base_tris, self._base_alive, self.increments.merged(k),
                                 self.k, self.block_centres_m, self.block_bounds_m, source=self.source,
                                 crs=self.crs, notes=self.notes, block_boxes_m=self.block_boxes_m)
        m._full_tris = self._full_tris
        return m

    # -- files -------------------------------------------------------------------------------------------
    def _payload(self) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
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
        n_rec = raw.n_records
        rec_u = raw.rec_u.astype(np.int64)
        rec_m = np.diff(raw.rep_ptr)
        label = np.full(self.vertices_m.shape[0], nb, np.int64)
        label[rec_u] = raw.record_block
        vpos, vat, lo, hi = _insert_order(label, nb)
        # a vertex out of the base is mostly inserted by the sub-block whose cell holds it: 0, else label + 1
        out = np.ones(label.size, np.bool_)
        out[self._base_tris[:n_base].ravel()] = False
        cell = _block_cells(self.vertices_m, self.k)[out]
        label_escape = np.where(label[out] == cell, 0, label[out] + 1)
        sym = [np.zeros(n_rec, np.int64) for _ in range(6)]
        status, n_esc = split_codes(True, _grid_xy(self.vertices_m), self.vertices_m[:, 2].copy(), label,
                                    self._base_tris[:n_base], raw.block_ptr, vpos, vat, lo, hi, rec_u,
                                    raw.rec_v.astype(np.int64),
                                    raw.del_tri[0::2, 2].astype(np.int64), rec_m, *sym)  # fmt: skip
        if status != 0:
            raise RuntimeError(f"vertex splits do not code (record {status - 1})")
        sym_u, sym_v, sym_j, after, esc_v, esc_x = sym
        meta = {
            "format": "terralod detail-increment model (paper 003)",
            "k": self.k,
            "n_slots": self.n_slots,
            "step": inc.step,
            "source": self.source,
            "crs": self.crs,
            "notes": list(self.notes),
            "units": "metres; x east, y north, z up",
        }
        arrays = {
            "vertices_m": self.vertices_m,
            "base_rows": encode_mesh_rows(self._base_tris[:n_base]),
            "block_centres_m": self.block_centres_m,
            "block_bounds_m": self.block_bounds_m,
            "block_boxes_m": self.block_boxes_m,
            "block_records": np.diff(raw.block_ptr),
            "vertex_block_escape": label_escape,
            "split_u": sym_u,
            "split_v": sym_v,
            "split_j": sym_j,
            "split_after": after,
            "escape_v": esc_v[:n_esc],
            "escape_x1": esc_x[:n_esc],
            "mmqe_first": first,
            "mmqe_drop": drop,
            "error_first": ecode[raw.mmqe_ptr[:-1]],
            "error_drop": edrop,
        }
        return meta, arrays

    def save(self, path: str | os.PathLike[str], *, compress: bool = True) -> int:
        """Write the model (base mesh + increments + MMQE) to one checksummed file; returns its size, bytes."""
        meta, arrays = self._payload()
        return write_container(path, meta, arrays, compress=compress)

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
            raise CorruptStoreError("inconsistent detail-increment records: base triangles do not fit the mesh", src)
        out = np.ones(v.shape[0], np.bool_)
        out[base_tri.ravel()] = False
        label = np.full(v.shape[0], nb, np.int64)
        if lab_esc.size != int(out.sum()):
            raise CorruptStoreError("inconsistent detail-increment file: vertex blocks", src)
        label[out] = np.where(lab_esc == 0, _block_cells(v, k)[out], lab_esc - 1)
        if not np.array_equal(np.bincount(label, minlength=nb + 1)[:nb], br):
            raise CorruptStoreError("inconsistent detail-increment file: vertex blocks", src)
        sym_u, sym_v, sym_j, after = (a[n].astype(np.int64) for n in ("split_u", "split_v", "split_j", "split_after"))
        rec_u, rec_v, rec_x, rec_m = (np.zeros(n_rec, np.int64) for _ in range(4))
        vpos, vat, lo, hi = _insert_order(label, nb)
        status, _ = split_codes(False, _grid_xy(v), v[:, 2].copy(), label, base_tri.astype(np.int32), bptr, vpos, vat,
                                lo, hi, rec_u, rec_v,
                                rec_x, rec_m, sym_u, sym_v, sym_j, after, a["escape_v"].astype(np.int64),
                                a["escape_x1"].astype(np.int64))  # fmt: skip
        if status != 0:
            where = "base triangles" if status < 0 else f"record {max(status, 1) - 1}"
            raise CorruptStoreError(f"inconsistent detail-increment records: {where} does not fit the mesh", src)
        inc, base_tris, base_alive = Increments.from_compact(
            v.shape[0], base_tri, br, rec_u, rec_v, rec_x, rec_m, codes(a["mmqe_first"], a["mmqe_drop"]),
            codes(a["error_first"], a["error_drop"]), source=src,
        )
        if step > 1:
            inc = inc.merged(step)
        m = cls(v, base_tris, base_alive, inc, k, a["block_centres_m"], a["block_bounds_m"],
                source=str(meta.get("source", src)), crs=meta.get("crs"), notes=meta.get("notes", ()),
                block_boxes_m=a["block_boxes_m"])
        return m
