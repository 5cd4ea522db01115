"""Cost of the diagnostics (docs/diagnostics.md) against what they diagnose, timed in one run.

Usage: python bench/bench_diagnostics.py [--quick]

Per case (seed 0, case defaults, and 4 waves of 5 runs for beam-1d): the history match
against each wave's leave-one-run-out check and the space views; each decoupled scenario at
the paper's sizes (``--quick``: N_s = 200, N_φ = 100) against its θ–δ split at the test
inputs. Shortest of 5 for the diagnostics.
"""

import sys
import time
import warnings

from bench_speed import best_of

from mdcore import _cases as cases
from mdcore._diagnostics import space_views, theta_delta_split, validate_waves
from mdcore._history_matching import history_match_case
from mdcore._pipeline import Method, Settings, run_method


def main():
    quick = "--quick" in sys.argv
    warnings.simplefilter("ignore")
    runs = [("beam-1d", {}), ("beam-1d", dict(n_runs=5, convergence_ratio=1e-3, max_waves=4)),
            ("beam-2d", {}), ("shear-5", {})]
    for name, options in runs:
        case = cases.load(name, seed=0)
        t = time.perf_counter()
        hm = history_match_case(case, seed=0, **options)
        t_hm = time.perf_counter() - t
        t_loo = best_of(lambda hm=hm: validate_waves(hm, warn=False))
        t_space = best_of(lambda hm=hm: space_views(hm))
        label = f"{name} {len(hm.waves)} wave(s)"
        print(f"{label:<20} history match {t_hm:6.3f} s | LOO, all waves {t_loo:6.4f} s "
              f"({100 * t_loo / t_hm:4.1f} %) | space views {t_space:6.4f} s "
              f"({100 * t_space / t_hm:4.1f} %)")
        if options:
            continue
        settings = Settings(n_s=200, n_phi=100) if quick else Settings.paper(name)
        for method in (Method.S2, Method.S3):
            run_method(case, hm, method, Settings(n_s=5, n_phi=5), seed=0)     # compile
            t = time.perf_counter()
            r = run_method(case, hm, method, settings, seed=0)
            t_m = time.perf_counter() - t
            t_split = best_of(lambda r=r, X=case.X_test: theta_delta_split(r.model, X))
            size = f"{settings.n_s}×{settings.n_phi if method is Method.S3 else 1}"
            print(f"{'':<20} {method.label} {size:>9} {t_m:6.2f} s | θ–δ split {t_split:5.2f} s "
                  f"({100 * t_split / t_m:4.1f} %)")


if __name__ == "__main__":
    main()
