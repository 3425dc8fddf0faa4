"""Epochs of one terrain in one store (issue 15): update = fresh build, sharing, killed updates, edits,
epoch listing and deletion, bad inputs, and the change overlay's golden frame.

Small inputs (97 x 113 and 129 x 129 synthetic grids at tile size 17, a subsampled St Helens crater) keep
the file well under 30 s on two cores.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import sqlite3
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import rasterio
from affine import Affine
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from terralod import Heightfield, build_store, open_store
from terralod.pyramid import adaptive
from terralod.pyramid.builder import register_method
from terralod.pyramid.update import update_store

from conftest import fractal_terrain

CRS = "EPSG:32610"
ORIGIN = (500000.0, 5200000.0)


def _hf(z: np.ndarray, spacing: float = 10.0, crs: str | None = CRS, source: str = "<array>") -> Heightfield:
    t = Affine(spacing, 0, ORIGIN[0], 0, -spacing, ORIGIN[1])
    return Heightfield(z.astype(np.float32), np.ones(z.shape, bool), t, crs, source)


def _base(rows: int = 97, cols: int = 113, seed: int = 5) -> np.ndarray:
    return fractal_terrain(rows, cols, seed, relief_m=300.0) + 1000.0


def _rows(path: Path, epoch: str | None = None) -> dict:
    """Every tile row (all columns, checksum included) of one epoch."""
    with open_store(path, epoch=epoch) as s:
        return {c: s.raw_tile(*c) for c in s.tile_codes()}


def _sha(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def write_tif(path: Path, z: np.ndarray, crs: str = CRS, spacing: float = 10.0, origin=ORIGIN) -> Path:
    with rasterio.open(path, "w", driver="GTiff", width=z.shape[1], height=z.shape[0], count=1, dtype="float32",
                       crs=crs, transform=Affine(spacing, 0, origin[0], 0, -spacing, origin[1])) as ds:  # fmt: skip
        ds.write(z.astype(np.float32), 1)
    return path


def run_cli(*args: str) -> subprocess.CompletedProcess:
    """The real ``terralod`` CLI in a fresh process (used where a process boundary matters)."""
    return subprocess.run(
        [sys.executable, "-m", "terralod", *args], capture_output=True, text=True, timeout=300
    )


def _error_lines(p: subprocess.CompletedProcess) -> list[str]:
    """stderr without the progress bar (drawn in-process, where pytest's capture may look like a tty)."""
    return [ln for ln in p.stderr.strip().splitlines() if not ln.startswith(("updating", "editing"))]


def cli(capfd, *args: str) -> subprocess.CompletedProcess:
    """The ``terralod`` entry point in this process (same code path as the command: errors -> one line,
    exit 2), to save a process start per call."""
    from terralod.cli import main

    capfd.readouterr()
    try:
        main(list(args))
        rc = 0
    except SystemExit as exc:
        rc = int(exc.code or 0)
    out, err = capfd.readouterr()
    return subprocess.CompletedProcess(list(args), rc, out, err)


@pytest.fixture(scope="module")
def base_store(tmp_path_factory) -> tuple[Path, np.ndarray]:
    out = tmp_path_factory.mktemp("ep") / "base.terra"
    z = _base()
    build_store(_hf(z), out, tile_size=17, epoch="2000-01-01", workers=2)
    return out, z


# -- update = fresh build ------------------------------------------------------------------------------
@settings(max_examples=4, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    r0=st.integers(0, 90), c0=st.integers(0, 105), h=st.integers(1, 12), w=st.integers(1, 12),
    dz=st.floats(-40.0, 40.0).filter(lambda v: abs(v) > 0.05), data=st.data(),
)  # fmt: skip
def test_update_is_byte_identical_to_fresh_build(
    base_store, tmp_path_factory, r0, c0, h, w, dz, data
) -> None:
    src, z = base_store
    tmp = tmp_path_factory.mktemp("u")
    store = tmp / "s.terra"
    shutil.copy(src, store)
    z2 = z.copy()
    z2[r0 : r0 + h, c0 : c0 + w] += np.float32(dz)
    if data.draw(st.booleans(), label="second patch"):
        z2[-5:, :7] -= np.float32(3.0)
    rep = update_store(_hf(z2), store, "2001-01-01", workers=2)
    assert rep.complete and 0 < rep.tiles_dirty < rep.tiles_total
    fresh = tmp / "fresh.terra"
    with open_store(store) as s:
        quant = s.quantisation
        assert s.epoch == "2001-01-01" and s.epochs == ["2000-01-01", "2001-01-01"]
        method, opts = s.meta["method"], s.meta["build_options"]
    if method == "adaptive":
        # the default ladder is computed from the data: the update meshes with the stated one (the fresh
        # build too, so that the two can be compared bit for bit)
        method = "adaptive_stated_ladder"
        register_method(method, adaptive.mesher_for(opts))
    build_store(_hf(z2), fresh, tile_size=17, quantisation=quant, workers=2, method=method)
    new, ref, old = _rows(store), _rows(fresh), _rows(store, "2000-01-01")
    assert new.keys() == ref.keys() == old.keys()
    assert all(new[c] == ref[c] for c in ref), [c for c in ref if new[c] != ref[c]]
    # every tile whose bytes changed was rebuilt; the rest are the old epoch's rows
    changed = {c for c in ref if ref[c] != old[c]}
    assert changed and changed <= _revs(store, "2001-01-01", rebuilt=True)


def _revs(path: Path, epoch: str, rebuilt: bool) -> set:
    con = sqlite3.connect(path)
    try:
        eid = con.execute("SELECT id FROM epochs WHERE name = ?", (epoch,)).fetchone()[0]
        q = "SELECT level, x, y FROM epoch_tiles WHERE epoch = ? AND rev " + ("= ?" if rebuilt else "!= ?")
        return {tuple(r) for r in con.execute(q, (eid, eid))}
    finally:
        con.close()


def test_chunked_update_identical_and_unchanged_tiles_shared(tmp_path: Path) -> None:
    z = _base(129, 129, 9)
    store, fresh = tmp_path / "c.terra", tmp_path / "f.terra"
    build_store(_hf(z), store, tile_size=17, method="chunked", epoch="a", workers=2)
    z2 = z.copy()
    z2[70:75, 20:30] += 15.0
    rep = update_store(_hf(z2), store, "b", workers=2)
    with open_store(store) as s:
        build_store(_hf(z2), fresh, tile_size=17, method="chunked", quantisation=s.quantisation, workers=2)
    assert _rows(store) == _rows(fresh)
    con = sqlite3.connect(store)
    n_base = con.execute("SELECT count(*) FROM tiles").fetchone()[0]
    n_rev = con.execute("SELECT count(*) FROM tile_revs").fetchone()[0]
    shared = con.execute(
        "SELECT count(*) FROM epoch_tiles e JOIN epochs p ON p.id = e.epoch WHERE p.name = 'b' AND e.rev = 0"
    ).fetchone()[0]
    con.close()
    # one row per tile of the first epoch, one per rebuilt tile: nothing duplicated
    assert n_base == rep.tiles_total and n_rev == rep.tiles_dirty == rep.tiles_built
    assert shared == rep.tiles_total - rep.tiles_dirty > rep.tiles_total // 2
    # the dirty tiles are exactly the ancestors-closed set around the edit: the root and few others
    assert (0, 0, 0) in _revs(store, "b", rebuilt=True)


# -- a killed update -----------------------------------------------------------------------------------
def _snapshot(path: Path) -> dict:
    con = sqlite3.connect(path)
    try:
        return {
            "epochs": con.execute(
                "SELECT id, name, state, info FROM epochs WHERE state = 'complete'"
            ).fetchall(),
            "map": con.execute("SELECT * FROM epoch_tiles ORDER BY 1, 2, 3, 4").fetchall(),
            "tiles": con.execute("SELECT * FROM tiles ORDER BY level, x, y").fetchall(),
            "revs": con.execute("SELECT * FROM tile_revs ORDER BY level, x, y, rev").fetchall(),
            "source": con.execute(
                "SELECT * FROM epoch_source WHERE epoch IN (SELECT id FROM epochs WHERE state = 'complete') "
                "ORDER BY 1, 2"
            ).fetchall(),
        }
    finally:
        con.close()


def test_killed_update_changes_nothing_and_resume_finishes_it(base_store, tmp_path: Path, capfd) -> None:
    src, z = base_store
    store, ref = tmp_path / "k.terra", tmp_path / "r.terra"
    shutil.copy(src, store)
    shutil.copy(src, ref)
    z2 = z.copy()
    z2[10:60, 10:80] += 25.0  # many dirty tiles: several batches
    dem = write_tif(tmp_path / "after.tif", z2)
    before = _snapshot(store)
    # a real kill (os._exit, no clean-up) right after the first committed batch of rebuilt tiles
    code = (
        "import os, sys\n"
        "from terralod.io.reader import read_heightfield\n"
        "from terralod.pyramid.update import update_store\n"
        "def cb(done, total):\n"
        "    if done >= 16: os._exit(9)\n"
        f"update_store(read_heightfield({str(dem)!r}), {str(store)!r}, '2002-02-02', progress=cb, workers=2)\n"
    )
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert p.returncode == 9, p.stderr[-2000:]
    after = _snapshot(store)
    assert after["epochs"] == before["epochs"] and after["map"] == before["map"]
    assert after["tiles"] == before["tiles"] and after["source"] == before["source"]
    assert len(after["revs"]) >= 16  # the interrupted epoch's rows, invisible to readers
    with open_store(store) as s:
        assert s.epochs == ["2000-01-01"] and s.epoch == "2000-01-01"
        assert [p for p in s.verify_epochs() if "interrupted update" in p]
    assert _rows(store) == _rows(src)
    # without --resume: one line, nothing changed; with it: finished, identical to an uninterrupted update
    p = cli(capfd, "update", str(store), str(dem), "--epoch", "2002-02-02")
    assert p.returncode == 2 and "--resume" in _error_lines(p)[0] and len(_error_lines(p)) == 1
    p = cli(capfd, "update", str(store), str(dem), "--epoch", "2002-02-02", "--resume")
    assert p.returncode == 0, p.stderr
    update_store(_hf(z2, source=str(dem)), ref, "2002-02-02", workers=1)
    assert _rows(store) == _rows(ref)
    assert _rows(store, "2000-01-01") == _rows(src)
    with open_store(store) as s:
        assert s.verify_epochs() == []
    # a damaged source block is found
    con = sqlite3.connect(store)
    with con:
        con.execute("UPDATE source_blocks SET data = ? WHERE digest = (SELECT digest FROM source_blocks LIMIT 1)",
                    (b"x",))  # fmt: skip
    con.close()
    with open_store(store) as s:
        assert any("fails its checksum" in p for p in s.verify_epochs())


def test_reader_keeps_its_epoch_while_an_update_commits(base_store, tmp_path: Path) -> None:
    src, z = base_store
    store = tmp_path / "r.terra"
    shutil.copy(src, store)
    reader = open_store(store)
    old = {c: reader.raw_tile(*c) for c in reader.tile_codes()}
    z2 = z.copy()
    z2[40:50, 40:50] -= 20.0
    update_store(_hf(z2), store, "later", workers=2)
    assert reader.epoch == "2000-01-01"
    assert {c: reader.raw_tile(*c) for c in reader.tile_codes()} == old
    reader.close()
    with open_store(store) as s:
        assert s.epoch == "later"


# -- edits ---------------------------------------------------------------------------------------------
def _square(x0: float, y0: float, side: float, crs: str | None = CRS) -> dict:
    ring = [[x0, y0], [x0 + side, y0], [x0 + side, y0 + side], [x0, y0 + side], [x0, y0]]
    doc = {"type": "FeatureCollection",
           "features": [{"type": "Feature", "properties": {"name": "pit"},
                         "geometry": {"type": "Polygon", "coordinates": [ring]}}]}  # fmt: skip
    if crs:
        doc["crs"] = {"type": "name", "properties": {"name": crs}}
    return doc


def test_edit_polygon_touches_only_its_tiles_and_removes_depth_times_area(
    base_store, tmp_path: Path, capfd
) -> None:
    from terralod.change.epochs import edit_store, epoch_heightfield, polygon_area_m2, read_polygons
    from terralod.pyramid.update import dirty_tiles

    src, z = base_store
    store = tmp_path / "e.terra"
    shutil.copy(src, store)
    # a 212 m x 212 m pit (not cell-aligned) in the north-west, dug 12 m
    cut = tmp_path / "cut.geojson"
    cut.write_text(json.dumps(_square(ORIGIN[0] + 103.0, ORIGIN[1] - 420.0, 212.0)))
    res, rep = edit_store(store, polygon=cut, depth_m=12.0, workers=2)
    assert rep.complete and rep.epoch == "edit-1"
    area = polygon_area_m2(read_polygons(cut, CRS))
    cells_m2 = res.description["cells"] * 100.0
    assert res.volume_m3 == pytest.approx(-12.0 * cells_m2, rel=1e-6)
    # the cells inside differ from the polygon by at most half a cell along its outline
    assert abs(cells_m2 - area) <= 0.5 * (4 * 212.0) * 10.0
    assert abs(-res.volume_m3 - 12.0 * area) <= 12.0 * 0.5 * 4 * 212.0 * 10.0
    new = epoch_heightfield(store, "edit-1").elevation_m
    assert np.array_equal(new != z, res.changed)
    assert np.allclose((z - new)[res.changed], 12.0, atol=1e-3)
    with open_store(store) as s:
        expect = dirty_tiles(s.pyramid, res.changed, "cohesion")
    assert _revs(store, "edit-1", rebuilt=True) == expect
    assert len(expect) < rep.tiles_total // 2
    # a fill with the CLI: negative depth, named epoch
    p = cli(capfd, "edit", str(store), "--polygon", str(cut), "--depth-m", "-12", "--epoch", "dam")
    assert p.returncode == 0, p.stderr
    back = epoch_heightfield(store, "dam").elevation_m
    assert np.allclose(back, z, atol=1e-3)


def test_edit_patch_and_lonlat_polygon(base_store, tmp_path: Path) -> None:
    from pyproj import Transformer

    from terralod.change.epochs import edit_store, epoch_heightfield

    src, z = base_store
    store = tmp_path / "p.terra"
    shutil.copy(src, store)
    patch = np.full((6, 8), 1500.0, np.float32)
    pt = write_tif(tmp_path / "slide.tif", patch, origin=(ORIGIN[0] + 300.0, ORIGIN[1] - 300.0))
    res, rep = edit_store(store, patch=pt, epoch="slide", workers=2)
    hf = epoch_heightfield(store, "slide")
    assert np.allclose(hf.elevation_m[30:36, 30:38], 1500.0) and res.description["cells"] == 48
    # a polygon given in lon/lat (RFC 7946) is transformed to the store's CRS
    to_ll = Transformer.from_crs(CRS, "EPSG:4326", always_xy=True)
    x0, y0 = ORIGIN[0] + 500.0, ORIGIN[1] - 800.0
    ring = [
        list(to_ll.transform(x, y))
        for x, y in [(x0, y0), (x0 + 100, y0), (x0 + 100, y0 + 100), (x0, y0 + 100), (x0, y0)]
    ]
    gj = tmp_path / "ll.geojson"
    gj.write_text(json.dumps({"type": "Polygon", "coordinates": [ring]}))
    res2, _ = edit_store(store, polygon=gj, depth_m=5.0, epoch="ll", workers=2)
    assert 80 <= res2.description["cells"] <= 121


# -- listing, deleting, bad input ----------------------------------------------------------------------
def test_epochs_listing_and_deleting(base_store, tmp_path: Path, capfd) -> None:
    src, z = base_store
    store = tmp_path / "d.terra"
    shutil.copy(src, store)
    z1, z2 = z.copy(), z.copy()
    z1[5:15, 5:15] += 10.0
    z2[80:90, 90:100] += 10.0
    update_store(_hf(z1), store, "2001", workers=2)
    update_store(_hf(z2), store, "2002", workers=2)
    first, last = _rows(store, "2000-01-01"), _rows(store, "2002")
    n_rev_before = _count(store, "SELECT count(*) FROM tile_revs")
    p = cli(capfd, "epochs", str(store), "--json")
    assert p.returncode == 0, p.stderr
    assert [e["name"] for e in json.loads(p.stdout)] == ["2000-01-01", "2001", "2002"]
    p = cli(capfd, "info", str(store))
    assert p.returncode == 0 and "3 epochs" in p.stdout and "2001" in p.stdout
    p = cli(capfd, "epochs", str(store), "--delete", "2001")
    assert p.returncode == 0, p.stderr
    with open_store(store) as s:
        assert s.epochs == ["2000-01-01", "2002"]
    assert _rows(store, "2000-01-01") == first and _rows(store, "2002") == last
    # the rows only 2001 used are gone (2002 shares some of 2001's rebuilt tiles: those stay)
    orphans = _count(store, "SELECT count(*) FROM tile_revs t WHERE NOT EXISTS (SELECT 1 FROM epoch_tiles e "
                            "WHERE e.level=t.level AND e.x=t.x AND e.y=t.y AND e.rev=t.rev)")  # fmt: skip
    assert orphans == 0 and _count(store, "SELECT count(*) FROM tile_revs") < n_rev_before
    for bad in ("2001", "nope"):
        p = cli(capfd, "epochs", str(store), "--delete", bad)
        assert p.returncode == 2 and "has no epoch" in p.stderr
    cli(capfd, "epochs", str(store), "--delete", "2000-01-01")
    sha = _sha(store)
    p = cli(capfd, "epochs", str(store), "--delete", "2002")
    assert p.returncode == 2 and "only epoch" in p.stderr and _sha(store) == sha


def _count(path: Path, sql: str) -> int:
    con = sqlite3.connect(path)
    try:
        return int(con.execute(sql).fetchone()[0])
    finally:
        con.close()


def test_bad_inputs_one_line_store_untouched(base_store, tmp_path: Path, capfd) -> None:
    src, z = base_store
    store = tmp_path / "b.terra"
    shutil.copy(src, store)
    sha = _sha(store)
    same = write_tif(tmp_path / "same.tif", z)
    other_grid = write_tif(tmp_path / "grid.tif", z[:, :-1])
    other_crs = write_tif(tmp_path / "crs.tif", z, crs="EPSG:32611")
    shifted = write_tif(tmp_path / "shift.tif", z, origin=(ORIGIN[0] + 5.0, ORIGIN[1]))
    outside = tmp_path / "far.geojson"
    outside.write_text(json.dumps(_square(ORIGIN[0] + 1e5, ORIGIN[1] + 1e5, 100.0)))
    cases = [
        (("update", str(store), str(same), "--epoch", "2000-01-01"), "exists already"),
        (("update", str(store), str(other_grid), "--epoch", "x"), "grid"),
        (("update", str(store), str(shifted), "--epoch", "x"), "grid"),
        (("update", str(store), str(other_crs), "--epoch", "x"), "CRS"),
        (("edit", str(store), "--polygon", str(outside), "--depth-m", "3"), "outside the terrain"),
        (("update", str(tmp_path / "missing.terra"), str(same), "--epoch", "x"), "not found"),
    ]
    for i, (args, msg) in enumerate(cases):
        p = run_cli(*args) if i == 0 else cli(capfd, *args)  # one in a real process: the whole stderr
        assert p.returncode == 2, (args, p.stderr)
        lines = p.stderr.strip().splitlines() if i == 0 else _error_lines(p)
        assert len(lines) == 1 and lines[0].startswith("terralod: ") and msg in lines[0], (args, p.stderr)
        assert _sha(store) == sha, args
    # a store without epochs (built before them) opens as before and can take a first update
    plain = tmp_path / "plain.terra"
    from terralod.io.reader import read_heightfield

    build_store(read_heightfield(same), plain, tile_size=17, workers=2)
    with open_store(plain) as s:
        assert s.epochs == [] and s.epoch is None
    z2 = z.copy()
    z2[1:3, 1:3] += 2.0
    rep = update_store(_hf(z2, crs=read_heightfield(same).crs), plain, "after", workers=2)
    with open_store(plain) as s:
        assert s.epochs == ["base", "after"] and rep.tiles_dirty < rep.tiles_total


# -- the change overlay --------------------------------------------------------------------------------
def test_change_overlay_golden(shared_data: Path, tmp_path: Path) -> None:
    """St Helens 2000 -> 2007 subsampled 2x: the dome (gain, blue) in the crater, a legend in metres."""
    from PIL import Image

    from terralod.io.reader import read_heightfield
    from terralod.render.overlay import change_overlay
    from terralod.render.timelapse import epoch_frame, orbit_pose

    _mesa = "/usr/share/glvnd/egl_vendor.d/50_mesa.json"
    if os.path.exists(_mesa):
        os.environ.setdefault("__EGL_VENDOR_LIBRARY_FILENAMES", _mesa)
    a = read_heightfield(shared_data / "change/st_helens_crater_2000-09-25_10m.tif")
    b = read_heightfield(shared_data / "change/st_helens_crater_2007-07-05_10m.tif")

    def sub(hf):
        t = hf.transform @ Affine.scale(2.0)
        return Heightfield(hf.elevation_m[::2, ::2], hf.valid[::2, ::2], t, hf.crs, hf.source)

    store = tmp_path / "sh.terra"
    build_store(sub(a), store, tile_size=33, epoch="2000-09-25", workers=2)
    update_store(sub(b), store, "2007-07-05", workers=2)
    import terralod

    with terralod.open(store) as t:
        ov = change_overlay(t, lod_m=1.0)
        assert ov.max_m == 200.0 and ov.before == "2000-09-25"
        img = epoch_frame(t, None, orbit_pose(t, 20.0), 160, 96, overlay="change", caption=False)
        plain = epoch_frame(t, None, orbit_pose(t, 20.0), 160, 96, caption=False)
    sky = np.abs(plain.astype(int) - plain[0, 0].astype(int)).sum(axis=2) < 12
    assert 0.1 < (~sky).mean() < 0.9

    def blue(im: np.ndarray) -> int:
        return int(((im[..., 2].astype(int) - im[..., 0] > 50) & ~sky).sum())

    assert blue(img) > 200 and blue(plain) < blue(img) // 10
    Image.fromarray(np.concatenate([img, plain], axis=1)).save(tmp_path / "overlay_and_plain.png")
    golden = Path(__file__).resolve().parent / "golden" / "epochs_overlay_change.png"
    if os.environ.get("TERRALOD_REGEN_GOLDEN") or not golden.exists():
        Image.fromarray(img).save(golden)
    ref = np.asarray(Image.open(golden).convert("RGB")).astype(np.int16)
    diff = np.abs(ref - img.astype(np.int16))
    assert diff.mean() < 1.5 and np.percentile(diff.max(axis=2), 99.5) < 40


# -- the viewer's epoch controls -----------------------------------------------------------------------
def test_slider_and_ground_pick_headless() -> None:
    from terralod.render.renderer import look_at, perspective
    from terralod.render.viewer_epochs import pick_ground, slider_geometry, slider_hit, slider_image

    x0, y0, w, h = slider_geometry(800, 500)
    n = 27
    hits = [slider_hit(x0 + 18 + (w - 36) * i / (n - 1), y0 + 10, n, 800, 500) for i in range(n)]
    assert hits == list(range(n)) and slider_hit(x0 - 5, y0 + 10, n, 800, 500) is None
    assert slider_image([f"2004-10-{d:02d}" for d in range(1, 28)], 5, 800, 500, False).shape == (h, w, 4)
    # the ray through the pixel where a ground point projects meets the ground at that point
    z = _base(97, 113, 3)
    hf = _hf(z)
    r, c = 40, 61
    gx, gy = hf.world_xy(r, c)
    p = np.array([float(gx), float(gy), float(z[r, c])])
    eye = p + np.array([-200.0, -300.0, 1500.0])  # steep: no ridge between the eye and the point
    target = p
    vp = perspective(45.0, 640 / 400, 1.0, 1e5) @ look_at(eye, target, np.array([0.0, 0, 1]))
    q = vp @ np.append(p - eye, 1.0)
    px, py = (q[0] / q[3] + 1) / 2 * 640 - 0.5, (1 - q[1] / q[3]) / 2 * 400 - 0.5
    hit = pick_ground(eye, target, 45.0, 640, 400, px, py, hf)
    assert hit is not None and np.hypot(hit[0] - p[0], hit[1] - p[1]) <= 15.0
    assert pick_ground(eye, eye + np.array([0.0, 0.0, 1.0]) + [1, 0, 0], 45.0, 640, 400, 320, 10, hf) is None


@pytest.mark.skipif(shutil.which("xvfb-run") is None, reason="xvfb-run not installed (Debian package xvfb)")
def test_viewer_epoch_slider_overlay_and_cursor(base_store, tmp_path: Path) -> None:
    src, z = base_store
    store = tmp_path / "v.terra"
    shutil.copy(src, store)
    z2 = z.copy()
    z2[30:60, 40:80] += 60.0
    update_store(_hf(z2), store, "2001-06-30", workers=2)
    script = tmp_path / "v.py"
    script.write_text(
        "import json, sys\n"
        "import terralod\n"
        "from terralod.render.viewer import Viewer\n"
        "from terralod.render.viewer_epochs import slider_geometry\n"
        "v = Viewer(terralod.open(sys.argv[1]), width_px=480, height_px=300)\n"
        "g = v.glfw\n"
        "v.run(max_frames=2)\n"
        "out = {'start': v.epochs.epoch}\n"
        "v._on_key(v.window, g.KEY_PAGE_UP, 0, g.PRESS, 0)\n"
        "out['page_up'] = v.epochs.epoch\n"
        "v._on_key(v.window, g.KEY_RIGHT_BRACKET, 0, g.PRESS, 0)\n"
        "v._on_key(v.window, g.KEY_C, 0, g.PRESS, 0)\n"
        "v._mouse = (240.0, 150.0)\n"
        "r = v.run(max_frames=5, screenshot=sys.argv[2])\n"
        "out['hud'] = r['hud']; out['overlay'] = v.settings.overlay is not None\n"
        "x0, y0, w, h = slider_geometry(480, 300)\n"
        "v._mouse = (x0 + 18, y0 + 14)\n"
        "v._on_button(v.window, g.MOUSE_BUTTON_LEFT, g.PRESS, 0)\n"
        "out['click'] = v.epochs.epoch\n"
        "v.close()\n"
        "print(json.dumps(out))\n"
    )
    shot = tmp_path / "shot.png"
    env = {k: v for k, v in os.environ.items() if k != "DISPLAY"}
    p = subprocess.run(["xvfb-run", "-a", "-s", "-screen 0 1024x768x24", sys.executable, str(script), str(store),
                        str(shot)], capture_output=True, text=True, timeout=300, env=env)  # fmt: skip
    assert p.returncode == 0, p.stderr[-2000:]
    out = json.loads(p.stdout.strip().splitlines()[-1])
    assert out["start"] == "2001-06-30" and out["page_up"] == "2000-01-01" and out["click"] == "2000-01-01"
    assert out["overlay"] and any("30 Jun 2001  (2 of 2)" in ln for ln in out["hud"])
    cursor = [ln for ln in out["hud"] if ln.startswith("under cursor: elevation")]
    assert cursor and "change" in cursor[0] and "since 1 Jan 2000" in cursor[0]
    assert shot.exists()


def test_adaptive_update_keeps_the_stated_ladder(tmp_path: Path) -> None:
    """The adaptive TIN plans its error ladder from the first epoch (build_options): an update meshes with
    that ladder, so it equals a fresh build with the same ladder and quantisation."""
    from terralod.pyramid.adaptive import mesher_for
    from terralod.pyramid.builder import METHODS, register_method

    z = _base(97, 113, 5)
    store, fresh = tmp_path / "a.terra", tmp_path / "f.terra"
    build_store(_hf(z), store, tile_size=17, method="adaptive", epoch="a", workers=2)
    z2 = z.copy()
    z2[10:20, 10:20] += 30.0
    rep = update_store(_hf(z2), store, "b", workers=2)
    assert 0 < rep.tiles_dirty < rep.tiles_total
    with open_store(store) as s:
        quant, opts = s.quantisation, s.meta["build_options"]
    register_method("_adaptive_stated", mesher_for(opts))
    try:
        build_store(_hf(z2), fresh, tile_size=17, method="_adaptive_stated", quantisation=quant, workers=2)
    finally:
        METHODS.pop("_adaptive_stated", None)
    assert _rows(store) == _rows(fresh)


def test_log_attraction_margin_rebuilds_tiles_whose_roughness_window_changed(tmp_path: Path) -> None:
    """The cohesion map with LoG attraction reads roughness 2 strides around a tile: a change just outside
    tile (1, 0, 0)'s own samples changes that tile, so the update must (and does) rebuild it."""
    from terralod.pyramid.builder import METHODS, register_method
    from terralod.pyramid.cohesion import make_mesher

    register_method("_cohesion_log", make_mesher(attraction="log"))
    try:
        z = _base(97, 113, 5)
        store, fresh = tmp_path / "l.terra", tmp_path / "f.terra"
        build_store(_hf(z), store, tile_size=17, method="_cohesion_log", epoch="a", workers=2)
        z2 = z.copy()
        z2[2:62, 67] -= 50.0  # 3 columns east of the tile's last (64), inside its 8-sample margin
        update_store(_hf(z2), store, "b", workers=2)
        with open_store(store) as s:
            build_store(
                _hf(z2), fresh, tile_size=17, method="_cohesion_log", quantisation=s.quantisation, workers=2
            )
        new, ref, old = _rows(store), _rows(fresh), _rows(store, "a")
    finally:
        METHODS.pop("_cohesion_log", None)
    assert ref[(1, 0, 0)] != old[(1, 0, 0)] and (1, 0, 0) in _revs(store, "b", rebuilt=True)
    assert new == ref
