"""Detail-increment TIN build on flat ground: 513² windows of SRTM tiles with sea at 0 m.

The QEM's vertical term once located every point a flat fan carries for every candidate collapse (the
flat-area slow path of issue 19); :func:`terralod.kernels.qem._carried_gap2` now skips points on level
triangles. This times ``DetailIncrementModel.from_heightfield`` (4 sub-blocks, threads) on a coast and a
sea window, medians of ``--reps``, and a hash of the base mesh (compare it across versions: the same
collapses give the same hash).

    python benchmarks/tin_flat.py [--reps 3]

Writes ``benchmarks/results/tin_flat.json`` and ``tin_flat.md``.
"""

from __future__ import annotations

import argparse
import hashlib
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import SHARED, md_table, write_results  # noqa: E402

DEM = SHARED / "dem"
CASES = [
    ("Kattegat (srtm3_N57E011)", "srtm3_N57E011.tif"),
    ("Tarragona coast (srtm3_N41E001)", "srtm3_N41E001.tif"),
]
WINDOWS = {"srtm3_N57E011.tif": (300, 300), "srtm3_N41E001.tif": (600, 600)}


def main() -> None:
    import rasterio

    import terralod
    from terralod.tin import DetailIncrementModel

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reps", type=int, default=3)
    args = ap.parse_args()
    if not DEM.exists():
        print(f"skipping: {DEM} not present")
        return
    rows, payload = [], {"reps": args.reps, "results": []}
    for label, name in CASES:
        r0, c0 = WINDOWS[name]
        with rasterio.open(DEM / name) as ds:
            z = ds.read(1).astype(np.float32)[r0 : r0 + 513, c0 : c0 + 513]
        hf = terralod.Heightfield.from_array(z, 90.0, origin_m=(500000.0, 5200000.0))
        secs = []
        for _ in range(args.reps):
            t = time.perf_counter()
            m = DetailIncrementModel.from_heightfield(hf, sub_blocks=4)
            secs.append(time.perf_counter() - t)
        digest = hashlib.sha256(m._base_tris.tobytes() + m._base_alive.tobytes()).hexdigest()[:10]
        sea = float((z == 0).mean())
        s = statistics.median(secs)
        payload["results"].append({"case": label, "sea_fraction": sea, "s": s, "base_sha256": digest})
        rows.append([label, f"{sea:.0%}", z.size, round(s, 2), f"{z.size / s / 1e3:,.1f}", digest])
        print(rows[-1], flush=True)
    md = (f"# Detail-increment TIN build on flat ground (513² SRTM windows, medians of {args.reps})\n\n"
          + md_table(["window", "sea (0 m)", "points", "build s", "k points/s", "base mesh sha256"], rows))  # fmt: skip
    write_results("tin_flat", payload, md)


if __name__ == "__main__":
    main()
