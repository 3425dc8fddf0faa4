"""Two DEMs on one grid: the overlap check, the later surface resampled onto the earlier grid when their
CRS, spacing or origin differ, and the DEM of difference (DoD = after − before, metres).

The grid of BEFORE is the frame of every change figure. AFTER is kept as it was read (its own grid, in
BEFORE's CRS) so that co-registration can sample it at shifted positions once, instead of resampling an
already resampled grid:

- same CRS (or both in the same local frame): AFTER stays on its own grid; it is sampled at BEFORE's cell
  centres (bilinear, ``scipy.ndimage.map_coordinates``) only when spacing or origin differ;
- different CRS: AFTER is reprojected once onto BEFORE's grid with :func:`rasterio.warp.reproject`
  (bilinear, nodata kept as NaN), and that grid stands in for AFTER from then on.

Geographic and web-mercator inputs arrive here already in a UTM zone (the reader reprojects them once,
see :mod:`terralod.io.raster`); two DEMs read into different UTM zones take the reprojection path.
Every step is recorded in :attr:`AlignedPair.notes`, which the summary and the report print.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from terralod.errors import InputError
from terralod.heightfield import Heightfield

#: A cell of the resampled mask counts as valid when at least this much of its bilinear weight is valid.
VALID_WEIGHT = 0.999

_UNIT_NAMES = {
    "m": "m", "metre": "m", "meter": "m", "metres": "m", "meters": "m",
    "ft": "ft", "foot": "ft", "feet": "ft", "international foot": "ft", "foot (international)": "ft",
    "us-ft": "us-ft", "us survey foot": "us-ft", "foot_us": "us-ft", "us_survey_foot": "us-ft",
    "ftus": "us-ft", "us foot": "us-ft",
    "cm": "cm", "centimetre": "cm", "centimeter": "cm", "mm": "mm", "millimetre": "mm", "millimeter": "mm",
}  # fmt: skip


@dataclass
class AlignedPair:
    """BEFORE and AFTER in BEFORE's CRS, ready for co-registration and differencing.

    Attributes
    ----------
    before : the earlier DEM; its grid is the frame of the DoD.
    after : the later DEM in BEFORE's CRS: as read (same CRS), or reprojected onto BEFORE's grid.
    same_grid : True when AFTER's grid is BEFORE's (no resampling at all without a shift).
    notes : what was done to bring them together, one line each.
    """

    before: Heightfield
    after: Heightfield
    same_grid: bool
    notes: list[str] = field(default_factory=list)

    @property
    def cell_area_m2(self) -> float:
        dx, dy = self.before.spacing_m
        return dx * dy

    def after_on_before(self, shift_m: tuple[float, float, float] = (0.0, 0.0, 0.0), order: int = 3):
        """AFTER translated by ``shift_m`` = (dx, dy, dz) metres and sampled at BEFORE's cell centres.

        Returns (elevation (H, W) float64 with NaN where AFTER has no valid sample, valid (H, W) bool).
        The translated surface is ``after(x - dx, y - dy) + dz``.
        """
        tx, ty, tz = (float(v) for v in shift_m)
        if self.same_grid and tx == 0.0 and ty == 0.0:
            z = self.after.elevation_m.astype(np.float64)
            ok = self.after.valid.copy()
        else:
            rows, cols = np.indices(self.before.shape, dtype=np.float64)
            x, y = self.before.world_xy(rows, cols)
            r, c = self.after.sample_rc(x - tx, y - ty)
            z, ok = sample_surface(self.after, r, c, order=order)
        z = np.where(ok, z + tz, np.nan)
        return z, ok


def sample_surface(hf: Heightfield, rows: np.ndarray, cols: np.ndarray, order: int = 1):
    """Elevation of ``hf`` at fractional sample indices (bilinear for ``order=1``, cubic spline for 3) and
    whether every sample under the interpolation stencil is valid. Outside the grid → invalid."""
    from scipy import ndimage

    coords = np.stack([np.asarray(rows, np.float64), np.asarray(cols, np.float64)])
    z = ndimage.map_coordinates(hf.elevation_m.astype(np.float64), coords, order=order, mode="nearest")
    return z, _valid_at(hf, coords)


def valid_at(hf: Heightfield, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """The validity :func:`sample_surface` gives at fractional sample indices, without the elevations."""
    return _valid_at(hf, np.stack([np.asarray(rows, np.float64), np.asarray(cols, np.float64)]))


def _valid_at(hf: Heightfield, coords: np.ndarray) -> np.ndarray:
    from scipy import ndimage

    w = ndimage.map_coordinates(hf.valid.astype(np.float32), coords, order=1, mode="constant", cval=0.0)
    h, wd = hf.shape
    inside = (coords[0] >= -0.5) & (coords[0] <= h - 0.5) & (coords[1] >= -0.5) & (coords[1] <= wd - 0.5)
    return (w >= VALID_WEIGHT) & inside


def same_crs(a: str | None, b: str | None) -> bool:
    """True when two CRS descriptions name the same CRS (or both are the same local frame, None)."""
    if a is None or b is None:
        return a is None and b is None
    if a == b:
        return True
    from rasterio.crs import CRS

    return CRS.from_user_input(a) == CRS.from_user_input(b)


def align(before: Heightfield, after: Heightfield) -> AlignedPair:
    """Check that BEFORE and AFTER overlap and bring AFTER into BEFORE's CRS (see the module docstring).

    Raises
    ------
    InputError : (naming AFTER) the two do not overlap, or one has a CRS and the other none.
    """
    notes: list[str] = [f"BEFORE note: {n}" for n in before.notes] + [f"AFTER note: {n}" for n in after.notes]
    if (before.crs is None) != (after.crs is None):
        which = "AFTER has no CRS but BEFORE has one" if after.crs is None else "AFTER has a CRS, BEFORE none"
        raise InputError(f"cannot be compared with {before.source}: {which}", after.source)
    if same_crs(before.crs, after.crs):
        _check_overlap(before.bounds_m, after.bounds_m, before, after)
        same = after.shape == before.shape and np.allclose(
            tuple(after.transform)[:6], tuple(before.transform)[:6], rtol=0, atol=1e-6
        )
        if not same:
            notes.append(
                f"AFTER resampled onto BEFORE's grid (bilinear): spacing {_pair(after.spacing_m)} -> "
                f"{_pair(before.spacing_m)} m, origin {_pair(after.origin_m)} -> {_pair(before.origin_m)}"
            )
        pair = AlignedPair(before, after, same, notes)
    else:
        from rasterio.warp import transform_bounds

        b_after = transform_bounds(after.crs, before.crs, *after.bounds_m, densify_pts=21)
        _check_overlap(before.bounds_m, b_after, before, after)
        pair = AlignedPair(before, reproject_onto(after, before), True, notes)
        pair.notes.append(
            f"AFTER reprojected from {crs_label(after.crs)} onto BEFORE's grid in {crs_label(before.crs)} "
            f"(bilinear, {_pair(before.spacing_m)} m)"
        )
    z, ok = pair.after_on_before()
    if not np.any(ok & before.valid):
        raise InputError(f"has no valid sample where {before.source} has one (no overlap)", after.source)
    return pair


def reproject_onto(src: Heightfield, dst: Heightfield) -> Heightfield:
    """``src`` reprojected onto ``dst``'s grid and CRS (bilinear; cells without a valid source → invalid)."""
    from rasterio.warp import Resampling, reproject

    z = np.where(src.valid, src.elevation_m, np.nan).astype(np.float32)
    out = np.full(dst.shape, np.nan, np.float32)
    reproject(
        z, out, src_transform=src.transform, src_crs=src.crs, src_nodata=np.nan,
        dst_transform=dst.transform, dst_crs=dst.crs, dst_nodata=np.nan, resampling=Resampling.bilinear,
    )  # fmt: skip
    ok = np.isfinite(out)
    fill = np.where(ok, out, np.nanmedian(out) if ok.any() else 0.0)
    return Heightfield(
        fill.astype(np.float32), ok, dst.transform, crs=dst.crs, source=src.source,
        notes=(*src.notes, f"reprojected onto the grid of {dst.source}"),
    )  # fmt: skip


def dem_of_difference(pair: AlignedPair, shift_m=(0.0, 0.0, 0.0)) -> np.ndarray:
    """DoD = (AFTER translated by ``shift_m``) − BEFORE on BEFORE's grid, metres; NaN where either lacks a
    valid sample."""
    z, ok = pair.after_on_before(shift_m)
    d = z - pair.before.elevation_m.astype(np.float64)
    d[~(ok & pair.before.valid)] = np.nan
    return d


def _check_overlap(a, b, before: Heightfield, after: Heightfield) -> None:
    w, s, e, n = max(a[0], b[0]), max(a[1], b[1]), min(a[2], b[2]), min(a[3], b[3])
    if not (e > w and n > s):
        raise InputError(
            f"does not overlap {before.source}: bounds {_bounds(b)} vs {_bounds(a)} (W,S,E,N in "
            f"{crs_label(before.crs)})",
            after.source,
        )


# -- vertical units ------------------------------------------------------------------------------------
def vertical_unit(path: str | Path) -> str | None:
    """The vertical unit a DEM file declares, normalised ("m", "ft", "us-ft", ...), or None when it says
    nothing. Looked up in the band's unit tag, then the vertical part of a compound CRS, then the sidecar
    ``<stem>.json`` (``vertical.units`` or ``vertical_units``)."""
    p = Path(path)
    found: str | None = None
    if p.suffix.lower() not in (".png", ".webp", ".npy", ".npz") and p.is_file():
        try:
            import rasterio

            with rasterio.open(p) as ds:
                unit = (ds.units or (None,))[0]
                if unit:
                    found = unit
                elif ds.crs is not None:
                    found = _compound_vertical_unit(ds.crs.to_wkt())
        except Exception:  # noqa: BLE001 - the reader reports unreadable files itself
            found = None
    if found is None:
        side = p.with_suffix(".json")
        if side.is_file() and side != p:
            try:
                d = json.loads(side.read_text())
            except (OSError, ValueError):
                d = {}
            v = d.get("vertical")
            found = (v.get("units") if isinstance(v, dict) else None) or d.get("vertical_units")
    return normalise_unit(found) if found else None


def normalise_unit(name: str) -> str:
    key = re.sub(r"\s+", " ", str(name).strip().lower())
    return _UNIT_NAMES.get(key, key)


def _compound_vertical_unit(wkt: str) -> str | None:
    from pyproj import CRS

    crs = CRS.from_wkt(wkt)
    for sub in crs.sub_crs_list if crs.is_compound else []:
        if sub.is_vertical and sub.axis_info:
            return sub.axis_info[0].unit_name
    return None


def check_vertical_units(before_path, after_path) -> list[str]:
    """Refuse two DEMs whose files declare different vertical units; returns a note on what was found."""
    ub, ua = vertical_unit(before_path), vertical_unit(after_path)
    if ub and ua and ub != ua:
        raise InputError(
            f"vertical unit is {ua!r} but {before_path} is in {ub!r}; convert one first (e.g. "
            "--vertical-scale 0.3048 when reading feet)",
            str(after_path),
        )
    if ub or ua:
        return [f"vertical units: BEFORE {ub or 'not stated'}, AFTER {ua or 'not stated'}"]
    return ["vertical units: not stated in either file (metres assumed)"]


# -- labels --------------------------------------------------------------------------------------------
def crs_label(crs: str | None) -> str:
    if not crs:
        return "a local metric frame"
    try:
        from rasterio.crs import CRS

        c = CRS.from_user_input(crs)
        epsg = c.to_epsg()
        return f"EPSG:{epsg}" if epsg else c.to_string()[:60]
    except Exception:  # noqa: BLE001 - a label is cosmetic
        return str(crs)[:60]


def _pair(p) -> str:
    return f"({p[0]:.6g}, {p[1]:.6g})"


def _bounds(b) -> str:
    return "(" + ", ".join(f"{v:.1f}" for v in b) + ")"


#: dod.tif's internal tiles (samples a side) and compression: a Cloud Optimized GeoTIFF with overviews.
DOD_BLOCK = 512
#: Band description of ``dod.tif`` and of ``sigma.tif`` (σ of each cell, :mod:`terralod.change.uncertainty`).
DOD_DESCRIPTION = "elevation change after - before (m)"
SIGMA_DESCRIPTION = "1-sigma uncertainty of the elevation change (m)"


def write_dod(
    path: str | Path, dod: np.ndarray, hf: Heightfield, tags: dict | None = None,
    description: str = DOD_DESCRIPTION,
) -> None:  # fmt: skip
    """The DoD (or σ, with its ``description``) as a float32 Cloud Optimized GeoTIFF on ``hf``'s grid
    (:class:`DodWriter`)."""
    w = DodWriter(path, hf, tags, description)
    try:
        w.write(dod, 0, 0)
    except BaseException:
        w.abort()
        raise
    w.close()


class DodWriter:
    """``dod.tif`` written window by window: a float32 GeoTIFF on ``grid``'s frame (anything with ``width``,
    ``height``, ``transform``, ``crs``), NaN = no data, unit metres. Windows go to a tiled scratch file beside
    ``path``; :meth:`close` copies it into a Cloud Optimized GeoTIFF (GDAL's COG driver: 512² tiles,
    deflate with the floating-point predictor, overviews averaged down to one tile) and removes the scratch.
    The bytes depend only on the values, never on the order the windows came in."""

    def __init__(
        self, path: str | Path, grid, tags: dict | None = None, description: str = DOD_DESCRIPTION
    ) -> None:  # noqa: ANN001
        import rasterio

        self.path = Path(path)
        self.scratch = self.path.with_name(f".{self.path.name}.scratch.tif")
        h, w = grid.shape
        profile = {
            "driver": "GTiff", "width": w, "height": h, "count": 1, "dtype": "float32",
            "transform": grid.transform, "nodata": float("nan"), "compress": "deflate", "predictor": 3,
            "tiled": True, "blockxsize": DOD_BLOCK, "blockysize": DOD_BLOCK, "BIGTIFF": "IF_SAFER",
        }  # fmt: skip
        if grid.crs:
            profile["crs"] = grid.crs
        self.ds = rasterio.open(self.scratch, "w", **profile)
        self.ds.set_band_description(1, description)
        self.ds.set_band_unit(1, "metre")
        if tags:
            self.ds.update_tags(**{k: str(v) for k, v in tags.items()})

    def write(self, dod: np.ndarray, r0: int, c0: int) -> None:
        """Write a window of the DoD (metres) whose first cell is (r0, c0) of the grid."""
        from rasterio.windows import Window

        h, w = dod.shape
        self.ds.write(dod.astype(np.float32), 1, window=Window(c0, r0, w, h))

    def close(self) -> None:
        from rasterio.shutil import copy

        self.ds.close()
        copy(self.scratch, self.path, driver="COG", COMPRESS="DEFLATE", PREDICTOR="FLOATING_POINT",
             BLOCKSIZE=str(DOD_BLOCK), OVERVIEWS="IGNORE_EXISTING", RESAMPLING="AVERAGE", BIGTIFF="IF_SAFER")  # fmt: skip
        self.scratch.unlink()

    def abort(self) -> None:
        self.ds.close()
        self.scratch.unlink(missing_ok=True)
