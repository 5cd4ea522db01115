"""Bayesian history matching in waves (paper Eq. 16).

The implausibility of θ at observed input/output ``i``,
``I_i(θ) = |z_i − E[y_i(θ)]| / √(V_o,i + V_m,i + V[y_i(θ)])``, is combined over the targets
by the max (or 2nd / 3rd max); θ is not ruled out yet (NROY) when ``I(θ) ≤ T``.

Each wave fits an emulator to all runs so far, scores candidates uniform in the previous
NROY set and keeps those with ``I ≤ T``. Candidates of wave ``k > 1`` are the previous
survivors moved by a few random-walk Metropolis steps whose target is the uniform density
on that set; the walk leaves it invariant, so the NROY fraction of the box is estimated
without bias by ``f_k = f_{k−1} · P(I_k ≤ T | θ ∈ NROY_{k−1})``.

The multivariate rule (Vernon, Goldstein & Bower 2010; :mod:`mdcore._multivariate`)
scores all targets at once, I_M²(θ) with the full covariance ``V_o + V_m + V_em(θ)``
(V_m possibly correlated), against a χ² quantile instead of T.

Examples
--------
>>> import mdcore
>>> result = mdcore.history_match_case(mdcore.load_case("beam-1d"), n_candidates=20_000,
...                                    max_waves=2, seed=0)
>>> result.status in {"converged", "max_waves"}
True
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from concurrent.futures import Executor
from dataclasses import dataclass, field, fields, replace
from functools import cached_property
from typing import Any, NamedTuple

import numpy as np
import scipy.optimize
import scipy.special
import scipy.stats

from . import _multivariate as multivariate
from ._emulator import Emulator, fit_emulator
from ._runs import run_simulator
from ._threads import single_threaded_blas
from ._validation import (
    as_float_array,
    as_int,
    as_number,
    as_outputs,
    as_positive_float,
    as_seed_int,
    check_bounds,
    check_positive,
    choose,
    short,
)

__all__ = ["RULES", "MULTIVARIATE", "RULE_NAMES", "elementwise_implausibility", "combine",
           "Score", "Wave", "HistoryMatchOptions", "HistoryMatchProblem", "HistoryMatchResult",
           "setup", "setup_arguments", "next_wave", "iter_waves", "history_match",
           "history_match_case", "case_problem", "replicate_summary", "check_correlation"]

#: Combiner rules: the k-th largest implausibility over all targets.
RULES = {"max": 1, "2nd max": 2, "3rd max": 3}
#: The multivariate rule: I_M² over all targets against a χ² quantile (Vernon et al. 2010).
MULTIVARIATE = "multivariate"
#: Every rule :func:`setup` accepts.
RULE_NAMES = (*RULES, MULTIVARIATE)
#: Default largest share of a wave's simulator runs that may fail (and be dropped).
MAX_FAILED_FRACTION = 0.5
#: Largest sizes accepted up front (beyond them the work would not fit in memory): candidates
#: per wave, runs in all waves (the θ covariance is runs × runs), waves, Metropolis steps.
MAX_CANDIDATES = 10_000_000
MAX_RUNS = 10_000
MAX_WAVES = 100
MAX_MCMC_STEPS = 1_000
#: Values (θ rows × observed inputs × outputs) of the emulator's moments held at once while
#: candidates are scored or weighted (a fixed bound per array): memory does not grow with M × N.
CHUNK_VALUES = 2**21
#: Posterior draws kept per history match, by (n, seed): see ``posterior_samples``.
POSTERIOR_MEMO = 4
RULED_OUT_HINT = ("nothing is non-implausible: every candidate θ has I > T. Raise V_m (the "
                  "model-discrepancy variance) or the threshold T, or use the 2nd/3rd max rule.")
RULED_OUT_HINT_MV = ("nothing is non-implausible: every candidate θ has I_M² above the χ² "
                     "cut-off. Raise V_m, shorten V_m_length (a correlated V_m leaves less "
                     "room for a discrepancy that varies faster) or raise chi2_probability.")


def elementwise_implausibility(z, mean, var, *, V_o, V_m) -> np.ndarray:
    """Elementwise implausibility (Eq. 16), ``|z − mean| / √(V_o + V_m + var)``, of arrays
    that broadcast together (``var``, ``V_o``, ``V_m`` ≥ 0).

    >>> float(elementwise_implausibility(1.0, 0.0, 0.5, V_o=0.25, V_m=0.25))
    1.0
    """
    z = as_float_array(z, "z", allow_empty=True)
    mean = as_float_array(mean, "mean", allow_empty=True)
    var = check_positive(as_float_array(var, "var", allow_empty=True), "var", strict=False)
    V_o = check_positive(as_float_array(V_o, "V_o"), "V_o", strict=False)
    V_m = check_positive(as_float_array(V_m, "V_m"), "V_m", strict=False)
    total = V_o + V_m + var
    if np.any(total <= 0):
        raise ValueError("V_o + V_m + var must be positive for every target; received a zero. "
                         "Give V_m > 0 or a positive observation variance.")
    return np.abs(z - mean) / np.sqrt(total)


def combine(I, rule: str = "max") -> np.ndarray:
    """Combine implausibilities ``I`` (..., N, n_out) over the targets by ``rule``
    ("max", "2nd max" or "3rd max"): shape (...).

    >>> combine(np.array([[[1.0], [9.0], [4.0]]]), "2nd max")
    array([4.])
    """
    choose(rule, "rule", RULES)
    I = as_float_array(I, "I", min_ndim=2)
    flat = I.reshape(I.shape[:-2] + (-1,))
    k = RULES[rule]
    if flat.shape[-1] < k:
        raise ValueError(f"rule {rule!r} needs at least {k} targets; received {flat.shape[-1]}.")
    return -np.partition(-flat, k - 1, axis=-1)[..., k - 1]


def replicate_summary(X, z):
    """Group repeated rows of X: distinct inputs, replicate means and sample variances.

    Returns ``(X_unique (N_u, d_x), z_mean (N_u, n_out), z_var (N_u, n_out), counts (N_u,))``;
    ``z_var`` is NaN where an input has a single observation.
    """
    X = as_float_array(X, "X", ndim=2)
    z = as_float_array(z, "z", ndim=2)
    if z.shape[0] != X.shape[0]:
        raise ValueError(f"z must have one row per row of X; received X {X.shape} and z {z.shape}.")
    Xu, inverse, counts = np.unique(X, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    zm = np.zeros((len(Xu), z.shape[1]))
    np.add.at(zm, inverse, z)
    zm /= counts[:, None]
    ss = np.zeros_like(zm)
    np.add.at(ss, inverse, (z - zm[inverse]) ** 2)
    with np.errstate(invalid="ignore", divide="ignore"):
        zv = np.where(counts[:, None] > 1, ss / (counts[:, None] - 1), np.nan)
    return Xu, zm, zv, counts


@dataclass(frozen=True, eq=False)
class HistoryMatchOptions:
    """How a history match runs: its rule, sizes, stopping rule and simulator runs.

    :func:`setup` validates them (and fills ``n_runs`` and ``n_candidates``); the keyword
    arguments of :func:`history_match` and :func:`history_match_case` set them by name.

    Attributes
    ----------
    threshold : float, default=3
        Implausibility cut-off T > 0 (Pukelsheim's 3σ rule).
    rule : {"max", "2nd max", "3rd max", "multivariate"}, default="max"
        The k-th largest I_i(θ) against T, or the multivariate I_M²(θ) against a χ²
        quantile (:mod:`mdcore._multivariate`); θ_MAP and the posterior samples then use
        its multivariate Gaussian likelihood, and a wave converges when
        ``V_em(θ) ≼ convergence_ratio · (V_o + V_m)`` at the retained θ.
    n_runs : int, optional
        Simulator runs added per wave (default ``max(10, 5 p)``).
    n_candidates : int, optional
        Candidates scored per wave (default ``50,000 · p``).
    max_waves : int, default=5
    mcmc_steps : int, default=4
        Uniform-target Metropolis steps that spread candidates through the NROY set.
    convergence_ratio : float, default=1
        Converged when the emulator variance at every retained point is below
        ``convergence_ratio × (V_o + V_m)``; smaller values keep refining.
    executor : concurrent.futures.Executor, optional
        Runs the simulator runs of each wave (for example a ``ProcessPoolExecutor`` or a
        Dask ``Client(...).get_executor()``); the results equal the serial run's.
    batch_size : int, optional
        θ per submitted task (default: one per task with an executor, all at once without).
    timeout : float, optional
        Seconds after which a batch of runs counts as failed.
    max_failed_fraction : float, default=0.5
        Failed runs (raised, timed out, NaN/inf) are dropped and reported on the wave; when
        more than this share of a wave's runs fail (or all do), the wave is an error that
        names the first failure.
    V_m_length : float or ndarray of shape (n_out,), default=0
        Correlation length ℓ_m of the model discrepancy over x, per output, in X's units:
        ``V_m(x, x') = σ_m² m32(‖x − x'‖ / ℓ_m)``; 0 keeps V_m independent. Only
        the multivariate rule sees the correlation (the max rules use the diagonal).
    V_m_corr : ndarray of shape (n_out, n_out), optional
        Correlation matrix of the outputs' discrepancies (symmetric, unit diagonal,
        positive definite); default independent. Multivariate rule only.
    chi2_probability : float, default=0.995
        The multivariate rule rules out θ with I_M² above the χ² quantile of
        ``N_u · n_out`` degrees of freedom at this probability (Vernon et al. 2010).
    """

    threshold: float = 3.0
    rule: str = "max"
    n_runs: int | None = None
    n_candidates: int | None = None
    max_waves: int = 5
    mcmc_steps: int = 4
    convergence_ratio: float = 1.0
    executor: Executor | None = field(default=None, repr=False)
    batch_size: int | None = None
    timeout: float | None = None
    max_failed_fraction: float = MAX_FAILED_FRACTION
    V_m_length: Any = 0.0
    V_m_corr: Any = None
    chi2_probability: float = 0.995


@dataclass(frozen=True, eq=False)
class HistoryMatchProblem:
    """A validated history-matching set-up; build it with :func:`setup`.

    Attributes
    ----------
    simulate : callable
        ``simulate(X, theta) -> (n_theta, N, n_out)``.
    X : ndarray of shape (N_u, d_x)
        Distinct observed inputs.
    z : ndarray of shape (N_u, n_out)
        Observations (replicate means).
    V_o, V_m : ndarray of shape (N_u, n_out)
    bounds : ndarray of shape (p, 2)
    initial_design : ndarray of shape (R0, p)
    seed : int
    options : HistoryMatchOptions
        Validated: ``n_runs`` and ``n_candidates`` filled in, ``V_m_length`` of shape
        (n_out,), ``V_m_corr`` (n_out, n_out) or None.
    """

    simulate: Callable = field(repr=False)
    X: np.ndarray
    z: np.ndarray
    V_o: np.ndarray
    V_m: np.ndarray
    bounds: np.ndarray
    initial_design: np.ndarray
    seed: int
    options: HistoryMatchOptions

    @property
    def p(self) -> int:
        """Number of calibration parameters."""
        return self.bounds.shape[0]

    @cached_property
    def V(self) -> np.ndarray:
        """``V_o + V_m`` over all targets, (n_out · N_u, n_out · N_u), output-major
        (:func:`mdcore._multivariate.discrepancy_cov`); its diagonal is ``V_o + V_m``."""
        return np.diag(self.V_o.T.ravel()) + multivariate.discrepancy_cov(
            self.X, self.V_m, self.options.V_m_length, self.options.V_m_corr)

    @property
    def cutoff(self) -> float:
        """The value a combined implausibility is compared with: T for the max rules, the
        χ² quantile of ``N_u · n_out`` degrees of freedom at :attr:`chi2_probability` for
        the multivariate rule (whose implausibility is I_M²)."""
        if self.options.rule == MULTIVARIATE:
            return multivariate.chi2_cutoff(self.z.size, self.options.chi2_probability)
        return self.options.threshold

    def score(self, theta, emulator: Emulator) -> Score:
        """Implausibility (Eq. 16, combined by :attr:`rule`) and emulator variance of
        candidates ``theta`` (M, p) under a wave's ``emulator``
        (:meth:`mdcore.Emulator.implausibility_and_var`)."""
        theta = np.atleast_2d(as_float_array(theta, "theta"))
        if theta.ndim != 2 or theta.shape[1] != self.p:
            raise ValueError(f"theta must have shape (M, p) with p = {self.p}; received "
                             f"{theta.shape}.")
        if self.options.rule == MULTIVARIATE:     # I_M² over all targets at once
            return Score(*multivariate.multivariate_implausibility(emulator, theta, self.z,
                                                                   self.V))
        return Score(*emulator.implausibility_and_var(self.X, theta, self.z,
                                                      self.V_o + self.V_m,
                                                      rank=RULES[self.options.rule]))

    def combined_implausibility(self, theta, emulator: Emulator,
                                progress: Callable[[float], None] | None = None) -> np.ndarray:
        """Combined implausibility (Eq. 16) of ``theta`` (M, p) under ``emulator``, (M,).

        Scored in chunks of θ (:data:`CHUNK_VALUES`): memory stays bounded for any M.
        ``progress(fraction)`` is called before each chunk (it may raise to stop).
        """
        theta = np.atleast_2d(as_float_array(theta, "theta"))
        m, out = theta.shape[0], np.empty(theta.shape[0])
        for rows in self.chunks(m):
            if progress is not None:
                progress(rows.start / m)
            out[rows] = self.score(theta[rows], emulator).implausibility
        return out

    def chunks(self, m: int) -> list[slice]:
        """Slices of ``m`` θ rows whose emulator predictions at every observed input and
        output hold at most :data:`CHUNK_VALUES` values each (at least one row)."""
        step = max(1, CHUNK_VALUES // self.z.size)
        return [slice(i, min(i + step, m)) for i in range(0, m, step)]


class Score(NamedTuple):
    """:meth:`HistoryMatchProblem.score`: the combined ``implausibility`` (M,) and the
    emulator ``var`` (M, N_u, n_out) at each observed input and output."""

    implausibility: np.ndarray
    var: np.ndarray


@dataclass(frozen=True, eq=False)
class Wave:
    """One completed wave.

    Attributes
    ----------
    index : int
        1-based wave number.
    candidates : ndarray of shape (M, p)
        Scored candidates (uniform in the previous NROY set).
    candidate_implausibility : ndarray of shape (M,)
        Combined implausibility of each candidate.
    nroy : ndarray of shape (K, p)
        Candidates with ``I ≤ T`` (uniform in this wave's NROY set).
    nroy_fraction : float
        Estimated NROY volume as a fraction of the original prior box.
    runs_theta : ndarray of shape (r, p)
        Simulator runs added for this wave's emulator (wave 1: the initial design).
    emulator : Emulator
        Fitted to all runs so far.
    max_var : ndarray of shape (n_out,)
        Largest emulator variance at the retained points (NaN if none is retained).
    var_threshold : ndarray of shape (n_out,)
        Smallest ``V_o + V_m`` over the observed inputs (× ``convergence_ratio``);
        converged when ``max_var`` is below it for every output (the multivariate rule
        asks ``V_em(θ) ≼ convergence_ratio · (V_o + V_m)`` instead, see :func:`setup`).
    status : str
        ``"running"``, ``"converged"``, ``"max_waves"`` or ``"ruled_out"``.
    message : str
    seconds : float
    problem : HistoryMatchProblem
        The set-up the wave belongs to.
    failures : tuple of mdcore._runs.Failure
        Simulator runs of this wave that raised, timed out or returned NaN/inf (θ and
        message); they were dropped, and ``runs_theta`` holds only the runs that succeeded.
    """

    index: int
    candidates: np.ndarray
    candidate_implausibility: np.ndarray
    nroy: np.ndarray
    nroy_fraction: float
    runs_theta: np.ndarray
    emulator: Emulator
    max_var: np.ndarray
    var_threshold: np.ndarray
    status: str
    message: str
    seconds: float
    problem: HistoryMatchProblem = field(repr=False)
    failures: tuple = ()

    @property
    def done(self) -> bool:
        """Whether the stopping rule ended the history match at this wave."""
        return self.status != "running"

    def combined_implausibility(self, theta) -> np.ndarray:
        """Combined implausibility (Eq. 16) of ``theta`` (M, p) under this wave's emulator.

        Returns
        -------
        ndarray of shape (M,)
            θ with a value ≤ the problem's :attr:`~HistoryMatchProblem.cutoff` is
            non-implausible in this wave.
        """
        return self.problem.combined_implausibility(theta, self.emulator)


def setup(simulate: Callable, X, z, bounds, *, V_m, V_o=None, initial_design=None, seed=0,
          options: HistoryMatchOptions | None = None) -> HistoryMatchProblem:
    """Validate and assemble a history-matching problem.

    Parameters
    ----------
    simulate : callable
        ``simulate(X, theta) -> (n_theta, N, n_out)`` for any simulator.
    X : ndarray of shape (N, d_x)
        Observed inputs; repeated rows are replicates.
    z : ndarray of shape (N, n_out)
        Observations.
    bounds : ndarray of shape (p, 2)
        Prior box of θ.
    V_m : float or ndarray of shape (n_out,) or (N_u, n_out)
        Model-discrepancy variance, > 0.
    V_o : float or ndarray, optional
        Observation variance. Inputs with replicates use the replicate sample variance
        (``V_o`` is required for inputs without replicates).
    initial_design : ndarray of shape (R0, p), optional
        Runs of the first emulator (default: a Latin hypercube of ``max(10 p, n_runs)``).
    seed : int or numpy.random.Generator, default=0
        Seeds every wave (wave k uses ``default_rng([seed, k])``); a Generator is turned
        into an integer seed by one draw.
    options : HistoryMatchOptions, optional
        The rule, sizes, stopping rule and simulator runs (default: the paper's).
    """
    o = HistoryMatchOptions() if options is None else options
    if not isinstance(o, HistoryMatchOptions):
        raise ValueError(f"options must be a HistoryMatchOptions; received {type(o).__name__}.")
    threshold, rule, n_runs, n_candidates = o.threshold, o.rule, o.n_runs, o.n_candidates
    if not callable(simulate):
        raise ValueError(f"simulate must be callable (X, theta) -> (n_theta, N, n_out); "
                         f"received {type(simulate).__name__}.")
    bounds = check_bounds(bounds)
    p = bounds.shape[0]
    X = as_float_array(X, "X", ndim=2)
    z = as_outputs(z, X.shape[0])
    T = as_number(threshold)
    if not np.isfinite(T) or T <= 0:
        raise ValueError(f"threshold T must be a positive number; received {threshold!r}. "
                         "T = 3 is the usual choice.")
    choose(rule, "rule", RULE_NAMES)
    Xu, zm, zv, counts = replicate_summary(X, z)
    n_out = z.shape[1]

    def per_target(value, name: str, strict: bool) -> np.ndarray:
        value = check_positive(as_float_array(value, name), name, strict=strict)
        try:
            return np.broadcast_to(value, zm.shape).copy()
        except ValueError:
            raise ValueError(f"{name} must be a scalar, (n_out,) = ({n_out},) or (N_u, n_out) "
                             f"= {zm.shape}; received shape {value.shape}.") from None

    V_m = per_target(V_m, "V_m", True)
    if V_o is not None:
        V_o = per_target(V_o, "V_o", False)
    has_rep = counts > 1
    if V_o is None:
        if not np.all(has_rep):
            raise ValueError("V_o is required: some inputs have a single observation, so no "
                             "replicate variance is available. Pass the noise variance as V_o.")
        V_o = zv
    else:
        V_o = np.where(has_rep[:, None], zv, V_o)     # the replicate variance wins
    n_runs = as_int(max(10, 5 * p) if n_runs is None else n_runs, "n_runs", 1, MAX_RUNS)
    n_candidates = as_int(50_000 * p if n_candidates is None else n_candidates,
                           "n_candidates", 10, MAX_CANDIDATES)
    max_waves = as_int(o.max_waves, "max_waves", 1, MAX_WAVES)
    seed = as_seed_int(seed)
    if initial_design is None:
        lhs = scipy.stats.qmc.LatinHypercube(d=p, seed=np.random.default_rng([seed, 0]))
        initial_design = scipy.stats.qmc.scale(lhs.random(max(10 * p, n_runs)),
                                               bounds[:, 0], bounds[:, 1])
    initial_design = as_float_array(initial_design, "initial_design", ndim=2)
    if initial_design.shape[1] != p:
        raise ValueError(f"initial_design must have shape (R0, {p}); received "
                         f"{initial_design.shape}.")
    total = initial_design.shape[0] + n_runs * (max_waves - 1)
    if total > MAX_RUNS:
        raise ValueError(f"the simulator runs of all waves, initial_design's rows + n_runs × "
                         f"(max_waves − 1), must be at most {MAX_RUNS:,} (the emulator's "
                         f"covariance is runs × runs); received {initial_design.shape[0]:,} + "
                         f"{n_runs:,} × {max_waves - 1} = {total:,}. Lower n_runs or "
                         "max_waves.")
    convergence_ratio = as_positive_float(o.convergence_ratio, "convergence_ratio",
                                          "1 is the paper's rule.")
    failed = as_number(o.max_failed_fraction)
    if not 0.0 <= failed < 1.0:
        raise ValueError(f"max_failed_fraction must be in [0, 1); received "
                         f"{o.max_failed_fraction!r}.")
    V_m_length, V_m_corr, chi2_probability = check_correlation(
        o.V_m_length, o.V_m_corr, o.chi2_probability, n_out)
    if V_m_corr is not None or np.any(V_m_length > 0):
        _check_total_cov(np.diag(V_o.T.ravel()) + multivariate.discrepancy_cov(
            Xu, V_m, V_m_length, V_m_corr))
    if o.executor is not None and not callable(getattr(o.executor, "submit", None)):
        raise ValueError(f"executor must be a concurrent.futures.Executor (with submit); "
                         f"received {type(o.executor).__name__}.")
    checked = replace(
        o, threshold=T, n_runs=n_runs, n_candidates=n_candidates, max_waves=max_waves,
        mcmc_steps=as_int(o.mcmc_steps, "mcmc_steps", 0, MAX_MCMC_STEPS),
        convergence_ratio=convergence_ratio, max_failed_fraction=failed,
        V_m_length=V_m_length, V_m_corr=V_m_corr, chi2_probability=chi2_probability,
        batch_size=None if o.batch_size is None else as_int(o.batch_size, "batch_size", 1),
        timeout=None if o.timeout is None else as_positive_float(o.timeout, "timeout",
                                                                 "It is in seconds."))
    return HistoryMatchProblem(simulate, Xu, zm, V_o, V_m, bounds, initial_design, seed, checked)


def check_correlation(length, corr, probability, n_out: int):
    """Validated ``V_m_length`` (n_out,), ``V_m_corr`` (n_out, n_out) or None, and the χ²
    probability of :func:`setup` (also used by :mod:`mdcore._case_file`)."""
    length = as_float_array(length, "V_m_length")
    if length.size not in (1, n_out) or length.ndim > 1 or np.any(length < 0):
        raise ValueError(f"V_m_length must be one length ≥ 0 or one per output ({n_out}), in "
                         f"the inputs' units (0: independent); received {short(length)}.")
    length = np.broadcast_to(length.ravel(), (n_out,)).copy()
    prob = as_number(probability)
    if not 0.0 < prob < 1.0:
        raise ValueError(f"chi2_probability must be in (0, 1); received {probability!r}. "
                         "0.995 is Vernon et al.'s choice.")
    if corr is None:
        return length, None, prob
    R = as_float_array(corr, "V_m_corr")
    if R.shape != (n_out, n_out) or not np.allclose(R, R.T, rtol=0, atol=1e-12) \
            or not np.allclose(np.diag(R), 1.0, rtol=0, atol=1e-12):
        raise ValueError(f"V_m_corr must be a symmetric ({n_out}, {n_out}) correlation matrix "
                         f"with ones on its diagonal, one row per output; received "
                         f"{short(R.tolist())}.")
    lam = np.linalg.eigvalsh(R)[0]
    if lam <= 1e-10:
        raise ValueError(f"V_m_corr is not positive definite: its smallest eigenvalue is "
                         f"{lam:.3g}, so some combination of the outputs' discrepancies would "
                         "have zero or negative variance. Lower the off-diagonal "
                         "correlations (with one value ρ for every pair of outputs, ρ must "
                         f"be above −1/(n_out − 1) and below 1).")
    return length, (R + R.T) / 2, prob


def _check_total_cov(V: np.ndarray) -> None:
    """Refuse a ``V_o + V_m`` that no Cholesky factor can be trusted with."""
    lam = np.linalg.eigvalsh(V)
    if lam[0] <= 1e-12 * lam[-1]:
        raise ValueError(f"V_o + V_m over the observed inputs is not positive definite "
                         f"(eigenvalues from {lam[0]:.3g} to {lam[-1]:.3g}): a correlation "
                         "length V_m_length much longer than the spacing of the inputs "
                         "makes V_m nearly singular, and the observation variance V_o is too "
                         "small to make up for it. Shorten V_m_length or give a positive V_o.")


def _in_nroy(problem, waves, theta, progress=None) -> np.ndarray:
    """Whether each θ (M, p) is inside the box and non-implausible in every wave."""
    b = problem.bounds
    ok = np.all((theta >= b[:, 0]) & (theta <= b[:, 1]), axis=1)
    for j, w in enumerate(waves):
        idx = np.nonzero(ok)[0]
        if idx.size:
            ok[idx] = problem.combined_implausibility(
                theta[idx], w.emulator, None if progress is None
                else (lambda f, j=j: progress((j + f) / len(waves)))) <= problem.cutoff
    return ok


def _uniform_in_nroy(problem, waves, seeds: np.ndarray, n: int, rng,
                     progress=None) -> np.ndarray:
    """``n`` points uniform in the NROY set of ``waves``: resampled ``seeds`` (K, p) moved by
    Metropolis steps of covariance 2.38²/p × the seeds' (Gelman et al.), module docstring."""
    p = problem.p
    span = problem.bounds[:, 1] - problem.bounds[:, 0]
    theta = seeds[rng.integers(0, len(seeds), size=n)]
    if len(seeds) > p + 1:
        cov = np.cov(seeds, rowvar=False).reshape(p, p) * (2.38**2 / p)
    else:
        cov = np.diag((0.05 * span) ** 2)
    cov = cov + np.diag((1e-6 * span) ** 2)
    chol = np.linalg.cholesky(cov)
    steps = problem.options.mcmc_steps
    for k in range(steps):
        prop = theta + rng.standard_normal((n, p)) @ chol.T
        accept = _in_nroy(problem, waves, prop, None if progress is None
                          else (lambda f, k=k: progress((k + f) / steps)))
        theta[accept] = prop[accept]
    return theta


def _maximin(pool: np.ndarray, existing: np.ndarray, n: int, span: np.ndarray, rng) -> np.ndarray:
    """Greedy maximin subset of ``pool`` (K, p): each pick is farthest from runs so far."""
    if len(pool) > 4000:
        pool = pool[rng.choice(len(pool), 4000, replace=False)]
    P, E = pool / span, existing / span
    d = np.min(np.sum((P[:, None, :] - E[None, :, :]) ** 2, axis=-1), axis=1)
    picks = []
    for _ in range(min(n, len(pool))):
        i = int(np.argmax(d))
        picks.append(i)
        d = np.minimum(d, np.sum((P - P[i]) ** 2, axis=1))
        d[i] = -1.0
    return pool[picks]


@single_threaded_blas
def next_wave(problem: HistoryMatchProblem, previous: tuple = (),
              progress: Callable[[float], None] | None = None) -> Wave:
    """Run the wave after ``previous`` (a tuple of :class:`Wave`, possibly empty).

    Deterministic given ``problem.seed`` and the wave index, so stepping one wave at a
    time and running to the end give identical results. ``progress(fraction)`` is called
    between the steps of the emulator fit, of the candidates' random walk and of their
    scoring; if it raises (e.g. :class:`mdcore.Cancelled`), the wave stops.
    """
    def stage(lo: float, hi: float):
        return None if progress is None else (lambda f: progress(lo + (hi - lo) * f))

    t0 = time.perf_counter()
    k = len(previous) + 1
    if previous and previous[-1].done:
        raise ValueError(f"the history match already stopped at wave {k - 1} "
                         f"({previous[-1].status}); start a new one to change settings.")
    rng = np.random.default_rng([problem.seed, k])
    span = problem.bounds[:, 1] - problem.bounds[:, 0]
    n_runs, n_candidates = problem.options.n_runs, problem.options.n_candidates
    assert n_runs is not None and n_candidates is not None      # filled in by setup
    if k == 1:
        new_runs = problem.initial_design
        old_theta = np.empty((0, problem.p))
        old_y = np.empty((0,) + problem.z.shape)
    else:
        last = previous[-1]
        em = last.emulator
        old_theta, old_y = em.theta_train, em.y_train
        new_runs = _maximin(last.nroy, old_theta, n_runs, span, rng)
    runs = run_simulator(problem.simulate, problem.X, new_runs, problem.z.shape[1],
                         executor=problem.options.executor, batch_size=problem.options.batch_size,
                         timeout=problem.options.timeout)
    n_failed = len(runs.failures)
    if n_failed and (n_failed == len(new_runs)
                     or n_failed > problem.options.max_failed_fraction * len(new_runs)):
        first = runs.failures[0]
        raise ValueError(
            f"wave {k}: {n_failed} of {len(new_runs)} simulator runs failed (at most "
            f"{problem.options.max_failed_fraction:.0%} may); the first at θ = "
            f"{np.array2string(first.theta, precision=4)}: {first.message}. Fix the simulator "
            "(simulate) or narrow the bounds to where it runs.")
    new_runs, new_y = new_runs[runs.ok], runs.y
    emulator = fit_emulator(problem.X, np.vstack([old_theta, new_runs]),
                            np.concatenate([old_y, new_y]), problem.bounds, seed=rng,
                            progress=stage(0.1, 0.4))
    if k == 1:
        candidates = problem.bounds[:, 0] + span * rng.uniform(size=(n_candidates,
                                                                      problem.p))
        base_fraction = 1.0
    else:
        candidates = _uniform_in_nroy(problem, previous, previous[-1].nroy,
                                      n_candidates, rng, stage(0.4, 0.7))
        base_fraction = previous[-1].nroy_fraction
    # Scored in chunks (bounded memory): each chunk's largest emulator variance at its
    # retained rows, then the largest over the chunks (a maximum: the same values).
    I = np.empty(candidates.shape[0])
    chunk_max = []
    for rows in problem.chunks(candidates.shape[0]):
        if progress is not None:
            progress(0.7 + 0.3 * rows.start / candidates.shape[0])
        I[rows], var = problem.score(candidates[rows], emulator)
        kept = I[rows] <= problem.cutoff
        if np.any(kept):
            # the kept rows of (m, N·n_out), then the max over N: half the time of
            # np.max(var[kept], axis=(0, 1)) on shear-5's (10⁵, 3, 5), the same values
            chunk_max.append(var.reshape(len(var), -1)[kept].max(axis=0)
                             .reshape(var.shape[1:]).max(axis=0))
    keep = I <= problem.cutoff
    nroy = candidates[keep]
    fraction = base_fraction * float(np.mean(keep))       # chain rule, module docstring
    threshold_var = problem.options.convergence_ratio * np.min(problem.V_o + problem.V_m, axis=0)
    if nroy.shape[0]:
        max_var = np.max(chunk_max, axis=0)
        converged = bool(np.all(max_var < threshold_var))
        if problem.options.rule == MULTIVARIATE:  # V_em(θ) ≼ ratio · (V_o + V_m) at NROY
            converged = multivariate.cov_ratio(emulator, nroy, problem.V) \
                < problem.options.convergence_ratio
    else:
        max_var = np.full(problem.z.shape[1], np.nan)
        converged = False
    if not nroy.shape[0]:
        status, message = "ruled_out", f"wave {k}: " + (
            RULED_OUT_HINT_MV if problem.options.rule == MULTIVARIATE else RULED_OUT_HINT)
    elif converged:
        status = "converged"
        what = "covariance" if problem.options.rule == MULTIVARIATE else "variance"
        message = (f"wave {k}: converged — the emulator {what} is below V_o + V_m at every "
                   f"retained point; NROY is {100 * fraction:.3g}% of the box.")
    elif k >= problem.options.max_waves:
        status = "max_waves"
        message = (f"wave {k}: stopped at max_waves = {problem.options.max_waves}; NROY is "
                   f"{100 * fraction:.3g}% of the box (emulator not yet below V_o + V_m).")
    else:
        status = "running"
        message = f"wave {k}: NROY is {100 * fraction:.3g}% of the box."
    if n_failed:
        message += (f" {n_failed} of {n_failed + len(new_runs)} simulator runs failed and were "
                    f"dropped (first: {runs.failures[0].message}).")
    return Wave(k, candidates, I, nroy, fraction, new_runs, emulator, max_var, threshold_var,
                status, message, time.perf_counter() - t0, problem, runs.failures)


def iter_waves(problem: HistoryMatchProblem) -> Iterator[Wave]:
    """Yield waves one at a time until the stopping rule ends the match."""
    waves: tuple = ()
    while not (waves and waves[-1].done):
        waves += (next_wave(problem, waves),)
        yield waves[-1]


@dataclass(frozen=True, eq=False)
class HistoryMatchResult:
    """All waves of a history match.

    Attributes
    ----------
    problem : HistoryMatchProblem
    waves : tuple of Wave
    """

    problem: HistoryMatchProblem
    waves: tuple

    def __post_init__(self):
        if not self.waves:
            raise ValueError("a HistoryMatchResult needs at least one wave.")

    @property
    def status(self) -> str:
        return self.waves[-1].status

    @property
    def message(self) -> str:
        return self.waves[-1].message

    @property
    def nroy_fraction(self) -> list:
        """NROY fraction of the original box after each wave."""
        return [w.nroy_fraction for w in self.waves]

    def contains(self, theta) -> np.ndarray:
        """Whether each θ is inside the prior box and non-implausible in every wave.

        Parameters
        ----------
        theta : ndarray of shape (M, p) or (p,)

        Returns
        -------
        ndarray of bool, shape (M,)
        """
        theta = np.atleast_2d(as_float_array(theta, "theta"))
        if theta.ndim != 2 or theta.shape[1] != self.problem.p:
            raise ValueError(f"theta must have shape (M, p) with p = {self.problem.p}; "
                             f"received {theta.shape}.")
        return _in_nroy(self.problem, self.waves, theta)

    def nroy_samples(self, n: int, seed=None,
                     progress: Callable[[float], None] | None = None) -> np.ndarray:
        """``n`` samples of θ, uniform in the final NROY set, shape (n, p).

        These are not the posterior draws (see :meth:`posterior_samples`): the NROY set is
        the support of the posterior, and these samples fill it evenly. ``progress`` as in
        :func:`next_wave`.

        Raises
        ------
        ValueError
            If the last wave ruled out everything.
        """
        n = as_int(n, "n", 1, MAX_CANDIDATES)
        last = self.waves[-1]
        if last.nroy.shape[0] == 0:
            raise ValueError(f"no θ samples: {last.message}")
        return _uniform_in_nroy(self.problem, self.waves, last.nroy, n,
                                np.random.default_rng(seed), progress)

    def posterior_samples(self, n: int, seed=None,
                          progress: Callable[[float], None] | None = None) -> np.ndarray:
        """``n`` samples of θ from the posterior ``p(θ | z)`` restricted to NROY, (n, p).

        Sampling-importance-resampling: a pool of ``max(20 n, 20,000)`` uniform NROY
        samples (the prior is uniform on the box) is resampled with replacement in
        proportion to :meth:`log_likelihood` (normalised in log space). These are the
        θ^(j) ~ p(θ | z) of the discrepancy scenarios; repeats are
        possible when the likelihood is concentrated.

        With an integer ``seed`` the draws are kept (a few, the newest) and a repeated call
        returns a copy of them: scenarios 2 and 3 of one run ask for the same θ^(j).
        ``progress`` as in :func:`next_wave`.
        """
        n = as_int(n, "n", 1, MAX_CANDIDATES // 20)
        key = (n, int(seed)) if isinstance(seed, (int, np.integer)) \
            and not isinstance(seed, bool) else None
        memo = self._posterior_memo
        if key is not None and key in memo:
            return memo[key].copy()
        rng = np.random.default_rng(seed)
        pool = self.nroy_samples(max(20 * n, 20_000), seed=rng, progress=None if progress
                                 is None else (lambda f: progress(0.8 * f)))
        ll = self.log_likelihood(pool, None if progress is None
                                 else (lambda f: progress(0.8 + 0.2 * f)))
        w = np.exp(ll - scipy.special.logsumexp(ll))
        draws = pool[rng.choice(pool.shape[0], size=n, p=w / w.sum())]
        if key is not None:
            while len(memo) >= POSTERIOR_MEMO:
                memo.pop(next(iter(memo)))                      # the oldest
            memo[key] = draws.copy()
        return draws

    @cached_property
    def _posterior_memo(self) -> dict:
        """(n, seed) -> the draws of :meth:`posterior_samples` (the newest few)."""
        return {}

    def log_likelihood(self, theta,
                       progress: Callable[[float], None] | None = None) -> np.ndarray:
        """Gaussian log-likelihood behind the implausibility measure, shape (M,).

        ``log p(z | θ) = −½ Σ_i [(z_i − E[y_i(θ)])² / s_i² + log 2π s_i²]``,
        ``s_i² = V_o,i + V_m,i + V[y_i(θ)]``, with the final wave's emulator: the model that
        Eq. 16 standardises by. θ (M, p) -> (M,). In chunks of θ (bounded memory);
        ``progress`` as in :func:`next_wave`.
        """
        theta = np.atleast_2d(as_float_array(theta, "theta"))
        out = np.empty(theta.shape[0])
        for rows in self.problem.chunks(theta.shape[0]):
            if progress is not None:
                progress(rows.start / theta.shape[0])
            if self.problem.options.rule == MULTIVARIATE:   # the full Gaussian of I_M²
                out[rows] = multivariate.log_likelihood(self.waves[-1].emulator, theta[rows],
                                                        self.problem.z, self.problem.V)
                continue
            pred = self.waves[-1].emulator.predict(self.problem.X, theta[rows])
            s2 = self.problem.V_o + self.problem.V_m + pred.var
            r2 = (self.problem.z - pred.mean) ** 2 / s2
            out[rows] = -0.5 * np.sum(r2 + np.log(2.0 * np.pi * s2), axis=(1, 2))
        return out

    @cached_property
    def theta_map(self) -> np.ndarray:
        """θ_MAP: the maximiser of :meth:`log_likelihood` over the final NROY set (the
        prior is uniform on the box), the best of 2,000 NROY samples (seeded by the problem)
        polished by Nelder–Mead, the polish kept only if it stays non-implausible."""
        return self._find_theta_map()

    def compute_theta_map(self, progress: Callable[[float], None] | None = None) -> np.ndarray:
        """:attr:`theta_map`, found now unless it was already; ``progress`` as in
        :func:`next_wave` (if it raises, nothing is kept)."""
        if "theta_map" not in self.__dict__:                  # the cached_property's slot
            self.__dict__["theta_map"] = self._find_theta_map(progress)
        return self.theta_map

    def _find_theta_map(self, progress=None) -> np.ndarray:
        def stage(lo, hi):
            return None if progress is None else (lambda f: progress(lo + (hi - lo) * f))

        theta = self.nroy_samples(2000, seed=[self.problem.seed, 10_000], progress=stage(0, 0.4))
        ll = self.log_likelihood(theta, stage(0.4, 0.5))
        start = theta[int(np.argmax(ll))]
        b = self.problem.bounds
        span = b[:, 1] - b[:, 0]

        def objective(u):
            return -float(self.log_likelihood(b[:, 0] + span * u)[0])

        res = scipy.optimize.minimize(objective, (start - b[:, 0]) / span, method="Nelder-Mead",
                                      bounds=[(0.0, 1.0)] * self.problem.p,
                                      options=dict(xatol=1e-6, fatol=1e-9),
                                      callback=None if progress is None
                                      else (lambda *_: progress(0.5)))
        best = b[:, 0] + span * res.x
        if -res.fun > ll.max() and self.contains(best)[0]:
            return best
        return start


def setup_arguments(overrides: dict) -> dict:
    """Keyword arguments of :func:`setup` from ``overrides``, with the fields of
    :class:`HistoryMatchOptions` among them gathered into its ``options``."""
    names = {f.name for f in fields(HistoryMatchOptions)}
    direct = {"V_m", "V_o", "initial_design", "seed", "options"}
    unknown = sorted(set(overrides) - names - direct)
    if unknown:
        raise ValueError(f"unknown history-matching option(s) {unknown}; expected some of "
                         f"{sorted(direct | names)}.")
    kwargs = {k: v for k, v in overrides.items() if k in direct}
    chosen = {k: v for k, v in overrides.items() if k in names}
    if chosen:
        kwargs["options"] = replace(kwargs.get("options") or HistoryMatchOptions(), **chosen)
    return kwargs


def history_match(simulate: Callable, X, z, bounds, **options) -> HistoryMatchResult:
    """Run waves until the stopping rule ends them (Eq. 16).

    Takes the arguments of :func:`setup`, and the fields of :class:`HistoryMatchOptions` by
    name. A history match that rules out everything is not an exception: the result's
    ``status`` is ``"ruled_out"`` and its ``message`` suggests raising V_m or T.
    """
    problem = setup(simulate, X, z, bounds, **setup_arguments(options))
    return HistoryMatchResult(problem, tuple(iter_waves(problem)))


def case_problem(case, **overrides) -> HistoryMatchProblem:
    """A :class:`HistoryMatchProblem` for a :class:`~mdcore.Case` with its defaults.

    ``V_o`` defaults to the case's noise variance (replicates use their sample variance),
    ``V_m`` to ``case.V_m`` (its correlation to ``case.V_m_length`` and ``case.V_m_corr``)
    and the initial design to ``case.initial_design``. With a
    ``case.timeout``, each θ is a call of its own (``batch_size=1``), so a run that times
    out fails alone.
    """
    options = dict(V_o=case.noise_var, V_m=case.V_m, initial_design=case.initial_design,
                   seed=case.seed, batch_size=None if case.timeout is None else 1,
                   V_m_length=case.V_m_length, V_m_corr=case.V_m_corr)
    if "options" in overrides:        # an options object replaces the case's option defaults
        for key in ("batch_size", "V_m_length", "V_m_corr"):
            options.pop(key)
    options.update(overrides)
    return setup(case.simulate, case.X_train, case.z_train, case.theta_bounds,
                 **setup_arguments(options))


def history_match_case(case, **overrides) -> HistoryMatchResult:
    """Run :func:`history_match` on a case study with its defaults (see :func:`case_problem`)."""
    problem = case_problem(case, **overrides)
    return HistoryMatchResult(problem, tuple(iter_waves(problem)))
