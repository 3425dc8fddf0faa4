"""Footprints: triangles over nodata are not stored (every method), the fill stays for meshing only, errors
are measured over valid samples, and frames show the sky where the data has none."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from terralod import Heightfield, build_store, open_store
from terralod.pyramid.builder import METHODS
from terralod.pyramid.footprint import drop_nodata, footprint_mask

from conftest import fractal_terrain


def _covered(rows, cols, tri, shape):
    """Samples inside the closed triangle (numpy reference of the kernel's count)."""
    h, w = shape
    r = np.arange(h)[:, None]
    c = np.arange(w)[None, :]
    (ra, rb, rc), (ca, cb, cc) = rows[tri], cols[tri]
    area = (cb - ca) * (rc - ra) - (rb - ra) * (cc - ca)
    s = 1.0 if area >= 0 else -1.0
    e0 = s * ((cb - ca) * (r - ra) - (rb - ra) * (c - ca))
    e1 = s * ((cc - cb) * (r - rb) - (rc - rb) * (c - cb))
    e2 = s * ((ca - cc) * (r - rc) - (ra - rc) * (c - cc))
    tol = 1e-9 * max(abs(area), 1.0)
    # within the vertices' box too: a degenerate triangle's edge functions vanish on its whole line
    box = (r >= min(ra, rb, rc) - 1e-9) & (r <= max(ra, rb, rc) + 1e-9)
    box = box & (c >= min(ca, cb, cc) - 1e-9) & (c <= max(ca, cb, cc) + 1e-9)
    return (e0 >= -tol) & (e1 >= -tol) & (e2 >= -tol) & box


@given(seed=st.integers(0, 10_000), n=st.integers(1, 12))
@settings(max_examples=25, deadline=None)
def test_footprint_mask_is_the_majority_of_covered_samples(seed: int, n: int) -> None:
    rng = np.random.default_rng(seed)
    shape = (12, 14)
    valid = rng.random(shape) > rng.random()
    rows = rng.uniform(-1, 13, 3 * n)
    cols = rng.uniform(-1, 15, 3 * n)
    tris = np.arange(3 * n).reshape(n, 3)
    keep = footprint_mask(rows, cols, tris, valid)
    for k in range(n):
        cov = _covered(rows, cols, tris[k], shape)
        if cov.any():
            assert keep[k] == (2 * valid[cov].sum() >= cov.sum())


def _mask_reference(rows, cols, tris, valid) -> np.ndarray:
    """The footprint rule sample by sample: the majority of covered samples, or the centroid's sample."""
    h, w = valid.shape
    out = np.zeros(tris.shape[0], bool)
    for k, tri in enumerate(tris):
        cov = _covered(rows, cols, tri, valid.shape)
        if cov.any():
            out[k] = 2 * valid[cov].sum() >= cov.sum()
        else:
            r = min(max(int(round(rows[tri].sum() / 3.0)), 0), h - 1)
            c = min(max(int(round(cols[tri].sum() / 3.0)), 0), w - 1)
            out[k] = valid[r, c]
    return out


@given(
    seed=st.integers(0, 10_000),
    n=st.integers(1, 60),
    big=st.floats(0.5, 30.0),
    holes=st.floats(0, 1),
    on_samples=st.booleans(),
)
@settings(max_examples=60, deadline=None)
def test_footprint_mask_shortcut_is_the_sample_count(
    seed: int, n: int, big: float, holes: float, on_samples: bool
) -> None:
    """Triangles of every size over a mask of blobs (so that many boxes are wholly valid or wholly nodata,
    the summed-area shortcut's case), inside and across the grid's edges, slivers included: the kernel
    gives the sample-by-sample rule's answer for every one."""
    rng = np.random.default_rng(seed)
    shape = (41, 53)
    r, c = np.mgrid[0 : shape[0], 0 : shape[1]]
    blobs = np.zeros(shape)
    for _ in range(4):
        cy, cx, rad = rng.uniform(0, 41), rng.uniform(0, 53), rng.uniform(3, 15)
        blobs += np.exp(-((r - cy) ** 2 + (c - cx) ** 2) / rad**2)
    valid = blobs < holes * blobs.max()
    centre = rng.uniform(-3, [44, 56], (n, 2))
    pts = centre[:, None, :] + rng.normal(0, big, (n, 3, 2))
    sliver = rng.random(n) < 0.2  # the third corner near the first two's line
    pts[sliver, 2] = 0.5 * (pts[sliver, 0] + pts[sliver, 1]) + rng.normal(0, 0.05, (int(sliver.sum()), 2))
    if on_samples:  # vertices on samples, as the adaptive and chunked meshers make them (centroids at .5)
        pts = np.rint(pts)
    rows, cols = pts[..., 0].ravel(), pts[..., 1].ravel()
    tris = np.arange(3 * n).reshape(n, 3)
    assert np.array_equal(footprint_mask(rows, cols, tris, valid), _mask_reference(rows, cols, tris, valid))


def _holed(seed: int) -> Heightfield:
    z = fractal_terrain(97, 113, seed, relief_m=600.0)
    r, c = np.mgrid[0:97, 0:113]
    valid = (r + c > 25) & ~((r > 30) & (r < 70) & (c > 40) & (c < 90))  # a wedge and a lake of nodata
    return Heightfield.from_array(z, 30.0, origin_m=(500000.0, 4100000.0), valid=valid)


@given(
    seed=st.integers(0, 2**32 - 1), n=st.integers(3, 60), k=st.integers(0, 120),
    dtype=st.sampled_from([np.int32, np.int64, np.uint32]),
)  # fmt: skip
@settings(max_examples=150, deadline=None)
def test_drop_nodata_is_the_numpy_statement(seed: int, n: int, k: int, dtype) -> None:
    """drop_nodata (the footprint's triangles, compacted by a kernel) gives the numpy statement's arrays:
    the kept triangles in order, renumbered onto the vertices they use, in order, in the input's dtype."""
    rng = np.random.default_rng(seed)
    valid = rng.random((12, 12)) < 0.6
    rows = rng.integers(0, 12, n).astype(np.float64)
    cols = rng.integers(0, 12, n).astype(np.float64)
    hz = rng.normal(0.0, 10.0, n)
    tris = rng.integers(0, n, (k, 3)).astype(dtype)
    got = drop_nodata(rows, cols, hz, tris, valid, valid)
    keep = footprint_mask(rows, cols, tris.astype(np.int64), valid) if k else np.zeros(0, bool)
    kept = tris[keep]
    used = np.zeros(n, bool)
    used[kept.ravel()] = True
    remap = np.cumsum(used) - 1
    want = (rows[used], cols[used], hz[used], remap[kept].astype(dtype))
    if k == 0 or keep.all():
        want = (rows, cols, hz, tris)
    for g, w in zip(got, want, strict=True):
        assert g.dtype == w.dtype
        np.testing.assert_array_equal(g, w)


@pytest.mark.parametrize("method", sorted(METHODS))
def test_no_stored_triangle_lies_over_nodata(tmp_path: Path, method: str) -> None:
    hf = _holed(3)
    out = tmp_path / f"{method}.terra"
    build_store(hf, out, tile_size=17, method=method, workers=2)
    with open_store(out) as s:
        assert s.complete
        finest = max(s.levels)
        covered = np.zeros(hf.shape, bool)
        for code in s.tile_codes():
            t = s.tile(*code)
            if t.triangles.shape[0] == 0:
                assert t.vertices.shape[0] == 0 and t.error_m >= 0.0
                continue
            assert len(np.unique(t.triangles)) == len(t.vertices)  # no vertex left over
            rows, cols = t.grid_rc[:, 0], t.grid_rc[:, 1]
            keep = footprint_mask(rows, cols, t.triangles.astype(np.int64), hf.valid)
            assert keep.all(), f"{code}: {int((~keep).sum())} triangles over nodata"
            if code[0] == finest:
                for tri in t.triangles:
                    covered |= _covered(rows, cols, tri, hf.shape)
        assert not covered[40:60, 50:80].any()  # the lake's interior is sky
        if method not in ("chunked", "cohesion", "adaptive"):
            return  # other meshers' finest level is not the full-resolution grid (adaptive_ladder's TINs)
        # the finest level (the source grid) still covers every valid sample away from the nodata's edge
        inner = hf.valid.copy()
        for dr in (-1, 0, 1):
            for dc in (-1, 0, 1):
                inner &= np.roll(np.roll(hf.valid, dr, 0), dc, 1)
        inner[[0, -1], :] = inner[:, [0, -1]] = False
        assert covered[inner].all()


def test_fully_valid_tiles_are_untouched(tmp_path: Path) -> None:
    z = fractal_terrain(65, 65, 5, relief_m=300.0)
    a = Heightfield.from_array(z, 30.0)
    valid = np.ones(z.shape, bool)
    valid[60:, 60:] = False  # one corner tile of the finest level has nodata
    b = Heightfield.from_array(z, 30.0, valid=valid)
    build_store(a, tmp_path / "a.terra", tile_size=17, method="chunked")
    build_store(b, tmp_path / "b.terra", tile_size=17, method="chunked")
    with open_store(tmp_path / "a.terra") as sa, open_store(tmp_path / "b.terra") as sb:
        ta, tb = sa.tile(2, 0, 0), sb.tile(2, 0, 0)  # north-west: all valid, identical
        assert np.array_equal(ta.vertices, tb.vertices) and np.array_equal(ta.triangles, tb.triangles)
        assert sb.tile(2, 3, 3).triangles.shape[0] < sa.tile(2, 3, 3).triangles.shape[0]


def test_frame_shows_sky_over_nodata(tmp_path: Path) -> None:
    from terralod.render.offscreen import CameraPose, FrameRenderer
    from terralod.terrain import open_terrain

    hf = _holed(3)
    out = tmp_path / "h.terra"
    build_store(hf, out, tile_size=17, workers=2)
    x, y = hf.world_xy(50.0, 65.0)  # the middle of the lake
    pose = CameraPose((float(x), float(y) - 1.0, 6000.0), (float(x), float(y), 0.0))
    with open_terrain(out) as t:
        fr = FrameRenderer(t, 64, 64, settings=None)
        fr.settings.background = (1.0, 0.0, 1.0)
        fr.settings.fog = False
        img = fr.frame(pose)
        fr.close()
    mid = img[28:36, 28:36].reshape(-1, 3)
    assert (mid == (255, 0, 255)).all(), "terrain drawn over the nodata lake"


def test_exports_skip_tiles_wholly_over_nodata(tmp_path: Path) -> None:
    """3D Tiles of a store whose tiles lie partly wholly over nodata: those get no content, the rest a glb."""
    from pyproj import CRS

    from terralod.export.tiles3d import export_3dtiles
    from terralod.terrain import open_terrain

    z = fractal_terrain(97, 113, 3, relief_m=600.0)
    r, c = np.mgrid[0:97, 0:113]
    valid = r + c > 40  # the north-west corner tiles of the finest level are all nodata
    hf = Heightfield.from_array(
        z, 30.0, origin_m=(500000.0, 4100000.0), valid=valid, crs=CRS.from_epsg(32633).to_wkt()
    )
    build_store(hf, tmp_path / "w.terra", tile_size=17, method="chunked", workers=2)
    with open_store(tmp_path / "w.terra") as s:
        empty = sum(1 for code in s.tile_codes() if s.tile(*code).triangles.shape[0] == 0)
        total = len(s.tile_codes())
    assert empty > 0
    with open_terrain(tmp_path / "w.terra") as t:
        rep = export_3dtiles(t, tmp_path / "tiles")
    assert rep.tiles == total - empty
    assert len(list((tmp_path / "tiles").rglob("*.glb"))) == total - empty


def test_fractal_levels_add_no_detail_over_nodata(tmp_path: Path) -> None:
    from terralod.fractal import FractalDetail
    from terralod.runtime.fractal_source import FractalSource

    hf = _holed(3)
    build_store(hf, tmp_path / "f.terra", tile_size=17, method="chunked", workers=2)
    with open_store(tmp_path / "f.terra") as s:
        src = FractalSource(s, FractalDetail(hf), 1, workers=1)
        level = src.base_level + 1
        seen_empty = 0
        for code in src.pyramid.tile_codes(level):
            r0, c0 = (v / src.factor for v in src.pyramid.origin_rc(code))
            if not (20 <= r0 <= 70 and 30 <= c0 <= 100):
                continue  # tiles around the lake only (cheap)
            t = src.tile(*code)
            if t.triangles.shape[0] == 0:
                seen_empty += 1
                continue
            rc = t.grid_rc / src.factor
            assert footprint_mask(rc[:, 0], rc[:, 1], t.triangles.astype(np.int64), hf.valid).all()
        assert seen_empty > 0  # tiles inside the lake: nothing drawn
