"""A small thread pool that runs GIL-free numba kernels over chunks of an index range.

Chosen over ``@njit(parallel=True)`` by measurement: each parallel kernel cost another 3-5 s of
first (uncached) compile on this machine for its gufunc wrapper, and a shared counter of chunks
balances uneven tiles dynamically. It also keeps numba's OpenMP/TBB runtime out of processes that
already run torch's.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any

_lock = threading.Lock()
_pool: ThreadPoolExecutor | None = None
_pool_pid = 0  # a pool does not survive fork(): a child process makes its own
_threads = 0

CHUNKS_PER_THREAD = 4
"""Chunks per worker: enough to even out unequal tiles, few enough that dispatch stays ~0.1 ms."""


def default_threads() -> int:
    """Cores this process may use (``ACESPLAT_RASTER_THREADS`` overrides)."""
    env = os.environ.get("ACESPLAT_RASTER_THREADS")
    if env:
        return max(1, int(env))
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return max(1, os.cpu_count() or 1)


def set_num_threads(n: int | None) -> None:
    """Use ``n`` threads for the rasterizer, the caller included (None: all available cores)."""
    global _pool, _threads
    n = default_threads() if n is None else int(n)
    if n < 1:
        raise ValueError(f"need at least one thread, got {n}")
    with _lock:
        if _pool is not None and _pool_pid == os.getpid():
            _pool.shutdown(wait=True)
        _pool = None
        _threads = n


def get_num_threads() -> int:
    return _threads or default_threads()


def parallel_for(kernel: Callable[..., Any], n: int, *args: Any) -> None:
    """Run ``kernel(lo, hi, *args)`` over chunks covering range(n), in parallel; return when all are done.

    The calling thread works too and every thread takes the next chunk from a shared counter, so
    on a busy machine a worker that the OS wakes late finds nothing left and nobody waits for it:
    the call returns as soon as every chunk is finished. Results must not depend on the chunking:
    kernels write disjoint outputs.
    """
    global _pool, _pool_pid
    threads = get_num_threads()
    if n <= 0:
        return
    if threads == 1 or n == 1:
        kernel(0, n, *args)
        return
    chunks = min(n, threads * CHUNKS_PER_THREAD)
    bounds = [n * c // chunks for c in range(chunks + 1)]
    state = {"next": 0, "done": 0}
    errors: list[BaseException] = []
    take = threading.Lock()
    finished = threading.Event()

    def work() -> None:
        while True:
            with take:
                c = state["next"]
                if c >= chunks:
                    return
                state["next"] = c + 1
            try:
                kernel(bounds[c], bounds[c + 1], *args)
            except BaseException as e:  # re-raised in the caller
                errors.append(e)
            with take:
                state["done"] += 1
                if state["done"] == chunks:
                    finished.set()

    with _lock:
        if _pool is None or _pool_pid != os.getpid():
            _pool = ThreadPoolExecutor(max_workers=threads - 1, thread_name_prefix="acesplat-raster")
            _pool_pid = os.getpid()
        pool = _pool
    for _ in range(threads - 1):
        pool.submit(work)
    work()
    finished.wait()
    if errors:
        raise errors[0]
