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
