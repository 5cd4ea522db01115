"""Session state of the Model Discrepancy Explorer: parameters in, mdcore results out.

No widget code lives here. :class:`ExplorerState` holds the user's settings as ``param``
parameters, calls :mod:`mdcore`, and caches what it computed; the views only display it.

Long work (a wave, a discrepancy run) goes through :meth:`ExplorerState._submit`: by
default it runs synchronously (tests, scripts); the served app sets ``background=True`` and
a ``schedule`` function that hands results back to the session's event loop. Every request
takes a new generation number; an older request notices at its next progress report (or
when it finishes) that it has been superseded and is dropped, so stale work never lands.
"""

from __future__ import annotations

import threading
import time
import warnings
from typing import Callable, NamedTuple

import numpy as np
import param

from mdcore import cases
from mdcore import koh
from mdcore.discrepancy import DiscrepancyModel, DiscrepancyPrediction, infer
from mdcore.gp import NumericalWarning
from mdcore.history_matching import (RULES, HistoryMatchResult, _score, case_problem,
                                     next_wave)
from mdcore.reproduce import PAPER_SIZES, koh_phi_prior, score

#: Defaults sized for a sub-second scenario 1–3 update on beam-1d (see bench/bench_app.py).
DEFAULT_N_S, DEFAULT_N_PHI = 100, 50
#: Resolution of the implausibility map (per axis) and of 2-D δ maps.
MAP_RESOLUTION = 60
GRID_2D = 30
#: Seconds between progress-bar updates sent to the browser.
PROGRESS_INTERVAL = 0.25
#: The columns of the Discrepancy tab: decoupled scenarios 1–3 and the KOH baseline.
SCENARIOS = (1, 2, 3, "koh")
#: KOH chain settings: the app's short chain and the paper's (SPEC §7).
KOH_CHAINS = {"fast": koh.FAST, "paper": {"n_iter": koh.N_ITER, "burn_in": koh.BURN_IN}}


def scenario_order(scenario) -> int:
    """Sort key: 1, 2, 3, then "koh"."""
    return SCENARIOS.index(scenario)


class Superseded(Exception):
    """A newer request replaced this one."""


class ScenarioResult(NamedTuple):
    """One scenario's model, predictions on the plotting grid and at the test inputs."""

    scenario: int | str            # 1, 2, 3 or "koh"
    model: DiscrepancyModel | koh.KOHModel
    grid: np.ndarray               # (G, d_x) plotting inputs
    on_grid: DiscrepancyPrediction
    on_test: DiscrepancyPrediction
    metrics: dict
    seconds: float


def plotting_grid(case) -> np.ndarray:
    """Inputs (G, d_x) at which the bands are drawn: fine in 1-D, a square grid in 2-D."""
    lo = np.minimum(case.X_train.min(axis=0), case.X_test.min(axis=0))
    hi = np.maximum(case.X_train.max(axis=0), case.X_test.max(axis=0))
    if case.d_x == 1:
        return np.linspace(lo[0], hi[0], 201)[:, None]
    g1, g2 = np.meshgrid(np.linspace(lo[0], hi[0], GRID_2D), np.linspace(lo[1], hi[1], GRID_2D),
                         indexing="xy")
    return np.column_stack([g1.ravel(), g2.ravel()])


class ExplorerState(param.Parameterized):
    """All state of one browser session."""

    # --- case and history-matching controls -------------------------------------------
    case_name = param.Selector(objects=list(cases.names()), default="beam-1d", label="Case study")
    v_m = param.Number(default=0.05, softbounds=(0.001, 0.2), label="V_m",
                       doc="Model-discrepancy variance in the case's output units squared "
                           "(shear-5: of ω1; the other modes scale with their mean squared).")
    threshold = param.Number(default=3.0, softbounds=(1.0, 5.0), label="Threshold T")
    rule = param.Selector(objects=list(RULES), default="max", label="Implausibility rule")
    n_runs = param.Integer(default=10, bounds=(1, None), label="Runs per wave")
    n_candidates = param.Integer(default=50_000, bounds=(100, None), label="Candidates per wave")
    max_waves = param.Integer(default=5, bounds=(1, 20), label="Max waves")
    convergence_ratio = param.Number(
        default=1.0, bounds=(0.001, 1.0), label="Convergence ratio",
        doc="Stop when the emulator variance is below this × (V_o + V_m); 1 is SPEC §5. "
            "Lower it to keep refining after the SPEC rule has converged.")
    selected_wave = param.Integer(default=0, bounds=(0, None), label="Wave shown")

    # --- discrepancy controls ----------------------------------------------------------
    n_s = param.Integer(default=DEFAULT_N_S, bounds=(1, None), label="N_s (θ samples)")
    n_phi = param.Integer(default=DEFAULT_N_PHI, bounds=(1, None), label="N_φ (φ per θ)")
    paper_sizes = param.Boolean(default=False, label="Paper sizes")
    scenarios = param.ListSelector(default=[1, 2, 3], objects=list(SCENARIOS), label="Scenarios",
                                   doc="Decoupled scenarios 1–3 and the Kennedy–O'Hagan "
                                       "baseline (koh), which calibrates θ and δ jointly.")
    koh_chain = param.Selector(objects=list(KOH_CHAINS), default="fast", label="KOH chain",
                               doc="fast: 20,000 iterations (5,000 burn-in); paper: 150,000 "
                                   "(50,000 burn-in), about 25 s on beam-1d.")
    band = param.Selector(objects=[2, 3], default=3, label="Band (± k σ)")
    seed = param.Integer(default=0, bounds=(0, None), label="Seed")
    slice_x2 = param.Number(default=0.025, label="Slice at x₂",
                            doc="beam-2d: crack length [m] of the δ slice view.")

    # --- results (read by the views) -------------------------------------------------
    case = param.Parameter(doc="The loaded mdcore Case.")
    waves = param.Parameter(default=(), doc="Tuple of the completed waves of the current match.")
    implausibility_maps = param.Dict(default={}, doc="wave index -> (t1, t2, I) for p = 2.")
    status = param.String(default="", doc="Status line of the history match.")
    results = param.Dict(default={}, doc="scenario -> ScenarioResult for the current settings.")
    busy = param.Boolean(default=False)
    task = param.String(default="")
    progress = param.Number(default=0.0, bounds=(0.0, 1.0))
    error = param.String(default="", doc="Last error message (shown as a notification).")
    n_errors = param.Integer(default=0, doc="Counts errors, so a repeated message still fires.")
    notice = param.String(default="", doc="Last numerical warning (e.g. a low ESS).")
    n_notices = param.Integer(default=0)

    def __init__(self, **params):
        self.background = params.pop("background", False)
        self.schedule: Callable[[Callable], None] = params.pop("schedule", lambda fn: fn())
        super().__init__(**params)
        self._generation = 0
        self._problem = None
        self._problem_key = None
        self._hm = None
        self._cache: dict = {}
        self._load_case()

    # ------------------------------------------------------------------------------
    # Case

    @param.depends("case_name", watch=True)
    def _load_case(self):
        case = cases.load(self.case_name, seed=0)
        self._generation += 1                        # drop work for the previous case
        self._problem, self._problem_key, self._cache = None, None, {}
        with param.parameterized.batch_call_watchers(self):
            self.case = case
            self.v_m = float(case.V_m[0])
            self.n_runs = max(10, 5 * case.p)
            self.n_candidates = 50_000 * case.p
            if case.d_x == 2:
                self.param.slice_x2.bounds = (float(case.X_train[:, 1].min()),
                                              float(case.X_train[:, 1].max()))
                self.slice_x2 = float(np.median(case.X_train[:, 1]))
            self.waves = ()
            self.implausibility_maps = {}
            self.results = {}
            self.selected_wave = 0
            self.status = f"{case.title}. Press “Next wave” or “Run to convergence”."
            self.busy, self.task, self.progress = False, "", 0.0

    @param.depends("paper_sizes", watch=True)
    def _apply_paper_sizes(self):
        if self.paper_sizes:
            self.n_s, self.n_phi = PAPER_SIZES[self.case_name]
        else:
            self.n_s, self.n_phi = DEFAULT_N_S, DEFAULT_N_PHI

    def v_m_vector(self) -> np.ndarray:
        """V_m per output: ``v_m`` for output 1, scaled by (z̄_i / z̄_1)² for the others."""
        zbar = np.abs(self.case.z_train.mean(axis=0))
        return self.v_m * (zbar / zbar[0]) ** 2

    # ------------------------------------------------------------------------------
    # Background execution with supersession

    def _submit(self, label: str, compute: Callable, apply: Callable) -> None:
        """Run ``compute(progress)``, a generator of partial results, and ``apply`` each.

        ``apply`` runs on the session's thread (via :attr:`schedule`) and only while the
        request is the newest. A ``ValueError`` becomes :attr:`error`; earlier results stay.
        """
        self._generation += 1
        gen = self._generation
        self.busy, self.task, self.progress = True, label, 0.0

        def current() -> bool:
            return gen == self._generation

        last = [0.0, -1.0]                               # time and fraction last shown

        def report(fraction: float) -> None:
            if not current():
                raise Superseded
            now = time.perf_counter()
            if now - last[0] < PROGRESS_INTERVAL and fraction - last[1] < 0.1:
                return                                   # at most ~4 updates a second
            last[:] = now, fraction
            self.schedule(lambda: current() and self.param.update(progress=float(fraction)))

        def finish() -> None:
            if current():
                self.param.update(busy=False, task="", progress=1.0)

        def fail(exc: Exception) -> None:
            if current():
                self.param.update(busy=False, task="")
                self._report_error(str(exc))

        def run() -> None:
            try:
                for partial in compute(report):
                    if not current():
                        return
                    self.schedule(lambda p=partial: current() and apply(p))
            except Superseded:
                return
            except ValueError as exc:
                self.schedule(lambda e=exc: fail(e))
                return
            self.schedule(finish)

        if self.background:
            threading.Thread(target=run, name=f"mdcore-{label}", daemon=True).start()
        else:
            run()

    def _report_error(self, message: str) -> None:
        self.param.update(error=message, n_errors=self.n_errors + 1)

    def _report_notice(self, message: str) -> None:
        self.param.update(notice=message, n_notices=self.n_notices + 1)

    # ------------------------------------------------------------------------------
    # History matching

    def _settings(self) -> tuple:
        return (self.case_name, self.v_m, self.threshold, self.rule, self.n_runs,
                self.n_candidates, self.max_waves, self.convergence_ratio)

    def _current_problem(self):
        """The problem for the current settings; a changed setting starts a new match."""
        key = self._settings()
        if key != self._problem_key:
            problem = case_problem(self.case, V_m=self.v_m_vector(), threshold=self.threshold,
                                   rule=self.rule, n_runs=self.n_runs,
                                   n_candidates=self.n_candidates, max_waves=self.max_waves,
                                   convergence_ratio=self.convergence_ratio, seed=0)
            return problem, key, ()
        return self._problem, key, self.waves

    def _wave_task(self, until_done: bool):
        def compute(report):
            problem, key, waves = self._current_problem()
            if waves and waves[-1].done:
                raise ValueError(f"{waves[-1].message} Lower the convergence ratio or raise "
                                 "max waves to refine further, or change a setting to start over.")
            total = problem.max_waves - len(waves)
            while True:
                wave = next_wave(problem, waves)
                if wave.status == "ruled_out":
                    raise ValueError(wave.message + " The previous waves are kept.")
                waves = waves + (wave,)
                maps = self._implausibility_map(problem, wave)
                report(min(1.0, len(waves) / max(total, 1)))
                yield problem, key, waves, wave.index, maps
                if not until_done or wave.done:
                    return

        def apply(partial):
            problem, key, waves, index, maps = partial
            fresh = key != self._problem_key
            self._problem, self._problem_key = problem, key
            new_maps = {} if fresh else dict(self.implausibility_maps)
            if maps is not None:
                new_maps[index] = maps
            if fresh:
                self._cache = {}
            self.param.update(waves=waves, implausibility_maps=new_maps, selected_wave=index,
                              status=waves[-1].message)
            self._refresh_results()          # results of other wave counts are not shown

        return compute, apply

    def next_wave(self) -> None:
        """Run one more wave (a changed setting starts a new history match)."""
        self._submit("wave", *self._wave_task(until_done=False))

    def run_to_convergence(self) -> None:
        """Run waves until converged, max waves, or everything is ruled out."""
        self._submit("waves", *self._wave_task(until_done=True))

    def _implausibility_map(self, problem, wave):
        """(t1, t2, I) on a MAP_RESOLUTION² grid of the θ box, for p = 2 only."""
        if problem.p != 2:
            return None
        b = problem.bounds
        t1 = np.linspace(b[0, 0], b[0, 1], MAP_RESOLUTION)
        t2 = np.linspace(b[1, 0], b[1, 1], MAP_RESOLUTION)
        T1, T2 = np.meshgrid(t1, t2, indexing="xy")
        I, _ = _score(problem, wave.emulator, np.column_stack([T1.ravel(), T2.ravel()]))
        return t1, t2, I.reshape(T1.shape)

    @property
    def history_match(self) -> HistoryMatchResult | None:
        """The current history match, or None before the first wave."""
        if not self.waves:
            return None
        if self._hm is None or self._hm.waves is not self.waves:   # keeps θ_MAP cached
            self._hm = HistoryMatchResult(self._problem, self.waves)
        return self._hm

    # ------------------------------------------------------------------------------
    # Discrepancy

    def _key(self, scenario) -> tuple:
        if scenario == "koh":                    # θ and φ come from KOH's own chain
            return (self._problem_key, len(self.waves), scenario, self.koh_chain, 0, self.seed)
        return (self._problem_key, len(self.waves), scenario, self.n_s,
                1 if scenario < 3 else self.n_phi, self.seed)

    def _refresh_results(self) -> None:
        """Show the cached results that match the current settings (no computation)."""
        self.results = {s: self._cache[self._key(s)] for s in self.scenarios
                        if self._key(s) in self._cache}

    @param.depends("n_s", "n_phi", "seed", "scenarios", "koh_chain", watch=True)
    def _discrepancy_settings_changed(self):
        self._refresh_results()
        if self.results.keys() != set(self.scenarios) and self.waves and self._cache:
            self.run_discrepancy()      # only when the user has run discrepancy before

    def run_discrepancy(self) -> None:
        """Infer the selected scenarios that are not cached for the current settings."""
        if not self.waves:
            self._report_error("Run history matching first: the discrepancy scenarios need "
                               "θ samples from the non-implausible set.")
            return
        hm = self.history_match
        if hm.status == "ruled_out":
            self._report_error(hm.message)
            return
        todo = [s for s in sorted(self.scenarios, key=scenario_order)
                if self._key(s) not in self._cache]
        if not todo:
            self._refresh_results()
            return
        case = self.case
        keys = {s: self._key(s) for s in todo}
        n_s, n_phi, seed, chain = self.n_s, self.n_phi, self.seed, KOH_CHAINS[self.koh_chain]
        grid = plotting_grid(case)
        # φ̂ depends on the match and the seed, not on N_s: reuse a cached scenario-1 fit.
        same_fit = self._key(1)[:3] + self._key(1)[5:]
        hat = next((r.model.log_params_hat for k, r in self._cache.items()
                    if k[:3] + k[5:] == same_fit), None)

        def compute(report):
            nonlocal hat
            X_all = np.vstack([grid, case.X_test])
            G = grid.shape[0]
            decoupled = [s for s in todo if s != "koh"]
            theta = hm.posterior_samples(n_s, seed=seed) if decoupled else None
            done = []

            def finish(s, model, pred, t0):
                on_grid = DiscrepancyPrediction(*(a[:G] for a in pred))
                on_test = DiscrepancyPrediction(*(a[G:] for a in pred))
                done.append(ScenarioResult(s, model, grid, on_grid, on_test,
                                           score(case, on_test), time.perf_counter() - t0))

            for i, s in enumerate(todo):
                t0 = time.perf_counter()

                def sub(f, i=i):
                    report((i + 0.5 * f) / len(todo))

                with warnings.catch_warnings(record=True) as caught:
                    warnings.simplefilter("always", NumericalWarning)
                    if s == "koh":
                        if done:            # show scenarios 1–3 while the chain runs
                            yield done
                            done = []
                        model = koh.infer(hm.waves[-1].emulator, case.X_train, case.z_train,
                                          theta_prior=case.theta_prior, bounds=case.theta_bounds,
                                          phi_prior=koh_phi_prior(case), seed=seed,
                                          progress=sub, **chain)
                    else:
                        model = infer(case.simulate, theta, case.X_train, case.z_train,
                                      scenario=s, theta_map=hm.theta_map, n_phi=n_phi,
                                      phi_prior=case.phi_prior, seed=seed,
                                      log_params_hat=hat if s == 2 else None, progress=sub)
                for w in caught:
                    if issubclass(w.category, NumericalWarning):
                        self.schedule(lambda m=str(w.message): self._report_notice(m))
                if s == 1:
                    hat = model.log_params_hat
                pred = model.predict(X_all, progress=lambda f, i=i: report((i + 0.5 + 0.5 * f)
                                                                           / len(todo)))
                finish(s, model, pred, t0)
            yield done              # few updates: every re-render of the plots costs ~0.3 s

        def apply(done):
            for result in done:
                self._cache[keys[result.scenario]] = result
            self._refresh_results()

        self._submit("discrepancy", compute, apply)
