"""The one thread policy: one pool of compute threads, and BLAS at one thread for good.

(Whether OpenBLAS honours a limit set from a worker thread depends on its build, so the
BLAS limit is asserted in a subprocess that starts with two BLAS threads.)"""

import os
import subprocess
import sys
import threading

import numpy as np
import pytest

from mdcore import _linalg as linalg
from mdcore import _threads as threads


def test_pieces_run_once_in_order_on_one_pool(monkeypatch):
    monkeypatch.setenv(threads.THREADS_ENV, "2")
    seen: list[tuple[str, int]] = []

    def work(a, b):
        seen.append((threading.current_thread().name, threading.get_ident()))
        return np.arange(a, b).sum()

    pieces = [(0, 4), (4, 8), (8, 12)]
    for _ in range(3):                              # the same two threads every time
        assert threads.run_pieces(work, pieces) == [6, 22, 38]
    assert all(name.startswith("mdcore") for name, _ in seen)
    assert len({ident for _, ident in seen}) <= 2
    out = np.zeros(12)

    def chunk(sl, multi, n):
        out[sl] += np.arange(sl.start, sl.stop)

    linalg.for_each_chunk(chunk, linalg.chunks((12,), linalg.CHUNK_BYTES / 4))
    np.testing.assert_array_equal(out, np.arange(12))          # every chunk exactly once


def test_one_thread_and_nested_calls_run_in_the_calling_thread(monkeypatch):
    caller = threading.current_thread().name
    monkeypatch.setenv(threads.THREADS_ENV, "1")
    assert threads.run_pieces(lambda: threading.current_thread().name, [(), ()]) == [caller] * 2
    monkeypatch.setenv(threads.THREADS_ENV, "2")

    def outer(i):                       # work that queues work: no deadlock, runs inline
        me = threading.current_thread().name
        return threads.run_pieces(lambda: threading.current_thread().name == me, [(), ()])

    assert threads.run_pieces(outer, [(0,), (1,)]) == [[True, True], [True, True]]


@pytest.mark.parametrize("value", ["0", "-2", "two"])
def test_thread_count_from_the_environment(monkeypatch, value):
    monkeypatch.setenv(threads.THREADS_ENV, "3")
    assert threads.num_threads() == 3
    monkeypatch.setenv(threads.THREADS_ENV, value)
    with pytest.raises(ValueError, match="MDCORE_NUM_THREADS must be a positive integer"):
        threads.num_threads()


def test_an_entry_point_limits_blas_to_one_thread_for_good():
    code = """
import threading
import numpy as np
from threadpoolctl import threadpool_info
from mdcore import _gp as gp
blas = lambda: sorted(i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas")
before = blas()
X = np.linspace(0, 1, 20)[:, None]; Y = np.sin(3 * X); z = (Y + X)[:, 0]
lp = np.tile([0.0, 0.0, 0.0, -2.0], (50, 1))
jobs = [threading.Thread(target=gp.neg_log_marginal_likelihood, args=(lp, Y, X, z))
        for _ in range(2)]
[j.start() for j in jobs]; [j.join() for j in jobs]
print(before, blas())
"""
    env = dict(os.environ, OPENBLAS_NUM_THREADS="2")           # two, even on one core
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120, check=True, env=env).stdout.split("] [")
    before = [int(n) for n in out[0].strip("[] \n").split(",")]
    after = [int(n) for n in out[1].strip("[] \n").split(",")]
    assert before == [2] * len(before) and after == [1] * len(before)
