"""Compiled (numba) kernels for the two loops where NumPy cannot reach a user's target.

The NumPy code is the implementation of record; these compute the same numbers to rounding:

- scenario 3's (φ, y) pairs: the NLML of every pair (Eq. 9, :func:`nlml`) and the mixture
  prediction (Eq. 15, :func:`mixture_sums`), fused per pair in small buffers;
- the Kennedy–O'Hagan chain (:func:`koh_chain`).

numba is optional and imported on first use; kernels are cached on disk, and
:func:`warm_up_in_background` prepares them while the app starts. Callers validate inputs.
Large calls run as pieces on the compute threads; the pieces depend on the problem size
only, so sums over them are reproducible.
"""

from __future__ import annotations

import importlib.util
import os
import threading
import time
import warnings
from typing import NamedTuple

import numpy as np

from . import _mcmc as mcmc
from ._emulator import EmulatorArrays
from ._linalg import JITTER_LADDER, JitterLog
from ._threads import run_pieces

__all__ = ["BACKENDS", "BACKEND_ENV", "ChainState", "KOHData", "Pairs", "Test", "available",
           "koh_chain", "mixture_sums", "nlml", "resolve_backend",
           "warm_up", "warm_up_in_background"]

#: Values of the ``backend=`` argument of the numerical entry points.
BACKENDS = ("auto", "numpy", "numba")
#: Environment variable giving the default backend (one of :data:`BACKENDS`).
BACKEND_ENV = "MDCORE_BACKEND"
#: A large call is split into about this many pieces, for load balance over the threads.
PIECES = 32
#: Fewest pairs (or candidates) in a piece.
MIN_PIECE = 64

_module = None
_warm_thread: threading.Thread | None = None
_warm_lock = threading.Lock()


class Pairs(NamedTuple):
    """(φ, y) pairs of scenario 3: pair b is ``(theta[b], Y[row[b]])``."""

    theta: np.ndarray   # (B, P) log hyperparameters [log σ_f, log ℓ_y…, log ℓ_x…, log σ_n]
    row: np.ndarray     # (B,) int64, the row of Y (and of the Test arrays)
    Y: np.ndarray       # (S, N, d_y) simulator outputs at the training inputs
    X: np.ndarray       # (N, d_x) training inputs
    z: np.ndarray       # (N, n_z) observations: one or more outputs sharing the pairs


class Test(NamedTuple):
    """The mixture of Eq. 15 at the test inputs, for :func:`mixture_sums`."""

    Y_star: np.ndarray  # (S, M, d_y) simulator outputs at X_star, rows as Pairs.Y
    y_out: np.ndarray   # (S, M) the output whose discrepancy is inferred
    X_star: np.ndarray  # (M, d_x)
    weight: np.ndarray  # (B,) normalised weight of each pair (multiplicity / n allowed)
    centre: np.ndarray  # (2, M) a reference component's E[z*] and E[z*] − y*


class PairOut(NamedTuple):
    nlml: np.ndarray      # (B, n_z)
    step: np.ndarray      # (B,) the jitter step that worked (0: none needed)
    failed: np.ndarray    # (B,) bool: no step worked
    dropped: np.ndarray   # (B,) bool: left out of the mixture sums


class KOHData(NamedTuple):
    """The Kennedy–O'Hagan target besides the emulator, for :func:`koh_chain`."""

    base: np.ndarray    # (n_out, N, N) σ_f² m32(X, X) + K_δ + σ_n² I
    zT: np.ndarray      # (n_out, N) observations
    mu: np.ndarray      # (p,) prior mean of θ; θ = μ + sd u
    sd: np.ndarray      # (p,)
    lo_u: np.ndarray    # (p,) the box of θ, standardised
    hi_u: np.ndarray    # (p,)
    ladder: np.ndarray  # (L,) relative jitter steps


class ChainState(NamedTuple):
    """The state of an adaptive-Metropolis run, updated in place by the kernel."""

    x: np.ndarray         # (d,)
    mean: np.ndarray      # (d,) Welford mean of the states so far
    m2: np.ndarray        # (d, d) Welford sums
    L: np.ndarray         # (d, d) lower factor of the proposal covariance
    samples: np.ndarray   # (n_kept, d) output
    log_p: np.ndarray     # (n_kept,) output
    accepted: np.ndarray  # (2,) int64 [burn-in, kept]
    reg: np.ndarray       # (d, d) s_d ε I
    burn_in: int
    t0: int
    s_d: float


def available() -> bool:
    """Whether numba can be imported (the compiled path can run)."""
    if _module is not None:
        return True
    try:
        return importlib.util.find_spec("numba") is not None
    except (ImportError, ValueError):        # e.g. sys.modules["numba"] = None
        return False


def resolve_backend(backend: str | None = None) -> str:
    """``"numpy"`` or ``"numba"`` for ``backend`` (None reads ``MDCORE_BACKEND``; ``"auto"``
    is numba when installed); a ValueError for an unknown name or a missing numba."""
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
    """The kernel module, imported on first use."""
    global _module
    if _module is None:
        try:
            from . import _compiled_kernels
        except ImportError as exc:
            raise ImportError(
                "the compiled path needs numba (pip install 'numba>=0.60'); importing it "
                f"failed ({exc}). Use backend='numpy' instead.") from exc
        _module = _compiled_kernels
    return _module


def _contiguous(a, dtype=np.float64) -> np.ndarray:
    """C-contiguous and writeable (numba types read-only arrays apart: one signature)."""
    a = np.ascontiguousarray(a, dtype=dtype)
    return a if a.flags.writeable else a.copy()


def _pieces(n: int) -> list[tuple[int, int]]:
    size = max(MIN_PIECE, -(-n // PIECES))
    return [(a, min(n, a + size)) for a in range(0, n, size)]


def _run_pairs(mode: int, pairs: Pairs, test: Test, jitter_log: JitterLog | None):
    k = _kernels()
    theta, row, Y, X, z = pairs
    z = np.asarray(z, dtype=np.float64)
    z = z.reshape(z.shape[0], -1)
    pairs = Pairs(_contiguous(theta), _contiguous(row, np.int64), _contiguous(Y),
                  _contiguous(X), _contiguous(z))
    test = Test(*map(_contiguous, test))
    B, M = pairs.theta.shape[0], test.X_star.shape[0]
    out = PairOut(np.empty((B, z.shape[1])), np.empty(B), np.empty(B, bool),
                  np.empty(B, bool))
    ladder = np.asarray(JITTER_LADDER, dtype=np.float64)

    def work(b0, b1):
        acc = np.zeros((4, M))
        k.pair_range(mode, b0, b1, pairs, test, ladder, out, acc)
        return acc

    acc = np.zeros((4, M))
    for part in run_pieces(work, _pieces(B)):        # piece order: reproducible
        acc += part
    log = JitterLog() if jitter_log is None else jitter_log
    log.record_steps(out.step, out.failed)
    if jitter_log is None:
        log.warn("predict" if mode else "neg_log_marginal_likelihood")
    return out, acc


def nlml(pairs: Pairs, jitter_log: JitterLog | None = None) -> np.ndarray:
    """NLML (Eq. 9) of every pair ``(pairs.theta[b], pairs.Y[pairs.row[b]])``, as
    :func:`mdcore._gp.neg_log_marginal_likelihood`: (B,) or (B, n_z) as ``pairs.z`` (outputs
    share each pair's factor); ``jitter_log`` receives the jitter counts, else a warning."""
    d_y, d_x = pairs.Y.shape[2], pairs.X.shape[1]
    empty = Test(np.zeros((1, 0, d_y)), np.zeros((1, 0)), np.zeros((0, d_x)),
                 np.zeros(1), np.zeros((2, 0)))
    out = _run_pairs(_kernels().NLML, pairs, empty, jitter_log)[0].nlml
    return out[:, 0] if np.ndim(pairs.z) == 1 else out


def mixture_sums(pairs: Pairs, test: Test, jitter_log: JitterLog | None = None
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Weighted mixture sums of Eq. 15 over the pairs of one output (``pairs.z`` (N,)).

    For pair b with predictive mean ``μ`` and latent variance ``v`` (Eq. 7), noise ``σ_n²``,
    ``dz = μ − test.centre[0]`` and ``dd = μ − test.y_out[row[b]] − test.centre[1]``::

        acc = Σ_b weight[b] · [dz, dd, v + σ_n² + dz², v + dd²]

    Returns ``acc`` (4, M) and ``dropped`` (B,) bool (not factorisable, or non-finite).
    """
    out, acc = _run_pairs(_kernels().MIXTURE, pairs, test, jitter_log)
    return acc, out.dropped


def koh_chain(arrays: EmulatorArrays, koh: KOHData, setup: mcmc.ChainSetup, seed,
              progress=None, jitter_log: JitterLog | None = None) -> mcmc.Chain:
    """:func:`mdcore._mcmc.adaptive_metropolis` on the KOH target ``log p(z | θ, φ̂) −
    ½ uᵀu`` in ``u = (θ − μ) / sd`` (``-inf`` outside the box), compiled.

    ``arrays`` is the emulator at the observed inputs; ``setup`` comes from
    :func:`mdcore._mcmc.chain_setup` on the NumPy target. The random numbers are
    :func:`mdcore._mcmc.draw_blocks`'s, as the Python loop's; each block is one kernel call,
    and ``progress`` (which may raise to cancel) runs between blocks.
    """
    k = _kernels()
    em = type(arrays)(*map(_contiguous, arrays))
    koh = KOHData(*map(_contiguous, koh))
    d, kept = setup.x0.size, setup.n_iter - setup.burn_in
    state = ChainState(x=setup.x0.copy(), mean=setup.x0.copy(), m2=np.zeros((d, d)),
                       L=_contiguous(setup.L0), samples=np.empty((kept, d)),
                       log_p=np.empty(kept), accepted=np.zeros(2, np.int64),
                       reg=_contiguous(setup.reg), burn_in=setup.burn_in, t0=setup.t0,
                       s_d=setup.s_d)
    stats = np.zeros(3)
    lp = setup.lp0
    start = time.perf_counter()
    for t, steps, log_u in mcmc.draw_blocks(setup, seed, progress):
        lp = k.koh_steps(t, lp, _contiguous(steps), _contiguous(log_u), state, em, koh,
                         stats)
    if jitter_log is not None and (stats[0] or stats[1]):
        jitter_log.record(int(stats[0]), int(stats[1]), float(stats[2]))
    return mcmc.finish_chain(setup, state.samples, state.log_p, state.accepted, state.L,
                             time.perf_counter() - start)


def warm_up() -> float:
    """Load (the first time on a machine: compile) every kernel; returns seconds."""
    start = time.perf_counter()
    k = _kernels()
    one, eye = np.ones(1), np.eye(2)
    em = EmulatorArrays(t_lo=np.zeros(1), t_span=one, T_train=np.zeros((2, 1)),
                        inv_ell=np.ones((1, 1)), Q_t=eye[None].copy(), W=eye[None].copy(),
                        lin=np.zeros((1, 2)), beta_t=np.zeros((1, 1)), AK=eye[None].copy(),
                        V=eye[None].copy(), sf4=one, prior=eye[None].copy(), sf2=one,
                        G=eye[None].copy())
    X = np.linspace(0.0, 1.0, 3)[:, None]
    pairs = Pairs(np.array([[0.0, 0.0, -1.0, -2.0], [0.1, 0.2, -0.5, -3.0]]),
                  np.array([0, 1]), np.stack([np.sin(3.0 * X), np.cos(2.0 * X)]), X,
                  np.array([0.1, -0.2, 0.3]))
    test = Test(pairs.Y[:, :2].copy(), pairs.Y[:, :2, 0].copy(), X[:2].copy(),
                np.array([0.5, 0.5]), np.zeros((2, 2)))
    _run_pairs(k.MIXTURE, pairs, test, JitterLog())
    koh = KOHData(2.0 * eye[None], np.zeros((1, 2)), np.zeros(1), one, -one, one,
                  np.asarray(JITTER_LADDER, dtype=np.float64))
    setup = mcmc.ChainSetup(np.zeros(1), 0.0, np.eye(1), 4, 1, 2, 5.76, 1e-8 * np.eye(1))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        koh_chain(em, koh, setup, 0)
    return time.perf_counter() - start


def warm_up_in_background() -> threading.Thread | None:
    """Start :func:`warm_up` in a daemon thread, once per process (later calls return the
    same thread); ``None`` without numba."""
    global _warm_thread
    if not available():
        return None
    with _warm_lock:
        if _warm_thread is None:
            _warm_thread = threading.Thread(target=_quiet_warm_up, name="mdcore-warm-up",
                                            daemon=True)
            _warm_thread.start()
        return _warm_thread


def _quiet_warm_up() -> None:
    try:
        warm_up()
    except Exception as exc:  # noqa: BLE001 - reported, and the first real call retries
        warnings.warn(f"the compiled kernels could not be prepared in the background "
                      f"({type(exc).__name__}: {exc}); the first compiled call will try "
                      "again and raise if it fails.", RuntimeWarning, stacklevel=1)
