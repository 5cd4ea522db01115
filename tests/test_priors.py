"""Priors: densities against scipy, draws reproducible, θ draws inside the box, bad input."""

import numpy as np
import pytest
from scipy import stats

from mdcore._priors import GaussianPrior, ThetaPrior


def test_density_gradient_and_draws():
    p = ThetaPrior(mean=[35.0, 70.0], var=[10.0, 36.0])
    x = np.array([[30.0, 60.0], [40.0, 75.0]])
    want = stats.norm(p.mean, np.sqrt(p.var)).logpdf(x).sum(axis=1)
    np.testing.assert_allclose(p.logpdf(x), want, rtol=1e-12)
    np.testing.assert_allclose(p.grad(x), -(x - p.mean) / p.var)
    d = p.sample(200_000, seed=1)
    assert np.all(np.abs(d.mean(axis=0) - p.mean) < 5 * np.sqrt(p.var / 200_000))
    np.testing.assert_array_equal(p.sample(5, seed=3), p.sample(5, seed=3))


def test_truncated_draws_stay_in_the_box_and_follow_the_truncated_normal():
    p = ThetaPrior(mean=[0.0], var=[1.0])
    d = p.sample_in([[0.0, 1.0]], 20_000, seed=0)
    assert d.shape == (20_000, 1) and d.min() >= 0.0 and d.max() <= 1.0
    ref = stats.truncnorm(0.0, 1.0)
    assert stats.kstest(d[:, 0], ref.cdf).pvalue > 1e-3
    np.testing.assert_array_equal(p.sample_in([[0.0, 1.0]], 7, seed=4),
                                  p.sample_in([[0.0, 1.0]], 7, seed=4))


@pytest.mark.parametrize("make, match", [
    (lambda: ThetaPrior([1.0], [0.0]), "theta_prior var must be positive"),
    (lambda: ThetaPrior([np.nan], [1.0]), "theta_prior mean contains 1 NaN"),
    (lambda: ThetaPrior([1.0, 2.0], [1.0]), "must have the same shape"),
    (lambda: GaussianPrior([0.0], [-1.0]), "prior var must be positive"),
    (lambda: ThetaPrior([40.0], [1e-4]).sample_in([[0.0, 1.0]], 3), "almost no mass inside"),
    (lambda: ThetaPrior([0.5], [1.0]).sample_in([[0.0, 1.0], [0.0, 1.0]], 3),
     r"bounds must have shape \(p, 2\) = \(1, 2\)"),
    (lambda: ThetaPrior([0.5], [1.0]).sample(0), "n must be an integer ≥ 1"),
])
def test_bad_input(make, match):
    with pytest.raises(ValueError, match=match):
        make()
