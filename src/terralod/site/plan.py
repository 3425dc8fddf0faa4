"""The plan of a change site: what the page shows, computed once and read by both the site writer
(:mod:`terralod.site.build`) and ``terralod serve`` (:mod:`terralod.serve.server`), so that a folder and a
server of the same epochs show the same site.

A :class:`SitePlan` holds:

- the epochs (oldest first) and the pairs a site carries (:func:`terralod.site.data.pairs_of`), each measured
  once by :func:`terralod.change.volumes.measure_change` as :class:`SiteOptions` say (co-registration on or
  off, the estimator); a pair the caller already measured (``terralod change``'s own) is used as given;
- the bounds (degrees), from :meth:`terralod.export.geodesy.Geodesy.lonlat_bounds` of the first epoch's
  footprint and nowhere else; the heights, the area and the title;
- the pruning: ``keep_error_m``, the smallest level of detection of the pairs (tiles whose measured error is at
  most it become leaves; 0 = nothing pruned), and whether tiles several epochs share are kept once;
- each pair's description (``pairs/K.json``) and its rasters as tile pyramids (:mod:`terralod.site.tiles`), a
  pyramid several pairs share (the same tiles) written once: ``pair_meta[K]["rasters"]`` says where each
  pyramid's tiles are, ``files`` holds every tile once; ``site.json`` states the tiles' encoding.
"""

from __future__ import annotations

from collections.abc import Mapping, MutableMapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Any

from terralod.site.data import PairRasters, epoch_key, epoch_label, pair_key, pair_payload, pairs_of
from terralod.site.tiles import ENCODING

__all__ = ["PlannedPair", "SiteOptions", "SitePlan", "plan_site", "plan_store_site", "plan_windowed_site"]


@dataclass(frozen=True)
class SiteOptions:
    """How a site's pairs are measured and its tiles written."""

    #: line AFTER up with BEFORE before differencing (``terralod change --no-coregister`` turns it off)
    coregistration: bool = True
    #: the co-registration estimator (:data:`terralod.change.coregister.METHODS`)
    method: str = "xdem"
    #: leave out the tile levels finer than the pairs' level of detection
    prune: bool = True
    #: keep a tile several epochs share (the same bytes) once
    share_tiles: bool = True


@dataclass(frozen=True)
class PlannedPair:
    """One measured pair: epoch names, the dates the page shows (None for a name that is no date) and the
    :class:`terralod.change.volumes.ChangeResult`."""

    before: str
    after: str
    dates: tuple[str | None, str | None]
    result: Any


@dataclass(frozen=True)
class SitePlan:
    """Everything a site shows apart from the tiles themselves (module docstring)."""

    title: str
    epochs: tuple[str, ...]
    pairs: tuple[PlannedPair, ...]
    bounds_deg: tuple[float, float, float, float]
    elevation_range_m: tuple[float, float]
    area_km2: float
    keep_error_m: float
    share_tiles: bool
    pair_meta: tuple[dict[str, Any], ...]
    files: Mapping[str, bytes]
    #: what the heights are above, for the page's words: {"datum": key, "words": "above sea level" | ...,
    #: "conversion": what the 3D Tiles did with them (Geodesy.vertical_record: PROJ's operation, accuracy)}
    heights: Mapping[str, Any] = field(default_factory=lambda: {"datum": "unknown", "words": "as surveyed"})

    @property
    def between(self) -> str:
        """' between 25 Sep 2000 and 5 Jul 2007' (empty for a single epoch)."""
        if len(self.epochs) < 2:
            return ""
        return f" between {epoch_label(self.epochs[0])} and {epoch_label(self.epochs[-1])}"

    def manifest(self) -> dict[str, Any]:
        """``site.json``: the epochs, their tilesets, the pairs and where each is described, the rasters'
        encoding (:data:`terralod.site.tiles.ENCODING`)."""
        return {
            "generator": "terralod",
            "title": self.title,
            "bounds_deg": [float(v) for v in self.bounds_deg],
            "elevation_range_m": [float(v) for v in self.elevation_range_m],
            "epochs": [
                {"name": e, "label": epoch_label(e), "tileset": f"epochs/{i}/tileset.json"}
                for i, e in enumerate(self.epochs)
            ],  # fmt: skip
            "pairs": [
                {"from": p.before, "to": p.after, "url": f"pairs/{k}.json"} for k, p in enumerate(self.pairs)
            ],
            "heights": dict(self.heights),
            "rasters": dict(ENCODING),
        }

    def pair_files(self, k: int) -> dict[str, bytes]:
        """The tiles of pair ``k``'s rasters (some may be another pair's)."""
        prefixes = tuple(d["url"] + "/" for d in self.pair_meta[k]["rasters"].values())
        return {name: b for name, b in self.files.items() if name.startswith(prefixes)}


def height_words(vertical: Any) -> dict[str, str]:
    """What the page says heights are above: "above sea level" only for heights above a geoid (what a
    visitor calls sea level), "above the ellipsoid" for ellipsoidal heights, "as surveyed" when nobody said
    (:class:`terralod.export.vertical.VerticalDatum`)."""
    if vertical.above_sea_level:
        return {"datum": vertical.key, "words": "above sea level"}
    if vertical.is_ellipsoidal:
        return {"datum": vertical.key, "words": "above the WGS 84 ellipsoid"}
    return {"datum": vertical.key, "words": "as surveyed (the survey does not say above what)"}


def _heights(geo: Any) -> Mapping[str, Any]:
    """The plan's ``heights``: the page's words for them and what the 3D Tiles did with them."""
    return MappingProxyType({**height_words(geo.vertical), "conversion": geo.vertical_record()})


def _share_pyramids(meta: dict[str, Any], written: dict[str, dict[str, Any]], files: MutableMapping[str, bytes],
                    own: Mapping[str, bytes] | None = None) -> dict[str, Any]:  # fmt: skip
    """A pair's description with each raster pyramid another pair already has (``written``: digest → its
    description) pointing at that one: a pyramid several pairs share is kept once. ``own``: the pair's tiles,
    of which the new pyramids' go into ``files``; without it they are in ``files`` already and a shared
    pyramid's copy is removed from there."""
    for role, desc in list(meta["rasters"].items()):
        prefix = desc["url"] + "/"
        if desc["sha256"] in written:
            kept = written[desc["sha256"]]
            meta["rasters"][role] = kept
            if own is None and kept["url"] != desc["url"]:  # (the same name: the same files, written over)
                for name in [n for n in files if n.startswith(prefix)]:
                    del files[name]
        else:
            if any(
                d["url"] == desc["url"] for d in written.values()
            ):  # one name, other tiles: never silently
                raise ValueError(f"two different rasters under {desc['url']}")
            written[desc["sha256"]] = desc
            if own is not None:
                files.update((n, b) for n, b in own.items() if n.startswith(prefix))
    return meta


def pair_dates(a: str, b: str) -> tuple[str | None, str | None]:
    """The dates a pair of epoch names gives the page (None for a name that is no date)."""
    return (a if epoch_label(a) != a else None, b if epoch_label(b) != b else None)


def plan_site(
    epochs: Sequence[tuple[str, Any]],
    *,
    title: str,
    elevation_range_m: Sequence[float],
    options: SiteOptions = SiteOptions(),
    measured: Mapping[tuple[str, str], Any] | None = None,
    measure: bool = True,
) -> SitePlan:
    """The plan of a site of ``epochs`` ((name, heightfield), oldest first). ``measured``: pairs already
    measured (from, to) → ChangeResult; ``measure=False``: no pairs (the change extra is missing)."""
    from terralod.change.volumes import measure_change
    from terralod.export.geodesy import Geodesy

    names = [n for n, _ in epochs]
    hfs = dict(epochs)
    first = epochs[0][1]
    measured = measured or {}
    pairs = []
    for a, b in pairs_of(names) if measure else []:
        dates = pair_dates(a, b)
        res = measured.get((a, b))
        if res is None:
            res = measure_change(hfs[a], hfs[b], dates=dates, coregistration=options.coregistration,
                                 method=options.method)  # fmt: skip
        pairs.append(PlannedPair(a, b, dates, res))
    lods = [p.result.uncertainty.level_of_detection_m for p in pairs]
    files: dict[str, bytes] = {}
    written: dict[str, dict[str, Any]] = {}
    metas = []
    for p in pairs:
        meta, own = pair_payload(
            p.result,
            p.dates,
            (p.before, p.after),
            pair_key(p.before, p.after),
            before_key=epoch_key(p.before),
        )
        metas.append(_share_pyramids(meta, written, files, own))
    t = first.transform
    lo, hi = elevation_range_m
    geo = Geodesy(first.crs, geographic=True)
    return SitePlan(
        heights=_heights(geo),
        title=title,
        epochs=tuple(names),
        pairs=tuple(pairs),
        bounds_deg=geo.lonlat_bounds(first.bounds_m),
        elevation_range_m=(float(lo), float(hi)),
        area_km2=float(first.valid.sum()) * abs(t.a * t.e) / 1e6,
        keep_error_m=min(lods) if lods and options.prune else 0.0,
        share_tiles=options.share_tiles,
        pair_meta=tuple(metas),
        files=MappingProxyType(files),
    )


def plan_store_site(terrain: Any, options: SiteOptions = SiteOptions(), *, measure: bool = True) -> SitePlan:
    """The plan of a store's site: every epoch (the store's name for a store without epochs), the pairs
    :func:`~terralod.site.data.pairs_of` names. The title is the store's name, with ": how the ground
    changed" when there are pairs."""
    stem = Path(str(terrain.path)).stem if terrain.path else "terrain"
    names = list(terrain.epochs)
    epochs = [(n, terrain.heightfield(n)) for n in names] or [(stem, terrain.heightfield())]
    measure = measure and len(names) >= 2
    title = f"{stem}: how the ground changed" if measure else stem
    return plan_site(epochs, title=title, elevation_range_m=terrain.elevation_range_m, options=options,
                     measure=measure)  # fmt: skip


def plan_windowed_site(
    names: Sequence[str],
    pairs: Sequence[tuple[Any, PairRasters]],
    *,
    crs: Any,
    valid_cells: Any,
    title: str,
    elevation_range_m: Sequence[float],
    files: MutableMapping[str, bytes],
    options: SiteOptions = SiteOptions(),
) -> SitePlan:
    """The plan of a site of epochs ``names`` whose pairs (:func:`~terralod.site.data.pairs_of`, in its order)
    were measured window by window (``terralod change`` over a region with ``--site``, ``terralod export
    --format site`` of a regional store of epochs; :func:`terralod.change.windowed.measure_change_windowed`):
    ``pairs[K]`` is pair K's result (its arrays the report's decimated copies) and its rasters, the full grid's
    difference and BEFORE's heights read in strips, their tiles put in ``files`` (on disk for a region; a
    pyramid two pairs share kept once). ``valid_cells()`` gives the first epoch's valid cells once pair 0's
    BEFORE rows have been read (the area). The page is the same as for pairs measured in memory: level 0 of
    the pyramids is each cell's own value, the figures are the results'."""
    from terralod.export.geodesy import Geodesy

    planned, metas = [], []
    written: dict[str, dict[str, Any]] = {}
    for (a, b), (result, rasters) in zip(pairs_of(list(names)), pairs, strict=True):
        dates = pair_dates(a, b)
        meta, files = pair_payload(
            result, dates, (a, b), pair_key(a, b), rasters=rasters, files=files, before_key=epoch_key(a)
        )
        metas.append(_share_pyramids(meta, written, files))
        planned.append(PlannedPair(a, b, dates, result))
    t = pairs[0][1].transform
    h, w = pairs[0][1].shape
    geo = Geodesy(crs, geographic=True)
    lo, hi = elevation_range_m
    lods = [p.result.uncertainty.level_of_detection_m for p in planned]
    return SitePlan(
        heights=_heights(geo),
        title=title,
        epochs=tuple(names),
        pairs=tuple(planned),
        bounds_deg=geo.lonlat_bounds((t.c, t.f + h * t.e, t.c + w * t.a, t.f)),
        elevation_range_m=(float(lo), float(hi)),
        area_km2=float(valid_cells()) * abs(t.a * t.e) / 1e6,
        keep_error_m=min(lods) if options.prune else 0.0,
        share_tiles=options.share_tiles,
        pair_meta=tuple(metas),
        files=files,
    )
