"""``terralod update STORE DEM --epoch DATE``: add an epoch of the same terrain to a store, rebuilding only
the tiles whose source windows changed (:mod:`terralod.pyramid.update`)."""

from __future__ import annotations

from typing import Any

import click

from terralod.cli._console import console, progress
from terralod.cli._options import check_raster_size, load, memory_option, read_options


def print_update(rep: Any) -> None:
    """One summary of an :class:`terralod.pyramid.update.UpdateReport`."""
    if not rep.complete:
        console.print(
            f"{rep.path}: epoch {rep.epoch} INCOMPLETE: {rep.tiles_skipped + rep.tiles_built} of "
            f"{rep.tiles_dirty} tiles rebuilt (finish with --resume)"
        )
        return
    console.print(
        f"{rep.path}: epoch {rep.epoch} added (from {rep.base_epoch}): {rep.changed_samples:,} samples changed, "
        f"{rep.tiles_dirty} of {rep.tiles_total} tiles rebuilt ({rep.tiles_built} now), {rep.tiles_shared} "
        f"shared, in {rep.seconds:.2f} s ({rep.ms_per_tile:.1f} ms per rebuilt tile)"
    )


def run_update(hf, store: str, epoch: str, **kw: Any):
    """:func:`terralod.pyramid.update.update_store` with a progress bar."""
    from pathlib import Path

    from terralod.pyramid.update import update_store

    with progress("updating") as prog:
        task = prog.add_task(Path(store).name, total=None)

        def cb(done: int, total: int) -> None:
            prog.update(task, completed=done, total=total)

        return update_store(hf, store, epoch, progress=cb, **kw)


@click.command()
@click.argument("store")
@click.argument("dem", metavar="DEM...", nargs=-1, required=True)
@click.option("--epoch", required=True, help="Name of the new epoch, e.g. the survey date 2007-07-05.")
@click.option(
    "--from", "base", default=None, help="Epoch to share unchanged tiles with (default: the latest)."
)
@click.option("--resume", is_flag=True, help="Finish an interrupted update of the same epoch and DEM.")
@click.option("--workers", type=click.IntRange(1, 256), default=None, help="Threads (default: all cores).")
@click.option(
    "--dask", "dask_address", default=None,
    help="Rebuild on Dask (window by window): local (a LocalCluster) or tcp://HOST:PORT (a scheduler).",
)  # fmt: skip
@click.option(
    "--dask-workers", type=click.IntRange(1), default=None, help="Worker processes of --dask local (2)."
)
@memory_option
@read_options
def update(store: str, dem: tuple[str, ...], epoch: str, base, resume: bool, workers, dask_address,
           dask_workers, memory_bytes, **read: Any) -> None:  # fmt: skip
    """Add DEM as epoch EPOCH of STORE (same grid and CRS), rebuilding only the tiles that changed.

    DEM may be a mosaic (several files, a folder, a quoted glob, a VRT) or a raster too large to hold: it is
    then read window by window, compared with the base epoch's samples the store keeps (a store built with
    ``--epoch``), and the dirty tiles rebuilt as ``terralod build`` does out of core (``--dask`` too)."""
    from terralod.cli.build import windowed_build
    from terralod.pyramid.update import check_update
    from terralod.store import open_store

    with open_store(store) as s:  # a missing or foreign store is named before the DEM is read
        samples = int(s.meta.get("width", 0)) * int(s.meta.get("height", 0))
    for path in dem:  # the size limit before anything is read
        check_raster_size(path)
    from terralod.memory import in_memory_samples

    if windowed_build(dem, dask_address, epoch, memory_bytes) or samples > in_memory_samples(memory_bytes):
        from terralod.cli._windowed import run_windowed_update

        print_update(run_windowed_update(dem, store, epoch, base=base, resume=resume, workers=workers,
                                         dask_address=dask_address, dask_workers=dask_workers, read=read,
                                         memory_bytes=memory_bytes))  # fmt: skip
        return
    hf = load(dem[0], **read)
    check_update(store, hf, epoch, base=base, resume=resume)  # bad input: one line, before any progress
    print_update(run_update(hf, store, epoch, base=base, resume=resume, workers=workers))
