"""Discrepancy scenarios 1–3: against a naive loop, brute-force mixture sampling, limits
between scenarios, pruning, and beam-1d at reduced sizes."""

import warnings

import naive_gp
import numpy as np
import pytest
from scipy.special import logsumexp

from mdcore import _cases as cases
from mdcore._discrepancy import DiscrepancyOptions, infer_discrepancy
from mdcore._exceptions import LowESSWarning
from mdcore._history_matching import history_match_case
from mdcore._metrics import coverage, nmse
from mdcore._priors import GaussianPrior


def toy_simulate(X, theta):
    """Two outputs, linear in θ: y1 = θ1 sin 3x + θ2, y2 = θ1 x."""
    theta = np.atleast_2d(theta)
    x = X[:, 0]
    y1 = theta[:, :1] * np.sin(3 * x) + theta[:, 1:2]
    y2 = theta[:, :1] * x
    return np.stack([y1, y2], axis=-1)


@pytest.fixture
def toy(rng):
    X = np.linspace(0, 1, 7)[:, None]
    truth = np.array([1.0, 0.2])
    z = toy_simulate(X, truth)[0] + 0.3 * np.cos(4 * X) + 0.05 * rng.normal(size=(7, 2))
    theta = truth + 0.1 * rng.normal(size=(4, 2))
    prior = GaussianPrior(mean=[0.0, 0.0, 0.0, -0.5, -2.5], var=[0.3, 0.3, 0.3, 0.3, 0.3])
    return X, z, theta, truth, prior


def naive_mixture(model, X_star, Ys):
    """Mixture moments (docs/method.md §6) by a plain loop over components with the naive GP."""
    S, K = model.log_weights.shape[1:]
    out = np.zeros((4, X_star.shape[0], model.n_out))
    for o in range(model.n_out):
        w = np.exp(model.log_weights[o])
        ez = np.zeros(X_star.shape[0]); ez2 = np.zeros_like(ez)
        ed = np.zeros_like(ez); ed2 = np.zeros_like(ez)
        for j in range(S):
            for k in range(K):
                m, v, sn2 = naive_gp.predict(model.log_params[o, j, k], model.Y[j], model.X,
                                             model.z[:, o], Ys[j], X_star)
                d = m - Ys[j][:, o]
                ez += w[j, k] * m; ez2 += w[j, k] * (v + sn2 + m * m)
                ed += w[j, k] * d; ed2 += w[j, k] * (v + d * d)
        out[:, :, o] = [ez, ez2 - ez**2, ed, ed2 - ed**2]
    return out


@pytest.mark.filterwarnings("ignore::mdcore.LowESSWarning")
def test_scenario3_matches_naive_loop(toy):
    X, z, theta, _, prior = toy
    model = infer_discrepancy(toy_simulate, theta, X, z, scenario=3, seed=1,
        options=DiscrepancyOptions(n_phi=5, phi_prior=prior))
    # weights: −NLML of every pair by the naive oracle, normalised jointly
    for o in range(2):
        lw = np.array([[-naive_gp.nlml(model.log_params[o, j, k], model.Y[j], X, z[:, o])
                        for k in range(5)] for j in range(4)])
        np.testing.assert_allclose(model.log_weights[o], lw - logsumexp(lw), atol=1e-9)
    Xs = np.linspace(-0.1, 1.1, 9)[:, None]
    pred = model.predict(Xs, prune=0)
    ref = naive_mixture(model, Xs, toy_simulate(Xs, theta))
    for got, want in zip(pred, ref):
        np.testing.assert_allclose(got, want, rtol=1e-8, atol=1e-10)
    assert model.log_params.shape == (2, 4, 5, 5) and model.weights.sum() == pytest.approx(2.0)


@pytest.mark.filterwarnings("ignore::mdcore.LowESSWarning")
@pytest.mark.parametrize("backend", ["numpy", "numba"])
def test_replicated_inputs_are_predicted_once_with_the_same_numbers(toy, backend):
    """Replicated training and test inputs (shear-5 repeats each mass ten times): predict
    computes each distinct test input once; every replicate gets the prediction the input
    gets on its own, in the caller's order."""
    if backend == "numba":
        pytest.importorskip("numba")
    X, z, theta, _, prior = toy
    rows = np.array([0, 1, 1, 2, 3, 3, 3, 4, 5, 6, 6])
    model = infer_discrepancy(toy_simulate, theta, X[rows], z[rows], scenario=3, seed=1,
        options=DiscrepancyOptions(n_phi=5, phi_prior=prior, backend=backend))
    Xs = np.array([[0.5], [0.1], [0.5], [0.9], [0.1], [0.5]])
    pred = model.predict(Xs, prune=0)
    for i, x in enumerate(Xs):
        alone = model.predict(x[None], prune=0)
        for got, want in zip(pred, alone):
            np.testing.assert_allclose(got[i], want[0], rtol=1e-12, atol=1e-15)
    ref = naive_mixture(model, Xs, toy_simulate(Xs, theta))
    for got, want in zip(pred, ref):
        np.testing.assert_allclose(got, want, rtol=1e-8, atol=1e-10)


@pytest.mark.filterwarnings("ignore::mdcore.LowESSWarning")
def test_mixture_moments_match_brute_force_sampling(toy):
    X, z, theta, _, prior = toy
    model = infer_discrepancy(toy_simulate, theta, X, z, scenario=3, seed=2,
        options=DiscrepancyOptions(n_phi=3, phi_prior=prior))
    Xs = np.array([[0.25], [0.8]])
    pred = model.predict(Xs, prune=0)
    Ys = toy_simulate(Xs, theta)
    rng = np.random.default_rng(0)
    n = 400_000
    for o in range(2):
        w = model.weights[o].ravel()
        comp = rng.choice(w.size, size=n, p=w / w.sum())
        # per-component Gaussian of z* and of δ* (naive GP), then sample the mixture
        m = np.empty((w.size, 2)); v = np.empty((w.size, 2)); sn2 = np.empty(w.size)
        ys = np.empty((w.size, 2))
        for c in range(w.size):
            j, k = divmod(c, 3)
            m[c], v[c], sn2[c] = naive_gp.predict(model.log_params[o, j, k], model.Y[j], X,
                                                  z[:, o], Ys[j], Xs)
            ys[c] = Ys[j][:, o]
        eps = rng.standard_normal((n, 2))
        zs = m[comp] + np.sqrt(v[comp] + sn2[comp, None]) * eps
        ds = m[comp] - ys[comp] + np.sqrt(v[comp]) * eps
        for sample, mean, var in ((zs, pred.z_mean[:, o], pred.z_var[:, o]),
                                  (ds, pred.delta_mean[:, o], pred.delta_var[:, o])):
            se_mean = np.sqrt(var / n)
            assert np.all(np.abs(sample.mean(0) - mean) < 5 * se_mean)
            # var of the sample variance ≈ (μ4 − σ⁴)/n; use the sample's own 4th moment
            c4 = np.mean((sample - sample.mean(0)) ** 4, axis=0)
            se_var = np.sqrt((c4 - sample.var(0) ** 2) / n)
            assert np.all(np.abs(sample.var(0) - var) < 5 * se_var)


def test_scenario2_with_map_samples_reproduces_scenario1(toy):
    X, z, _, truth, prior = toy
    s1 = infer_discrepancy(toy_simulate, None, X, z, scenario=1, theta_map=truth, seed=3,
        options=DiscrepancyOptions(phi_prior=prior))
    same = np.repeat(truth[None], 6, axis=0)
    s2 = infer_discrepancy(toy_simulate, same, X, z, scenario=2, theta_map=truth, seed=3,
        options=DiscrepancyOptions(phi_prior=prior))
    np.testing.assert_array_equal(s1.log_params_hat, s2.log_params_hat)   # same seed, same fit
    Xs = np.linspace(0, 1, 11)[:, None]
    for a, b in zip(s1.predict(Xs), s2.predict(Xs)):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-14)
    assert s2.ess == pytest.approx([6.0, 6.0]) and s1.ess == pytest.approx([1.0, 1.0])


@pytest.mark.filterwarnings("ignore::mdcore.LowESSWarning")
def test_scenario3_with_concentrated_prior_approaches_scenario2(toy):
    """With φ pinned at φ̂, scenario 3 is scenario 2 with θ re-weighted by p(z | y^(j), φ̂):
    equal to scenario 2 when the θ samples are equally likely (here: identical)."""
    X, z, theta, truth, prior = toy
    Xs = np.linspace(0, 1, 11)[:, None]
    for thetas in (np.repeat(theta[:1], 3, axis=0), theta):
        s2 = infer_discrepancy(toy_simulate, thetas, X, z, scenario=2, theta_map=truth,
                   seed=4,
        options=DiscrepancyOptions(phi_prior=prior))
        for o in range(2):
            tight = GaussianPrior(mean=s2.log_params_hat[o], var=np.full(5, 1e-14))
            s3 = infer_discrepancy(toy_simulate, thetas, X, z, scenario=3, seed=4,
        options=DiscrepancyOptions(n_phi=4, phi_prior=tight))
            lw = -np.array([naive_gp.nlml(s2.log_params_hat[o], y, X, z[:, o]) for y in s2.Y])
            np.testing.assert_allclose(s3.weights[o].sum(axis=1), np.exp(lw - logsumexp(lw)),
                                       rtol=1e-5)
            if thetas is not theta:                       # equally likely θ: scenario 2
                for a, b in zip(s3.predict(Xs), s2.predict(Xs)):
                    np.testing.assert_allclose(a[:, o], b[:, o], rtol=1e-5, atol=1e-9)


def test_pruning_matches_unpruned_and_reports_mass(toy):
    X, z, theta, _, _ = toy
    wide = GaussianPrior(mean=[0.0, 0.0, 0.0, -0.5, -2.5], var=[4.0, 4.0, 4.0, 4.0, 4.0])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = infer_discrepancy(toy_simulate, theta, X, z, scenario=3, seed=5,
        options=DiscrepancyOptions(n_phi=400, phi_prior=wide))
    assert np.all(model.skipped_mass > 0)                       # something was pruned
    assert np.all(model.skipped_mass <= 1e-12 * model.weights[0].size)
    assert np.all(model.n_components < model.weights[0].size)
    Xs = np.linspace(0, 1, 9)[:, None]
    for a, b in zip(model.predict(Xs), model.predict(Xs, prune=0)):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-8)


@pytest.mark.filterwarnings("ignore::mdcore.LowESSWarning")
def test_same_seed_same_numbers_and_progress(toy):
    X, z, theta, truth, prior = toy
    seen = []
    a = infer_discrepancy(toy_simulate, theta, X, z, scenario=3, seed=7,
              progress=seen.append,
        options=DiscrepancyOptions(n_phi=6, phi_prior=prior))
    b = infer_discrepancy(toy_simulate, theta, X, z, scenario=3, seed=7,
        options=DiscrepancyOptions(n_phi=6, phi_prior=prior))
    np.testing.assert_array_equal(a.log_weights, b.log_weights)
    assert seen == sorted(seen) and seen[-1] == 1.0
    seen.clear()
    np.testing.assert_array_equal(a.predict(X, progress=seen.append).z_mean, b.predict(X).z_mean)
    assert seen[-1] == 1.0

    class Stop(Exception):
        pass

    def cancel(fraction):
        raise Stop

    with pytest.raises(Stop):
        infer_discrepancy(toy_simulate, theta, X, z, scenario=3, progress=cancel,
        options=DiscrepancyOptions(n_phi=6, phi_prior=prior))


@pytest.mark.filterwarnings("ignore::mdcore.LowESSWarning")
@pytest.mark.parametrize("seed", [4, np.random.Generator(np.random.MT19937(4))])
def test_prior_draws_not_kept_are_drawn_again_bit_for_bit(toy, monkeypatch, seed):
    """Above KEEP_DRAWS_BYTES scenario 3 keeps the generator state per chunk instead of the
    (N_s, N_φ, P) draws; the weights, the prediction and log_params are the same."""
    from mdcore import _discrepancy as discrepancy
    X, z, theta, _, prior = toy
    theta = np.repeat(theta, 5, axis=0)                             # 20 θ rows
    monkeypatch.setattr(discrepancy, "WEIGHT_PAIRS", 21)            # 3 rows × 7 draws a chunk
    monkeypatch.setattr(discrepancy, "MIN_FUSED_BLOCK", 16)
    state = seed.bit_generator.state if isinstance(seed, np.random.Generator) else None

    def run():
        if state is not None:
            seed.bit_generator.state = state
        return infer_discrepancy(toy_simulate, theta, X, z, scenario=3, seed=seed,
        options=DiscrepancyOptions(n_phi=7, phi_prior=prior))

    kept = run()
    monkeypatch.setattr(discrepancy, "KEEP_DRAWS_BYTES", 0)
    lazy = run()
    assert kept._log_params is not None and lazy._log_params is None
    assert len(lazy.phi_draws.states) == 7                          # ceil(20 / 3) chunks
    np.testing.assert_array_equal(lazy.log_weights, kept.log_weights)
    for a, b in zip(lazy.predict(X, prune=0.0), kept.predict(X, prune=0.0)):
        np.testing.assert_array_equal(a, b)
    assert lazy._log_params is None                                 # predict drew blocks only
    np.testing.assert_array_equal(lazy.log_params, kept.log_params)
    np.testing.assert_array_equal(lazy.phi_draws.between(5, 11), kept.log_params[0, 5:11])


def test_low_ess_warns_with_a_suggestion(toy):
    X, z, theta, _, _ = toy
    far = GaussianPrior(mean=[3.0, 3.0, 3.0, 3.0, -6.0], var=[9.0] * 5)
    with pytest.warns(LowESSWarning, match=r"raise N_φ \(now 20\) or N_s \(now "):
        infer_discrepancy(toy_simulate, theta, X, z, scenario=3, seed=0,
        options=DiscrepancyOptions(n_phi=20, phi_prior=far))


@pytest.mark.parametrize("kwargs, match", [
    (dict(scenario=4), "not a valid scenario"),
    (dict(scenario="two"), "not a valid scenario"),
    (dict(scenario=3, n_phi=0), "n_phi must be an integer ≥ 1"),
    (dict(scenario=2), "needs theta_map"),
    (dict(scenario=3, theta_samples=np.empty((0, 2))), "theta_samples is empty"),
    (dict(scenario=3, theta_samples=np.array([[np.nan, 1.0]])), "theta_samples contains 1 NaN"),
    (dict(scenario=3, theta_samples=np.ones(2)), "theta_samples must have 2 dimension"),
    (dict(scenario=3, z=np.ones((5, 2))), "z must have shape"),
    (dict(scenario=3, phi_prior=GaussianPrior([0.0], [1.0])), "phi_prior must be a GaussianPrior"),
    (dict(scenario=3, prune=2.0), "prune must be in"),
    (dict(scenario=3, prune="tiny"), "prune must be in"),
    (dict(scenario=3, prune=np.nan), "prune must be in"),
    (dict(scenario=3, X=np.ones((7, 1, 1))), "X must have 2 dimension"),
    (dict(scenario=3, z=np.full((7, 2), np.nan)), "z contains 14 NaN"),
    (dict(scenario=1, theta_map=[np.nan, 1.0]), "theta_map contains 1 NaN"),
    (dict(scenario=2, theta_map=[1.0, 0.2], log_params_hat=np.ones((2, 3))),
     r"log_params_hat must have shape \(n_out, P\) = \(2, 5\)"),
    (dict(scenario=2, theta_map=[1.0, 0.2, 3.0]), "p = 3 like theta_map"),
])
@pytest.mark.filterwarnings("ignore::mdcore.LowESSWarning")
def test_bad_input(toy, kwargs, match):
    """Each bad argument is refused by name: the options when they are made, the data
    when infer_discrepancy sees them."""
    X, z, theta, _, prior = toy
    args = dict(theta_samples=theta, X=X, z=z, n_phi=2)
    args.update(kwargs)
    keys = ("n_phi", "phi_prior", "prune", "log_params_hat")
    with pytest.raises(ValueError, match=match):
        options = DiscrepancyOptions(**{k: args.pop(k) for k in keys if k in args})
        infer_discrepancy(toy_simulate, args.pop("theta_samples"), args.pop("X"), args.pop("z"),
                          options=options, **args)


def test_predict_bad_input(toy):
    X, z, theta, truth, prior = toy
    model = infer_discrepancy(toy_simulate, theta, X, z, scenario=2, theta_map=truth, seed=0)
    with pytest.raises(ValueError, match=r"X_star must have shape \(N\*, d_x\) with d_x = 1"):
        model.predict(np.ones((3, 2)))
    with pytest.raises(ValueError, match="X_star contains 1 NaN"):
        model.predict(np.array([[np.nan]]))


@pytest.fixture(scope="module")
def beam1d():
    case = cases.load("beam-1d")
    return case, history_match_case(case, seed=0)


@pytest.mark.parametrize("scenario", [1, 2, 3])
def test_beam1d_reduced_sizes(beam1d, scenario):
    case, hm = beam1d
    theta = hm.posterior_samples(200, seed=0)
    model = infer_discrepancy(case.simulate, theta, case.X_train, case.z_train, scenario=scenario,
                  theta_map=hm.theta_map, seed=0,
        options=DiscrepancyOptions(n_phi=50, phi_prior=case.phi_prior))
    pred = model.predict(case.X_test)
    delta = case.true_delta(case.X_test)
    assert pred.z_mean.shape == pred.delta_var.shape == (200, 1)
    assert nmse(case.z_test, pred.z_mean)[0] < 3.0
    if scenario in (2, 3):
        assert nmse(delta, pred.delta_mean)[0] < 10.0
        assert coverage(delta, pred.delta_mean, pred.delta_var, k=3)[0] >= 0.9


@pytest.mark.filterwarnings("ignore::mdcore.LowESSWarning")
def test_adaptive_proposal_agrees_with_a_long_prior_run_and_keeps_more_samples(rng):
    """Same budget, same target (Eq. 15): the adaptive proposal's mixture is close to a
    40,000-draw prior run, with far more effective samples than 800 prior draws."""
    X = np.linspace(0, 1, 7)[:, None]
    z = toy_simulate(X, np.array([1.0, 0.2]))[0] + 0.3 * np.cos(4 * X) \
        + 0.05 * rng.normal(size=(7, 2))
    theta = np.array([1.0, 0.2]) + 0.1 * rng.normal(size=(3, 2))
    wide = GaussianPrior(mean=[0.0, 0.0, 0.0, -0.5, -2.5], var=[2.0] * 5)
    Xs = np.linspace(0, 1, 5)[:, None]
    ref_model = infer_discrepancy(toy_simulate, theta, X, z, scenario=3,
                      seed=1,
        options=DiscrepancyOptions(n_phi=40_000, phi_prior=wide))
    ref = ref_model.predict(Xs)
    ada = infer_discrepancy(toy_simulate, theta, X, z, scenario=3, seed=2,
        options=DiscrepancyOptions(n_phi=800, phi_prior=wide, proposal="adaptive"))
    plain = infer_discrepancy(toy_simulate, theta, X, z, scenario=3, seed=2,
        options=DiscrepancyOptions(n_phi=800, phi_prior=wide))
    assert ada.proposal == "adaptive" and plain.proposal == "prior"
    assert ada.log_params.shape == (2, 3, 800, 5)
    np.testing.assert_allclose(logsumexp(ada.log_weights.reshape(2, -1), axis=1), 0.0,
                               atol=1e-12)
    p = ada.predict(Xs)
    sd = np.sqrt(ref.delta_var)
    assert np.max(np.abs(p.delta_mean - ref.delta_mean) / sd) < 0.2
    np.testing.assert_allclose(np.sqrt(p.delta_var), sd, rtol=0.1)
    # θ marginal weights agree with the long run's (the evidence of each θ).
    np.testing.assert_allclose(np.exp(logsumexp(ada.log_weights, axis=2)),
                               np.exp(logsumexp(ref_model.log_weights, axis=2)), atol=0.05)
    assert np.all(ada.ess > 5 * plain.ess) and np.all(ada.k_hat < 0.7)
    same = infer_discrepancy(toy_simulate, theta, X, z, scenario=3, seed=2,
        options=DiscrepancyOptions(n_phi=800, phi_prior=wide, proposal="adaptive"))
    np.testing.assert_array_equal(same.log_weights, ada.log_weights)
    with pytest.raises(ValueError, match="'amis' is not a valid proposal"):
        infer_discrepancy(toy_simulate, theta, X, z, scenario=3,
        options=DiscrepancyOptions(n_phi=8, phi_prior=wide, proposal="amis"))
