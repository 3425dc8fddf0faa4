"""``terralod edit STORE --polygon cut.geojson --depth-m 12`` (or ``--patch slide.tif``): an excavation, a
fill (negative depth) or a pasted raster as a new epoch, rebuilding only the tiles it touches."""

from __future__ import annotations

import click

from terralod.cli._console import console


@click.command()
@click.argument("store")
@click.option(
    "--polygon", default=None, help="GeoJSON polygon(s) to dig (CRS from its crs member, else lon/lat)."
)
@click.option(
    "--depth-m", type=float, default=None, help="Metres to lower the polygon by (negative: fill/dam)."
)
@click.option("--patch", default=None, help="Raster pasted over the terrain (a landslide, a surveyed pit).")
@click.option("--epoch", default=None, help="Name of the new epoch (default: edit-N).")
@click.option("--from", "base", default=None, help="Epoch to edit (default: the latest).")
@click.option("--resume", is_flag=True, help="Finish an interrupted edit of the same epoch.")
@click.option("--workers", type=click.IntRange(1, 256), default=None, help="Threads (default: all cores).")
def edit(store: str, polygon, depth_m, patch, epoch, base, resume: bool, workers) -> None:
    """Dig, fill or patch the terrain of STORE and keep the result as a new epoch.

    Rerunning an edit that finished (the same polygon and depth, or patch) digs nothing a second time: it
    says which epoch holds it. To apply it once more, name a new epoch with --epoch.
    """
    from terralod.change.epochs import EditAlreadyDone, prepare_edit
    from terralod.cli.update import print_update, run_update

    if (polygon is None) == (patch is None):
        raise click.UsageError("give --polygon with --depth-m, or --patch")
    if polygon is not None and depth_m is None:
        raise click.BadParameter(
            "--polygon needs --depth-m (metres down; negative for a fill)", param_hint="--depth-m"
        )
    try:
        res, name, base_name, info = prepare_edit(store, polygon=polygon, depth_m=depth_m, patch=patch, epoch=epoch,
                                                  base=base, resume=resume)  # fmt: skip
    except EditAlreadyDone as done:  # a rerun after the edit committed (e.g. killed before it said so)
        console.print(f"{store}: {done.message}", highlight=False, markup=False)
        return
    d = res.description
    what = {"excavation": "removed", "fill": "added", "patch": "changed (net)"}[d["edit"]]
    console.print(f"{d['edit']}: {abs(res.volume_m3):,.0f} m³ {what} over {d['cells']:,} cells")
    rep = run_update(res.heightfield, store, name, base=base_name, resume=resume, workers=workers, kind="edit",
                     info=info)  # fmt: skip
    print_update(rep)
