"""Image heightmaps and arrays: 8/16-bit greyscale PNG, RGB-encoded elevation tiles (Mapbox Terrain-RGB,
Terrarium; PNG or WebP) and ``.npy`` / ``.npz`` grids.

These formats carry no georeferencing of their own: the spacing, tile address, CRS and transform come from
the caller (arguments or the sidecar, resolved by :mod:`terralod.io.reader`) as
:class:`~terralod.io.raster.FrameHints` and are applied by :func:`terralod.io.raster.place_heightfield`.

Decoding (metres):

- greyscale: ``h = value * vertical_scale + vertical_offset``; ``nodata`` is compared with the *stored*
  value, before scaling. An RGB image whose three channels are equal is read as greyscale.
- Terrain-RGB (Mapbox): ``h = -10000 + (R * 65536 + G * 256 + B) * 0.1`` (0.1 m steps).
- Terrarium (Mapzen/AWS, Mapterhorn): ``h = R * 256 + G + B / 256 - 32768`` (1/256 m steps).
  For encoded tiles ``nodata`` is compared with the decoded metres; alpha is ignored.
"""

from __future__ import annotations

import math
import warnings
import zipfile
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from terralod.errors import InputError
from terralod.fill import check_dimensions
from terralod.heightfield import Heightfield
from terralod.io.encodings import (  # noqa: F401 - re-exported: the codecs' historical home
    ENCODINGS,
    decode_rgb,
    decode_terrain_rgb,
    decode_terrarium,
    encode_terrain_rgb,
    encode_terrarium,
)
from terralod.io.raster import FrameHints, apply_vertical, error_line, place_heightfield

#: Pillow modes read as a single greyscale channel without conversion.
_GREY_MODES = ("L", "I", "F", "I;16", "I;16L", "I;16B", "I;16N")
#: Pillow modes converted to 8-bit greyscale ("1" bilevel, palette, greyscale with alpha).
_TO_GREY_MODES = ("1", "P", "PA", "LA", "La")


# -- images --------------------------------------------------------------------------------------------
@contextmanager
def _pixel_limit() -> Iterator[None]:
    """Let Pillow open images up to our own size limit (checked by ``check_dimensions``) instead of its
    decompression-bomb limit of ~89 M pixels. Pillow's limit is a module global, restored on exit."""
    from PIL import Image

    old = Image.MAX_IMAGE_PIXELS
    Image.MAX_IMAGE_PIXELS = None
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            yield
    finally:
        Image.MAX_IMAGE_PIXELS = old


def read_image(
    path: str | Path,
    *,
    vertical_scale: float | None = None,
    vertical_offset: float | None = None,
    encoding: str | None = None,
    nodata: float | None = None,
    hints: FrameHints | None = None,
    notes: tuple[str, ...] = (),
) -> Heightfield:
    """Read a PNG/WebP heightmap or RGB-encoded elevation tile.

    Parameters
    ----------
    path : PNG or WebP file (anything Pillow opens).
    vertical_scale, vertical_offset : metres per stored unit and metres added (default 1 and 0).
    encoding : None for greyscale, or "terrain-rgb" / "terrarium" for RGB-encoded elevations.
    nodata : stored (greyscale) or decoded (encoded) value marking missing samples.
    hints : spacing / tile / CRS placing the grid (see :class:`~terralod.io.raster.FrameHints`).
    notes : notes carried into the Heightfield.
    """
    from PIL import Image, UnidentifiedImageError

    src = str(path)
    try:
        with _pixel_limit(), Image.open(path) as im:
            check_dimensions(im.height, im.width, src)
            mode = im.mode
            if encoding:
                if mode in _GREY_MODES:
                    raise InputError(
                        f"is a greyscale image (mode {mode}); encoding {encoding} needs an RGB image", src
                    )
                values = decode_rgb(np.asarray(im.convert("RGB")), encoding, src)
                notes = (*notes, f"decoded {encoding} RGB")
            elif mode in _GREY_MODES:
                values = np.asarray(im).astype(np.float64)
            elif mode in _TO_GREY_MODES:
                values = np.asarray(im.convert("L")).astype(np.float64)
            else:
                rgb = np.asarray(im.convert("RGB"))
                if not (
                    np.array_equal(rgb[..., 0], rgb[..., 1]) and np.array_equal(rgb[..., 0], rgb[..., 2])
                ):
                    raise InputError(
                        f"is a colour {mode} image; pass encoding (CLI --encoding terrain-rgb|terrarium) "
                        "for RGB-encoded elevation tiles, or save the heightmap as greyscale",
                        src,
                    )
                values = rgb[..., 0].astype(np.float64)
                notes = (*notes, f"{mode} image with equal channels read as 8-bit greyscale")
    except InputError:
        raise
    except UnidentifiedImageError:
        raise InputError("not a PNG/WebP image (Pillow cannot identify it)", src) from None
    except MemoryError:
        raise InputError("image does not fit in memory", src) from None
    except Exception as exc:  # Pillow's decoders raise many classes on corrupt data; all mean "cannot decode"
        raise InputError(f"not a PNG/WebP image Pillow can decode ({error_line(exc)})", src) from None
    valid = np.ones(values.shape, bool)
    if nodata is not None and not math.isnan(nodata) and not encoding:
        valid &= values != nodata
    values, vnote = apply_vertical(values, _or(vertical_scale, 1.0), _or(vertical_offset, 0.0), src)
    if nodata is not None and not math.isnan(nodata) and encoding:
        valid &= values != nodata
    return place_heightfield(values, valid, src, hints or FrameHints(), notes=(*notes, *vnote))


# -- arrays --------------------------------------------------------------------------------------------
def read_array(
    path: str | Path,
    *,
    vertical_scale: float | None = None,
    vertical_offset: float | None = None,
    nodata: float | None = None,
    hints: FrameHints | None = None,
    notes: tuple[str, ...] = (),
) -> Heightfield:
    """Read a 2-D grid from ``.npy``, or from ``.npz`` (array ``elevation``, else the first 2-D numeric
    array). An ``.npz`` may carry its own ``transform`` (GDAL geotransform) and ``crs`` arrays, used
    when ``hints`` give no transform / CRS.

    Parameters are those of :func:`read_image` (without encoding); the shape is checked from the array
    header before the data are loaded.
    """
    src = str(path)
    hints = hints or FrameHints()
    try:
        if zipfile.is_zipfile(path):
            values, hints, note = _read_npz(Path(path), hints, src)
            notes = (*notes, note)
        else:
            with open(path, "rb") as f:
                shape, dtype = _npy_header(f, src)
                _check_grid(shape, dtype, src)
            values = np.load(path, allow_pickle=False)
    except InputError:
        raise
    except MemoryError:
        raise InputError("array does not fit in memory", src) from None
    except Exception as exc:  # numpy's header parser raises tokenizer/syntax errors on corrupt headers
        raise InputError(f"not a NumPy .npy/.npz array file ({error_line(exc)})", src) from None
    raw = np.asarray(values)
    vals = raw.astype(np.float64)
    valid = np.isfinite(vals)
    if nodata is not None and not math.isnan(nodata):
        valid &= raw != nodata
    vals, vnote = apply_vertical(vals, _or(vertical_scale, 1.0), _or(vertical_offset, 0.0), src)
    return place_heightfield(vals, valid, src, hints, notes=(*notes, *vnote))


def _read_npz(p: Path, hints: FrameHints, src: str) -> tuple[np.ndarray, FrameHints, str]:
    """(grid, hints completed from the archive's transform/crs, note naming the array used)."""
    from affine import Affine

    with zipfile.ZipFile(p) as zf:
        names = [n[:-4] for n in zf.namelist() if n.endswith(".npy")]
        headers = {}
        for n in names:
            with zf.open(n + ".npy") as f:
                headers[n] = _npy_header(f, src)
    grids = [n for n in names if len(headers[n][0]) == 2 and headers[n][1].kind in "iuf"]
    key = "elevation" if "elevation" in names else (grids[0] if grids else None)
    if key is None:
        found = ", ".join(f"{n} {headers[n][1]} {headers[n][0]}" for n in names) or "none"
        raise InputError(f"holds no 2-D numeric array (arrays: {found})", src)
    _check_grid(*headers[key], src)
    with np.load(p, allow_pickle=False) as data:
        values = np.asarray(data[key])
        if hints.transform is None and hints.bounds is None and "transform" in names:
            g = np.asarray(data["transform"], np.float64).ravel()
            if g.size == 6:
                hints = replace(hints, transform=Affine.from_gdal(*g.tolist()))
        if hints.crs is None and "crs" in names and data["crs"].dtype.kind in "US":
            hints = replace(hints, crs=str(data["crs"]))
    return values, hints, f"array '{key}' of {p.name}"


def _npy_header(f: Any, src: str) -> tuple[tuple[int, ...], np.dtype]:
    """(shape, dtype) of a .npy stream from its header, without reading the data."""
    version = np.lib.format.read_magic(f)
    if version == (1, 0):
        shape, _, dtype = np.lib.format.read_array_header_1_0(f)
    else:
        shape, _, dtype = np.lib.format.read_array_header_2_0(f)
    return tuple(int(s) for s in shape), np.dtype(dtype)


def _check_grid(shape: tuple[int, ...], dtype: np.dtype, src: str) -> None:
    if len(shape) != 2 or dtype.kind not in "iuf":
        raise InputError(f"expected a 2-D numeric array, got {dtype} of shape {shape}", src)
    check_dimensions(shape[0], shape[1], src)


def _or(value: float | None, default: float) -> float:
    return float(default if value is None else value)
