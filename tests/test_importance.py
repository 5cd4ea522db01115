"""Importance-sampling tools: PSIS against arviz and known Pareto tails, ESS, Student-t,
stratified resampling and the adaptive proposal."""

import warnings

import numpy as np
import pytest
from scipy import stats

from mdcore._exceptions import K_HAT_THRESHOLD
from mdcore._importance import (
    StudentT,
    generalized_pareto_fit,
    psis,
    resample,
)


def pareto_log_weights(k, n, rng, sigma=1.0):
    """Log of generalised-Pareto draws with shape k (the tail PSIS estimates)."""
    u = rng.uniform(size=n)
    return np.log(sigma * np.expm1(-k * np.log1p(-u)) / k)


@pytest.mark.parametrize("kind", ["normal", "pareto-0.4", "pareto-0.9", "with-zeros"])
def test_psis_matches_arviz(kind):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        az = pytest.importorskip("arviz")
    rng = np.random.default_rng(3)
    if kind == "normal":
        lw = 2.0 * rng.standard_normal(3000)
    elif kind.startswith("pareto"):
        lw = pareto_log_weights(float(kind.split("-")[1]), 5000, rng)
    else:
        lw = rng.standard_normal(2000)
        lw[::7] = -np.inf
    ours = psis(lw)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ref_lw, ref_k = az.psislw(lw.copy())
    np.testing.assert_allclose(ours.k_hat, float(ref_k), rtol=1e-10)
    finite = np.isfinite(ref_lw)
    np.testing.assert_array_equal(np.isfinite(ours.log_weights), finite)
    np.testing.assert_allclose(ours.log_weights[finite], np.asarray(ref_lw)[finite],
                               rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("k", [0.2, 0.5, 0.9])
def test_k_hat_recovers_a_known_pareto_tail(k):
    rng = np.random.default_rng(11)
    estimates = [psis(pareto_log_weights(k, 20_000, rng)).k_hat for _ in range(5)]
    # The tail has M = 3 √S ≈ 424 samples; the estimator's sd is about (1 + k)/√M ≈ 0.07.
    assert abs(np.mean(estimates) - k) < 0.08, estimates
    assert (np.mean(estimates) > K_HAT_THRESHOLD) == (k > K_HAT_THRESHOLD)


def effective_sample_size(log_weights):
    """Kish's ``(Σ w)² / Σ w²`` from log weights (the oracle the tests compare with)."""
    lw = np.ravel(log_weights)
    return float(np.exp(2 * np.logaddexp.reduce(lw) - np.logaddexp.reduce(2 * lw)))


def test_psis_edge_cases_and_bad_input():
    out = psis(np.zeros(3))                    # tail too short to fit: k̂ = inf, weights kept
    assert out.k_hat == np.inf
    np.testing.assert_allclose(np.exp(out.log_weights), 1 / 3)
    with pytest.raises(ValueError, match="NaN or \\+inf"):
        psis([0.0, np.nan, 1.0])
    with pytest.raises(ValueError, match="every weight is zero"):
        psis([-np.inf, -np.inf])
    with pytest.raises(ValueError, match="log_weights must have 1 dimension"):
        psis(np.zeros((3, 3)))
    with pytest.raises(ValueError, match="at least 5 positive values sorted"):
        generalized_pareto_fit([1.0, 2.0, 3.0])


def test_generalized_pareto_fit_against_scipy_mle():
    rng = np.random.default_rng(5)
    x = np.sort(stats.genpareto(c=0.3, scale=2.0).rvs(20_000, random_state=rng))
    k, sigma = generalized_pareto_fit(x)
    c_mle, _, scale_mle = stats.genpareto.fit(x, floc=0.0)
    assert abs(k - c_mle) < 0.03 and abs(sigma / scale_mle - 1) < 0.03
    assert abs(k - 0.3) < 0.05 and abs(sigma - 2.0) < 0.1


def test_student_t_density_sampling_and_fit():
    mean = np.array([1.0, -2.0, 0.5])
    A = np.array([[1.0, 0.3, 0.0], [0.3, 2.0, -0.4], [0.0, -0.4, 0.5]])
    t = StudentT(mean, A, df=5.0)
    x = np.random.default_rng(0).standard_normal((6, 3))
    np.testing.assert_allclose(t.logpdf(x), stats.multivariate_t(mean, A, df=5).logpdf(x),
                               rtol=1e-12)
    draws = t.sample(200_000, seed=1)
    np.testing.assert_array_equal(draws[:5], t.sample(200_000, seed=1)[:5])
    cov = A * 5.0 / 3.0
    se = np.sqrt(np.diag(cov) / 200_000)
    assert np.all(np.abs(draws.mean(axis=0) - mean) < 5 * se)
    np.testing.assert_allclose(np.cov(draws, rowvar=False), cov, atol=0.06)
    # The fit matches the moments of FIT_POINTS stratified draws by weight: exactly those of
    # the samples when the weights are equal (each is drawn FIT_POINTS / n times), to
    # within the draws' sampling error otherwise.
    rng = np.random.default_rng(2)
    s = rng.standard_normal((50, 3))
    f = StudentT.fit(s, np.zeros(50), df=4.0, inflate=2.0, seed=0)
    np.testing.assert_allclose(f.mean, s.mean(axis=0), rtol=1e-12, atol=1e-14)
    cov = np.cov(s, rowvar=False, bias=True)
    np.testing.assert_allclose(f.scale * 4.0 / 2.0, 2.0 * cov, rtol=1e-9, atol=1e-12)
    floored = StudentT.fit(s, np.zeros(50), df=4.0, inflate=2.0, floor=[0.1, 0.2, 0.3], seed=0)
    np.testing.assert_allclose(floored.scale * 4.0 / 2.0,
                               2.0 * (cov + np.diag([0.01, 0.04, 0.09])), rtol=1e-9)
    x = rng.standard_normal((100_000, 2))
    lw = stats.multivariate_normal([1.0, -0.5], [[0.5, 0.2], [0.2, 0.3]]).logpdf(x) - \
        stats.multivariate_normal(np.zeros(2), np.eye(2)).logpdf(x)
    g = StudentT.fit(x, lw, df=5.0, seed=1)
    np.testing.assert_allclose(g.mean, [1.0, -0.5], atol=5 * np.sqrt(0.5 / 4000))
    np.testing.assert_allclose(g.scale * 5.0 / 3.0, [[0.5, 0.2], [0.2, 0.3]], atol=0.05)


def test_student_t_bad_input():
    with pytest.raises(ValueError, match="log_weights must have a finite value"):
        StudentT.fit(np.zeros((3, 1)), np.full(3, -np.inf))
    with pytest.raises(ValueError, match="n must be an integer ≥ 1"):
        StudentT(np.zeros(1), np.eye(1), 5.0).sample(0)


def test_stratified_resampling():
    """Every index is drawn within 2 of n·w times (a stratum holds one draw); the mean of f
    over the draws is unbiased with at most the multinomial variance Var_w(f) / n."""
    rng = np.random.default_rng(6)
    w = rng.dirichlet(np.full(500, 0.3))
    f = rng.standard_normal(500) + 3.0 * (np.arange(500) % 2)
    n = 200
    estimates = []
    for seed in range(2000):
        idx, counts = resample(np.log(w), n, seed=seed)
        assert counts.sum() == n and np.all(np.diff(idx) > 0)
        full = np.zeros(500)
        full[idx] = counts
        assert np.all(np.abs(full - n * w) < 2)
        estimates.append(counts @ f[idx] / n)
    var_w = w @ (f - w @ f) ** 2
    assert abs(np.mean(estimates) - w @ f) < 4 * np.sqrt(var_w / n / 2000)
    assert np.var(estimates) < 1.2 * var_w / n
    zero = resample([0.0, -np.inf, 0.0], 10, seed=0)
    assert 1 not in zero[0] and zero[1].sum() == 10
    with pytest.raises(ValueError, match="log_weights must have a finite value"):
        resample([-np.inf, -np.inf], 3)


def test_stage_sizes():
    from mdcore._importance import stage_sizes
    assert stage_sizes(1000) == [100] + [180] * 5 and sum(stage_sizes(37)) == 37
    assert stage_sizes(1000, 4) == [100, 300, 300, 300]
    assert stage_sizes(3) == [1, 1, 1] and stage_sizes(2, 1) == [2]
    with pytest.raises(ValueError, match="n must be an integer ≥ 1"):
        stage_sizes(0)


def test_adaptive_sampling_against_a_conjugate_gaussian():
    """Groups j with prior x ~ N(0, v0 I) and likelihood N(y_j | x, r I): the posterior of
    each group and the groups' marginal likelihoods N(y_j | 0, (v0 + r) I) are closed form."""
    from mdcore._importance import adaptive_importance_sampling, stage_sizes
    from mdcore._priors import GaussianPrior
    P, v0, r = 3, 4.0, 0.05
    y = np.array([[0.5, -1.0, 0.2], [0.6, -0.9, 0.1], [0.4, -1.2, 0.3]])
    prior = GaussianPrior(np.zeros(P), np.full(P, v0))

    def loglik(x):                                      # x (S, m, P)
        return stats.multivariate_normal(np.zeros(P), r * np.eye(P)).logpdf(
            x - y[:, None, :]).reshape(x.shape[:2])

    out = adaptive_importance_sampling(loglik, prior, 3, 4000, seed=0)
    assert out.samples.shape == (3, 4000, P) and out.stage_sizes == tuple(stage_sizes(4000))
    np.testing.assert_allclose(np.exp(out.log_weights).sum(), 1.0, rtol=1e-12)
    w = np.exp(out.log_weights)
    evidence = stats.multivariate_normal(np.zeros(P), (v0 + r) * np.eye(P)).logpdf(y)
    want = np.exp(evidence - np.log(np.sum(np.exp(evidence))))
    np.testing.assert_allclose(w.sum(axis=1), want, rtol=0.08)    # ~3 sd at ESS ≈ 1000
    post_var = 1.0 / (1.0 / v0 + 1.0 / r)
    for j in range(3):
        wj = w[j] / w[j].sum()
        mean = wj @ out.samples[j]
        np.testing.assert_allclose(mean, post_var * y[j] / r, atol=5 * np.sqrt(post_var / 500))
        var = wj @ (out.samples[j] - mean) ** 2
        np.testing.assert_allclose(var, post_var, rtol=0.15)
    # The prior alone wastes almost every draw on this narrow posterior.
    ess_adaptive = effective_sample_size(out.log_weights)
    plain = adaptive_importance_sampling(loglik, prior, 3, 4000, seed=0, n_stages=1)
    assert ess_adaptive > 1000 and ess_adaptive > 20 * effective_sample_size(plain.log_weights)
    assert psis(out.log_weights.ravel()).k_hat < 0.7
    # The deterministic-mixture weights, recomputed per draw from the returned proposals
    # with SciPy's densities: log L + log p − log Σ_t (n_t / n) q_t, normalised jointly.
    x = out.samples.reshape(-1, P)
    sizes = np.array(out.stage_sizes)
    dens = [stats.multivariate_normal(np.zeros(P), v0 * np.eye(P)).logpdf(x)]
    dens += [stats.multivariate_t(q.mean, q.scale, df=q.df).logpdf(x) for q in out.proposals]
    mixture = np.logaddexp.reduce(np.log(sizes / sizes.sum())[:, None] + np.array(dens), axis=0)
    naive = out.log_likelihood.ravel() + dens[0] - mixture
    np.testing.assert_allclose(out.log_weights.ravel(), naive - np.logaddexp.reduce(naive),
                               rtol=1e-10, atol=1e-10)
    same = adaptive_importance_sampling(loglik, prior, 3, 4000, seed=0)
    np.testing.assert_array_equal(same.log_weights, out.log_weights)
    with pytest.raises(ValueError, match="every adaptive importance weight is zero"):
        adaptive_importance_sampling(lambda x: np.full(x.shape[:2], -np.inf), prior, 2, 8,
                                     seed=0, n_stages=1)


def test_laplace_stage_finds_the_posterior_mode_and_curvature():
    """With the likelihood's gradient, stage 2 is a Student-t at the mode and inverse
    Hessian of the best stage-1 draw's group: for a Gaussian prior and likelihood both are
    closed form, ``v y / r`` and ``v I`` with ``v = 1 / (1/v0 + 1/r)``."""
    from mdcore._importance import DF, FLOOR, INFLATE, adaptive_importance_sampling
    from mdcore._priors import GaussianPrior
    P, v0, r = 4, 9.0, 1e-4                      # a posterior 300× narrower than the prior
    y = np.array([[0.5, -1.0, 0.2, 0.1], [0.502, -0.998, 0.201, 0.099]])
    prior = GaussianPrior(np.zeros(P), np.full(P, v0))

    def loglik(x):
        return -0.5 * np.sum((x - y[:, None, :]) ** 2, axis=-1) / r

    def grad(x, j):
        return -0.5 * np.sum((x - y[j]) ** 2) / r, -(x - y[j]) / r

    out = adaptive_importance_sampling(loglik, prior, 2, 200, seed=1, log_likelihood_grad=grad)
    v = 1.0 / (1.0 / v0 + 1.0 / r)
    laplace = out.proposals[0]
    assert any(np.allclose(laplace.mean, v * y[j] / r, atol=1e-6) for j in range(2))
    np.testing.assert_allclose(laplace.scale * DF / (DF - 2.0) / INFLATE,
                               v * np.eye(P) + np.diag(np.full(P, (FLOOR * 3.0) ** 2)),
                               rtol=1e-4)
    w = np.exp(out.log_weights)
    for j in range(2):
        wj = w[j] / w[j].sum()
        np.testing.assert_allclose(wj @ out.samples[j], v * y[j] / r, atol=4 * np.sqrt(v / 100))
    # Without the Laplace stage, 20 prior draws per group find nothing this narrow.
    blind = adaptive_importance_sampling(loglik, prior, 2, 200, seed=1)
    assert effective_sample_size(out.log_weights) > 100
    assert effective_sample_size(blind.log_weights) < 2
