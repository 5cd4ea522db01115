"""mdcore's one thread policy: one pool of compute threads and one BLAS thread.

The core works on many small matrices (13–100 rows). Threads pay over independent pieces of
work (chunks of pairs, of candidates), not inside one BLAS call: on such sizes a second BLAS
thread only spins. So:

- :func:`run_pieces` runs pieces on one process-wide pool of :func:`num_threads` threads
  (``MDCORE_NUM_THREADS``, default every core). Every caller, NumPy chunks and compiled
  kernels alike, queues on the same pool, so the process never runs more compute threads
  than that, and concurrent calls (app sessions, jobs) take turns piece by piece.
- :func:`single_threaded_blas_for_process` limits BLAS to one thread for the whole process,
  once. The numerical entry points call it (through :func:`single_threaded_blas`) on first
  use; a program that owns its process (the app, the command line) calls it at start.
  The limit is never undone: undoing a process-wide setting is not safe while another
  thread still relies on it.
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


def _forget_pool_after_fork() -> None:
    """A forked child has none of the pool's threads: it starts a new pool on first use."""
    _pool.clear()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_pool_after_fork)


def cores() -> int:
    """Cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:            # not on Linux
        return os.cpu_count() or 1


def num_threads() -> int:
    """Compute threads: ``MDCORE_NUM_THREADS`` if set, else every core.

    Raises
    ------
    ValueError
        If ``MDCORE_NUM_THREADS`` is set to anything but a positive integer.
    """
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
    """``[work(*piece) for piece in pieces]``, on the process's compute threads.

    A single piece, one compute thread, or a call from a pool thread (nested work would
    wait on itself) runs in the calling thread. ``work`` must release the GIL to gain
    anything (NumPy's loops, LAPACK and the compiled kernels do).
    """
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
    """Limit every BLAS library loaded so far to one thread, for the whole process.

    Idempotent and cheap: it scans the loaded libraries again only when modules were
    imported since the last call (one of them may have loaded another BLAS).
    """
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
