"""NLML throughput of the batched GP core against a scikit-learn per-pair loop.

Usage: python bench/bench_gp.py [--pairs 20000] [--sk-pairs 300]

Prints pairs per second for mdcore._gp.neg_log_marginal_likelihood (one batched call) and
for scikit-learn's GaussianProcessRegressor.log_marginal_likelihood called once per pair
(same kernel: ConstantKernel * Matern(nu=1.5, ARD) + WhiteKernel, d_y = 1, d_x = 1),
both measured in this run, and the ratio.
"""

import argparse
import time

import numpy as np

from mdcore import _gp as gp


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs", type=int, default=20000)
    ap.add_argument("--sk-pairs", type=int, default=300)
    args = ap.parse_args()
    from sklearn.gaussian_process import GaussianProcessRegressor
    from sklearn.gaussian_process.kernels import ConstantKernel, Matern, WhiteKernel

    rng = np.random.default_rng(0)
    print(f"{'N':>4} {'mdcore pairs/s':>16} {'sklearn pairs/s':>16} {'ratio':>8}")
    for N in (13, 30, 64):
        X = np.linspace(0, 1, N)[:, None]
        Y = np.sin(3 * X) + 0.01 * rng.normal(size=(args.pairs, N, 1))
        z = (np.sin(3 * X) + X)[:, 0]
        lp = np.column_stack([rng.normal(0, 0.3, args.pairs), rng.normal(0, 0.3, args.pairs),
                              rng.normal(-1, 0.3, args.pairs), rng.uniform(-4, -2, args.pairs)])
        gp.neg_log_marginal_likelihood(lp[:100], Y[:100], X, z)        # warm-up
        t = time.perf_counter()
        gp.neg_log_marginal_likelihood(lp, Y, X, z)
        ours = args.pairs / (time.perf_counter() - t)

        n_sk = args.sk_pairs
        t = time.perf_counter()
        for i in range(n_sk):
            sf, ly, lx, sn = np.exp(lp[i])
            k = (ConstantKernel(sf**2) * Matern(length_scale=[ly, lx], nu=1.5)
                 + WhiteKernel(sn**2))
            reg = GaussianProcessRegressor(k, optimizer=None, alpha=0.0)
            reg.fit(np.column_stack([Y[i], X]), z)
            reg.log_marginal_likelihood()
        theirs = n_sk / (time.perf_counter() - t)
        print(f"{N:>4} {ours:>16,.0f} {theirs:>16,.0f} {ours / theirs:>7.0f}x")


if __name__ == "__main__":
    main()
