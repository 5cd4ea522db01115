"""History matching of a session: its settings, and the waves run one by one."""

from __future__ import annotations

import threading
from functools import partial
from typing import NamedTuple

import numpy as np
import param

from mdcore._history_matching import (
    MULTIVARIATE,
    RULE_NAMES,
    HistoryMatchResult,
    case_problem,
    next_wave,
)

from .case_model import CaseModel
from .glossary import tooltip
from .session_model import APP_MAX_CANDIDATES, APP_MAX_RUNS
from .teaching import PRESETS, preset_controls, teaching_design

#: Resolution of the implausibility map (per axis).
MAP_RESOLUTION = 60
#: Seconds of wave k = 1, 2, …: a fixed cost, plus per candidate a cost growing with the
#: observed values (rows × outputs), × (2k − 1) as later waves also walk the candidates
#: through the earlier waves' emulators. Fitted to the app's waves of the built-in cases
#: (docs/performance.md, "Run estimates": bench/app_estimates.py).
WAVE_FIXED, WAVE_PER_CANDIDATE, WAVE_PER_CANDIDATE_VALUE = 0.08, 1.8e-7, 7e-9


def wave_seconds(n_obs: int, n_out: int, n_candidates: int, k: int) -> float:
    """Rough seconds of wave ``k`` scoring ``n_candidates`` against ``n_obs`` rows of
    ``n_out`` outputs (within about a factor of 2)."""
    per = WAVE_PER_CANDIDATE + WAVE_PER_CANDIDATE_VALUE * n_obs * n_out
    return WAVE_FIXED + n_candidates * per * (2 * k - 1)
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


#: The controls of the history match, restored with a case's results when switching back.
HM_CONTROLS = ("preset", "v_m", "v_m_length", "threshold", "rule", "n_runs", "n_candidates",
               "max_waves", "convergence_ratio")



class Note(NamedTuple):
    """A job's message for the status line (nothing computed)."""

    text: str


class WaveDone(NamedTuple):
    """A wave a job has run: the match's problem and key, all its waves so far, the new
    wave's index, and its implausibility map (t1, t2, I) or None (p ≠ 2)."""

    problem: object
    key: ProblemKey
    waves: tuple
    index: int
    maps: tuple | None


def implausibility_map(problem, wave):
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


class HistoryModel(CaseModel):
    """History-matching settings and the waves of the current match."""

    preset = param.Selector(
        objects=list(PRESETS), default="teaching", label="Preset",
        doc="teaching: a wave-1 design of a few runs and a strict convergence rule, so you "
            "can watch 3–5 waves shrink the non-implausible set; paper: the paper's design "
            "(docs/method.md §5), which converges after one wave.")
    v_m = param.Number(default=0.05, bounds=(0.0, 1e12), inclusive_bounds=(False, True),
                       softbounds=(0.001, 0.2), label="V_m",
                       doc=tooltip("V_m") + " In the case's output units squared (shear-5: "
                           "of ω1; the other modes scale with their mean squared).")
    threshold = param.Number(default=3.0, bounds=(0.0, 1e6), inclusive_bounds=(False, True),
                             softbounds=(1.0, 5.0), label="Threshold T",
                             doc=tooltip("T"))
    rule = param.Selector(
        objects=list(RULE_NAMES), default="max", label="Implausibility rule",
        doc="max / 2nd max / 3rd max: each output and input scored alone, ruled out above T. "
            f"{MULTIVARIATE}: I_M² = (z − E f)ᵀ (V_o + V_m + V_em)⁻¹ (z − E f) over all points "
            "at once, ruled out above the χ² quantile at 0.995 (degrees of freedom = points × "
            "outputs; shown on the map) instead of T; ℓ_m correlates V_m between inputs "
            "(0: independent).")
    v_m_length = param.Number(
        default=0.0, bounds=(0.0, 1e6), label="V_m length ℓ_m",
        doc="Correlation length of the model discrepancy variance over the inputs (Matérn "
            "3/2, in input units); 0: V_m independent at each input. Used by the "
            "multivariate rule (the max rules use only V_m's diagonal).")
    n_runs = param.Integer(default=10, bounds=(1, APP_MAX_RUNS), label="Runs per wave")
    n_candidates = param.Integer(default=50_000, bounds=(100, APP_MAX_CANDIDATES),
                                 label="Candidates per wave")
    max_waves = param.Integer(default=5, bounds=(1, 20), label="Max waves")
    convergence_ratio = param.Number(
        default=1.0, bounds=(0.001, 1.0), label="Convergence ratio",
        doc="Stop when the emulator variance is below this × (V_o + V_m); 1 is the rule of "
            "docs/method.md §5. Lower it to keep refining after that rule has converged.")
    selected_wave = param.Integer(default=0, bounds=(0, None), label="Wave shown")

    waves = param.Parameter(default=(), doc="Tuple of the completed waves of the current match.")
    implausibility_maps = param.Dict(default={}, doc="wave index -> (t1, t2, I) for p = 2.")
    status = param.String(default="", doc="Status line of the history match.")

    def _init_history(self) -> None:
        self._problem = None
        self._problem_key: ProblemKey | None = None
        self._hm = None
        self._hm_lock = threading.Lock()

    @param.depends("preset", watch=True)
    def _apply_preset(self):
        """Runs per wave, convergence ratio and max waves of the preset (the wave-1
        design follows the preset in :meth:`_current_problem`)."""
        self.param.update(**preset_controls(self.case, self.base_case_name(), self.preset))

    def v_m_vector(self) -> np.ndarray:
        """V_m per output: ``v_m`` for output 1, scaled by (z̄_i / z̄_1)² for the others."""
        zbar = np.abs(self.case.z_train.mean(axis=0))
        return self.v_m * (zbar / zbar[0]) ** 2

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

    def wave_steps(self, problem, key, waves, stop, report):
        """Run waves on a worker thread and yield a :class:`WaveDone` after each.

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
            self.history_match_of(problem, waves).compute_theta_map(
                lambda f, k=k: report(min(1.0, (k - first + 1) / total), f"wave {k + 1}: θ_MAP"))
            maps = implausibility_map(problem, wave)
            report(min(1.0, (len(waves) - first) / total), f"wave {wave.index} done")
            yield WaveDone(problem, key, waves, wave.index, maps)
            if wave.done or stop(wave):
                return

    def _apply_wave(self, done: WaveDone) -> None:
        problem, key, waves, index, maps = done
        fresh = key != self._problem_key
        self._problem, self._problem_key = problem, key
        new_maps = {} if fresh else dict(self.implausibility_maps)
        if maps is not None:
            new_maps[index] = maps
        self._waves_changed(fresh)
        self.param.update(waves=waves, implausibility_maps=new_maps, selected_wave=index,
                          status=waves[-1].message)
        self._refresh_results()          # results of other wave counts are not shown

    def _waves_changed(self, fresh: bool) -> None:
        """A wave arrived; ``fresh``: it starts a new match (a hook for what depends on
        the waves)."""

    def _refresh_results(self) -> None:
        """Show what is computed for the current waves (a hook; nothing here)."""

    def _wave_job(self, until_done: bool, report, cancel):
        """The job of :meth:`next_wave` and :meth:`run_to_convergence`."""
        problem, key, waves = self._current_problem()
        if waves and waves[-1].done:
            # Nothing to compute: say so calmly (a notice, not an error).
            yield Note(f"Already converged after {len(waves)} wave(s): {waves[-1].message} "
                       "To refine further, lower the convergence ratio or raise max waves; "
                       "a changed setting starts a new history match.")
            return
        yield from self.wave_steps(problem, key, waves, lambda w: not until_done, report)

    def waves_seconds(self, until_done: bool = True) -> float:
        """Estimated seconds of the next wave, or (``until_done``) of every wave up to max
        waves: an upper bound, as the match may converge sooner (:func:`wave_seconds`)."""
        waves = self.waves if self._settings_key() == self._problem_key else ()
        if waves and waves[-1].done:
            return 0.0
        last = self.max_waves if until_done else len(waves) + 1
        return sum(wave_seconds(self.case.X_train.shape[0], self.case.n_out,
                                self.n_candidates, k) for k in range(len(waves) + 1, last + 1))

    def next_wave(self) -> None:
        """Run one more wave (a changed setting starts a new history match)."""
        self._jobs.submit("wave", partial(self._wave_job, False), self._apply)

    def run_to_convergence(self) -> None:
        """Run waves until converged, max waves, or everything is ruled out."""
        self._jobs.submit("waves", partial(self._wave_job, True), self._apply)

    @property
    def history_match(self) -> HistoryMatchResult | None:
        """The current history match, or None before the first wave."""
        if not self.waves:
            return None
        return self.history_match_of(self._problem, self.waves)

    def history_match_of(self, problem, waves: tuple) -> HistoryMatchResult:
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
