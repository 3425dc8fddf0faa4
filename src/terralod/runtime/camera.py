"""Camera, view frustum and screen-space error for runtime selection.

Implements the view-dependent part of ``../shared/papers/000_0f8c6950ace8a2d1.txt`` §3.3 (the stored
Hausdorff error projected to pixels) with DESIGN.md's formula

    rho_px = error_m * H_px / (2 * d_m * tan(fov_y / 2))

where ``d_m`` is the distance from the eye to the tile's axis-aligned bounding box (0 inside it, so a tile
that contains the eye always refines), and the frustum culling of ``../shared/papers/002_037d1654b87e3b6a.txt``
§3.3 ("terrain frustum culling is used to perform a preliminary investigation").

Deviations: the paper's screen error is measured on the rendered image; ours is the conservative projection
of the measured error at the nearest point of the box (the CDLOD / Cesium convention). The far plane is
optional (``far_m=None`` culls nothing by distance) because the screen-space error already coarsens
distant terrain.

The box tests are numba kernels (pure, on arrays) shared with :mod:`terralod.runtime.select`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from terralod.kernels import jit

__all__ = ["Camera", "box_distance", "box_visible"]


@jit
def _box_distance(box, eye):
    """Distance, metres, from ``eye`` (3,) to the box (xmin, ymin, zmin, xmax, ymax, zmax); 0 inside."""
    s = 0.0
    for a in range(3):
        lo = box[a]
        hi = box[a + 3]
        e = eye[a]
        if e < lo:
            s += (lo - e) * (lo - e)
        elif e > hi:
            s += (e - hi) * (e - hi)
    return math.sqrt(s)


@jit
def _box_visible(box, planes):
    """True unless the box lies entirely on the outer side of one plane (n . p + d >= 0 is inside)."""
    for i in range(planes.shape[0]):
        nx = planes[i, 0]
        ny = planes[i, 1]
        nz = planes[i, 2]
        # the box corner farthest along the plane normal (the "p-vertex")
        px = box[3] if nx >= 0.0 else box[0]
        py = box[4] if ny >= 0.0 else box[1]
        pz = box[5] if nz >= 0.0 else box[2]
        if nx * px + ny * py + nz * pz + planes[i, 3] < 0.0:
            return False
    return True


@jit
def _boxes_visible(boxes, planes):
    out = np.empty(boxes.shape[0], np.bool_)
    for i in range(boxes.shape[0]):
        out[i] = _box_visible(boxes[i], planes)
    return out


@jit
def _boxes_distance(boxes, eye):
    out = np.empty(boxes.shape[0], np.float64)
    for i in range(boxes.shape[0]):
        out[i] = _box_distance(boxes[i], eye)
    return out


def box_visible(boxes: np.ndarray, planes: np.ndarray) -> np.ndarray:
    """Frustum test of axis-aligned boxes.

    Parameters
    ----------
    boxes : (n, 6) float64, (xmin, ymin, zmin, xmax, ymax, zmax) world metres
    planes : (p, 4) float64 inward planes ``n . x + d >= 0`` (see :attr:`Camera.planes`)

    Returns
    -------
    (n,) bool, False where the box is certainly outside the frustum (conservative: True may still be outside).
    """
    b = np.ascontiguousarray(np.atleast_2d(boxes), dtype=np.float64)
    return _boxes_visible(b, np.ascontiguousarray(planes, dtype=np.float64))


def box_distance(boxes: np.ndarray, eye: Sequence[float]) -> np.ndarray:
    """(n,) distance in metres from ``eye`` to each box (n, 6); 0 where the eye is inside."""
    b = np.ascontiguousarray(np.atleast_2d(boxes), dtype=np.float64)
    return _boxes_distance(b, np.asarray(eye, dtype=np.float64))


def _unit(v: np.ndarray, what: str) -> np.ndarray:
    n = float(np.linalg.norm(v))
    if not math.isfinite(n) or n < 1e-12:
        raise ValueError(f"Expected a non-zero finite {what}, got {v.tolist()}")
    return v / n


@dataclass(frozen=True)
class Camera:
    """A perspective camera in world metres (x east, y north, z up).

    Parameters
    ----------
    eye : (3,) position of the eye, metres
    target : (3,) a point the camera looks at, metres
    up : (3,) approximate up direction (default +z); must not be parallel to the view direction
    fov_y_deg : vertical field of view, degrees, in (0, 180)
    width_px, height_px : viewport size, pixels (H in the screen-space error)
    near_m : near plane distance, metres (> 0)
    far_m : far plane distance, metres, or None for no far culling
    """

    eye: tuple[float, float, float]
    target: tuple[float, float, float]
    up: tuple[float, float, float] = (0.0, 0.0, 1.0)
    fov_y_deg: float = 60.0
    width_px: int = 1920
    height_px: int = 1080
    near_m: float = 1.0
    far_m: float | None = None
    _basis: np.ndarray = field(init=False, repr=False, compare=False)
    _planes: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        eye = np.asarray(self.eye, dtype=np.float64).reshape(-1)
        tgt = np.asarray(self.target, dtype=np.float64).reshape(-1)
        up = np.asarray(self.up, dtype=np.float64).reshape(-1)
        for name, v in (("eye", eye), ("target", tgt), ("up", up)):
            if v.shape != (3,) or not np.isfinite(v).all():
                raise ValueError(f"Expected {name} as 3 finite numbers, got {v.tolist()}")
        if not (0.0 < float(self.fov_y_deg) < 180.0):
            raise ValueError(f"Expected fov_y_deg in (0, 180), got {self.fov_y_deg}")
        if int(self.width_px) < 1 or int(self.height_px) < 1:
            raise ValueError(f"Expected a viewport of at least 1x1 px, got {self.width_px}x{self.height_px}")
        if not float(self.near_m) > 0.0:
            raise ValueError(f"Expected near_m > 0, got {self.near_m}")
        if self.far_m is not None and not float(self.far_m) > float(self.near_m):
            raise ValueError(f"Expected far_m > near_m ({self.near_m}), got {self.far_m}")
        f = _unit(tgt - eye, "view direction (target - eye)")
        r = np.cross(f, _unit(up, "up vector"))
        if float(np.linalg.norm(r)) < 1e-9:
            raise ValueError(f"Expected an up vector not parallel to the view direction, got {up.tolist()}")
        r = r / np.linalg.norm(r)
        u = np.cross(r, f)
        set_ = object.__setattr__
        set_(self, "eye", tuple(float(a) for a in eye))
        set_(self, "target", tuple(float(a) for a in tgt))
        set_(self, "up", tuple(float(a) for a in up))
        set_(self, "fov_y_deg", float(self.fov_y_deg))
        set_(self, "width_px", int(self.width_px))
        set_(self, "height_px", int(self.height_px))
        set_(self, "near_m", float(self.near_m))
        set_(self, "far_m", None if self.far_m is None else float(self.far_m))
        set_(self, "_basis", np.stack([r, u, f]))
        set_(self, "_planes", self._make_planes(eye, r, u, f))

    # -- frame -----------------------------------------------------------------------------------------
    @property
    def eye_array(self) -> np.ndarray:
        """(3,) float64 eye position, metres."""
        return np.asarray(self.eye, dtype=np.float64)

    @property
    def forward(self) -> np.ndarray:
        """(3,) unit view direction."""
        return self._basis[2].copy()

    @property
    def right(self) -> np.ndarray:
        """(3,) unit right vector of the image."""
        return self._basis[0].copy()

    @property
    def true_up(self) -> np.ndarray:
        """(3,) unit up vector of the image (orthogonal to forward and right)."""
        return self._basis[1].copy()

    @property
    def aspect(self) -> float:
        """width / height."""
        return self.width_px / self.height_px

    @property
    def screen_factor_px(self) -> float:
        """K = H / (2 tan(fov_y / 2)), pixels per (metre of error / metre of distance)."""
        return self.height_px / (2.0 * math.tan(math.radians(self.fov_y_deg) / 2.0))

    @property
    def key(self) -> tuple[float, ...]:
        """Every number that changes the view (equal keys mean identical selections)."""
        return (*self.eye, *self.target, *self.up, self.fov_y_deg, float(self.width_px), float(self.height_px),
                self.near_m, -1.0 if self.far_m is None else self.far_m)  # fmt: skip

    # -- frustum ---------------------------------------------------------------------------------------
    def _make_planes(self, eye: np.ndarray, r: np.ndarray, u: np.ndarray, f: np.ndarray) -> np.ndarray:
        ty = math.tan(math.radians(self.fov_y_deg) / 2.0)
        tx = ty * self.width_px / self.height_px
        normals = [f, r + tx * f, -r + tx * f, u + ty * f, -u + ty * f]
        ds = [-float(f @ eye) - self.near_m]
        out = []
        for i, n in enumerate(normals):
            n = n / np.linalg.norm(n)
            out.append([*n, ds[0] if i == 0 else -float(n @ eye)])
        if self.far_m is not None:
            out.append([*(-f), float(f @ eye) + self.far_m])
        return np.ascontiguousarray(out, dtype=np.float64)

    @property
    def planes(self) -> np.ndarray:
        """(5, 4) or (6, 4) float64 inward frustum planes (near, left, right, bottom, top[, far]).

        A world point p is inside when ``n . p + d >= 0`` for every row (nx, ny, nz, d); normals are unit.
        """
        return self._planes.copy()

    def contains(self, points: np.ndarray) -> np.ndarray:
        """(n,) bool: which world points (n, 3) lie inside the frustum."""
        p = np.atleast_2d(np.asarray(points, dtype=np.float64))
        return np.all(p @ self._planes[:, :3].T + self._planes[:, 3] >= 0.0, axis=1)

    # -- projection ------------------------------------------------------------------------------------
    def screen_error_px(self, error_m: np.ndarray | float, distance_m: np.ndarray | float) -> np.ndarray:
        """DESIGN.md screen-space error: ``error_m * H / (2 d tan(fov_y/2))``, pixels (inf at d = 0)."""
        e = np.asarray(error_m, dtype=np.float64)
        d = np.asarray(distance_m, dtype=np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(e > 0, e * self.screen_factor_px / d, 0.0)

    @property
    def view_matrix(self) -> np.ndarray:
        """(4, 4) float64 world -> eye (OpenGL look-at: the camera looks down -z of eye space)."""
        r, u, f = self._basis
        eye = self.eye_array
        m = np.eye(4)
        m[0, :3], m[1, :3], m[2, :3] = r, u, -f
        m[:3, 3] = [-(r @ eye), -(u @ eye), f @ eye]
        return m

    @property
    def projection_matrix(self) -> np.ndarray:
        """(4, 4) float64 OpenGL perspective projection (infinite far plane when ``far_m`` is None)."""
        t = 1.0 / math.tan(math.radians(self.fov_y_deg) / 2.0)
        n = self.near_m
        p = np.zeros((4, 4))
        p[0, 0] = t / self.aspect
        p[1, 1] = t
        p[3, 2] = -1.0
        if self.far_m is None:
            p[2, 2], p[2, 3] = -1.0, -2.0 * n
        else:
            fr = self.far_m
            p[2, 2], p[2, 3] = -(fr + n) / (fr - n), -2.0 * fr * n / (fr - n)
        return p

    def project(self, points: np.ndarray) -> np.ndarray:
        """(n, 2) pixel coordinates (x right, y down, origin top-left) of world points (n, 3)."""
        p = np.atleast_2d(np.asarray(points, dtype=np.float64))
        h = np.c_[p, np.ones(len(p))] @ (self.projection_matrix @ self.view_matrix).T
        ndc = h[:, :2] / h[:, 3:4]
        return np.c_[(ndc[:, 0] + 1.0) * 0.5 * self.width_px, (1.0 - ndc[:, 1]) * 0.5 * self.height_px]
