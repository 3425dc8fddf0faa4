"""Quantized-mesh ordering kernels: the triangle and vertex order a tile is written in, and the merge of
vertices that quantise to one (u, v).

The format (Cesium quantized-mesh 1.0) writes indices with high-water-mark coding and vertices as zig-zag
deltas: both are small, and gzip well, when each next triangle shares an edge with the one before and
vertices are numbered in first use. :func:`walk_order` gives that triangle order, :func:`rotate_after`
turns each triangle to (shared, shared, new), :func:`first_use` renumbers the vertices; the encoder
(:mod:`terralod.export.quantized_mesh_format`) calls them. :func:`merge_uv` keeps one vertex per quantised
(u, v) (clipped meshes make the same edge crossing in two neighbours). Pure functions on arrays.
"""

from __future__ import annotations

import numpy as np

from terralod.kernels import jit, leaf


@leaf
def _slot(key, shift):  # pragma: no cover - numba
    """Fibonacci hashing: the top ``64 - shift`` bits of key x 2^64/φ, the slot of ``key`` in a table of
    2^(64 - shift) slots. (The low bits of the product depend only on the low bits of the key: a u * 32768 + v
    key's slot was its v alone, so the vertices of one lattice row all probed one run of slots.)"""
    return np.int64((np.uint64(key) * np.uint64(0x9E3779B97F4A7C15)) >> np.uint64(shift))


@leaf
def _free(nbr, seen, t):  # pragma: no cover - numba
    """How many unvisited neighbours triangle t has."""
    k = 0
    for q in range(3):
        m = nbr[3 * t + q]
        if m >= 0 and not seen[m]:
            k += 1
    return k


@jit
def walk_order(tris, seeds, nv):  # pragma: no cover - numba
    """Triangle order: a depth-first walk across shared edges (each next triangle shares an edge with the
    one before wherever it can, so two of its three indices are recent ones and the high-water-mark codes
    stay small), going on to the unvisited neighbour that comes first in ``seeds`` (Morton order of the
    centroids), restarting at the next unvisited seed when the walk is stuck."""
    nt = tris.shape[0]
    # each undirected edge's two triangles through an open-addressing table of edge keys (one pass)
    # (key, first half-edge) side by side, at most 3 nt keys in 4 nt slots or more: one cache line a probe
    cap, bits = 16, 4
    while cap < 4 * nt:
        cap, bits = cap * 2, bits + 1
    slot = np.full(2 * cap, -1, np.int64)
    nbr = np.full(3 * nt, -1, np.int64)
    for t in range(nt):
        for q in range(3):
            a = tris[t, q]
            b = tris[t, (q + 1) % 3]
            key = min(a, b) * nv + max(a, b)
            h = _slot(key, 64 - bits)
            while slot[2 * h] >= 0 and slot[2 * h] != key:
                h = (h + 1) & (cap - 1)
            if slot[2 * h] == key:
                o = slot[2 * h + 1]
                nbr[3 * t + q] = o // 3
                nbr[o] = t
            else:
                slot[2 * h] = key
                slot[2 * h + 1] = 3 * t + q
    rank = np.empty(nt, np.int64)
    for i in range(nt):
        rank[seeds[i]] = i
    seen = np.zeros(nt, np.bool_)
    out = np.empty(nt, np.int64)
    no = 0
    stack = np.empty(2 * nt + 1, np.int64)
    sp = 0
    for s in seeds:
        if seen[s]:
            continue
        cur = s
        while True:
            seen[cur] = True
            out[no] = cur
            no += 1
            best = -1
            for q in range(3):
                m = nbr[3 * cur + q]
                if m >= 0 and not seen[m]:
                    if best < 0:
                        best = m
                    elif _free(nbr, seen, m) * nt + rank[m] < _free(nbr, seen, best) * nt + rank[best]:
                        stack[sp] = best
                        sp += 1
                        best = m
                    else:
                        stack[sp] = m
                        sp += 1
            if best < 0:
                while sp > 0:
                    sp -= 1
                    if not seen[stack[sp]]:
                        best = stack[sp]
                        break
            if best < 0:
                break
            cur = best
    return out


@leaf
def _spread10(a):  # pragma: no cover - numba
    """The low 10 bits of ``a`` spread to the even bits (half of a Morton code)."""
    a &= 0x3FF
    a = (a | (a << 8)) & 0x00FF00FF
    a = (a | (a << 4)) & 0x0F0F0F0F
    a = (a | (a << 2)) & 0x33333333
    return (a | (a << 1)) & 0x55555555


@jit
def morton_seeds(tris, u, v):  # pragma: no cover - numba
    """The triangles in Morton order of their centroids (the sums of their corners' u and v over 96:
    10 bits each), ties in index order: what ``np.argsort(codes, kind="stable")`` gives, by two
    counting-sort passes of 10 bits (the walk's seeds, :func:`walk_order`)."""
    nt = tris.shape[0]
    code = np.empty(nt, np.int64)
    for t in range(nt):
        cu = (u[tris[t, 0]] + u[tris[t, 1]] + u[tris[t, 2]]) // 96
        cv = (v[tris[t, 0]] + v[tris[t, 1]] + v[tris[t, 2]]) // 96
        code[t] = _spread10(cu) | (_spread10(cv) << 1)
    return _counting_pass(code, _counting_pass(code, np.arange(nt), 0), 10)


@jit
def _counting_pass(code, src, shift):  # pragma: no cover - numba
    """``src`` stably sorted by the 10 bits of ``code[src]`` from bit ``shift``."""
    at = np.zeros(1025, np.int64)
    for i in range(src.size):
        at[((code[src[i]] >> shift) & 0x3FF) + 1] += 1
    for b in range(1024):
        at[b + 1] += at[b]
    dst = np.empty_like(src)
    for i in range(src.size):
        b = (code[src[i]] >> shift) & 0x3FF
        dst[at[b]] = src[i]
        at[b] += 1
    return dst


@jit
def rotate_after(tris):  # pragma: no cover - numba
    """Each triangle rotated (its winding kept) so that the vertex it does not share with the triangle
    before comes last: a walk's triangles then read (shared, shared, new)."""
    out = tris.copy()
    for t in range(1, tris.shape[0]):
        for q in range(3):
            i = tris[t, q]
            if i != out[t - 1, 0] and i != out[t - 1, 1] and i != out[t - 1, 2]:
                out[t, 0] = tris[t, (q + 1) % 3]
                out[t, 1] = tris[t, (q + 2) % 3]
                out[t, 2] = i
                break
    return out


@jit
def first_use(tris, nv):  # pragma: no cover - numba
    """Vertices renumbered in first-use order of ``tris`` (unused ones last): (order, renumbered tris)."""
    remap = np.full(nv, -1, np.int64)
    order = np.empty(nv, np.int64)
    k = 0
    out = np.empty_like(tris)
    for t in range(tris.shape[0]):
        for q in range(3):
            i = tris[t, q]
            if remap[i] < 0:
                remap[i] = k
                order[k] = i
                k += 1
            out[t, q] = remap[i]
    for i in range(nv):
        if remap[i] < 0:
            remap[i] = k
            order[k] = i
            k += 1
    return order, out


@jit
def merge_uv(tris, u, v):  # pragma: no cover - numba
    """One vertex per quantised (u, v) among those ``tris`` uses (the lowest index of each, in index
    order; open-addressing hash of u * 32768 + v): (kept indices, tris renumbered to them)."""
    n = u.size
    used = np.zeros(n, np.bool_)
    for t in range(tris.shape[0]):
        for q in range(3):
            used[tris[t, q]] = True
    cap, bits = 16, 4
    while cap < 2 * n:
        cap, bits = cap * 2, bits + 1
    slot_key = np.full(cap, -1, np.int64)
    slot_val = np.empty(cap, np.int64)
    remap = np.full(n, -1, np.int64)
    keep = np.empty(n, np.int64)
    k = 0
    for i in range(n):
        if not used[i]:
            continue
        key = u[i] * 32768 + v[i]
        h = _slot(key, 64 - bits)
        while slot_key[h] >= 0 and slot_key[h] != key:
            h = (h + 1) & (cap - 1)
        if slot_key[h] == key:
            remap[i] = slot_val[h]
        else:
            slot_key[h] = key
            slot_val[h] = k
            remap[i] = k
            keep[k] = i
            k += 1
    out = np.empty_like(tris)
    for t in range(tris.shape[0]):
        for q in range(3):
            out[t, q] = remap[tris[t, q]]
    return keep[:k], out
