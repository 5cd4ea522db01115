"""Adaptive Metropolis and its diagnostics: the IAT of an AR(1) chain in closed form, chain
reliability (emcee's 50 τ rule) and its warning, bad input. (The sampler's posterior against
a closed form is tested through the KOH toy in tests/test_koh.py.)"""

import warnings

import numpy as np
import pytest

from mdcore._exceptions import ConvergenceWarning
from mdcore._mcmc import RELIABLE_TAUS, adaptive_metropolis, integrated_autocorr_time


def target(x):
    return -0.5 * float(x @ x)


def test_a_short_chain_is_flagged_and_a_long_one_is_not():
    with pytest.warns(ConvergenceWarning, match="shorter than 50 autocorrelation times.*raise "
                                                "n_iter to at least"):
        short = adaptive_metropolis(target, np.zeros(2), n_iter=60, burn_in=20, seed=0)
    assert not short.reliable
    assert np.any(short.samples.shape[0] <= RELIABLE_TAUS * short.iat)
    with warnings.catch_warnings():
        warnings.simplefilter("error", ConvergenceWarning)
        long = adaptive_metropolis(target, np.zeros(2), n_iter=20_000, burn_in=2_000, seed=0)
    assert long.reliable and np.all(long.samples.shape[0] > RELIABLE_TAUS * long.iat)



def test_acceptance_rates_count_burn_in_and_kept_steps_apart():
    """A flat target accepts every proposal (log u < 0); a target that is -inf away from
    x0 accepts none. The burn-in rate counts the burn-in's steps only (it used to add
    every kept step's acceptance to both counters)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        flat = adaptive_metropolis(lambda x: 0.0, np.zeros(2), n_iter=3000, burn_in=500,
                                   seed=1)
        stuck = adaptive_metropolis(lambda x: 0.0 if not np.any(x) else -np.inf,
                                    np.zeros(2), n_iter=3000, burn_in=500, seed=1)
    assert flat.acceptance_rate == flat.acceptance_rate_burn_in == 1.0
    assert stuck.acceptance_rate == stuck.acceptance_rate_burn_in == 0.0


def test_iat_of_ar1_matches_closed_form():
    rng = np.random.default_rng(3)
    a, n = 0.8, 400_000
    e = rng.standard_normal(n)
    x = np.empty(n)
    x[0] = e[0] / np.sqrt(1 - a * a)
    for i in range(1, n):
        x[i] = a * x[i - 1] + e[i]
    tau = integrated_autocorr_time(np.column_stack([x, e]))
    assert tau[0] == pytest.approx((1 + a) / (1 - a), rel=0.1)     # = 9
    assert tau[1] == pytest.approx(1.0, abs=0.1)                   # white noise
    assert integrated_autocorr_time(np.ones(50))[0] == 50          # never moved


def test_mcmc_bad_input():
    with pytest.raises(ValueError, match="burn_in must be smaller"):
        adaptive_metropolis(lambda x: 0.0, [0.0], n_iter=10, burn_in=10)
    with pytest.raises(ValueError, match=r"log_target\(x0\) must be finite"):
        adaptive_metropolis(lambda x: -np.inf, [0.0], n_iter=10, burn_in=1)
    with pytest.raises(ValueError, match="n must be ≥ 2|n ≥ 2"):
        integrated_autocorr_time([1.0])
    with pytest.raises(ValueError, match="NaN"):
        integrated_autocorr_time([1.0, np.nan, 2.0])
