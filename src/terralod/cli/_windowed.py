"""``terralod build`` and ``terralod update`` out of core: a mosaic, ``--dask local|tcp://HOST:PORT``, or a
raster too large to hold, built by :func:`terralod.pyramid.distributed.build_store_windowed` (an epoch added by
:func:`terralod.pyramid.update.update_store_windowed`) with a progress bar. A geographic
or Mercator input is a :class:`terralod.io.windowed.WarpedSource` (warped block by block, every error also
measured against its own samples)."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from terralod.cli._console import progress
from terralod.cli._options import parse_pair

#: A single GDAL raster of more samples than this builds out of core without being asked, whatever
#: ``--memory`` says (an in-memory build's own limit is :func:`terralod.memory.in_memory_samples`).
OUT_OF_CORE_SAMPLES = 1 << 28
_GDAL_SUFFIXES = (".tif", ".tiff", ".vrt", ".img", ".hgt")
#: Store bytes a sample of the build's grid, for the free-disk check before an out-of-core build: measured
#: 7.9 / 8.8 on 16 / 64 SRTM3 tiles warped to UTM (benchmarks/results/region_build.md), with headroom for
#: rougher terrain.
STORE_BYTES_PER_SAMPLE = 12.0


#: Bytes a grid sample of a warped (geographic) source can take in its spill file beside the output while
#: the build runs (:class:`terralod.io.windowed.WarpedSource`: heights as float64 and a bit of validity).
SPILL_BYTES_PER_SAMPLE = 8.125
#: Bytes a sample of a resampled source's own grid can take in the positions' spill file (the samples'
#: metre coordinates, two float64: :mod:`terralod.pyramid.original`).
POSITION_SPILL_BYTES_PER_SAMPLE = 16


def check_store_space(output: str, samples: int, resume: bool = False, scratch_bytes: int = 0) -> None:
    """Refuse (InputError, one line naming the output) an out-of-core build whose store would need more
    than its disk has free: about :data:`STORE_BYTES_PER_SAMPLE` a sample of the build's grid, less what a
    store being resumed already holds (a store being replaced stays until the new one is whole), plus
    ``scratch_bytes`` of spill files written beside it while it runs."""
    import shutil

    from terralod.errors import InputError

    p = Path(output).resolve()
    have = p.stat().st_size if resume and p.is_file() else 0
    need = int(STORE_BYTES_PER_SAMPLE * samples) - have + int(scratch_bytes)
    folder = p.parent
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    free = shutil.disk_usage(folder).free
    if need > free:
        spill = (
            f", of which {scratch_bytes / 1e9:.2f} GB of spill files while it runs" if scratch_bytes else ""
        )
        raise InputError(
            f"the store needs about {need / 1e9:.2f} GB ({samples:,} grid samples{spill}) and its disk has "
            f"{free / 1e9:.2f} GB free; free some space or write it to another disk",
            output,
        )


def is_large_raster(path: str, memory_bytes: int | None = None) -> bool:
    """True for a GDAL raster of more samples than an in-memory build holds within ``memory_bytes``
    (:func:`terralod.memory.in_memory_samples`; at most :data:`OUT_OF_CORE_SAMPLES`); its header only is
    read."""
    from terralod.memory import in_memory_samples

    limit = min(OUT_OF_CORE_SAMPLES, in_memory_samples(memory_bytes))
    if Path(path).suffix.lower() not in _GDAL_SUFFIXES or not Path(path).is_file():
        return False
    try:
        import rasterio

        with rasterio.open(path) as ds:
            return ds.width * ds.height > limit
    except Exception:
        return False  # the in-memory reader reports what is wrong with it


def is_region(path: str) -> bool:
    """True for an input that stands for several files: a folder, or a glob pattern no file is named."""
    from terralod.io.region import _is_glob

    p = Path(path)
    return p.is_dir() or (not p.exists() and _is_glob(path))


def open_window_source(input_paths: tuple[str, ...], read: dict[str, Any]):
    """The window source of the inputs with the read options (:func:`terralod.io.windowed.open_source`)."""
    from terralod.errors import InputError
    from terralod.io.windowed import open_source

    if read.get("encoding") or read.get("tile_zxy"):
        raise InputError(
            "--encoding and --tile need an in-memory build (one file, no --dask)", input_paths[0]
        )
    src = open_source(
        list(input_paths),
        spacing_m=parse_pair(read.get("spacing"), "--spacing"),
        vertical_scale=read.get("vertical_scale"),
        vertical_offset=read.get("vertical_offset"),
        crs=read.get("crs"),
    )
    if read.get("vertical_datum"):
        from terralod.io.reader import crs_with_vertical_datum

        src.crs, note = crs_with_vertical_datum(src.crs, read["vertical_datum"], src.source)
        src.notes = (*src.notes, note)
    return src


@contextlib.contextmanager
def windowed_runner(
    memory_bytes: int | None, workers: int | None, dask_address: str | None, dask_workers: int | None
) -> Iterator[tuple[int | None, Any]]:
    """(threads, Dask client or None) within the memory budget (:func:`terralod.memory.plan_memory`: the
    units in flight, or the local Dask workers, their threads and their memory limit); the client (and a
    local cluster) closed after."""
    from terralod.errors import InputError
    from terralod.memory import plan_memory
    from terralod.pyramid.distributed import dask_client

    try:
        plan = plan_memory(memory_bytes, threads=workers, dask_workers=dask_workers,
                           dask_local=dask_address == "local")  # fmt: skip
    except ValueError as exc:
        raise InputError(str(exc), "--memory") from None
    client = None
    if dask_address:
        client = dask_client(dask_address, n_workers=plan.dask_workers, threads=plan.threads,
                             memory_limit=plan.worker_bytes)  # fmt: skip
    else:
        workers = plan.threads
    try:
        yield workers, client
    finally:
        if client is not None:
            cluster = client.cluster if dask_address == "local" else None
            client.close()
            if cluster is not None:
                cluster.close()


def run_windowed_build(
    input_paths: tuple[str, ...], output: str, *, tile_size: int, method: str, workers: int | None, resume: bool,
    overwrite: bool, dask_address: str | None, dask_workers: int | None, read: dict[str, Any],
    memory_bytes: int | None = None, epoch: str | None = None,
):  # fmt: skip
    """Open the window source, connect to Dask (before anything is written), build, close the cluster. The
    memory budget (:func:`terralod.memory.plan_memory`) decides the units in flight: threads here, or the
    local Dask workers, their threads and their memory limit."""
    from terralod.io.windowed import WarpedSource
    from terralod.pyramid.distributed import build_store_windowed

    src = open_window_source(input_paths, read)
    samples = src.width * src.height
    spill = int(SPILL_BYTES_PER_SAMPLE * samples) if isinstance(src, WarpedSource) else 0
    own = getattr(src.original_grid, "shape", None)  # a resampled source: its own samples' positions
    spill += int(POSITION_SPILL_BYTES_PER_SAMPLE * own[0] * own[1]) if own is not None else 0
    # before a worker starts or a file is written; a store of epochs also keeps its samples (about 3 B each)
    check_store_space(output, samples, resume, spill + (3 * samples if epoch is not None else 0))
    with windowed_runner(memory_bytes, workers, dask_address, dask_workers) as (workers, client):
        with progress("building") as prog:
            task = prog.add_task(Path(output).name, total=None)

            def cb(done: int, total: int) -> None:
                prog.update(task, completed=done, total=total)

            return build_store_windowed(src, output, tile_size=tile_size, method=method, workers=workers,
                                        client=client, resume=resume, overwrite=overwrite, progress=cb,
                                        epoch=epoch)  # fmt: skip


def run_windowed_update(
    input_paths: tuple[str, ...], store: str, epoch: str, *, base: str | None, resume: bool, workers: int | None,
    dask_address: str | None, dask_workers: int | None, read: dict[str, Any], memory_bytes: int | None = None,
):  # fmt: skip
    """``terralod update`` of a survey read window by window: open it, connect to Dask, add the epoch."""
    from terralod.pyramid.update import update_store_windowed

    src = open_window_source(input_paths, read)
    check_store_space(store, 0, False, int(3 * src.width * src.height))  # the epoch's samples, at most
    with windowed_runner(memory_bytes, workers, dask_address, dask_workers) as (workers, client):
        with progress("updating") as prog:
            task = prog.add_task(Path(store).name, total=None)

            def cb(done: int, total: int) -> None:
                prog.update(task, completed=done, total=total)

            return update_store_windowed(src, store, epoch, base=base, resume=resume, workers=workers,
                                         client=client, progress=cb)  # fmt: skip
