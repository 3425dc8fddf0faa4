"""A tile of an out-of-core build is a pure function of its code, whatever window it was built in.

The units of a build group tiles into windows; a resumed build groups the tiles it has left into other
windows, and Dask or a different ``unit_span_samples`` other windows again. Every tile, its errors against
the original samples of a geographic source included, must come out bit for bit the same (before the fix,
a tile measured against the original samples was placed from its window's origin, whose rounding
depended on the window: errors moved in the 11th digit after a resume).
"""

from __future__ import annotations

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
