"""A drop area whose file reaches the server in counted chunks (the Files tab's uploads).

The browser (``upload.js``) announces a file (name and size), then sends it in chunks of
:data:`CHUNK_BYTES`, each after the server has answered the one before. The server counts
what arrives: a file announced or grown beyond ``max_bytes`` is refused at that message
and its chunks are dropped, so memory never holds more than the cap, whatever a client
sends. A complete file goes to ``take(data, filename)``; the area then shows the verdict:
loaded, or refused with the reason (plain text, never markup). The same file chosen or
dropped again is a new upload.

A Panel ``JSComponent``: its ESM module and the messages it sends (``on_msg``) are Panel's
public API for custom components; the browser reads the parameters below.
"""

from __future__ import annotations

import base64
import binascii
from collections.abc import Callable
from pathlib import Path

import panel as pn
import param
from panel.custom import JSComponent
from panel.io.state import set_curdoc

from .session import megabytes

__all__ = ["CHUNK_BYTES", "FileUpload"]

#: Bytes per chunk sent by the browser (base64 on the websocket: a third more).
CHUNK_BYTES = 256 * 1024
#: Longest file name taken (bytes of UTF-8 are not counted: characters).
MAX_NAME = 255


class FileUpload(JSComponent):
    """A drop area (or file chooser) for one file at a time, sent in counted chunks.

    Parameters
    ----------
    take : callable
        ``take(data: bytes, filename: str) -> str | None``: use a complete file; return
        None when it was taken, else why not (shown under the area).
    refuse : callable, optional
        ``refuse(message)`` for a file refused before ``take`` (too large, a broken
        transfer): the app's notification.
    **params
        ``accept``, ``prompt``, ``max_bytes``, layout parameters.
    """

    accept = param.String(default="", doc="What the file chooser offers (the input's "
                                          "accept: '.csv,text/csv').")
    prompt = param.String(default="Drop a file here, or click to choose one.")
    max_bytes = param.Integer(default=5_000_000, bounds=(1, None), constant=True,
                              doc="The largest file taken, in bytes.")
    chunk_bytes = param.Integer(default=CHUNK_BYTES, constant=True, bounds=(1, None))
    state = param.Selector(objects=["idle", "receiving", "accepted", "rejected"],
                           default="idle", doc="The last file's state, shown by the area.")
    message = param.String(default="", doc="What the area says about the last file.")
    ack = param.Integer(default=0, doc="Counts the server's answers: the browser sends its "
                                       "next message after each.")

    _esm = Path(__file__).with_name("upload.js")

    _stylesheets = ["""
    .mdcore-drop { display: flex; align-items: center; justify-content: center; gap: 10px;
                   min-height: 64px; padding: 8px 12px; box-sizing: border-box;
                   border: 2px dashed #9aa4ae; border-radius: 6px; background: #f6f7f8;
                   cursor: pointer; font-size: 14px; color: #333; text-align: center; }
    .mdcore-drop:hover, .mdcore-drop.mdcore-drop-over { border-color: #0072b5;
                                                       background: #eef5fb; }
    .mdcore-drop:focus-within { outline: 2px solid #0072b5; outline-offset: 2px; }
    .mdcore-drop input { position: absolute; width: 1px; height: 1px; opacity: 0; }
    .mdcore-drop progress { width: 120px; visibility: hidden; }
    .mdcore-drop-status { min-height: 1.4em; margin-top: 4px; font-size: 13px;
                          overflow-wrap: anywhere; }
    .mdcore-drop-status[data-state="receiving"] { color: #555; }
    .mdcore-drop-status[data-state="accepted"] { color: #1e7b34; }
    .mdcore-drop-status[data-state="rejected"] { color: #b00020; }
    """]

    def __init__(self, take: Callable[[bytes, str], str | None],
                 refuse: Callable[[str], object] | None = None, **params):
        super().__init__(**params)
        self._take = take
        self._refuse = refuse
        self._name: str | None = None           # the file being received
        self._size = 0                          # its announced size
        self._buffer = bytearray()
        self.on_msg(self._on_msg)

    # --- the browser's messages ---------------------------------------------------------
    def _on_msg(self, event) -> None:
        # Panel hands ``on_msg`` callbacks the event (its ``data`` is what the browser
        # sent) outside the Bokeh document's lock; ``take`` changes the app's Bokeh models,
        # which needs it (Bokeh refused the change otherwise, "we should have the lock when
        # the document changes", and the session broke). So the message is handled in a
        # next-tick callback of the document, which holds the lock, in the order the
        # messages came, and held (as the app's jobs hand back their results: main.py),
        # so that changes to Panel objects and to Bokeh models reach the page together.
        msg = getattr(event, "data", event)
        doc = pn.state.curdoc
        if doc is None or doc.session_context is None:
            self._received(msg)
            return

        def handle() -> None:
            with set_curdoc(doc), pn.io.hold(doc):
                self._received(msg)

        doc.add_next_tick_callback(handle)

    def _received(self, msg) -> None:
        """Handle one message of the browser (``upload.js``)."""
        if not isinstance(msg, dict):
            return
        if "start" in msg:
            self._start(msg.get("start"), msg.get("size"))
        elif "offset" in msg:
            self._chunk(msg.get("offset"), msg.get("data"))
        elif "end" in msg:
            self._end()
        else:
            return
        self.ack += 1

    def _start(self, name, size) -> None:
        self._drop()
        if not isinstance(name, str) or not name or len(name) > MAX_NAME:
            self._reject(f"The file name must be 1 to {MAX_NAME} characters; rename the "
                         "file and send it again.")
            return
        if isinstance(size, bool) or not isinstance(size, int) or size < 0:
            self._reject(f"{name}: the browser sent no file size; send the file again.")
            return
        if size > self.max_bytes:
            self._reject(f"{name} is {size:,} bytes, more than the "
                         f"{megabytes(self.max_bytes)} limit ({self.max_bytes:,} bytes); "
                         "nothing was taken.")
            return
        self._name, self._size = name, size
        self.param.update(state="receiving", message=f"{name}: receiving …")

    def _chunk(self, offset, data) -> None:
        name = self._name
        if name is None:
            return                               # not receiving (refused, or no start)
        if offset != len(self._buffer) or not isinstance(data, str):
            self._reject(f"{name}: the transfer broke off (a chunk out of order); send the "
                         "file again.")
            return
        if len(data) > 4 * -(-self.chunk_bytes // 3):          # base64 of one chunk
            self._reject(f"{name}: a chunk larger than {self.chunk_bytes:,} bytes arrived; "
                         "send the file again.")
            return
        try:
            self._buffer += base64.b64decode(data, validate=True)
        except (binascii.Error, ValueError):
            self._reject(f"{name}: the transfer was garbled; send the file again.")
            return
        if len(self._buffer) > min(self._size, self.max_bytes):
            self._reject(f"{name}: more than the announced {megabytes(self._size)} "
                         "arrived; nothing was taken.")

    def _end(self) -> None:
        name = self._name
        if name is None:
            return
        data, size = bytes(self._buffer), self._size
        self._drop()
        if len(data) != size:
            self._reject(f"{name}: {len(data):,} of {size:,} bytes arrived; send the file "
                         "again.")
            return
        why = self._take(data, name)
        if why:
            said = why if why.startswith(name) else f"{name}: {why}"  # the name once
            self.param.update(state="rejected", message=f"Not loaded: {said}")
        else:
            self.param.update(state="accepted", message=f"{name}: loaded.")

    # --- helpers --------------------------------------------------------------------------
    def _drop(self) -> None:
        self._name, self._size, self._buffer = None, 0, bytearray()

    def _reject(self, message: str) -> None:
        self._drop()
        self.param.update(state="rejected", message=message)
        if self._refuse is not None:
            self._refuse(message)
