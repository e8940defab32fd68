"""Chunked work over both cores: one place for the worker-pool rules the pipeline follows.

Workers are *spawned*, never forked: a child forked from a process that already runs OpenCV's (or Embree's)
thread pool can deadlock on a lock held at fork time. Results come back in task order, as they finish, so a
caller can stream them (progress, bounded memory). A pool has one worker per core, so each worker keeps to one
BLAS/OpenMP thread (``OMP/OPENBLAS/MKL_NUM_THREADS=1`` in the environment it is spawned with) and its chunk tasks
to one OpenCV thread (:func:`bodyslam.vision.odometry.set_worker_threads`): more would only compete for the same
cores. (The testbed's renderer runs its own pool: :mod:`testbed.simulate`.)
"""

from __future__ import annotations

import multiprocessing as mp
import os
from typing import Callable, Iterator, Sequence, TypeVar

__all__ = ["available_cores", "imap_tasks"]

T = TypeVar("T")


def available_cores() -> int:
    """Cores this process may run on (its affinity set where the OS has one)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def _ignore_ctrl_c() -> None:
    """Pool workers leave Ctrl-C to the parent (the terminal sends it to the whole process group): the parent
    stops the pool and says 'interrupted'; a worker's own KeyboardInterrupt traceback would only be noise."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)


def imap_tasks(func: Callable[..., T], tasks: Sequence, jobs: int | None = None, ordered: bool = True) -> Iterator[T]:
    """``func(task)`` for every task, in order (or as they finish with ``ordered=False``); in this process when
    one job suffices, else in a spawned pool of ``jobs`` (default: one per available core) workers, closed when
    the iteration ends."""
    jobs = available_cores() if jobs is None else int(jobs)
    jobs = max(1, min(jobs, len(tasks)))
    if jobs == 1:
        yield from map(func, tasks)
        return
    # the workers read these when they load BLAS: set for the spawn only (a user's own setting is kept)
    saved = {v: os.environ.get(v) for v in _THREAD_VARS}
    for v in _THREAD_VARS:
        os.environ.setdefault(v, "1")
    try:
        pool = mp.get_context("spawn").Pool(jobs, initializer=_ignore_ctrl_c)
    finally:
        for v, x in saved.items():
            if x is None:
                os.environ.pop(v, None)
            else:
                os.environ[v] = x
    with pool:
        yield from (pool.imap if ordered else pool.imap_unordered)(func, tasks)
