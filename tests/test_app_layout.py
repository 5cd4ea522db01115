"""The app for a class at a projector's size (issues 39 and 41), in Debian's Chromium.

Each test fails on something found by going through the app at 1280×720 and 1920×1080:
plots scrolled away to reach a control, a progress bar hidden during a long run, a band
legend that did not say its band (or said "Invalid field"), a refused number that named
the state's class, and a tab that was blank before its first run.
"""

import re
import time

import pytest
from browser import PageLog, shown, tab

SIZES = [(1280, 720), (1920, 1080)]


def open_page(browser, url, size=(1280, 720)):
    page = browser.new_page(viewport={"width": size[0], "height": size[1]})
    log = PageLog(page)
    page.goto(url)
    page.wait_for_selector(".data-plot canvas", timeout=60_000)
    return page, log


def wait_idle(page, timeout=120_000):
    page.wait_for_timeout(300)
    page.locator(".mdcore-idle").wait_for(state="attached", timeout=timeout)


def in_view(page, locator) -> bool:
    """Whether the element is wholly inside the window."""
    box = locator.bounding_box()
    size = page.viewport_size
    return (box is not None and box["width"] > 0 and box["y"] >= 0 and box["x"] >= 0
            and box["y"] + box["height"] <= size["height"] + 1
            and box["x"] + box["width"] <= size["width"] + 1)


#: Scroll every scrolling box that holds an element of class ``cls`` to its end (across
#: shadow roots); returns how many it scrolled.
SCROLL_BOX_OF = """(cls) => {
  let n = 0;
  const walk = root => { for (const e of root.querySelectorAll('*')) {
    if (e.classList.contains(cls) && e.scrollHeight > e.clientHeight) {
      e.scrollTop = e.scrollHeight; n++; }
    if (e.shadowRoot) walk(e.shadowRoot); } };
  walk(document);
  return n;
}"""


def controls_out_of_view(page, selector: str) -> list[str]:
    """The inputs and buttons under ``selector`` that are not wholly in the window."""
    found = page.locator(f"{selector} input, {selector} button, {selector} select").all()
    assert found, selector
    return [c.evaluate("e => e.outerHTML.slice(0, 80)") for c in found if not in_view(page, c)]


@pytest.mark.parametrize("size", SIZES, ids=lambda s: f"{s[0]}x{s[1]}")
def test_every_control_of_the_tab_is_seen_beside_its_plots(browser, server, size):
    """Issue 41 item 4: the page itself never scrolls, and the controls of the tab shown
    are in view beside its plots without scrolling anything: the band control was below
    the sidebar's fold at 720 px (the sidebar had to be scrolled to reach it)."""
    page, log = open_page(browser, server.url, size)
    page.locator(".run-discrepancy button").click()
    tab(page, "Discrepancy")
    wait_idle(page)
    plot = page.locator(".disc-plot").first
    plot.wait_for(timeout=60_000)
    page.wait_for_timeout(1500)                      # the cards fold after 0.6 s
    assert in_view(page, plot)
    scrolling = page.evaluate("() => document.scrollingElement.scrollHeight")
    assert scrolling <= size[1] + 1, "the whole page scrolls"
    assert controls_out_of_view(page, ".disc-controls") == []
    assert controls_out_of_view(page, ".band-choice") == []
    tab(page, "History matching")
    page.wait_for_timeout(1500)                      # the cards fold after 0.6 s
    assert controls_out_of_view(page, ".hm-controls") == []
    assert in_view(page, page.locator(".hm-plot").first)
    for case in ("beam-2d", "shear-5"):        # longer descriptions, a stand-in warning
        page.locator("select").first.select_option(case)
        wait_idle(page)
        page.wait_for_timeout(1500)                      # the cards fold after 0.6 s
        assert controls_out_of_view(page, ".hm-controls") == [], case
    assert log.errors == []
    page.close()


def test_the_progress_bar_shows_during_a_long_run(browser, server):
    """Issue 41 item 2: the bar was ``visibility: hidden`` for the whole of a long run."""
    page, log = open_page(browser, server.url)
    page.locator(".bk-Checkbox", has_text="Paper sizes").locator("input").check()
    page.get_by_role("button", name="Run discrepancy").click()
    page.locator(".mdcore-busy").wait_for(state="attached", timeout=30_000)
    bar = page.locator(".job-progress progress")
    end, seen = time.monotonic() + 90, []
    while time.monotonic() < end and page.locator(".mdcore-busy").count():
        if bar.is_visible():
            seen.append(bar.evaluate("e => [getComputedStyle(e).visibility, e.value]"))
        page.wait_for_timeout(250)
    assert seen, "no visible progress bar during the run"
    assert all(v == "visible" for v, _ in seen) and max(x for _, x in seen) > 0
    if page.locator(".mdcore-busy").count():
        page.locator(".cancel-job button").click(timeout=5_000)
    wait_idle(page)
    assert log.errors == []
    page.close()


def test_the_band_legend_says_its_band(browser, server):
    """Issue 41 item 10: the legend read "±kσ" whatever the band; set as a field name,
    Bokeh drew "Invalid field"."""
    page, log = open_page(browser, server.url)
    page.get_by_role("button", name="Run discrepancy").click()
    tab(page, "Discrepancy")
    wait_idle(page)
    def labels():          # the legends' labels as the browser holds them (drawn on canvas)
        return page.evaluate("""() => { const out = [];
          for (const d of Bokeh.documents) for (const m of d.all_models)
            if (m.constructor.__name__ === "LegendItem") out.push(JSON.stringify(m.label));
          return out; }""")

    page.locator(".disc-plot canvas").first.wait_for(timeout=60_000)
    texts = " ".join(labels())
    assert "Scenario 1 ±3σ" in texts and "kσ" not in texts
    assert '"field"' not in texts                     # drawn as "Invalid field"
    group = page.locator(".bk-btn-group").filter(has_text="2").filter(has_text="3").last
    group.get_by_role("button", name="2", exact=True).click()
    # Every legend follows (the figures' patches arrive one by one): wait for the last.
    page.wait_for_function("""() => { let two = false;
      for (const d of Bokeh.documents) for (const m of d.all_models)
        if (m.constructor.__name__ === "LegendItem") {
          const label = JSON.stringify(m.label);
          if (label.includes("±3σ")) return false;
          two = two || label.includes("Scenario 1 ±2σ");
        }
      return two; }""", timeout=30_000)
    assert "±3σ" not in " ".join(labels())
    assert log.errors == []
    page.close()


def test_a_refused_number_says_what_is_allowed_in_plain_words(browser, server):
    """Issue 41 item 10: the toast named ``ExplorerState.v_m``, and its text overflowed."""
    page, log = open_page(browser, server.url)
    field = page.get_by_label("V_m", exact=True)
    field.fill("-1")
    field.press("Enter")
    toast = page.locator(".notyf__toast", has_text="V_m").first
    toast.wait_for(timeout=30_000)
    text = toast.inner_text()
    assert "is not allowed" in text and "greater than 0" in text
    assert "ExplorerState" not in text and "v_m" not in text
    message = page.locator(".notyf__message").first
    fits = message.evaluate("e => e.scrollWidth <= e.clientWidth + 1")
    box, outer = message.bounding_box(), toast.bounding_box()
    assert fits and box["x"] + box["width"] <= outer["x"] + outer["width"] + 1
    page.close()


#: Is an element of class ``cls`` (searched through shadow roots) laid out with a size,
#: and with ``canvas``, does it hold a drawn canvas; the tab it sits in need not be shown.
BUILT = """([cls, canvas]) => {
  const all = (root, out) => { for (const e of root.querySelectorAll('*')) { out.push(e);
      if (e.shadowRoot) all(e.shadowRoot, out); } return out; };
  return all(document, []).filter(e => e.classList.contains(cls)).some(h => !canvas ||
      all(h.shadowRoot || h, [h]).some(e => e.tagName === 'CANVAS' && e.width > 0));
}"""


@pytest.mark.parametrize("name, css, words", [
    ("History matching", "hm-placeholder", "Press Next wave"),
    ("Discrepancy", "disc-warnings", "press Run discrepancy"),
    ("Metrics", "metrics-placeholder", "press Run discrepancy")])
def test_no_tab_is_blank_before_its_first_run(browser, server, name, css, words):
    """Issue 41 item 9: before any run a tab says what to press. What it says is in the
    page before its header is clicked, so showing it waits for no server."""
    page, log = open_page(browser, server.url)
    page.get_by_text(words).first.wait_for(state="attached", timeout=30_000)
    assert not shown(page, css)                              # the Data tab is shown
    tab(page, name)
    assert shown(page, css), f"{name} does not show {words!r} at once"
    assert page.locator(f".{css}", has_text=words).count() == 1
    assert log.errors == []
    page.close()


@pytest.mark.parametrize("case", ["beam-1d", "shear-5"])
def test_the_tabs_are_drawn_before_they_are_clicked(browser, server, case):
    """Issue 41 item 9: after a run, each visit of a tab was blank 0.3-2.4 s while the
    server sent its plots again (or first drew the waves, the metrics, the diagnostics).
    Now every tab's plots are drawn in the page while the Data tab is shown, once the
    session is idle, and a visit only shows them."""
    page, log = open_page(browser, server.url)
    if case != "beam-1d":
        page.locator("select").first.select_option(case)
        wait_idle(page)
    page.locator(".run-discrepancy button").click()
    page.locator(".mdcore-busy").wait_for(state="attached", timeout=30_000)
    wait_idle(page)
    for css, canvas in [("hm-plot", True), ("disc-plot", True), ("metrics-table", False),
                        ("diagnostics-table", False), ("diag-loo", False)]:
        page.wait_for_function(BUILT, arg=[css, canvas], timeout=30_000)
    assert page.locator(".bk-tab.bk-active", has_text="Data").count() == 1
    for name, css in [("History matching", "hm-plot"), ("Discrepancy", "disc-plot"),
                      ("Metrics", "metrics-table"), ("Diagnostics", "diag-loo")]:
        assert not shown(page, css), name                      # the Data tab is shown
        tab(page, name)
        assert shown(page, css), f"{name} does not show its .{css} at once"
    assert log.errors == []
    page.close()


@pytest.mark.parametrize("name, css", [("Metrics", "metrics-table"),
                                       ("Diagnostics", "diag-loo")])
def test_a_tab_stale_after_a_display_change_keeps_its_content_while_rebuilt(
        browser, server, name, css):
    """Issue 41 item 9: after a scenario was hidden on the Discrepancy tab, a visit of
    Metrics or Diagnostics showed only "Updating …" / "Computing …" for 1.3-2.1 s while
    they were rebuilt. The old content now stays (dimmed) under that line."""
    from playwright.sync_api import expect
    page, log = open_page(browser, server.url)
    tab(page, "Discrepancy")
    page.locator(".run-discrepancy button").click()
    page.locator(".mdcore-busy").wait_for(state="attached", timeout=30_000)
    wait_idle(page)
    page.wait_for_function(BUILT, arg=[css, False], timeout=30_000)
    s2 = page.locator(".bk-btn-group").filter(has_text="koh").get_by_role(
        "button", name="2", exact=True)
    s2.click()                                                        # hide scenario 2
    expect(s2).not_to_have_class(re.compile(r"\bbk-active\b"), timeout=10_000)
    page.wait_for_timeout(1000)
    tab(page, name)
    seen = []
    end = time.monotonic() + 3.0
    while time.monotonic() < end:
        seen.append(shown(page, css))
        page.wait_for_timeout(40)
    assert all(seen), f"{name} showed no .{css} in {seen.count(False)} of {len(seen)} looks"
    page.locator(".mdcore-updating").first.wait_for(state="detached", timeout=30_000)
    assert log.errors == []
    page.close()


def test_waves_run_from_another_tab_are_drawn_while_the_job_runs(browser, server):
    """History matching was still being drawn 0.7-0.9 s after a run started from the Data
    tab had ended (its panels waited for the session to be idle). Now they are drawn
    while the job runs: here, beam-2d at paper sizes, a run of a minute, cancelled."""
    page, log = open_page(browser, server.url)
    page.locator("select").first.select_option("beam-2d")
    wait_idle(page)
    page.locator(".bk-Checkbox", has_text="Paper sizes").locator("input").check()
    page.locator(".run-discrepancy button").click()
    page.locator(".mdcore-busy").wait_for(state="attached", timeout=30_000)
    page.wait_for_function(BUILT, arg=["hm-plot", True], timeout=60_000)
    assert page.locator(".mdcore-busy").count() == 1, "the run ended first"
    assert page.locator(".bk-tab.bk-active", has_text="Data").count() == 1
    page.locator(".cancel-job button").click()
    wait_idle(page)
    assert log.errors == []
    page.close()


#: Scroll the nearest scrolling box around an element (across shadow roots) to its end;
#: returns how far it scrolled.
SCROLL_ANCESTOR = """(e) => {
  while (e) { if (e.scrollHeight > e.clientHeight + 10 &&
                  ['auto', 'scroll'].includes(getComputedStyle(e).overflowY)) {
      e.scrollTop = e.scrollHeight; return e.scrollTop; }
    e = e.parentElement || (e.getRootNode() && e.getRootNode().host); }
  return 0;
}"""


#: The scroll offset of the nearest scrolling box around an element (across shadow roots).
SCROLL_TOP = """(e) => {
  while (e) { if (['auto', 'scroll'].includes(getComputedStyle(e).overflowY))
      return e.scrollTop;
    e = e.parentElement || (e.getRootNode() && e.getRootNode().host); }
  return null;
}"""


def overlaps(a, b) -> bool:
    return not (a["x"] + a["width"] <= b["x"] or b["x"] + b["width"] <= a["x"]
                or a["y"] + a["height"] <= b["y"] or b["y"] + b["height"] <= a["y"])


def shown_status(page) -> str:
    return page.locator(".hm-status").evaluate("e => (e.shadowRoot || e).textContent")


def card_note(page) -> str:
    return page.locator(".card-note").evaluate("e => (e.shadowRoot || e).textContent")


def run_card(page, key: str, tab_name: str) -> None:
    """Press the card ``key``: its tab must be shown at once (the browser switches it),
    then wait for the server's answer (the card line's "look at") and the card's run."""
    tab(page, "Things to try")
    page.locator(f".try-{key} button").click()
    page.locator(".bk-tab.bk-active", has_text=tab_name).wait_for(timeout=10_000)
    wait_card_answer(page)
    wait_idle(page)


def wait_card_answer(page, timeout: float = 60.0) -> None:
    """Until the card line says where to look: the server has run the card's click."""
    end = time.monotonic() + timeout
    while "look at:" not in card_note(page):
        assert time.monotonic() < end, f"no answer to the card: {card_note(page)[-80:]!r}"
        page.wait_for_timeout(200)


def test_a_card_shows_its_tab_at_once_while_the_server_is_busy(browser, server):
    """Under load (tests alongside, hidden tabs catching up after a run) the server
    answered a card's click seconds later, and until then the page showed nothing: the
    tab switch looked lost. The browser now switches the tab and says the card is starting
    by itself; the server's answer follows. The server is stopped (SIGSTOP) to show it."""
    import os
    import signal
    page, log = open_page(browser, server.url)
    wait_idle(page)
    tab(page, "Things to try")
    os.kill(server.proc.pid, signal.SIGSTOP)
    try:
        page.locator(".try-ess button").click()
        page.locator(".bk-tab.bk-active", has_text="Metrics").wait_for(timeout=5_000)
        assert shown(page, "card-note")
        assert "starting" in card_note(page)
    finally:
        os.kill(server.proc.pid, signal.SIGCONT)
    wait_card_answer(page)
    assert "look at: Metrics tab" in card_note(page)
    # The same card again: the line says "starting", then the server's "look at" again.
    tab(page, "Things to try")
    os.kill(server.proc.pid, signal.SIGSTOP)
    try:
        page.locator(".try-ess button").click()
        page.locator(".bk-tab.bk-active", has_text="Metrics").wait_for(timeout=5_000)
        assert "starting" in card_note(page)
    finally:
        os.kill(server.proc.pid, signal.SIGCONT)
    wait_card_answer(page)
    wait_idle(page)
    assert page.locator(".bk-tab.bk-active").inner_text() == "Metrics"
    assert log.errors == []
    page.close()


def test_a_card_shows_its_plot_in_view_even_after_the_tab_was_scrolled(browser, server):
    """The History matching tab kept its scroll position: after a card, the class saw
    θ_MAP's plot, not the NROY samples the card points at. A card now shows its tab, and
    every tab is shown from its top."""
    page, log = open_page(browser, server.url)
    tab(page, "History matching")
    page.locator(".run-convergence button").click()
    page.wait_for_selector(".hm-status:has-text('converged')", timeout=60_000)
    wait_idle(page)
    nroy = page.locator(".hm-plot").first
    assert nroy.evaluate(SCROLL_ANCESTOR) > 0       # the tab scrolls on its own: to its end
    page.wait_for_timeout(500)
    assert not in_view(page, nroy)
    run_card(page, "rule-out", "History matching")
    page.wait_for_timeout(500)
    assert in_view(page, nroy), (nroy.bounding_box(), nroy.evaluate(SCROLL_TOP))
    assert log.errors == []
    page.close()


def test_the_ess_card_shows_its_diagnostics_and_advice_uncovered(browser, server):
    """Card 4 pointed at ESS φ and k̂, below the fold of the Metrics tab and under the
    low-ESS toast: the tab now opens on the tables, with the advice beside them."""
    page, log = open_page(browser, server.url)
    run_card(page, "ess", "Metrics")
    table = page.locator(".diagnostics-table")
    table.wait_for(timeout=30_000)
    advice = page.locator(".metrics-advice")
    advice.get_by_text("unreliable").first.wait_for(timeout=5_000)
    page.wait_for_timeout(1000)                     # a toast would be shown by now
    assert in_view(page, table) and in_view(page, advice)
    # Where to look, said on the card's own tab (the status line is on History matching).
    assert shown(page, "card-note")
    note = card_note(page)
    assert "look at: Metrics tab: ESS φ" in note, note
    for toast in page.locator(".notyf__toast").all():
        box = toast.bounding_box()
        assert box is None or not overlaps(box, table.bounding_box()), toast.inner_text()
    assert log.errors == []
    page.close()


@pytest.mark.parametrize("size", SIZES, ids=lambda s: f"{s[0]}x{s[1]}")
def test_the_plots_fill_the_height_of_the_screen(browser, server, size):
    """The plots were 300 px high whatever the screen: at 1920×1080 the lower half of the
    Data and Discrepancy tabs stayed white. They now share the tab's height (at least
    300 px each, the tab scrolls below that)."""
    page, log = open_page(browser, server.url, size)
    data = page.locator(".data-plot").first.bounding_box()
    page.locator(".run-discrepancy button").click()
    tab(page, "Discrepancy")
    wait_idle(page)
    page.wait_for_timeout(1000)
    boxes = [b for b in (p.bounding_box() for p in page.locator(".disc-plot").all()) if b]
    lowest = max(b["y"] + b["height"] for b in boxes)
    assert min(b["height"] for b in boxes) >= 299
    assert lowest >= size[1] - 20, (lowest, "white below the plots")      # filled
    if size[1] >= 1000:
        assert min(b["height"] for b in boxes) > 400 and data["height"] > 600
    assert log.errors == []
    page.close()


def test_a_card_pressed_after_another_case_draws_its_plots(browser, server):
    """After a beam-2d run, the KOH card switched the Discrepancy tab it shows to beam-1d
    inside the button's own event: Bokeh refused the change ("_pending_writes should be
    non-None"), the session stopped updating and the tab stayed blank. Then, the plots
    were drawn 1,200 px down, out of view."""
    page, log = open_page(browser, server.url)
    page.locator("select").first.select_option("beam-2d")
    wait_idle(page)
    page.locator(".run-discrepancy button").click()
    tab(page, "Discrepancy")
    wait_idle(page)
    before = server.log.text().count("Traceback")
    run_card(page, "koh", "Discrepancy")
    end = time.monotonic() + 60
    while page.locator("select").first.input_value() != "beam-1d":
        assert time.monotonic() < end, "the card did not switch to beam-1d"
        page.wait_for_timeout(250)
    wait_idle(page)
    while True:                     # z and δ of S1 and KOH, drawn
        boxes = [b for b in (p.bounding_box() for p in page.locator(".disc-plot").all())
                 if b and b["height"]]
        if len(boxes) >= 4:
            break
        assert time.monotonic() < end, "the card's plots were not drawn"
        page.wait_for_timeout(250)
    # in view: an empty box stretched by beam-2d's rows kept 1,200 px above them
    assert min(b["y"] for b in boxes) < 200, boxes
    assert server.log.text().count("Traceback") == before, server.log.text()[-3000:]
    assert log.errors == []
    page.close()


#: Plot titles (drawn on the canvas, so measured here with the title's own font) wider
#: than their plot's frame: Bokeh cuts them off at the toolbar.
WIDE_TITLES = """() => {
  const ctx = document.createElement('canvas').getContext('2d'), out = [];
  for (const d of Bokeh.documents) for (const m of d.all_models) {
    const t = m.title;
    if (!t || !t.text || !m.inner_width) continue;
    ctx.font = `${t.text_font_style} ${t.text_font_size} ${t.text_font}`;
    const w = ctx.measureText(t.text).width;
    if (w > m.inner_width + 5) out.push(`${t.text}: ${Math.round(w)} > ${m.inner_width}`);
  }
  return out;
}"""


@pytest.mark.parametrize("case", ["beam-1d", "beam-2d", "shear-5"])
def test_no_plot_title_is_cut_off_with_four_methods_at_1280(browser, server, case):
    """Issue 41's "no title is clipped": with KOH as a fourth column at 1280×720 the z
    row read "Scenario 1: z (bias-correctec" (shear-5: "Scenario 1: z, ω1 (bias-corre"),
    and the Diagnostics tab "Left-out runs: emulator against simu" on every case. Every
    tab is laid out, shown or not, so the titles of all are measured: History matching's
    "emulator variance vs V_o + V_m (converged …" and beam-2d's "Scenario 1: δ, crack
    length 0.02…" were cut too."""
    page, log = open_page(browser, server.url)
    if case != "beam-1d":
        page.locator("select").first.select_option(case)
        wait_idle(page)
    page.get_by_role("button", name="koh", exact=True).click()
    page.locator(".run-discrepancy button").click()
    tab(page, "Discrepancy")
    wait_idle(page)
    page.locator(".disc-plot canvas").nth(7).wait_for(timeout=60_000)   # z, δ of four
    page.wait_for_timeout(1500)
    assert page.evaluate(WIDE_TITLES) == []
    tab(page, "Diagnostics")      # "Left-out runs: emulator against simu", and others
    page.locator(".diag-plot canvas").nth(5).wait_for(timeout=60_000)
    page.wait_for_timeout(1500)
    assert page.evaluate(WIDE_TITLES) == []
    assert log.errors == []
    page.close()


def test_a_button_pressed_while_a_change_is_on_its_way_keeps_the_page_updating(
        browser, server):
    """Panel waits a moment before it processes a field's change; a button pressed
    meanwhile made it process the change outside Bokeh's document lock, where the views
    that redraw raw Bokeh models raised "_pending_writes should be non-None" and the page
    stopped following the state (a case chosen and "Next wave" pressed at once)."""
    page, log = open_page(browser, server.url)
    tab(page, "History matching")
    wait_idle(page)
    before = server.log.text().count("Traceback")
    for case in ("beam-2d", "shear-5", "beam-1d"):
        page.locator("select").first.select_option(case)
        page.locator(".next-wave button").click()
        wait_idle(page)
        end = time.monotonic() + 30
        while "wave 1:" not in shown_status(page):
            assert time.monotonic() < end, (case, shown_status(page),
                                            server.log.text()[-3000:])
            page.wait_for_timeout(250)
    assert server.log.text().count("Traceback") == before, server.log.text()[-3000:]
    assert log.errors == []
    page.close()
