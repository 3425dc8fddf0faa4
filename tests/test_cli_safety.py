"""Nothing lost, nothing silently wrong (issue 48, items 1, 2 and 5): exports that would delete their input,
one size limit in every command, what killed runs leave behind, epoch names."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

from conftest import terralod_cli

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "change"
BEFORE = DATA / "st_helens_crater_2000-09-25_10m.tif"
AFTER = DATA / "st_helens_crater_2007-07-05_10m.tif"
needs_data = pytest.mark.skipif(not BEFORE.exists(), reason="../shared/data (St Helens pair) is absent")


def terralod(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    """``terralod ARGS`` in this process (tests/conftest.py ``terralod_cli``; tests/test_cli.py runs the
    one-line refusal in a real process too)."""
    return terralod_cli(*args, cwd=cwd)


@pytest.fixture(scope="module")
def small_store(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from terralod.io.reader import read_heightfield
    from terralod.pyramid.builder import build_store

    if not BEFORE.exists():
        pytest.skip("../shared/data (St Helens pair) is absent")
    out = tmp_path_factory.mktemp("store") / "sh.terra"
    build_store(read_heightfield(str(BEFORE)), out, tile_size=33)
    return out


# -- 48.1: export --overwrite never deletes its own input --------------------------------------------------


@needs_data
@pytest.mark.parametrize("depth", [0, 1])
@pytest.mark.parametrize("fmt", ["3dtiles", "quantized-mesh"])
def test_export_overwrite_refuses_a_folder_holding_the_input(
    tmp_path: Path, small_store: Path, depth: int, fmt: str
) -> None:
    site = tmp_path / "site"
    holder = site / "deeper" if depth else site
    holder.mkdir(parents=True)
    store = holder / "s.terra"
    store.write_bytes(small_store.read_bytes())
    (site / "keep.txt").write_text("mine")
    before = sorted(p.relative_to(site) for p in site.rglob("*"))
    r = terralod("export", str(store), "--format", fmt, "-o", str(site), "--overwrite", cwd=tmp_path)
    assert r.returncode == 2, r.stdout + r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "(or holds) the input" in lines[0] and str(site) in lines[0], r.stderr
    assert sorted(p.relative_to(site) for p in site.rglob("*")) == before  # nothing deleted, nothing added
    assert store.read_bytes() == small_store.read_bytes()
    assert not list(tmp_path.glob(".site*"))  # no temporary folder left beside it


# -- 48.2: one size limit, checked up front, with the file named -------------------------------------------


def _huge_vrt(folder: Path, side: int) -> Path:
    """A VRT claiming side x side float32 samples over a small real raster: nothing is allocated."""
    vrt = folder / f"huge_{side}.vrt"
    vrt.write_text(f"""<VRTDataset rasterXSize="{side}" rasterYSize="{side}">
  <GeoTransform>560000, 1, 0, 5120000, 0, -1</GeoTransform>
  <VRTRasterBand dataType="Float32" band="1">
    <SimpleSource><SourceFilename relativeToVRT="0">{BEFORE}</SourceFilename><SourceBand>1</SourceBand>
      <SrcRect xOff="0" yOff="0" xSize="303" ySize="442"/><DstRect xOff="0" yOff="0" xSize="303" ySize="442"/>
    </SimpleSource>
  </VRTRasterBand>
</VRTDataset>""")
    return vrt


@needs_data
@pytest.mark.parametrize("side", [100_000, 50_000])
def test_one_size_limit_in_every_command(tmp_path: Path, small_store: Path, side: int) -> None:
    vrt = _huge_vrt(tmp_path, side)
    out = tmp_path / "out"
    store = tmp_path / "s.terra"
    store.write_bytes(small_store.read_bytes())
    cases = [
        ["info", str(vrt)],
        ["build", str(vrt), "-o", str(out / "b.terra")],
        ["render", str(vrt), "-o", str(out / "r.png")],
        ["flythrough", str(vrt), "-o", str(out / "f.mp4")],
        ["view", str(vrt)],
        ["amplify", str(vrt), "-o", str(out / "a.tif")],
        ["update", str(store), str(vrt), "--epoch", "big"],
        ["change", str(BEFORE), str(vrt), "-o", str(out / "c")],
    ]
    out.mkdir()
    for args in cases:
        r = terralod(*args, cwd=tmp_path)
        lines = r.stderr.strip().splitlines()
        assert r.returncode == 2, (args, r.stdout, r.stderr)
        assert len(lines) == 1 and str(vrt) in lines[0] and "beyond the supported" in lines[0], (
            args,
            r.stderr,
        )
        assert list(out.iterdir()) == [], args  # nothing written, no incomplete store
    assert store.read_bytes() == small_store.read_bytes()


# -- 48.5: epoch names from a documented set -----------------------------------------------------------------


@needs_data
@pytest.mark.parametrize("name", ["..", "--", "' OR 1=1 --", ".hidden", "a..b", "-x", "a/b"])
def test_update_refuses_odd_epoch_names(tmp_path: Path, small_store: Path, name: str) -> None:
    store = tmp_path / "s.terra"
    store.write_bytes(small_store.read_bytes())
    r = terralod("update", str(store), str(AFTER), f"--epoch={name}", cwd=tmp_path)
    assert r.returncode == 2, r.stdout + r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and "epoch name" in r.stderr, r.stderr
    assert store.read_bytes() == small_store.read_bytes()


@needs_data
@pytest.mark.parametrize("fmt", ["3dtiles", "quantized-mesh"])
def test_export_of_a_store_without_tiles_is_one_line(tmp_path: Path, small_store: Path, fmt: str) -> None:
    """A store whose tiles are gone (its meta intact) is refused in one line naming it, exit 2, nothing
    written; the check looks at one row, not a tree of every tile."""
    import sqlite3

    store = tmp_path / "empty.terra"
    store.write_bytes(small_store.read_bytes())
    con = sqlite3.connect(store)
    with con:
        con.execute("DELETE FROM tiles")
    con.close()
    out = tmp_path / "out"
    r = terralod("export", str(store), "--format", fmt, "-o", str(out), cwd=tmp_path)
    assert r.returncode == 2, r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "has no tiles" in lines[0] and str(store) in lines[0], r.stderr
    assert not out.exists()
