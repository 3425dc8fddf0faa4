"""A projected region (UTM tiles, as a county's LiDAR DEMs come) exported to quantized-mesh window by window.

A 161² crop of the Kilauea 30 m UTM DEM (with voids) is cut into four GeoTIFFs sharing their edge row and
column. The windowed reader (:class:`terralod.export.source.RegionGrid`) must give the tiles, byte for byte,
that the in-memory reader gives (:class:`terralod.export.source.SourceGrid` of the merged DEM read whole),
its errors measured against every original sample; and it must never read the region whole: coarse tiles are
measured strip by strip, whatever the region's size.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from terralod.cli import main

pytest.importorskip("pydelatin")
pytest.importorskip("pyproj")

N = 161  #: samples a side of the merged crop
K = 80  #: the split: tiles [0, K] and [K, N) share row/column K
CROP = (560, 640)  #: (row, col) of the crop in the Kilauea DEM: 1,366 voids


def _write(path: Path, a: np.ndarray, transform, crs) -> Path:  # noqa: ANN001
    import rasterio

    with rasterio.open(path, "w", driver="GTiff", width=a.shape[1], height=a.shape[0], count=1, dtype=a.dtype,
                       crs=crs, transform=transform, nodata=-32768, tiled=True, blockxsize=64, blockysize=64,
                       compress="deflate") as ds:  # fmt: skip
        ds.write(a, 1)
    return path


@pytest.fixture(scope="module")
def crop(shared_data: Path) -> tuple[np.ndarray, object, object]:
    import rasterio
    from rasterio.windows import Window

    with rasterio.open(shared_data / "dem" / "kilauea_hawaii_30m_utm5.tif") as ds:
        win = Window(CROP[1], CROP[0], N, N)
        a = ds.read(1, window=win)
        t, crs = ds.window_transform(win), ds.crs
    assert (a == -32768).sum() > 100 and crs.is_projected
    return a, t, crs


@pytest.fixture(scope="module")
def quads(crop: tuple[np.ndarray, object, object], tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    from affine import Affine

    a, t, crs = crop
    d = tmp_path_factory.mktemp("quads")
    out = []
    for name, r0, c0 in (("nw", 0, 0), ("ne", 0, K), ("sw", K, 0), ("se", K, K)):
        q = a[r0 : (K + 1 if r0 == 0 else N), c0 : (K + 1 if c0 == 0 else N)]
        out.append(_write(d / f"{name}.tif", np.ascontiguousarray(q), t @ Affine.translation(c0, r0), crs))
    return out


def test_a_projected_region_gives_the_in_memory_tiles(
    crop: tuple[np.ndarray, object, object], quads: list[Path], tmp_path: Path
) -> None:
    from terralod.export.quantized_mesh import QuantizedMesh
    from terralod.export.source import RegionGrid, SourceGrid, source_from_region

    a, t, crs = crop
    region = source_from_region([str(q) for q in quads])
    assert isinstance(region, RegionGrid) and not region.identity
    # the merged DEM read whole, filled as a store fills it: the in-memory reader
    from terralod.io.reader import read_heightfield

    hf = read_heightfield(_write(tmp_path / "merged.tif", a, t, crs))
    whole = SourceGrid(
        np.asarray(hf.elevation_m, np.float64), np.asarray(hf.valid), hf.transform, hf.crs, "m"
    )
    assert region.bbox == whole.bbox and region.spacing_deg == whole.spacing_deg
    qa, qb = QuantizedMesh(region), QuantizedMesh(whole)
    codes = qa.tile_codes()
    assert codes == qb.tile_codes() and len(codes) > 10
    for code in codes:
        ta, tb = qa.tile(*code), qb.tile(*code)
        assert ta.raw == tb.raw and ta.error_m == tb.error_m, code
    # and through the command line, every form of the region alike
    out = tmp_path / "cli"
    main(["export", *map(str, quads), "--format", "quantized-mesh", "-o", str(out)])
    for code in codes:
        assert (out / f"{code[0]}/{code[1]}/{code[2]}.terrain").read_bytes() == qa.tile(*code).raw


def test_a_projected_region_is_never_read_whole(
    quads: list[Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """With strips of 2,000 samples and a cache of 2 blocks of 32², the largest window the export reads is a
    strip or a finest tile's footprint, far below the region; the declared errors are the same as with
    the default strips (a strip's maximum is the tile's)."""
    from terralod.export import source as src_mod
    from terralod.export.quantized_mesh import QuantizedMesh
    from terralod.io import region as rg

    want = {}
    q0 = QuantizedMesh(src_mod.source_from_region([str(q) for q in quads]))
    for code in q0.tile_codes():
        want[code] = q0.tile(*code).error_m
    monkeypatch.setattr(src_mod, "READ_STRIP_SAMPLES", 2000)
    monkeypatch.setattr(rg, "FILL_BLOCK", 32)
    monkeypatch.setattr(rg, "CACHE_BLOCKS", 2)
    seen: list[int] = []
    real = rg.RegionReader.window

    def window(self, r0: int, r1: int, c0: int, c1: int):  # noqa: ANN001, ANN202
        seen.append((r1 - r0) * (c1 - c0))
        return real(self, r0, r1, c0, c1)

    monkeypatch.setattr(rg.RegionReader, "window", window)
    qm = QuantizedMesh(src_mod.source_from_region([str(q) for q in quads]))
    got = {code: qm.tile(*code).error_m for code in qm.tile_codes()}
    assert got == want
    assert seen and max(seen) <= N * N // 4, max(seen)
