"""The compiled (numba) kernels against the NumPy implementation of record.

Agreement is by tolerance, never bit for bit: rtol 1e-8 on NLMLs, log weights, chains and
the mixture moments (moments relative to their largest magnitude, since a latent variance
near a training point is a difference of O(σ_f²) numbers). Jitter steps, failures and
their warnings must match. One looser tolerance, on shear-5 (see its test): its φ prior
reaches covariances with condition numbers near 1e14, where any two correct orders of
summation differ far above rounding.
"""

import subprocess
import sys
import threading
import warnings

import numpy as np
import pytest

pytest.importorskip("numba")

from mdcore import _cases as cases  # noqa: E402
from mdcore import _compiled as compiled
from mdcore import _gp as gp
from mdcore import _linalg as linalg
from mdcore._discrepancy import DiscrepancyOptions, _mixture_chunk, infer_discrepancy  # noqa: E402
from mdcore._exceptions import NumericalWarning  # noqa: E402
from mdcore._history_matching import history_match_case  # noqa: E402

RTOL = 1e-8


def random_pairs(rng, N, d_y, d_x, B=40, S=4, n_z=1):
    X = rng.uniform(size=(N, d_x))
    Y = rng.normal(size=(S, N, d_y))
    theta = rng.normal(scale=0.4, size=(B, 2 + d_y + d_x))
    theta[:, -1] = rng.uniform(-3, -1, size=B)
    row = np.sort(rng.integers(0, S, size=B))
    z = rng.normal(size=(N, n_z))
    return compiled.Pairs(theta, row, Y, X, z[:, 0] if n_z == 1 else z)


def numpy_nlml(pairs, column=None):
    z = pairs.z if column is None else pairs.z[:, column]
    return gp.neg_log_marginal_likelihood(pairs.theta, pairs.Y[pairs.row], pairs.X, z)


def random_test(rng, pairs, M):
    S, _, d_y = pairs.Y.shape
    Y_star = rng.normal(size=(S, M, d_y))
    w = rng.uniform(size=pairs.theta.shape[0])
    return compiled.Test(Y_star, rng.normal(size=(S, M)), rng.uniform(size=(M, pairs.X.shape[1])),
                         w / w.sum(), rng.normal(size=(2, M)))


@pytest.mark.parametrize("N, d_y, d_x", [(1, 1, 1), (13, 1, 1), (30, 5, 1), (64, 1, 2),
                                         (9, 0, 2), (9, 3, 0)])
def test_nlml_and_mixture_sums_match_numpy(rng, N, d_y, d_x):
    pairs = random_pairs(rng, N, d_y, d_x)
    np.testing.assert_allclose(compiled.nlml(pairs), numpy_nlml(pairs), rtol=RTOL)
    test = random_test(rng, pairs, M=7)
    acc, dropped = compiled.mixture_sums(pairs, test)
    want, bad, _ = _mixture_chunk(pairs, test, "numpy")
    np.testing.assert_array_equal(dropped, bad)
    scale = np.max(np.abs(want), axis=1, keepdims=True)
    np.testing.assert_allclose(acc / scale, want / scale, rtol=0, atol=RTOL)


def test_outputs_share_one_factorisation(rng):
    """Several columns of z share each pair's factor: each column's NLML is NumPy's."""
    pairs = random_pairs(rng, 30, 2, 1, B=200, n_z=3)
    full = compiled.nlml(pairs)
    for c in range(3):
        np.testing.assert_allclose(full[:, c], numpy_nlml(pairs, c), rtol=RTOL)


def test_jitter_ladder_and_failure_like_numpy(rng, monkeypatch):
    """Replicated inputs without noise make singular covariances, which get the jitter
    ladder: whether a given one needs a step is decided by rounding, so each backend counts
    its own. Without the ladder they fail: NLML ``inf``, a warning, no mixture part."""
    X = np.repeat(rng.uniform(size=(4, 1)), 3, axis=0)
    theta = np.tile([0.0, 0.0, 0.0, -40.0], (30, 1))
    theta[:, 1:3] = rng.uniform(-1, 1, size=(30, 2))
    pairs = compiled.Pairs(theta, np.zeros(30, int), np.sin(3 * X)[None], X, np.sin(4 * X[:, 0]))
    logs = [linalg.JitterLog(), linalg.JitterLog()]
    got = compiled.nlml(pairs, logs[0])
    want = gp.neg_log_marginal_likelihood(theta, pairs.Y[pairs.row], X, pairs.z,
                                          jitter_log=logs[1])
    assert logs[0].jittered > 0 and logs[1].jittered > 0 and logs[0].failed == logs[1].failed == 0
    assert np.all(np.isfinite(got)) and np.all(np.isfinite(want))
    monkeypatch.setattr(compiled, "JITTER_LADDER", ())
    log = linalg.JitterLog()
    out = compiled.nlml(pairs, log)
    failed = out == np.inf
    assert log.jittered == 0 and log.failed == np.count_nonzero(failed) > 0
    np.testing.assert_array_equal(out[~failed], got[~failed])
    with pytest.warns(NumericalWarning, match="stayed non-positive-definite.*NaN"):
        compiled.nlml(pairs)
    acc, dropped = compiled.mixture_sums(pairs, random_test(rng, pairs, 5), linalg.JitterLog())
    np.testing.assert_array_equal(dropped, failed)
    assert np.all(np.isfinite(acc))


def test_results_do_not_depend_on_the_threads(rng, monkeypatch):
    pairs = random_pairs(rng, 13, 1, 1, B=3000)
    test = random_test(rng, pairs, 11)
    runs = []
    for n in ("1", "2"):
        monkeypatch.setenv("MDCORE_NUM_THREADS", n)
        runs.append((compiled.nlml(pairs), compiled.mixture_sums(pairs, test)[0]))
    for a, b in zip(*runs):
        np.testing.assert_array_equal(a, b)                   # pieces fixed by the sizes
    results = {}

    def call(i):
        results[i] = compiled.nlml(pairs)

    workers = [threading.Thread(target=call, args=(i,)) for i in range(3)]
    [w.start() for w in workers]
    [w.join() for w in workers]
    for i in range(3):
        np.testing.assert_array_equal(results[i], runs[0][0])


def test_warm_up_compiles_one_signature_per_kernel():
    from mdcore import _compiled_kernels as k

    assert compiled.available() and compiled.warm_up() >= 0.0
    assert len(k.pair_range.signatures) == 1, k.pair_range.signatures
    assert len(k.koh_steps.signatures) == 1, k.koh_steps.signatures


def test_package_runs_without_numba():
    """With numba unimportable, mdcore imports, the NumPy path runs, and the compiled path
    says what is missing."""
    code = """
import sys
sys.modules["numba"] = None
import numpy as np
from mdcore import _compiled as compiled, _gp as gp
assert not compiled.available() and compiled.warm_up_in_background() is None
assert compiled.resolve_backend("auto") == "numpy"
X = np.linspace(0, 1, 5)[:, None]
print(float(gp.neg_log_marginal_likelihood([0.0, 0.0, 0.0, -2.0], np.sin(3 * X), X, X[:, 0])))
try:
    compiled.warm_up()
except ImportError as exc:
    print("ImportError:", exc)
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=300, check=True).stdout
    assert "ImportError: the compiled path needs numba" in out


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
        DiscrepancyOptions(backend="gpu")
    monkeypatch.setattr(compiled, "available", lambda: False)
    with pytest.raises(ValueError, match=r"needs numba.*pip install 'mdcore\[fast\]'"):
        compiled.resolve_backend("numba")


# ---------------------------------------------------------------------------------------
# Scenario 3 and the KOH chain, end to end


def posterior(name, n):
    case = cases.load(name)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        hm = history_match_case(case, seed=0, n_candidates=5000)
    return case, hm


@pytest.fixture(scope="module")
def beam1d():
    case, hm = posterior("beam-1d", 60)
    return case, hm.posterior_samples(60, seed=1)


def both_backends(case, theta, **options):
    out = {}
    for backend in ("numpy", "numba"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            model = infer_discrepancy(
                case.simulate, theta, case.X_train, case.z_train, scenario=3, seed=4,
                options=DiscrepancyOptions(phi_prior=case.phi_prior, backend=backend,
                                           **options))
            out[backend] = model, model.predict(case.X_test, prune=1e-8)
    return out["numpy"], out["numba"]


def assert_same_scenario_3(ref, new, rtol, level=1e-8):
    """Log weights of the pairs above ``level`` × the largest, and the predictions."""
    (m0, p0), (m1, p1) = ref, new
    kept = m0.log_weights > m0.log_weights.max() + np.log(level)
    np.testing.assert_allclose(m1.log_weights[kept], m0.log_weights[kept], rtol=rtol)
    for name in p0._fields:
        want, got = getattr(p0, name), getattr(p1, name)
        scale = np.max(np.abs(want), axis=0)
        np.testing.assert_allclose(got / scale, want / scale, rtol=0, atol=rtol, err_msg=name)


@pytest.mark.parametrize("proposal", ["prior", "adaptive"])
def test_scenario_3_is_the_same_on_both_backends(beam1d, proposal):
    """The adaptive proposal's later stages are fitted to the weights, so its draws carry
    the weights' rounding differences too; the prior's draws are identical."""
    case, theta = beam1d
    ref, new = both_backends(case, theta, n_phi=30, proposal=proposal)
    assert_same_scenario_3(ref, new, RTOL)
    if proposal == "prior":
        np.testing.assert_array_equal(new[0].log_params, ref[0].log_params)


def test_scenario_3_on_shear_5_agrees_to_its_conditioning():
    """shear-5's φ prior allows lengthscales far above the input range and a nugget of
    ~1e-6 Hz², so some covariances have condition numbers near 1e14: rounding differences
    of 1e-16 between two correct summation orders grow to ~1e-4 in such pairs' log weight
    (seen on pairs of weight 1e-7 of the largest), ~1e-6 in the mixture. The tolerance is
    set by that, not by the kernels: rtol 1e-5 on the pairs above 1e-4 of the largest
    weight and on the predictions."""
    case, hm = posterior("shear-5", 20)
    ref, new = both_backends(case, hm.posterior_samples(20, seed=1), n_phi=40,
                             proposal="prior")
    assert_same_scenario_3(ref, new, 1e-5, level=1e-4)


def test_fused_prediction_reports_progress_and_stops_when_asked(beam1d):
    case, theta = beam1d
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = infer_discrepancy(
            case.simulate, theta, case.X_train, case.z_train, scenario=3, seed=0,
            options=DiscrepancyOptions(n_phi=200, phi_prior=case.phi_prior, backend="numba",
                                       prune=0.0, proposal="prior"))
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


@pytest.mark.parametrize("name", ["beam-1d", "shear-5"])
def test_koh_chain_is_the_python_loop(name):
    """The compiled chain takes the Python loop's random numbers and steps: the same
    chain, acceptance and jitter counts, to rounding."""
    from mdcore._koh import KOHOptions, infer_koh
    from mdcore._pipeline import koh_phi_prior

    case, hm = posterior(name, 0)
    models = {}
    for backend in ("numpy", "numba"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            models[backend] = infer_koh(
                hm.waves[-1].emulator, case.X_train, case.z_train,
                theta_prior=case.theta_prior, bounds=case.theta_bounds, seed=2,
                options=KOHOptions(n_iter=3000, burn_in=1000, phi_prior=koh_phi_prior(case),
                                   backend=backend))
    a, b = models["numpy"].chain, models["numba"].chain
    np.testing.assert_allclose(b.samples, a.samples, rtol=RTOL)
    np.testing.assert_allclose(b.log_target, a.log_target, rtol=RTOL)
    assert (b.acceptance_rate, b.acceptance_rate_burn_in) == \
        (a.acceptance_rate, a.acceptance_rate_burn_in)
    np.testing.assert_allclose(b.proposal_cov, a.proposal_cov, rtol=RTOL)


def test_koh_compiled_chain_stops_when_progress_raises():
    from mdcore._koh import KOHOptions, infer_koh

    case, hm = posterior("beam-1d", 0)
    seen = []

    class Stop(Exception):
        pass

    def progress(fraction):
        seen.append(fraction)
        if fraction > 0.5:
            raise Stop

    with pytest.raises(Stop):
        infer_koh(hm.waves[-1].emulator, case.X_train, case.z_train,
                  theta_prior=case.theta_prior, bounds=case.theta_bounds, progress=progress,
                  options=KOHOptions(n_iter=20_000, burn_in=1000, backend="numba"))
    assert 0.5 < seen[-1] < 0.6 and seen == sorted(seen)
