"""Fractal detail (paper 001): fBm statistics, kept DEM samples, seamless and deterministic generation,
georeferencing of the amplified grid, fractal tiles and diagonal rules, culling helpers, the amplify
product, and a real SRTM crop."""

from __future__ import annotations

import hashlib
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from affine import Affine
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from terralod import fractal
from terralod.errors import InputError
from terralod.fractal import (
    FractalDetail,
    amplify_command,
    boxes_in_frustum,
    boxes_in_region,
    estimate_fbm,
    fractal_tile,
    patch_backfacing,
    patches_backfacing,
    stencil_table,
    visible_region,
)
from terralod.heightfield import Heightfield
from terralod.kernels import noise
from terralod.tiles import TilePyramid

from conftest import fractal_terrain

HYP = settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def _hf(rows: int, cols: int, seed: int, spacing=(30.0, 30.0), holes: bool = False) -> Heightfield:
    z = fractal_terrain(rows, cols, seed, relief_m=600.0)
    valid = None
    if holes:
        valid = np.random.default_rng(seed).random((rows, cols)) > 0.08
    return Heightfield.from_array(z, spacing, origin_m=(500010.0, 4100020.0), valid=valid)


def _spectral_fbm(n: int, hurst: float, seed: int, over: int = 4) -> np.ndarray:
    """fBm of exponent ``hurst`` by spectral synthesis (power ~ f^-(2H+2)) on an ``over``-times finer
    grid, decimated: the aliased high frequencies make the sampled variogram close to h^2H at lag 1."""
    rng = np.random.default_rng(seed)
    m = n * over
    fy = np.fft.fftfreq(m)[:, None]
    fx = np.fft.rfftfreq(m)[None, :]
    f = np.sqrt(fx * fx + fy * fy)
    f[0, 0] = 1.0
    amp = f ** (-(hurst + 1.0))
    amp[0, 0] = 0.0
    spec = amp * (rng.normal(size=amp.shape) + 1j * rng.normal(size=amp.shape))
    z = np.fft.irfft2(spec, s=(m, m))[::over, ::over]
    return z / np.sqrt(noise.axis_variogram(z, 1)[0])  # sigma = 1 at one sample


def _slope(z: np.ndarray, lags: int = 8) -> float:
    g = noise.axis_variogram(np.ascontiguousarray(z, dtype=np.float64), lags)
    return float(np.polyfit(np.log(np.arange(1, lags + 1)), np.log(g), 1)[0])


# -- noise and stencil ---------------------------------------------------------------------------------
def test_hashed_noise_is_standard_normal_and_position_keyed():
    seed = np.uint64(12345)
    g = noise.gauss_grid(seed, 3, -300, -200, 400, 400)
    assert abs(g.mean()) < 0.01 and abs(g.std() - 1.0) < 0.01
    # neighbours and levels are uncorrelated
    assert abs(np.corrcoef(g[:, :-1].ravel(), g[:, 1:].ravel())[0, 1]) < 0.01
    h = noise.gauss_grid(seed, 4, -300, -200, 400, 400)
    assert abs(np.corrcoef(g.ravel(), h.ravel())[0, 1]) < 0.01
    # a point's value does not depend on the grid it was asked with
    assert noise.gauss_grid(seed, 3, -5, 7, 1, 1)[0, 0] == g[295, 207]
    assert noise.gauss_at(np.uint64(12346), 3, -5, 7) != g[295, 207]


@pytest.mark.parametrize("hurst", [0.05, 0.3, 0.5, 0.8, 0.95])
def test_stencil_table_is_unbiased_and_beats_the_mean_of_four(hurst):
    i = int(round(hurst * fractal.STENCIL_TABLE_STEPS))
    wa, wb, wc, k2 = stencil_table("kriging")[i]
    assert 4 * wa + 8 * wb + 4 * wc == pytest.approx(1.0, abs=1e-9)
    c = stencil_table("classic")[i]
    assert tuple(c[:3]) == (0.25, 0.0, 0.0)
    assert c[3] == pytest.approx(2.0**-hurst - 0.25 - 0.125 * 2.0**hurst)
    # the kriging predictor is the best linear unbiased one: smaller error variance than the mean of 4
    assert 0.0 < k2 <= c[3] + 1e-12


# -- statistics ----------------------------------------------------------------------------------------
@pytest.mark.parametrize("hurst", [0.3, 0.5, 0.8])
def test_variogram_slope_of_detail_on_flat_dem_is_2h(hurst):
    # 10 iterations on a flat 2 x 2 DEM: lags 1..8 finest samples lie deep below the DEM spacing
    flat = Heightfield.from_array(np.zeros((2, 2), np.float32), 1.0)
    slopes = []
    for seed in range(4):
        fine = FractalDetail(flat, hurst=hurst, sigma_m=1.0, seed=seed).amplify(1024).elevation_m
        slopes.append(_slope(fine))
    assert np.mean(slopes) == pytest.approx(2 * hurst, abs=0.1)
    assert np.std(slopes) < 0.05


def test_classic_mean_of_four_falls_short_at_high_h():
    """The documented reason for the kriging stencil: the textbook predictor is too rough at H = 0.8."""
    flat = Heightfield.from_array(np.zeros((2, 2), np.float32), 1.0)
    k = [_slope(FractalDetail(flat, hurst=0.8, sigma_m=1.0, seed=s).amplify(256).elevation_m) for s in (0, 1)]
    c = [
        _slope(
            FractalDetail(flat, hurst=0.8, sigma_m=1.0, seed=s, stencil="classic").amplify(256).elevation_m
        )
        for s in (0, 1)
    ]
    assert np.mean(c) < np.mean(k) - 0.1


@pytest.mark.parametrize("hurst", [0.3, 0.5, 0.8])
def test_refining_an_fbm_dem_continues_its_variogram(hurst):
    z = _spectral_fbm(128, hurst, seed=11)
    hf = Heightfield.from_array(z.astype(np.float32), 1.0)
    fine = FractalDetail(hf, hurst=hurst, sigma_m=1.0, seed=5).amplify(16).elevation_m.astype(np.float64)
    lags = np.array([1, 2, 4, 8])  # 1/16 .. 1/2 DEM sample: all generated scales
    g = noise.axis_variogram(fine, 8)[lags - 1]
    ratio = g / (lags / 16.0) ** (2 * hurst)
    assert np.all(np.abs(ratio - 1.0) < 0.12), ratio


@pytest.mark.parametrize("hurst", [0.3, 0.5, 0.8])
def test_estimated_hurst_and_sigma_of_synthetic_fbm(hurst):
    z = _spectral_fbm(512, hurst, seed=3) * 7.0
    h, s = estimate_fbm(z.astype(np.float32))
    assert h.shape == (8, 8) and s.shape == (8, 8)
    assert h.mean() == pytest.approx(hurst, abs=0.1)
    assert s.mean() == pytest.approx(7.0, rel=0.15)
    assert np.all((h >= 0.05) & (h <= 0.95))


def test_estimate_handles_flat_blocks_nodata_and_given_values():
    z = _spectral_fbm(128, 0.5, seed=1).astype(np.float32)
    z[:72, :72] = 100.0  # a lake covering block (0, 0) and every pair that starts in it
    valid = np.ones(z.shape, bool)
    valid[64:, 64:] = False  # no data in one block: takes the whole-DEM estimate
    h, s = estimate_fbm(z, valid, smooth=False)
    assert s[0, 0] == 0.0
    assert np.isfinite(h).all() and np.isfinite(s).all() and s[1, 1] > 0
    hf = Heightfield.from_array(z, 10.0, valid=valid)
    d = FractalDetail(hf, hurst=0.4, seed=1)
    assert d.hurst_blocks.shape == (1, 1) and np.all(d.hurst_map == np.float32(0.4))
    assert d.sigma_map.shape == hf.shape and d.sigma_blocks.shape == (2, 2)
    with pytest.raises(InputError):
        FractalDetail(hf, hurst=1.0)
    with pytest.raises(InputError):
        FractalDetail(hf, sigma_m=-1.0)


# -- exactness, seamlessness, determinism --------------------------------------------------------------
@HYP
@given(
    rows=st.integers(2, 24),
    cols=st.integers(2, 24),
    k=st.integers(0, 4),
    seed=st.integers(-(2**63), 2**64 - 1),
    data_seed=st.integers(0, 1000),
)
def test_dem_samples_are_kept_exactly(rows, cols, k, seed, data_seed):
    hf = _hf(rows, cols, data_seed)
    f = 1 << k
    fine = FractalDetail(hf, seed=seed, block=8).amplify(f)
    assert fine.shape == ((rows - 1) * f + 1, (cols - 1) * f + 1)
    assert np.array_equal(fine.elevation_m[::f, ::f], hf.elevation_m)
    assert np.isfinite(fine.elevation_m).all()


@HYP
@given(data=st.data(), k=st.integers(1, 4), stencil=st.sampled_from(["kriging", "classic"]))
def test_window_equals_crop_of_amplify(data, k, stencil):
    rows = data.draw(st.integers(2, 20), label="rows")
    cols = data.draw(st.integers(2, 20), label="cols")
    hf = _hf(rows, cols, data.draw(st.integers(0, 99), label="terrain"))
    d = FractalDetail(hf, seed=data.draw(st.integers(0, 9), label="seed"), block=4, stencil=stencil)
    f = 1 << k
    full = d.amplify(f).elevation_m
    nr, nc = full.shape
    for _ in range(4):
        r0 = data.draw(st.integers(0, nr - 1))
        c0 = data.draw(st.integers(0, nc - 1))
        n = data.draw(st.integers(1, nr - r0))
        m = data.draw(st.integers(1, nc - c0))
        w = d.window(r0, c0, n, m, f)
        assert w.dtype == np.float32 and w.shape == (n, m)
        assert np.array_equal(w, full[r0 : r0 + n, c0 : c0 + m])


@HYP
@given(data=st.data(), k=st.integers(1, 5))
def test_windows_generated_apart_agree_on_shared_edges(data, k):
    hf = _hf(17, 21, data.draw(st.integers(0, 99), label="terrain"))
    d = FractalDetail(hf, seed=7, block=8)
    f = 1 << k
    nr, nc = d.amplified_shape(f)
    r0 = data.draw(st.integers(0, nr - 3))
    c0 = data.draw(st.integers(0, nc - 3))
    cut = data.draw(st.integers(c0 + 1, nc - 2))  # shared column
    n = data.draw(st.integers(1, min(40, nr - r0)))
    west = d.window(r0, c0, n, cut - c0 + 1, f)
    east = FractalDetail(hf, seed=7, block=8).window(r0, cut, n, min(40, nc - cut), f)
    assert np.array_equal(west[:, -1], east[:, 0])
    cut_r = data.draw(st.integers(r0 + 1, nr - 2))  # shared row
    north = d.window(r0, c0, cut_r - r0 + 1, 5 if c0 + 5 <= nc else nc - c0, f)
    south = d.window(cut_r, c0, 3 if cut_r + 3 <= nr else nr - cut_r, north.shape[1], f)
    assert np.array_equal(north[-1], south[0])


def test_levels_are_nested():
    d = FractalDetail(_hf(13, 9, 1), seed=3, block=4)
    a2, a8 = d.amplify(2).elevation_m, d.amplify(8).elevation_m
    assert np.array_equal(a8[::4, ::4], a2)


def test_same_seed_same_bytes_other_seed_other_detail():
    hf = _hf(33, 29, 4)
    a = FractalDetail(hf, seed=42).amplify(4).elevation_m
    b = FractalDetail(hf, seed=42).amplify(4).elevation_m
    c = FractalDetail(hf, seed=43).amplify(4).elevation_m
    assert a.tobytes() == b.tobytes()
    new = np.ones(a.shape, bool)
    new[::4, ::4] = False
    assert np.all(a[~new] == c[~new])
    assert np.mean(a[new] != c[new]) > 0.99


def test_same_bytes_in_another_process():
    code = (
        "import hashlib, numpy as np; from terralod.heightfield import Heightfield; "
        "from terralod.fractal import FractalDetail; "
        "z = np.add.outer(np.arange(20.0), np.arange(15.0) ** 1.5).astype(np.float32); "
        "hf = Heightfield.from_array(z, 5.0); "
        "print(hashlib.sha256(FractalDetail(hf, seed=9).amplify(8).elevation_m.tobytes()).hexdigest())"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True
    ).stdout.strip()
    z = np.add.outer(np.arange(20.0), np.arange(15.0) ** 1.5).astype(np.float32)
    here = FractalDetail(Heightfield.from_array(z, 5.0), seed=9).amplify(8).elevation_m
    assert out == hashlib.sha256(here.tobytes()).hexdigest()


def test_noise_is_keyed_by_world_position():
    """A crop of a DEM (same grid) gets the same detail as the whole DEM, away from the crop's edges.

    The crop's edge changes points within reach of its stencil fallback (< 1.5 DEM samples) plus the
    stencils' reach over all later iterations (sum of 3 * 2^-(k-1) < 6 DEM samples).
    """
    hf = _hf(40, 40, 2)
    t = hf.transform
    d = FractalDetail(hf, hurst=0.6, sigma_m=3.0, seed=1)
    r0, c0 = 9, 13
    sub = Heightfield(
        hf.elevation_m[r0:, c0:],
        hf.valid[r0:, c0:],
        Affine(t.a, 0.0, t.c + c0 * t.a, 0.0, t.e, t.f + r0 * t.e),
        crs=hf.crs,
    )
    ds = FractalDetail(sub, hurst=0.6, sigma_m=3.0, seed=1)
    assert ds.lattice_offset == (d.lattice_offset[0] + r0, d.lattice_offset[1] + c0)
    f, m = 8, 8  # compare beyond 8 DEM samples from the crop's edge
    far = d.window((r0 + 3) * f, (c0 + 3) * f, 12 * f, 12 * f, f)
    near = ds.window(3 * f, 3 * f, 12 * f, 12 * f, f)
    assert not np.array_equal(far, near)  # close to the crop's edge the detail differs
    a = d.window((r0 + m) * f, (c0 + m) * f, 12 * f, 12 * f, f)
    b = ds.window(m * f, m * f, 12 * f, 12 * f, f)
    assert np.array_equal(a, b)


# -- georeferencing and nodata -------------------------------------------------------------------------
@pytest.mark.parametrize("factor", [2, 4, 16])
def test_amplified_grid_keeps_input_samples_at_their_world_position(factor):
    hf = _hf(11, 14, 0, spacing=(30.0, 20.0))
    fine = FractalDetail(hf, seed=1).amplify(factor)
    assert fine.crs == hf.crs
    assert fine.spacing_m == pytest.approx((30.0 / factor, 20.0 / factor))
    r, c = np.meshgrid(np.arange(11), np.arange(14), indexing="ij")
    x0, y0 = hf.world_xy(r, c)
    x1, y1 = fine.world_xy(r * factor, c * factor)
    np.testing.assert_allclose(x1, x0, rtol=0, atol=1e-6)
    np.testing.assert_allclose(y1, y0, rtol=0, atol=1e-6)
    # the footprint is the input's sample rectangle plus half an output pixel on each side
    w, s, e, n = fine.bounds_m
    wi, si, ei, ni = hf.bounds_m
    assert w == pytest.approx(wi + 15.0 - 15.0 / factor) and n == pytest.approx(ni - 10.0 + 10.0 / factor)
    assert e == pytest.approx(ei - 15.0 + 15.0 / factor) and s == pytest.approx(si + 10.0 - 10.0 / factor)


def test_nodata_spreads_to_cells_between_invalid_samples():
    hf = _hf(12, 12, 3, holes=True)
    f = 4
    fine = FractalDetail(hf, seed=0).amplify(f)
    assert np.array_equal(fine.valid[::f, ::f], hf.valid)
    v = hf.valid
    cell_ok = v[:-1, :-1] & v[:-1, 1:] & v[1:, :-1] & v[1:, 1:]
    inner = fine.valid[1::f, 1::f]  # a sample strictly inside each DEM cell
    assert np.array_equal(inner, cell_ok)


def test_bad_arguments_are_refused():
    d = FractalDetail(_hf(9, 9, 0), seed=0)
    for bad in (3, 0, -2, 2.5):
        with pytest.raises(InputError, match="power of 2"):
            d.amplify(bad)
    with pytest.raises(ValueError, match="window inside"):
        d.window(0, 0, 40, 2, 4)
    with pytest.raises(ValueError):
        FractalDetail(_hf(9, 9, 0), stencil="cubic")


# -- tiles and diagonal rules --------------------------------------------------------------------------
@pytest.mark.parametrize("extra", [0, 1, 2, 3])
def test_fractal_tiles_are_well_formed_and_share_edges(extra):
    hf = _hf(70, 90, 6)
    d = FractalDetail(hf, seed=2)
    top = TilePyramid(hf.width, hf.height, 17).max_level
    lv = top + extra
    t = fractal_tile(d, (lv, 1, 1), tile_size=17)
    east = fractal_tile(d, (lv, 2, 1), tile_size=17)
    south = d.tile((lv, 1, 2), tile_size=17)
    assert t.extra_levels == extra and t.vertices.shape == (17 * 17, 3)
    tri = t.triangles
    assert tri.dtype == np.int32 and tri.shape == (2 * 16 * 16, 3) and tri.min() >= 0 and tri.max() < 289
    v = t.vertices
    n = np.cross(v[tri[:, 1]] - v[tri[:, 0]], v[tri[:, 2]] - v[tri[:, 0]])
    assert np.all(n[:, 2] > 0)  # counter-clockwise seen from above
    grid = v.reshape(17, 17, 3)
    assert np.array_equal(grid[:, -1], east.vertices.reshape(17, 17, 3)[:, 0])
    assert np.array_equal(grid[-1], south.vertices.reshape(17, 17, 3)[0])
    # heights are the refined grid's, positions the heightfield's world frame
    f = 1 << extra
    w = d.window(16, 16, 17, 17, f)
    assert np.array_equal(grid[:, :, 2], w.astype(np.float64))
    x, y = hf.world_xy(16 / f, 16 / f)
    assert grid[0, 0, 0] == pytest.approx(float(x)) and grid[0, 0, 1] == pytest.approx(float(y))
    assert 0.0 < t.rms_error_m <= t.error_m
    assert fractal_tile(d, (lv, 1, 1), tile_size=17) is t  # LRU hit


def test_tiles_at_the_dem_edge_are_clipped_and_missing_tiles_refused():
    hf = _hf(40, 50, 1)
    d = FractalDetail(hf, seed=0)
    top = TilePyramid(50, 40, 17).max_level
    t = d.tile((top + 1, 6, 0), tile_size=17)  # refined grid 79 x 99: columns 96..98
    assert t.vertices.shape == (17 * 3, 3) and t.triangles.shape == (2 * 16 * 2, 3)
    with pytest.raises(ValueError, match="existing tile"):
        d.tile((top + 1, 7, 0), tile_size=17)
    with pytest.raises(ValueError, match="tile level"):
        d.tile((top - 1, 0, 0), tile_size=17)


def test_diagonal_rules():
    hf = _hf(65, 65, 8)
    d = FractalDetail(hf, seed=4)
    top = TilePyramid(65, 65, 17).max_level
    code = (top + 2, 3, 2)
    err = d.tile(code, tile_size=17, diagonal="error")
    low = d.tile(code, tile_size=17, diagonal="lowest")
    fix = d.tile(code, tile_size=17, diagonal="fixed")
    assert err.error_m <= low.error_m and err.error_m <= fix.error_m
    assert np.array_equal(err.vertices, low.vertices)
    # the paper's rule joins the two lowest vertices whenever they are opposite corners
    zg = np.array([[0.0, 5.0], [6.0, 1.0]])
    diag1, *_ = fractal.choose_diagonals(zg, np.zeros((3, 3)), 2, "lowest")
    assert not diag1[0, 0]  # a-d joins 0 and 1
    diag1, *_ = fractal.choose_diagonals(zg[:, ::-1], np.zeros((3, 3)), 2, "lowest")
    assert diag1[0, 0]
    with pytest.raises(ValueError):
        d.tile(code, tile_size=17, diagonal="shortest")


def test_extra_levels_for_screen_error():
    d = FractalDetail(_hf(64, 64, 2), seed=0)
    errs = [d.detail_error_m(e) for e in range(6)]
    assert all(a > b > 0 for a, b in zip(errs, errs[1:], strict=False))
    dist = np.array([1.0, 10.0, 100.0, 1e3, 1e4, 1e7])
    lv = d.extra_levels_for(dist, screen_factor_px=935.0, threshold_px=2.0, max_extra=6)
    assert lv.shape == dist.shape and np.all(np.diff(lv) <= 0)
    assert lv[0] == 6 and lv[-1] == 0


# -- culling -------------------------------------------------------------------------------------------
def _slope_patch(facing_east: bool) -> tuple[np.ndarray, np.ndarray]:
    """A 3 x 3 grid (10 m) on a plane rising west->east (faces west) or east->west (faces east)."""
    r, c = np.meshgrid(np.arange(3), np.arange(3), indexing="ij")
    x, y = c * 10.0, -r * 10.0
    z = (20.0 - x) if facing_east else x
    v = np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1).astype(np.float64)
    idx = np.arange(9).reshape(3, 3)
    a, b, cc, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    tris = np.concatenate([np.stack([a, cc, d], 1), np.stack([a, d, b], 1)])
    return v, tris


def test_backface_culling_of_patches():
    v, t = _slope_patch(facing_east=True)
    assert not patch_backfacing(v, t, (100.0, -10.0, 5.0))  # eye east of the east-facing slope
    assert patch_backfacing(v, t, (-100.0, -10.0, 5.0))  # eye behind the slope, low
    assert not patch_backfacing(v, t, (-100.0, -10.0, 500.0))  # high above: sees its top
    assert patch_backfacing(v, t[:0], (0.0, 0.0, 0.0))
    # a valley: one face toward the eye keeps the patch
    w, u = _slope_patch(facing_east=False)
    both_v = np.concatenate([v, w + [20.0, 0.0, 0.0]])
    both_t = np.concatenate([t, u + 9])
    assert not patch_backfacing(both_v, both_t, (-100.0, -10.0, 5.0))
    out = patches_backfacing(both_v, both_t, np.repeat([0, 1], len(t)), 3, (-100.0, -10.0, 5.0))
    assert out.tolist() == [True, False, True]


def test_visible_region_looking_down_and_at_the_horizon():
    h = 1000.0
    poly = visible_region((0, 0, h), (0, 0, 0), up=(0, 1, 0), fov_y_deg=90.0, aspect=1.0, far_m=5000.0)
    assert poly.shape == (4, 2)
    np.testing.assert_allclose(np.sort(np.abs(poly), axis=0), h, atol=1e-6)
    # looking north, level: a trapezoid from the near ground line to the far plane
    poly = visible_region((0, 0, 100), (0, 1000, 100), fov_y_deg=60.0, aspect=1.5, near_m=1.0, far_m=3000.0)
    assert poly[:, 1].min() > 0 and poly[:, 1].max() <= 3000.0 + 1e-6
    assert visible_region((0, 0, 100), (0, 1000, 300), fov_y_deg=20.0, far_m=3000.0).shape == (0, 2)
    boxes = np.array(
        [[-50, 500, 50, 600], [-50, -600, 50, -500], [2000, 900, 2100, 1000], [-10, -10, 10, 250]]
    )
    assert boxes_in_region(boxes, poly).tolist() == [True, False, False, True]


@settings(max_examples=40, deadline=None)
@given(
    eye=st.tuples(st.floats(-500, 500), st.floats(-500, 500), st.floats(20, 800)),
    look=st.tuples(st.floats(-1, 1), st.floats(-1, 1), st.floats(-1, -0.05)),
    box=st.tuples(st.floats(-3000, 3000), st.floats(-3000, 3000), st.floats(1, 800), st.floats(1, 800)),
)
def test_region_test_matches_sampling(eye, look, box):
    up = (0.0, 0.0, 1.0) if np.hypot(look[0], look[1]) > 0.05 else (0.0, 1.0, 0.0)
    poly = visible_region(eye, np.add(eye, look), up=up, fov_y_deg=50.0, aspect=1.3, far_m=4000.0)
    b = np.array([[box[0], box[1], box[0] + box[2], box[1] + box[3]]])
    got = bool(boxes_in_region(b, poly)[0])
    if poly.shape[0] < 3:
        assert not got
        return
    assert got == _clip_nonempty(poly, b[0])


def _clip_nonempty(poly: np.ndarray, box: np.ndarray) -> bool:
    """Sutherland–Hodgman: does the convex polygon keep a point after clipping by the box?"""
    pts = [tuple(p) for p in poly]
    for axis, bound, keep_above in (
        (0, box[0], True),
        (0, box[2], False),
        (1, box[1], True),
        (1, box[3], False),
    ):
        out = []
        for i, cur in enumerate(pts):
            prev = pts[i - 1]
            cin = cur[axis] >= bound if keep_above else cur[axis] <= bound
            pin = prev[axis] >= bound if keep_above else prev[axis] <= bound
            if cin != pin:
                t = (bound - prev[axis]) / (cur[axis] - prev[axis])
                out.append(tuple(prev[k] + t * (cur[k] - prev[k]) for k in range(2)))
            if cin:
                out.append(cur)
        pts = out
        if not pts:
            return False
    return True


def test_boxes_in_frustum():
    # planes of a box-shaped "frustum": x in [0, 10], y in [0, 10], z >= 0
    planes = np.array([[1, 0, 0, 0], [-1, 0, 0, 10], [0, 1, 0, 0], [0, -1, 0, 10], [0, 0, 1, 0]], float)
    boxes = np.array(
        [[1, 1, 1, 2, 2, 2], [-5, -5, 0, -1, 2, 1], [9, 9, -5, 20, 20, -1], [9, 9, -1, 20, 20, 1]]
    )
    assert boxes_in_frustum(boxes, planes).tolist() == [True, False, False, True]


# -- the amplify product -------------------------------------------------------------------------------
def test_amplify_command_writes_a_georeferenced_geotiff(tmp_path, monkeypatch):
    import rasterio

    monkeypatch.setattr(fractal, "STRIP_ROWS", 16)  # several strips
    src = tmp_path / "dem.tif"
    hf = _hf(23, 31, 9, spacing=(10.0, 10.0), holes=True)
    from rasterio.crs import CRS

    with rasterio.open(
        src, "w", driver="GTiff", height=23, width=31, count=1, dtype="float32", nodata=-9999.0,
        crs=CRS.from_epsg(32633), transform=hf.transform,
    ) as dst:  # fmt: skip
        dst.write(np.where(hf.valid, hf.elevation_m, -9999.0).astype(np.float32), 1)
    out = tmp_path / "fine.tif"
    summary = amplify_command(src, out, factor=4, seed=3)
    assert summary["shape_out"] == [89, 121] and summary["factor"] == 4
    assert summary["spacing_out_m"] == [2.5, 2.5] and 0 < summary["nodata_fraction"] < 1
    assert 0.05 <= summary["hurst"]["min"] <= summary["hurst"]["max"] <= 0.95
    with rasterio.open(out) as ds:
        assert ds.crs == CRS.from_epsg(32633)
        assert ds.transform.a == 2.5 and ds.transform.e == -2.5
        z = ds.read(1)
        mask = ds.read_masks(1) > 0
        # world xy of input sample (r, c) == output (4r, 4c)
        assert ds.xy(8, 12) == pytest.approx(rasterio.transform.xy(hf.transform, 2, 3))
    from terralod.io.reader import read_heightfield

    hf_in = read_heightfield(src)
    ref = FractalDetail(hf_in, seed=3).amplify(4)
    assert np.array_equal(mask, ref.valid)
    assert np.array_equal(z[ref.valid], ref.elevation_m[ref.valid])
    assert np.all(np.isnan(z[~ref.valid]))
    assert np.array_equal(z[::4, ::4][hf_in.valid], hf_in.elevation_m[hf_in.valid])
    with pytest.raises(InputError, match="power of 2"):
        amplify_command(src, tmp_path / "x.tif", factor=3)
    assert not (tmp_path / "x.tif").exists()
    with pytest.raises(InputError, match="does not exist"):
        amplify_command(hf_in, tmp_path / "no" / "x.tif", factor=2)
    mem = amplify_command(hf_in, tmp_path / "y.tif", factor=2, seed=3, hurst=0.7, sigma=2.0)
    assert mem["hurst"]["mean"] == 0.7 and mem["sigma_m"]["max"] == 2.0
    (tmp_path / "y.tif").unlink()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dem.tif", "fine.tif"]


# -- real data -----------------------------------------------------------------------------------------
def test_real_srtm_alpine_crop(shared_data: Path, tmp_path):
    from terralod.io.reader import read_heightfield

    path = shared_data / "dem" / "srtm1_crop256_alpine.tif"
    hf = read_heightfield(path)
    d = FractalDetail(hf, seed=1)
    assert 0.5 < float(d.hurst_map.mean()) < 0.95  # reprojected SRTM relief is smooth at its finest lags
    assert 1.0 < float(d.sigma_map.mean()) < 100.0
    fine = d.amplify(4)
    assert np.array_equal(fine.elevation_m[::4, ::4], hf.elevation_m)
    assert fine.crs == hf.crs and np.array_equal(fine.valid[::4, ::4], hf.valid)
    # generated relief stays within a few sigma of the DEM's cell range
    z = fine.elevation_m
    lo = np.minimum.reduce(
        [hf.elevation_m[:-1, :-1], hf.elevation_m[1:, 1:], hf.elevation_m[:-1, 1:], hf.elevation_m[1:, :-1]]
    )
    assert np.all(z[2::4, 2::4] > lo - 10 * float(d.sigma_map.max()))
    assert np.array_equal(d.window(400, 300, 65, 65, 4), z[400:465, 300:365])
    summary = amplify_command(path, tmp_path / "alpine4.tif", factor=2, seed=1)
    assert summary["shape_out"] == [2 * hf.height - 1, 2 * hf.width - 1]
