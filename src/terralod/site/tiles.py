"""The change site's rasters as tile pyramids: the difference (DoD) and the BEFORE heights of a pair reach the
browser as small tiles at the levels the view needs, never as one array (issue 54).

Levels: level 0 is the grid itself (each sample the cell's own value, as ``dod.tif`` has it: ``changeAt`` and
``volume`` read only this level); level k + 1 halves level k, each sample the mean of the valid level-0 cells
of its 2^k × 2^k block (carried as sums and counts, so a mean is never a mean of means), no data where the
block has none; the last level is one tile. Levels are for display (the drape); figures come from level 0.

Tiles: :data:`TILE_PX`² samples (smaller at the right and bottom edges: the level's own shape, nothing padded),
row-major, named ``PREFIX/LEVEL/ROW_COL.i32.gz``; a tile with no data is not written (the pyramid's ``tiles``
string says which exist: one character per tile, "1" written, "0" not, row-major).

Encoding (:data:`ENCODING`, stated in ``site.json``): a sample ``v`` metres is ``q = round(v / STEP_M)``, int32
(:data:`STEP_M` = 1 mm, so a decoded value is within 0.5 mm of the float it came from), no data is
:data:`NODATA_Q`; each row is delta-coded left to right (int32 arithmetic that wraps, the first sample of a row
against 0), the int32s' four bytes are split into four planes (all first bytes, then all second, ...: little
endian), and the whole is gzip'd. The page inflates it with ``DecompressionStream`` (no host configuration),
so any static host serves the files as they are.

The writer (:func:`write_pyramid`) reads its source in strips of rows (``read(row0, row1)``: an array in memory
or a windowed read of ``dod.tif``, :func:`raster_rows`) and keeps at most two tile rows per level, so a grid
of any size is never whole in memory.
"""

from __future__ import annotations

import gzip
import hashlib
import os
from collections.abc import Callable, Iterator, MutableMapping
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["ENCODING", "NODATA_Q", "STEP_M", "TILE_PX", "FolderFiles", "decode_tile", "encode_tile",
           "raster_rows", "write_pyramid"]  # fmt: skip

#: Samples per tile side.
TILE_PX = 256
#: The quantisation step in metres (1 mm): a decoded sample is within STEP_M / 2 of its source.
STEP_M = 0.001
#: The int32 of "no data".
NODATA_Q = -(2**31)
#: What ``site.json`` says of the tiles (the page decodes them by it).
ENCODING = {
    "name": "int32-step-delta-byteplanes-gzip",
    "step_m": STEP_M,
    "nodata": NODATA_Q,
    "tile_px": TILE_PX,
    "levels": "level 0 = the grid (each cell's own value); level k+1 = the mean of the valid cells of level "
    "0's 2^(k+1)-cell blocks",
    "decode": "gunzip; 4 byte planes -> little-endian int32; per row running sum (int32, wrapping) from 0; "
    "q == nodata -> no data, else q * step_m metres",
}

RowReader = Callable[[int, int], np.ndarray]


def encode_tile(values: np.ndarray) -> bytes:
    """One tile (float metres, NaN = no data) in :data:`ENCODING`."""
    v = np.asarray(values, np.float64)
    ok = np.isfinite(v)
    q = np.full(v.shape, NODATA_Q, np.int32)
    scaled = np.round(v[ok] / STEP_M)
    if scaled.size and np.abs(scaled).max() >= 2**31 - 1:
        raise ValueError(f"a value of {np.abs(v[ok]).max():.0f} m is beyond the tiles' int32 millimetres")
    q[ok] = scaled.astype(np.int32)
    d = q.copy()
    d[:, 1:] = (q[:, 1:].astype(np.int64) - q[:, :-1]).astype(np.int32)  # wraps, as JS's `| 0` does
    planes = d.astype("<i4").view(np.uint8).reshape(-1, 4).T
    return gzip.compress(np.ascontiguousarray(planes).tobytes(), 6, mtime=0)


def decode_tile(data: bytes, shape: tuple[int, int]) -> np.ndarray:
    """A tile's float64 metres (NaN = no data): the inverse of :func:`encode_tile`, as the page decodes it."""
    n = shape[0] * shape[1]
    planes = np.frombuffer(gzip.decompress(data), np.uint8).reshape(4, n)
    d = np.ascontiguousarray(planes.T).view("<i4").reshape(shape).astype(np.int64)
    q = (np.cumsum(d, axis=1) + 2**31) % 2**32 - 2**31  # the running sum, wrapping as int32
    return np.where(q == NODATA_Q, np.nan, q * STEP_M)


def _halve(s: np.ndarray, n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sums and counts of 2 × 2 blocks (an odd last row or column is a block of its own)."""
    h, w = s.shape
    H, W = -(-h // 2), -(-w // 2)
    ps = np.zeros((2 * H, 2 * W), np.float64)
    pn = np.zeros((2 * H, 2 * W), np.int64)
    ps[:h, :w], pn[:h, :w] = s, n
    return ps.reshape(H, 2, W, 2).sum(axis=(1, 3)), pn.reshape(H, 2, W, 2).sum(axis=(1, 3))


class _Level:
    """One level being written: rows of (sum, count) arrive in order; each full tile row is written and its
    halves go to the next level."""

    def __init__(self, k: int, shape: tuple[int, int], emit: Callable[[int, int, int, np.ndarray], None]):
        self.k, self.shape, self.emit = k, shape, emit
        self.rows_done = 0
        self.buf_s: list[np.ndarray] = []
        self.buf_n: list[np.ndarray] = []
        self.next: _Level | None = None
        if max(shape) > TILE_PX:
            self.next = _Level(k + 1, (-(-shape[0] // 2), -(-shape[1] // 2)), emit)

    def push(self, s: np.ndarray, n: np.ndarray) -> None:
        self.buf_s.append(s)
        self.buf_n.append(n)
        if sum(len(b) for b in self.buf_s) >= TILE_PX:
            self._flush(final=False)

    def _flush(self, final: bool) -> None:
        if not self.buf_s:
            return
        s, n = np.concatenate(self.buf_s), np.concatenate(self.buf_n)
        take = len(s) if final else (len(s) // TILE_PX) * TILE_PX
        ts, tn = s[:take], n[:take]
        self.buf_s, self.buf_n = ([s[take:]], [n[take:]]) if take < len(s) else ([], [])
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = np.where(tn > 0, ts / np.maximum(tn, 1), np.nan)
        for r0 in range(0, take, TILE_PX):
            tr = (self.rows_done + r0) // TILE_PX
            for c0 in range(0, self.shape[1], TILE_PX):
                self.emit(self.k, tr, c0 // TILE_PX, mean[r0 : r0 + TILE_PX, c0 : c0 + TILE_PX])
        self.rows_done += take
        if self.next is not None:
            hs, hn = _halve(ts, tn)  # take is a multiple of TILE_PX (even) except at the end
            self.next.push(hs, hn)

    def finish(self) -> None:
        self._flush(final=True)
        if self.next is not None:
            self.next.finish()


def write_pyramid(read: RowReader, shape: tuple[int, int], prefix: str, *, strip_rows: int = 4 * TILE_PX,
                  files: MutableMapping[str, bytes] | None = None,
                  ) -> tuple[dict[str, Any], MutableMapping[str, bytes]]:  # fmt: skip
    """The pyramid of a raster of ``shape`` whose rows ``read(row0, row1)`` gives (float metres, NaN = no data),
    read ``strip_rows`` at a time: (its description for the pair's JSON, {file name: bytes}: ``files`` when
    given, with this pyramid's tiles added). The description holds ``url`` (``prefix``), ``tile_px``, each
    level's ``shape`` and ``tiles`` (which exist) and ``sha256`` (of every tile's name and bytes: two
    pyramids of the same digest are the same files)."""
    h, w = int(shape[0]), int(shape[1])
    files = {} if files is None else files
    own: list[str] = []
    written: dict[int, set[tuple[int, int]]] = {}
    shapes: dict[int, tuple[int, int]] = {}

    def emit(k: int, tr: int, tc: int, block: np.ndarray) -> None:
        written.setdefault(k, set())
        if np.isfinite(block).any():
            name = f"{prefix}/{k}/{tr}_{tc}.i32.gz"
            files[name] = encode_tile(block)
            own.append(name)
            written[k].add((tr, tc))

    top = _Level(0, (h, w), emit)
    lvl: _Level | None = top
    while lvl is not None:
        shapes[lvl.k] = lvl.shape
        lvl = lvl.next
    for r0 in range(0, h, strip_rows):
        v = np.asarray(read(r0, min(h, r0 + strip_rows)), np.float64)
        ok = np.isfinite(v)
        top.push(np.where(ok, v, 0.0), ok.astype(np.int64))
    top.finish()
    digest = hashlib.sha256()
    levels = []
    for k in sorted(shapes):
        lh, lw = shapes[k]
        nr, nc = -(-lh // TILE_PX), -(-lw // TILE_PX)
        have = written.get(k, set())
        levels.append({"shape": [lh, lw], "tiles": "".join("1" if (r, c) in have else "0"
                                                          for r in range(nr) for c in range(nc))})  # fmt: skip
    for name in sorted(own):
        digest.update(name[len(prefix) :].encode() + b"\0" + files[name])
    desc = {"url": prefix, "tile_px": TILE_PX, "levels": levels, "sha256": digest.hexdigest()}
    return desc, files


class FolderFiles(MutableMapping[str, bytes]):
    """A mapping of file names to bytes kept as files under ``root`` (the tiles of a region's pyramids, which
    would not fit in memory as a dict): setting writes the file, getting reads it back."""

    def __init__(self, root: str | os.PathLike[str]) -> None:
        self.root = Path(root)
        self._names: set[str] = set()

    def __setitem__(self, name: str, data: bytes) -> None:
        f = self.root / name
        f.parent.mkdir(parents=True, exist_ok=True)
        f.write_bytes(data)
        self._names.add(name)

    def __getitem__(self, name: str) -> bytes:
        if name not in self._names:
            raise KeyError(name)
        return (self.root / name).read_bytes()

    def __delitem__(self, name: str) -> None:
        self._names.remove(name)
        (self.root / name).unlink()

    def __iter__(self) -> Iterator[str]:
        return iter(sorted(self._names))

    def __len__(self) -> int:
        return len(self._names)


def array_rows(a: np.ndarray) -> RowReader:
    """A row reader of an array in memory (float; NaN = no data)."""
    return lambda r0, r1: np.asarray(a[r0:r1], np.float64)


def raster_rows(path: Any, band: int = 1) -> tuple[RowReader, tuple[int, int], Callable[[], None]]:
    """A windowed row reader of a GeoTIFF (``dod.tif``; its nodata and mask read as NaN): (read, shape,
    close)."""
    import rasterio
    from rasterio.windows import Window

    ds = rasterio.open(path)

    def read(r0: int, r1: int) -> np.ndarray:
        m = ds.read(band, window=Window(0, r0, ds.width, r1 - r0), masked=True)
        return np.asarray(m.astype(np.float64).filled(np.nan))

    return read, (ds.height, ds.width), ds.close


def read_level(desc: dict[str, Any], files: Callable[[str], bytes | None], level: int = 0) -> np.ndarray:
    """Level ``level`` of a pyramid whole (float64 metres, NaN = no data), its tiles decoded as the page decodes
    them: ``files(name)`` gives a tile's bytes (a dict's ``get``, or a reader of a site folder's files)."""
    lv = desc["levels"][level]
    h, w = lv["shape"]
    nc = -(-w // TILE_PX)
    out = np.full((h, w), np.nan)
    for i, flag in enumerate(lv["tiles"]):
        if flag != "1":
            continue
        tr, tc = divmod(i, nc)
        r0, c0 = tr * TILE_PX, tc * TILE_PX
        r1, c1 = min(h, r0 + TILE_PX), min(w, c0 + TILE_PX)
        data = files(f"{desc['url']}/{level}/{tr}_{tc}.i32.gz")
        if data is None:
            raise FileNotFoundError(f"{desc['url']}/{level}/{tr}_{tc}.i32.gz")
        out[r0:r1, c0:c1] = decode_tile(data, (r1 - r0, c1 - c0))
    return out
