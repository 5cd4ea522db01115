"""The compiled (numba) GP path against the NumPy reference path of mdcore.gp.

The reference is the public NumPy implementation (itself tested against naive loops and
scikit-learn in test_gp.py). Agreement is to 1e-10 relative: NLML values directly; the
predictive mean relative to its largest magnitude and the latent variance relative to
σ_f² (a variance near a training point is a difference of O(σ_f²) numbers, so it has
absolute, not relative, accuracy). Jitter and failure flags and the NumericalWarnings must
be identical, and a NaN is never returned without a warning.
"""

import subprocess
import sys
import threading
import time
import warnings

import numpy as np
import pytest

pytest.importorskip("numba")

import naive_gp

from mdcore import compiled, gp

try:  # the module whose JITTER_LADDER the NumPy path reads (gp before the split)
    from mdcore import linalg as ladder_home
except ImportError:
    ladder_home = gp

RTOL = 1e-10


def random_problem(rng, N, d_y, d_x, batch=(), n_y=()):
    X = rng.uniform(size=(N, d_x))
    z = rng.normal(size=N)
    Y = rng.normal(size=n_y + (N, d_y))
    lp = rng.normal(scale=0.4, size=batch + (2 + d_y + d_x,))
    lp[..., -1] = rng.uniform(-3, -1, size=batch)
    return lp, Y, X, z


def jitter_messages(record):
    return [str(w.message) for w in record if "covariance matrix" in str(w.message)]


def both(fn_ref, fn_new, *args):
    """Results and jitter warnings of the NumPy and the compiled call."""
    out = []
    for fn in (fn_ref, fn_new):
        with warnings.catch_warnings(record=True) as rec:
            warnings.simplefilter("always")
            res = fn(*args)
        out.append((res, jitter_messages(rec)))
    return out


def assert_close(got, want, scale):
    """``|got − want| ≤ RTOL (|want| + scale)`` elementwise, NaN where ``want`` is NaN."""
    np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
    ok = np.isnan(want) | (np.abs(got - want) <= RTOL * (np.abs(want) + scale))
    assert np.all(ok), f"max difference {np.nanmax(np.abs(got - want))}"


def assert_moments_close(got, want, lp):
    """Mean relative to its largest magnitude per batch element; variance relative to σ_f²."""
    mean, var, noise = got
    sf2 = np.broadcast_to(np.exp(2.0 * lp[..., 0]), want.noise_var.shape)[..., None]
    assert_close(mean, want.mean, np.nanmax(np.abs(want.mean), axis=-1, keepdims=True,
                                            initial=0.0))
    assert_close(var, want.var, sf2)
    np.testing.assert_allclose(noise, want.noise_var, rtol=1e-15)


@pytest.mark.parametrize("N", [1, 13, 64])
@pytest.mark.parametrize("d_x", [1, 2])
@pytest.mark.parametrize("d_y", [0, 1, 5])
def test_nlml_and_predict_match_numpy_path(rng, N, d_y, d_x):
    lp, Y, X, z = random_problem(rng, N, d_y, d_x, batch=(5, 1), n_y=(3,))
    (ref, ref_w), (new, new_w) = both(gp.neg_log_marginal_likelihood, compiled.nlml, lp, Y, X, z)
    assert new.shape == ref.shape == (5, 3)
    np.testing.assert_allclose(new, ref, rtol=RTOL)
    assert new_w == ref_w == []
    Xs = rng.uniform(size=(70, d_x))                        # two tiles of test points
    Ys = rng.normal(size=(3, 70, d_y))
    (p_ref, _), (p_new, _) = both(gp.predict, compiled.predict, lp, Y, X, z, Ys, Xs)
    assert p_new[0].shape == p_ref.mean.shape == (5, 3, 70)
    assert_moments_close(p_new, p_ref, lp)


@pytest.mark.parametrize("log_ell", [1.0, -4.0])
def test_separable_one_dimensional_path(rng, log_ell):
    """One-dimensional y and x far from the origin: with long length scales K_f* is built
    from per-point exponentials (√3 h/ℓ ≤ SEPARABLE_LIMIT), with short ones per entry."""
    lp, Y, X, z = random_problem(rng, 13, 1, 1, batch=(6,), n_y=(6,))
    X, Y = X + 1e3, Y - 50.0
    lp[:, 1:3] = log_ell + 0.3 * rng.normal(size=(6, 2))
    Xs = X[0] + rng.uniform(-1.0, 2.0, size=(90, 1))
    Ys = Y[:, :1] + rng.normal(size=(6, 90, 1))
    p = compiled.predict(lp, Y, X, z, Ys, Xs)
    assert_moments_close(p, gp.predict(lp, Y, X, z, Ys, Xs), lp)


def test_scenario_3_and_fitting_layouts(rng):
    """phi (S, K, P) against Y (S, 1, N, d_y), and particles (n, P) against one Y."""
    lp, Y, X, z = random_problem(rng, 13, 1, 1, batch=(4, 6), n_y=(4, 1))
    np.testing.assert_allclose(compiled.nlml(lp, Y, X, z),
                               gp.neg_log_marginal_likelihood(lp, Y, X, z), rtol=RTOL)
    particles = lp.reshape(-1, lp.shape[-1])
    np.testing.assert_allclose(compiled.nlml(particles, Y[0, 0], X, z),
                               gp.neg_log_marginal_likelihood(particles, Y[0, 0], X, z), rtol=RTOL)
    one = compiled.nlml(particles[0], Y[0, 0], X, z)
    assert one.shape == () and one == pytest.approx(naive_gp.nlml(particles[0], Y[0, 0], X, z),
                                                    rel=1e-9)


def test_predict_with_separate_test_batch_and_no_test_points(rng):
    lp, Y, X, z = random_problem(rng, 9, 2, 1, batch=(3,))
    Ys = rng.normal(size=(2, 1, 5, 2))                      # broadcasts to (2, 3)
    Xs = rng.uniform(size=(5, 1))
    p = compiled.predict(lp, Y, X, z, Ys, Xs)
    assert_moments_close(p, gp.predict(lp, Y, X, z, Ys, Xs), lp)
    mean, var, noise = compiled.predict(lp, Y, X, z, Ys[..., :0, :], Xs[:0])
    assert mean.shape == var.shape == (2, 3, 0) and noise.shape == (2, 3)


@pytest.mark.parametrize("d_y,d_x", [(1, 1), (5, 1), (1, 2)])
def test_replicated_training_inputs_match_numpy_path(rng, d_y, d_x):
    """Shear-5's layout: a few distinct inputs, each observed several times (y is a function
    of x, so replicated x come with replicated y). The compiled path computes the kernel
    entries of the distinct inputs once and copies them to the replicates; the NLML and
    the predictions are those of the NumPy path, and of the naive loop."""
    distinct = rng.uniform(size=(3, d_x))
    rows = rng.permutation(np.repeat(np.arange(3), [4, 3, 5]))      # 12 observations
    X = distinct[rows]
    Y = rng.normal(size=(4, 3, d_y))[:, rows]                        # 4 θ, replicated rows
    z = rng.normal(size=12)
    lp = rng.normal(scale=0.4, size=(4, 6, 2 + d_y + d_x))
    lp[..., -1] = rng.uniform(-3, -1, size=(4, 6))
    Yb = Y[:, None]                                                 # (S, 1, N, d_y)
    (ref, ref_w), (new, new_w) = both(gp.neg_log_marginal_likelihood, compiled.nlml, lp, Yb,
                                      X, z)
    assert new.shape == (4, 6) and new_w == ref_w == []
    np.testing.assert_allclose(new, ref, rtol=RTOL)
    assert new[2, 3] == pytest.approx(naive_gp.nlml(lp[2, 3], Y[2], X, z), rel=1e-9)
    Xs = distinct[[0, 2, 1, 0]] + 0.01
    Ys = rng.normal(size=(4, 1, 4, d_y))
    (p_ref, _), (p_new, _) = both(gp.predict, compiled.predict, lp, Yb, X, z, Ys, Xs)
    assert_moments_close(p_new, p_ref, lp)


@pytest.mark.parametrize("d_x", [1, 2])
def test_grid_inputs_match_numpy_path(rng, d_x):
    """x on a grid (beam-2d's layout) repeats its differences, so with one-dimensional y the
    compiled path builds the training entries from one exponential per distinct x
    difference and per point (``_grid_entries``) from ``GRID_MIN_POINTS`` points on. Long
    and short y length scales: the short ones (√3 h_y/ℓ_y > SEPARABLE_LIMIT) take the
    per-entry path."""
    from mdcore import _compiled_kernels as k

    axes = ([np.linspace(0.1, 0.5, 48)] if d_x == 1
            else [np.linspace(0.1, 0.5, 8), np.linspace(0.0, 0.05, 6)])
    X = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, d_x)
    N = X.shape[0]
    n = N + 1
    diffs = np.empty((d_x, n * (n + 1) // 2))
    k._packed_diffs(X, n, diffs)
    assert k._grid_space(diffs, N, True)[0] > 0                    # the grid path is on
    small = np.linspace(0.1, 0.9, 13)[:, None]                     # beam-1d's 13: off
    small_diffs = np.empty((1, 14 * 15 // 2))
    k._packed_diffs(small, 14, small_diffs)
    assert k._grid_space(small_diffs, 13, True)[0] == 0
    Y = 1.5 + 0.4 * rng.normal(size=(3, 1, N, 1))
    z = rng.normal(size=N)
    lp = rng.normal(scale=0.4, size=(3, 8, 3 + d_x))
    lp[..., 1] = np.linspace(-4.0, 1.5, 8)                         # log ℓ_y
    lp[..., 2:2 + d_x] = np.log(0.2) + 0.3 * rng.normal(size=(3, 8, d_x))
    lp[..., -1] = rng.uniform(-3, -1, size=(3, 8))
    (ref, ref_w), (new, new_w) = both(gp.neg_log_marginal_likelihood, compiled.nlml, lp, Y,
                                      X, z)
    assert new_w == ref_w == []
    np.testing.assert_allclose(new, ref, rtol=RTOL)
    assert new[1, 5] == pytest.approx(naive_gp.nlml(lp[1, 5], Y[1, 0], X, z), rel=1e-9)
    Xs = rng.uniform(0.1, 0.5, size=(40, d_x))
    Ys = 1.5 + 0.4 * rng.normal(size=(3, 1, 40, 1))
    (p_ref, _), (p_new, _) = both(gp.predict, compiled.predict, lp, Y, X, z, Ys, Xs)
    assert_moments_close(p_new, p_ref, lp)


def duplicated_points(rng, N=20):
    """Two problems on data whose first two points coincide. With σ_f = 1 and σ_n = e^-40
    the second Cholesky pivot is exactly 1 − 1 = 0, a deterministic failure that jitter
    (1e-10 × mean diagonal) repairs, unless the jitter is below the diagonal's ulp; the
    second is well conditioned."""
    X = rng.uniform(size=(N, 1))
    X[1] = X[0]
    Y = rng.normal(size=(N, 1))
    Y[1] = Y[0]
    z = rng.normal(size=N)
    lp = np.array([[0.0, 0.3, -1.0, -40.0], [0.2, 0.1, -1.5, -2.0]])
    return lp, Y, X, z


def test_jitter_matches_numpy_path(rng):
    lp, Y, X, z = duplicated_points(rng)
    (ref, ref_w), (new, new_w) = both(gp.neg_log_marginal_likelihood, compiled.nlml, lp, Y, X, z)
    assert np.all(np.isfinite(ref))
    np.testing.assert_allclose(new, ref, rtol=RTOL)
    assert len(ref_w) == 1 and "added jitter up to 1.0e-10" in ref_w[0]
    assert new_w == ref_w
    Xs, Ys = X[:6] + 0.01, Y[:6]
    (p_ref, ref_w), (p_new, new_w) = both(gp.predict, compiled.predict, lp, Y, X, z, Ys, Xs)
    assert new_w == ref_w and len(new_w) == 1
    assert_moments_close(p_new, p_ref, lp)


@pytest.mark.parametrize("ladder", [(), (1e-300,)])
def test_failure_matches_numpy_path(rng, monkeypatch, ladder):
    """No jitter step, or one below the diagonal's ulp: the duplicated-point matrix stays
    singular in both paths; NLML +inf, predictions NaN, the same warnings."""
    monkeypatch.setattr(ladder_home, "JITTER_LADDER", ladder)
    lp, Y, X, z = duplicated_points(rng)
    (ref, ref_w), (new, new_w) = both(gp.neg_log_marginal_likelihood, compiled.nlml, lp, Y, X, z)
    assert ref[0] == new[0] == np.inf
    assert new[1] == pytest.approx(ref[1], rel=RTOL)
    assert new_w == ref_w and "stayed non-positive-definite" in new_w[-1]
    (p_ref, ref_w), (p_new, new_w) = both(gp.predict, compiled.predict, lp, Y, X, z, Y[:3],
                                          X[:3])
    assert new_w == ref_w and "predictions are NaN" in new_w[-1]
    assert_moments_close(p_new, p_ref, lp)
    assert np.all(np.isnan(p_new[0][0])) and np.all(np.isnan(p_new[1][0]))


def test_nan_is_never_silent(rng, monkeypatch):
    monkeypatch.setattr(ladder_home, "JITTER_LADDER", ())
    lp, Y, X, z = duplicated_points(rng)
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        value = compiled.nlml(lp, Y, X, z)
        mean, var, _ = compiled.predict(lp, Y, X, z, Y[:3], X[:3])
    assert not np.any(np.isnan(value))
    assert np.any(np.isnan(mean)) and np.any(np.isnan(var))
    assert any("predictions are NaN" in m for m in jitter_messages(rec))


@pytest.mark.parametrize("N", [13, 40])
def test_stop_gives_inf_to_exactly_the_pairs_above_it(rng, N):
    """Below EARLY_STOP_ROWS the compiled path compares the NLML at the end, from it during
    the factorisation; both give +inf where, and only where, the full NLML exceeds stop."""
    from mdcore._compiled_kernels import EARLY_STOP_ROWS

    assert N < EARLY_STOP_ROWS or N > EARLY_STOP_ROWS
    lp, Y, X, z = random_problem(rng, N, 1, 2, batch=(300,), n_y=(300,))
    lp[:, 0] = rng.uniform(-4.0, 1.0, size=300)           # many hopeless σ_f
    full = gp.neg_log_marginal_likelihood(lp, Y, X, z)
    stop = float(np.quantile(full, 0.3))
    (ref, ref_w), (new, new_w) = both(
        lambda *a: gp.neg_log_marginal_likelihood(*a, stop=stop),
        lambda *a: compiled.nlml(*a, stop=stop), lp, Y, X, z)
    gone = full > stop
    np.testing.assert_array_equal(ref, np.where(gone, np.inf, full))
    np.testing.assert_array_equal(np.isinf(new), gone)
    np.testing.assert_allclose(new[~gone], full[~gone], rtol=RTOL)
    assert new_w == ref_w == []
    with pytest.raises(ValueError, match="stop must be an NLML level"):
        gp.neg_log_marginal_likelihood(lp, Y, X, z, stop=np.nan)
    for bad in ([1.0, 2.0], np.array([]), "high"):        # one level, a number
        with pytest.raises(ValueError, match="stop"):
            gp.neg_log_marginal_likelihood(lp, Y, X, z, stop=bad)


@pytest.mark.parametrize("backend", ["numpy", "numba"])
def test_pairs_above_stop_count_neither_as_jittered_nor_failed(rng, backend):
    """The duplicated-point pair needs jitter; above stop it is left out without a warning
    (the compiled path abandons it before the failing pivot), below it warns as before."""
    lp, Y, X, z = duplicated_points(rng, N=30)
    full = gp.neg_log_marginal_likelihood(lp, Y, X, z)            # warns: jitter
    for stop, warned in ((full[0] - 1.0, False), (full[0] + 1.0, True)):
        with warnings.catch_warnings(record=True) as rec:
            warnings.simplefilter("always")
            got = gp.neg_log_marginal_likelihood(lp, Y, X, z, stop=stop, backend=backend)
        assert bool(jitter_messages(rec)) is warned
        assert np.isinf(got[0]) is not warned
        assert got[1] == pytest.approx(full[1], rel=RTOL)


@pytest.mark.parametrize("backend", ["numpy", "numba"])
def test_a_pair_a_bound_from_the_sigmas_puts_above_stop_is_left_out_unfactorised(
        rng, backend, monkeypatch):
    """½ zᵀz / (N σ_f² + σ_n²) + N log σ_n (+ (N/2) log 2π) is a lower bound of the NLML; a
    pair it puts above ``stop`` is left out before its matrix is built, on both backends:
    here one that cannot be factorised (duplicated points, σ_n² 1e-18 of σ_f², no jitter)
    counts as neither failed nor jittered. N = 13 is below EARLY_STOP_ROWS, so without
    this bound the compiled path would factorise it, fail and warn."""
    monkeypatch.setattr(ladder_home, "JITTER_LADDER", ())
    lp, Y, X, z = duplicated_points(rng, N=13)
    lp[0, 0], lp[0, -1] = np.log(1e-4), np.log(1e-13)
    N = 13
    floor = 0.5 * z @ z / (N * 1e-8 + 1e-26) + N * np.log(1e-13) + 0.5 * N * np.log(2 * np.pi)
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        full = gp.neg_log_marginal_likelihood(lp, Y, X, z, backend=backend)
    assert np.isinf(full[0]) and jitter_messages(rec)           # fails without a stop
    assert floor > 1e6 > full[1]
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        got = gp.neg_log_marginal_likelihood(lp, Y, X, z, stop=full[1] + 1.0, backend=backend)
    assert jitter_messages(rec) == []
    assert np.isinf(got[0]) and got[1] == full[1]


def test_factorisation_stops_at_the_first_check_past_the_bound(rng):
    """The kernel leaves the rows after the abandoning check as they were copied from the
    packed matrix, and the bound it checks is ½ Σ w_i² + Σ log L_ii + (rows left) log σ_n
    (NumPy's factor here); a full factorisation is NumPy's factor."""
    from mdcore import _compiled_kernels as K
    from mdcore.kernels import train_cov

    N = 40
    lp, Y, X, z = random_problem(rng, N, 1, 1)
    A = train_cov(lp[None], Y[None], X, border=z)[0]          # bordered, lower triangle
    A = A + np.tril(A, -1).T
    L = np.linalg.cholesky(A[None])[0]
    w, d = L[N, :N], np.diag(L)[:N]
    bound = np.cumsum(0.5 * w * w + np.log(d)) + (N - 1 - np.arange(N)) * lp[-1]
    n = N + 1
    packed = np.concatenate([A[i, i:] for i in range(n)])
    R = K._factor_rows(n)
    assert K._cholesky_rows(packed, R, n, N, 0.0, bound[-1] + 1e-9, lp[-1]) == K.FACTORED
    upper = np.triu_indices(n)
    np.testing.assert_allclose(R[:, :n][upper], L.T[upper], rtol=1e-11, atol=1e-14)
    row = 17                                                    # crossing here: next check 19
    stop = 0.5 * (bound[row - 1] + bound[row])
    assert K._cholesky_rows(packed, R, n, N, 0.0, stop, lp[-1]) == K.ABANDONED
    for i in range(20, n):
        np.testing.assert_array_equal(R[i, i:n], A[i, i:])
    np.testing.assert_allclose(R[1, 1:n], L[1:, 1], rtol=1e-12)   # row 1 was done


def test_factor_rows_padding_never_reaches_the_factor(rng):
    """The spare columns past each row (whole vector iterations) only meet each other: a
    factorisation after one of a matrix with NaN entries (which leaves NaN there) gives
    the bits of one in a fresh array, and the spare columns of a normal one stay 0."""
    from mdcore import _compiled_kernels as K

    n = 21
    B = rng.standard_normal((n, n))
    A = B @ B.T + n * np.eye(n)
    packed = np.concatenate([A[i, i:] for i in range(n)])
    fresh = K._factor_rows(n)
    assert K._cholesky_rows(packed, fresh, n, n, 0.0, np.inf, 0.0) == K.FACTORED
    assert not fresh[:, n:].any()
    used = K._factor_rows(n)
    bad = packed.copy()
    bad[[1, 5]] = np.nan                                        # row 0's entries (0, 1), (0, 5)
    assert K._cholesky_rows(bad, used, n, n, 0.0, np.inf, 0.0) == K.FAILED
    assert np.isnan(used[:, n:]).any()
    assert K._cholesky_rows(packed, used, n, n, 0.0, np.inf, 0.0) == K.FACTORED
    upper = np.triu_indices(n)
    np.testing.assert_array_equal(used[:, :n][upper], fresh[:, :n][upper])


def numpy_mixture_sums(lp, Y, j, X, z, Ys, out, w, Xs, cz, cd):
    p = gp.predict(lp, Y[j], X, z, Ys[j], Xs)
    dz = p.mean - cz
    dd = p.mean - Ys[j][..., out] - cd
    return np.stack([w @ dz, w @ dd, w @ (p.var + p.noise_var[:, None] + dz * dz),
                     w @ (p.var + dd * dd)])


def test_mixture_sums_match_numpy_accumulation(rng):
    S, K, N, M = 5, 40, 13, 70
    lp, Y, X, z = random_problem(rng, N, 2, 1, batch=(S * K,), n_y=(S,))
    j = np.repeat(np.arange(S), K)
    Ys = rng.normal(size=(S, M, 2))
    Xs = rng.uniform(size=(M, 1))
    w = rng.dirichlet(np.ones(S * K))
    ref_p = gp.predict(lp[0], Y[0], X, z, Ys[0], Xs)
    cz, cd = ref_p.mean, ref_p.mean - Ys[0, :, 1]
    got = compiled.mixture_sums(lp, Y, j, X, z, Ys, Ys[..., 1], w, Xs, cz, cd)
    want = numpy_mixture_sums(lp, Y, j, X, z, Ys, 1, w, Xs, cz, cd)
    assert not np.any(got.dropped)
    np.testing.assert_allclose(got.acc, want, rtol=RTOL, atol=RTOL * np.abs(want).max())


def test_mixture_sums_drop_unfactorisable_pairs(rng, monkeypatch):
    monkeypatch.setattr(ladder_home, "JITTER_LADDER", ())
    lp, Y, X, z = duplicated_points(rng)
    lp = lp[[1, 0, 1]]
    Yb = np.stack([Y, Y])
    j = np.array([0, 1, 1])
    w = np.array([0.2, 0.3, 0.5])
    Xs, Ys = X[:4] + 0.01, np.stack([Y[:4], Y[:4]])
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        got = compiled.mixture_sums(lp, Yb, j, X, z, Ys, Ys[..., 0], w, Xs, np.zeros(4),
                                    np.zeros(4))
    np.testing.assert_array_equal(got.dropped, [False, True, False])
    keep = np.array([0, 2])
    want = numpy_mixture_sums(lp[keep], Yb, j[keep], X, z, Ys, 0, w[keep], Xs, np.zeros(4),
                              np.zeros(4))
    np.testing.assert_allclose(got.acc, want, rtol=RTOL, atol=RTOL * np.abs(want).max())
    assert any("stayed non-positive-definite" in m for m in jitter_messages(rec))


def test_results_do_not_depend_on_threads_and_pieces_only_reorder_sums(rng, monkeypatch):
    lp, Y, X, z = random_problem(rng, 13, 1, 1, batch=(3000,), n_y=(30,))
    j = np.repeat(np.arange(30), 100)
    Xs = rng.uniform(size=(20, 1))
    Ys = rng.normal(size=(30, 20, 1))
    w = np.full(3000, 1 / 3000)
    args = (lp, Y, j, X, z, Ys, Ys[..., 0], w, Xs, np.zeros(20), np.zeros(20))
    whole = compiled.nlml(lp, Y[j], X, z)
    acc = compiled.mixture_sums(*args).acc
    monkeypatch.setenv(compiled.THREADS_ENV, "1")
    np.testing.assert_array_equal(compiled.nlml(lp, Y[j], X, z), whole)
    np.testing.assert_array_equal(compiled.mixture_sums(*args).acc, acc)
    monkeypatch.setattr(compiled, "LAUNCH_FLOPS", 1.0)          # 64 pairs per piece
    np.testing.assert_array_equal(compiled.nlml(lp, Y[j], X, z), whole)
    np.testing.assert_allclose(compiled.mixture_sums(*args).acc, acc, rtol=0,
                               atol=1e-13 * np.abs(acc).max())


def test_concurrent_calls_from_threads(rng):
    problems = [random_problem(rng, 13, 1, 1, batch=(2000,)) for _ in range(3)]
    want = [gp.neg_log_marginal_likelihood(*p) for p in problems]
    got = [None] * 3

    def work(i):
        got[i] = compiled.nlml(*problems[i])

    threads = [threading.Thread(target=work, args=(i,)) for i in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=120)
    for g, w in zip(got, want):
        np.testing.assert_allclose(g, w, rtol=RTOL)


def test_thread_limit_from_environment(monkeypatch):
    monkeypatch.setenv(compiled.THREADS_ENV, "1")
    assert compiled.num_threads() == 1
    monkeypatch.setenv(compiled.THREADS_ENV, "two")
    with pytest.raises(ValueError, match="MDCORE_NUM_THREADS must be a positive integer"):
        compiled.num_threads()
    monkeypatch.delenv(compiled.THREADS_ENV)
    assert compiled.num_threads() >= 1


def test_exponential_within_one_ulp():
    from mdcore import _compiled_kernels as k

    rng = np.random.default_rng(0)
    x = np.concatenate([rng.uniform(-760, 720, 100_000), rng.uniform(-2, 2, 100_000),
                        [0.0, -0.0, np.nan, np.inf, -np.inf, -708.0, 709.0, -708.5, 709.5,
                         -745.2, 709.9]])
    out = np.empty_like(x)
    k._qexp(np.ones_like(x), x, out, np.empty_like(x), np.empty(x.size, dtype=np.int64))
    with np.errstate(over="ignore"):
        ref = np.exp(x)
    normal = np.isfinite(ref) & (ref > np.finfo(float).tiny)
    assert np.max(np.abs(out[normal] - ref[normal]) / np.spacing(ref[normal])) <= 1.0
    np.testing.assert_array_equal(out[~normal], ref[~normal])


@pytest.mark.parametrize("d_y, d_x", [(1, 1), (1, 2), (2, 1), (5, 3), (0, 2), (1, 0)])
def test_kernel_entries_are_the_separate_steps_to_the_bit(rng, d_y, d_x):
    """The fused pass of ``_matern_entries`` (distances, factors and the exponential's first
    step at once) gives, bit for bit, Eq. 3 computed step by step in NumPy with the same
    operations in the same order, then ``_qexp``: also for zero, NaN and inf differences
    and arguments past the exponential's range."""
    from mdcore import _compiled_kernels as k

    n = 3000
    Dy = rng.normal(size=(d_y, n)) if d_y == 1 else rng.uniform(size=(d_y, n)) ** 2
    Dx = rng.normal(size=(d_x, n)) if d_x == 1 else rng.uniform(size=(d_x, n)) ** 2
    Dy[:, :4] = Dx[:, 2:6] = 0.0
    if d_y:
        Dy[0, 7], Dy[-1, 8] = np.nan, 1e6                  # NaN; far past exp's range
    if d_x:
        Dx[0, 9] = np.inf
    sy, sx = rng.uniform(0.1, 3.0, d_y), rng.uniform(0.1, 3.0, d_x)
    out = np.empty(n)
    k._matern_entries(Dy, Dx, sy, sx, 0.7, k._workspace(n), out)

    def scaled(D, s):                  # √3 r: |Δ| s in one dimension, else √(Σ Δ² s²)
        if s.size == 1:
            return np.abs(D[0]) * s[0]
        if s.size == 0:
            return np.zeros(n)
        r2 = D[0] * (s[0] * s[0])
        for Dk, sk in zip(D[1:], s[1:]):
            r2 = r2 + Dk * (sk * sk)
        return np.sqrt(r2)

    a, b = scaled(Dy, sy), scaled(Dx, sx)
    want = np.empty(n)
    k._qexp(a * b + (a + b) + 1.0, 0.7 - (a + b), want, np.empty(n),
            np.empty(n, dtype=np.int64))
    np.testing.assert_array_equal(out, want)


def test_warm_up_compiles_the_one_kernel_signature():
    from mdcore import _compiled_kernels as k

    assert compiled.available()
    start = time.perf_counter()
    seconds = compiled.warm_up()                  # the seconds of this call, measured inside
    assert 0.0 < seconds <= time.perf_counter() - start
    assert len(k.pair_range.signatures) == 1, k.pair_range.signatures


def test_package_runs_without_numba():
    """With numba unimportable, mdcore imports, the NumPy path runs, and the compiled path
    says what is missing."""
    code = """
import sys
sys.modules["numba"] = None
import numpy as np
from mdcore import compiled, gp
assert not compiled.available() and compiled.warm_up_in_background() is None
X = np.linspace(0, 1, 5)[:, None]
print(float(gp.neg_log_marginal_likelihood([0.0, 0.0, 0.0, -2.0], np.sin(3 * X), X, X[:, 0])))
try:
    compiled.warm_up()
except ImportError as exc:
    print("ImportError:", exc)
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=300, check=True).stdout
    assert "ImportError: the compiled GP path needs numba" in out


# ---------------------------------------------------------------------------------------
# The backend switch of the library (gp, discrepancy, pipeline)


def test_resolve_backend(monkeypatch):
    monkeypatch.delenv(compiled.BACKEND_ENV, raising=False)
    assert compiled.resolve_backend("numpy") == "numpy"
    assert compiled.resolve_backend("auto") == compiled.resolve_backend(None) == "numba"
    monkeypatch.setenv(compiled.BACKEND_ENV, "numpy")
    assert compiled.resolve_backend(None) == "numpy"
    monkeypatch.setenv(compiled.BACKEND_ENV, "cuda")
    with pytest.raises(ValueError, match="MDCORE_BACKEND must be one of .*received 'cuda'"):
        compiled.resolve_backend(None)
    with pytest.raises(ValueError, match="backend must be one of"):
        gp.neg_log_marginal_likelihood([0.0, 0.0, 0.0, -2.0], np.ones((3, 1)),
                                       np.ones((3, 1)), np.ones(3), backend="gpu")
    monkeypatch.setattr(compiled, "available", lambda: False)
    assert compiled.resolve_backend("auto") == "numpy"
    with pytest.raises(ValueError, match=r"needs numba.*pip install 'mdcore\[fast\]'"):
        compiled.resolve_backend("numba")


def test_gp_backend_argument_matches_reference(rng):
    lp, Y, X, z = random_problem(rng, 13, 2, 1, batch=(7,), n_y=(7,))
    ref = gp.neg_log_marginal_likelihood(lp, Y, X, z)
    assert_close(gp.neg_log_marginal_likelihood(lp, Y, X, z, backend="numba"), ref, 0.0)
    Xs = rng.uniform(size=(5, 1))
    Ys = rng.normal(size=(7, 5, 2))
    want = gp.predict(lp, Y, X, z, Ys, Xs)
    got = gp.predict(lp, Y, X, z, Ys, Xs, backend="numba")
    assert isinstance(got, gp.GPPrediction)
    assert_moments_close(got, want, lp)


@pytest.fixture(scope="module")
def beam1d():
    from mdcore import cases
    from mdcore.history_matching import history_match_case

    case = cases.load("beam-1d")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        hm = history_match_case(case, seed=0, n_candidates=5000)
    return case, hm.posterior_samples(60, seed=1)


@pytest.mark.parametrize("proposal", ["prior", "adaptive"])
def test_scenario_3_is_the_same_on_both_backends(beam1d, proposal):
    """Weights and the fused mixture prediction (compiled.mixture_sums) against the NumPy
    path: the log weights to 1e-10 of their range, the moments to 1e-10 relative."""
    from mdcore.discrepancy import infer_discrepancy

    case, theta = beam1d
    out = {}
    for backend in ("numpy", "numba"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            model = infer_discrepancy(case.simulate, theta, case.X_train, case.z_train,
                                      scenario=3, n_phi=30, phi_prior=case.phi_prior, seed=4,
                                      proposal=proposal, backend=backend)
        assert model.backend == backend
        out[backend] = model, model.predict(case.X_test, prune=1e-8)
    (m0, p0), (m1, p1) = out["numpy"], out["numba"]
    kept = m0.log_weights > m0.log_weights.max() + np.log(1e-8)
    scale = np.ptp(m0.log_weights[np.isfinite(m0.log_weights)])
    assert np.max(np.abs(m1.log_weights[kept] - m0.log_weights[kept])) <= 1e-10 * scale
    np.testing.assert_array_equal(np.isinf(m1.log_weights), np.isinf(m0.log_weights))
    # The adaptive proposal's later stages are fitted to the weights, so its draws carry the
    # weights' rounding differences (~1e-12); the prior's draws are identical.
    np.testing.assert_allclose(m1.log_params, m0.log_params, rtol=0,
                               atol=0.0 if proposal == "prior" else 1e-9)
    for name in p0._fields:
        want, got = getattr(p0, name), getattr(p1, name)
        assert np.max(np.abs(got - want)) <= RTOL * np.max(np.abs(want)), name


def test_fused_prediction_reports_progress_and_stops_when_asked(beam1d):
    from mdcore.discrepancy import infer_discrepancy

    case, theta = beam1d
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = infer_discrepancy(case.simulate, theta, case.X_train, case.z_train,
                                  scenario=3, n_phi=200, phi_prior=case.phi_prior, seed=0,
                                  backend="numba", prune=0.0)
    seen = []
    model.predict(case.X_test, progress=seen.append)
    assert seen[-1] == 1.0 and seen == sorted(seen) and len(seen) >= 5

    class Stop(Exception):
        pass

    def stop(fraction):
        if fraction > 0.3:
            raise Stop

    with pytest.raises(Stop):
        model.predict(case.X_test, progress=stop)


# ---------------------------------------------------------------------------------------
# The KOH likelihood step


@pytest.fixture(scope="module")
def koh_setup():
    from mdcore import cases
    from mdcore.history_matching import history_match_case
    from mdcore.koh import noise_cov

    case = cases.load("beam-1d")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        hm = history_match_case(case, seed=0, n_candidates=5000)
    at = hm.waves[-1].emulator.at(case.X_train)
    log_phi = np.array([[np.log(0.3), np.log(0.2), np.log(0.05)]])
    return case, hm, at, noise_cov(log_phi, case.X_train), np.ascontiguousarray(case.z_train.T)


def test_koh_step_matches_numpy_likelihood(koh_setup, rng):
    from mdcore.koh import gaussian_log_likelihood
    from mdcore.linalg import JitterLog

    case, _, at, B, zT = koh_setup
    lo, hi = case.theta_bounds[:, 0], case.theta_bounds[:, 1]
    theta = lo + (hi - lo) * rng.uniform(size=(50, lo.size))
    arrays = at.arrays()
    step = compiled.koh_log_likelihood(arrays, arrays.prior + B, zT, JitterLog())
    want = gaussian_log_likelihood(*at.moments_at(at.theta_terms(theta)), B, zT, JitterLog())
    got = np.array([step(t) for t in theta])
    np.testing.assert_allclose(got, want, rtol=RTOL)


def test_koh_step_jitter_and_failure_match_numpy(koh_setup, monkeypatch):
    """A noise covariance that makes Σ_η + B indefinite: the same ladder step, the same
    warning text, and -inf where every step fails, on both paths."""
    from mdcore.koh import gaussian_log_likelihood
    from mdcore.linalg import JitterLog

    case, _, at, B, zT = koh_setup
    theta = case.theta_bounds.mean(axis=1)
    mean, cov = at.moments_at(at.theta_terms(theta[None]))
    w, Q = np.linalg.eigh(cov[0, 0] + B[0])
    for shift, expect_finite in ((1.0001 * w[0] + 1e-9 * np.mean(np.diag(cov[0, 0] + B[0])),
                                  True), (w[0] + 10.0 * abs(w).max(), False)):
        B_bad = B - shift * np.eye(B.shape[-1])
        logs = JitterLog(), JitterLog()
        want = gaussian_log_likelihood(mean, cov, B_bad, zT, logs[0])[0]
        arrays = at.arrays()
        got = compiled.koh_log_likelihood(arrays, arrays.prior + B_bad, zT, logs[1])(theta)
        assert np.isfinite(want) == expect_finite == np.isfinite(got)
        if expect_finite:
            # Σ_η + B_bad is singular to 1e-4 of its smallest eigenvalue: rounding that
            # differs by CPU (AVX2 or AVX-512 kernels) moves the value by ~1e-7 (seen: 6e-8),
            # far less than one step of the jitter ladder (10×), which the texts check.
            np.testing.assert_allclose(got, want, rtol=1e-6)
        texts = []
        for log in logs:
            with warnings.catch_warnings(record=True) as rec:
                warnings.simplefilter("always")
                log.warn("KOH likelihood")
            texts.append([str(r.message) for r in rec])
        assert texts[0] == texts[1] and texts[0], texts


def koh_chain(case, emulator, log_phi, backend, n_iter, burn_in, progress=None):
    from mdcore.koh import infer_koh

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return infer_koh(emulator, case.X_train, case.z_train, theta_prior=case.theta_prior,
                         bounds=case.theta_bounds, log_phi=log_phi, n_iter=n_iter,
                         burn_in=burn_in, seed=3, backend=backend, progress=progress).chain


@pytest.mark.parametrize("name", ["beam-1d", "shear-5"])
def test_koh_chain_is_the_same_on_both_backends(name, koh_setup):
    """The compiled chain (compiled.KOHTarget.advance) against the Python loop around the
    NumPy likelihood: every acceptance the same, the states to rounding (NumPy's ``L @ s``
    may fuse multiply-adds, and for shear-5's three parameters LAPACK factorises the
    proposal covariance), and the same progress calls. 4,099 steps: the compiled runs
    stop at the ends of the random draws (4,096) and at every progress call (40 steps)."""
    from mdcore import cases
    from mdcore.history_matching import history_match_case

    if name == "beam-1d":
        case, hm, *_ = koh_setup
        log_phi = [np.log(0.3), np.log(0.2), np.log(0.05)]
    else:
        case = cases.load(name)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            hm = history_match_case(case, seed=0, n_candidates=5000)
        log_phi = np.tile([np.log(0.3), np.log(0.2), np.log(0.05)], (5, 1))
    compiled.warm_up()
    chains, calls = [], []
    for backend in ("numpy", "numba"):
        seen = []
        chains.append(koh_chain(case, hm.waves[-1].emulator, log_phi, backend, 4099, 1003,
                                seen.append))
        calls.append(seen)
    old, new = chains
    assert old.samples.shape[1] == case.theta_bounds.shape[0]
    assert new.acceptance_rate == old.acceptance_rate
    assert new.acceptance_rate_burn_in == old.acceptance_rate_burn_in
    assert 0.05 < new.acceptance_rate < 0.95                  # the chain moves
    np.testing.assert_allclose(new.samples, old.samples, rtol=1e-12, atol=0)
    np.testing.assert_allclose(new.log_target, old.log_target, rtol=RTOL, atol=0)
    np.testing.assert_allclose(new.proposal_cov, old.proposal_cov, rtol=1e-10, atol=0)
    assert calls[1] == calls[0] and len(calls[0]) > 100
    kernels = compiled._koh_kernels()                  # the warm-up's signatures, only
    for kernel in (kernels.chain_steps, kernels.target):    # target: KOHTarget's call at x0
        assert len(kernel.signatures) == 1, (kernel, kernel.signatures)


def test_koh_compiled_chain_stops_when_progress_raises(koh_setup):
    case, hm, *_ = koh_setup

    def stop(f):
        if f > 0.5:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        koh_chain(case, hm.waves[-1].emulator, [np.log(0.3), np.log(0.2), np.log(0.05)],
                  "numba", 3000, 500, stop)


# ---------------------------------------------------------------------------------------
# The history-matching emulator at many candidates


@pytest.fixture(scope="module")
def emulators():
    """Wave-1 emulators of the three cases: p = 1–3, d_x = 1–2, 1 or 5 outputs, R = 4–27
    training runs (R % 4 = 0, 1, 3: every branch of the unrolled loops)."""
    from mdcore import cases
    from mdcore.history_matching import case_problem, next_wave

    out = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for name in ("beam-1d", "beam-2d", "shear-5"):
            problem = case_problem(cases.load(name), max_waves=1, n_candidates=1000,
                                   backend="numpy")
            out[name] = problem, next_wave(problem).emulator
    return out


def candidates(problem, rng, M):
    """M random θ over the box and 10 % beyond it on every side (extrapolation too)."""
    lo, hi = problem.bounds[:, 0], problem.bounds[:, 1]
    return lo - 0.1 * (hi - lo) + 1.2 * (hi - lo) * rng.uniform(size=(M, problem.p))


@pytest.mark.parametrize("name", ["beam-1d", "beam-2d", "shear-5"])
def test_emulator_moments_match_numpy_path(emulators, rng, name):
    """Mean relative to its largest magnitude per output, variance relative to σ_f²; at the
    observed inputs and at other inputs; 3,001 θ is not a multiple of the block or piece."""
    from mdcore import cases

    problem, em = emulators[name]
    theta = candidates(problem, rng, 3001)
    sf2 = np.exp(2.0 * em.log_params[:, 0])
    for X in (problem.X, cases.load(name).X_test[:50]):
        ref = em.predict(X, theta, backend="numpy")
        got = em.predict(X, theta, backend="numba")
        assert got.mean.shape == got.var.shape == ref.mean.shape == (3001, X.shape[0], em.n_out)
        scale = np.max(np.abs(ref.mean), axis=(0, 1))
        assert np.all(np.abs(got.mean - ref.mean) <= RTOL * scale), \
            np.max(np.abs(got.mean - ref.mean) / scale)
        assert np.all(np.abs(got.var - ref.var) <= RTOL * sf2)
        assert np.all(got.var >= 0.0)


@pytest.mark.parametrize("name", ["beam-1d", "shear-5"])
def test_emulator_implausibility_matches_numpy_path(emulators, rng, name):
    """The fused kernel against Eq. 16 and the combiner on the NumPy moments, for every rule;
    and, on one backend, exactly the formula on that backend's own moments."""
    from mdcore.history_matching import RULES, combine, implausibility

    problem, em = emulators[name]
    theta = candidates(problem, rng, 2000)
    V = problem.V_o + problem.V_m
    ref = em.predict(problem.X, theta, backend="numpy")
    own = em.predict(problem.X, theta, backend="numba")
    # |ΔI| ≤ |Δ mean| / sqrt(V + var): the mean's tolerance over the smallest sd.
    tol = RTOL * np.max(np.abs(ref.mean)) / np.sqrt(np.min(V))
    for rule, rank in RULES.items():
        want = combine(implausibility(problem.z, ref.mean, ref.var, V_o=problem.V_o,
                                      V_m=problem.V_m), rule)
        I, var = em.implausibility(problem.X, theta, problem.z, V, rank=rank, backend="numba")
        np.testing.assert_allclose(I, want, rtol=RTOL, atol=tol)
        np.testing.assert_array_equal(var, own.var)
        exact = combine(np.abs(problem.z - own.mean) / np.sqrt(V + own.var), rule)
        np.testing.assert_array_equal(I, exact)
        I_np, var_np = em.implausibility(problem.X, theta, problem.z, V, rank=rank,
                                         backend="numpy")
        np.testing.assert_array_equal(I_np, want)
        np.testing.assert_array_equal(var_np, ref.var)


def test_emulator_kernel_bad_input_and_empty_batch(emulators):
    problem, em = emulators["beam-1d"]
    theta = problem.bounds.mean(axis=1)[None]
    V = problem.V_o + problem.V_m
    for backend in ("numpy", "numba"):
        with pytest.raises(ValueError, match="V_o \\+ V_m \\+ var must be positive"):
            em.implausibility(problem.X, theta, problem.z, -np.ones_like(V), backend=backend)
        with pytest.raises(ValueError, match="rank must be 1, 2 or 3"):
            em.implausibility(problem.X, theta, problem.z, V, rank=4, backend=backend)
        with pytest.raises(ValueError, match="rank 3 needs at least 3 targets"):
            em.implausibility(problem.X[:2], theta, problem.z[:2], V[:2], rank=3,
                              backend=backend)
        with pytest.raises(ValueError, match=r"z and V must broadcast to \(N, n_out\)"):
            em.implausibility(problem.X, theta, problem.z[:3], V, backend=backend)
        I, var = em.implausibility(problem.X, np.empty((0, 2)), problem.z, V, backend=backend)
        assert I.shape == (0,) and var.shape == (0, 13, 1)
        pred = em.predict(problem.X, np.empty((0, 2)), backend=backend)
        assert pred.mean.shape == pred.var.shape == (0, 13, 1)


def test_emulator_kernel_does_not_depend_on_threads_or_pieces(emulators, rng, monkeypatch):
    problem, em = emulators["shear-5"]
    theta = candidates(problem, rng, 5000)
    V = problem.V_o + problem.V_m
    whole = em.implausibility(problem.X, theta, problem.z, V, rank=2, backend="numba")
    moments = em.predict(problem.X, theta, backend="numba")
    monkeypatch.setenv(compiled.THREADS_ENV, "1")
    for a, b in zip(em.implausibility(problem.X, theta, problem.z, V, rank=2,
                                      backend="numba"), whole):
        np.testing.assert_array_equal(a, b)
    monkeypatch.delenv(compiled.THREADS_ENV)
    monkeypatch.setattr(compiled, "LAUNCH_FLOPS", 1.0)          # 64 candidates per piece
    for a, b in zip(em.implausibility(problem.X, theta, problem.z, V, rank=2,
                                      backend="numba"), whole):
        np.testing.assert_array_equal(a, b)
    for a, b in zip(em.predict(problem.X, theta, backend="numba"), moments):
        np.testing.assert_array_equal(a, b)


def test_emulator_kernels_compile_one_signature(emulators, rng):
    from mdcore import _compiled_emulator as e

    compiled.warm_up()
    problem, em = emulators["beam-2d"]
    theta = candidates(problem, rng, 100)
    em.predict(problem.X, theta, backend="numba")
    em.implausibility(problem.X, theta, problem.z, problem.V_o + problem.V_m, rank=np.int64(2),
                      backend="numba")
    assert len(e.candidate_range.signatures) == 1, e.candidate_range.signatures
    # The fit's kernels: warm_up compiled the layouts a real fit passes (d_x = 2 here).
    from mdcore.emulator import fit_emulator

    fit_emulator(problem.X, em.theta_train, em.y_train, problem.bounds, seed=0,
                 backend="numba")
    for kernel in (e.fit_factors, e.fit_kernels, e.fit_spectrum, e.fit_terms,
                   e.fit_gradient):
        assert len(kernel.signatures) == 1, (kernel, kernel.signatures)


@pytest.mark.parametrize("name,options", [
    ("beam-1d", dict(max_waves=3)),
    ("shear-5", dict(max_waves=2, rule="2nd max")),
])
def test_history_match_is_the_same_on_both_backends(name, options):
    """Multi-wave runs (wave ≥ 2 scores its Metropolis proposals under every earlier wave):
    the same candidates, NROY sets and fractions to the last bit, and the same θ_MAP."""
    from mdcore import cases
    from mdcore.history_matching import history_match_case

    case = cases.load(name)
    runs = []
    for backend in ("numpy", "numba"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            result = history_match_case(case, seed=0, n_candidates=20_000,
                                        convergence_ratio=1e-3, backend=backend, **options)
        assert result.problem.backend == backend
        runs.append(result)
    ref, new = runs
    assert len(new.waves) == len(ref.waves) == options["max_waves"]
    for a, b in zip(ref.waves, new.waves):
        np.testing.assert_array_equal(b.candidates, a.candidates)
        np.testing.assert_array_equal(b.nroy, a.nroy)
        np.testing.assert_allclose(b.candidate_implausibility, a.candidate_implausibility,
                                   rtol=1e-8)
        np.testing.assert_allclose(b.max_var, a.max_var, rtol=1e-8)
        assert b.status == a.status
    assert new.nroy_fraction == ref.nroy_fraction
    np.testing.assert_allclose(new.theta_map, ref.theta_map, rtol=1e-8)
    np.testing.assert_array_equal(new.nroy_samples(500, seed=1), ref.nroy_samples(500, seed=1))


def test_history_match_backend_is_checked(monkeypatch):
    from mdcore import cases
    from mdcore.history_matching import case_problem

    case = cases.load("beam-1d")
    with pytest.raises(ValueError, match="backend must be one of"):
        case_problem(case, backend="cuda")
    monkeypatch.setenv(compiled.BACKEND_ENV, "numpy")
    assert case_problem(case).backend == "numpy"
    monkeypatch.setenv(compiled.BACKEND_ENV, "auto")
    assert case_problem(case).backend == "numba"
