"""Vertex cohesion map (paper 000, ``../shared/papers/000_0f8c6950ace8a2d1.txt`` §3-4) against the Chunked-LOD
baseline, side by side in one run, on the real DEMs of ../shared/data (skipped when absent) and the bundled
Jacksboro sample:

a. per level, at the same vertex count (both methods store M x M vertices per tile): max and RMS error of
   the tiles' own measured surfaces (Hausdorff, metres; RMS vertical), and the mean of the per-tile max;
b. the analogue of paper 000 tables 1-2: 16 valley key points chosen automatically (the 16 largest
   Laplacian-of-Gaussian responses, sigma = 2 samples, at least N / 8 samples apart, i.e. the most negative
   values of the paper's eq. 1, whose sign is flipped against ``scipy.ndimage.gaussian_laplace``); the
   geometric error at those points (3-D distance from the sample to the drawn tile's surface) for both
   methods at one fixed screen error (the engine's selection at 2 px from a camera above the centre that
   sees the whole terrain, ~N / 1080 samples per pixel; the paper's data had 100 m per pixel) and at the
   same level (equal vertex count), with counts above 0.5 and 1 sample spacing (the paper's 50 m / 100 m
   at 100 m spacing);
c. triangles drawn along a scripted camera path (a circle over the terrain, 20 degrees down) at 2 px
   for both methods with :class:`terralod.Engine`, and the build cost: whole-store build seconds on one
   thread per tile, and the mesher alone per level (ms per 65² tile per core).

Targets (issue 3): at equal vertex count cohesion's max error <= 0.8 x Chunked LOD's on mountainous DEMs;
at equal error <= 0.5 x the triangles; build <= 50 ms per 65² tile per core.

Usage: ``python benchmarks/cohesion_vs_chunked.py [--quick] [--frames N]``;
writes benchmarks/results/cohesion_vs_chunked.{json,md,png}. Stores are cached in $TERRALOD_BENCH_CACHE.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from scipy import ndimage  # noqa: E402

from terralod import Camera, Engine, Heightfield, build_store, measure_error, open_store  # noqa: E402
from terralod.io.reader import read_heightfield, sample_heightfield  # noqa: E402
from terralod.pyramid import cohesion  # noqa: E402
from terralod.pyramid.builder import METHODS, register_method  # noqa: E402

from _common import RESULTS, SHARED, md_table, puget_sound_1k, write_results  # noqa: E402

CACHE = Path(os.environ.get("TERRALOD_BENCH_CACHE", Path(tempfile.gettempdir()) / "terralod-bench"))
TILE_SIZE = 65
THRESHOLD_PX = 2.0
#: "cohesion_paper" is paper 000 as written: LoG attraction + Hooke balance, no error-driven refinement.
METHOD_NAMES = ("chunked", "cohesion", "cohesion_paper")
register_method(
    "cohesion_paper", cohesion.make_mesher(attraction="log", refine=False, metric="vertical", work_stride=0)
)
N_KEY = 16


# -- terrains --------------------------------------------------------------------------------------------
def terrains(quick: bool) -> list[tuple[str, bool, Any]]:
    """(name, mountainous, loader) for every DEM; loaders return None when the file is absent."""

    def dem(name: str, **kw: Any):
        def load() -> Heightfield | None:
            p = SHARED / "dem" / name
            return read_heightfield(p, **kw) if p.exists() else None

        return load

    out = [
        ("puget_sound_1k", True, puget_sound_1k),
        ("grand_canyon_1200", True, dem("grand_canyon_hoppe_1200_u8.png", spacing_m=60.0)),
        ("pyrenees_srtm3_N42E001", True, dem("srtm3_N42E001.tif")),
        ("kilauea_30m", False, dem("kilauea_hawaii_30m_utm5.tif")),
        ("jacksboro_sample", False, sample_heightfield),
    ]
    return out[:1] + out[-1:] if quick else out


def cached_store(name: str, hf: Heightfield, method: str) -> tuple[Path, float | None]:
    """Build (single thread, timed) or reuse the store of ``hf``; returns (path, build seconds or None)."""
    CACHE.mkdir(parents=True, exist_ok=True)
    p = CACHE / f"{name}_{method}_m{TILE_SIZE}.terra"
    if p.exists():
        try:
            with open_store(p) as s:
                if (
                    s.complete
                    and s.meta.get("source_digest") == hf.digest()
                    and s.meta.get("method") == method
                ):
                    return p, None
        except Exception:  # noqa: BLE001 - a stale or broken cache entry is rebuilt
            pass
    t = time.perf_counter()
    build_store(hf, p, tile_size=TILE_SIZE, method=method, workers=1, overwrite=True)
    return p, time.perf_counter() - t


# -- (a) per level at equal vertex count ----------------------------------------------------------------
def per_level(store: Any) -> dict[int, dict[str, float]]:
    out: dict[int, dict[str, float]] = {}
    for r in store.tile_summaries():
        d = out.setdefault(r["level"], {"tiles": 0, "vertices": 0, "triangles": 0, "max_m": 0.0, "sum_tile_max": 0.0,
                                        "sumsq": 0.0, "samples": 0})  # fmt: skip
        d["tiles"] += 1
        d["vertices"] += r["n_vertices"]
        d["triangles"] += r["n_triangles"]
        d["max_m"] = max(d["max_m"], r["measured_error_m"])
        d["sum_tile_max"] += r["measured_error_m"]
        d["sumsq"] += r["rms_error_m"] ** 2 * r["n_samples"]
        d["samples"] += r["n_samples"]
    for d in out.values():
        d["rms_m"] = math.sqrt(d.pop("sumsq") / max(d.pop("samples"), 1))
        d["mean_tile_max_m"] = d.pop("sum_tile_max") / d["tiles"]
    return dict(sorted(out.items()))


# -- (b) valley key points --------------------------------------------------------------------------------
def key_points(hf: Heightfield, n: int = N_KEY) -> np.ndarray:
    """(n, 2) (row, col): the largest LoG responses (valleys), greedy, >= N / 8 samples apart, away from
    the border and from nodata."""
    lap = ndimage.gaussian_laplace(hf.elevation_m.astype(np.float64), 2.0, mode="nearest")
    ok = hf.valid & ndimage.binary_erosion(hf.valid, iterations=4, border_value=0)
    score = np.where(ok, lap, -np.inf)
    order = np.argsort(score, axis=None, kind="stable")[::-1]
    min_d = max(hf.height, hf.width) / 8.0
    picked: list[tuple[int, int]] = []
    for flat in order:
        if not np.isfinite(score.flat[flat]):
            break
        r, c = divmod(int(flat), hf.width)
        if all((r - pr) ** 2 + (c - pc) ** 2 >= min_d**2 for pr, pc in picked):
            picked.append((r, c))
            if len(picked) == n:
                break
    return np.array(picked, np.int64)


def top_camera(store: Any) -> Camera:
    """Straight down over the centre, high enough that the whole terrain fits the 1080 px height."""
    t, pyr = store.transform, store.pyramid
    w_m, h_m = pyr.width * t.a, pyr.height * -t.e
    cx, cy = t.c + 0.5 * w_m, t.f - 0.5 * h_m
    top = max(r["z_max_m"] for r in store.tile_summaries())
    fov = 60.0
    dist = 0.5 * max(h_m, w_m * 1080 / 1920) / math.tan(math.radians(fov / 2)) * 1.05
    return Camera((cx, cy, top + dist), (cx, cy, top), (0.0, 1.0, 0.0), fov, 1920, 1080, near_m=1.0)


def point_errors(
    hf: Heightfield, store: Any, pts: np.ndarray, tiles: list[tuple[int, int, int]]
) -> np.ndarray:
    """3-D distance (metres) from each key sample to the surface of the tile of ``tiles`` covering it."""
    pyr = store.pyramid
    out = np.full(len(pts), np.nan)
    for i, (r, c) in enumerate(pts):
        for code in tiles:
            r0, c0 = pyr.origin_rc(code)
            span = pyr.span(code[0])
            if r0 <= r <= r0 + span and c0 <= c <= c0 + span:
                t = store.tile(*code)
                mask = np.zeros(hf.shape, bool)
                mask[r, c] = True
                rep = measure_error(t.vertices, t.triangles, hf, mask=mask)
                if rep.n_samples:
                    out[i] = rep.hausdorff_m
                    break
    return out


def to_px(err_m: np.ndarray, cam: Camera, hf: Heightfield, pts: np.ndarray) -> np.ndarray:
    x, y = hf.world_xy(pts[:, 0].astype(float), pts[:, 1].astype(float))
    z = hf.elevation_m[pts[:, 0], pts[:, 1]]
    d = np.sqrt((x - cam.eye[0]) ** 2 + (y - cam.eye[1]) ** 2 + (z - cam.eye[2]) ** 2)
    return err_m * cam.height_px / (2.0 * d * math.tan(math.radians(cam.fov_y_deg) / 2.0))


# -- (c) camera path -------------------------------------------------------------------------------------
def path(store: Any, frames: int) -> list[Camera]:
    """A circle of radius 0.3 x extent around the centre, 20 degrees down, eye 0.02 x extent above the top."""
    t, pyr = store.transform, store.pyramid
    w_m, h_m = pyr.width * t.a, pyr.height * -t.e
    cx, cy = t.c + 0.5 * w_m, t.f - 0.5 * h_m
    top = max(r["z_max_m"] for r in store.tile_summaries())
    radius = 0.3 * min(w_m, h_m)
    ez = top + 0.02 * max(w_m, h_m)
    cams = []
    for i in range(frames):
        a = 2.0 * math.pi * i / frames
        ex, ey = cx + radius * math.cos(a), cy + radius * math.sin(a)
        heading = a + math.pi / 2
        p = math.radians(-20.0)
        d = (math.cos(p) * math.cos(heading), math.cos(p) * math.sin(heading), math.sin(p))
        cams.append(Camera((ex, ey, ez), (ex + 1000 * d[0], ey + 1000 * d[1], ez + 1000 * d[2]), fov_y_deg=60.0,
                           width_px=1920, height_px=1080))  # fmt: skip
    return cams


def tiles_worse(name: str) -> dict[str, int]:
    """Per cohesion variant: tiles whose own measured error exceeds the Chunked-LOD tile's (1e-6 m slack)."""
    out = {}
    with open_store(CACHE / f"{name}_chunked_m{TILE_SIZE}.terra") as b:
        ref = {(r["level"], r["x"], r["y"]): r["measured_error_m"] for r in b.tile_summaries()}
    for method in METHOD_NAMES[1:]:
        with open_store(CACHE / f"{name}_{method}_m{TILE_SIZE}.terra") as a:
            out[method] = sum(
                1
                for r in a.tile_summaries()
                if r["measured_error_m"] > ref[(r["level"], r["x"], r["y"])] + 1e-6
            )
    return out


def mesher_ms(hf: Heightfield, method: str, per_level_tiles: int = 8) -> dict[int, float]:
    """Mesher alone (no measurement, no encoding), ms per tile on one thread, per level (8 tiles spread over
    the level; a level of fewer tiles meshes them again up to 8 calls, so that a one-tile root is not a
    single sample of a loaded machine): CPU time of the calling thread (``time.thread_time``), the per-core
    cost, which other work on a shared machine does not inflate as it does wall time."""
    from terralod.tiles import TilePyramid

    pyr = TilePyramid(hf.width, hf.height, TILE_SIZE)
    fn = METHODS[method]
    out = {}
    for k in pyr.levels:
        codes = list(pyr.tile_codes(k))
        step = max(1, len(codes) // per_level_tiles)
        codes = codes[::step][:per_level_tiles]
        codes = [codes[i % len(codes)] for i in range(max(per_level_tiles, len(codes)))]
        t = time.thread_time()
        for c in codes:
            if getattr(fn, "needs_spacing", False):
                fn(hf.elevation_m, hf.valid, pyr, c, spacing_m=hf.spacing_m)
            else:
                fn(hf.elevation_m, hf.valid, pyr, c)
        out[k] = 1000.0 * (time.thread_time() - t) / len(codes)
    return out


# -- driver ----------------------------------------------------------------------------------------------
def run(quick: bool = False, frames: int = 48) -> dict[str, Any]:
    results: dict[str, Any] = {}
    # compile the kernels before anything is timed
    warm = sample_heightfield()
    for m in METHODS:
        mesher_ms(warm, m, per_level_tiles=1)
    for name, mountainous, load in terrains(quick):
        hf = load()
        if hf is None:
            print(f"skip {name}: data absent", flush=True)
            continue
        print(f"{name}: {hf.width}x{hf.height}", flush=True)
        rec: dict[str, Any] = {"size": [hf.width, hf.height], "spacing_m": list(hf.spacing_m),
                               "mountainous": mountainous, "methods": {}}  # fmt: skip
        pts = key_points(hf)
        rec["key_points_rc"] = pts.tolist()
        spacing = float(np.mean(hf.spacing_m))
        thresholds = (0.5 * spacing, 1.0 * spacing)
        rec["key_thresholds_m"] = list(thresholds)
        for method in METHOD_NAMES:
            p, secs = cached_store(name, hf, method)
            with open_store(p) as store:
                lv = per_level(store)
                n_tiles = sum(d["tiles"] for d in lv.values())
                m: dict[str, Any] = {"per_level": lv, "tiles": n_tiles}
                if secs is not None:
                    m["build_s_1thread"] = secs
                    m["build_ms_per_tile"] = 1000.0 * secs / n_tiles
                m["mesher_ms_per_tile"] = mesher_ms(hf, method)
                # (b) key points: engine at 2 px from the top camera, and at one fixed level
                cam = top_camera(store)
                sel = Engine(store, THRESHOLD_PX).update(cam)
                e_m = point_errors(hf, store, pts, sel.tiles)
                fixed = max(0, store.pyramid.max_level - 2)
                e_fix = point_errors(hf, store, pts, list(store.pyramid.tile_codes(fixed)))
                m["key"] = {
                    "engine_2px": {"errors_m": e_m.tolist(), "errors_px": to_px(e_m, cam, hf, pts).tolist(),
                                   "triangles": sel.stats.triangles, "levels": sel.stats.levels},
                    f"level_{fixed}": {"errors_m": e_fix.tolist()},
                }  # fmt: skip
                # (c) path
                eng = Engine(store, THRESHOLD_PX)
                tri, worst = [], []
                for c in path(store, frames):
                    s = eng.update(c)
                    tri.append(s.stats.triangles)
                    worst.append(s.stats.max_screen_error_px)
                m["path"] = {"frames": frames, "triangles": tri, "max_screen_error_px": worst}
            rec["methods"][method] = m
        rec["tiles_worse_than_chunked"] = tiles_worse(name)
        results[name] = rec
    return results


def _summary_tables(results: dict[str, Any]) -> str:
    md = ["# Vertex cohesion map vs Chunked LOD (paper 000), measured side by side\n"]
    md.append(f"Tiles of M = {TILE_SIZE}; errors are each tile's own measured surface (before the monotone max), "
              "metres; ratios are cohesion / chunked.\n")  # fmt: skip
    # (a)
    rows = []
    for name, rec in results.items():
        ch, co = rec["methods"]["chunked"]["per_level"], rec["methods"]["cohesion"]["per_level"]
        pa = rec["methods"]["cohesion_paper"]["per_level"]
        for k in ch:
            a, b, c = ch[k], co[k], pa[k]
            if a["max_m"] == 0 and b["max_m"] == 0:
                continue
            rows.append([name, k, a["vertices"], b["vertices"], a["max_m"], b["max_m"],
                         b["max_m"] / a["max_m"] if a["max_m"] else float("nan"), a["rms_m"], b["rms_m"],
                         b["rms_m"] / a["rms_m"] if a["rms_m"] else float("nan"),
                         b["mean_tile_max_m"] / a["mean_tile_max_m"] if a["mean_tile_max_m"] else float("nan"),
                         c["max_m"] / a["max_m"] if a["max_m"] else float("nan"),
                         c["rms_m"] / a["rms_m"] if a["rms_m"] else float("nan")])  # fmt: skip
    md.append("## (a) Error per level at equal vertex count\n")
    md.append("The last two columns: paper 000 as written (LoG attraction + Hooke balance, no error-driven "
              "refinement) / chunked.\n\n")  # fmt: skip
    md.append(md_table(["terrain", "level", "vertices chunked", "vertices cohesion", "max m chunked", "max m cohesion",
                        "max ratio", "RMS m chunked", "RMS m cohesion", "RMS ratio", "mean tile-max ratio",
                        "paper max ratio", "paper RMS ratio"], rows))  # fmt: skip
    # (b)
    rows = []
    for name, rec in results.items():
        lo, hi = rec["key_thresholds_m"]
        for method in METHOD_NAMES:
            k = rec["methods"][method]["key"]
            e = np.asarray(k["engine_2px"]["errors_m"])
            px = np.asarray(k["engine_2px"]["errors_px"])
            fixed_key = next(x for x in k if x.startswith("level_"))
            ef = np.asarray(k[fixed_key]["errors_m"])
            rows.append([name, method, float(np.nanmax(e)), float(np.nanmax(px)), int((e > hi).sum()), int((e > lo).sum()),
                         k["engine_2px"]["triangles"], fixed_key.replace("level_", ""), float(np.nanmax(ef)),
                         int((ef > hi).sum()), int((ef > lo).sum())])  # fmt: skip
    md.append("\n## (b) Paper 000 tables 1-2 analogue: 16 valley key points\n")
    md.append("Left: the engine's selection at 2 px from a camera above the centre seeing the whole terrain; right: "
              "all tiles of one level (equal vertex count). Thresholds: 1 and 0.5 x the DEM spacing.\n\n")  # fmt: skip
    md.append(md_table(["terrain", "method", "max error m (2 px)", "max error px", "# > 1 spacing", "# > 0.5 spacing",
                        "triangles drawn", "level", "max error m (level)", "# > 1 spacing", "# > 0.5 spacing"], rows))  # fmt: skip
    # (c)
    rows = []
    for name, rec in results.items():
        ch, co = rec["methods"]["chunked"], rec["methods"]["cohesion"]
        pa = rec["methods"]["cohesion_paper"]
        t_ch, t_co = np.asarray(ch["path"]["triangles"], float), np.asarray(co["path"]["triangles"], float)
        t_pa = np.asarray(pa["path"]["triangles"], float)
        rows.append([name, int(t_ch.mean()), int(t_co.mean()), float(t_co.sum() / t_ch.sum()),
                     float(np.median(t_co / t_ch)), float(t_pa.sum() / t_ch.sum()),
                     float(max(ch["path"]["max_screen_error_px"])),
                     float(max(co["path"]["max_screen_error_px"])), ch.get("build_ms_per_tile", float("nan")),
                     co.get("build_ms_per_tile", float("nan")), pa.get("build_ms_per_tile", float("nan")),
                     rec["tiles_worse_than_chunked"]["cohesion"], co["tiles"]])  # fmt: skip
    md.append(f"\n## (c) Triangles drawn along the camera path at {THRESHOLD_PX:g} px, and build cost\n")
    md.append(
        "Build: whole store (mesh + measure + encode) on one thread, ms per tile averaged over every level.\n\n"
    )
    md.append(md_table(["terrain", "mean triangles chunked", "mean triangles cohesion", "ratio (total)",
                        "median frame ratio", "paper ratio (total)", "worst px chunked", "worst px cohesion",
                        "build ms/tile chunked", "build ms/tile cohesion", "build ms/tile paper",
                        "cohesion tiles worse than chunked", "tiles"], rows))  # fmt: skip
    rows = []
    for name, rec in results.items():
        for method in METHOD_NAMES:
            ms = rec["methods"][method]["mesher_ms_per_tile"]
            rows.append([name, method] + [float(ms[k]) for k in sorted(ms)])
    width = max(len(r) for r in rows) - 2
    md.append("\nMesher alone, ms per 65² tile on one thread (CPU time of the thread, mean of 8 tile meshings per level, a level of fewer tiles meshes them again), by "
              "level (coarsest first; the finest level is the regular grid for both):\n\n")  # fmt: skip
    md.append(md_table(["terrain", "method"] + [f"L{k}" for k in range(width)],
                       [r + [""] * (width + 2 - len(r)) for r in rows]))  # fmt: skip
    return "".join(md)


def _plot(results: dict[str, Any], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(12, 4.5))
    for name, rec in results.items():
        ch, co = rec["methods"]["chunked"]["per_level"], rec["methods"]["cohesion"]["per_level"]
        ks = [k for k in ch if ch[k]["max_m"] > 0]
        ax[0].plot(ks, [co[k]["max_m"] / ch[k]["max_m"] for k in ks], "o-", label=name)
        t_ch = np.asarray(rec["methods"]["chunked"]["path"]["triangles"], float)
        t_co = np.asarray(rec["methods"]["cohesion"]["path"]["triangles"], float)
        ax[1].plot(t_co / t_ch, label=name)
    ax[0].axhline(0.8, color="k", ls="--", lw=0.8)
    ax[0].set(xlabel="level", ylabel="max error cohesion / chunked", title="(a) equal vertex count")
    ax[1].axhline(0.5, color="k", ls="--", lw=0.8)
    ax[1].set(
        xlabel="frame", ylabel="triangles cohesion / chunked", title=f"(c) camera path at {THRESHOLD_PX:g} px"
    )
    for a in ax:
        a.grid(alpha=0.3)
        a.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="Puget Sound and the bundled sample only")
    ap.add_argument("--frames", type=int, default=48, help="frames of the camera path")
    a = ap.parse_args(argv)
    results = run(quick=a.quick, frames=a.frames)
    md = _summary_tables(results)
    name = "cohesion_vs_chunked" + ("_quick" if a.quick else "")
    RESULTS.mkdir(parents=True, exist_ok=True)
    _plot(results, RESULTS / f"{name}.png")
    md += f"\n![ratios]({name}.png)\n"
    write_results(name, {"tile_size": TILE_SIZE, "threshold_px": THRESHOLD_PX, "terrains": results}, md)


if __name__ == "__main__":
    main()
