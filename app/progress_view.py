"""The sidebar's busy line, progress bar and Cancel button, updated in place."""

from __future__ import annotations

import html
import time

import panel as pn

from .session_loop import later

#: The busy line names a job's step once it has run this long (seconds), so that runs at
#: the default sizes (a fraction of a second) do not flash it.
SHOW_PROGRESS_AFTER = 0.5
#: Height of the busy line (two lines of text), fixed so that a new message never
#: changes the page's layout.
STATUS_HEIGHT = 40


def status_html(busy: bool, task: str, detail: str = "") -> str:
    """The busy line: "Idle." or "Running <task> … <detail>", in a span whose class
    (``mdcore-busy`` or ``mdcore-idle``) says which."""
    if not busy:
        return '<span class="mdcore-idle">Idle.</span>'
    tail = f" {html.escape(detail)}" if detail else ""
    return f'<span class="mdcore-busy">Running <b>{html.escape(task)}</b> …{tail}</span>'


def progress_panel(state) -> tuple[pn.Column, pn.widgets.Button]:
    """Busy line and progress bar, and a Cancel button (placed apart: beside the run
    buttons), of ``state`` (an :class:`~mdcore_app.state.ExplorerState`), updated in place.

    The bar and the button are always there (the button disabled between jobs), so a
    job changes no size, visibility or layout: only the bar's value and the line's
    text, whose fixed height never moves what is below it. The line names the job
    once it has run :data:`SHOW_PROGRESS_AFTER` seconds, so short runs do not flash.
    """
    text = pn.pane.HTML(status_html(False, ""), height=STATUS_HEIGHT,
                        sizing_mode="stretch_width",
                        styles={"overflow": "hidden", "font-size": "0.9em"})
    bar = pn.indicators.Progress(value=0, max=100, sizing_mode="stretch_width",
                                 css_classes=["job-progress-bar"])
    cancel = pn.widgets.Button(label="Cancel", color="warning", disabled=True,
                               css_classes=["cancel-job"])
    row = pn.Row(bar, sizing_mode="stretch_width", css_classes=["job-progress"])
    cancel.on_click(lambda _: state.cancel())
    since: list[float | None] = [None]          # when the current job started

    def update(*_):
        s = state
        if not s.busy:
            since[0] = None
        elif since[0] is None:
            since[0] = time.monotonic()
            later(SHOW_PROGRESS_AFTER + 0.02, update)     # look again then, progress or not
        show = since[0] is not None and time.monotonic() - since[0] >= SHOW_PROGRESS_AFTER
        text.object = status_html(s.busy, s.task, s.progress_message if show else "")
        if cancel.disabled == s.busy:
            cancel.disabled = not s.busy
        bar.value = int(100 * s.progress) if s.busy else 0

    state.param.watch(update, ["busy", "progress", "task", "progress_message"])
    update()
    return pn.Column(text, row, sizing_mode="stretch_width"), cancel
