"""The HTML report: self-contained, every plot has data, and it renders offline in Chromium."""

import html
import re
import warnings

import numpy as np
import pytest

pytest.importorskip("bokeh")
from bokeh.models import Div, GlyphRenderer, Plot  # noqa: E402
from browser import CHROMIUM, FLAGS, files_only, require_browser  # noqa: E402

from mdcore import _cases as cases  # noqa: E402
from mdcore._pipeline import Settings  # noqa: E402
from mdcore._reproduce import run_case  # noqa: E402
from mdcore_app.report import report_html, report_layout, write_report  # noqa: E402


@pytest.fixture(scope="module")
def run():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return run_case(cases.load("beam-1d"), methods=[1, 3, "koh"],
                        settings=Settings(n_s=20, n_phi=10, n_iter=1000, burn_in=200),
                        n_candidates=5000)


def test_every_plot_has_data(run):
    layout = report_layout(run)
    renderers = list(layout.select({"type": GlyphRenderer}))
    assert len(renderers) >= 20
    for r in renderers:
        data = r.data_source.data
        lengths = {len(v) for v in data.values()}
        assert lengths and min(lengths) > 0, (r.glyph, {k: len(v) for k, v in data.items()})
    titles = [f.title.text for f in layout.select({"type": Plot}) if f.title is not None]
    assert "KOH: δ tip deflection (±2σ)" in titles
    # the app's figure builders: the space each wave ruled out, the θ posterior with θ_MAP
    # and the metrics chart
    assert "NROY share of the box" in titles
    assert f"l_cr: θ_MAP = {run.hm.theta_map[0]:.4g} mm" in titles
    assert any(t.startswith("NMSE at the test inputs") for t in titles)
    text = " ".join(d.text for d in layout.select({"type": Div}))
    for words in ("Settings", "History matching", "Metrics at the test inputs", "Warnings",
                  "Scenario 3", "KOH", "θ_MAP", "truth in NROY",
                  "Emulator check, leaving out each run", "wrongly ruled out",
                  "θ–δ trade-off", "share of Var(δ) from θ"):
        assert words in text


def test_html_is_self_contained(run):
    # Importing Panel (as the app does) registers models whose scripts Bokeh would add to every
    # page as <script src="static/extensions/...">; the report must leave them out.
    pytest.importorskip("panel")
    html = report_html(run)
    assert not re.search(r"<script[^>]+src=", html) and not re.search(r"<link[^>]+href=", html)
    assert "Cracked cantilever" in html and "Bokeh" in html


def test_report_renders_offline_in_chromium(run, tmp_path):
    require_browser()
    from playwright.sync_api import sync_playwright
    path = write_report(run, tmp_path / "report.html")
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=FLAGS)
        page = browser.new_page(viewport={"width": 1280, "height": 720})
        outside = files_only(page)
        page.goto(path.as_uri())
        page.wait_for_function("window.Bokeh && Object.keys(Bokeh.index).length > 0",
                               timeout=30_000)
        page.wait_for_load_state("networkidle")
        shot = page.screenshot(full_page=True)
        browser.close()
    assert outside == []
    from io import BytesIO

    from PIL import Image
    img = np.asarray(Image.open(BytesIO(shot)).convert("L"), dtype=float)
    # Plots drawn: well below the page top (text), many rows differ from the white page.
    body = img[img.shape[0] // 3:]
    assert np.mean(np.std(body, axis=1) > 10) > 0.3


def test_the_report_does_not_depend_on_bokehs_current_document(run):
    """In a server process Bokeh's global current document can be a session's document
    that has been destroyed; the served app's report download failed with an
    AttributeError (``_js_event_callbacks``) there. The report is built in a document of
    its own."""
    from bokeh.document import Document
    from bokeh.io.doc import curdoc, set_curdoc
    before = curdoc()
    gone = Document()

    def session(event):                     # a session's change callback, as Bokeh's
        pass

    gone.on_change(session)
    gone.destroy(session)                   # what the server does when a session ends
    set_curdoc(gone)
    try:
        html = report_html(run)
    finally:
        set_curdoc(before)
    assert "Cracked cantilever" in html and html.count("<script") >= 2


def test_bands_are_drawn_on_a_dense_grid_of_inputs_as_in_the_app(run):
    """Issue 39/41: the report joined only the test inputs with straight lines (a tent on
    beam-lab). Its bands are the app's BandFigure on the app's plotting grid."""
    from bokeh.models import VArea

    from mdcore_app.case_model import GRID_1D, plotting_grid

    layout = report_layout(run)
    bands = [r for r in layout.select({"type": GlyphRenderer}) if isinstance(r.glyph, VArea)]
    assert len(bands) == 2 * len(run.results)                  # z and δ per method
    grid = plotting_grid(run.case)[:, 0]
    for r in bands:
        x = np.asarray(r.data_source.data["x"])
        assert x.size == GRID_1D and np.allclose(x, grid)
        assert np.all(np.isfinite(r.data_source.data["lower"]))
    s1 = next(r for r in run.results if r.method.value == "1")
    expected = s1.model.predict(plotting_grid(run.case))
    (fig,) = [f for f in layout.select({"type": Plot})
              if f.title is not None and f.title.text == "Scenario 1: tip deflection (±2σ)"]
    (band,) = [r for r in fig.renderers if isinstance(r.glyph, VArea)]
    data = band.data_source.data
    np.testing.assert_allclose(data["upper"] - data["lower"],
                               4 * np.sqrt(expected.z_var[:, 0]), rtol=1e-8)


def test_settings_and_warnings_say_what_the_run_did(run):
    # Issue 41, item 7: the settings listed KOH's chain when KOH did not run, and
    # "Warnings: None." stood under the run's own advice in red.
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        lone = run_case(cases.load("beam-1d"), methods=[3], n_candidates=5000,
                        settings=Settings(n_s=5, n_phi=2, n_iter=1000, burn_in=200))
    for r, koh in ((lone, False), (run, True)):
        text = " ".join(d.text for d in report_layout(r).select({"type": Div}))
        settings = text.split("<h2>Settings</h2>")[1].split("<h2>")[0]
        assert "N_φ" in settings and "φ proposal" in settings
        assert ("KOH chain" in settings) == koh
        said = [v.advice for v in r.validation if v.advice]
        said += [w for m in r.results for w in m.warnings]
        assert said or koh, "N_φ = 2 must raise the advice this test is about"
        tail = text.split("<h2>Warnings</h2>")[1]
        assert "None." not in tail
        for w in said:
            assert html.escape(w) in tail
