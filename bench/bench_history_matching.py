"""Time per history-matching wave and candidates scored per second.

Usage: python bench/bench_history_matching.py

For beam-1d and shear-5 (case defaults, seed 0, up to 3 waves with convergence_ratio 0.02
so that later waves run): seconds per wave, and emulator scoring throughput (candidate θ
per second at all observed inputs and outputs) with the wave-1 emulator.
"""

import time

import numpy as np

from mdcore import _cases as cases
from mdcore._history_matching import case_problem, iter_waves


def main():
    for name in ("beam-1d", "shear-5"):
        case = cases.load(name, seed=0)
        problem = case_problem(case, max_waves=3, convergence_ratio=0.02)
        waves = []
        for w in iter_waves(problem):
            waves.append(w)
            print(f"{name} wave {w.index}: {w.seconds:6.2f} s, {len(w.candidates):,} candidates, "
                  f"NROY {100 * w.nroy_fraction:.2f} %, {w.status}")
        rng = np.random.default_rng(0)
        b = case.theta_bounds
        theta = b[:, 0] + (b[:, 1] - b[:, 0]) * rng.uniform(size=(100_000, case.p))
        problem.score(theta[:1000], waves[0].emulator)
        t = time.perf_counter()
        problem.score(theta, waves[0].emulator)
        dt = time.perf_counter() - t
        print(f"{name}: scored 100,000 candidates in {dt:.3f} s = {1e5 / dt:,.0f} candidates/s "
              f"({problem.X.shape[0]} inputs × {problem.z.shape[1]} outputs)\n")


if __name__ == "__main__":
    main()
