"""The GP emulator (SPEC §4): the Kronecker solve against the dense core, interpolation of
the runs, the analytic gradient, a fit that does not converge, and bad input."""

import warnings

import numpy as np
import pytest
from conftest import missing
from test_history_matching import TOY_BOUNDS, toy_simulator

from mdcore import cases, gp, kernels
from mdcore.emulator import _kron_nlml, _kron_solve, _m32_and_dlog_ell, _sq_diffs, fit_emulator
from mdcore.exceptions import ConvergenceWarning


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


@pytest.mark.parametrize("d", [0, 1, 2, 4])
def test_fit_kernel_is_bit_identical_to_the_core_kernel(rng, d):
    """The fit's own Matérn + derivative (precomputed differences, one shared exp) computes
    exactly what kernels.matern32_and_dlog_ell computes: the emulator fit, and so every
    history match, must not move by a bit (L-BFGS-B would turn 1 ulp into ~1e-5)."""
    for n in (1, 7, 40):
        A = rng.uniform(size=(n, d))
        ell = np.exp(rng.normal(scale=1.5, size=d))
        K, D = _m32_and_dlog_ell(A, ell, _sq_diffs(A))
        K_ref, D_ref = kernels.matern32_and_dlog_ell(A, ell)
        np.testing.assert_array_equal(K, K_ref)
        np.testing.assert_array_equal(D, D_ref)
        assert D.shape == (d, n, n)


def test_fit_precomputed_differences_change_nothing(rng):
    Tu, Xu, res = rng.uniform(size=(9, 3)), rng.uniform(size=(6, 2)), rng.normal(size=(9, 6))
    diffs = (_sq_diffs(Tu), _sq_diffs(Xu))
    for _ in range(20):
        lp = np.r_[rng.normal(), rng.normal(scale=1.5, size=5), rng.uniform(-12, -2)]
        f, g = _kron_nlml(lp, Tu, Xu, res)
        f2, g2 = _kron_nlml(lp, Tu, Xu, res, diffs)
        assert f == f2
        np.testing.assert_array_equal(g, g2)
        for a, b in zip(_kron_solve(lp, Tu, Xu, res), _kron_solve(lp, Tu, Xu, res, diffs)):
            np.testing.assert_array_equal(a, b)


# The compiled fit: the same bits as the NumPy fit (numba only)


def test_compiled_sums_and_einsum_are_numpys_to_the_bit(rng):
    pytest.importorskip("numba")
    from mdcore import compiled

    k = compiled.fit_kernels()
    for n in [*range(0, 300), 1000, 4096, 8191, 8193, 20_000]:
        x = rng.normal(size=n) * np.exp(rng.normal(scale=5.0, size=n))
        assert k.total(x) == np.sum(x), n
    A = rng.normal(size=(27, 3))
    assert k.total(A) == A.sum()
    for n in (1, 2, 3, 7, 27, 64):
        K = rng.normal(size=(n, n))
        Q = np.linalg.eigh(K @ K.T)[1]
        D = rng.normal(size=(2, n, n))
        np.testing.assert_array_equal(k.diag_quad(Q, D[1]), np.einsum("ra,rs,sa->a", Q, D[1], Q))


def test_compiled_likelihood_is_numpys_to_the_bit(rng):
    """Random designs (grids with repeated coordinates among them), residual scales and
    hyperparameters down to a nugget of 1e-6: f and every gradient entry bit-identical."""
    pytest.importorskip("numba")
    from mdcore import compiled
    from mdcore.emulator import _kron_nlml_compiled

    k = compiled.fit_kernels()
    for trial in range(300):
        R, N = rng.integers(1, 40), rng.integers(1, 50)
        p, d_x = rng.integers(1, 4), rng.integers(1, 3)
        Tu, Xu = rng.uniform(size=(R, p)), rng.uniform(size=(N, d_x))
        if trial % 3 == 0:
            Tu, Xu = np.round(Tu * 3) / 3, np.round(Xu * 4) / 4
        res = rng.normal(size=(R, N)) * np.exp(rng.normal())
        lp = np.r_[rng.normal(), rng.normal(scale=1.5, size=p + d_x), rng.uniform(-14, -1)]
        diffs = (_sq_diffs(Tu), _sq_diffs(Xu))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            f, g = _kron_nlml(lp, Tu, Xu, res, diffs)
            f2, g2 = _kron_nlml_compiled(lp, Tu, Xu, res, diffs, k)
        assert f == f2 or (np.isnan(f) and np.isnan(f2))
        np.testing.assert_array_equal(g, g2)


def test_eigh_without_numpys_wrapper_gives_its_bits(rng):
    """The fit's eigendecomposition (NumPy's kernel called directly) is np.linalg.eigh to
    the bit, on the Kronecker factors' sizes and an empty matrix, for a matrix with NaN too."""
    from mdcore.emulator import _eigh, _eigh_lo

    if _eigh_lo is None:
        missing("this NumPy moved its eigh kernel: _eigh is np.linalg.eigh itself")
    raised = 0
    for n in (0, 1, 2, 3, 13, 27, 64):
        A = rng.normal(size=(n, n))
        for K in (A @ A.T, np.round(A @ A.T, 1), np.where(np.eye(n) > 0, np.nan, A + A.T)):
            try:
                ref = np.linalg.eigh(K)
            except np.linalg.LinAlgError:
                raised += 1
                with pytest.raises(np.linalg.LinAlgError, match="did not converge"):
                    _eigh(K)
                continue
            got = _eigh(K)
            np.testing.assert_array_equal(got[0], ref[0])
            np.testing.assert_array_equal(got[1], ref[1])
    assert raised                                  # NaN on the diagonal: no convergence


@pytest.mark.parametrize("name", ["beam-1d", "beam-2d", "shear-5"])
def test_fit_is_the_same_on_both_backends(name):
    pytest.importorskip("numba")
    c = cases.load(name)
    X, T = np.unique(c.X_train, axis=0), c.initial_design
    y = c.simulate(X, T)
    ems = [fit_emulator(X, T, y, c.theta_bounds, seed=1, backend=b) for b in ("numpy", "numba")]
    for a, b in zip(*(em.gps for em in ems)):
        for u, v in zip(a, b):
            np.testing.assert_array_equal(u, v)
