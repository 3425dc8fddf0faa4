"""OGC 3D Tiles 1.1 export of any terrain: ``tileset.json`` + one binary glTF 2.0 per LOD node.

Where a tile's bytes are decided: all here. The mesh is the store's own node (no re-meshing), the
normals, skirts and ECEF positions are made in :meth:`Tiles3D.glb` and written by ``_write_glb``. A glb is
a function of the store and the node's code alone (a node's normals are summed over the nodes of its level
that share its vertex positions, in the level's order: the same whichever block of the level it is encoded
with, see below), whatever was encoded before it.

Cost: linear in the triangles exported. The topology (lone edges, used vertices, positions merged) is
made by the kernels of :mod:`terralod.kernels.meshtopo` (counting sorts and hashing, not row sorts), a point
array shared by every node (a TIN's) is converted to geographic and ECEF coordinates once, and the export
walks the tree level by level and each level block by block (:func:`terralod.export.distributed.level_blocks`:
square cells of about 256 nodes, each built with the nodes around it), keeping one block's meshes at a time:
a whole level's (the finest level of 16 SRTM3 tiles: 62 M triangles) took 5.4 GiB.

The tileset is the terrain's static LOD tree (:meth:`terralod.terrain.Terrain.lod_tree`) as stored:
REPLACE refinement. ``geometricError`` as the specification defines it: a tile's is the error of drawing it
instead of its children, i.e. the node's *measured* error in metres (the one-sided Hausdorff ``error_m``, or
``vertical_error_m`` with ``metric="vertical"``; never below a child's); the tileset's is the error of
drawing nothing at all, the terrain's whole extent (diagonal with relief), so that CesiumJS at its default
``maximumScreenSpaceError`` draws the coarse root from any distance at which the terrain covers more than a
few pixels. A terrain with several roots (the sub-blocks of a TIN) gets one content-less root above them,
with the tileset's error (drawing it is drawing nothing). Bounding volumes are ``region``s of the stored node boxes (their edges
sampled through pyproj, the skirt depth below ``z_min``).

Each glb (written with pygltflib) holds one triangle mesh: positions relative to the tile centre (the
centre's ECEF is the tile's ``transform`` composed with its ancestors', as 3D Tiles composes them), converted exactly from the store's CRS with pyproj; heights are
the DEM's as read, used as ellipsoidal heights (no geoid change). glTF is y-up: positions are stored as
(x, z, -y) of ECEF so that the 3D Tiles y-up → z-up rotation gives ECEF back. Vertices are renumbered in
the order the triangles first use them (the index stream then climbs slowly: fewer bytes after gzip or
meshopt). Indices are UNSIGNED_BYTE, UNSIGNED_SHORT or UNSIGNED_INT, the smallest that holds the vertex
count without its largest value, which glTF reserves for primitive restart (UNSIGNED_SHORT at least under
meshopt, whose triangle codec takes 2- or 4-byte indices).

Geometry (``geometry=``), as gltfpack writes it:

- ``"float"``: float32 positions and normals (24 B a vertex before indices);
- ``"quantized"`` (default, ``KHR_mesh_quantization``): positions as unnormalized UNSIGNED_SHORT on a grid
  of step ``q`` (a power of two, so exact in float32), the dequantisation ``p = q · (u + o)`` folded into
  the glTF node's uniform ``scale`` and ``translation`` (uniform, so normals transform unchanged); normals
  as normalized BYTE. Each vertex element is padded to 4 bytes (glTF's vertex alignment): 8 B + 4 B.
  ``q`` is a function of the node's box alone (:meth:`Tiles3D.quant_step_m`: the box's ECEF extent,
  sampled, padded 2 %, over 65535 steps), so the tileset needs no mesh. Rounding to the nearest step moves
  a vertex by at most ``q/2`` along each axis, ``√3·q/2`` in all (:meth:`Tiles3D.quant_error_m`), and a
  triangle's points, convex combinations of its vertices, by no more: that bound is added to the tile's
  declared error and to the skirts, and each glb's actual worst shift is recorded in the export report;
- ``"meshopt"``: the quantized layout with every buffer view compressed by ``EXT_meshopt_compression``
  (vertex codec version 0, triangle codec; the spec's fallback buffer, no uncompressed copy), encoded by
  the npm ``meshoptimizer`` package's own encoder through node (:class:`MeshoptEncoder`).

``max_error_m``: the tree stops at a finest declared error. A node is left out when its parent's declared
error (in the whole tree) is already at most ``max_error_m``; the kept nodes are a subtree, and its leaves
declare their own errors (each ≤ ``max_error_m`` unless the whole tree's finest level is coarser).

Normals: the nodes of one level (one rung of a TIN) are merged by position and their area-weighted face
normals summed (:func:`terralod.runtime.normals.reference_normals`, the normals of the uniform-LoD mesh,
what the runtime's stitcher gives same-level neighbours, Li, Liu & Liu §3.4), so the lighting is continuous
across the borders of same-level tiles. Across a level change the two tiles have different geometry, and
their normals differ as much as their surfaces do.

Cracks between tiles of different levels (which CesiumJS mixes freely) are closed by skirts: every border
edge of a tile's mesh gets a vertical wall hanging down by ``vertical_error(tile) + vertical_error(parent)``,
which bounds the height gap to any neighbour of the same or the parent's level (each surface lies within
its measured vertical error of the source on the shared border, and errors are monotone up the tree). The
walls are as short as the errors: never the long spikes of fixed-depth skirts. Skirt vertices carry the
normal of the border vertex above them.

Nodata: when the source DEM of a grid store can be read again, triangles whose centroid falls on a nodata
sample are dropped (the web formats' convention for 3D Tiles; quantized-mesh keeps the fill).
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable, Generator, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from terralod.export.common import check_exportable, export_inputs, export_key, source_validity, valid_at
from terralod.export.geodesy import Geodesy

__all__ = ["ExportReport", "Tiles3D", "export_3dtiles", "node_uri", "split_tileset"]

#: Skirts never shorter than this (metres): closes float rounding where both errors are zero.
MIN_SKIRT_M = 0.01
#: The glb geometry encodings (see the module's docstring).
GEOMETRIES = ("float", "quantized", "meshopt")
#: Steps of the position grid across a tile (UNSIGNED_SHORT).
QUANT_STEPS = 65535
#: The sampled ECEF extent of a node's box is padded by this fraction, and by PAD_M metres, before it is
#: divided into QUANT_STEPS (the box's faces bulge between samples by far less: a 100 km box, 9 samples a
#: side, by under 4 m of its 100 km).
QUANT_PAD = 0.02
QUANT_PAD_M = 1.0


#: Levels of the tree one tileset file holds: every node this many levels below the root of its file that
#: has children starts an external tileset (``tileset-K.json``), so no file grows with the region (a
#: 7.9 M-cell store's one tileset.json was 3.26 MB) and a viewer fetches the parts it refines into.
SPLIT_LEVELS = 4


def split_tileset(ts: dict[str, Any], levels: int = SPLIT_LEVELS) -> dict[str, dict[str, Any]]:
    """``ts`` (one nested tileset) as files: ``{"tileset.json": ..., "tileset-K.json": ...}``.

    A node ``levels`` levels below the root of its file, with children, moves with its subtree to an
    external tileset (3D Tiles 1.1 § External tilesets): in its place a tile with the same bounding volume,
    geometric error and transform whose content is the external file; the external file's root is the node
    itself without a transform (it composes with the referencing tile's) and with its refinement stated.
    Files sit beside tileset.json, so every content URI keeps its meaning; K counts the external files in
    the order a depth-first walk meets them, so the same tree always gives the same files."""
    files: dict[str, dict[str, Any]] = {}
    counter = [0]
    refine = ts["root"].get("refine", "REPLACE")

    def cut(tile: dict[str, Any], depth: int) -> dict[str, Any]:
        kids = tile.get("children")
        if depth > 0 and depth % levels == 0 and kids:
            counter[0] += 1
            name = f"tileset-{counter[0]}.json"
            root = {k: v for k, v in tile.items() if k != "transform"}
            root["refine"] = tile.get("refine", refine)
            root["children"] = [cut(k, 1) for k in kids]
            files[name] = {"asset": ts["asset"], "geometricError": tile["geometricError"], "root": root}
            ref = {k: tile[k] for k in ("boundingVolume", "geometricError", "transform") if k in tile}
            ref["content"] = {"uri": name}
            return ref
        out = dict(tile)
        if kids:
            out["children"] = [cut(k, depth + 1) for k in kids]
        return out

    files["tileset.json"] = {**ts, "root": cut(ts["root"], 0)}
    return files


def node_uri(code: tuple[int, int, int]) -> str:
    """Content URI of a node, relative to the tileset."""
    return f"tiles/{code[0]}/{code[1]}_{code[2]}.glb"


@dataclass
class ExportReport:
    """What an export wrote."""

    path: Path
    tiles: int = 0
    bytes: int = 0
    triangles: int = 0
    seconds: float = 0.0
    extra: dict[str, Any] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        return {"path": str(self.path), "tiles": self.tiles, "bytes": self.bytes, "triangles": self.triangles,
                "seconds": round(self.seconds, 3), **self.extra}  # fmt: skip


def boundary_edges(triangles: np.ndarray) -> np.ndarray:
    """(E, 2) directed edges used by exactly one triangle, in the triangles' (counter-clockwise) order:
    every ``(t0, t1)`` edge of such, then every ``(t1, t2)``, then every ``(t2, t0)``."""
    from terralod.kernels.meshtopo import lone_edge_mask

    t = np.ascontiguousarray(triangles, np.int64)
    if t.size == 0:
        return np.zeros((0, 2), np.int64)
    e = np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]])
    return e[lone_edge_mask(t, int(t.max()) + 1)]


def _position_groups(v: np.ndarray) -> np.ndarray:
    """(N,) int64: one group for the vertices at the same (x, y) rounded to 0.1 mm (the merge of
    :func:`terralod.runtime.normals.reference_normals` at 4 decimals)."""
    from terralod.kernels.meshtopo import merge_pairs

    xy = np.ascontiguousarray(np.round(np.asarray(v)[:, :2], 4) + 0.0)  # -0.0 → 0.0: equal values, equal bits
    return merge_pairs(xy.view(np.int64).reshape(-1, 2))


@dataclass
class _Level:
    """The nodes of one level (one rung of a TIN) with the normals of their merged mesh.

    ``nodes[code] = (points, used, local)``: the node's vertex array as the terrain gave it, the rows of
    it the node's triangles use (ascending) and those triangles renumbered into them; ``normals[code]``
    (len(used), 3) float32."""

    nodes: dict[Any, tuple[np.ndarray, np.ndarray, np.ndarray]]
    normals: dict[Any, np.ndarray]


class Tiles3D:
    """The 3D Tiles view of one terrain: :meth:`tileset` (JSON dict) and :meth:`glb` per node (bytes).

    Used by :func:`export_3dtiles` (every node to files) and by ``terralod serve`` (on request).
    """

    def __init__(
        self,
        terrain: Any,
        *,
        metric: str = "hausdorff",
        drop_nodata: bool = True,
        vertical_datum: str | None = None,
        geometry: str = "quantized",
        max_error_m: float | None = None,
        encoder: MeshoptEncoder | None = None,
    ) -> None:
        if metric not in ("hausdorff", "vertical"):
            raise ValueError(f"Expected metric hausdorff or vertical, got {metric!r}")
        if geometry not in GEOMETRIES:
            raise ValueError(f"Expected geometry one of {', '.join(GEOMETRIES)}, got {geometry!r}")
        if max_error_m is not None and not max_error_m >= 0:
            raise ValueError(f"Expected max_error_m >= 0, got {max_error_m!r}")
        self.terrain = terrain
        self.metric = metric
        self.geometry = geometry
        self.max_error_m = max_error_m
        self._encoder = encoder  # made on the first meshopt glb when not given
        self._quant: dict[Any, tuple[float, float]] = {}
        where = str(terrain.path) if terrain.path is not None else None
        self.geo = Geodesy(terrain.crs, where, vertical_datum=vertical_datum)
        self.geo.geoid  # noqa: B018 - fail now, not mid-export, when PROJ lacks the datum's geoid grid
        self.tree = terrain.lod_tree()
        self.nodes = {n.code: n for n in self.tree}
        self.children: dict[Any, list[Any]] = {}
        for n in self.tree:
            self.children.setdefault(n.parent, []).append(n.code)
        self._tile_errors: dict[Any, float] = {}
        self._spread: dict[Any, float] = {}
        if max_error_m is not None:
            self._prune(float(max_error_m))
        self._levels: dict[int, _Level] = {}
        self._by_level: dict[int, list[Any]] | None = None  # level_nodes(), made on first use
        self._tree_pos: dict[Any, int] = {}
        self._boxes: dict[int, np.ndarray] = {}
        self._content: dict[Any, bool] = {}
        self._triangles: dict[Any, int] = {}  # triangles of each node made, before the nodata drop
        # a point array shared by several nodes (a TIN's), converted once: lon, lat, ellipsoidal height,
        # ECEF, and the east, north, up vectors (each a pointwise function of one vertex)
        self._shared: np.ndarray | None = None
        self._shared_frame: tuple[np.ndarray, ...] | None = None
        self._shared_groups: np.ndarray | None = None
        self._hf = source_validity(terrain) if drop_nodata else None
        if self._hf is not None and bool(self._hf.valid.all()):
            self._hf = None

    def _prune(self, max_error_m: float) -> None:
        """Keep the roots and the nodes whose parent declares more than ``max_error_m`` in the whole tree
        (declared errors fall down the tree, so the kept nodes are a subtree)."""
        keep = [n for n in self.tree if n.parent is None or self.tile_error_m(n.parent) > max_error_m]
        self.tree = keep
        self._by_level, self._boxes = None, {}
        self.nodes = {n.code: n for n in keep}
        self.children = {}
        for n in keep:
            self.children.setdefault(n.parent, []).append(n.code)
        self._tile_errors = {}  # the leaves now declare their own errors

    # -- errors ------------------------------------------------------------------------------------------
    def error_m(self, code: Any) -> float:
        """The node's measured error, plus the spread of the geoid undulation over it when heights are made
        ellipsoidal (each vertex moves by its own undulation, each sample by its own)."""
        n = self.nodes[code]
        return float(n.vertical_error_m if self.metric == "vertical" else n.error_m) + self._geoid_m(code)

    def _geoid_m(self, code: Any) -> float:
        if self.geo.geoid is None:
            return 0.0
        if code not in self._spread:
            self._spread[code] = self.geo.undulation_spread_m(self.nodes[code].box_m)
        return self._spread[code]

    def tile_error_m(self, code: Any) -> float:
        """A tile's ``geometricError``: the error of drawing it instead of its children, i.e. its measured
        error plus what its glb's position encoding adds (:meth:`quant_error_m`), never below a child's (the
        specification's monotone errors down the tree)."""
        if code not in self._tile_errors:
            kids = self.children.get(code, [])
            own = self.error_m(code) + self.quant_error_m(code)
            self._tile_errors[code] = max([own, *(self.tile_error_m(k) for k in kids)])
        return self._tile_errors[code]

    def _extent(self, code: Any) -> tuple[float, float]:
        """(span, reach), metres: the largest axis extent of the node's box in ECEF (its top and its skirts'
        bottom, a 9 × 9 grid each, heights made ellipsoidal), padded by QUANT_PAD and QUANT_PAD_M, and the
        largest distance of an axis coordinate from the tile centre, padded alike."""
        if code not in self._quant:
            n = self.nodes[code]
            w, s, z0, e, nn, z1 = n.box_m
            gx, gy = np.meshgrid(np.linspace(w, e, 9), np.linspace(s, nn, 9))
            lon, lat = self.geo.lonlat(gx.ravel(), gy.ravel())
            low = float(z0) - self._skirt_raw_m(code)
            pts = [self.geo.ecef_lonlat(lon, lat, self.geo.ellipsoidal(lon, lat, np.full(lon.size, z)))
                   for z in (low, float(z1))]  # fmt: skip
            rel = np.concatenate(pts) - self._centre(n)
            span = float((rel.max(axis=0) - rel.min(axis=0)).max()) * (1.0 + QUANT_PAD) + QUANT_PAD_M
            reach = float(np.abs(rel).max()) * (1.0 + QUANT_PAD) + QUANT_PAD_M
            self._quant[code] = (span, reach)
        return self._quant[code]

    def quant_step_m(self, code: Any) -> float:
        """The position grid step of a quantized glb, metres: the smallest power of two that divides the
        node's padded ECEF extent (:meth:`_extent`) into at most QUANT_STEPS steps."""
        return float(2.0 ** math.ceil(math.log2(self._extent(code)[0] / QUANT_STEPS)))

    def quant_error_m(self, code: Any) -> float:
        """The most a vertex of the node's glb is moved by its encoding, metres: √3·q/2 on the quantized
        grid (half a step on each axis); with float32, half a unit in the last place of the largest
        coordinate relative to the tile centre on each axis, √3 · reach · 2⁻²⁴."""
        if self.geometry == "float":
            return math.sqrt(3.0) * self._extent(code)[1] * 2.0**-24
        return math.sqrt(3.0) * 0.5 * self.quant_step_m(code)

    def nothing_error_m(self) -> float:
        """The tileset's ``geometricError``: the error of drawing nothing at all, i.e. the terrain's whole
        extent (horizontal diagonal and relief; never below the roots' errors)."""
        w, s, e, n = self.terrain.bounds_m
        boxes = [self.nodes[c].box_m for c in self.children.get(None, [])]
        relief = max(b[5] for b in boxes) - min(b[2] for b in boxes)
        extent = math.sqrt((e - w) ** 2 + (n - s) ** 2 + relief**2)
        return float(max(extent, *(self.tile_error_m(c) for c in self.children.get(None, [])), 1.0))

    def _skirt_raw_m(self, code: Any) -> float:
        """The skirt's depth before the encoding's shifts: both measured vertical errors and geoid spreads."""
        n = self.nodes[code]
        up = self.nodes[n.parent].vertical_error_m if n.parent is not None else n.vertical_error_m
        spread = self._geoid_m(code) + (self._geoid_m(n.parent) if n.parent is not None else 0.0)
        return float(n.vertical_error_m) + float(up) + spread

    def skirt_m(self, code: Any) -> float:
        """How far a tile's skirts hang below its border, metres: the tile's and its parent's measured
        vertical errors, geoid spreads and encoding shifts (:meth:`quant_error_m`), so that the gap to any
        neighbour of the same or the parent's level is covered."""
        n = self.nodes[code]
        shift = self.quant_error_m(code) + (self.quant_error_m(n.parent) if n.parent is not None else 0.0)
        return max(self._skirt_raw_m(code) + shift, MIN_SKIRT_M)

    # -- a part ------------------------------------------------------------------------------------------
    def lonlat_box(self, code: Any) -> tuple[float, float, float, float]:
        """(west, south, east, north) degrees of a node's box (its edges densified, 17 points each)."""
        w, s, _, e, nn, _ = self.nodes[code].box_m
        k = np.linspace(0.0, 1.0, 17)
        x = np.concatenate([w + (e - w) * k, np.full(17, e), w + (e - w) * k, np.full(17, w)])
        y = np.concatenate([np.full(17, s), s + (nn - s) * k, np.full(17, nn), s + (nn - s) * k])
        lon, lat = self.geo.lonlat(x, y)
        return float(np.min(lon)), float(np.min(lat)), float(np.max(lon)), float(np.max(lat))

    def part_nodes(self, part: Any) -> set[Any]:
        """The nodes of a part of the tree (``part``: :class:`terralod.export.quantized_mesh.Part`, its
        zooms the tree's levels): those of levels up to ``max_zoom`` whose box meets ``bbox``, with their
        ancestors (a valid tree). Each node's glb is the whole export's: the part chooses which are written."""
        top = math.inf if part.max_zoom is None else part.max_zoom
        keep = set()
        for code in self.nodes:
            if code[0] > top:
                continue
            if part.bbox is not None:
                w, s, e, n = self.lonlat_box(code)
                pw, ps, pe, pn = part.bbox
                if w > pe or e < pw or s > pn or n < ps:
                    continue
            keep.add(code)
        for code in list(keep):  # ancestors, so every kept node hangs from a root
            up = self.nodes[code].parent
            while up is not None and up not in keep:
                keep.add(up)
                up = self.nodes[up].parent
        return keep

    # -- tileset -----------------------------------------------------------------------------------------
    def _tile_json(self, code: Any, above: np.ndarray) -> dict[str, Any]:
        """A tile and its subtree; ``above`` is the ECEF translation its parent's transform already
        applies (3D Tiles transforms compose down the tree). With a part (:meth:`tileset`), only its nodes,
        and content only from its first level."""
        tile, c, kids = self._tile_head(code, above)
        if kids:
            tile["children"] = [self._tile_json(k, c) for k in kids]
        return tile

    def _tile_head(self, code: Any, above: np.ndarray) -> tuple[dict[str, Any], np.ndarray, list[Any]]:
        """(a tile without its children, its ECEF centre, its children's codes in the part)."""
        n = self.nodes[code]
        c = self._centre(n)
        w, s, z0, e, nn, z1 = n.box_m
        pad = self.quant_error_m(code)  # the encoded vertices may stand this far outside the box
        tile: dict[str, Any] = {
            "boundingVolume": {
                "region": self.geo.region(
                    (w - pad, s - pad, z0, e + pad, nn + pad, z1 + pad), self.skirt_m(code) + pad
                )
            },
            "geometricError": self.tile_error_m(code),
            "transform": self._transform(c - above),
        }
        if code[0] >= self._part_from and self.has_content(code):
            tile["content"] = {"uri": node_uri(code)}
        kids = [k for k in self.children.get(code, []) if self._part is None or k in self._part]
        return tile, c, kids

    def tileset_files(
        self, part: Any = None, levels: int = SPLIT_LEVELS
    ) -> Iterator[tuple[str, dict[str, Any]]]:
        """``split_tileset(self.tileset(part), levels)``'s files, the same JSON, each yielded as soon as its
        subtree is made (tileset.json last): memory holds the files open along one path of the tree (at
        most ``levels`` levels each), not the whole tileset (1.3 KB a node as Python objects, measured on the
        16-tile SRTM3 store: some 1.1 GB at the 853,358 nodes of 256 tiles)."""
        self._part = None if part is None or part.whole else self.part_nodes(part)
        self._part_from = 0 if part is None else int(part.min_zoom)
        counter = [0]
        head = self._tileset_head()
        asset = head["asset"]
        File = tuple[str, dict[str, Any]]

        def cut(code: Any, above: np.ndarray, depth: int) -> Generator[File, None, dict[str, Any]]:
            # split_tileset's cut, made from the tree as it goes (the same keys in the same order); yields
            # each external file as its subtree is done and returns the node's tile
            tile, c, kids = self._tile_head(code, above)
            if depth > 0 and depth % levels == 0 and kids:
                counter[0] += 1
                name = f"tileset-{counter[0]}.json"
                root = {k: v for k, v in tile.items() if k != "transform"}
                children = []
                for k in kids:
                    children.append((yield from cut(k, c, 1)))
                root["children"] = children
                root["refine"] = "REPLACE"
                yield name, {"asset": asset, "geometricError": tile["geometricError"], "root": root}
                ref = {k: tile[k] for k in ("boundingVolume", "geometricError", "transform") if k in tile}
                ref["content"] = {"uri": name}
                return ref
            if kids:
                children = []
                for k in kids:
                    children.append((yield from cut(k, c, depth + 1)))
                tile["children"] = children
            return tile

        try:
            roots = [c for c in self.children.get(None, []) if self._part is None or c in self._part]
            zero = np.zeros(3)
            if len(roots) == 1:
                root = yield from cut(roots[0], zero, 0)
            else:  # split_tileset cuts the made-up root's children at depth 1
                kids = []
                for c in roots:
                    kids.append((yield from cut(c, zero, 1)))
                root = self._common_root(kids)
            root["refine"] = "REPLACE"
            yield "tileset.json", {**head, "root": root}
        finally:
            self._part, self._part_from = None, 0

    def _centre(self, n: Any) -> np.ndarray:
        w, s, z0, e, nn, z1 = n.box_m
        return self.geo.ecef(np.array([[0.5 * (w + e), 0.5 * (s + nn), 0.5 * (z0 + z1)]]))[0]

    @staticmethod
    def _transform(c: np.ndarray) -> list[float]:
        return [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, float(c[0]), float(c[1]),
                float(c[2]), 1.0]  # fmt: skip

    _part: set[Any] | None = None  #: the nodes of a part being written (None: all)
    _part_from: int = 0  #: its first level with content

    def tileset(self, part: Any = None) -> dict[str, Any]:
        """The tileset JSON; with ``part`` (see :meth:`part_nodes`) only its nodes, content from its
        ``min_zoom`` (the coarser nodes are its tree without content)."""
        self._part = None if part is None or part.whole else self.part_nodes(part)
        self._part_from = 0 if part is None else int(part.min_zoom)
        try:
            return self._tileset()
        finally:
            self._part, self._part_from = None, 0

    def _tileset(self) -> dict[str, Any]:
        roots = [c for c in self.children.get(None, []) if self._part is None or c in self._part]
        if len(roots) == 1:
            root = self._tile_json(roots[0], np.zeros(3))
        else:
            root = self._common_root([self._tile_json(c, np.zeros(3)) for c in roots])
        root["refine"] = "REPLACE"
        return {**self._tileset_head(), "root": root}

    def _common_root(self, kids: list[dict[str, Any]]) -> dict[str, Any]:
        """A root without content over several roots' tiles (their regions' union)."""
        reg = np.array([k["boundingVolume"]["region"] for k in kids])
        return {
            "boundingVolume": {"region": [float(reg[:, 0].min()), float(reg[:, 1].min()),
                                          float(reg[:, 2].max()), float(reg[:, 3].max()),
                                          float(reg[:, 4].min()), float(reg[:, 5].max())]},
            "geometricError": self.nothing_error_m(),  # a root without content: drawing it is drawing nothing
            "children": kids,
        }  # fmt: skip

    def _tileset_head(self) -> dict[str, Any]:
        """The tileset's members before its root."""
        return {
            "asset": {"version": "1.1", "generator": "terralod", "tilesetVersion": "1"},
            "geometricError": self.nothing_error_m(),
            "extras": {"terralod": {"metric": self.metric, "crs": self.geo.crs.to_string()[:120],
                                    "error": "measured, metres", "heights": self.geo.vertical_record()}},
        }  # fmt: skip

    # -- content -----------------------------------------------------------------------------------------
    #: The nodes a level is built over (None: all): a block of the level and its neighbours
    #: (:func:`terralod.export.distributed.level_blocks`), whose glbs are then the whole level's.
    only: set[Any] | None = None

    def level_nodes(self, group: int) -> list[Any]:
        """The nodes of level ``group``, in the tree's order."""
        if self._by_level is None:
            self._by_level = {}
            self._tree_pos = {}
            for i, n in enumerate(self.tree):
                self._by_level.setdefault(n.code[0], []).append(n)
                self._tree_pos[n.code] = i
        return self._by_level.get(group, [])

    def level_boxes(self, group: int) -> np.ndarray:
        """(N, 4) west, south, east, north of level ``group``'s nodes (:meth:`level_nodes`' order), metres."""
        got = self._boxes.get(group)
        if got is None:
            nodes = self.level_nodes(group)
            got = self._boxes[group] = np.array([n.box_m for n in nodes], np.float64).reshape(-1, 6)[
                :, [0, 1, 3, 4]
            ]
        return got

    def level_vertices(self, group: int) -> np.ndarray | None:
        """(N,) vertices of level ``group``'s nodes (:meth:`level_nodes`' order) when the terrain counts them
        without making their meshes (a grid store does); None otherwise."""
        got = self.terrain.lod_vertices(group)
        if got is None:
            return None
        return np.array([got.get(n.code, 0) for n in self.level_nodes(group)], np.int64)

    def _level_codes(self, group: int) -> list[Any]:
        """The codes of level ``group``'s nodes (of ``only``), in the tree's order (the order their normals
        are summed)."""
        nodes = self.level_nodes(group)
        if self.only is None:
            return [n.code for n in nodes]
        return sorted(
            (c for c in self.only if c[0] == group and c in self.nodes), key=self._tree_pos.__getitem__
        )

    def _level(self, group: int) -> _Level:
        """The nodes of level ``group`` and their normals: the nodes merged by position (rounded to 0.1 mm)
        and their area-weighted face normals summed (:func:`terralod.runtime.normals.reference_normals`'s
        arithmetic, in the same order: each node's sums over its triangles, added node by node)."""
        lv = self._levels.get(group)
        if lv is not None:
            return lv
        from terralod.kernels.meshtopo import add_rows, compact_triangles
        from terralod.kernels.stitch import normal_sums, normalize_all

        nodes: dict[Any, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        seen: dict[int, int] = {}
        for c in self._level_codes(group):
            v, t = self.terrain.lod_mesh(c)
            v = np.asarray(v, np.float64)
            used, local = compact_triangles(np.ascontiguousarray(t, np.int64), len(v))
            nodes[c] = (v, used, local)
            self._triangles[c] = len(local)
            seen[id(v)] = seen.get(id(v), 0) + 1
        for v, _, _ in nodes.values():
            if seen[id(v)] > 1 and v is not self._shared:  # one point array for several nodes (a TIN's)
                self._shared, self._shared_frame, self._shared_groups = v, None, None
        if nodes and all(v is self._shared for v, _, _ in nodes.values()):
            # the groups of the shared array's positions, made once: a level's are their restriction
            if self._shared_groups is None:
                self._shared_groups = _position_groups(self._shared)
            groups = [self._shared_groups[used] for _, used, _ in nodes.values()]
            n_groups = int(self._shared_groups.max()) + 1 if self._shared_groups.size else 0
        else:
            xy = np.concatenate([v[used] for v, used, _ in nodes.values()]) if nodes else np.zeros((0, 3))
            merged = _position_groups(xy)
            n_groups = int(merged.max()) + 1 if merged.size else 0
            bounds = np.cumsum([0] + [used.size for _, used, _ in nodes.values()])
            groups = [merged[bounds[i] : bounds[i + 1]] for i in range(len(nodes))]
        acc = np.zeros((n_groups, 3))
        for (v, used, local), g in zip(nodes.values(), groups, strict=True):
            add_rows(acc, g, normal_sums(v[used], local))
        unit = normalize_all(acc)
        lv = _Level(nodes, {c: unit[g] for c, g in zip(nodes, groups, strict=True)})
        self._levels[group] = lv
        return lv

    def release(self, group: int) -> None:
        """Forget level ``group``'s meshes (an export is done with them); asked again, they are made again,
        the same."""
        self._levels.pop(group, None)

    def normals(self, code: Any) -> np.ndarray:
        """(N, 3) float32 normals of a node's vertices (CRS frame: x east, y north, z up)."""
        return self._level(code[0]).normals[code]

    def mesh(self, code: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(vertices (N, 3) CRS metres, triangles (K, 3) int64, normals (N, 3) float32) of a node with the
        nodata triangles dropped (no skirts yet)."""
        lv = self._level(code[0])
        pts, used, t = lv.nodes[code]
        v = pts[used]
        return v, self._over_data(v, t), lv.normals[code]

    def _over_data(self, v: np.ndarray, t: np.ndarray) -> np.ndarray:
        """The triangles of ``t`` (rows of vertices ``v``) whose centre lies over a valid source sample."""
        if self._hf is None or not t.size:
            return t
        cen = np.asarray(v, np.float64)[t].mean(axis=1)
        return t[valid_at(self._hf, cen[:, 0], cen[:, 1])]

    def has_content(self, code: Any) -> bool:
        """False for a node whose every triangle is nodata (it gets no content in the tileset); a stored
        tile wholly over nodata has no triangle at all (terralod.pyramid.footprint)."""
        if code not in self._content:
            lv = self._levels.get(code[0])
            if lv is not None and code in lv.nodes:
                self._content[code] = bool(self.mesh(code)[1].size)
            else:  # the node's own mesh, without its level's normals (a tileset asks of every node)
                v, t = self.terrain.lod_mesh(code)
                t = np.asarray(t)
                self._triangles.setdefault(code, len(t))
                self._content[code] = bool(self._over_data(v, t).size)
        return self._content[code]

    def _geodesy(self, code: Any, v: np.ndarray) -> tuple[Any, ...]:
        """(lon, lat, ellipsoidal height, ECEF, east, north, up) of a node's vertices ``v``. For a point
        array shared by several nodes, made once for the whole array: ECEF and the frames are then the
        node's rows of it, lon, lat and height the whole array's, with the rows (else None) last."""
        pts, used, _ = self._level(code[0]).nodes[code]
        from terralod.export.geodesy import enu_frame

        if pts is self._shared:
            if self._shared_frame is None:
                lon, lat = self.geo.lonlat(pts[:, 0], pts[:, 1])
                h = self.geo.ellipsoidal(lon, lat, pts[:, 2])
                self._shared_frame = (lon, lat, h, self.geo.ecef_lonlat(lon, lat, h), *enu_frame(lon, lat))
            lon, lat, h, *rest = self._shared_frame
            return (lon, lat, h, *(a[used] for a in rest), used)
        lon, lat = self.geo.lonlat(v[:, 0], v[:, 1])
        h = self.geo.ellipsoidal(lon, lat, v[:, 2])
        return (lon, lat, h, self.geo.ecef_lonlat(lon, lat, h), *enu_frame(lon, lat), None)

    def glb(self, code: Any) -> bytes:
        """The binary glTF of node ``code`` (on request, as ``terralod serve`` asks: its level built over the
        node's neighbourhood only, :func:`terralod.export.distributed.level_blocks`; the same bytes)."""
        if self.only is not None:
            return self.encode(code)[0]
        from terralod.export.distributed import level_blocks

        block, near = next(level_blocks(self, [code]))
        self.only = near
        self.release(code[0])
        try:
            return self.encode(code)[0]
        finally:
            self.release(code[0])
            self.only = None

    def encode(self, code: Any) -> tuple[bytes, float]:
        """(the binary glTF of node ``code``, the largest distance its encoding moved a vertex, metres)."""
        v, t, nrm = self.mesh(code)
        n = self.nodes[code]
        lon, lat, h, ecef, east, north, up, rows = self._geodesy(code, v)
        nrm_ecef = _enu_combine(nrm, east, north, up)
        be = boundary_edges(t)
        if be.size:
            depth = self.skirt_m(code)
            ends = np.unique(be)
            low = np.full(len(v), -1, np.int64)
            low[ends] = len(v) + np.arange(ends.size)
            at = ends if rows is None else rows[ends]
            ecef = np.concatenate([ecef, self.geo.ecef_lonlat(lon[at], lat[at], h[at] - depth)])
            nrm_ecef = np.concatenate([nrm_ecef, nrm_ecef[ends]])
            a, b = be[:, 0], be[:, 1]
            walls = np.concatenate([np.stack([a, low[b], b], 1), np.stack([a, low[a], low[b]], 1)])
            t = np.concatenate([t, walls])
        rel = ecef - self._centre(n)
        extras = {"error_m": n.error_m, "vertical_error_m": n.vertical_error_m,
                  "encoding_error_m": self.quant_error_m(code), "code": list(code)}  # fmt: skip
        step = None if self.geometry == "float" else self.quant_step_m(code)
        if self.geometry == "meshopt" and self._encoder is None:
            self._encoder = MeshoptEncoder()
        enc = self._encoder if self.geometry == "meshopt" else None
        return _write_glb(rel, nrm_ecef, t, extras, step=step, encoder=enc)

    def close(self) -> None:
        """Stop the meshopt encoder's process, if one was started (a later meshopt glb starts another)."""
        if self._encoder is not None:
            self._encoder.close()
            self._encoder = None


class MeshoptEncoder:
    """meshoptimizer's own encoder (the npm ``meshoptimizer`` package) in one node process.

    ``encode(data, count, size, mode)`` is ``MeshoptEncoder.encodeGltfBuffer`` of the JavaScript module,
    with ``mode`` ATTRIBUTES (vertex codec version 0, what ``EXT_meshopt_compression`` reads) or TRIANGLES.
    The package is found in ``node_modules`` of the current folder or of a folder above it, or of the
    repository this module sits in; ``TERRALOD_NODE_MODULES`` names another. A context manager.
    """

    _SCRIPT = r"""
import { pathToFileURL } from "url";
const { MeshoptEncoder: E } = await import(pathToFileURL(process.env.TERRALOD_MESHOPT).href);
await E.ready;
const modes = ["ATTRIBUTES", "TRIANGLES"];
let chunks = [], have = 0;
process.stdin.on("data", (chunk) => {
  chunks.push(chunk); have += chunk.length;
  for (;;) {
    let buf = chunks.length === 1 ? chunks[0] : Buffer.concat(chunks);
    chunks = [buf];
    if (have < 16) return;
    const n = buf.readUInt32LE(12);
    if (have < 16 + n) return;
    const src = new Uint8Array(buf.subarray(16, 16 + n));
    const out = E.encodeGltfBuffer(src, buf.readUInt32LE(4), buf.readUInt32LE(8), modes[buf.readUInt32LE(0)]);
    const hdr = Buffer.alloc(4);
    hdr.writeUInt32LE(out.length, 0);
    process.stdout.write(Buffer.concat([hdr, Buffer.from(out.buffer, out.byteOffset, out.length)]));
    chunks = [buf.subarray(16 + n)]; have -= 16 + n;
  }
});
"""

    def __init__(self, node_modules: str | Path | None = None) -> None:
        import os
        import shutil
        import subprocess

        from terralod.errors import InputError

        node = shutil.which("node")
        where = _find_node_modules(node_modules)
        if node is None or where is None:
            raise InputError("needs node and the npm package meshoptimizer (`npm ci` in the repository, or "
                             "TERRALOD_NODE_MODULES naming a node_modules that holds it)",
                             "--glb-geometry meshopt")  # fmt: skip
        env = dict(os.environ, TERRALOD_MESHOPT=str(where / "meshoptimizer" / "meshopt_encoder.js"))
        self._proc = subprocess.Popen([node, "--input-type=module", "-e", self._SCRIPT], stdin=subprocess.PIPE,
                                      stdout=subprocess.PIPE, env=env)  # fmt: skip

    def encode(self, data: bytes, count: int, size: int, mode: str) -> bytes:
        """``data`` (``count`` elements of ``size`` bytes) compressed as ``EXT_meshopt_compression`` stores it."""
        import struct

        p = self._proc
        assert p.stdin is not None and p.stdout is not None
        p.stdin.write(
            struct.pack("<4I", ("ATTRIBUTES", "TRIANGLES").index(mode), count, size, len(data)) + data
        )
        p.stdin.flush()
        head = p.stdout.read(4)
        if len(head) < 4:
            raise RuntimeError(f"the meshoptimizer encoder (node) stopped with code {p.wait()}")
        return p.stdout.read(struct.unpack("<I", head)[0])

    def close(self) -> None:
        p = self._proc
        if p.poll() is None:
            assert p.stdin is not None
            p.stdin.close()
            p.wait(timeout=30)

    def __enter__(self) -> MeshoptEncoder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _find_node_modules(given: str | Path | None) -> Path | None:
    """The node_modules folder holding meshoptimizer: ``given``, TERRALOD_NODE_MODULES, or the first found
    from the current folder up, then from this module's folder up (an editable install's repository)."""
    import os

    if given is not None or os.environ.get("TERRALOD_NODE_MODULES"):
        p = Path(given if given is not None else os.environ["TERRALOD_NODE_MODULES"])
        return p if (p / "meshoptimizer" / "meshopt_encoder.js").is_file() else None
    for start in (Path.cwd(), Path(__file__).resolve().parent):
        for d in (start, *start.parents):
            if (d / "node_modules" / "meshoptimizer" / "meshopt_encoder.js").is_file():
                return d / "node_modules"
    return None


def _enu_to_ecef(n: np.ndarray, lon: np.ndarray, lat: np.ndarray) -> np.ndarray:
    """Normals in the local (east, north, up) frame → ECEF (the projected frame's grid convergence, a
    fraction of a degree, is ignored)."""
    from terralod.export.geodesy import enu_frame

    return _enu_combine(n, *enu_frame(lon, lat))


def _enu_combine(n: np.ndarray, e: np.ndarray, nn: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Normals ``n`` (east, north, up components) in the frames (e, nn, u) → unit ECEF vectors."""
    n = np.asarray(n, np.float64)
    out = e * n[:, :1] + nn * n[:, 1:2] + u * n[:, 2:3]
    return out / np.maximum(np.linalg.norm(out, axis=1, keepdims=True), 1e-30)


def _yup(a: np.ndarray) -> np.ndarray:
    """ECEF (x, y, z) → glTF y-up (x, z, -y)."""
    return np.stack([a[:, 0], a[:, 2], -a[:, 1]], axis=1)


def _first_use(tris: np.ndarray, nv: int) -> tuple[np.ndarray, np.ndarray]:
    """(order, triangles renumbered): the vertices the triangles use, in the order they first use them (a
    vertex no triangle uses, under a dropped nodata triangle, is left out), and the triangles in the new
    numbers."""
    from terralod.kernels.meshtopo import first_use

    order, local = first_use(np.ascontiguousarray(tris, np.int64).ravel(), int(nv))
    return order, local.reshape(-1, 3)


def _write_glb(
    pos: np.ndarray, nrm: np.ndarray, tris: np.ndarray, extras: dict[str, Any], *, step: float | None = None,
    encoder: MeshoptEncoder | None = None,
) -> tuple[bytes, float]:  # fmt: skip
    """(glb bytes, the largest distance a vertex moved in the encoding, metres) of one triangle mesh:
    positions ``pos`` (N, 3) ECEF metres relative to the tile centre, unit normals ``nrm`` (N, 3) ECEF.
    ``step`` None: float32; else the KHR_mesh_quantization grid step (metres); ``encoder`` also compresses
    every buffer view with EXT_meshopt_compression."""
    import pygltflib as g

    order, tris = _first_use(tris, len(pos))
    p64, nm = _yup(pos)[order], _yup(nrm)[order]
    nv = len(p64)
    node = g.Node(mesh=0)
    used: list[str] = []
    if step is None:
        p = np.ascontiguousarray(p64, np.float32)
        moved = p.astype(np.float64) - p64
        pa = g.Accessor(componentType=g.FLOAT, count=nv, type=g.VEC3,
                        min=[float(a) for a in p.min(axis=0)], max=[float(a) for a in p.max(axis=0)])  # fmt: skip
        na = g.Accessor(componentType=g.FLOAT, count=nv, type=g.VEC3)
        pb, nb, ps, ns = p.tobytes(), np.ascontiguousarray(nm, np.float32).tobytes(), None, None
    else:
        k = np.round(p64 / step)
        off = k.min(axis=0)
        u = k - off
        if u.max() > 65535:
            raise RuntimeError(
                f"Expected positions within {QUANT_STEPS} steps of {step} m, got {u.max():.0f}"
            )
        moved = k * step - p64
        q4 = np.zeros((nv, 4), np.uint16)
        q4[:, :3] = u
        n4 = np.zeros((nv, 4), np.int8)
        n4[:, :3] = np.clip(np.round(nm * 127.0), -127, 127)
        node.scale = [float(step)] * 3
        node.translation = [float(o * step) for o in off]
        pa = g.Accessor(componentType=g.UNSIGNED_SHORT, count=nv, type=g.VEC3,
                        min=[int(a) for a in u.min(axis=0)], max=[int(a) for a in u.max(axis=0)])  # fmt: skip
        na = g.Accessor(componentType=g.BYTE, normalized=True, count=nv, type=g.VEC3)
        pb, nb, ps, ns = q4.tobytes(), n4.tobytes(), 8, 4
        used.append("KHR_mesh_quantization")
    if nv <= 255 and encoder is None:  # the largest value of each type is primitive restart (glTF §3.7.2.1)
        idx, ctype = tris.astype(np.uint8), g.UNSIGNED_BYTE
    elif nv <= 65535:
        idx, ctype = tris.astype(np.uint16), g.UNSIGNED_SHORT
    else:
        idx, ctype = tris.astype(np.uint32), g.UNSIGNED_INT
    ia = g.Accessor(componentType=ctype, count=int(idx.size), type=g.SCALAR,
                    min=[int(idx.min())] if idx.size else [0], max=[int(idx.max())] if idx.size else [0])  # fmt: skip
    views = [(idx.ravel().tobytes(), None, g.ELEMENT_ARRAY_BUFFER, "TRIANGLES", idx.itemsize),
             (pb, ps, g.ARRAY_BUFFER, "ATTRIBUTES", ps or 12), (nb, ns, g.ARRAY_BUFFER, "ATTRIBUTES", ns or 12)]  # fmt: skip
    blob = b""
    buffer_views: list[Any] = []
    buffers = []
    if encoder is None:
        for data, stride, target, _, _ in views:
            blob += b"\x00" * (-len(blob) % 4)
            buffer_views.append(g.BufferView(buffer=0, byteOffset=len(blob), byteLength=len(data),
                                             byteStride=stride, target=target))  # fmt: skip
            blob += data
        buffers.append(g.Buffer(byteLength=len(blob)))
    else:
        used.append("EXT_meshopt_compression")
        fallback = 0
        for data, stride, target, mode, size in views:
            blob += b"\x00" * (-len(blob) % 4)
            fallback += -fallback % 4
            count = len(data) // size
            packed = encoder.encode(data, count, size, mode)
            ext = {"buffer": 0, "byteOffset": len(blob), "byteLength": len(packed), "byteStride": size,
                   "count": count, "mode": mode}  # fmt: skip
            buffer_views.append(g.BufferView(buffer=1, byteOffset=fallback, byteLength=len(data), byteStride=stride,
                                             target=target, extensions={"EXT_meshopt_compression": ext}))  # fmt: skip
            blob += packed
            fallback += len(data)
        blob += b"\x00" * (-len(blob) % 4)
        buffers += [g.Buffer(byteLength=len(blob)),
                    g.Buffer(byteLength=fallback, extensions={"EXT_meshopt_compression": {"fallback": True}})]  # fmt: skip
    for i, a in enumerate((ia, pa, na)):
        a.bufferView = i
    gl = g.GLTF2(
        asset=g.Asset(version="2.0", generator="terralod"),
        scene=0,
        scenes=[g.Scene(nodes=[0])],
        nodes=[node],
        meshes=[g.Mesh(primitives=[g.Primitive(attributes=g.Attributes(POSITION=1, NORMAL=2), indices=0,
                                               material=0, mode=g.TRIANGLES)])],
        materials=[g.Material(pbrMetallicRoughness=g.PbrMetallicRoughness(
            baseColorFactor=[0.75, 0.72, 0.62, 1.0], metallicFactor=0.0, roughnessFactor=1.0), doubleSided=False)],
        accessors=[ia, pa, na],
        bufferViews=buffer_views,
        buffers=buffers,
        extensionsUsed=used,
        extensionsRequired=list(used),
        extras=extras,
    )  # fmt: skip
    worst = float(np.sqrt((moved**2).sum(axis=1)).max()) if nv else 0.0
    return _glb_container(gl.gltf_to_json(separators=(",", ":"), indent=None).encode(), blob), worst


def _glb_container(js: bytes, blob: bytes) -> bytes:
    """A GLB (glTF 2.0 §4.4): the 12-byte header, the JSON chunk padded with spaces and the BIN chunk padded
    with zeros to 4 bytes. Written here, not by pygltflib, which merges every buffer into one (the meshopt
    fallback buffer, which has no bytes, must stay a buffer of its own)."""
    import struct

    js += b" " * (-len(js) % 4)
    blob += b"\x00" * (-len(blob) % 4)
    total = 12 + 8 + len(js) + 8 + len(blob)
    return b"".join([b"glTF", struct.pack("<II", 2, total), struct.pack("<I", len(js)), b"JSON", js,
                     struct.pack("<I", len(blob)), b"BIN\x00", blob])  # fmt: skip


class _Deps:
    """Each glb's dependency digest (:mod:`terralod.export.incremental`), recorded with it."""

    def __init__(self, view: Tiles3D, **options: Any) -> None:
        from terralod.export.incremental import tiles3d_global

        self.view = view
        self.glob = tiles3d_global(view, options)
        self.memo: dict[Any, str] = {}

    def of(self, code: Any) -> str | None:
        from terralod.export.incremental import tiles3d_digest

        return tiles3d_digest(self.view, code, self.glob, self.memo)


def export_3dtiles(
    terrain: Any,
    out: str | Path,
    *,
    metric: str = "hausdorff",
    epoch: str | None = None,
    overwrite: bool = False,
    resume: bool = False,
    update: bool = False,
    progress: Callable[[int, int], None] | None = None,
    vertical_datum: str | None = None,
    geometry: str = "quantized",
    max_error_m: float | None = None,
    client: Any = None,
    part: Any = None,
    split_levels: int | None = SPLIT_LEVELS,
) -> ExportReport:
    """Write ``out/tileset.json`` and ``out/tiles/L/X_Y.glb`` for every node of ``terrain``'s LOD tree.

    ``part`` (:class:`terralod.export.quantized_mesh.Part`: a box in degrees, levels of the tree as zooms)
    writes only the nodes that meet the box up to ``max_zoom``, with content from ``min_zoom``, each glb
    byte for byte the whole export's. ``split_levels``: the tileset in files of that many levels
    (:func:`split_tileset`); None writes one tileset.json (the site splits its own after pruning).

    ``geometry``: ``"quantized"`` (KHR_mesh_quantization), ``"meshopt"`` (also EXT_meshopt_compression,
    needs node and the npm meshoptimizer package) or ``"float"``; ``max_error_m``: leave out the nodes whose
    parent already declares at most this (see :class:`Tiles3D`). ``extra["encoding_error_m"]`` is the
    largest distance the encoding moved any vertex (each tile declares its bound, at least that).

    ``vertical_datum``: what the stored heights are above, when the store's CRS does not say (see
    :mod:`terralod.export.vertical`); heights are then written above the WGS 84 ellipsoid.

    ``resume``: the glbs an interrupted export of the same terrain and options finished are not encoded
    again; ``update``: only the files whose bytes change are rewritten (``extra["rewritten"]``). The output
    is written through :class:`terralod.output.Output`. ``client`` (a ``dask.distributed`` Client): the
    glbs are encoded on its workers (:mod:`terralod.export.distributed`), the same bytes.
    """
    from terralod.export.distributed import encode_3dtiles, recipe_of
    from terralod.output import Output

    t0 = time.perf_counter()
    check_exportable(terrain, epoch)
    if epoch is not None and epoch != getattr(terrain, "epoch", None):
        terrain = terrain.with_epoch(epoch)
    output = Output(out, inputs=export_inputs(terrain), overwrite=overwrite, resume=resume, update=update,
                    key=export_key(terrain, "3dtiles", metric=metric, vertical_datum=vertical_datum,
                                   geometry=geometry, max_error_m=max_error_m,
                                   **({} if part is None or part.whole else {"part": part.key()})),
                    keep_records=True)  # fmt: skip
    output.check()  # refusals first, before the view's set-up
    view = Tiles3D(terrain, metric=metric, vertical_datum=vertical_datum, geometry=geometry,
                   max_error_m=max_error_m)  # fmt: skip
    wanted = None if part is None or part.whole else view.part_nodes(part)
    if wanted is not None and not wanted:
        from terralod.errors import InputError

        raise InputError(f"has no tile that meets the box {list(part.bbox)}", str(terrain.path))
    recipe = None
    if client is not None:
        recipe = recipe_of(terrain, Tiles3D, epoch, metric=metric, vertical_datum=vertical_datum,
                           geometry=geometry, max_error_m=max_error_m)  # fmt: skip
    rep = ExportReport(Path(out))
    moved = 0.0
    with output as o:
        # level by level, block by block (terralod.export.distributed.level_blocks): a block's meshes are
        # made with its neighbours' and dropped when its tiles are written, so memory holds one block
        codes = sorted((n.code for n in view.tree), key=lambda c: c[0])
        if wanted is not None:  # a part: its nodes from its first level with content
            codes = [c for c in codes if c in wanted and c[0] >= part.min_zoom]
        deps = _Deps(view, metric=metric, vertical_datum=vertical_datum, geometry=geometry,
                     max_error_m=max_error_m)  # fmt: skip
        if update:  # a glb made from what it was made of last time is kept as it is, not encoded
            for c in codes:
                prev = o.previous(node_uri(c)) if o.record(node_uri(c)) is None else None
                if prev is not None and prev.get("deps") is not None and prev["deps"] == deps.of(c):
                    o.keep(node_uri(c), prev)
        todo = [c for c in codes if o.record(node_uri(c)) is None]  # the others: finished by the run resumed
        done = 0
        for code in codes:
            r = o.record(node_uri(code))
            if r is not None:
                view._content[code] = True
                view._triangles.setdefault(code, int(r.get("triangles", 0)))
                rep.tiles += 1
                rep.bytes += r["bytes"]
                moved = max(moved, float(r.get("moved_m", 0.0)))
                done += 1
        # here or on the Dask workers, level by level and block by block (encode_3dtiles' order)
        for code, data, r in encode_3dtiles(view, todo, client=client, recipe=recipe):
            done += 1
            if progress is not None:
                progress(done, len(codes))
            if data is None:  # every triangle over nodata: no content
                continue
            o.write(node_uri(code), data, {**r, "deps": deps.of(code)})
            rep.tiles += 1
            rep.bytes += r["bytes"]
            moved = max(moved, float(r.get("moved_m", 0.0)))
        view.close()
        files = (
            [("tileset.json", view.tileset(part))]
            if split_levels is None
            else view.tileset_files(part, split_levels)
        )
        for name, js in files:  # (split: each file as its subtree is made, never the whole tileset)
            data = json.dumps(js, separators=(",", ":"))
            o.write(name, data.encode())
            rep.bytes += len(data)

        o.seal()
        changes = {"rewritten": list(o.rewritten), "removed": o.prune()} if update else {}
    rep.triangles = int(sum(view._triangles.values()))
    rep.seconds = time.perf_counter() - t0
    rep.extra = {"format": "3dtiles", "metric": metric, "max_error_m": max(view.error_m(c) for c in view.nodes),
                 "levels": len({c[0] for c in view.nodes}), "geometric_error_root": math.nan,
                 "heights": view.geo.vertical_record(), "geometry": geometry, "max_error_m_option": max_error_m,
                 "encoding_error_m": moved}  # fmt: skip
    rep.extra["geometric_error_root"] = view.nothing_error_m()
    rep.extra.update(resumed=o.adopted is not None, encoded=len(todo), **changes)
    return rep
