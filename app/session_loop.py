"""Callbacks on a served session's event loop: on its next tick, after a delay, when a tab
is shown, and once the session is idle. Each runs under Panel's ``hold``, so its changes
to Panel objects and to raw Bokeh models reach the browser in one message. Not served
(tests, the report), a callback runs at once, and :func:`when_idle` calls nothing.
"""

from __future__ import annotations

import logging
import time
import weakref

import panel as pn
from panel.io.state import set_curdoc
from tornado.ioloop import IOLoop

log = logging.getLogger("mdcore_app")

#: Seconds after a poke before the views of hidden tabs start to catch up with the state:
#: a tab is then drawn before it is clicked.
CATCH_UP_AFTER = 0.5
#: ... and seconds the session's state must have stayed unchanged (no setting, card or
#: job's end) when no job runs: the work waits for the user to pause on a result, and a
#: click right after a run is not delayed by it (docs/performance.md, "A card's click").
CATCH_UP_QUIET = 3.0
#: Seconds between two hooks of a session's catching up, longer than the browser takes to
#: lay out one rebuilt view: run in one go, they kept the browser busy for seconds after a
#: run, and a card's click waited for all of them (docs/performance.md, "A card's click").
CATCH_UP_GAP = 1.0
#: Per session state: its :class:`_Waiting` hooks.
_catch_up_queue: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
#: The clock of :data:`CATCH_UP_QUIET` (a test's own clock replaces it).
clock = time.monotonic


class _Waiting:
    """A session's hooks waiting for their turn to catch up, in order, and when its state
    last changed. It holds the state weakly: it is the value of the state's entry in
    :data:`_catch_up_queue`."""

    def __init__(self, state):
        self.hooks: list = []
        self.changed = clock()
        self._state = weakref.ref(state)
        state.param.watch(self._touch, [p for p in state.param if p != "name"])

    def _touch(self, *_) -> None:
        self.changed = clock()

    def wait(self) -> float:
        """Seconds until the state has been quiet long enough (0 while a job runs)."""
        state = self._state()
        if state is None or state.busy:
            return 0.0
        return max(0.0, CATCH_UP_QUIET - (clock() - self.changed))


def _served_doc():
    """The session's document, or None when not served."""
    doc = pn.state.curdoc
    return None if doc is None or doc.session_context is None else doc


def _held(doc, fn):
    def run() -> None:
        with set_curdoc(doc), pn.io.hold(doc):
            fn()
    return run


def later(seconds: float, fn) -> None:
    """Call ``fn()`` ``seconds`` from now (not served: at once)."""
    doc = _served_doc()
    if doc is None:
        fn()
    else:
        doc.add_timeout_callback(_held(doc, fn), int(1000 * seconds))


def next_tick(fn) -> None:
    """Call ``fn()`` on the session's next tick (not served: at once): raw Bokeh models
    changed inside a widget's or a tab's own event were refused ("_pending_writes should
    be non-None"), leaving a tab blank."""
    doc = _served_doc()
    if doc is None:
        fn()
    else:
        doc.add_next_tick_callback(_held(doc, fn))


def watch_in_session(obj, fn, names) -> None:
    """``obj.param.watch(fn, names)``, with ``fn(*events)`` called on the session's next
    tick (:func:`next_tick`; not served: at once): for a watcher that changes raw Bokeh
    models (a figure's data, a :func:`~mdcore_app.live_figures.live_text` line).

    A button pressed while a field's change waits for Panel's short debounce makes Panel
    process that change first, outside Bokeh's document lock, and Bokeh then refuses a raw
    model's change ("_pending_writes should be non-None"): the page stopped following the
    state. In a callback of the session, Bokeh holds the lock."""
    obj.param.watch(lambda *events: next_tick(lambda: fn(*events)), names)


def job_scheduler(doc):
    """``schedule(fn)`` for a session's jobs: ``fn()`` on the session's next tick, called
    from any thread (not served: at once).

    The worker thread hands ``fn`` to Tornado's loop (``add_callback``, safe from any
    thread), which adds it to the document. Added from the worker itself, it raced the
    session's thread: while that thread holds the document, Bokeh queues the "callback
    added" event and dispatches the queue when the hold ends, and an event queued as the
    hold ended was lost (Bokeh's queue has no lock). A lost wave left the state one wave
    short of its results, so a finished run showed nothing. Create it on the session's
    loop (``create_app`` runs there).
    """
    if doc is None or doc.session_context is None:
        return lambda fn: fn()
    loop = IOLoop.current()

    def add(fn):
        try:
            doc.add_next_tick_callback(_held(doc, fn))
        except RuntimeError:                   # the session's document is destroyed
            log.debug("session ended; a job's callback was dropped")

    return lambda fn: loop.add_callback(add, fn)


def when_shown(tabs: pn.Tabs, index: int, hook) -> None:
    """Call ``hook()`` whenever tab ``index`` of ``tabs`` becomes active (:func:`next_tick`)."""
    tabs.param.watch(lambda event: event.new == index and next_tick(hook), "active")


def when_idle(state, hook):
    """Call ``hook()`` once ``state`` (a session's state with ``busy`` and ``cancelled``)
    has been idle for :data:`CATCH_UP_AFTER` s after each job ends, unless it was
    cancelled (Cancel gives the CPU back), and after each ``poke()`` (a new case); returns
    ``poke``. ``poke(busy=True)`` calls it even while a job runs (a hidden tab whose
    data a job is changing: its first drawing then happens while the browser waits).

    A session's hooks run one at a time, :data:`CATCH_UP_GAP` s apart, in the order they
    were poked, each once the state has not changed for :data:`CATCH_UP_QUIET` s (or at
    once while a job runs). ``hook`` decides itself whether anything is left to do (a view
    that is stale). A change of what is shown (a band, a scenario hidden) does not poke:
    hidden tabs would redo their plots for each click, and the browser lays out the page
    again each time."""
    doc = _served_doc()
    if doc is None:
        return lambda *_, busy=False: None
    waiting = _catch_up_queue.get(state)
    if waiting is None:
        waiting = _catch_up_queue[state] = _Waiting(state)
        # A closed session's pending timeouts never run: its hooks (and through them its
        # state, the queue's key) must not stay in the queue.
        doc.on_session_destroyed(lambda _context: waiting.hooks.clear())
    queue = waiting.hooks

    def poke(*_, busy: bool = False):
        queue.append(lambda: (state.busy and not busy) or hook())
        if len(queue) == 1:                       # else the hook before it calls it
            later(CATCH_UP_AFTER, lambda: _next_catch_up(waiting))

    state.param.watch(lambda event: event.new or state.cancelled or poke(), "busy")
    return poke


def _next_catch_up(waiting: _Waiting) -> None:
    """Run the first hook waiting, once the state is quiet, and the next one
    :data:`CATCH_UP_GAP` s after it returns."""
    queue, wait = waiting.hooks, waiting.wait()
    if not queue:
        return
    if wait > 0:
        later(wait, lambda: _next_catch_up(waiting))
        return
    try:
        queue[0]()
    finally:
        del queue[0]
        if queue:
            later(CATCH_UP_GAP, lambda: _next_catch_up(waiting))


#: CSS class of the line above a box whose content is being rebuilt.
UPDATING = "mdcore-updating"


def show_updating(box: pn.Column, text: str, keep: bool = True) -> None:
    """Put ``text`` (italic) at the top of ``box`` until it is rebuilt; with ``keep``, the
    box's content stays under it, dimmed: a rebuild of seconds (shear-5's metrics) left a
    tab blank but for that line."""
    old = [o for o in box.objects if UPDATING not in o.css_classes] if keep else []
    for o in old:
        o.styles = {**o.styles, "opacity": "0.45"}
    box.objects = [pn.pane.Markdown(f"*{text}*", css_classes=[UPDATING]), *old]
