"""Detail-increment TIN builds (paper 003) on Dask: the sub-blocks simplified on the workers.

Paper: ``../shared/papers/003_2a2cfcda929de24c.txt`` §2.1 (the sub-blocks are simplified independently,
in the paper by parallel threads).

The client reads the cloud, thins it and triangulates it (one Delaunay TIN, as a local build:
:mod:`terralod.tin.delaunay`), cuts one job per sub-block (:func:`terralod.tin.qem.block_jobs`: its
triangles, its seam and outline LOCKED, the quadrics of the whole TIN) and sends the jobs to the workers;
each worker simplifies its block and measures its errors (:func:`terralod.tin.qem.run_block`, a pure
function of the job). The client merges the results block by block, in the order the file format needs
(block-major records, :class:`terralod.tin.records.Increments`), and writes the one file: the model and
its bytes are those of a local build with any number of threads.

Deviation: the triangulation is not distributed. Per-block Delaunay triangulations stitched along the
seams (the paper) give long thin gap triangles, and a distributed exact Delaunay needs a merge step of its
own; the global TIN keeps the seams on shared edges (see :mod:`terralod.tin.delaunay`). The one
triangulation on the client is then the floor of a distributed build: about 1 M points/s with Triangle,
0.13-0.33 M with Qhull (``benchmarks/tin_build.py``).

Clients come from :func:`terralod.pyramid.distributed.dask_client` (``"local"``: a LocalCluster of worker
processes; ``tcp://HOST:PORT``: a running scheduler, refused in one line when it cannot be reached).
"""

from __future__ import annotations

from typing import Any

from terralod.pyramid.distributed import dask_client, tune_worker_malloc
from terralod.tin.qem import BlockJob, BlockResult, run_block

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


def _run_block(job: BlockJob) -> BlockResult:
    """:func:`terralod.tin.qem.run_block` on a worker, with glibc's adaptive thresholds back
    (:func:`terralod.pyramid.distributed.tune_worker_malloc`)."""
    tune_worker_malloc()
    return run_block(job)


def dask_executor(client: Any, retries: int = 2):
    """An ``executor`` for :func:`terralod.tin.qem.simplify_blocks`: each job a task on the cluster
    (biggest first, as given; retried elsewhere when a worker dies), results gathered in job order."""

    def run(jobs: list[BlockJob]) -> list[BlockResult]:
        futures = [client.submit(_run_block, j, pure=False, retries=retries) for j in jobs]
        try:
            return list(client.gather(futures))
        finally:
            for f in futures:
                f.release()

    return run
