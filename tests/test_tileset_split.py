"""A tileset in files (3D Tiles external tilesets): every node once, the same tree when the files are read
back, no file deeper than its levels, and an export's files the ones its tree gives."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from terralod.export.tiles3d import split_tileset


def _tree(draw: st.DrawFn, depth: int, counter: list[int]) -> dict:
    counter[0] += 1
    k = counter[0]
    tile: dict = {"boundingVolume": {"region": [0.0, 0.0, 1.0, 1.0, 0.0, float(k)]},
                  "geometricError": 1000.0 / (depth + 1), "transform": [float(k)] * 16}  # fmt: skip
    if draw(st.booleans()):
        tile["content"] = {"uri": f"tiles/{depth}/{k}.glb"}
    if depth < 7:
        n = draw(st.integers(0, 4 if depth < 3 else 2))
        if n:
            tile["children"] = [_tree(draw, depth + 1, counter) for _ in range(n)]
    return tile


@st.composite
def tilesets(draw: st.DrawFn) -> dict:
    root = _tree(draw, 0, [0])
    root["refine"] = "REPLACE"
    return {"asset": {"version": "1.1"}, "geometricError": 5000.0, "root": root}


def _read_back(files: dict[str, dict], name: str = "tileset.json") -> dict:
    """The one nested tree the files stand for: each external reference replaced by the external root,
    carrying the referencing tile's transform."""

    def walk(tile: dict) -> dict:
        uri = tile.get("content", {}).get("uri", "")
        if uri.endswith(".json"):
            ext = files[uri]["root"]
            assert "transform" not in ext and ext["refine"] == "REPLACE"
            assert ext["boundingVolume"] == tile["boundingVolume"]
            assert ext["geometricError"] == tile["geometricError"] == files[uri]["geometricError"]
            assert "children" not in tile
            node = {k: v for k, v in ext.items() if k != "refine"}
            if "transform" in tile:
                node["transform"] = tile["transform"]
            tile = node
        out = dict(tile)
        if "children" in tile:
            out["children"] = [walk(k) for k in tile["children"]]
        return out

    ts = files[name]
    return {**ts, "root": walk(ts["root"])}


def _depth(tile: dict) -> int:
    return 1 + max((_depth(k) for k in tile.get("children", [])), default=0)


@settings(max_examples=60, deadline=None)
@given(tilesets(), st.integers(1, 4))
def test_the_files_read_back_as_the_one_tree(ts: dict, levels: int) -> None:
    before = copy.deepcopy(ts)
    files = split_tileset(ts, levels)
    assert ts == before  # the tree given is not changed
    back = _read_back(files)
    strip = {**back, "root": {**back["root"]}}
    strip["root"].pop("refine", None)
    want = {**ts, "root": {k: v for k, v in ts["root"].items() if k != "refine"}}
    assert strip == want
    for name, js in files.items():
        assert _depth(js["root"]) <= levels + 1, name  # a file holds its levels, then references
    assert split_tileset(ts, levels) == files  # the same tree, the same files


def test_an_export_writes_the_files_its_tree_gives(shared_data: Path, tmp_path: Path) -> None:
    pytest.importorskip("pyproj")
    from terralod.cli import main

    from conftest import crop_geotiff

    dem = crop_geotiff(shared_data / "dem" / "kilauea_hawaii_30m_utm5.tif", tmp_path / "k.tif", 300, 200, 257)
    main(["build", str(dem), "-o", str(tmp_path / "k.terra"), "--tile-size", "9"])
    main(["export", str(tmp_path / "k.terra"), "--format", "3dtiles", "-o", str(tmp_path / "t")])
    files = {f.name: json.loads(f.read_text()) for f in (tmp_path / "t").glob("tileset*.json")}
    assert len(files) > 1  # a tree deeper than one file's levels
    back = _read_back(files)
    uris = []

    def walk(t: dict) -> None:
        if "content" in t:
            uris.append(t["content"]["uri"])
        for k in t.get("children", []):
            walk(k)

    walk(back["root"])
    glbs = sorted(str(f.relative_to(tmp_path / "t")) for f in (tmp_path / "t").rglob("*.glb"))
    assert sorted(uris) == glbs  # every glb reachable exactly once through the files
