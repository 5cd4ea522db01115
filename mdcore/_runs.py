"""Simulator runs: batched over any ``concurrent.futures`` executor, with failures dropped.

Real simulators raise, hang or return NaN for parts of the parameter box. A batch that
raises is re-run one θ at a time, so one bad θ costs only its own run; results are assembled
in θ order, so the numbers do not depend on the executor (a Dask client's ``get_executor()``
included).
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import os
import pickle
import queue
import subprocess
import sys
import threading
import time
import weakref
from collections.abc import Callable
from concurrent.futures import Executor
from pathlib import Path
from typing import NamedTuple

import numpy as np

from ._validation import as_float_array, as_int, as_positive_float


class Failure(NamedTuple):
    """A failed run: ``theta`` (p,) and what went wrong (``"ValueError: …"``, ``"timed out
    after 5 s"``, ``"returned NaN or inf"``)."""

    theta: np.ndarray
    message: str


class Runs(NamedTuple):
    """Result of :func:`run_simulator`: outputs ``y`` (R_ok, N, n_out) of the runs that
    succeeded, which θ did (``ok``, bool (R,)) and the ``failures``, all in θ order."""

    y: np.ndarray
    ok: np.ndarray
    failures: tuple


def _call(simulate: Callable, X: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """Run one batch (module level, so process and Dask executors can pickle it)."""
    try:
        return np.asarray(simulate(X, theta), dtype=np.float64)
    except SystemExit as exc:                 # not the end of the program: a failed run
        raise SimulatorError(f"the simulator called sys.exit({exc.code!r})") from None


def call_with_timeout(simulate: Callable, X: np.ndarray, theta: np.ndarray,
                      timeout: float) -> np.ndarray:
    """One batch on a thread of its own; ``TimeoutError`` after ``timeout`` seconds (the run
    is abandoned, not stopped: :class:`SimulatorProcess` stops it)."""
    pool = concurrent.futures.ThreadPoolExecutor(max_workers=1)
    try:
        return pool.submit(_call, simulate, X, theta).result(timeout=timeout)
    except concurrent.futures.TimeoutError:
        raise TimeoutError(f"timed out after {timeout:g} s") from None
    finally:
        pool.shutdown(wait=False, cancel_futures=True)


class SimulatorError(RuntimeError):
    """A simulator run in a :class:`SimulatorProcess` raised, exited or could not start."""


#: The worker of :class:`SimulatorProcess` (``python -c``): imports only the simulator's
#: module, answers each pickled (X, θ) with a pickled result, ends when its parent does.
_WORKER = r"""
import os, pickle, sys, threading, time
out = os.fdopen(os.dup(1), "wb")
os.dup2(2, 1)                                   # the simulator's prints go to stderr
sys.dont_write_bytecode = True                  # no __pycache__ beside the user's module
parent = os.getppid()

def orphaned():                                 # the parent was killed: do not linger
    while os.getppid() == parent:
        time.sleep(0.5)
    os._exit(1)

threading.Thread(target=orphaned, daemon=True).start()

def send(*message):
    pickle.dump(message, out)
    out.flush()

module, function, path = pickle.load(sys.stdin.buffer)
sys.path[:] = path
try:
    import importlib
    fn = getattr(importlib.import_module(module), function, None)
except BaseException as exc:
    send("failed", f"cannot import module {module!r} ({type(exc).__name__}: {exc}); set "
         "[simulator] path to the folder that contains it")
    sys.exit()
if not callable(fn):
    send("failed", f"module {module!r} has no function {function!r}")
    sys.exit()
send("ready", None)
while True:
    try:
        X, theta = pickle.load(sys.stdin.buffer)
    except EOFError:
        break
    try:
        import numpy
        send("ok", numpy.asarray(fn(X, theta), dtype=numpy.float64))
    except SystemExit as exc:
        send("exit", f"the simulator called sys.exit({exc.code!r}), which ends its process")
        break
    except BaseException as exc:
        send("error", f"{type(exc).__name__}: {exc}")
"""


class SimulatorProcess:
    """``module.function`` (imported from ``folder``, first on the path) run in a child
    process of its own, so that a hanging import or run cannot stop this one.

    A call past ``timeout`` kills the process and raises ``TimeoutError`` (the next call starts
    another); a raise, ``sys.exit`` or crash raises :class:`SimulatorError`, a failed import
    ``ImportError``. Threads take turns. Pickled (process pool, Dask) it travels as the
    function by value (cloudpickle), with the modules of ``folder``.
    """

    def __init__(self, module: str, function: str, folder=None):
        self.module, self.function = module, function
        self.folder = None if folder is None else str(folder)
        self._lock = threading.Lock()
        self._proc: subprocess.Popen | None = None
        self._answers: queue.Queue = queue.Queue()
        self._shipped: bytes | None = None          # the function by value, once pickled

    def __repr__(self) -> str:
        where = "" if self.folder is None else f" from {self.folder}"
        return f"SimulatorProcess({self.module}:{self.function}{where})"

    def __call__(self, X, theta, timeout: float | None = None) -> np.ndarray:
        """``simulate(X, θ)`` in the process; ``timeout`` in seconds from the call (None: no
        limit)."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._lock:
            if self._proc is None:
                self._start()
                self._answer(deadline, timeout)               # "ready", or why not
            self._send((np.asarray(X), np.asarray(theta)))
            return self._answer(deadline, timeout)

    def _send(self, message) -> None:
        stdin = None if self._proc is None else self._proc.stdin
        if stdin is not None:
            with contextlib.suppress(OSError):    # it ended; its answer says how
                pickle.dump(message, stdin)
                stdin.flush()

    def _start(self) -> None:
        proc = subprocess.Popen([sys.executable, "-c", _WORKER], stdin=subprocess.PIPE,
                                stdout=subprocess.PIPE)
        self._proc, self._answers = proc, queue.Queue()
        self._stop = weakref.finalize(self, _stop, proc)      # at exit too
        path = ([self.folder] if self.folder else []) + [os.getcwd() if p == "" else p
                                                        for p in sys.path]
        self._send((self.module, self.function, path))

        def read(answers=self._answers, stream=proc.stdout):
            try:
                while True:
                    answers.put(pickle.load(stream))
            except Exception:                                 # EOF: the process ended
                answers.put(None)

        # Not "mdcore-…", which names the app's job threads (app/jobs.py).
        threading.Thread(target=read, daemon=True, name="simulator-reader").start()

    def _answer(self, deadline: float | None, timeout: float | None):
        """The process's next value; raises for an error, an exit or an ended process."""
        try:
            answer = self._answers.get(
                timeout=None if deadline is None else max(deadline - time.monotonic(), 0.0))
        except queue.Empty:
            self.close()
            raise TimeoutError(f"timed out after {timeout:g} s") from None
        kind, value = ("ended", None) if answer is None else answer
        if kind in ("ready", "ok"):
            return value
        if kind != "error":                   # it ended: the next call starts another
            code = self.close()
            if kind == "failed":
                raise ImportError(value)
            value = value or (f"the simulator's process ended (exit code {code}) without an "
                              "answer: it crashed or was killed")
        raise SimulatorError(value)

    def close(self) -> int | None:
        """Stop the process and return its exit code; from another thread this cancels the
        running call, which raises :class:`SimulatorError`."""
        proc, self._proc = self._proc, None
        return None if proc is None else self._stop()

    def __reduce__(self):
        try:
            import cloudpickle
        except ImportError:            # a local process pool: the worker imports it itself
            return _import_function, (self.module, self.function, self.folder)
        if self._shipped is None:
            self._shipped = cloudpickle.dumps(self._function_by_value())
        return cloudpickle.loads, (self._shipped,)

    def _function_by_value(self) -> Callable:
        """The function, its module and those from its folder registered to pickle by value."""
        import cloudpickle
        fn = _import_function(self.module, self.function, self.folder)
        top = sys.modules[self.module.split(".")[0]]
        ours = [top] + [m for m in list(sys.modules.values()) if self.folder
                        and Path(getattr(m, "__file__", None) or "/").resolve()
                        .is_relative_to(self.folder)]
        for m in ours:
            if m.__name__ not in cloudpickle.list_registry_pickle_by_value():
                cloudpickle.register_pickle_by_value(m)
        return fn


def _stop(proc: subprocess.Popen) -> int:
    """Kill a :class:`SimulatorProcess`'s process and close its pipes; its exit code."""
    proc.kill()
    code = proc.wait()
    for stream in (proc.stdin, proc.stdout):
        if stream is not None:
            stream.close()
    return code


def _import_function(module: str, function: str, folder: str | None) -> Callable:
    """``module.function``, imported in this process with ``folder`` first on the path."""
    import importlib
    path = list(sys.path)
    sys.path[:0] = [folder] if folder else []
    try:
        return getattr(importlib.import_module(module), function)
    finally:
        sys.path[:] = path


def run_simulator(simulate: Callable, X, theta, n_out: int, *,
                  executor: Executor | None = None, batch_size: int | None = None,
                  timeout: float | None = None) -> Runs:
    """``simulate(X, θ)`` (n_θ, N, n_out) for every row of ``theta`` (R, p), in batches of
    ``batch_size`` θ (default: all, or one per task on an ``executor``), dropping the runs that
    fail or outlast ``timeout`` seconds (from when a batch is awaited). A wrong output shape is
    a wrong simulator, not a failed run: ValueError."""
    if not callable(simulate):
        raise ValueError(f"simulate must be callable (X, theta) -> (n_theta, N, n_out); "
                         f"received {type(simulate).__name__}.")
    X = as_float_array(X, "X", ndim=2)
    theta = as_float_array(theta, "theta", ndim=2, allow_empty=True)
    n_out = as_int(n_out, "n_out", 1)
    R = theta.shape[0]
    if batch_size is None:
        batch_size = max(R, 1) if executor is None else 1
    batch_size = as_int(batch_size, "batch_size", 1)
    if timeout is not None:
        timeout = as_positive_float(timeout, "timeout", "Give seconds per batch of runs.")
    want = (X.shape[0], n_out)
    y = np.empty((R,) + want)
    ok = np.zeros(R, dtype=bool)
    messages: dict[int, str] = {}

    def collect(idx: np.ndarray, get: Callable[[], np.ndarray]) -> None:
        try:
            out = get()
        except TimeoutError as exc:           # the batch is abandoned, its runs failed
            for i in idx:
                messages[int(i)] = str(exc) or f"timed out after {timeout:g} s"
            return
        except Exception as exc:                              # a failing simulator run
            if len(idx) > 1:                                   # isolate the bad θ
                for i in idx:
                    collect(np.array([i]), run(np.array([i])))
                return
            messages[int(idx[0])] = str(exc) if isinstance(exc, SimulatorError) \
                else f"{type(exc).__name__}: {exc}"           # the process says which error
            return
        if out.shape != (len(idx),) + want:
            raise ValueError(f"simulate(X, theta) must return shape (n_theta, N, n_out) = "
                             f"{(len(idx),) + want}; it returned {out.shape}.")
        finite = np.all(np.isfinite(out), axis=(1, 2))
        y[idx], ok[idx] = out, finite
        for i in idx[~finite]:
            messages[int(i)] = "returned NaN or inf"

    def run(idx: np.ndarray) -> Callable[[], np.ndarray]:
        """Start a batch (with an executor); return a function that waits for its result."""
        if executor is not None:
            future = executor.submit(_call, simulate, X, theta[idx])
            return lambda: future.result(timeout=timeout)
        if timeout is None:
            return lambda: _call(simulate, X, theta[idx])
        return lambda: call_with_timeout(simulate, X, theta[idx], timeout)

    batches = [np.arange(s, min(R, s + batch_size)) for s in range(0, R, batch_size)]
    waits = [run(idx) for idx in batches]                     # submit all, then wait in order
    for idx, wait in zip(batches, waits):
        collect(idx, wait)
    failures = tuple(Failure(theta[i].copy(), messages[i]) for i in sorted(messages))
    return Runs(y[ok], ok, failures)
