#!/usr/bin/env bash
# terralod set-up on a fresh Debian/Ubuntu machine: Mesa's EGL/OpenGL (headless rendering on llvmpipe
# when there is no GPU) and Xvfb for the window tests, then the package with its test tools.
set -euo pipefail
cd "$(dirname "$0")/.."
SUDO=""
if [ "$(id -u)" != "0" ]; then SUDO="sudo"; fi
# wait (up to 10 min) for another apt/dpkg run to release its lock instead of failing on it
APT=(env DEBIAN_FRONTEND=noninteractive apt-get -o DPkg::Lock::Timeout=600 -y -qq)
if command -v apt-get >/dev/null 2>&1; then
  echo "install.sh: apt packages: Mesa EGL/OpenGL (libegl1 libgl1 libegl-mesa0 libgl1-mesa-dri libglx-mesa0)," \
    "Xvfb (xvfb xauth), PROJ's geoid grids (proj-data), Chromium, and Node/npm if missing"
  $SUDO "${APT[@]}" update
  $SUDO "${APT[@]}" install --no-install-recommends \
    libegl1 libgl1 libegl-mesa0 libgl1-mesa-dri libglx-mesa0 xvfb xauth >/dev/null
  # PROJ's geoid grids (egm96_15.gtx): heights above EGM96 made ellipsoidal for the web exports
  $SUDO "${APT[@]}" install --no-install-recommends proj-data >/dev/null
  # the web viewer and its browser tests: Debian's Chromium (software WebGL) and Node for CesiumJS
  $SUDO "${APT[@]}" install --no-install-recommends chromium >/dev/null
  command -v npm >/dev/null 2>&1 || $SUDO "${APT[@]}" install --no-install-recommends nodejs npm >/dev/null
else
  echo "apt-get not found: install Mesa EGL/OpenGL and Xvfb with your package manager" >&2
fi
echo "install.sh: pip install -e .[all,dev,fast-tin] (terralod with every extra, its test tools and Triangle, into $(python -c 'import sys; print(sys.prefix)'))"
python -m pip install -e ".[all,dev,fast-tin]"
# CesiumJS, the Khronos glTF validator and puppeteer-core (drives the system Chromium: no browser download)
if command -v npm >/dev/null 2>&1; then
  PUPPETEER_SKIP_DOWNLOAD=1 npm ci --no-audit --no-fund
  # the viewer's CesiumJS into the package (src/terralod/site/cesium, package data of the wheel)
  python scripts/vendor_cesium.py
fi
# compile and cache every numba kernel now, so the first build / render / demo does not sit silent
echo "install.sh: compiling terralod's kernels once (about 3 minutes on an idle machine)"
python -m terralod warmup
