"""End-to-end runs of a case (``python -m mdcore reproduce``, the paper's Tables 1–3): history
matching, then each method through :func:`mdcore.run_method`, as in the app."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from concurrent.futures import Executor
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from . import _cases as _cases
from . import _compiled as compiled
from ._diagnostics import space_removed, theta_delta_split, validate_waves
from ._discrepancy import DiscrepancyModel, check_executor
from ._history_matching import HistoryMatchResult, history_match_case
from ._koh import KOHModel
from ._pipeline import Method, MethodResult, Progress, Settings, run_method
from ._validation import as_seed_int

#: Version of :meth:`CaseRun.to_dict`'s layout (5: each wave's emulator validation and space
#: removed, each decoupled scenario's θ–δ share).
SCHEMA_VERSION = 5


def default_methods(name: str) -> tuple[Method, ...]:
    """Scenarios 1–3, plus KOH on beam-1d (the only case the paper runs it on)."""
    base = (Method.S1, Method.S2, Method.S3)
    return base + (Method.KOH,) if name == "beam-1d" else base


def parse_methods(values) -> tuple[Method, ...]:
    """Methods from labels (1, "2", "koh", Method), unique and in the order 1, 2, 3, KOH."""
    out = {Method.parse(v) for v in values}
    if not out:
        raise ValueError(f"methods is empty; pick at least one of {[m.value for m in Method]}.")
    return tuple(m for m in Method if m in out)


@dataclass(frozen=True, eq=False)
class CaseRun:
    """A history match and the methods run on it (:func:`reproduce`).

    Attributes
    ----------
    case : Case
    hm : HistoryMatchResult
    settings : Settings
    seed : int
    results : tuple of MethodResult
        In the order 1, 2, 3, KOH.
    """

    case: _cases.Case
    hm: HistoryMatchResult
    settings: Settings
    seed: int
    results: tuple

    @property
    def truth_in_nroy(self) -> bool | None:
        """Whether the data-generating θ is non-implausible (None where it is unknown)."""
        t = self.case.theta_true
        return None if t is None else bool(self.hm.contains(t)[0])

    @cached_property
    def validation(self) -> tuple:
        """Each wave's leave-one-run-out check (:func:`mdcore.validate_waves`)."""
        return validate_waves(self.hm, warn=False)

    @cached_property
    def theta_delta(self) -> dict:
        """Each decoupled scenario's :class:`~mdcore._diagnostics.ThetaDeltaSplit` at X_test."""
        return {r.method.value: theta_delta_split(r.model, self.case.X_test)
                for r in self.results if isinstance(r.model, DiscrepancyModel)}

    def to_dict(self) -> dict:
        """The JSON layout of ``reproduce --json`` (see the README), versioned."""
        s, hm, opts = self.settings, self.hm, self.hm.problem.options
        return {"schema_version": SCHEMA_VERSION, "case": self.case.name, "seed": self.seed,
                "settings": {"n_s": s.n_s, "n_phi": s.n_phi, "n_iter": s.n_iter,
                             "burn_in": s.burn_in, "prune": s.prune, "proposal": s.proposal,
                             "fit_iterations": s.fit_iterations,
                             "backend": compiled.resolve_backend(s.backend)},
                "history_matching": {
                    "rule": opts.rule, "cutoff": hm.problem.cutoff,
                    "V_m_length": opts.V_m_length.tolist(),
                    "V_m_corr": None if opts.V_m_corr is None else opts.V_m_corr.tolist(),
                    "waves": len(hm.waves), "nroy_fraction": hm.nroy_fraction,
                    "theta_map": hm.theta_map.tolist(), "truth_nroy": self.truth_in_nroy,
                    "status": hm.status,
                    "failed_runs": [[{"theta": f.theta.tolist(), "message": f.message}
                                     for f in w.failures] for w in hm.waves],
                    "validation": [v.as_dict() for v in self.validation],
                    "space_removed": [space_removed(w.nroy, hm.problem.bounds).tolist()
                                      for w in hm.waves]},
                "methods": {r.method.value: {**_entry(r), "theta_delta": (
                    t := self.theta_delta.get(r.method.value)) and t.as_dict()}
                            for r in self.results}}


def _entry(r: MethodResult) -> dict:
    """One method's part of :meth:`CaseRun.to_dict`."""
    entry: dict = {"metrics": r.metrics.as_dict(), **{
        name: None if d is None else {k: list(v) if isinstance(v, tuple) else v
                                      for k, v in d.__dict__.items()}
        for name, d in (("importance", r.importance), ("chain", r.chain))},
        "warnings": list(r.warnings), "seconds": r.seconds}
    if isinstance(r.model, KOHModel):
        theta = r.model.theta
        entry["posterior"] = {"theta_mean": theta.mean(axis=0).tolist(),
                              "theta_sd": theta.std(axis=0).tolist(),
                              "theta_interval_99": np.percentile(theta, [0.5, 99.5],
                                                                 axis=0).T.tolist(),
                              "log_phi": r.model.log_phi.tolist()}
    return entry


def reproduce(name: str, *, methods=None, settings: Settings | None = None, seed=0,
              report: Callable[[str], None] | None = None, progress: Progress | None = None,
              executor: Executor | None = None, timeout: float | None = None,
              history_matching: dict | None = None) -> CaseRun:
    """History-match a built-in case, run the methods, and score them (``reproduce``).

    Parameters
    ----------
    name : str
        Case study name (:func:`mdcore._cases.names`).
    methods : sequence of {1, 2, 3, "koh"} or Method, optional
        Default :func:`default_methods` (KOH is included for beam-1d).
    settings : Settings, optional
        Default: the paper's sizes (:meth:`Settings.paper`).
    seed : int or numpy.random.Generator, default=0
        Seeds the case's noise and everything :func:`run_case` seeds.
    report, progress, executor
        As in :func:`run_case`.
    timeout : float, optional
        Seconds one simulator run may take (:attr:`mdcore.Case.timeout`).
    history_matching : dict, optional
        :func:`run_case`'s ``**history_matching``.

    Returns
    -------
    CaseRun
    """
    case = dataclasses.replace(_cases.load(name, seed=seed), timeout=timeout)
    return run_case(case, methods=default_methods(name) if methods is None else methods,
                    settings=Settings.paper(name) if settings is None else settings,
                    seed=case.seed, report=report, progress=progress, executor=executor,
                    **(history_matching or {}))


def run_case(case: _cases.Case, *, methods=(Method.S1, Method.S2, Method.S3),
             settings: Settings | None = None, seed=0,
             report: Callable[[str], None] | None = None, progress: Progress | None = None,
             executor: Executor | None = None, **history_matching) -> CaseRun:
    """History-match any case (built-in or :func:`mdcore.load_case_file`), then
    run the methods on it through :func:`mdcore.run_method`.

    Parameters
    ----------
    case : Case
    methods : sequence of {1, 2, 3, "koh"} or Method, default=(1, 2, 3)
    settings : Settings, optional
        Default :meth:`Settings.paper` of the case's name.
    seed : int or numpy.random.Generator, default=0
        Seeds the history match, the θ samples, the φ draws and the KOH chain.
    report : callable, optional
        Called with a line of text as each stage finishes.
    progress : callable, optional
        ``progress(fraction, message)`` within each method (see :func:`run_method`).
    executor : concurrent.futures.Executor, optional
        Runs the history match's simulator runs (one θ per task unless ``batch_size`` is
        given) and :func:`mdcore.run_method`'s chunks, with the serial run's numbers.
    **history_matching
        Options of :func:`mdcore._history_matching.setup` (``rule``, ``n_runs``,
        ``V_m_length``, ``batch_size`` …).

    Returns
    -------
    CaseRun
    """
    seed = as_seed_int(seed)
    chosen = parse_methods(methods)
    executor = check_executor(executor)
    settings = Settings.paper(case.name) if settings is None else settings
    hm = history_match_case(case, seed=seed, executor=executor, **history_matching)
    validate_waves(hm)                          # EmulatorWarning for a wave that fails LOO
    if report:
        report(hm.message)
    results = run_methods(case, hm, chosen, settings, seed=seed, report=report,
                          progress_for=None if progress is None else (lambda m: progress),
                          executor=executor)
    return CaseRun(case, hm, settings, seed, results)


def run_methods(case: _cases.Case, hm: HistoryMatchResult, methods, settings: Settings, *,
                seed=0, report: Callable[[str], None] | None = None,
                progress_for: Callable[[Method], Progress | None] | None = None,
                executor: Executor | None = None) -> tuple[MethodResult, ...]:
    """:func:`run_method` of each method in the order 1, 2, 3, KOH, scenario 2 reusing
    scenario 1's φ̂; ``report(line)`` after each, ``progress_for(method)`` gives each one's
    ``progress`` (the command line's bar per method)."""
    results: list[MethodResult] = []
    for method in parse_methods(methods):
        hat = next((r.model.log_params_hat for r in results
                    if r.method is Method.S1 and isinstance(r.model, DiscrepancyModel)), None)
        result = run_method(case, hm, method, settings, seed=seed, log_params_hat=hat,
                            progress=None if progress_for is None else progress_for(method),
                            executor=executor)
        results.append(result)
        if report:
            report(f"{method.label}: {result.seconds:.2f} s")
    return tuple(results)
