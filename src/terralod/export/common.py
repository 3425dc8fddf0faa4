"""What both web exports share: the source samples behind a store, the epoch choice, what an export's
output is made of (its inputs, its key).

An export writes through :class:`terralod.output.Output`: into a work folder beside the output, renamed into
place at the end, so an interrupted export leaves nothing half-written under the output name; with
``resume`` the tiles an interrupted export of the same key finished are kept (a tile is a pure function of
its code, so the result is byte for byte the uninterrupted one); with ``update`` only the files whose bytes
change are rewritten. An output folder that exists and is not empty needs ``overwrite``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from terralod.errors import InputError, StoreError

__all__ = [
    "apply_affine",
    "check_exportable",
    "export_inputs",
    "export_key",
    "source_heightfield",
    "source_validity",
    "streamed_digest",
    "valid_at",
]


def check_exportable(terrain: Any, epoch: str | None = None) -> None:
    """Refuse a terrain the exports cannot write: no tiles, a store still being written, a missing epoch."""
    where = str(terrain.path) if terrain.path is not None else None
    meta = getattr(terrain, "meta", {}) or {}
    if meta.get("complete") is False:
        raise StoreError("is incomplete (being written or interrupted); finish the build first", where)
    store = getattr(terrain, "store", None)  # a tile store answers from one row, not a tree of every tile
    if not (store.has_tiles() if hasattr(store, "has_tiles") else terrain.lod_tree()):
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


#: A store epoch of more samples than this has its validity read block by block (:class:`KeptValidity`).
WHOLE_VALIDITY_SAMPLES = 1 << 24


def source_validity(terrain: Any) -> Any:
    """What the exports drop nodata triangles against: :func:`source_heightfield`, except for an epoch of a
    store of more than :data:`WHOLE_VALIDITY_SAMPLES` samples, whose validity is read only where asked
    (:class:`KeptValidity`), never the grid whole."""
    store = getattr(terrain, "store", None)
    if getattr(terrain, "epochs", None) and store is not None:
        meta = store.meta
        if int(meta["width"]) * int(meta["height"]) > WHOLE_VALIDITY_SAMPLES:
            eid = store.epoch_source_id(terrain.epoch)
            if eid is not None:
                return KeptValidity(
                    store.path, eid, int(meta["width"]), int(meta["height"]), store.meta["transform"]
                )
    return source_heightfield(terrain)


class KeptValidity:
    """The validity of one store epoch's kept samples (:mod:`terralod.store_epochs`) where
    :func:`valid_at` asks: ``valid[rows, cols]`` reads only the 64 x 64 blocks those samples fall in (each
    checked against its digest), through a read-only connection per thread. ``valid.all()`` answers False
    (unknown without reading every block: the triangles are checked)."""

    def __init__(self, path: Any, eid: int, width: int, height: int, transform: Any) -> None:
        import threading

        from affine import Affine

        self.path, self.eid, self.width, self.height = str(path), int(eid), int(width), int(height)
        self.transform = Affine(*list(transform)[:6])
        self._local = threading.local()

    def __getstate__(self) -> dict[str, Any]:
        return {k: v for k, v in self.__dict__.items() if k != "_local"}  # connections stay per process

    def __setstate__(self, state: dict[str, Any]) -> None:
        import threading

        self.__dict__.update(state)
        self._local = threading.local()

    @property
    def valid(self) -> KeptValidity:
        return self

    def all(self) -> bool:
        return False

    def digest(self) -> str:
        """A digest that changes whenever the epoch's kept samples do: of its blocks' digests (each the sha256
        of a block's stored bytes, elevations and validity), read from the store, not the samples."""
        import hashlib
        import sqlite3

        conn = sqlite3.connect(f"file:{self.path}?mode=ro", uri=True)
        try:
            rows = conn.execute(
                "SELECT block, digest FROM epoch_source WHERE epoch = ? ORDER BY block", (self.eid,)
            )
            h = hashlib.sha256(f"{self.width}x{self.height}".encode())
            for block, d in rows:
                h.update(f"{block}:{d};".encode())
        finally:
            conn.close()
        return h.hexdigest()

    def __getitem__(self, index: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
        import sqlite3

        from terralod.store_epochs import SOURCE_BLOCK, source_window

        rows, cols = (np.asarray(i, np.int64) for i in index)
        out = np.zeros(rows.shape, bool)
        if not rows.size:
            return out
        conn = getattr(self._local, "conn", None)
        if conn is None:
            conn = self._local.conn = sqlite3.connect(
                f"file:{self.path}?mode=ro", uri=True, check_same_thread=False
            )
        b = SOURCE_BLOCK
        nbx = -(-self.width // b)
        key = (rows // b) * nbx + cols // b
        order = np.argsort(key, kind="stable")
        bounds = np.flatnonzero(np.diff(key[order])) + 1
        for part in np.split(order, bounds):
            by, bx = divmod(int(key[part[0]]), nbx)
            r0, c0 = by * b, bx * b
            _, ok = source_window(conn, self.eid, self.width, self.height, r0, c0, min(r0 + b, self.height),
                                  min(c0 + b, self.width), self.path, f"epoch id {self.eid}")  # fmt: skip
            out[part] = ok[rows[part] - r0, cols[part] - c0]
        return out


#: Samples per strip of :func:`streamed_digest` (a few tens of MB at a time).
DIGEST_STRIP_SAMPLES = 1 << 22


def streamed_digest(src: Any) -> str:
    """:meth:`terralod.heightfield.Heightfield.digest` of a window source (:mod:`terralod.io.windowed`: the
    grid a build made of its input), read in strips of full rows: the sha256 of the float32 elevations in
    row order, then of the packed validity, then of the transform and CRS, the bytes the whole grid's
    digest hashes. Memory: one strip."""
    import hashlib
    import tempfile

    h, w = src.height, src.width
    step = max(8, (DIGEST_STRIP_SAMPLES // max(w, 1)) // 8 * 8)  # rows: whole bytes of packed bits
    hz = hashlib.sha256()
    carry = np.zeros(0, bool)
    with tempfile.TemporaryFile() as bits:
        for r0 in range(0, h, step):
            r1 = min(r0 + step, h)
            z, ok = src.read(r0, 0, r1, w)
            hz.update(np.ascontiguousarray(z, dtype=np.float32))
            flat = np.concatenate([carry, np.asarray(ok, bool).ravel()])
            cut = flat.size - flat.size % 8
            bits.write(np.packbits(flat[:cut]).tobytes())
            carry = flat[cut:]
        if carry.size:
            bits.write(np.packbits(carry).tobytes())
        bits.seek(0)
        while chunk := bits.read(1 << 24):
            hz.update(chunk)
    hz.update(repr(tuple(src.transform)[:6]).encode())
    hz.update((src.crs or "").encode())
    return hz.hexdigest()


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


def export_inputs(terrain: Any) -> list[Path]:
    """The files an export of ``terrain`` reads (a store, a DEM): its output may be none of them."""
    path = getattr(terrain, "path", None) or getattr(terrain, "name", None)
    return [Path(path)] if path is not None and Path(path).exists() else []


def export_key(terrain: Any, fmt: str, **options: Any) -> dict[str, Any]:
    """What an export writes, for :class:`terralod.output.Output`'s resume: the format, its options, the
    epoch and the input file (resolved path, size, mtime): an interrupted export is resumed only by the
    same export of the same, unchanged input."""
    ident = None
    for f in export_inputs(terrain):
        st = f.stat()
        ident = [str(f.resolve()), st.st_size, st.st_mtime_ns]
    return {"format": fmt, "epoch": getattr(terrain, "epoch", None), "input": ident, **options}
