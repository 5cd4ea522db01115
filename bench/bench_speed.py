"""Issue 15's speed table, for the rows the compiled GP kernels cover, in one run.

Usage: python bench/bench_speed.py [--quick] [--rows beam-1d beam-2d shear-5 app koh hm-wave]
                                   [--sklearn-pairs 300] [--no-jit] [--repeat 5]

Rows: scenario 3 at the paper's sizes (beam-1d 1000 × 500, beam-2d 1000 × 1000, shear-5
1000 × 500 on all 5 outputs), weights of every pair plus the mixture prediction at the
case's test inputs; and scenario 3 at the app's default sizes (100 × 50) on every case.
For each row:

- ``numpy``: the library path (``infer_discrepancy`` + ``DiscrepancyModel.predict``) with
  ``backend="numpy"``, the reference kernels of :mod:`mdcore.gp`;
- ``numba``: the same calls with ``backend="numba"``: compiled weights, and the prediction
  fused with the mixture sums (:func:`mdcore.compiled.mixture_sums`: no per-pair moments
  are stored);
- ``sklearn``: one ``GaussianProcessRegressor`` per pair (fixed hyperparameters,
  ``optimizer=None``): ``fit`` (which computes the log marginal likelihood) for every pair
  and ``predict(return_std=True)`` for the pairs the prediction keeps, timed on
  ``--sklearn-pairs`` random pairs of each kind and extrapolated. scikit-learn has no
  per-dimension kernels, so it uses an ARD Matérn 3/2 over [y, x]: the same cost, not
  the same kernel;
- ``bound``: the arithmetic of the row, exponentials at the machine's measured exp rate and
  flops at its measured dgemm rate, spread over all cores (formula in :func:`work`). It
  counts every pair's full factorisation: the compiled path stops early for the pairs
  it leaves out as negligible (the share is on the row's second line), so it can beat it;
- ``cpu/cor``: the compiled run's process CPU time over the cores, what it would take on
  idle cores (on a shared machine the wall clock also counts others' turns);
- agreement: the largest difference of the compiled predictions from the NumPy ones,
  relative to each field's largest magnitude, and the largest |Δ log w| over the pairs
  the prediction keeps.

``--quick`` runs the NumPy path and the agreement check on a tenth of the θ samples and
extrapolates its time by pair counts. ``koh``: the KOH chain (150,000 steps, beam-1d) on
both backends. ``hm-wave``: one history-matching wave of 10⁵ candidates on every case
(:func:`mdcore.history_matching.next_wave`: simulator runs, emulator fit, candidates,
scoring), shortest of ``--repeat`` runs per backend; its second line splits it into the
emulator fit (bit-identical on both backends: see :func:`hm_wave_rows`) and the scoring
of the candidates, with the scoring's bound (its exps and flops); ``sklearn`` is
``GaussianProcessRegressor.predict(return_std=True)`` of the equivalent dense GP over
(x, θ) at the candidates, timed on 500 of them and extrapolated; ``Δ pred`` is the
largest |ΔI| relative to I, and the NROY sets are compared. ``koh-wave`` runs both.
The JIT section times ``warm_up()`` (every kernel) and the emulator kernel alone in fresh
processes with an empty and then a filled numba cache. Peak memory is the process's peak
resident set size so far (``ru_maxrss``), so it only grows down the table. Figures only:
the machine may be shared, so the load average is printed; nothing is asserted.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import os
import resource
import subprocess
import sys
import tempfile
import time
import warnings
from functools import partial

import numpy as np

from mdcore import cases, compiled
from mdcore.discrepancy import infer_discrepancy
from mdcore.emulator import fit_emulator
from mdcore.history_matching import case_problem, history_match_case, next_wave
from mdcore.pipeline import Method, Settings, run_method

PAPER = {"beam-1d": (1000, 500), "beam-2d": (1000, 1000), "shear-5": (1000, 500)}
APP = (100, 50)


# ---------------------------------------------------------------------------------------
# The machine


def cores() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()


def best_of(fn, repeat=5) -> float:
    """Shortest of ``repeat`` wall-clock timings (the least disturbed by other load)."""
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return min(times)


def machine_rates():
    """Single-core exp rate (NumPy's and the compiled kernels') and dgemm flop rate."""
    from threadpoolctl import threadpool_limits

    x = -np.random.default_rng(0).uniform(0.0, 20.0, 2**20)
    out = np.empty_like(x)
    np_exp = best_of(lambda: np.exp(x, out=out)) / x.size
    from mdcore import _compiled_kernels as k

    n = 4096
    q, e = np.ones(n), x[:n].copy()
    tb, ib = np.empty(n), np.empty(n, dtype=np.int64)
    k._qexp(q, e, out[:n], tb, ib)

    def many():
        for _ in range(256):
            k._qexp(q, e, out[:n], tb, ib)

    q_exp = best_of(many) / (256 * n)
    a, b = np.random.rand(128, 128), np.random.rand(128, 400)
    c = np.empty((128, 400))
    with threadpool_limits(1, user_api="blas"):
        np.dot(a, b, out=c)
        t = best_of(lambda: [np.dot(a, b, out=c) for _ in range(20)])
    flops = 20 * 2 * 128 * 128 * 400 / t
    return {"numpy_exp_s": np_exp, "compiled_exp_s": q_exp, "exp_s": min(np_exp, q_exp),
            "flop_s": 1.0 / flops, "cores": cores()}


def work(N, d_y, d_x, M, pairs, kept, U=None, Ux=0, M_u=None):
    """Exponentials and flops of scenario 3: NLML on ``pairs`` pairs, prediction on
    ``kept`` pairs (each also refactorises), at M test points.

    Per pair, NLML: one exponential per distinct kernel entry (N(N+1)/2; U(U+1)/2 with U
    distinct training inputs, as shear-5's replicates; ``Ux + N`` on a grid, ``Ux``
    distinct x differences with one-dimensional y, as the compiled kernels build them)
    and N logs; flops: the kernel entries, N(N−1)/2 × (3(d_y + d_x) + 6), and the
    bordered Cholesky, (N+1)³/3. Prediction, at the ``M_u`` distinct test inputs, adds
    N·M_u exps and N·M_u × (3(d_y + d_x) + 6) flops for K_f*, N²·M_u for the triangular
    solve (N²M_u/2 multiply-adds) and 4·N·M_u + 8·M for the moments and sums.
    """
    d = d_y + d_x
    U = N if U is None else U
    M_u = M if M_u is None else M_u
    ex_n = U * (U + 1) / 2 if U < N else (Ux + N if Ux else N * (N + 1) / 2)
    fl_n = N * (N - 1) / 2 * (3 * d + 6) + (N + 1) ** 3 / 3 + 3 * N
    ex_p = N * M_u
    fl_p = N * M_u * (3 * d + 6) + N * N * M_u + 4 * N * M_u + 8 * M
    return (pairs + kept) * ex_n + kept * ex_p, (pairs + kept) * fl_n + kept * fl_p


def distinct_work(case, theta):
    """``(U, Ux, M_u)`` of :func:`work` for a case: distinct training inputs (of the joint
    [y, x] at one θ), distinct x differences when y is one-dimensional (else 0), and
    distinct test inputs."""
    from mdcore import _compiled_kernels as k

    X = np.ascontiguousarray(case.X_train, dtype=np.float64)
    Y = case.simulate(X, theta[:1])[0]
    N = X.shape[0]
    U = np.unique(np.hstack([Y, X]), axis=0).shape[0]
    Ux = 0
    if Y.shape[1] == 1 and U == N:
        n = N + 1
        D = np.empty((X.shape[1], n * (n + 1) // 2))
        k._packed_diffs(X, n, D)
        Ux = k._grid_space(D, N, True)[0]
    return U, Ux, np.unique(case.X_test, axis=0).shape[0]


# ---------------------------------------------------------------------------------------
# The paths


def library(case, theta, n_phi, backend):
    """(model, prediction, infer seconds, predict seconds, CPU seconds) of the library path.

    CPU seconds (all threads of the process) say what the run would take on idle cores:
    on a shared machine the wall clock also counts the time other processes held them.
    """
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        c0, t0 = time.process_time(), time.perf_counter()
        model = infer_discrepancy(case.simulate, theta, case.X_train, case.z_train,
                                  scenario=3, n_phi=n_phi, phi_prior=case.phi_prior, seed=0,
                                  backend=backend)
        t1 = time.perf_counter()
        pred = model.predict(case.X_test)
        t2, c2 = time.perf_counter(), time.process_time()
    return model, pred, t1 - t0, t2 - t1, c2 - c0


def kept_log_weight_gap(model, ref) -> float:
    """Largest |Δ log w| over the pairs the prediction keeps (the reference's pruning).

    Below the pruning level some covariances are singular to working precision (σ_f ≫
    σ_n); their NLML is rounding noise in either path and carries no weight.
    """
    gap = 0.0
    for o in range(ref.n_out):
        lw, lc = ref.log_weights[o].ravel(), model.log_weights[o].ravel()
        keep = lw >= lw.max() + np.log(ref.prune)
        gap = max(gap, float(np.max(np.abs(lw[keep] - lc[keep]))))
    return gap


def agreement(pred, ref) -> float:
    """Largest difference over the four fields, relative to each field's largest value."""
    worst = 0.0
    for a, b in zip(pred, ref):
        scale = np.max(np.abs(b), axis=0)
        worst = max(worst, float(np.max(np.abs(a - b) / np.where(scale > 0, scale, 1.0))))
    return worst


def sklearn_seconds(case, theta, model, n_sample, rng):
    """Extrapolated seconds of a scikit-learn per-pair loop doing the same work."""
    from sklearn.gaussian_process import GaussianProcessRegressor
    from sklearn.gaussian_process.kernels import ConstantKernel, Matern, WhiteKernel

    y_train = model.Y
    y_test = case.simulate(case.X_test, theta)
    K = model.log_params.shape[2]

    def regressor(o, flat):
        j, k = divmod(int(flat), K)
        p = np.exp(model.log_params[o][j, k])
        kern = (ConstantKernel(p[0] ** 2) * Matern(length_scale=p[1:-1], nu=1.5)
                + WhiteKernel(p[-1] ** 2))
        reg = GaussianProcessRegressor(kern, optimizer=None, alpha=0.0)
        return reg, j

    pairs = model.log_weights[0].size
    total = 0.0
    for o in range(model.n_out):
        fit_idx = rng.choice(pairs, size=min(n_sample, pairs), replace=False)
        t = time.perf_counter()
        for flat in fit_idx:
            reg, j = regressor(o, flat)
            with contextlib.suppress(np.linalg.LinAlgError):    # not PD: sklearn gives up
                reg.fit(np.column_stack([y_train[j], case.X_train]), case.z_train[:, o])
        total += (time.perf_counter() - t) / fit_idx.size * pairs
        lw = model.log_weights[o].ravel()
        kept = np.flatnonzero(lw >= lw.max() + np.log(model.prune))
        pred_idx = rng.choice(kept, size=min(n_sample, kept.size), replace=False)
        fitted = []
        for flat in pred_idx:
            reg, j = regressor(o, flat)
            with contextlib.suppress(np.linalg.LinAlgError):
                fitted.append((reg.fit(np.column_stack([y_train[j], case.X_train]),
                                       case.z_train[:, o]), j))
        t = time.perf_counter()
        for reg, j in fitted:
            reg.predict(np.column_stack([y_test[j], case.X_test]), return_std=True)
        total += (time.perf_counter() - t) / max(1, len(fitted)) * kept.size
    return total


# ---------------------------------------------------------------------------------------
# Rows


def row(name, sizes, rates, args, rng):
    case = cases.load(name)
    n_s, n_phi = sizes
    hm = history_match_case(case, seed=0)
    theta = hm.posterior_samples(n_s, seed=0)
    N, d_x = case.X_train.shape
    n_out = case.z_train.shape[1]
    M = case.X_test.shape[0]

    compiled.warm_up()
    library(case, theta[:2], 2, "numpy")                # first-call costs out of the way
    library(case, theta[:2], 2, "numba")
    model_n, pred_n, inf_n, pre_n, cpu_n = library(case, theta, n_phi, "numba")
    kept = int(np.sum(model_n.n_components))
    pairs = n_out * n_s * n_phi

    sub = max(1, n_s // 10) if args.quick and n_s > 100 else n_s
    model_r, pred_r, inf_r, pre_r, _ = library(case, theta[:sub], n_phi, "numpy")
    scale_inf, scale_pre = n_s / sub, kept / max(1, int(np.sum(model_r.n_components)))
    numpy_s = inf_r * scale_inf + pre_r * scale_pre
    if sub == n_s:
        agree, agree_w = agreement(pred_n, pred_r), kept_log_weight_gap(model_n, model_r)
    else:                      # compare on the subset the NumPy path ran on
        model_c, pred_c, _, _, _ = library(case, theta[:sub], n_phi, "numba")
        agree, agree_w = agreement(pred_c, pred_r), kept_log_weight_gap(model_c, model_r)

    sk = (sklearn_seconds(case, theta, model_n, args.sklearn_pairs, rng)
          if args.sklearn_pairs else np.nan)
    exps, flops = work(N, n_out, d_x, M, pairs, kept, *distinct_work(case, theta))
    bound = (exps * rates["exp_s"] + flops * rates["flop_s"]) / rates["cores"]
    numba_s = inf_n + pre_n
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    label = f"S3 {name} {n_s}×{n_phi}" + (f" ×{n_out} outputs" if n_out > 1 else "")
    print(f"{label:<28} {pairs:>9,} {kept:>9,} {numpy_s:>8.2f}{'*' if sub < n_s else ' '}"
          f" {numba_s:>7.2f} {cpu_n / rates['cores']:>7.2f} {sk:>9.1f}"
          f" {numpy_s / numba_s:>6.1f}x {sk / numba_s:>7.0f}x {bound:>7.3f}"
          f" {numba_s / bound:>6.1f}x {agree:>8.1e} {agree_w:>8.1e} {peak:>6.0f}", flush=True)
    print(f"{'':<28} {'':>9} {'':>9}   (numpy: weights {inf_r * scale_inf:.2f} + predict "
          f"{pre_r * scale_pre:.2f}; numba: {inf_n:.2f} + {pre_n:.2f}; "
          f"{exps / 1e9:.2f} G exps, {flops / 1e9:.1f} Gflop; left out as negligible: "
          f"{np.mean(model_n.log_weights == -np.inf):.1%} of the pairs, weight ≤ "
          f"{np.max(model_n.abandoned_mass):.1e})", flush=True)


def koh_row():
    """The KOH chain on both backends."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        case = cases.load("beam-1d")
        hm = history_match_case(case, seed=0)
        seconds, chains = {}, {}
        for backend in ("numpy", "numba"):
            settings = dataclasses.replace(Settings.paper("beam-1d"), backend=backend)
            t = time.perf_counter()
            res = run_method(case, hm, Method.KOH, settings, seed=0)
            seconds[backend] = time.perf_counter() - t
            chains[backend] = res.model.chain.samples
        gap = float(np.max(np.abs(chains["numba"] - chains["numpy"])))
        ratio = seconds["numpy"] / seconds["numba"]
        print(f"{'KOH beam-1d 150,000 steps':<28} {'':>9} {'':>9} {seconds['numpy']:>8.2f} "
              f" {seconds['numba']:>7.2f} {'':>7} {'':>9} {ratio:>6.1f}x"
              f"   (target ≤ 15 s; chains differ by at most {gap:.1e})", flush=True)


def sklearn_wave_seconds(problem, emulator, theta, n_sample=500):
    """``GaussianProcessRegressor.predict(return_std=True)`` of the dense GP over (x, θ)
    with the emulator's hyperparameters, per output, at ``n_sample`` candidates × the
    observed inputs, extrapolated to all of ``theta``. scikit-learn has no product of
    per-block kernels: an ARD Matérn 3/2 over [x, θ] (the same cost, not the same kernel)."""
    from sklearn.gaussian_process import GaussianProcessRegressor
    from sklearn.gaussian_process.kernels import ConstantKernel, Matern, WhiteKernel

    p, d_x = problem.p, problem.X.shape[1]
    lo, span = problem.bounds[:, 0], problem.bounds[:, 1] - problem.bounds[:, 0]
    Xu = emulator.unit_x(problem.X)
    Tu = (emulator.theta_train - lo) / span
    train = np.column_stack([np.tile(Xu, (len(Tu), 1)), np.repeat(Tu, len(Xu), axis=0)])
    sub = (theta[:n_sample] - lo) / span
    test = np.column_stack([np.tile(Xu, (len(sub), 1)), np.repeat(sub, len(Xu), axis=0)])
    total = 0.0
    for o, g in enumerate(emulator.gps):
        e = np.exp(g.log_params)
        ell = np.r_[e[1 + p:1 + p + d_x], e[1:1 + p]]
        kern = (ConstantKernel(e[0] ** 2) * Matern(length_scale=ell, nu=1.5)
                + WhiteKernel(e[-1] ** 2))
        reg = GaussianProcessRegressor(kern, optimizer=None, alpha=0.0)
        with contextlib.suppress(np.linalg.LinAlgError):
            reg.fit(train, emulator.y_train[..., o].ravel())
            t = time.perf_counter()
            reg.predict(test, return_std=True)
            total += time.perf_counter() - t
    return total * len(theta) / len(sub)


def hm_wave_rows(rates, repeat):
    """One history-matching wave of 10⁵ candidates per case, on both backends.

    The emulator fit gives the same bits on both backends, on purpose: its result must not
    move (L-BFGS-B turns a 1-ulp change of the NLML into ~1e-5 in the hyperparameters and
    ~1e-7 in θ_MAP), so the compiled fit replays NumPy's arithmetic and sums exactly
    (:func:`mdcore.emulator._kron_nlml_compiled`).
    """
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for name in ("beam-1d", "beam-2d", "shear-5"):
            hm_wave_row(cases.load(name), rates, repeat)


def hm_wave_row(case, rates, repeat):
    wave, wall, cpu, score = {}, {}, {}, {}
    for backend in ("numpy", "numba"):
        problem = case_problem(case, n_candidates=100_000, max_waves=1, backend=backend)
        next_wave(problem)                                      # first-call costs
        best = (np.inf, 0.0)
        for _ in range(repeat):
            c0, t0 = time.process_time(), time.perf_counter()
            w = next_wave(problem)
            best = min(best, (time.perf_counter() - t0, time.process_time() - c0))
        wave[backend], (wall[backend], cpu[backend]) = w, best
        score[backend] = best_of(partial(problem.score, w.candidates, w.emulator), repeat)
    ref, new = wave["numpy"], wave["numba"]
    problem, em, theta = new.problem, new.emulator, new.candidates
    fit = {b: best_of(partial(fit_emulator, problem.X, em.theta_train, em.y_train,
                              problem.bounds, seed=0, backend=b), repeat)
           for b in ("numpy", "numba")}
    same = np.array_equal(ref.nroy, new.nroy)
    dI = float(np.max(np.abs(new.candidate_implausibility - ref.candidate_implausibility)
                      / ref.candidate_implausibility))
    sk = sklearn_wave_seconds(problem, em, theta)
    M, (N, n_out), R, p = len(theta), problem.z.shape, len(em.theta_train), problem.p
    exps = M * n_out * R
    flops = M * n_out * (R * (3 * p + 4) + 2 * R * R + 4 * R * N + 8 * N)
    bound = (exps * rates["exp_s"] + flops * rates["flop_s"]) / rates["cores"]
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    label = f"HM wave {case.name} 10⁵ cand."
    print(f"{label:<28} {M:>9,} {len(new.nroy):>9,} {wall['numpy']:>8.3f} "
          f" {wall['numba']:>7.3f} {cpu['numba'] / rates['cores']:>7.3f} {sk:>9.2f}"
          f" {wall['numpy'] / wall['numba']:>6.1f}x {sk / wall['numba']:>7.0f}x"
          f" {bound:>7.3f} {score['numba'] / bound:>6.1f}x {dI:>8.1e} {'':>8}"
          f" {peak:>6.0f}", flush=True)
    print(f"{'':<28} {'':>9} {'':>9}   (target ≤ 0.2 s; emulator fit numpy {fit['numpy']:.3f} s,"
          f" numba {fit['numba']:.3f} s (bit-identical); scoring numpy {score['numpy']:.3f} s,"
          f" numba {score['numba']:.3f} s ({score['numpy'] / score['numba']:.1f}x; nb/bd is the"
          f" scoring's); NROY sets {'identical' if same else 'DIFFER'}; R = {R}, N = {N},"
          f" {n_out} output{'s' if n_out > 1 else ''}; shortest of {repeat})", flush=True)


#: The emulator kernel alone, both modes, on a tiny problem (p = 1, R = N = 2, one output).
EMULATOR_JIT = """
import time
import numpy as np
t = time.perf_counter()
from mdcore import _compiled_emulator as e
eye = np.eye(2).reshape(1, 2, 2)
fixed = (np.zeros(1), np.ones(1), np.zeros((2, 1)), np.ones((1, 1)), eye.copy(),
         np.ones((1, 1)), np.zeros((1, 2)), eye.copy(), eye.copy(), np.ones(1),
         np.zeros((2, 1)), np.ones((2, 1)), 1)
for mode in (e.MOMENTS, e.SCORES):
    e.candidate_range(mode, 0, 3, np.full((3, 1), 0.5), *fixed, np.empty((3, 2, 1)),
                      np.empty((3, 2, 1)), np.empty(3))
print(time.perf_counter() - t)
"""


def jit_times():
    """warm_up() (every kernel), and the emulator kernel alone, in fresh processes: empty
    numba cache (cold), then filled (warm)."""
    code = ("import time; t = time.perf_counter(); from mdcore import compiled; "
            "w = compiled.warm_up(); print(w, time.perf_counter() - t)")
    out = []
    for script in (code, EMULATOR_JIT):
        with tempfile.TemporaryDirectory() as cache:
            env = dict(os.environ, NUMBA_CACHE_DIR=cache)
            for _ in range(2):
                res = subprocess.run([sys.executable, "-c", script], env=env,
                                     capture_output=True, text=True, check=True)
                out.append(tuple(float(v) for v in res.stdout.split()))
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true",
                    help="NumPy path on a tenth of the θ samples, extrapolated")
    ap.add_argument("--rows", nargs="+",
                    default=["beam-1d", "beam-2d", "shear-5", "app", "koh", "hm-wave"])
    ap.add_argument("--sklearn-pairs", type=int, default=300)
    ap.add_argument("--no-jit", action="store_true", help="skip the cold/warm JIT timing")
    ap.add_argument("--repeat", type=int, default=5,
                    help="timings of the hm-wave rows: shortest of this many runs")
    args = ap.parse_args()
    rng = np.random.default_rng(1)

    print(f"cores {cores()}, compiled threads {compiled.num_threads()}, load average "
          f"{os.getloadavg()[0]:.1f} at start")
    if not args.no_jit:
        (cold_w, cold_t), (warm_w, warm_t), (cold_e,), (warm_e,) = jit_times()
        print(f"JIT: warm_up() in a fresh process, empty cache {cold_w:.1f} s (process "
              f"{cold_t:.1f} s); cache filled {warm_w:.2f} s (process {warm_t:.2f} s)")
        print(f"JIT: the history-matching emulator kernel alone, empty cache {cold_e:.1f} s; "
              f"cache filled {warm_e:.2f} s")
    rates = machine_rates()
    print(f"machine (1 core): exp {rates['numpy_exp_s'] * 1e9:.2f} ns (NumPy), "
          f"{rates['compiled_exp_s'] * 1e9:.2f} ns (compiled); dgemm "
          f"{1e-9 / rates['flop_s']:.1f} Gflop/s; bound uses the faster exp × "
          f"{rates['cores']} cores")
    print(f"peak RSS before the rows: "
          f"{resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB\n")
    print(f"{'row':<28} {'pairs':>9} {'kept':>9} {'numpy s':>9} {'numba s':>7}"
          f" {'cpu/cor':>7} {'sklearn s':>9} {'np/nb':>7} {'sk/nb':>8} {'bound s':>7}"
          f" {'nb/bd':>7} {'Δ pred':>8} {'Δ log w':>8} {'RSS MB':>6}")
    for r in args.rows:
        if r == "app":
            for name in PAPER:
                row(name, APP, rates, args, rng)
        elif r in ("koh", "koh-wave"):
            koh_row()
            if r == "koh-wave":
                hm_wave_rows(rates, args.repeat)
        elif r == "hm-wave":
            hm_wave_rows(rates, args.repeat)
        else:
            row(r, PAPER[r], rates, args, rng)
    print("\n* NumPy time extrapolated from a tenth of the θ samples (--quick).")
    print(f"load average {os.getloadavg()[0]:.1f} at end")


if __name__ == "__main__":
    main()
