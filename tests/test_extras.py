"""The core without its extras (issue 46): every module imports and the core commands run with the extras'
modules blocked (a meta-path finder that refuses them, so nothing is uninstalled), and each command that
needs an extra says which one in one line, exit 2, nothing written."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from terralod.cli._errors import EXTRAS

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "change"
BEFORE = DATA / "st_helens_crater_2000-09-25_10m.tif"
AFTER = DATA / "st_helens_crater_2007-07-05_10m.tif"
needs_data = pytest.mark.skipif(not BEFORE.exists(), reason="../shared/data (St Helens pair) is absent")

#: What each extra brings (its own modules and the ones they pull in), blocked when the extra is "absent".
BRINGS = {
    "web": {"pyproj", "pygltflib", "pydelatin"},
    "change": {"xdem", "geoutils", "geopandas", "shapely", "pyproj"},
    "dask": {"dask", "distributed"},
    "window": {"glfw"},
}
#: Benchmark peers, never needed by terralod itself.
PEERS = {"quantized_mesh_encoder", "pymartini", "pyfqmr", "fast_simplification", "psutil"}
ALL_EXTRA_MODULES = set().union(*BRINGS.values()) | PEERS

PRELUDE = """
import importlib.abc, sys
BLOCKED = set({blocked!r})
class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path, target=None):
        if name.split(".")[0] in BLOCKED:
            raise ModuleNotFoundError(f"No module named {{name!r}} (blocked by the test)", name=name)
        return None
sys.meta_path.insert(0, Block())
for m in list(sys.modules):
    if m.split(".")[0] in BLOCKED:
        del sys.modules[m]
"""


def run_blocked(code: str, blocked: set[str], cwd: Path) -> subprocess.CompletedProcess[str]:
    src = PRELUDE.format(blocked=sorted(blocked)) + textwrap.dedent(code)
    return subprocess.run([sys.executable, "-c", src], capture_output=True, text=True, cwd=cwd, timeout=600)


def cli_blocked(args: list[str], blocked: set[str], cwd: Path) -> subprocess.CompletedProcess[str]:
    return run_blocked(f"from terralod.cli import main\nmain({args!r})", blocked, cwd)


def test_extras_table_matches_pyproject() -> None:
    """The modules the CLI checks are the ones the extras of pyproject install (by distribution name)."""
    import tomllib

    meta = tomllib.loads((Path(__file__).resolve().parents[1] / "pyproject.toml").read_text())
    opt = meta["project"]["optional-dependencies"]
    for extra, modules in EXTRAS.items():
        dists = {r.split(">")[0].split("[")[0].split("=")[0].strip().lower() for r in opt[extra]}
        assert set(modules) <= dists, (extra, modules, dists)
    core = " ".join(meta["project"]["dependencies"]).lower()
    for mod in ALL_EXTRA_MODULES:
        assert mod.replace("_", "-") not in core, f"{mod} is a core dependency"
    assert set(opt["all"]) == {"terralod[web,change,dask,window]"}


def test_every_module_and_help_without_extras(tmp_path: Path) -> None:
    code = """
    import importlib, json, pkgutil
    import terralod
    for probe in sorted(BLOCKED):
        try:
            importlib.import_module(probe)
        except ImportError:
            pass
        else:
            raise SystemExit(f"{probe} was not blocked")
    failed = {}
    for m in pkgutil.walk_packages(terralod.__path__, "terralod."):
        if m.name.endswith("__main__"):
            continue
        try:
            importlib.import_module(m.name)
        except Exception as exc:
            failed[m.name] = repr(exc)
    from click.testing import CliRunner
    from terralod.cli import COMMANDS, cli
    helps = {}
    for _module, name in COMMANDS:
        r = CliRunner().invoke(cli, [name, "--help"])
        helps[name] = (r.exit_code, r.output[-200:])
    print(json.dumps({"failed": failed, "helps": helps, "n": len(COMMANDS)}))
    """
    r = run_blocked(code, ALL_EXTRA_MODULES, tmp_path)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert out["failed"] == {}
    assert out["n"] >= 15
    assert all(code == 0 for code, _ in out["helps"].values()), out["helps"]


@needs_data
def test_core_commands_run_without_extras(tmp_path: Path) -> None:
    store = tmp_path / "sh.terra"
    r = cli_blocked(["info", str(BEFORE)], ALL_EXTRA_MODULES, tmp_path)
    assert r.returncode == 0, r.stderr
    assert "-122." in r.stdout  # lon/lat bounds without pyproj (rasterio's PROJ)
    r = cli_blocked(["build", str(BEFORE), "-o", str(store)], ALL_EXTRA_MODULES, tmp_path)
    assert r.returncode == 0, r.stderr
    r = cli_blocked(["update", str(store), str(AFTER), "--epoch", "2007-07-05"], ALL_EXTRA_MODULES, tmp_path)
    assert r.returncode == 0, r.stderr
    r = cli_blocked(["check", str(store)], ALL_EXTRA_MODULES, tmp_path)
    assert r.returncode == 0 and "sound" in r.stdout, r.stdout + r.stderr
    png = tmp_path / "r.png"
    r = cli_blocked(["render", str(store), "-o", str(png), "--size", "160x90"], ALL_EXTRA_MODULES, tmp_path)
    assert r.returncode == 0, r.stderr
    assert png.stat().st_size > 0


def _commands(tmp_path: Path) -> dict[str, tuple[list[str], str, Path]]:
    """extra -> (arguments of a command that needs it, the command's words, its output)."""
    store = tmp_path / "sh.terra"
    return {
        "change": (
            ["change", str(BEFORE), str(AFTER), "-o", str(tmp_path / "chg")],
            "change",
            tmp_path / "chg",
        ),
        "web": (
            ["export", str(store), "--format", "3dtiles", "-o", str(tmp_path / "t3d")],
            "export",
            tmp_path / "t3d",
        ),
        "dask": (
            ["build", str(BEFORE), "-o", str(tmp_path / "d.terra"), "--dask", "local", "--dask-workers", "1"],
            "build --dask",
            tmp_path / "d.terra",
        ),
        "window": (["view", str(store)], "view", tmp_path / "nothing"),
    }


@needs_data
@pytest.mark.parametrize("extra", sorted(BRINGS))
def test_missing_extra_is_one_line(tmp_path: Path, extra: str) -> None:
    from terralod.io.reader import read_heightfield
    from terralod.pyramid.builder import build_store

    build_store(read_heightfield(str(BEFORE)), tmp_path / "sh.terra", tile_size=33)
    args, words, out = _commands(tmp_path)[extra]
    r = cli_blocked(args, BRINGS[extra], tmp_path)
    assert r.returncode == 2
    assert r.stderr.strip() == f"terralod {words} needs the {extra} extra: pip install 'terralod[{extra}]'"
    assert not out.exists()
    if extra == "web":  # serve too
        r = cli_blocked(["serve", str(tmp_path / "sh.terra"), "--port", "0"], BRINGS[extra], tmp_path)
        assert (r.returncode, r.stderr.strip()) == (
            2,
            "terralod serve needs the web extra: pip install 'terralod[web]'",
        )


@needs_data
@pytest.mark.parametrize("extra", ["change", "web"])
def test_each_extra_alone(tmp_path: Path, extra: str) -> None:
    """With one extra and none of the others, its command runs to the end."""
    from terralod.io.reader import read_heightfield
    from terralod.pyramid.builder import build_store

    build_store(read_heightfield(str(BEFORE)), tmp_path / "sh.terra", tile_size=33)
    args, _, out = _commands(tmp_path)[extra]
    r = cli_blocked(args, ALL_EXTRA_MODULES - BRINGS[extra], tmp_path)
    assert r.returncode == 0, r.stderr
    assert out.is_dir() and any(out.iterdir())
