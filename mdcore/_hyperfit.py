"""Empirical Bayes and MAP fits of the GP hyperparameters (Eq. 8), and the L-BFGS-B runs
that the emulator and KOH fits share."""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import scipy.optimize

from ._exceptions import ConvergenceWarning
from ._gp import check_problem, neg_log_marginal_likelihood, nlml_and_gradient
from ._linalg import JitterLog
from ._priors import GaussianPrior
from ._threads import single_threaded_blas
from ._validation import as_float_array, as_int, choose

__all__ = ["FitOptions", "HyperFit", "PROJECTED_GRADIENT_TOL", "QPSO_ITERATIONS",
           "default_bounds", "fit_hyperparameters", "lbfgs_converged", "best_lbfgs"]

#: Projected gradient per log hyperparameter below which a stalled L-BFGS-B run counts as
#: converged: a 1 % change of any hyperparameter then moves the objective by < 1e-4.
PROJECTED_GRADIENT_TOL = 1e-2
#: Swarm steps of the QPSO (the default of :func:`fit_hyperparameters`).
QPSO_ITERATIONS = 120


class HyperFit(NamedTuple):
    """The optimum ``log_params`` (P,), its ``nlml`` (Eq. 9), the minimised ``objective``
    (``nlml − log prior`` for MAP), the evaluations used, and whether the L-BFGS-B run
    behind it ``converged`` (False without a polish)."""

    log_params: np.ndarray
    nlml: float
    objective: float
    method: str
    n_evaluations: int
    converged: bool


def default_bounds(Y, X, z) -> np.ndarray:
    """Search box (P, 2) of the log hyperparameters from the data scales: σ_f ∈
    [1e-2, 1e2] s_z (``s_z = √mean z²``), each ℓ ∈ [1e-2, 1e2] × its input's range, σ_n ∈
    [1e-6, 1] s_z."""
    Y = as_float_array(Y, "Y", ndim=2, allow_empty=True)
    X = as_float_array(X, "X", ndim=2, allow_empty=True)
    z = as_float_array(z, "z", ndim=1)
    sz = float(np.sqrt(np.mean(z * z))) or 1.0

    def rng_of(A):
        r = np.ptp(A, axis=0) if A.shape[0] else np.ones(A.shape[1])
        return np.where(r > 0, r, 1.0)

    rows = [[np.log(1e-2 * sz), np.log(1e2 * sz)]]
    rows += [[np.log(1e-2 * r), np.log(1e2 * r)] for r in rng_of(Y)]
    rows += [[np.log(1e-2 * r), np.log(1e2 * r)] for r in rng_of(X)]
    rows += [[np.log(1e-6 * sz), np.log(sz)]]
    return np.array(rows)


def lbfgs_converged(res: scipy.optimize.OptimizeResult, lo: np.ndarray,
                    hi: np.ndarray) -> bool:
    """Whether an L-BFGS-B result is at a local optimum of its box ``lo``, ``hi`` (P,):
    SciPy's ``success``, or a line search that found no descent beyond rounding (typical
    at a bound of an ill-conditioned problem) with the projected gradient below
    :data:`PROJECTED_GRADIENT_TOL`."""
    if res.success:
        return True
    if res.status != 2 or not np.isfinite(res.fun) or res.fun >= 1e300:
        return False
    x, g = np.asarray(res.x, dtype=np.float64), np.asarray(res.jac, dtype=np.float64)
    near = 1e-6 * (hi - lo)
    pushing_out = ((x - lo <= near) & (g > 0)) | ((hi - x <= near) & (g < 0))
    return bool(np.max(np.abs(np.where(pushing_out, 0.0, g)), initial=0.0)
                <= PROJECTED_GRADIENT_TOL)


def lbfgs_advice(res: scipy.optimize.OptimizeResult, iterations: str | None = None) -> str:
    """Why a run :func:`lbfgs_converged` rejects stopped, and what to change."""
    if res.status == 1:
        return "it ran out of iterations" + (f": raise {iterations}" if iterations else "")
    return ("its line search found no descent (the objective or its gradient is inaccurate "
            "there, e.g. an ill-conditioned covariance)")


def best_lbfgs(fun: Callable, starts, lo: np.ndarray, hi: np.ndarray, *, maxiter: int = 15_000,
               progress: Callable[[int], None] | None = None):
    """The best (first of ties) of L-BFGS-B runs from each of ``starts`` (k, P) in the box
    ``lo``, ``hi`` (P,), and the evaluations of all runs; ``fun(x) -> (f, grad)``.
    ``progress(k)`` after every iteration of run ``k`` (it may raise to stop)."""
    best, evals = None, 0
    for k, x0 in enumerate(starts):
        res = scipy.optimize.minimize(
            fun, x0, jac=True, method="L-BFGS-B", bounds=list(zip(lo, hi)),
            options={"maxiter": maxiter},
            callback=None if progress is None else (lambda *_, k=k: progress(k)))
        evals += int(res.nfev)
        if best is None or res.fun < best.fun:
            best = res
    return best, evals


def _qpso(objective: Callable, lo: np.ndarray, hi: np.ndarray, rng, n_particles: int,
          n_iterations: int, step: Callable[[float], None] | None = None):
    """Quantum-behaved PSO (Sun et al. 2004) -> (best x, best f, evals); ``step(fraction)``
    before every iteration (it may raise to stop)."""
    P = lo.size
    x = lo + (hi - lo) * rng.uniform(size=(n_particles, P))
    f = objective(x)
    pbest, pf = x.copy(), f.copy()
    g = int(np.argmin(pf))
    for t in range(n_iterations):
        if step is not None:
            step(t / n_iterations)
        beta = 1.0 - 0.5 * t / max(n_iterations - 1, 1)  # contraction 1.0 -> 0.5
        mbest = pbest.mean(axis=0)
        phi = rng.uniform(size=(n_particles, P))
        p = phi * pbest + (1.0 - phi) * pbest[g]
        u = 1.0 - rng.uniform(size=(n_particles, P))  # in (0, 1]
        sign = np.where(rng.uniform(size=(n_particles, P)) < 0.5, -1.0, 1.0)
        x = np.clip(p + sign * beta * np.abs(mbest - x) * np.log(1.0 / u), lo, hi)
        f = objective(x)
        better = f < pf
        pbest[better], pf[better] = x[better], f[better]
        g = int(np.argmin(pf))
    return pbest[g].copy(), float(pf[g]), n_particles * (n_iterations + 1)


@dataclass(frozen=True)
class FitOptions:
    """How :func:`fit_hyperparameters` searches, validated on construction.

    Parameters
    ----------
    method : {"qpso", "lbfgs"}, default="qpso"
        ``"qpso"``: the paper's particle swarm of ``n_particles`` for ``n_iterations``
        steps, then (``polish``) L-BFGS-B from its best. ``"lbfgs"``: L-BFGS-B from
        ``n_starts`` uniform starts.
    maxiter : int, default=15000
        Iterations of each L-BFGS-B run (SciPy's default).
    """

    method: str = "qpso"
    n_particles: int = 40
    n_iterations: int = QPSO_ITERATIONS
    n_starts: int = 8
    polish: bool = True
    maxiter: int = 15_000

    def __post_init__(self):
        choose(self.method, "method", {"qpso", "lbfgs"})
        for name in ("n_particles", "n_iterations", "n_starts", "maxiter"):
            object.__setattr__(self, name, as_int(getattr(self, name), name, 1))


@single_threaded_blas
def fit_hyperparameters(Y, X, z, *, log_prior: GaussianPrior | None = None, bounds=None,
                        seed=None, options: FitOptions = FitOptions(),
                        progress: Callable[[float], None] | None = None) -> HyperFit:
    """Empirical Bayes (Eq. 8): minimise the NLML over the log hyperparameters, or
    ``NLML − log p(φ)`` (MAP) with ``log_prior``.

    Parameters
    ----------
    Y : ndarray of shape (N, d_y)
    X : ndarray of shape (N, d_x)
    z : ndarray of shape (N,)
    log_prior : GaussianPrior, optional
        Prior over the log vector (MAP).
    bounds : ndarray of shape (P, 2), optional
        Box in log space; default :func:`default_bounds`.
    seed : int or numpy.random.Generator, optional
        Same seed, same result.
    options : FitOptions, optional
    progress : callable, optional
        ``progress(fraction)`` before every swarm iteration and after every L-BFGS-B
        iteration; if it raises (e.g. :class:`mdcore.Cancelled`), the fit stops.

    Returns
    -------
    HyperFit

    Examples
    --------
    >>> X = np.linspace(0, 1, 8)[:, None]; Y = np.sin(3 * X); z = (Y + X)[:, 0]
    >>> fit = fit_hyperparameters(Y, X, z, options=FitOptions("lbfgs", n_starts=2), seed=0)
    >>> fit.log_params.shape
    (4,)
    """
    if not isinstance(options, FitOptions):
        raise ValueError(f"options must be a FitOptions; received {type(options).__name__}.")
    prob = check_problem(np.zeros(2 + np.shape(Y)[-1] + np.shape(X)[-1]), Y, X, z)
    if prob.Y.ndim != 2:
        raise ValueError(f"Y must have shape (N, d_y) for fitting; received {prob.Y.shape}.")
    Y, X, z = prob.Y, prob.X, prob.z
    P = 2 + Y.shape[1] + X.shape[1]
    b = default_bounds(Y, X, z) if bounds is None else as_float_array(bounds, "bounds", ndim=2)
    if b.shape != (P, 2) or np.any(b[:, 0] >= b[:, 1]):
        raise ValueError(f"bounds must have shape (P, 2) = ({P}, 2) with lower < upper; "
                         f"received shape {b.shape}.")
    if log_prior is not None and log_prior.size != P:
        raise ValueError(f"log_prior must have P = {P} entries; received {log_prior.size}.")
    lo, hi = b[:, 0], b[:, 1]
    rng = np.random.default_rng(seed)

    # A swarm tries ill-posed corners on purpose: its jitter goes to a log, unreported.
    trials = JitterLog()

    def batch_objective(theta):
        f = neg_log_marginal_likelihood(theta, Y, X, z, jitter_log=trials)
        return f if log_prior is None else f - log_prior.logpdf(theta)

    def objective_and_grad(theta):
        f, g = nlml_and_gradient(theta, Y, X, z, jitter_log=trials)
        if log_prior is not None:
            f, g = f - float(log_prior.logpdf(theta)), g - log_prior.grad(theta)
        if not np.isfinite(f):
            return 1e300, np.zeros_like(theta)
        return f, g

    converged = False
    if options.method == "qpso":
        best, best_f, evals = _qpso(batch_objective, lo, hi, rng, options.n_particles,
                                    options.n_iterations, None if progress is None
                                    else (lambda f: progress(f / 2)))
        starts = [best] if options.polish else []
    else:
        starts = list(lo + (hi - lo) * rng.uniform(size=(options.n_starts, P)))
        best, best_f, evals = starts[0], np.inf, 0
    if starts:
        res, n = best_lbfgs(objective_and_grad, starts, lo, hi, maxiter=options.maxiter,
                            progress=None if progress is None
                            else (lambda i: progress(0.5 + 0.5 * i / len(starts))))
        evals += n
        converged = lbfgs_converged(res, lo, hi)
        if res.fun < best_f:
            best, best_f = res.x, float(res.fun)
        if not converged:
            warnings.warn(f"fit_hyperparameters: L-BFGS-B did not converge ({res.message}; "
                          f"{lbfgs_advice(res, 'maxiter')}); the hyperparameters may not be "
                          "the optimum. Give tighter bounds or a log_prior if raising maxiter "
                          "does not help.", ConvergenceWarning, stacklevel=2)
    nlml = float(batch_objective(best[None])[0]) if log_prior is None else \
        float(neg_log_marginal_likelihood(best, Y, X, z))
    return HyperFit(np.asarray(best, dtype=np.float64), nlml, float(best_f), options.method,
                    evals, converged)

