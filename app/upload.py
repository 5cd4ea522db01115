"""A drop area whose file reaches the server in counted chunks (the Files tab's uploads),
a Panel ``JSComponent`` (public API: its ESM module ``upload.js`` and ``on_msg``).

The browser announces a file (name, size), then sends chunks of :data:`CHUNK_BYTES`, each
after the server answered the one before. The server counts what arrives: a file announced
or grown beyond ``max_bytes`` is refused at that message and its chunks dropped, so memory
never holds more than the cap, whatever a client sends. A complete file goes to ``take``;
the area shows the verdict as plain text, never markup.
"""

from __future__ import annotations

import base64
import binascii
from collections.abc import Callable
from pathlib import Path

import param
from panel.custom import JSComponent

from .session import megabytes
from .session_loop import next_tick

#: Bytes per chunk sent by the browser (base64 on the websocket: a third more).
CHUNK_BYTES = 256 * 1024
#: Longest file name taken (bytes of UTF-8 are not counted: characters).
MAX_NAME = 255


class FileUpload(JSComponent):
    """A drop area (or file chooser) for one file at a time. ``take(data, filename)`` uses a
    complete file and returns None, or why not (shown under the area); ``refuse(message)``
    reports a file refused before ``take`` (too large, a broken transfer)."""

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
    .mdcore-drop-status[data-state="receiving"],
    .mdcore-drop-status[data-state="sending"] { color: #555; }
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
        # Panel calls ``on_msg`` outside the document's lock, and ``take`` changes Bokeh
        # models, which needs it ("we should have the lock when the document changes"
        # broke the session). So each message is handled, in order, on the next tick
        # (with the lock, under ``hold``: Panel's and Bokeh's changes reach the page
        # together).
        msg = getattr(event, "data", event)
        next_tick(lambda: self._received(msg))

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
