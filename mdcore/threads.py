"""Keep BLAS single-threaded inside mdcore's numerical entry points, safely across threads.

The core works on many small matrices (13–100 rows). On a 2-core machine OpenBLAS's own
threads make such calls an order of magnitude slower (measured: an emulator fit took 4.2 s
with default BLAS threading and 0.30 s single-threaded), so the entry points limit BLAS to
one thread and parallelise over chunks themselves where that pays (:mod:`mdcore.linalg`).

The BLAS thread count is a process-wide setting, and threadpoolctl's ``limit`` context is
not safe when two threads (two app sessions, two jobs) enter and leave it interleaved: the
one that leaves last restores what the first one set, and the process can stay at one
thread for good. So the limit is reference-counted under a lock: the first caller in saves
the original setting and sets one thread, nested and concurrent callers only count, and
the last one out restores the original.

A program that owns its process (the app server, the command line) calls
:func:`single_threaded_blas_for_process` once at start instead. Between the entry points, the
restored two-thread BLAS wakes OpenBLAS's worker thread on every call from other code (the
app's plots, Bokeh, SciPy's optimiser), and that thread then spins for about 0.1 s: measured
in the served app, two OpenBLAS workers burned 3.9 CPU-s of a 5.9 s shear-5 wave and made
its emulator fit (``eigh``) five times slower; with the process-wide limit the wave took
2.7 s and 1.1 CPU-s. Two BLAS threads bought no wall time on these matrix sizes.
"""

from __future__ import annotations

import functools
import sys
import threading

from threadpoolctl import ThreadpoolController

_lock = threading.Lock()
_depth = 0
_saved: list = []          # threadpoolctl's limiters to restore, held while _depth > 0
_controller: ThreadpoolController | None = None
_scanned_modules = 0
_process_wide = False      # set by single_threaded_blas_for_process: never restore two threads


def _enter() -> None:
    global _depth, _controller, _scanned_modules
    with _lock:
        if _depth == 0:
            # A scan of the loaded libraries costs 4–15 ms, a limit 0.4 ms, and a small
            # reproduce enters ~100 times: scan again only when modules were imported since
            # the last scan (one of them may have loaded another BLAS).
            if _controller is None or len(sys.modules) != _scanned_modules:
                _controller = ThreadpoolController()
                _scanned_modules = len(sys.modules)
            _saved.append(_controller.limit(limits=1, user_api="blas"))
        _depth += 1


def _exit() -> None:
    global _depth
    with _lock:
        _depth -= 1
        if _depth == 0:
            limiter = _saved.pop()
            if not _process_wide:
                limiter.restore_original_limits()


def single_threaded_blas_for_process() -> None:
    """Limit every BLAS library loaded so far to one thread, for the whole process.

    For programs that own their process (``panel serve app/main.py``, ``python -m
    mdcore``); a library import never calls it. Call it from the main thread after the
    imports that load BLAS (NumPy, SciPy). Idempotent (a second call only scans again if
    modules were imported since); it is not undone: :func:`single_threaded_blas` sections,
    even one that began before the call, then leave BLAS at one thread.
    """
    global _controller, _scanned_modules, _process_wide
    with _lock:
        if _process_wide and len(sys.modules) == _scanned_modules:
            return
        _process_wide = True
        _controller = ThreadpoolController()
        _scanned_modules = len(sys.modules)
        _controller.limit(limits=1, user_api="blas")


def single_threaded_blas(fn):
    """Decorator: run ``fn`` with BLAS limited to one thread (restored by the last caller)."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        _enter()
        try:
            return fn(*args, **kwargs)
        finally:
            _exit()

    return wrapper
