"""Multivariate implausibility (issue 43): scoring a wave of 100,000 candidates.

Usage: python bench/bench_multivariate.py [--quick]

For each case (its default V_m correlation length, seed 0, the wave-1 emulator): seconds to
score 100,000 candidate θ under the multivariate rule (``HistoryMatchProblem.score``: the
emulator's joint moments, then I_M² over every target), against the max rule on the same
emulator and against a naive loop that, per candidate, takes the emulator's covariance
(``EmulatorAt.moments``) and calls ``scipy.linalg.cho_factor`` / ``cho_solve``. The naive
loop runs on the first 2,000 candidates (1,000 with --quick) and is scaled to 100,000; the
two agree to the printed relative difference. Targets: ≤ 1 s on beam-2d, ≤ 0.5 s on
beam-1d, on 2 cores. Best of 3 runs; the machine may be shared, so read the ratios.
"""

import sys
import time

import numpy as np
from scipy.linalg import cho_factor, cho_solve

from mdcore import _cases as cases
from mdcore._history_matching import case_problem, next_wave
from mdcore._threads import single_threaded_blas_for_process

M = 100_000


def best(fn, *args, repeats=3):
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        out = fn(*args)
        times.append(time.perf_counter() - t)
    return min(times), out


def naive(problem, emulator, theta):
    at = emulator.at(problem.X)
    N = problem.X.shape[0]
    out = np.empty(len(theta))
    for i, t in enumerate(theta):
        mean, cov = at.moments(t[None])
        S = problem.V.copy()
        for o in range(cov.shape[1]):
            S[o * N:(o + 1) * N, o * N:(o + 1) * N] += cov[0, o]
        r = (problem.z.T - mean[0]).ravel()
        out[i] = r @ cho_solve(cho_factor(S, lower=True), r)
    return out


def main():
    single_threaded_blas_for_process()        # as the command line and the app run
    n_naive = 1000 if "--quick" in sys.argv else 2000
    print(f"{'case':>8} {'targets':>7} {'multivariate s':>14} {'max rule s':>10} "
          f"{'naive s (scaled)':>16} {'naive / mv':>10} {'mv / max':>8} {'max rel diff':>12}")
    for name in ("beam-1d", "beam-2d", "shear-5"):
        case = cases.load(name, seed=0)
        mv = case_problem(case, rule="multivariate", max_waves=1)
        mx = case_problem(case, rule="max", max_waves=1)
        emulator = next_wave(mv).emulator
        b = case.theta_bounds
        theta = b[:, 0] + (b[:, 1] - b[:, 0]) * np.random.default_rng(0).uniform(size=(M, case.p))
        mv.score(theta[:1000], emulator)
        t_mv, score = best(mv.score, theta, emulator)
        t_max, _ = best(mx.score, theta, emulator)
        t = time.perf_counter()
        ref = naive(mv, emulator, theta[:n_naive])
        t_naive = (time.perf_counter() - t) * M / n_naive
        diff = np.max(np.abs(score.implausibility[:n_naive] - ref) / ref)
        print(f"{name:>8} {mv.z.size:>7} {t_mv:>14.3f} {t_max:>10.3f} {t_naive:>16.2f} "
              f"{t_naive / t_mv:>10.0f} {t_mv / t_max:>8.1f} {diff:>12.1e}")


if __name__ == "__main__":
    main()
