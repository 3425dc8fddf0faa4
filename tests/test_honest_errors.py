"""Stored errors of a store built from a reprojected DEM hold against the samples the user gave.

A geographic (EPSG:4326) or Web Mercator (EPSG:3857) DEM is reprojected once to UTM before meshing; every
stored error must still bound the distance from the tile surface to every *original* sample. The check
here is independent of the builder: the original samples are read with rasterio, placed in the store's
CRS with pyproj, and compared with the height of the mesh (``terralod.open(...).lod_mesh``) of the tile
that holds them, at every level, by barycentric interpolation written here.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

import terralod
from terralod.io.reader import read_heightfield
from terralod.kernels.scattered import scattered_vertical_error
from terralod.pyramid import builder, original
from terralod.pyramid.builder import build_store, store_summary
from terralod.store import open_store

rasterio = pytest.importorskip("rasterio")
pyproj = pytest.importorskip("pyproj")

SRTM = Path("/work/shared/data/dem/srtm3_N42E001.tif")
TOL_M = 1e-3


# -- inputs ----------------------------------------------------------------------------------------------
def _write(path: Path, z: np.ndarray, transform, crs: str, nodata: float | None = None) -> Path:
    with rasterio.open(
        path, "w", driver="GTiff", width=z.shape[1], height=z.shape[0], count=1, dtype=z.dtype,
        crs=crs, transform=transform, nodata=nodata,
    ) as ds:  # fmt: skip
        ds.write(z, 1)
    return path


def _sharp_relief(n: int, seed: int) -> np.ndarray:
    """Cliffs, a ridge and needles: relief that bilinear resampling moves by tens of metres."""
    rng = np.random.default_rng(seed)
    r, c = np.mgrid[0:n, 0:n].astype(np.float64)
    z = 800.0 + 300.0 * np.sin(r / 7.0) * np.cos(c / 5.0)
    z += np.where(c > 0.6 * n + 5.0 * np.sin(r / 4.0), 250.0, 0.0)  # a wavy cliff
    z += 400.0 * np.exp(-(((r - n / 3) / 1.5) ** 2))  # a knife-edge ridge
    spikes = rng.integers(0, n, (40, 2))
    z[spikes[:, 0], spikes[:, 1]] += rng.uniform(100.0, 600.0, 40)
    return z.astype(np.float32)


def geographic_dem(path: Path) -> Path:
    """150 x 150 samples of 3 arc-seconds near 45 N 7 E (EPSG:4326), sharp relief, a few nodata."""
    from affine import Affine

    z = _sharp_relief(150, 1)
    z[70:74, 20:25] = -9999.0
    d = 3.0 / 3600.0
    return _write(path, z, Affine(d, 0.0, 7.0, 0.0, -d, 45.2), "EPSG:4326", nodata=-9999.0)


def mercator_dem(path: Path) -> Path:
    """140 x 140 samples of 100 Web Mercator metres (about 70 ground metres at 46 N), sharp relief."""
    from affine import Affine

    x0, y0 = pyproj.Transformer.from_crs("EPSG:4326", "EPSG:3857", always_xy=True).transform(8.0, 46.0)
    return _write(path, _sharp_relief(140, 2), Affine(100.0, 0.0, x0, 0.0, -100.0, y0), "EPSG:3857")


def utm_dem(path: Path) -> Path:
    """120 x 120 samples of 30 m in UTM 32N (no reprojection)."""
    from affine import Affine

    return _write(
        path, _sharp_relief(120, 3), Affine(30.0, 0.0, 400000.0, 0.0, -30.0, 5000000.0), "EPSG:32632"
    )


def srtm_crop(path: Path) -> Path:
    """200 x 200 samples of SRTM3 N42E001 (Pyrenees, rugged) written as a GeoTIFF of their own."""
    if not SRTM.exists():
        pytest.skip(f"{SRTM} is absent (the shared real-data folder is not mounted)")
    from affine import Affine
    from rasterio.windows import Window

    with rasterio.open(SRTM) as ds:
        z = ds.read(1, window=Window(450, 300, 200, 200))
        return _write(
            path, z, ds.transform @ Affine.translation(450, 300), ds.crs.to_string(), nodata=ds.nodata
        )


# -- the independent check -------------------------------------------------------------------------------
def _mesh_heights(verts: np.ndarray, tris: np.ndarray, px: np.ndarray, py: np.ndarray) -> np.ndarray:
    """Height of the mesh at each (px, py), NaN where no triangle covers it (edges included).

    Every (triangle, point) pair whose point lies in the triangle's bounding box (1e-6 m margin) is tested
    with barycentric coordinates, in numpy batches of pairs (a later triangle wins a shared edge)."""
    out = np.full(px.size, np.nan)
    order = np.argsort(px, kind="stable")
    xs = px[order]
    a, b, c = verts[tris[:, 0]], verts[tris[:, 1]], verts[tris[:, 2]]
    x_lo = np.minimum(np.minimum(a[:, 0], b[:, 0]), c[:, 0]) - 1e-6
    x_hi = np.maximum(np.maximum(a[:, 0], b[:, 0]), c[:, 0]) + 1e-6
    y_lo = np.minimum(np.minimum(a[:, 1], b[:, 1]), c[:, 1]) - 1e-6
    y_hi = np.maximum(np.maximum(a[:, 1], b[:, 1]), c[:, 1]) + 1e-6
    lo, hi = np.searchsorted(xs, x_lo), np.searchsorted(xs, x_hi)
    count = np.maximum(hi - lo, 0)
    ends = np.cumsum(count)
    t0 = 0
    while t0 < len(tris):  # batches of about 4 M pairs
        t1 = max(int(np.searchsorted(ends, ends[t0 - 1] + 4_000_000 if t0 else 4_000_000)), t0 + 1)
        t1 = min(t1, len(tris))
        k = np.repeat(np.arange(t0, t1), count[t0:t1])
        first = np.repeat(ends[t0:t1] - count[t0:t1], count[t0:t1])
        idx = order[lo[k] + np.arange(k.size) - (first - (ends[t0 - 1] if t0 else 0))]
        keep = (py[idx] >= y_lo[k]) & (py[idx] <= y_hi[k])
        k, idx = k[keep], idx[keep]
        ak, bk, ck = a[k], b[k], c[k]
        det = (bk[:, 1] - ck[:, 1]) * (ak[:, 0] - ck[:, 0]) + (ck[:, 0] - bk[:, 0]) * (ak[:, 1] - ck[:, 1])
        x, y = px[idx], py[idx]
        with np.errstate(divide="ignore", invalid="ignore"):
            la = ((bk[:, 1] - ck[:, 1]) * (x - ck[:, 0]) + (ck[:, 0] - bk[:, 0]) * (y - ck[:, 1])) / det
            lb = ((ck[:, 1] - ak[:, 1]) * (x - ck[:, 0]) + (ak[:, 0] - ck[:, 0]) * (y - ck[:, 1])) / det
        lc = 1.0 - la - lb
        inside = (det != 0.0) & (la >= -1e-12) & (lb >= -1e-12) & (lc >= -1e-12)
        out[idx[inside]] = (la * ak[:, 2] + lb * bk[:, 2] + lc * ck[:, 2])[inside]
        t0 = t1
    return out


def check_against_original(src: Path, store_path: Path) -> dict[int, tuple[int, float]]:
    """For every original valid sample and every level: |mesh - sample| <= the tile's stored errors.

    Returns {level: (samples checked, largest gap found)}."""
    with rasterio.open(src) as ds:
        z = ds.read(1, masked=True)
        t, crs = ds.transform, ds.crs
    ok = ~np.ma.getmaskarray(z)
    rows, cols = np.nonzero(ok)
    lon, lat = rasterio.transform.xy(t, rows, cols, offset="center")
    zs = np.ma.getdata(z)[ok].astype(np.float64)
    with terralod.open(store_path) as terrain:
        store = terrain.store
        tr = pyproj.Transformer.from_crs(pyproj.CRS.from_wkt(crs.to_wkt()), pyproj.CRS.from_wkt(store.crs).to_2d(),
                                         always_xy=True)  # fmt: skip
        x, y = tr.transform(np.asarray(lon, np.float64), np.asarray(lat, np.float64))
        st = store.transform
        col = (x - (st.c + 0.5 * st.a)) / st.a
        row = (y - (st.f + 0.5 * st.e)) / st.e
        w, h = int(store.meta["width"]), int(store.meta["height"])
        inside = (row >= 0) & (col >= 0) & (row <= h - 1) & (col <= w - 1)
        nodes = {n.code: n for n in terrain.lod_tree()}
        out: dict[int, tuple[int, float]] = {}
        for level in store.levels:
            span = store.pyramid.span(level)
            tx = np.minimum(np.floor(col / span), math.ceil((w - 1) / span) - 1).astype(np.int64)
            ty = np.minimum(np.floor(row / span), math.ceil((h - 1) / span) - 1).astype(np.int64)
            key = np.where(inside, ty * 1_000_003 + tx, -1)
            checked, worst = 0, 0.0
            for k in np.unique(key[key >= 0]):
                code = (level, int(k % 1_000_003), int(k // 1_000_003))
                if code not in nodes:
                    continue
                idx = np.nonzero(key == k)[0]
                verts, tris = terrain.lod_mesh(code)
                hz = _mesh_heights(verts, np.asarray(tris, np.int64), x[idx], y[idx])
                cov = ~np.isnan(hz)
                if not cov.any():
                    continue
                gap = np.abs(hz[cov] - zs[idx][cov])
                node = nodes[code]
                assert gap.max() <= node.error_m + TOL_M, (code, float(gap.max()), node.error_m)
                assert gap.max() <= node.vertical_error_m + TOL_M, (
                    code,
                    float(gap.max()),
                    node.vertical_error_m,
                )
                checked += int(cov.sum())
                worst = max(worst, float(gap.max()))
            out[level] = (checked, worst)
    return out


def _assert_monotone(store_path: Path) -> None:
    with open_store(store_path) as s:
        errs = s.tile_errors()
        for code, (e, v) in errs.items():
            for ch in s.pyramid.children(code):
                if ch in errs:
                    assert e >= errs[ch][0] and v >= errs[ch][1], (code, ch)


def _build(src: Path, tmp_path: Path) -> Path:
    out = tmp_path / (src.stem + ".terra")
    build_store(read_heightfield(src), out, workers=2)
    return out


# -- (a) geographic, (b) Web Mercator --------------------------------------------------------------------
@pytest.mark.parametrize(
    "make", [geographic_dem, mercator_dem, srtm_crop], ids=["geographic", "mercator", "srtm3"]
)
def test_every_original_sample_within_the_stored_error(tmp_path: Path, make) -> None:
    src = make(tmp_path / "dem.tif")
    hf = read_heightfield(src)
    assert hf.original_grid is not None  # reprojected: the original samples are kept
    store_path = _build(src, tmp_path)
    res = check_against_original(src, store_path)
    n_valid = int(hf.original_grid.n_valid)
    with open_store(store_path) as s:
        finest = s.pyramid.max_level
        assert s.meta["errors_measured_against"]["samples"] == "original"
        assert s.meta["errors_measured_against"]["valid_samples"] == n_valid
        summary = store_summary(s)
    # nearly every sample is checked at every level (those beyond the grid's last sample excepted), and
    # resampling moved some by metres: the finest level, meshed on the resampled grid, is not lossless
    for level, (checked, _) in res.items():
        assert checked >= 0.97 * n_valid, (level, checked, n_valid)
    assert res[finest][1] > 1.0
    assert summary["per_level"][finest]["max_error_m"] >= res[finest][1] - TOL_M
    assert "original samples" in summary["errors_against"]
    _assert_monotone(store_path)


def test_the_grid_alone_understated(tmp_path: Path) -> None:
    """The same build measured on the resampled grid only (as before) fails the independent check: the
    check can fail."""
    import dataclasses

    src = geographic_dem(tmp_path / "dem.tif")
    hf = dataclasses.replace(read_heightfield(src), original_grid=None)
    out = tmp_path / "grid_only.terra"
    build_store(hf, out, workers=2)
    with pytest.raises(AssertionError):
        check_against_original(src, out)


# -- (c) a projected input: nothing moves, nothing changes ----------------------------------------------
def test_projected_input_takes_no_new_path(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    src = utm_dem(tmp_path / "utm.tif")
    hf = read_heightfield(src)
    assert hf.original_grid is None

    def refuse(*_a, **_k):
        raise AssertionError("a projected input is measured on its own grid only")

    monkeypatch.setattr(builder, "tile_samples", refuse)
    monkeypatch.setattr(builder, "original_error", refuse)
    out = tmp_path / "utm.terra"
    build_store(hf, out, workers=2)
    with open_store(out) as s:
        assert "errors_measured_against" not in s.meta
        assert "own samples" in store_summary(s)["errors_against"]
        finest = s.tile_errors()
        assert max(e for (k, _, _), (e, _) in finest.items() if k == s.pyramid.max_level) < 0.05


# -- the kernel ------------------------------------------------------------------------------------------
def test_scattered_kernel_plane_and_holes() -> None:
    """Two triangles of the plane z = x over [0, 10]²: points on it (edges and corners included) gap 0
    off by their z offset; points outside are counted uncovered."""
    verts = np.array([[0, 0, 0], [10, 0, 10], [0, 10, 0], [10, 10, 10]], np.float64)
    tris = np.array([[0, 1, 2], [1, 3, 2]], np.int64)
    rng = np.random.default_rng(0)
    p = rng.uniform(-2.0, 12.0, (2000, 2))
    p[:4] = [[0, 0], [10, 10], [5, 5], [10, 0]]  # corners and a point on the shared diagonal
    off = rng.uniform(-3.0, 3.0, 2000)
    pz = p[:, 0] + off
    err, sumsq, n, missed = scattered_vertical_error(verts, tris, p[:, 0].copy(), p[:, 1].copy(), pz)
    inside = ((p >= 0) & (p <= 10)).all(axis=1)
    assert n == inside.sum() and missed == (~inside).sum()
    assert err == pytest.approx(np.abs(off[inside]).max(), abs=1e-9)
    assert sumsq == pytest.approx((off[inside] ** 2).sum(), rel=1e-9)


def test_tile_samples_cover_the_footprint_once(tmp_path: Path) -> None:
    """Every original sample inside the grid's extent falls in the footprint of the tiles of a level that
    hold it (edges shared), and its local coordinates put it back where pyproj places it."""
    src = geographic_dem(tmp_path / "dem.tif")
    hf = read_heightfield(src)
    g = hf.original_grid
    span = 32
    seen = 0
    for r0 in range(0, hf.height - 1, span):
        for c0 in range(0, hf.width - 1, span):
            r1, c1 = min(r0 + span, hf.height - 1), min(c0 + span, hf.width - 1)
            x, y, z = original.tile_samples(g, hf.crs, hf.origin_m, hf.spacing_m, (r0, c0), (r1, c1))
            assert (x >= 0).all() and (y >= 0).all()
            assert (x <= (c1 - c0) * hf.spacing_m[0] + 1e-6).all() and (
                y <= (r1 - r0) * hf.spacing_m[1] + 1e-6
            ).all()
            seen += x.size
    assert seen >= 0.97 * g.n_valid
