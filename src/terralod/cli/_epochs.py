"""Epoch options shared by ``render``, ``flythrough`` and ``view``: which epoch to draw, and the
change overlay (gain / loss since another epoch, greyed below a level of detection)."""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator
from typing import Any

import click


def epoch_options(fn: Callable[..., Any]) -> Callable[..., Any]:
    """--epoch, --overlay, --from-epoch, --lod-m."""
    fn = click.option(
        "--lod-m", type=click.FloatRange(min=0.0), default=None,
        help="Level of detection for --overlay change, metres: smaller changes are greyed out "
        "(default 1 m).",
    )(fn)  # fmt: skip
    fn = click.option(
        "--from-epoch", "from_epoch", default=None, metavar="DATE",
        help="Epoch the change overlay compares with (default: the first).",
    )(fn)  # fmt: skip
    fn = click.option(
        "--overlay", type=click.Choice(["none", "change"]), default="none", show_default=True,
        help="change: colour where the ground rose (blue) or dropped (red) since --from-epoch.",
    )(fn)  # fmt: skip
    return click.option("--epoch", default=None, metavar="DATE", help="Epoch to draw (default: the latest).")(
        fn
    )


@contextlib.contextmanager
def at_epoch(terrain: Any, epoch: str | None) -> Iterator[Any]:
    """``terrain`` itself, or the same store at ``epoch`` (closed on exit)."""
    from terralod.errors import InputError

    if epoch is None or epoch == getattr(terrain, "epoch", None):
        yield terrain
        return
    if not hasattr(terrain, "with_epoch"):
        raise InputError("has no epochs (a TIN model)", str(terrain.path))
    eps = terrain.epochs
    if epoch not in eps:
        raise InputError(f"has no epoch {epoch!r} (epochs: {', '.join(eps) or 'none'})", str(terrain.path))
    t = terrain.with_epoch(epoch)
    try:
        yield t
    finally:
        t.close()


def overlay_for(
    terrain: Any, overlay: str, from_epoch: str | None, lod_m: float | None, settings: Any
) -> Any:
    """The :class:`terralod.render.overlay.ChangeOverlay` asked for (set on ``settings``, whose elevation
    legend then gives way to the change legend), or None."""
    if overlay != "change":
        return None
    from terralod.render.overlay import DEFAULT_LOD_M, change_overlay

    ov = change_overlay(terrain, None, from_epoch, lod_m=DEFAULT_LOD_M if lod_m is None else lod_m)
    settings.overlay = ov
    settings.legend = False
    return ov


def caption(img: Any, terrain: Any, ov: Any) -> Any:
    """The date of the epoch drawn (stores with epochs) and the change legend, burnt into ``img``."""
    from terralod.render.overlay import annotate

    date = getattr(terrain, "epoch", None)
    if len(getattr(terrain, "epochs", [])) < 2:
        date = None  # one epoch: nothing to tell apart
    if not date and ov is None:
        return img
    return annotate(img, date=date, overlay=ov)
