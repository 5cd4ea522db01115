"""The GP emulator (docs/method.md §4): the Kronecker solve against the dense core, interpolation of
the runs, the analytic gradient, a fit that does not converge, and bad input."""

import warnings

import numpy as np
import pytest
from test_history_matching import TOY_BOUNDS, toy_simulator

from mdcore import _cases as cases
from mdcore import _gp as gp
from mdcore._emulator import _kron_nlml, fit_emulator
from mdcore._exceptions import ConvergenceWarning


def test_emulator_bad_input():
    X = np.linspace(0, 1, 4)[:, None]
    T = np.array([[0.2, 0.1], [0.8, -0.4], [1.5, 0.6]])
    y = toy_simulator(X, T)
    with pytest.raises(ValueError, match=r"y must have shape \(R, N, n_out\) = \(3, 4"):
        fit_emulator(X, T, y[:2], TOY_BOUNDS)
    with pytest.raises(ValueError, match=r"lower < upper in every row"):
        fit_emulator(X, T, y, [[0, 2], [1, 1]])
    with pytest.raises(ValueError, match="y contains 1 NaN"):
        fit_emulator(X, T, np.where(np.arange(y.size).reshape(y.shape) == 0, np.nan, y),
                     TOY_BOUNDS)
    em = fit_emulator(X, T, y, TOY_BOUNDS, seed=0)
    with pytest.raises(ValueError, match=r"theta \(n_theta, 2\)"):
        em.predict(X, np.zeros((5, 3)))
    with pytest.raises(ValueError, match="theta contains 1 NaN"):
        em.predict(X, [[np.nan, 0.0]])
    assert em.predict(X, np.empty((0, 2))).mean.shape == (0, 4, 1)


def test_emulator_matches_dense_gp_and_interpolates_runs():
    c = cases.load("beam-1d")
    T, X = c.initial_design, c.X_train
    y = c.simulate(X, T)
    em = fit_emulator(X, T, y, c.theta_bounds, seed=0)
    pred = em.predict(X, T)
    np.testing.assert_allclose(pred.mean, y, atol=1e-3)          # nugget is tiny
    # Dense reference: the same GP written as one (R·N)-point regression with the core.
    g = em.gps[0]
    Tu = (T - c.theta_bounds[:, 0]) / np.ptp(c.theta_bounds, axis=1)
    Xu = (X - X.min()) / np.ptp(X)
    F = np.column_stack([np.ones(325), np.tile(Xu, (25, 1)), np.repeat(Tu, 13, axis=0)])
    res = y[..., 0].ravel() - F @ g.beta
    th = np.array([[12.0, 55.0], [38.0, 68.0], [49.0, 88.0]])
    Ts = (th - c.theta_bounds[:, 0]) / np.ptp(c.theta_bounds, axis=1)
    dense = gp.predict(g.log_params, np.repeat(Tu, 13, axis=0), np.tile(Xu, (25, 1)), res,
                       np.repeat(Ts, 13, axis=0), np.tile(Xu, (3, 1)))
    Fs = np.column_stack([np.ones(39), np.tile(Xu, (3, 1)), np.repeat(Ts, 13, axis=0)])
    got = em.predict(X, th)
    np.testing.assert_allclose(got.mean.ravel(), dense.mean + Fs @ g.beta, atol=1e-7)
    np.testing.assert_allclose(got.var.ravel(), dense.var, rtol=1e-6, atol=1e-12)



def test_emulator_likelihood_and_gradient_match_dense_core(rng):
    Tu, Xu, res = rng.uniform(size=(7, 2)), rng.uniform(size=(5, 1)), rng.normal(size=(7, 5))
    lp = np.array([0.2, -0.5, 0.1, -0.3, -2.0])
    f, g = _kron_nlml(lp, Tu, Xu, res)
    dense = gp.neg_log_marginal_likelihood(lp, np.repeat(Tu, 5, axis=0), np.tile(Xu, (7, 1)),
                                           res.ravel())
    assert f == pytest.approx(float(dense), rel=1e-10)
    h = 1e-6
    fd = [(_kron_nlml(lp + h * e, Tu, Xu, res)[0] - _kron_nlml(lp - h * e, Tu, Xu, res)[0])
          / (2 * h) for e in np.eye(5)]
    np.testing.assert_allclose(g, fd, rtol=1e-6, atol=1e-6)



def test_emulator_fits_of_the_cases_converge_quietly():
    """A normal fit raises no ConvergenceWarning (beam-1d's initial 5 × 5 design)."""
    c = cases.load("beam-1d")
    with warnings.catch_warnings():
        warnings.simplefilter("error", ConvergenceWarning)
        fit_emulator(c.X_train, c.initial_design, c.simulate(c.X_train, c.initial_design),
                     c.theta_bounds, seed=0)


def test_scoring_is_the_implausibility_of_the_predicted_moments(rng):
    """Emulator.implausibility (chunked, distances by one product, G = W (V ⊙ V)ᵀ) gives
    the formula of Eq. 16 on Emulator.predict's moments, for every rank rule. The mean is
    a sum of terms up to ~1e5 times larger than itself (a tiny nugget), so the two orders
    of summation agree to ~1e-11 of the terms: an absolute 1e-8 in I."""
    c = cases.load("shear-5")
    X = np.unique(c.X_train, axis=0)
    em = fit_emulator(X, c.initial_design, c.simulate(X, c.initial_design), c.theta_bounds,
                      seed=0)
    lo, hi = c.theta_bounds[:, 0], c.theta_bounds[:, 1]
    theta = lo + (hi - lo) * rng.uniform(size=(5000, 3))
    z, V = c.simulate(X, c.theta_true[None])[0], 0.01 * np.ones((X.shape[0], 5))
    pred = em.predict(X, theta)
    I_all = (np.abs(z - pred.mean) / np.sqrt(V + pred.var)).reshape(len(theta), -1)
    for rank in (1, 2, 3):
        I, var = em.implausibility_and_var(X, theta, z, V, rank=rank)
        np.testing.assert_allclose(I, -np.sort(-I_all, axis=1)[:, rank - 1], rtol=1e-9,
                                   atol=1e-8)
        np.testing.assert_allclose(var, pred.var, rtol=1e-9, atol=1e-12 * pred.var.max())
