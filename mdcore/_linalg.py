"""Batched Cholesky with a jitter ladder, and the bounded-memory chunks of the GP core."""

from __future__ import annotations

import threading
import warnings

import numpy as np

from ._exceptions import NumericalWarning
from ._threads import run_pieces

__all__ = ["JITTER_LADDER", "CHUNK_BYTES", "JitterLog", "cholesky", "solve_lower_inplace",
           "workspace", "gather", "chunks", "for_each_chunk"]

#: Relative jitter steps (× mean diagonal) tried when a Cholesky fails.
JITTER_LADDER = (1e-10, 1e-9, 1e-8, 1e-7, 1e-6, 1e-5, 1e-4)
#: Working-memory budget of one chunk, in bytes.
CHUNK_BYTES = 4 * 2**20


def _raw_cholesky(K: np.ndarray) -> np.ndarray:
    """Lower factors of (B, n, n) matrices, NaN where not positive definite (bisects on error)."""
    try:
        return np.linalg.cholesky(K)
    except np.linalg.LinAlgError:
        pass
    if K.shape[0] == 1:
        return np.full_like(K, np.nan)
    half = K.shape[0] // 2
    return np.concatenate([_raw_cholesky(K[:half]), _raw_cholesky(K[half:])])


class JitterLog:
    """Counts matrices that needed jitter or failed, to warn once per public call."""

    def __init__(self):
        self.jittered, self.failed, self.max_jitter = 0, 0, 0.0
        self._lock = threading.Lock()

    def record(self, jittered: int, failed: int, max_jitter: float):
        with self._lock:
            self.jittered += jittered
            self.failed += failed
            self.max_jitter = max(self.max_jitter, max_jitter)

    def record_steps(self, step: np.ndarray, failed: np.ndarray):
        """Record a batch: ``step`` (B,) the ladder step each matrix used (0 for none),
        ``failed`` (B,) bool those that failed every step."""
        jittered = (step > 0.0) & ~failed
        if np.any(failed) or np.any(jittered):
            self.record(int(np.count_nonzero(jittered)), int(np.count_nonzero(failed)),
                        float(np.max(step[jittered], initial=0.0)))

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
                "their NLML is +inf (zero weight) and their predictions are NaN.",
                NumericalWarning, stacklevel=3)


def cholesky(K: np.ndarray, log: JitterLog, n_cov: int | None = None):
    """Lower factors ``(L, ok)`` of (B, n, n) matrices, NaN where ``ok`` is False.

    A failed matrix retries with :data:`JITTER_LADDER` × the mean of its first ``n_cov``
    diagonal entries (default all) added to them, so a bordered ``[[K, z], [zᵀ, c]]`` jitters
    only ``K``; ``log`` records the outcome.
    """
    n_cov = K.shape[-1] if n_cov is None else n_cov
    L = _raw_cholesky(K)
    step = np.zeros(K.shape[0])
    idx = np.flatnonzero(np.isnan(L[:, -1, -1]))
    if idx.size:
        diag = np.arange(n_cov)
        scale = np.mean(K[idx][:, diag, diag], axis=-1)
        for jit in JITTER_LADDER:
            todo = np.isnan(L[idx, -1, -1])
            if not np.any(todo):
                break
            Kj = K[idx[todo]]
            Kj[:, diag, diag] += (jit * scale[todo])[:, None]
            L[idx[todo]] = _raw_cholesky(Kj)
            step[idx[todo]] = jit
    ok = ~np.isnan(L[:, -1, -1])
    log.record_steps(step, ~ok)
    return L, ok


def solve_lower_inplace(L: np.ndarray, B: np.ndarray) -> np.ndarray:
    """Overwrite ``B`` (b, N, M) with ``L⁻¹ B`` row by row (no temporaries of B's size)."""
    for i in range(L.shape[-1]):
        if i:
            B[:, i, :] -= (L[:, i:i + 1, :i] @ B[:, :i, :])[:, 0, :]
        B[:, i, :] /= L[:, i, i, None]
    return B


_local = threading.local()


def workspace(name: str, shape: tuple) -> np.ndarray:
    """A per-thread reusable float64 buffer of ``shape``, contents undefined (at chunk sizes,
    fresh arrays' page faults cost more than the arithmetic)."""
    cache = _local.__dict__.setdefault("buffers", {})
    size = int(np.prod(shape))
    buf = cache.get(name)
    if buf is None or buf.size < size:
        buf = cache[name] = np.empty(size)
    return buf[:size].reshape(shape)


def gather(arr: np.ndarray, core_ndim: int, batch_shape: tuple, multi: tuple) -> np.ndarray:
    """Rows of ``arr`` (batch..., core...) for the flat batch indices unravelled in
    ``multi``, without materialising the broadcast batch."""
    own = arr.shape[:arr.ndim - core_ndim]
    offset = len(batch_shape) - len(own)
    index = tuple(multi[offset + i] if n != 1 else np.zeros_like(multi[0])
                  for i, n in enumerate(own))
    if not index:
        return np.broadcast_to(arr, (len(multi[0]) if multi else 1,) + arr.shape)
    return arr[index]


def chunks(batch_shape: tuple, bytes_per_item: float):
    """(slice, multi-index, size) chunks covering the flattened batch."""
    total = int(np.prod(batch_shape, dtype=np.int64))
    step = max(1, int(CHUNK_BYTES // max(bytes_per_item, 1.0)))
    out = []
    for start in range(0, total, step):
        idx = np.arange(start, min(total, start + step))
        multi = np.unravel_index(idx, batch_shape) if batch_shape else ()
        out.append((slice(start, start + len(idx)), multi, len(idx)))
    return out


#: ``for_each_chunk(work, chunks(...))`` runs ``work(slice, multi, n)`` per chunk on the compute
#: threads (NumPy's loops and LAPACK release the GIL); each writes a disjoint output slice.
for_each_chunk = run_pieces
