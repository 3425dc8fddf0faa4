"""Store integrity and protected outputs: ``terralod check`` (0 sound / 2 with one line per problem,
``--repair`` + ``--resume``, ``--upgrade``), the metadata checksum, no ``-wal``/``-shm`` left by readers,
the one ``-o``/``--overwrite`` rule (never onto an input: same path, hard link, symlink), and the inputs
that used to be accepted without a word. The CLI runs in-process (``terralod.cli.main``)."""

from __future__ import annotations

import os
import sqlite3
from pathlib import Path

import numpy as np
import pytest
import rasterio
from rasterio.transform import from_origin

from terralod import build_store, open_store, read_heightfield
from terralod.cli import main
from terralod.errors import CorruptStoreError, InputError, StoreError
from terralod.integrity import check_store
from terralod.store import FORMAT_VERSION, TileStore, seal_meta

from conftest import fractal_terrain


def cli(capsys: pytest.CaptureFixture, *args: str) -> tuple[int, str, str]:
    try:
        main(list(args))
        code = 0
    except SystemExit as exc:
        code = int(exc.code or 0)
    out = capsys.readouterr()
    return code, out.out, out.err


def one_line(err: str, *needles: str) -> str:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("terralod: "), err
    for n in needles:
        assert n in lines[0], (n, lines[0])
    return lines[0]


def _tif(path: Path, z: np.ndarray, crs: str = "EPSG:32610", res: float = 30.0, nodata=None, x0=500000.0,
         y0=5200000.0) -> Path:  # fmt: skip
    with rasterio.open(path, "w", driver="GTiff", width=z.shape[1], height=z.shape[0], count=1, dtype=z.dtype,
                       crs=crs, transform=from_origin(x0, y0, res, res), nodata=nodata) as ds:  # fmt: skip
        ds.write(z, 1)
    return path


@pytest.fixture(scope="module")
def built(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    d = tmp_path_factory.mktemp("integrity")
    src = _tif(d / "dem.tif", fractal_terrain(60, 52, 4).astype(np.float32))
    out = d / "dem.terra"
    build_store(read_heightfield(src), out, tile_size=9, workers=1)
    return src, out


def _copy(p: Path, to: Path) -> Path:
    to.write_bytes(p.read_bytes())
    return to


def test_check_sound_store(built, capsys) -> None:
    src, store = built
    code, out, err = cli(capsys, "check", str(store))
    assert code == 0 and "verdict: sound" in out and "shared borders" in out, (out, err)
    assert not Path(f"{store}-wal").exists() and not Path(f"{store}-shm").exists()  # readers leave nothing


def test_check_repair_resume(built, tmp_path: Path, capsys) -> None:
    src, store = built
    s = _copy(store, tmp_path / "c.terra")
    con = sqlite3.connect(s)
    blob = bytearray(con.execute("SELECT vertices FROM tiles WHERE level=2 AND x=1 AND y=0").fetchone()[0])
    blob[3] ^= 0x40
    con.execute("UPDATE tiles SET vertices=? WHERE level=2 AND x=1 AND y=0", (bytes(blob),))
    con.execute("UPDATE tiles SET error_m = 0 WHERE level=1 AND x=0 AND y=0")  # not monotone, and a bad CRC
    con.commit()
    con.close()
    # info reads every row's checksum: it no longer calls such a store "complete" and exits 2
    code, out, err = cli(capsys, "info", str(s))
    assert code == 2 and "2 tile(s) FAIL their checksums" in out, (out, err)
    one_line(err, "2 tile(s) fail their checksums", "check --repair")
    code, out, _ = cli(capsys, "info", str(store))
    assert code == 0 and "every tile's checksum verified" in out
    code, out, _ = cli(capsys, "check", str(s))
    assert code == 2
    problems = [ln for ln in out.splitlines() if ln.strip().startswith("problem:")]
    assert any("(2, 1, 0) fails its checksum" in p for p in problems), out
    assert any("(1, 0, 0) fails its checksum" in p for p in problems), out
    assert "verdict: " in out and "sound" not in out.splitlines()[-1]
    code, out, _ = cli(capsys, "check", str(s), "--repair")
    assert code == 2 and "--resume` rebuilds" in out
    rep = build_store(read_heightfield(src), s, tile_size=9, workers=1, resume=True)
    assert rep.tiles_built >= 2
    assert check_store(s).sound
    ref, new = (
        sqlite3.connect(p).execute("SELECT * FROM tiles ORDER BY level, x, y").fetchall() for p in (store, s)
    )
    assert ref == new


def test_metadata_checksum_and_upgrade(built, tmp_path: Path, capsys) -> None:
    _, store = built
    for key, old, new in (
        ("transform", "5200000", "5200001"),
        ("tile_size", "9", "17"),
        ("crs", "UTM", "UTN"),
    ):
        s = _copy(store, tmp_path / f"m_{key}.terra")
        con = sqlite3.connect(s)
        v = con.execute("SELECT value FROM meta WHERE key = ?", (key,)).fetchone()[0]
        assert old in v
        con.execute("UPDATE meta SET value = ? WHERE key = ?", (v.replace(old, new, 1), key))
        con.commit()
        con.close()
        with pytest.raises(CorruptStoreError, match="metadata fails its checksum"):
            open_store(s)
        code, _, err = cli(capsys, "info", str(s))
        assert code == 2
        one_line(err, "metadata fails its checksum")
    # a version-1 store (no checksum): one line naming the upgrade, which then makes it open
    s = _copy(store, tmp_path / "v1.terra")
    con = sqlite3.connect(s)
    con.execute("DELETE FROM meta WHERE key = 'meta_sha256'")
    con.execute("UPDATE meta SET value = '1' WHERE key = 'version'")
    con.commit()
    con.close()
    with pytest.raises(StoreError, match="check --upgrade"):
        open_store(s)
    code, out, _ = cli(capsys, "check", "--upgrade", str(s))
    assert code == 0 and "upgraded from format version 1" in out
    with open_store(s) as st:
        assert st.verify() == [] and st.meta["version"] == FORMAT_VERSION == 3


def _with_version(src: Path, to: Path, version: int) -> Path:
    s = _copy(src, to)
    con = sqlite3.connect(s)
    with con:
        con.execute("UPDATE meta SET value = ? WHERE key = 'version'", (str(version),))
        seal_meta(con)
    con.close()
    return s


def test_format_version_3_epochs(built, tmp_path: Path, capsys) -> None:
    """Epochs bumped the format to 3: a version-2 store (no epochs) reads as it is and becomes version 3
    when it gets epoch tables; a newer version is refused with one line; ``--upgrade`` brings 2 to 3."""
    _, store = built
    with open_store(store) as st:
        assert st.meta["version"] == 3
    v2 = _with_version(store, tmp_path / "v2.terra", 2)
    with open_store(v2) as st:
        assert st.meta["version"] == 2 and st.verify() == []
    with TileStore.open(v2, writable=True) as st:
        st.adopt_tiles_as_epoch("2020-01-01", {"kind": "build"})
    with open_store(v2) as st:  # re-sealed: opens, and says 3
        assert st.meta["version"] == 3 and st.has_epochs and st.verify() == []
    code, out, _ = cli(capsys, "check", "--upgrade", str(_with_version(store, tmp_path / "u.terra", 2)))
    assert code == 0 and "upgraded from format version 2 to 3" in out
    v4 = _with_version(store, tmp_path / "v4.terra", 4)
    with pytest.raises(StoreError, match="newer than this terralod"):
        open_store(v4)
    code, _, err = cli(capsys, "info", str(v4))
    assert code == 2
    one_line(err, "format version 4 is newer", "upgrade terralod")


def test_damaged_stores_one_line(built, tmp_path: Path, capsys) -> None:
    _, store = built
    empty = tmp_path / "empty.terra"
    empty.write_bytes(b"")
    notiles = _copy(store, tmp_path / "notiles.terra")
    con = sqlite3.connect(notiles)
    con.execute("DROP TABLE tiles")
    con.commit()
    con.close()
    noroot = _copy(store, tmp_path / "noroot.terra")
    con = sqlite3.connect(noroot)
    con.execute("DELETE FROM tiles WHERE level = 0")
    con.commit()
    con.close()
    for p, needle in ((empty, "empty file"), (notiles, "no tiles table")):
        for args in (["info", str(p)], ["check", str(p)]):
            code, out, err = cli(capsys, *args)
            assert code == 2 and needle in out + err, (args, out, err)
    code, out, _ = cli(capsys, "check", str(noroot))
    assert code == 2 and "1 of" in out and "missing" in out


def test_never_writes_onto_an_input(built, tmp_path: Path, capsys) -> None:
    src, store = built
    dem = _copy(src, tmp_path / "dem.tif")
    before = dem.read_bytes()
    hard = tmp_path / "hard.tif"
    os.link(dem, hard)
    sym = tmp_path / "sym.terra"
    sym.symlink_to(dem)
    for out in (dem, hard, sym):
        code, _, err = cli(capsys, "build", str(dem), "-o", str(out), "--overwrite")
        assert code == 2, err
        one_line(err, "input")
    code, _, err = cli(capsys, "amplify", str(dem), "-o", str(hard))
    assert code == 2
    one_line(err)
    code, _, err = cli(capsys, "amplify", str(dem), "-o", str(dem), "--overwrite")
    assert code == 2
    one_line(err, "input")
    assert dem.read_bytes() == before
    s = _copy(store, tmp_path / "s.terra")
    for args in (["render", str(s), "-o", str(s), "--overwrite"], ["render", str(s), "-o", str(tmp_path / "f")],
                 ["render", str(s), "-o", str(tmp_path / "f.xyz")], ["flythrough", str(s), "-o", str(tmp_path / "f.terra")]):  # fmt: skip
        code, _, err = cli(capsys, *args)
        assert code == 2, (args, err)
        one_line(err)
    with pytest.raises(StoreError, match="input DEM"):
        build_store(read_heightfield(dem), hard, tile_size=9, overwrite=True)


def test_overwrite_replaces_only_when_complete(built, tmp_path: Path) -> None:
    src, store = built
    out = _copy(store, tmp_path / "o.terra")
    z = fractal_terrain(40, 36, 9).astype(np.float32)
    other = _tif(tmp_path / "other.tif", z)
    build_store(read_heightfield(other), out, tile_size=9, workers=1, overwrite=True, stop_after=3)
    assert check_store(out).sound  # stopped early: the old store is still there, whole
    build_store(read_heightfield(other), out, tile_size=9, workers=1, overwrite=True)
    with open_store(out) as s:
        assert s.complete and s.meta["width"] == 36
    assert not [f for f in tmp_path.iterdir() if f.name.endswith(".tmp")]


def test_verbose_keeps_exit_code_2(tmp_path: Path, capsys) -> None:
    bad = tmp_path / "x.tif"
    bad.write_text("not a raster")
    code, _, err = cli(capsys, "-v", "info", str(bad))
    assert code == 2 and err.strip().splitlines()[-1].startswith(f"terralod: {bad}: ")


def test_inputs_no_longer_accepted_silently(tmp_path: Path) -> None:
    polar = _tif(tmp_path / "polar.tif", np.ones((50, 50), np.float32), crs="EPSG:4326", res=0.01, x0=0.0,
                 y0=90.0)  # fmt: skip
    with pytest.raises(InputError, match="16x"):
        read_heightfield(polar)
    cplx = _tif(tmp_path / "c.tif", (np.ones((20, 20)) * (3 + 4j)).astype(np.complex64))
    with pytest.raises(InputError, match="complex64"):
        read_heightfield(cplx)
    z = np.full((100, 100), -9999, np.float32)
    z[50, 50] = 10
    sparse = _tif(tmp_path / "s.tif", z, nodata=-9999.0)
    with pytest.raises(InputError, match="1 of 10000 samples are valid"):
        read_heightfield(sparse)


def test_las_header_count_disagrees(tmp_path: Path, capsys) -> None:
    import struct

    import laspy

    las = laspy.create(point_format=3, file_version="1.2")
    rng = np.random.default_rng(0)
    las.x, las.y, las.z = rng.uniform(0, 50, 200), rng.uniform(0, 50, 200), rng.uniform(0, 5, 200)
    p = tmp_path / "c.las"
    las.write(p)
    b = bytearray(p.read_bytes())
    b[107:111] = struct.pack("<I", 700)  # the legacy point count claims more than the records
    p.write_bytes(bytes(b))
    code, out, err = cli(capsys, "info", str(p))
    assert code == 0 and "disagrees" in out and "200 records" in out, (out, err)
    from terralod.tin.pointcloud import read_las

    assert read_las(p).xyz_m.shape[0] == 200
    b[100:104] = struct.pack("<I", 2**31)  # an absurd VLR count
    p.write_bytes(bytes(b))
    with pytest.raises(InputError, match="variable-length records"):
        read_las(p)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_check_finds_what_a_whole_store_reading_finds(built, tmp_path: Path, seed: int) -> None:
    """``check`` reads a level in raster order with two rows of tiles and the errors as arrays (memory
    bounded by a row, not the region); it finds exactly what reading the whole store at once finds: tiles
    re-written (checksums valid) with errors below their children's or their own measurement (and every
    tile above those), missing tiles, a tile beyond the plan, and one border check per stored pair of east
    / south neighbours."""
    import dataclasses

    from terralod.tiles import parent

    _, store = built
    s = _copy(store, tmp_path / "t.terra")
    rng = np.random.default_rng(seed)
    with TileStore.open(s, writable=True) as w:
        codes = w.tile_codes()
        picks = [codes[i] for i in rng.choice(len(codes), 6, replace=False)]
        low = [dataclasses.replace(w.raw_tile(*c), error_m=0.0) for c in picks[:3]]
        w.write_tiles(low)
    con = sqlite3.connect(s)
    for c in picks[3:5]:
        con.execute("DELETE FROM tiles WHERE level=? AND x=? AND y=?", c)
    cur = con.execute("SELECT * FROM tiles WHERE level=? AND x=? AND y=?", picks[5])
    names = [d[0] for d in cur.description]
    row = list(cur.fetchone())
    row[names.index("x")] += 1000  # beyond the pyramid's plan
    con.execute(f"INSERT INTO tiles ({', '.join(names)}) VALUES ({', '.join('?' * len(names))})", row)
    stray = (picks[5][0], picks[5][1] + 1000, picks[5][2])
    con.commit()
    con.close()
    with open_store(s) as r:
        errs = r.tile_errors()
        rows = {c: errs[c] for c in r.tile_codes() if c != stray}
        meas = {(t["level"], t["x"], t["y"]): (t["measured_error_m"], t["measured_vertical_error_m"])
                for t in r.tile_summaries()}  # fmt: skip
        pyr = r.pyramid
        planned = sum(nx * ny for nx, ny in map(pyr.grid_count, pyr.levels))
    want: set = {stray}
    for c, (e, v) in rows.items():
        if e < meas[c][0] or v < meas[c][1]:
            want.add(c)
        kids = [k for k in pyr.children(c) if k in rows]
        if kids and (e < max(rows[k][0] for k in kids) or v < max(rows[k][1] for k in kids)):
            q = c
            while q is not None:
                want.add(q)
                q = parent(q)
    pairs = sum((c[0], c[1] + 1, c[2]) in rows for c in rows) + sum(
        (c[0], c[1], c[2] + 1) in rows for c in rows
    )
    rep = check_store(s)
    assert rep.broken_tiles == want and want, (sorted(rep.broken_tiles ^ want), rep.problems)
    assert rep.missing_tiles == planned - len(rows) == 2
    assert f"{pairs} shared borders" in rep.checked
    assert f"{len(rows)}/{len(rows) + 1} tiles decode and pass their checksums" in rep.checked
    assert any("not in the pyramid's plan" in p for p in rep.problems)
