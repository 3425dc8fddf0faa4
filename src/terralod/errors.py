"""Error classes of terralod.

Every user-facing error derives from :class:`TerralodError` and from the builtin that matches it, so
``except ValueError`` keeps working for callers who do not know terralod (the rasterio habit). The CLI
turns any ``TerralodError`` into one line ``terralod: <file>: <problem>`` and exit code 2.
"""

from __future__ import annotations


class TerralodError(Exception):
    """Root of every terralod error. ``path`` names the file concerned, when there is one."""

    def __init__(self, message: str, path: str | None = None) -> None:
        self.message = " ".join(str(message).split())  # always one line (SQLite, GDAL, PROJJSON wrap theirs)
        self.path = None if path is None else str(path)
        super().__init__(f"{self.path}: {message}" if self.path else message)


class InputError(TerralodError, ValueError):
    """The input data is unusable: wrong format, no valid samples, absurd size, NaN everywhere."""


class InputNotFoundError(TerralodError, FileNotFoundError):
    """The input file does not exist."""


class StoreError(TerralodError, OSError):
    """The tile store cannot be opened or written."""


class CorruptStoreError(StoreError):
    """The tile store exists but is corrupted, foreign, or from an incompatible version."""


class BuildMismatchError(TerralodError, ValueError):
    """A resumed build does not match the store it resumes (other source or options)."""


class WorkerLostError(TerralodError, RuntimeError):
    """A distributed build lost the workers of one work unit more times than it retries (out of memory,
    usually): the tiles committed so far are kept."""


class DisplayError(TerralodError, RuntimeError):
    """No OpenGL context or window could be made (no GPU driver, no EGL, no display): the machine's
    set-up, not a bug of terralod."""


class OutputBusyError(TerralodError, OSError):
    """Another run, still alive, is writing the same output (its work folder's lock names it)."""
