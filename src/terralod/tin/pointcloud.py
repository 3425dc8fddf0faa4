"""Points for the TIN: LAS/LAZ reading (laspy with lazrs), units to metres, ground class, duplicate thinning.

Paper: ``../shared/papers/003_2a2cfcda929de24c.txt`` §3 ("before generating the TIN model, the point
cloud was processed ... such as points filtering and thinning"). The paper gives no rule; the rules here:

- **Ground only.** A classified cloud (any point of class 2, ASPRS "ground") keeps its class-2 points, the
  bare earth a terrain TIN should show; an unclassified cloud keeps every point. ``ground_only=True``
  demands class 2, ``False`` keeps everything.
- **CRS and units.** The file's CRS is its WKT record or its GeoTIFF keys (read by GDAL from a one-pixel
  GeoTIFF carrying them; when both exist and disagree, :func:`las_crs` says which is taken or refuses).
  x/y become metres by the unit of the CRS's axes (international foot 0.3048, US survey foot 1200/3937,
  ...), and the CRS stored with them is the same CRS with metre axes (:func:`terralod.io.georef.metric_crs`),
  so the coordinates and the CRS always agree. z takes the unit of the CRS's vertical axis when it has one
  (a compound CRS) and the horizontal unit otherwise (the LAS habit: Autzen stores x, y and z in
  international feet). No CRS: metres in a local frame, with a note. A geographic CRS (degrees) is
  refused (reproject first), and so are points far outside the CRS's area of use.
- **Thinning.** Points whose xy fall in the same ``tol_m`` square cell (cells anchored at the cloud's
  south-west corner) are one location; the **lowest** point is kept (for LiDAR the lowest return of a
  location is the one nearest the ground). Two points closer than ``tol_m`` but on either side of a cell
  edge both stay; the triangulator then drops any that still coincide, so the TIN never sees a duplicate.
- **A part of a survey** (``bbox_deg``, the build's ``--bbox``): a point is kept when its longitude and
  latitude fall in the box (ends included). A file whose header bounds miss the box is not opened further; a
  COPC file (LAZ with its octree, https://copc.io) is read through its hierarchy, decoding only the nodes
  whose cubes meet the box (laspy's ``CopcReader.query``); any other file is read in chunks and filtered.
  The ground rule is decided on the points decoded, before the box cuts them.
"""

from __future__ import annotations

import logging
import math
import os
import re
import struct
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from terralod.errors import InputError, InputNotFoundError

__all__ = ["PointCloud", "check_points", "las_inputs", "read_las", "read_las_survey", "thin_duplicates",
           "unit_factor_from_wkt"]  # fmt: skip

log = logging.getLogger(__name__)

#: Points per chunk of a LAS/LAZ read (laspy's chunk iterator): about 60 MB of records and xyz at a time.
LAS_CHUNK_POINTS = 1 << 20

#: EPSG unit codes of the GeoTIFF keys → metres per unit.
_GEOKEY_UNITS = {9001: ("metre", 1.0), 9002: ("foot", 0.3048), 9003: ("US survey foot", 1200.0 / 3937.0)}
#: Names accepted by ``units=``.
_UNIT_NAMES = {
    "m": 1.0,
    "metre": 1.0,
    "meter": 1.0,
    "ft": 0.3048,
    "foot": 0.3048,
    "us-ft": 1200.0 / 3937.0,
    "us_survey_foot": 1200.0 / 3937.0,
}

#: ASPRS ground class.
GROUND = 2


@dataclass(frozen=True)
class PointCloud:
    """Points in metres with where they came from.

    Attributes
    ----------
    xyz_m : (N, 3) float64
        x east, y north, z up, metres (the file's projected frame scaled to metres).
    crs : str or None
        WKT of the file's CRS as read (its unit may be feet: the coordinates here are metres regardless).
    source : str
        The file.
    n_read : int
        Points in the file before filtering.
    classified : bool
        True when the file had ground (class 2) points.
    notes : tuple of str
        Filters and conversions applied, one line each.
    """

    xyz_m: np.ndarray
    crs: str | None
    source: str
    n_read: int
    classified: bool
    notes: tuple[str, ...] = field(default_factory=tuple)


def check_points(xyz: np.ndarray, source: str | None = None) -> np.ndarray:
    """(N, 3) float64 C-contiguous copy of ``xyz``; InputError on a bad shape or non-finite coordinates."""
    a = np.asarray(xyz)
    if a.ndim != 2 or a.shape[1] != 3:
        raise InputError(f"Expected points of shape (N, 3) (x, y, z metres), got {a.shape}", source)
    if not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
        raise InputError(f"Expected numeric points, got dtype {a.dtype}", source)
    a = np.ascontiguousarray(a, dtype=np.float64)
    bad = ~np.isfinite(a).all(axis=1)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise InputError(
            f"Expected finite coordinates, got {int(bad.sum())} point(s) with NaN/inf, first at index {i}: "
            f"{a[i].tolist()}",
            source,
        )
    return a


def thin_duplicates(xyz: np.ndarray, tol_m: float = 0.01) -> np.ndarray:
    """Indices of the points kept when points sharing a ``tol_m`` xy cell are merged (lowest z kept).

    Parameters
    ----------
    xyz : (N, 3) float64
        Points, metres (finite).
    tol_m : float
        Cell side, metres; 0 merges exact xy duplicates only.

    Returns
    -------
    (K,) int64
        Ascending indices into ``xyz`` of the kept points (the lowest point of each cell; the first in
        input order among equal lowest).
    """
    n = xyz.shape[0]
    if n == 0:
        return np.zeros(0, np.int64)
    if tol_m < 0 or not np.isfinite(tol_m):
        raise InputError(f"Expected a duplicate tolerance >= 0 metres, got {tol_m}")
    if tol_m == 0:
        kx, ky = xyz[:, 0], xyz[:, 1]
    else:
        kx = np.floor((xyz[:, 0] - xyz[:, 0].min()) / tol_m)
        ky = np.floor((xyz[:, 1] - xyz[:, 1].min()) / tol_m)
    order = np.lexsort((np.arange(n), xyz[:, 2], ky, kx))  # by cell, then lowest z, then input order
    sx, sy = kx[order], ky[order]
    first = np.ones(n, bool)
    first[1:] = (sx[1:] != sx[:-1]) | (sy[1:] != sy[:-1])
    return np.sort(order[first])


def unit_factor_from_wkt(wkt: str) -> tuple[str, float, float | None]:
    """(unit name, metres per horizontal unit, metres per vertical unit or None) of a CRS's WKT.

    Raises InputError for a geographic CRS (degrees) or a WKT GDAL cannot parse.
    """
    from rasterio.crs import CRS
    from rasterio.errors import CRSError

    head = wkt.split("VERT_CS")[0]
    try:
        crs = CRS.from_wkt(head if head.strip().startswith("PROJCS") else wkt)
    except CRSError as exc:
        raise InputError(f"cannot parse the CRS WKT ({exc})") from exc
    if crs.is_geographic:
        raise InputError("coordinates are geographic (degrees); reproject the cloud to a projected CRS first")
    name, factor = crs.linear_units_factor
    vert = None
    m = re.search(r"VERT_CS\[.*?UNIT\[\s*\"([^\"]+)\"\s*,\s*([0-9.eE+-]+)", wkt, flags=re.S)
    if m:
        vert = float(m.group(2))
    return str(name), float(factor), vert


def _units_from_geokeys(header) -> tuple[str, float, float | None, str | None] | None:
    """(name, horizontal factor, vertical factor or None, crs text) from the GeoTIFF keys, or None."""
    for vlr in header.vlrs:
        if type(vlr).__name__ != "GeoKeyDirectoryVlr":
            continue
        keys = {k.id: k.value_offset for k in vlr.geo_keys if k.tiff_tag_location == 0}
        vert = _GEOKEY_UNITS.get(keys.get(4099, -1), (None, None))[1]
        if keys.get(1024) == 2:  # ModelTypeGeographic
            raise InputError(
                "coordinates are geographic (degrees); reproject the cloud to a projected CRS first"
            )
        if 3076 in keys and keys[3076] in _GEOKEY_UNITS:
            name, f = _GEOKEY_UNITS[keys[3076]]
            return name, f, vert, None
        code = keys.get(3072)
        if code and code != 32767:
            from rasterio.crs import CRS

            crs = CRS.from_epsg(int(code))
            name, f = crs.linear_units_factor
            return str(name), float(f), vert, crs.to_wkt()
    return None


def _probe_laz_decoding(p: Path, timeout_s: float = 600.0) -> bool:
    """Decode a LAZ file once in a forked child first: lazrs aborts the whole process (a Rust allocation
    failure, not an exception) on some corrupt compressed points (found by fuzzing), which must become one
    line instead. POSIX only; elsewhere, and for uncompressed LAS, nothing is done. Returns True for LAZ.
    (A COPC file's part is read in a child of its own: :func:`_copc_part`.)"""
    import signal
    import time

    try:
        with open(p, "rb") as fh:
            head = fh.read(105)
    except OSError:
        return False
    if len(head) < 105 or not (head[104] & 0x80 or p.suffix.lower() == ".laz"):
        return False
    if not hasattr(os, "fork"):
        return True
    pid = os.fork()
    if pid == 0:  # child: decode, say nothing, exit
        code = 3
        try:
            # die by the signal itself: a handler the host process installed (faulthandler, a fuzzer's
            # crash reporter) must not turn the child's abort into an exit code or a report of its own
            for sig in (signal.SIGABRT, signal.SIGSEGV, signal.SIGBUS, signal.SIGILL, signal.SIGFPE):
                signal.signal(sig, signal.SIG_DFL)
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, 2)
            os.dup2(devnull, 1)
            import laspy

            # single-threaded: a parallel decoder's thread pool, if the parent started one, is not in the child
            laspy.read(str(p), laz_backend=laspy.LazBackend.Lazrs)
            code = 0
        except BaseException:  # noqa: BLE001 - the parent reads again and reports the error itself
            code = 3
        finally:
            os._exit(code)
    t_end = time.monotonic() + timeout_s
    while True:
        try:
            done, status = os.waitpid(pid, os.WNOHANG)
            if not done:
                time.sleep(0.005)
        except BaseException:  # interrupted (Ctrl-C, an alarm): the child must not outlive us
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
            raise
        if done:
            break
        if time.monotonic() > t_end:
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
            raise InputError(
                f"decoding the LAZ points took over {timeout_s:g} s; the file is probably corrupt", str(p)
            )
    if os.WIFSIGNALED(status) or os.WEXITSTATUS(status) not in (0, 3):  # 3: an exception, reported below
        raise InputError(
            "the LAZ decoder (lazrs) crashed on the compressed points ("
            + (
                f"signal {os.WTERMSIG(status)}"
                if os.WIFSIGNALED(status)
                else f"exit {os.WEXITSTATUS(status)}"
            )
            + "): the file is corrupt",
            str(p),
        )
    return True


#: Largest ratio of decompressed point bytes to compressed bytes believed of a LAZ file (LASzip reaches
#: ~10x on real clouds; constant synthetic data more): beyond it the header's point count is refused.
MAX_LAZ_EXPANSION = 200


def check_las_header(p: Path) -> None:
    """Refuse, before laspy parses it, a LAS/LAZ public header whose counts cannot fit the file (an absurd
    VLR count makes laspy loop for hours; found by fuzzing)."""
    src = str(p)
    try:
        size = p.stat().st_size
        with open(p, "rb") as fh:
            head = fh.read(375)
    except OSError as exc:
        raise InputError(f"cannot read ({exc.strerror or exc})", src) from None
    if len(head) < 4 or head[:4] != b"LASF":
        raise InputError("cannot read as LAS/LAZ (no LASF signature)", src)
    if len(head) < 227:
        raise InputError(f"cannot read as LAS/LAZ (truncated header: {len(head)} of at least 227 bytes)", src)
    major, minor = head[24], head[25]
    header_size, offset = struct.unpack_from("<HI", head, 94)
    (n_vlr,) = struct.unpack_from("<I", head, 100)
    if major != 1 or minor > 4:
        raise InputError(f"LAS version {major}.{minor} is not one laspy reads (1.0-1.4)", src)
    if not 227 <= header_size <= offset <= size:
        raise InputError(
            f"LAS header size {header_size} / point data offset {offset} do not fit the {size}-byte file", src
        )
    if n_vlr * 54 > offset - header_size:
        raise InputError(
            f"LAS header claims {n_vlr:,} variable-length records, more than fit before the points", src
        )
    if minor >= 4 and len(head) >= 247:
        start, n_evlr = struct.unpack_from("<QI", head, 235)
        if n_evlr and (start > size or n_evlr * 60 > size - start):
            raise InputError(f"LAS header claims {n_evlr:,} extended records beyond the file", src)
    # LAZ: the decoder (lazrs) allocates points x record length up front and aborts the process when that
    # fails, so a claim far beyond what the compressed bytes can hold is refused here
    compressed = bool(head[104] & 0x80) or p.suffix.lower() == ".laz"
    (record_len,) = struct.unpack_from("<H", head, 105)
    (n_points,) = struct.unpack_from("<I", head, 107)
    if minor >= 4 and len(head) >= 255:
        n_points = max(n_points, struct.unpack_from("<Q", head, 247)[0])
    if compressed and n_points * record_len > MAX_LAZ_EXPANSION * max(size - offset, 1):
        raise InputError(
            f"LAZ header claims {n_points:,} points ({n_points * record_len / 2**30:.1f} GiB decompressed), far more "
            f"than its {size - offset:,} compressed bytes can hold",
            src,
        )


def _records_in_file(p: Path, header) -> int | None:
    """Point records an uncompressed LAS file holds by its size (None for LAZ or when unknown)."""
    try:
        if p.suffix.lower() == ".laz" or header.are_points_compressed:
            return None
        size = int(header.point_format.size)
        evlr = int(getattr(header, "start_of_first_evlr", 0) or 0)
        end = evlr if evlr > 0 else p.stat().st_size
        return max(0, (end - int(header.offset_to_point_data)) // size) if size > 0 else None
    except Exception:  # noqa: BLE001 - a size estimate is a courtesy
        return None


def describe_las(path: str | os.PathLike[str], *, crs: Any = None) -> dict[str, Any]:
    """What ``terralod info`` says about a LAS/LAZ cloud, from its header (points are not read):
    version, point format, header point count, records in the file, bounds (file units and lon/lat) and
    CRS (``crs_name``: the file's CRS named; ``crs``: the WKT of the metre frame a build uses).
    Georeferencing :func:`read_las` would refuse is refused here too (InputError)."""
    import laspy

    p = Path(path)
    src = str(p)
    if not p.exists():
        raise InputNotFoundError("file not found", src)
    check_las_header(p)
    try:
        with laspy.open(src) as f:
            h = f.header
            d: dict[str, Any] = {
                "kind": "point cloud",
                "source": src,
                "las_version": f"{h.version.major}.{h.version.minor}",
                "point_format": int(h.point_format.id),
                "points": int(h.point_count),
                "bounds": [float(h.mins[0]), float(h.mins[1]), float(h.maxs[0]), float(h.maxs[1])],
                "z_range": [float(h.mins[2]), float(h.maxs[2])],
                "compressed": bool(h.are_points_compressed),
            }
    except (KeyboardInterrupt, SystemExit):
        raise
    except BaseException as exc:  # laspy raises its own, OSError/ValueError, and lazrs pyo3 PanicException
        raise InputError(f"cannot read as LAS/LAZ ({type(exc).__name__}: {exc})", src) from None
    n_file = _records_in_file(p, h)
    d["records_in_file"] = n_file
    notes = (
        [f"header point count {d['points']} disagrees with the {n_file} records in the file"]
        if n_file is not None and n_file != d["points"]
        else []
    )
    wkt, fh, fv, crs_notes, file_crs = _las_frame(h, src, crs, None)
    d["crs"] = wkt  # the CRS of the metre coordinates a build makes
    from terralod.io.georef import describe_crs

    d["crs_name"] = describe_crs(file_crs)
    d["unit_m"], d["z_unit_m"] = fh, fv
    d["notes"] = notes + [n for n in crs_notes if not n.startswith(("CRS from", "CRS given"))]
    d["bounds_lonlat"] = None
    if wkt is not None:
        from rasterio.warp import transform_bounds

        w, s_, e, n = (v * fh for v in d["bounds"])
        try:
            d["bounds_lonlat"] = [
                float(v) for v in transform_bounds(wkt, "EPSG:4326", w, s_, e, n, densify_pts=21)
            ]
        except Exception:  # noqa: BLE001 - placed by check_area_of_use already; lon/lat is a courtesy
            d["bounds_lonlat"] = None
    return d


def _crs_records(header) -> list[Any]:
    """The VLRs and extended VLRs of a header (a LAS 1.4 file may keep its WKT in an EVLR)."""
    return [*header.vlrs, *(getattr(header, "evlrs", None) or [])]


def _wkt_of(header) -> str | None:
    for vlr in _crs_records(header):
        if type(vlr).__name__ == "WktCoordinateSystemVlr":
            s = vlr.string
            text = s.decode("ascii", "replace") if isinstance(s, bytes) else str(s)
            return text.strip("\x00").strip() or None
    return None


def _geotiff_with_keys(directory: bytes, doubles: bytes, ascii_: bytes) -> bytes:
    """A 1x1 GeoTIFF carrying a LAS file's GeoTIFF key records (GeoKeyDirectoryTag 34735,
    GeoDoubleParamsTag 34736, GeoAsciiParamsTag 34737), so GDAL (libgeotiff) turns the keys into a CRS
    exactly as it does for a raster: user-defined projections and vertical keys included."""
    # (tag, TIFF type, count, value bytes): SHORT 3, LONG 4, DOUBLE 12, ASCII 2
    if len(ascii_) and not ascii_.endswith(b"\x00"):
        ascii_ += b"\x00"
    entries = [
        (256, 3, 1, struct.pack("<H", 1)), (257, 3, 1, struct.pack("<H", 1)), (258, 3, 1, struct.pack("<H", 8)),
        (259, 3, 1, struct.pack("<H", 1)), (262, 3, 1, struct.pack("<H", 1)), (273, 4, 1, b""),
        (277, 3, 1, struct.pack("<H", 1)), (278, 3, 1, struct.pack("<H", 1)), (279, 4, 1, struct.pack("<I", 1)),
        (33550, 12, 3, struct.pack("<3d", 1.0, 1.0, 0.0)), (33922, 12, 6, struct.pack("<6d", 0, 0, 0, 0, 0, 0)),
        (34735, 3, len(directory) // 2, directory),
    ]  # fmt: skip
    if doubles:
        entries.append((34736, 12, len(doubles) // 8, doubles))
    if ascii_:
        entries.append((34737, 2, len(ascii_), ascii_))
    ifd_size = 2 + 12 * len(entries) + 4
    data_at = 8 + ifd_size
    pixel_at = data_at + sum(len(v) + (len(v) & 1) for *_, v in entries if len(v) > 4)
    ifd = [struct.pack("<H", len(entries))]
    blobs = []
    for tag, typ, count, value in entries:
        if tag == 273:
            value = struct.pack("<I", pixel_at)
        if len(value) <= 4:
            ifd.append(struct.pack("<HHI", tag, typ, count) + value.ljust(4, b"\x00"))
        else:
            ifd.append(struct.pack("<HHII", tag, typ, count, data_at))
            pad = value + b"\x00" * (len(value) & 1)
            blobs.append(pad)
            data_at += len(pad)
    ifd.append(struct.pack("<I", 0))
    return b"II*\x00" + struct.pack("<I", 8) + b"".join(ifd) + b"".join(blobs) + b"\x00"


def _geokeys_crs(header) -> str | None:
    """The CRS (WKT) the GeoTIFF keys of a LAS header define, read by GDAL; None without keys or when GDAL
    makes no CRS of them."""
    recs = {type(v).__name__: v for v in _crs_records(header)}
    keys = recs.get("GeoKeyDirectoryVlr")
    if keys is None:
        return None
    try:
        import rasterio
        from rasterio.io import MemoryFile

        def raw(name: str) -> bytes:
            v = recs.get(name)
            return bytes(v.record_data_bytes()) if v is not None else b""

        d = raw("GeoKeyDirectoryVlr")
        shorts = struct.unpack(f"<{len(d) // 2}H", d[: len(d) // 2 * 2])
        n = min(shorts[3], (len(shorts) - 4) // 4)
        entries = [shorts[4 + 4 * k : 8 + 4 * k] for k in range(n) if shorts[4 + 4 * k] != 0]  # id 0: padding
        d = struct.pack(
            f"<{4 + 4 * len(entries)}H", *shorts[:3], len(entries), *(v for e in entries for v in e)
        )
        tif = _geotiff_with_keys(d, raw("GeoDoubleParamsVlr"), raw("GeoAsciiParamsVlr"))
        with rasterio.Env(GTIFF_REPORT_COMPD_CS="YES"), MemoryFile(tif) as mem, mem.open() as ds:
            return None if ds.crs is None else ds.crs.to_wkt(version="WKT2_2019")
    except Exception:  # noqa: BLE001 - keys GDAL cannot read: the simple key reading below decides
        g = _units_from_geokeys(header)
        return g[3] if g is not None else None


def _lonlat_gap_m(a: Any, b: Any, xs: list[float], ys: list[float]) -> float:
    """Largest ground distance (metres, spherical) between the lon/lat of the same x/y read in CRS ``a`` and
    in CRS ``b``; inf when either cannot place them."""
    from rasterio.warp import transform

    try:
        la, pa = transform(a, "EPSG:4326", xs, ys)
        lb, pb = transform(b, "EPSG:4326", xs, ys)
    except Exception:  # noqa: BLE001 - one of them cannot be placed
        return math.inf
    gap = 0.0
    for x1, y1, x2, y2 in zip(la, pa, lb, pb, strict=True):
        d = math.hypot((x1 - x2) * math.cos(math.radians(y1)), y1 - y2) * 111_320.0
        gap = max(gap, d if math.isfinite(d) else math.inf)
    return gap


def las_crs(header, source: str) -> tuple[str | None, tuple[str, ...]]:
    """(the CRS of a LAS/LAZ file as WKT, or None when it has none; notes) from its WKT record and its
    GeoTIFF keys.

    When both are there and place the points more than 1 m apart or give other units, they disagree: a
    LAS 1.4 file flagged WKT takes its WKT (the specification's rule); otherwise the one whose area of use
    holds the points is taken; when both or neither do, the file is refused (ambiguous). A taken one is
    said in a note and a warning."""
    from terralod.io.georef import check_area_of_use, crs_summary, describe_crs, to_crs

    wkt = _wkt_of(header)
    keys = _geokeys_crs(header)
    if wkt is None or keys is None:
        text = wkt or keys
        if text is None:
            return None, ()
        what = "WKT record" if wkt else "GeoTIFF keys"
        to_crs(text, source)  # InputError: not a CRS PROJ can use
        return text, (f"CRS from the {what}: {describe_crs(text)}",)
    cw, ck = to_crs(wkt, source), to_crs(keys, source)
    bounds = (float(header.mins[0]), float(header.mins[1]), float(header.maxs[0]), float(header.maxs[1]))
    xs = [bounds[0], bounds[2], bounds[0], bounds[2], (bounds[0] + bounds[2]) / 2]
    ys = [bounds[1], bounds[1], bounds[3], bounds[3], (bounds[1] + bounds[3]) / 2]
    sw, sk = crs_summary(cw), crs_summary(ck)
    same_units = sw.unit_m == sk.unit_m and (sw.vertical_unit_m or sw.unit_m) == (
        sk.vertical_unit_m or sk.unit_m
    )
    if same_units and _lonlat_gap_m(cw, ck, xs, ys) <= 1.0:
        return wkt, (f"CRS from the WKT record (the GeoTIFF keys agree): {describe_crs(wkt)}",)
    both = f"the WKT record says {describe_crs(cw)!r}, the GeoTIFF keys say {describe_crs(ck)!r}"
    if bool(header.global_encoding.wkt) and int(header.version.minor) >= 4:
        chosen, why = "WKT record", "the header flags WKT (LAS 1.4)"
    else:
        fits = []
        for name, c in (("WKT record", cw), ("GeoTIFF keys", ck)):
            try:
                check_area_of_use(c, bounds, source)
                fits.append(name)
            except InputError:
                pass
        if len(fits) != 1:
            raise InputError(
                f"its CRS records disagree: {both}; the points lie in "
                + ("the area of use of both" if fits else "the area of use of neither")
                + ", so terralod cannot tell which is right: rewrite the file with one CRS "
                "(e.g. pdal translate --writers.las.a_srs=EPSG:<code>), or pass the CRS (read_las(crs=...))",
                source,
            )
        chosen, why = fits[0], "only its area of use holds the points"
    note = f"CRS records disagree: {both}; took the {chosen} ({why})"
    log.warning("%s: %s", source, note)
    return (wkt if chosen == "WKT record" else keys), (note,)


def read_las(
    path: str | os.PathLike[str],
    *,
    ground_only: bool | None = None,
    units: str | float | None = None,
    crs: Any = None,
    bbox_deg: tuple[float, float, float, float] | None = None,
) -> PointCloud:
    """Read a LAS/LAZ cloud as metres, ground points only when it is classified.

    Parameters
    ----------
    path : LAS or LAZ file (LAZ needs the lazrs or laszip backend of laspy).
    ground_only : None (default) keeps class 2 when the cloud has any, else every point; True demands
        class 2 points; False keeps every point.
    units : override the file's unit: "m", "ft" (international foot), "us-ft" (US survey foot), or
        metres per unit as a number (applied to x, y and z).
    crs : the CRS of the file's coordinates (EPSG code, WKT, PROJ string), instead of the file's own.
    bbox_deg : (west, south, east, north) in degrees: only the points inside (see the module docstring);
        the cloud may then hold no point (a tile of a survey outside the box), with a note.

    Returns
    -------
    PointCloud

    Raises
    ------
    InputNotFoundError : no such file.
    InputError : unreadable file, geographic coordinates, no points left after filtering.
    """
    import laspy

    p = Path(path)
    src = str(p)
    if not p.exists():
        raise InputNotFoundError("file not found", src)
    check_las_header(p)
    part = copc_box = None
    if bbox_deg is not None:  # a part: the file's box first (a tile outside it is not decoded at all)
        try:
            with laspy.open(src) as f:
                header = f.header
        except (KeyboardInterrupt, SystemExit):
            raise
        except BaseException as exc:
            raise InputError(f"cannot read as LAS/LAZ ({type(exc).__name__}: {exc})", src) from exc
        part = _native_part(header, src, crs, units, bbox_deg)
        if part is None:
            return _empty_part(header, src, crs, units, "its header bounds miss --bbox")
        copc_box = part.box if _is_copc(header) else None
    compressed = copc_box is not None or _probe_laz_decoding(p)  # a COPC part: read in a child process
    # Points are read in chunks of LAS_CHUNK_POINTS (laspy's chunk iterator): only the kept points' xyz
    # (24 bytes a point) outlive a chunk, never the whole file's records and dimensions.
    backend = {"laz_backend": laspy.LazBackend.Lazrs} if compressed else {}
    kept: list[np.ndarray] = []  # xyz of the points kept so far, file units
    unclassified: list[np.ndarray] = []  # every point's xyz until a ground point shows up (ground_only None)
    n_read = n_ground = 0
    notes: list[str] = []
    try:  # the decoder the probe proved on this file (the parallel one may fail differently)
        with laspy.open(src, **backend) as f:
            header = f.header
            has_cls = "classification" in header.point_format.dimension_names
            for pts in _records(f, src, copc_box, notes):
                n = len(pts)
                if n == 0:
                    break
                n_read += n
                xyz_c = np.empty((n, 3), np.float64)
                xyz_c[:, 0] = np.asarray(pts.x, dtype=np.float64)
                xyz_c[:, 1] = np.asarray(pts.y, dtype=np.float64)
                xyz_c[:, 2] = np.asarray(pts.z, dtype=np.float64)
                ground = (np.asarray(pts.classification) == GROUND) if has_cls else np.zeros(n, np.bool_)
                if part is not None:  # the ground rule on every decoded point; the box's points kept
                    inside = part.contains(xyz_c)
                    n_ground += int(np.count_nonzero(ground & ~inside)) if ground_only is not False else 0
                    xyz_c, ground = xyz_c[inside], ground[inside]
                    n = len(xyz_c)
                g = int(np.count_nonzero(ground))
                if ground_only is False:
                    kept.append(xyz_c)
                    n_ground += g
                    continue
                if g:
                    if n_ground == 0:
                        unclassified.clear()  # the cloud is classified: ground points only from here
                    n_ground += g
                    kept.append(xyz_c[ground])
                elif n_ground == 0 and ground_only is None:
                    unclassified.append(xyz_c)
    except (KeyboardInterrupt, SystemExit):
        raise
    except InputError:
        raise
    except BaseException as exc:  # laspy raises its own, OSError/ValueError, and lazrs pyo3 PanicException
        raise InputError(f"cannot read as LAS/LAZ ({type(exc).__name__}: {exc})", src) from exc
    n_file = _records_in_file(p, header)
    whole = part is None  # a part's records decoded are not the file's (COPC: the nodes meeting the box)
    if whole and (n_read != int(header.point_count) or (n_file is not None and n_file != n_read)):
        held = f"the file holds {n_file}" if n_file is not None else f"{n_read} could be read"
        notes.append(
            f"header point count {int(header.point_count)} disagrees with the records ({held}); read {n_read}"
        )
        log.warning("%s: %s", src, notes[-1])
    if n_read == 0:
        raise InputError("the file has no point records", src)

    # CRS: given, else the file's (WKT record, GeoTIFF keys); units: given, else the CRS's axes.
    wkt, fh, fv, crs_notes, _ = _las_frame(header, src, crs, units)
    notes += crs_notes

    # Ground class.
    classified = n_ground > 0
    if ground_only is True and not classified:
        raise InputError(
            "no ground points (class 2) in the cloud; pass ground_only=False to use all points", src
        )
    parts = kept if classified or ground_only is False else unclassified
    xyz = np.concatenate(parts) if parts else np.zeros((0, 3), np.float64)
    del kept, unclassified, parts
    xyz[:, 0] *= fh
    xyz[:, 1] *= fh
    xyz[:, 2] *= fv
    if classified and ground_only is not False:
        notes.append(f"kept {xyz.shape[0]} ground points (class 2) of {n_read}")
    if part is not None:
        xyz = xyz[part.contains_lonlat(xyz, wkt)] if xyz.shape[0] else xyz
        notes.append(f"{xyz.shape[0]:,} points inside --bbox")
        if xyz.shape[0] == 0:
            return PointCloud(xyz, wkt, src, n_read, classified, tuple(notes))
    if xyz.shape[0] == 0:
        raise InputError("the file has no points", src)
    xyz = check_points(xyz, src)
    return PointCloud(xyz, wkt, src, n_read, classified, tuple(notes))


@dataclass(frozen=True)
class _Part:
    """The file-coordinate box around a --bbox (``box``: x0, y0, x1, y1 in the file's units), and the
    test of metre coordinates against the box in degrees."""

    box: tuple[float, float, float, float]
    bbox_deg: tuple[float, float, float, float]

    def contains(self, xyz_file: np.ndarray) -> np.ndarray:
        x0, y0, x1, y1 = self.box
        x, y = xyz_file[:, 0], xyz_file[:, 1]
        return (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)

    def contains_lonlat(self, xyz_m: np.ndarray, wkt: str | None) -> np.ndarray:
        from pyproj import CRS, Transformer

        t = Transformer.from_crs(CRS.from_user_input(wkt), "EPSG:4326", always_xy=True)
        lon, lat = t.transform(xyz_m[:, 0], xyz_m[:, 1])
        w, s, e, n = self.bbox_deg
        return (lon >= w) & (lon <= e) & (lat >= s) & (lat <= n)


def _native_part(header, src: str, crs: Any, units: str | float | None,
                 bbox_deg: tuple[float, float, float, float]) -> _Part | None:  # fmt: skip
    """The --bbox as a box of the file's own coordinates (the box in degrees transformed with its edges
    densified, enlarged by a part in a million for rounding), or None when the file's header bounds miss
    it. InputError for a cloud without a CRS (a box in degrees places nothing in a local frame)."""
    from pyproj import CRS, Transformer

    wkt, fh, _, _, native = _las_frame(header, src, crs, units)
    if wkt is None:
        raise InputError("--bbox needs the cloud's CRS: the file has none (give --crs)", src)
    own = CRS.from_user_input(native if native is not None else wkt)
    to_own = Transformer.from_crs("EPSG:4326", own, always_xy=True)
    x0, y0, x1, y1 = to_own.transform_bounds(*bbox_deg, densify_pts=64)
    if units is not None and native is not None:  # coordinates in the given units, not the CRS's
        k = _las_frame(header, src, crs, None)[1] / fh
        x0, y0, x1, y1 = (v * k for v in (x0, y0, x1, y1))
    pad = 1e-6 * max(x1 - x0, y1 - y0) + 0.01 / fh  # fh: metres per file unit
    box = (x0 - pad, y0 - pad, x1 + pad, y1 + pad)
    mins, maxs = header.mins, header.maxs
    if box[0] > maxs[0] or box[2] < mins[0] or box[1] > maxs[1] or box[3] < mins[1]:
        return None
    return _Part(box, bbox_deg)


def _empty_part(header, src: str, crs: Any, units: str | float | None, why: str) -> PointCloud:
    """The empty cloud of a survey tile outside --bbox (its CRS checked like any other tile's)."""
    wkt = _las_frame(header, src, crs, units)[0]
    return PointCloud(np.zeros((0, 3)), wkt, src, 0, False, (f"{Path(src).name}: {why}",))


def _is_copc(header) -> bool:
    """A COPC file: a LAZ 1.4 file whose first VLR is the COPC info record (user "copc", record 1)."""
    return any(getattr(v, "user_id", "") == "copc" and getattr(v, "record_id", -1) == 1 for v in header.vlrs)


#: The child process that reads a part of a COPC file (:func:`_copc_part`): laspy and numpy only.
_COPC_CHILD = """
import sys
import numpy as np, laspy
src, out = sys.argv[1], sys.argv[2]
x0, y0, x1, y1 = (float(v) for v in sys.argv[3:7])
with laspy.CopcReader.open(src) as r:
    z0, z1 = float(r.header.mins[2]) - 1.0, float(r.header.maxs[2]) + 1.0
    p = r.query(bounds=laspy.copc.Bounds(mins=np.array([x0, y0, z0]), maxs=np.array([x1, y1, z1])))
    np.savez(out, x=np.asarray(p.x, np.float64), y=np.asarray(p.y, np.float64), z=np.asarray(p.z, np.float64),
             classification=np.asarray(p.classification, np.uint8))
"""


@dataclass(frozen=True)
class _Chunk:
    """Points as a chunk of a LAS read offers them (x, y, z in file units, classification)."""

    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    classification: np.ndarray

    def __len__(self) -> int:
        return len(self.x)


def _copc_part(src: str, box: tuple, timeout_s: float = 600.0) -> _Chunk:
    """The points of the COPC file ``src`` in the octree nodes whose cubes meet ``box`` (x0, y0, x1, y1 of
    the file; every height), by laspy's ``CopcReader.query``, run in a fresh child process. The child is
    the probe of :func:`_probe_laz_decoding` for this read (a corrupt node that aborts the decoder becomes
    one line), and a fresh one because the query decodes on lazrs's thread pool, which a forked child of a
    process that already started one would wait on for ever."""
    import subprocess
    import sys
    import tempfile

    with tempfile.TemporaryDirectory(prefix="terralod-copc-") as d:
        out = Path(d) / "part.npz"
        try:
            r = subprocess.run([sys.executable, "-c", _COPC_CHILD, src, str(out), *(repr(float(v)) for v in box)],
                               capture_output=True, text=True, timeout=timeout_s)  # fmt: skip
        except subprocess.TimeoutExpired:
            raise InputError(f"decoding the COPC nodes took over {timeout_s:g} s; the file is probably corrupt",
                             src) from None  # fmt: skip
        if r.returncode != 0 or not out.exists():
            lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
            why = lines[-1] if lines else f"the decoder ended with {r.returncode}"
            raise InputError(f"cannot read the COPC octree ({why})", src)
        with np.load(out) as f:
            return _Chunk(f["x"], f["y"], f["z"], f["classification"])


def _records(f, src: str, copc_box: tuple | None, notes: list[str]):
    """The point records to read from the open LAS/LAZ ``f``: every chunk, or for a part of a COPC file
    (``copc_box``) the points of the octree nodes meeting it (:func:`_copc_part`)."""
    if copc_box is None:
        yield from f.chunk_iterator(LAS_CHUNK_POINTS)
        return
    pts = _copc_part(src, copc_box)
    notes.append(f"COPC: decoded {len(pts):,} of {int(f.header.point_count):,} points (the octree nodes "
                 "meeting --bbox)")  # fmt: skip
    yield pts


def _las_frame(
    header, src: str, crs: Any, units: str | float | None
) -> tuple[str | None, float, float, tuple[str, ...], str | None]:
    """(the CRS of the metre coordinates as WKT or None, metres per x/y unit, metres per z unit, notes, the
    CRS of the file's own coordinates) of a LAS/LAZ header, with the ``crs`` and ``units`` overrides of
    :func:`read_las`."""
    from terralod.io.georef import check_area_of_use, describe_crs, metric_crs, to_crs
    from terralod.io.raster import crs_text

    notes: list[str] = []
    if crs is not None:
        text: str | None = to_crs(crs, src).to_wkt(version="WKT2_2019")
        notes.append(f"CRS given: {describe_crs(text)} (the file's own is ignored)")
    else:
        text, found = las_crs(header, src)
        notes += found
    user: float | None = None
    if units is not None:
        if isinstance(units, str):
            if units.lower() not in _UNIT_NAMES:
                raise InputError(f"Expected units in {sorted(_UNIT_NAMES)} or a number, got {units!r}", src)
            user = _UNIT_NAMES[units.lower()]
        else:
            user = float(units)
            if not (user > 0 and np.isfinite(user)):
                raise InputError(f"Expected a positive metres-per-unit factor, got {units}", src)
        notes.append(f"units given: {units} ({user} m per unit)")
    if text is None:
        f = 1.0 if user is None else user
        if user is None:
            notes.append(
                "no CRS in the file: coordinates taken as metres in a local frame, not placed on the globe"
            )
            log.info("%s: no CRS; coordinates taken as metres in a local frame", src)
        return None, f, f, tuple(notes), None
    c = to_crs(text, src)
    if c.is_geographic:
        raise InputError(
            "coordinates are geographic (degrees); reproject the cloud to a projected CRS first", src
        )
    x0, y0, x1, y1 = (
        float(header.mins[0]),
        float(header.mins[1]),
        float(header.maxs[0]),
        float(header.maxs[1]),
    )
    metric, fh, fv_crs, unit_notes = metric_crs(c, ((x0 + x1) / 2, (y0 + y1) / 2), src)
    k = 1.0 if user is None else user / fh  # file units -> CRS units
    notes += check_area_of_use(c, (x0 * k, y0 * k, x1 * k, y1 * k), src, what="the points")
    if user is not None:
        return crs_text(metric), user, user, tuple(notes), text
    notes += unit_notes
    fv = fh if fv_crs is None else fv_crs  # no vertical axis: z in the horizontal unit (the LAS habit)
    if fv != 1.0 or fh != 1.0:
        why = (
            "the CRS's vertical axis"
            if fv_crs is not None
            else "the horizontal unit: the CRS names no vertical one"
        )
        notes.append(f"z scaled by {fv:.10g} to metres ({why})")
    return crs_text(metric), fh, fv, tuple(notes), text


#: Suffixes of the point-cloud files a folder or glob of a survey contributes.
LAS_SUFFIXES = (".las", ".laz")


def las_inputs(inputs: Sequence[str | os.PathLike[str]]) -> list[Path]:
    """The LAS/LAZ files of a survey given as files, quoted globs or folders, in name order within each
    folder or glob (a folder: its ``*.las``/``*.laz``; COPC files are LAZ and read as such)."""
    import glob

    out: list[Path] = []
    for item in inputs:
        text = str(item)
        p = Path(text)
        if p.is_dir():
            found = sorted(q for q in p.iterdir() if q.suffix.lower() in LAS_SUFFIXES and q.is_file())
            if not found:
                raise InputError("holds no .las or .laz file", text)
            out += found
        elif any(ch in text for ch in "*?[") and not p.exists():
            found = sorted(Path(q) for q in glob.glob(text) if Path(q).suffix.lower() in LAS_SUFFIXES)
            if not found:
                raise InputNotFoundError("matches no .las or .laz file", text)
            out += found
        else:
            out.append(p)
    seen: set[Path] = set()
    unique = []
    for q in out:  # a file named twice (a folder and one of its files) counts once
        r = q.resolve()
        if r not in seen:
            seen.add(r)
            unique.append(q)
    return unique


def read_las_survey(
    paths: Sequence[str | os.PathLike[str]],
    *,
    ground_only: bool | None = None,
    units: str | float | None = None,
    crs: Any = None,
    bbox_deg: tuple[float, float, float, float] | None = None,
) -> PointCloud:
    """The points of a survey delivered as several LAS/LAZ tiles, as one cloud in metres (``bbox_deg``:
    only those inside a box in degrees, see :func:`read_las`).

    Each file is read by :func:`read_las` (the same classes, units and CRS checks as one file); every file
    must place its points in the same CRS (the metre frame a build uses): a file that disagrees is named in
    one line. When any file is classified, only ground points (class 2) are kept from every file (a tile
    without ground points contributes none, and the notes say which). Points are returned in one canonical
    order (by x, then y, then z), so the cloud — and the TIN built from it — does not depend on how the
    survey was cut into files or listed.
    """
    from terralod.io.georef import to_crs

    files = [Path(p) for p in paths]
    if not files:
        raise InputError("no point-cloud files given")
    clouds = [read_las(f, ground_only=ground_only, units=units, crs=crs, bbox_deg=bbox_deg) for f in files]
    first = clouds[0]
    for f, pc in zip(files[1:], clouds[1:], strict=True):
        same = (pc.crs is None) == (first.crs is None) and (
            pc.crs is None or to_crs(pc.crs, str(f)) == to_crs(first.crs, str(files[0]))
        )
        if not same:
            raise InputError(
                f"its CRS ({_crs_label(pc.crs)}) differs from {files[0].name}'s ({_crs_label(first.crs)}); a "
                "survey's tiles must share one CRS (give --crs to override every file's)",
                str(f),
            )
    classified = any(pc.classified for pc in clouds)
    notes = list(first.notes)
    parts = []
    for f, pc in zip(files, clouds, strict=True):
        if bbox_deg is not None and f is not files[0]:
            notes += [n for n in pc.notes if "--bbox" in n]
        if pc.xyz_m.shape[0] == 0:
            continue
        if classified and not pc.classified and ground_only is not False:
            notes.append(f"{f.name}: no ground (class 2) points while other tiles have some: none taken")
            continue
        parts.append(pc.xyz_m)
    xyz = np.concatenate(parts) if parts else np.zeros((0, 3))
    if xyz.shape[0] == 0:
        w, s, e, n = bbox_deg if bbox_deg is not None else (0.0, 0.0, 0.0, 0.0)
        raise InputError(f"no point inside --bbox {w:g},{s:g},{e:g},{n:g} (west,south,east,north in degrees)",
                         str(files[0]) if len(files) == 1 else f"{len(files)} LAS/LAZ files")  # fmt: skip
    order = np.lexsort((xyz[:, 2], xyz[:, 1], xyz[:, 0]))
    notes.append(f"{len(files)} LAS/LAZ files read as one survey ({xyz.shape[0]:,} points)")
    source = str(files[0]) if len(files) == 1 else f"{len(files)} LAS/LAZ files ({files[0].name}, ...)"
    return PointCloud(np.ascontiguousarray(xyz[order]), first.crs, source,
                      sum(pc.n_read for pc in clouds), classified, tuple(notes))  # fmt: skip


def _crs_label(crs: str | None) -> str:
    if crs is None:
        return "none"
    from terralod.io.georef import describe_crs

    return describe_crs(crs)
