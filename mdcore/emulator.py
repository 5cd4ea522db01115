"""GP emulator of a simulator over the joint input (x, θ) (SPEC §4).

One emulator per output: a linear mean ``m = β₀ + βᵀ[x, θ]`` fitted by least squares,
plus a zero-mean GP on the residuals with the core's separable Matérn 3/2 kernel
(:func:`mdcore.kernels.matern32` on each block; ARD lengthscales in θ and in x)::

    k((θ, x), (θ', x')) = σ_f² m32(r_θ) m32(r_x) + σ_n² δ

Inputs are scaled to [0, 1] internally. This is the core's kernel with the simulator
parameters θ in the "y" slot, not a Matérn over the joint distance (SPEC §4 says
"Matérn 3/2 ARD over the joint input"); the product form is what makes the design
below solvable exactly and fast.

Simulator runs come as full sweeps: every run θ_r is evaluated at every training input
x_i, so the training covariance is ``σ_f² K_θ ⊗ K_x + σ_n² I``. With the eigenpairs
``K_θ = Q_θ Λ Q_θᵀ`` and ``K_x = Q_x M Q_xᵀ`` the marginal likelihood and predictions are
exact at O(R³ + N³ + R N (R + N)) instead of O(R³ N³), and scoring 100,000 candidate θ at
every training input costs two small matrix products.
"""

from __future__ import annotations

import importlib
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import scipy.optimize

from . import compiled
from .exceptions import ConvergenceWarning
from .gp import LOG_2PI
from .hyperfit import lbfgs_advice, lbfgs_converged
from .kernels import SQRT3, matern32, scaled_sq_dist
from .threads import single_threaded_blas
from .validation import as_float_array, check_bounds

__all__ = ["Emulator", "EmulatorArrays", "EmulatorAt", "EmulatorPrediction", "KronGP",
           "ThetaTerms", "fit_emulator"]


class EmulatorArrays(NamedTuple):
    """The fixed pieces of :class:`EmulatorAt`'s algebra as stacked float64 arrays, for
    compiled kernels (:meth:`EmulatorAt.arrays`). Shapes: R training θ, p parameters,
    N inputs, N_t training inputs of the emulator, n_out outputs.

    Attributes
    ----------
    t_lo, t_span : ndarray of shape (p,)
        θ's unit box: ``unit = (θ − t_lo) / t_span``.
    T_train : ndarray of shape (R, p)
        Training θ in the unit box.
    inv_ell : ndarray of shape (n_out, p)
        ``1 / ℓ_θ``.
    Q_t : ndarray of shape (n_out, R, R)
    W : ndarray of shape (n_out, R, N_t)
    lin : ndarray of shape (n_out, N)
        ``β₀ + β_xᵀ x``.
    beta_t : ndarray of shape (n_out, p)
    AK : ndarray of shape (n_out, R, N)
    V : ndarray of shape (n_out, N, N_t)
    sf4 : ndarray of shape (n_out,)
    prior : ndarray of shape (n_out, N, N)
        ``σ_f² m32(X, X)``.
    sf2 : ndarray of shape (n_out,)
        ``σ_f²``.
    G : ndarray of shape (n_out, R, N)
        ``W (V ⊙ V)ᵀ``: the predictive variance at ``x_n`` is
        ``σ_f² − σ_f⁴ Σ_a (k_θ Q_θ)_a² G[a, n]``.
    """

    t_lo: np.ndarray
    t_span: np.ndarray
    T_train: np.ndarray
    inv_ell: np.ndarray
    Q_t: np.ndarray
    W: np.ndarray
    lin: np.ndarray
    beta_t: np.ndarray
    AK: np.ndarray
    V: np.ndarray
    sf4: np.ndarray
    prior: np.ndarray
    sf2: np.ndarray
    G: np.ndarray


class ThetaTerms(NamedTuple):
    """The θ-dependent pieces of the emulator's posterior (:meth:`EmulatorAt.theta_terms`).

    Attributes
    ----------
    unit : ndarray of shape (M, p)
        θ scaled to the unit box.
    per_output : tuple of (ndarray (M, R), ndarray (M, N_train))
        Per output, ``k_θ = m32(θ, Θ_train)`` and ``d(θ) = (k_θ Q_θ)² W``.
    """

    unit: np.ndarray
    per_output: tuple


class EmulatorPrediction(NamedTuple):
    """Emulator moments.

    Attributes
    ----------
    mean, var : ndarray of shape (n_theta, N, n_out)
        Predictive mean ``E[y]`` and latent variance ``V[y]`` (simulator units).
    """

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
    """Scale inputs to the unit box: (A − lo) / span."""
    return (A - lo) / span


def _eig(K):
    lam, Q = np.linalg.eigh(K)
    return np.maximum(lam, 0.0), Q


def _numpy_eigh_kernel():
    """The kernel np.linalg.eigh calls for a real matrix (UPLO="L"), or None if NumPy
    moved it (then :func:`_eigh` calls np.linalg.eigh)."""
    try:
        return importlib.import_module("numpy.linalg._umath_linalg").eigh_lo
    except (ImportError, AttributeError):                # pragma: no cover
        return None


_eigh_lo = _numpy_eigh_kernel()


def _eigh(K):
    """``np.linalg.eigh(K)`` of a float64 matrix, bit for bit, without the ~4 µs of its
    checks and wrapping (the fit calls it ~1,000 times): NumPy's own LAPACK kernel. When
    that gives NaN (NaN in ``K``, or no convergence), the answer is np.linalg.eigh's own:
    its NaN, or its ``LinAlgError``."""
    if _eigh_lo is None:
        return np.linalg.eigh(K)
    with np.errstate(invalid="ignore"):
        lam, Q = _eigh_lo(K, signature="d->dd")
    if lam.size and np.isnan(lam[0]):
        return np.linalg.eigh(K)
    return lam, Q


def _design(Xu, Tu):
    """Rows [1, x, θ] for every (run, input) pair in run-major order: (R·N, 1 + d_x + p)."""
    R, N = Tu.shape[0], Xu.shape[0]
    return np.column_stack([np.ones(R * N), np.tile(Xu, (R, 1)), np.repeat(Tu, N, axis=0)])


def _sq_diffs(A) -> np.ndarray:
    """Squared differences of the rows of ``A`` (n, d) per column, shape (d, n, n)."""
    A = np.asarray(A, dtype=np.float64)
    return np.ascontiguousarray(((A[:, None, :] - A[None, :, :]) ** 2).transpose(2, 0, 1))


def _m32_and_dlog_ell(A, ell, diffs):
    """:func:`mdcore.kernels.matern32_and_dlog_ell` of ``A`` (n, d) at lengthscales ``ell``,
    given ``diffs = _sq_diffs(A)`` (fixed during a fit).

    The same floating-point operations in the same order (``scaled_sq_dist``, one
    exponential shared by ``m32`` and its derivative), so the results are bit-identical
    (``test_emulator`` checks), with about half the NumPy calls: the emulator fit is
    dominated by per-call overhead on these small matrices, and its result must not move
    (L-BFGS-B turns a 1-ulp change of the NLML into ~1e-5 in the hyperparameters).
    """
    n, d = A.shape
    inv = 1.0 / ell
    r2 = np.zeros((n, n))
    for k in range(d):
        a = A[:, k] * inv[k]
        diff = a[:, None] - a[None, :]
        r2 += diff * diff
    r = np.sqrt(r2)                            # r2 ≥ +0: what matern32's max(r2, 0) gives
    e = np.exp(-SQRT3 * r)
    ell2 = np.array([ell[k] ** 2 for k in range(d)])    # a scalar ** 2 is pow(), not x * x
    D = (3.0 * e) * diffs / ell2[:, None, None]
    return (1.0 + SQRT3 * r) * e, D


def _kron_solve(lp, Tu, Xu, res, diffs=None):
    """Eigen-solve of ``K = σ_f² K_θ ⊗ K_x + σ_n² I`` for residuals ``res`` (R, N).

    Returns the factors, their log-ℓ derivatives, the eigenpairs, ``σ_f² λ_a μ_b``,
    ``S_ab = σ_f² λ_a μ_b + σ_n²`` and ``α`` in the eigenbasis, ``(Q_θᵀ Res Q_x) / S``;
    shared by the likelihood and the fit. ``diffs``: ``(_sq_diffs(Tu), _sq_diffs(Xu))``.
    """
    p = Tu.shape[1]
    dt2, dx2 = (_sq_diffs(Tu), _sq_diffs(Xu)) if diffs is None else diffs
    Kt, Dt = _m32_and_dlog_ell(Tu, np.exp(lp[1:1 + p]), dt2)
    Kx, Dx = _m32_and_dlog_ell(Xu, np.exp(lp[1 + p:-1]), dx2)
    lam, Qt = _eig(Kt)
    mu, Qx = _eig(Kx)
    SO = np.exp(2 * lp[0]) * (lam[:, None] * mu[None, :])
    S = SO + np.exp(2 * lp[-1])
    return Kt, Dt, Kx, Dx, lam, Qt, mu, Qx, SO, S, (Qt.T @ res @ Qx) / S


def _kron_nlml(lp, Tu, Xu, res, diffs=None):
    """NLML of the Kronecker GP and its analytic gradient; ``res`` (R, N) residuals.

    With ``S_ab = σ_f² λ_a μ_b + σ_n²`` and ``P = Q_θᵀ Res Q_x``::

        NLML = ½ Σ P²/S + ½ Σ log S + (RN/2) log 2π
        ∂NLML/∂φ = ½ tr(K⁻¹ ∂K) − ½ αᵀ ∂K α,   α = vec(Q_θ (P/S) Q_xᵀ)

    ``diffs`` as in :func:`_kron_solve` (precomputed once per fit).
    :func:`_kron_nlml_compiled` gives the same bits, faster.
    """
    p = Tu.shape[1]
    sf2, sn2 = np.exp(2 * lp[0]), np.exp(2 * lp[-1])
    Kt, Dt, Kx, Dx, lam, Qt, mu, Qx, SO, S, Pa = _kron_solve(lp, Tu, Xu, res, diffs)
    PP = Pa * Pa
    f = 0.5 * (PP * S).sum() + 0.5 * np.log(S).sum() + 0.5 * res.size * LOG_2PI
    A0 = Qt @ Pa @ Qx.T
    g = np.empty_like(lp)
    Z = 1.0 / S - PP
    g[0] = (SO * Z).sum()
    g[-1] = sn2 * Z.sum()
    for d in range(p):
        diag_t = np.einsum("ra,rs,sa->a", Qt, Dt[d], Qt)
        g[1 + d] = 0.5 * sf2 * (((diag_t[:, None] * mu[None, :]) / S).sum()
                                - (A0 * (Dt[d] @ A0 @ Kx)).sum())
    for d in range(Xu.shape[1]):
        diag_x = np.einsum("ra,rs,sa->a", Qx, Dx[d], Qx)
        g[1 + p + d] = 0.5 * sf2 * (((lam[:, None] * diag_x[None, :]) / S).sum()
                                    - (A0 * (Kt @ A0 @ Dx[d])).sum())
    return f, g


def _kron_nlml_compiled(lp, Tu, Xu, res, diffs, k):
    """:func:`_kron_nlml` to the last bit, with its elementwise arithmetic and sums in the
    compiled kernels ``k`` (:func:`mdcore.compiled.fit_kernels`): about 30 calls per
    evaluation instead of about 100 (the fit is dominated by per-call overhead on these
    small matrices). ``exp``, ``log``, ``pow``, ``eigh`` (:func:`_eigh`) and the matrix
    products stay the NumPy/BLAS calls of :func:`_kron_nlml`, on the same operands."""
    p = Tu.shape[1]
    sf2, sn2 = np.exp(2 * lp[0]), np.exp(2 * lp[-1])
    (dt2, dx2), R, N = diffs, Tu.shape[0], Xu.shape[0]
    ell_t, ell_x = np.exp(lp[1:1 + p]), np.exp(lp[1 + p:-1])
    rt, tt, rx, tx = np.empty((R, R)), np.empty((R, R)), np.empty((N, N)), np.empty((N, N))
    k.fit_factors(Tu, ell_t, rt, tt, Xu, ell_x, rx, tx)
    Kt, Dt = np.empty((R, R)), np.empty((p, R, R))
    Kx, Dx = np.empty((N, N)), np.empty((Xu.shape[1], N, N))
    k.fit_kernels(rt, np.exp(tt), dt2, np.array([v ** 2 for v in ell_t]), Kt, Dt,
                  rx, np.exp(tx), dx2, np.array([v ** 2 for v in ell_x]), Kx, Dx)
    lam, Qt = _eigh(Kt)
    mu, Qx = _eigh(Kx)
    SO, S, Pa = np.empty((R, N)), np.empty((R, N)), np.empty((R, N))
    k.fit_spectrum(lam, mu, sf2, sn2, SO, S)
    s_f, s_log, s_0, s_n = k.fit_terms(Qt.T @ res @ Qx, S, SO, np.log(S), Pa)
    f = 0.5 * s_f + 0.5 * s_log + 0.5 * res.size * LOG_2PI
    A0 = Qt @ Pa @ Qx.T
    g = np.empty_like(lp)
    g[0] = s_0
    g[-1] = sn2 * s_n
    # the products of every dimension at once: a stack's matmul is each slice's, bit for bit
    k.fit_gradient(sf2, Qt, Dt, mu, Qx, Dx, lam, S, A0, Dt @ A0 @ Kx, Kt @ A0 @ Dx, g)
    return f, g


def _fit_one(Tu, Xu, y, rng, n_starts, output=0, kernels=None, step=None):
    """Fit one output: least-squares linear mean, then empirical Bayes for the GP.

    ``kernels`` (:func:`mdcore.compiled.fit_kernels`): evaluate the likelihood with
    :func:`_kron_nlml_compiled`, the same bits as :func:`_kron_nlml`, faster. ``step()``
    is called after every L-BFGS-B iteration (it may raise to stop the fit).
    """
    F = _design(Xu, Tu)
    beta, *_ = np.linalg.lstsq(F, y.ravel(), rcond=None)
    res = (y.ravel() - F @ beta).reshape(y.shape)
    sd = float(np.std(res)) or float(np.std(y)) or 1.0
    p, d_x = Tu.shape[1], Xu.shape[1]
    lo = np.r_[np.log(sd) - 3, np.full(p + d_x, np.log(0.03)), np.log(sd * 1e-7)]
    hi = np.r_[np.log(sd) + 3, np.full(p + d_x, np.log(30.0)), np.log(sd * 0.3)]
    best = None
    starts = lo + (hi - lo) * rng.uniform(size=(n_starts, lo.size))
    starts[0] = np.r_[np.log(sd), np.full(p + d_x, np.log(0.5)), np.log(sd * 1e-3)]
    diffs = (_sq_diffs(Tu), _sq_diffs(Xu))
    fun, args = ((_kron_nlml, (Tu, Xu, res, diffs)) if kernels is None else
                 (_kron_nlml_compiled, (Tu, Xu, res, diffs, kernels)))
    for x0 in starts:
        r = scipy.optimize.minimize(fun, x0, args=args, jac=True, method="L-BFGS-B",
                                    bounds=list(zip(lo, hi)),
                                    callback=None if step is None else (lambda *_: step()))
        if best is None or r.fun < best.fun:
            best = r
    if not lbfgs_converged(best, lo, hi):
        warnings.warn(f"emulator fit, output {output}: the best of {n_starts} L-BFGS-B runs did "
                      f"not converge ({best.message}; {lbfgs_advice(best)}); its "
                      "predictions may be off. Add simulator runs (n_runs) or raise n_starts.",
                      ConvergenceWarning, stacklevel=3)
    lp = best.x
    *_, Qt, _, Qx, _, S, Pa = _kron_solve(lp, Tu, Xu, res, diffs)
    return KronGP(lp, beta, Qt, Qx, np.exp(2 * lp[0]) * Qt @ Pa @ Qx.T, 1.0 / S)


@dataclass(frozen=True, eq=False)
class Emulator:
    """Fitted GP emulators (one per output) of ``simulate(X, θ)``.

    Build with :func:`fit_emulator`; call :meth:`predict`.

    Attributes
    ----------
    X_train : ndarray of shape (N, d_x)
        Training inputs (original units).
    theta_train : ndarray of shape (R, p)
        Simulator runs (original units).
    y_train : ndarray of shape (R, N, n_out)
    bounds : ndarray of shape (p, 2)
        Box the θ inputs are scaled with.
    """

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
    def predict(self, X, theta, *, backend: str | None = None) -> EmulatorPrediction:
        """Emulator mean and variance for every (θ, x) pair.

        Parameters
        ----------
        X : ndarray of shape (N, d_x)
        theta : ndarray of shape (n_theta, p)
        backend : {"auto", "numpy", "numba"}, optional
            ``"numpy"`` is the reference below; ``"numba"`` the compiled kernel
            (:func:`mdcore.compiled.emulator_moments`). Default ``MDCORE_BACKEND``, else
            numba when installed (:func:`mdcore.compiled.resolve_backend`). The two agree
            to rounding: the variance to ~1e-15 σ_f²; the mean to ~1e-11 of its magnitude,
            because with a tiny nugget it is a sum of terms ``k_θ A k_x`` up to ~1e5 times
            larger than itself, so either path carries that rounding.

        Returns
        -------
        EmulatorPrediction
            ``mean`` and ``var`` of shape (n_theta, N, n_out).
        """
        X, theta = self._inputs(X, theta)
        if compiled.resolve_backend(backend) == "numba":
            return EmulatorPrediction(*compiled.emulator_moments(self.at(X).arrays(), theta))
        d_x, p = self.X_train.shape[1], self.theta_train.shape[1]
        t_lo, t_span = self.bounds[:, 0], self.bounds[:, 1] - self.bounds[:, 0]
        Xu, Xtr = _unit(X, self._x_lo, self._x_span), _unit(self.X_train, self._x_lo, self._x_span)
        Tu, Ttr = _unit(theta, t_lo, t_span), _unit(self.theta_train, t_lo, t_span)
        mean = np.empty((theta.shape[0], X.shape[0], self.n_out))
        var = np.empty_like(mean)
        for o, g in enumerate(self._gps):
            sf2 = np.exp(2 * g.log_params[0])
            kt = matern32(scaled_sq_dist(Tu, Ttr, np.exp(g.log_params[1:1 + p])))   # (M, R)
            kx = matern32(scaled_sq_dist(Xu, Xtr, np.exp(g.log_params[1 + p:-1])))  # (N*, N)
            lin = g.beta[0] + Xu @ g.beta[1:1 + d_x]
            mean[..., o] = (kt @ g.A @ kx.T) + lin[None, :] + (Tu @ g.beta[1 + d_x:])[:, None]
            U = (kt @ g.Q_t) ** 2
            V = (kx @ g.Q_x) ** 2
            var[..., o] = np.maximum(sf2 - sf2**2 * (U @ g.W @ V.T), 0.0)
        return EmulatorPrediction(mean, var)

    @single_threaded_blas
    def implausibility(self, X, theta, z, V, *, rank: int = 1,
                       backend: str | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Combined implausibility of every θ (SPEC §5, Eq. 16) and the emulator variance.

        ``I(θ)`` is the ``rank``-th largest over the targets (n, o) of
        ``|z[n, o] − E[y]| / sqrt(V[n, o] + V[y])`` at ``(θ, X[n])``, output ``o``: with
        ``V = V_o + V_m`` what :func:`mdcore.history_matching.implausibility` and
        :func:`~mdcore.history_matching.combine` give on :meth:`predict`. The compiled path
        fuses the three and never stores the mean.

        Parameters
        ----------
        X : ndarray of shape (N, d_x)
        theta : ndarray of shape (M, p)
        z, V : ndarray of shape (N, n_out)
            Observations and the variance ``V_o + V_m`` added to the emulator's.
        rank : {1, 2, 3}, default=1
            The max, 2nd max or 3rd max rule.
        backend : {"auto", "numpy", "numba"}, optional
            As in :meth:`predict`; on the same backend, ``var`` equals :meth:`predict`'s
            and ``I`` is the formula above on its moments, to the last bit.

        Returns
        -------
        implausibility : ndarray of shape (M,)
        var : ndarray of shape (M, N, n_out)
            ``V[y]``, as :meth:`predict`'s.
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
        if compiled.resolve_backend(backend) == "numba":
            I, var, n_bad = compiled.emulator_scores(self.at(X).arrays(), theta, z, V,
                                                     int(rank))
            total = None
        else:
            mean, var = self.predict(X, theta, backend="numpy")
            total = V + var
            n_bad = int(np.count_nonzero(total <= 0))
        if n_bad:
            raise ValueError("V_o + V_m + var must be positive for every target; received a "
                             "zero. Give V_m > 0 or a positive observation variance.")
        if total is not None:                   # the NumPy reference
            I = np.abs(z - mean) / np.sqrt(total)
            I = -np.partition(-I.reshape(len(I), z.size), rank - 1, axis=-1)[:, rank - 1]
        return I, var

    def at(self, X) -> EmulatorAt:
        """The emulator's joint Gaussian at fixed inputs ``X`` as a function of θ.

        Everything that does not depend on θ is computed here, once, so that
        :meth:`EmulatorAt.moments` costs O(R² + R N + N² N_train) per θ (the Kennedy–
        O'Hagan likelihood evaluates it at every MCMC step).

        Parameters
        ----------
        X : ndarray of shape (N, d_x)
            Inputs (original units); repeated rows are allowed.
        """
        X = as_float_array(X, "X", ndim=2)
        d_x, p = self.X_train.shape[1], self.theta_train.shape[1]
        if X.shape[1] != d_x:
            raise ValueError(f"X must have shape (N, {d_x}); received {X.shape}.")
        Xu, Xtr = _unit(X, self._x_lo, self._x_span), _unit(self.X_train, self._x_lo, self._x_span)
        lin, AK, V, prior = [], [], [], []
        for g in self._gps:
            kx = matern32(scaled_sq_dist(Xu, Xtr, np.exp(g.log_params[1 + p:-1])))  # (N, N_tr)
            lin.append(g.beta[0] + Xu @ g.beta[1:1 + d_x])
            AK.append(g.A @ kx.T)
            V.append(kx @ g.Q_x)
            prior.append(np.exp(2 * g.log_params[0]) * matern32(
                scaled_sq_dist(Xu, Xu, np.exp(g.log_params[1 + p:-1]))))
        return EmulatorAt(self, X, Xu, np.stack(lin), np.stack(AK), np.stack(V), np.stack(prior))


@dataclass(frozen=True, eq=False)
class EmulatorAt:
    """Emulator moments at fixed inputs ``X``, for any θ; build with :meth:`Emulator.at`.

    For output ``o`` with Kronecker GP ``σ_f² K_θ ⊗ K_x + σ_n² I`` (eigenpairs
    ``Q_θ Λ Q_θᵀ``, ``Q_x M Q_xᵀ``, ``W = 1 / (σ_f² λ_a μ_b + σ_n²)``) the posterior of
    the emulated simulator at ``(θ, X_A)`` and ``(θ, X_B)`` is, with
    ``k_θ = m32(θ, Θ_train)``, ``V_A = m32(X_A, X_train) Q_x`` and
    ``d(θ) = (k_θ Q_θ)² W`` (a length-N_train vector)::

        m_η(X_A, θ)       = β₀ + βᵀ[x, θ] + k_θ A m32(X_A, X_train)ᵀ
        Σ_η(X_A, X_B; θ)  = σ_f² m32(X_A, X_B) − σ_f⁴ V_A diag(d(θ)) V_Bᵀ

    Only ``k_θ`` and ``d(θ)`` depend on θ. The diagonal of Σ_η equals
    :meth:`Emulator.predict`'s ``var``.

    Attributes
    ----------
    emulator : Emulator
    X : ndarray of shape (N, d_x)
    """

    emulator: Emulator
    X: np.ndarray
    _Xu: np.ndarray
    _lin: np.ndarray     # (n_out, N) x-part of the linear mean
    _AK: np.ndarray      # (n_out, R, N)
    _V: np.ndarray       # (n_out, N, N_train)
    _prior: np.ndarray   # (n_out, N, N) σ_f² m32(X, X)

    def theta_terms(self, theta, *, check: bool = True) -> ThetaTerms:
        """The θ-dependent pieces at ``theta`` (M, p), shared by every input set.

        One evaluation serves :meth:`moments_at` and :meth:`cross_cov_at` of every
        :class:`EmulatorAt` of the same emulator (an MCMC step, a prediction block).
        ``check=False`` skips validating ``theta`` (hot loops that built it themselves).
        """
        em = self.emulator
        p = em.theta_train.shape[1]
        if check:
            theta = np.atleast_2d(as_float_array(theta, "theta"))
            if theta.ndim != 2 or theta.shape[1] != p:
                raise ValueError(f"theta must have shape (M, {p}); received {theta.shape}.")
        t_lo, t_span = em.bounds[:, 0], em.bounds[:, 1] - em.bounds[:, 0]
        Tu, Ttr = _unit(theta, t_lo, t_span), _unit(em.theta_train, t_lo, t_span)
        terms = []
        for g in em._gps:
            kt = matern32(scaled_sq_dist(Tu, Ttr, np.exp(g.log_params[1:1 + p])))
            terms.append((kt, (kt @ g.Q_t) ** 2 @ g.W))
        return ThetaTerms(Tu, tuple(terms))

    def arrays(self) -> EmulatorArrays:
        """The fixed pieces of the algebra above, stacked over outputs (for compiled code)."""
        em = self.emulator
        p, d_x = em.theta_train.shape[1], self.X.shape[1]
        t_lo, t_span = em.bounds[:, 0], em.bounds[:, 1] - em.bounds[:, 0]
        gps = em.gps
        return EmulatorArrays(
            t_lo, t_span, _unit(em.theta_train, t_lo, t_span),
            np.stack([np.exp(-g.log_params[1:1 + p]) for g in gps]),
            np.stack([g.Q_t for g in gps]), np.stack([g.W for g in gps]), self._lin,
            np.stack([g.beta[1 + d_x:] for g in gps]), self._AK, self._V,
            np.array([np.exp(4 * g.log_params[0]) for g in gps]), self._prior,
            np.array([np.exp(2 * g.log_params[0]) for g in gps]),
            np.stack([g.W @ (V * V).T for g, V in zip(gps, self._V)]))

    def moments(self, theta):
        """Mean and covariance of the emulated simulator at ``X`` for each θ.

        Parameters
        ----------
        theta : ndarray of shape (M, p) or (p,)

        Returns
        -------
        mean : ndarray of shape (M, n_out, N)
        cov : ndarray of shape (M, n_out, N, N)
            ``Σ_η(X, X; θ)`` (output units squared).
        """
        return self.moments_at(self.theta_terms(theta))

    def moments_at(self, terms: ThetaTerms, *, with_cov: bool = True):
        """:meth:`moments` from :meth:`theta_terms`; ``cov`` is None unless ``with_cov``."""
        Tu, per_output = terms
        d_x = self.X.shape[1]
        M, (n_out, N) = Tu.shape[0], self._lin.shape
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
        """:meth:`cross_cov` from :meth:`theta_terms`. The θ-terms belong to the emulator,
        so one evaluation serves every input set."""
        if other.emulator is not self.emulator:
            raise ValueError("other must come from the same emulator (Emulator.at).")
        per_output = terms.per_output
        p = self.emulator.theta_train.shape[1]
        M = terms.unit.shape[0]
        n_out, N, N_o = self._lin.shape[0], self.X.shape[0], other.X.shape[0]
        cross = np.empty((M, n_out, N_o, N))
        diag = np.empty((M, n_out, N_o))
        for o, (g, (_, d)) in enumerate(zip(self.emulator._gps, per_output)):
            sf2 = np.exp(2 * g.log_params[0])
            kx = matern32(scaled_sq_dist(other._Xu, self._Xu, np.exp(g.log_params[1 + p:-1])))
            Vd = other._V[o] * d[:, None, :]                               # (M, N_o, N_tr)
            cross[:, o] = sf2 * kx - sf2**2 * (Vd @ self._V[o].T)
            diag[:, o] = np.maximum(sf2 - sf2**2 * np.einsum("mij,ij->mi", Vd, other._V[o]), 0.0)
        return cross, diag


@single_threaded_blas
def fit_emulator(X, theta, y, bounds, *, n_starts: int = 2, seed=None,
                 backend: str | None = None,
                 progress: Callable[[float], None] | None = None) -> Emulator:
    """Fit one GP emulator per output from full simulator sweeps.

    Parameters
    ----------
    X : ndarray of shape (N, d_x)
        Distinct training inputs (replicates removed).
    theta : ndarray of shape (R, p)
        Simulator runs.
    y : ndarray of shape (R, N, n_out)
        ``simulate(X, theta)``.
    bounds : ndarray of shape (p, 2)
        Parameter box used to scale θ to [0, 1].
    n_starts : int, default=2
        L-BFGS-B starts per output for the hyperparameters (empirical Bayes).
    seed : int or Generator, optional
    backend : {"auto", "numpy", "numba"}, optional
        ``"numba"`` evaluates the likelihood and its gradient with compiled kernels that
        give the NumPy evaluation's exact bits (:func:`_kron_nlml_compiled`), so the
        fitted emulator is identical on both backends, only faster. Default as
        :func:`mdcore.compiled.resolve_backend`.
    progress : callable, optional
        ``progress(fraction)`` after every optimiser iteration; if it raises (e.g.
        :class:`mdcore.Cancelled`), the fit stops.

    Returns
    -------
    Emulator
    """
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
    kernels = compiled.fit_kernels() if compiled.resolve_backend(backend) == "numba" else None
    n_out = y.shape[2]
    gps = tuple(_fit_one(Tu, Xu, y[..., o], rng, n_starts, o, kernels,
                         None if progress is None else (lambda o=o: progress(o / n_out)))
                for o in range(n_out))
    return Emulator(X, theta, y, bounds, x_lo, x_span, gps)
