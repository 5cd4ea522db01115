"""Importance sampling for scenario 3 (Eq. 15): ESS, Pareto smoothing and Student-t proposals.

The (θ, φ) weights are judged by the ESS ``1 / Σ w²`` and the Pareto shape ``k̂`` of their
right tail (Vehtari et al., "Pareto smoothed importance sampling", JMLR 2024): above 0.7 the
estimate is unreliable whatever the ESS. PSIS replaces the largest weights by the expected
order statistics of a generalised Pareto fitted to them (Zhang & Stephens 2009). The
adaptive proposal draws φ from Student-t fits to the weighted draws (AMIS, Cornuet et al.
2012).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
import scipy.optimize
from scipy.linalg import solve_triangular
from scipy.special import gammaln, logsumexp

from ._validation import as_float_array, as_int


class PSIS(NamedTuple):
    """Smoothed, normalised ``log_weights`` (S,) and the Pareto shape ``k_hat`` of the raw
    weights' right tail (``inf`` for a tail of five samples or fewer)."""

    log_weights: np.ndarray
    k_hat: float


def generalized_pareto_fit(x) -> tuple[float, float]:
    """Shape ``k`` and scale ``σ`` of a generalised Pareto fitted to exceedances ``x`` (n ≥ 5,
    positive, ascending): Zhang & Stephens' (2009) posterior mean of ``b = −k/σ`` over
    ``30 + ⌊√n⌋`` grid values, then ``k`` shrunk toward 0.5 by Vehtari et al.'s prior (a
    prior sample size of 10)."""
    x = as_float_array(x, "x", ndim=1)
    n = x.size
    if n < 5 or np.any(x <= 0) or np.any(np.diff(x) < 0):
        raise ValueError(f"x must be at least 5 positive values sorted ascending; received "
                         f"{n} values with minimum {float(x.min()):.3g}.")
    m = 30 + int(np.sqrt(n))
    # Grid of b (Zhang & Stephens 2009, Eq. 6): centred near 1/x_max, spread by the quartile.
    b = 1.0 - np.sqrt(m / (np.arange(1, m + 1) - 0.5))
    b /= 3.0 * x[int(n / 4 + 0.5) - 1]
    b += 1.0 / x[-1]
    k = np.mean(np.log1p(-b[:, None] * x), axis=1)
    profile = n * (np.log(-b / k) - k - 1.0)                   # profile log likelihood
    with np.errstate(over="ignore"):                          # exp -> inf: weight 0
        weights = 1.0 / np.sum(np.exp(profile[None, :] - profile[:, None]), axis=1)
    keep = weights >= 10 * np.finfo(float).eps
    weights, b = weights[keep], b[keep]
    b_post = float(np.sum(b * weights / weights.sum()))
    k_post = float(np.mean(np.log1p(-b_post * x)))
    sigma = -k_post / b_post
    k_post = (n * k_post + 10 * 0.5) / (n + 10)                # prior: 10 samples at k = 0.5
    return k_post, sigma


def _gp_quantiles(p: np.ndarray, k: float, sigma: float) -> np.ndarray:
    """Quantiles of the generalised Pareto distribution at probabilities ``p`` in (0, 1)."""
    if abs(k) < np.finfo(float).eps:
        return -sigma * np.log1p(-p)
    return sigma * np.expm1(-k * np.log1p(-p)) / k


def psis(log_weights) -> PSIS:
    """Pareto-smoothed importance sampling (Vehtari et al. 2024, Algorithm 1) of unnormalised
    ``log_weights`` (S,) (``-inf``: zero weight) of independent draws."""
    lw = as_float_array(log_weights, "log_weights", ndim=1, finite=False)
    if np.any(np.isnan(lw)) or np.any(lw == np.inf):
        raise ValueError("log_weights must not contain NaN or +inf; a zero weight is -inf.")
    if not np.any(np.isfinite(lw)):
        raise ValueError("every weight is zero (all log_weights are -inf); nothing to smooth.")
    S = lw.size
    x = lw - np.max(lw)
    tail = int(np.ceil(min(0.2 * S, 3.0 * np.sqrt(S))))
    # the (tail + 1)-th largest weight: a partition, not a sort (10⁶ weights on beam-2d)
    cutoff = max(np.partition(x, S - tail - 1)[S - tail - 1] if tail < S else -np.inf,
                 np.log(np.finfo(float).tiny))
    idx = np.flatnonzero(x > cutoff)
    k_hat = np.inf
    if idx.size > 4:
        by_size = idx[np.argsort(x[idx])]
        exceed = np.exp(x[by_size]) - np.exp(cutoff)
        k_hat, sigma = generalized_pareto_fit(exceed)
        if np.isfinite(k_hat) and sigma > 0:
            p = (np.arange(idx.size) + 0.5) / idx.size
            x[by_size] = np.log(_gp_quantiles(p, k_hat, sigma) + np.exp(cutoff))
            np.minimum(x, 0.0, out=x)                          # not above the largest raw
    return PSIS(x - logsumexp(x), float(k_hat))


def resample(log_weights, n: int, seed=None) -> tuple[np.ndarray, np.ndarray]:
    """Stratified resampling (Kitagawa 1996): ``n`` draws by the normalised weights of
    ``log_weights`` (M,) (``-inf``: zero weight), one uniform in each ``[i / n, (i + 1) / n)``.
    Returns the distinct indices drawn, ascending, and their counts (summing to ``n``):
    ``Σ counts · f(idx) / n`` is unbiased for ``Σ w f``, with a variance of at most the
    multinomial ``Var_w(f) / n`` (Douc, Cappé & Moulines 2005).

    >>> resample(np.log([0.5, 0.25, 0.25]), 4, seed=0)
    (array([0, 1, 2]), array([2, 1, 1]))
    """
    lw = as_float_array(log_weights, "log_weights", ndim=1, finite=False)
    if np.any(np.isnan(lw)) or np.any(lw == np.inf) or not np.any(np.isfinite(lw)):
        raise ValueError("log_weights must have a finite value and no NaN or +inf; a zero "
                         "weight is -inf.")
    n = as_int(n, "n", 1)
    cdf = np.cumsum(np.exp(lw - np.max(lw)))
    u = (np.arange(n) + np.random.default_rng(seed).uniform(size=n)) * (cdf[-1] / n)
    return np.unique(np.minimum(np.searchsorted(cdf, u, side="right"), lw.size - 1),
                     return_counts=True)


#: Adaptive proposal (docs/scenario3.md): prior share of the budget in stage 1, stages,
#: Student-t degrees of freedom, covariance inflation, smallest sd as a share of the prior's,
#: and the draws by weight a Student-t is fitted to.
FIRST_STAGE, N_STAGES, DF, INFLATE, FLOOR, FIT_POINTS = 0.1, 6, 5.0, 1.5, 1e-3, 4000


@dataclass(frozen=True)
class StudentT:
    """A multivariate Student-t: ``mean`` (P,), positive-definite ``scale`` (P, P) (the
    covariance is ``scale · df / (df − 2)``) and ``df`` > 2 degrees of freedom."""

    mean: np.ndarray
    scale: np.ndarray
    df: float
    _chol: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self):            # built only here, from a floored covariance
        object.__setattr__(self, "_chol", np.linalg.cholesky(0.5 * (self.scale + self.scale.T)))

    @classmethod
    def fit(cls, samples, log_weights, *, df: float = 5.0, inflate: float = 1.0,
            floor=None, seed=None) -> StudentT:
        """Match the mean and covariance of :data:`FIT_POINTS` draws by weight
        (:func:`resample`) from ``samples`` (n, P), ``floor`` (P,) squared added to its
        variances (keeps a collapsed sample usable), × ``inflate``."""
        idx, counts = resample(log_weights, FIT_POINTS, seed)   # refuses all-zero weights
        x, w = samples[idx], counts / FIT_POINTS
        mean = w @ x
        cov = ((x - mean) * w[:, None]).T @ (x - mean)
        if floor is not None:
            cov += np.diag(np.asarray(floor) ** 2)
        return cls(mean, cov * (float(inflate) * (df - 2.0) / df), df)

    @property
    def size(self) -> int:
        return self.mean.size

    def logpdf(self, x) -> np.ndarray:
        """Log density at ``x`` of shape (..., P); returns shape (...)."""
        x = np.asarray(x, dtype=np.float64)
        P, nu = self.size, self.df
        d = (x - self.mean).reshape(-1, P)
        u = solve_triangular(self._chol, d.T, lower=True)      # L⁻¹ (x − μ)
        q = np.sum(u * u, axis=0)
        log_det = 2.0 * np.sum(np.log(np.diag(self._chol)))
        out = (gammaln(0.5 * (nu + P)) - gammaln(0.5 * nu) - 0.5 * P * np.log(nu * np.pi)
               - 0.5 * log_det - 0.5 * (nu + P) * np.log1p(q / nu))
        return out.reshape(x.shape[:-1])

    def sample(self, n: int, seed=None) -> np.ndarray:
        """``n`` draws, shape (n, P): ``μ + L g / √(χ²_ν / ν)``."""
        n = as_int(n, "n", 1)
        rng = np.random.default_rng(seed)
        g = rng.standard_normal((n, self.size))
        chi = rng.chisquare(self.df, size=n)
        return self.mean + (g @ self._chol.T) / np.sqrt(chi / self.df)[:, None]


def stage_sizes(n: int, n_stages: int = N_STAGES) -> list[int]:
    """Split a per-group budget ``n`` into stages: a tenth from the prior, the rest evenly.

    >>> stage_sizes(500), stage_sizes(3), stage_sizes(1)
    ([50, 90, 90, 90, 90, 90], [1, 1, 1], [1])
    """
    n = as_int(n, "n", 1)
    n_stages = max(1, min(as_int(n_stages, "n_stages", 1), n))
    if n_stages == 1:
        return [n]
    first = min(n - (n_stages - 1), max(1, int(round(FIRST_STAGE * n))))
    rest, k = n - first, n_stages - 1
    return [first] + [rest // k + (1 if i < rest % k else 0) for i in range(k)]


class AdaptiveSample(NamedTuple):
    """``samples`` (S, n, P) stage by stage, their deterministic-mixture ``log_weights``
    (S, n) normalised jointly, ``log_likelihood`` (S, n), the proposals of stages 2, 3, …
    and the ``stage_sizes``."""

    samples: np.ndarray
    log_weights: np.ndarray
    log_likelihood: np.ndarray
    proposals: tuple
    stage_sizes: tuple


def adaptive_importance_sampling(log_likelihood: Callable[[np.ndarray], np.ndarray],
                                 prior, n_groups: int, n: int, *, seed=None,
                                 log_likelihood_grad: Callable | None = None,
                                 n_stages: int = N_STAGES, df: float = DF,
                                 inflate: float = INFLATE,
                                 progress: Callable[[float], None] | None = None
                                 ) -> AdaptiveSample:
    """Adaptive multiple importance sampling (AMIS, Cornuet et al. 2012) of ``p(x | group)``.

    For each of ``n_groups`` groups (scenario 3: the θ samples) the target is
    ``log_likelihood(x, group) + log prior(x)``. Stage 1 draws from the prior; stage 2, given
    ``log_likelihood_grad``, from the Laplace approximation of the best stage-1 draw's group
    (a posterior far narrower than the prior leaves few good prior draws to fit to); the
    others from a Student-t fitted to all weighted draws so far, pooled over groups. Every
    draw is weighted against the mixture of all proposals, ``log w = log L + log p − log
    Σ_t (n_t / n) q_t``, normalised jointly over groups and draws.

    ``log_likelihood`` maps ``x`` (S, m, P), row j for group j, to (S, m) (``-inf``
    allowed); ``log_likelihood_grad(x, j)`` its value and gradient at one ``x`` (P,) of
    group j; ``prior`` has ``sample(n, seed)``, ``logpdf``, ``grad`` and ``var`` (e.g.
    :class:`mdcore.GaussianPrior`); ``progress`` gets the fraction done after each
    stage and may raise to stop.
    """
    S = as_int(n_groups, "n_groups", 1)
    sizes = stage_sizes(n, n_stages)
    rng = np.random.default_rng(seed)
    P = int(np.size(prior.var))
    n_total = sum(sizes)
    x = np.empty((S, n_total, P))
    # log_mass = log Σ_s n_s q_s(x) of every draw so far: each stage adds its proposal to the
    # old draws and all proposals to its new ones, so each q_s is evaluated once per draw.
    loglik, log_prior, log_mass = np.empty((3, S, n_total))
    proposals: list = []
    floor = FLOOR * np.sqrt(np.asarray(prior.var, dtype=np.float64))
    col = 0
    for t, n_t in enumerate(sizes):
        if t == 0:
            draws = prior.sample(S * n_t, seed=rng)
        else:
            q = None if t > 1 or log_likelihood_grad is None else _laplace(
                log_likelihood_grad, prior, x[:, :col], loglik[:, :col] + log_prior[:, :col],
                df, inflate, floor)
            if q is None:
                lw = _mixture_log_weights(loglik[:, :col], log_prior[:, :col],
                                          log_mass[:, :col], col)
                q = StudentT.fit(x[:, :col].reshape(-1, P), lw.ravel(), df=df,
                                 inflate=inflate, floor=floor, seed=rng)
            proposals.append(q)
            draws = q.sample(S * n_t, seed=rng)
            np.logaddexp(log_mass[:, :col], np.log(n_t) + q.logpdf(x[:, :col]),
                         out=log_mass[:, :col])
        sl = slice(col, col + n_t)
        x[:, sl] = draws.reshape(S, n_t, P)
        log_prior[:, sl] = prior.logpdf(x[:, sl])
        log_mass[:, sl] = logsumexp([np.log(sizes[0]) + log_prior[:, sl]]
                                    + [np.log(sizes[s + 1]) + f.logpdf(x[:, sl])
                                       for s, f in enumerate(proposals)], axis=0)
        loglik[:, sl] = log_likelihood(x[:, sl])
        col += n_t
        if progress is not None:
            progress((t + 1) / len(sizes))
    lw = _mixture_log_weights(loglik, log_prior, log_mass, n_total)
    total = logsumexp(lw)
    if not np.isfinite(total):
        raise ValueError("every adaptive importance weight is zero: the likelihood is zero "
                         "at every draw; check the prior.")
    return AdaptiveSample(x, lw - total, loglik, tuple(proposals), tuple(sizes))


def _laplace(log_likelihood_grad, prior, x, log_post, df, inflate, floor):
    """A Student-t at the Laplace approximation of the posterior of the group j whose draw
    in ``x`` (S, m, P) has the largest ``log_post`` (S, m): L-BFGS-B from that draw, then the
    inverse of the Hessian by central differences of the gradient (no variance above the
    prior's largest), ``floor`` (P,) squared added to its variances, × ``inflate``. None
    when no draw or no optimum is finite."""
    if not np.any(np.isfinite(log_post)):
        return None
    j, k = np.unravel_index(int(np.argmax(log_post)), log_post.shape)

    def objective(v):
        f, g = log_likelihood_grad(v, int(j))
        if not np.isfinite(f):
            return 1e300, np.zeros_like(v)
        return -(f + float(prior.logpdf(v))), -(g + prior.grad(v))

    res = scipy.optimize.minimize(objective, x[j, k], jac=True, method="L-BFGS-B")
    mode, h = np.asarray(res.x, dtype=np.float64), 1e-4
    if not (np.all(np.isfinite(mode)) and res.fun < 1e300):
        return None
    H = np.array([objective(mode + h * e)[1] - objective(mode - h * e)[1]
                  for e in np.eye(mode.size)]) / (2.0 * h)
    lam, U = np.linalg.eigh(0.5 * (H + H.T))
    cov = (U / np.maximum(lam, 1.0 / np.max(prior.var))) @ U.T + np.diag(floor ** 2)
    return StudentT(mode, cov * (inflate * (df - 2.0) / df), df)


def _mixture_log_weights(loglik, log_prior, log_mass, n: int) -> np.ndarray:
    """Deterministic-mixture log weights ``log L + log p − log Σ_t (n_t / n) q_t`` from
    ``loglik``, ``log_prior`` and ``log_mass = log Σ_t n_t q_t`` (S, m); ``n = Σ_t n_t``."""
    with np.errstate(invalid="ignore"):
        lw = loglik + log_prior - (log_mass - np.log(n))
    return np.where(np.isnan(lw), -np.inf, lw)
