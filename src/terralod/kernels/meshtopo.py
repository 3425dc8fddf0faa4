"""Linear-time mesh topology for the exports: lone edges, used vertices, positions merged, ordered sums.

Each kernel replaces a numpy idiom that sorts (``np.unique`` over rows, ``np.add.at``) with one pass over a
counting sort or a hash table, and gives the idiom's exact result: the same edges in the same order, the
same vertices in ascending order, the same groups of equal positions, the same floating-point additions in
the same order. The 3D Tiles export runs them on every node of a pyramid (tens of millions of triangles for
a detail-increment TIN), where the sorts were most of its time.
"""

from __future__ import annotations

import numpy as np

from terralod.kernels import jit

__all__ = ["add_rows", "compact_triangles", "first_use", "lone_edge_mask", "merge_pairs", "used_bounds"]

#: Odd 64-bit multipliers of the position hash (the golden ratio's and xxHash's), as signed int64.
_MIX_A = np.int64(-7046029254386353131)
_MIX_B = np.int64(-4417276706812531889)


@jit
def lone_edge_mask(tris, n_vertices):
    """(3K,) bool: which of the directed edges ``(t[:, 0], t[:, 1])``, then ``(t[:, 1], t[:, 2])``, then
    ``(t[:, 2], t[:, 0])`` (concatenated in that order) are used by exactly one triangle, whatever their
    direction. ``tris`` (K, 3) int64 with indices in [0, n_vertices).

    Edges are bucketed by their lower vertex (a counting sort), and each bucket (the vertex's degree, a
    handful) is compared pairwise: O(K + V)."""
    k = tris.shape[0]
    ne = 3 * k
    start = np.zeros(n_vertices + 1, np.int64)
    for i in range(k):
        for j in range(3):
            start[min(tris[i, j], tris[i, (j + 1) % 3]) + 1] += 1
    for v in range(n_vertices):
        start[v + 1] += start[v]
    fill = start[:-1].copy()
    far = np.empty(ne, np.int32)  # by bucket: the edge's higher vertex ... (int32: half the traffic)
    edge = np.empty(ne, np.int32)  # ... and its index in the concatenated order
    for j in range(3):
        for i in range(k):
            p = tris[i, j]
            q = tris[i, (j + 1) % 3]
            lo = min(p, q)
            at = fill[lo]
            far[at] = max(p, q)
            edge[at] = j * k + i
            fill[lo] = at + 1
    out = np.zeros(ne, np.bool_)
    for v in range(n_vertices):
        for i in range(start[v], start[v + 1]):
            same = 0
            for j in range(start[v], start[v + 1]):
                if far[j] == far[i]:
                    same += 1
            out[edge[i]] = same == 1
    return out


@jit
def compact_triangles(tris, n_vertices):
    """(used, local): the vertices ``tris`` uses, ascending (``np.unique(tris)``), and ``tris`` renumbered
    into them (int64). ``tris`` (K, 3) int64 with indices in [0, n_vertices)."""
    slot = np.full(n_vertices, -1, np.int64)
    for i in range(tris.shape[0]):
        for j in range(3):
            slot[tris[i, j]] = 0
    n = 0
    for v in range(n_vertices):
        if slot[v] == 0:
            slot[v] = n
            n += 1
    used = np.empty(n, np.int64)
    for v in range(n_vertices):
        if slot[v] >= 0:
            used[slot[v]] = v
    local = np.empty((tris.shape[0], 3), np.int64)
    for i in range(tris.shape[0]):
        for j in range(3):
            local[i, j] = slot[tris[i, j]]
    return used, local


@jit
def first_use(flat, n_vertices):
    """(order, local): the vertices the flat index list ``flat`` (int64, in [0, n_vertices)) uses, in the
    order of their first use (``flat[np.sort(np.unique(flat, return_index=True)[1])]``), and ``flat``
    renumbered into that order (int64). One pass: a vertex-cache friendly numbering for a glTF mesh."""
    slot = np.full(n_vertices, -1, np.int64)
    order = np.empty(min(flat.size, n_vertices), np.int64)
    local = np.empty(flat.size, np.int64)
    n = 0
    for i in range(flat.size):
        v = flat[i]
        s = slot[v]
        if s < 0:
            s = n
            slot[v] = n
            order[n] = v
            n += 1
        local[i] = s
    return order[:n], local


@jit
def merge_pairs(bits):
    """(N,) int64 group of each row of ``bits`` (N, 2) int64: rows with equal pairs share a group, numbered
    in order of first appearance. Given the bit patterns of float64 coordinates (``-0.0`` made ``0.0``
    first), the groups are those of ``np.unique(xy, axis=0)``: an open-addressing hash table, O(N)."""
    n = bits.shape[0]
    size = 1
    while size < 2 * n + 2:
        size *= 2
    mask = size - 1
    table = np.full(size, -1, np.int64)
    first = np.empty(n, np.int64)  # the first row of each group
    out = np.empty(n, np.int64)
    groups = 0
    for i in range(n):
        a = bits[i, 0]
        b = bits[i, 1]
        h = (a * _MIX_A) ^ (b * _MIX_B)  # int64 products wrap
        h ^= h >> 29
        s = h & mask
        while True:
            g = table[s]
            if g < 0:
                table[s] = groups
                first[groups] = i
                out[i] = groups
                groups += 1
                break
            r = first[g]
            if bits[r, 0] == a and bits[r, 1] == b:
                out[i] = g
                break
            s = (s + 1) & mask
    return out


@jit
def add_rows(acc, rows, values):
    """In place, in row order: ``acc[rows[i]] += values[i]`` (``np.add.at``'s result, bit for bit)."""
    for i in range(rows.shape[0]):
        r = rows[i]
        for c in range(acc.shape[1]):
            acc[r, c] += values[i, c]


@jit
def used_bounds(v, tris):
    """(low (3,), high (3,)) of the vertices of ``v`` (N, 3) that ``tris`` (K, 3) uses (zeros without
    triangles): ``v[np.unique(tris)].min(axis=0)`` and ``.max(axis=0)`` without the sort (the used
    vertices marked, then ``v`` read in order)."""
    lo = np.zeros(3, np.float64)
    hi = np.zeros(3, np.float64)
    if tris.shape[0] == 0:
        return lo, hi
    mark = np.zeros(v.shape[0], np.bool_)
    for i in range(tris.shape[0]):
        for j in range(3):
            mark[tris[i, j]] = True
    for c in range(3):
        lo[c] = v[tris[0, 0], c]
        hi[c] = lo[c]
    for p in range(v.shape[0]):
        if mark[p]:
            for c in range(3):
                x = v[p, c]
                if x < lo[c]:
                    lo[c] = x
                if x > hi[c]:
                    hi[c] = x
    return lo, hi
