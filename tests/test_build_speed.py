"""The build's fast paths give the numbers of the plain ones, bit for bit (issue 19, build speed).

- the tile coding kernels (:mod:`terralod.kernels.codec`) against the store's numpy coding
  (``terralod.store.encode_vertices`` / ``encode_triangles``) and the builder's ``_quantise``;
- the error kernel's path for unit lattice triangles (every tile of stride 1) against the brute-force
  reference of ``tests/test_error.py``, on full-resolution grids mixed with larger triangles;
- the adaptive mesher's raster order kernel against numpy's lexsort;
- a build that meshes every level in one stream (no barrier between levels) against the same build tile
  by tile with ``build_tile`` and the children's errors, on one and several threads, and resumed: every
  stored error is the measured maximum (a brute-force re-measurement of each tile as stored) made
  monotone, every tile byte-identical.
"""

from __future__ import annotations

import math
import sqlite3
import tempfile
import zlib
from pathlib import Path

import deflate
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from terralod import build_store, open_store
from terralod.error import measure_error_window
from terralod.heightfield import Heightfield
from terralod.kernels.codec import quantise_tile, triangle_codes16, triangle_codes32, vertex_codes
from terralod.pyramid import adaptive
from terralod.pyramid.builder import (
    _TASK_SAMPLES,
    METHODS,
    _quantise,
    _tasks,
    build_tile,
    plan_quantisation,
)
from terralod.pyramid.footprint import _all_true
from terralod.store import (
    DEFLATE_LEVEL,
    LevelQuantisation,
    encode_triangles,
    encode_vertices,
)
from terralod.tiles import TilePyramid
from test_error import reference, terrain  # type: ignore[import-not-found]


def _zigzag_delta16(a: np.ndarray) -> np.ndarray:
    """The store's coding in numpy (the reference the kernels replace): zig-zag of wrapped 16-bit deltas."""
    d = np.diff(a.astype(np.int64), prepend=np.int64(0)).astype(np.uint16).view(np.int16).astype(np.int32)
    return ((d << 1) ^ (d >> 15)).astype(np.uint16)


def _zigzag_delta32(a: np.ndarray) -> np.ndarray:
    d = np.diff(a.astype(np.int64), prepend=np.int64(0)).astype(np.uint32).view(np.int32).astype(np.int64)
    return ((d << 1) ^ (d >> 31)).astype(np.uint32)


def _encode_vertices(q: np.ndarray) -> bytes:
    cols = [_zigzag_delta16(q[:, k]) for k in range(3)]
    return deflate.zlib_compress(np.concatenate(cols).astype("<u2").tobytes(), DEFLATE_LEVEL)


def _encode_triangles(t: np.ndarray) -> bytes:
    flat = t.astype(np.int64).ravel()
    if flat.size == 0 or flat.max() < 65536:
        return b"\x02" + deflate.zlib_compress(_zigzag_delta16(flat).astype("<u2").tobytes(), DEFLATE_LEVEL)
    return b"\x04" + deflate.zlib_compress(_zigzag_delta32(flat).astype("<u4").tobytes(), DEFLATE_LEVEL)


SETTINGS = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])


# -- tile coding ---------------------------------------------------------------------------------------


@given(seed=st.integers(0, 2**32 - 1), n=st.integers(0, 300), spread=st.sampled_from([3, 300, 65535]))
@SETTINGS
def test_coding_kernels_match_the_store(seed: int, n: int, spread: int) -> None:
    rng = np.random.default_rng(seed)
    q = rng.integers(0, spread + 1, (n, 3)).astype(np.uint16)
    assert np.array_equal(vertex_codes(q), np.concatenate([_zigzag_delta16(q[:, k]) for k in range(3)]))
    assert _encode_vertices(q) == encode_vertices(q)
    assert type(encode_vertices(q)) is bytes  # (libdeflate returns a bytearray; the store keeps bytes)
    assert zlib.decompress(encode_vertices(q)) == vertex_codes(q).astype("<u2").tobytes()  # zlib reads it
    for top in (10, 65535, 65536, 2**31 + 5):
        t = rng.integers(0, top, (n, 3)).astype(np.int64)
        flat = t.ravel()
        if top <= 65536:
            assert np.array_equal(triangle_codes16(t), _zigzag_delta16(flat))
        assert np.array_equal(triangle_codes32(t), _zigzag_delta32(flat))
        assert _encode_triangles(t) == encode_triangles(t)
        assert type(encode_triangles(t)) is bytes
        assert _encode_triangles(t.astype(np.int32) if top <= 2**31 else t) == encode_triangles(t)
        # the builder's call: the vertex count bounds the indices (any count above the largest index)
        n_vertices = int(t.max()) + 1 + int(rng.integers(0, 3)) if t.size else 0
        assert encode_triangles(t, n_vertices=n_vertices) == _encode_triangles(t)
        if top <= 2**31:
            assert encode_triangles(t.astype(np.int32), n_vertices=n_vertices) == _encode_triangles(t)


@given(seed=st.integers(0, 2**32 - 1), shape=st.tuples(st.integers(1, 40), st.integers(1, 40)),
       p_false=st.sampled_from([0.0, 0.001, 0.3, 1.0]), step=st.integers(1, 3))  # fmt: skip
@SETTINGS
def test_all_true_kernel_is_numpy_all(seed: int, shape: tuple[int, int], p_false: float, step: int) -> None:
    """drop_nodata's GIL-free all-valid test equals ``ndarray.all()``, on strided windows of a mask too."""
    rng = np.random.default_rng(seed)
    mask = rng.random(shape) >= p_false
    for win in (mask, mask[::step, ::step], mask[1:, :-1], mask[:, ::-1]):
        assert _all_true(win) == bool(win.all())


@given(
    size=st.tuples(st.integers(2, 700), st.integers(2, 700)),
    m=st.sampled_from([3, 5, 17, 65]),
    skip=st.integers(0, 400),
)
@SETTINGS
def test_tasks_cut_the_stream_in_order(size: tuple[int, int], m: int, skip: int) -> None:
    """The builder's tasks: the codes in order, each task one level, at least _TASK_SAMPLES samples unless it
    ends its level's run, and never a tile more than needed to reach that."""
    pyr = TilePyramid(size[1], size[0], m)
    codes = pyr.all_codes(finest_first=True)[skip:]  # a resumed build's remaining tiles
    tasks = _tasks(pyr, codes)
    assert [c for t in tasks for c in t] == codes
    for i, t in enumerate(tasks):
        level = t[0][0]
        assert all(c[0] == level for c in t)
        per_tile = pyr.span(level) ** 2
        assert (len(t) - 1) * per_tile < _TASK_SAMPLES  # no tile beyond the one that reaches it
        last_of_run = i + 1 == len(tasks) or tasks[i + 1][0][0] != level
        assert last_of_run or len(t) * per_tile >= _TASK_SAMPLES


@given(
    seed=st.integers(0, 2**32 - 1),
    n=st.integers(1, 200),
    bits=st.integers(0, 10),
    step=st.sampled_from([1e-6, 0.01, 0.37, 5.0]),
    snap=st.booleans(),
)
@SETTINGS
def test_quantise_kernel_matches_the_builder(seed: int, n: int, bits: int, step: float, snap: bool) -> None:
    rng = np.random.default_rng(seed)
    span = min(64, (65535 >> bits) - 1)  # what a level's lattice holds
    r0, c0 = int(rng.integers(0, 5000)), int(rng.integers(0, 5000))
    rows = r0 + rng.uniform(0, span, n)
    cols = c0 + rng.uniform(0, span, n)
    if snap:  # on the sample lattice, as most meshers make them, with ties of the rounding
        rows, cols = np.round(rows), np.round(cols) + 0.5 / (1 << bits) * rng.integers(0, 2, n)
    hz = rng.uniform(-1.0, 1.0, n) * 30000.0 * step
    hz[rng.random(n) < 0.2] = step * (rng.integers(-50, 50) + 0.5)  # exact halves: round half to even
    quant = LevelQuantisation(bits, step)
    dx, dy = 30.0, 21.29
    qv, z0 = _quantise(rows, cols, hz, r0, c0, quant)
    kq, kz0, local, ok = quantise_tile(rows, cols, hz, r0, c0, bits, step, dx, dy)
    assert ok and int(kz0) == z0 and np.array_equal(kq, qv) and kq.dtype == np.uint16
    scale = 1.0 / (1 << bits)
    ref = np.empty((n, 3))
    ref[:, 0] = qv[:, 0] * scale * dx
    ref[:, 1] = qv[:, 1] * scale * dy
    ref[:, 2] = (z0 + qv[:, 2].astype(np.int64)) * step
    assert np.array_equal(local, ref)
    # out of the 16-bit lattice: flagged, as _quantise raises
    _, _, _, ok = quantise_tile(rows, cols + 70000.0, hz, r0, c0, bits, step, dx, dy)
    assert not ok


# -- the error kernel on unit lattice triangles --------------------------------------------------------


@st.composite
def lattice_meshes(draw):
    """A full-resolution grid (random diagonals, vertex heights off the samples by noise) whose cells are
    partly merged into larger triangles: unit lattice triangles next to general ones."""
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    h, w = draw(st.integers(2, 26)), draw(st.integers(2, 26))
    dx, dy = draw(st.sampled_from([1.0, 21.29, 160.0])), draw(st.sampled_from([1.0, 30.71, 160.0]))
    z = terrain(rng, h, w)
    valid = np.ones((h, w), bool) if draw(st.booleans()) else rng.random((h, w)) < 0.8
    noise = float(rng.choice([0.0, 0.3, 40.0]))
    rr, cc = np.mgrid[0:h, 0:w]
    zv = z.ravel().astype(np.float64) + rng.uniform(-noise, noise, h * w)
    verts = np.stack([cc.ravel() * dx, rr.ravel() * dy, zv], 1)
    idx = np.arange(h * w).reshape(h, w)
    tris = []
    merged = np.zeros((h - 1, w - 1), bool)
    for _ in range(int(rng.integers(0, 4))):  # 2 x 2 blocks of cells as 2 big triangles
        if h >= 3 and w >= 3:
            i, j = int(rng.integers(0, h - 2)), int(rng.integers(0, w - 2))
            if not merged[i : i + 2, j : j + 2].any():
                merged[i : i + 2, j : j + 2] = True
                a, b, c, d = idx[i, j], idx[i, j + 2], idx[i + 2, j], idx[i + 2, j + 2]
                tris += [[a, b, d], [a, d, c]]
    for i in range(h - 1):
        for j in range(w - 1):
            if merged[i, j]:
                continue
            a, b, c, d = idx[i, j], idx[i, j + 1], idx[i + 1, j], idx[i + 1, j + 1]
            tris += [[a, b, d], [a, d, c]] if rng.random() < 0.5 else [[a, b, c], [b, d, c]]
    return verts, np.asarray(tris, np.int64), z, valid, dx, dy


@given(case=lattice_meshes())
@SETTINGS
def test_unit_lattice_triangles_match_brute_force(case) -> None:
    verts, tris, z, valid, dx, dy = case
    rep = measure_error_window(verts, tris, z, valid, dx, dy)
    # the builder's call (its own float64 vertices, int32 triangles, no checks) measures the same, bit for bit
    unchecked = measure_error_window(
        verts, np.ascontiguousarray(tris, np.int32), z, valid, dx, dy, check=False
    )
    assert unchecked == rep
    vert, dist = reference(verts, tris, z, valid, dx, dy)
    cov = np.isfinite(vert)
    assert rep.n_samples == int(cov.sum())
    if rep.n_samples == 0:
        return
    tol = 1e-9 * max(1.0, float(np.abs(z).max()))
    # the maximum is exactly the brute-force one (a vertex sample's error is |z - vertex height| both ways
    # when no larger triangle attains it)
    assert rep.max_vertical_m == pytest.approx(vert[cov].max(), rel=1e-9, abs=tol)
    assert rep.rms_vertical_m == pytest.approx(math.sqrt(np.mean(vert[cov] ** 2)), rel=1e-9, abs=tol)
    assert rep.hausdorff_m == pytest.approx(np.nanmax(dist), rel=1e-9, abs=tol)
    # an all-unit grid: every covered sample is a vertex, the errors are exact
    if len(tris) == 2 * (z.shape[0] - 1) * (z.shape[1] - 1):
        assert rep.max_vertical_m == vert[cov].max()


# -- the adaptive mesher's order -----------------------------------------------------------------------


@given(seed=st.integers(0, 2**32 - 1), size=st.sampled_from([(65, 65), (40, 70), (129, 129)]))
@settings(max_examples=15, deadline=None)
def test_raster_order_kernel_matches_lexsort(seed: int, size: tuple[int, int]) -> None:
    rng = np.random.default_rng(seed)
    z = terrain(rng, *size)
    valid = np.ones(size, bool)
    pyr = TilePyramid(size[1], size[0], 33)
    for code in pyr.all_codes()[:6]:
        got = adaptive.mesh_tile(z, valid, pyr, code)
        old = adaptive._KERNEL_ORDER_MAX_VERTICES
        adaptive._KERNEL_ORDER_MAX_VERTICES = 0
        try:
            want = adaptive.mesh_tile(z, valid, pyr, code)
        finally:
            adaptive._KERNEL_ORDER_MAX_VERTICES = old
        for a, b in zip(got, want, strict=True):
            assert a.dtype == b.dtype and np.array_equal(a, b)


# -- the build stream ----------------------------------------------------------------------------------


def _rows(path: Path) -> list[tuple]:
    con = sqlite3.connect(path)
    try:
        return con.execute("SELECT * FROM tiles ORDER BY level, x, y").fetchall()
    finally:
        con.close()


def _brute_measure(hf: Heightfield, store, code) -> tuple[float, float]:
    """Hausdorff and max vertical error of a stored tile, re-measured by the brute-force reference."""
    t = store.tile(*code)
    if len(t.triangles) == 0:
        return 0.0, 0.0
    pyr = store.pyramid
    r0, c0 = pyr.origin_rc(code)
    span = pyr.span(code[0])
    r1, c1 = min(r0 + span, hf.height - 1), min(c0 + span, hf.width - 1)
    rc = t.grid_rc - np.array([r0, c0])
    dx, dy = hf.spacing_m
    local = np.stack([rc[:, 1] * dx, rc[:, 0] * dy, t.vertices[:, 2]], 1)
    vert, dist = reference(local, t.triangles, hf.elevation_m[r0 : r1 + 1, c0 : c1 + 1],
                           hf.valid[r0 : r1 + 1, c0 : c1 + 1], dx, dy)  # fmt: skip
    cov = np.isfinite(vert)
    return (float(np.nanmax(dist)), float(vert[cov].max())) if cov.any() else (0.0, 0.0)


@pytest.mark.parametrize("method", ["chunked", "cohesion", "adaptive"])
@given(seed=st.integers(0, 2**32 - 1), nodata=st.booleans())
@settings(max_examples=3, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
def test_streamed_build_equals_tile_by_tile(tmp_path: Path, method: str, seed: int, nodata: bool) -> None:
    rng = np.random.default_rng(seed)
    h, w = int(rng.integers(30, 56)), int(rng.integers(30, 56))
    z = terrain(rng, h, w)
    if nodata:
        z[int(rng.integers(0, h - 10)) :][:10, int(rng.integers(0, w - 10)) :][:, :12] = np.nan
    hf = Heightfield.from_array(z, 30.0)
    d = Path(tempfile.mkdtemp(dir=tmp_path))  # one folder per example (tmp_path is the test's)
    a, b, c = d / "a.terra", d / "b.terra", d / "c.terra"
    build_store(hf, a, tile_size=17, method=method, workers=1, overwrite=True)
    build_store(hf, b, tile_size=17, method=method, workers=3, overwrite=True)
    build_store(hf, c, tile_size=17, method=method, workers=2, stop_after=7, overwrite=True)
    build_store(hf, c, tile_size=17, method=method, workers=2, resume=True)
    rows = _rows(a)
    assert rows == _rows(b) == _rows(c)
    # the reference: tile by tile, finest first, each with its children's stored errors
    pyr = TilePyramid(hf.width, hf.height, 17)
    quant = plan_quantisation(hf, pyr, grid_vertices=(method == "chunked"))
    errors: dict = {}
    ref = {}
    for code in pyr.all_codes(finest_first=True):
        enc = build_tile(
            hf, pyr, code, quant[code[0]], METHODS[method], [errors[k] for k in pyr.children(code)]
        )
        errors[code] = (enc.error_m, enc.vertical_error_m)
        ref[code] = enc
    with open_store(a) as s:
        for r in rows:
            code = (r[0], r[1], r[2])
            e = ref[code]
            assert r[3:14] == (e.error_m, e.vertical_error_m, e.measured_error_m, e.measured_vertical_error_m,
                               e.rms_error_m, e.n_samples, e.z_min_m, e.z_max_m, e.n_vertices, e.n_triangles,
                               e.z0_index)  # fmt: skip
            assert (bytes(r[14]), bytes(r[15])) == (e.vertices, e.triangles)
            # every stored measured error is the exact maximum over the tile's samples, as stored
            hd, vmax = _brute_measure(hf, s, code)
            tol = 1e-9 * max(1.0, float(np.nanmax(np.abs(z))))
            assert e.measured_error_m == pytest.approx(hd, rel=1e-9, abs=tol)
            assert e.measured_vertical_error_m == pytest.approx(vmax, rel=1e-9, abs=tol)
            kids = [errors[k] for k in pyr.children(code)]
            assert e.error_m == max([e.measured_error_m] + [k[0] for k in kids])
