"""Rendering on the real GPU path (EGL; Mesa llvmpipe where there is no GPU): rendered crack test on a
magenta background, golden images with a tolerance, and the viewer in a real window under Xvfb.

Regenerate the golden images with ``TERRALOD_REGEN_GOLDEN=1 python -m pytest tests/test_render.py``.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from terralod import Camera, Engine, Heightfield, build_store, open_store, sample_heightfield

from conftest import fractal_terrain

# Reproducible images: force Mesa's EGL even on a machine with a GPU (DESIGN.md).
_MESA = "/usr/share/glvnd/egl_vendor.d/50_mesa.json"
if os.path.exists(_MESA):
    os.environ.setdefault("__EGL_VENDOR_LIBRARY_FILENAMES", _MESA)

GOLDEN = Path(__file__).resolve().parent / "golden"
MAGENTA = (1.0, 0.0, 1.0)


def _renderer(w: int, h: int):
    try:
        from terralod.render import TerrainRenderer

        return TerrainRenderer(w, h)
    except Exception as exc:  # noqa: BLE001 - report why the GPU path is unavailable
        pytest.fail(f"EGL/OpenGL context could not be created ({exc}); .ci/run installs Mesa's EGL")


@pytest.fixture(scope="module", params=["chunked", "cohesion"])
def rough_store(tmp_path_factory, request) -> Path:
    """A rough terrain built by each tile mesher (cohesion tiles have relocated, non-uniform borders)."""
    z = fractal_terrain(513, 513, 21, relief_m=900.0, beta=2.6)
    hf = Heightfield.from_array(z, 20.0, origin_m=(400000.0, 5300000.0))
    out = tmp_path_factory.mktemp("r") / f"rough_{request.param}.terra"
    build_store(hf, out, tile_size=17, method=request.param)
    return out


def _magenta_pixels(img: np.ndarray) -> int:
    return int(((img[..., 0] > 200) & (img[..., 1] < 60) & (img[..., 2] > 200)).sum())


def _chain_leaves(pyramid, px: float, py: float) -> list[tuple[int, int, int]]:
    """A partition refined only toward source sample (py, px): finest tiles there, every coarser level
    beside them, so LoD differences of up to L - 1 meet along the refined chain's edges."""
    leaves = [(0, 0, 0)]
    while True:
        hit = [c for c in leaves if c[0] < pyramid.max_level and _contains(pyramid, c, px, py)]
        if not hit:
            return leaves
        leaves.remove(hit[0])
        leaves += pyramid.children(hit[0])


def _contains(pyramid, code, px, py) -> bool:
    r0, c0 = pyramid.origin_rc(code)
    span = pyramid.span(code[0])
    return c0 <= px < c0 + span and r0 <= py < r0 + span


def _top_views(store, px: float, py: float):
    """Cameras above sample (py, px) looking down, steep enough that terrain fills the frame."""
    t = store.transform
    x, y = t.c + (px + 0.5) * t.a, t.f + (py + 0.5) * t.e
    zmax = max(r["z_max_m"] for r in store.tile_summaries() if r["level"] == 0)
    for height, dx, dy in ((600.0, 0.0, 1.0), (1400.0, 1.0, 0.3), (1100.0, -0.5, -1.0), (900.0, 0.2, -0.4)):
        eye = np.array([x - 0.3 * height * dx, y - 0.3 * height * dy, zmax + height])
        yield eye, np.array([x, y, zmax - 2.0 * height])


def test_rendered_crack_test_forced_lod_differences(rough_store: Path) -> None:
    """Leaf sets with LoD differences 1..4 across tile borders, stitched, drawn over magenta: no hole."""
    from terralod.render import RenderSettings
    from terralod.runtime import stitch_leaves

    st = RenderSettings(background=MAGENTA, fog=False)
    r, r_raw = _renderer(320, 240), _renderer(320, 240)
    seen = set()
    unstitched = 0
    with open_store(rough_store) as store:
        pyr = store.pyramid
        half = pyr.span(1)
        for px, py in ((half - 3.0, half * 0.5 + 7), (half + 2.0, half * 1.3), (half * 0.5 + 5, half - 2.0)):
            leaves = _chain_leaves(pyr, px, py)
            meshes = stitch_leaves(store, leaves)
            for c in leaves:
                for d in ("L", "R", "U", "D"):
                    off = {"L": (-1, 0), "R": (1, 0), "U": (0, -1), "D": (0, 1)}[d]
                    for o in leaves:
                        if o[0] < c[0] and _contains(pyr, o, *_edge_probe(pyr, c, off)):
                            seen.add(c[0] - o[0])
            stitched = [(c, v, t, n) for c, (v, t, n) in meshes.items()]
            raw = [(c, store.tile(*c).vertices, store.tile(*c).triangles, None) for c in leaves]
            for eye, tgt in _top_views(store, px, py):
                img = r.render(stitched, eye, tgt, fov_y_deg=50.0, settings=st)
                assert img.mean() > 20, "frame is black"
                assert _magenta_pixels(img) == 0, f"{_magenta_pixels(img)} crack pixels, eye {eye}"
                unstitched += _magenta_pixels(r_raw.render(raw, eye, tgt, fov_y_deg=50.0, settings=st))
    assert {1, 2, 3, 4} <= seen, f"LoD differences seen across borders: {sorted(seen)}"
    assert unstitched > 0, "the unstitched control shows no crack: the test could not see one"
    r.release()
    r_raw.release()


def _edge_probe(pyr, code, off) -> tuple[float, float]:
    """A sample position just across the middle of one edge of ``code``."""
    r0, c0 = pyr.origin_rc(code)
    span = pyr.span(code[0])
    px = c0 + span / 2 + off[0] * (span / 2 + 0.5)
    py = r0 + span / 2 + off[1] * (span / 2 + 0.5)
    return px, py


def test_rendered_crack_test_engine_path(rough_store: Path) -> None:
    """The engine's own selections along a camera path, drawn over magenta: no hole in the terrain."""
    from terralod.render import RenderSettings

    r = _renderer(320, 240)
    st = RenderSettings(background=MAGENTA, fog=False)
    levels_seen = set()
    with open_store(rough_store) as store:
        engine = Engine(store, threshold_px=24.0)
        pyr = store.pyramid
        for k, (px, py) in enumerate(((100.0, 120.0), (300.0, 260.0), (400.0, 90.0), (250.0, 420.0))):
            for eye, tgt in _top_views(store, px, py):
                cam = Camera(tuple(eye), tuple(tgt), (0, 0, 1.0), 50.0, 320, 240, near_m=1.0)
                sel = engine.update(cam)
                levels_seen |= {c[0] for c in sel.tiles}
                img = r.render(list(sel.meshes()), eye, tgt, fov_y_deg=50.0, settings=st)
                assert _magenta_pixels(img) == 0, f"{_magenta_pixels(img)} crack pixels, view {k}"
    assert len(levels_seen) >= 2 and pyr.max_level >= 4
    r.release()


def _golden(name: str, img: np.ndarray) -> None:
    from PIL import Image

    path = GOLDEN / f"{name}.png"
    if os.environ.get("TERRALOD_REGEN_GOLDEN") or not path.exists():
        if not os.environ.get("TERRALOD_REGEN_GOLDEN") and os.environ.get("CI"):
            pytest.fail(f"golden image {path.name} missing; regenerate with TERRALOD_REGEN_GOLDEN=1")
        Image.fromarray(img).save(path)
        return
    ref = np.asarray(Image.open(path).convert("RGB")).astype(np.int16)
    diff = np.abs(ref - img.astype(np.int16))
    assert ref.shape == img.shape
    assert diff.mean() < 1.5 and np.percentile(diff.max(axis=2), 99.5) < 40, (
        f"{name}: mean diff {diff.mean():.2f}, p99.5 {np.percentile(diff.max(axis=2), 99.5)}"
    )


def test_golden_sample_frames(tmp_path: Path) -> None:
    from terralod.render import RenderSettings
    from terralod.render.offscreen import FrameRenderer, auto_path

    build_store(sample_heightfield(), tmp_path / "s.terra", tile_size=33, method="chunked")
    with open_store(tmp_path / "s.terra") as s:
        for mode in ("elevation", "lod"):
            fr = FrameRenderer(s, 320, 180, threshold_px=1.0, settings=RenderSettings(mode=mode))
            img = fr.frame(auto_path(s, 5)[3])
            assert len({c[0] for c in fr.engine.update(fr.camera(auto_path(s, 5)[3])).tiles}) >= 2
            # not black, not empty: sky and terrain both present
            sky = np.abs(img.astype(int) - np.array([168, 199, 235])).sum(axis=2) < 12
            assert 0.05 < sky.mean() < 0.9 and img.std() > 10
            _golden(f"sample_overview_{mode}", img)
            fr.close()


@pytest.mark.skipif(shutil.which("xvfb-run") is None, reason="xvfb-run not installed (Debian package xvfb)")
def test_viewer_window_under_xvfb(tmp_path: Path) -> None:
    build_store(sample_heightfield(), tmp_path / "v.terra", tile_size=33)
    shot = tmp_path / "shot.png"
    env = {k: v for k, v in os.environ.items() if k != "DISPLAY"}
    p = subprocess.run(
        ["xvfb-run", "-a", "-s", "-screen 0 1024x768x24", sys.executable, "-m", "terralod", "view",
         str(tmp_path / "v.terra"), "--size", "480x270", "--frames", "4", "--screenshot", str(shot),
         "--cull", "backface", "--cull", "region"],
        capture_output=True, text=True, timeout=300, env=env,
    )  # fmt: skip
    assert p.returncode == 0, p.stderr[-2000:]
    out = json.loads(p.stdout.strip().splitlines()[-1])
    stats, hud = out["stats"], out["hud"]
    assert out["frames"] == 4
    # the HUD shows the engine's own numbers
    assert f"tiles {stats['tiles']}" in hud[1] and f"triangles {stats['triangles']:,}" in hud[1]
    assert f"max screen error {stats['max_screen_error_px']:.2f} px" in hud[2]
    assert f"select {stats['select_ms']:.2f} ms" in hud[3] and f"stitch {stats['stitch_ms']:.2f} ms" in hud[3]
    from PIL import Image

    img = np.asarray(Image.open(shot).convert("RGB"))
    assert img.shape == (270, 480, 3) and img.std() > 10 and img.mean() > 30


def test_renderer_updates_changed_vertices_in_place() -> None:
    """A re-stitched tile (same topology, new border heights) is written into its buffer, not re-uploaded,
    and only the changed vertex runs are written; the frame equals a fresh upload of the new geometry."""
    from terralod.render import RenderSettings

    r = _renderer(160, 120)
    r2 = _renderer(160, 120)
    n = 9
    yy, xx = np.mgrid[0:n, 0:n] * 10.0
    v = np.stack([xx.ravel(), -yy.ravel(), np.sin(xx.ravel() / 17.0) * 5], 1)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    tris = np.concatenate([np.stack([a, c, d], 1), np.stack([a, d, b], 1)]).astype(np.uint32)
    eye, tgt = (40.0, -140.0, 90.0), (40.0, -40.0, 0.0)
    st = RenderSettings(fog=False)
    r.render([((3, 0, 0), v, tris, None)], eye, tgt, settings=st)
    v2 = v.copy()
    v2[idx[:, -1].ravel(), 2] += 3.0  # move the east border, as stitching does
    img = r.render([((3, 0, 0), v2, tris, None)], eye, tgt, settings=st)
    assert r.uploads == 1 and r.updates == 1
    assert 0 < r.bytes_written < v.shape[0] * 24  # only part of the buffer was written
    ref = r2.render([((3, 0, 0), v2, tris, None)], eye, tgt, settings=st)
    assert np.array_equal(img, ref)
    r.release()
    r2.release()


def test_indirect_and_plain_draws_give_identical_frames(rough_store: Path) -> None:
    """One multi-draw-indirect call per frame (shared arenas) draws the same pixels as a draw per tile,
    along a camera path whose selections change, in every colour mode, under a memory budget small
    enough that tiles are evicted and re-uploaded."""
    from terralod.render import RenderSettings, TerrainRenderer

    plain = TerrainRenderer(256, 192, draw_mode="plain")
    ind = TerrainRenderer(256, 192, draw_mode="indirect", memory_budget_bytes=120_000)
    with open_store(rough_store) as store:
        eng = Engine(store, threshold_px=1.0)
        t = store.transform
        x0, y0 = t.c, t.f
        w, h = store.pyramid.span(0) * t.a, store.pyramid.span(0) * -t.e
        evicted_before = None
        for k, mode in enumerate(["elevation", "lod", "error", "elevation", "lod", "elevation"]):
            f = k / 5.0
            eye = np.array([x0 + w * (0.2 + 0.6 * f), y0 - h * 1.1, 2600.0 - 1500.0 * f])
            tgt = np.array([x0 + w * 0.5, y0 - h * (0.3 + 0.3 * f), 0.0])
            sel = eng.update(Camera(eye, tgt, (0, 0, 1), 50.0, 256, 192))
            meshes = list(sel.meshes())
            colours = {c: (0.1 * (i % 10), 0.5, 0.9) for i, (c, *_) in enumerate(meshes)}
            st = RenderSettings(mode=mode, fog=k % 2 == 0, wireframe=k == 4)
            a = plain.render(meshes, eye, tgt, fov_y_deg=50.0, settings=st, tile_colours=colours)
            b = ind.render(meshes, eye, tgt, fov_y_deg=50.0, settings=st, tile_colours=colours)
            assert a.std() > 5, "frame is flat"
            assert np.array_equal(a, b), f"frame {k} ({mode}): {(a != b).any(axis=2).sum()} pixels differ"
            assert ind.gpu_bytes <= max(120_000, sum(v.shape[0] * 24 + t.size * 4 for _, v, t, _ in meshes))
            evicted_before = evicted_before or ind.uploads > len(meshes)
    assert ind.draw_calls == 6 and plain.draw_calls > 6
    assert evicted_before, "the budget never forced an eviction"
    plain.release()
    ind.release()


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.booleans(), st.integers(1, 40)), min_size=1, max_size=80))
def test_arena_allocations_never_overlap(ops) -> None:
    """The first-fit arena behind the shared buffers: live blocks never overlap, stay inside the
    capacity, and freeing everything coalesces back to one free block."""
    from terralod.render.renderer import _Arena

    arena = _Arena(200)
    live: list[tuple[int, int]] = []
    for alloc, n in ops:
        if alloc or not live:
            start = arena.alloc(n)
            if start is None:
                arena.grow(arena.capacity + n)
                start = arena.alloc(n)
            assert start is not None
            live.append((start, n))
        else:
            arena.release(*live.pop(len(live) // 2))
        spans = sorted(live)
        for (s0, n0), (s1, _) in zip(spans, spans[1:], strict=False):
            assert s0 + n0 <= s1
        assert all(0 <= s and s + n <= arena.capacity for s, n in spans)
        assert arena.used == sum(n for _, n in live)
    for blk in live:
        arena.release(*blk)
    assert arena.free == [[0, arena.capacity]] and arena.used == 0


# -- depth range: a tight near plane keeps the far side of distant ridges hidden ------------------------------
def _point_triangle_distance_sampled(p: np.ndarray, tri: np.ndarray, n: int = 60) -> float:
    """Distance to a dense barycentric sampling of the triangle: an upper bound of the exact distance
    that comes within the sampling step of it."""
    u, v = np.meshgrid(np.linspace(0, 1, n + 1), np.linspace(0, 1, n + 1))
    keep = u + v <= 1.0
    u, v = u[keep], v[keep]
    pts = tri[0] + u[:, None] * (tri[1] - tri[0]) + v[:, None] * (tri[2] - tri[0])
    return float(np.sqrt(((pts - p) ** 2).sum(1)).min())


@settings(max_examples=60, deadline=None)
@given(
    st.lists(st.floats(-50, 50), min_size=9, max_size=9),
    st.lists(st.floats(-80, 80), min_size=3, max_size=3),
)
def test_min_distance_to_triangles_matches_sampling(coords, point) -> None:
    from terralod.kernels.cull import min_distance_to_triangles

    tri = np.asarray(coords, np.float64).reshape(3, 3)
    p = np.asarray(point, np.float64)
    exact = min_distance_to_triangles(tri, np.array([[0, 1, 2]], np.int64), *p)
    sampled = _point_triangle_distance_sampled(p, tri)
    step = max(np.linalg.norm(tri[1] - tri[0]), np.linalg.norm(tri[2] - tri[0])) / 60.0
    assert exact <= sampled + 1e-9
    assert sampled - exact <= 1.5 * step + 1e-9


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**31 - 1), st.floats(5.0, 3000.0), st.floats(0.5, 3.0))
def test_depth_range_holds_every_triangle(seed: int, eye_height_m: float, exaggeration: float) -> None:
    """near <= the nearest point of any drawn triangle (nothing clipped) and far >= the farthest vertex,
    over random terrains and eyes above them."""
    from terralod.render.renderer import depth_range

    rng = np.random.default_rng(seed)
    z = fractal_terrain(33, 33, seed, relief_m=300.0).astype(np.float64)
    xs, ys = np.meshgrid(np.arange(33) * 30.0, np.arange(33) * 30.0)
    v = np.stack([xs.ravel(), ys.ravel(), z.ravel()], 1)
    q = (np.arange(32)[:, None] + 33 * np.arange(32)[None, :]).ravel()
    tris = np.concatenate([np.stack([q, q + 1, q + 34], 1), np.stack([q, q + 34, q + 33], 1)])
    meshes = [((0, 0, 0), v, tris)]
    ex, ey = rng.uniform(-500, 1500, 2)
    eye = np.array([ex, ey, z.max() + eye_height_m])
    near, far = depth_range(meshes, eye, exaggeration)
    rel = (v - eye) * np.array([1.0, 1.0, exaggeration])
    assert far >= np.sqrt((rel**2).sum(1)).max()
    # exact nearest distance bounded above by the nearest vertex and below by sampling of nearby triangles
    d_vertex = np.sqrt((rel**2).sum(1))
    near_tris = tris[np.argsort(d_vertex[tris].min(1))[:40]]
    sampled = min(_point_triangle_distance_sampled(np.zeros(3), rel[t], 20) for t in near_tris)
    assert 0.05 <= near <= sampled
    assert near >= 0.5 * (sampled - 30.0 * 1.5 / 20) * 0.999  # tight: half the true distance, not 1e-5 x far


def test_no_back_faces_show_on_distant_ridges(shared_data: Path, tmp_path: Path) -> None:
    """Oblique frames over Puget Sound drawn with back-face culling off and the 'facing' diagnostic
    (back faces red): with the depth range from depth_range a back face wins almost no pixel. The former
    fixed range (near = 1e-5 x (2 x distance + 100 km)) let 44-279 pixels per frame of ridges' far sides
    through (the dark specks on distant crests)."""
    from PIL import Image

    from terralod.render.offscreen import FrameRenderer, auto_path
    from terralod.render.renderer import RenderSettings

    z = np.asarray(Image.open(shared_data / "dem" / "puget_sound_1k_u16.png")).astype(np.float32) * 0.1
    hf = Heightfield.from_array(z, 160.0)
    out = tmp_path / "puget.terra"
    build_store(hf, out, tile_size=65)
    with open_store(out) as s:
        fr = FrameRenderer(s, 1280, 720, settings=RenderSettings(mode="facing", cull_back_faces=False,
                                                                   background=(0.0, 0.0, 1.0)))  # fmt: skip
        red = []
        for pose in auto_path(s, 12):
            img = fr.frame(pose)
            red.append(int(((img[..., 0] > 200) & (img[..., 1] < 50)).sum()))
            terrain = int((img[..., 2] < 200).sum() + ((img[..., 0] > 200) & (img[..., 2] > 200)).sum())
            assert terrain > 10_000  # the frame shows terrain
        fr.close()
        fr = FrameRenderer(s, 1280, 720, settings=RenderSettings(mode="facing", background=(0.0, 0.0, 1.0)))
        culled = []
        for pose in auto_path(s, 3):
            img = fr.frame(pose)
            culled.append(int(((img[..., 0] > 200) & (img[..., 1] < 50)).sum()))
        fr.close()
    assert max(red) <= 20, red
    assert culled == [0, 0, 0]
