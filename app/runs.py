"""Discrepancy runs of a session: scenarios 1–3 and KOH on the current history match.

A run is planned on the session's thread (:class:`RunPlan`: everything it needs, taken
from the state at that moment) and computed by plain functions on the job's thread
(:func:`discrepancy_job`): first the waves it needs, then the methods not cached yet.
"""

from __future__ import annotations

import contextlib
from functools import partial
from typing import NamedTuple

import numpy as np
import param

from mdcore._pipeline import PAPER_SIZES, Method, MethodKey, MethodResult, Settings, run_method

from . import experiments, session
from .experiments import KOH_CHAINS
from .glossary import tooltip
from .history_model import HistoryModel, Note, ProblemKey, WaveDone
from .markup import html_text
from .session_model import (
    ANNOUNCE_SECONDS,
    APP_MAX_N_PHI,
    APP_MAX_N_S,
    estimate_seconds,
    work_problem,
)

_INTERACTIVE = Settings.interactive()
#: Defaults sized for a sub-second scenario 1–3 update on beam-1d (see bench/bench_app.py).
DEFAULT_N_S, DEFAULT_N_PHI = _INTERACTIVE.n_s, _INTERACTIVE.n_phi
#: The columns of the Discrepancy tab, in order: decoupled scenarios 1–3 and the KOH
#: baseline. The keys are the labels of the scenario buttons.
METHODS = {"1": Method.S1, "2": Method.S2, "3": Method.S3, "koh": Method.KOH}

def method_order(method: Method) -> int:
    """Sort key: scenario 1, 2, 3, then KOH."""
    return list(Method).index(method)


class ResultKey(NamedTuple):
    """What a cached :class:`~mdcore.MethodResult` depends on."""

    problem: ProblemKey
    n_waves: int
    method: MethodKey          # Settings.key(method): only the sizes that method uses
    seed: int


class MethodsDone(NamedTuple):
    """Results a job has computed: their cache keys, the results, and the saved metrics
    of a session file to compare them with (or None)."""

    keys: dict
    done: list
    expected: dict | None


class RunPlan(NamedTuple):
    """Everything a discrepancy job needs, taken from the state when it is submitted."""

    model: DiscrepancyModel   # for the cache and the waves' shared objects
    case: object
    grid: np.ndarray
    seed: int
    settings: Settings
    chosen: tuple             # the methods, in order
    problem: object
    key: ProblemKey
    waves: tuple              # the waves the run starts from
    target: int | None        # run exactly this many waves first (None: to convergence)
    n_shown: int              # waves the state shows now
    expected: dict | None = None
    waves_only: bool = False


def method_seconds(case, settings: Settings, method: Method) -> float:
    """Estimated seconds of one method's run (:func:`estimate_seconds`)."""
    n, out = case.X_train.shape[0], case.n_out
    return estimate_seconds(
        n, out, koh_steps=settings.n_iter if method is Method.KOH else 0,
        s3_pairs=settings.n_s * settings.n_phi if method is Method.S3 else 0,
        proposal=settings.proposal)


def discrepancy_job(plan: RunPlan, report, cancel):
    """The job of a run: its waves (:func:`waves_for`), then its methods
    (:func:`methods_for`); yields :class:`Note`, :class:`WaveDone`, :class:`MethodsDone`.
    The progress bar's share of each step is its estimated seconds."""
    too_much = work_problem(plan.case, plan.settings, plan.chosen)
    if too_much is not None:
        raise ValueError(too_much)
    hm = plan.model.waves_seconds() if plan.target is None and not plan.waves else 0.0
    methods = 0.0 if plan.waves_only else sum(
        method_seconds(plan.case, plan.settings, m) for m in plan.chosen)
    share = hm / (hm + methods) if hm + methods > 0 else 1.0
    waves = yield from waves_for(plan, lambda f, m: report(share * f, m))
    if not plan.waves_only:
        yield from methods_for(plan, waves, lambda f, m: report(share + (1 - share) * f, m),
                               cancel)


def waves_for(plan: RunPlan, report):
    """Run the waves ``plan`` needs (to convergence, or up to its target); yields each
    wave and returns the waves."""
    waves, target = plan.waves, plan.target
    if target is None:
        yield Note("No history match for these settings yet: running the waves until "
                   "convergence, then the discrepancy methods.")
    if target is None or len(waves) < target:
        for done in plan.model.wave_steps(plan.problem, plan.key, waves,
                                           lambda w: target is not None and w.index >= target,
                                           report):
            waves = done.waves
            yield done
        if target is not None and len(waves) != target:
            raise ValueError(f"The saved session has {target} wave(s), but the history "
                             f"match converged after {len(waves)}; the file does not "
                             "match this version's results.")
    elif len(waves) != plan.n_shown:
        yield WaveDone(plan.problem, plan.key, waves, len(waves), None)
    return waves


def methods_for(plan: RunPlan, waves: tuple, report, cancel):
    """Run the chosen methods not cached yet on ``waves``; yields :class:`MethodsDone`
    (scenarios 1–3 before KOH's chain starts, so they show while it runs). Each method's
    share of the progress is its estimated seconds (:func:`method_seconds`)."""
    model, key, settings, seed = plan.model, plan.key, plan.settings, plan.seed
    hm = model.history_match_of(plan.problem, waves)
    if hm.status == "ruled_out":
        raise ValueError(hm.message)
    keys = {m: ResultKey(key, len(waves), settings.key(m), seed) for m in plan.chosen}
    todo = [m for m in plan.chosen if not model.is_cached(keys[m])]
    hat = model.cached_phi_hat(ResultKey(key, len(waves), settings.key(Method.S1), seed))
    cost = np.array([method_seconds(plan.case, settings, m) for m in todo])
    start = np.concatenate([[0.0], np.cumsum(cost)]) / max(cost.sum(), 1e-12)
    done: list[MethodResult] = []
    for i, method in enumerate(todo):
        if method is Method.KOH and done:
            yield MethodsDone(keys, done, None)      # show 1–3 while the chain runs
            done = []
        result = run_method(
            plan.case, hm, method, settings, seed=seed, X_extra=plan.grid,
            log_params_hat=hat if method is Method.S2 else None,
            progress=lambda f, message, i=i: report(
                start[i] + (start[i + 1] - start[i]) * f, message),
            cancel=cancel)
        if method is Method.S1:
            hat = result.model.log_params_hat
        done.append(result)
    yield MethodsDone(keys, done, plan.expected)  # few updates: each one re-renders the page


class DiscrepancyModel(HistoryModel):
    """Discrepancy settings, the cache of computed results and the ones shown."""

    n_s = param.Integer(default=DEFAULT_N_S, bounds=(1, APP_MAX_N_S), label="N_s (θ samples)",
                        doc=tooltip("N_s, N_φ"))
    n_phi = param.Integer(default=DEFAULT_N_PHI, bounds=(1, APP_MAX_N_PHI),
                          label="N_φ (φ per θ)", doc=tooltip("N_s, N_φ"))
    paper_sizes = param.Boolean(default=False, label="Paper sizes")
    scenarios = param.ListSelector(default=[Method.S1, Method.S2, Method.S3],
                                   objects=METHODS, label="Scenarios",
                                   doc=" ".join(f"{t[0].upper()}{t[1:]}: {tooltip(t)}" for t in (
                                       "scenario 1", "scenario 2", "scenario 3", "KOH")))
    koh_chain = param.Selector(objects=list(KOH_CHAINS), default="fast", label="KOH chain",
                               doc="fast: 20,000 iterations (5,000 burn-in); paper: 150,000 "
                                   "(50,000 burn-in). The time grows with chain steps × "
                                   "outputs × training rows³.")
    proposal = param.Selector(objects=["adaptive", "prior"], default=_INTERACTIVE.proposal,
                              label="φ proposal (scenario 3)",
                              doc="adaptive (default, as on the command line): importance "
                                  "sampling that adapts a Student-t to the weights (reliable "
                                  "weights at any N_φ); prior: the paper's prior draws.")
    band = param.Selector(objects=[2, 3], default=3, label="Band (± k σ)")
    seed = param.Integer(default=0, bounds=(0, None), label="Seed")
    results = param.Dict(default={}, doc="Method -> MethodResult for the current settings "
                                         "(on_extra is the prediction on grid).")

    _restoring = False

    def _init_runs(self) -> None:
        self._cache: dict[ResultKey, MethodResult] = {}

    @param.depends("paper_sizes", watch=True)
    def _apply_paper_sizes(self):
        if self.paper_sizes:
            self.n_s, self.n_phi = PAPER_SIZES.get(self.base_case_name(),
                                                   PAPER_SIZES["beam-1d"])
        else:
            self.n_s, self.n_phi = DEFAULT_N_S, DEFAULT_N_PHI

    def method_settings(self) -> Settings:
        """The pipeline settings of the current controls (validated)."""
        return experiments.method_settings(self.param.values())

    def run_seconds(self, chain: str | None = None) -> float:
        """Estimated seconds of running the chosen methods (:func:`estimate_seconds`), with
        the KOH chain ``chain`` (default: the chosen one) if KOH is chosen."""
        c, steps = self.case, KOH_CHAINS[chain or self.koh_chain]["n_iter"]
        return estimate_seconds(c.X_train.shape[0], c.n_out,
                                koh_steps=steps if Method.KOH in self.scenarios else 0,
                                s3_pairs=self.n_s * self.n_phi if Method.S3 in self.scenarios
                                else 0, proposal=self.proposal)

    def announcements(self) -> dict[str, dict[str, str]]:
        """Label and tooltip (``description``) of each run button, by its CSS class
        ("next-wave", "run-convergence", "run-discrepancy"): the estimated seconds in the
        tooltip, and on the label when over :data:`ANNOUNCE_SECONDS`; and (key "koh") the
        KOH chain's tooltip with both chains' estimates on this case."""
        wave, waves = self.waves_seconds(False), self.waves_seconds()
        out: dict = {}
        for key, label, t, tip in (
                ("next-wave", "Next wave", wave, ""),
                ("run-convergence", "Run to convergence", wave,
                 f" a wave, at most {waves:.1f} s up to max waves"),
                ("run-discrepancy", "Run discrepancy", self.run_seconds(), " for the methods")):
            out[key] = {"description": f"Estimated {t:.1f} s{tip}.", "label": label + (
                f" (≈ {t:.0f} s)" if t > ANNOUNCE_SECONDS else "")}
        c = self.case
        koh = [estimate_seconds(c.X_train.shape[0], c.n_out, koh_steps=KOH_CHAINS[k]["n_iter"])
               for k in KOH_CHAINS]
        out["koh"] = (f"{self.param.koh_chain.doc} Estimated for KOH on {html_text(c.name)}: "
                      + ", ".join(f"{k} ≈ {t:.1f} s" for k, t in zip(KOH_CHAINS, koh))
                      + (" (over 3 s: the run button says so)."
                         if max(koh) > ANNOUNCE_SECONDS else "."))
        return out

    def _key(self, method: Method, settings: Settings | None = None, *,
             problem_key: ProblemKey | None = None, n_waves: int | None = None) -> ResultKey:
        settings = self.method_settings() if settings is None else settings
        return ResultKey(self._problem_key if problem_key is None else problem_key,
                         len(self.waves) if n_waves is None else n_waves,
                         settings.key(method), self.seed)

    def held_results(self) -> dict[Method, MethodResult]:
        """Every method's cached result for the current settings, shown or hidden (what a
        plot's axes must hold so that showing a method again does not rescale them)."""
        try:
            settings = self.method_settings()
        except ValueError:
            return {}
        keys = {m: self._key(m, settings) for m in Method}
        return {m: self._cache[k] for m, k in keys.items() if k in self._cache}

    def _refresh_results(self) -> None:
        """Show the cached results that match the current settings (no computation)."""
        held = self.held_results()
        self.results = {m: held[m] for m in self.scenarios if m in held}

    def is_cached(self, key: ResultKey) -> bool:
        """Whether a result for ``key`` is computed (any thread may ask)."""
        return key in self._cache

    def _waves_changed(self, fresh: bool) -> None:
        if fresh:
            self._cache = {}

    @param.depends("n_s", "n_phi", "seed", "scenarios", "koh_chain", "proposal", watch=True)
    def _discrepancy_settings_changed(self):
        # Served, one batch: the views see the cleared results together with the busy flag
        # of the recompute, so they keep the earlier plots (dimmed) instead of blanking
        # them. (Inline, the job runs inside this call, and its partial results must show.)
        with (param.parameterized.batch_call_watchers(self) if self.background
              else contextlib.nullcontext()):
            self._refresh_results()
            if self._restoring:
                return                  # open_session submits one job for everything
            # Only when the user has run discrepancy before, or is running it (a change
            # during the first run, with nothing cached yet, left the tab empty).
            running = self._jobs.busy and self._jobs.job.label == "discrepancy"
            if self.results.keys() != set(self.scenarios) and (
                    (self.waves and self._cache) or running):
                self.run_discrepancy()

    def cached_phi_hat(self, key: ResultKey):
        """φ̂ of a cached scenario-1 result on the same match and seed, or None.

        φ̂ depends on the match, the fit's settings and the seed, not on N_s, so scenario 2
        can reuse it. ``key`` is the scenario-1 key of the current settings.
        """
        for k, r in self._cache.items():
            if (k.method == key.method and k.problem == key.problem
                    and k.n_waves == key.n_waves and k.seed == key.seed):
                return r.model.log_params_hat
        return None

    def run_discrepancy(self) -> None:
        """Run the selected methods that are not cached for the current settings.

        With no history match yet (or after a history-match setting changed), the job
        first runs the waves until convergence, and the status line says so.
        """
        try:
            settings = self.method_settings()
        except ValueError as exc:
            self.report_error(str(exc))
            return
        if self.waves and self._settings_key() == self._problem_key:
            hm = self.history_match
            if hm.status == "ruled_out":
                self.report_error(hm.message)
                return
            keys = {m: self._key(m, settings) for m in sorted(self.scenarios, key=method_order)}
            if all(k in self._cache for k in keys.values()):
                self._refresh_results()
                return
        self._jobs.submit("discrepancy", partial(discrepancy_job, self._plan(settings)),
                          self._apply)

    def _plan(self, settings: Settings, n_waves: int | None = None,
              expected: dict | None = None, waves_only: bool = False) -> RunPlan:
        """The :class:`RunPlan` of a run with ``settings`` from the current state.

        Parameters
        ----------
        settings : Settings
        n_waves : int, optional
            Run exactly this many waves first (a restored session); default: use the
            current waves, or run to convergence when there are none.
        expected : dict, optional
            ``method value -> metrics dict`` of a saved session, checked when done.
        waves_only : bool, default=False
            Stop after the waves (a restored session without results).
        """
        problem, key, waves = self._current_problem()
        if n_waves is not None and len(waves) > n_waves:
            waves = waves[:n_waves]              # each wave depends only on the earlier ones
        return RunPlan(self, self.case, self.grid, self.seed, settings,
                       tuple(sorted(self.scenarios, key=method_order)), problem, key, waves,
                       n_waves if n_waves is not None else (len(waves) or None),
                       len(self.waves), expected, waves_only)

    def _apply_methods(self, message: MethodsDone) -> None:
        keys, done, expected = message
        for result in done:
            self._cache[keys[result.method]] = result
        advice = [w for result in done for w in result.warnings]
        if advice:
            self._report_notice("\n\n".join(advice))
        self._refresh_results()
        if expected is not None:
            self.status = session.compare_metrics(expected, self.results)
