"""Discrepancy inference: the GP map {y = η(X, θ), X} -> z, scenarios 1–3 (paper Section 2).

Per output a zero-mean GP maps all simulator outputs ``y`` (``d_y = n_out``) and the inputs
``X`` to ``z``. A scenario is a Gaussian mixture over components ``(θ^(j), φ^(j,k))``:

- scenario 1: θ_MAP with the empirical-Bayes φ̂ (Eq. 8);
- scenario 2: N_s samples θ^(j) with φ̂ and ``w_j = 1/N_s`` (Eq. 13);
- scenario 3: N_s × N_φ components, φ^(j,k) from the prior (or an adaptive proposal),
  ``log w_jk = −NLML`` normalised jointly (Eq. 15).

The mixture moments are summed about the heaviest component, so large means do not cancel
small variances. The (θ, φ) pairs go in chunks that depend on the problem size only, each
one call of a module-level function, so ``executor=`` (any ``concurrent.futures.Executor``,
e.g. Dask's) runs them with the serial run's numbers (results reduced in chunk order).
"""

from __future__ import annotations

import collections
import contextlib
import time
import warnings
from collections.abc import Callable, Generator, Iterable
from concurrent.futures import Executor
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np
from scipy.special import logsumexp

from . import _compiled as compiled
from . import _gp as gp
from ._exceptions import (
    K_HAT_THRESHOLD,
    LOW_ESS,
    LowESSWarning,
    NumericalWarning,
    output_label,
    weights_advice,
)
from ._hyperfit import FitOptions, default_bounds, fit_hyperparameters
from ._importance import adaptive_importance_sampling, psis, resample
from ._linalg import JitterLog
from ._priors import GaussianPrior
from ._threads import single_threaded_blas
from ._validation import as_float_array, as_int, as_outputs, check_type, choose

SCENARIOS = (1, 2, 3)
PROPOSALS = ("prior", "adaptive")
#: Components below ``PRUNE × max`` weight are skipped by the prediction (reported).
PRUNE = 1e-12
#: The adaptive proposal predicts at M inputs from PREDICT_WORK // M pairs drawn by weight,
#: 1 to 10 × PREDICT_DRAWS (all if fewer): its mean's error has an sd ≤ 1 / √PREDICT_DRAWS
#: (2.2 %) of the predictive sd, whatever the ESS (docs/scenario3.md).
PREDICT_DRAWS, PREDICT_WORK = 2_000, 800_000
#: Largest N_s, N_φ and pairs accepted: beyond them the work would not fit in memory.
MAX_N_S = 100_000
MAX_N_PHI = 100_000
MAX_PAIRS = 100_000_000
#: Bytes of one NumPy prediction block; fewest pairs per compiled block; pairs per chunk
#: of the weights; chunks in flight.
BLOCK_BYTES = 32 * 2**20
MIN_FUSED_BLOCK = 2048
WEIGHT_PAIRS = 100_000
IN_FLIGHT = 32
#: Scenario 3's draws are kept up to this many bytes, else redrawn (:class:`PriorDraws`).
KEEP_DRAWS_BYTES = 64 * 2**20


class DiscrepancyPrediction(NamedTuple):
    """Mixture moments, each (N*, n_out): bias-corrected ``z_mean``, ``z_var`` (with σ_n²),
    and the latent discrepancy ``delta_mean``, ``delta_var``."""

    z_mean: np.ndarray
    z_var: np.ndarray
    delta_mean: np.ndarray
    delta_var: np.ndarray


@dataclass(frozen=True, eq=False)
class DiscrepancyOptions:
    """Settings of :func:`infer_discrepancy`, validated on construction.

    Parameters
    ----------
    n_phi : int, default=500
        Hyperparameter samples per θ sample (scenario 3).
    phi_prior : GaussianPrior, optional
        Prior of the log hyperparameters (P = 2 + n_out + d_x). Scenario 3 samples from it
        (default :func:`default_phi_prior`); scenarios 1–2 use it as the hyperprior of the
        φ̂ fit (default none: plain empirical Bayes, Eq. 8).
    proposal : {"adaptive", "prior"}, default="adaptive"
        Scenario 3's N_φ draws of φ per θ: in adaptive stages (reliable weights,
        :func:`mdcore._importance.adaptive_importance_sampling`), or the paper's prior draws.
    prune : float, default=1e-12
        See :attr:`DiscrepancyModel.prune`.
    backend : {"auto", "numpy", "numba"} or None, default="auto"
        Scenario 3's kernels: NumPy (the reference) or :mod:`mdcore._compiled`; None reads
        ``MDCORE_BACKEND``.
    fit : FitOptions, optional
        The φ̂ search of scenarios 1–2.
    log_params_hat : ndarray of shape (n_out, P), optional
        φ̂ from an earlier scenario-1 fit, to skip refitting (scenarios 1–2).
    """

    n_phi: int = 500
    phi_prior: GaussianPrior | None = None
    proposal: str = "adaptive"
    prune: float = PRUNE
    backend: str = "auto"
    fit: FitOptions = FitOptions()
    log_params_hat: np.ndarray | None = None

    def __post_init__(self):
        object.__setattr__(self, "n_phi", as_int(self.n_phi, "n_phi", 1, MAX_N_PHI))
        check_type(self.phi_prior, (GaussianPrior, type(None)), "phi_prior",
                   "a GaussianPrior or None")
        choose(self.proposal, "proposal", PROPOSALS)
        object.__setattr__(self, "prune", check_prune(self.prune))
        object.__setattr__(self, "backend", compiled.resolve_backend(self.backend))


def default_phi_prior(Y, X, z) -> GaussianPrior:
    """A weak prior on the log hyperparameters of ``Y`` (N, d_y), ``X`` (N, d_x), ``z`` (N,):
    mean the centre of :func:`mdcore._hyperfit.default_bounds`' box, ±2 sd spanning it."""
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


def check_prune(value) -> float:
    """``prune`` as a float in [0, 1) (a fraction of the largest weight)."""
    try:
        p = float(value)
    except (TypeError, ValueError):
        p = np.nan
    if not np.isfinite(p) or p < 0 or p >= 1:
        raise ValueError(f"prune must be in [0, 1) (a fraction of the largest weight; 0 keeps "
                         f"every component); received {value!r}.")
    return p


def simulated(simulate: Callable, X: np.ndarray, theta: np.ndarray, n_out: int, *,
              finite: bool = True) -> np.ndarray:
    """``simulate(X, theta)``, checked: shape (n_theta, N, n_out), and finite if ``finite``."""
    y = np.asarray(simulate(X, theta), dtype=np.float64)
    want = (theta.shape[0], X.shape[0], n_out)
    if y.shape != want:
        raise ValueError(f"simulate(X, theta) must return shape (n_theta, N, n_out) = {want}; "
                         f"it returned {y.shape}.")
    if finite and not np.all(np.isfinite(y)):
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
    """``fn(*args)`` for each ``args`` of ``payloads``, in order: here, one at a time, or on
    ``executor`` with up to :data:`IN_FLIGHT` calls ahead of the one awaited; when the consumer
    stops early (an exception, a cancel), the calls not yet collected are cancelled."""
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


def _counts(log: JitterLog) -> tuple:
    return log.jittered, log.failed, log.max_jitter


def _weights_chunk(phi: np.ndarray, Y: np.ndarray, X: np.ndarray, z: np.ndarray,
                   backend: str) -> tuple[np.ndarray, tuple]:
    """``−NLML`` (Eq. 15), (n_out, R, K), of ``phi`` (R, K, P) on ``Y`` (R, N, n_out), and
    the jitter counts for the caller to report once."""
    R, K, P = phi.shape
    log = JitterLog()
    if backend == "numba":          # the outputs share each pair's factor
        pairs = compiled.Pairs(phi.reshape(R * K, P), np.repeat(np.arange(R), K), Y, X, z)
        out = -compiled.nlml(pairs, log).T.reshape(z.shape[1], R, K)
        return out, _counts(log)
    out = np.empty((z.shape[1], R, K))
    for o in range(z.shape[1]):
        out[o] = -gp.neg_log_marginal_likelihood(phi, Y[:, None], X, z[:, o], jitter_log=log)
    return out, _counts(log)


@single_threaded_blas       # one BLAS thread, as on a Dask worker: the same sums everywhere
def _mixture_chunk(pairs: compiled.Pairs, test: compiled.Test, backend: str
                   ) -> tuple[np.ndarray, np.ndarray, tuple]:
    """:func:`mdcore._compiled.mixture_sums` of one block of one output: ``acc`` (4, M), the
    components left out (B,) and the jitter counts."""
    log = JitterLog()
    if backend == "numba":
        acc, bad = compiled.mixture_sums(pairs, test, log)
        return acc, bad, _counts(log)
    theta, j, Y, X, z = pairs
    p = gp.predict(theta, Y[j], X, z, test.Y_star[j], test.X_star)
    mean, var, sn2, ystar = p.mean, p.var, p.noise_var[:, None], test.y_out[j]
    bad = ~np.all(np.isfinite(mean) & np.isfinite(var), axis=1)
    w = test.weight
    if np.any(bad):
        w = np.where(bad, 0.0, w)
        mean = np.where(bad[:, None], 0.0, mean)
        var = np.where(bad[:, None], 0.0, var)
    dz = mean - test.centre[0]
    dd = mean - ystar - test.centre[1]
    acc = np.stack([w @ dz, w @ dd,
                    w @ (var + sn2 + dz * dz),   # Eq. 13/15: total variance of z*
                    w @ (var + dd * dd)])        # latent variance goes to δ
    return acc, bad, (0, 0, 0.0)                # gp.predict warned itself


@dataclass(frozen=True, eq=False)
class PriorDraws:
    """Scenario 3's prior draws as their random stream: block ``b`` of θ rows is drawn
    again, bit for bit, from the generator state ``states[b]``."""

    prior: GaussianPrior
    n_theta: int
    n_phi: int
    rows: int
    states: tuple      # the generator's ``bit_generator.state`` before each block's draws

    def block(self, b: int) -> np.ndarray:
        state = self.states[b]
        bit_generator = getattr(np.random, state["bit_generator"])()
        bit_generator.state = state
        n_rows = min(self.n_theta, (b + 1) * self.rows) - b * self.rows
        return self.prior.sample(n_rows * self.n_phi, seed=np.random.Generator(bit_generator)
                                 ).reshape(n_rows, self.n_phi, self.prior.size)

    def between(self, lo: int, hi: int, cache: dict | None = None) -> np.ndarray:
        """The draws of θ rows ``lo`` to ``hi − 1``, (hi − lo, N_φ, P); ``cache`` keeps
        blocks between calls that go through the rows in order."""
        first, last = lo // self.rows, (hi - 1) // self.rows
        cache = {} if cache is None else cache
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


@dataclass(frozen=True, eq=False)
class DiscrepancyModel:
    """A fitted discrepancy mixture; call :meth:`predict` for z* and δ*.

    Attributes
    ----------
    theta : ndarray of shape (S, p)
        The θ of the mixture (S = 1 for scenario 1); ``Y`` (S, N, n_out) = ``η(X, θ^(j))``.
    log_params : ndarray of shape (n_out, S, K, P)
        Every component's hyperparameters (K = 1 for scenarios 1–2, N_φ for 3), redrawn
        from :attr:`phi_draws` when too large to keep.
    log_weights : ndarray of shape (n_out, S, K)
        Normalised log weights (``logsumexp`` over (S, K) is 0 per output).
    log_params_hat, nlml_hat : ndarray of shape (n_out, P) and (n_out,), or None
        Scenarios 1–2: φ̂, and the NLML there on ``y(θ_MAP)``.
    prune : float
        Components below ``prune × max`` weight are skipped in :meth:`predict`.
    k_hat : ndarray of shape (n_out,) or None
        Scenario 3: Pareto shape of each output's raw weights (above 0.7: unreliable).
    draw_seed : int or None
        Adaptive proposal: seeds the pairs :meth:`predict` draws by weight
        (:data:`PREDICT_DRAWS`).
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
    draw_seed: int | None = None

    @property
    def n_out(self) -> int:
        return self.z.shape[1]

    @property
    def log_params(self) -> np.ndarray:
        """Hyperparameters of every component, (n_out, S, K, P) (see the class)."""
        if self._log_params is None:
            if self.phi_draws is None:
                raise ValueError("this model has neither log_params nor phi_draws.")
            phi = self.phi_draws.between(0, self.phi_draws.n_theta)
            object.__setattr__(self, "_log_params",
                               np.broadcast_to(phi, (self.n_out,) + phi.shape))
        assert self._log_params is not None
        return self._log_params

    def _params(self, o: int, j: np.ndarray, k: np.ndarray, cache: dict) -> np.ndarray:
        """Hyperparameters (B, P) of components ``(j, k)``, ``j`` ascending, of output ``o``."""
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

    def _kept(self, prune: float | None = None, m: int = PREDICT_WORK // PREDICT_DRAWS):
        """Per output: flat indices, weights (sum 1) and skipped mass of the components
        :meth:`predict` evaluates at ``m`` inputs (``prune`` None: as :meth:`predict`)."""
        n = min(max(PREDICT_DRAWS, PREDICT_WORK // m), 10 * PREDICT_DRAWS)
        rng, p = np.random.default_rng(self.draw_seed), self.prune if prune is None else prune
        out = []
        for o in range(self.n_out):
            lw = self.log_weights[o].ravel()
            if prune is None and self.draw_seed is not None and n < lw.size:
                idx, counts = resample(lw, n, rng)
                out.append((idx, counts / n, 0.0))
                continue
            cut = lw.max() + np.log(p) if p > 0 else -np.inf
            keep = np.isfinite(lw) & (lw >= cut)
            skipped = float(np.exp(logsumexp(lw[~keep]))) if np.any(~keep) else 0.0
            idx = np.flatnonzero(keep)
            w = np.exp(lw[idx] - logsumexp(lw[idx]))               # renormalised over kept
            out.append((idx, w, skipped))
        return out

    @property
    def skipped_mass(self) -> np.ndarray:
        """Normalised weight mass that :meth:`predict` skips, (n_out,)."""
        return np.array([s for *_, s in self._kept()])

    @property
    def n_components(self) -> np.ndarray:
        """Components :meth:`predict` evaluates per output at 400 inputs or more, (n_out,)."""
        return np.array([idx.size for idx, *_ in self._kept()])

    def predict(self, X_star, *, prune: float | None = None,
                progress: Callable[[float], None] | None = None,
                executor: Executor | None = None) -> DiscrepancyPrediction:
        """Bias-corrected prediction and discrepancy at ``X_star`` (N*, d_x) (Eq. 13/15).

        Over pairs drawn by weight if :attr:`draw_seed`, else above :attr:`prune`; a
        ``prune`` given asks for every component above it (0: all). ``progress`` gets the
        fraction done and may raise to cancel; ``executor`` runs the blocks.
        """
        X_star = as_float_array(X_star, "X_star", ndim=2)
        if X_star.shape[1] != self.X.shape[1]:
            raise ValueError(f"X_star must have shape (N*, d_x) with d_x = {self.X.shape[1]} "
                             f"like the training X; received {X_star.shape}.")
        prune = None if prune is None else check_prune(prune)
        executor = check_executor(executor)
        distinct, inverse = np.unique(X_star, axis=0, return_inverse=True)
        if distinct.shape[0] < X_star.shape[0]:     # replicates: predict each input once
            pred = self.predict(distinct, prune=prune, progress=progress, executor=executor)
            return DiscrepancyPrediction(*(a[inverse.reshape(-1)] for a in pred))
        Ys = simulated(self.simulate, X_star, self.theta, self.n_out)     # (S, N*, n_out)
        M, K = X_star.shape[0], self.log_weights.shape[2]
        N, d_y, P = self.X.shape[0], self.n_out, 2 + self.n_out + self.X.shape[1]
        if self.backend == "numba":     # pairs per compiled call: ~20 blocks an output
            block = max(MIN_FUSED_BLOCK, -(-self.log_weights[0].size // 20))
        else:           # pairs per NumPy chunk, in BLOCK_BYTES of temporaries
            block = max(1, int(BLOCK_BYTES // (8 * (M * (d_y + 6) + N * (d_y + 2) + P))))
        kept = self._kept(prune, M)
        total = sum(max(1, -(-idx.size // block)) for idx, *_ in kept)
        done = 0
        jitter = JitterLog()
        out = np.empty((4, M, self.n_out))
        for o, (idx, w, _) in enumerate(kept):
            z_o = self.z[:, o]
            ys_o = np.ascontiguousarray(Ys[..., o])          # (S, N*)
            # The heaviest component is the reference the sums are taken about.
            j0, k0 = divmod(int(idx[int(np.argmax(w))]), K)
            lp0 = self._params(o, np.array([j0]), np.array([k0]), {})
            ref = gp.predict(lp0, self.Y[[j0]], self.X, z_o, Ys[[j0]], X_star).mean[0]
            centre = np.stack([ref, ref - ys_o[j0]])
            blocks = list(_blocks(idx.size, block))

            def payloads(o=o, idx=idx, w=w, z_o=z_o, ys_o=ys_o, centre=centre, blocks=blocks):
                draws: dict = {}       # block of φ draws -> array (PriorDraws.between)
                for sel in blocks:
                    j, k = np.divmod(idx[sel], K)
                    lp = self._params(o, j, k, draws)        # (B, P)
                    Y, Y_star, y_out = self.Y, Ys, ys_o
                    if executor is not None:     # send only the θ rows the block uses
                        rows, j = np.unique(j, return_inverse=True)
                        Y, Y_star, y_out = Y[rows], Y_star[rows], y_out[rows]
                    yield (compiled.Pairs(lp, j, Y, self.X, z_o),
                           compiled.Test(Y_star, y_out, X_star, w[sel], centre), self.backend)

            acc = np.zeros((4, M))                          # Σw dz, Σw dδ, Σw(..z²), Σw(..δ²)
            with contextlib.closing(_in_order(executor, _mixture_chunk, payloads())) as results:
                for sel, (part, bad, counts) in zip(blocks, results):
                    acc += part                              # block order: reproducible
                    jitter.record(*counts)
                    if np.any(bad):
                        warnings.warn(f"{int(bad.sum())} component(s) of output {o} could not "
                                      "be factorised and were dropped from the mixture (weight "
                                      f"{float(w[sel][bad].sum()):.3g}).",
                                      NumericalWarning, stacklevel=2)
                    done += 1
                    if progress is not None:
                        progress(min(done / total, 1.0))
            out[0, :, o] = centre[0] + acc[0]
            out[1, :, o] = np.maximum(acc[2] - acc[0] ** 2, 0.0)
            out[2, :, o] = centre[1] + acc[1]
            out[3, :, o] = np.maximum(acc[3] - acc[1] ** 2, 0.0)
        jitter.warn("predict")
        return DiscrepancyPrediction(out[0], out[1], out[2], out[3])


class _Data(NamedTuple):
    Y: np.ndarray          # (S, N, n_out)
    X: np.ndarray          # (N, d_x)
    z: np.ndarray          # (N, n_out), or one output's column
    backend: str
    executor: Executor | None


def _nlml_rows(blocks: Iterable[tuple[slice, np.ndarray]], K: int, data: _Data,
               jitter: JitterLog, progress: Callable[[float], None] | None = None
               ) -> np.ndarray:
    """``−NLML`` (Eq. 15), (n_out, S, K), of every pair ``(φ^(j,k), Y[j])``; ``blocks``
    yields (slice of θ rows, their φ (R, K, P)) lazily, so only chunks in flight are held."""
    S = data.Y.shape[0]
    log_weights = np.empty((data.z.shape[1], S, K))
    steps: collections.deque = collections.deque()

    def payloads():
        for sl, phi in blocks:
            steps.append(sl)
            yield phi, data.Y[sl], data.X, data.z, data.backend

    with contextlib.closing(_in_order(data.executor, _weights_chunk, payloads())) as results:
        for part, counts in results:
            sl = steps.popleft()
            log_weights[:, sl] = part
            jitter.record(*counts)
            if progress is not None:
                progress(sl.stop / S)
    return log_weights


def _prior_proposal(data: _Data, prior, n_phi, rng, progress, jitter):
    """The paper's scenario 3: φ^(j,k) ~ p(φ) shared by the outputs, ``log w = −NLML``
    (Eq. 15). Returns ``(log_params (n_out, S, N_φ, P) or None, log_weights, PriorDraws)``."""
    n_out, S, P = data.z.shape[1], data.Y.shape[0], prior.size
    rows = max(1, WEIGHT_PAIRS // n_phi)
    phi = np.empty((S, n_phi, P)) if 8 * S * n_phi * P <= KEEP_DRAWS_BYTES else None
    states = list()           # generator state before each chunk

    def blocks():
        for sl in _blocks(S, rows):                 # one stream, drawn in pieces
            states.append(rng.bit_generator.state)
            draws = prior.sample((sl.stop - sl.start) * n_phi, seed=rng).reshape(-1, n_phi, P)
            if phi is not None:
                phi[sl] = draws
            yield sl, draws

    log_weights = _nlml_rows(blocks(), n_phi, data, jitter, progress)
    for o in range(n_out):
        _normalise(log_weights[o], o)
    log_params = None if phi is None else np.broadcast_to(phi, (n_out, S, n_phi, P))
    return log_params, log_weights, PriorDraws(prior, S, n_phi, rows, tuple(states))


def _adaptive_proposal(data: _Data, prior, n_phi, rng, progress, jitter):
    """Scenario 3 with adaptive importance sampling of φ per output."""
    n_out, S = data.z.shape[1], data.Y.shape[0]
    log_params = np.empty((n_out, S, n_phi, prior.size))
    log_weights = np.empty((n_out, S, n_phi))
    for o in range(n_out):
        one = data._replace(z=data.z[:, o:o + 1])

        def loglik(phi, one=one):                                               # Eq. 15
            rows = _blocks(S, max(1, WEIGHT_PAIRS // phi.shape[1]))
            return _nlml_rows(((sl, phi[sl]) for sl in rows), phi.shape[1], one, jitter)[0]

        def loglik_grad(phi, j, o=o):       # Eq. 9 and its gradient: the Laplace stage
            return tuple(-v for v in gp.nlml_and_gradient(phi, data.Y[j], data.X,
                                                          data.z[:, o], jitter_log=JitterLog()))

        def report(f, o=o):
            if progress is not None:
                progress((o + f) / n_out)

        try:
            out = adaptive_importance_sampling(loglik, prior, S, n_phi, seed=rng,
                                               log_likelihood_grad=loglik_grad,
                                               progress=report)
        except ValueError:
            raise ValueError(_all_zero_message(o)) from None
        log_params[o], log_weights[o] = out.samples, out.log_weights
    return log_params, log_weights, None


def _all_zero_message(o: int) -> str:
    return (f"every scenario-3 component of output {o} has zero likelihood (no covariance "
            "matrix could be factorised); check phi_prior, whose samples give "
            "non-positive-definite covariances.")


def _normalise(log_weights: np.ndarray, o: int) -> None:
    """Normalise one output's log weights in place."""
    norm = logsumexp(log_weights)
    if not np.isfinite(norm):
        raise ValueError(_all_zero_message(o))
    log_weights -= norm


def _fit_phi_hat(Y_map, X, z, options, rng, progress):
    """φ̂ of scenarios 1–2 (Eq. 8 on ``Y_map = y(X, θ_MAP)``), and the NLML there."""
    n_out = z.shape[1]
    P = 2 + n_out + X.shape[1]
    if options.log_params_hat is not None:
        hat = np.atleast_2d(as_float_array(options.log_params_hat, "log_params_hat"))
        if hat.shape != (n_out, P):
            raise ValueError(f"log_params_hat must have shape (n_out, P) = ({n_out}, {P}); "
                             f"received {hat.shape}.")
    else:
        hat = np.empty((n_out, P))
        for o in range(n_out):
            hat[o] = fit_hyperparameters(
                Y_map, X, z[:, o], log_prior=options.phi_prior, seed=rng, options=options.fit,
                progress=None if progress is None
                else (lambda f, o=o: progress((o + f) / n_out))).log_params
            if progress is not None:
                progress((o + 1) / n_out)
    nlml = np.array([float(gp.neg_log_marginal_likelihood(hat[o], Y_map, X, z[:, o]))
                     for o in range(n_out)])
    return hat, nlml


@single_threaded_blas
def infer_discrepancy(simulate: Callable, theta_samples, X, z, *, scenario, theta_map=None,
                      options: DiscrepancyOptions | None = None, seed=None,
                      progress: Callable[[float], None] | None = None,
                      executor: Executor | None = None) -> DiscrepancyModel:
    """Infer the model discrepancy by one of the three scenarios (paper Section 2).

    Parameters
    ----------
    simulate : callable
        ``simulate(X, theta) -> (n_theta, N, n_out)``.
    theta_samples : ndarray of shape (N_s, p)
        Calibration samples (unused by scenario 1).
    X : ndarray of shape (N, d_x)
    z : ndarray of shape (N, n_out) or (N,)
    scenario : {1, 2, 3}
    theta_map : ndarray of shape (p,), optional
        Where scenarios 1–2 fit φ̂ (scenario 2 may get ``options.log_params_hat`` instead).
    options : DiscrepancyOptions, optional
    seed : int or numpy.random.Generator, optional
        Seeds the empirical-Bayes swarm and the φ draws.
    progress : callable, optional
        Fraction done in [0, 1]; raising from it cancels.
    executor : concurrent.futures.Executor, optional
        Runs scenario 3's chunks of pairs (module docstring), with the serial run's numbers.

    Warns
    -----
    LowESSWarning
        Scenario 3, when an output's ESS is below :data:`LOW_ESS` or k̂ above 0.7.
    """
    start = time.perf_counter()
    options = check_type(DiscrepancyOptions() if options is None else options,
                         DiscrepancyOptions, "options", "a DiscrepancyOptions")
    scenario = _scenario(scenario)
    X = as_float_array(X, "X", ndim=2)
    z = as_outputs(z, X.shape[0])
    n_out, P = z.shape[1], 2 + z.shape[1] + X.shape[1]
    rng = np.random.default_rng(seed)
    executor = check_executor(executor)
    if options.phi_prior is not None and options.phi_prior.size != P:
        raise ValueError(f"phi_prior must be a GaussianPrior over P = 2 + n_out + d_x = {P} "
                         f"log hyperparameters ([log σ_f, log ℓ_y×{n_out}, log ℓ_x×"
                         f"{X.shape[1]}, log σ_n]); received {options.phi_prior!r}.")
    if scenario in (1, 2) and options.log_params_hat is None and theta_map is None:
        raise ValueError(f"scenario {scenario} needs theta_map (φ̂ is fitted by empirical Bayes "
                         "at θ_MAP); pass HistoryMatchResult.theta_map, or log_params_hat.")
    if theta_map is not None and scenario in (1, 2):
        theta_map = as_float_array(theta_map, "theta_map", ndim=1)
    if scenario == 1:
        theta = theta_map[None, :]
    else:
        theta = as_float_array(theta_samples, "theta_samples", ndim=2)
        if theta_map is not None and scenario == 2 and theta.shape[1] != theta_map.size:
            raise ValueError(f"theta_samples must have shape (N_s, p) with p = {theta_map.size} "
                             f"like theta_map; received {theta.shape}.")
    S = theta.shape[0]
    if scenario == 3 and S * options.n_phi > MAX_PAIRS:   # before any simulator run
        raise ValueError(f"N_s × n_phi must be at most {MAX_PAIRS:,} (θ, φ) pairs; received "
                         f"{S:,} × {options.n_phi:,}. Lower N_s or n_phi.")
    Y = simulated(simulate, X, theta, n_out)

    hat, nlml_hat, prior, draws, k_hat, draw_seed = None, None, None, None, None, None
    if scenario in (1, 2):
        # Without θ_MAP (scenario 2 given φ̂) the first θ sample stands in for nlml_hat.
        Y_map = Y[0] if scenario == 1 or theta_map is None else \
            simulated(simulate, X, theta_map[None], n_out)[0]
        hat, nlml_hat = _fit_phi_hat(Y_map, X, z, options, rng, progress)
        log_params = np.broadcast_to(hat[:, None, None, :], (n_out, S, 1, P))
        log_weights = np.full((n_out, S, 1), -np.log(S))
    else:
        prior = default_phi_prior(Y[0], X, z[:, 0]) if options.phi_prior is None \
            else options.phi_prior
        jitter = JitterLog()
        propose = _prior_proposal if options.proposal == "prior" else _adaptive_proposal
        log_params, log_weights, draws = propose(
            _Data(Y, X, z, options.backend, executor), prior, options.n_phi, rng, progress,
            jitter)
        jitter.warn("neg_log_marginal_likelihood")
        smoothed = [psis(log_weights[o].ravel()) for o in range(n_out)]
        k_hat = np.array([p.k_hat for p in smoothed])
        if options.proposal == "adaptive":  # Pareto-smoothed weights (Vehtari et al. 2024)
            log_weights = np.stack([p.log_weights.reshape(S, -1) for p in smoothed])
            draw_seed = int(rng.integers(2**63))      # predict draws pairs by weight
    model = DiscrepancyModel(
        scenario=scenario, simulate=simulate, theta=theta, Y=Y, X=X, z=z,
        _log_params=log_params, log_weights=log_weights, log_params_hat=hat,
        nlml_hat=nlml_hat, prune=options.prune, phi_prior=prior,
        seconds=time.perf_counter() - start, k_hat=k_hat, backend=options.backend,
        proposal=options.proposal if scenario == 3 else None, phi_draws=draws,
        draw_seed=draw_seed)
    if scenario == 3:
        for o, (e, k) in enumerate(zip(model.ess, np.asarray(k_hat))):
            if e < LOW_ESS or k > K_HAT_THRESHOLD:
                place = output_label("scenario 3", o, n_out)
                warnings.warn(weights_advice(place, e, S, options.n_phi, k, options.proposal),
                              LowESSWarning, stacklevel=2)
    return model
