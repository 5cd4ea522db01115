"""How long each tab waits after its header is clicked, in Chromium at 1280×720.

Usage: python bench/bench_tabs.py [--url URL] [--cases beam-1d beam-2d shear-5]
                                  [--rounds 2] [--hm-first] [--after 2]

Serves ``app/main.py`` with ``panel serve`` (or uses ``--url``). Per case, on a new page:
"Run discrepancy" from the Data tab (it runs the history match too; with ``--hm-first``,
"Run to convergence" on the History matching tab first), then, ``--after`` seconds after
the run ended, a visit of History matching, Discrepancy, Metrics, Diagnostics and Data,
``--rounds`` times round. Issue 41's target: no tab waits more than 0.5 s.

For each visit a ``requestAnimationFrame`` loop records, per frame, the painted canvases
and the tables in view right of the sidebar, and whether a waiting line ("Updating …",
"Computing …", "Drawing N waves …") is in view. *ready* is the first frame after the
click with a canvas (a table on Metrics) and no waiting line; *settled* the last frame in
which any of the three changed (within 4.5 s). Wall time on a shared machine: the load
average is printed.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT / "bench"))
from bench_browser import serve  # noqa: E402
from browser import launch, tab  # noqa: E402

TARGET = 0.5
TABS = ("History matching", "Discrepancy", "Metrics", "Diagnostics", "Data")
#: Starts the frame recorder of one visit (window.__series, window.__click).
RECORD = """() => {
  const series = []; window.__series = series; window.__click = null;
  document.addEventListener('pointerdown', () => { window.__click = performance.now(); },
                            {capture: true, once: true});
  const all = (root, out) => { for (const e of root.querySelectorAll('*')) { out.push(e);
      if (e.shadowRoot) all(e.shadowRoot, out); } return out; };
  const seen = e => { const r = e.getBoundingClientRect();
      return r.width > 2 && r.height > 2 && r.left >= 320 && r.top < innerHeight &&
             e.checkVisibility({opacityProperty: true, visibilityProperty: true}); };
  const end = performance.now() + 4500;
  const frame = () => {
    const els = all(document, []);
    const canvases = els.filter(e => e.tagName === 'CANVAS' && e.width > 0 && seen(e)).length;
    const tables = els.filter(e => e.tagName === 'TABLE' && seen(e)).length;
    const waiting = els.some(e => e.children.length === 0 && seen(e) &&
        /Updating …|Computing|Drawing \\d+ wave/.test(e.textContent || ''));
    series.push([performance.now(), canvases, tables, waiting]);
    if (performance.now() < end) requestAnimationFrame(frame);
  };
  requestAnimationFrame(frame);
}"""


def visit(page, name: str) -> tuple[float | None, float]:
    """Click the tab ``name``; (seconds to ready or None, seconds to settled)."""
    page.evaluate(RECORD)
    page.locator(".bk-tab", has_text=name).click()
    page.wait_for_timeout(4700)
    click = page.evaluate("window.__click")
    frames = [f for f in page.evaluate("window.__series") if f[0] >= click]
    table = name == "Metrics"
    ready = next((t for t, canvases, tables, waiting in frames
                  if (tables if table else canvases) > 0 and not waiting), None)
    last, before = click, None
    for t, *state in frames:
        if state != before:
            last, before = t, state
    return (None if ready is None else (ready - click) / 1000), (last - click) / 1000


def wait_idle(page) -> None:
    try:                                   # a run that ends within the wait is not missed
        page.wait_for_selector(".mdcore-busy", state="attached", timeout=5_000)
    except Exception:                      # noqa: BLE001 - playwright's TimeoutError
        pass
    page.wait_for_selector(".mdcore-idle", state="attached", timeout=180_000)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--url", help="an app already served (default: serve one)")
    ap.add_argument("--cases", nargs="+", default=["beam-1d", "beam-2d", "shear-5"])
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--hm-first", action="store_true",
                    help="converge on the History matching tab before Run discrepancy")
    ap.add_argument("--after", type=float, default=2.0,
                    help="seconds between the run's end and the first visit (default 2; "
                         "0: at once, before the hidden tabs have caught up)")
    a = ap.parse_args()
    from playwright.sync_api import sync_playwright

    proc, url = (None, a.url) if a.url else serve()
    print(f"load average before: {os.getloadavg()[0]:.2f}")
    worst = 0.0
    try:
        with sync_playwright() as pw:
            browser = launch(pw)
            for case in a.cases:
                page = browser.new_page(viewport={"width": 1280, "height": 720})
                page.goto(url)
                page.wait_for_selector(".data-plot canvas", timeout=60_000)
                if case != "beam-1d":
                    page.locator("select").first.select_option(case)
                    wait_idle(page)
                if a.hm_first:
                    tab(page, "History matching")
                    page.locator(".run-convergence button").click()
                    wait_idle(page)
                    tab(page, "Data")
                page.locator(".run-discrepancy button").click()
                wait_idle(page)
                page.wait_for_timeout(1000 * a.after)    # hidden tabs catch up when idle
                for k in range(a.rounds):
                    for name in TABS:
                        ready, settled = visit(page, name)
                        worst = max(worst, float("inf") if ready is None else ready)
                        shown = "never" if ready is None else f"{ready:.2f} s"
                        print(f"{case:8s} round {k + 1}  {name:17s} ready {shown:>7s}  "
                              f"settled {settled:.2f} s", flush=True)
                page.close()
    finally:
        if proc is not None:
            proc.kill()
    print(f"load average after: {os.getloadavg()[0]:.2f}")
    print(f"slowest visit {worst:.2f} s against the target {TARGET} s: "
          f"{'met' if worst <= TARGET else 'MISSED'}")


if __name__ == "__main__":
    main()
