"""Kernel speed of terralod.kernels.error.tile_error on 65x65-vertex regular-grid tiles (chunked-style).

samples/s = covered samples / CPU time (thread_time, robust to other load on the machine) of one tile_error call (single thread, warm cache).
"""

import json
import sys
import time
from pathlib import Path

import numpy as np
import PIL.Image

sys.path.insert(0, str(Path(__file__).resolve().parent))
from terralod.kernels.error import tile_error  # noqa: E402

from _common import SHARED, fractal_terrain, md_table, write_results  # noqa: E402


def grid_tile(z, r0, c0, s, m=65, diag="nw"):
    rr, cc = np.mgrid[0:m, 0:m] * s
    rr += r0
    cc += c0
    zq = z[rr, cc].ravel().astype(np.float64)
    step = max(float(np.ptp(zq)) / 65534.0, 1e-6)  # the store's 16-bit vertical lattice, as the builder
    zq = np.rint(zq / step) * step
    verts = np.stack([(cc - c0).ravel() * DX, (rr - r0).ravel() * DY, zq], 1)
    idx = np.arange(m * m).reshape(m, m)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    tris = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)]).astype(np.int64)
    span = (m - 1) * s
    win = np.ascontiguousarray(z[r0 : r0 + span + 1, c0 : c0 + span + 1])
    return verts, tris, win


def bench(name, z, strides, reps=3):
    out = []
    ok_full = np.ones(z.shape, bool)
    for s in strides:
        span = 64 * s
        if span + 1 > min(z.shape):
            continue
        starts = [
            (r, c)
            for r in range(0, z.shape[0] - span, max(span, (z.shape[0] - span) // 3 or 1))
            for c in range(0, z.shape[1] - span, max(span, (z.shape[1] - span) // 3 or 1))
        ][:9]
        tot_n = 0
        tot_t = 0.0
        res = None
        for r0, c0 in starts:
            verts, tris, win = grid_tile(z, r0, c0, s)
            ok = ok_full[: win.shape[0], : win.shape[1]]
            best = 1e9
            for _ in range(reps):
                t = time.thread_time()
                res = tile_error(verts, tris, win, ok, DX, DY)
                best = min(best, time.thread_time() - t)
            tot_n += res[2]
            tot_t += best
        row = dict(
            terrain=name,
            stride=s,
            tiles=len(starts),
            samples_per_tile=tot_n // len(starts),
            ms_per_tile=1e3 * tot_t / len(starts),
            msamples_per_s=tot_n / tot_t / 1e6,
            last_max_v=res[0],
            last_hd=res[3],
        )
        print(json.dumps(row))
        out.append(row)
    return out


# warm up / compile
DX = DY = 160.0
z0 = np.zeros((65, 65), np.float32)
v, t, w = grid_tile(z0, 0, 0, 1)
tile_error(v, t, w, np.ones(w.shape, bool), 1.0, 1.0)
rows = []
ps = SHARED / "dem" / "puget_sound_1k_u16.png"
if ps.exists():
    puget = np.asarray(PIL.Image.open(ps)).astype(np.float32) * 0.1
    rows += bench("puget_1k_160m", puget, [1, 2, 4, 8, 16], reps=5)
DX = DY = 30.0
frac = fractal_terrain(4097, 4097, seed=1, relief_m=2500.0)
rows += bench("fbm4097_30m", frac, [1, 4, 16, 64], reps=2)
md = "## Error kernel speed (65x65-vertex grid tiles, one thread, CPU time)\n\n" + md_table(
    ["terrain", "stride", "samples/tile", "ms/tile", "M samples/s"],
    [
        [r["terrain"], r["stride"], int(r["samples_per_tile"]), r["ms_per_tile"], r["msamples_per_s"]]
        for r in rows
    ],
)
write_results("error_kernel", {"rows": rows}, md)
