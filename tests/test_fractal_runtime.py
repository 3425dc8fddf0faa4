"""Fractal levels below the store's finest level, generated on demand by the runtime (paper 001 §3.1):
selected by the same screen-space rule, watertight with the stored levels, never stored."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from terralod import Camera, Engine, build_store, open_store, sample_heightfield
from terralod.fractal import FractalDetail
from terralod.runtime import find_cracks
from terralod.runtime.fractal_source import FractalSource

_MESA = "/usr/share/glvnd/egl_vendor.d/50_mesa.json"
if os.path.exists(_MESA):
    os.environ.setdefault("__EGL_VENDOR_LIBRARY_FILENAMES", _MESA)


@pytest.fixture(scope="module")
def sample(tmp_path_factory):
    hf = sample_heightfield()
    out = tmp_path_factory.mktemp("f") / "s.terra"
    build_store(hf, out, tile_size=33)
    return hf, out


def _close_views(hf):
    for r, c, back, up in ((200, 200, 500.0, 300.0), (120, 300, 300.0, 150.0), (300, 100, 900.0, 500.0)):
        x, y = (float(v) for v in hf.world_xy(r, c))
        z = float(hf.elevation_m[r, c])
        yield (x - back, y - back, z + up), (x, y, z - 0.3 * up)


def test_engine_refines_into_fractal_levels_without_cracks(sample) -> None:
    hf, path = sample
    with open_store(path) as store:
        src = FractalSource(store, FractalDetail(hf, seed=3), extra_levels=2)
        L = store.pyramid.max_level
        # the extended pyramid keeps every stored tile's code and footprint; errors stay monotone
        rows = {(r["level"], r["x"], r["y"]): r for r in src.tile_summaries()}
        for (k, x, y), r in rows.items():
            if k > 0:
                assert rows[(k - 1, x // 2, y // 2)]["error_m"] >= r["error_m"]
        engine = Engine(src, threshold_px=1.0)
        deepest = 0
        for eye, tgt in _close_views(hf):
            cam = Camera(eye, tgt, (0, 0, 1.0), 60.0, 640, 360, near_m=1.0)
            sel = engine.update(cam)
            deepest = max(deepest, max(c[0] for c in sel.tiles))
            rep = find_cracks(sel.mesh_dict(), src.pyramid, src.transform)
            assert sum(rep.cracked.values()) == 0 and rep.cracked_corners == 0, rep
            fresh = Engine(src, threshold_px=1.0).update(cam)
            assert sorted(fresh.tiles) == sorted(sel.tiles)
        assert deepest == L + 2, f"close views reached level {deepest} of {L + 2}"
        # fractal tiles keep the DEM's samples exactly (up to the stored level's own quantisation)
        t = src.tile(L + 1, 3, 2)
        on = (np.mod(t.grid_rc, src.factor) == 0).all(axis=1)
        r, c = (t.grid_rc[on] / src.factor).astype(int).T
        assert np.array_equal(t.vertices[on, 2], hf.elevation_m[r, c].astype(np.float64))


def test_rendered_fractal_close_up_has_no_crack(sample, tmp_path: Path) -> None:
    from terralod.render import RenderSettings, TerrainRenderer

    hf, path = sample
    r = TerrainRenderer(320, 240)
    st = RenderSettings(background=(1.0, 0.0, 1.0), fog=False)
    with open_store(path) as store:
        src = FractalSource(store, FractalDetail(hf), extra_levels=2)
        engine = Engine(src, threshold_px=1.0)
        for r0, c0 in ((150, 150), (250, 220)):
            x, y = (float(v) for v in hf.world_xy(r0, c0))
            z = float(hf.elevation_m[r0, c0])
            eye, tgt = (x - 60.0, y - 80.0, z + 700.0), (x, y, z - 800.0)  # steep: terrain fills the frame
            sel = engine.update(Camera(eye, tgt, (0, 0, 1.0), 50.0, 320, 240, near_m=1.0))
            assert max(c[0] for c in sel.tiles) > store.pyramid.max_level
            img = r.render(list(sel.meshes()), eye, tgt, fov_y_deg=50.0, settings=st)
            magenta = int(((img[..., 0] > 200) & (img[..., 1] < 60) & (img[..., 2] > 200)).sum())
            assert img.std() > 5 and magenta == 0, f"{magenta} crack pixels"
    r.release()


def test_threaded_generation_gives_the_same_tiles_and_frames(sample) -> None:
    """tiles() on several threads returns, in order, the bytes tile() gives one by one; engines fed by a
    threaded and a serial source select and stitch identical meshes."""
    hf, path = sample
    with open_store(path) as store:
        serial = FractalSource(store, FractalDetail(hf, seed=11), extra_levels=2, workers=1)
        threaded = FractalSource(store, FractalDetail(hf, seed=11), extra_levels=2, workers=4)
        L = store.pyramid.max_level
        codes = [(L - 1, 1, 1), *[(L + 1, x, y) for x in range(4) for y in range(3)], (L, 2, 2),
                 *[(L + 2, x, 5) for x in range(6)]]  # fmt: skip
        for a, b in zip(threaded.tiles(codes), [serial.tile(*c) for c in codes], strict=True):
            assert a.code == b.code
            assert np.array_equal(a.vertices, b.vertices) and np.array_equal(a.triangles, b.triangles)
            assert a.error_m == b.error_m and np.array_equal(a.grid_rc, b.grid_rc)
        e1, e2 = Engine(serial, threshold_px=1.0), Engine(threaded, threshold_px=1.0)
        for eye, tgt in _close_views(hf):
            cam = Camera(eye, tgt, (0, 0, 1.0), 60.0, 640, 360, near_m=1.0)
            m1, m2 = e1.update(cam).mesh_dict(), e2.update(cam).mesh_dict()
            assert m1.keys() == m2.keys() and max(c[0] for c in m1) > L
            for code in m1:
                assert all(np.array_equal(x, y) for x, y in zip(m1[code], m2[code], strict=True)), code
