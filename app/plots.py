"""Plotting functions: arrays in, HoloViews elements out (Bokeh backend).

Nothing here computes a model; everything takes the numbers the state already holds.
"""

from __future__ import annotations

import holoviews as hv
import numpy as np

from mdcore.pipeline import Method

#: Category10 (the wave colours repeat after ten waves).
WAVE_COLORS = ["#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2",
               "#7f7f7f", "#bcbd22", "#17becf"]
METHOD_COLORS = {Method.S1: "#1f77b4", Method.S2: "#ff7f0e", Method.S3: "#2ca02c",
                 Method.KOH: "#d62728"}
PLOT = {"responsive": True, "height": 300, "min_width": 200, "tools": ["hover"], "show_grid": True}


def _label(name: str, unit: str) -> str:
    return f"{name} [{unit}]" if unit and unit != "-" else name


def data_overview(case, var_bar: np.ndarray, *, output: int = 0) -> hv.Layout:
    """Paper Fig. 1: data with ±2√(V_o + V_m) bars, η(θ_true), and the true δ.

    Parameters
    ----------
    case : mdcore.cases.Case
    var_bar : ndarray of shape (n_out,)
        ``V_o + V_m`` per output, output units squared.
    output : int
        Which output to show (1-D input cases); shear-5 shows every mode.
    """
    xname = _label(case.x_names[0], case.x_units[0])
    if case.d_x == 2:
        return _data_overview_2d(case, var_bar)
    outputs = range(case.n_out) if case.n_out > 1 else [output]
    lo, hi = case.X_train[:, 0].min(), case.X_train[:, 0].max()
    lo, hi = min(lo, case.X_test[:, 0].min()), max(hi, case.X_test[:, 0].max())
    xs = np.linspace(lo, hi, 201)[:, None]
    sim = None if case.theta_true is None else case.simulate(xs, case.theta_true)[0]
    delta = case.true_delta(xs)
    panels = []
    for o in outputs:
        yname = _label(case.output_names[o], case.output_units[o])
        bar = 2.0 * np.sqrt(var_bar[o])
        train = hv.ErrorBars((case.X_train[:, 0], case.z_train[:, o],
                              np.full(len(case.X_train), bar)),
                             kdims=[xname], vdims=[yname, "±2σ"], label="train ±2√(V_o+V_m)")
        pts = hv.Scatter((case.X_train[:, 0], case.z_train[:, o]), xname, yname,
                         label="training data").opts(color="black", size=6)
        test = hv.Scatter((case.X_test[:, 0], case.z_test[:, o]), xname, yname,
                          label="test data").opts(color="grey", size=3, alpha=0.6)
        layers = [train.opts(color="black", alpha=0.5), pts, test]
        if sim is not None:
            layers.append(hv.Curve((xs[:, 0], sim[:, o]), xname, yname,
                                   label="simulator at true θ").opts(color="#d62728"))
        overlay = hv.Overlay(layers).opts(title=f"{case.output_names[o]}: data and simulator",
                                          legend_position="top_right", **PLOT)
        panels.append(overlay)
        if delta is not None:
            panels.append(hv.Curve((xs[:, 0], delta[:, o]), xname,
                                   _label("δ " + case.output_names[o], case.output_units[o]),
                                   label="true δ").opts(color="#9467bd",
                                                        title=f"true discrepancy δ, "
                                                              f"{case.output_names[o]}", **PLOT))
    return hv.Layout(panels).cols(2).opts(shared_axes=False)


def _data_overview_2d(case, var_bar) -> hv.Layout:
    x1 = _label(case.x_names[0], case.x_units[0])
    x2 = _label(case.x_names[1], case.x_units[1])
    yname = _label(case.output_names[0], case.output_units[0])
    pts = hv.Points((case.X_train[:, 0], case.X_train[:, 1], case.z_train[:, 0]), [x1, x2],
                    [yname]).opts(color=yname, cmap="viridis", size=9, colorbar=True,
                                  title=f"training data (±2√(V_o+V_m) = "
                                        f"±{2 * np.sqrt(var_bar[0]):.3g})", **PLOT)
    panels = [pts]
    if case.true_delta(case.X_train[:1]) is not None:
        panels.append(true_delta_2d(case).opts(title="true discrepancy δ"))
    return hv.Layout(panels).cols(2).opts(shared_axes=False)


def _span(case, d):
    X = np.vstack([case.X_train, case.X_test])
    return float(X[:, d].min()), float(X[:, d].max())


def nroy_samples(waves, names, units, bounds, truth, upto: int, *,
                 max_points: int = 1500) -> list:
    """NROY samples of waves 1..upto in θ space, coloured by wave, with the true θ.

    One overlaid histogram per wave for p = 1; one scatter plot per pair of parameters for
    p ≥ 2. A list of plots: the view gives each its own pane (responsive plots inside one
    HoloViews layout collapsed to zero width in the browser).
    """
    labels = [_label(n, u) for n, u in zip(names, units)]
    p = len(labels)
    shown = [w for w in waves if w.index <= upto]
    rng = np.random.default_rng(0)
    samples = []
    for w in shown:
        nroy = w.nroy
        if nroy.shape[0] > max_points:
            nroy = nroy[rng.choice(nroy.shape[0], max_points, replace=False)]
        samples.append((w.index, nroy))
    if p == 1:
        hists = [hv.Histogram(np.histogram(s[:, 0], bins=40, range=tuple(bounds[0])),
                              kdims=[labels[0]], label=f"wave {k}").opts(
                                  alpha=0.5, color=WAVE_COLORS[(k - 1) % 10])
                 for k, s in samples if s.shape[0]]
        if truth is not None:
            hists.append(hv.VLine(truth[0]).opts(color="black", line_dash="dashed"))
        return [hv.Overlay(hists).opts(title="NROY samples", **PLOT)]
    panels = []
    for i in range(p):
        for j in range(i + 1, p):
            layers = [hv.Scatter((s[:, i], s[:, j]), labels[i], labels[j],
                                 label=f"wave {k}").opts(color=WAVE_COLORS[(k - 1) % 10], size=3,
                                                         alpha=0.5)
                      for k, s in samples if s.shape[0]]
            if truth is not None:
                layers.append(hv.Scatter(([truth[i]], [truth[j]]), labels[i], labels[j],
                                         label="true θ").opts(color="black", marker="x",
                                                              size=14, line_width=3))
            panels.append(hv.Overlay(layers).opts(
                title=f"NROY samples: {names[i]} vs {names[j]}",
                xlim=tuple(bounds[i]), ylim=tuple(bounds[j]), legend_position="top_right",
                **PLOT))
    return panels


def implausibility_map(t1, t2, I, threshold, names, units, truth, wave_index):
    """Combined implausibility over the θ plane for one wave, with the T contour."""
    l1, l2 = (_label(n, u) for n, u in zip(names, units))
    img = hv.Image((t1, t2, np.minimum(I, 3 * threshold)), [l1, l2], "implausibility").opts(
        cmap="viridis_r", colorbar=True, clim=(0.0, 3 * threshold),
        title=f"wave {wave_index}: implausibility (clipped at 3T; contour at T = {threshold:g})",
        **PLOT)
    contour = hv.operation.contours(hv.Image((t1, t2, I), [l1, l2], "I"),
                                    levels=[threshold]).opts(color="white", line_width=2)
    layers = [img, contour]
    if truth is not None:
        layers.append(hv.Scatter(([truth[0]], [truth[1]]), l1, l2, label="true θ").opts(
            color="red", marker="x", size=14, line_width=3))
    return hv.Overlay(layers)


def nroy_fraction(waves) -> hv.Overlay:
    """NROY fraction of the original box after each wave (percent)."""
    k = [w.index for w in waves]
    f = [100 * w.nroy_fraction for w in waves]
    return (hv.Curve((k, f), "wave", "NROY [% of box]") *
            hv.Scatter((k, f), "wave", "NROY [% of box]").opts(size=8)).opts(
        title="NROY fraction per wave", xticks=k or None, **PLOT)


def emulator_variance(waves, output_names) -> hv.Overlay:
    """Largest emulator variance at retained points ÷ (V_o + V_m); converged below 1."""
    k = [w.index for w in waves]
    ylabel = "max var / (V_o + V_m)"
    layers = [hv.HLine(1.0, kdims=["wave", ylabel]).opts(color="black", line_dash="dashed")]
    ratios = np.array([[w.max_var[o] / w.var_threshold[o] for w in waves]
                       for o in range(len(output_names))], dtype=float)
    finite = ratios[np.isfinite(ratios) & (ratios > 0)]
    lo = min(float(finite.min()) if finite.size else 1.0, 1.0) / 3
    hi = max(float(finite.max()) if finite.size else 1.0, 1.0) * 3
    for o, name in enumerate(output_names):
        r = ratios[o].tolist()
        layers.append(hv.Curve((k, r), "wave", ylabel, label=name))
        layers.append(hv.Scatter((k, r), "wave", ylabel, label=name).opts(size=7))
    return hv.Overlay(layers).opts(title="emulator variance vs V_o + V_m (converged below 1)",
                                   logy=True, ylim=(lo, hi), xticks=k or None, **PLOT)


def band_1d(x, mean, var, k, *, color, label, xname, yname) -> hv.Overlay:
    """Mean ± k·sd band over a 1-D input."""
    sd = k * np.sqrt(var)
    return (hv.Area((x, mean - sd, mean + sd), xname, [yname, f"{yname} (upper)"],
                    label=f"{label} ±{k}σ").opts(color=color, alpha=0.25, line_alpha=0) *
            hv.Curve((x, mean), xname, yname, label=f"{label} mean").opts(color=color))


def discrepancy_1d(case, grid, results, methods, k, output, quantity) -> list:
    """Per method, one plot of z* (with data) or δ* (with the true δ), 1-D input.

    ``grid`` (G, 1) are the inputs of each result's ``on_extra`` prediction.
    """
    xname = _label(case.x_names[0], case.x_units[0])
    unit = case.output_units[output]
    x = grid[:, 0]
    truth = case.true_delta(grid)
    plots = []
    for s in methods:
        on_grid = results[s].on_extra
        if quantity == "z":
            yname = _label(case.output_names[output], unit)
            layers = [band_1d(x, on_grid.z_mean[:, output], on_grid.z_var[:, output], k,
                              color=METHOD_COLORS[s], label=s.label, xname=xname,
                              yname=yname),
                      hv.Scatter((case.X_test[:, 0], case.z_test[:, output]), xname, yname,
                                 label="test data").opts(color="grey", size=3, alpha=0.6),
                      hv.Scatter((case.X_train[:, 0], case.z_train[:, output]), xname, yname,
                                 label="training data").opts(color="black", size=6)]
            title = f"{s.label}: bias-corrected {case.output_names[output]}"
        else:
            yname = _label("δ " + case.output_names[output], unit)
            layers = [band_1d(x, on_grid.delta_mean[:, output], on_grid.delta_var[:, output],
                              k, color=METHOD_COLORS[s], label=s.label, xname=xname,
                              yname=yname)]
            if truth is not None:
                layers.append(hv.Curve((x, truth[:, output]), xname, yname,
                                       label="true δ").opts(color="black", line_dash="dashed"))
            title = f"{s.label}: discrepancy δ, {case.output_names[output]}"
        plots.append(hv.Overlay(layers).opts(title=title, legend_position="top_right",
                                             **PLOT))
    return plots


def discrepancy_2d(case, grid, result, k, x2_slice) -> list:
    """beam-2d: δ mean and band width on the (x₁, x₂) plane, and a slice at x₂.

    ``grid`` (G, 2) is the square grid of ``result.on_extra`` (x₁ fastest).
    """
    x1 = _label(case.x_names[0], case.x_units[0])
    x2 = _label(case.x_names[1], case.x_units[1])
    u1, u2 = np.unique(grid[:, 0]), np.unique(grid[:, 1])
    shape = (u2.size, u1.size)
    on_grid = result.on_extra
    mean = on_grid.delta_mean[:, 0].reshape(shape)
    width = (2 * k * np.sqrt(on_grid.delta_var[:, 0])).reshape(shape)
    s = result.method
    img = hv.Image((u1, u2, mean), [x1, x2], "δ mean [mm]").opts(
        cmap="RdBu_r", colorbar=True, title=f"{s.label}: δ mean", **PLOT)
    band = hv.Image((u1, u2, width), [x1, x2], f"band width ±{k}σ [mm]").opts(
        cmap="magma", colorbar=True, title=f"{s.label}: band width (±{k}σ)", **PLOT)
    row = int(np.argmin(np.abs(u2 - x2_slice)))      # nearest grid row to the slice
    xs = u1
    var = on_grid.delta_var[:, 0].reshape(shape)
    slice_plot = band_1d(xs, mean[row], var[row], k, color=METHOD_COLORS[s],
                         label=s.label, xname=x1, yname="δ [mm]")
    truth = case.true_delta(np.column_stack([xs, np.full_like(xs, u2[row])]))
    layers = [slice_plot]
    if truth is not None:
        layers.append(hv.Curve((xs, truth[:, 0]), x1, "δ [mm]", label="true δ").opts(
            color="black", line_dash="dashed"))
    return [img, band, hv.Overlay(layers).opts(
        title=f"{s.label}: slice at {case.x_names[1]} = {u2[row]:.4f} m",
        legend_position="top_right", **PLOT)]


def true_delta_2d(case) -> hv.Image:
    """beam-2d: the true δ on the plotting grid (for comparison with the scenarios)."""
    x1 = _label(case.x_names[0], case.x_units[0])
    x2 = _label(case.x_names[1], case.x_units[1])
    n = 60
    g1, g2 = np.meshgrid(np.linspace(*_span(case, 0), n), np.linspace(*_span(case, 1), n))
    delta = case.true_delta(np.column_stack([g1.ravel(), g2.ravel()]))
    return hv.Image((g1[0], g2[:, 0], delta[:, 0].reshape(n, n)), [x1, x2], "δ mean [mm]").opts(
        cmap="RdBu_r", colorbar=True, title="true δ", **PLOT)


def koh_posterior(case, model) -> list:
    """KOH: per parameter, the chain's histogram against the prior density and the truth.

    A posterior that looks like the prior is the non-identifiability the paper warns of:
    the GP discrepancy absorbs what θ should explain.
    """
    out = []
    for j, (name, unit) in enumerate(zip(case.theta_names, case.theta_units)):
        label = _label(name, unit)
        samples = model.theta[:, j]
        lo, hi = case.theta_bounds[j]
        edges = np.linspace(lo, hi, 61)
        density, _ = np.histogram(samples, bins=edges, density=True)
        mu, var = model.theta_prior.mean[j], model.theta_prior.var[j]
        x = np.linspace(lo, hi, 200)
        prior = np.exp(-0.5 * (x - mu) ** 2 / var) / np.sqrt(2 * np.pi * var)
        layers = [hv.Histogram((edges, density), kdims=[label], vdims=["density"],
                               label="KOH posterior").opts(
                      color=METHOD_COLORS[Method.KOH], alpha=0.5, line_alpha=0),
                  hv.Curve((x, prior), label, "density", label="prior").opts(
                      color="black", line_dash="dotted")]
        if case.theta_true is not None:
            layers.append(hv.VLine(float(case.theta_true[j]), label="truth").opts(
                color="black", line_width=2))
        out.append(hv.Overlay(layers).opts(title=f"KOH posterior of {name}",
                                           legend_position="top_right", **PLOT))
    return out
