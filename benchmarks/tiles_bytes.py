"""Bytes a host serves: gzip'd bytes per source sample of the 3D Tiles export against quantized-mesh.

    python benchmarks/tiles_bytes.py [--keep DIR]

Two DEMs of ../shared/data, each built with ``terralod build DEM -o store.terra`` (the default adaptive
store) and exported from that store:

- ``quantized-mesh`` (gzip'd tiles, what a host sends): its declared max vertical error ``E`` is that of its
  finest zoom (``layer.json``'s ``terralod.error_m``, measured on the decoded tiles against the samples);
- ``3dtiles`` with ``--metric vertical --max-error-m E`` (every leaf declares a vertical error ≤ ``E``), in
  each glb geometry (``float``, ``quantized`` = KHR_mesh_quantization, ``meshopt`` = also
  EXT_meshopt_compression), and for reference the whole tree down to the lossless level (``float`` is the
  export as it was before KHR_mesh_quantization) and the tree cut at quantized-mesh's greedy-insertion
  target of its finest zoom (what its tiles aim at, not what they declare: the declared ``E`` is measured
  against the source's own samples after the re-tiling into Cesium's geographic grid, several times the
  target on a DEM with cliffs).

Every tile is gzip'd at level 6 (what quantized-mesh's ``--gzip`` and ``terralod serve`` use) and the bytes
summed, tileset.json and layer.json left out; "per sample" divides by the DEM's valid samples. ``vs QM`` is
the ratio to quantized-mesh's gzip'd bytes at the same ``E``. Writes benchmarks/results/tiles_bytes.json
and .md.
"""

from __future__ import annotations

import argparse
import gzip
import json
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import SHARED, md_table, write_results  # noqa: E402

DEMS = ["kilauea_hawaii_30m_utm5", "big_tujunga_srtm30m_utm11"]


def _gz_bytes(folder: Path, suffix: str) -> tuple[int, int, int]:
    """(files, raw bytes, gzip'd bytes at level 6) of the tiles under ``folder``."""
    files = raw = gz = 0
    for p in sorted(folder.rglob(f"*{suffix}")):
        data = p.read_bytes()
        if data[:2] == b"\x1f\x8b":  # already gzip'd (quantized-mesh --gzip)
            data = gzip.decompress(data)
        files += 1
        raw += len(data)
        gz += len(gzip.compress(data, 6, mtime=0))
    return files, raw, gz


def _leaf_errors(ts: dict[str, Any]) -> float:
    """The largest geometricError of a tileset's leaves (tiles with content and no children)."""
    worst, stack = 0.0, [ts["root"]]
    while stack:
        t = stack.pop()
        kids = t.get("children", [])
        if not kids and "content" in t:
            worst = max(worst, float(t["geometricError"]))
        stack += kids
    return worst


def run(work: Path) -> dict[str, Any]:
    from terralod.export import export_3dtiles, export_quantized_mesh
    from terralod.io.reader import read_heightfield
    from terralod.pyramid.builder import build_store
    from terralod.terrain import open_terrain

    out: dict[str, Any] = {"dems": {}}
    for name in DEMS:
        dem = SHARED / "dem" / f"{name}.tif"
        hf = read_heightfield(dem)
        samples = int(np.count_nonzero(hf.valid))
        store = work / f"{name}.terra"
        if not store.exists():
            build_store(hf, store, workers=2)
        rows: list[dict[str, Any]] = []
        with open_terrain(store) as t:
            rep = export_quantized_mesh(t, work / f"{name}_qm", gzip_tiles=True, overwrite=True)
            e = float(rep.extra["error_m_per_level"][-1])
            files, raw, gz = _gz_bytes(work / f"{name}_qm", ".terrain")
            qm = {"export": "quantized-mesh", "geometry": "-", "max_error_m": e, "tiles": files, "raw": raw,
                  "gz": gz, "leaf_error_m": e}  # fmt: skip
            rows.append(qm)
            fine = float(
                json.loads((work / f"{name}_qm" / "layer.json").read_text())["terralod"]["target_error_m"][-1]
            )
            runs = [
                ("float", None),
                ("quantized", None),
                ("meshopt", None),
                ("float", e),
                ("quantized", e),
                ("meshopt", e),
                ("quantized", fine),
                ("meshopt", fine),
            ]
            for geometry, cap in runs:
                dest = work / f"{name}_3d_{geometry}_{'all' if cap is None else cap}"
                r3 = export_3dtiles(
                    t, dest, metric="vertical", geometry=geometry, max_error_m=cap, overwrite=True
                )
                files, raw, gz = _gz_bytes(dest, ".glb")
                ts = json.loads((dest / "tileset.json").read_text())
                rows.append({"export": "3dtiles", "geometry": geometry, "max_error_m": cap, "tiles": files,
                             "raw": raw, "gz": gz, "leaf_error_m": _leaf_errors(ts),
                             "encoding_error_m": r3.extra["encoding_error_m"]})  # fmt: skip
        for r in rows:
            r["gz_per_sample"] = r["gz"] / samples
            r["vs_qm"] = r["gz"] / qm["gz"]
        out["dems"][name] = {"samples": samples, "E_m": e, "qm_finest_target_m": fine, "rows": rows}
    return out


def table(res: dict[str, Any]) -> str:
    lines = ["# Bytes per source sample: 3D Tiles against quantized-mesh\n",
             "Tiles gzip'd at level 6, tileset.json / layer.json left out. `E`: quantized-mesh's declared max "
             "vertical error at its finest zoom; `3dtiles` rows with a max error are `--metric vertical "
             "--max-error-m E`; `leaf error` is the largest geometricError of a leaf (declared, encoding "
             "included). Reproduce: `python benchmarks/tiles_bytes.py`.\n"]  # fmt: skip
    for name, d in res["dems"].items():
        lines.append(f"\n## {name} ({d['samples']:,} samples, E = {d['E_m']:.3f} m)\n")
        rows = [[r["export"], r["geometry"], "lossless" if r["max_error_m"] is None else f"{r['max_error_m']:.3f}",
                 r["tiles"], r["raw"] / d["samples"], r["gz_per_sample"], r["vs_qm"], r["leaf_error_m"]]
                for r in d["rows"]]  # fmt: skip
        lines.append(md_table(["export", "glb geometry", "max error (m)", "tiles", "raw B/sample",
                               "gzip B/sample", "vs QM", "leaf error (m)"], rows))  # fmt: skip
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--keep", type=Path, default=None, help="Keep the stores and exports in this folder.")
    a = ap.parse_args()
    if a.keep is not None:
        a.keep.mkdir(parents=True, exist_ok=True)
        res = run(a.keep)
    else:
        with tempfile.TemporaryDirectory() as d:
            res = run(Path(d))
    write_results("tiles_bytes", res, table(res))


if __name__ == "__main__":
    main()
