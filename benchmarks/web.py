"""Web globe figures: export throughput, bytes per triangle against quantized-mesh-encoder, greedy insertion
against the regular grid at equal measured error, a loopback load test of ``terralod serve`` (1,000
concurrent tile requests), and CesiumJS load times in headless Chromium: the stock page's (the stock
section; the page ``terralod serve`` once showed, which an earlier section loaded, is the change site now,
measured by ``benchmarks/site.py``).

    python benchmarks/web.py [--runs 3] [--no-browser] [--stock-only]

The stock section (``stock_figures``): full DEMs exported as a user would (SRTM3 N41E001 straight from the
DEM, Big Tujunga through a store), bytes per triangle as written and gzip'd, declared error per zoom, and
the load time to all tiles in stock CesiumJS (benchmarks/web/stock_cesium.html) from three views.

Terrains: the bundled sample (Jacksboro fault, 416 x 440 at 74.6 m) and the 256² SRTM crop of Mt Rainier
from ../shared/data (skipped when absent). Writes benchmarks/results/web.json and web.md.
"""

from __future__ import annotations

import argparse
import gzip
import io
import json
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import ROOT, SHARED, write_results  # noqa: E402


def stores(tmp: Path) -> dict[str, Path]:
    from terralod.io.reader import read_heightfield, sample_heightfield
    from terralod.pyramid.builder import build_store

    out = {}
    p = tmp / "sample.terra"
    build_store(sample_heightfield(), p, workers=2, method="cohesion")  # as recorded in results/web.md
    out["sample (Jacksboro 416x440)"] = p
    alp = SHARED / "dem" / "srtm1_crop256_alpine.tif"
    if alp.exists():
        p = tmp / "alpine.terra"
        build_store(read_heightfield(alp), p, workers=2, method="cohesion")
        out["SRTM Mt Rainier 256x378"] = p
    return out


def export_figures(path: Path, tmp: Path, runs: int) -> dict:
    from terralod.export import export_3dtiles, export_quantized_mesh
    from terralod.terrain import open_terrain

    res: dict = {}
    for fmt, fn in (("3dtiles", export_3dtiles), ("quantized-mesh", export_quantized_mesh)):
        times, rep = [], None
        for _ in range(runs):
            with open_terrain(path) as t:
                rep = fn(t, tmp / f"out-{fmt}", overwrite=True)
            times.append(rep.seconds)
        s = statistics.median(times)
        res[fmt] = {"tiles": rep.tiles, "triangles": rep.triangles, "bytes": rep.bytes, "seconds": s,
                    "tiles_per_s": rep.tiles / s, "mb_per_s": rep.bytes / 1e6 / s}  # fmt: skip
    return res


def bytes_per_triangle(path: Path) -> dict:
    """Both formats and quantized-mesh-encoder on the same meshes (store tiles; quantized-mesh tiles)."""
    from terralod.export.quantized_mesh import QuantizedMesh, decode_tile, encode_tile, tile_rectangle
    from terralod.export.tiles3d import Tiles3D
    from terralod.terrain import open_terrain

    out: dict = {}
    with open_terrain(path) as t:
        view = Tiles3D(t)
        glb = glbz = qm_ours = qm_ours_z = qm_lib = qm_lib_z = tri = 0
        for n in view.tree:
            v, tr, _ = view.mesh(n.code)
            data = view.glb(n.code)
            glb += len(data)
            glbz += len(gzip.compress(data, 6))
            lon, lat = view.geo.lonlat(v[:, 0], v[:, 1])
            rect = (float(lon.min()), float(lat.min()), float(lon.max()), float(lat.max()))
            raw = encode_tile(lon, lat, v[:, 2], tr, rect)
            qm_ours += len(raw)
            qm_ours_z += len(gzip.compress(raw, 6))
            b = io.BytesIO()
            import quantized_mesh_encoder as qme

            qme.encode(b, np.column_stack([lon, lat, v[:, 2]]), np.asarray(tr, np.uint32), bounds=rect)
            qm_lib += len(b.getvalue())
            qm_lib_z += len(gzip.compress(b.getvalue(), 6))
            tri += len(tr)
        out["store tiles"] = {"triangles": tri, "glb_B_per_tri": glb / tri, "glb_gzip_B_per_tri": glbz / tri,
                              "qm_ours_B_per_tri": qm_ours / tri, "qm_ours_gzip_B_per_tri": qm_ours_z / tri,
                              "qme_B_per_tri": qm_lib / tri, "qme_gzip_B_per_tri": qm_lib_z / tri}  # fmt: skip
        qm = QuantizedMesh(t)
        ours = ours_z = lib = lib_z = tri = 0
        codes = qm.tile_codes()
        for z, x, y in codes:
            d = decode_tile(qm.tile(z, x, y).data, tile_rectangle(z, x, y))
            rect = tile_rectangle(z, x, y)
            raw = encode_tile(d["lon"], d["lat"], d["height"], d["triangles"], rect)
            ours += len(raw)
            ours_z += len(gzip.compress(raw, 6))
            b = io.BytesIO()
            import quantized_mesh_encoder as qme

            qme.encode(b, np.column_stack([d["lon"], d["lat"], d["height"]]), d["triangles"].astype(np.uint32),
                       bounds=rect)  # fmt: skip
            lib += len(b.getvalue())
            lib_z += len(gzip.compress(b.getvalue(), 6))
            tri += len(d["triangles"])
        out["quantized-mesh tiles"] = {"triangles": tri, "qm_ours_B_per_tri": ours / tri,
                                       "qm_ours_gzip_B_per_tri": ours_z / tri, "qme_B_per_tri": lib / tri,
                                       "qme_gzip_B_per_tri": lib_z / tri}  # fmt: skip
        # greedy insertion vs the 65² regular grid at equal measured error (finest level)
        zmax = qm.max_zoom
        g_raw = g_z = r_raw = r_z = g_tri = r_tri = 0
        g_err, r_err = [], []
        interior: list = []
        for z in range(zmax, zmax + 3):  # the finest level that has tiles wholly inside the source
            x0, y0, x1, y1 = qm.level_range(z)
            cand = [(z, x, y) for y in range(y0, y1 + 1) for x in range(x0, x1 + 1)]
            interior = [c for c in cand if qm.tile(*c).nodata_fraction == 0.0][:6]
            if interior:
                break
        for z, x, y in interior:  # no footprint cliff in either mesh
            grid = qm.tile(z, x, y, regular=65)
            target = max(grid.error_m, 0.01)
            for _ in range(5):  # equal measured error: tighten the target until greedy is not worse
                greedy = qm.tile(z, x, y, target_m=target)
                if greedy.error_m <= grid.error_m:
                    break
                target *= 0.8
            gr = len(gzip.decompress(greedy.data))
            rr = len(gzip.decompress(grid.data))
            g_raw, g_z, r_raw, r_z = g_raw + gr, g_z + len(greedy.data), r_raw + rr, r_z + len(grid.data)
            g_tri, r_tri = g_tri + greedy.triangles, r_tri + grid.triangles
            g_err.append(greedy.error_m)
            r_err.append(grid.error_m)
        out["greedy vs grid (finest level)"] = {
            "tiles": len(g_err), "level": interior[0][0] if interior else None, "greedy_bytes": g_raw, "greedy_gzip_bytes": g_z, "grid_bytes": r_raw,
            "grid_gzip_bytes": r_z, "greedy_triangles": g_tri, "grid_triangles": r_tri,
            "greedy_max_error_m": max(g_err), "grid_max_error_m": max(r_err),
            "greedy_median_error_m": float(np.median(g_err)), "grid_median_error_m": float(np.median(r_err)),
        }  # fmt: skip
    return out


def start_server(path: Path) -> tuple[subprocess.Popen, str]:
    import socket

    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    proc = subprocess.Popen([sys.executable, "-m", "terralod", "serve", str(path), "--port", str(port)],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, cwd=ROOT)  # fmt: skip
    base = f"http://127.0.0.1:{port}"
    for _ in range(200):
        try:
            urllib.request.urlopen(base + "/info.json", timeout=60).read()
            return proc, base
        except OSError:
            time.sleep(0.1)
    proc.kill()
    raise RuntimeError("server did not start")


def load_test(base: str, n: int = 1000) -> dict:
    """n requests at once (one thread each, released together) over the tiles of both formats."""
    layer = json.loads(urllib.request.urlopen(base + "/terrain/layer.json").read())
    urls = []
    for z, ranges in enumerate(layer["available"]):
        for r in ranges:
            urls += [f"/terrain/{z}/{x}/{y}.terrain" for x in range(r["startX"], r["endX"] + 1)
                     for y in range(r["startY"], r["endY"] + 1)]  # fmt: skip
    ts = json.loads(
        gzip.decompress(
            urllib.request.urlopen(
                urllib.request.Request(base + "/3dtiles/tileset.json", headers={"Accept-Encoding": "gzip"})
            ).read()
        )
    )
    stack = [ts["root"]]
    while stack:
        t = stack.pop()
        if "content" in t:
            urls.append("/3dtiles/" + t["content"]["uri"])
        stack += t.get("children", [])
    for u in urls:  # warm the cache: the test measures serving, the export figures measure encoding
        urllib.request.urlopen(base + u).read()
    lat = [0.0] * n
    err = [None] * n
    barrier = threading.Barrier(n)

    def one(i: int) -> None:
        u = base + urls[i % len(urls)]
        barrier.wait()
        t0 = time.perf_counter()
        try:
            with urllib.request.urlopen(urllib.request.Request(u, headers={"Accept-Encoding": "gzip"}),
                                        timeout=60) as r:  # fmt: skip
                r.read()
                if r.status != 200:
                    err[i] = str(r.status)
        except Exception as exc:  # noqa: BLE001 - counted
            err[i] = type(exc).__name__
        lat[i] = time.perf_counter() - t0

    threads = [threading.Thread(target=one, args=(i,)) for i in range(n)]
    t0 = time.perf_counter()
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    wall = time.perf_counter() - t0
    ms = np.array(lat) * 1e3
    return {"requests": n, "distinct_tiles": len(urls), "errors": sum(e is not None for e in err),
            "p50_ms": float(np.percentile(ms, 50)), "p99_ms": float(np.percentile(ms, 99)), "wall_s": wall}  # fmt: skip


def _dir_bytes(d: Path, suffix: str) -> tuple[int, int]:
    """(bytes as written, bytes gzip'd at level 6) of every file with ``suffix`` under ``d``."""
    raw = gz = 0
    for f in d.rglob(f"*{suffix}"):
        b = f.read_bytes()
        raw += len(b)
        gz += len(b) if b[:2] == b"\x1f\x8b" else len(gzip.compress(b, 6, mtime=0))
    return raw, gz


def _site(tmp: Path, exports: dict[str, Path]) -> Path:
    """A folder for a plain static server: the stock page, CesiumJS, the exports (symlinks)."""
    try:
        from terralod.serve import cesium_dir

        cesium = Path(cesium_dir())
    except Exception:  # noqa: BLE001 - no packaged copy: the npm one
        cesium = ROOT / "node_modules" / "cesium" / "Build" / "Cesium"
    site = tmp / "site"
    site.mkdir(exist_ok=True)
    (site / "cesium").symlink_to(cesium, target_is_directory=True)
    shutil.copy(ROOT / "benchmarks" / "web" / "stock_cesium.html", site / "stock_cesium.html")
    for name, d in exports.items():
        (site / name).symlink_to(d, target_is_directory=True)
    return site


def stock_figures(tmp: Path, browser_runs: bool) -> dict:
    """Full DEMs exported as a user would (N41E001 straight from the DEM; Big Tujunga through a store),
    bytes per triangle as written and gzip'd (every extension included), the declared error per zoom, and
    the load time to all tiles in stock CesiumJS (defaults) from three views, from a plain static server."""
    from terralod.export import export_3dtiles, export_quantized_mesh
    from terralod.export.source import source_from_dem
    from terralod.io.reader import read_heightfield
    from terralod.pyramid.builder import build_store
    from terralod.terrain import open_terrain

    out: dict = {}
    geo = SHARED / "dem" / "srtm3_N41E001.tif"
    utm = SHARED / "dem" / "big_tujunga_srtm30m_utm11.tif"
    if not geo.exists():
        return out
    exports: dict[str, Path] = {}
    rep = export_quantized_mesh(source_from_dem(geo), tmp / "qm_geo")
    exports["qm_geo"] = tmp / "qm_geo"
    out["N41E001 quantized-mesh (from the DEM)"] = rep
    store = tmp / "tujunga.terra"
    build_store(read_heightfield(utm), store, workers=2)
    with open_terrain(store) as t:
        out["Big Tujunga quantized-mesh (store)"] = export_quantized_mesh(t, tmp / "qm_utm")
        out["Big Tujunga 3D Tiles (store)"] = export_3dtiles(t, tmp / "t3_utm")
    exports["qm_utm"], exports["t3_utm"] = tmp / "qm_utm", tmp / "t3_utm"
    res: dict = {}
    for name, r in out.items():
        suffix = ".glb" if "3D Tiles" in name else ".terrain"
        raw, gz = _dir_bytes(r.path, suffix)
        res[name] = {"tiles": r.tiles, "triangles": r.triangles, "seconds": r.seconds, "bytes": raw,
                     "gzip_bytes": gz, "B_per_tri": raw / max(r.triangles, 1), "gzip_B_per_tri": gz / max(r.triangles, 1),
                     **{k: v for k, v in r.extra.items() if k in ("water_masks", "error_m_per_level", "max_zoom",
                                                                   "geometric_error_root")}}  # fmt: skip
    if browser_runs and shutil.which("node") and shutil.which("chromium"):
        site = _site(tmp, exports)
        proc = subprocess.Popen([sys.executable, "-u", "-m", "http.server", "0", "--bind", "127.0.0.1"], cwd=site,
                                stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)  # fmt: skip
        try:
            port = proc.stdout.readline().split("port ")[1].split()[0]
            base = f"http://127.0.0.1:{port}"
            for name, query, kind, bbox, ridge in (
                ("N41E001 quantized-mesh (from the DEM)", "terrain=qm_geo/&hmin=0&hmax=1200", "terrain",
                 (1.0, 41.0, 2.0, 42.0), (1.83, 41.6)),
                ("Big Tujunga 3D Tiles (store)", "tileset=t3_utm/tileset.json", "tileset",
                 (-118.35, 34.22, -117.95, 34.40), (-118.15, 34.33)),
                ("Big Tujunga quantized-mesh (store)", "terrain=qm_utm/&hmin=300&hmax=2300", "terrain",
                 (-118.35, 34.22, -117.95, 34.40), (-118.15, 34.33)),
            ):  # fmt: skip
                w, s_, e, n = bbox
                cfg = {"kind": kind, "points": [list(ridge)], "views": [
                    {"name": "whole", "rect": [w, s_, e, n]},
                    {"name": "ridge", "lon": ridge[0], "lat": ridge[1], "height": 2000 + 1500, "pitch": -90},
                    {"name": "oblique", "lon": 0.5 * (w + e), "lat": s_ - 0.3 * (n - s_), "height": 1500, "pitch": -5}]}  # fmt: skip
                (tmp / "cfg.json").write_text(json.dumps(cfg))
                r = subprocess.run(["node", str(ROOT / "benchmarks" / "web" / "stock_check.mjs"),
                                    f"{base}/stock_cesium.html?{query}", str(tmp / "cfg.json"), str(tmp / "shot_"),
                                    "180000"], capture_output=True, text=True, timeout=900)  # fmt: skip
                try:
                    j = json.loads(r.stdout.strip().splitlines()[-1])
                except (IndexError, json.JSONDecodeError):
                    j = {"errors": [r.stderr[-300:]], "views": []}
                res[name]["stock_cesium"] = {"views": j.get("views", []), "errors": len(j.get("errors", [])),
                                             "wall_ms": j.get("wallMs")}  # fmt: skip
        finally:
            proc.terminate()
            proc.wait(10)
    return res


def _stock_md(res: dict) -> list[str]:
    md = ["", "## Exports as a user makes them, in stock CesiumJS (defaults, plain static server)", "",
          "Bytes of the tile files as written (uncompressed quantized-mesh, every extension included) and gzip'd;",
          "declared error per zoom = max over the zoom's tiles of the true error of each tile as decoded, against",
          "every source sample in it (the DEM's own samples).", "",
          "| export | tiles | triangles | s | B/tri | gzip B/tri | water masks (none/all/some) | load ms whole / ridge / oblique | errors |",
          "|---|---|---|---|---|---|---|---|---|"]  # fmt: skip
    for name, r in res.items():
        wm = r.get("water_masks")
        wms = f"{wm['none']}/{wm['all']}/{wm['some']}" if wm else "–"
        sc = r.get("stock_cesium", {})
        loads = " / ".join(str(v["ms"]) for v in sc.get("views", [])) or "–"
        md.append(f"| {name} | {r['tiles']} | {r['triangles']:,} | {r['seconds']:.1f} | {r['B_per_tri']:.2f} | "
                  f"{r['gzip_B_per_tri']:.2f} | {wms} | {loads} | {sc.get('errors', '–')} |")  # fmt: skip
    md += ["", "| export | declared max vertical error per zoom, m |", "|---|---|"]
    for name, r in res.items():
        if "error_m_per_level" in r:
            md.append(
                f"| {name} | {', '.join(f'z{z}: {e:.2f}' for z, e in enumerate(r['error_m_per_level']))} |"
            )
    return md


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--no-browser", action="store_true")
    ap.add_argument("--requests", type=int, default=1000)
    ap.add_argument("--stock-only", action="store_true", help="only the stock-client section")
    a = ap.parse_args()
    payload: dict = {"terrains": {}}
    if a.stock_only:
        with tempfile.TemporaryDirectory() as d:
            payload["stock"] = stock_figures(Path(d), not a.no_browser)
        md = ["# Web globe: exports in stock clients", *_stock_md(payload["stock"])]
        write_results("web_stock", payload, "\n".join(md) + "\n")
        return
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        for name, path in stores(tmp).items():
            print("benchmarking", name, flush=True)
            entry = {"export": export_figures(path, tmp, a.runs), "bytes": bytes_per_triangle(path)}
            proc, base = start_server(path)
            try:
                entry["serve"] = load_test(base, a.requests)
            finally:
                proc.terminate()
                proc.wait(10)
            payload["terrains"][name] = entry
        print("benchmarking the stock-client exports", flush=True)
        payload["stock"] = stock_figures(tmp, not a.no_browser)
    md = ["# Web globe: exports, encodings, browser, serve", "",
          "Medians of the runs; machine shared (2 cores, loaded). Bytes per triangle of the same meshes;",
          "quantized-mesh sizes without extensions for the encoder comparison.", "",
          "## Export throughput", "", "| terrain | format | tiles | triangles | MB | s | tiles/s | MB/s |",
          "|---|---|---|---|---|---|---|---|"]  # fmt: skip
    for name, e in payload["terrains"].items():
        for fmt, r in e["export"].items():
            md.append(f"| {name} | {fmt} | {r['tiles']} | {r['triangles']:,} | {r['bytes'] / 1e6:.2f} | "
                      f"{r['seconds']:.2f} | {r['tiles_per_s']:.1f} | {r['mb_per_s']:.2f} |")  # fmt: skip
    md += ["", "## Bytes per triangle (same meshes)", "",
           "| terrain | meshes | triangles | glb | glb gzip | quantized-mesh (ours) | ours gzip | quantized-mesh-encoder | qme gzip |",
           "|---|---|---|---|---|---|---|---|---|"]  # fmt: skip
    for name, e in payload["terrains"].items():
        for k, r in e["bytes"].items():
            if k.startswith("greedy"):
                continue
            na = "–"
            glb = (
                f"{r['glb_B_per_tri']:.2f} | {r['glb_gzip_B_per_tri']:.2f}"
                if "glb_B_per_tri" in r
                else f"{na} | {na}"
            )
            md.append(f"| {name} | {k} | {r['triangles']:,} | {glb} | {r['qm_ours_B_per_tri']:.2f} | "
                      f"{r['qm_ours_gzip_B_per_tri']:.2f} | {r['qme_B_per_tri']:.2f} | {r['qme_gzip_B_per_tri']:.2f} |")  # fmt: skip
    md += ["", "## Quantized-mesh: greedy insertion vs the 65² regular grid at equal measured error (tiles wholly inside the source, of the finest level that has such tiles)", "",
           "| terrain | level | tiles | grid max err m | greedy max err m | grid tris | greedy tris | grid B | greedy B | grid gzip B | greedy gzip B |",
           "|---|---|---|---|---|---|---|---|---|---|---|"]  # fmt: skip
    for name, e in payload["terrains"].items():
        r = e["bytes"]["greedy vs grid (finest level)"]
        md.append(f"| {name} | {r['level']} | {r['tiles']} | {r['grid_max_error_m']:.2f} | {r['greedy_max_error_m']:.2f} | "
                  f"{r['grid_triangles']:,} | {r['greedy_triangles']:,} | {r['grid_bytes']:,} | {r['greedy_bytes']:,} | "
                  f"{r['grid_gzip_bytes']:,} | {r['greedy_gzip_bytes']:,} |")  # fmt: skip
    md += [
        "",
        "## Serve: concurrent tile requests on loopback (warm cache)",
        "",
        "| terrain | requests | distinct tiles | errors | p50 ms | p99 ms | wall s |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, e in payload["terrains"].items():
        r = e["serve"]
        md.append(f"| {name} | {r['requests']} | {r['distinct_tiles']} | {r['errors']} | {r['p50_ms']:.1f} | "
                  f"{r['p99_ms']:.1f} | {r['wall_s']:.2f} |")  # fmt: skip
    md += _stock_md(payload["stock"])
    write_results("web", payload, "\n".join(md) + "\n")


if __name__ == "__main__":
    main()
