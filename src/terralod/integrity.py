"""Integrity of a ``.terra`` store: everything that decodes a tile is checked (``terralod check``).

Checks, each problem one line:

- **metadata**: format version and the checksum over every meta row (:func:`terralod.store.verify_meta`);
  quantisation, transform, CRS, levels and method are what turn tile bytes into coordinates, so a store
  whose metadata fails is not read further;
- **tiles**: every row's CRC-32 and its decoding (vertex and index streams, indices in range, a level
  with a quantisation); codes outside the pyramid's plan; planned tiles missing;
- **errors monotone**: ``error_m`` and ``vertical_error_m`` of a parent are at least its children's (what
  the selection relies on to stop refining), and at least the tile's own measurement;
- **shared borders**: the vertices two same-level neighbours have on their common edge are bit-identical
  (the per-level lattice makes them so; a crack otherwise). Where the store cuts its footprint at nodata, a
  vertex may exist on one side only; coinciding positions must still agree in height;
- **bounds**: every vertex finite, inside its tile's window (``span`` samples from the tile origin; the
  window may reach past the grid's last sample) and inside the tile's stored z-range;
- **epochs** (stores that have them): every complete epoch's tile map points at stored tile rows, source
  blocks match their SHA-256;
- **TIN stores**: the metadata checksum, the model payload's SHA-256, and the model file's own checksums.

:func:`repair_store` drops what is broken (tile rows) so ``terralod build SOURCE -o STORE --resume``
rebuilds exactly those tiles (the build is deterministic).
"""

from __future__ import annotations

import hashlib
import json
import math
import sqlite3
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from terralod.errors import StoreError, TerralodError
from terralod.store import TIN_METHOD, TileStore, _check_header, store_method
from terralod.tiles import TileCode, parent

__all__ = ["CheckReport", "check_store", "repair_store"]


@dataclass
class CheckReport:
    """What :func:`check_store` found: ``problems`` (one line each) and the codes of broken tiles."""

    path: str
    kind: str = "unknown"
    checked: list[str] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)
    broken_tiles: set[TileCode] = field(default_factory=set)
    missing_tiles: int = 0
    metadata_ok: bool = False
    source: str | None = None

    @property
    def sound(self) -> bool:
        return not self.problems

    def as_dict(self) -> dict[str, Any]:
        return {
            "path": self.path, "kind": self.kind, "sound": self.sound, "checked": self.checked,
            "problems": self.problems, "broken_tiles": sorted(self.broken_tiles),
            "missing_tiles": self.missing_tiles, "metadata_ok": self.metadata_ok,
        }  # fmt: skip


def check_store(path: str | Path) -> CheckReport:
    """Verify a store of either kind; never raises for a damaged store (problems are reported)."""
    p = Path(path)
    rep = CheckReport(str(p))
    try:
        if not p.exists():
            raise StoreError("store not found", str(p))
        if p.is_dir():
            raise StoreError("is a directory, not a store", str(p))
        _check_header(p)
    except TerralodError as exc:
        rep.problems.append(exc.message)
        return rep
    if store_method(p) == TIN_METHOD:
        _check_tin(p, rep)
    else:
        _check_grid(p, rep)
    return rep


def _check_tin(p: Path, rep: CheckReport) -> None:
    from terralod.tin.terra import load_model_from_store

    rep.kind = "TIN store"
    try:
        model, meta = load_model_from_store(p)
    except TerralodError as exc:
        rep.problems.append(exc.message)
        return
    except Exception as exc:  # noqa: BLE001 - a damaged model is a problem to report, whatever raised
        rep.problems.append(f"TIN model cannot be loaded ({type(exc).__name__}: {exc})")
        return
    rep.metadata_ok = True
    rep.source = meta.get("source")
    rep.checked += ["metadata checksum", "model payload SHA-256", "model file checksums"]
    v = model.vertices_m
    if v.size and not np.isfinite(v).all():
        rep.problems.append("TIN model has non-finite vertex coordinates")
    rep.checked.append(f"{v.shape[0]:,} vertices finite")


def _check_grid(p: Path, rep: CheckReport) -> None:
    rep.kind = "grid store"
    try:
        store = TileStore.open(p)
    except TerralodError as exc:
        rep.problems.append(exc.message)
        return
    with store:
        rep.metadata_ok = True
        rep.source = store.meta.get("source")
        rep.checked.append("metadata checksum")
        _check_meta_values(store, rep)
        _check_tiles(store, rep)
        _check_epochs(store, rep)


def _check_meta_values(store: TileStore, rep: CheckReport) -> None:
    t = store.transform
    if not all(math.isfinite(v) for v in tuple(t)[:6]) or t.a <= 0 or t.e >= 0:
        rep.problems.append(f"transform {tuple(t)[:6]} is not a finite north-up grid")
    missing = [k for k in store.levels if k not in store.quantisation]
    if missing:
        rep.problems.append(f"no quantisation for level(s) {missing}")
    for k, q in store.quantisation.items():
        if not (q.z_step_m > 0 and math.isfinite(q.z_step_m)) or not -16 <= q.xy_frac_bits <= 16:
            rep.problems.append(f"level {k} quantisation {q} is not usable")


def _check_tiles(store: TileStore, rep: CheckReport) -> None:
    """Every stored tile decoded, inside its tile, its borders shared with its east and south neighbours,
    its errors at least its measurement and its children's. A level is read in raster order keeping two
    rows of decoded tiles, and the errors as two arrays a level: memory bounded by a row of tiles, not
    by the region (a 256-SRTM3-tile store holds some 850,000 tiles)."""
    pyr = store.pyramid
    n_planned = sum(nx * ny for nx, ny in map(pyr.grid_count, pyr.levels))
    x0 = store.transform.c + 0.5 * store.transform.a
    y0 = store.transform.f + 0.5 * store.transform.e
    has_cut_footprint = float(store.meta.get("nodata_fraction") or 0.0) > 0.0
    n_stored = n_planned_stored = n_decoded = n_borders = n_parents = 0
    below: list[np.ndarray] = []  # the finer level's (error, vertical error) arrays, NaN where not stored
    try:
        levels = sorted(set(store.stored_levels()) | set(pyr.levels), reverse=True)
        for level in levels:
            nx, ny = pyr.grid_count(level) if 0 <= level <= pyr.max_level else (0, 0)
            err = np.full((2, ny, nx), np.nan)
            prev: dict[int, Any] = {}
            row: dict[int, Any] = {}
            row_y = -1
            for c in store.each_tile_code(level):
                n_stored += 1
                if not pyr.exists(c):
                    rep.problems.append(f"tile {c} is not in the pyramid's plan")
                    rep.broken_tiles.add(c)
                    continue
                n_planned_stored += 1
                if c[2] != row_y:  # a new row: the one above it is the previous row, if adjacent
                    prev, row = (row if c[2] == row_y + 1 else {}), {}
                    row_y = c[2]
                t = _decode(store, c, rep)
                if t is None:
                    continue
                n_decoded += 1
                _check_tile_bounds(store, t, x0, y0, rep)
                if c[1] - 1 in row:
                    n_borders += 1
                    _check_border(store, row[c[1] - 1], t, 1, has_cut_footprint, rep)
                if c[1] in prev:
                    n_borders += 1
                    _check_border(store, prev[c[1]], t, 0, has_cut_footprint, rep)
                row[c[1]] = t
            for (k, x, y), (e, ev), (me, mev) in store.each_tile_error_measured(level):
                if not pyr.exists((k, x, y)):
                    continue
                err[0, y, x], err[1, y, x] = e, ev
                if e < me or ev < mev:
                    rep.problems.append(f"tile {(k, x, y)} stores an error below its own measurement")
                    rep.broken_tiles.add((k, x, y))
            if below and nx and ny:
                n_parents += _check_monotone(level, err, below[0], rep)
            below = [err]
    except sqlite3.DatabaseError as exc:
        rep.problems.append(f"tiles table cannot be read ({exc})")
        return
    rep.missing_tiles = n_planned - n_planned_stored
    if rep.missing_tiles:
        state = "marked complete, but " if store.complete else "incomplete: "
        rep.problems.append(
            f"{state}{rep.missing_tiles} of {n_planned} tiles missing; finish with "
            f"`terralod build {rep.source or 'SOURCE'} -o {store.path} --resume`"
        )
    rep.checked += [
        f"{n_decoded}/{n_stored} tiles decode and pass their checksums",
        f"errors monotone over {n_parents} parents",
        f"{n_borders} shared borders",
        "vertices inside their tiles and z-ranges",
    ]


def _decode(store: TileStore, c: TileCode, rep: CheckReport) -> Any:
    """Tile ``c`` decoded (checksum checked), or None with the problem reported."""
    try:
        return store.tile(*c)
    except TerralodError as exc:
        rep.problems.append(exc.message)
    except KeyError:  # listed by the index, absent from the table: the file's b-trees disagree
        rep.problems.append(f"tile {c} is listed but cannot be read (damaged index)")
    rep.broken_tiles.add(c)
    return None


def _check_monotone(level: int, err: np.ndarray, kids: np.ndarray, rep: CheckReport) -> int:
    """Parents of ``level`` (errors ``err``, (2, ny, nx), NaN where not stored) against the largest error of
    their stored children (``kids``, the finer level's): a parent below them, and everything above it,
    is broken. Returns the parents checked (stored, with a stored child)."""
    _, ny, nx = err.shape
    _, cy, cx = kids.shape
    pad = np.full((2, 2 * ny, 2 * nx), np.nan)
    pad[:, : min(cy, 2 * ny), : min(cx, 2 * nx)] = kids[:, : 2 * ny, : 2 * nx]
    blocks = pad.reshape(2, ny, 2, nx, 2)
    have = ~np.isnan(blocks).all(axis=(2, 4))
    top = np.where(have, np.nanmax(np.where(np.isnan(blocks), -np.inf, blocks), axis=(2, 4)), np.nan)
    checked = have[0] & ~np.isnan(err[0])
    bad = checked & ((err[0] < top[0]) | (err[1] < top[1]))
    for y, x in zip(*np.nonzero(bad), strict=True):
        c = (level, int(x), int(y))
        e, ev, ke, kv = err[0, y, x], err[1, y, x], top[0, y, x], top[1, y, x]
        rep.problems.append(
            f"tile {c} error {e:.6g} m / {ev:.6g} m is below its children's {ke:.6g} m / {kv:.6g} m "
            "(errors not monotone)"
        )
        q: TileCode | None = c
        while q is not None:  # the parent and everything above it derive from the children
            rep.broken_tiles.add(q)
            q = parent(q)
    return int(checked.sum())


def _check_tile_bounds(store: TileStore, t: Any, x0: float, y0: float, rep: CheckReport) -> None:
    if t.vertices.shape[0] == 0:
        return
    pyr = store.pyramid
    r0, c0 = pyr.origin_rc(t.code)
    span = pyr.span(t.code[0])
    rc = t.grid_rc
    eps = 1e-9 * max(1.0, span)
    ok = (
        np.isfinite(t.vertices).all()
        and rc[:, 0].min() >= r0 - eps
        and rc[:, 1].min() >= c0 - eps
        and rc[:, 0].max() <= r0 + span + eps
        and rc[:, 1].max() <= c0 + span + eps
    )
    if not ok:
        rep.problems.append(f"tile {t.code} has vertices outside its window of the grid")
        rep.broken_tiles.add(t.code)
        return
    z = t.vertices[:, 2]
    tol = 1e-9 * max(1.0, abs(t.z_max_m), abs(t.z_min_m))
    if z.min() < t.z_min_m - tol or z.max() > t.z_max_m + tol:
        rep.problems.append(
            f"tile {t.code} heights {z.min():.6g}..{z.max():.6g} m leave its stored range "
            f"{t.z_min_m:.6g}..{t.z_max_m:.6g} m"
        )
        rep.broken_tiles.add(t.code)


def _check_border(store: TileStore, a: Any, b: Any, axis: int, cut: bool, rep: CheckReport) -> None:
    """Vertices of ``a`` and its east (axis 1) / south (axis 0) neighbour ``b`` on their common edge."""
    r0, c0 = store.pyramid.origin_rc(a.code)
    edge = (c0 if axis == 1 else r0) + store.pyramid.span(a.code[0])
    ea = a.vertices[a.grid_rc[:, axis] == edge] if a.vertices.size else np.zeros((0, 3))
    eb = b.vertices[b.grid_rc[:, axis] == edge] if b.vertices.size else np.zeros((0, 3))
    if ea.shape[0] == 0 and eb.shape[0] == 0:
        return
    za = {(x, y): z for x, y, z in ea.tolist()}
    zb = {(x, y): z for x, y, z in eb.tolist()}
    common = za.keys() & zb.keys()
    differ = [k for k in common if za[k] != zb[k]]
    one_sided = (za.keys() ^ zb.keys()) if not cut else set()
    if differ or one_sided:
        what = f"{len(differ)} heights differ" if differ else f"{len(one_sided)} vertices on one side only"
        rep.problems.append(f"tiles {a.code} and {b.code} do not share their border bit-identically ({what})")
        rep.broken_tiles.update((a.code, b.code))


def _check_epochs(store: TileStore, rep: CheckReport) -> None:
    """Epoch tables (``terralod update``), when the store has them: references and source blocks."""
    conn = store._conn
    try:
        tables = {r[0] for r in conn.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
        if "epochs" not in tables:
            return
        epochs = conn.execute("SELECT id, name, state, info FROM epochs ORDER BY id").fetchall()
        cols = {r[1] for r in conn.execute("PRAGMA table_info(tiles)")}
        n_refs = 0
        for eid, name, state, info in epochs:
            if state != "complete":
                from terralod.pyramid.update import finish_advice

                row = {"name": name, "info": json.loads(info)}
                rep.problems.append(
                    f"epoch {name!r} is unfinished (state {state}); {finish_advice(store.path, row)}"
                )
                continue
            if "epoch_tiles" in tables and "rev" in cols:
                dangling = conn.execute(
                    "SELECT count(*) FROM epoch_tiles e LEFT JOIN tiles t ON t.level = e.level AND t.x = e.x "
                    "AND t.y = e.y AND t.rev = e.rev WHERE e.epoch = ? AND t.level IS NULL",
                    (eid,),
                ).fetchone()[0]
                (n,) = conn.execute("SELECT count(*) FROM epoch_tiles WHERE epoch = ?", (eid,)).fetchone()
                n_refs += n
                if dangling:
                    rep.problems.append(f"epoch {name!r}: {dangling} tiles of its map are not stored")
        n_blocks = 0
        if "source_blocks" in tables:
            for digest, data in conn.execute("SELECT digest, data FROM source_blocks"):
                n_blocks += 1
                if hashlib.sha256(bytes(data)).hexdigest() != digest:
                    rep.problems.append(f"source block {str(digest)[:12]}… fails its SHA-256")
        rep.checked.append(f"{len(epochs)} epochs ({n_refs} tile references, {n_blocks} source blocks)")
    except (sqlite3.DatabaseError, TypeError, ValueError) as exc:
        rep.problems.append(f"epoch tables cannot be read ({exc})")


def repair_store(path: str | Path, report: CheckReport) -> list[str]:
    """Drop the broken tiles of a grid store found by :func:`check_store` (one transaction), mark it
    incomplete; returns lines saying what was done and what ``--resume`` will rebuild."""
    p = Path(path)
    if report.sound:
        return ["nothing to repair"]
    if report.kind != "grid store" or not report.metadata_ok:
        return [
            "cannot repair: the metadata or the TIN model decodes everything else; rebuild with "
            f"`terralod build {report.source or 'SOURCE'} -o {p} --overwrite`"
        ]
    codes = sorted(report.broken_tiles)
    with TileStore.open(p, writable=True) as s:
        try:
            with s._conn:
                s._conn.executemany("DELETE FROM tiles WHERE level = ? AND x = ? AND y = ?", codes)
        except sqlite3.Error as exc:
            raise StoreError(f"cannot repair ({exc})", str(p)) from exc
        if codes or report.missing_tiles:
            s.set_meta("complete", False)
    lines = [
        f"dropped {len(codes)} broken tile(s)" + (f": {', '.join(map(str, codes[:8]))}" if codes else "")
    ]
    n = len(codes) + report.missing_tiles
    if n:
        lines.append(
            f"`terralod build {report.source or 'SOURCE'} -o {p} --resume` rebuilds {n} tile(s) "
            "(same source and options; identical bytes)"
        )
    return lines


def meta_rows(path: str | Path) -> dict[str, Any]:
    """Every meta row of a store, JSON-decoded, without verifying anything (for tools and tests)."""
    conn = sqlite3.connect(f"file:{Path(path).resolve()}?mode=ro", uri=True)
    try:
        return {k: json.loads(v) for k, v in conn.execute("SELECT key, value FROM meta")}
    finally:
        conn.close()
