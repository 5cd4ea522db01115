"""Batched Gaussian-process regression core (SPEC §2–3, paper Eqs. 2–9).

The discrepancy GP maps simulator outputs and inputs ``{y, x}`` to observations ``z``
with the separable kernel (paper Eq. 3, corrected)::

    k((y, x), (y', x')) = σ_f² · m32(r_y) · m32(r_x),   m32(r) = (1 + √3 r) exp(−√3 r)

The paper prints ``exp(+√3 r)``; the Matérn 3/2 kernel decays, so ``exp(−√3 r)`` is used.

Hyperparameters travel as one log vector of length ``P = 2 + d_y + d_x``::

    [log σ_f, log ℓ_y,1 … log ℓ_y,d_y, log ℓ_x,1 … log ℓ_x,d_x, log σ_n]

Every function is batched: leading dimensions of ``log_params`` (..., P) and ``Y``
(..., N, d_y) broadcast against each other, and the work is chunked internally so that
hundreds of thousands of (hyperparameter, Y) pairs run in bounded memory.
"""

from __future__ import annotations

import os
import threading
import warnings
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Callable, NamedTuple

import numpy as np
import scipy.linalg
import scipy.optimize

from ._threads import single_threaded_blas
from ._validation import as_float_array, choose

__all__ = [
    "GPPrediction", "HyperFit", "GaussianPrior", "NumericalWarning",
    "matern32", "scaled_sq_dist", "kernel", "neg_log_marginal_likelihood",
    "nlml_and_gradient", "predict", "fit_hyperparameters", "default_bounds",
    "split_log_params",
]

SQRT3 = np.sqrt(3.0)
LOG_2PI = np.log(2.0 * np.pi)
#: Relative jitter steps (× mean diagonal) tried when a Cholesky fails (SPEC §3).
JITTER_LADDER = (1e-10, 1e-9, 1e-8, 1e-7, 1e-6, 1e-5, 1e-4)
#: Working-memory budget of one chunk, in bytes.
CHUNK_BYTES = 4 * 2**20
#: Threads used over chunks (the core is otherwise single-threaded NumPy).
N_WORKERS = max(1, min(os.cpu_count() or 1, 8))


class NumericalWarning(RuntimeWarning):
    """A numerical fallback was used (jitter, clipped variance, low effective sample size)."""


class GPPrediction(NamedTuple):
    """Predictive moments of the latent GP.

    Attributes
    ----------
    mean : ndarray of shape (..., N*)
        Predictive mean (Eq. 7).
    var : ndarray of shape (..., N*)
        Latent predictive variance ``k** − diag(K*f K⁻¹ Kf*)``; add ``noise_var``
        for the variance of a new observation.
    noise_var : ndarray of shape (...)
        ``σ_n²`` of each batch element.
    """

    mean: np.ndarray
    var: np.ndarray
    noise_var: np.ndarray


class HyperFit(NamedTuple):
    """Result of :func:`fit_hyperparameters`.

    Attributes
    ----------
    log_params : ndarray of shape (P,)
        The optimum, in the SPEC §2 layout.
    nlml : float
        Negative log marginal likelihood (Eq. 9) at the optimum.
    objective : float
        The minimised value: ``nlml`` for empirical Bayes, ``nlml − log prior`` for MAP.
    method : str
        ``"qpso"`` or ``"lbfgs"``.
    n_evaluations : int
        Objective evaluations used (a batch of particles counts each particle).
    converged : bool
        Whether the final gradient polish reported success.
    """

    log_params: np.ndarray
    nlml: float
    objective: float
    method: str
    n_evaluations: int
    converged: bool


@dataclass(frozen=True)
class GaussianPrior:
    """Independent Gaussian prior on the log hyperparameter vector (SPEC §2 layout).

    Parameters
    ----------
    mean : ndarray of shape (P,)
        Prior means of the log hyperparameters.
    var : ndarray of shape (P,)
        Prior variances (second argument of ``N(·, ·)`` in SPEC §9 is a variance).

    Examples
    --------
    >>> prior = GaussianPrior(mean=[0.0, 0.0, 0.0, -3.0], var=[1.0, 1.0, 1.0, 1.0])
    >>> prior.sample(2, seed=0).shape
    (2, 4)
    """

    mean: np.ndarray
    var: np.ndarray

    def __post_init__(self):
        mean = as_float_array(self.mean, "prior mean", ndim=1)
        var = as_float_array(self.var, "prior var", ndim=1)
        if mean.shape != var.shape:
            raise ValueError(f"prior mean and var must have the same shape (P,); received "
                             f"{mean.shape} and {var.shape}.")
        if np.any(var <= 0):
            raise ValueError(f"prior var must be positive; received {var.tolist()}. "
                             "Use a small positive variance for a nearly fixed hyperparameter.")
        object.__setattr__(self, "mean", mean)
        object.__setattr__(self, "var", var)

    @property
    def size(self) -> int:
        """Number of hyperparameters ``P``."""
        return self.mean.size

    def logpdf(self, log_params) -> np.ndarray:
        """Log density at ``log_params`` of shape (..., P); returns shape (...)."""
        d = np.asarray(log_params, dtype=np.float64) - self.mean
        return -0.5 * np.sum(d * d / self.var + np.log(2.0 * np.pi * self.var), axis=-1)

    def grad(self, log_params) -> np.ndarray:
        """Gradient of :meth:`logpdf`, shape (..., P)."""
        return -(np.asarray(log_params, dtype=np.float64) - self.mean) / self.var

    def sample(self, n: int, seed=None) -> np.ndarray:
        """Draw ``n`` samples, shape (n, P), from ``default_rng(seed)``."""
        if int(n) < 1:
            raise ValueError(f"n must be at least 1 to draw prior samples; received {n}.")
        rng = np.random.default_rng(seed)
        return self.mean + np.sqrt(self.var) * rng.standard_normal((int(n), self.size))


# ---------------------------------------------------------------------------------------
# Kernel pieces


def matern32(r2) -> np.ndarray:
    """Matérn 3/2 correlation from squared scaled distance, ``(1 + √3 r) exp(−√3 r)``.

    Parameters
    ----------
    r2 : ndarray
        Squared scaled distances ``r²`` (any shape); tiny negative round-off is clipped.
    """
    r = np.sqrt(np.maximum(r2, 0.0))
    return (1.0 + SQRT3 * r) * np.exp(-SQRT3 * r)


def scaled_sq_dist(A, B, lengthscale) -> np.ndarray:
    """Squared distance ``Σ_d (a_d − b_d)² / ℓ_d²`` between all rows of ``A`` and ``B``.

    Shapes: ``A`` (..., Na, d), ``B`` (..., Nb, d), ``lengthscale`` (..., d) ->
    (..., Na, Nb); leading dimensions broadcast. With ``d = 0`` the result is zeros.
    """
    A = np.asarray(A, dtype=np.float64)
    B = np.asarray(B, dtype=np.float64)
    inv = 1.0 / np.asarray(lengthscale, dtype=np.float64)
    d = A.shape[-1]
    shape = np.broadcast_shapes(A.shape[:-2], B.shape[:-2], inv.shape[:-1])
    out = np.zeros(shape + (A.shape[-2], B.shape[-2]))
    for k in range(d):  # loop over dimensions keeps memory at one (..., Na, Nb) array
        s = inv[..., k, None]
        diff = (A[..., :, k] * s)[..., :, None] - (B[..., :, k] * s)[..., None, :]
        out += diff * diff
    return out


def split_log_params(log_params, d_y: int, d_x: int):
    """Split (..., P) log hyperparameters into natural-scale pieces.

    Returns ``(sigma_f, ell_y, ell_x, sigma_n)`` with shapes (...), (..., d_y),
    (..., d_x), (...).
    """
    lp = np.asarray(log_params, dtype=np.float64)
    return (np.exp(lp[..., 0]), np.exp(lp[..., 1:1 + d_y]),
            np.exp(lp[..., 1 + d_y:1 + d_y + d_x]), np.exp(lp[..., -1]))


def _separable_matern(log_sf2, ry, rx, tmp=None) -> np.ndarray:
    """``σ_f² m32(r_y) m32(r_x)`` from distances already multiplied by √3 (Eq. 3).

    ``(1 + a)(1 + b) exp(−a − b) = (1 + s + a b) exp(log σ_f² − s)``, ``s = a + b``:
    one exp. The result overwrites ``ry`` (which must have the full broadcast shape;
    ``rx`` may broadcast against it); ``tmp``, a buffer like ``ry``, is optional.
    """
    s = np.add(ry, rx, out=tmp)
    ry *= rx
    ry += s
    ry += 1.0
    np.subtract(log_sf2, s, out=s)
    np.exp(s, out=s)
    ry *= s
    return ry


def kernel(log_params, Ya, Xa, Yb, Xb) -> np.ndarray:
    """Cross-covariance ``σ_f² m32(r_y) m32(r_x)`` (Eq. 3), without the noise term.

    Shapes: ``log_params`` (..., P); ``Ya`` (..., Na, d_y); ``Xa`` (Na, d_x);
    ``Yb`` (..., Nb, d_y); ``Xb`` (Nb, d_x) -> (..., Na, Nb).
    """
    d_y, d_x = np.shape(Ya)[-1], np.shape(Xa)[-1]
    sf, ly, lx, _ = split_log_params(log_params, d_y, d_x)
    ry = SQRT3 * np.sqrt(scaled_sq_dist(Ya, Yb, ly))
    rx = SQRT3 * np.sqrt(scaled_sq_dist(Xa, Xb, lx))
    return _separable_matern(2.0 * np.log(sf)[..., None, None], ry, rx)


# ---------------------------------------------------------------------------------------
# Validation and chunked iteration over the broadcast batch


class _Problem(NamedTuple):
    log_params: np.ndarray  # (..., P)
    Y: np.ndarray           # (..., N, d_y)
    X: np.ndarray           # (N, d_x)
    z: np.ndarray           # (N,)
    batch_shape: tuple


def _check_problem(log_params, Y, X, z) -> _Problem:
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
    d_y = Y.shape[-1]
    lp = as_float_array(log_params, "log_params", min_ndim=1)
    P = 2 + d_y + d_x
    if lp.shape[-1] != P:
        raise ValueError(
            f"log_params must have last dimension P = 2 + d_y + d_x = 2 + {d_y} + {d_x} = {P} "
            f"([log σ_f, log ℓ_y×{d_y}, log ℓ_x×{d_x}, log σ_n]); received shape {lp.shape}.")
    try:
        batch = np.broadcast_shapes(lp.shape[:-1], Y.shape[:-2])
    except ValueError:
        raise ValueError(
            f"the leading dimensions of log_params {lp.shape} and Y {Y.shape} do not "
            f"broadcast ({lp.shape[:-1]} vs {Y.shape[:-2]}); add size-1 axes to align them."
        ) from None
    return _Problem(lp, Y, X, z, batch)


def _gather(arr: np.ndarray, core_ndim: int, batch_shape: tuple, multi: tuple) -> np.ndarray:
    """Rows of ``arr`` (batch..., core...) for flat batch indices unravelled in ``multi``.

    Indexes only the needed rows, so broadcasting never materialises the full batch.
    """
    own = arr.shape[:arr.ndim - core_ndim]
    offset = len(batch_shape) - len(own)
    index = tuple(multi[offset + i] if n != 1 else np.zeros_like(multi[0])
                  for i, n in enumerate(own))
    n = len(multi[0]) if multi else 1
    if not index:
        return np.broadcast_to(arr, (n,) + arr.shape)
    return arr[index]


def _chunks(batch_shape: tuple, bytes_per_item: float):
    """(slice, multi-index, size) chunks covering the flattened batch."""
    total = int(np.prod(batch_shape, dtype=np.int64))
    step = max(1, int(CHUNK_BYTES // max(bytes_per_item, 1.0)))
    out = []
    for start in range(0, total, step):
        idx = np.arange(start, min(total, start + step))
        multi = np.unravel_index(idx, batch_shape) if batch_shape else ()
        out.append((slice(start, start + len(idx)), multi, len(idx)))
    return out


def _for_each_chunk(work: Callable, chunks: list) -> None:
    """Run ``work(slice, multi, n)`` on every chunk, on all cores.

    NumPy's element-wise loops and LAPACK release the GIL, so threads over independent
    chunks scale on the machine's cores; each chunk writes a disjoint output slice.
    """
    workers = min(N_WORKERS, len(chunks))
    if workers <= 1:
        for c in chunks:
            work(*c)
        return
    with ThreadPoolExecutor(max_workers=workers) as pool:
        for f in [pool.submit(work, *c) for c in chunks]:
            f.result()


# ---------------------------------------------------------------------------------------
# Batched linear algebra

try:  # the gufunc behind np.linalg.cholesky: NaN per failed matrix instead of raising
    from numpy.linalg import _umath_linalg as _ul

    def _raw_cholesky(K):
        with np.errstate(invalid="ignore", over="ignore", divide="ignore", under="ignore"):
            return _ul.cholesky_lo(K, signature="d->d")
except (ImportError, AttributeError):  # pragma: no cover - fallback for other NumPy builds
    def _raw_cholesky(K):
        out = np.empty_like(K)
        for i in range(K.shape[0]):
            try:
                out[i] = np.linalg.cholesky(K[i])
            except np.linalg.LinAlgError:
                out[i] = np.nan
        return out


class _JitterLog:
    """Counts matrices that needed jitter or failed, to warn once per public call."""

    def __init__(self):
        self.jittered = 0
        self.failed = 0
        self.max_jitter = 0.0
        self._lock = threading.Lock()

    def record(self, jittered: int, failed: int, max_jitter: float):
        with self._lock:
            self.jittered += jittered
            self.failed += failed
            self.max_jitter = max(self.max_jitter, max_jitter)

    def warn(self, what: str):
        if self.jittered:
            warnings.warn(
                f"{what}: {self.jittered} covariance matrix(es) were not numerically positive "
                f"definite; added jitter up to {self.max_jitter:.1e} × mean diagonal.",
                NumericalWarning, stacklevel=3)
        if self.failed:
            warnings.warn(
                f"{what}: {self.failed} covariance matrix(es) stayed non-positive-definite "
                f"after jitter up to {max(JITTER_LADDER, default=0.0):.0e} × mean diagonal; "
                "their NLML is "
                "+inf (zero weight) and their predictions are NaN.",
                NumericalWarning, stacklevel=3)


def _cholesky(K: np.ndarray, log: _JitterLog, n_cov: int | None = None):
    """Lower Cholesky factors of (B, n, n) matrices with a per-matrix jitter ladder.

    The jitter (SPEC §3: growing steps × mean diagonal) is scaled by, and added to, the
    first ``n_cov`` diagonal entries only (default all), so a bordered matrix
    ``[[K, z], [zᵀ, c]]`` jitters just its covariance block.

    Returns ``(L, ok)``; rows with ``ok == False`` failed every jitter step and hold NaN.
    """
    n_cov = K.shape[-1] if n_cov is None else n_cov
    L = _raw_cholesky(K)
    bad = np.isnan(L[:, -1, -1])
    if not np.any(bad):
        return L, ~bad
    idx = np.nonzero(bad)[0]
    diag = np.arange(n_cov)
    scale = np.mean(K[idx][:, diag, diag], axis=-1)
    used = np.zeros(len(idx))
    for jit in JITTER_LADDER:
        todo = np.isnan(L[idx, -1, -1])
        if not np.any(todo):
            break
        sel = idx[todo]
        Kj = K[sel]
        Kj[:, diag, diag] += (jit * scale[todo])[:, None]
        L[sel] = _raw_cholesky(Kj)
        used[todo] = jit
    ok = ~np.isnan(L[:, -1, -1])
    log.record(int(np.count_nonzero(ok[idx])), int(np.count_nonzero(~ok)),
               float(np.max(used[ok[idx]], initial=0.0)))
    return L, ok


def _solve_lower_inplace(L: np.ndarray, B: np.ndarray) -> np.ndarray:
    """Overwrite ``B`` (b, N, M) with ``L⁻¹ B`` row by row (no temporaries of B's size)."""
    for i in range(L.shape[-1]):
        if i:
            B[:, i, :] -= (L[:, i:i + 1, :i] @ B[:, :i, :])[:, 0, :]
        B[:, i, :] /= L[:, i, i, None]
    return B


_local = threading.local()


def _workspace(name: str, shape: tuple) -> np.ndarray:
    """A per-thread reusable float64 buffer of ``shape`` (contents undefined).

    Fresh multi-megabyte arrays come from the OS page by page, and at GP-chunk sizes the
    page faults cost more than the arithmetic; reusing one buffer per thread avoids them.
    """
    cache = _local.__dict__.setdefault("buffers", {})
    size = int(np.prod(shape))
    buf = cache.get(name)
    if buf is None or buf.size < size:
        buf = cache[name] = np.empty(size)
    return buf[:size].reshape(shape)


def _scaled_dist(D: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """``scale_b · sqrt(Σ_d D²/ℓ²)``-style distances (b, T) from differences D (b or 1, T, d)
    and per-dimension factors ``scale`` (b, d) (``√3/ℓ`` here)."""
    if D.shape[-1] == 1:                              # no square root needed in 1-D
        return np.abs(D[..., 0]) * scale
    if D.shape[-1] == 0:
        return np.zeros((scale.shape[0], D.shape[-2]))
    D2 = np.broadcast_to(D * D, (scale.shape[0],) + D.shape[-2:])
    return np.sqrt(np.einsum("btd,bd->bt", D2, scale * scale))


def _train_cov(theta: np.ndarray, Y: np.ndarray, X: np.ndarray, border=None) -> np.ndarray:
    """``K = K_ff + σ_n² I`` for a flat chunk: theta (b, P), Y (b, N, d_y) -> (b, N, N).

    Only the lower triangle is filled (the upper one is zero): the Cholesky factorisation
    and forward substitution read nothing else, and this halves the kernel work.
    With ``border = z`` (N,) the result is the bordered (b, N+1, N+1) matrix
    ``[[K, ·], [zᵀ, c]]`` with ``c = 2 zᵀz / σ_n² + 1 > zᵀ K⁻¹ z``: its Cholesky factor
    carries ``L⁻¹ z`` in the last row, so the NLML needs no separate triangular solve.
    """
    b, N, d_y = Y.shape
    n = N if border is None else N + 1
    d_x = X.shape[1]
    I, J = np.tril_indices(N)
    ry = _scaled_dist(Y[:, I, :] - Y[:, J, :], SQRT3 * np.exp(-theta[:, 1:1 + d_y]))
    rx = _scaled_dist((X[I] - X[J])[None], SQRT3 * np.exp(-theta[:, 1 + d_y:1 + d_y + d_x]))
    K = np.zeros((b, n, n))
    K[:, I, J] = _separable_matern(2.0 * theta[:, :1], ry, rx)
    sn2 = np.exp(2.0 * theta[:, -1:])
    K[:, np.arange(N), np.arange(N)] += sn2
    if border is not None:
        K[:, N, :N] = border
        K[:, N, N] = 2.0 * (border @ border) / sn2[:, 0] + 1.0
    return K


def _scaled_cross_dist(A: np.ndarray, B: np.ndarray, scale: np.ndarray, out: np.ndarray,
                       tmp: np.ndarray) -> np.ndarray:
    """``out[b, n, m] = sqrt(Σ_d (scale[b, d] (A[b, n, d] − B[b, m, d]))²)`` in place.

    ``A`` (b or 1, Na, d), ``B`` (b or 1, Nb, d), ``scale`` (b, d); ``out`` and ``tmp``
    are (b, Na, Nb) work buffers. The scale is applied to the (b, N, d) inputs, not to the
    (b, Na, Nb) differences, and writing into buffers avoids a fresh allocation per
    element-wise step, which at these sizes costs more than the arithmetic.
    """
    d = A.shape[-1]
    if d == 0:
        out[...] = 0.0
        return out
    As, Bs = A * scale[:, None, :], B * scale[:, None, :]
    if d == 1:
        np.subtract(As[:, :, None, 0], Bs[:, None, :, 0], out=out)
        return np.abs(out, out=out)
    for k in range(d):
        dst = out if k == 0 else tmp
        np.subtract(As[:, :, None, k], Bs[:, None, :, k], out=dst)
        dst *= dst
        if k:
            out += tmp
    return np.sqrt(out, out=out)


def _cross_cov(theta: np.ndarray, Ya: np.ndarray, Xa: np.ndarray, Yb: np.ndarray,
               Xb: np.ndarray) -> np.ndarray:
    """Flat-chunk cross-covariance: theta (b, P), Ya (b, Na, d_y), Xa (Na, d_x),
    Yb (b, Nb, d_y), Xb (Nb, d_x) -> (b, Na, Nb); same values as :func:`kernel`.

    The result lives in this thread's workspace: use it before the next call."""
    b, d_y, d_x = theta.shape[0], Ya.shape[-1], Xa.shape[-1]
    shape = (b, Ya.shape[-2], Xb.shape[0])
    ry, rx, tmp = (_workspace(name, shape) for name in ("cross", "cross_x", "cross_tmp"))
    _scaled_cross_dist(Ya, Yb, SQRT3 * np.exp(-theta[:, 1:1 + d_y]), ry, tmp)
    if d_x == 1:                      # |Δx| is shared by the chunk: one scaling pass
        np.multiply(np.abs(Xa[:, None, 0] - Xb[None, :, 0]),
                    SQRT3 * np.exp(-theta[:, 1 + d_y, None, None]), out=rx)
    else:
        _scaled_cross_dist(Xa[None], Xb[None], SQRT3 * np.exp(-theta[:, 1 + d_y:1 + d_y + d_x]),
                           rx, tmp)
    return _separable_matern(2.0 * theta[:, :1, None], ry, rx, tmp)


# ---------------------------------------------------------------------------------------
# Public batched functions


@single_threaded_blas
def neg_log_marginal_likelihood(log_params, Y, X, z) -> np.ndarray:
    """Negative log marginal likelihood (Eq. 9), batched over hyperparameters and ``Y``.

    ``NLML = ½ zᵀ K⁻¹ z + Σ log L_ii + (N/2) log 2π`` with ``K = K_ff + σ_n² I``,
    ``L = chol(K)``.

    Parameters
    ----------
    log_params : ndarray of shape (..., P)
        ``P = 2 + d_y + d_x``, SPEC §2 layout.
    Y : ndarray of shape (..., N, d_y)
        Simulator outputs used as GP inputs; leading dims broadcast with ``log_params``.
    X : ndarray of shape (N, d_x)
        Inputs.
    z : ndarray of shape (N,)
        Observations.

    Returns
    -------
    ndarray of shape (...)
        The NLML of every broadcast batch element. A matrix that stays non-positive-definite
        after the jitter ladder gets ``+inf`` and a :class:`NumericalWarning`.

    Examples
    --------
    >>> X = np.linspace(0, 1, 5)[:, None]; Y = np.sin(3 * X); z = (Y + X)[:, 0]
    >>> lp = np.array([[0.0, 0.0, 0.0, -2.0], [0.5, 0.0, 0.0, -2.0]])
    >>> neg_log_marginal_likelihood(lp, Y, X, z).shape
    (2,)
    """
    prob = _check_problem(log_params, Y, X, z)
    N = prob.X.shape[0]
    out = np.empty(int(np.prod(prob.batch_shape, dtype=np.int64)))
    log = _JitterLog()
    per_item = 8.0 * N * (4 * N + 2 * prob.Y.shape[-1] + 4)

    def work(sl, multi, n):
        theta = _gather(prob.log_params, 1, prob.batch_shape, multi)
        Yc = _gather(prob.Y, 2, prob.batch_shape, multi)
        L, ok = _cholesky(_train_cov(theta, Yc, prob.X, border=prob.z), log, n_cov=N)
        w = L[:, N, :N]                                   # L⁻¹ z from the bordered factor
        logdet = np.sum(np.log(np.diagonal(L, axis1=-2, axis2=-1)[:, :N]), axis=-1)
        val = 0.5 * np.sum(w * w, axis=-1) + logdet + 0.5 * N * LOG_2PI  # Eq. 9
        out[sl] = np.where(ok, val, np.inf)

    _for_each_chunk(work, _chunks(prob.batch_shape, per_item))
    log.warn("neg_log_marginal_likelihood")
    return out.reshape(prob.batch_shape)


@single_threaded_blas
def predict(log_params, Y, X, z, Y_star, X_star) -> GPPrediction:
    """Posterior predictive moments of the latent GP (Eq. 7), batched.

    Parameters
    ----------
    log_params : ndarray of shape (..., P)
    Y : ndarray of shape (..., N, d_y)
        Training simulator outputs.
    X : ndarray of shape (N, d_x)
    z : ndarray of shape (N,)
    Y_star : ndarray of shape (..., N*, d_y)
        Test simulator outputs; leading dims broadcast with ``Y`` and ``log_params``.
    X_star : ndarray of shape (N*, d_x)

    Returns
    -------
    GPPrediction
        ``mean`` and latent ``var`` of shape (..., N*), ``noise_var`` of shape (...).

    Examples
    --------
    >>> X = np.linspace(0, 1, 5)[:, None]; Y = np.sin(3 * X); z = (Y + X)[:, 0]
    >>> p = predict([0.0, 0.0, 0.0, -3.0], Y, X, z, Y[:2], X[:2])
    >>> p.mean.shape, p.var.shape
    ((2,), (2,))
    """
    prob = _check_problem(log_params, Y, X, z)
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
    mean = np.empty((total, M))
    var = np.empty((total, M))
    noise = np.empty(total)
    log = _JitterLog()
    per_item = 8.0 * (N * (4 * N + 3 * M + 2 * d_y) + 4 * M)

    def work(sl, multi, n):
        theta = _gather(prob.log_params, 1, batch, multi)
        Yc = _gather(prob.Y, 2, batch, multi)
        Ys = _gather(Y_star, 2, batch, multi)
        L, ok = _cholesky(_train_cov(theta, Yc, prob.X, border=prob.z), log, n_cov=N)
        # Eq. 7 via V = L⁻¹ K_f* and w = L⁻¹ z: mean = Vᵀ w, var = k** − Σ V².
        V = _solve_lower_inplace(L[:, :N, :N], _cross_cov(theta, Yc, prob.X, Ys, X_star))
        mean[sl] = np.einsum("bnm,bn->bm", V, L[:, N, :N])
        sf2 = np.exp(2.0 * theta[:, 0])
        var[sl] = np.maximum(sf2[:, None] - np.einsum("bnm,bnm->bm", V, V), 0.0)
        noise[sl] = np.exp(2.0 * theta[:, -1])
        if not np.all(ok):
            mean[sl][~ok] = np.nan
            var[sl][~ok] = np.nan

    _for_each_chunk(work, _chunks(batch, per_item))
    log.warn("predict")
    return GPPrediction(mean.reshape(batch + (M,)), var.reshape(batch + (M,)),
                        noise.reshape(batch))


def nlml_and_gradient(log_params, Y, X, z) -> tuple[float, np.ndarray]:
    """NLML (Eq. 9) and its analytic gradient for one hyperparameter vector.

    Uses ``∂NLML/∂φ = ½ tr((K⁻¹ − ααᵀ) ∂K/∂φ)``, ``α = K⁻¹ z`` (Rasmussen & Williams
    Eq. 5.9), with ``∂m32/∂log ℓ_d = 3 exp(−√3 r) Δ_d² / ℓ_d²``.

    Parameters
    ----------
    log_params : ndarray of shape (P,)
    Y : ndarray of shape (N, d_y)
    X : ndarray of shape (N, d_x)
    z : ndarray of shape (N,)

    Returns
    -------
    nlml : float
    grad : ndarray of shape (P,)
    """
    prob = _check_problem(log_params, Y, X, z)
    if prob.batch_shape != ():
        raise ValueError(f"nlml_and_gradient takes one vector: log_params (P,) and Y (N, d_y); "
                         f"received batch shape {prob.batch_shape}. Use "
                         "neg_log_marginal_likelihood for batches.")
    lp, Y, X, z = prob.log_params, prob.Y, prob.X, prob.z
    N, d_y, d_x = X.shape[0], Y.shape[1], X.shape[1]
    sf, ly, lx, sn = split_log_params(lp, d_y, d_x)
    ry2 = scaled_sq_dist(Y, Y, ly)
    rx2 = scaled_sq_dist(X, X, lx)
    my, mx = matern32(ry2), matern32(rx2)
    Kf = sf**2 * my * mx
    K = Kf + sn**2 * np.eye(N)
    log = _JitterLog()
    L, ok = _cholesky(K[None], log)
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
    ey = np.exp(-SQRT3 * np.sqrt(np.maximum(ry2, 0.0)))
    for d in range(d_y):
        D = (Y[:, None, d] - Y[None, :, d]) ** 2 / ly[d] ** 2
        grad[1 + d] = 0.5 * np.sum(W * sf**2 * mx * 3.0 * ey * D)
    ex = np.exp(-SQRT3 * np.sqrt(np.maximum(rx2, 0.0)))
    for d in range(d_x):
        D = (X[:, None, d] - X[None, :, d]) ** 2 / lx[d] ** 2
        grad[1 + d_y + d] = 0.5 * np.sum(W * sf**2 * my * 3.0 * ex * D)
    grad[-1] = 0.5 * np.trace(W) * 2.0 * sn**2
    return float(nlml), grad


def default_bounds(Y, X, z) -> np.ndarray:
    """Search box for the log hyperparameters, shape (P, 2), derived from the data scales.

    σ_f ∈ [1e-2, 1e2] × s_z with ``s_z = sqrt(mean z²)`` (zero-mean GP);
    each ℓ ∈ [1e-2, 1e2] × the input's range; σ_n ∈ [1e-6, 1] × s_z.
    """
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


def _qpso(objective: Callable, lo: np.ndarray, hi: np.ndarray, rng, n_particles: int,
          n_iterations: int):
    """Quantum-behaved PSO (Sun et al. 2004, SPEC §3); returns (best x, best f, evals)."""
    P = lo.size
    x = lo + (hi - lo) * rng.uniform(size=(n_particles, P))
    f = objective(x)
    pbest, pf = x.copy(), f.copy()
    g = int(np.argmin(pf))
    for t in range(n_iterations):
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


@single_threaded_blas
def fit_hyperparameters(Y, X, z, *, log_prior: GaussianPrior | None = None, bounds=None,
                        method: str = "qpso", seed=None, n_particles: int = 40,
                        n_iterations: int = 120, n_starts: int = 8,
                        polish: bool = True) -> HyperFit:
    """Empirical Bayes (Eq. 8): minimise the NLML over the log hyperparameters.

    With ``log_prior`` the objective is ``NLML − log p(φ)`` (MAP) instead.

    Parameters
    ----------
    Y : ndarray of shape (N, d_y)
    X : ndarray of shape (N, d_x)
    z : ndarray of shape (N,)
    log_prior : GaussianPrior, optional
        Prior over the log vector; turns empirical Bayes into MAP.
    bounds : ndarray of shape (P, 2), optional
        Box in log space; default :func:`default_bounds`.
    method : {"qpso", "lbfgs"}, default="qpso"
        ``"qpso"``: the paper's quantum-behaved particle swarm (batched over particles),
        then, with ``polish``, one L-BFGS-B run with the analytic gradient from the swarm's
        best. ``"lbfgs"``: multi-start L-BFGS-B with the analytic gradient from
        ``n_starts`` uniform starting points.
    seed : int or numpy.random.Generator, optional
        Same seed, same result.

    Returns
    -------
    HyperFit

    Examples
    --------
    >>> X = np.linspace(0, 1, 8)[:, None]; Y = np.sin(3 * X); z = (Y + X)[:, 0]
    >>> fit = fit_hyperparameters(Y, X, z, method="lbfgs", n_starts=2, seed=0)
    >>> fit.log_params.shape
    (4,)
    """
    choose(method, "method", {"qpso", "lbfgs"})
    prob = _check_problem(np.zeros(2 + np.shape(Y)[-1] + np.shape(X)[-1]), Y, X, z)
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

    def batch_objective(theta):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", NumericalWarning)
            f = neg_log_marginal_likelihood(theta, Y, X, z)
        return f if log_prior is None else f - log_prior.logpdf(theta)

    def objective_and_grad(theta):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", NumericalWarning)
            f, g = nlml_and_gradient(theta, Y, X, z)
        if log_prior is not None:
            f, g = f - float(log_prior.logpdf(theta)), g - log_prior.grad(theta)
        if not np.isfinite(f):
            return 1e300, np.zeros_like(theta)
        return f, g

    evals, converged = 0, False
    if method == "qpso":
        best, best_f, evals = _qpso(batch_objective, lo, hi, rng, n_particles, n_iterations)
        starts = [best] if polish else []
    else:
        starts = list(lo + (hi - lo) * rng.uniform(size=(max(int(n_starts), 1), P)))
        best, best_f = starts[0], np.inf
    for x0 in starts:
        res = scipy.optimize.minimize(objective_and_grad, x0, jac=True, method="L-BFGS-B",
                                      bounds=list(zip(lo, hi)))
        evals += int(res.nfev)
        if res.fun < best_f:
            best, best_f, converged = res.x, float(res.fun), bool(res.success)
    nlml = float(batch_objective(best[None])[0]) if log_prior is None else \
        float(neg_log_marginal_likelihood(best, Y, X, z))
    return HyperFit(np.asarray(best, dtype=np.float64), nlml, float(best_f), method, evals,
                    converged)
