"""Write the change site: a self-contained folder (the page, CesiumJS, each epoch's 3D Tiles, each pair's
difference raster and drape, the manifest, a README.txt for whoever hosts it) that works from any static web
host and offline. Written through :class:`terralod.output.Output` (a work folder beside the output, renamed
into place at the end), so an interrupted run leaves nothing half-written."""

from __future__ import annotations

import hashlib
import json
import shutil
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

from terralod.site.plan import SiteOptions, SitePlan, pair_dates, plan_site, plan_store_site

#: The page's files (package data of :mod:`terralod.site`).
PAGE_FILES = ("index.html", "site.js", "site.css")

README_TXT = """\
{title}
{underline}

This folder is a web page that shows how the ground changed{between}, in 3D, in any modern browser.
It needs no internet connection, no account and no server software of its own: any static web host serves it.

To look at it on this computer, open a terminal in this folder and run

    python3 -m http.server 8000

then open http://localhost:8000/ in a browser. (Opening index.html directly from the disk does not work:
browsers do not let a page read its own files that way.)

To publish it, copy the whole folder to any web host (a web server's folder, an object store with website
hosting, GitHub Pages, ...). No special configuration is needed: every file is sent as it is.

What is in it:
  index.html, site.js, site.css   the page
  site.json                       what the page shows (dates, places, file names)
  epochs/                         the terrain of each date (3D Tiles)
  pairs/                          the measured change between dates: the difference of heights and the
                                  heights before (tiles of millimetres at several levels of detail), its
                                  uncertainty, the colours and the plain-language summary
  cesium/                         CesiumJS, the 3D globe library (Apache-2.0, see cesium/LICENSE.md)

Made with terralod. Size: {size_mb:.1f} MB.
"""


@dataclass
class SiteReport:
    """What was written: the folder, its size, and the bytes per part."""

    path: Path
    bytes: int = 0
    parts: dict[str, int] = field(default_factory=dict)
    epochs: int = 0
    pairs: int = 0
    area_km2: float = 0.0
    shared_bytes: int = 0
    pruned_bytes: int = 0
    keep_error_m: float = 0.0
    #: with ``update``: the files whose bytes changed (rewritten) and those the new site no longer has
    rewritten: list[str] = field(default_factory=list)
    removed: list[str] = field(default_factory=list)

    def as_dict(self) -> dict[str, Any]:
        per_epoch = self.parts.get("epochs", 0) / max(self.epochs, 1)
        return {"path": self.path.name, "bytes": self.bytes, "parts": self.parts, "epochs": self.epochs,
                "pairs": self.pairs, "area_km2": self.area_km2,
                "bytes_per_km2": self.bytes / self.area_km2 if self.area_km2 else None,
                "epoch_bytes_each": per_epoch, "tile_bytes_shared": self.shared_bytes,
                "tile_bytes_below_lod": self.pruned_bytes, "finest_error_kept_m": self.keep_error_m}  # fmt: skip


def copy_page(dest: Path) -> None:
    """The page's own files into ``dest``."""
    for name in PAGE_FILES:
        (dest / name).write_bytes(resources.files("terralod.site").joinpath("static", name).read_bytes())


#: Parts of CesiumJS's build the page never asks for (it has no sky box, no imagery, no pins, no lens flare
#: and no globe water): left out of a site (2.5 of 13.2 MB). The browser tests fail on any request that
#: finds nothing, so a part the page does need cannot go missing unnoticed.
UNUSED_CESIUM = {"SkyBox", "NaturalEarthII", "maki", "LensFlare", "waterNormals.jpg"}


def _unused_by_the_page(folder: str, names: list[str]) -> set[str]:
    return UNUSED_CESIUM.intersection(names) if Path(folder).name == "Textures" else set()


def copy_cesium(dest: Path) -> None:
    """CesiumJS's browser build (with its licence) into ``dest/cesium``."""
    from terralod.errors import TerralodError
    from terralod.site.cesium import cesium_dir

    src = cesium_dir()
    if src is None:
        raise TerralodError(
            "CesiumJS is not installed with this terralod (it ships with the web extra: "
            "pip install 'terralod[web]'); the site cannot be written"
        )
    shutil.copytree(src, dest / "cesium", ignore=_unused_by_the_page)
    lic = src / "LICENSE.md"
    if not lic.is_file():
        for cand in (src.parent.parent / "LICENSE.md",):
            if cand.is_file():
                shutil.copy2(cand, dest / "cesium" / "LICENSE.md")


def prune_tileset(ts: dict[str, Any], keep_error_m: float) -> list[str]:
    """Make every tile of tileset ``ts`` (changed in place) whose measured error is at most ``keep_error_m``
    a leaf: the levels below it refine the terrain by less than the pairs' level of detection (a change the
    data cannot tell from survey error). The drape and every figure the page shows come from the difference
    raster, not from the mesh, so they stay exact. Returns the content URIs left out."""
    dropped: list[str] = []
    if keep_error_m <= 0:
        return dropped

    def drop(node: dict[str, Any]) -> None:
        uri = (node.get("content") or {}).get("uri")
        if uri:
            dropped.append(uri)
        for c in node.get("children", []):
            drop(c)

    stack = [ts["root"]]
    while stack:
        node = stack.pop()
        if node.get("content") and node["geometricError"] <= keep_error_m and node.get("children"):
            for c in node["children"]:
                drop(c)
            del node["children"]
            continue
        stack.extend(node.get("children", []))
    return dropped


def prune_tiles(root: Path, keep_error_m: float) -> int:
    """:func:`prune_tileset` on the tileset written in ``root``, its left-out tiles deleted. Returns the
    bytes left out."""
    if keep_error_m <= 0:
        return 0
    ts_path = root / "tileset.json"
    ts = json.loads(ts_path.read_text())
    dropped = 0
    for uri in prune_tileset(ts, keep_error_m):
        if (root / uri).is_file():
            dropped += (root / uri).stat().st_size
            (root / uri).unlink()
    ts_path.write_text(json.dumps(ts, separators=(",", ":")))
    return dropped


def share_tiles(epochs_dir: Path, n: int) -> int:
    """Tiles an epoch has in common with an earlier one (the same bytes: an update rebuilds only the tiles
    whose samples changed) are kept once: the later tileset.json points at the earlier file (a relative URI,
    which 3D Tiles resolves against the tileset). Returns the bytes saved."""

    seen: dict[str, str] = {}
    saved = 0
    for i in range(n):
        root = epochs_dir / str(i)
        moved: dict[str, str] = {}
        for f in sorted(root.rglob("*.glb")):
            data = f.read_bytes()
            h = hashlib.sha256(data).hexdigest()
            rel = f.relative_to(root).as_posix()
            if h in seen:
                moved[rel] = seen[h]
                saved += len(data)
                f.unlink()
            else:
                seen[h] = f"../{i}/{rel}"
        if not moved:
            continue
        ts_path = root / "tileset.json"
        ts = json.loads(ts_path.read_text())
        stack = [ts["root"]]
        while stack:
            node = stack.pop()
            c = node.get("content")
            if c is not None and c.get("uri") in moved:
                c["uri"] = moved[c["uri"]]
            stack.extend(node.get("children", []))
        ts_path.write_text(json.dumps(ts, separators=(",", ":")))
    return saved


def _folder_bytes(p: Path) -> int:
    return sum(f.stat().st_size for f in p.rglob("*") if f.is_file())


def _atomic_site(
    out: Path,
    overwrite: bool,
    inputs: Sequence[Path],
    fill: Callable[[Path], SiteReport],
    update: bool = False,
) -> SiteReport:
    """``fill`` the work folder of ``out`` (:class:`terralod.output.Output`), which becomes ``out`` whole; an
    output on, in or around an input is refused first, even with ``overwrite``.

    With ``update`` (after ``terralod update`` of the store), the site is made whole in the scratch folder,
    then each of its files goes through the output's update (:meth:`~terralod.output.Output.write`): a file
    whose bytes are the existing site's stays as it is (same inode, same mtime), the others are rewritten
    and listed, files the new site no longer has are removed; the swap is atomic as always."""
    from terralod.output import Output

    if not update:
        with Output(out, inputs=inputs, overwrite=overwrite) as o:
            rep = fill(o.folder)
        rep.path = out
        return rep
    with Output(out, inputs=inputs, update=True) as o:
        made = o.scratch / "site"
        made.mkdir()
        rep = fill(made)
        for f in sorted(q for q in made.rglob("*") if q.is_file()):
            o.write(f.relative_to(made).as_posix(), f.read_bytes())
            f.unlink()  # the scratch copy goes as it is taken: one site's bytes on the disk, not two
        rep.removed = o.prune()
        rep.rewritten = list(o.rewritten)
    rep.path = out
    return rep


def _write(tmp: Path, plan: SitePlan, terrains: Sequence[Any]) -> SiteReport:
    """The site of ``plan`` into ``tmp``: each of ``terrains`` (one per epoch, in order) as 3D Tiles, pruned
    and shared as the plan says, the pairs' files, the manifest, the page and CesiumJS."""
    from terralod.export.tiles3d import export_3dtiles, split_tileset
    from terralod.output import RECORDS

    rep = SiteReport(tmp, epochs=len(plan.epochs), pairs=len(plan.pairs), area_km2=plan.area_km2)
    (tmp / "epochs").mkdir()
    pruned = 0
    for i, t in enumerate(terrains):
        export_3dtiles(t, tmp / "epochs" / str(i), split_levels=None)  # pruned and shared whole, then split
        (tmp / "epochs" / str(i) / RECORDS).unlink(
            missing_ok=True
        )  # the export's own journal, not the site's
        pruned += prune_tiles(tmp / "epochs" / str(i), plan.keep_error_m)
    rep.keep_error_m = plan.keep_error_m
    shared = share_tiles(tmp / "epochs", len(terrains)) if plan.share_tiles else 0
    for i in range(len(terrains)):  # each epoch's tileset in files a viewer fetches as it refines
        ts_path = tmp / "epochs" / str(i) / "tileset.json"
        for name, js in split_tileset(json.loads(ts_path.read_text())).items():
            (ts_path.parent / name).write_text(json.dumps(js, separators=(",", ":")))
    (tmp / "pairs").mkdir()
    for (
        name,
        data,
    ) in plan.files.items():  # the rasters' tiles (terralod.site.tiles): pairs/KEY-ROLE/LEVEL/R_C
        (tmp / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp / name).write_bytes(data)
    for k, meta in enumerate(plan.pair_meta):
        (tmp / "pairs" / f"{k}.json").write_text(json.dumps(meta, separators=(",", ":")))
    (tmp / "site.json").write_text(json.dumps(plan.manifest(), indent=1))
    copy_page(tmp)
    copy_cesium(tmp)
    for part in ("epochs", "pairs", "cesium"):
        rep.parts[part] = _folder_bytes(tmp / part)
    rep.pruned_bytes = pruned
    rep.parts["page"] = sum((tmp / f).stat().st_size for f in (*PAGE_FILES, "site.json"))
    size = sum(rep.parts.values())
    underline = "=" * len(plan.title)
    (tmp / "README.txt").write_text(README_TXT.format(title=plan.title, underline=underline,
                                                      between=plan.between, size_mb=size / 1e6))  # fmt: skip
    rep.bytes = _folder_bytes(tmp)
    rep.shared_bytes = shared
    return rep


#: A store of epochs whose grid has more cells than this makes its site window by window.
WINDOWED_SITE_CELLS = 1 << 24


def site_from_store(store: str | Path, out: str | Path, *, overwrite: bool = False,
                    coregistration: bool = True, update: bool = False,
                    windowed: bool | None = None) -> SiteReport:  # fmt: skip
    """The site of a store's epochs (``terralod export STORE --format site -o OUT``): every epoch's 3D Tiles,
    the pairs :func:`terralod.site.plan.plan_store_site` plans, measured as ``terralod change`` measures them.
    ``update``: rewrite, in the existing site ``out``, only the files whose bytes change (see
    :func:`_atomic_site`). ``windowed`` (default: a store of epochs whose grid has more than
    :data:`WINDOWED_SITE_CELLS` cells): each pair measured window by window from the samples the store keeps
    (:func:`terralod.change.windowed.measure_change_windowed`, as ``terralod change STORE --from --to``), its
    rasters tiled from its ``dod.tif`` in strips (:func:`_fill_windowed`), never a grid whole."""
    from terralod.terrain import open_terrain

    store, out = Path(store), Path(out)
    with open_terrain(store) as terrain:
        names = list(terrain.epochs)
        if windowed is None:
            meta = getattr(terrain, "meta", {}) or {}
            windowed = int(meta.get("width", 0)) * int(meta.get("height", 0)) > WINDOWED_SITE_CELLS
        if windowed and len(names) >= 2:
            return _atomic_site(out, overwrite, [store], lambda tmp: _store_site_windowed(
                tmp, store, names, coregistration), update)  # fmt: skip
        plan = plan_store_site(terrain, SiteOptions(coregistration=coregistration))
        terrains = [terrain.with_epoch(e) for e in names] if names else [terrain]
        return _atomic_site(out, overwrite, [store], lambda tmp: _write(tmp, plan, terrains), update)


def _store_site_windowed(folder: Path, store: Path, names: list[str], coregistration: bool) -> SiteReport:
    """The site of a store's epochs, each pair measured window by window (:func:`site_from_store`); the
    pairs' ``dod.tif`` and tiles in a scratch folder beside ``folder``, removed after."""
    import tempfile

    from terralod.change.epochs import EpochSource
    from terralod.change.windowed import measure_change_windowed
    from terralod.site.data import pairs_of

    sides = [EpochSource(store, n) for n in names]
    by_name = dict(zip(names, sides, strict=True))
    with tempfile.TemporaryDirectory(prefix=".site-", dir=folder.parent) as tmp:
        scratch = Path(tmp)
        results, dods = [], []
        for k, (a, b) in enumerate(pairs_of(names)):
            dod = scratch / f"{k}-dod.tif"
            results.append(measure_change_windowed(
                by_name[a], by_name[b], names=(f"{store.name} {a}", f"{store.name} {b}"), dod_path=dod,
                sigma_path=scratch / f"{k}-sigma.tif", coregistration=coregistration, dates=pair_dates(a, b),
            ))  # fmt: skip
            dods.append(dod)
        return _fill_windowed(folder, scratch, sides, names, results, dods, store=store,
                              title=f"{store.stem}: how the ground changed", workers=None,
                              options=SiteOptions(coregistration=coregistration))  # fmt: skip


def _on_grid_of(first: Any, hf: Any) -> Any:
    """``hf`` on ``first``'s grid (as given when it is already; else resampled as the change aligns it)."""
    import numpy as np

    from terralod.change.difference import align
    from terralod.heightfield import Heightfield

    if hf.shape == first.shape and tuple(hf.transform) == tuple(first.transform) and hf.crs == first.crs:
        return hf
    z, ok = align(first, hf).after_on_before()
    return Heightfield(np.where(ok, z, np.nan).astype(np.float32), ok, first.transform, first.crs)


def _epoch_name(name: str, i: int) -> str:
    import re

    clean = re.sub(r"[^A-Za-z0-9_.-]+", "-", name).strip("-.")[:64]
    return clean if clean and ".." not in clean else f"survey-{i + 1}"


def site_from_change(heightfields: Sequence[Any], names: Sequence[str], results: Sequence[tuple[str, str, Any]],
                     out: str | Path, *, title: str | None = None, workers: int | None = None,
                     options: SiteOptions | None = None, surveys: Sequence[Sequence[str]] | None = None,
                     crs: Any = None) -> SiteReport:  # fmt: skip
    """The site of a ``terralod change`` run (``--site``): one store with an epoch per DEM (built in the
    output's scratch folder, never part of the site; later DEMs on the first one's grid, so the tiles they
    share are written once) for the 3D Tiles; ``results`` are the pairs already measured (from, to,
    ChangeResult), used as given; the plan measures any other pair it carries with ``options``.

    ``surveys`` (LiDAR: each epoch's LAS/LAZ files, ``crs`` the one given for them): each epoch's 3D Tiles
    are its continuous-scale TIN (Ai et al., 2019: :class:`terralod.tin.DetailIncrementModel`, ground points,
    sub-blocks ``auto``), built in the scratch folder, instead of the gridded surface; the pairs' rasters
    stay the gridded surfaces' (the rule ``terralod change`` states)."""
    from contextlib import ExitStack

    from terralod.output import Output
    from terralod.pyramid.builder import build_store
    from terralod.pyramid.update import update_store
    from terralod.terrain import open_terrain

    out = Path(out)
    epochs = [_epoch_name(n, i) for i, n in enumerate(names)]
    rename = dict(zip(names, epochs, strict=True))
    pairs = [(rename[a], rename[b], r) for a, b, r in results]
    with (
        Output(out) as o,
        ExitStack() as stack,
    ):  # the epochs' stores in its scratch folder, the site in its folder
        if surveys is not None:
            terrains = [stack.enter_context(open_terrain(_tin_store(files, o.scratch / f"epoch-{i}.terra", crs,
                                                                    workers))) for i, files in enumerate(surveys)]  # fmt: skip
        else:
            store = o.scratch / "epochs.terra"
            first = heightfields[0]
            build_store(first, store, workers=workers, epoch=epochs[0])
            for hf, name in zip(heightfields[1:], epochs[1:], strict=True):
                update_store(_on_grid_of(first, hf), store, name, workers=workers)
            terrain = stack.enter_context(open_terrain(store))
            terrains = [stack.enter_context(terrain.with_epoch(e)) for e in epochs]
        ranges = [t.elevation_range_m for t in terrains]
        plan = plan_site(list(zip(epochs, heightfields, strict=True)), title=title or "How the ground changed",
                         elevation_range_m=(min(r[0] for r in ranges), max(r[1] for r in ranges)),
                         options=options or SiteOptions(), measured={(a, b): r for a, b, r in pairs})  # fmt: skip
        rep = _write(o.folder, plan, terrains)
    rep.path = out
    return rep


def _tin_store(files: Sequence[str], path: Path, crs: Any, workers: int | None) -> Path:
    """The continuous-scale TIN store of one LiDAR survey (its ground points; ``terralod build --method tin``
    with its defaults) at ``path``."""
    from terralod.tin import DetailIncrementModel
    from terralod.tin.terra import save_model_to_store

    model = DetailIncrementModel.from_las(
        [Path(f) for f in files], sub_blocks="auto", workers=workers, crs=crs
    )
    save_model_to_store(model, path, workers=workers)
    return path


def site_from_windowed(sides: Sequence[Any], names: Sequence[str], results: Sequence[Any],
                       dod_paths: Sequence[str | Path], out: str | Path, *, store: str | Path | None = None,
                       title: str | None = None, workers: int | None = None,
                       options: SiteOptions | None = None) -> SiteReport:  # fmt: skip
    """The site of epochs measured window by window (``terralod change`` over a region, ``--site``).

    ``sides`` are the epochs' window sources (:mod:`terralod.io.windowed`; or epochs of ``store``,
    :class:`terralod.change.epochs.EpochSource`), oldest first, ``results`` and ``dod_paths`` each pair's
    measured change (:func:`terralod.change.windowed.measure_change_windowed`) and its ``dod.tif``, in
    :func:`~terralod.site.data.pairs_of`'s order. Each epoch's 3D Tiles come from a store built out of core
    (:func:`terralod.pyramid.distributed.build_store_windowed`, in the output's scratch folder, never part of
    the site) or, for epochs of ``store``, from that store; the pairs' rasters are read in strips of rows from
    each ``dod.tif`` and BEFORE's source and their tiles kept on disk
    (:func:`terralod.site.plan.plan_windowed_site`). The memory is the out-of-core build's, then the 3D Tiles
    export's, then a strip of rows and two tile rows a pyramid level."""
    from terralod.output import Output

    out = Path(out)
    with Output(out) as o:
        rep = _fill_windowed(o.folder, o.scratch, sides, names, results, dod_paths, store=store,
                             title=title or "How the ground changed", workers=workers, options=options)  # fmt: skip
    rep.path = out
    return rep


def _fill_windowed(folder: Path, scratch: Path, sides: Sequence[Any], names: Sequence[str], results: Sequence[Any],
                   dod_paths: Sequence[str | Path], *, store: str | Path | None, title: str,
                   workers: int | None, options: SiteOptions | None) -> SiteReport:  # fmt: skip
    """:func:`site_from_windowed` into ``folder``, its stores and tiles in ``scratch``."""
    from contextlib import ExitStack

    import numpy as np

    from terralod.pyramid.distributed import build_store_windowed
    from terralod.site.data import PairRasters, pairs_of
    from terralod.site.plan import plan_windowed_site
    from terralod.site.tiles import FolderFiles, raster_rows
    from terralod.terrain import open_terrain

    epochs = tuple(_epoch_name(n, i) for i, n in enumerate(names))
    by_name = dict(zip(epochs, sides, strict=True))
    valid = [0]

    def rows_of(src: Any, count: bool) -> Any:
        def rows(r0: int, r1: int) -> np.ndarray:
            z, ok = src.read(r0, 0, r1, src.width)
            if count:
                valid[0] += int(np.count_nonzero(ok))
            return np.where(ok, z, np.nan).astype("<f4")

        return rows

    with ExitStack() as stack:
        if store is None:
            terrains = []
            for i, src in enumerate(sides):
                build_store_windowed(src, scratch / f"epoch-{i}.terra", workers=workers)
                terrains.append(stack.enter_context(open_terrain(scratch / f"epoch-{i}.terra")))
        else:
            terrain = stack.enter_context(open_terrain(store))
            terrains = [stack.enter_context(terrain.with_epoch(s.epoch)) for s in sides]
        pairs = []
        for k, ((a, _), result, dod) in enumerate(
            zip(pairs_of(list(epochs)), results, dod_paths, strict=True)
        ):
            dod_rows, shape, close = raster_rows(dod)
            stack.callback(close)
            before = by_name[a]
            pairs.append((result, PairRasters(dod_rows, rows_of(before, k == 0), shape, before.transform)))
        ranges = [t.elevation_range_m for t in terrains]
        plan = plan_windowed_site(
            epochs, pairs, crs=sides[0].crs, valid_cells=lambda: valid[0], title=title,
            elevation_range_m=(min(r[0] for r in ranges), max(r[1] for r in ranges)),
            files=FolderFiles(scratch / "pair-tiles"), options=options or SiteOptions(),
        )  # fmt: skip
        return _write(folder, plan, terrains)
