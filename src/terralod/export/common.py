"""What both web exports share: the source samples behind a store, atomic output folders, the epoch choice.

An export is written into a temporary folder beside the output and renamed into place at the end, so an
interrupted export leaves nothing half-written under the output name (a leftover ``.DIR.tmp-*`` folder is
removed by the next export; an old output set aside by a kill between the two renames of a replacement is
put back first). An output folder that exists and is not empty needs ``overwrite``.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from terralod.errors import InputError, StoreError

__all__ = [
    "apply_affine",
    "atomic_folder",
    "check_exportable",
    "check_output",
    "restore_set_aside",
    "source_heightfield",
    "valid_at",
]


def check_exportable(terrain: Any, epoch: str | None = None) -> None:
    """Refuse a terrain the exports cannot write: no tiles, a store still being written, a missing epoch."""
    where = str(terrain.path) if terrain.path is not None else None
    meta = getattr(terrain, "meta", {}) or {}
    if meta.get("complete") is False:
        raise StoreError("is incomplete (being written or interrupted); finish the build first", where)
    if not terrain.lod_tree():
        raise StoreError("has no tiles", where)
    if epoch is not None:
        if not terrain.epochs:
            raise InputError(f"has no epochs (asked for --epoch {epoch})", where)
        if epoch not in terrain.epochs:
            raise InputError(f"has no epoch {epoch} (it has {', '.join(terrain.epochs)})", where)
        if not hasattr(terrain, "with_epoch"):
            raise InputError("epoch selection is not available for this kind of store", where)


def source_heightfield(terrain: Any) -> Any:
    """The source DEM of a grid store when it can be read again and is the one the store was built from
    (same digest); None otherwise (TIN stores, moved or changed sources)."""
    if getattr(terrain, "epochs", None) and hasattr(terrain, "heightfield"):
        # a store of epochs keeps each epoch's samples; the recorded source is only its first epoch, so a
        # failure here is an error to report, never a reason to fall back to another epoch's DEM
        return terrain.heightfield()
    meta = getattr(terrain, "meta", {}) or {}
    src, digest = meta.get("source"), meta.get("source_digest")
    if not src or not digest:
        return None
    try:
        from terralod.io.reader import SAMPLE_SOURCE, read_heightfield, sample_heightfield

        if src == SAMPLE_SOURCE:
            hf = sample_heightfield()
        elif Path(src).is_file():
            hf = read_heightfield(src)
        else:
            return None
    except Exception:  # noqa: BLE001 - a source that no longer reads is simply not used
        return None
    return hf if hf.digest() == digest else None


def apply_affine(t: Any, x: Any, y: Any) -> tuple[np.ndarray, np.ndarray]:
    """An affine transform applied to arrays of points."""
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    return t.a * x + t.b * y + t.c, t.d * x + t.e * y + t.f


def valid_at(hf: Any, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Validity of the source sample nearest to each CRS point (False outside the grid)."""
    col, row = apply_affine(~hf.transform, x, y)
    c = np.floor(col).astype(np.int64)
    r = np.floor(row).astype(np.int64)
    inside = (r >= 0) & (c >= 0) & (r < hf.height) & (c < hf.width)
    out = np.zeros(np.shape(x), bool)
    out[inside] = hf.valid[r[inside], c[inside]]
    return out


def check_output(out: str | os.PathLike[str], overwrite: bool) -> None:
    """Refuse an output that is a file, a non-empty folder without ``overwrite``, or in a missing or
    read-only folder (an old output a killed replacement set aside is put back first)."""
    dst = Path(out)
    restore_set_aside(dst)
    if dst.exists() and not dst.is_dir():
        raise InputError("exists and is not a folder", str(dst))
    if dst.is_dir() and any(dst.iterdir()) and not overwrite:
        raise InputError("output folder is not empty (pass --overwrite to replace it)", str(dst))
    parent = dst.resolve().parent
    if not parent.is_dir():
        raise InputError(f"output folder {parent} does not exist", str(dst))
    if not os.access(parent, os.W_OK):
        raise InputError(f"output folder {parent} is not writable", str(dst))


def restore_set_aside(out: str | os.PathLike[str]) -> bool:
    """Put back an output folder that an export killed between its two renames left aside.

    Replacing ``out`` renames it to ``.OUT.tmp-old-*/x`` and then the new folder to ``out``; a kill in
    between leaves no ``out``. The old folder is then still whole: it is moved back (True), so a killed
    export leaves either the old output or the new one, never none.
    """
    dst = Path(out)
    if dst.exists() or dst.is_symlink():
        return False
    for old in sorted(dst.resolve().parent.glob(f".{dst.name}.tmp-old-*")):
        if (old / "x").is_dir():
            os.replace(old / "x", dst)
            shutil.rmtree(old, ignore_errors=True)
            return True
    return False


@contextmanager
def atomic_folder(out: str | os.PathLike[str], overwrite: bool) -> Iterator[Path]:
    """Yield a temporary folder that becomes ``out`` when the block ends without error."""
    check_output(out, overwrite)
    dst = Path(out)
    parent = dst.resolve().parent
    for stale in parent.glob(f".{dst.name}.tmp-*"):
        shutil.rmtree(stale, ignore_errors=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{dst.name}.tmp-", dir=parent))
    try:
        yield tmp
        if dst.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{dst.name}.tmp-old-", dir=parent))
            os.replace(dst, old / "x")  # a kill between these two renames: the next export puts it back
            os.replace(tmp, dst)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, dst)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
