"""Detail-increment replay (numba kernels): applying ΔT records and replaying compact vertex splits.

Paper: ``../shared/papers/003_2a2cfcda929de24c.txt`` §2.2.1 (one record per collapse: deleted triangles
with their vertex indices, replaced triangles with original and new vertex indices; here derived from a
compact vertex split, :func:`replay_splits`) and §2.3.1 (reconstruction by applying records forwards,
:func:`refine_records`, or backwards, :func:`coarsen_records`). Pure functions on arrays: no I/O, no
exceptions; validation and frames live in :mod:`terralod.tin.records` and :mod:`terralod.tin.increments`.

The collapses that produce the records (quadrics, heap, link test) are in :mod:`terralod.kernels.qem`,
whose vocabulary (slot, star(v) arena) this module shares and whose star-list helpers it imports (one way:
:mod:`terralod.kernels.qem` never imports this module).
"""

from __future__ import annotations

import numpy as np

from terralod.kernels import jit
from terralod.kernels.qem import _empty_arena, _next_after, _set_row, _star_add, _star_remove


# -- detail-increment replay (Ai et al. (2019) §2.3.1) ----------------------------------------------------------
@jit
def refine_records(tris, alive, r0, r1, del_ptr, del_slot, del_tri, rep_ptr, rep_slot, rep_old):
    """Vertex splits: apply records r0, r0+1, …, r1-1 (refinement order) to the state (tris, alive).

    Deleted slots come back with their stored triple, replaced slots get their original triple.
    """
    for r in range(r0, r1):
        for i in range(del_ptr[r], del_ptr[r + 1]):
            s = del_slot[i]
            _set_row(tris, s, del_tri, i)
            alive[s] = True
        for i in range(rep_ptr[r], rep_ptr[r + 1]):
            _set_row(tris, rep_slot[i], rep_old, i)


@jit
def coarsen_records(tris, alive, r0, r1, del_ptr, del_slot, rep_ptr, rep_slot, rep_new):
    """Edge collapses: revert records r1-1, r1-2, …, r0 (the inverse of :func:`refine_records`)."""
    for r in range(r1 - 1, r0 - 1, -1):
        for i in range(del_ptr[r], del_ptr[r + 1]):
            alive[del_slot[i]] = False
        for i in range(rep_ptr[r], rep_ptr[r + 1]):
            _set_row(tris, rep_slot[i], rep_new, i)


# -- vertex-split records (Ai et al. (2019) §2.2.1, compact file layout) ------------------------------------------
@jit
def replay_splits(n_vertices, base_tri, rec_u, rec_v, rec_x, rec_w, rec_m, encode):
    r"""Vertex splits from the compact records, replayed from the base: every record's full table-1 fields.

    Record r (refinement order) splits kept vertex ``v = rec_v[r]`` into v and the removed vertex
    ``u = rec_u[r]``; the wing vertices x1 and x_m delimit the fan of v's triangles that moves to u::

        coarse (after the collapse u -> v)       fine (after the split)
              x3 ------ x2                          x3 ------ x2
             /  \      /  \                        /  \      /  \
          x_m -- v ------ x1         ──▶        x_m -- u ------ x1
                 (v's other triangles)                \  |  /
                                                        v  (v's other triangles below)

    The fan (v, x1, x2) … (v, x_{m-1}, x_m) gets u in place of v, and the two triangles of the collapsed
    edge, (u, v, x1) and (u, x_m, v), come back (every triple counter-clockwise).
    x1 is stored as ``rec_w[r]``, its rank among v's neighbours sorted by vertex index (one byte), and m
    as ``rec_m[r]``, the number of triangles that move. ``encode``: x1 is given in ``rec_x`` and its rank
    is written to ``rec_w``; otherwise x1 is read from the rank.

    Slots: the base triangles take slots 0 … n_base-1 (in the given order); record r's two new triangles
    take n_base + 2r and n_base + 2r + 1. A moved triangle keeps its slot.

    Returns
    -------
    status, tris, del_tri, rep_ptr, rep_slot, rep_old, rep_new
        status 0, or r + 1 for the first record that does not fit the mesh (corrupt input); tris (S, 3)
        the full-resolution state; record r re-creates slots n_base + 2r, +1 with triples
        ``del_tri[2r : 2r+2]`` and gives the moved slots ``rep_slot[rep_ptr[r] : rep_ptr[r+1]]`` their
        finer triple ``rep_old`` (u in place of v) instead of their coarser one ``rep_new``.
    """
    n_rec = rec_u.shape[0]
    n_base = base_tri.shape[0]
    n_slots = n_base + 2 * n_rec
    tris = np.zeros((n_slots, 3), np.int32)
    del_tri = np.zeros((2 * n_rec, 3), np.int32)
    rep_ptr = np.zeros(n_rec + 1, np.int64)
    for r in range(n_rec):
        rep_ptr[r + 1] = rep_ptr[r] + max(rec_m[r], 0)
    n_rep = rep_ptr[n_rec]
    rep_slot = np.zeros(n_rep, np.int32)
    rep_old = np.zeros((n_rep, 3), np.int32)
    rep_new = np.zeros((n_rep, 3), np.int32)
    present = np.zeros(n_vertices, np.bool_)
    deg = np.zeros(n_vertices, np.int64)
    for t in range(n_base):
        for k in range(3):
            w = base_tri[t, k]
            if w < 0 or w >= n_vertices:
                return -1, tris, del_tri, rep_ptr, rep_slot, rep_old, rep_new
            tris[t, k] = w
            deg[w] += 1
            present[w] = True
    arena, start, length, cap, top = _empty_arena(deg, 6)
    for t in range(n_base):
        for k in range(3):
            w = tris[t, k]
            arena[start[w] + length[w]] = t
            length[w] += 1
    nbr = np.empty(64, np.int64)
    for r in range(n_rec):
        u = rec_u[r]
        v = rec_v[r]
        m = rec_m[r]
        if u < 0 or u >= n_vertices or v < 0 or v >= n_vertices or present[u] or not present[v] or m < 1:
            return r + 1, tris, del_tri, rep_ptr, rep_slot, rep_old, rep_new
        # v's neighbours, sorted by index, without repeats (insertion sort: a ring is small)
        sv = start[v]
        nv = length[v]
        if 2 * nv > nbr.shape[0]:
            nbr = np.empty(4 * nv, np.int64)
        nn = 0
        for i in range(nv):
            t = arena[sv + i]
            a = _next_after(tris, t, v)
            b = _next_after(tris, t, a)
            for x in (a, b):
                j = nn
                while j > 0 and nbr[j - 1] > x:
                    j -= 1
                if j > 0 and nbr[j - 1] == x:
                    continue
                for q in range(nn, j, -1):
                    nbr[q] = nbr[q - 1]
                nbr[j] = x
                nn += 1
        if encode:
            x1 = rec_x[r]
            w = -1
            for j in range(nn):
                if nbr[j] == x1:
                    w = j
            if w < 0:
                return r + 1, tris, del_tri, rep_ptr, rep_slot, rep_old, rep_new
            rec_w[r] = w
        else:
            w = rec_w[r]
            if w < 0 or w >= nn:
                return r + 1, tris, del_tri, rep_ptr, rep_slot, rep_old, rep_new
            x1 = nbr[w]
        # walk the fan (v, x1, x2) … (v, x_{m-1}, x_m) counter-clockwise, giving each triangle u for v
        x = x1
        for j in range(m):
            found = -1
            sv = start[v]
            for i in range(length[v]):
                t = arena[sv + i]
                if _next_after(tris, t, v) == x:
                    found = t
                    break
            if found < 0:
                return r + 1, tris, del_tri, rep_ptr, rep_slot, rep_old, rep_new
            q = rep_ptr[r] + j
            rep_slot[q] = found
            for k in range(3):
                rep_new[q, k] = tris[found, k]
                if tris[found, k] == v:
                    tris[found, k] = u
                rep_old[q, k] = tris[found, k]
            x = _next_after(tris, found, x)  # found is now (u, x_j, x_{j+1}): go on from x_{j+1}
            _star_remove(arena, start, length, v, found)
            arena, top = _star_add(arena, start, length, cap, top, u, found)
        xm = x
        if xm == x1 or xm == v:
            return r + 1, tris, del_tri, rep_ptr, rep_slot, rep_old, rep_new
        # the two triangles of the collapsed edge come back
        s1 = n_base + 2 * r
        s2 = s1 + 1
        tris[s1, 0] = u
        tris[s1, 1] = v
        tris[s1, 2] = x1
        tris[s2, 0] = u
        tris[s2, 1] = xm
        tris[s2, 2] = v
        for k in range(3):
            del_tri[2 * r, k] = tris[s1, k]
            del_tri[2 * r + 1, k] = tris[s2, k]
            arena, top = _star_add(arena, start, length, cap, top, tris[s1, k], s1)
            arena, top = _star_add(arena, start, length, cap, top, tris[s2, k], s2)
        present[u] = True
    return 0, tris, del_tri, rep_ptr, rep_slot, rep_old, rep_new


@jit
def halving_rungs(err):  # pragma: no cover - numba
    """(K,) int64 scales of a sub-block whose errors ``err`` (by scale, base first) halve: 0, then each first
    scale at or below half the previous rung's error, and the last scale; after a rung of error 0 only the
    last follows (see :meth:`terralod.terrain.TinTerrain.ladder`)."""
    n = err.shape[0]
    out = np.empty(max(n, 1), np.int64)
    out[0] = 0
    k = 1
    last = 0
    for s in range(1, n):
        if s == n - 1 or (err[last] > 0.0 and err[s] <= 0.5 * err[last]):
            out[k] = s
            k += 1
            last = s
    return out[:k]
