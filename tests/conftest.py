"""Shared fixtures: real data from ../shared/data (skipped with a reason when absent), random terrains."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

SHARED_DATA = Path(
    os.environ.get("TERRALOD_SHARED_DATA", Path(__file__).resolve().parents[1] / ".." / "shared" / "data")
)


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The real terrain of ../shared/data; tests using it skip when the folder is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real terrain data not present at {SHARED_DATA} (../shared/data beside the repository)")
    return SHARED_DATA.resolve()


def fractal_terrain(
    rows: int, cols: int, seed: int, relief_m: float = 500.0, beta: float = 2.2
) -> np.ndarray:
    """A spectral-synthesis fBm terrain (power ~ f^-beta), float32 metres; deterministic per seed."""
    rng = np.random.default_rng(seed)
    n = max(rows, cols)
    fy = np.fft.fftfreq(n)[:, None]
    fx = np.fft.rfftfreq(n)[None, :]
    f = np.sqrt(fx * fx + fy * fy)
    f[0, 0] = 1.0
    amp = f ** (-beta / 2.0)
    amp[0, 0] = 0.0
    spec = amp * (rng.normal(size=amp.shape) + 1j * rng.normal(size=amp.shape))
    z = np.fft.irfft2(spec, s=(n, n))[:rows, :cols]
    z = (z - z.min()) / max(np.ptp(z), 1e-12) * relief_m
    return z.astype(np.float32)


def crop_geotiff(src: Path, dest: Path, col: int, row: int, side: int) -> Path:
    """A side x side window of the GeoTIFF ``src`` from (col, row) written to ``dest``, its georeferencing
    kept (untiled); asserts the window holds no nodata."""
    import rasterio
    from rasterio.windows import Window

    with rasterio.open(src) as ds:
        win = Window(col, row, side, side)
        a = ds.read(1, window=win)
        prof = dict(ds.profile, width=side, height=side, transform=ds.window_transform(win), tiled=False)
    prof.pop("blockxsize", None)
    prof.pop("blockysize", None)
    assert prof.get("nodata") is None or not (a == prof["nodata"]).any()
    with rasterio.open(dest, "w", **prof) as out:
        out.write(a, 1)
    return dest
