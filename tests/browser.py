"""Shared helpers of the browser tests: Debian's Chromium through Playwright.

A test calls :func:`require_browser` first: it skips when Chromium or Playwright is
missing, unless ``MDCORE_REQUIRE_BROWSER=1`` (set by ``.ci/run``) turns the skip into a
failure.
"""

import os

import pytest

CHROMIUM = "/usr/bin/chromium"
FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
         "--disable-component-update", "--disable-sync", "--no-first-run"]


def require_browser() -> None:
    reason = None
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        reason = "playwright is not installed"
    if reason is None and not os.path.exists(CHROMIUM):
        reason = f"Chromium is not at {CHROMIUM} (apt-get install -y chromium)"
    if reason is not None:
        if os.environ.get("MDCORE_REQUIRE_BROWSER") == "1":
            pytest.fail(f"browser test required (MDCORE_REQUIRE_BROWSER=1) but {reason}")
        pytest.skip(reason)


def launch(playwright):
    """Debian's Chromium, headless, with the project's flags."""
    return playwright.chromium.launch(executable_path=CHROMIUM, args=FLAGS)


def chromium():
    """Yield a launched Chromium, closed afterwards: the body of a ``browser`` fixture
    (``yield from chromium()``)."""
    from playwright.sync_api import sync_playwright
    with sync_playwright() as p:
        browser = launch(p)
        yield browser
        browser.close()


def tab(page, name: str, timeout: float = 30.0) -> None:
    """Show the tab ``name`` and wait until the page says it is the active one.

    A click that lands while Bokeh re-lays-out the page can be lost; the tab header is
    clicked again (at most once a second) until the tab is active.
    """
    import time

    header = page.locator(".bk-tab", has_text=name)
    end = time.monotonic() + timeout
    while True:
        header.click()
        try:
            page.locator(".bk-tab.bk-active", has_text=name).wait_for(timeout=1_000)
            return
        except Exception:                   # noqa: BLE001 - playwright's TimeoutError
            if time.monotonic() > end:
                raise AssertionError(f"the tab {name!r} did not become active") from None
