"""Detail-increment files: the paper's text scheme and the binary container (format 5) with its codings.

Paper: ``../shared/papers/003_2a2cfcda929de24c.txt``

- §2.2.2, "external storage scheme": the text export of the records (:func:`write_text`,
  :func:`read_text`);
- §4: storage of base + increments against a static pyramid (``benchmarks/tin.py`` codes the pyramid
  with the same container, :func:`_encode_arrays`, and mesh rows, :func:`encode_mesh_rows`).

Deviation, and why:

- **Binary format, version 5** (the paper's text scheme stays as an export): a header (magic, version,
  payload length, sha256 of the payload) and one raw LZMA2 stream holding the metadata (JSON) and numpy
  arrays (integers in the narrowest type, byte-shuffled; float arrays column by column as their distinct
  values and the rank changes from one element to the next when that is smaller, the same container as
  the static pyramid of ``benchmarks/tin.py``): :func:`write_container`, :func:`read_container`. Table 1's
  fields are not stored: a raw record is one vertex split (removed vertex u, kept vertex v, the wing x1
  where the fan of m moved triangles starts, see :func:`terralod.kernels.qem_replay.replay_splits`), coded from
  geometry by :mod:`terralod.kernels.tincodec`: u as its rank among the vertices its sub-block has still
  to insert, largest vertical distance to the current surface first (a per-vertex sub-block label, stored
  as "the cell holding the vertex" or an exception, says which sub-block inserts a vertex), v as a corner
  (0-2, nearest first) of the current triangle holding u's xy, the fan as its triangles before and after
  that triangle (escape: v and x1 as they are), v and the fan's counts ranked by frequency within a
  geometric context; the base mesh in canonical order (:func:`terralod.tin.records.canonical_rows`) as
  delta rows (:func:`encode_mesh_rows`); each block's MMQE and measured-error codes as the first and the
  drops; the LZMA2 stream of a payload over 2 MiB is coded in pieces on threads (:data:`LZMA_PIECE_BYTES`,
  dictionary resets inside the one stream: same format, same decoded payload). What goes into the arrays is :meth:`terralod.tin.increments.DetailIncrementModel.save`'s; a file
  of a merged model stores the raw splits and the merge factor. Versions 1 (slots and triples), 2 (no
  measured error), 3 (floats not coded by column) and 4 (splits as plain indices, deflated per array)
  are refused with one line naming the file.
"""

from __future__ import annotations

import hashlib
import io
import json
import lzma
import math
import os
import struct
import zlib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from terralod.errors import CorruptStoreError, InputError, InputNotFoundError
from terralod.tin.records import DeltaT, Increments

__all__ = [
    "FORMAT_VERSION",
    "MAGIC",
    "decode_mesh_rows",
    "encode_mesh_rows",
    "read_container",
    "read_text",
    "write_container",
    "write_container_stream",
    "write_text",
]

MAGIC = b"TLODDIM\x00"
#: 5: splits coded from geometry (u's rank in its sub-block, v a corner of the triangle holding u, the
#: fan's offset), base rows delta-coded, one LZMA2 stream; 4: float arrays coded by column (distinct values
#: + rank changes); 3: + measured error per scale; 2: compact vertex-split records; 1: slots and triples
#: (1 to 4 no longer read)
FORMAT_VERSION = 5
_HEADER = struct.Struct("<8sHHIQ32s8x")  # magic, version, flags, reserved, payload length, sha256
_FLAG_LZMA = 2  #: the payload is one raw LZMA2 stream


# -- text export (Ai et al. (2019) §2.2.2, "external storage scheme") -------------------------------------------
def write_text(inc: Increments, path: str | os.PathLike[str]) -> None:
    """Write the increments in the paper's text scheme.

    Line 1: the number of collapses merged per record (element 1, stored once). Then, per sub-block, a
    comment line ``# block <b> records <n_b>`` and one row per record ΔT_0, ΔT_1, … with, separated by
    spaces: (2) the number of changed triangles d + r; (3) the d deleted slots; (4) the r replaced
    slots; (5) 3·d vertex indices of the deleted triangles; (6) 3·r original and (7) 3·r new vertex
    indices of the replaced triangles. d follows from the row length (4 (d + r) + 3 r numbers).
    """
    with open(path, "w", encoding="ascii") as f:
        f.write(f"{inc.step}\n")
        for b in range(inc.n_blocks):
            f.write(f"# block {b} records {int(inc.block_ptr[b + 1] - inc.block_ptr[b])}\n")
            for r in range(int(inc.block_ptr[b]), int(inc.block_ptr[b + 1])):
                d0, d1 = inc.del_ptr[r], inc.del_ptr[r + 1]
                r0, r1 = inc.rep_ptr[r], inc.rep_ptr[r + 1]
                parts = [
                    np.array([d1 - d0 + r1 - r0]),
                    inc.del_slot[d0:d1],
                    inc.rep_slot[r0:r1],
                    inc.del_tri[d0:d1].ravel(),
                    inc.rep_old[r0:r1].ravel(),
                    inc.rep_new[r0:r1].ravel(),
                ]
                f.write(" ".join(map(str, np.concatenate(parts).tolist())) + "\n")


def read_text(path: str | os.PathLike[str]) -> tuple[int, list[list[DeltaT]]]:
    """Parse :func:`write_text` output: (step, records per block; MMQE is not part of the scheme: NaN)."""
    blocks: list[list[DeltaT]] = []
    with open(path, encoding="ascii") as f:
        step = int(f.readline())
        for line in f:
            if line.startswith("#"):
                blocks.append([])
                continue
            a = np.array(line.split(), np.int64)
            n = int(a[0])
            r = (a.size - 1 - 4 * n) // 3
            d = n - r
            if d < 0 or r < 0 or a.size != 1 + 4 * n + 3 * r:
                raise InputError(f"malformed record row of {a.size} numbers", str(path))
            p = 1
            ds = a[p : p + d]
            p += d
            rs = a[p : p + r]
            p += r
            dv = a[p : p + 3 * d].reshape(-1, 3)
            p += 3 * d
            ro = a[p : p + 3 * r].reshape(-1, 3)
            p += 3 * r
            rn = a[p : p + 3 * r].reshape(-1, 3)
            blk = blocks[-1]
            blk.append(DeltaT(len(blk), math.nan, ds, dv, rs, ro, rn, len(blocks) - 1))
    return step, blocks


# -- binary container ------------------------------------------------------------------------------------
#: The generic entropy coder of format 5: the whole payload after the header is one raw LZMA2 stream (no


#: per-section stream overheads; the static pyramid of ``benchmarks/tin.py`` is coded by the same function).
_LZMA_FILTERS = [{"id": lzma.FILTER_LZMA2, "preset": 9}]


#: Payloads over this are compressed as independent pieces of this many bytes, on threads, and joined into
#: the same one LZMA2 stream (each piece's first chunk resets the dictionary, which LZMA2 allows anywhere):
#: any reader of format 5 decodes it; the bytes depend on the payload alone, never on the thread count.
#: About 0.02 % larger than one piece (a 8 MB payload: 3,448,628 against 3,448,040 bytes), ~2x faster on 2
#: cores; a payload up to one piece is coded exactly as before.
LZMA_PIECE_BYTES = 1 << 21
#: What the writer codes with: preset 9 with a dictionary of one piece. No match reaches further back than
#: a piece, so the bytes are those of preset 9's 64 MiB dictionary (checked on the 8 MB Puget payload of
#: ``benchmarks/tin_build.py``: identical), without allocating and clearing 64 MiB per piece (about 28 %
#: of the coding time there). Readers decode with :data:`_LZMA_FILTERS`.
_LZMA_ENCODE_FILTERS = [{"id": lzma.FILTER_LZMA2, "preset": 9, "dict_size": LZMA_PIECE_BYTES}]


def _pack_piece(raw: bytes) -> bytes:
    """One raw LZMA2 stream without its end marker (the 0 control byte)."""
    c = lzma.compress(raw, format=lzma.FORMAT_RAW, filters=_LZMA_ENCODE_FILTERS)
    if not c or c[-1] != 0:  # pragma: no cover - liblzma always ends a raw LZMA2 stream with 0x00
        raise RuntimeError("unexpected LZMA2 stream end")
    return c[:-1]


def _pack(raw: bytes, workers: int | None = None) -> bytes:
    if len(raw) <= LZMA_PIECE_BYTES:
        return lzma.compress(raw, format=lzma.FORMAT_RAW, filters=_LZMA_ENCODE_FILTERS)
    pieces = [raw[i : i + LZMA_PIECE_BYTES] for i in range(0, len(raw), LZMA_PIECE_BYTES)]
    n = min(len(pieces), workers if workers is not None else min(os.cpu_count() or 1, 8))
    if n <= 1:
        coded = [_pack_piece(b) for b in pieces]
    else:
        from concurrent.futures import ThreadPoolExecutor

        with ThreadPoolExecutor(n) as pool:  # liblzma runs without the GIL
            coded = list(pool.map(_pack_piece, pieces))
    return b"".join(coded) + b"\x00"


def _unpack(buf: bytes, src: str) -> bytes:
    try:
        return lzma.decompress(buf, format=lzma.FORMAT_RAW, filters=_LZMA_FILTERS)
    except lzma.LZMAError as exc:
        raise CorruptStoreError(f"damaged compressed payload ({exc})", src) from exc


def _narrow(a: np.ndarray) -> np.ndarray:
    """Integers in the narrowest little-endian type holding them."""
    if a.dtype.kind not in "iu" or a.size == 0:
        return a.astype(a.dtype.newbyteorder("<"))
    lo, hi = int(a.min()), int(a.max())
    for t in (
        (np.uint8, np.uint16, np.uint32, np.uint64) if lo >= 0 else (np.int8, np.int16, np.int32, np.int64)
    ):
        info = np.iinfo(t)
        if info.min <= lo and hi <= info.max:
            return a.astype(np.dtype(t).newbyteorder("<"))
    return a


_FLOAT_CODED = "coded"  #: stored-dtype tag of a float64 array coded column by column (:func:`_encode_floats`)


def _shuffle(a: np.ndarray) -> bytes:
    """Bytes of ``a`` regrouped by byte position (all first bytes, then all second bytes, …)."""
    raw = a.tobytes()
    if a.dtype.itemsize > 1 and a.size:
        raw = np.frombuffer(raw, np.uint8).reshape(-1, a.dtype.itemsize).T.tobytes()
    return raw


def _unshuffle(raw: bytes, dtype: np.dtype, n: int) -> np.ndarray:
    if dtype.itemsize > 1 and n:
        raw = np.frombuffer(raw, np.uint8).reshape(dtype.itemsize, -1).T.tobytes()
    return np.frombuffer(raw, dtype)


def _zigzag(d: np.ndarray) -> np.ndarray:
    d = np.asarray(d, np.int64)
    return ((d << 1) ^ (d >> 63)).view(np.uint64)


def _unzigzag(z: np.ndarray) -> np.ndarray:
    z = np.asarray(z).astype(np.uint64)
    return (z >> np.uint64(1)).view(np.int64) ^ -(z & np.uint64(1)).view(np.int64)


def encode_mesh_rows(tris: np.ndarray) -> np.ndarray:
    """(K, 3) uint64: triangle rows as (first vertex - previous row's first, second - first, third - first),
    zigzag: a mesh coding for any row order, compact when rows are sorted by their first vertex and
    neighbouring vertices have near indices. The model's base mesh and every mesh of the static pyramid
    (``benchmarks/tin.py``) use it; :func:`decode_mesh_rows` inverts it."""
    t = np.asarray(tris, np.int64).reshape(-1, 3)
    a = t[:, 0]
    return np.ascontiguousarray(np.stack([_zigzag(np.diff(a, prepend=0)), _zigzag(t[:, 1] - a),
                                          _zigzag(t[:, 2] - a)], axis=1))  # fmt: skip


def decode_mesh_rows(rows: np.ndarray) -> np.ndarray:
    """(K, 3) int64 triangles of :func:`encode_mesh_rows` output."""
    d = _unzigzag(np.asarray(rows).reshape(-1, 3))
    a = np.cumsum(d[:, 0])
    return np.stack([a, a + d[:, 1], a + d[:, 2]], axis=1)


#: :func:`_estimate` compresses at most this many bytes of a column: evenly spaced chunks of it.
_ESTIMATE_BYTES = 1 << 19
_ESTIMATE_CHUNKS = 8


def _estimate(raw: bytes) -> int:
    """Cheap stand-in for the coded size, to choose between two codings of a float column: zlib level 1
    of the column, or of :data:`_ESTIMATE_CHUNKS` evenly spaced chunks of it (:data:`_ESTIMATE_BYTES` in
    all) scaled to its length when it is longer. A deterministic function of the bytes, so the file's
    bytes still depend on the model alone. On the Puget crop, Autzen and Autzen 4x4 it makes the same
    choice on every column as zlib level 6 of the whole column did, in a seventh of the time (Puget:
    0.045 s against 0.33 s a save)."""
    n = len(raw)
    if n <= _ESTIMATE_BYTES:
        return len(zlib.compress(raw, 1))
    step = _ESTIMATE_BYTES // _ESTIMATE_CHUNKS
    starts = [(n - step) * i // (_ESTIMATE_CHUNKS - 1) for i in range(_ESTIMATE_CHUNKS)]
    coded = sum(len(zlib.compress(raw[a : a + step], 1)) for a in starts)
    return coded * n // _ESTIMATE_BYTES


def _encode_floats(a: np.ndarray) -> bytes:
    """A float64 array (1-D, or 2-D coded column by column) losslessly, each column the smaller of:
    0, its values, shuffled; 1, its sorted distinct values (bit patterns made monotone, then differences)
    and, per element, the change of its rank from the previous element (zigzag), each narrowed and
    shuffled. A grid's heights take few distinct values and change little from one vertex to the next: 1
    halves them; scattered LiDAR coordinates keep 0. The bytes go to the payload's one compressed stream."""
    cols = a.reshape(a.shape[0], -1) if a.ndim else a.reshape(1, 1)
    out = io.BytesIO()
    for j in range(cols.shape[1]):
        c = np.ascontiguousarray(cols[:, j], np.float64)
        plain = _shuffle(c.astype("<f8"))
        best: tuple = (0, [plain])
        if c.size > 64:
            bits = c.view(np.int64)
            mono = bits ^ ((bits >> 63) & np.int64(0x7FFFFFFFFFFFFFFF))  # order of the floats, as integers
            uniq, rank = np.unique(mono, return_inverse=True)
            du = _narrow(_zigzag(np.diff(uniq, prepend=np.int64(0)) if uniq.size else uniq))
            dr = _narrow(_zigzag(np.diff(rank.astype(np.int64).ravel(), prepend=0)))
            parts = [_shuffle(du), _shuffle(dr)]
            if sum(map(_estimate, parts)) + 16 < _estimate(plain):
                best = (1, parts, du.dtype.str, dr.dtype.str, uniq.size)
        out.write(struct.pack("<B", best[0]))
        if best[0] == 1:
            out.write(struct.pack("<Q", best[4]))
            for dt in (best[2], best[3]):
                out.write(struct.pack("<B", len(dt)) + dt.encode())
        for part in best[1]:
            out.write(part)
    return out.getvalue()


def _decode_floats(buf: bytes, shape: tuple[int, ...], src: str) -> np.ndarray:
    n = shape[0] if shape else 1
    k = int(np.prod(shape[1:])) if len(shape) > 1 else 1
    cols = np.empty((n, k), np.float64)
    pos = 0

    def take(m: int) -> bytes:
        nonlocal pos
        if m < 0 or pos + m > len(buf):
            raise CorruptStoreError("truncated float array", src)
        pos += m
        return buf[pos - m : pos]

    for j in range(k):
        (mode,) = struct.unpack("<B", take(1))
        if mode == 0:
            cols[:, j] = _unshuffle(take(8 * n), np.dtype("<f8"), n)
        elif mode == 1:
            (nu,) = struct.unpack("<Q", take(8))
            dts = []
            for _ in range(2):
                (ld,) = struct.unpack("<B", take(1))
                dts.append(np.dtype(take(ld).decode()))
            uniq = np.cumsum(_unzigzag(_unshuffle(take(nu * dts[0].itemsize), dts[0], nu)))
            rank = np.cumsum(_unzigzag(_unshuffle(take(n * dts[1].itemsize), dts[1], n)))
            if n and (rank.min() < 0 or rank.max() >= nu):
                raise CorruptStoreError("inconsistent float array", src)
            mono = uniq[rank]
            cols[:, j] = (mono ^ ((mono >> 63) & np.int64(0x7FFFFFFFFFFFFFFF))).view(np.float64)
        else:
            raise CorruptStoreError(f"unknown float coding {mode}", src)
    if pos != len(buf):
        raise CorruptStoreError("inconsistent float array", src)
    return cols.reshape(shape)


def _array_section(arrays: dict[str, np.ndarray]) -> bytes:
    """Named arrays, uncoded: their count, then per array its name, dtype, stored dtype, shape, byte length
    and bytes (integers narrowed and shuffled; large float arrays by :func:`_encode_floats`)."""
    return struct.pack("<I", len(arrays)) + b"".join(_array_bytes(n, a) for n, a in arrays.items())


def _array_bytes(name: str, arr: np.ndarray) -> bytes:
    """One array's part of :func:`_array_section`."""
    a = np.ascontiguousarray(arr)
    if a.dtype == np.float64 and a.ndim in (1, 2) and a.size > 256:  # small ones: as they are
        stored_str = _FLOAT_CODED
        raw = _encode_floats(a)
    else:
        stored = _narrow(a)
        stored_str = stored.dtype.str
        raw = _shuffle(stored)
    nm = name.encode()
    out = [struct.pack("<B", len(nm)) + nm]
    for dt in (a.dtype.newbyteorder("<").str, stored_str):
        out.append(struct.pack("<B", len(dt)) + dt.encode())
    out.append(struct.pack("<B", a.ndim) + b"".join(_uvarint(s) for s in a.shape))
    out.append(_uvarint(len(raw)))
    out.append(raw)
    return b"".join(out)


def _uvarint(x: int) -> bytes:
    """LEB128: 7 bits a byte, low first (array shapes and lengths: mostly 1 to 3 bytes)."""
    out = bytearray()
    x = int(x)
    while True:
        b = x & 0x7F
        x >>= 7
        if x:
            out.append(b | 0x80)
        else:
            out.append(b)
            return bytes(out)


def _encode_arrays(arrays: dict[str, np.ndarray], compress: bool = True) -> bytes:
    """Named arrays as one stream, compressed by the file's entropy coder when ``compress``."""
    raw = _array_section(arrays)
    return _pack(raw) if compress else raw


def _decode_arrays(buf: bytes, compress: bool, src: str) -> dict[str, np.ndarray]:
    return _parse_arrays(_unpack(buf, src) if compress else buf, src)


def _parse_arrays(buf: bytes, src: str) -> dict[str, np.ndarray]:
    view = memoryview(buf)
    pos = 0

    def take(n: int) -> memoryview:
        nonlocal pos
        if n < 0 or pos + n > len(view):
            raise CorruptStoreError("truncated array section", src)
        out = view[pos : pos + n]
        pos += n
        return out

    def varint() -> int:
        x, shift = 0, 0
        while True:
            (b,) = take(1)
            x |= (b & 0x7F) << shift
            if b < 0x80:
                return x
            shift += 7
            if shift > 63:
                raise CorruptStoreError("malformed length", src)

    (count,) = struct.unpack("<I", take(4))
    arrays = {}
    for _ in range(count):
        (ln,) = take(1)
        name = bytes(take(ln)).decode()
        dts = []
        for _ in range(2):
            (ld,) = take(1)
            dts.append(bytes(take(ld)).decode())
        (ndim,) = take(1)
        shape = tuple(varint() for _ in range(ndim))
        raw = bytes(take(varint()))
        if dts[1] == _FLOAT_CODED:
            arrays[name] = _decode_floats(raw, shape, src).astype(np.dtype(dts[0]).newbyteorder("="))
            continue
        stored = np.dtype(dts[1])
        n = int(np.prod(shape))
        if len(raw) != n * stored.itemsize:
            raise CorruptStoreError(f"array {name}: {len(raw)} bytes for shape {shape}", src)
        arrays[name] = _unshuffle(raw, stored, n).reshape(shape).astype(np.dtype(dts[0]).newbyteorder("="))
    return arrays


def write_container(
    path: str | os.PathLike[str],
    meta: dict[str, Any],
    arrays: dict[str, np.ndarray],
    *,
    compress: bool = True,
    workers: int | None = None,
) -> int:
    """Write ``meta`` (JSON) and named arrays with the checksummed header; returns the file size, bytes.

    The payload (meta + arrays) is one LZMA2 stream when ``compress`` (:func:`_pack`; pieces of
    :data:`LZMA_PIECE_BYTES` compressed on ``workers`` threads, the same bytes for any number). Written
    to ``path + '.tmp'`` then renamed, so an interrupted write never leaves a half file.
    """
    return write_container_stream(path, meta, len(arrays), iter(arrays.items()), compress=compress,
                                  workers=workers)  # fmt: skip


def write_container_stream(
    path: str | os.PathLike[str],
    meta: dict[str, Any],
    n_arrays: int,
    arrays: Iterator[tuple[str, np.ndarray]],
    *,
    compress: bool = True,
    workers: int | None = None,
) -> int:
    """:func:`write_container` of ``n_arrays`` named arrays that arrive one by one, in order, the same
    bytes: each whole piece of :data:`LZMA_PIECE_BYTES` is compressed on a thread as soon as its bytes
    are known, so the coder runs beside whatever computes the later arrays (the splits' codes of
    :meth:`terralod.tin.increments.DetailIncrementModel.save`). ValueError when the iterator yields other
    than ``n_arrays`` arrays; nothing is written then, nor when it raises."""
    body = json.dumps(meta, sort_keys=True, separators=(",", ":")).encode()
    buf = bytearray(_uvarint(len(body)) + body + struct.pack("<I", n_arrays))
    count = 0
    if not compress:
        for name, arr in arrays:
            buf += _array_bytes(name, arr)
            count += 1
        payload = bytes(buf)
    else:
        from concurrent.futures import ThreadPoolExecutor

        n = max(1, workers if workers is not None else min(os.cpu_count() or 1, 8))
        coded = []
        done = 0  # bytes of buf handed to the coder
        with ThreadPoolExecutor(n) as pool:  # liblzma runs without the GIL
            for name, arr in arrays:
                buf += _array_bytes(name, arr)
                count += 1
                while len(buf) - done > LZMA_PIECE_BYTES:  # a whole piece, and more after it
                    coded.append(pool.submit(_pack_piece, bytes(buf[done : done + LZMA_PIECE_BYTES])))
                    done += LZMA_PIECE_BYTES
            coded.append(pool.submit(_pack_piece, bytes(buf[done:])))  # the last piece: 1 to a whole
            payload = b"".join(f.result() for f in coded) + b"\x00"
    if count != n_arrays:
        raise ValueError(f"Expected {n_arrays} arrays, got {count}")
    head = _HEADER.pack(
        MAGIC,
        FORMAT_VERSION,
        _FLAG_LZMA if compress else 0,
        0,
        len(payload),
        hashlib.sha256(payload).digest(),
    )
    from terralod.io.raster import atomic_file

    with atomic_file(Path(path)) as tmp, open(tmp, "wb") as f:
        f.write(head)
        f.write(payload)
    return len(head) + len(payload)


def read_container(path: str | os.PathLike[str]) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """Read :func:`write_container` output; CorruptStoreError on a foreign, damaged, older or newer file."""
    p = Path(path)
    src = str(p)
    if not p.exists():
        raise InputNotFoundError("file not found", src)
    data = p.read_bytes()
    if len(data) < _HEADER.size or data[:8] != MAGIC:
        raise CorruptStoreError("not a terralod detail-increment file (bad magic)", src)
    magic, version, flags, _, length, digest = _HEADER.unpack_from(data)
    if version > FORMAT_VERSION:
        raise CorruptStoreError(
            f"format version {version} is newer than this terralod's ({FORMAT_VERSION})", src
        )
    if version < FORMAT_VERSION:
        raise CorruptStoreError(
            f"format version {version} is no longer read (this terralod reads {FORMAT_VERSION}): rebuild the model "
            "from its source",
            src,
        )
    payload = data[_HEADER.size :]
    if len(payload) != length:
        raise CorruptStoreError(
            f"truncated or padded: payload of {len(payload)} bytes, header says {length}", src
        )
    if hashlib.sha256(payload).digest() != digest:
        raise CorruptStoreError("checksum mismatch: the file is corrupted", src)
    plain = _unpack(payload, src) if flags & _FLAG_LZMA else payload
    view = memoryview(plain)
    lm, shift, pos = 0, 0, 0
    while pos < len(view):
        b = view[pos]
        pos += 1
        lm |= (b & 0x7F) << shift
        shift += 7
        if b < 0x80:
            break
    try:
        meta = json.loads(bytes(view[pos : pos + lm]).decode())
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CorruptStoreError(f"unreadable metadata ({exc})", src) from exc
    arrays = _parse_arrays(bytes(view[pos + lm :]), src)
    return meta, arrays
