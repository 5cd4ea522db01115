"""Bokeh figures whose data are replaced in place: the plots of the Discrepancy tab.

HoloViews re-ran a plot's whole pipeline (elements, options, ranges) for every change,
0.1–0.2 s per plot on the server (issue 17). Here the figure is built once; a new band, new
results or a new slice only replace the arrays of a few ``ColumnDataSource`` objects, and
the browser redraws and re-ranges the glyphs itself.
"""

from __future__ import annotations

import numpy as np
import panel as pn
from bokeh.core.properties import value
from bokeh.models import (
    ColorBar,
    ColumnDataSource,
    Div,
    HoverTool,
    Legend,
    LegendItem,
    LinearColorMapper,
    Range1d,
)
from bokeh.palettes import Magma256, RdBu11
from bokeh.plotting import figure

from mdcore._validation import as_float_array, as_int, check_positive

from .session_loop import watch_in_session, when_idle, when_shown
from .sources import blank, replace_data

TOOLS = "pan,wheel_zoom,box_zoom,reset,save"


def live_figure(title: str, xname: str, yname: str, css_class: str, **kw):
    """A responsive Bokeh figure, 300 px high, with the app's tools and CSS class."""
    fig = figure(title=title, x_axis_label=xname, y_axis_label=yname, tools=TOOLS,
                 height=300, min_width=200, sizing_mode="stretch_width",
                 css_classes=[css_class], **kw)
    fig.toolbar.logo = None
    fig.grid.grid_line_alpha = 0.6
    return fig


def figure_pane(fig, height: int = 300, stretch: bool = False) -> pn.pane.Bokeh:
    """A Bokeh figure in the layout, ``height`` px high, stretching to the width; with
    ``stretch``, at least ``height`` px, sharing the height of its layout (which must
    stretch too) with the other stretching panes: plots that fill a tall screen."""
    if not stretch:
        return pn.pane.Bokeh(fig, height=height, sizing_mode="stretch_width")
    fig.update(sizing_mode="stretch_both", height=None, min_height=height)
    return pn.pane.Bokeh(fig, min_height=height, sizing_mode="stretch_both")


def show_pane(pane, shown: bool) -> None:
    """Show or hide a Panel object in place (its ``visible``).

    A Bokeh pane copies the visibility of the model it wraps: shown again (``visible``
    back to its default), it re-read its figure's ``False`` and stayed hidden. So the
    figures inside are shown first.

    Raises
    ------
    ValueError
        If ``pane`` is not a Panel object or ``shown`` not a bool.
    """
    if not isinstance(pane, pn.viewable.Viewable):
        raise ValueError(f"pane must be a Panel object (a pane or a layout); received "
                         f"{type(pane).__name__}.")
    if not isinstance(shown, (bool, np.bool_)):
        raise ValueError(f"shown must be True or False; received {shown!r}.")
    if shown:
        for child in pane.select(pn.pane.Bokeh):
            if child.object is not None:
                child.object.visible = True
    if pane.visible != shown:
        pane.visible = shown


def show_only(panes: dict, shown, parent, *, attach: bool) -> None:
    """Show ``panes[shown]`` and hide the other panes (in place, :func:`show_pane`); with
    ``attach``, first make them the children of ``parent`` (a pane was added).

    For views built one key at a time (an output's plots when it is first shown): the
    new pane is drawn before it joins the layout (see :class:`LivePanel`).
    """
    if shown not in panes:
        raise ValueError(f"shown must be a key of panes, one of {list(panes)}; received "
                         f"{shown!r}. Build its pane first.")
    for key, pane in panes.items():
        show_pane(pane, key == shown)
    if attach:
        parent.objects = list(panes.values())


#: Styles of a group of plots that is shown. Explicit: styles of ``{}`` would leave an
#: earlier opacity or visibility on in the browser.
CURRENT = {"opacity": "1", "visibility": "visible"}
#: ... of a group that keeps its place, empty: plots built ahead of their data, or hidden
#: by a button while their data are kept. Nothing else moves or resizes when it is shown
#: or hidden: collapsing it made the browser re-lay-out and repaint every other plot
#: (0.6-0.9 s on shear-5's 20 plots); this is a style change (0.05 s).
SLOT = {"opacity": "1", "visibility": "hidden"}


def check_shown_in(shown_in, name: str) -> None:
    """Raise a ValueError naming ``name`` unless ``shown_in`` is ``(tabs, index)``: a
    ``pn.Tabs`` and a tab index ≥ 0."""
    if not (isinstance(shown_in, tuple) and len(shown_in) == 2
            and isinstance(shown_in[0], pn.Tabs) and isinstance(shown_in[1], int)
            and 0 <= shown_in[1]):
        raise ValueError(f"{name} must be (tabs, index): a pn.Tabs and the panel's tab "
                         f"index ≥ 0; received {shown_in!r}.")


class LivePanel(pn.viewable.Viewer):
    """A view of the app's state whose figures are built per case and then updated in
    place.

    Subclasses set :attr:`UPDATE_ON` and define ``_rebuild`` (a new case: build the
    figures and call ``_update``) and ``_update`` (draw what the state holds);
    ``_setup`` makes what outlives a case. ``state`` is the session's
    :class:`mdcore_app.state.ExplorerState`.

    New figures are drawn completely *before* they are put into the layout. A Bokeh
    model changed after it joined the document goes to the browser as its own patch, and
    that patch can arrive before the one, sent through Panel, that defines the model: the
    page then fails with "reference pNNNN isn't known" and drops later updates (seen in
    the browser tests under load).
    """

    #: State parameters whose change calls ``_update``.
    UPDATE_ON: tuple[str, ...] = ()
    #: The layout's sizing mode ("stretch_both": its plots fill the height).
    SIZING = "stretch_width"

    def __init__(self, *, shown_in: tuple | None = None, **params):
        """``shown_in = (tabs, index)``: the panel is tab ``index`` of ``tabs`` and is
        built when that tab is shown or later (:meth:`defer_while_hidden`); a new session's
        first page then builds the figures of the tab in view only."""
        if shown_in is not None:
            check_shown_in(shown_in, "shown_in")
        super().__init__(**params)
        self._layout = pn.Column(sizing_mode=self.SIZING)
        self._case = None                        # the case drawn (set by _rebuild)
        self._setup()
        self._shown = lambda: True               # see defer_while_hidden
        self._poke = lambda busy=False: None     # ... and its catching up (when_idle)
        self._stale = False                      # a case change waits for the tab
        watch_in_session(self.state, self._case_changed, "case")
        watch_in_session(self.state, self._state_changed, list(self.UPDATE_ON))
        if shown_in is not None:
            self.defer_while_hidden(*shown_in)
        self._case_changed()

    def __panel__(self):
        return self._layout

    def defer_while_hidden(self, tabs, index: int) -> None:
        """Rebuild for a new case when tab ``index`` of ``tabs`` shows this panel, or
        once the session is idle after it (:func:`when_idle`). A case switch then draws
        the tab in view first: the History-matching panels were most of a switch made from
        the Data tab (docs/performance.md).
        """
        self._shown = lambda: tabs.active == index
        when_shown(tabs, index, self._catch_up)
        self._poke = when_idle(self.state, self._catch_up)

    def _catch_up(self) -> None:
        if self._stale:
            self._stale = False
            self._rebuild()

    def _case_changed(self, *_) -> None:
        if self._shown():
            self._stale = False
            self._rebuild()
        else:
            self._stale = True
            if self._case is not None:           # not a new session's page: see when_idle
                self._poke()

    def _state_changed(self, *events) -> None:
        if not self._stale:                      # else the coming rebuild draws it all
            self._update(*events)
        else:              # waves run with the tab hidden: drawn while the job runs
            self._poke(busy=True)

    def _setup(self) -> None:
        """Widgets and watchers kept across cases (none by default)."""

    def _rebuild(self, *_) -> None:
        raise NotImplementedError

    def _update(self, *_) -> None:
        raise NotImplementedError


def live_text(css_class: str, height: int | None = None) -> tuple[pn.pane.Bokeh, Div]:
    """A line of HTML whose text is replaced in place: ``(pane for the layout, Div)``; set
    ``div.text``.

    A Bokeh ``Div`` and not a Panel HTML pane: updating a Panel pane re-sends its style
    sheets, and one updated while its tab was hidden came back with Panel's CDN addresses
    (``cdn.holoviz.org/.../loading.css``), which an offline app must never request.
    """
    size = {} if height is None else {"height": as_int(height, "height", 1)}
    div = Div(text="", css_classes=[css_class], sizing_mode="stretch_width", **size)
    return pn.pane.Bokeh(div, sizing_mode="stretch_width", margin=(0, 10)), div


def below_legend(fig, items, ncols: int = 4) -> Legend:
    """A legend under the plot (inside, it covered the data at 1280 px); a click on an
    item hides its glyphs."""
    legend = Legend(items=items, ncols=ncols, click_policy="hide", margin=0, padding=2,
                    label_text_font_size="9pt")
    fig.add_layout(legend, "below")
    return legend


class BandFigure:
    """Mean ± k·sd of one method over a 1-D input, with fixed points (the data) or a
    reference line (the true δ).

    Parameters
    ----------
    title, xname, yname : str
        Title and axis labels (with units).
    color : str
        The method's colour.
    label : str
        The method's name in the legend.
    points : sequence of (x, y, label, style)
        Fixed scatter layers, e.g. the training and test data; ``style`` is passed to
        ``figure.scatter``.
    reference : str, optional
        Legend label of a dashed black reference line (set by :meth:`show`).
    css_class : str
        The figure's CSS class (what the browser tests look for).
    x_range, y_range : bokeh Range, optional
        Ranges shared with other figures (linked axes); default: the figure's own.
    x : ndarray of shape (G,), optional
        The inputs :meth:`show` will draw at, when known: the sources start there, blank
        (:func:`blank`), and each result is sent as a patch.
    k : int, default=3
        The band's width in sd that the legend says until :meth:`show` draws another.
    """

    def __init__(self, *, title: str, xname: str, yname: str, color: str, label: str,
                 points=(), reference: str | None = None, css_class: str = "live-plot",
                 x_range=None, y_range=None, x=None, k: int = 3):
        ranges = {k: v for k, v in (("x_range", x_range), ("y_range", y_range)) if v}
        self.figure = fig = live_figure(title, xname, yname, css_class, **ranges)
        x = np.zeros(0) if x is None else as_float_array(x, "x", ndim=1)
        self._band = ColumnDataSource(blank(x.size, "lower", "upper", x=x))
        self._mean = ColumnDataSource(blank(x.size, "mean", x=x))
        band = fig.varea("x", "lower", "upper", source=self._band, fill_color=color,
                         fill_alpha=0.25)
        mean = fig.line("x", "mean", source=self._mean, line_color=color, line_width=2)
        # The band's entry says its k (``k`` until show says otherwise: a new text
        # rebuilds the legend's entries in the browser).
        self._label = label
        self._band_item = LegendItem(label=value(f"{label} ±{k}σ"), renderers=[band])
        items = [self._band_item,
                 LegendItem(label=f"{label} mean", renderers=[mean])]
        for x, y, name, style in points:
            items.append(LegendItem(label=name, renderers=[fig.scatter(
                np.asarray(x, float), np.asarray(y, float), **style)]))
        self._reference = None
        if reference is not None:
            self._reference = ColumnDataSource(blank(x.size, "y", x=x))
            line = fig.line("x", "y", source=self._reference, line_color="black",
                            line_dash="dashed", line_width=1.5)
            items.append(LegendItem(label=reference, renderers=[line]))
        below_legend(fig, items, ncols=2)
        fig.add_tools(HoverTool(renderers=[mean], tooltips=[
            (xname, "@x{0.[0000]}"), ("mean", "@mean{0.[0000]}"),
            ("± band", "@lower{0.[0000]} to @upper{0.[0000]}")]))

    def show(self, x, mean, var, k: int, *, reference=None, title: str | None = None) -> None:
        """Draw mean ± ``k``·sqrt(``var``) over ``x`` (all (G,)); optionally a new
        reference line (y on ``x``) and title.

        Raises
        ------
        ValueError
            For arrays that are not 1-D, empty, of different lengths or not finite, a
            negative variance, or ``k`` < 1.
        """
        x = as_float_array(x, "x", ndim=1)
        columns = {"mean": mean, "var": var}
        if reference is not None:
            columns["reference"] = reference
        for name, column in columns.items():
            columns[name] = as_float_array(column, name, ndim=1)
            if columns[name].shape != x.shape:
                raise ValueError(f"{name} must have the shape of x, {x.shape}; received "
                                 f"{columns[name].shape}.")
        mean, reference = columns["mean"], columns.get("reference")
        k = as_int(k, "k", 1)
        sd = k * np.sqrt(check_positive(columns["var"], "var", strict=False))
        replace_data(self._band, {"x": x, "lower": mean - sd, "upper": mean + sd})
        band_label = value(f"{self._label} ±{k}σ")     # a text, not a column's name
        if self._band_item.label != band_label:
            self._band_item.label = band_label
        replace_data(self._mean, {"x": x, "mean": mean})     # a new band keeps the mean
        if self._reference is not None and reference is not None:
            replace_data(self._reference, {"x": x, "y": reference})
        if title is not None:
            self.figure.title.text = title


class MapFigure:
    """A field over two inputs on a regular grid, with a colour bar.

    Parameters
    ----------
    title, xname, yname, zname : str
        Title, axis labels and the colour bar's title.
    u1, u2 : ndarray, shape (n1,), (n2,)
        The grid's coordinates (increasing).
    diverging : bool
        Blue–white–red, symmetric about 0 (a signed δ); else magma from the minimum.
    css_class : str
        The figure's CSS class.
    """

    def __init__(self, *, title: str, xname: str, yname: str, zname: str, u1, u2,
                 diverging: bool, css_class: str = "live-plot"):
        u1, u2 = np.asarray(u1, float), np.asarray(u2, float)
        self.figure = fig = live_figure(title, xname, yname, css_class,
                                    x_range=Range1d(u1[0], u1[-1]),
                                    y_range=Range1d(u2[0], u2[-1]))
        self._diverging = diverging
        self._shape = (u2.size, u1.size)
        self._mapper = LinearColorMapper(palette=RdBu11 if diverging else Magma256)
        self._image = ColumnDataSource({"image": []})
        fig.image(image="image", x=u1[0], y=u2[0], dw=u1[-1] - u1[0], dh=u2[-1] - u2[0],
                  color_mapper=self._mapper, source=self._image)
        fig.add_layout(ColorBar(color_mapper=self._mapper, title=zname, width=10), "right")
        # A third of the page wide at 1280 px: six x ticks ran into each other
        fig.xaxis.ticker.desired_num_ticks = 4

    def show(self, values, *, title: str | None = None) -> None:
        """Draw ``values`` (n2, n1): row j at u2[j].

        Raises
        ------
        ValueError
            For values that are not finite or not of the grid's shape (n2, n1).
        """
        values = as_float_array(values, "values", ndim=2)
        if values.shape != self._shape:
            raise ValueError(f"values must have the grid's shape (n2, n1) = {self._shape}; "
                             f"received {values.shape}.")
        lo, hi = float(values.min()), float(values.max())
        if self._diverging:
            m = max(abs(lo), abs(hi)) or 1.0
            lo, hi = -m, m
        elif hi <= lo:
            hi = lo + 1.0
        self._mapper.update(low=lo, high=hi)
        replace_data(self._image, {"image": [values]})
        if title is not None:
            self.figure.title.text = title
