"""The change site's figures: its size (bytes in all, per part, per km² of terrain, per epoch, the tile bytes
shared between epochs) and, in headless Chromium (software WebGL: SwiftShader here, the renderer string is
recorded), the time from opening the page to the first full view and per epoch switch and swipe.

    python benchmarks/site.py [--runs 3] [--no-series] [--mosaic N]

Sites: the St Helens pair (``terralod change 2000.tif 2007.tif -o OUT --site``) and, unless --no-series, the
27-epoch St Helens series (``terralod change series.npz -o OUT --site``), from ../shared/data/change. Each site
is served by ``python -m http.server`` (a plain static host); --mosaic N adds a pair of N x N real SRTM3 tiles
with a planted change (N = 4: 23 M cells a survey), given as two folders (read window by window). The first full view's bytes come from resource timing. Writes benchmarks/results/site.json and site.md.
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import ROOT, SHARED, md_table, write_results  # noqa: E402

PAIR = ["change/st_helens_crater_2000-09-25_10m.tif", "change/st_helens_crater_2007-07-05_10m.tif"]
SERIES = "change/st_helens_crater_timeseries_2000-2007_10m.npz"


def mosaic_pair(n: int, tmp: Path) -> list[Path]:
    """BEFORE / AFTER folders of n x n real SRTM3 tiles (benchmarks/region.py's mosaic) with
    benchmarks/change_region.py's planted mound and pit: two regions, which ``change --site`` reads window by
    window (each side's store built out of core)."""
    from change_region import write_after
    from region import write_mosaic

    before = write_mosaic(SHARED / "dem" / "srtm3_N41E001.tif", n, tmp / "mosaic_before")
    write_after(before, tmp / "mosaic_after", n)
    return [tmp / "mosaic_before", tmp / "mosaic_after"]


def make_site(inputs: list[Path], out: Path) -> tuple[Path, float, float]:
    """``terralod change BEFORE AFTER -o OUT --site``: (the site, seconds, peak RSS MiB by GNU time)."""
    t0 = time.perf_counter()
    r = subprocess.run(["/usr/bin/time", "-f", "%M", sys.executable, "-m", "terralod", "change", *map(str, inputs),
                        "-o", str(out), "--site", "--no-views"], check=True, capture_output=True, text=True)  # fmt: skip
    return out / "site", time.perf_counter() - t0, int(r.stderr.strip().splitlines()[-1]) / 1024


def size_figures(site: Path) -> dict:
    parts = {
        p: sum(f.stat().st_size for f in (site / p).rglob("*") if f.is_file())
        for p in ("epochs", "pairs", "cesium")
    }
    total = sum(f.stat().st_size for f in site.rglob("*") if f.is_file())
    m = json.loads((site / "site.json").read_text())
    pair = json.loads((site / m["pairs"][0]["url"]).read_text())
    h, w = pair["grid"]["shape"]
    cells_km2 = h * w * pair["grid"]["cell_area_m2"] / 1e6
    glb = list((site / "epochs").rglob("*.glb"))
    largest = max((f for f in site.rglob("*") if f.is_file()), key=lambda f: f.stat().st_size)
    largest_data = max((f for p in ("epochs", "pairs") for f in (site / p).rglob("*") if f.is_file()),
                       key=lambda f: f.stat().st_size)  # fmt: skip
    refs = sum(  # every tileset file (the root and the external ones it splits into)
        json.loads(t.read_text()).__repr__().count(".glb") for t in (site / "epochs").glob("*/tileset*.json")
    )
    return {"bytes": total, "parts": parts, "epochs": len(m["epochs"]), "pairs": len(m["pairs"]), "area_km2": cells_km2,
            "bytes_per_km2": total / cells_km2, "data_bytes_per_km2": (total - parts["cesium"]) / cells_km2,
            "epoch_bytes_each": parts["epochs"] / len(m["epochs"]), "glb_files": len(glb), "tile_references": refs,
            "cells": h * w, "largest_file": [largest.relative_to(site).as_posix(), largest.stat().st_size],
            "largest_data_file": [largest_data.relative_to(site).as_posix(), largest_data.stat().st_size]}  # fmt: skip


def browser_times(site: Path, epochs: list[str], runs: int, shots: str = "") -> dict:
    """Open the site ``runs`` times in headless Chromium; with ``shots`` (a path prefix), the first run's first
    full view, its "largest change" view and its swipe are saved as PNGs."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    srv = subprocess.Popen([sys.executable, "-m", "http.server", str(port), "--bind", "127.0.0.1"], cwd=site,
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # fmt: skip
    time.sleep(1.0)
    try:
        switches = epochs[:: max(1, len(epochs) // 6)][:6]
        steps = [{"op": "transfer"}]  # what the first full view fetched (the page is ready once it is drawn)
        steps += [{"op": "setEpoch", "args": [e]} for e in switches]
        steps.append({"op": "setSwipe", "args": [epochs[0], epochs[-1], 0.5]})
        out = []
        for k in range(runs):
            run_steps = steps
            if shots and k == 0:
                run_steps = [{**steps[0], "shot": "first-view"}, *steps[1:-1], {**steps[-1], "shot": "swipe"},
                             {"op": "press", "args": ["largest"], "shot": "largest", "settleMs": 6000}]  # fmt: skip
            job = {"url": f"http://127.0.0.1:{port}/", "shots": shots if k == 0 else "", "steps": run_steps,
                   "timeoutMs": 240000, "width": 1280, "height": 720}  # fmt: skip
            r = subprocess.run(["node", str(ROOT / "benchmarks" / "web" / "site_check.mjs")], input=json.dumps(job),
                               capture_output=True, text=True, timeout=600, cwd=ROOT)  # fmt: skip
            out.append(json.loads(r.stdout.strip().splitlines()[-1]))
    finally:
        srv.terminate()
        srv.wait(10)
    ready = [o["readyMs"] for o in out if "readyMs" in o]
    first = [x["value"] for o in out for x in o["results"] if x["op"] == "transfer"]
    data = [sum(v for k, v in f["bytes"].items() if k != "cesium") for f in first]
    switch = [x["ms"] for o in out for x in o["results"] if x["op"] == "setEpoch"]
    swipe = [x["ms"] for o in out for x in o["results"] if x["op"] == "setSwipe"]
    return {"renderer": out[0].get("renderer"), "errors": sum(len(o["errors"]) for o in out),
            "ready_ms_median": statistics.median(ready) if ready else None, "ready_ms": ready,
            "switch_ms_median": statistics.median(switch) if switch else None, "switch_ms_max": max(switch, default=None),
            "swipe_ms_median": statistics.median(swipe) if swipe else None, "viewport": "1280x720",
            "first_view": first[0] if first else None, "first_view_data_bytes_max": max(data, default=None)}  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--no-series", action="store_true")
    ap.add_argument("--mosaic", type=int, default=0, metavar="N",
                    help="also a pair of N x N real SRTM3 tiles with a planted mound and pit (change_region.py's)")  # fmt: skip
    ap.add_argument("--shots", default="", metavar="DIR",
                    help="save each site's first full view, swipe and largest-change view as PNGs in DIR")  # fmt: skip
    a = ap.parse_args()
    cases = {"St Helens pair (2000, 2007)": [SHARED / p for p in PAIR]}
    if not a.no_series:
        cases["St Helens series (27 epochs)"] = [SHARED / SERIES]
    rows, payload = [], {"sites": {}, "load_1min_before": os.getloadavg()[0]}
    with tempfile.TemporaryDirectory() as tmp:
        if a.mosaic:
            cases[f"SRTM3 mosaic {a.mosaic}² tiles, planted"] = mosaic_pair(a.mosaic, Path(tmp))
        for k, (name, inputs) in enumerate(cases.items()):
            site, secs, rss_mib = make_site(inputs, Path(tmp) / f"site{k}")
            sz = size_figures(site)
            epochs = [e["name"] for e in json.loads((site / "site.json").read_text())["epochs"]]
            shots = ""
            if a.shots:
                Path(a.shots).mkdir(parents=True, exist_ok=True)
                shots = str(Path(a.shots).resolve() / f"site{k}-")
            tm = browser_times(site, epochs, a.runs, shots)
            payload["sites"][name] = {"size": sz, "browser": tm, "change_site_seconds": secs,
                                      "change_site_peak_rss_mib": rss_mib}  # fmt: skip
            rows.append([name, sz["epochs"], sz["pairs"], f"{sz['bytes'] / 1e6:.1f}", f"{sz['parts']['cesium'] / 1e6:.1f}",
                         f"{sz['data_bytes_per_km2'] / 1e6:.2f}", f"{sz['epoch_bytes_each'] / 1e6:.2f}",
                         f"{sz['glb_files']:,} / {sz['tile_references']:,}",
                         f"{sz['cells'] / 1e6:.2f}", f"{sz['largest_data_file'][1] / 1e6:.2f}",
                         f"{tm['first_view_data_bytes_max'] / 1e6:.2f}", f"{tm['ready_ms_median'] / 1e3:.1f}",
                         f"{tm['switch_ms_median']:.0f} (max {tm['switch_ms_max']:.0f})", f"{tm['swipe_ms_median']:.0f}",
                         tm["errors"], f"{secs:.1f}", f"{rss_mib:,.0f}"])  # fmt: skip
            renderer = tm["renderer"]
    md = (
        "# The change site: size and load times\n\n"
        f"`python benchmarks/site.py` — served by `python -m http.server`, headless Chromium {a.runs} runs, "
        f"renderer: {renderer} (software WebGL: absolute times are this machine's CPU, not a GPU's); "
        f"1-minute load {payload['load_1min_before']:.1f} on {os.cpu_count()} CPUs before the run. The first view's "
        "data is what the page fetched by its first full view besides CesiumJS and the page's own files "
        "(site.json, the pair's JSON, the 3D Tiles, the rasters' tiles: resource timing's body sizes).\n\n"
        + md_table(
            [
                "site",
                "epochs",
                "pairs",
                "MB in all",
                "of which CesiumJS MB",
                "data MB per km²",
                "tiles MB per epoch",
                "glb files / tile references",
                "cells (M)",
                "largest data file MB",
                "first view data MB (max)",
                "open → first full view s",
                "epoch switch ms (median)",
                "swipe ms",
                "console errors",
                "`change --site` s",
                "`change --site` peak RSS MiB",
            ],
            rows,
        )  # fmt: skip
    )
    write_results("site", payload, md)


if __name__ == "__main__":
    main()
