"""Long work of one app session: progress, supersession, cancel, and failures that never
leave the session busy.

A job is ``compute(report, cancel)``, a generator of partial results that runs on a worker
thread (or inline when ``background=False``, for tests and scripts), and ``apply(partial)``,
which puts each partial result into the session's state on the session's thread (through
``schedule``). :class:`JobRunner` runs one job at a time per session:

* **Progress.** ``report(fraction, message="")`` forwards at most about four updates a
  second to ``on_progress`` (every re-render reaches the browser).
* **Supersession.** Submitting a job retires the running one: its ``cancel`` event is set
  (so the pipeline stops at its next chunk, see :func:`mdcore.run_method`) and
  nothing it yields or raises afterwards reaches the state.
* **Cancel.** :meth:`JobRunner.cancel` sets the running job's event; the work raises
  :class:`mdcore.Cancelled` and the job ends quietly, keeping what it already
  applied (each applied partial result is a consistent state).
* **Failure.** Any ``Exception`` from ``compute`` or from ``apply`` ends the job: the
  state is restored from the snapshot taken when the job was submitted (so partial
  results of a failed job never disagree with the status), busy is cleared, and the
  message goes to ``on_error`` once.

The runner knows nothing of Panel or param: the session wires it to its state with the
``on_*``, ``snapshot`` and ``restore`` callbacks.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

from mdcore._exceptions import Cancelled

__all__ = ["PROGRESS_INTERVAL", "Cancelled", "Job", "JobRunner"]

#: Seconds between progress updates sent to the browser (unless the fraction jumps ≥ 0.1).
PROGRESS_INTERVAL = 0.25

#: ``report(fraction, message="")``: fraction done in [0, 1] and what is running.
Report = Callable[..., None]
#: ``compute(report, cancel)``: yields partial results for ``apply``.
Compute = Callable[[Report, threading.Event], Iterator[Any]]

log = logging.getLogger(__name__)


def _noop(*_args) -> None:
    return None


class Job:
    """One submitted job: its label, its cancel event and how it ended.

    Attributes
    ----------
    label : str
        Shown while the job runs ("wave", "discrepancy").
    cancel : threading.Event
        Set by :meth:`JobRunner.cancel`, by a newer submission and by a failure; the work
        checks it between chunks.
    status : str
        ``"running"``, then one of ``"done"``, ``"failed"``, ``"cancelled"`` or
        ``"superseded"``.
    error : BaseException or None
        What a failed job raised.
    """

    def __init__(self, label: str, snapshot: Any):
        self.label = label
        self.cancel = threading.Event()
        self.status = "running"
        self.error: BaseException | None = None
        self.snapshot = snapshot
        #: Set once the job has ended (done, cancelled, failed or dropped).
        self.ended = threading.Event()

    @property
    def running(self) -> bool:
        return self.status == "running"

    def wait(self, timeout: float | None = None) -> bool:
        """Block until the worker has finished with this job; False on timeout.

        In background mode the last state change is delivered through ``schedule``, so
        this returns once that callback has run.
        """
        return self.ended.wait(timeout)

    def __repr__(self) -> str:
        return f"Job({self.label!r}, status={self.status!r})"


class JobRunner:
    """Runs one session's jobs, one at a time, newest first.

    Parameters
    ----------
    background : bool, default=False
        Run ``compute`` on a daemon thread (the served app) or inline (tests, scripts).
    schedule : callable, optional
        ``schedule(fn)`` runs ``fn`` on the session's thread (the served app: the Bokeh
        document's next tick). Default: call it at once.
    on_start : callable, optional
        ``on_start(label)`` when a job is submitted (show busy).
    on_progress : callable, optional
        ``on_progress(fraction, message)``, throttled to about 1 / ``interval`` per second.
    on_finish : callable, optional
        ``on_finish()`` when the newest job ends for any reason (clear busy).
    on_error : callable, optional
        ``on_error(message)`` once per failed job (one notification).
    snapshot, restore : callable, optional
        ``snapshot()`` is taken when a job is submitted; ``restore(snapshot)`` puts it back
        when the job fails.
    interval : float, default=PROGRESS_INTERVAL
        Seconds between forwarded progress updates.
    clock : callable, default=time.monotonic
        Injectable for tests of the throttling.
    """

    def __init__(self, *, background: bool = False,
                 schedule: Callable[[Callable[[], Any]], Any] | None = None,
                 on_start: Callable[[str], Any] = _noop,
                 on_progress: Callable[[float, str], Any] = _noop,
                 on_finish: Callable[[], Any] = _noop,
                 on_error: Callable[[str], Any] = _noop,
                 snapshot: Callable[[], Any] = _noop,
                 restore: Callable[[Any], Any] = _noop,
                 interval: float = PROGRESS_INTERVAL,
                 clock: Callable[[], float] = time.monotonic):
        self.background = bool(background)
        self.schedule = schedule if schedule is not None else (lambda fn: fn())
        self._on_start, self._on_progress, self._on_finish = on_start, on_progress, on_finish
        self._on_error, self._snapshot, self._restore = on_error, snapshot, restore
        self.interval = float(interval)
        self._clock = clock
        self._job: Job | None = None
        self._closed = False

    # ------------------------------------------------------------------------------
    # Public

    @property
    def job(self) -> Job | None:
        """The newest job (running or ended), or None before the first."""
        return self._job

    @property
    def busy(self) -> bool:
        return self._job is not None and self._job.running

    def submit(self, label: str, compute: Compute, apply: Callable[[Any], Any]) -> Job:
        """Start ``compute`` and apply what it yields; retire the running job, if any.

        Call from the session's thread.
        """
        self._retire()
        job = Job(label, self._snapshot())
        self._job = job
        self._on_start(label)
        if self.background:
            threading.Thread(target=self._work, args=(job, compute, apply),
                             name=f"mdcore-{label}", daemon=True).start()
        else:
            self._work(job, compute, apply)
        return job

    def cancel(self) -> bool:
        """Ask the running job to stop; it ends quietly at its next check.

        Returns whether a job was running.
        """
        job = self._job
        if job is None or not job.running:
            return False
        job.cancel.set()
        return True

    def drop(self) -> None:
        """Retire the running job without any callback (the state is being reset)."""
        self._retire()

    def close(self) -> None:
        """The session has ended: retire the running job, and hand nothing more to
        ``schedule`` (the session's document is gone)."""
        self._closed = True
        self._retire()

    # ------------------------------------------------------------------------------
    # Worker side

    def _live(self, job: Job) -> bool:
        return job is self._job and job.running

    def _retire(self) -> None:
        job = self._job
        if job is not None and job.running:
            job.status = "superseded"
            job.cancel.set()

    def _reporter(self, job: Job) -> Report:
        last = [-float("inf"), -1.0]                      # time and fraction last shown

        def report(fraction: float, message: str = "") -> None:
            if job.cancel.is_set() or not self._live(job):
                raise Cancelled(f"{job.label} was cancelled.")
            now = self._clock()
            if now - last[0] < self.interval and fraction - last[1] < 0.1:
                return                                    # at most ~4 updates a second
            last[:] = now, fraction
            f = min(max(float(fraction), 0.0), 1.0)
            self._post(lambda: self._live(job) and self._on_progress(f, message))

        return report

    def _work(self, job: Job, compute: Compute, apply: Callable[[Any], Any]) -> None:
        try:
            for partial in compute(self._reporter(job), job.cancel):
                if not self._live(job):
                    break
                self._post(lambda p=partial: self._apply(job, apply, p))
        except Exception as exc:                          # noqa: BLE001 - every failure ends the job
            self._post(lambda e=exc: self._end(job, e), job)
            return
        self._post(lambda: self._end(job, None), job)

    def _post(self, fn: Callable[[], Any], ending: Job | None = None) -> None:
        """``schedule(fn)`` unless the session has ended; ``ending``: the job that ``fn``
        would end, marked ended here instead."""
        if not self._closed:
            try:
                self.schedule(fn)
                return
            except Exception:
                if not self._closed:                      # closed while scheduling: expected
                    raise
        if ending is not None:
            ending.ended.set()

    # ------------------------------------------------------------------------------
    # Session side (through schedule)

    def _apply(self, job: Job, apply: Callable[[Any], Any], partial: Any) -> None:
        if not self._live(job):
            return
        try:
            apply(partial)
        except Exception as exc:                          # noqa: BLE001
            self._fail(job, exc)

    def _end(self, job: Job, exc: BaseException | None) -> None:
        try:
            if not self._live(job):
                return                                    # superseded, dropped or failed
            if exc is None:
                job.status = "done"
                self._on_finish()
            elif isinstance(exc, Cancelled):
                job.status = "cancelled"
                self._on_finish()
            else:
                self._fail(job, exc)
        finally:
            job.ended.set()

    def _fail(self, job: Job, exc: BaseException) -> None:
        job.status, job.error = "failed", exc
        job.cancel.set()                                  # the worker stops at its next check
        if not isinstance(exc, ValueError):               # ValueErrors are the user's to fix
            log.error("%s failed", job.label, exc_info=exc)
        try:
            self._restore(job.snapshot)
        except Exception:
            log.exception("restoring the state after %s failed", job.label)
        self._on_finish()
        self._on_error(error_message(job.label, exc))


def error_message(label: str, exc: BaseException) -> str:
    """The notification text: a ValueError's own message (it says what to change), else
    the label, the exception type and its message."""
    if isinstance(exc, ValueError):
        return str(exc)
    text = str(exc) or "no message"
    return f"{label} failed with {type(exc).__name__}: {text}"
