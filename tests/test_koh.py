"""Kennedy–O'Hagan baseline: emulator covariance, sampler, closed-form posterior, beam-1d."""

import numpy as np
import pytest
import scipy.stats

from mdcore import _cases as cases
from mdcore._emulator import fit_emulator
from mdcore._kernels import matern32
from mdcore._koh import KOHOptions, infer_koh
from mdcore._mcmc import adaptive_metropolis
from mdcore._pipeline import Method, Settings, run_method, scores
from mdcore._priors import GaussianPrior, ThetaPrior

# ---------------------------------------------------------------------------------------
# A naive dense reference for the emulator's joint posterior (no Kronecker algebra)

def _m32(A, B, ell):
    d = (A[:, None, :] - B[None, :, :]) / ell
    return matern32(np.sum(d * d, axis=-1))


def naive_emulator_joint(em, o, theta, XA, XB):
    """Dense-GP mean at XA and covariance between XA and XB for one θ and output o."""
    g = em.gps[o]
    p, d_x = em.theta_train.shape[1], em.X_train.shape[1]
    lp = g.log_params
    sf2, sn2 = np.exp(2 * lp[0]), np.exp(2 * lp[-1])
    lt, lx = np.exp(lp[1:1 + p]), np.exp(lp[1 + p:-1])
    t_lo, t_span = em.bounds[:, 0], em.bounds[:, 1] - em.bounds[:, 0]
    xu = em.unit_x
    Ttr = (em.theta_train - t_lo) / t_span
    Xtr = xu(em.X_train)
    R, N = Ttr.shape[0], Xtr.shape[0]
    T_rows, X_rows = np.repeat(Ttr, N, axis=0), np.tile(Xtr, (R, 1))   # run-major
    K = sf2 * _m32(T_rows, T_rows, lt) * _m32(X_rows, X_rows, lx) + sn2 * np.eye(R * N)
    F = np.column_stack([np.ones(R * N), X_rows, T_rows])
    res = em.y_train[..., o].ravel() - F @ g.beta
    tu = ((np.asarray(theta) - t_lo) / t_span)[None]

    def cross(X):
        return sf2 * _m32(tu, T_rows, lt) * _m32(xu(X), X_rows, lx)          # (n, R N)

    kA, kB = cross(XA), cross(XB)
    mean = g.beta[0] + xu(XA) @ g.beta[1:1 + d_x] + tu @ g.beta[1 + d_x:] + kA @ np.linalg.solve(K, res)
    cov = sf2 * _m32(xu(XA), xu(XB), lx) - kA @ np.linalg.solve(K, kB.T)
    return mean, cov


@pytest.fixture(scope="module")
def beam():
    case = cases.load("beam-1d", seed=0)
    design = case.initial_design[::2]                                     # 13 runs keeps it small
    y = case.simulate(case.X_train, design)
    em = fit_emulator(case.X_train, design, y, case.theta_bounds, seed=0)
    return case, em


def test_emulator_at_matches_dense_gp(beam):
    case, em = beam
    XA = case.X_train[[0, 3, 3, 7, 12]]                    # includes a repeated row
    XB = np.array([[0.15], [0.5], [0.77]])
    at, at_b = em.at(XA), em.at(XB)
    thetas = np.array([[37.0, 68.0], [12.0, 83.0]])
    mean, cov = at.moments(thetas)
    cross, var_b = at.cross_cov(thetas, at_b)
    for i, th in enumerate(thetas):
        m_ref, c_ref = naive_emulator_joint(em, 0, th, XA, XA)
        _, cb_ref = naive_emulator_joint(em, 0, th, XB, XA)
        _, bb_ref = naive_emulator_joint(em, 0, th, XB, XB)
        scale = np.max(np.abs(c_ref)) + 1e-12
        np.testing.assert_allclose(mean[i, 0], m_ref, rtol=0, atol=1e-8)
        np.testing.assert_allclose(cov[i, 0], c_ref, rtol=0, atol=1e-7 * scale)
        np.testing.assert_allclose(cross[i, 0], cb_ref, rtol=0, atol=1e-7 * scale)
        np.testing.assert_allclose(var_b[i, 0], np.maximum(np.diag(bb_ref), 0), atol=1e-7 * scale)
    pred = em.predict(XA, thetas)                           # the diagonal is predict()'s var
    np.testing.assert_allclose(np.diagonal(cov, axis1=-2, axis2=-1)[:, 0],
                               pred.var[..., 0], atol=1e-12)


def test_emulator_at_bad_input(beam):
    case, em = beam
    with pytest.raises(ValueError, match=r"X must have shape \(N, 1\)"):
        em.at(np.zeros((3, 2)))
    with pytest.raises(ValueError, match="NaN"):
        em.at(case.X_train).moments([[np.nan, 70.0]])
    with pytest.raises(ValueError, match=r"theta must have shape \(M, 2\)"):
        em.at(case.X_train).moments([[1.0, 2.0, 3.0]])
    other = fit_emulator(case.X_train, case.initial_design[:6],
                         case.simulate(case.X_train, case.initial_design[:6]),
                         case.theta_bounds, seed=0)
    with pytest.raises(ValueError, match="same emulator"):
        em.at(case.X_train).cross_cov([[30.0, 70.0]], other.at(case.X_train))


# ---------------------------------------------------------------------------------------
# Linear-Gaussian toy: simulator linear in θ, Gaussian prior, fixed φ -> Gaussian posterior

TOY_X = np.linspace(0.0, 1.0, 9)[:, None]
TOY_G = np.column_stack([1.0 + TOY_X[:, 0], np.sin(3 * TOY_X[:, 0])])   # η = G θ
TOY_PHI = np.log([0.3, 0.4, 0.1])                                       # σ_f, ℓ_x, σ_n
TOY_PRIOR = ThetaPrior(mean=np.array([1.0, -0.5]), var=np.array([0.5, 2.0]))


def _toy_simulate(X, theta):
    G = np.column_stack([1.0 + X[:, 0], np.sin(3 * X[:, 0])])
    return (theta @ G.T)[..., None]


def _toy_posterior(z):
    sf, ell, sn = np.exp(TOY_PHI)
    C = sf**2 * _m32(TOY_X, TOY_X, np.array([ell])) + sn**2 * np.eye(len(TOY_X))
    P0 = np.diag(1 / TOY_PRIOR.var)
    prec = P0 + TOY_G.T @ np.linalg.solve(C, TOY_G)
    cov = np.linalg.inv(prec)
    return cov @ (P0 @ TOY_PRIOR.mean + TOY_G.T @ np.linalg.solve(C, z)), cov


@pytest.fixture(scope="module")
def toy():
    rng = np.random.default_rng(11)
    z = TOY_G @ np.array([1.3, 0.2]) + 0.2 * np.sin(6 * TOY_X[:, 0]) \
        + 0.1 * rng.standard_normal(len(TOY_X))
    bounds = TOY_PRIOR.mean[:, None] + 15 * np.sqrt(TOY_PRIOR.var)[:, None] * [-1, 1]
    model = infer_koh(_toy_simulate, TOY_X, z, theta_prior=TOY_PRIOR, bounds=bounds, seed=5,
        options=KOHOptions(log_phi=TOY_PHI, n_iter=80_000, burn_in=20_000))
    return model, _toy_posterior(z)


def test_toy_posterior_mean_and_covariance_match_closed_form(toy):
    model, (mu, cov) = toy
    s = model.theta
    ess = model.ess
    assert np.all(ess > 3000), ess
    sd = np.sqrt(np.diag(cov))
    # Monte Carlo standard errors from the ESS; 4 standard errors each.
    assert np.all(np.abs(s.mean(axis=0) - mu) < 4 * sd / np.sqrt(ess)), (s.mean(axis=0), mu)
    emp = np.cov(s.T)
    assert np.all(np.abs(np.diag(emp) - sd**2) < 4 * sd**2 * np.sqrt(2 / ess))
    rho, rho_hat = cov[0, 1] / (sd[0] * sd[1]), emp[0, 1] / np.sqrt(emp[0, 0] * emp[1, 1])
    assert abs(rho_hat - rho) < 4 * (1 - rho**2) / np.sqrt(ess.min())
    assert 0.15 < model.acceptance_rate < 0.6


def test_toy_marginals_pass_ks_at_level_0_001(toy):
    model, (mu, cov) = toy
    step = int(np.ceil(2 * model.iat.max()))                # thin to nearly independent draws
    thinned = model.theta[::step]
    for j in range(2):
        p = scipy.stats.kstest(thinned[:, j], "norm", args=(mu[j], np.sqrt(cov[j, j]))).pvalue
        assert p > 0.001, (j, p, thinned.shape)


def test_adaptive_proposal_converges_to_scaled_posterior_covariance(toy):
    model, (_, cov) = toy
    target = 2.4**2 / 2 * cov
    err = np.linalg.norm(model.chain.proposal_cov - target) / np.linalg.norm(target)
    assert err < 0.1, (model.chain.proposal_cov, target)


def test_reproducible_under_seed():
    kw = dict(theta_prior=TOY_PRIOR, bounds=[[-5.0, 7.0], [-8.0, 8.0]],
              options=KOHOptions(log_phi=TOY_PHI, n_iter=600, burn_in=100))
    z = TOY_G @ np.array([1.0, 0.0])
    a = infer_koh(_toy_simulate, TOY_X, z, seed=4, **kw)
    b = infer_koh(_toy_simulate, TOY_X, z, seed=4, **kw)
    c = infer_koh(_toy_simulate, TOY_X, z, seed=5, **kw)
    np.testing.assert_array_equal(a.theta, b.theta)
    assert not np.array_equal(a.theta, c.theta)


# ---------------------------------------------------------------------------------------
# Predictions against dense conditioning

def test_predictions_match_dense_conditioning(beam):
    case, em = beam
    model = infer_koh(em, case.X_train, case.z_train, theta_prior=case.theta_prior,
                  bounds=case.theta_bounds, seed=1,
        options=KOHOptions(log_phi=[np.log(0.4), np.log(0.3), np.log(0.03)], n_iter=300, burn_in=100))
    Xs = np.array([[0.12], [0.41], [0.88]])
    pred = model.predict(Xs, n_samples=3)
    idx = np.unique(np.linspace(0, model.theta.shape[0] - 1, 3).round().astype(int))
    sf, ell, sn = 0.4, 0.3, 0.03
    X = case.X_train
    Kd = lambda A, B: sf**2 * _m32(A, B, np.array([ell]))       # noqa: E731
    parts = []
    for th in model.theta[idx]:
        m, cXX = naive_emulator_joint(em, 0, th, X, X)
        ms, cSX = naive_emulator_joint(em, 0, th, Xs, X)
        _, cSS = naive_emulator_joint(em, 0, th, Xs, Xs)
        C = cXX + Kd(X, X) + sn**2 * np.eye(len(X))
        r = case.z_train[:, 0] - m
        G = cSX + Kd(Xs, X)
        zm = ms + G @ np.linalg.solve(C, r)
        zv = np.diag(cSS) + sf**2 + sn**2 - np.einsum("ij,ji->i", G, np.linalg.solve(C, G.T))
        dm = Kd(Xs, X) @ np.linalg.solve(C, r)
        dv = sf**2 - np.einsum("ij,ji->i", Kd(Xs, X), np.linalg.solve(C, Kd(X, Xs)))
        parts.append((zm, zv, dm, dv))
    zm, zv, dm, dv = map(np.array, zip(*parts))
    np.testing.assert_allclose(pred.z_mean[:, 0], zm.mean(0), atol=1e-8)
    np.testing.assert_allclose(pred.z_var[:, 0], zv.mean(0) + zm.var(0), atol=1e-8)
    np.testing.assert_allclose(pred.delta_mean[:, 0], dm.mean(0), atol=1e-8)
    np.testing.assert_allclose(pred.delta_var[:, 0], dv.mean(0) + dm.var(0), atol=1e-8)


# ---------------------------------------------------------------------------------------
# beam-1d, reduced chain (the paper runs 150,000 iterations)

def test_beam1d_reduced_chain_contains_truth_and_predicts_z_like_the_decoupled_scenarios():
    from mdcore._history_matching import history_match_case
    case = cases.load("beam-1d", seed=0)
    hm = history_match_case(case, seed=0)
    pp = case.phi_prior
    hyper = GaussianPrior(np.r_[pp.mean[0], pp.mean[2:]], np.r_[pp.var[0], pp.var[2:]])
    model = infer_koh(hm.waves[-1].emulator, case.X_train, case.z_train,
                  theta_prior=case.theta_prior, bounds=case.theta_bounds, seed=0,
        options=KOHOptions(phi_prior=hyper, n_iter=20_000, burn_in=5_000))
    lo, hi = np.percentile(model.theta, [0.5, 99.5], axis=0)
    assert np.all((lo < case.theta_true) & (case.theta_true < hi)), (lo, hi)
    koh = scores(case, model.predict(case.X_test))
    s1 = run_method(case, hm, Method.S1, Settings(n_s=50, n_phi=1), seed=0).metrics
    assert koh.nmse_z[0] < 1.25 * s1.nmse_z[0], (koh.nmse_z, s1.nmse_z)
    # The paper's point (Table 1): joint inference learns a much worse δ.
    assert koh.nmse_delta[0] > 5 * s1.nmse_delta[0], (koh.nmse_delta, s1.nmse_delta)


# ---------------------------------------------------------------------------------------
# Bad input

@pytest.mark.parametrize("kwargs, match", [
    (dict(theta_prior=ThetaPrior([1.0, -0.5], [0.5, 2.0]), bounds=[[3.0, 1.0], [-5, 5]]),
     "lower < upper"),
    (dict(theta_prior=([1.0, -0.5], [0.0, 2.0])), "theta_prior var must be positive"),
    (dict(theta_prior=([1.0, -0.5], [-1.0, 2.0])), "theta_prior var must be positive"),
    (dict(theta_prior=([np.nan, -0.5], [1.0, 2.0])), "theta_prior mean contains 1 NaN"),
    (dict(theta_prior=([1.0], [1.0])), "p = 2 entries"),
    (dict(theta_prior="wide"), "ThetaPrior or a \\(mean, var\\) pair"),
    (dict(theta_prior=([40.0, 40.0], [1e-4, 1e-4])), "almost no mass inside bounds"),
    (dict(z=np.full(9, np.nan)), "z contains 9 NaN"),
    (dict(z=np.zeros(8)), "z must have shape"),
    (dict(log_phi=[0.0, 0.0]), "log_phi must have shape"),
    (dict(log_phi=[0.0, np.inf, 0.0]), "log_phi contains 1 NaN"),
    (dict(n_iter=100, burn_in=100), "burn_in must be smaller"),
    (dict(n_iter=0), "n_iter must be an integer"),
    (dict(phi_prior=GaussianPrior([0.0], [1.0])), "phi_prior must have 2 \\+ d_x = 3"),
    (dict(model=42), "model must be an Emulator or a callable"),
])
def test_infer_bad_input(kwargs, match):
    args = dict(model=_toy_simulate, X=TOY_X, z=TOY_G @ np.array([1.0, 0.0]),
                theta_prior=TOY_PRIOR, bounds=[[-5.0, 7.0], [-8.0, 8.0]], log_phi=TOY_PHI,
                n_iter=200, burn_in=50, seed=0)
    args.update(kwargs)
    keys = ("n_iter", "burn_in", "log_phi", "phi_prior")
    with pytest.raises(ValueError, match=match):
        options = KOHOptions(**{k: args.pop(k) for k in keys if k in args})
        infer_koh(args.pop("model"), args.pop("X"), args.pop("z"), options=options, **args)


def test_emulator_dimensions_must_match_data(beam):
    case, em = beam
    with pytest.raises(ValueError, match="the emulator has p = 2"):
        infer_koh(em, case.X_train, case.z_train, theta_prior=([70.0], [36.0]),
              bounds=[[50.0, 90.0]],
        options=KOHOptions(n_iter=10, burn_in=1))


def test_predict_bad_input_and_cancel(toy):
    model, _ = toy
    with pytest.raises(ValueError, match=r"X_star must have shape \(N\*, d_x\) with d_x = 1"):
        model.predict(np.zeros((4, 2)))
    with pytest.raises(ValueError, match="n_samples must be an integer"):
        model.predict(TOY_X, n_samples=0)

    class Stop(Exception):
        pass

    def cancel(fraction):
        raise Stop

    with pytest.raises(Stop):
        infer_koh(_toy_simulate, TOY_X, TOY_G @ np.array([1.0, 0.0]), theta_prior=TOY_PRIOR,
              bounds=[[-5.0, 7.0], [-8.0, 8.0]],
              progress=cancel,
        options=KOHOptions(log_phi=TOY_PHI, n_iter=5000, burn_in=10))


def test_evidence_gradient_matches_finite_differences(beam):
    import scipy.optimize

    from mdcore._koh import _EvidenceObjective
    from mdcore._linalg import JitterLog
    case, em = beam
    X = np.column_stack([case.X_train[:, 0]])
    draws = np.array([[30.0, 60.0], [38.0, 68.0], [45.0, 80.0]])
    mean, cov = em.at(X).moments(draws)
    prior = GaussianPrior([np.log(0.5), np.log(0.3), np.log(0.03)], [1.0, 1.0, 1.0])
    for hyper in (None, prior):
        obj = _EvidenceObjective(mean, cov, X, case.z_train.T, 1, hyper, JitterLog())
        x = np.log([0.4, 0.25, 0.05])
        f, g = obj(x)
        fd = scipy.optimize.approx_fprime(x, lambda v, obj=obj: obj(v)[0], 1e-6)
        np.testing.assert_allclose(g, fd, rtol=1e-4, atol=1e-6)
        # The value is minus the log of the prior-averaged likelihood (plus the hyperprior).
        ref = -np.log(np.mean([np.exp(scipy.stats.multivariate_normal.logpdf(
            case.z_train[:, 0], mean[m, 0], cov[m, 0] + 0.4**2 * _m32(X, X, np.array([0.25]))
            + 0.05**2 * np.eye(len(X)))) for m in range(3)]))
        if hyper is not None:
            ref -= float(hyper.logpdf(x))
        assert f == pytest.approx(ref, rel=1e-9)


def test_nan_wrong_shape_and_empty_inputs_of_the_other_public_functions(beam, toy):
    case, em = beam
    for bad, match in ((np.array([[np.nan]]), "NaN"), (np.empty((0, 1)), "empty"),
                       (np.zeros(3), "2 dimension")):
        with pytest.raises(ValueError, match=match):
            em.at(bad)
    model, _ = toy
    for bad, match in ((np.array([[np.nan]]), "NaN"), (np.empty((0, 1)), "empty")):
        with pytest.raises(ValueError, match=match):
            model.predict(bad)
    for x0, match in (([np.nan, 0.0], "x0 contains 1 NaN"), ([], "x0 is empty"),
                      ([[0.0]], "x0 must have 1 dimension")):
        with pytest.raises(ValueError, match=match):
            adaptive_metropolis(lambda x: 0.0, x0, n_iter=10, burn_in=1)
