"""Fractal detail benchmark (paper 001): tile generation time, amplify throughput, the diagonal rules, and
the statistics of the generated detail.

Run: ``python benchmarks/fractal.py`` (writes benchmarks/results/fractal.{json,md}). Timings are wall-clock
medians on this machine after a warm-up call (numba compiled and cached); they are not test assertions.

- Tiles: 65 x 65-vertex tiles of Puget Sound 1k (160 m) at 1, 2, 3 fractal levels below the finest DEM
  level: the window of refined heights alone, and the whole tile (window + the next level's window for
  its measured error + diagonals + world vertices).
- Amplify: x4 of the 1025 x 1025 DEM in memory (``FractalDetail.amplify``) and to a GeoTIFF
  (``amplify_command``, strip-streamed, deflate).
- Diagonals: the paper's "join the two lowest vertices" rule against the diagonal of smaller error and a
  fixed diagonal, measured against the generated surface 1 and 2 levels finer than the tile.
- Statistics: variogram slope at lags 1..8 finest samples of detail on a flat DEM (2 x 2, 10 levels,
  4 seeds) for the kriging and the classic mean-of-4 stencil, against 2H.
"""

from __future__ import annotations

import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from terralod.fractal import FractalDetail, amplify_command, choose_diagonals  # noqa: E402
from terralod.heightfield import Heightfield  # noqa: E402
from terralod.kernels import noise  # noqa: E402
from terralod.tiles import TilePyramid  # noqa: E402

from _common import md_table, puget_sound_1k, write_results  # noqa: E402

TILE = 65
SEED = 1


def _median_time(fn, repeat: int) -> float:
    ts = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts)


def _codes(top: int, extra: int, n: int, rng: np.random.Generator) -> list[tuple[int, int, int]]:
    """n random tile codes at level top + extra that lie inside a 1025² DEM (all tiles full)."""
    side = 16 << extra  # tiles per side at this level for 1024 cells / 64
    xs = rng.integers(0, side, n)
    ys = rng.integers(0, side, n)
    return [(top + extra, int(x), int(y)) for x, y in zip(xs, ys, strict=True)]


def bench_tiles(d: FractalDetail, top: int) -> list[dict]:
    rng = np.random.default_rng(0)
    out = []
    cells = TILE - 1
    for extra in (1, 2, 3):
        codes = _codes(top, extra, 48, rng)
        f = 1 << extra
        d.window(0, 0, TILE, TILE, f)  # warm-up
        d._make_tile(codes[0], TILE, "error")

        def windows(codes=codes, f=f):
            for _, x, y in codes:
                d.window(y * cells, x * cells, TILE, TILE, f)

        def tiles(codes=codes):
            for c in codes:
                d._make_tile(c, TILE, "error")  # bypass the LRU: generation cost

        tw = _median_time(windows, 3) / len(codes)
        tt = _median_time(tiles, 3) / len(codes)
        out.append(
            {
                "extra_levels": extra,
                "spacing_m": 160.0 / f,
                "window_ms": tw * 1e3,
                "tile_ms": tt * 1e3,
                "window_samples_per_s": TILE * TILE / tw,
            }
        )
    return out


def bench_amplify(hf: Heightfield) -> dict:
    d = FractalDetail(hf, seed=SEED)
    d.window(0, 0, 8, 8, 4)
    t_mem = _median_time(lambda: d.amplify(4), 3)
    nr, nc = d.amplified_shape(4)
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        summary = amplify_command(hf, Path(tmp) / "fine.tif", factor=4, seed=SEED)
        t_tif = time.perf_counter() - t0
    t_init = _median_time(lambda: FractalDetail(hf, seed=SEED), 3)
    return {
        "shape_in": list(hf.shape),
        "shape_out": [nr, nc],
        "estimate_s": t_init,
        "amplify_s": t_mem,
        "amplify_samples_per_s": nr * nc / t_mem,
        "geotiff_s": t_tif,
        "geotiff_samples_per_s": nr * nc / t_tif,
        "geotiff_bytes": summary["bytes"],
        "hurst": {k: float(v) for k, v in summary["hurst"].items()},
        "sigma_m": {k: float(v) for k, v in summary["sigma_m"].items()},
    }


def bench_diagonals(d: FractalDetail, top: int) -> list[dict]:
    rng = np.random.default_rng(1)
    cells = TILE - 1
    out = []
    for extra in (0, 1, 2):
        f = 1 << extra
        for ref_levels in (1, 2):
            sub = 1 << ref_levels
            acc = {r: {"max": [], "ss": 0.0, "n": 0} for r in ("lowest", "error", "fixed")}
            agree = 0
            quads = 0
            for _, x, y in _codes(top, extra, 24, rng):
                r0, c0 = y * cells, x * cells
                zg = d.window(r0, c0, TILE, TILE, f).astype(np.float64)
                ref = d.window(r0 * sub, c0 * sub, cells * sub + 1, cells * sub + 1, f * sub)
                picks = {}
                for rule in acc:
                    diag1, emax, ess, _, _ = choose_diagonals(zg, ref, sub, rule)
                    picks[rule] = diag1
                    acc[rule]["max"].append(float(emax.max()))
                    acc[rule]["ss"] += float(ess.sum())
                    acc[rule]["n"] += ess.size * (sub + 1) ** 2
                agree += int((picks["lowest"] == picks["error"]).sum())
                quads += picks["lowest"].size
            for rule, a in acc.items():
                out.append(
                    {
                        "extra_levels": extra,
                        "reference": f"+{ref_levels} level{'s' if ref_levels > 1 else ''}",
                        "rule": rule,
                        "mean_tile_max_error_m": float(np.mean(a["max"])),
                        "rms_error_m": float(np.sqrt(a["ss"] / a["n"])),
                        "same_diagonal_as_error_rule": agree / quads if rule == "lowest" else None,
                    }
                )
    return out


def bench_statistics() -> list[dict]:
    flat = Heightfield.from_array(np.zeros((2, 2), np.float32), 1.0)
    lags = np.arange(1, 9)
    out = []
    for hurst in (0.3, 0.5, 0.8):
        row = {"hurst": hurst, "target_slope": 2 * hurst}
        for stencil in ("kriging", "classic"):
            slopes = []
            for seed in range(4):
                z = FractalDetail(flat, hurst=hurst, sigma_m=1.0, seed=seed, stencil=stencil).amplify(1024)
                g = noise.axis_variogram(z.elevation_m.astype(np.float64), 8)
                slopes.append(float(np.polyfit(np.log(lags), np.log(g), 1)[0]))
            row[f"{stencil}_slope"] = float(np.mean(slopes))
        out.append(row)
    return out


def _spectral_fbm(n: int, hurst: float, seed: int, over: int = 4) -> np.ndarray:
    """fBm by spectral synthesis on an ``over``-times finer grid, decimated; sigma = 1 at one sample."""
    rng = np.random.default_rng(seed)
    m = n * over
    f = np.sqrt(np.fft.rfftfreq(m)[None, :] ** 2 + np.fft.fftfreq(m)[:, None] ** 2)
    f[0, 0] = 1.0
    amp = f ** (-(hurst + 1.0))
    amp[0, 0] = 0.0
    z = np.fft.irfft2(amp * (rng.normal(size=amp.shape) + 1j * rng.normal(size=amp.shape)), s=(m, m))
    z = z[::over, ::over]
    return z / np.sqrt(noise.axis_variogram(z, 1)[0])


def bench_continuation() -> list[dict]:
    """D(h) / (sigma^2 h^2H) of a true-fBm DEM (128², sigma 1) refined x16, at the generated lags."""
    lags = np.array([1, 2, 4, 8])
    out = []
    for hurst in (0.3, 0.5, 0.8):
        for stencil in ("kriging", "classic"):
            ratios = []
            for seed in (11, 12, 13):
                hf = Heightfield.from_array(_spectral_fbm(128, hurst, seed).astype(np.float32), 1.0)
                d = FractalDetail(hf, hurst=hurst, sigma_m=1.0, seed=5, stencil=stencil)
                g = noise.axis_variogram(d.amplify(16).elevation_m.astype(np.float64), 8)[lags - 1]
                ratios.append(g / (lags / 16.0) ** (2 * hurst))
            out.append({"hurst": hurst, "stencil": stencil, "ratio_at_lag": np.mean(ratios, axis=0).tolist()})
    return out


def main() -> None:
    hf = puget_sound_1k()
    if hf is None:
        print("benchmarks/fractal.py: ../shared/data/dem/puget_sound_1k_u16.png not found; nothing measured")
        return
    top = TilePyramid(hf.width, hf.height, TILE).max_level
    d = FractalDetail(hf, seed=SEED)
    tiles = bench_tiles(d, top)
    amp = bench_amplify(hf)
    diags = bench_diagonals(d, top)
    stats = bench_statistics()
    cont = bench_continuation()

    md = ["# Fractal detail (paper 001)\n", "Puget Sound 1025² at 160 m, seed 1, estimated H and sigma maps "]
    md.append(
        f"(H {amp['hurst']['min']:.2f}..{amp['hurst']['max']:.2f}, mean {amp['hurst']['mean']:.2f}; "
        f"sigma {amp['sigma_m']['min']:.1f}..{amp['sigma_m']['max']:.1f} m). Wall-clock medians, 2 shared cores.\n\n"
    )
    md.append("## Tile generation (65 x 65 vertices)\n\n")
    md.append(
        md_table(
            ["fractal levels", "vertex spacing (m)", "window (ms)", "window (M samples/s)", "tile mesh (ms)"],
            [
                [
                    t["extra_levels"],
                    t["spacing_m"],
                    t["window_ms"],
                    t["window_samples_per_s"] / 1e6,
                    t["tile_ms"],
                ]
                for t in tiles
            ],
        )
    )
    md.append(
        "\n'tile mesh' = refined heights + the next level's heights (measured error) + diagonals + world "
        "vertices, i.e. one `fractal_tile` call without the LRU.\n\n## Amplify x4 (1025² -> 4097²)\n\n"
    )
    md.append(
        md_table(
            ["step", "seconds", "M output samples/s"],
            [
                ["estimate H, sigma maps", amp["estimate_s"], "-"],
                ["amplify (in memory)", amp["amplify_s"], amp["amplify_samples_per_s"] / 1e6],
                ["amplify_command (GeoTIFF, deflate)", amp["geotiff_s"], amp["geotiff_samples_per_s"] / 1e6],
            ],
        )
    )
    md.append("\n## Diagonal rule (§3.2) against the generated finer surface\n\n")
    md.append(
        md_table(
            [
                "fractal levels",
                "reference",
                "rule",
                "mean tile max error (m)",
                "RMS error (m)",
                "same as error rule",
            ],
            [
                [
                    r["extra_levels"],
                    r["reference"],
                    r["rule"],
                    r["mean_tile_max_error_m"],
                    r["rms_error_m"],
                    "-"
                    if r["same_diagonal_as_error_rule"] is None
                    else f"{100 * r['same_diagonal_as_error_rule']:.1f} %",
                ]
                for r in diags
            ],
        )
    )
    md.append(
        "\n24 random tiles per row; 'fractal levels' 0 is the DEM's own finest tile. 'error' picks per quad "
        "the diagonal of smaller max error against that row's reference surface.\n\n"
        "## Variogram slope of detail on a flat DEM (lags 1..8 finest samples, 10 levels, 4 seeds)\n\n"
    )
    md.append(
        md_table(
            ["H", "target 2H", "kriging 4x4 stencil", "classic mean of 4"],
            [[s["hurst"], s["target_slope"], s["kriging_slope"], s["classic_slope"]] for s in stats],
        )
    )
    md.append(
        "\n## Refining a true fBm DEM continues its variogram (x16, 3 seeds)\n\n"
        "D(h) / (sigma² h^2H) of the refined grid at lags h of 1/16 .. 1/2 DEM sample (1 = exact).\n\n"
    )
    md.append(
        md_table(
            ["H", "stencil", "h = 1/16", "1/8", "1/4", "1/2"],
            [[c["hurst"], c["stencil"], *c["ratio_at_lag"]] for c in cont],
        )
    )
    write_results(
        "fractal",
        {
            "tile_size": TILE,
            "seed": SEED,
            "tiles": tiles,
            "amplify_x4": amp,
            "diagonals": diags,
            "statistics": stats,
            "continuation": cont,
        },
        "".join(md),
    )


if __name__ == "__main__":
    main()
