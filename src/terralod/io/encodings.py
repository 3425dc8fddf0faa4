"""RGB-encoded elevation (web-map terrain tiles), both directions, in metres.

- Terrain-RGB (Mapbox): ``h = -10000 + (R * 65536 + G * 256 + B) * 0.1`` (0.1 m steps).
- Terrarium (Mapzen/AWS, Mapterhorn): ``h = R * 256 + G + B / 256 - 32768`` (1/256 m steps).

Pure array codecs shared by the image reader (:mod:`terralod.io.heightmap`) and the GDAL reader
(:mod:`terralod.io.raster`), so neither imports the other.
"""

from __future__ import annotations

import numpy as np

from terralod.errors import InputError

#: Canonical encoding names.
ENCODINGS = ("terrain-rgb", "terrarium")


def decode_terrain_rgb(rgb: np.ndarray) -> np.ndarray:
    """Mapbox Terrain-RGB (H, W, >=3) uint8 → (H, W) float64 metres: -10000 + (R*65536 + G*256 + B) * 0.1."""
    code = _rgb_code(rgb)
    return code * 0.1 - 10000.0


def decode_terrarium(rgb: np.ndarray) -> np.ndarray:
    """Terrarium (H, W, >=3) uint8 → (H, W) float64 metres: R*256 + G + B/256 - 32768."""
    code = _rgb_code(rgb)
    return code / 256.0 - 32768.0


def encode_terrain_rgb(elevation_m: np.ndarray) -> np.ndarray:
    """(H, W) metres → (H, W, 3) uint8 Terrain-RGB, rounded to 0.1 m, clipped to -10000..1667721.5 m."""
    code = np.clip(np.round((np.asarray(elevation_m, np.float64) + 10000.0) * 10.0), 0, 2**24 - 1)
    return _code_rgb(code.astype(np.int64))


def encode_terrarium(elevation_m: np.ndarray) -> np.ndarray:
    """(H, W) metres → (H, W, 3) uint8 Terrarium, rounded to 1/256 m, clipped to -32768..32767.996 m."""
    code = np.clip(np.round((np.asarray(elevation_m, np.float64) + 32768.0) * 256.0), 0, 2**24 - 1)
    return _code_rgb(code.astype(np.int64))


def decode_rgb(rgb: np.ndarray, encoding: str, source: str | None = None) -> np.ndarray:
    """Decode an (H, W, >=3) RGB array with ``encoding`` ("terrain-rgb" or "terrarium") to metres."""
    if encoding == "terrain-rgb":
        return decode_terrain_rgb(rgb)
    if encoding == "terrarium":
        return decode_terrarium(rgb)
    raise InputError(f"unknown encoding {encoding!r}; expected one of {', '.join(ENCODINGS)}", source)


def _rgb_code(rgb: np.ndarray) -> np.ndarray:
    a = np.asarray(rgb)
    if a.ndim != 3 or a.shape[2] < 3:
        raise ValueError(f"Expected an (H, W, 3) RGB array, got shape {a.shape}")
    a = a.astype(np.int64)
    return ((a[..., 0] << 16) | (a[..., 1] << 8) | a[..., 2]).astype(np.float64)


def _code_rgb(code: np.ndarray) -> np.ndarray:
    return np.stack([(code >> 16) & 255, (code >> 8) & 255, code & 255], axis=-1).astype(np.uint8)
