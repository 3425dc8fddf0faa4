"""QEM simplifier kernels (paper 003 §2.1): the indexed heap pops in (cost, vertex) order whatever the
updates, and the vertical term's point location gives the largest vertical distance to the collapsed fan
that an exhaustive search gives."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from terralod.kernels import qem as K


@settings(max_examples=80, deadline=None)
@given(
    n=st.integers(1, 40),
    ops=st.lists(st.tuples(st.integers(0, 39), st.integers(-1, 6)), max_size=200),
)
def test_indexed_heap_pops_in_cost_then_vertex_order(n: int, ops: list[tuple[int, int]]) -> None:
    """Queue, move (up or down) and unqueue vertices at random, with many tied keys: popping the root until
    empty gives every queued vertex once, in increasing (key, vertex)."""
    hk = np.empty(n, np.float64)
    hv = np.empty(n, np.int64)
    hpos = np.full(n, -1, np.int64)
    size = 0
    ref: dict[int, float] = {}
    for v, k in ops:
        v %= n
        if k < 0:
            size = K._heap_remove(hk, hv, hpos, size, v)
            ref.pop(v, None)
        else:
            size = K._heap_set(hk, hv, hpos, size, float(k), v)
            ref[v] = float(k)
        assert size == len(ref)
        assert all(hv[hpos[u]] == u for u in ref) and (hpos >= 0).sum() == size
    out = []
    while size > 0:
        out.append((hk[0], int(hv[0])))
        size = K._heap_remove(hk, hv, hpos, size, int(hv[0]))
    assert out == sorted((k, v) for v, k in ref.items())
    assert (hpos == -1).all()


def _reference_gap2(P: np.ndarray, ring: list[int], w: int, pts: list[int]) -> float:
    """Largest squared vertical distance from the points to the fan (w, a, b) over the ring edges (a, b)
    not at w, each point in the triangle with the largest smallest barycentric coordinate."""
    g = 0.0
    k = len(ring)
    tris = [(ring[i], ring[(i + 1) % k]) for i in range(k) if w not in (ring[i], ring[(i + 1) % k])]
    for q in pts:
        best, bz = -np.inf, 0.0
        for a, b in tris:
            m_ = np.array([[P[a, 0] - P[w, 0], P[b, 0] - P[w, 0]], [P[a, 1] - P[w, 1], P[b, 1] - P[w, 1]]])
            l1, l2 = np.linalg.solve(m_, P[q, :2] - P[w, :2])
            m = min(1.0 - l1 - l2, l1, l2)
            if m > best:
                best, bz = m, P[w, 2] + l1 * (P[a, 2] - P[w, 2]) + l2 * (P[b, 2] - P[w, 2])
        g = max(g, (P[q, 2] - bz) ** 2)
    return g


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), k=st.integers(4, 10), n_pts=st.integers(0, 30), level=st.booleans())
def test_vertical_gap_matches_an_exhaustive_search(seed: int, k: int, n_pts: int, level: bool) -> None:
    """u inside a convex ring of k neighbours, removed vertices scattered in its star and carried by the
    slot that holds them: for every target w, the kernel's squared vertical gap (own slot first, first
    triangle that holds the point) equals the exhaustive search's, and an early stop returns a value past
    its limit. ``level``: most heights are sea level (0 m), and so are u, an arc of the ring and every point
    its slots carry, so the kernel's skips of points on level triangles (one by one, and of a whole slot)
    run against the exhaustive search too."""
    rng = np.random.default_rng(seed)
    ang = np.linspace(0.0, 2 * np.pi, k, endpoint=False) + rng.uniform(-0.2, 0.2) * (2 * np.pi / k)
    ring_xy = np.c_[np.cos(ang), np.sin(ang)] * 100.0
    u_xy = rng.uniform(-20.0, 20.0, 2)
    # points inside the convex ring: random convex combinations of the centre and two ring neighbours
    pts_xy = []
    slot_of = []
    for _ in range(n_pts):
        i = int(rng.integers(k))
        a, b = rng.uniform(0.0, 1.0, 2)
        if a + b > 1.0:
            a, b = 1.0 - a, 1.0 - b
        pts_xy.append(u_xy + a * (ring_xy[i] - u_xy) + b * (ring_xy[(i + 1) % k] - u_xy))
        slot_of.append(i)
    xy = np.vstack([u_xy[None], ring_xy, np.array(pts_xy).reshape(-1, 2)])
    z = rng.normal(0.0, 10.0, xy.shape[0])
    if level:
        z[rng.random(xy.shape[0]) < 0.75] = 0.0
        # a sea arc: u, ring neighbours first .. last and the points of the slots between them at 0 m
        first = int(rng.integers(k))
        arc = [(first + d) % k for d in range(int(rng.integers(2, k)))]
        z[0] = 0.0
        z[[1 + i for i in arc]] = 0.0
        for j, s in enumerate(slot_of):
            if s in arc and (s + 1) % k in arc:
                z[k + 1 + j] = 0.0
    P = np.c_[xy, z]
    u, ring = 0, list(range(1, k + 1))
    tris = np.array([[u, ring[i], ring[(i + 1) % k]] for i in range(k)], np.int32)
    arena = np.arange(k, dtype=np.int32)
    head = np.full(k, -1, np.int64)
    nxt = np.full(P.shape[0], -1, np.int64)
    for j, s in enumerate(slot_of):
        q = k + 1 + j
        nxt[q] = head[s]
        head[s] = q
    nv = P.shape[0]
    sa, sb, ps = np.empty(nv, np.int64), np.empty(nv, np.int64), np.empty(nv, np.int64)
    geo, pxyz, tri = np.empty((nv, 6)), np.empty((nv, 3)), np.empty((nv, 7))
    pst, seg = np.empty(k + 1, np.int64), np.empty((k, 5))
    npts = K._gather_star(u, P, tris, arena, 0, k, head, nxt, sa, sb, geo, pxyz, ps, pst, seg)
    assert npts == n_pts + 1
    for i in range(k):  # slot i's points, their box and their one height
        own = pxyz[pst[i] : pst[i + 1]]
        assert (ps[pst[i] : pst[i + 1]] == i).all() and own.shape[0] == slot_of.count(i)
        if own.shape[0]:
            assert (seg[i, :4] == [own[:, 0].min(), own[:, 0].max(), own[:, 1].min(), own[:, 1].max()]).all()
            assert seg[i, 4] == own[0, 2] if (own[:, 2] == own[0, 2]).all() else np.isnan(seg[i, 4])
    for w in ring:
        g = K._carried_gap2(w, P, sa, sb, k, geo, pxyz, ps, pst, seg, npts, tri, np.inf)
        ref = _reference_gap2(P, ring, w, [u] + list(range(k + 1, nv)))
        assert g == np.float64(ref) or abs(g - ref) <= 1e-9 * max(ref, 1.0)
        lim = 0.5 * ref
        if lim > 0.0:
            assert K._carried_gap2(w, P, sa, sb, k, geo, pxyz, ps, pst, seg, npts, tri, lim) >= lim


@settings(max_examples=150, deadline=None)
@given(
    n_vertices=st.integers(1, 5000),
    k=st.integers(0, 60),
    seed=st.integers(0, 2**32 - 1),
)
def test_block_vertices_are_the_used_vertices_ascending(n_vertices: int, k: int, seed: int) -> None:
    """block_vertices (a mask over the TIN, or a sort of the block's own indices when the TIN is far
    larger) gives the distinct indices the triangles use, ascending, as int64, on both paths."""
    from terralod.tin.qem import block_vertices

    t = np.random.default_rng(seed).integers(0, n_vertices, (k, 3)).astype(np.int32)
    got = block_vertices(t, n_vertices)
    assert got.dtype == np.int64
    np.testing.assert_array_equal(got, np.unique(t.ravel()))
