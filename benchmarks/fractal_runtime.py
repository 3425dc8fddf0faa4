"""Fractal levels at run time (paper 001 §3.1): along a close-up fly-through over Puget Sound 1k (or the
bundled sample when ../shared/data is absent), per frame: tiles and triangles drawn at 2 px with and
without fractal levels, the time spent selecting + generating + stitching, and the deepest level reached;
then the same path with paper 001's culling options (§3.2 back-face patches, §3.1 visible region) on, and
with a frame's new fractal tiles generated on one thread instead of every core (``FractalSource(workers=)``).

Writes ``benchmarks/results/fractal_runtime.{json,md}``. Run: ``python benchmarks/fractal_runtime.py``.
"""

from __future__ import annotations

import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from terralod import Camera, Engine, build_store, open_store, sample_heightfield  # noqa: E402
from terralod.fractal import FractalDetail  # noqa: E402
from terralod.runtime.fractal_source import FractalSource  # noqa: E402

from _common import md_table, puget_sound_1k, write_results  # noqa: E402


def close_path(hf, n: int):
    """A low pass across the terrain, 150-400 m above the ground, looking ahead and down."""
    h, w = hf.shape
    out = []
    for i in range(n):
        s = i / max(1, n - 1)
        r, c = int(h * (0.3 + 0.4 * s)), int(w * (0.25 + 0.5 * s))
        x, y = (float(v) for v in hf.world_xy(r, c))
        z = float(hf.elevation_m[max(0, r - 20) : r + 20, max(0, c - 20) : c + 20].max())
        up = 150.0 + 250.0 * abs(np.sin(3 * s))
        out.append(((x, y, z + up), (x + 8 * up, y - 8 * up, z - up)))
    return out


def main() -> None:
    hf = puget_sound_1k()
    name = "puget_sound_1k"
    if hf is None:
        hf, name = sample_heightfield(), "jacksboro_sample"
    frames = 60
    size = (1920, 1080)
    rows, results = [], {"terrain": name, "frames": frames, "size": size, "threshold_px": 2.0, "runs": {}}
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "s.terra"
        build_store(hf, out, tile_size=65, method="cohesion")  # as recorded in results/fractal_runtime.md
        with open_store(out) as store:
            cores = os.cpu_count() or 1
            runs = [(0, "", cores), (1, "", cores), (2, "", cores), (3, "", cores), (2, "", 1), (3, "", 1),
                    (0, "backface+region", cores), (1, "backface+region", cores), (2, "backface+region", cores)]  # fmt: skip
            for extra, cull, workers in runs:
                # a fresh detail per run: no run starts with tiles another one generated
                src = store if extra == 0 else FractalSource(store, FractalDetail(hf), extra, workers=workers)
                engine = Engine(src, threshold_px=2.0, cull_backfacing="backface" in cull,
                                cull_region="region" in cull)  # fmt: skip
                per = []
                for eye, tgt in close_path(hf, frames):
                    cam = Camera(eye, tgt, (0, 0, 1.0), 60.0, *size, near_m=1.0)
                    t = time.perf_counter()
                    sel = engine.update(cam)
                    meshes = list(sel.meshes())
                    ms = (time.perf_counter() - t) * 1e3
                    per.append((ms, sel.stats.triangles, sel.stats.tiles, max(c[0] for c in sel.tiles),
                                sel.stats.max_screen_error_px, sel.stats.backface_culled,
                                sel.stats.region_culled))  # fmt: skip
                    del meshes
                a = np.array(per, float)
                r = {"frame_ms_median": float(np.median(a[:, 0])), "frame_ms_max": float(a[:, 0].max()),
                     "triangles_median": float(np.median(a[:, 1])), "tiles_median": float(np.median(a[:, 2])),
                     "deepest_level": int(a[:, 3].max()), "max_screen_error_px_median": float(np.median(a[:, 4])),
                     "backface_culled_median": float(np.median(a[:, 5])),
                     "region_culled_median": float(np.median(a[:, 6]))}  # fmt: skip
                r["generation_threads"] = workers if extra else 0
                results["runs"][f"{extra}{'/' + cull if cull else ''}/{workers} threads"] = r
                rows.append([extra, cull or "-", workers if extra else "-", r["deepest_level"], int(r["triangles_median"]),
                             int(r["tiles_median"]), int(r["backface_culled_median"]), int(r["region_culled_median"]),
                             r["max_screen_error_px_median"], r["frame_ms_median"], r["frame_ms_max"]])  # fmt: skip
    md = (f"## Fractal levels along a close-up fly-through ({name}, {frames} frames, {size[0]}x{size[1]}, 2 px)\n\n"
          "Frame ms = select + on-demand fractal tile generation + stitching + normals (no drawing). "
          f"Generation threads: a frame's new fractal tiles generated on that many threads ({os.cpu_count()} cores "
          "here). A max screen error of inf means the eye is inside the box of a deepest-level tile (d = 0), "
          "which cannot be refined further.\n\n")  # fmt: skip
    md += md_table(["fractal levels", "culling", "generation threads", "deepest level", "triangles (median)", "tiles (median)",
                    "back-facing culled", "outside region culled", "max screen err px (median)",
                    "frame ms (median)", "frame ms (max)"], rows)  # fmt: skip
    write_results("fractal_runtime", results, md)


if __name__ == "__main__":
    main()
