"""The change site of a pair read window by window (issue 54 #4): ``terralod change BEFORE/ AFTER/ --site`` on
two regions (folders of tiles) builds each side's store out of core, exports its 3D Tiles, and writes the pair's
pyramids from ``dod.tif`` and BEFORE's source in strips of rows, never a whole grid in memory.

Checked on the St Helens pair given as two one-tile regions (a pair small enough to be its own co-registration
sample, so every figure is the in-memory chain's): the pair's description is the in-memory site's (the same
grid, drape, lattice, legend and totals), level 0 of the pyramids is dod.tif and BEFORE's DEM within the step,
every tile the manifests name is there and no other, each epoch's tileset stops at the level of detection and
every content it names exists. The page itself on such a site: tests/test_site.py (the same files)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from terralod.cli import main
from terralod.site.tiles import STEP_M, TILE_PX, read_level

from conftest import read_tileset

BEFORE = "change/st_helens_crater_2000-09-25_10m.tif"
AFTER = "change/st_helens_crater_2007-07-05_10m.tif"


def _change(args: list[str]) -> None:
    try:
        main(["change", *args, "--site", "--no-views"])
    except SystemExit as exc:
        assert exc.code in (0, None)


@pytest.fixture(scope="module")
def runs(shared_data: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    tmp = tmp_path_factory.mktemp("site_windowed")
    folders = []
    for name, rel in (("before", BEFORE), ("after", AFTER)):
        (tmp / name).mkdir()
        (tmp / name / Path(rel).name).symlink_to(shared_data / rel)
        folders.append(str(tmp / name))
    _change([*folders, "-o", str(tmp / "windowed")])
    _change([str(shared_data / BEFORE), str(shared_data / AFTER), "-o", str(tmp / "in_memory")])
    return tmp / "windowed", tmp / "in_memory"


def _files(site: Path):  # noqa: ANN202
    def get(name: str) -> bytes | None:
        f = site / name
        return f.read_bytes() if f.is_file() else None

    return get


def test_the_windowed_path_was_taken(runs: tuple[Path, Path]) -> None:
    windowed, in_memory = runs
    assert "windowed" in json.loads((windowed / "summary.json").read_text())
    assert "windowed" not in json.loads((in_memory / "summary.json").read_text())


def test_the_pair_is_the_in_memory_sites(runs: tuple[Path, Path]) -> None:
    windowed, in_memory = runs
    got = json.loads((windowed / "site/pairs/0.json").read_text())
    want = json.loads((in_memory / "site/pairs/0.json").read_text())
    for key in ("key", "from", "to", "dates", "grid", "lattice", "legend", "largest", "olympic_pool_m3"):
        assert got[key] == want[key], key
    for key in ("u", "v", "centre_ecef"):  # the drape: the same fit up to the order of float sums
        assert np.allclose(got["drape"][key], want["drape"][key], rtol=1e-9, atol=1e-12), key
    assert got["drape"]["residual_cells"] < 0.5
    for key, v in want["totals"].items():
        assert got["totals"][key] == pytest.approx(v, rel=1e-9), key
    s = json.loads((windowed / "summary.json").read_text())
    assert got["totals"]["net_m3"] == s["net_m3"] and got["error_model"]["lod_m"] == s["level_of_detection_m"]
    for role in ("dod", "before"):  # the same tiles
        assert got["rasters"][role]["levels"] == want["rasters"][role]["levels"], role
    m = json.loads((windowed / "site/site.json").read_text())
    assert m["rasters"] == json.loads((in_memory / "site/site.json").read_text())["rasters"]
    assert [e["name"] for e in m["epochs"]] == ["2000-09-25", "2007-07-05"]


def test_level_0_is_dod_tif_and_the_before_dem(runs: tuple[Path, Path], shared_data: Path) -> None:
    import rasterio

    windowed, _ = runs
    site = windowed / "site"
    pair = json.loads((site / "pairs/0.json").read_text())
    with rasterio.open(windowed / "dod.tif") as ds:
        dod = ds.read(1, masked=True).astype(np.float64).filled(np.nan)
    level0 = read_level(pair["rasters"]["dod"], _files(site), 0)
    assert np.array_equal(np.isfinite(level0), np.isfinite(dod))
    assert np.nanmax(np.abs(level0 - dod)) <= STEP_M / 2 + 1e-9
    before = read_level(pair["rasters"]["before"], _files(site), 0)
    with rasterio.open(shared_data / BEFORE) as ds:
        z = ds.read(1, masked=True).astype(np.float64).filled(np.nan)
    assert np.array_equal(np.isfinite(before), np.isfinite(z))
    assert np.nanmax(np.abs(before - z)) <= STEP_M / 2 + 1e-6
    named = set()
    for d in pair["rasters"].values():
        for k, lv in enumerate(d["levels"]):
            nc = -(-lv["shape"][1] // TILE_PX)
            named |= {
                f"{d['url']}/{k}/{i // nc}_{i % nc}.i32.gz" for i, f in enumerate(lv["tiles"]) if f == "1"
            }
    assert named == {p.relative_to(site).as_posix() for p in (site / "pairs").rglob("*.i32.gz")}


def test_each_epoch_stops_at_the_level_of_detection(runs: tuple[Path, Path]) -> None:
    windowed, _ = runs
    site = windowed / "site"
    lod = json.loads((site / "pairs/0.json").read_text())["error_model"]["lod_m"]
    for i in (0, 1):
        ts = read_tileset(site / "epochs" / str(i))
        stack, leaves = [ts["root"]], 0
        while stack:
            n = stack.pop()
            stack += n.get("children", [])
            if "content" in n:
                assert (site / "epochs" / str(i) / n["content"]["uri"]).resolve().is_file()
            if not n.get("children"):
                leaves += 1
                assert n["geometricError"] <= lod
        assert leaves > 1
    assert not list(windowed.rglob("*.terra"))  # the stores were scratch
    assert not list(site.rglob(".*"))  # nor the exports' journals
    biggest = max((p.stat().st_size for p in site.rglob("*") if p.is_file()), default=0)
    assert biggest <= 8 << 20


def test_two_epochs_of_a_store_make_the_same_pair(
    runs: tuple[Path, Path], shared_data: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``change STORE --from A --to B --site`` read window by window (the threshold lowered to take that path
    on a small store): its 3D Tiles are the store's own epochs, its pair the folder pair's (the same grid and
    samples: the same description and the same tiles)."""
    import terralod.cli.change as change_cli

    store = tmp_path / "pair.terra"
    for args in (["build", str(shared_data / BEFORE), "-o", str(store), "--epoch", "2000-09-25"],
                 ["update", str(store), str(shared_data / AFTER), "--epoch", "2007-07-05"]):  # fmt: skip
        try:
            main(args)
        except SystemExit as exc:
            assert exc.code in (0, None)
    monkeypatch.setattr(change_cli, "WINDOWED_MIN_CELLS", 0)
    _change([str(store), "--from", "2000-09-25", "--to", "2007-07-05", "-o", str(tmp_path / "out")])
    assert "windowed" in json.loads((tmp_path / "out/summary.json").read_text())
    got = json.loads((tmp_path / "out/site/pairs/0.json").read_text())
    want = json.loads((runs[0] / "site/pairs/0.json").read_text())
    for key in ("grid", "lattice", "legend", "rasters", "error_model"):
        assert got[key] == want[key], key
    for key, v in want["totals"].items():
        assert got["totals"][key] == pytest.approx(v, rel=1e-9), key
    for i in (0, 1):
        assert (tmp_path / "out/site/epochs" / str(i) / "tileset.json").is_file()
    assert not list((tmp_path / "out").rglob("*.terra"))
