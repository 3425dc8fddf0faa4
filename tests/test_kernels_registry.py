"""Every numba kernel is registered in terralod.kernels and compiled by ``terralod warmup``."""

from __future__ import annotations

from terralod import kernels


def _name(d) -> str:
    return f"{d.py_func.__module__}.{d.py_func.__name__}"


def test_dispatchers_split_entry_points_and_helpers() -> None:
    """The entry points are the kernels no kernel calls; with the helpers they are every kernel, the
    web export's included."""
    entry = {_name(d) for d in kernels.dispatchers()}
    every = {_name(d) for d in kernels.dispatchers(helpers=True)}
    assert entry and entry < every
    assert {"terralod.kernels.qmesh.walk_order", "terralod.kernels.qmesh.merge_uv",
            "terralod.kernels.lattice.clip_mesh", "terralod.kernels.error.points_vertical_error",
            "terralod.kernels.error.lattice_vertical_error"} <= entry  # fmt: skip
    assert {"terralod.kernels.qmesh._free", "terralod.kernels.error.triangle_gap"} <= every - entry


def test_warm_up_compiles_every_entry_point() -> None:
    """After warm_up every entry point holds a compiled signature (from the on-disk cache or compiled
    now); the helpers compile inside them."""
    from terralod.warmup import warm_up

    warm_up()
    cold = [_name(d) for d in kernels.dispatchers() if len(d.signatures) == 0]
    assert cold == []
