"""An uncompressed quantized-mesh tile whose first bytes happen to be gzip's magic.

A tile begins with its centre's x (a little-endian double): its first two bytes are 1f 8b once in 65,536
tiles, and the 256-tile SRTM3 region (11,483 tiles) has one. Reading it back as gzip failed the export at
68 % ("Unknown compression method"): a tile's bytes are read as they are unless they are told, or proved
by decompressing, to be gzip'd.
"""

from __future__ import annotations

import gzip

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from terralod.export.quantized_mesh_format import decode_tile, encode_tile


def _tile(seed: int) -> tuple[bytes, tuple[float, float, float, float]]:
    rng = np.random.default_rng(seed)
    rect = (1.0, 41.0, 1.0 + 180 / 2**10, 41.0 + 180 / 2**10)
    n = 9
    u, v = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n))
    lon = rect[0] + u.ravel() * (rect[2] - rect[0])
    lat = rect[1] + v.ravel() * (rect[3] - rect[1])
    h = rng.uniform(0, 500, lon.size)
    a = (np.arange(n - 1)[None, :] + n * np.arange(n - 1)[:, None]).ravel()
    tris = np.concatenate([np.stack([a, a + 1, a + n], 1), np.stack([a + 1, a + n + 1, a + n], 1)])
    return encode_tile(lon, lat, h, tris, rect), rect


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**31), st.binary(min_size=6, max_size=6))
def test_a_raw_tile_starting_like_gzip_reads_as_itself(seed: int, rest: bytes) -> None:
    raw, rect = _tile(seed)
    # the centre's x with gzip's magic and method (1f 8b 08) as its first bytes: still a double, a tile
    looks = b"\x1f\x8b\x08" + rest[:5] + raw[8:]
    want = decode_tile(raw, rect)
    for got in (decode_tile(looks, rect), decode_tile(looks, rect, gzipped=False)):
        for k in ("u", "v", "height", "triangles"):
            assert np.array_equal(got[k], want[k]), k
    # a gzip'd tile still reads, guessed or told
    gz = gzip.compress(raw, 6, mtime=0)
    for got in (decode_tile(gz, rect), decode_tile(gz, rect, gzipped=True)):
        assert np.array_equal(got["triangles"], want["triangles"])
