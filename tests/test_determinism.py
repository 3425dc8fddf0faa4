"""A web tile is a function of (source, options, z, x, y): the same bytes whichever tiles were made before
it, from the export or from ``terralod serve``, in this process or in another one.

On a crop of SRTM3 with a coast and nodata (the quantized-mesh tiles on the DEM's own lattice, whose goal
zoom takes a statistic from its parent) and the 3D Tiles of the store built from it.
"""

from __future__ import annotations

import gzip
import hashlib
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

pytest.importorskip("pydelatin")
pytest.importorskip("pygltflib")

Code = tuple[int, int, int]


@pytest.fixture(scope="module")
def store(shared_data: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A store built from a 160² crop of SRTM3 N41E001 (coast, nodata); its source is read again on its own
    lattice by the quantized-mesh tiler."""
    import rasterio
    from rasterio.windows import Window

    from terralod.io.reader import read_heightfield
    from terralod.pyramid.builder import build_store

    d = tmp_path_factory.mktemp("determinism")
    dem = d / "coast.tif"
    with rasterio.open(shared_data / "dem" / "srtm3_N41E001.tif") as ds:
        win = Window(900, 250, 160, 160)
        a = ds.read(1, window=win)
        prof = dict(ds.profile, width=160, height=160, transform=ds.window_transform(win), tiled=False)
    prof.pop("blockxsize", None)
    prof.pop("blockysize", None)
    with rasterio.open(dem, "w", **prof) as out:
        out.write(a, 1)
    assert (a == prof["nodata"]).any()  # the fill is part of what must not depend on the order
    build_store(read_heightfield(dem), d / "coast.terra", tile_size=33, workers=1)
    return d / "coast.terra"


@pytest.fixture(scope="module")
def exported(store: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, dict[Code, bytes]]:
    """The exports' tiles: quantized-mesh of the coarsest zoom and the three finest (the goal zoom, its
    parents and children), every 3D Tiles glb."""
    from terralod.export import export_3dtiles, export_quantized_mesh
    from terralod.terrain import open_terrain

    d = tmp_path_factory.mktemp("exports")
    with open_terrain(store) as t:
        rep = export_quantized_mesh(t, d / "qm")
        export_3dtiles(t, d / "3d")
    top = rep.extra["max_zoom"]
    qm = {}
    for f in (d / "qm").rglob("*.terrain"):
        code = (int(f.parent.parent.name), int(f.parent.name), int(f.stem))
        if code[0] in (0, top - 2, top - 1, top):
            qm[code] = f.read_bytes()
    glb = {}
    for f in (d / "3d" / "tiles").rglob("*.glb"):
        x, y = f.stem.split("_")
        glb[(int(f.parent.name), int(x), int(y))] = f.read_bytes()
    assert any(c[0] == top - 1 for c in qm) and len(glb) > 4
    return {"qm": qm, "glb": glb}


def _served(service, path: str) -> bytes:
    body, _, _, gz = service.get(path)
    return gzip.decompress(body) if gz else body


@settings(max_examples=6, deadline=None)
@given(data=st.data())
def test_quantized_mesh_tiles_in_any_order(store: Path, exported: dict, data: st.DataObject) -> None:
    """Any order of the tiles (children before parents included), from a fresh tiler or a fresh server:
    the export's bytes."""
    from terralod.export.quantized_mesh import QuantizedMesh
    from terralod.serve.server import TileService
    from terralod.terrain import open_terrain

    codes = data.draw(st.permutations(sorted(exported["qm"])))
    with open_terrain(store) as t:
        if data.draw(st.booleans(), label="served"):
            svc = TileService(t)
            got = {c: _served(svc, "/terrain/{}/{}/{}.terrain".format(*c)) for c in codes}
        else:
            qm = QuantizedMesh(t)
            got = {c: qm.tile(*c).raw for c in codes}
    assert got == {c: exported["qm"][c] for c in codes}


@settings(max_examples=4, deadline=None)
@given(data=st.data())
def test_3dtiles_tiles_in_any_order(store: Path, exported: dict, data: st.DataObject) -> None:
    from terralod.export.tiles3d import Tiles3D
    from terralod.serve.server import TileService
    from terralod.terrain import open_terrain

    codes = data.draw(st.permutations(sorted(exported["glb"])))
    with open_terrain(store) as t:
        if data.draw(st.booleans(), label="served"):
            svc = TileService(t)
            got = {c: _served(svc, "/3dtiles/tiles/{}/{}_{}.glb".format(*c)) for c in codes}
        else:
            view = Tiles3D(t)
            got = {c: view.glb(c) for c in codes}
    assert got == {c: exported["glb"][c] for c in codes}


_SECOND_PROCESS = """
import hashlib, json, sys
from terralod.export.quantized_mesh import QuantizedMesh
from terralod.export.tiles3d import Tiles3D
from terralod.terrain import open_terrain
qm_codes, glb_codes = json.loads(sys.argv[2])
with open_terrain(sys.argv[1]) as t:
    qm, view = QuantizedMesh(t), Tiles3D(t)
    out = {"qm": [hashlib.sha256(qm.tile(*c).raw).hexdigest() for c in qm_codes],
           "glb": [hashlib.sha256(view.glb(tuple(c))).hexdigest() for c in glb_codes]}
print(json.dumps(out))
"""


def test_tiles_in_a_second_process(store: Path, exported: dict) -> None:
    """Another process, finest tiles first (every child before its parent): the same bytes."""
    qm_codes = sorted(exported["qm"], reverse=True)
    glb_codes = sorted(exported["glb"], reverse=True)
    run = subprocess.run(
        [sys.executable, "-c", _SECOND_PROCESS, str(store), json.dumps([qm_codes, glb_codes])],
        capture_output=True, text=True, timeout=600, check=True,
    )  # fmt: skip
    got = json.loads(run.stdout.strip().splitlines()[-1])
    assert got["qm"] == [hashlib.sha256(exported["qm"][c]).hexdigest() for c in qm_codes]
    assert got["glb"] == [hashlib.sha256(exported["glb"][c]).hexdigest() for c in glb_codes]


def test_goal_zoom_statistic_is_its_parents_own() -> None:
    """The parent's RMS per metre of target that a goal-zoom tile reads is what the parent's own tile
    gives, whether or not the parent was made (or made first)."""
    from affine import Affine

    from terralod.export.quantized_mesh import QuantizedMesh
    from terralod.export.source import SourceGrid

    rng = np.random.default_rng(5)
    z = np.cumsum(np.cumsum(rng.normal(0.0, 3.0, (120, 120)), 0), 1).astype(np.float32)
    arc3 = 1.0 / 1200.0
    src = SourceGrid(z, np.ones(z.shape, bool), Affine(arc3, 0.0, 1.0, 0.0, -arc3, 42.0), "EPSG:4326", "walk")
    qm = QuantizedMesh(src)
    z0, x0, y0 = qm.max_zoom - 2, *qm.level_range(qm.max_zoom - 2)[:2]
    fresh = QuantizedMesh(src).rms_ratio(z0, x0, y0)
    t = qm.tile(z0, x0, y0)
    assert fresh is not None and qm._rms_ratio[(z0, x0, y0)] == fresh
    assert fresh == pytest.approx(np.sqrt(t.sumsq_m2 / t.samples) / qm.target_error_m(z0))
