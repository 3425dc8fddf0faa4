"""Fuzzing harness shared by ``benchmarks/fuzz.py`` (the long campaign) and ``tests/test_fuzz.py`` (a
bounded number of cases): valid seed files of every reader, byte mutations drawn by hypothesis (bit flips,
truncation, splices, absurd header integers), and the contract each reader must keep.

Contract: a reader given any bytes returns a result or raises a :class:`terralod.errors.TerralodError`
(one line naming the file at the CLI) — never another exception, a hang or a crash. Cases run in a child
process with a memory limit (``RLIMIT_AS``) so an absurd header that made a reader allocate without bound
shows up as a failure instead of taking the machine down, and a crash (signal) as a failure with its case.
"""

from __future__ import annotations

import json
import math
import os
import resource
import signal
import struct
import sys
import tempfile
import threading
import time
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

#: Absurd integers written into headers (little and big endian, 2/4/8 bytes).
ABSURD = (0, 1, 2, 3, 0x7F, 0xFF, 0x7FFF, 0xFFFF, 0x7FFFFFFF, 0xFFFFFFFF, 2**31, 65537, 2**40 + 1)
#: Seconds a case may take before it counts as a hang.
CASE_TIMEOUT_S = 60
#: Memory a fuzz case may use (bytes) before the reader is deemed to allocate without bound.
MEMORY_LIMIT = 3 << 30


# -- seeds ---------------------------------------------------------------------------------------------
def _terrain(h: int = 24, w: int = 28, seed: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:h, 0:w]
    return (100.0 + 20.0 * np.sin(x / 5.0) * np.cos(y / 4.0) + rng.normal(0, 0.5, (h, w))).astype(np.float32)


def make_seeds(folder: Path) -> dict[str, Path]:
    """One small valid file per reader (target name → path)."""
    import laspy
    import rasterio
    from PIL import Image
    from rasterio.transform import from_origin

    from terralod import Heightfield, build_store
    from terralod.io.encodings import encode_terrain_rgb, encode_terrarium
    from terralod.tin import DetailIncrementModel
    from terralod.tin.terra import save_model_to_store

    folder.mkdir(parents=True, exist_ok=True)
    z = _terrain()
    seeds: dict[str, Path] = {}
    prof = dict(driver="GTiff", width=z.shape[1], height=z.shape[0], count=1, dtype="float32",
                crs="EPSG:32610", transform=from_origin(500000, 5200000, 30, 30), nodata=-9999.0)  # fmt: skip
    with rasterio.open(folder / "seed.tif", "w", **prof) as ds:
        ds.write(z, 1)
    seeds["geotiff"] = folder / "seed.tif"
    with rasterio.open(folder / "seed_cog.tif", "w", **{**prof, "tiled": True, "blockxsize": 16,
                       "blockysize": 16, "compress": "deflate"}) as ds:  # fmt: skip
        ds.write(z, 1)
    seeds["cog"] = folder / "seed_cog.tif"
    Image.fromarray((z * 100).astype(np.uint16)).save(folder / "seed_grey.png")
    seeds["png"] = folder / "seed_grey.png"
    Image.fromarray(encode_terrain_rgb(z)).save(folder / "seed_rgb.png")
    seeds["terrain-rgb"] = folder / "seed_rgb.png"
    Image.fromarray(encode_terrarium(z)).save(folder / "seed_terrarium.png")
    seeds["terrarium"] = folder / "seed_terrarium.png"
    Image.fromarray(encode_terrarium(z)).save(folder / "seed_terrarium.webp", lossless=True)
    seeds["webp"] = folder / "seed_terrarium.webp"
    np.save(folder / "seed.npy", z)
    seeds["npy"] = folder / "seed.npy"
    np.savez(folder / "seed.npz", elevation=z, transform=np.array([500000, 30, 0, 5200000, 0, -30.0]),
             crs=np.array("EPSG:32610"))  # fmt: skip
    seeds["npz"] = folder / "seed.npz"
    las = laspy.create(point_format=3, file_version="1.2")
    rng = np.random.default_rng(3)
    n = 300
    las.header.scales = [0.01, 0.01, 0.01]
    las.header.offsets = [0.0, 0.0, 0.0]
    las.x = rng.uniform(0, 100, n)
    las.y = rng.uniform(0, 100, n)
    las.z = 50 + np.sin(np.asarray(las.x) / 10.0) * 5
    las.classification = np.full(n, 2, np.uint8)
    las.write(folder / "seed.las")
    seeds["las"] = folder / "seed.las"
    try:
        las.write(folder / "seed.laz")
        seeds["laz"] = folder / "seed.laz"
    except Exception:  # noqa: BLE001 - no LAZ backend: the LAS target still runs
        pass
    hf = Heightfield.from_array(z.astype(np.float64), 30.0)
    build_store(hf, folder / "seed.terra", tile_size=9, workers=1)
    seeds["terra"] = folder / "seed.terra"
    model = DetailIncrementModel.from_heightfield(hf, sub_blocks=1, base_fraction=0.3)
    model.save(folder / "seed.tdim")
    seeds["increments"] = folder / "seed.tdim"
    save_model_to_store(model, folder / "seed_tin.terra")
    seeds["tin-terra"] = folder / "seed_tin.terra"
    return seeds


# -- readers -------------------------------------------------------------------------------------------
def _read_dem(**kw: Any) -> Callable[[Path], Any]:
    def run(p: Path) -> Any:
        from terralod.io.reader import read_heightfield

        return read_heightfield(p, **kw)

    return run


def _read_las(p: Path) -> Any:
    from terralod.tin.pointcloud import describe_las, read_las

    describe_las(p)
    return read_las(p)


def _read_store(p: Path) -> Any:
    """Open, decode every tile, and run the whole check (which must report, never raise)."""
    from terralod.errors import TerralodError
    from terralod.integrity import check_store
    from terralod.store import open_store

    check_store(p)
    with open_store(p) as s:
        for c in s.tile_codes():
            try:
                s.tile(*c)
            except (TerralodError, KeyError):  # KeyError: the documented answer for a tile not stored
                pass


def _read_tin_store(p: Path) -> Any:
    from terralod.integrity import check_store
    from terralod.tin.terra import load_model_from_store

    check_store(p)
    return load_model_from_store(p)


def _read_increments(p: Path) -> Any:
    from terralod.tin import DetailIncrementModel

    return DetailIncrementModel.load(p)


READERS: dict[str, Callable[[Path], Any]] = {
    "geotiff": _read_dem(),
    "cog": _read_dem(),
    "png": _read_dem(spacing_m=10.0),
    "terrain-rgb": _read_dem(spacing_m=10.0, encoding="terrain-rgb"),
    "terrarium": _read_dem(spacing_m=10.0, encoding="terrarium"),
    "webp": _read_dem(spacing_m=10.0, encoding="terrarium"),
    "npy": _read_dem(spacing_m=10.0),
    "npz": _read_dem(),
    "las": _read_las,
    "laz": _read_las,
    "terra": _read_store,
    "tin-terra": _read_tin_store,
    "increments": _read_increments,
}


# -- mutations -----------------------------------------------------------------------------------------
def mutation_strategy(seed: bytes):
    """A hypothesis strategy of byte strings derived from ``seed`` by 1-4 mutations."""
    from hypothesis import strategies as st

    n = len(seed)
    flip = st.tuples(st.just("flip"), st.integers(0, n - 1), st.integers(1, 255))
    cut = st.tuples(st.just("cut"), st.integers(0, n - 1), st.just(0))
    splice = st.tuples(st.just("splice"), st.integers(0, n), st.binary(min_size=1, max_size=64))
    absurd = st.tuples(
        st.just("int"), st.integers(0, min(n - 1, 1024)),
        st.tuples(st.sampled_from(ABSURD), st.sampled_from(["<H", ">H", "<I", ">I", "<Q", ">Q"])),
    )  # fmt: skip
    ops = st.lists(st.one_of(flip, cut, splice, absurd), min_size=1, max_size=4)
    return ops.map(lambda o: apply_mutations(seed, o))


def apply_mutations(seed: bytes, ops: list[tuple[str, int, Any]]) -> bytes:
    b = bytearray(seed)
    for op, pos, arg in ops:
        pos = min(pos, max(len(b) - 1, 0))
        if op == "flip" and b:
            b[pos] ^= arg
        elif op == "cut":
            del b[pos:]
        elif op == "splice":
            b[pos:pos] = arg
        elif op == "int" and b:
            value, fmt = arg
            raw = struct.pack(fmt, value & ((1 << (8 * struct.calcsize(fmt))) - 1))
            b[pos : pos + len(raw)] = raw
    return bytes(b)


# -- running cases -------------------------------------------------------------------------------------
def run_case(target: str, data: bytes, folder: Path, suffix: str) -> str | None:
    """Write ``data`` and read it with ``target``'s reader in this process; None when the contract held,
    else the unexpected exception with its traceback's last lines."""
    from terralod.errors import TerralodError

    p = folder / f"case{suffix}"
    for side in ("", "-wal", "-shm", "-journal"):
        Path(f"{p}{side}").unlink(missing_ok=True)
    p.write_bytes(data)
    alarm = hasattr(signal, "SIGALRM") and threading.current_thread() is threading.main_thread()
    if alarm:
        signal.signal(signal.SIGALRM, _hung)
        signal.alarm(CASE_TIMEOUT_S)
    try:
        READERS[target](p)
    except CaseHung:
        return f"hang: no answer within {CASE_TIMEOUT_S} s"
    except TerralodError as exc:
        if "\n" in str(exc) or not str(exc).startswith(str(p)):
            return f"TerralodError not one line naming the file: {str(exc)[:300]!r}"
        return None
    except (KeyboardInterrupt, SystemExit):
        raise
    except BaseException as exc:  # noqa: BLE001 - this is what the fuzzing is looking for (pyo3 panics too)
        tb = traceback.format_exception(type(exc), exc, exc.__traceback__)
        return f"{type(exc).__name__}: {str(exc)[:200]} | " + "".join(tb[-3:]).replace("\n", " ")[:600]
    finally:
        if alarm:
            signal.alarm(0)
    return None


class CaseHung(BaseException):
    """Raised by the alarm in a case that takes longer than :data:`CASE_TIMEOUT_S` (a hang)."""


def _hung(signum: int, frame: Any) -> None:
    raise CaseHung()


def _make_case(
    target: str, stats: dict, work: Path, suffix: str, seed: bytes, spec: dict
) -> Callable[[], None]:
    from hypothesis import HealthCheck, given, settings

    @settings(max_examples=spec["examples"], deadline=None, database=None,
              derandomize=spec.get("derandomize", True), suppress_health_check=list(HealthCheck))  # fmt: skip
    @given(data=mutation_strategy(seed))
    def case(data: bytes) -> None:
        if time.time() > spec.get("t_end", math.inf):  # the campaign's time is up: the rest are skipped
            return
        stats["cases"] += 1
        bad = run_case(target, data, work, suffix)
        if bad and len(stats["failures"]) < 5:
            stats["failures"].append(bad)

    return case


def child_main(spec_path: str) -> None:
    """Child process: run hypothesis over the targets in the spec JSON, write the results JSON."""
    import warnings

    spec = json.loads(Path(spec_path).read_text())
    resource.setrlimit(resource.RLIMIT_AS, (spec.get("memory_limit", MEMORY_LIMIT),) * 2)
    warnings.simplefilter("ignore")
    import logging

    logging.disable(logging.CRITICAL)
    folder = Path(spec["folder"])
    results: dict[str, Any] = {}
    for target, seed_path in spec["targets"].items():
        seed = Path(seed_path).read_bytes()
        work = Path(tempfile.mkdtemp(prefix=f"fuzz-{target}-", dir=folder))
        stats = {"cases": 0, "failures": []}

        case = _make_case(target, stats, work, Path(seed_path).suffix, seed, spec)
        case()
        results[target] = stats
        Path(spec["out"]).write_text(json.dumps(results))


def run_campaign(
    seeds: dict[str, Path],
    folder: Path,
    examples: int,
    *,
    derandomize: bool = True,
    timeout_s: float = 600,
    seconds: float | None = None,
) -> dict[str, Any]:
    """Run ``examples`` cases per target in one child process (within ``seconds`` when given: later cases
    are skipped); returns {target: {cases, failures}} plus a ``_crash`` entry when the child died (signal,
    timeout: a hang)."""
    import subprocess

    spec = folder / "spec.json"
    out = folder / "results.json"
    out.unlink(missing_ok=True)
    spec.write_text(json.dumps({
        "targets": {k: str(v) for k, v in seeds.items()}, "examples": examples, "folder": str(folder),
        "out": str(out), "derandomize": derandomize, "memory_limit": MEMORY_LIMIT,
        "t_end": math.inf if seconds is None else time.time() + seconds,
    }))  # fmt: skip
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(Path(__file__).parent), *sys.path])}
    try:
        proc = subprocess.run([sys.executable, "-c", f"import fuzzing; fuzzing.child_main({str(spec)!r})"],
                              env=env, capture_output=True, text=True, timeout=timeout_s)  # fmt: skip
        crash = None if proc.returncode == 0 else f"child exit {proc.returncode}: {proc.stderr[-800:]}"
    except subprocess.TimeoutExpired:
        crash = f"child timed out after {timeout_s} s (a hang)"
    results = json.loads(out.read_text()) if out.exists() else {}
    if crash:
        results["_crash"] = crash
    return results
