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
"""

from __future__ import annotations

import click

from terralod.cli._console import console, progress
from terralod.cli._errors import require_extra
from terralod.cli._options import check_raster_size
from terralod.output import Lock, Output, refuse_inputs, work_path


@click.command()
@click.argument("store")
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
    "list them; the others are left untouched (3dtiles, quantized-mesh).",
)
def export(
    store: str, fmt: str, output: str, metric: str, epoch: str | None, overwrite: bool, gzip_tiles: bool,
    normals: bool, resume: bool, update_output: bool,
) -> None:  # fmt: skip
    """Export a .terra store (or, for quantized-mesh, a DEM file) as 3D Tiles or Cesium quantized-mesh."""
    require_extra("export", "web")
    refuse_inputs(output, [store])  # even with --overwrite: replacing it would delete the input
    if fmt == "site" and (resume or update_output):
        raise click.BadParameter(
            "--resume and --update are for 3dtiles and quantized-mesh", param_hint="--format"
        )
    opts = {"overwrite": overwrite, "resume": resume, "update": update_output}
    from terralod.export.common import check_exportable
    from terralod.export.geodesy import Geodesy
    from terralod.terrain import _is_sqlite, open_terrain

    if fmt == "site":
        require_extra("export --format site", "change")  # the pairs are measured as `terralod change` does
        _run_site(store, output, overwrite)
        return
    if _is_dem(store, _is_sqlite):
        if fmt == "3dtiles":
            from terralod.errors import InputError

            raise InputError(
                "is a DEM; 3D Tiles are written from a store (run `terralod build` first)", store
            )
        _run_dem(store, output, epoch, opts, gzip_tiles, normals)
        return
    with open_terrain(store) as terrain:
        if epoch is not None:
            check_exportable(terrain, epoch)  # a missing epoch: one line naming the ones there are
        _output(output, store, opts).check()  # refusals first: one line, before any progress output
        Geodesy(terrain.crs, store)
        check_exportable(terrain, epoch)
        _run(terrain, fmt, output, metric, epoch, opts, gzip_tiles, normals)


def _output(output: str, source: str, opts: dict[str, bool]) -> Output:
    """The output of ``terralod export`` (its refusals are checked before the long work)."""
    return Output(
        output, inputs=[source], overwrite=opts["overwrite"], resume=opts["resume"], update=opts["update"]
    )


def _run_site(store: str, output: str, overwrite: bool) -> None:
    """The change site of a store's epochs (:mod:`terralod.site`), its size printed."""
    from terralod.site import site_from_store

    rep = site_from_store(store, output, overwrite=overwrite)
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
    from pathlib import Path

    p = Path(path)
    return p.is_file() and not is_sqlite(p)


def _run_dem(
    dem: str, output: str, epoch: str | None, opts: dict[str, bool], gzip_tiles: bool, normals: bool = False
) -> None:
    from terralod.errors import InputError
    from terralod.export.source import source_from_dem

    if epoch is not None:
        raise InputError("is a DEM; --epoch selects an epoch of a store", dem)
    check_raster_size(dem)  # the one size limit, from the header, before any sample is read
    _output(output, dem, opts).check()
    source = source_from_dem(dem)
    _run(source, "quantized-mesh", output, "vertical", None, opts, gzip_tiles, normals)


def _run(
    terrain, fmt: str, output: str, metric: str, epoch: str | None, opts: dict[str, bool],
    gzip_tiles: bool = False, normals: bool = False,
) -> None:  # fmt: skip
    from terralod.export import export_3dtiles, export_quantized_mesh

    adopted = Lock.read(work_path(output)) if opts["resume"] else None

    with progress("exporting") as prog:
        task = prog.add_task(fmt, total=None)

        def cb(done: int, total: int) -> None:
            prog.update(task, completed=done, total=total)

        if fmt == "3dtiles":
            rep = export_3dtiles(terrain, output, metric=metric, epoch=epoch, progress=cb, **opts)
        else:
            rep = export_quantized_mesh(terrain, output, epoch=epoch, gzip_tiles=gzip_tiles, normals=normals,
                                        progress=cb, **opts)  # fmt: skip
    if rep.extra.get("resumed") and adopted is not None:
        console.print(f"resumed the export interrupted in {work_path(output).name} ({adopted.describe()})",
                      highlight=False)  # fmt: skip
    console.print(f"{fmt}: {rep.tiles} tiles, {rep.triangles:,} triangles, {rep.bytes / 1e6:.2f} MB in "
                  f"{rep.seconds:.1f} s → {output}")  # fmt: skip
    if opts["update"]:
        changed, removed = rep.extra["rewritten"], rep.extra["removed"]
        console.print(f"updated: {len(changed)} file(s) rewritten, {len(removed)} removed, the others untouched",
                      highlight=False)  # fmt: skip
        for rel in changed:
            console.print(f"  rewritten {rel}", highlight=False)
        for rel in removed:
            console.print(f"  removed {rel}", highlight=False)
