"""Views of the Model Discrepancy Explorer, built from an :class:`ExplorerState`.

The views hold no results: they read the state, draw with :mod:`app.plots`, and turn
button presses into calls of the state's methods.
"""

from __future__ import annotations

import time

import holoviews as hv
import pandas as pd
import panel as pn
import param

from mdcore.pipeline import Method, MethodResult

from . import plots
from .state import ExplorerState, method_order

SIDEBAR_WIDTH = 330
#: A job's progress bar and Cancel button appear once it has run this long (seconds), so
#: that runs at the default sizes (a fraction of a second) do not flash them.
SHOW_PROGRESS_AFTER = 0.5
#: Shown in the metrics table where a diagnostic does not apply to a method.
NOT_APPLICABLE = "—"
#: The columns of :func:`metrics_frame` shown in the diagnostics table, not the metrics one.
DIAGNOSTICS = ("ESS pairs", "ESS φ", "Pareto k", "acceptance", "IAT (max)", "chain ESS (min)")


def metrics_frame(case, results: dict[Method, MethodResult]) -> pd.DataFrame:
    """One row per (method, output): the SPEC §8 metrics, the δ RMSE (output units), then
    the method's diagnostics.

    The importance-sampling diagnostics (ESS over the (θ, φ) pairs, ESS over φ, Pareto k̂,
    "Pareto k")
    belong to scenario 3 and the chain diagnostics (acceptance, the largest IAT, the
    smallest chain ESS over the parameters) to KOH; elsewhere, and for δ metrics where the
    true δ is unknown, the cell holds :data:`NOT_APPLICABLE`, never NaN.
    """
    def per_output(values, o):
        return NOT_APPLICABLE if values is None else float(values[o])

    rows = []
    for method in sorted(results, key=method_order):
        r = results[method]
        m, imp, chain = r.metrics, r.importance, r.chain
        for o, name in enumerate(case.output_names):
            rows.append({
                "method": method.label, "output": name,
                "NMSE z [%]": per_output(m.nmse_z, o),
                "NMSE δ [%]": per_output(m.nmse_delta, o),
                "RMSE δ": per_output(m.rmse_delta, o),
                "MMD": per_output(m.mmd, o), "LPL": per_output(m.lpl, o),
                "cover z ±2σ": per_output(m.coverage_z_2sd, o),
                "cover z ±3σ": per_output(m.coverage_z_3sd, o),
                "cover δ ±2σ": per_output(m.coverage_delta_2sd, o),
                "cover δ ±3σ": per_output(m.coverage_delta_3sd, o),
                "ESS pairs": per_output(None if imp is None else imp.ess, o),
                "ESS φ": per_output(None if imp is None else imp.ess_phi, o),
                "Pareto k": per_output(None if imp is None else imp.k_hat, o),
                "acceptance": NOT_APPLICABLE if chain is None else chain.acceptance_rate,
                "IAT (max)": NOT_APPLICABLE if chain is None else max(chain.iat),
                "chain ESS (min)": NOT_APPLICABLE if chain is None else min(chain.ess),
                "seconds": r.seconds})
    return pd.DataFrame(rows)


class ExplorerView(pn.viewable.Viewer):
    """The whole page: controls on the left, tabs of plots on the right."""

    state = param.ClassSelector(class_=ExplorerState)
    quantity = param.Selector(objects=["z and δ", "δ", "z"], default="z and δ",
                              label="Show")

    def __init__(self, **params):
        super().__init__(**params)
        self.state.param.watch(self._notify_error, "n_errors")
        self.state.param.watch(self._notify_warning, "n_notices")
        self.state.param.watch(self._case_changed, "case_name")
        self._case_changed()

    # --- events ------------------------------------------------------------------------
    def _notify_error(self, *_):
        if pn.state.notifications is not None:
            pn.state.notifications.error(self.state.error, duration=10_000)

    def _notify_warning(self, *_):
        if pn.state.notifications is not None:
            pn.state.notifications.warning(self.state.notice, duration=10_000)

    def _case_changed(self, *_):
        self.quantity = "δ" if self.state.case.n_out > 1 else "z and δ"

    # --- controls ----------------------------------------------------------------------
    def _controls(self):
        s = self.state
        w = pn.Param(s.param, parameters=["case_name"], show_name=False,
                     widgets={"case_name": pn.widgets.Select})
        hm = pn.Column(
            self._number_input("v_m", pn.widgets.FloatInput, step=0.005),
            self._number_input("threshold", pn.widgets.FloatInput, step=0.5),
            pn.Param(s.param, parameters=["rule"], show_name=False,
                     widgets={"rule": pn.widgets.RadioButtonGroup}),
            self._number_input("n_runs", pn.widgets.IntInput),
            self._number_input("n_candidates", pn.widgets.IntInput, step=10_000),
            pn.Param(s.param, parameters=["max_waves"], show_name=False),
            self._number_input("convergence_ratio", pn.widgets.FloatInput, step=0.1))
        next_btn = pn.widgets.Button(label="Next wave", color="primary")
        conv_btn = pn.widgets.Button(label="Run to convergence", color="primary")
        next_btn.on_click(lambda _: s.next_wave())
        conv_btn.on_click(lambda _: s.run_to_convergence())
        disc = pn.Column(
            self._number_input("n_s", pn.widgets.IntInput),
            self._number_input("n_phi", pn.widgets.IntInput),
            pn.Param(s.param, parameters=["paper_sizes", "scenarios", "proposal", "koh_chain",
                                          "band"], show_name=False,
                     widgets={"scenarios": pn.widgets.CheckButtonGroup,
                              "koh_chain": pn.widgets.RadioButtonGroup,
                              "proposal": pn.widgets.RadioButtonGroup,
                              "band": pn.widgets.RadioButtonGroup}),
            self._number_input("seed", pn.widgets.IntInput))
        run_btn = pn.widgets.Button(label="Run discrepancy", color="success")
        run_btn.on_click(lambda _: s.run_discrepancy())
        for b, label in ((next_btn, "next-wave"), (conv_btn, "run-convergence"),
                         (run_btn, "run-discrepancy")):
            b.css_classes = [label]
        return pn.Column(
            pn.pane.Markdown("### Model Discrepancy Explorer\nGardner et al., MSSP 2021: "
                             "history matching, then GP discrepancy (scenarios 1–3), "
                             "against the joint Kennedy–O'Hagan baseline (koh)."),
            w, self._case_info, pn.pane.Markdown("#### History matching"), hm,
            pn.Row(next_btn, conv_btn), pn.pane.Markdown("#### Discrepancy"), disc, run_btn,
            self._progress_panel(), width=SIDEBAR_WIDTH)

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
        if c.stand_in:                 # synthetic data standing in for unpublished ones
            return pn.pane.Alert(c.description, alert_type="warning",
                                 styles={"font-size": "0.85em"}, css_classes=["stand-in"])
        return pn.pane.Markdown(c.description, styles={"font-size": "0.85em"})

    def _progress_panel(self):
        """Busy line, progress bar and a Cancel button, updated in place.

        Replacing the widgets on each report made the browser re-lay-out the whole page
        every time (seconds per report with eight plots on screen); changing a few
        properties does not.
        """
        text = pn.pane.Markdown("Idle.", css_classes=["mdcore-idle"])
        bar = pn.indicators.Progress(value=0, max=100, visible=False,
                                     sizing_mode="stretch_width")
        cancel = pn.widgets.Button(label="Cancel", color="warning", visible=False,
                                   css_classes=["cancel-job"])
        cancel.on_click(lambda _: self.state.cancel())
        since: list[float | None] = [None]          # when the current job started

        def update(*_):
            s = self.state
            if not s.busy:
                since[0] = None
            elif since[0] is None:
                since[0] = time.monotonic()
            detail = f" {s.progress_message}" if s.busy and s.progress_message else ""
            text.param.update(object=f"Running **{s.task}** …{detail}" if s.busy else "Idle.",
                              css_classes=["mdcore-busy" if s.busy else "mdcore-idle"])
            show = since[0] is not None and time.monotonic() - since[0] >= SHOW_PROGRESS_AFTER
            bar.param.update(visible=show, value=int(100 * s.progress))
            cancel.visible = show

        self.state.param.watch(update, ["busy", "progress", "task", "progress_message"])
        update()
        return pn.Column(text, pn.Row(bar, cancel, sizing_mode="stretch_width"),
                         sizing_mode="stretch_width")

    # --- tabs --------------------------------------------------------------------------
    @param.depends("state.case", "state.v_m")
    def data_view(self):
        c = self.state.case
        return pn.pane.HoloViews(plots.data_overview(c, c.noise_var + self.state.v_m_vector()),
                                 sizing_mode="stretch_width", css_classes=["data-plot"])

    @param.depends("state.status", "state.waves")
    def status_view(self):
        return pn.pane.Alert(self.state.status or "No waves yet.", alert_type=self._alert(),
                             css_classes=["hm-status"])

    def _alert(self):
        w = self.state.waves
        if not w:
            return "info"
        return {"converged": "success", "max_waves": "warning",
                "ruled_out": "danger"}.get(w[-1].status, "info")

    @param.depends("state.waves", "state.selected_wave", "state.implausibility_maps")
    def waves_view(self):
        s = self.state
        c = s.case
        if not s.waves:
            return pn.pane.Markdown("Press **Next wave** to run the first wave.")
        upto = s.selected_wave or len(s.waves)
        pairs = plots.nroy_samples(s.waves, c.theta_names, c.theta_units, c.theta_bounds,
                                   c.theta_true, upto)
        rows = [pn.Row(*[pn.pane.HoloViews(o, sizing_mode="stretch_width", height=300,
                                           css_classes=["hm-plot"]) for o in pairs[i:i + 3]],
                       sizing_mode="stretch_width") for i in range(0, len(pairs), 3)]
        if upto in s.implausibility_maps:
            t1, t2, I = s.implausibility_maps[upto]
            rows.append(pn.pane.HoloViews(
                plots.implausibility_map(t1, t2, I, s.threshold, c.theta_names,
                                         c.theta_units, c.theta_true, upto),
                sizing_mode="stretch_width", css_classes=["hm-plot"]))
        shown = [w for w in s.waves if w.index <= upto]
        # Each plot its own pane, every pane stretching: responsive plots inside one
        # HoloViews layout, or beside a fixed-width sibling, collapsed to zero width.
        summary = pn.Row(pn.pane.HoloViews(plots.nroy_fraction(shown), sizing_mode="stretch_width"),
                         pn.pane.HoloViews(plots.emulator_variance(shown, c.output_names),
                                           sizing_mode="stretch_width"),
                         sizing_mode="stretch_width")
        return pn.Column(*rows, summary, sizing_mode="stretch_width")

    @param.depends("state.waves")
    def wave_selector(self):
        n = len(self.state.waves)
        if n < 2:
            return pn.Spacer(height=0)
        return pn.widgets.Player.from_param(self.state.param.selected_wave, start=1, end=n,
                                            loop_policy="once", interval=800, name="Wave shown")

    @param.depends("state.results", "state.band", "state.scenarios", "state.slice_x2", "quantity")
    def discrepancy_view(self):
        s = self.state
        c = s.case
        shown = [k for k in sorted(s.scenarios, key=method_order) if k in s.results]
        if not shown:
            return pn.pane.Markdown("Run history matching, then press **Run discrepancy**.",
                                    css_classes=["disc-empty"])
        k = int(s.band)
        # The diagnostics' warnings stay beside the bands they concern (the notification
        # that also reports them fades).
        advice = [w for m in shown for w in s.results[m].warnings]
        head = [pn.pane.Alert("\n\n".join(f"**{w.split(':', 1)[0]}**:{w.split(':', 1)[1]}"
                                            for w in advice),
                              alert_type="warning", css_classes=["disc-warnings"])] \
            if advice else []
        if c.d_x == 2:
            # A fixed width on this (responsive) plot collapsed the scenario rows below the
            # slider to zero width in the browser.
            rows = [pn.pane.HoloViews(plots.true_delta_2d(c), height=320,
                                      sizing_mode="stretch_width")]
            for sc in shown:
                # One pane per plot in a Row: responsive plots inside one hv.Layout pane
                # collapsed to zero width in the browser (blank panels).
                rows.append(pn.Row(*[pn.pane.HoloViews(p, sizing_mode="stretch_width",
                                                       height=300, css_classes=["disc-plot"])
                                     for p in plots.discrepancy_2d(c, s.grid, s.results[sc],
                                                                   k, s.slice_x2)],
                                   sizing_mode="stretch_width"))
            slider = pn.widgets.FloatSlider.from_param(s.param.slice_x2, step=0.001)
            return pn.Column(*head, slider, *rows, sizing_mode="stretch_width")
        quantities = {"z and δ": ["z", "δ"], "δ": ["δ"], "z": ["z"]}[self.quantity]
        cells = []
        for o in range(c.n_out):
            for q in quantities:
                cells += plots.discrepancy_1d(c, s.grid, s.results, shown, k, o,
                                              "z" if q == "z" else "delta")
        layout = hv.Layout(cells).cols(len(shown))
        plot = pn.pane.HoloViews(layout, sizing_mode="stretch_width", css_classes=["disc-plot"])
        return pn.Column(*head, plot, sizing_mode="stretch_width") if head else plot

    @param.depends("state.results", "state.scenarios")
    def metrics_view(self):
        s = self.state
        shown = {k: v for k, v in s.results.items() if k in s.scenarios}
        if not shown:
            return pn.pane.Markdown("No scenario has run yet.")
        df = metrics_frame(s.case, shown)
        table = pn.pane.DataFrame(df.drop(columns=list(DIAGNOSTICS)), index=False,
                                  float_format="{:.4g}".format, sizing_mode="stretch_width",
                                  css_classes=["metrics-table"])
        objs = [table]
        if Method.S3 in shown or Method.KOH in shown:
            rows = df["method"].isin([Method.S3.label, Method.KOH.label])
            objs += [pn.pane.Markdown("Diagnostics: importance weights of scenario 3 (ESS "
                                      "over the (θ, φ) pairs and over φ, Pareto k̂ ≤ 0.7 is "
                                      "reliable) and the KOH chain (acceptance, largest "
                                      "autocorrelation time, smallest ESS)."),
                     pn.pane.DataFrame(df.loc[rows, ["method", "output", *DIAGNOSTICS]],
                                       index=False, float_format="{:.4g}".format,
                                       css_classes=["diagnostics-table"])]
        if Method.KOH not in shown:
            return pn.Column(*objs, sizing_mode="stretch_width")
        r = shown[Method.KOH]
        m, chain = r.model, r.chain
        c = s.case
        theta = ", ".join(f"{n} = {mu:.4g} ± {sd:.2g}" + ("" if u in ("", "-") else f" {u}")
                          for n, mu, sd, u in zip(c.theta_names, m.theta.mean(axis=0),
                                                  m.theta.std(axis=0), c.theta_units))
        caveat = "" if chain.reliable else (" The chain is shorter than 50 autocorrelation "
                                            "times, so these are themselves uncertain.")
        summary = pn.pane.Markdown(
            f"**KOH chain:** {chain.n_iter:,} iterations ({chain.burn_in:,} burn-in), "
            f"acceptance {chain.acceptance_rate:.2f}, integrated autocorrelation time "
            f"{', '.join(f'{t:.1f}' for t in chain.iat)}, ESS "
            f"{', '.join(f'{e:,.0f}' for e in chain.ess)}.{caveat} Posterior θ: {theta}.",
            css_classes=["koh-summary"])
        post = pn.pane.HoloViews(hv.Layout(plots.koh_posterior(c, m)).cols(3)
                                 .opts(shared_axes=False),     # densities differ in scale
                                 sizing_mode="stretch_width", css_classes=["koh-plot"])
        return pn.Column(*objs, summary, post, sizing_mode="stretch_width")

    def __panel__(self):
        hm_tab = pn.Column(self.status_view, self.wave_selector, self.waves_view,
                           sizing_mode="stretch_width")
        disc_tab = pn.Column(pn.widgets.RadioButtonGroup.from_param(self.param.quantity),
                             self.discrepancy_view, sizing_mode="stretch_width")
        metrics_tab = pn.Column(
            pn.pane.Markdown("SPEC §8 metrics at the test inputs. NMSE in percent; RMSE δ "
                             "in the output's units (NMSE δ divides by the variance of the "
                             "true δ, which is tiny where δ hardly varies, as on shear-5); "
                             "coverage = share of test points (or of the true δ) inside the "
                             "band."),
            self.metrics_view, sizing_mode="stretch_width")
        tabs = pn.Tabs(("Data", self.data_view), ("History matching", hm_tab),
                       ("Discrepancy", disc_tab), ("Metrics", metrics_tab),
                       dynamic=False, sizing_mode="stretch_width")
        return pn.Row(self._controls(), tabs, sizing_mode="stretch_width")
