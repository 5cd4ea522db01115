"""The BLAS limit is reference-counted: concurrent jobs leave the process as they found it.

(Whether OpenBLAS honours a limit set from a worker thread depends on its build: the one
NumPy and SciPy ship ignores it once its thread server runs, so the limit is asserted
from the main thread only.)"""

import os
import subprocess
import sys
import threading

import numpy as np
from threadpoolctl import threadpool_info

from mdcore import gp
from mdcore.threads import single_threaded_blas


def blas_threads():
    return sorted(i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas")


def test_two_concurrent_jobs_restore_the_blas_thread_count():
    before = blas_threads()
    assert before, "NumPy's BLAS is not visible to threadpoolctl"
    rng = np.random.default_rng(0)
    X = np.linspace(0, 1, 20)[:, None]
    Y = np.sin(3 * X)
    z = (Y + X)[:, 0]
    lp = rng.normal(scale=0.3, size=(400, 4))
    lp[:, -1] = -2.0
    start = threading.Barrier(2)

    def job():
        start.wait(timeout=30)
        for _ in range(15):
            gp.neg_log_marginal_likelihood(lp, Y, X, z)
            gp.predict(lp[:50], Y, X, z, Y, X)

    threads = [threading.Thread(target=job) for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=120)
    assert not any(t.is_alive() for t in threads)
    assert blas_threads() == before


def test_nested_calls_keep_the_limit_until_the_outermost_returns():
    before = blas_threads()

    @single_threaded_blas
    def inner():
        return blas_threads()

    @single_threaded_blas
    def outer():
        first = inner()
        return first, blas_threads()

    first, after_inner = outer()
    assert set(first) == {1} and set(after_inner) == {1}
    assert blas_threads() == before


def test_the_process_wide_limit_outlasts_a_section_that_began_before_it():
    # In a subprocess: the limit is process-wide and not undone.
    code = """
import threading
from threadpoolctl import threadpool_info
from mdcore import threads
blas = lambda: sorted(i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas")
before = blas()
inside, go = threading.Event(), threading.Event()
@threads.single_threaded_blas
def section():
    inside.set()
    go.wait(30)
t = threading.Thread(target=section)
t.start()
inside.wait(30)
threads.single_threaded_blas_for_process()
threads.single_threaded_blas_for_process()
go.set()
t.join(30)
threads.single_threaded_blas(blas)()
print(before, blas())
"""
    env = dict(os.environ, OPENBLAS_NUM_THREADS="2")           # two, even on one core
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120, check=True, env=env).stdout.split("] [")
    before = [int(n) for n in out[0].strip("[] \n").split(",")]
    after = [int(n) for n in out[1].strip("[] \n").split(",")]
    assert before == [2] * len(before) and after == [1] * len(before)
