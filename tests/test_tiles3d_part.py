"""A part of a 3D Tiles export (``--bbox``, ``--min-zoom``, ``--max-zoom``): the nodes that meet the box up to
the last level, with their ancestors, content from the first level; every glb byte for byte the whole
export's, the tileset a valid tree (each content's file there, errors never growing down the tree)."""

from __future__ import annotations

from pathlib import Path

import pytest

from terralod.cli import main

from conftest import crop_geotiff, read_tileset

pytest.importorskip("pyproj")


@pytest.fixture(scope="module")
def store(shared_data: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("part")
    dem = crop_geotiff(shared_data / "dem" / "kilauea_hawaii_30m_utm5.tif", d / "k.tif", 300, 200, 257)
    main(["build", str(dem), "-o", str(d / "k.terra"), "--tile-size", "33"])
    return d / "k.terra"


@pytest.fixture(scope="module")
def whole(store: Path) -> Path:
    out = store.parent / "whole"
    main(["export", str(store), "--format", "3dtiles", "-o", str(out)])
    return out


def _nodes(tile: dict, out: list[dict]) -> list[dict]:
    out.append(tile)
    for k in tile.get("children", []):
        _nodes(k, out)
    return out


def _check_tree(out: Path) -> list[dict]:
    ts = read_tileset(out)
    nodes = _nodes(ts["root"], [])

    def walk(t: dict) -> None:
        for k in t.get("children", []):
            assert k["geometricError"] <= t["geometricError"]
            walk(k)

    walk(ts["root"])
    for n in nodes:
        if "content" in n:
            assert (out / n["content"]["uri"]).is_file()
    return nodes


def test_a_box_and_levels_give_the_whole_exports_glbs(store: Path, whole: Path, tmp_path: Path) -> None:
    from terralod.export.quantized_mesh import Part
    from terralod.export.tiles3d import Tiles3D
    from terralod.terrain import open_terrain

    all_glbs = {f.relative_to(whole): f.read_bytes() for f in whole.rglob("*.glb")}
    levels = sorted({int(p.parts[1]) for p in all_glbs})
    assert len(levels) >= 3
    with open_terrain(store) as t:
        view = Tiles3D(t)
        w, s, e, n = view.lonlat_box(next(c for c in view.nodes if c[0] == 0))
        box = (w, s, w + 0.3 * (e - w), s + 0.3 * (n - s))  # the south-west corner
        part = Part(bbox=box, min_zoom=levels[1], max_zoom=levels[-2])
        keep = view.part_nodes(part)
    out = tmp_path / "part"
    main(["export", str(store), "--format", "3dtiles", "-o", str(out), "--bbox", ",".join(map(str, box)),
          "--min-zoom", str(levels[1]), "--max-zoom", str(levels[-2])])  # fmt: skip
    got = {f.relative_to(out): f.read_bytes() for f in out.rglob("*.glb")}
    assert got and len(got) < len(all_glbs)
    for rel, data in got.items():
        assert data == all_glbs[rel], rel  # the whole export's bytes
        level = int(rel.parts[1])
        assert levels[1] <= level <= levels[-2]
    nodes = _check_tree(out)
    # every node written meets the box, and every node of those levels that meets it is written
    written = {(int(r.parts[1]), *map(int, r.stem.split("_"))) for r in got}
    want = {
        c for c in keep if levels[1] <= c[0] and (f"tiles/{c[0]}/{c[1]}_{c[2]}.glb" in map(str, all_glbs))
    }
    assert written == want
    assert all("content" not in x or int(x["content"]["uri"].split("/")[1]) >= levels[1] for x in nodes)


def test_a_box_that_meets_nothing_is_one_line(store: Path, tmp_path: Path, capsys) -> None:  # noqa: ANN001
    with pytest.raises(SystemExit) as exc:
        main(
            ["export", str(store), "--format", "3dtiles", "-o", str(tmp_path / "o"), "--bbox", "10,10,11,11"]
        )
    err = capsys.readouterr().err.strip()
    assert exc.value.code == 2 and "has no tile that meets the box" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "o").exists()


@pytest.fixture(scope="module")
def tin(store: Path) -> Path:
    """A TIN store of a 65² crop: its tree has a root a sub-block, and its nodes share one point array."""
    from terralod.io.reader import read_heightfield
    from terralod.tin import DetailIncrementModel
    from terralod.tin.terra import save_model_to_store

    out = store.parent / "tin.terra"
    crop = crop_geotiff(store.parent / "k.tif", store.parent / "crop.tif", 0, 0, 65)
    save_model_to_store(DetailIncrementModel.from_heightfield(read_heightfield(crop), sub_blocks=4), out)
    return out


def _files(out: Path) -> dict[str, bytes]:
    return {str(p.relative_to(out)): p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()}


def test_a_tins_blocks_give_its_whole_level_glbs(
    tin: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The same for a TIN store, whose nodes share one point array (one block a node)."""
    import terralod.export.distributed as dist

    monkeypatch.setattr(dist, "BLOCK_NODES", 10**9)
    monkeypatch.setattr(dist, "BLOCK_VERTICES", 10**15)
    main(["export", str(tin), "--format", "3dtiles", "-o", str(tmp_path / "whole-levels")])
    monkeypatch.setattr(dist, "BLOCK_NODES", 1)
    main(["export", str(tin), "--format", "3dtiles", "-o", str(tmp_path / "blocks")])
    want, got = _files(tmp_path / "whole-levels"), _files(tmp_path / "blocks")
    assert len(want) > 10 and got == want


@pytest.mark.parametrize(("bound", "size"), [("nodes", 1), ("nodes", 5), ("vertices", 3)])
def test_blocks_of_any_size_give_the_whole_level_glbs(
    store: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, bound: str, size: int
) -> None:
    """A level encoded block by block (its normals summed over each block and its neighbours only) gives
    the bytes of every file the level encoded whole gives (one block a level); a node asked for alone
    (``terralod serve``) gives its file's bytes too. Blocks are cut by a count of nodes, or by a count of
    mesh vertices (here about ``size`` nodes' worth) where the terrain counts them."""
    import terralod.export.distributed as dist
    from terralod.export.tiles3d import Tiles3D, node_uri
    from terralod.terrain import open_terrain

    monkeypatch.setattr(dist, "BLOCK_NODES", 10**9)
    monkeypatch.setattr(dist, "BLOCK_VERTICES", 10**15)
    main(["export", str(store), "--format", "3dtiles", "-o", str(tmp_path / "whole-levels")])
    want = _files(tmp_path / "whole-levels")
    block_nodes = size
    with open_terrain(store) as terrain:
        view = Tiles3D(terrain)
        finest = max(n.code[0] for n in view.tree)
        level = [n.code for n in view.tree if n.code[0] == finest]
        if bound == "nodes":
            monkeypatch.setattr(dist, "BLOCK_NODES", size)
        else:
            counts = view.level_vertices(finest)
            assert counts is not None and counts.min() > 0  # a grid store counts its tiles' vertices
            monkeypatch.setattr(dist, "BLOCK_VERTICES", int(size * counts.mean()))
        blocks = list(dist.level_blocks(view, level))
        assert len(blocks) >= len(level) // (2 * block_nodes) > 1
        assert sorted(c for b, _ in blocks for c in b) == sorted(level)  # each node in one block
        assert max(len(near) for _, near in blocks) < len(level)
        for code in level[:: max(1, len(level) // 5)] + [view.tree[0].code]:
            assert view.glb(code) == want[node_uri(code)], code
    main(["export", str(store), "--format", "3dtiles", "-o", str(tmp_path / "blocks")])
    got = _files(tmp_path / "blocks")
    assert len(want) > 20 and got.keys() == want.keys()
    assert [k for k in want if got[k] != want[k]] == []


def test_the_tileset_files_made_as_they_go_are_the_split_whole_tileset(store: Path, tin: Path) -> None:
    """Tiles3D.tileset_files (each external tileset yielded as its subtree is made, never the whole tree)
    gives split_tileset(tileset())'s files, the same JSON in the same order, for any split depth, a part,
    and a TIN store's tree of several roots."""
    import json

    from terralod.export.quantized_mesh import Part
    from terralod.export.tiles3d import Tiles3D, split_tileset
    from terralod.terrain import open_terrain

    roots = []
    for path in (store, tin):
        with open_terrain(path) as terrain:
            view = Tiles3D(terrain)
            roots.append(len(view.children[None]))
            w, s, e, n = view.lonlat_box(view.tree[0].code)
            parts = [None, Part(bbox=(w, s, w + 0.3 * (e - w), s + 0.3 * (n - s)), min_zoom=1, max_zoom=3)]
            for part in parts:
                for levels in (1, 2, 3, 4):
                    want = list(split_tileset(view.tileset(part), levels).items())
                    got = list(view.tileset_files(part, levels))
                    assert [k for k, _ in got] == [k for k, _ in want]
                    assert [json.dumps(v) for _, v in got] == [json.dumps(v) for _, v in want], (path, levels)
            made = [0]  # the files go as they are made: the first before most of the tree is
            head = view._tile_head

            def counted(*a, _head=head, _made=made):  # noqa: ANN001, ANN202
                _made[0] += 1
                return _head(*a)

            view._tile_head = counted
            gen = view.tileset_files(None, 1)
            next(gen)
            first = made[0]
            rest = list(gen)
            assert rest and first < made[0] / 2, (path, first, made[0])
    assert roots[0] == 1 and roots[1] > 1, roots
