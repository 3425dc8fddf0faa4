"""The wheel (issue 46): ``python -m build --wheel`` gives a wheel that installs without the source tree and
runs ``terralod demo``, ``terralod serve`` (the viewer page and the CesiumJS it carries) and ``terralod
change`` on the St Helens pair.

The venv sees the running interpreter's own site-packages through a ``.pth`` file (the dependencies come
from there, the wheel is installed with ``--no-deps``): ``--system-site-packages`` would give it the *base*
interpreter's, which inside a virtual environment lacks them; the ``.pth`` lists plain folders, so the
running environment's editable terralod (a ``.pth`` hook of its own) is not picked up; every command runs from a folder outside the
repository, and the test proves that the ``terralod`` imported there is the wheel's (``terralod.__file__``
inside the venv, its sources byte-identical to the tree's). The numba kernels' on-disk caches of the source
tree are copied next to the installed modules (same code, the sources' timestamps carried over), so the
test does not spend minutes compiling what ``terralod warmup`` compiled already; a stale entry compiles.
"""

from __future__ import annotations

import os
import shutil
import site as site_module
import subprocess
import sys
import urllib.request
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "src" / "terralod"
DATA = ROOT.parent / "shared" / "data" / "change"
BEFORE = DATA / "st_helens_crater_2000-09-25_10m.tif"
AFTER = DATA / "st_helens_crater_2007-07-05_10m.tif"

pytestmark = [
    pytest.mark.skipif(not BEFORE.exists(), reason="../shared/data (St Helens pair) is absent"),
    pytest.mark.skipif(
        not (SRC / "site" / "cesium" / "Cesium.js").is_file(),
        reason="CesiumJS is not vendored (npm ci, then python scripts/vendor_cesium.py: scripts/install.sh)",
    ),
]


def _run(cmd: list[str], cwd: Path, env: dict[str, str], timeout: float = 300) -> subprocess.CompletedProcess:
    r = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    assert r.returncode == 0, f"{cmd}: exit {r.returncode}\n{r.stdout[-2000:]}\n{r.stderr[-3000:]}"
    return r


def _carry_kernel_caches(site: Path) -> None:
    """Copy the tree's numba caches beside the installed modules, with the sources' timestamps."""
    for cache in SRC.rglob("__pycache__"):
        rel = cache.parent.relative_to(SRC)
        dest = site / "terralod" / rel
        if not dest.is_dir():
            continue
        files = [f for f in cache.iterdir() if f.suffix in (".nbi", ".nbc")]
        if not files:
            continue
        (dest / "__pycache__").mkdir(exist_ok=True)
        for f in files:
            shutil.copy2(f, dest / "__pycache__" / f.name)
        for py in cache.parent.glob("*.py"):
            if (dest / py.name).is_file() and (dest / py.name).read_bytes() == py.read_bytes():
                st = py.stat()
                os.utime(dest / py.name, ns=(st.st_atime_ns, st.st_mtime_ns))


@pytest.fixture(scope="module")
def wheel_venv(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, Path, dict[str, str]]:
    tmp = tmp_path_factory.mktemp("wheel")
    dist = tmp / "dist"
    _run([sys.executable, "-m", "build", "--wheel", "--outdir", str(dist), str(ROOT)], ROOT, dict(os.environ))
    (wheel,) = dist.glob("terralod-*.whl")
    venv = tmp / "venv"
    _run([sys.executable, "-m", "venv", str(venv)], tmp, dict(os.environ))
    py = venv / "bin" / "python"
    venv_site = Path(_run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"], tmp,
                          dict(os.environ)).stdout.strip())  # fmt: skip
    parent = [
        p
        for p in dict.fromkeys(site_module.getsitepackages() + [site_module.getusersitepackages()])
        if Path(p).is_dir()
    ]
    (venv_site / "_terralod_test_parent_env.pth").write_text("\n".join(parent) + "\n")
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "TERRALOD_CESIUM_DIR", "DISPLAY")}
    env.update(PYTHONUNBUFFERED="1", PIP_DISABLE_PIP_VERSION_CHECK="1", PATH=f"{venv / 'bin'}:{env['PATH']}")
    _run(
        [str(py), "-m", "pip", "install", "--no-deps", "--no-index", "--force-reinstall", str(wheel)],
        tmp,
        env,
    )
    work = tmp / "work"  # outside the repository: no src/ nor node_modules/ to fall back on
    work.mkdir()
    site = Path(_run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"], work, env)
                .stdout.strip())  # fmt: skip
    _carry_kernel_caches(site)
    return wheel, venv, work, env


def test_wheel_carries_the_package_and_cesium(wheel_venv) -> None:
    wheel, venv, work, env = wheel_venv
    names = zipfile.ZipFile(wheel).namelist()
    assert "terralod/site/cesium/Cesium.js" in names
    assert "terralod/site/cesium/LICENSE.md" in names
    assert "terralod/site/static/index.html" in names and "terralod/site/static/site.js" in names
    assert not any(n.endswith(("cesium/index.cjs", "cesium/index.js")) for n in names)  # Node bundles
    meta = zipfile.ZipFile(wheel).read(next(n for n in names if n.endswith(".dist-info/METADATA"))).decode()
    assert "License-Expression: MIT AND Apache-2.0" in meta
    core = [
        line for line in meta.splitlines() if line.startswith("Requires-Dist:") and "extra ==" not in line
    ]
    assert not any(p in " ".join(core) for p in ("xdem", "dask", "glfw", "pyproj", "quantized-mesh-encoder"))
    r = _run([str(venv / "bin" / "python"), "-c", "import terralod; print(terralod.__file__)"], work, env)
    installed = Path(r.stdout.strip())
    assert installed.is_relative_to(venv), installed
    assert not installed.is_relative_to(ROOT)
    pkg = installed.parent
    # every file of the tree (modules, shaders, the viewer page, CesiumJS) is in the installed package
    files = sorted(p.relative_to(SRC) for p in SRC.rglob("*") if p.is_file() and "__pycache__" not in p.parts)
    assert len(files) > 400 and [f for f in files if not (pkg / f).is_file()] == []


def test_wheel_demo(wheel_venv) -> None:
    _, venv, work, env = wheel_venv
    _run(["terralod", "demo", "--no-window", "--frames", "4", "-o", "demo.terra"], work, env)
    assert (work / "demo.png").stat().st_size > 0 and (work / "demo.mp4").stat().st_size > 0


def test_wheel_serve_viewer_and_cesium(wheel_venv) -> None:
    _, venv, work, env = wheel_venv
    store = work / "sh.terra"
    _run(["terralod", "build", str(BEFORE), "-o", str(store)], work, env)
    proc = subprocess.Popen(["terralod", "serve", str(store), "--port", "0"], cwd=work, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)  # fmt: skip
    try:
        line = proc.stdout.readline()  # "serving ... on http://127.0.0.1:PORT/ ..."
        assert " on http://" in line, line + proc.stderr.read()
        url = line.split(" on ", 1)[1].split()[0]
        with urllib.request.urlopen(url, timeout=30) as resp:
            assert resp.status == 200 and b"cesium/Cesium.js" in resp.read()
        with urllib.request.urlopen(url + "cesium/Cesium.js", timeout=30) as resp:
            body = resp.read()
            if resp.headers.get("Content-Encoding") == "gzip":
                import gzip

                body = gzip.decompress(body)
        assert body == (SRC / "site" / "cesium" / "Cesium.js").read_bytes()
    finally:
        proc.terminate()
        proc.wait(timeout=30)
        proc.stdout.close()
        proc.stderr.close()


def test_wheel_change(wheel_venv) -> None:
    _, venv, work, env = wheel_venv
    r = _run(["terralod", "change", str(BEFORE), str(AFTER), "-o", "chg", "--no-views"], work, env)
    assert "m³" in r.stdout, r.stdout
    assert (work / "chg").is_dir() and any((work / "chg").iterdir())
