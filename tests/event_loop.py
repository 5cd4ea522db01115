"""Play an app session's event loop in a test: run the callbacks a JobRunner scheduled."""

import queue
import time


def drain(inbox: queue.Queue, until, timeout: float = 30.0) -> None:
    """Run scheduled callbacks on this thread until ``until()`` holds; fail after
    ``timeout`` seconds."""
    end = time.monotonic() + timeout
    while not until():
        if time.monotonic() > end:
            raise AssertionError("condition not reached before the timeout")
        try:
            inbox.get(timeout=0.05)()
        except queue.Empty:
            pass
