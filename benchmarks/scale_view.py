"""Runtime out of core (issue 20, part 3): a store viewed within a memory budget selects what an unbounded
cache selects.

Builds (out of core, :func:`terralod.pyramid.distributed.build_store_windowed`) the 4097² mirror-tiled
Pyrenees of ``benchmarks/scale.py`` into a temporary folder, then flies ``render.offscreen.auto_path``
(FRAMES frames, 1920 x 1080, 2 px) twice through :class:`terralod.runtime.Engine`: once with a cache that
holds every tile, once with ``cache_bytes`` = BUDGET_MIB (the LRU of ``runtime/stitch.TileCache``, which
keeps at least the current view's working set). Both with ``async_loads`` off, so each frame's selection
is complete. Records per frame whether the drawn tiles are identical, the largest bytes the bounded cache
held, its misses (tile reads), and the store's tile payload. Writes ``benchmarks/results/scale_view.json``
and ``.md``. Run: ``python benchmarks/scale_view.py``.

Two paths: ``auto_path`` (overview descending toward the relief: its working set is every tile it reads,
so no budget can bind) and a low traverse (TRAVERSE_FRAMES frames, 1.5 km above the highest peak, west
to east across the whole terrain, looking ahead and down), which reads fine tiles and leaves them behind:
there the budget evicts, and the selection must still be the unbounded cache's.
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from scale import DEM, write_terrains  # noqa: E402

from _common import md_table, write_results  # noqa: E402

FRAMES = 120
TRAVERSE_FRAMES = 240
BUDGET_MIB = 4


def main() -> None:
    import terralod
    from terralod.io.windowed import RasterSource
    from terralod.pyramid.distributed import build_store_windowed
    from terralod.render.offscreen import auto_path
    from terralod.runtime import Camera, Engine

    if not DEM.exists():
        print(f"skipped: {DEM} not present")
        return
    with tempfile.TemporaryDirectory(prefix="terralod-view-") as tmp:
        dem = write_terrains(Path(tmp), False)["4097"]
        store_path = Path(tmp) / "big.terra"
        build_store_windowed(RasterSource(dem), store_path, method="chunked", workers=2)
        with terralod.open_store(store_path) as store:
            payload_mib = store.size_bytes() / 2**20
            paths = {"auto_path": auto_path(store, FRAMES), "low traverse": traverse(store, TRAVERSE_FRAMES)}
            runs: dict[str, dict] = {}
            for pname, path in paths.items():
                cams = [Camera(p.eye, p.target, (0.0, 0.0, 1.0), 60.0, 1920, 1080) for p in path]
                for name, kw in (("unbounded", {"cache_tiles": 10**6, "cache_bytes": 1 << 40}),
                                 ("budget", {"cache_tiles": 10**6, "cache_bytes": BUDGET_MIB << 20})):  # fmt: skip
                    eng = Engine(store, threshold_px=2.0, **kw)
                    tiles, peak, t = [], 0, time.perf_counter()
                    for cam in cams:
                        sel = eng.update(cam)
                        tiles.append(list(sel.tiles))
                        peak = max(peak, eng.cache.nbytes)
                    runs[f"{pname}/{name}"] = {
                        "path": pname, "cache": name, "tiles": tiles, "peak_cache_mib": peak / 2**20,
                        "misses": eng.cache.misses, "evicted": eng.cache.misses - len(eng.cache),
                        "seconds": time.perf_counter() - t, "frames": len(cams),
                    }  # fmt: skip
                    eng.close()
    rows, same = [], {}
    for pname in paths:
        a, b = runs[f"{pname}/unbounded"]["tiles"], runs[f"{pname}/budget"]["tiles"]
        same[pname] = sum(x == y for x, y in zip(a, b, strict=True))
        for cname in ("unbounded", "budget"):
            r = runs[f"{pname}/{cname}"]
            rows.append([pname, cname, r["peak_cache_mib"], r["misses"], r["evicted"], r["seconds"],
                         max(len(t) for t in r["tiles"]), f"{same[pname]} / {r['frames']}"])  # fmt: skip
    md = (f"# Viewing a store within a memory budget (issue 20)\n\n4097² Pyrenees store ({payload_mib:.1f} MiB on "
          f"disk, chunked), 1920x1080, 2 px, synchronous loads, budget {BUDGET_MIB} MiB; auto_path {FRAMES} "
          f"frames (overview to relief), low traverse {TRAVERSE_FRAMES} frames (1.5 km above the highest "
          "peak, west to east).\n\n"
          + md_table(["path", "cache", "peak cache MiB", "tile reads", "tiles evicted", "seconds",
                      "most drawn tiles", "frames with the unbounded run's tiles"], rows)
          + "\nThe engine's cache never evicts below its working set (the drawn tiles plus 25 % for neighbours, "
          "``TileCache.floor_tiles``), so a budget smaller than a frame's working set holds the working set: "
          "'peak cache MiB' above the budget is that floor. On auto_path every tile read stays in the working "
          "set (nothing to evict); the low traverse leaves tiles behind, which the budget evicts (and reads "
          "again if the path comes back).\n")  # fmt: skip
    write_results("scale_view", {"budget_mib": BUDGET_MIB, "same_frames": same, "store_mib": payload_mib,
                                 "runs": {k: {kk: vv for kk, vv in v.items() if kk != "tiles"} for k, v in runs.items()}},
                  md)  # fmt: skip


def traverse(store, n_frames: int) -> list:
    """West to east across the middle of the store, 1.5 km above its highest sample, looking 8 km ahead
    and down to the lowest height: fine tiles under the eye, coarse ones toward the horizon."""
    import numpy as np

    from terralod.render.offscreen import CameraPose, store_extent

    lo, hi = store_extent(store)
    y = 0.5 * (lo[1] + hi[1])
    out = []
    for i in range(n_frames):
        x = lo[0] + (hi[0] - lo[0]) * (0.02 + 0.96 * i / max(1, n_frames - 1))
        eye = np.array([x, y, hi[2] + 1500.0])
        tgt = np.array([x + 8000.0, y, lo[2]])
        out.append(CameraPose(tuple(map(float, eye)), tuple(map(float, tgt))))
    return out


if __name__ == "__main__":
    main()
