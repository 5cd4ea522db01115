"""Batched GP core against a naive loop oracle, scikit-learn, and finite differences."""


import warnings

import naive_gp
import numpy as np
import pytest

from mdcore import _gp as gp
from mdcore import _linalg as linalg
from mdcore._exceptions import NumericalWarning


def random_problem(rng, N=9, d_y=5, d_x=2):
    X = rng.uniform(0, 1, size=(N, d_x))
    Y = rng.normal(size=(N, d_y))
    z = rng.normal(size=N)
    return Y, X, z


def random_log_params(rng, d_y, d_x, shape=()):
    lp = rng.normal(scale=0.4, size=shape + (2 + d_y + d_x,))
    lp[..., -1] = rng.uniform(-3, -1, size=shape)
    return lp


@pytest.mark.parametrize("d_y,d_x", [(1, 1), (5, 2), (0, 2), (3, 0)])
def test_nlml_matches_naive_loop(rng, d_y, d_x):
    N = 11
    X = rng.uniform(size=(N, d_x))
    z = rng.normal(size=N)
    Y = rng.normal(size=(3, N, d_y))
    lp = random_log_params(rng, d_y, d_x, (4, 1))          # broadcasts to (4, 3)
    got = gp.neg_log_marginal_likelihood(lp, Y, X, z)
    assert got.shape == (4, 3)
    for a in range(4):
        for b in range(3):
            want = naive_gp.nlml(lp[a, 0], Y[b], X, z)
            assert got[a, b] == pytest.approx(want, rel=1e-9)


def test_predict_matches_naive_loop(rng):
    Y, X, z = random_problem(rng, N=10, d_y=5, d_x=2)
    Yb = Y + 0.1 * rng.normal(size=(2, 1) + Y.shape)       # batch (2, 1)
    lp = random_log_params(rng, 5, 2, (3,))                 # -> batch (2, 3)
    Xs = rng.uniform(size=(6, 2))
    Ys = rng.normal(size=(6, 5))
    p = gp.predict(lp, Yb, X, z, Ys, Xs)
    assert p.mean.shape == (2, 3, 6) and p.var.shape == (2, 3, 6) and p.noise_var.shape == (2, 3)
    for a in range(2):
        for b in range(3):
            m, v, n = naive_gp.predict(lp[b], Yb[a, 0], X, z, Ys, Xs)
            np.testing.assert_allclose(p.mean[a, b], m, rtol=1e-9, atol=1e-12)
            np.testing.assert_allclose(p.var[a, b], v, rtol=1e-9, atol=1e-12)
            assert p.noise_var[a, b] == pytest.approx(n, rel=1e-12)


def test_chunking_gives_identical_results(rng, monkeypatch):
    Y, X, z = random_problem(rng, N=8, d_y=2, d_x=1)
    Yb = Y + rng.normal(size=(50,) + Y.shape)
    lp = random_log_params(rng, 2, 1, (50,))
    whole = gp.neg_log_marginal_likelihood(lp, Yb, X, z)
    whole_p = gp.predict(lp, Yb, X, z, Yb[:, :3], X[:3])
    monkeypatch.setattr(linalg, "CHUNK_BYTES", 1)               # one pair per chunk
    np.testing.assert_array_equal(gp.neg_log_marginal_likelihood(lp, Yb, X, z), whole)
    np.testing.assert_allclose(gp.predict(lp, Yb, X, z, Yb[:, :3], X[:3]).mean, whole_p.mean,
                               rtol=1e-12)


def test_large_batch_in_one_call(rng):
    """200,000 (hyperparameter, Y) pairs in one call, spot-checked against the oracle."""
    Y, X, z = random_problem(rng, N=13, d_y=1, d_x=1)
    Yb = Y + 0.05 * rng.normal(size=(1000, 1) + Y.shape)
    lp = random_log_params(rng, 1, 1, (200,))
    out = gp.neg_log_marginal_likelihood(lp, Yb, X, z)
    assert out.shape == (1000, 200) and np.all(np.isfinite(out))
    for a, b in [(0, 0), (999, 199), (517, 42)]:
        assert out[a, b] == pytest.approx(naive_gp.nlml(lp[b], Yb[a, 0], X, z), rel=1e-9)


def test_matches_scikit_learn_when_y_factor_is_one(rng):
    sklearn_gp = pytest.importorskip("sklearn.gaussian_process")
    kernels = pytest.importorskip("sklearn.gaussian_process.kernels")
    N, d_x = 15, 2
    X = rng.uniform(size=(N, d_x))
    z = np.sin(4 * X[:, 0]) + X[:, 1] ** 2 + 0.05 * rng.normal(size=N)
    Y = rng.normal(size=(N, 1))
    sf, lx, sn = 1.3, np.array([0.3, 0.7]), 0.08
    lp = np.r_[np.log(sf), np.log(1e12), np.log(lx), np.log(sn)]  # ℓ_y huge: y factor = 1
    k = (kernels.ConstantKernel(sf**2) * kernels.Matern(length_scale=lx, nu=1.5)
         + kernels.WhiteKernel(sn**2))
    ref = sklearn_gp.GaussianProcessRegressor(k, optimizer=None, alpha=0.0).fit(X, z)
    assert gp.neg_log_marginal_likelihood(lp, Y, X, z) == pytest.approx(
        -ref.log_marginal_likelihood(), rel=1e-9)
    Xs = rng.uniform(size=(7, d_x))
    Ys = rng.normal(size=(7, 1))
    p = gp.predict(lp, Y, X, z, Ys, Xs)
    m, s = ref.predict(Xs, return_std=True)                     # includes WhiteKernel noise
    np.testing.assert_allclose(p.mean, m, rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(p.var + p.noise_var, s**2, rtol=1e-8, atol=1e-12)


@pytest.mark.parametrize("d_y,d_x", [(1, 1), (5, 1), (2, 2)])
def test_gradient_matches_central_differences(rng, d_y, d_x):
    Y, X, z = random_problem(rng, N=12, d_y=d_y, d_x=d_x)
    lp = random_log_params(rng, d_y, d_x)
    _, g = gp.nlml_and_gradient(lp, Y, X, z)
    h = 1e-5
    fd = np.array([(naive_gp.nlml(lp + h * e, Y, X, z) - naive_gp.nlml(lp - h * e, Y, X, z))
                   / (2 * h) for e in np.eye(lp.size)])
    np.testing.assert_allclose(g, fd, rtol=1e-5, atol=1e-7)


def draw_from_gp(rng, log_params, Y, X):
    K = naive_gp.cov(log_params, Y, X, Y, X) + np.exp(2 * log_params[-1]) * np.eye(len(X))
    return np.linalg.cholesky(K) @ rng.normal(size=len(X))


def ill_conditioned(rng):
    """Batch of two: element 0 has ℓ_x = e^14 on 30 distinct points and σ_n = e^-40, which
    is singular to working precision; element 1 is well conditioned."""
    N = 30
    X = np.linspace(0, 1, N)[:, None]
    Y = np.zeros((N, 1))
    z = np.sin(3 * X[:, 0])
    lp = np.array([[0.0, 0.0, 14.0, -40.0], [0.0, 0.0, -1.0, -1.0]])
    return lp, Y, X, z


def test_jitter_ladder_is_per_matrix_and_warns_once(rng):
    lp, Y, X, z = ill_conditioned(rng)
    with pytest.warns(NumericalWarning, match="jitter") as rec:
        out = gp.neg_log_marginal_likelihood(lp, Y, X, z)
    assert len([w for w in rec if issubclass(w.category, NumericalWarning)]) == 1
    assert np.all(np.isfinite(out))
    assert out[1] == pytest.approx(naive_gp.nlml(lp[1], Y, X, z), rel=1e-9)
    with pytest.warns(NumericalWarning, match="jitter"):
        p = gp.predict(lp, Y, X, z, Y[:4], X[:4])
    assert np.all(np.isfinite(p.mean)) and np.all(p.var >= 0)


def test_a_jitter_log_takes_the_counts_instead_of_a_warning(rng):
    """A caller that reports jitter itself (an optimiser's trial points) passes a log: the
    same values, the counts in the log, no warning, and no warnings filter touched
    (``catch_warnings`` is process-wide, unsafe with fits on several threads)."""
    lp, Y, X, z = ill_conditioned(rng)
    with pytest.warns(NumericalWarning, match="jitter"):
        warned = gp.neg_log_marginal_likelihood(lp, Y, X, z)
    log = linalg.JitterLog()
    filters = list(warnings.filters)
    with warnings.catch_warnings():
        warnings.simplefilter("error")                      # any warning fails the test
        quiet = gp.neg_log_marginal_likelihood(lp, Y, X, z, jitter_log=log)
        assert log.jittered == 1 and log.failed == 0 and log.max_jitter > 0
        f, g = gp.nlml_and_gradient(lp[0], Y, X, z, jitter_log=log)
        assert log.jittered == 2 and np.isfinite(f) and np.all(np.isfinite(g))
    np.testing.assert_array_equal(quiet, warned)
    assert list(warnings.filters) == filters
    for fn, args in [(gp.neg_log_marginal_likelihood, (lp, Y, X, z)),
                     (gp.nlml_and_gradient, (lp[0], Y, X, z))]:
        with pytest.raises(ValueError, match="jitter_log must be a mdcore._linalg.JitterLog or "
                                             "None; received list"):
            fn(*args, jitter_log=[])


def test_matrix_that_never_factorises_gives_inf_not_nan(rng, monkeypatch):
    monkeypatch.setattr(linalg, "JITTER_LADDER", ())
    lp, Y, X, z = ill_conditioned(rng)
    with pytest.warns(NumericalWarning, match="stayed non-positive-definite"):
        out = gp.neg_log_marginal_likelihood(lp, Y, X, z)
    assert out[0] == np.inf and np.isfinite(out[1])
    with pytest.warns(NumericalWarning, match="predictions are NaN"):
        p = gp.predict(lp, Y, X, z, Y[:4], X[:4])
    assert np.all(np.isnan(p.mean[0])) and np.all(np.isfinite(p.mean[1]))


def test_bad_input_messages(rng):
    Y, X, z = random_problem(rng, N=5, d_y=1, d_x=1)
    lp = np.zeros(4)
    with pytest.raises(ValueError, match=r"log_params must have last dimension P = .*= 4"):
        gp.neg_log_marginal_likelihood(np.zeros(5), Y, X, z)
    with pytest.raises(ValueError, match=r"z must have shape \(N,\) = \(5,\)"):
        gp.neg_log_marginal_likelihood(lp, Y, X, z[:4])
    with pytest.raises(ValueError, match=r"Y must have shape \(\.\.\., N, d_y\) with N = 5"):
        gp.neg_log_marginal_likelihood(lp, Y[:3], X, z)
    with pytest.raises(ValueError, match="X has N = 0 rows"):
        gp.neg_log_marginal_likelihood(lp, Y[:0], X[:0], z[:0])
    with pytest.raises(ValueError, match="z contains 1 NaN"):
        gp.neg_log_marginal_likelihood(lp, Y, X, np.r_[z[:4], np.nan])
    with pytest.raises(ValueError, match="Y contains 1 NaN or infinite"):
        gp.neg_log_marginal_likelihood(lp, np.r_[Y[:4], [[np.inf]]], X, z)
    with pytest.raises(ValueError, match="do not broadcast"):
        gp.neg_log_marginal_likelihood(np.zeros((3, 4)), np.zeros((2, 5, 1)), X, z)
    with pytest.raises(ValueError, match="X must have 2 dimension"):
        gp.neg_log_marginal_likelihood(lp, Y, X[:, 0], z)
    with pytest.raises(ValueError, match=r"X_star must have shape \(N\*, d_x\)"):
        gp.predict(lp, Y, X, z, Y, np.zeros((5, 2)))

