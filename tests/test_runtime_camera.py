"""Camera: frustum planes against the projection matrix, conservative box culling, box distance and the
DESIGN.md screen-space error."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from terralod.runtime import Camera
from terralod.runtime.camera import box_distance, box_visible


def _camera(seed: int, far: bool = False) -> Camera:
    rng = np.random.default_rng(seed)
    eye = rng.uniform(-1000, 1000, 3)
    tgt = eye + rng.normal(size=3) * rng.uniform(10, 5000)
    return Camera(
        tuple(eye), tuple(tgt), fov_y_deg=float(rng.uniform(10, 120)), width_px=int(rng.integers(50, 2000)),
        height_px=int(rng.integers(50, 2000)), near_m=float(rng.uniform(0.1, 10)),
        far_m=float(rng.uniform(2000, 9000)) if far else None,
    )  # fmt: skip


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**31), st.booleans())
def test_planes_agree_with_projection(seed: int, far: bool) -> None:
    cam = _camera(seed, far)
    rng = np.random.default_rng(seed + 1)
    pts = np.array(cam.eye) + rng.normal(size=(2000, 3)) * 3000.0
    clip = np.c_[pts, np.ones(len(pts))] @ (cam.projection_matrix @ cam.view_matrix).T
    w = clip[:, 3]
    ndc = clip[:, :3] / w[:, None]
    inside_proj = (w > 0) & (np.abs(ndc[:, 0]) <= 1) & (np.abs(ndc[:, 1]) <= 1) & (ndc[:, 2] >= -1)
    if far:
        inside_proj &= ndc[:, 2] <= 1
    inside = cam.contains(pts)
    # points within 1e-6 relative of a plane may fall either way
    margin = np.min(np.abs(pts @ cam.planes[:, :3].T + cam.planes[:, 3]), axis=1)
    sure = margin > 1e-6 * (1 + np.linalg.norm(pts - np.array(cam.eye), axis=1))
    assert np.array_equal(inside[sure], inside_proj[sure])
    assert inside.any() or not inside_proj[sure].any()


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**31))
def test_box_culling_is_conservative(seed: int) -> None:
    cam = _camera(seed)
    rng = np.random.default_rng(seed)
    lo = np.array(cam.eye) + rng.normal(size=(300, 3)) * 2000.0
    boxes = np.c_[lo, lo + rng.uniform(1, 800, (300, 3))]
    vis = box_visible(boxes, cam.planes)
    for b, v in zip(boxes, vis, strict=True):
        pts = b[:3] + rng.random((200, 3)) * (b[3:] - b[:3])
        corners = np.array([[b[i], b[j], b[k]] for i in (0, 3) for j in (1, 4) for k in (2, 5)])
        if cam.contains(np.r_[pts, corners]).any():
            assert v, "a box with a point inside the frustum was culled"
    # a box behind the eye is culled
    behind = np.array(cam.eye) - cam.forward * 500.0
    assert not box_visible(np.r_[behind - 10, behind + 10][None], cam.planes)[0]


def test_box_distance_and_screen_error() -> None:
    boxes = np.array([[0, 0, 0, 10, 10, 10], [20, 0, 0, 30, 10, 10], [0, 0, 0, 1, 1, 1.0]])
    d = box_distance(boxes, (5.0, 5.0, 5.0))
    assert d[0] == 0.0 and d[1] == pytest.approx(15.0) and d[2] == pytest.approx(math.sqrt(3 * 4**2))
    cam = Camera((0, 0, 0), (0, 100, 0), fov_y_deg=60, width_px=1000, height_px=800)
    k = 800 / (2 * math.tan(math.radians(30)))
    assert cam.screen_factor_px == pytest.approx(k)
    assert cam.screen_error_px(3.0, 1500.0) == pytest.approx(3.0 * k / 1500.0)
    assert cam.screen_error_px(0.0, 0.0) == 0.0 and math.isinf(cam.screen_error_px(1.0, 0.0))
    # a vertical segment of length e at distance d straight ahead projects to e*K/d pixels
    e, dist = 7.0, 900.0
    p = cam.project(np.array([[0, dist, -e / 2], [0, dist, e / 2]]))
    assert abs(p[0, 1] - p[1, 1]) == pytest.approx(float(cam.screen_error_px(e, dist)), rel=1e-9)
    assert p[0, 0] == pytest.approx(500.0) and (p[0, 1] + p[1, 1]) / 2 == pytest.approx(400.0)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"eye": (0, 0, 0), "target": (0, 0, 0)}, "view direction"),
        ({"eye": (0, 0, 0), "target": (0, 0, -5)}, "parallel"),
        ({"fov_y_deg": 0}, "fov_y_deg"),
        ({"fov_y_deg": 180}, "fov_y_deg"),
        ({"width_px": 0}, "viewport"),
        ({"near_m": 0}, "near_m"),
        ({"far_m": 0.5}, "far_m"),
        ({"eye": (0, 0, math.nan)}, "eye"),
    ],
)
def test_bad_cameras_get_clear_errors(kwargs: dict, match: str) -> None:
    base = {"eye": (0, 0, 10), "target": (5, 5, 0)}
    with pytest.raises(ValueError, match=match):
        Camera(**{**base, **kwargs})


def test_camera_key_and_matrices() -> None:
    a = Camera((1, 2, 3), (4, 5, 0))
    b = Camera((1.0, 2.0, 3.0), np.array([4, 5, 0]))
    assert a.key == b.key
    assert a.key != Camera((1, 2, 3.5), (4, 5, 0)).key
    v = a.view_matrix
    assert np.allclose(v[:3, :3] @ v[:3, :3].T, np.eye(3))
    assert np.allclose(v @ np.r_[a.eye, 1.0], [0, 0, 0, 1])
    # the target lies straight ahead (-z in eye space)
    t = v @ np.r_[a.target, 1.0]
    assert abs(t[0]) < 1e-9 and abs(t[1]) < 1e-9 and t[2] < 0
