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
