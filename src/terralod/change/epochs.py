"""Epochs of a ``.terra`` store for the change analysis, and edits that write a new epoch.

- :func:`epoch_heightfield` — the elevation grid of one epoch, exactly as it was built (the samples the
  store keeps with each epoch; see :mod:`terralod.store_epochs`).
- :class:`EpochSource` — the same grid read a window at a time (a :class:`~terralod.io.windowed.WindowSource`:
  the windowed change reads a store's epochs as it reads two mosaics, without holding either).
- :func:`epoch_names` — the epochs of a store, oldest first (in the order they were added).
- :func:`difference` — ``after - before`` of two epochs on the store's grid (metres), for overlays.
- Edits, each a new epoch through :func:`terralod.pyramid.update.update_store` (only the dirty tiles are
  rebuilt): :func:`excavate` (a polygon lowered by ``depth_m``; a negative depth raises it: a dam, a fill)
  and :func:`apply_patch` (a raster pasted over the terrain: a landslide, a surveyed pit), both also as
  :func:`edit_store`.

Polygons: a GeoJSON file (Feature, FeatureCollection or a bare geometry; Polygon / MultiPolygon) in the CRS
its ``crs`` member names, else lon/lat (RFC 7946); a store without a CRS takes the coordinates as its own
metres. A cell is inside when its centre is (rasterio's ``geometry_mask``), so the volume of an edit is
``depth_m`` x the area of the cells inside: the polygon's area within about half a cell along its outline.
"""

from __future__ import annotations

import datetime
import os
import sqlite3
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from terralod.errors import InputError, StoreError
from terralod.heightfield import Heightfield
from terralod.io.windowed import WindowSource

__all__ = [
    "EditResult",
    "EpochSource",
    "apply_patch",
    "difference",
    "edit_store",
    "epoch_heightfield",
    "epoch_names",
    "excavate",
    "polygon_mask",
    "prepare_edit",
    "read_polygons",
]


def epoch_heightfield(store_path: str | os.PathLike[str], date: str | None = None) -> Heightfield:
    """The elevation grid of epoch ``date`` (default: the latest) of the store at ``store_path``, exactly as
    it was built (float32 elevation, validity mask, the store's transform and CRS).

    Raises StoreError (one line naming the store) when the epoch does not exist.
    """
    from terralod.pyramid.update import stored_heightfield
    from terralod.store import open_store

    with open_store(store_path, epoch=date) as s:
        return stored_heightfield(s)


class EpochSource(WindowSource):
    """Epoch ``date`` of the store at ``store_path`` read a window at a time: the samples the store keeps
    with the epoch (:func:`terralod.store_epochs.source_window`: only the 64 x 64 blocks a window touches,
    each checked against its digest), the same values as :func:`epoch_heightfield` gives for those cells.

    The store is opened and checked once here (its epoch, and that it keeps every block of the epoch's
    samples); reads go through one read-only SQLite connection per thread, opened on first use, so the
    source pickles (Dask workers read their own windows). StoreError when the epoch does not exist,
    :class:`NoSamplesKept` when the store keeps none of its samples (a store built without ``--epoch``,
    whose first epoch is re-read from its source file by :func:`epoch_heightfield`).
    """

    def __init__(self, store_path: str | os.PathLike[str], date: str | None = None) -> None:
        from affine import Affine

        from terralod.store import open_store

        self.path = str(Path(store_path).resolve())
        with open_store(store_path, epoch=date) as s:
            eid = s.epoch_source_id(s.epoch)
            if eid is None:
                raise NoSamplesKept(
                    f"keeps no samples of epoch {s.epoch!r} to read a window at a time", str(store_path)
                )
            info = s.epoch_info(s.epoch)
            self.eid, self.epoch, self.label = eid, str(s.epoch), f"epoch {s.epoch!r}"
            self.width, self.height = int(s.meta["width"]), int(s.meta["height"])
            self.transform, self.crs = Affine(*s.meta["transform"][:6]), s.crs
        self.source = str(info.get("source", ""))
        self.fill_method = str(info.get("fill_method", ""))
        self.notes = tuple(info.get("notes", ()))
        self._local = threading.local()

    def __getstate__(self) -> dict[str, Any]:
        state = dict(self.__dict__)
        del state["_local"]  # connections are per process and thread
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self._local = threading.local()

    def read(self, r0: int, c0: int, r1: int, c1: int) -> tuple[np.ndarray, np.ndarray]:
        from terralod.store_epochs import source_window

        self._check_window(r0, c0, r1, c1)
        conn = getattr(self._local, "conn", None)
        if conn is None:
            conn = self._local.conn = sqlite3.connect(f"file:{self.path}?mode=ro", uri=True)
        return source_window(conn, self.eid, self.width, self.height, r0, c0, r1, c1, self.path, self.label)


class NoSamplesKept(StoreError):
    """A store epoch whose samples the store does not keep (see :class:`EpochSource`)."""


def epoch_names(store_path: str | os.PathLike[str]) -> list[str]:
    """Names of the complete epochs of a store, in the order they were added ([] for a store without)."""
    from terralod.store import open_store

    with open_store(store_path) as s:
        return s.epochs


def difference(store_path: str | os.PathLike[str], before: str, after: str) -> np.ndarray:
    """(H, W) float32 ``after - before`` in metres on the store's grid (NaN where either is invalid)."""
    a = epoch_heightfield(store_path, before)
    b = epoch_heightfield(store_path, after)
    d = b.elevation_m.astype(np.float32) - a.elevation_m.astype(np.float32)
    d[~(a.valid & b.valid)] = np.nan
    return d


# -- polygons ------------------------------------------------------------------------------------------
def read_polygons(path: str | os.PathLike[str], crs: str | None) -> list[dict[str, Any]]:
    """The Polygon / MultiPolygon geometries of a GeoJSON file, in ``crs`` (the store's), each as a GeoJSON
    geometry dict with a ``name`` (its feature's ``name`` property, else ``polygon N``)."""
    from terralod.change.zones import read_geojson_polygons

    p = Path(path)
    feats, src_crs = read_geojson_polygons(p, "polygon")
    out = [{"type": g["type"], "coordinates": g.get("coordinates"), "name": name} for name, g in feats]
    if crs and src_crs != "local":
        from rasterio.warp import transform_geom

        try:
            out = [dict(transform_geom(src_crs, crs, {k: g[k] for k in ("type", "coordinates")}),
                        name=g["name"]) for g in out]  # fmt: skip
        except Exception as exc:  # noqa: BLE001 - any projection failure is the file's problem
            raise InputError(f"cannot transform its polygons to the terrain's CRS ({exc})", str(p)) from None
    return out


def polygon_mask(polygons: list[dict[str, Any]], hf: Heightfield) -> np.ndarray:
    """(H, W) bool: cells of ``hf`` whose centre lies inside any of ``polygons`` (in hf's CRS)."""
    from rasterio.features import geometry_mask

    geoms = [{k: g[k] for k in ("type", "coordinates")} for g in polygons]
    return ~geometry_mask(geoms, out_shape=hf.shape, transform=hf.transform, all_touched=False)


def polygon_area_m2(polygons: list[dict[str, Any]]) -> float:
    """Planar area of the polygons (holes subtracted), square metres of their CRS."""

    def ring(r: Any) -> float:
        a = np.asarray(r, np.float64)[:, :2]
        x, y = a[:, 0], a[:, 1]
        return 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))

    total = 0.0
    for g in polygons:
        polys = [g["coordinates"]] if g["type"] == "Polygon" else g["coordinates"]
        for poly in polys:
            total += ring(poly[0]) - sum(ring(h) for h in poly[1:])
    return total


# -- edits ---------------------------------------------------------------------------------------------
@dataclass
class EditResult:
    """What an edit changed: the heightfield of the new epoch, the cells changed, the volume (m³, positive
    = material added), and a description kept with the epoch."""

    heightfield: Heightfield
    changed: np.ndarray
    volume_m3: float
    description: dict[str, Any]


def _replace(hf: Heightfield, z: np.ndarray, valid: np.ndarray, source: str) -> Heightfield:
    return Heightfield(z.astype(np.float32), valid, hf.transform, hf.crs, source, hf.fill_method, hf.notes)


def excavate(hf: Heightfield, polygons: list[dict[str, Any]], depth_m: float, where: str) -> EditResult:
    """Lower the cells inside ``polygons`` by ``depth_m`` (negative: raise them — a dam, a fill)."""
    if not np.isfinite(depth_m) or depth_m == 0:
        raise InputError(f"expected a non-zero depth in metres, got {depth_m}", where)
    mask = polygon_mask(polygons, hf)
    if not mask.any():
        raise InputError("polygon lies outside the terrain (no cell centre inside it)", where)
    z = hf.elevation_m.astype(np.float32).copy()
    z[mask] = z[mask] - np.float32(depth_m)
    dz = z.astype(np.float64) - hf.elevation_m.astype(np.float64)
    dx, dy = hf.spacing_m
    vol = float(dz[mask].sum()) * dx * dy
    desc = {"edit": "excavation" if depth_m > 0 else "fill", "depth_m": float(depth_m),
            "polygons": [g["name"] for g in polygons], "cells": int(mask.sum()), "volume_m3": vol,
            "polygon_area_m2": polygon_area_m2(polygons)}  # fmt: skip
    return EditResult(_replace(hf, z, hf.valid, f"{hf.source} + edit {Path(where).name}"), mask, vol, desc)


def apply_patch(hf: Heightfield, patch: Heightfield, where: str) -> EditResult:
    """Paste the valid samples of ``patch`` over ``hf`` (resampled bilinearly onto hf's grid when the
    grids differ; same CRS or reprojected by rasterio)."""
    from rasterio.warp import Resampling, reproject

    src = np.where(patch.valid, patch.elevation_m, np.nan).astype(np.float32)
    dst = np.full(hf.shape, np.nan, np.float32)
    if hf.crs is None or patch.crs is None:
        if (hf.crs is None) != (patch.crs is None):
            raise InputError("has a CRS and the terrain has none (or the other way round)", where)
        crs_a = crs_b = "EPSG:3857"  # both local metric frames: any metric CRS maps them one to one
    else:
        crs_a, crs_b = patch.crs, hf.crs
    reproject(src, dst, src_transform=patch.transform, src_crs=crs_a, dst_transform=hf.transform, dst_crs=crs_b,
              src_nodata=np.nan, dst_nodata=np.nan, resampling=Resampling.bilinear)  # fmt: skip
    mask = np.isfinite(dst)
    if not mask.any():
        raise InputError("patch lies outside the terrain", where)
    z = hf.elevation_m.astype(np.float32).copy()
    z[mask] = dst[mask]
    mask &= z != hf.elevation_m
    dz = z.astype(np.float64) - hf.elevation_m.astype(np.float64)
    dx, dy = hf.spacing_m
    vol = float(dz.sum()) * dx * dy
    valid = hf.valid | np.isfinite(dst)
    desc = {"edit": "patch", "patch": str(patch.source), "cells": int(mask.sum()), "volume_m3": vol}
    return EditResult(_replace(hf, z, valid, f"{hf.source} + patch {Path(where).name}"), mask, vol, desc)


class EditAlreadyDone(InputError):
    """The edit asked for is already an epoch of the store (a rerun after the edit committed): nothing to do.
    ``epoch`` names that epoch."""

    def __init__(self, message: str, path: str, epoch: str) -> None:
        super().__init__(message, path)
        self.epoch = epoch


def edit_key(polygon: Any = None, depth_m: float | None = None, patch_digest: str | None = None) -> str:
    """What identifies an edit's parameters, kept with its epoch: the polygon file's bytes and the depth,
    or the patch's samples (their digest)."""
    import hashlib

    h = hashlib.sha256()
    if polygon is not None:
        h.update(b"polygon\0" + Path(polygon).read_bytes() + f"\0{float(depth_m)!r}".encode())  # type: ignore[arg-type]
    else:
        h.update(b"patch\0" + str(patch_digest).encode())
    return h.hexdigest()


def _done_edit(rows: list[dict[str, Any]], key: str, epoch: str | None, base: str | None, latest: str) -> Any:
    """The complete epoch that already holds this edit, or None: the epoch named (from the base given, if
    one is), else the base given's edit of these parameters, else the latest epoch when it is this edit."""
    done = [r for r in rows if r["state"] == "complete" and r["info"].get("edit_key") == key]
    if epoch is not None:
        return next((r for r in done if r["name"] == epoch and base in (None, r["info"].get("base"))), None)
    if base is not None:
        return next((r for r in done if r["info"].get("base") == base), None)
    return next((r for r in done if r["name"] == latest), None)


def default_edit_name(existing: list[str]) -> str:
    """``edit-N``: the first N not taken."""
    n = 1
    while f"edit-{n}" in existing:
        n += 1
    return f"edit-{n}"


def prepare_edit(
    store_path: str | os.PathLike[str],
    *,
    polygon: str | os.PathLike[str] | None = None,
    depth_m: float | None = None,
    patch: str | os.PathLike[str] | None = None,
    epoch: str | None = None,
    base: str | None = None,
    resume: bool = False,
) -> tuple[EditResult, str, str, dict[str, Any]]:
    """The edit of epoch ``base`` (default: the latest) checked and computed, nothing written: (the edit,
    the new epoch's name, the base epoch's name, the info kept with the epoch)."""
    from terralod.io.reader import read_heightfield
    from terralod.pyramid.update import check_update, stored_heightfield
    from terralod.store import open_store

    if (polygon is None) == (patch is None):
        raise InputError("give --polygon with --depth-m, or --patch", str(store_path))
    with open_store(store_path, epoch=base) as s:
        hf = stored_heightfield(s)
        crs = s.crs
        existing = s.epochs
        base_name = str(s.epoch)
        rows = s.epoch_rows() if s.has_epochs else []
    if polygon is not None:
        if depth_m is None:
            raise InputError("--polygon needs --depth-m (metres down; negative for a fill)", str(polygon))
        res = excavate(hf, read_polygons(polygon, crs), float(depth_m), str(polygon))
        key = edit_key(polygon, depth_m)
        args = {"polygon": str(polygon), "depth_m": float(depth_m)}
    else:
        patch_hf = read_heightfield(patch)
        res = apply_patch(hf, patch_hf, str(patch))
        key = edit_key(patch_digest=patch_hf.digest())
        args = {"patch": str(patch)}
    if not resume and (done := _done_edit(rows, key, epoch, base, base_name)) is not None:
        raise EditAlreadyDone(
            f"this edit is already epoch {done['name']!r} (the same {'polygon and depth' if polygon else 'patch'} "
            f"on {done['info'].get('base')!r}, a run that finished); nothing done. To apply it once more, "
            f"name a new epoch with --epoch",
            str(store_path),
            done["name"],
        )
    name = epoch or default_edit_name(existing)
    check_update(store_path, res.heightfield, name, base=base_name, resume=resume)
    info = {"edit": res.description, "edited": datetime.date.today().isoformat(), "edit_key": key,
            "edit_args": args}  # fmt: skip
    return res, name, base_name, info


def edit_store(
    store_path: str | os.PathLike[str],
    *,
    polygon: str | os.PathLike[str] | None = None,
    depth_m: float | None = None,
    patch: str | os.PathLike[str] | None = None,
    epoch: str | None = None,
    base: str | None = None,
    resume: bool = False,
    workers: int | None = None,
    progress: Any = None,
    stop_after: int | None = None,
) -> tuple[EditResult, Any]:
    """Edit epoch ``base`` (default: the latest) of a store and write the result as new epoch ``epoch``
    (default ``edit-N``), rebuilding only the tiles the edit touches. Returns (the edit, the UpdateReport).
    Raises :class:`EditAlreadyDone` when the store already holds this very edit (the same polygon file and
    depth, or patch) as that epoch, or, without ``epoch``, as the latest one (a rerun after a finished edit).
    """
    from terralod.pyramid.update import update_store

    res, name, base_name, info = prepare_edit(store_path, polygon=polygon, depth_m=depth_m, patch=patch,
                                              epoch=epoch, base=base, resume=resume)  # fmt: skip
    rep = update_store(res.heightfield, store_path, name, base=base_name, resume=resume, workers=workers,
                       progress=progress, stop_after=stop_after, kind="edit", info=info)  # fmt: skip
    return res, rep
