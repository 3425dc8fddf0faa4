"""Tile loads off the frame path: a worker thread reads, decodes and prepares tiles ahead of need.

With ``Engine(..., async_loads=True)`` a frame never reads the store: selection refines a tile only where
all its children are already decoded (resident), draws the resident tiles meanwhile (coarser, their
measured error still reported in the frame's ``max_screen_error_px``), and asks this loader for the
children of every drawn tile whose projected error exceeds the threshold, most important first (largest
projected error). Each finished load bumps a generation counter, so the next update refines into it.
This is the usual streaming rule of web globes (CesiumJS refines a tile once its children are loaded);
the partition is always made of resident tiles, so stitching sees complete tiles and frames stay
watertight while loading.

Cost per frame on the frame thread: the resident-children test over the quadtree (a few numpy bincounts)
and the queue update; reading, zlib decoding and the stitcher's boundary preparation (``TilePrep``) run on
the worker (numba kernels release the GIL), between frames: while the engine updates a frame the worker
finishes the tile in hand and waits (:attr:`TileLoader.frame_idle`).
"""

from __future__ import annotations

import heapq
import threading
from collections.abc import Callable, Sequence
from typing import Any

from terralod.tiles import TileCode

__all__ = ["TileLoader"]


class TileLoader:
    """A worker thread filling a :class:`terralod.runtime.stitch.TileCache` from its source.

    Parameters
    ----------
    cache : the engine's tile cache (its ``lock`` guards inserts; its source is read under ``io_lock``)
    io_lock : serialises reads of the source with the frame thread's own (synchronous) loads
    on_loaded : called with the codes just inserted (on the worker thread)
    batch : tiles read per round
    """

    def __init__(self, cache: Any, io_lock: threading.Lock, on_loaded: Callable[[list[TileCode]], None], *,
                 batch: int = 4) -> None:  # fmt: skip
        self.cache = cache
        self.io_lock = io_lock
        self.on_loaded = on_loaded
        self.batch = max(1, int(batch))
        self._cv = threading.Condition()
        self._heap: list[tuple[float, int, TileCode]] = []
        self._queued: dict[TileCode, float] = {}
        self._busy = False
        self._closed = False
        self._seq = 0
        self.loaded = 0
        self.error: BaseException | None = None
        #: cleared by the engine while a frame is selected and stitched: the worker finishes the tile in
        #: hand and waits, so the frame thread never competes with it for the GIL (whose hand-over waits
        #: up to ``sys.getswitchinterval()``, 5 ms, per switch: the spikes of a frame that loads meanwhile)
        self.frame_idle = threading.Event()
        self.frame_idle.set()
        self._thread = threading.Thread(target=self._run, name="terralod-load", daemon=True)
        self._thread.start()

    def request(self, codes: Sequence[TileCode], priority: Sequence[float]) -> int:
        """Queue ``codes`` not cached nor queued yet (higher ``priority`` first; a new request of a queued
        code raises its priority); returns how many are waiting."""
        with self._cv:
            for code, p in zip(codes, priority, strict=True):
                if code in self.cache or self._queued.get(code, -1.0) >= p:
                    continue
                self._queued[code] = p
                self._seq += 1
                heapq.heappush(self._heap, (-float(p), self._seq, code))
            if self._heap:
                self._cv.notify_all()
            return len(self._queued)

    @property
    def pending(self) -> int:
        with self._cv:
            return len(self._queued) + (1 if self._busy else 0)

    def wait(self, timeout: float | None = None) -> bool:
        """Block until every queued tile is loaded (or ``timeout`` seconds); True when idle."""
        with self._cv:
            return self._cv.wait_for(lambda: (not self._queued and not self._busy) or self._closed, timeout)

    def _take(self) -> list[TileCode]:
        out: list[TileCode] = []
        while self._heap and len(out) < self.batch:
            negp, _, code = heapq.heappop(self._heap)
            if self._queued.get(code) == -negp:  # not superseded by a higher-priority entry
                del self._queued[code]
                out.append(code)
        return out

    def _run(self) -> None:
        from terralod.runtime.stitch import TilePrep

        while True:
            with self._cv:
                self._cv.wait_for(lambda: bool(self._heap) or self._closed)
                if self._closed:
                    return
                codes = self._take()
                self._busy = bool(codes)
            try:
                done = []
                for code in codes:
                    self.frame_idle.wait()  # never during a frame's update (see frame_idle)
                    if code in self.cache:
                        continue
                    with self.io_lock:
                        tile = self.cache.source.tile(*code)
                    prep = TilePrep.from_tile(tile, self.cache.source.pyramid)
                    self.cache.insert(code, prep)
                    done.append(code)
                self.loaded += len(done)
                if done:
                    self.on_loaded(done)
            except BaseException as exc:  # surfaced by the engine's next update
                self.error = exc
            finally:
                with self._cv:
                    self._busy = False
                    self._cv.notify_all()

    def close(self) -> None:
        self.frame_idle.set()
        with self._cv:
            self._closed = True
            self._heap.clear()
            self._queued.clear()
            self._cv.notify_all()
        self._thread.join(timeout=10.0)
