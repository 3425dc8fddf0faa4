"""Add an epoch to a store: rebuild only the tiles whose source windows changed.

A tile's *source window* is every sample its mesher reads: the tile's own samples ``[r0, r0 + span]`` x
``[c0, c0 + span]`` (clipped to the data, whose last row and column stand in for the padding), widened by
the mesher's margin — 0 for Chunked LOD and for the vertex cohesion map (Sung, Lee & Shin, 2021) with its default
error-driven attraction, ``2 * stride`` for the cohesion map with LoG attraction (the paper as written),
whose roughness of sigma = stride / 2 is taken over 4 sigma around the window
(``cohesion._window_roughness``); other meshers get ``4 * stride`` unless they declare
``window_margin(stride)`` (the adaptive TIN: 0). One sample more is added for safety. A tile is *dirty* when
any sample of its window differs (bit for bit, elevation or validity) between the base epoch and the new
one. A parent's window holds its children's, so every ancestor of a dirty tile is dirty too and is
re-meshed and re-measured, and a clean tile's children are clean: its bytes, including its monotone error,
are those of the base epoch, so it is shared (the new epoch's map points at the base's row).

The quantisation is the store's, fixed at its first build (with headroom, ``plan_quantisation``); an
epoch whose relief leaves it is refused before anything is written. With the same quantisation every tile
of the new epoch is byte-identical to a fresh ``build_store(new, quantisation=store.quantisation)``:
``build_tile`` is deterministic and gets the same heightfield, lattice and children's errors.

Transactions: rebuilt tiles are committed in batches under the new epoch's rev (invisible to readers);
the epoch's map and ``complete`` state in one last transaction (:mod:`terralod.store_epochs`). A killed
update leaves the earlier epochs untouched; ``resume=True`` skips the tiles already written.

Window by window (:func:`update_store_windowed`): a survey never held whole (a region, a raster too large)
is compared with the base epoch's kept samples in strips of rows, the dirty tiles found strip by strip
(:class:`DirtyTiles`, the same rule) and rebuilt by the out-of-core builder's work units
(:mod:`terralod.pyramid.distributed`), so each rebuilt tile is the one an out-of-core build of the survey
with the store's lattice makes.
"""

from __future__ import annotations

import itertools
import logging
import os
import re
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from affine import Affine

from terralod.errors import InputError, StoreError
from terralod.heightfield import Heightfield
from terralod.pyramid.builder import METHODS, _level_max_range, build_tile, commit_streamed
from terralod.pyramid.cohesion import CohesionOptions
from terralod.store import EncodedTile, TileStore
from terralod.store_epochs import DEFAULT_EPOCH, epoch_record
from terralod.tiles import TileCode, TilePyramid

log = logging.getLogger(__name__)

_BATCH_TILES = 16


def window_margin(method: str, stride: int) -> int:
    """Samples beyond a tile's own window that mesher ``method`` reads at ``stride`` (see the module doc)."""
    fn = METHODS.get(method)
    own = getattr(fn, "window_margin", None)
    if callable(own):
        return int(own(stride))
    if method == "chunked":
        return 0
    opt = getattr(fn, "options", None)
    if method == "cohesion" or isinstance(opt, CohesionOptions):
        # the default (error-driven attraction) reads only the tile's own samples; LoG attraction (the paper
        # as written) reads 4 sigma = 2 strides of roughness around them
        return 2 * stride if getattr(opt, "attraction", "error") == "log" else 0
    return 4 * stride


def stated_mesher(method: str, build_options: dict[str, Any]) -> Any:
    """The mesher of ``method`` with the options the store states: a mesher module's
    ``mesher_for(build_options)`` where it has one (e.g. the adaptive TIN's error ladder, planned from the
    first epoch's data and fixed for the store like the quantisation), else the registered mesher."""
    import sys

    fn = METHODS[method]
    make = getattr(fn, "mesher_for", None) or getattr(sys.modules.get(fn.__module__), "mesher_for", None)
    return make(build_options) if callable(make) else fn


def changed_samples(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """(H, W) bool: where elevation (bit for bit, as float32) or validity differ between two epochs."""
    za = np.ascontiguousarray(a[0], np.float32).view(np.uint32)
    zb = np.ascontiguousarray(b[0], np.float32).view(np.uint32)
    return (za != zb) | (np.asarray(a[1], bool) != np.asarray(b[1], bool))


def dirty_tiles(pyramid: TilePyramid, changed: np.ndarray, method: str) -> set[TileCode]:
    """Tiles whose source window (with the mesher's margin, plus one sample) holds a changed sample."""
    h, w = changed.shape
    sat = np.zeros((h + 1, w + 1), np.int64)
    sat[1:, 1:] = np.cumsum(np.cumsum(changed, axis=0, dtype=np.int64), axis=1)
    if sat[-1, -1] == 0:
        return set()
    out = set()
    for code in pyramid.all_codes():
        s = pyramid.stride(code[0])
        m = window_margin(method, s) + 1
        r0, c0 = pyramid.origin_rc(code)
        span = pyramid.span(code[0])
        ra, rb = max(r0 - m, 0), min(r0 + span + m, h - 1) + 1
        ca, cb = max(c0 - m, 0), min(c0 + span + m, w - 1) + 1
        if sat[rb, cb] - sat[ra, cb] - sat[rb, ca] + sat[ra, ca] > 0:
            out.add(code)
    return out


def check_same_grid(store: TileStore, hf: Heightfield, where: str) -> None:
    """Refuse (one line naming ``where``) a heightfield on another grid or CRS than the store's."""
    if (hf.width, hf.height) != (int(store.meta["width"]), int(store.meta["height"])):
        raise InputError(
            f"is {hf.width} x {hf.height} samples, the store {store.path.name} holds "
            f"{store.meta['width']} x {store.meta['height']}: an epoch must share the store's grid",
            where,
        )
    t = tuple(hf.transform)[:6]
    if not np.allclose(t, store.meta["transform"][:6], rtol=0, atol=1e-6):
        raise InputError(
            f"lies on another grid (transform {t}) than the store {store.path.name} "
            f"({tuple(store.meta['transform'][:6])}): an epoch must share the store's grid",
            where,
        )
    if not _same_crs(hf.crs, store.crs):
        raise InputError(f"has another CRS than the store {store.path.name}: an epoch must share it", where)


def _same_crs(a: str | None, b: str | None) -> bool:
    if not a or not b:
        return not a and not b
    if a == b:
        return True
    try:
        from rasterio.crs import CRS

        return bool(CRS.from_user_input(a) == CRS.from_user_input(b))
    except Exception:  # noqa: BLE001 - unparsable CRS text: compare the text
        return False


def check_quantisation(store: TileStore, hf: Any, where: str, ranges: Sequence[float] | None = None) -> None:
    """Refuse an epoch whose relief leaves the store's fixed 16-bit vertical lattice at some level.
    ``ranges``: each level's largest tile relief as measured by a streamed scan (else taken from ``hf``)."""
    method = str(store.meta.get("method"))
    p = store.pyramid
    for k in p.levels:
        s = p.stride(k)
        rng = (
            float(ranges[k])
            if ranges is not None
            else float(_level_max_range(hf.elevation_m, s, p.tile_size, s if method == "chunked" else 1))
        )
        cap = 65534.0 * store.quantisation[k].z_step_m
        if rng > cap:
            raise InputError(
                f"relief {rng:.1f} m within one tile of level {k} exceeds the {cap:.1f} m the store "
                f"{store.path.name} quantises (fixed at its first build); rebuild the store from its "
                "epochs with `terralod build ... --epoch`",
                where,
            )


def stored_heightfield(store: TileStore, epoch: str | None = None) -> Heightfield:
    """The elevation grid of ``epoch`` (default: the store's selected epoch) exactly as it was built: from
    the samples the store keeps, else (a store built without ``--epoch``) re-read from the source file it
    names, when that still has the digest the store recorded."""
    t = Affine(*store.meta["transform"][:6])
    name = epoch if epoch is not None else store.epoch
    what = f"epoch {name!r}" if name is not None else "its tiles"
    info = store.epoch_info(name) if (store.has_epochs and name is not None) else dict(store.meta)
    kept = store.epoch_source(name) if store.has_epochs and name is not None else None
    if kept is not None:
        z, v = kept
        return Heightfield(z, v, t, store.crs, str(info.get("source", "")), str(info.get("fill_method", "")),
                           tuple(info.get("notes", ())))  # fmt: skip
    src = str(info.get("source") or store.meta.get("source") or "")
    digest = info.get("source_digest") or store.meta.get("source_digest")
    from terralod.io.reader import SAMPLE_SOURCE, read_heightfield, sample_heightfield

    if src == SAMPLE_SOURCE:
        hf = sample_heightfield()
    elif src and Path(src).exists():
        hf = read_heightfield(src)
    else:
        raise StoreError(
            f"keeps no source samples for {what} and its source {src!r} is gone; "
            "rebuild the store with `terralod build SOURCE -o STORE --epoch DATE`",
            str(store.path),
        )
    if hf.digest() != digest:
        raise StoreError(
            f"keeps no source samples for {what} and {src} no longer reads as the DEM it was built "
            "from; rebuild the store with `terralod build SOURCE -o STORE --epoch DATE`",
            str(store.path),
        )
    return hf


@dataclass
class UpdateReport:
    """What an update did. ``tiles_dirty`` = tiles of the new epoch rebuilt (now or before a resume);
    ``tiles_shared`` = tiles taken unchanged from the base epoch."""

    path: Path
    epoch: str
    base_epoch: str
    tiles_total: int
    tiles_dirty: int
    tiles_built: int
    tiles_skipped: int
    changed_samples: int
    seconds: float
    build_seconds: float
    complete: bool
    build_cpu_s: float = 0.0

    @property
    def tiles_shared(self) -> int:
        return self.tiles_total - self.tiles_dirty

    @property
    def ms_per_tile(self) -> float:
        return 1e3 * self.build_seconds / self.tiles_built if self.tiles_built else 0.0

    @property
    def cpu_ms_per_tile(self) -> float:
        """CPU milliseconds (all threads) of meshing, measuring and writing per rebuilt tile."""
        return 1e3 * self.build_cpu_s / self.tiles_built if self.tiles_built else 0.0

    def as_dict(self) -> dict[str, Any]:
        d = dict(vars(self))
        d["path"] = str(self.path)
        d["tiles_shared"] = self.tiles_shared
        d["ms_per_tile"] = self.ms_per_tile
        d["cpu_ms_per_tile"] = self.cpu_ms_per_tile
        return d


#: Epoch names: dates and simple names, 1 to 64 of letters, digits, ``-``, ``_`` and ``.``, not starting
#: with ``-`` or ``.``, without ``..`` (they appear in URLs, file names and command lines as they are).
EPOCH_NAME = re.compile(r"^(?!.*\.\.)[A-Za-z0-9_][A-Za-z0-9_.-]{0,63}$")


def validate_epoch_name(name: str, where: str) -> str:
    """``name`` when it is an allowed epoch name (:data:`EPOCH_NAME`), else one line naming ``where``."""
    name = str(name).strip()
    if not EPOCH_NAME.match(name):
        raise InputError(
            f"expected an epoch name such as 2007-07-05 or survey_2 (letters, digits, '-', '_', '.'; not "
            f"starting with '-' or '.', no '..', at most 64), got {name!r}",
            where,
        )
    return name


def finish_advice(store_path: str | os.PathLike[str], row: dict[str, Any]) -> str:
    """How to finish (or drop) the interrupted epoch ``row`` (a :meth:`TileStore.epoch_rows` row): the exact
    ``terralod update|edit ... --resume`` command, from what the epoch recorded when it began."""
    import shlex

    q, info, name, store = shlex.quote, row["info"], str(row["name"]), str(store_path)
    base = f" --from {q(str(info['base']))}" if info.get("base") else ""
    args, src = info.get("edit_args") or {}, info.get("source")
    cmd = None
    if info.get("kind") == "edit" and "polygon" in args:
        cmd = f"terralod edit {q(store)} --polygon {q(args['polygon'])} --depth-m {args['depth_m']!r}"
    elif info.get("kind") == "edit" and "patch" in args:
        cmd = f"terralod edit {q(store)} --patch {q(args['patch'])}"
    elif info.get("kind") == "update" and src and Path(src).is_file():
        cmd = f"terralod update {q(store)} {q(str(src))}"
    drop = f"`terralod epochs {q(store)} --delete {q(name)}`"
    if cmd is None:
        return f"finish it with the same command plus --resume, or remove it with {drop}"
    return f"finish it with `{cmd} --epoch {q(name)}{base} --resume` or remove it with {drop}"


def _check_update(
    store: TileStore, hf: Any, epoch: str, resume: bool, digest: str | None = None,
    ranges: Sequence[float] | None = None,
) -> dict[str, Any] | None:  # fmt: skip
    """Refuse an update that cannot go ahead (one line); the interrupted row of ``epoch`` when resuming.
    ``hf``: the new epoch's heightfield, or a window source with its streamed ``digest`` and ``ranges``."""
    p = store.path
    if not store.complete:
        raise StoreError("is an incomplete build; finish it with `terralod build ... --resume` first", str(p))
    rows = store.epoch_rows()
    same = next((r for r in rows if r["name"] == epoch), None)
    pending = [r for r in rows if r["state"] == "building"]
    if same is not None and same["state"] == "complete":
        raise InputError(f"epoch {epoch!r} exists already (epochs: {', '.join(store.epochs)})", str(p))
    if same is not None and not resume:
        raise StoreError(f"an update to epoch {epoch!r} was interrupted; {finish_advice(p, same)}", str(p))
    others = [r for r in pending if r["name"] != epoch]
    if others:
        raise StoreError(
            f"an update to epoch {others[0]['name']!r} was interrupted; {finish_advice(p, others[0])}", str(p)
        )
    if same is not None and same["info"].get("source_digest") != (digest or hf.digest()):
        raise StoreError(
            f"cannot resume epoch {epoch!r}: it was started from other data ({same['info'].get('source')})",
            str(p),
        )
    check_same_grid(store, hf, hf.source)
    check_quantisation(store, hf, hf.source, ranges)
    method = str(store.meta["method"])
    if method not in METHODS:
        raise StoreError(f"was built with mesher {method!r}, which this terralod does not have", str(p))
    return same


def check_update(
    path: str | os.PathLike[str],
    hf: Heightfield,
    epoch: str,
    *,
    base: str | None = None,
    resume: bool = False,
) -> None:
    """Refuse, before any work or output, an update :func:`update_store` would refuse (read-only)."""
    with TileStore.open(path, epoch=base) as ro:
        _check_update(ro, hf, validate_epoch_name(epoch, str(path)), resume)


def update_store(
    hf: Heightfield,
    path: str | os.PathLike[str],
    epoch: str,
    *,
    base: str | None = None,
    resume: bool = False,
    workers: int | None = None,
    progress: Callable[[int, int], None] | None = None,
    stop_after: int | None = None,
    kind: str = "update",
    info: dict[str, Any] | None = None,
    base_name: str = DEFAULT_EPOCH,
) -> UpdateReport:
    """Add epoch ``epoch`` (the heightfield ``hf``, on the store's grid) to the store at ``path``.

    Parameters
    ----------
    base : the epoch whose tiles are shared where nothing changed (default: the latest).
    resume : finish an interrupted update of the same epoch and source.
    progress : ``progress(done, total_dirty)`` after each committed batch.
    stop_after : rebuild at most this many tiles, then return without committing (tests).
    kind, info : recorded with the epoch ("update", "edit" and what the edit was).
    base_name : name given to the tiles of a store built without ``--epoch``, which become its first epoch.
    """
    p = Path(path)
    t_start = time.perf_counter()
    epoch = validate_epoch_name(epoch, str(p))
    with TileStore.open(
        p, epoch=base
    ) as ro:  # every check on a read-only connection: bad input writes nothing
        same = _check_update(ro, hf, epoch, resume)
        method = str(ro.meta["method"])
        old = stored_heightfield(ro)
    store = TileStore.open(p, writable=True, epoch=base)
    try:
        if not store.has_epochs:
            store.adopt_tiles_as_epoch(base_name, {**epoch_record(old, "build"), "created": None})
        base_epoch = str(store.epoch)
        base_id = int(store.epoch_id or 0)
        changed = changed_samples((old.elevation_m, old.valid), (hf.elevation_m, hf.valid))
        pyramid = store.pyramid
        dirty = dirty_tiles(pyramid, changed, method)
        record = epoch_record(hf, kind, base=base_epoch, **(info or {}))
        if same is None:
            eid = store.begin_epoch(epoch, record)
        else:
            eid = int(same["id"])
            store.resume_epoch(eid)
        store.put_epoch_source(eid, hf.elevation_m, hf.valid, like=base_id, changed=changed)
        errors = store.tile_errors()  # the base epoch's
        done = store.rev_tile_errors(eid)
        errors.update(done)
        todo = [c for c in pyramid.all_codes(finest_first=True) if c in dirty and c not in done]
        n_skipped = len(dirty) - len(todo)
        if stop_after is not None:
            todo = todo[: max(0, stop_after)]
        c_build = time.process_time()
        built, t_build = _rebuild(
            store, hf, pyramid, method, todo, errors, workers, progress, n_skipped, len(dirty)
        )
        c_build = time.process_time() - c_build
        complete = n_skipped + built == len(dirty)
        if complete:
            _commit_epoch(store, eid, base_id, dirty, record, int(changed.sum()))
            store.widen_colour_range(hf)
    finally:
        store.close()
    seconds = time.perf_counter() - t_start
    log.info("epoch %s: %d dirty tiles, %d rebuilt now, in %.2f s", epoch, len(dirty), built, seconds)
    return UpdateReport(p, epoch, base_epoch, len(pyramid.all_codes()), len(dirty), built, n_skipped,
                        int(changed.sum()), seconds, t_build, complete, c_build)  # fmt: skip


def _commit_epoch(store: TileStore, eid: int, base_id: int, dirty: Any, record: dict[str, Any],
                  changed: int) -> None:  # fmt: skip
    """Make epoch ``eid`` complete: the base epoch's map with the ``dirty`` tiles pointing at the new rev."""
    revs = store.epoch_tile_revs(base_id)
    n = 0
    for c in dirty:
        revs[c] = eid
        n += 1
    record.update(tiles_rebuilt=n, tiles_shared=len(revs) - n, changed_samples=changed)
    store.commit_epoch(eid, revs, record)


def _tile_count(pyramid: TilePyramid) -> int:
    return sum(nx * ny for nx, ny in map(pyramid.grid_count, pyramid.levels))


def _rebuild(
    store: TileStore, hf: Heightfield, pyramid: TilePyramid, method: str, todo: list[TileCode],
    errors: dict[TileCode, tuple[float, float]], workers: int | None,
    progress: Callable[[int, int], None] | None, n_skipped: int, total: int,
) -> tuple[int, float]:  # fmt: skip
    """Mesh and measure ``todo`` (finest first) level by level, committing batches; (tiles built, seconds)."""
    mesh_fn = stated_mesher(method, store.meta.get("build_options") or {})
    quant = store.quantisation
    n_workers = max(1, workers or os.cpu_count() or 1)
    built = 0
    t0 = time.perf_counter()
    if progress:
        progress(n_skipped, total)
    with ThreadPoolExecutor(max_workers=n_workers) as pool:
        for level in reversed(pyramid.levels):
            codes = [c for c in todo if c[0] == level]
            if not codes:
                continue

            def one(code: TileCode, _lvl: int = level) -> EncodedTile:
                kids = [errors[c] for c in pyramid.children(code)]
                return build_tile(hf, pyramid, code, quant[_lvl], mesh_fn, kids)

            batch: list[EncodedTile] = []
            for enc in pool.map(one, codes):
                batch.append(enc)
                errors[enc.code] = (enc.error_m, enc.vertical_error_m)
                if len(batch) >= _BATCH_TILES:
                    store.write_tiles(batch)
                    built += len(batch)
                    batch = []
                    if progress:
                        progress(n_skipped + built, total)
            if batch:
                store.write_tiles(batch)
                built += len(batch)
                if progress:
                    progress(n_skipped + built, total)
    return built, time.perf_counter() - t0


# -- window by window -----------------------------------------------------------------------------------
class DirtyTiles:
    """:func:`dirty_tiles` found strip by strip: each level's (ny, nx) mask of the tiles whose source window
    (the mesher's margin plus one sample) holds a changed sample, from the changed samples of full-width
    strips of rows given in any order. The same tiles as :func:`dirty_tiles` of the whole mask; memory: one
    byte a tile."""

    def __init__(self, pyramid: TilePyramid, method: str) -> None:
        self.pyramid, self.method = pyramid, method
        self.masks = {}
        for k in pyramid.levels:
            nx, ny = pyramid.grid_count(k)
            self.masks[k] = np.zeros((ny, nx), bool)
        self.changed_samples = 0

    def add(self, row0: int, changed: np.ndarray) -> None:
        """Record the changed samples ``changed`` ((rows, W) bool) of rows ``row0 ..``."""
        n = int(np.count_nonzero(changed))
        if n == 0:
            return
        self.changed_samples += n
        p = self.pyramid
        h, w = p.height, p.width
        a, b = int(row0), int(row0) + changed.shape[0]
        tx = np.arange(self.masks[p.max_level].shape[1] + 1)
        for k, mask in self.masks.items():
            span = p.span(k)
            m = window_margin(self.method, p.stride(k)) + 1
            ny, nx = mask.shape
            c0 = tx[:nx] * span
            ca, cb = np.maximum(c0 - m, 0), np.minimum(c0 + span + m, w - 1) + 1
            for ty in range(max(0, (a - span - m - 1) // span), min(ny, (b + m - 1) // span + 1)):
                ra, rb = max(ty * span - m, 0), min(ty * span + span + m, h - 1) + 1
                lo, hi = max(ra, a), min(rb, b)
                if lo >= hi:
                    continue
                cum = np.zeros(w + 1, np.int64)
                np.cumsum(changed[lo - a : hi - a].any(axis=0), out=cum[1:])
                mask[ty] |= (cum[cb] - cum[ca]) > 0

    def codes(self) -> list[TileCode]:
        """The dirty tiles, finest level first."""
        out: list[TileCode] = []
        for k in sorted(self.masks, reverse=True):
            ys, xs = np.nonzero(self.masks[k])
            out += [(k, int(x), int(y)) for y, x in zip(ys.tolist(), xs.tolist(), strict=True)]
        return out


def update_store_windowed(
    src: Any,
    path: str | os.PathLike[str],
    epoch: str,
    *,
    base: str | None = None,
    resume: bool = False,
    workers: int | None = None,
    client: Any = None,
    progress: Callable[[int, int], None] | None = None,
    stop_after: int | None = None,
    retries: int = 3,
) -> UpdateReport:
    """:func:`update_store` of a survey never held whole: ``src`` is a window source on the store's grid
    (:mod:`terralod.io.windowed`: a mosaic, a region of geographic tiles warped to the store's frame) and the
    store keeps the base epoch's samples (built with ``epoch=``, in memory or by
    :func:`terralod.pyramid.distributed.build_store_windowed`).

    1. One streamed pass over ``src`` (:func:`~terralod.pyramid.distributed.scan_source`): its digest and
       per-level relief, refused in one line, before anything is written, when the store's fixed lattice
       cannot hold it or the grid is not the store's.
    2. One pass in strips of :data:`~terralod.store_epochs.SOURCE_BLOCK` rows: the base epoch's kept
       samples and the survey's compared bit for bit (:func:`changed_samples`), the dirty tiles found
       (:class:`DirtyTiles`: :func:`dirty_tiles`' rule), the new samples kept (a block without a change
       shares the base's), in one transaction.
    3. The dirty tiles rebuilt by the out-of-core builder's work units (the same runner, threads or Dask,
       the same decimation of coarse tiles and measurement against every sample, also a resampled source's
       own), written under the new epoch's rev, their errors made monotone with the clean children's; then
       the epoch's map and ``complete`` in one transaction, as :func:`update_store`.

    Each rebuilt tile is the tile :func:`~terralod.pyramid.distributed.build_store_windowed` makes of the
    survey with the store's lattice; with a source read whole it is :func:`update_store`'s. Memory: a strip
    of each epoch, the units in flight and a byte or two a tile (the dirty masks, the errors)."""
    from terralod.pyramid import distributed as dist
    from terralod.store_epochs import SOURCE_BLOCK

    p = Path(path)
    t_start = time.perf_counter()
    epoch = validate_epoch_name(epoch, str(p))
    with TileStore.open(p, epoch=base) as ro:
        pyramid = ro.pyramid
        check_same_grid(ro, src, src.source)  # before the pass over the survey
        plan = dist.scan_source(src, pyramid)
        method = str(ro.meta["method"])
        ranges = plan.range_grid_m if method == "chunked" else plan.range_all_m
        same = _check_update(ro, src, epoch, resume, digest=plan.digest, ranges=ranges)
        base_src = ro.epoch_source_id(ro.epoch) if ro.has_epochs else None
        if base_src is None:
            raise StoreError(
                f"keeps no samples of {'epoch ' + repr(ro.epoch) if ro.epoch else 'its tiles'} to compare a "
                "survey with window by window; build it with `terralod build INPUT -o STORE --epoch DATE`",
                str(p),
            )
    store = TileStore.open(p, writable=True, epoch=base)
    runner = None
    try:
        base_epoch = str(store.epoch)
        base_id = int(store.epoch_id or 0)
        record = epoch_record(dist._FrameMeta(src, plan), "update", base=base_epoch)
        if same is None:
            eid = store.begin_epoch(epoch, record)
        else:
            eid = int(same["id"])
            store.resume_epoch(eid)
        dirty = DirtyTiles(pyramid, method)

        def strips() -> Any:
            for r0, z, ok in dist.source_strips(src, SOURCE_BLOCK):
                ch = changed_samples(store.epoch_source_window(base_src, r0, r0 + z.shape[0]), (z, ok))
                dirty.add(r0, ch)
                yield r0, z, ok, ch

        store.put_epoch_source_strips(eid, src.width, strips(), like=base_src)
        errors = dist.TileErrors(pyramid)
        errors.update(store.each_tile_error())  # the base epoch's
        done = store.rev_tile_errors(eid)
        errors.update(done)
        todo = {k: m.copy() for k, m in dirty.masks.items()}
        for k, x, y in done:
            todo[k][y, x] = False
        n_dirty = sum(int(m.sum()) for m in dirty.masks.values())
        n_skipped = n_dirty - sum(int(m.sum()) for m in todo.values())
        if stop_after is not None:
            left = max(0, stop_after)
            for k in sorted(todo, reverse=True):  # finest first: a tile's children come before it
                flat = todo[k].reshape(-1)
                at = np.flatnonzero(flat)
                flat[at[left:]] = False
                left = max(0, left - len(at))
        for k, m in todo.items():
            errors.forget(k, m)  # rebuilt: a parent waits for the new errors, not the base's
        if progress:
            progress(n_skipped, n_dirty)
        runner = (
            dist._DaskRunner(client, retries)
            if client is not None
            else dist._ThreadRunner(max(1, workers or os.cpu_count() or 1))
        )
        shared, slots = runner.share(src), runner.slots()
        options, quant, tile_size = store.meta.get("build_options"), store.quantisation, pyramid.tile_size
        early, rest = dist._unit_order(
            pyramid, todo, dist.UNIT_SPAN_SAMPLES, dist._EARLY_UNITS_PER_SLOT * slots
        )
        jobs = (dist.unit_job(shared, tile_size, method, u, quant, dist.MAX_WINDOW_SAMPLES, options)
                for u in itertools.chain(early, rest))  # fmt: skip
        c_build, t_build = time.process_time(), time.perf_counter()
        measured = (e for tiles in runner.stream(jobs, dist._AHEAD_UNITS_PER_SLOT * slots) for e in tiles)
        built = commit_streamed(store, dist._monotone(measured, pyramid, errors), errors, 0,
                                lambda n: progress(n_skipped + n, n_dirty) if progress else None)  # fmt: skip
        c_build, t_build = time.process_time() - c_build, time.perf_counter() - t_build
        complete = n_skipped + built == n_dirty
        if complete:
            _commit_epoch(store, eid, base_id, dirty.codes(), record, dirty.changed_samples)
            store.widen_colour_range_m(*plan.z_range_m)
    finally:
        if runner is not None:
            runner.close()
        store.close()
    seconds = time.perf_counter() - t_start
    log.info(
        "epoch %s: %d dirty tiles, %d rebuilt now, in %.2f s, window by window",
        epoch,
        n_dirty,
        built,
        seconds,
    )
    return UpdateReport(p, epoch, base_epoch, _tile_count(pyramid), n_dirty, built, n_skipped,
                        dirty.changed_samples, seconds, t_build, complete, c_build)  # fmt: skip
