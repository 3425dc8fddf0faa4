"""Fuzzed readers (a bounded number of cases; the long campaign is ``python benchmarks/fuzz.py --minutes N``):
every reader — GeoTIFF/COG, PNG/Terrain-RGB/Terrarium/WebP, .npy/.npz, LAS/LAZ, .terra (grid and TIN),
the detail-increment file — and the store decoder given mutated bytes and absurd headers returns a result
or raises a one-line TerralodError naming the file: no other exception, no hang, no crash. The command
line turns such a failure into one line and exit code 2, with or without -v.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

import fuzzing
from terralod.errors import TerralodError
from terralod.store import decode_triangles, decode_vertices

from conftest import terralod_cli

#: Cases per reader in the suite (derandomized: the same cases on every run).
EXAMPLES = 12


@pytest.fixture(scope="module")
def seeds(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    return fuzzing.make_seeds(tmp_path_factory.mktemp("seeds"))


def test_seeds_are_read(seeds: dict[str, Path], tmp_path: Path) -> None:
    """The unmutated seeds are valid (else the fuzzing would only exercise the first check)."""
    for target, p in seeds.items():
        fuzzing.READERS[target](p)


def test_every_reader_under_mutation(seeds: dict[str, Path], tmp_path: Path) -> None:
    res = fuzzing.run_campaign(seeds, tmp_path, EXAMPLES, timeout_s=600)
    assert "_crash" not in res, res.get("_crash")
    failures = {t: r["failures"] for t, r in res.items() if r["failures"]}
    assert not failures, failures
    assert set(res) == set(seeds) and all(r["cases"] >= EXAMPLES for r in res.values())


@given(blob=st.binary(max_size=200), n=st.integers(-5, 1 << 30))
@settings(max_examples=60, deadline=None)
def test_tile_decoders_never_raise_beyond_value_error(blob: bytes, n: int) -> None:
    """Absurd counts and bytes: the decoders raise ValueError/zlib.error (mapped to CorruptStoreError by the
    store), never allocate by the claimed count."""
    import zlib

    for fn in (decode_vertices, decode_triangles):
        try:
            fn(blob, n)
        except (ValueError, zlib.error):
            pass


@given(q=hnp.arrays(np.uint16, st.tuples(st.integers(1, 50), st.just(3))), k=st.integers(0, 3))
@settings(max_examples=30, deadline=None)
def test_decoders_refuse_wrong_counts(q: np.ndarray, k: int) -> None:
    from terralod.store import encode_vertices

    blob = encode_vertices(q)
    with pytest.raises(ValueError):
        decode_vertices(blob, len(q) + 1 + k)


def _cli(*args: str) -> subprocess.CompletedProcess:
    """``terralod ARGS`` in this process (tests/conftest.py ``terralod_cli``)."""
    return terralod_cli(*args)


def test_cli_one_line_with_and_without_verbose(seeds: dict[str, Path], tmp_path: Path) -> None:
    bad = tmp_path / "cut.tif"
    bad.write_bytes(seeds["cog"].read_bytes()[:900])
    p = _cli("info", str(bad))
    lines = [ln for ln in p.stderr.splitlines() if ln.strip()]
    assert p.returncode == 2 and len(lines) == 1 and lines[0].startswith(f"terralod: {bad}: "), p.stderr
    assert "previous exception" not in lines[0]
    v = _cli("-v", "info", str(bad))  # -v only adds detail: the traceback, then the same line, exit 2
    assert v.returncode == 2 and v.stderr.strip().splitlines()[-1] == lines[0], v.stderr


def test_mutated_store_detected_by_check(seeds: dict[str, Path], tmp_path: Path) -> None:
    """A changed digit of the metadata (the quantisation) is a checksum failure, not wrong coordinates."""
    import sqlite3

    from terralod.integrity import check_store
    from terralod.store import open_store

    p = tmp_path / "m.terra"
    p.write_bytes(seeds["terra"].read_bytes())
    con = sqlite3.connect(p)
    v = con.execute("SELECT value FROM meta WHERE key = 'quantisation'").fetchone()[0]
    changed = v.replace('"xy_frac_bits": 1', '"xy_frac_bits": 2', 1)
    assert changed != v
    con.execute("UPDATE meta SET value = ? WHERE key = 'quantisation'", (changed,))
    con.commit()
    con.close()
    with pytest.raises(TerralodError, match="metadata fails its checksum"):
        open_store(p)
    rep = check_store(p)
    assert not rep.sound and "checksum" in rep.problems[0]


#: A LAZ file found by atheris (mutated from the synthetic seed): lazrs aborts the process decoding its
#: points when the address space is limited (as the campaign limits it, 3 GiB).
LAZ_ABORT = Path(__file__).parent / "golden" / "fuzz_laz_lazrs_abort.laz"


@pytest.mark.parametrize("handler", ["default", "host_handler"])
def test_laz_decoder_abort_is_one_line(tmp_path: Path, handler: str) -> None:
    """The LAZ decoder's abort stays in the forked probe and becomes one line, also when the host process
    has its own SIGABRT handler (a fuzzer's crash reporter, faulthandler), which the probe must not run."""
    code = (
        "import os, resource, signal, sys\n"
        "resource.setrlimit(resource.RLIMIT_AS, (3 << 30, 3 << 30))\n"
        # a C-level handler, as libFuzzer's: SIGABRT calls _exit(6), so the process exits instead of dying
        + (
            "import ctypes\nlibc = ctypes.CDLL(None)\nlibc.signal(signal.SIGABRT, libc._exit)\n"
            if handler == "host_handler"
            else ""
        )  # fmt: skip
        + "from terralod.errors import TerralodError\n"
        "from terralod.tin.pointcloud import read_las\n"
        "try:\n"
        f"    read_las({str(LAZ_ABORT)!r})\n"
        "except TerralodError as exc:\n"
        "    print('ONE LINE:', exc)\n"
    )
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, (p.returncode, p.stderr[-2000:])
    assert "ONE LINE:" in p.stdout and "fuzz_laz_lazrs_abort.laz" in p.stdout, p.stdout


def test_npz_crs_with_an_impossible_code_point_is_one_line(tmp_path: Path) -> None:
    """Found by atheris: a .npz whose ``crs`` string holds a code point beyond U+10FFFF (numpy's UCS-4
    allows it) made rasterio raise SystemError; now one line."""
    from terralod import read_heightfield

    good = np.array("EPSG:32610")
    raw = bytearray(good.tobytes())
    raw[20:24] = (0x110000).to_bytes(4, "little")
    crs = np.frombuffer(bytes(raw), dtype=good.dtype).reshape(())
    p = tmp_path / "bad_crs.npz"
    np.savez(p, elevation=np.full((8, 8), 100.0, np.float32), transform=np.array([5e5, 30, 0, 5.2e6, 0, -30.0]),
             crs=crs)  # fmt: skip
    with pytest.raises(TerralodError, match="bad_crs.npz: CRS .* is not understood"):
        read_heightfield(p)
