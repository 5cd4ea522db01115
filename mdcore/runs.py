"""Simulator runs: batched over any ``concurrent.futures`` executor, with failures dropped.

Real simulators are expensive and sometimes fail for part of the parameter box: they raise,
hang, or return NaN. :func:`run_simulator` runs ``simulate(X, θ)`` for a set of θ, in
batches submitted to an executor (serially in this process by default), and returns the
outputs of the runs that succeeded, in their original order, together with the runs that
failed and why. A batch that raises is re-run one θ at a time, so one bad θ costs only its
own run. The caller decides how many failures are acceptable (history matching:
:attr:`mdcore.history_matching.HistoryMatchProblem.max_failed_fraction`).

Any ``concurrent.futures.Executor`` works, including a Dask client's ``get_executor()``;
the numbers do not depend on the executor, because results are assembled in θ order.

Examples
--------
>>> import numpy as np
>>> def simulate(X, theta):        # fails where θ < 0
...     if np.any(theta < 0):
...         raise ValueError("negative stiffness")
...     return np.sqrt(theta)[:, None, :] * np.ones((1, len(X), 1))
>>> out = run_simulator(simulate, np.zeros((2, 1)), np.array([[1.0], [-1.0], [4.0]]), 1)
>>> out.ok.tolist(), out.y[:, 0, 0].tolist(), out.failures[0].message
([True, False, True], [1.0, 2.0], 'ValueError: negative stiffness')
"""

from __future__ import annotations

import concurrent.futures
from collections.abc import Callable
from concurrent.futures import Executor
from typing import NamedTuple

import numpy as np

from .validation import as_float_array, as_int

__all__ = ["Failure", "Runs", "run_simulator"]


class Failure(NamedTuple):
    """A simulator run that failed.

    Attributes
    ----------
    theta : ndarray of shape (p,)
    message : str
        What went wrong ("ValueError: …", "timed out after 5 s", "returned NaN or inf").
    """

    theta: np.ndarray
    message: str


class Runs(NamedTuple):
    """Result of :func:`run_simulator`.

    Attributes
    ----------
    y : ndarray of shape (R_ok, N, n_out)
        Outputs of the runs that succeeded, in θ order.
    ok : ndarray of bool, shape (R,)
        Which θ succeeded.
    failures : tuple of Failure
        The runs that failed, in θ order.
    """

    y: np.ndarray
    ok: np.ndarray
    failures: tuple


def _call(simulate: Callable, X: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """Run one batch (module level, so process and Dask executors can pickle it)."""
    return np.asarray(simulate(X, theta), dtype=np.float64)


def _in_own_thread(simulate: Callable, X: np.ndarray, theta: np.ndarray,
                   timeout: float) -> np.ndarray:
    """One batch on a thread of its own, so that waiting for it can end after ``timeout``
    (a thread cannot be killed: a run that hangs is abandoned, not stopped)."""
    pool = concurrent.futures.ThreadPoolExecutor(max_workers=1)
    try:
        return pool.submit(_call, simulate, X, theta).result(timeout=timeout)
    finally:
        pool.shutdown(wait=False, cancel_futures=True)


def run_simulator(simulate: Callable, X, theta, n_out: int, *,
                  executor: Executor | None = None, batch_size: int | None = None,
                  timeout: float | None = None) -> Runs:
    """Run ``simulate(X, θ)`` for every row of ``theta``, dropping the runs that fail.

    Parameters
    ----------
    simulate : callable
        ``simulate(X, theta) -> (n_theta, N, n_out)``.
    X : ndarray of shape (N, d_x)
    theta : ndarray of shape (R, p)
    n_out : int
        Outputs per input.
    executor : concurrent.futures.Executor, optional
        Runs the batches; default: in this process, one after the other.
    batch_size : int, optional
        θ per submitted batch (default: all at once without an executor, one per task with
        one).
    timeout : float, optional
        Seconds to wait for one batch; a batch that takes longer is abandoned and its runs
        count as failed (the work itself may still finish in the background). Without an
        executor each batch gets a thread of its own; with one, the wait starts when the
        batch's result is awaited, so give the executor room for a hanging run.

    Returns
    -------
    Runs

    Raises
    ------
    ValueError
        When ``simulate`` returns an array of the wrong shape: that is a wrong simulator,
        not a failed run.
    """
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
        timeout = float(timeout)
        if not timeout > 0:
            raise ValueError(f"timeout must be a positive number of seconds; received "
                             f"{timeout!r}.")
    want = (X.shape[0], n_out)
    y = np.empty((R,) + want)
    ok = np.zeros(R, dtype=bool)
    messages: dict[int, str] = {}

    def collect(idx: np.ndarray, get: Callable[[], np.ndarray]) -> None:
        try:
            out = get()
        except concurrent.futures.TimeoutError:
            for i in idx:
                messages[int(i)] = f"timed out after {timeout:g} s"
            return
        except Exception as exc:                              # a failing simulator run
            if len(idx) > 1:                                   # isolate the bad θ
                for i in idx:
                    collect(np.array([i]), run(np.array([i])))
                return
            messages[int(idx[0])] = f"{type(exc).__name__}: {exc}"
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
        return lambda: _in_own_thread(simulate, X, theta[idx], timeout)

    batches = [np.arange(s, min(R, s + batch_size)) for s in range(0, R, batch_size)]
    waits = [run(idx) for idx in batches]                     # submit all, then wait in order
    for idx, wait in zip(batches, waits):
        collect(idx, wait)
    failures = tuple(Failure(theta[i].copy(), messages[i]) for i in sorted(messages))
    return Runs(y[ok], ok, failures)
