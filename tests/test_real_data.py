"""Golden cases on real terrain: the bundled sample and DEMs of ../shared/data (skipped when absent)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from terralod import build_store, open_store, read_heightfield, sample_heightfield

from test_build import check_store_invariants


def test_bundled_sample_store(tmp_path: Path) -> None:
    hf = sample_heightfield()
    # reprojection turns the geographic grid slightly, so its corners fall outside the source footprint
    assert hf.crs is not None and "UTM zone 16N" in hf.crs and 0.0 < hf.nodata_fraction < 0.1
    dx, dy = hf.spacing_m
    assert 60 < dx < 95 and 60 < dy < 95
    out = tmp_path / "sample.terra"
    build_store(hf, out, tile_size=33)
    check_store_invariants(out, hf)
    with open_store(out) as s:
        # the finest level reproduces the reprojected grid up to quantisation, but its stored errors are
        # what the bilinear resampling moved the original samples by (tests/test_honest_errors.py)
        from terralod.error import measure_error

        top = s.pyramid.max_level
        on_grid = max(measure_error(t.vertices, t.triangles, hf).max_vertical_m for t in s.iter_tiles(top))
        assert on_grid <= s.quantisation[top].z_bound_m + 1e-6
        errs = s.tile_errors()
        finest = max(v for (k, _, _), (_, v) in errs.items() if k == top)
        assert finest > 10 * s.quantisation[top].z_bound_m
        assert s.meta["errors_measured_against"]["samples"] == "original"
        assert errs[(0, 0, 0)][1] >= finest


@pytest.mark.parametrize(
    "name, kwargs, tile_size",
    [
        ("dem/puget_sound_1k_u16.png", {}, 65),
        ("dem/kilauea_hawaii_30m_utm5.tif", {}, 65),
        ("dem/srtm1_crop256_coastal_flat_nodata.tif", {}, 33),
        ("dem/big_tujunga_srtm30m_utm11.tif", {}, 65),
    ],
)
def test_real_dem_store(shared_data: Path, tmp_path: Path, name: str, kwargs: dict, tile_size: int) -> None:
    hf = read_heightfield(shared_data / name, **kwargs)
    out = tmp_path / "real.terra"
    build_store(hf, out, tile_size=tile_size, workers=2)
    check_store_invariants(out, hf)
    with open_store(out) as s:
        errs = np.array([v for _, v in s.tile_errors().values()])
        assert np.isfinite(errs).all()


def test_puget_sound_golden(shared_data: Path, tmp_path: Path) -> None:
    """Puget Sound 1k, M = 65: 341 tiles over 5 levels; root error of the order of Rainier's relief."""
    hf = read_heightfield(shared_data / "dem/puget_sound_1k_u16.png")
    assert hf.width == hf.height == 1025 and hf.spacing_m == (160.0, 160.0)
    lo, hi = hf.valid_range_m()
    assert lo == 0.0 and abs(hi - 4379.8) < 0.01
    out = tmp_path / "ps.terra"
    build_store(hf, out, tile_size=65)
    with open_store(out) as s:
        assert s.levels == [0, 1, 2, 3, 4] and len(s.tile_codes()) == 341
        errs = s.tile_errors()
        root_h, root_v = errs[(0, 0, 0)]
        # a 65² grid over 164 km of Cascades misses peaks by hundreds of metres, not by tens of kilometres
        assert 100.0 < root_h <= root_v < 2000.0
        assert max(v for (k, _, _), (_, v) in errs.items() if k == 4) <= s.quantisation[4].z_bound_m + 1e-6
