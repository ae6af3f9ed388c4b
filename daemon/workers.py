"""Process pools for the pipeline's independent per-track work (the pipeline itself starts no workers).

calibrate(..., map_fn=...) fits one hypothesis per image track; on a 2-core RSU a pool of two processes
nearly halves that stage, which dominates a long recording. Results are identical to plain `map`.
"""

from __future__ import annotations

import multiprocessing
import os
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ProcessPoolExecutor
from contextlib import contextmanager
from typing import Any

MapFn = Callable[..., Iterable[Any]]


def _one_blas_thread() -> None:
    """Worker start-up: the per-track fits are tiny; BLAS threads would only fight over the cores."""
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=1)


@contextmanager
def track_pool(workers: int | None = None, chunksize: int = 8) -> Iterator[MapFn]:
    """A map function backed by `workers` processes (default: the machine's cores); plain map for 1."""
    count = workers if workers is not None else (os.cpu_count() or 1)
    if count <= 1:
        yield map
        return
    # fork: workers start in milliseconds and share the parent's loaded modules; the callers (CLI, bench,
    # the daemon's job process) create the pool before any thread of their own exists.
    context = multiprocessing.get_context("fork")
    with ProcessPoolExecutor(max_workers=count, mp_context=context, initializer=_one_blas_thread) as pool:

        def pool_map(fn: Callable[..., Any], *iterables: Iterable[Any]) -> Iterable[Any]:
            return pool.map(fn, *iterables, chunksize=chunksize)

        yield pool_map
