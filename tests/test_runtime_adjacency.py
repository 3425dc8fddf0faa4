"""Adjacency (paper 002 §3.1–3.2): edge and corner neighbours of every leaf against plain geometry, and
the CrackTileVector holding exactly the visible leaves whose neighbourhood changed."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from terralod.runtime import Adjacency, QuadIndex
from terralod.runtime.adjacency import CULLED, VISIBLE
from terralod.tiles import TilePyramid

from test_runtime_support import brute_neighbours, spike_partition

PYRAMIDS = [TilePyramid(257, 257, 9), TilePyramid(230, 150, 17), TilePyramid(100, 300, 5)]


def _relations(adj: Adjacency, idx: QuadIndex, slot: int) -> tuple:
    nb = adj.neighbours(slot)
    return tuple(tuple(idx.codes(e)) for e in nb.edges) + tuple(
        None if c < 0 else idx.code(c) for c in nb.corners
    )  # fmt: skip


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**31), st.sampled_from(range(len(PYRAMIDS))))
def test_neighbours_match_geometry(seed: int, which: int) -> None:
    pyr = PYRAMIDS[which]
    rng = np.random.default_rng(seed)
    leaves = spike_partition(pyr, rng, spikes=2)
    idx = QuadIndex(pyr)
    adj = Adjacency(idx)
    slots = idx.slots(leaves)
    assert adj.check_partition(slots) == (0, 0)
    adj.update(slots, np.full(len(slots), VISIBLE, np.int8))
    for code in leaves:
        nb = adj.neighbours(idx.slot(code))
        edges, corners = brute_neighbours(pyr, leaves, code)
        for d in range(4):
            got = idx.codes(nb.edges[d])
            assert set(got) == edges[d]
            # ascending along the side: rows for L/R, columns for U/D
            key = [pyr.origin_rc(c)[0 if d in (0, 2) else 1] for c in got]
            assert key == sorted(key)
        assert [None if c < 0 else idx.code(c) for c in nb.corners] == corners


def test_partition_check_rejects_bad_leaf_sets() -> None:
    pyr = PYRAMIDS[0]
    idx = QuadIndex(pyr)
    adj = Adjacency(idx)
    level2 = list(pyr.tile_codes(2))
    assert adj.check_partition(idx.slots(level2)) == (0, 0)
    assert adj.check_partition(idx.slots(level2[1:]))[1] > 0  # a hole
    assert adj.check_partition(idx.slots([*level2, (1, 0, 0)]))[0] > 0  # overlap
    with pytest.raises(KeyError):
        idx.slots([(9, 0, 0)])


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**31))
def test_crack_tile_vector_is_exactly_the_changed_neighbourhoods(seed: int) -> None:
    pyr = PYRAMIDS[seed % 2]
    rng = np.random.default_rng(seed)
    idx = QuadIndex(pyr)
    adj = Adjacency(idx)
    prev_rel: dict[int, tuple] = {}
    prev_vis: dict[int, bool] = {}
    leaves = spike_partition(pyr, rng, spikes=2)
    for step in range(6):
        if step:  # a local change: re-split one region, keep the rest
            leaves = _perturb(pyr, leaves, rng)
        slots = idx.slots(leaves)
        fresh = rng.random(len(slots)) < 0.85
        if step and rng.random() < 0.7:  # mostly keep the visibility of leaves that survived
            fresh = np.array(
                [prev_vis.get(s, f) for s, f in zip(slots.tolist(), fresh.tolist(), strict=True)]
            )
        states = np.where(fresh, VISIBLE, CULLED).astype(np.int8)
        crack = set(adj.update(slots, states).tolist())
        vis = {s for s, st_ in zip(slots.tolist(), states.tolist(), strict=True) if st_ == VISIBLE}
        vis_map = {s: st_ == VISIBLE for s, st_ in zip(slots.tolist(), states.tolist(), strict=True)}
        expected = set()
        rel = {}
        for s in vis:
            r = _relations(adj, idx, s)
            flat = {q for part in r[:4] for q in part} | {q for q in r[4:] if q is not None}
            rvis = tuple(sorted((q, vis_map[idx.slot(q)]) for q in flat))
            rel[s] = (r, rvis)
            if s not in prev_rel or prev_rel[s] != rel[s] or not prev_vis.get(s, False):
                expected.add(s)
        assert crack == expected
        adj.sleep(np.array(sorted(crack), np.int64))
        prev_rel = rel
        prev_vis = vis_map


def _perturb(pyr: TilePyramid, leaves: list, rng: np.random.Generator) -> list:
    """Split one random leaf or merge one random complete sibling group."""
    leaves = list(leaves)
    if rng.random() < 0.5:
        cand = [c for c in leaves if c[0] < pyr.max_level]
        if cand:
            c = cand[int(rng.integers(len(cand)))]
            leaves.remove(c)
            leaves.extend(pyr.children(c))
            return leaves
    s = set(leaves)
    groups = {}
    for c in leaves:
        if c[0] > 0:
            p = (c[0] - 1, c[1] // 2, c[2] // 2)
            groups.setdefault(p, []).append(c)
    full = [
        p for p, kids in groups.items() if set(pyr.children(p)) <= s and len(kids) == len(pyr.children(p))
    ]
    if full:
        p = full[int(rng.integers(len(full)))]
        for c in pyr.children(p):
            leaves.remove(c)
        leaves.append(p)
    return leaves
