"""Kill -9 at a hypothesis-chosen tile of a region's commands, then run it again with resume: it finishes
without redoing the finished tiles, and the result is byte for byte the uninterrupted run's.

The region is 2 x 2 small EPSG:4326 GeoTIFFs sharing their middle row and column (with a nodata void), as
in tests/test_region_build.py. The command runs in a forked child that kills itself (SIGKILL) from its
progress callback once the drawn number of tiles is done (tests/test_kill.py's ``_killed``).
"""

from __future__ import annotations

import hashlib
import os
import signal
import tempfile
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from test_kill import _killed
from test_region_build import BUILD, _merged, _quarters, _rows

pytestmark = pytest.mark.skipif(not hasattr(os, "fork"), reason="kill tests fork the command (POSIX only)")
pytest.importorskip("pydelatin")
pytest.importorskip("pyproj")

KILLS = settings(max_examples=4, deadline=None, derandomize=True, database=None,
                 suppress_health_check=[HealthCheck.function_scoped_fixture])  # fmt: skip


def _tree(d: Path) -> dict[str, str]:
    return {f.relative_to(d).as_posix(): hashlib.sha256(f.read_bytes()).hexdigest()
            for f in sorted(d.rglob("*")) if f.is_file()}  # fmt: skip


@pytest.fixture(scope="module")
def region(tmp_path_factory: pytest.TempPathFactory) -> dict:
    from terralod.export.quantized_mesh import export_quantized_mesh
    from terralod.export.source import source_from_region
    from terralod.io.windowed import open_source
    from terralod.pyramid.distributed import build_store_windowed

    d = tmp_path_factory.mktemp("kill_region")
    tiles = _quarters(_merged(d / "merged.tif"), d / "tiles")
    rep = export_quantized_mesh(source_from_region(tiles), d / "want")
    ref = d / "ref.terra"
    build_store_windowed(open_source(tiles), ref, **{**BUILD, "workers": 1})
    return {"tiles": tiles, "want": _tree(d / "want"), "tiles_total": rep.tiles, "ref_rows": _rows(ref)}


def _die_at(n: int):  # noqa: ANN202
    def cb(done: int, _total: int) -> None:
        if done >= n:
            os.kill(os.getpid(), signal.SIGKILL)

    return cb


@KILLS
@given(at=st.floats(0.0, 1.0))
def test_region_export_killed_anywhere_resumes_to_the_same_bytes(region: dict, at: float) -> None:
    from terralod.export.quantized_mesh import export_quantized_mesh
    from terralod.export.source import source_from_region

    tiles, total = region["tiles"], region["tiles_total"]
    n = 1 + round(at * (total - 2))  # a tile count in [1, total - 1]
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "out"
        _killed(lambda: export_quantized_mesh(source_from_region(tiles), out, progress=_die_at(n)))
        assert not out.exists()  # nothing under the output's name
        work = Path(tmp) / ".out.work" / "out"
        kept = {f.relative_to(work).as_posix(): f.stat().st_ino for f in work.rglob("*.terrain")}
        assert n <= len(kept) <= n + 1  # each tile finished before the kill, maybe the one in hand
        rep = export_quantized_mesh(source_from_region(tiles), out, resume=True)
        assert rep.extra["resumed"] and _tree(out) == region["want"]  # the uninterrupted bytes
        redone = [f for f, ino in kept.items() if (out / f).stat().st_ino != ino]
        assert len(redone) <= 1  # the finished tiles were kept (one written but not journaled at most)
        assert rep.extra["encoded"] == total - len(kept) + len(redone)


@KILLS
@given(at=st.floats(0.0, 1.0))
def test_region_build_killed_anywhere_resumes_to_the_same_store(region: dict, at: float) -> None:
    from terralod.io.windowed import open_source
    from terralod.pyramid.distributed import build_store_windowed

    tiles, ref_rows = region["tiles"], region["ref_rows"]
    total = len(ref_rows)
    n = 1 + round(at * (total - 2))
    build = {**BUILD, "workers": 1}
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "killed.terra"
        _killed(lambda: build_store_windowed(open_source(tiles), out, progress=_die_at(n), **build))
        partial = len(_rows(out)) if out.exists() else 0
        assert partial <= total  # killed at the last tile, every tile may be committed, not the flag
        rep = build_store_windowed(open_source(tiles), out, resume=True, **build)
        assert rep.tiles_skipped == partial  # the committed tiles were not made again
        assert rep.tiles_built + rep.tiles_skipped == total
        assert _rows(out) == ref_rows
