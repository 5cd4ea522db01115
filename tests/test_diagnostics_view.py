"""The Diagnostics tab (issue 42) on an own case with six parameters and two inputs."""

import time

import numpy as np
import panel as pn
import pytest
from bokeh.document import Document
from bokeh.models import GlyphRenderer, Image

from mdcore._case_file import load_case_file
from mdcore._pipeline import Method

FIN = '''
import numpy as np


def temperature(X, theta):
    """Temperature [°C] at (position x [m], time t [s]) of a cooling pin fin: ambient T_a,
    initial excess dT0, decay k [1/s], fin parameter m [1/m], sensor gain g and offset b."""
    theta = np.atleast_2d(theta)
    Ta, dT0, k, m, g, b = (theta[:, j, None] for j in range(6))
    x, t = X[None, :, 0], X[None, :, 1]
    shape = np.cosh(m * (0.2 - x)) / np.cosh(m * 0.2)
    return (g * (Ta + dT0 * np.exp(-k * t) * shape) + b)[..., None]
'''
FIN_BOUNDS = {"T_a": ("degC", 15.0, 25.0), "dT0": ("K", 40.0, 80.0), "k": ("1/s", 1e-3, 5e-3),
              "m": ("1/m", 5.0, 15.0), "g": ("-", 0.9, 1.1), "b": ("K", -2.0, 2.0)}


@pytest.fixture(scope="module")
def fin_case(tmp_path_factory):
    return write_fin_case(tmp_path_factory.mktemp("fin"))


def write_fin_case(folder):
    """A case file in ``folder``: six parameters, two inputs (position, time); the real fin
    also loses heat by radiation, ~ 4 % of the excess, which the simulator leaves out."""
    import sys
    (folder / "fin_sim.py").write_text(FIN, encoding="utf-8")
    params = "".join(f'[[parameters]]\nname = "{n}"\nunit = "{u}"\nlower = {lo}\n'
                     f"upper = {hi}\n" for n, (u, lo, hi) in FIN_BOUNDS.items())
    (folder / "fin.toml").write_text(
        'name = "pin-fin"\ntitle = "Cooling pin fin (SYNTHETIC)"\n[data]\nfile = "fin.csv"\n'
        'inputs = ["x", "t"]\ninput_units = ["m", "s"]\noutputs = ["T"]\n'
        'output_units = ["degC"]\ntest_column = "test"\nnoise_var = [0.04]\n[simulator]\n'
        'function = "fin_sim:temperature"\npath = "."\n' + params
        + "[history_matching]\nV_m = [1.0]\ninitial_design = 60\n", encoding="utf-8")
    sys.path.insert(0, str(folder))
    try:
        from fin_sim import temperature
    finally:
        sys.path.remove(str(folder))
    rng = np.random.default_rng(3)
    rows = ["x,t,T,test"]
    for test, xs, ts in ((0, (0.0, 0.05, 0.1, 0.15), (0, 200, 400)),
                         (1, (0.025, 0.075, 0.125, 0.175), (100, 300))):
        X = np.array([(x, t) for x in xs for t in ts], dtype=float)
        excess = temperature(X, [20.0, 60.0, 3e-3, 10.0, 1.0, 0.0])[0, :, 0] - 20.0
        z = 20.0 + 0.96 * excess + 0.2 * rng.standard_normal(len(X))
        rows += [f"{x},{t},{v:.4f},{test}" for (x, t), v in zip(X, z)]
    (folder / "fin.csv").write_text("\n".join(rows) + "\n", encoding="utf-8")
    return folder / "fin.toml"


def test_six_parameter_own_case_draws_every_view(fin_case):
    from mdcore_app.state import ExplorerState
    from mdcore_app.views import ExplorerView

    case = load_case_file(fin_case)
    assert case.p == 6 and case.d_x == 2
    s = ExplorerState(own_cases=(case,), n_candidates=20_000, n_s=20, n_phi=5)
    s.case_name = "pin-fin"
    s.param.update(preset="paper", max_waves=2)
    view = ExplorerView(state=s)
    doc = Document()
    doc.add_root(pn.panel(view).get_root(doc))
    d = view._diagnostics
    view._tabs.active = 4                        # before any wave: a placeholder, at once
    assert "Press" in d._box.objects[0].object.text
    s.run_to_convergence()
    s.scenarios = [Method.S1, Method.S2]
    s.run_discrepancy()
    assert not s.error and s.results
    n = d.numbers
    assert n is not None and len(n.validations) == len(s.waves)
    assert n.views.min_implausibility.shape == (15, 20, 20)
    assert set(n.splits) == {Method.S2} and 0.0 <= n.splits[Method.S2].share[0] <= 1.0
    # δ is drawn along x at one time shared by four test inputs (the test grid's t rows)
    assert len(n.rows) == 4 and np.unique(case.X_test[n.rows, 1]).size == 1
    figs = [p.object for p in d._box.select(pn.pane.Bokeh)]
    lattice = next(f for f in figs if "diag-lattice" in (f.css_classes or []))
    images = [r for r in lattice.renderers if isinstance(r.glyph, Image)]
    upper, lower = (r.data_source.data for r in images)
    assert len(upper["image"]) == len(lower["image"]) == 15
    # Orientation against a naive loop: the panel in column l, row k (from the top) holds,
    # at [bin of k, bin of l], the smallest implausibility of the candidates in that bin.
    v, p = n.views, case.p
    k, m = 1, 4
    c = next(i for i, (a, b) in enumerate(v.pairs) if (a, b) == (k, m))
    assert (upper["x"][c], upper["y"][c]) == (m, p - 1 - k)
    unit = (v.theta - case.theta_bounds[:, 0]) / np.ptp(case.theta_bounds, axis=1)
    bins = np.minimum((unit * 20).astype(int), 19)
    for bk, bm in ((3, 7), (10, 2), (19, 19)):
        sel = (bins[:, k] == bk) & (bins[:, m] == bm)
        assert upper["image"][c][bk, bm] == pytest.approx(v.implausibility[sel].min())
        assert lower["image"][c][bm, bk] == pytest.approx(np.mean(v.ruled_out_by[sel] == 0))
    # every figure of the tab has data: glyphs with at least one non-empty column
    plots = [f for f in figs if hasattr(f, "renderers")]
    assert len(plots) >= 9
    for f in plots:
        sizes = [len(next(iter(r.data_source.data.values()))) for r in f.renderers
                 if isinstance(r, GlyphRenderer) and r.data_source.data]
        assert sizes and max(sizes) > 0, f.title.text
    # a wrongly ruled-out run is crossed at its simulated against its left-out values
    from mdcore_app.diagnostics_view import loo_figures
    last = n.validations[-1]
    bad = np.zeros(len(last.theta), bool)
    bad[2] = True
    marked = n._replace(validations=(last._replace(wrongly_ruled_out=bad),),
                        simulated=n.simulated[-1:])
    crosses = [r.data_source.data for r in loo_figures(case, marked, 0)[0].renderers
               if getattr(r.glyph, "marker", None) == "x"]
    assert len(crosses) == 1
    assert np.allclose(crosses[0]["x"], n.simulated[-1][2, :, 0])
    assert np.allclose(crosses[0]["y"], last.loo.mean[2, :, 0])


def test_browser_diagnostics_tab_on_beam_1d():
    """Shown before any wave: a placeholder at once; after a history match and a
    discrepancy run: every view drawn, and the table holds one row per wave."""
    from browser import PageLog, chromium, require_browser, serve_app, tab
    require_browser()
    proc, url, _log = serve_app()
    try:
        for browser in chromium():
            page = browser.new_page(viewport={"width": 1280, "height": 720})
            log = PageLog(page)
            page.goto(url)
            page.wait_for_selector(".data-plot canvas", timeout=60_000)
            tab(page, "Diagnostics")
            page.wait_for_selector(".diag-placeholder:has-text('Press')", timeout=2_000)
            page.get_by_role("button", name="Run to convergence").click()
            page.wait_for_selector(".diag-loo-table", timeout=90_000)
            # A new request supersedes a running one: let the waves finish first.
            page.wait_for_selector(".mdcore-idle", timeout=90_000)
            page.get_by_role("button", name="Run discrepancy").click()
            page.wait_for_selector(".diag-delta", timeout=90_000)
            rows = page.locator(".diag-loo-table tr").count() - 1
            assert rows >= 2                 # the teaching preset: several waves
            canvases = page.locator(".diag-plot canvas")
            end = time.monotonic() + 30
            while True:                      # LOO 2, space 2, hits 2, θ–δ 2 per scenario
                drawn = [b for k in range(canvases.count())
                         if (b := canvases.nth(k).bounding_box()) and b["width"] > 100]
                if len(drawn) >= 10 or time.monotonic() > end:
                    break
                page.wait_for_timeout(250)
            assert len(drawn) >= 10, len(drawn)
            assert "diag-help-lattice" not in page.content()        # p = 2: the pair plot
            assert log.errors == [] and log.hosts <= {"127.0.0.1", "localhost"}
    finally:
        proc.terminate()
        proc.wait(timeout=10)
