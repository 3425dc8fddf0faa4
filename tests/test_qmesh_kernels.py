"""The quantized-mesh ordering kernels (terralod.kernels.qmesh) against plain numpy, over random meshes
whose vertices lie on few rows (a lattice tile's: the case that defeated the old hash's low bits):

- merge_uv keeps, per quantised (u, v) used by a triangle, its lowest index, in index order, and maps
  every triangle's corners to them;
- walk_order is a permutation of the triangles in which each triangle after the first shares an edge with
  one before it whenever it shares an edge with any triangle at all (a walk, restarted only when stuck).
"""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from terralod.kernels.qmesh import merge_uv, walk_order


def _grid_mesh(rows: int, cols: int) -> np.ndarray:
    a = (np.arange(cols - 1)[None, :] + cols * np.arange(rows - 1)[:, None]).ravel()
    return np.concatenate([np.stack([a, a + cols, a + 1], 1), np.stack([a + 1, a + cols, a + cols + 1], 1)])


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31), rows=st.integers(1, 40), n=st.integers(1, 3000), nt=st.integers(0, 3000))
def test_merge_uv_keeps_the_lowest_index_of_each_used_uv(seed, rows, n, nt) -> None:
    rng = np.random.default_rng(seed)
    v = rng.choice(rng.integers(0, 32768, rows), n)  # few distinct rows, many vertices on each
    u = rng.integers(0, 32768, n) // rng.choice([1, 64, 4096])  # from all distinct to many repeats
    tris = rng.integers(0, n, (nt, 3)).astype(np.int64)
    keep, out = merge_uv(tris, u.astype(np.int64), v.astype(np.int64))
    used = np.unique(tris)
    key = u[used] * 32768 + v[used]
    _, first = np.unique(key, return_index=True)
    want = np.sort(used[first])
    np.testing.assert_array_equal(keep, want)
    np.testing.assert_array_equal(u[keep][out], u[tris])
    np.testing.assert_array_equal(v[keep][out], v[tris])


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31), rows=st.integers(2, 30), cols=st.integers(2, 30), drop=st.floats(0, 0.5))
def test_walk_order_is_a_walk_across_shared_edges(seed, rows, cols, drop) -> None:
    rng = np.random.default_rng(seed)
    tris = _grid_mesh(rows, cols)
    tris = tris[rng.random(len(tris)) >= drop]  # holes: the walk must restart
    nt = len(tris)
    seeds = rng.permutation(nt)
    order = walk_order(np.ascontiguousarray(tris), seeds, rows * cols)
    np.testing.assert_array_equal(np.sort(order), np.arange(nt))
    edges = [{frozenset((t[q], t[(q + 1) % 3])) for q in range(3)} for t in tris]
    seen_edges: set = set()
    for k, t in enumerate(order):
        restart = k > 0 and not edges[t] & seen_edges  # not joined to the triangles walked so far
        if restart:  # allowed only when no unvisited triangle touches them
            assert not any(edges[r] & seen_edges for r in order[k:]), "walk restarted while it could go on"
        seen_edges |= edges[t]
