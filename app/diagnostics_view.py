"""The Diagnostics tab (issue 42, docs/diagnostics.md): can the emulator be trusted, what did
each wave rule out, and how much of δ is down to which θ was calibrated to. Numbers and
figures are made when the tab is shown after a change, on the tab's own JobRunner, so they
neither block the session nor supersede its wave or discrepancy job."""

from __future__ import annotations

import html
from functools import partial
from typing import NamedTuple

import numpy as np
import panel as pn
from bokeh.models import (
    ColorBar,
    ColumnDataSource,
    Div,
    FixedTicker,
    HoverTool,
    LegendItem,
    LinearColorMapper,
    Range1d,
)
from bokeh.palettes import Category10, RdBu11, Viridis256
from bokeh.plotting import figure

from mdcore import theta_delta_split, validate_waves
from mdcore._diagnostics import SMALLEST_P, space_views
from mdcore._pipeline import Method

from .alerts import alert_box, warnings_html
from .jobs import JobRunner
from .live_figures import TOOLS, below_legend, live_figure
from .plots import METHOD_COLORS, WAVE_COLORS, axis_label
from .session_loop import show_updating, when_idle, when_shown

HELP = {
    "loo": "Each wave's emulator predicts each simulator run from the others. Left: those "
           "predictions against the simulator (on the diagonal: good). Right: the errors "
           "over the emulator's own sd; trust it when they form a bell curve with about "
           "0.3 % beyond the dashed ±3 lines. Black crosses: runs it would have ruled out "
           "although the simulator keeps them (good θ lost). <b>If it looks bad</b> (p "
           "below 0.001 or crosses): add runs per wave, raise V_m if the simulator itself "
           "is near the cut-off, or give the simulator a smoother output (its log, say).",
    "space": "Left: the share of the prior box not ruled out after each wave. Right: how "
             "much of each parameter's range each wave removed (0: the survivors still "
             "spread over it). <b>If it looks bad</b>: a parameter near 0 after every wave "
             "is not constrained by these data (do not read its θ_MAP); a share near 0 "
             "means V_m may be too small for how wrong the simulator is.",
    "lattice": "One square per pair of parameters, each axis over its prior range. Above the "
               "diagonal: the smallest implausibility over the other parameters (blue: "
               "some θ with these two values survives; red: ruled out whatever the others). "
               "Below: the optical depth, the share of the other parameters' space that "
               "survives (dark: none). Diagonal: that share per parameter, coloured by the "
               "smallest implausibility. <b>If it looks bad</b>: all red means nothing fits "
               "(V_m too small, or a simulator that cannot match the data); a pair blue "
               "everywhere is not told apart by the data.",
    "hits": "Which wave ruled each candidate θ out (black: still in). <b>If it looks "
            "bad</b>: a late wave that removes much of what an earlier one kept means the "
            "earlier emulator was unsure there (see its errors above); late waves that "
            "remove almost nothing can be skipped (a looser convergence ratio).",
    "delta": "δ(x) learned at a few θ of the final non-implausible set (lines, ±2 sd), and "
             "its spread across θ against its spread at one θ. When the spread across θ "
             "dominates (share above 50 %), δ's shape says more about the θ picked than "
             "about the physics the simulator misses. <b>If it looks bad</b>: narrow θ "
             "first (data that tell the parameters apart, or a smaller V_m you can "
             "justify) before reading δ as physics.",
}
#: Points of the hits-by-wave scatter at most (every k-th candidate: they are uniform).
SCATTER_POINTS = 4000
#: Per-θ δ curves drawn (those of the largest weights).
N_CURVES = 5
HELP_WIDTH = 280
_fig = partial(live_figure, css_class="diag-plot")


class Numbers(NamedTuple):
    """What the tab draws: the LOO checks and each wave's runs (R, N, n_out), the space
    views, the θ–δ splits at the test inputs, drawn at ``rows`` of them along ``x``."""

    validations: tuple
    simulated: tuple
    views: object
    splits: dict
    rows: np.ndarray
    x: np.ndarray
    x_label: str


def delta_rows(case) -> tuple[np.ndarray, np.ndarray, str]:
    """Test inputs to draw δ along the first input: all of them for one input; else the
    largest set sharing the other inputs (nearest their median), sorted along x₁."""
    X, name = case.X_test, axis_label(case.x_names[0], case.x_units[0])
    groups, inverse, counts = np.unique(X[:, 1:], axis=0, return_inverse=True,
                                        return_counts=True)
    med = np.median(X[:, 1:], axis=0)
    best = max(range(len(groups)), key=lambda g: (counts[g], -np.abs(groups[g] - med).sum()))
    rows = np.flatnonzero((inverse.ravel() == best) | (case.d_x == 1 or counts[best] < 3))
    rows = rows[np.argsort(X[rows, 0], kind="stable")]
    at = ", ".join(f"{n} = {v:.4g}" for n, v in zip(case.x_names[1:], groups[best]))
    tail = "" if case.d_x == 1 else f" (at {at})" if counts[best] >= 3 else " (all test inputs)"
    return rows, X[rows, 0], name + tail


def compute(case, hm, results: dict) -> Numbers:
    """The tab's numbers for a history match and the discrepancy results shown."""
    rows, x, label = delta_rows(case)
    splits = {m: theta_delta_split(r.model, case.X_test)          # the CLI's share
              for m, r in results.items() if m in (Method.S2, Method.S3)}
    return Numbers(validate_waves(hm, warn=False), tuple(w.emulator.y_train for w in hm.waves),
                   space_views(hm), splits, rows, x, label)


def _help(key: str) -> Div:
    return Div(text=f"<div style='font-size:0.9em;line-height:1.35'>{HELP[key]}</div>",
               width=HELP_WIDTH, css_classes=[f"diag-help-{key}"])


def loo_figures(case, numbers: Numbers, o: int) -> list:
    """Per wave: LOO prediction against the simulator (wrongly ruled-out runs crossed), and
    every wave's standardised errors with the ±3 lines and N(0, 1)."""
    name = axis_label(case.output_names[o], case.output_units[o])
    fig = _fig("Left-out runs", f"simulator: {name}", f"emulator: {name}")
    items, lo, hi = [], np.inf, -np.inf
    for v, y in zip(numbers.validations, numbers.simulated):
        sim, loo, err = y[..., o], v.loo.mean[..., o], v.loo.error[..., o]
        R, N = sim.shape
        lo, hi = min(lo, sim.min(), loo.min()), max(hi, sim.max(), loo.max())
        src = ColumnDataSource({"sim": sim.ravel(), "loo": loo.ravel(), "e": err.ravel(),
                                "run": np.repeat(np.arange(1, R + 1), N),
                                "wave": np.full(R * N, v.wave)})
        r = fig.scatter("sim", "loo", source=src, size=5, alpha=0.7,
                        color=WAVE_COLORS[(v.wave - 1) % 10])
        items.append(LegendItem(label=f"wave {v.wave}", renderers=[r]))
        if (bad := v.wrongly_ruled_out).any():
            r = fig.scatter(sim[bad].ravel(), loo[bad].ravel(), marker="x", size=12,
                            color="black", line_width=2)
            items.append(LegendItem(label="wrongly ruled out", renderers=[r]))
    fig.line([lo, hi], [lo, hi], color="grey", line_dash="dashed")
    fig.add_tools(HoverTool(tooltips=[("wave", "@wave"), ("run", "@run"),
                                      ("standardised error", "@e{0.00}")]))
    below_legend(fig, items)
    errors = np.concatenate([v.loo.error[..., o].ravel() for v in numbers.validations])
    top = min(max(4.5, float(np.abs(errors).max()) * 1.05), 10.0)     # beyond: edge bins
    edges = np.linspace(-top, top, 41)
    dens, _ = np.histogram(np.clip(errors, -top, top), bins=edges, density=True)
    hist = _fig("Standardised errors, all waves", f"(simulator − emulator) / sd, within "
                f"±{top:.3g}", "density", x_range=Range1d(-top, top))
    bars = hist.quad(left=edges[:-1], right=edges[1:], top=dens, bottom=0, fill_alpha=0.6,
                     line_alpha=0)
    x = np.linspace(-top, top, 201)
    normal = hist.line(x, np.exp(-x * x / 2) / np.sqrt(2 * np.pi), color="black",
                       line_dash="dotted")
    lines = hist.vspan(x=[-3.0, 3.0], line_color="#d62728", line_dash="dashed", line_width=2)
    below_legend(hist, [LegendItem(label="left-out errors", renderers=[bars]),
                        LegendItem(label="N(0, 1)", renderers=[normal]),
                        LegendItem(label="±3", renderers=[lines])], ncols=3)
    return [fig, hist]


def loo_table(validations) -> str:
    """One row per wave's LOO check: runs, share beyond ±3, largest error, p and wrongly
    ruled out (the tab's and the report's table)."""
    head = ("<tr><th>wave</th><th>runs</th><th>beyond ±3</th><th>largest |e|</th>"
            "<th>p</th><th>wrongly ruled out</th></tr>")
    body = "".join(
        f"<tr><td>{v.wave}</td><td>{len(v.theta)}</td><td>{100 * v.share_beyond_3:.1f} %"
        f"</td><td>{np.abs(v.loo.error).max():.1f}</td><td>{max(v.p_value, SMALLEST_P):.2g}</td>"
        f"<td>{int(v.wrongly_ruled_out.sum())}</td></tr>" for v in validations)
    return (f"<table class='diag-loo-table' style='border-collapse:collapse' cellpadding='4'>"
            f"{head}{body}</table>")


def space_figures(case, views) -> list:
    """The NROY share per wave and the share of each parameter's range removed."""
    W, p = views.space_removed.shape
    share = _wave_bars("NROY share of the box", "share",
                       views.nroy_fraction, y_range=Range1d(0, 1.05))
    removed = _fig("Range removed per parameter", "", "share of the range",
                   x_range=Range1d(-0.5, p - 0.5), y_range=Range1d(0, 1.05))
    width, items = 0.8 / W, []
    for w in range(W):
        r = removed.vbar(x=np.arange(p) - 0.4 + (w + 0.5) * width,
                         top=views.space_removed[w], width=0.9 * width,
                         color=WAVE_COLORS[w % 10])
        items.append(LegendItem(label=f"wave {w + 1}", renderers=[r]))
    _name_ticks(removed.xaxis, case.theta_names, 0.0)
    below_legend(removed, items, ncols=min(W, 6))
    return [share, removed]


def _name_ticks(axis, names, offset: float) -> None:
    ticks = {k + offset: n for k, n in enumerate(names)}
    axis.ticker = FixedTicker(ticks=list(ticks))
    axis.major_label_overrides = ticks
    axis.minor_tick_line_color = None
    if len(names) > 5:
        axis.major_label_orientation = 0.8


def lattice_figure(case, views):
    """Upper triangle: minimum implausibility; lower: optical depth; diagonal: the 1-D
    optical depth as bars coloured by the 1-D minimum implausibility (Vernon et al. 2010)."""
    p, cut, bins = len(case.theta_names), views.cutoff, views.optical_depth_1d.shape[1]
    size = min(470, 90 * p + 110)
    fig = figure(title="Above: min implausibility; below: depth",
                 width=size + 130, height=size, tools=TOOLS, match_aspect=True,
                 x_range=Range1d(0, p), y_range=Range1d(0, p), css_classes=["diag-lattice"])
    fig.toolbar.logo = None
    implaus = LinearColorMapper(palette=RdBu11, low=0, high=2 * cut,
                                nan_color=(0, 0, 0, 0))
    depth = LinearColorMapper(palette=Viridis256, low=0, high=1, nan_color=(0, 0, 0, 0))
    upper, lower = [], []
    for (k, m), low, dep in zip(views.pairs, views.min_implausibility, views.optical_depth):
        upper.append((low, m, p - 1 - k))          # x: parameter m, y: parameter k
        lower.append((dep.T, k, p - 1 - m))        # x: parameter k, y: parameter m
    for cells, mapper, what in ((upper, implaus, "min implausibility"),
                                (lower, depth, "optical depth")):
        r = fig.image(image=[c[0] for c in cells], x=[c[1] for c in cells],
                      y=[c[2] for c in cells], dw=1, dh=1, color_mapper=mapper)
        fig.add_tools(HoverTool(renderers=[r], tooltips=[(what, "@image{0.00}")]))
    b = np.arange(bins) / bins
    left = np.concatenate([k + b for k in range(p)])
    bottom = np.repeat(p - 1 - np.arange(p), bins).astype(float)
    top = bottom + 0.05 + 0.9 * np.nan_to_num(views.optical_depth_1d.ravel())
    fig.quad(left="l", right="r", bottom="b", top="t", line_alpha=0,
             fill_color={"field": "I", "transform": implaus},
             source=ColumnDataSource({"l": left, "r": left + 1 / bins, "b": bottom, "t": top,
                                      "I": views.min_implausibility_1d.ravel()}))
    _name_ticks(fig.xaxis, case.theta_names, 0.5)
    _name_ticks(fig.yaxis, list(reversed(case.theta_names)), 0.5)
    fig.yaxis.major_label_orientation = "horizontal"
    fig.grid.ticker = FixedTicker(ticks=list(range(p + 1)))
    fig.grid.grid_line_color, fig.grid.grid_line_alpha = "black", 0.5
    for mapper, what in ((implaus, f"min I (cut-off {cut:.3g})"), (depth, "optical depth")):
        fig.add_layout(ColorBar(color_mapper=mapper, title=what, width=10, padding=4,
                                major_label_text_font_size="8pt"), "right")
    return fig


def hits_figures(case, views) -> list:
    """Candidates coloured by the wave that ruled them out (the two parameters most
    constrained; for one parameter, against its implausibility), and their counts."""
    W, p = views.space_removed.shape
    if p == 1:
        a, b = 0, None
    else:
        a, b = sorted(np.argsort(views.space_removed[-1])[::-1][:2])
    pick = slice(None, None, max(1, len(views.theta) // SCATTER_POINTS))
    th, by = views.theta[pick], views.ruled_out_by[pick]
    label = [axis_label(n, u) for n, u in zip(case.theta_names, case.theta_units)]
    yname = "implausibility" if b is None else label[b]
    scatter = _fig("Hits by wave", label[a], yname)
    items = []
    for w in [*range(1, W + 1), 0]:
        sel = by == w
        if sel.any():
            y = views.implausibility[pick][sel] if b is None else th[sel, b]
            r = scatter.scatter(th[sel, a], y, size=3, alpha=0.6,
                                color="black" if w == 0 else WAVE_COLORS[(w - 1) % 10])
            items.append(LegendItem(label="kept" if w == 0 else f"wave {w}", renderers=[r]))
    below_legend(scatter, items, ncols=min(len(items), 4))
    return [scatter, _wave_bars("Ruled out by each wave", "candidates", views.hits)]


def _wave_bars(title: str, yname: str, values, **kw):
    """One bar per wave, in the wave's colour."""
    W = len(values)
    fig = _fig(title, "wave", yname, x_range=Range1d(0.5, W + 0.5), **kw)
    fig.vbar(x=np.arange(1, W + 1), top=values, width=0.6,
             color=[WAVE_COLORS[w % 10] for w in range(W)])
    fig.xaxis.ticker = FixedTicker(ticks=list(range(1, W + 1)))
    return fig


def split_figures(case, numbers: Numbers, method, split, o: int) -> list:
    """δ at the θ of the largest weights, and the between/within bands around δ's mean."""
    name = axis_label(f"δ {case.output_names[o]}", case.output_units[o])
    x, w = numbers.x, split.weight[o]
    curves = _fig(f"Scenario {method.value}: δ at {N_CURVES} θ (±2 sd)", numbers.x_label,
                  name)
    for c, j in enumerate(np.argsort(w)[::-1][:N_CURVES]):
        mean, sd = split.mean[j, numbers.rows, o], np.sqrt(split.var[j, numbers.rows, o])
        color = Category10[10][c]
        curves.varea(x, mean - 2 * sd, mean + 2 * sd, fill_color=color, fill_alpha=0.1)
        curves.line(x, mean, color=color, line_width=2)
    mean = w @ split.mean[:, numbers.rows, o]
    bands = _fig(f"Scenario {method.value}: Var δ from θ {100 * split.share[o]:.0f} %",
                 numbers.x_label, name)
    items = []
    for part, alpha, what in ((split.between, 0.25, "across θ"), (split.within, 0.5,
                                                                    "at one θ")):
        sd = 2 * np.sqrt(part[numbers.rows, o])
        r = bands.varea(x, mean - sd, mean + sd, fill_color=METHOD_COLORS[method],
                        fill_alpha=alpha)
        items.append(LegendItem(label=f"±2 sd {what}", renderers=[r]))
    r = bands.line(x, mean, color="black", line_width=2)
    below_legend(bands, items + [LegendItem(label="δ mean", renderers=[r])], ncols=3)
    return [curves, bands]


def _row(figs, key=None):
    panes = [pn.pane.Bokeh(f, sizing_mode="stretch_width", min_width=250) for f in figs]
    if key is not None:
        panes.append(pn.pane.Bokeh(_help(key)))
    return pn.Row(*panes, sizing_mode="stretch_width")


def _text(html_text: str, css: str = "diag-text") -> pn.pane.Bokeh:
    return pn.pane.Bokeh(Div(text=html_text, css_classes=[css], sizing_mode="stretch_width"),
                         sizing_mode="stretch_width", margin=(5, 10))


class DiagnosticsView(pn.viewable.Viewer):
    """The Diagnostics tab: tab ``index`` of ``tabs``, rebuilt when shown after a change."""

    def __init__(self, state, tabs: pn.Tabs, index: int):
        super().__init__()
        self.state, self._tabs, self._index = state, tabs, index
        self._box = pn.Column(sizing_mode="stretch_width")
        self._stale = True
        self._numbers: tuple | None = None           # (hm, results, Numbers) computed last
        self._jobs = JobRunner(background=state.jobs.background, schedule=state.jobs.schedule,
                               on_error=lambda m: (self._say(m), state.report_error(m)))
        state.param.watch(self._changed, ["waves", "results", "output"])
        when_shown(tabs, index, lambda: self._stale and self.refresh())
        when_idle(state, lambda: self._stale and self.refresh())     # after a job
        self._say("Press “Next wave” or “Run to convergence”, then come back to this tab.")

    numbers = property(lambda self: self._numbers and self._numbers[2], doc="What it shows.")

    def _say(self, text: str) -> None:
        self._box.objects = [_text(f"<i>{html.escape(text)}</i>", "diag-placeholder")]
        self._drawn = False                          # what the box shows is not diagnostics

    def _changed(self, *_):
        self._stale = True
        if self._tabs.active == self._index:
            self.refresh()

    def refresh(self) -> None:
        """Compute (on a worker thread in the served app) and draw what the state holds."""
        self._stale = False
        s, hm = self.state, self.state.history_match
        if hm is None:
            self._say("Press “Next wave” or “Run to convergence” to see the diagnostics.")
            return
        show_updating(self._box, "Computing the diagnostics …", keep=self._drawn)
        case, results = s.case, dict(s.results)
        o = list(case.output_names).index(s.output)
        done = self._numbers

        def work(report, cancel):
            same = (done is not None and done[0] is hm and done[1].keys() == results.keys()
                    and all(done[1][m] is r for m, r in results.items()))
            n = done[2] if same else compute(case, hm, results)
            figs = {"loo": loo_figures(case, n, o), "space": space_figures(case, n.views),
                    "hits": hits_figures(case, n.views), "delta": {
                        m: split_figures(case, n, m, t, o) for m, t in n.splits.items()}}
            if case.p >= 3:
                figs["lattice"] = lattice_figure(case, n.views)
            yield (hm, results, n), figs, case, o

        self._jobs.submit("diagnostics", work, self._show)

    def _show(self, message) -> None:
        self._numbers, figs, case, o = message
        numbers, name = self._numbers[2], case.output_names[o]
        advice = [v.advice for v in numbers.validations if v.advice]
        parts = [_text("<h3>Can the emulator be trusted?</h3>" + loo_table(numbers.validations)
                       + (warnings_html(advice) if advice else
                          alert_box("No wave's emulator is too confident, and no run is "
                                    "wrongly ruled out.", "success")), "diag-loo"),
                 _row(figs["loo"], "loo"),
                 _text("<h3>What did each wave rule out?</h3>"), _row(figs["space"], "space")]
        if "lattice" in figs:
            ranges = "; ".join(f"{html.escape(axis_label(n, u))}: {lo:.4g} to {hi:.4g}"
                               for n, u, (lo, hi) in zip(case.theta_names, case.theta_units,
                                                         case.theta_bounds))
            parts.append(pn.Row(pn.pane.Bokeh(figs["lattice"]), pn.Column(
                pn.pane.Bokeh(_help("lattice")), _text(f"<small>Ranges: {ranges}.</small>"))))
        parts.append(_row(figs["hits"], "hits"))
        parts.append(_text("<h3>How much of δ is down to θ?</h3>"))
        if not figs["delta"]:
            parts.append(_text("<i>Press “Run discrepancy” with scenario 2 or 3 to see the "
                               "θ–δ trade-off.</i>", "diag-placeholder"))
        for m, pair in figs["delta"].items():
            split = numbers.splits[m]
            words = [a for a in split.advice(f"Scenario {m.value}", case.output_names)
                     if a.startswith(f"Scenario {m.value}, {name}:")]
            parts.append(_text(warnings_html(words) if words else alert_box(
                f"Scenario {m.value}, {html.escape(name)}: {100 * split.share[o]:.0f} % of "
                "δ's predictive variance comes from θ; its shape is not mostly a consequence "
                "of the θ chosen.", "success"), "diag-delta"))
            parts.append(_row(pair, "delta"))
        self._box.objects = parts
        self._drawn = True

    def __panel__(self):
        return self._box
