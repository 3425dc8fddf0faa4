"""Failures as one line and exit code 2: the error mapping of every command, missing extras, the
words for an input that does not fit in memory, and the libraries' warnings kept quiet without ``-v``.
"""

from __future__ import annotations

import logging
import os
import sys
from pathlib import Path
from typing import Any

import click

from terralod.cli._console import err_console, log, one_line

VERBOSE = {"on": False}


#: The DEM the command read last: a failure for want of memory names it (run_main).
LAST_INPUT: dict[str, str | None] = {"path": None}


#: The optional parts of terralod (``pip install 'terralod[EXTRA]'``) and the modules each one brings.
EXTRAS: dict[str, tuple[str, ...]] = {
    "web": ("pyproj", "pygltflib", "pydelatin"),  # export, serve: 3D Tiles, quantized-mesh, ECEF
    "change": ("xdem", "shapely", "pyproj"),  # change: co-registration, zones, reprojection
    "dask": ("dask", "distributed"),  # build --dask
    "window": ("glfw",),  # view: the real-time window
}


class MissingExtra(click.ClickException):
    """A command whose optional dependencies are not installed: one line, exit 2."""

    exit_code = 2

    def show(self, file: Any = None) -> None:
        click.echo(self.message, err=True)


def missing_modules(extra: str) -> list[str]:
    """The modules of ``extra`` (:data:`EXTRAS`) that cannot be imported here."""
    import importlib.util

    out = []
    for name in EXTRAS[extra]:
        try:
            found = importlib.util.find_spec(name) is not None
        except (ImportError, ValueError):
            found = False
        if not found:
            out.append(name)
    return out


def require_extra(command: str, extra: str) -> None:
    """Stop ``terralod COMMAND`` with one line naming the extra to install when its modules are missing."""
    missing = missing_modules(extra)
    if missing:
        log.info("missing modules of the %s extra: %s", extra, ", ".join(missing))
        raise MissingExtra(f"terralod {command} needs the {extra} extra: pip install 'terralod[{extra}]'")


def out_of_memory(path: str | Path) -> str:
    """The one line for a DEM this machine has not the memory to read (its size from the header)."""
    try:
        import rasterio

        with rasterio.open(path) as src:
            n = src.width * src.height
            size = f"{src.width}x{src.height} samples (about {n * 13 / 1e9:.1f} GB to read and fill)"
    except Exception:  # noqa: BLE001 - not a GDAL raster: say it without the size
        size = "its samples"
    return f"not enough memory for {size}; crop or split it into tiles first"


def store_write_error(exc: BaseException, out: str | Path) -> Exception:
    """The one line of a store that could not be written (full disk, I/O error, file-size limit): what
    is committed stays, and ``--resume`` finishes once there is room."""
    from terralod.errors import StoreError

    return StoreError(
        f"cannot write the store ({exc}; is the disk full?); the tiles committed so far are kept: free "
        "space, then run the same command with --resume",
        str(out),
    )


#: Loggers of the libraries whose warnings (GDAL through rasterio, laspy, Python warnings) would print
#: before the ``terralod:`` line; they are shown with ``-v`` only.
LIBRARY_LOGGERS = ("rasterio", "fiona", "laspy", "py.warnings", "PIL", "numba", "imageio")


def quiet_libraries(verbose: bool) -> None:
    """Route library warnings to logging and show them only with ``-v`` (INFO level and up)."""
    logging.captureWarnings(True)
    if not verbose:  # GDAL's own default handler (messages outside rasterio's handler, e.g. libtiff on close)
        os.environ.setdefault("CPL_LOG", os.devnull)
    for name in LIBRARY_LOGGERS:
        logging.getLogger(name).setLevel(logging.INFO if verbose else logging.CRITICAL)


def _fail(message: str) -> None:
    """Print the one line (after the traceback with -v) and exit 2."""
    if VERBOSE["on"]:
        import traceback

        traceback.print_exc(file=sys.stderr)
    click.echo(f"terralod: {one_line(message, 1000)}", err=True)  # room for a command with two long paths
    sys.exit(2)


def run_main(group: click.Group, argv: list[str] | None) -> None:
    """Run ``group``, turning every failure into one line ``terralod: <file>: <problem>`` and exit code 2;
    ``-v`` prints the traceback before that line and keeps exit code 2."""
    from terralod.errors import TerralodError

    try:
        group.main(args=argv, prog_name="terralod", standalone_mode=False)
    except click.exceptions.Abort:
        err_console.print("terralod: aborted; a build finishes with the same command and --resume")
        sys.exit(130)
    except click.exceptions.Exit as exc:
        sys.exit(exc.exit_code)
    except click.ClickException as exc:
        exc.show()
        sys.exit(2)
    except KeyboardInterrupt:
        err_console.print("terralod: interrupted; finished tiles are saved, finish with --resume")
        sys.exit(130)
    except TerralodError as exc:
        _fail(str(exc))
    except MemoryError:
        last = LAST_INPUT["path"]
        _fail(
            f"{last}: {out_of_memory(last)}"
            if last
            else "out of memory; split the input or use a smaller --tile-size"
        )
    except OSError as exc:
        name = getattr(exc, "filename", None)
        _fail(f"{str(name) + ': ' if name else ''}{exc.strerror or exc}")
    except Exception as exc:  # a bug: still one line (the traceback with -v), never a crash dump
        _fail(f"internal error ({type(exc).__name__}: {exc}); run with -v for the traceback and report it")


__all__ = [
    "VERBOSE",
    "LAST_INPUT",
    "EXTRAS",
    "MissingExtra",
    "missing_modules",
    "require_extra",
    "out_of_memory",
    "store_write_error",
    "LIBRARY_LOGGERS",
    "quiet_libraries",
    "run_main",
]
