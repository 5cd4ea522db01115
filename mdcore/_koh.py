"""Kennedy–O'Hagan baseline (docs/method.md §7): θ and δ(x) inferred jointly, each output
``z | θ, φ ~ N(m_η(X, θ), Σ_η(X, X; θ) + K_δ(X, X; φ) + σ_n² I)``, independent given θ, with
the emulator's moments ``m_η``, ``Σ_η`` and ``φ = [log σ_f, log ℓ_x…, log σ_n]`` of δ's GP.
"""

from __future__ import annotations

import dataclasses
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.linalg
from scipy.special import logsumexp

from . import _compiled as compiled
from ._discrepancy import DiscrepancyPrediction, _blocks, simulated
from ._emulator import Emulator, EmulatorAt, ThetaTerms
from ._exceptions import ConvergenceWarning, NumericalWarning
from ._gp import LOG_2PI
from ._hyperfit import best_lbfgs, default_bounds, lbfgs_advice, lbfgs_converged
from ._kernels import kernel, matern32_and_dlog_ell
from ._linalg import JITTER_LADDER, JitterLog, cholesky, solve_lower_inplace
from ._mcmc import MAX_CHAIN, Chain, adaptive_metropolis, chain_length, chain_setup
from ._priors import GaussianPrior, ThetaPrior
from ._validation import as_float_array, as_int, as_outputs, check_bounds, check_type

#: The paper's chain (150,000 steps, 50,000 burn-in), a short one for the app, the prior θ
#: draws of the empirical-Bayes objective and the θ samples of a prediction.
N_ITER, BURN_IN = 150_000, 50_000
FAST = {"n_iter": 20_000, "burn_in": 5_000}
N_THETA_EB = 200
N_PREDICT = 1000


class SimulatorAt:
    """An exact ``simulate(X, theta)`` at fixed ``X`` (N, d_x), with
    :class:`mdcore._emulator.EmulatorAt`'s protocol and zero covariance."""

    def __init__(self, simulate: Callable, X: np.ndarray, n_out: int):
        self.simulate, self.X, self.n_out = simulate, X, n_out

    def theta_terms(self, theta, *, check: bool = True) -> ThetaTerms:
        theta = np.atleast_2d(as_float_array(theta, "theta")) if check else theta
        return ThetaTerms(theta, ())

    def moments_at(self, terms: ThetaTerms, *, with_cov: bool = True):
        y = simulated(self.simulate, self.X, terms.unit, self.n_out, finite=False)
        mean = np.ascontiguousarray(np.moveaxis(y, 2, 1))
        cov = np.zeros(mean.shape + (self.X.shape[0],)) if with_cov else None
        return mean, cov

    def cross_cov_at(self, terms: ThetaTerms, other: SimulatorAt):
        M, N_o = terms.unit.shape[0], other.X.shape[0]
        return (np.zeros((M, self.n_out, N_o, self.X.shape[0])),
                np.zeros((M, self.n_out, N_o)))


def _at(model, X: np.ndarray, n_out: int):
    return model.at(X) if isinstance(model, Emulator) else SimulatorAt(model, X, n_out)


def _k_delta(log_phi: np.ndarray, Xa: np.ndarray, Xb: np.ndarray) -> np.ndarray:
    """``K_δ = σ_f² m32(r_x)`` per output, (n_out, Na, Nb): the kernel with no y inputs."""
    n_out = log_phi.shape[0]
    return kernel(log_phi, np.empty((n_out, len(Xa), 0)), Xa, np.empty((n_out, len(Xb), 0)), Xb)


def noise_cov(log_phi: np.ndarray, X: np.ndarray) -> np.ndarray:
    """``K_δ(X, X) + σ_n² I`` per output, (n_out, N, N): fixed once φ is."""
    return _k_delta(log_phi, X, X) + np.exp(2 * log_phi[:, -1])[:, None, None] * np.eye(len(X))


def _chol(C: np.ndarray, log: JitterLog) -> np.ndarray:
    """Batched lower Cholesky with the jitter ladder (NaN where it fails)."""
    return cholesky(C.reshape((-1,) + C.shape[-2:]), log)[0].reshape(C.shape)


def _solve_lower(L: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``L⁻¹ B`` for (b, N, N) factors and (b, N, k) right-hand sides, B overwritten."""
    if L.shape[0] > 8:
        return solve_lower_inplace(L, B)
    for i in range(L.shape[0]):
        B[i] = scipy.linalg.solve_triangular(L[i], B[i], lower=True, check_finite=False)
    return B


def gaussian_log_likelihood(mean, cov, B, zT, log) -> np.ndarray:
    """``Σ_o log N(z_o | mean_o, cov_o + B_o)`` for a batch: (M, n_out, N) … -> (M,)."""
    L = _chol(cov + B, log)                                    # (M, n_out, N, N)
    r = (zT - mean)[..., None]
    a = _solve_lower(L.reshape((-1,) + L.shape[-2:]), r.reshape((-1,) + r.shape[-2:]))
    a = a.reshape(mean.shape)
    logdet = np.sum(np.log(np.diagonal(L, axis1=-2, axis2=-1)), axis=(-2, -1))
    ll = -0.5 * np.sum(a * a, axis=(-2, -1)) - logdet - 0.5 * mean[0].size * LOG_2PI
    return np.where(np.isfinite(ll), ll, -np.inf)


def _theta_prior(theta_prior, bounds: np.ndarray) -> ThetaPrior:
    """The θ prior as a :class:`~mdcore.ThetaPrior` of size p."""
    if not isinstance(theta_prior, ThetaPrior):
        try:
            mean, var = theta_prior
        except (TypeError, ValueError):
            raise ValueError("theta_prior must be a ThetaPrior or a (mean, var) pair of "
                             f"length-p arrays; received {theta_prior!r}.") from None
        theta_prior = ThetaPrior(mean, var)
    p = bounds.shape[0]
    if theta_prior.size != p:
        raise ValueError(f"theta_prior mean and var must each have p = {p} entries, one per "
                         f"row of bounds; received {theta_prior.size}.")
    return theta_prior


def _log_phi(log_phi, n_out: int, d_x: int) -> np.ndarray:
    lp = as_float_array(log_phi, "log_phi")
    if lp.shape not in {(2 + d_x,), (n_out, 2 + d_x)}:
        raise ValueError(f"log_phi must have shape (2 + d_x,) = ({2 + d_x},) or (n_out, 2 + d_x) "
                         f"= ({n_out}, {2 + d_x}) ([log σ_f, log ℓ_x…, log σ_n]); received "
                         f"{np.shape(log_phi)}.")
    return np.array(np.broadcast_to(lp, (n_out, 2 + d_x)))


class _EvidenceObjective:
    """``−log (1/M) Σ_m p(z | θ_m, φ) − log p(φ)`` and its gradient in φ: with
    ``C = Σ_η + K_δ + σ_n² I``, ``α = C⁻¹ r`` and weights ``w_m ∝ p(z | θ_m, φ)``, the log
    evidence's derivative is ``½ Σ_m w_m tr((α αᵀ − C⁻¹) ∂K_δ)``."""

    def __init__(self, mean, cov, X, zT, n_out, phi_prior, log):
        self.cov, self.r = cov, zT - mean                          # (M, n_out, N[, N])
        self.X, self.n_out, self.prior, self.log = X, n_out, phi_prior, log

    def _terms(self, flat):
        lp = flat.reshape(self.n_out, -1)
        N = self.X.shape[0]
        ell = np.exp(lp[:, 1:-1])
        m32, dm32 = zip(*(matern32_and_dlog_ell(self.X, e) for e in ell))
        sf2, sn2 = np.exp(2 * lp[:, 0]), np.exp(2 * lp[:, -1])
        Kd = sf2[:, None, None] * np.stack(m32)                          # (n_out, N, N)
        L = _chol(self.cov + Kd + sn2[:, None, None] * np.eye(N), self.log)
        M = L.shape[0]
        flatL = L.reshape((-1, N, N))
        a = _solve_lower(flatL, self.r.reshape((-1, N, 1)).copy())          # L⁻¹ r
        ll = (-0.5 * np.sum(a[..., 0] ** 2, axis=-1).reshape(M, self.n_out)
              - np.sum(np.log(np.diagonal(L, axis1=-2, axis2=-1)), axis=-1)
              - 0.5 * N * LOG_2PI).sum(axis=1)
        return (lp, ell, np.stack(dm32), sf2, sn2, Kd, flatL, a,
                np.where(np.isfinite(ll), ll, -np.inf))

    def log_evidence(self, flat) -> float:
        ll = self._terms(flat)[-1]
        return float(logsumexp(ll) - np.log(ll.size))

    def __call__(self, flat):
        lp, ell, dm32, sf2, sn2, Kd, flatL, a, ll = self._terms(flat)
        f = -(logsumexp(ll) - np.log(ll.size))
        if not np.isfinite(f):
            return 1e300, np.zeros_like(flat)
        M, N = ll.size, self.X.shape[0]
        w = np.exp(ll - logsumexp(ll))                                  # (M,)
        Linv = _solve_lower(flatL, np.broadcast_to(np.eye(N), flatL.shape).copy())
        Cinv = np.swapaxes(Linv, -1, -2) @ Linv                         # C⁻¹ from the factor
        alpha = np.swapaxes(Linv, -1, -2) @ a                           # C⁻¹ r
        Wm = (alpha @ np.swapaxes(alpha, -1, -2) - Cinv).reshape(M, self.n_out, N, N)
        Wbar = np.einsum("m,moij->oij", w, Wm)                          # weighted α αᵀ − C⁻¹
        g = np.empty_like(lp)
        g[:, 0] = np.einsum("oij,oij->o", Wbar, 2 * Kd)
        g[:, -1] = 2 * sn2 * np.einsum("oii->o", Wbar)
        for d in range(ell.shape[1]):                     # ∂K_δ/∂log ℓ_d = σ_f² ∂m32/∂log ℓ_d
            g[:, 1 + d] = np.einsum("oij,oij->o", Wbar, sf2[:, None, None] * dm32[:, d])
        grad = -0.5 * g
        if self.prior is not None:
            f -= float(np.sum(self.prior.logpdf(lp)))
            grad -= self.prior.grad(lp)
        return float(f), grad.ravel()


def _fit_phi(mean, cov, X, z, phi_prior, n_starts, rng, progress=None):
    """φ̂ (n_out, 2 + d_x) maximising ``log (1/M) Σ_m p(z | θ_m, φ)`` (``phi_prior``: MAP) by
    ``n_starts`` L-BFGS-B runs, and that log evidence, from the simulator side's moments at
    M prior draws, fixed during the search: ``mean`` (M, n_out, N), ``cov`` (M, n_out, N,
    N). ``progress(f)`` after every L-BFGS-B iteration (it may raise to stop the fit)."""
    n_out = z.shape[1]
    resid = z.T - mean.mean(axis=0)                                # (n_out, N)
    boxes = np.stack([default_bounds(np.empty((len(X), 0)), X, r) for r in resid])
    lo, hi = boxes[..., 0].ravel(), boxes[..., 1].ravel()
    log = JitterLog()
    objective = _EvidenceObjective(mean, cov, X, z.T, n_out, phi_prior, log)
    starts = lo + (hi - lo) * rng.uniform(size=(n_starts, lo.size))
    starts[0] = np.clip(np.tile(phi_prior.mean, n_out), lo, hi) if phi_prior is not None \
        else 0.5 * (lo + hi)
    best, _ = best_lbfgs(objective, starts, lo, hi, progress=None if progress is None
                         else (lambda k: progress(k / n_starts)))
    log.warn("KOH empirical Bayes")
    if not lbfgs_converged(best, lo, hi):
        warnings.warn(f"KOH empirical Bayes: the best of {n_starts} L-BFGS-B runs for φ̂ did "
                      f"not converge ({best.message}; {lbfgs_advice(best)}); give "
                      "phi_prior, or log_phi directly.", ConvergenceWarning, stacklevel=3)
    return best.x.reshape(n_out, -1), objective.log_evidence(best.x)


@dataclass(frozen=True, eq=False)
class KOHModel:
    """A Kennedy–O'Hagan posterior (``scenario`` is ``"koh"``); :meth:`predict` gives z*, δ*.

    Attributes
    ----------
    log_phi : ndarray of shape (n_out, 2 + d_x)
        ``[log σ_f, log ℓ_x…, log σ_n]`` per output; ``log_evidence`` the prior-averaged
        log marginal likelihood there (None when ``log_phi`` was given).
    chain : Chain
        The adaptive-Metropolis output in parameter units.
    n_predict : int
        θ samples (evenly spaced over the kept chain) used by :meth:`predict`.
    """

    scenario: str
    X: np.ndarray
    z: np.ndarray
    bounds: np.ndarray
    theta_prior: ThetaPrior
    log_phi: np.ndarray
    log_evidence: float | None
    chain: Chain
    n_predict: int
    seconds_phi: float
    seconds: float
    _model: Emulator | Callable = dataclasses.field(repr=False)
    _at: EmulatorAt | SimulatorAt = dataclasses.field(repr=False)

    @property
    def n_out(self) -> int:
        return self.z.shape[1]

    @property
    def theta(self) -> np.ndarray:
        """Kept θ samples, (n_kept, p)."""
        return self.chain.samples

    @property
    def acceptance_rate(self) -> float:
        return self.chain.acceptance_rate

    @property
    def iat(self) -> np.ndarray:
        return self.chain.iat

    @property
    def ess(self) -> np.ndarray:
        return self.chain.ess

    def predict(self, X_star, *, n_samples: int | None = None,
                progress: Callable[[float], None] | None = None) -> DiscrepancyPrediction:
        """Bias-corrected prediction and discrepancy at ``X_star`` (N*, d_x) from
        ``n_samples`` θ over the kept chain (default :attr:`n_predict`).

        Per θ, with ``r = z − m_η(X, θ)``, ``C = Σ_η + K_δ + σ_n² I`` and ``G = Σ_η(X*, X; θ)
        + K_δ(X*, X)``: δ* has mean ``K_δ(X*, X) C⁻¹ r`` and variance ``σ_f² − diag(K_δ(X*,
        X) C⁻¹ K_δ(X, X*))``; z* has mean ``m_η(X*) + G C⁻¹ r`` and variance ``V_η(X*) + σ_f²
        + σ_n² − diag(G C⁻¹ Gᵀ)``.
        """
        X_star = as_float_array(X_star, "X_star", ndim=2)
        if X_star.shape[1] != self.X.shape[1]:
            raise ValueError(f"X_star must have shape (N*, d_x) with d_x = {self.X.shape[1]} "
                             f"like the training X; received {X_star.shape}.")
        n = self.n_predict if n_samples is None else as_int(n_samples, "n_samples", 1)
        kept = self.theta.shape[0]
        idx = np.unique(np.linspace(0, kept - 1, min(n, kept)).round().astype(int))
        theta = self.theta[idx]
        at, at_s = self._at, _at(self._model, X_star, self.n_out)
        lp = self.log_phi
        N, M = self.X.shape[0], X_star.shape[0]
        sf2, sn2 = np.exp(2 * lp[:, 0]), np.exp(2 * lp[:, -1])
        B = noise_cov(lp, self.X)
        Kd_s = _k_delta(lp, X_star, self.X)                              # (n_out, M, N)
        log = JitterLog()
        parts = np.empty((4, idx.size, self.n_out, M))
        block = max(1, int(16 * 2**20 // (8 * self.n_out * (3 * M * N + N * N + 4 * M))))
        for sl in _blocks(idx.size, block):
            th = theta[sl]
            terms = at.theta_terms(th, check=False)               # shared by X and X*
            mean, cov = at.moments_at(terms)
            mean_s, _ = at_s.moments_at(terms, with_cov=False)
            cross, var_s = at.cross_cov_at(terms, at_s)
            L = _chol(cov + B, log)                                       # (b, n_out, N, N)
            flat = L.reshape((-1, N, N))
            a = _solve_lower(flat, (self.z.T - mean).reshape((-1, N, 1)))
            G = _solve_lower(flat, np.swapaxes(cross + Kd_s, -1, -2).reshape(
                (-1, N, M)).copy())
            D = _solve_lower(flat, np.broadcast_to(
                np.swapaxes(Kd_s, -1, -2), (th.shape[0],) + Kd_s.shape[:1] + (N, M)
            ).reshape((-1, N, M)).copy())
            shape = (th.shape[0], self.n_out, M)
            parts[0, sl] = mean_s + np.einsum("bnm,bn->bm", G, a[..., 0]).reshape(shape)
            parts[1, sl] = np.maximum(var_s + (sf2 + sn2)[:, None]
                                      - np.sum(G * G, axis=1).reshape(shape), 0.0)
            parts[2, sl] = np.einsum("bnm,bn->bm", D, a[..., 0]).reshape(shape)
            parts[3, sl] = np.maximum(sf2[:, None] - np.sum(D * D, axis=1).reshape(shape), 0.0)
            if progress is not None:
                progress(sl.stop / idx.size)
        log.warn("KOH prediction")
        bad = ~np.all(np.isfinite(parts), axis=(0, 2, 3))
        if np.all(bad):
            raise ValueError("every KOH prediction failed to factorise; check log_phi.")
        if np.any(bad):
            warnings.warn(f"{int(bad.sum())} of {idx.size} θ samples could not be factorised "
                          "and were left out of the prediction.", NumericalWarning, stacklevel=2)
            parts = parts[:, ~bad]
        # Equal weights: E = mean of the means, V = mean of the variances + variance of the means.
        z_mean, d_mean = parts[0].mean(axis=0), parts[2].mean(axis=0)
        z_var = parts[1].mean(axis=0) + parts[0].var(axis=0)
        d_var = parts[3].mean(axis=0) + parts[2].var(axis=0)
        return DiscrepancyPrediction(z_mean.T, z_var.T, d_mean.T, d_var.T)


@dataclass(frozen=True, eq=False)
class KOHOptions:
    """Settings of :func:`infer_koh`.

    Parameters
    ----------
    n_iter, burn_in : int
        Chain length and burn-in (the paper's 150,000 and 50,000; :data:`FAST` for the app).
    n_theta_eb, n_predict : int
        Prior θ draws of the empirical-Bayes objective; θ samples of the prediction.
    log_phi : ndarray of shape (2 + d_x,) or (n_out, 2 + d_x), optional
        Fixed discrepancy hyperparameters instead of the empirical-Bayes φ̂.
    phi_prior : GaussianPrior of size 2 + d_x, optional
        Hyperprior of φ̂ (MAP); None is plain empirical Bayes.
    backend : {"auto", "numpy", "numba"} or None, default="auto"
        The chain with an emulator: :func:`mdcore._compiled.koh_chain` or the Python loop
        of :func:`mdcore._mcmc.adaptive_metropolis`; None reads ``MDCORE_BACKEND``.
    """

    n_iter: int = N_ITER
    burn_in: int = BURN_IN
    n_theta_eb: int = N_THETA_EB
    n_predict: int = N_PREDICT
    log_phi: np.ndarray | None = None
    phi_prior: GaussianPrior | None = None
    backend: str = "auto"

    def __post_init__(self):                   # the chain's length is checked before φ̂
        n_iter, burn_in = chain_length(self.n_iter, self.burn_in,
                                       " The paper: n_iter = 150,000 with burn_in = 50,000.")
        object.__setattr__(self, "n_iter", n_iter)
        object.__setattr__(self, "burn_in", burn_in)
        object.__setattr__(self, "n_theta_eb",
                           as_int(self.n_theta_eb, "n_theta_eb", 1, 1_000_000))
        object.__setattr__(self, "n_predict", as_int(self.n_predict, "n_predict", 1, MAX_CHAIN))
        object.__setattr__(self, "backend", compiled.resolve_backend(self.backend))


def infer_koh(model, X, z, *, theta_prior, bounds, options: KOHOptions | None = None,
              seed=None, progress: Callable[[float], None] | None = None) -> KOHModel:
    """Kennedy–O'Hagan calibration: φ̂ by empirical Bayes, then θ by adaptive Metropolis.

    Parameters
    ----------
    model : Emulator or callable
        The history-matching emulator (its mean and covariance enter the likelihood), or
        an exact ``simulate(X, theta) -> (n_theta, N, n_out)``.
    X : ndarray of shape (N, d_x)
    z : ndarray of shape (N, n_out) or (N,)
    theta_prior : ThetaPrior or (mean, var)
        Gaussian prior of θ, truncated to ``bounds`` (p, 2).
    options : KOHOptions, optional
        Default: the paper's chain.
    seed : int or Generator, optional
    progress : callable, optional
        Fraction done (0–1); raising from it cancels.
    """
    start = time.perf_counter()
    options = check_type(KOHOptions() if options is None else options, KOHOptions, "options",
                         "a KOHOptions")
    bounds = check_bounds(bounds)
    p = bounds.shape[0]
    prior = _theta_prior(theta_prior, bounds)
    X = as_float_array(X, "X", ndim=2)
    z = as_outputs(z, X.shape[0])
    n_out, d_x = z.shape[1], X.shape[1]
    if isinstance(model, Emulator):
        if model.theta_train.shape[1] != p or model.X_train.shape[1] != d_x \
                or model.n_out != n_out:
            raise ValueError(f"the emulator has p = {model.theta_train.shape[1]}, d_x = "
                             f"{model.X_train.shape[1]}, n_out = {model.n_out}; the data and "
                             f"bounds have p = {p}, d_x = {d_x}, n_out = {n_out}.")
    elif not callable(model):
        raise ValueError("model must be an Emulator or a callable simulate(X, theta); "
                         f"received {type(model).__name__}.")
    if options.phi_prior is not None and options.phi_prior.size != 2 + d_x:
        raise ValueError(f"phi_prior must have 2 + d_x = {2 + d_x} entries ([log σ_f, "
                         f"log ℓ_x…, log σ_n]); received {options.phi_prior.size}.")
    rng = np.random.default_rng(seed)
    at = _at(model, X, n_out)

    draws = prior.sample_in(bounds, options.n_theta_eb, seed=rng)
    mean, cov = at.moments_at(at.theta_terms(draws))     # for φ̂ and the starting point
    if options.log_phi is None:
        log_phi, log_evidence = _fit_phi(mean, cov, X, z, options.phi_prior, 4, rng,
                                         None if progress is None
                                         else (lambda f: progress(0.05 * f)))
    else:
        log_phi, log_evidence = _log_phi(options.log_phi, n_out, d_x), None
    seconds_phi = time.perf_counter() - start
    if progress is not None:
        progress(0.05)

    # Fixed during sampling: K_δ + σ_n² I, and z transposed to (n_out, N).
    B = noise_cov(log_phi, X)
    zT = np.ascontiguousarray(z.T)
    log = JitterLog()
    mu, sd = prior.mean, np.sqrt(prior.var)
    lo_u, hi_u = (bounds[:, 0] - mu) / sd, (bounds[:, 1] - mu) / sd

    def log_target(u):
        """log p(z | θ, φ̂) + log p(θ) in standardised coordinates u = (θ − μ) / sd."""
        if np.any(u < lo_u) or np.any(u > hi_u):
            return -np.inf
        theta = (mu + sd * u)[None]
        mean, cov = at.moments_at(at.theta_terms(theta, check=False))
        return float(gaussian_log_likelihood(mean, cov, B, zT, log)[0]) - 0.5 * float(u @ u)

    # Start at the most probable of the prior draws (φ̂ is fixed now).
    lp0 = gaussian_log_likelihood(mean, cov, B, zT, log) + prior.logpdf(draws)
    u0 = (draws[int(np.argmax(lp0))] - mu) / sd
    report = None if progress is None else (lambda f: progress(0.05 + 0.95 * f))
    chain_options = dict(n_iter=options.n_iter, burn_in=options.burn_in)
    if options.backend == "numba" and isinstance(at, EmulatorAt):
        arrays = at.arrays()
        koh = compiled.KOHData(arrays.prior + B, zT, mu, sd, lo_u, hi_u,
                               np.asarray(JITTER_LADDER, dtype=np.float64))
        chain = compiled.koh_chain(arrays, koh, chain_setup(log_target, u0, **chain_options),
                                   rng, report, log)
    else:
        chain = adaptive_metropolis(log_target, u0, seed=rng, progress=report,
                                    **chain_options)
    log.warn("KOH likelihood")
    chain = dataclasses.replace(chain, samples=mu + sd * chain.samples,
                                proposal_cov=chain.proposal_cov * np.outer(sd, sd))
    return KOHModel(scenario="koh", X=X, z=z, bounds=bounds, theta_prior=prior,
                    log_phi=log_phi, log_evidence=log_evidence, chain=chain,
                    n_predict=options.n_predict, seconds_phi=seconds_phi,
                    seconds=time.perf_counter() - start, _model=model, _at=at)
