"""``terralod export STORE --format 3dtiles|quantized-mesh -o DIR``: the web globe's two formats.

3D Tiles 1.1 writes ``DIR/tileset.json`` and one glb per LOD node; quantized-mesh 1.0 writes
``DIR/layer.json`` and gzip'd ``Z/X/Y.terrain`` tiles (serve them with ``Content-Encoding: gzip``, as
``terralod serve`` does). Heights are the DEM's as read (no geoid change). The output appears whole or not
at all; a folder that is not empty needs ``--overwrite``.
"""

from __future__ import annotations

import click

from terralod.cli._common import console, progress, refuse_output_holding_inputs, require_extra


@click.command()
@click.argument("store")
@click.option(
    "--format",
    "fmt",
    type=click.Choice(["3dtiles", "quantized-mesh"]),
    required=True,
    help="3dtiles (OGC 3D Tiles 1.1, glb per tile) or quantized-mesh (Cesium terrain 1.0).",
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
def export(store: str, fmt: str, output: str, metric: str, epoch: str | None, overwrite: bool) -> None:
    """Export a .terra store as 3D Tiles or Cesium quantized-mesh terrain."""
    require_extra("export", "web")
    refuse_output_holding_inputs(output, [store])  # --overwrite would delete it
    from terralod.export.common import check_exportable, check_output
    from terralod.export.geodesy import Geodesy
    from terralod.terrain import open_terrain

    with open_terrain(store) as terrain:
        if epoch is not None:
            check_exportable(terrain, epoch)  # a missing epoch: one line naming the ones there are
        check_output(output, overwrite)  # refusals first: one line, before any progress output
        Geodesy(terrain.crs, store)
        check_exportable(terrain, epoch)
        _run(terrain, fmt, output, metric, epoch, overwrite)


def _run(terrain, fmt: str, output: str, metric: str, epoch: str | None, overwrite: bool) -> None:
    from terralod.export import export_3dtiles, export_quantized_mesh

    with progress("exporting") as prog:
        task = prog.add_task(fmt, total=None)

        def cb(done: int, total: int) -> None:
            prog.update(task, completed=done, total=total)

        if fmt == "3dtiles":
            rep = export_3dtiles(
                terrain, output, metric=metric, epoch=epoch, overwrite=overwrite, progress=cb
            )
        else:
            rep = export_quantized_mesh(terrain, output, epoch=epoch, overwrite=overwrite, progress=cb)
    console.print(f"{fmt}: {rep.tiles} tiles, {rep.triangles:,} triangles, {rep.bytes / 1e6:.2f} MB in "
                  f"{rep.seconds:.1f} s → {output}")  # fmt: skip
