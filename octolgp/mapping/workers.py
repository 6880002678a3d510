"""Where an online map's leaf fits run: a thread pool over leaves, BLAS held to one thread.

Leaf GPs are small matrices, so parallelism is over leaves, not inside BLAS.
"""

from __future__ import annotations

import functools
import gc
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from typing import Any

from threadpoolctl import ThreadpoolController


@functools.cache
def blas_controller() -> ThreadpoolController:
    """The process's BLAS libraries, found once (finding them is the slow part of a limit)."""
    return ThreadpoolController()


class Workers:
    """A map's fitting threads, started on first use.

    Parameters
    ----------
    n_jobs : int
        Threads fitting leaves (1: fit on the calling thread).
    """

    def __init__(self, n_jobs: int) -> None:
        self.n_jobs = n_jobs
        self._pool: ThreadPoolExecutor | None = None

    def pool(self, n_tasks: int) -> ThreadPoolExecutor | None:
        """The thread pool when ``n_jobs > 1`` and there is more than one task."""
        if self.n_jobs <= 1 or n_tasks < 2:
            return None
        if self._pool is None:
            self._pool = ThreadPoolExecutor(max_workers=self.n_jobs)
        return self._pool

    def one_blas_thread(self) -> Any:
        """A context in which BLAS runs on one thread."""
        return blas_controller().limit(limits=1)

    def close(self) -> None:
        """Stop the threads (a later fit starts them again)."""
        if self._pool is not None:
            self._pool.shutdown()
            self._pool = None


@contextmanager
def collector_paused() -> Iterator[None]:
    """A context in which Python's cyclic garbage collector does not run by itself.

    A step allocates tens of thousands of small acyclic objects (leaves, their arrays'
    headers, tuples), which reference counting frees. Each allocation burst would
    otherwise trigger full collections that walk every leaf of the map (a fifth of a
    64-ring street insert). The collector's state is restored on exit, and it runs at
    the next allocation past its threshold as usual.
    """
    was_enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was_enabled:
            gc.enable()
