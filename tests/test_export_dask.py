"""``terralod export --dask``: the tiles encoded on Dask workers are the local run's, byte for byte.

One LocalCluster of two worker processes (one thread each) serves the module; the CLI reaches it by its
scheduler address (``--dask tcp://...``), the library through ``client=``. Paths: a UTM DEM straight to
quantized-mesh, a region of four EPSG:4326 GeoTIFFs (a crop of SRTM3 N41E001 with voids, so lattice tiles,
the RMS-goal zoom and water masks), a store to quantized-mesh and to 3D Tiles (small batches, so a worker
builds only part of a level), and an interrupted export resumed with ``--dask``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from terralod.cli import main
from test_outputs import _small_dem  # a 200² UTM hill, no shared data needed

pytest.importorskip("distributed")
pytest.importorskip("pydelatin")
pytest.importorskip("pyproj")
pytest.importorskip("pygltflib")

N = 161  #: samples a side of the region's crop
K = 80  #: the split: tiles [0, K] and [K, N) share row/column K


@pytest.fixture(scope="module")
def dask_address() -> Any:
    from distributed import Client, LocalCluster

    cluster = LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None)
    client = Client(cluster)
    yield client
    client.close()
    cluster.close()


def _tree(out: Path) -> dict[str, bytes]:
    return {str(f.relative_to(out)): f.read_bytes() for f in sorted(out.rglob("*")) if f.is_file()}


def _quads(shared_data: Path, d: Path) -> list[Path]:
    """161² of N41E001 around its voids as four EPSG:4326 GeoTIFFs sharing row and column K."""
    import rasterio
    from affine import Affine
    from rasterio.windows import Window

    with rasterio.open(shared_data / "dem" / "srtm3_N41E001.tif") as ds:
        win = Window(900, 400, N, N)
        a, t = ds.read(1, window=win), ds.window_transform(win)
    d.mkdir(exist_ok=True)
    out = []
    for name, r0, c0 in (("nw", 0, 0), ("ne", 0, K), ("sw", K, 0), ("se", K, K)):
        q = np.ascontiguousarray(a[r0 : (K + 1 if r0 == 0 else N), c0 : (K + 1 if c0 == 0 else N)])
        with rasterio.open(d / f"{name}.tif", "w", driver="GTiff", width=q.shape[1], height=q.shape[0], count=1,
                           dtype=q.dtype, crs="EPSG:4326", transform=t @ Affine.translation(c0, r0),
                           nodata=-32768.0) as o:  # fmt: skip
            o.write(q, 1)
        out.append(d / f"{name}.tif")
    return out


def _export(out: Path, *args: str | Path, extra: tuple[str, ...] = ()) -> dict[str, bytes]:
    main(["export", *map(str, args), "-o", str(out), *extra])
    return _tree(out)


def test_a_dem_to_quantized_mesh_on_dask_is_the_local_export(dask_address: Any, tmp_path: Path) -> None:
    dem = _small_dem(tmp_path / "small.tif")
    want = _export(tmp_path / "local", dem, "--format", "quantized-mesh")
    got = _export(tmp_path / "dask", dem, "--format", "quantized-mesh",
                  extra=("--dask", dask_address.scheduler.address))  # fmt: skip
    assert len([k for k in want if k.endswith(".terrain")]) > 8
    assert got == want
    opened = dask_address.run(lambda: len(__import__("terralod.export.distributed", fromlist=["_"])._OPENED))
    assert len(opened) == 2 and all(opened.values())  # both workers opened the source themselves


def test_a_region_to_quantized_mesh_on_dask_is_the_local_export(
    dask_address: Any, shared_data: Path, tmp_path: Path
) -> None:
    files = _quads(shared_data, tmp_path / "quads")
    want = _export(tmp_path / "local", *files, "--format", "quantized-mesh", extra=("--normals",))
    got = _export(tmp_path / "dask", *files, "--format", "quantized-mesh",
                  extra=("--normals", "--dask", dask_address.scheduler.address))  # fmt: skip
    assert len([k for k in want if k.endswith(".terrain")]) > 10
    assert got == want


def test_a_store_to_both_formats_on_dask_is_the_local_export(
    dask_address: Any, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import terralod.export.distributed as dist
    from terralod.export.tiles3d import Tiles3D
    from terralod.terrain import open_terrain

    dem = _small_dem(tmp_path / "small.tif")
    main(["build", str(dem), "-o", str(tmp_path / "s.terra")])
    store = tmp_path / "s.terra"
    monkeypatch.setattr(dist, "BATCH_TILES", 3)
    monkeypatch.setattr(dist, "BLOCK_NODES", 3)  # a block's neighbourhood is then part of its level
    with open_terrain(store) as terrain:
        view = Tiles3D(terrain)
        finest = max(n.code[0] for n in view.tree)
        level = [n.code for n in view.tree if n.code[0] == finest]
        blocks = list(dist.level_blocks(view, level))
        assert len(blocks) > 2 and all(len(near) < len(level) for _, near in blocks)
    addr = dask_address.scheduler.address
    for fmt in ("3dtiles", "quantized-mesh"):
        want = _export(tmp_path / f"local-{fmt}", store, "--format", fmt)
        got = _export(tmp_path / f"dask-{fmt}", store, "--format", fmt, extra=("--dask", addr))
        assert len(want) > 8
        assert got == want, fmt


def test_an_interrupted_export_resumes_on_dask_to_the_same_bytes(
    dask_address: Any, shared_data: Path, tmp_path: Path
) -> None:
    from terralod.export.quantized_mesh import export_quantized_mesh
    from terralod.export.source import source_from_region

    files = _quads(shared_data, tmp_path / "q")
    want = _export(tmp_path / "want", *files, "--format", "quantized-mesh")
    out = tmp_path / "out"

    def stop(done: int, total: int) -> None:
        if done == 5:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        export_quantized_mesh(source_from_region(files), out, progress=stop, client=dask_address)
    assert not out.exists() and len(list((tmp_path / ".out.work").rglob("*.terrain"))) == 5
    got = _export(out, *files, "--format", "quantized-mesh",
                  extra=("--resume", "--dask", dask_address.scheduler.address))  # fmt: skip
    assert got == want
