"""A detail-increment TIN's web exports: 3D Tiles and quantized-mesh of the TIN store of a 513² SRTM3 crop.

    python benchmarks/tin_export.py [--keep DIR] [--repeat N] [--before OTHER_CHECKOUT/src]

Two crops of ../shared/data, each built with ``terralod build crop.tif -o tin.terra --method tin`` and
exported with ``terralod export tin.terra --format 3dtiles`` and ``--format quantized-mesh``, every command
a fresh process (start-up and the model's load included):

- ``N50E011 utm``: SRTM3 N50E011 resampled (bilinear) to UTM 32N at 90 m, its central 513² samples (no
  voids): the full-resolution TIN has 263,169 vertices and 524,288 triangles, the size of the issue's crop;
- ``N42E001 [300:813]``: rows and columns 300:813 of SRTM3 N42E001 (Pyrenees, geographic, a few voids),
  which the build reprojects to UTM 31N (a larger TIN).

Per export: wall, CPU (user + sys of the child), peak RSS of the child, the tiles and the triangles of the
exported pyramid (the CLI's report: skirts not counted) and triangles per second of wall. ``BEFORE`` holds
the same commands measured on this machine at commit ff4e3c0, before the export was made linear and the
TIN's ladder stopped at its first exact rung. Writes benchmarks/results/tin_export.json and .md.
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import SHARED, md_table, write_results  # noqa: E402

#: The same commands at commit ff4e3c0 on this machine (2 shared cores): N50E011 utm crop.
BEFORE = {
    "3dtiles": {"wall_s": 60.5, "cpu_s": 53.2, "peak_rss_mb": 796.1, "tiles": 94, "triangles": 11_006_024},
    "quantized-mesh": {
        "wall_s": 35.3,
        "cpu_s": 23.6,
        "peak_rss_mb": 871.3,
        "tiles": 44,
        "triangles": 125_375,
    },
}


def crop_utm(out: Path, side: int = 513) -> Path:
    """SRTM3 N50E011 resampled to UTM 32N at 90 m, its central side² samples."""
    import rasterio
    from rasterio.warp import Resampling, calculate_default_transform, reproject
    from rasterio.windows import Window, transform

    with rasterio.open(SHARED / "dem" / "srtm3_N50E011.tif") as ds:
        t, w, h = calculate_default_transform(
            ds.crs, "EPSG:32632", ds.width, ds.height, *ds.bounds, resolution=90
        )
        z = np.zeros((h, w), np.float32)
        reproject(rasterio.band(ds, 1), z, dst_transform=t, dst_crs="EPSG:32632", resampling=Resampling.bilinear,
                  dst_nodata=-32768)  # fmt: skip
    r0, c0 = (h - side) // 2, (w - side) // 2
    a = z[r0 : r0 + side, c0 : c0 + side]
    prof = {"driver": "GTiff", "width": side, "height": side, "count": 1, "dtype": "float32", "crs": "EPSG:32632",
            "transform": transform(Window(c0, r0, side, side), t), "nodata": -32768}  # fmt: skip
    with rasterio.open(out, "w", **prof) as o:
        o.write(a, 1)
    return out


def crop_geographic(out: Path, side: int = 513) -> Path:
    """Rows and columns 300:300 + side of SRTM3 N42E001, as read."""
    import rasterio
    from rasterio.windows import Window

    with rasterio.open(SHARED / "dem" / "srtm3_N42E001.tif") as ds:
        win = Window(300, 300, side, side)
        a = ds.read(1, window=win)
        prof = dict(ds.profile, width=side, height=side, transform=ds.window_transform(win), tiled=False)
    prof.pop("blockxsize", None)
    prof.pop("blockysize", None)
    with rasterio.open(out, "w", **prof) as o:
        o.write(a, 1)
    return out


def run(cmd: list[str], src: str | None = None) -> tuple[dict, str]:
    """Wall, CPU and peak RSS of a child process, and its output; ``src``: the terralod source folder it
    imports (another checkout, for an A/B in one run) instead of the installed one."""
    env = dict(os.environ, PYTHONPATH=src) if src else None
    t0 = time.perf_counter()
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env=env)
    _, status, ru = os.wait4(p.pid, 0)
    wall = time.perf_counter() - t0
    text = p.stdout.read().decode() if p.stdout else ""
    if status != 0:
        raise RuntimeError(f"{' '.join(cmd)}: exit {status}: {text[-2000:]}")
    return {"wall_s": wall, "cpu_s": ru.ru_utime + ru.ru_stime, "peak_rss_mb": ru.ru_maxrss / 1024}, text


def _tin_rate(tin_triangles: str | None, export_s: float) -> float | str:
    """The store's TIN triangles per second of the CLI's export time, millions ("" when unknown)."""
    if not tin_triangles or export_s <= 0:
        return ""
    return int(tin_triangles.replace(",", "")) / export_s / 1e6


def export(store: Path, fmt: str, out: Path, repeat: int, src: str | None = None) -> dict:
    """The export run ``repeat`` times (a fresh process each): medians of wall, CPU, export time and peak RSS."""
    runs = []
    for _ in range(repeat):
        m, text = run([sys.executable, "-m", "terralod", "export", str(store), "--format", fmt, "-o", str(out),
                       "--overwrite"], src)  # fmt: skip
        got = re.search(r"(\d+) tiles, ([\d,]+) triangles, .* in ([\d.]+) s", text)
        if got is None:
            raise RuntimeError(f"no report in: {text[-500:]}")
        m.update(tiles=int(got.group(1)), triangles=int(got.group(2).replace(",", "")),
                 export_s=float(got.group(3)))  # fmt: skip
        runs.append(m)
    out_m = {
        k: float(np.median([r[k] for r in runs])) for k in ("wall_s", "cpu_s", "peak_rss_mb", "export_s")
    }
    out_m.update(tiles=runs[0]["tiles"], triangles=runs[0]["triangles"], runs=runs)
    out_m["triangles_per_s"] = out_m["triangles"] / out_m["wall_s"]
    return out_m


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument(
        "--keep", help="folder to keep the crops, stores and exports in (default: a temporary one)"
    )
    ap.add_argument("--repeat", type=int, default=3, help="runs of each export (medians reported)")
    ap.add_argument("--before", help="another checkout's src/ folder: its exports of the same stores beside")
    ap.add_argument("--before-label", default="before", help="the name of --before's rows")
    ap.add_argument(
        "--side", type=int, default=513, help="crop side in samples (other than 513: tin_export_SIDE.*)"
    )
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="tin_export_") as tmp:
        d = Path(args.keep) if args.keep else Path(tmp)
        d.mkdir(parents=True, exist_ok=True)
        rows, payload = [], {"crops": {}, "before_ff4e3c0": BEFORE, "load_average_start": os.getloadavg()}
        side = args.side
        crops = ((f"N50E011 utm{'' if side == 513 else f' {side}²'}", crop_utm),
                 (f"N42E001 [300:{300 + side}]", crop_geographic))  # fmt: skip
        for name, make in crops:
            stem = name.split()[0]
            dem = make(d / f"{stem}.tif", side)
            store = d / f"{stem}.terra"
            build, text = run([sys.executable, "-m", "terralod", "build", str(dem), "-o", str(store), "--method",
                               "tin", "--overwrite"])  # fmt: skip
            tin = re.search(r"TIN\s+([\d,]+) vertices, ([\d,]+) triangles", text)
            res = {"build": build, "tin_vertices": tin.group(1) if tin else None,
                   "tin_triangles": tin.group(2) if tin else None, "store_bytes": store.stat().st_size}  # fmt: skip
            for fmt in ("3dtiles", "quantized-mesh"):
                both = [(name, fmt, None)] + ([(f"{name} ({args.before_label})", f"{fmt}@before", args.before)]
                                               if args.before else [])  # fmt: skip
                for label, key, src in both:
                    res[key] = m = export(store, fmt, d / f"{stem}_{fmt}", args.repeat, src)
                    rows.append([label, res["tin_triangles"], fmt, m["tiles"], m["triangles"], m["wall_s"],
                                 m["export_s"], m["cpu_s"], m["peak_rss_mb"], m["triangles_per_s"] / 1e6,
                                 _tin_rate(res["tin_triangles"], m["export_s"])])  # fmt: skip
                if name == "N50E011 utm":
                    b = BEFORE[fmt]
                    rows.append([name + " (before, ff4e3c0)", res["tin_triangles"], fmt, b["tiles"], b["triangles"],
                                 b["wall_s"], "", b["cpu_s"], b["peak_rss_mb"], b["triangles"] / b["wall_s"] / 1e6, ""])  # fmt: skip
            payload["crops"][name] = res
        payload["load_average_end"] = os.getloadavg()
    load = f"{payload['load_average_start'][0]:.1f} → {payload['load_average_end'][0]:.1f}"
    head = ["crop", "TIN triangles", "format", "tiles", "triangles exported", "wall s", "export s", "CPU s",
            "peak RSS MB", "M triangles/s (wall)", "M TIN triangles/s (export s)"]  # fmt: skip
    md = (
        "# TIN store → web exports (fresh `terralod export` process: start-up and model load included)\n\n"
        + md_table(head, rows)
        + f"\nMedians of {args.repeat} runs each. Load average (1 min) on {os.cpu_count()} cores over the run: {load} (a shared machine: wall "
        "times stretch with it, CPU times much less). "
        "'export s' is the CLI's own figure (the export after the model is loaded). "
        + (
            "The 3D Tiles pyramid of the N50E011 crop shrank from 94 to 57 tiles: the sub-blocks' ladders no "
            "longer list every scale after the first of error 0 (tiles whose parents declare 0 are never "
            "refined to). "
            if side == 513
            else f"Crops of {side}² samples: {(side - 1) ** 2 / 512**2:.0f}x the default crops' samples. "
        )
        + "The "
        "quantized-mesh export re-tiles the TIN on Cesium's geographic grid: each tile samples the TIN's "
        "surface (export/source.py TinSource: points located by a bucket grid, kernels/tinlocate.py) and "
        "simplifies those samples to the tile's error, so its pyramid holds far fewer triangles than the "
        "TIN; the last column divides the TIN's own triangles by the export's time.\n"
    )
    payload["side"] = side
    write_results("tin_export" if side == 513 else f"tin_export_{side}", payload, md)


if __name__ == "__main__":
    main()
