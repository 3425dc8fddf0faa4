"""What each web tile is made from: its dependency digest, so that ``export --update`` makes again only the
tiles whose inputs changed.

A tile's bytes are a pure function of the export's options, a few whole-terrain facts (the grid, its
footprint, the levels) and the source samples or store rows it reads. :func:`qm_digest` and
:func:`tiles3d_digest` hash exactly those; the export records the digest with each file
(:class:`terralod.output.Output` ``keep_records``) and, on ``update``, keeps without encoding a file whose
recorded digest equals the new one. Whatever a digest leaves out would make an update differ from a fresh
export, so each one errs wide:

- a quantized-mesh tile reads the source samples of its rectangle plus a margin (one sample for the
  bilinear surface and the water mask, ``2 stride + 2`` on a lattice for the grid's clamp and the normals),
  and a tile of the zoom below the finest also its parent's (:meth:`QuantizedMesh.rms_ratio` sets its
  target). In memory (a store's samples, a DEM read whole) the digest hashes those filled heights and their
  validity; for a region of DEM files (:class:`terralod.export.source.RegionGrid`) it hashes the identity
  (path, size, mtime, place on the grid, order) of every file that meets the fill blocks of that window
  widened by the widest halo their fill took (recorded with the tile: a block's halo is decided by the raw
  samples inside it, so unchanged files there give the same halo and the same fill). A TIN's tile
  hashes the stored model's SHA-256 (in the global facts) and its code: any change to the model makes
  every tile again, none leaves every tile as it is (a TIN held only in memory gives no digest: its
  tiles are always encoded);
- a 3D Tiles glb reads its node's stored row, its parent's and grandparent's (skirt depth, encoding step),
  and its level neighbours' (normals are summed across shared vertices): the digest hashes those rows as
  stored, and the store's validity mask where the export drops nodata triangles. A TIN's glb: the stored
  model's SHA-256 and its code, as for quantized-mesh.
"""

from __future__ import annotations

import hashlib
import json
import math
from typing import Any

import numpy as np

__all__ = ["qm_digest", "qm_global", "tiles3d_digest", "tiles3d_global"]

#: Bumped whenever what a tile's bytes depend on changes shape (every tile is then made again).
DIGEST_VERSION = 1


def _sha(*parts: Any) -> str:
    h = hashlib.sha256()
    for p in parts:
        h.update(p if isinstance(p, bytes) else json.dumps(p, sort_keys=True, default=str).encode())
        h.update(b"\0")
    return h.hexdigest()


def _version() -> str:
    try:
        from importlib.metadata import version

        return version("terralod")
    except Exception:  # noqa: BLE001 - a source checkout without metadata
        return "unknown"


# -- quantized-mesh --------------------------------------------------------------------------------------
def qm_global(qm: Any, options: dict[str, Any]) -> str:
    """What every tile of quantized-mesh view ``qm`` depends on: the options, the grid, its footprint and
    the levels."""
    ref = qm.ref
    t = getattr(ref, "t", None)
    region = getattr(ref, "region", None)
    facts = {
        "v": DIGEST_VERSION, "terralod": _version(), "source": type(ref).__name__,
        "transform": list(t)[:6] if t is not None else None, "shape": list(getattr(ref, "shape", ()) or ()),
        "crs": ref.crs.to_wkt() if getattr(ref, "crs", None) is not None and hasattr(ref.crs, "to_wkt") else None,
        "bbox": list(ref.bbox), "spacing": ref.spacing_deg, "identity": bool(ref.identity),
        "any_water": bool(getattr(ref, "any_water", False)) if t is not None else None,
        "max_zoom": qm.max_zoom, "target_fraction": qm.target_fraction, "normals": qm.normals,
        "heights": qm.heights, "options": options,
        "constants": list(qm.digest_constants),
        "region": None if region is None else [str(region.dtype), region.scale, region.offset],
        "model": getattr(ref, "model_digest", None),
    }  # fmt: skip
    return _sha(facts)


def _lattice_window(qm: Any, z: int, x: int, y: int) -> tuple[int, int, int, int]:
    """Rows [r0, r1), columns [c0, c1) of the source lattice a lattice tile reads (clamped to the grid)."""
    from terralod.export.geodesy import tile_rectangle

    lat_ = qm.lattice
    stride = lat_.stride(z, qm.max_zoom)
    w, s, e, n = tile_rectangle(z, x, y)
    fc_w, fc_e = (w - lat_.c_deg) / lat_.a_deg - 0.5, (e - lat_.c_deg) / lat_.a_deg - 0.5
    fr_n, fr_s = (n - lat_.f_deg) / lat_.e_deg - 0.5, (s - lat_.f_deg) / lat_.e_deg - 0.5
    m = 2 * stride + 2
    r0 = max(math.floor(min(fr_n, fr_s)) - m, 0)
    r1 = min(math.ceil(max(fr_n, fr_s)) + m + 1, lat_.h)
    c0 = max(math.floor(min(fc_w, fc_e)) - m, 0)
    c1 = min(math.ceil(max(fc_w, fc_e)) + m + 1, lat_.w)
    return min(r0, lat_.h - 1), max(r1, 1), min(c0, lat_.w - 1), max(c1, 1)


def _grid_window(ref: Any, z: int, x: int, y: int, side: int) -> tuple[int, int, int, int]:
    """Rows [r0, r1), columns [c0, c1) of an in-memory grid a 257² tile reads: its rectangle plus one
    sample of the tile's grid, clamped to the footprint (outside it the edge values continue), mapped to
    the grid by its densified border, plus two samples."""
    from terralod.export.geodesy import tile_rectangle

    w, s, e, n = tile_rectangle(z, x, y)
    du, dv = (e - w) / (side - 1), (n - s) / (side - 1)
    k = np.linspace(0.0, 1.0, 65)
    lon = np.concatenate([w - du + (e - w + 2 * du) * k, np.full(65, e + du),
                          w - du + (e - w + 2 * du) * k, np.full(65, w - du)])  # fmt: skip
    lat = np.concatenate([np.full(65, n + dv), s - dv + (n - s + 2 * dv) * k,
                          np.full(65, s - dv), s - dv + (n - s + 2 * dv) * k])  # fmt: skip
    col, row = ref._colrow(lon, lat)
    h, wd = ref.shape
    r0, r1 = max(int(np.floor(row.min())) - 2, 0), min(int(np.ceil(row.max())) + 3, h)
    c0, c1 = max(int(np.floor(col.min())) - 2, 0), min(int(np.ceil(col.max())) + 3, wd)
    return r0, r1, c0, c1


def _union(a: tuple[int, int, int, int], b: tuple[int, int, int, int]) -> tuple[int, int, int, int]:
    return min(a[0], b[0]), max(a[1], b[1]), min(a[2], b[2]), max(a[3], b[3])


def _file_identity(fp: Any, order: int) -> list[Any]:
    from pathlib import Path

    try:
        st = Path(fp.shown).stat()
        size, mtime = st.st_size, st.st_mtime_ns
    except OSError:
        size, mtime = None, None
    return [order, str(Path(fp.shown).resolve()), fp.path, size, mtime, fp.row, fp.col, fp.height, fp.width]


def qm_digest(qm: Any, z: int, x: int, y: int, glob_digest: str) -> tuple[str | None, int]:
    """(digest, halo) of quantized-mesh tile z/x/y: None where the source gives none (a TIN's vertices).
    ``halo``: for a region, the widest fill halo of the blocks the tile reads (samples), recorded with the
    tile: :func:`qm_unchanged` hashes the files within that halo again."""
    return _qm_digest(qm, z, x, y, glob_digest, None)


def qm_unchanged(qm: Any, z: int, x: int, y: int, glob_digest: str, record: dict[str, Any] | None) -> bool:
    """True when ``record`` (what the output being updated keeps for tile z/x/y) was made from what the
    tile is made of now: the tile need not be encoded again."""
    if not record or not record.get("deps"):
        return False
    got, _ = _qm_digest(qm, z, x, y, glob_digest, int(record.get("halo", 0)))
    return got is not None and got == record["deps"]


def _qm_digest(qm: Any, z: int, x: int, y: int, glob_digest: str, halo: int | None) -> tuple[str | None, int]:
    from terralod.export.source import RegionGrid, SourceGrid

    ref = qm.ref
    if not isinstance(ref, SourceGrid):  # a TIN: the whole stored model (in the global facts) and the code
        model = getattr(ref, "model_digest", None)
        return (_sha(glob_digest, [z, x, y], model), 0) if model else (None, 0)
    if qm.lattice is not None:
        win = _lattice_window(qm, z, x, y)
        if z == qm.max_zoom - 1 and z > 0:  # its target comes from its parent's RMS
            win = _union(win, _lattice_window(qm, z - 1, x // 2, y // 2))
    else:
        win = _grid_window(ref, z, x, y, qm.grid_side)
    r0, r1, c0, c1 = win
    if not isinstance(ref, RegionGrid):
        zz = np.ascontiguousarray(ref.z_m[r0:r1, c0:c1])
        ok = np.packbits(np.ascontiguousarray(ref.valid[r0:r1, c0:c1]))
        return _sha(glob_digest, list(win), str(zz.dtype), zz.tobytes(), ok.tobytes()), 0
    from terralod.io.region import FILL_BLOCK

    b = FILL_BLOCK
    br0, br1, bc0, bc1 = r0 // b, (r1 - 1) // b + 1, c0 // b, (c1 - 1) // b + 1
    if halo is None:  # the widest halo its blocks' fill took (a block not filled here yet is filled now)
        halos = ref.reader.fill_halos
        for k in [(i, j) for i in range(br0, br1) for j in range(bc0, bc1)]:
            if k not in halos:
                ref.reader.block(*k)
        halo = max(halos.get((i, j), 0) for i in range(br0, br1) for j in range(bc0, bc1))
    ra, rb, ca, cb = br0 * b - halo, br1 * b + halo, bc0 * b - halo, bc1 * b + halo
    fps = ref.region.footprints
    meets = [i for i, f in enumerate(fps)
             if f.row < rb and f.row + f.height > ra and f.col < cb and f.col + f.width > ca]  # fmt: skip
    ident = [_file_identity(fps[i], i) for i in meets]
    return _sha(glob_digest, list(win), int(halo), ident), int(halo)


# -- 3D Tiles ----------------------------------------------------------------------------------------------
def tiles3d_global(view: Any, options: dict[str, Any]) -> str | None:
    """What every glb of 3D Tiles view ``view`` depends on (None: a terrain whose rows cannot be read, a
    TIN held only in memory: every glb is encoded)."""
    store = getattr(view.terrain, "store", None)
    model = (
        getattr(view.terrain, "model_digest", None) if getattr(view.terrain, "kind", "") == "tin" else None
    )
    if model:
        return _sha({"v": DIGEST_VERSION, "terralod": _version(), "tin": model,
                     "heights": view.geo.vertical_record(), "options": options})  # fmt: skip
    if store is None or not hasattr(store, "raw_tile"):
        return None
    meta = dict(store.meta)
    keep = {k: meta.get(k) for k in ("crs", "transform", "tile_size", "quantisation", "levels", "max_level",
                                      "width", "height", "spacing", "method", "format", "version")}  # fmt: skip
    for k, v in meta.items():
        if "quant" in k or "z_step" in k or "frac" in k:
            keep[k] = v
    hf = view._hf
    valid = None
    if hf is not None and hasattr(hf, "digest") and not hasattr(hf, "elevation_m"):
        valid = hf.digest()  # a regional epoch's validity, never read whole (export.common.KeptValidity)
    elif hf is not None:
        valid = hashlib.sha256(np.packbits(np.ascontiguousarray(hf.valid)).tobytes()).hexdigest()
    return _sha({"v": DIGEST_VERSION, "terralod": _version(), "meta": keep, "valid": valid,
                 "heights": view.geo.vertical_record(), "options": options})  # fmt: skip


def _row_digest(store: Any, code: Any, memo: dict[Any, str]) -> str:
    if code not in memo:
        try:
            t = store.raw_tile(*code)
            memo[code] = _sha(list(t.scalars()), t.vertices, t.triangles)
        except KeyError:
            memo[code] = "absent"
    return memo[code]


def tiles3d_digest(view: Any, code: Any, glob_digest: str | None, memo: dict[Any, str]) -> str | None:
    """The digest of node ``code``'s glb: its row, its parent's and grandparent's, its level neighbours'
    (None with no ``glob_digest``). ``memo`` keeps each row's digest for the run."""
    if glob_digest is None:
        return None
    if getattr(view.terrain, "kind", "") == "tin":  # the whole stored model is in the global digest
        return _sha(glob_digest, list(code))
    store = view.terrain.store
    n = view.nodes[code]
    chain = [code]
    p = n.parent
    for _ in range(2):
        if p is None:
            break
        chain.append(p)
        p = view.nodes[p].parent if p in view.nodes else None
    k, x, y = code
    around = [(k, x + dx, y + dy) for dy in (-1, 0, 1) for dx in (-1, 0, 1) if (dx, dy) != (0, 0)]
    rows = [[list(c), _row_digest(store, c, memo)] for c in chain]
    rows += [[list(c), _row_digest(store, c, memo) if c in view.nodes else "none"] for c in around]
    return _sha(glob_digest, [list(c) for c in chain], rows)
