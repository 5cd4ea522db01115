"""The BLAS limit is reference-counted: concurrent jobs leave the process as they found it.

(Whether OpenBLAS honours a limit set from a worker thread depends on its build: the one
NumPy and SciPy ship ignores it once its thread server runs, so the limit is asserted
from the main thread only.)"""

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
