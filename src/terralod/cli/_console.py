"""What a command prints: the consoles, progress of long jobs, and the tables and extents of
``info`` / ``build`` summaries.
"""

from __future__ import annotations

import logging
import sys
from typing import Any

import click
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

console = Console(stderr=False, width=None if sys.stdout.isatty() else 160)


err_console = Console(stderr=True)


log = logging.getLogger("terralod.cli")


def crs_name(crs: str | None) -> str:
    """The CRS in words: horizontal name, EPSG code and unit, vertical CRS when there is one; never WKT
    (:func:`terralod.io.georef.describe_crs`)."""
    from terralod.io.georef import describe_crs

    return describe_crs(crs)


class PlainProgress:
    """Progress as plain lines on stderr (for logs and pipes, where a bar would be noise): one line when a
    task starts, then ``label name: done/total (pct %), elapsed s`` at most every ``every_s`` seconds, and
    a last line when it ends. The subset of :class:`rich.progress.Progress` the commands use."""

    def __init__(self, label: str, every_s: float = 5.0, stream=None) -> None:
        self.label = label
        self.every_s = every_s
        self.stream = stream
        self._tasks: dict[int, dict[str, Any]] = {}

    def __enter__(self) -> PlainProgress:
        return self

    def __exit__(self, *exc: object) -> None:
        for k, t in self._tasks.items():
            if t["printed"] != (t["completed"], t["total"]):
                self._line(k)

    def add_task(self, description: str, total: float | None = None, **_: Any) -> int:
        import time

        k = len(self._tasks)
        self._tasks[k] = {"name": description, "total": total, "completed": 0, "t0": time.monotonic(),
                          "last": time.monotonic(), "printed": None}  # fmt: skip
        click.echo(f"{self.label} {description} ...", err=True, file=self.stream)
        return k

    def update(self, task: int, completed: float | None = None, total: float | None = None, **_: Any) -> None:
        import time

        t = self._tasks[task]
        if completed is not None:
            t["completed"] = completed
        if total is not None:
            t["total"] = total
        now = time.monotonic()
        done = t["total"] is not None and t["completed"] >= t["total"]
        if now - t["last"] >= self.every_s or (done and t["printed"] != (t["completed"], t["total"])):
            t["last"] = now
            self._line(task)

    def _line(self, task: int) -> None:
        import time

        t = self._tasks[task]
        t["printed"] = (t["completed"], t["total"])
        el = time.monotonic() - t["t0"]
        if t["total"]:
            pct = 100.0 * t["completed"] / t["total"]
            msg = f"{self.label} {t['name']}: {t['completed']:.0f}/{t['total']:.0f} ({pct:.0f} %), {el:.0f} s"
        else:
            msg = f"{self.label} {t['name']}: {t['completed']:.0f}, {el:.0f} s"
        click.echo(msg, err=True, file=self.stream)


def progress(label: str) -> Progress | PlainProgress:
    """A progress bar on stderr when it is a terminal; plain lines every few seconds otherwise."""
    if not sys.stderr.isatty():
        return PlainProgress(label)
    return Progress(
        TextColumn(f"[bold]{label}[/bold] {{task.description}}"), BarColumn(), MofNCompleteColumn(),
        TimeElapsedColumn(), console=err_console, transient=False,
    )  # fmt: skip


def frame_table(stats: dict[str, Any], title: str = "frame") -> None:
    """One row of frame statistics (tiles, triangles, screen error, select/stitch/draw ms)."""
    t = Table(title=title)
    for col in ("tiles", "triangles", "max screen error px", "select ms", "stitch ms", "draw ms"):
        t.add_column(col, justify="right")
    t.add_row(
        f"{float(stats.get('tiles', 0)):.0f}", f"{float(stats.get('triangles', 0)):,.0f}",
        f"{stats.get('max_screen_error_px', 0):.2f}", f"{stats.get('select_ms', 0):.2f}",
        f"{stats.get('stitch_ms', 0):.2f}", f"{stats.get('draw_ms', 0):.2f}",
    )  # fmt: skip
    console.print(t)


def extent_info(crs: str | None, bounds_m) -> dict[str, Any]:
    """``bounds_m`` [W, S, E, N] in the CRS, ``bounds_lonlat`` [W, S, E, N] in WGS84 degrees (None without
    a CRS) and ``size_km`` [east-west, north-south] of a footprint."""
    w, s_, e, n = (float(v) for v in bounds_m)
    lonlat = None
    if crs:
        try:  # rasterio's PROJ (pyproj is the web extra's)
            from rasterio.warp import transform_bounds

            lonlat = [float(v) for v in transform_bounds(crs, "EPSG:4326", w, s_, e, n, densify_pts=21)]
        except Exception:  # noqa: BLE001 - an unplaceable CRS has no lon/lat, the rest still holds
            lonlat = None
    return {"bounds_m": [w, s_, e, n], "bounds_lonlat": lonlat, "size_km": [(e - w) / 1e3, (n - s_) / 1e3]}


def print_extent(d: dict[str, Any], width: int = 13) -> None:
    """The footprint lines of ``info``: bounds in the CRS and in lon/lat, size in km, elevation range."""
    w, s_, e, n = d["bounds_m"]
    pad = " " * (width - 11)
    console.print(f"  bounds     {pad}W {w:,.1f}  S {s_:,.1f}  E {e:,.1f}  N {n:,.1f} m")
    if d.get("bounds_lonlat"):
        lw, ls, le, ln = d["bounds_lonlat"]
        console.print(f"  lon/lat    {pad}W {lw:.5f}  S {ls:.5f}  E {le:.5f}  N {ln:.5f} deg")
    console.print(f"  size       {pad}{d['size_km'][0]:,.2f} x {d['size_km'][1]:,.2f} km")
    lo, hi = d["elevation_range_m"]
    console.print(f"  elevation  {pad}{lo:,.2f} .. {hi:,.2f} m")


def heightfield_info(hf) -> dict[str, Any]:
    lo, hi = hf.valid_range_m()
    src = hf.nodata_fraction if hf.source_nodata_fraction is None else hf.source_nodata_fraction
    return {
        "kind": "heightfield",
        "source": hf.source,
        "size": [hf.width, hf.height],
        "crs": hf.crs,
        "spacing_m": list(hf.spacing_m),
        **extent_info(hf.crs, hf.bounds_m),
        "elevation_range_m": [lo, hi],
        "nodata_percent": 100.0 * hf.nodata_fraction,
        "source_nodata_percent": 100.0 * src,
        "reprojection_margin_percent": 100.0 * hf.margin_fraction,
        "fill_method": hf.fill_method,
        "notes": list(hf.notes),
    }


def print_store_summary(summary: dict[str, Any]) -> None:
    state = "complete" if summary["complete"] else "INCOMPLETE (finish with --resume)"
    console.print(f"{summary['path']}: {state}")
    bad = summary.get("checksum_failures")
    if bad:  # a line of its own: the path above may already fill the 80 columns
        first = ", ".join(str(tuple(c)) for c in summary.get("checksum_failures_first", [])[:2])
        console.print(f"{bad} tile(s) FAIL their checksums (e.g. {first}): run `terralod check`")
    elif bad == 0:
        console.print("every tile's checksum verified")
    from rich import box

    # compact (fits 80 columns with numbers of 10 digits): errors in metres, size in KiB
    t = Table(box=box.SIMPLE_HEAD, pad_edge=False, collapse_padding=True)
    for col in ("level", "tiles", "vertices", "triangles", "max error m", "max vert. m", "RMS m", "KiB"):
        t.add_column(col, justify="right", no_wrap=True)
    for k, d in summary["per_level"].items():
        t.add_row(
            str(k), f"{d['tiles']:,}", f"{d['vertices']:,}", f"{d['triangles']:,}", _g(d["max_error_m"]),
            _g(d["max_vertical_error_m"]), _g(d["rms_error_m"]), f"{d['bytes'] / 1024:,.0f}",
        )  # fmt: skip
    console.print(t)
    ladder = summary.get("target_error_m")
    if ladder:  # adaptive tiles: what each level was refined to (the measured errors are above)
        steps = ", ".join("0 (grid)" if v == 0 else f"{v:.4g}" for v in ladder)
        console.print(f"target max vertical error per level, m: {steps}")
    console.print(
        f"{summary['levels']} levels, {summary['tiles']}/{summary['tiles_planned']} tiles, tile size "
        f"{summary['tile_size']}, {summary['size_bytes'] / 1024 / 1024:.2f} MiB on disk"
    )
    if summary.get("errors_against"):  # a reprojected source: against which samples the errors hold
        console.print(summary["errors_against"])


def _g(v: float) -> str:
    """A metre figure in at most 7 characters (3 decimals below 100 m)."""
    return f"{v:.3f}" if abs(v) < 100 else f"{v:,.1f}" if abs(v) < 1e5 else f"{v:.3g}"


def print_tin_summary(d: dict[str, Any]) -> None:
    """Print :func:`terralod.tin.terra.model_summary` output."""
    console.print(
        f"  TIN          {d['vertices']:,} vertices, {d['triangles']:,} triangles (full resolution)"
    )
    base_pct = 100.0 * d["base_triangles"] / max(d["triangles"], 1)
    console.print(f"  base         {d['base_triangles']:,} triangles ({base_pct:.1f} %)")
    console.print(
        f"  scales       {d['scales']:,} ({d['records']:,} ΔT records of {d['collapses_per_record']} collapse(s), "
        f"{d['triangle_changes']:,} triangle changes) in {d['sub_blocks']} sub-blocks"
    )  # fmt: skip
    lo, hi = d["elevation_range_m"]
    console.print(f"  elevation    {lo:.2f} .. {hi:.2f} m")
    svo = d["svo_length_m"]
    console.print(f"  sqrt(MMQE)   {svo['base']:.3f} m at the base, {svo['full']:.3f} m at full resolution")
    if "max_vertical_error_m" in d:
        console.print(
            f"  max error    {d['max_vertical_error_m']['base']:.3f} m vertical at the base (measured), 0 at full"
        )
    if "size_bytes" in d:
        console.print(f"  size         {d['size_bytes']:,} bytes")
    for n in d.get("notes", []):
        console.print(f"  note         {n}")


def one_line(text: object, limit: int = 300) -> str:
    """``text`` on one line (multi-line PROJJSON, GDAL messages), at most ``limit`` characters."""
    t = " ".join(str(text).split())
    return t if len(t) <= limit else t[: limit - 3] + "..."


__all__ = [
    "console",
    "err_console",
    "log",
    "crs_name",
    "PlainProgress",
    "progress",
    "frame_table",
    "extent_info",
    "print_extent",
    "heightfield_info",
    "print_store_summary",
    "print_tin_summary",
    "one_line",
]
