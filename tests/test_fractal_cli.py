"""`terralod amplify`: a GeoTIFF at the finer spacing whose samples at the DEM's positions are the DEM's."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import rasterio
from rasterio.transform import from_origin

from conftest import fractal_terrain, terralod_cli


def _write_utm_tif(path: Path, z: np.ndarray, spacing_m: float) -> Path:
    """A float32 GeoTIFF in UTM 33N whose north-west corner is at (400000, 5000000)."""
    with rasterio.open(path, "w", driver="GTiff", width=z.shape[1], height=z.shape[0], count=1, dtype="float32",
                       crs="EPSG:32633", transform=from_origin(400000.0, 5000000.0, spacing_m, spacing_m)) as ds:  # fmt: skip
        ds.write(z, 1)
    return path


def test_amplify_cli_keeps_samples_and_georeferencing(tmp_path: Path) -> None:
    z = fractal_terrain(33, 41, 4, relief_m=300.0)
    src = _write_utm_tif(tmp_path / "dem.tif", z, 20.0)
    out = tmp_path / "fine.tif"
    p = terralod_cli("amplify", str(src), "-o", str(out), "--factor", "4")
    assert p.returncode == 0, p.stderr
    with rasterio.open(out) as ds:
        fine = ds.read(1)
        assert ds.res == (5.0, 5.0) and ds.crs.to_epsg() == 32633
        # DEM sample (r, c) is fine sample (4r, 4c) at the same world position
        x, y = ds.xy(8, 12)
        assert (x, y) == (400000.0 + 10.0 + 3 * 20.0, 5000000.0 - 10.0 - 2 * 20.0)
    assert fine.shape == (32 * 4 + 1, 40 * 4 + 1)
    assert np.array_equal(fine[::4, ::4], z)
    # the detail between the samples is not a plain interpolation
    assert np.abs(fine[2::4, 2::4] - 0.25 * (z[:-1, :-1] + z[1:, 1:] + z[:-1, 1:] + z[1:, :-1])).max() > 0.01


def test_build_fractal_levels_are_used_by_render(tmp_path: Path) -> None:
    """`build --fractal 2` records the levels in the store; `render` of that store then refines into
    fractal levels below the DEM without being told (and `--fractal 0` turns them off)."""
    z = fractal_terrain(65, 65, 9, relief_m=400.0)
    src = _write_utm_tif(tmp_path / "dem.tif", z, 30.0)
    store = tmp_path / "dem.terra"
    p = terralod_cli("build", str(src), "-o", str(store), "--tile-size", "17", "--fractal", "2")
    assert p.returncode == 0, p.stderr
    from terralod import open_store

    with open_store(store) as s:
        assert s.meta["fractal_levels"] == 2
        finest = s.pyramid.max_level
    # a low close-up over the middle of the terrain
    eye, tgt = f"400975,4999025,{float(z.max()) + 60.0:f}", f"401100,4998900,{float(z.mean()):f}"
    for extra in ([], ["--fractal", "0"]):
        out = tmp_path / f"f{len(extra)}.png"
        p = terralod_cli("-v", "render", str(store), "-o", str(out), "--eye", eye, "--target", tgt, "--size",
                         "320x240", "--threshold-px", "1", *extra)  # fmt: skip
        assert p.returncode == 0, p.stderr
        assert out.exists()
    from terralod.cli._inputs import with_fractal as _with_fractal

    read = dict.fromkeys(("spacing", "vertical_scale", "vertical_offset", "encoding", "tile_zxy"))
    with open_store(store) as s:
        assert _with_fractal(s, str(store), read, None).pyramid.max_level == finest + 2
        assert _with_fractal(s, str(store), read, 0) is s
        assert _with_fractal(s, str(store), read, 1).pyramid.max_level == finest + 1
