"""Detail-increment TIN model (paper 003): reconstruction is exact and reversible, every intermediate scale
is a manifold TIN with no flipped triangle and no gap, merged records give the same scales, files are
checksummed, degenerate point sets get clear errors, and the SVO rule picks finer scales nearer the eye."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from terralod.errors import CorruptStoreError, InputError
from terralod.tin import DetailIncrementModel

from conftest import fractal_terrain

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def _cloud(seed: int, n: int, relief_m: float = 40.0) -> np.ndarray:
    """Random xy over 1 km² with a smooth surface plus noise, metres."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0.0, 1000.0, (n, 2)) + np.array([500000.0, 4100000.0])
    x, y = xy[:, 0] - 500000.0, xy[:, 1] - 4100000.0
    z = relief_m * np.sin(x / 130.0) * np.cos(y / 170.0) + rng.normal(0.0, relief_m * 0.05, n) + 200.0
    return np.c_[xy, z]


def _xy_area2(v: np.ndarray, t: np.ndarray) -> np.ndarray:
    a, b, c = v[t[:, 0]], v[t[:, 1]], v[t[:, 2]]
    return (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])


def _check_tin(v: np.ndarray, t: np.ndarray, full_area2: float) -> None:
    """Manifold (every directed edge once, every undirected edge in at most two triangles), every triangle
    counter-clockwise with positive area, and the same covered area as the full TIN (no gap, no overlap)."""
    t = t.astype(np.int64)
    area2 = _xy_area2(v, t)
    assert (area2 > 0).all(), f"{int((area2 <= 0).sum())} flipped or degenerate triangles"
    e = np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]])
    n = int(v.shape[0])
    directed = e[:, 0] * n + e[:, 1]
    assert np.unique(directed).size == directed.size, "a directed edge is used twice (fold or non-manifold)"
    und = np.minimum(e[:, 0], e[:, 1]) * n + np.maximum(e[:, 0], e[:, 1])
    assert np.unique(und, return_counts=True)[1].max() <= 2
    assert np.isclose(area2.sum(), full_area2, rtol=1e-9, atol=1e-6), "covered area changed: gap or overlap"


def _full_state(m: DetailIncrementModel) -> np.ndarray:
    m.mesh_at(m.n_scales - 1)
    return m.triangles().copy()


def _canonical(t: np.ndarray) -> np.ndarray:
    """Triangles as a set: each triple rotated to start at its smallest index (orientation kept), rows
    sorted."""
    t = np.asarray(t, np.int64)
    rot = (np.argmin(t, axis=1)[:, None] + np.arange(3)) % 3
    c = np.take_along_axis(t, rot, axis=1)
    return c[np.lexsort(c.T[::-1])]


@settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    seed=st.integers(0, 2**31 - 1),
    n=st.integers(12, 600),
    blocks=st.sampled_from([1, 4, 9]),
    base=st.floats(0.05, 0.6),
)
def test_scales_are_exact_reversible_and_watertight(seed: int, n: int, blocks: int, base: float) -> None:
    m = DetailIncrementModel.from_points(_cloud(seed, n), sub_blocks=blocks, base_fraction=base)
    full = m._full_tris
    assert m.n_slots == full.shape[0]
    # refining the base fully reproduces the input triangulation exactly, as a set of oriented triangles
    assert np.array_equal(_canonical(_full_state(m)), _canonical(full))
    full_area2 = float(_xy_area2(m.vertices_m, full.astype(np.int64)).sum())
    rng = np.random.default_rng(seed)
    nmax = m.increments.block_n_records()
    # the base has about base_fraction of each block's triangles (blocks with few free vertices stop above)
    v0, t0 = m.mesh_at(0)
    assert t0.shape[0] <= full.shape[0]
    _check_tin(v0, t0, full_area2)
    for _ in range(4):
        # a global scale, then independent per-block scales
        g = int(rng.integers(0, m.n_scales))
        v, t = m.mesh_at(g)
        _check_tin(v, t, full_area2)
        per = np.array([rng.integers(0, k + 1) for k in nmax], np.int64)
        v, t = m.mesh_at(per)
        _check_tin(v, t, full_area2)
        # coarsen, then refine back: the same state, slot for slot
        before = m.triangles().copy()
        m.mesh_at(np.array([rng.integers(0, s + 1) for s in per], np.int64))
        m.mesh_at(per)
        assert np.array_equal(m.triangles(), before)
    # MMQE per block is monotone: finer scales never have a larger error
    for b in range(m.n_blocks):
        mm = m.mmqe_m2(b)
        assert mm.size == nmax[b] + 1 and (np.diff(mm) <= 0).all()


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), k=st.integers(2, 7))
def test_merged_records_reconstruct_the_same_scales(seed: int, k: int) -> None:
    """§2.2.2 compression: the model whose records each merge k collapses reaches S_0, S_k, S_2k, … with
    exactly the triangles of the raw model at those scales, forwards and backwards."""
    m = DetailIncrementModel.from_points(_cloud(seed, 300), sub_blocks=4, base_fraction=0.2)
    c = m.compressed(k)
    nmax = m.increments.block_n_records()
    assert np.array_equal(c.increments.block_n_records(), -(-nmax // k))
    rng = np.random.default_rng(seed)
    steps = [np.array([rng.integers(0, -(-x // k) + 1) for x in nmax]) for _ in range(5)]
    for j in steps + steps[::-1]:
        _, tc = c.mesh_at(j)
        _, tm = m.mesh_at(np.minimum(j * k, nmax))
        assert np.array_equal(tc, tm)
    # fewer records, fewer (or as many) stored triangle changes
    assert c.increments.del_slot.size + c.increments.rep_slot.size <= (
        m.increments.del_slot.size + m.increments.rep_slot.size
    )


def test_save_load_roundtrip_and_checksum(tmp_path: Path) -> None:
    m = DetailIncrementModel.from_points(_cloud(7, 2000), sub_blocks=4)
    path = tmp_path / "m.tdim"
    size = m.save(path)
    assert size == path.stat().st_size
    r = DetailIncrementModel.load(path)
    assert r.n_scales == m.n_scales and r.n_blocks == m.n_blocks
    for s in (0, m.n_scales // 3, m.n_scales - 1, 5):
        assert np.array_equal(r.mesh_at(s)[1], m.mesh_at(s)[1])
        assert np.array_equal(r.mesh_at(s)[0], m.mesh_at(s)[0])
    for b in range(m.n_blocks):
        assert np.array_equal(r.mmqe_m2(b), m.mmqe_m2(b))
    # every record of the paper's table 1 survives the file, new triples included
    for b in range(m.n_blocks):
        for a, c in zip(m.records(b), r.records(b), strict=True):
            assert a.level_index == c.level_index and a.mmqe_value == c.mmqe_value
            for f in (
                "deleted_tri",
                "deleted_tri_vex",
                "replaced_tri",
                "replaced_tri_vex_ori",
                "replaced_tri_vex_new",
            ):
                assert np.array_equal(getattr(a, f), getattr(c, f)), f
    # merged records use the general layout (original triples stored); they survive the file too
    c = m.compressed(4)
    c.save(tmp_path / "c.tdim")
    rc = DetailIncrementModel.load(tmp_path / "c.tdim")
    for s in (0, c.n_scales // 2, c.n_scales - 1):
        assert np.array_equal(rc.mesh_at(s)[1], c.mesh_at(s)[1])
    # the text scheme export
    m.export_text(tmp_path / "m.txt")
    assert (tmp_path / "m.txt").read_text().splitlines()[0].strip() == "1"
    # one flipped byte in the payload is caught by the checksum
    raw = bytearray(path.read_bytes())
    raw[len(raw) // 2] ^= 0x40
    bad = tmp_path / "bad.tdim"
    bad.write_bytes(bytes(raw))
    with pytest.raises(CorruptStoreError, match="bad.tdim"):
        DetailIncrementModel.load(bad)
    # a truncated file and a foreign file
    (tmp_path / "short.tdim").write_bytes(bytes(raw[:100]))
    with pytest.raises(CorruptStoreError):
        DetailIncrementModel.load(tmp_path / "short.tdim")
    (tmp_path / "foreign.tdim").write_text("hello, not a model\n" * 10)
    with pytest.raises(CorruptStoreError):
        DetailIncrementModel.load(tmp_path / "foreign.tdim")


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(12, 800), blocks=st.sampled_from([1, 4, 9]),
       k=st.sampled_from([1, 3]))  # fmt: skip
def test_compact_file_gives_every_table1_field(
    tmp_path_factory, seed: int, n: int, blocks: int, k: int
) -> None:
    """The file stores vertex splits, not table 1: loading derives every record field, slot and MMQE of
    the model that was saved, merged or not; the full scale is the input TIN."""
    m = DetailIncrementModel.from_points(_cloud(seed, n), sub_blocks=blocks).compressed(k)
    path = tmp_path_factory.mktemp("f") / "m.tdim"
    m.save(path)
    r = DetailIncrementModel.load(path)
    a, b = m.increments, r.increments
    assert a.step == b.step == k
    for f in ("block_ptr", "del_ptr", "del_slot", "del_tri", "rep_ptr", "rep_slot", "rep_old", "rep_new",
              "mmqe_m2", "rank", "error_m"):  # fmt: skip
        assert np.array_equal(getattr(a, f), getattr(b, f)), f
    assert np.array_equal(r.block_boxes_m, m.block_boxes_m)
    assert np.array_equal(r._base_tris[r._base_alive], m._base_tris[m._base_alive])
    assert np.array_equal(_canonical(r.mesh_at(r.n_scales - 1)[1]), _canonical(m._full_tris))


def test_inconsistent_or_old_files_are_refused(tmp_path: Path) -> None:
    """A file whose checksum is right but whose splits do not fit the mesh, and a version-1 file, get one
    clear CorruptStoreError."""
    from terralod.tin.fileformat import _HEADER, MAGIC, write_container

    m = DetailIncrementModel.from_points(_cloud(5, 500), sub_blocks=4)
    meta, arrays = m._payload()
    for field, change in (("split_u", 10**6), ("split_v", 7), ("split_j", 50), ("split_after", 50),
                          ("split_j", -10), ("base_rows", 10**7)):  # fmt: skip
        bad = dict(arrays)
        bad[field] = arrays[field].astype(np.int64).copy()
        bad[field].reshape(-1)[bad[field].size // 2] += change
        write_container(tmp_path / "bad.tdim", meta, bad)
        with pytest.raises(CorruptStoreError, match="bad.tdim.*(record|does not fit|inconsistent)"):
            DetailIncrementModel.load(tmp_path / "bad.tdim")
    m.save(tmp_path / "m.tdim")
    raw = bytearray((tmp_path / "m.tdim").read_bytes())
    head = list(_HEADER.unpack_from(raw))
    head[1] = 1
    raw[: _HEADER.size] = _HEADER.pack(*head)
    assert bytes(raw[:8]) == MAGIC
    (tmp_path / "old.tdim").write_bytes(bytes(raw))
    with pytest.raises(CorruptStoreError, match="version 1 is no longer read"):
        DetailIncrementModel.load(tmp_path / "old.tdim")
    for old in (2, 4):  # 2 had no measured error, 4 stored the splits as plain indices, deflated
        head[1] = old
        raw[: _HEADER.size] = _HEADER.pack(*head)
        (tmp_path / "old.tdim").write_bytes(bytes(raw))
        with pytest.raises(CorruptStoreError, match=f"old.tdim.*version {old} is no longer read"):
            DetailIncrementModel.load(tmp_path / "old.tdim")


@pytest.mark.parametrize(
    ("points", "message"),
    [
        (np.zeros((2, 3)), "at least 3"),
        (np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 2.0], [0.0, 0.0, 3.0], [0.0, 0.0, 4.0]]), "at least 3"),
        (np.c_[np.arange(10.0), 2.0 * np.arange(10.0), np.ones(10)], "collinear"),
        (np.array([[0.0, 0.0, 1.0], [1.0, np.nan, 2.0], [0.0, 1.0, 3.0], [1.0, 1.0, 1.0]]), "NaN|finite"),
        (np.ones((5, 2)), "3"),
    ],
)
def test_degenerate_points_get_clear_errors(points: np.ndarray, message: str) -> None:
    with pytest.raises(InputError, match=message):
        DetailIncrementModel.from_points(points, source="cloud.laz")


def test_svo_rule_refines_near_the_eye() -> None:
    """Per-sub-block scales from the smallest-visible-object rule: a block nearer the eye never gets a
    coarser scale than the same block seen from farther, and every selected scale meets N pixels unless
    it is the block's finest."""
    from terralod.tin.svo import svo_length_px

    m = DetailIncrementModel.from_points(_cloud(3, 4000, relief_m=80.0), sub_blocks=9)
    centre = m.block_centres_m.mean(axis=0)
    prev = None
    for height in (20000.0, 5000.0, 1500.0, 400.0):
        eye = centre + np.array([0.0, 0.0, height])
        s = m.scales_for_camera(eye, 60.0, 1080, 2.0, error="mmqe")
        d = np.linalg.norm(m.block_centres_m - eye, axis=1)
        for b in range(m.n_blocks):
            mm = m.mmqe_m2(b)
            px = svo_length_px(mm[s[b]], d[b], np.radians(60.0), 1080)
            assert px <= 2.0 or s[b] == mm.size - 1
            if s[b] > 0:  # the next coarser scale would not have met the rule
                assert svo_length_px(mm[s[b] - 1], d[b], np.radians(60.0), 1080) > 2.0
        if prev is not None:
            assert (s >= prev).all()
        prev = s
        v, t = m.mesh_for_camera(eye, 60.0, 1080, 2.0, error="mmqe")
        assert np.array_equal(m.block_scales, s)
    assert prev is not None and prev.sum() > 0


def _vertical_error_per_block(m: DetailIncrementModel) -> np.ndarray:
    """(B,) max over the input points of |z - surface| under the model's current TIN, grouped by the
    sub-block of the triangle holding each point (brute force: every point against every triangle)."""
    from terralod.runtime.tin import slot_blocks

    v = m.vertices_m
    slots = np.flatnonzero(m._alive)
    t = m._tris[slots].astype(np.int64)
    blk = slot_blocks(m)[slots]
    a, b, c = v[t[:, 0]], v[t[:, 1]], v[t[:, 2]]
    det = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    out = np.zeros(m.n_blocks)
    for p in v:
        qx, qy = p[0] - a[:, 0], p[1] - a[:, 1]
        l1 = (qx * (c[:, 1] - a[:, 1]) - qy * (c[:, 0] - a[:, 0])) / det
        l2 = ((b[:, 0] - a[:, 0]) * qy - (b[:, 1] - a[:, 1]) * qx) / det
        l0 = 1.0 - l1 - l2
        inside = np.minimum(l0, np.minimum(l1, l2)) >= -1e-9
        z = l0 * a[:, 2] + l1 * b[:, 2] + l2 * c[:, 2]
        for k in np.flatnonzero(inside):
            out[blk[k]] = max(out[blk[k]], abs(p[2] - z[k]))
    return out


@settings(max_examples=10, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    seed=st.integers(0, 2**31 - 1),
    n=st.integers(60, 400),
    blocks=st.sampled_from([1, 4]),
    relief=st.floats(1.0, 200.0),
    pick=st.floats(0.0, 1.0),
)
def test_stored_error_bounds_the_measured_error(
    seed: int, n: int, blocks: int, relief: float, pick: float
) -> None:
    """The stored measured error of every sub-block's scale is at least the max vertical distance, measured
    independently, from the input points to that scale's surface; it falls to 0 at full resolution, never
    grows from coarse to fine, and merged records keep it at their scales."""
    m = DetailIncrementModel.from_points(_cloud(seed, n, relief_m=relief), sub_blocks=blocks)
    nb = m.increments.block_n_records()
    rng = np.random.default_rng(seed)
    for scales in (np.zeros(m.n_blocks, np.int64), np.round(pick * nb).astype(np.int64),
                   rng.integers(0, nb + 1), nb):  # fmt: skip
        m.set_block_scales(scales)
        got = _vertical_error_per_block(m)
        stored = np.array([m.error_m(b)[scales[b]] for b in range(m.n_blocks)])
        assert (got <= stored * (1 + 1e-12) + 1e-9).all(), (got, stored)
    for b in range(m.n_blocks):
        e = m.error_m(b)
        assert e[-1] == 0.0 and (np.diff(e) <= 0).all()
    k4 = m.compressed(4)
    for b in range(m.n_blocks):
        assert np.array_equal(
            k4.error_m(b), m.error_m(b)[np.minimum(np.arange(k4.block_n_scales[b]) * 4, nb[b])]
        )


def test_measured_rule_refines_near_the_eye_and_meets_n_pixels() -> None:
    """error="measured" (the default): every selected scale's measured error, seen from the nearest point of
    the sub-block's box, projects to at most N pixels, the next coarser scale would not, a nearer eye never
    coarsens a sub-block, and an eye close above the terrain gets more triangles than a far one."""
    from terralod.tin.svo import box_distance_m, projected_px

    m = DetailIncrementModel.from_points(_cloud(3, 4000, relief_m=80.0), sub_blocks=9)
    centre = m.block_centres_m.mean(axis=0)
    prev, tris = None, []
    for height in (20000.0, 5000.0, 1500.0, 400.0, 50.0):
        eye = centre + np.array([0.0, 0.0, height])
        s = m.scales_for_camera(eye, 60.0, 1080, 2.0)
        d = box_distance_m(m.block_boxes_m, eye)
        px = m.projected_error_px(eye, 60.0, 1080, s)
        for b in range(m.n_blocks):
            e = m.error_m(b)
            assert px[b] == pytest.approx(projected_px(e[s[b]], d[b], np.radians(60.0), 1080))
            assert px[b] <= 2.0 or s[b] == e.size - 1
            if s[b] > 0:
                assert projected_px(e[s[b] - 1], d[b], np.radians(60.0), 1080) > 2.0
        if prev is not None:
            assert (s >= prev).all()
        prev = s
        tris.append(m.mesh_for_camera(eye, 60.0, 1080, 2.0)[1].shape[0])
    assert tris[-1] > tris[0]
    with pytest.raises(ValueError, match="measured.*mmqe"):
        m.scales_for_camera(centre, 60.0, 1080, 2.0, error="max")


def test_heightfield_model_full_scale_is_the_grid_tin() -> None:
    from terralod import Heightfield

    z = fractal_terrain(40, 50, 5, relief_m=200.0)
    hf = Heightfield.from_array(z, 10.0, origin_m=(300000.0, 5000000.0))
    m = DetailIncrementModel.from_heightfield(hf, sub_blocks=4)
    v, t = m.mesh_at(m.n_scales - 1)
    assert t.shape[0] == 2 * 39 * 49 and v.shape[0] == 40 * 50
    assert np.allclose(np.sort(v[:, 2]), np.sort(z.ravel().astype(np.float64)))
    v0, t0 = m.mesh_at(0)
    assert t0.shape[0] < 0.35 * t.shape[0]


@pytest.mark.skipif(not (SHARED / "lidar" / "autzen_trim.laz").exists(),
                    reason=f"real LiDAR not present at {SHARED} (../shared/data beside the repository)")  # fmt: skip
def test_real_laz_ground_model() -> None:
    """Autzen (LAZ, international feet): ground points in metres, and the model's full scale is exactly
    its Delaunay TIN; the base is a valid TIN of the same footprint."""
    m = DetailIncrementModel.from_las(SHARED / "lidar" / "autzen_trim.laz", sub_blocks=4)
    v = m.vertices_m
    assert 20_000 < v.shape[0] <= 26_107  # ground class only (26,107 of 110,000 points)
    # metres: the ground lies at 406-434 ft (international feet), 123.8-132.3 m
    assert 123.0 < v[:, 2].min() and v[:, 2].max() < 133.0
    assert any("foot" in n for n in m.notes) and any("ground" in n for n in m.notes)
    full = m._full_tris
    area2 = float(_xy_area2(v, full.astype(np.int64)).sum())
    assert np.array_equal(_canonical(_full_state(m)), _canonical(full))
    for s in (0, m.n_scales // 2):
        _check_tin(*m.mesh_at(s), area2)


@pytest.mark.parametrize("weight", [-1.0, float("nan"), float("inf")])
def test_bad_vertical_weight_is_refused(weight: float) -> None:
    from terralod.tin.qem import simplify_mesh

    m = DetailIncrementModel.from_points(_cloud(1, 200), sub_blocks=1)
    with pytest.raises(InputError, match="vertical_weight"):
        simplify_mesh(m.vertices_m, m._full_tris, target_triangles=50, vertical_weight=weight)


def test_both_costs_reach_the_target_with_valid_tins() -> None:
    """The default cost (quadric + vertical term) and the paper's (quadric alone) both stop at the target
    with every triangle counter-clockwise and the covered area kept."""
    from terralod.tin.qem import simplify_mesh

    m = DetailIncrementModel.from_points(_cloud(2, 1500, relief_m=60.0), sub_blocks=1)
    full = m._full_tris
    total = _xy_area2(m.vertices_m, full.astype(np.int64)).sum()
    for w in (None, 0.0):
        v, t = simplify_mesh(m.vertices_m, full, target_triangles=600, vertical_weight=w)
        assert t.shape[0] <= 601
        area2 = _xy_area2(v, t.astype(np.int64))
        assert (area2 > 0).all() and area2.sum() == pytest.approx(total, rel=1e-9)


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    n=st.integers(0, 400),
    cols=st.sampled_from([0, 1, 3]),
    distinct=st.integers(1, 50),
    special=st.booleans(),
)
def test_float_coding_is_bit_exact(seed: int, n: int, cols: int, distinct: int, special: bool) -> None:
    """Float arrays in a file come back bit for bit (signed zeros, NaN, infinities, subnormals included),
    whether a column is coded by its distinct values or stored as it is."""
    from terralod.tin.fileformat import _decode_arrays, _encode_arrays

    rng = np.random.default_rng(seed)
    pool = rng.normal(0.0, 1000.0, distinct)
    if special:
        pool = np.concatenate([pool, [0.0, -0.0, np.nan, np.inf, -np.inf, 5e-324, -1.7e308]])
    shape = (n,) if cols == 0 else (n, cols)
    a = rng.choice(pool, shape) if rng.random() < 0.7 else rng.normal(0.0, 1e5, shape)
    b = _decode_arrays(_encode_arrays({"a": a}, True), True, "t.tdim")["a"]
    assert b.shape == a.shape and b.dtype == np.float64
    assert np.array_equal(a.view(np.int64), b.view(np.int64))


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), h=st.integers(3, 40), w=st.integers(3, 40), blocks=st.sampled_from([1, 4, 9]),
       flat=st.booleans())  # fmt: skip
def test_grid_models_survive_the_split_coder(
    tmp_path_factory, seed: int, h: int, w: int, blocks: int, flat: bool
) -> None:
    """Grid TINs put removed vertices exactly on edges of the coarser mesh (zero orientations in the coder's
    walk): every record, slot and scale still comes back from the file, with no escape needed for most."""
    from terralod import Heightfield

    rng = np.random.default_rng(seed)
    z = np.zeros((h, w)) if flat else np.round(rng.normal(0.0, 5.0, (h, w)).cumsum(axis=0), 1)
    hf = Heightfield.from_array(z.astype(np.float32), 10.0, origin_m=(500000.0, 5300000.0))
    m = DetailIncrementModel.from_heightfield(hf, sub_blocks=blocks)
    path = tmp_path_factory.mktemp("g") / "g.tdim"
    m.save(path)
    r = DetailIncrementModel.load(path)
    a, b = m.increments, r.increments
    for f in ("block_ptr", "del_slot", "del_tri", "rep_ptr", "rep_slot", "rep_old", "rep_new", "mmqe_m2", "error_m",
              "rank"):  # fmt: skip
        assert np.array_equal(getattr(a, f), getattr(b, f)), f
    assert np.array_equal(r._base_tris[r._base_alive], m._base_tris[m._base_alive])
    sym_v = m._payload()[1]["split_v"]
    assert (sym_v == 3).sum() <= max(2, sym_v.size // 10)


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1), n=st.integers(0, 300), nv=st.integers(1, 10**6), canonical=st.booleans()
)
def test_mesh_rows_coding_is_exact(seed: int, n: int, nv: int, canonical: bool) -> None:
    """Delta-coded triangle rows (the base mesh in a file, every mesh of the benchmark's pyramid) decode to
    the same rows, in any order; canonical rows keep every triangle and its orientation."""
    from terralod.tin.fileformat import decode_mesh_rows, encode_mesh_rows
    from terralod.tin.records import canonical_rows

    t = np.random.default_rng(seed).integers(0, nv, (n, 3)).astype(np.int32)
    if canonical:
        c = canonical_rows(t)
        assert c.shape == t.shape and (c[:, 0] <= c[:, 1:].min(axis=1, initial=nv)).all()
        assert np.array_equal(c, _canonical(t))
        t = c
    assert np.array_equal(decode_mesh_rows(encode_mesh_rows(t)), t.astype(np.int64))


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(12, 400), blocks=st.sampled_from([1, 4]),
       scramble=st.floats(0.0, 1.0))  # fmt: skip
def test_split_coder_roundtrips_with_any_geometry(seed: int, n: int, blocks: int, scramble: float) -> None:
    """The split coder only predicts from geometry: with vertex positions partly scrambled (walks that fail,
    triangles that do not hold v, escapes), encoding then decoding still gives every split back."""
    from terralod.kernels.tincodec import split_codes
    from terralod.tin.increments import _grid_xy, _insert_order

    m = DetailIncrementModel.from_points(_cloud(seed, n), sub_blocks=blocks)
    inc = m.increments
    rng = np.random.default_rng(seed)
    q = _grid_xy(m.vertices_m)
    pick = rng.random(q.shape[0]) < scramble
    q[pick] = rng.integers(0, 2**26, (int(pick.sum()), 2))
    label = np.full(q.shape[0], inc.n_blocks, np.int64)
    label[inc.rec_u] = inc.record_block
    vpos, vat, lo, hi = _insert_order(label, inc.n_blocks)
    base = m._base_tris[m._base_alive]
    u, v, x1 = inc.rec_u.astype(np.int64), inc.rec_v.astype(np.int64), inc.del_tri[0::2, 2].astype(np.int64)
    mm = np.diff(inc.rep_ptr)
    sym = [np.zeros(inc.n_records, np.int64) for _ in range(6)]
    z = m.vertices_m[:, 2].copy()
    none = (np.zeros((0, 3), np.int32), np.zeros(0, np.int64))
    status, n_esc, *_ = split_codes(True, q, z, label, base, inc.block_ptr, vpos, vat, lo, hi, u, v, x1, mm, *sym,
                                    False, *none)  # fmt: skip
    assert status == 0 and n_esc == int((sym[1] == 3).sum())
    out = [np.zeros(inc.n_records, np.int64) for _ in range(4)]
    del_tri, rep_ptr = np.zeros((2 * inc.n_records, 3), np.int32), np.zeros(inc.n_records + 1, np.int64)
    status, n_dec, rep_slot, rep_old, rep_new = split_codes(
        False, q, z, label, base, inc.block_ptr, vpos, vat, lo, hi, *out, *sym[:4], sym[4][:n_esc], sym[5][:n_esc],
        True, del_tri, rep_ptr,
    )  # fmt: skip
    assert status == 0 and n_dec == n_esc
    for a, b in zip(out, (u, v, x1, mm), strict=True):
        assert np.array_equal(a, b)
    # what the decoder says each split does to the mesh is what the replay of the same splits derives
    n = int(rep_ptr[-1])
    assert np.array_equal(rep_ptr, inc.rep_ptr) and np.array_equal(del_tri, inc.del_tri)
    for a, b in ((rep_slot[:n], inc.rep_slot), (rep_old[:n], inc.rep_old), (rep_new[:n], inc.rep_new)):
        assert np.array_equal(a, b)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(12, 600), blocks=st.sampled_from([1, 4, 9]))
def test_splits_coded_beside_the_build_give_the_same_file(
    tmp_path_factory, seed: int, n: int, blocks: int
) -> None:
    """A built model's file, whose split codes were computed on a thread beside the records' replay, has
    the bytes of the same model coded after the build (the save's own pass), for any thread count."""
    d = tmp_path_factory.mktemp("ahead")
    m = DetailIncrementModel.from_points(_cloud(seed, n), sub_blocks=blocks)
    assert m._splits_ahead is not None
    m.save(d / "ahead.tdim", workers=2)
    m._splits_ahead = None
    m.save(d / "after.tdim", workers=1)
    assert (d / "ahead.tdim").read_bytes() == (d / "after.tdim").read_bytes()


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), sizes=st.lists(st.integers(0, 6_000), min_size=1, max_size=5),
       workers=st.sampled_from([None, 1, 2, 3]))  # fmt: skip
def test_streamed_container_has_the_bytes_of_the_whole_one(tmp_path_factory, seed: int, sizes: list[int],
                                                           workers: int | None) -> None:  # fmt: skip
    """write_container_stream (arrays one by one, whole LZMA2 pieces coded as they are known) writes the
    bytes of write_container, including payloads of several pieces and a piece boundary inside an array;
    a wrong array count raises and writes nothing. Pieces of 16 KiB instead of 2 MiB: the same cases
    (arrays of up to 24 KB as packed: up to 8 pieces, boundaries inside arrays) at 1/64 of the bytes LZMA
    codes."""
    from unittest import mock

    from terralod.tin import fileformat as F

    with mock.patch.object(F, "LZMA_PIECE_BYTES", 1 << 14):
        _streamed_equals_whole(F, tmp_path_factory.mktemp("stream"), seed, sizes, workers)


def _streamed_equals_whole(F, d: Path, seed: int, sizes: list[int], workers: int | None) -> None:  # noqa: N803
    rng = np.random.default_rng(seed)
    arrays = {f"a{i}": rng.integers(0, 1 << 20, s).astype(np.int64) for i, s in enumerate(sizes)}
    whole = d / "whole.bin"
    F.write_container(whole, {"k": 1}, arrays, workers=1)
    plain = F._uvarint(len(b'{"k":1}')) + b'{"k":1}' + F._array_section(arrays)
    assert whole.read_bytes()[F._HEADER.size :] == F._pack(plain, 1)  # the one-shot coder's bytes
    streamed = d / "streamed.bin"
    F.write_container_stream(streamed, {"k": 1}, len(arrays), iter(arrays.items()), workers=workers)
    assert streamed.read_bytes() == whole.read_bytes()
    assert np.array_equal(F.read_container(streamed)[1][f"a{len(sizes) - 1}"], arrays[f"a{len(sizes) - 1}"])
    with pytest.raises(ValueError, match="Expected 9 arrays"):
        F.write_container_stream(d / "wrong.bin", {"k": 1}, 9, iter(arrays.items()))
    assert not (d / "wrong.bin").exists()


@settings(max_examples=20, deadline=None)
@given(
    seed=st.integers(0, 10_000), n=st.integers(1, 400_000), kind=st.sampled_from(["walk", "noise", "steps"])
)
def test_float_coding_estimate_tracks_the_compressed_size(seed: int, n: int, kind: str) -> None:
    """The estimate that picks a float column's coding is zlib level 1 of the column, or of evenly spaced
    chunks of a long one scaled to its length: the same on the same bytes, exact for short columns and
    within a quarter of the whole column's zlib level 1 size for long ones (smooth, noisy or stepped
    data, shuffled as the file shuffles them); the file still round-trips whichever coding it picks."""
    import zlib

    from terralod.tin import fileformat as ff

    rng = np.random.default_rng(seed)
    if kind == "walk":
        a = np.cumsum(rng.normal(0.0, 1.0, n))
    elif kind == "noise":
        a = rng.uniform(-1e3, 1e3, n)
    else:
        a = np.repeat(rng.normal(0.0, 50.0, n // 500 + 1), 500)[:n]
    raw = ff._shuffle(a.astype("<f8"))
    est = ff._estimate(raw)
    assert est == ff._estimate(bytes(raw))
    full = len(zlib.compress(raw, 1))
    if len(raw) <= ff._ESTIMATE_BYTES:
        assert est == full
    else:
        assert 0.75 * full <= est <= 1.25 * full
    back = ff._decode_floats(ff._encode_floats(a), a.shape, "t")
    assert np.array_equal(back.view(np.int64), a.view(np.int64))
