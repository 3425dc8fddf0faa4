"""A series over a region (issue 54 #5): three surveys of n x n SRTM3 tiles as one store of epochs, and its
change site kept up to date, every step out of core.

Per mosaic size: the 1° tiles of ``srtm3_N41E001`` mirror-tiled (``region.write_mosaic``), a second survey with
a planted mound and pit (``change_region.write_after``), a third with a pit dug into one tile. Then, each a
fresh ``terralod`` process (wall, CPU of the process tree, peak RSS of the tree sampled every 50 ms):

1. ``terralod build 2000/ -o series.terra --epoch 2000-01-01`` (out of core; the samples kept);
2. ``terralod update series.terra 2007/ --epoch 2007-01-01`` (window by window: the dirty tiles rebuilt);
3. ``terralod export series.terra --format site -o site/`` (each pair measured window by window);
4. ``terralod update series.terra 2012/ --epoch 2012-01-01``;
5. ``terralod export series.terra --format site -o site/ --update`` (only the files whose bytes change).

Writes ``results/series_region.{json,md}``. Usage: ``python benchmarks/series_region.py --counts 4 16``.
"""

from __future__ import annotations

import argparse
import re
import shutil
import sqlite3
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from change_region import write_after  # noqa: E402
from region import run_tree, write_mosaic  # noqa: E402

from _common import SHARED, md_table, write_results  # noqa: E402

SRC = SHARED / "dem" / "srtm3_N41E001.tif"


def write_third(after: Path, folder: Path, n: int) -> str:
    """The second survey with a pit 40 m deep, 1.5 km across, dug into the south-west tile; its name."""
    import rasterio

    shutil.copytree(after, folder)
    name = f"N{41:02d}E{1:03d}.tif"
    with rasterio.open(folder / name) as ds:
        z, prof = ds.read(1), ds.profile
    r, c = np.indices(z.shape)
    bowl = np.clip(1.0 - ((r - 600) ** 2 + (c - 600) ** 2) / 9.0**2, 0.0, None)  # 9 cells ≈ 0.8 km radius
    dz = np.rint(-40.0 * bowl).astype(z.dtype)
    dz[z == prof["nodata"]] = 0
    with rasterio.open(folder / name, "w", **prof) as ds:
        ds.write(z + dz, 1)
    return name


def _stamps(site: Path) -> dict[str, tuple[int, int]]:
    """Each file of the site: (inode, mtime ns)."""
    if not site.is_dir():
        return {}
    return {q.relative_to(site).as_posix(): (q.stat().st_ino, q.stat().st_mtime_ns) for q in site.rglob("*")
            if q.is_file()}  # fmt: skip


def _part(name: str) -> str:
    """The part of the site a file belongs to: epochs/K, the pairs' tiles, the pairs' descriptions, the rest."""
    bits = name.split("/")
    if bits[0] == "epochs":
        return f"epochs/{bits[1]}"
    if bits[0] == "pairs":
        return "pair tiles" if len(bits) > 2 else "pair descriptions"
    return "page, manifest, CesiumJS"


def _breakdown(before: dict, after: dict) -> str:
    """What an update did, per part: new, rewritten, removed, untouched files."""
    out: dict[str, list[int]] = {}
    for f in set(before) | set(after):
        k = out.setdefault(_part(f), [0, 0, 0, 0])
        if f not in before:
            k[0] += 1
        elif f not in after:
            k[2] += 1
        elif after[f] != before[f]:
            k[1] += 1
        else:
            k[3] += 1
    return "; ".join(f"{p}: {a:,} new, {b:,} rewritten, {c:,} removed, {d:,} untouched"
                     for p, (a, b, c, d) in sorted(out.items()))  # fmt: skip


def _epochs(store: Path) -> list[dict]:
    import json

    conn = sqlite3.connect(store)
    try:
        return [json.loads(i) for (i,) in conn.execute("SELECT info FROM epochs ORDER BY id")]
    finally:
        conn.close()


def run(n: int, work: Path) -> list[dict]:
    tm = sys.executable, "-m", "terralod"
    before, after, third = work / "2000", work / "2007", work / "2012"
    write_mosaic(SRC, n, before)
    write_after(sorted(before.glob("*.tif")), after, n)
    write_third(after, third, n)
    store, site = work / "series.terra", work / "site"
    steps = [
        ("build --epoch", [*tm, "build", str(before), "-o", str(store), "--epoch", "2000-01-01"]),
        ("update (2nd survey)", [*tm, "update", str(store), str(after), "--epoch", "2007-01-01"]),
        ("export --format site", [*tm, "export", str(store), "--format", "site", "-o", str(site)]),
        ("update (3rd survey)", [*tm, "update", str(store), str(third), "--epoch", "2012-01-01"]),
        ("export --format site --update", [*tm, "export", str(store), "--format", "site", "-o", str(site), "--update"]),
    ]  # fmt: skip
    rows = []
    for step, cmd in steps:
        print(f"{n * n} tiles: {step} ...", flush=True)
        stamps = _stamps(site)
        r = run_tree(cmd)
        out = str(r["stdout"])
        row = {"tiles": n * n, "step": step, "wall_s": r["wall_s"], "cpu_s": r["cpu_s"],
               "peak_rss_mib": r["peak_rss_mib"], "detail": ""}  # fmt: skip
        if step.startswith("update"):
            info = _epochs(store)[-1]
            row["detail"] = (f"{info['tiles_rebuilt']:,} tiles rebuilt, {info['tiles_shared']:,} shared, "
                             f"{info['changed_samples']:,} samples changed")  # fmt: skip
        elif step.startswith("export"):
            files = sum(1 for p in site.rglob("*") if p.is_file())
            m = re.search(r"updated: (\d+) file\(s\) rewritten, (\d+) removed", out)
            row["detail"] = (
                f"{files:,} files, {sum(p.stat().st_size for p in site.rglob('*') if p.is_file()) / 1e6:,.0f} MB"
            )
            if m:
                row["detail"] += f"; {int(m.group(1)):,} rewritten, {int(m.group(2)):,} removed"
                row["update"] = _breakdown(stamps, _stamps(site))
        print(f"  {row['wall_s']:.0f} s, {row['peak_rss_mib']:.0f} MiB, {row['detail']}", flush=True)
        rows.append(row)
    cells = _grid_cells(store)
    for row in rows:
        row["grid_cells"] = cells
    return rows


def _grid_cells(store: Path) -> int:
    import json

    conn = sqlite3.connect(store)
    try:
        meta = dict(conn.execute("SELECT key, value FROM meta").fetchall())
    finally:
        conn.close()
    return int(json.loads(meta["width"])) * int(json.loads(meta["height"]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--counts", type=int, nargs="+", default=[2, 4], help="tiles a side of each mosaic")
    ap.add_argument("--work", type=Path, default=None, help="work folder (default: a temporary one)")
    ap.add_argument(
        "--keep", action="store_true", help="keep the earlier results' rows of other mosaic sizes"
    )
    a = ap.parse_args()
    rows = []
    if a.keep:
        import json

        from _common import RESULTS

        old = RESULTS / "series_region.json"
        if old.is_file():
            rows = [
                r for r in json.loads(old.read_text())["rows"] if r["tiles"] not in {n * n for n in a.counts}
            ]
    for n in a.counts:
        work = Path(tempfile.mkdtemp(prefix=f"series{n}-", dir=a.work))
        try:
            rows += run(n, work)
            rows.sort(key=lambda r: r["tiles"])
        finally:
            shutil.rmtree(work, ignore_errors=True)
    table = md_table(
        ["tiles", "grid cells", "step", "wall s", "CPU s", "peak RSS MiB", "what"],
        [[r["tiles"], r["grid_cells"], r["step"], r["wall_s"], r["cpu_s"], r["peak_rss_mib"], r["detail"]] for r in rows],
    )  # fmt: skip
    head = (
        "# A series over a region (issue 54 #5)\n\nThree surveys of n x n SRTM3 tiles (srtm3_N41E001 "
        "mirror-tiled; the 2nd with a planted mound and pit, the 3rd with a pit in one tile) as one store of "
        "epochs and its change site, each step a fresh `terralod` process out of core; peak RSS of the process "
        "tree (psutil, 50 ms). One run each, 2-core shared machine.\n\n"
    )
    updates = "".join(
        f"\n- {r['tiles']} tiles, `{r['step']}`: {r['update']}" for r in rows if r.get("update")
    )
    if updates:
        table += "\n\nWhat each site update did to the files, by part of the site:\n" + updates + "\n"
    write_results("series_region", {"rows": rows}, head + table)
    print(head + table)


if __name__ == "__main__":
    main()
