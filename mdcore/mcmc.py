"""Adaptive Metropolis (Haario, Saksman & Tamminen 2001) and chain diagnostics.

The sampler is a random-walk Metropolis whose Gaussian proposal covariance is, at step t,

    C_t = C_0                                   for t ≤ t_0
    C_t = s_d Cov(x_0, …, x_{t−1}) + s_d ε I     for t > t_0,      s_d = 2.4² / d

(Haario et al. 2001, Eq. 2.1). The chain covariance is updated at every step with
Welford's recursion, so the adaptation is the paper's, not a batched approximation.

Examples
--------
>>> import numpy as np
>>> from mdcore.mcmc import adaptive_metropolis
>>> chain = adaptive_metropolis(lambda x: -0.5 * float(x @ x), np.zeros(2), n_iter=5000,
...                             burn_in=1000, seed=0)
>>> chain.samples.shape, 0.1 < chain.acceptance_rate < 0.9
((4000, 2), True)
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .exceptions import ConvergenceWarning
from .validation import as_float_array, as_int

__all__ = ["Chain", "MAX_CHAIN", "RELIABLE_TAUS", "adaptive_metropolis",
           "integrated_autocorr_time"]

#: A chain is long enough to trust its IAT when it spans this many autocorrelation times
#: (Foreman-Mackey et al., emcee: "more than 50 τ").
RELIABLE_TAUS = 50
#: Longest chain accepted (the kept steps are stored): longer is refused up front.
MAX_CHAIN = 100_000_000


@dataclass(frozen=True, eq=False)
class Chain:
    """The kept part of an adaptive-Metropolis run.

    Attributes
    ----------
    samples : ndarray of shape (n_iter − burn_in, d)
        States after burn-in (every state, repeats included).
    log_target : ndarray of shape (n_iter − burn_in,)
        Log target density at each kept state.
    acceptance_rate : float
        Fraction of accepted proposals after burn-in.
    acceptance_rate_burn_in : float
        The same during burn-in.
    proposal_cov : ndarray of shape (d, d)
        The proposal covariance ``C_t`` at the last step.
    iat : ndarray of shape (d,)
        Integrated autocorrelation time of each coordinate of :attr:`samples`.
    n_iter, burn_in, adapt_start : int
    seconds : float
    """

    samples: np.ndarray
    log_target: np.ndarray
    acceptance_rate: float
    acceptance_rate_burn_in: float
    proposal_cov: np.ndarray
    iat: np.ndarray
    n_iter: int
    burn_in: int
    adapt_start: int
    seconds: float

    @property
    def reliable(self) -> bool:
        """Whether the kept chain is longer than 50 autocorrelation times in every
        coordinate (emcee's check): otherwise the IAT, and the ESS, are themselves unsure."""
        return bool(np.all(self.samples.shape[0] > RELIABLE_TAUS * self.iat))

    @property
    def ess(self) -> np.ndarray:
        """Effective sample size per coordinate, ``n_kept / iat``, shape (d,)."""
        return self.samples.shape[0] / self.iat


def integrated_autocorr_time(x, *, c: float = 5.0) -> np.ndarray:
    """Integrated autocorrelation time per coordinate, with Sokal's automatic window.

    ``τ = 1 + 2 Σ_{k=1}^{M} ρ(k)`` where ``ρ`` is the FFT estimate of the normalised
    autocorrelation and ``M`` is the smallest window with ``M ≥ c τ(M)`` (Sokal 1997; the
    estimator of ``emcee``). For an AR(1) chain with coefficient a, ``τ = (1 + a)/(1 − a)``.

    Parameters
    ----------
    x : ndarray of shape (n,) or (n, d)
        A chain (rows are successive states), n ≥ 2.
    c : float, default=5
        Window constant.

    Returns
    -------
    ndarray of shape (d,)
        τ ≥ 1 per coordinate in samples; ``n / τ`` is the effective sample size. A
        constant coordinate (a chain that never moved) gets τ = n.
    """
    x = as_float_array(x, "x")
    if x.ndim == 1:
        x = x[:, None]
    if x.ndim != 2 or x.shape[0] < 2:
        raise ValueError(f"x must have shape (n, d) with n ≥ 2; received {x.shape}.")
    n = x.shape[0]
    xc = x - x.mean(axis=0)
    size = 1 << int(np.ceil(np.log2(2 * n)))
    f = np.fft.rfft(xc, n=size, axis=0)
    acov = np.fft.irfft(f * np.conj(f), n=size, axis=0)[:n]
    tau = np.full(x.shape[1], float(n))
    for j in range(x.shape[1]):
        if acov[0, j] <= 0:
            continue                                     # never moved
        taus = 2.0 * np.cumsum(acov[:, j] / acov[0, j]) - 1.0
        window = np.arange(n) >= c * taus
        m = int(np.argmax(window)) if np.any(window) else n - 1
        tau[j] = min(max(taus[m], 1.0), float(n))
    return tau


def adaptive_metropolis(log_target: Callable[[np.ndarray], float], x0, *, n_iter: int,
                        burn_in: int, initial_cov=None, adapt_start: int | None = None,
                        epsilon: float = 1e-8, seed=None,
                        progress: Callable[[float], None] | None = None) -> Chain:
    """Sample ``exp(log_target)`` by adaptive Metropolis (Haario et al. 2001).

    Parameters
    ----------
    log_target : callable
        ``log_target(x)`` for x of shape (d,): the log density up to a constant; ``-inf``
        outside the support. A target with an ``advance`` method (as
        :class:`mdcore.compiled.KOHTarget`) takes runs of steps itself:
        ``advance(t, stop, x, lp, mean, m2, L, burn_in, t0, s_d, reg, steps, log_u,
        samples, log_p, accepted)`` does steps ``t ≤ s < stop`` of the loop below on the
        state in place and returns the log target of the state.
    x0 : ndarray of shape (d,)
        Starting state; ``log_target(x0)`` must be finite.
    n_iter : int
        Total iterations, burn-in included.
    burn_in : int
        Leading iterations dropped from :attr:`Chain.samples` (0 ≤ burn_in < n_iter).
    initial_cov : ndarray of shape (d, d), optional
        ``C_0``, used up to ``adapt_start``. Default ``(0.1)² I``.
    adapt_start : int, optional
        ``t_0``: adaptation starts after this many iterations (default
        ``min(1000, n_iter // 10)``, at least 2 d).
    epsilon : float, default=1e-8
        ``ε`` of the regularising term ``s_d ε I`` (in the units of x squared).
    seed : int or numpy.random.Generator, optional
    progress : callable, optional
        Called with the fraction done (0–1) about every 1 % of the run; if it raises,
        sampling stops and the exception propagates (use this to cancel).

    Returns
    -------
    Chain
    """
    x = as_float_array(x0, "x0", ndim=1).copy()
    d = x.size
    n_iter = as_int(n_iter, "n_iter", 2, MAX_CHAIN)
    burn_in = as_int(burn_in, "burn_in", 0, MAX_CHAIN)
    if burn_in >= n_iter - 1:
        raise ValueError(f"burn_in must be smaller than n_iter − 1 = {n_iter - 1} so that at "
                         f"least two samples are kept; received burn_in={burn_in}.")
    C0 = 0.01 * np.eye(d) if initial_cov is None else \
        as_float_array(initial_cov, "initial_cov", ndim=2)
    if C0.shape != (d, d):
        raise ValueError(f"initial_cov must have shape ({d}, {d}); received {C0.shape}.")
    try:
        L = np.linalg.cholesky(C0)
    except np.linalg.LinAlgError:
        raise ValueError("initial_cov must be symmetric positive definite.") from None
    t0 = max(min(1000, n_iter // 10), 2 * d) if adapt_start is None else \
        as_int(adapt_start, "adapt_start", 2)
    epsilon = float(epsilon)
    if not (np.isfinite(epsilon) and epsilon > 0):
        raise ValueError(f"epsilon must be a positive number; received {epsilon!r}.")
    lp = float(log_target(x))
    if not np.isfinite(lp):
        raise ValueError(f"log_target(x0) must be finite; it is {lp} at x0 = {x.tolist()}. "
                         "Start the chain inside the support (e.g. at the prior mean).")
    rng = np.random.default_rng(seed)
    s_d = 2.4**2 / d
    reg = s_d * epsilon * np.eye(d)
    kept = n_iter - burn_in
    samples = np.empty((kept, d))
    log_p = np.empty(kept)
    accepted = np.zeros(2, dtype=np.int64)               # [burn-in, kept]
    mean, m2 = x.copy(), np.zeros((d, d))                # Welford: states x_0 … x_{t−1}
    every = max(1, n_iter // 100)
    block = 4096
    start = time.perf_counter()
    advance = getattr(log_target, "advance", None)
    t = 1
    while t <= n_iter:
        if (t - 1) % block == 0:
            steps = rng.standard_normal((min(block, n_iter - t + 1), d))
            log_u = np.log(rng.uniform(size=steps.shape[0]))
        i = (t - 1) % block
        if advance is not None:
            # A compiled target takes the steps t … last in one call (the same steps: see
            # its advance), last the end of these draws, the next progress call or the end.
            last = min(t - i + steps.shape[0] - 1, -(-t // every) * every, n_iter)
            lp = advance(t, last + 1, x, lp, mean, m2, L, burn_in, t0, s_d, reg,
                         steps[i:i + last + 1 - t], log_u[i:i + last + 1 - t], samples,
                         log_p, accepted)
            t = last
        else:
            y = x + L @ steps[i]
            lq = float(log_target(y))
            if lq - lp > log_u[i]:                       # NaN and -inf are rejected
                x, lp = y, lq
                accepted[int(t > burn_in)] += 1
            if t > burn_in:
                samples[t - burn_in - 1] = x
                log_p[t - burn_in - 1] = lp
            # Welford update with x_t; the proposal for step t + 1 uses Cov(x_0, …, x_t).
            delta = x - mean
            mean = mean + delta / (t + 1)
            m2 += np.outer(delta, x - mean)
            if t >= t0:
                try:
                    L = np.linalg.cholesky(s_d * m2 / t + reg)   # Eq. 2.1: s_d Cov + s_d ε I
                except np.linalg.LinAlgError:
                    pass                                 # keep the previous proposal
        if progress is not None and t % every == 0:
            progress(t / n_iter)
        t += 1
    chain = Chain(samples, log_p, float(accepted[1] / kept),
                  float(accepted[0] / burn_in) if burn_in else float("nan"), L @ L.T,
                  integrated_autocorr_time(samples), n_iter, burn_in, t0,
                  time.perf_counter() - start)
    if not chain.reliable:
        tau = float(np.max(chain.iat))
        warnings.warn(f"adaptive Metropolis: the {kept:,} kept steps are fewer than 50 "
                      f"autocorrelation times (τ up to {tau:.1f}), so the IAT and ESS are "
                      f"unreliable; raise n_iter to at least "
                      f"{int(np.ceil(RELIABLE_TAUS * tau)) + burn_in:,}.",
                      ConvergenceWarning, stacklevel=2)
    return chain
