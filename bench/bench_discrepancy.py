"""Scenario 3 at the paper's sizes against a scikit-learn per-pair loop.

Usage: python bench/bench_discrepancy.py [--cases beam-1d beam-2d] [--fraction 0.002]

For each case: history matching (not timed), then scenario 3 with the paper's N_s × N_φ
(beam-1d 1000 × 500, beam-2d 1000 × 1000): the weights of every pair and the mixture
prediction at the test inputs. In the same run, a scikit-learn loop fits and predicts one
GaussianProcessRegressor per pair (fixed hyperparameters, ``optimizer=None``; the NLML of
every pair and the predictive mean and std at the test inputs) on a random ``fraction`` of
the pairs; its time is extrapolated to all pairs. Peak memory is the process's peak
resident set size so far (``ru_maxrss``), which includes the interpreter and libraries.
"""

import argparse
import resource
import time
import warnings

import numpy as np

from mdcore import _cases as cases
from mdcore._discrepancy import DiscrepancyOptions, infer_discrepancy
from mdcore._history_matching import history_match_case
from mdcore._reproduce import PAPER_SIZES


def sklearn_loop(case, theta, phi, idx):
    """Fit + predict one scikit-learn GP per (θ, φ) pair in ``idx``; seconds taken."""
    from sklearn.gaussian_process import GaussianProcessRegressor
    from sklearn.gaussian_process.kernels import ConstantKernel, Matern, WhiteKernel

    y_train = case.simulate(case.X_train, theta)
    y_test = case.simulate(case.X_test, theta)
    n_phi = phi.shape[1]
    start = time.perf_counter()
    for flat in idx:
        j, k = divmod(int(flat), n_phi)
        lp = np.exp(phi[j, k])
        sf, ls, sn = lp[0], lp[1:-1], lp[-1]
        kern = ConstantKernel(sf**2) * Matern(length_scale=ls, nu=1.5) + WhiteKernel(sn**2)
        reg = GaussianProcessRegressor(kern, optimizer=None, alpha=0.0)
        reg.fit(np.column_stack([y_train[j], case.X_train]), case.z_train[:, 0])
        _ = reg.log_marginal_likelihood_value_
        reg.predict(np.column_stack([y_test[j], case.X_test]), return_std=True)
    return time.perf_counter() - start


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="+", default=["beam-1d", "beam-2d"])
    ap.add_argument("--fraction", type=float, default=0.002)
    args = ap.parse_args()
    print(f"{'case':>8} {'N_s×N_φ':>11} {'infer s':>8} {'predict s':>9} {'total s':>8} "
          f"{'kept':>8} {'peak RSS MB':>11} {'sklearn s (extrap.)':>20} {'ratio':>7}")
    for name in args.cases:
        case = cases.load(name)
        hm = history_match_case(case, seed=0)
        n_s, n_phi = PAPER_SIZES[name]
        theta = hm.posterior_samples(n_s, seed=0)
        t0 = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            model = infer_discrepancy(
                case.simulate, theta, case.X_train, case.z_train, scenario=3, seed=0,
                options=DiscrepancyOptions(n_phi=n_phi, phi_prior=case.phi_prior))
            t1 = time.perf_counter()
            model.predict(case.X_test)
        t2 = time.perf_counter()
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024

        rng = np.random.default_rng(1)
        n_pairs = n_s * n_phi
        idx = rng.choice(n_pairs, size=max(1, int(args.fraction * n_pairs)), replace=False)
        sk = sklearn_loop(case, theta, model.log_params[0], idx) * n_pairs / idx.size
        print(f"{name:>8} {f'{n_s}×{n_phi}':>11} {t1 - t0:>8.2f} {t2 - t1:>9.2f} "
              f"{t2 - t0:>8.2f} {int(model.n_components[0]):>8,} {peak:>11.0f} {sk:>20.0f} "
              f"{sk / (t2 - t0):>6.0f}x")


if __name__ == "__main__":
    main()
