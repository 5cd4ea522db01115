"""A self-contained HTML report of a run: opens offline, every resource inline.

The report holds the case, the settings, the history-matching waves, the bands of every
method (z and δ at the test inputs), the metrics table and a metrics chart with the
paper's values, and the warnings. Plots are Bokeh figures with BokehJS inlined
(:class:`bokeh.resources.Resources` in ``inline`` mode), so the file needs no network.

Examples
--------
>>> import mdcore
>>> from mdcore import Settings
>>> from mdcore import run_case
>>> run = run_case(mdcore.load_case("beam-1d"), methods=[1], settings=Settings(n_s=10),
...                n_candidates=5000)
>>> html = report_html(run)
>>> "<script src=" in html, "Bokeh" in html
(False, True)
"""

from __future__ import annotations

import html as _html
from pathlib import Path

import numpy as np
from bokeh.document import Document
from bokeh.embed import components
from bokeh.layouts import column, gridplot
from bokeh.models import ColumnDataSource, Div, FactorRange, Whisker
from bokeh.plotting import figure
from bokeh.resources import Resources

from mdcore._study import PAPER

from .case_model import plotting_grid
from .live_figures import BandFigure

__all__ = ["report_html", "report_layout", "write_report", "metric_bars"]

COLORS = {"1": "#1f77b4", "2": "#ff7f0e", "3": "#2ca02c", "koh": "#d62728"}
LABELS = {"1": "Scenario 1", "2": "Scenario 2", "3": "Scenario 3", "koh": "KOH"}
#: Marker colour of the paper's reference values in the metrics charts.
PAPER_COLOR = "#dd8452"


def _unit(name: str, unit: str) -> str:
    return f"{name} [{unit}]" if unit and unit != "-" else name


def _esc(text) -> str:
    return _html.escape(str(text))


def _on_grid(result, grid):
    """Predictions at the dense ``grid`` (G, d_x): the run's own when it made them there
    (the app's runs predict at its plotting grid), else the fitted model's."""
    p = result.on_extra
    if p is not None and p.z_mean.shape[0] == grid.shape[0]:
        return p
    return result.model.predict(grid)


def _band_figure(case, result, o: int, quantity: str, grid, pred, k: int = 2):
    """z or δ of a 1-D case on a dense grid of inputs, with the app's figure builder
    (:class:`~mdcore_app.live_figures.BandFigure`): the ±kσ band, the mean, and the data
    or the true δ."""
    label = result.method.label
    yname = case.output_names[o] if quantity == "z" else f"δ {case.output_names[o]}"
    points, truth = [], None
    if quantity == "z":
        points = [(case.X_test[:, 0], case.z_test[:, o], "test data",
                   {"color": "grey", "size": 3, "alpha": 0.6}),
                  (case.X_train[:, 0], case.z_train[:, o], "training data",
                   {"color": "black", "size": 5})]
    else:
        truth = case.true_delta(grid)
    band = BandFigure(title=f"{label}: {yname} (±{k:g}σ)",
                      xname=_unit(case.x_names[0], case.x_units[0]),
                      yname=_unit(yname, case.output_units[o]), color=COLORS[result.method.value],
                      label=label, points=points, css_class="report-band",
                      reference=None if truth is None else "true δ", x=grid[:, 0])
    mean, var = ((pred.z_mean, pred.z_var) if quantity == "z"
                 else (pred.delta_mean, pred.delta_var))
    band.show(grid[:, 0], mean[:, o], var[:, o], k,
              reference=None if truth is None else truth[:, o])
    return band.figure


def _residual_figure(case, result, o: int):
    """Any input dimension: predicted δ ± 2σ against the test point index."""
    p = result.on_test
    i = np.arange(case.X_test.shape[0])
    fig = figure(height=260, sizing_mode="stretch_width",
                 title=f"{LABELS[result.method.value]}: δ {case.output_names[o]} at the test "
                       "inputs (±2σ)", x_axis_label="test input index",
                 y_axis_label=_unit(f"δ {case.output_names[o]}", case.output_units[o]))
    sd = np.sqrt(p.delta_var[:, o])
    src = ColumnDataSource({"i": i, "m": p.delta_mean[:, o], "lo": p.delta_mean[:, o] - 2 * sd,
                            "hi": p.delta_mean[:, o] + 2 * sd})
    fig.add_layout(Whisker(source=src, base="i", lower="lo", upper="hi"))
    fig.scatter("i", "m", source=src, color=COLORS[result.method.value], size=4)
    truth = case.true_delta(case.X_test)
    if truth is not None:
        fig.scatter(i, truth[:, o], color="black", marker="x", size=5, legend_label="true δ")
    return fig


def _nroy_figure(run):
    """NROY fraction of the prior box after each wave."""
    f = run.hm.nroy_fraction
    waves = [str(w.index) for w in run.hm.waves]
    fig = figure(height=240, sizing_mode="stretch_width", x_range=waves,
                 title="History matching: NROY fraction of the box per wave",
                 x_axis_label="wave", y_axis_label="NROY fraction")
    fig.vbar(x=waves, top=f, width=0.6, color="#4c72b0")
    return fig


def _theta_figure(run):
    """Final-wave NROY samples in the first two θ (a histogram for one θ), θ_MAP marked."""
    case, hm = run.case, run.hm
    last = hm.waves[-1].nroy
    if case.p == 1:
        hist, edges = np.histogram(last[:, 0], bins=30)
        fig = figure(height=240, sizing_mode="stretch_width",
                     title="Final NROY samples", x_axis_label=_unit(case.theta_names[0],
                                                                    case.theta_units[0]))
        fig.quad(top=hist, bottom=0, left=edges[:-1], right=edges[1:], alpha=0.6)
        fig.scatter([hm.theta_map[0]], [0], size=10, color="red", legend_label="θ_MAP")
        return fig
    fig = figure(height=240, sizing_mode="stretch_width", title="Final NROY samples",
                 x_axis_label=_unit(case.theta_names[0], case.theta_units[0]),
                 y_axis_label=_unit(case.theta_names[1], case.theta_units[1]))
    pick = last[:: max(1, len(last) // 2000)]
    fig.scatter(pick[:, 0], pick[:, 1], size=2, alpha=0.4, legend_label="NROY")
    fig.scatter([hm.theta_map[0]], [hm.theta_map[1]], size=10, color="red",
                legend_label="θ_MAP")
    if case.theta_true is not None:
        fig.scatter([case.theta_true[0]], [case.theta_true[1]], size=10, marker="x",
                    color="black", legend_label="true θ")
    return fig


def metric_bars(case, results, metric: str, paper: dict | None = None) -> list[tuple]:
    """One metric per method and output, beside the paper's value where it has one.

    The one place that pairs this run's metrics with the paper's (mdcore._study.PAPER): the report's
    metrics figures and :func:`mdcore_app.plots.metrics_chart` both draw from it.

    Parameters
    ----------
    case : mdcore.Case
    results : iterable of mdcore.MethodResult
        In the order the bars are drawn. Methods whose metric is None (no true δ) are left out.
    metric : str
        A field of :class:`mdcore._pipeline.Metrics`, e.g. ``"nmse_z"`` or ``"nmse_delta"``.
    paper : dict, optional
        The paper's values in the layout of :data:`mdcore._study.PAPER` ``[case]``:
        ``{metric: {method value ("1", "2", "3", "koh"): value}}``. A single value stands
        for a single-output case only (the paper's tables are per case); a sequence of
        ``n_out`` values gives one per output.

    Returns
    -------
    list of tuple ``(method, output, value, paper_value)``
        ``method`` a :class:`mdcore.Method`, ``output`` the output index,
        ``value`` this run's metric and ``paper_value`` the paper's (NaN where it has none).
    """
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


def _metrics_figure(run, metric: str, title: str):
    """A metric per method and output, with the paper's value where it has one."""
    case = run.case
    rows = metric_bars(case, run.results, metric, PAPER.get(case.name))
    factors = [(LABELS[m.value], case.output_names[o]) for m, o, _, _ in rows]
    ours = [v for _, _, v, _ in rows]
    ref = [p for _, _, _, p in rows]
    if not factors:
        return None
    fig = figure(height=260, sizing_mode="stretch_width", x_range=FactorRange(*factors),
                 title=title + " (log scale)", y_axis_label="%", y_axis_type="log")
    fig.vbar(x=factors, top=ours, bottom=min(min(ours), np.nanmin(ref + [np.inf])) / 3,
             width=0.7, color="#4c72b0", legend_label="this run")
    if np.any(np.isfinite(ref)):
        keep = [i for i, v in enumerate(ref) if np.isfinite(v)]
        fig.scatter([factors[i] for i in keep], [ref[i] for i in keep], size=12,
                    marker="diamond", color=PAPER_COLOR, legend_label="paper")
    fig.xaxis.major_label_orientation = 0.6
    fig.add_layout(fig.legend[0], "right")
    return fig


def _table(headers, rows) -> str:
    head = "".join(f"<th>{_esc(h)}</th>" for h in headers)
    body = "".join("<tr>" + "".join(f"<td>{_esc(c)}</td>" for c in row) + "</tr>" for row in rows)
    return f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


def _fmt(v, spec="{:.4g}") -> str:
    return "—" if v is None or (isinstance(v, float) and not np.isfinite(v)) else spec.format(v)


def report_html(run) -> str:
    """The report of a :class:`mdcore.CaseRun` as one self-contained HTML page.

    The layout is the one root of a document of its own, which ``components`` writes.
    Given bare models, it would make one and copy into it the JS callbacks of Bokeh's
    global current document, which in a server process can be a session's
    document already destroyed (an ``AttributeError`` on ``_js_event_callbacks``: the
    served app's report download failed).
    """
    layout = report_layout(run)
    Document().add_root(layout)
    script, div = components(layout)
    # BokehJS inlined; not file_html's resources, which add the scripts of every model
    # class registered in the process (Panel's, served from a path a file cannot load).
    bokeh_js = "".join(f"<script>{code}</script>" for code in Resources(mode="inline").js_raw)
    title = _esc(f"mdcore report: {run.case.name}")
    return (f"<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
            f"<title>{title}</title>{bokeh_js}{script}</head><body>{div}</body></html>\n")


def _failures(case, hm) -> str:
    """The failed simulator runs of every wave (θ and what went wrong), or nothing."""
    rows = [[w.index, ", ".join(f"{n} = {v:.6g}" for n, v in zip(case.theta_names, f.theta)),
             f.message] for w in hm.waves for f in w.failures]            # _table escapes
    return "<h3>Failed simulator runs</h3>" + _table(["wave", "θ", "message"], rows) \
        if rows else ""


def _diagnostics(run) -> str:
    """Each wave's leave-one-run-out check and each decoupled scenario's θ–δ share
    (docs/diagnostics.md), with their advice."""
    check = _table(["wave", "runs", "LOO |e| > 3 %", "p (bound)", "wrongly ruled out"],
                   [[v.wave, len(v.theta), f"{100 * v.share_beyond_3:.2f}", f"{v.p_value:.2g}",
                     int(v.wrongly_ruled_out.sum())] for v in run.validation])
    share = _table(["method", "output", "share of Var(δ) from θ"],
                   [[LABELS[m], name, f"{split.share[o]:.2f}"]
                    for m, split in run.theta_delta.items()
                    for o, name in enumerate(run.case.output_names)])
    notes = [v.advice for v in run.validation if v.advice] + [
        t for m, split in run.theta_delta.items()
        for t in split.advice(LABELS[m], run.case.output_names)]
    return ("<h3>Emulator check, leaving out each run</h3>" + check
            + ("<h3>θ–δ trade-off</h3>" + share if run.theta_delta else "")
            + "".join(f"<p class='warn'>{_esc(t)}</p>" for t in notes))


def report_layout(run):
    """The report's Bokeh layout: text, tables, and the figures (see :func:`report_html`)."""
    case, hm, s = run.case, run.hm, run.settings
    style = ("<style>body{font-family:sans-serif;max-width:1100px;margin:auto}"
             "table{border-collapse:collapse;font-size:13px}td,th{border:1px solid #ccc;"
             "padding:2px 6px;text-align:right}.warn{color:#a00}</style>")
    theta_map = ", ".join(f"{n} = {v:.4g} {u}" for n, v, u in
                          zip(case.theta_names, hm.theta_map, case.theta_units))
    intro = (f"{style}<h1>{_esc(case.title)}</h1><p>{_esc(case.description)}</p>"
             f"<h2>Settings</h2>" + _table(
                 ["seed", "N_s", "N_φ", "φ proposal", "φ̂ swarm steps", "KOH chain",
                  "threshold T", "rule"],
                 [[run.seed, s.n_s, s.n_phi, s.proposal, s.fit_iterations,
                   f"{s.n_iter:,} ({s.burn_in:,} burn-in)", f"{hm.problem.options.threshold:g}",
                   hm.problem.options.rule]])
             + "<h2>History matching</h2>" + _table(
                 ["wave", "NROY % of box", "runs", "failed runs", "status"],
                 [[w.index, f"{100 * w.nroy_fraction:.3g}", len(w.runs_theta), len(w.failures),
                   w.status] for w in hm.waves])
             + _failures(case, hm)
             + f"<p>{_esc(hm.message)}</p><p>θ_MAP: {_esc(theta_map)}; truth in NROY: "
               f"{_esc(run.truth_in_nroy)}</p>" + _diagnostics(run))
    rows = []
    for r in run.results:
        m, imp = r.metrics, r.importance
        for o, name in enumerate(case.output_names):
            def pick(v, o=o):
                return None if v is None else v[o]
            rows.append([r.method.label, name, _fmt(m.nmse_z[o]), _fmt(pick(m.nmse_delta)),
                         _fmt(pick(m.rmse_delta)), _fmt(m.mmd[o]), _fmt(m.lpl[o], "{:.1f}"),
                         _fmt(m.coverage_z_2sd[o], "{:.2f}"),
                         _fmt(pick(m.coverage_delta_2sd), "{:.2f}"),
                         _fmt(None if imp is None else imp.ess[o], "{:,.1f}"),
                         _fmt(None if imp is None else imp.k_hat[o], "{:.2f}"),
                         _fmt(r.seconds, "{:.2f}")])
    metrics = "<h2>Metrics at the test inputs</h2>" + _table(
        ["method", "output", "NMSE z %", "NMSE δ %", "RMSE δ", "MMD", "LPL", "cover z ±2σ",
         "cover δ ±2σ", "ESS pairs", "k̂", "seconds"], rows)
    notes = [w for r in run.results for w in r.warnings]
    warn = "<h2>Warnings</h2>" + ("".join(f"<p class='warn'>{_esc(w)}</p>" for w in notes)
                                  if notes else "<p>None.</p>")
    figs = [_nroy_figure(run), _theta_figure(run)]
    for metric, title in (("nmse_z", "NMSE of z [%]"), ("nmse_delta", "NMSE of δ [%]")):
        f = _metrics_figure(run, metric, title)
        if f is not None:
            figs.append(f)
    bands = []
    grid = plotting_grid(case)
    for r in run.results:
        pred = _on_grid(r, grid) if case.d_x == 1 else None
        for o in range(case.n_out):
            if case.d_x == 1:
                bands += [_band_figure(case, r, o, q, grid, pred) for q in ("z", "δ")]
            else:
                bands.append(_residual_figure(case, r, o))
    layout = column(Div(text=intro + metrics + warn, sizing_mode="stretch_width"),
                    gridplot(figs, ncols=2, sizing_mode="stretch_width"),
                    Div(text="<h2>Bands</h2>"),
                    gridplot(bands, ncols=2, sizing_mode="stretch_width"),
                    sizing_mode="stretch_width")
    return layout


def write_report(run, path) -> Path:
    """Write :func:`report_html` to ``path``; returns the path."""
    path = Path(path)
    path.write_text(report_html(run), encoding="utf-8")
    return path
