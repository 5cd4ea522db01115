"""The plotting functions of issue 17's missing views, as Bokeh figures checked in numbers.

Each plot is a Bokeh figure (HoloViews ones are rendered with ``hv.render``); its glyphs are found by legend label and their data
sources are compared with independent computations from mdcore: scenario 3's importance
weights and prior, and the metrics. (θ_MAP, the θ posterior and the simulator at θ_MAP are
live figures: tests/test_calibration_panel.py and tests/test_waves_panel.py.)
"""

import warnings
from types import SimpleNamespace

import numpy as np
import pytest

pytest.importorskip("holoviews")
import holoviews as hv  # noqa: E402
from bokeh.document import Document  # noqa: E402
from bokeh.model import Model  # noqa: E402
from bokeh.models import GlyphRenderer  # noqa: E402
from legends import legend  # noqa: E402

from mdcore import _cases as cases  # noqa: E402
from mdcore._history_matching import history_match_case  # noqa: E402
from mdcore._pipeline import Method, Settings, run_method  # noqa: E402
from mdcore._study import PAPER  # noqa: E402
from mdcore_app import plots  # noqa: E402

hv.extension("bokeh")


# --- helpers -----------------------------------------------------------------------------

def render(obj):
    """The Bokeh figure of ``obj`` (a figure, or a HoloViews element rendered); every glyph
    renderer must have non-empty data."""
    # A document of its own: an in-process server test may leave a closed session's
    # document as the current one, and HoloViews renders into the current one.
    fig = obj if isinstance(obj, Model) else \
        hv.renderer("bokeh").get_plot(obj, doc=Document()).state
    renderers = list(fig.select({"type": GlyphRenderer}))
    assert renderers, "the plot has no glyphs"
    for r in renderers:
        lengths = {len(v) for v in r.data_source.data.values()}
        assert lengths and min(lengths) > 0, (type(r.glyph).__name__, r.data_source.data)
    return fig


def renderer(fig, label: str) -> GlyphRenderer:
    """The one renderer whose legend label starts with ``label``."""
    found = [r for k, rs in legend(fig).items() if k.startswith(label) for r in rs]
    assert len(found) == 1, (label, list(legend(fig)))
    return found[0]


def one(fig, label: str) -> dict:
    """The data of the one renderer whose legend label starts with ``label``."""
    return dict(renderer(fig, label).data_source.data)


def histogram(data: dict):
    """Centres, widths and heights of a rendered hv.Histogram (a Quad glyph)."""
    left, right = np.asarray(data["left"]), np.asarray(data["right"])
    return 0.5 * (left + right), right - left, np.asarray(data["top"])


def column(data: dict, name: str) -> np.ndarray:
    """The column of a rendered source named ``name``, or the one column starting with it
    (dimension names carry their units: "E [GPa]")."""
    if name in data:
        return np.asarray(data[name])
    keys = [k for k in data if k.startswith(name)]
    assert len(keys) == 1, (name, list(data))
    return np.asarray(data[keys[0]])


# --- fixtures ----------------------------------------------------------------------------

@pytest.fixture(scope="module")
def beam():
    case = cases.load("beam-1d")
    return case, history_match_case(case, n_candidates=4000)


@pytest.fixture(scope="module")
def results(beam):
    case, hm = beam
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")          # low ESS at these sizes, on purpose
        return {m: run_method(case, hm, m, Settings(n_s=30, n_phi=8), seed=0)
                for m in (Method.S1, Method.S3)}


# --- scenario 3's φ posterior -------------------------------------------------------------

def test_phi_posterior_is_the_weighted_draws_against_the_prior(beam, results):
    case, _ = beam
    model = results[Method.S3].model
    P = model.log_params.shape[-1]
    names = plots.phi_names(case.n_out, case.d_x)
    assert names == ["log σ_f", "log ℓ_y", "log ℓ_x", "log σ_n"] and len(names) == P
    w = np.exp(model.log_weights[0]).ravel()                   # independent of the plot
    assert abs(w.sum() - 1.0) < 1e-12
    ess = 1.0 / np.sum(w * w)
    phi = model.log_params[0].reshape(-1, P)
    overlays = plots.phi_posterior(case, results[Method.S3])
    assert len(overlays) == case.n_out * P
    for c, obj in enumerate(overlays):
        fig = render(obj)
        assert fig.title.text == f"tip deflection: {names[c]} (ESS {ess:,.1f} of {w.size})"
        assert fig.xaxis[0].axis_label.startswith(names[c])
        x, width, dens = histogram(one(fig, "weighted posterior"))
        assert abs(np.sum(dens * width) - 1.0) < 1e-9             # the weights sum to 1
        assert abs(np.sum(x * dens * width) - w @ phi[:, c]) < 0.5 * width[0]
        mean_line = column(one(fig, "posterior mean"), names[c])
        assert np.allclose(mean_line, [w @ phi[:, c]], rtol=0, atol=1e-12)
        prior = one(fig, "prior")
        xs, ys = column(prior, names[c]), column(prior, "density")
        assert abs(np.trapezoid(ys, xs) - 1.0) < 1e-3              # ±4 sd at least
        mu, var = case.phi_prior.mean[c], case.phi_prior.var[c]
        assert np.allclose(ys, np.exp(-0.5 * (xs - mu) ** 2 / var) / np.sqrt(2 * np.pi * var))
    assert len(plots.phi_posterior(case, results[Method.S3], output=0)) == P
    assert plots.phi_posterior(case, results[Method.S1]) == []


def test_phi_posterior_of_the_adaptive_proposal_keeps_all_the_weight(beam):
    case, hm = beam
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = run_method(case, hm, Method.S3, Settings(n_s=30, n_phi=8, proposal="adaptive"),
                            seed=0)
    P = result.model.log_params.shape[-1]
    w = np.exp(result.model.log_weights[0]).ravel()
    phi = result.model.log_params[0].reshape(-1, P)
    for c, obj in enumerate(plots.phi_posterior(case, result)):
        x, width, dens = histogram(one(render(obj), "weighted posterior"))
        assert abs(np.sum(dens * width) - 1.0) < 1e-9
        assert abs(np.sum(x * dens * width) - w @ phi[:, c]) < width[0]


# --- the metrics chart -------------------------------------------------------------------

def test_metrics_chart_bars_are_the_metrics_and_markers_the_paper(beam, results):
    case, _ = beam
    paper = PAPER["beam-1d"]
    fig = render(plots.metrics_chart(case, results, paper))
    ticks = fig.xaxis[0].major_label_overrides
    assert list(ticks.values()) == ["NMSE z", "NMSE δ"]
    labels = legend(fig)
    assert set(labels) == {"Scenario 1", "Scenario 3", "paper"}
    marks = one(fig, "paper")
    for m, r in results.items():
        bars = one(fig, m.label)
        want = [r.metrics.nmse_z[0], r.metrics.nmse_delta[0]]
        assert np.allclose(bars["top"], want, rtol=1e-12, atol=0)
        assert np.all(np.asarray(bars["bottom"]) < min(want))   # bars start below, log axis
        for g, metric in enumerate(("nmse_z", "nmse_delta")):
            right = bars["right"][g]
            # the paper's value sits just right of its bar, inside the method's slot
            i = [k for k, x in enumerate(marks["x"]) if right < x < right + 0.1]
            assert len(i) == 1 and marks["NMSE [%]"][i[0]] == paper[metric][m.value]
            assert abs(bars["left"][g] - g) < 0.5
    assert fig.y_scale.__class__.__name__ == "LogScale"
    ticks = fig.yaxis[0].ticker.ticks                  # 1-2-5 in the axis's decades
    assert ticks and all(fig.y_range.start <= t <= fig.y_range.end for t in ticks)
    assert {round(t / 10 ** np.floor(np.log10(t)), 9) for t in ticks} <= {1.0, 2.0, 5.0}


def test_metrics_chart_groups_by_output_and_shares_the_reports_pairing():
    case = cases.load("shear-5")
    z = {Method.S1: (1.0, 2.0, 3.0, 4.0, 5.0), Method.KOH: (1.5, 2.5, 3.5, 4.5, 5.5)}
    results = {m: SimpleNamespace(method=m, metrics=SimpleNamespace(nmse_z=v, nmse_delta=None))
               for m, v in z.items()}
    fig = render(plots.metrics_chart(case, results))
    assert list(fig.xaxis[0].major_label_overrides.values()) == \
        [f"NMSE z · ω{o}" for o in range(1, 6)]
    assert "paper" not in legend(fig)
    for m, v in z.items():
        assert np.allclose(one(fig, m.label)["top"], v)
    # The pairing with the paper's values is one function, shared with the report:
    # a scalar stands for single-output cases only, a sequence gives one per output.
    paper = {"nmse_z": {"1": 9.0, "koh": list(z[Method.S1])}}
    rows = plots.metric_bars(case, results.values(), "nmse_z", paper)
    assert [(r[0], r[1], r[2]) for r in rows] == [(m, o, v[o]) for m, v in z.items()
                                                  for o in range(5)]
    assert all(np.isnan(r[3]) for r in rows[:5])
    assert [r[3] for r in rows[5:]] == list(z[Method.S1])
    marks = one(render(plots.metrics_chart(case, results, paper)), "paper")
    assert list(marks["NMSE [%]"]) == list(z[Method.S1])
    with pytest.raises(ValueError, match="run a method first"):
        plots.metrics_chart(case, {})


# --- KOH's θ posterior ----------------------------------------------------------------------

def test_koh_posterior_is_the_chain_against_the_prior_and_the_true_theta(beam):
    case, hm = beam
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")          # a short chain: few autocorrelation times
        result = run_method(case, hm, Method.KOH, Settings(n_iter=3000, burn_in=1000), seed=0)
    model = result.model
    figs = [render(o) for o in plots.koh_posterior(case, model)]
    assert len(figs) == len(case.theta_names) == 2
    for j, fig in enumerate(figs):
        name = case.theta_names[j]
        assert fig.title.text == f"KOH posterior of {name}"
        x, width, dens = histogram(one(fig, "KOH posterior"))
        lo, hi = case.theta_bounds[j]
        inside = np.mean((model.theta[:, j] >= lo) & (model.theta[:, j] <= hi))
        assert abs(np.sum(dens * width) - 1.0) < 1e-9 and inside == 1.0
        assert abs(np.sum(x * dens * width) - model.theta[:, j].mean()) < width[0]
        prior = one(fig, "prior")
        xs, ys = column(prior, name), column(prior, "density")
        mu, var = model.theta_prior.mean[j], model.theta_prior.var[j]
        assert np.allclose(ys, np.exp(-0.5 * (xs - mu) ** 2 / var) / np.sqrt(2 * np.pi * var))
        truth = one(fig, "true θ")                 # in the legend (an hv.VLine was not)
        assert np.array_equal(column(truth, name), [case.theta_true[j]] * 2)
        ty = column(truth, "density")
        assert ty[0] == 0.0 and ty[1] >= max(dens.max(), ys.max())


def test_an_axis_label_gives_its_unit_once():
    """Issue 41: beam-lab's case file names its columns ``position_m`` and
    ``deflection_mm``; the axes read "deflection_mm [mm]"."""
    from pathlib import Path

    from mdcore import load_case_file
    case = load_case_file(Path(__file__).resolve().parent.parent / "examples" / "beam_lab"
                          / "beam_lab.toml")
    assert plots.axis_label(case.output_names[0], case.output_units[0]) == "deflection [mm]"
    assert plots.axis_label(case.x_names[0], case.x_units[0]) == "position [m]"
    assert plots.axis_label("tip deflection", "mm") == "tip deflection [mm]"
    assert plots.axis_label("E", "-") == "E" and plots.axis_label("nu", "") == "nu"
