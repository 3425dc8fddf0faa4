"""CRS facts shared by every reader: what a CRS is called, its units, where it is valid, and the same CRS
with its axes re-expressed in metres.

Everything here works on the CRS's WKT2 (GDAL's export through rasterio; pyproj is not needed), read into
a small tree (:func:`parse_wkt`), so the parts that matter are looked up by their WKT2 keywords (ISO 19162):

- **name, EPSG code**: the first string and the ``ID["EPSG", n]`` of the top node (``SOURCECRS`` of a
  ``BOUNDCRS``); a CRS without an ID gets GDAL's identification (``to_epsg``) when it is certain.
- **units**: the ``LENGTHUNIT`` of the coordinate system's axes (``AXIS[...]`` of the ``PROJCRS`` and of the
  ``VERTCRS`` of a ``COMPOUNDCRS``), metres per unit as written.
- **area of use**: ``USAGE[... BBOX[south, west, north, east]]`` (degrees), the union of all of them.
- **metre re-expression** (:func:`metric_crs`): only the axes' ``LENGTHUNIT`` nodes change (to
  ``"metre", 1``); projection parameters keep their own units (WKT2 gives each one), so false eastings in
  feet stay right; the EPSG IDs of the changed nodes go (the code named the foot CRS) and a ``REMARK`` says
  what was done. The result is checked by transforming a point through both CRSs.

Coordinates outside a CRS's area of use (:func:`check_area_of_use`) are refused when they lie well outside
it: half the area's own width (height) beyond it, and at least :data:`AREA_MARGIN_DEG` degrees. The usual
cause is a unit mix-up (feet read as metres); the message says which factor would put them inside.
"""

from __future__ import annotations

import math
import re
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TypeVar

from terralod.errors import InputError

__all__ = [
    "assign_crs",
    "AREA_MARGIN_DEG",
    "area_of_use",
    "CrsSummary",
    "check_area_of_use",
    "check_on_globe",
    "crs_summary",
    "describe_crs",
    "metric_crs",
    "parse_wkt",
    "to_crs",
]

#: Least margin (degrees) beyond a CRS's area of use within which coordinates are still accepted.
AREA_MARGIN_DEG = 2.0
#: Metres per unit of the usual mix-ups, for the hint of an out-of-area refusal.
_UNIT_MIXUPS = (
    ("international feet", 0.3048),
    ("US survey feet", 1200.0 / 3937.0),
)
_REMARK_PREFIX = "terralod: "
_PROJECTED = ("PROJCRS", "PROJECTEDCRS")
_VERTICAL = ("VERTCRS", "VERTICALCRS")
_GEOGRAPHIC = ("GEOGCRS", "GEOGRAPHICCRS", "GEODCRS", "GEODETICCRS")


# -- the WKT tree ----------------------------------------------------------------------------------------
@dataclass
class WktNode:
    """``KEYWORD[item, ...]``: items are nodes, quoted strings (kept as ``'"text"'``) or bare tokens."""

    keyword: str
    items: list[Any]

    def children(self, *keywords: str) -> list[WktNode]:
        return [i for i in self.items if isinstance(i, WktNode) and i.keyword.upper() in keywords]

    def child(self, *keywords: str) -> WktNode | None:
        found = self.children(*keywords)
        return found[0] if found else None

    def text(self, k: int = 0) -> str | None:
        """The ``k``-th quoted string among the items, unquoted."""
        strings = [i for i in self.items if isinstance(i, str) and i.startswith('"')]
        return strings[k][1:-1].replace('""', '"') if len(strings) > k else None

    def number(self, k: int = 0) -> float | None:
        nums = []
        for i in self.items:
            if isinstance(i, str) and not i.startswith('"'):
                try:
                    nums.append(float(i))
                except ValueError:
                    continue
        return nums[k] if len(nums) > k else None

    def walk(self):
        yield self
        for i in self.items:
            if isinstance(i, WktNode):
                yield from i.walk()

    def __str__(self) -> str:
        return f"{self.keyword}[{','.join(str(i) for i in self.items)}]"


_TOKEN = re.compile(r'\s*(?:("(?:[^"]|"")*")|([\[\](),])|([^\s\[\](),"]+))')


def parse_wkt(wkt: str) -> WktNode:
    """The tree of a WKT (1 or 2) string; ValueError when it is not one."""
    pos, stack, root = 0, [], None
    pending: str | None = None  # a bare token that may be the keyword of a node
    n = len(wkt)
    while pos < n:
        m = _TOKEN.match(wkt, pos)
        if m is None:
            if wkt[pos:].strip() == "":
                break
            raise ValueError(f"unexpected text at {pos}: {wkt[pos : pos + 20]!r}")
        pos = m.end()
        quoted, punct, bare = m.groups()
        if punct in ("[", "("):
            if pending is None:
                raise ValueError(f"bracket without a keyword at {pos}")
            node = WktNode(pending, [])
            pending = None
            if stack:
                stack[-1].items.append(node)
            stack.append(node)
        elif punct in ("]", ")"):
            if not stack:
                raise ValueError(f"unbalanced bracket at {pos}")
            if pending is not None:
                stack[-1].items.append(pending)
                pending = None
            root = stack.pop()
        elif punct == ",":
            if pending is not None and stack:
                stack[-1].items.append(pending)
            pending = None
        elif quoted is not None:
            if not stack:
                raise ValueError("a string outside any node")
            stack[-1].items.append(quoted)
        elif bare is not None:
            pending = bare
        if root is not None and not stack:
            if wkt[pos:].strip():
                raise ValueError("text after the WKT")
            return root
    raise ValueError("unterminated WKT")


# -- reading a CRS ---------------------------------------------------------------------------------------
def to_crs(crs: Any, source: str | None = None) -> Any:
    """``rasterio.crs.CRS`` of anything it reads (EPSG code, WKT, PROJ string); InputError naming the
    input otherwise."""
    from rasterio.crs import CRS

    if isinstance(crs, CRS):
        return crs
    try:
        return CRS.from_user_input(crs)
    except Exception as exc:  # noqa: BLE001 - CRSError, and SystemError on text PROJ's decoder chokes on
        first = (str(exc).strip().splitlines() or [type(exc).__name__])[0][:160]
        raise InputError(f"its CRS {_short(crs)!r} is not one PROJ can use ({first})", source) from None


def assign_crs(given: Any, own: Any, source: str | None = None) -> tuple[Any, str]:
    """(CRS, note) for a CRS given from outside the file (``--crs``): it assigns one to a file without a
    CRS, or overrides the file's own; the note says which, naming both."""
    crs = to_crs(given, source)
    if own is None or not str(own):
        return crs, f"CRS given with --crs: {describe_crs(crs)} (the file has none)"
    if to_crs(own, source) == crs:
        return crs, f"CRS given with --crs: {describe_crs(crs)} (the file says the same)"
    return crs, f"CRS given with --crs: {describe_crs(crs)}, overriding the file's {describe_crs(own)}"


def _wkt2_tree(crs: Any) -> WktNode | None:
    try:
        return parse_wkt(crs.to_wkt(version="WKT2_2019"))
    except Exception:  # noqa: BLE001 - a CRS GDAL cannot write as WKT2 has no tree; callers fall back
        return None


def _main_node(tree: WktNode) -> WktNode:
    """The CRS a ``BOUNDCRS`` wraps (its ``SOURCECRS``), else the tree itself."""
    if tree.keyword.upper() == "BOUNDCRS":
        src = tree.child("SOURCECRS")
        inner = src.children(*_PROJECTED, *_VERTICAL, *_GEOGRAPHIC, "COMPOUNDCRS") if src else []
        if inner:
            return inner[0]
    return tree


def _axis_unit(node: WktNode) -> tuple[str, float] | None:
    """(name, metres per unit) of the length unit of ``node``'s axes (or of its CS-wide unit)."""
    for ax in node.children("AXIS"):
        u = ax.child("LENGTHUNIT", "UNIT")
        if u is not None and u.number() is not None:
            return u.text() or "?", float(u.number())  # type: ignore[arg-type]
    u = node.child("LENGTHUNIT", "UNIT")
    if u is not None and u.number() is not None:
        return u.text() or "?", float(u.number())  # type: ignore[arg-type]
    return None


def _epsg(node: WktNode) -> int | None:
    for i in node.children("ID", "AUTHORITY"):
        if (i.text() or "").upper() == "EPSG":
            code = i.number()
            if code is None and i.text(1):
                code = float(i.text(1))  # type: ignore[arg-type]
            return int(code) if code is not None else None
    return None


@dataclass(frozen=True)
class CrsSummary:
    """What a CRS is, in the words ``terralod info`` prints.

    Attributes
    ----------
    kind : "projected", "geographic", "compound", "vertical", "engineering" or "other"
    name, epsg : the horizontal CRS's name and EPSG code (None when it has none)
    unit, unit_m : the horizontal axes' unit and metres per unit ("degree" and None for geographic)
    vertical_name, vertical_epsg, vertical_unit, vertical_unit_m : the vertical CRS of a compound CRS
    remark : what terralod did to it (the metre re-expression), or None
    area_deg : (west, south, east, north) area of use in degrees, or None
    """

    kind: str
    name: str
    epsg: int | None = None
    unit: str | None = None
    unit_m: float | None = None
    vertical_name: str | None = None
    vertical_epsg: int | None = None
    vertical_unit: str | None = None
    vertical_unit_m: float | None = None
    remark: str | None = None
    area_deg: tuple[float, float, float, float] | None = None


_T = TypeVar("_T")
#: Results of :func:`crs_summary` and :func:`area_of_use` by the CRS's WKT2, which decides them (GDAL's
#: identification in them costs about 0.1 s of CPU a call, and every reader asks for the same few CRSs)
_BY_WKT2: dict[tuple[str, str], Any] = {}
_BY_WKT2_LOCK = threading.Lock()
_BY_WKT2_SIZE = 256


def _by_wkt2(kind: str, c: Any, compute: Callable[[Any], _T]) -> _T:
    """``compute(c)``, remembered by (``kind``, ``c``'s WKT2); a CRS GDAL cannot write as WKT2 is not."""
    try:
        key = (kind, c.to_wkt(version="WKT2_2019"))
    except Exception:  # noqa: BLE001 - no WKT2: computed each time (and it has no tree either)
        return compute(c)
    with _BY_WKT2_LOCK:
        if key in _BY_WKT2:
            return _BY_WKT2[key]
    out = compute(c)
    with _BY_WKT2_LOCK:
        if len(_BY_WKT2) >= _BY_WKT2_SIZE:
            _BY_WKT2.pop(next(iter(_BY_WKT2)))
        _BY_WKT2[key] = out
    return out


def crs_summary(crs: Any) -> CrsSummary:
    """The :class:`CrsSummary` of a CRS (anything :func:`to_crs` reads); InputError when unreadable."""
    return _by_wkt2("summary", to_crs(crs), _crs_summary)


def _crs_summary(c: Any) -> CrsSummary:
    tree = _wkt2_tree(c)
    if tree is None:
        return CrsSummary("other", _short(c.to_string()), c.to_epsg())
    main = _main_node(tree)
    kw = main.keyword.upper()
    horiz, vert = main, None
    if kw == "COMPOUNDCRS":
        parts = [i for i in main.items if isinstance(i, WktNode) and i.keyword.upper().endswith("CRS")]
        horiz = next((p for p in parts if p.keyword.upper() not in _VERTICAL), parts[0] if parts else main)
        vert = next((p for p in parts if p.keyword.upper() in _VERTICAL), None)
    elif kw in _VERTICAL:
        horiz, vert = main, main
    hk = horiz.keyword.upper()
    kind = (
        "compound" if kw == "COMPOUNDCRS" else "projected" if hk in _PROJECTED else "geographic"
        if hk in _GEOGRAPHIC else "vertical" if hk in _VERTICAL else "engineering"
        if hk in ("ENGCRS", "ENGINEERINGCRS") else "other"
    )  # fmt: skip
    epsg = _epsg(horiz)
    if epsg is None and kw != "COMPOUNDCRS" and main.child("REMARK") is None:
        try:
            epsg = c.to_epsg(confidence_threshold=90)
        except Exception:  # noqa: BLE001 - identification is a courtesy
            epsg = None
    unit = _axis_unit(horiz)
    if hk in _GEOGRAPHIC:
        unit_name, unit_m = "degree", None
    else:
        unit_name, unit_m = unit if unit else (None, None)
    vu = _axis_unit(vert) if vert is not None else None
    remark = main.child("REMARK") or tree.child("REMARK")
    name = horiz.text() or "unnamed"
    if name.lower() in ("unknown", "unnamed", ""):  # GDAL's name for a CRS built from parameters
        conv = horiz.child("CONVERSION")
        datum = next((n for n in horiz.walk() if n.keyword.upper() in ("DATUM", "ENSEMBLE")), None)
        dname = datum.text() if datum is not None else None
        parts = [
            conv.text() or "" if conv is not None else "",
            f"datum {dname}" if dname and dname != "unknown" else "",
        ]
        name = "unnamed CRS" + (f" ({', '.join(p for p in parts if p)})" if any(parts) else "")
    return CrsSummary(
        kind=kind,
        name=name,
        epsg=epsg,
        unit=unit_name,
        unit_m=unit_m,
        vertical_name=vert.text() if vert is not None and vert is not horiz else None,
        vertical_epsg=_epsg(vert) if vert is not None and vert is not horiz else None,
        vertical_unit=vu[0] if vu else None,
        vertical_unit_m=vu[1] if vu else None,
        remark=(remark.text() or "").removeprefix(_REMARK_PREFIX) or None if remark is not None else None,
        area_deg=area_of_use(c),
    )


def describe_crs(crs: Any) -> str:
    """One line naming a CRS: horizontal name, EPSG code and unit, then the vertical CRS when there is one,
    then what terralod did to it, e.g. ``NAD83(HARN) / Oregon GIC Lambert (ft) (EPSG:2994), unit foot;
    vertical NAVD88 height (EPSG:5703), unit metre``. Never the WKT."""
    if not crs:
        return "none (local metric frame, not placed on the globe)"
    try:
        s = crs_summary(crs)
    except InputError:
        return f"unreadable ({_short(crs)!r})"
    out = s.name + (f" (EPSG:{s.epsg})" if s.epsg else "")
    if s.unit:
        out += f", unit {s.unit}"
    if s.vertical_name:
        out += f"; vertical {s.vertical_name}" + (f" (EPSG:{s.vertical_epsg})" if s.vertical_epsg else "")
        if s.vertical_unit:
            out += f", unit {s.vertical_unit}"
    if s.remark:
        out += f" ({s.remark})"
    return out


def _short(crs: Any, limit: int = 60) -> str:
    text = " ".join(str(crs).split())
    return text if len(text) <= limit else text[: limit - 3] + "..."


# -- area of use -----------------------------------------------------------------------------------------
def _area(tree: WktNode) -> tuple[float, float, float, float] | None:
    """Union (west, south, east, north, degrees) of the ``BBOX`` of the CRS's own usages; for a compound
    CRS without usages of its own, those of its horizontal part."""
    main = _main_node(tree)
    holders = [main]
    if main.keyword.upper() == "COMPOUNDCRS":
        holders += [i for i in main.items if isinstance(i, WktNode) and i.keyword.upper() not in _VERTICAL]
    for holder in holders:
        boxes = []
        for usage in [holder, *holder.children("USAGE")]:
            for node in usage.children("BBOX"):
                vals = [node.number(k) for k in range(4)]
                if all(v is not None for v in vals):
                    s, w, n, e = (float(v) for v in vals)  # type: ignore[arg-type]
                    boxes.append((w, s, e, n))
        if boxes:
            w, s, e, n = boxes[0]
            for bw, bs, be, bn in boxes[1:]:
                w, s, e, n = min(w, bw), min(s, bs), max(e, be), max(n, bn)
            return w, s, e, n
    return None


def area_of_use(crs: Any) -> tuple[float, float, float, float] | None:
    """(west, south, east, north) degrees where a CRS is meant to be used: its WKT's ``USAGE``, else the
    EPSG definition's when GDAL identifies the CRS (a CRS read from GeoTIFF keys carries no usage)."""
    return _by_wkt2("area", to_crs(crs), _area_of_use)


def _area_of_use(c: Any) -> tuple[float, float, float, float] | None:
    tree = _wkt2_tree(c)
    area = _area(tree) if tree is not None else None
    if area is not None or tree is None or _main_node(tree).child("REMARK") is not None:
        return area
    try:
        code = _epsg(_main_node(tree)) or c.to_epsg(confidence_threshold=90)
    except Exception:  # noqa: BLE001 - no identification: no area
        code = None
    if not code:
        return None
    from rasterio.crs import CRS

    try:
        full = _wkt2_tree(CRS.from_epsg(code))
    except Exception:  # noqa: BLE001 - a code GDAL's database lacks
        return None
    return _area(full) if full is not None else None


def _lonlat(crs: Any, xs: list[float], ys: list[float]) -> tuple[list[float], list[float]] | None:
    from rasterio.warp import transform

    try:
        lon, lat = transform(crs, "EPSG:4326", xs, ys)
    except Exception:  # noqa: BLE001 - no operation to WGS 84: the caller says so
        return None
    if not all(math.isfinite(v) for v in (*lon, *lat)) or max(abs(v) for v in lat) > 90.0:
        return None
    return list(lon), list(lat)


def _grid(bounds: tuple[float, float, float, float], n: int = 5) -> tuple[list[float], list[float]]:
    w, s, e, nn = bounds
    xs = [w + (e - w) * i / (n - 1) for i in range(n) for _ in range(n)]
    ys = [s + (nn - s) * j / (n - 1) for _ in range(n) for j in range(n)]
    return xs, ys


def check_on_globe(crs: Any, bounds: tuple[float, float, float, float], source: str | None) -> None:
    """Refuse (one line) a CRS with no transformation to WGS 84 for ``bounds`` (x/y in the CRS's units):
    an engineering/local CRS, or coordinates the projection cannot invert."""
    c = to_crs(crs, source)
    if c.is_geographic:
        return
    if _lonlat(c, *_grid(bounds)) is None:
        w, s, e, n = bounds
        raise InputError(
            f"its CRS {describe_crs(c)!r} cannot place x {w:,.6g} .. {e:,.6g}, y {s:,.6g} .. {n:,.6g} on the "
            "globe (PROJ finds no transformation to WGS 84 lon/lat); assign a CRS PROJ knows "
            "(gdal_edit.py -a_srs EPSG:<code>), or remove it to use a local metric frame",
            source,
        )


def check_area_of_use(
    crs: Any, bounds: tuple[float, float, float, float], source: str | None, *, what: str = "coordinates"
) -> tuple[str, ...]:
    """Refuse (one line) ``bounds`` (x/y in the CRS's own units) that lie well outside the CRS's area of
    use (see the module docstring); returns a note when they lie a little outside it, else ``()``.

    The refusal says which unit mix-up (feet read as metres, or metres read as feet) would put the
    coordinates inside the area, when one would. A CRS without an area of use is not checked."""
    c = to_crs(crs, source)
    if c.is_geographic:
        return ()
    ll = _lonlat(c, *_grid(bounds))
    if ll is None:
        check_on_globe(c, bounds, source)
        return ()
    area = area_of_use(c)
    if area is None:
        return ()
    aw, as_, ae, an = area
    if ae < aw:  # across the antimeridian
        ae += 360.0
    mx = max(AREA_MARGIN_DEG, 0.5 * (ae - aw))
    my = max(AREA_MARGIN_DEG, 0.5 * (an - as_))

    def inside(lon: list[float], lat: list[float], mx: float, my: float) -> bool:
        lon_c = [v + 360.0 if v < aw - mx else v for v in lon]
        return (
            min(lon_c) <= ae + mx and max(lon_c) >= aw - mx and min(lat) <= an + my and max(lat) >= as_ - my
        )

    lon, lat = ll
    w, s, e, n = bounds
    name = describe_crs(c)
    where = (
        f"lon {min(lon):.4f} .. {max(lon):.4f}, lat {min(lat):.4f} .. {max(lat):.4f}"
        f" (area of use: lon {aw:.2f} .. {area[2]:.2f}, lat {as_:.2f} .. {an:.2f})"
    )
    if inside(lon, lat, mx, my):
        if inside(lon, lat, 0.0, 0.0):
            return ()
        return (f"{what} lie partly outside the area of use of {name}: {where}",)
    hint = ""
    unit_m = crs_summary(c).unit_m or 1.0
    tries = (
        [(f, f"{label} read as metres") for label, f in _UNIT_MIXUPS]
        if unit_m == 1.0
        else [(1.0 / unit_m, f"metres read as {crs_summary(c).unit}")]
    )
    for k, says in tries:
        scaled = _lonlat(c, *_grid((w * k, s * k, e * k, n * k)))
        if scaled is not None and inside(*scaled, mx, my):
            hint = f"; they look like {says}"
            break
    raise InputError(
        f"{what} x {w:,.2f} .. {e:,.2f}, y {s:,.2f} .. {n:,.2f} fall far outside the area of use of {name}: "
        f"{where}{hint}; terralod refuses to guess: give the file its right CRS and units",
        source,
    )


# -- metres ----------------------------------------------------------------------------------------------
def metric_crs(
    crs: Any, point: tuple[float, float], source: str | None
) -> tuple[Any, float, float | None, tuple[str, ...]]:
    """The same CRS with its axes in metres (see the module docstring).

    Parameters
    ----------
    crs : a projected (or compound projected + vertical) CRS, anything :func:`to_crs` reads.
    point : an (x, y) in ``crs`` units where the re-expression is checked (the data's centre).
    source : file named in errors.

    Returns
    -------
    (CRS in metres, metres per horizontal unit, metres per vertical unit or None when the CRS has no
    vertical axis, notes). The CRS is returned unchanged (factor 1) when its axes are metres already.
    """
    from rasterio.crs import CRS
    from rasterio.warp import transform

    c = to_crs(crs, source)
    tree = _wkt2_tree(c)
    if tree is None:
        raise InputError(
            f"its CRS {_short(c.to_string())!r} cannot be read as WKT2; reproject it first", source
        )
    main = _main_node(tree)
    found: dict[str, tuple[str, float]] = {}
    changed: list[WktNode] = []
    for node in main.walk():
        kw = node.keyword.upper()
        if kw not in (*_PROJECTED, *_VERTICAL, "ENGCRS", "ENGINEERINGCRS"):
            continue
        role = "v" if kw in _VERTICAL else "h"
        unit = _axis_unit(node)
        if unit is None:
            continue
        found[role] = unit
        if unit[1] == 1.0:
            continue
        for holder in [node, *node.children("AXIS")]:
            for k, item in enumerate(holder.items):
                if isinstance(item, WktNode) and item.keyword.upper() in ("LENGTHUNIT", "UNIT"):
                    holder.items[k] = WktNode("LENGTHUNIT", ['"metre"', "1"])
        changed.append(node)
    if "h" not in found:
        raise InputError(
            f"its CRS {describe_crs(c)!r} is neither geographic nor projected with a known linear unit; "
            "reproject it to a metric CRS first (gdalwarp -t_srs EPSG:<UTM zone>)",
            source,
        )
    fh = found["h"][1]
    fv = found["v"][1] if "v" in found else None
    if not changed:
        return c, 1.0, fv, ()
    summ = crs_summary(c)
    before = summ.name + (f" (EPSG:{summ.epsg})" if summ.epsg else "")
    for node in {id(n): n for n in (*changed, main)}.values():
        node.items = [i for i in node.items if not (isinstance(i, WktNode) and i.keyword.upper() == "ID")]
    was = found["h"][0] + (f"; heights {found['v'][0]}" if "v" in found and found["v"][1] != 1.0 else "")
    remark = f"{_REMARK_PREFIX}axes re-expressed in metres, were {was}" + (
        f" in EPSG:{summ.epsg}" if summ.epsg else ""
    )
    main.items = [i for i in main.items if not (isinstance(i, WktNode) and i.keyword.upper() == "REMARK")]
    main.items.append(WktNode("REMARK", ['"' + remark.replace('"', '""') + '"']))
    try:
        metric = CRS.from_wkt(str(tree))
        (mx,), (my,) = transform(c, metric, [point[0]], [point[1]])
    except Exception:  # noqa: BLE001 - checked below
        mx = my = math.nan
    if not (abs(mx - point[0] * fh) < 1e-3 and abs(my - point[1] * fh) < 1e-3):
        raise InputError(
            f"its CRS {before!r} is in {found['h'][0]} and could not be re-expressed in metres; reproject it to "
            "a metric CRS first (gdalwarp -t_srs ...)",
            source,
        )
    note = f"x/y converted from {found['h'][0]} to metres (x {fh:.10g})"
    if fv is not None and fv != 1.0:
        note += f", heights from {found['v'][0]} (x {fv:.10g})"
    note += f"; the CRS ({before}) re-expressed with metre axes"
    return metric, fh, fv, (note,)
