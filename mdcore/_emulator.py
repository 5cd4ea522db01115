"""GP emulator of a simulator over the joint input (x, θ), for history matching and KOH.

Per output, a least-squares linear mean ``β₀ + βᵀ[x, θ]`` plus a GP on the residuals with
covariance ``σ_f² K_θ ⊗ K_x + σ_n² I`` (Matérn 3/2, inputs scaled to [0, 1]), handled through
the eigenpairs ``K_θ = Q_θ Λ Q_θᵀ``, ``K_x = Q_x M Q_xᵀ`` (docs/method.md §4).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from ._exceptions import ConvergenceWarning
from ._gp import LOG_2PI
from ._hyperfit import best_lbfgs, lbfgs_advice, lbfgs_converged
from ._kernels import matern32, matern32_and_dlog_ell, scaled_sq_dist, separable_matern
from ._linalg import chunks, for_each_chunk
from ._threads import single_threaded_blas
from ._validation import as_float_array, check_bounds

__all__ = ["Emulator", "EmulatorArrays", "EmulatorAt", "EmulatorPrediction", "KronGP",
           "ThetaTerms", "fit_emulator"]


class EmulatorArrays(NamedTuple):
    """:class:`EmulatorAt`'s fixed pieces at N inputs, stacked over outputs; R training θ
    of p parameters, N_t training inputs."""

    t_lo: np.ndarray     # (p,) θ's box: unit θ = (θ − t_lo) / t_span
    t_span: np.ndarray   # (p,)
    T_train: np.ndarray  # (R, p) training θ, unit box
    inv_ell: np.ndarray  # (n_out, p) 1 / ℓ_θ
    Q_t: np.ndarray      # (n_out, R, R) eigenvectors of K_θ
    W: np.ndarray        # (n_out, R, N_t) 1 / (σ_f² λ_a μ_b + σ_n²)
    lin: np.ndarray      # (n_out, N) β₀ + β_xᵀ x
    beta_t: np.ndarray   # (n_out, p)
    AK: np.ndarray       # (n_out, R, N) A m32(X, X_train)ᵀ
    V: np.ndarray        # (n_out, N, N_t) m32(X, X_train) Q_x
    sf4: np.ndarray      # (n_out,) σ_f⁴
    prior: np.ndarray    # (n_out, N, N) σ_f² m32(X, X)
    sf2: np.ndarray      # (n_out,) σ_f²
    G: np.ndarray        # (n_out, R, N) W (V ⊙ V)ᵀ: V[y(θ, x_n)] = σ_f² − σ_f⁴ (k_θ Q_θ)² G


class ThetaTerms(NamedTuple):
    """The θ-dependent pieces (:meth:`EmulatorAt.theta_terms`): ``unit`` θ (M, p) and, per
    output, ``(k_θ = m32(θ, Θ_train) (M, R), d(θ) = (k_θ Q_θ)² W (M, N_t))``."""

    unit: np.ndarray
    per_output: tuple


class EmulatorPrediction(NamedTuple):
    """Predictive ``mean`` ``E[y]`` and latent ``var`` ``V[y]``, (n_theta, N, n_out)."""

    mean: np.ndarray
    var: np.ndarray


class KronGP(NamedTuple):
    """One output's fitted Kronecker GP (unit-scaled inputs; :attr:`Emulator.gps`)."""

    log_params: np.ndarray   # (P,) [log σ_f, log ℓ_θ (p), log ℓ_x (d_x), log σ_n]
    beta: np.ndarray         # (1 + d_x + p,) linear mean coefficients
    Q_t: np.ndarray          # (R, R)
    Q_x: np.ndarray          # (N, N)
    A: np.ndarray            # (R, N): σ_f² Q_θ (W ⊙ Q_θᵀ Res Q_x) Q_xᵀ
    W: np.ndarray            # (R, N): 1 / (σ_f² λ_a μ_b + σ_n²)


def _unit(A, lo, span):
    return (A - lo) / span


def _m32(A, B, log_ell):
    return matern32(scaled_sq_dist(A, B, np.exp(log_ell)))


def _eig(K):
    lam, Q = np.linalg.eigh(K)
    return np.maximum(lam, 0.0), Q


def _design(Xu, Tu):
    """Rows [1, x, θ] for every (run, input) pair in run-major order: (R·N, 1 + d_x + p)."""
    R, N = Tu.shape[0], Xu.shape[0]
    return np.column_stack([np.ones(R * N), np.tile(Xu, (R, 1)), np.repeat(Tu, N, axis=0)])


def _kron_solve(lp, Tu, Xu, res, sq=(None, None)):
    """Eigen-solve of ``σ_f² K_θ ⊗ K_x + σ_n² I`` for residuals ``res`` (R, N): factors, their
    log-ℓ derivatives, eigenpairs, ``σ_f² λ_a μ_b``, ``S`` and ``(Q_θᵀ Res Q_x) / S``; ``sq``
    the squared differences of Tu and Xu per dimension, if known."""
    p = Tu.shape[1]
    Kt, Dt = matern32_and_dlog_ell(Tu, np.exp(lp[1:1 + p]), sq[0])
    Kx, Dx = matern32_and_dlog_ell(Xu, np.exp(lp[1 + p:-1]), sq[1])
    lam, Qt = _eig(Kt)
    mu, Qx = _eig(Kx)
    SO = np.exp(2 * lp[0]) * (lam[:, None] * mu[None, :])
    S = SO + np.exp(2 * lp[-1])
    return Kt, Dt, Kx, Dx, lam, Qt, mu, Qx, SO, S, (Qt.T @ res @ Qx) / S


def _kron_nlml(lp, Tu, Xu, res, sq=(None, None)):
    """NLML of the Kronecker GP for residuals ``res`` (R, N) and its gradient: with ``S_ab =
    σ_f² λ_a μ_b + σ_n²``, ``P = Q_θᵀ Res Q_x``, ``NLML = ½ Σ P²/S + ½ Σ log S + (RN/2) log 2π``
    and ``∂NLML/∂φ = ½ tr(K⁻¹ ∂K) − ½ αᵀ ∂K α``, ``α = vec(Q_θ (P/S) Q_xᵀ)``. The L-BFGS-B
    path turns a 1-ulp change of these into ~1e-6 in the fit, so each dimension's sums and
    products keep one order (a stack's matmul is each slice's)."""
    p = Tu.shape[1]
    sf2, sn2 = np.exp(2 * lp[0]), np.exp(2 * lp[-1])
    Kt, Dt, Kx, Dx, lam, Qt, mu, Qx, SO, S, Pa = _kron_solve(lp, Tu, Xu, res, sq)
    PP = Pa * Pa
    f = 0.5 * (PP * S).sum() + 0.5 * np.log(S).sum() + 0.5 * res.size * LOG_2PI
    A0 = Qt @ Pa @ Qx.T
    g = np.empty_like(lp)
    Z = 1.0 / S - PP
    g[0] = (SO * Z).sum()
    g[-1] = sn2 * Z.sum()
    diag_t = np.einsum("ra,drs,sa->da", Qt, Dt, Qt)[:, :, None] * mu[None, None, :]
    diag_x = lam[None, :, None] * np.einsum("ra,drs,sa->da", Qx, Dx, Qx)[:, None, :]
    g[1:1 + p] = 0.5 * sf2 * ((diag_t / S).sum(axis=(1, 2))
                              - (A0 * (Dt @ A0 @ Kx)).sum(axis=(1, 2)))
    g[1 + p:-1] = 0.5 * sf2 * ((diag_x / S).sum(axis=(1, 2))
                               - (A0 * (Kt @ A0 @ Dx)).sum(axis=(1, 2)))
    return f, g


def _fit_one(Tu, Xu, y, rng, n_starts, output=0, step=None):
    """Fit one output: least-squares linear mean, then the GP's NLML by L-BFGS-B; ``step()``
    after every iteration (it may raise to stop the fit)."""
    F = _design(Xu, Tu)
    beta, *_ = np.linalg.lstsq(F, y.ravel(), rcond=None)
    res = (y.ravel() - F @ beta).reshape(y.shape)
    sd = float(np.std(res)) or float(np.std(y)) or 1.0
    p, d_x = Tu.shape[1], Xu.shape[1]
    lo = np.r_[np.log(sd) - 3, np.full(p + d_x, np.log(0.03)), np.log(sd * 1e-7)]
    hi = np.r_[np.log(sd) + 3, np.full(p + d_x, np.log(30.0)), np.log(sd * 0.3)]
    starts = lo + (hi - lo) * rng.uniform(size=(n_starts, lo.size))
    starts[0] = np.r_[np.log(sd), np.full(p + d_x, np.log(0.5)), np.log(sd * 1e-3)]
    sq = tuple((A[:, :, None] - A[:, None, :]) ** 2 for A in (Tu.T.copy(), Xu.T.copy()))
    best, _ = best_lbfgs(lambda lp: _kron_nlml(lp, Tu, Xu, res, sq), starts, lo, hi,
                         progress=None if step is None else (lambda _: step()))
    if not lbfgs_converged(best, lo, hi):
        warnings.warn(f"emulator fit, output {output}: the best of {n_starts} L-BFGS-B runs did "
                      f"not converge ({best.message}; {lbfgs_advice(best)}); its "
                      "predictions may be off. Add simulator runs (n_runs) or raise n_starts.",
                      ConvergenceWarning, stacklevel=3)
    lp = best.x
    *_, Qt, _, Qx, _, S, Pa = _kron_solve(lp, Tu, Xu, res, sq)
    return KronGP(lp, beta, Qt, Qx, np.exp(2 * lp[0]) * Qt @ Pa @ Qx.T, 1.0 / S)


@dataclass(frozen=True, eq=False)
class Emulator:
    """GP emulators of ``simulate(X, θ)`` (:func:`fit_emulator`): ``X_train`` (N, d_x),
    ``theta_train`` (R, p), ``y_train`` (R, N, n_out) and the θ ``bounds`` (p, 2)."""

    X_train: np.ndarray
    theta_train: np.ndarray
    y_train: np.ndarray
    bounds: np.ndarray
    _x_lo: np.ndarray
    _x_span: np.ndarray
    _gps: tuple

    @property
    def n_out(self) -> int:
        return self.y_train.shape[2]

    @property
    def gps(self) -> tuple:
        """The fitted Kronecker GP of each output (:class:`KronGP`, unit-scaled inputs)."""
        return self._gps

    def unit_x(self, X) -> np.ndarray:
        """Inputs ``X`` (N, d_x) scaled as the emulator scales them (training range -> [0, 1])."""
        return _unit(np.asarray(X, dtype=np.float64), self._x_lo, self._x_span)

    def _theta_box(self):
        return self.bounds[:, 0], self.bounds[:, 1] - self.bounds[:, 0]

    @property
    def log_params(self) -> np.ndarray:
        """Fitted log hyperparameters, shape (n_out, 2 + p + d_x), unit-scaled inputs."""
        return np.stack([g.log_params for g in self._gps])

    def _inputs(self, X, theta):
        """Validated ``X`` (N, d_x) and ``theta`` (n_theta, p)."""
        X = as_float_array(X, "X", ndim=2)
        theta = np.atleast_2d(as_float_array(theta, "theta", allow_empty=True))
        d_x, p = self.X_train.shape[1], self.theta_train.shape[1]
        if X.shape[1] != d_x or theta.shape[1] != p:
            raise ValueError(f"X must be (N, {d_x}) and theta (n_theta, {p}); received "
                             f"{X.shape} and {theta.shape}.")
        return X, theta

    @single_threaded_blas
    def predict(self, X, theta) -> EmulatorPrediction:
        """Emulator mean and variance at every (θ, x) pair: ``X`` (N, d_x), ``theta``
        (n_theta, p) -> ``mean``, ``var`` (n_theta, N, n_out)."""
        X, theta = self._inputs(X, theta)
        d_x, p = self.X_train.shape[1], self.theta_train.shape[1]
        Xu, Xtr = self.unit_x(X), self.unit_x(self.X_train)
        Tu, Ttr = _unit(theta, *self._theta_box()), _unit(self.theta_train, *self._theta_box())
        mean = np.empty((theta.shape[0], X.shape[0], self.n_out))
        var = np.empty_like(mean)
        for o, g in enumerate(self._gps):
            sf2 = np.exp(2 * g.log_params[0])
            kt = _m32(Tu, Ttr, g.log_params[1:1 + p])                        # (M, R)
            kx = _m32(Xu, Xtr, g.log_params[1 + p:-1])                       # (N*, N)
            lin = g.beta[0] + Xu @ g.beta[1:1 + d_x]
            mean[..., o] = (kt @ g.A @ kx.T) + lin[None, :] + (Tu @ g.beta[1 + d_x:])[:, None]
            U, V = (kt @ g.Q_t) ** 2, (kx @ g.Q_x) ** 2
            var[..., o] = np.maximum(sf2 - sf2**2 * (U @ g.W @ V.T), 0.0)
        return EmulatorPrediction(mean, var)

    @single_threaded_blas
    def implausibility_and_var(self, X, theta, z, V, *,
                               rank: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """Combined implausibility (Eq. 16) of every θ and the emulator variance.

        ``I(θ)`` is the ``rank``-th largest over the targets (n, o) of ``|z[n, o] − E[y]| /
        √(V[n, o] + V[y])`` at ``(θ, X[n])``, with :meth:`predict`'s moments.

        Parameters
        ----------
        X : ndarray of shape (N, d_x)
        theta : ndarray of shape (M, p)
        z, V : ndarray of shape (N, n_out)
            Observations and ``V_o + V_m``.
        rank : {1, 2, 3}, default=1

        Returns
        -------
        implausibility : ndarray of shape (M,)
        var : ndarray of shape (M, N, n_out)
        """
        X, theta = self._inputs(X, theta)
        shape = (X.shape[0], self.n_out)
        z, V = as_float_array(z, "z"), as_float_array(V, "V")
        try:
            z, V = np.broadcast_to(z, shape), np.broadcast_to(V, shape)
        except ValueError:
            raise ValueError(f"z and V must broadcast to (N, n_out) = {shape}; received "
                             f"{z.shape} and {V.shape}.") from None
        if rank not in (1, 2, 3):
            raise ValueError(f"rank must be 1, 2 or 3 (the max, 2nd max or 3rd max rule); "
                             f"received {rank!r}.")
        if z.size < rank:
            raise ValueError(f"rank {rank} needs at least {rank} targets; received {z.size}.")
        I, var, n_bad = _implausibility(self.at(X).arrays(), theta, z, V, rank)
        if n_bad:
            raise ValueError("V_o + V_m + var must be positive for every target; received a "
                             "zero. Give V_m > 0 or a positive observation variance.")
        return I, var

    def at(self, X) -> EmulatorAt:
        """The emulator's joint Gaussian at fixed inputs ``X`` (N, d_x) as a function of θ,
        with what does not depend on θ computed once (the KOH likelihood's per-step cost)."""
        X = as_float_array(X, "X", ndim=2)
        d_x, p = self.X_train.shape[1], self.theta_train.shape[1]
        if X.shape[1] != d_x:
            raise ValueError(f"X must have shape (N, {d_x}); received {X.shape}.")
        Xu, Xtr = self.unit_x(X), self.unit_x(self.X_train)
        lin, AK, V, prior = [], [], [], []
        for g in self._gps:
            kx = _m32(Xu, Xtr, g.log_params[1 + p:-1])                         # (N, N_tr)
            lin.append(g.beta[0] + Xu @ g.beta[1:1 + d_x])
            AK.append(g.A @ kx.T)
            V.append(kx @ g.Q_x)
            prior.append(np.exp(2 * g.log_params[0]) * _m32(Xu, Xu, g.log_params[1 + p:-1]))
        return EmulatorAt(self, X, Xu, np.stack(lin), np.stack(AK), np.stack(V), np.stack(prior))


def _implausibility(a: EmulatorArrays, theta: np.ndarray, z: np.ndarray, vt: np.ndarray,
                    rank: int) -> tuple[np.ndarray, np.ndarray, int]:
    """Eq. 16 by chunks of candidates: ``E = lin + θᵀβ_θ + k_θ AK``, ``V = max(σ_f² −
    σ_f⁴ (k_θ Q_θ)² G, 0)``. Returns ``I`` (M,), ``var`` (M, N, n_out) and the count of
    targets with ``V_o + V_m + var ≤ 0``."""
    M, (N, n_out), (R, p) = theta.shape[0], z.shape, a.T_train.shape
    imp, var = np.empty(M), np.empty((M, N, n_out))
    bad = []
    s2 = 3.0 * a.inv_ell ** 2                                   # (√3 / ℓ)², (n_out, p)
    # (√3 r)² = |u|² − 2 u·t + |t|² in the s2 metric, as one product [u, 1, |u|²] @ T
    T = [np.vstack([-2.0 * (a.T_train * s2[o]).T, a.T_train ** 2 @ s2[o], np.ones(R)])
         for o in range(n_out)]
    QA = [np.hstack([a.Q_t[o], a.AK[o]]) for o in range(n_out)]     # k_θ Q_θ and k_θ AK

    def work(sl, multi, n):
        Tu = _unit(theta[sl], a.t_lo, a.t_span)
        U = np.empty((n, p + 2))
        U[:, :p], U[:, p] = Tu, 1.0
        I = np.empty((n, N, n_out))
        for o in range(n_out):
            U[:, p + 1] = Tu ** 2 @ s2[o]
            r = U @ T[o]
            np.sqrt(np.maximum(r, 0.0, out=r), out=r)
            kq = separable_matern(0.0, r) @ QA[o]                       # (n, R + N)
            mean = kq[:, R:] + (a.lin[o] + (Tu @ a.beta_t[o])[:, None])
            q = kq[:, :R]
            v = var[sl, :, o] = np.maximum(a.sf2[o] - a.sf2[o] ** 2 * ((q * q) @ a.G[o]), 0.0)
            total = vt[:, o] + v
            bad.append(np.count_nonzero(total <= 0))
            I[..., o] = np.abs(z[:, o] - mean) / np.sqrt(total)
        I = I.reshape(n, -1)
        imp[sl] = -np.partition(-I, rank - 1, axis=1)[:, rank - 1]

    for_each_chunk(work, chunks((M,), 8.0 * (6 * N * n_out + 6 * a.T_train.shape[0])))
    return imp, var, int(sum(bad))


@dataclass(frozen=True, eq=False)
class EmulatorAt:
    """Emulator moments at fixed inputs ``X`` (N, d_x), for any θ (:meth:`Emulator.at`).

    For output ``o`` (eigenpairs ``Q_θ Λ Q_θᵀ``, ``Q_x M Q_xᵀ``, ``W = 1 / (σ_f² λ_a μ_b +
    σ_n²)``), with ``k_θ = m32(θ, Θ_train)``, ``V_A = m32(X_A, X_train) Q_x`` and
    ``d(θ) = (k_θ Q_θ)² W``::

        m_η(X_A, θ)       = β₀ + βᵀ[x, θ] + k_θ A m32(X_A, X_train)ᵀ
        Σ_η(X_A, X_B; θ)  = σ_f² m32(X_A, X_B) − σ_f⁴ V_A diag(d(θ)) V_Bᵀ

    Only ``k_θ`` and ``d(θ)`` depend on θ.
    """

    emulator: Emulator
    X: np.ndarray
    _Xu: np.ndarray
    _lin: np.ndarray     # (n_out, N) x-part of the linear mean
    _AK: np.ndarray      # (n_out, R, N)
    _V: np.ndarray       # (n_out, N, N_train)
    _prior: np.ndarray   # (n_out, N, N) σ_f² m32(X, X)

    def theta_terms(self, theta, *, check: bool = True) -> ThetaTerms:
        """The θ-dependent pieces at ``theta`` (M, p), shared by every :class:`EmulatorAt` of
        the emulator."""
        em = self.emulator
        p = em.theta_train.shape[1]
        if check:
            theta = np.atleast_2d(as_float_array(theta, "theta"))
            if theta.ndim != 2 or theta.shape[1] != p:
                raise ValueError(f"theta must have shape (M, {p}); received {theta.shape}.")
        Tu, Ttr = _unit(theta, *em._theta_box()), _unit(em.theta_train, *em._theta_box())
        kts = [_m32(Tu, Ttr, g.log_params[1:1 + p]) for g in em._gps]
        return ThetaTerms(Tu, tuple((kt, (kt @ g.Q_t) ** 2 @ g.W) for kt, g in zip(kts, em._gps)))

    def arrays(self) -> EmulatorArrays:
        """The fixed pieces, stacked over outputs (for compiled code)."""
        em = self.emulator
        p, d_x = em.theta_train.shape[1], self.X.shape[1]
        t_lo, t_span = em._theta_box()
        gps = em.gps
        return EmulatorArrays(
            t_lo=t_lo, t_span=t_span, T_train=_unit(em.theta_train, t_lo, t_span),
            inv_ell=np.stack([np.exp(-g.log_params[1:1 + p]) for g in gps]),
            Q_t=np.stack([g.Q_t for g in gps]), W=np.stack([g.W for g in gps]),
            lin=self._lin, beta_t=np.stack([g.beta[1 + d_x:] for g in gps]), AK=self._AK,
            V=self._V, sf4=np.array([np.exp(4 * g.log_params[0]) for g in gps]),
            prior=self._prior, sf2=np.array([np.exp(2 * g.log_params[0]) for g in gps]),
            G=np.stack([g.W @ (V * V).T for g, V in zip(gps, self._V)]))

    def moments(self, theta):
        """``m_η`` (M, n_out, N) and ``Σ_η(X, X; θ)`` (M, n_out, N, N) for ``theta`` (M, p)."""
        return self.moments_at(self.theta_terms(theta))

    def moments_at(self, terms: ThetaTerms, *, with_cov: bool = True):
        """:meth:`moments` from :meth:`theta_terms`; ``cov`` is None unless ``with_cov``."""
        Tu, per_output = terms
        d_x, M, (n_out, N) = self.X.shape[1], Tu.shape[0], self._lin.shape
        mean = np.empty((M, n_out, N))
        cov = np.empty((M, n_out, N, N) if with_cov else (0,))
        for o, (g, (kt, d)) in enumerate(zip(self.emulator._gps, per_output)):
            mean[:, o] = self._lin[o] + (Tu @ g.beta[1 + d_x:])[:, None] + kt @ self._AK[o]
            if with_cov:
                sf4 = np.exp(4 * g.log_params[0])
                cov[:, o] = self._prior[o] - sf4 * ((self._V[o] * d[:, None, :]) @ self._V[o].T)
        return mean, (cov if with_cov else None)

    def cross_cov(self, theta, other: EmulatorAt):
        """``Σ_η(X_other, X; θ)``, shape (M, n_out, N_other, N), and the diagonal of
        ``Σ_η(X_other, X_other; θ)``, shape (M, n_out, N_other)."""
        return self.cross_cov_at(self.theta_terms(theta), other)

    def cross_cov_at(self, terms: ThetaTerms, other: EmulatorAt):
        """:meth:`cross_cov` from :meth:`theta_terms`."""
        if other.emulator is not self.emulator:
            raise ValueError("other must come from the same emulator (Emulator.at).")
        p, M = self.emulator.theta_train.shape[1], terms.unit.shape[0]
        n_out, N, N_o = self._lin.shape[0], self.X.shape[0], other.X.shape[0]
        cross, diag = np.empty((M, n_out, N_o, N)), np.empty((M, n_out, N_o))
        for o, (g, (_, d)) in enumerate(zip(self.emulator._gps, terms.per_output)):
            sf2 = np.exp(2 * g.log_params[0])
            kx = _m32(other._Xu, self._Xu, g.log_params[1 + p:-1])
            Vd = other._V[o] * d[:, None, :]                               # (M, N_o, N_tr)
            cross[:, o] = sf2 * kx - sf2**2 * (Vd @ self._V[o].T)
            diag[:, o] = np.maximum(sf2 - sf2**2 * np.einsum("mij,ij->mi", Vd, other._V[o]), 0.0)
        return cross, diag


@single_threaded_blas
def fit_emulator(X, theta, y, bounds, *, n_starts: int = 2, seed=None,
                 progress: Callable[[float], None] | None = None) -> Emulator:
    """Fit one GP emulator per output to ``y = simulate(X, theta)`` (R, N, n_out): inputs
    ``X`` (N, d_x), runs ``theta`` (R, p) in ``bounds`` (p, 2); ``n_starts`` L-BFGS-B starts.
    ``progress(fraction)`` after every optimiser iteration; raising from it stops the fit."""
    X = as_float_array(X, "X", ndim=2)
    theta = as_float_array(theta, "theta", ndim=2)
    y = as_float_array(y, "y", ndim=3)
    bounds = check_bounds(bounds)
    if y.shape[:2] != (theta.shape[0], X.shape[0]):
        raise ValueError(f"y must have shape (R, N, n_out) = ({theta.shape[0]}, {X.shape[0]}, "
                         f"n_out) to match theta {theta.shape} and X {X.shape}; received "
                         f"{y.shape}.")
    if bounds.shape != (theta.shape[1], 2):
        raise ValueError(f"bounds must have shape ({theta.shape[1]}, 2); received {bounds.shape}.")
    rng = np.random.default_rng(seed)
    x_lo = X.min(axis=0)
    x_span = np.where(np.ptp(X, axis=0) > 0, np.ptp(X, axis=0), 1.0)
    Xu = _unit(X, x_lo, x_span)
    Tu = _unit(theta, bounds[:, 0], bounds[:, 1] - bounds[:, 0])
    n_out = y.shape[2]
    gps = tuple(_fit_one(Tu, Xu, y[..., o], rng, n_starts, o,
                         None if progress is None else (lambda o=o: progress(o / n_out)))
                for o in range(n_out))
    return Emulator(X, theta, y, bounds, x_lo, x_span, gps)
