"""Copy CesiumJS's browser build into the package, so the wheel carries the viewer's globe.

``node_modules/cesium/Build/Cesium`` (after ``npm ci``) goes to ``src/terralod/site/cesium/`` with
cesium's ``LICENSE.md`` (Apache-2.0, third-party notices included). The Node bundles (``index.cjs``,
``index.js``: the ``require``/``import`` entry points for bundlers) are left out; the browser loads
``Cesium.js`` with its ``Workers``, ``Assets``, ``ThirdParty`` and ``Widgets``. The target is gitignored and
package data (pyproject), rebuilt whole on each run (a temporary folder renamed into place).

Usage: ``python scripts/vendor_cesium.py [--node-modules DIR]`` (run by scripts/install.sh after ``npm ci``).
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TARGET = ROOT / "src" / "terralod" / "site" / "cesium"
#: Node-only entry points of Build/Cesium (not loaded by a browser page).
NODE_ONLY = {"index.cjs", "index.js", "package.json"}


def vendor(node_modules: Path, target: Path = TARGET) -> int:
    """Copy the browser build into ``target``; returns its size in bytes."""
    pkg = node_modules / "cesium"
    src = pkg / "Build" / "Cesium"
    if not (src / "Cesium.js").is_file():
        raise SystemExit(f"vendor_cesium: {src}/Cesium.js not found: run `npm ci` first")
    lic = pkg / "LICENSE.md"
    if not lic.is_file():
        raise SystemExit(f"vendor_cesium: {lic} not found")
    tmp = target.with_name(f".{target.name}.tmp-{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    shutil.copytree(src, tmp, ignore=lambda d, names: [n for n in names if Path(d) == src and n in NODE_ONLY])
    shutil.copy2(lic, tmp / "LICENSE.md")
    old = target.with_name(f".{target.name}.old-{os.getpid()}")
    if target.exists():
        target.rename(old)
    tmp.rename(target)
    shutil.rmtree(old, ignore_errors=True)
    return sum(f.stat().st_size for f in target.rglob("*") if f.is_file())


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--node-modules", type=Path, default=ROOT / "node_modules")
    args = ap.parse_args(argv)
    size = vendor(args.node_modules)
    print(f"vendor_cesium: {TARGET.relative_to(ROOT)} ({size / 1e6:.1f} MB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
