"""Numba kernels, grouped by concern; every kernel is a pure function on arrays (no I/O, no exceptions).

``jit`` is the one decorator every kernel uses (the datashader habit), so compile options are set in one
place:

- ``cache=True``: compiled code is cached on disk next to the module, so a second process starts fast;
  a cache that cannot be written (full disk, read-only install, file-size limit) is logged and skipped:
  the kernel compiled in memory runs all the same (numba would raise the ``OSError`` instead);
- ``nogil=True``: kernels release the GIL, so the builder can mesh and measure tiles on threads;
- ``fastmath=False``: IEEE arithmetic, no reassociation or contraction, so results are reproducible and
  the exact geometric predicates (e.g. the shared-edge coverage test in :mod:`terralod.kernels.error`)
  give the same answer as the numpy reference;
- ``error_model="numpy"``: division by zero gives inf/nan instead of raising, so kernels never raise and
  divisions carry no zero check.

``leaf`` is ``jit`` for the small helpers that kernels call in their inner loops with array arguments and
that allocate nothing (they make, slice or return no array): it compiles them without the runtime's
reference counting (numba's ``_nrt=False``). With it, every call of a helper increments and decrements the
count of each array it reads, atomically: with numba 0.68 about 40 ns a call with three arrays, which was
most of the time of a Delaunay insertion (:mod:`terralod.kernels.adaptive`), of a cohesion vertex move
(:mod:`terralod.kernels.cohesion`) and of the rasterisation of a small triangle (:mod:`terralod.kernels.error`).
The arithmetic is the same (results bit for bit); a leaf that allocated would fail to compile. Leaves are
called from kernels only, not from Python.

:func:`dispatchers` lists the kernels (the entry points, or every one): ``terralod warmup`` compiles them
and its test checks it. numba is imported nowhere else in the package (tests/test_architecture.py).
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, TypeVar

import numba

_F = TypeVar("_F", bound=Callable[..., Any])

if TYPE_CHECKING:  # to a type checker a kernel is the Python function it compiles (same signature)

    def jit(fn: _F, /) -> _F: ...

    def leaf(fn: _F, /) -> _F: ...

else:
    jit = functools.partial(numba.njit, cache=True, nogil=True, fastmath=False, error_model="numpy")
    leaf = functools.partial(jit, _nrt=False)


def _tolerate_cache_write_errors() -> None:
    """Make a failed write of numba's on-disk cache a logged warning instead of an error of the caller."""
    from numba.core import caching

    save = caching.Cache.save_overload
    if getattr(save, "_terralod_tolerant", False):
        return

    @functools.wraps(save)
    def save_overload(self: Any, sig: Any, data: Any) -> None:
        try:
            save(self, sig, data)
        except OSError as exc:
            logging.getLogger("terralod.kernels").warning(
                "kernel cache not written (%s); the kernel compiles again in the next process", exc
            )

    save_overload._terralod_tolerant = True  # type: ignore[attr-defined]
    caching.Cache.save_overload = save_overload  # type: ignore[method-assign]


_tolerate_cache_write_errors()


def dispatchers(*, helpers: bool = False) -> list[Any]:
    """The kernels of this package (numba dispatchers, in module and definition order); imports every
    kernel module.

    By default the entry points only: the kernels no other kernel calls, which the API layer calls from
    Python. ``helpers=True`` adds the kernels and leaves that other kernels call: each compiles inside its
    callers (and is cached with them), so its own dispatcher holds no signature when its callers come from
    the on-disk cache. ``terralod warmup`` compiles every entry point, hence every kernel."""
    import importlib
    import pkgutil

    from numba.core.registry import CPUDispatcher

    found: list[Any] = []
    called: set[int] = set()
    for m in sorted(pkgutil.iter_modules(__path__), key=lambda m: m.name):
        mod = importlib.import_module(f"{__name__}.{m.name}")
        space = vars(mod)
        for v in list(space.values()):
            if isinstance(v, CPUDispatcher) and v.py_func.__module__ == mod.__name__:
                found.append(v)
                called.update(id(c) for c in _callees(v.py_func.__code__, space, CPUDispatcher) if c is not v)
    return found if helpers else [d for d in found if id(d) not in called]


def _callees(code: Any, space: dict[str, Any], kind: type) -> list[Any]:
    """The dispatchers a function's code names (its nested code objects included), looked up in ``space``."""
    out = [space[n] for n in code.co_names if isinstance(space.get(n), kind)]
    for c in code.co_consts:
        if hasattr(c, "co_names"):
            out += _callees(c, space, kind)
    return out


__all__ = ["dispatchers", "jit", "leaf"]
