"""``export --update`` encodes only the tiles whose inputs changed, and the result is a fresh export's bytes.

Each tile records a dependency digest (:mod:`terralod.export.incremental`); on update a tile whose digest
is unchanged is kept as it is (not encoded). Checked on a store after ``terralod update`` (quantized-mesh and
3D Tiles) and on a region of four EPSG:4326 DEM tiles where one tile is replaced by a modified copy.
"""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytest.importorskip("pydelatin")
pytest.importorskip("pyproj")

sys.path.insert(0, str(Path(__file__).parent))
from test_outputs import _dem_with_bump, _small_dem  # noqa: E402

from conftest import terralod_cli  # noqa: E402


def _tree(d: Path) -> dict[str, str]:
    return {f.relative_to(d).as_posix(): hashlib.sha256(f.read_bytes()).hexdigest()
            for f in sorted(d.rglob("*")) if f.is_file()}  # fmt: skip


def _terralod(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    """``terralod ARGS`` in this process (tests/conftest.py ``terralod_cli``)."""
    return terralod_cli(*args, cwd=cwd)


@pytest.mark.parametrize("fmt", ["quantized-mesh", "3dtiles"])
def test_store_update_encodes_only_the_changed_tiles(tmp_path: Path, fmt: str) -> None:
    from terralod.export import export_3dtiles, export_quantized_mesh
    from terralod.terrain import open_terrain

    _small_dem(tmp_path / "small.tif")
    _dem_with_bump(tmp_path / "small.tif", tmp_path / "later.tif")
    p = _terralod("build", "small.tif", "-o", "s.terra", "--epoch", "2000-01-01", cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    export = export_3dtiles if fmt == "3dtiles" else export_quantized_mesh
    export(open_terrain(tmp_path / "s.terra"), tmp_path / "web")
    p = _terralod("update", "s.terra", "later.tif", "--epoch", "2001-01-01", cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    want = export(open_terrain(tmp_path / "s.terra"), tmp_path / "want")
    assert want.extra["encoded"] == want.tiles  # a fresh export encodes every tile
    got = export(open_terrain(tmp_path / "s.terra"), tmp_path / "web", update=True)
    assert _tree(tmp_path / "web") == _tree(tmp_path / "want")  # a fresh export's bytes
    tiles_rewritten = [f for f in got.extra["rewritten"] if f.endswith((".terrain", ".glb"))]
    # every tile whose bytes changed was encoded, and fewer than all
    assert 0 < len(tiles_rewritten) <= got.extra["encoded"] < got.tiles, (got.extra, got.tiles)
    print(fmt, "encoded", got.extra["encoded"], "of", got.tiles, "rewritten", len(tiles_rewritten))
    # an update with nothing changed encodes nothing and rewrites nothing
    again = export(open_terrain(tmp_path / "s.terra"), tmp_path / "web", update=True)
    assert again.extra["encoded"] == 0 and again.extra["rewritten"] == []
    assert _tree(tmp_path / "web") == _tree(tmp_path / "want")


# -- a region of four DEM tiles, one replaced ---------------------------------------------------------------
Q = 601  #: samples a side of each of the four tiles (they share their edge row and column, as SRTM does)
STEP_DEG = 1.0 / 1200.0


def _surface(n: int) -> np.ndarray:
    y, x = np.mgrid[0:n, 0:n].astype(np.float64)
    return (300.0 + 120.0 * np.sin(x / 97.0) * np.cos(y / 131.0) + 40.0 * np.sin((x + y) / 23.0)).astype(
        np.float32
    )


def _write_quads(d: Path, z: np.ndarray) -> list[Path]:
    import rasterio
    from affine import Affine

    d.mkdir(exist_ok=True)
    t = Affine(STEP_DEG, 0, 1.0 - STEP_DEG / 2, 0, -STEP_DEG, 43.0 + STEP_DEG / 2)
    out = []
    k = Q - 1
    for name, r0, c0 in (("nw", 0, 0), ("ne", 0, k), ("sw", k, 0), ("se", k, k)):
        a = np.ascontiguousarray(z[r0 : r0 + Q, c0 : c0 + Q])
        p = d / f"{name}.tif"
        with rasterio.open(p, "w", driver="GTiff", width=Q, height=Q, count=1, dtype="float32", crs="EPSG:4326",
                           transform=t @ Affine.translation(c0, r0)) as ds:  # fmt: skip
            ds.write(a, 1)
        out.append(p)
    return out


def _encoded(monkeypatch: pytest.MonkeyPatch) -> list[tuple[int, int, int]]:
    from terralod.export.quantized_mesh import QuantizedMesh

    seen: list[tuple[int, int, int]] = []
    tile = QuantizedMesh.tile

    def counting(self: Any, z: int, x: int, y: int, **kw: Any) -> Any:
        seen.append((z, x, y))
        return tile(self, z, x, y, **kw)

    monkeypatch.setattr(QuantizedMesh, "tile", counting)
    return seen


def test_region_update_encodes_only_the_tiles_near_the_replaced_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from terralod.export.geodesy import tile_rectangle
    from terralod.export.quantized_mesh import export_quantized_mesh
    from terralod.export.source import source_from_region

    z = _surface(2 * Q - 1)
    files = _write_quads(tmp_path / "q", z)
    export_quantized_mesh(source_from_region(files), tmp_path / "web")
    # the SE tile replaced by a modified copy (a 30 m mound in it)
    y, x = np.mgrid[0 : 2 * Q - 1, 0 : 2 * Q - 1]
    z2 = z + (30.0 * np.exp(-((x - 1000.0) ** 2 + (y - 1000.0) ** 2) / 500.0)).astype(np.float32)
    se = tmp_path / "q" / "se.tif"
    os.unlink(se)
    _write_quads(tmp_path / "new", z2)
    os.replace(tmp_path / "new" / "se.tif", se)
    want = export_quantized_mesh(source_from_region(files), tmp_path / "want")
    seen = _encoded(monkeypatch)
    got = export_quantized_mesh(source_from_region(files), tmp_path / "web", update=True)
    assert _tree(tmp_path / "web") == _tree(tmp_path / "want")  # a fresh export's bytes
    assert got.extra["encoded"] == len(set(seen)) and 0 < len(set(seen)) < want.tiles * 2 // 3
    # every tile encoded meets the fill blocks (512 samples) the replaced file meets; none away from them
    from terralod.io.region import FILL_BLOCK

    lo = ((Q - 1) // FILL_BLOCK) * FILL_BLOCK  # first row/column of the blocks SE meets
    west = 1.0 - STEP_DEG / 2 + lo * STEP_DEG
    north = 43.0 + STEP_DEG / 2 - lo * STEP_DEG
    margin = 0.01  # a few samples (the lattice's clamp and normals) of each tile's rectangle
    for c in set(seen):
        w, s, e, n = tile_rectangle(*c)
        assert e + margin > west and s - margin < north, c
    finest = [c for c in want_codes(tmp_path / "want") if c[0] == got.extra["max_zoom"]]
    far = [c for c in finest if tile_rectangle(*c)[2] + 0.05 < west or tile_rectangle(*c)[1] - 0.05 > north]
    assert far and not set(far) & set(seen)


def want_codes(out: Path) -> list[tuple[int, int, int]]:
    return [tuple(int(v) for v in f.relative_to(out).with_suffix("").parts)  # type: ignore[misc]
            for f in out.rglob("*.terrain")]  # fmt: skip


@pytest.mark.parametrize("fmt", ["quantized-mesh", "3dtiles"])
def test_a_tin_stores_update_encodes_nothing_when_the_model_is_the_same_and_everything_when_not(
    tmp_path: Path, fmt: str
) -> None:
    """A TIN's web tiles depend on the stored model as a whole (its SHA-256) and their code: an update of
    an export from the same model encodes and rewrites nothing; after the store is rebuilt from other
    points, it gives a fresh export's bytes."""
    from terralod.export import export_3dtiles, export_quantized_mesh
    from terralod.terrain import open_terrain
    from terralod.tin import DetailIncrementModel
    from terralod.tin.pointcloud import read_las
    from terralod.tin.terra import save_model_to_store

    laz = Path(__file__).resolve().parents[2] / "shared" / "data" / "lidar" / "autzen_trim.laz"
    if not laz.exists():
        pytest.skip("../shared/data/lidar/autzen_trim.laz is absent (the shared data folder)")
    pc = read_las(laz)
    store = tmp_path / "tin.terra"
    save_model_to_store(DetailIncrementModel.from_points(pc.xyz_m, crs=pc.crs, workers=1), store)
    export = export_3dtiles if fmt == "3dtiles" else export_quantized_mesh
    export(open_terrain(store), tmp_path / "web")
    before = _tree(tmp_path / "web")
    same = export(open_terrain(store), tmp_path / "web", update=True)
    assert same.extra["encoded"] == 0 and same.extra["rewritten"] == []
    assert _tree(tmp_path / "web") == before
    xyz = pc.xyz_m.copy()
    xyz[xyz[:, 0] > np.median(xyz[:, 0]), 2] += 3.0  # half the survey 3 m higher
    save_model_to_store(DetailIncrementModel.from_points(xyz, crs=pc.crs, workers=1), store, overwrite=True)
    want = export(open_terrain(store), tmp_path / "want")
    got = export(open_terrain(store), tmp_path / "web", update=True)
    assert got.extra["encoded"] == got.tiles == want.tiles
    assert _tree(tmp_path / "web") == _tree(tmp_path / "want")
