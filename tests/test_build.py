"""Tile store built by the Chunked-LOD builder: measured errors, monotone pyramid, shared boundaries,
quantisation bounds, determinism and resume."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from terralod import Heightfield, build_store, measure_error, open_store
from terralod.pyramid.footprint import footprint_mask
from terralod.tiles import parent

from conftest import fractal_terrain

TOL = 1e-6


def _hf(rows: int, cols: int, seed: int, spacing=(30.0, 30.0), relief=800.0, holes=False) -> Heightfield:
    z = fractal_terrain(rows, cols, seed, relief_m=relief)
    valid = None
    if holes:
        rng = np.random.default_rng(seed)
        valid = rng.random((rows, cols)) > 0.1
    return Heightfield.from_array(z, spacing, origin_m=(500000.0, 4100000.0), valid=valid)


def _xy_keys(v: np.ndarray) -> np.ndarray:
    """Each vertex's (x, y) as one complex number x + iy: equal exactly when both coordinates are."""
    k = np.empty(len(v), np.complex128)
    k.real, k.imag = v[:, 0], v[:, 1]
    return k


def check_store_invariants(path: Path, hf: Heightfield) -> None:
    with open_store(path) as s:
        assert s.complete
        codes = s.tile_codes()
        assert set(codes) == set(s.pyramid.all_codes())
        tiles = {c: s.tile(*c) for c in codes}
        dx, dy = hf.spacing_m

        def window_valid(c) -> bool:
            r0, c0 = s.pyramid.origin_rc(c)
            span = s.pyramid.span(c[0])
            return bool(hf.valid[r0 : r0 + span + 1, c0 : c0 + span + 1].all())

        for c, t in tiles.items():
            q = s.quantisation[c[0]]
            if t.triangles.shape[0] == 0:  # a tile wholly over nodata stores nothing (pyramid.footprint)
                assert t.vertices.shape[0] == 0 and not window_valid(c)
                continue
            # no stored triangle lies over nodata (at least half of its covered samples are valid)
            assert footprint_mask(
                t.grid_rc[:, 0], t.grid_rc[:, 1], t.triangles.astype(np.int64), hf.valid
            ).all()
            # independently measured errors never exceed the stored ones
            rep = measure_error(t.vertices, t.triangles, hf)
            assert rep.hausdorff_m <= t.error_m + TOL
            assert rep.max_vertical_m <= t.vertical_error_m + TOL
            assert t.error_m <= t.vertical_error_m + TOL
            if hf.original_grid is None:  # measured on the grid alone
                assert abs(rep.hausdorff_m - t.measured_error_m) <= 1e-6 + 1e-9 * t.measured_error_m
            else:  # a reprojected source: the original samples too (tests/test_honest_errors.py)
                assert rep.hausdorff_m <= t.measured_error_m + TOL
            # parent error >= child error (monotone)
            p = parent(c)
            if p is not None:
                assert tiles[p].error_m >= t.error_m and tiles[p].vertical_error_m >= t.vertical_error_m
            # quantisation: grid vertices exactly on samples, heights within half a step of the source
            rows, cols = t.grid_rc[:, 0], t.grid_rc[:, 1]
            assert np.array_equal(rows, np.round(rows)) and np.array_equal(cols, np.round(cols))
            ri = np.minimum(rows.astype(int), hf.height - 1)
            ci = np.minimum(cols.astype(int), hf.width - 1)
            dz = np.abs(t.vertices[:, 2] - hf.elevation_m[ri, ci].astype(np.float64))
            assert dz.max() <= q.z_bound_m * (1 + 1e-9) + 1e-4 * q.z_step_m
            x, y = hf.world_xy(rows, cols)
            assert np.array_equal(t.vertices[:, 0], x) or np.allclose(t.vertices[:, 0], x, rtol=0, atol=1e-6)
            assert np.allclose(t.vertices[:, 1], y, rtol=0, atol=1e-6)
            # triangles: indices in range, counter-clockwise seen from above, every vertex used
            assert t.triangles.max() < len(t.vertices)
            v = t.vertices
            a, b, cc = v[t.triangles[:, 0]], v[t.triangles[:, 1]], v[t.triangles[:, 2]]
            cross = (b[:, 0] - a[:, 0]) * (cc[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (cc[:, 0] - a[:, 0])
            assert (cross > 0).all()
            assert len(np.unique(t.triangles)) == len(t.vertices)
        # neighbouring tiles of one level share identical boundary vertices
        for c, t in tiles.items():
            for d in ("R", "D"):
                n = s.pyramid.neighbour(c, d)
                if n is None:
                    continue
                u = tiles[n]
                # the vertices of u at the exact (x, y) of a vertex of t have its height (x + iy: one key)
                key_a, key_b = _xy_keys(t.vertices), _xy_keys(u.vertices)
                order = np.argsort(key_a, kind="stable")
                pos = np.searchsorted(key_a[order], key_b, side="right") - 1
                hit = (pos >= 0) & (key_a[order][np.maximum(pos, 0)] == key_b) if key_a.size else pos >= 0
                z_a, z_b = t.vertices[order, 2][pos[hit]], u.vertices[hit, 2]
                bad = np.flatnonzero(z_a != z_b)
                assert not bad.size, (
                    f"{c}/{n} boundary vertex {key_b[hit][bad[0]]} differs: {z_a[bad[0]]} vs {z_b[bad[0]]}"
                )
                if window_valid(c) and window_valid(n):  # else triangles over nodata may be dropped there
                    assert hit.any(), f"{c} and {n} share no vertex"
                    # the shared edge has the same vertex count on both sides
                    assert hit.sum() >= 2


@given(
    rows=st.integers(3, 90),
    cols=st.integers(3, 90),
    m=st.sampled_from([3, 5, 9, 17]),
    seed=st.integers(0, 10_000),
    holes=st.booleans(),
)
@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
def test_store_invariants_random_terrain(
    tmp_path: Path, rows: int, cols: int, m: int, seed: int, holes: bool
) -> None:
    hf = _hf(rows, cols, seed, spacing=(25.0, 35.0), holes=holes)
    out = tmp_path / f"t{rows}_{cols}_{m}_{seed}_{holes}.terra"
    # the Chunked-LOD builder (the cohesion default gets the same invariants in test_cohesion.py)
    build_store(hf, out, tile_size=m, method="chunked", workers=2, overwrite=True)
    check_store_invariants(out, hf)


def test_flat_terrain_zero_error(tmp_path: Path) -> None:
    hf = Heightfield.from_array(np.full((65, 97), 120.0, np.float32), 10.0)
    build_store(hf, tmp_path / "f.terra", tile_size=17)
    with open_store(tmp_path / "f.terra") as s:
        assert max(e for e, _ in s.tile_errors().values()) == 0.0
        root = s.tile(0, 0, 0)
        assert np.allclose(root.vertices[:, 2], 120.0)


def test_tilted_plane_zero_error(tmp_path: Path) -> None:
    r, c = np.mgrid[0:129, 0:129]
    hf = Heightfield.from_array((3.0 * r - 2.0 * c + 1000).astype(np.float32), 5.0)
    build_store(hf, tmp_path / "p.terra", tile_size=9)
    with open_store(tmp_path / "p.terra") as s:
        for code, (_e, v) in s.tile_errors().items():
            q = s.quantisation[code[0]]
            assert v <= q.z_bound_m * 2 + 1e-9, (code, v)


def test_deterministic_and_resume_identical(tmp_path: Path) -> None:
    hf = _hf(300, 257, 7)
    a, b, c = tmp_path / "a.terra", tmp_path / "b.terra", tmp_path / "c.terra"
    build_store(hf, a, tile_size=17, workers=2)
    build_store(hf, b, tile_size=17, workers=1)
    rep = build_store(hf, c, tile_size=17, workers=2, stop_after=37)
    assert rep.tiles_built == 37
    with open_store(c) as s:
        assert not s.complete and len(s.tile_codes()) == 37
    rep2 = build_store(hf, c, tile_size=17, resume=True)
    assert rep2.tiles_skipped == 37 and rep2.tiles_built == rep.tiles_total - 37
    dumps = []
    for p in (a, b, c):
        con = sqlite3.connect(p)
        dumps.append(con.execute("SELECT * FROM tiles ORDER BY level, x, y").fetchall())
        con.close()
    assert dumps[0] == dumps[1] == dumps[2]


def test_resume_refuses_other_source(tmp_path: Path) -> None:
    from terralod.errors import BuildMismatchError, StoreError

    out = tmp_path / "x.terra"
    build_store(_hf(70, 70, 1), out, tile_size=17, stop_after=3)
    with pytest.raises(BuildMismatchError, match="cannot resume"):
        build_store(_hf(70, 70, 2), out, tile_size=17, resume=True)
    with pytest.raises(StoreError, match="already exists"):
        build_store(_hf(70, 70, 1), out, tile_size=17)
