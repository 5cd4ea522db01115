"""What history matching calibrated, on the History matching tab: θ_MAP in numbers, the
weighted θ posterior (a histogram per parameter) and the simulator at θ_MAP against the
data per output (the paper's Fig. 12 for shear-5). Built once per case; a new wave only
replaces the arrays (HoloViews rebuilt every plot per wave: docs/performance.md)."""

from __future__ import annotations

import html
from typing import NamedTuple

import numpy as np
import panel as pn
import param
from bokeh.core.properties import value
from bokeh.models import ColumnDataSource, LegendItem, Range1d

from .live_figures import (
    CURRENT,
    SLOT,
    LivePanel,
    below_legend,
    figure_pane,
    live_figure,
    live_text,
    show_only,
)
from .plots import THETA_MAP_COLOR, axis_label, input_span
from .sources import blank, replace_data, set_top
from .state import ExplorerState

#: CSS class of the plots (shared with the waves: the browser tests count them together).
CSS = "hm-plot"
#: NROY samples weighted for the θ posterior, and its histogram bins per parameter.
POSTERIOR_SAMPLES, BINS = 4000, 40
#: Points of the input grid of the simulator curves.
GRID = 201
POSTERIOR_COLOR = "#2ca02c"


class ThetaPosterior(NamedTuple):
    """The weighted θ posterior of history matching, binned per parameter: ``edges``
    (bins + 1,) over the prior box, densities (bins,) of the ``nroy`` samples and of the
    same samples weighted by their likelihood (``posterior``), the weights' ``ess`` of
    ``n``."""

    edges: list
    nroy: list
    posterior: list
    ess: float
    n: int


def theta_edges(case, j: int, bins: int = BINS) -> np.ndarray:
    """Edges (bins + 1,) of the histograms of parameter ``j`` over its prior box."""
    return np.linspace(*(float(b) for b in case.theta_bounds[j]), bins + 1)


def theta_posterior(case, hm, n: int = POSTERIOR_SAMPLES, seed=0, *,
                    bins: int = BINS) -> ThetaPosterior | None:
    """The weighted θ posterior of history matching, None when NROY is empty: ``n``
    samples uniform in the final NROY set, each weighted by its normalised likelihood
    (:meth:`mdcore.HistoryMatchResult.log_likelihood`, uniform prior on the box): what
    :meth:`~mdcore.HistoryMatchResult.posterior_samples` resamples, without its noise."""
    if hm.waves[-1].nroy.shape[0] == 0:
        return None
    theta = hm.nroy_samples(n, seed=seed)                                   # (n, p)
    log_l = hm.log_likelihood(theta)                                        # (n,)
    w = np.exp(log_l - log_l.max())                                         # log space
    w /= w.sum()
    edges, nroy, post = [], [], []
    for j in range(case.p):
        e = theta_edges(case, j, bins)
        edges.append(e)
        nroy.append(np.histogram(theta[:, j], bins=e, density=True)[0])
        post.append(np.histogram(theta[:, j], bins=e, weights=w, density=True)[0])
    return ThetaPosterior(edges, nroy, post, 1.0 / float(np.sum(w * w)), n)


def input_grid(case, n: int = GRID) -> np.ndarray:
    """(n, 1): the span of the training and test inputs of a 1-D case."""
    return np.linspace(*input_span(case, 0), n)[:, None]


def number(v: float, unit: str) -> str:
    """``v`` to four significant figures, with its unit when it has one."""
    return f"{v:.4g} {unit}" if unit and unit != "-" else f"{v:.4g}"


def map_text(case, theta_map) -> str:
    """θ_MAP in numbers (with the truth when known), as HTML for the text above the plots."""
    theta = ", ".join(f"{n} = {number(v, u)}"
                      for n, v, u in zip(case.theta_names, theta_map, case.theta_units))
    truth = "" if case.theta_true is None else " (true: " + ", ".join(
        f"{v:.4g}" for v in case.theta_true) + ")"
    return html.escape(f"θ_MAP (most likely non-implausible θ): {theta}{truth}. Below: the "
                       "weighted θ posterior of history matching (green) over the NROY "
                       "samples (grey).").replace("θ_MAP", "<b>θ_MAP</b>", 1)


def posterior_figure(case, j: int, css: str = CSS):
    """Parameter j, empty until :func:`draw_posterior`: NROY and posterior histograms,
    θ_MAP (solid) and the truth (dashed). Returns (figure, sources, θ_MAP source, item)."""
    name, unit = case.theta_names[j], case.theta_units[j]
    fig = live_figure(name, axis_label(name, unit), "density", css,
                      x_range=Range1d(*(float(b) for b in case.theta_bounds[j])),
                      y_range=Range1d(0.0, 1.0))     # set with the data (set_top)
    e = theta_edges(case, j)
    sources = [ColumnDataSource(blank(BINS, "top", left=e[:-1], right=e[1:])) for _ in range(2)]
    nroy = fig.quad(left="left", right="right", top="top", bottom=0.0, source=sources[0],
                    fill_color="grey", fill_alpha=0.25, line_alpha=0)
    post = fig.quad(left="left", right="right", top="top", bottom=0.0, source=sources[1],
                    fill_color=POSTERIOR_COLOR, fill_alpha=0.6, line_alpha=0)
    at_map = ColumnDataSource(blank(1, "x"))
    line = fig.vspan(x="x", source=at_map, line_color=THETA_MAP_COLOR, line_width=3)
    post_item = LegendItem(label="posterior", renderers=[post])
    items = [LegendItem(label="NROY (uniform)", renderers=[nroy]), post_item,
             LegendItem(label="θ_MAP", renderers=[line])]
    if case.theta_true is not None:
        truth = fig.vspan(x=[float(case.theta_true[j])], line_color="black",
                          line_dash="dashed", line_width=2)
        items.append(LegendItem(label="true θ", renderers=[truth]))
    below_legend(fig, items, ncols=2)
    return fig, sources, at_map, post_item


def draw_posterior(cell, case, post: ThetaPosterior, theta_map, j: int) -> None:
    """Fill the :func:`posterior_figure` ``cell`` of parameter j."""
    fig, (nroy, weighted), at_map, item = cell
    e = post.edges[j]
    replace_data(nroy, {"left": e[:-1], "right": e[1:], "top": post.nroy[j]})
    replace_data(weighted, {"left": e[:-1], "right": e[1:], "top": post.posterior[j]})
    set_top(fig.y_range, max(post.nroy[j].max(), post.posterior[j].max()))
    replace_data(at_map, {"x": np.array([float(theta_map[j])])})
    item.label = value(f"posterior (ESS {post.ess:,.0f} of {post.n:,})")
    fig.title.text = f"{case.theta_names[j]}: θ_MAP = {number(theta_map[j], case.theta_units[j])}"


class CalibrationPanel(LivePanel):
    """θ_MAP, the θ posterior per parameter and (1-D inputs) the simulator at θ_MAP."""

    state = param.ClassSelector(class_=ExplorerState)
    UPDATE_ON = ("waves", "output")

    # --- structure -----------------------------------------------------------------------
    def _rebuild(self, *_):
        c = self.state.case
        self._case = c
        self._text, self._text_div = live_text("theta-map")
        self._posterior = [posterior_figure(c, j) for j in range(c.p)]
        objects = [self._text, pn.Row(*[figure_pane(f[0]) for f in self._posterior],
                                      sizing_mode="stretch_width")]
        #: output -> (figure, curve source) of the simulator at θ_MAP (1-D input), built
        #: when the output is first shown (state.output: one at a time)
        self._simulator: dict[int, tuple] = {}
        self._simulator_row = pn.Row(sizing_mode="stretch_width")
        if c.d_x == 1:                          # the output shown, ahead of θ_MAP
            objects += [pn.pane.Markdown(
                "**The simulator at θ_MAP against the data**: what is left between them is "
                "the discrepancy δ (the RMSE is to the training data)."),
                self._simulator_row]
            self._add_simulator(self.state.output_index)
            show_only({o: cell[2] for o, cell in self._simulator.items()},
                      self.state.output_index, self._simulator_row, attach=True)
        # In the layout from the start, keeping their place but not shown until there is
        # a θ_MAP (a style change then), as the waves' plots (waves_panel).
        self._body = pn.Column(*objects, sizing_mode="stretch_width", styles=SLOT)
        self._layout.objects = [self._body]
        self._update()

    def _add_simulator(self, o: int) -> None:
        """Build the plot of output o, empty until :meth:`_update`: the test (grey) and
        training (black) data, η(x, θ_MAP) (red) and η(x, θ_true) (dashed)."""
        c = self._case
        grid = input_grid(c)
        fig = live_figure(f"{c.output_names[o]} at θ_MAP", axis_label(c.x_names[0], c.x_units[0]),
                          axis_label(c.output_names[o], c.output_units[o]), CSS)
        items = [
            LegendItem(label="test data", renderers=[fig.scatter(
                c.X_test[:, 0], c.z_test[:, o], color="grey", size=4, alpha=0.6)]),
            LegendItem(label="training data", renderers=[fig.scatter(
                c.X_train[:, 0], c.z_train[:, o], color="black", size=6)])]
        curve = ColumnDataSource(blank(grid.shape[0], "y", x=grid[:, 0]))
        items.append(LegendItem(label="simulator at θ_MAP", renderers=[fig.line(
            "x", "y", source=curve, line_color=THETA_MAP_COLOR, line_width=2)]))
        if c.theta_true is not None:
            truth = c.simulate(grid, c.theta_true)[0]
            items.append(LegendItem(label="simulator at true θ", renderers=[fig.line(
                grid[:, 0], truth[:, o], line_color="black", line_dash="dashed")]))
        below_legend(fig, items, ncols=2)
        self._simulator[o] = (fig, curve, figure_pane(fig))

    # --- data ----------------------------------------------------------------------------
    def _update(self, *_):
        s, c = self.state, self._case
        if c is not s.case:
            return                               # a new case: its rebuild draws it all
        hm = s.history_match
        post = None if hm is None else theta_posterior(c, hm)
        if post is None:                         # no wave, or everything ruled out
            if self._body.styles != SLOT:
                self._body.styles = SLOT
            return
        theta_map = hm.theta_map
        self._text_div.text = map_text(c, theta_map)
        for j, cell in enumerate(self._posterior):
            draw_posterior(cell, c, post, theta_map, j)
        if c.d_x == 1:
            grid = input_grid(c)
            shown = s.output_index
            new = shown not in self._simulator
            if new:
                self._add_simulator(shown)
            at_map = c.simulate(grid, theta_map)[0]                           # (G, n_out)
            at_data = c.simulate(c.X_train, theta_map)[0]                     # (N, n_out)
            for o, (fig, curve, _) in self._simulator.items():
                replace_data(curve, {"x": grid[:, 0], "y": at_map[:, o]})
                rmse = float(np.sqrt(np.mean((at_data[:, o] - c.z_train[:, o]) ** 2)))
                # In the title: the legend's two columns must fit a third of 1280 px.
                fig.title.text = (f"{c.output_names[o]} at θ_MAP (RMSE "
                                  f"{number(rmse, c.output_units[o])})")
            show_only({o: cell[2] for o, cell in self._simulator.items()}, shown,
                      self._simulator_row, attach=new)
        if self._body.styles != CURRENT:
            self._body.styles = CURRENT
