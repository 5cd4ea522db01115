"""Server time of one band plot's update: HoloViews streams against the app's BandFigure.

Usage: python bench/bench_plot_layer.py [--repeats 20]

Issue 39 asks for one plotting layer, HoloViews where it meets the targets. This times,
in-process (no browser), what the server does for the Discrepancy tab's most frequent
display-only change (a new band ±kσ over beam-1d's 101-point grid) and for a new result:

* HoloViews: a ``DynamicMap`` over a ``Pipe`` (band ``hv.Area`` × mean ``hv.Curve`` × data
  ``hv.Scatter``), rendered once into a Bokeh document by ``pn.pane.HoloViews``, then
  ``pipe.send(new data)``: HoloViews re-runs the element pipeline and patches the plot;
* BandFigure (app/live_figures.py): ``show(...)``, which patches the two sources' arrays.

It prints the minimum and median over ``--repeats`` updates (the minimum: the machine is
shared) and their ratio, in the same run. The browser's share is in bench_browser.py.
"""

from __future__ import annotations

import argparse
import statistics
import time

import holoviews as hv
import numpy as np
import panel as pn
from bokeh.document import Document

from mdcore_app.live_figures import BandFigure


def data(k: int, shift: float):
    x = np.linspace(0.1, 0.9, 101)
    mean = np.sin(6 * x) + shift
    sd = 0.1 + 0.05 * np.cos(3 * x)
    return x, mean, sd ** 2, k


def holoviews_plot():
    pipe = hv.streams.Pipe(data=data(3, 0.0))
    rng = np.random.default_rng(0)
    xs = rng.uniform(0.1, 0.9, 13)
    points = hv.Scatter((xs, np.sin(6 * xs)), "x", "z").opts(color="black", size=6)

    def draw(data):
        x, mean, var, k = data
        sd = k * np.sqrt(var)
        return (hv.Area((x, mean - sd, mean + sd), "x", ["z", "z2"], label=f"±{k}σ")
                .opts(alpha=0.25) * hv.Curve((x, mean), "x", "z", label="mean") * points)

    dmap = hv.DynamicMap(draw, streams=[pipe]).opts(responsive=True, height=300,
                                                    title="Scenario 1: z")
    pane = pn.pane.HoloViews(dmap, sizing_mode="stretch_width", height=300)
    pane.get_root(Document())
    return lambda d: pipe.send(d)


def bokeh_plot():
    rng = np.random.default_rng(0)
    xs = rng.uniform(0.1, 0.9, 13)
    fig = BandFigure(title="Scenario 1: z", xname="x", yname="z", color="#1f77b4",
                     label="Scenario 1",
                     points=[(xs, np.sin(6 * xs), "data", {"color": "black", "size": 6})],
                     x=np.linspace(0.1, 0.9, 101))
    pn.pane.Bokeh(fig.figure).get_root(Document())
    return lambda d: fig.show(d[0], d[1], d[2], d[3])


def timed(update, repeats: int) -> list[float]:
    out = []
    for i in range(repeats):
        d = data(2 + i % 2, 0.01 * i)            # alternate the band, move the mean
        t0 = time.perf_counter()
        update(d)
        out.append(time.perf_counter() - t0)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=20)
    args = ap.parse_args()
    hv.extension("bokeh")
    holoviews_plot(), bokeh_plot()               # one-time costs (imports, caches) first
    rows = []
    for name, make in (("HoloViews DynamicMap + Pipe", holoviews_plot),
                       ("BandFigure (Bokeh sources)", bokeh_plot)):
        t0 = time.perf_counter()
        update = make()
        build = time.perf_counter() - t0
        times = timed(update, args.repeats)
        rows.append((name, build, min(times), statistics.median(times)))
    print(f"{'one band plot, server side':<30}{'build':>10}{'update min':>12}"
          f"{'update median':>15}")
    for name, build, lo, mid in rows:
        print(f"{name:<30}{build * 1e3:>8.1f} ms{lo * 1e3:>9.1f} ms{mid * 1e3:>12.1f} ms")
    print(f"HoloViews / BandFigure, update (min): {rows[0][2] / rows[1][2]:.1f}x; "
          f"build: {rows[0][1] / rows[1][1]:.1f}x")


if __name__ == "__main__":
    main()
