"""Headless tests of the app: state callbacks, rendering into a Bokeh Document, errors,
caching and supersession."""

import queue
import warnings
from itertools import pairwise
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("panel")
import holoviews as hv  # noqa: E402
import panel as pn  # noqa: E402
from bokeh.document import Document  # noqa: E402
from bokeh.models import GlyphRenderer  # noqa: E402
from event_loop import drain  # noqa: E402

import mdcore_app.history_model as history_module  # noqa: E402
import mdcore_app.runs as runs_module  # noqa: E402
import mdcore_app.state as state_module  # noqa: E402
import mdcore_app.views as views_module  # noqa: E402
from mdcore._pipeline import Method  # noqa: E402
from mdcore_app.metrics_view import NOT_APPLICABLE, metrics_frame  # noqa: E402
from mdcore_app.progress_view import STATUS_HEIGHT, progress_panel  # noqa: E402
from mdcore_app.state import ExplorerState  # noqa: E402
from mdcore_app.views import ExplorerView  # noqa: E402

hv.extension("bokeh")
SMALL = {"preset": "paper", "n_candidates": 4000, "n_s": 30, "n_phi": 8}
S123 = [Method.S1, Method.S2, Method.S3]
NA = NOT_APPLICABLE


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
    # the cards switch tabs by these indices in the browser (views.TAB_NAMES)
    assert tuple(t.name for t in v._tabs) == views_module.TAB_NAMES
    c = s.case
    assert c.name == "beam-1d"
    data = glyph_data(render(v.data_view))
    xs = [np.asarray(d.get("x", [])) for d in data]
    assert any(x.shape == (13,) and np.allclose(x, c.X_train[:, 0]) for x in xs)
    # the bars are ±2√(V_o + V_m) about the training data
    (bars,) = [d for d in data if "y0" in d]
    half = 2 * np.sqrt(c.noise_var[0] + s.v_m_vector()[0])
    assert np.allclose(bars["y1"] - c.z_train[:, 0], half)
    assert np.allclose(c.z_train[:, 0] - bars["y0"], half)
    # the simulator at θ_true and the true δ are drawn on a 201-point grid
    ys = [np.asarray(d["y"]) for d in data if "y" in d]
    grid = np.linspace(0.1, 0.9, 201)[:, None]
    assert any(y.shape == (201,) and np.allclose(y, c.simulate(grid, c.theta_true)[0, :, 0])
               for y in ys)
    assert any(y.shape == (201,) and np.allclose(y, c.true_delta(grid)[:, 0]) for y in ys)
    figures = [p.object for p in v.data_view._layout.select(pn.pane.Bokeh)]
    s.v_m = 4 * s.v_m                                       # V_m moves the bars in place
    assert [p.object for p in v.data_view._layout.select(pn.pane.Bokeh)] == figures
    (moved,) = [d for d in glyph_data(render(v.data_view)) if "y0" in d]
    wider = 2 * np.sqrt(c.noise_var[0] + s.v_m_vector()[0])
    assert wider > half and np.allclose(moved["y1"] - c.z_train[:, 0], wider)
    render(v)                                               # the whole page renders


@pytest.mark.parametrize("case", ["beam-1d", "beam-2d", "shear-5"])
def test_waves_then_scenarios_for_each_case(case):
    s = small_state(case)
    s.preset = "paper"                       # the paper's design, refined past docs/method.md §5
    s.param.update(max_waves=3, convergence_ratio=0.01)
    v = ExplorerView(state=s)
    s.next_wave()
    assert len(s.waves) == 1 and s.error == ""
    s.run_to_convergence()
    f = [w.nroy_fraction for w in s.waves]
    assert len(f) >= 2 and all(b <= a + 1e-12 for a, b in pairwise(f))    # non-increasing
    assert s.history_match.contains(s.case.theta_true)[0]     # the truth is never ruled out
    assert s.selected_wave == len(s.waves)
    v._tabs.active = 1                       # the History matching tab: built when shown
    hm = glyph_data(render(v.waves_view))
    assert len(hm) >= len(s.waves)
    if s.case.p == 2:
        assert set(s.implausibility_maps) == {w.index for w in s.waves}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        s.run_discrepancy()
    assert s.error == "" and list(s.results) == S123
    G = s.grid.shape[0]
    for r in s.results.values():
        assert r.on_extra.z_mean.shape == (G, s.case.n_out)
        assert r.on_test.delta_var.shape == s.case.z_test.shape
        assert np.all(np.isfinite(r.on_extra.delta_mean))
    disc = render(v.discrepancy_view)
    means = [d for d in glyph_data(disc) if d]
    assert len(means) >= 3
    table = metrics_frame(s.case, s.results)
    assert len(table) == 3 * s.case.n_out and np.all(np.isfinite(table["NMSE z [%]"]))
    rmse = table.loc[table["method"] == "Scenario 1", "RMSE δ"].astype(float).to_numpy()
    np.testing.assert_allclose(rmse, np.sqrt(np.mean(
        (s.case.true_delta(s.case.X_test) - s.results[Method.S1].on_test.delta_mean) ** 2,
        axis=0)), rtol=1e-12)                             # against the prediction itself
    s3 = table["method"] == "Scenario 3"
    assert np.all(np.isfinite(table.loc[s3, "ESS pairs"].astype(float)))
    assert np.all(np.isfinite(table.loc[s3, "ESS φ"].astype(float)))
    # k̂, as the glossary and the advice write it (the header said "Pareto k")
    np.testing.assert_array_equal(table.loc[s3, "Pareto k̂"].astype(float),
                                  s.results[Method.S3].importance.k_hat)
    assert set(table.loc[~s3, "ESS pairs"]) == {NA}                 # "—", never NaN
    assert set(table["acceptance"]) == {NA}                         # no KOH here
    assert not table.isna().any().any()
    shown = v.metrics_view().objects
    metrics = next(o for o in shown if "metrics-table" in o.css_classes).object
    diagnostics = next(o for o in shown if "diagnostics-table" in o.css_classes).object
    assert "ESS pairs" not in metrics and "NMSE z [%]" in metrics
    assert list(diagnostics["method"]) == ["Scenario 3"] * s.case.n_out


def test_toggling_scenarios_or_band_recomputes_nothing(monkeypatch):
    s = small_state()
    s.run_to_convergence()
    s.run_discrepancy()
    before = dict(s.results)

    def boom(*a, **k):
        raise AssertionError("infer must not run")

    monkeypatch.setattr(runs_module, "run_method", boom)
    s.band = 2
    s.scenarios = [Method.S1, Method.S3]
    assert list(s.results) == [Method.S1, Method.S3]
    s.scenarios = S123
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

    monkeypatch.setattr(history_module, "next_wave", no_waves)
    s.n_s = 20
    assert s.waves is waves and list(s.results) == S123
    assert s.results[Method.S2].model.theta.shape[0] == 20


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
    with pytest.raises(ValueError, match="greater than 0"):   # the field reports it
        s.threshold = -1.0
    assert s.waves is waves and s.threshold == 3.0
    s.param.update(v_m=0.05, threshold=3.0)
    s.next_wave()                                      # still usable afterwards
    assert s.waves is waves and s.status.startswith("Already converged")
    s.v_m = 0.06
    s.next_wave()
    assert len(s.waves) == 1 and s.waves[0].index == 1     # a new match, wave 1


def test_discrepancy_before_any_wave_runs_the_history_match_first():
    """The app knows what a request needs: on a fresh case, "Run discrepancy" runs the
    waves to convergence, then the methods, and the outcome equals doing it by hand."""
    s = small_state(scenarios=[Method.S1])
    notes = []
    s.param.watch(lambda e: notes.append(e.new), "status")
    s.run_discrepancy()
    assert s.error == "" and list(s.results) == [Method.S1]
    assert any("running the waves until convergence" in n for n in notes)
    assert s.waves[-1].done
    by_hand = small_state(scenarios=[Method.S1])
    by_hand.run_to_convergence()
    by_hand.run_discrepancy()
    assert len(by_hand.waves) == len(s.waves)
    np.testing.assert_array_equal(by_hand.results[Method.S1].on_test.delta_mean,
                                  s.results[Method.S1].on_test.delta_mean)


def test_next_wave_after_convergence_is_a_calm_status():
    s = small_state()
    s.run_to_convergence()
    n = len(s.waves)
    s.next_wave()
    assert s.error == "" and len(s.waves) == n
    assert s.status.startswith(f"Already converged after {n} wave(s)")


def test_newer_request_supersedes_older_one():
    """Background mode: results reach the state only through ``schedule``; a request that
    is superseded before its results are applied never lands."""
    inbox = queue.Queue()
    s = ExplorerState(background=True, schedule=inbox.put)
    s.param.update(**SMALL)
    s.run_to_convergence()
    drain(inbox, timeout=120.0, until=lambda: not s.busy)
    assert len(s.waves) == 1
    s.scenarios = [Method.S3]
    s.n_phi = 400                                      # a slower run …
    s.run_discrepancy()
    job = s.jobs.job
    s.case_name = "beam-2d"                           # … superseded by a case switch
    assert job.status == "superseded" and job.cancel.is_set() and not s.busy
    drain(inbox, timeout=120.0, until=lambda: job.wait(0) and inbox.empty())
    assert s.results == {} and s.case.name == "beam-2d" and s.waves == ()
    assert s.error == ""


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
    assert (s.n_s, s.n_phi) == (runs_module.DEFAULT_N_S, runs_module.DEFAULT_N_PHI)


def test_low_ess_becomes_a_notice_not_a_failure():
    s = small_state(n_s=5, n_phi=2)
    s.scenarios = [Method.S3]
    s.run_to_convergence()
    s.run_discrepancy()
    assert s.n_notices == 1 and "importance weights are unreliable" in s.notice
    assert "raise N_φ" in s.notice and s.error == ""
    assert list(s.results) == [Method.S3]
    # ... and it stays beside the band in the Discrepancy tab (issue 16).
    panel = ExplorerView(state=s).discrepancy_view
    text = panel.message
    assert "importance weights are unreliable" in text and "raise N_φ" in text
    assert "mdcore-alert-warning" in text and text.count("<b>") == 1   # subject in bold


def test_advice_is_a_toast_only_away_from_the_discrepancy_tab(monkeypatch):
    """The Discrepancy tab shows a result's advice beside the bands; a toast there would say
    it twice (one notification per event), elsewhere it says that there is advice."""
    toasts = []

    class Toasts:
        def warning(self, message, duration):
            toasts.append(message)

    monkeypatch.setattr(type(pn.state), "notifications", property(lambda self: Toasts()))
    s = small_state(n_s=5, n_phi=2)
    s.scenarios = [Method.S3]
    view = ExplorerView(state=s)
    s.run_to_convergence()
    view._tabs.active = views_module.DISCREPANCY_TAB
    s.run_discrepancy()
    assert s.n_notices == 1 and toasts == []
    assert "importance weights are unreliable" in view.discrepancy_view.message
    view._tabs.active = 0                                   # the Data tab
    s.seed = 1
    assert s.n_notices == 2 and len(toasts) == 1
    assert "importance weights are unreliable" in toasts[0]


def test_reused_phi_hat_follows_the_seed():
    """Scenario 2 reuses a cached scenario-1 φ̂ only when it was fitted with the same seed."""
    a = small_state()
    a.run_to_convergence()
    a.scenarios = [Method.S1, Method.S2]
    a.run_discrepancy()
    a.param.update(scenarios=[Method.S2], seed=1)
    b = small_state(seed=1)
    b.scenarios = [Method.S2]
    b.run_to_convergence()
    b.run_discrepancy()
    np.testing.assert_array_equal(a.results[Method.S2].model.log_params_hat,
                                  b.results[Method.S2].model.log_params_hat)
    assert a.history_match is a.history_match                  # θ_MAP is not recomputed


def test_a_job_and_the_views_share_one_history_match():
    """θ_MAP and the θ draws a discrepancy job computed are the ones the views read: the
    state's history match is the job's object, not a fresh one that computes them again."""
    s = small_state()
    s.scenarios = [Method.S1, Method.S2]
    s.run_discrepancy()                          # runs the waves, then the methods
    hm = s.history_match
    assert "theta_map" in vars(hm)               # computed by scenario 1, in the job
    assert (s.n_s, s.seed) in hm._posterior_memo  # scenario 2's draws
    s.seed = 1                                   # a new job on the same waves
    assert s.history_match is hm
    assert (s.n_s, 1) in hm._posterior_memo


def test_koh_is_a_fourth_column(monkeypatch):
    """KOH runs beside scenarios 1–3: its bands, its metrics row and its chain summary."""
    from mdcore import _koh as koh
    s = small_state()
    v = ExplorerView(state=s)
    s.run_to_convergence()
    # A short chain keeps the test quick; the app's own default is koh.FAST.
    monkeypatch.setitem(runs_module.KOH_CHAINS, "fast", {"n_iter": 3000, "burn_in": 1000})
    updates = []
    s.param.watch(lambda e: updates.append(list(e.new)), "results")
    s.scenarios = [Method.S1, Method.KOH]
    s.run_discrepancy()
    assert s.error == "" and list(s.results) == [Method.S1, Method.KOH]
    assert [Method.S1] in updates                  # scenario 1 is shown before the chain ends
    r = s.results[Method.KOH]
    assert isinstance(r.model, koh.KOHModel) and r.chain.n_iter == 3000
    assert r.on_extra.delta_mean.shape == (s.grid.shape[0], 1)
    assert np.all(np.isfinite(r.on_extra.z_var)) and np.all(r.on_extra.delta_var >= 0)
    # Direct check of the plotted band against the model's own prediction.
    ref = r.model.predict(s.grid)
    np.testing.assert_allclose(r.on_extra.delta_mean, ref.delta_mean, atol=1e-12)
    disc = glyph_data(render(v.discrepancy_view))
    ys = [np.asarray(d["mean"]) for d in disc if "mean" in d]
    assert any(y.shape == ref.delta_mean[:, 0].shape and np.allclose(y, ref.delta_mean[:, 0])
               for y in ys)
    table = metrics_frame(s.case, s.results)
    assert list(table["method"]) == ["Scenario 1", "KOH"]
    assert table["chain ESS (min)"].iloc[1] == pytest.approx(min(r.chain.ess))
    assert table["IAT (max)"].iloc[1] == pytest.approx(max(r.chain.iat))
    assert table["acceptance"].iloc[1] == pytest.approx(r.chain.acceptance_rate)
    assert table["chain ESS (min)"].iloc[0] == NA and table["ESS pairs"].iloc[1] == NA
    assert not table.isna().any().any()
    metrics = v.metrics_view()
    summary = next(o for o in metrics.objects if "koh-summary" in o.css_classes)
    assert "KOH chain" in summary.object and f"{r.chain.acceptance_rate:.2f}" in summary.object
    render(v.metrics_view)
    # The chain setting is part of KOH's cache key only.
    before = s.results[Method.S1]
    s.scenarios = [Method.S1]
    s.koh_chain = "paper"
    assert s.results == {Method.S1: before} and s._key(Method.KOH) not in s._cache


def test_cache_keys_are_typed_and_hashable():
    """The cache is keyed by NamedTuples: the match, Settings.key(method) and the seed."""
    s = small_state()
    s.run_to_convergence()
    s.scenarios = [Method.S1, Method.S3]
    s.run_discrepancy()
    keys = list(s._cache)
    assert all(isinstance(k, runs_module.ResultKey) for k in keys)
    assert {k.method.method for k in keys} == {Method.S1, Method.S3}
    k3 = next(k for k in keys if k.method.method is Method.S3)
    assert k3.method == s.method_settings().key(Method.S3)
    assert k3.problem.case_name == "beam-1d" and k3.n_waves == len(s.waves) and k3.seed == 0
    assert hash(k3) == hash(runs_module.ResultKey(*k3))
    s.n_phi = 9                                   # scenario 1's key does not hold N_φ …
    assert Method.S1 in s.results and s.results[Method.S3].key.n_phi == 9


def test_case_info_names_the_stand_in_once():
    """shear-5's data are a synthetic stand-in: said once, not "SYNTHETIC — SYNTHETIC"."""
    s = ExplorerState()
    v = ExplorerView(state=s)
    assert not s.case.stand_in and isinstance(v._case_info(), pn.pane.Markdown)
    s.case_name = "shear-5"
    info = v._case_info()
    assert s.case.stand_in and "stand-in" in info.css_classes
    assert info.object.count("SYNTHETIC") == 1


def test_a_case_that_fails_to_load_is_one_error_and_keeps_the_current_case(monkeypatch):
    s = small_state()
    s.next_wave()
    waves, n = s.waves, s.n_errors
    real = state_module.cases.load

    def broken(name, **kwargs):
        if name == "shear-5":
            raise RuntimeError("measurement file is missing")
        return real(name, **kwargs)

    monkeypatch.setattr(state_module.cases, "load", broken)
    s.case_name = "shear-5"
    assert s.n_errors == n + 1 and "measurement file is missing" in s.error
    assert s.case_name == "beam-1d" and s.case.name == "beam-1d" and s.waves is waves


def test_progress_bar_is_always_shown_and_cancel_enabled_only_while_busy(monkeypatch):
    """Issue 41: the bar was ``visibility: hidden`` during long runs. Now the bar and
    Cancel are always in place (nothing a job does changes a layout): the bar holds the
    job's fraction while busy and 0 between jobs, Cancel is enabled only while busy; the
    busy line says busy or idle by a class inside its text, at a fixed height, and names
    the job's step only after SHOW_PROGRESS_AFTER (no flash for short runs)."""
    import mdcore_app.progress_view as progress_module

    s = ExplorerState()
    panel, cancel = progress_panel(s)
    text, row = panel[0], panel[1]
    bar = row[0]
    clock = [100.0]
    monkeypatch.setattr(progress_module.time, "monotonic", lambda: clock[0])
    assert cancel.disabled and bar.value == 0 and not row.styles
    s.param.update(busy=True, task="scenario 1")
    s.param.update(progress=0.5, progress_message="pairs 10 of 20")
    assert not cancel.disabled and bar.value == 50
    assert 'class="mdcore-busy"' in text.object and "scenario 1" in text.object
    assert "pairs" not in text.object                      # a short run: no flash
    s.busy = False
    assert 'class="mdcore-idle"' in text.object and "Idle." in text.object
    assert cancel.disabled and bar.value == 0
    clock[0] += 10.0
    s.param.update(busy=True, task="scenario 3")
    clock[0] += progress_module.SHOW_PROGRESS_AFTER
    s.param.update(progress=0.2, progress_message="pairs 1 of 5 <b>")
    assert bar.value == 20 and not cancel.disabled
    assert "pairs 1 of 5 &lt;b&gt;" in text.object        # messages are text, not HTML
    s.busy = False
    assert [bar.visible, cancel.visible, text.height] == [True, True, STATUS_HEIGHT]
    assert not row.styles and not bar.styles


def test_typed_values_the_parameter_refuses_notify_once_and_revert():
    s = ExplorerState()
    controls = ExplorerView(state=s)._controls()
    fields = {w.label: w for w in controls.select(pn.widgets.Widget) if hasattr(w, "label")}
    t, vm, n_s = fields["Threshold T"], fields["V_m"], fields["N_s (θ samples)"]
    assert t.start is None and t.end is None            # soft bounds are not limits
    t.value = 7.0                                       # beyond the soft range: valid
    assert s.threshold == 7.0 and s.n_errors == 0
    for field, bad, name in ((t, 0.0, "threshold"), (vm, -0.05, "v_m"), (n_s, 0, "n_s"),
                             (t, None, "threshold")):
        before, errors = getattr(s, name), s.n_errors
        field.value = bad
        assert s.n_errors == errors + 1, (name, bad)
        assert getattr(s, name) == before and field.value == before
        assert field.label in s.error and "is not allowed" in s.error
        assert "ExplorerState" not in s.error and name not in s.error   # plain words
    s.v_m = 0.1                                         # the state moves the field too
    assert vm.value == 0.1 and s.n_errors == 4


@pytest.mark.parametrize("case, waves", [("beam-1d", (3, 5)), ("beam-2d", (3, 5))])
def test_the_teaching_preset_shows_waves_shrinking(case, waves):
    """The default preset: a few wave-1 runs, so 3–5 waves each cut NROY, and the true θ
    stays non-implausible; the paper preset converges after one wave."""
    s = ExplorerState()
    s.case_name = case
    assert s.preset == "teaching"
    s.run_to_convergence()
    f = [w.nroy_fraction for w in s.waves]
    assert waves[0] <= len(f) <= waves[1] and s.waves[-1].status == "converged"
    assert all(b < a for a, b in pairwise(f)) or f[-1] < 0.8 * f[0]
    assert all(b <= a + 1e-12 for a, b in pairwise(f))
    assert s.history_match.contains(s.case.theta_true)[0]
    assert len(s.waves[0].runs_theta) <= 4
    s.preset = "paper"
    assert (s.n_runs, s.convergence_ratio) == (max(10, 5 * s.case.p), 1.0)
    s.run_to_convergence()
    assert len(s.waves) == 1 and len(s.waves[0].runs_theta) == s.case.initial_design.shape[0]


def test_a_card_builds_its_tab_once_from_its_own_settings(monkeypatch):
    """A card showed its tab before it ran: the tab's stale views were rebuilt from the
    settings before the card, then again from the card's, and the card's answer waited
    for the first rebuild (docs/performance.md, "A card's click").
    The card now runs first and shows its tab after."""
    from mdcore_app.experiments import EXPERIMENTS
    s = small_state("beam-1d")
    v = ExplorerView(state=s)
    s.run_discrepancy()                             # results on the Metrics tab, not shown
    built = []
    panel = views_module.metrics_panel
    monkeypatch.setattr(views_module, "metrics_panel",
                        lambda state: built.append(dict(state.results)) or panel(state))
    v._tabs.active = views_module.TAB_NAMES.index("Things to try")
    ess = next(e for e in EXPERIMENTS if e.key == "ess")
    v._try(ess)
    assert v._tabs.active == views_module.TAB_NAMES.index("Metrics")
    assert s.card.startswith(ess.title) and s.results
    assert len(built) == 1, built


def test_things_to_try_set_the_controls_and_say_what_to_press():
    from mdcore_app.experiments import EXPERIMENTS
    s = ExplorerState()
    for exp in EXPERIMENTS:
        s.try_experiment(exp.key)
        assert s.case_name == exp.settings["case_name"] and s.error == ""
        for name, value in exp.settings.items():
            assert getattr(s, name) == value, (exp.key, name)
        assert s.card.startswith(exp.title) and s.card.endswith(exp.look)
        assert exp.look not in s.status            # said once: the card line, on every tab
    assert s.case_name == "shear-5" and "switched the case from beam-1d to shear-5" in s.card
    s.case_name = "beam-1d"                     # the line is for the card's case only
    assert s.card == ""
    s.try_experiment("rule-out")
    s.run_to_convergence()                 # the experiment does what it says
    assert "nothing is non-implausible" in s.error or not s.history_match.contains(
        s.case.theta_true)[0]
    s.try_experiment("nope")
    assert "Unknown experiment 'nope'" in s.error


def test_the_papers_missing_views_have_data():
    """θ_MAP in numbers and on the plots, the weighted θ posterior, the simulator at θ_MAP,
    scenario 3's φ posterior against its prior, and the metrics chart."""
    s = small_state()
    v = ExplorerView(state=s)
    s.scenarios = S123
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        s.run_discrepancy()
    hm = s.history_match
    v._tabs.active = 1                       # the History matching tab: built when shown
    cal = pn.panel(v.calibration_view)
    root = cal.get_root(Document())
    from bokeh.models import Div
    text = " ".join(d.text for d in root.select({"type": Div}))
    assert f"l_cr = {hm.theta_map[0]:.4g} mm" in text and "θ_MAP" in text
    data = [d for d in glyph_data(root) if d]
    assert len(data) >= 2 * s.case.p + 1
    stars = [[d["t0"][0], d["t1"][0]] for d in glyph_data(render(v.waves_view))
             if set(d) == {"t0", "t1"} and len(d["t0"]) == 1]          # θ_MAP's marker
    assert stars and all(np.array_equal(pt, hm.theta_map) for pt in stars)
    metrics = pn.panel(v.metrics_view)
    mroot = metrics.get_root(Document())
    assert [o for o in metrics.select(pn.pane.Bokeh) if "metrics-chart" in o.object.css_classes]
    phi = [o for o in metrics.select(pn.pane.Bokeh) if "phi-plot" in o.object.css_classes]
    assert len(phi) == s.case.phi_prior.mean.size               # one per φ component
    assert all(d for d in glyph_data(mroot))


def test_shear5_teaching_keeps_its_own_design():
    s = ExplorerState()
    s.case_name = "shear-5"
    s.param.update(n_candidates=20_000)
    s.next_wave()
    assert len(s.waves[0].runs_theta) == s.case.initial_design.shape[0] and s.n_runs == 15


def test_hidden_tabs_are_rebuilt_when_shown_not_on_every_change():
    """The metrics (rebuilt from scratch on each change) wait until their tab is shown
    (served, or the session is idle: tests/test_app_layout.py); a shown tab follows every
    change. A new session's says what to press."""
    s = small_state()
    page = pn.panel(ExplorerView(state=s))
    page.get_root(Document())
    (tabs,) = page.select(pn.Tabs)
    metrics_box = tabs[3][0][2]         # (in its scrolling column, after two lines)
    first = metrics_box.objects
    assert "press **Run discrepancy**" in first[0].object
    s.run_to_convergence()
    s.run_discrepancy()
    assert metrics_box.objects == first                    # never shown: not rebuilt
    tabs.active = 3
    (table,) = [o for o in metrics_box.select(pn.pane.DataFrame)
                if "metrics-table" in o.css_classes]
    assert list(table.object["method"]) == ["Scenario 1", "Scenario 2", "Scenario 3"]
    s.scenarios = [Method.S1]                              # shown: follows at once
    (table,) = [o for o in metrics_box.select(pn.pane.DataFrame)
                if "metrics-table" in o.css_classes]
    assert list(table.object["method"]) == ["Scenario 1"]
    tabs.active = 2
    built = metrics_box.objects
    s.scenarios = S123                                     # hidden again: left as it was
    assert metrics_box.objects == built
    tabs.active = 3
    (table,) = [o for o in metrics_box.select(pn.pane.DataFrame)
                if "metrics-table" in o.css_classes]
    assert list(table.object["method"]) == ["Scenario 1", "Scenario 2", "Scenario 3"]


def test_a_new_session_builds_the_live_panels_of_the_tab_in_view_only():
    """A new page shows the Data tab: the History-matching panels are built when their tab
    is first shown (they were half of a new session's server time)."""
    from bokeh.models import Plot

    s = small_state()
    view = ExplorerView(state=s)
    pn.panel(view).get_root(Document())
    waves, calibration = view.waves_view, view.calibration_view

    def plots(panel):
        return [p for p in panel._layout.select(pn.pane.Bokeh) if isinstance(p.object, Plot)]

    assert view.data_view._case is s.case and plots(view.data_view)
    assert waves._stale and calibration._stale and not plots(waves)
    s.run_to_convergence()                                  # hidden: nothing drawn yet
    assert not plots(waves)
    view._tabs.active = 1
    assert not waves._stale and plots(waves) and plots(calibration)
    assert waves._case is s.case


def test_a_case_switch_rebuilds_only_the_live_panels_in_view():
    """The History-matching panels of a case switched to from the Data tab are built when
    their tab is shown (before it is drawn), from what the state holds then."""
    from bokeh.models import Plot

    s = small_state()
    view = ExplorerView(state=s)
    page = pn.panel(view)
    page.get_root(Document())
    (tabs,) = page.select(pn.Tabs)
    waves, data = view.waves_view, view.data_view

    def plots():
        return [p.object for p in waves._layout.select(pn.pane.Bokeh)
                if isinstance(p.object, Plot)]

    s.case_name = "shear-5"
    assert data._case is s.case                             # in view: rebuilt at once
    assert waves._stale and waves._case is not s.case
    s.next_wave()                                           # hidden and stale: no update
    assert waves._stale and plots() == []
    tabs.active = 1
    assert not waves._stale and waves._case is s.case and view.calibration_view._case is s.case
    titles = [p.title.text for p in plots()]
    assert "NROY samples: E vs ν" in titles               # shear-5's pairs, with the wave
    s.case_name = "beam-1d"                                 # in view now: at once
    assert not waves._stale and waves._case is s.case


def test_status_line_is_one_pane_whose_text_and_colour_change():
    """The status line is updated in place (a new pane per wave re-laid-out the page):
    its colour says how the last wave ended, and its text is escaped."""
    s = small_state()
    v = ExplorerView(state=s)
    pane = v.status_view
    assert "mdcore-alert-info" in v.status_html and "Press “Next wave”" in v.status_html
    s.run_to_convergence()
    assert v.status_view is pane
    assert s.waves[-1].status == "converged" and "mdcore-alert-success" in v.status_html
    s.status = "a <b>tag</b> & more"
    assert "a &lt;b&gt;tag&lt;/b&gt; &amp; more" in v.status_html



def test_the_phi_posterior_follows_the_output_shown():
    """shear-5: scenario 3's φ posterior (Metrics tab) is the chosen output's, each plot
    a Bokeh figure titled with it."""
    s = small_state("shear-5", n_s=10, n_phi=4)
    v = ExplorerView(state=s)
    s.scenarios = [Method.S3]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        s.run_discrepancy()

    def titles():
        return [p.object.title.text for p in pn.panel(v.metrics_view()).select(pn.pane.Bokeh)
                if "phi-plot" in p.object.css_classes]

    P = s.case.phi_prior.mean.size
    assert len(titles()) == P and all(t.startswith("ω1: ") for t in titles())
    s.output = "ω3"
    assert len(titles()) == P and all(t.startswith("ω3: ") for t in titles())


def test_the_app_uses_no_private_framework_internals():
    """Issue 39: no monkeypatching of Panel or Bokeh, no process-wide switches, no
    gc.freeze, and no private attribute of another object (``x._name`` only on ``self``
    or ``cls``) anywhere in app/."""
    import re

    banned = re.compile(r"DocHandler|_update_active|gc\.freeze|_priority_changes|"
                        r"_template_variables|perform_document_validation|validate\(False\)")
    private = re.compile(r"\b(\w+)\._[a-z]\w*")
    app_dir = Path(__file__).resolve().parent.parent / "app"
    found = []
    for path in sorted([*app_dir.glob("*.py"), *app_dir.glob("*.js")]):
        for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
            code = line.split("#")[0]
            if banned.search(line) or any(m.group(1) not in ("self", "cls", "mdcore")
                                          for m in private.finditer(code)
                                          if not code.lstrip().startswith(("from", "import"))):
                found.append(f"{path.name}:{n}: {line.strip()}")
    assert found == []


#: Properties whose change makes BokehJS lay out the whole page again
#: (``LayoutDOMView.connect_signals``: ``invalidate_layout``), 0.2-0.3 s in Chromium.
RELAYOUT = {"visible", "css_classes", "stylesheets", "width", "height", "min_width",
            "min_height", "max_width", "max_height", "margin", "width_policy",
            "height_policy", "flow_mode", "sizing_mode", "aspect_ratio", "resizable"}


def test_waves_runs_and_reruns_never_change_what_relays_out_the_page():
    """A wave, the player appearing, a discrepancy run with advice beside the bands, a
    seed change and a band change show and hide things by style or text, never by a
    layout's ``visible`` or size (issue 17: each such change cost 0.2-0.3 s of browser)."""
    from bokeh.document.events import ModelChangedEvent
    from bokeh.models import LayoutDOM

    s = ExplorerState(n_candidates=4000, n_s=5, n_phi=2)        # the teaching preset
    s.scenarios = [Method.S1, Method.S3]
    view = ExplorerView(state=s)
    doc = Document()
    doc.add_root(pn.panel(view).get_root(doc))
    for tab in (1, 2, 0):                                # each tab shown once, as a user
        view._tabs.active = tab
    seen = []
    doc.on_change(lambda e: seen.append(e))
    s.next_wave()
    s.next_wave()
    view._tabs.active = 2
    s.run_discrepancy()
    assert "importance weights are unreliable" in view.discrepancy_view.message
    s.seed = 1
    s.band = 2
    assert len(s.waves) >= 2 and s.results and not s.error
    relayout = [(type(e.model).__name__, e.attr) for e in seen
                if isinstance(e, ModelChangedEvent) and isinstance(e.model, LayoutDOM)
                and e.attr in RELAYOUT]
    assert relayout == []
    assert len(seen) > 20                                # the updates themselves did come


@pytest.mark.parametrize("case", ["beam-1d", "beam-2d", "shear-5"])
def test_every_tab_passes_bokehs_integrity_checks(case):
    """Bokeh's document checks (layout and model rules: W-/E- codes) find nothing on any
    tab, results shown, but empty layouts (W-1002: boxes that wait for a result or for
    their tab). The served app skips them per session (app/main.py); this is where they
    run."""
    from bokeh.core.validation.check import check_integrity
    from bokeh.core.validation.warnings import EMPTY_LAYOUT

    s = small_state(case)
    doc = Document()
    page = pn.panel(ExplorerView(state=s))
    page.server_doc(doc)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        s.run_discrepancy()
    (tabs,) = page.select(pn.Tabs)
    for index in range(len(tabs)):
        tabs.active = index
        for root in doc.roots:
            issues = check_integrity(root.references())
            warned = [w for w in issues.warning if w.code != EMPTY_LAYOUT.code]
            assert issues.error == [] and warned == [], (case, f"tab {index}", issues)


#: Seconds measured for one method's run (run_method, and the app's run_discrepancy with
#: its plotting grid; medians of 2–4 alternated runs on the 2-core machine, other jobs
#: running): (training rows, outputs, KOH chain steps, scenario-3 pairs) -> seconds, with
#: the paper's prior proposal for scenario 3.
MEASURED_SECONDS = {
    (13, 1, 20_000, 0): 0.375, (13, 1, 150_000, 0): 0.505,       # beam-1d KOH fast, paper
    (64, 1, 20_000, 0): 3.985, (30, 5, 20_000, 0): 6.265,        # beam-2d, shear-5 KOH fast
    (13, 1, 0, 50_000): 0.71, (64, 1, 0, 50_000): 6.17, (30, 5, 0, 50_000): 3.9,
    (13, 1, 0, 20_000): 0.52, (64, 1, 0, 20_000): 2.79, (30, 5, 0, 20_000): 0.87,
    (13, 1, 0, 5_000): 0.21, (64, 1, 0, 5_000): 0.71, (30, 5, 0, 5_000): 0.41,
}
#: ... and scenario 3 with the adaptive proposal, the default (bench/app_estimates.py; one
#: run each, docs/performance.md "Run estimates").
MEASURED_ADAPTIVE = {
    (13, 1, 500_000): 0.98, (64, 1, 200_000): 3.49, (64, 1, 500_000): 10.54,
    (64, 1, 1_000_000): 17.8, (30, 5, 50_000): 1.96, (30, 5, 200_000): 3.6,
    (30, 5, 500_000): 10.09,
}
#: Seconds of history-matching waves (bench/app_estimates.py): (observed rows, outputs,
#: candidates, wave) -> seconds.
MEASURED_WAVES = {
    (13, 1, 1_000_000, 1): 0.27, (13, 1, 1_000_000, 2): 0.83, (13, 1, 1_000_000, 3): 1.28,
    (64, 1, 1_000_000, 1): 0.68, (64, 1, 1_000_000, 2): 1.98, (64, 1, 1_000_000, 3): 3.47,
    (30, 5, 1_000_000, 1): 1.24, (13, 1, 100_000, 1): 0.10, (64, 1, 100_000, 3): 0.47,
}


def test_estimate_seconds_matches_measured_runs():
    """The run button's estimate is within a factor of 2.2 of every measured run (timings
    on a shared machine vary by 1.5× between repeats), and says "over 3 s" exactly for
    the runs measured over 3 s but one near the line (beam-2d's 2.8 s, estimated 3.0)."""
    from mdcore_app.session_model import ANNOUNCE_SECONDS, estimate_seconds
    for (n, out, steps, pairs), seconds in MEASURED_SECONDS.items():
        est = estimate_seconds(n, out, koh_steps=steps, s3_pairs=pairs, proposal="prior")
        assert 1 / 2.2 < est / seconds < 2.2, ((n, out, steps, pairs), est, seconds)
        if seconds > ANNOUNCE_SECONDS:
            assert est > ANNOUNCE_SECONDS, ((n, out, steps, pairs), est, seconds)


def test_adaptive_and_wave_estimates_are_within_2x_of_measured_runs():
    """Scenario 3's adaptive proposal (the default) and the history-matching waves: the
    estimate is within a factor of 2 of each measured run of ≥ 0.1 s."""
    from mdcore_app.history_model import wave_seconds
    from mdcore_app.session_model import estimate_seconds
    for (n, out, pairs), seconds in MEASURED_ADAPTIVE.items():
        est = estimate_seconds(n, out, s3_pairs=pairs)
        assert 0.5 <= est / seconds <= 2.0, ((n, out, pairs), est, seconds)
    for (n, out, candidates, k), seconds in MEASURED_WAVES.items():
        est = wave_seconds(n, out, candidates, k)
        assert 0.5 <= est / seconds <= 2.0, ((n, out, candidates, k), est, seconds)


def test_long_runs_say_so_on_the_button_and_koh_tooltip():
    s = ExplorerState()
    page = ExplorerView(state=s).__panel__()
    (run,) = [b for b in page.select(pn.widgets.Button) if "run-discrepancy" in b.css_classes]
    s.scenarios = [Method.S1, Method.KOH]
    assert run.label == "Run discrepancy"                      # beam-1d: under a second
    s.case_name = "beam-2d"
    s.scenarios = [Method.S1, Method.KOH]
    assert run.label.startswith("Run discrepancy (≈ ") and run.label.endswith(" s)")
    (koh,) = [i for i in page.select(pn.widgets.TooltipIcon) if "KOH on" in str(i.value)]
    assert "0.4–1.2" not in koh.value and "beam-2d: fast ≈ 7.2 s, paper ≈ 51" in koh.value
    s.scenarios = [Method.S1, Method.S2, Method.S3]
    s.paper_sizes = True                # beam-2d's 10⁶ pairs (docs/performance.md)
    assert run.label.startswith("Run discrepancy (≈ ") and 12 <= s.run_seconds() <= 40
    # The history match's buttons: their estimate in the tooltip, on the label when > 3 s.
    (conv,) = [b for b in page.select(pn.widgets.Button) if "run-convergence" in b.css_classes]
    assert conv.label == "Run to convergence" and "a wave, at most" in conv.description
    s.n_candidates = 1_000_000                 # waves of 0.7, 2.0, 3.5 s … (MEASURED_WAVES)
    s.next_wave()
    s.next_wave()
    assert conv.label.startswith("Run to convergence (≈ ") and conv.label.endswith(" s)")


def test_progress_follows_the_estimated_work_of_each_method():
    """The bar jumped to 67–83 % once scenarios 1 and 2 (a fraction of a second) were done,
    then crept through scenario 3's seconds: each method's share is now its estimate."""
    import threading

    from mdcore_app.runs import discrepancy_job, method_seconds
    s = ExplorerState()
    s.run_to_convergence()
    s.param.update(n_s=1000, n_phi=500)
    settings = s.method_settings()
    seen: list[tuple[float, str]] = []
    plan = s._plan(settings)
    for _ in discrepancy_job(plan, lambda f, m: seen.append((f, m)), threading.Event()):
        pass
    fractions = [f for f, _ in seen]
    assert fractions == sorted(fractions) and fractions[-1] == pytest.approx(1.0)
    starts = [f for f, m in seen if m == "starting"]            # S1, S2, S3
    cost = [method_seconds(s.case, settings, m) for m in (Method.S1, Method.S2, Method.S3)]
    assert len(starts) == 3 and starts[2] == pytest.approx(sum(cost[:2]) / sum(cost))
    assert starts[2] < 0.6                                         # was 2/3
