"""The web exports of a detail-increment TIN, checked from the outside.

Each 3D Tiles glb is decoded (pygltflib), its positions taken back through the tileset's transforms and
pyproj to the store's CRS, and every DEM sample the TIN was built from (read again with rasterio, not
taken from the model) that falls on a tile's surface is compared with it: the vertical distance stays
within the tile's declared ``vertical_error_m`` (and its ``geometricError``). The quantized-mesh export
likewise: each tile decoded, the DEM samples it covers within its error in ``errors.json``. Then the export
is a pure function of the store: the same bytes tile by tile in any order, and the export level by level.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from conftest import read_tileset

pytest.importorskip("pygltflib")
pytest.importorskip("pyproj")

#: Float32 positions relative to a tile centre a few km away round to ~1 mm; ECEF → lon/lat/h adds nothing
#: near that. What a surface may be off beyond its declared error, metres.
TOLERANCE_M = 0.01


@pytest.fixture(scope="module")
def crop(shared_data: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 65² crop of the Big Tujunga DEM (UTM 11N, 30 m, steep mountains, no nodata inside)."""
    from conftest import crop_geotiff

    d = tmp_path_factory.mktemp("tin_export")
    return crop_geotiff(shared_data / "dem" / "big_tujunga_srtm30m_utm11.tif", d / "crop.tif", 500, 300, 65)


@pytest.fixture(scope="module")
def tin(crop: Path) -> Path:
    from terralod.io.reader import read_heightfield
    from terralod.tin import DetailIncrementModel
    from terralod.tin.terra import save_model_to_store

    out = crop.parent / "crop.terra"
    save_model_to_store(DetailIncrementModel.from_heightfield(read_heightfield(crop), sub_blocks=4), out)
    return out


@pytest.fixture(scope="module")
def exported(tin: Path) -> Path:
    from terralod.export import export_3dtiles
    from terralod.terrain import open_terrain

    out = tin.parent / "3d"
    with open_terrain(tin) as t:
        export_3dtiles(t, out)
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


def _decode_glb(data: bytes) -> tuple[np.ndarray, np.ndarray, dict]:
    """(positions (N, 3) float64 glTF y-up, triangles (K, 3) int64, extras) of a one-mesh glb."""
    import pygltflib as g

    gl = g.GLTF2.load_from_bytes(data)
    blob = gl.binary_blob()
    prim = gl.meshes[0].primitives[0]
    acc = gl.accessors[prim.indices]
    bv = gl.bufferViews[acc.bufferView]
    dt = {g.UNSIGNED_BYTE: np.uint8, g.UNSIGNED_SHORT: np.uint16, g.UNSIGNED_INT: np.uint32}[
        acc.componentType
    ]
    tri = np.frombuffer(blob, dt, acc.count, bv.byteOffset).astype(np.int64).reshape(-1, 3)
    acc = gl.accessors[prim.attributes.POSITION]
    bv = gl.bufferViews[acc.bufferView]
    dt = np.dtype({g.FLOAT: np.float32, g.UNSIGNED_SHORT: np.uint16}[acc.componentType])
    width = (bv.byteStride or 3 * dt.itemsize) // dt.itemsize  # KHR_mesh_quantization pads to 4 bytes
    pos = (
        np.frombuffer(blob, dt, acc.count * width, bv.byteOffset).reshape(-1, width)[:, :3].astype(np.float64)
    )
    node = gl.nodes[0]  # KHR_mesh_quantization's dequantisation: the node's scale and translation
    pos = pos * np.array(node.scale or [1.0, 1.0, 1.0]) + np.array(node.translation or [0.0, 0.0, 0.0])
    return pos, tri, gl.extras


def _tiles(node: dict, above: np.ndarray) -> list[tuple[dict, np.ndarray]]:
    """Every tile of a tileset with its composed translation (ECEF)."""
    here = above + (np.array(node["transform"][12:15]) if "transform" in node else 0.0)
    out = [(node, here)]
    for k in node.get("children", []):
        out += _tiles(k, here)
    return out


def _surface(xyz: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """The triangles of a glb that are terrain, not skirt: a skirt vertex hangs right below another."""
    from scipy.spatial import cKDTree

    pairs = cKDTree(xyz[:, :2]).query_pairs(0.05, output_type="ndarray")
    lower = np.where(xyz[pairs[:, 0], 2] < xyz[pairs[:, 1], 2], pairs[:, 0], pairs[:, 1])
    skirt = np.zeros(len(xyz), bool)
    skirt[lower] = True
    return tri[~skirt[tri].any(axis=1)]


def test_3dtiles_declared_errors_bound_the_dem(crop: Path, exported: Path) -> None:
    """Every DEM sample on a tile's surface is within the tile's declared vertical error of it."""
    import matplotlib.tri as mtri
    from pyproj import CRS, Transformer

    pts, wkt = _samples(crop)
    back = Transformer.from_crs(CRS.from_epsg(4978), CRS.from_wkt(wkt), always_xy=True)
    ts = read_tileset(exported)
    covered: dict[int, np.ndarray] = {}
    checked = 0
    for node, centre in _tiles(ts["root"], np.zeros(3)):
        if "content" not in node:
            continue
        pos, tri, extras = _decode_glb((exported / node["content"]["uri"]).read_bytes())
        ecef = np.column_stack([pos[:, 0], -pos[:, 2], pos[:, 1]]) + centre  # glTF y-up → ECEF
        x, y, h = back.transform(ecef[:, 0], ecef[:, 1], ecef[:, 2])
        xyz = np.column_stack([x, y, h])
        surf = _surface(xyz, tri)
        assert surf.size and len(surf) < len(tri)  # a surface, and skirts around it
        interp = mtri.LinearTriInterpolator(mtri.Triangulation(x, y, surf), h)
        at = np.asarray(interp(pts[:, 0], pts[:, 1]).filled(np.nan))
        on = np.isfinite(at)
        assert on.any()
        gap = np.abs(at[on] - pts[on, 2])
        declared = float(extras["vertical_error_m"]) + float(extras.get("encoding_error_m", 0.0))
        assert declared <= node["geometricError"] + 1e-9
        assert gap.max() <= declared + TOLERANCE_M, (extras["code"], float(gap.max()), declared)
        rung = int(extras["code"][0])
        covered[rung] = covered.get(rung, np.zeros(len(pts), bool)) | on
        checked += int(on.sum())
    # the bases of the sub-blocks cover the DEM (the check is not vacuous)
    assert covered[0].mean() > 0.95
    assert checked > 3 * len(pts)  # and so do the finer rungs


def test_3dtiles_full_resolution_is_exact(exported: Path) -> None:
    """The finest node of each sub-block holds the input TIN: its measured error is 0."""
    ts = read_tileset(exported)
    leaves = [n for n, _ in _tiles(ts["root"], np.zeros(3)) if "content" in n and not n.get("children")]
    assert leaves
    for n in leaves:
        _, _, extras = _decode_glb((exported / n["content"]["uri"]).read_bytes())
        assert extras["vertical_error_m"] == 0.0


def test_3dtiles_tin_tiles_in_any_order(tin: Path, exported: Path) -> None:
    """A TIN's glb is a function of the store and its code: reverse order, every other tile, a fresh
    view per tile (the model moved elsewhere in between) give the export's bytes."""
    from terralod.export.tiles3d import Tiles3D, node_uri
    from terralod.terrain import open_terrain

    with open_terrain(tin) as t:
        codes = [n.code for n in t.lod_tree()]
        view = Tiles3D(t)
        got = {c: view.glb(c) for c in reversed(codes)}
        fresh = {c: Tiles3D(t).glb(c) for c in codes[1::3]}
    for c in codes:
        assert got[c] == (exported / node_uri(c)).read_bytes()
    for c, data in fresh.items():
        assert data == got[c]


def test_quantized_mesh_declared_errors_bound_the_dem(crop: Path, tin: Path) -> None:
    """The TIN exported as quantized-mesh (re-tiled on Cesium's geographic grid): each tile decoded, its
    surface taken in lon/lat, and every DEM sample it covers (read again with rasterio, moved to lon/lat
    with pyproj) within the tile's declared error in errors.json."""
    import json

    import matplotlib.tri as mtri
    from pyproj import CRS, Transformer

    from terralod.export import export_quantized_mesh
    from terralod.export.geodesy import tile_rectangle
    from terralod.export.quantized_mesh_format import decode_tile
    from terralod.terrain import open_terrain

    out = tin.parent / "qm"
    with open_terrain(tin) as t:
        export_quantized_mesh(t, out, overwrite=True)
    pts, wkt = _samples(crop)
    lon, lat = Transformer.from_crs(CRS.from_wkt(wkt), CRS.from_epsg(4326), always_xy=True).transform(
        pts[:, 0], pts[:, 1]
    )
    errors = json.loads((out / "errors.json").read_text())["tiles"]
    finest = max(int(k.split("/")[0]) for k in errors)
    checked = covered = 0
    for key, declared in errors.items():
        z, x, y = map(int, key.split("/"))
        rect = tile_rectangle(z, x, y)
        tile = decode_tile((out / f"{key}.terrain").read_bytes(), rect)
        w, s, e, n = rect
        inside = (lon >= w) & (lon <= e) & (lat >= s) & (lat <= n)
        if not inside.any():
            continue
        interp = mtri.LinearTriInterpolator(mtri.Triangulation(tile["lon"], tile["lat"], tile["triangles"]),
                                            tile["height"])  # fmt: skip
        at = np.asarray(interp(lon[inside], lat[inside]).filled(np.nan))
        on = np.isfinite(at)
        gap = np.abs(at[on] - pts[inside, 2][on])
        assert gap.max() <= declared + TOLERANCE_M, (key, float(gap.max()), declared)
        checked += int(on.sum())
        covered += int(on.sum()) if z == finest else 0
    assert covered > 0.95 * len(pts)  # the finest tiles cover the DEM: the check is not vacuous
    assert checked > 2 * len(pts)


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(seed=st.integers(0, 2**32 - 1), outside=st.floats(0.0, 1.0))
def test_tin_source_heights_do_not_depend_on_the_batch(tin: Path, seed: int, outside: float) -> None:
    """A TIN's surface at a point is the same asked alone or among others, repeated or not, inside the
    TIN or clipped onto its bounding box from far outside (the source looks each distinct position up once)."""
    from terralod.export.quantized_mesh import QuantizedMesh
    from terralod.terrain import open_terrain

    with open_terrain(tin) as t:
        src = QuantizedMesh(t).ref
    w, s, e, n = src.bbox
    rng = np.random.default_rng(seed)
    k = 300
    far = rng.random(k) < outside  # these lie up to a box's width beyond it: clipped onto its edges
    lon = w + (e - w) * np.where(far, rng.uniform(-1, 2, k), rng.random(k))
    lat = s + (n - s) * np.where(far, rng.uniform(-1, 2, k), rng.random(k))
    lon, lat = np.concatenate([lon, lon[::3]]), np.concatenate([lat, lat[::3]])  # repeats
    whole = src.height_at(lon, lat)
    alone = np.array([src.height_at(lon[i : i + 1], lat[i : i + 1])[0] for i in range(0, lon.size, 7)])
    assert np.isfinite(whole).all()
    np.testing.assert_array_equal(whole[::7], alone)
    np.testing.assert_array_equal(whole[k:], whole[:k][::3])
    square = src.height_at(lon.reshape(20, 20), lat.reshape(20, 20))  # a tile's lattice is 2-D
    np.testing.assert_array_equal(square.ravel(), whole)


@pytest.mark.skipif(not hasattr(__import__("os"), "fork"), reason="the kill forks the export (POSIX only)")
@pytest.mark.parametrize("fmt", ["3dtiles", "quantized-mesh"])
def test_a_killed_tin_export_resumes_to_the_uninterrupted_bytes(tin: Path, tmp_path: Path, fmt: str) -> None:
    """A TIN's export killed with SIGKILL halfway, then run again with ``resume``: the tiles it finished are
    kept (same inodes), and the output is the uninterrupted export's, byte for byte."""
    from terralod.export import export_3dtiles, export_quantized_mesh
    from terralod.output import work_path
    from terralod.terrain import open_terrain
    from test_kill import _die, _killed, _tree

    export = export_3dtiles if fmt == "3dtiles" else export_quantized_mesh
    totals: list[int] = []
    with open_terrain(tin) as t:
        export(t, tmp_path / "want", progress=lambda d, n: totals.append(n))
    half = totals[-1] // 2

    def killed_halfway() -> None:
        def cb(done: int, total: int) -> None:
            if done >= half:
                _die()

        with open_terrain(tin) as t:
            export(t, tmp_path / "out", progress=cb)

    _killed(killed_halfway)
    work = work_path(tmp_path / "out") / "out"
    before = {f: f.stat().st_ino for f in work.rglob("*") if f.is_file() and f.suffix in (".glb", ".terrain")}
    assert before and not (tmp_path / "out").exists()
    with open_terrain(tin) as t:
        export(t, tmp_path / "out", resume=True)
    assert _tree(tmp_path / "out") == _tree(tmp_path / "want")
    kept = [f for f, ino in before.items() if (tmp_path / "out" / f.relative_to(work)).stat().st_ino == ino]
    assert len(kept) == len(before)  # every finished tile kept, none encoded again
