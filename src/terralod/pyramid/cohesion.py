"""Vertex cohesion map tiles: Sung, Lee & Shin (2021) (``../shared/papers/000_0f8c6950ace8a2d1.txt``), §3.1 and §3.2.

Each tile starts as the Chunked-LOD regular M x M grid of its level (:mod:`terralod.pyramid.chunked`) and its
vertices are relocated toward the places the grid misrepresents, the "vertex cohesion map" of the paper,
then re-triangulated (per quad, the diagonal of smaller max error, as in the baseline) and measured.

Roughness (eq. 1). The paper's first observation: a plain Laplacian is a 3 x 3 second difference, so it
sees only the sample-scale curvature. A small bump (figure 2a) has a sharp kink (a small angle theta_a)
and scores higher than a mountain (figure 2b) whose slope changes gently per sample but over many samples,
although the mountain leaves the larger error delta between grid vertices s samples apart. Smoothing with
a Gaussian first (the Laplacian of Gaussian, ``scipy.ndimage.gaussian_laplace``) measures the curvature at
the scale of the level: we take sigma = s / 2 samples for stride s, so a bump narrower than the grid
spacing is averaged away and a bend the grid cannot follow scores high. The roughness map is scale
normalised (|LoG| * sigma^2) so its units are metres at every level.

Relocation (eq. 2-9), per level and tile, with the reading of ``READING-NOTES.md``:

- attraction A (the paper's sum of A_n, not specified there): each vertex P is pulled toward the weighted
  centroid of the source samples in the 4 quads around it. Weights: the squared vertical error of the
  *current* mesh at each sample (``attraction="error"``, default) — vertices gather where the surface the
  grid makes departs most from the data, which is what the measured (Hausdorff) error rewards — or the
  LoG roughness above (``attraction="log"``, the paper as written);
- elasticity (eq. 2-5): a Hooke pull K * (T - P) toward the centroid T of the quad of P's 4 edge
  neighbours, by the shoelace formula (eq. 3-4 are mis-typeset in the paper); the area S is the shoelace
  area (the paper's Heron's formula gives the same for a triangle, and is not needed);
- adaptive K (eq. 6-8) from a = (area of the regular quad) / (area of the relocated quad), per-level
  thresholds tau_low = 1 / s, tau_up = s (the paper's 1/4-size map: 1/2..2, 1/64: 1/8..8);
- V = K (T - P) + alpha * A, iterated (Gauss-Seidel, raster order) a fixed number of times or until no
  vertex moves (eq. 9's balance);
- then our improvement, error-driven refinement (``refine=True``, :func:`refine_max_error`): the quad of
  largest error moves one of its corners onto its worst sample (or half-way) when that lowers the largest
  error of the quads around that corner (or onto a sample next to the worst one when the worst cannot
  be reached); repeated worst-first until no quad improves. The per-sample error it minimises is the
  distance to the triangle's plane (``metric="normal"``, the measured Hausdorff error's proxy on steep
  slopes); ``"vertical"`` and ``"both"`` (relocate with each, keep the better tile) are options. Two
  additions keep it cheap and less greedy: ``focus=0.8`` stops once every quad it could still improve is
  below 0.8 x the error of a quad that cannot (those no longer decide the tile's max error; with the pair
  moves below, 0.8 costs half of 0.5 for the same triangles on Puget Sound and Grand Canyon, 1.0 draws
  3-5 % more), and ``escape=4`` lets a stuck worst quad search a lattice of up to 9 x 9
  sample points over each corner's star (5 x 5 on coarse levels, deviation 6) (the tile before that search stays a fallback candidate: the
  per-sample proxy can be fooled at sharp rims, Grand Canyon level 3 otherwise measured 0.89 x Chunked
  LOD); when the tile's worst quad (only that one) is still stuck, ``pairs=4`` moves two of its corners
  together over a lattice of each one's star, or else a corner with one of its neighbours outside the
  quad, which makes room for the corner (a single-vertex optimum is not a pair optimum, and the max error
  of a tile is one quad's). The benchmark (``benchmarks/cohesion_vs_chunked.py``, results in
  ``benchmarks/results/cohesion_vs_chunked.md``) shows why: the force balance as the paper writes it
  (LoG attraction, no refinement) leaves the max error per level at 0.63-1.0 x the regular grid's and
  draws 0.96-1.0 x its triangles at 2 px; with the refinement the max error is 0.15-0.64 x and the
  triangles 0.40-0.49 x on the real DEMs (0.75 x on the small Jacksboro sample: with 4 levels the path
  draws mostly the finest level, the full-resolution grid of both methods; the selection reaches 0.50 x
  only at 6 px, i.e. it would take every error 3 x smaller).

Deviations, and why:

1. Eq. 8 is printed as k = a / tau_up, which jumps from 0 to 1 / tau_up at a = 1; we use
   (a - 1) / (tau_up - 1), continuous and symmetric to eq. 7.
2. No fold-over: every move is checked against the 4 quads around the vertex, each of which must keep a
   valid diagonal (both its triangles counter-clockwise with positive area); quads may become non-convex
   (then only the diagonal through the reflex corner is used), which lets a corner reach the middle of its
   quad — at stride 2 that is the only sample a vertex can add. A failing move is halved twice, then
   dropped; a force step is capped at s / 2 per axis. (The paper warns of "overlapping or twisting" for
   small K but gives no guard.)
3. Tile sides: corners are fixed and side vertices slide only along their side, by a 1-D version of the
   same forces computed from the samples of that side's line alone (:func:`relax_edge`), so the two tiles
   sharing a side compute bit-identical vertices and same-level tiles never crack; across levels the
   runtime stitcher fits relocated boundaries (fractional or not) to the coarser polyline.
4. Heights come from the source. By default positions are snapped to the sample lattice (``snap=True``):
   every vertex is a source sample, its height exact, and positions quantise without loss. With
   ``snap=False`` positions are continuous and heights bilinear.
5. Parent fallback (§3.2). The builder stores ``error_m = max(measured, children's error_m)`` (monotone),
   and the runtime's selection draws a parent whose own measured error meets the threshold where its
   children are no better (:mod:`terralod.runtime.select`). Because the builder runs finest level first,
   the per-area fallback is done per tile at build time, the documented equivalent: a tile keeps the
   relocated mesh only when its measured Hausdorff error is smaller than that of the unrelocated mesh
   (the regular grid with the same, shared, side vertices; with ``slide_boundary=False`` exactly the
   Chunked-LOD tile), so relocation never makes a tile worse than its grid. With sliding sides (the
   default) the grid it falls back to has the slid sides, so a tile can in principle measure worse than
   the Chunked-LOD tile (the sides are fixed by their line's samples alone, before the 2-D fit); the
   benchmark counts such tiles.
6. The paper relocates on the GPU in 0.34 s for 64^2 x 8 levels; this is a CPU numba kernel per tile. To
   bound its cost, a level of stride s > 4 (``work_stride``) is relaxed and refined first on every
   (s / 4)-th sample (the cost of a stride-4 tile), then refined again on the full source with focus 1 (only
   the tile's max error is pursued, which fixes what the coarse pass could not see between its samples);
   both passes keep every vertex on a source sample. On those levels the star search on the full source
   uses a 5 x 5 lattice (``coarse_escape=2``) instead of 9 x 9: it was the costliest step of a root tile
   (1024^2 samples and more), and the camera path at 2 px draws those levels little (same triangle ratios
   on the five DEMs of the benchmark; the coarse levels' max error ratio moves by at most 0.05, e.g.
   Pyrenees level 0 0.58 -> 0.63 x Chunked LOD). Everything else that saves time gives the same tiles
   bit for bit: per-quad errors are measured once per pass over the full source and kept up to date by the
   refinement (the mesh reuses its diagonals), the relaxation re-measures only the quads around vertices
   that moved, a candidate is rejected as soon as a row of samples reaches the error to beat, the pair
   search measures the quads that depend on one vertex once per position of it, and the unrelocated grid
   (the fallback of deviation 5) is built and measured only when a lower bound of its Hausdorff error
   (:func:`terralod.kernels.cohesion_measure.grid_error_bound`) does not already exceed the relocated tile's
   largest vertical error; the candidates are measured in a series
   (:func:`terralod.error.measure_error_window_series`: the second re-rasterises only the rows where it
   differs from the first, exact and bit-identical to measuring each alone). Measured per level and core in ``benchmarks/results/cohesion_vs_chunked.md``.

Partial tiles at the data edge: only vertices whose 4 quads lie entirely inside the data move (the rest
keep their grid position), so the dropped padding quads are the baseline's.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from terralod.error import ErrorReport, measure_error_window, measure_error_window_series
from terralod.kernels.cohesion import (
    refine_edge_max_error,
    refine_max_error,
    relax_edge,
    relax_interior,
)
from terralod.kernels.cohesion_measure import (
    WEIGHT_ERROR,
    WEIGHT_FEATURE,
    assemble,
    assemble_diagonals,
    grid_error_bound,
    measure_quads,
)
from terralod.pyramid import chunked
from terralod.tiles import TileCode, TilePyramid

__all__ = ["CohesionOptions", "make_mesher", "mesh_tile", "roughness_log"]


@dataclass(frozen=True)
class CohesionOptions:
    """Settings of the cohesion mesher (keyword-only in :func:`make_mesher`).

    Attributes
    ----------
    attraction : "error" (squared vertical error of the current mesh) or "log" (LoG roughness, the paper)
    iterations : relocation sweeps per tile (fewer when nothing moves)
    alpha : gain of the attraction term
    snap : positions on the sample lattice (exact heights) instead of continuous (bilinear heights)
    slide_boundary : side vertices slide along their side (1-D, shared); False keeps them on the grid
    fallback : keep the unrelocated mesh where relocation measures worse (per tile)
    refine : after the force relaxation, error-driven moves of vertices onto their quads' worst samples
    refine_budget : tries of that refinement per vertex (budget = refine_budget * M^2)
    metric : error the relocation minimises per sample: "vertical" |dz|, "normal", the distance to the
        triangle's plane |dz| / sqrt(1 + |grad|^2) (closer to the measured Hausdorff on steep slopes, but
        blind to the triangle's end at sharp rims), or "both": relocate with each, keep the tile of smaller
        measured Hausdorff error (twice the cost)
    escape : when no short move lowers the worst quad, search a lattice of up to (2 escape + 1)^2 sample
        points over each of its corners' stars (0: off); the tile before that search stays a fallback
        candidate, since the per-sample proxy can be fooled at sharp rims
    pairs : when the tile's worst quad is still stuck after the star search, move two vertices together
        over a lattice of up to (2 pairs + 1)^2 points each: two of its corners (4 sides, 2 diagonals), else
        a corner and one of its 5 neighbours outside the quad (0: off; levels refined coarse to fine skip it)
    focus : the refinement stops once every quad it could still improve is below focus x the largest
        error of a quad that cannot improve (0: run the whole budget; 1: pursue the tile's max error only)
    work_stride : levels of stride s > work_stride are relaxed and refined first on every
        (s / work_stride)-th sample, then refined on the full source with focus 1 (coarse to fine; 0: off;
        ``snap`` only)
    coarse_escape : the star search of those levels (on the full source) uses at most this lattice
        half-size, min(escape, coarse_escape): (2 coarse_escape + 1)^2 points (2: 25 instead of 81; it is
        the costliest step of a coarse tile, and the path at 2 px draws those levels little)
    """

    attraction: str = "error"
    iterations: int = 8
    alpha: float = 0.5
    snap: bool = True
    slide_boundary: bool = True
    fallback: bool = True
    refine: bool = True
    refine_budget: int = 2
    metric: str = "normal"
    escape: int = 4
    focus: float = 0.8
    work_stride: int = 4
    pairs: int = 4
    coarse_escape: int = 2

    def __post_init__(self) -> None:
        if self.attraction not in ("error", "log"):
            raise ValueError(f"Expected attraction 'error' or 'log', got {self.attraction!r}")
        if self.metric not in ("vertical", "normal", "both"):
            raise ValueError(f"Expected metric 'vertical', 'normal' or 'both', got {self.metric!r}")
        if self.iterations < 0:
            raise ValueError(f"Expected iterations >= 0, got {self.iterations}")
        if self.escape < 0:
            raise ValueError(f"Expected escape >= 0, got {self.escape}")
        if self.pairs < 0:
            raise ValueError(f"Expected pairs >= 0, got {self.pairs}")
        if self.coarse_escape < 0:
            raise ValueError(f"Expected coarse_escape >= 0, got {self.coarse_escape}")
        if not 0.0 <= self.focus <= 1.0:
            raise ValueError(f"Expected focus in [0, 1], got {self.focus}")
        if self.work_stride < 0 or (self.work_stride & (self.work_stride - 1)):
            raise ValueError(f"Expected work_stride 0 or a power of 2, got {self.work_stride}")


#: Roughness below this (metres, scale-normalised LoG) is flat: the paper's "specific threshold" above which
#: terrain counts as curved. It also keeps rounding noise on planes from attracting vertices.
ROUGHNESS_THRESHOLD_M = 1e-3


def roughness_log(z: np.ndarray, stride: int, *, threshold_m: float = ROUGHNESS_THRESHOLD_M) -> np.ndarray:
    """Scale-normalised LoG roughness max(|LoG_sigma(z)| * sigma^2 - threshold_m, 0) (metres), sigma =
    stride / 2 samples (``scipy.ndimage.gaussian_laplace``; 1-D lines and 2-D windows alike).

    The array is first extended by odd reflection (linear continuation) so a plane stays flat up to its
    edges, where "nearest" or "reflect" padding would put a false crease.
    """
    sigma = max(0.5 * stride, 0.5)
    a = np.asarray(z, np.float64)
    pad = int(np.ceil(4.0 * sigma))
    ext = np.pad(a, pad, mode="reflect", reflect_type="odd") if min(a.shape) > 1 else a
    lap = ndimage.gaussian_laplace(ext, sigma, mode="nearest")
    if ext is not a:
        lap = lap[tuple(slice(pad, pad + n) for n in a.shape)]
    return np.maximum(np.abs(lap) * sigma**2 - threshold_m, 0.0)


def _window(
    z: np.ndarray, valid: np.ndarray, r0: int, c0: int, n: int, step: int = 1
) -> tuple[np.ndarray, np.ndarray]:
    """Source window of up to (n, n) samples from (r0, c0), every ``step``-th, cut at the data's edge: a
    last row (column) of the data that falls between two steps is added, marked invalid, so that the kernels,
    which read past the window's end as edge-replicated, see the data's last sample there."""
    h, w = z.shape
    rows = np.arange(r0, min(r0 + step * (n - 1), h - 1) + 1, step)
    cols = np.arange(c0, min(c0 + step * (n - 1), w - 1) + 1, step)
    rows_ok = np.ones(len(rows), np.bool_)
    cols_ok = np.ones(len(cols), np.bool_)
    if len(rows) < n and rows[-1] < h - 1:
        rows, rows_ok = np.append(rows, h - 1), np.append(rows_ok, False)
    if len(cols) < n and cols[-1] < w - 1:
        cols, cols_ok = np.append(cols, w - 1), np.append(cols_ok, False)
    if step == 1:
        win = (slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1))
        return np.ascontiguousarray(z[win], dtype=np.float64), np.ascontiguousarray(valid[win])
    zw = np.ascontiguousarray(z[np.ix_(rows, cols)], dtype=np.float64)
    vw = valid[np.ix_(rows, cols)] & rows_ok[:, None] & cols_ok[None, :]
    return zw, np.ascontiguousarray(vw)


def _window_roughness(z: np.ndarray, r0: int, c0: int, span: int, s: int) -> np.ndarray:
    """LoG roughness over the tile window, computed on the data around it (a margin of 4 sigma where the
    data has it); window samples past the data copy the nearest value (they are never measured)."""
    h, w = z.shape
    pad = int(np.ceil(2.0 * s))
    ra, rb = max(r0 - pad, 0), min(r0 + span + pad, h - 1)
    ca, cb = max(c0 - pad, 0), min(c0 + span + pad, w - 1)
    rough = roughness_log(z[ra : rb + 1, ca : cb + 1], s)
    rr = np.minimum(np.arange(r0, r0 + span + 1), h - 1) - ra
    cc = np.minimum(np.arange(c0, c0 + span + 1), w - 1) - ca
    return np.ascontiguousarray(rough[np.ix_(rr, cc)])


def _line(z: np.ndarray, valid: np.ndarray, fixed: int, start: int, n: int, horizontal: bool, step: int = 1):
    """Samples of one tile side: row ``fixed`` (horizontal) or column ``fixed``, n samples from ``start``,
    every ``step``-th. Returns (heights, ok, limit: the last index on the data) or None when the line lies
    past the data."""
    h, w = z.shape
    along = w if horizontal else h
    if fixed > (h if horizontal else w) - 1:
        return None
    idx = start + step * np.arange(n)
    cl = np.minimum(idx, along - 1)
    if horizontal:
        lz, lv = z[fixed, cl], valid[fixed, cl]
    else:
        lz, lv = z[cl, fixed], valid[cl, fixed]
    ok = lv & (idx <= along - 1)
    return (
        np.ascontiguousarray(lz, np.float64),
        np.ascontiguousarray(ok),
        min((along - 1 - start) // step, n - 1),
    )


def _relocate_sides(z, valid, r0, c0, s, m, opt: CohesionOptions, pv, pu, step: int = 1) -> None:
    """1-D relocation of the four sides (in place on the grid positions pv, pu, in units of ``step``
    samples; s is the level's stride in samples)."""
    span = (m - 1) * s
    sd = s // step
    mode = WEIGHT_FEATURE if opt.attraction == "log" else WEIGHT_ERROR
    tau_low, tau_up = 1.0 / s, float(s)
    # (side fixed coordinate, along-start, horizontal, grid row/col index of the side)
    for fixed, start, horizontal, k in ((r0, c0, True, 0), (r0 + span, c0, True, m - 1),
                                        (c0, r0, False, 0), (c0 + span, r0, False, m - 1)):  # fmt: skip
        ln = _line(z, valid, fixed, start, span // step + 1, horizontal, step)
        if ln is None:
            continue
        lz, ok, limit = ln
        feat = np.zeros(lz.shape[0] if mode == WEIGHT_FEATURE else 1)
        if mode == WEIGHT_FEATURE and limit >= 1:
            feat[: limit + 1] = roughness_log(lz[: limit + 1], sd)  # the line's data only, no padding
        t = relax_edge(lz, ok, feat, mode, sd, m, limit, opt.snap, opt.iterations, opt.alpha, tau_low, tau_up)
        if opt.refine:
            refine_edge_max_error(lz, ok, t, sd, limit, opt.snap, 4 * m)
        if horizontal:
            pu[k, :] = t
        else:
            pv[:, k] = t


def mesh_tile_with(
    z: np.ndarray,
    valid: np.ndarray,
    pyramid: TilePyramid,
    code: TileCode,
    opt: CohesionOptions,
    spacing_m: tuple[float, float] = (1.0, 1.0),
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Cohesion-map mesh of tile ``code`` with settings ``opt`` (see :func:`mesh_tile`); ``spacing_m``
    (dx, dy) is only used by the fallback's Hausdorff comparison."""
    level = code[0]
    s = pyramid.stride(level)
    m = pyramid.tile_size
    if s == 1:  # every sample is a vertex: the regular grid is exact
        return chunked.mesh_tile(z, valid, pyramid, code)
    h, w = z.shape
    r0, c0 = pyramid.origin_rc(code)
    span = pyramid.span(level)
    # coarse to fine: a level of stride s > work_stride is relaxed and refined first on every f-th sample
    # (stride work_stride there, so it costs about what a tile of that stride costs), then refined again on
    # the full source from there, where only the quads whose error the coarse pass could not see still move
    f = max(1, s // opt.work_stride) if (opt.work_stride and opt.snap) else 1
    sd = s // f
    zf, vf = _window(z, valid, r0, c0, span + 1)
    zw, vw = _window(z, valid, r0, c0, span // f + 1, f) if f > 1 else (zf, vf)
    gi = np.arange(m, dtype=np.float64) * sd
    pv = np.ascontiguousarray(np.repeat(gi[:, None], m, axis=1))
    pu = np.ascontiguousarray(np.repeat(gi[None, :], m, axis=0))
    cells = m - 1
    keep = np.ascontiguousarray(
        ((r0 + np.arange(cells) * s) < h - 1)[:, None] & ((c0 + np.arange(cells) * s) < w - 1)[None, :]
    )
    if opt.slide_boundary:
        _relocate_sides(z, valid, r0, c0, s, m, opt, pv, pu, f)
    base_v, base_u = pv.copy(), pu.copy()
    inside_r = (r0 + (np.arange(m) + 1) * s) <= h - 1
    inside_c = (c0 + (np.arange(m) + 1) * s) <= w - 1
    movable = np.zeros((m, m), np.bool_)
    movable[1:-1, 1:-1] = (inside_r[:, None] & inside_c[None, :])[1:-1, 1:-1]
    if opt.attraction == "log":
        feat_f = _window_roughness(z, r0, c0, span, s)
        feat = np.ascontiguousarray(feat_f[::f, ::f])
        mode = WEIGHT_FEATURE
    else:
        feat = feat_f = np.zeros((1, 1))
        mode = WEIGHT_ERROR
    vmax = float(min(span, h - 1 - r0) // f)
    umax = float(min(span, w - 1 - c0) // f)
    normal = np.array([1.0 / spacing_m[0], 1.0 / spacing_m[1]])
    metrics = {"vertical": [np.zeros(2)], "normal": [normal], "both": [np.zeros(2), normal]}[opt.metric]
    budget = opt.refine_budget * m * m
    pairs = opt.pairs if f == 1 else 0  # joint moves on the full source of a coarse level cost too much
    escape = opt.escape if f == 1 else min(opt.escape, opt.coarse_escape)  # likewise a fine star lattice

    def mesh(pv, pu, sxy):  # the tile on the full source
        return assemble(zf, vf, feat_f, pv, pu, keep, r0, c0, opt.snap, sxy)[:4]

    # candidates: the unrelocated grid (same side vertices, diagonals by vertical error; without sliding
    # exactly the Chunked-LOD tile), then one relocation per metric; the fallback keeps the first of smallest
    # measured Hausdorff error. The grid is only built and measured when a relocated tile might not beat it:
    # its Hausdorff error is at least v / sqrt(1 + L^2), v a lower bound of its largest vertical error (from
    # the work window) and L its steepest slope (a sample dz off a surface z = f(x, y) with |grad f| <= L is
    # at least |dz| / sqrt(1 + L^2) from it), and a tile's Hausdorff error is at most its vertical error.
    grid_bound_m = 0.0
    if opt.slide_boundary and opt.fallback:
        scale = np.array([1.0 / (f * spacing_m[0]), 1.0 / (f * spacing_m[1])])
        side_m = s * min(spacing_m)
        # the measure reads float32 elevations: other inputs get the slack of that rounding
        slack_m = 0.0 if z.dtype == np.float32 else float(np.abs(zw).max(initial=0.0)) * 2.0**-23
        grid_bound_m = (
            grid_error_bound(zw, vw, base_v, base_u, keep, scale, side_m) * (1.0 - 1e-9) - 1e-9 - slack_m
        )

    def grid_mesh():
        if not opt.slide_boundary:
            return chunked.mesh_tile(z, valid, pyramid, code)
        gv, gu = base_v * f, base_u * f
        grid = _quad_state(m)
        measure_quads(zf, vf, gv, gu, keep, opt.snap, np.zeros(2), *grid)
        return assemble_diagonals(zf, gv, gu, keep, grid[3], r0, c0, opt.snap)

    cands = []
    for sxy in metrics:
        pv, pu = base_v.copy(), base_u.copy()
        relax_interior(zw, vw, feat, mode, pv, pu, movable, keep, sd, opt.snap, opt.iterations, opt.alpha,
                       1.0 / s, float(s), sxy / f, vmax, umax)  # fmt: skip
        if not opt.refine:
            cands.append(mesh(pv * f, pu * f, sxy))
            continue
        if f > 1:
            state = _quad_state(m)
            measure_quads(zw, vw, pv, pu, keep, opt.snap, sxy / f, *state)
            refine_max_error(
                zw, vw, pv, pu, movable, keep, sd, opt.snap, budget, sxy / f, 0, opt.focus, 0, *state
            )
        pv *= f
        pu *= f
        # per-quad errors and diagonals, measured once on the full source and kept up to date by the refinement
        state = _quad_state(m)
        measure_quads(zf, vf, pv, pu, keep, opt.snap, sxy, *state)
        # after a coarse pass only the tile's max error is pursued (focus 1) on the full source
        focus = opt.focus if f == 1 else 1.0
        refine_max_error(zf, vf, pv, pu, movable, keep, s, opt.snap, budget, sxy, 0, focus, 0, *state)
        cands.append(assemble_diagonals(zf, pv, pu, keep, state[3], r0, c0, opt.snap))
        # the star search can fool the per-sample proxy: the tile before it stays a candidate
        if escape and refine_max_error(
            zf, vf, pv, pu, movable, keep, s, opt.snap, budget, sxy, escape, focus, pairs, *state
        ):
            cands.append(assemble_diagonals(zf, pv, pu, keep, state[3], r0, c0, opt.snap))
    if not opt.fallback:
        return cands[-1]
    reports = _measure_series(cands, z, valid, r0, c0, span, spacing_m)
    errs = [r.hausdorff_m for r in reports]
    if min(r.max_vertical_m for r in reports) < grid_bound_m:  # the grid cannot win
        return cands[int(np.argmin(errs))]
    cands.insert(0, grid_mesh())
    errs.insert(0, _measure(cands[0], z, valid, r0, c0, span, spacing_m).hausdorff_m)
    return cands[int(np.argmin(errs))]


def _quad_state(m: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per-quad (max error, worst row, worst col, diagonal) arrays of :func:`measure_quads`."""
    cells = m - 1
    return (np.full((cells, cells), -1.0), np.zeros((cells, cells)), np.zeros((cells, cells)),
            np.zeros((cells, cells), np.int8))  # fmt: skip


def _measure(mesh, z, valid, r0: int, c0: int, span: int, spacing_m: tuple[float, float]) -> ErrorReport:
    """Measured error (one-sided Hausdorff and vertical, metres) of a tile mesh, in the builder's window
    frame."""
    rows, cols, hz, tris = mesh
    h, w = z.shape
    dx, dy = spacing_m
    r1 = min(r0 + span, h - 1)
    c1 = min(c0 + span, w - 1)
    local = np.stack([(cols - c0) * dx, (rows - r0) * dy, hz], axis=1)
    win = (slice(r0, r1 + 1), slice(c0, c1 + 1))
    return measure_error_window(local, tris, z[win], valid[win], dx, dy)


def _measure_series(meshes, z, valid, r0: int, c0: int, span: int, spacing_m) -> list[ErrorReport]:
    """:func:`_measure` of each mesh, bit for bit; a candidate after the first re-rasterises only the rows
    where it differs from the one before (:func:`terralod.error.measure_error_window_series`)."""
    h, w = z.shape
    dx, dy = spacing_m
    r1 = min(r0 + span, h - 1)
    c1 = min(c0 + span, w - 1)
    local = [
        (np.stack([(cols - c0) * dx, (rows - r0) * dy, hz], axis=1), tris) for rows, cols, hz, tris in meshes
    ]
    win = (slice(r0, r1 + 1), slice(c0, c1 + 1))
    return measure_error_window_series(local, z[win], valid[win], dx, dy)


def make_mesher(**options):
    """A tile mesher (for :func:`terralod.pyramid.builder.register_method`) with :class:`CohesionOptions`."""
    opt = CohesionOptions(**options)

    def mesher(z: np.ndarray, valid: np.ndarray, pyramid: TilePyramid, code: TileCode, *,
               spacing_m: tuple[float, float] = (1.0, 1.0)):  # fmt: skip
        return mesh_tile_with(z, valid, pyramid, code, opt, spacing_m)

    mesher.options = opt  # type: ignore[attr-defined]
    mesher.needs_spacing = True  # type: ignore[attr-defined]
    return mesher


_DEFAULT = CohesionOptions()


def mesh_tile(
    z: np.ndarray,
    valid: np.ndarray,
    pyramid: TilePyramid,
    code: TileCode,
    *,
    spacing_m: tuple[float, float] = (1.0, 1.0),
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Vertex-cohesion-map mesh of tile ``code`` with the default :class:`CohesionOptions`; ``spacing_m``
    (dx, dy metres) makes the fallback compare true 3-D Hausdorff errors (the builder passes it).

    Returns
    -------
    rows, cols : (N,) float64 source sample coordinates (row south, col east) of the vertices
    heights_m : (N,) float64 elevation, metres
    triangles : (K, 3) int32, counter-clockwise seen from above
    """
    return mesh_tile_with(z, valid, pyramid, code, _DEFAULT, spacing_m)


mesh_tile.needs_spacing = True  # type: ignore[attr-defined]
