"""``--memory``: a budget for the whole process tree, spent on work units in flight, refused in one line when it
cannot hold one (:mod:`terralod.memory`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from terralod.memory import (
    BUILD_UNIT_BYTES,
    PROCESS_BYTES,
    WORKER_PROCESS_BYTES,
    in_memory_samples,
    parse_size,
    plan_memory,
)


@given(st.integers(1, 1 << 20), st.sampled_from(["", "K", "M", "G", "KiB", "MiB", "GiB", "kb", "mb", "g"]),
       st.sampled_from(["", " "]))  # fmt: skip
def test_sizes_read_as_people_write_them(n: int, unit: str, space: str) -> None:
    scale = {"": 1, "k": 1 << 10, "m": 1 << 20, "g": 1 << 30}[unit[:1].lower()]
    assert parse_size(f"{n}{space}{unit}") == n * scale


@pytest.mark.parametrize("text", ["", "lots", "-1G", "0", "2 GiBs", "1e3M", "nan", "2GiB4"])
def test_a_size_that_is_not_one_is_refused(text: str) -> None:
    with pytest.raises(ValueError, match="size"):
        parse_size(text)


@settings(max_examples=200)
@given(st.integers(0, 64 << 30), st.one_of(st.none(), st.integers(1, 64)), st.one_of(st.none(), st.integers(1, 16)),
       st.booleans())  # fmt: skip
def test_a_plan_fits_its_budget_or_is_refused(budget: int, threads: int | None, workers: int | None,
                                              local: bool) -> None:  # fmt: skip
    try:
        plan = plan_memory(budget, threads=threads, dask_workers=workers, dask_local=local)
    except ValueError as exc:
        assert "give at least" in str(exc)
        least = PROCESS_BYTES + BUILD_UNIT_BYTES + (WORKER_PROCESS_BYTES if local else 0)
        assert budget < least
        return
    assert plan.threads >= 1
    if threads is not None:
        assert plan.threads <= threads
    if not local:
        assert plan.dask_workers is None
        assert PROCESS_BYTES + plan.threads * BUILD_UNIT_BYTES <= budget
        return
    assert plan.dask_workers is not None and plan.worker_bytes is not None
    assert 1 <= plan.dask_workers <= (workers or 2)
    assert (
        plan.worker_bytes >= WORKER_PROCESS_BYTES + plan.threads * BUILD_UNIT_BYTES
    )  # each worker holds its units
    assert PROCESS_BYTES + plan.dask_workers * plan.worker_bytes <= budget  # and all of them the budget


def test_more_memory_never_means_fewer_units() -> None:
    sizes = [832 << 20, 1 << 30, 2 << 30, 4 << 30, 16 << 30]
    threads = [plan_memory(b, threads=64).threads for b in sizes]
    assert threads == sorted(threads) and threads[0] == 1 and threads[-1] > 4
    workers = [plan_memory(b, dask_workers=8, dask_local=True).dask_workers for b in sizes[2:]]
    assert workers == sorted(workers) and workers[-1] == 8  # type: ignore[type-var]


def test_a_raster_builds_out_of_core_when_the_budget_cannot_hold_it(tmp_path: Path) -> None:
    import rasterio
    from rasterio.transform import from_origin

    from terralod.cli._windowed import is_large_raster

    p = tmp_path / "dem.tif"
    with rasterio.open(p, "w", driver="GTiff", width=300, height=200, count=1, dtype="float32",
                       crs="EPSG:32610", transform=from_origin(500000, 4100000, 30, 30)) as ds:  # fmt: skip
        ds.write(np.zeros((1, 200, 300), np.float32))
    assert in_memory_samples(PROCESS_BYTES + 27 * 60_000) == 60_000
    assert not is_large_raster(str(p))  # 60,000 samples: in memory at the default 2 GiB
    assert is_large_raster(str(p), PROCESS_BYTES + 27 * 59_999)
    assert not is_large_raster(str(p), PROCESS_BYTES + 27 * 60_000)


def _terralod(args: list[str], capfd: pytest.CaptureFixture[str]) -> tuple[int, str]:
    """The command line in this process (its exit code and what it printed)."""
    from terralod.cli import main

    try:
        main(args)
        code = 0
    except SystemExit as exc:
        code = int(exc.code or 0)
    out = capfd.readouterr()
    return code, out.out + out.err


def test_build_refuses_a_budget_below_one_unit_in_one_line_and_writes_nothing(
    tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    import rasterio
    from rasterio.transform import from_origin

    for i in range(2):
        with rasterio.open(tmp_path / f"t{i}.tif", "w", driver="GTiff", width=64, height=64, count=1,
                           dtype="float32", crs="EPSG:32610",
                           transform=from_origin(500000 + 64 * 30 * i, 4100000, 30, 30)) as ds:  # fmt: skip
            ds.write(np.ones((1, 64, 64), np.float32))
    out = tmp_path / "r.terra"
    code, text = _terralod(["build", str(tmp_path / "t0.tif"), str(tmp_path / "t1.tif"), "-o", str(out),
                            "--memory", "300MiB"], capfd)  # fmt: skip
    assert code == 2
    assert (
        text.strip()
        == "terralod: --memory: 300 MiB cannot hold one process with one work unit: give at least 832 MiB"
    )
    assert not out.exists() and not list(tmp_path.glob(".*"))
    code, text = _terralod(["build", str(tmp_path / "t0.tif"), "-o", str(out), "--memory", "plenty"], capfd)
    assert code == 2 and "expected a size such as 2GiB" in text


def test_a_smaller_budget_builds_the_same_store(tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    """The budget decides the units in flight, never a tile: one unit at a time (900 MiB) gives the default
    budget's tiles byte for byte."""
    import sqlite3

    import rasterio
    from rasterio.transform import from_origin

    rng = np.random.default_rng(5)
    z = np.cumsum(np.cumsum(rng.normal(size=(96, 160)), axis=0), axis=1).astype(np.float32)
    for i in range(2):
        with rasterio.open(tmp_path / f"t{i}.tif", "w", driver="GTiff", width=81, height=96, count=1,
                           dtype="float32", crs="EPSG:32610",
                           transform=from_origin(500000 + 79 * 30 * i, 4100000, 30, 30)) as ds:  # fmt: skip
            ds.write(z[None, :, 79 * i : 79 * i + 81])
    blobs = []
    for name, memory in (("a", []), ("b", ["--memory", "900MiB"])):
        out = tmp_path / f"{name}.terra"
        code, text = _terralod(["build", str(tmp_path / "t0.tif"), str(tmp_path / "t1.tif"), "-o", str(out),
                                *memory], capfd)  # fmt: skip
        assert code == 0, text
        with sqlite3.connect(out) as db:
            blobs.append(db.execute("SELECT * FROM tiles ORDER BY 1, 2, 3").fetchall())
    assert blobs[0] and blobs[0] == blobs[1]


def test_export_plans_its_dask_workers_within_the_budget(
    tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    """An export's unit is a batch of tiles: a budget below one process and one batch is refused in one line
    before anything is written; a local cluster gets the workers and memory limits the budget holds."""
    from terralod.cli.export import _dask_plan
    from terralod.memory import EXPORT_UNIT_BYTES

    code, text = _terralod(["export", str(tmp_path / "none.tif"), "--format", "quantized-mesh", "-o",
                            str(tmp_path / "o"), "--memory", "300MiB"], capfd)  # fmt: skip
    assert code == 2 and text.strip().startswith("terralod: --memory: 300 MiB cannot hold")
    assert not (tmp_path / "o").exists()
    assert _dask_plan(None, None, None)[1:] == (None, None)
    address, workers, limit = _dask_plan("local", 4, 1 << 30)
    assert address == "local" and workers == 1 and limit >= WORKER_PROCESS_BYTES + EXPORT_UNIT_BYTES
    _, workers, limit = _dask_plan("local", 4, 4 << 30)
    assert workers == 4 and PROCESS_BYTES + 4 * limit <= 4 << 30
