"""Detail-increment TIN builds (Ai et al., 2019) on Dask: triangulated and simplified on the workers.

Paper: ``../shared/papers/003_2a2cfcda929de24c.txt`` §2.1 (the sub-blocks are simplified independently,
in the paper by parallel threads).

The client reads the cloud and thins it. The Delaunay triangulation is computed block by block on the
workers (:func:`terralod.tin.delaunay_blocks.block_triangles`: each block triangulates its core and a
halo and keeps the triangles whose circumcircle it has seen whole and whose centre is its own); the client
joins the pieces and fills the narrow gaps none could keep with a constrained Delaunay triangulation
(:func:`terralod.tin.delaunay_blocks.fill_holes`). The client then cuts one job per sub-block
(:func:`terralod.tin.qem.block_jobs`: its triangles, its seam and outline LOCKED, the quadrics of the
whole TIN) and sends the jobs to the workers; each worker simplifies its block and measures its errors
(:func:`terralod.tin.qem.run_block`, a pure function of the job). The client merges the results block by
block, in the order the file format needs (block-major records, :class:`terralod.tin.records.Increments`),
and writes the one file: the model and its bytes are those of a local build with any number of threads
(the local build computes the same blocks on threads).

Deviation: the cloud is read and thinned on the client (one pass, laspy's chunked reader), and the
blocks' points are sent to the workers with their tasks, so no shared file system is needed.

Clients come from :func:`terralod.pyramid.distributed.dask_client` (``"local"``: a LocalCluster of worker
processes; ``tcp://HOST:PORT``: a running scheduler, refused in one line when it cannot be reached).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any

from terralod.errors import WorkerLostError
from terralod.pyramid.distributed import dask_client, tune_worker_malloc

__all__ = ["close_client", "dask_executor", "open_client"]


def open_client(address: str, n_workers: int | None = None, threads: int = 1, timeout_s: float = 10.0) -> Any:
    """A dask.distributed Client for ``address`` ("local" or ``tcp://HOST:PORT``); ``n_workers`` worker
    processes of ``threads`` threads for "local". InputError when the scheduler cannot be reached within
    ``timeout_s``."""
    return dask_client(address, n_workers=n_workers or 2, threads=threads, timeout_s=timeout_s)


def close_client(client: Any) -> None:
    """Close ``client``, and the LocalCluster it started, if any (a scheduler it connected to stays up)."""
    from dask.distributed import LocalCluster

    cluster = getattr(client, "cluster", None)
    client.close()
    if isinstance(cluster, LocalCluster):
        cluster.close()


def _on_worker(fn: Callable[[Any], Any], job: Any) -> Any:
    """``fn(job)`` on a worker, with glibc's adaptive thresholds back
    (:func:`terralod.pyramid.distributed.tune_worker_malloc`)."""
    tune_worker_malloc()
    return fn(job)


def dask_executor(
    client: Any, retries: int = 2
) -> Callable[[Iterable[Any], Callable[[Any], Any]], list[Any]]:
    """An ``executor(jobs, fn)`` for :meth:`terralod.tin.increments.DetailIncrementModel.from_points`: each
    ``fn(job)`` a task on the cluster, submitted as the iterable ``jobs`` yields it, in that order
    (Delaunay blocks, :func:`terralod.tin.delaunay_blocks.block_triangles`; sub-block simplification,
    :func:`terralod.tin.qem.run_block`, biggest first, cut while the first ones run), retried elsewhere
    when a worker dies; results gathered in job order."""

    def run(jobs: Iterable[Any], fn: Callable[[Any], Any]) -> list[Any]:
        from distributed import KilledWorker

        futures = [client.submit(_on_worker, fn, j, pure=False, retries=retries) for j in jobs]
        try:
            return list(client.gather(futures))
        except KilledWorker as exc:  # the task's workers died, retries included: memory, usually
            raise WorkerLostError(
                f"Dask workers died running {getattr(fn, '__name__', 'a task')} ({exc}); out of memory? give "
                "each worker more memory, or split the cloud into more sub-blocks (--sub-blocks); nothing "
                "was written"
            ) from None
        finally:
            for f in futures:
                f.release()

    return run
