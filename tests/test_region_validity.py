"""A region's reader takes a sample's validity from the nodata value where that value says it exactly (an
integer band's nodata, NaN, no nodata at all) and from GDAL's mask otherwise: over random rasters (dtype,
nodata value, holes, NaN) in one file and in a folder of two (read through the region's VRT), every
window it reads has the validity and the values of rasterio's masked read of the same file."""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import pytest
import rasterio
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from rasterio.transform import from_origin

from terralod.io.region import RegionReader, resolve_region

CASES = [("int16", -32768), ("int16", 0), ("uint8", None), ("uint16", 65535), ("float32", float("nan")),
         ("float32", -9999.0), ("float64", None), ("int32", -9999)]  # fmt: skip


def _write(path: Path, a: np.ndarray, x0: float, nodata) -> None:
    with rasterio.open(path, "w", driver="GTiff", width=a.shape[1], height=a.shape[0], count=1, dtype=a.dtype,
                       crs="EPSG:4326", transform=from_origin(x0, 42.0, 0.001, 0.001), nodata=nodata,
                       tiled=True, blockxsize=16, blockysize=16) as ds:  # fmt: skip
        ds.write(a, 1)


@pytest.mark.parametrize(("dtype", "nodata"), CASES)
@settings(max_examples=8, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(seed=st.integers(0, 2**31), holes=st.floats(0.0, 0.6), two=st.booleans())
def test_validity_is_the_masked_reads(tmp_path: Path, dtype, nodata, seed, holes, two) -> None:
    rng = np.random.default_rng(seed)
    dt = np.dtype(dtype)
    h, w = int(rng.integers(5, 60)), int(rng.integers(5, 60))
    d = Path(tempfile.mkdtemp(dir=tmp_path))
    files = []
    for k in range(2 if two else 1):
        if np.issubdtype(dt, np.integer):
            a = rng.integers(max(np.iinfo(dt).min, -500), min(np.iinfo(dt).max, 500), (h, w)).astype(dt)
        else:
            a = rng.normal(100.0, 50.0, (h, w)).astype(dt)
            a[rng.random((h, w)) < 0.05] = np.nan  # NaN samples: invalid whatever the nodata
        if nodata is not None:
            a[rng.random((h, w)) < holes] = nodata
        p = d / f"t{k}.tif"
        _write(p, a, 1.0 + k * (w - 1) * 0.001, nodata)  # side by side, one shared column
        files.append(p)
    region = resolve_region(d if two else files[0])
    reader = RegionReader(region)
    with rasterio.open(region.target) as ds:
        H, W = ds.height, ds.width
        for _ in range(4):
            r0, c0 = int(rng.integers(0, H)), int(rng.integers(0, W))
            r1, c1 = int(rng.integers(r0 + 1, H + 1)), int(rng.integers(c0 + 1, W + 1))
            m = ds.read(1, window=((r0, r1), (c0, c1)), masked=True)
            want_ok = ~np.ma.getmaskarray(m) & np.isfinite(np.ma.getdata(m).astype(np.float64))
            values, ok = reader.read_raw(r0, r1, c0, c1)
            np.testing.assert_array_equal(ok, want_ok)
            np.testing.assert_array_equal(values[ok], np.ma.getdata(m)[want_ok].astype(values.dtype))
    reader.close()
