"""Epochs of one store (issue 15): the 27-epoch Mount St Helens series 2000-2007 (10 m, 303 x 442) built as
epochs of one ``.terra`` store, against a full rebuild of every epoch.

For each epoch i >= 1 (epoch i = base + delta[i], ../shared/data/change/*.npz):
- ``update_store`` of the store of epochs (the tiles whose source windows changed, ancestors included):
  wall and CPU seconds, tiles rebuilt, ms per rebuilt 65² tile (one worker, so per core);
- a full rebuild of the same epoch with the store's quantisation (one worker): seconds — and its tiles
  compared byte for byte with the update's (they must be identical);
- sizes: the store of 27 epochs against the 27 separate stores of those full rebuilds.

Then the time-lapse of the series is rendered once with ``terralod flythrough STORE --epochs all``, and a few
frames are extracted as PNGs beside the results to look at.

Run: ``python benchmarks/epochs.py [--quick]`` (``--quick``: 6 epochs). Writes results/epochs.{json,md}.
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from affine import Affine

from terralod import Heightfield, build_store, open_store
from terralod.pyramid.update import update_store

from _common import RESULTS, SHARED, md_table, write_results

SERIES = SHARED / "change" / "st_helens_crater_timeseries_2000-2007_10m.npz"


def load_series():
    z = np.load(SERIES)
    t = Affine.from_gdal(*[float(v) for v in z["transform"]])
    crs = str(z["crs"])
    base = z["base"].astype(np.float32)
    hfs = []
    for i, d in enumerate(z["dates"]):
        e = base + z["delta"][i]
        hfs.append((str(d), Heightfield(e, np.ones(e.shape, bool), t, crs, f"{SERIES.name}[{i}]")))
    return hfs


def rows(path: Path, epoch: str | None = None) -> dict:
    with open_store(path, epoch=epoch) as s:
        return {c: s.raw_tile(*c) for c in s.tile_codes()}


def local_edits(tmp: Path, quick: bool) -> dict | None:
    """Pits dug into Puget Sound 1k one after the other (each a new epoch) vs a full rebuild."""
    import json

    from terralod.change.epochs import edit_store

    from _common import puget_sound_1k

    hf = puget_sound_1k()
    if hf is None:
        return None
    store = tmp / "puget.terra"
    build_store(hf, store, tile_size=65, epoch="2020-01-01", workers=1, method="cohesion")
    out = []
    w, s_, e, n = hf.bounds_m
    pits = [(0.3, 0.6), (0.7, 0.4), (0.5, 0.25)][: 2 if quick else 3]
    for k, (fx, fy) in enumerate(pits):
        x0, y0 = w + fx * (e - w), s_ + fy * (n - s_)
        ring = [[x0, y0], [x0 + 2000, y0], [x0 + 2000, y0 + 2000], [x0, y0 + 2000], [x0, y0]]
        gj = tmp / f"pit{k}.geojson"
        gj.write_text(json.dumps({"type": "Polygon", "coordinates": [ring], "crs": {"type": "name",
                                  "properties": {"name": "local"}}}))  # fmt: skip
        t0, c0 = time.perf_counter(), time.process_time()
        res, rep = edit_store(store, polygon=gj, depth_m=12.0, epoch=f"pit-{k + 1}", workers=1)
        out.append({"pit": f"pit-{k + 1}", "tiles_rebuilt": rep.tiles_dirty, "tiles_total": rep.tiles_total,
                    "edit_wall_s": time.perf_counter() - t0, "edit_cpu_s": time.process_time() - c0,
                    "cpu_ms_per_rebuilt_tile": 1e3 * (time.process_time() - c0) / max(rep.tiles_built, 1),
                    "mesh_cpu_ms_per_rebuilt_tile": rep.cpu_ms_per_tile,
                    "volume_m3": res.volume_m3})  # fmt: skip
    with open_store(store) as st:
        quant = st.quantisation
        last = st.epoch
    from terralod.change.epochs import epoch_heightfield

    fresh = tmp / "puget_fresh.terra"
    t0, c0 = time.perf_counter(), time.process_time()
    build_store(
        epoch_heightfield(store, last), fresh, tile_size=65, quantisation=quant, workers=1, method="cohesion"
    )
    full_wall, full_cpu = time.perf_counter() - t0, time.process_time() - c0
    identical = rows(store, last) == rows(fresh)
    med = statistics.median
    return {"rows": out, "summary": {
        "n": len(out), "tiles_total": out[0]["tiles_total"],
        "median_tiles_rebuilt": med(r["tiles_rebuilt"] for r in out),
        "median_edit_wall_s": med(r["edit_wall_s"] for r in out),
        "median_edit_cpu_s": med(r["edit_cpu_s"] for r in out),
        "median_cpu_ms_per_rebuilt_tile": med(r["cpu_ms_per_rebuilt_tile"] for r in out),
        "median_mesh_cpu_ms_per_rebuilt_tile": med(r["mesh_cpu_ms_per_rebuilt_tile"] for r in out),
        "full_wall_s": full_wall, "full_cpu_s": full_cpu, "identical": identical,
    }}  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="6 epochs only")
    ap.add_argument("--no-video", action="store_true")
    args = ap.parse_args()
    if not SERIES.exists():
        sys.exit(f"skipped: {SERIES} not present")
    series = load_series()
    if args.quick:
        series = series[:6]
    tmp = Path(tempfile.mkdtemp(prefix="epochs_bench_"))
    store = tmp / "st_helens_27.terra"
    t0, c0 = time.perf_counter(), time.process_time()
    first = build_store(series[0][1], store, tile_size=65, epoch=series[0][0], workers=1, method="cohesion")
    build0 = {
        "wall_s": time.perf_counter() - t0,
        "cpu_s": time.process_time() - c0,
        "tiles": first.tiles_total,
    }
    with open_store(store) as s:
        quant = s.quantisation
    per_epoch = []
    separate_bytes = 0
    sep0 = tmp / "separate_00.terra"
    build_store(series[0][1], sep0, tile_size=65, quantisation=quant, workers=1, method="cohesion")
    separate_bytes += sep0.stat().st_size
    for i, (date, hf) in enumerate(series[1:], start=1):
        t0, c0 = time.perf_counter(), time.process_time()
        rep = update_store(hf, store, date, workers=1)
        up_wall, up_cpu = time.perf_counter() - t0, time.process_time() - c0
        sep = tmp / f"separate_{i:02d}.terra"
        t0, c0 = time.perf_counter(), time.process_time()
        full = build_store(hf, sep, tile_size=65, quantisation=quant, workers=1, method="cohesion")
        full_wall, full_cpu = time.perf_counter() - t0, time.process_time() - c0
        separate_bytes += sep.stat().st_size
        identical = rows(store, date) == rows(sep)
        per_epoch.append({
            "epoch": date, "changed_samples": rep.changed_samples, "tiles_total": rep.tiles_total,
            "tiles_rebuilt": rep.tiles_dirty, "update_wall_s": up_wall, "update_cpu_s": up_cpu,
            "rebuild_wall_s": rep.build_seconds,
            "ms_per_rebuilt_tile": 1e3 * rep.build_seconds / max(rep.tiles_built, 1),
            "cpu_ms_per_rebuilt_tile": 1e3 * up_cpu / max(rep.tiles_built, 1),
            "mesh_cpu_ms_per_rebuilt_tile": rep.cpu_ms_per_tile,
            "full_wall_s": full_wall, "full_cpu_s": full_cpu, "full_tiles": full.tiles_built,
            "ms_per_tile_full": 1e3 * full_wall / full.tiles_built,
            "cpu_ms_per_tile_full": 1e3 * full_cpu / full.tiles_built,
            "identical_to_full_build": identical,
        })  # fmt: skip
        print(f"{date}: {rep.tiles_dirty}/{rep.tiles_total} tiles, update {up_wall:.2f} s, full {full_wall:.2f} s, "
              f"identical {identical}", flush=True)  # fmt: skip
    store_bytes = store.stat().st_size
    med = statistics.median
    summary = {
        "epochs": len(series),
        "grid": [series[0][1].width, series[0][1].height],
        "tile_size": 65,
        "first_build": build0,
        "median_update_wall_s": med(r["update_wall_s"] for r in per_epoch),
        "median_full_wall_s": med(r["full_wall_s"] for r in per_epoch),
        "median_update_cpu_s": med(r["update_cpu_s"] for r in per_epoch),
        "median_full_cpu_s": med(r["full_cpu_s"] for r in per_epoch),
        "median_tiles_rebuilt": med(r["tiles_rebuilt"] for r in per_epoch),
        "median_ms_per_rebuilt_tile": med(r["ms_per_rebuilt_tile"] for r in per_epoch),
        "median_ms_per_tile_full": med(r["ms_per_tile_full"] for r in per_epoch),
        "median_cpu_ms_per_rebuilt_tile": med(r["cpu_ms_per_rebuilt_tile"] for r in per_epoch),
        "median_mesh_cpu_ms_per_rebuilt_tile": med(r["mesh_cpu_ms_per_rebuilt_tile"] for r in per_epoch),
        "median_cpu_ms_per_tile_full": med(r["cpu_ms_per_tile_full"] for r in per_epoch),
        "all_identical": all(r["identical_to_full_build"] for r in per_epoch),
        "store_bytes": store_bytes,
        "separate_stores_bytes": separate_bytes,
        "store_over_separate": store_bytes / separate_bytes,
    }
    edits = local_edits(tmp, quick=args.quick)
    summary["edits_puget_1k"] = edits["summary"] if edits else None
    frames = []
    if not args.no_video:
        video = RESULTS / "epochs_timelapse.mp4"
        t0 = time.perf_counter()
        p = subprocess.run([sys.executable, "-m", "terralod", "flythrough", str(store), "--epochs", "all", "-o",
                            str(video), "--overlay", "change", "--size", "960x540", "--fps", "12",
                            "--seconds-per-epoch", "0.5", "--overwrite"], capture_output=True, text=True)  # fmt: skip
        summary["timelapse_s"] = time.perf_counter() - t0
        if p.returncode != 0:
            print(p.stderr[-2000:])
        else:
            import imageio.v2 as imageio

            rd = imageio.get_reader(str(video))
            n = rd.count_frames()
            for k in (3, n // 2, n - 3):
                img = rd.get_data(k)
                out = RESULTS / f"epochs_timelapse_frame{k:03d}.png"
                imageio.imwrite(out, img)
                frames.append(out.name)
            summary["timelapse_frames"] = n
            summary["timelapse_bytes"] = video.stat().st_size
    hdr = ["epoch", "samples changed", "tiles rebuilt / total", "update s", "full rebuild s", "update / full",
           "update CPU s", "full CPU s", "mesh CPU ms per rebuilt tile", "wall ms per rebuilt tile", "identical"]  # fmt: skip
    table = [[r["epoch"], r["changed_samples"], f"{r['tiles_rebuilt']}/{r['tiles_total']}", r["update_wall_s"],
              r["full_wall_s"], r["update_wall_s"] / r["full_wall_s"], r["update_cpu_s"], r["full_cpu_s"],
              r["mesh_cpu_ms_per_rebuilt_tile"], r["ms_per_rebuilt_tile"],
              "yes" if r["identical_to_full_build"] else "NO"] for r in per_epoch]  # fmt: skip
    md = (
        f"# Epochs of one store: St Helens {len(series)} epochs, {summary['grid'][0]} x {summary['grid'][1]} at "
        "10 m, 65² tiles, one worker\n\n"
        f"Medians over {len(per_epoch)} epoch updates: update {summary['median_update_wall_s']:.2f} s vs full "
        f"rebuild {summary['median_full_wall_s']:.2f} s (CPU {summary['median_update_cpu_s']:.2f} vs "
        f"{summary['median_full_cpu_s']:.2f} s); {summary['median_tiles_rebuilt']:.0f} of "
        f"{per_epoch[0]['tiles_total'] if per_epoch else 0} tiles rebuilt; "
        f"{summary['median_mesh_cpu_ms_per_rebuilt_tile']:.1f} ms CPU per rebuilt tile to mesh, measure and "
        f"write it ({summary['median_cpu_ms_per_rebuilt_tile']:.1f} ms with the whole update's CPU time; wall {summary['median_ms_per_rebuilt_tile']:.1f} ms on this shared machine; full build: "
        f"{summary['median_cpu_ms_per_tile_full']:.1f} ms CPU per tile; goal <= 50 ms per tile per core). "
        "Rebuilt tiles are always the costlier ones: every ancestor of a change up to the root, each "
        "re-meshed and measured against all the samples it covers.\n\n"
        f"Every updated epoch byte-identical to its full rebuild: {summary['all_identical']}.\n\n"
        f"Size: one store of {len(series)} epochs {store_bytes / 2**20:.2f} MiB (tiles + each epoch's source "
        f"samples) vs {len(series)} separate stores {separate_bytes / 2**20:.2f} MiB (tiles only): "
        f"{summary['store_over_separate']:.3f} x.\n\n"
        + md_table(hdr, table)
        + ("\nTime-lapse: results/epochs_timelapse.mp4; frames " + ", ".join(frames) + "\n" if frames else "")
    )
    if edits:
        e = edits["summary"]
        md += (
            "\n## Local edits on a larger terrain: Puget Sound 1025² (160 m), 65² tiles, one worker\n\n"
            f"{e['n']} pits of 2 x 2 km dug 12 m (`edit_store`): median {e['median_tiles_rebuilt']:.0f} of "
            f"{e['tiles_total']} tiles rebuilt, edit {e['median_edit_wall_s']:.2f} s (CPU "
            f"{e['median_edit_cpu_s']:.2f} s) vs full rebuild {e['full_wall_s']:.2f} s (CPU {e['full_cpu_s']:.2f} s); "
            f"{e['median_mesh_cpu_ms_per_rebuilt_tile']:.1f} ms CPU per rebuilt tile to mesh, measure and write it "
            f"({e['median_cpu_ms_per_rebuilt_tile']:.1f} with the whole edit's CPU time; the tiles rebuilt are the "
            "chain of ancestors up to the root, the costliest of the store); byte-identical to a full "
            f"rebuild: {e['identical']}.\n\n"
            + md_table(
                ["pit", "tiles rebuilt", "edit s", "edit CPU s", "mesh CPU ms per rebuilt tile"],
                [
                    [
                        r["pit"],
                        r["tiles_rebuilt"],
                        r["edit_wall_s"],
                        r["edit_cpu_s"],
                        r["mesh_cpu_ms_per_rebuilt_tile"],
                    ]
                    for r in edits["rows"]
                ],
            )  # fmt: skip
        )
    write_results("epochs", {"summary": summary, "per_epoch": per_epoch,
                             "edits_puget_1k": edits["rows"] if edits else None}, md)  # fmt: skip
    shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
