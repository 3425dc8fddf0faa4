"""House rules a user meets: validation that survives ``python -O``, and a bug reported as the internal
error it is (a ``RuntimeError`` is not a user mistake), while a missing display stays one plain line."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import click
import numpy as np
import pytest


def _geotiff(path: Path) -> Path:
    import rasterio
    from rasterio.transform import from_origin

    z = np.add.outer(np.arange(40.0), np.arange(50.0)).astype(np.float32)
    with rasterio.open(path, "w", driver="GTiff", width=50, height=40, count=1, dtype="float32",
                       crs="EPSG:32633", transform=from_origin(500000.0, 4600000.0, 30.0, 30.0)) as ds:  # fmt: skip
        ds.write(z, 1)
    return path


def _terralod_optimised(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    """The CLI under ``python -O``: asserts are gone, validation must not be."""
    return subprocess.run([sys.executable, "-O", "-m", "terralod", *args], capture_output=True, text=True,
                          cwd=cwd, timeout=600)  # fmt: skip


@pytest.mark.parametrize(
    ("args", "expect"),
    [
        (["render", "{dem}", "-o", "x.png", "--size", "5x5"], "expected WIDTHxHEIGHT"),
        (["render", "{dem}", "-o", "x.png", "--background", "1,2"], "expected R,G,B"),
        (["build", "{dem}", "-o", "x.terra", "--tile", "3/4"], "expected Z/X/Y"),
    ],
)
def test_cli_validation_holds_under_python_O(tmp_path: Path, args: list[str], expect: str) -> None:
    dem = _geotiff(tmp_path / "dem.tif")
    r = _terralod_optimised(*(a.replace("{dem}", str(dem)) for a in args), cwd=tmp_path)
    assert r.returncode == 2, r.stdout + r.stderr
    assert expect in r.stderr, r.stderr
    assert not (tmp_path / "x.png").exists()


def test_cli_info_runs_under_python_O(tmp_path: Path) -> None:
    dem = _geotiff(tmp_path / "dem.tif")
    r = _terralod_optimised("info", str(dem), cwd=tmp_path)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "32633" in r.stdout


def _group_raising(exc: BaseException) -> click.Group:
    @click.group()
    def g() -> None:
        pass

    @g.command()
    def boom() -> None:
        raise exc

    return g


def test_a_runtime_error_is_reported_as_an_internal_error(capsys: pytest.CaptureFixture[str]) -> None:
    from terralod.cli._errors import run_main

    with pytest.raises(SystemExit) as e:
        run_main(_group_raising(RuntimeError("5 samples fall outside every triangle of the tile")), ["boom"])
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "internal error" in err[0] and "report" in err[0], err


def test_a_missing_display_is_one_plain_line(capsys: pytest.CaptureFixture[str]) -> None:
    from terralod.cli._errors import run_main
    from terralod.errors import DisplayError

    with pytest.raises(SystemExit) as e:
        run_main(_group_raising(DisplayError("glfw could not open a window")), ["boom"])
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["terralod: glfw could not open a window"], err
