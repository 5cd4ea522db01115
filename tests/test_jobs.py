"""Tests of the app's job runner (app/jobs.py): failures of any type end the job with one
notification and the earlier state, newer jobs supersede older ones, cancel stops a running
job quietly, and progress is throttled.

Background mode is driven the way the served app drives it: the worker hands callbacks to
``schedule`` (here a queue), and the test thread plays the session's event loop. No fixed
sleeps: every wait is on a condition with a timeout.
"""

import queue
import threading

import numpy as np
import pytest
from event_loop import drain

from mdcore._exceptions import Cancelled
from mdcore_app.jobs import JobRunner, error_message

TIMEOUT = 30.0


class Host:
    """A stand-in session state: a value the jobs change, busy/progress/error fields."""

    def __init__(self):
        self.value = "before"
        self.status = "status before"
        self.busy = False
        self.progress = []
        self.errors = []

    def runner(self, **options) -> JobRunner:
        return JobRunner(
            on_start=lambda label: setattr(self, "busy", True),
            on_progress=lambda f, m: self.progress.append((f, m)),
            on_finish=lambda: setattr(self, "busy", False),
            on_error=self.errors.append,
            snapshot=lambda: (self.value, self.status),
            restore=self._restore, **options)

    def _restore(self, snap):
        self.value, self.status = snap

    def apply(self, partial):
        self.value, self.status = partial, f"status of {partial}"


def background(host: Host, **options):
    inbox: queue.Queue = queue.Queue()
    return host.runner(background=True, schedule=inbox.put, **options), inbox


# --- failures ----------------------------------------------------------------------------

@pytest.mark.parametrize("exc_type", [RuntimeError, ValueError, ZeroDivisionError, KeyError])
def test_exception_from_compute_restores_state_and_clears_busy(exc_type):
    host = Host()
    runner = host.runner()

    def compute(report, cancel):
        yield "partial"                               # applied: state and status change …
        report(0.5)
        raise exc_type("injected")                    # … then the work fails

    job = runner.submit("wave", compute, host.apply)
    assert job.status == "failed" and isinstance(job.error, exc_type)
    assert (host.value, host.status) == ("before", "status before")     # restored together
    assert not host.busy and not runner.busy
    assert len(host.errors) == 1 and "injected" in host.errors[0]


def test_exception_from_apply_restores_state_and_stops_the_work():
    host = Host()
    runner = host.runner()
    yielded = []

    def compute(report, cancel):
        for k in range(5):
            yielded.append(k)
            yield k
            report((k + 1) / 5)

    def apply(partial):
        host.apply(partial)
        if partial == 1:
            raise RuntimeError("apply broke")

    job = runner.submit("discrepancy", compute, apply)
    assert job.status == "failed"
    assert yielded == [0, 1]                          # the worker stopped at its next check
    assert (host.value, host.status) == ("before", "status before")
    assert not host.busy and host.errors == ["discrepancy failed with RuntimeError: apply broke"]


def test_runtime_error_in_background_mode():
    host = Host()
    runner, inbox = background(host)

    def compute(report, cancel):
        yield "partial"
        raise RuntimeError("boom")

    job = runner.submit("waves", compute, host.apply)
    drain(inbox, timeout=TIMEOUT, until=lambda: job.wait(0) and inbox.empty())
    assert not host.busy and len(host.errors) == 1 and host.value == "before"
    runner.submit("waves", lambda report, cancel: iter(["after"]), host.apply)
    drain(inbox, timeout=TIMEOUT, until=lambda: not host.busy)
    assert host.value == "after" and len(host.errors) == 1          # still usable


def test_error_message_names_the_type_except_for_value_errors():
    assert error_message("wave", ValueError("Raise V_m.")) == "Raise V_m."
    assert error_message("wave", RuntimeError("x")) == "wave failed with RuntimeError: x"
    assert error_message("wave", KeyError()) == "wave failed with KeyError: no message"


# --- supersession and cancel --------------------------------------------------------------

def test_newer_job_supersedes_and_drops_stale_results():
    host = Host()
    runner, inbox = background(host)
    started, release = threading.Event(), threading.Event()

    def slow(report, cancel):
        started.set()
        release.wait(TIMEOUT)
        yield "stale"
        raise RuntimeError("stale failure")            # must not notify either

    old = runner.submit("slow", slow, host.apply)
    assert started.wait(TIMEOUT)
    new = runner.submit("fast", lambda report, cancel: iter(["fresh"]), host.apply)
    assert old.status == "superseded" and old.cancel.is_set()
    drain(inbox, timeout=TIMEOUT, until=lambda: new.wait(0))
    release.set()
    drain(inbox, timeout=TIMEOUT, until=lambda: old.wait(0) and inbox.empty())
    assert host.value == "fresh" and host.errors == [] and not host.busy
    assert old.status == "superseded" and new.status == "done"


def test_cancel_stops_a_running_job_quietly():
    host = Host()
    runner, inbox = background(host)
    started = threading.Event()
    steps = []

    def endless(report, cancel):
        yield "first"                                 # applied before the cancel: kept
        started.set()
        while True:                                   # stops only through cancel
            steps.append(1)
            report(0.5, "working")
            cancel.wait(0.01)

    job = runner.submit("endless", endless, host.apply)
    drain(inbox, timeout=TIMEOUT, until=lambda: started.is_set() and host.value == "first")
    assert runner.cancel()
    drain(inbox, timeout=TIMEOUT, until=lambda: job.wait(0) and not host.busy)
    n = len(steps)
    assert job.status == "cancelled" and host.errors == [] and host.value == "first"
    assert not runner.cancel()                        # nothing running any more
    assert len(steps) == n                            # the worker has stopped


def test_pipeline_cancelled_is_not_a_notification_storm():
    """Many retired or cancelled jobs, each raising Cancelled or failing late: no errors."""
    host = Host()
    runner, inbox = background(host)
    gates = []

    def work(report, cancel):
        gate = threading.Event()
        gates.append(gate)
        gate.wait(TIMEOUT)
        for _ in range(100):
            report(0.1)                               # raises Cancelled once retired
        yield "late"

    jobs = [runner.submit(f"job {k}", work, host.apply) for k in range(5)]
    runner.cancel()
    drain(inbox, timeout=TIMEOUT, until=lambda: len(gates) == 5)
    for gate in gates:
        gate.set()
    drain(inbox, timeout=TIMEOUT, until=lambda: all(j.wait(0) for j in jobs) and inbox.empty())
    assert not host.busy
    assert host.errors == [] and host.value == "before"
    assert [j.status for j in jobs] == ["superseded"] * 4 + ["cancelled"]


def test_cancelled_from_the_work_itself_ends_quietly():
    host = Host()
    runner = host.runner()

    def compute(report, cancel):
        yield "partial"
        raise Cancelled("run_method was cancelled")

    job = runner.submit("discrepancy", compute, host.apply)
    assert job.status == "cancelled" and host.errors == [] and not host.busy
    assert host.value == "partial"                    # a cancel keeps what was applied


def test_drop_retires_without_callbacks():
    host = Host()
    runner, inbox = background(host)
    release = threading.Event()

    def compute(report, cancel):
        release.wait(TIMEOUT)
        yield "stale"

    job = runner.submit("x", compute, host.apply)
    runner.drop()
    release.set()
    drain(inbox, timeout=TIMEOUT, until=lambda: job.wait(0))
    assert job.status == "superseded" and host.value == "before" and host.errors == []
    assert host.busy                                  # drop leaves busy to the caller


def test_close_stops_the_job_and_schedules_nothing_more():
    """A closed session (its browser tab gone): the running job stops at its next check,
    and the worker hands nothing to ``schedule``, which would fail on a destroyed document."""
    host = Host()
    scheduled = []
    closed = threading.Event()

    def schedule(fn):
        if closed.is_set():
            raise AttributeError("the document is gone")   # as Bokeh does after destroy
        scheduled.append(fn)

    runner = host.runner(background=True, schedule=schedule)
    started = threading.Event()
    steps = []

    def endless(report, cancel):
        started.set()
        while True:
            steps.append(1)
            report(0.5, "working")                    # raises Cancelled once closed
            cancel.wait(0.01)
        yield "never"

    job = runner.submit("endless", endless, host.apply)
    assert started.wait(TIMEOUT)
    runner.close()
    closed.set()
    n_scheduled = len(scheduled)
    assert job.wait(TIMEOUT)                          # ended, without any scheduled callback
    n = len(steps)
    assert job.status == "superseded" and host.errors == []
    assert len(scheduled) == n_scheduled
    assert not runner.cancel() and len(steps) == n


# --- progress ------------------------------------------------------------------------------

def test_progress_is_throttled_on_a_clock():
    host = Host()
    now = [0.0]
    runner = host.runner(clock=lambda: now[0], interval=0.25)

    def compute(report, cancel):
        for k in range(100):                          # 100 reports at one instant …
            report(k / 1000, "fine steps")
        report(0.2, "big jump")                       # … a jump of ≥ 0.1 always shows
        now[0] += 0.3
        report(0.201, "later")                        # … and so does the first after 0.25 s
        report(0.202, "too soon")
        yield "done"

    runner.submit("x", compute, host.apply)
    assert host.progress == [(0.0, "fine steps"), (0.2, "big jump"), (0.201, "later")]


# --- the session state on the runner ------------------------------------------------------

def _state(**extra):
    pytest.importorskip("panel")
    from mdcore_app.state import ExplorerState
    s = ExplorerState(**{k: v for k, v in extra.items() if k in ("background", "schedule")})
    s.param.update(n_candidates=4000, n_s=30, n_phi=8,
                   **{k: v for k, v in extra.items() if k not in ("background", "schedule")})
    return s


def _fields(s):
    return (s.waves, dict(s.implausibility_maps), s.selected_wave, s.status, dict(s.results),
            dict(s._cache), s._problem_key)


def test_state_runtime_error_in_a_later_method_restores_the_earlier_results(monkeypatch):
    """Scenario 1 is applied before KOH starts; KOH then fails: the results go back to what
    they were before the run (not scenario 1 alone), with one notification."""
    import mdcore_app.runs as runs_module
    from mdcore._pipeline import Method
    s = _state()
    s.run_to_convergence()
    s.scenarios = [Method.S2]
    s.run_discrepancy()
    before, n = _fields(s), s.n_errors
    real = runs_module.run_method
    applied = []
    s.param.watch(lambda e: applied.append(list(e.new)), "results")

    def failing(case, hm, method, *args, **kwargs):
        if method is Method.KOH:
            raise RuntimeError("injected in KOH")
        return real(case, hm, method, *args, **kwargs)

    monkeypatch.setattr(runs_module, "run_method", failing)
    s.scenarios = [Method.S1, Method.S2, Method.KOH]   # runs S1 and KOH (S2 is cached)
    assert [Method.S1, Method.S2] in applied           # S1 was shown before KOH failed
    assert not s.busy and s.n_errors == n + 1
    assert "RuntimeError" in s.error and "injected in KOH" in s.error
    assert s.results == {Method.S2: before[4][Method.S2]}
    assert _fields(s)[5] == before[5]                  # the cache too: nothing half-done


def test_state_runtime_error_in_a_later_wave_restores_waves_and_status(monkeypatch):
    import mdcore_app.history_model as history_module
    s = _state(max_waves=4, convergence_ratio=0.001)
    s.next_wave()
    before, n = _fields(s), s.n_errors
    real, calls = history_module.next_wave, []

    def failing(problem, waves, progress=None):
        calls.append(len(waves))
        if len(calls) == 2:
            raise RuntimeError("simulator crashed")
        return real(problem, waves, progress)

    monkeypatch.setattr(history_module, "next_wave", failing)
    s.run_to_convergence()                             # wave 2 is applied, wave 3 fails
    assert calls == [1, 2]
    after = _fields(s)
    assert after[0] is before[0] and after[1:] == before[1:]     # waves, maps, status …
    assert s.status == before[3] and len(s.waves) == 1
    assert not s.busy and s.n_errors == n + 1 and "simulator crashed" in s.error


def test_state_runtime_error_from_apply(monkeypatch):
    s = _state(max_waves=4, convergence_ratio=0.001)
    s.next_wave()
    before, n = _fields(s), s.n_errors

    def broken():
        raise RuntimeError("apply failed")

    monkeypatch.setattr(s, "_refresh_results", broken)     # called inside the wave's apply
    s.next_wave()
    assert _fields(s)[0] is before[0] and _fields(s)[1:] == before[1:]
    assert not s.busy and s.n_errors == n + 1 and "apply failed" in s.error
    monkeypatch.undo()
    s.next_wave()                                          # still usable
    assert len(s.waves) == 2 and s.n_errors == n + 1


def test_state_value_error_restores_and_notifies_once():
    s = _state()
    s.next_wave()
    before, n = _fields(s), s.n_errors
    s.v_m = 1e-7                                  # valid, but rules everything out
    s.next_wave()
    assert _fields(s)[0] is before[0] and not s.busy and s.n_errors == n + 1
    assert "nothing is non-implausible" in s.error


def test_state_cancel_stops_a_running_discrepancy_run():
    """Background mode: cancel a slow scenario-3 run once it reports progress; it ends with
    no error and no result, and the session is idle again."""
    from mdcore._pipeline import Method
    inbox: queue.Queue = queue.Queue()
    s = _state(background=True, schedule=inbox.put)
    s.run_to_convergence()
    drain(inbox, timeout=TIMEOUT, until=lambda: len(s.waves) >= 1 and not s.busy)
    s.scenarios = [Method.S3]
    s.param.update(n_s=400, n_phi=1000)                 # long enough to be cancelled
    s.run_discrepancy()
    job = s.jobs.job
    drain(inbox, timeout=TIMEOUT, until=lambda: s.progress > 0 or not s.busy)
    assert s.busy, "the run finished before it could be cancelled"
    s.cancel()
    drain(inbox, until=lambda: job.wait(0) and not s.busy, timeout=120.0)
    assert job.status == "cancelled" and s.n_errors == 0 and s.results == {}
    assert s.progress_message == ""


def test_a_seed_changed_during_the_first_discrepancy_run_runs_it_again():
    """A discrepancy setting changed while the first run was still working (nothing
    cached yet) started no run: the first run's results, for the old seed, were not
    shown for the new one, and the tab stayed empty (seen as a CI flake of the end-to-end
    browser test). The change now restarts the run with the new setting."""
    inbox: queue.Queue = queue.Queue()
    s = _state(background=True, schedule=inbox.put)
    s.run_to_convergence()
    drain(inbox, timeout=TIMEOUT, until=lambda: len(s.waves) >= 1 and not s.busy)
    s.run_discrepancy()
    first = s.jobs.job
    assert s.busy and not s.results
    s.seed = 1
    assert s.jobs.job is not first and first.status == "superseded"
    drain(inbox, timeout=TIMEOUT, until=lambda: not s.busy)
    assert set(s.results) == set(s.scenarios)     # the results shown are the seed's own


def test_a_served_session_gets_job_callbacks_on_its_own_loop_in_order():
    """The job's worker thread added its callbacks to the Bokeh document itself. While the
    session's thread held the document (Panel's ``hold``), Bokeh queued the event without
    a lock and now and then lost it: under load a run's last wave never arrived, and the
    finished run showed nothing. The document is now only touched on the session's
    loop, in the order the worker handed the callbacks over."""
    import asyncio
    import time

    from bokeh.document import Document as BokehDocument
    from tornado.ioloop import IOLoop

    from mdcore_app.session_loop import job_scheduler

    class Document(BokehDocument):
        """A served session's document that records the callbacks added to it."""
        session_context = object()

        def __init__(self):
            super().__init__()
            self.added = []

        def add_next_tick_callback(self, callback):
            self.added.append((threading.current_thread(), callback))

    doc, ready, loop_of = Document(), threading.Event(), {}

    def session_loop():
        asyncio.set_event_loop(asyncio.new_event_loop())
        loop_of.update(loop=IOLoop.current(), thread=threading.current_thread(),
                       schedule=job_scheduler(doc))
        ready.set()
        loop_of["loop"].start()

    threading.Thread(target=session_loop, daemon=True).start()
    assert ready.wait(TIMEOUT)
    ran = []
    fns = [lambda k=k: ran.append(k) for k in range(50)]
    worker = threading.Thread(target=lambda: [loop_of["schedule"](fn) for fn in fns])
    worker.start()
    worker.join(TIMEOUT)
    end = time.monotonic() + TIMEOUT
    while len(doc.added) < len(fns) and time.monotonic() < end:
        time.sleep(0.01)
    loop_of["loop"].add_callback(loop_of["loop"].stop)
    assert [thread for thread, _ in doc.added] == [loop_of["thread"]] * len(fns)
    for _, callback in doc.added:          # as the session's next ticks would
        callback()
    assert ran == list(range(len(fns)))


def test_a_sessions_views_catch_up_one_at_a_time_once_the_user_pauses(monkeypatch):
    """After a run, every hidden view of a session caught up at once: the browser laid
    them out for seconds, and a card's click waited that long for its answer. Each waits
    now for the one before it, plus a gap in which the browser lays out the last one; and
    none starts before the state has been unchanged for CATCH_UP_QUIET s, so that a click
    right after a run (a band, a card) is not delayed by them (docs/performance.md, "A
    card's click")."""
    import param
    from bokeh.document import Document as BokehDocument
    from panel.io.state import set_curdoc

    from mdcore_app import session_loop

    now = [100.0]
    monkeypatch.setattr(session_loop, "clock", lambda: now[0])

    class Document(BokehDocument):
        """A served session's document that records its timeout callbacks."""
        session_context = object()

        def __init__(self):
            super().__init__()
            self.timeouts = []

        def add_timeout_callback(self, callback, timeout_milliseconds):
            self.timeouts.append((callback, timeout_milliseconds))

    class State(param.Parameterized):
        busy = param.Boolean(False)
        cancelled = param.Boolean(False)
        band = param.Integer(3)

    def run_timeouts(on_the_way=None):
        """Run the pending timeouts in order, the clock moving with them; returns their
        delays (s). ``on_the_way(k)`` runs as the clock passes the k-th one."""
        delays = []
        while doc.timeouts:
            assert len(doc.timeouts) == 1, "two views would catch up at once"
            callback, ms = doc.timeouts.pop()
            delays.append(ms / 1000)
            now[0] += ms / 1000
            if on_the_way:
                on_the_way(len(delays))
            callback()
        return delays

    doc, state, ran = Document(), State(), []
    quiet, after, gap = (session_loop.CATCH_UP_QUIET, session_loop.CATCH_UP_AFTER,
                         session_loop.CATCH_UP_GAP)
    with set_curdoc(doc):
        for k in range(3):
            session_loop.when_idle(state, lambda k=k: ran.append(k))
        state.busy = True
        state.busy = False                              # a job ended: all three are due
        delays = run_timeouts()
    assert ran == [0, 1, 2]
    np.testing.assert_allclose(delays, [after, quiet - after, gap, gap])
    # A change of the state as they wait (the band, as the first timeout fires) puts them off
    # until it has been quiet again; none of them runs before.
    ran.clear()
    with set_curdoc(doc):
        state.busy = True
        state.busy = False
        delays = run_timeouts(lambda k: k == 1 and ran == [] and setattr(state, "band", 2))
    assert ran == [0, 1, 2]
    np.testing.assert_allclose(delays, [after, quiet, gap, gap])
    # A session closed while its views wait lets go of them (and of its state).
    with set_curdoc(doc):
        state.busy = True
        state.busy = False
    assert session_loop._catch_up_queue[state].hooks
    for callback in doc.session_destroyed_callbacks:
        callback(None)
    assert session_loop._catch_up_queue[state].hooks == []
