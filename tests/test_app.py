"""Headless tests of the app: state callbacks, rendering into a Bokeh Document, errors,
caching and supersession."""

import queue
import warnings

import numpy as np
import pytest

pytest.importorskip("panel")
import holoviews as hv  # noqa: E402
import panel as pn  # noqa: E402
from bokeh.document import Document  # noqa: E402
from bokeh.models import GlyphRenderer  # noqa: E402

import mdcore_app.state as state_module  # noqa: E402
from mdcore.history_matching import _in_nroy  # noqa: E402
from mdcore_app.state import ExplorerState  # noqa: E402
from mdcore_app.views import ExplorerView, metrics_frame  # noqa: E402

hv.extension("bokeh")
SMALL = dict(n_candidates=4000, n_s=30, n_phi=8)


def render(view_fn):
    """Render a view callable into a fresh Document; return the root Bokeh model."""
    return pn.panel(view_fn).get_root(Document())


def glyph_data(root):
    return [r.data_source.data for r in root.select({"type": GlyphRenderer})]


def small_state(case="beam-1d", **extra):
    s = ExplorerState()
    s.case_name = case
    s.param.update(**{k: v for k, v in {**SMALL, **extra}.items()})
    return s


def test_first_screen_is_the_paper_fig1():
    s = ExplorerState()
    v = ExplorerView(state=s)
    c = s.case
    assert c.name == "beam-1d"
    data = glyph_data(render(v.data_view))
    xs = [np.asarray(d.get("crack location [m]", d.get("x", []))) for d in data]
    assert any(x.shape == (13,) and np.allclose(x, c.X_train[:, 0]) for x in xs)
    # the simulator at θ_true and the true δ are drawn on a 201-point grid
    ys = [np.asarray(d[k]) for d in data for k in d if k.startswith(("tip deflection",
                                                                       "δ tip deflection"))]
    grid = np.linspace(0.1, 0.9, 201)[:, None]
    assert any(y.shape == (201,) and np.allclose(y, c.simulate(grid, c.theta_true)[0, :, 0])
               for y in ys)
    assert any(y.shape == (201,) and np.allclose(y, c.true_delta(grid)[:, 0]) for y in ys)
    render(v)                                               # the whole page renders


@pytest.mark.parametrize("case", ["beam-1d", "beam-2d", "shear-5"])
def test_waves_then_scenarios_for_each_case(case):
    s = small_state(case, max_waves=3, convergence_ratio=0.05)
    v = ExplorerView(state=s)
    s.next_wave()
    assert len(s.waves) == 1 and s.error == ""
    s.run_to_convergence()
    f = [w.nroy_fraction for w in s.waves]
    assert len(f) >= 2 and all(b <= a + 1e-12 for a, b in zip(f, f[1:]))    # non-increasing
    if case != "shear-5":   # shear-5's V_m = (1 % z̄)² rules out the generating θ (see notes)
        assert _in_nroy(s._problem, s.waves, s.case.theta_true[None])[0]
    assert s.selected_wave == len(s.waves)
    hm = glyph_data(render(v.waves_view))
    assert len(hm) >= len(s.waves)
    if s.case.p == 2:
        assert set(s.implausibility_maps) == {w.index for w in s.waves}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        s.run_discrepancy()
    assert s.error == "" and sorted(s.results) == [1, 2, 3]
    G = s.results[1].grid.shape[0]
    for r in s.results.values():
        assert r.on_grid.z_mean.shape == (G, s.case.n_out)
        assert r.on_test.delta_var.shape == s.case.z_test.shape
        assert np.all(np.isfinite(r.on_grid.delta_mean))
    disc = render(v.discrepancy_view)
    means = [d for d in glyph_data(disc) if d]
    assert len(means) >= 3
    table = metrics_frame(s.case, s.results)
    assert len(table) == 3 * s.case.n_out and np.all(np.isfinite(table["NMSE z [%]"]))


def test_toggling_scenarios_or_band_recomputes_nothing(monkeypatch):
    s = small_state()
    s.run_to_convergence()
    s.run_discrepancy()
    before = dict(s.results)

    def boom(*a, **k):
        raise AssertionError("infer must not run")

    monkeypatch.setattr(state_module, "infer", boom)
    s.band = 2
    s.scenarios = [1, 3]
    assert sorted(s.results) == [1, 3]
    s.scenarios = [1, 2, 3]
    assert all(s.results[k] is before[k] for k in before)
    v = ExplorerView(state=s)
    render(v.discrepancy_view)
    render(v.metrics_view)


def test_changing_n_s_reruns_without_history_matching(monkeypatch):
    s = small_state()
    s.run_to_convergence()
    s.run_discrepancy()
    waves = s.waves

    def no_waves(*a, **k):
        raise AssertionError("history matching must not re-run")

    monkeypatch.setattr(state_module, "next_wave", no_waves)
    s.n_s = 20
    assert s.waves is waves and sorted(s.results) == [1, 2, 3]
    assert s.results[2].model.theta.shape[0] == 20


def test_everything_ruled_out_is_an_error_and_keeps_the_earlier_state():
    s = small_state()
    s.run_to_convergence()
    s.run_discrepancy()
    waves, results, n = s.waves, dict(s.results), s.n_errors
    s.v_m = 1e-7
    s.next_wave()
    assert s.n_errors == n + 1 and "nothing is non-implausible" in s.error
    assert "Raise V_m" in s.error
    assert s.waves is waves and s.results == results and not s.busy
    s.threshold = -1.0
    s.next_wave()
    assert s.n_errors == n + 2 and "threshold T must be a positive number" in s.error
    assert s.waves is waves
    s.param.update(v_m=0.05, threshold=3.0)
    s.next_wave()                                      # still usable afterwards
    assert len(s.waves) == 1


def test_discrepancy_before_any_wave_is_an_error():
    s = ExplorerState()
    s.run_discrepancy()
    assert "Run history matching first" in s.error and s.results == {}


def test_newer_request_supersedes_older_one():
    """Background mode: results reach the state only through ``schedule``; a request that
    is superseded before its results are applied never lands."""
    inbox = queue.Queue()
    s = ExplorerState(background=True, schedule=inbox.put)
    s.param.update(**SMALL)
    s.run_to_convergence()
    _drain(inbox, until=lambda: not s.busy)
    assert len(s.waves) == 1
    s.scenarios = [3]
    s.n_phi = 400                                      # a slower run …
    s.run_discrepancy()
    s.case_name = "beam-2d"                           # … superseded by a case switch
    _drain(inbox, until=lambda: False, timeout=3.0)
    assert s.results == {} and s.case.name == "beam-2d" and s.waves == ()


def _drain(inbox, until, timeout=60.0):
    import time
    end = time.time() + timeout
    while time.time() < end:
        try:
            fn = inbox.get(timeout=0.2)
        except queue.Empty:
            if until():
                return
            continue
        fn()
        if until():
            return


def test_two_sessions_are_independent():
    a, b = small_state(), small_state()
    a.run_to_convergence()
    assert len(a.waves) == 1 and b.waves == () and b.status != a.status
    b.case_name = "shear-5"
    assert a.case.name == "beam-1d"


def test_paper_sizes_switch():
    s = ExplorerState()
    s.paper_sizes = True
    assert (s.n_s, s.n_phi) == (1000, 500)
    s.paper_sizes = False
    assert (s.n_s, s.n_phi) == (state_module.DEFAULT_N_S, state_module.DEFAULT_N_PHI)


def test_low_ess_becomes_a_notice_not_a_failure():
    s = small_state(n_s=5, n_phi=2)
    s.scenarios = [3]
    s.run_to_convergence()
    s.run_discrepancy()
    assert s.n_notices >= 1 and "effective sample size" in s.notice
    assert sorted(s.results) == [3]


def test_reused_phi_hat_follows_the_seed():
    """Scenario 2 reuses a cached scenario-1 φ̂ only when it was fitted with the same seed."""
    a = small_state()
    a.run_to_convergence()
    a.scenarios = [1, 2]
    a.run_discrepancy()
    a.param.update(scenarios=[2], seed=1)
    b = small_state(seed=1)
    b.scenarios = [2]
    b.run_to_convergence()
    b.run_discrepancy()
    np.testing.assert_array_equal(a.results[2].model.log_params_hat,
                                  b.results[2].model.log_params_hat)
    assert a.history_match is a.history_match                  # θ_MAP is not recomputed


def test_koh_is_a_fourth_column(monkeypatch):
    """KOH runs beside scenarios 1–3: its bands, its metrics row and its chain summary."""
    from mdcore import koh
    s = small_state()
    v = ExplorerView(state=s)
    s.run_to_convergence()
    # A short chain keeps the test quick; the app's own default is koh.FAST.
    monkeypatch.setitem(state_module.KOH_CHAINS, "fast", {"n_iter": 3000, "burn_in": 1000})
    updates = []
    s.param.watch(lambda e: updates.append(sorted(e.new, key=state_module.scenario_order)),
                  "results")
    s.scenarios = [1, "koh"]
    s.run_discrepancy()
    assert s.error == "" and list(s.results) == [1, "koh"]
    assert [1] in updates                          # scenario 1 is shown before the chain ends
    r = s.results["koh"]
    assert isinstance(r.model, koh.KOHModel) and r.model.chain.n_iter == 3000
    assert r.on_grid.delta_mean.shape == (r.grid.shape[0], 1)
    assert np.all(np.isfinite(r.on_grid.z_var)) and np.all(r.on_grid.delta_var >= 0)
    # Direct check of the plotted band against the model's own prediction.
    ref = r.model.predict(r.grid)
    np.testing.assert_allclose(r.on_grid.delta_mean, ref.delta_mean, atol=1e-12)
    disc = glyph_data(render(v.discrepancy_view))
    ys = [np.asarray(d[k]) for d in disc for k in d if k.startswith("δ tip deflection")]
    assert any(y.shape == ref.delta_mean[:, 0].shape and np.allclose(y, ref.delta_mean[:, 0])
               for y in ys)
    table = metrics_frame(s.case, s.results)
    assert list(table["scenario"]) == ["scenario 1", "KOH"]
    assert table["ESS"].iloc[1] == pytest.approx(float(np.min(r.model.ess)))
    metrics = v.metrics_view()
    summary = [o for o in metrics.objects if "koh-summary" in o.css_classes][0]
    assert "KOH chain" in summary.object and f"{r.model.acceptance_rate:.2f}" in summary.object
    render(v.metrics_view)
    # The chain setting is part of KOH's cache key only.
    before = s.results[1]
    s.scenarios = [1]
    s.koh_chain = "paper"
    assert s.results == {1: before} and s._key("koh") not in s._cache
