"""The Discrepancy tab updates in place (issue 17): a new band, hidden or shown methods,
the quantity shown, a new slice and new results change data sources and visibilities of
the figures already built, never the figures themselves; the numbers drawn are the
results' own (mean ± k·sd, checked against the closed form)."""

import warnings

import numpy as np
import param
import pytest

pytest.importorskip("panel")
import holoviews as hv  # noqa: E402
import panel as pn  # noqa: E402
from bokeh.document import Document  # noqa: E402
from bokeh.models import ColumnDataSource, Plot  # noqa: E402

from mdcore._pipeline import Method  # noqa: E402
from mdcore_app.discrepancy_panel import (  # noqa: E402
    CURRENT,
    SLOT,
    STALE_OPACITY,
    DiscrepancyPanel,
)
from mdcore_app.discrepancy_text import EMPTY_HTML, NONE_CHOSEN_HTML, not_run_html  # noqa: E402
from mdcore_app.state import ExplorerState  # noqa: E402

hv.extension("bokeh")
SMALL = {"preset": "paper", "n_candidates": 4000, "n_s": 30, "n_phi": 8}
S123 = [Method.S1, Method.S2, Method.S3]


def run(case="beam-1d", **extra):
    s = ExplorerState()
    s.case_name = case
    s.param.update(**{**SMALL, **extra})
    s.run_to_convergence()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        s.run_discrepancy()
    assert s.error == "" and list(s.results) == S123
    return s


def figures(root) -> dict[str, Plot]:
    return {p.title.text: p for p in root.select({"type": Plot})}


def source(fig: Plot, column: str) -> dict:
    (src,) = [s for s in fig.select({"type": ColumnDataSource}) if column in s.data]
    return src.data


@pytest.fixture(scope="module")
def beam1d():
    s = run()
    panel = DiscrepancyPanel(state=s)
    root = pn.panel(panel).get_root(Document())
    return s, panel, root


def test_band_change_patches_the_data_of_the_same_figures(beam1d):
    s, panel, root = beam1d
    before = {t: f.id for t, f in figures(root).items()}
    assert len(before) == 6                         # z and δ of three scenarios
    s.band = 2
    try:
        after = figures(root)
        assert {t: f.id for t, f in after.items()} == before
        on_grid = s.results[Method.S2].on_extra
        band = source(after["Scenario 2: δ"], "lower")
        sd = 2 * np.sqrt(on_grid.delta_var[:, 0])
        np.testing.assert_allclose(band["x"], s.grid[:, 0])
        np.testing.assert_allclose(band["lower"], on_grid.delta_mean[:, 0] - sd, rtol=1e-12)
        np.testing.assert_allclose(band["upper"], on_grid.delta_mean[:, 0] + sd, rtol=1e-12)
        z = source(after["Scenario 2: z"], "lower")
        np.testing.assert_allclose(z["upper"] - z["lower"],
                                   4 * np.sqrt(on_grid.z_var[:, 0]), rtol=1e-10)
        truth = source(after["Scenario 2: δ"], "y")
        np.testing.assert_allclose(truth["y"], s.case.true_delta(s.grid)[:, 0])
        # The legend says the band's actual k (issue 41: it read "±kσ" whatever the band).
        labels = [item.label for f in after.values() for item in f.legend[0].items]
        texts = [getattr(label, "value", None) for label in labels]   # texts, no field names
        assert "Scenario 2 ±2σ" in texts and None not in texts
        assert "±3σ" not in str(labels) and "kσ" not in str(labels)
    finally:
        s.band = 3


def test_hiding_a_method_or_a_quantity_changes_only_visibility(beam1d):
    s, panel, root = beam1d
    before = {t: f.id for t, f in figures(root).items()}
    groups = panel._groups
    s.scenarios = [Method.S1, Method.S3]
    # S2's column keeps its place, empty (CSS visibility): the others do not move
    assert groups[Method.S2].visible and groups[Method.S2].styles == SLOT
    assert groups[Method.S1].styles == CURRENT and panel.message != EMPTY_HTML
    assert {t: f.id for t, f in figures(root).items()} == before
    s.scenarios = [Method.S3]
    s.scenarios = []
    assert panel.message == NONE_CHOSEN_HTML       # every column hidden: say what to do
    s.scenarios = S123
    assert all(g.visible and g.styles == CURRENT for g in groups.values())
    assert panel.message != EMPTY_HTML
    panel.quantity = "δ"
    shown = [cell[0] for (m, (o, q)), cell in panel._cells.items() if cell[0].visible]
    assert len(shown) == 3 and all(p.object.title.text.endswith("δ") for p in shown)
    panel.quantity = "z and δ"
    assert {t: f.id for t, f in figures(root).items()} == before
    # shown again: the panes and their figures (a pane re-reads its figure's visible)
    assert all(cell[0].visible and cell[1].figure.visible for cell in panel._cells.values())


def test_a_recompute_keeps_the_earlier_plots_dimmed_until_its_results_arrive(beam1d):
    s, panel, root = beam1d
    results = dict(s.results)
    with param.parameterized.batch_call_watchers(s):  # as the served app clears and starts
        s.results = {}
        s.busy = True
    try:
        assert all(g.visible and g.styles.get("opacity") == STALE_OPACITY
                   for g in panel._groups.values())
        assert panel.message != EMPTY_HTML
        s.busy = False                                 # cancelled: nothing to show
        assert not any(g.visible for g in panel._groups.values())
        assert panel.message == EMPTY_HTML
    finally:
        s.results = results
    # Back to full opacity, said explicitly (styles of {} leave the browser's dimming on).
    assert all(g.visible and g.styles == CURRENT for g in panel._groups.values())


def test_new_results_are_drawn_in_the_same_figures():
    s = run()
    panel = DiscrepancyPanel(state=s)
    root = pn.panel(panel).get_root(Document())
    before = {t: f.id for t, f in figures(root).items()}
    old = s.results[Method.S3].on_extra.delta_mean[:, 0].copy()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        s.seed = 1                                     # recomputes the three scenarios
    assert list(s.results) == S123
    after = figures(root)
    assert {t: f.id for t, f in after.items()} == before
    mean = source(after["Scenario 3: δ"], "mean")["mean"]       # seed-dependent draws
    np.testing.assert_allclose(mean, s.results[Method.S3].on_extra.delta_mean[:, 0])
    assert not np.allclose(mean, old)


def test_beam_2d_maps_and_slice_follow_the_band_and_the_slider():
    s = run("beam-2d")
    panel = DiscrepancyPanel(state=s)
    assert not panel._show.visible                     # "Show z/δ" means nothing here
    root = pn.panel(panel).get_root(Document())
    figs = figures(root)
    before = {t: f.id for t, f in figs.items()}
    r = s.results[Method.S3].on_extra
    u1, u2 = np.unique(s.grid[:, 0]), np.unique(s.grid[:, 1])
    shape = (u2.size, u1.size)
    mean = source(figs["Scenario 3: δ mean"], "image")["image"][0]
    np.testing.assert_allclose(mean, r.delta_mean[:, 0].reshape(shape))
    sd_map = figures(root)["Scenario 3: δ sd (σ)"]
    sd = source(sd_map, "image")["image"][0]
    np.testing.assert_allclose(sd, np.sqrt(r.delta_var[:, 0].reshape(shape)))
    s.band = 2                                         # the maps show no band: unchanged
    assert source(figures(root)["Scenario 3: δ sd (σ)"], "image")["image"][0] is sd
    row = 3
    s.slice_x2 = float(u2[row])
    (title,) = [t for t in figures(root) if t.startswith("Scenario 3: δ at x₂ = ")]
    assert f"{u2[row]:.3g}" in title
    sliced = source(figures(root)[title], "mean")
    np.testing.assert_allclose(sliced["x"], u1)
    np.testing.assert_allclose(sliced["mean"], r.delta_mean[:, 0].reshape(shape)[row])
    truth = s.case.true_delta(np.column_stack([u1, np.full_like(u1, u2[row])]))[:, 0]
    np.testing.assert_allclose(source(figures(root)[title], "y")["y"], truth, rtol=1e-12)
    assert {f.id for f in figures(root).values()} == set(before.values())
    s.scenarios = [Method.S1, Method.S3]           # S2's row keeps its place, empty
    assert panel._groups[Method.S2].visible and panel._groups[Method.S2].styles == SLOT
    s.scenarios = S123
    assert panel._groups[Method.S2].styles == CURRENT
    assert {f.id for f in figures(root).values()} == set(before.values())


def test_a_case_switch_rebuilds_for_the_new_case(beam1d):
    s = run()
    panel = DiscrepancyPanel(state=s)
    s.case_name = "shear-5"
    assert panel._groups == {} and panel.message == EMPTY_HTML and panel.quantity == "z and δ"
    assert s.output == "ω1"                           # the first output is shown
    s.case_name = "beam-1d"                            # results kept per case come back
    assert set(panel._groups) == set(S123) and panel.quantity == "z and δ"
    assert panel._show.value == "z and δ" and s.output == "tip deflection"


def test_several_outputs_are_shown_one_at_a_time():
    """shear-5: the plots of the chosen output only (two per method, not ten), each the
    result's bands for that output; a new choice builds its plots once, then only their
    visibility changes."""
    s = run("shear-5", n_s=10, n_phi=4)
    panel = DiscrepancyPanel(state=s)
    root = pn.panel(panel).get_root(Document())

    def shown():
        return {cell[1].figure.title.text: (o, q) for (m, (o, q)), cell in panel._cells.items()
                if cell[0].visible}

    assert set(shown()) == {f"{m.label}: {t}" for m in S123
                            for t in ("z, ω1", "δ, ω1")}
    assert set(shown().values()) == {(0, "z"), (0, "delta")}
    s.output = "ω4"                                  # as a click on the "ω4" button
    assert set(shown().values()) == {(3, "z"), (3, "delta")}
    on_grid = s.results[Method.S3].on_extra
    band = source(figures(root)["Scenario 3: δ, ω4"], "lower")
    sd = 3 * np.sqrt(on_grid.delta_var[:, 3])
    np.testing.assert_allclose(band["lower"], on_grid.delta_mean[:, 3] - sd, rtol=1e-12)
    ids = {f.id for f in figures(root).values()}
    s.output = "ω1"
    s.output = "ω4"
    assert {f.id for f in figures(root).values()} == ids    # built once per output
    assert len(shown()) == 6


def test_the_methods_plots_of_one_quantity_share_their_axes(beam1d):
    """Scenario 1's narrow δ band and scenario 2's wide one are compared at one scale."""
    s, panel, root = beam1d
    figs = figures(root)
    for q in ("δ", "z"):
        plots = [figs[f"{m.label}: {q}"] for m in S123]
        assert len({p.y_range.id for p in plots}) == 1 and len({p.x_range.id for p in plots}) == 1
    assert figs["Scenario 1: δ"].y_range is not figs["Scenario 1: z"].y_range


def test_axes_hold_every_method_at_the_widest_band_and_stay_put(beam1d):
    """The shared axes cover mean ± 3 sd of every result (shown or not) and the data or
    true δ, 5 % beyond; a new band or a hidden method leaves them where they are (in the
    browser, rescaled axes re-laid-out every plot: 0.9 s per band click)."""
    s, panel, root = beam1d
    figs = figures(root)

    def axes():
        return {t: (f.x_range.start, f.x_range.end, f.y_range.start, f.y_range.end)
                for t, f in figures(root).items()}

    before = axes()
    for q, o in (("delta", 0), ("z", 0)):
        fig = figs["Scenario 2: δ" if q == "delta" else "Scenario 2: z"]
        lo, hi = [], []
        for r in s.results.values():                         # independent of the panel
            mean = getattr(r.on_extra, f"{q}_mean")[:, o]
            sd = 3 * np.sqrt(getattr(r.on_extra, f"{q}_var")[:, o])
            lo.append((mean - sd).min())
            hi.append((mean + sd).max())
        extra = (s.case.true_delta(s.grid)[:, o] if q == "delta"
                 else np.concatenate([s.case.z_train[:, o], s.case.z_test[:, o]]))
        y0, y1 = min(min(lo), extra.min()), max(max(hi), extra.max())
        pad = 0.05 * (y1 - y0)
        assert fig.y_range.start == pytest.approx(y0 - pad, rel=1e-12)
        assert fig.y_range.end == pytest.approx(y1 + pad, rel=1e-12)
        assert fig.x_range.start <= s.grid[:, 0].min() < s.grid[:, 0].max() <= fig.x_range.end
    s.band = 2
    s.scenarios = [Method.S1, Method.S3]
    try:
        assert axes() == before
    finally:
        s.band = 3
        s.scenarios = S123


def test_new_results_keep_the_axes_while_they_fit(beam1d, monkeypatch):
    """Another seed is seen at the same scale: the axes move only when the new extent
    leaves them or fills less than KEEP_SPAN of them."""
    s, panel, root = beam1d
    key = (0, "delta")
    rng = panel._ranges[key]["y_range"]
    start = (rng.start, rng.end)

    def fit(y):
        monkeypatch.setattr(panel, "_extent", lambda k, held: ((0.1, 0.9), y))
        panel._fit_ranges()
        return rng.start, rng.end

    try:
        assert fit((0.0, 10.0)) == (0.0, 10.0)
        assert fit((1.0, 9.0)) == (0.0, 10.0)          # inside, 80 % of the span: kept
        assert fit((4.0, 6.0)) == (4.0, 6.0)           # 20 %: refitted
        assert fit((3.0, 6.5)) == (3.0, 6.5)           # outside: refitted
    finally:
        monkeypatch.undo()
        panel._fitted.discard(key)
        panel._fit_ranges()
    assert (rng.start, rng.end) == start


def test_a_new_band_sends_the_band_only(beam1d):
    """Each data assignment is sent to the browser and redraws the plot: a new band
    replaces the band's data, never the unchanged mean or true δ."""
    s, panel, root = beam1d
    fig = figures(root)["Scenario 2: δ"]
    sources = {c: [x for x in fig.select({"type": ColumnDataSource}) if c in x.data][0]
               for c in ("lower", "mean", "y")}
    changed = []
    for name, src in sources.items():
        src.on_change("data", lambda attr, old, new, name=name: changed.append(name))
    s.band = 2
    s.band = 3
    assert changed == ["lower", "lower"]


def test_after_a_card_a_method_it_did_not_choose_gives_up_its_column(beam1d):
    """The KOH card (scenario 1 and KOH) run after cards that drew scenarios 2 and 3 showed
    its two columns with two empty ones between them: the buttons' rule keeps a hidden
    method's place. A card chooses what it shows, so the place goes while its line is up."""
    s, panel, _root = beam1d
    groups = panel._groups
    try:
        s.param.update(card="Joint calibration — look at: Discrepancy tab",
                       scenarios=[Method.S1, Method.S3])
        assert not groups[Method.S2].visible
        assert groups[Method.S1].visible and groups[Method.S3].visible
        s.card = ""                                    # the buttons' rule again
        assert groups[Method.S2].visible and groups[Method.S2].styles == SLOT
    finally:
        s.param.update(card="", scenarios=S123)
    assert all(g.visible and g.styles == CURRENT for g in groups.values())


def test_a_chosen_method_without_a_result_is_named_above_the_plots(beam1d):
    """The tour's waves card left scenarios 1-3 chosen but only 1 and 2 computed for the
    new settings: the tab showed two methods and said nothing of the third."""
    from types import SimpleNamespace
    s, panel, _root = beam1d
    assert "not run" not in panel.message                # every chosen method has run
    state = SimpleNamespace(busy=False, scenarios=[Method.KOH, Method.S1, Method.S3],
                            results={Method.S1: s.results[Method.S1]})
    assert not_run_html(state) == ("<p>Scenario 3 and KOH: not run for these settings "
                                   "yet; press <b>Run discrepancy</b>.</p>")
    state.busy = True                                    # running: the line says so
    assert not_run_html(state) == ""


def test_beam_2d_without_a_known_delta_keeps_one_group_per_method(monkeypatch):
    """An own 2-D case whose δ is unknown has no truth map above the methods: the head is
    the slider, then each method's group once, however often the groups are placed."""
    import mdcore_app.discrepancy_panel as module
    monkeypatch.setattr(module, "true_delta_figure", lambda case, css_class: None)
    s = run("beam-2d")
    panel = DiscrepancyPanel(state=s)
    for band in (2, 3, 2):                            # each change places the groups again
        s.band = band
        head = list(panel._head.objects)
        assert isinstance(head[0], pn.widgets.FloatSlider)
        assert head[1:] == [panel._groups[m] for m in S123]


def test_showing_the_tab_builds_the_plots_ahead_and_a_run_only_fills_them():
    """The chosen methods' plots are built, empty and hidden, when the tab is shown (a first
    run was mostly building them); the run fills the same figures and shows them. Empty
    plots are never shown, not even dimmed while the first run computes."""
    s = ExplorerState()
    s.case_name = "beam-1d"
    s.param.update(**SMALL)
    s.run_to_convergence()
    panel = DiscrepancyPanel(state=s)
    tabs = pn.Tabs(("Data", pn.Column()), ("HM", pn.Column()), ("Discrepancy", panel))
    panel.prebuild_when_shown(tabs, 2)
    for bad in [(None, 2), (tabs, -1), (tabs, "2")]:
        with pytest.raises(ValueError, match=r"\(tabs, index\) must be \(tabs, index\)"):
            panel.prebuild_when_shown(*bad)
    root = pn.panel(tabs).get_root(Document())
    assert panel._groups == {}                          # not shown yet: nothing built
    tabs.active = 2
    assert set(panel._groups) == set(S123)
    assert all(g.styles == SLOT for g in panel._groups.values())
    assert panel.message == EMPTY_HTML
    # The waves have run: the line no longer says "Run history matching, then ..."
    assert not panel.message.startswith("Run history") and "press <b>Run discrepancy" in \
        panel.message
    ahead = {t: f.id for t, f in figures(root).items()}
    assert len(ahead) == 6                              # z and δ of three methods
    # Blank (NaN, nothing drawn) at the plotting grid: the run's data come as patches.
    assert all(np.isnan(source(f, "mean")["mean"]).all() and
               len(source(f, "mean")["mean"]) == s.grid.shape[0] for f in figures(root).values())
    s.param.update(busy=True, task="discrepancy")     # the first run computes: still hidden
    assert all(g.styles == SLOT for g in panel._groups.values())
    # ... and the line says what runs, not "Run history matching" (the match converged)
    assert panel.message.startswith("Running the discrepancy methods")
    s.param.update(busy=False, task="")
    s.param.update(busy=True, task="waves")
    assert panel.message.startswith("Running history matching")
    s.param.update(busy=False, task="")
    assert panel.message == EMPTY_HTML
    # A method no longer chosen gives up its empty place: the KOH card (scenario 1 and
    # KOH) showed its two columns with two empty ones between them.
    s.scenarios = [Method.S1, Method.S3]
    assert not panel._groups[Method.S2].visible
    assert panel._groups[Method.S1].visible and panel._groups[Method.S3].visible
    s.scenarios = S123
    assert all(g.visible for g in panel._groups.values())
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        s.run_discrepancy()
    after = figures(root)
    assert {t: f.id for t, f in after.items()} == ahead   # the same figures, filled
    assert all(g.visible and g.styles == CURRENT for g in panel._groups.values())
    np.testing.assert_allclose(source(after["Scenario 2: δ"], "mean")["mean"],
                               s.results[Method.S2].on_extra.delta_mean[:, 0])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        s.scenarios = [Method.S1, Method.S2, Method.S3, Method.KOH]   # chosen while shown
    assert Method.KOH in panel._groups
    assert panel._groups[Method.KOH].visible == (Method.KOH in s.results)
