"""Speed of the Kennedy–O'Hagan baseline on beam-1d (issue 6: the paper chain in ≤ 60 s).

Usage: python bench/bench_koh.py [--n-iter 150000] [--burn-in 50000] [--ref-steps 3000]

Times ``mdcore._koh.infer`` with the paper's chain (empirical Bayes, 150,000 adaptive-
Metropolis steps) and the prediction at the 200 test inputs. The reference, measured in the
same run, is the same log posterior evaluated naively: every step rebuilds what does not
depend on θ (the emulator's x-parts via ``Emulator.at``, ``K_δ + σ_n² I``) before the
θ-dependent work. Its per-step cost is measured over ``--ref-steps`` steps and extrapolated.
"""

import argparse
import time

import numpy as np

from mdcore import _cases as cases
from mdcore._history_matching import history_match_case
from mdcore._koh import KOHOptions, gaussian_log_likelihood, infer_koh, noise_cov
from mdcore._linalg import JitterLog
from mdcore._pipeline import koh_phi_prior


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n-iter", type=int, default=150_000)
    ap.add_argument("--burn-in", type=int, default=50_000)
    ap.add_argument("--ref-steps", type=int, default=3000)
    args = ap.parse_args()

    case = cases.load("beam-1d", seed=0)
    em = history_match_case(case, seed=0).waves[-1].emulator
    t0 = time.perf_counter()
    model = infer_koh(em, case.X_train, case.z_train, theta_prior=case.theta_prior,
                  bounds=case.theta_bounds, seed=0,
        options=KOHOptions(phi_prior=koh_phi_prior(case), n_iter=args.n_iter, burn_in=args.burn_in))
    t1 = time.perf_counter()
    model.predict(case.X_test)
    t2 = time.perf_counter()

    # Reference: the same log likelihood, rebuilding the θ-independent parts every step.
    X, zT, lp = case.X_train, case.z_train.T, model.log_phi
    rng = np.random.default_rng(0)
    thetas = model.theta[rng.integers(0, model.theta.shape[0], args.ref_steps)]
    log = JitterLog()
    ours, naive = np.empty(args.ref_steps), np.empty(args.ref_steps)
    B = noise_cov(lp, X)
    at = em.at(X)
    s = time.perf_counter()
    for i, th in enumerate(thetas):
        mean, cov = at.moments_at(at.theta_terms(th[None], check=False))
        ours[i] = gaussian_log_likelihood(mean, cov, B, zT, log)[0]
    per_ours = (time.perf_counter() - s) / args.ref_steps
    s = time.perf_counter()
    for i, th in enumerate(thetas):
        at_i = em.at(X)
        B_i = noise_cov(lp, X)
        mean, cov = at_i.moments(th[None])
        naive[i] = gaussian_log_likelihood(mean, cov, B_i, zT, log)[0]
    per_naive = (time.perf_counter() - s) / args.ref_steps
    assert np.allclose(ours, naive, rtol=1e-12, atol=1e-9)

    chain = model.chain
    print(f"beam-1d KOH, {args.n_iter:,} iterations ({args.burn_in:,} burn-in), seed 0")
    print(f"{'empirical Bayes φ̂':<28} {model.seconds_phi:8.2f} s")
    print(f"{'adaptive Metropolis':<28} {chain.seconds:8.2f} s   "
          f"({1e6 * chain.seconds / args.n_iter:.0f} µs per step incl. the sampler)")
    print(f"{'infer total':<28} {t1 - t0:8.2f} s   "
          f"{'ok' if t1 - t0 <= 60 else 'over'} (goal ≤ 60 s on 2 cores)")
    print(f"{'predict (200 inputs)':<28} {t2 - t1:8.2f} s")
    print(f"{'log posterior per step':<28} {1e6 * per_ours:8.1f} µs   naive (rebuilds θ-free "
          f"parts) {1e6 * per_naive:.1f} µs   ratio {per_naive / per_ours:.1f}x")
    print(f"{'naive chain (extrapolated)':<28} {per_naive * args.n_iter:8.1f} s of likelihood "
          f"alone, against {per_ours * args.n_iter:.1f} s")
    print(f"acceptance {chain.acceptance_rate:.3f}; IAT "
          f"{', '.join(f'{t:.1f}' for t in chain.iat)}; ESS "
          f"{', '.join(f'{e:,.0f}' for e in chain.ess)}; "
          f"ESS per second {np.min(chain.ess) / (t1 - t0):.0f}")


if __name__ == "__main__":
    main()
