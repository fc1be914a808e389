"""Threads for work that releases the GIL: a forest's blocks of rows, the regional stage's cuts.

Scikit-learn's trees, SciPy's sparse and graph routines and NumPy's large reductions run
without the GIL, so threads share one process's memory (the feature maps, the fitted forests)
and still run in parallel. One pool per thread count is made once per process and reused:
a segmentation asks for it hundreds of times (every landmark's forest), and starting threads
each time would cost more than the small batches gain. Work is handed out in order and
collected in order, so results do not depend on the number of threads.
"""

from __future__ import annotations

import functools
import os
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

from joblib import effective_n_jobs

__all__ = ["thread_map"]

T = TypeVar("T")
R = TypeVar("R")


def thread_map(function: Callable[[T], R], items: Iterable[T], n_jobs: int | None) -> list[R]:
    """``[function(x) for x in items]`` on up to ``n_jobs`` threads, in the items' order.

    ``n_jobs`` as in scikit-learn (None: 1; -1: every core). One item, or one job, runs on the
    calling thread. Not for nesting: ``function`` must not call :func:`thread_map` itself
    (the pool's threads would wait on work queued behind them).
    """
    items = list(items)
    workers = min(effective_n_jobs(n_jobs), len(items))
    if workers <= 1:
        return [function(item) for item in items]
    return list(_pool(workers, os.getpid()).map(function, items))


@functools.cache
def _pool(workers: int, pid: int) -> ThreadPoolExecutor:
    """``workers`` threads of the process ``pid``: a forked child makes its own (it inherits
    the parent's pool object but none of its threads, and would wait on it forever)."""
    return ThreadPoolExecutor(max_workers=workers, thread_name_prefix="medseg")
