"""Adaptive tiles (greedy-insertion TIN per tile, terralod.pyramid.adaptive): every invariant the other
methods obey, over random terrains — stored >= measured errors, monotone, no fold-over, the tile's data
rectangle covered exactly, shared borders bit-identical, the ladder met, byte-identical rebuilds — and the
runtime's stitching closes every crack for forced LoD differences and along engine frames."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from terralod import Heightfield, build_store, open_store
from terralod.error import measure_error_window
from terralod.kernels.adaptive import simplify_line, tin_window, tin_window_seeded
from terralod.pyramid import adaptive
from terralod.runtime import Engine, find_cracks, stitch_leaves
from terralod.tiles import TilePyramid, parent

from conftest import fractal_terrain
from test_runtime_support import random_camera, spike_partition

SPACING_M = 30.0


def _terrain(rows: int, cols: int, seed: int, relief_m: float, sea: float) -> np.ndarray:
    z = fractal_terrain(rows, cols, seed, relief_m=relief_m, beta=2.4)
    z[:, : int(sea * cols)] = 0.0  # a flat sea: tiles of 2 triangles beside rough ones
    return z


def _rows_cols(store, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    t = store.transform
    return (v[:, 1] - (t.f + 0.5 * t.e)) / t.e, (v[:, 0] - (t.c + 0.5 * t.a)) / t.a


def _check_store(store, z: np.ndarray) -> None:
    pyr = store.pyramid
    h, w = z.shape
    opts = store.meta["build_options"]
    ladder = opts["target_error_m"]
    assert len(ladder) == pyr.max_level + 1
    halving = ladder if opts["finest_level_error_m"] is None else ladder[:-1]
    assert all(a == 2.0 * b for a, b in zip(halving, halving[1:], strict=False))  # halving from the root
    if opts["finest_level_error_m"] == 0.0:
        assert ladder[-1] == 0.0
    errs = store.tile_errors()
    lines: dict[tuple, dict] = {}
    for code in pyr.all_codes():
        tile = store.tile(*code)
        raw = store.raw_tile(*code)
        # stored >= measured; monotone over the pyramid
        assert raw.error_m >= raw.measured_error_m and raw.vertical_error_m >= raw.measured_vertical_error_m
        assert raw.measured_error_m <= raw.measured_vertical_error_m + 1e-9
        if parent(code) is not None:
            pe, pv = errs[parent(code)]
            assert pe >= raw.error_m and pv >= raw.vertical_error_m
        # the level's target is met up to the vertical quantisation step
        assert raw.measured_vertical_error_m <= ladder[code[0]] + store.quantisation[code[0]].z_step_m
        v, t = tile.vertices, tile.triangles.astype(np.int64)
        rows, cols = _rows_cols(store, v)
        # no fold-over: counter-clockwise seen from above, positive area; every vertex used
        a, b, c = v[t[:, 0]], v[t[:, 1]], v[t[:, 2]]
        cross = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
        assert (cross > 0).all()
        assert np.array_equal(np.unique(t), np.arange(len(v)))
        # vertices are source samples with their own heights (on the level's lattice)
        assert np.array_equal(rows, np.rint(rows)) and np.array_equal(cols, np.rint(cols))
        # the data rectangle of the tile is covered exactly (areas in samples^2 sum to its area)
        r0, c0 = pyr.origin_rc(code)
        span = pyr.span(code[0])
        r1, c1 = min(r0 + span, h - 1), min(c0 + span, w - 1)
        assert rows.min() == r0 and rows.max() == r1 and cols.min() == c0 and cols.max() == c1
        assert np.isclose(cross.sum() / 2.0 / (SPACING_M * SPACING_M), (r1 - r0) * (c1 - c0))
        if ladder[code[0]] == 0.0:  # a lossless finest level: the regular grid of the tile's samples
            assert len(v) == (r1 - r0 + 1) * (c1 - c0 + 1) and len(t) == 2 * (r1 - r0) * (c1 - c0)
            assert raw.measured_vertical_error_m <= store.quantisation[code[0]].z_step_m
        # border vertices, per line of the level (to compare with the neighbour's)
        for key, on in (
            (("row", code[0], r0), rows == r0),
            (("row", code[0], r1), rows == r1),
            (("col", code[0], c0), cols == c0),
            (("col", code[0], c1), cols == c1),
        ):
            lines.setdefault(key, {})[code] = {tuple(p) for p in v[on].tolist()}
    # same-level neighbours share their border vertices bit for bit (world x, y and the stored z)
    for (kind, _level, _), tiles in lines.items():
        for code, pts in tiles.items():
            for other, opts in tiles.items():
                if other == code:
                    continue
                same_span = other[1] == code[1] if kind == "row" else other[2] == code[2]
                adjacent = abs(other[1] - code[1]) + abs(other[2] - code[2]) == 1
                if same_span and adjacent:
                    assert pts == opts, (code, other)


@settings(max_examples=5, deadline=None)
@given(
    st.integers(20, 70),
    st.integers(20, 70),
    st.integers(0, 2**20),
    st.floats(5.0, 800.0),
    st.sampled_from([0.0, 0.4]),
    st.sampled_from([5, 9, 17]),
    st.sampled_from(["adaptive", "adaptive_ladder"]),
)
def test_adaptive_store_invariants(tmp_path_factory, rows, cols, seed, relief_m, sea, m, method) -> None:
    """The default (grid finest level) and the ladder down to the finest level both obey every invariant."""
    z = _terrain(rows, cols, seed, relief_m, sea)
    hf = Heightfield.from_array(z, SPACING_M, origin_m=(500000.0, 4600000.0))
    d = tmp_path_factory.mktemp("ad")
    build_store(hf, d / "a.terra", tile_size=m, method=method, workers=2)
    with open_store(d / "a.terra") as store:
        _check_store(store, z)
        first = {c: store.raw_tile(*c) for c in store.pyramid.all_codes()}
        meta = store.meta
    # byte-identical rebuild (one worker this time: the order tiles are meshed in does not matter)
    build_store(hf, d / "b.terra", tile_size=m, method=method, workers=1)
    with open_store(d / "b.terra") as again:
        assert again.meta["build_options"] == meta["build_options"]
        assert all(again.raw_tile(*c) == first[c] for c in first)


def test_flat_tiles_are_two_triangles_and_ladder_options(tmp_path) -> None:
    z = np.full((65, 97), 12.5, np.float32)
    hf = Heightfield.from_array(z, SPACING_M)
    build_store(hf, tmp_path / "f.terra", tile_size=17, method="adaptive")
    with open_store(tmp_path / "f.terra") as store:
        top = store.pyramid.max_level
        rows = store.tile_summaries()
        assert all(r["n_triangles"] == 2 and r["error_m"] == 0.0 for r in rows if r["level"] < top)
        assert all(r["n_triangles"] == 2 * 16 * 16 for r in rows if r["level"] == top)  # the grid
    build_store(hf, tmp_path / "g.terra", tile_size=17, method="adaptive_ladder")
    with open_store(tmp_path / "g.terra") as store:
        assert all(r["n_triangles"] == 2 and r["error_m"] == 0.0 for r in store.tile_summaries())
    pyr = TilePyramid(97, 65, 17)
    assert adaptive.target_ladder(pyr, adaptive.AdaptiveOptions(finest_error_m=1.5)) == [
        1.5 * 2**k for k in range(pyr.max_level, -1, -1)
    ]
    assert adaptive.target_ladder(pyr, adaptive.AdaptiveOptions(root_error_m=64.0)) == [64.0, 32.0, 16.0, 0.0]
    ladder_only = adaptive.AdaptiveOptions(root_error_m=64.0, finest_level_error_m=None)
    assert adaptive.target_ladder(pyr, ladder_only)[-1] == 64.0 / 2**pyr.max_level
    with pytest.raises(ValueError, match="root_error_m"):
        adaptive.AdaptiveOptions(root_error_m=0.0)


@settings(max_examples=20, deadline=None)
@given(st.integers(2, 300), st.integers(0, 2**20), st.floats(0.0, 50.0))
def test_simplify_line_meets_its_target(n, seed, target) -> None:
    rng = np.random.default_rng(seed)
    z = np.cumsum(rng.normal(0.0, 10.0, n)).astype(np.float32)
    ok = rng.random(n) > 0.1
    keep = simplify_line(z, ok, target)
    assert keep[0] == 0 and keep[-1] == n - 1 and np.all(np.diff(keep) > 0)
    interp = np.interp(np.arange(n), keep, z[keep].astype(np.float64))
    assert (np.abs(z - interp)[ok] <= target + 1e-9).all()
    # a lower target never keeps fewer samples
    assert len(simplify_line(z, ok, target / 2)) >= len(keep)


@settings(max_examples=15, deadline=None)
@given(st.integers(2, 40), st.integers(2, 40), st.integers(0, 2**20), st.floats(0.0, 30.0))
def test_tin_window_meets_target_without_fold_over(h, w, seed, target) -> None:
    """The kernel alone (no fixed border beyond the corners): every interior sample within the target,
    exact coverage, Delaunay-made triangles all counter-clockwise."""
    rng = np.random.default_rng(seed)
    z = np.ascontiguousarray(rng.normal(0.0, 20.0, (h, w)).astype(np.float32))
    valid = np.ones((h, w), np.bool_)
    valid[0, :] = valid[-1, :] = valid[:, 0] = valid[:, -1] = False  # the border is not measured here
    e = np.zeros(0, np.int64)
    px, py, tris, worst, best = tin_window(z, valid, e, e, target, h * w)
    a = np.stack([px, py], 1)[tris.astype(np.int64)]
    cross = (a[:, 1, 0] - a[:, 0, 0]) * (a[:, 2, 1] - a[:, 0, 1]) - (a[:, 1, 1] - a[:, 0, 1]) * (
        a[:, 2, 0] - a[:, 0, 0]
    )
    assert (cross > 0).all() and cross.sum() == 2 * (h - 1) * (w - 1)
    assert len({(x, y) for x, y in zip(px.tolist(), py.tolist(), strict=True)}) == len(px)
    verts = np.stack([px, py, z[py, px]], 1).astype(np.float64)
    rep = measure_error_window(verts, tris[:, [0, 2, 1]], z, valid, 1.0, 1.0)
    assert worst <= target and rep.max_vertical_m <= target + 1e-4


@settings(max_examples=10, deadline=None)
@given(st.integers(4, 24), st.integers(4, 24), st.integers(0, 2**20))
def test_tin_window_best_error_is_the_running_minimum_of_measured_max_errors(h, w, seed) -> None:
    """``best_error`` with a cap of n vertices is the lowest measured max error of the meshes the insertion
    made with at most n vertices (so it never rises with n), while ``max_error`` is that cap's mesh's own
    measured max error (which may rise: a flip can make a worse triangle)."""
    rng = np.random.default_rng(seed)
    z = np.ascontiguousarray(np.cumsum(rng.normal(0.0, 20.0, (h, w)), axis=1).astype(np.float32))
    valid = np.ones((h, w), np.bool_)
    valid[0, :] = valid[-1, :] = valid[:, 0] = valid[:, -1] = False
    e = np.zeros(0, np.int64)
    running = np.inf
    for cap in range(4, min(h * w, 4 + 3 * (h - 2) * (w - 2) // 4) + 1):
        px, py, tris, worst, best = tin_window(z, valid, e, e, 0.0, cap)
        verts = np.stack([px, py, z[py, px]], 1).astype(np.float64)
        measured = measure_error_window(verts, tris[:, [0, 2, 1]], z, valid, 1.0, 1.0).max_vertical_m
        assert abs(worst - measured) <= 1e-4 * max(1.0, measured)
        if len(px) == cap:  # (the insertion stopped at the cap, not because every sample was exact)
            running = min(running, worst)
            assert best == pytest.approx(running, abs=1e-9)
        assert best <= worst


@settings(max_examples=20, deadline=None)
@given(
    st.integers(3, 90), st.integers(3, 90), st.integers(0, 2**20), st.floats(0.0, 30.0), st.integers(0, 400)
)
def test_seeded_tin_window_keeps_its_seeds_and_meets_target(h, w, seed, target, n_seeds) -> None:
    """Seeds (any distinct interior samples, as a decimated pass gives them) are vertices of the result,
    which still meets the target at every interior sample, covers the window exactly, never folds."""
    rng = np.random.default_rng(seed)
    z = np.ascontiguousarray(rng.normal(0.0, 20.0, (h, w)).astype(np.float32))
    z[:, : w // 3] = 5.0  # level ground too: seeds on flat runs, co-circular samples
    valid = np.ones((h, w), np.bool_)
    valid[0, :] = valid[-1, :] = valid[:, 0] = valid[:, -1] = False
    interior = np.flatnonzero(np.ones((h - 2, w - 2), np.bool_))
    pick = np.sort(rng.choice(interior.size, min(n_seeds, interior.size), replace=False))
    sy, sx = np.divmod(interior[pick], w - 2)
    sx, sy = (sx + 1).astype(np.int64), (sy + 1).astype(np.int64)
    e = np.zeros(0, np.int64)
    px, py, tris, worst, best = tin_window_seeded(z, valid, e, e, sx, sy, target, h * w)
    a = np.stack([px, py], 1)[tris.astype(np.int64)]
    cross = (a[:, 1, 0] - a[:, 0, 0]) * (a[:, 2, 1] - a[:, 0, 1]) - (a[:, 1, 1] - a[:, 0, 1]) * (
        a[:, 2, 0] - a[:, 0, 0]
    )
    assert (cross > 0).all() and cross.sum() == 2 * (h - 1) * (w - 1)
    verts = {(x, y) for x, y in zip(px.tolist(), py.tolist(), strict=True)}
    assert len(verts) == len(px) and {(x, y) for x, y in zip(sx.tolist(), sy.tolist(), strict=True)} <= verts
    pts = np.stack([px, py, z[py, px]], 1).astype(np.float64)
    rep = measure_error_window(pts, tris[:, [0, 2, 1]], z, valid, 1.0, 1.0)
    assert worst <= target and rep.max_vertical_m <= target + 1e-4


@pytest.fixture(scope="module")
def adaptive_store(tmp_path_factory):
    """A rough 129 x 193 terrain with a flat sea, M = 9 (levels 0..5): large LoD differences meet."""
    z = _terrain(129, 193, 11, 600.0, 0.3)
    p = tmp_path_factory.mktemp("st") / "adaptive.terra"
    build_store(Heightfield.from_array(z, SPACING_M, origin_m=(400000.0, 5300000.0)), p, tile_size=9,
                method="adaptive", workers=2)  # fmt: skip
    with open_store(p) as s:
        yield s


@settings(max_examples=4, deadline=None)
@given(st.integers(0, 2**31))
def test_adaptive_forced_partitions_have_no_cracks(adaptive_store, seed) -> None:
    store = adaptive_store
    rng = np.random.default_rng(seed)
    leaves = spike_partition(store.pyramid, rng, spikes=int(rng.integers(1, 4)), p_split=0.3)
    meshes = stitch_leaves(store, leaves)
    rep = find_cracks(meshes, store.pyramid, store.transform, tol_m=1e-4)
    assert rep.total_cracked == 0, rep
    raw = {c: (store.tile(*c).vertices, store.tile(*c).triangles) for c in meshes}
    raw_rep = find_cracks(raw, store.pyramid, store.transform, tol_m=1e-4)
    assert raw_rep.cracked.get(0, 0) == 0  # same-level tiles share their border vertices
    if sum(n for d, n in rep.boundaries.items() if d > 0):
        assert sum(raw_rep.cracked[d] for d in raw_rep.cracked if d > 0) > 0  # the detector sees cracks


def test_adaptive_engine_frames_are_watertight(adaptive_store) -> None:
    rng = np.random.default_rng(3)
    engine = Engine(adaptive_store, threshold_px=2.0)
    levels = set()
    for _ in range(3):
        frame = engine.update(random_camera(rng, adaptive_store))
        meshes = {code: (v, t) for code, v, t, _n in frame.meshes()}
        levels |= {c[0] for c in meshes}
        rep = find_cracks(meshes, adaptive_store.pyramid, adaptive_store.transform, tol_m=1e-4)
        assert rep.total_cracked == 0, rep
    assert len(levels) >= 2


def test_mesher_for_a_store_remakes_its_tiles(adaptive_store) -> None:
    """A partial rebuild meshes with the store's stated ladder: the same tiles, bit for bit, even when the
    terrain (hence the default ladder) has changed elsewhere."""
    z = _terrain(129, 193, 11, 600.0, 0.3)
    valid = np.ones(z.shape, np.bool_)
    stated = adaptive.mesher_for(adaptive_store.meta["build_options"])
    pyr = adaptive_store.pyramid
    codes = [(k, 0, 0) for k in pyr.levels] + [(pyr.max_level, 3, 2)]
    for code in codes:
        ref = adaptive.mesh_tile(z, valid, pyr, code)
        assert all(np.array_equal(a, b) for a, b in zip(stated(z, valid, pyr, code), ref, strict=True))
    z2 = z.copy()
    z2[-5:, -5:] += 300.0  # a change far from tile (k, 0, 0): the default ladder moves, the stated one not
    assert (
        adaptive.target_ladder(pyr, adaptive.AdaptiveOptions(), z2, valid)
        != adaptive_store.meta["build_options"]["target_error_m"]
    )
    for code in codes[:-1]:
        ref = adaptive.mesh_tile(z, valid, pyr, code)
        if code[0] == pyr.max_level:
            assert all(np.array_equal(a, b) for a, b in zip(stated(z2, valid, pyr, code), ref, strict=True))


@settings(max_examples=6, deadline=None)
@given(
    st.integers(20, 140),
    st.integers(20, 140),
    st.integers(0, 2**20),
    st.floats(20.0, 800.0),
    st.sampled_from([5, 9, 17]),
)
def test_halving_the_tile_size_adds_a_level_and_keeps_the_others(rows, cols, seed, relief_m, m) -> None:
    """Tiles of size (m - 1) / 2 + 1 mesh every level that tiles of m have (same footprints) alike, bit for
    bit, and add one ladder level, at half the target of m's last: the tile size sets how deep the ladder
    goes, not what it is (the root's vertex count does not move with M)."""
    z = _terrain(rows, cols, seed, relief_m, 0.0)
    valid = np.ones(z.shape, bool)
    big, small = TilePyramid(cols, rows, m), TilePyramid(cols, rows, (m - 1) // 2 + 1)
    opt = adaptive.AdaptiveOptions(root_vertices=m * m)
    lb, ls = adaptive.target_ladder(big, opt, z, valid), adaptive.target_ladder(small, opt, z, valid)
    top = big.max_level
    assert small.max_level == top + 1 and small.span(0) == big.span(0)
    assert ls[: top + 1] == lb[:top] + [lb[top - 1] / 2.0] and ls[-1] == lb[-1] == 0.0
    default = adaptive.AdaptiveOptions()  # the root at ROOT_VERTICES whatever M: the same ladder
    assert (
        adaptive.target_ladder(big, default, z, valid)[:top]
        == adaptive.target_ladder(small, default, z, valid)[:top]
    )
    for code in big.all_codes():
        if code[0] == top:
            continue  # m's finest level is the grid; small's level there is the ladder's next step
        a = adaptive.mesh_tile_with(z, valid, big, code, opt)
        b = adaptive.mesh_tile_with(z, valid, small, code, opt)
        assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True)), code


def test_seeded_coarse_tiles_do_not_depend_on_the_tile_size() -> None:
    """A window of 512 samples and more is seeded from every (span / 256)-th sample whatever M: its mesh
    with 33² tiles is the one with 65² tiles."""
    z = _terrain(600, 560, 3, 900.0, 0.0)
    valid = np.ones(z.shape, bool)
    opt = adaptive.AdaptiveOptions(root_vertices=2000)
    p65, p33 = TilePyramid(560, 600, 65), TilePyramid(560, 600, 33)
    assert p65.span(0) == p33.span(0) >= adaptive.SEED_MIN_SPAN
    a = adaptive.mesh_tile_with(z, valid, p65, (0, 0, 0), opt)
    b = adaptive.mesh_tile_with(z, valid, p33, (0, 0, 0), opt)
    assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
    assert len(a[0]) > 100  # a real TIN, not two triangles


def test_default_tile_size_is_the_methods() -> None:
    from terralod.pyramid.builder import default_tile_size

    assert default_tile_size("adaptive") == adaptive.DEFAULT_TILE_SIZE == 33
    assert default_tile_size("chunked") == default_tile_size("cohesion") == 65
    z = _terrain(70, 90, 1, 300.0, 0.0)
    hf = Heightfield.from_array(z, SPACING_M)
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        build_store(hf, f"{d}/a.terra", method="adaptive")
        build_store(hf, f"{d}/c.terra", method="chunked")
        with open_store(f"{d}/a.terra") as a, open_store(f"{d}/c.terra") as c:
            assert a.tile_size == 33 and c.tile_size == 65
        build_store(hf, f"{d}/s.terra", method="adaptive", tile_size=17)
        import sqlite3

        from terralod.store import page_size_bytes

        for name, m in (("a", 33), ("c", 65), ("s", 17)):
            conn = sqlite3.connect(f"{d}/{name}.terra")
            assert (
                conn.execute("PRAGMA page_size").fetchone()[0]
                == page_size_bytes(m)
                == (1024 if m == 17 else 2048)
            )
            conn.close()
