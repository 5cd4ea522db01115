"""Shared helpers of the browser tests: Debian's Chromium through Playwright.

A test calls :func:`require_browser` first: it skips when Chromium or Playwright is
missing, unless ``MDCORE_REQUIRE_BROWSER=1`` (set by ``.ci/run``) turns the skip into a
failure.
"""

import os
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from urllib.parse import urlparse

import pytest

ROOT = Path(__file__).resolve().parent.parent
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


class ServerLog:
    """Reads ``panel serve``'s output on a thread (so the pipe never fills) and signals
    when the app is being served."""

    READY = "Bokeh app running at"

    def __init__(self, proc):
        self.lines: list[str] = []
        self.ready = threading.Event()
        self.closed = threading.Event()
        threading.Thread(target=self._read, args=(proc.stdout,), daemon=True).start()

    def _read(self, stream):
        for line in stream:
            self.lines.append(line)
            if self.READY in line:
                self.ready.set()
        self.closed.set()

    def text(self) -> str:
        return "".join(self.lines)


def serve_app(script: str = "main.py", args: tuple[str, ...] = (),
              options: tuple[str, ...] | None = None):
    """Start ``panel serve app/<script> [--args ARGS]`` on a free port; return (process,
    url, log). ``options``: panel serve's options instead of ``--address 127.0.0.1
    --allow-websocket-origin 127.0.0.1:PORT`` ("{port}" in them is the port)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    if options is None:
        options = ("--address", "127.0.0.1", "--allow-websocket-origin", "127.0.0.1:{port}")
    proc = subprocess.Popen(
        [sys.executable, "-m", "panel", "serve", str(ROOT / "app" / script), "--port",
         str(port), *(o.format(port=port) for o in options),
         *(["--args", *args] if args else [])],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=ROOT)
    log = ServerLog(proc)
    end = time.monotonic() + 60
    while not log.ready.wait(timeout=1.0):            # a condition, polled once a second
        if log.closed.is_set() or time.monotonic() > end:
            proc.kill()
            pytest.fail("panel serve did not start:\n" + log.text())
    return proc, f"http://127.0.0.1:{port}/{Path(script).stem}", log


class PageLog:
    """Console errors and every network host of one page (data: and blob: URLs are local)."""

    def __init__(self, page):
        self.errors, self.hosts = [], set()
        page.on("console", lambda m: m.type == "error" and self.errors.append(m.text))
        page.on("pageerror", lambda e: self.errors.append(str(e)))
        page.on("request", self._request)
        page.on("requestfailed", self._failed)
        page.on("websocket", lambda ws: self.hosts.add(urlparse(ws.url).hostname))

    def _failed(self, request):
        """A failed request, with its address (the console line has none). Aborted ones
        are not errors: a style sheet of a widget replaced while it loads is aborted."""
        if request.failure != "net::ERR_ABORTED":
            self.errors.append(f"request failed ({request.failure}): {request.url[:300]}")

    def _request(self, request):
        url = urlparse(request.url)
        if url.scheme not in ("data", "blob", "about"):
            self.hosts.add(url.hostname)


def files_only(page) -> list[str]:
    """Refuse every request of ``page`` but file:, data: and blob: (a file opened from
    disk, offline); returns the list the refused addresses are added to."""
    outside: list[str] = []

    def route(r):
        if r.request.url.startswith(("file:", "data:", "blob:")):
            r.continue_()
        else:
            outside.append(r.request.url)
            r.abort()

    page.route("**/*", route)
    return outside


#: Is the first element of class ``cls`` (searched through shadow roots) with a size the
#: one the page shows at its centre? Hit-testing through the shadow roots skips elements
#: hidden by ``visibility`` (an inactive tab: Playwright's ``is_visible`` calls its
#: content visible) and those covered by others.
SHOWN = """(cls) => {
  const all = (root, out) => { for (const e of root.querySelectorAll('*')) { out.push(e);
      if (e.shadowRoot) all(e.shadowRoot, out); } return out; };
  const host = all(document, []).find(e => e.classList.contains(cls) &&
      e.getBoundingClientRect().width > 0 && e.getBoundingClientRect().height > 0);
  if (!host) return false;
  const r = host.getBoundingClientRect();
  const x = r.x + Math.min(r.width / 2, 40), y = r.y + Math.min(r.height / 2, 20);
  let hit = document.elementFromPoint(x, y);
  while (hit && hit.shadowRoot) {
    const inner = hit.shadowRoot.elementFromPoint(x, y);
    if (!inner || inner === hit) break;
    hit = inner;
  }
  for (let e = hit; e; e = e.parentElement || (e.getRootNode() && e.getRootNode().host))
    if (e === host) return true;
  return false;
}"""


def shown(page, css_class: str) -> bool:
    """Whether the page shows the element of ``css_class`` now (see :data:`SHOWN`)."""
    return page.evaluate(SHOWN, css_class)


#: Counts, in ``window.mdcoreJobs``, the busy lines the server sends (BokehJS's public
#: ``Document.on_change``): a short job (a seed's rerun) can start and end between
#: two polls of ``wait_for_selector(".mdcore-busy")`` on a loaded machine.
COUNT_JOBS = """() => { window.mdcoreJobs = 0;
  for (const d of Bokeh.documents) d.on_change(e => {
    if (e.attr !== undefined && String(e.value).includes('mdcore-busy')) window.mdcoreJobs++;
  }); }"""


def count_jobs(page) -> None:
    """From now on, count the jobs started in ``page`` (see :func:`wait_job_started`)."""
    page.evaluate(COUNT_JOBS)


def wait_job_started(page, timeout: float = 30_000) -> None:
    """Until a job has started since :func:`count_jobs` (it may have ended already)."""
    page.wait_for_function("() => window.mdcoreJobs > 0", timeout=timeout)
