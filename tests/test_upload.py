"""The drop areas' transport (app/upload.py): a file arrives in counted chunks, and nothing
a client sends makes the server hold more than the cap.

These drive the server side with the messages the page sends (``upload.js``); the browser
tests (tests/test_app_security.py) send real files through the page.
"""

import base64

import pytest

pytest.importorskip("panel")
from mdcore_app.upload import CHUNK_BYTES, FileUpload  # noqa: E402

FIVE_HUNDRED = base64.b64encode(b"x" * 500).decode()


def area(max_bytes=1000, verdict=None):
    taken, refused = [], []

    def take(data, name):
        taken.append((name, data))
        return verdict

    return FileUpload(take=take, refuse=refused.append, max_bytes=max_bytes), taken, refused


def send(upload, data: bytes, name="a.csv", size=None, chunk=CHUNK_BYTES):
    """What the page sends for ``data``: start, chunks, end (stopping once refused)."""
    upload._received({"start": name, "size": len(data) if size is None else size})
    for offset in range(0, len(data), chunk):
        if upload.state != "receiving":
            return
        upload._received({"offset": offset,
                          "data": base64.b64encode(data[offset:offset + chunk]).decode()})
    if upload.state == "receiving":
        upload._received({"end": name})


def test_a_file_in_many_chunks_arrives_whole_and_is_taken():
    upload, taken, refused = area(max_bytes=10_000)
    data = bytes(range(256)) * 30                                    # 7,680 bytes
    acks = upload.ack
    send(upload, data, chunk=1000)                                   # 8 chunks
    assert taken == [("a.csv", data)] and refused == []
    assert upload.state == "accepted" and upload.message == "a.csv: loaded."
    assert upload.ack == acks + 10                                   # start, 8 chunks, end
    send(upload, data)                                               # the same file again
    assert len(taken) == 2 and upload.state == "accepted"


def test_a_file_refused_by_its_taker_says_why():
    upload, taken, _ = area(verdict="line 2: 'x' is not a number.")
    send(upload, b"x,y\n1,x\n")
    assert upload.state == "rejected"
    assert upload.message == "Not loaded: a.csv: line 2: 'x' is not a number."


def test_a_file_announced_over_the_cap_is_refused_before_any_chunk():
    upload, taken, refused = area(max_bytes=1000)
    upload._received({"start": "big.csv", "size": 1001})
    message = ("big.csv is 1,001 bytes, more than the 1,000 bytes limit (1,000 bytes); "
               "nothing was taken.")
    assert upload.state == "rejected" and refused == [message] and upload.message == message
    upload._received({"offset": 0, "data": base64.b64encode(b"x" * 500).decode()})
    upload._received({"end": "big.csv"})
    assert taken == [] and len(upload._buffer) == 0


@pytest.mark.parametrize("messages, problem", [
    # more than announced: a client that never ends its file
    ([{"start": "a.csv", "size": 600}] + [{"offset": 500 * k, "data": FIVE_HUNDRED}
                                           for k in range(3)], "more than the announced"),
    ([{"start": "a.csv", "size": 600}, {"offset": 7, "data": "eA=="}], "out of order"),
    ([{"start": "a.csv", "size": 600}, {"offset": 0, "data": "not base64!"}], "garbled"),
    ([{"start": "a.csv", "size": 600}, {"offset": 0, "data": 12}], "out of order"),
    ([{"start": "a.csv", "size": 4},
      {"offset": 0, "data": base64.b64encode(b"x" * (CHUNK_BYTES + 3)).decode()}],
     "a chunk larger than"),
    ([{"start": "a.csv", "size": 600}, {"offset": 0, "data": "eA=="}, {"end": "a.csv"}],
     "1 of 600 bytes arrived"),
    ([{"start": "a.csv", "size": -1}], "no file size"),
    ([{"start": "a.csv", "size": "600"}], "no file size"),
    ([{"start": "", "size": 6}], "file name must be"),
    ([{"start": "x" * 256, "size": 6}], "file name must be"),
], ids=["never-ending", "out-of-order", "garbled", "not-text", "huge-chunk", "short",
        "negative-size", "text-size", "no-name", "long-name"])
def test_a_broken_or_hostile_transfer_is_refused_and_dropped(messages, problem):
    upload, taken, refused = area(max_bytes=1000)
    for message in messages:
        upload._received(message)
    assert upload.state == "rejected" and problem in upload.message
    assert refused == [upload.message] and taken == []
    assert len(upload._buffer) == 0                  # nothing kept of the refused file


def test_messages_outside_a_transfer_are_ignored():
    upload, taken, refused = area()
    for message in ({"offset": 0, "data": "eA=="}, {"end": "a.csv"}, "text", [1, 2],
                    {"unknown": 1}, None):
        upload._received(message)
    assert upload.state == "idle" and taken == [] and refused == []
