"""The Data tab in Bokeh: the paper's Fig. 1 numbers, in place updates and the 2-D maps."""

import numpy as np
import pytest

pytest.importorskip("panel")
import panel as pn  # noqa: E402
from bokeh.models import GlyphRenderer, Image  # noqa: E402

from mdcore_app.data_panel import DataPanel, error_bars, true_delta_figure  # noqa: E402
from mdcore_app.state import ExplorerState  # noqa: E402


def renderers(panel):
    return [r for p in panel._layout.select(pn.pane.Bokeh)
            for r in p.object.select({"type": GlyphRenderer})]


def test_error_bars_are_symmetric_about_the_data():
    bars = error_bars(np.array([1.0, 2.0]), np.array([3.0, -1.0]), 0.5)
    assert np.array_equal(bars["y0"], [2.5, -1.5]) and np.array_equal(bars["y1"], [3.5, -0.5])


def test_beam_2d_shows_the_training_data_and_the_true_delta_map():
    s = ExplorerState(case_name="beam-2d")
    panel = DataPanel(state=s)
    c = s.case
    (points,) = [r.data_source.data for r in renderers(panel) if "z" in r.data_source.data]
    assert np.array_equal(points["x"], c.X_train[:, 0])
    assert np.array_equal(points["y"], c.X_train[:, 1])
    assert np.array_equal(points["z"], c.z_train[:, 0])
    (image,) = [r for r in renderers(panel) if isinstance(r.glyph, Image)]
    d = np.asarray(image.data_source.data["image"][0])
    assert d.shape == (60, 60)
    # the image's corners are the true δ at the corners of the inputs' span
    X = np.vstack([c.X_train, c.X_test])
    lo, hi = X.min(axis=0), X.max(axis=0)
    # (Bokeh's row 0 is the bottom: x2 = lo; columns run along x1)
    corners = c.true_delta(np.array([[lo[0], lo[1]], [hi[0], hi[1]], [hi[0], lo[1]]]))[:, 0]
    assert np.allclose([d[0, 0], d[-1, -1], d[0, -1]], corners)
    assert not np.isclose(d[0, -1], d[-1, 0])                     # not transposed
    mapper = image.glyph.color_mapper
    assert mapper.low == -mapper.high == -np.abs(d).max()          # centred on δ = 0
    half = 2 * np.sqrt(c.noise_var[0] + s.v_m_vector()[0])
    (fig,) = [p.object for p in panel._layout.select(pn.pane.Bokeh)
              if p.object.title.text.startswith("training data")]
    assert f"±{half:.3g}" in fig.title.text
    s.v_m = 2 * s.v_m
    assert f"±{2 * np.sqrt(c.noise_var[0] + s.v_m_vector()[0]):.3g}" in fig.title.text


def test_no_true_delta_map_when_delta_is_unknown():
    s = ExplorerState(case_name="beam-2d")
    c = s.case

    class Unknown:
        def __getattr__(self, name):
            return getattr(c, name)

        def true_delta(self, X):
            return None

    assert true_delta_figure(Unknown(), "x") is None
    assert true_delta_figure(c, "x") is not None


def test_several_outputs_are_shown_one_at_a_time_with_their_bars():
    """shear-5: the data and true δ of the output shown (two plots, not ten); another output
    is built when first shown, its bars at ±2√(V_o + V_m) of that output, then a V_m change
    moves the bars of every built output in place."""
    s = ExplorerState(case_name="shear-5")
    panel = DataPanel(state=s)
    c = s.case

    def shown():
        return [p.object for row in panel._layout.objects if row.visible
                for p in row.select(pn.pane.Bokeh) if p.object.visible]

    def bars(o):
        (fig,) = [f for f in shown() if f.title.text == f"{c.output_names[o]}: data and simulator"]
        (data,) = [r.data_source.data for r in fig.select({"type": GlyphRenderer})
                   if "y0" in r.data_source.data]
        return data

    assert [f.title.text for f in shown()] == ["ω1: data and simulator", "true discrepancy δ, ω1"]
    s.output = "ω3"
    assert [f.title.text for f in shown()] == ["ω3: data and simulator", "true discrepancy δ, ω3"]
    half = 2 * np.sqrt(c.noise_var + s.v_m_vector())
    np.testing.assert_allclose(bars(2)["y1"] - c.z_train[:, 2], half[2], rtol=1e-12)
    built = {p.object.id for p in panel._layout.select(pn.pane.Bokeh)}
    assert len(built) == 4
    s.v_m = 2 * s.v_m
    s.output = "ω1"
    assert {p.object.id for p in panel._layout.select(pn.pane.Bokeh)} == built   # kept
    half = 2 * np.sqrt(c.noise_var + s.v_m_vector())
    np.testing.assert_allclose(bars(0)["y1"] - c.z_train[:, 0], half[0], rtol=1e-12)


def test_an_output_the_case_does_not_have_is_refused_with_a_notification():
    s = ExplorerState(case_name="shear-5")
    s.output = "ω3"
    s.output = "ω9"
    assert s.output == "ω1" and s.n_errors == 1
    assert "'ω9' is not an output of shear-5" in s.error and "ω1, ω2, ω3, ω4, ω5" in s.error
