"""A region in, whatever its form: several DEM files exported as one quantized-mesh terrain.

A 161² crop of SRTM3 N41E001 (with voids) is cut into four GeoTIFFs that share their edge row and column
as SRTM tiles do; every form of that region (the files, a folder, a glob, a VRT) exports the tiles of the
merged GeoTIFF byte for byte, a gap is nodata (flagged in the water mask, in no declared error), an
unreadable tile is named before anything is written, a part (--bbox, --max-zoom) is the whole export's
tiles, and an interrupted region export resumes to the same bytes. The window-by-window fill equals the
global fill, and a downloaded ``.hgt.zip`` reads as its GeoTIFF.
"""

from __future__ import annotations

import json
import zipfile
from pathlib import Path

import numpy as np
import pytest

from terralod.cli import main

pytest.importorskip("pydelatin")
pytest.importorskip("pyproj")

N = 161  #: samples a side of the merged crop
K = 80  #: the split: tiles [0, K] and [K, N) share row/column K


def _write(path: Path, a: np.ndarray, transform, nodata: float | None = -32768.0) -> Path:  # noqa: ANN001
    import rasterio

    with rasterio.open(path, "w", driver="GTiff", width=a.shape[1], height=a.shape[0], count=1, dtype=a.dtype,
                       crs="EPSG:4326", transform=transform, nodata=nodata, tiled=True, blockxsize=64,
                       blockysize=64, compress="deflate") as ds:  # fmt: skip
        ds.write(a, 1)
    return path


@pytest.fixture(scope="module")
def crop(shared_data: Path) -> tuple[np.ndarray, object]:
    """161² of N41E001 around its voids (int16, nodata -32768) and its transform."""
    import rasterio
    from rasterio.windows import Window

    with rasterio.open(shared_data / "dem" / "srtm3_N41E001.tif") as ds:
        win = Window(900, 400, N, N)
        a = ds.read(1, window=win)
        t = ds.window_transform(win)
    assert (a == -32768).any()
    return a, t


def _quads(crop: tuple[np.ndarray, object], d: Path, skip: str = "") -> list[Path]:
    """The crop as four GeoTIFFs NW, NE, SW, SE sharing row and column K (``skip``: one left out)."""
    from affine import Affine

    a, t = crop
    d.mkdir(exist_ok=True)
    out = []
    for name, r0, c0 in (("nw", 0, 0), ("ne", 0, K), ("sw", K, 0), ("se", K, K)):
        if name == skip:
            continue
        q = a[r0 : (K + 1 if r0 == 0 else N), c0 : (K + 1 if c0 == 0 else N)]
        out.append(_write(d / f"{name}.tif", np.ascontiguousarray(q), t @ Affine.translation(c0, r0)))
    return out


def _export(tmp: Path, name: str, *inputs: str | Path, extra: tuple[str, ...] = ()) -> Path:
    out = tmp / name
    main(["export", *map(str, inputs), "--format", "quantized-mesh", "-o", str(out), *extra])
    return out


def _tiles(out: Path) -> dict[str, bytes]:
    """Every tile and errors.json (layer.json names its input, so it is left out)."""
    got = {str(f.relative_to(out)): f.read_bytes() for f in out.rglob("*.terrain")}
    got["errors.json"] = (out / "errors.json").read_bytes()
    return got


@pytest.fixture(scope="module")
def merged(crop: tuple[np.ndarray, object], tmp_path_factory: pytest.TempPathFactory) -> dict[str, bytes]:
    d = tmp_path_factory.mktemp("merged")
    dem = _write(d / "merged.tif", crop[0], crop[1])
    got = _tiles(_export(d, "out", dem))
    assert len(got) > 10
    return got


def test_every_form_of_a_mosaic_exports_the_merged_tiles(
    crop: tuple[np.ndarray, object], merged: dict[str, bytes], tmp_path: Path
) -> None:
    from terralod.io.region import resolve_region

    files = _quads(crop, tmp_path / "quads")
    assert _tiles(_export(tmp_path, "files", *files)) == merged
    assert _tiles(_export(tmp_path, "folder", tmp_path / "quads")) == merged
    assert _tiles(_export(tmp_path, "glob", str(tmp_path / "quads" / "*.tif"))) == merged
    vrt = resolve_region(files).write_vrt(tmp_path / "region.vrt")
    assert _tiles(_export(tmp_path, "vrt", vrt)) == merged


def test_the_window_fill_is_the_global_fill(crop: tuple[np.ndarray, object], tmp_path: Path) -> None:
    from terralod.fill import fill_nodata
    from terralod.io import region as rg

    a, t = crop
    dem = _write(tmp_path / "m.tif", a, t)
    ok = a != -32768
    want = fill_nodata(a.astype(np.float32), ok).astype(np.float32)
    for block in (rg.FILL_BLOCK, 32):  # one block, and blocks of 32 (with halos) around every void
        old = rg.FILL_BLOCK
        rg.FILL_BLOCK = block
        try:
            reader = rg.RegionReader(rg.resolve_region([dem]))
            z, valid = reader.window(0, N, 0, N)
        finally:
            rg.FILL_BLOCK = old
        assert np.array_equal(valid, ok) and np.array_equal(z, want)


def test_a_gap_is_nodata_flagged_and_in_no_error(crop: tuple[np.ndarray, object], tmp_path: Path) -> None:
    from terralod.export.geodesy import tile_rectangle
    from terralod.export.quantized_mesh_format import decode_tile

    a, t = crop
    holed = a.copy()
    holed[K + 1 :, K + 1 :] = -32768  # the SE file's cells no other file covers
    want = _tiles(_export(tmp_path, "want", _write(tmp_path / "holed.tif", holed, t)))
    got = _tiles(_export(tmp_path, "gap", *_quads(crop, tmp_path / "q", skip="se")))
    assert got == want
    # the finest tiles wholly inside the gap: all water, declared error 0 (no valid sample in them)
    errors = json.loads(got["errors.json"])["tiles"]
    top = max(int(k.split("/")[0]) for k in errors)
    w, s = t.c + (K + 1) * t.a, t.f + N * t.e
    e, n = t.c + N * t.a, t.f + (K + 1) * t.e
    inside = []
    for k in errors:
        z, x, y = map(int, k.split("/"))
        tw, ts, te, tn = tile_rectangle(z, x, y)
        if z == top and tw >= w and te <= e and ts >= s and tn <= n:
            inside.append(k)
            tile = decode_tile(got[f"{k}.terrain"], (tw, ts, te, tn))
            assert tile["watermask"] == 255 and errors[k] == 0.0
    some = [k for k in errors if k.startswith(f"{top}/")]
    masks = [decode_tile(got[f"{k}.terrain"])["watermask"] for k in some]
    assert inside or any(isinstance(m, np.ndarray) and m.any() for m in masks)


def test_an_unreadable_tile_is_named_and_nothing_written(
    crop: tuple[np.ndarray, object], tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    files = _quads(crop, tmp_path / "q")
    bad = files[2]
    data = bytearray(bad.read_bytes())
    data[len(data) // 2 :] = b"\x5a" * (len(data) - len(data) // 2)  # its tiles' compressed bytes garbled
    bad.write_bytes(bytes(data))
    out = tmp_path / "out"
    with pytest.raises(SystemExit) as exc:
        main(["export", *map(str, files), "--format", "quantized-mesh", "-o", str(out)])
    err = capsys.readouterr().err.strip()
    assert exc.value.code == 2 and len(err.splitlines()) == 1 and str(bad) in err, err
    assert not out.exists() and not (tmp_path / ".out.work").exists()


def test_too_little_free_disk_is_refused_before_any_tile(
    crop: tuple[np.ndarray, object],
    tmp_path: Path,
    capsys: pytest.CaptureFixture,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    import collections
    import shutil

    usage = collections.namedtuple("usage", "total used free")
    monkeypatch.setattr(shutil, "disk_usage", lambda p: usage(10**9, 10**9 - 50_000, 50_000))
    with pytest.raises(SystemExit) as exc:
        main(["export", *map(str, _quads(crop, tmp_path / "q")), "--format", "quantized-mesh", "-o",
              str(tmp_path / "o")])  # fmt: skip
    err = capsys.readouterr().err.strip()
    assert exc.value.code == 2 and len(err.splitlines()) == 1 and "free" in err, err
    assert not (tmp_path / "o").exists() and not (tmp_path / ".o.work").exists()


def test_different_resolutions_are_refused_naming_both(
    crop: tuple[np.ndarray, object], tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    from affine import Affine

    a, t = crop
    fine = _write(tmp_path / "fine.tif", a, t)
    coarse = _write(tmp_path / "coarse.tif", a[::2, ::2].copy(), t @ Affine.scale(2.0))
    with pytest.raises(SystemExit) as exc:
        main(["export", str(fine), str(coarse), "--format", "quantized-mesh", "-o", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip()
    assert exc.value.code == 2 and len(err.splitlines()) == 1
    assert str(fine) in err and str(coarse) in err and "resolution" in err
    assert not (tmp_path / "o").exists()


def test_a_part_is_the_whole_exports_tiles(merged: dict[str, bytes], crop: tuple[np.ndarray, object],
                                           tmp_path: Path) -> None:  # fmt: skip
    files = _quads(crop, tmp_path / "q")
    a, t = crop
    box = f"{t.c + 0.01},{t.f - 0.05},{t.c + 0.04},{t.f - 0.01}"
    tops = sorted({int(k.split("/")[0]) for k in merged if k.endswith(".terrain")})
    out = _export(tmp_path, "part", *files, extra=("--bbox", box, "--max-zoom", str(tops[-1] - 1)))
    got = _tiles(out)
    tiles = [k for k in got if k.endswith(".terrain")]
    assert 0 < len(tiles) < len([k for k in merged if k.endswith(".terrain")])
    assert all(got[k] == merged[k] for k in tiles)
    assert max(int(k.split("/")[0]) for k in tiles) == tops[-1] - 1
    layer = json.loads((out / "layer.json").read_text())
    assert layer["maxzoom"] == tops[-1] - 1 and len(layer["available"]) == tops[-1]


def test_an_interrupted_region_export_resumes_to_the_same_bytes(
    merged: dict[str, bytes], crop: tuple[np.ndarray, object], tmp_path: Path
) -> None:
    from terralod.export.quantized_mesh import export_quantized_mesh
    from terralod.export.source import source_from_region

    files = _quads(crop, tmp_path / "q")
    out = tmp_path / "out"

    def stop(done: int, total: int) -> None:
        if done == 5:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        export_quantized_mesh(source_from_region(files), out, progress=stop)
    assert not out.exists() and len(list((tmp_path / ".out.work").rglob("*.terrain"))) == 5
    _export(tmp_path, "out", *files, extra=("--resume",))
    assert _tiles(out) == merged


def test_an_hgt_zip_reads_as_its_geotiff(shared_data: Path, tmp_path: Path) -> None:
    import rasterio

    from terralod.io.region import RegionReader, resolve_region

    tif = shared_data / "dem" / "srtm3_N41E001.tif"
    with rasterio.open(tif) as ds:
        a = ds.read(1)
    hgt = tmp_path / "N41E001.hgt.zip"
    with zipfile.ZipFile(hgt, "w", zipfile.ZIP_DEFLATED) as zf:
        zf.writestr("N41E001.hgt", a.astype(">i2").tobytes())
    rz, rt = resolve_region([hgt]), resolve_region([tif])
    assert rz.transform.almost_equals(rt.transform, precision=1e-12) and rz.shape == rt.shape
    z1, v1 = RegionReader(rz).window(400, 700, 850, 1150)
    z2, v2 = RegionReader(rt).window(400, 700, 850, 1150)
    assert np.array_equal(v1, v2) and np.array_equal(z1, z2)
    # and a part of its export is the GeoTIFF's
    extra = ("--bbox", "1.50,41.50,1.52,41.52", "--min-zoom", "9")
    assert _tiles(_export(tmp_path, "a", hgt, extra=extra)) == _tiles(
        _export(tmp_path, "b", tif, extra=extra)
    )


def test_info_describes_a_region_from_its_headers(crop: tuple[np.ndarray, object], tmp_path: Path) -> None:
    """``terralod info FOLDER`` / a quoted glob: the files, the one grid they make (the shared edge rows
    counted once) and its lon/lat extent, as the export reads them."""
    import json

    from click.testing import CliRunner

    from terralod.cli import cli

    tiles = _quads(crop, tmp_path / "q")
    a, t = crop
    for arg in (str(tiles[0].parent), str(tiles[0].parent / "*.tif")):
        res = CliRunner().invoke(cli, ["info", arg, "--json"])
        assert res.exit_code == 0, res.output
        d = json.loads(res.output)
        assert len(d["files"]) == 4 and d["size"] == [a.shape[1], a.shape[0]]
        w, s, e, n = d["bounds_lonlat"]
        assert w == pytest.approx(t.c) and n == pytest.approx(t.f)
        assert e == pytest.approx(t.c + a.shape[1] * t.a) and s == pytest.approx(t.f + a.shape[0] * t.e)
