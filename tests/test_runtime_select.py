"""Selection: partition, threshold and minimality invariants, culling, incremental == fresh, reuse when
still, triangle budget, parent fallback, background mode and the tile cache."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from terralod.runtime import Camera, Engine, TileCache
from terralod.runtime.camera import box_distance, box_visible
from terralod.tiles import parent

from test_runtime_support import random_camera, terrain_store


@pytest.fixture(scope="module")
def store():
    s = terrain_store(257, 257, 11, 9)
    yield s
    s.close()


@pytest.fixture(scope="module")
def store_ns():
    """Non-square, with partial tiles at the far edges."""
    s = terrain_store(150, 230, 5, 17, relief_m=800.0, beta=2.6)
    yield s
    s.close()


def _rho(engine: Engine, cam: Camera, slots: np.ndarray, err: np.ndarray) -> np.ndarray:
    """Independent numpy projection of errors (DESIGN.md formula) at the tiles' boxes."""
    d = box_distance(engine.table.boxes[slots], cam.eye)
    return np.asarray(cam.screen_error_px(err, d))


def check_selection(engine: Engine, cam: Camera, sel) -> None:
    idx, tb = engine.index, engine.table
    tau = engine.threshold_px
    vis = idx.slots(sel.tiles) if sel.tiles else np.zeros(0, np.int64)
    culled = idx.slots(sel.culled) if sel.culled else np.zeros(0, np.int64)
    leaves = np.r_[vis, culled]
    # the leaves (drawn and culled) partition the terrain
    assert engine.adjacency.check_partition(leaves) == (0, 0)
    assert len(np.unique(leaves)) == len(leaves)
    # culling is exactly the frustum test of the tile box; drawn tiles intersect the frustum
    assert box_visible(tb.boxes[vis], cam.planes).all() if vis.size else True
    assert not box_visible(tb.boxes[culled], cam.planes).any() if culled.size else True
    # every drawn tile meets the threshold unless it cannot be refined (finest level / children missing)
    fb = np.array([c in sel.fallback for c in sel.tiles], bool)
    rho = _rho(engine, cam, vis, np.where(fb, tb.measured_error_m[vis], tb.error_m[vis]))
    stuck = ~tb.kids_ok[vis]
    assert np.all((rho <= tau * (1 + 1e-12)) | stuck)
    assert np.allclose(rho, sel.screen_error_px, rtol=1e-12, atol=0)
    # minimality: every leaf's parent had to be refined (visible and over the threshold)
    for s in np.r_[vis[~fb], culled].tolist():
        code = idx.code(s)
        p = parent(code)
        if p is None:
            continue
        ps = idx.slot(p)
        assert box_visible(tb.boxes[ps][None], cam.planes)[0]
        assert _rho(engine, cam, np.array([ps]), tb.error_m[[ps]])[0] > tau
    # parent fallback: own geometry within the threshold and no worse than its worst child
    for c in sel.fallback:
        s = idx.slot(c)
        kids = idx.slots(engine.store.pyramid.children(c))
        assert tb.measured_error_m[kids].max() >= tb.measured_error_m[s]
    # the boxes bound the stored geometry (stitching may move a border onto a coarser neighbour's edge,
    # which lies in that neighbour's box)
    for code in sel.tiles[:: max(1, len(sel.tiles) // 20)]:
        v = engine.store.tile(*code).vertices
        b = tb.boxes[idx.slot(code)]
        assert np.all(v >= b[:3] - 1e-6) and np.all(v <= b[3:] + 1e-6)
    assert sel.stats.tiles == len(sel.tiles)
    assert sel.stats.triangles == sum(len(t) for _, _, t, _ in sel.meshes())


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**31), st.sampled_from([0.5, 2.0, 8.0]))
def test_selection_invariants(store, seed: int, tau: float) -> None:
    eng = Engine(store, threshold_px=tau)
    cam = random_camera(np.random.default_rng(seed), store)
    check_selection(eng, cam, eng.update(cam))


@settings(max_examples=15, deadline=None)
@given(st.integers(0, 2**31))
def test_selection_invariants_non_square(store_ns, seed: int) -> None:
    eng = Engine(store_ns, threshold_px=1.0)
    cam = random_camera(np.random.default_rng(seed), store_ns)
    check_selection(eng, cam, eng.update(cam))


def _path(store, seed: int, n: int) -> list[Camera]:
    """A wandering camera: small steps and occasional jumps (so merges, splits and big changes all occur)."""
    rng = np.random.default_rng(seed)
    cams = [random_camera(rng, store)]
    for _ in range(n - 1):
        c = cams[-1]
        if rng.random() < 0.15:
            cams.append(random_camera(rng, store))
            continue
        step = rng.normal(size=3) * np.array([300, 300, 80])
        eye = np.array(c.eye) + step
        tgt = np.array(c.target) + step + rng.normal(size=3) * 100
        cams.append(
            Camera(tuple(eye), tuple(tgt), fov_y_deg=c.fov_y_deg, width_px=c.width_px, height_px=c.height_px)
        )
    return cams


@settings(max_examples=4, deadline=None)
@given(st.integers(0, 2**31))
def test_incremental_equals_fresh(store, seed: int) -> None:
    inc = Engine(store, threshold_px=1.5)
    for cam in _path(store, seed, 18):  # 4 wandering paths of 18 views (merges, splits and jumps all occur)
        a = inc.update(cam)
        b = Engine(store, threshold_px=1.5).update(cam)
        assert a.tiles == b.tiles and a.culled == b.culled and a.fallback == b.fallback
        assert np.array_equal(a.screen_error_px, b.screen_error_px)


def test_still_camera_reuses_the_result(store) -> None:
    eng = Engine(store)
    cam = random_camera(np.random.default_rng(3), store)
    a = eng.update(cam)
    b = eng.update(Camera(cam.eye, cam.target, cam.up, cam.fov_y_deg, cam.width_px, cam.height_px))
    assert b is a
    moved = Camera(tuple(np.array(cam.eye) + 1.0), cam.target, fov_y_deg=cam.fov_y_deg,
                   width_px=cam.width_px, height_px=cam.height_px)  # fmt: skip
    assert eng.update(moved) is not a


def test_triangle_budget(store) -> None:
    rng = np.random.default_rng(8)
    for _ in range(5):
        cam = random_camera(rng, store)
        free = Engine(store, threshold_px=1.0).update(cam)
        budgets = [int(free.stats.triangles * f) for f in (0.2, 0.5, 0.9)]
        tris = []
        for b in budgets:
            eng = Engine(store, threshold_px=1.0, triangle_budget=b)
            sel = eng.update(cam)
            root_tris = eng.table.triangles[0]
            # the budget counts stored triangles; stitching may add a few splitting T-junctions
            stored = int(eng.table.triangles[eng.index.slots(sel.tiles)].sum())
            assert stored <= max(b, root_tris) and stored <= sel.stats.triangles
            assert eng.adjacency.check_partition(eng.index.slots(sel.tiles + sel.culled)) == (0, 0)
            tris.append(stored)
            # largest error first: every tile that was split projects at least the error of any drawn tile
            # still waiting to be split (errors are monotone, so the split sequence is non-increasing)
            vis = eng.index.slots(sel.tiles)
            rho = _rho(eng, cam, vis, eng.table.error_m[vis])
            waiting = rho[(rho > 1.0) & eng.table.kids_ok[vis]]
            split = {p for c in sel.tiles + sel.culled for p in _ancestors(c)}
            if waiting.size and split:
                ss = eng.index.slots(sorted(split))
                assert _rho(eng, cam, ss, eng.table.error_m[ss]).min() >= waiting.max()
        assert tris == sorted(tris)
        big = Engine(store, threshold_px=1.0, triangle_budget=10**9).update(cam)
        assert big.tiles == free.tiles


def _ancestors(code):
    p = parent(code)
    while p is not None:
        yield p
        p = parent(p)


class _WorseChildren:
    """Store wrapper whose finest tiles claim a larger measured error than their parent (cohesion-map case);
    the engine makes the monotone error of every ancestor follow."""

    def __init__(self, store, factor: float) -> None:
        self._s, self.pyramid, self.transform, self.factor = store, store.pyramid, store.transform, factor

    def tile(self, *a):
        return self._s.tile(*a)

    def tile_summaries(self):
        rows = self._s.tile_summaries()
        by = {(r["level"], r["x"], r["y"]): r for r in rows}
        out = []
        for r in rows:
            r = dict(r)
            p = parent((r["level"], r["x"], r["y"]))
            if p is not None and r["level"] == self.pyramid.max_level:
                r["measured_error_m"] = r["error_m"] = by[p]["measured_error_m"] * self.factor
            out.append(r)
        return out


def test_parent_fallback(store) -> None:
    rng = np.random.default_rng(4)
    hits = 0
    for _ in range(8):
        cam = random_camera(rng, store)
        eng = Engine(_WorseChildren(store, 1.5), threshold_px=4.0)
        sel = eng.update(cam)
        check_selection(eng, cam, sel)
        hits += len(sel.fallback)
        # without the anomaly nothing falls back
        assert not Engine(_WorseChildren(store, 0.0), threshold_px=4.0).update(cam).fallback
    assert hits > 0


def test_background_mode(store) -> None:
    cams = _path(store, 2, 6)
    with Engine(store, threshold_px=2.0, background=True) as eng:
        assert eng.latest() is None
        for c in cams:
            eng.request(c)  # never blocks; older requests are replaced
        sel = eng.wait(timeout=60)
        assert sel is not None and sel.camera.key == cams[-1].key
        ref = Engine(store, threshold_px=2.0).update(cams[-1])
        assert sel.tiles == ref.tiles
    with pytest.raises(RuntimeError):
        Engine(store).request(cams[0])


def test_engine_rejects_bad_options(store) -> None:
    with pytest.raises(ValueError, match="threshold_px"):
        Engine(store, threshold_px=0)
    with pytest.raises(ValueError, match="triangle_budget"):
        Engine(store, triangle_budget=0)
    with pytest.raises(ValueError, match="stitch_mode"):
        Engine(store, stitch_mode="fast")
    with pytest.raises(TypeError):
        Engine(store).update("camera")  # type: ignore[arg-type]


def test_tile_cache_is_lru_bounded(store) -> None:
    cache = TileCache(store, max_tiles=5)
    codes = store.tile_codes(3)[:8]
    for c in codes:
        cache.get(c)
    assert len(cache) == 5 and codes[-1] in cache and codes[0] not in cache
    cache.get(codes[3])  # refresh
    cache.get(codes[0])  # evicts the least recently used (codes[4])
    assert codes[3] in cache and codes[4] not in cache
    assert cache.misses == 9 and cache.hits == 1
    one = cache.get(codes[0]).nbytes
    small = TileCache(store, max_bytes=int(2.5 * one))
    for c in codes:
        small.get(c)
    assert small.nbytes <= 2.5 * one and len(small) == 2


class _Partial:
    """A store whose finest level is missing in the west half (an interrupted or streaming build)."""

    def __init__(self, store) -> None:
        self._s, self.pyramid, self.transform = store, store.pyramid, store.transform
        nx = store.pyramid.grid_count(store.pyramid.max_level)[0]
        self.missing = lambda r: r["level"] == store.pyramid.max_level and r["x"] < nx // 2

    def tile(self, *a):
        if self.missing({"level": a[0], "x": a[1]}):
            raise KeyError(a)
        return self._s.tile(*a)

    def tile_summaries(self):
        return [r for r in self._s.tile_summaries() if not self.missing(r)]


def test_missing_children_fall_back_to_parent(store) -> None:
    src = _Partial(store)
    rng = np.random.default_rng(9)
    top = store.pyramid.max_level
    nx = store.pyramid.grid_count(top)[0]
    for _ in range(6):
        cam = random_camera(rng, store)
        eng = Engine(src, threshold_px=0.5)
        sel = eng.update(cam)  # never asks the store for a missing tile
        check_selection(eng, cam, sel)
        assert not any(c[0] == top and c[1] < nx // 2 for c in sel.tiles + sel.culled)
        full = Engine(store, threshold_px=0.5).update(cam)
        if any(c[0] == top and c[1] < nx // 2 for c in full.tiles):
            assert any(c[0] == top - 1 and c[1] < nx // 4 for c in sel.tiles)


def _facing(v: np.ndarray, t: np.ndarray, eye) -> np.ndarray:
    """Reference: G = n . (eye - A) per triangle (paper 001 §3.2), numpy."""
    t = t.astype(np.int64)
    a, b, c = v[t[:, 0]], v[t[:, 1]], v[t[:, 2]]
    return np.einsum("ij,ij->i", np.cross(b - a, c - b), np.asarray(eye) - a)


@pytest.fixture(scope="module")
def ridge_store(tmp_path_factory):
    """A tent-shaped ridge (two planar slopes, 1.2 km high) with a little fBm: far-slope tiles face away
    from a low eye on the near side."""
    from terralod import Heightfield, build_store, open_store

    from conftest import fractal_terrain

    n = 129
    x = np.arange(n) / (n - 1)
    z = 1200.0 * np.maximum(0.0, 1.0 - np.abs(x - 0.5) / 0.5)[None, :] * np.ones((n, 1))
    z = z + fractal_terrain(n, n, 3, relief_m=4.0, beta=3.0)
    hf = Heightfield.from_array(z.astype(np.float32), 30.0, origin_m=(500000.0, 4100000.0))
    p = tmp_path_factory.mktemp("ridge") / "ridge.terra"
    build_store(hf, p, tile_size=9)
    with open_store(p) as s:
        yield s


def test_backface_culling_drops_exactly_the_backfacing_tiles(ridge_store) -> None:
    """cull_backfacing removes a drawn tile iff every stitched triangle faces away from the eye (numpy
    reference), keeps the partition, and does remove tiles behind the ridge."""
    t = ridge_store.transform
    w = ridge_store.pyramid.width * t.a
    rng = np.random.default_rng(5)
    removed_total = 0
    for _ in range(12):
        side = rng.choice([-1.0, 1.0])
        eye = (t.c + w * (0.5 + side * rng.uniform(0.45, 0.9)), t.f - w * rng.uniform(0.2, 0.8),
               rng.uniform(300.0, 900.0))  # fmt: skip
        tgt = (t.c + w * 0.5, t.f - w * rng.uniform(0.3, 0.7), rng.uniform(200.0, 1000.0))
        cam = Camera(eye, tgt, fov_y_deg=70.0, width_px=640, height_px=480)
        full = Engine(ridge_store, threshold_px=1.0).update(cam)
        cull = Engine(ridge_store, threshold_px=1.0, cull_backfacing=True).update(cam)
        meshes = full.mesh_dict()
        front = {c: bool((_facing(v, tr, eye) >= 0).any()) for c, (v, tr, _) in meshes.items()}
        assert sorted(cull.tiles) == sorted(c for c in full.tiles if front[c])
        assert sorted(cull.tiles + cull.culled) == sorted(full.tiles + full.culled)
        assert cull.stats.backface_culled == sum(not f for f in front.values())
        assert cull.stats.triangles == sum(len(meshes[c][1]) for c in cull.tiles)
        removed_total += cull.stats.backface_culled
    assert removed_total > 0, "no camera saw a back-facing tile behind the ridge"


def test_region_culling_drops_only_tiles_whose_mean_plane_footprint_is_unseen(store) -> None:
    """The §3.1 visible region is exact on the terrain's mean plane: no tile it drops has a point of its
    footprint, lifted to that plane, inside the view frustum; drawn tiles are a subset of the plain
    selection's, the partition is unchanged, and over many cameras some tiles are dropped."""
    pyr, t = store.pyramid, store.transform
    dropped_total = 0
    for seed in range(30):
        cam = random_camera(np.random.default_rng(seed), store)
        eng = Engine(store, threshold_px=2.0, cull_region=True)
        sel = eng.update(cam)
        ref = Engine(store, threshold_px=2.0).update(cam)
        dropped = set(ref.tiles) - set(sel.tiles)
        assert set(sel.tiles) <= set(ref.tiles) and len(dropped) == sel.stats.region_culled
        assert sorted(sel.tiles + sel.culled) == sorted(ref.tiles + ref.culled)
        dropped_total += len(dropped)
        for code in dropped:
            r0, c0 = pyr.origin_rc(code)
            span = pyr.span(code[0])
            rr, cc = np.meshgrid(np.linspace(r0, min(r0 + span, pyr.height - 1), 9),
                                 np.linspace(c0, min(c0 + span, pyr.width - 1), 9))  # fmt: skip
            x, y = t.c + (cc.ravel() + 0.5) * t.a, t.f + (rr.ravel() + 0.5) * t.e
            pts = np.stack([x, y, np.full(x.size, eng._mean_z_m)], 1)
            assert not cam.contains(pts).any(), f"tile {code} dropped but its footprint is in view"
    assert dropped_total > 0
