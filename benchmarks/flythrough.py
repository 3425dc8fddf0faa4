"""Fly-through benchmark (paper 000 Figures 6-7 analogue): the same scripted camera path over Puget Sound 1k
and a 4097² terrain mirror-tiled from it, for every build method available (Chunked LOD; cohesion once
registered), drawn by the real renderer (EGL; Mesa llvmpipe on machines without a GPU).

Per method and terrain: median/p95 frame time (select + stitch + upload + draw + read-back), the draw
part alone for both draw paths of the renderer (one multi-draw-indirect call per frame over shared
buffers, or one draw call per tile), triangles and tiles drawn, max screen error, and GPU memory held by
tile geometry. On llvmpipe the absolute frame rate
says little; compare methods by the ratios. Writes ``benchmarks/results/flythrough.{json,md}``.

Run: ``python benchmarks/flythrough.py [--quick] [--frames N] [--size 1280x720]``.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from terralod import build_store, open_store  # noqa: E402
from terralod.pyramid.builder import METHODS  # noqa: E402

from _common import md_table, puget_sound_1k, puget_sound_4k, write_results  # noqa: E402


def run(store_path: Path, frames: int, size: tuple[int, int], threshold_px: float, draw_mode: str) -> dict:
    from terralod.render.offscreen import FrameRenderer, auto_path

    with open_store(store_path) as s:
        fr = FrameRenderer(s, size[0], size[1], threshold_px=threshold_px, draw_mode=draw_mode)
        path = auto_path(s, frames)
        fr.frame(path[0])  # warm-up: shader compile, first uploads
        rows = []
        for pose in path:
            t = time.perf_counter()
            fr.frame(pose)
            ms = (time.perf_counter() - t) * 1e3
            st = fr.last_stats
            rows.append((ms, st["triangles"], st["tiles"], st["max_screen_error_px"], fr.renderer.gpu_bytes,
                         st["draw_ms"]))  # fmt: skip
        info = {"gl_renderer": fr.renderer.gl_renderer, "draw_mode": fr.renderer.draw_mode,
                "draw_calls_per_frame": fr.renderer.draw_calls / (len(path) + 1)}  # fmt: skip
        fr.close()
    a = np.array(rows, float)
    return {
        "frame_ms_median": float(np.median(a[:, 0])), "frame_ms_p95": float(np.percentile(a[:, 0], 95)),
        "draw_ms_median": float(np.median(a[:, 5])),
        "triangles_median": float(np.median(a[:, 1])), "tiles_median": float(np.median(a[:, 2])),
        "max_screen_error_px": float(a[:, 3].max()), "gpu_mib_max": float(a[:, 4].max() / 2**20), **info,
    }  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="Puget Sound 1k only")
    ap.add_argument("--frames", type=int, default=120)
    ap.add_argument("--size", default="1280x720")
    ap.add_argument("--threshold-px", type=float, default=2.0)
    ap.add_argument("--draw-modes", default="indirect,plain", help="renderer draw paths to compare")
    args = ap.parse_args()
    size = tuple(int(v) for v in args.size.split("x"))
    terrains = {"puget_sound_1k": puget_sound_1k}
    if not args.quick:
        terrains["puget_sound_4k_mirror"] = puget_sound_4k
    methods = [m for m in ("chunked", "cohesion") if m in METHODS]
    results: dict = {"size": size, "frames": args.frames, "threshold_px": args.threshold_px, "runs": {}}
    rows = []
    cache = Path(os.environ.get("TERRALOD_BENCH_CACHE", tempfile.gettempdir())) / "terralod-flythrough"
    cache.mkdir(parents=True, exist_ok=True)
    for tname, make in terrains.items():
        hf = make()
        if hf is None:
            print(f"skip {tname}: ../shared/data not present")
            continue
        base = None
        for method in methods:
            out = cache / f"{tname}-{method}.terra"
            if not out.exists():
                build_store(hf, out, tile_size=65, method=method)
            for mode in args.draw_modes.split(","):
                r = run(out, args.frames, size, args.threshold_px, mode)
                results["runs"][f"{tname}/{method}/{r['draw_mode']}"] = r
                base = base or r
                rows.append([tname, method, r["draw_mode"], r["frame_ms_median"], r["frame_ms_p95"],
                             r["draw_ms_median"], r["draw_calls_per_frame"], int(r["triangles_median"]),
                             int(r["tiles_median"]), r["max_screen_error_px"], r["gpu_mib_max"],
                             r["triangles_median"] / base["triangles_median"],
                             r["gpu_mib_max"] / base["gpu_mib_max"]])  # fmt: skip
    gl = next(iter(results["runs"].values()), {}).get("gl_renderer", "?")
    md = f"## Fly-through, {args.frames} frames at {size[0]}x{size[1]}, threshold {args.threshold_px} px ({gl})\n\n"
    md += md_table(["terrain", "method", "draw path", "frame ms (median)", "frame ms (p95)", "draw ms (median)",
                    "draw calls/frame", "triangles", "tiles", "max screen err px", "GPU MiB",
                    "triangles vs chunked", "GPU mem vs chunked"], rows)  # fmt: skip
    write_results("flythrough", results, md)


if __name__ == "__main__":
    main()
