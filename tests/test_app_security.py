"""What a shared file, an upload or a stranger's browser can do to the served app: nothing.

Browser tests in Debian's headless Chromium against ``panel serve`` on a free port. Files
go in through the Files tab's drop areas as a user's do: the area's file input
(``set_input_files``) or a real drop of a ``DataTransfer`` on the area, sent by the page in
chunks over the websocket (app/upload.py).

Skipped when Chromium or Playwright is missing, unless ``MDCORE_REQUIRE_BROWSER=1``
(set by ``.ci/run``), which turns the skip into a failure.
"""

from __future__ import annotations

import base64
import json
import time
from pathlib import Path

import pytest
from browser import CHROMIUM, FLAGS, PageLog, serve_app, tab


def expect(locator):
    """Playwright's ``expect``, imported when a browser test runs (the other tests here
    need no Playwright)."""
    from playwright.sync_api import expect as playwright_expect
    return playwright_expect(locator)

ARTIFACTS = Path(__file__).resolve().parent.parent / "test-artifacts"
#: Markup that runs script wherever it is rendered as HTML: a handler on a broken image.
HOSTILE = '<img src=x onerror="window.__pwned=(window.__pwned||0)+1;alert(1)">'
#: Everything in the page, through its shadow roots: the text, and whether an element of
#: ``HOSTILE`` exists anywhere.
PAGE_TEXT = """() => {
  const parts = []; let images = 0;
  const walk = root => { for (const e of root.querySelectorAll('*')) {
    if (e.tagName === 'IMG' && e.getAttribute('src') === 'x') images++;
    if (e.shadowRoot) walk(e.shadowRoot); } };
  walk(document);
  const text = root => { for (const n of root.childNodes) {
    if (n.nodeType === 3) parts.push(n.textContent);
    else if (!['STYLE', 'SCRIPT'].includes(n.nodeName)) {
      if (n.shadowRoot) text(n.shadowRoot);
      text(n);
      if (n.tagName === 'OPTION' || n.tagName === 'INPUT') parts.push(n.value || ''); } } };
  text(document.body);
  return {text: parts.join(' '), images};
}"""


def open_app(browser, url):
    """A page at 1280×720 that records dialogs and whether ``HOSTILE`` ever ran."""
    page = browser.new_page(viewport={"width": 1280, "height": 720})
    log = PageLog(page)
    dialogs: list[str] = []
    page.on("dialog", lambda d: (dialogs.append(d.message), d.dismiss()))
    page.goto(url)
    page.wait_for_selector(".data-plot canvas", timeout=60_000)
    return page, log, dialogs


def choose_file(page, area: str, path: Path) -> None:
    """Give ``path`` to the file input of the drop area of CSS class ``area``."""
    page.locator(f".{area} .mdcore-drop").wait_for(timeout=30_000)
    page.locator(f".{area} input[type=file]").set_input_files(str(path))


def drop_file(page, area: str, name: str, data: bytes) -> None:
    """Drop a file called ``name`` holding ``data`` on the drop area of CSS class
    ``area``, as a drag from the desktop does (dragenter, dragover, drop)."""
    target = page.locator(f".{area} .mdcore-drop")
    target.wait_for(timeout=30_000)
    transfer = page.evaluate_handle(
        """([name, b64]) => {
            const bytes = Uint8Array.from(atob(b64), c => c.charCodeAt(0));
            const type = name.endsWith('.json') ? 'application/json' : 'text/csv';
            const dt = new DataTransfer();
            dt.items.add(new File([bytes], name, {type}));
            return dt;
        }""", [name, base64.b64encode(data).decode()])
    box = target.bounding_box()
    point = {"clientX": box["x"] + box["width"] / 2, "clientY": box["y"] + box["height"] / 2}
    for event in ("dragenter", "dragover", "drop"):
        target.dispatch_event(event, {"dataTransfer": transfer, **point})


def toasts(page) -> list[str]:
    """The text of every notification shown now."""
    return [t.strip() for t in page.locator(".notyf__message").all_inner_texts()]


def wait_toast(page, needle: str, timeout: float = 30.0) -> str:
    """The first notification whose text holds ``needle`` (waits for it)."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        for text in toasts(page):
            if needle in text:
                return text
        time.sleep(0.2)
    raise AssertionError(f"no notification with {needle!r}; shown: {toasts(page)}")


def session_file(tmp_path: Path, name: str, **edits) -> Path:
    """A valid session file of beam-1d (no waves) with ``edits`` ("case.name": value)."""
    from mdcore_app.state import ExplorerState
    doc = json.loads(ExplorerState().session_json())
    for key, value in edits.items():
        section, field = key.split(".")
        doc[section][field] = value
    path = tmp_path / name
    path.write_text(json.dumps(doc), encoding="utf-8")
    return path


def beam_csv() -> str:
    from mdcore import _cases as cases
    from mdcore._case_file import measurements_template
    return measurements_template(cases.load("beam-1d"))


def test_hostile_names_are_shown_as_text_and_run_nothing(browser, server, tmp_path):
    """Session files with markup in ``case.name``, ``controls.rule`` and
    ``case.measurements_file``, a CSV whose *file name* is that markup, and one whose
    header is: each is refused or taken with the markup shown literally (notification,
    case list, case description), no script runs and no dialog opens."""
    url = server.url
    page, log, dialogs = open_app(browser, url)
    tab(page, "Files")

    choose_file(page, "open-session", session_file(tmp_path, "a.json", **{"case.name": HOSTILE}))
    text = wait_toast(page, "is not in this app")
    assert HOSTILE in text, text
    choose_file(page, "open-session",
                session_file(tmp_path, "b.json", **{"controls.rule": HOSTILE}))
    text = wait_toast(page, "controls.rule")
    assert HOSTILE in text, text

    header = beam_csv().replace("tip deflection", HOSTILE)
    drop_file(page, "upload-csv", "header.csv", header.encode())
    text = wait_toast(page, "not found in the header")
    # A long header cell is cut in the middle (no message echoes a whole line of a file),
    # but what is shown is shown literally.
    assert HOSTILE[:14] in text, text

    # A file named with the markup: taken (a new case named after it).
    drop_file(page, "upload-csv", HOSTILE + ".csv", beam_csv().encode())
    expect(page.locator("select").first).to_have_value(f"beam-1d · {HOSTILE}.csv",
                                                       timeout=60_000)
    # Retried: the description is a new pane per case, and the old one can still be in
    # the page for a moment (an empty paragraph was read once in CI).
    expect(page.locator(".case-description p").first).to_contain_text(f"{HOSTILE}.csv",
                                                                      timeout=30_000)

    # The same markup as the uploaded file's name inside a session file.
    choose_file(page, "open-session", session_file(
        tmp_path, "c.json", **{"case.based_on": "beam-1d", "case.measurements_csv": beam_csv(),
                               "case.measurements_file": "x" + HOSTILE + ".csv"}))
    expect(page.locator("select").first).to_have_value(f"beam-1d · x{HOSTILE}.csv",
                                                       timeout=60_000)
    page.locator(".case-description", has_text=f"x{HOSTILE}").wait_for(timeout=30_000)

    for name in ("Data", "History matching", "Discrepancy", "Metrics", "Things to try"):
        tab(page, name)
    page.wait_for_timeout(500)
    ARTIFACTS.mkdir(exist_ok=True)
    page.screenshot(path=str(ARTIFACTS / "security-hostile-names.png"))
    seen = page.evaluate(PAGE_TEXT)
    assert page.evaluate("window.__pwned") is None and dialogs == []
    assert seen["images"] == 0, "the markup became an element"
    assert HOSTILE in seen["text"]
    assert log.errors == [], log.errors
    page.close()


def test_the_page_refuses_inline_event_handlers(browser, server):
    """The Content-Security-Policy, the second line of defence: markup put into the page
    by its own script (as escaping gone wrong would) cannot run a handler, and nothing
    of the app is blocked by the policy (no console error on any tab)."""
    url = server.url
    page, log, dialogs = open_app(browser, url)
    policy = page.locator("meta[http-equiv='Content-Security-Policy']")
    assert policy.count() == 1
    content = policy.get_attribute("content")
    assert "default-src 'self'" in content and "script-src-attr 'none'" in content
    for name in ("History matching", "Discrepancy", "Metrics", "Files", "Things to try",
                 "Data"):
        tab(page, name)
    assert log.errors == [], log.errors
    page.evaluate("html => document.body.insertAdjacentHTML('beforeend', html)", HOSTILE)
    page.wait_for_timeout(1_000)
    assert page.evaluate("window.__pwned") is None and dialogs == []
    assert any("Content Security Policy" in e for e in log.errors), log.errors
    assert log.hosts <= {"127.0.0.1", "localhost"}, log.hosts
    page.close()


@pytest.mark.parametrize("text", [
    HOSTILE, "[a](javascript:alert(1)) `x` **b** $x^2$ :smile: <b>&amp;",
    "line\n# heading\n    indented", "<script>alert(1)</script>"])
def test_user_text_in_markdown_and_html_is_shown_literally(text):
    """markup.markdown_text through Panel's Markdown pane, and markup.html_text, render
    no element: the page shows the characters typed (line breaks as spaces, or <br>)."""
    import html
    import re

    import panel as pn

    from mdcore_app.markup import html_text, markdown_text
    rendered = html.unescape(pn.pane.Markdown(markdown_text(text)).get_root().text)
    inner = re.fullmatch(r"<p>(.*)</p>\n", rendered, re.S)
    assert inner is not None, rendered
    assert html.unescape(inner.group(1)) == " ".join(text.split())
    shown = html_text(text)
    assert "<" not in shown.replace("<br>", "")
    assert html.unescape(shown.replace("<br>", "\n")) == text


def hostile_case_file(folder: Path) -> Path:
    """examples/beam_lab with ``HOSTILE`` in its title, description, input, output,
    unit and parameter names (the CSV's header to match)."""
    import shutil
    example = Path(__file__).resolve().parent.parent / "examples" / "beam_lab"
    shutil.copy(example / "beam_lab_simulator.py", folder)
    toml = (example / "beam_lab.toml").read_text(encoding="utf-8")
    quoted = HOSTILE.replace('"', '\\"')
    for old, new in (('title = "', f'title = "{quoted} '),
                     ('description = "', f'description = "{quoted} '),
                     ('"position_m"', f'"x{quoted}"'), ('"deflection_mm"', f'"y{quoted}"'),
                     ('input_units = ["m"]', f'input_units = ["m{quoted}"]'),
                     ('name = "E"\nunit = "GPa"', f'name = "E{quoted}"\nunit = "GPa{quoted}"')):
        assert old in toml
        toml = toml.replace(old, new, 1)
    csv_text = (example / "measurements.csv").read_text(encoding="utf-8")
    cell = '"{}"'.format(HOSTILE.replace('"', '""'))
    csv_text = csv_text.replace("position_m,reading,deflection_mm,test",
                                f"x{cell},reading,y{cell},test".replace('x"', '"x', 1)
                                .replace('y"', '"y', 1))
    (folder / "measurements.csv").write_text(csv_text, encoding="utf-8")
    path = folder / "hostile.toml"
    path.write_text(toml, encoding="utf-8")
    return path


def test_a_case_file_with_markup_in_its_names_runs_nothing(browser, tmp_path):
    """A case file given to the server (``--args --case``) with markup in every name it
    can carry: after the waves and scenario 1 + KOH, every tab shows the names literally
    (description, metrics table, KOH summary, plot labels) and no element is made."""
    path = hostile_case_file(tmp_path)
    proc, url, server_log = serve_app(args=("--case", str(path)))
    try:
        page, log, dialogs = open_app(browser, url)
        page.locator("select").first.select_option("beam-lab")
        page.locator(".case-description", has_text="Three readings").wait_for(timeout=30_000)
        page.locator(".bk-btn-group button", has_text="koh").first.click()
        page.get_by_role("button", name="Run discrepancy").click()
        tab(page, "Metrics")
        page.locator(".koh-summary").wait_for(timeout=120_000)
        for name in ("Data", "History matching", "Discrepancy", "Files", "Metrics"):
            tab(page, name)
            page.wait_for_timeout(300)
            seen = page.evaluate(PAGE_TEXT)
            assert seen["images"] == 0, f"the markup became an element on {name}"
            assert HOSTILE in seen["text"], name
        assert page.evaluate("window.__pwned") is None and dialogs == []
        assert log.errors == [], log.errors
        page.close()
    finally:
        proc.terminate()
        proc.wait(timeout=10)


def app_failures(log: str) -> list[str]:
    """The tracebacks in a server log that pass through the app or mdcore, or that Bokeh
    raised for a document changed without its lock (a closed page's websocket write
    failing is Tornado's, not ours)."""
    blocks = log.split("Traceback (most recent call last):")[1:]
    return [b[:3000] for b in blocks
            if "/app/" in b or "/mdcore/" in b or "should have the lock" in b]


def status_of(page, area: str, state: str, name: str = "", timeout: float = 60_000) -> str:
    """The drop area's line once it says ``state`` (accepted, rejected) about the file
    ``name``."""
    line = page.locator(f".{area} .mdcore-drop-status[data-state={state}]", has_text=name)
    line.wait_for(timeout=timeout)
    return line.inner_text()


#: Record each ``data-state`` the element takes (in ``e.mdcoreSeen``) from now on.
WATCH_STATE = """e => { e.mdcoreSeen = [];
  new MutationObserver(() => e.mdcoreSeen.push(e.dataset.state))
    .observe(e, {attributes: true, attributeFilter: ['data-state']}); }"""


def states_until_verdict(line, timeout: float = 60.0) -> list[str]:
    """The states :data:`WATCH_STATE` recorded once the last is a verdict."""
    end = time.monotonic() + timeout
    while True:
        seen = line.evaluate("e => e.mdcoreSeen")
        if seen and seen[-1] in ("accepted", "rejected"):
            return seen
        if time.monotonic() > end:
            raise AssertionError(f"no verdict on the upload; states so far {seen}")
        line.page.wait_for_timeout(100)


def test_uploads_through_the_page_chunked_again_and_over_the_limits(browser, server,
                                                                    tmp_path):
    """Through the Files tab as a user goes: a CSV of three chunks (a drop) is taken whole;
    the same file chosen again replaces it; after a run, the session saved and opened
    twice in the same page recomputes the same metrics; files over the row limit and over
    the byte cap are refused in red with a notification, and the session keeps its case.
    Nothing fails on the server (its log has no traceback)."""
    from mdcore._cases import MAX_ROWS
    from mdcore_app.session import MAX_UPLOAD_BYTES
    from mdcore_app.upload import CHUNK_BYTES
    url, server_log = server.url, server.log
    page, log, dialogs = open_app(browser, url)
    tab(page, "Files")
    select = page.locator("select").first

    padding = "".join(f"# note {i:06d} " + "." * 90 + "\n" for i in range(6_000))
    lab = padding + beam_csv()
    assert 2 * CHUNK_BYTES < len(lab.encode()) < 3 * CHUNK_BYTES         # three chunks
    drop_file(page, "upload-csv", "lab.csv", lab.encode())
    assert status_of(page, "upload-csv", "accepted") == "lab.csv: loaded."
    expect(select).to_have_value("beam-1d · lab.csv", timeout=30_000)

    again = tmp_path / "lab.csv"
    again.write_text(beam_csv().replace(",0\n", ",0\n", 1), encoding="utf-8")
    # The line under the area said the last file's "loaded." until the server answered:
    # under load, a run pressed meanwhile was dropped when the upload replaced the case.
    # It now says "sending" at once.
    line = page.locator(".upload-csv .mdcore-drop-status")
    for _ in range(2):              # the same name with new data, then the very same file
        line.evaluate(WATCH_STATE)
        choose_file(page, "upload-csv", again)
        seen = states_until_verdict(line)
        assert seen[0] == "sending" and seen[-1] == "accepted", seen
        assert line.inner_text() == "lab.csv: loaded."
    assert select.locator("option").all_inner_texts().count("beam-1d · lab.csv") == 1

    page.get_by_role("button", name="Run discrepancy").click()
    try:
        expect(page.locator(".dl-report").get_by_role("button")).to_be_enabled(timeout=120_000)
    except AssertionError as exc:          # once in a full run: say what the page had
        raise AssertionError(f"the report stayed disabled; page errors {log.errors}; busy "
                             f"line {page.locator('.mdcore-busy').count()}; server log: "
                             f"{server_log.text()[-3000:]}") from exc
    page.locator(".mdcore-idle").wait_for(state="attached", timeout=120_000)
    with page.expect_download() as got:
        page.locator(".dl-session").get_by_role("button").click()
    saved = tmp_path / "lab_session.json"
    got.value.save_as(str(saved))
    for _ in range(2):                                      # the session you are on, again
        choose_file(page, "open-session", saved)
        assert status_of(page, "open-session", "accepted") == "lab_session.json: loaded."
        tab(page, "History matching")
        page.locator(".hm-status", has_text="every metric equals the saved one").wait_for(
            timeout=120_000)
        page.locator(".mdcore-idle").wait_for(timeout=120_000)
        tab(page, "Files")
    expect(select).to_have_value("beam-1d · lab.csv")

    rows = tmp_path / "rows.csv"
    rows.write_text("crack location,tip deflection,test\n" + "0.3,1.0,1\n" * (MAX_ROWS + 1),
                    encoding="utf-8")
    choose_file(page, "upload-csv", rows)
    text = status_of(page, "upload-csv", "rejected", "rows.csv")
    assert f"more than {MAX_ROWS:,} data rows" in text, text
    wait_toast(page, f"more than {MAX_ROWS:,} data rows")

    big = tmp_path / "big.csv"
    big.write_bytes(b"#" * (MAX_UPLOAD_BYTES + 1))
    choose_file(page, "upload-csv", big)
    text = status_of(page, "upload-csv", "rejected", "big.csv")
    assert text == ("big.csv is 5,000,001 bytes, more than the 5 MB limit (5,000,000 bytes); "
                    "nothing was taken."), text
    wait_toast(page, "nothing was taken")
    expect(select).to_have_value("beam-1d · lab.csv")
    ARTIFACTS.mkdir(exist_ok=True)
    page.screenshot(path=str(ARTIFACTS / "security-uploads.png"))

    assert page.evaluate("window.__pwned") is None and dialogs == []
    assert log.errors == [], log.errors
    assert app_failures(server_log.text()) == []
    page.close()


# --------------------------------------------------------------------------------------
# Who may use the app (app/network.py)


def websocket_handshake(port: int, origin: str) -> int:
    """The HTTP status of a websocket handshake with the app at ``port`` sent with
    ``origin`` (101: switched to the websocket)."""
    import os
    import socket

    from bokeh.util.token import generate_jwt_token, generate_session_id
    token = generate_jwt_token(generate_session_id())
    request = (f"GET /main/ws HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\n"
               "Connection: Upgrade\r\nSec-WebSocket-Version: 13\r\n"
               f"Sec-WebSocket-Key: {base64.b64encode(os.urandom(16)).decode()}\r\n"
               f"Sec-WebSocket-Protocol: bokeh, {token}\r\nOrigin: {origin}\r\n\r\n")
    with socket.create_connection(("127.0.0.1", port), timeout=30) as s:
        s.sendall(request.encode())
        return int(s.recv(4096).split(b"\r\n", 1)[0].split()[1])


def test_a_forged_websocket_origin_is_refused(server):
    """A websocket whose Origin is another site (a page elsewhere that talks to the app)
    gets 403; the app's own page origin is accepted."""
    from urllib.parse import urlparse
    url = server.url
    port = urlparse(url).port
    for origin in (f"http://evil.example:{port}", "http://evil.example",
                   f"http://localhost.evil.example:{port}", "null"):
        assert websocket_handshake(port, origin) == 403, origin
    assert websocket_handshake(port, f"http://127.0.0.1:{port}") == 101


def test_a_page_for_another_host_name_gets_no_app(browser, tmp_path):
    """DNS rebinding: a page at http://evil.example:PORT whose name resolves to this
    machine. Even when the websocket origin is let through (a careless
    --allow-websocket-origin), the app refuses the session: the page shows the refusal,
    not the app."""
    proc, url, log = serve_app(options=(
        "--address", "127.0.0.1", "--allow-websocket-origin", "127.0.0.1:{port}",
        "--allow-websocket-origin", "evil.example:{port}"))
    try:
        evil = url.replace("127.0.0.1", "evil.example")
        chrome = browser.browser_type.launch(executable_path=CHROMIUM, args=[
            *FLAGS, "--host-resolver-rules=MAP evil.example 127.0.0.1"])
        try:
            page = chrome.new_page(viewport={"width": 1280, "height": 720})
            page_log = PageLog(page)
            page.goto(evil)
            refused = page.locator(".mdcore-refused p")
            for words in ("Refused a request for the host 'evil.example'",
                          "--address 127.0.0.1", "--allow-remote"):
                expect(refused).to_contain_text(words, timeout=60_000)
            assert page.locator(".data-plot").count() == 0
            page.wait_for_timeout(500)                  # the refusal loads nothing else
            assert page_log.errors == [] and page_log.hosts == {"evil.example"}, \
                (page_log.errors, page_log.hosts)
        finally:
            chrome.close()
        assert "Refused a request for the host 'evil.example'" in log.text()
    finally:
        proc.terminate()
        proc.wait(timeout=10)


def test_a_server_listening_beyond_this_machine_refuses_and_stops(browser):
    """panel serve without --address listens on every interface: the first page shows
    why the app refuses and how to restart (or opt in), the log says the same, and the
    server stops. With ``--args --allow-remote`` it serves."""
    from mdcore_app.network import own_addresses
    if not own_addresses():
        pytest.skip("this machine has no network address beyond loopback")
    proc, url, log = serve_app(options=("--allow-websocket-origin", "127.0.0.1:{port}"))
    try:
        page = browser.new_page(viewport={"width": 1280, "height": 720})
        page.goto(url)
        refused = page.locator(".mdcore-refused p")
        for words in ("This server listens beyond this machine", "--address 127.0.0.1",
                      "--allow-remote"):
            expect(refused).to_contain_text(words, timeout=60_000)
        page.close()
        proc.wait(timeout=30)                                 # it stopped by itself
        log.closed.wait(timeout=10)
        assert "This server listens beyond this machine" in log.text(), log.text()
    finally:
        if proc.poll() is None:
            proc.terminate()
            proc.wait(timeout=10)
    proc, url, log = serve_app(args=("--allow-remote",),
                               options=("--allow-websocket-origin", "127.0.0.1:{port}"))
    try:
        page = browser.new_page(viewport={"width": 1280, "height": 720})
        page.goto(url)
        page.wait_for_selector(".data-plot canvas", timeout=60_000)
        assert page.locator(".mdcore-refused").count() == 0 and proc.poll() is None
        page.close()
    finally:
        proc.terminate()
        proc.wait(timeout=10)


class _Request:
    def __init__(self, remote_ip="127.0.0.1", **headers):
        self.remote_ip, self.headers = remote_ip, {k.replace("_", "-"): v
                                                   for k, v in headers.items()}


@pytest.mark.parametrize("request_, refused", [
    (_Request(Host="127.0.0.1:5006"), None),
    (_Request(Host="localhost:5006", Origin="http://localhost:5006"), None),
    (_Request(remote_ip="::1", Host="[::1]:5006", Origin="http://[::1]:5006"), None),
    (_Request(remote_ip="192.168.1.7", Host="127.0.0.1:5006"), "another machine"),
    (_Request(Host="evil.example:5006"), "for the host 'evil.example'"),
    (_Request(Host="127.0.0.1.evil.example:5006"), "which is not this machine"),
    (_Request(), None),                        # no Host: not a browser, judged by its IP
    (_Request(Host="127.0.0.1:5006", Origin="http://evil.example:5006"), "another site"),
    (_Request(Host="127.0.0.1:5006", Origin="http://127.0.0.1:6000"), "another site"),
], ids=["loopback", "localhost", "ipv6", "remote", "rebinding", "lookalike", "no-host",
        "cross-site", "other-port"])
def test_which_requests_the_app_refuses(request_, refused):
    from mdcore_app.network import request_refusal
    why = request_refusal(request_)
    if refused is None:
        assert why is None, why
    else:
        assert refused in why and "--address 127.0.0.1" in why and "--allow-remote" in why
