"""``terralod build INPUT -o STORE``: the level-of-detail tile store of a DEM (Sung, Lee & Shin, 2021; Hu & Wang), or the
detail-increment TIN of a LAS/LAZ cloud (Ai et al., 2019)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import click

from terralod.cli._console import console, print_store_summary, print_tin_summary
from terralod.cli._errors import require_extra
from terralod.cli._inputs import run_build
from terralod.cli._options import check_output, check_raster_size, load, memory_option, numbers, read_options
from terralod.output import scratch_beside


@click.command()
@click.argument("input_paths", metavar="INPUT...", nargs=-1, required=True)
@click.option("-o", "--output", required=True, help="Output .terra store.")
@click.option(
    "--tile-size", type=int, default=None,
    help="Vertices per tile side (2^n + 1); default 33 for adaptive tiles (one error level deeper than 65: "
    "0.5-0.6x the triangles drawn at 2 px, 1.8x the build time), 65 for cohesion and chunked.",
)  # fmt: skip
@click.option(
    "--method", default="adaptive", show_default=True,
    help="Tile mesher: adaptive (a greedy-insertion TIN per tile on a halving error ladder, the finest "
    "level lossless against the grid it meshes; adaptive_ladder: the ladder down to the finest level too), cohesion (Sung, Lee & "
    "Shin's vertex cohesion map, 2021: one shared grid per level whose vertices are pulled towards the "
    "relief, so every tile shares one index buffer) or chunked (Ulrich's Chunked LOD, 2002: plainly "
    "decimated grids, the classic baseline); tin builds a detail-increment TIN from LiDAR (Ai et al., "
    "2019: QEM edge collapses stored as reversible increments), the default for LAS/LAZ input.",
)  # fmt: skip
@click.option(
    "--sub-blocks", default="4", show_default=True, help="TIN: sub-blocks, a square number or auto."
)
@click.option(
    "--base-fraction",
    type=float,
    default=0.2,
    show_default=True,
    help="TIN: triangles kept in the base mesh.",
)
@click.option("--workers", type=int, default=None, help="Threads (default: all cores).")
@click.option("--resume", is_flag=True, help="Finish an interrupted build of the same input.")
@click.option("--overwrite", is_flag=True, help="Replace an existing output store.")
@click.option(
    "--fractal", "fractal_levels", type=click.IntRange(0, 6), default=0, show_default=True,
    help="Fractal levels below the DEM that view/render/flythrough add by default (Hu & Wang; generated "
    "on demand from the source DEM, never stored).",
)  # fmt: skip
@click.option(
    "--epoch", default=None,
    help="Name of the terrain's first epoch (e.g. the survey date 2000-09-25): the store keeps its samples, "
    "so `terralod update` / `terralod edit` can add later epochs.",
)  # fmt: skip
@click.option(
    "--dask",
    "dask_address",
    default=None,
    help="Build on Dask: local (a LocalCluster of worker processes) or tcp://HOST:PORT (a scheduler).",
)
@click.option(
    "--dask-workers", type=click.IntRange(1), default=None, help="Worker processes of --dask local (2)."
)
@click.option(
    "--bbox",
    default=None,
    metavar="W,S,E,N",
    help="LAS/LAZ surveys: build the part inside this box (degrees west,south,east,north); COPC files are "
    "read through their octree (only the nodes meeting the box), tiles outside it are skipped.",
)
@memory_option
@read_options
def build(
    input_paths: tuple[str, ...], output: str, tile_size: int | None, method: str, sub_blocks: str, base_fraction: float,
    workers, resume, overwrite, fractal_levels, epoch, dask_address, dask_workers, bbox, memory_bytes, **read: Any,
) -> None:  # fmt: skip
    """Build the level-of-detail tile store of a DEM (or of a mosaic of DEM tiles on one grid), or the
    detail-increment TIN of a LAS/LAZ cloud. Mosaics (files, a folder, a quoted glob), --dask and rasters
    over 2^28 samples build out of core; geographic and Web Mercator ones are warped to the UTM zone of
    their centre (a Transverse Mercator on their central meridian when wider than one zone takes)."""
    input_path = input_paths[0]
    from terralod.pyramid.builder import METHODS, default_tile_size, store_summary
    from terralod.store import TileStore, open_store
    from terralod.tiles import is_valid_tile_size

    if resume and overwrite:
        raise click.BadParameter("give --resume or --overwrite, not both", param_hint="--resume")
    check_output(output, list(input_paths), overwrite=overwrite, resume=resume, what="output store")
    for path in input_paths:  # the size limit before anything is written
        check_raster_size(path)
    if dask_address:
        require_extra("build --dask", "dask")
    survey = _las_survey(input_paths)
    if method == "tin" or survey:
        if len(input_paths) > 1 and not survey:
            raise click.BadParameter("a TIN from a DEM takes one DEM (a survey: several LAS/LAZ files)",
                                     param_hint="INPUT")  # fmt: skip
        if workers is not None and workers < 1:
            raise click.BadParameter(f"expected >= 1, got {workers}", param_hint="--workers")
        if bbox is not None and not survey:
            raise click.BadParameter("a build's --bbox is for LAS/LAZ surveys (export --bbox takes a part of a "
                                     "DEM's tiles)", param_hint="--bbox")  # fmt: skip
        build_tin(survey or input_path, output, sub_blocks, base_fraction, overwrite, read, workers=workers,
                  dask_address=dask_address, dask_workers=dask_workers, bbox_deg=_bbox_deg(bbox))  # fmt: skip
        return
    if bbox is not None:
        raise click.BadParameter("a build's --bbox is for LAS/LAZ surveys (export --bbox takes a part of a "
                                 "DEM's tiles)", param_hint="--bbox")  # fmt: skip
    if tile_size is None:
        tile_size = default_tile_size(method) if method in METHODS else 65
    if not is_valid_tile_size(tile_size) or tile_size > 257:
        raise click.BadParameter(
            f"expected 2^n + 1 between 3 and 257, got {tile_size}", param_hint="--tile-size"
        )
    if method not in METHODS:
        raise click.BadParameter(
            f"expected one of {', '.join(sorted(METHODS))}, got {method!r}", param_hint="--method"
        )
    if workers is not None and workers < 1:
        raise click.BadParameter(f"expected >= 1, got {workers}", param_hint="--workers")
    if epoch is not None:
        from terralod.pyramid.update import validate_epoch_name

        epoch = validate_epoch_name(epoch, output)
    if windowed_build(input_paths, dask_address, epoch, memory_bytes):
        from terralod.cli._windowed import run_windowed_build

        with scratch_beside(output):  # spill files (positions of a geographic source) on the store's disk
            rep = run_windowed_build(input_paths, output, tile_size=tile_size, method=method, workers=workers,
                                     resume=resume, overwrite=overwrite, dask_address=dask_address,
                                     dask_workers=dask_workers, read=read, memory_bytes=memory_bytes,
                                     epoch=epoch)  # fmt: skip
    else:
        hf = load(input_path, **read)
        with scratch_beside(output):
            rep = run_build(
                hf, output, tile_size=tile_size, method=method, workers=workers, resume=resume,
                overwrite=overwrite, **({"epoch": epoch} if epoch is not None else {}),
            )  # fmt: skip
    console.print(
        f"built {rep.tiles_built} tiles ({rep.tiles_skipped} already done) in {rep.seconds:.2f} s, "
        f"{rep.samples_per_second / 1e6:.2f} M source samples/s"
    )
    if fractal_levels:
        with TileStore.open(output, writable=True) as s:
            s.set_meta("fractal_levels", int(fractal_levels))
        console.print(f"fractal: {fractal_levels} levels below the DEM when viewed (from {input_path})")
    with open_store(output) as s:
        print_store_summary(store_summary(s))


def windowed_build(
    input_paths: tuple[str, ...], dask_address: str | None, epoch: str | None, memory_bytes: int | None = None
) -> bool:
    """True when the build reads windows (:mod:`terralod.pyramid.distributed`): a mosaic (several files, a
    folder or a quoted glob), --dask, or one GDAL raster of more samples than an in-memory build holds
    within ``--memory`` (:func:`terralod.memory.in_memory_samples`: 62 M at 2 GiB); with --epoch the store
    keeps the samples either way (read again in strips). Geographic and Mercator mosaics are warped block by
    block to a metric grid (:class:`terralod.io.windowed.WarpedSource`)."""
    from terralod.cli._windowed import is_large_raster, is_region

    if len(input_paths) > 1 or dask_address or is_region(input_paths[0]):
        return True
    return is_large_raster(input_paths[0], memory_bytes)


def _las_survey(input_paths: tuple[str, ...]) -> list[Path]:
    """The LAS/LAZ files of the inputs when they are a point-cloud survey (files, folders or quoted globs of
    LAS/LAZ tiles), else an empty list."""
    from terralod.tin.pointcloud import LAS_SUFFIXES, las_inputs

    def is_las(text: str) -> bool:
        p = Path(text)
        if p.is_dir():
            return any(q.suffix.lower() in LAS_SUFFIXES for q in p.iterdir())
        return p.suffix.lower() in LAS_SUFFIXES

    if not all(is_las(t) for t in input_paths):
        return []
    return las_inputs(input_paths)


def _bbox_deg(text: str | None) -> tuple[float, float, float, float] | None:
    """``--bbox W,S,E,N`` as degrees, checked by the export's rule (west < east, south < north, on the globe)."""
    from terralod.export.quantized_mesh import Part

    box = numbers(text, 4, "--bbox", "W,S,E,N in degrees (west,south,east,north)")
    if box is None:
        return None
    try:
        Part(bbox=box)  # type: ignore[arg-type]
    except ValueError as exc:
        raise click.BadParameter(str(exc), param_hint="--bbox") from None
    return (box[0], box[1], box[2], box[3])


def build_tin(input_path: str | list[Path], output: str, sub_blocks: str, base_fraction: float, overwrite: bool,
              read: dict[str, Any], *, workers: int | None = None, dask_address: str | None = None,
              dask_workers: int | None = None,
              bbox_deg: tuple[float, float, float, float] | None = None) -> None:  # fmt: skip
    """``build --method tin``: LAS/LAZ points (or a DEM's samples) → detail-increment TIN store; sub-blocks
    simplified on ``workers`` threads, or on Dask workers with ``dask_address`` (the same store)."""
    from terralod.errors import StoreError
    from terralod.tin import DetailIncrementModel
    from terralod.tin.terra import save_model_to_store

    blocks: int | str = sub_blocks
    if sub_blocks != "auto":
        try:
            blocks = int(sub_blocks)
        except ValueError:
            raise click.BadParameter(f"expected a square number or auto, got {sub_blocks!r}",
                                     param_hint="--sub-blocks") from None  # fmt: skip
    if not 0.0 < base_fraction <= 1.0:
        raise click.BadParameter(
            f"expected a fraction in (0, 1], got {base_fraction}", param_hint="--base-fraction"
        )
    if Path(output).exists() and not overwrite:
        raise StoreError("already exists (pass --overwrite to replace it)", output)
    client = executor = None
    if dask_address:
        from terralod.tin.distributed import close_client, dask_executor, open_client

        client = open_client(dask_address, dask_workers)  # InputError (one line) when unreachable
        executor = dask_executor(client)
    t0 = time.perf_counter()
    stages: dict[str, float] = {}
    try:
        if isinstance(input_path, list):
            model = DetailIncrementModel.from_las(input_path, sub_blocks=blocks, base_fraction=base_fraction,
                                                  workers=workers, executor=executor, timings=stages,
                                                  crs=read.get("crs"), bbox_deg=bbox_deg)  # fmt: skip
        else:
            model = DetailIncrementModel.from_heightfield(load(input_path, **read), sub_blocks=blocks,
                                                          base_fraction=base_fraction, workers=workers,
                                                          executor=executor)  # fmt: skip
    finally:
        if client is not None:
            close_client(client)
    t_save = time.perf_counter()
    summary = save_model_to_store(model, output, overwrite=overwrite, workers=workers)
    total_s = time.perf_counter() - t0
    n_points = int(model.vertices_m.shape[0])
    console.print(f"built a detail-increment TIN (Ai et al., 2019) in {total_s:.2f} s, "
                  f"{n_points / max(total_s, 1e-9) / 1e3:,.1f} k points/s")  # fmt: skip
    if stages:
        stages["save"] = time.perf_counter() - t_save
        console.print("  stages       " + ", ".join(f"{k} {v:.2f} s" for k, v in stages.items()))
    print_tin_summary(summary)
