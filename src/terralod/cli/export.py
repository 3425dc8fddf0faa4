"""``terralod export STORE|DEM --format 3dtiles|quantized-mesh -o DIR``: the web globe's two formats.

3D Tiles 1.1 writes ``DIR/tileset.json`` and one glb per LOD node (from a store). Quantized-mesh 1.0 writes
``DIR/layer.json``, ``DIR/errors.json`` (measured error per tile) and ``Z/X/Y.terrain`` tiles, from a store
or straight from a DEM file (its samples meshed into Cesium's geographic tiles directly, no store and no
UTM round trip). Tiles are uncompressed, so any static file server serves them as they are; ``--gzip``
writes them gzip'd, for a host configured to send ``Content-Encoding: gzip`` with ``.terrain`` files
(CesiumJS cannot read gzip'd tiles without that header). Heights are the DEM's as read (no geoid change).

The output appears whole or not at all (:class:`terralod.output.Output`: written in ``.DIR.work`` beside it,
renamed into place at the end); a folder that is not empty needs ``--overwrite``. ``--resume`` finishes an
interrupted export of the same input and options: the tiles it wrote are kept, the rest encoded, and the
result is byte for byte the uninterrupted export's (a tile is a pure function of its code). ``--update``
rewrites, in an existing output, only the files whose bytes change (after ``terralod update``): the others
keep their inode and mtime, so a sync to a web host sends only what changed.

A region in, for quantized-mesh: several DEMs, a quoted glob, a folder (its rasters), a GDAL VRT, SRTM
``.hgt`` or ``.hgt.zip`` as downloaded — one grid (:func:`terralod.io.region.resolve_region`: the same CRS,
resolution and grid, or one line naming the two files that differ). Where files overlap the last one listed
wins (a glob's or folder's files in name order); cells no file covers are nodata (filled, flagged in the
water mask, never in a declared error). Every file is read once before anything is written (an unreadable
one is named, exit 2) and the free disk is checked against an estimate; a WGS 84 longitude/latitude region, or
one projected in metres (UTM, a national grid: a county of LiDAR DEM tiles), is then read a window at a time
(memory independent of its size; a coarse tile's error is measured against its samples strip by strip).
``--bbox`` and ``--min-zoom`` / ``--max-zoom`` export a part: the same tiles as the whole export, fewer of
them (3D Tiles too: the zooms are the levels of the tree, the nodes above ``--min-zoom`` kept without content).

3D Tiles geometry (``--glb-geometry``): ``quantized`` (default) writes KHR_mesh_quantization glbs
(UNSIGNED_SHORT positions on a power-of-two grid folded into the node's scale and translation, BYTE
normals), ``meshopt`` also compresses them with EXT_meshopt_compression (needs node and the npm
``meshoptimizer`` package, as ``npm ci`` installs it), ``float`` writes float32 as before. The shift the
quantisation may add (√3/2 of a grid step) is counted in every tile's declared error. ``--max-error-m E``
stops the tree at a finest declared error: the tiles whose parent already declares at most E are left out
(3D Tiles only).

``--dask local|tcp://HOST:PORT`` (``--dask-workers N``: the local cluster's worker processes, 2) encodes the
tiles on a Dask cluster, for every export but the site: each worker opens the store, DEM or region itself
and reads its own windows of it; only tile bytes come back. The output is the local run's, byte for byte,
written here through the same journal (``--resume`` and ``--update`` as without it).
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import click

from terralod.cli._console import PlainProgress, console, err_console
from terralod.cli._errors import require_extra
from terralod.cli._options import check_raster_size, memory_option, numbers
from terralod.output import Lock, Output, refuse_inputs, scratch_beside, work_path


@click.command()
@click.argument("inputs", nargs=-1, required=True, metavar="STORE|DEM...")
@click.option(
    "--format",
    "fmt",
    type=click.Choice(["3dtiles", "quantized-mesh", "site"]),
    required=True,
    help="3dtiles (OGC 3D Tiles 1.1, glb per tile), quantized-mesh (Cesium terrain 1.0) or site (a folder any "
    "static web host serves: a store's epochs and the change between them, for people who are not experts).",
)
@click.option("-o", "--output", required=True, help="Output folder (tileset.json / layer.json inside).")
@click.option(
    "--metric",
    type=click.Choice(["hausdorff", "vertical"]),
    default="hausdorff",
    show_default=True,
    help="3D Tiles geometricError: the measured one-sided Hausdorff or max vertical error.",
)
@click.option("--epoch", default=None, help="Epoch (date) of a store with epochs.")
@click.option("--overwrite", is_flag=True, help="Replace a non-empty output folder.")
@click.option(
    "--gzip",
    "gzip_tiles",
    is_flag=True,
    help="quantized-mesh: write gzip'd tiles (only for a host that sends Content-Encoding: gzip with them).",
)
@click.option(
    "--normals",
    is_flag=True,
    help="quantized-mesh: add oct-encoded vertex normals (about 0.7 B per triangle gzip'd; CesiumJS uses "
    "them only with requestVertexNormals, for lighting).",
)
@click.option(
    "--resume",
    is_flag=True,
    help="Finish an interrupted export into the same folder: the tiles it wrote are kept, not encoded again "
    "(3dtiles, quantized-mesh).",
)
@click.option(
    "--update",
    "update_output",
    is_flag=True,
    help="Rewrite, in an existing output, only the files whose bytes change (after `terralod update`) and "
    "list them; the others are left untouched (3dtiles, quantized-mesh, site).",
)
@click.option(
    "--bbox",
    default=None,
    metavar="W,S,E,N",
    help="Export only the tiles that meet this box (degrees); each tile is the whole export's (quantized-mesh, "
    "3dtiles).",
)
@click.option("--min-zoom", type=click.IntRange(0, 30), default=0, show_default=True,
              help="First level written (3dtiles: level of the tree; the coarser ones without content).")  # fmt: skip
@click.option("--max-zoom", type=click.IntRange(0, 30), default=None,
              help="Last level written (default: the finest the data holds).")  # fmt: skip
@click.option(
    "--glb-geometry",
    type=click.Choice(["float", "quantized", "meshopt"]),
    default=None,
    help="3dtiles: glb positions and normals as quantized (the default: KHR_mesh_quantization, int16 "
    "positions, int8 normals; the quantisation counted in each tile's error), meshopt (also "
    "EXT_meshopt_compression, through node and the npm meshoptimizer package) or float (float32).",
)
@click.option(
    "--max-error-m",
    type=click.FloatRange(min=0.0),
    default=None,
    metavar="E",
    help="3dtiles: stop at a finest declared error of E metres: leave out the tiles whose parent already "
    "declares at most E (default: down to the finest level the store holds).",
)
@click.option(
    "--vertical-datum", default=None,
    help="What the heights are above when the store's or DEM's CRS does not say: egm96 (SRTM, Copernicus), "
    "egm2008, navd88, ellipsoid or a vertical CRS (EPSG:5773); the tiles then carry heights above the WGS 84 "
    "ellipsoid (the operation PROJ used is recorded in tileset.json / layer.json).",
)  # fmt: skip
@click.option(
    "--dask",
    "dask_address",
    default=None,
    help="Encode the tiles on Dask: local (a LocalCluster of worker processes) or tcp://HOST:PORT (a "
    "scheduler); the same bytes as without it (3dtiles, quantized-mesh).",
)
@click.option(
    "--dask-workers", type=click.IntRange(1), default=None, help="Worker processes of --dask local (2)."
)
@memory_option
def export(
    inputs: tuple[str, ...], fmt: str, output: str, metric: str, epoch: str | None, overwrite: bool,
    gzip_tiles: bool, normals: bool, resume: bool, update_output: bool, bbox: str | None, min_zoom: int,
    max_zoom: int | None, glb_geometry: str | None, max_error_m: float | None, vertical_datum: str | None,
    dask_address: str | None, dask_workers: int | None, memory_bytes: int | None,
) -> None:  # fmt: skip
    """Export a .terra store as 3D Tiles or Cesium quantized-mesh, or DEMs (a region: files, a quoted glob, a
    folder, a VRT, .hgt/.hgt.zip; where they overlap the last one listed wins) as quantized-mesh."""
    require_extra("export", "web")
    refuse_inputs(output, [i for i in inputs if Path(i).exists()])  # even with --overwrite
    part = _part(bbox, min_zoom, max_zoom)
    if fmt != "3dtiles" and (glb_geometry is not None or max_error_m is not None):
        raise click.BadParameter("--glb-geometry and --max-error-m are for 3dtiles", param_hint="--format")
    tiles = {"geometry": glb_geometry or "quantized", "max_error_m": max_error_m}
    if dask_address:
        if fmt == "site":
            raise click.BadParameter("--dask is for 3dtiles and quantized-mesh", param_hint="--format")
        require_extra("export --dask", "dask")
    dask = _dask_plan(dask_address, dask_workers, memory_bytes)
    if len(inputs) > 1 or not _is_one_file(inputs[0]):
        if fmt != "quantized-mesh":
            raise click.BadParameter("several inputs, a glob or a folder make a region of DEMs: quantized-mesh "
                                     "only", param_hint="--format")  # fmt: skip
        with scratch_beside(output):  # the reader's spill file on the output's disk
            _run_dem(list(inputs), output, epoch, {"overwrite": overwrite, "resume": resume,
                     "update": update_output}, gzip_tiles, normals, part, dask)  # fmt: skip
        return
    store = inputs[0]
    if not part.whole and fmt == "site":
        raise click.BadParameter(
            "--bbox, --min-zoom and --max-zoom are for quantized-mesh and 3dtiles", param_hint="--format"
        )
    if fmt == "site" and resume:
        raise click.BadParameter("--resume is for 3dtiles and quantized-mesh", param_hint="--format")
    opts = {
        "overwrite": overwrite,
        "resume": resume,
        "update": update_output,
        "vertical_datum": vertical_datum,
    }
    from terralod.export.common import check_exportable
    from terralod.export.geodesy import Geodesy
    from terralod.terrain import _is_sqlite, open_terrain

    if fmt == "site":
        require_extra("export --format site", "change")  # the pairs are measured as `terralod change` does
        _run_site(store, output, overwrite, update_output)
        return
    if _is_dem(store, _is_sqlite):
        if fmt == "3dtiles":
            from terralod.errors import InputError

            raise InputError(
                "is a DEM; 3D Tiles are written from a store (run `terralod build` first)", store
            )
        with scratch_beside(output):
            _run_dem([store], output, epoch, opts, gzip_tiles, normals, part, dask)
        return
    with open_terrain(store) as terrain:
        if epoch is not None:
            check_exportable(terrain, epoch)  # a missing epoch: one line naming the ones there are
        _output(output, store, opts).check()  # refusals first: one line, before any progress output
        Geodesy(terrain.crs, store)
        check_exportable(terrain, epoch)
        with scratch_beside(output):
            _run(terrain, fmt, output, metric, epoch, opts, gzip_tiles, normals, part, tiles, dask)


def _part(bbox: str | None, min_zoom: int, max_zoom: int | None) -> Any:
    """The part of a quantized-mesh export the options ask for (:class:`~terralod.export.quantized_mesh.Part`)."""
    from terralod.export.quantized_mesh import Part

    box = numbers(bbox, 4, "--bbox", "W,S,E,N in degrees (west,south,east,north)")
    try:
        return Part(bbox=box, min_zoom=min_zoom, max_zoom=max_zoom)  # type: ignore[arg-type]
    except ValueError as exc:
        raise click.BadParameter(
            str(exc), param_hint="--bbox" if "box" in str(exc) else "--max-zoom"
        ) from None


def _is_one_file(text: str) -> bool:
    """One store or DEM file (or a missing path, left to open_terrain's message): not a folder, a zip or a
    glob, which make a region."""
    p = Path(text)
    if p.is_dir() or (p.is_file() and p.name.lower().endswith(".zip")):
        return False
    return p.exists() or not any(ch in text for ch in "*?[")


def _output(output: str, source: str, opts: dict[str, bool]) -> Output:
    """The output of ``terralod export`` (its refusals are checked before the long work)."""
    return Output(
        output, inputs=[source], overwrite=opts["overwrite"], resume=opts["resume"], update=opts["update"]
    )


def _run_site(store: str, output: str, overwrite: bool, update: bool = False) -> None:
    """The change site of a store's epochs (:mod:`terralod.site`), its size printed (with ``update``, the
    files rewritten and removed)."""
    from terralod.site import site_from_store

    rep = site_from_store(store, output, overwrite=overwrite, update=update)
    if update:
        console.print(f"updated: {len(rep.rewritten)} file(s) rewritten, {len(rep.removed)} removed, the others "
                      "untouched", highlight=False)  # fmt: skip
        for rel in rep.rewritten:
            console.print(f"  rewritten {rel}", highlight=False)
        for rel in rep.removed:
            console.print(f"  removed {rel}", highlight=False)
    d = rep.as_dict()
    parts = ", ".join(f"{k} {v / 1e6:.1f} MB" for k, v in d["parts"].items())
    console.print(
        f"{output}: site of {d['epochs']} epoch(s), {d['pairs']} pair(s): {d['bytes'] / 1e6:.1f} MB ({parts}); "
        f"{d['bytes'] / 1e6 / max(d['area_km2'], 1e-9):.2f} MB per km² of terrain. Serve it with "
        f"`python -m http.server` in that folder (see its README.txt).",
        highlight=False,
    )


def _is_dem(path: str, is_sqlite) -> bool:  # noqa: ANN001
    """A file that is not a .terra store (a missing path is left to open_terrain's message)."""
    p = Path(path)
    return p.is_file() and not is_sqlite(p)


def _run_dem(
    dems: list[str], output: str, epoch: str | None, opts: dict[str, bool], gzip_tiles: bool,
    normals: bool = False, part: Any = None, dask: tuple[Any, ...] = (None, None, None),
) -> None:  # fmt: skip
    """A DEM or a region of DEMs exported as quantized-mesh: every file read once first (an unreadable one
    named in one line), then the tiles, a window of the region at a time for WGS 84 lon/lat data."""
    from terralod.errors import InputError
    from terralod.export.source import source_from_dem, source_from_region
    from terralod.fill import check_dimensions
    from terralod.io.region import resolve_region

    if epoch is not None:
        raise InputError("is a DEM; --epoch selects an epoch of a store", dems[0])
    if len(dems) == 1 and _is_one_file(dems[0]):
        try:
            one = resolve_region(dems)
        except InputError:  # a heightmap with a sidecar frame, a .npy: the in-memory readers say what it is
            one = None
        if one is None or not _windowed(one.crs):  # one file read whole, as before regions existed
            check_raster_size(dems[0])  # the one size limit, from the header, before any sample is read
            _output(output, dems[0], opts).check()
            _run(source_from_dem(dems[0]), "quantized-mesh", output, "vertical", None, opts, gzip_tiles, normals,
                 part, None, dask)  # fmt: skip
            return
    region = resolve_region(dems)  # headers only: one grid, or one line naming the two files that differ
    if not _windowed(region.crs):  # read whole, in memory: the one size limit, from the headers
        check_dimensions(region.height, region.width, region.name)
    Output(output, inputs=region.files, overwrite=opts["overwrite"], resume=opts["resume"],
           update=opts["update"]).check()  # fmt: skip
    source = source_from_region(region)
    _run(source, "quantized-mesh", output, "vertical", None, opts, gzip_tiles, normals, part, None, dask)


def _windowed(crs: Any) -> bool:
    """A region read window by window: WGS 84 lon/lat, or projected in metres with heights in metres."""
    from terralod.export.source import windowed_crs

    return windowed_crs(crs)


def _run(
    terrain, fmt: str, output: str, metric: str, epoch: str | None, opts: dict[str, bool],
    gzip_tiles: bool = False, normals: bool = False, part: Any = None, tiles: dict[str, Any] | None = None,
    dask: tuple[Any, ...] = (None, None, None),
) -> None:  # fmt: skip
    from terralod.export import export_3dtiles, export_quantized_mesh

    adopted = Lock.read(work_path(output)) if opts["resume"] else None

    with _client(*dask) as client, _progress("exporting") as prog:
        tasks: list[Any] = []  # added at the first tile: a refusal before it prints no progress

        def cb(done: int, total: int) -> None:
            if not tasks:
                tasks.append(prog.add_task(fmt, total=total))
            prog.update(tasks[0], completed=done, total=total)

        if fmt == "3dtiles":
            rep = export_3dtiles(terrain, output, metric=metric, epoch=epoch, progress=cb, client=client,
                                 part=part, **(tiles or {}), **opts)  # fmt: skip
        else:
            rep = export_quantized_mesh(terrain, output, epoch=epoch, gzip_tiles=gzip_tiles, normals=normals,
                                        part=part, progress=cb, client=client, **opts)  # fmt: skip
    if rep.extra.get("resumed") and adopted is not None:
        console.print(f"resumed the export interrupted in {work_path(output).name} ({adopted.describe()})",
                      highlight=False)  # fmt: skip
    worst = rep.extra.get("worst_error_m")
    worst_text = f"; worst declared error {worst:.2f} m" if worst is not None else ""
    console.print(f"{fmt}: {rep.tiles} tiles, {rep.triangles:,} triangles, {rep.bytes / 1e6:.2f} MB in "
                  f"{rep.seconds:.1f} s{worst_text} → {output}", highlight=False)  # fmt: skip
    if opts["update"]:
        changed, removed = rep.extra["rewritten"], rep.extra["removed"]
        console.print(f"updated: {len(changed)} file(s) rewritten, {len(removed)} removed, the others untouched",
                      highlight=False)  # fmt: skip
        if "encoded" in rep.extra:  # the tiles whose inputs changed (terralod.export.incremental)
            console.print(f"encoded {rep.extra['encoded']} of {rep.tiles} tiles", highlight=False)
        for rel in changed:
            console.print(f"  rewritten {rel}", highlight=False)
        for rel in removed:
            console.print(f"  removed {rel}", highlight=False)


def _dask_plan(address: str | None, workers: int | None, memory_bytes: int | None) -> tuple[Any, ...]:
    """(address, local workers, each one's memory limit) within ``--memory`` (:func:`terralod.memory.plan_memory`,
    a batch of tiles as the unit); a budget that cannot hold one is refused in one line, before any work."""
    from terralod.errors import InputError
    from terralod.memory import EXPORT_UNIT_BYTES, plan_memory

    try:
        plan = plan_memory(memory_bytes, threads=1, dask_workers=workers, dask_local=address == "local",
                           unit_bytes=EXPORT_UNIT_BYTES)  # fmt: skip
    except ValueError as exc:
        raise InputError(str(exc), "--memory") from None
    return address, plan.dask_workers, plan.worker_bytes


@contextmanager
def _client(address: str | None, workers: int | None, memory_limit: int | None = None) -> Iterator[Any]:
    """The Dask client of ``--dask`` (None without it), as ``terralod build`` makes it; a local cluster is
    closed at the end."""
    if not address:
        yield None
        return
    from terralod.pyramid.distributed import dask_client

    client = dask_client(address, n_workers=workers, memory_limit=memory_limit)
    try:
        yield client
    finally:
        cluster = client.cluster if address == "local" else None
        client.close()
        if cluster is not None:
            cluster.close()


class _PlainProgress(PlainProgress):
    """Plain progress lines with the time left (from the rate so far)."""

    def _line(self, task: int) -> None:
        import time

        t = self._tasks[task]
        t["printed"] = (t["completed"], t["total"])
        el = time.monotonic() - t["t0"]
        msg = f"{self.label} {t['name']}: {t['completed']:.0f}"
        if t["total"]:
            msg += f"/{t['total']:.0f} ({100.0 * t['completed'] / t['total']:.0f} %)"
        msg += f", {el:.0f} s"
        if t["total"] and 0 < t["completed"] < t["total"]:
            msg += f", about {el * (t['total'] - t['completed']) / t['completed']:.0f} s left"
        click.echo(msg, err=True, file=self.stream)


def _progress(label: str) -> Any:
    """A bar with tiles done / total, elapsed and time left on a terminal; plain lines otherwise."""
    import sys

    if not sys.stderr.isatty():
        return _PlainProgress(label)
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    return Progress(
        TextColumn(f"[bold]{label}[/bold] {{task.description}}"), BarColumn(), MofNCompleteColumn(),
        TimeElapsedColumn(), TimeRemainingColumn(), console=err_console, transient=False,
    )  # fmt: skip
