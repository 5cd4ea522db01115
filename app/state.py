"""Session state of the Model Discrepancy Explorer: parameters in, mdcore results out.

No widget code lives here. :class:`ExplorerState` holds the user's settings as ``param``
parameters, calls :mod:`mdcore` (history matching wave by wave, then
:func:`mdcore.run_method` per method), and caches what it computed; the views
only display it.

Long work (a wave, a discrepancy run) goes through a :class:`~mdcore_app.jobs.JobRunner`:
by default it runs synchronously (tests, scripts); the served app sets ``background=True``
and a ``schedule`` function that hands results back to the session's event loop. A newer
request supersedes an older one, :meth:`ExplorerState.cancel` stops the running one, and
a failure of any kind becomes one notification with the earlier state put back.
"""

from __future__ import annotations

import contextlib
import json
import threading
from collections.abc import Callable
from typing import NamedTuple

import numpy as np
import param
import scipy.stats

from mdcore import _cases as cases
from mdcore import _koh as koh
from mdcore._case_file import with_measurements
from mdcore._cases import Case
from mdcore._history_matching import (
    MULTIVARIATE,
    RULE_NAMES,
    HistoryMatchResult,
    case_problem,
    next_wave,
)
from mdcore._pipeline import (
    PAPER_SIZES,
    Method,
    MethodKey,
    MethodResult,
    Settings,
    run_method,
)

from . import session
from .jobs import JobRunner

_INTERACTIVE = Settings.interactive()
#: Defaults sized for a sub-second scenario 1–3 update on beam-1d (see bench/bench_app.py).
DEFAULT_N_S, DEFAULT_N_PHI = _INTERACTIVE.n_s, _INTERACTIVE.n_phi
#: Resolution of the implausibility map (per axis).
MAP_RESOLUTION = 60
#: Points of the 1-D bands: smooth at a third of the page (a GP band between points 1 % of
#: the span apart is straight to the eye), and the mixture of scenario 3 predicts at them
#: as well as at the test inputs (201 were 40 % of shear-5's scenario-3 run).
GRID_1D = 101
#: Points per axis of the 2-D δ maps: beam-2d's test grid (20 × 20 over the same span), so
#: the maps show the very predictions the metrics score, and the grid costs no second
#: prediction (``run_method`` predicts once at inputs that are both; 30 × 30 made
#: scenario 3's mixture 1,300 points instead of 400, 0.9 s of a 1.5 s run).
GRID_2D = 20
#: The columns of the Discrepancy tab, in order: decoupled scenarios 1–3 and the KOH
#: baseline. The keys are the labels of the scenario buttons.
METHODS = {"1": Method.S1, "2": Method.S2, "3": Method.S3, "koh": Method.KOH}
#: KOH chain settings: the app's short chain and the paper's (SPEC §7); the app runs no
#: longer chain (the library takes up to mdcore._mcmc.MAX_CHAIN = 10⁸ steps).
KOH_CHAINS = {"fast": dict(koh.FAST), "paper": {"n_iter": koh.N_ITER, "burn_in": koh.BURN_IN}}

# The app's own limits, tighter than the library's (which only refuse what cannot fit in
# memory): each keeps one click of one session within about a minute and well under 1 GB on
# the built-in cases, and the command line (python -m mdcore reproduce / run) takes more.
#: Candidates per wave (library: 10⁷). A wave scores each at every observed input, in
#: chunks (memory does not grow), and later waves walk them through the earlier waves.
APP_MAX_CANDIDATES = 1_000_000
#: Simulator runs per wave (library: 10⁴). The emulator factorises runs × runs over all
#: waves so far.
APP_MAX_RUNS = 100
#: θ samples and φ per θ (library: 10⁵ each and 10⁸ pairs): at most 10⁶ (θ, φ) pairs, the
#: paper's largest (beam-2d: 1000 × 1000).
APP_MAX_N_S = APP_MAX_N_PHI = 1_000
#: Work of one run of scenario 3 and of KOH, in units of (θ, φ) pairs or chain steps ×
#: outputs × training rows³ (each pair or step factorises an N × N covariance per output):
#: beam-2d at the paper's sizes (10⁶ pairs × 64³ = 2.6 × 10¹¹, the paper chain
#: 150,000 × 64³ = 3.9 × 10¹⁰) is the most a built-in case asks for; an upload with many
#: training rows reaches these with smaller N_s × N_φ or the fast chain.
MAX_S3_WORK, MAX_KOH_WORK = 1e12, 4e10
#: What the app says when a value is beyond one of its limits.
APP_LIMITS = {
    "n_candidates": f"The app scores at most {APP_MAX_CANDIDATES:,} candidates per wave "
                    "(a wave then takes seconds); the command line takes up to 10,000,000.",
    "n_runs": f"The app runs at most {APP_MAX_RUNS} simulator runs per wave (its emulator "
              "factorises all runs × all runs); the command line takes up to 10,000.",
    "n_s": f"The app takes at most {APP_MAX_N_S:,} θ samples and {APP_MAX_N_PHI:,} φ per θ "
           "(10⁶ pairs, the paper's largest; a minute or so); the command line takes more.",
}
APP_LIMITS["n_phi"] = APP_LIMITS["n_s"]


def work_problem(case, settings: Settings, methods) -> str | None:
    """Why the app will not run ``methods`` on ``case`` with ``settings`` (scenario 3 or
    KOH beyond :data:`MAX_S3_WORK` / :data:`MAX_KOH_WORK`), or None."""
    n = case.X_train.shape[0]
    per = case.n_out * float(n) ** 3
    if Method.S3 in methods and settings.n_s * settings.n_phi * per > MAX_S3_WORK:
        most = int(MAX_S3_WORK / per)
        return (f"Scenario 3 with N_s × N_φ = {settings.n_s * settings.n_phi:,} pairs on "
                f"{n} training rows × {case.n_out} output(s) is more than the app runs in "
                f"one go (minutes to hours): every pair factorises a {n} × {n} covariance. "
                f"Lower N_s × N_φ to at most {most:,}, or run it from the command line.")
    if Method.KOH in methods and settings.n_iter * per > MAX_KOH_WORK:
        return (f"KOH with a {settings.n_iter:,}-step chain on {n} training rows × "
                f"{case.n_out} output(s) is more than the app runs in one go (minutes to "
                f"hours): every step factorises a {n} × {n} covariance. Choose the fast "
                "chain, fewer training rows, or run it from the command line "
                "(python -m mdcore run … --methods koh).")
    return None


def allowed_values(p: param.Parameter) -> str:
    """What the parameter ``p`` accepts, in words: "a whole number from 1 to 100", "a
    number greater than 0", "one of max, 2nd max"."""
    if isinstance(p, param.Selector):
        return "one of " + ", ".join(str(o) for o in p.objects)
    if not isinstance(p, param.Number):
        return "a value of the field's kind"
    kind = "a whole number" if isinstance(p, param.Integer) else "a number"
    lo, hi = p.bounds or (None, None)
    lo_in, hi_in = getattr(p, "inclusive_bounds", (True, True))
    hi = hi if hi is not None and hi <= 1e7 else None         # not a limit worth saying

    def num(v) -> str:
        return f"{int(v):,}" if float(v).is_integer() else f"{v:g}"

    if lo is not None and hi is not None and lo_in and hi_in:
        return f"{kind} from {num(lo)} to {num(hi)}"
    parts = []
    if lo is not None:
        parts.append(f"{'at least' if lo_in else 'greater than'} {num(lo)}")
    if hi is not None:
        parts.append(f"{'at most' if hi_in else 'less than'} {num(hi)}")
    return kind + (" " + " and ".join(parts) if parts else "")


def method_order(method: Method) -> int:
    """Sort key: scenario 1, 2, 3, then KOH."""
    return list(Method).index(method)


#: The teaching preset's wave-1 design and runs per wave: small enough that the waves
#: visibly shrink NROY (beam-1d: 5 waves, 34.8 → 21.2 %; beam-2d: 3 waves, 54.5 → 37.7 %,
#: with the true θ non-implausible), then ``TEACHING_RATIO`` × (V_o + V_m) to converge.
#: shear-5 keeps its own 27-run design (None): its data pin only E/ρ, so NROY stays about
#: 65 % whatever the design, and a 4-run emulator wrongly ruled out a sixth of the box.
TEACHING = {"beam-1d": (4, 3), "beam-2d": (2, 1), "shear-5": (None, 15)}
TEACHING_RATIO, TEACHING_MAX_WAVES = 0.1, 6


def teaching_design(case, base_name: str) -> np.ndarray:
    """The teaching preset's wave-1 design: a seeded Latin hypercube of a few runs, or the
    case's own design where :data:`TEACHING` says None; shape (R0, p)."""
    r0 = TEACHING.get(base_name, (case.p + 2, case.p))[0]
    if r0 is None:
        return case.initial_design
    lhs = scipy.stats.qmc.LatinHypercube(d=case.p, seed=np.random.default_rng(0))
    b = case.theta_bounds
    return scipy.stats.qmc.scale(lhs.random(r0), b[:, 0], b[:, 1])


class ProblemKey(NamedTuple):
    """The settings that define a history-matching problem; a change starts a new match."""

    case_name: str
    preset: str
    v_m: float
    v_m_length: float
    threshold: float
    rule: str
    n_runs: int
    n_candidates: int
    max_waves: int
    convergence_ratio: float


class ResultKey(NamedTuple):
    """What a cached :class:`~mdcore.MethodResult` depends on."""

    problem: ProblemKey
    n_waves: int
    method: MethodKey          # Settings.key(method): only the sizes that method uses
    seed: int


#: The controls of the history match, restored with a case's results when switching back.
HM_CONTROLS = ("preset", "v_m", "v_m_length", "threshold", "rule", "n_runs", "n_candidates",
               "max_waves", "convergence_ratio")


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
        return np.linspace(lo[0], hi[0], GRID_1D)[:, None]
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
    output = param.String(default="", label="Output",
                          doc="The output whose plots are shown, for cases with several "
                              "(shear-5's five modes): one at a time, so each plot is "
                              "readable and a change redraws a few plots, not all.")
    preset = param.Selector(
        objects=["teaching", "paper"], default="teaching", label="Preset",
        doc="teaching: a wave-1 design of a few runs and a strict convergence rule, so you "
            "can watch 3–5 waves shrink the non-implausible set; paper: the paper's design "
            "(SPEC §5), which converges after one wave.")
    v_m = param.Number(default=0.05, bounds=(0.0, 1e12), inclusive_bounds=(False, True),
                       softbounds=(0.001, 0.2), label="V_m",
                       doc="Model-discrepancy variance in the case's output units squared "
                           "(shear-5: of ω1; the other modes scale with their mean squared).")
    threshold = param.Number(default=3.0, bounds=(0.0, 1e6), inclusive_bounds=(False, True),
                             softbounds=(1.0, 5.0), label="Threshold T")
    rule = param.Selector(
        objects=list(RULE_NAMES), default="max", label="Implausibility rule",
        doc="max / 2nd max / 3rd max: each output and input scored alone, ruled out above T. "
            f"{MULTIVARIATE}: I_M² = (z − E f)ᵀ (V_o + V_m + V_em)⁻¹ (z − E f) over all points "
            "at once, ruled out above the χ² quantile at 0.995 (degrees of freedom = points × "
            "outputs; shown on the map) instead of T; ℓ_m correlates V_m between inputs "
            "(0: independent).")
    v_m_length = param.Number(
        default=0.0, bounds=(0.0, 1e6), label="ℓ_m (V_m correlation length)",
        doc="Correlation length of the model discrepancy variance over the inputs (Matérn "
            "3/2, in input units); 0: V_m independent at each input. Used by the "
            "multivariate rule (the max rules use only V_m's diagonal).")
    n_runs = param.Integer(default=10, bounds=(1, APP_MAX_RUNS), label="Runs per wave")
    n_candidates = param.Integer(default=50_000, bounds=(100, APP_MAX_CANDIDATES),
                                 label="Candidates per wave")
    max_waves = param.Integer(default=5, bounds=(1, 20), label="Max waves")
    convergence_ratio = param.Number(
        default=1.0, bounds=(0.001, 1.0), label="Convergence ratio",
        doc="Stop when the emulator variance is below this × (V_o + V_m); 1 is SPEC §5. "
            "Lower it to keep refining after the SPEC rule has converged.")
    selected_wave = param.Integer(default=0, bounds=(0, None), label="Wave shown")

    # --- discrepancy controls ----------------------------------------------------------
    n_s = param.Integer(default=DEFAULT_N_S, bounds=(1, APP_MAX_N_S), label="N_s (θ samples)")
    n_phi = param.Integer(default=DEFAULT_N_PHI, bounds=(1, APP_MAX_N_PHI),
                          label="N_φ (φ per θ)")
    paper_sizes = param.Boolean(default=False, label="Paper sizes")
    scenarios = param.ListSelector(default=[Method.S1, Method.S2, Method.S3],
                                   objects=METHODS, label="Scenarios",
                                   doc="Decoupled scenarios 1–3 and the Kennedy–O'Hagan "
                                       "baseline (koh), which calibrates θ and δ jointly.")
    koh_chain = param.Selector(objects=list(KOH_CHAINS), default="fast", label="KOH chain",
                               doc="fast: 20,000 iterations (5,000 burn-in); paper: 150,000 "
                                   "(50,000 burn-in), 0.4–1.2 s on beam-1d (compiled; "
                                   "10–50 s on the NumPy backend), by machine.")
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
                 schedule: Callable[[Callable], object] | None = None,
                 own_cases: tuple[Case, ...] = (), **params):
        #: Cases of this session beyond the built-in ones: from ``--case`` files, and
        #: uploaded measurements (name -> (Case, built-in base name or None, CSV text or
        #: None, file name or None)).
        self._own: dict[str, tuple[Case, str | None, str | None, str | None]] = {
            c.name: (c, None, None, None) for c in own_cases}
        #: Results and history-match controls of the cases switched away from.
        self._kept: dict[str, tuple[dict, Snapshot]] = {}
        self._restoring = False
        super().__init__(**params)
        if self._own:
            self.param.case_name.objects = list(cases.names()) + list(self._own)
        self._jobs = JobRunner(
            background=background, schedule=schedule,
            on_start=lambda label: self.param.update(busy=True, task=label, progress=0.0,
                                                     progress_message=""),
            on_progress=lambda f, message: self.param.update(progress=f,
                                                             progress_message=message),
            on_finish=lambda: self.param.update(busy=False, task="", progress_message=""),
            on_error=self.report_error, snapshot=self._snapshot, restore=self._restore)
        self._problem = None
        self._problem_key: ProblemKey | None = None
        self._hm = None
        self._hm_lock = threading.Lock()
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
    def _load_case(self, replace: bool = False):
        """Load the case ``case_name`` names; ``replace``: it is the current case with new
        data (an upload or a session file of the same name), whose results are dropped.
        ``case`` goes from one case to the next, never through None (its watchers draw it)."""
        if not replace and self.case is not None and self.case_name == self.case.name:
            return                                   # put back after a failed load
        try:
            case = (self._own[self.case_name][0] if self.case_name in self._own
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
            self.output = case.output_names[0]
            self.grid = plotting_grid(case)
            self.v_m = float(case.V_m[0])
            self.v_m_length = float(np.max(case.V_m_length))
            self._apply_preset()
            self.n_candidates = min(50_000 * case.p, APP_MAX_CANDIDATES)
            if case.d_x == 2:
                self.param.slice_x2.bounds = (float(case.X_train[:, 1].min()),
                                              float(case.X_train[:, 1].max()))
                u2 = np.unique(self.grid[:, 1])     # a row of the grid: the one drawn
                self.slice_x2 = float(u2[np.argmin(np.abs(u2 - np.median(case.X_train[:, 1])))])
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

    def base_case_name(self) -> str:
        """The built-in case the current case builds on (itself, if built-in)."""
        own = self._own.get(self.case_name)
        return self.case_name if own is None else (own[1] or self.case_name)

    @property
    def output_index(self) -> int:
        """Index of ``output`` in the case's outputs (``_check_output`` keeps it one)."""
        return self.case.output_names.index(self.output)

    @param.depends("output", watch=True)
    def _check_output(self):
        """An output the case does not have: one notification, and the first output."""
        names = self.case.output_names
        if self.output not in names:
            bad, self.output = self.output, names[0]
            self.report_error(f"Output: {bad!r} is not an output of {self.case.name}; it "
                              f"has {', '.join(names)}. Showing {names[0]}.")

    @param.depends("preset", watch=True)
    def _apply_preset(self):
        """Runs per wave, convergence ratio and max waves of the preset (the wave-1
        design follows the preset in :meth:`_current_problem`)."""
        if self.preset == "teaching":
            runs = TEACHING.get(self.base_case_name(), (0, self.case.p))[1]
            self.param.update(n_runs=runs, convergence_ratio=TEACHING_RATIO,
                              max_waves=TEACHING_MAX_WAVES)
        else:
            self.param.update(n_runs=max(10, 5 * self.case.p), convergence_ratio=1.0,
                              max_waves=5)

    @param.depends("paper_sizes", watch=True)
    def _apply_paper_sizes(self):
        if self.paper_sizes:
            self.n_s, self.n_phi = PAPER_SIZES.get(self.base_case_name(),
                                                   PAPER_SIZES["beam-1d"])
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
        """Report a typed value the parameter ``name`` refused (the field reverts) in plain
        words: what is allowed, never param's own message (it names the class, as in
        ``ExplorerState.v_m``); for the app's own limits (:data:`APP_LIMITS`), also why."""
        p = self.param[name]
        if name in APP_LIMITS and isinstance(value, int) and not isinstance(value, bool) \
                and value > p.bounds[1]:
            why = (f"{p.label}: {value:,} is not allowed (at most {p.bounds[1]:,}: "
                   f"{APP_LIMITS[name].rstrip('.')}).")
        else:
            shown = "an empty field" if value is None else repr(value)
            why = f"{p.label}: {shown} is not allowed ({allowed_values(p)})."
        self.report_error(f"{why} The field keeps {getattr(self, name)!r}.")

    def report_error(self, message: str) -> None:
        """Show ``message`` as one error notification."""
        self.param.update(error=message, n_errors=self.n_errors + 1)

    def _report_notice(self, message: str) -> None:
        self.param.update(notice=message, n_notices=self.n_notices + 1)

    # ------------------------------------------------------------------------------
    # History matching

    def _settings_key(self) -> ProblemKey:
        return ProblemKey(self.case_name, self.preset, self.v_m, self.v_m_length,
                          self.threshold, self.rule,
                          self.n_runs,
                          self.n_candidates, self.max_waves, self.convergence_ratio)

    def _current_problem(self):
        """The problem for the current settings; a changed setting starts a new match."""
        key = self._settings_key()
        if key != self._problem_key:
            design = ({"initial_design": teaching_design(self.case, self.base_case_name())}
                      if self.preset == "teaching" else {})
            problem = case_problem(self.case, V_m=self.v_m_vector(),
                                   V_m_length=self.v_m_length, threshold=self.threshold,
                                   rule=self.rule, n_runs=self.n_runs,
                                   n_candidates=self.n_candidates, max_waves=self.max_waves,
                                   convergence_ratio=self.convergence_ratio, seed=0,
                                   **design)
            return problem, key, ()
        return self._problem, key, self.waves

    def _wave_steps(self, problem, key, waves, stop, report):
        """Run waves on a worker thread and yield ``("wave", ...)`` partial results.

        ``stop(wave)`` says when to end after ``wave`` (converged waves always end).
        """
        total = max(problem.options.max_waves - len(waves), 1)
        first = len(waves)
        report(0.0, f"wave {first + 1}")
        while True:
            k = len(waves)            # the wave's steps report (and check Cancel) as it runs
            wave = next_wave(problem, waves, progress=lambda f, k=k: report(
                min(1.0, (k - first + f) / total), f"wave {k + 1}"))
            if wave.status == "ruled_out":
                raise ValueError(wave.message + " The previous waves are kept.")
            waves = waves + (wave,)
            # θ_MAP here, where Cancel reaches it, not when the views first draw it on the
            # session's thread (seconds for a large upload).
            self._history_match_of(problem, waves).compute_theta_map(
                lambda f, k=k: report(min(1.0, (k - first + 1) / total), f"wave {k + 1}: θ_MAP"))
            maps = self._implausibility_map(problem, wave)
            report(min(1.0, (len(waves) - first) / total), f"wave {wave.index} done")
            yield "wave", (problem, key, waves, wave.index, maps)
            if wave.done or stop(wave):
                return

    def _apply_wave(self, partial) -> None:
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

    def _apply(self, partial) -> None:
        """Apply a ``("wave", ...)`` or ``("methods", ...)`` partial result of a job."""
        kind, payload = partial
        if kind == "note":
            self.status = payload
            return
        (self._apply_wave if kind == "wave" else self._apply_methods)(payload)

    def _wave_task(self, until_done: bool):
        def compute(report, cancel):
            problem, key, waves = self._current_problem()
            if waves and waves[-1].done:
                # Nothing to compute: say so calmly (a notice, not an error).
                yield "note", (f"Already converged after {len(waves)} wave(s): "
                               f"{waves[-1].message} To refine further, lower the "
                               "convergence ratio or raise max waves; a changed setting "
                               "starts a new history match.")
                return
            yield from self._wave_steps(problem, key, waves, lambda w: not until_done, report)

        return compute, self._apply

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
        grid = np.column_stack([T1.ravel(), T2.ravel()])
        I = problem.combined_implausibility(grid, wave.emulator)
        return t1, t2, I.reshape(T1.shape)

    @property
    def history_match(self) -> HistoryMatchResult | None:
        """The current history match, or None before the first wave."""
        if not self.waves:
            return None
        return self._history_match_of(self._problem, self.waves)

    def _history_match_of(self, problem, waves: tuple) -> HistoryMatchResult:
        """The one :class:`HistoryMatchResult` of these waves, whichever thread asks first.

        It caches θ_MAP (0.2 s on shear-5) and the θ draws of scenarios 2 and 3: a job
        and the views that show its result use the same object, so neither is computed
        twice (once in the job, again for the θ_MAP markers).
        """
        with self._hm_lock:
            hm = self._hm
            if hm is None or hm.waves is not waves or hm.problem is not problem:
                hm = self._hm = HistoryMatchResult(problem, waves)
            return hm

    # ------------------------------------------------------------------------------
    # Discrepancy

    def method_settings(self) -> Settings:
        """The pipeline settings of the current controls (validated)."""
        return Settings(n_s=self.n_s, n_phi=self.n_phi, proposal=self.proposal,
                        fit_iterations=_INTERACTIVE.fit_iterations,
                        **KOH_CHAINS[self.koh_chain])

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
            if self.results.keys() != set(self.scenarios) and self.waves and self._cache:
                self.run_discrepancy()  # only when the user has run discrepancy before

    def _cached_phi_hat(self, key: ResultKey):
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
        self._jobs.submit("discrepancy", self._discrepancy_compute(settings), self._apply)

    def _discrepancy_compute(self, settings: Settings, n_waves: int | None = None,
                             expected: dict | None = None, waves_only: bool = False):
        """The job of :meth:`run_discrepancy` (and of :meth:`open_session`).

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
        case, grid, seed = self.case, self.grid, self.seed
        chosen = sorted(self.scenarios, key=method_order)
        problem, key, waves = self._current_problem()
        if n_waves is not None and len(waves) > n_waves:
            waves = waves[:n_waves]              # each wave depends only on the earlier ones
        target = n_waves if n_waves is not None else (len(waves) or None)

        too_much = work_problem(case, settings, chosen)

        def compute(report, cancel):
            nonlocal waves
            if too_much is not None:
                raise ValueError(too_much)
            if target is None:
                yield "note", ("No history match for these settings yet: running the waves "
                               "until convergence, then the discrepancy methods.")
            if target is None or len(waves) < target:
                steps = self._wave_steps(problem, key, waves,
                                         lambda w: target is not None and w.index >= target,
                                         lambda f, m: report(0.3 * f, m))
                for partial in steps:
                    waves = partial[1][2]
                    yield partial
                if target is not None and len(waves) != target:
                    raise ValueError(f"The saved session has {target} wave(s), but the history "
                                     f"match converged after {len(waves)}; the file does not "
                                     "match this version's results.")
            elif len(waves) != len(self.waves):
                yield "wave", (problem, key, waves, len(waves),
                               self.implausibility_maps.get(len(waves)))
            if waves_only:
                return
            hm = self._history_match_of(problem, waves)
            if hm.status == "ruled_out":
                raise ValueError(hm.message)
            keys = {m: ResultKey(key, len(waves), settings.key(m), seed) for m in chosen}
            todo = [m for m in chosen if keys[m] not in self._cache]
            hat = self._cached_phi_hat(keys.get(Method.S1,
                                                ResultKey(key, len(waves),
                                                          settings.key(Method.S1), seed)))
            base = 0.3 if target is None else 0.0
            done: list[MethodResult] = []
            for i, method in enumerate(todo):
                if method is Method.KOH and done:
                    yield "methods", (keys, done, None)   # show 1–3 while the chain runs
                    done = []
                result = run_method(
                    case, hm, method, settings, seed=seed, X_extra=grid,
                    log_params_hat=hat if method is Method.S2 else None,
                    progress=lambda f, message, i=i: report(
                        base + (1 - base) * (i + f) / len(todo), message),
                    cancel=cancel)
                if method is Method.S1:
                    hat = result.model.log_params_hat
                done.append(result)
            yield "methods", (keys, done, expected)  # few updates: each re-render costs ~0.3 s

        return compute

    def _apply_methods(self, payload) -> None:
        keys, done, expected = payload
        for result in done:
            self._cache[keys[result.method]] = result
        advice = [w for result in done for w in result.warnings]
        if advice:
            self._report_notice("\n\n".join(advice))
        self._refresh_results()
        if expected is not None:
            self.status = session.compare_metrics(expected, self.results)

    # ------------------------------------------------------------------------------
    # Your data in, results out

    def upload_measurements(self, data: bytes, filename: str) -> bool:
        """Use uploaded measurements with the current case's simulator (a new case).

        The file must have the layout of :func:`mdcore.measurements_template`
        (the "Template CSV" download). It is only parsed: nothing in it is run. Each
        problem found becomes one notification, and the session keeps its case.

        Parameters
        ----------
        data : bytes
            The file's content (at most :data:`session.MAX_UPLOAD_BYTES`).
        filename : str

        Returns
        -------
        bool
            Whether the case was added and selected.
        """
        base = self.base_case_name()
        try:
            text = session.decode_upload(data, filename, kind="measurements CSV")
            case = with_measurements(cases.load(base, seed=0), text, source=filename)
        except ValueError as exc:
            for problem in getattr(exc, "problems", (str(exc),)):
                self.report_error(problem)
            return False
        self._add_case(case, base, text, filename)
        return True

    def _add_case(self, case: Case, base: str | None, text: str | None,
                  filename: str | None) -> None:
        """Add (or replace) a session case and select it."""
        self._kept.pop(case.name, None)
        self._own[case.name] = (case, base, text, filename)
        names = list(cases.names()) + list(self._own)
        self.param.case_name.objects = names
        if self.case_name == case.name:              # replaced: load the new data
            self._load_case(replace=True)
        else:
            self.case_name = case.name

    def case_run(self):
        """The current history match and shown results as a :class:`~mdcore.CaseRun`
        (what the CLI's ``--json``, ``--csv`` and ``--out`` write), or None before any
        result."""
        from mdcore._reproduce import CaseRun
        if not self.results or self.history_match is None:
            return None
        results = tuple(self.results[m] for m in sorted(self.results, key=method_order))
        return CaseRun(self.case, self.history_match, self.method_settings(), self.seed,
                       results)

    def session_json(self) -> str:
        """The session as JSON (the layout of :mod:`mdcore_app.session`)."""
        own = self._own.get(self.case_name)
        controls = {k: getattr(self, k) for k in (*session.CONTROLS, *session.OPTIONAL_CONTROLS)}
        controls["scenarios"] = [m.value for m in sorted(self.scenarios, key=method_order)]
        run = self.case_run()
        doc = session.session_document(
            case_name=self.case_name, based_on=None if own is None else own[1],
            measurements_csv=None if own is None else own[2],
            measurements_file=None if own is None else own[3], controls=controls,
            n_waves=len(self.waves) if self._problem_key == self._settings_key() else 0,
            run=None if run is None else run.to_dict())
        return json.dumps(doc, indent=1, allow_nan=False)

    def set_controls(self, controls: dict, filename: str) -> Settings:
        """Set a session file's ``controls`` on ``state`` in the file's order (a preset
        first sets what it implies); returns the pipeline settings they make.

        Raises
        ------
        SessionError
            Naming the first control outside its parameter's bounds or choices.
        """
        self._restoring = True
        try:
            for k, v in controls.items():
                try:
                    setattr(self, k, v)
                except ValueError:                       # the parameter's own bounds or choices
                    why = f" {APP_LIMITS[k]}" if k in APP_LIMITS else ""
                    raise session.SessionError([
                        f"{filename}: controls.{k} = {v!r} is not allowed for "
                        f"{self.param[k].label} ({allowed_values(self.param[k])}).{why}"]
                    ) from None
        finally:
            self._restoring = False
        return self.method_settings()

    def open_session(self, data: bytes, filename: str) -> bool:
        """Restore a saved session: its case (with uploaded data), controls, waves and
        methods, recomputed and checked against the saved metrics.

        Returns whether the file was accepted; each problem with it is one notification,
        and the session is unchanged (the file is checked in full, its controls on a
        scratch state, before anything of this session changes).
        """
        before = {k: getattr(self, k)
                  for k in ("case_name", *session.CONTROLS, *session.OPTIONAL_CONTROLS)}
        try:
            doc = session.parse_session(
                session.decode_upload(data, filename, kind="session JSON"), filename)
            case = doc["case"]
            controls = dict(doc["controls"])
            controls["scenarios"] = [Method.parse(v) for v in controls["scenarios"]]
            ExplorerState().set_controls(controls, filename)   # refused before any change
            own = None
            if case["measurements_csv"] is not None:
                base = case["based_on"]
                if base not in cases.names():
                    raise session.SessionError([f"{filename}: case.based_on must be one of "
                                                f"{list(cases.names())}; found {base!r}."])
                own = with_measurements(cases.load(base, seed=0), case["measurements_csv"],
                                        source=case["measurements_file"] or "measurements.csv")
            elif case["name"] not in self.param.case_name.objects:
                raise session.SessionError([
                    f"{filename}: the case {case['name']!r} is not in this app (it has "
                    f"{', '.join(self.param.case_name.objects)}); start the app with "
                    f"`--args --case <its case file>.toml` to add it."])
            if own is not None:
                self._add_case(own, case["based_on"], case["measurements_csv"],
                               case["measurements_file"])
            else:
                self.case_name = case["name"]
            settings = self.set_controls(controls, filename)
        except ValueError as exc:
            self._restoring = True
            try:
                self.param.update(**before)              # the session keeps its state
            finally:
                self._restoring = False
            for problem in getattr(exc, "problems", (str(exc),)):
                self.report_error(problem)
            return False
        saved = (doc["run"] or {}).get("methods")
        if doc["n_waves"] == 0:
            self.status = f"Session opened from {filename} (it had no waves yet)."
            return True
        if not saved:
            self._jobs.submit("waves", self._discrepancy_compute(
                settings, n_waves=doc["n_waves"], waves_only=True), self._apply)
            return True
        self._jobs.submit("session", self._discrepancy_compute(
            settings, n_waves=doc["n_waves"], expected=saved), self._apply)
        return True

    # ------------------------------------------------------------------------------
    # Things to try

    def try_experiment(self, key: str) -> None:
        """Set the controls of the guided experiment ``key`` (see
        :mod:`mdcore_app.experiments`) and say in the status line what to press next."""
        from .experiments import EXPERIMENTS
        exp = next((e for e in EXPERIMENTS if e.key == key), None)
        if exp is None:
            self.report_error(f"Unknown experiment {key!r}; choose one of "
                              f"{[e.key for e in EXPERIMENTS]}.")
            return
        settings = dict(exp.settings)
        self.case_name = settings.pop("case_name", self.case_name)
        if "preset" in settings:
            self.preset = settings.pop("preset")        # sets runs per wave etc. first
        self.param.update(**settings)
        self.status = f"{exp.title}: {exp.then}"
