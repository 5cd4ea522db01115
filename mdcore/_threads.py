"""mdcore's one thread policy: one process-wide pool of compute threads, BLAS at one thread.

On the core's small matrices (13–100 rows) threads pay over independent pieces of work, while
a second BLAS thread only spins. The BLAS limit is never undone: another thread relies on it.
"""

from __future__ import annotations

import functools
import os
import sys
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

__all__ = ["THREADS_ENV", "cores", "num_threads", "run_pieces", "single_threaded_blas",
           "single_threaded_blas_for_process"]

#: Environment variable limiting the compute threads of mdcore (a positive integer).
THREADS_ENV = "MDCORE_NUM_THREADS"

_lock = threading.Lock()
_pool: dict[int, ThreadPoolExecutor] = {}  # the process's pool (by size), made on first use
_in_pool = threading.local()
_blas_modules = -1                         # len(sys.modules) when BLAS was last limited

if hasattr(os, "register_at_fork"):          # a forked child has none of the pool's threads
    os.register_at_fork(after_in_child=_pool.clear)


def cores() -> int:
    """Cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:            # not on Linux
        return os.cpu_count() or 1


def num_threads() -> int:
    """Compute threads: ``MDCORE_NUM_THREADS`` (a positive integer) if set, else every core."""
    raw = os.environ.get(THREADS_ENV, "").strip()
    if not raw:
        return cores()
    try:
        n = int(raw)
    except ValueError:
        n = 0
    if n < 1:
        raise ValueError(f"{THREADS_ENV} must be a positive integer (the number of compute "
                         f"threads); received {raw!r}. Unset it to use every core.")
    return n


def _mark_pool_thread() -> None:
    _in_pool.active = True


def run_pieces(work: Callable, pieces: list) -> list:
    """``[work(*piece) for piece in pieces]`` on the compute threads; in the calling thread
    for one piece, one thread, or a call from a pool thread (it would wait on itself)."""
    n = num_threads()
    if len(pieces) <= 1 or n == 1 or getattr(_in_pool, "active", False):
        return [work(*p) for p in pieces]
    with _lock:
        if n not in _pool:                     # a new MDCORE_NUM_THREADS replaces the pool
            for old in _pool.values():
                old.shutdown(wait=False)
            _pool.clear()
            _pool[n] = ThreadPoolExecutor(n, thread_name_prefix="mdcore",
                                          initializer=_mark_pool_thread)
        pool = _pool[n]
    return [f.result() for f in [pool.submit(work, *p) for p in pieces]]


def single_threaded_blas_for_process() -> None:
    """Limit every BLAS library loaded so far to one thread, for the whole process; cheap
    when repeated (a new scan only if modules were imported since: one may load a BLAS)."""
    global _blas_modules
    if len(sys.modules) == _blas_modules:
        return
    from threadpoolctl import threadpool_limits

    with _lock:
        _blas_modules = len(sys.modules)
        threadpool_limits(limits=1, user_api="blas")


def single_threaded_blas(fn):
    """Decorator of the numerical entry points: BLAS at one thread (for good) before ``fn``."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        single_threaded_blas_for_process()
        return fn(*args, **kwargs)

    return wrapper
