"""Kernel maths: the Matérn derivative against finite differences, and property-based checks
of the GP core's invariants (hypothesis): symmetric PSD covariances, non-negative predictive
variance, invariance to the order of the training points."""


import naive_gp
import numpy as np
import pytest

from mdcore import _gp as gp
from mdcore._kernels import kernel, matern32, matern32_and_dlog_ell, train_cov

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402
from hypothesis.extra.numpy import arrays  # noqa: E402


def test_matern32_closed_form_and_derivative():
    assert matern32(0.0) == 1.0
    r = np.array([0.5, 1.0, 2.0])
    np.testing.assert_allclose(matern32(r**2), (1 + np.sqrt(3) * r) * np.exp(-np.sqrt(3) * r))
    rng = np.random.default_rng(0)
    A = rng.uniform(size=(6, 3))
    ell = np.array([0.3, 0.7, 1.5])
    m, dm = matern32_and_dlog_ell(A, ell)
    assert m.shape == (6, 6) and dm.shape == (3, 6, 6)
    h = 1e-6
    for d in range(3):
        e = np.zeros(3)
        e[d] = h
        up = matern32_and_dlog_ell(A, ell * np.exp(e))[0]
        down = matern32_and_dlog_ell(A, ell * np.exp(-e))[0]
        np.testing.assert_allclose(dm[d], (up - down) / (2 * h), rtol=1e-6, atol=1e-9)
    m0, d0 = matern32_and_dlog_ell(A[:, :0], np.empty(0))
    assert np.all(m0 == 1.0) and d0.shape == (0, 6, 6)


finite = st.floats(-2.0, 2.0, allow_nan=False, allow_infinity=False)


@st.composite
def problems(draw):
    N = draw(st.integers(2, 8))
    d_y, d_x = draw(st.integers(0, 3)), draw(st.integers(1, 2))
    X = draw(arrays(np.float64, (N, d_x), elements=finite, unique=True))
    Y = draw(arrays(np.float64, (N, d_y), elements=finite))
    z = draw(arrays(np.float64, (N,), elements=finite))
    lp = draw(arrays(np.float64, (2 + d_y + d_x,), elements=st.floats(-1.5, 1.5)))
    lp[-1] = draw(st.floats(-4.0, -0.5))
    return lp, Y, X, z


@settings(max_examples=40, deadline=None)
@given(problems())
def test_covariance_is_symmetric_positive_semidefinite(problem):
    lp, Y, X, z = problem
    K = kernel(lp, Y, X, Y, X)
    np.testing.assert_allclose(K, K.T, rtol=0, atol=1e-12)
    np.testing.assert_allclose(K, naive_gp.cov(lp, Y, X, Y, X), rtol=1e-10, atol=1e-12)
    assert np.linalg.eigvalsh(K).min() >= -1e-9 * np.exp(2 * lp[0]) * len(X)


@settings(max_examples=40, deadline=None)
@given(problems(), st.randoms(use_true_random=False))
def test_prediction_variance_is_non_negative_and_order_free(problem, random):
    lp, Y, X, z = problem
    perm = np.array(random.sample(range(len(X)), len(X)))
    p = gp.predict(lp, Y, X, z, Y, X)
    q = gp.predict(lp, Y[perm], X[perm], z[perm], Y, X)
    assert np.all(p.var >= 0) and np.all(np.isfinite(p.mean))
    scale = 1.0 + np.max(np.abs(p.mean))
    np.testing.assert_allclose(q.mean, p.mean, rtol=1e-7, atol=1e-7 * scale)
    np.testing.assert_allclose(q.var, p.var, rtol=1e-6, atol=1e-9 * np.exp(2 * lp[0]))
    a = gp.neg_log_marginal_likelihood(lp, Y, X, z)
    b = gp.neg_log_marginal_likelihood(lp, Y[perm], X[perm], z[perm])
    np.testing.assert_allclose(b, a, rtol=1e-8, atol=1e-8)


@settings(max_examples=40, deadline=None)
@given(problems(), st.randoms(use_true_random=False))
def test_training_covariance_and_predictions_at_new_inputs(problem, random):
    """The chunk kernel the NLML and the predictions factorise: train_cov's lower triangle is
    K_ff + σ_n² I, symmetric positive definite with every eigenvalue ≥ σ_n²; at inputs that
    are not training points the latent variance lies in [0, σ_f²] and does not depend on the
    order of the training points."""
    lp, Y, X, z = problem
    N = len(X)
    sf2, sn2 = np.exp(2 * lp[0]), np.exp(2 * lp[-1])
    lower = train_cov(lp[None], Y[None], X)[0]
    assert np.all(np.triu(lower, 1) == 0)                  # only the lower triangle is filled
    K = np.tril(lower) + np.tril(lower, -1).T
    np.testing.assert_allclose(K, kernel(lp, Y, X, Y, X) + sn2 * np.eye(N), rtol=1e-10,
                               atol=1e-12)
    assert np.linalg.eigvalsh(K).min() >= sn2 - 1e-9 * sf2 * N
    rng = np.random.default_rng(random.getrandbits(32))
    X_star = rng.uniform(-3.0, 3.0, size=(5, X.shape[1]))
    Y_star = rng.uniform(-3.0, 3.0, size=(5, Y.shape[1]))
    perm = np.array(random.sample(range(N), N))
    p = gp.predict(lp, Y, X, z, Y_star, X_star)
    q = gp.predict(lp, Y[perm], X[perm], z[perm], Y_star, X_star)
    assert np.all(p.var >= 0) and np.all(p.var <= sf2 * (1 + 1e-9))
    scale = 1.0 + np.max(np.abs(p.mean))
    np.testing.assert_allclose(q.mean, p.mean, rtol=1e-7, atol=1e-7 * scale)
    np.testing.assert_allclose(q.var, p.var, rtol=1e-6, atol=1e-9 * sf2)


def assert_one_matches_naive(K, theta, Y, X, rng):
    """The strict lower triangle of one random batch element of the bordered ``K`` equals
    the naive covariance (tests/naive_gp.py)."""
    N = X.shape[0]
    j = int(rng.integers(K.shape[0]))
    naive = naive_gp.cov(theta[j], Y[j], X, Y[j], X)
    np.testing.assert_allclose(np.tril(K[j, :N, :N], -1), np.tril(naive, -1), rtol=1e-10,
                               atol=1e-13)


@settings(max_examples=60, deadline=None)
@given(st.integers(1, 50), st.integers(2, 40), st.integers(1, 6), st.integers(0, 5),
       st.integers(1, 2), st.integers(0, 2**32 - 1))
def test_a_shared_y_and_replicated_inputs_give_the_naive_covariance(b, N, n_distinct, d_y,
                                                                    d_x, seed):
    """A Y shared by the batch (a broadcast view: a fit's particles) with replicated
    inputs (shear-5's repeats): the covariance is the naive one."""
    rng = np.random.default_rng(seed)
    rows = rng.integers(0, min(n_distinct, N), size=N)
    X = rng.normal(size=(n_distinct, d_x))[rows]
    Y = np.broadcast_to(rng.normal(size=(n_distinct, d_y))[rows], (b, N, d_y))
    theta = rng.normal(scale=0.5, size=(b, 2 + d_y + d_x))
    K = train_cov(theta, Y, X, border=rng.normal(size=N))
    assert_one_matches_naive(K, theta, Y, X, rng)
