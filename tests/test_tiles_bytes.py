"""The 3D Tiles glb geometry (float, KHR_mesh_quantization, EXT_meshopt_compression), checked from outside.

Each glb is decoded here by its JSON alone: accessors read by their component type, stride and
``normalized`` flag, the node's scale and translation applied (the dequantisation KHR_mesh_quantization
folds there), EXT_meshopt_compression buffer views decompressed by meshoptimizer's *decoder* (the npm
package's ``MeshoptDecoder``, the one CesiumJS bundles) through node. None of the writer's code is used.
Then: the positions lie within the declared error of the DEM's own samples (read again with rasterio),
every stored vertex is within the tile's declared encoding bound of a decoded one, ``--max-error-m`` cuts
the tree where it says, and the bytes fall as they should.
"""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from conftest import read_tileset

pytest.importorskip("pygltflib")
pytest.importorskip("pyproj")

REPO = Path(__file__).resolve().parents[1]
NODE_MODULES = REPO / "node_modules"
#: What a surface may be off beyond its declared error, metres (ECEF ↔ CRS round trips, float64).
TOLERANCE_M = 0.001

_COMPONENTS = {
    5120: np.int8,
    5121: np.uint8,
    5122: np.int16,
    5123: np.uint16,
    5125: np.uint32,
    5126: np.float32,
}
_WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}
_MESHOPT_DECODE = r"""
import fs from "fs";
import { pathToFileURL } from "url";
const { MeshoptDecoder: D } = await import(pathToFileURL(process.env.MESHOPT_DECODER).href);
await D.ready;
const glb = fs.readFileSync(0);
const jsonLen = glb.readUInt32LE(12);
const gl = JSON.parse(glb.subarray(20, 20 + jsonLen).toString());
const bin = glb.subarray(20 + jsonLen + 8);
const views = gl.bufferViews.map((v) => {
  const m = v.extensions.EXT_meshopt_compression;
  const out = new Uint8Array(m.count * m.byteStride);
  D.decodeGltfBuffer(out, m.count, m.byteStride, bin.subarray(m.byteOffset, m.byteOffset + m.byteLength), m.mode,
                     m.filter || "NONE");
  return Buffer.from(out).toString("base64");
});
process.stdout.write(JSON.stringify(views));
"""


def _meshopt_views(data: bytes) -> list[bytes]:
    """The decompressed bytes of every buffer view of a meshopt glb (meshoptimizer's decoder, node)."""
    import base64
    import os

    env = dict(os.environ, MESHOPT_DECODER=str(NODE_MODULES / "meshoptimizer" / "meshopt_decoder.mjs"))
    out = subprocess.run(["node", "--input-type=module", "-e", _MESHOPT_DECODE], input=data, capture_output=True,
                         env=env, timeout=60, check=True)  # fmt: skip
    return [base64.b64decode(v) for v in json.loads(out.stdout)]


def decode_glb(data: bytes) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
    """(positions (N, 3) float64 in the scene's y-up frame after the node's transform, normals (N, 3) float64
    unit, triangles (K, 3) int64, the glTF JSON) of a one-mesh, one-node glb, from its JSON alone."""
    import struct

    assert data[:4] == b"glTF" and struct.unpack("<I", data[4:8])[0] == 2
    n_json = struct.unpack("<I", data[12:16])[0]
    gl = json.loads(data[20 : 20 + n_json])
    bin_ = data[20 + n_json + 8 :]
    if "EXT_meshopt_compression" in gl.get("extensionsUsed", []):
        views = _meshopt_views(data)
    else:
        views = [
            bin_[v.get("byteOffset", 0) : v.get("byteOffset", 0) + v["byteLength"]] for v in gl["bufferViews"]
        ]

    def read(i: int) -> np.ndarray:
        acc = gl["accessors"][i]
        bv = gl["bufferViews"][acc["bufferView"]]
        dt = np.dtype(_COMPONENTS[acc["componentType"]])
        w = _WIDTH[acc["type"]]
        stride = bv.get("byteStride", dt.itemsize * w)
        raw = np.frombuffer(views[acc["bufferView"]], np.uint8)
        start = acc.get("byteOffset", 0)
        rows = np.stack(
            [raw[start + k * stride : start + k * stride + dt.itemsize * w] for k in range(acc["count"])]
        )
        a = rows.view(dt).reshape(acc["count"], w).astype(np.float64)
        if acc.get("normalized"):  # glTF 2.0 §3.11: c / (2^(b-1) - 1), at least -1, for signed types
            a = np.maximum(a / np.iinfo(dt).max, -1.0)
        return a

    prim = gl["meshes"][0]["primitives"][0]
    pos, nrm = read(prim["attributes"]["POSITION"]), read(prim["attributes"]["NORMAL"])
    tri = read(prim["indices"]).astype(np.int64).reshape(-1, 3)
    node = gl["nodes"][0]
    assert "matrix" not in node and "rotation" not in node
    pos = pos * np.array(node.get("scale", [1.0, 1.0, 1.0])) + np.array(
        node.get("translation", [0.0, 0.0, 0.0])
    )
    return pos, nrm, tri, gl


def _tiles(node: dict, above: np.ndarray) -> list[tuple[dict, np.ndarray]]:
    """Every tile of a tileset with its composed translation (ECEF)."""
    here = above + (np.array(node["transform"][12:15]) if "transform" in node else 0.0)
    out = [(node, here)]
    for k in node.get("children", []):
        out += _tiles(k, here)
    return out


def _meshopt_missing() -> str | None:
    if shutil.which("node") is None:
        return "node not installed"
    if not (NODE_MODULES / "meshoptimizer" / "meshopt_decoder.mjs").is_file():
        return "node_modules/meshoptimizer missing (run `npm ci` in the repository)"
    return None


# -- the encoder alone, over random meshes ---------------------------------------------------------------
@settings(max_examples=25, deadline=None)
@given(st.integers(3, 400), st.integers(0, 2**31 - 1), st.sampled_from([0.5, 30.0, 2000.0, 60000.0]))
def test_quantized_positions_within_the_bound(n: int, seed: int, extent_m: float) -> None:
    """Random meshes: decoded positions within √3·q/2 of the input (q the grid step), the reported shift
    is the decoded one, normals within 1/127 of the input per axis, indices in range and never the
    primitive-restart value."""
    from terralod.export.tiles3d import QUANT_STEPS, _write_glb

    rng = np.random.default_rng(seed)
    pos = (rng.random((n, 3)) - 0.5) * extent_m
    nrm = rng.normal(size=(n, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    tri = np.stack([rng.permutation(n)[:3] for _ in range(max(1, n // 2))])
    tri = np.concatenate(
        [tri, np.stack([np.arange(n), np.roll(np.arange(n), 1), np.roll(np.arange(n), 2)], 1)]
    )
    q = float(2.0 ** np.ceil(np.log2(extent_m * 1.01 / QUANT_STEPS)))
    data, moved = _write_glb(pos, nrm, tri, {}, step=q)
    dpos, dnrm, dtri, gl = decode_glb(data)
    assert gl["extensionsRequired"] == ["KHR_mesh_quantization"]
    # the writer's vertex order is its own: compare triangle by triangle, corners in order
    yup = np.stack([pos[:, 0], pos[:, 2], -pos[:, 1]], 1)
    shift = np.linalg.norm(dpos[dtri] - yup[tri], axis=2)
    assert shift.max() <= np.sqrt(3) / 2 * q + 1e-9
    assert abs(shift.max() - moved) <= 1e-9 * max(1.0, extent_m)
    ny = np.stack([nrm[:, 0], nrm[:, 2], -nrm[:, 1]], 1)
    assert np.abs(dnrm[dtri] - ny[tri]).max() <= 0.5 / 127 + 1e-9
    limit = {1: 255, 2: 65535, 4: 2**32 - 1}[
        np.dtype(_COMPONENTS[gl["accessors"][0]["componentType"]]).itemsize
    ]
    assert dtri.max() < len(dpos) and dtri.max() < limit


# -- whole exports of a real DEM -----------------------------------------------------------------------
@pytest.fixture(scope="module")
def crop(shared_data: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 129² crop of the Big Tujunga DEM (UTM 11N, 30 m, steep mountains, no nodata inside)."""
    from conftest import crop_geotiff

    d = tmp_path_factory.mktemp("tiles_bytes")
    return crop_geotiff(shared_data / "dem" / "big_tujunga_srtm30m_utm11.tif", d / "crop.tif", 400, 200, 129)


@pytest.fixture(scope="module")
def store(crop: Path) -> Path:
    from terralod.io.reader import read_heightfield
    from terralod.pyramid.builder import build_store

    out = crop.parent / "crop.terra"
    build_store(read_heightfield(crop), out, workers=2, tile_size=33)
    return out


@pytest.fixture(scope="module")
def exports(store: Path) -> dict[str, Path]:
    """The store exported with --metric vertical in each geometry (meshopt when node has the package)."""
    from terralod.export import export_3dtiles
    from terralod.terrain import open_terrain

    out = {}
    with open_terrain(store) as t:
        for g in ("float", "quantized") + (() if _meshopt_missing() else ("meshopt",)):
            out[g] = store.parent / f"3d_{g}"
            export_3dtiles(t, out[g], metric="vertical", geometry=g)
    return out


def _samples(crop: Path) -> tuple[np.ndarray, str]:
    """(N, 3) x, y, z of every sample of the DEM (pixel centres, its CRS), and the CRS."""
    import rasterio

    with rasterio.open(crop) as ds:
        z = ds.read(1).astype(np.float64)
        t = ds.transform
        r, c = np.mgrid[0 : ds.height, 0 : ds.width]
        x = t.c + (c + 0.5) * t.a + (r + 0.5) * t.b
        y = t.f + (c + 0.5) * t.d + (r + 0.5) * t.e
        return np.column_stack([x.ravel(), y.ravel(), z.ravel()]), ds.crs.to_wkt()


def _surface(xyz: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """The triangles of a glb that are terrain, not skirt: a skirt vertex hangs right below another."""
    from scipy.spatial import cKDTree

    pairs = cKDTree(xyz[:, :2]).query_pairs(0.2, output_type="ndarray")
    lower = np.where(xyz[pairs[:, 0], 2] < xyz[pairs[:, 1], 2], pairs[:, 0], pairs[:, 1])
    skirt = np.zeros(len(xyz), bool)
    skirt[lower] = True
    return tri[~skirt[tri].any(axis=1)]


@pytest.mark.parametrize("geometry", ["float", "quantized", "meshopt"])
def test_declared_errors_bound_the_dem(crop: Path, exports: dict[str, Path], geometry: str) -> None:
    """Every DEM sample on a decoded tile's surface is within the tile's geometricError of it (vertically:
    the export's metric is vertical), the encoding's shift included."""
    import matplotlib.tri as mtri
    from pyproj import CRS, Transformer

    if geometry not in exports:
        pytest.skip(_meshopt_missing() or "")
    out = exports[geometry]
    pts, wkt = _samples(crop)
    back = Transformer.from_crs(CRS.from_epsg(4978), CRS.from_wkt(wkt), always_xy=True)
    ts = read_tileset(out)
    checked, worst_shift = 0, 0.0
    for node, centre in _tiles(ts["root"], np.zeros(3)):
        pos, _, tri, gl = decode_glb((out / node["content"]["uri"]).read_bytes())
        ecef = np.column_stack([pos[:, 0], -pos[:, 2], pos[:, 1]]) + centre  # glTF y-up → ECEF
        x, y, h = back.transform(ecef[:, 0], ecef[:, 1], ecef[:, 2])
        xyz = np.column_stack([x, y, h])
        surf = _surface(xyz, tri)
        assert surf.size and len(surf) < len(tri)  # a surface, and skirts around it
        at = np.asarray(
            mtri.LinearTriInterpolator(mtri.Triangulation(x, y, surf), h)(pts[:, 0], pts[:, 1]).filled(np.nan)
        )
        on = np.isfinite(at)
        assert on.any()
        gap = float(np.abs(at[on] - pts[on, 2]).max())
        extras = gl["extras"]
        assert extras["vertical_error_m"] + extras["encoding_error_m"] <= node["geometricError"] + 1e-9
        assert gap <= node["geometricError"] + TOLERANCE_M, (extras["code"], gap, node["geometricError"])
        worst_shift = max(worst_shift, extras["encoding_error_m"])
        checked += int(on.sum())
    assert checked > 2.5 * len(pts)  # every level covers the DEM
    if geometry != "float":
        assert worst_shift > 0.005  # the quantisation is counted, not assumed away


def test_stored_vertices_within_the_encoding_bound(store: Path, exports: dict[str, Path]) -> None:
    """Every stored vertex of a tile is within the tile's declared encoding bound of a decoded vertex (in
    ECEF, through pyproj), and geometricError ≥ measured error + the shift measured here."""
    from pyproj import Transformer
    from scipy.spatial import cKDTree

    from terralod.terrain import open_terrain

    with open_terrain(store) as t:
        to_ecef = Transformer.from_crs(t.crs, "EPSG:4978", always_xy=True)
        tree = {n.code: n for n in t.lod_tree()}
        for g, out in exports.items():
            ts = read_tileset(out)
            for node, centre in _tiles(ts["root"], np.zeros(3)):
                pos, _, tri, gl = decode_glb((out / node["content"]["uri"]).read_bytes())
                code = tuple(gl["extras"]["code"])
                v, vt = t.lod_mesh(code)
                v = np.asarray(v)[np.unique(vt)]
                exact = np.column_stack(to_ecef.transform(v[:, 0], v[:, 1], v[:, 2]))
                ecef = np.column_stack([pos[:, 0], -pos[:, 2], pos[:, 1]]) + centre
                shift = float(cKDTree(ecef).query(exact)[0].max())
                assert len(pos) > len(v)  # the stored vertices and the skirts' below them
                bound = gl["extras"]["encoding_error_m"]
                assert shift <= bound + 1e-6, (g, code, shift, bound)
                assert node["geometricError"] >= tree[code].vertical_error_m + shift
                if g != "float":
                    assert gl["extensionsRequired"][0] == "KHR_mesh_quantization"
                    assert node["geometricError"] >= tree[code].vertical_error_m + bound


def test_khronos_validator_clean(exports: dict[str, Path]) -> None:
    """The Khronos glTF validator: 0 errors and 0 warnings on every glb of every geometry."""
    if shutil.which("node") is None or not (NODE_MODULES / "gltf-validator").is_dir():
        pytest.skip("node or node_modules/gltf-validator missing (run `npm ci` in the repository)")
    for g, out in exports.items():
        val = subprocess.run(["node", str(REPO / "tests" / "web" / "validate_glb.mjs"), str(out)], capture_output=True,
                             text=True, timeout=120, cwd=REPO)  # fmt: skip
        res = json.loads(val.stdout.strip().splitlines()[-1])
        assert res["files"] == len(list(out.rglob("*.glb"))) > 0
        assert res["errors"] == 0 and res["warnings"] == 0, (g, res)


def test_fewer_bytes(exports: dict[str, Path]) -> None:
    """Quantized glbs are under 0.7 of the float ones gzip'd; meshopt's under quantized's, raw and gzip'd."""
    import gzip

    def size(g: str, gz: bool) -> int:
        return sum(
            len(gzip.compress(p.read_bytes(), 6) if gz else p.read_bytes()) for p in exports[g].rglob("*.glb")
        )

    assert size("quantized", True) < 0.7 * size("float", True)
    if "meshopt" in exports:
        assert size("meshopt", False) < 0.7 * size("quantized", False)
        assert size("meshopt", True) < size("quantized", True)


def test_max_error_cuts_the_tree(store: Path, tmp_path: Path) -> None:
    """--max-error-m E: a kept tile has children exactly when it declares more than E; every leaf declares
    at most E; the tiles kept are the whole export's tiles whose parent declares more than E there, each
    glb the same bytes when its level is whole."""
    from terralod.cli import main

    full, cut = tmp_path / "full", tmp_path / "cut"
    main(["export", str(store), "--format", "3dtiles", "--metric", "vertical", "-o", str(full)])
    whole = {n["content"]["uri"]: n for n, _ in _tiles(read_tileset(full)["root"],
                                                       np.zeros(3))}  # fmt: skip
    errs = sorted({n["geometricError"] for n in whole.values()})
    e = errs[len(errs) // 2]
    main(
        [
            "export",
            str(store),
            "--format",
            "3dtiles",
            "--metric",
            "vertical",
            "--max-error-m",
            str(e),
            "-o",
            str(cut),
        ]
    )
    kept = _tiles(read_tileset(cut)["root"], np.zeros(3))
    parent_of = {}
    for n in whole.values():
        for k in n.get("children", []):
            parent_of[k["content"]["uri"]] = n["content"]["uri"]
    expect = {u for u in whole if u not in parent_of or whole[parent_of[u]]["geometricError"] > e}
    assert {n["content"]["uri"] for n, _ in kept} == expect and len(expect) < len(whole)
    for n, _ in kept:
        assert bool(n.get("children")) == (n["geometricError"] > e)
        assert n["geometricError"] <= whole[n["content"]["uri"]]["geometricError"]
    assert len(list(cut.rglob("*.glb"))) == len(expect)


def test_meshopt_glb_is_deterministic(store: Path) -> None:
    """The meshopt encoder (a node process) gives the same bytes whatever was encoded before."""
    if _meshopt_missing():
        pytest.skip(_meshopt_missing() or "")
    from terralod.export.tiles3d import Tiles3D
    from terralod.terrain import open_terrain

    with open_terrain(store) as t:
        a, b = Tiles3D(t, geometry="meshopt"), Tiles3D(t, geometry="meshopt")
        codes = [n.code for n in a.tree]
        first = {c: a.glb(c) for c in codes}
        for c in reversed(codes):
            assert b.glb(c) == first[c]
        a.close()
        b.close()
