"""Plotting functions: arrays in, Bokeh figures out (the KOH θ posterior: HoloViews).

Nothing here computes a model; everything takes the numbers the state already holds.
The Metrics tab's figures are plain Bokeh: HoloViews took 0.32 s per plot to build, and
shear-5's tab (the chart and eight φ posteriors) 3.9 s.
"""

from __future__ import annotations

import holoviews as hv
import numpy as np
from bokeh.models import ColumnDataSource, FixedTicker, HoverTool, LegendItem, Range1d

from mdcore._pipeline import Method

from .live_figures import below_legend, live_figure

#: Category10 (the wave colours repeat after ten waves).
WAVE_COLORS = ["#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2",
               "#7f7f7f", "#bcbd22", "#17becf"]
METHOD_COLORS = {Method.S1: "#1f77b4", Method.S2: "#ff7f0e", Method.S3: "#2ca02c",
                 Method.KOH: "#d62728"}
#: θ_MAP's marker on every θ plot: a red star (the truth is a cross or a dashed line).
THETA_MAP_COLOR = "red"
THETA_MAP_MARKER = {"marker": "star", "size": 18, "fill_color": THETA_MAP_COLOR,
                    "line_color": "black", "line_width": 1}
#: Marker colour of the paper's reference values in the metrics chart.
PAPER_COLOR = "#dd8452"
PLOT = {"responsive": True, "height": 300, "min_width": 200, "tools": ["hover"], "show_grid": True}


def axis_label(name: str, unit: str) -> str:
    return f"{name} [{unit}]" if unit and unit != "-" else name


def input_span(case, d: int) -> tuple[float, float]:
    """(min, max) of input ``d`` over the training and test inputs."""
    X = np.vstack([case.X_train, case.X_test])
    return float(X[:, d].min()), float(X[:, d].max())


def koh_posterior(case, model) -> list:
    """KOH: per parameter, the chain's histogram against the prior density and the truth.

    A posterior that looks like the prior is the non-identifiability the paper warns of:
    the GP discrepancy absorbs what θ should explain.
    """
    out = []
    for j, (name, unit) in enumerate(zip(case.theta_names, case.theta_units)):
        label = axis_label(name, unit)
        samples = model.theta[:, j]
        lo, hi = case.theta_bounds[j]
        edges = np.linspace(lo, hi, 61)
        density, _ = np.histogram(samples, bins=edges, density=True)
        mu, var = model.theta_prior.mean[j], model.theta_prior.var[j]
        x = np.linspace(lo, hi, 200)
        prior = np.exp(-0.5 * (x - mu) ** 2 / var) / np.sqrt(2 * np.pi * var)
        layers = [hv.Histogram((edges, density), kdims=[label], vdims=["density"],
                               label="KOH posterior").opts(
                      color=METHOD_COLORS[Method.KOH], alpha=0.5, line_alpha=0),
                  hv.Curve((x, prior), label, "density", label="prior").opts(
                      color="black", line_dash="dotted")]
        if case.theta_true is not None:          # a segment, not an hv.VLine: it has a legend
            t, top = float(case.theta_true[j]), 1.05 * max(density.max(), prior.max())
            layers.append(hv.Curve(([t, t], [0.0, top]), label, "density",
                                   label="true θ").opts(color="black", line_width=2))
        out.append(hv.Overlay(layers).opts(title=f"KOH posterior of {name}",
                                           legend_position="bottom", legend_cols=3, **PLOT))
    return out


# --- θ_MAP, the weighted θ posterior, scenario 3's φ posterior, the simulator at θ_MAP and
# --- the metrics chart (issue 17, "the missing views").

def phi_names(n_out: int, d_x: int) -> list[str]:
    """Names of the discrepancy GP's log hyperparameters in the layout of docs/method.md §2.

    Parameters
    ----------
    n_out, d_x : int
        The GP's simulator-output inputs (d_y = n_out) and physical inputs.

    Returns
    -------
    list of str, length P = 2 + n_out + d_x
        ``["log σ_f", "log ℓ_y1", …, "log ℓ_x1", …, "log σ_n"]`` (without the index where
        there is one of a kind).

    Examples
    --------
    >>> phi_names(1, 2)
    ['log σ_f', 'log ℓ_y', 'log ℓ_x1', 'log ℓ_x2', 'log σ_n']
    """
    def numbered(symbol: str, k: int) -> list[str]:
        return [f"log {symbol}"] if k == 1 else [f"log {symbol}{i + 1}" for i in range(k)]

    return ["log σ_f"] + numbered("ℓ_y", n_out) + numbered("ℓ_x", d_x) + ["log σ_n"]


def _phi_meaning(case, c: int) -> str:
    """What φ component ``c`` scales, in words and units (for the axis label)."""
    n_out = case.n_out
    if c == 0:
        return "signal sd"
    if c <= n_out:
        o = c - 1
        return f"lengthscale in {case.output_names[o]}, {case.output_units[o]}"
    if c <= n_out + case.d_x:
        d = c - 1 - n_out
        return f"lengthscale in {case.x_names[d]}, {case.x_units[d]}"
    return "noise sd"


def phi_posterior(case, result, *, output: int | None = None, bins: int = 30) -> list:
    """Scenario 3's hyperparameter posterior against its prior (the paper's Figs 6, 9, 16).

    Scenario 3 draws φ^(j,k) (docs/method.md §2 layout, log scale) and weights each (θ^(j), φ^(j,k))
    pair by its marginal likelihood (Eq. 15). The φ posterior of output o is the histogram
    of all drawn φ weighted by the normalised pair weights ``w_jk`` (they sum to 1 per
    output); the prior is the Gaussian the draws came from.

    Parameters
    ----------
    case : mdcore.Case
    result : mdcore.MethodResult
        A scenario-3 result; its ``model`` (a :class:`mdcore.DiscrepancyModel`)
        holds ``log_params`` (n_out, N_s, N_φ, P) and ``log_weights`` (n_out, N_s, N_φ).
    output : int, optional
        Only this output (default: every output).
    bins : int, default=30

    Returns
    -------
    list of bokeh Figure
        Output by output, component by component (``n_out × P``, or ``P`` with ``output``):
        the weighted histogram (density, green), the prior density (dotted black curve over
        the prior mean ± 4 sd, widened to every draw of weight ≥ 1e-6 × the largest; draws
        beyond fall in the edge bins) and the weighted posterior mean (green line). Titled
        with the output, the component's name (:func:`phi_names`) and the output's ESS.
        Empty for a result that is not scenario 3.
    """
    model = result.model
    if result.method is not Method.S3 or getattr(model, "log_weights", None) is None:
        return []
    prior = model.phi_prior if model.phi_prior is not None else case.phi_prior
    names = phi_names(case.n_out, case.d_x)
    outputs = range(case.n_out) if output is None else [int(output)]
    out = []
    for o in outputs:
        phi = model.log_params[o].reshape(-1, model.log_params.shape[-1])      # (S K, P)
        lw = model.log_weights[o].ravel()                                     # (S K,)
        w = np.exp(lw - lw.max())
        w /= w.sum()
        ess = 1.0 / float(np.sum(w * w))
        carried = w >= 1e-6 * w.max()           # draws that carry visible weight
        for c, name in enumerate(names):
            mu, sd = float(prior.mean[c]), float(np.sqrt(prior.var[c]))
            lo = min(mu - 4 * sd, float(phi[carried, c].min()))
            hi = max(mu + 4 * sd, float(phi[carried, c].max()))
            edges = np.linspace(lo, hi, bins + 1)
            # Far draws of negligible weight (the adaptive proposal's heavy tails) go to the
            # edge bins rather than stretching the axis, so the histogram keeps all the mass.
            post, _ = np.histogram(np.clip(phi[:, c], lo, hi), bins=edges, weights=w,
                                   density=True)
            x = np.linspace(lo, hi, 301)
            dens = np.exp(-0.5 * ((x - mu) / sd) ** 2) / (sd * np.sqrt(2 * np.pi))
            label = f"{name} ({_phi_meaning(case, c)})"
            title = f"{case.output_names[o]}: {name} (ESS {ess:,.1f} of {w.size:,})"
            fig = live_figure(title, label, "density", "phi-plot", x_range=Range1d(lo, hi))
            hist = fig.quad(left=edges[:-1], right=edges[1:], top=post, bottom=0.0,
                            fill_color=METHOD_COLORS[Method.S3], fill_alpha=0.6, line_alpha=0)
            curve = fig.line(source=ColumnDataSource({label: x, "density": dens}), x=label,
                             y="density", line_color="black", line_dash="dotted", line_width=2)
            mean = fig.vspan(source=ColumnDataSource({label: [float(w @ phi[:, c])]}),
                             x=label, line_color=METHOD_COLORS[Method.S3], line_width=2)
            below_legend(fig, [LegendItem(label="weighted posterior", renderers=[hist]),
                               LegendItem(label="prior", renderers=[curve]),
                               LegendItem(label="posterior mean", renderers=[mean])], ncols=3)
            out.append(fig)
    return out


def metric_bars(case, results, metric: str, paper: dict | None = None) -> list[tuple]:
    """``(method, output, value, paper value or NaN)`` of ``metric`` (a Metrics field) for
    each of ``results`` whose metric is known and each output. ``paper`` is laid out as
    ``mdcore._study.PAPER[case]``: a scalar stands for a single-output case only, a
    sequence gives one value per output."""
    ref = (paper or {}).get(metric) or {}
    rows = []
    for r in results:
        values = getattr(r.metrics, metric)
        if values is None:
            continue
        theirs = ref.get(r.method.value)
        for o in range(case.n_out):
            if theirs is None:
                p = np.nan
            elif np.ndim(theirs) == 0:
                p = float(theirs) if case.n_out == 1 else np.nan
            else:
                p = float(theirs[o]) if len(theirs) == case.n_out else np.nan
            rows.append((r.method, o, float(values[o]), p))
    return rows


#: The metrics :func:`metrics_chart` draws: Metrics field -> short name.
CHART_METRICS = {"nmse_z": "NMSE z", "nmse_delta": "NMSE δ"}


def metrics_chart(case, results, paper=None, *, logy: bool = True):
    """NMSE of z and of δ per method as grouped bars, with the paper's values beside them.

    The pairing of this run's metrics with the paper's is
    :func:`mdcore_app.report.metric_bars`, shared with the HTML report's metrics figures.

    Parameters
    ----------
    case : mdcore.Case
    results : dict
        :class:`mdcore.Method` -> :class:`mdcore.MethodResult`; drawn in
        the order S1, S2, S3, KOH, each in its method colour.
    paper : dict, optional
        The paper's values, as :data:`mdcore._study.PAPER` ``[case.name]`` (``{metric:
        {"1" | "2" | "3" | "koh": value}}``); None draws no reference.
    logy : bool, default=True
        Log y axis (KOH's δ NMSE is ~20× the scenarios' on beam-1d).

    Returns
    -------
    bokeh Figure
        One group of bars per metric (NMSE z; NMSE δ when the true δ is known), and per
        output for multi-output cases ("NMSE z · ω1", …), one bar per method (``quad``:
        bar heights are the metrics, in %); where ``paper`` has a value, a diamond at that
        value just right of the method's bar, legend "paper".

    Raises
    ------
    ValueError
        If ``results`` holds no metric to draw.
    """
    methods = [m for m in Method if m in results]
    rows = {metric: metric_bars(case, [results[m] for m in methods], metric, paper)
            for metric in CHART_METRICS}
    groups = [(metric, o) for o in range(case.n_out) for metric in CHART_METRICS
              if any(r[1] == o for r in rows[metric])]
    if not groups:
        raise ValueError("results holds no metrics to draw; run a method first.")
    values = [r[2] for metric in rows for r in rows[metric]]
    refs = [r[3] for metric in rows for r in rows[metric] if np.isfinite(r[3])]
    positive = [v for v in values + refs if v > 0]
    floor = (min(positive) / 3 if positive else 1e-3) if logy else 0.0
    top = max(values + refs)
    slot = 0.8 / len(methods)
    bars = {m: [] for m in methods}
    marks = []
    for g, (metric, o) in enumerate(groups):
        for metric_o in rows[metric]:
            m, out, value, ref = metric_o
            if out != o:
                continue
            left = g - 0.4 + methods.index(m) * slot
            bars[m].append((left + 0.05 * slot, floor, left + 0.65 * slot, value,
                            m.label, case.output_names[o], CHART_METRICS[metric], value))
            if np.isfinite(ref):
                marks.append((left + 0.82 * slot, ref, m.label, CHART_METRICS[metric]))
    ticks = {g: CHART_METRICS[metric] if case.n_out == 1 else
             f"{CHART_METRICS[metric]} · {case.output_names[o]}"
             for g, (metric, o) in enumerate(groups)}
    scale = ", log scale" if logy else ""
    fig = live_figure(f"NMSE at the test inputs [%]{scale}", "", "NMSE [%]", "metrics-chart",
                      x_range=Range1d(-0.5, len(groups) - 0.5),
                      y_range=Range1d(floor, top * (3 if logy else 1.1)),
                      y_axis_type="log" if logy else "linear")
    fig.xaxis.ticker = FixedTicker(ticks=list(ticks))
    fig.xaxis.major_label_overrides = ticks
    # A log axis over a few decades: ticks at 1, 2 and 5 of each (Bokeh's log ticker
    # labelled only 5, 10 and 15 on beam-1d's 0.2-15 %). Over more, its decades do.
    lo, hi = fig.y_range.start, fig.y_range.end
    if logy and hi / lo <= 1e3:
        decades = range(int(np.floor(np.log10(lo))), int(np.ceil(np.log10(hi))))
        fig.yaxis.ticker = FixedTicker(ticks=[m * 10.0 ** k for k in decades for m in (1, 2, 5)
                                              if lo <= m * 10.0 ** k <= hi])
    items = []
    for m in methods:
        if not bars[m]:
            continue
        cols = list(zip(*bars[m]))
        source = ColumnDataSource({"left": cols[0], "bottom": cols[1], "right": cols[2],
                                   "top": cols[3], "method": cols[4], "output": cols[5],
                                   "metric": cols[6], "NMSE [%]": cols[7]})
        items.append(LegendItem(label=m.label, renderers=[fig.quad(
            source=source, left="left", right="right", top="top", bottom="bottom",
            fill_color=METHOD_COLORS[m], line_alpha=0)]))
    if marks:
        cols = list(zip(*marks))
        source = ColumnDataSource({"x": cols[0], "NMSE [%]": cols[1], "method": cols[2],
                                   "metric": cols[3]})
        items.append(LegendItem(label="paper", renderers=[fig.scatter(
            source=source, x="x", y="NMSE [%]", marker="diamond", size=14,
            fill_color=PAPER_COLOR, line_color="black")]))
    fig.add_tools(HoverTool(tooltips=[("method", "@method"), ("metric", "@metric"),
                                      ("NMSE", "@{NMSE [%]}{0.[000]} %")]))
    below_legend(fig, items, ncols=len(items))
    return fig
