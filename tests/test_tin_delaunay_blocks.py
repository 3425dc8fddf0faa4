"""The Delaunay triangulation computed block by block (terralod.tin.delaunay_blocks): the same triangles as
one call in general position, a valid Delaunay triangulation among co-circular points and duplicates, the
same bytes on any number of threads and on Dask workers."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

pytest.importorskip("triangle", reason="Shewchuk's Triangle is not installed: the blocks need it")

from terralod.kernels.delaunay import canonical_order, orient_ccw  # noqa: E402
from terralod.kernels.qem import edge_topology  # noqa: E402
from terralod.tin import delaunay_blocks as db  # noqa: E402
from terralod.tin.delaunay import delaunay_tin  # noqa: E402

HYP = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def _blocks(
    xy: np.ndarray, per: int, threads: int = 1, reverse: bool = False
) -> tuple[np.ndarray, db.BlockLayout]:
    """The block pipeline on ``xy`` with ``per`` points a block (jobs run in reverse order when asked:
    the result must not depend on the order they finish in)."""
    from concurrent.futures import ThreadPoolExecutor

    layout = db.block_layout(xy, per)
    jobs = db.block_jobs(xy, layout)
    order = jobs[::-1] if reverse else jobs
    with ThreadPoolExecutor(threads) as pool:
        got = {r.block: r for r in pool.map(db.block_triangles, order)}
    tris = db.fill_holes(xy, [got[j.block] for j in jobs])
    assert tris is not None
    return tris, layout


def _tri_set(tris: np.ndarray) -> set[tuple[int, ...]]:
    return {tuple(t) for t in np.sort(tris, axis=1).tolist()}


def _area2(xy: np.ndarray, t: np.ndarray) -> np.ndarray:
    a, b, c = xy[t[:, 0]], xy[t[:, 1]], xy[t[:, 2]]
    return (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])


def _hull_area2(xy: np.ndarray) -> float:
    from scipy.spatial import ConvexHull

    return 2.0 * ConvexHull(xy).volume


def _cloud(kind: str, seed: int, n: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    if kind == "uniform":
        return rng.uniform(-500.0, 500.0, (n, 2))
    if kind == "clusters":  # dense clumps and sparse gaps: big circles, most of them left to the fill
        centres = rng.uniform(-500.0, 500.0, (5, 2))
        return centres[rng.integers(0, 5, n)] + rng.normal(0.0, 40.0, (n, 2))
    if kind == "strip":  # a long thin cloud: cores far wider than tall
        return np.c_[rng.uniform(0.0, 5000.0, n), rng.uniform(0.0, 30.0, n)]
    raise AssertionError(kind)


def _is_delaunay_exact(xy_int: np.ndarray, tris: np.ndarray) -> bool:
    """No point strictly inside any triangle's circumcircle: exact int64 in-circle tests (coordinates
    below 2^10, so the determinant's terms stay far below 2^63), the candidates found with a k-d tree."""
    from scipy.spatial import cKDTree

    p = xy_int.astype(np.int64)
    a, b, c = p[tris[:, 0]], p[tris[:, 1]], p[tris[:, 2]]
    f = p.astype(np.float64)
    bx, by = f[tris[:, 1], 0] - f[tris[:, 0], 0], f[tris[:, 1], 1] - f[tris[:, 0], 1]
    cx, cy = f[tris[:, 2], 0] - f[tris[:, 0], 0], f[tris[:, 2], 1] - f[tris[:, 0], 1]
    d = 2.0 * (bx * cy - by * cx)
    ux = (cy * (bx * bx + by * by) - by * (cx * cx + cy * cy)) / d
    uy = (bx * (cx * cx + cy * cy) - cx * (bx * bx + by * by)) / d
    centre = f[tris[:, 0]] + np.c_[ux, uy]
    radius = np.hypot(ux, uy)
    tree = cKDTree(f)
    for t, near in enumerate(tree.query_ball_point(centre, radius * (1 + 1e-9) + 1e-9)):
        for q in near:
            if q in tris[t]:
                continue
            ad, bd, cd = a[t] - p[q], b[t] - p[q], c[t] - p[q]
            det = (
                (ad[0] * ad[0] + ad[1] * ad[1]) * (bd[0] * cd[1] - cd[0] * bd[1])
                - (bd[0] * bd[0] + bd[1] * bd[1]) * (ad[0] * cd[1] - cd[0] * ad[1])
                + (cd[0] * cd[0] + cd[1] * cd[1]) * (ad[0] * bd[1] - bd[0] * ad[1])
            )
            if det > 0:  # counter-clockwise triangle: > 0 is strictly inside
                return False
    return True


@HYP
@given(seed=st.integers(0, 10_000), n=st.integers(50, 3000), per=st.integers(30, 800),
       kind=st.sampled_from(["uniform", "clusters", "strip"]))  # fmt: skip
def test_blocks_give_the_one_delaunay_triangulation_in_general_position(seed, n, per, kind) -> None:
    """Random points (almost surely no four co-circular): the blocks' kept triangles plus the fill are
    exactly the triangles of one Triangle call, each once, counter-clockwise."""
    import triangle

    xy = _cloud(kind, seed, n)
    tris, layout = _blocks(xy, per, threads=2)
    ref = np.asarray(triangle.triangulate({"vertices": xy}, "Q")["triangles"], np.int64)
    assert _tri_set(tris) == _tri_set(ref)
    assert tris.shape[0] == ref.shape[0]  # no triangle twice
    assert (_area2(xy, tris) > 0).all()


@HYP
@given(seed=st.integers(0, 10_000), w=st.integers(3, 60), h=st.integers(3, 60), per=st.integers(20, 400),
       drop=st.floats(0.0, 0.6), dups=st.integers(0, 50))  # fmt: skip
def test_blocks_on_a_lattice_with_holes_and_duplicates_are_a_delaunay_triangulation(
    seed, w, h, per, drop, dups
) -> None:
    """Integer lattices (every cell's four corners co-circular) with random gaps and exact duplicates:
    every distinct point is used (the lowest row of duplicates), the triangles are counter-clockwise,
    cover the convex hull exactly once (area, and every directed edge once), and no point lies strictly
    inside any triangle's circumcircle (exact integer test)."""
    rng = np.random.default_rng(seed)
    xx, yy = np.meshgrid(np.arange(w) * 7, np.arange(h) * 5)
    xy = np.c_[xx.ravel(), yy.ravel()].astype(np.float64)
    xy = xy[rng.random(xy.shape[0]) >= drop]
    if xy.shape[0] < 3 or np.unique(xy[:, 0]).size < 2 or np.unique(xy[:, 1]).size < 2:
        return
    if dups:
        xy = np.concatenate([xy, xy[rng.integers(0, xy.shape[0], dups)]])
        xy = xy[rng.permutation(xy.shape[0])]
    tris, layout = _blocks(xy, per, threads=2)
    first = np.unique(xy, axis=0, return_index=True)[1]
    assert np.array_equal(np.unique(tris), np.sort(first))  # each distinct point once, its lowest row
    assert (_area2(xy, tris) > 0).all()
    assert _area2(xy, tris).sum() == pytest.approx(_hull_area2(xy), rel=1e-12)
    repeated, _ = edge_topology(np.ascontiguousarray(tris, np.int64), xy.shape[0])
    assert not repeated
    assert _is_delaunay_exact(xy, tris)


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 1000))
def test_blocks_do_not_depend_on_threads_or_finishing_order(seed) -> None:
    """A jittered lattice with exact co-circular cells left in: 1 thread in order, 3 threads in reverse
    order, the same triangles in the same order (bytes)."""
    rng = np.random.default_rng(seed)
    xx, yy = np.meshgrid(np.arange(80.0), np.arange(70.0))
    xy = np.c_[xx.ravel(), yy.ravel()]
    jit = rng.random(xy.shape[0]) < 0.5
    xy[jit] += rng.uniform(-0.3, 0.3, (int(jit.sum()), 2))
    a, _ = _blocks(xy, 500, threads=1)
    b, _ = _blocks(xy, 500, threads=3, reverse=True)
    assert a.tobytes() == b.tobytes()


def test_points_by_block_lists_every_point_its_halo_reaches() -> None:
    """Each block's points are exactly those inside its core grown by the halo (closed), ascending."""
    rng = np.random.default_rng(3)
    xy = rng.uniform(0.0, 100.0, (5000, 2))
    layout = db.block_layout(xy, 300)
    jobs = db.block_jobs(xy, layout)
    assert len(jobs) == layout.m**2 and layout.m == 4
    for j in jobs:
        x0, x1, y0, y1 = j.known
        want = np.flatnonzero((xy[:, 0] >= x0) & (xy[:, 0] <= x1) & (xy[:, 1] >= y0) & (xy[:, 1] <= y1))
        assert np.array_equal(j.index, want)
        assert np.array_equal(j.xy, xy[want])


def test_triangulate_xy_matches_the_triangle_package_and_honours_segments() -> None:
    """The GIL-free ctypes call gives the package's triangles and neighbours; with segments (p) every
    segment is an edge of the result and no point is added."""
    import triangle

    rng = np.random.default_rng(11)
    xy = rng.uniform(0.0, 10.0, (400, 2))
    t, nbr, n_out = db.triangulate_xy(xy)
    ref = triangle.triangulate({"vertices": xy}, "nQ")
    assert np.array_equal(t, ref["triangles"]) and np.array_equal(nbr, ref["neighbors"]) and n_out == 400
    seg = np.array([[0, 1], [2, 3], [4, 5]])
    t, nbr, n_out = db.triangulate_xy(xy, seg, hull=True)
    edges = {
        tuple(sorted(e)) for tri in t.tolist() for e in ((tri[0], tri[1]), (tri[1], tri[2]), (tri[2], tri[0]))
    }
    crossing = [s for s in seg.tolist() if tuple(sorted(s)) not in edges]
    assert n_out >= 400 and (n_out > 400 or not crossing)  # a crossing pair of segments adds a point
    assert (_area2(np.asarray(xy), t[(t < 400).all(axis=1)]) > 0).all()


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(1, 300))
def test_orient_ccw_kernel_matches_the_numpy_rule(seed, n) -> None:
    """Counter-clockwise triples and their doubled area, zero-area triples dropped: as numpy computes it."""
    rng = np.random.default_rng(seed)
    xy = np.round(rng.uniform(0.0, 4.0, (12, 2)))  # small integers: many collinear triples
    t = rng.integers(0, 12, (n, 3)).astype(np.int64)
    out, area2 = orient_ccw(xy, t)
    a = _area2(xy, t)
    flip = a < 0
    want = t.copy()
    want[flip, 1], want[flip, 2] = t[flip, 2], t[flip, 1]
    keep = np.abs(a) > 0
    assert np.array_equal(out, want[keep]) and np.array_equal(area2, np.abs(a)[keep])


def test_delaunay_tin_uses_blocks_on_threads_and_on_dask_workers(monkeypatch, tmp_path) -> None:
    """delaunay_tin with small blocks: the single call's arrays (general position), the same bytes on
    1 and 2 threads, and on a LocalCluster's worker processes through the Dask executor; a whole model
    built on the workers saves the local model's bytes."""
    pytest.importorskip("dask.distributed", reason="dask[distributed] is not installed")
    from terralod.tin import DetailIncrementModel
    from terralod.tin.distributed import close_client, dask_executor, open_client

    rng = np.random.default_rng(8)
    pts = np.c_[rng.uniform(0.0, 2000.0, (6000, 2)) + [500000.0, 4100000.0], rng.normal(100.0, 5.0, 6000)]
    single = delaunay_tin(pts)
    monkeypatch.setattr(db, "POINTS_PER_BLOCK", 600)
    one = delaunay_tin(pts, workers=1)
    two = delaunay_tin(pts, workers=2)
    # general position: the same triangles, and (canonical order) the same arrays
    assert all(np.array_equal(x, y) for x, y in zip(one, single, strict=True))
    assert all(np.array_equal(x, y) for x, y in zip(one, two, strict=True))
    local_model = DetailIncrementModel.from_points(pts, sub_blocks=9, workers=2)
    client = open_client("local", 2)
    try:
        on_dask = delaunay_tin(pts, executor=dask_executor(client))
        dask_model = DetailIncrementModel.from_points(pts, sub_blocks=9, executor=dask_executor(client))
    finally:
        close_client(client)
    assert all(np.array_equal(x, y) for x, y in zip(one, on_dask, strict=True))
    # the whole model (blocks' Delaunay, then the sub-blocks simplified on the workers): the same file
    local_model.save(tmp_path / "local.tin")
    dask_model.save(tmp_path / "dask.tin")
    assert (tmp_path / "local.tin").read_bytes() == (tmp_path / "dask.tin").read_bytes()


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(3, 2000))
def test_canonical_order_depends_on_the_triangle_set_only(seed, n) -> None:
    """Shuffled and rotated copies of a triangulation give the same array: each triangle starts at its
    smallest vertex with its orientation kept, sorted by its first two vertices."""
    import triangle

    rng = np.random.default_rng(seed)
    xy = rng.uniform(0.0, 100.0, (n, 2))
    t = np.asarray(triangle.triangulate({"vertices": xy}, "Q").get("triangles", np.zeros((0, 3))), np.int32)
    if t.shape[0] == 0:
        return
    a = canonical_order(t, n)
    shuffled = t[rng.permutation(t.shape[0])]
    shuffled = np.take_along_axis(shuffled, (rng.integers(0, 3, (t.shape[0], 1)) + np.arange(3)) % 3, 1)
    b = canonical_order(shuffled, n)
    assert a.dtype == t.dtype and np.array_equal(a, b)
    assert (a[:, 0] < a[:, 1]).all() and (a[:, 0] < a[:, 2]).all()
    assert _tri_set(a) == _tri_set(t) and (_area2(xy, a) > 0).all()
    key = a[:, 0].astype(np.int64) * n + a[:, 1]
    assert (np.diff(key) > 0).all()
