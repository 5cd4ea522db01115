"""Entry point of the Model Discrepancy Explorer: ``panel serve app/main.py``.

Your own cases join the built-in ones with ``panel serve app/main.py --address 127.0.0.1
--warm --args --case my_case.toml [--case other.toml ...]`` (TOML case files, see
:mod:`mdcore._case_file`); ``--warm`` loads them when the server starts, not for its first
visitor.

Each browser session runs this module and gets its own :class:`ExplorerState`, so two
sessions never see each other's results. Long work runs on a background thread and hands
its results back to the session's event loop.
"""

import argparse
import logging
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import holoviews as hv
import panel as pn
from panel.io.resources import LOCAL_DIST
from panel.io.state import set_curdoc
from tornado.ioloop import IOLoop

from mdcore import _compiled as compiled
from mdcore import _threads as threads
from mdcore._case_file import load_case_file
from mdcore_app import network
from mdcore_app.markup import markdown_text
from mdcore_app.session_loop import job_scheduler
from mdcore_app.state import ExplorerState
from mdcore_app.views import ExplorerView

# Panel's default design, not "bootstrap": Bokeh reads every glyph's colours and widths
# through getComputedStyle while it paints, and Bootstrap's style sheets in every
# component's shadow root made each of those style recalculations 3-6x dearer (shear-5:
# 1.5 s of a scenario toggle's 2.2 s of browser time).
# The notifications live outside Bokeh's shadow roots, where Panel's font variable
# (--bokeh-base-font) is not defined: they came out in the browser's serif. A narrower
# toast also covers less of the plots while it fades; long words (file names) wrap inside it.
NOTIFICATION_CSS = """
.notyf__message { font-family: -apple-system, BlinkMacSystemFont, "Segoe UI", Roboto,
                  "Helvetica Neue", Arial, sans-serif; font-size: 13px; line-height: 1.35;
                  overflow-wrap: anywhere; min-width: 0; }
.notyf__toast { max-width: 380px !important; }
.notyf__wrapper { min-width: 0; }
"""
pn.extension(notifications=True, raw_css=[NOTIFICATION_CSS])
hv.extension("bokeh")
#: The page's Content-Security-Policy: everything from the page's own origin (its scripts,
#: style sheets, fonts and the websocket: 'self' covers ws:// of the same host), nothing
#: from elsewhere. What Panel and Bokeh need beyond that: inline <script> elements (the
#: page's own; Bokeh's carries the session's token, so no hash can name it), code compiled
#: in the browser (BokehJS compiles CustomJS callbacks and Panel's ReactiveHTML scripts,
#: such as the notifications', with ``new Function``), blob: scripts (es-module-shims
#: fetches and loads the drop areas' module, app/upload.js, as one, and probes ``import()`` with
#: another; only a script already running can make a blob), inline styles, and data:/blob:
#: images (Bokeh's image glyphs, the "save" tool). ``script-src-attr 'none'`` refuses
#: every inline event handler (``<img onerror=…>``), so markup that slipped into an HTML
#: pane runs nothing; user text is escaped everywhere (:mod:`mdcore_app.markup`), which is
#: what keeps it from becoming a <script> or an iframe's ``srcdoc``. A <meta> element, the
#: first in the page's head: Panel 1.9 / Bokeh 3.9 offer no public way to add a response
#: header to ``panel serve``'s page (and a <meta> policy cannot carry frame-ancestors).
CONTENT_SECURITY_POLICY = "; ".join((
    "default-src 'self'",
    "script-src 'self' 'unsafe-inline' 'unsafe-eval' blob:",
    "script-src-attr 'none'",
    "style-src 'self' 'unsafe-inline'",
    "img-src 'self' data: blob:",
    "font-src 'self' data:",
    "connect-src 'self' blob:",
    "object-src 'none'",
    "frame-src 'none'",
    "base-uri 'self'",
    "form-action 'self'"))
#: Panel's page (a string template extends it) with the policy first in its head.
PAGE_TEMPLATE = (
    "{% block inner_head %}<meta http-equiv=\"Content-Security-Policy\" content=\""
    + CONTENT_SECURITY_POLICY + "\">{{ super() }}{% endblock %}")
log = logging.getLogger("mdcore_app")
# One BLAS thread for the whole server: a second one only spins between the small calls.
threads.single_threaded_blas_for_process()
# Load (or, on a new machine, compile) the numba kernels while the first page is drawn.
compiled.warm_up_in_background()


def app_args(argv: list[str]) -> argparse.Namespace:
    """The options given after ``panel serve app/main.py --args``."""
    parser = argparse.ArgumentParser(prog="panel serve app/main.py --args")
    parser.add_argument("--case", action="append", default=[], type=Path,
                        help="a TOML case file to add to the case list (repeatable)")
    parser.add_argument(network.OPT_IN, action="store_true",
                        help="serve other machines too (with panel serve --address 0.0.0.0); "
                             "by default the app refuses any but this one")
    return parser.parse_args(argv)


def refusal(doc, allow_remote: bool) -> str | None:
    """Why this session's request is refused (:mod:`mdcore_app.network`), or None. The
    first session of a server also checks where the server listens; a server that
    answers beyond this machine stops (its log says why), unless ``allow_remote``."""
    if allow_remote:
        return None
    request = doc.session_context.request
    why = network.request_refusal(request)
    port = network.port_of(request)          # None for --warm's session: no request yet
    if why is None and port is not None:
        if "mdcore-binding" not in pn.state.cache:
            pn.state.cache["mdcore-binding"] = network.binding_refusal(port)
        why = pn.state.cache["mdcore-binding"]
        if why is not None:                      # stop once the page shows why
            loop = IOLoop.current()
            doc.on_event("document_ready", lambda _event: loop.call_later(0.5, loop.stop))
            loop.call_later(10.0, loop.stop)
    if why is not None:
        log.error("mdcore: %s", why)
    return why


#: Seconds one run of a ``--case`` file's simulator may take when the file sets no
#: ``[simulator] timeout``. It also bounds loading the file (the simulator's import and a
#: first run), so a simulator that hangs cannot hold up the server.
CASE_TIMEOUT = 60.0


def own_cases(paths: list[Path]):
    """Load the case files once per server (cached by path and mtime), in parallel, each
    within its simulator's timeout (:data:`CASE_TIMEOUT` by default).

    Returns the cases and one error message per file that could not be loaded.
    """
    def load(path: Path):
        try:
            key = ("mdcore-case-file", str(path.resolve()), path.stat().st_mtime_ns)
        except OSError:
            return f"--case {path}: the file does not exist."
        if key not in pn.state.cache:             # a refused file is not retried either
            try:
                pn.state.cache[key] = load_case_file(path, default_timeout=CASE_TIMEOUT)
            except ValueError as exc:
                pn.state.cache[key] = f"--case {path}: {exc}"
        return pn.state.cache[key]

    with ThreadPoolExecutor(max_workers=max(len(paths), 1)) as pool:
        loaded = list(pool.map(load, paths))
    return ([c for c in loaded if not isinstance(c, str)],
            [c for c in loaded if isinstance(c, str)])


def create_app(argv: list[str] | None = None) -> pn.viewable.Viewable:
    """Build one session's page (state + view) for the current Bokeh document."""
    doc = pn.state.curdoc
    args = app_args(sys.argv[1:] if argv is None else argv)
    served = doc is not None and doc.session_context is not None
    if served:
        _local_style_sheets(doc)
        doc.template = PAGE_TEMPLATE
        why = refusal(doc, args.allow_remote)
        if why is not None:
            return pn.pane.Alert(markdown_text(why), alert_type="danger",
                                 css_classes=["mdcore-refused"], sizing_mode="stretch_width")
    cases, errors = own_cases(args.case)
    state = ExplorerState(background=served, schedule=job_scheduler(doc), own_cases=tuple(cases))
    view = ExplorerView(state=state)
    if served:
        # A closed tab stops its running job: nobody will see the result, and the CPU is
        # shared by every session of the server. The page's websocket closing says so at
        # once (Bokeh ends the session itself only after its unused lifetime, 15-32 s by
        # default); the session stays for a reconnect, idle.
        doc.on_event("connection_lost", lambda _event: state.cancel())
        doc.on_session_destroyed(lambda _context: state.jobs.close())
    for message in errors:                        # shown once the page is there
        pn.state.onload(lambda m=message: state.report_error(m))
    return view


def _local_style_sheets(doc) -> None:
    """Make Panel give this session's components the server's style sheets, never its CDN's.

    Panel patches its components' style-sheet addresses (cdn.holoviz.org by default) to
    the server's when it renders the session's HTML page (``dist_url``). A session that
    Bokeh creates on the websocket's connection (the one from the page expired unused
    first: seen with five pages loading at once) never has its page rendered, so every
    component of it asked cdn.holoviz.org for its CSS, which an offline app must not.
    The address is the one Panel's page would set.
    """
    with set_curdoc(doc):
        local = f"{pn.state.rel_path}/{LOCAL_DIST}" if pn.state.rel_path else LOCAL_DIST
    doc.template_variables.setdefault("dist_url", local)


if pn.state.served:
    create_app().servable(title="Model Discrepancy Explorer")
