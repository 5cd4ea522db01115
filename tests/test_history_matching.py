"""History matching: implausibility by hand, a closed-form toy, and beam-1d against the
case study's expected NROY region."""

import numpy as np
import pytest

from mdcore import _cases as cases
from mdcore._history_matching import (
    HistoryMatchResult,
    combine,
    elementwise_implausibility,
    history_match,
    history_match_case,
    iter_waves,
    next_wave,
    replicate_summary,
    setup_arguments,
)
from mdcore._history_matching import setup as hm_setup


def setup(simulate, X, z, bounds, **kwargs):
    """:func:`mdcore._history_matching.setup` with the options' fields by name."""
    return hm_setup(simulate, X, z, bounds, **setup_arguments(kwargs))


def test_implausibility_by_hand():
    I = elementwise_implausibility(np.array([1.0, 4.0]), np.array([0.0, 1.0]), np.array([0.5, 0.0]),
                       V_o=0.25, V_m=np.array([0.25, 1 / 9 - 0.25 + 0.25]))
    # |1−0|/sqrt(0.25+0.25+0.5) = 1;  |4−1|/sqrt(0.25 + 1/9) ...
    np.testing.assert_allclose(I, [1.0, 3.0 / np.sqrt(0.25 + 1 / 9)])
    np.testing.assert_allclose(elementwise_implausibility(2.0, 1.0, 0.0, V_o=0.0, V_m=1 / 81), 9.0)


def test_combiner_rules_by_hand():
    I = np.array([[[1.0, 7.0], [9.0, 2.0], [4.0, 3.0]]])        # one θ, 3 inputs × 2 outputs
    assert combine(I, "max")[0] == 9.0
    assert combine(I, "2nd max")[0] == 7.0
    assert combine(I, "3rd max")[0] == 4.0
    with pytest.raises(ValueError, match="not a valid rule"):
        combine(I, "median")
    with pytest.raises(ValueError, match="needs at least 3 targets"):
        combine(I[:, :1, :1], "3rd max")
    with pytest.raises(ValueError, match="I contains 1 NaN"):
        combine(np.array([[[1.0], [np.nan]]]))
    with pytest.raises(ValueError, match=r"I must have at least 2 dimension"):
        combine(np.array([1.0, 2.0]))


def test_implausibility_bad_input():
    with pytest.raises(ValueError, match="mean contains 1 NaN"):
        elementwise_implausibility(1.0, np.nan, 0.1, V_o=0.1, V_m=0.1)
    with pytest.raises(ValueError, match="var must be non-negative"):
        elementwise_implausibility(1.0, 0.0, -0.1, V_o=0.1, V_m=0.1)
    with pytest.raises(ValueError, match="V_m is empty"):
        elementwise_implausibility(1.0, 0.0, 0.1, V_o=0.1, V_m=[])
    with pytest.raises(ValueError, match="must be positive for every target"):
        elementwise_implausibility(1.0, 0.0, 0.0, V_o=0.0, V_m=0.0)


def test_replicates_use_mean_and_sample_variance():
    X = np.array([[0.0], [0.0], [0.0], [1.0], [1.0]])
    z = np.array([[1.0], [2.0], [3.0], [5.0], [7.0]])
    Xu, zm, zv, counts = replicate_summary(X, z)
    np.testing.assert_array_equal(Xu[:, 0], [0.0, 1.0])
    np.testing.assert_allclose(zm[:, 0], [2.0, 6.0])
    np.testing.assert_allclose(zv[:, 0], [1.0, 2.0])
    prob = setup(lambda X, t: np.zeros((len(t), len(X), 1)), X, z, [[0, 1]], V_m=0.1)
    np.testing.assert_allclose(prob.V_o[:, 0], [1.0, 2.0])


def toy_simulator(X, theta):
    """y = θ₁ sin(2πx) + θ₂ (closed form)."""
    return (theta[:, 0, None] * np.sin(2 * np.pi * X[None, :, 0]) + theta[:, 1, None])[..., None]


TOY_BOUNDS = np.array([[0.0, 2.0], [-1.0, 1.0]])
TOY_TRUTH = np.array([1.2, 0.3])


def toy_data():
    X = np.linspace(0.05, 0.95, 8)[:, None]
    rng = np.random.default_rng(0)
    z = toy_simulator(X, TOY_TRUTH[None])[0] + 0.05 * rng.standard_normal((8, 1))
    return X, z


def test_toy_history_match_recovers_exact_nroy_region():
    X, z = toy_data()
    V_o, V_m = 0.0025, 0.01
    result = history_match(toy_simulator, X, z, TOY_BOUNDS, V_o=V_o, V_m=V_m, n_runs=8,
                           n_candidates=40_000, max_waves=3, convergence_ratio=1e-9, seed=1)
    assert len(result.waves) == 3
    fractions = result.nroy_fraction
    assert all(b <= a + 1e-12 for a, b in zip(fractions, fractions[1:]))
    for k in range(1, len(result.waves) + 1):     # the truth is NROY after every wave
        assert HistoryMatchResult(result.problem, result.waves[:k]).contains(TOY_TRUTH)[0]
    # Exact NROY region on a dense grid with the exact simulator (emulator variance 0).
    g1, g2 = np.meshgrid(np.linspace(0, 2, 301), np.linspace(-1, 1, 301), indexing="ij")
    grid = np.column_stack([g1.ravel(), g2.ravel()])
    I = combine(elementwise_implausibility(z, toy_simulator(X, grid), 0.0, V_o=V_o, V_m=V_m))
    exact = I <= 3.0
    assert fractions[-1] == pytest.approx(exact.mean(), rel=0.10)
    # Classification agrees on ≥ 97 % of the grid (disagreement only at the boundary).
    final = result.contains(grid)
    assert np.mean(final == exact) >= 0.97


def test_stepping_matches_full_run_and_seed_is_reproducible():
    X, z = toy_data()
    kw = dict(V_o=0.0025, V_m=0.01, n_candidates=5000, max_waves=2, convergence_ratio=1e-9,
              seed=5)
    full = history_match(toy_simulator, X, z, TOY_BOUNDS, **kw)
    prob = setup(toy_simulator, X, z, TOY_BOUNDS, **kw)
    w1 = next_wave(prob)
    w2 = next_wave(prob, (w1,))
    np.testing.assert_array_equal(w2.nroy, full.waves[1].nroy)
    np.testing.assert_array_equal(full.nroy_samples(50, seed=3), full.nroy_samples(50, seed=3))
    assert [w.index for w in iter_waves(prob)] == [1, 2]
    with pytest.raises(ValueError, match="already stopped"):
        next_wave(prob, full.waves)


def test_everything_ruled_out_is_a_status_not_a_crash():
    X, z = toy_data()
    z = z + 50.0                                      # far from anything the simulator makes
    result = history_match(toy_simulator, X, z, TOY_BOUNDS, V_o=1e-6, V_m=1e-6, threshold=0.5,
                           n_candidates=2000, seed=0)
    assert result.status == "ruled_out"
    assert "Raise V_m" in result.message and result.waves[-1].nroy.shape == (0, 2)
    with pytest.raises(ValueError, match="no θ samples.*Raise V_m"):
        result.nroy_samples(10)


def test_samples_needs_a_positive_count():
    X, z = toy_data()
    result = history_match(toy_simulator, X, z, TOY_BOUNDS, V_o=0.0025, V_m=0.01,
                           n_candidates=2000, max_waves=1, seed=0)
    with pytest.raises(ValueError, match="n must be an integer ≥ 1"):
        result.nroy_samples(0)
    with pytest.raises(ValueError, match="n must be an integer ≥ 1"):
        result.posterior_samples(0)
    with pytest.raises(ValueError, match="theta contains 1 NaN"):
        result.log_likelihood(np.array([[np.nan, 0.5]]))
    with pytest.raises(ValueError, match=r"theta \(n_theta, 2\)"):
        result.log_likelihood(np.ones((2, 3)))
    with pytest.raises(ValueError, match="theta is empty"):
        result.log_likelihood(np.empty((0, 2)))


@pytest.mark.parametrize("kwargs,match", [
    (dict(threshold=0.0), "threshold T must be a positive number"),
    (dict(threshold=-3.0), "threshold T must be a positive number"),
    (dict(V_m=-0.1), "V_m must be positive"),
    (dict(V_o=-1.0), "V_o must be non-negative"),
    (dict(rule="4th max"), "not a valid rule"),
    (dict(n_runs=0), "n_runs must be an integer"),
])
def test_bad_settings(kwargs, match):
    X, z = toy_data()
    opts = dict(V_o=0.0025, V_m=0.01)
    opts.update(kwargs)
    with pytest.raises(ValueError, match=match):
        setup(toy_simulator, X, z, TOY_BOUNDS, **opts)


def test_bad_data():
    X, z = toy_data()
    with pytest.raises(ValueError, match=r"lower < upper in every row; rows \[1\]"):
        setup(toy_simulator, X, z, [[0, 2], [1, -1]], V_o=0.1, V_m=0.1)
    with pytest.raises(ValueError, match="z must have shape \\(N, n_out\\) with N = 8"):
        setup(toy_simulator, X, z[:5], TOY_BOUNDS, V_o=0.1, V_m=0.1)
    with pytest.raises(ValueError, match="z contains 1 NaN"):
        setup(toy_simulator, X, np.r_[z[:7], [[np.nan]]], TOY_BOUNDS, V_o=0.1, V_m=0.1)
    with pytest.raises(ValueError, match="V_o is required"):
        setup(toy_simulator, X, z, TOY_BOUNDS, V_m=0.1)


@pytest.fixture(scope="module")
def beam1d_match():
    c = cases.load("beam-1d", seed=0)
    return c, history_match_case(c, n_candidates=50_000, max_waves=3, convergence_ratio=0.02,
                                 seed=0)


def test_beam1d_nroy_matches_exact_simulator(beam1d_match):
    c, result = beam1d_match
    rng = np.random.default_rng(1)
    th = rng.uniform(c.theta_bounds[:, 0], c.theta_bounds[:, 1], (200_000, 2))
    exact = combine(elementwise_implausibility(c.z_train, c.simulate(c.X_train, th), 0.0,
                                   V_o=c.noise_var, V_m=c.V_m)) <= 3
    f_exact = exact.mean()
    assert 0.19 <= f_exact <= 0.29                        # a ridge of ≈ 24 % of the box
    f = result.nroy_fraction
    assert abs(f[-1] - f_exact) <= abs(f[0] - f_exact) + 0.005   # approaches with waves
    assert f[-1] == pytest.approx(f_exact, abs=0.02)
    for k in range(1, len(result.waves) + 1):
        assert HistoryMatchResult(result.problem, result.waves[:k]).contains(c.theta_true)[0]
    s = result.nroy_samples(4000, seed=0)
    near = s[np.abs(s[:, 1] - 68.0) < 1.0, 0]                 # l_cr at E ≈ 68 GPa
    assert 27.0 <= near.min() <= 33.0 and 39.0 <= near.max() <= 45.0
    tm = result.theta_map
    assert np.all(tm >= c.theta_bounds[:, 0]) and np.all(tm <= c.theta_bounds[:, 1])
    assert result.contains(tm)[0]


def test_public_scoring_matches_the_closed_form_and_the_waves():
    """problem.score / Wave.implausibility / contains agree with Eq. 16 by hand."""
    X, z = toy_data()
    V_o, V_m = 0.0025, 0.01
    result = history_match(toy_simulator, X, z, TOY_BOUNDS, V_o=V_o, V_m=V_m,
                           n_candidates=4000, max_waves=2, convergence_ratio=1e-9, seed=2)
    prob, wave = result.problem, result.waves[-1]
    theta = np.array([[1.0, 0.0], [0.2, 0.9], [1.9, -0.9]])
    pred = wave.emulator.predict(prob.X, theta)
    by_hand = np.max(np.abs(prob.z - pred.mean) / np.sqrt(V_o + V_m + pred.var), axis=(1, 2))
    np.testing.assert_allclose(wave.combined_implausibility(theta), by_hand, rtol=1e-12)
    score = prob.score(theta, wave.emulator)
    np.testing.assert_allclose(score.implausibility, by_hand, rtol=1e-12)
    sf2 = np.exp(2 * wave.emulator.log_params[:, 0])         # var = σ_f² − (…) cancels
    np.testing.assert_allclose(score.var, pred.var, rtol=1e-12, atol=1e-14 * sf2.max())
    # The candidates' stored implausibility is the same function.
    np.testing.assert_allclose(wave.combined_implausibility(wave.candidates[:50]),
                               wave.candidate_implausibility[:50], rtol=1e-12)
    # contains = inside the box and I <= T in every wave.
    inside = np.all([w.combined_implausibility(theta) <= prob.options.threshold for w in result.waves], axis=0)
    np.testing.assert_array_equal(result.contains(theta), inside)
    assert not result.contains([5.0, 0.0])[0]                  # outside the prior box
    with pytest.raises(ValueError, match=r"theta must have shape \(M, p\) with p = 2"):
        result.contains(np.zeros((3, 3)))
    with pytest.raises(ValueError, match="theta contains 1 NaN"):
        prob.score([[np.nan, 0.0]], wave.emulator)


def test_seed_accepts_a_generator():
    X, z = toy_data()
    kw = dict(V_o=0.0025, V_m=0.01, n_candidates=2000, max_waves=1)
    a = history_match(toy_simulator, X, z, TOY_BOUNDS, seed=np.random.default_rng(7), **kw)
    b = history_match(toy_simulator, X, z, TOY_BOUNDS, seed=np.random.default_rng(7), **kw)
    np.testing.assert_array_equal(a.waves[0].nroy, b.waves[0].nroy)
    assert a.problem.seed == b.problem.seed
    for bad in (-1, 1.5, "0", True):
        with pytest.raises(ValueError, match="seed must be an integer from 0 to 2..63 − 1 or a numpy.random"):
            history_match(toy_simulator, X, z, TOY_BOUNDS, seed=bad, **kw)


def test_posterior_samples_are_kept_per_seed_and_equal_a_fresh_draw(beam1d_match):
    """Scenarios 2 and 3 of one run ask for the same θ^(j): the second call returns the
    kept draws, which equal those of a match that has drawn nothing yet (same seed)."""
    _, result = beam1d_match
    fresh = HistoryMatchResult(result.problem, result.waves)         # nothing kept yet
    a = result.posterior_samples(300, seed=5)
    a[0, 0] = np.nan                                  # the caller's copy, not the kept one
    b = result.posterior_samples(300, seed=5)
    np.testing.assert_array_equal(b, fresh.posterior_samples(300, seed=5))
    assert np.all(np.isfinite(b))
    assert not np.array_equal(b, result.posterior_samples(300, seed=6))
    assert result.posterior_samples(299, seed=5).shape == (299, 2)
    # A generator is a stream, not a key: two generators in the same state draw alike,
    # and a used one draws anew.
    g = np.random.default_rng(5)
    first = result.posterior_samples(50, seed=g)
    assert not np.array_equal(first, result.posterior_samples(50, seed=g))
    np.testing.assert_array_equal(first, fresh.posterior_samples(50, seed=np.random.default_rng(5)))
    for s in range(8):                                # the memo stays small
        result.posterior_samples(20, seed=100 + s)
    assert len(result._posterior_memo) <= 4


def test_scoring_in_chunks_gives_the_same_waves(monkeypatch):
    """Candidates are scored (and θ weighted) in chunks of at most CHUNK_VALUES values,
    so memory does not grow with candidates × observations; chunks of a few rows give
    the waves, implausibilities and likelihoods of one chunk for all (to rounding: BLAS
    may sum a product in another order for another number of rows)."""
    import mdcore._history_matching as hm_module
    case = cases.load("shear-5", seed=0)

    def run():
        problem = hm_module.case_problem(case, n_candidates=3000, max_waves=2, seed=0,
                                         convergence_ratio=0.001)
        waves = (hm_module.next_wave(problem),)
        waves += (hm_module.next_wave(problem, waves),)
        result = hm_module.HistoryMatchResult(problem, waves)
        return problem, waves, result.log_likelihood(waves[-1].nroy[:500])

    monkeypatch.setattr(hm_module, "CHUNK_VALUES", 10**9)
    problem, whole, ll_whole = run()
    assert len(problem.chunks(3000)) == 1
    monkeypatch.setattr(hm_module, "CHUNK_VALUES", 7 * problem.z.size)
    problem, chunked, ll_chunked = run()
    assert len(problem.chunks(3000)) == 429                   # 7 rows a chunk
    for a, b in zip(whole, chunked):
        np.testing.assert_allclose(a.candidate_implausibility, b.candidate_implausibility,
                                   rtol=1e-10)
        np.testing.assert_allclose(a.nroy, b.nroy, rtol=1e-10)
        np.testing.assert_allclose(a.max_var, b.max_var, rtol=1e-10)
        assert a.nroy_fraction == b.nroy_fraction and a.status == b.status
    np.testing.assert_allclose(ll_whole, ll_chunked, rtol=1e-10)


def test_options_by_name_are_checked():
    """Keyword options are split into setup's arguments and HistoryMatchOptions' fields;
    a name that is neither, or an options object of another type, is refused."""
    X, z = toy_data()
    with pytest.raises(ValueError, match=r"unknown history-matching option\(s\) \['tresh'\]"):
        history_match(toy_simulator, X, z, TOY_BOUNDS, V_o=0.1, V_m=0.1, tresh=3.0)
    with pytest.raises(ValueError, match="options must be a HistoryMatchOptions; received dict"):
        hm_setup(toy_simulator, X, z, TOY_BOUNDS, V_o=0.1, V_m=0.1, options={"threshold": 3})
    with pytest.raises(ValueError, match="threshold T must be a positive number; received nan"):
        setup(toy_simulator, X, z, TOY_BOUNDS, V_o=0.1, V_m=0.1, threshold=float("nan"))
    kwargs = setup_arguments({"V_m": 0.1, "max_waves": 2})
    assert kwargs["V_m"] == 0.1 and kwargs["options"].max_waves == 2
