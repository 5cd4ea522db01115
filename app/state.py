"""Session state of the Model Discrepancy Explorer: parameters in, mdcore results out.

No widget code lives here. :class:`ExplorerState` is one session's state, put together
from small ``param`` models, each in its module: the session's jobs and messages
(:mod:`.session_model`), the case and its data (:mod:`.case_model`), history matching
(:mod:`.history_model`), discrepancy runs (:mod:`.runs`) and its own data in and results
out (:mod:`.own_data`). It calls :mod:`mdcore` (history matching wave by wave, then
:func:`mdcore.run_method` per method) and caches what it computed; the views only display
it.

Long work (a wave, a discrepancy run) goes through a :class:`~mdcore_app.jobs.JobRunner`:
by default it runs synchronously (tests, scripts); the served app sets ``background=True``
and a ``schedule`` function that hands results back to the session's event loop. A job
yields typed messages (:class:`~.history_model.Note`, :class:`~.history_model.WaveDone`,
:class:`~.runs.MethodsDone`). A newer request supersedes an older one,
:meth:`ExplorerState.cancel` stops the running one, and a failure of any kind becomes one
notification with the earlier state put back.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import numpy as np
import param

from mdcore import _cases as cases
from mdcore._cases import Case

from .case_model import OwnCase
from .history_model import HM_CONTROLS, Note, ProblemKey, WaveDone
from .jobs import JobRunner
from .own_data import OwnDataModel
from .runs import MethodsDone
from .session_model import APP_MAX_CANDIDATES

__all__ = ["ExplorerState", "Snapshot"]


class Snapshot(NamedTuple):
    """The result fields a job may change, as they were when it was submitted."""

    waves: tuple
    implausibility_maps: dict
    selected_wave: int
    status: str
    results: dict
    problem: object
    problem_key: ProblemKey | None
    cache: dict


class ExplorerState(OwnDataModel):
    """All state of one browser session.

    Parameters
    ----------
    background : bool, default=False
        Run long work on a worker thread (the served app).
    schedule : callable, optional
        ``schedule(fn)`` runs ``fn`` on the session's thread; default: at once.
    own_cases : tuple of Case
        Cases beyond the built-in ones (``--case`` files).
    **params
        Initial values of the parameters of the models.
    """

    def __init__(self, *, background: bool = False,
                 schedule: Callable[[Callable], object] | None = None,
                 own_cases: tuple[Case, ...] = (), **params):
        #: Cases of this session beyond the built-in ones: from ``--case`` files, and
        #: uploaded measurements.
        self._own: dict[str, OwnCase] = {c.name: OwnCase(c) for c in own_cases}
        #: Results and history-match controls of the cases switched away from.
        self._kept: dict[str, tuple[dict, Snapshot]] = {}
        super().__init__(**params)
        if self._own:
            self.param.case_name.objects = list(cases.names()) + list(self._own)
        self._jobs = JobRunner(
            background=background, schedule=schedule,
            on_start=lambda label: self.param.update(busy=True, task=label, progress=0.0,
                                                     progress_message="", cancelled=False),
            on_progress=lambda f, message: self.param.update(progress=f,
                                                             progress_message=message),
            on_finish=lambda: self.param.update(busy=False, task="", progress_message=""),
            on_error=self.report_error, snapshot=self._snapshot, restore=self._restore)
        self._init_history()
        self._init_runs()
        self._load_case()

    @param.depends("case_name", watch=True)
    def _load_case(self, replace: bool = False):
        """Load the case ``case_name`` names; ``replace``: it is the current case with new
        data (an upload or a session file of the same name), whose results are dropped.
        ``case`` goes from one case to the next, never through None (its watchers draw it)."""
        if not replace and self.case is not None and self.case_name == self.case.name:
            return                                   # put back after a failed load
        try:
            case = (self._own[self.case_name].case if self.case_name in self._own
                    else cases.load(self.case_name, seed=0))
        except Exception as exc:                     # noqa: BLE001 - any failure: keep the case
            if self.case is None:
                raise
            self.report_error(f"Could not load the case {self.case_name!r}, so "
                               f"{self.case.name} stays loaded: {exc}")
            self.case_name = self.case.name
            return
        self._jobs.drop()                            # drop work for the previous case
        if self.case is not None and not replace:    # keep its results for switching back
            self._kept[self.case.name] = ({k: getattr(self, k) for k in HM_CONTROLS},
                                          self._snapshot())
        self._problem, self._problem_key, self._cache = None, None, {}
        with param.parameterized.batch_call_watchers(self):
            self.case = case
            self._show_case(case)
            self.v_m = float(case.V_m[0])
            self.v_m_length = float(np.max(case.V_m_length))
            self._apply_preset()
            self.n_candidates = min(50_000 * case.p, APP_MAX_CANDIDATES)
            self.waves = ()
            self.implausibility_maps = {}
            self.results = {}
            self.selected_wave = 0
            self.status = f"{case.title}. Press “Next wave” or “Run to convergence”."
            self.busy, self.task, self.progress, self.progress_message = False, "", 0.0, ""
            if case.name in self._kept:
                controls, snap = self._kept.pop(case.name)
                self.param.update(**controls)
                self._restore(snap)
                self._refresh_results()          # the discrepancy settings may differ now

    def _snapshot(self) -> Snapshot:
        return Snapshot(self.waves, dict(self.implausibility_maps), self.selected_wave,
                        self.status, dict(self.results), self._problem, self._problem_key,
                        dict(self._cache))

    def _restore(self, snap: Snapshot) -> None:
        """Put back the result fields of ``snap`` together, so they agree with each other."""
        self._problem, self._problem_key, self._cache = (snap.problem, snap.problem_key,
                                                         dict(snap.cache))
        self.param.update(waves=snap.waves, implausibility_maps=snap.implausibility_maps,
                          selected_wave=snap.selected_wave, status=snap.status,
                          results=snap.results)

    def _apply(self, message: Note | WaveDone | MethodsDone) -> None:
        """Put one message of a job into the state (on the session's thread)."""
        if isinstance(message, Note):
            self.status = message.text
        elif isinstance(message, WaveDone):
            self._apply_wave(message)
        else:
            self._apply_methods(message)
