"""TileStore: round trips of the blob coding, corrupted and foreign files give clear errors."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from terralod import CorruptStoreError, Heightfield, StoreError, build_store, open_store
from terralod.store import decode_triangles, decode_vertices, encode_triangles, encode_vertices

from conftest import fractal_terrain


@given(q=hnp.arrays(np.uint16, st.tuples(st.integers(1, 300), st.just(3))))
@settings(max_examples=100, deadline=None)
def test_vertex_coding_round_trip(q: np.ndarray) -> None:
    assert np.array_equal(decode_vertices(encode_vertices(q), len(q)), q)


@given(t=hnp.arrays(np.uint32, st.tuples(st.integers(1, 300), st.just(3)), elements=st.integers(0, 2**20)))
@settings(max_examples=100, deadline=None)
def test_triangle_coding_round_trip(t: np.ndarray) -> None:
    assert np.array_equal(decode_triangles(encode_triangles(t), len(t)), t)


@pytest.fixture()
def small_store(tmp_path: Path) -> Path:
    hf = Heightfield.from_array(fractal_terrain(80, 70, 3), 20.0)
    out = tmp_path / "s.terra"
    build_store(hf, out, tile_size=17)
    return out


def test_open_store_api(small_store: Path) -> None:
    with open_store(small_store) as s:
        assert s.levels == [0, 1, 2, 3]
        assert s.tile_codes(0) == [(0, 0, 0)]
        t = s.tile(0, 0, 0)
        assert t.vertices.dtype == np.float64 and t.vertices.shape[1] == 3
        assert t.triangles.dtype == np.uint32 and t.triangles.shape[1] == 3
        assert t.error_m >= 0 and t.vertical_error_m >= t.error_m
        assert t.z_min_m <= t.vertices[:, 2].min() + 1e-9 and t.z_max_m >= t.vertices[:, 2].max() - 1e-9
        assert s.verify() == []
        with pytest.raises(KeyError):
            s.tile(9, 0, 0)


def test_missing_and_foreign_files(tmp_path: Path) -> None:
    with pytest.raises(StoreError, match="store not found"):
        open_store(tmp_path / "nope.terra")
    txt = tmp_path / "notes.terra"
    txt.write_text("hello, this is not a database at all " * 10)
    with pytest.raises(CorruptStoreError, match=r"notes\.terra: not a terralod store"):
        open_store(txt)
    foreign = tmp_path / "foreign.terra"
    con = sqlite3.connect(foreign)
    con.execute("CREATE TABLE t (a)")
    con.commit()
    con.close()
    with pytest.raises(CorruptStoreError, match="foreign SQLite"):
        open_store(foreign)


def test_corrupted_tile_detected(small_store: Path) -> None:
    con = sqlite3.connect(small_store)
    blob = bytearray(con.execute("SELECT vertices FROM tiles WHERE level=1 AND x=0 AND y=0").fetchone()[0])
    blob[len(blob) // 2] ^= 0xFF
    con.execute("UPDATE tiles SET vertices=? WHERE level=1 AND x=0 AND y=0", (bytes(blob),))
    con.commit()
    con.close()
    with open_store(small_store) as s:
        s.tile(0, 0, 0)  # others still readable
        with pytest.raises(CorruptStoreError, match=r"tile \(1, 0, 0\) fails its checksum"):
            s.tile(1, 0, 0)
        assert s.verify() == [(1, 0, 0)]


def test_truncated_store(small_store: Path, tmp_path: Path) -> None:
    data = small_store.read_bytes()
    cut = tmp_path / "cut.terra"
    cut.write_bytes(data[: len(data) // 3])
    with pytest.raises(CorruptStoreError, match=r"cut\.terra"):
        with open_store(cut) as s:
            s.verify()


@settings(max_examples=6, deadline=None)
@given(
    w=st.integers(40, 200), h=st.integers(40, 200), tile=st.sampled_from([9, 17, 33]), seed=st.integers(0, 50)
)
def test_the_store_summary_summed_by_sqlite_is_the_per_tile_sum(tmp_path_factory, w: int, h: int, tile: int,
                                                                seed: int) -> None:  # fmt: skip
    """``store_summary`` (what ``build`` prints and ``info`` shows), summed by SQLite a level at a time so
    that a region's summary holds no row a tile, gives the per-tile loop's figures: counts and maxima
    exactly, the RMS to rounding; and ``info``'s elevation range is the range of the tiles with vertices."""
    import math

    from terralod.cli.info import grid_extent
    from terralod.pyramid.builder import store_summary

    hf = Heightfield.from_array(fractal_terrain(h, w, seed), 20.0)
    hf.valid[: h // 3, : w // 4] = False  # a corner of nodata: tiles without vertices
    p = tmp_path_factory.mktemp("summary") / "s.terra"
    build_store(hf, p, tile_size=tile)
    with open_store(p) as s:
        got = store_summary(s)
        rows = s.tile_summaries()
        rng = grid_extent(s)["elevation_range_m"]
    assert got["tiles"] == len(rows) == got["tiles_planned"]
    for level, d in got["per_level"].items():
        mine = [r for r in rows if r["level"] == level]
        assert d["tiles"] == len(mine)
        for key, col in (("vertices", "n_vertices"), ("triangles", "n_triangles"), ("samples", "n_samples"),
                         ("bytes", "bytes")):  # fmt: skip
            assert d[key] == sum(r[col] for r in mine)
        assert d["max_error_m"] == max(r["error_m"] for r in mine)
        assert d["max_vertical_error_m"] == max(r["vertical_error_m"] for r in mine)
        n = sum(r["n_samples"] for r in mine)
        want = math.sqrt(sum(r["rms_error_m"] ** 2 * r["n_samples"] for r in mine) / n) if n else 0.0
        assert math.isclose(d["rms_error_m"], want, rel_tol=1e-12, abs_tol=1e-12)
    live = [r for r in rows if r["n_vertices"] > 0]
    assert rng == [min(r["z_min_m"] for r in live), max(r["z_max_m"] for r in live)]
