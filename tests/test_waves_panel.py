"""The History matching tab's waves, updated in place (app/waves_panel.py): the data each
figure draws against the waves it comes from, and no figure rebuilt by a wave or a step of
the wave player."""

import numpy as np
import pytest

pytest.importorskip("panel")
import panel as pn  # noqa: E402
from bokeh.document import Document  # noqa: E402

from mdcore_app.live_figures import CURRENT  # noqa: E402
from mdcore_app.plots import WAVE_COLORS  # noqa: E402
from mdcore_app.state import ExplorerState  # noqa: E402
from mdcore_app.wave_data import (  # noqa: E402
    MAX_POINTS,
    RULED_OUT_COLOR,
    contour_lines,
    decades,
    histogram_columns,
    nroy_columns,
    padded,
    truth_verdict,
    variance_ratios,
    wave_colors,
)
from mdcore_app.waves_panel import MAX_WAVES, PLAYER_HIDDEN, PLAYER_SHOWN, WavesPanel  # noqa: E402


@pytest.fixture(scope="module")
def beam():
    """beam-1d (p = 2) with the teaching preset: several waves, each cutting NROY."""
    s = ExplorerState()
    s.run_to_convergence()
    assert len(s.waves) >= 3 and s.error == ""
    return s


def test_contour_is_the_level_set_of_a_closed_form():
    t1, t2 = np.linspace(-2, 2, 81), np.linspace(-1.5, 1.5, 61)
    T1, T2 = np.meshgrid(t1, t2)
    lines = contour_lines(t1, t2, np.hypot(T1, T2), 1.0)
    assert len(lines["xs"]) == 1                          # one closed circle
    r = np.hypot(lines["xs"][0], lines["ys"][0])
    np.testing.assert_allclose(r, 1.0, atol=2e-3)         # linear interpolation on h = 0.05
    assert contour_lines(t1, t2, np.hypot(T1, T2), 5.0) == {"xs": [], "ys": []}


def shown_waves(panel) -> np.ndarray:
    """The ``wave`` of the rows the browser shows: what the filter's code
    (``SHOWN_WAVES_JS``, ``w[i] <= upto``) keeps."""
    assert "shown[i] = w[i] <= upto" in panel._upto.code
    wave = np.asarray(panel._nroy.data["wave"])
    return wave[wave <= panel._upto.args["upto"]]


def test_wave_colours_follow_the_wave_index():
    spec = wave_colors()
    mapper = spec["transform"]
    assert spec["field"] == "wave" and len(mapper.palette) == MAX_WAVES
    for k in range(1, MAX_WAVES + 1):          # BokehJS's LinearColorMapper: the bin of k
        b = int(np.floor((k - mapper.low) / (mapper.high - mapper.low) * len(mapper.palette)))
        assert mapper.palette[b] == WAVE_COLORS[(k - 1) % len(WAVE_COLORS)]


def test_a_new_wave_streams_its_rows_and_the_player_sends_no_samples():
    """Issue 17: a wave's message carried every earlier wave's samples again, and a step
    of the player all of them (beam-1d 78-130 kB)."""
    from bokeh.document.events import ColumnDataChangedEvent, ColumnsStreamedEvent

    s = ExplorerState(n_candidates=4000)                    # teaching: several waves
    panel = WavesPanel(state=s)
    doc = Document()
    doc.add_root(pn.panel(panel).get_root(doc))
    s.next_wave()
    n1 = len(panel._nroy.data["wave"])
    seen = []
    doc.on_change(lambda e: seen.append(e))
    s.next_wave()
    assert len(s.waves) == 2
    data_events = [e for e in seen if getattr(e, "model", None) is panel._nroy]
    assert [type(e) for e in data_events] == [ColumnsStreamedEvent]
    assert set(np.asarray(data_events[0].data["wave"])) == {2}
    assert len(panel._nroy.data["wave"]) > n1 and set(shown_waves(panel)) == {1, 2}
    seen.clear()
    panel._player.value = 1
    assert not [e for e in seen if getattr(e, "model", None) is panel._nroy]
    assert set(shown_waves(panel)) == {1}
    s.threshold = 2.5                                        # a new match replaces them
    s.next_wave()
    assert any(isinstance(e, ColumnDataChangedEvent) for e in seen
               if getattr(e, "model", None) is panel._nroy)
    assert set(panel._nroy.data["wave"]) == {1} and set(shown_waves(panel)) == {1}


def test_panel_draws_the_waves_and_the_player_redraws_in_place(beam):
    s = beam
    panel = WavesPanel(state=s)
    layout, body = list(panel._layout.objects), list(panel._body.objects)
    assert panel._body.styles == CURRENT and panel._legend_div.text.startswith("<span")
    figures = [o.object for row in body[2:] for o in row]
    n = len(s.waves)
    data = panel._nroy.data
    # Every shown wave's samples (at most MAX_POINTS each, all of them NROY points of that
    # wave), later waves after earlier ones, coloured by wave.
    for w in s.waves:
        mine = np.column_stack([data["t0"], data["t1"]])[np.asarray(data["wave"]) == w.index]
        assert mine.shape[0] == min(MAX_POINTS, w.nroy.shape[0])
        assert {tuple(r) for r in mine} <= {tuple(r) for r in w.nroy}
    assert list(data["wave"]) == sorted(data["wave"])
    np.testing.assert_array_equal(panel._fraction.data["percent"],
                                  [100 * w.nroy_fraction for w in s.waves])
    # One row per possible wave, NaN (not drawn) after the last one run.
    ratio, wave = panel._ratios[0].data["ratio"], panel._ratios[0].data["wave"]
    assert ratio.shape == wave.shape == (MAX_WAVES,)
    np.testing.assert_array_equal(ratio[:n], [w.max_var[0] / w.var_threshold[0] for w in s.waves])
    np.testing.assert_array_equal(wave[:n], [w.index for w in s.waves])
    assert np.isnan(ratio[n:]).all() and np.isnan(wave[n:]).all()
    np.testing.assert_array_equal(panel._map_point.data["t0"], [s.history_match.theta_map[0]])
    stars = [r for f in figures for r in f.renderers if getattr(r, "data_source", None)
             is panel._map_point]
    assert len(stars) == 2 and all(r.glyph.marker == "star" for r in stars)   # pair, map
    # The truth's cross is drawn over the star: the tour's waves card had θ_MAP on the
    # truth, and the star hid the × the card points at.
    for f in figures:
        kinds = [getattr(r.glyph, "marker", None) for r in f.renderers]
        if "star" in kinds:
            assert kinds.index("x") > kinds.index("star"), f.title.text
    t1, t2, I = s.implausibility_maps[n]
    np.testing.assert_array_equal(panel._image.data["image"][0],
                                  np.minimum(I, 3 * s.history_match.problem.options.threshold))

    player = panel._player
    assert (player.styles, player.end, player.value) == (PLAYER_SHOWN, n, n)
    player.value = 2                                       # the player: waves 1–2 only
    assert s.selected_wave == 2
    assert set(shown_waves(panel)) == {1, 2}               # all waves kept, 1–2 shown
    assert set(panel._nroy.data["wave"]) == {w.index for w in s.waves}
    assert len(panel._fraction.data["wave"]) == 2
    assert panel._map_point.data["t0"] == []               # θ_MAP is the final wave's
    assert panel._image_fig.title.text.startswith("wave 2:")
    np.testing.assert_array_equal(panel._image.data["image"][0], np.minimum(
        s.implausibility_maps[2][2], 3 * s.history_match.problem.options.threshold))
    # A wave keeps its points whichever wave the player is at.
    assert np.array_equal(
        np.asarray(panel._nroy.data["t0"])[np.asarray(panel._nroy.data["wave"]) == 1],
        np.asarray(data["t0"])[np.asarray(data["wave"]) == 1])
    s.selected_wave = n
    assert player.value == n
    assert list(panel._layout.objects) == layout           # nothing re-laid-out
    assert list(panel._body.objects) == body
    assert [o.object for row in body[2:] for o in row] == figures


def test_one_parameter_histograms_count_each_waves_samples():
    s = ExplorerState(case_name="beam-2d")
    s.run_to_convergence()
    panel = WavesPanel(state=s)
    cols = panel._nroy.data
    for w in s.waves:
        rows = np.asarray(cols["wave"]) == w.index
        assert np.sum(np.asarray(cols["top"])[rows]) == min(MAX_POINTS, w.nroy.shape[0])
    assert panel._map_line.location == s.history_match.theta_map[0]
    s.selected_wave = 1
    assert panel._player.value == 1
    assert panel._map_line.location is None
    assert set(shown_waves(panel)) == {1}
    first = np.asarray(cols["top"])[np.asarray(cols["wave"]) == 1]
    assert panel._count_range.end == pytest.approx(1.05 * first.max())
    assert histogram_columns([], s.case.theta_bounds)["top"].size == 0


def test_many_outputs_each_have_a_variance_line():
    s = ExplorerState(case_name="shear-5")
    s.next_wave()
    w = s.waves[0]
    ratios = variance_ratios(s.waves, s.case.n_out)
    np.testing.assert_allclose(ratios[:, 0], w.max_var / w.var_threshold)
    panel = WavesPanel(state=s)
    assert len(panel._ratios) == 5
    # Three pairs of (E, ν, ρ) share one source, titled with the symbols the cards and
    # the README use (they said "nu" and "rho").
    assert set(nroy_columns(s.waves, 3)) == {"t0", "t1", "t2", "wave"}
    titles = [o.object.title.text for o in panel._body.objects[2]]
    assert titles == ["NROY samples: E vs ν", "NROY samples: E vs ρ", "NROY samples: ν vs ρ"]
    assert len(panel._body.objects) == 4 and panel._image is None   # player, legend, 2 rows
    # One wave: nothing to step; the player keeps its place, not shown, and nothing
    # in the tab changes its visible (a page-wide re-layout in BokehJS).
    assert panel._player.styles == PLAYER_HIDDEN and panel._player.visible
    # Its variance ratios on whole decades, two at least (1, 2, … 6 crowded the axis).
    r = variance_ratios(s.waves, s.case.n_out)
    lo, hi = min(r.min(), 1) / 3, max(r.max(), 1) * 3
    y = panel._body.objects[3][1].object.y_range
    assert np.log10(y.start) == np.floor(np.log10(lo)) and y.start <= lo
    assert np.log10(y.end) == max(np.ceil(np.log10(hi)), np.log10(y.start) + 2) and y.end >= hi
    assert decades(0.33, 6.3) == (0.1, 10.0) and decades(1e-3, 30.0) == (1e-3, 100.0)


def test_bad_inputs_name_the_argument():
    from mdcore_app.alerts import alert_box
    from mdcore_app.live_figures import live_text
    with pytest.raises(ValueError, match="kind must be one of"):
        alert_box("x", "fatal")
    with pytest.raises(ValueError, match="height"):
        live_text("x", height=-1)


def test_padded_fills_with_nan():
    np.testing.assert_array_equal(padded([1, 2], 4), [1.0, 2.0, np.nan, np.nan])
    assert padded([], 2).shape == (2,)
    np.testing.assert_array_equal(padded([np.inf], 2), [np.inf, np.nan])


def test_the_multivariate_rule_draws_its_map_against_the_chi2_cutoff():
    """Issue 43 item 5: the rule selector offers "multivariate"; its implausibility is I_M²,
    so the map's contour and colour clip are at ``problem.cutoff`` (the χ² quantile), not
    T, and the title says which. ℓ_m reaches the problem."""
    from mdcore._history_matching import RULE_NAMES
    from mdcore._multivariate import chi2_cutoff

    s = ExplorerState()
    assert list(s.param.rule.objects) == list(RULE_NAMES) and "multivariate" in RULE_NAMES
    assert "χ²" in s.param.rule.doc and "ℓ_m" in s.param.rule.doc
    s.param.update(preset="paper", n_candidates=4000, rule="multivariate", v_m_length=0.1)
    panel = WavesPanel(state=s)
    pn.panel(panel).get_root(Document())
    s.next_wave()
    problem = s.history_match.problem
    assert problem.options.rule == "multivariate"
    np.testing.assert_allclose(problem.options.V_m_length, 0.1)
    cutoff = chi2_cutoff(s.case.z_train.size, 0.995)
    assert problem.cutoff == pytest.approx(cutoff) and cutoff > 3 * s.threshold
    t1, t2, I = s.implausibility_maps[1]
    np.testing.assert_array_equal(panel._image.data["image"][0], np.minimum(I, 3 * cutoff))
    assert f"χ² = {cutoff:.3g}" in panel._image_fig.title.text


def test_a_hidden_tab_says_its_waves_are_being_drawn_not_press_next_wave():
    # Waves run from another tab: the History matching tab's figures are built when it is
    # first shown (up to seconds); meanwhile it said "Press Next wave" under "converged".
    s = ExplorerState()
    tabs = pn.Tabs(("Data", pn.pane.Markdown("data")), ("History matching", pn.Column()))
    panel = WavesPanel(state=s, shown_in=(tabs, 1))
    placeholder = panel._layout.objects[0]
    assert "Next wave" in placeholder.object
    s.next_wave()
    assert s.waves and panel._layout.objects == [placeholder]    # not built while hidden
    assert placeholder.object == "Drawing 1 wave …"
    s.next_wave()
    assert placeholder.object == f"Drawing {len(s.waves)} waves …"


def test_a_marker_on_the_edge_of_the_box_is_drawn_whole():
    """shear-5's θ_MAP sits on E's lower bound: with the plots' ranges equal to the box,
    its star was cut in half. Every range now leaves a margin beyond the box."""
    s = ExplorerState(case_name="shear-5")
    s.next_wave()
    panel = WavesPanel(state=s)
    bounds = np.asarray(s.case.theta_bounds, float)
    figs = [f for f in panel._layout.select(pn.pane.Bokeh) if f.object is not None
            and getattr(f.object, "x_range", None) is not None
            and "NROY samples:" in str(getattr(f.object.title, "text", ""))]
    assert len(figs) == 3                                 # (E, ν), (E, ρ), (ν, ρ)
    theta_map = s.history_match.theta_map
    assert np.isclose(theta_map[0], bounds[0, 0], rtol=0.02)   # the star on the edge
    for pane in figs:
        fig = pane.object
        names = fig.title.text.split(": ")[1].split(" vs ")
        i, j = (list(s.case.theta_names).index(n) for n in names)
        for rng, (lo, hi) in ((fig.x_range, bounds[i]), (fig.y_range, bounds[j])):
            margin = 0.03 * (hi - lo)
            assert rng.start <= lo - margin and rng.end >= hi + margin, fig.title.text


def test_the_legend_says_whether_the_truth_is_ruled_out_and_by_how_much():
    """At V_m = 0.014 mm² (the "rule out" card) the truth's cross sat on the edge of the
    last wave's points, so the class could not see that it was outside NROY: the legend
    says it, with the implausibility that decides it (Eq. 16 from the emulator's moments)."""
    s = ExplorerState()
    s.v_m = 0.014
    s.run_to_convergence()
    hm, t = s.history_match, np.asarray(s.case.theta_true, float)
    assert not hm.contains(t)[0] and hm.waves[-1].nroy.shape[0] > 0
    p = hm.problem
    # Eq. 16 by hand: max over targets of |z − E[y]| / √(V_o + V_m + Var y), per wave.
    by_hand = []
    for w in hm.waves:
        pred = w.emulator.predict(p.X, t[None, :])
        by_hand.append(float(np.max(np.abs(p.z - pred.mean[0])
                                    / np.sqrt(p.V_o + p.V_m + pred.var[0]))))
    first = next(k for k, v in enumerate(by_hand) if v > 3.0)
    inside, words = truth_verdict(hm.waves, t)
    assert not inside
    assert words == f"ruled out at wave {first + 1} (implausibility {by_hand[first]:.3g} > 3)"
    panel = WavesPanel(state=s)
    assert f'<b style="color:{RULED_OUT_COLOR}">{words}</b>' in panel._legend_div.text
    # The default V_m keeps it, and says by how much; outside the box, it says so.
    s.v_m = float(s.case.V_m[0])
    s.run_to_convergence()
    inside, words = truth_verdict(s.history_match.waves, t)
    assert inside and s.history_match.contains(t)[0]
    assert words.startswith("non-implausible (implausibility ≤ ") and words.endswith("≤ 3)")
    assert f"true θ: {words}" in panel._legend_div.text
    assert truth_verdict(s.history_match.waves, [60.0, 68.0]) == (False,
                                                                  "outside the prior box")
