"""Tile blob coding kernels: zig-zag coded wrapped deltas (quantized-mesh style), pure and allocation-exact."""

from __future__ import annotations

import numpy as np

from terralod.kernels import jit


@jit
def undo_zigzag_delta(codes, mask):
    """Inverse of zig-zag delta coding: running sum of the decoded deltas, wrapped to ``mask`` (0xFFFF or
    0xFFFFFFFF). ``codes`` are unsigned ints; returns int64 values in 0..mask."""
    out = np.empty(codes.size, np.int64)
    acc = 0
    for i in range(codes.size):
        z = np.int64(codes[i])
        acc = (acc + ((z >> 1) ^ -(z & 1))) & mask
        out[i] = acc
    return out


@jit
def zigzag_delta_codes(a, mask, out, at):
    """Zig-zag codes of the deltas of ``a`` wrapped to ``mask`` bits (0xFFFF or 0xFFFFFFFF), written to
    ``out[at : at + a.size]``: the delta of each value from the one before (0 before the first), read as a
    signed 16- or 32-bit number d, coded ``(d << 1) ^ (d >> bits - 1)`` (small numbers for coherent data).
    The store's tile coding (:func:`terralod.store.encode_vertices`); tests/test_build_speed.py checks it
    against the numpy formula."""
    half = (mask >> 1) + 1  # 2^15 or 2^31
    sign = 15 if mask == 0xFFFF else 31
    prev = np.int64(0)
    for i in range(a.size):
        v = np.int64(a[i])
        d = (v - prev) & mask
        if d >= half:
            d -= mask + 1
        out[at + i] = ((d << 1) ^ (d >> sign)) & mask
        prev = v
    return at + a.size


@jit
def vertex_codes(q):
    """(N, 3) uint16 quantised (u, v, h) → (3 N,) uint16: the zig-zag delta codes of column u, then v, then h
    (the payload of a tile's vertex blob before zlib)."""
    n = q.shape[0]
    out = np.empty(3 * n, np.uint16)
    for k in range(3):
        zigzag_delta_codes(q[:, k], 0xFFFF, out, k * n)
    return out


@jit
def triangle_codes16(t):
    """(K, 3) indices, all < 2^16 → (3 K,) uint16 zig-zag delta codes of the flat index list."""
    flat = t.ravel()
    out = np.empty(flat.size, np.uint16)
    zigzag_delta_codes(flat, 0xFFFF, out, 0)
    return out


@jit
def triangle_codes32(t):
    """(K, 3) indices → (3 K,) uint32 zig-zag delta codes (32-bit wrap) of the flat index list."""
    flat = t.ravel()
    out = np.empty(flat.size, np.uint32)
    zigzag_delta_codes(flat, 0xFFFFFFFF, out, 0)
    return out


@jit
def quantise_tile(rows, cols, hz, r0, c0, xy_frac_bits, z_step_m, dx, dy):
    """A tile's vertices on its level's 16-bit lattice, and the same vertices dequantised (the geometry
    exactly as stored, which the builder measures).

    u = rint((col - c0) 2^bits), v = rint((row - r0) 2^bits), z index = rint(h / z_step_m) (round half to
    even, as numpy's rint); q = (u, v, z index - z0) with z0 the smallest z index. Dequantised, in the
    window frame: (u 2^-bits dx, v 2^-bits dy, (z0 + q_h) z_step_m).

    Returns (q (N, 3) uint16, z0, local (N, 3) float64, ok): ok is False when a value falls outside
    0..65535 (q is then not meaningful); N must be > 0.
    """
    n = rows.shape[0]
    scale = 2.0**xy_frac_bits  # exact; bits < 0 where a tile spans over 65,535 samples
    u = np.rint((cols - c0) * scale)
    v = np.rint((rows - r0) * scale)
    zi = np.empty(n, np.int64)
    for i in range(n):
        zi[i] = np.int64(np.rint(hz[i] / z_step_m))
    z0 = zi.min()
    ok = True
    q = np.empty((n, 3), np.uint16)
    for i in range(n):
        qz = zi[i] - z0
        if not (0.0 <= u[i] <= 65535.0 and 0.0 <= v[i] <= 65535.0 and qz <= 65535):
            ok = False
            continue
        q[i, 0] = np.uint16(u[i])
        q[i, 1] = np.uint16(v[i])
        q[i, 2] = np.uint16(qz)
    inv = 2.0 ** (-xy_frac_bits)
    local = np.empty((n, 3), np.float64)
    for i in range(n):
        local[i, 0] = q[i, 0] * inv * dx
        local[i, 1] = q[i, 1] * inv * dy
        local[i, 2] = (z0 + np.int64(q[i, 2])) * z_step_m
    return q, z0, local, ok
