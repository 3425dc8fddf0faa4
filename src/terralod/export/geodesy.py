"""Geodesy at the export boundary: the store's CRS → WGS 84 longitude/latitude and ECEF, through pyproj.

Heights: both web formats take heights above the WGS 84 ellipsoid. When the store's CRS names its vertical
datum (a compound CRS, e.g. after ``--vertical-datum egm96``), :meth:`Geodesy.ellipsoidal` adds the geoid
undulation through PROJ (:mod:`terralod.export.vertical`); otherwise heights are written as read, and the
outputs say so. The horizontal coordinates go through pyproj (datum shifts included where the CRS has them);
ECEF is pyproj's EPSG:4979 → EPSG:4978 conversion (exact, double precision).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from terralod.errors import InputError

__all__ = ["Geodesy", "ecef_lonlat", "enu_frame", "wgs84_radius_m"]

#: WGS 84 semi-major axis, metres.
WGS84_A_M = 6378137.0


def wgs84_radius_m() -> float:
    return WGS84_A_M


_ECEF: list[Any] = []


def ecef_lonlat(lon: Any, lat: Any, h: Any) -> np.ndarray:
    """(N,) degrees, degrees, ellipsoidal metres → (N, 3) ECEF metres (pyproj EPSG:4979 → EPSG:4978)."""
    if not _ECEF:
        from pyproj import Transformer

        _ECEF.append(Transformer.from_crs("EPSG:4979", "EPSG:4978", always_xy=True))
    x, y, z = _ECEF[0].transform(np.asarray(lon, np.float64), np.asarray(lat, np.float64),
                                 np.asarray(h, np.float64))  # fmt: skip
    return np.stack([np.asarray(x), np.asarray(y), np.asarray(z)], axis=-1).astype(np.float64)


class Geodesy:
    """Transforms of one store's CRS (WKT or any pyproj input). Raises InputError on an unknown CRS, and on
    a geographic one unless ``geographic`` (the web exports need metres; a page's lon/lat lattice does not)."""

    def __init__(
        self, crs: str | None, where: str | None = None, *, geographic: bool = False,
        vertical_datum: str | None = None,
    ) -> None:  # fmt: skip
        from pyproj import CRS, Transformer
        from pyproj.exceptions import CRSError

        from terralod.export.vertical import resolve_vertical_datum

        if not crs:
            raise InputError(
                "has no CRS (a local metric frame); the web exports need a georeferenced store", where
            )
        try:
            self.crs = CRS.from_user_input(crs)
        except CRSError as exc:
            raise InputError(f"unknown CRS ({str(exc)[:80]})", where) from exc
        self.vertical = resolve_vertical_datum(vertical_datum, crs, where)
        self._where = where
        self._geoid: list[Any] = []
        #: why heights above a known datum could not be made ellipsoidal (PROJ lacks its grid), or None
        self.vertical_problem: str | None = None
        if self.crs.is_compound:
            self.crs = self.crs.sub_crs_list[0]  # the horizontal part places x, y; the vertical is above
        elif len(self.crs.axis_info) == 3:
            self.crs = self.crs.to_2d()
        if self.crs.is_geographic and not geographic:
            raise InputError("has a geographic CRS; expected a projected (metric) CRS", where)
        try:
            self._to_ll = Transformer.from_crs(self.crs, "EPSG:4326", always_xy=True)
            self._from_ll = Transformer.from_crs("EPSG:4326", self.crs, always_xy=True)
        except Exception as exc:  # noqa: BLE001 - pyproj raises several kinds
            raise InputError(f"CRS cannot be transformed to WGS 84 ({str(exc)[:80]})", where) from exc

    def lonlat(self, x: Any, y: Any) -> tuple[np.ndarray, np.ndarray]:
        """CRS metres → (longitude, latitude) degrees."""
        lon, lat = self._to_ll.transform(np.asarray(x, np.float64), np.asarray(y, np.float64))
        return np.asarray(lon, np.float64), np.asarray(lat, np.float64)

    def xy(self, lon: Any, lat: Any) -> tuple[np.ndarray, np.ndarray]:
        """(longitude, latitude) degrees → CRS metres."""
        x, y = self._from_ll.transform(np.asarray(lon, np.float64), np.asarray(lat, np.float64))
        return np.asarray(x, np.float64), np.asarray(y, np.float64)

    def ecef_lonlat(self, lon: Any, lat: Any, h: Any) -> np.ndarray:
        """(N,) degrees, degrees, ellipsoidal metres → (N, 3) ECEF metres."""
        return ecef_lonlat(lon, lat, h)

    @property
    def geoid(self) -> Any:
        """The conversion of the stored heights to ellipsoidal ones (:class:`~terralod.export.vertical.
        GeoidConverter`), None when none is needed or the datum is unknown; made on first use (PROJ's
        operation lookup), an InputError when PROJ lacks the datum's grid."""
        if not self._geoid:
            try:
                self._geoid.append(self.vertical.converter(self._where))
            except InputError as exc:  # the datum is known but PROJ lacks its grid: said, never guessed
                import logging

                self.vertical_problem = exc.message
                logging.getLogger("terralod.export").warning("%s: heights written as read", exc)
                self._geoid.append(None)
        return self._geoid[0]

    def ellipsoidal(self, lon: Any, lat: Any, h: Any) -> np.ndarray:
        """Heights as stored (above the store's vertical datum) → heights above the WGS 84 ellipsoid; as
        stored when the datum is the ellipsoid or unknown."""
        if self.geoid is None:
            return np.asarray(h, np.float64)
        return self.geoid.to_ellipsoidal(lon, lat, h)

    def undulation_spread_m(self, box_m: tuple[float, ...], n: int = 9) -> float:
        """max − min of the geoid undulation over a CRS box (w, s, zmin, e, n, zmax), sampled on an n × n
        lattice: shifting each vertex by its own undulation moves a surface between vertices by at most
        this against samples shifted by theirs, so a declared error grows by it (0 without a geoid)."""
        if self.geoid is None:
            return 0.0
        w, s, _, e, nn, _ = box_m
        gx, gy = np.meshgrid(np.linspace(w, e, n), np.linspace(s, nn, n))
        lon, lat = self.lonlat(gx.ravel(), gy.ravel())
        und = self.geoid.undulation_m(lon, lat)
        return float(np.nanmax(und) - np.nanmin(und)) if np.isfinite(und).any() else 0.0

    def vertical_record(self) -> dict[str, Any]:
        """What an output says of its heights: the datum, and the operation that made them ellipsoidal."""
        if self.geoid is not None:
            return self.geoid.to_json()
        if self.vertical_problem:
            return {**self.vertical.to_json(), "converted_to": f"none: {self.vertical_problem}; heights written "
                    "as read, used as ellipsoidal"}  # fmt: skip
        if self.vertical.is_ellipsoidal:
            return {**self.vertical.to_json(), "converted_to": "none needed (ellipsoidal heights)"}
        return {
            **self.vertical.to_json(),
            "converted_to": "none: heights written as read, used as ellipsoidal",
        }

    def ecef(self, vertices_m: np.ndarray) -> np.ndarray:
        """(N, 3) CRS metres with heights as stored → (N, 3) ECEF metres (heights made ellipsoidal)."""
        v = np.asarray(vertices_m, np.float64)
        lon, lat = self.lonlat(v[:, 0], v[:, 1])
        return self.ecef_lonlat(lon, lat, self.ellipsoidal(lon, lat, v[:, 2]))

    def lonlat_bounds(
        self, box_m: tuple[float, float, float, float], n: int = 65
    ) -> tuple[float, float, float, float]:
        """(west, south, east, north) degrees around a CRS box (w, s, e, n), its edges sampled at ``n``
        points each (a projected box is curved in longitude/latitude)."""
        w, s, e, nn = box_m
        t = np.linspace(0.0, 1.0, n)
        xs = np.concatenate([w + (e - w) * t, np.full(n, e), w + (e - w) * t, np.full(n, w)])
        ys = np.concatenate([np.full(n, s), s + (nn - s) * t, np.full(n, nn), s + (nn - s) * t])
        lon, lat = self.lonlat(xs, ys)
        return float(lon.min()), float(lat.min()), float(lon.max()), float(lat.max())

    def region(self, box_m: tuple[float, ...], drop_m: float = 0.0, n: int = 9) -> list[float]:
        """3D Tiles ``region`` (west, south, east, north radians, min, max height) around a CRS box
        (w, s, zmin, e, n, zmax), its edges sampled at ``n`` points each (a projected box is curved)."""
        w, s, zmin, e, nn, zmax = box_m
        t = np.linspace(0.0, 1.0, n)
        xs = np.concatenate([w + (e - w) * t, np.full(n, e), w + (e - w) * t, np.full(n, w)])
        ys = np.concatenate([np.full(n, s), s + (nn - s) * t, np.full(n, nn), s + (nn - s) * t])
        lon, lat = self.lonlat(xs, ys)
        r = np.radians
        lo, hi = float(zmin - drop_m), float(zmax)
        if self.geoid is not None:  # the box's heights made ellipsoidal, over its whole area
            gx, gy = np.meshgrid(np.linspace(w, e, n), np.linspace(s, nn, n))
            und = self.geoid.undulation_m(*self.lonlat(gx.ravel(), gy.ravel()))
            lo, hi = lo + float(np.nanmin(und)), hi + float(np.nanmax(und))
        return [float(r(lon.min())), float(r(lat.min())), float(r(lon.max())), float(r(lat.max())), lo, hi]


def enu_frame(lon_deg: np.ndarray, lat_deg: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(east, north, up) unit vectors (N, 3) in ECEF at geodetic (lon, lat)."""
    lo, la = np.radians(lon_deg), np.radians(lat_deg)
    so, co, sa, ca = np.sin(lo), np.cos(lo), np.sin(la), np.cos(la)
    east = np.stack([-so, co, np.zeros_like(lo)], axis=-1)
    north = np.stack([-sa * co, -sa * so, ca], axis=-1)
    up = np.stack([ca * co, ca * so, sa], axis=-1)
    return east, north, up


def tile_rectangle(z: int, x: int, y: int) -> tuple[float, float, float, float]:
    """(west, south, east, north) degrees of geographic-scheme tile z/x/y (TMS: y = 0 at the south pole)."""
    d = 180.0 / (1 << z)
    return (-180.0 + x * d, -90.0 + y * d, -180.0 + (x + 1) * d, -90.0 + (y + 1) * d)
