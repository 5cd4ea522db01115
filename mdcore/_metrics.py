"""Metrics of docs/method.md §8: NMSE, MMD, LPL and band coverage.

Every function takes column-wise data: ``(N,)`` for one output or ``(N, n_out)`` for
several, and returns a float or an ``(n_out,)`` array accordingly.
"""

from __future__ import annotations

import numpy as np
from scipy.stats import norm

from ._validation import as_float_array, as_positive_float, check_positive


def _columns(name: str, value, like: np.ndarray | None = None) -> np.ndarray:
    arr = as_float_array(value, name, min_ndim=1)
    if arr.ndim > 2:
        raise ValueError(f"{name} must have shape (N,) or (N, n_out); received {arr.shape}.")
    if like is not None and arr.shape != like.shape:
        raise ValueError(f"{name} must have the same shape as the targets {like.shape}; "
                         f"received {arr.shape}.")
    return arr


def _predictive(target, mean, var, *, strict: bool):
    """Checked (target, mean, var) columns; ``strict`` requires var > 0, else var ≥ 0."""
    t = _columns("target", target)
    return (t, _columns("mean", mean, t),
            check_positive(_columns("var", var, t), "var", strict=strict))


def _squeeze(out: np.ndarray, like: np.ndarray):
    return float(np.ravel(out)[0]) if like.ndim == 1 else out


def nmse(target, prediction):
    """Normalised mean squared error in percent, ``100 / (N var(t)) Σ (t_i − t̂_i)²`` with the
    1/N variance of the targets (docs/method.md §8).

    Parameters
    ----------
    target : ndarray of shape (N,) or (N, n_out)
        Test observations z, or the noise-free true δ.
    prediction : ndarray of the same shape
        Predictive means.
    """
    t = _columns("target", target)
    p = _columns("prediction", prediction, t)
    var = np.var(t, axis=0)
    if np.any(var <= 0):
        raise ValueError("target must vary (its variance is the NMSE's denominator); "
                         "received a constant column.")
    return _squeeze(100.0 * np.mean((t - p) ** 2, axis=0) / var, t)


def lpl(target, mean, var):
    """Log predictive likelihood ``Σ_i log N(z_i | E[z*_i], V[z*_i])`` (docs/method.md §8).

    Parameters
    ----------
    target : ndarray of shape (N,) or (N, n_out)
        Test observations.
    mean, var : ndarray of the same shape
        Predictive mean and variance of a new observation (including σ_n²).
    """
    t, m, v = _predictive(target, mean, var, strict=True)
    return _squeeze(-0.5 * np.sum((t - m) ** 2 / v + np.log(2.0 * np.pi * v), axis=0), t)


def coverage(target, mean, var, *, k: float = 3.0):
    """Fraction of targets inside the ``mean ± k·sd`` band (docs/method.md §8).

    Parameters
    ----------
    target, mean, var : ndarray of shape (N,) or (N, n_out)
        Test observations, predictive mean and variance (non-negative).
    k : float, default=3.0
        Band half-width in standard deviations (the paper reports 2 and 3).
    """
    k = as_positive_float(k, "k", "It is the band half-width in standard deviations.")
    t, m, v = _predictive(target, mean, var, strict=False)
    return _squeeze(np.mean(np.abs(t - m) <= k * np.sqrt(v), axis=0), t)


def _groups(X, n: int) -> np.ndarray:
    """Group label (n,) per row: equal rows of ``X`` are repeats of one test input."""
    if X is None:
        return np.arange(n)
    X = as_float_array(X, "X", min_ndim=1)
    if X.shape[0] != n:
        raise ValueError(f"X must have one row per target (N = {n}); received {X.shape}.")
    return np.unique(X.reshape(n, -1), axis=0, return_inverse=True)[1].ravel()


#: Groups of test inputs whose MMD terms are computed at once (bounds the (groups, n, n)
#: kernel and distance arrays: n = r + max(r, 20) pooled points per group).
MMD_CHUNK = 1024


def _mmd_groups(a: np.ndarray, mu: np.ndarray, s2: np.ndarray) -> np.ndarray:
    """Biased MMD (square root) between each row of points ``a`` (G, r) and N(mu, s2),
    Gaussian kernel; ``mu``, ``s2`` of shape (G,). Returns (G,)."""
    r = a.shape[1]
    q = max(r, 20)
    # Median heuristic over the pooled sample: the observations plus q predictive quantiles.
    quantiles = norm.ppf((np.arange(q) + 0.5) / q)
    out = np.empty(a.shape[0])
    for lo in range(0, a.shape[0], MMD_CHUNK):
        sl = slice(lo, lo + MMD_CHUNK)
        ag, m, v = a[sl], mu[sl, None], s2[sl, None]
        pooled = np.concatenate([ag, m + np.sqrt(v) * quantiles], axis=1)
        i, j = np.triu_indices(pooled.shape[1], 1)
        ell2 = np.maximum(np.median(np.abs(pooled[:, i] - pooled[:, j]), axis=1) ** 2,
                          1e-300)[:, None]
        kaa = np.mean(np.exp(-(ag[:, :, None] - ag[:, None, :]) ** 2 / (2.0 * ell2[:, :, None])),
                      axis=(1, 2))
        # Closed-form Gaussian expectations of the kernel:
        # E_y k(a, y) = sqrt(ℓ²/(ℓ²+s²)) exp(−(a−μ)²/(2(ℓ²+s²))), E k(y, y') = sqrt(ℓ²/(ℓ²+2s²)).
        kay = np.mean(np.sqrt(ell2 / (ell2 + v)) * np.exp(-(ag - m) ** 2 / (2.0 * (ell2 + v))),
                      axis=1)
        kyy = np.sqrt(ell2 / (ell2 + 2.0 * v))[:, 0]
        out[sl] = np.sqrt(np.maximum(kaa - 2.0 * kay + kyy, 0.0))
    return out


def mmd(target, mean, var, *, X=None):
    """Maximum mean discrepancy between observed repeats and the Gaussian predictive
    (docs/method.md §8).

    Per test input, the biased MMD (its square root) between the ``r`` observed repeats and
    ``N(E[z*], V[z*])`` with the Gaussian kernel ``exp(−(a − b)² / (2ℓ²))``, averaged over
    the test inputs. The predictive side is exact (closed-form Gaussian integrals of the
    kernel). ℓ is the median heuristic over a pooled sample: the repeats plus
    ``max(r, 20)`` evenly spaced quantiles of the predictive (a deterministic stand-in for
    predictive samples). docs/method.md §8: the paper's absolute values cannot be reproduced.

    Parameters
    ----------
    target : ndarray of shape (N,) or (N, n_out)
        Test observations; rows with equal ``X`` are repeats of one test input.
    mean, var : ndarray of the same shape
        Predictive mean and variance of a new observation at each row.
    X : ndarray of shape (N, d_x), optional
        Test inputs, to group repeats. Default: every row is its own input.
    """
    t, m, v = _predictive(target, mean, var, strict=False)
    groups = _groups(X, t.shape[0])
    t2, m2, v2 = (a.reshape(t.shape[0], -1) for a in (t, m, v))
    # Rows of each group in their original order; groups of equal size r are one batch.
    order = np.argsort(groups, kind="stable")
    sizes = np.bincount(groups)
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    vals = np.empty((sizes.size, t2.shape[1]))
    for r in np.unique(sizes[sizes > 0]):
        labels = np.flatnonzero(sizes == r)
        rows = order[starts[labels, None] + np.arange(r)]          # (groups, r)
        for o in range(t2.shape[1]):
            vals[labels, o] = _mmd_groups(t2[rows, o], np.mean(m2[rows, o], axis=1),
                                          np.mean(v2[rows, o], axis=1))
    return _squeeze(np.mean(vals[sizes > 0], axis=0), t)
