"""From a history match to a scored method (docs/method.md §6–8): :func:`run_method` is the
one place that wires a method (scenarios 1–3 or KOH) to a case, for the API, CLI and app."""

from __future__ import annotations

import enum
import threading
import time
from collections.abc import Callable
from concurrent.futures import Executor
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from scipy.special import logsumexp

from . import _compiled as compiled
from ._cases import Case
from ._discrepancy import (
    MAX_N_PHI,
    MAX_N_S,
    MAX_PAIRS,
    PROPOSALS,
    PRUNE,
    DiscrepancyModel,
    DiscrepancyOptions,
    DiscrepancyPrediction,
    _blocks,
    check_executor,
    check_prune,
    infer_discrepancy,
)
from ._exceptions import (
    K_HAT_THRESHOLD,
    LOW_ESS,
    Cancelled,
    chain_advice,
    output_label,
    weights_advice,
)
from ._history_matching import HistoryMatchResult
from ._hyperfit import QPSO_ITERATIONS, FitOptions
from ._koh import BURN_IN, FAST, MAX_CHAIN, N_ITER, KOHModel, KOHOptions, infer_koh
from ._mcmc import chain_length
from ._metrics import coverage, lpl, mmd, nmse
from ._priors import GaussianPrior
from ._validation import as_float_array, as_int, as_seed_int, check_type, choose

#: The paper's (N_s, N_φ) per case study (docs/method.md §6).
PAPER_SIZES = {"beam-1d": (1000, 500), "beam-2d": (1000, 1000), "shear-5": (1000, 500)}

#: Most swarm steps of the φ̂ fit (10× the default; more only costs time).
MAX_FIT_ITERATIONS = 10 * QPSO_ITERATIONS
#: The app's swarm steps (:meth:`Settings.interactive`).
INTERACTIVE_FIT_ITERATIONS = 30

#: ``progress(fraction, message)``: fraction done in [0, 1] and what is running.
Progress = Callable[[float, str], None]


class Method(enum.Enum):
    """A way to learn the discrepancy: the decoupled scenarios 1–3 or the KOH baseline.

    Examples
    --------
    >>> Method.parse(3), Method.parse("koh").label
    (<Method.S3: '3'>, 'KOH')
    """

    S1 = "1"
    S2 = "2"
    S3 = "3"
    KOH = "koh"

    @classmethod
    def parse(cls, value) -> Method:
        """A :class:`Method` from ``1``, ``"1"``, ``"koh"``, ``"KOH"`` or a Method."""
        if isinstance(value, cls):
            return value
        label = None if isinstance(value, bool) else str(value).strip().lower()
        for m in cls:
            if m.value == label:
                return m
        raise ValueError(f"{value!r} is not a valid method. It must be one of "
                         f"{[m.value for m in cls]} (1–3: the decoupled scenarios; koh: the "
                         "Kennedy–O'Hagan baseline; docs/method.md §6–7).")

    @property
    def label(self) -> str:
        """Display name: "Scenario 1" … "Scenario 3", "KOH"."""
        return "KOH" if self is Method.KOH else f"Scenario {self.value}"

    @property
    def scenario(self) -> int | None:
        """The scenario number 1–3, or None for KOH."""
        return None if self is Method.KOH else int(self.value)

    def __str__(self) -> str:
        return self.value


class MethodKey(NamedTuple):
    """The settings a method's result depends on (others are None); hashable, for caches."""

    method: Method
    n_s: int | None
    n_phi: int | None
    n_iter: int | None
    burn_in: int | None
    prune: float | None
    proposal: str | None
    fit_iterations: int | None


@dataclass(frozen=True)
class Settings:
    """Sizes of the discrepancy methods, validated.

    Parameters
    ----------
    n_s, n_phi : int, default=1000 and 500
        θ samples ``θ^(j) ~ p(θ | z)`` (scenarios 2–3); hyperparameter samples per θ (3).
    n_iter, burn_in : int, default=150,000 and 50,000
        The KOH chain (docs/method.md §7).
    prune : float, default=1e-12
        Scenario 3 with the prior proposal skips components whose weight is below
        ``prune × max`` when predicting (the skipped mass is in :class:`ImportanceDiagnostics`).
    proposal : {"adaptive", "prior"}, default="adaptive"
        Scenario 3's φ proposal: adaptive (reliable weights) or the paper's prior draws.
    fit_iterations : int, default=120
        Swarm steps of the QPSO behind φ̂ of scenarios 1–2 (Eq. 8) before its L-BFGS-B
        polish (:func:`mdcore._hyperfit.fit_hyperparameters`).
    backend : {"auto", "numpy", "numba"}, default="auto"
        Kernels of scenario 3 and the KOH chain (:func:`mdcore._compiled.resolve_backend`;
        "auto" is the compiled path when numba is installed); they agree to ~1e-12, so
        :meth:`key` leaves the backend out.

    Examples
    --------
    >>> key = Settings(n_s=10).key(Method.S2)
    >>> key.n_s, key.n_phi, key.proposal
    (10, None, None)
    """

    n_s: int = 1000
    n_phi: int = 500
    n_iter: int = N_ITER
    burn_in: int = BURN_IN
    prune: float = PRUNE
    proposal: str = "adaptive"
    backend: str = "auto"
    fit_iterations: int = QPSO_ITERATIONS

    def __post_init__(self):
        for name, minimum, maximum in (("n_s", 1, MAX_N_S), ("n_phi", 1, MAX_N_PHI),
                                       ("n_iter", 2, MAX_CHAIN), ("burn_in", 0, MAX_CHAIN),
                                       ("fit_iterations", 1, MAX_FIT_ITERATIONS)):
            object.__setattr__(self, name, as_int(getattr(self, name), name, minimum, maximum))
        if self.n_s * self.n_phi > MAX_PAIRS:
            raise ValueError(f"n_s × n_phi must be at most {MAX_PAIRS:,} (θ, φ) pairs for "
                             f"scenario 3; received n_s = {self.n_s:,} and n_phi = "
                             f"{self.n_phi:,} ({self.n_s * self.n_phi:,} pairs). Lower one of "
                             "them (the paper: 1000 × 500).")
        # The chain's own rule (two kept samples), so that KOH never refuses what passed here.
        chain_length(self.n_iter, self.burn_in, " Raise n_iter or lower burn_in (the paper: "
                     "150,000 and 50,000).")
        object.__setattr__(self, "prune", check_prune(self.prune))
        choose(self.proposal, "proposal", PROPOSALS)
        compiled.resolve_backend(choose(self.backend, "backend", compiled.BACKENDS))

    @classmethod
    def paper(cls, case_name: str) -> Settings:
        """The paper's sizes for a built-in case (docs/cases.md); other cases get beam-1d's."""
        n_s, n_phi = PAPER_SIZES.get(case_name, PAPER_SIZES["beam-1d"])
        return cls(n_s=n_s, n_phi=n_phi)

    @classmethod
    def interactive(cls) -> Settings:
        """Small sizes for the app: N_s = 100, N_φ = 50, the 20,000-step KOH chain and a
        30-step swarm for φ̂, which with the L-BFGS-B polish after it reaches the 120-step
        optimum at a quarter of the cost (docs/performance.md)."""
        return cls(n_s=100, n_phi=50, n_iter=FAST["n_iter"], burn_in=FAST["burn_in"],
                   fit_iterations=INTERACTIVE_FIT_ITERATIONS)

    def key(self, method) -> MethodKey:
        """The fields ``method``'s result depends on; the others are None."""
        m = Method.parse(method)
        return MethodKey(m,
                         self.n_s if m in (Method.S2, Method.S3) else None,
                         self.n_phi if m is Method.S3 else None,
                         self.n_iter if m is Method.KOH else None,
                         self.burn_in if m is Method.KOH else None,
                         self.prune if m is Method.S3 else None,
                         self.proposal if m is Method.S3 else None,
                         self.fit_iterations if m in (Method.S1, Method.S2) else None)


@dataclass(frozen=True)
class Metrics:
    """docs/method.md §8 metrics of a prediction at the test inputs; each a tuple over outputs.

    ``nmse_delta``, ``rmse_delta`` and the δ coverages are None when the true δ is unknown.
    Beside docs/method.md §8: ``rmse_delta`` is the δ error in output units (NMSE divides by the
    variance of the true δ over the test inputs, which is nearly zero where δ hardly varies,
    as on shear-5), and ``sd_z``, ``sd_delta`` are the mean predictive standard deviations
    (the band widths, output units).
    """

    nmse_z: tuple
    mmd: tuple
    lpl: tuple
    coverage_z_2sd: tuple
    coverage_z_3sd: tuple
    nmse_delta: tuple | None
    coverage_delta_2sd: tuple | None
    coverage_delta_3sd: tuple | None
    rmse_delta: tuple | None
    sd_z: tuple
    sd_delta: tuple

    def as_dict(self) -> dict:
        """Field -> list over outputs (or None), for JSON."""
        return {k: None if v is None else list(v) for k, v in self.__dict__.items()}


@dataclass(frozen=True)
class ImportanceDiagnostics:
    """How well scenario 3's importance weights (Eq. 15) are spread, per output: ``ess`` over
    the ``n_pairs`` (θ, φ) pairs, ``1 / Σ w_jk²``, and ``ess_phi`` over the ``n_phi`` φ given
    θ averaged with the θ weights, ``Σ_j w_j / Σ_k (w_jk / w_j)²``; the ``skipped_mass`` of
    the prediction (below ``prune × max``); ``k_hat`` the Pareto shape of the raw weights'
    tail (Vehtari et al.; above 0.7 unreliable); the ``proposal``."""

    ess: tuple
    ess_phi: tuple
    skipped_mass: tuple
    k_hat: tuple
    n_pairs: int
    n_phi: int
    proposal: str

    @property
    def low(self) -> tuple:
        """Per output, whether the weights are unreliable: ESS over pairs below
        :data:`mdcore._exceptions.LOW_ESS` or k̂ above 0.7."""
        return tuple(e < LOW_ESS or k > K_HAT_THRESHOLD for e, k in zip(self.ess, self.k_hat))


@dataclass(frozen=True)
class ChainDiagnostics:
    """The KOH chain (docs/method.md §7): acceptance rate, integrated autocorrelation time
    ``iat`` and ``ess = n_kept / iat`` per parameter, and whether it is ``reliable``: longer
    than 50 autocorrelation times in every parameter (emcee's check; if not, the IAT and ESS
    are themselves uncertain)."""

    acceptance_rate: float
    iat: tuple
    ess: tuple
    n_iter: int
    burn_in: int
    reliable: bool


@dataclass(frozen=True, eq=False)
class MethodResult:
    """One method run on one case (:func:`run_method`) with the ``key`` of settings it depends
    on: the fitted ``model`` (its ``predict`` takes other inputs), the predictions ``on_test``
    at ``case.X_test`` (each field (N_test, n_out)) and ``on_extra`` at ``X_extra`` (or None),
    the ``metrics``, the ``importance`` (scenario 3) or ``chain`` (KOH) diagnostics or None,
    the ``warnings`` they call for in words, and the inference and prediction ``seconds``."""

    method: Method
    key: MethodKey
    seed: int
    model: DiscrepancyModel | KOHModel
    on_test: DiscrepancyPrediction
    on_extra: DiscrepancyPrediction | None
    metrics: Metrics
    importance: ImportanceDiagnostics | None
    chain: ChainDiagnostics | None
    warnings: tuple
    seconds: float


#: The metrics table's columns after "method" and "output": heading -> how text shows it.
#: Metrics (docs/method.md §8), then scenario 3's weight diagnostics, then KOH's chain's.
METRIC_COLUMNS = {
    "NMSE z %": "{:.3f}", "NMSE δ %": "{:.3f}", "RMSE δ": "{:.3g}", "MMD": "{:.4f}",
    "LPL": "{:.1f}", "cover z ±2σ": "{:.2f}", "cover z ±3σ": "{:.2f}", "cover δ ±2σ": "{:.2f}",
    "cover δ ±3σ": "{:.2f}", "ESS pairs": "{:,.1f}", "ESS φ": "{:.1f}", "k̂": "{:.2f}",
    "acceptance": "{:.3f}", "IAT (max)": "{:.1f}", "chain ESS (min)": "{:,.0f}",
    "seconds": "{:.2f}"}


def metrics_table(results, output_names) -> list[dict]:
    """The metrics table of the command line, the app and the report: one row per (method,
    output) of ``results`` (MethodResult, in the order given).

    Each row maps "method" (the :class:`Method`), "output" (its name), "unreliable" (whether its
    importance weights are, see :attr:`ImportanceDiagnostics.low`) and every
    :data:`METRIC_COLUMNS` heading to a float, or to None where the number does not apply
    (δ metrics without a known δ, scenario 3's diagnostics elsewhere, KOH's chain's).
    """
    rows = []
    for r in results:
        m, imp, chain = r.metrics, r.importance, r.chain
        whole = (None,) * 3 if chain is None else (
            chain.acceptance_rate, max(chain.iat), min(chain.ess))
        for o, name in enumerate(output_names):
            cells = (m.nmse_z, m.nmse_delta, m.rmse_delta, m.mmd, m.lpl, m.coverage_z_2sd,
                     m.coverage_z_3sd, m.coverage_delta_2sd, m.coverage_delta_3sd,
                     *((None,) * 3 if imp is None else (imp.ess, imp.ess_phi, imp.k_hat)))
            values = [None if v is None else v[o] for v in cells] + [*whole, r.seconds]
            rows.append({"method": r.method, "output": name,
                         "unreliable": imp is not None and imp.low[o],
                         **{k: None if v is None else float(v)
                            for k, v in zip(METRIC_COLUMNS, values, strict=True)}})
    return rows


def metric_text(heading: str, value) -> str:
    """A :func:`metrics_table` cell as text: its column's format, "—" where it does not
    apply."""
    return "—" if value is None else METRIC_COLUMNS[heading].format(value)


def _floats(values) -> tuple:
    return tuple(float(v) for v in np.atleast_1d(values))


def scores(case: Case, prediction: DiscrepancyPrediction) -> Metrics:
    """docs/method.md §8 metrics, per output, of a prediction at ``case.X_test``."""
    z, p = case.z_test, prediction
    if p.z_mean.shape != z.shape:
        raise ValueError(f"prediction must be at case.X_test: z_mean has shape "
                         f"{p.z_mean.shape}, z_test {z.shape}.")
    delta = case.true_delta(case.X_test)

    def of_delta(metric) -> tuple | None:
        return None if delta is None else _floats(metric(delta))

    return Metrics(
        nmse_z=_floats(nmse(z, p.z_mean)),
        mmd=_floats(mmd(z, p.z_mean, p.z_var, X=case.X_test)),
        lpl=_floats(lpl(z, p.z_mean, p.z_var)),
        coverage_z_2sd=_floats(coverage(z, p.z_mean, p.z_var, k=2)),
        coverage_z_3sd=_floats(coverage(z, p.z_mean, p.z_var, k=3)),
        nmse_delta=of_delta(lambda d: nmse(d, p.delta_mean)),
        coverage_delta_2sd=of_delta(lambda d: coverage(d, p.delta_mean, p.delta_var, k=2)),
        coverage_delta_3sd=of_delta(lambda d: coverage(d, p.delta_mean, p.delta_var, k=3)),
        rmse_delta=of_delta(lambda d: np.sqrt(np.mean((d - p.delta_mean) ** 2, axis=0))),
        sd_z=_floats(np.mean(np.sqrt(p.z_var), axis=0)),
        sd_delta=_floats(np.mean(np.sqrt(p.delta_var), axis=0)))


def koh_phi_prior(case: Case) -> GaussianPrior:
    """The case's discrepancy prior without its ``ℓ_y`` entries: the KOH δ is a GP over x
    only, ``[log σ_f, log ℓ_x…, log σ_n]``. Used as the hyperprior of KOH's φ̂, as
    scenarios 1–2 use ``case.phi_prior`` for theirs (docs/method.md §7 leaves it to us)."""
    keep = np.r_[0, np.arange(1 + case.n_out, case.phi_prior.size)]
    return GaussianPrior(case.phi_prior.mean[keep], case.phi_prior.var[keep])


DIAGNOSTIC_ROWS = 1000


def importance_diagnostics(model: DiscrepancyModel) -> ImportanceDiagnostics:
    """ESS over pairs and over φ of a scenario-3 model's log weights (n_out, S, K), in blocks
    of :data:`DIAGNOSTIC_ROWS` θ rows so that the temporaries stay small."""
    lw_all = model.log_weights
    n_out, S, K = lw_all.shape
    lw_theta = np.empty((n_out, S))                                    # log w_j
    log_ess_j = np.empty((n_out, S))
    for rows in _blocks(S, DIAGNOSTIC_ROWS):
        lw = lw_all[:, rows]
        lw_theta[:, rows] = logsumexp(lw, axis=2)
        # ESS_j over φ given θ_j: 1 / Σ_k (w_jk / w_j)², in log space.
        with np.errstate(invalid="ignore"):
            cond = lw - lw_theta[:, rows, None]
            log_ess_j[:, rows] = -logsumexp(2.0 * np.where(np.isfinite(cond), cond, -np.inf),
                                            axis=2)
    ess_phi = np.sum(np.exp(lw_theta + np.where(np.isfinite(lw_theta), log_ess_j, 0.0)),
                     axis=1)
    k_hat = np.broadcast_to(np.nan if model.k_hat is None else model.k_hat, n_out)
    return ImportanceDiagnostics(_floats(model.ess), _floats(ess_phi),
                                 _floats(model.skipped_mass), _floats(k_hat), S * K, K,
                                 str(model.proposal))


def _chain_diagnostics(model: KOHModel) -> ChainDiagnostics:
    chain = model.chain
    return ChainDiagnostics(float(chain.acceptance_rate), _floats(chain.iat),
                            _floats(chain.ess), int(chain.n_iter), int(chain.burn_in),
                            bool(chain.reliable))


def _advice(importance, chain) -> tuple:
    """The warnings the diagnostics call for, each saying what to change."""
    out = [] if importance is None else [
        weights_advice(output_label("scenario 3", o, len(importance.low)), importance.ess[o],
                       importance.n_pairs // importance.n_phi, importance.n_phi,
                       importance.k_hat[o], importance.proposal)
        for o, low in enumerate(importance.low) if low]
    if chain is not None and not chain.reliable:
        out.append(chain_advice("adaptive Metropolis", max(chain.iat),
                                chain.n_iter - chain.burn_in, chain.burn_in))
    return tuple(out)


def _union(X_extra: np.ndarray, X_test: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rows of ``X_extra`` not in ``X_test``, then ``X_test`` (M_new + N*, d_x), and each
    ``X_extra`` row's index there (M,): a grid holding the test inputs (beam-2d's) costs no
    second prediction."""
    at = {row.tobytes(): i for i, row in enumerate(X_test)}
    where = np.fromiter((at.get(row.tobytes(), -1) for row in X_extra), dtype=np.int64,
                        count=X_extra.shape[0])
    new = where < 0
    n_new = int(np.count_nonzero(new))
    rows = np.where(new, np.cumsum(new) - 1, n_new + where)
    return np.vstack([X_extra[new], X_test]), rows


def run_method(case: Case, hm: HistoryMatchResult, method, settings: Settings, *, seed,
               X_extra=None, log_params_hat=None, progress: Progress | None = None,
               cancel: threading.Event | None = None,
               executor: Executor | None = None) -> MethodResult:
    """Learn the discrepancy of ``case`` by one method and score it (docs/method.md §6–8).

    Parameters
    ----------
    case : Case
        Data, simulator and priors (:func:`mdcore._cases.load`).
    hm : HistoryMatchResult
        A history match of ``case``; the decoupled scenarios draw θ from its posterior and
        use its θ_MAP, KOH uses its final emulator.
    method : Method, int or str
        1, 2, 3 or "koh".
    settings : Settings
    seed : int or numpy.random.Generator
        Seeds the θ draws, the φ̂ swarm, the φ draws and the KOH chain.
    X_extra : ndarray of shape (M, d_x), optional
        More inputs to predict at (for example a plotting grid): :attr:`MethodResult.on_extra`.
    log_params_hat : ndarray of shape (n_out, P), optional
        φ̂ of an earlier scenario-1 result on the same ``hm`` and ``seed``
        (``result.model.log_params_hat``); scenario 2 then skips the refit, with the same
        numbers.
    progress : callable, optional
        ``progress(fraction, message)`` as the work goes on.
    cancel : threading.Event, optional
        Checked between chunks of work; when set, the run raises :class:`Cancelled`.
    executor : concurrent.futures.Executor, optional
        Runs the chunks of (θ, φ) pairs of scenarios 2–3 (:mod:`mdcore._discrepancy`), e.g.
        a Dask ``Client(...).get_executor()``, with the serial run's numbers. Default: here.

    Raises
    ------
    ValueError
        For bad input, or a history match that ruled out everything.
    """
    start = time.perf_counter()
    check_type(case, Case, "case", "an mdcore Case (mdcore.load_case)")
    check_type(hm, HistoryMatchResult, "hm", "a HistoryMatchResult (history_match_case)")
    check_type(settings, Settings, "settings", "a pipeline.Settings")
    method = Method.parse(method)
    executor = check_executor(executor)
    if hm.problem.p != case.p or hm.problem.X.shape[1] != case.d_x:
        raise ValueError(f"hm does not belong to {case.name}: it has p = {hm.problem.p} and "
                         f"d_x = {hm.problem.X.shape[1]}; the case has p = {case.p} and "
                         f"d_x = {case.d_x}.")
    if hm.status == "ruled_out":
        raise ValueError(f"hm (the history match) ruled out every θ, so there is nothing to "
                         f"learn the discrepancy from: {hm.message}")
    seed = as_seed_int(seed)
    X_all = case.X_test
    if X_extra is not None:
        X_extra = as_float_array(X_extra, "X_extra", ndim=2)
        if X_extra.shape[1] != case.d_x:
            raise ValueError(f"X_extra must have shape (M, d_x) with d_x = {case.d_x}; "
                             f"received {X_extra.shape}.")
        X_all, extra_rows = _union(X_extra, case.X_test)

    def stage(lo: float, hi: float, message: str) -> Callable[[float], None]:
        """A core progress callback mapped onto [lo, hi] that also checks ``cancel``."""
        def report(fraction: float) -> None:
            if cancel is not None and cancel.is_set():
                raise Cancelled(f"{method.label} on {case.name} was cancelled.")
            if progress is not None:
                progress(lo + (hi - lo) * float(fraction), message)
        return report

    stage(0.0, 0.0, "starting")(0.0)
    model: DiscrepancyModel | KOHModel
    if method is Method.KOH:
        koh_options = KOHOptions(n_iter=settings.n_iter, burn_in=settings.burn_in,
                                 phi_prior=koh_phi_prior(case), backend=settings.backend)
        model = infer_koh(hm.waves[-1].emulator, case.X_train, case.z_train,
                          theta_prior=case.theta_prior, bounds=case.theta_bounds,
                          options=koh_options, seed=seed,
                          progress=stage(0.0, 0.9, "KOH: φ̂ and the θ chain"))
    else:
        theta_map = hm.compute_theta_map(stage(0.0, 0.0, f"{method.label}: θ_MAP"))
        theta = hm.posterior_samples(settings.n_s, seed=seed, progress=stage(
            0.0, 0.0, f"{method.label}: θ draws")) if method is not Method.S1 else None
        options = DiscrepancyOptions(
            n_phi=settings.n_phi, phi_prior=case.phi_prior, proposal=settings.proposal,
            prune=settings.prune, backend=settings.backend,
            fit=FitOptions(n_iterations=settings.fit_iterations),
            log_params_hat=log_params_hat if method is Method.S2 else None)
        model = infer_discrepancy(
            case.simulate, theta, case.X_train, case.z_train, scenario=method.scenario,
            theta_map=theta_map, options=options, seed=seed,
            progress=stage(0.0, 0.5, f"{method.label}: fitting the discrepancy GP"),
            executor=executor)
    predicting = stage(0.9 if method is Method.KOH else 0.5, 1.0, f"{method.label}: predicting")
    pred = model.predict(X_all, progress=predicting, executor=executor) \
        if isinstance(model, DiscrepancyModel) else model.predict(X_all, progress=predicting)
    n_new = X_all.shape[0] - case.X_test.shape[0]
    on_extra = None if X_extra is None else \
        DiscrepancyPrediction(*(a[extra_rows] for a in pred))
    on_test = DiscrepancyPrediction(*(a[n_new:] for a in pred))
    importance = importance_diagnostics(model) if isinstance(model, DiscrepancyModel) \
        and method is Method.S3 else None
    chain = _chain_diagnostics(model) if isinstance(model, KOHModel) else None
    return MethodResult(method, settings.key(method), seed, model, on_test, on_extra,
                        scores(case, on_test), importance, chain,
                        _advice(importance, chain),
                        time.perf_counter() - start)
