"""Diagnostics (docs/diagnostics.md): the closed-form leave-one-run-out against a naive refit
loop, the warning of a too-confident emulator, the space views against per-point loops, and
the θ–δ split against the mixture's own moments and a naive loop."""

import dataclasses
import json
import warnings

import naive_gp
import numpy as np
import pytest
from scipy.linalg import cho_factor, cho_solve
from scipy.special import logsumexp
from scipy.stats import binom, norm

from mdcore import _cases as cases
from mdcore import _diagnostics as diagnostics
from mdcore import _discrepancy as discrepancy
from mdcore._diagnostics import (
    emulator_loo,
    loo_p_value,
    space_removed,
    space_views,
    theta_delta_split,
    validate_wave,
    validate_waves,
)
from mdcore._discrepancy import DiscrepancyOptions, infer_discrepancy
from mdcore._emulator import KronGP, fit_emulator
from mdcore._exceptions import EmulatorWarning
from mdcore._history_matching import (
    HistoryMatchResult,
    combine,
    history_match_case,
    next_wave,
    setup,
    setup_arguments,
)
from mdcore._kernels import matern32, scaled_sq_dist
from mdcore._priors import GaussianPrior

BOUNDS = np.array([[0.0, 2.0], [-1.0, 1.0]])
TRUTH = np.array([1.2, 0.3])


def two_outputs(X, theta):
    """Two smooth outputs of (x, θ), shape (n_theta, N, 2)."""
    t1, t2, x = theta[:, 0, None], theta[:, 1, None], X[None, :, 0]
    return np.stack([t1 * np.sin(2 * np.pi * x) + t2, t1 ** 2 * np.cos(3 * x) + t1 * t2], -1)


def unit_inputs(em):
    lo, span = em.bounds[:, 0], em.bounds[:, 1] - em.bounds[:, 0]
    return (em.theta_train - lo) / span, em.unit_x(em.X_train)


def naive_loo(em):
    """Drop each run in turn: least-squares mean on the rest, then the dense GP with the
    same hyperparameters, predicting the run's N values. Mean, latent var, latent cov."""
    Tu, Xu = unit_inputs(em)
    R, N, n_out = em.y_train.shape
    T_all, X_all = np.repeat(Tu, N, axis=0), np.tile(Xu, (R, 1))
    F = np.column_stack([np.ones(R * N), X_all, T_all])
    mean, var = np.empty((2, R, N, n_out))
    cov = np.empty((R, n_out, N, N))
    for o, g in enumerate(em.gps):
        y = em.y_train[..., o].ravel()
        sn2 = np.exp(2 * g.log_params[-1])
        K_all = naive_gp.cov(g.log_params, T_all, X_all, T_all, X_all)   # sliced per drop
        for r in range(R):
            out = np.arange(r * N, (r + 1) * N)
            keep = np.setdiff1d(np.arange(R * N), out)
            beta = np.linalg.lstsq(F[keep], y[keep], rcond=None)[0]
            K = K_all[np.ix_(keep, keep)]
            factor = cho_factor(K + sn2 * np.eye(keep.size), lower=True)
            Ks, Kss = K_all[np.ix_(out, keep)], K_all[np.ix_(out, out)]
            mean[r, :, o] = F[out] @ beta + Ks @ cho_solve(factor, y[keep] - F[keep] @ beta)
            cov[r, o] = Kss - Ks @ cho_solve(factor, Ks.T)
            var[r, :, o] = np.diag(cov[r, o])
    return mean, var, cov


def with_params(em, log_params):
    """``em`` with other hyperparameters per output (same linear mean): the Kronecker
    factors rebuilt from the kernel matrices."""
    Tu, Xu = unit_inputs(em)
    p = Tu.shape[1]
    F = np.concatenate([np.ones(Tu.shape[:1] + Xu.shape[:1] + (1,)),
                        np.broadcast_to(Xu, (len(Tu),) + Xu.shape),
                        np.broadcast_to(Tu[:, None], (len(Tu), len(Xu), p))], axis=2)
    gps = []
    for o, (g, lp) in enumerate(zip(em.gps, log_params)):
        lam, Qt = np.linalg.eigh(matern32(scaled_sq_dist(Tu, Tu, np.exp(lp[1:1 + p]))))
        mu, Qx = np.linalg.eigh(matern32(scaled_sq_dist(Xu, Xu, np.exp(lp[1 + p:-1]))))
        S = np.exp(2 * lp[0]) * np.maximum(lam, 0)[:, None] * np.maximum(mu, 0)[None] \
            + np.exp(2 * lp[-1])
        res = em.y_train[..., o] - F @ g.beta
        A = np.exp(2 * lp[0]) * Qt @ ((Qt.T @ res @ Qx) / S) @ Qx.T
        gps.append(KronGP(np.asarray(lp, dtype=float), g.beta, Qt, Qx, A, 1.0 / S))
    return dataclasses.replace(em, _gps=tuple(gps))


@pytest.mark.parametrize("seed, R, N", [(0, 6, 5), (1, 9, 4), (2, 4, 7)])
def test_closed_form_loo_matches_a_naive_refit_loop(seed, R, N):
    rng = np.random.default_rng(seed)
    X = np.sort(rng.uniform(0.0, 1.0, size=(N, 1)), axis=0)
    T = BOUNDS[:, 0] + (BOUNDS[:, 1] - BOUNDS[:, 0]) * rng.uniform(size=(R, 2))
    em = fit_emulator(X, T, two_outputs(X, T), BOUNDS, seed=seed)
    loo = emulator_loo(em)
    mean, var, cov = naive_loo(em)
    scale = np.abs(em.y_train).max()
    np.testing.assert_allclose(loo.mean, mean, rtol=1e-8, atol=1e-8 * scale)
    np.testing.assert_allclose(loo.var, var, rtol=1e-8, atol=1e-8 * scale ** 2)
    # the latent covariance over the inputs, Q_x diag(s) Q_xᵀ, and the errors it implies
    for o, g in enumerate(em.gps):
        got = np.einsum("ib,rb,jb->rij", g.Q_x, loo.s[:, o], g.Q_x)
        np.testing.assert_allclose(got, cov[:, o], rtol=1e-8, atol=1e-8 * scale ** 2)
    sd = np.sqrt(var + np.exp(2 * em.log_params[:, -1]))
    np.testing.assert_allclose(loo.error, (em.y_train - mean) / sd, rtol=1e-6, atol=1e-6)


def test_loo_needs_two_runs():
    X = np.linspace(0, 1, 4)[:, None]
    T = np.array([[1.0, 0.0]])
    em = fit_emulator(X, T, two_outputs(X, T), BOUNDS, seed=0)
    with pytest.raises(ValueError, match="at least 2 simulator runs; the emulator has 1"):
        emulator_loo(em)


def toy_problem(**kw):
    X = np.linspace(0.05, 0.95, 6)[:, None]
    rng = np.random.default_rng(0)
    z = two_outputs(X, TRUTH[None])[0] + 0.02 * rng.standard_normal((6, 2))
    options = dict(V_o=4e-4, V_m=4e-3, n_runs=10, n_candidates=20_000, max_waves=2,
                   convergence_ratio=1e-9, seed=3)
    return setup(two_outputs, X, z, BOUNDS, **setup_arguments({**options, **kw}))


def naive_implausibility(problem, mean, var, cov):
    """Each run's combined implausibility from the naive LOO (the rule of ``problem``)."""
    if problem.options.rule == "multivariate":
        out = []
        for r in range(mean.shape[0]):
            resid = (problem.z - mean[r]).T.ravel()                    # output-major
            total = problem.V.copy()
            N = problem.z.shape[0]
            for o in range(problem.z.shape[1]):
                total[o * N:(o + 1) * N, o * N:(o + 1) * N] += cov[r, o]
            out.append(resid @ np.linalg.solve(total, resid))
        return np.array(out)
    I = np.abs(problem.z - mean) / np.sqrt(problem.V_o + problem.V_m + var)
    return np.sort(I.reshape(len(I), -1), axis=1)[:, -{"max": 1, "2nd max": 2}[problem.options.rule]]


@pytest.mark.parametrize("rule", ["max", "2nd max", "multivariate"])
def test_validation_of_a_too_confident_emulator_warns_and_names_the_wave(rule):
    grid = np.stack(np.meshgrid(np.linspace(0.1, 1.9, 4), np.linspace(-0.9, 0.9, 4),
                                indexing="ij"), -1).reshape(-1, 2)
    problem = toy_problem(rule=rule, initial_design=np.vstack([grid, TRUTH]))
    wave = next_wave(problem)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        good = validate_wave(wave)                      # a fitted emulator: no warning
    assert good.advice is None and good.p_value > diagnostics.TOO_CONFIDENT_P
    assert good.share_beyond_3 < 0.01 and not good.wrongly_ruled_out.any()
    # deliberately too confident: σ_f and σ_n / 1000, lengthscales / 30 (so between runs
    # it predicts little more than its linear mean, with a tiny variance)
    shrink = np.array([[-np.log(1e3)] + [np.log(1 / 30)] * 3 + [-np.log(1e3)]])
    bad_em = with_params(wave.emulator, wave.emulator.log_params + shrink)
    bad = dataclasses.replace(wave, emulator=bad_em)
    with pytest.warns(EmulatorWarning, match=r"wave 1: .* beyond ±3 and the largest is .* too confident.*Add "
                      r"simulator runs"):
        v = validate_wave(bad)
    assert v.p_value < diagnostics.TOO_CONFIDENT_P and v.share_beyond_3 > 0.2
    # an underflowed bound is stated as the smallest one, as the app's table shows it
    assert f"p ≤ {max(v.p_value, diagnostics.SMALLEST_P):.1e})" in v.advice, v.advice
    assert "p ≤ 0.0e+00" not in v.advice, v.p_value
    # the wrongly-ruled-out runs, from the naive loop's moments and the simulator itself
    mean, var, cov = naive_loo(bad_em)
    I_loo = naive_implausibility(problem, mean, var, cov)
    I_sim = naive_implausibility(problem, bad_em.y_train, 0.0 * var, 0.0 * cov)
    np.testing.assert_allclose(v.loo_implausibility, I_loo, rtol=1e-6)
    np.testing.assert_allclose(v.simulator_implausibility, I_sim, rtol=1e-8)
    cut = problem.cutoff
    np.testing.assert_array_equal(v.wrongly_ruled_out, (I_loo > cut) & (I_sim <= cut))
    assert v.wrongly_ruled_out.any()
    assert f"{v.wrongly_ruled_out.sum()} of its 17 runs would be ruled out" in v.advice
    assert (f"(implausibility up to {I_loo[v.wrongly_ruled_out].max():.2f}, cut-off {cut:.3g})"
            in v.advice)
    summary = v.as_dict()
    assert summary["wave"] == 1 and summary["runs"] == 17
    assert summary["wrongly_ruled_out"] == int(v.wrongly_ruled_out.sum())


def test_a_calibrated_emulator_has_standard_normal_errors_and_rarely_warns():
    """GP draws with the emulator's own kernel: the errors are N(0, 1) (sd 1, 0.27 % beyond
    ±3), and the test of 1e-3 fires in none of 20 designs."""
    X = np.linspace(0, 1, 8)[:, None]
    rng = np.random.default_rng(7)
    T = BOUNDS[:, 0] + (BOUNDS[:, 1] - BOUNDS[:, 0]) * rng.uniform(size=(30, 2))
    em0 = fit_emulator(X, T, two_outputs(X, T)[..., :1], BOUNDS, seed=0)
    lp = np.array([0.0, np.log(0.4), np.log(0.4), np.log(0.3), np.log(1e-3)])
    Tu, Xu = unit_inputs(em0)
    K = np.kron(matern32(scaled_sq_dist(Tu, Tu, np.exp(lp[1:3]))),
                matern32(scaled_sq_dist(Xu, Xu, np.exp(lp[3:4])))) + 1e-6 * np.eye(240)
    L = np.linalg.cholesky(K)
    errors = []
    for _ in range(20):
        y = (L @ rng.standard_normal(240)).reshape(30, 8, 1)
        errors.append(emulator_loo(with_params(dataclasses.replace(em0, y_train=y), [lp])).error)
    assert max(loo_p_value(e) for e in errors) > 0.01
    assert min(loo_p_value(e) for e in errors) > diagnostics.TOO_CONFIDENT_P
    assert 0.95 < np.std(errors) < 1.05 and np.mean(np.abs(errors) > 3) < 0.006


def test_loo_p_value_counts_runs_not_correlated_errors():
    error = np.zeros((40, 13, 1))
    error[0, :6] = 3.5                          # one run off at 6 of its inputs
    assert loo_p_value(error) > 0.3             # 1 of 40 runs; q = 13 × 0.27 %
    error[:8, 0] = 3.5                          # 8 of 40 runs
    assert loo_p_value(error) < 1e-3
    np.testing.assert_allclose(loo_p_value(error),
                               2 * binom.sf(7, 40, 13 * diagnostics.P_BEYOND_3))
    # or one error no calibrated emulator makes: 520 × P(|e| > 6) = 1e-6
    error[:] = 0.0
    error[3, 4] = -6.0
    np.testing.assert_allclose(loo_p_value(error), 2 * 520 * 2 * norm.sf(6.0))


def toy_simulate(X, theta):
    """Two outputs, linear in θ: y1 = θ1 sin 3x + θ2, y2 = θ1 x."""
    theta = np.atleast_2d(theta)
    x = X[:, 0]
    return np.stack([theta[:, :1] * np.sin(3 * x) + theta[:, 1:2], theta[:, :1] * x], axis=-1)


def toy_model(scenario, S, n_phi=8, backend="numpy", seed=0):
    rng = np.random.default_rng(seed)
    X = np.linspace(0, 1, 7)[:, None]
    truth = np.array([1.0, 0.2])
    z = toy_simulate(X, truth)[0] + 0.3 * np.cos(4 * X) + 0.05 * rng.normal(size=(7, 2))
    theta = truth + 0.1 * rng.normal(size=(S, 2))
    prior = GaussianPrior(mean=[0.0, 0.0, 0.0, -0.5, -2.5], var=[0.3, 0.3, 0.3, 0.3, 0.3])
    options = DiscrepancyOptions(n_phi=n_phi, phi_prior=prior, prune=0.0, backend=backend,
                                 proposal="prior")        # the redrawn φ are the prior's
    return infer_discrepancy(toy_simulate, theta, X, z, scenario=scenario, theta_map=truth,
                             options=options, seed=seed)


def naive_split(model, X_star):
    """E[δ | θ_j], Var[δ | θ_j], between and within by plain loops with the naive GP."""
    n_out, S, K = model.log_weights.shape
    Ys = toy_simulate(X_star, model.theta)
    mean, var = np.zeros((2, S, len(X_star), n_out))
    between, within = np.zeros((2, len(X_star), n_out))
    for o in range(n_out):
        w_theta = np.exp(logsumexp(model.log_weights[o], axis=1))
        for j in range(S):
            moments = []
            for k in range(K):
                m, v, _ = naive_gp.predict(model.log_params[o, j, k], model.Y[j], model.X,
                                           model.z[:, o], Ys[j], X_star)
                w = np.exp(model.log_weights[o, j, k]) / w_theta[j]
                moments.append((w, m - Ys[j, :, o], v))
            mean[j, :, o] = sum(w * d for w, d, _ in moments)
            var[j, :, o] = sum(w * (v + (d - mean[j, :, o]) ** 2) for w, d, v in moments)
        total = sum(w_theta[j] * mean[j, :, o] for j in range(S))
        between[:, o] = sum(w_theta[j] * (mean[j, :, o] - total) ** 2 for j in range(S))
        within[:, o] = sum(w_theta[j] * var[j, :, o] for j in range(S))
    return mean, var, between, within


@pytest.mark.filterwarnings("ignore::mdcore.LowESSWarning")     # N_φ = 8 on purpose
@pytest.mark.parametrize("scenario, backend, redraw", [(2, "numpy", False), (3, "numpy", False),
                                                      (3, "numpy", True), (3, "numba", False)])
def test_theta_delta_split_matches_a_naive_loop_and_the_mixture(scenario, backend, redraw,
                                                                monkeypatch):
    if backend == "numba":
        pytest.importorskip("numba")
    if redraw:                              # φ draws too large to keep: redrawn per θ row
        monkeypatch.setattr(discrepancy, "KEEP_DRAWS_BYTES", 0)
    model = toy_model(scenario, S=5, backend=backend)
    assert (model.phi_draws is not None and model._log_params is None) == redraw
    X_star = np.linspace(0.05, 0.95, 6)[:, None]
    split = theta_delta_split(model, X_star)
    mean, var, between, within = naive_split(model, X_star)
    np.testing.assert_allclose(split.mean, mean, rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(split.var, var, rtol=1e-8, atol=1e-12)
    np.testing.assert_allclose(split.between, between, rtol=1e-8, atol=1e-14)
    np.testing.assert_allclose(split.within, within, rtol=1e-8, atol=1e-14)
    np.testing.assert_allclose(split.share, between.sum(0) / (between + within).sum(0),
                               rtol=1e-8)
    # the law of total variance: the two parts add up to the mixture's own Var[δ]
    pred = model.predict(X_star)
    np.testing.assert_allclose(split.between + split.within, pred.delta_var, rtol=1e-8)
    np.testing.assert_allclose(np.einsum("oj,jno->no", split.weight, split.mean),
                               pred.delta_mean, rtol=1e-8, atol=1e-12)
    # replicated prediction inputs are predicted once and give the same rows
    twice = theta_delta_split(model, np.vstack([X_star, X_star[:2]]))
    np.testing.assert_allclose(twice.between[-2:], split.between[:2], rtol=1e-12)


@pytest.mark.filterwarnings("ignore::mdcore.LowESSWarning")
def test_theta_delta_split_subsamples_theta_and_scenario_1_has_no_theta_share():
    model = toy_model(2, S=60)
    X_star = np.linspace(0.05, 0.95, 9)[:, None]
    exact = theta_delta_split(model, X_star)
    part = theta_delta_split(model, X_star, n_theta=20)       # systematic: every third θ
    assert len(exact.theta) == 60
    np.testing.assert_array_equal(part.theta, model.theta[1::3])
    np.testing.assert_allclose(part.weight, 1 / 20)
    np.testing.assert_array_equal(part.share, theta_delta_split(model, X_star,
                                                                n_theta=20).share)
    half = theta_delta_split(model, X_star, n_theta=30)
    assert np.all(np.abs(half.share - exact.share) < 0.1)
    # unequal θ weights (scenario 3): a θ with weight ≥ 1/n is always kept, and the kept
    # θ are reweighted per output by w_oj / w̄_j
    s3 = toy_model(3, S=30, n_phi=4)
    w = np.exp(logsumexp(s3.log_weights, axis=2))
    split = theta_delta_split(s3, X_star, n_theta=10)
    rows = [np.flatnonzero((s3.theta == t).all(1))[0] for t in split.theta]
    assert set(np.flatnonzero(w.mean(0) >= 0.1)) <= set(rows)
    counts = split.weight / (w[:, rows] / w.mean(0)[rows])      # ∝ picks of each θ
    counts = 10 * counts / counts.sum(axis=1, keepdims=True)
    np.testing.assert_allclose(counts, np.round(counts), atol=1e-9)
    np.testing.assert_allclose(counts[0], counts[1], atol=1e-9)
    one = theta_delta_split(toy_model(1, S=1), X_star)
    assert one.theta.shape == (1, 2) and np.all(one.share == 0.0)
    with pytest.raises(ValueError, match=r"X_star must have shape \(N\*, 1\); received"):
        theta_delta_split(model, np.zeros((3, 2)))
    with pytest.raises(ValueError, match="X_star contains 1 NaN"):
        theta_delta_split(model, np.array([[np.nan]]))
    with pytest.raises(ValueError, match="X_star is empty"):
        theta_delta_split(model, np.zeros((0, 1)))
    with pytest.raises(ValueError, match="model must be a DiscrepancyModel .*received str"):
        theta_delta_split("model", np.zeros((3, 1)))


def test_theta_delta_advice_says_when_delta_is_mostly_theta():
    split = diagnostics.ThetaDeltaSplit(*[None] * 6, share=np.array([0.3, 0.93]))
    (text,) = split.advice("Scenario 2", ["tip", "root"])
    assert text.startswith("Scenario 2, root: 93 % of δ's predictive variance") \
        and "not physics" in text


def test_space_removed_reads_the_share_of_each_range_left_empty():
    rng = np.random.default_rng(0)
    box = np.array([[0.0, 10.0], [-1.0, 1.0], [5.0, 6.0]])
    samples = np.column_stack([rng.uniform(2.0, 6.0, 50_000), rng.uniform(-1, 1, 50_000),
                               rng.uniform(5.0, 5.5, 50_000)])
    np.testing.assert_allclose(space_removed(samples, box), [0.6, 0.0, 0.5], atol=0.01)
    np.testing.assert_array_equal(space_removed(np.empty((0, 3)), box), 1.0)


def test_space_views_match_per_point_loops():
    problem = toy_problem(n_candidates=3000, max_waves=3)
    waves = (next_wave(problem),)
    while not waves[-1].done:
        waves += (next_wave(problem, waves),)
    hm = HistoryMatchResult(problem, waves)
    assert len(hm.waves) == 3
    views = space_views(hm, bins=6)
    theta, cut = hm.waves[0].candidates, problem.cutoff
    # per point: the first wave whose implausibility is above the cut-off, and the largest
    # implausibility up to it
    I_all = np.stack([w.combined_implausibility(theta) for w in hm.waves])    # (W, M)
    above = I_all > cut
    first = np.where(above.any(0), above.argmax(0) + 1, 0)
    np.testing.assert_array_equal(views.ruled_out_by, first)
    last = np.where(first > 0, first, len(hm.waves))
    expect = np.array([I_all[:last[m], m].max() for m in range(theta.shape[0])])
    np.testing.assert_allclose(views.implausibility, expect, rtol=1e-10)
    np.testing.assert_array_equal(views.hits, [np.sum(first == k) for k in (1, 2, 3)])
    # the lattice, bin by bin
    edges = views.edges
    assert views.pairs.tolist() == [[0, 1]] and views.min_implausibility.shape == (1, 6, 6)
    for i in range(6):
        for j in range(6):
            inside = ((theta[:, 0] >= edges[0, i]) & (theta[:, 0] < edges[0, i + 1])
                      & (theta[:, 1] >= edges[1, j]) & (theta[:, 1] < edges[1, j + 1]))
            if inside.any():
                assert views.min_implausibility[0, i, j] == pytest.approx(expect[inside].min(),
                                                                          rel=1e-9)
                assert views.optical_depth[0, i, j] == np.mean(first[inside] == 0)
            else:
                assert np.isnan(views.min_implausibility[0, i, j])
    np.testing.assert_allclose(views.optical_depth_1d[0],
                               [np.mean(first[(theta[:, 0] >= edges[0, i])
                                              & (theta[:, 0] < edges[0, i + 1])] == 0)
                                for i in range(6)])
    np.testing.assert_allclose(views.nroy_fraction, hm.nroy_fraction)
    np.testing.assert_allclose(views.space_removed[-1],
                               space_removed(hm.waves[-1].nroy, problem.bounds, bins=6))
    early = space_views(hm, bins=6, waves=1)
    np.testing.assert_array_equal(early.ruled_out_by, np.where(first == 1, 1, 0))
    # the share never ruled out estimates the final NROY fraction
    share = np.mean(first == 0)
    assert abs(share - hm.nroy_fraction[-1]) < 4 * np.sqrt(share * (1 - share) / 3000) + 0.01


@pytest.mark.parametrize("name", ["beam-1d", "shear-5"])
def test_validation_and_views_on_the_built_in_cases(name):
    hm = history_match_case(cases.load(name), n_candidates=5000 * cases.load(name).p,
                            seed=0)
    (v,) = validate_waves(hm, warn=False)
    assert v.loo.mean.shape == hm.waves[0].emulator.y_train.shape
    assert not v.wrongly_ruled_out.any() and v.share_beyond_3 < 0.02 and v.advice is None
    # only a little too confident: σ_f / 3, so every emulator variance / 9
    wave = hm.waves[0]
    shrink = np.zeros(wave.emulator.log_params.shape[1])
    shrink[0] = -np.log(3.0)
    bad = dataclasses.replace(wave, emulator=with_params(wave.emulator,
                                                         wave.emulator.log_params + shrink))
    with pytest.warns(EmulatorWarning, match="wave 1: .* too confident"):
        assert validate_wave(bad).p_value < diagnostics.TOO_CONFIDENT_P
    views = space_views(hm)
    p = cases.load(name).p
    assert views.min_implausibility.shape == (p * (p - 1) // 2, 20, 20)
    assert views.space_removed.shape == (1, p)


PLUME = '''
import numpy as np


def log_concentration(X, theta):
    """Ground-level ln concentration [ln(µg/m³)] at (x downwind, y crosswind) [m] of a
    Gaussian plume: source Q [g/s], wind u [m/s], stack height H [m], σ_y = a x^b,
    σ_z = c x^0.9 [m]."""
    theta = np.atleast_2d(theta)
    Q, u, H, a, b, c = (theta[:, k, None] for k in range(6))
    x, y = X[None, :, 0], X[None, :, 1]
    sy, sz = a * x ** b, c * x ** 0.9
    return (np.log(1e6 * Q / (np.pi * u * sy * sz)) - y ** 2 / (2 * sy ** 2)
            - H ** 2 / (2 * sz ** 2))[..., None]
'''

PLUME_BOUNDS = {"Q": (50.0, 150.0), "u": (2.0, 8.0), "H": (20.0, 80.0), "a": (0.1, 0.3),
                "b": (0.8, 0.95), "c": (0.05, 0.15)}


@pytest.fixture(scope="module")
def plume(tmp_path_factory):
    """An own case from files: six parameters, two inputs; the "real" plume loses
    1e-4 ln units a metre to deposition, which the simulator leaves out."""
    import sys
    folder = tmp_path_factory.mktemp("plume")
    (folder / "plume_sim.py").write_text(PLUME, encoding="utf-8")
    params = "".join(f"[[parameters]]\nname = \"{n}\"\nlower = {lo}\nupper = {hi}\n"
                     for n, (lo, hi) in PLUME_BOUNDS.items())
    (folder / "plume.toml").write_text(
        'name = "stack-plume"\n[data]\nfile = "plume.csv"\ninputs = ["x_m", "y_m"]\n'
        'outputs = ["ln_c"]\ntest_column = "test"\nnoise_var = [0.0025]\n[simulator]\n'
        'function = "plume_sim:log_concentration"\npath = "."\n' + params
        + "[history_matching]\nV_m = [0.1]\ninitial_design = 60\n", encoding="utf-8")
    sys.path.insert(0, str(folder))
    try:
        from plume_sim import log_concentration
    finally:
        sys.path.remove(str(folder))
    rng = np.random.default_rng(1)
    rows = ["x_m,y_m,ln_c,test"]
    for test, xs, ys in ((0, (500, 1000, 2000, 3000), (-150, 0, 150)),
                         (1, (750, 1500, 2500), (-75, 75))):
        X = np.array([(x, y) for x in xs for y in ys], dtype=float)
        z = (log_concentration(X, [100.0, 5.0, 50.0, 0.2, 0.88, 0.1])[0, :, 0]
             - 1e-4 * X[:, 0] + 0.05 * rng.standard_normal(len(X)))
        rows += [f"{x},{y},{v:.5f},{test}" for (x, y), v in zip(X, z)]
    (folder / "plume.csv").write_text("\n".join(rows) + "\n", encoding="utf-8")
    return folder / "plume.toml"


def test_an_own_case_with_six_parameters_and_two_inputs(plume, tmp_path, capsys):
    from mdcore._case_file import load_case_file
    from mdcore._cli import main

    case = load_case_file(plume)
    assert case.p == 6 and case.X_train.shape == (12, 2)
    hm = history_match_case(case, n_candidates=20_000, n_runs=30, max_waves=3, seed=0)
    assert len(hm.waves) == 3
    checks = validate_waves(hm, warn=False)
    # the closed form against the naive refit loop, on wave 1 (60 runs × 12 inputs)
    em = hm.waves[0].emulator
    mean, var, _ = naive_loo(em)
    scale = np.abs(em.y_train).max()
    np.testing.assert_allclose(checks[0].loo.mean, mean, rtol=1e-8, atol=1e-8 * scale)
    np.testing.assert_allclose(checks[0].loo.var, var, rtol=1e-8, atol=1e-8 * scale ** 2)
    I_loo = combine(np.abs(hm.problem.z - mean) / np.sqrt(hm.problem.V_o + hm.problem.V_m
                                                           + var), "max")
    np.testing.assert_allclose(checks[0].loo_implausibility, I_loo, rtol=1e-8)
    # the space views against per-point, per-bin loops (4 bins a parameter)
    views = space_views(hm, bins=4)
    theta, cut = hm.waves[0].candidates, hm.problem.cutoff
    first = np.zeros(len(theta), dtype=int)
    worst = np.zeros(len(theta))
    for w in hm.waves:                          # each wave scores what is still alive
        alive = first == 0
        I = w.combined_implausibility(theta[alive])
        worst[alive] = np.maximum(worst[alive], I)
        first[np.flatnonzero(alive)[I > cut]] = w.index
    np.testing.assert_array_equal(views.ruled_out_by, first)
    np.testing.assert_allclose(views.implausibility, worst, rtol=1e-10)
    np.testing.assert_array_equal(views.hits, [np.sum(first == k) for k in (1, 2, 3)])
    assert len(views.pairs) == 15 and views.min_implausibility.shape == (15, 4, 4)
    box = np.array(list(PLUME_BOUNDS.values()))
    which = np.minimum(((theta - box[:, 0]) / (box[:, 1] - box[:, 0]) * 4).astype(int), 3)
    for n, (k, l) in enumerate(views.pairs):
        for i in range(4):
            for j in range(4):
                inside = (which[:, k] == i) & (which[:, l] == j)
                assert views.min_implausibility[n, i, j] == worst[inside].min()
                assert views.optical_depth[n, i, j] == np.mean(first[inside] == 0)
    for k in range(6):
        for i in range(4):
            assert views.optical_depth_1d[k, i] == np.mean(first[which[:, k] == i] == 0)
    for k, w in enumerate(hm.waves):            # space removed from np.histogram's counts
        counts = np.histogram(w.nroy[:, 1], bins=4, range=box[1])[0]
        q = counts[counts > 0] / counts.sum()
        H = -np.sum(q * np.log(q)) + (q.size - 1) / (2 * counts.sum())
        assert views.space_removed[k, 1] == pytest.approx(1 - min(np.exp(H) / 4, 1), abs=1e-12)
    np.testing.assert_allclose(views.nroy_fraction, hm.nroy_fraction)
    # the command line: every wave's check and the θ–δ shares, in the text and the JSON
    out = tmp_path / "plume.json"
    assert main(["run", str(plume), "--methods", "1", "2", "--n-s", "20", "--max-waves", "2",
                 "--n-candidates", "20000", "--n-runs", "30", "--json", str(out)]) == 0
    doc = json.loads(out.read_text(encoding="utf-8"))
    hm_json = doc["history_matching"]
    assert [c["wave"] for c in hm_json["validation"]] == [1, 2]
    assert [c["runs"] for c in hm_json["validation"]] == [60, 90]
    assert len(hm_json["space_removed"]) == 2 and len(hm_json["space_removed"][0]) == 6
    td = doc["methods"]["2"]["theta_delta"]
    assert td["n_theta"] == 20 and 0 <= td["share"][0] <= 1
    text = capsys.readouterr().out
    assert "wrongly ruled out" in text and "share from θ" in text and "Q " in text


def test_validate_waves_refuses_what_is_not_a_history_match():
    with pytest.raises(ValueError, match="hm must be a HistoryMatchResult .*received str"):
        validate_waves("hm")
