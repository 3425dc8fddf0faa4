"""Stitching (paper 002 §3.3) and normals (§3.4): a geometric crack detector over random terrains × forced
LoD differences 1..5 and random cameras finds no crack; it does find the cracks of unstitched tiles;
relocated (fractional) boundary vertices; only borders move; normals match the uniform-LoD reference."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from terralod.runtime import Camera, Engine, find_cracks, reference_normals, stitch_leaves, tile_local_normals

from test_runtime_support import (
    SlidingStore,
    brute_boundary_normals,
    corner_spike,
    random_camera,
    spike_partition,
    terrain_store,
    tile_rect,
)

TOL_M = 1e-4


@pytest.fixture(scope="module")
def store6():
    """513 x 513 samples, M = 9: levels 0..6, so LoD differences up to 5 can be forced."""
    s = terrain_store(513, 513, 21, 9, relief_m=600.0, beta=2.7)
    yield s
    s.close()


@pytest.fixture(scope="module", params=["m9", "m5"])
def terrain(request):
    """Two terrains: the 513² M = 9 one, and a non-square 385 x 257 with M = 5 (levels 0..7), where a coarse
    neighbour 3+ levels up has its vertices farther apart than a whole fine tile."""
    if request.param == "m9":
        s = terrain_store(513, 513, 21, 9, relief_m=600.0, beta=2.7)
    else:
        s = terrain_store(257, 385, 4, 5, relief_m=500.0, beta=2.3)
    yield s
    s.close()


@pytest.fixture(scope="module")
def coast():
    """A rough terrain with a flat sea on its west 39 % (the coast off the tile grid): flat coarse tiles
    meet the finest land tiles, so camera selections mix LoDs 3 apart."""
    s = terrain_store(513, 513, 3, 9, relief_m=900.0, beta=2.4, sea=0.39)
    yield s
    s.close()


@pytest.fixture(scope="module")
def store_ns():
    s = terrain_store(201, 140, 7, 9, relief_m=400.0, beta=2.5)
    yield s
    s.close()


def _raw(store, codes):
    return {c: (store.tile(*c).vertices, store.tile(*c).triangles) for c in codes}


def _assert_watertight(meshes, store) -> dict:
    rep = find_cracks(meshes, store.pyramid, store.transform, tol_m=TOL_M)
    assert rep.total_cracked == 0, rep
    assert rep.max_gap_m <= TOL_M
    return rep


@settings(max_examples=15, deadline=None)
@given(st.integers(0, 2**31), st.floats(0.0, 0.3))
def test_forced_partitions_have_no_cracks(terrain, seed: int, p_culled: float) -> None:
    store6 = terrain
    rng = np.random.default_rng(seed)
    leaves = spike_partition(
        store6.pyramid, rng, spikes=int(rng.integers(1, 5)), p_split=float(rng.uniform(0, 0.5))
    )
    visible = rng.random(len(leaves)) >= p_culled
    meshes = stitch_leaves(store6, leaves, visible)
    assert set(meshes) == {c for c, v in zip(leaves, visible, strict=True) if v}
    rep = _assert_watertight(meshes, store6)
    mixed = sum(n for d, n in rep.boundaries.items() if d > 0)
    raw = find_cracks(_raw(store6, meshes), store6.pyramid, store6.transform, tol_m=TOL_M)
    # the detector is not blind: unstitched mixed-LoD borders of a rough terrain do crack
    assert raw.boundaries == rep.boundaries
    if mixed:
        assert sum(raw.cracked[d] for d in raw.cracked if d > 0) > 0
    assert raw.cracked.get(0, 0) == 0  # same-level tiles share their boundary vertices


def test_every_lod_difference_1_to_5_is_stitched(store6) -> None:
    pyr = store6.pyramid
    top = pyr.max_level
    n = (1 << top) - 1
    seen: dict[int, int] = {}
    for corner in [(top, 0, 0), (top, n // 2, n // 2), (top, n // 2 + 1, n // 2), (top, 5, 9), (top, n, 3)]:
        leaves = corner_spike(pyr, corner)
        meshes = stitch_leaves(store6, leaves)
        rep = _assert_watertight(meshes, store6)
        raw = find_cracks(_raw(store6, meshes), pyr, store6.transform, tol_m=TOL_M)
        for d, b in rep.boundaries.items():
            seen[d] = seen.get(d, 0) + b
        assert raw.total_cracked > 0
    assert all(seen.get(d, 0) > 0 for d in range(1, 6)), seen


@settings(max_examples=10, deadline=None)
@given(st.integers(0, 2**31))
def test_relocated_boundary_vertices(store_ns, seed: int) -> None:
    src = SlidingStore(store_ns)
    rng = np.random.default_rng(seed)
    leaves = spike_partition(store_ns.pyramid, rng, spikes=3)
    meshes = stitch_leaves(src, leaves)
    _assert_watertight(meshes, store_ns)
    inserted = 0
    for code, (v, t, nrm) in meshes.items():
        tile = src.tile(*code)
        n0 = len(tile.vertices)
        inserted += len(v) - n0
        # the tile's own vertices keep their xy; inserted ones lie on the tile square
        assert np.array_equal(v[:n0, :2], tile.vertices[:, :2])
        r0, c0, r1, c1 = tile_rect(store_ns.pyramid, code)
        tr = store_ns.transform
        rows = (v[n0:, 1] - (tr.f + 0.5 * tr.e)) / tr.e
        cols = (v[n0:, 0] - (tr.c + 0.5 * tr.a)) / tr.a
        on = (
            (np.abs(rows - r0) < 1e-6)
            | (np.abs(rows - r1) < 1e-6)
            | (np.abs(cols - c0) < 1e-6)
            | (np.abs(cols - c1) < 1e-6)
        )
        assert on.all()
        # fan splits keep every triangle counter-clockwise seen from above and every vertex used
        a, b, c = v[t[:, 0]], v[t[:, 1]], v[t[:, 2]]
        cross = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
        assert (cross > 0).all()
        assert np.array_equal(np.unique(t), np.arange(len(v)))
        assert np.all(np.isfinite(nrm)) and np.allclose(np.linalg.norm(nrm, axis=1), 1.0, atol=1e-6)
        # off the border a normal is the tile's own (patched after the fan splits, not recomputed): it must
        # equal the normal recomputed from every triangle of the stitched tile
        rows_all = (v[:, 1] - (tr.f + 0.5 * tr.e)) / tr.e
        cols_all = (v[:, 0] - (tr.c + 0.5 * tr.a)) / tr.a
        inner = (
            (np.abs(rows_all - r0) > 1e-6) & (np.abs(rows_all - r1) > 1e-6)
            & (np.abs(cols_all - c0) > 1e-6) & (np.abs(cols_all - c1) > 1e-6)
        )  # fmt: skip
        assert np.abs(nrm[inner] - tile_local_normals(v, t)[inner]).max(initial=0.0) < 1e-5
    assert inserted > 0  # relocated coarse vertices fell inside fine segments and were inserted


def test_only_borders_move(store6) -> None:
    rng = np.random.default_rng(5)
    pyr = store6.pyramid
    for _ in range(4):
        leaves = spike_partition(pyr, rng, spikes=3)
        visible = rng.random(len(leaves)) > 0.15
        meshes = stitch_leaves(store6, leaves, visible)
        levels = {c: c[0] for c in meshes}
        for code, (v, t, _) in meshes.items():
            tile = store6.tile(*code)
            n0 = len(tile.vertices)
            # stored vertices keep their place; vertices added to close T-junctions lie on the tile border
            assert np.array_equal(v[:n0, :2], tile.vertices[:, :2])
            if len(v) > n0:
                r0, c0, r1, c1 = tile_rect(pyr, code)
                t0 = store6.transform
                cols_new = (v[n0:, 0] - (t0.c + 0.5 * t0.a)) / t0.a
                rows_new = (v[n0:, 1] - (t0.f + 0.5 * t0.e)) / t0.e
                on = (np.isclose(rows_new, r0) | np.isclose(rows_new, r1) | np.isclose(cols_new, c0)
                      | np.isclose(cols_new, c1))  # fmt: skip
                assert on.all(), "an added vertex is not on the tile border"
            else:
                assert np.array_equal(t, tile.triangles)
            moved = np.flatnonzero(v[:n0, 2] != tile.vertices[:, 2])
            rows = np.rint(tile.grid_rc[moved, 0]).astype(int)
            cols = np.rint(tile.grid_rc[moved, 1]).astype(int)
            r0, c0, r1, c1 = tile_rect(pyr, code)
            assert np.all((rows == r0) | (rows == r1) | (cols == c0) | (cols == c1)), (
                "an interior vertex moved"
            )
            # a vertex moves only if a strictly coarser visible tile touches its position
            for r, c in zip(rows.tolist(), cols.tolist(), strict=True):
                touching = [q for q in meshes if q != code and _touches(pyr, q, r, c)]
                assert any(levels[q] < code[0] for q in touching)


def _touches(pyr, q, r, c) -> bool:
    a0, b0, a1, b1 = tile_rect(pyr, q)
    return a0 <= r <= a1 and b0 <= c <= b1


def test_normals_uniform_lod_equal_reference(store6) -> None:
    pyr = store6.pyramid
    for level in (2, 4):
        leaves = list(pyr.tile_codes(level))
        meshes = stitch_leaves(store6, leaves)
        ref = reference_normals({c: (v, t) for c, (v, t, _) in meshes.items()})
        worst = max(float(np.abs(ref[c] - n).max()) for c, (_, _, n) in meshes.items())
        assert worst <= 1e-6
        # tile-local normals ("conventional") differ at the borders: the comparison is not vacuous
        local = max(float(np.abs(ref[c] - tile_local_normals(v, t)).max()) for c, (v, t, _) in meshes.items())
        assert local > 1e-3


@settings(max_examples=6, deadline=None)
@given(st.integers(0, 2**31), st.booleans())
def test_boundary_normals_follow_their_definition(store_ns, seed: int, sliding: bool) -> None:
    rng = np.random.default_rng(seed)
    src = SlidingStore(store_ns) if sliding else store_ns
    leaves = spike_partition(store_ns.pyramid, rng, spikes=2)
    visible = rng.random(len(leaves)) > 0.1
    meshes = stitch_leaves(src, leaves, visible)
    ref = brute_boundary_normals(meshes, store_ns.pyramid, store_ns.transform)
    for code, (bnd, n_ref) in ref.items():
        assert np.abs(meshes[code][2][bnd] - n_ref).max() <= 1e-6


def test_normals_where_lod_is_uniform_match_uniform_reference(store6) -> None:
    """In a mixed selection, vertices whose whole neighbourhood is level k and unmoved get the normal of
    the all-level-k mesh."""
    pyr = store6.pyramid
    top = pyr.max_level
    uni = stitch_leaves(store6, list(pyr.tile_codes(top - 1)))
    ref = reference_normals({c: (v, t) for c, (v, t, _) in uni.items()})
    leaves = corner_spike(pyr, (top, 3, 40))
    # refine everything else down to level top - 1 so level top - 1 dominates
    leaves = [k for c in leaves for k in ([c] if c[0] >= top - 1 else _descend(pyr, c, top - 1))]
    mixed = stitch_leaves(store6, leaves)
    checked = 0
    for code, (v, t, n) in mixed.items():
        if code[0] != top - 1:
            continue
        raw = store6.tile(*code).vertices
        n0 = len(raw)
        moved = np.ones(len(v), bool)  # vertices added to close T-junctions count as moved
        moved[:n0] = v[:n0, 2] != raw[:, 2]
        ring_moved = np.zeros(len(v), bool)
        np.logical_or.at(ring_moved, t.ravel(), np.repeat(moved[t].any(axis=1), 3))
        # ... and no neighbour of another level touches the vertex
        r0, c0, r1, c1 = tile_rect(pyr, code)
        near_other = np.array([
            any(q[0] != code[0] and _touches(pyr, q, r, c) for q in mixed)
            for r, c in np.rint(store6.tile(*code).grid_rc).astype(int).tolist()
        ])  # fmt: skip
        ok = ~ring_moved[:n0] & ~near_other
        assert np.abs(n[:n0][ok] - ref[code][ok]).max() <= 1e-6
        checked += int(ok.sum())
    assert checked > 0


def _descend(pyr, code, level):
    out, stack = [], [code]
    while stack:
        c = stack.pop()
        if c[0] >= level:
            out.append(c)
        else:
            stack.extend(pyr.children(c))
    return out


def test_engine_frames_are_watertight_and_incremental_equals_full(coast) -> None:
    store6 = coast
    rng = np.random.default_rng(12)
    inc = Engine(store6, threshold_px=1.0)
    full = Engine(store6, threshold_px=1.0, stitch_mode="full", incremental=False)
    cam = random_camera(rng, store6)
    differences: set[int] = set()
    for f in range(10):  # two random jumps (frames 4 and 9) among small steps
        if f % 5 == 4:
            cam = random_camera(rng, store6)
        else:
            step = rng.normal(size=3) * np.array([400, 400, 60])
            cam = Camera(tuple(np.array(cam.eye) + step), tuple(np.array(cam.target) + step), fov_y_deg=cam.fov_y_deg,
                         width_px=cam.width_px, height_px=cam.height_px)  # fmt: skip
        a, b = inc.update(cam), full.update(cam)
        assert a.tiles == b.tiles
        ma, mb = a.mesh_dict(), b.mesh_dict()
        for code in ma:
            for x, y in zip(ma[code], mb[code], strict=True):
                assert np.array_equal(x, y), (f, code)
        rep = _assert_watertight(ma, store6)
        differences |= {d for d, n in rep.boundaries.items() if n}
        assert a.stats.crack_tiles <= b.stats.crack_tiles == len(a.tiles)
    assert max(differences) >= 2


def test_detector_finds_small_gaps_and_holes(store6) -> None:
    pyr = store6.pyramid
    leaves = corner_spike(pyr, (pyr.max_level, 9, 9))
    meshes = {c: (v.copy(), t.copy()) for c, (v, t, _) in stitch_leaves(store6, leaves).items()}
    assert find_cracks(meshes, pyr, store6.transform).total_cracked == 0
    code = next(c for c in meshes if c[0] == pyr.max_level)
    v, t = meshes[code]
    r0, c0, _, _ = tile_rect(pyr, code)
    i = int(np.flatnonzero(store6.tile(*code).grid_rc[:, 0] == r0)[3])
    bumped = {**meshes, code: (v + np.where(np.arange(len(v))[:, None] == i, [0, 0, 3 * TOL_M], 0), t)}
    rep = find_cracks(bumped, pyr, store6.transform, tol_m=TOL_M)
    assert rep.total_cracked >= 1 and 2 * TOL_M < rep.max_gap_m < 4 * TOL_M
    # a missing border triangle leaves a hole in the neighbour's span
    on = np.isin(t, np.flatnonzero(store6.tile(*code).grid_rc[:, 0] == r0)).sum(axis=1) == 2
    holed = {**meshes, code: (v, t[~(np.cumsum(on) == 2) | ~on])}
    assert find_cracks(holed, pyr, store6.transform).total_cracked >= 1


def test_no_t_junction_remains(store6) -> None:
    """After stitching, every boundary vertex of a visible tile is also a vertex (same x, y, z bit for bit)
    of every other visible tile whose border passes through it — the rasteriser sees no T-junction."""
    rng = np.random.default_rng(11)
    pyr = store6.pyramid
    t0 = store6.transform
    for _ in range(4):
        leaves = spike_partition(pyr, rng, spikes=3)
        meshes = stitch_leaves(store6, leaves)
        keys = {}
        rects = {}
        for code, (v, t, _) in meshes.items():
            keys[code] = {tuple(p) for p in v.tolist()}
            rects[code] = tile_rect(pyr, code)
            a = v[t[:, 0]]
            b = v[t[:, 1]]
            c = v[t[:, 2]]
            area = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
            assert (area > 0).all(), f"{code}: a triangle is not counter-clockwise"
        checked = 0
        for code, (v, _, _) in meshes.items():
            r0, c0, r1, c1 = rects[code]
            cols = (v[:, 0] - (t0.c + 0.5 * t0.a)) / t0.a
            rows = (v[:, 1] - (t0.f + 0.5 * t0.e)) / t0.e
            border = np.isclose(rows, r0) | np.isclose(rows, r1) | np.isclose(cols, c0) | np.isclose(cols, c1)
            for p, r, c in zip(v[border].tolist(), rows[border].tolist(), cols[border].tolist(), strict=True):
                for q, (a0, b0, a1, b1) in rects.items():
                    if q == code or not (a0 - 1e-9 <= r <= a1 + 1e-9 and b0 - 1e-9 <= c <= b1 + 1e-9):
                        continue
                    on_border = min(abs(r - a0), abs(r - a1), abs(c - b0), abs(c - b1)) < 1e-9
                    if on_border and len(meshes[q][0]):
                        checked += 1
                        assert tuple(p) in keys[q], f"T-junction: {code} vertex {p} not a vertex of {q}"
        assert checked > 0
