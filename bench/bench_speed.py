"""The speed table of the user-visible targets, with ratios timed in the same run.

Usage: python bench/bench_speed.py [--quick] [--rows beam-1d beam-2d shear-5 app koh hm-wave]
                                   [--sklearn-pairs 300] [--no-jit] [--repeat 5]
                                   [--proposal {adaptive,prior}]

Rows:

- ``S3 <case>``: scenario 3 at the paper's sizes (beam-1d 1000 × 500, beam-2d 1000 × 1000,
  shear-5 1000 × 500 on all 5 outputs): the weights of every pair and the mixture
  prediction at the case's test inputs (``infer_discrepancy`` + ``predict``), with
  ``backend="numpy"`` (the implementation of record) and ``backend="numba"`` (the compiled
  pair kernel), with ``--proposal``'s φ proposal (the library's default unless given);
  ``app`` runs the app's default sizes (100 × 50) on every case. ``sklearn``
  is one ``GaussianProcessRegressor`` per pair (fixed hyperparameters): ``fit`` for every
  pair and ``predict(return_std=True)`` for the pairs the prediction keeps, timed on
  ``--sklearn-pairs`` pairs of each kind and extrapolated (an ARD Matérn 3/2 over [y, x]:
  the same cost, not the same kernel). ``cpu/cor`` is the compiled run's CPU time over the
  cores (what it takes on idle cores); ``Δ pred`` the largest difference of the compiled
  predictions from NumPy's relative to each field's largest magnitude, ``Δ log w`` the
  largest difference of the log weights the prediction keeps. ``--quick`` runs NumPy on a
  tenth of the θ samples and extrapolates by pair counts.
- ``KOH``: the KOH chain of beam-1d at the paper's 150,000 steps, both backends.
- ``HM wave``: one history-matching wave of 10⁵ candidates per case (simulator runs,
  emulator fit, candidates, scoring; NumPy), shortest of ``--repeat``, split into the fit
  and the scoring; ``sklearn`` is ``GaussianProcessRegressor.predict(return_std=True)`` of
  the dense GP over (x, θ) at the candidates, timed on 500 and extrapolated.

The JIT line times ``compiled.warm_up()`` in fresh processes with an empty and then a filled
numba cache. Figures only, nothing is asserted: the machine may be shared, so the load
average is printed.
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

from mdcore import _cases as cases
from mdcore import _compiled as compiled
from mdcore import _threads as threads
from mdcore._discrepancy import DiscrepancyOptions, infer_discrepancy
from mdcore._emulator import fit_emulator
from mdcore._history_matching import case_problem, history_match_case, next_wave
from mdcore._pipeline import PAPER_SIZES, Method, Settings, run_method

APP = (100, 50)


def best_of(fn, repeat=5) -> float:
    """Shortest of ``repeat`` wall-clock timings (the least disturbed by other load)."""
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return min(times)


def rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def library(case, theta, n_phi, backend, proposal=None):
    """(model, prediction, infer s, predict s, CPU s) of the library path."""
    proposal = {} if proposal is None else {"proposal": proposal}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        c0, t0 = time.process_time(), time.perf_counter()
        model = infer_discrepancy(
            case.simulate, theta, case.X_train, case.z_train, scenario=3, seed=0,
            options=DiscrepancyOptions(n_phi=n_phi, phi_prior=case.phi_prior, backend=backend,
                                       **proposal))
        t1 = time.perf_counter()
        pred = model.predict(case.X_test)
        t2, c2 = time.perf_counter(), time.process_time()
    return model, pred, t1 - t0, t2 - t1, c2 - c0


def evaluated(model, X) -> list:
    """Per output, the flat indices of the pairs ``model.predict(X)`` evaluates (the prior
    proposal: above ``prune``; the adaptive one: its draws by weight for X's inputs)."""
    return [idx for idx, *_ in model._kept(None, len(np.unique(X, axis=0)))]


def kept_log_weight_gap(model, ref) -> float:
    """Largest |Δ log w| over the pairs the prediction keeps (the reference's pruning)."""
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

    y_test = case.simulate(case.X_test, theta)
    K = model.log_params.shape[2]

    def fitted(o, flat):
        j, k = divmod(int(flat), K)
        p = np.exp(model.log_params[o][j, k])
        kern = (ConstantKernel(p[0] ** 2) * Matern(length_scale=p[1:-1], nu=1.5)
                + WhiteKernel(p[-1] ** 2))
        reg = GaussianProcessRegressor(kern, optimizer=None, alpha=0.0)
        with contextlib.suppress(np.linalg.LinAlgError):         # not PD: sklearn gives up
            reg.fit(np.column_stack([model.Y[j], case.X_train]), case.z_train[:, o])
            return reg, j
        return None

    pairs, total = model.log_weights[0].size, 0.0
    for o in range(model.n_out):
        idx = rng.choice(pairs, size=min(n_sample, pairs), replace=False)
        t = time.perf_counter()
        for flat in idx:
            fitted(o, flat)
        total += (time.perf_counter() - t) / idx.size * pairs
        kept = evaluated(model, case.X_test)[o]
        regs = [r for r in (fitted(o, f) for f in rng.choice(kept, min(n_sample, kept.size),
                                                              replace=False)) if r]
        t = time.perf_counter()
        for reg, j in regs:
            reg.predict(np.column_stack([y_test[j], case.X_test]), return_std=True)
        total += (time.perf_counter() - t) / max(1, len(regs)) * kept.size
    return total


def s3_row(name, sizes, args, rng):
    case = cases.load(name)
    n_s, n_phi = sizes
    hm = history_match_case(case, seed=0)
    theta = hm.posterior_samples(n_s, seed=0)
    compiled.warm_up()
    library(case, theta[:2], 2, "numpy", args.proposal)  # first-call costs out of the way
    model_n, pred_n, inf_n, pre_n, cpu_n = library(case, theta, n_phi, "numba", args.proposal)
    kept = sum(i.size for i in evaluated(model_n, case.X_test))
    pairs = case.z_train.shape[1] * n_s * n_phi
    sub = max(1, n_s // 10) if args.quick and n_s > 100 else n_s
    model_r, pred_r, inf_r, pre_r, _ = library(case, theta[:sub], n_phi, "numpy", args.proposal)
    numpy_s = inf_r * n_s / sub + pre_r * kept / max(1, sum(i.size for i in
                                                        evaluated(model_r, case.X_test)))
    sk = sklearn_seconds(case, theta, model_n, args.sklearn_pairs, rng) \
        if args.sklearn_pairs else np.nan
    if sub < n_s:                  # compare on the subset the NumPy path ran on
        model_n, pred_n, *_ = library(case, theta[:sub], n_phi, "numba", args.proposal)
    gaps = agreement(pred_n, pred_r), kept_log_weight_gap(model_n, model_r)
    numba_s = inf_n + pre_n
    label = f"S3 {name} {n_s}×{n_phi}" + (f" ×{case.z_train.shape[1]}" if pairs > n_s * n_phi
                                          else "")
    print(f"{label:<26} {pairs:>9,} {kept:>9,} {numpy_s:>8.2f}{'*' if sub < n_s else ' '}"
          f" {numba_s:>7.2f} {cpu_n / threads.num_threads():>7.2f} {sk:>9.1f}"
          f" {numpy_s / numba_s:>6.1f}x {sk / numba_s:>7.0f}x {gaps[0]:>8.1e} {gaps[1]:>8.1e}"
          f" {rss_mb():>6.0f}", flush=True)
    print(f"{'':<26}   (numba: weights {inf_n:.2f} + predict {pre_n:.2f} s)", flush=True)


def koh_row():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        case = cases.load("beam-1d")
        hm = history_match_case(case, seed=0)
        seconds, chains = {}, {}
        for backend in ("numpy", "numba"):
            settings = dataclasses.replace(Settings.paper("beam-1d"), backend=backend)
            run_method(case, hm, Method.KOH, dataclasses.replace(settings, n_iter=3000,
                                                                 burn_in=1000), seed=0)
            t = time.perf_counter()
            res = run_method(case, hm, Method.KOH, settings, seed=0)
            seconds[backend] = time.perf_counter() - t
            chains[backend] = res.model.chain.samples
    gap = float(np.max(np.abs(chains["numba"] - chains["numpy"])))
    print(f"{'KOH beam-1d 150,000 steps':<26} {'':>9} {'':>9} {seconds['numpy']:>8.2f} "
          f" {seconds['numba']:>7.2f} {'':>7} {'':>9} {seconds['numpy'] / seconds['numba']:>6.1f}x"
          f"   (target ≤ 2 s; chains differ by at most {gap:.1e})", flush=True)


def sklearn_wave_seconds(problem, emulator, theta, n_sample=500):
    """``GaussianProcessRegressor.predict(return_std=True)`` of the dense GP over (x, θ)
    with the emulator's hyperparameters, per output, extrapolated to every candidate."""
    from sklearn.gaussian_process import GaussianProcessRegressor
    from sklearn.gaussian_process.kernels import ConstantKernel, Matern, WhiteKernel

    p, d_x = problem.p, problem.X.shape[1]
    lo, span = problem.bounds[:, 0], problem.bounds[:, 1] - problem.bounds[:, 0]
    Xu, Tu = emulator.unit_x(problem.X), (emulator.theta_train - lo) / span
    train = np.column_stack([np.tile(Xu, (len(Tu), 1)), np.repeat(Tu, len(Xu), axis=0)])
    sub = (theta[:n_sample] - lo) / span
    test = np.column_stack([np.tile(Xu, (len(sub), 1)), np.repeat(sub, len(Xu), axis=0)])
    total = 0.0
    for o, g in enumerate(emulator.gps):
        e = np.exp(g.log_params)
        kern = (ConstantKernel(e[0] ** 2) * Matern(length_scale=np.r_[e[1 + p:1 + p + d_x],
                                                                      e[1:1 + p]], nu=1.5)
                + WhiteKernel(e[-1] ** 2))
        reg = GaussianProcessRegressor(kern, optimizer=None, alpha=0.0)
        with contextlib.suppress(np.linalg.LinAlgError):
            reg.fit(train, emulator.y_train[..., o].ravel())
            t = time.perf_counter()
            reg.predict(test, return_std=True)
            total += time.perf_counter() - t
    return total * len(theta) / len(sub)


def hm_wave_row(name, repeat):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        problem = case_problem(cases.load(name), n_candidates=100_000, max_waves=1)
        wave = next_wave(problem)                                # first-call costs
        wall = best_of(partial(next_wave, problem), repeat)
        em, theta = wave.emulator, wave.candidates
        fit = best_of(partial(fit_emulator, problem.X, em.theta_train, em.y_train,
                              problem.bounds, seed=0), repeat)
        score = best_of(partial(problem.score, theta, em), repeat)
        sk = sklearn_wave_seconds(problem, em, theta)
    print(f"{'HM wave ' + name + ' 10⁵ cand.':<26} {len(theta):>9,} {len(wave.nroy):>9,}"
          f" {wall:>8.3f}  {'':>7} {'':>7} {sk:>9.2f} {'':>7} {sk / wall:>7.0f}x"
          f"   (target ≤ 0.2 s; fit {fit:.3f} s, scoring {score:.3f} s; R = "
          f"{len(em.theta_train)}, N = {problem.X.shape[0]}, {problem.z.shape[1]} output(s))",
          flush=True)


def jit_times():
    """warm_up() in fresh processes: empty numba cache (cold), then filled (warm)."""
    code = ("import time; t = time.perf_counter(); from mdcore import _compiled as compiled; "
            "w = compiled.warm_up(); print(w, time.perf_counter() - t)")
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, NUMBA_CACHE_DIR=cache)
        return [tuple(float(v) for v in subprocess.run(
            [sys.executable, "-c", code], env=env, capture_output=True, text=True,
            check=True).stdout.split()) for _ in range(2)]


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
    ap.add_argument("--proposal", choices=["adaptive", "prior"], default=None,
                    help="scenario 3's φ proposal in the S3 rows (default: the library's)")
    args = ap.parse_args()
    rng = np.random.default_rng(1)
    threads.single_threaded_blas_for_process()
    print(f"cores {threads.cores()}, compute threads {threads.num_threads()}, load average "
          f"{os.getloadavg()[0]:.1f} at start")
    if not args.no_jit:
        (cold, cold_p), (warm, warm_p) = jit_times()
        print(f"JIT: warm_up() in a fresh process, empty cache {cold:.1f} s (process "
              f"{cold_p:.1f} s); cache filled {warm:.2f} s (process {warm_p:.2f} s)")
    print(f"\n{'row':<26} {'pairs':>9} {'kept':>9} {'numpy s':>9} {'numba s':>7}"
          f" {'cpu/cor':>7} {'sklearn s':>9} {'np/nb':>7} {'sk/nb':>8} {'Δ pred':>8}"
          f" {'Δ log w':>8} {'RSS MB':>6}")
    for r in args.rows:
        if r == "app":
            for name in PAPER_SIZES:
                s3_row(name, APP, args, rng)
        elif r == "koh":
            koh_row()
        elif r == "hm-wave":
            for name in PAPER_SIZES:
                hm_wave_row(name, args.repeat)
        else:
            s3_row(r, PAPER_SIZES[r], args, rng)
    print("\n* NumPy time extrapolated from a tenth of the θ samples (--quick).")
    print(f"load average {os.getloadavg()[0]:.1f} at end")


if __name__ == "__main__":
    main()
