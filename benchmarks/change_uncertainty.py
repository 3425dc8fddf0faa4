"""Does the ± of a volume hold where the change is? (issue 54, deliverable 2)

Planted pairs on the seven terrain kinds of ../shared/data (flat, coast, rolling, alpine, canyon, volcanic
island, 1 m LiDAR), crops of at most 256² cells. Each draw plants a cosine mound or pit of known volume
at a random place (on flat or steep ground alike) and adds survey noise whose σ grows with slope
(σ = σ0 · (1 + slope / 15°)), part of it white and part spatially correlated (a Gaussian-smoothed field
of a random width of 2-8 cells, 35 % of the variance). The volume is summed over a disc around the plant
(1.5 radii, a zone) and its 95 % interval taken from

- **model**: terralod's error model (:mod:`terralod.change.uncertainty`: σ by slope and curvature ×
  a sum of spherical ranges, fitted on the stable ground, i.e. everything outside the disc);
- **single σ**: the old model (one NMAD σ, one fitted range: ``--sigma-m`` and ``--corr-range-m``'s
  model, :func:`terralod.change.volumes.estimate_uncertainty` without the terrain).

Counted: draws whose planted volume lies inside the interval (per terrain, pooled), the mean half-width
and the 95th percentile of the absolute volume errors. The issue's bar: ≥ 651 of 700 pooled, ≥ 88 of 100
per terrain, mean half-width ≤ 1.5 × that 95th percentile.

Run: ``python benchmarks/change_uncertainty.py [--draws 100]``; writes
``benchmarks/results/change_uncertainty.{json,md}``.
"""

from __future__ import annotations

import argparse
import time
import warnings

import numpy as np
from scipy import ndimage

from change_plants import bowl, crop
from terralod.change.uncertainty import terrain_attributes
from terralod.change.volumes import budget, estimate_uncertainty

from _common import md_table, write_results

#: kind: (file, row, col, size, σ0 of the noise on flat ground in metres)
TERRAINS = {
    "flat": ("srtm3_N52E008.tif", 300, 300, 256, 1.0),
    "coast": ("srtm1_crop256_coastal_flat_nodata.tif", 0, 0, 256, 1.0),
    "rolling": ("srtm1_crop256_rolling.tif", 0, 0, 256, 1.0),
    "alpine": ("srtm1_crop256_alpine.tif", 0, 0, 256, 1.0),
    "canyon": ("srtm1_crop256_canyon.tif", 0, 0, 256, 1.0),
    "volcanic_island": ("kilauea_hawaii_30m_utm5.tif", 250, 300, 256, 1.0),
    "lidar_1m": ("lidar_1m_prairie_depressions_utm15.tif", 0, 0, 256, 0.1),
}
CONF = 0.95


def draw(hf, slope, rng: np.random.Generator, sigma0_m: float) -> dict:  # noqa: ANN001
    """One planted pair: the DoD, the zone, the planted volume."""
    h, w = hf.shape
    a = float(np.prod(hf.spacing_m))
    radius = float(rng.uniform(8, 16))
    zr = 1.5 * radius
    far = ndimage.distance_transform_edt(np.pad(hf.valid, 1))[1:-1, 1:-1]
    cand = np.argwhere(far > radius + 1)
    r, c = cand[rng.integers(len(cand))]
    height = float(rng.uniform(3, 10)) * sigma0_m * (1 if rng.random() < 0.5 else -1)
    plant = height * bowl(hf.shape, r, c, radius)
    rr, cc = np.indices(hf.shape)
    zone = (np.hypot(rr - r, cc - c) <= zr) & hf.valid
    sig = sigma0_m * (1.0 + slope / 15.0)
    width = float(rng.uniform(2, 8))
    corr = ndimage.gaussian_filter(rng.normal(size=(h, w)), width, mode="wrap")
    corr /= corr.std()
    noise = sig * (np.sqrt(0.65) * rng.normal(size=(h, w)) + np.sqrt(0.35) * corr)
    dod = np.where(hf.valid, plant + noise, np.nan)
    stable = hf.valid & ~ndimage.binary_dilation(zone, iterations=3)
    return {"dod": dod, "zone": zone, "stable": stable, "planted_m3": float(plant[zone].sum() * a), "a": a}


def run_terrain(kind: str, draws: int, seed: int) -> dict:
    name, r0, c0, n, sigma0 = TERRAINS[kind]
    hf = crop(name, r0, c0, n)
    slope, _c = terrain_attributes(hf.elevation_m, hf.valid, hf.spacing_m)
    rng = np.random.default_rng(seed)
    rows = []
    t0 = time.perf_counter()
    for _ in range(draws):
        d = draw(hf, slope, rng, sigma0)
        out = {"planted_m3": d["planted_m3"]}
        for key, terrain in (("single", False), ("model", True)):
            kw = {"z_before_m": hf.elevation_m, "valid_before": hf.valid} if terrain else {}
            unc = estimate_uncertainty(d["dod"], d["stable"], d["a"], hf.spacing_m, confidence=CONF, **kw)
            sg = unc.sigma_grid(hf.elevation_m, hf.valid, hf.spacing_m) if unc.model is not None else None
            b = budget(d["dod"], unc, d["zone"], sg)
            out[key] = {"net_m3": b["net_m3"], "pm_m3": b["net_uncertainty_m3"],
                        "fitted": unc.model is not None}  # fmt: skip
        rows.append(out)
    return {"kind": kind, "file": name, "crop": [r0, c0, n], "sigma0_m": sigma0, "draws": rows,
            "seconds": time.perf_counter() - t0, "spacing_m": list(hf.spacing_m),
            "slope_p50_p95_deg": [float(np.percentile(slope[hf.valid], q)) for q in (50, 95)]}  # fmt: skip


def score(rows: list[dict], key: str) -> dict:
    err = np.array([abs(r[key]["net_m3"] - r["planted_m3"]) for r in rows])
    pm = np.array([r[key]["pm_m3"] for r in rows])
    p95 = float(np.percentile(err, 95))
    return {"inside": int((err <= pm).sum()), "draws": len(rows), "mean_half_width_m3": float(pm.mean()),
            "p95_abs_error_m3": p95, "ratio": float(pm.mean() / p95) if p95 > 0 else float("inf"),
            "fitted": int(sum(r[key]["fitted"] for r in rows))}  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--draws", type=int, default=100)
    ap.add_argument("--seed", type=int, default=54)
    args = ap.parse_args()
    warnings.filterwarnings("ignore")
    per = []
    for i, kind in enumerate(TERRAINS):
        res = run_terrain(kind, args.draws, args.seed + i)
        res["model"], res["single"] = score(res["draws"], "model"), score(res["draws"], "single")
        per.append(res)
        m, s = res["model"], res["single"]
        print(f"{kind}: model {m['inside']}/{m['draws']} (ratio {m['ratio']:.2f}), single σ {s['inside']}/{s['draws']}"
              f" (ratio {s['ratio']:.2f}), {res['seconds']:.0f} s", flush=True)  # fmt: skip
    pooled = {k: score([r for t in per for r in t["draws"]], k) for k in ("model", "single")}
    need_pool = int(np.ceil(0.93 * len(per) * args.draws))
    need_each = int(np.ceil(0.88 * args.draws))
    ok = (pooled["model"]["inside"] >= need_pool and all(t["model"]["inside"] >= need_each for t in per)
          and all(t["model"]["ratio"] <= 1.5 for t in per) and pooled["model"]["ratio"] <= 1.5)  # fmt: skip
    headers = ["terrain", "slope p50/p95 (°)", "model inside", "model mean ±", "P95 |error|", "ratio",
               "single-σ inside", "single-σ mean ±", "ratio (single)", "s"]  # fmt: skip
    table = []
    for t in per:
        m, s = t["model"], t["single"]
        table.append([t["kind"], "{:.0f} / {:.0f}".format(*t["slope_p50_p95_deg"]), f"{m['inside']}/{m['draws']}",
                      m["mean_half_width_m3"], m["p95_abs_error_m3"], m["ratio"], f"{s['inside']}/{s['draws']}",
                      s["mean_half_width_m3"], s["ratio"], round(t["seconds"])])  # fmt: skip
    pm, ps = pooled["model"], pooled["single"]
    table.append(["**pooled**", "", f"{pm['inside']}/{pm['draws']}", pm["mean_half_width_m3"], pm["p95_abs_error_m3"],
                  pm["ratio"], f"{ps['inside']}/{ps['draws']}", ps["mean_half_width_m3"], ps["ratio"], ""])  # fmt: skip
    verdict = (f"Bar (issue 54): ≥ {need_pool} of {len(per) * args.draws} pooled, ≥ {need_each} of {args.draws} per "
               f"terrain, mean half-width ≤ 1.5 × P95 |error|: **{'met' if ok else 'not met'}**.")  # fmt: skip
    md = __doc__.split("\n\n")[0] + "\n\n" + md_table(headers, table) + "\n\n" + verdict + "\n"
    for t in per:
        t.pop("draws")
    write_results("change_uncertainty", {"terrains": per, "pooled": pooled, "bar_met": ok,
                                         "draws_per_terrain": args.draws}, md)  # fmt: skip
    print(md)


if __name__ == "__main__":
    main()
