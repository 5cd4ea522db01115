"""θ_MAP, the weighted θ posterior and the simulator at θ_MAP (app/calibration_panel.py),
checked in numbers against independent computations from mdcore, through the glyphs each
live figure draws (found by legend label)."""

import numpy as np
import pytest

pytest.importorskip("panel")
from bokeh.models import GlyphRenderer  # noqa: E402
from legends import legend  # noqa: E402

from mdcore_app.calibration_panel import CalibrationPanel, map_text  # noqa: E402
from mdcore_app.live_figures import CURRENT, SLOT  # noqa: E402
from mdcore_app.state import ExplorerState  # noqa: E402


def one(fig, label: str) -> tuple[dict, GlyphRenderer]:
    """(data, renderer) of the one legend entry starting with ``label``."""
    found = [(k, r) for k, rs in legend(fig).items() if k.startswith(label) for r in rs]
    assert len(found) == 1, (label, list(legend(fig)))
    (key, r), = found
    return {k: np.asarray(v) for k, v in r.data_source.data.items()}, r


def figures(panel):
    return [pane.object for row in panel._body.objects if hasattr(row, "objects")
            for pane in row.objects]


@pytest.fixture(scope="module")
def beam():
    s = ExplorerState(preset="paper", n_candidates=4000)
    s.run_to_convergence()
    return s, CalibrationPanel(state=s)


def test_theta_posterior_matches_the_posterior_samples(beam):
    s, panel = beam
    case, hm = s.case, s.history_match
    assert panel._text_div.text == map_text(case, hm.theta_map)
    assert f"l_cr = {hm.theta_map[0]:.4g} mm" in panel._text_div.text
    figs = figures(panel)[:case.p]
    draws = hm.posterior_samples(4000, seed=1)           # independent: SIR, another seed
    pool = hm.nroy_samples(4000, seed=0)                 # the weighting the plot shows
    ll = hm.log_likelihood(pool)
    w = np.exp(ll - ll.max())
    w /= w.sum()
    for j, fig in enumerate(figs):
        name, unit = case.theta_names[j], case.theta_units[j]
        assert fig.title.text == f"{name}: θ_MAP = {hm.theta_map[j]:.4g} {unit}"
        lo, hi = case.theta_bounds[j]
        assert (fig.x_range.start, fig.x_range.end) == (lo, hi)
        post, _ = one(fig, "posterior (ESS")
        x, width = 0.5 * (post["left"] + post["right"]), post["right"] - post["left"]
        assert x.min() > lo and x.max() < hi
        assert abs(np.sum(post["top"] * width) - 1.0) < 1e-9              # a density
        mean = np.sum(x * post["top"] * width)
        # Binning moves the mean by less than half a bin; the two Monte Carlo estimates
        # (ESS ≈ 850 and 4000 draws) differ by a few hundredths of a posterior sd.
        assert abs(mean - w @ pool[:, j]) < 0.5 * width[0]
        assert abs(mean - draws[:, j].mean()) < 0.15 * draws[:, j].std()
        nroy, _ = one(fig, "NROY")
        assert abs(np.sum(nroy["top"] * width) - 1.0) < 1e-9 and np.count_nonzero(nroy["top"]) > 5
        # The density axis is set by the server to hold both histograms (a fitted one
        # warned while blank and sent each fit back to the server).
        top = max(nroy["top"].max(), post["top"].max())
        assert (fig.y_range.start, fig.y_range.end) == (0.0, pytest.approx(1.05 * top))
        at_map, line = one(fig, "θ_MAP")
        assert list(at_map["x"]) == [hm.theta_map[j]] and line.glyph.line_color == "red"
        truth, _ = one(fig, "true θ")
        assert list(truth["x"]) == [case.theta_true[j]]


def test_simulator_at_map_equals_the_simulator(beam):
    s, panel = beam
    case, hm = s.case, s.history_match
    (fig,) = figures(panel)[case.p:]
    curve, _ = one(fig, "simulator at θ_MAP")
    x = curve["x"]
    assert x.size == 201 and np.allclose(
        curve["y"], case.simulate(x[:, None], hm.theta_map)[0, :, 0], rtol=1e-12, atol=0)
    truth, _ = one(fig, "simulator at true θ")
    np.testing.assert_allclose(truth["y"], case.simulate(x[:, None], case.theta_true)[0, :, 0],
                               rtol=1e-12)
    train, _ = one(fig, "training data")
    assert np.array_equal(train["y"], case.z_train[:, 0])
    test, _ = one(fig, "test data")
    assert np.array_equal(test["x"], case.X_test[:, 0])
    rmse = np.sqrt(np.mean((case.simulate(case.X_train, hm.theta_map)[0] - case.z_train) ** 2))
    assert fig.title.text == f"tip deflection at θ_MAP (RMSE {rmse:.4g} mm)"


def test_a_new_wave_redraws_in_place_and_a_new_case_rebuilds():
    s = ExplorerState(case_name="shear-5")
    panel = CalibrationPanel(state=s)
    assert panel._body.styles == SLOT                    # nothing shown before the first wave
    built = figures(panel)                               # but built: E, ν, ρ and ω1
    s.next_wave()
    assert panel._body.styles == CURRENT and figures(panel) == built
    figs = figures(panel)
    assert len(figs) == 3 + 1                            # E, ν, ρ; the output shown, ω1
    hm = s.history_match
    for o in range(5):                                   # each mode when it is shown
        s.output = f"ω{o + 1}"
        (fig,) = [f for f in figures(panel)[3:] if f.visible]
        assert fig.title.text.startswith(f"ω{o + 1} at θ_MAP (RMSE ")
        curve, _ = one(fig, "simulator at θ_MAP")
        np.testing.assert_allclose(curve["y"], s.case.simulate(curve["x"][:, None],
                                                               hm.theta_map)[0, :, o],
                                   rtol=1e-12)
    figs = figures(panel)
    assert len(figs) == 3 + 5                            # each built once
    s.output = "ω2"
    layout = list(panel._layout.objects)
    s.n_candidates = 20_000                              # a new history match
    s.next_wave()
    assert list(panel._layout.objects) == layout and figures(panel) == figs
    s.case_name = "beam-2d"                              # one parameter, a 2-D input
    assert panel._body.styles == SLOT                    # nothing shown before its wave
    s.next_wave()
    assert panel._body.styles == CURRENT
    (post,) = figures(panel)
    hm = s.history_match
    assert post.title.text == f"E: θ_MAP = {hm.theta_map[0]:.4g} GPa"
