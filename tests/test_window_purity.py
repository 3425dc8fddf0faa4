"""A tile of an out-of-core build is a pure function of its code, whatever window it was built in.

The units of a build group tiles into windows; a resumed build groups the tiles it has left into other
windows, and Dask or a different ``unit_span_samples`` other windows again. Every tile, its errors against
the original samples of a geographic source included, must come out bit for bit the same (before the fix,
a tile measured against the original samples was placed from its window's origin, whose rounding
depended on the window: errors moved in the 11th digit after a resume).
"""

from __future__ import annotations

import weakref
from pathlib import Path

import pytest

from test_region_build import BUILD, _merged, _quarters, _rows

pytest.importorskip("pydelatin")
pytest.importorskip("pyproj")


def test_the_same_tiles_from_any_grouping_into_windows(tmp_path: Path) -> None:
    from terralod.io.windowed import open_source
    from terralod.pyramid.distributed import build_store_windowed

    tiles = _quarters(_merged(tmp_path / "merged.tif"), tmp_path / "tiles")
    got = []
    for span in (32, 64, 160):  # windows of one tile, of 2 x 2 or 4 x 4 tiles, and of whole levels
        out = tmp_path / f"span{span}.terra"
        build_store_windowed(open_source(tiles), out, **{**BUILD, "workers": 1, "unit_span_samples": span})
        got.append(_rows(out))
    assert got[0] and got[0] == got[1] == got[2]


def test_positions_dropped_from_memory_come_back_from_the_spill_file(tmp_path: Path, monkeypatch) -> None:
    """A region larger than the position blocks kept in memory transforms each block once: the blocks the
    LRU drops are read back from the spill file, and the tiles are the same numbers as with every block
    kept."""
    import terralod.pyramid.original as original
    from terralod.io.windowed import open_source
    from terralod.pyramid.distributed import build_store_windowed

    tiles = _quarters(_merged(tmp_path / "merged.tif"), tmp_path / "tiles")
    kept = tmp_path / "kept.terra"
    build_store_windowed(open_source(tiles), kept, **{**BUILD, "workers": 1})
    transformed: dict[tuple[int, int, int], int] = {}
    plain = original._Positions._transform

    def counted(self, br, bc, shape):
        key = (id(self), br, bc)  # per source grid: a mosaic has one per input tile
        transformed[key] = transformed.get(key, 0) + 1
        return plain(self, br, bc, shape)

    monkeypatch.setattr(original, "_POSITIONS", weakref.WeakKeyDictionary())  # no block of the first build
    monkeypatch.setattr(original, "POSITION_BLOCK", 8)
    monkeypatch.setattr(original, "POSITION_BLOCKS_KEPT", 2)
    monkeypatch.setattr(original._Positions, "_transform", counted)
    spilled = tmp_path / "spilled.terra"
    build_store_windowed(open_source(tiles), spilled, **{**BUILD, "workers": 1})
    assert len(transformed) > 4 * original.POSITION_BLOCKS_KEPT  # most blocks went through the spill file
    assert set(transformed.values()) == {1}, transformed
    assert _rows(kept) and _rows(kept) == _rows(spilled)


@pytest.fixture(scope="module")
def islet(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 1,800² projected DEM whose only data is a 300² patch near its north-west corner (the rest
    nodata: the open sea of a coastal survey, the corners of a region warped to UTM)."""
    import numpy as np
    import rasterio
    from rasterio.transform import from_origin

    rng = np.random.default_rng(11)
    z = np.full((1800, 1800), -9999.0, np.float32)
    yy, xx = np.mgrid[0:300, 0:300]
    z[100:400, 150:450] = 40 + 30 * np.sin(xx / 23.0) * np.cos(yy / 31.0) + rng.normal(0, 0.5, (300, 300))
    p = tmp_path_factory.mktemp("islet") / "islet.tif"
    with rasterio.open(p, "w", driver="GTiff", width=1800, height=1800, count=1, dtype="float32",
                       crs="EPSG:32631", transform=from_origin(400000, 4600000, 10, 10), nodata=-9999,
                       tiled=True, blockxsize=256, blockysize=256) as ds:  # fmt: skip
        ds.write(z, 1)
    return p


def test_a_block_far_from_the_data_takes_one_value_without_a_window_that_grows_with_the_distance(
    islet: Path,
) -> None:
    """A fill block with no valid sample within FILL_HALO_EXACT_MAX of it is one value: a valid sample's,
    the one nearest its centre here (one patch of data), read a block at a time (no read over the
    largest exact halo); any order of windows gives the same heights."""
    import numpy as np

    from terralod.io.region import FILL_HALO_EXACT_MAX
    from terralod.io.windowed import FILL_BLOCK, RasterSource

    src = RasterSource(islet)
    sizes: list[int] = []
    raw = src.read_raw

    def counted(r0: int, c0: int, r1: int, c1: int):
        sizes.append((r1 - r0) * (c1 - c0))
        return raw(r0, c0, r1, c1)

    src.read_raw = counted  # type: ignore[method-assign]
    z, ok = src.read(0, 0, 1800, 1800)
    assert sizes[0] == 1800 * 1800  # the window asked for, then the fill's reads
    assert max(sizes[1:]) <= (FILL_BLOCK + 2 * FILL_HALO_EXACT_MAX) ** 2
    data, valid = raw(0, 0, 1800, 1800)
    vr, vc = np.nonzero(valid)
    b = FILL_BLOCK
    far = 0
    for br in range(4):
        for bc in range(4):
            r0, c0 = br * b, bc * b
            near = valid[max(r0 - FILL_HALO_EXACT_MAX, 0) : r0 + b + FILL_HALO_EXACT_MAX,
                         max(c0 - FILL_HALO_EXACT_MAX, 0) : c0 + b + FILL_HALO_EXACT_MAX].any()  # fmt: skip
            if near:
                continue
            far += 1
            block = z[r0 : r0 + b, c0 : c0 + b]
            cr = (r0 + min(r0 + b, 1800) - 1) / 2.0
            cc = (c0 + min(c0 + b, 1800) - 1) / 2.0
            d2 = (vr - cr) ** 2 + (vc - cc) ** 2
            nearest = np.lexsort((vc, vr, d2))[0]
            assert np.all(block == np.float32(data[vr[nearest], vc[nearest]]))
    assert far >= 6
    again = RasterSource(islet)  # another process's copy, windows in another order
    rng = np.random.default_rng(2)
    for _ in range(10):
        r0, c0 = int(rng.integers(0, 1700)), int(rng.integers(0, 1700))
        r1, c1 = int(rng.integers(r0 + 1, 1801)), int(rng.integers(c0 + 1, 1801))
        wz, wok = again.read(r0, c0, r1, c1)
        assert np.array_equal(wz, z[r0:r1, c0:c1]) and np.array_equal(wok, ok[r0:r1, c0:c1])


def test_the_region_reader_fills_a_block_far_from_the_data_with_one_value_read_a_block_at_a_time(
    islet: Path,
) -> None:
    """The export's region reader (DEM tiles read straight, no store) follows the window sources' rule: a
    block with no valid sample within FILL_HALO_EXACT_MAX is the value of the valid sample nearest its
    centre, found with reads of a block at a time (never a window grown to the coast); blocks near the data
    keep their haloed fill; a second reader reading in another order gives the same heights."""
    import numpy as np

    from terralod.io.region import FILL_BLOCK, FILL_HALO_EXACT_MAX, RegionReader, resolve_region

    reader = RegionReader(resolve_region([islet]))
    reader.open()
    sizes: list[int] = []
    raw = reader.read_raw

    def counted(r0: int, r1: int, c0: int, c1: int):
        sizes.append((r1 - r0) * (c1 - c0))
        return raw(r0, r1, c0, c1)

    reader.read_raw = counted  # type: ignore[method-assign]
    b = FILL_BLOCK
    n = -(-1800 // b)
    blocks = {(i, j): reader.block(i, j) for i in range(n) for j in range(n)}
    assert max(sizes) <= (b + 2 * FILL_HALO_EXACT_MAX) ** 2
    data, valid = raw(0, 1800, 0, 1800)
    vr, vc = np.nonzero(valid)
    far = 0
    for (i, j), (z, ok) in blocks.items():
        r0, c0 = i * b, j * b
        r1, c1 = min(r0 + b, 1800), min(c0 + b, 1800)
        assert np.array_equal(z[ok], data[r0:r1, c0:c1][ok])  # valid samples kept
        near = valid[max(r0 - FILL_HALO_EXACT_MAX, 0) : r1 + FILL_HALO_EXACT_MAX,
                     max(c0 - FILL_HALO_EXACT_MAX, 0) : c1 + FILL_HALO_EXACT_MAX].any()  # fmt: skip
        if near:
            continue
        far += 1
        d2 = (vr - (r0 + r1 - 1) / 2.0) ** 2 + (vc - (c0 + c1 - 1) / 2.0) ** 2
        k = np.lexsort((vc, vr, d2))[0]
        assert np.all(z == data[vr[k], vc[k]]), (i, j)
    assert far >= 4
    again = RegionReader(resolve_region([islet]))
    again.open()
    for i, j in sorted(blocks, reverse=True):
        z, ok = again.block(i, j)
        assert np.array_equal(z, blocks[(i, j)][0]) and np.array_equal(ok, blocks[(i, j)][1])
    reader.close()
    again.close()
