"""Shared helpers of the runtime tests (no tests here): small stores, random leaf partitions, a store
wrapper with relocated boundary vertices, brute-force references for adjacency and normals."""

from __future__ import annotations

import atexit
import shutil
import tempfile
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

from terralod import Heightfield, build_store, open_store
from terralod.store import TileStore
from terralod.tiles import TileCode, TilePyramid, parent

from conftest import fractal_terrain

_DIR = Path(tempfile.mkdtemp(prefix="terralod-runtime-tests-"))
atexit.register(shutil.rmtree, _DIR, True)
_STORES: dict[tuple, Path] = {}

#: Metres between samples of the test terrains.
SPACING_M = 30.0
ORIGIN_M = (500000.0, 4100000.0)


def terrain_store(
    rows: int,
    cols: int,
    seed: int,
    tile_size: int,
    relief_m: float = 300.0,
    beta: float = 3.0,
    sea: float = 0.0,
) -> TileStore:
    """A chunked store of a spectral fBm terrain (cached per process; open a fresh handle per call).

    ``sea``: fraction of the columns (west) flattened to a sea at the terrain's minimum, so flat coarse tiles
    meet rough fine ones (large LoD differences under a camera, as on a coast).
    """
    key = (rows, cols, seed, tile_size, relief_m, beta, sea)
    p = _STORES.get(key)
    if p is None:
        z = fractal_terrain(rows, cols, seed, relief_m=relief_m, beta=beta)
        z[:, : int(sea * cols)] = 0.0
        hf = Heightfield.from_array(z, SPACING_M, origin_m=ORIGIN_M)
        p = _DIR / f"t_{rows}_{cols}_{seed}_{tile_size}_{int(relief_m)}_{beta}_{sea}.terra"
        build_store(hf, p, tile_size=tile_size, method="chunked", workers=2)
        _STORES[key] = p
    return open_store(p)


def spike_partition(
    pyr: TilePyramid, rng: np.random.Generator, spikes: int = 3, p_split: float = 0.3
) -> list[TileCode]:
    """A random leaf partition with large LoD differences: every ancestor of a few random finest tiles is
    split (a finest tile at the corner of a level-1 tile then borders a level-1 leaf: difference L - 1),
    plus random splits elsewhere."""
    split: set[TileCode] = set()
    top = pyr.max_level
    for _ in range(spikes):
        nx, ny = pyr.grid_count(top)
        a = parent((top, int(rng.integers(nx)), int(rng.integers(ny))))
        while a is not None:
            split.add(a)
            a = parent(a)
    leaves = []
    stack: list[TileCode] = [(0, 0, 0)]
    while stack:
        c = stack.pop()
        if c[0] < top and (c in split or (c[0] > 0 and rng.random() < p_split)):
            stack.extend(pyr.children(c))
        else:
            leaves.append(c)
    return leaves


def corner_spike(pyr: TilePyramid, corner_code: TileCode) -> list[TileCode]:
    """Partition where only the ancestors of one finest tile are split (deterministic large differences)."""
    split = set()
    a = parent(corner_code)
    while a is not None:
        split.add(a)
        a = parent(a)
    leaves, stack = [], [(0, 0, 0)]
    while stack:
        c = stack.pop()
        if c in split:
            stack.extend(pyr.children(c))
        else:
            leaves.append(c)
    return leaves


class SlidingStore:
    """Wraps a store: every boundary vertex that is not a tile corner slides along its edge by up to 0.45 of
    the level's stride (a pure function of level, line and position, so same-level neighbours agree), its
    height interpolated along the original edge — the fractional boundary vertices of cohesion-map tiles."""

    def __init__(self, store: TileStore) -> None:
        self.store = store
        self.pyramid = store.pyramid
        self.transform = store.transform

    def tile_summaries(self) -> list[dict[str, Any]]:
        return self.store.tile_summaries()

    def tile(self, level: int, x: int, y: int) -> Any:
        t = self.store.tile(level, x, y)
        pyr = self.pyramid
        r0, c0 = pyr.origin_rc((level, x, y))
        span, st = pyr.span(level), pyr.stride(level)
        rc = t.grid_rc.copy()
        v = t.vertices.copy()
        for axis, line in ((1, c0), (0, r0), (1, c0 + span), (0, r0 + span)):
            on = np.flatnonzero(rc[:, axis] == line)
            along = 1 - axis
            order = np.argsort(rc[on, along])
            on = on[order]
            tt = rc[on, along]
            if len(on) < 3:
                continue
            hh = v[on, 2]
            inner = tt % span != 0
            d = 0.45 * st * np.sin(12.9898 * tt + 78.233 * line + 3.1 * axis + level)
            tn = np.where(inner, tt + d, tt)
            rc[on, along] = tn
            v[on, 2] = np.interp(tn, tt, hh)
        tr = self.transform
        v[:, 0] = tr.c + 0.5 * tr.a + rc[:, 1] * tr.a
        v[:, 1] = tr.f + 0.5 * tr.e + rc[:, 0] * tr.e
        return SimpleNamespace(code=(level, x, y), vertices=v, triangles=t.triangles, grid_rc=rc)


def tile_rect(pyr: TilePyramid, code: TileCode) -> tuple[int, int, int, int]:
    """(r0, c0, r1, c1) of the tile square in source samples."""
    r0, c0 = pyr.origin_rc(code)
    s = pyr.span(code[0])
    return r0, c0, r0 + s, c0 + s


def data_rect(pyr: TilePyramid, code: TileCode) -> tuple[int, int, int, int]:
    """(r0, c0, r1, c1) of the part of the tile square its quads cover (partial tiles end past the data)."""
    r0, c0, r1, c1 = tile_rect(pyr, code)
    s = pyr.stride(code[0])
    return (
        r0,
        c0,
        min(r1, r0 + -(-(pyr.height - 1 - r0) // s) * s),
        min(c1, c0 + -(-(pyr.width - 1 - c0) // s) * s),
    )


def brute_neighbours(pyr: TilePyramid, leaves: list[TileCode], code: TileCode) -> tuple[list[set], list]:
    """Edge neighbours (sets) and corner neighbours of ``code`` among ``leaves`` by plain geometry (on the
    part of each tile square that its quads cover)."""
    r0, c0, r1, c1 = tile_rect(pyr, code)
    # corners of the tile square, just outside it
    pts = [(r0 - 0.5, c0 - 0.5), (r0 - 0.5, c1 + 0.5), (r1 + 0.5, c1 + 0.5), (r1 + 0.5, c0 - 0.5)]
    r0, c0, r1, c1 = data_rect(pyr, code)
    edges: list[set] = [set(), set(), set(), set()]
    corners: list = [None, None, None, None]
    for q in leaves:
        if q == code:
            continue
        a0, b0, a1, b1 = data_rect(pyr, q)
        rows_overlap = min(r1, a1) - max(r0, a0) > 0
        cols_overlap = min(c1, b1) - max(c0, b0) > 0
        if b1 == c0 and rows_overlap:
            edges[0].add(q)
        if a1 == r0 and cols_overlap:
            edges[1].add(q)
        if b0 == c1 and rows_overlap:
            edges[2].add(q)
        if a0 == r1 and cols_overlap:
            edges[3].add(q)
        for i, (pr, pc) in enumerate(pts):
            inside_data = pr < pyr.height - 1 and pc < pyr.width - 1  # past the data: no neighbour
            if inside_data and a0 < pr < a1 and b0 < pc < b1:
                corners[i] = q
    return edges, corners


def brute_boundary_normals(meshes: dict, pyr: TilePyramid, transform: Any) -> dict:
    """Reference normals of every tile's boundary vertices by the definition: normalised sum of
    cross(b - a, c - a) / 2 over every triangle of every tile whose xy footprint contains the vertex."""
    tris = np.concatenate([v[t.astype(np.int64)] for v, t, _ in meshes.values()])
    a, b, c = tris[:, 0], tris[:, 1], tris[:, 2]
    cross = 0.5 * np.cross(b - a, c - a)
    den = (b[:, 1] - c[:, 1]) * (a[:, 0] - c[:, 0]) + (c[:, 0] - b[:, 0]) * (a[:, 1] - c[:, 1])
    x0, y0 = transform.c + 0.5 * transform.a, transform.f + 0.5 * transform.e
    out = {}
    for code, (v, _, _) in meshes.items():
        r0, c0, r1, c1 = tile_rect(pyr, code)
        rows = (v[:, 1] - y0) / transform.e
        cols = (v[:, 0] - x0) / transform.a
        bnd = np.flatnonzero(
            (np.abs(rows - r0) < 1e-6)
            | (np.abs(rows - r1) < 1e-6)
            | (np.abs(cols - c0) < 1e-6)
            | (np.abs(cols - c1) < 1e-6)
        )
        p = v[bnd, :2]
        px = p[:, 0:1]
        py = p[:, 1:2]
        l1 = ((b[:, 1] - c[:, 1]) * (px - c[:, 0]) + (c[:, 0] - b[:, 0]) * (py - c[:, 1])) / den
        l2 = ((c[:, 1] - a[:, 1]) * (px - c[:, 0]) + (a[:, 0] - c[:, 0]) * (py - c[:, 1])) / den
        inside = (l1 >= -1e-9) & (l2 >= -1e-9) & (1 - l1 - l2 >= -1e-9)
        s = inside.astype(np.float64) @ cross
        out[code] = (bnd, s / np.linalg.norm(s, axis=1, keepdims=True))
    return out


def random_camera(rng: np.random.Generator, store: TileStore, **kw: Any):
    """A camera above the terrain looking at a random point of it (may look partly off the terrain)."""
    from terralod.runtime import Camera

    pyr, t = store.pyramid, store.transform
    w, h = pyr.width * t.a, pyr.height * -t.e
    zmax = max(r["z_max_m"] for r in store.tile_summaries())
    eye = (t.c + w * rng.uniform(-0.2, 1.2), t.f - h * rng.uniform(-0.2, 1.2), zmax + rng.uniform(20, 2000))
    tgt = (t.c + w * rng.uniform(0, 1), t.f - h * rng.uniform(0, 1), rng.uniform(0, zmax))
    return Camera(eye, tgt, fov_y_deg=float(rng.uniform(30, 90)), width_px=int(rng.integers(200, 1200)),
                  height_px=int(rng.integers(150, 900)), **kw)  # fmt: skip
