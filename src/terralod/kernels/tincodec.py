"""Detail-increment file coding kernels: vertex splits as small, predictable symbols (format 5).

Paper: ``../shared/papers/003_2a2cfcda929de24c.txt`` §2.2.2 and §4 (the increments stored compactly, against
a static pyramid). Pure functions on arrays: no I/O, no exceptions; the file layout, validation and the
generic entropy coder live in :mod:`terralod.tin.increments`.

A raw record splits kept vertex v into v and the removed vertex u, moving the fan (v, x1, x2) …
(v, x_m, x_{m+1}) of v's triangles to u (see :func:`terralod.kernels.qem.replay_splits`). Every vertex's
position is in the file before the records, so the coder predicts from geometry (the deviations from the
paper's table 1 are in :mod:`terralod.tin.increments`)::

    u   its rank among the vertices its sub-block has still to insert (a label per vertex says which
        sub-block inserts it), ordered by their vertical distance to the current surface, largest first
        (half-octave buckets, ties in insertion order): refinement puts back the vertices the coarse
        surface misses most, so ranks are small (the Puget crop: 11.1 bits a record, 12.1 by index);
    v   u lies in the fan's region, so the current triangle T that holds u's xy (the slot u is filed in,
        else a walk from a nearby slot) has v as a corner: v is T's corner 0, 1 or 2 by distance to u
        (nearest first), 3 = escape (v and x1 stored as they are);
    x1, m  T is one of the m moved triangles: j, the number of fan triangles before T (counter-clockwise
        order), gives x1, and the number after T gives m.

v, j and the number after are sent as their rank by frequency so far within a context (adaptive, the
same on both sides): for v, which corner faces the edge nearest u and whether u lies on it; for j and
the number after, how many ring vertices in that direction lie on u's side of v. The Puget crop: v 1.4
bits, j + after 3.1 bits a record (1.7 and 3.7 without the contexts).

Coordinates are integers (xy scaled to [0, 2^26]) so the walk's orientation tests are exact and the
encoder and decoder take the same path on every machine; an error's bucket comes from ``frexp`` and one
comparison, not from a libm logarithm. Each candidate (vertex still to insert) sits in the list of the
slot holding its xy; a split re-files the candidates of the slots it moved among its m + 2 triangles.
Per bucket, a Fenwick tree over chunks of the insertion order counts candidates (N_BUCKETS / CHUNK
counters a vertex).
"""

from __future__ import annotations

import math

import numpy as np

from terralod.kernels import jit

#: v's symbol when it is not a corner of the triangle holding u (or T is not in the fan): stored raw
V_ESCAPE = 3


@jit
def _after(tris, t, w):
    """The vertex after ``w`` in triangle ``t`` (counter-clockwise); -1 when ``w`` is not in it."""
    for k in range(3):
        if tris[t, k] == w:
            return tris[t, (k + 1) % 3]
    return -1


@jit
def _star_add(head, nxt, node_tri, free, w, t):
    """Push slot ``t`` on vertex ``w``'s star list; returns the new free-list head."""
    n = free
    free = nxt[n]
    node_tri[n] = t
    nxt[n] = head[w]
    head[w] = n
    return free


@jit
def _star_remove(head, nxt, node_tri, free, w, t):
    """Unlink slot ``t`` from vertex ``w``'s star list; returns the new free-list head."""
    prev = -1
    n = head[w]
    while n >= 0:
        if node_tri[n] == t:
            if prev < 0:
                head[w] = nxt[n]
            else:
                nxt[prev] = nxt[n]
            nxt[n] = free
            return n
        prev = n
        n = nxt[n]
    return free


@jit
def _edge_tri(tris, head, nxt, node_tri, a, b):
    """The live slot holding the directed edge a -> b, or -1."""
    n = head[a]
    while n >= 0:
        t = node_tri[n]
        if _after(tris, t, a) == b:
            return t
        n = nxt[n]
    return -1


@jit
def _orient(qxy, a, b, px, py):
    """Twice the signed area of (a, b, p), exact (integer coordinates below 2^26)."""
    return (qxy[b, 0] - qxy[a, 0]) * (py - qxy[a, 1]) - (qxy[b, 1] - qxy[a, 1]) * (px - qxy[a, 0])


@jit
def _walk(tris, head, nxt, node_tri, qxy, t, px, py, max_steps):
    """Slot of the triangle holding (px, py), walking from slot ``t`` across the edge p lies beyond (the
    edge tried first turns with a fixed pseudo-random sequence, so the walk cannot cycle for ever); -1 when
    it leaves the mesh or takes more than ``max_steps``."""
    seed = np.uint32(12345)
    for _ in range(max_steps):
        seed = seed * np.uint32(1103515245) + np.uint32(12345)
        e0 = np.int64((seed >> np.uint32(16)) % np.uint32(3))
        moved = False
        for kk in range(3):
            e = (e0 + kk) % 3
            a = tris[t, e]
            b = tris[t, (e + 1) % 3]
            if _orient(qxy, a, b, px, py) < 0:
                n = _edge_tri(tris, head, nxt, node_tri, b, a)
                if n < 0:
                    return -1
                t = n
                moved = True
                break
        if not moved:
            return t
    return -1


@jit
def _fen_add(tree, i, d):
    i += 1
    while i < tree.size:
        tree[i] += d
        i += i & -i


@jit
def _fen_sum(tree, i):
    """Sum of positions [0, i)."""
    s = 0
    while i > 0:
        s += tree[i]
        i -= i & -i
    return s


@jit
def _fen_find(tree, k):
    """Position of the (k+1)-th one (k >= 0); tree.size - 1 when there are not that many."""
    n = tree.size - 1
    step = 1
    while step * 2 <= n:
        step *= 2
    pos = 0
    while step > 0:
        if pos + step <= n and tree[pos + step] <= k:
            pos += step
            k -= tree[pos]
        step //= 2
    return pos


#: fan symbols: values below FAN_VALUES are sent as their rank by frequency so far in their context (one
#: of FAN_CONTEXTS), larger ones as they are
FAN_VALUES = 16
FAN_CONTEXTS = 8


@jit
def _side_run(tris, head, nxt, node_tri, qxy, t, v, dx, dy, back):
    """Context of a fan offset: how many triangles around v, from slot t, clockwise (``back``) or
    counter-clockwise, reach a ring vertex on u's side of v (positive dot product with (dx, dy))."""
    c = 0
    while c < FAN_CONTEXTS - 1:
        a = _after(tris, t, v) if back else _after(tris, t, _after(tris, t, v))
        if (qxy[a, 0] - qxy[v, 0]) * dx + (qxy[a, 1] - qxy[v, 1]) * dy <= 0:
            break
        t2 = (
            _edge_tri(tris, head, nxt, node_tri, a, v) if back else _edge_tri(tris, head, nxt, node_tri, v, a)
        )
        if t2 < 0:
            break
        t = t2
        c += 1
    return c


@jit
def _ranked(n_ctx, n_values):
    """Counts of ``n_values`` symbols in ``n_ctx`` contexts, none seen yet: (counts, order, pos), ``order[c]``
    the values most frequent first (ties by value) and ``pos[c]`` its inverse, kept so by :func:`_seen`."""
    counts = np.zeros((n_ctx, n_values), np.int64)
    order = np.empty((n_ctx, n_values), np.int64)
    pos = np.empty((n_ctx, n_values), np.int64)
    for c in range(n_ctx):
        for w in range(n_values):
            order[c, w] = w
            pos[c, w] = w
    return counts, order, pos


@jit
def _seen(counts, order, pos, ctx, value):
    """Count ``value`` once more in ``ctx`` (values from counts.shape[1] on are not counted): it moves
    ahead of every value now less frequent, or as frequent and larger."""
    if value < 0 or value >= counts.shape[1]:
        return
    counts[ctx, value] += 1
    c = counts[ctx, value]
    i = pos[ctx, value]
    while i > 0:
        w = order[ctx, i - 1]
        if counts[ctx, w] > c or (counts[ctx, w] == c and w < value):
            break
        order[ctx, i] = w
        pos[ctx, w] = i
        i -= 1
    order[ctx, i] = value
    pos[ctx, value] = i


@jit
def _to_rank(pos, ctx, value):
    """Rank of ``value`` in context ``ctx``: most frequent so far first, ties by value (values from
    pos.shape[1] on are their own rank)."""
    if value >= pos.shape[1]:
        return value
    return pos[ctx, value]


@jit
def _from_rank(order, ctx, rank):
    """Inverse of :func:`_to_rank` (-1 for a negative rank)."""
    if rank < 0:
        return -1
    if rank >= order.shape[1]:
        return rank
    return order[ctx, rank]


#: error buckets: 0 for errors below 2^-16 m, then two a octave (1 … 63)
N_BUCKETS = 64
_SQRT_HALF = 0.7071067811865476


@jit
def _bucket(e):
    """Half-octave bucket of a vertical error e >= 0, metres (exact: frexp and one comparison)."""
    if not e >= 2.0**-16:
        return 0
    mant, ex = math.frexp(e)  # e = mant * 2^ex, mant in [0.5, 1)
    k = 2 * (ex + 15) + (1 if mant >= _SQRT_HALF else 0)
    return min(max(k, 1), N_BUCKETS - 1)


@jit
def _bary(qxy, tris, t, px, py):
    """Twice the areas opposite each corner of slot t for point p, and twice t's area (exact integers)."""
    a = tris[t, 0]
    b = tris[t, 1]
    c = tris[t, 2]
    wa = _orient(qxy, b, c, px, py)
    wb = _orient(qxy, c, a, px, py)
    wc = _orient(qxy, a, b, px, py)
    return wa, wb, wc, wa + wb + wc


@jit
def _error_bucket(qxy, z, tris, t, w):
    """Bucket of vertex w's vertical distance to slot t's plane (0 when t is degenerate)."""
    wa, wb, wc, det = _bary(qxy, tris, t, qxy[w, 0], qxy[w, 1])
    if det <= 0:
        return 0
    zp = (z[tris[t, 0]] * float(wa) + z[tris[t, 1]] * float(wb) + z[tris[t, 2]] * float(wc)) / float(det)
    return _bucket(abs(z[w] - zp))


#: the most star-list nodes (3 a triangle slot) the replay's int32 links address: a model of up to about
#: 715 M triangle slots (some 350 M vertices); half the bytes of int64 links, in the cache twice as often
MAX_NODES = 2**31 - 2

#: positions per chunk of the per-bucket counts (memory: N_BUCKETS / CHUNK counters a vertex)
CHUNK = 64


@jit
def _set_bucket(fen, cnt, label, vpos, cbucket, pbucket, w, k):
    """Move candidate w to bucket k (-1: out of every bucket); ``pbucket`` is ``cbucket`` by insertion
    position (what the chunk scans read: one cache line for 64 positions, where ``cbucket[vat[p]]`` missed
    the cache at every position)."""
    old = cbucket[w]
    if old == k:
        return
    if old >= 0:
        _fen_add(fen[old], vpos[w] // CHUNK, -1)
        cnt[label[w], old] -= 1
    if k >= 0:
        _fen_add(fen[k], vpos[w] // CHUNK, 1)
        cnt[label[w], k] += 1
    cbucket[w] = k
    pbucket[vpos[w]] = k


@jit
def _bucket_below(fen, pbucket, k, x):
    """Candidates in bucket k at insertion positions below x: whole chunks from the tree, the rest counted."""
    c = x // CHUNK
    n = _fen_sum(fen[k], c)
    for p in range(c * CHUNK, x):
        if pbucket[p] == k:
            n += 1
    return n


@jit
def _bucket_find(fen, pbucket, k, i):
    """Insertion position of the (i+1)-th candidate of bucket k (i >= 0); -1 when there is none."""
    c = _fen_find(fen[k], i)
    if c >= fen.shape[1] - 1:
        return -1
    i -= _fen_sum(fen[k], c)
    for p in range(c * CHUNK, min((c + 1) * CHUNK, pbucket.shape[0])):
        if pbucket[p] == k:
            if i == 0:
                return p
            i -= 1
    return -1


@jit
def _link(slot_head, cnext, cprev, cand_slot, t, w):
    cand_slot[w] = t
    cprev[w] = -1
    cnext[w] = slot_head[t]
    if slot_head[t] >= 0:
        cprev[slot_head[t]] = w
    slot_head[t] = w


@jit
def _unlink(slot_head, cnext, cprev, cand_slot, w):
    t = cand_slot[w]
    if t < 0:
        return
    if cprev[w] >= 0:
        cnext[cprev[w]] = cnext[w]
    else:
        slot_head[t] = cnext[w]
    if cnext[w] >= 0:
        cprev[cnext[w]] = cprev[w]
    cand_slot[w] = -1


@jit
def _grown(rep_slot, rep_old, rep_new, need):
    """The three move arrays copied into twice the room (at least ``need`` rows)."""
    n = max(2 * rep_slot.shape[0], need + 16)
    s = np.zeros(n, np.int32)
    o = np.zeros((n, 3), np.int32)
    w = np.zeros((n, 3), np.int32)
    k = rep_slot.shape[0]
    s[:k] = rep_slot
    o[:k] = rep_old
    w[:k] = rep_new
    return s, o, w


@jit
def split_codes(
    encode,
    qxy,
    z,
    label,
    base_tri,
    block_ptr,
    vpos,
    vat,
    seg_lo,
    seg_hi,
    rec_u,
    rec_v,
    rec_x,
    rec_m,
    sym_u,
    sym_v,
    sym_j,
    sym_a,
    esc_v,
    esc_x,
    moves,
    del_tri,
    rep_ptr,
):
    """Vertex splits to symbols (``encode``) or back, replaying them from the base mesh.

    Parameters
    ----------
    encode : bool
        True: read ``rec_u, rec_v, rec_x`` (x1), write ``sym_u, sym_v, sym_j`` and the escapes; False: the
        reverse (``rec_u, rec_v, rec_x`` written).
    qxy : (V, 2) int64, vertex xy on the integer grid (exact orientation tests).
    z : (V,) float64, vertex heights, metres. label : (V,) int64, the sub-block inserting each vertex
        (B: none).
    base_tri : (n_base, 3) int32, counter-clockwise. block_ptr : (B + 1,) int64, records block-major.
    vpos : (V,) int64, each vertex's position in the block-major insertion order (``vat`` its inverse);
        block b's vertices to insert take positions ``seg_lo[b] … seg_hi[b] - 1``.
    rec_m : (R,) int64, triangles moved by each split (read in both directions).
    sym_u, sym_v, sym_j : (R,) int64. esc_v, esc_x : (R,) int64, the first n_escapes entries used.
    moves : bool
        Also write what each split does to the mesh (the fields :func:`terralod.kernels.qem_replay.replay_splits`
        derives, the same values): ``del_tri`` (2R, 3) int32 the two triangles record r creates, ``rep_ptr``
        (R + 1,) int64, and the returned ``rep_slot, rep_old, rep_new`` (the moved slots, their finer and
        coarser triples: their first ``rep_ptr[R]`` rows). False: ``del_tri`` and ``rep_ptr`` are not touched
        (pass empty arrays).

    Returns
    -------
    status, n_escapes, rep_slot, rep_old, rep_new
        status 0, or r + 1 for the first record that does not fit (a corrupt file); -1: a base triangle
        names no vertex; -2: more triangle slots than :data:`MAX_NODES` allows.
    """
    n_rec = rec_m.shape[0]
    n_base = base_tri.shape[0]
    n_slots = n_base + 2 * n_rec
    n_v = qxy.shape[0]
    n_rep = 0
    if moves:  # grown as the fans arrive (about 4 moved triangles a split)
        rep_ptr[0] = 0
        n_rep = 4 * n_rec + 16
    rep_slot = np.zeros(n_rep, np.int32)
    rep_old = np.zeros((n_rep, 3), np.int32)
    rep_new = np.zeros((n_rep, 3), np.int32)
    if 3 * n_slots + 1 > MAX_NODES:
        return -2, 0, rep_slot, rep_old, rep_new
    tris = np.zeros((max(n_slots, 1), 3), np.int32)
    head = np.full(n_v, -1, np.int32)
    n_nodes = 3 * n_slots + 1
    nxt = np.arange(1, n_nodes + 1, dtype=np.int32)
    nxt[n_nodes - 1] = -1
    node_tri = np.zeros(n_nodes, np.int32)
    free = 0
    present = np.zeros(n_v, np.bool_)
    for t in range(n_base):
        for k in range(3):
            w = base_tri[t, k]
            if w < 0 or w >= n_v:
                return -1, 0, rep_slot, rep_old, rep_new
            tris[t, k] = w
            present[w] = True
            free = _star_add(head, nxt, node_tri, free, w, t)
    max_steps = n_slots + 16
    n_esc = 0
    # walks start from a hint: per cell of a coarse grid, the last slot made around a vertex in it
    g = 1
    shift = 26  # cell of integer coordinate q: q >> shift (q <= 2^26)
    while g * g * 16 < n_slots and shift > 0:
        g *= 2
        shift -= 1
    hint = np.full(g * g, -1, np.int64)
    for t in range(n_base):
        w = tris[t, 0]
        hint[min(qxy[w, 1] >> shift, g - 1) * g + min(qxy[w, 0] >> shift, g - 1)] = t
    last = 0
    for c in range(g * g):  # an empty cell takes the hint of the cell before it (row-major)
        if hint[c] < 0:
            hint[c] = last
        last = hint[c]
    # every vertex still to insert (a candidate) sits in the slot holding its xy, in the bucket of its
    # vertical distance to that slot's plane; per bucket a Fenwick tree over the insertion order
    nb = seg_lo.shape[0]
    cand_slot = np.full(n_v, -1, np.int32)
    slot_head = np.full(max(n_slots, 1), -1, np.int32)
    cnext = np.full(n_v, -1, np.int32)
    cprev = np.full(n_v, -1, np.int32)
    cbucket = np.full(n_v, -1, np.int8)
    pbucket = np.full(n_v, -1, np.int8)  # cbucket by insertion position (N_BUCKETS < 128)
    cnt = np.zeros((max(nb, 1), N_BUCKETS), np.int64)
    fen = np.zeros((N_BUCKETS, n_v // CHUNK + 2), np.int32)  # per bucket, a Fenwick tree over chunks
    for b in range(nb):
        for p in range(seg_lo[b], seg_hi[b]):
            w = vat[p]
            k = 0
            if n_base:
                t = _walk(tris, head, nxt, node_tri, qxy, hint[min(qxy[w, 1] >> shift, g - 1) * g
                                                               + min(qxy[w, 0] >> shift, g - 1)],
                          qxy[w, 0], qxy[w, 1], max_steps)  # fmt: skip
                if t >= 0:
                    _link(slot_head, cnext, cprev, cand_slot, t, w)
                    k = _error_bucket(qxy, z, tris, t, w)
            _set_bucket(fen, cnt, label, vpos, cbucket, pbucket, w, k)
    j_counts, j_order, j_pos = _ranked(FAN_CONTEXTS, FAN_VALUES)  # the fan offsets j
    a_counts, a_order, a_pos = _ranked(FAN_CONTEXTS, FAN_VALUES)  # ... and after
    v_counts, v_order, v_pos = _ranked(6, V_ESCAPE)
    moved = np.empty(16, np.int64)
    gather = np.empty(n_v, np.int64)
    for b in range(block_ptr.shape[0] - 1):
        for r in range(block_ptr[b], block_ptr[b + 1]):
            m = rec_m[r] if encode else 1
            # u: its rank among the block's candidates, by bucket (largest error first), then insertion order
            if encode:
                u = rec_u[r]
                if u < 0 or u >= n_v or vpos[u] < seg_lo[b] or vpos[u] >= seg_hi[b] or cbucket[u] < 0:
                    return r + 1, n_esc, rep_slot, rep_old, rep_new
                bu = cbucket[u]
                rank = _bucket_below(fen, pbucket, bu, vpos[u]) - _bucket_below(fen, pbucket, bu, seg_lo[b])
                for k in range(bu + 1, N_BUCKETS):
                    rank += cnt[b, k]
                sym_u[r] = rank
            else:
                rank = sym_u[r]
                bu = -1
                for k in range(N_BUCKETS - 1, -1, -1):
                    if rank < cnt[b, k]:
                        bu = k
                        break
                    rank -= cnt[b, k]
                if sym_u[r] < 0 or bu < 0:
                    return r + 1, n_esc, rep_slot, rep_old, rep_new
                p = _bucket_find(fen, pbucket, bu, rank + _bucket_below(fen, pbucket, bu, seg_lo[b]))
                if p < seg_lo[b] or p >= seg_hi[b]:
                    return r + 1, n_esc, rep_slot, rep_old, rep_new
                u = vat[p]
                rec_u[r] = u
            if present[u] or m < 1:
                return r + 1, n_esc, rep_slot, rep_old, rep_new
            px = qxy[u, 0]
            py = qxy[u, 1]
            cell = min(py >> shift, g - 1) * g + min(px >> shift, g - 1)
            t_in = cand_slot[u]
            if t_in < 0 and n_base:
                t_in = _walk(tris, head, nxt, node_tri, qxy, hint[cell], px, py, max_steps)
            _set_bucket(fen, cnt, label, vpos, cbucket, pbucket, u, -1)
            _unlink(slot_head, cnext, cprev, cand_slot, u)
            # T's corners, nearest to u first (ties: corner order)
            c0 = c1 = c2 = -1
            cv = 0  # v's context: the corner (by distance) facing u's nearest edge, and u on it or not
            if t_in >= 0:
                d = np.empty(3, np.int64)
                for k in range(3):
                    w = tris[t_in, k]
                    d[k] = (qxy[w, 0] - px) ** 2 + (qxy[w, 1] - py) ** 2
                o = np.argsort(d, kind="mergesort")
                c0 = tris[t_in, o[0]]
                c1 = tris[t_in, o[1]]
                c2 = tris[t_in, o[2]]
                wa, wb, wc, det = _bary(qxy, tris, t_in, px, py)
                kmin = 0 if wa <= min(wb, wc) else (1 if wb <= wc else 2)
                wmin = min(wa, min(wb, wc))
                for i in range(3):
                    if o[i] == kmin:
                        cv = 2 * i + (1 if wmin <= 0 else 0)
            if encode:
                v = rec_v[r]
                x1 = rec_x[r]
                if v < 0 or v >= n_v or not present[v]:
                    return r + 1, n_esc, rep_slot, rep_old, rep_new
                sv = V_ESCAPE
                if v == c0:
                    sv = 0
                elif v == c1:
                    sv = 1
                elif v == c2:
                    sv = 2
                j = -1
                if sv != V_ESCAPE:  # T's place in the fan
                    x = x1
                    for i in range(m):
                        t = _edge_tri(tris, head, nxt, node_tri, v, x)
                        if t < 0:
                            return r + 1, n_esc, rep_slot, rep_old, rep_new
                        if t == t_in:
                            j = i
                            break
                        x = _after(tris, t, x)
                    if j < 0:
                        sv = V_ESCAPE
                sym_v[r] = _to_rank(v_pos, cv, sv)
                _seen(v_counts, v_order, v_pos, cv, sv)
                if sv == V_ESCAPE:
                    esc_v[n_esc] = v
                    esc_x[n_esc] = x1
                    n_esc += 1
                    sym_j[r] = 0
                    sym_a[r] = m
                else:
                    cj = _side_run(
                        tris, head, nxt, node_tri, qxy, t_in, v, px - qxy[v, 0], py - qxy[v, 1], True
                    )
                    ca = _side_run(
                        tris, head, nxt, node_tri, qxy, t_in, v, px - qxy[v, 0], py - qxy[v, 1], False
                    )
                    after = m - 1 - j
                    sym_j[r] = _to_rank(j_pos, cj, j)
                    sym_a[r] = _to_rank(a_pos, ca, after)
                    _seen(j_counts, j_order, j_pos, cj, j)
                    _seen(a_counts, a_order, a_pos, ca, after)
            else:
                sv = _from_rank(v_order, cv, sym_v[r])
                _seen(v_counts, v_order, v_pos, cv, sv)
                if sv == V_ESCAPE:
                    if n_esc >= esc_v.shape[0]:
                        return r + 1, n_esc, rep_slot, rep_old, rep_new
                    v = esc_v[n_esc]
                    x1 = esc_x[n_esc]
                    n_esc += 1
                    m = sym_a[r]
                elif 0 <= sv < V_ESCAPE and t_in >= 0:
                    v = c0 if sv == 0 else (c1 if sv == 1 else c2)
                    cj = _side_run(
                        tris, head, nxt, node_tri, qxy, t_in, v, px - qxy[v, 0], py - qxy[v, 1], True
                    )
                    ca = _side_run(
                        tris, head, nxt, node_tri, qxy, t_in, v, px - qxy[v, 0], py - qxy[v, 1], False
                    )
                    j = _from_rank(j_order, cj, sym_j[r])
                    after = _from_rank(a_order, ca, sym_a[r])
                    if j < 0 or after < 0:
                        return r + 1, n_esc, rep_slot, rep_old, rep_new
                    _seen(j_counts, j_order, j_pos, cj, j)
                    _seen(a_counts, a_order, a_pos, ca, after)
                    m = after + 1 + j
                    # step back j triangles around v (clockwise) from T to the fan's first
                    t = t_in
                    for _ in range(j):
                        a = _after(tris, t, v)
                        t = _edge_tri(tris, head, nxt, node_tri, a, v)  # (v, ., a) shares edge v-a
                        if t < 0:
                            return r + 1, n_esc, rep_slot, rep_old, rep_new
                    x1 = _after(tris, t, v)
                else:
                    return r + 1, n_esc, rep_slot, rep_old, rep_new
                if v < 0 or v >= n_v or x1 < 0 or x1 >= n_v or m < 1 or m > n_slots:
                    return r + 1, n_esc, rep_slot, rep_old, rep_new
                rec_v[r] = v
                rec_x[r] = x1
                rec_m[r] = m
            if not present[v]:
                return r + 1, n_esc, rep_slot, rep_old, rep_new
            # the split: the fan (v, x1, x2) … moves to u; (u, v, x1) and (u, x_m, v) come back
            x = x1
            if m > moved.shape[0]:
                moved = np.empty(2 * m, np.int64)
            q0 = 0
            if moves:
                q0 = rep_ptr[r]
                if q0 + m > rep_slot.shape[0]:
                    rep_slot, rep_old, rep_new = _grown(rep_slot, rep_old, rep_new, q0 + m)
                rep_ptr[r + 1] = q0 + m
            for i in range(m):
                t = _edge_tri(tris, head, nxt, node_tri, v, x)
                if t < 0:
                    return r + 1, n_esc, rep_slot, rep_old, rep_new
                moved[i] = t
                if moves:
                    rep_slot[q0 + i] = t
                    for k in range(3):
                        rep_new[q0 + i, k] = tris[t, k]
                for k in range(3):
                    if tris[t, k] == v:
                        tris[t, k] = u
                if moves:
                    for k in range(3):
                        rep_old[q0 + i, k] = tris[t, k]
                x = _after(tris, t, x)
                free = _star_remove(head, nxt, node_tri, free, v, t)
                free = _star_add(head, nxt, node_tri, free, u, t)
            xm = x
            if xm == x1 or xm == v:
                return r + 1, n_esc, rep_slot, rep_old, rep_new
            s1 = n_base + 2 * r
            s2 = s1 + 1
            tris[s1, 0] = u
            tris[s1, 1] = v
            tris[s1, 2] = x1
            tris[s2, 0] = u
            tris[s2, 1] = xm
            tris[s2, 2] = v
            if moves:
                for k in range(3):
                    del_tri[2 * r, k] = tris[s1, k]
                    del_tri[2 * r + 1, k] = tris[s2, k]
            for k in range(3):
                free = _star_add(head, nxt, node_tri, free, tris[s1, k], s1)
                free = _star_add(head, nxt, node_tri, free, tris[s2, k], s2)
            present[u] = True
            hint[cell] = s1
            # the candidates of the moved slots go to whichever of the m + 2 new triangles holds them
            ng = 0
            for i in range(m):
                w = slot_head[moved[i]]
                while w >= 0:
                    gather[ng] = w
                    ng += 1
                    w = cnext[w]
                slot_head[moved[i]] = -1
            for i in range(ng):
                w = gather[i]
                cand_slot[w] = -1
                best = -1
                best_min = np.int64(-(2**62))
                for q in range(m + 2):
                    t = moved[q] if q < m else s1 + (q - m)
                    wa, wb, wc, det = _bary(qxy, tris, t, qxy[w, 0], qxy[w, 1])
                    lo_ = min(wa, min(wb, wc))
                    if lo_ > best_min:
                        best_min = lo_
                        best = t
                    if lo_ >= 0:
                        break
                _link(slot_head, cnext, cprev, cand_slot, best, w)
                _set_bucket(fen, cnt, label, vpos, cbucket, pbucket, w, _error_bucket(qxy, z, tris, best, w))
    return 0, n_esc, rep_slot, rep_old, rep_new
