"""Views of the Model Discrepancy Explorer: they read an :class:`ExplorerState`, draw it
(tabs rebuilt when shown, or panels updated in place) and turn presses into state calls."""

from __future__ import annotations

import html
import json

import panel as pn
import param

from .alerts import alert_box
from .calibration_panel import CalibrationPanel
from .data_panel import DataPanel
from .diagnostics_view import DiagnosticsView
from .discrepancy_panel import DiscrepancyPanel
from .experiments import EXPERIMENTS
from .files_view import FilesView
from .glossary import terms_html
from .live_figures import live_text
from .markup import html_text, markdown_text
from .metrics_view import metrics_panel
from .progress_view import progress_panel
from .session_loop import later, next_tick, show_updating, watch_in_session, when_idle, when_shown
from .state import ExplorerState
from .waves_panel import WavesPanel

SIDEBAR_WIDTH = 330
#: The tabs, in order.
TAB_NAMES = ("Data", "History matching", "Discrepancy", "Metrics", "Diagnostics", "Files",
             "Things to try")
DISCREPANCY_TAB = TAB_NAMES.index("Discrepancy")


def pair(a, b) -> pn.Row:
    """Two controls side by side, sharing the sidebar's width."""
    for w in (a, b):
        w.sizing_mode = "stretch_width"
    return pn.Row(a, b, sizing_mode="stretch_width", margin=0)


#: Seconds after a tab switch when the sidebar's cards fold: BokehJS lays out the whole
#: page again for a fold, which at once kept the new tab blank longer (docs/performance.md).
FOLD_AFTER = 0.6


def fold(cards, tab: int) -> None:
    """Open the card of the controls of ``tab`` (History matching: tab 1; Discrepancy:
    tabs 2-4) and fold the other; other tabs leave them as they are."""
    want = {1: (False, True)}.get(tab, (True, False) if 2 <= tab <= 4 else None)
    for card, collapsed in zip(cards, want or ()):
        if card.collapsed != collapsed:
            card.collapsed = collapsed


def starting_html(exp) -> str:
    """The card line from a card's click until the server answers."""
    return html.escape(f"{exp.title} — starting …")


def terms(*words: str) -> pn.pane.HTML:
    """The line of a tab naming its ``words``, their definitions as tooltips."""
    return pn.pane.HTML(terms_html(*words), css_classes=["glossary-terms"],
                        sizing_mode="stretch_width", styles={"font-size": "0.85em"})


class ExplorerView(pn.viewable.Viewer):
    """The whole page: controls on the left, tabs of plots on the right."""

    state = param.ClassSelector(class_=ExplorerState)

    def __init__(self, **params):
        super().__init__(**params)
        self.state.param.watch(self._notify_error, "n_errors")
        self.state.param.watch(self._notify_warning, "n_notices")
        # Every tab is in the page (not ``dynamic``): a visit only shows it. Sent again on
        # each visit, a tab was blank for a while every time (docs/performance.md). The live
        # panels of a hidden tab are built (for a new session, or rebuilt for a new case)
        # when their tab is shown or once the session is idle (when_idle): the
        # History-matching ones were half of a new session's server time.
        self._tabs = pn.Tabs(dynamic=False, sizing_mode="stretch_both")
        self.data_view = DataPanel(state=self.state, shown_in=(self._tabs, 0))
        self.discrepancy_view = DiscrepancyPanel(state=self.state)
        self.discrepancy_view.prebuild_when_shown(self._tabs, DISCREPANCY_TAB)
        self.waves_view = WavesPanel(state=self.state, shown_in=(self._tabs, 1))
        self.calibration_view = CalibrationPanel(state=self.state, shown_in=(self._tabs, 1))
        self.status_view, self._status_div = live_text("hm-status")
        watch_in_session(self.state, self._show_status, ["status", "waves"])
        self._show_status()
        self._card_pane, self._card_div = live_text("card-note")
        self._card_div.styles = {"font-size": "0.9em", "padding": "2px 6px",
                                 "background": "#e8f1fb"}
        watch_in_session(self.state, self._show_card, "card")
        self._show_card()
        self._fill_tabs()

    # --- events ------------------------------------------------------------------------
    # A toast renders its message as HTML, and messages quote user text (file names,
    # names from session files, CSV headers): escaped, they show it literally.
    def _notify_error(self, *_):
        if pn.state.notifications is not None:
            pn.state.notifications.error(html_text(self.state.error), duration=10_000)

    def _notify_warning(self, *_):
        # A notice is a result's advice (a low ESS, a chain that did not mix), which the
        # Discrepancy and Metrics tabs show beside the bands and the diagnostics: there, a
        # toast would say it twice (and covered the tables a card points at), and
        # each toast makes Bokeh walk the whole document (0.17 s of the server's main
        # thread per beam-2d run). Elsewhere, the toast says that there is advice to read.
        if self._tabs.active in (DISCREPANCY_TAB, DISCREPANCY_TAB + 1):
            return
        if pn.state.notifications is not None:
            pn.state.notifications.warning(html_text(self.state.notice), duration=10_000)

    # --- controls ----------------------------------------------------------------------
    def _controls(self):
        s = self.state
        w = pn.Column(pn.Param(s.param, parameters=["case_name"], show_name=False,
                               widgets={"case_name": pn.widgets.Select}),
                      self._output_choice(), sizing_mode="stretch_width", margin=0)
        num = self._number_input
        # Two controls a row, so that a tab's card fits beside its plots at 1280×720.
        hm = pn.Column(
            pair(self._choice("preset"), pn.widgets.IntSlider.from_param(s.param.max_waves)),
            pair(num("v_m", pn.widgets.FloatInput, step=0.005, format="0.[0000]"),
                 num("threshold", pn.widgets.FloatInput, step=0.5, format="0.[00]")),
            self._choice("rule"),
            pair(num("v_m_length", pn.widgets.FloatInput, step=0.05, format="0.[0000]"),
                 num("n_runs", pn.widgets.IntInput)),
            pair(num("n_candidates", pn.widgets.IntInput, step=10_000),
                 num("convergence_ratio", pn.widgets.FloatInput, step=0.1, format="0.[000]")))
        next_btn = pn.widgets.Button(label="Next wave", color="primary")
        conv_btn = pn.widgets.Button(label="Run to convergence", color="primary")
        next_btn.on_click(lambda _: s.next_wave())
        conv_btn.on_click(lambda _: s.run_to_convergence())
        koh = self._choice("koh_chain")
        disc = pn.Column(          # the band is chosen beside the bands (DiscrepancyPanel)
            pair(num("n_s", pn.widgets.IntInput), num("n_phi", pn.widgets.IntInput)),
            pair(pn.widgets.Checkbox.from_param(s.param.paper_sizes, margin=(25, 10, 0, 10)),
                 num("seed", pn.widgets.IntInput)),
            self._choice("scenarios", pn.widgets.CheckButtonGroup),
            pair(self._choice("proposal"), koh))
        run_btn = pn.widgets.Button(label="Run discrepancy", color="success")
        run_btn.on_click(lambda _: s.run_discrepancy())
        for b, label in ((next_btn, "next-wave"), (conv_btn, "run-convergence"),
                         (run_btn, "run-discrepancy")):
            b.css_classes = [label]
        self._announce((next_btn, conv_btn, run_btn), koh.select(pn.widgets.TooltipIcon)[0])
        # The buttons and the progress line come first, the settings follow in cards: the
        # History matching tab's card is open beside it and the other folded, and the
        # same for the Discrepancy, Metrics and Diagnostics tabs, so at 1280×720 every
        # control of the tab shown is in view. The sidebar scrolls on its own.
        progress, cancel = progress_panel(self.state)
        cards = [pn.Card(hm, title="History matching", sizing_mode="stretch_width",
                         css_classes=["hm-controls"]),
                 pn.Card(disc, title="Discrepancy", sizing_mode="stretch_width",
                         css_classes=["disc-controls"])]
        self._tabs.param.watch(lambda e: later(FOLD_AFTER, lambda: fold(cards, e.new)),
                               "active")
        return pn.Column(
            w, self._case_info, pn.Row(next_btn, conv_btn), pn.Row(run_btn, cancel), progress,
            *cards, width=SIDEBAR_WIDTH, sizing_mode="stretch_height", scroll=True,
            css_classes=["mdcore-sidebar"])

    def _announce(self, buttons, koh_icon) -> None:
        """The state's estimates (:meth:`ExplorerState.announcements`) on ``buttons`` (by
        CSS class) and in ``koh_icon``, kept up to date."""
        def show(*_):
            said = self.state.announcements()
            for b in buttons:
                b.param.update(**said[b.css_classes[0]])
            koh_icon.value = said["koh"]

        self.state.param.watch(show, ["case", "scenarios", "koh_chain", "n_s", "n_phi",
                                      "proposal", "waves", "n_candidates", "max_waves"])
        show()

    def _choice(self, name: str, cls=pn.widgets.RadioButtonGroup):
        """A button group for the state's parameter ``name``, with its label above it (a
        bare group of buttons does not say what it chooses)."""
        p = self.state.param[name]
        widget = cls.from_param(p, name="", description=None, sizing_mode="stretch_width")
        return self._labelled(name, widget)

    def _output_choice(self) -> pn.Column:
        """Buttons for the output the tabs show (``state.output``), under the case: only for
        a case with several outputs. The options follow the case."""
        s = self.state
        buttons = pn.widgets.RadioButtonGroup(options=list(s.case.output_names),
                                              value=s.output, sizing_mode="stretch_width",
                                              css_classes=["output-choice"])
        box = self._labelled("output", buttons)
        box.visible = s.case.n_out > 1

        def from_state(*_):
            names = list(s.case.output_names)
            buttons.param.update(options=names, value=s.output)
            box.visible = len(names) > 1

        def to_state(event):
            if event.new in s.case.output_names:    # not the None of an options change
                s.output = event.new

        buttons.param.watch(to_state, "value")
        s.param.watch(from_state, ["case", "output"])
        return box

    def _labelled(self, name: str, widget) -> pn.Column:
        """``widget`` with the label (and the doc as a tooltip) of the state's ``name``."""
        p = self.state.param[name]
        label = pn.pane.HTML(f"<label>{html.escape(p.label)}</label>", margin=(5, 0, 0, 10),
                             css_classes=["group-label"])
        head = pn.Row(label, pn.widgets.TooltipIcon(value=p.doc, margin=(5, 0, 0, 0))) \
            if p.doc else label
        return pn.Column(head, widget, sizing_mode="stretch_width", margin=0)

    def _number_input(self, name: str, cls, **kw):
        """A number field for the state's parameter ``name`` whose typed value the parameter
        checks: a value it refuses (outside the hard bounds, empty, wrong type) becomes one
        notification saying what is allowed, and the field reverts. The parameter's soft
        bounds are only a hint, so values beyond them (T = 7, V_m = 0.5) are accepted."""
        s = self.state
        p = s.param[name]
        field = cls(label=p.label, value=getattr(s, name), description=p.doc, **kw)

        def push(event):
            if event.new == getattr(s, name):
                return
            try:
                setattr(s, name, event.new)
            except ValueError as exc:
                s.reject(name, event.new, exc)
                field.value = getattr(s, name)

        field.param.watch(push, "value")
        s.param.watch(lambda e: setattr(field, "value", e.new), name)
        return field

    @param.depends("state.case")
    def _case_info(self):
        c = self.state.case
        text = markdown_text(c.description)      # an upload's file name, a case file's text
        # At most four lines, the rest scrolls: a long description pushed the controls of
        # the tab below the fold at 1280×720.
        style = {"font-size": "0.85em", "max-height": "5.6em", "overflow-y": "auto"}
        if c.stand_in:                 # synthetic data standing in for unpublished ones
            style.update({"background": "#fff3cd", "color": "#664d03", "padding": "0 6px"})
        return pn.pane.Markdown(text, styles=style, margin=(0, 10),
                                stylesheets=["p { margin: 2px 0; }"], css_classes=[
            "stand-in" if c.stand_in else "case-description"])

    # --- tabs --------------------------------------------------------------------------
    @property
    def status_html(self) -> str:
        """The status line's HTML as shown."""
        return self._status_div.text

    def _show_status(self, *_):
        """New text and colour in the same line (a new pane re-laid-out the page)."""
        self._status_div.text = alert_box(html.escape(self.state.status or "No waves yet."),
                                          self._alert())

    def _alert(self):
        w = self.state.waves
        if not w:
            return "info"
        return {"converged": "success", "max_waves": "warning",
                "ruled_out": "danger"}.get(w[-1].status, "info")

    @param.depends("state.results")              # filtered by the scenarios already
    def metrics_view(self):
        return metrics_panel(self.state)

    def files_view(self):
        """The Files tab: your measurements in, a saved session in, results out."""
        return FilesView(state=self.state).__panel__()

    def try_view(self):
        """The "Things to try" tab: guided experiments, each a prediction to make and one
        button that sets its controls and runs it."""
        cards = []
        for exp in EXPERIMENTS:
            button = pn.widgets.Button(label="Run it", color="primary",
                                       css_classes=[f"try-{exp.key}"], width=120)
            button.on_click(lambda _, e=exp: self._try(e))
            # The card's tab and line at once, in the browser: the server's answer can
            # wait seconds behind a busy page (hidden tabs catching up after a run, a
            # loaded machine), and until then the class saw nothing happen
            # (docs/performance.md, "A card's click").
            button.js_on_click(args={"tabs": self._tabs, "line": self._card_div}, code=(
                f"tabs.active = {TAB_NAMES.index(exp.tab)}; "
                f"line.text = {json.dumps(starting_html(exp))}; line.visible = true;"))
            cards.append(pn.Column(
                pn.pane.Markdown(f"**{exp.title}**\n\n**Predict first:** {exp.predict} "
                                 f"*Then:* {exp.then}", margin=(0, 10)),
                button, styles={"border-bottom": "1px solid #ddd"},
                sizing_mode="stretch_width"))
        intro = pn.pane.Markdown(
            "**Model Discrepancy Explorer** · Gardner et al., MSSP 2021: history matching, "
            "then GP discrepancy (scenarios 1–3), against the joint Kennedy–O'Hagan baseline "
            "(koh). Each card sets every control it needs, runs, and shows its tab.")
        return pn.Column(intro, *cards, sizing_mode="stretch_width", max_width=900)

    def _try(self, exp) -> None:
        """Run the card ``exp``, then show its tab (from the top: see _fill_tabs); its
        settings change the shown tab's figures, so not inside the button's own event.

        The browser has shown the tab already (try_view). Shown here first, its stale
        views were rebuilt from the old settings before the card's own changes, which
        made them stale again, and the card's answer waited for that rebuild."""
        def run():
            self.state.try_experiment(exp.key)
            # Sent even when ``card`` is as it was (the same card again): the browser
            # says "starting" since the click.
            self._card_div.text = ""
            self._show_card()
            self._tabs.active = TAB_NAMES.index(exp.tab)
        next_tick(run)

    def _shown_only(self, tabs: pn.Tabs, index: int, view, params: list[str]) -> pn.Column:
        """A box holding ``view()``, rebuilt when one of the state's ``params`` changes
        while tab ``index`` is shown, or when that tab is shown after such a change, or
        once a job has ended (:func:`when_idle`): a change of what is shown (a scenario
        hidden) rebuilt all the hidden metrics' plots for each click (docs/performance.md)."""
        box = pn.Column(sizing_mode="stretch_width")
        stale = [True]

        def build():
            stale[0] = False
            box.objects = [view()]

        when_idle(self.state, lambda: stale[0] and build())

        def refresh(*_):
            if tabs.active != index:
                stale[0] = True
                return
            doc = pn.state.curdoc
            if doc is None or doc.session_context is None:
                build()                                # not served: at once
                return
            # Served: say so at once, over the old content, and build on the next tick.
            show_updating(box, "Updating …")
            pn.state.execute(build, schedule=True)

        self.state.param.watch(refresh, params)
        when_shown(tabs, index, lambda: stale[0] and refresh())
        build()                # a new session's: what to press, in the page from the start
        return box

    def _fill_tabs(self) -> None:
        tabs = self._tabs
        # Views rebuilt from scratch on a change are built while their tab is shown, else
        # when it is next shown or after a job: rebuilding the metrics is the slowest part
        # of a scenario toggle, which a hidden tab must not add to the one in view.
        metrics = self._shown_only(tabs, 3, self.metrics_view, ["results", "output"])
        self._diagnostics = DiagnosticsView(self.state, tabs, 4)
        hm_tab = pn.Column(terms("NROY", "V_o", "V_m", "T", "θ_MAP", "implausibility", "wave"),
                           self.status_view, self.waves_view,
                           self.calibration_view, sizing_mode="stretch_width")
        metrics_tab = pn.Column(
            terms("NMSE", "RMSE δ", "MMD", "LPL", "ESS", "ESS over φ", "k̂", "IAT", "KOH"),
            pn.pane.Markdown("Metrics at the test inputs (docs/method.md §8). NMSE in percent; "
                             "RMSE δ in the output's units (NMSE δ divides by the variance of the "
                             "true δ, which is tiny where δ hardly varies, as on shear-5); "
                             "coverage = share of test points (or of the true δ) inside the "
                             "band."),
            metrics, sizing_mode="stretch_width")
        # Each tab scrolls on its own, below its header, beside the sidebar; shown from its
        # top (kept scrolled down, a card's plot was out of view).
        tabs.param.watch(lambda e: tabs[e.new].scroll_to(0), "active")
        tabs.extend([pn.Column(view, name=name, scroll=True, sizing_mode="stretch_both")
                     for name, view in (
                         ("Data", pn.Column(terms("V_o", "V_m", "θ"), self.data_view,
                                            sizing_mode="stretch_both")),
                         ("History matching", hm_tab),
                         ("Discrepancy", pn.Column(terms(
                             "δ", "scenario 1", "scenario 2", "scenario 3", "KOH", "N_s, N_φ"),
                             self.discrepancy_view, sizing_mode="stretch_both")),
                         ("Metrics", metrics_tab),
                         ("Diagnostics", self._diagnostics),
                         ("Files", self.files_view()), ("Things to try", self.try_view()))])

    def _show_card(self, *_):
        """The last card's "look at" line above the tabs: its tab may be Discrepancy or
        Metrics, away from the status line (History matching)."""
        self._card_div.text = html.escape(self.state.card)
        self._card_div.visible = bool(self.state.card)

    def __panel__(self):
        return pn.Row(self._controls(), pn.Column(self._card_pane, self._tabs,
                                                  sizing_mode="stretch_both"),
                      sizing_mode="stretch_both")
