"""Nothing lost, nothing silently wrong (issue 48, items 1, 2 and 5): exports that would delete their input,
one size limit in every command, what killed runs leave behind, epoch names."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "change"
BEFORE = DATA / "st_helens_crater_2000-09-25_10m.tif"
AFTER = DATA / "st_helens_crater_2007-07-05_10m.tif"
needs_data = pytest.mark.skipif(not BEFORE.exists(), reason="../shared/data (St Helens pair) is absent")


def terralod(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "terralod", *args], capture_output=True, text=True, cwd=cwd,
                          timeout=600)  # fmt: skip


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
