"""Plotting functions: arrays in, Bokeh figures out (the KOH θ posterior: HoloViews).

The Metrics tab's figures are plain Bokeh: HoloViews took 0.32 s per plot to build, and
shear-5's tab (the chart and eight φ posteriors) 3.9 s.
"""

from __future__ import annotations

import holoviews as hv
import numpy as np
from bokeh.models import ColumnDataSource, FixedTicker, HoverTool, LegendItem, Range1d
from bokeh.palettes import Category10

from mdcore._export import with_unit
from mdcore._pipeline import Method

from .live_figures import below_legend, live_figure

#: The wave colours repeat after ten waves.
WAVE_COLORS = list(Category10[10])
METHOD_COLORS = {Method.S1: "#1f77b4", Method.S2: "#ff7f0e", Method.S3: "#2ca02c",
                 Method.KOH: "#d62728"}
#: θ_MAP's marker on every θ plot: a red star (the truth is a cross or a dashed line).
THETA_MAP_COLOR = "red"
THETA_MAP_MARKER = {"marker": "star", "size": 18, "fill_color": THETA_MAP_COLOR,
                    "line_color": "black", "line_width": 1}
#: The true θ's marker on the θ plots, drawn over θ_MAP's star (which often hides it).
TRUTH_MARKER = {"marker": "x", "color": "black", "size": 14, "line_width": 3}
#: Marker colour of the paper's reference values in the metrics chart.
PAPER_COLOR = "#dd8452"
PLOT = {"responsive": True, "height": 300, "min_width": 200, "tools": ["hover"], "show_grid": True}


def axis_label(name: str, unit: str) -> str:
    """``name [unit]``, the unit said once (as in the CSV headings); "-" means no unit."""
    return with_unit(name, "" if unit == "-" else unit)


def input_span(case, d: int) -> tuple[float, float]:
    """(min, max) of input ``d`` over the training and test inputs."""
    X = np.vstack([case.X_train, case.X_test])
    return float(X[:, d].min()), float(X[:, d].max())


def koh_posterior(case, model) -> list:
    """KOH: per parameter, the chain's histogram against the prior density and the truth
    (a posterior like the prior: the discrepancy absorbs what θ should explain)."""
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


def phi_names(n_out: int, d_x: int) -> list[str]:
    """Names of the discrepancy GP's P = 2 + n_out + d_x log hyperparameters (docs/method.md
    §2), e.g. ``phi_names(1, 2) == ['log σ_f', 'log ℓ_y', 'log ℓ_x1', 'log ℓ_x2', 'log σ_n']``."""
    def numbered(symbol: str, k: int) -> list[str]:
        return [f"log {symbol}"] if k == 1 else [f"log {symbol}{i + 1}" for i in range(k)]

    return ["log σ_f"] + numbered("ℓ_y", n_out) + numbered("ℓ_x", d_x) + ["log σ_n"]


def _phi_meaning(case, c: int) -> str:
    """What φ component ``c`` scales, in words and units (for the axis label)."""
    if c == 0:
        return "signal sd"
    if c <= case.n_out:
        return f"lengthscale in {case.output_names[c - 1]}, {case.output_units[c - 1]}"
    if c <= case.n_out + case.d_x:
        d = c - 1 - case.n_out
        return f"lengthscale in {case.x_names[d]}, {case.x_units[d]}"
    return "noise sd"


def phi_posterior(case, result, *, output: int | None = None, bins: int = 30) -> list:
    """Scenario 3's φ posterior against its prior (the paper's Figs 6, 9, 16): one figure
    per output (or only ``output``) and component, [] for another method.

    Each shows the histogram of the drawn log φ weighted by the normalised pair weights
    (Eq. 15), the Gaussian prior they were drawn from (over its mean ± 4 sd, widened to
    every draw of weight ≥ 1e-6 of the largest; draws beyond fall in the edge bins) and
    the weighted mean, titled with the output's ESS.
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


def metrics_chart(case, results, paper=None):
    """NMSE of z and of δ [%] per method (``results``: Method -> MethodResult) as bars on a
    log axis, grouped by metric (and output), with the paper's value (``paper`` as in
    :func:`metric_bars`) as a diamond right of each bar. ValueError if there is nothing
    to draw."""
    methods = [m for m in Method if m in results]
    rows = [(metric, *r) for metric in CHART_METRICS
            for r in metric_bars(case, [results[m] for m in methods], metric, paper)]
    if not rows:
        raise ValueError("results holds no metrics to draw; run a method first.")
    groups = [(metric, o) for o in range(case.n_out) for metric in CHART_METRICS
              if any(r[0] == metric and r[2] == o for r in rows)]
    values = [r[3] for r in rows] + [r[4] for r in rows if np.isfinite(r[4])]
    floor = min([v for v in values if v > 0] or [3e-3]) / 3
    slot = 0.8 / len(methods)
    bars = {m: [] for m in methods}
    marks = []
    for metric, m, o, value, ref in rows:
        left = groups.index((metric, o)) - 0.4 + methods.index(m) * slot
        bars[m].append((left + 0.05 * slot, floor, left + 0.65 * slot, value, m.label,
                        case.output_names[o], CHART_METRICS[metric], value))
        if np.isfinite(ref):
            marks.append((left + 0.82 * slot, ref, m.label, CHART_METRICS[metric]))
    ticks = {g: CHART_METRICS[metric] if case.n_out == 1 else
             f"{CHART_METRICS[metric]} · {case.output_names[o]}"
             for g, (metric, o) in enumerate(groups)}
    lo, hi = floor, 3 * max(values)
    fig = live_figure("NMSE at the test inputs [%], log scale", "", "NMSE [%]",
                      "metrics-chart", x_range=Range1d(-0.5, len(groups) - 0.5),
                      y_range=Range1d(lo, hi), y_axis_type="log")
    fig.xaxis.ticker = FixedTicker(ticks=list(ticks))
    fig.xaxis.major_label_overrides = ticks
    if len(ticks) > 4:                       # several outputs: slanted, or they overlap
        fig.xaxis.major_label_orientation = 0.6
    # Over a few decades, ticks at 1, 2 and 5 of each (Bokeh's log ticker labelled only 5,
    # 10 and 15 on beam-1d's 0.2-15 %). Over more, its decades do.
    if hi / lo <= 1e3:
        decades = range(int(np.floor(np.log10(lo))), int(np.ceil(np.log10(hi))))
        fig.yaxis.ticker = FixedTicker(ticks=[m * 10.0 ** k for k in decades for m in (1, 2, 5)
                                              if lo <= m * 10.0 ** k <= hi])
    items = []
    for m in methods:
        if bars[m]:
            cols = dict(zip(("left", "bottom", "right", "top", "method", "output", "metric",
                             "NMSE [%]"), zip(*bars[m])))
            items.append(LegendItem(label=m.label, renderers=[fig.quad(
                source=ColumnDataSource(cols), left="left", right="right", top="top",
                bottom="bottom", fill_color=METHOD_COLORS[m], line_alpha=0)]))
    if marks:
        cols = dict(zip(("x", "NMSE [%]", "method", "metric"), zip(*marks)))
        items.append(LegendItem(label="paper", renderers=[fig.scatter(
            source=ColumnDataSource(cols), x="x", y="NMSE [%]", marker="diamond", size=14,
            fill_color=PAPER_COLOR, line_color="black")]))
    fig.add_tools(HoverTool(tooltips=[("method", "@method"), ("metric", "@metric"),
                                      ("NMSE", "@{NMSE [%]}{0.[000]} %")]))
    below_legend(fig, items, ncols=len(items))
    return fig
