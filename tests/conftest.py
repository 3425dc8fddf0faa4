"""Shared fixtures: real data from ../shared/data (skipped with a reason when absent), random terrains."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

# the benchmarks' helpers (benchmarks/_common.py, fuzzing.py, change_plants.py) serve the tests too: tests
# import from benchmarks, never the other way round; tests take fractal_terrain from here
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from _common import fractal_terrain  # noqa: E402, F401

SHARED_DATA = Path(
    os.environ.get("TERRALOD_SHARED_DATA", Path(__file__).resolve().parents[1] / ".." / "shared" / "data")
)


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The real terrain of ../shared/data; tests using it skip when the folder is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real terrain data not present at {SHARED_DATA} (../shared/data beside the repository)")
    return SHARED_DATA.resolve()


@pytest.fixture(scope="session")
def browser() -> Iterator[str]:
    """The one headless Chromium the browser tests share (benchmarks/web/browser.mjs, started on first use and
    closed at the end of the session): its DevTools websocket URL. A page check (benchmarks/web/stock_check.mjs,
    site_check.mjs) given it as ``TERRALOD_BROWSER_WS`` opens a fresh browser context of its own in it."""
    repo = Path(__file__).resolve().parents[1]
    if shutil.which("chromium") is None:
        pytest.skip("Debian chromium not installed (bash scripts/install.sh installs it)")
    if shutil.which("node") is None or not (repo / "node_modules" / "puppeteer-core").is_dir():
        pytest.skip("node or node_modules/puppeteer-core missing (run `npm ci` in the repository)")
    import tempfile

    with tempfile.TemporaryFile("w+") as log:
        proc = subprocess.Popen(["node", str(repo / "benchmarks" / "web" / "browser.mjs")], cwd=repo, text=True,
                                stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=log)  # fmt: skip
        assert proc.stdout is not None and proc.stdin is not None
        url = proc.stdout.readline().strip()
        if not url.startswith("ws://"):
            proc.kill()
            proc.wait()
            log.seek(0)
            pytest.fail(f"the shared Chromium did not start: {url!r} {log.read()[-2000:]}")
        try:
            yield url
        finally:
            proc.stdin.close()  # browser.mjs closes the browser when its stdin ends
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


def crop_geotiff(src: Path, dest: Path, col: int, row: int, side: int) -> Path:
    """A side x side window of the GeoTIFF ``src`` from (col, row) written to ``dest``, its georeferencing
    kept (untiled); asserts the window holds no nodata."""
    import rasterio
    from rasterio.windows import Window

    with rasterio.open(src) as ds:
        win = Window(col, row, side, side)
        a = ds.read(1, window=win)
        prof = dict(ds.profile, width=side, height=side, transform=ds.window_transform(win), tiled=False)
    prof.pop("blockxsize", None)
    prof.pop("blockysize", None)
    assert prof.get("nodata") is None or not (a == prof["nodata"]).any()
    with rasterio.open(dest, "w", **prof) as out:
        out.write(a, 1)
    return dest


#: Python's own warning filters in a fresh interpreter (pytest's differ), for :func:`terralod_cli`.
_FRESH_FILTERS = [
    ("default", None, DeprecationWarning, "__main__", 0),
    ("ignore", None, DeprecationWarning, None, 0),
    ("ignore", None, PendingDeprecationWarning, None, 0),
    ("ignore", None, ImportWarning, None, 0),
    ("ignore", None, ResourceWarning, None, 0),
]


def terralod_cli(*args: str, cwd: Path | str | None = None, env: dict[str, str] | None = None):
    """``python -m terralod ARGS`` run in this process: the entry point ``terralod.cli.main`` (errors become
    one line and exit code 2) with stdout, stderr and the root logger's handlers its own, the working
    folder ``cwd``, ``env`` added to the environment, Python's default warning filters and no stdin; it
    returns a ``subprocess.CompletedProcess`` like ``subprocess.run(..., capture_output=True, text=True)``.
    Library warnings go where the command routes them (logging: shown with ``-v`` only), as in a process.
    It saves a process start (about 1.3 s of CPU: numba, rasterio, pyproj) per call; a test of what only a
    process shows (a kill, a signal, a resource limit, ``python -O``, import-time output) runs the real one."""
    import contextlib
    import io
    import logging
    import sys
    import traceback
    import warnings

    from terralod.cli import main
    from terralod.cli._errors import LAST_INPUT, VERBOSE

    out, err = io.StringIO(), io.StringIO()
    root = logging.getLogger()
    handlers, level = root.handlers[:], root.level
    old_env = {k: os.environ.get(k) for k in env or {}}
    here = os.getcwd()
    rc: int = 0
    VERBOSE["on"], LAST_INPUT["path"] = False, None  # a fresh process starts with them unset
    try:
        root.handlers = []  # the command's logging.basicConfig then writes to this stderr, as in a process
        os.environ.update(env or {})
        if cwd is not None:
            os.chdir(cwd)
        with (
            warnings.catch_warnings(),
            contextlib.redirect_stdout(out),
            contextlib.redirect_stderr(err),
            contextlib.ExitStack() as stack,
        ):
            warnings.resetwarnings()
            for action, _msg, cat, mod, _line in reversed(_FRESH_FILTERS):
                warnings.filterwarnings(action, category=cat, module=mod or "")
            # the command's logging.captureWarnings(True) must take effect as in a fresh process (an earlier
            # in-process command left it on, bound to a showwarning that is gone): off now, off after
            logging.captureWarnings(False)
            stack.callback(logging.captureWarnings, False)
            stdin, sys.stdin = sys.stdin, io.StringIO()
            stack.callback(setattr, sys, "stdin", stdin)
            try:
                main([str(a) for a in args])
            except SystemExit as exc:
                if exc.code is None or isinstance(exc.code, int):
                    rc = int(exc.code or 0)
                else:  # sys.exit("message"): Python prints it and exits 1
                    print(exc.code, file=sys.stderr)
                    rc = 1
            except BaseException:  # noqa: BLE001 - what escapes the entry point: Python's traceback, exit 1
                traceback.print_exc(file=sys.stderr)
                rc = 1
    finally:
        os.chdir(here)
        for h in root.handlers:
            if h not in handlers:
                h.close()
        root.handlers, root.level = handlers, level
        for k, v in old_env.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    return subprocess.CompletedProcess(["terralod", *map(str, args)], rc, out.getvalue(), err.getvalue())


def read_tileset(folder: Path | str, name: str = "tileset.json") -> dict:
    """A 3D Tiles tileset read as a client reads it: an external tileset (a tile whose content is a
    ``.json``) replaced by that file's root, which takes the referencing tile's transform (3D Tiles 1.1,
    external tilesets): one nested tree, whatever the files it is split into."""
    import json

    folder = Path(folder)
    ts = json.loads((folder / name).read_text())

    def walk(tile: dict) -> dict:
        uri = tile.get("content", {}).get("uri", "")
        if uri.endswith(".json"):
            ext = read_tileset(folder, uri)["root"]
            ref = tile
            tile = {k: v for k, v in ext.items() if k != "transform"}
            if "transform" in ref:
                tile["transform"] = ref["transform"]
        out = dict(tile)
        if "children" in tile:
            out["children"] = [walk(k) for k in tile["children"]]
        return out

    return {**ts, "root": walk(ts["root"])}


_CPU_LOG = os.environ.get("TERRALOD_TEST_CPU")


if _CPU_LOG:  # a per-test account of user + system CPU, this process and its reaped children: where the suite's time goes

    @pytest.hookimpl(hookwrapper=True)
    def pytest_runtest_protocol(item, nextitem):  # noqa: ANN001, ANN201 - pytest's hook signature
        import json
        import resource
        import time

        def cpu() -> float:
            s, c = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
            return s.ru_utime + s.ru_stime + c.ru_utime + c.ru_stime

        t0, c0 = time.perf_counter(), cpu()
        yield
        with open(_CPU_LOG, "a") as f:
            f.write(
                json.dumps({"id": item.nodeid, "cpu_s": cpu() - c0, "wall_s": time.perf_counter() - t0})
                + "\n"
            )
