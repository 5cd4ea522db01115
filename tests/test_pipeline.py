"""The typed pipeline: Method, Settings, run_method and its diagnostics, cancel, bad input."""

import dataclasses
import threading
import warnings

import numpy as np
import pytest

from mdcore import Cancelled, LowESSWarning
from mdcore import _cases as cases
from mdcore._history_matching import history_match_case
from mdcore._metrics import coverage, lpl, mmd, nmse
from mdcore._pipeline import (
    INTERACTIVE_FIT_ITERATIONS,
    ChainDiagnostics,
    Method,
    MethodKey,
    Settings,
    _union,
    importance_diagnostics,
    metric_text,
    metrics_table,
    run_method,
    scores,
)

SMALL = Settings(n_s=30, n_phi=20, n_iter=3000, burn_in=1000)


@pytest.fixture(scope="module")
def beam():
    case = cases.load("beam-1d", seed=0)
    return case, history_match_case(case, n_candidates=20_000, seed=0)


def quiet(fn, *args, **kwargs):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return fn(*args, **kwargs)


# ---------------------------------------------------------------------------------------
# Method and Settings

def test_method_parse_and_labels():
    assert [Method.parse(v) for v in (1, "2", " 3 ", "KOH", Method.S1)] == \
        [Method.S1, Method.S2, Method.S3, Method.KOH, Method.S1]
    assert [m.label for m in Method] == ["Scenario 1", "Scenario 2", "Scenario 3", "KOH"]
    assert [m.scenario for m in Method] == [1, 2, 3, None] and str(Method.KOH) == "koh"
    for bad in (4, "kennedy", True, None, 2.5):
        with pytest.raises(ValueError, match="is not a valid method. It must be one of"):
            Method.parse(bad)


def test_settings_validate_and_key_only_what_matters():
    s = Settings(n_s=10, n_phi=5, n_iter=100, burn_in=10)
    assert s.key(1) == MethodKey(Method.S1, None, None, None, None, None, None, 120)
    assert s.key("2") == MethodKey(Method.S2, 10, None, None, None, None, None, 120)
    assert s.key(3) == MethodKey(Method.S3, 10, 5, None, None, 1e-12, "prior", None)
    assert s.key("koh") == MethodKey(Method.KOH, None, None, 100, 10, None, None, None)
    other = Settings(n_s=99, n_phi=5, n_iter=100, burn_in=10)
    assert s.key(1) == other.key(1) and s.key("koh") == other.key("koh")
    assert s.key(3) != other.key(3)
    assert len({s.key(m) for m in Method} | {other.key(m) for m in Method}) == 6   # hashable
    assert hash(s) == hash(Settings(n_s=10, n_phi=5, n_iter=100, burn_in=10))
    assert Settings.paper("beam-2d").n_phi == 1000 and Settings.interactive().n_iter == 20_000
    with pytest.raises(dataclasses.FrozenInstanceError):
        s.n_s = 3                                           # type: ignore[misc]
    cases_ = [(dict(n_s=0), "n_s must be an integer ≥ 1; received 0"),
              (dict(n_phi=2.5), "n_phi must be an integer ≥ 1"),
              (dict(n_iter=100, burn_in=100), "burn_in must be smaller than n_iter"),
              (dict(prune=1.0), r"prune must be in \[0, 1\)"),
              (dict(prune=float("nan")), r"prune must be in \[0, 1\)"),
              (dict(n_s=True), "n_s must be an integer")]
    for kwargs, match in cases_:
        with pytest.raises(ValueError, match=match):
            Settings(**kwargs)


# ---------------------------------------------------------------------------------------
# run_method

def test_scenario3_predictions_metrics_and_importance_against_references(beam):
    case, hm = beam
    grid = np.linspace(0.1, 0.9, 7)[:, None]
    r = quiet(run_method, case, hm, Method.S3, SMALL, seed=1, X_extra=grid)
    assert r.method is Method.S3 and r.key == SMALL.key(3) and r.seed == 1 and r.chain is None
    # Predictions: the same model's predict at each input set.
    direct_test = quiet(r.model.predict, case.X_test)
    direct_grid = quiet(r.model.predict, grid)
    for a, b in zip(r.on_test, direct_test):
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-14)
    for a, b in zip(r.on_extra, direct_grid):
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-14)
    # Metrics: the metric functions on the test prediction.
    p, z, d = r.on_test, case.z_test, case.true_delta(case.X_test)
    np.testing.assert_allclose(r.metrics.nmse_z, nmse(z, p.z_mean), rtol=1e-12)
    np.testing.assert_allclose(r.metrics.mmd, mmd(z, p.z_mean, p.z_var, X=case.X_test),
                               rtol=1e-12)
    np.testing.assert_allclose(r.metrics.lpl, lpl(z, p.z_mean, p.z_var), rtol=1e-12)
    np.testing.assert_allclose(r.metrics.coverage_delta_3sd,
                               coverage(d, p.delta_mean, p.delta_var, k=3))
    np.testing.assert_allclose(r.metrics.rmse_delta,
                               np.sqrt(np.mean((d - p.delta_mean) ** 2, axis=0)), rtol=1e-12)
    np.testing.assert_allclose(r.metrics.sd_delta, np.mean(np.sqrt(p.delta_var), axis=0))
    np.testing.assert_allclose(r.metrics.sd_z, np.mean(np.sqrt(p.z_var), axis=0))
    assert r.metrics == scores(case, p)
    # Importance diagnostics against a plain (linear-space) loop over θ.
    w = np.exp(r.model.log_weights[0])                            # (S, K)
    ess_phi = 0.0
    for j in range(w.shape[0]):
        wj = w[j].sum()
        if wj > 0:
            ess_phi += wj / np.sum((w[j] / wj) ** 2)
    imp = r.importance
    assert imp.n_pairs == 30 * 20 and imp.n_phi == 20
    np.testing.assert_allclose(imp.ess[0], 1.0 / np.sum(w ** 2), rtol=1e-9)
    np.testing.assert_allclose(imp.ess_phi[0], ess_phi, rtol=1e-9)
    assert 1.0 <= imp.ess_phi[0] <= 20.0
    assert imp.low == (imp.ess[0] < 30.0,)
    assert importance_diagnostics(r.model) == imp


def test_extra_inputs_that_are_test_inputs_are_predicted_once(beam):
    """A plotting grid holding test inputs (beam-2d's is its test grid): those rows are the
    test prediction itself, the others the model's prediction there, in the grid's order."""
    case, hm = beam
    new_points = np.array([[0.123], [0.5555], [0.123]])
    grid = np.vstack([case.X_test[[17, 3]], new_points, case.X_test[[3]]])
    X_all, rows = _union(grid, case.X_test)
    assert X_all.shape == (3 + case.X_test.shape[0], 1)       # the new points, then X_test
    np.testing.assert_array_equal(X_all[:3], new_points)
    np.testing.assert_array_equal(X_all[rows], grid)
    r = quiet(run_method, case, hm, Method.S3, SMALL, seed=1, X_extra=grid)
    direct = quiet(r.model.predict, grid)
    for extra, test, d in zip(r.on_extra, r.on_test, direct):
        assert extra.shape == (6, 1)
        np.testing.assert_array_equal(extra[[0, 1, 5]], test[[17, 3, 3]])
        np.testing.assert_allclose(extra, d, rtol=1e-10, atol=1e-14)
    none_new, rows = _union(case.X_test[::-1], case.X_test)
    np.testing.assert_array_equal(none_new, case.X_test)
    np.testing.assert_array_equal(rows, np.arange(case.X_test.shape[0])[::-1])


def test_scenarios_1_and_2_have_no_importance_diagnostics_and_reuse_phi_hat(beam):
    case, hm = beam
    r1 = quiet(run_method, case, hm, 1, SMALL, seed=0)
    assert r1.importance is None and r1.chain is None and r1.warnings == ()
    np.testing.assert_array_equal(r1.model.theta, hm.theta_map[None])
    r2 = quiet(run_method, case, hm, 2, SMALL, seed=0)
    r2_hat = quiet(run_method, case, hm, 2, SMALL, seed=0,
                   log_params_hat=r1.model.log_params_hat)
    np.testing.assert_array_equal(r2.model.log_params_hat, r1.model.log_params_hat)
    for a, b in zip(r2.on_test, r2_hat.on_test):
        np.testing.assert_array_equal(a, b)
    assert r2.model.theta.shape == (30, 2)


def test_fit_iterations_reach_the_fit_and_the_apps_short_swarm_finds_the_same_phi_hat(beam):
    """``Settings.fit_iterations`` is the φ̂ fit's swarm length; the app's 30 steps, then the
    L-BFGS-B polish, end at the 120-step optimum (to the polish's tolerance)."""
    case, hm = beam
    full = quiet(run_method, case, hm, 1, SMALL, seed=0)
    short_settings = dataclasses.replace(SMALL, fit_iterations=INTERACTIVE_FIT_ITERATIONS)
    short = quiet(run_method, case, hm, 1, short_settings, seed=0)
    assert short.key != full.key and short.key.fit_iterations == 30
    a, b = full.model.log_params_hat, short.model.log_params_hat
    assert not np.array_equal(a, b)                       # another swarm ...
    np.testing.assert_allclose(b, a, rtol=0, atol=1e-3)   # ... the same optimum
    np.testing.assert_allclose(short.model.nlml_hat, full.model.nlml_hat, rtol=0, atol=1e-5)
    assert Settings.interactive().fit_iterations == INTERACTIVE_FIT_ITERATIONS
    with pytest.raises(ValueError, match="fit_iterations must be an integer ≥ 1; received 0"):
        Settings(fit_iterations=0)


def test_koh_chain_diagnostics_and_advice(beam):
    case, hm = beam
    r = quiet(run_method, case, hm, "koh", SMALL, seed=0)
    assert r.importance is None and isinstance(r.chain, ChainDiagnostics)
    c = r.chain
    assert c.n_iter == 3000 and c.burn_in == 1000 and 0 < c.acceptance_rate < 1
    np.testing.assert_allclose(np.array(c.ess) * np.array(c.iat), 2000.0)
    assert c.reliable == bool(np.all(2000 > 50 * np.array(c.iat)))
    short = quiet(run_method, case, hm, "koh", Settings(n_iter=120, burn_in=20), seed=0)
    assert not short.chain.reliable
    assert any("raise n_iter to at least" in w for w in short.warnings)


def test_low_ess_gives_advice_in_words(beam):
    case, hm = beam
    with pytest.warns(LowESSWarning) as caught:
        r = run_method(case, hm, 3, Settings(n_s=2, n_phi=2), seed=0)
    assert r.importance.ess[0] < 30
    assert len(r.warnings) == 1 and "raise N_φ (now 2) or N_s (now 2)" in r.warnings[0]
    # Worded once: the core's warning and the result's advice are the same text, and a
    # single-output case names no output.
    assert r.warnings[0] in {str(w.message) for w in caught}
    assert "output" not in r.warnings[0]


def test_progress_and_cancel(beam):
    case, hm = beam
    seen = []
    quiet(run_method, case, hm, 3, SMALL, seed=0,
          progress=lambda f, msg: seen.append((f, msg)))
    fractions = [f for f, _ in seen]
    assert fractions == sorted(fractions) and 0.0 <= fractions[0] and fractions[-1] == 1.0
    assert any("predicting" in m for _, m in seen)
    cancel = threading.Event()
    cancel.set()
    with pytest.raises(Cancelled, match="Scenario 3 on beam-1d was cancelled"):
        run_method(case, hm, 3, SMALL, seed=0, cancel=cancel)
    for method in (3, "koh"):                         # set while running: stops at a chunk
        cancel = threading.Event()
        calls = []

        def progress(f, msg, cancel=cancel, calls=calls):
            calls.append(f)
            if len(calls) == 2:
                cancel.set()

        with pytest.raises(Cancelled):
            quiet(run_method, case, hm, method, SMALL, seed=0, progress=progress,
                  cancel=cancel)
        assert len(calls) == 2


def test_seed_is_reproducible_and_accepts_a_generator(beam):
    case, hm = beam
    a = quiet(run_method, case, hm, 3, SMALL, seed=3)
    b = quiet(run_method, case, hm, 3, SMALL, seed=3)
    np.testing.assert_array_equal(a.on_test.delta_mean, b.on_test.delta_mean)
    g1 = quiet(run_method, case, hm, 3, SMALL, seed=np.random.default_rng(5))
    g2 = quiet(run_method, case, hm, 3, SMALL, seed=np.random.default_rng(5))
    assert g1.seed == g2.seed
    np.testing.assert_array_equal(g1.on_test.delta_mean, g2.on_test.delta_mean)


def test_bad_input(beam):
    case, hm = beam
    ruled_out = history_match_case(case, V_m=1e-8, threshold=0.1, n_candidates=2000, seed=0)
    assert ruled_out.status == "ruled_out"
    other = cases.load("beam-2d")
    bad = [((case, ruled_out, 1, SMALL), {}, "ruled out every θ.*Raise V_m"),
           (("beam-1d", hm, 1, SMALL), {}, "case must be an mdcore Case"),
           ((case, None, 1, SMALL), {}, "hm must be a HistoryMatchResult"),
           ((case, hm, 1, {"n_s": 3}), {}, "settings must be a pipeline.Settings"),
           ((case, hm, 5, SMALL), {}, "5 is not a valid method"),
           ((other, hm, 1, SMALL), {}, "hm does not belong to beam-2d"),
           ((case, hm, 1, SMALL), {"X_extra": np.zeros((3, 2))},
            r"X_extra must have shape \(M, d_x\) with d_x = 1"),
           ((case, hm, 1, SMALL), {"X_extra": [[np.nan]]}, "X_extra contains 1 NaN"),
           ((case, hm, 1, SMALL), {"seed": -2}, "seed must be an integer from 0 to 2..63 − 1")]
    for args, kwargs, match in bad:
        kwargs = {"seed": 0, **kwargs}
        with pytest.raises(ValueError, match=match):
            run_method(*args, **kwargs)


def test_metrics_table_is_the_results_numbers_per_output(beam):
    """One row per (method, output) carrying each result's own numbers; None (shown "—")
    where a number does not apply: scenario 3's diagnostics elsewhere, KOH's chain's."""
    case, hm = beam
    results = [quiet(run_method, case, hm, m, SMALL, seed=0) for m in (3, "koh")]
    rows = metrics_table(results, case.output_names)
    assert [(r["method"], r["output"]) for r in rows] == [(Method.S3, "tip deflection"),
                                                         (Method.KOH, "tip deflection")]
    s3, koh = rows
    m = results[0].metrics
    assert s3["NMSE z %"] == m.nmse_z[0] and s3["cover δ ±2σ"] == m.coverage_delta_2sd[0]
    assert s3["ESS φ"] == results[0].importance.ess_phi[0] and s3["acceptance"] is None
    assert koh["ESS pairs"] is None and koh["IAT (max)"] == max(results[1].chain.iat)
    assert s3["unreliable"] == results[0].importance.low[0] and not koh["unreliable"]
    assert metric_text("k̂", None) == "—" and metric_text("LPL", 12.345) == "12.3"


def test_one_v_m_scales_by_the_squared_output_means():
    case = cases.load("shear-5")
    zbar = case.z_train.mean(axis=0)
    v = case.scaled_v_m(0.2)
    np.testing.assert_allclose(v, [0.2 * (zbar[i] / zbar[0]) ** 2 for i in range(5)],
                               rtol=1e-14)
    # shear-5's own default is this rule at 3 % of each mean
    np.testing.assert_allclose(case.scaled_v_m(case.V_m[0]), case.V_m, rtol=1e-12)
