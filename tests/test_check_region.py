"""``terralod check`` on a region of DEM files: every file read whole, every problem named (not only the
first), exit 0 when sound and 2 otherwise; a store is checked as before."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest


def _tile(path: Path, lon: int, lat: int, n: int = 121, fill: float | None = None) -> Path:
    import rasterio
    from rasterio.transform import from_origin

    d = 1.0 / (n - 1)
    y, x = np.mgrid[0:n, 0:n]
    z = (500 + 40 * np.sin((x + lon * (n - 1)) / 9.0) + 30 * np.cos((y - lat * (n - 1)) / 7.0)).astype(
        np.int16
    )
    if fill is not None:
        z[:] = fill
    with rasterio.open(path, "w", driver="GTiff", width=n, height=n, count=1, dtype="int16", crs="EPSG:4326",
                       transform=from_origin(lon - d / 2, lat + 1 + d / 2, d, d), nodata=-32768, tiled=True,
                       blockxsize=32, blockysize=32, compress="deflate") as ds:  # fmt: skip
        ds.write(z, 1)
    return path


def _check(args: list[str], capfd: pytest.CaptureFixture[str]) -> tuple[int, str]:
    from terralod.cli import main

    try:
        main(["check", *args])
        code = 0
    except SystemExit as exc:
        code = int(exc.code or 0)
    out = capfd.readouterr()
    return code, out.out + out.err


def test_a_sound_region_in_every_form(tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    d = tmp_path / "tiles"
    d.mkdir()
    files = [_tile(d / f"N{lat}E00{lon}.tif", lon, lat) for lat in (41, 42) for lon in (1, 2)]
    for args in ([str(d)], [str(d / "*.tif")], [str(f) for f in files]):
        code, text = _check(args, capfd)
        assert code == 0, text
        assert "region of 4 DEM file(s)" in text and "4 of 4 file(s) read whole" in text
        assert "one grid: 241 x 241 samples" in text and text.strip().endswith("verdict: sound")
    code, text = _check([str(d), "--json"], capfd)
    rep = json.loads(text)
    assert code == 0 and rep["sound"] and rep["files"] == 4 and rep["samples"] == 241 * 241
    assert rep["valid_in_files"] == 4 * 121 * 121  # every sample of every file read


def test_every_problem_is_named_not_only_the_first(tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    d = tmp_path / "tiles"
    d.mkdir()
    files = [_tile(d / f"N{lat}E00{lon}.tif", lon, lat) for lat in (41, 42) for lon in (1, 2)]
    for bad in (files[1], files[3]):  # their tiles' compressed bytes garbled
        data = bytearray(bad.read_bytes())
        data[len(data) // 2 :] = b"\x5a" * (len(data) - len(data) // 2)
        bad.write_bytes(bytes(data))
    _tile(files[0], 1, 41, fill=-32768)  # all nodata
    code, text = _check([str(d)], capfd)
    assert code == 2
    problems = [line for line in text.splitlines() if line.strip().startswith("problem:")]
    assert len(problems) == 3, text
    assert any(str(files[1]) in p and "cannot be read" in p for p in problems)
    assert any(str(files[3]) in p and "cannot be read" in p for p in problems)
    assert any(str(files[0]) in p and "no valid samples" in p for p in problems)
    assert "verdict: 3 problems" in text


def test_files_off_one_grid_are_a_problem_naming_both(
    tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    a = _tile(tmp_path / "a.tif", 1, 41)
    b = _tile(tmp_path / "b.tif", 2, 41, n=61)  # another resolution
    code, text = _check([str(a), str(b)], capfd)
    assert code == 2 and str(a) in text and str(b) in text and "verdict: 1 problem" in text


def test_a_store_is_still_checked_as_a_store(tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    code, text = _check([str(tmp_path / "missing.terra")], capfd)
    assert code == 2 and "store not found" in text
    code, text = _check([str(tmp_path), "--repair"], capfd)
    assert code == 2 and "--repair and --upgrade are for a store" in text
