"""Parallel detail-increment builds (paper 003 §2.1, one heap per sub-block): the same model and file bytes
for 1 and 2 threads and on Dask workers; one block gives exactly the former single-heap collapses; the
per-block collapses keep the whole TIN a manifold with no flipped triangle and no gap at every scale; the
edge-topology kernel and the pieced LZMA2 stream agree with their plain references."""

from __future__ import annotations

import hashlib
import lzma
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from terralod.errors import InputError
from terralod.kernels.qem import FREE, edge_topology
from terralod.tin import DetailIncrementModel
from terralod.tin.delaunay import delaunay_tin, split_sub_blocks
from terralod.tin.fileformat import LZMA_PIECE_BYTES, _pack, _unpack
from terralod.tin.qem import block_jobs, measured_errors, run_block, simplify, simplify_blocks

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data"
AUTZEN = SHARED / "lidar" / "autzen_trim.laz"
HYP = settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def _cloud(seed: int, n: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0.0, 1000.0, (n, 2)) + np.array([500000.0, 4100000.0])
    x, y = xy[:, 0] - 500000.0, xy[:, 1] - 4100000.0
    z = 40.0 * np.sin(x / 130.0) * np.cos(y / 170.0) + rng.normal(0.0, 2.0, n) + 200.0
    return np.c_[xy, z]


def _tin(seed: int, n: int, k: int):
    v, t, _ = delaunay_tin(_cloud(seed, n))
    return v, t, split_sub_blocks(v, t, k)


def _log_arrays(log, err) -> dict[str, np.ndarray]:
    d = {f: getattr(log, f) for f in log.__dataclass_fields__}
    d["error"] = err
    return d


def _area2(v: np.ndarray, t: np.ndarray) -> np.ndarray:
    a, b, c = v[t[:, 0]], v[t[:, 1]], v[t[:, 2]]
    return (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])


@HYP
@given(seed=st.integers(0, 10_000), n=st.integers(40, 600), k=st.sampled_from([1, 2, 3]),
       base=st.sampled_from([0.2, 0.5]))  # fmt: skip
def test_threads_give_the_same_collapses_and_one_block_is_the_single_heap(seed, n, k, base) -> None:
    v, t, sb = _tin(seed, n, k)
    one = simplify_blocks(v, t, sb.kind, sb.tri_block, base_fraction=base, n_blocks=k * k, workers=1)
    two = simplify_blocks(v, t, sb.kind, sb.tri_block, base_fraction=base, n_blocks=k * k, workers=2)
    a, b = _log_arrays(*one), _log_arrays(*two)
    for f in a:
        assert np.array_equal(a[f], b[f]), f
    # a build's log (the fields its records read, the others dropped as each block ends): the same
    lean = _log_arrays(*simplify_blocks(v, t, sb.kind, sb.tri_block, base_fraction=base, n_blocks=k * k,
                                        workers=2, keep_rewrites=False))  # fmt: skip
    dropped = {"cost", "del_slot", "rep_slot", "rep_old", "rep_new"}
    for f in a:
        assert lean[f].size == 0 if f in dropped else np.array_equal(a[f], lean[f]), f
    log, err = one
    # each block's collapses are its job's alone (run apart, they are the same) and remove FREE vertices
    # of that block only
    nb, make = block_jobs(v, t, sb.kind, sb.tri_block, base_fraction=base, n_blocks=k * k)
    for blk in range(nb):
        job = make(blk)
        sel = log.block == blk
        if job is None:
            assert not sel.any()
            continue
        r = run_block(job)
        assert np.array_equal(job.verts[r.out[1]], log.u[sel]) and np.array_equal(
            job.verts[r.out[2]], log.v[sel]
        )
        assert np.array_equal(r.error_m, err[sel])
    assert (sb.kind[log.u] == FREE).all() and (sb.vert_block[log.u] == log.block).all()
    # per-block measured errors are the whole-TIN replay's
    assert np.array_equal(err, measured_errors(v, t, log))
    if k == 1:  # one block: exactly the former single heap (same collapses, MMQE, errors, base)
        old = simplify(v, t, sb.kind, sb.tri_block, sb.vert_block, base_fraction=base, single_heap=True)
        for f in ("u", "v", "block", "mmqe_m2", "cost", "mmqe0_m2", "del_slot", "del_tri", "rep_ptr",
                  "rep_slot", "rep_old", "rep_new", "base_tris", "base_alive"):  # fmt: skip
            assert np.array_equal(getattr(old, f), getattr(log, f)), f
        assert np.array_equal(measured_errors(v, t, old), err)


@HYP
@given(seed=st.integers(0, 10_000), n=st.integers(60, 500), k=st.sampled_from([2, 3]))
def test_per_block_collapses_keep_the_whole_tin_valid_at_every_scale(seed, n, k) -> None:
    """Each block tests the link condition on its own mesh: the whole TIN stays a manifold, counter-
    clockwise, covering the same area, at every global scale (the base included)."""
    pts = _cloud(seed, n)
    m = DetailIncrementModel.from_points(pts, sub_blocks=k * k, workers=2)
    full = None
    for s in sorted({0, m.n_scales - 1, *np.linspace(0, m.n_scales - 1, 6).astype(int).tolist()}):
        v, tri = m.mesh_at(int(s))
        tri = tri.astype(np.int64)
        area2 = _area2(v, tri)
        assert (area2 > 0).all()
        repeated, _ = edge_topology(tri, v.shape[0])
        assert not repeated
        full = area2.sum() if full is None else full
        assert np.isclose(area2.sum(), full, rtol=1e-9)


def _model_arrays(m: DetailIncrementModel) -> dict[str, np.ndarray]:
    inc = m.increments
    d = {n: getattr(inc, n) for n in ("block_ptr", "del_slot", "del_tri", "rep_ptr", "rep_slot", "rep_old",
                                      "rep_new", "mmqe_m2", "error_m", "rank")}  # fmt: skip
    d.update(vertices=m.vertices_m, base=m._base_tris, alive=m._base_alive, boxes=m.block_boxes_m)
    return d


@pytest.mark.skipif(not AUTZEN.exists(), reason=f"real LiDAR not present at {SHARED}")
def test_autzen_model_and_file_are_the_same_for_1_and_2_workers(tmp_path: Path) -> None:
    ms = [DetailIncrementModel.from_las(AUTZEN, sub_blocks=9, workers=w) for w in (1, 2)]
    a, b = (_model_arrays(m) for m in ms)
    for f in a:
        assert np.array_equal(a[f], b[f]), f
    digests = []
    for i, m in enumerate(ms):
        p = tmp_path / f"m{i}.tin"
        m.save(p, workers=i + 1)
        digests.append(hashlib.sha256(p.read_bytes()).hexdigest())
        back = DetailIncrementModel.load(p)
        for f, x in _model_arrays(back).items():
            assert np.array_equal(x, a[f]), f
    assert digests[0] == digests[1]


def test_dask_cli_build_is_byte_identical_to_a_local_build(tmp_path: Path) -> None:
    """``terralod build cloud.las -o x.terra --dask local --dask-workers 2`` stores the local build's model
    bytes (the sub-blocks simplified on two worker processes)."""
    pytest.importorskip("dask.distributed", reason="dask[distributed] is not installed")
    from click.testing import CliRunner

    from terralod.cli import cli
    from terralod.store import read_tin_store
    from test_tin_cli import write_las

    las = write_las(tmp_path / "c.las", _cloud(7, 3000))
    blobs = []
    for name, extra in (("local", ["--workers", "1"]), ("dask", ["--dask", "local", "--dask-workers", "2"])):
        out = tmp_path / f"{name}.terra"
        r = CliRunner().invoke(cli, ["build", str(las), "-o", str(out), "--sub-blocks", "9", *extra])
        assert r.exit_code == 0, r.output
        blobs.append(read_tin_store(out)[1])
    assert blobs[0] == blobs[1]


def test_unreachable_scheduler_is_one_line(tmp_path: Path) -> None:
    pytest.importorskip("dask.distributed", reason="dask[distributed] is not installed")
    from terralod.tin.distributed import open_client

    with pytest.raises(InputError, match="cannot reach the Dask scheduler"):
        open_client("tcp://127.0.0.1:9", timeout_s=1.0)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(3, 200), flip=st.floats(0.0, 0.3))
def test_edge_topology_matches_the_sorting_reference(seed: int, n: int, flip: float) -> None:
    v, t, _ = delaunay_tin(_cloud(seed, n)) if n >= 3 else (None, None, None)
    rng = np.random.default_rng(seed)
    t = t.astype(np.int64)
    keep = rng.random(t.shape[0]) > 0.2  # holes
    t = t[keep] if keep.any() else t
    f = rng.random(t.shape[0]) < flip  # inconsistent orientation
    t[f] = t[f][:, ::-1]
    nv = int(v.shape[0])
    e = np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]])
    directed = e[:, 0] * nv + e[:, 1]
    und = np.minimum(e[:, 0], e[:, 1]) * nv + np.maximum(e[:, 0], e[:, 1])
    uniq, cnt = np.unique(und, return_counts=True)
    outline = np.zeros(nv, bool)
    outline[uniq[cnt == 1] // nv] = outline[uniq[cnt == 1] % nv] = True
    repeated, got = edge_topology(t, nv)
    assert repeated == (np.unique(directed).size != directed.size)
    assert np.array_equal(got, outline)


@pytest.mark.parametrize("pieces", [0.0, 0.3, 1.0, 1.001, 3.02])
def test_pieced_lzma_stream_is_one_stream_for_any_thread_count(pieces: float, monkeypatch) -> None:
    import terralod.tin.fileformat as ff

    assert LZMA_PIECE_BYTES == 1 << 21
    piece = 1 << 14  # small pieces, the same code path
    monkeypatch.setattr(ff, "LZMA_PIECE_BYTES", piece)
    n = int(pieces * piece)
    rng = np.random.default_rng(n)
    raw = (rng.integers(0, 7, n, dtype=np.uint8) * 3).tobytes()
    outs = {_pack(raw, w) for w in (1, 2, 3)}
    assert len(outs) == 1
    out = outs.pop()
    assert _unpack(out, "x") == raw
    # the standard raw LZMA2 decoder reads it in one go; one piece is coded exactly as before
    filters = [{"id": lzma.FILTER_LZMA2, "preset": 9}]
    assert lzma.decompress(out, format=lzma.FORMAT_RAW, filters=filters) == raw
    if n <= piece:
        assert out == lzma.compress(raw, format=lzma.FORMAT_RAW, filters=filters)


def test_writer_codes_a_whole_piece_as_preset_9_does() -> None:
    """The writer's one-piece dictionary gives preset 9's bytes: no match reaches beyond a piece."""
    import terralod.tin.fileformat as ff

    rng = np.random.default_rng(5)
    walk = np.cumsum(rng.integers(-3, 4, LZMA_PIECE_BYTES // 4)).astype("<i4")  # a coded column's like
    raw = walk.tobytes()
    assert len(raw) == LZMA_PIECE_BYTES
    filters = [{"id": lzma.FILTER_LZMA2, "preset": 9}]
    assert ff._pack(raw, 1) == lzma.compress(raw, format=lzma.FORMAT_RAW, filters=filters)


def test_two_distinct_points_are_refused() -> None:
    with pytest.raises(InputError, match="got 2"):
        delaunay_tin(np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 2.0], [1.0, 0.0, 3.0]]))
    with pytest.raises(InputError, match="got 1"):
        delaunay_tin(np.zeros((4, 3)))


def _tri_set(v: np.ndarray, t: np.ndarray) -> set[tuple[tuple[float, ...], ...]]:
    return {tuple(sorted(tuple(v[i, :2]) for i in tri)) for tri in t}


triangle_missing = pytest.mark.skipif(
    not __import__("terralod.tin.delaunay", fromlist=["_triangle_available"])._triangle_available(),
    reason="Shewchuk's Triangle is not installed (the fast-tin extra); Qhull alone is in use",
)


@triangle_missing
@HYP
@given(seed=st.integers(0, 10_000), n=st.integers(3, 800), grid=st.booleans())
def test_triangle_and_qhull_give_the_same_tin(seed: int, n: int, grid: bool) -> None:
    """Points in general position have one Delaunay triangulation: Triangle and Qhull find it (same
    vertices, same triangles, all counter-clockwise). On a lattice (cocircular quads) the diagonals may
    differ; both still cover the same hull with the same vertices and no fold-over."""
    import terralod.tin.delaunay as dl

    pts = _cloud(seed, n)
    if grid:  # a lattice: the cocircular case
        pts[:, :2] = np.round(pts[:, :2] / 100.0) * 100.0
    out = {}
    try:
        for engine in ("triangle", "qhull"):
            dl.ENGINE = engine
            try:
                out[engine] = delaunay_tin(pts)
            except InputError as exc:
                out[engine] = str(exc)
    finally:
        dl.ENGINE = "triangle"
    a, b = out["triangle"], out["qhull"]
    if isinstance(a, str) or isinstance(b, str):
        assert isinstance(a, str) and isinstance(b, str), (a, b)  # both refuse (too few / collinear)
        return
    (va, ta, _), (vb, tb, _) = a, b
    assert (_area2(va, ta) > 0).all() and (_area2(vb, tb) > 0).all()
    assert np.isclose(_area2(va, ta).sum(), _area2(vb, tb).sum(), rtol=1e-12)
    assert {tuple(p) for p in va[:, :2]} == {tuple(p) for p in vb[:, :2]} or grid
    if not grid:  # the same triangles, in the same (canonical) order: the same arrays
        assert _tri_set(va, ta) == _tri_set(vb, tb)
        assert np.array_equal(va, vb) and np.array_equal(ta, tb)


@triangle_missing
@pytest.mark.parametrize("engine", ["triangle", "qhull"])
def test_collinear_points_are_refused_by_both_engines(engine: str, monkeypatch) -> None:
    import terralod.tin.delaunay as dl

    monkeypatch.setattr(dl, "ENGINE", engine)
    line = np.c_[np.arange(50.0), 3.0 * np.arange(50.0) + 7.0, np.ones(50)]
    with pytest.raises(InputError, match="collinear"):
        delaunay_tin(line, source="line.laz")
