"""Terrain renderer on moderngl: tiles uploaded once into GPU buffers (LRU under a memory budget), drawn
with an elevation colour ramp, hillshade from the vertex normals, and distance fog toward the sky.

Precision: vertex positions are uploaded relative to each tile's origin (float32) and the tile origin
relative to the eye is computed per draw in float64, so projected UTM coordinates (x ~ 5e5, y ~ 5e6 m)
render without float32 jitter.

Headless: :func:`create_offscreen_context` opens an EGL context (Mesa llvmpipe on machines without a GPU;
OpenGL 4.5 core there). A window viewer passes its own context.
"""

from __future__ import annotations

import bisect
import math
import zlib
from collections import OrderedDict
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from terralod.errors import DisplayError

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
    """A standalone EGL OpenGL context (no display needed); :class:`~terralod.errors.DisplayError` when the
    machine has no EGL/OpenGL driver that gives one."""
    import moderngl

    try:
        return moderngl.create_context(standalone=True, backend="egl", require=require)
    except Exception as exc:  # moderngl raises plain Exception subclasses for a missing driver
        raise DisplayError(
            f"no OpenGL {require // 100}.{require % 100 // 10} context through EGL ({exc}); install Mesa's EGL "
            "(libegl1 libegl-mesa0 libgl1-mesa-dri) or a GPU driver"
        ) from exc


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


def depth_range(meshes: list, eye: np.ndarray, z_exaggeration: float = 1.0) -> tuple[float, float]:
    """Near and far plane distances (metres) that hold every drawn triangle: far just past the farthest
    tile-box corner, near half the distance to the nearest triangle (exact for the tiles whose boxes come
    nearest, branch and bound). A tight near plane is what keeps a 24-bit depth buffer precise far away:
    depth steps grow as distance² / near, and with a near plane of ~1 m a ridge 30 km away gets ~50 m
    steps, enough for its far side to show through (dark specks along distant crests)."""
    from terralod.kernels.cull import min_distance_to_triangles

    if not meshes:
        return 0.05, 10.0
    scale = np.array([1.0, 1.0, z_exaggeration])
    boxes = []
    far = 1.0
    for m in meshes:
        v = m[1]
        a = (v.min(axis=0) - eye) * scale
        b = (v.max(axis=0) - eye) * scale
        lo, hi = np.minimum(a, b), np.maximum(a, b)
        boxes.append((float(np.linalg.norm(np.maximum(np.maximum(lo, -hi), 0.0))), m))
        far = max(far, float(np.linalg.norm(np.maximum(np.abs(lo), np.abs(hi)))))
    boxes.sort(key=lambda x: x[0])
    nearest = math.inf
    for box_m, m in boxes:
        if box_m >= nearest:
            break
        v = (np.asarray(m[1], np.float64) - eye) * scale
        nearest = min(nearest, min_distance_to_triangles(v, np.asarray(m[2], np.int64), 0.0, 0.0, 0.0))
    near = max(0.05, 0.5 * nearest) if math.isfinite(nearest) else 0.05
    return near, max(far * 1.01 + 1.0, near * 2.0)


@dataclass
class RenderSettings:
    """What a frame looks like. Colours are RGB 0..1."""

    background: tuple[float, float, float] = (0.66, 0.78, 0.92)
    mode: str = "elevation"  # "elevation", "lod", "error", "facing" (diagnostic: back faces red)
    wireframe: bool = False
    z_exaggeration: float = 1.0
    sun_azimuth_deg: float = 315.0
    sun_altitude_deg: float = 45.0
    fog: bool = True
    #: heights of the colour ramp's ends, metres (None: the drawn tiles' range, which changes per frame;
    #: the frame renderer and the viewer fix it to the terrain's range)
    height_range_m: tuple[float, float] | None = None
    #: heights drawn as water (lo, hi), metres, or None (see terralod.render.offscreen.terrain_colours)
    water_m: tuple[float, float] | None = None
    water_colour: tuple[float, float, float] = (0.23, 0.42, 0.62)
    #: a colour legend (metres) in the frame's corner (frame renderer and viewer)
    legend: bool = False
    #: skip triangles seen from behind (terrain is seen from above; counter-clockwise from above is front)
    cull_back_faces: bool = True
    #: a :class:`terralod.render.overlay.ChangeOverlay` coloured over the terrain (gain / loss), or None
    overlay: object = None


class _Arena:
    """First-fit allocator over ``capacity`` units of one GPU buffer; freed blocks are coalesced."""

    def __init__(self, capacity: int) -> None:
        self.capacity = int(capacity)
        self.free: list[list[int]] = [[0, self.capacity]] if capacity > 0 else []
        self.used = 0

    def alloc(self, n: int) -> int | None:
        for i, blk in enumerate(self.free):
            if blk[1] >= n:
                start = blk[0]
                if blk[1] == n:
                    del self.free[i]
                else:
                    blk[0] += n
                    blk[1] -= n
                self.used += n
                return start
        return None

    def release(self, start: int, n: int) -> None:
        if n <= 0:
            return
        self.used -= n
        i = bisect.bisect_left(self.free, [start, 0])
        self.free.insert(i, [start, n])
        if i + 1 < len(self.free) and self.free[i][0] + self.free[i][1] == self.free[i + 1][0]:
            self.free[i][1] += self.free.pop(i + 1)[1]
        if i > 0 and self.free[i - 1][0] + self.free[i - 1][1] == self.free[i][0]:
            self.free[i - 1][1] += self.free.pop(i)[1]

    def grow(self, capacity: int) -> None:
        extra = int(capacity) - self.capacity
        if extra <= 0:
            return
        if self.free and self.free[-1][0] + self.free[-1][1] == self.capacity:
            self.free[-1][1] += extra
        else:
            self.free.append([self.capacity, extra])
        self.capacity = int(capacity)


@dataclass
class _GpuTile:
    origin: np.ndarray
    n_indices: int
    n_vertices: int
    nbytes: int
    digest: int
    tri_digest: int
    level: int
    data: np.ndarray  # CPU copy of the interleaved vertex data, to find what changed
    # plain draws: a buffer pair per tile
    vbo: object = None
    ibo: object = None
    vao: object = None
    # indirect draws: ranges in the shared arenas (vertices, indices)
    first_vertex: int = -1
    first_index: int = -1


_VERTEX_BYTES = 24  # 3 float32 position + 3 float32 normal
_INSTANCE_BYTES = 28  # 3 float32 tile offset + float32 origin z + 3 float32 colour
_COMMAND_BYTES = 20  # DrawElementsIndirectCommand: count, instanceCount, firstIndex, baseVertex, baseInstance


class TerrainRenderer:
    """Draws tile meshes into an offscreen framebuffer (or a window's default framebuffer).

    Two draw paths, the same pixels:

    - ``"indirect"`` (OpenGL >= 4.3): every tile lives in one shared vertex buffer and one shared index
      buffer (first-fit arenas, grown on demand), and a frame is one ``glMultiDrawElementsIndirect`` call;
      per-tile data (origin relative to the eye, colour) is an instanced attribute picked by each
      command's ``baseInstance``. Indices stay tile-local (``baseVertex``).
    - ``"plain"``: a buffer pair per tile, one draw call per tile (OpenGL 3.3).

    ``draw_mode="auto"`` picks indirect where the context offers 4.3.

    Parameters
    ----------
    width_px, height_px : viewport size
    ctx : a moderngl context; a standalone EGL one is created when None
    memory_budget_bytes : GPU bytes of tile geometry kept; least recently drawn tiles are released beyond it
    draw_mode : "auto", "indirect" or "plain"
    """

    def __init__(
        self, width_px: int, height_px: int, *, ctx=None, memory_budget_bytes: int = 512 * 2**20,
        draw_mode: str = "auto",
    ) -> None:  # fmt: skip
        import moderngl

        self.ctx = ctx if ctx is not None else create_offscreen_context()
        if draw_mode not in ("auto", "indirect", "plain"):
            raise ValueError(f"Expected draw_mode auto, indirect or plain, got {draw_mode!r}")
        if draw_mode == "auto":
            draw_mode = "indirect" if self.ctx.version_code >= 430 else "plain"
        elif draw_mode == "indirect" and self.ctx.version_code < 430:
            raise DisplayError(f"Indirect draws need OpenGL 4.3, this context has {self.ctx.version_code}")
        self.draw_mode = draw_mode
        self.gl_renderer = str(self.ctx.info.get("GL_RENDERER", "?"))
        self.width_px, self.height_px = int(width_px), int(height_px)
        self.memory_budget_bytes = memory_budget_bytes
        vert = (_SHADERS / "terrain.vert").read_text()
        if draw_mode == "indirect":
            vert = vert.replace("#version 330 core\n", "#version 330 core\n#define INDIRECT 1\n", 1)
        self.prog = self.ctx.program(
            vertex_shader=vert, fragment_shader=(_SHADERS / "terrain.frag").read_text()
        )
        ramp = self._ramp_texture()
        self.ramp = self.ctx.texture((256, 1), 3, ramp.tobytes())
        self.ramp.filter = (moderngl.LINEAR, moderngl.LINEAR)
        self.ramp.repeat_x = False
        self._tiles: OrderedDict[tuple, _GpuTile] = OrderedDict()
        self._frame: set = set()
        self.gpu_bytes = 0
        self.uploads = 0
        self.updates = 0
        self.bytes_uploaded = 0
        self.bytes_written = 0
        self.draw_calls = 0
        self.fbo = None
        if draw_mode == "indirect":
            self._varena = _Arena(0)
            self._iarena = _Arena(0)
            self._vbuf = self._ibuf = None
            self._draw_capacity = 0
            self._inst = self._cmd = self._vao = None
            self._grow_geometry(1 << 16, 1 << 18)
            self._grow_draws(256)
        if ctx is None:
            self._make_fbo()

    @property
    def gpu_bytes_reserved(self) -> int:
        """GPU bytes held by tile geometry buffers (arena capacity for indirect draws)."""
        if self.draw_mode == "indirect":
            return self._varena.capacity * _VERTEX_BYTES + self._iarena.capacity * 4
        return self.gpu_bytes

    def _make_fbo(self) -> None:
        self.fbo = self.ctx.simple_framebuffer((self.width_px, self.height_px), components=4)

    @staticmethod
    def _ramp_texture() -> np.ndarray:
        t = np.linspace(0, 1, 256)
        stops = np.array([s for s, _ in _RAMP])
        cols = np.array([c for _, c in _RAMP])
        rgb = np.stack([np.interp(t, stops, cols[:, k]) for k in range(3)], axis=1)
        return (rgb * 255).astype(np.uint8)

    # -- shared arenas (indirect draws) ---------------------------------------------------------------
    def _make_vao(self) -> None:
        if self._vao is not None:
            self._vao.release()
        self._vao = self.ctx.vertex_array(
            self.prog,
            [
                (self._vbuf, "3f 3f", "in_position", "in_normal"),
                (self._inst, "4f 3f/i", "in_tile", "in_colour"),
            ],
            index_buffer=self._ibuf,
            index_element_size=4,
        )

    def _grow_geometry(self, vertices: int, indices: int) -> None:
        """Grow the shared buffers to hold at least ``vertices`` / ``indices`` (contents kept)."""
        for name, arena, unit, need in (("_vbuf", self._varena, _VERTEX_BYTES, vertices),
                                        ("_ibuf", self._iarena, 4, indices)):  # fmt: skip
            if need <= arena.capacity:
                continue
            cap = max(int(need), arena.capacity * 2)
            buf = self.ctx.buffer(reserve=cap * unit)
            old = getattr(self, name)
            if old is not None:
                if arena.capacity:
                    self.ctx.copy_buffer(buf, old, size=arena.capacity * unit)
                old.release()
            setattr(self, name, buf)
            arena.grow(cap)
        if self._inst is not None:
            self._make_vao()

    def _grow_draws(self, n: int) -> None:
        if n <= self._draw_capacity:
            return
        cap = max(n, self._draw_capacity * 2)
        for name, unit in (("_inst", _INSTANCE_BYTES), ("_cmd", _COMMAND_BYTES)):
            old = getattr(self, name)
            if old is not None:
                old.release()
            setattr(self, name, self.ctx.buffer(reserve=cap * unit))
        self._draw_capacity = cap
        self._make_vao()

    def _place(self, n_vertices: int, n_indices: int, keep: set) -> tuple[int, int]:
        """Ranges for a tile in the arenas: grow them while the memory budget allows, else evict the least
        recently drawn tiles (never those of the frame being drawn), else grow past the budget."""
        while True:
            fv = self._varena.alloc(n_vertices)
            fi = self._iarena.alloc(n_indices) if fv is not None else None
            if fv is not None and fi is not None:
                return fv, fi
            if fv is not None:
                self._varena.release(fv, n_vertices)
            nv = max(self._varena.capacity + n_vertices, 2 * self._varena.capacity)
            ni = max(self._iarena.capacity + n_indices, 2 * self._iarena.capacity)
            if nv * _VERTEX_BYTES + ni * 4 <= self.memory_budget_bytes:
                self._grow_geometry(nv, ni)
                continue
            victim = next((c for c in self._tiles if c not in keep), None)
            if victim is not None:
                self._release(victim)
                continue
            self._grow_geometry(self._varena.capacity + n_vertices, self._iarena.capacity + n_indices)

    # -- tile buffers ----------------------------------------------------------------------------------
    def upload(
        self, code: tuple, vertices: np.ndarray, triangles: np.ndarray, normals: np.ndarray | None
    ) -> None:
        """Make tile ``code`` drawable with this geometry. Unchanged tiles cost one checksum; changed
        geometry of the same size (stitched boundaries) is written into the existing buffer."""
        with self.ctx:
            self._upload(code, vertices, triangles, normals)

    def _upload(
        self, code: tuple, vertices: np.ndarray, triangles: np.ndarray, normals: np.ndarray | None
    ) -> None:
        if normals is None:
            normals = vertex_normals(vertices, triangles)
        # the tile origin: the vertex-grid corner, stable when stitching moves boundary heights
        origin = np.floor(vertices.min(axis=0) / 64.0) * 64.0
        data = np.empty((len(vertices), 6), np.float32)
        data[:, :3] = vertices - origin
        data[:, 3:] = normals
        raw = data.tobytes()
        digest = zlib.crc32(raw)
        idx = np.ascontiguousarray(triangles, dtype=np.uint32)
        tri_digest = zlib.crc32(idx.tobytes())
        g = self._tiles.get(code)
        keep = self._frame | {code}
        if g is not None:
            self._tiles.move_to_end(code)
            if g.digest == digest and g.tri_digest == tri_digest:
                return
            if g.n_vertices == len(data) and g.n_indices == idx.size and np.array_equal(g.origin, origin):
                # stitched borders: write only the runs of vertices that changed (small buffer writes)
                vbo = g.vbo if self.draw_mode == "plain" else self._vbuf
                base = 0 if self.draw_mode == "plain" else g.first_vertex * _VERTEX_BYTES
                changed = np.flatnonzero((g.data != data).any(axis=1))
                if changed.size:
                    breaks = np.flatnonzero(np.diff(changed) > 1)
                    starts = np.r_[changed[0], changed[breaks + 1]]
                    ends = np.r_[changed[breaks], changed[-1]] + 1
                    for a, b in zip(starts, ends, strict=True):
                        vbo.write(data[a:b].tobytes(), offset=base + int(a) * _VERTEX_BYTES)
                        self.bytes_written += int(b - a) * _VERTEX_BYTES
                if g.tri_digest != tri_digest:
                    if self.draw_mode == "plain":
                        g.ibo.write(idx.tobytes())
                    else:
                        self._ibuf.write(idx.tobytes(), offset=g.first_index * 4)
                    self.bytes_written += idx.nbytes
                g.data = data
                g.digest = digest
                g.tri_digest = tri_digest
                self.updates += 1
                return
            self._release(code)
        nbytes = len(raw) + idx.nbytes
        g = _GpuTile(origin, idx.size, len(data), nbytes, digest, tri_digest, int(code[0]), data)
        if self.draw_mode == "plain":
            g.vbo = self.ctx.buffer(raw)
            g.ibo = self.ctx.buffer(idx.tobytes())
            g.vao = self.ctx.vertex_array(
                self.prog,
                [(g.vbo, "3f 3f", "in_position", "in_normal")],
                index_buffer=g.ibo,
                index_element_size=4,
            )
        else:
            g.first_vertex, g.first_index = self._place(len(data), idx.size, keep)
            self._vbuf.write(raw, offset=g.first_vertex * _VERTEX_BYTES)
            self._ibuf.write(idx.tobytes(), offset=g.first_index * 4)
        self._tiles[code] = g
        self.gpu_bytes += nbytes
        self.bytes_uploaded += nbytes
        self.uploads += 1
        self._evict(keep)

    def _release(self, code: tuple) -> None:
        g = self._tiles.pop(code)
        if self.draw_mode == "plain":
            g.vao.release()
            g.vbo.release()
            g.ibo.release()
        else:
            self._varena.release(g.first_vertex, g.n_vertices)
            self._iarena.release(g.first_index, g.n_indices)
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
        frame as (H, W, 3) uint8 (row 0 at the top) when ``read``. Makes this renderer's context current
        for the call, so several renderers can share a thread."""
        with self.ctx:
            return self._render(meshes, eye, target, up, fov_y_deg, settings, tile_colours, read)

    def _render(self, meshes, eye, target, up, fov_y_deg, settings, tile_colours, read) -> np.ndarray | None:
        import moderngl

        st = settings or RenderSettings()
        eye = np.asarray(eye, np.float64)
        target = np.asarray(target, np.float64)
        meshes = [m for m in meshes if len(m[2])]  # tiles wholly over nodata store no triangle
        codes = [m[0] for m in meshes]
        self._frame = set(codes)
        zlo, zhi = math.inf, -math.inf
        for m in meshes:
            code, v, t, n = m[0], m[1], m[2], (m[3] if len(m) > 3 else None)
            self._upload(code, v, t, n)
            zlo, zhi = min(zlo, float(v[:, 2].min())), max(zhi, float(v[:, 2].max()))
        near, far = depth_range(meshes, eye, st.z_exaggeration)
        self._evict(keep=self._frame)
        self._frame = set()
        if self.fbo is not None:
            self.fbo.use()
        ctx = self.ctx
        ctx.viewport = (0, 0, self.width_px, self.height_px)
        ctx.clear(*st.background, 1.0)
        ctx.enable(moderngl.DEPTH_TEST)
        if st.cull_back_faces:
            ctx.enable(moderngl.CULL_FACE)
            ctx.front_face = "ccw"
        else:
            ctx.disable(moderngl.CULL_FACE)
        ctx.wireframe = st.wireframe
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
        if "u_water" in self.prog:  # (a shader variant may draw no water)
            self.prog["u_water"].value = tuple(map(float, st.water_m)) if st.water_m else (1.0, -1.0)
            self.prog["u_water_colour"].value = tuple(map(float, st.water_colour))
        dist = float(np.linalg.norm(target - eye))
        self.prog["u_fog_distance"].value = (dist * 6.0) if st.fog else 1e12
        self.prog["u_z_exaggeration"].value = float(st.z_exaggeration)
        self.prog["u_mode"].value = {"elevation": 0, "lod": 1, "error": 2, "facing": 3}[st.mode]
        self.ramp.use(0)
        self.prog["u_ramp"].value = 0
        self.prog["u_overlay"].value = 0 if st.overlay is None else 1
        if st.overlay is not None:
            self._bind_change(st.overlay, eye)
        n = len(codes)
        inst = np.empty((n, 7), np.float32)
        for i, c in enumerate(codes):
            g = self._tiles[c]
            inst[i, :3] = g.origin - eye
            inst[i, 3] = g.origin[2]
            if st.mode == "lod":
                inst[i, 4:] = LEVEL_COLOURS[g.level % len(LEVEL_COLOURS)]
            elif st.mode == "error" and tile_colours is not None:
                inst[i, 4:] = tile_colours.get(c, (1.0, 0.0, 1.0))
            else:
                inst[i, 4:] = 1.0
        if self.draw_mode == "indirect":
            if n:
                self._grow_draws(n)
                cmd = np.empty((n, 5), np.uint32)
                for i, c in enumerate(codes):
                    g = self._tiles[c]
                    cmd[i] = (g.n_indices, 1, g.first_index, g.first_vertex, i)
                self._inst.write(inst.tobytes())
                self._cmd.write(cmd.tobytes())
                self._vao.render_indirect(self._cmd, moderngl.TRIANGLES, count=n)
                self.draw_calls += 1
        else:
            for i, c in enumerate(codes):
                g = self._tiles[c]
                self.prog["u_tile_offset"].value = tuple(map(float, inst[i, :3]))
                self.prog["u_origin_z"].value = float(inst[i, 3])
                self.prog["u_tile_colour"].value = tuple(map(float, inst[i, 4:]))
                g.vao.render(moderngl.TRIANGLES)
                self.draw_calls += 1
        ctx.wireframe = False
        if not read:
            return None
        fbo = self.fbo if self.fbo is not None else ctx.screen
        raw = fbo.read(components=3, alignment=1)
        img = np.frombuffer(raw, np.uint8).reshape(self.height_px, self.width_px, 3)
        return img[::-1].copy()

    def _bind_change(self, ov, eye: np.ndarray) -> None:
        """Upload (once per overlay) the change grid as an RG float texture and set its uniforms."""
        import moderngl

        from terralod.render import overlay as ovm

        if getattr(self, "_change_key", None) != ov.key:
            d = np.asarray(ov.change_m, np.float32)
            rg = np.empty(d.shape + (2,), np.float32)
            rg[..., 0] = np.nan_to_num(d, nan=0.0)
            rg[..., 1] = np.isfinite(d)
            old = getattr(self, "_change_tex", None)
            if old is not None:
                old.release()
            self._change_tex = self.ctx.texture((d.shape[1], d.shape[0]), 2, rg.tobytes(), dtype="f4")
            self._change_tex.filter = (moderngl.LINEAR, moderngl.LINEAR)
            self._change_tex.repeat_x = self._change_tex.repeat_y = False
            self._change_key = ov.key
        t = ov.transform
        h, w = ov.change_m.shape
        self._change_tex.use(1)
        p = self.prog
        p["u_change"].value = 1
        p["u_change_origin"].value = (float(t.c - eye[0]), float(t.f - eye[1]))
        p["u_change_scale"].value = (1.0 / (w * t.a), 1.0 / (h * t.e))
        p["u_change_lod"].value = float(ov.lod_m)
        p["u_change_max"].value = float(ov.max_m)
        for name, rgb in (("u_gain_light", ovm.GAIN_LIGHT), ("u_gain_dark", ovm.GAIN_DARK),
                          ("u_loss_light", ovm.LOSS_LIGHT), ("u_loss_dark", ovm.LOSS_DARK)):  # fmt: skip
            p[name].value = tuple(float(c) for c in rgb)

    @property
    def tiles_resident(self) -> int:
        return len(self._tiles)

    def release(self) -> None:
        with self.ctx:
            self._release_all()

    def _release_all(self) -> None:
        for code in list(self._tiles):
            self._release(code)
        if self.draw_mode == "indirect":
            for b in (self._vao, self._vbuf, self._ibuf, self._inst, self._cmd):
                if b is not None:
                    b.release()
        if self.fbo is not None:
            self.fbo.release()
