"""Cesium quantized-mesh 1.0 export of any terrain: ``layer.json`` + gzip'd ``Z/X/Y.terrain`` tiles.

The tiling. Quantized-mesh lives on Cesium's *geographic* tiling scheme (EPSG:4326, two 180° roots at
level 0, 2^(z+1) x 2^z tiles at level z, TMS rows: y grows north). That is a second tiling beside the
store's own quadtree, and it exists only here at the export boundary: each tile's rectangle is converted
to the store's CRS with pyproj and the terrain is re-tiled into it from the *source samples* (the store's
source DEM when it can be read again and has the store's digest; otherwise the store's finest meshes, i.e.
the full-resolution TIN of a TIN store or the finest tiles of a grid store, interpolated on their own
triangles). Levels run from 0 to the first level whose tiles, sampled at 257², are as fine as the source.

The meshing is adaptive greedy insertion (pydelatin, Garland & Heckbert's scheme as in Delatin) on the
257² samples of each tile with a target error of a quarter of CesiumJS's level maximum geometric error
(the error CesiumJS assumes for the level when it computes screen-space error); the error written with
each tile is then *measured*: max vertical distance between the tile surface and every source sample inside
the tile (metadata extension ``terralod.error_m``, and ``error_m`` per level in ``layer.json``). The store's
own cohesion mesher needs the store's quantised lattice, which does not exist in the geographic tiling;
greedy insertion is the closest method that meshes an arbitrary sample grid to an error target (deviation
from the issue's "store's own method", and why).

A geographic DEM (``terralod export dem.tif``, or a store whose source DEM is one) is meshed on its own
lattice instead (:mod:`terralod.export.lattice`): every sample at the two finest zooms, every 2nd, 4th...
below; the finest zoom at FINEST_ERROR_M, the one below it at its level target, tiles whose RMS is then
above RMS_GOAL_M meshed again at a target scaled to it.

Nodata: outside the source footprint the surface continues the data's edge values; inside, nodata samples
keep the fill (the store's; the push-pull fill of :func:`terralod.export.source.fill_push_pull` for a DEM
read on its lattice). The water-mask extension marks nodata and sea at 0 m where a tile holds any (one
byte elsewhere). Normals (oct-encoded extension, only with ``normals=True``: about 0.7 B a triangle
gzip'd, and CesiumJS asks for them only with ``requestVertexNormals``) are the normals of the continuous
sampled surface at each vertex (central differences on the samples, ENU → ECEF), so the tiles of one
level have identical normals at their shared borders. CesiumJS adds its own skirts from the edge indices.

Bytes: triangles in a walk across shared edges seeded in Morton order, each rotated to (shared, shared,
new), vertices in first-use order: high-water-mark codes are mostly 0 and small offsets, the zig-zag
deltas of neighbours small (SRTM3: 2.7-3.4 B per triangle gzip'd without normals).

The binary is written by :func:`encode_tile` following the format's specification (header, zig-zag delta
u/v/h, high-water-mark indices, edge lists, extensions), with the horizon-occlusion point computed as CesiumJS's ellipsoidal occluder describes it.
quantized-mesh-encoder (the peer of ``benchmarks/web.py``) is not used for the tiles: its ``encode`` casts longitudes to float32 (0.7 m steps at 85°W, coarser than the
u/v lattice of deep tiles), so the vertex data is written here in double precision.
"""

from __future__ import annotations

import gzip
import io
import json
import math
import struct
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numba import njit

from terralod.export.common import check_exportable, export_inputs, export_key
from terralod.export.geodesy import WGS84_A_M, Geodesy, ecef_lonlat, enu_frame, tile_rectangle
from terralod.export.tiles3d import ExportReport
from terralod.kernels.error import triangle_gap

__all__ = [
    "QuantizedMesh",
    "decode_tile",
    "encode_tile",
    "export_quantized_mesh",
    "level_max_error_m",
    "tile_rectangle",
]

#: Samples per tile side of the re-tiling (the water mask is 256², so this is one more).
SAMPLES = 257
#: Target error of the greedy insertion, as a fraction of CesiumJS's level maximum geometric error.
TARGET_FRACTION = 0.25
#: Greedy-insertion target at the finest zoom of a lattice export at most this (m): the zoom CesiumJS
#: shows up close and never refines, holding the DEM's detail (SRTM heights are whole metres).
FINEST_ERROR_M = 3.0
#: RMS error (m) the zoom below the finest aims at on a lattice export: a tile whose RMS at the level's
#: target is above it is meshed again at a target scaled down to it (once; the measured errors are what
#: the tile declares either way). It puts one zoom of the pyramid at the RMS of the finest tiles other
#: tools serve (Cesium Terrain Builder's z12 on SRTM3: 6-9 m), between the level's quarter of CesiumJS's
#: error and the finest zoom's full detail.
RMS_GOAL_M = 8.0
#: Extension ids of the format.
EXT_NORMALS, EXT_WATERMASK, EXT_METADATA = 1, 2, 4


def level_max_error_m(z: int) -> float:
    """CesiumJS's level maximum geometric error of the geographic scheme (a 65² heightmap's, 0.25 quality)."""
    return WGS84_A_M * 2.0 * math.pi * 0.25 / (65 * 2) / (1 << z)


# -- the binary format ---------------------------------------------------------------------------------
def _zigzag_delta(a: np.ndarray) -> np.ndarray:
    d = np.diff(a.astype(np.int64), prepend=np.int64(0))
    return ((d << 1) ^ (d >> 63)).astype(np.uint16)


def _unzigzag_delta(z: np.ndarray) -> np.ndarray:
    z = z.astype(np.int64)
    return np.cumsum((z >> 1) ^ -(z & 1)).astype(np.int64)


def _hwm_encode(idx: np.ndarray) -> np.ndarray:
    """High-water-mark coding: each index as (highest + 1 so far) - index; needs first-use order."""
    flat = idx.astype(np.int64).ravel()
    hw = np.maximum.accumulate(np.concatenate([[-1], flat[:-1]])) + 1
    return hw - flat


def _hwm_decode(code: np.ndarray) -> np.ndarray:
    """Inverse of :func:`_hwm_encode`: each index is (highest + 1 so far) - code, the mark rising at 0."""
    c = code.astype(np.int64)
    zero = (c == 0).astype(np.int64)
    return np.cumsum(zero) - zero - c


def oct_encode(n: np.ndarray) -> np.ndarray:
    """(N, 3) unit vectors → (N, 2) uint8 oct encoding (the format's normal extension)."""
    n = np.asarray(n, np.float64)
    p = n[:, :2] / np.maximum(np.abs(n).sum(axis=1, keepdims=True), 1e-30)
    neg = n[:, 2] < 0
    q = p.copy()
    q[neg] = (1.0 - np.abs(p[neg][:, ::-1])) * np.where(p[neg] >= 0, 1.0, -1.0)
    return np.rint((np.clip(q, -1, 1) * 0.5 + 0.5) * 255).astype(np.uint8)


def oct_decode(e: np.ndarray) -> np.ndarray:
    f = e.astype(np.float64) / 255.0 * 2.0 - 1.0
    z = 1.0 - np.abs(f).sum(axis=1)
    xy = f.copy()
    neg = z < 0
    xy[neg] = (1.0 - np.abs(f[neg][:, ::-1])) * np.where(f[neg] >= 0, 1.0, -1.0)
    v = np.column_stack([xy, z])
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def _spread10(a: np.ndarray) -> np.ndarray:
    """The low 10 bits of ``a`` spread to the even bits (half of a Morton code)."""
    a = a.astype(np.int64) & 0x3FF
    a = (a | (a << 8)) & 0x00FF00FF
    a = (a | (a << 4)) & 0x0F0F0F0F
    a = (a | (a << 2)) & 0x33333333
    return (a | (a << 1)) & 0x55555555


@njit(cache=True)
def _free(nbr, seen, t):  # pragma: no cover - numba
    """How many unvisited neighbours triangle t has."""
    k = 0
    for q in range(3):
        m = nbr[3 * t + q]
        if m >= 0 and not seen[m]:
            k += 1
    return k


@njit(cache=True)
def _walk_order(tris, seeds, nv):  # pragma: no cover - numba
    """Triangle order: a depth-first walk across shared edges (each next triangle shares an edge with the
    one before wherever it can, so two of its three indices are recent ones and the high-water-mark codes
    stay small), going on to the unvisited neighbour that comes first in ``seeds`` (Morton order of the
    centroids), restarting at the next unvisited seed when the walk is stuck."""
    nt = tris.shape[0]
    # each undirected edge's two triangles through an open-addressing table of edge keys (one pass)
    cap = 16
    while cap < 6 * nt:
        cap *= 2
    slot_key = np.full(cap, -1, np.int64)
    slot_half = np.empty(cap, np.int64)
    nbr = np.full(3 * nt, -1, np.int64)
    for t in range(nt):
        for q in range(3):
            a = tris[t, q]
            b = tris[t, (q + 1) % 3]
            key = min(a, b) * nv + max(a, b)
            h = (key * 2654435761) & (cap - 1)
            while slot_key[h] >= 0 and slot_key[h] != key:
                h = (h + 1) & (cap - 1)
            if slot_key[h] == key:
                o = slot_half[h]
                nbr[3 * t + q] = o // 3
                nbr[o] = t
            else:
                slot_key[h] = key
                slot_half[h] = 3 * t + q
    rank = np.empty(nt, np.int64)
    for i in range(nt):
        rank[seeds[i]] = i
    seen = np.zeros(nt, np.bool_)
    out = np.empty(nt, np.int64)
    no = 0
    stack = np.empty(2 * nt + 1, np.int64)
    sp = 0
    for s in seeds:
        if seen[s]:
            continue
        cur = s
        while True:
            seen[cur] = True
            out[no] = cur
            no += 1
            best = -1
            for q in range(3):
                m = nbr[3 * cur + q]
                if m >= 0 and not seen[m]:
                    if best < 0:
                        best = m
                    elif _free(nbr, seen, m) * nt + rank[m] < _free(nbr, seen, best) * nt + rank[best]:
                        stack[sp] = best
                        sp += 1
                        best = m
                    else:
                        stack[sp] = m
                        sp += 1
            if best < 0:
                while sp > 0:
                    sp -= 1
                    if not seen[stack[sp]]:
                        best = stack[sp]
                        break
            if best < 0:
                break
            cur = best
    return out


@njit(cache=True)
def _rotate_after(tris):  # pragma: no cover - numba
    """Each triangle rotated (its winding kept) so that the vertex it does not share with the triangle
    before comes last: a walk's triangles then read (shared, shared, new)."""
    out = tris.copy()
    for t in range(1, tris.shape[0]):
        for q in range(3):
            i = tris[t, q]
            if i != out[t - 1, 0] and i != out[t - 1, 1] and i != out[t - 1, 2]:
                out[t, 0] = tris[t, (q + 1) % 3]
                out[t, 1] = tris[t, (q + 2) % 3]
                out[t, 2] = i
                break
    return out


@njit(cache=True)
def _first_use(tris, nv):  # pragma: no cover - numba
    """Vertices renumbered in first-use order of ``tris`` (unused ones last): (order, renumbered tris)."""
    remap = np.full(nv, -1, np.int64)
    order = np.empty(nv, np.int64)
    k = 0
    out = np.empty_like(tris)
    for t in range(tris.shape[0]):
        for q in range(3):
            i = tris[t, q]
            if remap[i] < 0:
                remap[i] = k
                order[k] = i
                k += 1
            out[t, q] = remap[i]
    for i in range(nv):
        if remap[i] < 0:
            remap[i] = k
            order[k] = i
            k += 1
    return order, out


@njit(cache=True)
def _merge_uv(tris, u, v):  # pragma: no cover - numba
    """One vertex per quantised (u, v) among those ``tris`` uses (the lowest index of each, in index
    order; open-addressing hash of u * 32768 + v): (kept indices, tris renumbered to them)."""
    n = u.size
    used = np.zeros(n, np.bool_)
    for t in range(tris.shape[0]):
        for q in range(3):
            used[tris[t, q]] = True
    cap = 16
    while cap < 2 * n:
        cap *= 2
    slot_key = np.full(cap, -1, np.int64)
    slot_val = np.empty(cap, np.int64)
    remap = np.full(n, -1, np.int64)
    keep = np.empty(n, np.int64)
    k = 0
    for i in range(n):
        if not used[i]:
            continue
        key = u[i] * 32768 + v[i]
        h = (key * 2654435761) & (cap - 1)
        while slot_key[h] >= 0 and slot_key[h] != key:
            h = (h + 1) & (cap - 1)
        if slot_key[h] == key:
            remap[i] = slot_val[h]
        else:
            slot_key[h] = key
            slot_val[h] = k
            remap[i] = k
            keep[k] = i
            k += 1
    out = np.empty_like(tris)
    for t in range(tris.shape[0]):
        for q in range(3):
            out[t, q] = remap[tris[t, q]]
    return keep[:k], out


def _reorder(uvh: np.ndarray, tris: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Triangles in a walk across shared edges seeded in Morton order of their centroids, vertices
    renumbered in first-use order of them (what high-water-mark coding wants; neighbours come together,
    so the zig-zag deltas and the index codes are small and gzip well)."""
    tris = np.ascontiguousarray(tris, np.int64)
    if len(tris):
        cu = uvh[tris, 0].sum(axis=1) // 96  # centroid / 32: 10 bits
        cv = uvh[tris, 1].sum(axis=1) // 96
        seeds = np.argsort(_spread10(cu) | (_spread10(cv) << 1), kind="stable")
        tris = _rotate_after(tris[_walk_order(tris, seeds, len(uvh))])
    return _first_use(tris, len(uvh))


#: WGS 84 radii (a, a, b), metres: the ellipsoid's scaled space of the horizon-occlusion point.
_RADII_M = np.array([6378137.0, 6378137.0, 6356752.314245179])


def horizon_occlusion_point(ecef: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """The format's horizon-occlusion point (ellipsoid-scaled space): along the scaled direction of
    ``centre``, far enough that it is above the horizon whenever any vertex is. A tile that spans a
    quarter of the globe or more has no such point; it gets one far out along that direction (seen from
    the whole hemisphere around it, so the tile is never wrongly culled where it can be seen)."""
    p = ecef / _RADII_M
    d = centre / _RADII_M
    d = d / np.linalg.norm(d)
    m2 = np.maximum((p * p).sum(axis=1), 1.0)
    m = np.sqrt(m2)
    u = p / np.linalg.norm(p, axis=1, keepdims=True)
    cos_a = u @ d
    sin_a = np.linalg.norm(np.cross(u, d), axis=1)
    cos_b = 1.0 / m
    sin_b = np.sqrt(m2 - 1.0) * cos_b
    den = cos_a * cos_b - sin_a * sin_b
    if np.any(den <= 1e-9):
        return d * 1e3
    return d * float((1.0 / den).max())


def encode_tile(
    lon: np.ndarray, lat: np.ndarray, h: np.ndarray, tris: np.ndarray, rect: tuple[float, float, float, float],
    *, normals: np.ndarray | None = None, watermask: np.ndarray | int | None = None,
    metadata: dict[str, Any] | None = None,
) -> bytes:  # fmt: skip
    """One quantized-mesh 1.0 tile (uncompressed bytes) of a mesh in degrees / ellipsoidal metres.

    ``tris`` counter-clockwise seen from above; ``normals`` (N, 3) ECEF unit vectors; ``watermask`` a
    256² uint8 grid (north row first) or one byte; ``metadata`` a JSON object.
    """
    w, s, e, n = rect
    u = np.rint(np.clip((lon - w) / (e - w), 0, 1) * 32767).astype(np.int64)
    v = np.rint(np.clip((lat - s) / (n - s), 0, 1) * 32767).astype(np.int64)
    # the height range as the header stores it (float32), widened to hold every height
    lo32, hi32 = np.float32(h.min()), np.float32(h.max())
    lo32 = lo32 if lo32 <= h.min() else np.nextafter(lo32, np.float32(-np.inf))
    hi32 = hi32 if hi32 >= h.max() else np.nextafter(hi32, np.float32(np.inf))
    hmin, hmax = float(lo32), float(hi32)
    hq = np.rint((h - hmin) / max(hmax - hmin, 1e-9) * 32767).astype(np.int64) if hmax > hmin else 0 * u
    order, t = _reorder(np.column_stack([u, v]), np.asarray(tris, np.int64))
    u, v, hq = u[order], v[order], hq[order]
    # the header bounds the vertices as a decoder sees them (after quantisation, float32 height range)
    ecef = ecef_lonlat(
        w + u / 32767.0 * (e - w), s + v / 32767.0 * (n - s), hmin + hq / 32767.0 * (hmax - hmin)
    )
    lo, hi = ecef.min(axis=0), ecef.max(axis=0)
    centre = 0.5 * (lo + hi)
    sc = centre  # the box centre and the farthest vertex (a tight enough sphere, in double precision)
    radius = float(np.sqrt(((ecef - sc) ** 2).sum(axis=1).max())) + 1e-3
    # the occlusion point's direction is the tile rectangle's centre on the ellipsoid, as CesiumJS's own
    # tessellators take it: the box centre of a tile that spans a hemisphere (zooms 0-1) lies near the
    # Earth's centre, and the direction it gives culled tile 0/1/0 from a camera above it
    towards = ecef_lonlat(np.array([0.5 * (w + e)]), np.array([0.5 * (s + n)]), np.array([0.0]))[0]
    occ = horizon_occlusion_point(ecef, towards)
    out = io.BytesIO()
    out.write(struct.pack("<3d2f4d3d", *centre, hmin, hmax, *sc, radius, *occ))
    nv = len(u)
    out.write(struct.pack("<I", nv))
    for a in (u, v, hq):
        out.write(_zigzag_delta(a).astype("<u2").tobytes())
    wide = nv > 65536
    if wide and out.tell() % 4:
        out.write(b"\x00" * (4 - out.tell() % 4))
    dt = "<u4" if wide else "<u2"
    out.write(struct.pack("<I", len(t)))
    out.write(_hwm_encode(t).astype(dt).tobytes())
    for side in (u == 0, v == 0, u == 32767, v == 32767):  # west, south, east, north
        ids = np.flatnonzero(side)
        out.write(struct.pack("<I", ids.size))
        out.write(ids.astype(dt).tobytes())
    if normals is not None:
        enc = oct_encode(np.asarray(normals)[order]).tobytes()
        out.write(struct.pack("<BI", EXT_NORMALS, len(enc)) + enc)
    if watermask is not None:
        wm = np.asarray(watermask, np.uint8).tobytes()
        out.write(struct.pack("<BI", EXT_WATERMASK, len(wm)) + wm)
    if metadata is not None:
        js = json.dumps(metadata, separators=(",", ":")).encode()
        out.write(struct.pack("<BII", EXT_METADATA, len(js) + 4, len(js)) + js)
    return out.getvalue()


def decode_tile(data: bytes, rect: tuple[float, float, float, float] | None = None) -> dict[str, Any]:
    """Parse a quantized-mesh tile (gzip'd or not): header, u/v/h, triangles, edges, extensions; with
    ``rect`` also lon/lat/height of the vertices."""
    if data[:2] == b"\x1f\x8b":
        data = gzip.decompress(data)
    head = struct.unpack_from("<3d2f4d3d", data, 0)
    pos = 88
    (nv,) = struct.unpack_from("<I", data, pos)
    pos += 4
    uvh = [_unzigzag_delta(np.frombuffer(data, "<u2", nv, pos + 2 * k * nv)) for k in range(3)]
    pos += 6 * nv
    wide = nv > 65536
    if wide and pos % 4:
        pos += 4 - pos % 4
    dt, sz = ("<u4", 4) if wide else ("<u2", 2)
    (nt,) = struct.unpack_from("<I", data, pos)
    pos += 4
    tris = _hwm_decode(np.frombuffer(data, dt, 3 * nt, pos)).reshape(-1, 3)
    pos += sz * 3 * nt
    edges = []
    for _ in range(4):
        (ne,) = struct.unpack_from("<I", data, pos)
        pos += 4
        edges.append(np.frombuffer(data, dt, ne, pos).astype(np.int64))
        pos += sz * ne
    ext: dict[int, bytes] = {}
    while pos < len(data):
        eid, ln = struct.unpack_from("<BI", data, pos)
        ext[eid] = data[pos + 5 : pos + 5 + ln]
        pos += 5 + ln
    out: dict[str, Any] = {
        "center": head[0:3], "min_height": head[3], "max_height": head[4], "sphere": head[5:9],
        "occlusion": head[9:12], "u": uvh[0], "v": uvh[1], "hq": uvh[2], "triangles": tris,
        "west": edges[0], "south": edges[1], "east": edges[2], "north": edges[3],
    }  # fmt: skip
    out["height"] = head[3] + uvh[2] / 32767.0 * (head[4] - head[3])
    if EXT_NORMALS in ext:
        out["normals"] = oct_decode(np.frombuffer(ext[EXT_NORMALS], np.uint8).reshape(-1, 2))
    if EXT_WATERMASK in ext:
        wm = np.frombuffer(ext[EXT_WATERMASK], np.uint8)
        out["watermask"] = wm.reshape(256, 256) if wm.size == 65536 else int(wm[0])
    if EXT_METADATA in ext:
        (ln,) = struct.unpack_from("<I", ext[EXT_METADATA], 0)
        out["metadata"] = json.loads(ext[EXT_METADATA][4 : 4 + ln])
    if rect is not None:
        w, s, e, n = rect
        out["lon"] = w + uvh[0] / 32767.0 * (e - w)
        out["lat"] = s + uvh[1] / 32767.0 * (n - s)
    return out


# -- the true error of a decoded tile --------------------------------------------------------------------
@njit(cache=True)
def _max_vertical_error_kernel(tu, tv, th, tris, pu, pv, pz):  # pragma: no cover - numba
    """Max |surface - z| over points (pu, pv, pz) of the triangles (tu, tv, th) in u/v units, and how many
    points no triangle covered (the points are bucketed on a square grid; each triangle visits the
    buckets of its bounding box; a point on a shared edge is tested by both triangles)."""
    n = pu.size
    nb = max(1, min(256, int(math.sqrt(n / 4.0)) + 1))
    scale = nb / 32768.0
    cell = np.empty(n, np.int64)
    start = np.zeros(nb * nb + 1, np.int64)
    for i in range(n):
        cx = min(max(int(pu[i] * scale), 0), nb - 1)
        cy = min(max(int(pv[i] * scale), 0), nb - 1)
        cell[i] = cy * nb + cx
        start[cell[i] + 1] += 1
    for k in range(nb * nb):
        start[k + 1] += start[k]
    fill = start[:-1].copy()
    order = np.empty(n, np.int64)
    for i in range(n):
        order[fill[cell[i]]] = i
        fill[cell[i]] += 1
    covered = np.zeros(n, np.bool_)
    err = 0.0
    for t in range(tris.shape[0]):
        a, b, c = tris[t, 0], tris[t, 1], tris[t, 2]
        ua, va, ub, vb, uc, vc = tu[a], tv[a], tu[b], tv[b], tu[c], tv[c]
        det = (vb - vc) * (ua - uc) + (uc - ub) * (va - vc)
        if det == 0.0:
            continue
        x0 = min(max(int(min(ua, ub, uc) * scale), 0), nb - 1)
        x1 = min(max(int(max(ua, ub, uc) * scale), 0), nb - 1)
        y0 = min(max(int(min(va, vb, vc) * scale), 0), nb - 1)
        y1 = min(max(int(max(va, vb, vc) * scale), 0), nb - 1)
        tol = 1e-9
        for cy in range(y0, y1 + 1):
            for cx in range(x0, x1 + 1):
                k = cy * nb + cx
                for j in range(start[k], start[k + 1]):
                    i = order[j]
                    d = triangle_gap(
                        ua, va, ub, vb, uc, vc, det, th[a], th[b], th[c], pu[i], pv[i], pz[i], tol
                    )
                    if d >= 0.0:
                        if d > err:
                            err = d
                        covered[i] = True
    missed = 0
    for i in range(n):
        if not covered[i]:
            missed += 1
    return err, missed


def true_error_m(tile: dict[str, Any], rect: tuple[float, float, float, float], lon: np.ndarray,
                 lat: np.ndarray, z_m: np.ndarray) -> float:  # fmt: skip
    """Max vertical distance (m) between a *decoded* tile (:func:`decode_tile`: u/v/h after quantisation,
    the surface CesiumJS interpolates, linear in u/v) and sample points (lon, lat, z) inside ``rect``."""
    if lon.size == 0:
        return 0.0
    w, s, e, n = rect
    pu = np.clip((lon - w) / (e - w), 0.0, 1.0) * 32767.0
    pv = np.clip((lat - s) / (n - s), 0.0, 1.0) * 32767.0
    err, missed = _max_vertical_error_kernel(
        tile["u"].astype(np.float64), tile["v"].astype(np.float64), np.asarray(tile["height"], np.float64),
        np.ascontiguousarray(tile["triangles"], np.int64), pu, pv, np.asarray(z_m, np.float64),
    )  # fmt: skip
    if missed:
        raise RuntimeError(f"{missed} samples fall outside every triangle of the tile (a hole in its mesh)")
    return float(err)


def _ceil4(x: float) -> float:
    """Round up to 0.1 mm (a declared error is never below the measured one)."""
    return math.ceil(x * 1e4) / 1e4


# -- the tiles -----------------------------------------------------------------------------------------
@dataclass
class QmTile:
    raw: bytes  # uncompressed (what the export writes by default)
    error_m: float
    triangles: int
    vertices: int
    nodata_fraction: float
    water: str  # "none", "all" or "some": the water mask the tile carries
    sumsq_m2: float = 0.0  # sum of squared vertical errors over the source samples measured ...
    samples: int = 0  # ... and how many (the level's RMS error; lattice tiles only)
    _gz: bytes | None = None

    @property
    def data(self) -> bytes:
        """gzip'd (what ``terralod serve`` sends with Content-Encoding: gzip); made on first use."""
        if self._gz is None:
            self._gz = gzip.compress(self.raw, 6, mtime=0)
        return self._gz


class QuantizedMesh:
    """The quantized-mesh view of one terrain: :meth:`layer` (layer.json dict) and :meth:`tile`.

    ``terrain`` is a store (:func:`terralod.terrain.open_terrain`) or a DEM's samples
    (:func:`terralod.export.source.source_from_dem`).
    """

    def __init__(
        self, terrain: Any, *, target_fraction: float = TARGET_FRACTION, normals: bool = False
    ) -> None:
        from terralod.export.lattice import Lattice
        from terralod.export.source import SourceGrid, TinSource, source_for

        if isinstance(terrain, SourceGrid):
            self.terrain = None
            self.ref = terrain
            self.name = Path(terrain.name).stem
        else:
            self.terrain = terrain
            where = str(terrain.path) if terrain.path is not None else None
            self.ref = source_for(terrain, Geodesy(terrain.crs, where))
            self.name = Path(str(terrain.path)).stem if terrain.path is not None else "terrain"
        self.target_fraction = target_fraction
        self.normals = bool(normals)
        self.bbox = self.ref.bbox
        # a geographic DEM is meshed on its own lattice (no resampling); anything else on 257² tile grids
        geographic = not isinstance(self.ref, TinSource) and getattr(self.ref, "identity", False)
        self.lattice = Lattice(self.ref) if geographic else None
        self.max_zoom = 0
        if self.lattice is not None:
            self.max_zoom = self.lattice.finest_zoom()
        else:
            while 180.0 / (1 << self.max_zoom) / (SAMPLES - 1) > self.ref.spacing_deg and self.max_zoom < 22:
                self.max_zoom += 1
        self._errors: dict[tuple[int, int, int], float] = {}
        self._rms_ratio: dict[tuple[int, int, int], float] = {}  # RMS / target of each lattice tile made

    def target_error_m(self, z: int) -> float:
        """Greedy-insertion target of level z: a fraction of CesiumJS's level error; 2x finer at the last
        level (nothing refines it, so it carries the detail of the source)."""
        f = self.target_fraction / (2.0 if z >= self.max_zoom else 1.0)
        if self.lattice is not None and z >= self.max_zoom:
            return min(f * level_max_error_m(z), FINEST_ERROR_M)
        return f * level_max_error_m(z)

    def level_range(self, z: int) -> tuple[int, int, int, int]:
        """(x0, y0, x1, y1) inclusive of the tiles of level z that meet the terrain (both roots at 0)."""
        if z == 0:
            return (0, 0, 1, 0)
        d = 180.0 / (1 << z)
        w, s, e, n = self.bbox
        x0, x1 = int((w + 180.0) // d), int((e + 180.0) // d)
        y0, y1 = int((s + 90.0) // d), int((n + 90.0) // d)
        return (x0, y0, min(x1, (2 << z) - 1), min(y1, (1 << z) - 1))

    def available(self, z: int, x: int, y: int) -> bool:
        if not 0 <= z <= self.max_zoom:
            return False
        x0, y0, x1, y1 = self.level_range(z)
        return x0 <= x <= x1 and y0 <= y <= y1

    def tile_codes(self) -> list[tuple[int, int, int]]:
        out = []
        for z in range(self.max_zoom + 1):
            x0, y0, x1, y1 = self.level_range(z)
            out += [(z, x, y) for y in range(y0, y1 + 1) for x in range(x0, x1 + 1)]
        return out

    def layer(self) -> dict[str, Any]:
        """layer.json: ``available`` per level, no per-tile metadata extension (CesiumJS parses that
        extension by default and then expects tile availability inside it); the measured errors are in
        ``terralod.error_m`` (per level) and ``errors.json`` (per tile) beside it."""
        return {
            "tilejson": "2.1.0",
            "name": self.name,
            "description": "terralod export: measured max vertical error per level in terralod.error_m, "
                           "per tile in errors.json",
            "version": "1.0.0",
            "format": "quantized-mesh-1.0",
            "scheme": "tms",
            "projection": "EPSG:4326",
            "tiles": ["{z}/{x}/{y}.terrain?v={version}"],
            "bounds": list(self.bbox),
            "minzoom": 0,
            "maxzoom": self.max_zoom,
            "extensions": (["octvertexnormals"] if self.normals else []) + ["watermask"],
            "available": [[dict(zip(("startX", "startY", "endX", "endY"), self.level_range(z), strict=True))]
                          for z in range(self.max_zoom + 1)],
            "terralod": {"heights": "as read (no geoid change)",
                         "error": "max vertical distance (m) between each tile as decoded (after quantisation) "
                                  "and every valid source sample inside it, in the source's own samples",
                         "outside": "the data's edge values extended outward (no cliff); watermask 255 marks "
                                    "nodata and sea at 0 m",
                         "target_error_m": [round(self.target_error_m(z), 4) for z in range(self.max_zoom + 1)]},
        }  # fmt: skip

    def samples(self, z: int, x: int, y: int, n: int = SAMPLES) -> tuple[np.ndarray, ...]:
        """(lon, lat, heights, water) on the tile's n² lattice plus a one-sample margin ((n+2)², north row
        first); outside the data the heights continue its edge values."""
        w, s, e, nn = tile_rectangle(z, x, y)
        du, dv = (e - w) / (n - 1), (nn - s) / (n - 1)
        lon = w + du * np.arange(-1, n + 1)
        lat = nn - dv * np.arange(-1, n + 1)
        LON, LAT = np.meshgrid(lon, lat)
        hgt = self.ref.height_at(LON.ravel(), LAT.ravel()).reshape(LON.shape)
        water = self.ref.water_at(LON.ravel(), LAT.ravel()).reshape(LON.shape)
        return LON, LAT, hgt, water

    def tile(
        self, z: int, x: int, y: int, *, regular: int | None = None, target_m: float | None = None
    ) -> QmTile:
        """Tile z/x/y: greedy-insertion mesh (or, with ``regular=k``, the k² regular grid), its error
        measured on the decoded tile against the source samples inside it."""
        from pydelatin import Delatin

        rect = tile_rectangle(z, x, y)
        target = self.target_error_m(z) if target_m is None else float(target_m)
        if self.lattice is not None and not regular:
            goal_zoom = target_m is None and z == self.max_zoom - 1
            floor_m = self.target_error_m(self.max_zoom)
            ratio = self._rms_ratio.get((z - 1, x // 2, y // 2)) if goal_zoom else None
            if ratio:  # the parent's RMS per metre of target predicts this tile's (same terrain)
                target = min(target, max(RMS_GOAL_M / ratio, floor_m))
            t = self._lattice_tile(z, x, y, rect, target)
            if t.samples and target > 0:
                rms = math.sqrt(t.sumsq_m2 / t.samples)
                self._rms_ratio[(z, x, y)] = rms / target
                # RMS is about proportional to the target: scale it down once where still above the goal
                if goal_zoom and rms > 1.05 * RMS_GOAL_M and target > floor_m:
                    t = self._lattice_tile(z, x, y, rect, max(target * RMS_GOAL_M / rms, floor_m))
            if target_m is None:
                self._errors[(z, x, y)] = t.error_m
            return t
        LON, LAT, filled, water = self.samples(z, x, y)
        core = filled[1:-1, 1:-1]
        n = SAMPLES
        if regular:
            step = (n - 1) // (regular - 1)
            ii = np.arange(0, n, step)
            C, R = np.meshgrid(ii, ii)
            cols, rows = C.ravel(), R.ravel()
            k = len(ii)
            a = (np.arange(k - 1)[None, :] + k * np.arange(k - 1)[:, None]).ravel()
            tris = np.concatenate([np.stack([a, a + k, a + 1], 1), np.stack([a + 1, a + k, a + k + 1], 1)])
        else:
            d = Delatin(core.astype(np.float32), width=n, height=n, max_error=target)
            cols = np.rint(d.vertices[:, 0]).astype(np.int64)
            rows = (n - 1) - np.rint(d.vertices[:, 1]).astype(np.int64)  # Delatin's y grows north
            tris = np.asarray(d.triangles, np.int64)
        hv = core[rows, cols]
        w, s, e, nn = rect
        lon = w + cols * (e - w) / (n - 1)
        lat = nn - rows * (nn - s) / (n - 1)
        # counter-clockwise seen from above (east, north)
        a, b = np.column_stack([lon, lat])[tris[:, 1]], np.column_stack([lon, lat])[tris[:, 2]]
        o = np.column_stack([lon, lat])[tris[:, 0]]
        cr = (a[:, 0] - o[:, 0]) * (b[:, 1] - o[:, 1]) - (a[:, 1] - o[:, 1]) * (b[:, 0] - o[:, 0])
        tris[cr < 0] = tris[cr < 0][:, ::-1]
        normals = self._normals(filled, rows, cols, rect, lon, lat) if self.normals else None
        wmask = water[1:-1, 1:-1][:256, :256]
        if not wmask.any():
            wm: np.ndarray | int = 0
            kind = "none"
        elif wmask.all():
            wm, kind = 255, "all"
        else:
            wm, kind = (wmask * 255).astype(np.uint8), "some"
        raw = encode_tile(lon, lat, hv, tris, rect, normals=normals, watermask=wm)
        plon, plat, pz = self.ref.points_in(z, x, y)
        err = _ceil4(true_error_m(decode_tile(raw, rect), rect, plon, plat, pz))
        nodata = float(water[1:-1, 1:-1].mean()) if kind != "none" else 0.0
        if regular is None and target_m is None:
            self._errors[(z, x, y)] = err
        return QmTile(raw, err, len(tris), len(lon), nodata, kind)

    def _lattice_tile(self, z: int, x: int, y: int, rect: tuple[float, float, float, float],
                      target: float) -> QmTile:  # fmt: skip
        """Greedy insertion on the tile's window of the source lattice (:mod:`terralod.export.lattice`);
        its error measured on the decoded tile against every valid source sample inside it."""
        from pydelatin import Delatin

        from terralod.export.lattice import clip_mesh, lattice_error

        lat_ = self.lattice
        stride = lat_.stride(z, self.max_zoom)
        r0, c0, g, (xw, xe, yn, ys) = lat_.grid(rect, stride)
        nr, nc = g.shape
        d = Delatin(g.astype(np.float32), width=nc, height=nr, max_error=target)
        vx = d.vertices
        gx, gy = vx[:, 0].copy(), (nr - 1) - vx[:, 1]  # Delatin's y grows north
        hx = g[np.rint(gy).astype(np.int64), np.rint(gx).astype(np.int64)]
        px, py, ph, tris = clip_mesh(gx, gy, hx, np.asarray(d.triangles, np.int64), xw, xe, yn, ys)
        fc, fr = c0 + px * stride, r0 + py * stride  # fractional lattice indices
        w, s, e, n = rect
        # one vertex per quantised u/v (clipping makes the same edge crossing in both neighbours)
        u = np.rint(np.clip((fc - (c0 + xw * stride)) / ((xe - xw) * stride), 0, 1) * 32767).astype(np.int64)
        v = np.rint(np.clip(((r0 + ys * stride) - fr) / ((ys - yn) * stride), 0, 1) * 32767).astype(np.int64)
        keep, tris = _merge_uv(np.ascontiguousarray(tris, np.int64), u, v)
        fc, fr, hv, u, v = fc[keep], fr[keep], ph[keep], u[keep], v[keep]
        area = (u[tris[:, 1]] - u[tris[:, 0]]) * (v[tris[:, 2]] - v[tris[:, 0]]) - (
            v[tris[:, 1]] - v[tris[:, 0]]
        ) * (u[tris[:, 2]] - u[tris[:, 0]])
        tris = tris[area != 0]
        tris[area[area != 0] < 0] = tris[area[area != 0] < 0][:, ::-1]  # counter-clockwise (east, north)
        lon = w + u / 32767.0 * (e - w)
        lat = s + v / 32767.0 * (n - s)
        normals = None
        if self.normals:
            enu = lat_.normals_enu(fr, fc, lat, stride)
            ea, no, up = enu_frame(lon, lat)
            normals = ea * enu[:, :1] + no * enu[:, 1:2] + up * enu[:, 2:3]
            normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        wm = lat_.water_mask(rect)
        kind = "some" if isinstance(wm, np.ndarray) else ("all" if wm == 255 else "none")
        raw = encode_tile(lon, lat, hv, tris, rect, normals=normals, watermask=wm)
        err, sumsq, count = lattice_error(lat_, decode_tile(raw, rect), rect)
        nodata = float(np.mean(wm) / 255.0) if kind != "none" else 0.0
        return QmTile(raw, _ceil4(err), len(tris), len(lon), nodata, kind, sumsq, count)

    def _normals(self, filled: np.ndarray, rows: np.ndarray, cols: np.ndarray, rect: tuple[float, ...],
                 lon: np.ndarray, lat: np.ndarray) -> np.ndarray:  # fmt: skip
        """ECEF unit normals of the sampled surface at the vertices (central differences, metres)."""
        w, s, e, n = rect
        du_m = (e - w) / (SAMPLES - 1) * 111320.0 * np.cos(np.radians(np.clip(lat, -89.9, 89.9)))
        dv_m = (n - s) / (SAMPLES - 1) * 111320.0
        r, c = rows + 1, cols + 1
        dzdx = (filled[r, c + 1] - filled[r, c - 1]) / (2 * np.maximum(du_m, 1e-6))
        dzdy = (filled[r - 1, c] - filled[r + 1, c]) / (2 * dv_m)
        enu = np.column_stack([-dzdx, -dzdy, np.ones_like(dzdx)])
        enu /= np.linalg.norm(enu, axis=1, keepdims=True)
        ea, no, up = enu_frame(lon, lat)
        out = ea * enu[:, :1] + no * enu[:, 1:2] + up * enu[:, 2:3]
        return out / np.linalg.norm(out, axis=1, keepdims=True)


def export_quantized_mesh(
    terrain: Any,
    out: str | Path,
    *,
    epoch: str | None = None,
    overwrite: bool = False,
    gzip_tiles: bool = False,
    normals: bool = False,
    resume: bool = False,
    update: bool = False,
    progress: Callable[[int, int], None] | None = None,
) -> ExportReport:
    """Write ``out/layer.json``, ``out/errors.json`` (measured error per tile) and ``out/Z/X/Y.terrain``.

    ``terrain`` is a store or a DEM's samples (:func:`terralod.export.source.source_from_dem`). Tiles are
    uncompressed (any static host serves them as they are); ``gzip_tiles`` writes them gzip'd, for a host
    that sends ``Content-Encoding: gzip`` with them (CesiumJS cannot read gzip'd tiles without it).
    ``resume``: the tiles an interrupted export of the same terrain and options finished are not encoded
    again; ``update``: only the files whose bytes change are rewritten (``extra["rewritten"]``). The output
    is written through :class:`terralod.output.Output`.
    """
    from terralod.export.source import SourceGrid
    from terralod.output import Output

    t0 = time.perf_counter()
    if not isinstance(terrain, SourceGrid):
        check_exportable(terrain, epoch)
        if epoch is not None and epoch != getattr(terrain, "epoch", None):
            terrain = terrain.with_epoch(epoch)
    output = Output(out, inputs=export_inputs(terrain), overwrite=overwrite, resume=resume, update=update,
                    key=export_key(terrain, "quantized-mesh", gzip=bool(gzip_tiles), normals=bool(normals)))  # fmt: skip
    output.check()  # refusals first, before the tiler's set-up
    qm = QuantizedMesh(terrain, normals=normals)
    rep = ExportReport(Path(out))
    per_level: dict[int, float] = {}
    per_tile: dict[str, float] = {}
    raw_bytes = gz_bytes = 0
    water = {"none": 0, "all": 0, "some": 0}
    level_sq: dict[int, list] = {}
    with output as o:
        codes = qm.tile_codes()
        for i, (z, x, y) in enumerate(codes):
            rel = f"{z}/{x}/{y}.terrain"
            r = o.record(rel)  # finished by the interrupted export this one resumes
            if r is None:
                t = qm.tile(z, x, y)
                data = t.data if gzip_tiles else t.raw
                r = {"bytes": len(data), "raw": len(t.raw), "gz": len(t.data) if gzip_tiles else 0,
                     "triangles": int(t.triangles), "sumsq_m2": float(t.sumsq_m2), "samples": int(t.samples),
                     "water": t.water, "error_m": float(t.error_m)}  # fmt: skip
                o.write(rel, data, r)
            rep.tiles += 1
            rep.bytes += r["bytes"]
            raw_bytes += r["raw"]
            gz_bytes += r["gz"]
            rep.triangles += r["triangles"]
            sq = level_sq.setdefault(z, [0.0, 0])
            sq[0] += r["sumsq_m2"]
            sq[1] += r["samples"]
            water[r["water"]] += 1
            per_level[z] = max(per_level.get(z, 0.0), r["error_m"])
            per_tile[f"{z}/{x}/{y}"] = r["error_m"]
            if progress is not None:
                progress(i + 1, len(codes))
        layer = qm.layer()
        layer["terralod"]["error_m"] = [_ceil4(per_level.get(z, 0.0)) for z in range(qm.max_zoom + 1)]
        if qm.lattice is not None:  # RMS over every valid source sample of the level (edge samples twice)
            layer["terralod"]["rms_m"] = [
                round(math.sqrt(level_sq[z][0] / level_sq[z][1]), 4) if level_sq.get(z, [0, 0])[1] else 0.0
                for z in range(qm.max_zoom + 1)
            ]
        layer["terralod"]["gzip"] = bool(gzip_tiles)
        js = json.dumps(layer, indent=1)
        o.write("layer.json", js.encode())
        o.write("errors.json", json.dumps({"unit": "m", "tiles": per_tile}, separators=(",", ":")).encode())
        rep.bytes += len(js)
        changes = {"rewritten": list(o.rewritten), "removed": o.prune()} if update else {}
    rep.seconds = time.perf_counter() - t0
    rep.extra = {
        "format": "quantized-mesh",
        "max_zoom": qm.max_zoom,
        "gzip": bool(gzip_tiles),
        "tile_bytes_raw": raw_bytes,
        "tile_bytes_gzip": gz_bytes if gzip_tiles else None,
        "water_masks": water,
        "error_m_per_level": layer["terralod"]["error_m"],
        "resumed": o.adopted is not None,
        **changes,
    }
    return rep
