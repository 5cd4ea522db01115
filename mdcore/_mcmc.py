"""Adaptive Metropolis (Haario, Saksman & Tamminen 2001) and chain diagnostics.

The proposal covariance is ``C_0`` up to step ``t_0``, then ``s_d Cov(x_0, …, x_{t−1}) + s_d ε
I``, ``s_d = 2.4² / d`` (Haario et al. Eq. 2.1), by Welford's recursion. :func:`chain_setup`,
:func:`draw_blocks` and :func:`finish_chain` are shared with :func:`mdcore._compiled.koh_chain`,
so both draw the same random numbers.
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from ._exceptions import RELIABLE_TAUS, ConvergenceWarning, chain_advice
from ._validation import as_float_array, as_int

#: Longest chain accepted (the kept steps are stored): longer is refused up front.
MAX_CHAIN = 100_000_000
#: Steps whose random numbers are drawn at once; the ε of the proposal's ``s_d ε I``.
DRAW_BLOCK = 4096
EPSILON = 1e-8


@dataclass(frozen=True, eq=False)
class Chain:
    """The kept part of an adaptive-Metropolis run: ``samples`` (n_iter − burn_in, d) and
    their ``log_target``, acceptance rates after and during burn-in, the last proposal
    covariance ``C_t`` (d, d) and the integrated autocorrelation time ``iat`` (d,)."""

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
        """Whether the kept chain spans 50 autocorrelation times in every coordinate."""
        return bool(np.all(self.samples.shape[0] > RELIABLE_TAUS * self.iat))

    @property
    def ess(self) -> np.ndarray:
        """Effective sample size per coordinate, ``n_kept / iat``, shape (d,)."""
        return self.samples.shape[0] / self.iat


def integrated_autocorr_time(x, *, c: float = 5.0) -> np.ndarray:
    """Integrated autocorrelation time ``τ = 1 + 2 Σ_{k≤M} ρ(k)`` (d,) per coordinate of a
    chain ``x`` (n ≥ 2,) or (n, d), ``ρ`` by FFT and ``M`` the smallest window with
    ``M ≥ c τ(M)`` (Sokal 1997, as emcee); 1 ≤ τ ≤ n (n for a chain that never moved)."""
    x = as_float_array(x, "x")
    x = x[:, None] if x.ndim == 1 else x
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


class ChainSetup(NamedTuple):
    """A validated adaptive-Metropolis run (:func:`chain_setup`)."""

    x0: np.ndarray       # (d,) starting state
    lp0: float           # log target at x0
    L0: np.ndarray       # (d, d) lower factor of C_0
    n_iter: int
    burn_in: int
    t0: int              # adaptation starts after this many steps
    s_d: float           # 2.4² / d
    reg: np.ndarray      # (d, d) s_d ε I


def chain_length(n_iter, burn_in, hint: str = "") -> tuple[int, int]:
    """Validated ``(n_iter, burn_in)``: at least two kept samples, at most :data:`MAX_CHAIN`."""
    n_iter = as_int(n_iter, "n_iter", 2, MAX_CHAIN)
    burn_in = as_int(burn_in, "burn_in", 0, MAX_CHAIN)
    if burn_in >= n_iter - 1:
        raise ValueError(f"burn_in must be smaller than n_iter − 1 = {n_iter - 1} so that at "
                         f"least two samples are kept; received burn_in={burn_in}.{hint}")
    return n_iter, burn_in


def chain_setup(log_target: Callable[[np.ndarray], float], x0, *, n_iter: int,
                burn_in: int) -> ChainSetup:
    """The validated start of :func:`adaptive_metropolis` (which documents it)."""
    x = as_float_array(x0, "x0", ndim=1).copy()
    d = x.size
    n_iter, burn_in = chain_length(n_iter, burn_in)
    L = np.linalg.cholesky(0.01 * np.eye(d))
    t0 = max(min(1000, n_iter // 10), 2 * d)
    lp = float(log_target(x))
    if not np.isfinite(lp):
        raise ValueError(f"log_target(x0) must be finite; it is {lp} at x0 = {x.tolist()}. "
                         "Start the chain inside the support (e.g. at the prior mean).")
    s_d = 2.4**2 / d
    return ChainSetup(x, lp, L, n_iter, burn_in, t0, s_d, s_d * EPSILON * np.eye(d))


def draw_blocks(setup: ChainSetup, seed, progress: Callable[[float], None] | None = None
                ) -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
    """The chain's random numbers in blocks ``(t, steps (b, d), log_u (b,))`` for steps
    ``t … t + b − 1``; ``progress(t / n_iter)`` runs between blocks every 1 % of the run
    (raising stops sampling)."""
    rng = np.random.default_rng(seed)
    n_iter, d = setup.n_iter, setup.x0.size
    every = max(1, n_iter // 100)
    for start in range(1, n_iter + 1, DRAW_BLOCK):
        steps = rng.standard_normal((min(DRAW_BLOCK, n_iter - start + 1), d))
        log_u = np.log(rng.uniform(size=steps.shape[0]))
        t = start
        while t < start + steps.shape[0]:
            last = min(start + steps.shape[0] - 1, -(-t // every) * every)
            yield t, steps[t - start:last + 1 - start], log_u[t - start:last + 1 - start]
            if progress is not None and last % every == 0:
                progress(last / n_iter)
            t = last + 1


def finish_chain(setup: ChainSetup, samples: np.ndarray, log_p: np.ndarray,
                 accepted: np.ndarray, L: np.ndarray, seconds: float) -> Chain:
    """The :class:`Chain` of a finished run; warns when it is too short to trust its IAT."""
    kept, burn_in = samples.shape[0], setup.burn_in
    chain = Chain(samples=samples, log_target=log_p,
                  acceptance_rate=float(accepted[1] / kept),
                  acceptance_rate_burn_in=float(accepted[0] / burn_in) if burn_in else np.nan,
                  proposal_cov=L @ L.T, iat=integrated_autocorr_time(samples),
                  n_iter=setup.n_iter, burn_in=burn_in, adapt_start=setup.t0, seconds=seconds)
    if not chain.reliable:
        warnings.warn(chain_advice("adaptive Metropolis", float(np.max(chain.iat)), kept, burn_in),
                      ConvergenceWarning, stacklevel=3)
    return chain


def adaptive_metropolis(log_target: Callable[[np.ndarray], float], x0, *, n_iter: int,
                        burn_in: int, seed=None,
                        progress: Callable[[float], None] | None = None) -> Chain:
    """Sample ``exp(log_target(x))``, x (d,), ``-inf`` outside the support, from ``x0`` where
    it is finite: ``n_iter`` steps of which the first ``burn_in`` are dropped; proposals
    ``C_0 = 0.01 I`` up to ``t_0 = max(min(1000, n_iter // 10), 2 d)``, then the module's.
    ``progress`` gets the fraction done every 1 % (and may raise to cancel)."""
    setup = chain_setup(log_target, x0, n_iter=n_iter, burn_in=burn_in)
    start = time.perf_counter()
    x, lp, L = setup.x0.copy(), setup.lp0, setup.L0
    burn_in, s_d, reg, t0 = setup.burn_in, setup.s_d, setup.reg, setup.t0
    samples = np.empty((n_iter - burn_in, x.size))
    log_p = np.empty(n_iter - burn_in)
    accepted = np.zeros(2, dtype=np.int64)               # [burn-in, kept]
    mean, m2 = x.copy(), np.zeros((x.size, x.size))      # Welford: states x_0 … x_{t−1}
    for first, steps, log_u in draw_blocks(setup, seed, progress):
        for i, t in enumerate(range(first, first + len(steps))):
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
    return finish_chain(setup, samples, log_p, accepted, L, time.perf_counter() - start)
