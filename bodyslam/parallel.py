"""Chunked work over both cores: one place for the worker-pool rules the pipeline follows.

Workers are *spawned*, never forked: a child forked from a process that already runs OpenCV's (or Embree's)
thread pool can deadlock on a lock held at fork time. Results come back in task order, as they finish, so a
caller can stream them (progress, bounded memory). A pool has one worker per core, so each worker keeps to one
BLAS/OpenMP thread (threadpoolctl, at its start) and its chunk tasks to one OpenCV thread
(:func:`bodyslam.vision.odometry.set_worker_threads`): more would only compete for the same cores.
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


def _one_thread_per_worker() -> None:
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # scikit-learn's dependency; without it BLAS keeps its default
        return
    threadpool_limits(1)


def imap_tasks(func: Callable[..., T], tasks: Sequence, jobs: int | None = None, ordered: bool = True) -> Iterator[T]:
    """``func(task)`` for every task, in order (or as they finish with ``ordered=False``); in this process when
    one job suffices, else in a spawned pool of ``jobs`` (default: one per available core) workers, closed when
    the iteration ends."""
    jobs = available_cores() if jobs is None else int(jobs)
    jobs = max(1, min(jobs, len(tasks)))
    if jobs == 1:
        yield from map(func, tasks)
        return
    with mp.get_context("spawn").Pool(jobs, initializer=_one_thread_per_worker) as pool:
        yield from (pool.imap if ordered else pool.imap_unordered)(func, tasks)
