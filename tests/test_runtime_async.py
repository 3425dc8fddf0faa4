"""Tile loads off the frame path (``Engine(async_loads=True)``, :mod:`terralod.runtime.loader`): no frame
reads the store, every frame drawn while loading is watertight, and once the loads settle the frame is
exactly the synchronous engine's."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import terralod
from terralod.runtime import Camera, Engine, find_cracks


@pytest.fixture(scope="module")
def store_path(tmp_path_factory: pytest.TempPathFactory) -> Path:
    p = tmp_path_factory.mktemp("async") / "s.terra"
    rng = np.random.default_rng(3)
    z = np.cumsum(np.cumsum(rng.normal(0, 1, (129, 129)), 0), 1) * 0.3
    hf = terralod.Heightfield.from_array(z, 20.0, origin_m=(300000.0, 5000000.0), crs="EPSG:32610")
    terralod.build_store(hf, p, tile_size=17, method="chunked", workers=1)
    return p


def _camera(store: terralod.TileStore, u: float, v: float, h: float, az: float) -> Camera:
    t = terralod.as_terrain(store)
    w, s, e, n = t.bounds_m
    lo, hi = t.elevation_range_m
    eye = (w + u * (e - w), s + v * (n - s), hi + h * (e - w))
    tgt = (eye[0] + np.sin(az) * (e - w) * 0.3, eye[1] + np.cos(az) * (n - s) * 0.3, lo)
    return Camera(eye, tgt, (0.0, 0.0, 1.0), 60.0, 640, 360)


def _meshes(sel) -> dict:
    return {c: (v, t) for c, v, t, _ in sel.meshes()}


@settings(max_examples=3, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    path=st.lists(
        st.tuples(st.floats(0, 1), st.floats(0, 1), st.floats(0.02, 0.6), st.floats(0, 6.28)),
        min_size=1,
        max_size=3,
    )
)
def test_async_frames_are_watertight_and_settle_on_the_synchronous_frame(
    store_path: Path, path: list
) -> None:
    with terralod.open_store(store_path) as s:
        a = Engine(s, async_loads=True)
        b = Engine(s)
        try:
            for u, v, h, az in path:
                cam = _camera(s, u, v, h, az)
                for _ in range(40):  # refine one level per round of loads, drawing resident tiles meanwhile
                    sel = a.update(cam)
                    assert sel.stats.loaded == 0, "the frame thread read the store"
                    rep = find_cracks(sel.mesh_dict(), s.pyramid, s.transform, tol_m=1e-4)
                    assert rep.total_cracked == 0
                    if sel.stats.pending_loads == 0 and a.wait_loads(30) and a.update(cam) is sel:
                        break
                    assert a.wait_loads(30)
                final, ref = _meshes(a.update(cam)), _meshes(b.update(cam))
                assert final.keys() == ref.keys()
                assert all(
                    np.array_equal(final[k][0], ref[k][0]) and np.array_equal(final[k][1], ref[k][1])
                    for k in ref
                )
                assert a.update(cam).stats.max_screen_error_px == pytest.approx(
                    b.update(cam).stats.max_screen_error_px
                )
        finally:
            a.close()
            b.close()


def test_a_jump_draws_a_coarse_frame_at_once_and_reports_its_error(store_path: Path) -> None:
    """Right after a jump to a close view the frame is the resident (coarse) tiles, its larger projected
    error reported honestly, and the loads asked for are pending."""
    with terralod.open_store(store_path) as s:
        a = Engine(s, async_loads=True)
        try:
            cam = _camera(s, 0.5, 0.5, 0.03, 1.0)
            first = a.update(cam)
            assert first.stats.tiles >= 1 and first.stats.pending_loads > 0
            assert first.stats.max_screen_error_px > a.threshold_px
            assert a.wait_loads(30)
            for _ in range(20):
                sel = a.update(cam)
                if sel.stats.pending_loads == 0 and a.wait_loads(30) and a.update(cam) is sel:
                    break
                a.wait_loads(30)
            assert sel.stats.max_screen_error_px <= a.threshold_px + 1e-9 or sel.stats.fallback > 0
            assert max(c[0] for c in sel.tiles) > max(c[0] for c in first.tiles)
        finally:
            a.close()


def _refined(sel) -> set:
    """Tiles a frame split: proper ancestors of its leaves (drawn and culled) and of its fallback tiles
    (drawn instead of their children, which its first pass selected)."""
    out = set()
    for lvl, x, y in [*sel.tiles, *sel.culled, *sel.fallback]:
        while lvl > 0:
            lvl, x, y = lvl - 1, x >> 1, y >> 1
            out.add((lvl, x, y))
    return out | set(sel.fallback)


def _new_tiles_per_frame(store: terralod.TileStore, budget: int) -> list[int]:
    """Near view, far view, near view again (its fine tiles still decoded), each until settled: per frame,
    the drawn tiles whose parent the previous frame did not split; every frame watertight and the settled
    frame the synchronous engine's."""
    a = Engine(store, async_loads=True, max_new_tiles=budget)
    b = Engine(store)
    try:
        new_per_frame, prev = [], None
        for u, v, h, az in ((0.3, 0.3, 0.02, 0.8), (0.8, 0.9, 0.05, 4.0), (0.3, 0.3, 0.02, 0.8)):
            cam = _camera(store, u, v, h, az)
            for _ in range(200):
                sel = a.update(cam)
                if prev is not None:
                    split = _refined(prev)
                    new_per_frame.append(sum(c[0] > 0 and (c[0] - 1, c[1] >> 1, c[2] >> 1) not in split
                                             for c in sel.tiles if c not in prev.tiles))  # fmt: skip
                rep = find_cracks(sel.mesh_dict(), store.pyramid, store.transform, tol_m=1e-4)
                assert rep.total_cracked == 0
                prev = sel
                if sel.stats.pending_loads == 0 and a.wait_loads(30) and a.update(cam) is sel:
                    break
                a.wait_loads(30)
            assert sel.tiles == b.update(cam).tiles
        return new_per_frame
    finally:
        a.close()
        b.close()


@pytest.mark.parametrize("budget", [4, 8])
def test_a_jump_back_to_cached_tiles_stitches_a_bounded_number_of_new_tiles_per_frame(
    store_path: Path, budget: int
) -> None:
    """After a jump to a view whose fine tiles are all still decoded, the engine does not draw them all in
    one frame: every frame draws at most ``max_new_tiles`` tiles (whole sibling groups, at least one) whose
    parent the previous frame did not split, and settles on the synchronous frame."""
    with terralod.open_store(store_path) as s:
        assert max(_new_tiles_per_frame(s, budget)) <= max(budget, 4)
        assert max(_new_tiles_per_frame(s, 10**6)) > budget  # unbounded, the same views spike past it
