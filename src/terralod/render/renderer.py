"""Terrain renderer on moderngl: tiles uploaded once into GPU buffers (LRU under a memory budget), drawn
with an elevation colour ramp, hillshade from the vertex normals, and distance fog toward the sky.

Precision: vertex positions are uploaded relative to each tile's origin (float32) and the tile origin
relative to the eye is computed per draw in float64, so projected UTM coordinates (x ~ 5e5, y ~ 5e6 m)
render without float32 jitter.

Headless: :func:`create_offscreen_context` opens an EGL context (Mesa llvmpipe on machines without a GPU;
OpenGL 4.5 core there). A window viewer passes its own context.
"""

from __future__ import annotations

import math
import zlib
from collections import OrderedDict
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

_SHADERS = Path(__file__).resolve().parent / "shaders"

#: Hypsometric ramp stops (fraction of the height range → RGB 0..1): water-blue lowlands to snow.
_RAMP = [
    (0.00, (0.27, 0.45, 0.32)),
    (0.15, (0.40, 0.58, 0.33)),
    (0.35, (0.72, 0.72, 0.45)),
    (0.55, (0.66, 0.52, 0.36)),
    (0.75, (0.55, 0.45, 0.40)),
    (0.90, (0.80, 0.78, 0.76)),
    (1.00, (0.97, 0.97, 0.98)),
]

#: Distinct colours for level-of-detail mode, by level modulo their count.
LEVEL_COLOURS = np.array(
    [
        (0.90, 0.30, 0.25), (0.95, 0.65, 0.20), (0.95, 0.90, 0.30), (0.45, 0.80, 0.35),
        (0.25, 0.70, 0.80), (0.30, 0.45, 0.90), (0.60, 0.40, 0.85), (0.85, 0.45, 0.70),
    ],
    np.float32,
)  # fmt: skip


def create_offscreen_context(require: int = 330):
    """A standalone EGL OpenGL context (no display needed)."""
    import moderngl

    return moderngl.create_context(standalone=True, backend="egl", require=require)


def vertex_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals, (N, 3) float32 unit vectors (z up for counter-clockwise triangles)."""
    v = vertices
    t = triangles.astype(np.int64)
    fn = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
    n = np.zeros_like(v)
    for k in range(3):
        np.add.at(n, t[:, k], fn)
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    norm[norm == 0] = 1.0
    return (n / norm).astype(np.float32)


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """View matrix (4x4, column vectors) with the eye at the origin (translation applied per tile)."""
    f = target - eye
    f = f / np.linalg.norm(f)
    s = np.cross(f, up)
    if np.linalg.norm(s) < 1e-9:
        s = np.cross(f, np.array([0.0, 1.0, 0.0]))
    s = s / np.linalg.norm(s)
    u = np.cross(s, f)
    m = np.eye(4)
    m[0, :3], m[1, :3], m[2, :3] = s, u, -f
    return m


def perspective(fov_y_deg: float, aspect: float, near: float, far: float) -> np.ndarray:
    f = 1.0 / math.tan(math.radians(fov_y_deg) / 2.0)
    m = np.zeros((4, 4))
    m[0, 0] = f / aspect
    m[1, 1] = f
    m[2, 2] = (far + near) / (near - far)
    m[2, 3] = 2.0 * far * near / (near - far)
    m[3, 2] = -1.0
    return m


@dataclass
class RenderSettings:
    """What a frame looks like. Colours are RGB 0..1."""

    background: tuple[float, float, float] = (0.66, 0.78, 0.92)
    mode: str = "elevation"  # "elevation", "lod", "error"
    wireframe: bool = False
    z_exaggeration: float = 1.0
    sun_azimuth_deg: float = 315.0
    sun_altitude_deg: float = 45.0
    fog: bool = True
    height_range_m: tuple[float, float] | None = None


@dataclass
class _GpuTile:
    vbo: object
    ibo: object
    vao: object
    origin: np.ndarray
    n_indices: int
    nbytes: int
    digest: int
    level: int
    data: np.ndarray  # CPU copy of the interleaved vertex data, to find what changed


class TerrainRenderer:
    """Draws tile meshes into an offscreen framebuffer (or a window's default framebuffer).

    Parameters
    ----------
    width_px, height_px : viewport size
    ctx : a moderngl context; a standalone EGL one is created when None
    memory_budget_bytes : GPU bytes of tile buffers kept; least recently drawn tiles are released beyond it
    """

    def __init__(
        self, width_px: int, height_px: int, *, ctx=None, memory_budget_bytes: int = 512 * 2**20
    ) -> None:
        import moderngl

        self.ctx = ctx if ctx is not None else create_offscreen_context()
        self.width_px, self.height_px = int(width_px), int(height_px)
        self.memory_budget_bytes = memory_budget_bytes
        self.prog = self.ctx.program(
            vertex_shader=(_SHADERS / "terrain.vert").read_text(),
            fragment_shader=(_SHADERS / "terrain.frag").read_text(),
        )
        ramp = self._ramp_texture()
        self.ramp = self.ctx.texture((256, 1), 3, ramp.tobytes())
        self.ramp.filter = (moderngl.LINEAR, moderngl.LINEAR)
        self.ramp.repeat_x = False
        self._tiles: OrderedDict[tuple, _GpuTile] = OrderedDict()
        self.gpu_bytes = 0
        self.uploads = 0
        self.updates = 0
        self.bytes_uploaded = 0
        self.bytes_written = 0
        self.fbo = None
        if ctx is None:
            self._make_fbo()

    def _make_fbo(self) -> None:
        self.fbo = self.ctx.simple_framebuffer((self.width_px, self.height_px), components=4)

    @staticmethod
    def _ramp_texture() -> np.ndarray:
        t = np.linspace(0, 1, 256)
        stops = np.array([s for s, _ in _RAMP])
        cols = np.array([c for _, c in _RAMP])
        rgb = np.stack([np.interp(t, stops, cols[:, k]) for k in range(3)], axis=1)
        return (rgb * 255).astype(np.uint8)

    # -- tile buffers ----------------------------------------------------------------------------------
    def upload(
        self, code: tuple, vertices: np.ndarray, triangles: np.ndarray, normals: np.ndarray | None
    ) -> None:
        """Make tile ``code`` drawable with this geometry. Unchanged tiles cost one checksum; changed
        geometry of the same size (stitched boundaries) is written into the existing buffer."""
        if normals is None:
            normals = vertex_normals(vertices, triangles)
        # the tile origin: the vertex-grid corner, stable when stitching moves boundary heights
        origin = np.floor(vertices.min(axis=0) / 64.0) * 64.0
        data = np.empty((len(vertices), 6), np.float32)
        data[:, :3] = vertices - origin
        data[:, 3:] = normals
        raw = data.tobytes()
        digest = zlib.crc32(raw)
        g = self._tiles.get(code)
        if g is not None:
            self._tiles.move_to_end(code)
            if g.digest == digest:
                return
            if g.vbo.size == len(raw) and g.n_indices == triangles.size and np.array_equal(g.origin, origin):
                # stitched borders: write only the runs of vertices that changed (small buffer writes)
                changed = np.flatnonzero((g.data != data).any(axis=1))
                if changed.size:
                    breaks = np.flatnonzero(np.diff(changed) > 1)
                    starts = np.r_[changed[0], changed[breaks + 1]]
                    ends = np.r_[changed[breaks], changed[-1]] + 1
                    stride = data.shape[1] * 4
                    for a, b in zip(starts, ends, strict=True):
                        g.vbo.write(data[a:b].tobytes(), offset=int(a) * stride)
                        self.bytes_written += int(b - a) * stride
                g.data = data
                g.digest = digest
                self.updates += 1
                return
            self._release(code)
        vbo = self.ctx.buffer(raw)
        ibo = self.ctx.buffer(np.ascontiguousarray(triangles, dtype=np.uint32).tobytes())
        vao = self.ctx.vertex_array(self.prog, [(vbo, "3f 3f", "in_position", "in_normal")], index_buffer=ibo)
        nbytes = len(raw) + triangles.size * 4
        self._tiles[code] = _GpuTile(
            vbo, ibo, vao, origin, triangles.size, nbytes, digest, int(code[0]), data
        )
        self.gpu_bytes += nbytes
        self.bytes_uploaded += nbytes
        self.uploads += 1
        self._evict()

    def _release(self, code: tuple) -> None:
        g = self._tiles.pop(code)
        g.vao.release()
        g.vbo.release()
        g.ibo.release()
        self.gpu_bytes -= g.nbytes

    def _evict(self, keep: set | None = None) -> None:
        for code in list(self._tiles):
            if self.gpu_bytes <= self.memory_budget_bytes:
                break
            if keep and code in keep:
                continue
            self._release(code)

    # -- drawing ---------------------------------------------------------------------------------------
    def render(
        self,
        meshes: Iterable[tuple],
        eye,
        target,
        up=(0.0, 0.0, 1.0),
        fov_y_deg: float = 45.0,
        settings: RenderSettings | None = None,
        tile_colours: dict | None = None,
        read: bool = True,
    ) -> np.ndarray | None:
        """Draw ``meshes`` ((code, vertices, triangles, normals) tuples, world metres) and return the
        frame as (H, W, 3) uint8 (row 0 at the top) when ``read``."""
        import moderngl

        st = settings or RenderSettings()
        eye = np.asarray(eye, np.float64)
        target = np.asarray(target, np.float64)
        codes = []
        zlo, zhi = math.inf, -math.inf
        for m in meshes:
            code, v, t, n = m[0], m[1], m[2], (m[3] if len(m) > 3 else None)
            self.upload(code, v, t, n)
            codes.append(code)
            zlo, zhi = min(zlo, float(v[:, 2].min())), max(zhi, float(v[:, 2].max()))
        self._evict(keep=set(codes))
        if self.fbo is not None:
            self.fbo.use()
        ctx = self.ctx
        ctx.viewport = (0, 0, self.width_px, self.height_px)
        ctx.clear(*st.background, 1.0)
        ctx.enable(moderngl.DEPTH_TEST)
        ctx.disable(moderngl.CULL_FACE)
        ctx.wireframe = st.wireframe
        # near/far from the scene: far reaches past every drawn tile, near keeps 1e5 depth range
        far = 10.0
        for c in codes:
            g = self._tiles[c]
            far = max(far, float(np.linalg.norm(g.origin - eye)) * 2.0 + 1e5)
        near = max(0.05, far * 1e-5)
        view = look_at(eye, target, np.asarray(up, np.float64))
        proj = perspective(fov_y_deg, self.width_px / self.height_px, near, far)
        vp = (proj @ view).astype(np.float32)
        self.prog["u_view_proj"].write(vp.T.tobytes())
        az, alt = math.radians(st.sun_azimuth_deg), math.radians(st.sun_altitude_deg)
        light = np.array([math.cos(alt) * math.sin(az), math.cos(alt) * math.cos(az), math.sin(alt)])
        self.prog["u_light_dir"].value = tuple(light / np.linalg.norm(light))
        hr = st.height_range_m or ((zlo, zhi) if codes else (0.0, 1.0))
        self.prog["u_height_range"].value = (float(hr[0]), float(hr[1]))
        self.prog["u_fog_colour"].value = tuple(st.background)
        dist = float(np.linalg.norm(target - eye))
        self.prog["u_fog_distance"].value = (dist * 6.0) if st.fog else 1e12
        self.prog["u_z_exaggeration"].value = float(st.z_exaggeration)
        self.prog["u_mode"].value = {"elevation": 0, "lod": 1, "error": 2}[st.mode]
        self.ramp.use(0)
        self.prog["u_ramp"].value = 0
        for c in codes:
            g = self._tiles[c]
            off = g.origin - eye
            self.prog["u_tile_offset"].value = tuple(off.astype(np.float32))
            self.prog["u_origin_z"].value = float(g.origin[2])
            if st.mode == "lod":
                colour = LEVEL_COLOURS[g.level % len(LEVEL_COLOURS)]
            elif st.mode == "error" and tile_colours is not None:
                colour = tile_colours.get(c, (1.0, 0.0, 1.0))
            else:
                colour = (1.0, 1.0, 1.0)
            self.prog["u_tile_colour"].value = tuple(float(x) for x in colour)
            g.vao.render(moderngl.TRIANGLES)
        ctx.wireframe = False
        if not read:
            return None
        fbo = self.fbo if self.fbo is not None else ctx.screen
        raw = fbo.read(components=3, alignment=1)
        img = np.frombuffer(raw, np.uint8).reshape(self.height_px, self.width_px, 3)
        return img[::-1].copy()

    @property
    def tiles_resident(self) -> int:
        return len(self._tiles)

    def release(self) -> None:
        for code in list(self._tiles):
            self._release(code)
        if self.fbo is not None:
            self.fbo.release()
