"""Multivariate implausibility with a correlated model discrepancy (docs/method.md §5).

Vernon, Goldstein & Bower (2010), Bayesian Analysis 5(4), §4: over all n = N · n_out targets,
``I_M²(θ) = (z − E[f(θ)])ᵀ (V_o + V_m + V_em(θ))⁻¹ (z − E[f(θ)])`` against the χ²_n quantile.
Targets are ordered output-major, index ``o · N + n``. At its training inputs the Kronecker
emulator's covariance is diagonal in the eigenbasis Q_o of its x-kernel,
``V_em,o(θ) = Q_o diag(s_o(θ)) Q_oᵀ``, so in that basis the total covariance is
``B + diag s(θ)`` with one fixed ``B = Qᵀ (V_o + V_m) Q``: one Cholesky factor per candidate,
or, when V_m does not couple outputs, a Neumann series (:func:`_series`, docs/performance.md).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import scipy.linalg
import scipy.stats

from ._kernels import matern32, scaled_sq_dist
from ._linalg import chunks, for_each_chunk
from ._validation import as_float_array

#: Relative truncation error of the Neumann series (below the Cholesky route's rounding).
SERIES_TOL = 1e-14
#: Largest ε = max e / λ_min(B) summed as a series (at most three steps); above it, Cholesky.
SERIES_MAX_EPS = 0.01


class EmulatorCov(NamedTuple):
    """The emulator's joint moments at its training inputs (:func:`emulator_cov`): ``mean``
    E[f(θ)] (M, n_out, N); ``basis`` Q_o (n_out, N, N), the orthonormal eigenvectors of
    output o's x-kernel; ``s`` (M, n_out, N), ``V_em,o(θ) = Q_o diag(s[m, o]) Q_oᵀ`` in
    output units squared; ``prior`` σ_f² μ (n_out, N), ``s`` before the simulator runs."""

    mean: np.ndarray
    basis: np.ndarray
    s: np.ndarray
    prior: np.ndarray


def chi2_cutoff(n_targets: int, probability: float = 0.995) -> float:
    """The χ² quantile at ``probability`` with N · n_out degrees of freedom that I_M² is
    compared with."""
    return float(scipy.stats.chi2.ppf(probability, n_targets))


def _correlation_sqrt(X, length: float) -> np.ndarray:
    """Symmetric square root of ``m32(‖x − x'‖ / ℓ)`` over the rows of X (N, d_x); I for ℓ = 0."""
    if length == 0.0:
        return np.eye(X.shape[0])
    lam, U = np.linalg.eigh(matern32(scaled_sq_dist(X, X, np.full(X.shape[1], length))))
    return (U * np.sqrt(np.maximum(lam, 0.0))) @ U.T


def discrepancy_cov(X, V_m, length=0.0, output_corr=None) -> np.ndarray:
    """The model-discrepancy covariance, correlated in x and across outputs.

    ``V_m[(o, x), (o', x')] = σ_o(x) σ_o'(x') R_oo' [C_o^½ C_o'^½](x, x')`` with
    ``C_o(x, x') = m32(‖x − x'‖ / ℓ_o)`` and C^½ its symmetric square root (C_o = I for
    ℓ_o = 0): the separable R ⊗ C for one ℓ, the max rules' independent V_m for ℓ = 0.

    ``X`` (N, d_x) are the distinct inputs, ``V_m`` (N, n_out) the targets' variances,
    ``length`` ℓ_m per output in X's units and ``output_corr`` R (n_out, n_out; validated by
    :func:`mdcore._history_matching.setup`). Returns (n_out · N, n_out · N), output-major.
    """
    X = as_float_array(X, "X", ndim=2)
    V_m = as_float_array(V_m, "V_m", ndim=2)
    N, n_out = V_m.shape
    length = np.broadcast_to(np.asarray(length, dtype=np.float64), (n_out,))
    R = np.eye(n_out) if output_corr is None else np.asarray(output_corr, dtype=np.float64)
    roots = [_correlation_sqrt(X, float(ell)) for ell in length]
    sd = np.sqrt(V_m.T.ravel())
    out = np.zeros((n_out * N, n_out * N))
    for o in range(n_out):
        for q in range(n_out):
            if R[o, q] != 0.0:
                block = roots[o] @ roots[q] if o != q or length[o] > 0 else np.eye(N)
                out[o * N:(o + 1) * N, q * N:(q + 1) * N] = R[o, q] * block
    out = sd[:, None] * out * sd[None, :]
    np.fill_diagonal(out, V_m.T.ravel())          # a correlation's diagonal is exactly 1
    return out


def emulator_cov(emulator, theta) -> EmulatorCov:
    """The emulator's moments at its training inputs for ``theta`` (M, p): ``s = σ_f² μ −
    σ_f⁴ μ² d(θ)`` clipped at 0, μ the eigenvalues of ``m32(X, X)`` and ``d(θ) = (k_θ Q_θ)²
    W`` of :class:`mdcore._emulator.EmulatorAt`."""
    X = emulator.X_train
    at = emulator.at(X)
    terms = at.theta_terms(theta)
    mean, _ = at.moments_at(terms, with_cov=False)
    Xu, p = emulator.unit_x(X), emulator.theta_train.shape[1]
    s, prior = np.empty_like(mean), np.empty(mean.shape[1:])
    for o, (g, (_, d)) in enumerate(zip(emulator.gps, terms.per_output)):
        sf2 = np.exp(2 * g.log_params[0])
        Kx = matern32(scaled_sq_dist(Xu, Xu, np.exp(g.log_params[1 + p:-1])))
        mu = np.einsum("ib,ij,jb->b", g.Q_x, Kx, g.Q_x)
        prior[o] = sf2 * mu
        s[:, o] = np.maximum(sf2 * mu - sf2**2 * mu**2 * d, 0.0)
    return EmulatorCov(mean, np.stack([g.Q_x for g in emulator.gps]), s, prior)


def _rotated(cov: EmulatorCov, z, V):
    """``B = Qᵀ V Q``, ``r = Qᵀ (z − E[f])`` (M, n) and ``s`` (M, n), Q = blockdiag(Q_o)."""
    Q = scipy.linalg.block_diag(*cov.basis)
    resid = np.asarray(z, dtype=np.float64).T[None] - cov.mean               # (M, n_out, N)
    r = np.concatenate([resid[:, o] @ Qo for o, Qo in enumerate(cov.basis)], axis=1)
    return Q.T @ V @ Q, r, cov.s.reshape(len(resid), -1)


def _factor_rows(B, r, s, lam_min: float):
    """Cholesky factors of ``[[B + diag s, r], [rᵀ, c]]`` for each row of r, s (m, n): the
    last row of the factor is ``(L⁻¹ r)ᵀ``, so ``rᵀ (B + diag s)⁻¹ r`` is its squared norm;
    ``c`` bounds ``rᵀ B⁻¹ r`` from above so that the factor exists. Shape (m, n+1, n+1)."""
    m, n = r.shape
    i = np.arange(n)
    C = np.empty((m, n + 1, n + 1))
    C[:, :n, :n] = B
    C[:, i, i] += s
    C[:, n, :n] = C[:, :n, n] = r
    C[:, n, n] = 1.0 + 2.0 * np.einsum("mi,mi->m", r, r) / lam_min
    return np.linalg.cholesky(C)


def _dense(B, r, s, log_det: bool):
    """``rᵀ (B + diag s)⁻¹ r`` and ``log det(B + diag s)`` per row of r, s (M, n), one
    Cholesky factor each (:func:`_factor_rows`)."""
    M, n = r.shape
    I2, ld = np.empty(M), np.empty(M)
    lam_min = np.linalg.eigvalsh(B)[0]

    def work(sl, _multi, m):
        L = _factor_rows(B, r[sl], s[sl], lam_min)
        I2[sl] = np.einsum("mi,mi->m", L[:, n, :n], L[:, n, :n])
        if log_det:
            ld[sl] = 2.0 * np.log(np.diagonal(L, axis1=1, axis2=2)[:, :n]).sum(axis=1)

    for_each_chunk(work, chunks((M,), 16.0 * (n + 1) ** 2))
    return I2, (ld if log_det else None)


def _series(B, p, r, s):
    """``rᵀ (B + diag s)⁻¹ r`` per row of r, s (M, n) of one output block.

    With ``s = v p + e`` (p the prior variances, e ≥ 0), ``Yᵀ B Y = I``, ``Yᵀ diag(p) Y =
    diag(γ)``, ``D = I + v γ`` and ``G = D^-½ Yᵀ diag(e) Y D^-½`` (0 ≼ G ≼ ε I,
    ``ε = max e / λ_min(B)``): ``I_M² = Σ_j (−1)^j x₀ᵀ G^j x₀``, ``x₀ = D^-½ Yᵀ r``. Rows
    with ε > ``SERIES_MAX_EPS`` get a Cholesky factor each (:func:`_factor_rows`).
    """
    n = B.shape[0]
    Li = scipy.linalg.solve_triangular(np.linalg.cholesky(B), np.eye(n), lower=True)
    gam, U = np.linalg.eigh((Li * p) @ Li.T)
    Y = Li.T @ U
    lam_min = np.linalg.eigvalsh(B)[0]
    out = np.empty(len(r))

    def work(sl, _multi, m):
        sc = s[sl]
        with np.errstate(divide="ignore", invalid="ignore"):
            v = np.where(p > 0, sc / p, np.inf).min(axis=1)
        v[~np.isfinite(v)] = 0.0
        e = sc - v[:, None] * p
        eps = e.max(axis=1) / lam_min
        ok = eps <= SERIES_MAX_EPS
        worst = float(eps[ok].max()) if ok.any() else 0.0
        # terms up to j = 2K: the remainder is below ε^(2K+1) (1 + ε) of I_M²
        K = 0 if worst == 0.0 else max(0, int(np.ceil(
            (np.log(SERIES_TOL) / np.log(worst) - 1) / 2)))
        Dh = 1.0 / np.sqrt(1.0 + v[ok, None] * gam)
        e, x = e[ok], (r[sl][ok] @ Y) * Dh
        I2 = np.einsum("mi,mi->m", x, x)
        for _ in range(K):
            x1 = ((((x * Dh) @ Y.T) * e) @ Y) * Dh
            I2 += np.einsum("mi,mi->m", x1, x1 - x)
            x = x1
        res = out[sl]
        res[ok] = I2
        if not ok.all():
            L = _factor_rows(B, r[sl][~ok], sc[~ok], lam_min)[:, n, :n]
            res[~ok] = np.einsum("mi,mi->m", L, L)

    for_each_chunk(work, chunks((len(r),), 64.0 * n))
    return out


def implausibility_and_logdet(cov: EmulatorCov, z, V, *, log_det: bool = False):
    """I_M²(θ) (M,) of the M candidates of ``cov`` given ``z`` (N, n_out) and ``V`` = V_o + V_m
    (:func:`discrepancy_cov`), and with ``log_det`` ``log det(V + V_em(θ))`` (M,), else None."""
    B, r, s = _rotated(cov, z, V)
    n_out, N = cov.s.shape[1:]
    coupled = any(np.any(B[o * N:(o + 1) * N, q * N:(q + 1) * N])
                  for o in range(n_out) for q in range(n_out) if o != q)
    if log_det or coupled:
        return _dense(B, r, s, log_det)
    I2 = np.zeros(len(r))
    for o in range(n_out):
        b = slice(o * N, (o + 1) * N)
        I2 += _series(B[b, b], cov.prior[o], r[:, b], s[:, b])
    return I2, None


def multivariate_implausibility(emulator, theta, z, V) -> tuple[np.ndarray, np.ndarray]:
    """I_M²(θ) (M,) of ``theta`` (M, p) given ``z`` at the training inputs and ``V``, and
    the diagonal of ``V_em(θ)`` (M, N, n_out), as :meth:`~mdcore.Emulator.predict`'s var."""
    cov = emulator_cov(emulator, theta)
    var = np.stack([cov.s[:, o] @ (Qo * Qo).T for o, Qo in enumerate(cov.basis)], axis=-1)
    return implausibility_and_logdet(cov, z, V)[0], var


def log_likelihood(emulator, theta, z, V) -> np.ndarray:
    """The Gaussian log-likelihood whose exponent is −½ I_M², shape (M,).

    ``log p(z | θ) = −½ [I_M²(θ) + log det(V + V_em(θ)) + n log 2π]``, n = N · n_out.
    """
    I2, ld = implausibility_and_logdet(emulator_cov(emulator, theta), z, V, log_det=True)
    return -0.5 * (I2 + ld + V.shape[0] * np.log(2.0 * np.pi))


def cov_ratio(emulator, theta, V) -> float:
    """An upper bound r on ``max_θ λ_max(V⁻¹ V_em(θ))`` over ``theta`` (M, p), V = V_o + V_m:
    a perfect emulator would change no I_M² by more than the factor 1 + r.

    ``diag s(θ) ≼ diag s_max`` per direction, so r is the largest eigenvalue of
    ``diag(√s_max) B⁻¹ diag(√s_max)``, ``B = Qᵀ V Q`` (exact for one θ).
    """
    cov = emulator_cov(emulator, theta)
    Q = scipy.linalg.block_diag(*cov.basis)
    root = np.sqrt(cov.s.reshape(len(cov.s), -1).max(axis=0))
    L = np.linalg.cholesky(Q.T @ V @ Q)
    A = scipy.linalg.solve_triangular(L, np.diag(root), lower=True)
    return float(np.linalg.eigvalsh(A.T @ A)[-1])
