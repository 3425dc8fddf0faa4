"""Outputs written whole or not at all: one work folder per output, one lock, one atomic swap.

Every folder output (the web exports, the site, ``terralod change``) is written through :class:`Output`::

    with Output("web", inputs=[store], overwrite=True, resume=True, key=options) as o:
        for rel, encode in tiles:
            if not o.done(rel):  # finished by an interrupted run this one resumes
                o.write(rel, encode())
    # "web" now holds what was written; after any exception it is as it was

Beside the target ``OUT``, in the same folder (so the swap is a rename on one file system)::

    .OUT.work/          the work folder
        lock.json       who writes it: pid, host, start time, command, the writer's key
        journal.jsonl   one line per finished file: its relative path and the writer's record
        out/            the files, renamed to OUT at the end
        old/            the previous OUT, set aside during the swap
        scratch/        the writer's intermediate files, never part of OUT

Invariants:

- OUT changes only by renames: before the swap it is the old output (or absent), after it the new one. A kill
  between the swap's two renames leaves the old output whole in ``old/``; the next run on OUT puts it back
  first (:func:`restore_set_aside`), so OUT is never lost;
- a work folder whose lock names a process alive on this host is never touched: the run is refused with one
  line naming that process. A lock from another host counts as alive (its process cannot be asked);
- a work folder whose process is gone is adopted with ``resume`` (its finished files kept, :meth:`Output.done`)
  when it was started with the same key; without ``resume`` it is replaced;
- a file inside the work folder is whole under its name or absent (:meth:`Output.write`: temporary name,
  then rename). A temporary is named after its process (``.NAME.PID.tmp``) and removed once that process is
  gone (:func:`remove_stale_temporaries`, shared with the store's files);
- an output is never one of its inputs, never holds one and never lies inside one (:func:`refuse_inputs`);
- with ``keep_records`` the finished output carries its files' records (``RECORDS``, one JSON object, sorted,
  the same bytes for the same records), so a later ``update`` knows what each file was made from
  (:meth:`Output.previous`) and may keep a file without making it again (:meth:`Output.keep`).

This module imports nothing from the exports, the site, the change report or the CLI: all of them use it.
"""

from __future__ import annotations

import contextlib
import datetime
import json
import os
import shutil
import socket
import sys
import tempfile
from collections.abc import Callable, Iterable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from types import TracebackType
from typing import Any

from terralod.errors import InputError, OutputBusyError

__all__ = [
    "Lock",
    "Output",
    "SpillFile",
    "check_target",
    "pid_alive",
    "refuse_inputs",
    "remove_stale_temporaries",
    "restore_set_aside",
    "same_file",
    "scratch_beside",
    "temporary_path",
    "work_path",
]

#: The file of a finished output that holds its files' records (``Output(keep_records=True)``).
RECORDS = ".terralod-records.json"

PathLike = str | os.PathLike[str]


# -- processes and their temporaries -----------------------------------------------------------------------
def pid_alive(pid: int) -> bool:
    """True unless process ``pid`` is known to be gone (off POSIX, and for another user's, assumed alive)."""
    if os.name != "posix" or pid <= 0:
        return pid > 0
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # EPERM: alive, someone else's
        return True
    return True


def _process_start(pid: int) -> str | None:
    """When process ``pid`` started (clock ticks since boot, Linux ``/proc``), None where unknown: a pid
    reused by a later process has another start."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
        return stat[stat.rindex(")") + 2 :].split()[19]
    except (OSError, ValueError, IndexError):
        return None


def temporary_path(p: PathLike) -> Path:
    """The name under which this process writes what becomes ``p``: ``.NAME.PID.tmp`` in ``p``'s folder
    (same file system, so the final rename is atomic)."""
    p = Path(p)
    return p.with_name(f"{_hidden(p.name)}.{os.getpid()}.tmp")


def _hidden(name: str) -> str:
    return name if name.startswith(".") else f".{name}"


def _remove(p: Path) -> None:
    if p.is_dir() and not p.is_symlink():
        shutil.rmtree(p, ignore_errors=True)
    else:
        p.unlink(missing_ok=True)


def remove_stale_temporaries(p: PathLike, remove: Callable[[Path], None] | None = None) -> list[Path]:
    """Remove the temporaries of ``p`` (:func:`temporary_path`) whose process is gone; a live process's
    (this one's included) are never touched. ``remove`` deletes one (default: the file or folder).
    Returns what was removed."""
    p = Path(p)
    prefix = _hidden(p.name) + "."
    try:
        found = list(p.parent.glob(f"{prefix}*.tmp"))
    except OSError:
        return []
    gone = []
    for f in found:
        try:
            pid = int(f.name[len(prefix) : -len(".tmp")])
        except ValueError:
            continue
        if pid != os.getpid() and not pid_alive(pid):
            (remove or _remove)(f)
            gone.append(f)
    return gone


# -- the input guard and the target rule -------------------------------------------------------------------
def same_file(a: PathLike, b: PathLike) -> bool:
    """True when ``a`` and ``b`` are one existing file or folder (same path, hard link or symlink)."""
    try:
        return os.path.samefile(a, b)
    except (OSError, ValueError):
        return False


def refuse_inputs(output: PathLike, inputs: Iterable[PathLike], *, what: str = "output") -> None:
    """Refuse an ``output`` that is one of ``inputs`` (same path, hard link or symlink), holds one at any
    depth (replacing it would delete the input), lies inside one, or is an input's sidecar ``STEM.json``.

    Checked before anything is written, whatever ``overwrite`` says. Raises :class:`InputError`, one line
    naming the output and the input.
    """
    out = Path(output)
    o = out.resolve()
    exists = out.exists() or out.is_symlink()
    for src in inputs:
        s = Path(src)
        r = s.resolve()
        if (exists and same_file(out, s)) or r == o or o in r.parents:
            raise InputError(f"is (or holds) the input {src}; writing there would destroy it; choose another {what}",
                             str(output))  # fmt: skip
        if r in o.parents:
            raise InputError(f"lies inside the input {src}; choose another {what}", str(output))
        side = s.with_suffix(".json")
        if (exists and same_file(out, side)) or side.resolve() == o:
            raise InputError(
                f"is the input's sidecar {side}; writing there would destroy it; choose another {what}",
                str(output),
            )


def check_target(
    output: PathLike,
    inputs: Sequence[PathLike] = (),
    *,
    overwrite: bool = False,
    resume: bool = False,
    suffixes: tuple[str, ...] = (),
    what: str = "output",
) -> Path:
    """The ``-o`` / ``--overwrite`` rule of a file output (a store, an image, a video, a GeoTIFF).

    - ``suffixes``: the accepted name endings (e.g. ``(".png",)``), refused otherwise;
    - never onto, into or around an input (:func:`refuse_inputs`), even with ``overwrite``;
    - an existing output needs ``overwrite`` (or ``resume`` where the command resumes);
    - the folder the output goes into must exist.

    Folder outputs get the same rules from :class:`Output`. Raises :class:`InputError` (one line).
    """
    out = Path(output)
    name = str(out)
    if suffixes and out.suffix.lower() not in suffixes:
        got = f"'{out.suffix}'" if out.suffix else "no extension"
        raise InputError(f"{what} must end in {' or '.join(suffixes)} (got {got})", name)
    refuse_inputs(out, inputs, what=what)
    if out.exists() or out.is_symlink():
        if not (overwrite or resume):
            raise InputError("already exists; pass --overwrite to replace it", name)
    elif not out.resolve().parent.is_dir():
        raise InputError(f"output folder {out.resolve().parent} does not exist", name)
    return out


# -- the lock ----------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Lock:
    """Who writes a work folder (``lock.json``). ``key`` is what the writer writes (format, options, input),
    canonical JSON; ``released`` marks a writer that stopped on an error and left its files for ``resume``."""

    pid: int
    host: str
    started: str
    command: str
    process_start: str | None = None
    key: str | None = None
    released: bool = False

    @classmethod
    def mine(cls, key: str | None, command: str | None = None) -> Lock:
        now = datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")
        cmd = command if command is not None else " ".join([Path(sys.argv[0]).name, *sys.argv[1:]])
        pid = os.getpid()
        return cls(pid, socket.gethostname(), now, cmd, _process_start(pid), key)

    @classmethod
    def read(cls, work: PathLike) -> Lock | None:
        """The lock of work folder ``work``; None when it has none that reads (its writer is gone)."""
        try:
            d = json.loads((Path(work) / "lock.json").read_text())
            return cls(int(d["pid"]), str(d["host"]), str(d["started"]), str(d["command"]),
                       d.get("process_start"), d.get("key"), bool(d.get("released", False)))  # fmt: skip
        except (OSError, ValueError, KeyError, TypeError):
            return None

    def write(self, work: PathLike) -> None:
        tmp = temporary_path(Path(work) / "lock.json")
        tmp.write_text(json.dumps(asdict(self)) + "\n")
        os.replace(tmp, Path(work) / "lock.json")

    def alive(self) -> bool:
        """Whether the writer may still be running: its pid is alive on this host and was not reused by a
        later process, or it runs on another host."""
        if self.released:
            return False
        if self.host != socket.gethostname():
            return True
        if not pid_alive(self.pid):
            return False
        now = _process_start(self.pid)
        return self.process_start is None or now is None or now == self.process_start

    def describe(self) -> str:
        return f"pid {self.pid} on {self.host} since {self.started} ({self.command})"


def work_path(target: PathLike) -> Path:
    """The work folder of output ``target``: ``.NAME.work`` beside it."""
    t = Path(target)
    return t.resolve().parent / f".{t.name}.work"


def restore_set_aside(target: PathLike) -> bool:
    """Put back an output that a run killed between the two renames of its swap left aside.

    The swap renames ``OUT`` to ``.OUT.work/old`` and then ``.OUT.work/out`` to ``OUT``; a kill in between
    leaves no ``OUT`` and the old one whole. It is moved back (True) unless its writer still runs, so a
    killed run leaves the old output or the new one, never none.
    """
    dst = Path(target)
    if dst.exists() or dst.is_symlink():
        return False
    work = work_path(dst)
    old = work / "old"
    if not old.is_dir():
        return False
    lock = Lock.read(work)
    if lock is not None and lock.alive():
        return False
    try:
        os.replace(old, dst)
    except OSError:  # another run put it back first
        return False
    return True


# -- the output --------------------------------------------------------------------------------------------
class Output:
    """A folder output written in its work folder and swapped into place whole (see the module's notes).

    Parameters
    ----------
    target
        The output folder.
    inputs
        What the run reads: the output is never one of them, never holds one, never lies inside one.
    overwrite
        Replace an existing non-empty ``target`` (refused otherwise).
    resume
        Adopt the work folder of an interrupted run of the same ``key``: the files it finished are kept
        (:meth:`done` is True for them, :meth:`record` gives what the writer recorded with each).
    update
        Start from the existing ``target``: its files hard-linked into the work folder (same inode, same
        mtime), each :meth:`write` compares and replaces only a file whose bytes change (:attr:`rewritten`).
        Implies ``overwrite``.
    key
        What this run writes (format, options, input identity; anything JSON takes): an interrupted run is
        adopted only when its key is the same.
    keep_on_error
        After an exception, keep the work folder (its lock released) for a later ``resume``; else remove it.
    keep_records
        Write every file's record into the finished output (``RECORDS``); an ``update`` reads the previous
        output's (:meth:`previous`).
    """

    def __init__(
        self,
        target: PathLike,
        *,
        inputs: Sequence[PathLike] = (),
        overwrite: bool = False,
        resume: bool = False,
        update: bool = False,
        key: Any = None,
        keep_on_error: bool | None = None,
        command: str | None = None,
        keep_records: bool = False,
    ) -> None:
        self.target = Path(target)
        self.inputs = list(inputs)
        self.update = update
        self.overwrite = overwrite or update
        self.resume = resume
        self.key = (
            None if key is None else json.dumps(key, sort_keys=True, separators=(",", ":"), default=str)
        )
        self.keep_on_error = (resume or key is not None) if keep_on_error is None else keep_on_error
        self.command = command
        self.work = work_path(self.target)
        self.adopted: Lock | None = None
        self.rewritten: list[str] = []
        self._records: dict[str, dict[str, Any]] = {}
        self.keep_records = keep_records
        self._previous: dict[str, dict[str, Any]] | None = None
        self._sealed = False
        self._journal: Any = None
        self._open = False

    # -- where things go
    @property
    def folder(self) -> Path:
        """The folder that becomes ``target``: write the output here."""
        return self.work / "out"

    @property
    def scratch(self) -> Path:
        """A folder for intermediate files, removed with the work folder, never part of ``target``."""
        d = self.work / "scratch"
        d.mkdir(exist_ok=True)
        return d

    def path(self, rel: str) -> Path:
        """Where the output's file ``rel`` (``/``-separated, relative to ``target``) is written."""
        return self.folder / rel

    # -- resume and update
    def done(self, rel: str) -> bool:
        """True when file ``rel`` was finished (by this run or the interrupted run it adopted)."""
        return rel in self._records and self.path(rel).is_file()

    def record(self, rel: str) -> dict[str, Any] | None:
        """What the writer recorded with finished file ``rel`` (:meth:`write`'s ``record``), else None."""
        return self._records.get(rel) if self.done(rel) else None

    def previous(self, rel: str) -> dict[str, Any] | None:
        """With ``update`` and ``keep_records``: the record the output being updated keeps for ``rel``
        (None when it has none, or the file is not in the work folder)."""
        if not (self.update and self.keep_records):
            return None
        if self._previous is None:
            try:
                got = json.loads((self.target / RECORDS).read_text())
                self._previous = {str(k): v for k, v in got.items() if isinstance(v, dict)}
            except (OSError, ValueError, AttributeError):
                self._previous = {}
        r = self._previous.get(rel)
        return r if r is not None and self.path(rel).is_file() else None

    def keep(self, rel: str, record: dict[str, Any] | None = None) -> None:
        """Count file ``rel``, already in the work folder (the output being updated has it), as finished
        without writing it (same inode, same mtime), with ``record``."""
        if not self._open:
            raise RuntimeError("Output.keep outside its with block")
        if not self.path(rel).is_file():
            raise FileNotFoundError(self.path(rel))
        self._journal.write(json.dumps({"path": rel, "record": record, "changed": False}) + "\n")
        self._journal.flush()
        self._records[rel] = record or {}

    def write(
        self, rel: str, data: bytes, record: dict[str, Any] | None = None, *, fsync: bool = False
    ) -> bool:
        """Write file ``rel`` of the output whole: under a temporary name, then renamed (``fsync``: on disk
        before the rename). With ``update``, a file whose bytes are already these is left as it is (same
        inode and mtime). ``record`` (anything JSON writes exactly: floats round-trip) is kept in the
        journal for :meth:`record`. Returns True when the file was (re)written."""
        if not self._open:
            raise RuntimeError("Output.write outside its with block")
        p = self.path(rel)
        p.parent.mkdir(parents=True, exist_ok=True)
        changed = True
        if self.update:
            try:
                changed = p.stat().st_size != len(data) or p.read_bytes() != data
            except FileNotFoundError:
                changed = True
        if changed:
            tmp = temporary_path(p)
            with open(tmp, "wb") as fh:
                fh.write(data)
                if fsync:
                    fh.flush()
                    os.fsync(fh.fileno())
            os.replace(tmp, p)
        self._journal.write(json.dumps({"path": rel, "record": record, "changed": changed}) + "\n")
        self._journal.flush()
        self._records[rel] = record or {}
        if changed and self.update and rel not in self.rewritten:
            self.rewritten.append(rel)
        return changed

    def seal(self) -> None:
        """With ``keep_records``: write ``RECORDS`` (every finished file's record) into the output, like any
        file (with ``update``, rewritten only when it changes). Entering the end of the block does it when
        the writer did not; a writer that reports :attr:`rewritten` calls it first."""
        if not self.keep_records:
            return
        recs = {k: v for k, v in sorted(self._records.items()) if k != RECORDS}
        data = json.dumps(recs, sort_keys=True, separators=(",", ":")).encode()
        was = self._open
        self._open = True
        try:
            self.write(RECORDS, data)
        finally:
            self._open = was
        self._sealed = True

    def files(self) -> list[str]:
        """The output's files now in the work folder (relative, ``/``-separated, sorted)."""
        return sorted(f.relative_to(self.folder).as_posix() for f in self.folder.rglob("*") if f.is_file())

    def prune(self) -> list[str]:
        """Remove the files of the work folder that were not :meth:`write`-n (by this run or the run it
        resumed): with ``update``, what the new output no longer has. Returns them."""
        gone = [f for f in self.files() if f not in self._records]
        for f in gone:
            self.path(f).unlink()
        for d in sorted((d for d in self.folder.rglob("*") if d.is_dir()), key=lambda d: -len(d.parts)):
            if not any(d.iterdir()):
                d.rmdir()
        return gone

    # -- the context
    def __enter__(self) -> Output:
        self.check()
        self._acquire()
        self._journal = open(self.work / "journal.jsonl", "a")  # noqa: SIM115 - closed in __exit__
        self._open = True
        return self

    def __exit__(
        self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if kind is None and self.keep_records and not self._sealed:
            self.seal()
        self._open = False
        self._journal.close()
        if kind is None:
            self._swap()
        elif self.keep_on_error:  # released: a later run with resume adopts it, one without replaces it
            with contextlib.suppress(OSError):
                Lock(**{**asdict(Lock.read(self.work) or Lock.mine(self.key)), "released": True}).write(
                    self.work
                )
        else:
            shutil.rmtree(self.work, ignore_errors=True)

    def check(self) -> None:
        """The refusals, before anything is written (a command calls it before its long work): never onto,
        into or around an input, a folder, not empty without ``overwrite``, in a writable folder, no run
        alive on it. Entering the block checks again."""
        dst = self.target
        refuse_inputs(dst, self.inputs)
        restore_set_aside(dst)
        if dst.exists() and not dst.is_dir():
            raise InputError("exists and is not a folder", str(dst))
        if self.update and not dst.is_dir():
            raise InputError("does not exist; there is nothing to update (export it first)", str(dst))
        if dst.is_dir() and any(dst.iterdir()) and not self.overwrite:
            raise InputError("output folder is not empty (pass --overwrite to replace it)", str(dst))
        parent = dst.resolve().parent
        if not parent.is_dir():
            raise InputError(f"output folder {parent} does not exist", str(dst))
        if not os.access(parent, os.W_OK):
            raise InputError(f"output folder {parent} is not writable", str(dst))
        lock = Lock.read(self.work)
        if lock is not None and lock.alive():
            raise self._busy(lock)

    def _busy(self, lock: Lock) -> OutputBusyError:
        return OutputBusyError(
            f"is being written by {lock.describe()}; wait for it to finish (if it is gone, remove {self.work})",
            str(self.target),
        )

    def _acquire(self) -> None:
        """Make the work folder this process's: fresh, adopted (``resume``) or replacing a dead run's."""
        remove_stale_temporaries(self.work)
        mine = temporary_path(self.work)
        _remove(mine)
        lock = Lock.mine(self.key, self.command)
        if self.work.exists():
            old = Lock.read(self.work)
            if old is not None and old.alive():
                raise self._busy(old)
            try:
                os.rename(self.work, mine)  # claimed: of two runs that find it dead, one gets it
            except FileNotFoundError:
                old = None  # another run claimed it: start fresh (the rename below says if it is busy)
            else:
                if self.resume and old is not None and old.key != self.key:
                    os.rename(mine, self.work)  # not ours to take: left as it was
                    raise InputError(
                        f"the interrupted run in {self.work} wrote something else ({old.command}); run "
                        "without --resume to start over",
                        str(self.target),
                    )
                if self.resume and old is not None:
                    self.adopted = old
                    self._adopt(mine)
                else:
                    shutil.rmtree(mine)
        if self.adopted is None:
            mine.mkdir()
            if self.update:
                _link_tree(self.target, mine / "out")
            else:
                (mine / "out").mkdir()
        _remove(mine / "old")
        lock.write(mine)
        try:
            os.rename(mine, self.work)
        except OSError:
            other = Lock.read(self.work)
            shutil.rmtree(mine, ignore_errors=True)
            if other is not None:
                raise self._busy(other) from None
            raise

    def _adopt(self, mine: Path) -> None:
        """Keep an interrupted run's finished files: the journal's entries whose file exists; its
        temporaries (its process is gone) removed."""
        (mine / "out").mkdir(exist_ok=True)
        for f in list((mine / "out").rglob(".*.tmp")):
            _remove(f)
        try:
            lines = (mine / "journal.jsonl").read_text().splitlines()
        except OSError:
            lines = []
        for line in lines:
            try:
                e = json.loads(line)
            except ValueError:  # the last line of a kill mid-write
                continue
            self._records[e["path"]] = e.get("record") or {}
            if e.get("changed") and self.update and e["path"] not in self.rewritten:
                self.rewritten.append(e["path"])

    def _swap(self) -> None:
        """The one change of ``target``: the finished work folder renamed onto it (an existing target set
        aside in the work folder first, removed after)."""
        dst = self.target
        if dst.exists() or dst.is_symlink():
            os.replace(dst, self.work / "old")  # a kill between these renames: the next run puts it back
        os.replace(self.folder, dst)
        shutil.rmtree(self.work, ignore_errors=True)


def _link_tree(src: Path, dst: Path) -> None:
    """``dst`` as a copy of folder ``src`` made of hard links (same inodes, same mtimes); a file system
    without hard links gets copies with their mtimes."""
    for d, _, names in os.walk(src):
        rel = Path(d).relative_to(src)
        (dst / rel).mkdir(parents=True, exist_ok=True)
        for n in names:
            s, t = Path(d) / n, dst / rel / n
            if s.is_symlink():
                continue
            try:
                os.link(s, t)
            except OSError:
                shutil.copy2(s, t)


# -- spill files: what a bounded memory cache drops, kept on disk instead of made again -----------------------
_SCRATCH: list[Path] = []


@contextlib.contextmanager
def scratch_beside(target: PathLike) -> Any:
    """While inside, this process's spill files go to the folder of ``target`` (the output's file system:
    a large disk, seldom a RAM-backed ``/tmp``) instead of the system's temporary folder."""
    _SCRATCH.append(Path(target).resolve().parent)
    try:
        yield
    finally:
        _SCRATCH.pop()


#: Free space a spill file leaves on its file system: the larger of these (bytes, fraction of the free
#: space when the file is made). Past it, :meth:`SpillFile.put` declines and the caller makes the data
#: again: a spill never fills the disk the output is written to, it only stops saving time.
SPILL_RESERVE_BYTES = 2 << 30
SPILL_RESERVE_FRACTION = 0.25


def pack_block(z: Any, ok: Any, dtype: Any) -> bytes:
    """A block's heights as ``dtype`` then its validity as one bit a sample: a spill file's slot."""
    import numpy as np

    return np.ascontiguousarray(z, dtype).tobytes() + np.packbits(ok, axis=None).tobytes()


def unpack_block(raw: bytes, dtype: Any, shape: tuple[int, int]) -> tuple[Any, Any]:
    """:func:`pack_block`'s bytes back as (heights, read-only; validity)."""
    import numpy as np

    n = shape[0] * shape[1]
    width = n * np.dtype(dtype).itemsize
    z = np.frombuffer(raw, dtype, count=n).reshape(shape)
    ok = np.unpackbits(np.frombuffer(raw, np.uint8, offset=width), count=n).view(bool).reshape(shape)
    return z, ok


class SpillFile:
    """Fixed-size slots of bytes at given offsets of one unlinked temporary file (sparse: only the slots
    written take space), for caches that drop what memory cannot hold and read it back later as the same
    bytes. Thread-safe (positional reads and writes); made on the first :meth:`put`, in the folder of
    :func:`scratch_beside` or the system's temporary folder; gone with the process or this object."""

    def __init__(self, prefix: str) -> None:
        self.prefix = prefix
        self._file: Any = None
        self._allowance = 0
        self.bytes_written = 0

    def put(self, offset: int, data: bytes) -> bool:
        """Write ``data`` at ``offset``; False (nothing written) when the disk's reserve would be reached."""
        if self._file is None:
            folder = _SCRATCH[-1] if _SCRATCH else Path(tempfile.gettempdir())
            try:
                free = shutil.disk_usage(folder).free
                self._file = tempfile.TemporaryFile(prefix=self.prefix, dir=folder)
            except OSError:
                self._allowance = -1  # a folder that takes no file: no spill, the data made again
                return False
            self._allowance = int(free - max(SPILL_RESERVE_BYTES, SPILL_RESERVE_FRACTION * free))
        if self.bytes_written + len(data) > self._allowance:
            return False
        try:
            done = os.pwrite(self._file.fileno(), data, offset)
        except OSError:
            done = -1
        if done != len(data):
            self._allowance = -1  # the disk said no: stop spilling, never fail the caller for it
            return False
        self.bytes_written += done
        return True

    def get(self, offset: int, size: int) -> bytes:
        """The ``size`` bytes at ``offset`` (a slot :meth:`put` wrote)."""
        got = os.pread(self._file.fileno(), size, offset)
        if len(got) != size:
            raise OSError(f"short read from the spill file at {offset}")
        return got
