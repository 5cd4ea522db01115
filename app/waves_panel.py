"""The waves of the History matching tab, updated in place (issue 17).

The figures are built once per history match: each wave is a renderer of its own in every
NROY plot, so the wave player only switches renderers' visibility, a new wave adds one
renderer per plot, and the implausibility map and the per-wave summaries replace the
arrays of their data sources. A new match (a new case or new settings) rebuilds them.
"""

from __future__ import annotations

import numpy as np
import panel as pn
import param
from bokeh.core.properties import value
from bokeh.models import (
    ColorBar,
    ColumnDataSource,
    Legend,
    LegendItem,
    LinearColorMapper,
    Range1d,
    Span,
)
from bokeh.palettes import Viridis256
from bokeh.plotting.contour import contour_data

from .live_figures import below_legend, live_figure
from .plots import THETA_MAP_COLOR, WAVE_COLORS, axis_label
from .state import ExplorerState

#: At most this many NROY samples of a wave are drawn (a fixed, seeded subset).
MAX_POINTS = 1500
CSS = "hm-plot"


def _figure(title: str, xname: str, yname: str, **kw):
    return live_figure(title, xname, yname, CSS, **kw)


def _subset(wave) -> np.ndarray:
    nroy = wave.nroy
    if nroy.shape[0] > MAX_POINTS:
        rng = np.random.default_rng(wave.index)
        nroy = nroy[np.sort(rng.choice(nroy.shape[0], MAX_POINTS, replace=False))]
    return nroy


def _color(index: int) -> str:
    return WAVE_COLORS[(index - 1) % len(WAVE_COLORS)]


class WavesPanel(pn.viewable.Viewer):
    """NROY samples per wave (a histogram for p = 1, a scatter per pair for p ≥ 2), the
    implausibility map of the shown wave (p = 2), the NROY fraction and the emulator
    variance per wave."""

    state = param.ClassSelector(class_=ExplorerState)

    def __init__(self, **params):
        super().__init__(**params)
        self._empty = pn.pane.Markdown("Press **Next wave** to run the first wave.")
        self._layout = pn.Column(self._empty, sizing_mode="stretch_width")
        self._waves: tuple = ()
        self.state.param.watch(self._waves_changed, "waves")
        self.state.param.watch(self._show, ["selected_wave", "implausibility_maps"])
        self._waves_changed()

    def __panel__(self):
        return self._layout

    # --- structure -----------------------------------------------------------------------
    def _waves_changed(self, *_):
        waves = self.state.waves
        old = self._waves
        if waves and old and len(waves) >= len(old) and all(
                a is b for a, b in zip(old, waves)):
            for wave in waves[len(old):]:
                self._add_wave(wave)            # the same match, one wave further
        elif waves:
            self._build()
            for wave in waves:
                self._add_wave(wave)
        self._waves = waves
        if not waves:
            self._layout.objects = [self._empty]
            return
        self._show()

    def _build(self) -> None:
        """Empty figures for the current case's θ box."""
        c = self.state.case
        p = c.p
        self._labels = [axis_label(n, u) for n, u in zip(c.theta_names, c.theta_units)]
        self._names = list(c.theta_names)
        b = c.theta_bounds
        self._wave_renderers: list[list] = []            # per figure, per wave
        self._nroy_figs = []
        self._legends = []
        self._map_sources = []                           # (i, j, θ_MAP source)
        if p == 1:
            fig = _figure("NROY samples", self._labels[0], "count",
                          x_range=Range1d(*b[0]))
            fixed = []
            if c.theta_true is not None:
                r = fig.vspan(x=[float(c.theta_true[0])], line_color="black",
                              line_dash="dashed", line_width=2)
                fixed.append(LegendItem(label="true θ", renderers=[r]))
            src = ColumnDataSource({"x": []})
            r = fig.vspan(x="x", source=src, line_color=THETA_MAP_COLOR, line_width=2)
            fixed.append(LegendItem(label="θ_MAP", renderers=[r]))
            self._map_sources.append((0, None, src))
            self._nroy_figs.append(fig)
            self._legends.append(below_legend(fig, fixed))
            self._wave_renderers.append([])
        else:
            for i in range(p):
                for j in range(i + 1, p):
                    fig = _figure(f"NROY samples: {c.theta_names[i]} vs {c.theta_names[j]}",
                                  self._labels[i], self._labels[j],
                                  x_range=Range1d(*b[i]), y_range=Range1d(*b[j]))
                    fixed = []
                    if c.theta_true is not None:
                        r = fig.scatter([c.theta_true[i]], [c.theta_true[j]], marker="x",
                                        color="black", size=14, line_width=3, level="overlay")
                        fixed.append(LegendItem(label="true θ", renderers=[r]))
                    src = ColumnDataSource({"x": [], "y": []})
                    r = fig.scatter("x", "y", source=src, marker="star", size=18,
                                    color=THETA_MAP_COLOR, line_color="black", line_width=1,
                                    level="overlay")
                    fixed.append(LegendItem(label="θ_MAP", renderers=[r]))
                    self._map_sources.append((i, j, src))
                    self._nroy_figs.append(fig)
                    self._legends.append(below_legend(fig, fixed))
                    self._wave_renderers.append([])
        rows = [pn.Row(*[pn.pane.Bokeh(f, height=330, sizing_mode="stretch_width")
                         for f in self._nroy_figs[k:k + 3]], sizing_mode="stretch_width")
                for k in range(0, len(self._nroy_figs), 3)]
        objects = [*rows]
        self._imp = None
        if p == 2:
            objects.append(pn.pane.Bokeh(self._build_map(c), height=330,
                                         sizing_mode="stretch_width"))
        objects.append(pn.Row(pn.pane.Bokeh(self._build_fraction(), height=300,
                                            sizing_mode="stretch_width"),
                              pn.pane.Bokeh(self._build_variance(c), height=300,
                                            sizing_mode="stretch_width"),
                              sizing_mode="stretch_width"))
        self._layout.objects = objects

    def _build_map(self, c):
        b = c.theta_bounds
        fig = _figure("implausibility", self._labels[0], self._labels[1],
                      x_range=Range1d(*b[0]), y_range=Range1d(*b[1]))
        # viridis reversed: low implausibility (plausible) bright.
        self._imp_mapper = LinearColorMapper(palette=Viridis256[::-1], low=0.0, high=9.0)
        self._imp_image = ColumnDataSource({"image": []})
        fig.image(image="image", x=float(b[0, 0]), y=float(b[1, 0]),
                  dw=float(b[0, 1] - b[0, 0]), dh=float(b[1, 1] - b[1, 0]),
                  color_mapper=self._imp_mapper, source=self._imp_image)
        fig.add_layout(ColorBar(color_mapper=self._imp_mapper, title="implausibility",
                                width=10), "right")
        t = np.linspace(0.0, 1.0, 3)
        self._contour = fig.contour(t, t, np.zeros((3, 3)), levels=[0.5], line_color="white",
                                    line_width=2)
        items = []
        if c.theta_true is not None:
            r = fig.scatter([c.theta_true[0]], [c.theta_true[1]], marker="x", color="red",
                            size=14, line_width=3)
            items.append(LegendItem(label="true θ", renderers=[r]))
        self._imp_map_src = ColumnDataSource({"x": [], "y": []})
        r = fig.scatter("x", "y", source=self._imp_map_src, marker="star", size=18,
                        color=THETA_MAP_COLOR, line_color="black", line_width=1)
        items.append(LegendItem(label="θ_MAP", renderers=[r]))
        fig.add_layout(Legend(items=items, location="top_right", label_text_font_size="9pt"))
        self._imp = fig
        return fig

    def _build_fraction(self):
        fig = _figure("NROY fraction per wave", "wave", "NROY [% of box]")
        self._fraction = ColumnDataSource({"wave": [], "percent": []})
        fig.line("wave", "percent", source=self._fraction, line_width=2)
        fig.scatter("wave", "percent", source=self._fraction, size=8)
        fig.xaxis.ticker.desired_num_ticks = 6
        return fig

    def _build_variance(self, c):
        fig = _figure("emulator variance vs V_o + V_m (converged below 1)", "wave",
                      "max var / (V_o + V_m)", y_axis_type="log")
        fig.add_layout(Span(location=1.0, dimension="width", line_color="black",
                            line_dash="dashed"))
        self._variance = ColumnDataSource({"wave": [], **{f"r{o}": [] for o in range(c.n_out)}})
        items = []
        palette = ["#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b"]
        for o, name in enumerate(c.output_names):
            color = palette[o % len(palette)]
            line = fig.line("wave", f"r{o}", source=self._variance, line_color=color,
                            line_width=2)
            dots = fig.scatter("wave", f"r{o}", source=self._variance, color=color, size=7)
            items.append(LegendItem(label=value(name), renderers=[line, dots]))
        below_legend(fig, items, ncols=3)
        return fig

    def _add_wave(self, wave) -> None:
        """One renderer per NROY plot for ``wave``."""
        nroy = _subset(wave)
        color = _color(wave.index)
        label = value(f"wave {wave.index}")
        for f, fig in enumerate(self._nroy_figs):
            if len(self._labels) == 1:
                lo, hi = self.state.case.theta_bounds[0]
                counts, edges = np.histogram(nroy[:, 0], bins=40, range=(lo, hi))
                r = fig.quad(left=edges[:-1], right=edges[1:], bottom=0, top=counts,
                             fill_color=color, fill_alpha=0.5, line_color=color)
            else:
                i, j = self._map_sources[f][:2]
                r = fig.scatter(nroy[:, i], nroy[:, j], color=color, size=3, alpha=0.5)
            self._wave_renderers[f].append(r)
            legend = self._legends[f]
            legend.items = [*legend.items, LegendItem(label=label, renderers=[r])]

    # --- what is shown -------------------------------------------------------------------
    def _show(self, *_):
        """Show waves 1..selected (visibility), that wave's map and the summaries."""
        s = self.state
        waves = s.waves
        if not waves or waves is not self._waves:
            return
        upto = s.selected_wave or len(waves)
        for renderers in self._wave_renderers:
            for k, r in enumerate(renderers):
                r.visible = k < upto
        hm = s.history_match
        theta_map = hm.theta_map if upto == len(waves) else None   # of the final wave
        for i, j, src in self._map_sources:
            if theta_map is None:
                src.data = {k: [] for k in src.data}
            else:
                src.data = ({"x": [theta_map[i]]} if j is None
                            else {"x": [theta_map[i]], "y": [theta_map[j]]})
        if self._imp is not None:
            self._show_map(upto, theta_map)
        shown = [w for w in waves if w.index <= upto]
        self._fraction.data = {"wave": [w.index for w in shown],
                               "percent": [100 * w.nroy_fraction for w in shown]}
        ratios = {f"r{o}": [float(w.max_var[o] / w.var_threshold[o]) for w in shown]
                  for o in range(s.case.n_out)}
        self._variance.data = {"wave": [w.index for w in shown], **ratios}

    def _show_map(self, upto: int, theta_map) -> None:
        s = self.state
        T = s.threshold
        maps = s.implausibility_maps
        if upto not in maps:
            self._imp.visible = False
            return
        t1, t2, I = maps[upto]
        self._imp.visible = True
        self._imp_mapper.update(low=0.0, high=3 * T)
        self._imp_image.data = {"image": [np.minimum(I, 3 * T)]}
        self._contour.set_data(contour_data(t1, t2, I, levels=[T], want_fill=False))
        self._imp.title.text = (f"wave {upto}: implausibility (clipped at 3T; contour at "
                                f"T = {T:g})")
        self._imp_map_src.data = ({"x": [theta_map[0]], "y": [theta_map[1]]}
                                  if theta_map is not None else {"x": [], "y": []})
