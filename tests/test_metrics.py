"""docs/method.md §8 metrics on tiny hand-computed cases, and MMD's closed form against quadrature."""


import numpy as np
import pytest
from scipy import integrate
from scipy.stats import norm

from mdcore._metrics import coverage, lpl, mmd, nmse


def test_nmse_by_hand():
    # t = [1, 2, 3]: var (1/N) = 2/3; squared errors [0, 0, 1] -> 100 · (1/3) / (2/3) = 50
    assert nmse([1.0, 2.0, 3.0], [1.0, 2.0, 4.0]) == pytest.approx(50.0)
    two = nmse(np.array([[1.0, 0.0], [2.0, 2.0], [3.0, 4.0]]),
               np.array([[1.0, 0.0], [2.0, 2.0], [4.0, 2.0]]))
    np.testing.assert_allclose(two, [50.0, 100 * (4 / 3) / (8 / 3)])
    with pytest.raises(ValueError, match="target must vary"):
        nmse([1.0, 1.0], [1.0, 2.0])
    with pytest.raises(ValueError, match="same shape as the targets"):
        nmse([1.0, 2.0], [1.0])


def test_lpl_by_hand():
    # log N(1 | 0, 4) + log N(0 | 0, 1) = −½(1/4 + log 8π) − ½ log 2π
    want = -0.5 * (0.25 + np.log(8 * np.pi)) - 0.5 * np.log(2 * np.pi)
    assert lpl([1.0, 0.0], [0.0, 0.0], [4.0, 1.0]) == pytest.approx(want)
    with pytest.raises(ValueError, match="var must be positive"):
        lpl([1.0], [0.0], [0.0])


def test_coverage_by_hand():
    t, m, v = [0.0, 1.9, 2.1, 3.5], [0.0, 0.0, 0.0, 0.0], [1.0, 1.0, 1.0, 1.0]
    assert coverage(t, m, v, k=2) == pytest.approx(0.5)        # 0 and 1.9 inside ±2
    assert coverage(t, m, v, k=3) == pytest.approx(0.75)       # 3.5 outside ±3
    with pytest.raises(ValueError, match="var must be non-negative"):
        coverage([0.0], [0.0], [-1.0])
    with pytest.raises(ValueError, match="k must be a positive"):
        coverage([0.0], [0.0], [1.0], k=0)


def _mmd_by_quadrature(a, mu, s2):
    q = max(a.size, 20)
    pooled = np.r_[a, mu + np.sqrt(s2) * norm.ppf((np.arange(q) + 0.5) / q)]
    d = [abs(x - y) for i, x in enumerate(pooled) for y in pooled[i + 1:]]
    ell = np.median(d)
    k = lambda x, y: np.exp(-(x - y) ** 2 / (2 * ell * ell))
    pdf = lambda y: norm.pdf(y, mu, np.sqrt(s2))
    lim = (mu - 12 * np.sqrt(s2), mu + 12 * np.sqrt(s2))
    kaa = np.mean([[k(x, y) for y in a] for x in a])
    kay = np.mean([integrate.quad(lambda y, x=x: k(x, y) * pdf(y), *lim)[0] for x in a])
    kyy = integrate.dblquad(lambda y, x: k(x, y) * pdf(x) * pdf(y), *lim, *lim)[0]
    return np.sqrt(kaa - 2 * kay + kyy)


def test_mmd_closed_form_matches_quadrature():
    a = np.array([0.9, 1.05, 1.2])
    got = mmd(a, np.full(3, 1.1), np.full(3, 0.02), X=np.zeros(3))
    assert got == pytest.approx(_mmd_by_quadrature(a, 1.1, 0.02), rel=1e-6)
    # two test inputs, repeats grouped by X; result is the average over inputs
    b = np.array([2.0, 2.4])
    got2 = mmd(np.r_[a, b], np.r_[np.full(3, 1.1), np.full(2, 2.1)],
               np.r_[np.full(3, 0.02), np.full(2, 0.05)], X=np.r_[0, 0, 0, 1, 1.0])
    want2 = 0.5 * (_mmd_by_quadrature(a, 1.1, 0.02) + _mmd_by_quadrature(b, 2.1, 0.05))
    assert got2 == pytest.approx(want2, rel=1e-6)


@pytest.mark.parametrize("fn, args, match", [
    (nmse, ([], []), "target is empty"),
    (nmse, ([1.0, np.nan], [1.0, 2.0]), "target contains 1 NaN"),
    (lpl, ([1.0, 2.0], [1.0, np.inf], [1.0, 1.0]), "mean contains 1 NaN"),
    (coverage, (np.ones((2, 2, 2)),) * 3, r"shape \(N,\) or \(N, n_out\)"),
    (mmd, ([1.0, 2.0], [1.0, 2.0], [np.nan, 1.0]), "var contains 1 NaN"),
    (mmd, ([1.0, 2.0], [1.0, 2.0, 3.0], [1.0, 1.0]), "same shape as the targets"),
])
def test_bad_input(fn, args, match):
    with pytest.raises(ValueError, match=match):
        fn(*args)


def test_mmd_grows_with_predictive_bias():
    a = np.array([0.0, 0.1, -0.1, 0.05])
    vals = [mmd(a, np.full(4, shift), np.full(4, 0.01), X=np.zeros(4)) for shift in (0, 0.2, 1)]
    assert vals[0] < vals[1] < vals[2]
    with pytest.raises(ValueError, match="one row per target"):
        mmd(a, a, np.ones(4), X=np.zeros(3))


def _mmd_loop(target, mean, var, X):
    """The per-input loop that the batched MMD replaced: one test input (a group of equal
    rows of X) at a time, closed-form Gaussian terms, per output."""
    labels = np.unique(X, axis=0, return_inverse=True)[1].ravel()
    out = []
    for o in range(target.shape[1]):
        vals = []
        for g in np.unique(labels):
            a = target[labels == g, o]
            mu, s2 = mean[labels == g, o].mean(), var[labels == g, o].mean()
            q = max(a.size, 20)
            pooled = np.r_[a, mu + np.sqrt(s2) * norm.ppf((np.arange(q) + 0.5) / q)]
            ell2 = np.median([abs(x - y) for i, x in enumerate(pooled)
                              for y in pooled[i + 1:]]) ** 2
            kaa = np.mean([[np.exp(-(x - y) ** 2 / (2 * ell2)) for y in a] for x in a])
            kay = np.mean([np.sqrt(ell2 / (ell2 + s2)) * np.exp(-(x - mu) ** 2 / (2 * (ell2 + s2)))
                           for x in a])
            kyy = np.sqrt(ell2 / (ell2 + 2 * s2))
            vals.append(np.sqrt(max(kaa - 2 * kay + kyy, 0.0)))
        out.append(np.mean(vals))
    return np.array(out)


def test_batched_mmd_matches_the_per_input_loop(monkeypatch):
    """Groups of 1, 2, 3 and 25 repeats in shuffled row order, two outputs, and more groups
    than one chunk: the batched MMD equals the loop to 1e-12."""
    import mdcore._metrics as metrics
    monkeypatch.setattr(metrics, "MMD_CHUNK", 7)
    rng = np.random.default_rng(3)
    sizes = [1] * 12 + [2] * 9 + [3] * 5 + [25] * 2
    X = np.repeat(np.arange(len(sizes), dtype=float), sizes)[:, None]
    X = X[rng.permutation(X.shape[0])]
    n = X.shape[0]
    target = rng.normal(size=(n, 2))
    mean = target + rng.normal(scale=0.5, size=(n, 2))
    var = rng.uniform(0.01, 2.0, size=(n, 2))
    got = mmd(target, mean, var, X=X)
    np.testing.assert_allclose(got, _mmd_loop(target, mean, var, X), rtol=1e-12)
    # every row its own input (X omitted)
    single = mmd(target[:, 0], mean[:, 0], var[:, 0])
    want = _mmd_loop(target[:, :1], mean[:, :1], var[:, :1], np.arange(n)[:, None])[0]
    assert single == pytest.approx(want, rel=1e-12)
