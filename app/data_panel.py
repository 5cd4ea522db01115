"""The Data tab (the paper's Fig. 1): the measurements with their ±2√(V_o + V_m) bars, the
simulator at the true θ and the true discrepancy δ, built once per case in Bokeh; a new V_m
only moves the bars (HoloViews rebuilt the layout: docs/performance.md)."""

from __future__ import annotations

import numpy as np
import panel as pn
import param
from bokeh.models import ColorBar, ColumnDataSource, LegendItem, LinearColorMapper, Range1d
from bokeh.palettes import Viridis256

from .live_figures import LivePanel, MapFigure, below_legend, figure_pane, live_figure, show_only
from .plots import axis_label, input_span
from .sources import replace_data
from .state import ExplorerState

#: CSS class of the Data tab's plots (the browser tests and the bench wait for them).
CSS = "data-plot"
#: Points of the simulator and δ curves (1-D input), and of the true-δ image per side.
GRID, GRID_2D = 201, 60
SIMULATOR_COLOR, DELTA_COLOR = "#d62728", "#9467bd"


def error_bars(x: np.ndarray, z: np.ndarray, half_width: float) -> dict:
    """Columns of vertical bars ``z ± half_width`` at ``x`` (both (N,)), for a ``segment``."""
    return {"x": x, "y0": z - half_width, "y1": z + half_width}


def true_delta_figure(case, css_class: str):
    """2-D input: the true δ on a GRID_2D² grid of the inputs' span, drawn as the
    scenarios' δ maps (blue < 0 < red); None when δ is unknown."""
    u1, u2 = (np.linspace(*input_span(case, d), GRID_2D) for d in range(2))
    g1, g2 = np.meshgrid(u1, u2)
    delta = case.true_delta(np.column_stack([g1.ravel(), g2.ravel()]))
    if delta is None:
        return None
    x1, x2 = (axis_label(n, u) for n, u in zip(case.x_names, case.x_units))
    fig = MapFigure(title="true discrepancy δ", xname=x1, yname=x2, u1=u1, u2=u2,
                    zname=axis_label("δ " + case.output_names[0], case.output_units[0]),
                    diverging=True, css_class=css_class)
    fig.show(delta[:, 0].reshape(GRID_2D, GRID_2D))
    return fig.figure


class DataPanel(LivePanel):
    """Data, simulator at the true θ and true δ of the output shown (1-D input; a case
    with several outputs shows one at a time, ``state.output``) or as maps (beam-2d); the
    bars follow V_m in place."""

    state = param.ClassSelector(class_=ExplorerState)
    UPDATE_ON = ("v_m", "output")
    SIZING = "stretch_both"                      # the plots fill the tab's height

    def _rebuild(self, *_):
        c = self.state.case
        self._case = c
        #: output -> (bars source, x, z) of its training data
        self._bars: dict[int, tuple[ColumnDataSource, np.ndarray, np.ndarray]] = {}
        self._titled: list = []            # (figure, output) whose title states the bars
        #: output -> its row of panes (1-D input), built when the output is first shown
        self._rows: dict[int, pn.Row] = {}
        if c.d_x == 2:
            figs = self._maps()
            self._update()                   # drawn before it is attached (see LivePanel)
            self._layout.objects = [pn.Row(*[figure_pane(f, stretch=True) for f in figs],
                                           sizing_mode="stretch_both")]
            return
        self._layout.objects = []
        self._update()

    def _curves(self, o: int) -> list:
        """1-D input, output o: the data with bars and the simulator, then the true δ."""
        c = self._case
        xname = axis_label(c.x_names[0], c.x_units[0])
        xs = np.linspace(*input_span(c, 0), GRID)[:, None]
        sim = None if c.theta_true is None else c.simulate(xs, c.theta_true)[0]
        delta = c.true_delta(xs)
        yname = axis_label(c.output_names[o], c.output_units[o])
        fig = live_figure(f"{c.output_names[o]}: data and simulator", xname, yname, CSS)
        bars = ColumnDataSource(error_bars(c.X_train[:, 0], c.z_train[:, o], 0.0))
        self._bars[o] = (bars, c.X_train[:, 0], c.z_train[:, o])
        items = [
            LegendItem(label="train ±2√(V_o+V_m)", renderers=[fig.segment(
                "x", "y0", "x", "y1", source=bars, line_color="black", line_alpha=0.5,
                line_width=2)]),
            LegendItem(label="training data", renderers=[fig.scatter(
                c.X_train[:, 0], c.z_train[:, o], color="black", size=6)]),
            LegendItem(label="test data", renderers=[fig.scatter(
                c.X_test[:, 0], c.z_test[:, o], color="grey", size=4, alpha=0.6)])]
        if sim is not None:
            items.append(LegendItem(label="simulator at true θ", renderers=[fig.line(
                xs[:, 0], sim[:, o], line_color=SIMULATOR_COLOR, line_width=2)]))
        below_legend(fig, items, ncols=2)
        figs = [fig]
        if delta is not None:
            d = live_figure(f"true discrepancy δ, {c.output_names[o]}", xname,
                            axis_label("δ " + c.output_names[o], c.output_units[o]), CSS)
            line = d.line(xs[:, 0], delta[:, o], line_color=DELTA_COLOR, line_width=2)
            below_legend(d, [LegendItem(label="true δ", renderers=[line])], ncols=1)
            figs.append(d)
        return figs

    def _maps(self) -> list:
        """2-D input: the training data coloured by the output, and the true δ map."""
        c = self._case
        x1, x2 = (axis_label(n, u) for n, u in zip(c.x_names, c.x_units))
        span = [input_span(c, d) for d in range(2)]
        ranges = {"x_range": Range1d(*span[0]), "y_range": Range1d(*span[1])}
        z = c.z_train[:, 0]
        fig = live_figure("training data", x1, x2, CSS, **ranges)
        mapper = LinearColorMapper(palette=Viridis256, low=float(z.min()), high=float(z.max()))
        points = ColumnDataSource({"x": c.X_train[:, 0], "y": c.X_train[:, 1], "z": z})
        fig.scatter("x", "y", source=points, size=9, line_color="black",
                    fill_color={"field": "z", "transform": mapper})
        fig.add_layout(ColorBar(color_mapper=mapper, width=10, title=axis_label(
            c.output_names[0], c.output_units[0])), "right")
        self._titled.append((fig, 0))
        figs = [fig]
        delta = true_delta_figure(c, CSS)
        return figs if delta is None else [*figs, delta]

    def _update(self, *_):
        """The output shown (built the first time), and the bars at ±2√(V_o + V_m) of the
        current V_m."""
        c = self._case
        if c is not self.state.case:
            return                               # a new case: its rebuild draws it all
        half = 2.0 * np.sqrt(c.noise_var + self.state.v_m_vector())
        shown = self.state.output_index
        new_row = c.d_x == 1 and shown not in self._rows
        if new_row:
            panes = [figure_pane(f, stretch=True) for f in self._curves(shown)]
            self._rows[shown] = pn.Row(*panes, sizing_mode="stretch_both")
        for o, (source, x, z) in self._bars.items():
            replace_data(source, error_bars(x, z, float(half[o])))
        for fig, o in self._titled:
            fig.title.text = f"training data (±2√(V_o+V_m) = ±{half[o]:.3g})"
        if c.d_x == 1:
            show_only(self._rows, shown, self._layout, attach=new_row)
