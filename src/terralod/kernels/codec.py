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
