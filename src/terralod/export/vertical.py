"""Vertical datums: what a DEM's heights are measured from, and their conversion to heights above the WGS 84
ellipsoid, which CesiumJS, 3D Tiles and every other layer of a globe use.

SRTM, Copernicus and most national DEMs give heights above a geoid (EGM96, EGM2008, NAVD88 …); the
difference to the ellipsoid (the geoid undulation N, ``h_ellipsoid = H_geoid + N``) reaches −106 … +85 m
over the Earth, about +50 m off Liguria. A datum is known when the file says it (a compound CRS with a
vertical part) or when the user says it (``--vertical-datum``); otherwise heights are written as read and
every output says so.

The conversion is PROJ's own (pyproj): a vertical grid shift through a geoid grid. PROJ looks the grid up
in its data folders; Debian's ``proj-data`` ships ``egm96_15.gtx`` (EGM96 on a 15' grid), which
``scripts/install.sh`` installs and :func:`_proj_data_dirs` adds. Asked for a conversion whose grid it
cannot find, PROJ silently falls back to a "ballpark" operation that returns the height unchanged: that
case is refused here in one line, never taken.
"""

from __future__ import annotations

import os
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from terralod.errors import InputError

__all__ = ["VerticalDatum", "resolve_vertical_datum", "vertical_datum_from_crs", "VERTICAL_DATUM_CHOICES"]

#: Names ``--vertical-datum`` takes (besides the path of a geoid grid file) and the vertical CRS of each.
_NAMED = {
    "egm96": ("EGM96 geoid", "EPSG:5773"),
    "egm2008": ("EGM2008 geoid", "EPSG:3855"),
    "navd88": ("NAVD88", "EPSG:5703"),
    "ellipsoid": ("the WGS 84 ellipsoid", None),
}
VERTICAL_DATUM_CHOICES = ("egm96", "egm2008", "navd88", "ellipsoid", "a geoid grid file (.gtx, .tif)")

#: Folders where system packages keep PROJ's grids (Debian's proj-data), searched after pyproj's own.
_SYSTEM_PROJ_DIRS = ("/usr/share/proj", "/usr/local/share/proj")


def _proj_data_dirs() -> None:
    """Let pyproj find the system's geoid grids (its wheel carries none), once per process."""
    import pyproj.datadir

    have = pyproj.datadir.get_data_dir().split(os.pathsep)
    for d in _SYSTEM_PROJ_DIRS:
        if Path(d).is_dir() and d not in have:
            pyproj.datadir.append_data_dir(d)
            have.append(d)


@dataclass(frozen=True)
class VerticalDatum:
    """What a DEM's heights are measured from, and how to make them ellipsoidal.

    ``key``: ``"egm96"``, ``"egm2008"``, ``"navd88"``, ``"ellipsoid"``, ``"grid:<path>"``, ``"EPSG:<code>"``
    (a vertical CRS a file named) or ``"unknown"``; ``name``: words for a page; ``said_by``: ``"file"``,
    ``"option"`` or ``"nobody"``.
    """

    key: str
    name: str
    said_by: str
    #: the vertical CRS itself (WKT) when a file named one: PROJ's operation is looked up from it
    crs_wkt: str | None = None

    @property
    def known(self) -> bool:
        return self.key != "unknown"

    @property
    def is_ellipsoidal(self) -> bool:
        return self.key == "ellipsoid"

    @property
    def above_sea_level(self) -> bool:
        """True when the heights are above a geoid (what a visitor calls "above sea level")."""
        return self.known and not self.is_ellipsoidal

    def to_json(self) -> dict[str, Any]:
        return {"datum": self.key, "name": self.name, "said_by": self.said_by}

    def converter(self, where: str | None = None) -> GeoidConverter | None:
        """The conversion to ellipsoidal heights, or None when none is needed or none is possible
        (ellipsoidal heights already, or an unknown datum: heights are written as read)."""
        if not self.known or self.is_ellipsoidal:
            return None
        return GeoidConverter(self, where)


UNKNOWN = VerticalDatum("unknown", "unknown (heights as read)", "nobody")


def resolve_vertical_datum(
    option: str | None, crs: str | None = None, where: str | None = None
) -> VerticalDatum:
    """The datum of a DEM: ``option`` (``--vertical-datum``) wins over what the CRS says; neither → unknown.

    Raises :class:`~terralod.errors.InputError` for a name that is neither a known datum nor an existing
    grid file.
    """
    if option:
        text = option.strip()
        low = text.lower()
        if low in _NAMED:
            return VerticalDatum(low, _NAMED[low][0], "option")
        if low.startswith("epsg:"):
            return VerticalDatum(text.upper(), _vertical_crs_name(text, where), "option")
        p = Path(text).expanduser()
        if p.is_file():
            return VerticalDatum(f"grid:{p.resolve()}", f"geoid grid {p.name}", "option")
        raise InputError(
            f"--vertical-datum: expected one of {', '.join(VERTICAL_DATUM_CHOICES)}, got {option!r}", where
        )
    found = vertical_datum_from_crs(crs)
    return found if found is not None else UNKNOWN


def vertical_datum_from_crs(crs: str | None) -> VerticalDatum | None:
    """The vertical datum a CRS names (a compound CRS's vertical part, or a 3D geographic CRS: the
    ellipsoid), or None when it names none."""
    if not crs:
        return None
    try:
        from pyproj import CRS

        c = CRS.from_user_input(crs)
    except Exception:  # noqa: BLE001 - a CRS pyproj cannot read names no datum
        return None
    if c.is_compound:
        for sub in c.sub_crs_list:
            if sub.is_vertical:
                epsg = sub.to_epsg()
                for key, (name, code) in _NAMED.items():
                    if code is not None and epsg is not None and code == f"EPSG:{epsg}":
                        return VerticalDatum(key, name, "file", sub.to_wkt())
                return VerticalDatum(f"EPSG:{epsg}" if epsg else sub.name, sub.name, "file", sub.to_wkt())
    if len(c.axis_info) == 3 and any("ellipsoidal height" in a.name.lower() for a in c.axis_info):
        ell = c.ellipsoid.name if c.ellipsoid is not None else ""
        named = ell and ell.lower() != "unknown"
        return VerticalDatum("ellipsoid", f"the {ell} ellipsoid" if named else "the CRS's ellipsoid", "file")
    return None


def _vertical_crs_name(text: str, where: str | None) -> str:
    try:
        from pyproj import CRS

        c = CRS.from_user_input(text)
    except Exception as exc:  # noqa: BLE001
        raise InputError(
            f"--vertical-datum: {text} is not a CRS pyproj knows ({str(exc)[:80]})", where
        ) from exc
    if not c.is_vertical:
        raise InputError(f"--vertical-datum: {text} ({c.name}) is not a vertical CRS", where)
    return c.name


class GeoidConverter:
    """Geoid heights → heights above the WGS 84 ellipsoid at (longitude, latitude) degrees, through PROJ.

    ``operation`` and ``accuracy_m`` say which operation PROJ used and its stated accuracy (None when
    PROJ states none); :meth:`undulation_m` is N, so ``h = H + N``.
    """

    def __init__(self, datum: VerticalDatum, where: str | None = None) -> None:
        from pyproj import Transformer
        from pyproj.transformer import TransformerGroup

        _proj_data_dirs()
        self.datum = datum
        if datum.key.startswith("grid:"):
            grid = datum.key[len("grid:") :]
            pipeline = (
                "+proj=pipeline +step +proj=unitconvert +xy_in=deg +xy_out=rad "
                f"+step +proj=vgridshift +grids={grid} +multiplier=1 "
                "+step +proj=unitconvert +xy_in=rad +xy_out=deg"
            )
            try:
                self._t = Transformer.from_pipeline(pipeline)
            except Exception as exc:  # noqa: BLE001
                raise InputError(
                    f"geoid grid {grid} cannot be used by PROJ ({str(exc)[:80]})", where
                ) from exc
            self.operation = f"vertical grid shift through {Path(grid).name}"
            self.accuracy_m: float | None = None
        else:
            from pyproj import CRS
            from pyproj.crs import CompoundCRS

            code = _NAMED[datum.key][1] if datum.key in _NAMED else datum.key
            vertical = CRS.from_wkt(datum.crs_wkt) if datum.crs_wkt else CRS.from_user_input(code)
            source = CompoundCRS(f"WGS 84 + {vertical.name}", [CRS.from_epsg(4326), vertical])
            with warnings.catch_warnings():  # "best transformation is not available": said below, in one line
                warnings.simplefilter("ignore", UserWarning)
                group = TransformerGroup(source, "EPSG:4979", always_xy=True)
            usable = [t for t in group.transformers if "ballpark" not in t.description.lower()]
            if not usable:
                missing = sorted({g.short_name for op in group.unavailable_operations for g in op.grids
                                  if not g.available and "geoid" in g.short_name.lower()})  # fmt: skip
                named = ", ".join(missing[:3]) + (f" or {len(missing) - 3} more" if len(missing) > 3 else "")
                raise InputError(
                    f"heights above {datum.name} cannot be made ellipsoidal here: PROJ has no geoid grid for it "
                    f"({named or 'none listed'}); give the grid file with --vertical-datum PATH "
                    "(EGM96: Debian's proj-data)",
                    where,
                )
            self._t = usable[0]
            self.operation = usable[0].description
            acc = usable[0].accuracy
            self.accuracy_m = None if acc is None or acc < 0 else float(acc)
        global_model = datum.key in ("egm96", "egm2008")  # a regional grid has no value off its region
        probe = self.undulation_m(np.array([10.0]), np.array([45.0])) if global_model else np.zeros(1)
        if not np.isfinite(probe).all():
            raise InputError(
                f"the {datum.name} conversion gives no value (is the grid file complete?)", where
            )

    def undulation_m(self, lon_deg: Any, lat_deg: Any) -> np.ndarray:
        """N (metres) at each (longitude, latitude) degrees; NaN outside the grid."""
        lon = np.asarray(lon_deg, np.float64)
        lat = np.asarray(lat_deg, np.float64)
        out = self._t.transform(lon, lat, np.zeros_like(lon))
        h = np.asarray(out[2], np.float64)
        return np.where(np.isinf(h), np.nan, h)

    def to_ellipsoidal(self, lon_deg: Any, lat_deg: Any, height_m: Any) -> np.ndarray:
        """Heights above the geoid → heights above the WGS 84 ellipsoid (metres)."""
        return np.asarray(height_m, np.float64) + self.undulation_m(lon_deg, lat_deg)

    def to_json(self) -> dict[str, Any]:
        """What an output records: from which datum, by which operation, with which stated accuracy."""
        return {**self.datum.to_json(), "converted_to": "WGS 84 ellipsoid (EPSG:4979)",
                "operation": self.operation, "operation_accuracy_m": self.accuracy_m}  # fmt: skip
