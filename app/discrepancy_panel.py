"""The Discrepancy tab, updated in place: new results, a new band or a new beam-2d slice
replace the arrays of the figures they change (:mod:`.live_figures`); hiding a method only
changes a visibility (its place stays, empty: :data:`SLOT`). The chosen methods' plots are
built empty when the tab is shown, so a run only fills them; during a recompute the
earlier plots stay, dimmed.
"""

from __future__ import annotations

import html
from typing import Any

import numpy as np
import panel as pn
import param
from bokeh.models import Range1d

from mdcore._pipeline import Method

from .alerts import warnings_html
from .band_axes import band_extent
from .data_panel import true_delta_figure
from .discrepancy_text import EMPTY_HTML, empty_html, not_run_html
from .live_figures import (
    CURRENT,
    SLOT,
    BandFigure,
    LivePanel,
    MapFigure,
    check_shown_in,
    figure_pane,
    live_text,
    show_pane,
)
from .plots import METHOD_COLORS, axis_label
from .runs import method_order
from .session_loop import watch_in_session, when_shown
from .state import ExplorerState

#: The "Show" choices of a 1-D case and the quantities they show.
QUANTITIES = {"z and δ": ("z", "delta"), "δ": ("delta",), "z": ("z",)}
#: CSS class of every plot of the tab (the browser tests find them by it).
CSS = "disc-plot"
#: Styles of the earlier plots while their recompute runs (see CURRENT and SLOT).
STALE_OPACITY = "0.45"
STALE = {"opacity": STALE_OPACITY, "visibility": "visible"}
#: New results keep the axes while their extent fits inside and spans at least this
#: fraction of them (another seed, or N_s, seen at the same scale, and not re-laid-out).
KEEP_SPAN = 0.6


class DiscrepancyPanel(LivePanel):
    """Bands of the shown methods: z* and δ* per output (1-D input), or δ maps and a slice
    (beam-2d), one column (1-D) or row (2-D) per method."""

    state = param.ClassSelector(class_=ExplorerState)
    quantity = param.Selector(objects=list(QUANTITIES), default="z and δ", label="Show")

    UPDATE_ON = ("results", "band", "busy", "scenarios", "waves", "card")
    SIZING = "stretch_both"                      # the plots fill the tab's height

    def _setup(self):
        self._show = pn.widgets.RadioButtonGroup.from_param(self.param.quantity)
        # The band beside the bands it sets (it was below the sidebar's fold at 720 px).
        band = self.state.param.band
        self._bar = pn.Row(self._show, pn.pane.HTML(f"<label>{html.escape(band.label)}</label>",
                                                    margin=(12, 5, 0, 25)),
                           pn.widgets.RadioButtonGroup.from_param(band, name="",
                                                                  css_classes=["band-choice"]))
        # One line above the plots: what to press while no plot is shown, else the
        # diagnostics' warnings; its text changes, never its ``visible`` (a page re-layout).
        self._warnings, self._warnings_div = live_text("disc-warnings")
        self._warnings_div.text = EMPTY_HTML
        self._head = pn.Column(sizing_mode="stretch_width")        # beam-2d: truth, slider
        self._methods = pn.Row(sizing_mode="stretch_both")         # 1-D: one column each
        self._layout.objects = [self._bar, self._warnings, self._head, self._methods]
        self._case = None
        self._truth = None
        #: (method, cell key) -> [pane, figure, payload last drawn]
        self._cells: dict[tuple[Method, Any], list] = {}
        self._groups: dict[Method, pn.layout.ListPanel] = {}
        self._pending: dict[Method, list] = {}   # a group's new panes, for _place
        self._drawn: set[Method] = set()         # methods whose plots hold data
        self._ready = lambda: False              # whether to prebuild (the tab is shown)
        self._head_fixed: list = []              # beam-2d: the slider and the truth map
        watch_in_session(self.state, self._slice_moved, "slice_x2")
        watch_in_session(self, self._quantity_changed, "quantity")
        watch_in_session(self.state, self._quantity_changed, "output")

    # --- structure -----------------------------------------------------------------------
    def _rebuild(self, *_):
        """A new case: drop every plot, then draw what the state holds."""
        c = self.state.case
        self._case = c
        self._truth = c.true_delta(self.state.grid)       # None when δ is unknown
        self._cells, self._groups, self._pending, self._drawn = {}, {}, {}, set()
        self._ranges: dict = {}                  # cell key -> axes shared by the methods
        self._fitted: set = set()                # cell keys whose axes have been set
        self._methods.objects = []
        self._show.visible = c.d_x == 1
        # One output at a time (state.output): shear-5's five modes side by side were 20-40
        # plots, all redrawn on every change.
        if c.d_x == 1:
            self._head.objects = []
            self.quantity = "z and δ"
        else:
            # Steps of the grid's rows, shown to 4 decimals: the value is the row drawn
            u2 = np.unique(self.state.grid[:, 1])
            slider = pn.widgets.FloatSlider.from_param(
                self.state.param.slice_x2, step=float(u2[1] - u2[0]) if u2.size > 1 else 0.001,
                format="0.0000")
            truth = true_delta_figure(c, "disc-truth")          # None: δ is unknown
            self._head_fixed = [slider] + ([] if truth is None
                                           else [figure_pane(truth)])
            self._head.objects = list(self._head_fixed)
        self._update()

    def prebuild_when_shown(self, tabs, index: int) -> None:
        """Build the chosen methods' plots, empty and hidden, when tab ``index`` of ``tabs``
        shows this panel and while it does: a run then only fills them. A ValueError
        unless ``(tabs, index)`` is a pn.Tabs and a tab index ≥ 0."""
        check_shown_in((tabs, index), "(tabs, index)")
        self._ready = lambda: tabs.active == index
        when_shown(tabs, index, self._prebuild)

    def _prebuild(self) -> None:
        """Empty, hidden plots of the chosen methods that have none yet (see the module)."""
        if self._case is not self.state.case:
            return
        added = False
        for method in sorted(self.state.scenarios, key=method_order):
            if method in self._groups:
                continue
            panes = []
            for key in self._keys(method):
                if self._wanted(key):
                    fig = self._figure(method, key)
                    pane = figure_pane(fig.figure, stretch=self._case.d_x == 1)
                    self._cells[method, key] = [pane, fig, None]
                    panes.append(pane)
            self._groups[method] = (pn.Row if self._case.d_x == 2 else pn.Column)(
                *panes, sizing_mode=self._sizing(), styles=SLOT)
            added = True
        if added:
            self._place()

    def _sizing(self) -> str:
        """A method's group's sizing: 1-D, it shares the tab's height; beam-2d's rows do not
        (a box once stretched by a child stayed stretched, with its height, for 1-D)."""
        return "stretch_both" if self._case.d_x == 1 else "stretch_width"

    def _keys(self, method: Method) -> list:
        """The cell keys of a method's plots, in display order."""
        c = self._case
        if c.d_x == 2:
            return [0, 1, 2]                    # δ mean, δ sd, slice
        return [(o, q) for o in range(c.n_out) for q in ("z", "delta")]

    def _wanted(self, key) -> bool:
        """Whether the plot of cell ``key`` is shown: its quantity and its output are."""
        c = self._case
        return c.d_x == 2 or (key[1] in QUANTITIES[self.quantity]
                              and key[0] == self.state.output_index)

    def _ensure(self, method: Method) -> None:
        """Build the method's missing plots (those of the quantities shown) and its group."""
        added = False
        for key in self._keys(method):
            if (method, key) in self._cells or not self._wanted(key):
                continue
            payload = self._payload(method, key)
            fig = self._figure(method, key)
            self._draw(fig, key, payload)
            self._drawn.add(method)
            pane = figure_pane(fig.figure, stretch=self._case.d_x == 1)
            self._cells[method, key] = [pane, fig, payload]
            added = True
        if not added and method in self._groups:
            return
        panes = [self._cells[method, k][0] for k in self._keys(method)
                 if (method, k) in self._cells]
        if method in self._groups:
            self._pending[method] = panes        # attached by _place, once drawn
        else:
            self._groups[method] = (pn.Row if self._case.d_x == 2 else pn.Column)(
                *panes, sizing_mode=self._sizing())

    def _place(self) -> None:
        """Put the groups in method order into the layout: one assignment per change
        (each assignment is one message to the browser)."""
        for method, panes in self._pending.items():
            self._groups[method].objects = panes
        self._pending = {}
        groups = [self._groups[m] for m in sorted(self._groups, key=method_order)]
        parent, objects = ((self._head, [*self._head_fixed, *groups])
                           if self._case.d_x == 2 else (self._methods, groups))
        if list(parent.objects) != objects:
            parent.objects = objects

    # --- data ----------------------------------------------------------------------------
    def _payload(self, method: Method, key) -> tuple:
        s = self.state
        result = s.results[method]
        if self._case.d_x == 2:                  # the maps (mean, sd) do not show a band
            return (result, int(s.band), float(s.slice_x2)) if key == 2 else (result, 0)
        return (result, int(s.band))

    def _linked(self, key) -> dict:
        """The x and y ranges of cell ``key``, shared by every method's figure, so their
        bands compare at one scale (as the paper's panels do). :meth:`_fit_ranges` sets
        them."""
        if key not in self._ranges:
            self._ranges[key] = {"x_range": Range1d(0.0, 1.0), "y_range": Range1d(0.0, 1.0)}
        return self._ranges[key]

    def _extent(self, key, held: dict) -> tuple[tuple[float, float], tuple[float, float]]:
        """x and y extents of cell ``key`` over the ``held`` results (:func:`band_extent`)."""
        return band_extent(self.state.grid, self._case, self._truth, key, held)

    def _fit_ranges(self) -> None:
        """Set the shared axes of every band plot to :meth:`_extent`: at once for a new
        plot, else only when the extent leaves them or fills less than
        :data:`KEEP_SPAN` of them."""
        held = self.state.held_results()
        if not self.state.results or not held:
            return                               # nothing to fit to (or a recompute runs)
        for key, ranges in self._ranges.items():
            for rng, (lo, hi) in zip((ranges["x_range"], ranges["y_range"]),
                                     self._extent(key, held)):
                start, end = rng.start, rng.end
                fits = start <= lo and hi <= end and hi - lo >= KEEP_SPAN * (end - start)
                if key in self._fitted and fits:
                    continue
                rng.update(start=lo, end=hi)
            self._fitted.add(key)

    def _figure(self, method: Method, key):
        """The empty figure of one cell."""
        c = self._case
        color, label = METHOD_COLORS[method], method.label
        x1 = axis_label(c.x_names[0], c.x_units[0])
        if c.d_x == 2:
            x2 = axis_label(c.x_names[1], c.x_units[1])
            unit = c.output_units[0]
            if key == 2:
                return BandFigure(title="", xname=x1, yname=axis_label("δ", unit), color=color,
                                  label=label, reference=None if self._truth is None
                                  else "true δ", css_class=CSS, k=self.state.band,
                                  **self._linked(key), x=np.unique(self.state.grid[:, 0]))
            u1, u2 = np.unique(self.state.grid[:, 0]), np.unique(self.state.grid[:, 1])
            zname = axis_label("δ mean" if key == 0 else "δ sd", unit)
            return MapFigure(title="", xname=x1, yname=x2, zname=zname, u1=u1, u2=u2,
                             diverging=key == 0, css_class=CSS)
        o, q = key
        name, unit = c.output_names[o], c.output_units[o]
        of = f", {name}" if c.n_out > 1 else ""            # which output, when several
        if q == "z":
            points = [(c.X_test[:, 0], c.z_test[:, o], "test data",
                       {"color": "grey", "size": 4, "alpha": 0.6}),
                      (c.X_train[:, 0], c.z_train[:, o], "training data",
                       {"color": "black", "size": 7})]
            return BandFigure(title=f"{label}: z{of}", xname=x1,
                              yname=axis_label(name, unit), color=color, label=label,
                              points=points, css_class=CSS, k=self.state.band, **self._linked(key),
                              x=self.state.grid[:, 0])
        return BandFigure(title=f"{label}: δ{of}",
                          xname=x1, yname=axis_label("δ " + name, unit), color=color,
                          label=label, reference=None if self._truth is None else "true δ",
                          css_class=CSS, k=self.state.band, **self._linked(key),
                          x=self.state.grid[:, 0])

    def _draw(self, fig, key, data) -> None:
        """Show ``data`` (result, band k[, slice]) in a cell's figure (k = 0: a map)."""
        c, grid = self._case, self.state.grid
        result, k = data[0], data[1]
        on_grid = result.on_extra
        if c.d_x == 1:
            o, q = key
            mean, var = ((on_grid.z_mean, on_grid.z_var) if q == "z"
                         else (on_grid.delta_mean, on_grid.delta_var))
            fig.show(grid[:, 0], mean[:, o], var[:, o], k,
                     reference=None if q == "z" or self._truth is None
                     else self._truth[:, o])
            return
        # beam-2d: grid is the square grid of on_extra, x1 fastest.
        u1, u2 = np.unique(grid[:, 0]), np.unique(grid[:, 1])
        shape = (u2.size, u1.size)
        mean = on_grid.delta_mean[:, 0].reshape(shape)
        var = on_grid.delta_var[:, 0].reshape(shape)
        label = result.method.label
        if key == 0:
            fig.show(mean, title=f"{label}: δ mean")
        elif key == 1:
            # σ, not the band's width 2kσ: the band control then leaves this map alone
            fig.show(np.sqrt(np.maximum(var, 0.0)), title=f"{label}: δ sd (σ)")
        else:
            row = int(np.argmin(np.abs(u2 - data[2])))      # nearest grid row to the slice
            truth = None if self._truth is None else self._truth.reshape(shape)[row]
            fig.show(u1, mean[row], var[row], k, reference=truth,
                     title=f"{label}: δ at x₂ = {u2[row]:.3g}")     # the slider's x₂

    def _send(self, method: Method, key) -> None:
        cell = self._cells[method, key]
        payload = self._payload(method, key)
        if cell[2] is not None and payload[0] is cell[2][0] and payload[1:] == cell[2][1:]:
            return                               # this plot already shows it
        cell[2] = payload
        self._draw(cell[1], key, payload)
        self._drawn.add(method)

    def _update(self, *_):
        """New results, band, scenarios or busy state: update the plots in place."""
        s = self.state
        if s.case is not self._case:
            return                               # the case watcher rebuilds first
        if self._ready():
            self._prebuild()                     # a method chosen: its empty plots
        for method in sorted(s.results, key=method_order):
            self._ensure(method)
        self._fit_ranges()                 # the new plots' axes, before they are attached
        self._place()
        for method in sorted(s.results, key=method_order):
            for key in self._keys(method):
                if (method, key) in self._cells:
                    self._send(method, key)
        # A recompute is running (the new settings cleared the results): keep the earlier
        # plots, dimmed, until the new ones arrive.
        stale = s.busy and not s.results
        kept = s.held_results()
        for method, group in self._groups.items():
            drawn = method in self._drawn
            if method in s.results:
                visible, styles = True, CURRENT
            elif not drawn:        # built ahead, empty: a chosen method's place is kept
                visible, styles = method in s.scenarios, SLOT
            elif stale and method in s.scenarios:
                visible, styles = True, STALE
            else:   # hidden by the buttons: its place stays, empty; not after a card,
                # which chooses what it shows (KOH's showed two empty columns)
                visible, styles = method in kept and method not in s.scenarios and not s.card, SLOT
            if group.visible != visible:
                group.visible = visible
            if group.styles != styles:
                group.styles = styles
        shown = any(g.visible and g.styles.get("visibility") != "hidden"
                    for g in self._groups.values())
        if stale and shown:
            return                     # the warnings stay with the dimmed plots they concern
        advice = [w for m in sorted(s.results, key=method_order) for w in s.results[m].warnings]
        text = warnings_html(advice) + not_run_html(s) if shown else empty_html(s)
        if self._warnings_div.text != text:
            self._warnings_div.text = text

    @property
    def message(self) -> str:
        """The line above the plots (HTML): what to do while no plot is shown, else the
        diagnostics' warnings, else ''."""
        return self._warnings_div.text

    def _slice_moved(self, *_):
        if self._case is not None and self._case.d_x == 2:
            for method in self._groups:
                if method in self.state.results:
                    self._send(method, 2)

    def _quantity_changed(self, *_):
        if self._case is not self.state.case or self._case.d_x == 2:
            return                               # a new case: its rebuild draws it all
        for method in list(self._groups):
            if method in self.state.results:
                self._ensure(method)             # a quantity shown for the first time
        self._fit_ranges()
        self._place()
        for (_method, key), cell in self._cells.items():
            show_pane(cell[0], self._wanted(key))
        self._update()
