"""TileStore: the level-of-detail tiles of one terrain in one SQLite file (``*.terra``).

Integrity (format versions 2 and 3; 3 may hold epochs): ``meta_sha256`` is the SHA-256 of every other meta row (:func:`meta_checksum`),
re-sealed by every metadata write and verified at open, so a changed quantisation or transform is a
:class:`CorruptStoreError`, never wrong coordinates; each tile row has its CRC-32. A store is created
atomically (schema and metadata committed to a temporary beside it, then linked into place) and replaced
atomically (``--overwrite`` builds beside the old one, :func:`install_store` renames it over when complete).
Writers work in WAL mode and leave rollback mode when they close, so readers (``mode=ro``) leave no
``-wal``/``-shm`` behind. Older formats open with one line naming ``terralod check --upgrade``.

Layout
------
``meta(key, value)``  JSON values: format, version, source, source digest, CRS (WKT), transform,
                      spacing, width/height, tile size M, max level, method, build options, per-level
                      quantisation (horizontal fractional bits, vertical step), ``complete`` flag.
``tiles``             one row per tile code (level, x, y): monotone ``error_m`` (one-sided Hausdorff) and
                      ``vertical_error_m``, the raw measured values, RMS, covered sample count, z-range,
                      the quantised geometry and a CRC-32 of everything in the row.

A TIN store (``method = "tin"``, Ai et al. (2019)) holds instead ``meta`` and ``tin_model(name, model, sha256)``:
one detail-increment model as opaque bytes (written by ``terralod.tin``) and their SHA-256;
:func:`write_tin_store` / :func:`read_tin_store`. :meth:`TileStore.open` refuses it with a clear error.

Quantisation (quantized-mesh style, 16 bits per axis, but on a lattice shared by a whole level so the
boundary vertices of neighbouring tiles dequantise to identical coordinates):
``col = col0 + u / 2^f``, ``row = row0 + v / 2^f`` (f per level, see ``TilePyramid.xy_frac_bits``) and
``z = (z0_index + q) * z_step_m`` with one ``z_step_m`` per level. Blobs: the three uint16 columns
zig-zag coded as wrapped 16-bit deltas (as quantized-mesh does), then a zlib stream (written by libdeflate,
read by zlib); triangle indices likewise, 16-bit when every index fits, else 32-bit.

Writes go through transactions (the builder commits batches of finished tiles), so a store killed mid-build
opens with every committed tile and ``complete = false``. The store never imports the builder.
"""

from __future__ import annotations

import hashlib
import json
import os
import sqlite3
import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import deflate
import numpy as np
from affine import Affine

from terralod.errors import CorruptStoreError, StoreError
from terralod.kernels.codec import triangle_codes16, triangle_codes32, undo_zigzag_delta, vertex_codes
from terralod.output import remove_stale_temporaries, temporary_path
from terralod.store_epochs import TILE_COLUMNS, EpochTables
from terralod.tiles import TileCode, TilePyramid

FORMAT_NAME = "terralod-store"
#: Bumped by every change of the store format. 2: the metadata carries a checksum (``meta_sha256``) and a
#: closed store is left in rollback-journal mode (no ``-wal``/``-shm`` beside it). 3: the store may hold
#: epochs (:mod:`terralod.store_epochs`); a reader of version 2 would read only the first epoch's tiles
#: without a word, so it must refuse such a store (it does: it reads only version 2).
FORMAT_VERSION = 3
#: Versions opened as they are (each has the metadata checksum). A version-2 store is a version-3 store
#: without epoch tables; the first epoch tables written into it make it version 3
#: (:meth:`TileStore.add_epoch_tables`).
READABLE_VERSIONS = (2, FORMAT_VERSION)
#: Older versions :func:`upgrade_store` (``terralod check --upgrade``) brings to ``FORMAT_VERSION``.
UPGRADABLE_VERSIONS = (1,)
#: SQLite page size of a new store, bytes, by tile size (:func:`page_size_bytes`). SQLite never splits a
#: row across leaf pages, so a row of more than half a page holds a page alone and a larger one ends in a
#: partly filled overflow page. With the default 4 KiB pages the files were 1.6x their tile blobs for 33²
#: adaptive tiles (1.2-1.35x for 65² and 17²). Measured on Puget Sound 1k (adaptive; file / blobs):
#: 33²: 1 KiB pages 1.11x, 2 KiB 1.14x, 4 KiB 1.60x, 8 KiB 2.07x; 65²: 1.06x, 1.10x, 1.19x, 1.30x;
#: 17²: 1.31x, 1.85x, 1.35x, 1.71x. Reading every tile in random order (33² and 65²) took as long with
#: 2 and 4 KiB pages, and 10-20 % longer with 1 KiB pages (2-6 % once decoded).
PAGE_SIZE_BYTES = 2048
SMALL_TILE_PAGE_SIZE_BYTES = 1024


def page_size_bytes(tile_size: int | None) -> int:
    """SQLite page size of a new store of ``tile_size``² tiles: 2 KiB, or 1 KiB for 17² tiles and smaller
    (their rows are about 1 KiB: one a 2 KiB page)."""
    if tile_size is not None and tile_size <= 17:
        return SMALL_TILE_PAGE_SIZE_BYTES
    return PAGE_SIZE_BYTES


#: SQLite ``PRAGMA application_id`` of a terralod store ("TLOD").
APPLICATION_ID = 0x544C4F44
#: The meta row holding the SHA-256 of every other meta row (see :func:`meta_checksum`).
META_CHECKSUM_KEY = "meta_sha256"
#: Tables a tile store must hold (others, e.g. epochs, may be added by later versions).
REQUIRED_TABLES = ("meta", "tiles")


def meta_checksum(conn: sqlite3.Connection) -> str:
    """SHA-256 of the canonical JSON of every meta row but the checksum itself, ``[[key, value], ...]``
    sorted by key, values as stored. Covers every key, including ones added later (epochs, fractal
    levels): whoever writes meta calls :func:`seal_meta` in the same transaction."""
    rows = conn.execute(
        "SELECT key, value FROM meta WHERE key != ? ORDER BY key", (META_CHECKSUM_KEY,)
    ).fetchall()
    text = json.dumps([[str(k), str(v)] for k, v in rows], separators=(",", ":"), ensure_ascii=True)
    return hashlib.sha256(text.encode("ascii")).hexdigest()


def seal_meta(conn: sqlite3.Connection) -> None:
    """Store the checksum of the meta table; call inside the transaction that changed it."""
    conn.execute(
        "INSERT OR REPLACE INTO meta(key, value) VALUES (?, ?)",
        (META_CHECKSUM_KEY, json.dumps(meta_checksum(conn))),
    )


def verify_meta(conn: sqlite3.Connection, meta: dict[str, Any], path: Path) -> None:
    """Refuse, with one line, a store whose metadata is from another version or fails its checksum."""
    if meta.get("format") != FORMAT_NAME:
        raise CorruptStoreError("not a terralod store (no format marker)", str(path))
    version = meta.get("version")
    if version not in READABLE_VERSIONS:
        if isinstance(version, int) and version > FORMAT_VERSION:
            raise StoreError(
                f"store format version {version} is newer than this terralod (it reads versions "
                f"{', '.join(map(str, READABLE_VERSIONS))}); upgrade terralod to read it",
                str(path),
            )
        if version in UPGRADABLE_VERSIONS:
            raise StoreError(
                f"store format version {version}, this terralod reads {FORMAT_VERSION}; upgrade it with "
                f"`terralod check --upgrade {path}`",
                str(path),
            )
        raise CorruptStoreError(
            f"store format version {version!r}, this terralod reads {FORMAT_VERSION}; rebuild it with "
            "`terralod build SOURCE -o STORE --overwrite`",
            str(path),
        )
    if meta.get(META_CHECKSUM_KEY) != meta_checksum(conn):
        raise CorruptStoreError(
            "metadata fails its checksum (quantisation, transform or levels changed after the build); "
            "rebuild it with `terralod build SOURCE -o STORE --overwrite`",
            str(path),
        )


def _check_header(p: Path) -> None:
    """Refuse, with one line naming the file, anything that is not an SQLite database of terralod's."""
    try:
        with open(p, "rb") as fh:
            head = fh.read(100)
    except OSError as exc:
        raise StoreError(f"cannot read ({exc.strerror or exc})", str(p)) from exc
    if not head:
        raise CorruptStoreError(
            "empty file (0 bytes), not a terralod store; rebuild it with `terralod build SOURCE -o STORE "
            "--overwrite`",
            str(p),
        )
    if len(head) < 100 or not head.startswith(b"SQLite format 3\x00"):
        raise CorruptStoreError("not a terralod store (not an SQLite database)", str(p))
    if int.from_bytes(head[68:72], "big") != APPLICATION_ID:
        raise CorruptStoreError("not a terralod store (foreign SQLite database)", str(p))


# -- atomic files --------------------------------------------------------------------------------------
def _temporary_path(p: Path) -> Path:
    """A hidden name in ``p``'s folder for a file being written (``.NAME.PID.tmp``: same file system, so a
    rename is atomic; :func:`terralod.output.temporary_path`)."""
    return temporary_path(p)


def _remove_stale_temporaries(p: Path) -> None:
    """Remove temporaries of ``p`` left by processes that died, with their SQLite side files (the rule of
    every output's temporaries, :func:`terralod.output.remove_stale_temporaries`)."""
    remove_stale_temporaries(p, remove=remove_store_files)


def _link_into_place(tmp: Path, p: Path) -> None:
    """Give the finished file ``tmp`` the name ``p``, failing if ``p`` appeared meanwhile (no clobbering)."""
    try:
        os.link(tmp, p)
    except FileExistsError:
        raise StoreError("already exists", str(p)) from None
    except OSError:  # a file system without hard links: check, then rename
        if p.exists():
            raise StoreError("already exists", str(p)) from None
        os.replace(tmp, p)
        return
    tmp.unlink(missing_ok=True)


def replacement_path(p: str | os.PathLike[str]) -> Path:
    """Where a store that will replace ``p`` is built (``--overwrite``): the old store stays untouched
    until :func:`install_store` renames the complete new one over it."""
    q = Path(p)
    _remove_stale_temporaries(q)
    return _temporary_path(q)


def remove_store_files(p: str | os.PathLike[str]) -> None:
    """Delete a store file and its SQLite side files."""
    for side in ("", "-journal", "-wal", "-shm"):
        Path(f"{p}{side}").unlink(missing_ok=True)


def install_store(new: str | os.PathLike[str], p: str | os.PathLike[str]) -> None:
    """Atomically replace the store ``p`` by the closed, complete store ``new`` (same folder).

    The old store's WAL is folded into it first (so a kill before the rename leaves the old store whole),
    then side files that would be replayed onto the new file are removed and ``new`` renamed over ``p``.
    """
    new, p = Path(new), Path(p)
    if Path(f"{p}-wal").exists():
        try:
            conn = sqlite3.connect(str(p))
            try:
                conn.execute("PRAGMA wal_checkpoint(TRUNCATE)")
                conn.execute("PRAGMA journal_mode = DELETE")
            finally:
                conn.close()
        except sqlite3.Error:
            pass  # not a database we can fold: it is being replaced anyway
    for side in ("-journal", "-wal", "-shm"):
        Path(f"{p}{side}").unlink(missing_ok=True)
    try:
        os.replace(new, p)
    except OSError as exc:
        raise StoreError(
            f"cannot replace ({exc.strerror or exc}); the new store is at {new}", str(p)
        ) from exc


def upgrade_store(path: str | os.PathLike[str]) -> str:
    """Bring a store of an older format version (:data:`UPGRADABLE_VERSIONS`) to :data:`FORMAT_VERSION`
    in place, in one transaction; returns a line saying what was done.

    1 -> 3: the metadata gets its checksum (computed from the metadata as found: version 1 had none to
    check it against) and the file leaves WAL mode. 2 -> 3: the version number only (a version-2 store
    reads as it is; upgrading it makes sure an older terralod no longer opens it).
    """
    p = Path(path)
    if not p.exists():
        raise StoreError("store not found", str(p))
    _check_header(p)
    try:
        conn = sqlite3.connect(str(p))
    except sqlite3.Error as exc:
        raise StoreError(f"cannot open ({exc})", str(p)) from exc
    try:
        version = _meta_value(conn, "version")
        if version == FORMAT_VERSION:
            return f"{p}: format version {version} is current, nothing to do"
        if version in READABLE_VERSIONS:  # readable as it is: verify before re-sealing
            verify_meta(
                conn, {str(k): json.loads(v) for k, v in conn.execute("SELECT key, value FROM meta")}, p
            )
        elif version not in UPGRADABLE_VERSIONS:
            raise CorruptStoreError(
                f"store format version {version!r} cannot be upgraded; rebuild it", str(p)
            )
        with conn:
            conn.execute(
                "INSERT OR REPLACE INTO meta(key, value) VALUES ('version', ?)", (json.dumps(FORMAT_VERSION),)
            )
            seal_meta(conn)
        conn.execute(f"PRAGMA user_version = {FORMAT_VERSION}")
        conn.execute("PRAGMA journal_mode = DELETE")
    except sqlite3.Error as exc:
        raise StoreError(f"cannot upgrade ({exc})", str(p)) from exc
    finally:
        conn.close()
    what = "metadata checksum added" if version in UPGRADABLE_VERSIONS else "version number only"
    return f"{p}: upgraded from format version {version} to {FORMAT_VERSION} ({what})"


_SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS tiles (
    level INTEGER NOT NULL, x INTEGER NOT NULL, y INTEGER NOT NULL,
    error_m REAL NOT NULL, vertical_error_m REAL NOT NULL,
    measured_error_m REAL NOT NULL, measured_vertical_error_m REAL NOT NULL,
    rms_error_m REAL NOT NULL, n_samples INTEGER NOT NULL,
    z_min_m REAL NOT NULL, z_max_m REAL NOT NULL,
    n_vertices INTEGER NOT NULL, n_triangles INTEGER NOT NULL, z0_index INTEGER NOT NULL,
    vertices BLOB NOT NULL, triangles BLOB NOT NULL, checksum INTEGER NOT NULL,
    PRIMARY KEY (level, x, y)
) WITHOUT ROWID;
"""


# -- blob coding ---------------------------------------------------------------------------------------
def _undo_zigzag_delta16(z: np.ndarray) -> np.ndarray:
    out: np.ndarray = undo_zigzag_delta(z, 0xFFFF).astype(np.uint16)
    return out


def _undo_zigzag_delta32(z: np.ndarray) -> np.ndarray:
    out: np.ndarray = undo_zigzag_delta(z, 0xFFFFFFFF).astype(np.uint32)
    return out


#: Compression level of tile blobs, coded as a zlib stream by libdeflate (the ``deflate`` package; zlib reads
#: it): on the 1,404 blobs of the Pyrenees adaptive store, level 1 codes them 2.2x faster than zlib's level 3
#: did (0.093 against 0.209 s, one thread) into 2.4 % fewer bytes (6.92 against 7.09 MB), and they decode
#: as fast (0.080 against 0.077 s); libdeflate's levels 2-6 were slower and no smaller. Its matchfinder is
#: portable C (no per-CPU variant), so every machine writes the same bytes (a Dask worker as the client).
DEFLATE_LEVEL = 1


def _deflate(raw: np.ndarray) -> bytes:
    """A zlib stream of an array's bytes (libdeflate; the GIL is released while it codes)."""
    return bytes(deflate.zlib_compress(raw.tobytes(), DEFLATE_LEVEL))  # (it returns a bytearray)


def encode_vertices(q: np.ndarray) -> bytes:
    """(N, 3) uint16 quantised (u, v, h) → zlib of the zig-zag wrapped deltas of each column (uint16 LE);
    the codes by :func:`terralod.kernels.codec.vertex_codes` (no GIL: builder threads code in parallel)."""
    codes = vertex_codes(np.ascontiguousarray(q, np.uint16))
    return _deflate(codes.astype("<u2", copy=False))


def _inflate(blob: bytes, n_bytes: int) -> bytes:
    """zlib-decompress at most ``n_bytes`` + 2 bytes (a corrupt or hostile blob cannot inflate beyond it)."""
    d = zlib.decompressobj()
    out = d.decompress(blob, n_bytes + 2)
    if d.unconsumed_tail or len(out) > n_bytes:
        raise ValueError(f"Expected {n_bytes} bytes of codes, got more")
    return out


def decode_vertices(blob: bytes, n: int) -> np.ndarray:
    if not 0 <= n <= 1 << 26:
        raise ValueError(f"Expected a vertex count in 0..2^26, got {n}")
    raw = np.frombuffer(_inflate(blob, 6 * n), dtype="<u2")
    if raw.size != 3 * n:
        raise ValueError(f"Expected {3 * n} vertex codes, got {raw.size}")
    return np.stack([_undo_zigzag_delta16(raw[k * n : (k + 1) * n]) for k in range(3)], axis=1)


def encode_triangles(t: np.ndarray, n_vertices: int | None = None) -> bytes:
    """(K, 3) indices → one width byte (2 or 4) + zlib of zig-zag wrapped deltas of the flat index list
    (codes by :func:`terralod.kernels.codec.triangle_codes16` / ``32``). ``n_vertices``, when given and at
    most 2^16, bounds the indices (every index < n_vertices), so their largest need not be looked for; the
    width is the same as without it."""
    tt = t if t.dtype in (np.int32, np.int64) and t.flags.c_contiguous else np.ascontiguousarray(t, np.int64)
    if tt.size == 0 or (n_vertices is not None and n_vertices <= 65536) or int(tt.max()) < 65536:
        return b"\x02" + _deflate(triangle_codes16(tt).astype("<u2", copy=False))
    return b"\x04" + _deflate(triangle_codes32(tt).astype("<u4", copy=False))


def decode_triangles(blob: bytes, k: int) -> np.ndarray:
    if not 0 <= k <= 1 << 26:
        raise ValueError(f"Expected a triangle count in 0..2^26, got {k}")
    width = blob[:1]
    if width == b"\x02":
        flat = _undo_zigzag_delta16(np.frombuffer(_inflate(blob[1:], 6 * k), dtype="<u2"))
    elif width == b"\x04":
        flat = _undo_zigzag_delta32(np.frombuffer(_inflate(blob[1:], 12 * k), dtype="<u4"))
    else:
        raise ValueError(f"Expected index width 2 or 4, got {width!r}")
    if flat.size != 3 * k:
        raise ValueError(f"Expected {3 * k} indices, got {flat.size}")
    return flat.astype(np.uint32).reshape(k, 3)


def row_checksum(values: tuple[Any, ...], vblob: bytes, tblob: bytes) -> int:
    """CRC-32 of a tile row: the scalar fields (packed) and both blobs."""
    head = struct.pack("<3q6d2d3q", *values)
    return zlib.crc32(tblob, zlib.crc32(vblob, zlib.crc32(head)))


# -- records -------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class EncodedTile:
    """A tile ready for the store (what the builder produces)."""

    code: TileCode
    error_m: float
    vertical_error_m: float
    measured_error_m: float
    measured_vertical_error_m: float
    rms_error_m: float
    n_samples: int
    z_min_m: float
    z_max_m: float
    n_vertices: int
    n_triangles: int
    z0_index: int
    vertices: bytes
    triangles: bytes

    def scalars(self) -> tuple[Any, ...]:
        return (
            *self.code,
            self.error_m,
            self.vertical_error_m,
            self.measured_error_m,
            self.measured_vertical_error_m,
            self.rms_error_m,
            float(self.n_samples),
            self.z_min_m,
            self.z_max_m,
            self.n_vertices,
            self.n_triangles,
            self.z0_index,
        )

    @property
    def checksum(self) -> int:
        return row_checksum(self.scalars(), self.vertices, self.triangles)


@dataclass(frozen=True, eq=False)
class Tile:
    """One decoded tile.

    Attributes
    ----------
    code : (level, x, y)
    vertices : (N, 3) float64 world metres (x east, y north, z up), exactly as stored (dequantised)
    triangles : (K, 3) uint32, counter-clockwise seen from above
    error_m : one-sided Hausdorff distance from every covered source sample to the tile surface, metres,
        made monotone over the pyramid (>= every descendant's)
    vertical_error_m : max vertical distance over the same samples (monotone; an upper bound of error_m)
    measured_error_m, measured_vertical_error_m : the tile's own measurements before the monotone pass
    rms_error_m : RMS vertical distance, metres; n_samples : covered valid source samples
    z_min_m, z_max_m : elevation range of the vertices, metres
    """

    code: TileCode
    vertices: np.ndarray
    triangles: np.ndarray
    grid_rc: np.ndarray
    error_m: float
    vertical_error_m: float
    measured_error_m: float
    measured_vertical_error_m: float
    rms_error_m: float
    n_samples: int
    z_min_m: float
    z_max_m: float


@dataclass(frozen=True)
class LevelQuantisation:
    """The shared 16-bit lattice of one level."""

    xy_frac_bits: int
    z_step_m: float

    @property
    def xy_bound_samples(self) -> float:
        """Largest horizontal rounding error, in source samples (0 for grid vertices)."""
        return 0.5 * 2.0 ** (-self.xy_frac_bits)

    @property
    def z_bound_m(self) -> float:
        """Largest vertical rounding error, metres."""
        return 0.5 * self.z_step_m


# -- the store -----------------------------------------------------------------------------------------
class TileStore(EpochTables):
    """A ``.terra`` file. Open with :func:`open_store` (read) or :meth:`TileStore.create` (build)."""

    def __init__(
        self, path: str | os.PathLike[str], conn: sqlite3.Connection, writable: bool, epoch: str | None = None
    ) -> None:
        self.path = Path(path)
        self._conn = conn
        self.writable = writable
        self.meta = self._read_meta()
        self.pyramid = TilePyramid(
            int(self.meta["width"]), int(self.meta["height"]), int(self.meta["tile_size"])
        )
        t = self.meta["transform"]
        self.transform = Affine(*t[:6])
        self.quantisation = {
            int(k): LevelQuantisation(int(v["xy_frac_bits"]), float(v["z_step_m"]))
            for k, v in self.meta["quantisation"].items()
        }
        self._init_epochs(epoch)  # which epoch's tiles this store reads (terralod.store_epochs)

    # -- opening ---------------------------------------------------------------------------------------
    @classmethod
    def open(
        cls, path: str | os.PathLike[str], *, writable: bool = False, epoch: str | None = None
    ) -> TileStore:
        p = Path(path)
        if not p.exists():
            raise StoreError("store not found", str(p))
        if p.is_dir():
            raise StoreError("is a directory, not a tile store", str(p))
        _check_header(p)
        try:
            uri = f"file:{p.resolve()}" + ("" if writable else "?mode=ro")
            conn = sqlite3.connect(uri, uri=True, check_same_thread=False)
        except sqlite3.Error as exc:
            raise StoreError(f"cannot open ({exc})", str(p)) from exc
        conn.text_factory = _lenient_text  # a damaged file may hold text that is not UTF-8 (found by fuzzing)
        try:
            conn.execute(f"PRAGMA query_only = {0 if writable else 1}")
            ok = conn.execute("PRAGMA quick_check").fetchone()[0]
        except (sqlite3.DatabaseError, ValueError) as exc:
            conn.close()
            raise CorruptStoreError(f"corrupted store ({exc})", str(p)) from exc
        if ok != "ok":
            conn.close()
            detail = " ".join(str(ok).split())[:200]
            raise CorruptStoreError(f"corrupted store (SQLite integrity check: {detail})", str(p))
        if _meta_value(conn, "method") == TIN_METHOD:
            conn.close()
            raise StoreError("holds a TIN detail-increment model (Ai et al., 2019), not tiles", str(p))
        try:
            store = cls(p, conn, writable, epoch)
        except (KeyError, ValueError, TypeError, AttributeError, IndexError, sqlite3.DatabaseError) as exc:
            conn.close()
            raise CorruptStoreError(
                f"corrupted store metadata ({type(exc).__name__}: {exc})", str(p)
            ) from exc
        except BaseException:
            conn.close()
            raise
        if writable:  # a writer works in WAL mode (readers alongside); close() leaves rollback mode again
            try:
                conn.execute("PRAGMA journal_mode = WAL")
            except sqlite3.Error as exc:
                conn.close()
                raise StoreError(f"cannot open for writing ({exc})", str(p)) from exc
        return store

    @classmethod
    def create(cls, path: str | os.PathLike[str], meta: dict[str, Any]) -> TileStore:
        """Create a new store with ``meta`` (fails if the file exists).

        Atomic: schema and metadata are committed to a temporary file in the same folder, which is then
        linked into place, so ``path`` is either absent or a store that opens (and resumes), never a
        0-byte or half-initialised file, whenever the process dies.
        """
        p = Path(path)
        if p.exists() or p.is_symlink():
            raise StoreError("already exists", str(p))
        parent = p.resolve().parent
        if not parent.is_dir():
            raise StoreError(f"output folder {parent} does not exist", str(p))
        if not os.access(parent, os.W_OK):
            raise StoreError(f"output folder {parent} is not writable", str(p))
        _remove_stale_temporaries(p)
        tmp = _temporary_path(p)
        try:
            conn = sqlite3.connect(str(tmp))
            try:
                page = page_size_bytes(meta.get("tile_size"))
                conn.execute(f"PRAGMA page_size = {page}")  # before any table
                conn.execute(f"PRAGMA application_id = {APPLICATION_ID}")
                conn.execute(f"PRAGMA user_version = {FORMAT_VERSION}")
                with conn:
                    conn.executescript(_SCHEMA)
                    full = {"format": FORMAT_NAME, "version": FORMAT_VERSION, "complete": False, **meta}
                    conn.executemany(
                        "INSERT INTO meta(key, value) VALUES (?, ?)",
                        [(k, json.dumps(v, sort_keys=True)) for k, v in full.items()],
                    )
                    seal_meta(conn)
            finally:
                conn.close()
            _link_into_place(tmp, p)
        except (sqlite3.Error, OSError) as exc:
            tmp.unlink(missing_ok=True)
            if isinstance(exc, StoreError):
                raise
            raise StoreError(f"cannot write ({exc})", str(p)) from exc
        return cls.open(p, writable=True)

    def _read_meta(self) -> dict[str, Any]:
        try:
            rows = self._conn.execute("SELECT key, value FROM meta").fetchall()
        except sqlite3.DatabaseError as exc:
            raise CorruptStoreError(f"not a terralod store ({exc})", str(self.path)) from exc
        meta = {k: json.loads(v) for k, v in rows}
        verify_meta(self._conn, meta, self.path)
        tables = {r[0] for r in self._conn.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
        missing = [t for t in REQUIRED_TABLES if t not in tables]
        if missing:
            raise CorruptStoreError(f"corrupted store (no {', '.join(missing)} table)", str(self.path))
        return meta

    def close(self) -> None:
        """Close; a writer folds its WAL back into the file and leaves rollback mode, so no ``-wal`` /
        ``-shm`` stays beside a closed store (skipped while other connections hold it)."""
        if self.writable:
            try:
                self._conn.execute("PRAGMA wal_checkpoint(TRUNCATE)")
                self._conn.execute("PRAGMA journal_mode = DELETE")
            except sqlite3.Error:
                pass  # busy (a reader holds it) or read-only file system: the WAL stays, still consistent
        self._conn.close()

    def __enter__(self) -> TileStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- metadata --------------------------------------------------------------------------------------
    @property
    def levels(self) -> list[int]:
        """Levels present in the plan, coarsest (0) first."""
        return self.pyramid.levels

    @property
    def tile_size(self) -> int:
        return self.pyramid.tile_size

    @property
    def complete(self) -> bool:
        return bool(
            json.loads(self._conn.execute("SELECT value FROM meta WHERE key='complete'").fetchone()[0])
        )

    @property
    def crs(self) -> str | None:
        return self.meta.get("crs")

    @property
    def spacing_m(self) -> tuple[float, float]:
        return float(self.transform.a), float(-self.transform.e)

    def set_meta(self, key: str, value: Any) -> None:
        """Set one meta value and re-seal the metadata checksum, in one transaction."""
        self.set_metas({key: value})

    def set_metas(self, values: dict[str, Any]) -> None:
        """Set several meta values and re-seal the metadata checksum, in one transaction."""
        if not self.writable:
            raise StoreError("store opened read-only", str(self.path))
        if META_CHECKSUM_KEY in values:
            raise ValueError(f"{META_CHECKSUM_KEY} is computed, not set")
        try:
            with self._conn:
                self._conn.executemany(
                    "INSERT OR REPLACE INTO meta(key, value) VALUES (?, ?)",
                    [(k, json.dumps(v, sort_keys=True)) for k, v in values.items()],
                )
                seal_meta(self._conn)
        except sqlite3.Error as exc:
            raise StoreError(f"cannot write metadata ({exc})", str(self.path)) from exc
        self.meta.update(values)
        self.meta[META_CHECKSUM_KEY] = _meta_value(self._conn, META_CHECKSUM_KEY)

    # -- tiles -----------------------------------------------------------------------------------------
    def tile_codes(self, level: int | None = None) -> list[TileCode]:
        """Codes of the stored tiles (of one level, or all), sorted by (level, y, x)."""
        q = f"SELECT level, x, y FROM {self._tiles_src}"
        args: tuple[int, ...] = ()
        if level is not None:
            q += " WHERE level = ?"
            args = (level,)
        return sorted(
            ((int(k), int(x), int(y)) for k, x, y in self._conn.execute(q, args)),
            key=lambda c: (c[0], c[2], c[1]),
        )

    def each_tile_code(self, level: int) -> Iterator[TileCode]:
        """Codes of the stored tiles of ``level`` in raster order (y, then x), read as taken."""
        q = f"SELECT x, y FROM {self._tiles_src} WHERE level = ? ORDER BY y, x"
        return ((level, int(x), int(y)) for x, y in self._conn.execute(q, (level,)))

    def tile_vertex_counts(self, level: int) -> dict[TileCode, int]:
        """{code: vertices} of the stored tiles of ``level`` (no geometry read)."""
        q = f"SELECT x, y, n_vertices FROM {self._tiles_src} WHERE level = ?"
        return {(level, int(x), int(y)): int(n) for x, y, n in self._conn.execute(q, (level,))}

    def each_tile_error_measured(
        self, level: int
    ) -> Iterator[tuple[TileCode, tuple[float, float], tuple[float, float]]]:
        """(code, (error_m, vertical_error_m), (measured_error_m, measured_vertical_error_m)) of the stored
        tiles of ``level``, read as taken."""
        q = (f"SELECT x, y, error_m, vertical_error_m, measured_error_m, measured_vertical_error_m "
             f"FROM {self._tiles_src} WHERE level = ?")  # fmt: skip
        return (
            ((level, int(x), int(y)), (e, v), (me, mv))
            for x, y, e, v, me, mv in self._conn.execute(q, (level,))
        )

    def has_tiles(self) -> bool:
        """Whether the store (its selected epoch) holds any tile: one row looked at, not every one."""
        return self._conn.execute(f"SELECT 1 FROM {self._tiles_src} LIMIT 1").fetchone() is not None

    def stored_levels(self) -> list[int]:
        """The levels that hold at least one stored tile (whatever the pyramid plans)."""
        return [
            int(k)
            for (k,) in self._conn.execute(f"SELECT DISTINCT level FROM {self._tiles_src} ORDER BY level")
        ]

    def __contains__(self, code: object) -> bool:
        if not (isinstance(code, tuple) and len(code) == 3):
            return False
        q = f"SELECT 1 FROM {self._tiles_src} WHERE level=? AND x=? AND y=?"
        r = self._conn.execute(q, code).fetchone()
        return r is not None

    def tile_errors(self) -> dict[TileCode, tuple[float, float]]:
        """{code: (error_m, vertical_error_m)} of every stored tile (cheap: no geometry)."""
        return dict(self.each_tile_error())

    def each_tile_error(self) -> Iterator[tuple[TileCode, tuple[float, float]]]:
        """(code, (error_m, vertical_error_m)) of every stored tile, read as taken (no dict of them all)."""
        rows = self._conn.execute(f"SELECT level, x, y, error_m, vertical_error_m FROM {self._tiles_src}")
        return (((k, x, y), (e, v)) for k, x, y, e, v in rows)

    def level_summaries(self) -> dict[int, dict[str, Any]]:
        """{level: tiles, vertices, triangles, max errors, sum of RMS² x samples, samples, bytes, and the
        z range of its tiles with vertices} over the stored tiles, summed by SQLite (one row a level held:
        a region's summary without a row a tile in memory)."""
        q = (
            "SELECT level, COUNT(*), SUM(n_vertices), SUM(n_triangles), MAX(error_m), MAX(vertical_error_m), "
            "SUM(rms_error_m * rms_error_m * n_samples), SUM(n_samples), SUM(length(vertices) + length(triangles)), "
            "MIN(CASE WHEN n_vertices > 0 THEN z_min_m END), MAX(CASE WHEN n_vertices > 0 THEN z_max_m END) "
            f"FROM {self._tiles_src} GROUP BY level"
        )
        names = ("tiles", "vertices", "triangles", "max_error_m", "max_vertical_error_m", "sum_rms_sq", "samples",
                 "bytes", "z_min_m", "z_max_m")  # fmt: skip
        return {int(r[0]): dict(zip(names, r[1:], strict=True)) for r in self._conn.execute(q)}

    def tile_summaries(self) -> list[dict[str, Any]]:
        """Per-tile scalars (no geometry): code, errors, z-range, counts."""
        cols = (
            "level, x, y, error_m, vertical_error_m, measured_error_m, measured_vertical_error_m, rms_error_m, "
            "n_samples, z_min_m, z_max_m, n_vertices, n_triangles, length(vertices) + length(triangles)"
        )
        names = [c.strip() for c in cols.split(",")]
        names[-1] = "bytes"
        rows = self._conn.execute(f"SELECT {cols} FROM {self._tiles_src}")
        return [dict(zip(names, r, strict=True)) for r in rows]

    def each_tile_extent(self) -> Iterator[tuple[int, int, int, float, float, float, float]]:
        """(level, x, y, error_m, vertical_error_m, z_min_m, z_max_m) of every tile, by level, then row, then
        column, read as a stream (what a LOD tree needs, without a row object a tile)."""
        q = (
            f"SELECT level, x, y, error_m, vertical_error_m, z_min_m, z_max_m FROM {self._tiles_src} "
            "ORDER BY level, y, x"
        )
        yield from self._conn.execute(q)

    def write_tiles(self, tiles: list[EncodedTile]) -> None:
        """Insert finished tiles in one transaction."""
        if not self.writable:
            raise StoreError("store opened read-only", str(self.path))
        rows = [
            (*t.scalars()[:8], t.n_samples, *t.scalars()[9:], t.vertices, t.triangles, t.checksum)
            for t in tiles
        ]
        try:
            with self._conn:
                self._insert_tile_rows(rows)  # table tiles, or an epoch's revision (terralod.store_epochs)
        except sqlite3.Error as exc:
            raise StoreError(
                f"cannot write the store ({exc}; is the disk full?); the tiles committed so far are kept: "
                "free space, then run the same command with --resume",
                str(self.path),
            ) from exc

    def raw_tile(self, level: int, x: int, y: int) -> EncodedTile:
        """The stored row of a tile, checksum verified."""
        try:
            r = self._tile_row(level, x, y)  # of the selected epoch
        except sqlite3.DatabaseError as exc:
            raise CorruptStoreError(f"tile {(level, x, y)} cannot be read ({exc})", str(self.path)) from exc
        if r is None:
            raise KeyError(f"tile {(level, x, y)} is not in {self.path}")
        try:
            (k, tx, ty, e, ev, me, mev, rms, ns, zmin, zmax, nv, nt, z0, vb, tb, ck) = r
            t = EncodedTile(
                (k, tx, ty), e, ev, me, mev, rms, ns, zmin, zmax, nv, nt, z0, bytes(vb), bytes(tb)
            )
            ok = t.checksum == ck
        except (ValueError, TypeError, struct.error) as exc:
            raise CorruptStoreError(
                f"tile {(level, x, y)} has a malformed row ({exc})", str(self.path)
            ) from exc
        if not ok:
            raise CorruptStoreError(f"tile {(level, x, y)} fails its checksum", str(self.path))
        return t

    def tile(self, level: int, x: int, y: int) -> Tile:
        """Decode tile (level, x, y): vertices in world metres exactly as stored."""
        t = self.raw_tile(level, x, y)
        try:
            q = decode_vertices(t.vertices, t.n_vertices)
            tris = decode_triangles(t.triangles, t.n_triangles)
            if tris.size and int(tris.max()) >= t.n_vertices:
                raise ValueError(f"triangle index {int(tris.max())} beyond {t.n_vertices} vertices")
            rows, cols, z = self.dequantise(t.code, q, t.z0_index)
        except (zlib.error, ValueError, KeyError, OverflowError) as exc:
            raise CorruptStoreError(
                f"tile {(level, x, y)} cannot be decoded ({exc})", str(self.path)
            ) from exc
        x0, y0 = self.transform.c + 0.5 * self.transform.a, self.transform.f + 0.5 * self.transform.e
        verts = np.empty((t.n_vertices, 3), np.float64)
        verts[:, 0] = x0 + cols * self.transform.a
        verts[:, 1] = y0 + rows * self.transform.e
        verts[:, 2] = z
        return Tile(
            t.code, verts, tris, np.stack([rows, cols], axis=1), t.error_m, t.vertical_error_m,
            t.measured_error_m, t.measured_vertical_error_m, t.rms_error_m, t.n_samples, t.z_min_m, t.z_max_m,
        )  # fmt: skip

    def dequantise(
        self, code: TileCode, q: np.ndarray, z0_index: int
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Quantised (u, v, h) → (rows, cols) source sample coordinates and heights in metres."""
        lq = self.quantisation[code[0]]
        r0, c0 = self.pyramid.origin_rc(code)
        scale = 2.0 ** (-lq.xy_frac_bits)  # bits < 0: a step over a sample (level 0 of > 32,769)
        cols = c0 + q[:, 0].astype(np.float64) * scale
        rows = r0 + q[:, 1].astype(np.float64) * scale
        z = (z0_index + q[:, 2].astype(np.int64)).astype(np.float64) * lq.z_step_m
        return rows, cols, z

    def iter_tiles(self, level: int | None = None) -> Iterator[Tile]:
        for c in self.tile_codes(level):
            yield self.tile(*c)

    def verify(self) -> list[TileCode]:
        """Codes of tiles whose checksum or decoding fails (empty for a sound store)."""
        bad = []
        for c in self.tile_codes():
            try:
                self.tile(*c)
            except CorruptStoreError:
                bad.append(c)
        return bad

    def add_epoch_tables(self) -> None:
        """Create the epoch tables (idempotent); a version-2 store becomes version 3 in doing so."""
        super().add_epoch_tables()
        if self.meta.get("version") != FORMAT_VERSION:
            self.set_metas({"version": FORMAT_VERSION})
            try:
                self._conn.execute(f"PRAGMA user_version = {FORMAT_VERSION}")
            except sqlite3.Error as exc:
                raise StoreError(f"cannot write the format version ({exc})", str(self.path)) from exc

    def checksum_failures(self) -> list[TileCode]:
        """Codes of tiles whose row fails its checksum (blobs not decoded; :meth:`verify` decodes too),
        in one pass over the selected epoch's rows."""
        bad: list[TileCode] = []
        try:
            for r in self._conn.execute(f"SELECT {TILE_COLUMNS} FROM {self._tiles_src}"):
                (k, tx, ty, e, ev, me, mev, rms, ns, zmin, zmax, nv, nt, z0, vb, tb, ck) = r
                try:
                    values = (k, tx, ty, e, ev, me, mev, rms, float(ns), zmin, zmax, nv, nt, z0)
                    ok = row_checksum(values, bytes(vb), bytes(tb)) == ck
                except (ValueError, TypeError, struct.error):
                    ok = False
                if not ok:
                    bad.append((k, tx, ty))
        except sqlite3.DatabaseError as exc:
            raise CorruptStoreError(f"tiles cannot be read ({exc})", str(self.path)) from exc
        return bad

    def size_bytes(self) -> int:
        return sum(os.path.getsize(p) for p in (self.path, Path(f"{self.path}-wal")) if os.path.exists(p))


def open_store(path: str | os.PathLike[str], epoch: str | None = None) -> TileStore:
    """Open a ``.terra`` store read-only; use as a context manager.

    >>> with open_store("dem.terra") as s:  # doctest: +SKIP
    ...     t = s.tile(0, 0, 0); t.vertices.shape, t.error_m
    """
    return TileStore.open(path, writable=False, epoch=epoch)


# -- TIN detail-increment models (Ai et al., 2019) ------------------------------------------------------------
#: ``method`` of a store holding one TIN detail-increment model (``terralod.tin``) instead of tiles.
TIN_METHOD = "tin"

_TIN_SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS tin_model (name TEXT PRIMARY KEY, model BLOB NOT NULL, sha256 TEXT NOT NULL);
"""


def _lenient_text(raw: bytes) -> str:
    """SQLite text as str, undecodable bytes replaced (so damage is reported, not raised as UnicodeError)."""
    return raw.decode("utf-8", "replace")


def _meta_value(conn: sqlite3.Connection, key: str) -> Any:
    """One meta value (JSON-decoded), None when absent or unreadable."""
    try:
        row = conn.execute("SELECT value FROM meta WHERE key = ?", (key,)).fetchone()
        return None if row is None else json.loads(row[0])
    except (sqlite3.DatabaseError, ValueError):
        return None


def write_tin_store(
    path: str | os.PathLike[str], meta: dict[str, Any], model: bytes, *, overwrite: bool = False
) -> int:
    """Write a ``.terra`` holding one TIN model: ``meta`` plus the model's bytes, in one transaction.

    The model bytes are opaque here (the store never imports their producer); their SHA-256 is kept
    beside them. The file is written under a temporary name and renamed, so a failed write never leaves
    a half store nor damages an existing one. Returns the file size, bytes.
    """
    p = Path(path)
    if p.exists() and not overwrite:
        raise StoreError("already exists (pass overwrite to replace it)", str(p))
    parent = p.resolve().parent
    if not parent.is_dir():
        raise StoreError(f"output folder {parent} does not exist", str(p))
    if p.is_dir():
        raise StoreError("is a directory, not a store", str(p))
    _remove_stale_temporaries(p)
    tmp = _temporary_path(p)
    full = {"format": FORMAT_NAME, "version": FORMAT_VERSION, **meta, "method": TIN_METHOD, "complete": True}
    try:
        conn = sqlite3.connect(str(tmp))
        try:
            conn.execute(f"PRAGMA application_id = {APPLICATION_ID}")
            conn.execute(f"PRAGMA user_version = {FORMAT_VERSION}")
            with conn:
                conn.executescript(_TIN_SCHEMA)
                conn.executemany(
                    "INSERT INTO meta(key, value) VALUES (?, ?)",
                    [(k, json.dumps(v, sort_keys=True)) for k, v in full.items()],
                )
                conn.execute(
                    "INSERT INTO tin_model(name, model, sha256) VALUES ('model', ?, ?)",
                    (model, hashlib.sha256(model).hexdigest()),
                )
                seal_meta(conn)
        finally:
            conn.close()
        if p.exists():
            install_store(tmp, p)
        else:
            _link_into_place(tmp, p)
    except (sqlite3.Error, OSError) as exc:
        remove_store_files(tmp)
        if isinstance(exc, StoreError):
            raise
        raise StoreError(
            f"cannot write ({exc.strerror if isinstance(exc, OSError) else exc})", str(p)
        ) from exc
    return p.stat().st_size


def store_method(path: str | os.PathLike[str]) -> str | None:
    """The ``method`` meta of a ``.terra`` (``"tin"`` for a TIN model), None when unreadable or absent."""
    p = Path(path)
    try:
        conn = sqlite3.connect(f"file:{p.resolve()}?mode=ro", uri=True)
    except sqlite3.Error:
        return None
    try:
        method = _meta_value(conn, "method")
        return None if method is None else str(method)
    finally:
        conn.close()


def tin_model_sha256(path: str | os.PathLike[str]) -> str | None:
    """The SHA-256 a TIN store records for its model (what :func:`read_tin_store` verifies), or None when
    the file holds none or cannot be read."""
    try:
        conn = sqlite3.connect(f"file:{Path(path).resolve()}?mode=ro", uri=True)
        try:
            row = conn.execute("SELECT sha256 FROM tin_model WHERE name = 'model'").fetchone()
        finally:
            conn.close()
    except sqlite3.DatabaseError:
        return None
    return None if row is None else str(row[0])


def read_tin_store(path: str | os.PathLike[str]) -> tuple[dict[str, Any], bytes]:
    """(meta, model bytes) of a store written by :func:`write_tin_store`, the model's SHA-256 verified.

    Raises StoreError when missing, CorruptStoreError when foreign, damaged or not a TIN store.
    """
    p = Path(path)
    if not p.exists():
        raise StoreError("store not found", str(p))
    _check_header(p)
    try:
        conn = sqlite3.connect(f"file:{p.resolve()}?mode=ro", uri=True)
        conn.text_factory = _lenient_text
        try:
            meta = {k: json.loads(v) for k, v in conn.execute("SELECT key, value FROM meta")}
            verify_meta(conn, meta, p)
            if meta.get("method") != TIN_METHOD:
                raise CorruptStoreError("holds tiles, not a TIN model", str(p))
            row = conn.execute("SELECT model, sha256 FROM tin_model WHERE name = 'model'").fetchone()
        finally:
            conn.close()
    except (sqlite3.DatabaseError, ValueError, TypeError) as exc:
        raise CorruptStoreError(f"corrupted TIN store ({' '.join(str(exc).split())[:200]})", str(p)) from exc
    if row is None:
        raise CorruptStoreError("TIN store without a model", str(p))
    blob = bytes(row[0])
    if hashlib.sha256(blob).hexdigest() != row[1]:
        raise CorruptStoreError("TIN model fails its checksum", str(p))
    return meta, blob
