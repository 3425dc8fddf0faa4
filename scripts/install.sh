#!/usr/bin/env bash
# terralod set-up on a fresh Debian/Ubuntu machine: Mesa's EGL/OpenGL (headless rendering on llvmpipe
# when there is no GPU) and Xvfb for the window tests, then the package with its test tools.
set -euo pipefail
cd "$(dirname "$0")/.."
SUDO=""
if [ "$(id -u)" != "0" ]; then SUDO="sudo"; fi
if command -v apt-get >/dev/null 2>&1; then
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends \
    libegl1 libgl1 libegl-mesa0 libgl1-mesa-dri libglx-mesa0 xvfb xauth >/dev/null
  # the web viewer and its browser tests: Debian's Chromium (software WebGL) and Node for CesiumJS
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends chromium >/dev/null
  command -v npm >/dev/null 2>&1 || \
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends nodejs npm >/dev/null
else
  echo "apt-get not found: install Mesa EGL/OpenGL and Xvfb with your package manager" >&2
fi
python -m pip install -e ".[dev]"
# CesiumJS, the Khronos glTF validator and puppeteer-core (drives the system Chromium: no browser download)
if command -v npm >/dev/null 2>&1; then PUPPETEER_SKIP_DOWNLOAD=1 npm ci --no-audit --no-fund; fi
