"""Session state of the Model Discrepancy Explorer: parameters in, mdcore results out.

No widget code lives here. :class:`ExplorerState` holds the user's settings as ``param``
parameters, calls :mod:`mdcore` (history matching wave by wave, then
:func:`mdcore.pipeline.run_method` per method), and caches what it computed; the views
only display it.

Long work (a wave, a discrepancy run) goes through a :class:`~mdcore_app.jobs.JobRunner`:
by default it runs synchronously (tests, scripts); the served app sets ``background=True``
and a ``schedule`` function that hands results back to the session's event loop. A newer
request supersedes an older one, :meth:`ExplorerState.cancel` stops the running one, and
a failure of any kind becomes one notification with the earlier state put back.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import numpy as np
import param

from mdcore import cases, koh
from mdcore.history_matching import RULES, HistoryMatchResult, case_problem, next_wave
from mdcore.pipeline import (
    PAPER_SIZES,
    Method,
    MethodKey,
    MethodResult,
    Settings,
    run_method,
)

from .jobs import JobRunner

_INTERACTIVE = Settings.interactive()
#: Defaults sized for a sub-second scenario 1–3 update on beam-1d (see bench/bench_app.py).
DEFAULT_N_S, DEFAULT_N_PHI = _INTERACTIVE.n_s, _INTERACTIVE.n_phi
#: Resolution of the implausibility map (per axis) and of 2-D δ maps.
MAP_RESOLUTION = 60
GRID_2D = 30
#: The columns of the Discrepancy tab, in order: decoupled scenarios 1–3 and the KOH
#: baseline. The keys are the labels of the scenario buttons.
METHODS = {"1": Method.S1, "2": Method.S2, "3": Method.S3, "koh": Method.KOH}
#: KOH chain settings: the app's short chain and the paper's (SPEC §7).
KOH_CHAINS = {"fast": dict(koh.FAST), "paper": {"n_iter": koh.N_ITER, "burn_in": koh.BURN_IN}}


def method_order(method: Method) -> int:
    """Sort key: scenario 1, 2, 3, then KOH."""
    return list(Method).index(method)


class ProblemKey(NamedTuple):
    """The settings that define a history-matching problem; a change starts a new match."""

    case_name: str
    v_m: float
    threshold: float
    rule: str
    n_runs: int
    n_candidates: int
    max_waves: int
    convergence_ratio: float


class ResultKey(NamedTuple):
    """What a cached :class:`~mdcore.pipeline.MethodResult` depends on."""

    problem: ProblemKey
    n_waves: int
    method: MethodKey          # Settings.key(method): only the sizes that method uses
    seed: int


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
    """All state of one browser session.

    Parameters
    ----------
    background : bool, default=False
        Run long work on a worker thread (the served app).
    schedule : callable, optional
        ``schedule(fn)`` runs ``fn`` on the session's thread; default: at once.
    **params
        Initial values of the parameters below.
    """

    # --- case and history-matching controls -------------------------------------------
    case_name = param.Selector(objects=list(cases.names()), default="beam-1d", label="Case study")
    v_m = param.Number(default=0.05, bounds=(0.0, None), inclusive_bounds=(False, True),
                       softbounds=(0.001, 0.2), label="V_m",
                       doc="Model-discrepancy variance in the case's output units squared "
                           "(shear-5: of ω1; the other modes scale with their mean squared).")
    threshold = param.Number(default=3.0, bounds=(0.0, None), inclusive_bounds=(False, True),
                             softbounds=(1.0, 5.0), label="Threshold T")
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
    scenarios = param.ListSelector(default=[Method.S1, Method.S2, Method.S3],
                                   objects=METHODS, label="Scenarios",
                                   doc="Decoupled scenarios 1–3 and the Kennedy–O'Hagan "
                                       "baseline (koh), which calibrates θ and δ jointly.")
    koh_chain = param.Selector(objects=list(KOH_CHAINS), default="fast", label="KOH chain",
                               doc="fast: 20,000 iterations (5,000 burn-in); paper: 150,000 "
                                   "(50,000 burn-in), about 25 s on beam-1d.")
    proposal = param.Selector(objects=["adaptive", "prior"], default=_INTERACTIVE.proposal,
                              label="φ proposal (scenario 3)",
                              doc="adaptive: importance sampling that adapts a Student-t to the "
                                  "weights (reliable at small N_φ); prior: the paper's prior "
                                  "draws.")
    band = param.Selector(objects=[2, 3], default=3, label="Band (± k σ)")
    seed = param.Integer(default=0, bounds=(0, None), label="Seed")
    slice_x2 = param.Number(default=0.025, label="Slice at x₂",
                            doc="beam-2d: crack length [m] of the δ slice view.")

    # --- results (read by the views) -------------------------------------------------
    case = param.Parameter(doc="The loaded mdcore Case.")
    grid = param.Array(doc="(G, d_x) inputs at which the bands are drawn (plotting_grid).")
    waves = param.Parameter(default=(), doc="Tuple of the completed waves of the current match.")
    implausibility_maps = param.Dict(default={}, doc="wave index -> (t1, t2, I) for p = 2.")
    status = param.String(default="", doc="Status line of the history match.")
    results = param.Dict(default={}, doc="Method -> MethodResult for the current settings "
                                         "(on_extra is the prediction on grid).")
    busy = param.Boolean(default=False)
    task = param.String(default="")
    progress = param.Number(default=0.0, bounds=(0.0, 1.0))
    progress_message = param.String(default="", doc="What the running job is doing.")
    error = param.String(default="", doc="Last error message (shown as a notification).")
    n_errors = param.Integer(default=0, doc="Counts errors, so a repeated message still fires.")
    notice = param.String(default="", doc="Last numerical warning (e.g. a low ESS).")
    n_notices = param.Integer(default=0)

    def __init__(self, *, background: bool = False,
                 schedule: Callable[[Callable], object] | None = None, **params):
        super().__init__(**params)
        self._jobs = JobRunner(
            background=background, schedule=schedule,
            on_start=lambda label: self.param.update(busy=True, task=label, progress=0.0,
                                                     progress_message=""),
            on_progress=lambda f, message: self.param.update(progress=f,
                                                             progress_message=message),
            on_finish=lambda: self.param.update(busy=False, task="", progress_message=""),
            on_error=self._report_error, snapshot=self._snapshot, restore=self._restore)
        self._problem = None
        self._problem_key: ProblemKey | None = None
        self._hm = None
        self._cache: dict[ResultKey, MethodResult] = {}
        self._load_case()

    @property
    def background(self) -> bool:
        return self._jobs.background

    @property
    def jobs(self) -> JobRunner:
        """The session's job runner (its ``job`` is the newest job)."""
        return self._jobs

    # ------------------------------------------------------------------------------
    # Case

    @param.depends("case_name", watch=True)
    def _load_case(self):
        if self.case is not None and self.case_name == self.case.name:
            return                                   # put back after a failed load
        try:
            case = cases.load(self.case_name, seed=0)
        except Exception as exc:                     # noqa: BLE001 - any failure: keep the case
            if self.case is None:
                raise
            self._report_error(f"Could not load the case {self.case_name!r}, so "
                               f"{self.case.name} stays loaded: {exc}")
            self.case_name = self.case.name
            return
        self._jobs.drop()                            # drop work for the previous case
        self._problem, self._problem_key, self._cache = None, None, {}
        with param.parameterized.batch_call_watchers(self):
            self.case = case
            self.grid = plotting_grid(case)
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
            self.busy, self.task, self.progress, self.progress_message = False, "", 0.0, ""

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
    # Jobs

    def cancel(self) -> None:
        """Stop the running wave or discrepancy run; what it already showed stays."""
        if self._jobs.cancel():
            self.progress_message = "cancelling …"

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

    def reject(self, name: str, value, reason: Exception) -> None:
        """Report a typed value the parameter ``name`` refused (the field reverts)."""
        p = self.param[name]
        self._report_error(f"{p.label}: {value!r} is not allowed ({reason}). The field keeps "
                           f"{getattr(self, name)!r}.")

    def _report_error(self, message: str) -> None:
        self.param.update(error=message, n_errors=self.n_errors + 1)

    def _report_notice(self, message: str) -> None:
        self.param.update(notice=message, n_notices=self.n_notices + 1)

    # ------------------------------------------------------------------------------
    # History matching

    def _settings_key(self) -> ProblemKey:
        return ProblemKey(self.case_name, self.v_m, self.threshold, self.rule, self.n_runs,
                          self.n_candidates, self.max_waves, self.convergence_ratio)

    def _current_problem(self):
        """The problem for the current settings; a changed setting starts a new match."""
        key = self._settings_key()
        if key != self._problem_key:
            problem = case_problem(self.case, V_m=self.v_m_vector(), threshold=self.threshold,
                                   rule=self.rule, n_runs=self.n_runs,
                                   n_candidates=self.n_candidates, max_waves=self.max_waves,
                                   convergence_ratio=self.convergence_ratio, seed=0)
            return problem, key, ()
        return self._problem, key, self.waves

    def _wave_task(self, until_done: bool):
        def compute(report, cancel):
            problem, key, waves = self._current_problem()
            if waves and waves[-1].done:
                raise ValueError(f"{waves[-1].message} Lower the convergence ratio or raise "
                                 "max waves to refine further, or change a setting to start over.")
            total = problem.max_waves - len(waves)
            report(0.0, f"wave {len(waves) + 1}")
            while True:
                wave = next_wave(problem, waves)
                if wave.status == "ruled_out":
                    raise ValueError(wave.message + " The previous waves are kept.")
                waves = waves + (wave,)
                maps = self._implausibility_map(problem, wave)
                report(min(1.0, len(waves) / max(total, 1)), f"wave {wave.index} done")
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
        self._jobs.submit("wave", *self._wave_task(until_done=False))

    def run_to_convergence(self) -> None:
        """Run waves until converged, max waves, or everything is ruled out."""
        self._jobs.submit("waves", *self._wave_task(until_done=True))

    def _implausibility_map(self, problem, wave):
        """(t1, t2, I) on a MAP_RESOLUTION² grid of the θ box, for p = 2 only."""
        if problem.p != 2:
            return None
        b = problem.bounds
        t1 = np.linspace(b[0, 0], b[0, 1], MAP_RESOLUTION)
        t2 = np.linspace(b[1, 0], b[1, 1], MAP_RESOLUTION)
        T1, T2 = np.meshgrid(t1, t2, indexing="xy")
        I = problem.implausibility(np.column_stack([T1.ravel(), T2.ravel()]), wave.emulator)
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

    def method_settings(self) -> Settings:
        """The pipeline settings of the current controls (validated)."""
        return Settings(n_s=self.n_s, n_phi=self.n_phi, proposal=self.proposal,
                        **KOH_CHAINS[self.koh_chain])

    def _key(self, method: Method, settings: Settings | None = None) -> ResultKey:
        settings = self.method_settings() if settings is None else settings
        return ResultKey(self._problem_key, len(self.waves), settings.key(method), self.seed)

    def _refresh_results(self) -> None:
        """Show the cached results that match the current settings (no computation)."""
        try:
            settings = self.method_settings()
        except ValueError:
            self.results = {}
            return
        keys = {m: self._key(m, settings) for m in self.scenarios}
        self.results = {m: self._cache[k] for m, k in keys.items() if k in self._cache}

    @param.depends("n_s", "n_phi", "seed", "scenarios", "koh_chain", "proposal", watch=True)
    def _discrepancy_settings_changed(self):
        self._refresh_results()
        if self.results.keys() != set(self.scenarios) and self.waves and self._cache:
            self.run_discrepancy()      # only when the user has run discrepancy before

    def _cached_phi_hat(self, key: ResultKey):
        """φ̂ of a cached scenario-1 result on the same match and seed, or None.

        φ̂ depends on the match and the seed, not on N_s, so scenario 2 can reuse it.
        """
        for k, r in self._cache.items():
            if (k.method.method is Method.S1 and k.problem == key.problem
                    and k.n_waves == key.n_waves and k.seed == key.seed):
                return r.model.log_params_hat
        return None

    def run_discrepancy(self) -> None:
        """Run the selected methods that are not cached for the current settings."""
        if not self.waves:
            self._report_error("Run history matching first: the discrepancy scenarios need "
                               "θ samples from the non-implausible set.")
            return
        hm = self.history_match
        if hm.status == "ruled_out":
            self._report_error(hm.message)
            return
        try:
            settings = self.method_settings()
        except ValueError as exc:
            self._report_error(str(exc))
            return
        keys = {m: self._key(m, settings) for m in sorted(self.scenarios, key=method_order)}
        todo = [m for m, k in keys.items() if k not in self._cache]
        if not todo:
            self._refresh_results()
            return
        case, grid, seed = self.case, self.grid, self.seed
        hat = self._cached_phi_hat(keys.get(Method.S1, self._key(Method.S1, settings)))

        def compute(report, cancel):
            nonlocal hat
            done = []
            for i, method in enumerate(todo):
                if method is Method.KOH and done:
                    yield done                # show scenarios 1–3 while the chain runs
                    done = []
                result = run_method(
                    case, hm, method, settings, seed=seed, X_extra=grid,
                    log_params_hat=hat if method is Method.S2 else None,
                    progress=lambda f, message, i=i: report((i + f) / len(todo), message),
                    cancel=cancel)
                if method is Method.S1:
                    hat = result.model.log_params_hat
                done.append(result)
            yield done                # few updates: every re-render of the plots costs ~0.3 s

        def apply(done):
            for result in done:
                self._cache[keys[result.method]] = result
            advice = [w for result in done for w in result.warnings]
            if advice:
                self._report_notice("\n\n".join(advice))
            self._refresh_results()

        self._jobs.submit("discrepancy", compute, apply)
