"""Epochs of one terrain in one ``.terra`` store: the tables and the SQL of :class:`terralod.store.TileStore`.

Layout (tables added to a tile store when it gets epochs: ``build --epoch`` or a first ``update``; a store
without them reads as one unnamed epoch, exactly as before)
---------------------------------------------------------------------------------------------------------
``tiles``          unchanged: the tiles the store was first built with ("rev 0").
``tile_revs``      tiles rebuilt by a later epoch: the tile columns with ``rev``, the id of that epoch;
                   primary key (level, x, y, rev).
``epochs``         ``id`` (creation order, never reused), ``name`` (e.g. an ISO date), ``state``
                   (``building`` | ``complete``) and ``info`` (JSON: source, digest, fill, what was rebuilt).
``epoch_tiles``    (epoch, level, x, y) -> rev: the tiles of an epoch. An epoch shares every tile it did
                   not rebuild with the epoch before it by pointing at that tile's row (no copy).
``source_blocks``  content-addressed zlib blocks of 64 x 64 source samples (float32 elevation + packed
                   validity; key: sha256 of the stored bytes), so an epoch's grid is kept exactly as built,
``epoch_source``   (epoch, block) -> digest: unchanged blocks are shared between epochs like tiles.

Transactions: a first build writes each batch of tiles and their ``epoch_tiles`` rows together (a killed
build opens with its committed tiles, as before). An update writes its rebuilt tiles under its own rev —
invisible to every reader, who reads tiles through ``epoch_tiles`` of a *complete* epoch — and then commits
the new epoch's whole ``epoch_tiles`` map and ``state = complete`` in one transaction: a reader sees the old
epoch or the new one, never a mix, and a killed update leaves every earlier epoch's rows untouched.
Deleting an epoch removes its map, then every tile row and source block no epoch refers to any more.

The store never imports the builder; this module imports nothing of terralod but its errors.
"""

from __future__ import annotations

import hashlib
import json
import sqlite3
import zlib
from typing import Any

import numpy as np

#: The tile columns in table order (what :meth:`TileStore.raw_tile` reads).
TILE_COLUMNS = (
    "level, x, y, error_m, vertical_error_m, measured_error_m, measured_vertical_error_m, rms_error_m, "
    "n_samples, z_min_m, z_max_m, n_vertices, n_triangles, z0_index, vertices, triangles, checksum"
)

EPOCH_SCHEMA = """
CREATE TABLE IF NOT EXISTS tile_revs (
    level INTEGER NOT NULL, x INTEGER NOT NULL, y INTEGER NOT NULL, rev INTEGER NOT NULL,
    error_m REAL NOT NULL, vertical_error_m REAL NOT NULL,
    measured_error_m REAL NOT NULL, measured_vertical_error_m REAL NOT NULL,
    rms_error_m REAL NOT NULL, n_samples INTEGER NOT NULL,
    z_min_m REAL NOT NULL, z_max_m REAL NOT NULL,
    n_vertices INTEGER NOT NULL, n_triangles INTEGER NOT NULL, z0_index INTEGER NOT NULL,
    vertices BLOB NOT NULL, triangles BLOB NOT NULL, checksum INTEGER NOT NULL,
    PRIMARY KEY (level, x, y, rev)
) WITHOUT ROWID;
CREATE TABLE IF NOT EXISTS epochs (
    id INTEGER PRIMARY KEY AUTOINCREMENT, name TEXT NOT NULL UNIQUE, state TEXT NOT NULL, info TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS epoch_tiles (
    epoch INTEGER NOT NULL, level INTEGER NOT NULL, x INTEGER NOT NULL, y INTEGER NOT NULL,
    rev INTEGER NOT NULL, PRIMARY KEY (epoch, level, x, y)
) WITHOUT ROWID;
CREATE INDEX IF NOT EXISTS epoch_tiles_rev ON epoch_tiles (level, x, y, rev);
CREATE TABLE IF NOT EXISTS source_blocks (digest TEXT PRIMARY KEY, data BLOB NOT NULL) WITHOUT ROWID;
CREATE TABLE IF NOT EXISTS epoch_source (
    epoch INTEGER NOT NULL, block INTEGER NOT NULL, digest TEXT NOT NULL, PRIMARY KEY (epoch, block)
) WITHOUT ROWID;
"""

#: Name given to the tiles of a store built without ``--epoch`` when it gets a second epoch.
DEFAULT_EPOCH = "base"
#: Side of a source block, samples.
SOURCE_BLOCK = 64
_COLS = [c.strip() for c in TILE_COLUMNS.split(",")]


def _has_table(conn: sqlite3.Connection, name: str) -> bool:
    r = conn.execute("SELECT 1 FROM sqlite_master WHERE type='table' AND name=?", (name,)).fetchone()
    return r is not None


def _epoch_src(eid: int) -> str:
    """SQL of the tile rows of epoch ``eid`` (TILE_COLUMNS), through its map."""
    cols = ", ".join(f"t.{c}" for c in _COLS)
    on = "t.level = e.level AND t.x = e.x AND t.y = e.y"
    return (
        f"(SELECT {cols} FROM epoch_tiles e JOIN tiles t ON {on} WHERE e.epoch = {eid} AND e.rev = 0 "
        f"UNION ALL SELECT {cols} FROM epoch_tiles e JOIN tile_revs t ON {on} AND t.rev = e.rev "
        f"WHERE e.epoch = {eid} AND e.rev > 0)"
    )


def epoch_record(hf: Any, kind: str, **extra: Any) -> dict[str, Any]:
    """The info kept with an epoch built from heightfield ``hf`` (``kind``: build, update or edit)."""
    import datetime

    return {
        "kind": kind,
        "source": str(hf.source),
        "source_digest": hf.digest(),
        "fill_method": hf.fill_method,
        "notes": list(hf.notes),
        "created": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        **extra,
    }


class EpochTables:
    """The epoch half of :class:`terralod.store.TileStore` (mixed in; uses its ``_conn``, ``path``, ``meta``).

    After :meth:`_init_epochs` a store reads the tiles of one epoch (``epoch``): the one asked for, else
    the latest complete one (else, for a first build still running, that build's).
    """

    _conn: sqlite3.Connection
    writable: bool
    meta: dict[str, Any]
    path: Any

    # -- selection -----------------------------------------------------------------------------------
    def _init_epochs(self, epoch: str | None) -> None:
        from terralod.errors import StoreError

        self.has_epochs = _has_table(self._conn, "epochs")
        self.epoch: str | None = None
        self.epoch_id: int | None = None
        self.write_rev = 0  # rev of the rows written now: 0 = table tiles
        self._write_epoch: int | None = None  # epoch whose map grows with the rows written (first build)
        self._tiles_src = "tiles"
        if not self.has_epochs:
            if epoch is not None:
                raise StoreError(f"has no epochs; cannot select epoch {epoch!r}", str(self.path))
            return
        rows = self.epoch_rows()
        done = [r for r in rows if r["state"] == "complete"]
        if epoch is not None:
            pick = next((r for r in done if r["name"] == str(epoch)), None)
            if pick is None:
                names = ", ".join(r["name"] for r in done) or "none"
                raise StoreError(f"has no epoch {epoch!r} (epochs: {names})", str(self.path))
        elif done:
            pick = done[-1]
        else:
            pick = rows[0] if rows else None  # a first build in progress: its own tiles
            if pick is not None:
                self._write_epoch = int(pick["id"])
        self._select(pick)

    def _select(self, row: dict[str, Any] | None) -> None:
        if row is None:
            self.epoch, self.epoch_id = None, None
            self._tiles_src = f"(SELECT {TILE_COLUMNS} FROM tiles WHERE 0)"
            return
        self.epoch, self.epoch_id = str(row["name"]), int(row["id"])
        self._tiles_src = _epoch_src(self.epoch_id)

    def _tile_row(self, level: int, x: int, y: int) -> tuple[Any, ...] | None:
        """The stored row (TILE_COLUMNS) of a tile of the selected epoch, None when absent."""
        if self.has_epochs:
            r = self._conn.execute(
                "SELECT rev FROM epoch_tiles WHERE epoch = ? AND level = ? AND x = ? AND y = ?",
                (self.epoch_id if self.epoch_id is not None else -1, level, x, y),
            ).fetchone()
            if r is None:
                return None
            if int(r[0]) > 0:
                return self._conn.execute(
                    f"SELECT {TILE_COLUMNS} FROM tile_revs WHERE level=? AND x=? AND y=? AND rev=?",
                    (level, x, y, int(r[0])),
                ).fetchone()
        return self._conn.execute(
            f"SELECT {TILE_COLUMNS} FROM tiles WHERE level=? AND x=? AND y=?", (level, x, y)
        ).fetchone()

    def epoch_rows(self) -> list[dict[str, Any]]:
        """Every epoch row (complete and building), in creation order: id, name, state, info."""
        if not getattr(self, "has_epochs", False):
            return []
        out = []
        for i, name, state, info in self._conn.execute(
            "SELECT id, name, state, info FROM epochs ORDER BY id"
        ):
            out.append({"id": int(i), "name": str(name), "state": str(state), "info": json.loads(info)})
        return out

    @property
    def epochs(self) -> list[str]:
        """Names of the complete epochs, in the order they were added (the last is the default)."""
        return [r["name"] for r in self.epoch_rows() if r["state"] == "complete"]

    def epoch_info(self, name: str | None = None) -> dict[str, Any]:
        """The info of epoch ``name`` (default: the selected one) with its id, name and state."""
        name = self.epoch if name is None else name
        for r in self.epoch_rows():
            if r["name"] == name:
                return dict(r["info"], id=r["id"], state=r["state"], name=r["name"])
        raise KeyError(name)

    # -- writing ---------------------------------------------------------------------------------------
    def _insert_tile_rows(self, rows: list[tuple[Any, ...]]) -> None:
        """Insert tile rows (TILE_COLUMNS order) under this store's write rev; call inside a transaction."""
        if self.write_rev == 0:
            self._conn.executemany(
                f"INSERT OR REPLACE INTO tiles ({TILE_COLUMNS}) VALUES ({','.join('?' * 17)})", rows
            )
        else:
            self._conn.executemany(
                f"INSERT OR REPLACE INTO tile_revs ({TILE_COLUMNS}, rev) VALUES ({','.join('?' * 18)})",
                [(*r, self.write_rev) for r in rows],
            )
        if self._write_epoch is not None:
            self._conn.executemany(
                "INSERT OR REPLACE INTO epoch_tiles VALUES (?, ?, ?, ?, ?)",
                [(self._write_epoch, r[0], r[1], r[2], self.write_rev) for r in rows],
            )

    def add_epoch_tables(self) -> None:
        """Create the epoch tables (idempotent)."""
        with self._conn:
            self._conn.executescript(EPOCH_SCHEMA)
        self.has_epochs = True

    def adopt_tiles_as_epoch(self, name: str, info: dict[str, Any]) -> int:
        """A store without epochs: its tiles become complete epoch ``name`` (one transaction)."""
        self.add_epoch_tables()
        with self._conn:
            cur = self._conn.execute(
                "INSERT INTO epochs (name, state, info) VALUES (?, 'complete', ?)",
                (str(name), json.dumps(info, sort_keys=True)),
            )
            eid = int(cur.lastrowid or 0)
            self._conn.execute(f"INSERT INTO epoch_tiles SELECT {eid}, level, x, y, 0 FROM tiles")
        self._select({"id": eid, "name": str(name)})
        return eid

    def begin_epoch(self, name: str, info: dict[str, Any]) -> int:
        """Add epoch ``name`` in state ``building`` and write new tiles under it; returns its id. The first
        epoch of a store maps its tiles as they are written (into table ``tiles``); a later one writes
        ``tile_revs`` and maps its tiles only at :meth:`commit_epoch`."""
        self.add_epoch_tables()
        first = not self.epoch_rows()
        with self._conn:
            cur = self._conn.execute(
                "INSERT INTO epochs (name, state, info) VALUES (?, 'building', ?)",
                (str(name), json.dumps(info, sort_keys=True)),
            )
        eid = int(cur.lastrowid or 0)
        if first:
            self.write_rev, self._write_epoch = 0, eid
            self._select({"id": eid, "name": str(name)})
        else:
            self.write_rev, self._write_epoch = eid, None
        return eid

    def start_first_epoch(self, name: str, hf: Any) -> int:
        """A build with ``--epoch``: begin (or, resumed, find) the store's first epoch ``name`` and keep
        the heightfield ``hf``'s samples with it. Tiles already in table ``tiles`` join its map."""
        return self.start_first_epoch_from(
            name, epoch_record(hf, "build"), lambda eid: self.put_epoch_source(eid, hf.elevation_m, hf.valid),
            hf.valid_range_m(),
        )  # fmt: skip

    def start_first_epoch_from(self, name: str, record: dict[str, Any], put_source: Any,
                               z_range_m: tuple[float, float]) -> int:  # fmt: skip
        """:meth:`start_first_epoch` of a grid never held whole: ``record`` (:func:`epoch_record`),
        ``put_source(eid)`` keeps the samples (e.g. :meth:`put_epoch_source_strips`), ``z_range_m`` their
        elevation range."""
        from terralod.errors import BuildMismatchError

        rows = self.epoch_rows()
        if not rows:
            eid = self.begin_epoch(name, record)
            with self._conn:
                self._conn.execute(
                    f"INSERT OR REPLACE INTO epoch_tiles SELECT {eid}, level, x, y, 0 FROM tiles"
                )
        elif rows[0]["name"] != name:
            raise BuildMismatchError(
                f"cannot resume: the store's first epoch is {rows[0]['name']!r}, not {name!r}", str(self.path)
            )
        else:
            eid = int(rows[0]["id"])
        if self.epoch_source_id(name) is None:
            put_source(eid)
        self.widen_colour_range_m(*z_range_m)
        return eid

    def widen_colour_range(self, hf: Any) -> None:
        """Record in meta ``colour_range_m`` the elevation range of every epoch so far (with ``hf``'s), so
        all epochs are drawn on one colour ramp (terralod.render.offscreen.terrain_colours)."""
        self.widen_colour_range_m(*hf.valid_range_m())

    def widen_colour_range_m(self, lo: float, hi: float) -> None:
        """:meth:`widen_colour_range` with an epoch's elevation range (metres) given."""
        old = self.meta.get("colour_range_m")
        if old:
            lo, hi = min(lo, float(old[0])), max(hi, float(old[1]))
        if old != [float(lo), float(hi)]:
            self.set_metas({"colour_range_m": [float(lo), float(hi)]})  # type: ignore[attr-defined]

    def resume_epoch(self, eid: int) -> None:
        """Write new tiles under the building (not first) epoch ``eid`` again (a resumed update)."""
        self.write_rev, self._write_epoch = int(eid), None

    def epoch_tile_revs(self, eid: int) -> dict[tuple[int, int, int], int]:
        """{code: rev} of epoch ``eid``'s map."""
        q = "SELECT level, x, y, rev FROM epoch_tiles WHERE epoch = ?"
        return {(int(k), int(x), int(y)): int(r) for k, x, y, r in self._conn.execute(q, (int(eid),))}

    def rev_tile_errors(self, rev: int) -> dict[tuple[int, int, int], tuple[float, float]]:
        """{code: (error_m, vertical_error_m)} of the rows written under ``rev`` > 0 (a resumed update's work)."""
        q = "SELECT level, x, y, error_m, vertical_error_m FROM tile_revs WHERE rev = ?"
        return {
            (int(k), int(x), int(y)): (float(e), float(v)) for k, x, y, e, v in self._conn.execute(q, (rev,))
        }

    def rev_tile_row(self, code: tuple[int, int, int], rev: int) -> tuple[Any, ...] | None:
        """The row (TILE_COLUMNS) of tile ``code`` under ``rev`` (0: table tiles)."""
        if rev == 0:
            q, args = f"SELECT {TILE_COLUMNS} FROM tiles WHERE level=? AND x=? AND y=?", code
        else:
            q, args = (
                f"SELECT {TILE_COLUMNS} FROM tile_revs WHERE level=? AND x=? AND y=? AND rev=?",
                (*code, rev),
            )
        return self._conn.execute(q, args).fetchone()

    def commit_epoch(self, eid: int, revs: dict[tuple[int, int, int], int], info: dict[str, Any]) -> None:
        """Make epoch ``eid`` visible: its whole tile map and ``state = complete`` in one transaction."""
        with self._conn:
            self._conn.execute("DELETE FROM epoch_tiles WHERE epoch = ?", (int(eid),))
            self._conn.executemany(
                "INSERT INTO epoch_tiles VALUES (?, ?, ?, ?, ?)",
                [(int(eid), k, x, y, int(r)) for (k, x, y), r in sorted(revs.items())],
            )
            self._conn.execute(
                "UPDATE epochs SET state = 'complete', info = ? WHERE id = ?",
                (json.dumps(info, sort_keys=True), int(eid)),
            )

    def complete_first_epoch(self) -> None:
        """Mark the epoch of a first build complete (its map was written with its tiles)."""
        if self.has_epochs and self._write_epoch is not None:
            with self._conn:
                self._conn.execute("UPDATE epochs SET state = 'complete' WHERE id = ?", (self._write_epoch,))

    def check_delete(self, name: str) -> dict[str, Any]:
        """The row of epoch ``name`` if it may be deleted; else StoreError (no such epoch, or the only one)."""
        from terralod.errors import StoreError

        rows = self.epoch_rows()
        row = next((r for r in rows if r["name"] == name), None)
        if row is None:
            names = ", ".join(r["name"] for r in rows) or "none"
            raise StoreError(f"has no epoch {name!r} (epochs: {names})", str(self.path))
        done = [r for r in rows if r["state"] == "complete"]
        if row["state"] == "complete" and len(done) == 1:
            raise StoreError(
                f"epoch {name!r} is the store's only epoch; delete the file instead", str(self.path)
            )
        return row

    def delete_epoch(self, name: str) -> None:
        """Remove epoch ``name`` (complete, or an interrupted update), then every tile row and source block
        no epoch refers to, in one transaction. The only complete epoch cannot be deleted."""
        row = self.check_delete(name)
        rows = self.epoch_rows()
        building = [r["id"] for r in rows if r["state"] == "building" and r["id"] != row["id"]]
        keep = ",".join(str(i) for i in building) or "-1"
        ref = "SELECT 1 FROM epoch_tiles e WHERE e.level = {t}.level AND e.x = {t}.x AND e.y = {t}.y AND e.rev = {r}"
        with self._conn:
            self._conn.execute("DELETE FROM epoch_tiles WHERE epoch = ?", (row["id"],))
            self._conn.execute("DELETE FROM epoch_source WHERE epoch = ?", (row["id"],))
            self._conn.execute("DELETE FROM epochs WHERE id = ?", (row["id"],))
            self._conn.execute(
                f"DELETE FROM tile_revs WHERE rev NOT IN ({keep}) AND NOT EXISTS "
                f"({ref.format(t='tile_revs', r='tile_revs.rev')})"
            )
            self._conn.execute(f"DELETE FROM tiles WHERE NOT EXISTS ({ref.format(t='tiles', r='0')})")
            self._conn.execute(
                "DELETE FROM source_blocks WHERE NOT EXISTS "
                "(SELECT 1 FROM epoch_source s WHERE s.digest = source_blocks.digest)"
            )
        if self.epoch == name:
            self._init_epochs(None)

    def verify_epochs(self) -> list[str]:
        """Problems of the epoch tables, one line each (empty for a sound store): unfinished updates, map
        entries whose tile row is missing, epochs whose source blocks are missing or fail their sha256.
        (For ``terralod check``; the tile rows themselves are checked by their own CRC.)"""
        if not self.has_epochs:
            return []
        out = []
        for r in self.epoch_rows():
            if r["state"] != "complete":
                out.append(f"epoch {r['name']!r}: interrupted update (finish it with --resume or delete it)")
                continue
            missing = self._conn.execute(
                "SELECT count(*) FROM epoch_tiles e WHERE e.epoch = ? AND NOT ("
                "(e.rev = 0 AND EXISTS (SELECT 1 FROM tiles t WHERE t.level = e.level AND t.x = e.x AND t.y = e.y)) "
                "OR EXISTS (SELECT 1 FROM tile_revs t WHERE t.level = e.level AND t.x = e.x AND t.y = e.y "
                "AND t.rev = e.rev))",
                (r["id"],),
            ).fetchone()[0]
            if missing:
                out.append(f"epoch {r['name']!r}: {missing} tiles of its map are not stored")
            try:  # read in strips of 1,024 rows: a region's epoch is never held whole
                eid = self.epoch_source_id(r["name"])
                h = int(self.meta["height"])
                for r0 in range(0, h if eid is not None else 0, 16 * SOURCE_BLOCK):
                    self.epoch_source_window(eid, r0, min(r0 + 16 * SOURCE_BLOCK, h), f"epoch {r['name']!r}")  # type: ignore[arg-type]
            except Exception as exc:  # noqa: BLE001 - reported, not raised
                out.append(f"epoch {r['name']!r}: source samples unreadable ({getattr(exc, 'message', exc)})")
        return out

    def vacuum(self) -> None:
        """Give the pages of deleted rows back to the file system."""
        self._conn.execute("VACUUM")

    # -- source samples --------------------------------------------------------------------------------
    def put_epoch_source(
        self, eid: int, elevation_m: np.ndarray, valid: np.ndarray, *, like: int | None = None,
        changed: np.ndarray | None = None,
    ) -> None:  # fmt: skip
        """Keep epoch ``eid``'s elevation grid (float32, exactly) and validity mask, in shared blocks.
        With ``like`` (an epoch whose blocks are stored) and ``changed`` (where the samples differ from it),
        a block without a changed sample takes that epoch's block as it is (not compressed again)."""
        z = np.ascontiguousarray(elevation_m, np.float32)
        v = np.ascontiguousarray(valid, bool)
        b = SOURCE_BLOCK
        strips = (
            (r0, z[r0 : r0 + b], v[r0 : r0 + b], None if changed is None else changed[r0 : r0 + b])
            for r0 in range(0, z.shape[0], b)
        )
        self.put_epoch_source_strips(eid, z.shape[1], strips, like=like if changed is not None else None)

    def put_epoch_source_strips(self, eid: int, width: int, strips: Any, *, like: int | None = None) -> None:
        """:meth:`put_epoch_source` a strip of :data:`SOURCE_BLOCK` rows at a time (a grid never held whole):
        ``strips`` yields ``(row0, elevation_m, valid, changed)`` for rows ``row0 = 0, 64, 128, ...`` (each 64
        rows but the last, the grid's whole ``width``; ``changed`` None or where they differ from epoch
        ``like``). One transaction: the epoch keeps all its samples or none (its earlier rows replaced)."""
        b = SOURCE_BLOCK
        nbx = -(-int(width) // b)
        prior: dict[int, str] = {}
        if like is not None:
            q = "SELECT block, digest FROM epoch_source WHERE epoch = ?"
            prior = {int(k): str(d) for k, d in self._conn.execute(q, (int(like),))}
        with self._conn:
            self._conn.execute("DELETE FROM epoch_source WHERE epoch = ?", (int(eid),))
            for row0, z, v, changed in strips:
                self._put_source_strip(eid, nbx, int(row0) // b, z, v, changed, prior)

    def _put_source_strip(
        self, eid: int, nbx: int, by: int, z: Any, v: Any, changed: Any, prior: dict
    ) -> None:
        """One strip of :meth:`put_epoch_source_strips` (inside its transaction)."""
        b = SOURCE_BLOCK
        z = np.ascontiguousarray(z, np.float32)
        v = np.ascontiguousarray(v, bool)
        blocks, maps = {}, []
        for bx in range(nbx):
            k = by * nbx + bx
            if k in prior and changed is not None and not changed[:, bx * b : (bx + 1) * b].any():
                maps.append((int(eid), k, prior[k]))
                continue
            zz, vv = z[:, bx * b : (bx + 1) * b], v[:, bx * b : (bx + 1) * b]
            raw = np.ascontiguousarray(zz).astype("<f4").tobytes() + np.packbits(vv).tobytes()
            data = zlib.compress(raw, 6)
            d = hashlib.sha256(data).hexdigest()  # of the bytes stored (terralod check verifies them)
            blocks[d] = data
            maps.append((int(eid), k, d))
        self._conn.executemany("INSERT OR IGNORE INTO source_blocks VALUES (?, ?)", list(blocks.items()))
        self._conn.executemany("INSERT INTO epoch_source VALUES (?, ?, ?)", maps)

    def epoch_source(self, name: str | None = None) -> tuple[np.ndarray, np.ndarray] | None:
        """(elevation_m float32 (H, W), valid bool) of epoch ``name`` (default: the selected one) exactly as
        built, or None when the store does not keep that epoch's samples."""
        eid = self.epoch_source_id(name)
        if eid is None:
            return None
        w, h = int(self.meta["width"]), int(self.meta["height"])
        label = f"epoch {self.epoch_info(name)['name']!r}"
        return source_window(self._conn, eid, w, h, 0, 0, h, w, str(self.path), label)

    def epoch_source_window(
        self, eid: int, r0: int, r1: int, label: str | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """(elevation_m, valid) of rows [r0, r1), the grid's whole width, of epoch ``eid``'s kept samples
        (an id :meth:`epoch_source_id` gave; ``label`` names the epoch in an error)."""
        w, h = int(self.meta["width"]), int(self.meta["height"])
        return source_window(self._conn, eid, w, h, r0, 0, r1, w, str(self.path), label or f"epoch id {eid}")

    def epoch_source_id(self, name: str | None = None) -> int | None:
        """The id of epoch ``name`` (default: the selected one) when the store keeps all its samples (every
        block of the grid), None when it keeps none; CorruptStoreError when it keeps only some."""
        from terralod.errors import CorruptStoreError

        if not self.has_epochs or (name is None and self.epoch is None):
            return None
        info = self.epoch_info(name)
        (n,) = self._conn.execute(
            "SELECT COUNT(*) FROM epoch_source WHERE epoch = ?", (info["id"],)
        ).fetchone()
        if n == 0:
            return None
        b = SOURCE_BLOCK
        if n != -(-int(self.meta["width"]) // b) * -(-int(self.meta["height"]) // b):
            raise CorruptStoreError(f"epoch {info['name']!r}: source blocks missing", str(self.path))
        return int(info["id"])


def source_window(
    conn: sqlite3.Connection,
    eid: int,
    width: int,
    height: int,
    r0: int,
    c0: int,
    r1: int,
    c1: int,
    where: str,
    label: str = "epoch",
) -> tuple[np.ndarray, np.ndarray]:
    """(elevation_m float32, valid bool) of rows [r0, r1), columns [c0, c1) of epoch ``eid``'s kept samples
    on a ``height`` x ``width`` grid: only the :data:`SOURCE_BLOCK`-sample blocks the window touches are
    read (one range query per block row), each checked against its digest. CorruptStoreError (naming
    ``where`` and the epoch's ``label``) for a missing block or one that fails its checksum."""
    from terralod.errors import CorruptStoreError

    b = SOURCE_BLOCK
    nbx = -(-width // b)
    z = np.empty((r1 - r0, c1 - c0), np.float32)
    v = np.empty((r1 - r0, c1 - c0), bool)
    bx0, bx1 = c0 // b, -(-c1 // b)
    for by in range(r0 // b, -(-r1 // b)):
        rows = conn.execute(
            "SELECT s.block, b.data, s.digest FROM epoch_source s JOIN source_blocks b ON b.digest = s.digest "
            "WHERE s.epoch = ? AND s.block BETWEEN ? AND ? ORDER BY s.block",
            (int(eid), by * nbx + bx0, by * nbx + bx1 - 1),
        ).fetchall()
        if len(rows) != bx1 - bx0:
            raise CorruptStoreError(f"{label}: source blocks missing", where)
        for blk, data, digest in rows:
            if hashlib.sha256(bytes(data)).hexdigest() != digest:
                raise CorruptStoreError(f"{label}: a source block fails its checksum", where)
            raw = zlib.decompress(data)
            bx = int(blk) - by * nbx
            br0, bc0 = by * b, bx * b
            bh, bw = min(b, height - br0), min(b, width - bc0)
            n = bh * bw
            bz = np.frombuffer(raw[: 4 * n], "<f4").reshape(bh, bw)
            bv = np.unpackbits(np.frombuffer(raw[4 * n :], np.uint8))[:n].reshape(bh, bw).astype(bool)
            # the block's part inside the window
            ra, rb = max(br0, r0), min(br0 + bh, r1)
            ca, cb = max(bc0, c0), min(bc0 + bw, c1)
            z[ra - r0 : rb - r0, ca - c0 : cb - c0] = bz[ra - br0 : rb - br0, ca - bc0 : cb - bc0]
            v[ra - r0 : rb - r0, ca - c0 : cb - c0] = bv[ra - br0 : rb - br0, ca - bc0 : cb - bc0]
    return z, v
