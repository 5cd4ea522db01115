"""The app's run estimates against measured runs (docs/performance.md, "Run estimates").

Times what the app's buttons run, through its state (no browser): each case's waves to
convergence and single waves of 10⁶ candidates against ``waves_seconds``, and scenario 3
(the adaptive proposal) at several N_s × N_φ against ``run_seconds``. Wall seconds of one
run each: on a shared machine compare the ratios, not the seconds.

    python bench/app_estimates.py [case ...]
"""

import sys
import time
import warnings
from functools import partial

from mdcore._pipeline import Method
from mdcore_app.state import ExplorerState

SIZES = [(100, 50), (100, 500), (1000, 200), (1000, 500), (1000, 1000)]


def timed(fn) -> float:
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


def main(names: list[str]) -> None:
    warnings.simplefilter("ignore")
    print("case     run                          measured s  estimated s  ratio")
    for name in names:
        s = ExplorerState()
        s.case_name = name
        est = s.waves_seconds()
        row = f"{name:8} waves to convergence ({{}})"
        t = timed(s.run_to_convergence)
        print(f"{row.format(len(s.waves)):36} {t:8.2f}  {est:11.2f}  {est / t:5.2f}")
        w = ExplorerState()
        w.case_name, w.n_candidates = name, 1_000_000
        for k in (1, 2, 3):
            if w.waves and w.waves[-1].done:
                break
            est = w.waves_seconds(False)
            t = timed(w.next_wave)
            print(f"{name:8} wave {k} of 10⁶ candidates        {t:8.2f}  {est:11.2f}  "
                  f"{est / t:5.2f}")
        s.scenarios = [Method.S1]
        s.run_discrepancy()
        for n_s, n_phi in SIZES:
            s.scenarios = [Method.S1]
            s.param.update(n_s=n_s, n_phi=n_phi)
            # A new scenario with a result cached runs at once (DiscrepancyModel).
            t = timed(partial(s.param.update, scenarios=[Method.S3]))
            est = s.run_seconds()
            print(f"{name:8} scenario 3, {n_s} × {n_phi:<6}          {t:8.2f}  {est:11.2f}  "
                  f"{est / t:5.2f}")

if __name__ == "__main__":
    main(sys.argv[1:] or ["beam-1d", "beam-2d", "shear-5"])
