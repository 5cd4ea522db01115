"""The Matérn 3/2 kernel ``σ_f² m32(r_y) m32(r_x)`` in NumPy (Eq. 3 with exp(−√3 r), see
docs/method.md §3), written once in :func:`separable_matern`. Hyperparameters travel as one
log vector ``[log σ_f, log ℓ_y (d_y), log ℓ_x (d_x), log σ_n]`` of length P = 2 + d_y + d_x.
"""

from __future__ import annotations

import numpy as np

from ._linalg import workspace
from ._validation import as_float_array, as_log_params

__all__ = ["SQRT3", "matern32", "matern32_and_dlog_ell", "scaled_sq_dist", "split_log_params",
           "separable_matern", "kernel", "train_cov", "cross_cov"]

SQRT3 = np.sqrt(3.0)


def separable_matern(log_sf2, ry, rx=None, tmp=None) -> np.ndarray:
    """``σ_f² m32(r_y) m32(r_x) = (1 + s + a b) exp(log σ_f² − s)`` (Eq. 3), ``s = a + b``,
    from ``a = √3 r_y`` (``ry``, overwritten) and ``b = √3 r_x`` (``rx``, broadcasts; without
    it ``σ_f² m32(r_y)``); ``tmp`` is an optional buffer like ``ry``."""
    if rx is None:
        s = np.subtract(log_sf2, ry, out=tmp)
        ry += 1.0
    else:
        s = np.add(ry, rx, out=tmp)
        ry *= rx
        ry += s
        ry += 1.0
        np.subtract(log_sf2, s, out=s)
    np.exp(s, out=s)
    ry *= s
    return ry


def matern32(r2) -> np.ndarray:
    """``m32(r)`` from squared scaled distances ``r²`` (round-off below 0 is clipped).

    >>> float(matern32(0.0)), round(float(matern32(1.0)), 6)
    (1.0, 0.483358)
    """
    a = SQRT3 * np.sqrt(np.maximum(r2, 0.0))
    return separable_matern(0.0, a, tmp=np.empty_like(a))


def scaled_sq_dist(A, B, lengthscale) -> np.ndarray:
    """``Σ_d (a_d − b_d)² / ℓ_d²`` between the rows of ``A`` (..., Na, d) and ``B`` (..., Nb,
    d), ``lengthscale`` (..., d) -> (..., Na, Nb); leading dimensions broadcast."""
    A, B = np.asarray(A, dtype=np.float64), np.asarray(B, dtype=np.float64)
    inv = 1.0 / np.asarray(lengthscale, dtype=np.float64)
    shape = np.broadcast_shapes(A.shape[:-2], B.shape[:-2], inv.shape[:-1])
    out = np.zeros(shape + (A.shape[-2], B.shape[-2]))
    for k in range(A.shape[-1]):  # loop over dimensions keeps memory at one (..., Na, Nb) array
        s = inv[..., k, None]
        diff = (A[..., :, k] * s)[..., :, None] - (B[..., :, k] * s)[..., None, :]
        out += diff * diff
    return out


def matern32_and_dlog_ell(A, ell, sq=None) -> tuple[np.ndarray, np.ndarray]:
    """``m32`` (n, n) between the rows of ``A`` (n, d) for lengthscales ``ell`` (d,), and its
    derivatives in each ``log ℓ_d``, ``3 exp(−√3 r) Δ_d² / ℓ_d²`` (d, n, n); ``sq`` holds the
    ``Δ_d²`` (d, n, n) when a caller reuses them. The same operations as
    :func:`scaled_sq_dist` and :func:`matern32`, so the same bits."""
    At = np.ascontiguousarray(np.transpose(A), dtype=np.float64)     # C order: same bits below
    ell = np.asarray(ell, dtype=np.float64)
    As = At * (1.0 / ell)[:, None]
    diff = As[:, :, None] - As[:, None, :]
    a = SQRT3 * np.sqrt(np.add.reduce(diff * diff, axis=0))       # sums dimension by dimension
    e = np.exp(-a)
    if sq is None:
        sq = (At[:, :, None] - At[:, None, :]) ** 2
    return (a + 1.0) * e, (3.0 * e) * sq / np.array([v ** 2 for v in ell])[:, None, None]


def split_log_params(log_params, d_y: int, d_x: int):
    """``(σ_f (...), ℓ_y (..., d_y), ℓ_x (..., d_x), σ_n (...))`` from (..., P) logs."""
    lp = np.asarray(log_params, dtype=np.float64)
    return (np.exp(lp[..., 0]), np.exp(lp[..., 1:1 + d_y]),
            np.exp(lp[..., 1 + d_y:1 + d_y + d_x]), np.exp(lp[..., -1]))


def _check_kernel_args(log_params, Ya, Xa, Yb, Xb):
    Xa = as_float_array(Xa, "Xa", ndim=2, allow_empty=True)
    Xb = as_float_array(Xb, "Xb", ndim=2, allow_empty=True)
    if Xb.shape[1] != Xa.shape[1]:
        raise ValueError(f"Xb must have shape (Nb, d_x) with d_x = {Xa.shape[1]} like Xa "
                         f"{Xa.shape}; received {Xb.shape}.")
    Ya = as_float_array(Ya, "Ya", min_ndim=2, allow_empty=True)
    Yb = as_float_array(Yb, "Yb", min_ndim=2, allow_empty=True)
    for name, Y, X in (("Ya", Ya, Xa), ("Yb", Yb, Xb)):
        if Y.shape[-2] != X.shape[0]:
            raise ValueError(f"{name} must have shape (..., N, d_y) with N = {X.shape[0]} rows "
                             f"like X{name[-1]} {X.shape}; received {Y.shape}.")
    if Yb.shape[-1] != Ya.shape[-1]:
        raise ValueError(f"Yb must have d_y = {Ya.shape[-1]} columns like Ya {Ya.shape}; "
                         f"received {Yb.shape}.")
    lp = as_log_params(log_params, Ya.shape[-1], Xa.shape[1])
    try:
        np.broadcast_shapes(lp.shape[:-1], Ya.shape[:-2], Yb.shape[:-2])
    except ValueError:
        raise ValueError(f"the leading dimensions of log_params {lp.shape}, Ya {Ya.shape} and "
                         f"Yb {Yb.shape} do not broadcast; add size-1 axes to align them."
                         ) from None
    return lp, Ya, Xa, Yb, Xb


def kernel(log_params, Ya, Xa, Yb, Xb) -> np.ndarray:
    """Cross-covariance ``σ_f² m32(r_y) m32(r_x)`` (Eq. 3), without the noise term:
    ``log_params`` (..., P), ``Ya`` (..., Na, d_y), ``Xa`` (Na, d_x), ``Yb`` (..., Nb, d_y),
    ``Xb`` (Nb, d_x) -> (..., Na, Nb)."""
    log_params, Ya, Xa, Yb, Xb = _check_kernel_args(log_params, Ya, Xa, Yb, Xb)
    sf, ly, lx, _ = split_log_params(log_params, Ya.shape[-1], Xa.shape[-1])
    ry = SQRT3 * np.sqrt(scaled_sq_dist(Ya, Yb, ly))
    rx = SQRT3 * np.sqrt(scaled_sq_dist(Xa, Xb, lx))
    return separable_matern(2.0 * np.log(sf)[..., None, None], ry, rx)


def _scaled_dist(D: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """``√(Σ_d (D_d scale_d)²)`` (b, T) from differences D (b or 1, T, d), scale (b, d)."""
    if D.shape[-1] == 1:                              # no square root needed in 1-D
        return np.abs(D[..., 0]) * scale
    if D.shape[-1] == 0:
        return np.zeros((scale.shape[0], D.shape[-2]))
    D2 = np.broadcast_to(D * D, (scale.shape[0],) + D.shape[-2:])
    return np.sqrt(np.einsum("btd,bd->bt", D2, scale * scale))


def train_cov(theta: np.ndarray, Y: np.ndarray, X: np.ndarray, border=None) -> np.ndarray:
    """Lower triangle of ``K = K_ff + σ_n² I`` (b, N, N) for a chunk: theta (b, P), Y (b, N,
    d_y). With ``border = z`` (N,), the bordered ``[[K, ·], [zᵀ, c]]``, ``c = 2 zᵀz / σ_n² + 1
    > zᵀ K⁻¹ z``, whose factor's last row is ``L⁻¹ z`` (no separate solve)."""
    b, N, d_y = Y.shape
    n, d_x = N if border is None else N + 1, X.shape[1]
    I, J = np.tril_indices(N)
    ry = _scaled_dist(Y[:, I, :] - Y[:, J, :], SQRT3 * np.exp(-theta[:, 1:1 + d_y]))
    rx = _scaled_dist((X[I] - X[J])[None], SQRT3 * np.exp(-theta[:, 1 + d_y:1 + d_y + d_x]))
    K = np.zeros((b, n, n))
    K[:, I, J] = separable_matern(2.0 * theta[:, :1], ry, rx)
    sn2 = np.exp(2.0 * theta[:, -1:])
    K[:, np.arange(N), np.arange(N)] += sn2
    if border is not None:
        K[:, N, :N] = border
        K[:, N, N] = 2.0 * (border @ border) / sn2[:, 0] + 1.0
    return K


def _scaled_cross_dist(A: np.ndarray, B: np.ndarray, scale: np.ndarray, out: np.ndarray,
                       tmp: np.ndarray) -> np.ndarray:
    """``out[b, n, m] = √(Σ_d (scale[b, d] (A[b, n, d] − B[b, m, d]))²)`` in place: ``A`` (b or
    1, Na, d), ``B`` (b or 1, Nb, d), ``scale`` (b, d), buffers (b, Na, Nb)."""
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


def cross_cov(theta: np.ndarray, Ya: np.ndarray, Xa: np.ndarray, Yb: np.ndarray,
               Xb: np.ndarray) -> np.ndarray:
    """:func:`kernel` for a chunk: theta (b, P), Ya (b, Na, d_y), Xa (Na, d_x), Yb (b, Nb,
    d_y), Xb (Nb, d_x) -> (b, Na, Nb), in this thread's workspace (use it before the next call)."""
    d_y, d_x = Ya.shape[-1], Xa.shape[-1]
    shape = (theta.shape[0], Ya.shape[-2], Xb.shape[0])
    ry, rx, tmp = (workspace(name, shape) for name in ("cross", "cross_x", "cross_tmp"))
    _scaled_cross_dist(Ya, Yb, SQRT3 * np.exp(-theta[:, 1:1 + d_y]), ry, tmp)
    if d_x == 1:                      # |Δx| is shared by the chunk: one scaling pass
        np.multiply(np.abs(Xa[:, None, 0] - Xb[None, :, 0]),
                    SQRT3 * np.exp(-theta[:, 1 + d_y, None, None]), out=rx)
    else:
        _scaled_cross_dist(Xa[None], Xb[None], SQRT3 * np.exp(-theta[:, 1 + d_y:1 + d_y + d_x]),
                           rx, tmp)
    return separable_matern(2.0 * theta[:, :1, None], ry, rx, tmp)
