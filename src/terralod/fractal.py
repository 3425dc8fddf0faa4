"""Fractal detail beyond the DEM's resolution: seamless, deterministic fBm by square midpoint displacement.

Implements ``../shared/papers/001_aded52eb792094ea.txt`` (Hu & Wang, "Generation of realistic terrain
based on LOD simplification and fractal"):

- §2: fractional Brownian motion with Hurst exponent H and variance, realised by random midpoint
  displacement on squares (the "square recursive-subdivision law": diamond step, then square step). The
  DEM samples are the coarsest lattice and are kept exactly; each iteration halves the spacing and
  displaces the new points by a Gaussian with the *conditional* fBm variance for that scale, so the
  surface follows ``D(h) = E[(z(p) - z(q))^2] = sigma^2 h^2H`` (h = |p - q| in DEM samples). For a new
  point p predicted by weights w_i of parents x_i (sum 1) that variance is

      Var(z_p - sum_i w_i z_i) = sum_i w_i D(|p - x_i|) - 1/2 sum_ij w_i w_j D(|x_i - x_j|)
                               = sigma^2 s^2H kappa2(H)            (parent spacing s)

  so iteration k displaces by ``sigma_k = sigma 2^(-(k-1) H) sqrt(kappa2(H))`` at square centres and by
  ``2^(-H/2)`` of that at edge midpoints (the square step's parent lattice is the diamond's, rotated 45°
  and scaled by 1/sqrt(2)). With the classic mean of the 4 nearest parents, kappa2 = 2^-H - 1/4 - 2^H / 8
  (0 at H = 1, as a smooth field needs no displacement).
- §3 step 2: H and the variance are "determined" per patch. The paper does not say how; here they are
  estimated from the DEM itself (:func:`estimate_fbm`) — a variogram fit over its finest scales (lags 1..8
  samples along rows and columns, ``log D(h) = log sigma^2 + 2H log h``) per 64 x 64 block, smoothed over
  3 x 3 blocks, H clipped to [0.05, 0.95] — unless given. Both are then *functions of position*
  (bilinear between block centres), never per window.
- §3.1: the visible region (frustum ∩ the terrain's mean horizontal plane) and a patch test against it:
  :func:`visible_region`, :func:`boxes_in_region`, plus the conservative 3-D :func:`boxes_in_frustum`.
- §3.2: back-face patch culling (:func:`patch_backfacing`: a patch whose every triangle faces away from
  the eye is skipped) and the "join the two lowest vertices" diagonal rule, offered beside the diagonal of
  smaller error against the next fractal level (``diagonal="lowest" | "error" | "fixed"``).

Deviations, and why:

- **Predictor: 4 x 4 kriging stencil instead of the mean of 4.** The classic mean of the 4 nearest
  parents is bilinear: it ignores the curvature that the surrounding lattice reveals, so the detail is
  rougher than fBm at its finest lags and its variogram slope falls short of 2H (flat DEM, 10 levels,
  lags 1..8: 1.40 instead of 1.6 at H = 0.8, 0.88 instead of 1.0 at H = 0.5). Each new point is instead
  the ordinary-kriging predictor of fBm from the 4 x 4 parents around it (16 weights, 3 by symmetry,
  tabulated over H by :func:`stencil_table`) displaced with that predictor's error variance: the slopes
  become 1.55 and 0.99, and refining a true fBm DEM x16 continues its variogram to within 3 % at every
  generated lag (the mean of 4: off by up to 27 %; ``benchmarks/results/fractal.md``). The classic rule
  stays available (``stencil="classic"``). Where the stencil would leave the DEM (within 1.5 parent
  spacings of its edge) the mean of the nearest 4 parents (3 on the edge) is used.
- **Cracks (§3.3).** The paper admits cracks between patches generated separately. Here every
  displacement is a pure function of (world lattice position at its iteration level, level, seed) through
  a splitmix64 hash and Box–Muller, never of call order, so any window, tile or strip reproduces the same
  values bit for bit and neighbours agree on shared edges at every iteration count. Different iteration
  counts between neighbours are an ordinary LoD difference for the runtime's stitcher (Li, Liu & Liu).
- **Eq. 3 is missing** from the paper (the distance threshold from the error ε). The number of fractal
  levels is chosen by the same screen-space error rule as everything else (DESIGN.md):
  :meth:`FractalDetail.extra_levels_for` adds levels while the projected detail error exceeds the
  threshold; each :class:`FractalTile` also carries its measured error against the next level.
- **Back-face test.** The paper dots the normal with the reversed *view direction* (exact only for an
  orthographic view); here with the vector from the triangle to the *eye* (exact for perspective).
- **The two-lowest-vertices rule** is undefined when the two lowest vertices share an edge; it is read as
  "the diagonal whose end points are lower in sum", which is the paper's rule whenever it applies.
- **Extent.** The amplified grid spans the DEM's sample centres: ``(H - 1) f + 1`` rows, so input sample
  (r, c) is output sample (r f, c f) at the same world position (see :meth:`FractalDetail.amplified_transform`).
- **Anisotropy.** Lags are counted in samples, so the model is isotropic in metres only when dx == dy
  (the readers give square pixels for reprojected inputs).
"""

from __future__ import annotations

import functools
import logging
import math
import os
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from affine import Affine

from terralod.errors import InputError
from terralod.heightfield import Heightfield
from terralod.kernels import noise
from terralod.tiles import TileCode, TilePyramid, is_valid_tile_size

log = logging.getLogger(__name__)

__all__ = [
    "DIAGONAL_RULES",
    "FractalDetail",
    "FractalTile",
    "amplify_command",
    "boxes_in_frustum",
    "boxes_in_region",
    "choose_diagonals",
    "estimate_fbm",
    "fractal_tile",
    "patch_backfacing",
    "patches_backfacing",
    "stencil_table",
    "visible_region",
]

#: Quad diagonal rules of fractal tiles.
DIAGONAL_RULES = {
    "lowest": "Hu & Wang §3.2: join the two lowest vertices (the diagonal of smaller height sum)",
    "error": "the diagonal of smaller max vertical error against the next fractal level",
    "fixed": "always north-west to south-east",
}
#: Clip range of estimated Hurst exponents.
HURST_RANGE = (0.05, 0.95)
#: Deepest refinement: factor 2^16.
MAX_LEVELS = 16
#: Largest grid :meth:`FractalDetail.amplify` builds in memory (float32 output, float64 work arrays).
MAX_IN_MEMORY_SAMPLES = 1 << 29
#: Largest GeoTIFF :func:`amplify_command` writes (streamed in strips).
MAX_OUTPUT_SAMPLES = 1 << 34
#: Output rows per strip written by :func:`amplify_command` (a multiple of the GeoTIFF block size).
STRIP_ROWS = 512
#: Stored value of nodata cells in written GeoTIFFs.
NODATA = float("nan")


#: Stencils of the displacement predictor: 4 x 4 ordinary-kriging weights of fBm, or the classic mean of 4.
STENCILS = ("kriging", "classic")
#: Rows of the stencil table: H = i / STENCIL_TABLE_STEPS, interpolated linearly between rows.
STENCIL_TABLE_STEPS = 200
#: Level-k lattice units cropped from each side of a refined array (parents that the stencil lacks).
_MARGIN = 6


@functools.lru_cache(maxsize=8)
def _table(kind: str) -> np.ndarray:
    t = stencil_table(kind)
    t.flags.writeable = False
    return t


def stencil_table(kind: str = "kriging", steps: int = STENCIL_TABLE_STEPS) -> np.ndarray:
    """(steps + 1, 4) float64 (w_inner, w_ring, w_corner, kappa2) of the 4 x 4 stencil at H = i / steps.

    For "kriging" the weights are the ordinary-kriging (best linear unbiased) predictor of the centre of
    the middle square of a 4 x 4 unit lattice under ``D(h) = h^2H``, grouped by symmetry (4 inner
    corners, 8 ring points, 4 outer corners; they sum to 1), and ``kappa2`` is its error variance
    ``sum_i w_i D_i0 - 1/2 sum_ij w_i w_j D_ij`` per ``sigma^2 s^2H``. For "classic" the predictor is the
    mean of the 4 inner corners: ``kappa2 = 2^-H - 1/4 - 2^H / 8``. H is clipped to [0.01, 0.99].
    """
    if kind not in STENCILS:
        raise ValueError(f"Expected a stencil in {STENCILS}, got {kind!r}")
    pts = np.array([(i, j) for i in (-1, 0, 1, 2) for j in (-1, 0, 1, 2)], dtype=np.float64)
    p = np.array([0.5, 0.5])
    out = np.empty((steps + 1, 4))
    for row in range(steps + 1):
        h = min(max(row / steps, 0.01), 0.99)
        if kind == "classic":
            out[row] = (0.25, 0.0, 0.0, 2.0**-h - 0.25 - 0.125 * 2.0**h)
            continue
        dd = np.sum((pts[:, None] - pts[None]) ** 2, axis=-1) ** h
        d0 = np.sum((pts - p) ** 2, axis=-1) ** h
        a = np.ones((17, 17))
        a[:16, :16] = 0.5 * dd
        a[16, 16] = 0.0
        b = np.append(0.5 * d0, 1.0)
        w = np.linalg.solve(a, b)[:16]
        var = float(w @ d0 - 0.5 * w @ dd @ w)
        g = w.reshape(4, 4)
        out[row] = (g[1, 1], g[0, 1], g[0, 0], var)
    return out


def _levels_of(factor: int) -> int:
    f = int(factor)
    if f != factor or f < 1 or f & (f - 1) or f > (1 << MAX_LEVELS):
        raise InputError(
            f"Expected a refinement factor that is a power of 2 from 1 to {1 << MAX_LEVELS}, got {factor}"
        )
    return f.bit_length() - 1


# -- estimation ----------------------------------------------------------------------------------------
def _fit_loglog(d: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Weighted least squares of log d = a + b log h over the last axis (lags 1..n). Returns (H, sigma, ok)."""
    n = d.shape[-1]
    x = np.log(np.arange(1, n + 1, dtype=np.float64))
    w = w.astype(np.float64)
    sw = w.sum(-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        y = np.where(w > 0, np.log(np.where(d > 0, d, 1.0)), 0.0)
        xb = (w * x).sum(-1) / sw
        yb = (w * y).sum(-1) / sw
        sxx = (w * (x - xb[..., None]) ** 2).sum(-1)
        sxy = (w * (x - xb[..., None]) * (y - yb[..., None])).sum(-1)
        slope = sxy / sxx
        hurst = slope / 2.0
        sigma = np.exp((yb - slope * xb) / 2.0)
    ok = (sw >= 2) & np.isfinite(hurst) & np.isfinite(sigma)
    return hurst, sigma, ok


def estimate_fbm(
    elevation_m: np.ndarray,
    valid: np.ndarray | None = None,
    *,
    block: int = 64,
    max_lag: int = 8,
    smooth: bool = True,
    min_pairs: int = 32,
) -> tuple[np.ndarray, np.ndarray]:
    """Per-block Hurst exponent and sigma of a DEM from its variogram over the finest scales.

    Parameters
    ----------
    elevation_m : (H, W) elevation, metres, row 0 north.
    valid : (H, W) bool or None; pairs with an invalid sample are ignored.
    block : block side, samples (the last row/column of blocks may be partial).
    max_lag : lags 1..max_lag samples along rows and columns enter the fit.
    smooth : average each block with its 8 neighbours (weighted by data), so the maps vary gently.
    min_pairs : fewer valid pairs at some lag make a block take the whole DEM's estimate.

    Returns
    -------
    hurst, sigma_m : (ceil(H / block), ceil(W / block)) float64; ``sigma_m`` is the RMS elevation
    increment at a lag of one sample (metres), ``hurst`` in [0.05, 0.95]. A block that is exactly flat
    at lag 1 gets sigma 0 (no detail on lakes).
    """
    z = np.ascontiguousarray(elevation_m)
    ok_mask = np.ones(z.shape, bool) if valid is None else np.ascontiguousarray(valid, dtype=bool)
    if z.ndim != 2 or ok_mask.shape != z.shape:
        raise ValueError(f"Expected a 2-D elevation and matching mask, got {z.shape} and {ok_mask.shape}")
    if block < 2 or max_lag < 2:
        raise ValueError(f"Expected block >= 2 and max_lag >= 2, got {block} and {max_lag}")
    sums, counts = noise.block_variogram(z, ok_mask, int(block), int(max_lag))
    # Whole-DEM fit: the fallback of blocks without data.
    gs, gc = sums.sum((0, 1)), counts.sum((0, 1))
    gd = gs / np.maximum(gc, 1.0)
    gh, gsig, gok = _fit_loglog(gd, (gc >= min_pairs) & (gd > 0))
    g_hurst = float(np.clip(gh, *HURST_RANGE)) if gok else 0.5
    g_sigma = float(gsig) if gok else float(np.sqrt(gd[0])) if gc[0] > 0 else 0.0
    d = sums / np.maximum(counts, 1.0)
    enough = (counts >= min_pairs).all(axis=2)
    hurst, sigma, ok = _fit_loglog(d, (counts >= min_pairs) & (d > 0))
    flat = enough & (d[..., 0] == 0.0)
    hurst = np.where(ok & enough, np.clip(hurst, *HURST_RANGE), g_hurst)
    sigma = np.where(ok & enough, sigma, g_sigma)
    sigma = np.where(flat, 0.0, sigma)
    hurst = np.where(flat, g_hurst, hurst)
    if smooth and hurst.size > 1:
        from scipy import ndimage

        w = np.where(enough, counts[..., 0], 0.0) + 1e-9
        norm = ndimage.uniform_filter(w, 3, mode="nearest")
        hurst = ndimage.uniform_filter(w * hurst, 3, mode="nearest") / norm
        sigma = ndimage.uniform_filter(w * sigma, 3, mode="nearest") / norm
    return np.clip(hurst, *HURST_RANGE).astype(np.float64), np.maximum(sigma, 0.0).astype(np.float64)


# -- tiles ---------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class FractalTile:
    """One tile mesh at or below the DEM's finest pyramid level.

    Attributes
    ----------
    code : (level, x, y) tile code of the DEM's quadtree extended below its finest level L
    extra_levels : level - L, the fractal iterations in this tile (0: the DEM itself)
    rows, cols : (N,) float64 fractional DEM sample coordinates of the vertices (row south, col east)
    vertices : (N, 3) float64 world metres, x east, y north, z up
    triangles : (K, 3) int32, counter-clockwise seen from above
    error_m : max vertical distance, metres, from this mesh to the surface one fractal level finer
    rms_error_m : RMS of the same distances over each quad's 3 x 3 samples of the finer level
    diagonal : the quad diagonal rule used (a key of :data:`DIAGONAL_RULES`)
    """

    code: TileCode
    extra_levels: int
    rows: np.ndarray
    cols: np.ndarray
    vertices: np.ndarray
    triangles: np.ndarray
    error_m: float
    rms_error_m: float
    diagonal: str

    @property
    def bbox(self) -> np.ndarray:
        """(6,) float64 (xmin, ymin, zmin, xmax, ymax, zmax), world metres."""
        v = self.vertices
        return np.concatenate([v.min(axis=0), v.max(axis=0)])


def _triangles(nq_r: int, nq_c: int, diag1: np.ndarray) -> np.ndarray:
    """(2 nq, 3) int32 triangles of a (nq_r + 1) x (nq_c + 1) raster-order vertex grid, CCW from above."""
    idx = np.arange((nq_r + 1) * (nq_c + 1), dtype=np.int32).reshape(nq_r + 1, nq_c + 1)
    a, b = idx[:-1, :-1], idx[:-1, 1:]
    c, d = idx[1:, :-1], idx[1:, 1:]
    # diagonal 0 (a-d): (a, c, d), (a, d, b); diagonal 1 (b-c): (a, c, b), (b, c, d)
    t0 = np.stack([a, c, np.where(diag1, b, d)], axis=-1)
    t1 = np.stack([np.where(diag1, b, a), np.where(diag1, c, d), np.where(diag1, d, b)], axis=-1)
    return np.ascontiguousarray(np.stack([t0, t1], axis=2).reshape(-1, 3))


def choose_diagonals(
    zg: np.ndarray, ref: np.ndarray, sub: int, rule: str
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Pick each quad's diagonal by ``rule`` and report errors against a finer reference grid.

    Parameters
    ----------
    zg : (r + 1, c + 1) grid heights, metres; ref : (r sub + 1, c sub + 1) reference heights, metres
    rule : "lowest", "error" or "fixed" (:data:`DIAGONAL_RULES`)

    Returns
    -------
    diag1 : (r, c) bool, True where the quad is split north-east to south-west
    max_m, ss_m2 : (r, c) max |error| and summed squared error of the chosen diagonal
    max0, max1 : (r, c) max |error| of diagonal 0 and 1 (for comparing rules)
    """
    if rule not in DIAGONAL_RULES:
        raise ValueError(f"Expected a diagonal rule in {sorted(DIAGONAL_RULES)}, got {rule!r}")
    zg = np.ascontiguousarray(zg, dtype=np.float64)
    ref = np.ascontiguousarray(ref, dtype=np.float64)
    nq_r, nq_c = zg.shape[0] - 1, zg.shape[1] - 1
    max0, ss0, max1, ss1 = noise.quad_diagonal_errors(zg, ref, int(sub), nq_r, nq_c)
    if rule == "lowest":
        diag1 = (zg[:-1, 1:] + zg[1:, :-1]) < (zg[:-1, :-1] + zg[1:, 1:])
    elif rule == "error":
        diag1 = (max1 < max0) | ((max1 == max0) & (ss1 < ss0))
    else:
        diag1 = np.zeros((nq_r, nq_c), bool)
    return diag1, np.where(diag1, max1, max0), np.where(diag1, ss1, ss0), max0, max1


# -- the detail generator ------------------------------------------------------------------------------
class FractalDetail:
    """fBm detail below a DEM's resolution, a pure function of world position (Hu & Wang §2).

    Parameters
    ----------
    hf : the DEM; its samples are kept exactly at every refinement.
    hurst : Hurst exponent H in (0, 1) everywhere, or None to estimate a map from the DEM.
    sigma_m : RMS elevation increment at a lag of one DEM sample, metres, or None to estimate a map.
    seed : any integer; the same seed gives identical bytes, another seed other detail.
    block : side of the estimation blocks, samples.
    stencil : displacement predictor, "kriging" (4 x 4 fBm kriging weights, default) or "classic" (mean of
        the 4 nearest parents, the textbook diamond-square); see :func:`stencil_table`.
    cache_tiles : tiles kept by the LRU of :meth:`tile`.

    Notes
    -----
    The lattice offset on the world grid of the DEM's spacing (``lattice_offset``) enters the hash, so two
    DEMs on one grid (e.g. neighbouring sheets, or a crop) get the same noise at the same place.

    >>> detail = FractalDetail(hf, seed=7)  # doctest: +SKIP
    >>> fine = detail.amplify(4)           # 4x finer Heightfield, every DEM sample kept
    >>> tile = detail.tile((pyramid.max_level + 2, x, y))  # two fractal levels below the finest
    """

    def __init__(
        self,
        hf: Heightfield,
        *,
        hurst: float | None = None,
        sigma_m: float | None = None,
        seed: int = 0,
        block: int = 64,
        stencil: str = "kriging",
        cache_tiles: int = 256,
    ) -> None:
        if hurst is not None and not (0.0 < float(hurst) < 1.0):
            raise InputError(f"Expected a Hurst exponent in (0, 1), got {hurst}")
        if sigma_m is not None and not (math.isfinite(float(sigma_m)) and float(sigma_m) >= 0.0):
            raise InputError(f"Expected sigma_m >= 0 metres, got {sigma_m}")
        self.hf = hf
        self.seed = int(seed)
        self.stencil = stencil
        self._table = _table(stencil)
        self.block = int(block)
        if hurst is None or sigma_m is None:
            h_est, s_est = estimate_fbm(hf.elevation_m, hf.valid, block=self.block)
        hb = np.full((1, 1), float(hurst)) if hurst is not None else h_est
        sb = np.full((1, 1), float(sigma_m)) if sigma_m is not None else s_est
        self._h_blocks = np.ascontiguousarray(hb, dtype=np.float64)
        self._s_blocks = np.ascontiguousarray(sb, dtype=np.float64)
        t = hf.transform
        dx, dy = hf.spacing_m
        #: (row, col) of DEM sample (0, 0) on the world lattice of the DEM's spacing.
        self.lattice_offset = (round(-t.f / dy), round(t.c / dx))
        self._seed_u64 = np.uint64(self.seed & 0xFFFFFFFFFFFFFFFF)
        self._z = np.ascontiguousarray(hf.elevation_m)
        self._cache: OrderedDict[tuple, FractalTile] = OrderedDict()
        self._cache_size = int(cache_tiles)
        self._lock = threading.Lock()
        self._maps: dict[str, np.ndarray] = {}

    # -- maps ------------------------------------------------------------------------------------------
    @property
    def hurst_blocks(self) -> np.ndarray:
        """Hurst exponent per block (block centres at ((b + 0.5) block - 0.5) samples); (1, 1) if given."""
        return self._h_blocks.copy()

    @property
    def sigma_blocks(self) -> np.ndarray:
        """sigma (metres, RMS increment at one DEM sample) per block; (1, 1) if given."""
        return self._s_blocks.copy()

    def _map(self, name: str, blocks: np.ndarray) -> np.ndarray:
        if name not in self._maps:
            h, w = self.hf.shape
            self._maps[name] = noise.sample_blocks(blocks, self.block, h, w, 1.0).astype(np.float32)
        return self._maps[name]

    @property
    def hurst_map(self) -> np.ndarray:
        """(H, W) float32 Hurst exponent at every DEM sample (the bilinear map the generator uses)."""
        return self._map("hurst", self._h_blocks)

    @property
    def sigma_map(self) -> np.ndarray:
        """(H, W) float32 sigma, metres: RMS increment at a lag of one DEM sample, at every DEM sample."""
        return self._map("sigma", self._s_blocks)

    # -- geometry of the amplified grid ----------------------------------------------------------------
    def amplified_shape(self, factor: int) -> tuple[int, int]:
        """(rows, cols) of the grid refined ``factor`` times: ((H - 1) f + 1, (W - 1) f + 1)."""
        _levels_of(factor)
        h, w = self.hf.shape
        return (h - 1) * factor + 1, (w - 1) * factor + 1

    def amplified_transform(self, factor: int) -> Affine:
        """North-up transform of the refined grid (pixel corners), so input sample (r, c) and output sample
        (r f, c f) have the same world position (pixel centres): the output's north-west pixel corner is
        half an output pixel north-west of the input's first sample centre."""
        _levels_of(factor)
        t = self.hf.transform
        dx, dy = self.hf.spacing_m
        fx, fy = dx / factor, dy / factor
        return Affine(fx, 0.0, t.c + 0.5 * dx - 0.5 * fx, 0.0, -fy, t.f - 0.5 * dy + 0.5 * fy)

    # -- generation ------------------------------------------------------------------------------------
    def _check_window(self, row0: int, col0: int, rows: int, cols: int, factor: int) -> int:
        k = _levels_of(factor)
        nr, nc = self.amplified_shape(factor)
        if rows < 1 or cols < 1 or row0 < 0 or col0 < 0 or row0 + rows > nr or col0 + cols > nc:
            raise ValueError(
                f"Expected a window inside the {nr}x{nc} grid refined x{factor}, "
                f"got rows {row0}..{row0 + rows - 1}, cols {col0}..{col0 + cols - 1}"
            )
        return k

    def _generate(self, row0: int, col0: int, rows: int, cols: int, k: int) -> np.ndarray:
        """(rows, cols) float64 of the level-k lattice; each level computes only what the next one needs."""
        h, w = self.hf.shape
        ranges = [(0, 0, 0, 0)] * (k + 1)
        ranges[k] = (row0, row0 + rows - 1, col0, col0 + cols - 1)
        for lv in range(k, 0, -1):
            lr, hr, lc, hc = ranges[lv]
            nr, nc = (h - 1) << (lv - 1), (w - 1) << (lv - 1)
            # _MARGIN level-lv units beyond the window: the refined array's unreliable rim is cropped away
            m = _MARGIN
            ranges[lv - 1] = (max(0, (lr - m) // 2), min(nr, -(-(hr + m) // 2)),
                              max(0, (lc - m) // 2), min(nc, -(-(hc + m) // 2)))  # fmt: skip
        lr, hr, lc, hc = ranges[0]
        arr = self._z[lr : hr + 1, lc : hc + 1].astype(np.float64)
        ro, co = self.lattice_offset
        for lv in range(1, k + 1):
            plr, _, plc, _ = ranges[lv - 1]
            fine = noise.refine_level(
                arr, plr, plc, lv, (h - 1) << lv, (w - 1) << lv, self._h_blocks, self._s_blocks,
                self.block, self._table, ro, co, self._seed_u64,
            )  # fmt: skip
            lr, hr, lc, hc = ranges[lv]
            arr = fine[lr - 2 * plr : hr - 2 * plr + 1, lc - 2 * plc : hc - 2 * plc + 1]
            if lv < k:
                arr = np.ascontiguousarray(arr)
        return arr

    def window(self, row0: int, col0: int, rows: int, cols: int, factor: int) -> np.ndarray:
        """Elevations of a window of the grid refined ``factor`` times, without generating the rest.

        Parameters
        ----------
        row0, col0 : north-west sample of the window in the refined grid (row south, col east)
        rows, cols : window size, samples
        factor : refinement, a power of 2 (1 returns the DEM itself)

        Returns
        -------
        (rows, cols) float32 metres, identical bit for bit to the same crop of :meth:`amplify`.
        """
        k = self._check_window(row0, col0, rows, cols, factor)
        return self._generate(int(row0), int(col0), int(rows), int(cols), k).astype(np.float32)

    def window_valid(self, row0: int, col0: int, rows: int, cols: int, factor: int) -> np.ndarray:
        """(rows, cols) bool: True where every DEM sample around the refined sample is valid."""
        self._check_window(row0, col0, rows, cols, factor)
        i = np.arange(row0, row0 + rows)
        j = np.arange(col0, col0 + cols)
        rl, rh = i // factor, -(-i // factor)
        cl, ch = j // factor, -(-j // factor)
        v = self.hf.valid
        return v[np.ix_(rl, cl)] & v[np.ix_(rl, ch)] & v[np.ix_(rh, cl)] & v[np.ix_(rh, ch)]

    def amplify(self, factor: int) -> Heightfield:
        """The DEM refined ``factor`` (a power of 2) times with fractal detail.

        Returns
        -------
        Heightfield of ((H - 1) f + 1, (W - 1) f + 1) samples at spacing (dx / f, dy / f), same CRS, with
        ``elevation_m[r f, c f] == hf.elevation_m[r, c]`` at the same world position; a refined sample is
        valid when every DEM sample around it is.
        """
        _levels_of(factor)
        nr, nc = self.amplified_shape(factor)
        if nr * nc > MAX_IN_MEMORY_SAMPLES:
            raise InputError(
                f"Expected at most {MAX_IN_MEMORY_SAMPLES:,} refined samples in memory, got {nr * nc:,}; "
                "use window() or amplify_command(), which stream",
                self.hf.source,
            )
        z = self.window(0, 0, nr, nc, factor)
        valid = self.window_valid(0, 0, nr, nc, factor)
        note = f"fractal detail x{factor} (Hu & Wang fBm, seed {self.seed})"
        return Heightfield(
            z, valid, self.amplified_transform(factor), crs=self.hf.crs, source=self.hf.source,
            fill_method=self.hf.fill_method, notes=(*self.hf.notes, note),
        )  # fmt: skip

    # -- tiles -----------------------------------------------------------------------------------------
    def tile(self, code: TileCode, *, tile_size: int = 65, diagonal: str = "error") -> FractalTile:
        """Mesh of tile ``code`` of the DEM's quadtree extended below its finest level (LRU-cached).

        Parameters
        ----------
        code : (level, x, y) with level >= L (the finest DEM level of ``TilePyramid(W, H, tile_size)``);
            the tile covers refined-grid rows y (M - 1) .. (y + 1)(M - 1) at factor 2^(level - L), so the
            descendants of the DEM tile (L, X, Y) at level L + e are x in X 2^e .. (X + 1) 2^e - 1 (same
            for y), and the tile's vertices are a regular M x M grid (clipped at the DEM's edge).
        tile_size : M = 2^n + 1 vertices per side, as in the store.
        diagonal : quad diagonal rule, a key of :data:`DIAGONAL_RULES`. The default, "error", measured
            12-23 % smaller max error than the paper's "lowest" rule (``benchmarks/results/fractal.md``).

        Returns
        -------
        FractalTile with its error measured against the next fractal level.
        """
        key = (tuple(int(v) for v in code), int(tile_size), diagonal)
        with self._lock:
            hit = self._cache.get(key)
            if hit is not None:
                self._cache.move_to_end(key)
                return hit
        t = self._make_tile(key[0], int(tile_size), diagonal)
        with self._lock:
            self._cache[key] = t
            while len(self._cache) > self._cache_size:
                self._cache.popitem(last=False)
        return t

    def tile_mesher(
        self, *, tile_size: int = 65, diagonal: str = "error"
    ) -> Callable[[TileCode], FractalTile]:
        """A function ``code -> FractalTile`` bound to a tile size and diagonal rule (for the runtime)."""
        return lambda code: self.tile(code, tile_size=tile_size, diagonal=diagonal)

    def _make_tile(self, code: tuple[int, ...], m: int, diagonal: str) -> FractalTile:
        if not is_valid_tile_size(m):
            raise ValueError(f"Expected a tile size 2^n + 1, got {m}")
        if diagonal not in DIAGONAL_RULES:
            raise ValueError(f"Expected a diagonal rule in {sorted(DIAGONAL_RULES)}, got {diagonal!r}")
        level, x, y = code
        top = TilePyramid(self.hf.width, self.hf.height, m).max_level
        e = level - top
        if e < 0 or e >= MAX_LEVELS:
            raise ValueError(f"Expected a tile level from {top} to {top + MAX_LEVELS - 1}, got {level}")
        f = 1 << e
        nr, nc = self.amplified_shape(f)
        cells = m - 1
        r0, c0 = y * cells, x * cells
        if x < 0 or y < 0 or r0 >= nr - 1 or c0 >= nc - 1:
            raise ValueError(f"Expected an existing tile, got {tuple(code)} (refined grid {nr}x{nc})")
        nq_r, nq_c = min(cells, nr - 1 - r0), min(cells, nc - 1 - c0)
        zg = self._generate(r0, c0, nq_r + 1, nq_c + 1, e).astype(np.float32).astype(np.float64)
        ref = self._generate(2 * r0, 2 * c0, 2 * nq_r + 1, 2 * nq_c + 1, e + 1).astype(np.float32)
        diag1, emax, ess, _, _ = choose_diagonals(zg, ref, 2, diagonal)
        ii, jj = np.meshgrid(np.arange(nq_r + 1), np.arange(nq_c + 1), indexing="ij")
        rows = ((r0 + ii) / f).ravel()
        cols = ((c0 + jj) / f).ravel()
        wx, wy = self.hf.world_xy(rows, cols)
        verts = np.stack([wx, wy, zg.ravel()], axis=1)
        n_ref = ess.size * 9  # 3 x 3 reference samples per quad (shared borders counted in each quad)
        return FractalTile(
            code=(level, x, y), extra_levels=e, rows=rows, cols=cols, vertices=verts,
            triangles=_triangles(nq_r, nq_c, diag1), error_m=float(emax.max()),
            rms_error_m=float(math.sqrt(ess.sum() / n_ref)), diagonal=diagonal,
        )  # fmt: skip

    # -- view-dependent depth (eq. 3 replaced by the screen-space error) --------------------------------
    def detail_error_m(self, extra_levels: int) -> float:
        """A 3-sigma estimate, metres, of how far the full fractal surface departs from the surface after
        ``extra_levels`` iterations (0: the DEM itself): ``3 sum_{k > e} sigma_k``, the worst block, with
        sigma_k = sigma 2^(-(k-1) H) sqrt(kappa2(H)) the centre displacement of iteration k (a geometric
        series; the edge displacements are smaller).
        """
        e = int(extra_levels)
        h, s = np.broadcast_arrays(self._h_blocks, self._s_blocks)
        kappa = np.sqrt(np.interp(h, np.linspace(0.0, 1.0, self._table.shape[0]), self._table[:, 3]))
        per = 3.0 * s * kappa * 2.0 ** (-e * h) / (1.0 - 2.0 ** (-h))
        return float(per.max())

    def extra_levels_for(
        self, distance_m: np.ndarray | float, *, screen_factor_px: float, threshold_px: float = 2.0,
        max_extra: int = 8,
    ) -> np.ndarray:  # fmt: skip
        """Fractal levels to add to a finest-level DEM tile at ``distance_m`` (DESIGN.md screen-space rule).

        Parameters
        ----------
        distance_m : eye-to-tile distances, metres
        screen_factor_px : H_px / (2 tan(fov_y / 2)) of the camera
        threshold_px : refine while ``detail_error_m(e) * screen_factor_px / d`` exceeds this
        max_extra : cap on the levels

        Returns
        -------
        int array shaped like ``distance_m``: the smallest e in 0..max_extra whose projected error is
        within the threshold (max_extra when none is).
        """
        d = np.asarray(distance_m, dtype=np.float64)
        errs = np.array([self.detail_error_m(e) for e in range(max_extra + 1)])
        with np.errstate(divide="ignore"):
            rho = errs[:, None] * screen_factor_px / d.reshape(1, -1)
        need = (rho > threshold_px).sum(axis=0)
        return np.minimum(need, max_extra).reshape(d.shape)


def fractal_tile(
    detail: FractalDetail, code: TileCode, *, tile_size: int = 65, diagonal: str = "error"
) -> FractalTile:
    """Tile ``code`` at ``extra_levels = code[0] - L`` fractal levels below the DEM's finest level L.

    See :meth:`FractalDetail.tile` (this is the same call; results are LRU-cached on ``detail``).
    """
    return detail.tile(code, tile_size=tile_size, diagonal=diagonal)


# -- culling (Hu & Wang §3.1, §3.2) --------------------------------------------------------------------
def patch_backfacing(vertices: np.ndarray, triangles: np.ndarray, eye: Sequence[float]) -> bool:
    """Hu & Wang §3.2: True when every triangle of the patch faces away from the eye (skip the patch).

    Parameters
    ----------
    vertices : (N, 3) world metres; triangles : (K, 3) indices, counter-clockwise seen from the front
    eye : (3,) eye position, metres

    Notes
    -----
    A triangle ABC with outer normal n = (B - A) x (C - B) faces away when G = n . (eye - A) < 0; G >= 0
    (edge-on or degenerate included) keeps the patch. A patch without triangles is back-facing.
    """
    from terralod.kernels.cull import any_front_facing

    v = np.ascontiguousarray(vertices, dtype=np.float64)
    t = np.ascontiguousarray(np.asarray(triangles).reshape(-1, 3), dtype=np.int64)
    e = np.asarray(eye, dtype=np.float64)
    return not any_front_facing(v, t, float(e[0]), float(e[1]), float(e[2]))


def patches_backfacing(
    vertices: np.ndarray, triangles: np.ndarray, patch: np.ndarray, n_patches: int, eye: Sequence[float]
) -> np.ndarray:
    """:func:`patch_backfacing` for many patches at once.

    Parameters
    ----------
    patch : (K,) int, the patch of each triangle (0 .. n_patches - 1)

    Returns
    -------
    (n_patches,) bool, True where no triangle of the patch faces the eye.
    """
    v = np.asarray(vertices, dtype=np.float64)
    t = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    a, b, c = v[t[:, 0]], v[t[:, 1]], v[t[:, 2]]
    g = np.einsum("ij,ij->i", np.cross(b - a, c - b), np.asarray(eye, dtype=np.float64) - a)
    front = np.bincount(np.asarray(patch, dtype=np.int64)[g >= 0.0], minlength=int(n_patches))
    return front[: int(n_patches)] == 0


def _hull2d(p: np.ndarray) -> np.ndarray:
    """Convex hull (counter-clockwise, monotone chain) of 2-D points; fewer than 3 distinct -> as is."""
    pts = sorted({(float(x), float(y)) for x, y in np.round(p, 9)})
    if len(pts) < 3:
        return np.asarray(pts, dtype=np.float64).reshape(-1, 2)

    def cross(o, a, b):
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    lower: list = []
    for q in pts:
        while len(lower) >= 2 and cross(lower[-2], lower[-1], q) <= 0:
            lower.pop()
        lower.append(q)
    upper: list = []
    for q in reversed(pts):
        while len(upper) >= 2 and cross(upper[-2], upper[-1], q) <= 0:
            upper.pop()
        upper.append(q)
    return np.asarray(lower[:-1] + upper[:-1], dtype=np.float64)


def visible_region(
    eye: Sequence[float],
    target: Sequence[float],
    *,
    far_m: float,
    up: Sequence[float] = (0.0, 0.0, 1.0),
    fov_y_deg: float = 60.0,
    aspect: float = 16.0 / 9.0,
    near_m: float = 1.0,
    plane_z_m: float = 0.0,
) -> np.ndarray:
    """Hu & Wang §3.1: the visible region A'B'C'D', the view frustum cut by the terrain's mean plane.

    Parameters
    ----------
    eye, target, up : camera position, a looked-at point, the up hint (world metres)
    far_m : far distance, metres (the paper's region is unbounded when the view looks above the horizon)
    fov_y_deg, aspect, near_m : vertical field of view (degrees), width / height, near distance (metres)
    plane_z_m : elevation of the terrain's average horizontal plane XOY, metres

    Returns
    -------
    (k, 2) float64 convex polygon (x, y) counter-clockwise, world metres; empty (0, 2) when the frustum
    misses the plane. Exact section of the frustum solid (near to far) with z = plane_z_m.
    """
    eye_v = np.asarray(eye, dtype=np.float64)
    f = np.asarray(target, dtype=np.float64) - eye_v
    f /= np.linalg.norm(f)
    r = np.cross(f, np.asarray(up, dtype=np.float64))
    if np.linalg.norm(r) < 1e-12:
        raise ValueError(f"Expected an up vector not parallel to the view direction, got {list(up)}")
    r /= np.linalg.norm(r)
    u = np.cross(r, f)
    ty = math.tan(math.radians(fov_y_deg) / 2.0)
    tx = ty * aspect
    corners = []
    for dist in (near_m, far_m):
        for sx, sy in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
            corners.append(eye_v + dist * (f + sx * tx * r + sy * ty * u))
    c = np.asarray(corners)
    edges = [(i, (i + 1) % 4) for i in range(4)] + [(4 + i, 4 + (i + 1) % 4) for i in range(4)]
    edges += [(i, i + 4) for i in range(4)]
    pts = []
    for i, j in edges:
        a, b = c[i, 2] - plane_z_m, c[j, 2] - plane_z_m
        if a == 0.0:
            pts.append(c[i, :2])
        if b == 0.0:
            pts.append(c[j, :2])
        if a * b < 0.0:
            t = a / (a - b)
            pts.append(c[i, :2] + t * (c[j, :2] - c[i, :2]))
    if len(pts) < 3:
        return np.zeros((0, 2))
    return _hull2d(np.asarray(pts))


def boxes_in_region(boxes: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """Which patch footprints overlap the visible region (separating-axis test, exact for convex polygons).

    Parameters
    ----------
    boxes : (n, 4) (xmin, ymin, xmax, ymax) or (n, 6) (xmin, ymin, zmin, xmax, ymax, zmax), world metres
    polygon : (k, 2) convex polygon from :func:`visible_region`

    Returns
    -------
    (n,) bool, True where the footprint and the region share a point.
    """
    b = np.atleast_2d(np.asarray(boxes, dtype=np.float64))
    if b.shape[1] == 6:
        b = b[:, [0, 1, 3, 4]]
    poly = np.asarray(polygon, dtype=np.float64).reshape(-1, 2)
    if poly.shape[0] == 0:
        return np.zeros(b.shape[0], bool)
    edges = np.roll(poly, -1, axis=0) - poly
    axes = np.concatenate([np.eye(2), np.stack([-edges[:, 1], edges[:, 0]], axis=1)])
    axes = axes[np.linalg.norm(axes, axis=1) > 0]
    centre = 0.5 * (b[:, :2] + b[:, 2:])
    half = 0.5 * (b[:, 2:] - b[:, :2])
    pc = centre @ axes.T  # (n, m)
    pr = half @ np.abs(axes).T
    proj = poly @ axes.T  # (k, m)
    lo, hi = proj.min(axis=0), proj.max(axis=0)
    return np.all((pc - pr <= hi) & (pc + pr >= lo), axis=1)


def boxes_in_frustum(boxes: np.ndarray, planes: np.ndarray) -> np.ndarray:
    """Conservative 3-D test of boxes (n, 6) against inward planes (p, 4) ``n . x + d >= 0``: False only
    when a box lies wholly outside one plane (the p-vertex test)."""
    b = np.atleast_2d(np.asarray(boxes, dtype=np.float64))
    pl = np.atleast_2d(np.asarray(planes, dtype=np.float64))
    n = pl[:, :3]
    pv = np.where(n[None, :, :] >= 0.0, b[:, None, 3:], b[:, None, :3])  # (n, p, 3)
    return np.all(np.einsum("npk,pk->np", pv, n) + pl[None, :, 3] >= 0.0, axis=1)


# -- product: amplify a DEM file to a finer GeoTIFF -----------------------------------------------------
def write_geotiff(detail: FractalDetail, output: str | os.PathLike[str], factor: int) -> dict[str, Any]:
    """Write the DEM refined ``factor`` times to a float32 GeoTIFF, strip by strip (bounded memory).

    The file appears atomically (written beside the target, then renamed). Cells whose DEM neighbours are
    nodata are written as NaN, the declared nodata value. Returns counts for the summary.
    """
    import rasterio
    from rasterio.crs import CRS
    from rasterio.windows import Window

    nr, nc = detail.amplified_shape(factor)
    out = Path(output)
    if not out.parent.is_dir():
        raise InputError(f"cannot write the output: folder {out.parent} does not exist", str(out))
    profile = {
        "driver": "GTiff", "height": nr, "width": nc, "count": 1, "dtype": "float32",
        "transform": detail.amplified_transform(factor), "nodata": NODATA, "tiled": True,
        "blockxsize": 256, "blockysize": 256, "compress": "deflate", "predictor": 3, "BIGTIFF": "IF_SAFER",
    }  # fmt: skip
    if detail.hf.crs:
        profile["crs"] = CRS.from_user_input(detail.hf.crs)
    invalid = 0
    from terralod.io.raster import atomic_file, c_stderr_captured, error_line

    said: list[str] = []
    try:
        with c_stderr_captured() as said, atomic_file(out) as tmp, rasterio.open(tmp, "w", **profile) as dst:
            for r0 in range(0, nr, STRIP_ROWS):
                n = min(STRIP_ROWS, nr - r0)
                z = detail.window(r0, 0, n, nc, factor)
                ok = detail.window_valid(r0, 0, n, nc, factor)
                invalid += int((~ok).sum())
                z[~ok] = NODATA
                dst.write(z, 1, window=Window(0, r0, nc, n))
    except BaseException as exc:
        if isinstance(exc, Exception) and not isinstance(exc, InputError):  # full disk, I/O: name the file
            text = error_line(exc) + (f"; {said[0]}" if said else "")
            raise OSError(getattr(exc, "errno", None), f"cannot write ({text})", str(out)) from exc
        raise
    return {"rows": nr, "cols": nc, "invalid": invalid}


def _stats(a: np.ndarray) -> dict[str, float]:
    return {"min": float(a.min()), "mean": float(a.mean()), "max": float(a.max())}


def amplify_command(
    input: str | os.PathLike[str] | Heightfield,
    output: str | os.PathLike[str],
    factor: int = 2,
    seed: int = 0,
    hurst: float | None = None,
    sigma: float | None = None,
    **read: Any,
) -> dict[str, Any]:
    """``terralod amplify DEM --factor F -o FINE.tif``: write a DEM refined F times with fractal detail.

    Parameters
    ----------
    input : DEM path (anything :func:`terralod.io.reader.read_heightfield` reads; ``read`` is passed on)
        or a Heightfield
    output : GeoTIFF path (float32, deflate, tiled; replaced atomically)
    factor : refinement, a power of 2 >= 2
    seed : noise seed; the same seed gives identical bytes
    hurst : Hurst exponent in (0, 1), or None to estimate a map from the DEM
    sigma : RMS elevation increment at one DEM sample, metres, or None to estimate a map

    Returns
    -------
    dict: input, output, factor, seed, shape_in / shape_out (rows, cols), spacing_in_m / spacing_out_m,
    crs (WKT or None), hurst / sigma_m (min, mean, max over the DEM), nodata_fraction, seconds,
    samples_per_second, bytes.

    Raises
    ------
    InputError : bad factor, hurst or sigma, unreadable input, or an output beyond MAX_OUTPUT_SAMPLES.
    """
    t0 = time.perf_counter()
    if isinstance(input, Heightfield):
        hf = input
    else:
        from terralod.io.reader import read_heightfield

        hf = read_heightfield(input, **read)
    k = _levels_of(factor)
    if k < 1:
        raise InputError(f"Expected a factor of at least 2, got {factor}", str(output))
    detail = FractalDetail(hf, hurst=hurst, sigma_m=sigma, seed=seed)
    nr, nc = detail.amplified_shape(factor)
    if nr * nc > MAX_OUTPUT_SAMPLES:
        raise InputError(
            f"Expected at most {MAX_OUTPUT_SAMPLES:,} output samples, got {nr:,} x {nc:,}; "
            "use a smaller factor or crop the input",
            str(output),
        )
    written = write_geotiff(detail, output, factor)
    dt = time.perf_counter() - t0
    dx, dy = hf.spacing_m
    summary = {
        "input": hf.source if isinstance(input, Heightfield) else str(input),
        "output": str(output),
        "factor": int(factor),
        "seed": int(seed),
        "shape_in": [hf.height, hf.width],
        "shape_out": [nr, nc],
        "spacing_in_m": [dx, dy],
        "spacing_out_m": [dx / factor, dy / factor],
        "crs": hf.crs,
        "hurst": _stats(detail.hurst_map) if hurst is None else {"min": hurst, "mean": hurst, "max": hurst},
        "sigma_m": _stats(detail.sigma_map) if sigma is None else {"min": sigma, "mean": sigma, "max": sigma},
        "nodata_fraction": written["invalid"] / (nr * nc),
        "seconds": dt,
        "samples_per_second": nr * nc / dt if dt > 0 else math.inf,
        "bytes": Path(output).stat().st_size,
    }
    log.info("amplified %s x%d -> %s (%d x %d) in %.2f s", summary["input"], factor, output, nr, nc, dt)
    return summary
