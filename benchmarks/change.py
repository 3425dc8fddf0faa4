"""Terrain change: St Helens volumes per epoch, and co-registration accuracy / time / memory of xdem's
Nuth & Kääb against terralod's own, side by side on known shifts of real DEMs.

1. **St Helens series** (``../shared/data/change/st_helens_crater_timeseries_2000-2007_10m.npz``): the
   volume of each of the 27 epochs against the 2000 base (gain, loss, net ± 95 %, area beyond the LoD,
   largest rise), with σ = ``--sigma-m`` (default 1 m, the value ``terralod change`` assumes: the epochs
   are merged over the base, so their stable ground differs by exactly 0 and σ cannot be measured).
2. **Co-registration**: crops of real DEMs (Big Tujunga SRTM 30 m, Kilauea 30 m, the Mt Rainier SRTM 1"
   crop reprojected to UTM by the reader, 1 m prairie LiDAR) are shifted by known amounts and given a
   vertical offset, 0.3 m of survey noise and a cone of real change (so "stable ground" has to be found):
   ``offset`` moves the grid (AFTER = BEFORE's samples on a translated grid: an exact shift, unequal
   origins), ``resampled`` shifts the surface with a cubic spline on the same grid, ``coarser`` also puts
   AFTER on a 1.5x coarser grid, ``utm-zone`` reprojects AFTER into the neighbouring UTM zone. Both
   estimators get the same :class:`~terralod.change.difference.AlignedPair` (xdem needs both DEMs on one
   grid: the pair puts them there). Error = |fitted − true| horizontal shift in pixels, and dz in metres;
   time = median of ``--repeat`` fits; memory = tracemalloc peak of one fit (numpy allocations included).

3. **Planted real pairs, the whole chain against xdem** (issue 43): the plants of
   ``benchmarks/change_plants.py`` (a landslide's scarp and deposit, a lake whose level changed, AFTER
   shifted sub-cell or by several cells, a vertical bias, a 1.5x coarser grid, 1-1.5 m of noise) on each
   kind of terrain. terralod's chain (``measure_change``: stable ground, fit, volumes) with either estimator,
   against xdem's ``NuthKaab`` fitted alone on AFTER resampled onto BEFORE's grid, given the chain's stable
   mask as ``inlier_mask``, and given none. Errors: horizontal shift (cells), vertical bias (m), zone
   volumes (% of the planted volume, the worst zone), σ / NMAD of the true error; time of each.

Run: ``python benchmarks/change.py [--quick]``; writes ``benchmarks/results/change.{json,md}``.
"""

from __future__ import annotations

import argparse
import math
import statistics
import time
import tracemalloc
import warnings

import numpy as np
from affine import Affine

from terralod import read_heightfield
from terralod.change.coregister import coregister
from terralod.change.difference import align
from terralod.change.volumes import ASSUMED_RANGE_M, series_volumes
from terralod.heightfield import Heightfield

from _common import SHARED, md_table, write_results

SHIFTS_PX = [(0.25, -0.4), (0.7, 0.55), (2.3, -1.6), (-4.4, 3.7)]
DZ_M = 3.0
NOISE_M = 0.3


def helens_series(sigma_m: float) -> tuple[list[dict], float]:
    from terralod.cli.change import _read_npz_series

    p = SHARED / "change" / "st_helens_crater_timeseries_2000-2007_10m.npz"
    if not p.exists():
        return [], 0.0
    epochs, dates = _read_npz_series(str(p))
    t = time.perf_counter()
    rows = series_volumes(epochs, dates, sigma_m=sigma_m, coregistration=True)
    return rows, (time.perf_counter() - t) / max(1, len(rows) - 1)


def crops(quick: bool) -> list[tuple[str, Heightfield]]:
    items = [
        ("big_tujunga_srtm30m_utm11.tif", (180, 380), 256),
        ("kilauea_hawaii_30m_utm5.tif", (250, 300), 256),
        ("srtm1_crop256_alpine.tif", (0, 0), 256),
        ("lidar_1m_prairie_depressions_utm15.tif", (0, 0), 400),
    ]
    if quick:
        items = items[:2]
    out = []
    for name, (r0, c0), n in items:
        p = SHARED / "dem" / name
        if not p.exists():
            continue
        hf = read_heightfield(p)
        z = hf.elevation_m[r0 : r0 + n, c0 : c0 + n]
        v = hf.valid[r0 : r0 + n, c0 : c0 + n]
        out.append(
            (name, Heightfield(z, v, hf.transform * Affine.translation(c0, r0), crs=hf.crs, source=name))
        )
    return out


def make_after(before: Heightfield, shift_px, mode: str, rng) -> Heightfield:
    """BEFORE moved by ``shift_px`` (east, north), + DZ_M, + noise, + a cone of change."""
    from scipy import ndimage

    sx, sy = shift_px
    h, w = before.shape
    dx, dy = before.spacing_m
    rows, cols = np.indices(before.shape)
    r = np.hypot((rows - 0.7 * h) * dy, (cols - 0.3 * w) * dx)
    radius = 0.15 * min(h * dy, w * dx)
    bump = np.clip(0.1 * radius * (1 - r / radius), 0, None)
    z = before.elevation_m.astype(np.float64)
    if mode == "offset":
        t = before.transform * Affine.translation(sx, -sy)
    else:  # the surface moves by (sx, sy) px on the same grid: after(col) = before(col - sx)
        z = ndimage.shift(z, (-sy, sx), order=3, mode="nearest")
        t = before.transform
    z = z + DZ_M + bump + rng.normal(0, NOISE_M, z.shape)
    after = Heightfield(z.astype(np.float32), before.valid, t, crs=before.crs, source="after")
    if mode == "coarser":
        after = resample(after, 1.5)
    elif mode == "utm-zone":
        after = other_zone(after)
    return after


def resample(hf: Heightfield, factor: float) -> Heightfield:
    from rasterio.warp import Resampling, reproject

    dx, dy = hf.spacing_m
    w, h = int(hf.width / factor), int(hf.height / factor)
    t = Affine(dx * factor, 0, hf.transform.c, 0, -dy * factor, hf.transform.f)
    out = np.zeros((h, w), np.float32)
    reproject(hf.elevation_m, out, src_transform=hf.transform, src_crs=hf.crs, dst_transform=t, dst_crs=hf.crs,
              resampling=Resampling.cubic)  # fmt: skip
    return Heightfield(out, np.ones(out.shape, bool), t, crs=hf.crs, source="after (1.5x coarser)")


def other_zone(hf: Heightfield) -> Heightfield:
    from pyproj import CRS
    from rasterio.warp import Resampling, calculate_default_transform, reproject

    zone = CRS.from_user_input(hf.crs).utm_zone or "10N"
    num, hemi = int(zone[:-1]), zone[-1]
    dst = f"EPSG:{(32600 if hemi == 'N' else 32700) + (num % 60) + 1}"
    t, w, h = calculate_default_transform(hf.crs, dst, hf.width, hf.height, *hf.bounds_m,
                                          resolution=hf.spacing_m[0])  # fmt: skip
    out = np.full((h, w), np.nan, np.float32)
    reproject(hf.elevation_m, out, src_transform=hf.transform, src_crs=hf.crs, dst_transform=t, dst_crs=dst,
              dst_nodata=np.nan, resampling=Resampling.cubic)  # fmt: skip
    ok = np.isfinite(out)
    return Heightfield(np.where(ok, out, 0), ok, t, crs=dst, source=f"after ({dst})")


def fit(pair, method: str, repeat: int) -> dict:
    """The estimator alone on a fixed stable mask (``_fit_xdem`` / ``_fit_terralod``: wall and CPU time,
    tracemalloc peak), and the whole :func:`coregister` (stable ground found, fitted, NMAD after)."""
    from terralod.change import coregister as cr

    fn = cr._fit_xdem if method == "xdem" else cr._fit_terralod
    mask = cr.stable_ground(cr.dem_of_difference(pair))
    wall, cpu = [], []
    for _ in range(repeat):
        t, c = time.perf_counter(), time.process_time()
        shift, _ = fn(pair, mask, 0)
        wall.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
    tracemalloc.start()
    fn(pair, mask, 0)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    t = time.perf_counter()
    co = coregister(pair, method=method)
    return {"shift": shift, "fit_s": statistics.median(wall), "fit_cpu_s": statistics.median(cpu),
            "peak_mib": peak / 2**20, "coregister_s": time.perf_counter() - t, "full_shift": co.shift_m,
            "nmad_after_m": co.nmad_after_m}  # fmt: skip


def coreg_bench(quick: bool, repeat: int) -> list[dict]:
    rng = np.random.default_rng(7)
    modes = ["offset", "resampled", "coarser", "utm-zone"]
    shifts = SHIFTS_PX[1:3] if quick else SHIFTS_PX
    rows = []
    for name, before in crops(quick):
        px = before.spacing_m[0]
        for mode in modes:
            for sh in shifts:
                after = make_after(before, sh, mode, rng)
                pair = align(before, after)
                for method in ("xdem", "terralod"):
                    f = fit(pair, method, repeat)
                    shift = f["shift"]
                    err = math.hypot(shift[0] / px + sh[0], shift[1] / px + sh[1])
                    full = f["full_shift"]
                    rows.append({
                        "dem": name, "mode": mode, "shift_px": list(sh), "method": method,
                        "fitted_px": [shift[0] / px, shift[1] / px], "dz_m": shift[2],
                        "error_px": err, "dz_error_m": abs(shift[2] + DZ_M), "seconds": f["fit_s"],
                        "cpu_seconds": f["fit_cpu_s"], "peak_mib": f["peak_mib"],
                        "coregister_seconds": f["coregister_s"], "nmad_after_m": f["nmad_after_m"],
                        "coregister_error_px": math.hypot(full[0] / px + sh[0], full[1] / px + sh[1]),
                        "cells": before.width * before.height,
                    })  # fmt: skip
                    print(f"{name:40s} {mode:9s} {sh} {method:8s} err {err:.4f} px dz {shift[2]:+.3f} "
                          f"{f['fit_s'] * 1e3:.0f} ms (cpu {f['fit_cpu_s'] * 1e3:.0f}) {f['peak_mib']:.0f} MiB")  # fmt: skip
    return rows


def pairs_bench(quick: bool) -> list[dict]:
    """Section 3 of the module docstring."""

    import xdem
    from rasterio.crs import CRS

    import change_plants as plants
    from terralod.change.coregister import nmad
    from terralod.change.difference import dem_of_difference
    from terralod.change.volumes import budget, measure_change

    terrains = [*plants.TERRAINS, "flattest_kattegat"]
    cases = [((0.45, -0.3), 1.0), ((2.6, -3.1), 1.0), ((0.7, 0.4), 1.5), ((-1.8, 2.2), 1.5)]
    if quick:
        cases = cases[:2]
    rows = []
    for terrain in terrains:
        f, r0, c0, n, _ = plants.TERRAINS.get(terrain, plants.FLATTEST)
        for k, (shift_px, factor) in enumerate(cases):
            seed = 100 + k
            before = plants.crop(f, r0, c0, n)
            rng = np.random.default_rng(seed)
            lake_change = np.zeros(before.shape)
            if not terrain.startswith(("mountains", "geographic", "flattest")):
                zb, lake_change = plants.lake(before, rng, 24)
                before = Heightfield(zb, before.valid, before.transform, crs=before.crs, source=f)
            scarp, dep = plants.landslide(before, rng, float(rng.uniform(25, 40)), 14, avoid=lake_change != 0)
            change = scarp + dep + lake_change
            bias = float(rng.uniform(-3, 3))
            after, want = plants.make_after(
                before, before.elevation_m + change, shift_px, bias, 1.2, factor, seed
            )
            px = before.spacing_m[0]
            zones = [scarp < -0.01, dep > 0.01] + ([lake_change != 0] if lake_change.any() else [])

            def errors(pair, dod, unc, shift, stable, zones=zones, change=change, want=want, px=px):
                from scipy import ndimage

                a = pair.cell_area_m2
                vol = []
                for z in zones:
                    z = ndimage.binary_dilation(z, iterations=3)
                    truth = float(change[z & np.isfinite(dod)].sum() * a)
                    vol.append(abs(budget(dod, unc, z)["net_m3"] - truth) / abs(truth) * 100)
                true_err = dem_of_difference(pair, want) - change
                return {"shift_err_cells": math.hypot(shift[0] - want[0], shift[1] - want[1]) / px,
                        "bias_err_m": abs(shift[2] - want[2]), "volume_err_pct": max(vol),
                        "sigma_true_m": nmad(true_err[stable])}  # fmt: skip

            for method in ("xdem", "terralod"):
                t = time.perf_counter()
                r = measure_change(before, after, method=method)
                dt = time.perf_counter() - t
                e = errors(r.pair, r.dod, r.uncertainty, r.summary["shift_m"], r.stable)
                rows.append({"terrain": terrain, "shift_px": shift_px, "factor": factor, "estimator":
                             f"terralod chain ({method})", "mode": r.summary["coregistration"]["mode"], "seconds": dt, **e,
                             "sigma_ratio": r.summary["sigma_m"] / e["sigma_true_m"]})  # fmt: skip
                chain = r
            # xdem alone, on AFTER resampled onto BEFORE's grid, with the chain's stable mask and with none
            ref = np.where(before.valid, before.elevation_m, np.nan).astype(np.float32)
            tba, _ = chain.pair.after_on_before()
            for label, mask in (("xdem NuthKaab, same stable mask", chain.stable),
                                ("xdem NuthKaab, no mask", np.ones(before.shape, bool))):  # fmt: skip
                t = time.perf_counter()
                try:
                    nk = xdem.coreg.NuthKaab()
                    nk.fit(ref, tba.astype(np.float32), inlier_mask=mask, transform=before.transform,
                           crs=CRS.from_user_input(before.crs), random_state=0)  # fmt: skip
                    o = nk.meta["outputs"]["affine"]
                    shift = (float(o["shift_x"]), float(o["shift_y"]), float(o["shift_z"]))
                    fail = ""
                except Exception as exc:  # noqa: BLE001 - a failure is a result here
                    shift, fail = (float("nan"),) * 3, str(exc).splitlines()[0][:80]
                dt = time.perf_counter() - t
                if fail:
                    rows.append({"terrain": terrain, "shift_px": shift_px, "factor": factor, "estimator": label,
                                 "mode": f"failed: {fail}", "seconds": dt})  # fmt: skip
                    continue
                dod = dem_of_difference(chain.pair, shift)
                e = errors(chain.pair, dod, chain.uncertainty, shift, chain.stable)
                rows.append({"terrain": terrain, "shift_px": shift_px, "factor": factor, "estimator": label,
                             "mode": "shift and bias", "seconds": dt, **e, "sigma_ratio": float("nan")})  # fmt: skip
            print(terrain, shift_px, factor, *(f"{x['estimator']}: {x.get('shift_err_cells', float('nan')):.3f}c "
                  f"{x.get('bias_err_m', float('nan')):.3f}m {x.get('volume_err_pct', float('nan')):.2f}%"
                  for x in rows[-4:]), flush=True)  # fmt: skip
    return rows


def pairs_table(rows: list[dict]) -> str:
    out = []
    terrains = list(dict.fromkeys(r["terrain"] for r in rows))
    estimators = list(dict.fromkeys(r["estimator"] for r in rows))
    table = []
    for t in terrains:
        for e in estimators:
            rs = [r for r in rows if r["terrain"] == t and r["estimator"] == e and "shift_err_cells" in r]
            fails = sum(
                1 for r in rows if r["terrain"] == t and r["estimator"] == e and "shift_err_cells" not in r
            )
            if not rs:
                table.append([t, e, 0, "-", "-", "-", "-", "-", f"{fails} failed"])
                continue
            modes = sorted({r["mode"] for r in rs})
            sig = [r["sigma_ratio"] for r in rs if np.isfinite(r.get("sigma_ratio", float("nan")))]
            table.append([t, e, len(rs), max(r["shift_err_cells"] for r in rs), max(r["bias_err_m"] for r in rs),
                          max(r["volume_err_pct"] for r in rs),
                          f"{min(sig):.2f}-{max(sig):.2f}" if sig else "-",
                          statistics.median(r["seconds"] for r in rs),
                          ", ".join(modes) + (f"; {fails} failed" if fails else "")])  # fmt: skip
    out.append(md_table(["terrain", "estimator", "plants", "max shift error (cells)", "max bias error (m)",
                         "max zone volume error (%)", "σ / true NMAD", "median time (s)", "fitted"], table))  # fmt: skip
    return "\n".join(out)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--sigma-m", type=float, default=1.0)
    ap.add_argument("--pairs-only", action="store_true", help="only section 3 (planted pairs vs xdem)")
    args = ap.parse_args()
    warnings.simplefilter("ignore")
    pairs = pairs_bench(args.quick)
    pairs_md = (
        "\n## Planted real pairs: terralod's chain against xdem's NuthKaab alone (issue 43)\n\n"
        "Plants as in `benchmarks/change_plants.py` (landslide scarp + deposit, a lake's level change where there "
        "is flat land, bias ±3 m, noise 1.2 m, AFTER on the same or a 1.5x coarser grid, shifts (0.45, -0.3), "
        "(2.6, -3.1), (0.7, 0.4), (-1.8, 2.2) cells). Shift error for a bias-only fit is the planted shift "
        "itself (it was not fitted, and said so). xdem alone fits AFTER resampled onto BEFORE's grid; its "
        "volumes are summed on the same grid after applying its shift. Worst case per row.\n\n"
        + pairs_table(pairs)
    )
    if args.pairs_only:
        # section 3 replaced in change.{json,md}; sections 1-2 kept as they were measured
        import json

        from _common import RESULTS

        jp, mp = RESULTS / "change.json", RESULTS / "change.md"
        if jp.is_file() and mp.is_file():
            payload = json.loads(jp.read_text())
            payload["pairs"] = pairs
            md = mp.read_text()
            head = md.split("\n## Planted real pairs")[0].rstrip("\n") + "\n"
            write_results("change", {k: v for k, v in payload.items() if k != "machine"}, head + pairs_md)
        else:
            write_results("change_pairs", {"pairs": pairs}, "# Terrain change: planted pairs\n" + pairs_md)
        return

    series, per_epoch_s = helens_series(args.sigma_m)
    co = coreg_bench(args.quick, args.repeat)

    md = ["# Terrain change benchmark (`python benchmarks/change.py`)\n"]
    if series:
        md.append(
            f"## St Helens crater, 27 epochs against 25 Sep 2000 (σ = {args.sigma_m:g} m given: the epochs "
            f"are merged over the base, so σ cannot be measured; LoD = {1.96 * args.sigma_m:.2f} m, ± at 95 %, "
            f"correlation range {ASSUMED_RANGE_M:g} m assumed); "
            f"{per_epoch_s:.2f} s per epoch\n"
        )
        md.append(md_table(
            ["date", "gain > LoD (Mm³)", "loss > LoD (Mm³)", "net (Mm³)", "± net 95 % (Mm³)", "area gain (km²)",
             "max rise (m)"],
            [[r["date"], r["gain_m3_above_lod"] / 1e6, r["loss_m3_above_lod"] / 1e6, r["net_m3"] / 1e6,
              r["net_uncertainty_m3"] / 1e6, r["area_gain_m2"] / 1e6, r["max_rise_m"]] for r in series],
        ))  # fmt: skip
    md.append(
        f"\n## Co-registration on known shifts of real DEMs (dz = {-DZ_M:+g} m to find, noise {NOISE_M} m, a cone "
        "of change, stable ground found by `stable_ground`; each estimator fitted on the same pair and mask; "
        "wall/CPU = median of the fits; peak = tracemalloc peak of one fit)\n"
    )
    summ = []
    for method in ("xdem", "terralod"):
        for mode in ("offset", "resampled", "coarser", "utm-zone"):
            rs = [r for r in co if r["method"] == method and r["mode"] == mode]
            if not rs:
                continue
            summ.append([method, mode, len(rs), statistics.median(r["error_px"] for r in rs),
                         max(r["error_px"] for r in rs), max(r["dz_error_m"] for r in rs),
                         statistics.median(r["seconds"] for r in rs) * 1e3,
                         statistics.median(r["cpu_seconds"] for r in rs) * 1e3,
                         statistics.median(r["peak_mib"] for r in rs),
                         max(r["coregister_error_px"] for r in rs)])  # fmt: skip
    md.append(md_table(["method", "AFTER made by", "cases", "median error (px)", "max error (px)",
                        "max dz error (m)", "median fit wall (ms)", "median fit CPU (ms)", "median peak (MiB)",
                        "max error, whole coregister() (px)"], summ))  # fmt: skip
    md.append("\n### Every case\n")
    md.append(md_table(
        ["DEM", "mode", "true shift (px)", "method", "fitted (px)", "error (px)", "dz (m)", "ms", "MiB"],
        [[r["dem"], r["mode"], f"{r['shift_px'][0]:+.2f}, {r['shift_px'][1]:+.2f}", r["method"],
          f"{-r['fitted_px'][0]:+.3f}, {-r['fitted_px'][1]:+.3f}", r["error_px"], r["dz_m"], r["seconds"] * 1e3,
          r["peak_mib"]] for r in co],
    ))  # fmt: skip
    md.append(pairs_md)
    write_results("change", {"st_helens_series": series, "st_helens_seconds_per_epoch": per_epoch_s,
                             "sigma_m": args.sigma_m, "coregistration": co, "summary": summ, "pairs": pairs},
                  "\n".join(md))  # fmt: skip


if __name__ == "__main__":
    main()
