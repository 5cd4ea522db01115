"""Compiled (numba) GP kernels: the fast path beside the NumPy reference (SPEC §3, §6).

The functions here compute what :func:`mdcore.gp.neg_log_marginal_likelihood` and
:func:`mdcore.gp.predict` compute (Eqs. 7 and 9), with the same bordered Cholesky, the same
jitter ladder and the same warnings, but fused per (hyperparameter, Y) pair: kernel build
(Eq. 3), Cholesky, triangular solves, NLML and predictive moments run in small per-thread
buffers, with no pairs × N × N temporaries. :func:`mixture_sums` goes one step further for
scenarios 2–3 and accumulates the mixture sums of Eq. 13/15 directly, so the per-pair
moments are never stored. :func:`emulator_moments` and :func:`emulator_scores` do the same
for the history-matching emulator at many candidate θ (SPEC §4–5): its moments, or the
combined implausibility (Eq. 16) fused with them, a block of candidates at a time; and
:func:`fit_kernels` evaluate the emulator fit's likelihood with the exact bits of NumPy.

numba is optional. Nothing here imports it until a kernel is first needed (or
:func:`warm_up` is called); :func:`available` says whether it can be. Inputs are assumed
validated by the caller (:mod:`mdcore.gp` checks shapes and finiteness first).

Compile cost
    Kernels are compiled once per machine and cached on disk (numba ``cache=True``, next
    to this file, or in ``NUMBA_CACHE_DIR``); a later process only loads them.
    :func:`warm_up` loads (or compiles) every kernel on tiny inputs;
    :func:`warm_up_in_background` does it in a daemon thread, for the app and the CLI to
    call at start-up.

Threads
    The kernels are serial and release the GIL. A call is split into pieces (ranges of
    pairs, or of history-matching candidates, about 0.05 s of work each) that run on one
    process-wide pool of :func:`num_threads` threads (``MDCORE_NUM_THREADS`` if set, else
    every core). Every caller (app sessions, jobs) queues its pieces on that same pool, so
    the process never runs more compute threads than that, and concurrent calls take turns
    piece by piece. numba's own threading layer is not used (no ``parallel=True``, no
    OpenMP team, no nested parallelism), and the kernels call no BLAS, so the BLAS thread
    limit does not concern them. The emulator fit's small kernels (:func:`fit_kernels`)
    run in the calling thread, between BLAS calls that its caller holds to one thread.

Examples
--------
>>> import numpy as np
>>> from mdcore import compiled
>>> X = np.linspace(0, 1, 5)[:, None]; Y = np.sin(3 * X); z = (Y + X)[:, 0]
>>> lp = np.array([[0.0, 0.0, 0.0, -2.0], [0.5, 0.0, 0.0, -2.0]])
>>> compiled.nlml(lp, Y, X, z).shape  # doctest: +SKIP
(2,)
"""

from __future__ import annotations

import importlib.util
import os
import threading
import time
import warnings
from concurrent.futures import ThreadPoolExecutor
from typing import NamedTuple

import numpy as np

__all__ = [
    "BACKENDS",
    "BACKEND_ENV",
    "THREADS_ENV",
    "MixtureSums",
    "available",
    "emulator_moments",
    "emulator_scores",
    "koh_log_likelihood",
    "mixture_sums",
    "nlml",
    "nlml_batch",
    "num_threads",
    "predict",
    "predict_batch",
    "resolve_backend",
    "warm_up",
    "warm_up_in_background",
]

#: Values of the ``backend=`` argument of :mod:`mdcore.gp` and the pipeline.
BACKENDS = ("auto", "numpy", "numba")
#: Environment variable giving the default backend (one of :data:`BACKENDS`).
BACKEND_ENV = "MDCORE_BACKEND"
#: Environment variable limiting the compute threads of mdcore (a positive integer).
THREADS_ENV = "MDCORE_NUM_THREADS"
#: Work of one piece (a kernel call on a range of pairs), in flops: about 0.05 s.
LAUNCH_FLOPS = 2e8
#: Pieces a large call is split into, for load balance across the compute threads.
PIECES = 32
#: Fewest pairs in a piece.
MIN_PIECE = 64

_POOLS: dict[int, ThreadPoolExecutor] = {}


def _forget_pools_after_fork() -> None:
    """In a forked child (a fork-based ``ProcessPoolExecutor``), drop the thread pools:
    their threads did not survive the fork, and work queued on them would wait for ever.
    The child starts new ones on first use."""
    _POOLS.clear()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_pools_after_fork)
_POOL_LOCK = threading.Lock()
_kernels_module = None
_koh_module = None
_emulator_module = None
_warm_thread: threading.Thread | None = None


def available() -> bool:
    """Whether numba can be imported (the compiled path can run)."""
    if _kernels_module is not None:
        return True
    try:
        return importlib.util.find_spec("numba") is not None
    except (ImportError, ValueError):        # e.g. sys.modules["numba"] = None
        return False


def resolve_backend(backend: str | None = None) -> str:
    """The GP backend to use: ``"numpy"`` (the reference) or ``"numba"`` (this module).

    Parameters
    ----------
    backend : {"auto", "numpy", "numba"} or None
        ``None`` reads :data:`BACKEND_ENV` (``MDCORE_BACKEND``), default ``"auto"``.
        ``"auto"`` is ``"numba"`` when numba is installed, else ``"numpy"``.

    Raises
    ------
    ValueError
        For an unknown name, or ``"numba"`` without numba installed.
    """
    source = "backend"
    if backend is None:
        backend, source = os.environ.get(BACKEND_ENV, "").strip() or "auto", BACKEND_ENV
    if backend not in BACKENDS:
        raise ValueError(f"{source} must be one of {', '.join(map(repr, BACKENDS))}; "
                         f"received {backend!r}.")
    if backend == "auto":
        return "numba" if available() else "numpy"
    if backend == "numba" and not available():
        raise ValueError(f"{source}='numba' needs numba, which is not installed; install it "
                         "with pip install 'mdcore[fast]', or use backend='numpy'.")
    return backend


def _kernels():
    """The kernel module, imported on first use (the import may compile or load cache)."""
    global _kernels_module
    if _kernels_module is None:
        try:
            from . import _compiled_kernels
        except ImportError as exc:
            raise ImportError(
                "the compiled GP path needs numba (pip install 'numba>=0.60'); "
                f"importing it failed ({exc}). Use backend='numpy' instead.") from exc
        _kernels_module = _compiled_kernels
    return _kernels_module


def _koh_kernels():
    """The KOH kernel module, imported on first use."""
    global _koh_module
    if _koh_module is None:
        _kernels()                          # the same clear ImportError without numba
        from . import _compiled_koh
        _koh_module = _compiled_koh
    return _koh_module


def _emulator_kernels():
    """The history-matching emulator kernel module, imported on first use."""
    global _emulator_module
    if _emulator_module is None:
        _kernels()                          # the same clear ImportError without numba
        from . import _compiled_emulator
        _emulator_module = _compiled_emulator
    return _emulator_module


def cores() -> int:
    """Cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:            # not on Linux
        return os.cpu_count() or 1


def num_threads() -> int:
    """Compute threads of the compiled path: ``MDCORE_NUM_THREADS`` if set, else all cores."""
    raw = os.environ.get(THREADS_ENV, "").strip()
    if not raw:
        return cores()
    try:
        n = int(raw)
    except ValueError:
        n = 0
    if n < 1:
        raise ValueError(f"{THREADS_ENV} must be a positive integer (the number of compute "
                         f"threads); received {raw!r}. Unset it to use every core.")
    return n


def _pool(n: int) -> ThreadPoolExecutor:
    """The process-wide pool of ``n`` compute threads (one per distinct ``n``)."""
    with _POOL_LOCK:
        pool = _POOLS.get(n)
        if pool is None:
            pool = _POOLS[n] = ThreadPoolExecutor(max_workers=n,
                                                  thread_name_prefix="mdcore-compiled")
        return pool


def _pieces(B: int, N: int, d: int, M: int = 0) -> list[tuple[int, int]]:
    """Ranges of pairs: at most about :data:`LAUNCH_FLOPS` of work each, and about
    :data:`PIECES` of them for load balance. They depend on the problem size only (not on
    the thread count), so sums over pieces are reproducible."""
    per_pair = N**3 / 3.0 + N * N * (d + 12.0) + M * (N * N + N * (d + 12.0))
    size = max(MIN_PIECE, min(-(-B // PIECES), int(LAUNCH_FLOPS / per_pair)))
    return [(b0, min(B, b0 + size)) for b0 in range(0, B, size)]


def _in_pieces(work, pieces):
    """``[work(b0, b1) for (b0, b1) in pieces]``, on the compute threads.

    Every call (every app session, every job) queues its pieces on the same pool, so the
    process never runs more than :func:`num_threads` compute threads and concurrent calls
    take turns piece by piece. A single piece runs in the calling thread.
    """
    if len(pieces) == 1:
        return [work(*pieces[0])]
    n = num_threads()
    if n == 1:
        return [work(*p) for p in pieces]
    futures = [_pool(n).submit(work, *p) for p in pieces]
    return [f.result() for f in futures]


def _reference():
    """``(JitterLog class, JITTER_LADDER)`` of the NumPy path, read at call time."""
    try:
        from . import linalg as ref  # after the gp split (issue 14)
        log_cls = ref.JitterLog
    except (ImportError, AttributeError):
        from . import gp as ref
        log_cls = ref._JitterLog
    return log_cls, np.asarray(ref.JITTER_LADDER, dtype=np.float64).reshape(-1)


def _record(jitter_log, jitter: np.ndarray, failed: np.ndarray) -> None:
    """Add a launch's jitter outcome to ``jitter_log`` exactly as the NumPy ``cholesky`` does."""
    jitter_log.record_steps(jitter, failed)


def _contiguous(a, dtype=np.float64) -> np.ndarray:
    """C-contiguous and writeable (numba types read-only arrays apart: one signature)."""
    a = np.ascontiguousarray(a, dtype=dtype)
    return a if a.flags.writeable else a.copy()


def _flatten(log_params, Y, batch):
    """Flat ``theta (B, P)``, ``Y (B_y, N, d_y)`` and ``y_index (B,)`` for a batch."""
    P = log_params.shape[-1]
    theta = _contiguous(np.broadcast_to(log_params, batch + (P,)).reshape(-1, P))
    y_flat, y_index = _flat_rows(Y, batch)
    return theta, y_flat, y_index


def _flat_rows(A, batch):
    """``A`` (..., n, d) as (B_a, n, d) and the row of every batch element, (B,) int64."""
    lead = A.shape[:-2]
    n_rows = int(np.prod(lead, dtype=np.int64))
    flat = _contiguous(A.reshape((n_rows,) + A.shape[-2:]))
    index = np.broadcast_to(np.arange(n_rows).reshape(lead), batch)
    return flat, _contiguous(index.reshape(-1), np.int64)


# ---------------------------------------------------------------------------------------
# Flat kernels


def _run(mode, theta, Y, y_index, X, z, Y_star, s_index, y_star_out, weight, X_star, cz,
         cd, ladder, stop=np.inf):
    """:func:`mdcore._compiled_kernels.pair_range` over all pairs, piece by piece.

    Returns ``[nlml, mean, var, noise_var, jitter, failed, dropped, acc]``; the mixture sums
    ``acc`` of the pieces are added in piece order.
    """
    k = _kernels()
    theta, Y, X, z, Y_star, y_star_out, weight, X_star, cz, cd, ladder = map(
        _contiguous, (theta, Y, X, z, Y_star, y_star_out, weight, X_star, cz, cd, ladder))
    y_index = _contiguous(y_index, np.int64)
    s_index = _contiguous(s_index, np.int64)
    B, N = theta.shape[0], X.shape[0]
    M = 0 if mode == k.NLML else X_star.shape[0]
    rows = B if mode == k.PREDICT else 0
    nlml, noise, jitter = np.empty(B), np.empty(B), np.empty(B)
    failed, dropped = np.empty(B, dtype=bool), np.empty(B, dtype=bool)
    mean, var = np.empty((rows, M)), np.empty((rows, M))

    def work(b0, b1):
        acc = np.zeros((4, M))
        k.pair_range(mode, b0, b1, theta, Y, y_index, X, z, Y_star, s_index, y_star_out,
                     weight, X_star, cz, cd, ladder, float(stop), nlml, mean, var, noise,
                     jitter, failed, dropped, acc)
        return acc

    accs = _in_pieces(work, _pieces(B, N, Y.shape[2] + X.shape[1], M))
    acc = np.zeros((4, M))
    for part in accs:                                 # fixed order: reproducible
        acc += part
    return [nlml, mean, var, noise, jitter, failed, dropped, acc]


def nlml_batch(theta, Y, y_index, X, z, ladder, stop=np.inf):
    """NLML (Eq. 9) of pairs ``(theta[b], Y[y_index[b]])``, flat and unchecked.

    Parameters
    ----------
    theta : ndarray of shape (B, P)
        Log hyperparameters, SPEC §2 layout.
    Y : ndarray of shape (B_y, N, d_y)
    y_index : int ndarray of shape (B,)
        Row of ``Y`` for every pair, in ``[0, B_y)``.
    X : ndarray of shape (N, d_x)
    z : ndarray of shape (N,)
    ladder : ndarray of shape (L,)
        Relative jitter steps (``JITTER_LADDER``).
    stop : float, default=inf
        Pairs whose NLML exceeds it get ``+inf``, jitter 0 and not ``failed``
        (:func:`mdcore.gp.neg_log_marginal_likelihood`).

    Returns
    -------
    nlml, jitter, failed : ndarray of shape (B,)
        ``jitter`` is the ladder step that worked (0 when none was needed); a failed pair
        has NLML ``+inf``.
    """
    Y, X = np.asarray(Y, dtype=np.float64), np.asarray(X, dtype=np.float64)
    none = np.zeros(0)                               # no test points
    out = _run(_kernels().NLML, theta, Y, y_index, X, z, np.zeros((1, 0, Y.shape[2])),
               y_index, np.zeros((1, 0)), np.zeros(len(y_index)), np.zeros((0, X.shape[1])),
               none, none, ladder, stop)
    return out[0], out[4], out[5]


def predict_batch(theta, Y, y_index, X, z, Y_star, s_index, X_star, ladder):
    """Predictive moments (Eq. 7) of pairs at ``(Y_star[s_index[b]], X_star)``, unchecked.

    Parameters as :func:`nlml_batch`, plus ``Y_star`` (B_s, M, d_y), ``s_index`` (B,) and
    ``X_star`` (M, d_x).

    Returns
    -------
    mean, var : ndarray of shape (B, M)
        Predictive mean and latent variance; NaN for a pair that could not be factorised.
    noise_var : ndarray of shape (B,)
    jitter, failed : ndarray of shape (B,)
    """
    Y_star = np.asarray(Y_star, dtype=np.float64)
    M = Y_star.shape[1]
    out = _run(_kernels().PREDICT, theta, Y, y_index, X, z, Y_star, s_index,
               np.zeros((Y_star.shape[0], M)), np.zeros(len(y_index)), X_star, np.zeros(M),
               np.zeros(M), ladder)
    return out[1], out[2], out[3], out[4], out[5]


# ---------------------------------------------------------------------------------------
# Batched functions with the broadcasting of mdcore.gp


def nlml(log_params, Y, X, z, *, jitter_log=None, stop=np.inf) -> np.ndarray:
    """Compiled :func:`mdcore.gp.neg_log_marginal_likelihood` on validated input.

    Parameters
    ----------
    log_params : ndarray of shape (..., P)
    Y : ndarray of shape (..., N, d_y)
        Leading dimensions broadcast with those of ``log_params``.
    X : ndarray of shape (N, d_x)
    z : ndarray of shape (N,)
    jitter_log : JitterLog, optional
        Receives the jitter counts (``record(jittered, failed, max_jitter)``); the caller
        then warns. Without it this function warns itself, with the NumPy path's text.
    stop : float, default=inf
        As in :func:`mdcore.gp.neg_log_marginal_likelihood`.

    Returns
    -------
    ndarray of shape (...)
        NLML of every broadcast batch element; ``+inf`` where the covariance stayed
        non-positive-definite after the jitter ladder, or the NLML exceeds ``stop``.
    """
    log_cls, ladder = _reference()
    own = jitter_log is None
    jitter_log = log_cls() if own else jitter_log
    log_params, Y = np.asarray(log_params, np.float64), np.asarray(Y, np.float64)
    batch = np.broadcast_shapes(log_params.shape[:-1], Y.shape[:-2])
    theta, y_flat, y_index = _flatten(log_params, Y, batch)
    out, jitter, failed = nlml_batch(theta, y_flat, y_index, X, z, ladder, stop)
    _record(jitter_log, jitter, failed)
    if own:
        jitter_log.warn("neg_log_marginal_likelihood")
    return out.reshape(batch)


def predict(log_params, Y, X, z, Y_star, X_star, *, jitter_log=None):
    """Compiled :func:`mdcore.gp.predict` on validated input.

    Parameters as :func:`mdcore.gp.predict`; ``Y_star`` (..., M, d_y) broadcasts with the
    batch of ``log_params`` and ``Y``. ``jitter_log`` as in :func:`nlml`.

    Returns
    -------
    mean, var : ndarray of shape (..., M)
        Predictive mean and latent variance (Eq. 7); NaN for a matrix that could not be
        factorised.
    noise_var : ndarray of shape (...)
    """
    log_cls, ladder = _reference()
    own = jitter_log is None
    jitter_log = log_cls() if own else jitter_log
    log_params, Y = np.asarray(log_params, np.float64), np.asarray(Y, np.float64)
    Y_star = np.asarray(Y_star, np.float64)
    batch = np.broadcast_shapes(log_params.shape[:-1], Y.shape[:-2], Y_star.shape[:-2])
    theta, y_flat, y_index = _flatten(log_params, Y, batch)
    M = Y_star.shape[-2]
    s_flat, s_index = _flat_rows(Y_star, batch)
    mean, var, noise, jitter, failed = predict_batch(
        theta, y_flat, y_index, X, z, s_flat, s_index, X_star, ladder)
    _record(jitter_log, jitter, failed)
    if own:
        jitter_log.warn("predict")
    return (mean.reshape(batch + (M,)), var.reshape(batch + (M,)), noise.reshape(batch))


class MixtureSums(NamedTuple):
    """Result of :func:`mixture_sums`.

    Attributes
    ----------
    acc : ndarray of shape (4, M)
        ``Σ w dz``, ``Σ w dd``, ``Σ w (v + σ_n² + dz²)``, ``Σ w (v + dd²)`` over the
        pairs that were kept.
    dropped : bool ndarray of shape (B,)
        Pairs left out: not factorisable, or with non-finite moments.
    """

    acc: np.ndarray
    dropped: np.ndarray


def mixture_sums(log_params, Y, y_index, X, z, Y_star, y_star_out, weight, X_star, cz, cd,
                 *, jitter_log=None) -> MixtureSums:
    """Fused predict-and-accumulate of scenarios 2–3 (Eq. 13/15), validated input.

    For pair b (``θ = log_params[b]`` on ``Y[y_index[b]]``, test outputs
    ``Y_star[y_index[b]]``, weight ``w = weight[b]``) with predictive mean ``μ`` and
    latent variance ``v`` at ``X_star`` (Eq. 7), noise ``σ_n²`` and
    ``y* = y_star_out[y_index[b]]``, and with ``dz = μ − cz``, ``dd = μ − y* − cd`` about
    a reference component's ``cz``, ``cd`` (M,)::

        acc = Σ_b w · [dz, dd, v + σ_n² + dz², v + dd²]

    Parameters
    ----------
    log_params : ndarray of shape (B, P)
    Y : ndarray of shape (S, N, d_y)
    y_index : int ndarray of shape (B,)
    X : ndarray of shape (N, d_x)
    z : ndarray of shape (N,)
    Y_star : ndarray of shape (S, M, d_y)
    y_star_out : ndarray of shape (S, M)
        The simulator output whose discrepancy is inferred, at ``X_star``.
    weight : ndarray of shape (B,)
    X_star : ndarray of shape (M, d_x)
    cz, cd : ndarray of shape (M,)
    jitter_log : JitterLog, optional
        As in :func:`nlml`; without it jitter is reported as a ``predict`` warning.

    Returns
    -------
    MixtureSums
    """
    log_cls, ladder = _reference()
    own = jitter_log is None
    jitter_log = log_cls() if own else jitter_log
    out = _run(_kernels().MIXTURE, log_params, Y, y_index, X, z, Y_star, y_index, y_star_out,
               weight, X_star, cz, cd, ladder)
    acc, jitter, failed, dropped = out[7], out[4], out[5], out[6]
    _record(jitter_log, jitter, failed)
    if own:
        jitter_log.warn("predict")
    return MixtureSums(acc, dropped)


def koh_log_likelihood(arrays, base, zT, jitter_log):
    """The Kennedy–O'Hagan likelihood at one θ as a compiled callable (SPEC §7).

    Parameters
    ----------
    arrays : mdcore.emulator.EmulatorArrays
        From :meth:`mdcore.emulator.EmulatorAt.arrays` at the observed inputs.
    base : ndarray of shape (n_out, N, N)
        The θ-independent covariance ``σ_f² m32(X, X) + K_δ + σ_n² I``.
    zT : ndarray of shape (n_out, N)
        Observations.
    jitter_log : JitterLog
        Receives every call's jitter counts; the caller warns.

    Returns
    -------
    callable
        ``f(theta)`` for θ of shape (p,): ``Σ_o log N(z_o | m_η, Σ_η + base_o)``, what
        :func:`mdcore.koh.gaussian_log_likelihood` gives on the emulator's moments, or
        ``-inf`` where a covariance fails the jitter ladder. Runs in the calling thread.
    """
    k = _koh_kernels()
    fixed = _koh_fixed(arrays, base, zT)
    lo, span = arrays.t_lo, arrays.t_span
    stats = np.zeros(3)

    def log_likelihood(theta) -> float:
        stats[:] = 0.0
        value = k.log_likelihood(_contiguous((theta - lo) / span), *fixed, stats)
        _record_stats(jitter_log, stats)
        return value

    return log_likelihood


def _koh_fixed(arrays, base, zT) -> tuple:
    _, ladder = _reference()
    return tuple(map(_contiguous, (arrays.T_train, arrays.inv_ell, arrays.Q_t, arrays.W,
                                   arrays.lin, arrays.beta_t, arrays.AK, arrays.V,
                                   arrays.sf4, base, zT, ladder)))


def _record_stats(jitter_log, stats) -> None:
    if stats[0] or stats[1]:
        jitter_log.record(int(stats[0]), int(stats[1]), float(stats[2]))


class KOHTarget:
    """The KOH log target of :func:`mdcore.koh.infer_koh` in standardised coordinates
    ``u = (θ − μ) / sd``, compiled, for :func:`mdcore.mcmc.adaptive_metropolis`.

    ``target(u)`` is ``log p(z | θ, φ̂) − ½ uᵀu`` (``-inf`` outside the box
    ``lo_u ≤ u ≤ hi_u``), as :func:`koh_log_likelihood` gives it; :meth:`advance` runs
    whole stretches of the adaptive-Metropolis loop in compiled code
    (:func:`mdcore._compiled_koh.chain_steps`): beam-1d's paper chain (150,000 steps)
    in 0.5 s, against 10 s for the Python loop around the same likelihood. The chain
    agrees with the Python loop's to the last bit or two: there NumPy's ``L @ s`` (BLAS
    may fuse multiply-adds) and, for d ≥ 3 parameters, LAPACK's factor of the proposal
    covariance round differently.

    Parameters
    ----------
    arrays, base, zT, jitter_log
        As :func:`koh_log_likelihood`.
    mu, sd : ndarray of shape (p,)
        The Gaussian prior of θ.
    lo_u, hi_u : ndarray of shape (p,)
        The box of θ in standardised coordinates.
    """

    def __init__(self, arrays, base, zT, jitter_log, mu, sd, lo_u, hi_u):
        self._k = _koh_kernels()
        self._fixed = _koh_fixed(arrays, base, zT)
        self._box = tuple(map(_contiguous, (mu, sd, lo_u, hi_u, arrays.t_lo, arrays.t_span)))
        self._log = jitter_log

    def __call__(self, u) -> float:
        u = _contiguous(u)
        stats = np.zeros(3)
        value = self._k.target(u, *self._box, np.empty(u.size), *self._fixed, stats)
        _record_stats(self._log, stats)
        return value

    def advance(self, t, stop, x, lp, mean, m2, L, burn_in, t0, s_d, reg, steps, log_u,
                samples, log_p, accepted) -> float:
        """Steps ``t ≤ s < stop`` of :func:`mdcore.mcmc.adaptive_metropolis`, in place."""
        stats = np.zeros(3)
        lp = self._k.chain_steps(int(t), int(stop), x, float(lp), mean, m2, L, int(burn_in),
                                 int(t0), float(s_d), reg, steps, log_u, samples, log_p,
                                 accepted, *self._box, *self._fixed, stats)
        _record_stats(self._log, stats)
        return lp


# ---------------------------------------------------------------------------------------
# The history-matching emulator at many candidates


def _candidates(mode, arrays, theta, z, vt, rank):
    """:func:`mdcore._compiled_emulator.candidate_range` over all candidates, by pieces.

    Candidates are independent, so the numbers do not depend on the pieces or threads.
    Returns ``(mean, var, imp, n_bad)``.
    """
    k = _emulator_kernels()
    theta = _contiguous(theta)
    M = theta.shape[0]
    n_out, R, N = arrays.AK.shape
    p = arrays.T_train.shape[1]
    fixed = tuple(map(_contiguous, (arrays.t_lo, arrays.t_span, arrays.T_train, arrays.inv_ell,
                                    arrays.Q_t, arrays.beta_t, arrays.lin, arrays.AK, arrays.G,
                                    arrays.sf2, z, vt)))
    mean = np.empty((M if mode == k.MOMENTS else 0, N, n_out))
    var = np.empty((M, N, n_out))
    imp = np.empty(M if mode == k.SCORES else 0)
    per = n_out * (R * (3.0 * p + 12.0) + 2.0 * R * R + 4.0 * R * N + 8.0 * N)
    size = max(MIN_PIECE, min(-(-M // PIECES), int(LAUNCH_FLOPS / per)))

    def work(m0, m1):
        return k.candidate_range(mode, m0, m1, theta, *fixed, rank, mean, var, imp)

    n_bad = sum(_in_pieces(work, [(m0, min(M, m0 + size)) for m0 in range(0, M, size)])
                ) if M else 0
    return mean, var, imp, int(n_bad)


def emulator_moments(arrays, theta):
    """Compiled :meth:`mdcore.emulator.Emulator.predict` on validated input.

    Parameters
    ----------
    arrays : mdcore.emulator.EmulatorArrays
        From :meth:`mdcore.emulator.EmulatorAt.arrays` at the inputs X (N of them).
    theta : ndarray of shape (M, p)
        Candidates, in the case's units.

    Returns
    -------
    mean, var : ndarray of shape (M, N, n_out)
    """
    none = np.zeros((0, 0))
    mean, var, _, _ = _candidates(_emulator_kernels().MOMENTS, arrays, theta, none, none, 1)
    return mean, var


def emulator_scores(arrays, theta, z, vt, rank: int):
    """Combined implausibility (Eq. 16) fused with the emulator's moments, validated input.

    Parameters
    ----------
    arrays, theta
        As in :func:`emulator_moments`.
    z, vt : ndarray of shape (N, n_out)
        Observations and ``V_o + V_m``.
    rank : int
        1, 2 or 3: the combined implausibility is the rank-th largest over the targets.

    Returns
    -------
    imp : ndarray of shape (M,)
    var : ndarray of shape (M, N, n_out)
        The emulator variance at every target.
    n_bad : int
        Targets with ``V_o + V_m + var ≤ 0`` (the caller raises).
    """
    _, var, imp, n_bad = _candidates(_emulator_kernels().SCORES, arrays, theta, z, vt, rank)
    return imp, var, n_bad


def fit_kernels():
    """The compiled pieces of the emulator fit's likelihood (``fit_*`` of
    :mod:`mdcore._compiled_emulator`), for :func:`mdcore.emulator.fit_emulator`.

    They replay the NumPy evaluation's arithmetic and sums in the same order, so the fit,
    and every history match, is identical on both backends; they run in the calling
    thread and call no BLAS.
    """
    return _emulator_kernels()


# ---------------------------------------------------------------------------------------
# Warm-up


def warm_up() -> float:
    """Load (or, the first time on a machine, compile) every kernel; returns seconds.

    Runs the kernel once on a tiny problem, so that later calls start at full speed.
    Safe to call from several threads; numba compiles the kernel once. The history-matching
    kernels come first: a history match is the first thing the app and the CLI run.
    """
    start = time.perf_counter()
    # The history-matching emulator at candidates, both modes (one signature).
    e = _emulator_kernels()
    eye = np.eye(2).reshape(1, 2, 2)
    one, two = np.ones(1), np.ones((1, 1))
    fixed = (np.zeros(1), one, np.zeros((2, 1)), two, eye.copy(), two, np.zeros((1, 2)),
             eye.copy(), eye.copy(), one, np.zeros((2, 1)), np.ones((2, 1)), 1)
    for mode in (e.MOMENTS, e.SCORES):
        e.candidate_range(mode, 0, 3, np.full((3, 1), 0.5), *fixed, np.empty((3, 2, 1)),
                          np.empty((3, 2, 1)), np.empty(3))
    # The emulator fit's pieces, on the layouts the fit passes (rows of stacks included).
    from .emulator import _kron_nlml_compiled, _sq_diffs
    T, res = np.array([[0.1, 0.2], [0.7, 0.4], [0.3, 0.9]]), np.array([[0.1], [-0.2], [0.3]])
    Xu = np.array([[0.5]])
    _kron_nlml_compiled(np.array([0.0, -0.5, -0.5, 0.0, -3.0]), T, Xu, res,
                        (_sq_diffs(T), _sq_diffs(Xu)), e)
    k = _kernels()
    X = np.linspace(0.0, 1.0, 3)[:, None]
    Y = np.stack([np.sin(3.0 * X), np.cos(2.0 * X)])           # (2, 3, 1)
    z = np.array([0.1, -0.2, 0.3])
    theta = np.array([[0.0, 0.0, -1.0, -2.0], [0.1, 0.2, -0.5, -3.0]])
    index = np.array([0, 1], dtype=np.int64)
    ladder = np.array([1e-10])
    Xs = np.array([[0.25], [0.75]])
    Ys = np.ascontiguousarray(Y[:, :2])
    acc = np.zeros((4, 2))
    out = [np.empty(2), np.empty((0, 2)), np.empty((0, 2)), np.empty(2), np.empty(2),
           np.empty(2, dtype=bool), np.empty(2, dtype=bool)]
    k.pair_range(k.MIXTURE, 0, 2, theta, Y, index, X, z, Ys, index,
                 np.ascontiguousarray(Ys[..., 0]), np.array([0.5, 0.5]), Xs, np.zeros(2),
                 np.zeros(2), ladder, np.inf, *out, acc)
    # The KOH step: p = 1, R = 2 training θ, N = N_t = 2 inputs, one output.
    eye = np.eye(2).reshape(1, 2, 2)
    kf = (np.zeros((2, 1)), np.ones((1, 1)), eye.copy(), eye.copy(), np.zeros((1, 2)),
          np.zeros((1, 1)), eye.copy(), eye.copy(), np.ones(1), 2.0 * eye, np.zeros((1, 2)),
          ladder)
    kk = _koh_kernels()
    kk.log_likelihood(np.zeros(1), *kf, np.zeros(3))
    # ... the target at one state (KOHTarget's call) and a KOH chain's steps (d = 1, two
    # steps after one of burn-in)
    box = (np.zeros(1), np.ones(1), -np.ones(1), np.ones(1), -np.ones(1), 2.0 * np.ones(1))
    kk.target(np.zeros(1), *box, np.empty(1), *kf, np.zeros(3))
    kk.chain_steps(1, 4, np.zeros(1), 0.0, np.zeros(1), np.zeros((1, 1)), np.eye(1), 1, 2,
                   5.76, 1e-8 * np.eye(1), np.zeros((3, 1)), np.full(3, -1.0),
                   np.empty((2, 1)), np.empty(2), np.zeros(2, dtype=np.int64), *box, *kf,
                   np.zeros(3))
    return time.perf_counter() - start


def warm_up_in_background() -> threading.Thread | None:
    """Start :func:`warm_up` in a daemon thread, once per process; ``None`` without numba.

    Later calls return the same thread. A compiled call made meanwhile waits for the
    compilation instead of repeating it.
    """
    global _warm_thread
    if not available():
        return None
    with _POOL_LOCK:
        if _warm_thread is None:
            _warm_thread = threading.Thread(target=_quiet_warm_up, name="mdcore-warm-up",
                                            daemon=True)
            _warm_thread.start()
        return _warm_thread


def _quiet_warm_up() -> None:
    try:
        warm_up()
    except Exception as exc:  # noqa: BLE001 - reported, and the first real call retries
        warnings.warn(f"the compiled GP kernels could not be prepared in the background "
                      f"({type(exc).__name__}: {exc}); the first compiled call will try "
                      "again and raise if it fails.", RuntimeWarning, stacklevel=1)
