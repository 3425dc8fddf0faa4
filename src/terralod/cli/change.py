"""``terralod change BEFORE AFTER -o OUT``: the co-registered difference of two DEMs, its volumes with
their uncertainty, and a report for non-experts.

Input forms:

- ``BEFORE AFTER`` — two DEMs in any format and CRS the readers take; each side may also be a region of
  DEM tiles on one grid (a folder, a quoted glob or a .vrt), read window by window
  (:mod:`terralod.change.windowed`), as is a pair of more than :data:`WINDOWED_MIN_CELLS` cells;
- ``BEFORE AFTER`` — two LiDAR surveys, each a LAS/LAZ file, a folder or a quoted glob of tiles: each
  survey's ground points (class 2 when classified) joined into a Delaunay TIN whose linear surface is read
  on one grid (:mod:`terralod.change.lidar`: the spacing their density supports, or ``--spacing``); the
  rule is stated in ``gridding`` of the summary and in the report's notes;
- ``BEFORE AFTER1 AFTER2 ...`` — a series: the summary is BEFORE → the last, plus the volume of each
  epoch against BEFORE (``series`` in the summary, the volume-against-time figure in the report);
- ``SERIES.npz`` with arrays ``base``, ``delta`` (epoch i = base + delta[i]), ``dates`` and the
  georeferencing (``../shared/data/change/``'s layout) — a series of all its epochs;
- ``SITE.terra --from DATE --to DATE`` — two epochs of one store (``terralod.change.epochs``).

Contract (scripts rely on it): ``OUT/summary.json`` with ``gain_m3``, ``loss_m3``, ``net_m3`` (every valid
cell, no threshold; gain and loss positive), the same with ``_above_lod``, ``net_uncertainty_m3`` (95 %),
``area_gain_m2``, ``area_loss_m2`` (beyond the level of detection), ``sigma_m``, ``level_of_detection_m``,
``max_rise_m``, ``max_drop_m`` (positive), ``shift_m`` ([dx, dy, dz] metres applied to AFTER to align it
with BEFORE) and ``zones`` (one object per polygon of ``--zones``, empty without); also
``coregistration`` (``mode``: "shift and bias", "bias only", "identical" or "none", and ``statement``, one
plain sentence), ``stable_ground`` (cells, what was left out and ``description``, e.g. "fitted on 41 % of
the area: ground outside the change with slopes above 3°; left out: 1 flat water surface …"),
``fit_description`` and ``uncertainty`` (variogram, bias σ, resampling error, ``statements``). Inputs are
named by their file names only; ``OUT/dod.tif``; ``OUT/sigma.tif`` (σ of each cell of the difference on
dod.tif's grid: :mod:`terralod.change.uncertainty`'s error model, larger on steep and rugged ground, or
the one σ of ``--sigma-m``; the ``uncertainty`` object holds its ``model`` or the ``model_note`` of why
it was not fitted);
``OUT/report.html`` (plus the report's PNGs in ``OUT/figures/``). Exit 0, or 2 on bad input with one line
naming the file. OUT is written in its work folder ``.OUT.work`` beside it and renamed into place at the end
(:class:`terralod.output.Output`); a run still writing OUT is never disturbed.
"""

from __future__ import annotations

import json
import os
import re
from pathlib import Path
from typing import Any

import click

from terralod.cli._console import console
from terralod.cli._errors import require_extra
from terralod.cli._options import check_raster_size, is_store, load, read_options

_DATE = re.compile(r"(\d{4}-\d{2}-\d{2})")


def _date_of(path: str) -> str | None:
    m = _DATE.search(Path(path).name)
    return m.group(1) if m else None


def _read_npz_series(path: str):
    """Epochs of a base + delta series file as Heightfields, with their dates."""
    import numpy as np
    from affine import Affine

    from terralod.errors import InputError
    from terralod.io.raster import georeferenced_heightfield

    with np.load(path, allow_pickle=False) as z:
        if "base" not in z or "delta" not in z:
            return None
        base = np.asarray(z["base"], np.float32)
        delta = np.asarray(z["delta"], np.float32)
        dates = [str(d) for d in z["dates"]] if "dates" in z else [f"epoch {i}" for i in range(len(delta))]
        gt = [float(v) for v in z["transform"]] if "transform" in z else None
        crs = str(z["crs"]) if "crs" in z else None
    if gt is None or crs is None:
        raise InputError("a series .npz needs 'transform' (GDAL geotransform) and 'crs'", path)
    t = Affine.from_gdal(*gt)
    out = []
    for i in range(delta.shape[0]):
        e = base + delta[i]
        ok = np.isfinite(e)
        out.append(georeferenced_heightfield(np.where(ok, e, np.nan), ok, t, crs, f"{path}[{dates[i]}]"))
    return out, dates


def _epoch(store: str, date: str):
    from terralod.errors import InputError

    try:
        from terralod.change.epochs import epoch_heightfield
    except ImportError:
        raise InputError(
            "this terralod has no epoch stores (terralod.change.epochs); give two DEMs", store
        ) from None
    return epoch_heightfield(store, date)


@click.command()
@click.argument("inputs", nargs=-1, required=True)
@click.option("-o", "--output", required=True, help="Folder to write (summary.json, dod.tif, report.html).")
@click.option("--zones", help="GeoJSON polygons: a budget per polygon (its 'name' property).")
@click.option(
    "--stable",
    help="Ground you know did not change: a raster mask (non-zero = unchanged) or "
    "GeoJSON polygons. Only this ground is used to line the surveys up.",
)
@click.option(
    "--exclude",
    help="Ground that must not be used to line the surveys up (glaciers, lakes, "
    "the known change): GeoJSON polygons or a raster mask (non-zero = leave out).",
)
@click.option(
    "--min-slope-deg",
    type=click.FloatRange(0, 60),
    default=3.0,
    show_default=True,
    help="Only ground at least this steep is used to find a sideways shift.",
)
@click.option(
    "--no-coregister", is_flag=True, help="Compare the surveys as they are, without lining them up."
)
@click.option("--coreg", "coreg_method", type=click.Choice(["xdem", "terralod"]), default="xdem",
              show_default=True, help="How to line the surveys up (Nuth & Kääb 2011): xdem's or terralod's own.")  # fmt: skip
@click.option(
    "--sigma-m",
    type=float,
    help="Survey error of one cell of the difference, metres, the same everywhere: overrides the error "
    "measured on unchanged ground as a function of slope and curvature (default: measured).",
)
@click.option(
    "--corr-range-m",
    type=float,
    help="Distance over which survey errors stay alike, metres: overrides the ranges fitted on unchanged "
    "ground (default: measured, a sum of several ranges). Given with --sigma-m: one σ and one range.",
)
@click.option(
    "--confidence",
    type=click.FloatRange(0.5, 0.9999),
    default=0.95,
    show_default=True,
    help="How sure each ± range is.",
)
@click.option("--from", "date_from", help="Epoch date of BEFORE (a .terra store).")
@click.option("--to", "date_to", help="Epoch date of AFTER (a .terra store).")
@click.option("--dates", help="Comma-separated ISO dates of the inputs (default: from the file names).")
@click.option("--no-views", is_flag=True, help="Leave the 3D before/after views out of the report.")
@click.option("--overwrite", is_flag=True, help="Replace an existing output folder.")
@click.option("--site", "with_site", is_flag=True,
              help="Also write OUT/site/: a web page of the change in 3D that any static web host serves, offline.")  # fmt: skip
@click.option("--dask", "dask_address", metavar="local|tcp://HOST:PORT",
              help="Difference the windows of a pair read window by window on Dask workers (a local cluster, or "
              "a scheduler): the same numbers and dod.tif as without.")  # fmt: skip
@click.option(
    "--dask-workers", type=click.IntRange(1), default=None, help="Worker processes of --dask local (2)."
)
@read_options
def change(
    inputs, output, zones, stable, exclude, min_slope_deg, no_coregister, coreg_method, sigma_m, corr_range_m,
    confidence, date_from, date_to, dates, no_views, overwrite, with_site, dask_address, dask_workers,
    **read: Any,
) -> None:  # fmt: skip
    """How much ground was added or removed between two surveys (BEFORE AFTER), with a ± range and a report.

    The later survey is first lined up with the earlier one on ground that did not change; the volumes,
    the survey error and the level below which changes cannot be told from error are measured from the
    pair itself, the survey error as a function of slope and curvature. The output folder holds summary.json,
    dod.tif (the difference map), sigma.tif (the survey error of each cell) and report.html.

    BEFORE and AFTER may each be one DEM file, or a region of tiles on one grid: a folder, a quoted glob
    ("tiles/*.tif") or a .vrt; a region (or a pair too large to hold) is read window by window, lined up
    on an even sample of it, and dod.tif is written as a Cloud Optimized GeoTIFF.

    BEFORE and AFTER may also be two LiDAR surveys (LAS/LAZ files, folders or quoted globs): the ground
    points of each are joined into a surface of triangles read on one grid, every --spacing metres or at
    the spacing the point density supports; the summary and report say the rule.

    \b
    Example:
      terralod change dem_2015.tif dem_2021.tif -o site_change --exclude glacier.geojson
      terralod change tiles_2015/ "tiles_2021/*.tif" -o region_change
      terralod change lidar_2015/ lidar_2021/ -o lidar_change --site
    """
    require_extra("change", "change")
    if with_site:
        require_extra("change --site", "web")
    from terralod.change.coregister import read_stable_mask
    from terralod.change.difference import SIGMA_DESCRIPTION, check_vertical_units, write_dod
    from terralod.change.report import write_report
    from terralod.change.volumes import measure_change, series_volumes
    from terralod.errors import InputError
    from terralod.output import Output

    out = Path(output)
    output_of = Output(
        out, inputs=[*inputs, *(p for p in (zones, stable, exclude) if p)], overwrite=overwrite
    )
    output_of.check()  # refusals first, before the long measurement
    for path in inputs:  # the one size limit, from the headers, before anything is read (windowed or not)
        check_raster_size(path)
    first = inputs[0]
    lidar = _lidar_pair(inputs)
    if dask_address and lidar is not None:
        raise click.BadParameter("is for DEM files or regions, not LiDAR surveys", param_hint="--dask")
    epoch_sides = _epoch_sides(inputs, date_from, date_to, read, forced=bool(dask_address))
    if dask_address:
        require_extra("change --dask", "dask")
        if epoch_sides is None and not (len(inputs) == 2 and _windowed(inputs, read, forced=True)):
            raise click.BadParameter("is for a BEFORE AFTER pair of DEM files or regions, or two epochs of a store "
                                     "that keeps their samples (no --encoding, --tile or --spacing)",
                                     param_hint="--dask")  # fmt: skip
    if epoch_sides is not None or (
        lidar is None and len(inputs) == 2 and _windowed(inputs, read, forced=bool(dask_address))
    ):
        _change_windowed(
            inputs, output_of, out, zones=zones, stable=stable, exclude=exclude, no_coregister=no_coregister,
            coreg_method=coreg_method, sigma_m=sigma_m, corr_range_m=corr_range_m, confidence=confidence,
            dates=dates, no_views=no_views, min_slope_deg=min_slope_deg, read=read,
            dask=(dask_address, dask_workers), epoch_sides=epoch_sides, with_site=with_site,
        )  # fmt: skip
        return
    notes: list[str] = []
    series_hf = None
    gridding = None
    if lidar is not None:
        gridding = _grid_lidar(inputs, read)
        hfs = [gridding.before, gridding.after]
        ds = [_date_of(p) for p in inputs]
        notes.append(f"gridding: {gridding.statement}")
    elif len(inputs) == 1 and Path(first).is_file() and is_store(Path(first)):
        if not (date_from and date_to):
            raise InputError("a .terra store needs --from DATE and --to DATE", first)
        hfs, ds = [_epoch(first, date_from), _epoch(first, date_to)], [date_from, date_to]
    elif len(inputs) == 1 and first.lower().endswith(".npz") and (got := _read_npz_series(first)):
        series_hf, ds = got
        hfs = [series_hf[0], series_hf[-1]]
        ds = list(ds)
        if len(series_hf) < 2:
            raise InputError("a series needs at least two epochs", first)
    elif len(inputs) == 1:
        raise InputError("needs a second DEM to compare with (BEFORE AFTER)", first)
    else:
        hfs = [load(p, **read) for p in inputs]
        ds = [_date_of(p) for p in inputs]
        for p in inputs[1:]:
            notes += check_vertical_units(inputs[0], p)
        if len(inputs) > 2:
            series_hf = hfs
    if dates:
        given = [d.strip() for d in dates.split(",")]
        n = len(series_hf) if series_hf else 2
        if len(given) != n:
            raise click.BadParameter(f"expected {n} dates, got {len(given)}", param_hint="--dates")
        ds = given
    pair_dates = (ds[0], ds[-1])
    before, after = hfs[0], hfs[-1]
    mask = read_stable_mask(stable, before) if stable else None
    excl = read_stable_mask(exclude, before, what="cell to leave out") if exclude else None
    result = measure_change(
        before, after, stable=mask, exclude=excl, coregistration=not no_coregister, method=coreg_method,
        sigma_m=sigma_m, corr_range_m=corr_range_m, confidence=confidence, zones=zones, dates=pair_dates,
        slope_min_deg=min_slope_deg,
    )  # fmt: skip
    result.summary["alignment_notes"] = notes + result.summary["alignment_notes"]
    if gridding is not None:
        result.summary["gridding"] = gridding.as_dict()
    # the machine's folders are nobody's business: inputs are named by their file names only
    result.summary = _without_folders(result.summary, [*inputs, *(p for p in (zones, stable, exclude) if p)])
    series = None
    if series_hf is not None:
        series = series_volumes(series_hf, list(ds), sigma_m=sigma_m, corr_range_m=corr_range_m,
                                confidence=confidence, coregistration=not no_coregister, method=coreg_method)  # fmt: skip
        result.summary["series"] = series

    with output_of as o:
        tmp = o.folder
        s = result.summary
        tags = {
            "sigma_m": s["sigma_m"], "level_of_detection_m": s["level_of_detection_m"],
            "shift_m": s["shift_m"], "before": s["before"]["source"], "after": s["after"]["source"],
        }  # fmt: skip
        write_dod(tmp / "dod.tif", result.dod, before, tags)
        write_dod(tmp / "sigma.tif", result.sigma, before, tags, description=SIGMA_DESCRIPTION)
        write_report(
            result, tmp / "report.html", series=series, views=not no_views, figures_dir=tmp / "figures"
        )
        (tmp / "summary.json").write_text(json.dumps(_jsonable(s), indent=2) + "\n")
        if with_site:
            _write_site(tmp / "site", result, series_hf or [before, after], list(ds) if series_hf else list(pair_dates),
                        dict(sigma_m=sigma_m, corr_range_m=corr_range_m, confidence=confidence,
                             coregistration=not no_coregister, method=coreg_method), gridding)  # fmt: skip
    _print_result(result, pair_dates, out)


def _print_result(result, pair_dates, out: Path) -> None:  # noqa: ANN001
    from terralod.change.report import plain_summary

    for w in [*result.uncertainty.warnings, *result.summary.get("report_notes", [])]:
        click.echo(f"terralod: warning: {w}", err=True)
    for line in plain_summary(result, pair_dates):
        console.print(line)
    s = result.summary
    console.print(
        f"{out}: net {s['net_m3']:,.0f} ± {s['net_uncertainty_m3']:,.0f} m³, gain {s['gain_m3']:,.0f} m³, loss "
        f"{s['loss_m3']:,.0f} m³; beyond the LoD ({s['level_of_detection_m']:.2f} m) gain "
        f"{s['gain_m3_above_lod']:,.0f} m³ over {s['area_gain_m2']:,.0f} m², loss {s['loss_m3_above_lod']:,.0f} m³ "
        f"over {s['area_loss_m2']:,.0f} m²; σ {s['sigma_m']:.3f} m ({s['sigma_source']}); shift "
        + ", ".join(f"{v:.3f}" for v in s["shift_m"]) + " m"
    )  # fmt: skip
    for n in s["alignment_notes"]:
        console.print(f"  {n}")


def _lidar_pair(inputs) -> bool | None:  # noqa: ANN001
    """True when BEFORE AFTER are two LiDAR surveys (LAS/LAZ files, folders or globs), None when neither is;
    one of each is refused in one line naming the LiDAR side."""
    from terralod.change.lidar import is_lidar_input
    from terralod.errors import InputError

    if len(inputs) < 2:
        return None
    is_las = [is_lidar_input(p) for p in inputs]
    if not any(is_las):
        return None
    if len(inputs) != 2 or not all(is_las):
        bad = inputs[is_las.index(True)]
        raise InputError("is a LiDAR survey: compare it with another LiDAR survey (BEFORE AFTER, two of them), "
                         "not with a DEM or a series", bad)  # fmt: skip
    return True


def _grid_lidar(inputs, read: dict):  # noqa: ANN001
    """The two surveys gridded on one grid (:func:`terralod.change.lidar.grid_survey_pair`); --spacing is the
    grid's spacing in metres (one number, or DX,DY with DX = DY)."""
    from terralod.change.lidar import grid_survey_pair

    spacing_m = None
    if read.get("spacing"):
        try:
            parts = [float(v) for v in str(read["spacing"]).split(",")]
        except ValueError:
            raise click.BadParameter(
                f"expected metres, got {read['spacing']!r}", param_hint="--spacing"
            ) from None
        if not parts or any(not (v > 0) for v in parts) or len(set(parts)) != 1:
            raise click.BadParameter(
                "a LiDAR pair takes one positive spacing in metres", param_hint="--spacing"
            )
        spacing_m = parts[0]
    dem_only = {"encoding": "--encoding", "tile_zxy": "--tile", "vertical_scale": "--vertical-scale",
                "vertical_offset": "--vertical-offset"}  # fmt: skip
    for k, flag in dem_only.items():
        if read.get(k):
            raise click.BadParameter("is for DEM files, not LiDAR surveys", param_hint=flag)
    return grid_survey_pair(inputs[0], inputs[1], spacing_m=spacing_m, crs=read.get("crs"))


#: A pair of more cells than this is read window by window even when each side is one file.
WINDOWED_MIN_CELLS = 1 << 24


def _is_region_input(path: str) -> bool:
    """A folder, a quoted glob or a VRT: an input that stands for a region of files."""
    from terralod.cli._windowed import is_region

    return is_region(path) or path.lower().endswith(".vrt")


def _cells(path: str) -> int:
    try:
        import rasterio

        with rasterio.open(path) as ds:
            return int(ds.width) * int(ds.height)
    except Exception:  # noqa: BLE001 - not a raster GDAL reads: the in-memory reader says what is wrong
        return 0


def _windowed(inputs, read: dict, forced: bool = False) -> bool:  # noqa: ANN001
    """Whether a BEFORE AFTER pair is read window by window (:mod:`terralod.change.windowed`): either side a
    region (folder, glob, VRT), or a pair of more than :data:`WINDOWED_MIN_CELLS` cells; never with
    options only the in-memory readers know (--encoding, --tile, --spacing)."""
    if _in_memory_options(read):
        return False
    if forced or any(_is_region_input(p) for p in inputs):
        return True
    return all(Path(p).is_file() for p in inputs) and max(_cells(p) for p in inputs) > WINDOWED_MIN_CELLS


def _in_memory_options(read: dict) -> bool:
    """Whether options only the in-memory chain knows are given (--encoding, --tile, --spacing)."""
    return bool(read.get("encoding") or read.get("tile_zxy") or read.get("spacing"))


def _epoch_sides(inputs, date_from, date_to, read: dict, forced: bool = False):  # noqa: ANN001, ANN202
    """(BEFORE, AFTER) as :class:`terralod.change.epochs.EpochSource` when the input is one store, ``--from``
    and ``--to`` are given and the pair is read window by window (the rule of :func:`_windowed`: more than
    :data:`WINDOWED_MIN_CELLS` cells, or ``forced``); None otherwise, and for a store that keeps no samples of
    an epoch (its first epoch re-read from the source file, in memory)."""
    first = inputs[0]
    if (
        len(inputs) != 1
        or not (date_from and date_to)
        or not Path(first).is_file()
        or not is_store(Path(first))
    ):
        return None
    if _in_memory_options(read):
        return None
    from terralod.change.epochs import EpochSource, NoSamplesKept

    try:
        sides = EpochSource(first, date_from), EpochSource(first, date_to)
    except NoSamplesKept:
        return None
    if not forced and sides[0].width * sides[0].height <= WINDOWED_MIN_CELLS:
        return None
    return sides


def _open_side(path: str, read: dict):  # noqa: ANN001
    """The window source of one side: a file, a folder, a quoted glob or a VRT; every file of a region read
    once first (an unreadable tile named in one line, before anything is written)."""
    from terralod.io.region import expand_inputs, resolve_region, scan_region
    from terralod.io.windowed import RasterSource, needs_warp, open_source

    files = [shown for _name, shown in expand_inputs([path])]
    options = {"vertical_scale": read.get("vertical_scale"), "vertical_offset": read.get("vertical_offset"),
               "crs": read.get("crs")}  # fmt: skip
    if not needs_warp(files, read.get("crs")):
        scan_region(resolve_region(files, crs=read.get("crs")))  # WarpedSource scans its own
        return RasterSource(files if len(files) > 1 else files[0], **options)
    return open_source(files if len(files) > 1 else files[0], **options)


def _change_windowed(inputs, output_of, out: Path, *, zones, stable, exclude, no_coregister, coreg_method,
                     sigma_m, corr_range_m, confidence, dates, no_views, min_slope_deg, read,
                     dask=(None, None), epoch_sides=None, with_site=False) -> None:  # fmt: skip  # noqa: ANN001
    """BEFORE AFTER read window by window (:func:`terralod.change.windowed.measure_change_windowed`), the
    windows differenced on Dask workers with ``dask`` = (address, local workers); ``epoch_sides``: two
    epochs of the one store ``inputs`` names (:func:`_epoch_sides`) instead of two DEMs; ``with_site``:
    OUT/site/ too (:func:`terralod.site.build.site_from_windowed`: each side's 3D Tiles from a store built
    out of core here, or the store's own epochs)."""
    from terralod.change.difference import check_vertical_units
    from terralod.change.report import write_report
    from terralod.change.windowed import measure_change_windowed
    from terralod.io.region import expand_inputs

    if epoch_sides is not None:
        before, after = epoch_sides
        notes = []
        ds = [before.epoch, after.epoch]
        names = (before.source or f"{inputs[0]} {ds[0]}", after.source or f"{inputs[0]} {ds[1]}")
    else:
        before, after = (_open_side(p, read) for p in inputs)
        firsts = [expand_inputs([p])[0][1] for p in inputs]
        notes = check_vertical_units(firsts[0], firsts[1])
        ds = [_date_of(p) for p in firsts]
        names = (Path(inputs[0]).name, Path(inputs[1]).name)
    notes += [f"BEFORE note: {n}" for n in before.notes] + [f"AFTER note: {n}" for n in after.notes]
    if dates:
        given = [d.strip() for d in dates.split(",")]
        if len(given) != 2:
            raise click.BadParameter(f"expected 2 dates, got {len(given)}", param_hint="--dates")
        ds = given
    pair_dates = (ds[0], ds[1])
    client = None
    if dask[0]:
        from terralod.pyramid.distributed import dask_client

        client = dask_client(dask[0], n_workers=dask[1])  # before anything is written
    try:
        with output_of as o:
            tmp = o.folder
            result = measure_change_windowed(
                before, after, names=names, dod_path=tmp / "dod.tif", stable=stable, exclude=exclude,
                coregistration=not no_coregister, method=coreg_method, sigma_m=sigma_m, corr_range_m=corr_range_m,
                confidence=confidence, zones=zones, dates=pair_dates, slope_min_deg=min_slope_deg, notes=notes,
                client=client,
            )  # fmt: skip
            result.summary = _without_folders(
                result.summary, [*inputs, *(p for p in (zones, stable, exclude) if p)]
            )
            write_report(result, tmp / "report.html", views=not no_views, figures_dir=tmp / "figures")
            (tmp / "summary.json").write_text(json.dumps(_jsonable(result.summary), indent=2) + "\n")
            if with_site:
                from terralod.site.build import site_from_windowed

                rep = site_from_windowed(
                    (before, after), [d or f"survey-{i + 1}" for i, d in enumerate(pair_dates)], [result],
                    [tmp / "dod.tif"], tmp / "site", store=inputs[0] if epoch_sides is not None else None,
                )  # fmt: skip
                console.print(
                    f"site: {rep.bytes / 1e6:.1f} MB in site/ (open it with `python -m http.server` there)"
                )
    finally:
        if client is not None:
            cluster = client.cluster if dask[0] == "local" else None
            client.close()
            if cluster is not None:
                cluster.close()
    _print_result(result, pair_dates, out)


def _without_folders(v, paths: list[str]):
    """``v`` with every folder of ``paths`` (as given and absolute) removed from its strings."""
    dirs = set()
    for p in paths:
        for q in (Path(p), Path(p).resolve()):
            if str(q.parent) not in ("", "."):
                dirs.add(str(q.parent) + os.sep)
    dirs = sorted(dirs, key=len, reverse=True)

    def clean(x):
        if isinstance(x, str):
            for d in dirs:
                x = x.replace(d, "")
            return x
        if isinstance(x, dict):
            return {k: clean(y) for k, y in x.items()}
        if isinstance(x, list | tuple):
            return [clean(y) for y in x]
        return x

    return clean(v)


def _write_site(dest: Path, result, hfs: list, dates: list, options: dict, gridding=None) -> None:  # noqa: ANN001
    """OUT/site/ (:mod:`terralod.site`): each epoch's 3D Tiles, the first → last pair (this run's result) and,
    for a series, the other pairs a site carries (:func:`terralod.site.data.pairs_of`) measured the same way.
    A LiDAR pair (``gridding``): each epoch's 3D Tiles are its survey's continuous-scale TIN."""
    from terralod.change.volumes import measure_change
    from terralod.site import site_from_change
    from terralod.site.data import pairs_of

    names = [d or f"survey-{i + 1}" for i, d in enumerate(dates)]
    index = {n: i for i, n in enumerate(names)}
    pairs = [(names[0], names[-1], result)]
    for a, b in pairs_of(names)[1:]:
        i, j = index[a], index[b]
        r = measure_change(hfs[i], hfs[j], dates=(dates[i], dates[j]), **options)
        pairs.append((a, b, r))
    lidar = {} if gridding is None else {"surveys": gridding.files, "crs": gridding.crs}
    rep = site_from_change(hfs, names, pairs, dest, **lidar)
    console.print(
        f"site: {rep.bytes / 1e6:.1f} MB in {dest.name}/ (open it with `python -m http.server` there)"
    )


def _jsonable(v):
    import numpy as np

    if isinstance(v, dict):
        return {str(k): _jsonable(x) for k, x in v.items()}
    if isinstance(v, list | tuple):
        return [_jsonable(x) for x in v]
    if isinstance(v, np.generic):
        v = v.item()
    if isinstance(v, float) and not np.isfinite(v):
        return None
    return v
