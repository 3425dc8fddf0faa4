"""``terralod change BEFORE/ AFTER/`` on mosaics of real SRTM3 tiles with a planted change: memory and time
against the cells per survey.

    python benchmarks/change_region.py [--tiles 16,64] [--source srtm3_N41E001]

BEFORE is ``benchmarks/region.py``'s mosaic (``write_mosaic``: the real tile mirror-tiled into n x n 1°
GeoTIFFs, EPSG:4326, int16); AFTER the same tiles with a planted mound (+60 m cone, 4 km radius) and pit
(-40 m cone, 3 km radius), added by longitude/latitude to every tile they touch (shared edge rows agree)
and rounded to the int16 metres the tiles store. The planted volumes are the rounded heights summed over
the lon/lat samples times each sample's area on the WGS 84 ellipsoid. ``terralod change`` reads both
folders window by window (warped block by block to the UTM zone of the centre: its measured volume is on
that grid), in a fresh process; its peak RSS is summed over the process tree (psutil, every 50 ms).

Rows: SRTM tiles, cells per survey (lon/lat samples), wall, CPU (user + sys of the process), peak RSS,
µs of wall per cell, planted and measured gain beyond the LoD and loss beyond the LoD, the 1-minute load.
Writes benchmarks/results/change_region.json and change_region.md; a run of some sizes keeps the rows
of the others.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from region import _tree_peak_rss, write_mosaic  # noqa: E402

from _common import SHARED, md_table, write_results  # noqa: E402

MOUND = (60.0, 4000.0)  #: height m, radius m
PIT = (-40.0, 3000.0)


def _planted(lon: np.ndarray, lat: np.ndarray, centres: list[tuple[float, float]]) -> np.ndarray:
    """The planted change (m) at lon/lat samples: a mound at centres[0], a pit at centres[1]."""
    from pyproj import Geod

    geod = Geod(ellps="WGS84")
    out = np.zeros(np.broadcast_shapes(lon.shape, lat.shape))
    for (h, r), (clon, clat) in zip((MOUND, PIT), centres, strict=True):
        _, _, d = geod.inv(np.full(out.shape, clon), np.full(out.shape, clat),
                           np.broadcast_to(lon, out.shape), np.broadcast_to(lat, out.shape))  # fmt: skip
        out += h * np.clip(1.0 - d / r, 0.0, None)
    return out


def write_after(before: list[Path], folder: Path, n: int) -> tuple[float, float]:
    """AFTER: the BEFORE tiles with the mound and the pit; returns the planted (gain, loss) in m³."""
    import rasterio
    from pyproj import Geod

    folder.mkdir(parents=True, exist_ok=True)
    # the mound north-west of the mosaic's centre, the pit south-east: inside tiles, off their edges
    c_lon, c_lat = 1 + n / 2, 41 + n / 2
    centres = [(c_lon - 0.27, c_lat + 0.23), (c_lon + 0.31, c_lat - 0.36)]
    gain = loss = 0.0
    geod = Geod(ellps="WGS84")
    counted: set[int] = set()
    for p in before:
        q = folder / p.name
        with rasterio.open(p) as ds:
            t, a, prof = ds.transform, ds.read(1), ds.profile
        rows, cols = np.indices(a.shape)
        lon, lat = t.c + (cols + 0.5) * t.a, t.f + (rows + 0.5) * t.e
        if (
            min(abs(lon[0, :] - c).min() for c, _ in centres) > 0.2
            and min(abs(lat[:, 0] - c).min() for _, c in centres) > 0.2
        ):
            shutil.copyfile(p, q)
            continue
        dz = np.rint(_planted(lon, lat, centres))
        valid = a != prof["nodata"]
        dz[~valid] = 0
        with rasterio.open(q, "w", **prof) as ds:
            ds.write((a + dz).astype(a.dtype), 1)
        # each lon/lat sample once (tiles share edge rows and columns), times its ellipsoidal area (a
        # function of its latitude only: one per row)
        rr, cc = np.nonzero(dz)
        keys = np.rint((lat[rr, 0] - 41) / -t.e).astype(np.int64) * (1 << 32) + np.rint(
            (lon[0, cc] - 1) / t.a
        ).astype(np.int64)
        fresh = ~np.isin(keys, np.fromiter(counted, np.int64, len(counted)))
        counted.update(keys[fresh].tolist())
        rr, cc = rr[fresh], cc[fresh]
        row_area = np.array([abs(geod.polygon_area_perimeter(
            [0.0, t.a, t.a, 0.0], [la - t.e / 2, la - t.e / 2, la + t.e / 2, la + t.e / 2])[0]) for la in lat[:, 0]])  # fmt: skip
        v = dz[rr, cc] * row_area[rr]
        gain += float(v[v > 0].sum())
        loss -= float(v[v < 0].sum())
    return gain, loss


def run_change(before: Path, after: Path, out: Path) -> dict:
    cmd = [sys.executable, "-m", "terralod", "change", str(before), str(after), "-o", str(out), "--no-views"]
    t0 = time.perf_counter()
    c0 = os.times()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    peak = _tree_peak_rss(proc)
    wall = time.perf_counter() - t0
    err = proc.stderr.read() if proc.stderr else ""
    if proc.returncode != 0:
        raise RuntimeError(err[-2000:])
    c1 = os.times()
    cpu = (c1.children_user - c0.children_user) + (c1.children_system - c0.children_system)
    return {"wall_s": wall, "cpu_s": cpu, "peak_rss_mib": peak / 2**20,
            "summary": json.loads((out / "summary.json").read_text())}  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--tiles", default="16,64", help="SRTM tiles per survey (squares), comma-separated")
    ap.add_argument("--source", default="srtm3_N41E001")
    args = ap.parse_args()
    counts = [int(v) for v in args.tiles.split(",")]
    src = SHARED / "dem" / f"{args.source}.tif"
    rows = []
    for count in counts:
        n = int(round(count**0.5))
        with tempfile.TemporaryDirectory(prefix="change_region_") as tmp:
            d = Path(tmp)
            before = write_mosaic(src, n, d / "before")
            gain, loss = write_after(before, d / "after", n)
            r = run_change(d / "before", d / "after", d / "out")
        s = r.pop("summary")
        cells = (1200 * n + 1) ** 2
        rows.append({
            "srtm_tiles": count, "cells": cells, "grid_cells": s["grid"]["shape"][0] * s["grid"]["shape"][1],
            **r, "us_per_cell": r["wall_s"] / cells * 1e6, "planted_gain_m3": gain, "planted_loss_m3": loss,
            "gain_m3_above_lod": s["gain_m3_above_lod"], "loss_m3_above_lod": s["loss_m3_above_lod"],
            "gain_m3": s["gain_m3"], "loss_m3": s["loss_m3"], "sigma_m": s["sigma_m"],
            "coregistration": s["coregistration"]["mode"], "sample_cells": s["windowed"]["sample_cells"],
            "load_1min": os.getloadavg()[0],
        })  # fmt: skip
        print(json.dumps(rows[-1]), flush=True)
    p = Path(__file__).resolve().parent / "results" / "change_region.json"
    if p.exists():
        rows = [x for x in json.loads(p.read_text())["runs"] if x["srtm_tiles"] not in counts] + rows
    rows.sort(key=lambda x: x["srtm_tiles"])
    table = md_table(
        ["SRTM tiles", "cells", "wall s", "CPU s", "peak RSS MiB", "µs/cell", "planted gain m³",
         "measured gain m³ (>LoD)", "planted loss m³", "measured loss m³ (>LoD)", "load"],
        [[x["srtm_tiles"], x["cells"], x["wall_s"], x["cpu_s"], x["peak_rss_mib"], x["us_per_cell"],
          x["planted_gain_m3"], x["gain_m3_above_lod"], x["planted_loss_m3"], x["loss_m3_above_lod"],
          x["load_1min"]] for x in rows],
    )  # fmt: skip
    write_results("change_region", {"source": args.source, "runs": rows}, table)


if __name__ == "__main__":
    main()
