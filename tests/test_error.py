"""Measured mesh error against a brute-force numpy reference, plus invariants and a real-DEM golden case.

The reference tests every covered sample against every triangle. It shares only the *definition* of
coverage with the kernel (the canonical-edge orientation predicate, which decides samples lying exactly
on an edge); the point-triangle distance is computed another way (projection onto the plane when it falls
inside, else the nearest of the three edges) and there is no bucketing, pruning or early out.

Regenerate the golden numbers with ``python tests/test_error.py``.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st
from scipy.spatial import Delaunay

from terralod.error import ErrorReport, measure_error, measure_error_window, measure_error_window_series
from terralod.heightfield import Heightfield
from terralod.kernels.error import changed_rows, tile_error, tile_error_with

RTOL = 1e-9
SETTINGS = settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.too_slow])

# -- reference -----------------------------------------------------------------------------------------


def _canonical(ax, ay, bx, by):
    keep = (ax < bx) | ((ax == bx) & (ay <= by))
    return (
        np.where(keep, ax, bx),
        np.where(keep, ay, by),
        np.where(keep, bx - ax, ax - bx),
        np.where(keep, by - ay, ay - by),
    )


def _seg_dist2(p, a, b):
    """(S, T) squared distances from points p (S, 3) to segments a-b (T, 3)."""
    u = b - a
    wv = p[:, None, :] - a[None, :, :]
    uu = (u * u).sum(-1)
    t = np.where(uu > 0, (wv * u[None]).sum(-1) / np.where(uu > 0, uu, 1.0), 0.0)
    t = np.clip(t, 0.0, 1.0)
    d = wv - t[..., None] * u[None]
    return (d * d).sum(-1)


def _point_tri_dist2(p, a, b, c):
    """(S, T) squared distances, points to triangles: plane if the projection is inside, else edges."""
    ab, ac = b - a, c - a
    n = np.cross(ab, ac)
    nn = (n * n).sum(-1)
    ap = p[:, None, :] - a[None]
    h = (ap * n[None]).sum(-1)  # signed distance * |n|
    safe = np.where(nn > 0, nn, 1.0)
    q = ap - (h / safe)[..., None] * n[None]  # projection, relative to a
    d00, d01, d11 = (ab * ab).sum(-1), (ab * ac).sum(-1), (ac * ac).sum(-1)
    d20, d21 = (q * ab[None]).sum(-1), (q * ac[None]).sum(-1)
    den = d00 * d11 - d01 * d01
    dsafe = np.where(den > 0, den, 1.0)
    v = (d11 * d20 - d01 * d21) / dsafe
    w = (d00 * d21 - d01 * d20) / dsafe
    inside = (nn > 0)[None] & (den > 0)[None] & (v >= 0) & (w >= 0) & (v + w <= 1)
    plane = np.where(inside, h * h / safe, np.inf)
    return np.minimum.reduce([plane, _seg_dist2(p, a, b), _seg_dist2(p, b, c), _seg_dist2(p, c, a)])


def _snap(u):
    near = np.floor(u + 0.5)
    return np.where(np.abs(u - near) <= 1e-7, near, u)


def reference(verts, tris, z, valid, dx, dy, chunk=4096):
    """Per-sample vertical error (inf if uncovered) and Hausdorff distance (nan if uncovered), (h, w)."""
    verts = np.asarray(verts, np.float64)
    tris = np.asarray(tris, np.int64)
    h, w = z.shape
    vert = np.full((h, w), np.inf)
    dist = np.full((h, w), np.nan)
    if tris.shape[0] == 0:
        return vert, dist
    # Coverage in sample units, vertices within 1e-7 samples of a lattice point put on it (the definition).
    x, y, zz = _snap(verts[:, 0] / dx), _snap(verts[:, 1] / dy), verts[:, 2]
    edges = []
    for i in range(3):
        a, b, o = tris[:, (i + 1) % 3], tris[:, (i + 2) % 3], tris[:, i]
        px, py, ex, ey = _canonical(x[a], y[a], x[b], y[b])
        m = np.sign(ex * (y[o] - py) - ey * (x[o] - px))
        edges.append((px, py, ex, ey, m))
    coverable = (edges[0][4] != 0) & (edges[1][4] != 0) & (edges[2][4] != 0)
    rr, cc = np.nonzero(valid & ~np.isnan(z))
    tri_pts = [verts[tris[:, k]] for k in range(3)]
    for s in range(0, rr.size, chunk):
        r, c = rr[s : s + chunk], cc[s : s + chunk]
        sx, sy = c.astype(np.float64)[:, None], r.astype(np.float64)[:, None]
        ls = [(ex * (sy - py) - ey * (sx - px)) * m for px, py, ex, ey, m in edges]
        tot = ls[0] + ls[1] + ls[2]
        cov = coverable[None] & (ls[0] >= 0) & (ls[1] >= 0) & (ls[2] >= 0) & (tot > 0)
        with np.errstate(divide="ignore", invalid="ignore"):
            zs = sum((ls[k] / tot) * zz[tris[:, k]][None] for k in range(3))
        v = np.where(cov, np.abs(z[r, c].astype(np.float64)[:, None] - zs), np.inf).min(axis=1)
        vert[r, c] = v
        hit = np.isfinite(v)
        p = np.stack([c * dx, r * dy, z[r, c].astype(np.float64)], axis=1)[hit]
        rh, ch = r[hit], c[hit]
        for i, j, reach2 in _blocks(p, tri_pts, v[hit]):  # the minimum over every triangle, square by square
            d2 = _point_tri_dist2(p[i], *(t[j] for t in tri_pts)).min(axis=1) if j.size else np.inf
            if not np.all(d2 <= reach2):  # a triangle left out could be nearer: take them all
                d2 = _point_tri_dist2(p[i], *tri_pts).min(axis=1)
            dist[rh[i], ch[i]] = np.sqrt(d2)
    return vert, dist


def _blocks(p, tri_pts, v, cell=8.0):
    """(samples, triangles, reach²) of squares of samples: every triangle whose box is within reach of the
    square's box, reach being the square's largest vertical error (a covered sample lies about that far
    from the mesh: its drop onto the covering triangle). The caller checks each minimum is within reach; a
    triangle left out is further than reach, so the minimum over the rest is the minimum over all."""
    if p.shape[0] == 0:
        return []
    lo = np.minimum.reduce(tri_pts)
    hi = np.maximum.reduce(tri_pts)
    size = max(float(np.ptp(p[:, :2], axis=0).max()) / cell, 1e-9)
    key = np.floor((p[:, :2] - p[:, :2].min(axis=0)) / size).astype(np.int64)
    key = key[:, 0] * (int(cell) + 2) + key[:, 1]
    out = []
    for k in np.unique(key):
        i = np.nonzero(key == k)[0]
        plo, phi = p[i].min(axis=0), p[i].max(axis=0)
        gap = np.maximum(np.maximum(lo - phi, plo - hi), 0.0)
        reach2 = (float(v[i].max()) * (1.0 + 1e-6) + 1e-6 * (1.0 + float(np.abs(p[i]).max()))) ** 2
        out.append((i, np.nonzero((gap * gap).sum(-1) <= reach2 * (1.0 + 1e-6))[0], reach2))
    return out


def check_against_reference(
    verts, tris, z, valid, dx, dy, variants=((1, 0), (3, 1 << 30), (7, 0), (0, 0))
) -> ErrorReport:
    """Kernel == reference, with automatic settings and each (bucket_size, keep_samples) of variants.

    Only speed may depend on them: small buckets put many bucket edges through the mesh, keep_samples=0
    takes the bucket-by-bucket path that coarse tiles take. Returns the automatic report.
    """
    rep = measure_error_window(verts, tris, z, valid, dx, dy)
    vert, dist = reference(verts, tris, z, valid, dx, dy)
    args = (np.asarray(verts, np.float64), np.asarray(tris, np.int64), z, valid, float(dx), float(dy))
    for bs, keep in variants:
        out = tile_error_with(*args, bs, keep)
        assert out[2] == rep.n_samples, (bs, keep)
        assert out[0] == pytest.approx(rep.max_vertical_m, rel=RTOL), (bs, keep)
        assert out[3] == pytest.approx(rep.hausdorff_m, rel=RTOL, abs=1e-12), (bs, keep)
    cov = np.isfinite(vert)
    assert rep.n_samples == int(cov.sum())
    if rep.n_samples == 0:
        assert (rep.max_vertical_m, rep.rms_vertical_m, rep.hausdorff_m) == (0.0, 0.0, 0.0)
        assert rep.worst_vertical_rc is None and rep.worst_hausdorff_rc is None
        return rep
    tol = RTOL * max(1.0, float(np.abs(z).max()))  # absolute floor for errors near 0
    assert rep.max_vertical_m == pytest.approx(vert[cov].max(), rel=RTOL, abs=tol)
    assert rep.rms_vertical_m == pytest.approx(math.sqrt(np.mean(vert[cov] ** 2)), rel=RTOL, abs=tol)
    assert rep.hausdorff_m == pytest.approx(np.nanmax(dist), rel=RTOL, abs=tol)
    assert rep.hausdorff_m <= rep.max_vertical_m * (1 + RTOL) + tol
    # The reported worst samples attain the maxima.
    assert vert[rep.worst_vertical_rc] == pytest.approx(rep.max_vertical_m, rel=RTOL, abs=tol)
    assert dist[rep.worst_hausdorff_rc] == pytest.approx(rep.hausdorff_m, rel=RTOL, abs=tol)
    return rep


# -- random terrains and meshes -----------------------------------------------------------------------


def terrain(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """Smooth-ish random terrain (cumulated noise) or white noise, float32 metres."""
    kind = rng.integers(3)
    scale = float(rng.choice([0.01, 1.0, 30.0, 400.0]))
    if kind == 0:
        zz = np.cumsum(np.cumsum(rng.normal(size=(h, w)), 0), 1)
        zz = zz / max(np.ptp(zz), 1e-9) * scale
    elif kind == 1:
        zz = rng.normal(size=(h, w)) * scale
    else:
        zz = np.sin(np.arange(h)[:, None] * 0.7) * np.cos(np.arange(w)[None] * 0.45) * scale
    return (zz + rng.uniform(-1000, 3000)).astype(np.float32)


def grid_mesh(
    rng: np.random.Generator, z: np.ndarray, dx: float, dy: float, stride: int, diag: str, noise: float
) -> tuple[np.ndarray, np.ndarray]:
    """Regular grid at ``stride`` samples from a random lattice corner, possibly past the window edge.

    diag: "nw" (north-west/south-east diagonal), "ne", or "random" per quad. Vertex heights are the
    (edge-clamped) samples plus uniform noise of amplitude ``noise`` metres.
    """
    h, w = z.shape
    r0, c0 = int(rng.integers(-stride, h)), int(rng.integers(-stride, w))
    mr = int(rng.integers(2, max(3, (h - r0) // stride + 3)))
    mc = int(rng.integers(2, max(3, (w - c0) // stride + 3)))
    rows = r0 + stride * np.arange(mr)
    cols = c0 + stride * np.arange(mc)
    rg, cg = np.meshgrid(rows, cols, indexing="ij")
    zv = z[np.clip(rg, 0, h - 1), np.clip(cg, 0, w - 1)].astype(np.float64)
    zv = zv + rng.uniform(-noise, noise, zv.shape)
    verts = np.stack([cg.ravel() * dx, rg.ravel() * dy, zv.ravel()], axis=1)
    idx = np.arange(mr * mc).reshape(mr, mc)
    a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
    c, d = idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    nw = {"nw": np.ones(a.size, bool), "ne": np.zeros(a.size, bool)}.get(diag)
    if nw is None:
        nw = rng.random(a.size) < 0.5
    t1 = np.where(nw[:, None], np.stack([a, b, d], 1), np.stack([a, b, c], 1))
    t2 = np.where(nw[:, None], np.stack([a, d, c], 1), np.stack([b, d, c], 1))
    return verts, np.concatenate([t1, t2]).astype(np.int64)


def delaunay_mesh(
    rng: np.random.Generator, z: np.ndarray, dx: float, dy: float, n: int, noise: float, sliver: bool
) -> tuple[np.ndarray, np.ndarray]:
    """Delaunay of random points (some on the lattice, some beyond the window), heights near the terrain.

    sliver: add nearly collinear points along a random line, which makes needle and cap triangles.
    """
    h, w = z.shape
    pc = rng.uniform(-1.5, w + 0.5, n)
    pr = rng.uniform(-1.5, h + 0.5, n)
    on = rng.random(n) < 0.3
    pc[on], pr[on] = np.round(pc[on]), np.round(pr[on])
    if sliver:
        k = int(rng.integers(3, 12))
        t = np.sort(rng.uniform(0, 1, k))
        c0, r0, c1, r1 = (
            rng.uniform(0, w - 1),
            rng.uniform(0, h - 1),
            rng.uniform(0, w - 1),
            rng.uniform(0, h - 1),
        )
        pc = np.concatenate([pc, c0 + t * (c1 - c0) + rng.normal(0, 1e-4, k)])
        pr = np.concatenate([pr, r0 + t * (r1 - r0) + rng.normal(0, 1e-4, k)])
    corners = [[-1.0, -1.0], [w, -1.0], [-1.0, h]]  # never fewer than 3 non-collinear points (on the lattice)
    pts = np.unique(np.concatenate([np.stack([pc, pr], 1), corners]), axis=0)
    tri = Delaunay(pts).simplices.astype(np.int64)
    zi = z[
        np.clip(np.round(pts[:, 1]).astype(int), 0, h - 1), np.clip(np.round(pts[:, 0]).astype(int), 0, w - 1)
    ]
    zv = zi.astype(np.float64) + rng.uniform(-noise, noise, len(pts))
    return np.stack([pts[:, 0] * dx, pts[:, 1] * dy, zv], 1), tri


def soup_mesh(
    rng: np.random.Generator, z: np.ndarray, dx: float, dy: float, k: int
) -> tuple[np.ndarray, np.ndarray]:
    """Random overlapping triangles (folds, soups): coverage takes the min over covering triangles."""
    h, w = z.shape
    verts = np.stack(
        [
            rng.uniform(-1, w, 3 * k) * dx,
            rng.uniform(-1, h, 3 * k) * dy,
            rng.uniform(z.min() - 5, z.max() + 5, 3 * k),
        ],
        axis=1,
    )
    return verts, np.arange(3 * k, dtype=np.int64).reshape(k, 3)


@st.composite
def cases(draw, kinds=("grid", "delaunay", "sliver", "soup")):
    """(verts, tris, z, valid, dx, dy) of a random terrain window and mesh."""
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    h, w = draw(st.integers(2, 48)), draw(st.integers(2, 48))
    dx, dy = (
        draw(st.sampled_from([1.0, 0.5, 21.29, 30.71, 160.0])),
        draw(st.sampled_from([1.0, 0.3, 30.71, 160.0])),
    )
    z = terrain(rng, h, w)
    valid = np.ones((h, w), bool) if draw(st.booleans()) else rng.random((h, w)) < 0.8
    kind = draw(st.sampled_from(kinds))
    noise = float(rng.choice([0.0, 0.5, 20.0]))
    if kind == "grid":
        stride = draw(st.sampled_from([1, 2, 4, 8]))
        verts, tris = grid_mesh(rng, z, dx, dy, stride, draw(st.sampled_from(["nw", "ne", "random"])), noise)
    elif kind in ("delaunay", "sliver"):
        verts, tris = delaunay_mesh(rng, z, dx, dy, draw(st.integers(3, 60)), noise, kind == "sliver")
    else:
        verts, tris = soup_mesh(rng, z, dx, dy, draw(st.integers(1, 25)))
    return verts, tris, z, valid, dx, dy


# -- properties ---------------------------------------------------------------------------------------


@given(case=cases())
@SETTINGS
def test_kernel_matches_brute_force(case) -> None:
    check_against_reference(*case)


@given(case=cases(kinds=("grid", "delaunay")), data=st.data())
@SETTINGS
def test_invariant_to_winding_and_order(case, data) -> None:
    verts, tris, z, valid, dx, dy = case
    rep = measure_error_window(verts, tris, z, valid, dx, dy)
    rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1)))
    perm = rng.permutation(len(verts))
    inv = np.argsort(perm)
    t2 = inv[tris[rng.permutation(len(tris))]][:, ::-1]  # reorder vertices and triangles, flip winding
    rep2 = measure_error_window(verts[perm], t2, z, valid, dx, dy)
    tol = RTOL * max(1.0, float(np.abs(z).max()))
    assert rep2.n_samples == rep.n_samples
    for f in ("max_vertical_m", "rms_vertical_m", "hausdorff_m"):
        assert getattr(rep2, f) == pytest.approx(getattr(rep, f), rel=RTOL, abs=tol)
    assert measure_error_window(verts, tris, z, valid, dx, dy) == rep  # deterministic


@given(case=cases(), data=st.data())
@SETTINGS
def test_series_matches_one_by_one(case, data) -> None:
    """measure_error_window_series (only rows a changed triangle reaches rasterised again) equals
    measure_error_window on every mesh, bit for bit: a few vertices moved (on or off the lattice, heights
    changed), triangles re-indexed, the same mesh again, a mesh of another size."""
    verts, tris, z, valid, dx, dy = case
    rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1)))
    meshes = [(verts, tris)]
    for _ in range(4):
        v, t = meshes[-1][0].copy(), meshes[-1][1].copy()
        if len(v):
            moved = rng.choice(len(v), size=min(len(v), int(rng.integers(1, 4))), replace=False)
            v[moved, 0] += np.round(rng.uniform(-3, 3, moved.size)) * dx * rng.choice([1.0, 0.37])
            v[moved, 1] += np.round(rng.uniform(-3, 3, moved.size)) * dy * rng.choice([1.0, 0.37])
            v[moved, 2] += rng.normal(0.0, 5.0, moved.size)
        if len(t) and rng.random() < 0.3:
            k = int(rng.integers(len(t)))
            t[k] = t[k][::-1]
        meshes.append((v, t))
    meshes.append(meshes[-1])
    meshes.append((verts, tris[: len(tris) // 2]))
    got = measure_error_window_series(meshes, z, valid, dx, dy)
    assert got == [measure_error_window(v, t, z, valid, dx, dy) for v, t in meshes]


def _changed_rows_numpy(pv, pt, v, t, dy, h):
    """The numpy statement of changed_rows (the rows a differing triangle reaches in either mesh)."""
    moved = (pv != v).any(axis=1)
    changed = (pt != t).any(axis=1)
    if t.size:
        changed |= moved[pt].any(axis=1) | moved[t].any(axis=1)
    ys = np.concatenate([pv[pt[changed], 1], v[t[changed], 1]]) / dy
    lo = np.clip(np.floor(ys.min(axis=1, initial=np.inf)).astype(np.int64) - 1, 0, h) if len(ys) else ys
    hi = np.clip(np.ceil(ys.max(axis=1, initial=-np.inf)).astype(np.int64) + 2, 0, h) if len(ys) else ys
    edges = np.zeros(h + 1, np.int64)
    np.add.at(edges, lo.astype(np.int64), 1)
    np.add.at(edges, hi.astype(np.int64), -1)
    return np.cumsum(edges[:h]) > 0


@given(case=cases(), data=st.data())
@SETTINGS
def test_changed_rows_kernel_matches_numpy(case, data) -> None:
    """The kernel that picks the rows to rasterise again gives the numpy statement's rows: vertices moved
    in x, y or only z (on and off the lattice, past the window's edges), triangles re-indexed, no change."""
    verts, tris, z, _valid, _dx, dy = case
    h = z.shape[0]
    rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1)))
    v = np.ascontiguousarray(verts, np.float64).copy()
    t = np.ascontiguousarray(tris, np.int64).copy()
    pv, pt = v.copy(), t.copy()
    if len(v) and data.draw(st.booleans()):
        moved = rng.choice(len(v), size=min(len(v), int(rng.integers(1, 5))), replace=False)
        axis = int(rng.integers(3))
        v[moved, axis] += rng.uniform(-4, 4, moved.size) * (dy if axis == 1 else 1.0)
    if len(t) and data.draw(st.booleans()):
        k = int(rng.integers(len(t)))
        t[k] = t[k][::-1]
    got = changed_rows(pv, pt, v, t, float(dy), h)
    assert np.array_equal(got, _changed_rows_numpy(pv, pt, v, t, float(dy), h))
    assert not changed_rows(pv, pt, pv, pt, float(dy), h).any()


@given(case=cases(kinds=("grid", "delaunay", "sliver")), data=st.data())
@SETTINGS
def test_planar_heightfield_gives_zero(case, data) -> None:
    verts, tris, z, valid, dx, dy = case
    h, w = z.shape
    # Dyadic slopes and integer offset: every float32 sample of the plane is exact.
    a, b = data.draw(st.integers(-32, 32)) / 8, data.draw(st.integers(-32, 32)) / 8
    d = float(data.draw(st.integers(-500, 4000)))
    rr, cc = np.mgrid[0:h, 0:w]
    zp = (a * rr + b * cc + d).astype(np.float32)
    assert np.array_equal(zp.astype(np.float64), a * rr + b * cc + d)
    verts = verts.copy()
    verts[:, 2] = a * (verts[:, 1] / dy) + b * (verts[:, 0] / dx) + d
    rep = measure_error_window(verts, tris, zp, valid, dx, dy)
    tol = 1e-9 * (1.0 + abs(d) + 32 * (h + w))
    assert rep.max_vertical_m <= tol and rep.hausdorff_m <= tol and rep.rms_vertical_m <= tol


@given(data=st.data())
@SETTINGS
def test_full_resolution_grid_is_exact_and_bump_adds_its_height(data) -> None:
    rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1)))
    h, w = data.draw(st.integers(2, 30)), data.draw(st.integers(2, 30))
    dx, dy = data.draw(st.sampled_from([1.0, 21.29, 160.0])), data.draw(st.sampled_from([1.0, 30.71, 160.0]))
    z = terrain(rng, h, w)
    valid = np.ones((h, w), bool)
    rr, cc = np.mgrid[0:h, 0:w]
    verts = np.stack([cc.ravel() * dx, rr.ravel() * dy, z.ravel().astype(np.float64)], 1)
    idx = np.arange(h * w).reshape(h, w)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    nw = rng.random(a.size) < 0.5
    tris = np.concatenate(
        [np.where(nw[:, None], np.stack([a, b, d], 1), np.stack([a, b, c], 1)),
         np.where(nw[:, None], np.stack([a, d, c], 1), np.stack([b, d, c], 1))]
    )  # fmt: skip
    rep = measure_error_window(verts, tris, z, valid, dx, dy)
    assert rep == ErrorReport(0.0, 0.0, 0.0, h * w, rep.worst_vertical_rc, rep.worst_hausdorff_rc)
    # A bump of one vertex: the max vertical error is the bump, at that vertex.
    bump = data.draw(st.sampled_from([0.25, 3.0, 250.0])) * (1 if data.draw(st.booleans()) else -1)
    k = int(rng.integers(h * w))
    verts[k, 2] += bump
    rep = measure_error_window(verts, tris, z, valid, dx, dy)
    assert rep.max_vertical_m == pytest.approx(abs(bump), rel=1e-6)
    assert rep.worst_vertical_rc == divmod(k, w)
    assert 0.0 < rep.hausdorff_m <= rep.max_vertical_m
    assert rep.n_samples == h * w


@given(case=cases(kinds=("grid", "delaunay", "sliver")), data=st.data())
@SETTINGS
def test_bump_moves_max_vertical_by_at_most_the_bump(case, data) -> None:
    verts, tris, z, valid, dx, dy = case
    rep = measure_error_window(verts, tris, z, valid, dx, dy)
    k = data.draw(st.integers(0, len(verts) - 1))
    bump = data.draw(st.floats(-100, 100))
    v2 = verts.copy()
    v2[k, 2] += bump
    rep2 = measure_error_window(v2, tris, z, valid, dx, dy)
    tol = RTOL * max(1.0, float(np.abs(z).max()) + abs(bump))
    assert rep2.n_samples == rep.n_samples
    assert abs(rep2.max_vertical_m - rep.max_vertical_m) <= abs(bump) + tol


@given(case=cases(kinds=("grid", "delaunay", "sliver", "soup")), data=st.data())
@SETTINGS
def test_uncovered_and_invalid_samples_are_ignored(case, data) -> None:
    verts, tris, z, valid, dx, dy = case
    rep = measure_error_window(verts, tris, z, valid, dx, dy)
    vert, _ = reference(verts, tris, z, np.ones_like(valid), dx, dy)
    ignored = ~(np.isfinite(vert) & valid)  # uncovered, or covered but invalid
    garbage = np.where(ignored, data.draw(st.sampled_from([np.nan, 1e6, -1e6])), z).astype(np.float32)
    assert measure_error_window(verts, tris, garbage, valid, dx, dy) == rep
    # Invalid samples are exactly the ones dropped from the count.
    full = measure_error_window(verts, tris, z, np.ones_like(valid), dx, dy)
    assert full.n_samples - rep.n_samples == int((np.isfinite(vert) & ~valid).sum())


# -- kernel edge cases ---------------------------------------------------------------------------------


def test_empty_and_degenerate_inputs() -> None:
    z = np.zeros((5, 5), np.float32)
    ok = np.ones((5, 5), bool)
    empty = ErrorReport(0.0, 0.0, 0.0, 0)
    assert measure_error_window(np.zeros((0, 3)), np.zeros((0, 3), np.int64), z, ok, 1.0, 1.0) == empty
    # Zero-area triangles cover nothing but are still surface for the Hausdorff distance.
    verts = np.array([[0, 0, 1], [4, 0, 1], [0, 4, 1], [2, 0, 1], [4, 4, 1]], float)
    line = np.array([[0, 3, 1], [2, 2, 0]])  # collinear; repeated vertex
    assert measure_error_window(verts, line, z, ok, 1.0, 1.0) == empty
    tri = np.array([[0, 1, 2]])
    rep = measure_error_window(verts, np.concatenate([tri, line]), z, ok, 1.0, 1.0)
    assert rep.n_samples == 15 and rep.max_vertical_m == 1.0 and rep.hausdorff_m == 1.0
    assert measure_error_window(verts, tri, z, np.zeros_like(ok), 1.0, 1.0) == empty
    # A mesh entirely outside the window covers nothing.
    assert measure_error_window(verts + [100, 0, 0], tri, z, ok, 1.0, 1.0) == empty


def test_steep_wall_hausdorff_is_horizontal() -> None:
    # A step of 100 m between two flat halves, meshed by one ramp: the vertical error is 50 m but every
    # sample is within one sample spacing of the ramp triangle.
    z = np.zeros((9, 9), np.float32)
    z[:, 5:] = 100.0
    ok = np.ones_like(z, dtype=bool)
    verts = np.array([[0, 0, 0], [8, 0, 100], [0, 8, 0], [8, 8, 100]], float)
    tris = np.array([[0, 1, 3], [0, 3, 2]])
    rep = check_against_reference(verts, tris, z, ok, 1.0, 1.0)
    assert rep.max_vertical_m == pytest.approx(50.0)  # ramp at 12.5 m per sample, step at col 4.5
    assert rep.hausdorff_m < 5.0


def test_kernel_returns_window_indices() -> None:
    z = np.zeros((4, 6), np.float32)
    z[2, 3] = 7.0
    ok = np.ones_like(z, dtype=bool)
    verts = np.array([[0, 0, 0], [5, 0, 0], [0, 3, 0], [5, 3, 0]], float)
    out = tile_error(verts, np.array([[0, 1, 3], [0, 3, 2]], np.int64), z, ok, 1.0, 1.0)
    assert out == (7.0, 49.0, 24, 7.0, 2, 3, 2, 3)


# -- world API ---------------------------------------------------------------------------------------


@given(case=cases(kinds=("grid", "delaunay")), data=st.data())
@SETTINGS
def test_world_api_matches_window_kernel(case, data) -> None:
    verts, tris, z, valid, dx, dy = case
    assume(bool(valid.any()))  # a Heightfield refuses an all-nodata grid (tested in test_io)
    x0, y0 = data.draw(st.sampled_from([(0.0, 0.0), (523_000.0, 5_184_000.0), (-1200.5, 30.25)]))
    hf = Heightfield.from_array(z, (dx, dy), origin_m=(x0, y0), valid=valid)
    rows, cols = verts[:, 1] / dy, verts[:, 0] / dx
    wx, wy = hf.world_xy(rows, cols)
    world = np.stack([wx, wy, verts[:, 2]], 1)
    rep = measure_error(world, tris, hf)
    # The round trip world -> sample index -> window frame moves vertices by ulps of the world
    # coordinates; coverage is decided in sample units with lattice snapping, so the covered set is the
    # same and the errors agree to that precision.
    ref = measure_error_window(verts, tris, z, hf.valid, dx, dy)
    tol = 1e-6 * max(1.0, float(np.abs(z).max()))
    assert rep.n_samples == ref.n_samples
    assert rep.max_vertical_m == pytest.approx(ref.max_vertical_m, abs=tol, rel=1e-6)
    assert rep.hausdorff_m == pytest.approx(ref.hausdorff_m, abs=tol, rel=1e-6)
    assert rep.rms_vertical_m == pytest.approx(ref.rms_vertical_m, abs=tol, rel=1e-6)
    # mask restricts further
    mask = np.zeros(z.shape, bool)
    assert measure_error(world, tris, hf, mask=mask).n_samples == 0


def test_world_api_grid_on_samples_covers_every_sample() -> None:
    rng = np.random.default_rng(7)
    z = terrain(rng, 17, 25)
    hf = Heightfield.from_array(z, (30.71, 21.29), origin_m=(612_345.5, 4_987_654.25))
    rr, cc = np.mgrid[0:17:4, 0:25:4]
    wx, wy = hf.world_xy(rr.ravel(), cc.ravel())
    verts = np.stack([wx, wy, z[rr, cc].ravel().astype(np.float64)], 1)
    mr, mc = rr.shape
    idx = np.arange(mr * mc).reshape(mr, mc)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    tris = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])
    rep = measure_error(verts, tris, hf)
    assert rep.n_samples == 17 * 25  # the outer boundary passes exactly through the edge samples
    local = np.stack([cc.ravel() * 30.71, rr.ravel() * 21.29, verts[:, 2]], 1)
    ref = check_against_reference(local, tris, z, np.ones_like(z, dtype=bool), 30.71, 21.29)
    assert rep.max_vertical_m == pytest.approx(ref.max_vertical_m, rel=1e-9)
    assert rep.hausdorff_m == pytest.approx(ref.hausdorff_m, rel=1e-9)
    assert rep.worst_vertical_rc == ref.worst_vertical_rc
    # A mask excluding the worst sample lowers (or keeps) the max, never raises it.
    mask = np.ones(z.shape, bool)
    mask[rep.worst_vertical_rc] = False
    sub = measure_error(verts, tris, hf, mask=mask)
    assert sub.n_samples == rep.n_samples - 1 and sub.max_vertical_m <= rep.max_vertical_m


@pytest.mark.parametrize(
    ("verts", "tris", "match"),
    [
        (np.zeros((3, 2)), [[0, 1, 2]], "Expected vertices of shape"),
        (np.zeros((3, 3)), [[0, 1]], "Expected triangles of shape"),
        (np.zeros((3, 3)), [[0, 1, 3]], r"Expected triangle indices in \[0, 3\)"),
        (np.zeros((3, 3)), [[0, -1, 2]], r"Expected triangle indices in \[0, 3\)"),
        (np.zeros((3, 3)), [[0.0, 1.0, 2.0]], "Expected integer triangle indices"),
        ([[0, 0, 0], [1, 0, np.nan], [0, 1, 0]], [[0, 1, 2]], "Expected finite vertex coordinates"),
    ],
)
def test_bad_input_raises(verts, tris, match) -> None:
    hf = Heightfield.from_array(np.zeros((4, 4), np.float32))
    with pytest.raises(ValueError, match=match):
        measure_error(np.asarray(verts, float), np.asarray(tris), hf)
    with pytest.raises(ValueError, match=match):
        measure_error_window(np.asarray(verts, float), np.asarray(tris), hf.elevation_m, hf.valid, 1.0, 1.0)


def test_bad_window_raises() -> None:
    v, t = np.zeros((3, 3)), np.array([[0, 1, 2]])
    with pytest.raises(ValueError, match="Expected 2-D elevations"):
        measure_error_window(v, t, np.zeros((4, 4)), np.ones((4, 5), bool), 1.0, 1.0)
    with pytest.raises(ValueError, match="Expected positive finite spacing"):
        measure_error_window(v, t, np.zeros((4, 4)), np.ones((4, 4), bool), 0.0, 1.0)
    hf = Heightfield.from_array(np.zeros((4, 4), np.float32))
    with pytest.raises(ValueError, match="Expected a mask of shape"):
        measure_error(v, t, hf, mask=np.ones((3, 3), bool))


# -- golden case on a real DEM -------------------------------------------------------------------------

ALPINE = "dem/srtm1_crop256_alpine.tif"

#: (max_vertical_m, rms_vertical_m, hausdorff_m, n_samples, worst_vertical_rc, worst_hausdorff_rc) of the
#: stride-16 grid (north-west diagonals) and of a seeded Delaunay mesh on the alpine crop.
GOLDEN = {
    "grid16": (266.1875, 36.573135799596116, 253.7796008309767, 58081, (235, 4), (235, 4)),
    "delaunay": (943.5882352941176, 65.17992649143089, 247.3007784812908, 65536, (255, 94), (235, 2)),
}


def _alpine_meshes(path: Path):
    import rasterio

    with rasterio.open(path) as ds:
        z = ds.read(1).astype(np.float32)
    side = json.loads(path.with_suffix(".json").read_text())
    dx, dy = side["horizontal"]["spacing_m"]
    hf = Heightfield.from_array(z, (dx, dy))
    rng = np.random.default_rng(20240601)
    h, w = z.shape
    # stride-16 grid over rows/cols 0..240
    rr, cc = np.mgrid[0:241:16, 0:241:16]
    m = rr.shape[0]
    idx = np.arange(m * m).reshape(m, m)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    grid = (
        np.stack([cc.ravel() * dx, rr.ravel() * dy, z[rr, cc].ravel().astype(np.float64)], 1),
        np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)]),
    )
    # Delaunay of 400 random lattice points plus the corners, heights from the DEM
    pr = np.concatenate([rng.integers(0, h, 400), [0, 0, h - 1, h - 1]])
    pc = np.concatenate([rng.integers(0, w, 400), [0, w - 1, 0, w - 1]])
    pts = np.unique(np.stack([pr, pc], 1), axis=0)
    dverts = np.stack([pts[:, 1] * dx, pts[:, 0] * dy, z[pts[:, 0], pts[:, 1]].astype(np.float64)], 1)
    dela = (dverts, Delaunay(pts[:, ::-1].astype(float)).simplices.astype(np.int64))
    return hf, {"grid16": grid, "delaunay": dela}


def _as_tuple(rep: ErrorReport):
    return (rep.max_vertical_m, rep.rms_vertical_m, rep.hausdorff_m, rep.n_samples, rep.worst_vertical_rc,
            rep.worst_hausdorff_rc)  # fmt: skip


def _alpine(shared_data: Path) -> Path:
    path = shared_data / ALPINE
    if not path.exists():
        pytest.skip(f"{ALPINE} not present in {shared_data}")
    return path


def test_golden_alpine_dem(shared_data: Path) -> None:
    hf, meshes = _alpine_meshes(_alpine(shared_data))
    dx, dy = hf.spacing_m
    for name, (verts, tris) in meshes.items():
        want = GOLDEN[name]
        got = _as_tuple(measure_error_window(verts, tris, hf.elevation_m, hf.valid, dx, dy))
        assert got[3:] == want[3:], name
        assert got[:3] == pytest.approx(want[:3], rel=1e-9), name
        # The same mesh in world coordinates through the public API.
        wx, wy = hf.world_xy(verts[:, 1] / dy, verts[:, 0] / dx)
        got_w = _as_tuple(measure_error(np.stack([wx, wy, verts[:, 2]], 1), tris, hf))
        assert got_w[3:] == want[3:], name
        assert got_w[:3] == pytest.approx(want[:3], rel=1e-9), name


@pytest.mark.parametrize("stride", [1, 2, 4, 8, 16, 32])
def test_real_dem_matches_brute_force(shared_data: Path, stride: int) -> None:
    import rasterio

    with rasterio.open(_alpine(shared_data)) as ds:
        z = ds.read(1).astype(np.float32)
    side = min(max(16 * stride + 1, 33), 97)  # ~2 M sample-triangle pairs for the reference, at most
    z = z[64 : 64 + side, 96 : 96 + side]  # steep slopes
    rng = np.random.default_rng(stride)
    valid = np.ones(z.shape, bool)
    for diag in ("nw", "ne"):
        check_against_reference(*grid_mesh(rng, z, 21.29, 30.71, stride, diag, 0.0), z, valid, 21.29, 30.71)
    n = max(8, ((side - 1) // stride) ** 2)
    check_against_reference(*delaunay_mesh(rng, z, 21.29, 30.71, n, 0.0, False), z, valid, 21.29, 30.71)


if __name__ == "__main__":  # regenerate GOLDEN
    import os

    data = Path(
        os.environ.get("TERRALOD_SHARED_DATA", Path(__file__).resolve().parents[1] / ".." / "shared" / "data")
    )
    hf, meshes = _alpine_meshes(data / ALPINE)
    for name, (verts, tris) in meshes.items():
        print(
            f'    "{name}": {_as_tuple(measure_error_window(verts, tris, hf.elevation_m, hf.valid, *hf.spacing_m))!r},'
        )
