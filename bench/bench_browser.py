"""App timings in Chromium: click → pixels settled, against the targets of issue 17.

Usage: python bench/bench_browser.py [--cases beam-1d beam-2d shear-5] [--sessions 5]
                                     [--quiet 1.5] [--url URL]

Serves ``app/main.py`` with ``panel serve`` on a free port (or uses ``--url``), drives
Debian's Chromium (tests/browser.py) at 1280×720 with Playwright and prints, per case:

* first paint (beam-1d, the default case): navigation start → the Data tab drawn;
* case switch: choosing the case in the selector → its Data tab drawn (beam-1d: switched
  to from beam-2d);
* history-match wave: "Next wave" → the History matching tab drawn; then the next wave
  (on a case that has converged, shear-5, the calm note that says so), and one step back
  of the wave player (display only);
* discrepancy at the defaults: "Run discrepancy" → the Discrepancy tab drawn;
* display-only changes: the band ±3σ → ±2σ, hiding scenario 2 and showing it again;
* seed change: typing a new seed (a recompute of the shown scenarios);
* tab switch (no target in issue 17): Discrepancy → History matching, for the count of
  what it rebuilds;

and the first paint of five sessions opened at once (slowest and median).

How "settled" is measured: a script injected into every page records, with
``performance.now()``, the last canvas drawing call (2-D and WebGL) on a canvas in view,
the last DOM change of an element in view (in the document and in every shadow root), and
the last WebSocket message from the server; and the time of the triggering input event
(pointer down, key down, input). After an action the bench waits until the server has
answered, the busy line says "Idle.", nothing has been drawn, changed or received for
``--quiet`` seconds *and* the server process used less than a quarter of a core for as
long (a server still computing sends nothing), then checks that two screenshots 0.25 s
apart are equal. The figure is *last change in view − trigger*, so neither the quiet wait
nor the tabs out of view, which catch up once the session is idle, count (their cost is in
the CPU columns). It is wall time on a shared machine: the load average is printed before
and after.

The same instrumentation counts what each action rebuilt: canvases created, and Bokeh
models sent as new objects (``Figure`` = a plot rebuilt rather than updated in place);
and /proc gives the CPU seconds the action cost in the server and in the browser.
"""

from __future__ import annotations

import argparse
import os
import socket
import statistics
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))
from browser import launch, tab  # noqa: E402

VIEWPORT = {"width": 1280, "height": 720}
CASES = ("beam-1d", "beam-2d", "shear-5")

#: Issue 17's targets (seconds): display-only, recompute (beam-1d, others), case switch,
#: first paint, first paint with five sessions.
DISPLAY, RECOMPUTE_1D, RECOMPUTE, SWITCH, FIRST_PAINT, FIRST_PAINT_5 = 0.3, 1.0, 2.0, 1.5, 2.0, 3.0

INSTRUMENT = r"""
(() => {
  const md = window.__md = {lastDraw: 0, lastMut: 0, lastMsg: 0, msgs: 0, bytes: 0,
                            models: 0, figures: 0, canvases: 0, trigger: 0};
  const now = () => performance.now();
  // Only what can be seen counts: a tab not shown (display: none) is drawn and changed
  // while the session is idle, which no one waits for. Asked once per element per frame.
  let frame = 0;
  const tick = () => { frame++; requestAnimationFrame(tick); };
  tick();
  const seen = new WeakMap();
  const visible = el => {
    if (!el) return false;
    const c = seen.get(el);
    if (c && c[0] === frame) return c[1];
    const v = el.isConnected && el.checkVisibility();
    seen.set(el, [frame, v]);
    return v;
  };
  const wrap = (proto, names) => {
    if (!proto) return;
    for (const n of names) {
      const f = proto[n];
      if (typeof f !== 'function') continue;
      proto[n] = function (...a) {
        if (visible(this.canvas)) md.lastDraw = now();
        return f.apply(this, a);
      };
    }
  };
  wrap(window.CanvasRenderingContext2D && CanvasRenderingContext2D.prototype,
       ['fill', 'stroke', 'fillRect', 'clearRect', 'strokeRect', 'fillText', 'strokeText',
        'drawImage', 'putImageData']);
  for (const gl of [window.WebGLRenderingContext, window.WebGL2RenderingContext])
    wrap(gl && gl.prototype, ['drawArrays', 'drawElements', 'clear', 'drawArraysInstanced',
                              'drawElementsInstanced']);
  const opts = {subtree: true, childList: true, attributes: true, characterData: true};
  const mo = new MutationObserver(records => {
    if (records.some(r => visible(r.target.nodeType === 1 ? r.target : r.target.parentElement)))
      md.lastMut = now();
  });
  mo.observe(document, opts);
  const attach = Element.prototype.attachShadow;
  Element.prototype.attachShadow = function (init) {
    const root = attach.call(this, init);
    mo.observe(root, opts);
    return root;
  };
  const create = Document.prototype.createElement;
  Document.prototype.createElement = function (tag, ...rest) {
    if (String(tag).toLowerCase() === 'canvas') md.canvases++;
    return create.call(this, tag, ...rest);
  };
  const WS = window.WebSocket;
  window.WebSocket = class extends WS {
    constructor(...a) {
      super(...a);
      this.addEventListener('message', e => {
        md.lastMsg = now(); md.msgs++;
        const d = e.data;
        if (typeof d === 'string') {
          md.bytes += d.length;
          md.models += (d.match(/"type":"object","name":"[^"]+","id"/g) || []).length;
          md.figures += (d.match(/"type":"object","name":"(Figure|Plot|GridPlot)"/g)
                         || []).length;
        } else {
          md.bytes += d.byteLength || d.size || 0;
        }
      });
    }
  };
  for (const ev of ['pointerdown', 'keydown', 'input'])
    window.addEventListener(ev, () => { md.trigger = now(); }, true);
})();
"""

#: True when no job runs (the busy line of the progress panel says "Idle.").
IDLE = """() => {
  const find = root => {
    for (const e of root.querySelectorAll('*')) {
      if (e.classList.contains('mdcore-busy')) return true;
      if (e.shadowRoot && find(e.shadowRoot)) return true;
    }
    return false;
  };
  return !find(document);
}"""


@dataclass
class Timing:
    seconds: float
    canvases: int = 0
    models: int = 0
    figures: int = 0
    kbytes: float = 0.0
    server_cpu: float = float("nan")
    browser_cpu: float = float("nan")


@dataclass
class Row:
    case: str
    figures: dict[str, Timing | None] = field(default_factory=dict)


# --------------------------------------------------------------------------------------
# Serving and settling


def serve():
    """Start ``panel serve app/main.py`` on a free port; return (process, url)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    proc = subprocess.Popen(
        [sys.executable, "-m", "panel", "serve", str(ROOT / "app" / "main.py"), "--address",
         "127.0.0.1", "--port", str(port), "--allow-websocket-origin", f"127.0.0.1:{port}"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=ROOT)
    ready = threading.Event()

    def read():
        for line in proc.stdout:
            if "Bokeh app running at" in line:
                ready.set()

    threading.Thread(target=read, daemon=True).start()
    if not ready.wait(timeout=90):
        proc.kill()
        raise SystemExit("panel serve did not start")
    return proc, f"http://127.0.0.1:{port}/main"


#: JS predicate (with its argument ``[css_class, canvas]``): an element of ``css_class``
#: exists (searched through shadow roots), and with ``canvas``, one with a drawn (non-zero)
#: canvas inside it.
HAS = """([cls, canvas]) => {
  const all = (root, out) => {
    for (const e of root.querySelectorAll('*')) {
      out.push(e);
      if (e.shadowRoot) all(e.shadowRoot, out);
    }
    return out;
  };
  const hosts = all(document, []).filter(e => e.classList.contains(cls));
  if (!canvas) return hosts.length > 0;
  return hosts.some(h => all(h.shadowRoot || h, [h]).some(
    e => e.tagName === 'CANVAS' && e.width > 0 && e.height > 0));
}"""


def has(css_class: str, canvas: bool = False) -> tuple[str, list]:
    """A predicate for :func:`settle`: see :data:`HAS`."""
    return HAS, [css_class, canvas]


ALWAYS = ("() => true", None)


_CLK = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100


def _processes() -> dict[int, tuple[int, float]]:
    """pid -> (parent pid, CPU seconds) of every process, from /proc (Linux)."""
    out = {}
    for name in os.listdir("/proc"):
        if not name.isdigit():
            continue
        try:
            with open(f"/proc/{name}/stat") as f:
                stat = f.read()
        except OSError:
            continue
        fields = stat[stat.rindex(")") + 2:].split()      # from field 3 (state) on
        out[int(name)] = (int(fields[1]), (int(fields[11]) + int(fields[12])) / _CLK)
    return out


class Meter:
    """CPU seconds of the server process and of this script's other descendants (the
    Playwright driver and Chromium), read from /proc; zeros where /proc is missing."""

    def __init__(self, server_pid: int | None):
        self.server_pid = server_pid
        self.available = os.path.isdir("/proc")

    def read(self) -> tuple[float, float]:
        if not self.available:
            return 0.0, 0.0
        procs = _processes()
        children: dict[int, list[int]] = {}
        for pid, (ppid, _) in procs.items():
            children.setdefault(ppid, []).append(pid)
        server = procs.get(self.server_pid, (0, 0.0))[1] if self.server_pid else 0.0
        browser, todo = 0.0, list(children.get(os.getpid(), []))
        while todo:
            pid = todo.pop()
            if pid == self.server_pid:
                continue
            browser += procs[pid][1]
            todo += children.get(pid, [])
        return server, browser


METER = Meter(None)


def snapshot(page) -> dict:
    s = page.evaluate("() => Object.assign({now: performance.now()}, window.__md)")
    s["server_cpu"], s["browser_cpu"] = METER.read()
    return s


def settle(page, before: dict | None, *, ready: tuple[str, object] = ALWAYS,
           quiet: float = 1.5, timeout: float = 240.0) -> Timing:
    """Wait until the page has settled after an action; return trigger → last activity.

    ``before`` is :func:`snapshot` taken just before the action (None for a first load,
    timed from the navigation start). Settled: the server has sent something since, the
    busy line is idle, ``ready`` (a JS predicate and its argument) holds, for ``quiet``
    seconds nothing was drawn, changed or received *and* the server process used less
    than a quarter of a core (a server still computing sends nothing), and two
    screenshots 0.25 s apart are equal.
    """
    end = time.monotonic() + timeout
    msgs0 = 0 if before is None else before["msgs"]
    server_busy = time.monotonic()
    prev_cpu, prev_t = METER.read()[0], time.monotonic()
    while True:
        if time.monotonic() > end:
            raise TimeoutError("the page did not settle")
        s = snapshot(page)
        now = time.monotonic()
        if s["server_cpu"] - prev_cpu > 0.25 * (now - prev_t):
            server_busy = now
        prev_cpu, prev_t = s["server_cpu"], now
        last = max(s["lastDraw"], s["lastMut"])                  # the last change seen
        quiet_since = max(last, s["lastMsg"])
        if (s["msgs"] > msgs0 and (s["now"] - quiet_since) >= quiet * 1000
                and now - server_busy >= quiet
                and page.evaluate(IDLE) and page.evaluate(*ready)):
            a = page.screenshot()
            page.wait_for_timeout(250)
            if a == page.screenshot() and snapshot(page)["lastDraw"] == s["lastDraw"]:
                break
        page.wait_for_timeout(100)
    if before is None:
        t0 = 0.0
    else:
        t0 = s["trigger"] if s["trigger"] > before["now"] else before["now"]
    b = before or {"canvases": 0, "models": 0, "figures": 0, "bytes": 0,
                   "server_cpu": float("nan"), "browser_cpu": float("nan")}
    return Timing((last - t0) / 1000, s["canvases"] - b["canvases"], s["models"] - b["models"],
                  s["figures"] - b["figures"], (s["bytes"] - b["bytes"]) / 1024,
                  s["server_cpu"] - b["server_cpu"], s["browser_cpu"] - b["browser_cpu"])


def button_group(page, labels: list[str]):
    """The button group whose buttons read exactly ``labels``."""
    groups = page.locator(".bk-btn-group")
    for k in range(groups.count()):
        g = groups.nth(k)
        if [t.strip() for t in g.locator("button").all_inner_texts()] == labels:
            return g
    raise LookupError(f"no button group {labels}")


def wait_toasts_gone(page, timeout: float = 15.0) -> None:
    """Notifications fade after 10 s; wait, so their removal is not timed as a change."""
    end = time.monotonic() + timeout
    while time.monotonic() < end and page.evaluate(*has("notyf__toast")):
        page.wait_for_timeout(200)


def calm(page, quiet: float) -> None:
    """Wait until the page is quiet (after a tab switch, which the server need not answer)."""
    settle(page, snapshot(page) | {"msgs": -1}, quiet=quiet)


def act(page, action, *, ready=ALWAYS, quiet=1.5, answer: bool = True) -> Timing:
    """Time ``action`` (trigger → settled); ``answer=False`` when the server need not
    send anything back."""
    wait_toasts_gone(page)
    before = snapshot(page)
    action()
    return settle(page, before if answer else before | {"msgs": -1}, ready=ready, quiet=quiet)


# --------------------------------------------------------------------------------------
# The journeys


def new_page(browser):
    context = browser.new_context(viewport=VIEWPORT)
    context.add_init_script(INSTRUMENT)
    return context, context.new_page()


def first_paint(browser, url, quiet) -> Timing:
    context, page = new_page(browser)
    server0, browser0 = METER.read()
    page.goto(url, wait_until="commit")
    t = settle(page, None, ready=has("data-plot", canvas=True), quiet=quiet)
    server1, browser1 = METER.read()
    t.server_cpu, t.browser_cpu = server1 - server0, browser1 - browser0
    context.close()
    return t


def five_sessions(browser, url, n, quiet) -> list[float]:
    pages = [new_page(browser) for _ in range(n)]
    for _, page in pages:
        page.goto(url, wait_until="commit")
    times = [settle(page, None, ready=has("data-plot", canvas=True), quiet=quiet).seconds
             for _, page in pages]
    for context, _ in pages:
        context.close()
    return times


def journey(browser, url, case, quiet) -> Row:
    row = Row(case)
    context, page = new_page(browser)
    page.goto(url, wait_until="commit")
    settle(page, None, ready=has("data-plot", canvas=True), quiet=quiet)
    select = page.locator("select").first
    if case == "beam-1d":          # a switch *to* beam-1d: from beam-2d
        act(page, lambda: select.select_option("beam-2d"), quiet=quiet)
    row.figures["case switch"] = act(page, lambda: select.select_option(case),
                                     ready=has("data-plot", canvas=True), quiet=quiet)

    tab(page, "History matching")
    calm(page, quiet)
    row.figures["wave"] = act(page, lambda: page.get_by_role("button", name="Next wave").click(),
                              ready=has("hm-status"), quiet=quiet)
    # The next wave redraws the plots the first one built (shear-5 has converged: a note).
    row.figures["wave 2"] = act(page,
                                lambda: page.get_by_role("button", name="Next wave").click(),
                                ready=has("hm-status"), quiet=quiet)
    back = page.locator("button.previous")              # the wave player, once 2 waves
    if back.count() and back.first.is_visible():
        row.figures["player"] = act(page, lambda: back.first.click(), quiet=quiet)

    tab(page, "Discrepancy")
    calm(page, quiet)
    row.figures["discrepancy"] = act(
        page, lambda: page.get_by_role("button", name="Run discrepancy").click(),
        ready=has("disc-plot", canvas=True), quiet=quiet)

    band = button_group(page, ["2", "3"])
    row.figures["band ±2σ"] = act(page, lambda: band.get_by_role("button", name="2").click(),
                                  quiet=quiet)
    act(page, lambda: band.get_by_role("button", name="3").click(), quiet=quiet)
    scen = button_group(page, ["1", "2", "3", "koh"])
    row.figures["hide S2"] = act(page, lambda: scen.get_by_role("button", name="2").click(),
                                 quiet=quiet)
    row.figures["show S2"] = act(page, lambda: scen.get_by_role("button", name="2").click(),
                                 quiet=quiet)

    seed = page.get_by_label("Seed", exact=True)

    def new_seed():
        seed.fill("1")
        seed.press("Enter")

    row.figures["seed"] = act(page, new_seed, ready=has("disc-plot", canvas=True), quiet=quiet)
    row.figures["tab"] = act(page, lambda: tab(page, "History matching"),
                             ready=has("hm-status"), quiet=quiet, answer=False)
    context.close()
    return row


# --------------------------------------------------------------------------------------
# Report

COLUMNS = [("first paint", "first paint", FIRST_PAINT), ("case switch", "case switch", SWITCH),
           ("wave", "HM wave", None), ("wave 2", "next wave", None),
           ("player", "wave player", DISPLAY), ("discrepancy", "discrepancy", None),
           ("band ±2σ", "band ±2σ", DISPLAY), ("hide S2", "hide S2", DISPLAY),
           ("show S2", "show S2", DISPLAY), ("seed", "seed change", None),
           ("tab", "tab → HM", 0.0)]


def target(key, case, goal):
    """The target of ``key`` on ``case`` in seconds (0: none)."""
    if goal is not None:
        return goal
    return RECOMPUTE_1D if case == "beam-1d" else RECOMPUTE


def load() -> str:
    try:
        return subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    except OSError:
        one, five, fifteen = os.getloadavg()
        return f"load average: {one:.2f}, {five:.2f}, {fifteen:.2f}"


def report(rows: list[Row], sessions: list[float], n: int) -> None:
    print(f"\n{'interaction':<14}" + "".join(f"{r.case:>20}" for r in rows) + f"{'target':>10}")
    for key, name, goal in COLUMNS:
        cells = []
        for r in rows:
            t = r.figures.get(key)
            if t is None:
                cells.append(f"{'—':>20}")
                continue
            goal_s = target(key, r.case, goal)
            ok = "" if not goal_s else "ok" if t.seconds <= goal_s else "OVER"
            cells.append(f"{t.seconds:>13.2f} s {ok:>4}")
        goals = {target(key, r.case, goal) for r in rows}
        goal_text = "/".join(f"{g:g}" for g in sorted(goals))
        goal_text = "—" if goals == {0.0} else f"≤ {goal_text} s"
        print(f"{name:<14}" + "".join(cells) + f"{goal_text:>10}")
    if sessions:
        worst, mid = max(sessions), statistics.median(sessions)
        print(f"first paint, {n} sessions at once: slowest {worst:.2f} s, median {mid:.2f} s "
              f"(target ≤ {FIRST_PAINT_5:g} s) {'ok' if worst <= FIRST_PAINT_5 else 'OVER'}")
    print("\nWhat each action rebuilt: canvases created / new Bokeh models / of them plots "
          "(Figure) / kB from the server;\nand CPU seconds it cost: server (panel serve) + "
          "browser (Chromium and the Playwright driver):")
    print(f"{'interaction':<14}" + "".join(f"{r.case:>30}" for r in rows))
    for key, name, _ in COLUMNS:
        cells = []
        for r in rows:
            t = r.figures.get(key)
            text = "—" if t is None else (f"{t.canvases}/{t.models}/{t.figures}/{t.kbytes:.0f}"
                                          f"  {t.server_cpu:.1f}+{t.browser_cpu:.1f} s")
            cells.append(f"{text:>30}")
        print(f"{name:<14}" + "".join(cells))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="+", default=list(CASES), choices=CASES)
    ap.add_argument("--sessions", type=int, default=5, help="sessions opened at once (0: skip)")
    ap.add_argument("--quiet", type=float, default=1.5,
                    help="seconds without drawing, DOM change or message that count as settled")
    ap.add_argument("--url", help="an app already served (default: serve app/main.py)")
    args = ap.parse_args()
    from playwright.sync_api import sync_playwright

    print(f"start: {load()}")
    proc, url = (None, args.url) if args.url else serve()
    METER.server_pid = None if proc is None else proc.pid
    try:
        with sync_playwright() as p:
            browser = launch(p)
            first_paint(browser, url, args.quiet)      # warm-up: imports, kernels, caches
            paint = first_paint(browser, url, args.quiet)
            rows = []
            for case in args.cases:
                rows.append(journey(browser, url, case, args.quiet))
                print(f"{case}: done ({load()})", flush=True)
            if rows and rows[0].case == "beam-1d":
                rows[0].figures["first paint"] = paint
            sessions = five_sessions(browser, url, args.sessions, args.quiet) \
                if args.sessions else []
            browser.close()
    finally:
        if proc is not None:
            proc.terminate()
            proc.wait(timeout=10)
    if not rows or rows[0].case != "beam-1d":
        print(f"first paint (beam-1d): {paint.seconds:.2f} s (target ≤ {FIRST_PAINT:g} s)")
    report(rows, sessions, args.sessions)
    print(f"\nend: {load()}")


if __name__ == "__main__":
    main()
