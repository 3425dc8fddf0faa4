"""The web globe: 3D Tiles and quantized-mesh exports, ``terralod serve``, and both in a real browser.

Python tests decode what the exporters wrote (glb through pygltflib, quantized-mesh through the decoder)
and compare with the store and the source DEM; the server tests bind a loopback port. The browser test runs
Debian's headless Chromium (software WebGL) with CesiumJS through puppeteer-core (tests/test_interop.py, tests/test_site.py)
and the Khronos glTF validator through node; it skips with the reason when chromium or node_modules are
missing. Real data: ../shared/data/dem/srtm1_crop256_alpine.tif (skipped when absent).
"""

from __future__ import annotations

import gzip
import json
import re
import shutil
import subprocess
import threading
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from terralod.cli import main
from terralod.export.quantized_mesh import decode_tile, encode_tile, oct_decode, oct_encode, tile_rectangle
from terralod.export.tiles3d import Tiles3D, export_3dtiles, node_uri
from test_tiles_bytes import decode_glb

from conftest import read_tileset

REPO = Path(__file__).resolve().parents[1]
NODE_MODULES = REPO / "node_modules"
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
ALPINE = "dem/srtm1_crop256_alpine.tif"


def _browser_missing() -> str | None:
    if CHROMIUM is None:
        return "Debian chromium not installed (bash scripts/install.sh installs it)"
    if shutil.which("node") is None:
        return "node not installed"
    for pkg in ("cesium", "puppeteer-core", "gltf-validator"):
        if not (NODE_MODULES / pkg).is_dir():
            return f"node_modules/{pkg} missing (run `npm ci` in the repository)"
    return None


@pytest.fixture(scope="module")
def alpine_store(shared_data: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    from terralod.io.reader import read_heightfield
    from terralod.pyramid.builder import build_store

    p = tmp_path_factory.mktemp("web") / "alpine.terra"
    build_store(read_heightfield(shared_data / ALPINE), p, workers=2)
    return p


@pytest.fixture(scope="module")
def sample_store(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from terralod.io.reader import sample_heightfield
    from terralod.pyramid.builder import build_store

    p = tmp_path_factory.mktemp("web") / "sample.terra"
    build_store(sample_heightfield(), p, workers=2)
    return p


# -- quantized-mesh binary ----------------------------------------------------------------------------
@settings(max_examples=15, deadline=None)
@given(st.integers(3, 300), st.integers(0, 2**31 - 1))
def test_quantized_mesh_round_trip(n: int, seed: int) -> None:
    """encode_tile → decode_tile gives back u/v/h on the 15-bit lattice, the triangles (as sets, in the
    encoder's vertex order), the edge lists, normals to oct precision and the metadata."""
    rng = np.random.default_rng(seed)
    rect = tile_rectangle(12, 1325, 3114)
    w, s, e, nn = rect
    lon = np.concatenate([[w, e, e, w], w + (e - w) * rng.random(n)])
    lat = np.concatenate([[s, s, nn, nn], s + (nn - s) * rng.random(n)])
    h = rng.uniform(-50, 4000, lon.size)
    from scipy.spatial import Delaunay

    tris = Delaunay(np.column_stack([lon, lat])).simplices
    nrm = rng.normal(size=(lon.size, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    raw = encode_tile(
        lon, lat, h, tris, rect, normals=nrm, watermask=0, metadata={"terralod": {"error_m": 1.5}}
    )
    d = decode_tile(gzip.compress(raw), rect)
    assert len(d["u"]) == lon.size and len(d["triangles"]) == len(tris)
    step_h = (h.max() - h.min()) / 32767
    # map decoded vertices back to the input by position
    key_in = {(round(a, 9), round(b, 9)): i for i, (a, b) in enumerate(zip(lon, lat, strict=True))}
    order = []
    for a, b in zip(d["lon"], d["lat"], strict=True):
        j = min(key_in, key=lambda k: (k[0] - a) ** 2 + (k[1] - b) ** 2)
        order.append(key_in[j])
    order = np.array(order)
    assert np.allclose(d["lon"], lon[order], atol=(e - w) / 32767)
    assert np.allclose(d["lat"], lat[order], atol=(nn - s) / 32767)
    assert np.allclose(d["height"], h[order], atol=0.51 * step_h + 1e-6)
    got = {tuple(sorted(order[t])) for t in d["triangles"]}
    assert got == {tuple(sorted(t)) for t in tris}
    assert set(d["west"]) == set(np.flatnonzero(d["u"] == 0))
    assert set(d["north"]) == set(np.flatnonzero(d["v"] == 32767))
    assert np.max(np.abs(d["normals"] - nrm[order])) < 0.02
    assert d["metadata"]["terralod"]["error_m"] == 1.5 and d["watermask"] == 0


def test_oct_encoding_of_axes() -> None:
    axes = np.array([[0, 0, 1], [0, 0, -1], [1, 0, 0], [0, -1, 0]], float)
    assert np.allclose(oct_decode(oct_encode(axes)), axes, atol=0.01)


# -- 3D Tiles export ----------------------------------------------------------------------------------
def _decode_glb(data: bytes) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(positions, normals, triangles) of a glb, dequantised from its JSON alone (tests/test_tiles_bytes.py)."""
    pos, nrm, tri, _ = decode_glb(data)
    return pos, nrm, tri


def test_3dtiles_export_round_trip(sample_store: Path, tmp_path: Path) -> None:
    """tileset.json carries the stored errors plus the quantisation's bound, REPLACE and composed transforms;
    each glb's positions (dequantised, through the transforms and pyproj) are the stored vertices within that
    bound; skirts hang by the measured errors and the bounds."""
    from pyproj import Transformer

    from terralod.terrain import open_terrain

    out = tmp_path / "t3"
    with open_terrain(sample_store) as t:
        rep = export_3dtiles(t, out)
        tree = {n.code: n for n in t.lod_tree()}
        ts = read_tileset(out)
        assert ts["asset"]["version"] == "1.1" and ts["root"]["refine"] == "REPLACE"
        root = ts["root"]
        view = Tiles3D(t)
        assert ts["geometricError"] > root["geometricError"]
        assert root["geometricError"] == tree[(0, 0, 0)].error_m + view.quant_error_m((0, 0, 0))
        to_crs = Transformer.from_crs("EPSG:4978", "EPSG:4979", always_xy=True)
        back = Transformer.from_crs("EPSG:4326", t.crs, always_xy=True)
        checked = 0

        def walk(tile: dict, above: np.ndarray) -> None:
            nonlocal checked
            m = np.array(tile["transform"]).reshape(4, 4).T
            c = above + m[:3, 3]
            for k in tile.get("children", []):
                walk(k, c)
            code = tuple(int(a) for a in tile["content"]["uri"][6:-4].replace("/", "_").split("_"))
            bound = view.quant_error_m(code)
            assert tile["geometricError"] == pytest.approx(tree[code].error_m + bound, abs=1e-12)
            assert 0.0 < bound < 0.05 * max(tile["geometricError"], 1.0)  # a small part of the error
            kids = tile.get("children", [])
            assert all(k["geometricError"] <= tile["geometricError"] for k in kids)
            if checked >= 6:
                return
            pos, nrm, tri = _decode_glb((out / tile["content"]["uri"]).read_bytes())
            ecef = np.column_stack([pos[:, 0], -pos[:, 2], pos[:, 1]]).astype(np.float64) + c
            lon, lat, hgt = to_crs.transform(ecef[:, 0], ecef[:, 1], ecef[:, 2])
            x, y = back.transform(lon, lat)
            v, vt = t.lod_mesh(code)
            v = v[np.unique(vt)]
            n = len(v)
            # each stored vertex is a decoded one (within the bound), the others are skirts below them
            d = np.abs(x[:, None] - v[None, :, 0]) + np.abs(y[:, None] - v[None, :, 1])
            near = np.argmin(d, axis=1)
            top = np.abs(hgt - v[near, 2]) <= bound
            assert (
                top.sum() == n and set(near[top]) == set(range(n)) and d[top].min(axis=1).max() <= 2 * bound
            )
            skirt = v[near[~top], 2] - hgt[~top]
            view_depth = Tiles3D.skirt_m(view, code)
            assert np.allclose(skirt, view_depth, atol=2 * bound)
            parent = tree[code].parent or code
            assert view_depth <= (tree[code].vertical_error_m + tree[parent].vertical_error_m + bound
                                  + view.quant_error_m(parent) + 0.02)  # fmt: skip
            assert np.allclose(np.linalg.norm(nrm, axis=1), 1.0, atol=0.02)  # int8 normals
            assert tri.max() < len(pos)
            checked += 1

        walk(root, np.zeros(3))
        assert checked >= 6 and rep.tiles == len(tree)
    if shutil.which("node") and (NODE_MODULES / "gltf-validator").is_dir():  # Khronos: 0 errors, 0 warnings
        val = subprocess.run(["node", str(REPO / "tests" / "web" / "validate_glb.mjs"), str(out)], capture_output=True,
                             text=True, timeout=60, cwd=REPO)  # fmt: skip
        res = json.loads(val.stdout.strip().splitlines()[-1])
        assert res["files"] == rep.tiles and res["errors"] == 0 and res["warnings"] == 0, res


def test_3dtiles_normals_match_across_borders(sample_store: Path) -> None:
    """Same-level neighbours have the same normal at every shared border vertex (merged-mesh normals)."""
    from terralod.terrain import open_terrain

    with open_terrain(sample_store) as t:
        view = Tiles3D(t)
        level = max(c[0] for c in view.nodes)
        a, b = (level, 1, 1), (level, 2, 1)
        va, _, na = view.mesh(a)
        vb, _, nb = view.mesh(b)
        ka = {(round(x, 3), round(y, 3)): i for i, (x, y) in enumerate(va[:, :2])}
        pairs = [
            (ka[(round(x, 3), round(y, 3))], j)
            for j, (x, y) in enumerate(vb[:, :2])
            if (round(x, 3), round(y, 3)) in ka
        ]
        assert len(pairs) >= 10
        i, j = np.array(pairs).T
        assert np.allclose(na[i], nb[j], atol=1e-5)


def test_tin_store_exports(shared_data: Path, tmp_path: Path) -> None:
    """A detail-increment TIN store exports too: one root above the sub-blocks, ladders whose errors fall."""
    from terralod.heightfield import Heightfield
    from terralod.io.reader import read_heightfield
    from terralod.tin import DetailIncrementModel
    from terralod.tin.terra import save_model_to_store

    hf = read_heightfield(shared_data / "dem/srtm1_crop256_coastal_flat_nodata.tif")
    crop = Heightfield(hf.elevation_m[:96, :96].copy(), hf.valid[:96, :96].copy(), hf.transform, hf.crs)
    store = tmp_path / "tin.terra"
    save_model_to_store(DetailIncrementModel.from_heightfield(crop, sub_blocks=4), store)
    from terralod.terrain import open_terrain

    with open_terrain(store) as t:
        view = Tiles3D(t)
        ts = view.tileset()
        assert len(ts["root"]["children"]) == 4 and "content" not in ts["root"]
        chain = ts["root"]["children"][0]
        errs = []  # the declared errors less the encoding's bound: the measured ones, halving rung by rung
        code_of = {node_uri(c): c for c in view.nodes}
        while True:
            errs.append(chain["geometricError"] - view.quant_error_m(code_of[chain["content"]["uri"]]))
            if not chain.get("children"):
                break
            chain = chain["children"][0]
        assert len(errs) >= 2 and all(
            b <= 0.5 * a + 1e-9 or b == 0 for a, b in zip(errs, errs[1:], strict=False)
        )
        glb = view.glb(view.tree[-1].code)
        pos, _, tri = _decode_glb(glb)
        assert len(tri) and len(pos) < 200_000


# -- quantized-mesh export ----------------------------------------------------------------------------
def test_quantized_mesh_export_against_source(alpine_store: Path, shared_data: Path, tmp_path: Path) -> None:
    """layer.json's availability matches the files; finest tiles decode to heights within their measured
    error of the source samples; the gzip'd greedy-insertion tile is smaller than the 65² regular grid at
    a larger measured error."""
    from terralod.export.quantized_mesh import QuantizedMesh, export_quantized_mesh, true_error_m
    from terralod.terrain import open_terrain

    out = tmp_path / "qm"
    with open_terrain(alpine_store) as t:
        export_quantized_mesh(t, out)
        layer = json.loads((out / "layer.json").read_text())
        assert layer["format"] == "quantized-mesh-1.0" and layer["scheme"] == "tms"
        files = {
            tuple(int(a) for a in f.relative_to(out).with_suffix("").parts) for f in out.rglob("*.terrain")
        }
        listed = set()
        for z, ranges in enumerate(layer["available"]):
            for r in ranges:
                listed |= {
                    (z, x, y)
                    for x in range(r["startX"], r["endX"] + 1)
                    for y in range(r["startY"], r["endY"] + 1)
                }
        assert files == listed and {(0, 0, 0), (0, 1, 0)} <= files
        z = layer["maxzoom"]
        qm = QuantizedMesh(t)
        declared = json.loads((out / "errors.json").read_text())["tiles"]
        for zz, x, y in sorted(f for f in files if f[0] == z)[:2]:
            rect = tile_rectangle(zz, x, y)
            raw = (out / str(zz) / str(x) / f"{y}.terrain").read_bytes()
            assert raw[:2] != b"\x1f\x8b" and "metadata" not in decode_tile(raw)  # plain, no metadata block
            d = decode_tile(raw, rect)
            err = declared[f"{zz}/{x}/{y}"]
            assert err == pytest.approx(true_error_m(d, rect, *qm.ref.points_in(zz, x, y)), abs=2e-4)
            assert err <= layer["terralod"]["error_m"][z]
        # at equal measured error, fewer bytes than the regular 65² grid (an interior tile of the finest level)
        inner = sorted(f for f in files if f[0] == z)
        zz, x, y = inner[len(inner) // 2]
        grid = qm.tile(zz, x, y, regular=65)
        greedy = qm.tile(
            zz, x, y, target_m=0.5 * grid.error_m
        )  # the lattice's target; measured on the source
        assert greedy.error_m <= grid.error_m and len(greedy.data) < len(grid.data)


# -- errors of the CLI --------------------------------------------------------------------------------
def test_export_cli_refusals(
    sample_store: Path, shared_data: Path, tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    busy = tmp_path / "busy"
    busy.mkdir()
    (busy / "keep.txt").write_text("mine")
    with pytest.raises(SystemExit) as exc:
        main(["export", str(sample_store), "--format", "3dtiles", "-o", str(busy)])
    assert exc.value.code == 2 and "--overwrite" in capsys.readouterr().err
    assert (busy / "keep.txt").read_text() == "mine" and not list(tmp_path.glob(".busy.tmp-*"))

    from affine import Affine

    from terralod.io.reader import read_heightfield  # a store whose build was interrupted
    from terralod.pyramid.builder import build_store as _build

    part = tmp_path / "part.terra"
    _build(read_heightfield(shared_data / ALPINE), part, workers=1, stop_after=3)
    with pytest.raises(SystemExit) as exc:
        main(["export", str(part), "--format", "quantized-mesh", "-o", str(tmp_path / "part-out")])
    err = capsys.readouterr().err.strip()
    assert exc.value.code == 2 and "incomplete" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "part-out").exists()

    from terralod.heightfield import Heightfield  # a store without a CRS
    from terralod.pyramid.builder import build_store

    z = np.random.default_rng(1).random((40, 40)).astype(np.float32) * 10
    local = tmp_path / "local.terra"
    build_store(Heightfield(z, np.ones(z.shape, bool), Affine(10, 0, 0, 0, -10, 400)), local, workers=1)
    for fmt in ("3dtiles", "quantized-mesh"):
        with pytest.raises(SystemExit) as exc:
            main(["export", str(local), "--format", fmt, "-o", str(tmp_path / fmt)])
        err = capsys.readouterr().err.strip()
        assert exc.value.code == 2 and "CRS" in err and len(err.splitlines()) == 1
        assert not (tmp_path / fmt).exists()


# -- the server ---------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def server(alpine_store: Path):
    from terralod.serve import make_server
    from terralod.terrain import open_terrain

    t = open_terrain(alpine_store)
    srv, service = make_server(t, "127.0.0.1", 0)
    th = threading.Thread(target=srv.serve_forever, daemon=True)
    th.start()
    yield f"http://127.0.0.1:{srv.server_address[1]}", service
    srv.shutdown()
    srv.server_close()
    t.close()


def _get(url: str, headers: dict | None = None, method: str = "GET") -> tuple[int, dict, bytes]:
    req = urllib.request.Request(url, headers=headers or {}, method=method)
    try:
        with urllib.request.urlopen(req, timeout=30) as r:
            return r.status, dict(r.headers), r.read()
    except urllib.error.HTTPError as e:
        return e.code, dict(e.headers), e.read()


def test_server_binds_loopback_and_refuses_traversal(server) -> None:
    base, service = server
    assert base.startswith("http://127.0.0.1:")
    for bad in (
        "/cesium/../../../../etc/passwd",
        "/cesium/%2e%2e/%2e%2e/package.json",
        "/static/../server.py",
        "/static/server.py",
        "/../pyproject.toml",
        "/3dtiles/tiles/9/0_0.glb",
        "/terrain/0/5/0.terrain",
        "/terrain/3/0/0.terrain",
        "/3dtiles/tiles/0/0_0.glb/../../x",
        "/etc/passwd",
        "/terrain/..%2flayer.json",
    ):
        code, _, body = _get(base + bad)
        assert code == 404, bad
        assert b"root:" not in body
    code, hdr, _ = _get(base + "/3dtiles/tileset.json", method="POST")
    assert code == 405 and "GET" in hdr.get("Allow", "")


def test_server_tiles_cache_gzip_etag(server) -> None:
    base, service = server
    code, hdr, body = _get(base + "/terrain/layer.json", {"Accept-Encoding": "gzip"})
    layer = json.loads(gzip.decompress(body) if hdr.get("Content-Encoding") == "gzip" else body)
    z = layer["maxzoom"]
    r = layer["available"][z][0]
    url = f"{base}/terrain/{z}/{r['startX']}/{r['startY']}.terrain?v=1.0.0"
    code, hdr, body = _get(url, {"Accept-Encoding": "gzip"})
    assert code == 200 and hdr["Content-Encoding"] == "gzip" and body[:2] == b"\x1f\x8b"
    d = decode_tile(body)
    assert len(d["triangles"]) > 0
    before = service.stats["encoded"]
    code, hdr2, _ = _get(url, {"If-None-Match": hdr["ETag"]})
    assert code == 304 and service.stats["encoded"] == before
    code, hdr, body = _get(base + "/3dtiles/tiles/0/0_0.glb")
    assert code == 200 and body[:4] == b"glTF" and "Content-Encoding" not in hdr


def _top_sum(tile: dict) -> float:
    """Sum of the region tops of a tileset subtree (grows where any tile's terrain rose)."""
    return tile["boundingVolume"]["region"][5] + sum(_top_sum(k) for k in tile.get("children", []))


def test_epochs_export_and_serve(shared_data: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """A store with two epochs: --epoch exports that epoch's heights, an unknown epoch is one line + exit 2;
    the server serves /e/EPOCH/... per epoch (404 for another name) and the site's pair of the two epochs."""
    from terralod.heightfield import Heightfield
    from terralod.io.reader import read_heightfield
    from terralod.pyramid.builder import build_store
    from terralod.pyramid.update import update_store
    from terralod.serve import TileService
    from terralod.site.tiles import read_level
    from terralod.terrain import open_terrain

    hf = read_heightfield(shared_data / ALPINE)
    a = Heightfield(hf.elevation_m[:80, :80].copy(), hf.valid[:80, :80].copy(), hf.transform, hf.crs)
    z = a.elevation_m.copy()
    r, c = np.unravel_index(np.argmax(z), z.shape)
    z[max(r - 8, 0) : r + 8, max(c - 8, 0) : c + 8] += 60.0  # a 60 m mound on the top, in the second epoch
    b = Heightfield(z, a.valid.copy(), a.transform, a.crs)
    store = tmp_path / "ep.terra"
    build_store(a, store, workers=1, epoch="2019-01-01")
    update_store(b, store, "2020-01-01", workers=1)
    with open_terrain(store) as t:
        first, last = t.epochs[0], t.epochs[-1]
        assert last == "2020-01-01"
        svc = TileService(t)
        assert svc.get("/e/nope/3dtiles/tileset.json") is None and svc.get("/pairs/1.json") is None
        hi = _top_sum(svc.tiles3d(last).tileset()["root"])
        assert _top_sum(svc.tiles3d(first).tileset()["root"]) < hi - 20
        site = json.loads(
            gzip.decompress(svc.get("/site.json")[0])
            if svc.get("/site.json")[3]
            else svc.get("/site.json")[0]
        )
        assert [e["name"] for e in site["epochs"]] == [first, last] and site["pairs"][0]["from"] == first
        meta, files = svc.site_pair(0)
        dod = read_level(meta["rasters"]["dod"], files.get)  # terralod.site.tiles: the finest level
        assert np.nanmax(dod) == pytest.approx(60.0, abs=0.5)  # the mound (same grid: no shift)
        tile = meta["rasters"]["dod"]["url"] + "/0/0_0.i32.gz"  # served as the folder has it
        assert svc.get("/" + tile)[0] == files[tile]
    out = tmp_path / "first"
    main(["export", str(store), "--format", "3dtiles", "-o", str(out), "--epoch", first])
    ts = read_tileset(out)
    assert _top_sum(ts["root"]) < hi - 20
    capsys.readouterr()
    with pytest.raises(SystemExit) as exc:
        main(["export", str(store), "--format", "3dtiles", "-o", str(tmp_path / "x"), "--epoch", "1999"])
    err = capsys.readouterr().err.strip().splitlines()
    assert exc.value.code == 2 and "1999" in err[-1] and len(err) == 1


def test_serve_cli_binds_loopback_by_default(alpine_store: Path) -> None:
    """`terralod serve` listens on 127.0.0.1 unless told otherwise, and warns for any other address."""
    import sys

    for host, warn in ((None, False), ("127.0.0.2", True)):
        cmd = [sys.executable, "-m", "terralod", "serve", str(alpine_store), "--port", "0"]
        if host:
            cmd += ["--host", host]
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO)
        try:
            line = proc.stdout.readline()
            m = re.search(r"http://([\d.]+):(\d+)/", line)
            assert m, line
            assert m.group(1) == (host or "127.0.0.1")
            code, _, body = _get(f"http://{m.group(1)}:{m.group(2)}/info.json")
            assert code == 200 and json.loads(body)["kind"] == "grid"
        finally:
            proc.terminate()
            _, err = proc.communicate(timeout=20)
        assert ("warning" in err) == warn, err


# -- the DEM's own lattice: nodata fill, error kernel ------------------------------------------------
@settings(max_examples=15, deadline=None)
@given(h=st.integers(2, 30), w=st.integers(2, 30), seed=st.integers(0, 2**31 - 1), frac=st.floats(0.0, 0.9))
def test_dem_export_fills_nodata_as_a_store_does(h: int, w: int, seed: int, frac: float) -> None:
    """A geographic DEM read for a direct export (its own lattice) has the store's fill, bit for bit
    (terralod.fill.prepare_elevation); valid samples unchanged, holes between the valid extremes."""
    import tempfile

    import rasterio
    from affine import Affine

    from terralod.export.source import source_from_dem
    from terralod.fill import prepare_elevation

    rng = np.random.default_rng(seed)
    z = rng.integers(-50, 3000, (h, w)).astype(np.int16)
    valid = rng.random((h, w)) >= frac
    valid.flat[rng.integers(h * w)] = True
    z[~valid] = -32768
    with tempfile.TemporaryDirectory() as tmp:
        p = Path(tmp) / "dem.tif"
        prof = {"driver": "GTiff", "width": w, "height": h, "count": 1, "dtype": "int16", "nodata": -32768,
                "crs": "EPSG:4326", "transform": Affine(1 / 1200, 0.0, 1.0, 0.0, -1 / 1200, 42.0)}  # fmt: skip
        with rasterio.open(p, "w", **prof) as ds:
            ds.write(z, 1)
        got = source_from_dem(p)
    store_z, store_valid, _ = prepare_elevation(z.astype(np.float64), valid, "dem.tif")
    assert got.identity and np.array_equal(got.valid, store_valid)
    assert got.z_m.dtype == np.float32 and np.array_equal(got.z_m, store_z)
    assert np.array_equal(got.z_m[valid], z[valid])
    lo, hi = z[valid].min(), z[valid].max()
    assert got.z_m.min() >= lo - 1e-3 and got.z_m.max() <= hi + 1e-3


def test_lattice_error_against_independent_kernel(shared_data: Path) -> None:
    """On real SRTM3 samples (coast, nodata): each finest and next tile's lattice error equals the
    scattered-point kernel's max over the same samples, counts every valid sample inside the tile once,
    and a triangle taken out of the decoded tile is reported as a hole."""
    import rasterio
    from rasterio.windows import Window

    from terralod.export.lattice import lattice_error
    from terralod.export.quantized_mesh import QuantizedMesh, true_error_m
    from terralod.export.source import SourceGrid
    from terralod.fill import fill_nodata

    with rasterio.open(shared_data / "dem" / "srtm3_N41E001.tif") as ds:
        win = Window(900, 200, 300, 260)
        a = ds.read(1, window=win, masked=True)
        t = ds.window_transform(win)
    valid = ~np.ma.getmaskarray(a)
    valid[40:60, 100:130] = False  # a void inside the land as well
    z = np.ma.getdata(a).astype(np.float32)
    z = fill_nodata(z, valid).astype(np.float32)
    qm = QuantizedMesh(SourceGrid(z, valid, t, "EPSG:4326", "crop"))
    lat = qm.lattice
    for zz in (qm.max_zoom, qm.max_zoom - 1):
        x0, y0, x1, y1 = qm.level_range(zz)
        for x, y in ((x0, y0), (x1, y1)):
            rect = tile_rectangle(zz, x, y)
            d = decode_tile(qm.tile(zz, x, y).raw, rect)
            err, sumsq, count = lattice_error(lat, d, rect)
            plon, plat, pz = qm.ref.points_in(zz, x, y)
            assert count == plon.size
            assert err == pytest.approx(true_error_m(d, rect, plon, plat, pz), abs=1e-6)
            assert sumsq <= count * err * err + 1e-6
            if count:
                # every triangle whose bounding box holds one of the samples: that sample is uncovered
                w, s, e, n = rect
                pu = (plon[count // 2] - w) / (e - w) * 32767
                pv = (plat[count // 2] - s) / (n - s) * 32767
                tu, tv = d["u"][d["triangles"]], d["v"][d["triangles"]]
                hold = (tu.min(1) <= pu) & (tu.max(1) >= pu) & (tv.min(1) <= pv) & (tv.max(1) >= pv)
                assert hold.any()
                cut = dict(d, triangles=d["triangles"][~hold])
                with pytest.raises(RuntimeError, match="hole"):
                    lattice_error(lat, cut, rect)
