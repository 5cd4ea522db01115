"""One session built ahead, so that the next visitor's page needs no build.

A page of the app costs the server ~0.9 s of Python (the app's objects, their Bokeh
models), all of it inside the page's HTTP request: the browser waits for it before it can
even fetch the scripts. Building it during the script loading instead gains nothing on
two cores (measured: both compete for the same CPUs). Here the server builds the *next*
session while it is idle, and hands it to the next page request, which then answers at
once; its document is serialised ahead too, for the page's first pull. Idle means:
:data:`IDLE_SECONDS` after the last page request and after the last job of any session
ended, and :data:`LOADED_SECONDS` after the last page given out reported its document
drawn; so the build slows no page load and no computation, and does not show in the CPU
that a cancelled job frees.

The prebuilt session is an ordinary Bokeh session: created by Bokeh's own
``create_session_if_needed`` (so ``main.py`` runs for it as for any session) and kept from
expiring until it is handed out. At the hand-out it gets a fresh token (expiry, headers,
cookies and arguments of the request that gets it), as Bokeh would have made for that
request. A request that names its session (``bokeh-session-id``, ``bokeh-token``), a
server that reuses sessions (``--reuse-sessions``) or reloads the app on changes
(``--autoreload``) is served as before. An unused prebuilt session older than
:data:`MAX_AGE_SECONDS` is discarded rather than handed out.

:func:`install` wraps Panel's page handler once per process; ``main.py`` calls it. The
hand-out sets what Bokeh 3's ``create_session_if_needed`` sets on a new session (its
token, its session context's token and request view, the time its unused lifetime counts
from): attributes private to Bokeh. If they change, the page is built on request as before
(the failure is logged), and the browser test that follows a page served from the pool
(tests/test_app_browser.py) fails.
"""

from __future__ import annotations

import logging
import os
import time
from dataclasses import dataclass

from mdcore_app import network
from mdcore_app.jobs import seconds_since_work

log = logging.getLogger(__name__)

#: Seconds without a page request (and since the last job ended) before the next session
#: is built.
IDLE_SECONDS = 3.0
#: Seconds after the last loading page reported its document drawn.
LOADED_SECONDS = 1.0
#: Seconds between checks while the server is not idle yet.
POLL_SECONDS = 0.5
#: A prebuilt session older than this is not handed out (its app state would be a stale
#: copy after a long idle time; Bokeh's tokens expire after 300 s by default).
MAX_AGE_SECONDS = 240.0

_SESSION_ARGS = ("bokeh-session-id", "bokeh-token")
#: Environment variable that turns the pool off (``0``).
ENV = "MDCORE_SESSION_POOL"


@dataclass
class _Ready:
    session: object           # bokeh.server.session.ServerSession
    built: float              # time.monotonic() when built


class SessionPool:
    """At most one prebuilt session per application (Bokeh application context)."""

    def __init__(self, idle_seconds: float = IDLE_SECONDS,
                 max_age_seconds: float = MAX_AGE_SECONDS):
        if not idle_seconds > 0 or not max_age_seconds > 0:
            raise ValueError("idle_seconds and max_age_seconds must be > 0; received "
                             f"{idle_seconds!r} and {max_age_seconds!r}.")
        self.idle_seconds = idle_seconds
        self.max_age_seconds = max_age_seconds
        self._ready: dict[int, _Ready] = {}
        self._building: set[int] = set()
        self._last_request = time.monotonic()
        self._last_loading = -float("inf")
        self._pages: dict[int, float] = {}      # id(document) -> when given out
        self._timer = None
        self.handed_out = 0                     # sessions served from the pool

    # -- the page handler's side --------------------------------------------------------

    def take(self, handler):
        """The prebuilt session for ``handler``'s application, ready for its request, or
        None (nothing ready, too old, or the request names its own session)."""
        from bokeh.server.session import current_time

        if any(handler.get_argument(a, default=None) is not None for a in _SESSION_ARGS) \
                or "Bokeh-Session-Id" in handler.request.headers \
                or network.request_refusal(handler.request) is not None:
            return None         # the app decides on a request it may refuse (main.refusal)
        ready = self._ready.pop(id(handler.application_context), None)
        if ready is None:
            return None
        session = ready.session
        try:
            usable = time.monotonic() - ready.built <= self.max_age_seconds \
                and not session.destroyed and _give_token(handler, session)
        except Exception:                       # noqa: BLE001 - e.g. a Bokeh without these
            log.exception("a session built ahead could not be given out; building one")
            usable = False
        if not usable:
            self._discard(session)
            return None
        # From now on an ordinary session, as if created now: Bokeh discards a session
        # nobody connected to within its unused lifetime, counted from its creation.
        session._last_unsubscribe_time = current_time()
        session.unblock_expiration()
        self.handed_out += 1
        log.info("page served from a session built ahead (%s)", session.id)
        return session

    def refill_later(self, context, request) -> None:
        """Build the next session of ``context`` (a Bokeh ``ApplicationContext``) once the
        server is idle (see the module's docstring); ``request`` is the last page request
        (its view of headers and arguments is replaced at the hand-out)."""
        from tornado.ioloop import IOLoop

        self._last_request = time.monotonic()
        loop = IOLoop.current()
        if self._timer is not None:
            loop.remove_timeout(self._timer)

        def fire():
            self._timer = None
            now = time.monotonic()
            if self._loading():
                self._last_loading = now
            wait = max(self._last_request + self.idle_seconds - now,
                       self._last_loading + LOADED_SECONDS - now,
                       self.idle_seconds - seconds_since_work())
            if wait > 0:                        # a page loading, or a job, meanwhile
                self._timer = loop.call_later(min(wait, POLL_SECONDS), fire)
                return
            key = id(context)
            if key not in self._ready and key not in self._building:
                loop.add_callback(self._build, context, request)

        self._timer = loop.call_later(self.idle_seconds, fire)

    def page_started(self, doc) -> None:
        """A page's session ``doc`` was given out: it is loading until its browser reports
        the document drawn (BokehJS's ``document_ready`` event)."""
        key = id(doc)
        self._pages[key] = time.monotonic()
        doc.on_event("document_ready", lambda _event: self._pages.pop(key, None))

    def _loading(self) -> bool:
        """Whether a page is still loading: given out in the last minute, not drawn yet (a
        page that never reports is forgotten after a minute)."""
        now = time.monotonic()
        for key, started in list(self._pages.items()):
            if now - started > 60.0:
                del self._pages[key]
        return bool(self._pages)

    # -- building -----------------------------------------------------------------------

    async def _build(self, context, request) -> None:
        from bokeh.settings import settings
        from bokeh.util.token import generate_jwt_token, generate_session_id

        key = id(context)
        self._building.add(key)
        try:
            # Bokeh's own defaults for the id; the hand-out checks it against the server's
            # settings and gives the session the token of the request that gets it.
            session_id = generate_session_id(secret_key=settings.secret_key_bytes(),
                                             signed=settings.sign_sessions())
            token = generate_jwt_token(session_id, secret_key=settings.secret_key_bytes(),
                                       signed=settings.sign_sessions(),
                                       extra_payload={"headers": {}, "cookies": {},
                                                      "arguments": {}})
            session = await context.create_session_if_needed(session_id, request, token)
            session.block_expiration()          # unused, it must not be cleaned up
            _serialize_ahead(session.document)
            self._ready[key] = _Ready(session, time.monotonic())
            log.info("built a session ahead (%s) for the next page", session_id)
        except Exception:                       # noqa: BLE001 - never break the server
            log.exception("building a session ahead failed; pages are built on request")
        finally:
            self._building.discard(key)

    @staticmethod
    def _discard(session) -> None:
        session.unblock_expiration()            # Bokeh's cleanup then discards it
        session.request_expiration()


def _serialize_ahead(doc) -> None:
    """Serialise ``doc`` now for its first pull, which is on the page's critical path
    (~0.2 s of the server's time after the scripts have loaded). The copy serves one
    ``to_json()`` call and is dropped at the first change of the document, so a pull
    always gets the document as it is."""
    serialized = doc.to_json()

    def to_json(*, deferred: bool = True):
        del doc.to_json                         # one use; the method again after it
        return serialized if deferred else doc.to_json(deferred=False)

    def changed(_event) -> None:
        doc.__dict__.pop("to_json", None)

    doc.to_json = to_json
    doc.on_change(changed)


def _payload(handler) -> dict:
    """The token payload Bokeh's ``SessionHandler.get_session`` builds for the request."""
    app, request = handler.application, handler.request
    if app.include_headers is None:
        excluded = app.exclude_headers or []
        headers = {k: v for k, v in request.headers.items() if k not in excluded}
    else:
        headers = {k: v for k, v in request.headers.items() if k in app.include_headers}
    if app.include_cookies is None:
        excluded = app.exclude_cookies or []
        cookies = {k: v.value for k, v in request.cookies.items() if k not in excluded}
    else:
        cookies = {k: v.value for k, v in request.cookies.items() if k in app.include_cookies}
    if cookies and "Cookie" in headers and "Cookie" not in (app.include_headers or []):
        del headers["Cookie"]                   # restored from the cookies, as Bokeh does
    payload = {"headers": headers, "cookies": cookies,
               "arguments": {} if request.arguments is None else request.arguments}
    payload.update(handler.application_context.application.process_request(request))
    return payload


def _give_token(handler, session) -> bool:
    """Give ``session`` the token (and request view) Bokeh would have made for
    ``handler``'s request: a fresh expiry, this request's headers, cookies, arguments.
    False (nothing changed) if the session's id is not valid for this server."""
    from bokeh.server.contexts import _RequestProxy
    from bokeh.util.token import (
        check_session_id_signature,
        generate_jwt_token,
        get_token_payload,
    )

    app = handler.application
    if not check_session_id_signature(session.id, secret_key=app.secret_key,
                                      signed=app.sign_sessions):
        return False
    token = generate_jwt_token(session.id, secret_key=app.secret_key,
                               signed=app.sign_sessions,
                               expiration=app.session_token_expiration,
                               extra_payload=_payload(handler))
    payload = get_token_payload(token)
    if "cookies" in payload and "headers" in payload and "Cookie" not in payload["headers"]:
        payload["headers"]["Cookie"] = "; ".join(
            f"{k}={v}" for k, v in payload["cookies"].items())
    context = handler.application_context._session_contexts[session.id]
    session._token = token
    context._token = token
    context._request = _RequestProxy(handler.request, arguments=payload.get("arguments"),
                                     cookies=payload.get("cookies"),
                                     headers=payload.get("headers"))
    return True


#: The process's pool (one server per process).
POOL = SessionPool()


def install(pool: SessionPool = POOL) -> bool:
    """Make Panel's page handler serve pages from ``pool``, once per process.

    Returns True when this call installed it (the server's first session: the caller
    then starts the first build with :meth:`SessionPool.refill_later`), False when it was
    installed already or it is ruled out: by the server's settings (``--reuse-sessions``,
    ``--autoreload``) or by ``MDCORE_SESSION_POOL=0`` in the environment.
    """
    from panel.config import config
    from panel.io.server import DocHandler

    if config.reuse_sessions or config.autoreload or os.environ.get(ENV) == "0":
        return False
    if getattr(DocHandler.get_session, "_mdcore_pool", None) is not None:
        return False
    original = DocHandler.get_session

    async def get_session(self):
        session = pool.take(self)
        if session is None:
            session = await original(self)
        pool.page_started(session.document)
        pool.refill_later(self.application_context, self.request)
        return session

    get_session._mdcore_pool = pool
    DocHandler.get_session = get_session
    # Bokeh's ``--log-level`` sets the level of its own logger only: the pool's lines
    # (a page served from a session built ahead, a build) follow it.
    log.setLevel(logging.getLogger("bokeh").getEffectiveLevel())
    return True
