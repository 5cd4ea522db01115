"""App timings through the state classes (headless, no browser).

Usage: python bench/bench_app.py [--repeats 3]

Times (median of the repeats), for beam-1d at the app's default sizes:
- first figure: build the session state and render the default page into a Bokeh Document;
- one wave: ``ExplorerState.next_wave()`` (wave 1, 100,000 candidates);
- scenarios 1–3: ``ExplorerState.run_discrepancy()`` (N_s = 100, N_φ = 50), inference plus
  predictions on the plotting grid and the test inputs, plus rendering the Discrepancy tab.
Goal: each under 1 s on 2 cores.
"""

import argparse
import statistics
import time
import warnings

import holoviews as hv
import panel as pn
from bokeh.document import Document

from mdcore._pipeline import Method
from mdcore_app.state import ExplorerState
from mdcore_app.views import ExplorerView


def once():
    t0 = time.perf_counter()
    state = ExplorerState()
    view = ExplorerView(state=state)
    pn.panel(view).get_root(Document())
    t1 = time.perf_counter()
    state.next_wave()
    t2 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        state.run_discrepancy()
    pn.panel(view.discrepancy_view).get_root(Document())
    t3 = time.perf_counter()
    assert state.error == "" and set(state.results) == {Method.S1, Method.S2, Method.S3}, \
        state.error
    return t1 - t0, t2 - t1, t3 - t2


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    hv.extension("bokeh")
    once()                                              # warm-up (imports, Bokeh models)
    runs = [once() for _ in range(args.repeats)]
    for i, name in enumerate(["first figure", "one beam-1d wave", "scenarios 1–3 update"]):
        t = statistics.median(r[i] for r in runs)
        print(f"{name:<22} {t:6.2f} s  {'ok' if t < 1.0 else 'over the 1 s goal'}")


if __name__ == "__main__":
    main()
