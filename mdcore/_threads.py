"""Keep BLAS single-threaded inside mdcore's numerical entry points.

The core works on many small matrices (13–100 rows). On a 2-core machine OpenBLAS's own
threads make such calls an order of magnitude slower (measured: an emulator fit took 4.2 s
with default BLAS threading and 0.30 s single-threaded), so the entry points limit BLAS to
one thread and parallelise over chunks themselves where that pays (:mod:`mdcore.gp`).
"""

from __future__ import annotations

import functools
import threading

from threadpoolctl import ThreadpoolController

_controller: ThreadpoolController | None = None
_lock = threading.Lock()


def _get_controller() -> ThreadpoolController:
    global _controller
    with _lock:
        if _controller is None:
            _controller = ThreadpoolController()
        return _controller


def single_threaded_blas(fn):
    """Decorator: run ``fn`` with BLAS limited to one thread (restored afterwards)."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with _get_controller().limit(limits=1, user_api="blas"):
            return fn(*args, **kwargs)

    return wrapper
