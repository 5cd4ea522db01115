"""Batched linear algebra and the chunk engine of the GP core.

- :func:`cholesky`: lower Cholesky factors of a batch of matrices with a jitter ladder per
  matrix (growing steps × mean diagonal), and :class:`JitterLog`, which counts what needed
  jitter or failed so a public call warns once (never a silent NaN).
- :func:`solve_lower_inplace`: forward substitution over a batch without temporaries.
- The chunk engine: :func:`chunks` splits a broadcast batch into pieces of bounded memory,
  :func:`gather` picks a chunk's rows without materialising the broadcast, and
  :func:`for_each_chunk` runs chunks on the compute threads (:mod:`mdcore.threads`);
  :func:`workspace` hands each thread reusable buffers.

Examples
--------
>>> import numpy as np
>>> K = np.stack([np.eye(2), [[1.0, 2.0], [2.0, 1.0]]])     # the second is not PD
>>> L, ok = cholesky(K, JitterLog())
>>> ok.tolist(), bool(np.isnan(L[1]).all())
([True, False], True)
"""

from __future__ import annotations

import threading
import warnings
from collections.abc import Callable

import numpy as np

from .exceptions import NumericalWarning
from .threads import run_pieces

__all__ = ["JITTER_LADDER", "CHUNK_BYTES", "JitterLog", "cholesky", "cholesky_steps",
           "solve_lower_inplace", "workspace", "gather", "chunks", "for_each_chunk"]

#: Relative jitter steps (× mean diagonal) tried when a Cholesky fails.
JITTER_LADDER = (1e-10, 1e-9, 1e-8, 1e-7, 1e-6, 1e-5, 1e-4)
#: Working-memory budget of one chunk, in bytes.
CHUNK_BYTES = 4 * 2**20


def _raw_cholesky(K: np.ndarray) -> np.ndarray:
    """Lower factors of (B, n, n) matrices; NaN for the ones that are not positive definite.

    One batched :func:`numpy.linalg.cholesky` call; when it raises, the batch is halved
    until the failing matrices are found, so a few failures cost O(failures × log B)
    batched calls, and the factors of the others are exactly NumPy's.
    """
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
        self.jittered = 0
        self.failed = 0
        self.max_jitter = 0.0
        self._lock = threading.Lock()

    def record(self, jittered: int, failed: int, max_jitter: float):
        with self._lock:
            self.jittered += jittered
            self.failed += failed
            self.max_jitter = max(self.max_jitter, max_jitter)

    def record_steps(self, step: np.ndarray, failed: np.ndarray):
        """Record a batch by outcome: ``step`` (B,) the ladder step each matrix used (0 for
        none), ``failed`` (B,) bool those that failed every step."""
        jittered = (step > 0.0) & ~failed
        n_failed = int(np.count_nonzero(failed))
        n_jittered = int(np.count_nonzero(jittered))
        if n_failed or n_jittered:
            self.record(n_jittered, n_failed, float(np.max(step[jittered], initial=0.0)))

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


def cholesky(K: np.ndarray, log: JitterLog, n_cov: int | None = None):
    """Lower Cholesky factors of (B, n, n) matrices with a per-matrix jitter ladder.

    The jitter (growing steps × mean diagonal) is scaled by, and added to, the
    first ``n_cov`` diagonal entries only (default all), so a bordered matrix
    ``[[K, z], [zᵀ, c]]`` jitters just its covariance block. ``log`` records the matrices
    that needed jitter or failed.

    Returns ``(L, ok)``; rows with ``ok == False`` failed every jitter step and hold NaN.
    """
    L, ok, step = cholesky_steps(K, n_cov)
    log.record_steps(step, ~ok)
    return L, ok


def cholesky_steps(K: np.ndarray, n_cov: int | None = None):
    """:func:`cholesky` without the record: ``(L, ok, step)``, ``step`` (B,) the ladder
    step each matrix used (0 without jitter; for a failed one the last step tried)."""
    n_cov = K.shape[-1] if n_cov is None else n_cov
    L = _raw_cholesky(K)
    bad = np.isnan(L[:, -1, -1])
    step = np.zeros(K.shape[0])
    if not np.any(bad):
        return L, ~bad, step
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
    step[idx] = used
    return L, ~np.isnan(L[:, -1, -1]), step


def solve_lower_inplace(L: np.ndarray, B: np.ndarray) -> np.ndarray:
    """Overwrite ``B`` (b, N, M) with ``L⁻¹ B`` row by row (no temporaries of B's size)."""
    for i in range(L.shape[-1]):
        if i:
            B[:, i, :] -= (L[:, i:i + 1, :i] @ B[:, :i, :])[:, 0, :]
        B[:, i, :] /= L[:, i, i, None]
    return B


_local = threading.local()


def workspace(name: str, shape: tuple) -> np.ndarray:
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


def gather(arr: np.ndarray, core_ndim: int, batch_shape: tuple, multi: tuple) -> np.ndarray:
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


def for_each_chunk(work: Callable, pieces: list) -> None:
    """Run ``work(slice, multi, n)`` on every chunk, on the compute threads.

    NumPy's element-wise loops and LAPACK release the GIL, so threads over independent
    chunks scale on the machine's cores; each chunk writes a disjoint output slice.
    """
    run_pieces(work, pieces)
