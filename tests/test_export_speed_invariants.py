"""What the quantized-mesh exports' caches and locators must keep: the same samples and triangles as the
plain computation they stand in for.

- :class:`terralod.io.region.RegionReader`: a block evicted and read again (its fill kept, not redone) is
  the block first made; a coarse grid read through the thinned copies, and the water flags and bits,
  equal the whole grid's values.
- :mod:`terralod.kernels.tinlocate`: every point the bucket grid places is inside (edges included) the
  triangle it names, and every point inside some triangle is placed; heights are matplotlib's where it
  finds the same triangle.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st


@pytest.fixture(scope="module")
def holed(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 1,100 x 900 EPSG:4326 GeoTIFF with nodata holes (small ones and a large one) and sea at 0 m."""
    import rasterio
    from affine import Affine

    rng = np.random.default_rng(5)
    h, w = 1100, 900
    yy, xx = np.mgrid[0:h, 0:w]
    z = (200 + 80 * np.sin(xx / 37.0) + 60 * np.cos(yy / 53.0) + rng.normal(0, 2, (h, w))).astype(np.int16)
    z[:, :40] = 0  # sea
    z[100:103, 200:205] = -32768
    z[600:700, 500:640] = -32768  # beyond the first halo
    z[rng.integers(0, h, 300), rng.integers(0, w, 300)] = -32768
    p = tmp_path_factory.mktemp("reader") / "holed.tif"
    t = Affine(1 / 1200, 0, 1.0, 0, -1 / 1200, 43.0)
    with rasterio.open(p, "w", driver="GTiff", width=w, height=h, count=1, dtype="int16", crs="EPSG:4326",
                       transform=t, nodata=-32768, tiled=True, blockxsize=256, blockysize=256) as ds:  # fmt: skip
        ds.write(z, 1)
    return p


def _reader(path: Path, cache_blocks: int) -> object:
    from terralod.io.region import RegionReader, resolve_region

    return RegionReader(resolve_region([path]), cache_blocks=cache_blocks)


def test_an_evicted_block_reads_back_as_made_without_a_second_read_or_fill(holed: Path) -> None:
    whole = _reader(holed, 1000)
    z, ok = whole.window(0, 1100, 0, 900)
    small = _reader(holed, 1)  # every block evicted by the next
    for _ in range(2):
        for br in range(3):
            for bc in range(2):
                bz, bok = small.block(br, bc)
                r0, c0 = br * 512, bc * 512
                assert np.array_equal(bz, z[r0 : r0 + bz.shape[0], c0 : c0 + bz.shape[1]])
                assert np.array_equal(bok, ok[r0 : r0 + bz.shape[0], c0 : c0 + bz.shape[1]])
    assert small.blocks_read == 6  # each block read from the files once, again from the spill file
    assert small.blocks_filled == whole.blocks_filled  # each holed block filled once


@pytest.mark.parametrize("stride", [1, 2, 8, 64, 512])
def test_a_coarse_grid_and_the_water_are_the_whole_grids(holed: Path, stride: int) -> None:
    whole = _reader(holed, 1000)
    z, ok = whole.window(0, 1100, 0, 900)
    wet = ~ok | (z == 0.0)
    r = _reader(holed, 2)
    for r0, c0 in ((-3 * stride, -stride), (stride, 7 * stride), (1024, 512)):
        rows = np.clip(np.arange(r0, r0 + 40 * stride + 1, stride), 0, 1099)
        cols = np.clip(np.arange(c0, c0 + 40 * stride + 1, stride), 0, 899)
        gz, gok = r.gather(rows, cols)
        assert np.array_equal(gz, z[rows[:, None], cols[None, :]])
        assert np.array_equal(gok, ok[rows[:, None], cols[None, :]])
        assert np.array_equal(r.water_gather(rows, cols), wet[rows[:, None], cols[None, :]])
    for ra, rb, ca, cb in ((0, 1100, 0, 900), (90, 110, 190, 210), (0, 50, 0, 30), (0, 50, 60, 400),
                           (610, 690, 510, 630)):  # fmt: skip
        part = wet[ra:rb, ca:cb]
        assert r.water_any_all(ra, rb, ca, cb) == (bool(part.any()), bool(part.all()))


@settings(max_examples=30, deadline=None)
@given(n=st.integers(3, 60), seed=st.integers(0, 10_000))
def test_the_bucket_grid_places_points_in_their_triangles(n: int, seed: int) -> None:
    from scipy.spatial import Delaunay

    from terralod.export.source import _TriangleLocator

    rng = np.random.default_rng(seed)
    pts = rng.uniform(0, 100, (n, 2))
    pts = np.unique(np.round(pts, 3), axis=0)
    if len(pts) < 3:
        return
    try:
        tris = Delaunay(pts).simplices.astype(np.int64)
    except Exception:  # noqa: BLE001 - collinear draws: nothing to locate in
        return
    q = np.concatenate([rng.uniform(-10, 110, (400, 2)), pts])  # vertices: on edges of several triangles
    loc = _TriangleLocator(pts[:, 0], pts[:, 1], tris)
    got = loc.locate(q[:, 0], q[:, 1])
    a, b, c = pts[tris[:, 0]], pts[tris[:, 1]], pts[tris[:, 2]]

    def cross(p: np.ndarray, r: np.ndarray, s: np.ndarray) -> np.ndarray:
        return (r[..., 0] - p[..., 0]) * (s[..., 1] - p[..., 1]) - (r[..., 1] - p[..., 1]) * (
            s[..., 0] - p[..., 0]
        )

    qq = q[:, None, :]
    d1, d2, d3 = cross(a, b, qq), cross(b, c, qq), cross(c, a, qq)
    area = cross(a, b, c)
    inside = np.where(area > 0, (d1 >= 0) & (d2 >= 0) & (d3 >= 0), (d1 <= 0) & (d2 <= 0) & (d3 <= 0))
    inside &= area != 0
    found = got >= 0
    assert np.array_equal(found, inside.any(axis=1))
    assert inside[np.flatnonzero(found), got[found]].all()


def test_tin_heights_are_matplotlibs_where_the_triangle_is_the_same() -> None:
    import matplotlib.tri as mtri
    from scipy.spatial import Delaunay

    from terralod.export.source import _TriangleLocator

    rng = np.random.default_rng(1)
    pts = rng.uniform(0, 1000, (500, 2))
    z = rng.uniform(0, 300, 500)
    tris = Delaunay(pts).simplices.astype(np.int64)
    q = rng.uniform(-50, 1050, (5000, 2))
    tr = mtri.Triangulation(pts[:, 0], pts[:, 1], tris)
    ref = mtri.LinearTriInterpolator(tr, z)(q[:, 0], q[:, 1])
    theirs = tr.get_trifinder()(q[:, 0], q[:, 1])
    planes = tr.calculate_plane_coefficients(z)
    t = _TriangleLocator(pts[:, 0], pts[:, 1], tris).locate(q[:, 0], q[:, 1])
    assert np.array_equal(t >= 0, ~np.ma.getmaskarray(ref))
    same = (t >= 0) & (t == theirs)
    mine = planes[t[same], 0] * q[same, 0] + planes[t[same], 1] * q[same, 1] + planes[t[same], 2]
    assert same.sum() > 0.99 * (t >= 0).sum()
    assert np.array_equal(mine, np.ma.getdata(ref)[same])
    # the kernel the export evaluates them with: the same bits, NaN where no triangle holds the point
    from terralod.kernels.tinlocate import plane_heights

    qx, qy = np.ascontiguousarray(q[:, 0]), np.ascontiguousarray(q[:, 1])
    k = plane_heights(np.ascontiguousarray(planes, np.float64), t, qx, qy)
    assert np.array_equal(np.isnan(k), t < 0)
    assert np.array_equal(k[same], np.ma.getdata(ref)[same])


def test_a_spill_file_lives_beside_the_output_and_never_eats_the_disk_reserve(
    holed: Path, tmp_path: Path, monkeypatch
) -> None:
    """Spill files go to the output's folder (not a RAM-backed /tmp) and decline past the disk's reserve:
    the reader then reads a dropped block from the files again, the same values."""
    import terralod.output as output

    beside = tmp_path / "out"
    beside.mkdir()
    with output.scratch_beside(beside / "web"):
        spill = output.SpillFile("t-")
        assert spill.put(4096, b"abc") and spill.get(4096, 3) == b"abc"
        assert os.readlink(f"/proc/self/fd/{spill._file.fileno()}").startswith(str(beside))
    monkeypatch.setattr(output, "SPILL_RESERVE_BYTES", 1 << 62)  # no disk is that large: every put declines
    full = output.SpillFile("t-")
    assert not full.put(0, b"abc") and full.bytes_written == 0
    whole = _reader(holed, 1000)
    z, ok = whole.window(0, 1100, 0, 900)
    small = _reader(holed, 1)
    for _ in range(2):
        for br in range(3):
            for bc in range(2):
                bz, bok = small.block(br, bc)
                assert np.array_equal(
                    bz, z[br * 512 : br * 512 + bz.shape[0], bc * 512 : bc * 512 + bz.shape[1]]
                )
                assert np.array_equal(
                    bok, ok[br * 512 : br * 512 + bz.shape[0], bc * 512 : bc * 512 + bz.shape[1]]
                )
    assert small.blocks_read == 12  # nothing spilled: each block read from the files each time


def test_a_dropped_warped_block_reads_back_as_warped_without_a_second_warp(holed: Path, monkeypatch) -> None:
    """A geographic region's warped blocks that the LRU drops come back from the spill file as the same
    bytes (heights, NaN where invalid, and the mask), whatever the order windows ask for them; each block
    is warped from the source once."""
    from collections import OrderedDict

    import terralod.io.windowed as windowed

    monkeypatch.setattr(windowed, "WARP_ROWS", 128)  # several block rows on this small grid
    whole = windowed.WarpedSource([holed])
    z, ok = whole.read_raw(0, 0, whole.height, whole.width)
    distinct = whole._state.blocks_warped
    assert distinct == -(-whole.height // 128) * (len(whole._bands) - 1)
    monkeypatch.setattr(windowed, "_warp_states", OrderedDict())  # a fresh process's caches
    monkeypatch.setattr(windowed, "WARP_CACHE_SAMPLES", 1)  # every block dropped by the next
    small = windowed.WarpedSource([holed])
    rng = np.random.default_rng(3)
    for _ in range(12):
        r0, c0 = int(rng.integers(0, small.height - 1)), int(rng.integers(0, small.width - 1))
        r1 = int(rng.integers(r0 + 1, min(small.height, r0 + 400) + 1))
        c1 = int(rng.integers(c0 + 1, small.width + 1))
        wz, wok = small.read_raw(r0, c0, r1, c1)
        assert np.array_equal(wz, z[r0:r1, c0:c1], equal_nan=True)
        assert np.array_equal(wok, ok[r0:r1, c0:c1])
    assert small._state.blocks_warped <= distinct  # never a block warped twice
    assert small._state.spill.bytes_written > 0
