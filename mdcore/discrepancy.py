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

Chunks and executors
--------------------
The (θ, φ) pairs are processed in chunks whose layout depends on the problem size only:

- scenario 3's weights: :data:`WEIGHT_PAIRS` pairs per chunk (rows of θ × all N_φ draws),
  every output at once; with the prior proposal the first :data:`PILOT_PAIRS` pairs go
  first, alone, and set the cut below which pairs are left out as negligible (their total
  weight provably below :data:`ABANDON_MASS`; see :func:`_nlml_rows`);
- the prediction: about 20 blocks per output on the compiled backend (at least
  :data:`MIN_FUSED_BLOCK` pairs), or blocks of :data:`BLOCK_BYTES` of temporaries on NumPy.

Each chunk is one call of a module-level function on the arrays it needs (a few MB at
most), so ``executor=`` (any ``concurrent.futures.Executor``: a ``ThreadPoolExecutor``, a
``ProcessPoolExecutor``, a Dask ``Client(...).get_executor()``) can run them elsewhere. The
results are collected and reduced in chunk order, exactly as the serial run does, so the
numbers are identical to the serial run's for the same seed, on any executor.

Granularity: a Dask task costs a few ms when the cluster is idle (measured: ~36 ms for a
1.6 MB payload on a loaded two-core machine), so each chunk is sized at ~0.1–0.3 s of
one core's work on beam-1d: 100,000 NLMLs (3.2 MB of φ) per weight chunk, a compiled
prediction block of 25,000 pairs at the paper's sizes (0.8 MB), or ~2,900 pairs on NumPy.
A cluster therefore pays from the paper's sizes up (scenario 3: 5 weight chunks and 20
prediction blocks an output at N_s × N_φ = 1000 × 500, ten times as many chunks of the
weights at 10×); smaller runs (scenario 2, the app's sizes) are a chunk or two and are
quicker serially. The same layout keeps cancelling (``progress`` raising) within a chunk.
At most :data:`IN_FLIGHT` chunks are submitted and not yet collected, which bounds the
memory held by payloads and results.

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

import collections
import contextlib
import itertools
import time
import warnings
from collections.abc import Callable, Generator, Iterable
from concurrent.futures import Executor
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np
from scipy.special import logsumexp

from . import compiled, gp
from .exceptions import LowESSWarning, NumericalWarning
from .hyperfit import default_bounds, fit_hyperparameters
from .importance import K_HAT_THRESHOLD, adaptive_importance_sampling, psis
from .kernels import distinct_rows
from .linalg import JitterLog
from .priors import GaussianPrior
from .threads import single_threaded_blas
from .validation import as_float_array, as_int, as_outputs, choose

__all__ = ["infer_discrepancy", "DiscrepancyModel", "DiscrepancyPrediction", "default_phi_prior",
           "LowESSWarning", "SCENARIOS", "PROPOSALS", "LOW_ESS", "check_executor"]

SCENARIOS = (1, 2, 3)
#: Scenario 3's φ proposals: the paper's prior draws, or adaptive importance sampling.
PROPOSALS = ("prior", "adaptive")
#: Scenario 3 warns when an output's effective sample size is below this.
LOW_ESS = 30.0
#: Default pruning level: components with normalised weight below ``PRUNE × max`` are
#: skipped in the prediction step (their mass is reported).
PRUNE = 1e-12
#: Working-memory budget of one prediction block on the NumPy backend, in bytes.
BLOCK_BYTES = 32 * 2**20
#: Fewest pairs per block of the compiled prediction (which aims at ~20 blocks per output).
MIN_FUSED_BLOCK = 2048
#: (θ, φ) pairs per chunk of scenario 3's weights (one task, one progress step).
WEIGHT_PAIRS = 100_000
#: Scenario 3 (prior proposal) leaves out pairs whose weights provably add up to less than
#: this fraction of the total (float64 resolves ~1.1e-16 of a sum of 1), see
#: :func:`_nlml_rows`; :attr:`DiscrepancyModel.abandoned_mass` reports the bound. Set it
#: to 0 to weigh every pair (every log weight then finite unless its matrix fails).
ABANDON_MASS = 1e-16
#: Pairs weighed first, in full, to set scenario 3's cut (:data:`ABANDON_MASS`): the best
#: NLML of beam-2d's first 10 θ rows (10,000 pairs) is 4.4 nats from the best of all.
PILOT_PAIRS = 10_000
#: Chunks submitted to an executor and not yet collected, at most.
IN_FLIGHT = 32
#: Scenario 3's prior draws φ (N_s, N_φ, P) are kept up to this size, in bytes; larger
#: sets are regenerated from their random stream when needed (:class:`PriorDraws`).
KEEP_DRAWS_BYTES = 64 * 2**20


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


def check_executor(executor) -> Executor | None:
    """``executor`` if it is None or has a callable ``submit``; else a ValueError naming it."""
    if executor is not None and not callable(getattr(executor, "submit", None)):
        raise ValueError(f"executor must be a concurrent.futures.Executor (with submit), e.g. "
                         f"a ThreadPoolExecutor or a Dask Client(...).get_executor(); received "
                         f"{type(executor).__name__}.")
    return executor


def _in_order(executor: Executor | None, fn: Callable, payloads: Iterable[tuple]
              ) -> Generator[Any, None, None]:
    """``fn(*args)`` for each ``args`` of ``payloads``, in order.

    Without an executor the calls run here, one at a time. With one, up to
    :data:`IN_FLIGHT` calls are submitted ahead of the one awaited; when the consumer stops
    early (an exception, a cancel), the calls not yet collected are cancelled.
    """
    if executor is None:
        for args in payloads:
            yield fn(*args)
        return
    pending: collections.deque = collections.deque()
    try:
        for args in payloads:
            pending.append(executor.submit(fn, *args))
            if len(pending) >= IN_FLIGHT:
                yield pending.popleft().result()
        while pending:
            yield pending.popleft().result()
    finally:
        for future in pending:
            future.cancel()


def _weights_chunk(phi: np.ndarray, Y: np.ndarray, X: np.ndarray, z: np.ndarray,
                   backend: str, stop: np.ndarray) -> tuple[np.ndarray, tuple | None]:
    """Scenario 3's log weights ``−NLML`` (Eq. 15) of one chunk of pairs, every output.

    Module level and on plain arrays, so that process and Dask executors can run it.

    Parameters
    ----------
    phi : ndarray of shape (R, K, P)
        Log hyperparameters of the chunk's pairs: R θ rows × K draws.
    Y : ndarray of shape (R, N, n_out)
        Simulator outputs at the training inputs of the R θ.
    X : ndarray of shape (N, d_x)
    z : ndarray of shape (N, n_out)
    backend : {"numpy", "numba"}
    stop : ndarray of shape (n_out,)
        Per output, the NLML beyond which a pair's weight is not wanted (``inf``: none);
        see ``stop`` in :func:`mdcore.gp.neg_log_marginal_likelihood`.

    Returns
    -------
    log_w : ndarray of shape (n_out, R, K)
        Unnormalised log weights; ``-inf`` where the covariance could not be factorised
        or the NLML exceeds ``stop``.
    jitter : tuple or None
        Compiled backend: ``(jittered, failed, max_jitter)`` for the caller to report; the
        NumPy backend warns where it runs.
    """
    out = np.empty((z.shape[1],) + phi.shape[:2])
    if backend == "numba":
        log = JitterLog()
        for o in range(z.shape[1]):
            out[o] = -compiled.nlml(phi, Y[:, None], X, z[:, o], jitter_log=log,
                                    stop=stop[o])
        return out, (log.jittered, log.failed, log.max_jitter)
    for o in range(z.shape[1]):
        out[o] = -gp.neg_log_marginal_likelihood(phi, Y[:, None], X, z[:, o], backend="numpy",
                                                 stop=stop[o])
    return out, None


def _mixture_chunk(log_params: np.ndarray, Y: np.ndarray, j: np.ndarray, X: np.ndarray,
                   z: np.ndarray, Y_star: np.ndarray, y_star_out: np.ndarray, w: np.ndarray,
                   X_star: np.ndarray, cz: np.ndarray, cd: np.ndarray, backend: str
                   ) -> tuple[np.ndarray, np.ndarray, tuple | None]:
    """Weighted mixture sums (Eq. 13/15) of one block of components of one output.

    Module level and on plain arrays (only the θ rows the block uses), so that process and
    Dask executors can run it; the caller adds the blocks' sums in block order.

    Parameters
    ----------
    log_params : ndarray of shape (B, P)
        Hyperparameters of the block's B components.
    Y : ndarray of shape (S_b, N, d_y)
        Training simulator outputs of the θ rows the block uses.
    j : int ndarray of shape (B,)
        Row of ``Y``, ``Y_star`` and ``y_star_out`` of each component.
    X : ndarray of shape (N, d_x)
    z : ndarray of shape (N,)
        This output's observations.
    Y_star : ndarray of shape (S_b, M, d_y)
        Simulator outputs at ``X_star``.
    y_star_out : ndarray of shape (S_b, M)
        This output's column of ``Y_star``.
    w : ndarray of shape (B,)
        Normalised weights.
    X_star : ndarray of shape (M, d_x)
    cz, cd : ndarray of shape (M,)
        The reference component's ``E[z*]`` and ``E[z*] − y*``.
    backend : {"numpy", "numba"}

    Returns
    -------
    acc : ndarray of shape (4, M)
        ``Σ w dz``, ``Σ w dδ``, ``Σ w (V_f + σ_n² + dz²)``, ``Σ w (V_f + dδ²)``.
    bad : bool ndarray of shape (B,)
        Components left out (not factorisable, or non-finite moments).
    jitter : tuple or None
        As in :func:`_weights_chunk`.
    """
    if backend == "numba":       # the same sums, per pair in registers (mdcore.compiled)
        log = JitterLog()
        sums = compiled.mixture_sums(log_params, Y, j, X, z, Y_star, y_star_out, w, X_star,
                                     cz, cd, jitter_log=log)
        return sums.acc, sums.dropped, (log.jittered, log.failed, log.max_jitter)
    acc, bad = _numpy_mixture_sums(log_params, Y, j, X, z, Y_star, y_star_out, w, X_star,
                                   cz, cd)
    return acc, bad, None


@single_threaded_blas       # one BLAS thread, as on a Dask worker: the same sums everywhere
def _numpy_mixture_sums(log_params, Y, j, X, z, Y_star, y_star_out, w, X_star, cz, cd):
    """:func:`_mixture_chunk` on the NumPy backend: ``(acc (4, M), bad (B,))``."""
    p = gp.predict(log_params, Y[j], X, z, Y_star[j], X_star, backend="numpy")
    mean, var, sn2, ystar = p.mean, p.var, p.noise_var[:, None], y_star_out[j]
    bad = ~np.all(np.isfinite(mean) & np.isfinite(var), axis=1)
    if np.any(bad):
        w = np.where(bad, 0.0, w)
        mean = np.where(bad[:, None], 0.0, mean)
        var = np.where(bad[:, None], 0.0, var)
    dz = mean - cz
    dd = mean - ystar - cd
    acc = np.zeros((4, X_star.shape[0]))
    acc[0] += w @ dz
    acc[1] += w @ dd
    acc[2] += w @ (var + sn2 + dz * dz)          # Eq. 13/15: total variance of z*
    acc[3] += w @ (var + dd * dd)                # latent variance goes to δ
    return acc, bad


@dataclass(frozen=True, eq=False)
class PriorDraws:
    """Scenario 3's prior draws ``φ^(j,k) ~ p(φ)`` kept as the random stream that made them.

    The draws are made block by block of θ rows: block ``b`` (rows ``[b·rows, (b+1)·rows)``)
    is ``prior.sample(R_b · N_φ, seed=g)`` with ``g`` at ``states[b]``. So any block can be
    drawn again, bit for bit, and a large run need not keep the (N_s, N_φ, P) array
    (160 MB at N_s = 10,000, N_φ = 500, P = 4).

    Attributes
    ----------
    prior : GaussianPrior
    n_theta, n_phi : int
        N_s and N_φ.
    rows : int
        θ rows per block.
    states : tuple of dict
        The generator's ``bit_generator.state`` before each block's draws.
    """

    prior: GaussianPrior
    n_theta: int
    n_phi: int
    rows: int
    states: tuple

    def block(self, b: int) -> np.ndarray:
        """The draws of block ``b``, shape (R_b, N_φ, P)."""
        state = self.states[b]
        bit_generator = getattr(np.random, state["bit_generator"])()
        bit_generator.state = state
        n_rows = min(self.n_theta, (b + 1) * self.rows) - b * self.rows
        return self.prior.sample(n_rows * self.n_phi, seed=np.random.Generator(bit_generator)
                                 ).reshape(n_rows, self.n_phi, self.prior.size)

    def between(self, lo: int, hi: int, cache: dict | None = None) -> np.ndarray:
        """The draws of θ rows ``lo`` to ``hi − 1``, shape (hi − lo, N_φ, P).

        ``cache`` (block -> draws) keeps the blocks drawn for the caller; blocks before
        ``lo``'s are dropped from it, so a caller going through the rows in order holds
        about one block.
        """
        first, last = lo // self.rows, (hi - 1) // self.rows
        if cache is None:
            cache = {}
        for b in [b for b in cache if b < first]:
            del cache[b]
        parts = []
        for b in range(first, last + 1):
            if b not in cache:
                cache[b] = self.block(b)
            parts.append(cache[b])
        draws = parts[0] if len(parts) == 1 else np.concatenate(parts)
        offset = first * self.rows
        return draws[lo - offset:hi - offset]

    def all(self) -> np.ndarray:
        """Every draw, shape (N_s, N_φ, P)."""
        return self.between(0, self.n_theta)


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
        shares one prior draw between outputs (common random numbers). A property: when
        scenario 3's prior draws exceed :data:`KEEP_DRAWS_BYTES` they are kept as
        :attr:`phi_draws` and drawn again on first access (then kept).
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
    phi_draws : PriorDraws or None
        Scenario 3 with the prior proposal: the φ draws as their random stream (used when
        the array itself is not kept).
    abandoned_mass : ndarray of shape (n_out,) or None
        Scenario 3 with the prior proposal: a bound on the normalised weight of the pairs
        left out because their NLML provably exceeds the cut of :data:`ABANDON_MASS`
        (their log weight is ``−inf``); below ``ABANDON_MASS``. Zeros with the adaptive
        proposal (nothing is left out), None for scenarios 1–2.
    """

    scenario: int
    simulate: Callable
    theta: np.ndarray
    Y: np.ndarray
    X: np.ndarray
    z: np.ndarray
    _log_params: np.ndarray | None = field(repr=False)
    log_weights: np.ndarray
    log_params_hat: np.ndarray | None
    nlml_hat: np.ndarray | None
    prune: float
    phi_prior: GaussianPrior | None
    seconds: float
    proposal: str | None = None
    k_hat: np.ndarray | None = None
    backend: str = "numpy"
    phi_draws: PriorDraws | None = field(default=None, repr=False)
    abandoned_mass: np.ndarray | None = None

    @property
    def n_out(self) -> int:
        return self.z.shape[1]

    @property
    def log_params(self) -> np.ndarray:
        """Hyperparameters of every component, (n_out, S, K, P) (see the class)."""
        if self._log_params is None:
            if self.phi_draws is None:
                raise ValueError("this model has neither log_params nor phi_draws.")
            phi = self.phi_draws.all()
            object.__setattr__(self, "_log_params",
                               np.broadcast_to(phi, (self.n_out,) + phi.shape))
        assert self._log_params is not None
        return self._log_params

    def _params(self, o: int, j: np.ndarray, k: np.ndarray, cache: dict) -> np.ndarray:
        """Hyperparameters of components ``(j, k)`` of output ``o``, (B, P); ``j`` ascending.

        From the kept array, or drawn again from :attr:`phi_draws` (``cache`` holds the
        blocks of draws between calls)."""
        if self._log_params is not None or self.phi_draws is None:
            return self.log_params[o][j, k]
        lo = int(j[0])
        return self.phi_draws.between(lo, int(j[-1]) + 1, cache)[j - lo, k]

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
                progress: Callable[[float], None] | None = None,
                executor: Executor | None = None) -> DiscrepancyPrediction:
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
        executor : concurrent.futures.Executor, optional
            Runs the blocks of components (see "Chunks and executors" in
            :mod:`mdcore.discrepancy`); the numbers are identical to the serial run's.
            Default: in this process.

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
        executor = check_executor(executor)
        distinct, inverse = distinct_rows(X_star)
        if distinct.shape[0] < X_star.shape[0]:     # replicates: predict each input once
            pred = self.predict(distinct, prune=prune, progress=progress, executor=executor)
            return DiscrepancyPrediction(*(field[inverse] for field in pred))
        Ys = _simulate(self.simulate, X_star, self.theta, self.n_out)     # (S, N*, n_out)
        M, K = X_star.shape[0], self.log_weights.shape[2]
        N, d_y, P = self.X.shape[0], self.n_out, 2 + self.n_out + self.X.shape[1]
        if self.backend == "numba":     # pairs per compiled call: ~20 blocks an output
            block = max(MIN_FUSED_BLOCK, -(-self.log_weights[0].size // 20))
        else:           # pairs per NumPy chunk, in BLOCK_BYTES of temporaries
            block = max(1, int(BLOCK_BYTES // (8 * (M * (d_y + 6) + N * (d_y + 2) + P))))
        kept = self._kept(prune)
        total = sum(max(1, -(-idx.size // block)) for idx, _ in kept)
        done = 0
        jitter = JitterLog()
        out = np.empty((4, M, self.n_out))
        for o, (idx, _) in enumerate(kept):
            w = self.log_weights[o].ravel()[idx]
            w -= logsumexp(w)
            np.exp(w, out=w)                                # renormalised over kept
            z_o = self.z[:, o]
            ys_o = np.ascontiguousarray(Ys[..., o])          # (S, N*)

            # Reference: the heaviest component; sums are taken about it (no cancellation).
            j0, k0 = divmod(int(idx[int(np.argmax(w))]), K)
            lp0 = self._params(o, np.array([j0]), np.array([k0]), {})
            ref = gp.predict(lp0, self.Y[[j0]], self.X, z_o, Ys[[j0]], X_star,
                             backend=self.backend)
            cz, cd = ref.mean[0], ref.mean[0] - ys_o[j0]
            blocks = list(_blocks(idx.size, block))

            def payloads(o=o, idx=idx, w=w, z_o=z_o, ys_o=ys_o, cz=cz, cd=cd, blocks=blocks):
                draws = dict()         # block of φ draws -> array (PriorDraws.between)
                for sel in blocks:
                    j, k = np.divmod(idx[sel], K)
                    lp = self._params(o, j, k, draws)        # (B, P)
                    Y, Y_star, y_star_out = self.Y, Ys, ys_o
                    if executor is not None:     # send only the θ rows the block uses
                        rows, j = np.unique(j, return_inverse=True)
                        Y, Y_star, y_star_out = Y[rows], Y_star[rows], y_star_out[rows]
                    yield (lp, Y, j, self.X, z_o, Y_star, y_star_out, w[sel], X_star, cz, cd,
                           self.backend)

            acc = np.zeros((4, M))                          # Σw dz, Σw dδ, Σw(..z²), Σw(..δ²)
            with contextlib.closing(_in_order(executor, _mixture_chunk, payloads())) as results:
                for sel, (part, bad, counts) in zip(blocks, results):
                    acc += part                              # block order: reproducible
                    if counts is not None:
                        jitter.record(*counts)
                    if np.any(bad):
                        warnings.warn(f"{int(bad.sum())} component(s) of output {o} could not "
                                      "be factorised and were dropped from the mixture (weight "
                                      f"{float(w[sel][bad].sum()):.3g}).",
                                      NumericalWarning, stacklevel=2)
                    done += 1
                    if progress is not None:
                        progress(min(done / total, 1.0))
            out[0, :, o] = cz + acc[0]
            out[1, :, o] = np.maximum(acc[2] - acc[0] ** 2, 0.0)
            out[2, :, o] = cd + acc[1]
            out[3, :, o] = np.maximum(acc[3] - acc[1] ** 2, 0.0)
        jitter.warn("predict")
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


def _nlml_rows(blocks: Iterable[tuple[slice, np.ndarray]], S: int, K: int, Y, X, z,
               backend, executor, jitter: JitterLog,
               progress: Callable[[float], None] | None = None, abandon: bool = False
               ) -> tuple[np.ndarray, np.ndarray]:
    """``−NLML`` (Eq. 15) of every pair ``(φ^(j,k), Y[j])`` and output, one chunk of θ rows
    at a time, on ``executor`` or here.

    With ``abandon``, the pairs whose weight is provably negligible are not computed:
    the first :data:`PILOT_PAIRS` pairs are (their best NLML per output, ``best``), then
    every pair whose NLML exceeds ``stop = best + log(S K / ABANDON_MASS)`` gets
    ``−inf`` (:func:`mdcore.gp.neg_log_marginal_likelihood`'s ``stop``). Each such pair's
    normalised weight is below ``ABANDON_MASS / (S K)``, as the normaliser is at least
    the best pair's weight; so their total is below :data:`ABANDON_MASS`. The pilot is
    fixed, so the numbers do not depend on the executor or the threads.

    Parameters
    ----------
    blocks : iterable of (slice, ndarray of shape (R, K, P))
        The θ rows of each chunk and their φ draws, in row order, covering ``0:S``; made
        lazily, so only the chunks in flight are held.
    S, K : int
        θ rows and draws per row.
    Y : ndarray of shape (S, N, n_out)
    X : ndarray of shape (N, d_x)
    z : ndarray of shape (N, n_out)
        The outputs to weigh (a column slice for one output).
    backend : {"numpy", "numba"}
    executor : concurrent.futures.Executor or None
    jitter : JitterLog
        Receives the compiled backend's jitter counts.
    progress : callable, optional
        Called with the fraction of rows done after each chunk.
    abandon : bool, default=False
        Leave out the negligible pairs (above).

    Returns
    -------
    log_weights : ndarray of shape (n_out, S, K)
    stop : ndarray of shape (n_out,)
        The NLML cut per output (``inf`` without ``abandon``).
    """
    log_weights = np.empty((z.shape[1], S, K))
    stop = np.full(z.shape[1], np.inf)
    steps: collections.deque = collections.deque()
    blocks = iter(blocks)

    def payloads(chunks):
        for sl, phi in chunks:
            steps.append(sl)
            yield phi, Y[sl], X, z, backend, stop.copy()

    def collect(chunks):
        with contextlib.closing(_in_order(executor, _weights_chunk, payloads(chunks))) as results:
            for part, counts in results:
                sl = steps.popleft()
                log_weights[:, sl] = part
                if counts is not None:
                    jitter.record(*counts)
                if progress is not None:
                    progress(sl.stop / S)

    if abandon:
        first = next(blocks, None)
        if first is not None:
            sl, phi = first
            r0 = min(phi.shape[0], -(-PILOT_PAIRS // K))
            pilot = slice(sl.start, sl.start + r0)
            collect([(pilot, phi[:r0])])
            best = -np.max(log_weights[:, pilot].reshape(z.shape[1], -1), axis=1)
            stop[:] = np.where(np.isfinite(best), best + np.log(S * K / ABANDON_MASS), np.inf)
            lw = log_weights[:, pilot]
            lw[lw < -stop[:, None, None]] = -np.inf      # the rule, on the pilot too
            if r0 < phi.shape[0]:
                blocks = itertools.chain([(slice(pilot.stop, sl.stop), phi[r0:])], blocks)
    collect(blocks)
    return log_weights, stop


def _row_blocks(phi: np.ndarray):
    """``(slice, phi[slice])`` over chunks of about :data:`WEIGHT_PAIRS` pairs."""
    for sl in _blocks(phi.shape[0], max(1, WEIGHT_PAIRS // phi.shape[1])):
        yield sl, phi[sl]


def _prior_proposal(Y, X, z, prior, n_phi, rng, progress, backend, executor, jitter):
    """Scenario 3 as in the paper: φ^(j,k) ~ p(φ), shared by the outputs (common random
    numbers); ``log w_jk = −NLML`` (Eq. 15), normalised jointly over (j, k) per output.

    The draws are made chunk by chunk from one stream (the same numbers as one big draw)
    and weighed as they come; they are kept when they fit in :data:`KEEP_DRAWS_BYTES`,
    else only the generator state before each chunk is (:class:`PriorDraws`).

    The pairs whose weights are negligible are left out (``−inf``), :func:`_nlml_rows`.

    Returns ``(log_params (n_out, S, N_φ, P) or None, log_weights (n_out, S, N_φ),
    PriorDraws, abandoned (n_out,))``, ``abandoned`` a bound on the normalised weight of
    the pairs left out (below :data:`ABANDON_MASS`).
    """
    n_out, S, P = z.shape[1], Y.shape[0], prior.size
    rows = max(1, WEIGHT_PAIRS // n_phi)
    keep = 8 * S * n_phi * P <= KEEP_DRAWS_BYTES
    phi = np.empty((S, n_phi, P)) if keep else None
    states = list()           # generator state before each chunk

    def blocks():
        for sl in _blocks(S, rows):                 # one stream, drawn in pieces
            states.append(rng.bit_generator.state)
            draws = prior.sample((sl.stop - sl.start) * n_phi, seed=rng).reshape(-1, n_phi, P)
            if phi is not None:
                phi[sl] = draws
            yield sl, draws

    log_weights, stop = _nlml_rows(blocks(), S, n_phi, Y, X, z, backend, executor, jitter,
                                   progress, abandon=ABANDON_MASS > 0)
    abandoned = np.zeros(n_out)
    for o in range(n_out):
        log_norm = _normalise(log_weights[o], o)
        # each pair at −inf (left out, or failed) has NLML > stop[o]: weight < e^(−stop)
        n_out_pairs = np.count_nonzero(log_weights[o] == -np.inf)
        if n_out_pairs and np.isfinite(stop[o]):
            abandoned[o] = n_out_pairs * np.exp(-stop[o] - log_norm)
    draws = PriorDraws(prior, S, n_phi, rows, tuple(states))
    log_params = None if phi is None else np.broadcast_to(phi, (n_out, S, n_phi, P))
    return log_params, log_weights, draws, abandoned


def _adaptive_proposal(Y, X, z, prior, n_phi, rng, progress, backend, executor, jitter):
    """Scenario 3 with adaptive importance sampling of φ per output
    (:func:`mdcore.importance.adaptive_importance_sampling`): the same budget of N_φ draws
    per θ, drawn in stages from the prior and then from Student-t fits to the weighted
    draws, with deterministic-mixture weights normalised jointly over (j, k)."""
    n_out, S = z.shape[1], Y.shape[0]
    log_params = np.empty((n_out, S, n_phi, prior.size))
    log_weights = np.empty((n_out, S, n_phi))
    for o in range(n_out):
        def loglik(phi, o=o):                                                   # Eq. 15
            return _nlml_rows(_row_blocks(phi), S, phi.shape[1], Y, X, z[:, o:o + 1],
                              backend, executor, jitter)[0][0]

        def report(f, o=o):
            if progress is not None:
                progress((o + f) / n_out)

        try:
            out = adaptive_importance_sampling(loglik, prior, S, n_phi, seed=rng,
                                               progress=report)
        except ValueError:
            raise ValueError(_all_zero_message(o)) from None
        log_params[o], log_weights[o] = out.samples, out.log_weights
    return log_params, log_weights, None, np.zeros(n_out)


def _all_zero_message(o: int) -> str:
    return (f"every scenario-3 component of output {o} has zero likelihood (no covariance "
            "matrix could be factorised); check phi_prior, whose samples give "
            "non-positive-definite covariances.")


def _normalise(log_weights: np.ndarray, o: int) -> float:
    """Normalise one output's log weights in place (logsumexp over all pairs = 0); returns
    the log normaliser."""
    norm = logsumexp(log_weights)
    if not np.isfinite(norm):
        raise ValueError(_all_zero_message(o))
    log_weights -= norm
    return float(norm)


@single_threaded_blas    # the adaptive proposal's small solves (measured: 0.25 s under load)
def infer_discrepancy(simulate: Callable, theta_samples, X, z, *, scenario, theta_map=None,
          n_phi: int = 500, phi_prior: GaussianPrior | None = None, seed=None,
          log_params_hat=None, fit_options: dict | None = None, prune: float = PRUNE,
          proposal: str = "prior", backend: str | None = None,
          progress: Callable[[float], None] | None = None,
          executor: Executor | None = None) -> DiscrepancyModel:
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
    executor : concurrent.futures.Executor, optional
        Runs scenario 3's chunks of (θ, φ) pairs (see "Chunks and executors" in
        :mod:`mdcore.discrepancy`), for example a ``ProcessPoolExecutor`` or a Dask
        ``Client(...).get_executor()``; the numbers are identical to the serial run's.
        Scenarios 1–2 have no pair chunks here (their pairs are in
        :meth:`DiscrepancyModel.predict`, which takes an executor too). Default: in this
        process.

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
    executor = check_executor(executor)
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
    if scenario == 3:       # refuse an absurd budget before any simulator run
        from .pipeline import MAX_N_PHI, MAX_PAIRS
        n_phi = as_int(n_phi, "n_phi", 1, MAX_N_PHI)
        if theta.shape[0] * n_phi > MAX_PAIRS:
            raise ValueError(f"N_s × n_phi must be at most {MAX_PAIRS:,} (θ, φ) pairs; received "
                             f"{theta.shape[0]:,} × {n_phi:,}. Lower N_s or n_phi.")
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
                fits.append(fit_hyperparameters(
                    Y_map, X, z[:, o], seed=rng, **options, progress=None if progress is None
                    else (lambda f, o=o: progress((o + f) / n_out))))
                if progress is not None:
                    progress((o + 1) / n_out)
            log_params_hat_arr = np.array([f.log_params for f in fits])
        nlml_hat = np.array([float(gp.neg_log_marginal_likelihood(log_params_hat_arr[o], Y_map,
                                                                  X, z[:, o], backend=backend))
                             for o in range(n_out)])
        log_params = np.broadcast_to(log_params_hat_arr[:, None, None, :], (n_out, S, 1, P))
        log_weights = np.full((n_out, S, 1), -np.log(S))
        prior, phi_draws = None, None
    else:
        n_phi = as_int(n_phi, "n_phi", 1)
        prior = default_phi_prior(Y[0], X, z[:, 0]) if phi_prior is None else phi_prior
        jitter = JitterLog()
        propose = _prior_proposal if proposal == "prior" else _adaptive_proposal
        log_params, log_weights, phi_draws, abandoned = propose(
            Y, X, z, prior, n_phi, rng, progress, backend, executor, jitter)
        jitter.warn("neg_log_marginal_likelihood")
        k_hat = np.array([psis(log_weights[o].ravel()).k_hat for o in range(n_out)])
        if proposal == "adaptive":      # Pareto-smoothed weights (Vehtari et al. 2024)
            log_weights = np.stack([psis(log_weights[o].ravel()).log_weights.reshape(S, -1)
                                    for o in range(n_out)])
    model = DiscrepancyModel(scenario, simulate, theta, Y, X, z, log_params, log_weights,
                             log_params_hat_arr, nlml_hat, prune, prior,
                             time.perf_counter() - start, proposal if scenario == 3 else None,
                             k_hat if scenario == 3 else None, backend, phi_draws,
                             abandoned if scenario == 3 else None)
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
