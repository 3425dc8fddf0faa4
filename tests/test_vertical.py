"""Vertical datums: EGM96 heights made ellipsoidal by PROJ, checked against NGA's published EGM96 test values
(an independent source: the geoid's own publisher), never a silent "ballpark" no-op."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("pyproj")

from terralod.errors import InputError  # noqa: E402
from terralod.export.vertical import (  # noqa: E402
    GeoidConverter,
    resolve_vertical_datum,
    vertical_datum_from_crs,
)

#: NGA's EGM96 test points (latitude, longitude east 0-360 degrees, undulation N metres), from the
#: EGM96 distribution's own check file (INPUT.DAT / OUTINTPT.DAT of the 15' interpolation program).
NGA_EGM96 = [
    (38.6281550, 269.7791550, -31.628),
    (-14.6212170, 305.0211140, -2.969),
    (46.8743190, 102.4487290, -43.575),
    (-23.6174460, 133.8747120, 15.871),
    (38.6254730, 359.9995000, 50.066),
    (-0.4667440, 0.0023000, 17.329),
]


def _egm96() -> GeoidConverter:
    try:
        conv = resolve_vertical_datum("egm96").converter()
    except InputError as exc:
        pytest.skip(f"PROJ has no EGM96 grid here ({exc}); scripts/install.sh installs Debian's proj-data")
    assert conv is not None
    return conv


def test_egm96_undulation_matches_nga_test_values() -> None:
    conv = _egm96()
    lat = np.array([p[0] for p in NGA_EGM96])
    lon = np.array([p[1] for p in NGA_EGM96])
    lon = np.where(lon > 180.0, lon - 360.0, lon)
    n = conv.undulation_m(lon, lat)
    expect = np.array([p[2] for p in NGA_EGM96])
    assert np.all(np.abs(n) > 1.0)  # never the ballpark no-op
    # the 15' grid interpolated bilinearly against NGA's spherical-harmonic values: a few centimetres
    assert np.max(np.abs(n - expect)) < 0.1, n - expect
    h = conv.to_ellipsoidal(lon, lat, np.full(lon.shape, 100.0))
    np.testing.assert_allclose(h, 100.0 + n)


def test_liguria_offshore_is_about_fifty_metres() -> None:
    n = float(_egm96().undulation_m(np.array([9.0]), np.array([44.0]))[0])
    assert 45.0 < n < 55.0, n


def test_what_an_output_records_names_the_operation() -> None:
    js = _egm96().to_json()
    assert js["datum"] == "egm96" and js["said_by"] == "option"
    assert "EGM96" in js["operation"] and "ballpark" not in js["operation"].lower()
    assert js["converted_to"].startswith("WGS 84 ellipsoid")


@pytest.mark.parametrize(
    ("crs", "key"),
    [("EPSG:32610+5703", "navd88"), ("EPSG:4326+5773", "egm96"), ("EPSG:4979", "ellipsoid"), ("EPSG:32633", None), ("EPSG:4326", None),
     ("EPSG:32633", None)],
)  # fmt: skip
def test_the_datum_a_crs_names(crs: str, key: str | None) -> None:
    d = vertical_datum_from_crs(crs)
    assert (d.key if d else None) == key
    if d:
        assert d.said_by == "file"


def test_option_wins_and_unknown_is_said() -> None:
    assert resolve_vertical_datum("EGM96", "EPSG:4979").key == "egm96"
    unknown = resolve_vertical_datum(None, "EPSG:4326")
    assert not unknown.known and unknown.converter() is None and not unknown.above_sea_level
    assert resolve_vertical_datum("ellipsoid").converter() is None


def test_a_bad_datum_is_one_clear_line(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="--vertical-datum: expected one of"):
        resolve_vertical_datum("mean-sea-level", where="dem.tif")
    with pytest.raises(InputError, match="not a vertical CRS"):
        resolve_vertical_datum("EPSG:4326")
    junk = tmp_path / "geoid.gtx"
    junk.write_bytes(b"not a grid")
    with pytest.raises(InputError, match="cannot be used by PROJ|gives no value"):
        resolve_vertical_datum(str(junk)).converter()


# -- the web exports write ellipsoidal heights when the datum is known --------------------------------------
def _liguria_store(tmp_path: Path, vertical_datum: str | None) -> Path:
    """A small synthetic DEM on the Ligurian coast (UTM 32N), about 48 m of EGM96 undulation."""
    import rasterio
    from rasterio.transform import from_origin

    from terralod.io.reader import read_heightfield
    from terralod.pyramid.builder import build_store

    r, c = np.mgrid[0:65, 0:65]
    z = (300.0 + 80.0 * np.sin(r / 9.0) * np.cos(c / 7.0)).astype("float32")
    tif = tmp_path / "lig.tif"
    with rasterio.open(tif, "w", driver="GTiff", width=65, height=65, count=1, dtype="float32",
                       crs="EPSG:32632", transform=from_origin(500000.0, 4880000.0, 30.0, 30.0)) as ds:  # fmt: skip
        ds.write(z, 1)
    out = tmp_path / f"lig-{vertical_datum}.terra"
    build_store(read_heightfield(tif, vertical_datum=vertical_datum), out, tile_size=33)
    return out


def test_3dtiles_heights_are_ellipsoidal_with_a_known_datum(tmp_path: Path) -> None:
    pytest.importorskip("pygltflib")
    from pyproj import Transformer
    from scipy.spatial import cKDTree
    from tests.test_tiles_bytes import decode_glb

    from terralod.export.tiles3d import Tiles3D
    from terralod.terrain import open_terrain

    conv = _egm96()
    geo = open_terrain(_liguria_store(tmp_path, "egm96"))
    plain = open_terrain(_liguria_store(tmp_path, None))
    view, ref = Tiles3D(geo), Tiles3D(plain)
    to_ecef = Transformer.from_crs("EPSG:4979", "EPSG:4978", always_xy=True)
    to_ll = Transformer.from_crs(geo.crs, "EPSG:4326", always_xy=True)
    assert view.tileset()["extras"]["terralod"]["heights"]["datum"] == "egm96"
    assert "EGM96" in view.tileset()["extras"]["terralod"]["heights"]["operation"]
    assert ref.tileset()["extras"]["terralod"]["heights"]["datum"] == "unknown"
    for code in list(view.nodes)[:6]:
        v, t, _ = view.mesh(code)
        v = np.asarray(v)[np.unique(t)]
        pos, _, _, gl = decode_glb(view.glb(code))
        drawn = np.column_stack([pos[:, 0], -pos[:, 2], pos[:, 1]]) + view._centre(view.nodes[code])
        lon, lat = to_ll.transform(v[:, 0], v[:, 1])
        n = conv.undulation_m(lon, lat)
        assert np.all(n > 40.0)  # the undulation is applied, not a ballpark no-op
        # every stored vertex is drawn at its height + N (pyproj's own ECEF), within the glb's encoding bound
        want = np.column_stack(to_ecef.transform(lon, lat, v[:, 2] + n))
        miss = cKDTree(drawn).query(want)[0]
        assert miss.max() <= gl["extras"]["encoding_error_m"] + 1e-3, miss.max()
        assert view.error_m(code) >= ref.error_m(code)  # N's spread over the tile is added, never less
        assert view.error_m(code) - ref.error_m(code) < 1.0  # a 2 km tile: N moves by centimetres


def _geographic_dem(tmp_path: Path) -> Path:
    """A small EPSG:4326 DEM on the Ligurian coast (about 48 m of EGM96 undulation)."""
    import rasterio
    from rasterio.transform import from_origin

    r, c = np.mgrid[0:121, 0:121]
    z = (400.0 + 150.0 * np.sin(r / 11.0) * np.cos(c / 9.0)).astype("float32")
    tif = tmp_path / "lig_ll.tif"
    with rasterio.open(tif, "w", driver="GTiff", width=121, height=121, count=1, dtype="float32",
                       crs="EPSG:4326", transform=from_origin(8.9, 44.4, 0.001, 0.001)) as ds:  # fmt: skip
        ds.write(z, 1)
    return tif


@pytest.mark.parametrize("kind", ["store", "dem"])
def test_quantized_mesh_heights_are_ellipsoidal_and_errors_hold(tmp_path: Path, kind: str) -> None:
    """Decoded tile heights = the DEM's heights + N (independently: matplotlib's linear interpolation of the
    decoded tile at every DEM sample, against the sample's height + NGA-checked EGM96 N), within each tile's
    declared error; layer.json names the operation."""
    import json

    import matplotlib.tri as mtri
    import rasterio
    from pyproj import Transformer

    from terralod.export.quantized_mesh import decode_tile, export_quantized_mesh, tile_rectangle
    from terralod.export.source import source_from_dem
    from terralod.terrain import open_terrain

    conv = _egm96()
    if kind == "store":
        store = _liguria_store(tmp_path, None)
        src_tif, terrain = tmp_path / "lig.tif", open_terrain(store)
    else:
        src_tif = _geographic_dem(tmp_path)
        terrain = source_from_dem(src_tif)
    out = tmp_path / f"qm-{kind}"
    export_quantized_mesh(terrain, out, vertical_datum="egm96")
    layer = json.loads((out / "layer.json").read_text())
    assert layer["terralod"]["heights"]["datum"] == "egm96"
    assert "EGM96" in layer["terralod"]["heights"]["operation"]
    declared = json.loads((out / "errors.json").read_text())["tiles"]
    with rasterio.open(src_tif) as ds:
        z = ds.read(1).astype(np.float64)
        t, crs = ds.transform, ds.crs
    rr, cc = np.mgrid[0 : z.shape[0], 0 : z.shape[1]]
    x, y = t.c + (cc.ravel() + 0.5) * t.a, t.f + (rr.ravel() + 0.5) * t.e
    lon, lat = Transformer.from_crs(crs, "EPSG:4326", always_xy=True).transform(x, y)
    lon, lat = np.asarray(lon), np.asarray(lat)
    h_ell = z.ravel() + conv.undulation_m(lon, lat)
    zmax = max(int(k.split("/")[0]) for k in declared)
    checked = 0
    for key, err in declared.items():
        zz, xx, yy = (int(v) for v in key.split("/"))
        if zz != zmax:
            continue
        rect = tile_rectangle(zz, xx, yy)
        d = decode_tile((out / str(zz) / str(xx) / f"{yy}.terrain").read_bytes(), rect)
        inside = (lon >= rect[0]) & (lon <= rect[2]) & (lat >= rect[1]) & (lat <= rect[3])
        if not inside.any():
            continue
        tri = mtri.Triangulation(d["lon"], d["lat"], np.asarray(d["triangles"]))
        surf = np.ma.filled(mtri.LinearTriInterpolator(tri, d["height"])(lon[inside], lat[inside]), np.nan)
        ok = np.isfinite(surf)
        assert np.nanmedian(surf[ok] - z.ravel()[inside][ok]) > 40.0  # the undulation is in the tile
        assert np.max(np.abs(surf[ok] - h_ell[inside][ok])) <= err + 0.05, (key, err)
        checked += 1
    assert checked >= 1
