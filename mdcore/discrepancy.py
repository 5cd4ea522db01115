"""Discrepancy inference: GP map {y = η(X, θ), X} -> z, scenarios 1–3 (SPEC §6).

For each output a zero-mean GP maps all simulator outputs ``y`` (the GP's "y" inputs,
``d_y = n_out``) and the inputs ``X`` to the observations ``z``. A scenario is a Gaussian
mixture over components ``(θ^(j), φ^(j,k))`` with normalised weights ``w_jk``:

- scenario 1: one component, θ_MAP with the empirical-Bayes φ̂ (Eq. 8);
- scenario 2: N_s components θ^(j) with φ̂ from scenario 1 and ``w_j = 1/N_s`` (Eq. 13);
- scenario 3: N_s × N_φ components, φ^(j,k) drawn from the prior, ``log w_jk = −NLML``
  normalised jointly with logsumexp (Eq. 15).

Per component, the discrepancy is ``δ^(j,k)(X*) = E[z*^(j,k)] − y*^(j)`` (SPEC §6), and the
mixture moments are the laws of total expectation and variance::

    E[δ] = Σ w (E[z*] − y*),   V[δ] = Σ w (V_f + (E[z*] − y*)²) − E[δ]²
    E[z] = Σ w E[z*],          V[z] = Σ w (V_f + σ_n² + E[z*]²) − E[z]²

with ``V_f`` the latent GP variance. The sums are accumulated about a reference component
(the heaviest), so large means do not cancel the small variances.

Examples
--------
>>> from mdcore import cases
>>> from mdcore.discrepancy import infer_discrepancy
>>> case = cases.load("beam-1d")
>>> theta = case.theta_true + [[0.0, 0.0], [1.0, -0.5], [-1.0, 0.5]]
>>> model = infer_discrepancy(case.simulate, theta, case.X_train, case.z_train, scenario=2,
...               theta_map=case.theta_true, seed=0)
>>> pred = model.predict(case.X_test)
>>> pred.delta_mean.shape, round(float(model.ess[0]), 6)
((200, 1), 3.0)
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from scipy.special import logsumexp

from . import compiled, gp
from .exceptions import LowESSWarning, NumericalWarning
from .hyperfit import default_bounds, fit_hyperparameters
from .importance import K_HAT_THRESHOLD, adaptive_importance_sampling, psis
from .priors import GaussianPrior
from .validation import as_float_array, as_int, as_outputs, choose

__all__ = ["infer_discrepancy", "DiscrepancyModel", "DiscrepancyPrediction", "default_phi_prior",
           "LowESSWarning", "SCENARIOS", "PROPOSALS", "LOW_ESS"]

SCENARIOS = (1, 2, 3)
#: Scenario 3's φ proposals: the paper's prior draws, or adaptive importance sampling.
PROPOSALS = ("prior", "adaptive")
#: Scenario 3 warns when an output's effective sample size is below this.
LOW_ESS = 30.0
#: Default pruning level: components with normalised weight below ``PRUNE × max`` are
#: skipped in the prediction step (their mass is reported).
PRUNE = 1e-12
#: Working-memory budget of one prediction block, in bytes.
BLOCK_BYTES = 32 * 2**20


class DiscrepancyPrediction(NamedTuple):
    """Mixture moments at the prediction inputs (SPEC §6).

    Attributes
    ----------
    z_mean, z_var : ndarray of shape (N*, n_out)
        Bias-corrected prediction of a new observation; the variance includes σ_n².
        Output units and output units squared.
    delta_mean, delta_var : ndarray of shape (N*, n_out)
        The inferred discrepancy δ(X*) and its (latent) variance.
    """

    z_mean: np.ndarray
    z_var: np.ndarray
    delta_mean: np.ndarray
    delta_var: np.ndarray


def default_phi_prior(Y, X, z) -> GaussianPrior:
    """A weak prior on the log hyperparameters, centred in :func:`mdcore.hyperfit.default_bounds`.

    Each log hyperparameter gets the midpoint of its data-scaled search box as mean and
    a standard deviation of a quarter of the box width, so ±2 sd spans the box
    (σ_f and σ_n scale with the RMS of ``z``, each ℓ with its input's range).

    Parameters
    ----------
    Y : ndarray of shape (N, d_y)
    X : ndarray of shape (N, d_x)
    z : ndarray of shape (N,)
    """
    b = default_bounds(Y, X, z)
    return GaussianPrior(mean=b.mean(axis=1), var=((b[:, 1] - b[:, 0]) / 4.0) ** 2)


def _scenario(value) -> int:
    try:
        s = int(value)
    except (TypeError, ValueError):
        s = None
    if s not in SCENARIOS or isinstance(value, bool) or (isinstance(value, float) and value != s):
        raise ValueError(f"{value!r} is not a valid scenario. It must be one of [1, 2, 3] "
                         "(1: θ_MAP with φ̂, 2: θ samples with φ̂, 3: θ and φ samples).")
    return s


def _simulate(simulate: Callable, X: np.ndarray, theta: np.ndarray, n_out: int) -> np.ndarray:
    """Run ``simulate`` and check its (n_theta, N, n_out) result."""
    y = np.asarray(simulate(X, theta), dtype=np.float64)
    want = (theta.shape[0], X.shape[0], n_out)
    if y.shape != want:
        raise ValueError(f"simulate(X, theta) must return shape (n_theta, N, n_out) = {want}; "
                         f"it returned {y.shape}.")
    if not np.all(np.isfinite(y)):
        raise ValueError("simulate(X, theta) returned NaN or inf; check the θ samples lie "
                         "inside the simulator's valid range.")
    return y


def _blocks(n: int, size: int):
    for start in range(0, n, size):
        yield slice(start, min(n, start + size))


@dataclass(frozen=True, eq=False)
class DiscrepancyModel:
    """A fitted discrepancy mixture; call :meth:`predict` for z* and δ*.

    Attributes
    ----------
    scenario : int
        1, 2 or 3.
    theta : ndarray of shape (S, p)
        The θ of the mixture (S = 1 for scenario 1, N_s otherwise).
    Y : ndarray of shape (S, N, n_out)
        Simulator outputs at the training inputs, ``η(X, θ^(j))``.
    X : ndarray of shape (N, d_x)
    z : ndarray of shape (N, n_out)
    log_params : ndarray of shape (n_out, S, K, P)
        Hyperparameters of every component (K = 1 for scenarios 1–2, N_φ for 3). Together
        with :attr:`weights` this is scenario 3's hyperparameter posterior. Scenario 3
        shares one prior draw between outputs (common random numbers).
    log_weights : ndarray of shape (n_out, S, K)
        Normalised log weights; ``logsumexp`` over (S, K) is 0 for every output.
    log_params_hat : ndarray of shape (n_out, P) or None
        Empirical-Bayes φ̂ (scenarios 1–2).
    nlml_hat : ndarray of shape (n_out,) or None
        NLML at φ̂ on ``y(θ_MAP)``.
    prune : float
        Components whose weight is below ``prune × max`` are skipped in :meth:`predict`.
    phi_prior : GaussianPrior or None
        The prior scenario 3 sampled from.
    seconds : float
        Time spent in :func:`infer_discrepancy`.
    proposal : str or None
        Scenario 3's φ proposal, ``"prior"`` (the paper's) or ``"adaptive"``.
    k_hat : ndarray of shape (n_out,) or None
        Scenario 3: Pareto shape of each output's raw importance weights (Vehtari et al.;
        above 0.7 the mixture is unreliable).
    backend : {"numpy", "numba"}
        The GP backend :meth:`predict` uses (:func:`mdcore.compiled.resolve_backend`).
    """

    scenario: int
    simulate: Callable
    theta: np.ndarray
    Y: np.ndarray
    X: np.ndarray
    z: np.ndarray
    log_params: np.ndarray
    log_weights: np.ndarray
    log_params_hat: np.ndarray | None
    nlml_hat: np.ndarray | None
    prune: float
    phi_prior: GaussianPrior | None
    seconds: float
    proposal: str | None = None
    k_hat: np.ndarray | None = None
    backend: str = "numpy"

    @property
    def n_out(self) -> int:
        return self.z.shape[1]

    @property
    def weights(self) -> np.ndarray:
        """Normalised weights, shape (n_out, S, K); each output's weights sum to 1."""
        return np.exp(self.log_weights)

    @property
    def ess(self) -> np.ndarray:
        """Effective sample size ``1 / Σ w²`` per output, shape (n_out,)."""
        return np.exp(-logsumexp(2.0 * self.log_weights.reshape(self.n_out, -1), axis=1))

    def _kept(self, prune: float):
        """Per output: flat indices of the kept components and the skipped mass."""
        out = []
        for o in range(self.n_out):
            lw = self.log_weights[o].ravel()
            cut = lw.max() + np.log(prune) if prune > 0 else -np.inf
            keep = np.isfinite(lw) & (lw >= cut)
            skipped = float(np.exp(logsumexp(lw[~keep]))) if np.any(~keep) else 0.0
            out.append((np.flatnonzero(keep), skipped))
        return out

    @property
    def skipped_mass(self) -> np.ndarray:
        """Normalised weight mass that :meth:`predict` skips at :attr:`prune`, (n_out,)."""
        return np.array([s for _, s in self._kept(self.prune)])

    @property
    def n_components(self) -> np.ndarray:
        """Components :meth:`predict` evaluates per output at :attr:`prune`, (n_out,)."""
        return np.array([idx.size for idx, _ in self._kept(self.prune)])

    def predict(self, X_star, *, prune: float | None = None,
                progress: Callable[[float], None] | None = None) -> DiscrepancyPrediction:
        """Bias-corrected prediction and discrepancy at ``X_star`` (SPEC §6, Eq. 13/15).

        Parameters
        ----------
        X_star : ndarray of shape (N*, d_x)
            Prediction inputs, in the case's input units.
        prune : float, optional
            Override :attr:`prune`; ``0`` evaluates every component. The kept weights are
            renormalised; the skipped mass is at most ``prune × S × K``.
        progress : callable, optional
            Called with the fraction done in [0, 1] after each block. If it raises, the
            prediction stops and the exception propagates (use this to cancel).

        Returns
        -------
        DiscrepancyPrediction
            Each field of shape (N*, n_out).
        """
        X_star = as_float_array(X_star, "X_star", ndim=2)
        if X_star.shape[1] != self.X.shape[1]:
            raise ValueError(f"X_star must have shape (N*, d_x) with d_x = {self.X.shape[1]} "
                             f"like the training X; received {X_star.shape}.")
        prune = self.prune if prune is None else _prune(prune)
        Ys = _simulate(self.simulate, X_star, self.theta, self.n_out)     # (S, N*, n_out)
        M, K, P = X_star.shape[0], self.log_params.shape[2], self.log_params.shape[3]
        N, d_y = self.X.shape[0], self.n_out
        fused = self.backend == "numba"
        if fused:       # pairs per compiled call: progress and cancel about 20 times an output
            block = max(2048, -(-self.log_weights[0].size // 20))
        else:           # pairs per NumPy chunk, in BLOCK_BYTES of temporaries
            block = max(1, int(BLOCK_BYTES // (8 * (M * (d_y + 6) + N * (d_y + 2) + P))))
        kept = self._kept(prune)
        total = sum(max(1, -(-idx.size // block)) for idx, _ in kept)
        done = 0
        out = np.empty((4, M, self.n_out))
        for o, (idx, _) in enumerate(kept):
            lw = self.log_weights[o].ravel()[idx]
            w = np.exp(lw - logsumexp(lw))                  # renormalised over kept
            z_o = self.z[:, o]
            j_all, k_all = np.divmod(idx, K)

            def moments(sel, o=o, z_o=z_o, j_all=j_all, k_all=k_all):
                j = j_all[sel]
                p = gp.predict(self.log_params[o][j, k_all[sel]], self.Y[j], self.X, z_o, Ys[j],
                               X_star, backend=self.backend)
                return p.mean, p.var, p.noise_var[:, None], Ys[j][..., o]

            # Reference: the heaviest component; sums are taken about it (no cancellation).
            ref = int(np.argmax(w))
            m0, _, _, y0 = moments(slice(ref, ref + 1))
            cz, cd = m0[0], m0[0] - y0[0]
            acc = np.zeros((4, M))                          # Σw dz, Σw dδ, Σw(..z²), Σw(..δ²)
            for sel in _blocks(idx.size, block):
                wb = w[sel]
                if fused:       # the same sums, per pair in registers (mdcore.compiled)
                    sums = compiled.mixture_sums(
                        self.log_params[o][j_all[sel], k_all[sel]], self.Y, j_all[sel], self.X,
                        z_o, Ys, Ys[..., o], wb, X_star, cz, cd)
                    bad = sums.dropped
                    acc += sums.acc
                else:
                    mean, var, sn2, ystar = moments(sel)
                    bad = ~np.all(np.isfinite(mean) & np.isfinite(var), axis=1)
                    if np.any(bad):
                        wb = np.where(bad, 0.0, wb)
                        mean = np.where(bad[:, None], 0.0, mean)
                        var = np.where(bad[:, None], 0.0, var)
                    dz = mean - cz
                    dd = mean - ystar - cd
                    acc[0] += wb @ dz
                    acc[1] += wb @ dd
                    acc[2] += wb @ (var + sn2 + dz * dz)    # Eq. 13/15: total variance of z*
                    acc[3] += wb @ (var + dd * dd)          # latent variance goes to δ
                if np.any(bad):
                    warnings.warn(f"{int(bad.sum())} component(s) of output {o} could not be "
                                  "factorised and were dropped from the mixture (weight "
                                  f"{float(w[sel][bad].sum()):.3g}).",
                                  NumericalWarning, stacklevel=2)
                done += 1
                if progress is not None:
                    progress(min(done / total, 1.0))
            out[0, :, o] = cz + acc[0]
            out[1, :, o] = np.maximum(acc[2] - acc[0] ** 2, 0.0)
            out[2, :, o] = cd + acc[1]
            out[3, :, o] = np.maximum(acc[3] - acc[1] ** 2, 0.0)
        return DiscrepancyPrediction(out[0], out[1], out[2], out[3])


def _prune(value) -> float:
    try:
        p = float(value)
    except (TypeError, ValueError):
        p = np.nan
    if not np.isfinite(p) or p < 0 or p >= 1:
        raise ValueError(f"prune must be in [0, 1) (a fraction of the largest weight; 0 keeps "
                         f"every component); received {value!r}.")
    return p


def _prior_proposal(Y, X, z, prior, n_phi, rng, progress, backend):
    """Scenario 3 as in the paper: φ^(j,k) ~ p(φ), shared by the outputs (common random
    numbers); ``log w_jk = −NLML`` (Eq. 15), normalised jointly over (j, k) per output."""
    n_out, S, P = z.shape[1], Y.shape[0], prior.size
    phi = prior.sample(S * n_phi, seed=rng).reshape(S, n_phi, P)
    log_params = np.broadcast_to(phi, (n_out, S, n_phi, P))
    log_weights = np.empty((n_out, S, n_phi))
    rows = max(1, 50_000 // n_phi)                      # ~50k pairs per progress step
    steps = list(_blocks(S, rows))
    for o in range(n_out):
        for i, sl in enumerate(steps):
            # Eq. 15: log w_jk = log p(z | y^(j), X, φ^(j,k)) = −NLML
            log_weights[o, sl] = -gp.neg_log_marginal_likelihood(phi[sl], Y[sl, None], X,
                                                                 z[:, o], backend=backend)
            if progress is not None:
                progress((o * len(steps) + i + 1) / (n_out * len(steps)))
        _normalise(log_weights[o], o)
    return log_params, log_weights


def _adaptive_proposal(Y, X, z, prior, n_phi, rng, progress, backend):
    """Scenario 3 with adaptive importance sampling of φ per output
    (:func:`mdcore.importance.adaptive_importance_sampling`): the same budget of N_φ draws
    per θ, drawn in stages from the prior and then from Student-t fits to the weighted
    draws, with deterministic-mixture weights normalised jointly over (j, k)."""
    n_out, S = z.shape[1], Y.shape[0]
    log_params = np.empty((n_out, S, n_phi, prior.size))
    log_weights = np.empty((n_out, S, n_phi))
    for o in range(n_out):
        def loglik(phi, o=o):
            return -gp.neg_log_marginal_likelihood(phi, Y[:, None], X, z[:, o],   # Eq. 15
                                                   backend=backend)

        def report(f, o=o):
            if progress is not None:
                progress((o + f) / n_out)

        try:
            out = adaptive_importance_sampling(loglik, prior, S, n_phi, seed=rng,
                                               progress=report)
        except ValueError:
            raise ValueError(_all_zero_message(o)) from None
        log_params[o], log_weights[o] = out.samples, out.log_weights
    return log_params, log_weights


def _all_zero_message(o: int) -> str:
    return (f"every scenario-3 component of output {o} has zero likelihood (no covariance "
            "matrix could be factorised); check phi_prior, whose samples give "
            "non-positive-definite covariances.")


def _normalise(log_weights: np.ndarray, o: int) -> None:
    """Normalise one output's log weights in place (logsumexp over all pairs = 0)."""
    norm = logsumexp(log_weights)
    if not np.isfinite(norm):
        raise ValueError(_all_zero_message(o))
    log_weights -= norm


def infer_discrepancy(simulate: Callable, theta_samples, X, z, *, scenario, theta_map=None,
          n_phi: int = 500, phi_prior: GaussianPrior | None = None, seed=None,
          log_params_hat=None, fit_options: dict | None = None, prune: float = PRUNE,
          proposal: str = "prior", backend: str | None = None,
          progress: Callable[[float], None] | None = None) -> DiscrepancyModel:
    """Infer the model discrepancy by one of the three scenarios of SPEC §6.

    Parameters
    ----------
    simulate : callable
        ``simulate(X, theta) -> (n_theta, N, n_out)`` like :meth:`mdcore.cases.Case.simulate`.
    theta_samples : ndarray of shape (N_s, p)
        Calibration samples, e.g. ``HistoryMatchResult.samples``. Unused by scenario 1.
    X : ndarray of shape (N, d_x)
        Training inputs.
    z : ndarray of shape (N, n_out) or (N,)
        Observations.
    scenario : {1, 2, 3}
    theta_map : ndarray of shape (p,), optional
        Required by scenarios 1 and 2 (φ̂ is fitted at θ_MAP) unless ``log_params_hat`` is
        given to scenario 2.
    n_phi : int, default=500
        Hyperparameter samples per θ sample (scenario 3).
    phi_prior : GaussianPrior, optional
        Prior of the log hyperparameters (P = 2 + n_out + d_x), shared by the outputs.
        Scenario 3 samples from it. Scenarios 1–2 use it as the hyperprior of the φ̂ fit
        (type-II MAP): with N = 13 points, plain empirical Bayes drives σ_n to its lower
        bound and the z band misses the noisy test data. Pass
        ``fit_options={"log_prior": None}`` for the plain empirical Bayes of Eq. 8.
        Default: no hyperprior for scenarios 1–2, :func:`default_phi_prior` of the first
        output's data for scenario 3 (a weak prior).
    seed : int or numpy.random.Generator, optional
        Seeds the empirical-Bayes swarm and the prior draws.
    log_params_hat : ndarray of shape (n_out, P), optional
        φ̂ from an earlier scenario-1 fit, to skip refitting (scenarios 1–2).
    fit_options : dict, optional
        Extra keywords for :func:`mdcore.hyperfit.fit_hyperparameters` (default QPSO + polish).
    prune : float, default=1e-12
        See :attr:`DiscrepancyModel.prune`.
    proposal : {"prior", "adaptive"}, default="prior"
        Scenario 3's φ proposal. ``"prior"`` is the paper's: N_φ prior draws per θ, weighted
        by the marginal likelihood. ``"adaptive"`` spends the same N_φ draws per θ in stages
        (:func:`mdcore.importance.adaptive_importance_sampling`): a quarter from the prior,
        then from Student-t fits to the weighted draws, with deterministic-mixture weights,
        Pareto-smoothed (PSIS); it keeps far more effective samples where the likelihood
        is narrow compared with the prior (beam-2d).
    backend : {"auto", "numpy", "numba"}, optional
        GP kernels of the scenario-3 weights and of :meth:`DiscrepancyModel.predict`
        (:func:`mdcore.compiled.resolve_backend`; default ``MDCORE_BACKEND``, else numba
        when installed). Both give the same numbers to ~1e-12; ``"numpy"`` is the reference.
        The φ̂ fit of scenarios 1–2 stays on NumPy: the swarm's choices amplify rounding
        differences to the optimiser's tolerance (~4e-8 in the metrics).
    progress : callable, optional
        Called with the fraction done in [0, 1]; raising from it cancels.

    Returns
    -------
    DiscrepancyModel

    Warns
    -----
    LowESSWarning
        Scenario 3, when an output's ESS is below :data:`LOW_ESS`.
    """
    start = time.perf_counter()
    scenario = _scenario(scenario)
    X = as_float_array(X, "X", ndim=2)
    z = as_outputs(z, X.shape[0])
    N, d_x = X.shape
    n_out = z.shape[1]
    P = 2 + n_out + d_x
    rng = np.random.default_rng(seed)
    prune = _prune(prune)
    choose(proposal, "proposal", PROPOSALS)
    backend = compiled.resolve_backend(backend)
    if phi_prior is not None and (not isinstance(phi_prior, GaussianPrior) or phi_prior.size != P):
        raise ValueError(f"phi_prior must be a GaussianPrior over P = 2 + n_out + d_x = {P} log "
                         f"hyperparameters ([log σ_f, log ℓ_y×{n_out}, log ℓ_x×{d_x}, log σ_n]); "
                         f"received {phi_prior!r}.")

    if scenario in (1, 2) and log_params_hat is None and theta_map is None:
        raise ValueError(f"scenario {scenario} needs theta_map (φ̂ is fitted by empirical Bayes "
                         "at θ_MAP); pass HistoryMatchResult.theta_map, or log_params_hat.")
    if scenario == 1 or (theta_map is not None and scenario == 2):
        theta_map = as_float_array(theta_map, "theta_map", ndim=1)
    if scenario == 1:
        theta = theta_map[None, :]
    else:
        theta = as_float_array(theta_samples, "theta_samples", ndim=2)
        if theta_map is not None and theta.shape[1] != theta_map.size:
            raise ValueError(f"theta_samples must have shape (N_s, p) with p = {theta_map.size} "
                             f"like theta_map; received {theta.shape}.")
    Y = _simulate(simulate, X, theta, n_out)
    S = theta.shape[0]

    log_params_hat_arr, nlml_hat = None, None
    if scenario in (1, 2):
        # y(X, θ_MAP): scenario 1's only sample; without θ_MAP (scenario 2 given φ̂) the
        # first θ sample stands in for the nlml_hat report.
        Y_map = Y[0] if scenario == 1 or theta_map is None else \
            _simulate(simulate, X, theta_map[None], n_out)[0]
        if log_params_hat is not None:
            log_params_hat_arr = np.atleast_2d(as_float_array(log_params_hat, "log_params_hat"))
            if log_params_hat_arr.shape != (n_out, P):
                raise ValueError(f"log_params_hat must have shape (n_out, P) = ({n_out}, {P}); "
                                 f"received {log_params_hat_arr.shape}.")
        else:
            fits = []
            for o in range(n_out):
                # Eq. 8: empirical Bayes on {y(X, θ_MAP), X, z}
                options = {"log_prior": phi_prior, **(fit_options or {})}
                fits.append(fit_hyperparameters(Y_map, X, z[:, o], seed=rng, **options))
                if progress is not None:
                    progress((o + 1) / n_out)
            log_params_hat_arr = np.array([f.log_params for f in fits])
        nlml_hat = np.array([float(gp.neg_log_marginal_likelihood(log_params_hat_arr[o], Y_map,
                                                                  X, z[:, o], backend=backend))
                             for o in range(n_out)])
        log_params = np.broadcast_to(log_params_hat_arr[:, None, None, :], (n_out, S, 1, P))
        log_weights = np.full((n_out, S, 1), -np.log(S))
        prior = None
    else:
        n_phi = as_int(n_phi, "n_phi", 1)
        prior = default_phi_prior(Y[0], X, z[:, 0]) if phi_prior is None else phi_prior
        if proposal == "prior":
            log_params, log_weights = _prior_proposal(Y, X, z, prior, n_phi, rng, progress,
                                                      backend)
        else:
            log_params, log_weights = _adaptive_proposal(Y, X, z, prior, n_phi, rng, progress,
                                                         backend)
        k_hat = np.array([psis(log_weights[o].ravel()).k_hat for o in range(n_out)])
        if proposal == "adaptive":      # Pareto-smoothed weights (Vehtari et al. 2024)
            log_weights = np.stack([psis(log_weights[o].ravel()).log_weights.reshape(S, -1)
                                    for o in range(n_out)])
    model = DiscrepancyModel(scenario, simulate, theta, Y, X, z, log_params, log_weights,
                             log_params_hat_arr, nlml_hat, prune, prior,
                             time.perf_counter() - start, proposal if scenario == 3 else None,
                             k_hat if scenario == 3 else None, backend)
    if scenario == 3:
        switch = " or use proposal='adaptive'" if proposal == "prior" else ""
        for o, (e, k) in enumerate(zip(model.ess, k_hat)):
            if e < LOW_ESS or k > K_HAT_THRESHOLD:
                warnings.warn(
                    f"scenario 3, output {o}: the importance weights are unreliable (ESS "
                    f"{e:.1f} of {S * n_phi} pairs, Pareto k̂ = {k:.2f}; reliable needs ESS ≥ "
                    f"{LOW_ESS:g} and k̂ ≤ {K_HAT_THRESHOLD}). Increase n_phi or N_s{switch}.",
                    LowESSWarning, stacklevel=2)
    return model
