"""``terralod info PATH``: describe a DEM (size, CRS, spacing, range, nodata) or a ``.terra`` store."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import click

from terralod.cli._console import (
    console,
    crs_name,
    extent_info,
    heightfield_info,
    print_extent,
    print_store_summary,
    print_tin_summary,
)
from terralod.cli._options import is_store, load, read_options


def store_info(p: Path) -> dict[str, Any]:
    """The summary of a store of either kind (checksums of a TIN payload verified)."""
    from terralod.pyramid.builder import store_summary
    from terralod.store import TIN_METHOD, open_store, read_tin_store, store_method

    if store_method(p) == TIN_METHOD:
        meta, _ = read_tin_store(p)
        meta["size_bytes"] = p.stat().st_size
        if meta.get("bounds_m"):
            meta.update(extent_info(meta.get("crs"), meta["bounds_m"]))
        meta["crs_name"] = crs_name(meta.get("crs"))
        return meta
    with open_store(p) as s:
        summary = store_summary(s)
        summary["crs"] = s.crs
        summary["crs_name"] = crs_name(s.crs)
        summary["source"] = s.meta.get("source")
        summary["method"] = s.meta.get("method")
        summary["epochs"] = [{"name": r["name"], "state": r["state"], **r["info"]} for r in s.epoch_rows()]
        summary["epoch"] = s.epoch
        bad = s.checksum_failures()  # "complete" is said of tiles that pass their checksums
        summary["checksum_failures"] = len(bad)
        summary["checksum_failures_first"] = [list(c) for c in bad[:3]]
        summary.update(grid_extent(s))
    return summary


def grid_extent(s) -> dict[str, Any]:
    """Footprint of a grid store's source (pixel edges, from its metadata) and the elevation range of its
    stored vertices (tiles wholly over nodata excluded)."""
    t = s.meta.get("transform") or [1.0, 0.0, 0.0, 0.0, -1.0, 0.0]
    w, h = int(s.meta.get("width", 0)), int(s.meta.get("height", 0))
    a, _, c, _, e, f = (float(v) for v in t[:6])
    bounds = [min(c, c + w * a), min(f, f + h * e), max(c, c + w * a), max(f, f + h * e)]
    lo = [d["z_min_m"] for d in s.level_summaries().values() if d["z_min_m"] is not None]
    hi = [d["z_max_m"] for d in s.level_summaries().values() if d["z_max_m"] is not None]
    rng = [min(lo), max(hi)] if lo else [0.0, 0.0]
    out = extent_info(s.crs, bounds)
    out["elevation_range_m"] = [float(rng[0]), float(rng[1])]
    nf = s.meta.get("nodata_fraction")
    if nf is not None:
        out["nodata_percent"] = 100.0 * float(nf)
    snf, mf = s.meta.get("source_nodata_fraction"), s.meta.get("margin_fraction")
    if snf is not None:
        out["source_nodata_percent"] = 100.0 * float(snf)
    if mf is not None:
        out["reprojection_margin_percent"] = 100.0 * float(mf)
    return out


def print_nodata(d: dict[str, Any]) -> None:
    """The source's own nodata apart from the margin a reprojection leaves around it (DEMs and stores)."""
    if d.get("reprojection_margin_percent", 0.0) > 0 and d.get("source_nodata_percent") is not None:
        console.print(f"  nodata       {d['source_nodata_percent']:.4g} % of the source's samples")
        console.print(f"  margin       {d['reprojection_margin_percent']:.2f} % of the grid lies outside the "
                      "source (reprojection)")  # fmt: skip
    elif d.get("nodata_percent") is not None:
        console.print(f"  nodata       {d['nodata_percent']:.4g} %")


def print_epochs(d: dict[str, Any]) -> None:
    """One line per epoch of a store of epochs (the tiles above are those of ``d["epoch"]``)."""
    eps = d.get("epochs") or []
    if not eps:
        return
    console.print(f"{len(eps)} epochs (tiles above: {d.get('epoch')}; the last complete one is the default):")
    for e in eps:
        extra = (
            ""
            if e.get("kind") == "build"
            else f", {e.get('tiles_rebuilt', '?')} tiles rebuilt from {e.get('base')}"
        )
        state = "" if e["state"] == "complete" else " [INTERRUPTED: finish with update --resume]"
        console.print(f"  {e['name']:<12} {e.get('kind', '')}{extra}{state}")


@click.command()
@click.argument("path")
@click.option("--json", "as_json", is_flag=True, help="Print machine-readable JSON.")
@read_options
def info(path: str, as_json: bool, **read: Any) -> None:
    """Describe a DEM (size, CRS, spacing, range, nodata) or a .terra store (levels, tiles, errors)."""
    from terralod.store import TIN_METHOD

    p = Path(path)
    if p.is_dir() or (not p.exists() and any(ch in path for ch in "*?[")):
        _region_info(path, as_json, read.get("crs"))
        return
    if p.exists() and is_store(p):
        d = store_info(p)
        if as_json:
            click.echo(json.dumps(d, indent=2, default=str))
        elif d.get("method") == TIN_METHOD:
            console.print(f"source {d.get('source')}, method tin (Ai et al., 2019)")
            console.print(f"CRS {d['crs_name']}")
            if "bounds_m" in d:
                print_extent(d)
            print_tin_summary(d)
        else:
            console.print(f"source {d['source']}, method {d['method']}")
            console.print(f"CRS {d['crs_name']}")
            print_extent(d)
            print_nodata(d)
            print_store_summary(d)
            print_epochs(d)
        if d.get("checksum_failures"):
            from terralod.errors import CorruptStoreError

            raise CorruptStoreError(
                f"{d['checksum_failures']} tile(s) fail their checksums: `terralod check --repair` drops them, "
                "then `terralod build --resume` rebuilds them",
                str(p),
            )
        return
    if p.suffix.lower() in (".las", ".laz"):
        from terralod.tin.pointcloud import describe_las

        d = describe_las(p, crs=read.get("crs"))
        if as_json:
            click.echo(json.dumps(d, indent=2))
            return
        console.print(f"[bold]{d['source']}[/bold]")
        console.print(f"  kind         LAS {d['las_version']} point cloud, point format {d['point_format']}")
        console.print(f"  points       {d['points']:,} (header)")
        w, s, e, n = d["bounds"]
        console.print(f"  CRS          {d['crs_name']}")
        console.print(f"  bounds       {w:.2f}, {s:.2f} .. {e:.2f}, {n:.2f} (file units)")
        if d.get("bounds_lonlat"):
            lw, ls, le, ln = d["bounds_lonlat"]
            console.print(f"  lon/lat      W {lw:.5f}  S {ls:.5f}  E {le:.5f}  N {ln:.5f} deg")
        console.print(f"  z            {d['z_range'][0]:.2f} .. {d['z_range'][1]:.2f} (file units; "
                      f"{d['z_range'][0] * d['z_unit_m']:.2f} .. {d['z_range'][1] * d['z_unit_m']:.2f} m)")  # fmt: skip
        for note in d["notes"]:
            console.print(f"  note         {note}")
        return
    hf = load(path, **read)
    d = heightfield_info(hf)
    d["crs_name"] = crs_name(hf.crs)
    if as_json:
        click.echo(json.dumps(d, indent=2))
        return
    console.print(f"[bold]{d['source']}[/bold]")
    console.print(f"  size         {d['size'][0]} x {d['size'][1]} samples")
    console.print(f"  CRS          {d['crs_name']}")
    console.print(f"  spacing      {d['spacing_m'][0]:.3f} x {d['spacing_m'][1]:.3f} m")
    print_extent(d)
    print_nodata(d)
    for n in d["notes"] + ([d["fill_method"]] if d["fill_method"] else []):
        console.print(f"  note         {n}")


def _region_info(path: str, as_json: bool, crs: Any) -> None:
    """A region of DEM tiles (a folder or a quoted glob), from the files' headers only: how many files, the
    one grid they share, its extent in lon/lat (:func:`terralod.io.region.resolve_region`'s rules)."""
    from rasterio.warp import transform_bounds

    from terralod.io.region import resolve_region

    region = resolve_region([path], crs=crs)
    w, s, e, n = region.transform.c, region.transform.f + region.height * region.transform.e, (
        region.transform.c + region.width * region.transform.a), region.transform.f  # fmt: skip
    lw, ls, le, ln = transform_bounds(region.crs, "EPSG:4326", w, s, e, n, densify_pts=21)
    d = {
        "region": path,
        "files": [str(f) for f in region.files],
        "crs_name": crs_name(region.crs.to_wkt()),
        "size": [region.width, region.height],
        "samples": region.width * region.height,
        "resolution": [region.transform.a, -region.transform.e],
        "bounds_lonlat": [lw, ls, le, ln],
        "rules": "one grid; where files overlap the last listed wins; cells no file covers are nodata",
        "notes": list(region.notes),
    }
    if as_json:
        click.echo(json.dumps(d, indent=2, default=str))
        return
    console.print(f"region {path}: {len(d['files'])} files on one grid of {region.width:,} x {region.height:,} "
                  f"samples ({d['samples'] / 1e6:,.1f} M)", highlight=False)  # fmt: skip
    console.print(f"  CRS          {d['crs_name']}", highlight=False)
    console.print(
        f"  resolution   {region.transform.a:.9g} x {-region.transform.e:.9g} (CRS units)", highlight=False
    )
    console.print(f"  lon/lat      W {lw:.5f}  S {ls:.5f}  E {le:.5f}  N {ln:.5f} deg", highlight=False)
    console.print(f"  rules        {d['rules']}", highlight=False)
    for note in region.notes:
        console.print(f"  note         {note}", highlight=False)
