"""The Metrics tab: the metrics (docs/method.md §8), diagnostics and posteriors of the
shown results."""

from __future__ import annotations

import pandas as pd
import panel as pn

from mdcore._pipeline import Method, MethodResult
from mdcore._study import PAPER

from . import plots
from .alerts import warnings_html
from .live_figures import figure_pane
from .markup import markdown_text
from .runs import method_order

#: Shown in the metrics table where a diagnostic does not apply to a method.
NOT_APPLICABLE = "—"
#: The columns of :func:`metrics_frame` shown in the diagnostics table, not the metrics one.
DIAGNOSTICS = ("ESS pairs", "ESS φ", "Pareto k̂", "acceptance", "IAT (max)", "chain ESS (min)")


def metrics_frame(case, results: dict[Method, MethodResult]) -> pd.DataFrame:
    """One row per (method, output): the metrics (docs/method.md §8), the δ RMSE (output
    units), then the method's diagnostics.

    The importance-sampling diagnostics (ESS over the (θ, φ) pairs, ESS over φ, Pareto k̂)
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
                "Pareto k̂": per_output(None if imp is None else imp.k_hat, o),
                "acceptance": NOT_APPLICABLE if chain is None else chain.acceptance_rate,
                "IAT (max)": NOT_APPLICABLE if chain is None else max(chain.iat),
                "chain ESS (min)": NOT_APPLICABLE if chain is None else min(chain.ess),
                "seconds": r.seconds})
    return pd.DataFrame(rows)



def metrics_panel(s) -> pn.Column:
    """The Metrics tab's content for the state ``s``: chart, table, diagnostics, scenario
    3's φ posterior and KOH's chain, for the shown results."""
    shown = {k: v for k, v in s.results.items() if k in s.scenarios}
    if not shown:
        return pn.pane.Markdown("No scenario has run yet: press **Run discrepancy** (it runs "
                                "the history match first if there is none).",
                                css_classes=["metrics-placeholder"])
    df = metrics_frame(s.case, shown)
    chart = figure_pane(plots.metrics_chart(s.case, shown, PAPER.get(s.base_case_name())))
    table = pn.pane.DataFrame(df.drop(columns=list(DIAGNOSTICS)), index=False,
                              float_format="{:.4g}".format, sizing_mode="stretch_width",
                              css_classes=["metrics-table"])
    # The tables first, the chart below: at 1280×720 the diagnostics a card points at
    # (ESS φ, k̂) were below the fold, under a toast; the advice now sits beside them.
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
    advice = [w for m in sorted(shown, key=method_order) for w in shown[m].warnings]
    if advice:
        objs.append(pn.pane.HTML(warnings_html(advice), css_classes=["metrics-advice"],
                                 sizing_mode="stretch_width"))
    objs.append(chart)
    if Method.S3 in shown:
        o = s.output_index
        phi = plots.phi_posterior(s.case, shown[Method.S3], output=o)
        objs.append(pn.pane.Markdown(
            "**Scenario 3: the GP hyperparameters φ, posterior (weighted draws) against "
            f"prior** (the paper's Figs 6, 9, 16; output "
            f"{markdown_text(s.case.output_names[o])})."))
        # Two a row, the legend below: four a row at 1280 px clipped the titles and
        # axis labels, and a legend inside covered the histogram.
        for i in range(0, len(phi), 2):
            objs.append(pn.Row(*[figure_pane(f) for f in phi[i:i + 2]],
                               sizing_mode="stretch_width"))
    if Method.KOH not in shown:
        return pn.Column(*objs, sizing_mode="stretch_width")
    r = shown[Method.KOH]
    m, chain = r.model, r.chain
    c = s.case
    theta = markdown_text(", ".join(
        f"{n} = {mu:.4g} ± {sd:.2g}" + ("" if u in ("", "-") else f" {u}")
        for n, mu, sd, u in zip(c.theta_names, m.theta.mean(axis=0), m.theta.std(axis=0),
                                c.theta_units)))
    caveat = "" if chain.reliable else (" The chain is shorter than 50 autocorrelation "
                                        "times, so these are themselves uncertain.")
    summary = pn.pane.Markdown(
        f"**KOH chain:** {chain.n_iter:,} iterations ({chain.burn_in:,} burn-in), "
        f"acceptance {chain.acceptance_rate:.2f}, integrated autocorrelation time "
        f"{', '.join(f'{t:.1f}' for t in chain.iat)}, ESS "
        f"{', '.join(f'{e:,.0f}' for e in chain.ess)}.{caveat} Posterior θ: {theta}.",
        css_classes=["koh-summary"])
    # One pane per parameter, axes not linked (densities differ in scale): an
    # hv.Layout of responsive plots in one pane drew each frame with no height.
    post = pn.GridBox(*[pn.pane.HoloViews(o, sizing_mode="stretch_width",
                                          height=plots.PLOT["height"], linked_axes=False)
                        for o in plots.koh_posterior(c, m)],
                      ncols=3, sizing_mode="stretch_width", css_classes=["koh-plot"])
    return pn.Column(*objs, summary, post, sizing_mode="stretch_width")

