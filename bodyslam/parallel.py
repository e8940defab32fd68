"""Chunked work over both cores: one place for the worker-pool rules the pipeline follows.

Workers are *spawned*, never forked: a child forked from a process that already runs OpenCV's (or Embree's)
thread pool can deadlock on a lock held at fork time. Results come back in task order, as they finish, so a
caller can stream them (progress, bounded memory). A pool has one worker per core, so each worker keeps to one
BLAS/OpenMP thread (``OMP/OPENBLAS/MKL_NUM_THREADS=1`` in the environment it is spawned with) and its chunk tasks
to one OpenCV thread (:func:`bodyslam.vision.odometry.set_worker_threads`): more would only compete for the same
cores. (The testbed's renderer runs its own pool: :mod:`testbed.simulate`.)

Every CLI process and every pool worker gives large freed arrays back to the system at once
(:func:`return_large_frees`): a whole exam's arrays are freed and allocated again phase after phase, and the
process's resident peak should count what it holds, not what it once held. A chunk of frames keeps what it frees
while it runs (:func:`heap_top_kept`: SIFT's scale space is not faulted in again at every detection) and gives it
back when it ends.
"""

from __future__ import annotations

import contextlib
import multiprocessing as mp
import os
import sys
from typing import Callable, Iterator, Sequence, TypeVar

__all__ = ["available_cores", "heap_top_kept", "imap_tasks", "return_large_frees", "shared_pool", "submit",
           "MMAP_THRESHOLD_BYTES"]

T = TypeVar("T")


def available_cores() -> int:
    """Cores this process may run on (its affinity set where the OS has one)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")

# glibc's malloc gives an allocation of at least its mmap threshold a mapping of its own, unmapped when freed; the
# threshold starts at 128 KiB but rises (to 32 MiB on 64-bit) to the size of each such block freed, so after the
# first whole-exam array is freed the next ones (128 KiB-32 MiB: a 55,000-frame exam's 6x6 covariances are 15 MiB)
# come from the heap, whose freed memory the process keeps and its resident peak counts. Fixed at 1 MiB (setting it
# stops the rise): a frame (320x320 RGB: 300 KiB) stays on the heap, whole-exam arrays go back when freed. Measured
# (benchmarks/bench_fusion_memory.py, session 46, the same day): the fusion's peak 180 / 358 / 537 -> 166 / 296 / 466
# MiB at 10,000 / 55,000 / 100,000 frames, its results bit-identical (docs/RESULTS.md).
MMAP_THRESHOLD_BYTES = 1 << 20
_M_MMAP_THRESHOLD = -3  # mallopt's parameter number (glibc's malloc.h)


def _glibc():
    """glibc's C library through ctypes, or None where the C library is another (or not Linux)."""
    if not sys.platform.startswith("linux"):
        return None
    import ctypes

    try:
        libc = ctypes.CDLL("libc.so.6")
        libc.gnu_get_libc_version  # glibc's, not another C library's
    except (OSError, AttributeError):
        return None
    return libc


_LARGE_FREES = False  # whether this process fixed its mmap threshold (return_large_frees)


def return_large_frees() -> bool:
    """Fix glibc's mmap threshold at :data:`MMAP_THRESHOLD_BYTES` in this process (see there). True where set;
    False where the C library is not glibc or the user set ``MALLOC_MMAP_THRESHOLD_`` (theirs is kept)."""
    global _LARGE_FREES
    if "MALLOC_MMAP_THRESHOLD_" in os.environ:
        return False
    libc = _glibc()
    _LARGE_FREES = libc is not None and bool(libc.mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES))
    return _LARGE_FREES


# Fixing the mmap threshold (above) also freezes glibc's trim threshold at its start, 128 KiB: whenever more than
# that lies free at the heap's top it goes back to the system, and the next allocation takes it again page by page.
# (A block over the mmap threshold comes from the heap's top too where the top has room; where it has not, the block
# is mapped on its own.) A SIFT detection allocates and frees its scale space every call, ~20 MiB on a 320-px frame
# and ~70 MiB at 576 px: 6,300 minor page faults a detection at 320 px, 20,600 at 576. A chunk of frames keeps what
# it frees (:func:`heap_top_kept`: up to 128 MiB kept free at the heap's top, 16 MiB of padding, blocks up to 32 MiB
# from the heap): 0 faults at either size (900 at 576 px without the last), ~20-40% off a detection's time
# (docs/RESULTS.md, sessions 80 and 81). When the chunk ends, the process's settings come back and the free heap is
# given back, so an idle worker, and the whole-exam fusion that may run on it next, start from a trimmed heap.
HEAP_MMAP_THRESHOLD_BYTES = 32 << 20  # glibc's own ceiling for its dynamic threshold on 64-bit
HEAP_TRIM_THRESHOLD_BYTES = 128 << 20
HEAP_TOP_PAD_BYTES = 16 << 20
GLIBC_TRIM_THRESHOLD_BYTES = 128 << 10  # glibc's defaults (mallopt(3)), frozen by the fixed mmap threshold
GLIBC_TOP_PAD_BYTES = 128 << 10
_M_TRIM_THRESHOLD, _M_TOP_PAD = -1, -2


@contextlib.contextmanager
def heap_top_kept() -> Iterator[bool]:
    """Inside the block, glibc serves blocks up to :data:`HEAP_MMAP_THRESHOLD_BYTES` from its heap and keeps up to
    :data:`HEAP_TRIM_THRESHOLD_BYTES` free at its top (plus :data:`HEAP_TOP_PAD_BYTES` of padding) instead of giving
    them back at once (see above); at the block's end the process's settings (:func:`return_large_frees`'s) come
    back and ``malloc_trim`` gives the free heap back. Yields whether it applied: only in a process whose mmap
    threshold :func:`return_large_frees` fixed (every CLI process and pool worker; not where the C library is not
    glibc or the user set ``MALLOC_MMAP_THRESHOLD_``), and not where the user set ``MALLOC_TRIM_THRESHOLD_`` or
    ``MALLOC_TOP_PAD_`` (theirs is kept). Results never depend on it: only page faults, time and the memory held."""
    libc = _glibc() if _LARGE_FREES and not {"MALLOC_TRIM_THRESHOLD_", "MALLOC_TOP_PAD_"} & set(os.environ) else None
    if libc is None:
        yield False
        return
    libc.mallopt(_M_MMAP_THRESHOLD, HEAP_MMAP_THRESHOLD_BYTES)
    libc.mallopt(_M_TRIM_THRESHOLD, HEAP_TRIM_THRESHOLD_BYTES)
    libc.mallopt(_M_TOP_PAD, HEAP_TOP_PAD_BYTES)
    try:
        yield True
    finally:
        libc.mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)
        libc.mallopt(_M_TRIM_THRESHOLD, GLIBC_TRIM_THRESHOLD_BYTES)
        libc.mallopt(_M_TOP_PAD, GLIBC_TOP_PAD_BYTES)
        libc.malloc_trim(0)


def _init_worker(log_level: int | None = None, log_format: str | None = None) -> None:
    """A pool worker's start. It leaves Ctrl-C to the parent (the terminal sends it to the whole process group):
    the parent stops the pool and says 'interrupted'; a worker's own KeyboardInterrupt traceback would only be
    noise. It logs as the parent does (a spawned process starts without the CLI's logging set-up: the work moved to
    workers, the whole-exam fusion among it, would otherwise say nothing under ``-v``)."""
    import logging
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    return_large_frees()
    if log_format is not None:
        logging.basicConfig(level=log_level, format=log_format)


def _parent_logging() -> tuple[int | None, str | None]:
    """The root logger's level and its first handler's format, for :func:`_init_worker` (None: not set up)."""
    import logging

    root = logging.getLogger()
    fmt = next((h.formatter._fmt for h in root.handlers if h.formatter is not None), None)
    return root.level, fmt


def _spawn_pool(jobs: int):
    # the workers read these when they load BLAS: set for the spawn only (a user's own setting is kept)
    saved = {v: os.environ.get(v) for v in _THREAD_VARS}
    for v in _THREAD_VARS:
        os.environ.setdefault(v, "1")
    try:
        return mp.get_context("spawn").Pool(jobs, initializer=_init_worker, initargs=_parent_logging())
    finally:
        for v, x in saved.items():
            if x is None:
                os.environ.pop(v, None)
            else:
                os.environ[v] = x


class _Shared:
    """The pool a :func:`shared_pool` block lends to :func:`imap_tasks`, started on first use."""

    def __init__(self, jobs: int):
        self.jobs, self.pool = jobs, None

    def get(self):
        if self.pool is None:
            self.pool = _spawn_pool(self.jobs)
        return self.pool


_SHARED: list[_Shared] = []


@contextlib.contextmanager
def shared_pool(jobs: int | None = None) -> Iterator[None]:
    """Inside the block, :func:`imap_tasks` calls with as many jobs run on one pool of ``jobs`` workers (default:
    one per core), started at the first call and stopped when the block ends (also on an error or Ctrl-C). A
    run's phases then share their workers: a pool takes ~0.4 s to start, and what a worker builds once per
    process (the visual engine) stays built."""
    shared = _Shared(available_cores() if jobs is None else int(jobs))
    _SHARED.append(shared)
    try:
        yield
    finally:
        _SHARED.pop()
        if shared.pool is not None:
            shared.pool.terminate()
            shared.pool.join()


def imap_tasks(func: Callable[..., T], tasks: Sequence, jobs: int | None = None, ordered: bool = True) -> Iterator[T]:
    """``func(task)`` for every task, in order (or as they finish with ``ordered=False``); in this process when
    one job or one task suffices, else in a spawned pool of ``jobs`` (default: one per available core) workers,
    closed when the iteration ends -- or the enclosing :func:`shared_pool`'s when it has ``jobs`` workers, however
    few the tasks."""
    want = available_cores() if jobs is None else int(jobs)
    jobs = max(1, min(want, len(tasks)))
    if jobs == 1:
        yield from map(func, tasks)
        return
    # the block's pool serves fewer tasks than it has workers too: a pool of their number, spawned for them, took
    # 0.5 s more of a 4-job batch's gap bridging on this 2-core machine (3 gaps; docs/RESULTS.md, session 60)
    if _SHARED and _SHARED[-1].jobs == want:
        pool = _SHARED[-1].get()
        yield from (pool.imap if ordered else pool.imap_unordered)(func, tasks)
        return
    with _spawn_pool(jobs) as pool:
        yield from (pool.imap if ordered else pool.imap_unordered)(func, tasks)


def submit(func: Callable[..., T], task, jobs: int | None = None) -> Callable[[], T]:
    """``func(task)`` started now on a worker of the enclosing :func:`shared_pool` when it has ``jobs`` (default:
    one per core) workers and more than one; returns ``wait()``, which gives its result (or raises what it
    raised). Without such a pool the call runs in this process when waited for."""
    jobs = available_cores() if jobs is None else int(jobs)
    if jobs > 1 and _SHARED and _SHARED[-1].jobs == jobs:
        return _SHARED[-1].get().apply_async(func, (task,)).get
    return lambda: func(task)
