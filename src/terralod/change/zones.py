"""Zones of a change budget: GeoJSON polygons as masks on a heightfield's grid (GCD's budget segregation).

Coordinates are in the CRS named by the file's ``crs`` member, else lon/lat as RFC 7946 says. Used by the
budgets (:mod:`terralod.change.volumes`) and by stable-ground masks (:mod:`terralod.change.coregister`).
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from terralod.change.difference import crs_label
from terralod.errors import InputError
from terralod.heightfield import Heightfield


def read_zones(path: str | Path, hf: Heightfield) -> list[tuple[str, np.ndarray, float, dict]]:
    """Polygons of a GeoJSON file as masks on ``hf``'s grid: (name, mask, fraction of the polygon's area on
    the terrain, geometry in the grid CRS). Coordinates are in the CRS named by the file's ``crs`` member,
    else lon/lat (RFC 7946).

    Raises
    ------
    InputError : unreadable file, no polygon, a CRS that cannot be used, a polygon outside the terrain.
    """
    out = []
    for name, geom, frac in zone_geometries(path, hf.crs, hf.bounds_m):
        mask = zone_mask(geom, hf.shape, hf.transform)
        if not (mask & hf.valid).any():
            raise InputError(outside_message(name, geom, hf.crs, hf.bounds_m), str(Path(path)))
        out.append((name, mask, frac, geom))
    return out


def zone_mask(geom: dict, shape: tuple[int, int], transform) -> np.ndarray:  # noqa: ANN001
    """The cells of a grid (``shape``, ``transform``: a whole grid or a window of it) whose centre lies in
    the polygon ``geom`` (GeoJSON mapping in the grid CRS)."""
    from rasterio.features import rasterize

    return rasterize([(geom, 1)], out_shape=shape, transform=transform, fill=0, dtype="uint8").astype(bool)


def outside_message(name: str, geom: dict, crs: str | None, bounds_m) -> str:  # noqa: ANN001
    from shapely.geometry import shape

    b = ", ".join(f"{v:.1f}" for v in shape(geom).bounds)
    return (
        f"polygon {name!r} lies outside the terrain: its bounds ({b}) vs the terrain's "
        f"({', '.join(f'{v:.1f}' for v in bounds_m)}) in {crs_label(crs)}"
    )


def zone_geometries(path: str | Path, crs: str | None, bounds_m) -> list[tuple[str, dict, float]]:  # noqa: ANN001
    """The polygons of a GeoJSON file in the grid CRS ``crs``: (name, geometry mapping, fraction of its
    area inside ``bounds_m``), without rasterizing them (a region's grid is rasterized window by window).

    Raises
    ------
    InputError : unreadable file, no polygon, a CRS that cannot be used, a polygon wholly outside.
    """
    from shapely.geometry import box, mapping, shape
    from shapely.ops import transform as shp_transform

    src = str(Path(path))
    feats, crs_name = read_geojson_polygons(path, "zone")
    if crs_name == "local":
        crs_name = crs  # the terrain's own coordinates
    if crs is None:
        raise InputError("the terrain has no CRS, so GeoJSON coordinates cannot be placed on it", src)
    try:
        from pyproj import CRS, Transformer

        tr = Transformer.from_crs(CRS.from_user_input(crs_name), CRS.from_user_input(crs), always_xy=True)
    except Exception as exc:  # noqa: BLE001 - pyproj raises its own CRSError
        raise InputError(f"crs {crs_name!r} cannot be used ({exc})", src) from None
    terrain_box = box(*bounds_m)
    out = []
    for name, geom in feats:
        try:
            g = shp_transform(lambda x, y, z=None: tr.transform(x, y), shape(geom))
        except Exception as exc:  # noqa: BLE001 - shapely's errors for broken rings
            raise InputError(f"polygon {name!r} is not a valid geometry ({exc})", src) from None
        if g.is_empty or g.area <= 0:
            raise InputError(f"polygon {name!r} has no area", src)
        frac = float(g.intersection(terrain_box).area / g.area)
        if frac <= 0:
            raise InputError(outside_message(name, mapping(g), crs, bounds_m), src)
        out.append((name, mapping(g), frac))
    return out


def read_geojson_polygons(
    path: str | os.PathLike[str], default_name: str = "polygon"
) -> tuple[list[tuple[str, dict]], str]:
    """The Polygon / MultiPolygon geometries of a GeoJSON file (a FeatureCollection, a Feature or a bare
    geometry), each with its name (its feature's ``name`` property, else ``"{default_name} N"``), and the
    file's CRS: the name in its ``crs`` member (``"local"``: the terrain's own coordinates), else EPSG:4326
    (RFC 7946). The one GeoJSON reader of zones, stable-ground masks and epoch edits.

    Raises
    ------
    InputNotFoundError : no such file. InputError : not GeoJSON, or no polygon in it.
    """
    from terralod.errors import InputNotFoundError

    p = Path(path)
    src = str(p)
    try:
        data = json.loads(p.read_text())
    except FileNotFoundError:
        raise InputNotFoundError("file not found", src) from None
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise InputError(f"is not GeoJSON ({exc})", src) from None
    feats = _features(data, src)
    named = [
        (str(props.get("name", f"{default_name} {i + 1}")), geom) for i, (props, geom) in enumerate(feats)
    ]
    return named, _crs_name(data)


def _crs_name(data: dict) -> str:
    c = data.get("crs")
    if isinstance(c, dict):
        name = (c.get("properties") or {}).get("name")
        if name:
            return "local" if str(name).lower() == "local" else str(name)
    if isinstance(c, str) and c:
        return c
    return "EPSG:4326"


def _features(data, src: str) -> list[tuple[dict, dict]]:
    if not isinstance(data, dict):
        raise InputError("is not a GeoJSON object", src)
    kind = data.get("type")
    if kind == "FeatureCollection":
        items = [(f.get("properties") or {}, f.get("geometry")) for f in data.get("features") or []]
    elif kind == "Feature":
        items = [(data.get("properties") or {}, data.get("geometry"))]
    else:
        items = [({}, data)]
    polys = [(p, g) for p, g in items if isinstance(g, dict) and g.get("type") in ("Polygon", "MultiPolygon")]
    if not polys:
        raise InputError("holds no Polygon or MultiPolygon", src)
    return polys


# -- the whole chain -----------------------------------------------------------------------------------
