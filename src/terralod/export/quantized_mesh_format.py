"""Cesium quantized-mesh 1.0, the bytes of one tile: :func:`encode_tile` writes them, :func:`decode_tile`
reads them back (gzip'd or not).

Where a tile's bytes are decided: here, from a mesh handed in (vertex longitudes, latitudes and heights,
triangles, optional normals, water mask and metadata) and the tile's rectangle. Which tiles exist, which
mesh each holds and which error it declares is the tiler's (:mod:`terralod.export.quantized_mesh`).

Layout, in the specification's order (little-endian):

- header: tile centre (ECEF, 3 float64), height range (2 float32, widened to hold every height), bounding
  sphere (centre, radius) and horizon-occlusion point (ellipsoid-scaled space, CesiumJS's ellipsoidal
  occluder), all of the vertices as a decoder sees them (after quantisation);
- vertex data: count (uint32), then u, v and h each as zig-zag deltas (uint16; u/v on 0..32767 across the
  tile, quantised from double-precision degrees, h across the height range);
- indices: count (uint32), then high-water-mark codes (uint16, or uint32 aligned to 4 bytes above 65536
  vertices);
- edge indices: the vertices on the west, south, east and north edges (count + indices each);
- extensions: 1 oct-encoded normals (2 bytes a vertex), 2 water mask (one byte, or 256² north row first),
  4 metadata (a JSON object).

Order (the encoder's choice, the same for the same mesh): triangles in a walk across shared edges seeded
in Morton order of their centroids, each rotated to (shared, shared, new), vertices renumbered in
first-use order (:mod:`terralod.kernels.qmesh`): high-water-mark codes are mostly 0 and small offsets,
the zig-zag deltas of neighbours small (SRTM3: 2.7-3.4 B per triangle gzip'd without normals).

quantized-mesh-encoder (the peer of ``benchmarks/web.py``) is not used: its ``encode`` casts longitudes to
float32 (0.7 m steps at 85°W, coarser than the u/v lattice of deep tiles).
"""

from __future__ import annotations

import gzip
import io
import json
import struct
import zlib
from typing import Any

import numpy as np

from terralod.export.geodesy import ecef_lonlat
from terralod.kernels.qmesh import first_use, morton_seeds, rotate_after, walk_order

__all__ = [
    "EXT_METADATA",
    "EXT_NORMALS",
    "EXT_WATERMASK",
    "decode_tile",
    "encode_tile",
    "horizon_occlusion_point",
    "oct_decode",
    "oct_encode",
]

#: Extension ids of the format.
EXT_NORMALS, EXT_WATERMASK, EXT_METADATA = 1, 2, 4


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


def _reorder(u: np.ndarray, v: np.ndarray, tris: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Triangles in a walk across shared edges seeded in Morton order of their centroids, vertices
    renumbered in first-use order of them (what high-water-mark coding wants; neighbours come together,
    so the zig-zag deltas and the index codes are small and gzip well)."""
    tris = np.ascontiguousarray(tris, np.int64)
    if len(tris):
        seeds = morton_seeds(tris, u, v)
        tris = rotate_after(tris[walk_order(tris, seeds, len(u))])
    return first_use(tris, len(u))


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
    order, t = _reorder(u, v, np.asarray(tris, np.int64))
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


def decode_tile(
    data: bytes, rect: tuple[float, float, float, float] | None = None, *, gzipped: bool | None = None
) -> dict[str, Any]:
    """Parse a quantized-mesh tile (gzip'd or not): header, u/v/h, triangles, edges, extensions; with
    ``rect`` also lon/lat/height of the vertices.

    ``gzipped``: whether ``data`` is gzip'd; None guesses, and a guess never fails a tile: an uncompressed
    tile begins with its centre's x (a double) whose first two bytes are gzip's magic once in 65,536 tiles
    (a 256-tile SRTM3 region has 11,483 tiles: one of them did), so bytes that look gzip'd but do not
    decompress are read as they are."""
    if gzipped or (gzipped is None and data[:3] == b"\x1f\x8b\x08"):
        try:
            data = gzip.decompress(data)
        except (OSError, EOFError, zlib.error):
            if gzipped:
                raise
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
