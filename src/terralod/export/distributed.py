"""The exports' tile encoding on a Dask cluster: the one place where "encode these codes" is done.

:func:`encode_quantized_mesh` and :func:`encode_3dtiles` take the codes an export needs encoded (after
``--resume`` and whatever filter an export applies) and yield ``(code, bytes, record)`` for each, in the
order given (3D Tiles: in :func:`level_blocks`' order). Without a client they encode in this process.
With a ``dask.distributed`` client the quantized-mesh codes go out in batches of :data:`BATCH_TILES`
consecutive codes of one level (level by level, rows then columns: neighbouring tiles, so a worker's block
cache is reused), the 3D Tiles nodes a block at a time, at most :data:`BATCHES_PER_WORKER` per worker thread
in flight, submitted in order and yielded in order as they finish; the driver keeps writing through
:class:`terralod.output.Output`.

What travels: a :class:`Recipe` (a store's path and epoch, a region's file list and scan, a DEM's path, and
the export's options: bytes, never samples) to the workers, and each tile's bytes and record back. A worker
opens the source once (:func:`_opened`: the QuantizedMesh or Tiles3D kept per worker process, keyed by the
recipe) and reads its own windows of the inputs. A tile is a pure function of (source, options, code), so
the bytes are the local run's: the one statistic a quantized-mesh tile takes from elsewhere, its parent's
RMS ratio (:meth:`~terralod.export.quantized_mesh.QuantizedMesh.rms_ratio`), is sent back with the parents
and handed to the children's batches (a worker that lacks it meshes the parent again, the same).

3D Tiles: a glb's normals are those of its whole level merged (:meth:`~terralod.export.tiles3d.Tiles3D._level`),
but a node's normals only take sums from the nodes that share a vertex position with it, added in the
level's node order. So a level is encoded in blocks (:func:`level_blocks`: square cells of about
:data:`BLOCK_NODES` nodes), here or on a worker, each built with only the block's nodes and the level's nodes
whose boxes meet theirs (padded), in the level's order (``Tiles3D.only``): the same sums in the same order,
so the same bytes, without building a whole level anywhere. On a cluster a block is one task.

This module imports neither tiler (they import it): a recipe carries its view's class, pickled by name.
"""

from __future__ import annotations

import hashlib
import pickle
from collections import OrderedDict, deque
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = [
    "BATCH_TILES",
    "BATCHES_PER_WORKER",
    "Recipe",
    "encode_3dtiles",
    "encode_quantized_mesh",
    "level_blocks",
    "quantized_mesh_record",
    "recipe_of",
    "tiles3d_result",
]

#: Tiles of one batch: a few dozen neighbours, so a worker reuses its cached blocks and the scheduler's
#: per-task overhead (a few ms) stays small against the tiles' encoding (tens of ms each).
BATCH_TILES = 32
#: Batches in flight per worker thread: one running and one queued, so no worker waits on the driver.
BATCHES_PER_WORKER = 2
#: Opened sources a worker process keeps (the last ones used).
KEEP_OPENED = 2
#: A node's box is padded by this fraction of its size, and PAD_M metres, when looking for the nodes that
#: share a vertex position with it (positions are merged at 0.1 mm; extra neighbours cost time, not bytes).
NEIGHBOUR_PAD = 0.01
NEIGHBOUR_PAD_M = 1.0
#: 3D Tiles nodes of one block (about 16 x 16 of a level): a level is encoded block by block, each block's
#: normals summed over it and its neighbours only, so memory holds one block's meshes whatever the level's
#: size (the whole finest level of 16 SRTM3 tiles took 5.4 GiB), at (18 / 16)² of the meshes' reading.
BLOCK_NODES = 256
#: ... and of about this many mesh vertices, where the terrain counts them (a grid store): the coarse levels'
#: nodes hold 20-40 k vertices each on a 64-tile SRTM3 store, so 256 of them and their ring (some 6 M
#: vertices, about 200 bytes each in flight with their triangles, normals and glb) took the export to 1.07
#: GiB at level 4 against 0.43 between levels; the finest level's nodes (about 1 k vertices) keep 256.
BLOCK_VERTICES = 400_000

Code = tuple[int, ...]
Result = tuple[Any, bytes | None, dict[str, Any] | None]


@dataclass(frozen=True)
class Recipe:
    """How a worker opens an export's source: ``kind`` ("store", "region-grid", "region" or "dem"),
    ``source`` (what it needs: a path and epoch, a Region and its scan, a path), the view's class
    (``view``: QuantizedMesh or Tiles3D, pickled by name) and its options. Small and picklable."""

    view: Any
    kind: str
    source: tuple[Any, ...]
    options: tuple[tuple[str, Any], ...]

    def key(self) -> str:
        """The recipe's identity on a worker (its pickled bytes' digest)."""
        return hashlib.sha256(pickle.dumps(self, protocol=5)).hexdigest()

    def open(self) -> Any:
        """The view this recipe describes (a QuantizedMesh or Tiles3D of the source)."""
        from terralod.export.source import RegionGrid, source_from_dem, source_from_region
        from terralod.terrain import open_terrain

        terrain: Any
        if self.kind == "store":
            path, epoch = self.source
            terrain = open_terrain(path)
            if epoch is not None and epoch != getattr(terrain, "epoch", None):
                terrain = terrain.with_epoch(epoch)
        elif self.kind == "region-grid":
            terrain = RegionGrid(self.source[0], scan=self.source[1])
        elif self.kind == "region":
            terrain = source_from_region(self.source[0])
        else:
            terrain = source_from_dem(self.source[0])
        return self.view(terrain, **dict(self.options))


def recipe_of(terrain: Any, view: Any, epoch: str | None = None, **options: Any) -> Recipe:
    """The :class:`Recipe` of an export's ``terrain`` (a store opened from a file, or a DEM's or region's
    samples from :mod:`terralod.export.source`) for the class ``view`` with ``options``. Raises ValueError for a
    terrain a worker cannot open again (one built in memory)."""
    from terralod.export.source import RegionGrid, SampleSource

    opts = tuple(sorted(options.items()))
    if isinstance(terrain, RegionGrid):
        return Recipe(view, "region-grid", (terrain.region, terrain.scan), opts)
    if isinstance(terrain, SampleSource):
        origin = getattr(terrain, "origin", None)
        if origin is None:
            raise ValueError(
                f"Expected a DEM or region read from files, got samples in memory ({terrain.name})"
            )
        return Recipe(view, origin[0], tuple(origin[1:]), opts)
    path = getattr(terrain, "path", None)
    if path is None:
        raise ValueError("Expected a store opened from a file, got a terrain in memory")
    return Recipe(view, "store", (str(path), epoch), opts)


# -- on a worker ---------------------------------------------------------------------------------------
_OPENED: OrderedDict[str, Any] = OrderedDict()


def _opened(recipe: Recipe) -> Any:
    """The view of ``recipe``, opened once per worker process (the last KEEP_OPENED kept). The worker's
    allocator is given back its adaptive thresholds first (:func:`terralod.pyramid.distributed.
    tune_worker_malloc`: Dask's nanny starts workers with a fixed trim threshold, which made every tile's
    arrays fresh mmaps: a 4-tile region's export cost 2.5x the local CPU on one worker, a third of it in the
    kernel)."""
    from terralod.pyramid.distributed import tune_worker_malloc

    tune_worker_malloc()
    key = recipe.key()
    view = _OPENED.get(key)
    if view is None:
        view = recipe.open()
        _OPENED[key] = view
        while len(_OPENED) > KEEP_OPENED:
            _, old = _OPENED.popitem(last=False)
            if callable(getattr(old, "close", None)):
                old.close()
    _OPENED.move_to_end(key)
    return view


def quantized_mesh_record(qm: Any, code: Code, gzip_tiles: bool) -> Result:
    """(code, the file's bytes, its journal record) of quantized-mesh tile ``code``: the one encoding."""
    z, x, y = code
    t = qm.tile(z, x, y)
    data = t.data if gzip_tiles else t.raw
    r = {"bytes": len(data), "raw": len(t.raw), "gz": len(t.data) if gzip_tiles else 0,
         "triangles": int(t.triangles), "sumsq_m2": float(t.sumsq_m2), "samples": int(t.samples),
         "water": t.water, "error_m": float(t.error_m)}  # fmt: skip
    return code, data, r


def _qm_batch(recipe: Recipe, codes: list[Code], gzip_tiles: bool,
              ratios: dict[Code, float | None]) -> tuple[list[Result], dict[Code, float | None]]:  # fmt: skip
    """A batch of quantized-mesh tiles on a worker, and the RMS ratios it made (a child batch's input)."""
    qm = _opened(recipe)
    for k, v in ratios.items():
        qm._rms_ratio.setdefault(k, v)
    from terralod.pyramid.distributed import release_free_heap

    out = [quantized_mesh_record(qm, c, gzip_tiles) for c in codes]
    made = {c: qm._rms_ratio[c] for c in codes if c in qm._rms_ratio}
    release_free_heap(force=False)
    return out, made


def level_blocks(
    view: Any, codes: Sequence[Any], block_nodes: int | None = None
) -> Iterator[tuple[list[Any], set[Any]]]:
    """``codes`` (3D Tiles nodes of ``view``) as (block, neighbourhood) pairs: level by level (ascending),
    each level's codes grouped by square cells of about ``block_nodes`` (default :data:`BLOCK_NODES`) of its
    nodes, fewer where the terrain counts its nodes' vertices and that many would hold more than
    :data:`BLOCK_VERTICES` (cells in raster order, nodes in the tree's order within a cell); a block's
    neighbourhood is the block and every node of its level (in ``codes`` or not) whose padded box meets the
    box of the block's padded boxes: a superset of the nodes that may share a vertex position with one of
    the block's, which is all a node's normals need (extra neighbours cost time, not bytes).

    Found through the cells: a node whose padded box is at most a cell wide meets only nodes whose centres
    lie in its own cell or the eight around it; the wider ones are checked against every block."""
    block_nodes = BLOCK_NODES if block_nodes is None else block_nodes
    by_level: dict[int, list[Any]] = {}
    for c in codes:
        by_level.setdefault(c[0], []).append(c)
    for lv in sorted(by_level):
        level, box = view.level_nodes(lv), view.level_boxes(lv)
        size = np.maximum(box[:, 2] - box[:, 0], box[:, 3] - box[:, 1])
        pad = NEIGHBOUR_PAD * size + NEIGHBOUR_PAD_M
        pbox = box + np.stack([-pad, -pad, pad, pad], axis=1)
        per_block = block_nodes
        weight = view.level_vertices(lv)
        if weight is not None and weight.size and weight.mean() > 0:
            per_block = max(1, min(block_nodes, int(BLOCK_VERTICES / float(weight.mean()))))
        side = max(float(np.median(size + 2 * pad)), 1e-9) * max(1.0, float(np.sqrt(per_block)))
        cx = 0.5 * (box[:, 0] + box[:, 2]) - pbox[:, 0].min()
        cy = pbox[:, 3].max() - 0.5 * (box[:, 1] + box[:, 3])  # rows from the north
        bx, by = (cx // side).astype(np.int64), (cy // side).astype(np.int64)
        nbx = int(bx.max()) + 1
        key = by * nbx + bx
        wide = np.flatnonzero(np.maximum(pbox[:, 2] - pbox[:, 0], pbox[:, 3] - pbox[:, 1]) > side)
        pos = {n.code: i for i, n in enumerate(level)}
        want = np.zeros(len(level), bool)
        want[[pos[c] for c in by_level[lv]]] = True
        order = np.argsort(key, kind="stable")  # the tree's order within a cell
        keys, starts = np.unique(key[order], return_index=True)
        ends = np.append(starts[1:], len(order))
        cell = {
            int(k): order[a:b] for k, a, b in zip(keys.tolist(), starts.tolist(), ends.tolist(), strict=True)
        }
        for k, members in cell.items():
            mine = members[want[members]]
            if not mine.size:
                continue
            ky, kx = divmod(k, nbx)
            near = [cell[(ky + dy) * nbx + kx + dx] for dy in (-1, 0, 1) for dx in (-1, 0, 1)
                    if 0 <= kx + dx < nbx and (ky + dy) * nbx + kx + dx in cell]  # fmt: skip
            cand = np.unique(np.concatenate([*near, wide]))
            w, s, e, n = pbox[mine, 0].min(), pbox[mine, 1].min(), pbox[mine, 2].max(), pbox[mine, 3].max()
            pc = pbox[cand]
            hit = cand[(pc[:, 0] <= e) & (w <= pc[:, 2]) & (pc[:, 1] <= n) & (s <= pc[:, 3])]
            block = [level[i].code for i in mine.tolist()]
            yield block, {level[i].code for i in hit.tolist()} | set(block)


def tiles3d_result(view: Any, code: Any) -> Result:
    """(code, glb bytes or None for a node without content, its journal record) of one 3D Tiles node; the
    record holds the node's triangles (before the nodata drop) for the report."""
    if not view.has_content(code):
        return code, None, {"triangles": int(view._triangles.get(code, 0))}
    data, shift = view.encode(code)
    return code, data, {"bytes": len(data), "moved_m": shift, "triangles": int(view._triangles.get(code, 0))}


def _block_results(view: Any, codes: list[Any], near: set[Any]) -> list[Result]:
    """:func:`tiles3d_result` of a block of one level's nodes, that level built over ``near`` (the block's
    neighbourhood, :func:`level_blocks`) only and released after, the heap glibc keeps free handed back
    (:func:`terralod.pyramid.distributed.release_free_heap`, at most every few seconds): without it the
    16-tile store's export sat at 490-520 MiB through its finest level against 240-275 MiB trimmed, the
    pages of a coarse block's meshes kept for reuse."""
    from terralod.pyramid.distributed import release_free_heap

    view.only = near
    view.release(codes[0][0])
    try:
        return [tiles3d_result(view, c) for c in codes]
    finally:
        view.release(codes[0][0])
        view.only = None
        release_free_heap(force=False)


def _3dtiles_batch(recipe: Recipe, codes: list[Any], near: set[Any]) -> tuple[list[Result], None]:
    """A block of one level's 3D Tiles nodes on a worker (:func:`_block_results`)."""
    view = _opened(recipe)
    try:
        return _block_results(view, codes, near), None
    finally:
        for c in codes:
            view._content.pop(c, None)


# -- on the driver -------------------------------------------------------------------------------------
def _batches(codes: Sequence[Any], size: int) -> Iterator[list[Any]]:
    """Runs of at most ``size`` consecutive codes of one level."""
    run: list[Any] = []
    for c in codes:
        if run and (len(run) == size or run[-1][0] != c[0]):
            yield run
            run = []
        run.append(c)
    if run:
        yield run


def _threads(client: Any) -> int:
    try:
        return max(1, int(sum(client.nthreads().values())))
    except Exception:  # noqa: BLE001 - a scheduler that does not say: assume two
        return 2


def _stream(client: Any, batches: Iterable[list[Any]], submit: Callable[[Any, list[Any]], Any],
            after: Callable[[Any], None] | None = None) -> Iterator[Result]:  # fmt: skip
    """The results of ``submit(client, batch)`` futures, in order: at most BATCHES_PER_WORKER per worker
    thread in flight (memory bounded by the work in flight), the next submitted before a result is yielded."""
    ahead = BATCHES_PER_WORKER * _threads(client)
    it = iter(batches)
    pending: deque[Any] = deque()
    try:
        for b in it:
            pending.append(submit(client, b))
            if len(pending) >= ahead:
                break
        while pending:
            results, extra = pending.popleft().result()
            if after is not None:
                after(extra)
            nxt = next(it, None)
            if nxt is not None:
                pending.append(submit(client, nxt))
            yield from results
    finally:
        for f in pending:
            f.cancel()


def encode_quantized_mesh(qm: Any, codes: Sequence[Code], *, gzip_tiles: bool = False,
                          client: Any = None, recipe: Recipe | None = None) -> Iterator[Result]:  # fmt: skip
    """``(code, bytes, record)`` of every quantized-mesh tile of ``codes``, in that order: here, or on
    ``client``'s workers (each opening ``recipe``) in batches of :data:`BATCH_TILES`."""
    if client is None:
        from terralod.pyramid.distributed import release_free_heap

        for c in codes:
            yield quantized_mesh_record(qm, c, gzip_tiles)
            release_free_heap(force=False)  # the heap glibc keeps free, back at most every few seconds
        return
    if recipe is None:
        raise ValueError("Expected the source's recipe with a client")
    goal = qm.max_zoom - 1  # the level whose tiles take their parent's RMS ratio
    known: dict[Code, float | None] = {}

    def submit(cl: Any, b: list[Code]) -> Any:
        parents = {(z - 1, x // 2, y // 2) for z, x, y in b if z == goal and z > 0}
        ratios = {p: known[p] for p in parents if p in known}
        return cl.submit(_qm_batch, recipe, b, gzip_tiles, ratios, pure=False)

    yield from _stream(client, _batches(codes, BATCH_TILES), submit, lambda made: known.update(made))


def encode_3dtiles(view: Any, codes: Sequence[Any], *, client: Any = None,
                   recipe: Recipe | None = None) -> Iterator[Result]:  # fmt: skip
    """``(code, glb bytes or None without content, record)`` of every 3D Tiles node of ``codes``, in the
    order of :func:`level_blocks` (level by level, block by block): here, or on ``client``'s workers, a block
    at a time; either way a block's level is built over the block's neighbourhood only, so memory holds a
    block's meshes, not a level's. The driver's view learns each node's content and triangles from the
    records (its tileset needs no mesh)."""
    blocks = level_blocks(view, codes)
    if client is None:
        for block, near in blocks:
            yield from _block_results(view, block, near)
        return
    if recipe is None:
        raise ValueError("Expected the store's recipe with a client")

    def submit(cl: Any, b: tuple[list[Any], set[Any]]) -> Any:
        return cl.submit(_3dtiles_batch, recipe, b[0], b[1], pure=False)

    for code, data, r in _stream(client, blocks, submit):
        view._content[code] = data is not None
        view._triangles[code] = int((r or {}).get("triangles", 0))
        yield code, data, r
