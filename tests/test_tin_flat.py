"""Golden cases of the QEM's flat-ground paths on real coasts (issue 19): the vertical term's level-slot
skips, the carried points' hand-over, the test-first re-evaluation of fans of ~200 triangles and their
sorted candidates all leave the collapses as they were. The base meshes' hashes were recorded at 407f535,
before those changes (``benchmarks/tin_flat.py`` prints the same hashes)."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest

import terralod
from terralod.tin import DetailIncrementModel

#: (DEM file, window origin row/col, base mesh sha256[:10] at 407f535, sea fraction)
CASES = [
    ("srtm3_N41E001.tif", (600, 600), "3c354e6993", 0.32),  # Tarragona coast
    ("srtm3_N57E011.tif", (300, 300), "7b90526c5c", 0.98),  # Kattegat
]


@pytest.mark.parametrize(("name", "origin", "digest", "sea"), CASES)
def test_coast_and_sea_windows_keep_their_collapses(
    shared_data: Path, name: str, origin: tuple[int, int], digest: str, sea: float
) -> None:
    import rasterio

    path = shared_data / "dem" / name
    if not path.exists():
        pytest.skip(f"{path} not present")
    r0, c0 = origin
    with rasterio.open(path) as ds:
        z = ds.read(1).astype(np.float32)[r0 : r0 + 513, c0 : c0 + 513]
    assert abs(float((z == 0).mean()) - sea) < 0.01  # the window is the coast (sea) it is meant to be
    hf = terralod.Heightfield.from_array(z, 90.0, origin_m=(500000.0, 5200000.0))
    m = DetailIncrementModel.from_heightfield(hf, sub_blocks=4)
    got = hashlib.sha256(m._base_tris.tobytes() + m._base_alive.tobytes()).hexdigest()[:10]
    assert got == digest
