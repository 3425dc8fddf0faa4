"""The one interface: grid stores and detail-increment TINs both open with ``terralod.open`` as a Terrain,
select for a camera, give a static LOD tree with measured errors, and render through the same code."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import terralod
from terralod.runtime import Camera
from terralod.terrain import Frame, GridTerrain, Terrain, TerrainEngine, TinTerrain, as_terrain, frame_stats


@pytest.fixture(scope="module")
def stores(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    from terralod.tin import DetailIncrementModel
    from terralod.tin.terra import save_model_to_store

    d = tmp_path_factory.mktemp("terrain")
    rng = np.random.default_rng(7)
    z = np.cumsum(np.cumsum(rng.normal(0, 1, (65, 97)), 0), 1) * 0.5
    hf = terralod.Heightfield.from_array(z, 10.0, origin_m=(500000.0, 4000000.0), crs="EPSG:32616")
    terralod.build_store(hf, d / "grid.terra", tile_size=17, method="chunked", workers=1)
    save_model_to_store(DetailIncrementModel.from_heightfield(hf, sub_blocks=4), d / "tin.terra")
    return {"grid": d / "grid.terra", "tin": d / "tin.terra"}


def _camera(t: Terrain, az_deg: float, el_deg: float, dist: float) -> Camera:
    w, s, e, n = t.bounds_m
    lo, hi = t.elevation_range_m
    c = np.array([(w + e) / 2, (s + n) / 2, (lo + hi) / 2])
    r = dist * np.hypot(e - w, n - s)
    az, el = np.radians(az_deg), np.radians(el_deg)
    eye = c + r * np.array([np.sin(az) * np.cos(el), np.cos(az) * np.cos(el), np.sin(el)])
    return Camera(tuple(eye), tuple(c), (0.0, 0.0, 1.0), 50.0, 320, 180)


@pytest.mark.parametrize("kind", ["grid", "tin"])
def test_open_gives_a_terrain_of_either_kind(stores: dict[str, Path], kind: str) -> None:
    with terralod.open(stores[kind]) as t:
        assert isinstance(t, Terrain) and t.kind == kind
        assert isinstance(t, GridTerrain if kind == "grid" else TinTerrain)
        w, s, e, n = t.bounds_m
        assert 500000.0 <= w < e <= 500000.0 + 97 * 10 and 4000000.0 - 65 * 10 <= s < n <= 4000000.0
        lo, hi = t.elevation_range_m
        assert lo < hi and t.epochs == [] and t.crs == "EPSG:32616"
        eng = t.engine(threshold_px=2.0)
        assert isinstance(eng, TerrainEngine)
        f = eng.update(_camera(t, 200.0, 40.0, 1.2))
        assert isinstance(f, Frame)
        meshes = list(f.meshes())
        assert meshes and all(
            v.shape[1] == 3 and tr.shape[1] == 3 and nr.shape == v.shape for _, v, tr, nr in meshes
        )
        assert all(tr.size == 0 or int(tr.max()) < v.shape[0] for _, v, tr, _ in meshes)
        stats = frame_stats(f)
        assert stats["triangles"] == sum(int(tr.shape[0]) for _, _, tr, _ in meshes)
        assert {"tiles", "max_screen_error_px", "select_ms", "stitch_ms"} <= set(stats)
        eng.close()


@settings(max_examples=6, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(az=st.floats(0, 360), el=st.floats(15, 80), dist=st.floats(0.3, 2.0))
def test_select_is_the_engine_update(stores: dict[str, Path], az: float, el: float, dist: float) -> None:
    """``terrain.select(camera)`` draws what a fresh engine draws for that camera, for both kinds."""
    for kind in ("grid", "tin"):
        with terralod.open(stores[kind]) as t:
            cam = _camera(t, az, el, dist)
            a = {c: (v, tr) for c, v, tr, _ in t.select(cam).meshes()}
            eng = t.engine()
            b = {c: (v, tr) for c, v, tr, _ in eng.update(cam).meshes()}
            eng.close()
            assert a.keys() == b.keys()
            assert all(np.array_equal(a[k][1], b[k][1]) and np.array_equal(a[k][0], b[k][0]) for k in a)


def test_grid_lod_tree_is_the_stored_quadtree(stores: dict[str, Path]) -> None:
    with terralod.open(stores["grid"]) as t, terralod.open_store(stores["grid"]) as s:
        tree = t.lod_tree()
        codes = [n.code for n in tree]
        assert sorted(codes) == sorted(s.tile_codes()) and codes[0] == (0, 0, 0)
        seen: set = set()
        by = {n.code: n for n in tree}
        for n in tree:
            assert n.parent is None or n.parent in seen, "parents come first"
            seen.add(n.code)
            if n.parent is not None:
                assert (
                    by[n.parent].error_m >= n.error_m and by[n.parent].vertical_error_m >= n.vertical_error_m
                )
            v, tr = t.lod_mesh(n.code)
            tile = s.tile(*n.code)
            assert np.array_equal(v, tile.vertices) and np.array_equal(tr, tile.triangles)
            w, so, zlo, e, no, zhi = n.box_m
            assert (v[:, 0] >= w - 1e-6).all() and (v[:, 0] <= e + 1e-6).all()
            assert (v[:, 1] >= so - 1e-6).all() and (v[:, 1] <= no + 1e-6).all()
            assert (v[:, 2] >= zlo - 1e-6).all() and (v[:, 2] <= zhi + 1e-6).all()


def test_tin_lod_tree_is_a_ladder_of_halving_measured_errors(stores: dict[str, Path]) -> None:
    with terralod.open(stores["tin"]) as t:
        tree = t.lod_tree()
        m = t.model  # type: ignore[attr-defined]
        assert {n.code[1] for n in tree} == set(range(m.n_blocks))
        for b in range(m.n_blocks):
            rungs = [n for n in tree if n.code[1] == b]
            assert rungs[0].parent is None and [n.code[0] for n in rungs] == list(range(len(rungs)))
            assert rungs[-1].code[2] == int(m.block_n_scales[b]) - 1, "the ladder ends at full resolution"
            errs = [n.error_m for n in rungs]
            assert all(
                e1 <= 0.5 * e0 or i == len(errs) - 2
                for i, (e0, e1) in enumerate(zip(errs, errs[1:], strict=False))
            )
            assert errs[-1] == pytest.approx(0.0, abs=1e-9)
            for n in rungs:  # each rung's mesh is that sub-block's triangles at its scale
                v, tr = t.lod_mesh(n.code)
                assert tr.shape[1] == 3 and tr.size > 0 and int(tr.max()) < v.shape[0]


def test_as_terrain_wraps_what_consumers_are_given(stores: dict[str, Path]) -> None:
    with terralod.open_store(stores["grid"]) as s:
        t = as_terrain(s)
        assert isinstance(t, GridTerrain) and t.store is s and as_terrain(t) is t
    with pytest.raises(TypeError):
        as_terrain(object())


def test_open_refuses_what_is_not_a_store(tmp_path: Path) -> None:
    with pytest.raises(terralod.InputNotFoundError):
        terralod.open(tmp_path / "missing.terra")
    (tmp_path / "x.terra").write_bytes(b"not sqlite")
    with pytest.raises(terralod.StoreError):
        terralod.open(tmp_path / "x.terra")
