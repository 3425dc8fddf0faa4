"""Opening what a command is given as a terrain: a store, a TIN, or a DEM built once into a cached
store (with fractal detail below it when asked).
"""

from __future__ import annotations

import os
import sqlite3
from pathlib import Path
from typing import Any

from terralod.cli._console import progress
from terralod.cli._errors import store_write_error
from terralod.cli._options import check_raster_size, is_store, load


def run_build(hf, out: str, *, tile_size: int, method: str, workers: int | None, resume: bool, overwrite: bool,
              **extra: Any):  # fmt: skip
    """:func:`terralod.pyramid.builder.build_store` with a progress bar (``extra``: more of its options)."""
    from terralod.pyramid.builder import build_store

    with progress("building") as prog:
        task = prog.add_task(Path(out).name, total=None)

        def cb(done: int, total: int) -> None:
            prog.update(task, completed=done, total=total)

        try:
            return build_store(hf, out, tile_size=tile_size, method=method, workers=workers, resume=resume,
                               overwrite=overwrite, progress=cb, **extra)  # fmt: skip
        except sqlite3.Error as exc:  # disk full, I/O error, file-size limit: name the store and the way on
            raise store_write_error(exc, out) from exc


def user_cache_dir() -> Path:
    """``$XDG_CACHE_HOME/terralod`` (default ``~/.cache/terralod``): caches never go beside an input,
    whose folder may be read-only."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "terralod"


def cache_store_path(source: str | Path, digest: str) -> Path:
    """Where the cache store of a DEM goes: the user cache folder, named by the DEM and its digest."""
    p = Path(source)
    return user_cache_dir() / "views" / f"{p.stem}-{digest[:16]}.terra"


def open_or_build(path: str, read: dict[str, Any], tile_size: int | None = None) -> Path:
    """A store path as is; a DEM is built into a cache store in the user cache folder first (rebuilt only
    when missing or from another version of the DEM)."""
    from terralod.errors import StoreError
    from terralod.pyramid.builder import DEFAULT_METHOD, default_tile_size
    from terralod.store import open_store

    p = Path(path)
    tile_size = tile_size or default_tile_size(DEFAULT_METHOD)
    if p.exists() and is_store(p):
        return p
    hf = load(path, **read)
    cache = cache_store_path(p, hf.digest())
    cache.parent.mkdir(parents=True, exist_ok=True)
    if cache.exists():
        try:
            with open_store(cache) as s:
                if s.complete and s.meta.get("source_digest") == hf.digest():
                    return cache
        except StoreError:
            pass
    run_build(hf, str(cache), tile_size=tile_size, method=DEFAULT_METHOD, workers=None, resume=False,
              overwrite=True)  # fmt: skip
    return cache


def with_fractal(store, path: str, read: dict[str, Any], levels: int | None):
    """The store itself, or with ``levels`` fractal levels below its finest (Hu & Wang), generated on demand
    from the store's source DEM (the DEM given on the command line, else the one recorded in the store)."""
    if levels is None:  # not given: what the store was built with (``terralod build --fractal N``)
        levels = int(store.meta.get("fractal_levels", 0))
    if not levels:
        return store
    from terralod.errors import InputError
    from terralod.fractal import FractalDetail
    from terralod.io.reader import SAMPLE_SOURCE, sample_heightfield
    from terralod.runtime.fractal_source import FractalSource

    src = path if not is_store(Path(path)) else store.meta.get("source", "")
    hf = sample_heightfield() if src == SAMPLE_SOURCE else load(src, **read)
    if hf.digest() != store.meta.get("source_digest"):
        raise InputError("is not the DEM this store was built from; --fractal needs the store's source", src)
    return FractalSource(store, FractalDetail(hf), levels)


def open_terrain_arg(path: str, read: dict[str, Any], fractal_levels: int | None = None):
    """Any input of render / flythrough / view as a :class:`terralod.terrain.Terrain`: a grid store (with its
    fractal levels), a TIN store, or a DEM built into a cache store first. Close it when done."""
    from terralod.store import open_store
    from terralod.terrain import GridTerrain, open_terrain

    p = Path(path)
    check_raster_size(p)
    if p.is_file() and is_store(p):
        t = open_terrain(p)
        if t.kind != "grid":
            return t
        store = t.store  # type: ignore[union-attr]
    else:
        store = open_store(open_or_build(path, read))
    return GridTerrain(store, with_fractal(store, path, read, fractal_levels), own=True)


__all__ = [
    "run_build",
    "user_cache_dir",
    "cache_store_path",
    "open_or_build",
    "with_fractal",
    "open_terrain_arg",
]
