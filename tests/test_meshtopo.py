"""The export's small kernels give exactly the idioms they replace: the mesh topology (kernels/meshtopo.py)
on any triangle list (used vertices ascending, vertices in order of first use, lone edges), and a TIN's
ladder of halving errors (kernels/qem_replay.halving_rungs) on any error sequence."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from terralod.kernels.meshtopo import compact_triangles, first_use, lone_edge_mask
from terralod.kernels.qem_replay import halving_rungs

_meshes = st.tuples(st.integers(0, 2**32 - 1), st.integers(1, 60), st.integers(0, 200))


def _tris(seed: int, nv: int, k: int) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, nv, size=(k, 3)).astype(np.int64)


@settings(max_examples=60, deadline=None)
@given(_meshes)
def test_first_use_is_the_order_of_first_appearance(m: tuple[int, int, int]) -> None:
    seed, nv, k = m
    flat = _tris(seed, nv, k).ravel()
    order, local = first_use(flat, nv)
    _, first = np.unique(flat, return_index=True)
    want = flat[np.sort(first)]
    np.testing.assert_array_equal(order, want)
    np.testing.assert_array_equal(order[local], flat)  # the renumbering points back at the same vertices
    assert local.dtype == np.int64 and order.dtype == np.int64


@settings(max_examples=60, deadline=None)
@given(_meshes)
def test_compact_triangles_is_unique_and_its_inverse(m: tuple[int, int, int]) -> None:
    seed, nv, k = m
    tris = _tris(seed, nv, k)
    used, local = compact_triangles(tris, nv)
    np.testing.assert_array_equal(used, np.unique(tris))
    np.testing.assert_array_equal(used[local], tris)


@settings(max_examples=60, deadline=None)
@given(_meshes)
def test_lone_edges_are_the_edges_one_triangle_uses(m: tuple[int, int, int]) -> None:
    seed, nv, k = m
    tris = _tris(seed, nv, k)
    e = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]])
    key = np.sort(e, axis=1)
    _, inv, count = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    np.testing.assert_array_equal(lone_edge_mask(tris, nv), count[inv.ravel()] == 1)


@settings(max_examples=80, deadline=None)
@given(st.lists(st.sampled_from([0.0, 0.1, 0.25, 0.5, 1.0, 2.0, 7.5]) | st.floats(0.0, 50.0), max_size=40))
def test_halving_rungs_is_the_ladder_rule(err: list[float]) -> None:
    rungs = [0]  # base, then each first scale at or below half the last rung's error (none after a 0), last
    for s in range(1, len(err)):
        if s == len(err) - 1 or (err[rungs[-1]] > 0.0 and err[s] <= 0.5 * err[rungs[-1]]):
            rungs.append(s)
    assert halving_rungs(np.asarray(err, np.float64)).tolist() == rungs
