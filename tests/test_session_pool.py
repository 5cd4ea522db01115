"""The session built ahead (app/session_pool.py): its rules, without a server.

The served path (a page from a prebuilt session draws and is a session of its own) is
``test_a_page_from_a_session_built_ahead_is_a_whole_session_of_its_own`` in
test_app_browser.py.
"""

from __future__ import annotations

import time

import pytest
from bokeh.core.json_encoder import serialize_json
from bokeh.document import Document
from bokeh.plotting import figure
from bokeh.util.token import get_session_id, get_token_payload

from mdcore_app import session_pool
from mdcore_app.session_pool import SessionPool, _Ready, _serialize_ahead


def test_the_pool_asks_for_positive_times():
    with pytest.raises(ValueError, match="idle_seconds and max_age_seconds must be > 0"):
        SessionPool(idle_seconds=0.0)
    with pytest.raises(ValueError, match="received 3.0 and -1"):
        SessionPool(idle_seconds=3.0, max_age_seconds=-1)
    with pytest.raises(ValueError, match="received nan and 240.0"):
        SessionPool(idle_seconds=float("nan"))


def _doc():
    doc = Document()
    p = figure(title="before")
    p.line([0, 1, 2], [1.0, 3.0, 2.0])
    doc.add_root(p)
    return doc, p


def _text(serialized) -> str:
    """A serialised document's content as JSON text (buffers are referred to by id)."""
    return serialize_json(serialized.content)


def test_the_document_serialised_ahead_serves_one_pull_as_it_is():
    doc, _ = _doc()
    fresh = _text(Document.to_json(doc))
    _serialize_ahead(doc)
    assert "to_json" in doc.__dict__
    assert _text(doc.to_json()) == fresh                  # the copy made ahead ...
    assert "to_json" not in doc.__dict__                  # ... once; then the method again
    assert _text(doc.to_json()) == fresh


def test_a_change_drops_the_document_serialised_ahead():
    doc, p = _doc()
    _serialize_ahead(doc)
    p.title.text = "after"
    text = _text(doc.to_json())
    assert '"after"' in text and '"before"' not in text


class _Session:
    def __init__(self, session_id="abc"):
        self.id, self.destroyed, self._token = session_id, False, "old"
        self.blocked, self.expiring = 1, False
        self._last_unsubscribe_time = 0.0             # built long ago

    def unblock_expiration(self):
        self.blocked -= 1

    def request_expiration(self):
        self.expiring = True


class _Handler:
    """What the pool reads of Panel's page handler (tornado ``RequestHandler``)."""

    def __init__(self, session, arguments=None, headers=None):
        app = type("App", (), {})()
        app.secret_key, app.sign_sessions, app.session_token_expiration = None, False, 300
        app.include_headers = app.exclude_headers = None
        app.include_cookies = app.exclude_cookies = None
        self.application = app
        bokeh_app = type("BokehApp", (), {"process_request": lambda self, r: {}})()
        context = type("Context", (), {})()
        context.application = bokeh_app
        context._session_contexts = {session.id: type("SessionContext", (), {})()}
        self.application_context = context
        self.request = type("Request", (), {})()
        self.request.headers = headers or {"User-Agent": "the new visitor",
                                           "Host": "127.0.0.1:5006"}
        self.request.remote_ip = "127.0.0.1"
        self.request.cookies, self.request.arguments = {}, {}
        self._arguments = arguments or {}

    def get_argument(self, name, default=None):
        return self._arguments.get(name, default)


def _pool_with(session, handler, age=0.0):
    pool = SessionPool()
    pool._ready[id(handler.application_context)] = _Ready(session, time.monotonic() - age)
    return pool


def test_the_next_page_gets_the_session_with_its_own_fresh_token():
    session = _Session()
    handler = _Handler(session)
    pool = _pool_with(session, handler)
    assert pool.take(handler) is session
    assert session.blocked == 0 and not session.expiring     # an ordinary session now,
    assert session._last_unsubscribe_time > 0.0               # unused since the hand-out
    assert get_session_id(session._token) == "abc"
    payload = get_token_payload(session._token)
    assert payload["headers"] == {"User-Agent": "the new visitor", "Host": "127.0.0.1:5006"}
    assert payload["session_expiry"] > time.time() + 250
    context = handler.application_context._session_contexts["abc"]
    assert context._token == session._token
    # as Bokeh's own sessions: the Cookie header rebuilt from the (here no) cookies
    assert context._request.headers == {"User-Agent": "the new visitor",
                                        "Host": "127.0.0.1:5006", "Cookie": ""}
    assert pool.take(handler) is None                         # one page per session
    assert pool.handed_out == 1


@pytest.mark.parametrize("arguments", [{"bokeh-session-id": "mine"}, {"bokeh-token": "t"}])
def test_a_request_that_names_its_session_is_not_given_the_one_built_ahead(arguments):
    session = _Session()
    handler = _Handler(session, arguments=arguments)
    pool = _pool_with(session, handler)
    assert pool.take(handler) is None
    assert session.blocked == 1 and session._token == "old"     # kept for the next page
    handler._arguments = {}                                   # the next plain request
    assert pool.take(handler) is session


def test_a_session_built_long_ago_is_discarded_not_served():
    session = _Session()
    handler = _Handler(session)
    pool = _pool_with(session, handler, age=session_pool.MAX_AGE_SECONDS + 1)
    assert pool.take(handler) is None
    assert session.blocked == 0 and session.expiring          # Bokeh's cleanup ends it
    assert session._token == "old"


def test_a_session_whose_id_the_server_would_refuse_is_discarded():
    session = _Session()
    handler = _Handler(session)
    handler.application.sign_sessions = True                 # the id is not signed
    handler.application.secret_key = b"x" * 32
    pool = _pool_with(session, handler)
    assert pool.take(handler) is None
    assert session.expiring


def test_a_page_is_loading_until_its_browser_reports_it_drawn():
    from bokeh.events import DocumentReady

    pool = SessionPool()
    assert not pool._loading()
    doc, _ = _doc()
    pool.page_started(doc)
    assert pool._loading()                     # given out, scripts and drawing to come
    doc.callbacks.trigger_event(DocumentReady())
    assert not pool._loading()                 # drawn; a later close does not count
    other, _ = _doc()
    pool.page_started(other)
    pool._pages[id(other)] -= 61.0             # never reported, a minute ago: forgotten
    assert not pool._loading()


def test_a_hand_out_that_fails_builds_the_page_on_request_instead():
    session = _Session()
    handler = _Handler(session)
    del handler.application_context._session_contexts       # as if Bokeh had changed
    pool = _pool_with(session, handler)
    assert pool.take(handler) is None
    assert session.expiring                                   # dropped, not half given out


@pytest.mark.parametrize("remote, host", [("192.168.1.20", "127.0.0.1:5006"),
                                          ("127.0.0.1", "evil.example:5006")])
def test_a_request_the_app_may_refuse_is_not_given_the_session_built_ahead(remote, host):
    """Another machine, or a page for another host name (DNS rebinding): the page is built
    on request, where the app checks it (mdcore_app.main.refusal)."""
    session = _Session()
    handler = _Handler(session, headers={"Host": host})
    handler.request.remote_ip = remote
    assert _pool_with(session, handler).take(handler) is None
