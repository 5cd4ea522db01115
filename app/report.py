"""A self-contained HTML report of a run, drawn with the app's own figure builders.

It holds the case, the settings, the waves with their LOO checks and the space they ruled
out, the θ posterior, the metrics table and chart (with the paper's values), the bands of
every method and the warnings. BokehJS is inlined, so the file opens offline.

Examples
--------
>>> import mdcore
>>> run = mdcore.run_case(mdcore.load_case("beam-1d"), methods=[1],
...                       settings=mdcore.Settings(n_s=10), n_candidates=5000)
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
from bokeh.models import ColumnDataSource, Div, Whisker
from bokeh.resources import Resources

from mdcore import metrics_table
from mdcore._diagnostics import space_views
from mdcore._pipeline import Method, metric_text
from mdcore._study import PAPER

from .calibration_panel import draw_posterior, posterior_figure, theta_posterior
from .case_model import plotting_grid
from .diagnostics_view import loo_table, space_figures
from .live_figures import BandFigure, live_figure
from .plots import METHOD_COLORS, axis_label, metrics_chart

__all__ = ["report_html", "report_layout", "write_report"]

CSS = "report-plot"
#: The columns of :func:`mdcore.metrics_table` in the report.
METRICS = ("NMSE z %", "NMSE δ %", "RMSE δ", "MMD", "LPL", "cover z ±2σ", "cover δ ±2σ",
           "ESS pairs", "k̂", "seconds")
STYLE = ("<style>body{font-family:sans-serif;max-width:1100px;margin:auto}"
         "table{border-collapse:collapse;font-size:13px}td,th{border:1px solid #ccc;"
         "padding:2px 6px;text-align:right}.warn{color:#a00}</style>")


def _table(headers, rows) -> str:
    """An HTML table, every cell escaped."""
    def cells(tag, row):
        return "".join(f"<{tag}>{_html.escape(str(c))}</{tag}>" for c in row)
    body = "".join(f"<tr>{cells('td', row)}</tr>" for row in rows)
    return f"<table><thead><tr>{cells('th', headers)}</tr></thead><tbody>{body}</tbody></table>"


def _warnings(texts) -> str:
    return "".join(f"<p class='warn'>{_html.escape(t)}</p>" for t in texts)


def _bands(case, result, grid) -> list:
    """1-D input: z and δ of each output with the app's band figure on the dense ``grid``
    (the run's own predictions when it made them there); else δ ± 2σ at each test input."""
    label, color = result.method.label, METHOD_COLORS[result.method]
    if case.d_x != 1:
        return [_residual_figure(case, result, o) for o in range(case.n_out)]
    p = result.on_extra
    if p is None or p.z_mean.shape[0] != grid.shape[0]:
        p = result.model.predict(grid)
    x, truth = grid[:, 0], case.true_delta(grid)
    figs = []
    for o, name in enumerate(case.output_names):
        for q, yname, mean, var in (("z", name, p.z_mean, p.z_var),
                                    ("δ", f"δ {name}", p.delta_mean, p.delta_var)):
            points = [] if q == "δ" else [
                (case.X_test[:, 0], case.z_test[:, o], "test data",
                 {"color": "grey", "size": 3, "alpha": 0.6}),
                (case.X_train[:, 0], case.z_train[:, o], "training data",
                 {"color": "black", "size": 5})]
            ref = None if q == "z" or truth is None else truth[:, o]
            band = BandFigure(title=f"{label}: {yname} (±2σ)", color=color, label=label,
                              xname=axis_label(case.x_names[0], case.x_units[0]),
                              yname=axis_label(yname, case.output_units[o]), points=points,
                              reference=None if ref is None else "true δ", css_class=CSS, x=x)
            band.show(x, mean[:, o], var[:, o], 2, reference=ref)
            figs.append(band.figure)
    return figs


def _residual_figure(case, result, o: int):
    """Predicted δ ± 2σ of output o against the test input's index (any input dimension)."""
    p, name = result.on_test, f"δ {case.output_names[o]}"
    fig = live_figure(f"{result.method.label}: {name} at the test inputs (±2σ)",
                      "test input index", axis_label(name, case.output_units[o]), CSS)
    i, mean, sd = np.arange(case.X_test.shape[0]), p.delta_mean[:, o], np.sqrt(p.delta_var[:, o])
    src = ColumnDataSource({"i": i, "m": mean, "lo": mean - 2 * sd, "hi": mean + 2 * sd})
    fig.add_layout(Whisker(source=src, base="i", lower="lo", upper="hi"))
    fig.scatter("i", "m", source=src, color=METHOD_COLORS[result.method], size=4)
    truth = case.true_delta(case.X_test)
    if truth is not None:
        fig.scatter(i, truth[:, o], color="black", marker="x", size=5, legend_label="true δ")
    return fig


def _text(run) -> str:
    """The report's text: settings, waves, diagnostics, metrics and warnings."""
    case, hm, s = run.case, run.hm, run.settings
    theta_map = ", ".join(f"{n} = {v:.4g} {u}" for n, v, u in
                          zip(case.theta_names, hm.theta_map, case.theta_units))
    failures = [[w.index, ", ".join(f"{n} = {v:.6g}" for n, v in zip(case.theta_names, f.theta)),
                 f.message] for w in hm.waves for f in w.failures]
    shares = [[f"Scenario {m}", name, f"{split.share[o]:.2f}"]
              for m, split in run.theta_delta.items() for o, name in enumerate(case.output_names)]
    advice = [v.advice for v in run.validation if v.advice] + [
        t for m, split in run.theta_delta.items()
        for t in split.advice(f"Scenario {m}", case.output_names)]
    rows = metrics_table(run.results, case.output_names)
    notes = advice + [w for r in run.results for w in r.warnings if w not in advice]
    ran = {r.method for r in run.results}
    # Only the settings of the methods that ran (KOH's chain when KOH did not run misled).
    settings = [(name, value) for name, value, users in (
        ("seed", run.seed, None),
        ("N_s", s.n_s, {Method.S2, Method.S3}),
        ("N_φ", s.n_phi, {Method.S3}),
        ("φ proposal", s.proposal, {Method.S3}),
        ("φ̂ swarm steps", s.fit_iterations, {Method.S1, Method.S2, Method.S3}),
        ("KOH chain", f"{s.n_iter:,} ({s.burn_in:,} burn-in)", {Method.KOH}),
        ("threshold T", f"{hm.problem.options.threshold:g}", None),
        ("rule", hm.problem.options.rule, None)) if users is None or users & ran]
    return (
        f"{STYLE}<h1>{_html.escape(case.title)}</h1><p>{_html.escape(case.description)}</p>"
        "<h2>Settings</h2>" + _table([n for n, _ in settings], [[v for _, v in settings]])
        + "<h2>History matching</h2>" + _table(
            ["wave", "NROY % of box", "runs", "failed runs", "status"],
            [[w.index, f"{100 * w.nroy_fraction:.3g}", len(w.runs_theta), len(w.failures),
              w.status] for w in hm.waves])
        + ("<h3>Failed simulator runs</h3>" + _table(["wave", "θ", "message"], failures)
           if failures else "")
        + f"<p>{_html.escape(hm.message)}</p><p>θ_MAP: {_html.escape(theta_map)}; truth in "
          f"NROY: {_html.escape(str(run.truth_in_nroy))}</p>"
        + "<h3>Emulator check, leaving out each run</h3>" + loo_table(run.validation)
        + ("<h3>θ–δ trade-off</h3>" + _table(["method", "output", "share of Var(δ) from θ"],
                                             shares) if shares else "")
        + "<h2>Metrics at the test inputs</h2>" + _table(
            ["method", "output", *METRICS],
            [[r["method"].label, r["output"], *(metric_text(k, r[k]) for k in METRICS)]
             for r in rows])
        + "<h2>Warnings</h2>" + (_warnings(notes) if notes else "<p>None.</p>"))


def report_layout(run):
    """The report's Bokeh layout: text, tables, and the figures (see :func:`report_html`)."""
    case, hm = run.case, run.hm
    figs = space_figures(case, space_views(hm))
    post = theta_posterior(case, hm)
    for j in range(case.p if post is not None else 0):
        cell = posterior_figure(case, j, CSS)
        draw_posterior(cell, case, post, hm.theta_map, j)
        figs.append(cell[0])
    figs.append(metrics_chart(case, {r.method: r for r in run.results}, PAPER.get(case.name)))
    grid = plotting_grid(case)
    bands = [f for r in run.results for f in _bands(case, r, grid)]
    return column(Div(text=_text(run), sizing_mode="stretch_width"),
                  gridplot(figs, ncols=2, sizing_mode="stretch_width"),
                  Div(text="<h2>Bands</h2>"),
                  gridplot(bands, ncols=2, sizing_mode="stretch_width"),
                  sizing_mode="stretch_width")


def report_html(run) -> str:
    """The report of a :class:`mdcore.CaseRun` as one self-contained HTML page.

    The layout is the one root of a document of its own: given bare models, ``components``
    copies in the JS callbacks of Bokeh's current document, which in a server process can
    be a destroyed session's (the served app's download failed on ``_js_event_callbacks``).
    """
    layout = report_layout(run)
    Document().add_root(layout)
    script, div = components(layout)
    # BokehJS inlined; not file_html's resources, which add the scripts of every model
    # class registered in the process (Panel's, served from a path a file cannot load).
    bokeh_js = "".join(f"<script>{code}</script>" for code in Resources(mode="inline").js_raw)
    title = _html.escape(f"mdcore report: {run.case.name}")
    return (f"<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
            f"<title>{title}</title>{bokeh_js}{script}</head><body>{div}</body></html>\n")


def write_report(run, path) -> Path:
    """Write :func:`report_html` to ``path`` (the ``mdcore.report`` entry point of the
    command line's ``--out``); returns the path."""
    path = Path(path)
    path.write_text(report_html(run), encoding="utf-8")
    return path
