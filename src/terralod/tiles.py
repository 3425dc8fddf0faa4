"""Tile codes and the pyramid plan: pure integer math at the bottom of the house.

A terrain of W x H samples is covered by a square quadtree whose finest level samples the source at
stride 1. With M = 2^n + 1 vertices per tile side (default 65) and L = ceil(log2((max(W, H) - 1) / (M - 1))),
the padded grid is P = (M - 1) * 2^L + 1 samples on a side; level k (0 <= k <= L) has 2^k x 2^k tile slots
of stride s = 2^(L - k) samples, each spanning (M - 1) * s samples. Tile code (level, x, y): x grows east,
y grows south (raster order), level 0 is the single root — one definition for build, store and runtime.

Only tiles that cover source samples exist: tile (k, x, y) exists when x * span < W - 1 and
y * span < H - 1. A quad (i, j) of a tile is kept when its north-west corner lies strictly inside the
source's sample rectangle, so meshes end at the data instead of dragging a padded apron along; vertices
that fall in the padding (only on the far side of such a quad) take the edge-replicated source height.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Iterator
from dataclasses import dataclass

TileCode = tuple[int, int, int]

#: Edge neighbours as (dx, dy): left (west), up (north), right (east), down (south) — Li, Liu & Liu's LN/UN/RN/DN.
EDGE_OFFSETS: dict[str, tuple[int, int]] = {"L": (-1, 0), "U": (0, -1), "R": (1, 0), "D": (0, 1)}
#: Corner neighbours: LU (north-west), RU (north-east), RD (south-east), LD (south-west).
CORNER_OFFSETS: dict[str, tuple[int, int]] = {"LU": (-1, -1), "RU": (1, -1), "RD": (1, 1), "LD": (-1, 1)}


def is_valid_tile_size(m: int) -> bool:
    """True when ``m`` is 2^n + 1 with n >= 1."""
    return m >= 3 and ((m - 1) & (m - 2)) == 0


@dataclass(frozen=True)
class TilePyramid:
    """The quadtree plan over a W x H sample grid (pure; no data).

    Attributes
    ----------
    width, height : int
        Source size in samples (columns, rows).
    tile_size : int
        M, vertices per tile side (2^n + 1).
    """

    width: int
    height: int
    tile_size: int = 65

    def __post_init__(self) -> None:
        if not is_valid_tile_size(self.tile_size):
            raise ValueError(f"Expected tile size 2^n + 1 (e.g. 33, 65, 129), got {self.tile_size}")
        if self.width < 2 or self.height < 2:
            raise ValueError(f"Expected at least 2x2 samples, got {self.width}x{self.height}")

    @property
    def cells(self) -> int:
        """M - 1: quads per tile side."""
        return self.tile_size - 1

    @functools.cached_property
    def max_level(self) -> int:
        """L, the finest level (stride 1); computed once (every stride, span and child asks for it)."""
        need = (max(self.width, self.height) - 1) / self.cells
        return max(0, math.ceil(math.log2(need))) if need > 1 else 0

    @property
    def levels(self) -> list[int]:
        return list(range(self.max_level + 1))

    @property
    def padded_size(self) -> int:
        """P = (M - 1) * 2^L + 1 samples on a side."""
        return self.cells * (1 << self.max_level) + 1

    def stride(self, level: int) -> int:
        """Source samples between neighbouring vertices at ``level``."""
        return 1 << (self.max_level - level)

    def span(self, level: int) -> int:
        """Source samples spanned by one tile side at ``level`` ((M - 1) * stride)."""
        return self.cells * self.stride(level)

    def grid_count(self, level: int) -> tuple[int, int]:
        """(nx, ny): existing tiles east-west and north-south at ``level``."""
        s = self.span(level)
        return -(-(self.width - 1) // s), -(-(self.height - 1) // s)

    def exists(self, code: TileCode) -> bool:
        level, x, y = code
        if level < 0 or level > self.max_level or x < 0 or y < 0:
            return False
        nx, ny = self.grid_count(level)
        return x < nx and y < ny

    def tile_codes(self, level: int) -> Iterator[TileCode]:
        """Existing tiles of ``level`` in raster order (y, then x)."""
        nx, ny = self.grid_count(level)
        for y in range(ny):
            for x in range(nx):
                yield (level, x, y)

    def all_codes(self, finest_first: bool = False) -> list[TileCode]:
        lv = self.levels[::-1] if finest_first else self.levels
        return [c for k in lv for c in self.tile_codes(k)]

    def origin_rc(self, code: TileCode) -> tuple[int, int]:
        """Source (row, col) of the tile's north-west vertex."""
        level, x, y = code
        s = self.span(level)
        return y * s, x * s

    def children(self, code: TileCode) -> list[TileCode]:
        """Existing children (finer level) of ``code``, in NW, NE, SW, SE order."""
        level, x, y = code
        if level >= self.max_level:
            return []
        out = [(level + 1, 2 * x + dx, 2 * y + dy) for dy in (0, 1) for dx in (0, 1)]
        return [c for c in out if self.exists(c)]

    def neighbour(self, code: TileCode, direction: str) -> TileCode | None:
        """Same-level neighbour in one of the 8 directions of EDGE_OFFSETS / CORNER_OFFSETS, or None."""
        off = EDGE_OFFSETS.get(direction) or CORNER_OFFSETS.get(direction)
        if off is None:
            raise ValueError(
                f"Expected one of {list(EDGE_OFFSETS) + list(CORNER_OFFSETS)}, got {direction!r}"
            )
        n = (code[0], code[1] + off[0], code[2] + off[1])
        return n if self.exists(n) else None

    def xy_frac_bits(self, level: int) -> int:
        """Fractional bits of the 16-bit horizontal quantisation at ``level``.

        Vertex column/row offsets inside a tile are stored as ``offset_samples * 2^f`` in 0..65535, with
        f = floor(log2(65535 / span)). All tiles of a level share this lattice, so shared boundary
        vertices dequantise to identical coordinates, and grid vertices (integer offsets) are exact.
        f is negative where a tile spans over 65,535 samples (the coarse levels of a raster over 32,769
        samples a side): the lattice step is then 2^-f samples, still far finer than the level's stride,
        so its grid vertices stay exact.
        """
        return int(math.floor(math.log2(65535 / self.span(level))))


def parent(code: TileCode) -> TileCode | None:
    """The tile one level coarser that contains ``code`` (None for the root)."""
    level, x, y = code
    return None if level == 0 else (level - 1, x // 2, y // 2)


def ancestor(code: TileCode, level: int) -> TileCode:
    """The ancestor of ``code`` at ``level`` (<= code's level)."""
    k, x, y = code
    if level > k:
        raise ValueError(f"Expected a level <= {k}, got {level}")
    sh = k - level
    return (level, x >> sh, y >> sh)
