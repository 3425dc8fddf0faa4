"""Numba kernels, grouped by concern; every kernel is a pure function on arrays (no I/O, no exceptions).

``jit`` is the one decorator every kernel uses (the datashader habit), so compile options are set in one
place:

- ``cache=True``: compiled code is cached on disk next to the module, so a second process starts fast;
- ``nogil=True``: kernels release the GIL, so the builder can mesh and measure tiles on threads;
- ``fastmath=False``: IEEE arithmetic, no reassociation or contraction, so results are reproducible and
  the exact geometric predicates (e.g. the shared-edge coverage test in :mod:`terralod.kernels.error`)
  give the same answer as the numpy reference;
- ``error_model="numpy"``: division by zero gives inf/nan instead of raising, so kernels never raise and
  divisions carry no zero check.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, TypeVar

import numba

_F = TypeVar("_F", bound=Callable[..., Any])

if TYPE_CHECKING:  # to a type checker a kernel is the Python function it compiles (same signature)

    def jit(fn: _F, /) -> _F: ...

else:
    jit = functools.partial(numba.njit, cache=True, nogil=True, fastmath=False, error_model="numpy")

__all__ = ["jit"]
