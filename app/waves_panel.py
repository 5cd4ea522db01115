"""The waves of the History matching tab, updated in place (issue 17: "watch the waves
shrink" in a blink).

The figures are built once per case (:mod:`.live_figures`): a new wave, the wave player or a
new implausibility map only replace the arrays of a few ``ColumnDataSource`` objects (a new
wave's samples are appended; the player moves a filter of the waves shown), and the
browser redraws those glyphs; no layout is rebuilt, and nothing changes a layout's
``visible`` or size (a wave's plots keep their place). HoloViews rebuilt every plot of
the tab for each wave and each step of the player (shear-5: 922 models, about 1.5 s on the
server and ten in the browser).

What is drawn, for the waves 1..k shown (k: the player's wave, default the last):

* the NROY samples in θ space, coloured by wave: one scatter per pair of parameters
  (p ≥ 2), or stacked histograms (p = 1), with the true θ (black cross or dashed line) and,
  at the last wave, θ_MAP (red star or line);
* p = 2: wave k's combined implausibility over the θ box, clipped at 3T, with the contour
  at its cut-off (T, or the χ² quantile of the multivariate rule);
* the NROY fraction per wave, and the largest emulator variance at the retained points
  ÷ (V_o + V_m) per output (converged below 1).
"""

from __future__ import annotations

import numpy as np
import panel as pn
import param
from bokeh.models import (
    CDSView,
    ColorBar,
    ColumnDataSource,
    CustomJSFilter,
    FixedTicker,
    HoverTool,
    LegendItem,
    LinearColorMapper,
    Range1d,
    Span,
)
from bokeh.palettes import Category10_10, Viridis256

from mdcore._history_matching import MULTIVARIATE

from .live_figures import (
    CURRENT,
    SLOT,
    LivePanel,
    below_legend,
    figure_pane,
    live_figure,
    live_text,
)
from .plots import THETA_MAP_COLOR, THETA_MAP_MARKER, TRUTH_MARKER, axis_label
from .session_loop import watch_in_session
from .sources import blank, replace_data, set_range, set_top
from .state import ExplorerState
from .wave_data import (
    MAX_WAVES,
    SHOWN_WAVES_JS,
    contour_lines,
    decades,
    histogram_columns,
    legend_html,
    nroy_columns,
    padded,
    truth_verdict,
    variance_ratios,
    wave_colors,
)

#: CSS class of every plot of the panel (the browser tests find them by it).
CSS = "hm-plot"
#: The implausibility colours stop at this multiple of T.
CLIP = 3.0
#: Height of the legend line above the plots (fixed: a new wave changes no layout).
LEGEND_HEIGHT = 28
#: What the History matching tab says before the first wave (Markdown, and as HTML in the
#: legend line).
EMPTY_TEXT = "Press **Next wave** to run the first wave."
EMPTY_HTML = "Press <b>Next wave</b> to run the first wave."
#: The player's styles: not shown (below two waves), keeping its place, or shown. Opacity,
#: not only visibility: Panel's player sets its title's ``visibility`` to visible itself;
#: and no clicks on it while it is not shown. Not ``display: none``: a one-wave match then
#: had no gap above its plots, but a card's tab, to be shown from its top, often kept its
#: old scroll position (the player hidden and shown again as the card reran the waves).
PLAYER_HIDDEN = {**SLOT, "opacity": "0", "pointer-events": "none"}
PLAYER_SHOWN = {**CURRENT, "pointer-events": "auto"}


#: Share of a parameter's range left blank on each side of the box in the plots: a marker
#: on the box's edge (shear-5's θ_MAP, at E's lower bound) was cut in half.
EDGE = 0.04


def box_range(bounds) -> Range1d:
    """The plot range of a parameter with ``bounds`` (lo, hi), :data:`EDGE` wider each side."""
    lo, hi = (float(b) for b in bounds)
    return Range1d(lo - EDGE * (hi - lo), hi + EDGE * (hi - lo))


class WavesPanel(LivePanel):
    """NROY samples per wave, the implausibility map (p = 2) and the per-wave summary."""

    state = param.ClassSelector(class_=ExplorerState)
    UPDATE_ON = ("waves", "selected_wave", "implausibility_maps")

    def _setup(self):
        self._placeholder = pn.pane.Markdown(EMPTY_TEXT, css_classes=["hm-placeholder"])
        self._layout.objects = [self._placeholder]
        # One player for the session, kept in the layout: rebuilding it for each wave
        # re-laid-out the page. Kept in its place but not shown until there are two waves
        # to step through (a style: see _show_body).
        self._player = pn.widgets.Player(label="Wave shown", start=1, end=2, value=1,
                                         loop_policy="once", interval=800,
                                         show_loop_controls=False, styles=PLAYER_HIDDEN)
        watch_in_session(self._player, self._player_moved, "value")
        self._syncing = False

    def _state_changed(self, *events):
        # Waves run while the tab is hidden and not yet built: its first showing builds the
        # figures (up to seconds), and meanwhile the placeholder must not say "press Next
        # wave" under a status line that says converged.
        if self._stale and self._layout.objects == [self._placeholder]:
            n = len(self.state.waves)
            self._placeholder.object = f"Drawing {n} wave{'s' if n > 1 else ''} …" if n \
                else EMPTY_TEXT
        super()._state_changed(*events)

    # --- structure -----------------------------------------------------------------------
    def _rebuild(self, *_):
        """A new case: build its figures (shown once it has a wave)."""
        c = self.state.case
        self._case = c
        labels = [axis_label(n, u) for n, u in zip(c.theta_names, c.theta_units)]
        bounds = np.asarray(c.theta_bounds, float)
        self._legend, self._legend_div = live_text("hm-legend", height=LEGEND_HEIGHT)
        # Shown while the rest of the body is not: before the first wave it says what to do.
        self._legend_div.styles = CURRENT
        self._map_point = ColumnDataSource({f"t{i}": [] for i in range(c.p)})
        figs = self._histogram(labels, bounds) if c.p == 1 else self._pairs(labels, bounds)
        self._image = self._implausibility(labels, bounds) if c.p == 2 else None
        if self._image is not None:
            figs.append(self._image_fig)
        rows = [pn.Row(*[figure_pane(f) for f in figs[i:i + 3]], sizing_mode="stretch_width")
                for i in range(0, len(figs), 3)]
        summary = pn.Row(figure_pane(self._fraction_figure()),
                         figure_pane(self._variance_figure(c.output_names)),
                         sizing_mode="stretch_width")
        # In the layout from the start, keeping their place but not shown until the first
        # wave (a style change then): building them in the browser at that click was
        # most of the first wave's time.
        self._body = pn.Column(self._player, self._legend, *rows, summary,
                               sizing_mode="stretch_width", styles=SLOT)
        self._layout.objects = [self._body]
        self._update()

    def _pairs(self, labels, bounds) -> list:
        """One scatter per pair of parameters, all drawing from one source of samples."""
        c = self._case
        self._nroy = ColumnDataSource(nroy_columns([], c.p))
        self._new_nroy_source()
        figs = []
        for i in range(c.p):
            for j in range(i + 1, c.p):
                fig = live_figure(f"NROY samples: {c.theta_names[i]} vs {c.theta_names[j]}",
                                  labels[i], labels[j], CSS,
                                  x_range=box_range(bounds[i]), y_range=box_range(bounds[j]))
                dots = fig.scatter(f"t{i}", f"t{j}", source=self._nroy, color=wave_colors(),
                                   view=CDSView(filter=self._upto), size=3, alpha=0.5)
                fig.add_tools(HoverTool(renderers=[dots], tooltips=[
                    (labels[i], f"@t{i}{{0.[000]}}"), (labels[j], f"@t{j}{{0.[000]}}"),
                    ("wave", "@wave")]))
                fig.scatter(f"t{i}", f"t{j}", source=self._map_point, **THETA_MAP_MARKER)
                if c.theta_true is not None:      # over the star: θ_MAP often sits on it
                    fig.scatter([c.theta_true[i]], [c.theta_true[j]], **TRUTH_MARKER)
                figs.append(fig)
        return figs

    def _histogram(self, labels, bounds) -> list:
        """p = 1: each wave's NROY histogram, overlaid, with the truth and θ_MAP lines."""
        c = self._case
        self._nroy = ColumnDataSource(histogram_columns([], bounds))
        self._new_nroy_source()
        self._count_range = Range1d(0.0, 1.0)
        fig = live_figure("NROY samples", labels[0], "count", CSS,
                          x_range=box_range(bounds[0]), y_range=self._count_range)
        fig.quad(left="left", right="right", top="top", bottom=0.0, source=self._nroy,
                 fill_color=wave_colors(), line_color=wave_colors(), fill_alpha=0.5,
                 line_alpha=0.8, view=CDSView(filter=self._upto))
        if c.theta_true is not None:
            fig.add_layout(Span(location=float(c.theta_true[0]), dimension="height",
                                line_color="black", line_dash="dashed", line_width=2))
        self._map_line = Span(location=None, dimension="height", line_color=THETA_MAP_COLOR,
                              line_width=3)
        fig.add_layout(self._map_line)
        return [fig]

    def _implausibility(self, labels, bounds) -> ColumnDataSource:
        """p = 2: the combined implausibility image, its contour at T and the markers."""
        c = self._case
        fig = live_figure("implausibility", labels[0], labels[1], CSS,
                          x_range=box_range(bounds[0]), y_range=box_range(bounds[1]))
        self._mapper = LinearColorMapper(palette=Viridis256[::-1], low=0.0, high=1.0)
        image = ColumnDataSource({"image": []})
        fig.image(image="image", x=bounds[0][0], y=bounds[1][0],
                  dw=bounds[0][1] - bounds[0][0], dh=bounds[1][1] - bounds[1][0],
                  color_mapper=self._mapper, source=image)
        self._contour = ColumnDataSource({"xs": [], "ys": []})
        fig.multi_line("xs", "ys", source=self._contour, line_color="white", line_width=2)
        fig.scatter("t0", "t1", source=self._map_point, **THETA_MAP_MARKER)
        if c.theta_true is not None:
            fig.scatter([c.theta_true[0]], [c.theta_true[1]], **TRUTH_MARKER)
        fig.add_layout(ColorBar(color_mapper=self._mapper, title="implausibility", width=10),
                       "right")
        self._image_fig = fig
        return image

    def _fraction_figure(self):
        self._fraction = ColumnDataSource({"wave": [], "percent": []})
        # The summaries' axes are set here, not fitted in the browser: a fitted range is
        # sent back to the server after each wave or player step, one round trip each.
        self._wave_range = Range1d(0.5, 1.5)
        self._fraction_range = Range1d(0.0, 100.0)
        fig = live_figure("NROY fraction per wave", "wave", "NROY [% of box]", CSS,
                          x_range=self._wave_range, y_range=self._fraction_range)
        fig.line("wave", "percent", source=self._fraction, line_width=2)
        dots = fig.scatter("wave", "percent", source=self._fraction, size=8)
        fig.add_tools(HoverTool(renderers=[dots], tooltips=[
            ("wave", "@wave"), ("NROY", "@percent{0.[000]} %")]))
        self._fraction_ticks = fig.xaxis[0].ticker = FixedTicker(ticks=[])
        return fig

    def _variance_figure(self, output_names):
        fig = live_figure("emulator variance (converged below 1)", "wave",
                          "max var / (V_o + V_m)", CSS, y_axis_type="log",
                          x_range=self._wave_range, y_range=Range1d(0.1, 10.0))
        fig.add_layout(Span(location=1.0, dimension="width", line_color="black",
                            line_dash="dashed"))
        self._ratios, items = [], []
        for o, name in enumerate(output_names):
            # One row per possible wave, blank until run: each wave is then a patch, which
            # leaves the legend alone (a longer source rebuilt its five entries five times).
            source = ColumnDataSource(blank(MAX_WAVES, "wave", "ratio"))
            color = Category10_10[o % 10]
            line = fig.line("wave", "ratio", source=source, line_color=color, line_width=2)
            dots = fig.scatter("wave", "ratio", source=source, color=color, size=7)
            self._ratios.append(source)
            items.append(LegendItem(label=name, renderers=[line, dots]))
        below_legend(fig, items, ncols=5)
        self._variance_ticks = fig.xaxis[0].ticker = FixedTicker(ticks=[])
        self._variance_range = fig.y_range
        return fig

    # --- data ----------------------------------------------------------------------------
    def _update(self, *_):
        s, c = self.state, self._case
        if not s.waves:
            self._show_body(False)
            self._legend_div.text = EMPTY_HTML
            self._sync_player(0, 0)
            return
        upto = s.selected_wave or len(s.waves)
        shown = [w for w in s.waves if w.index <= upto]
        self._sync_player(len(s.waves), upto)
        hm = s.history_match
        theta_map = hm.theta_map if upto == len(s.waves) else None     # of the final wave
        self._draw_samples(s.waves, upto)
        replace_data(self._map_point, {f"t{i}": [] if theta_map is None
                                       else [float(theta_map[i])] for i in range(c.p)})
        if c.p == 1:
            self._map_line.location = None if theta_map is None else float(theta_map[0])
        if self._image is not None:
            self._show_map(s.implausibility_maps.get(upto), hm.problem, upto)
        truth = c.theta_true is not None and truth_verdict(shown, c.theta_true)
        self._legend_div.text = legend_html(shown, truth, theta_map is not None,
                                            lines=c.p == 1)
        k = [w.index for w in shown]
        replace_data(self._fraction, {"wave": k,
                                      "percent": [100 * w.nroy_fraction for w in shown]})
        ratios = variance_ratios(shown, c.n_out)
        for o, source in enumerate(self._ratios):
            replace_data(source, {"wave": padded(k, MAX_WAVES),
                                  "ratio": padded(ratios[o], MAX_WAVES)})
        finite = ratios[np.isfinite(ratios) & (ratios > 0)]
        lo = min(float(finite.min()) if finite.size else 1.0, 1.0) / 3
        hi = max(float(finite.max()) if finite.size else 1.0, 1.0) * 3
        set_range(self._variance_range, *decades(lo, hi))
        set_range(self._wave_range, 0.5, max(len(k), 1) + 0.5)
        set_top(self._fraction_range, max(100 * w.nroy_fraction for w in shown), pad=0.08)
        for ticker in (self._fraction_ticks, self._variance_ticks):
            if list(ticker.ticks) != k:
                ticker.ticks = k
        self._show_body(True)

    def _new_nroy_source(self) -> None:
        """The samples' source holds every wave run (``_in_source``); a filter shows waves
        1..``upto``."""
        self._in_source: tuple = ()
        self._upto = CustomJSFilter(args={"upto": 0}, code=SHOWN_WAVES_JS)

    def _columns(self, waves) -> dict:
        c = self._case
        return (histogram_columns(waves, np.asarray(c.theta_bounds, float)) if c.p == 1
                else nroy_columns(waves, c.p))

    def _draw_samples(self, waves: tuple, upto: int) -> None:
        """Every wave's samples in the source, waves 1..``upto`` shown.

        A new wave of the same match is *streamed* (its rows only) and a step of the player
        changes the filter's ``upto`` only: re-sending every wave's samples was most of a
        wave's or a step's message (beam-1d: 78-130 kB). A new match replaces them.
        """
        have = self._in_source
        same = len(waves) >= len(have) and all(a is b for a, b in zip(waves, have))
        if same and have and len(waves) > len(have):
            self._nroy.stream(self._columns(waves[len(have):]))
        elif not (same and len(waves) == len(have)):
            replace_data(self._nroy, self._columns(waves))
        self._in_source = tuple(waves)
        if self._upto.args.get("upto") != upto:
            self._upto.args = {"upto": upto}
        if self._case.p == 1:
            data = self._nroy.data
            tops = np.asarray(data["top"])[np.asarray(data["wave"]) <= upto]
            set_top(self._count_range, tops.max() if tops.size else 0.0)

    def _show_body(self, shown: bool) -> None:
        """The plots, or only the legend line (which then says to press Next wave).

        A style, never ``visible``: BokehJS answers a change of ``visible`` by laying out
        the whole page again (0.2-0.3 s in Chromium with beam-1d's plots), and a style
        that keeps the element's size by nothing but a repaint. Only what changes is sent.
        """
        styles = CURRENT if shown else SLOT
        if self._body.styles != styles:
            self._body.styles = styles

    def _sync_player(self, n: int, upto: int) -> None:
        """The player shows wave ``upto`` of ``n`` (one message; below 2 waves it keeps its
        place, not shown: see :meth:`_show_body`)."""
        p = self._player
        want = {"end": max(n, 2), "value": max(upto, 1),
                "styles": PLAYER_SHOWN if n >= 2 else PLAYER_HIDDEN}
        changed = {k: v for k, v in want.items() if getattr(p, k) != v}
        if changed:
            self._syncing = True
            try:
                p.param.update(**changed)
            finally:
                self._syncing = False

    def _player_moved(self, event) -> None:
        """The user stepped the player: show waves 1..its value."""
        n = len(self.state.waves)
        if not self._syncing and 1 <= event.new <= n and event.new != self.state.selected_wave:
            with pn.io.hold():           # the updates of every plot go as one message
                self.state.selected_wave = event.new

    def _show_map(self, grid, problem, wave: int) -> None:
        """Wave ``wave``'s implausibility ``grid`` = (t1, t2, I), or a blank image; the
        contour at the problem's cut-off (T, or the χ² quantile of the multivariate rule)."""
        fig = self._image_fig
        if grid is None:
            replace_data(self._image, {"image": []})
            replace_data(self._contour, {"xs": [], "ys": []})
            fig.title.text = f"wave {wave}: no implausibility map"
            return
        t1, t2, I = grid
        cutoff = problem.cutoff
        self._mapper.update(low=0.0, high=CLIP * cutoff)
        replace_data(self._image, {"image": [np.minimum(I, CLIP * cutoff)]})
        replace_data(self._contour, contour_lines(t1, t2, I, cutoff))
        name = ("χ²" if problem.options.rule == MULTIVARIATE else "T")
        fig.title.text = f"wave {wave}: implausibility, contour at {name} = {cutoff:.3g}"


__all__ = ["MAX_WAVES", "WavesPanel"]
