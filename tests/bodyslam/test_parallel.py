"""The worker pool (bodyslam.parallel)."""

import os

from bodyslam.parallel import imap_tasks


def blas_threads(_):
    import numpy  # noqa: F401 -- loads BLAS
    from threadpoolctl import threadpool_info

    return sorted({i["num_threads"] for i in threadpool_info() if i.get("user_api") in ("blas", "openmp")})


def test_pool_workers_keep_to_one_blas_thread_and_the_parent_is_untouched():
    before = {v: os.environ.get(v) for v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")}
    got = list(imap_tasks(blas_threads, [0, 1], jobs=2))
    assert got == [[1], [1]], got  # (this process: one per core)
    assert {v: os.environ.get(v) for v in before} == before
    assert list(imap_tasks(lambda x: x * 2, [1, 2, 3], jobs=1)) == [2, 4, 6]  # one job: in this process
