"""Multivariate implausibility with a correlated V_m (issue 43), against naive references:
a plain per-candidate loop with scipy.linalg.cho_factor on the emulator's own covariance
(:meth:`mdcore._emulator.EmulatorAt.moments`), and explicit loops for V_m."""

import math

import numpy as np
import pytest
import scipy.linalg
import scipy.stats
from scipy.linalg import cho_factor, cho_solve

from mdcore import _cases as cases
from mdcore import _multivariate as multivariate
from mdcore._emulator import fit_emulator
from mdcore._history_matching import history_match, history_match_case, setup_arguments
from mdcore._history_matching import setup as hm_setup


def setup(simulate, X, z, bounds, **kwargs):
    """:func:`mdcore._history_matching.setup` with the options' fields by name."""
    return hm_setup(simulate, X, z, bounds, **setup_arguments(kwargs))


def m32(r):
    return (1.0 + math.sqrt(3.0) * r) * math.exp(-math.sqrt(3.0) * r)


def naive_v_m(X, V_m, length, R):
    """V_m by loops: σσ' R_oq m32(|x − x'| / ℓ) with one ℓ for every output (ℓ > 0)."""
    N, n_out = V_m.shape
    out = np.zeros((n_out * N, n_out * N))
    for o in range(n_out):
        for q in range(n_out):
            for i in range(N):
                for j in range(N):
                    r = math.dist(X[i], X[j]) / length
                    out[o * N + i, q * N + j] = (math.sqrt(V_m[i, o] * V_m[j, q]) * R[o, q]
                                                 * m32(r))
    return out


def naive_scores(emulator, theta, z, V):
    """Per candidate: I_M² and log det of V + V_em(θ) by scipy's cho_factor."""
    at = emulator.at(emulator.X_train)
    I2, logdet = [], []
    for t in theta:
        mean, cov = at.moments(t[None])
        n_out, N = mean.shape[1:]
        S = V.copy()
        for o in range(n_out):
            S[o * N:(o + 1) * N, o * N:(o + 1) * N] += cov[0, o]
        r = (np.asarray(z).T - mean[0]).ravel()
        c = cho_factor(S, lower=True)
        I2.append(r @ cho_solve(c, r))
        logdet.append(2.0 * np.sum(np.log(np.diag(c[0]))))
    return np.array(I2), np.array(logdet)


def random_problem(seed, n_out, p=2, d_x=2, N=9, R=12):
    """A fitted emulator of a random smooth simulator, observations and V_o + V_m."""
    rng = np.random.default_rng(seed)
    X = rng.uniform(size=(N, d_x))
    theta = rng.uniform(size=(R, p))
    w = rng.normal(size=(n_out, p + d_x))
    y = np.stack([np.sin(theta @ w[o, :p])[:, None] + np.cos(X @ w[o, p:])[None, :]
                  + 0.3 * (theta[:, :1] * X[:, 0])
                  for o in range(n_out)], axis=-1)
    em = fit_emulator(X, theta, y, np.array([[0.0, 1.0]] * p), seed=seed)
    z = y[0] + 0.1 * rng.normal(size=(N, n_out))
    V_m = rng.uniform(0.01, 0.05, size=(N, n_out))
    return em, z, V_m, rng


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("coupled", [False, True])
def test_matches_a_naive_per_candidate_cholesky(seed, coupled):
    n_out = 2
    em, z, V_m, rng = random_problem(seed, n_out)
    R = np.array([[1.0, 0.6], [0.6, 1.0]]) if coupled else None
    lengths = 0.3 if coupled else np.array([0.2, 0.5])
    V = np.diag(np.full(V_m.size, 0.002)) + multivariate.discrepancy_cov(em.X_train, V_m,
                                                                         lengths, R)
    theta = rng.uniform(-0.1, 1.1, size=(40, 2))
    ref_I2, ref_ld = naive_scores(em, theta, z, V)
    I2, var = multivariate.multivariate_implausibility(em, theta, z, V)
    np.testing.assert_allclose(I2, ref_I2, rtol=1e-10)
    np.testing.assert_allclose(var, em.predict(em.X_train, theta).var,
                               rtol=1e-8, atol=1e-12)
    ll = multivariate.log_likelihood(em, theta, z, V)
    np.testing.assert_allclose(ll, -0.5 * (ref_I2 + ref_ld + V.shape[0] * math.log(2 * math.pi)),
                               rtol=1e-10, atol=1e-9)     # log scale: absolute near zero


def test_convergence_bound_is_the_largest_generalised_eigenvalue():
    em, z, V_m, rng = random_problem(4, 2)
    V = np.diag(np.full(V_m.size, 0.002)) + multivariate.discrepancy_cov(em.X_train, V_m, 0.3)
    theta = rng.uniform(size=(6, 2))
    _, cov = em.at(em.X_train).moments(theta)
    N = em.X_train.shape[0]
    exact = []
    for c in cov:
        S = np.zeros_like(V)
        for o in range(2):
            S[o * N:(o + 1) * N, o * N:(o + 1) * N] = c[o]
        exact.append(scipy.linalg.eigh(S, V, eigvals_only=True)[-1])
    assert multivariate.cov_ratio(em, theta[:1], V) == pytest.approx(exact[0], rel=1e-8)
    assert multivariate.cov_ratio(em, theta, V) >= max(exact) * (1 - 1e-10)


def test_series_and_its_cholesky_fallback_agree_with_the_reference(monkeypatch):
    em, z, V_m, rng = random_problem(3, 1, N=15)
    V = np.diag(np.full(V_m.size, 0.001)) + multivariate.discrepancy_cov(em.X_train, V_m, 0.3)
    theta = rng.uniform(size=(30, 2))
    ref, _ = naive_scores(em, theta, z, V)
    np.testing.assert_allclose(multivariate.multivariate_implausibility(em, theta, z, V)[0],
                               ref, rtol=1e-10)
    monkeypatch.setattr(multivariate, "SERIES_MAX_EPS", 0.0)     # every row by Cholesky
    np.testing.assert_allclose(multivariate.multivariate_implausibility(em, theta, z, V)[0],
                               ref, rtol=1e-10)


def test_discrepancy_covariance_by_hand():
    rng = np.random.default_rng(0)
    X = rng.uniform(size=(6, 2))
    V_m = rng.uniform(0.5, 2.0, size=(6, 3))
    R = np.array([[1.0, 0.5, 0.2], [0.5, 1.0, -0.3], [0.2, -0.3, 1.0]])
    np.testing.assert_allclose(multivariate.discrepancy_cov(X, V_m, 0.4, R),
                               naive_v_m(X, V_m, 0.4, R), rtol=1e-12, atol=1e-14)
    # ℓ = 0 and no output correlation: today's independent V_m
    np.testing.assert_array_equal(multivariate.discrepancy_cov(X, V_m, 0.0),
                                  np.diag(V_m.T.ravel()))
    # different ℓ per output, independent outputs: one Matérn block per output
    V = multivariate.discrepancy_cov(X, V_m, [0.2, 0.0, 0.7])
    for o, ell in enumerate([0.2, 0.0, 0.7]):
        block = V[o * 6:(o + 1) * 6, o * 6:(o + 1) * 6]
        ref = np.diag(V_m[:, o]) if ell == 0 else naive_v_m(X, V_m[:, [o]], ell, np.eye(1))
        np.testing.assert_allclose(block, ref, rtol=1e-12, atol=1e-14)
    assert not np.any(V[:6, 6:])


def test_chi2_cutoff_is_the_quantile():
    assert multivariate.chi2_cutoff(64) == pytest.approx(scipy.stats.chi2.ppf(0.995, 64))
    assert multivariate.chi2_cutoff(13, 0.99) == pytest.approx(27.688, abs=1e-3)


def line_with_smooth_discrepancy(seed):
    """η(x, θ) = θ₁ + θ₂ x on 15 inputs; data = truth + a δ drawn from the V_m GP + noise."""
    X = np.linspace(0.0, 1.0, 15)[:, None]
    truth = np.array([0.5, 1.0])
    V = 0.02 * multivariate.discrepancy_cov(X, np.ones((15, 1)), 0.3)
    rng = np.random.default_rng(seed)
    delta = np.linalg.cholesky(V + 1e-12 * np.eye(15)) @ rng.normal(size=15)
    z = (truth[0] + truth[1] * X + delta[:, None] + 0.03 * rng.normal(size=(15, 1)))

    def simulate(X, theta):
        return (theta[:, :1] + theta[:, 1:] * X[:, 0])[..., None]

    return simulate, X, z, truth


@pytest.mark.parametrize("seed", range(4))
def test_truth_stays_in_nroy_with_a_correlated_discrepancy(seed):
    simulate, X, z, truth = line_with_smooth_discrepancy(seed)
    hm = history_match(simulate, X, z, [[-1.0, 2.0], [0.0, 2.0]], V_m=0.02, V_o=0.03**2,
                       V_m_length=0.3, rule="multivariate", n_candidates=5000,
                       max_waves=3, seed=seed)
    assert hm.status != "ruled_out" and hm.contains(truth)[0]
    assert hm.problem.cutoff == pytest.approx(scipy.stats.chi2.ppf(0.995, 15))
    last = hm.waves[-1]
    np.testing.assert_array_equal(last.candidate_implausibility <= hm.problem.cutoff,
                                  np.isin(last.candidates, last.nroy).all(axis=1))


@pytest.mark.parametrize("rule", ["max", "2nd max", "3rd max"])
def test_old_rules_ignore_the_correlation(rule):
    """The max rules use V_m's diagonal only: NROY, implausibility and θ_MAP are unchanged."""
    case = cases.load("beam-1d")
    a, b = (history_match_case(case, n_candidates=4000, max_waves=2, rule=rule, **corr)
            for corr in (dict(V_m_length=0.0), dict(V_m_length=0.4)))
    for wa, wb in zip(a.waves, b.waves, strict=True):
        np.testing.assert_array_equal(wa.nroy, wb.nroy)
        np.testing.assert_array_equal(wa.candidate_implausibility, wb.candidate_implausibility)
    np.testing.assert_array_equal(a.theta_map, b.theta_map)
    assert a.problem.cutoff == b.problem.cutoff == 3.0


def test_multivariate_likelihood_drives_theta_map_and_samples():
    simulate, X, z, truth = line_with_smooth_discrepancy(0)
    hm = history_match(simulate, X, z, [[-1.0, 2.0], [0.0, 2.0]], V_m=0.02, V_o=0.03**2,
                       V_m_length=0.3, rule="multivariate", n_candidates=5000, max_waves=2)
    pool = hm.nroy_samples(500, seed=1)
    em, V = hm.waves[-1].emulator, hm.problem.V
    np.testing.assert_allclose(hm.log_likelihood(pool),
                               multivariate.log_likelihood(em, pool, hm.problem.z, V))
    assert hm.log_likelihood(hm.theta_map[None])[0] >= hm.log_likelihood(pool).max() - 1e-9


@pytest.mark.parametrize("kwargs, match", [
    (dict(V_m_length=-0.1), "V_m_length must be one length ≥ 0"),
    (dict(V_m_length=[0.1, 0.2]), "V_m_length must be one length ≥ 0 or one per output"),
    (dict(chi2_probability=1.0), "chi2_probability must be in"),
    (dict(rule="sum"), "rule"),
    (dict(V_m_corr=[[1.0, 0.5]]), r"V_m_corr must be a symmetric \(1, 1\)"),
    (dict(V_m_length=1e4, V_o=1e-300), "V_o \\+ V_m over the observed inputs is not positive"),
])
def test_bad_settings(kwargs, match):
    simulate, X, z, _ = line_with_smooth_discrepancy(0)
    options = dict(V_m=0.02, V_o=0.001, rule="multivariate") | kwargs
    with pytest.raises(ValueError, match=match):
        setup(simulate, X, z, [[-1.0, 2.0], [0.0, 2.0]], **options)


def test_a_correlation_matrix_that_is_not_positive_definite_is_refused():
    X = np.linspace(0, 1, 5)[:, None]
    z = np.zeros((5, 3))

    def simulate(X, theta):
        return np.zeros((len(theta), len(X), 3))

    R = np.full((3, 3), -0.6) + 1.6 * np.eye(3)          # ρ = −0.6 < −1/(n_out − 1)
    with pytest.raises(ValueError, match="V_m_corr is not positive definite: its smallest "
                       "eigenvalue is -0.2.*Lower the off-diagonal"):
        setup(simulate, X, z, [[0.0, 1.0]], V_m=1.0, V_o=0.1, V_m_corr=R)
