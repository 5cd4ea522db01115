"""Batched GP regression of ``z`` on ``{y, x}`` (Eqs. 2–9): NLML, its gradient, prediction.

Leading dimensions of ``log_params`` (..., P) and ``Y`` (..., N, d_y) broadcast; the work runs
in chunks of bounded memory on the compute threads.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import scipy.linalg

from ._kernels import cross_cov, matern32_and_dlog_ell, split_log_params, train_cov
from ._linalg import JitterLog, cholesky, chunks, for_each_chunk, gather, solve_lower_inplace
from ._threads import single_threaded_blas
from ._validation import as_float_array, as_log_params

__all__ = ["LOG_2PI", "GPPrediction", "Problem", "check_problem",
           "neg_log_marginal_likelihood", "predict", "nlml_and_gradient"]

LOG_2PI = np.log(2.0 * np.pi)


class GPPrediction(NamedTuple):
    """Latent ``mean`` and ``var`` (Eq. 7), (..., N*), and ``noise_var`` σ_n² (...)."""

    mean: np.ndarray
    var: np.ndarray
    noise_var: np.ndarray


class Problem(NamedTuple):
    """Validated GP inputs (:func:`check_problem`)."""

    log_params: np.ndarray  # (..., P)
    Y: np.ndarray           # (..., N, d_y)
    X: np.ndarray           # (N, d_x)
    z: np.ndarray           # (N,)
    batch_shape: tuple


def _check_jitter_log(jitter_log) -> None:
    if jitter_log is not None and not isinstance(jitter_log, JitterLog):
        raise ValueError(f"jitter_log must be a mdcore._linalg.JitterLog or None; received "
                         f"{type(jitter_log).__name__}.")


def check_problem(log_params, Y, X, z) -> Problem:
    X = as_float_array(X, "X", ndim=2, allow_empty=True)
    if X.shape[0] == 0:
        raise ValueError(f"X has N = 0 rows (shape {X.shape}); the GP needs at least one "
                         "training input.")
    N, d_x = X.shape
    z = as_float_array(z, "z", ndim=1)
    if z.shape[0] != N:
        raise ValueError(f"z must have shape (N,) = ({N},) to match X {X.shape}; "
                         f"received {z.shape}.")
    Y = as_float_array(Y, "Y", min_ndim=2, allow_empty=True)
    if Y.shape[-2] != N:
        raise ValueError(f"Y must have shape (..., N, d_y) with N = {N} rows to match X "
                         f"{X.shape}; received {Y.shape}.")
    lp = as_log_params(log_params, Y.shape[-1], d_x)
    try:
        batch = np.broadcast_shapes(lp.shape[:-1], Y.shape[:-2])
    except ValueError:
        raise ValueError(
            f"the leading dimensions of log_params {lp.shape} and Y {Y.shape} do not "
            f"broadcast ({lp.shape[:-1]} vs {Y.shape[:-2]}); add size-1 axes to align them."
        ) from None
    return Problem(lp, Y, X, z, batch)


@single_threaded_blas
def neg_log_marginal_likelihood(log_params, Y, X, z, *,
                                jitter_log: JitterLog | None = None) -> np.ndarray:
    """Negative log marginal likelihood (Eq. 9), batched over hyperparameters and ``Y``:
    ``½ zᵀ K⁻¹ z + Σ log L_ii + (N/2) log 2π``, ``K = K_ff + σ_n² I = L Lᵀ``.

    Parameters
    ----------
    log_params : ndarray of shape (..., P)
        ``[log σ_f, log ℓ_y (d_y), log ℓ_x (d_x), log σ_n]``.
    Y : ndarray of shape (..., N, d_y)
        Simulator outputs, the GP's inputs; leading dims broadcast with ``log_params``.
    X : ndarray of shape (N, d_x)
    z : ndarray of shape (N,)
    jitter_log : JitterLog, optional
        Receives the jitter counts instead of a warning (thread-safe, unlike catch_warnings).

    Returns
    -------
    ndarray of shape (...)
        ``+inf`` (and a :class:`NumericalWarning`) where no jitter step factorises.

    Examples
    --------
    >>> X = np.linspace(0, 1, 5)[:, None]; Y = np.sin(3 * X); z = (Y + X)[:, 0]
    >>> lp = np.array([[0.0, 0.0, 0.0, -2.0], [0.5, 0.0, 0.0, -2.0]])
    >>> neg_log_marginal_likelihood(lp, Y, X, z).shape
    (2,)
    """
    _check_jitter_log(jitter_log)
    prob = check_problem(log_params, Y, X, z)
    N = prob.X.shape[0]
    out = np.empty(int(np.prod(prob.batch_shape, dtype=np.int64)))
    log = JitterLog() if jitter_log is None else jitter_log
    per_item = 8.0 * N * (4 * N + 2 * prob.Y.shape[-1] + 4)

    def work(sl, multi, n):
        theta = gather(prob.log_params, 1, prob.batch_shape, multi)
        Yc = gather(prob.Y, 2, prob.batch_shape, multi)
        L, ok = cholesky(train_cov(theta, Yc, prob.X, border=prob.z), log, n_cov=N)
        w = L[:, N, :N]                                   # L⁻¹ z from the bordered factor
        logdet = np.sum(np.log(np.diagonal(L, axis1=-2, axis2=-1)[:, :N]), axis=-1)
        val = 0.5 * np.sum(w * w, axis=-1) + logdet + 0.5 * N * LOG_2PI  # Eq. 9
        out[sl] = np.where(ok, val, np.inf)

    for_each_chunk(work, chunks(prob.batch_shape, per_item))
    if jitter_log is None:
        log.warn("neg_log_marginal_likelihood")
    return out.reshape(prob.batch_shape)


@single_threaded_blas
def predict(log_params, Y, X, z, Y_star, X_star) -> GPPrediction:
    """Predictive moments of the latent GP (Eq. 7), batched: arguments as
    :func:`neg_log_marginal_likelihood`, ``Y_star`` (..., N*, d_y), ``X_star`` (N*, d_x);
    NaN (and a warning) where no jitter step factorises.

    Examples
    --------
    >>> X = np.linspace(0, 1, 5)[:, None]; Y = np.sin(3 * X); z = (Y + X)[:, 0]
    >>> p = predict([0.0, 0.0, 0.0, -3.0], Y, X, z, Y[:2], X[:2])
    >>> p.mean.shape, p.var.shape
    ((2,), (2,))
    """
    prob = check_problem(log_params, Y, X, z)
    d_x = prob.X.shape[1]
    X_star = as_float_array(X_star, "X_star", ndim=2, allow_empty=True)
    if X_star.shape[1] != d_x:
        raise ValueError(f"X_star must have shape (N*, d_x) with d_x = {d_x} like X; "
                         f"received {X_star.shape}.")
    Y_star = as_float_array(Y_star, "Y_star", min_ndim=2, allow_empty=True)
    d_y = prob.Y.shape[-1]
    if Y_star.shape[-2:] != (X_star.shape[0], d_y):
        raise ValueError(f"Y_star must have shape (..., N*, d_y) = (..., {X_star.shape[0]}, "
                         f"{d_y}) to match X_star {X_star.shape} and Y {prob.Y.shape}; "
                         f"received {Y_star.shape}.")
    try:
        batch = np.broadcast_shapes(prob.batch_shape, Y_star.shape[:-2])
    except ValueError:
        raise ValueError(f"the leading dimensions of Y_star {Y_star.shape} do not broadcast "
                         f"with log_params/Y ({prob.batch_shape}).") from None
    N, M = prob.X.shape[0], X_star.shape[0]
    total = int(np.prod(batch, dtype=np.int64))
    mean, var, noise = np.empty((total, M)), np.empty((total, M)), np.empty(total)
    log = JitterLog()
    per_item = 8.0 * (N * (4 * N + 3 * M + 2 * d_y) + 4 * M)

    def work(sl, multi, n):
        theta = gather(prob.log_params, 1, batch, multi)
        Yc = gather(prob.Y, 2, batch, multi)
        Ys = gather(Y_star, 2, batch, multi)
        L, ok = cholesky(train_cov(theta, Yc, prob.X, border=prob.z), log, n_cov=N)
        # Eq. 7 via V = L⁻¹ K_f* and w = L⁻¹ z: mean = Vᵀ w, var = k** − Σ V².
        V = solve_lower_inplace(L[:, :N, :N], cross_cov(theta, Yc, prob.X, Ys, X_star))
        mean[sl] = np.einsum("bnm,bn->bm", V, L[:, N, :N])
        sf2 = np.exp(2.0 * theta[:, 0])
        var[sl] = np.maximum(sf2[:, None] - np.einsum("bnm,bnm->bm", V, V), 0.0)
        noise[sl] = np.exp(2.0 * theta[:, -1])
        mean[sl][~ok] = var[sl][~ok] = np.nan

    for_each_chunk(work, chunks(batch, per_item))
    log.warn("predict")
    return GPPrediction(mean.reshape(batch + (M,)), var.reshape(batch + (M,)),
                        noise.reshape(batch))


def nlml_and_gradient(log_params, Y, X, z, *, jitter_log: JitterLog | None = None
                      ) -> tuple[float, np.ndarray]:
    """NLML (Eq. 9) and its gradient ``½ tr((K⁻¹ − ααᵀ) ∂K/∂φ)``, ``α = K⁻¹ z``, (P,), for
    one ``log_params`` (P,) and ``Y`` (N, d_y) (Rasmussen & Williams Eq. 5.9)."""
    _check_jitter_log(jitter_log)
    prob = check_problem(log_params, Y, X, z)
    if prob.batch_shape != ():
        raise ValueError(f"nlml_and_gradient takes one vector: log_params (P,) and Y (N, d_y); "
                         f"received batch shape {prob.batch_shape}. Use "
                         "neg_log_marginal_likelihood for batches.")
    lp, Y, X, z = prob.log_params, prob.Y, prob.X, prob.z
    N, d_y, d_x = X.shape[0], Y.shape[1], X.shape[1]
    sf, ly, lx, sn = split_log_params(lp, d_y, d_x)
    my, dmy = matern32_and_dlog_ell(Y, ly)           # m32 and ∂m32/∂log ℓ per dimension
    mx, dmx = matern32_and_dlog_ell(X, lx)
    Kf = sf**2 * my * mx
    log = JitterLog() if jitter_log is None else jitter_log
    L, ok = cholesky((Kf + sn**2 * np.eye(N))[None], log)
    if jitter_log is None:
        log.warn("nlml_and_gradient")
    if not ok[0]:
        return np.inf, np.zeros_like(lp)
    cf = (L[0], True)
    alpha = scipy.linalg.cho_solve(cf, z)
    nlml = 0.5 * z @ alpha + np.sum(np.log(np.diag(L[0]))) + 0.5 * N * LOG_2PI
    # W = K⁻¹ − ααᵀ from the Cholesky factor (GPML Alg. 5.1), needed for the trace term.
    W = scipy.linalg.cho_solve(cf, np.eye(N)) - np.outer(alpha, alpha)
    grad = np.empty_like(lp)
    grad[0] = 0.5 * np.sum(W * 2.0 * Kf)
    for d in range(d_y):
        grad[1 + d] = 0.5 * np.sum(W * sf**2 * mx * dmy[d])
    for d in range(d_x):
        grad[1 + d_y + d] = 0.5 * np.sum(W * sf**2 * my * dmx[d])
    grad[-1] = 0.5 * np.trace(W) * 2.0 * sn**2
    return float(nlml), grad
