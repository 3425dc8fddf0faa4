"""Pyramid plan invariants (pure integer math)."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from terralod.tiles import TilePyramid, ancestor, is_valid_tile_size, parent

sizes = st.integers(2, 3000)
tile_sizes = st.sampled_from([3, 5, 9, 17, 33, 65, 129])


@given(w=sizes, h=sizes, m=tile_sizes)
@settings(max_examples=200, deadline=None)
def test_plan_covers_source_once_per_level(w: int, h: int, m: int) -> None:
    p = TilePyramid(w, h, m)
    assert p.padded_size >= max(w, h)
    assert p.stride(p.max_level) == 1
    # L is the smallest level count that covers the source
    if p.max_level > 0:
        assert (m - 1) * (1 << (p.max_level - 1)) < max(w, h) - 1
    for k in p.levels:
        nx, ny = p.grid_count(k)
        span = p.span(k)
        # the existing tiles cover every sample column/row, and none is empty
        assert nx * span >= w - 1 and (nx - 1) * span < w - 1
        assert ny * span >= h - 1 and (ny - 1) * span < h - 1
        assert 0 < (1 << p.xy_frac_bits(k)) * span <= 65535
    assert p.grid_count(0) == (1, 1)


@given(w=sizes, h=sizes, m=tile_sizes, data=st.data())
@settings(max_examples=100, deadline=None)
def test_parent_child_consistency(w: int, h: int, m: int, data) -> None:
    p = TilePyramid(w, h, m)
    level = data.draw(st.integers(0, p.max_level))
    codes = list(p.tile_codes(level))
    code = data.draw(st.sampled_from(codes))
    for c in p.children(code):
        assert parent(c) == code and p.exists(c)
        r0, c0 = p.origin_rc(c)
        pr, pc = p.origin_rc(code)
        assert pr <= r0 < pr + p.span(level) and pc <= c0 < pc + p.span(level)
    if level > 0:
        assert p.exists(parent(code))
        assert ancestor(code, 0) == (0, 0, 0)
    # a tile with a child at level+1 has all children that the source reaches
    if level < p.max_level:
        assert len(p.children(code)) >= 1


def test_tile_sizes() -> None:
    assert [m for m in range(2, 300) if is_valid_tile_size(m)] == [3, 5, 9, 17, 33, 65, 129, 257]
    p = TilePyramid(1025, 1025, 65)
    assert p.max_level == 4 and p.padded_size == 1025
    assert TilePyramid(4097, 4097, 65).max_level == 6
    assert TilePyramid(1026, 1025, 65).max_level == 5
    assert np.array_equal(p.grid_count(4), (16, 16))
    assert p.neighbour((4, 0, 0), "L") is None and p.neighbour((4, 0, 0), "RD") == (4, 1, 1)
