"""Simulator runs over executors, with failing runs dropped and reported."""

import threading
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor

import numpy as np
import pytest

from mdcore import _cases as cases
from mdcore._runs import run_simulator

RELEASE = threading.Event()           # lets a "hanging" simulator finish after a test


def picky(X, theta):
    """Fails (raises) where θ₀ < 0, returns NaN where θ₀ > 10; else a smooth function."""
    theta = np.atleast_2d(theta)
    if np.any(theta[:, 0] < 0):
        raise ValueError("negative stiffness")
    y = np.sin(X[None, :, 0] * theta[:, :1]) + theta[:, 1:2]
    y[theta[:, 0] > 10] = np.nan
    return y[..., None]


def hangs_above_five(X, theta):
    if np.any(np.atleast_2d(theta)[:, 0] > 5):
        RELEASE.wait(30)
    return picky(X, theta)


def wrong_shape(X, theta):
    return np.zeros((len(theta), len(X)))


X = np.linspace(0, 1, 4)[:, None]
THETA = np.array([[1.0, 0.0], [-1.0, 0.0], [2.0, 1.0], [11.0, 0.0], [3.0, -1.0]])


def test_failures_are_isolated_and_ordered():
    out = run_simulator(picky, X, THETA, 1)
    np.testing.assert_array_equal(out.ok, [True, False, True, False, True])
    ok_theta = THETA[out.ok]
    np.testing.assert_array_equal(out.y, picky(X, ok_theta))
    assert [f.message for f in out.failures] == ["ValueError: negative stiffness",
                                                 "returned NaN or inf"]
    np.testing.assert_array_equal(out.failures[0].theta, [-1.0, 0.0])
    empty = run_simulator(picky, X, np.empty((0, 2)), 1)
    assert empty.y.shape == (0, 4, 1) and empty.failures == ()


@pytest.mark.parametrize("make", [lambda: ThreadPoolExecutor(2), lambda: ProcessPoolExecutor(2)])
@pytest.mark.parametrize("batch_size", [None, 2])
def test_executors_give_the_serial_numbers(make, batch_size):
    serial = run_simulator(picky, X, THETA, 1)
    with make() as pool:
        par = run_simulator(picky, X, THETA, 1, executor=pool, batch_size=batch_size)
    np.testing.assert_array_equal(par.y, serial.y)
    np.testing.assert_array_equal(par.ok, serial.ok)
    assert [f.message for f in par.failures] == [f.message for f in serial.failures]


def test_timeout_counts_as_failure():
    try:
        out = run_simulator(hangs_above_five, X, THETA[[0, 3, 4]], 1, batch_size=1,
                            timeout=0.3)
        np.testing.assert_array_equal(out.ok, [True, False, True])
        assert out.failures[0].message == "timed out after 0.3 s"
    finally:
        RELEASE.set()


def test_bad_input():
    with pytest.raises(ValueError, match=r"must return shape \(n_theta, N, n_out\) = \(5, 4, 1\)"):
        run_simulator(wrong_shape, X, THETA, 1)
    with pytest.raises(ValueError, match="simulate must be callable"):
        run_simulator("beam", X, THETA, 1)
    with pytest.raises(ValueError, match="timeout must be a positive number"):
        run_simulator(picky, X, THETA, 1, timeout=0)
    with pytest.raises(ValueError, match="batch_size must be an integer ≥ 1"):
        run_simulator(picky, X, THETA, 1, batch_size=0)
    with pytest.raises(ValueError, match="theta contains 1 NaN"):
        run_simulator(picky, X, [[np.nan, 0.0]], 1)


def beam_failing_on_short_cracks(X, theta):
    """beam-1d's simulator, failing for crack lengths below 8 mm (part of the box)."""
    theta = np.atleast_2d(theta)
    if np.any(theta[:, 0] < 8.0):
        raise RuntimeError("mesh generation failed")
    return cases.load("beam-1d").simulate(X, theta)


def test_history_match_survives_a_simulator_failing_on_part_of_the_box():
    from mdcore._history_matching import history_match_case, setup, setup_arguments
    case = cases.load("beam-1d")
    hm = history_match_case(case, n_candidates=5000, max_waves=2, convergence_ratio=0.05)
    failing = setup(beam_failing_on_short_cracks, case.X_train, case.z_train,
                    case.theta_bounds, **setup_arguments(dict(
                        V_o=case.noise_var, V_m=case.V_m, initial_design=case.initial_design,
                        n_candidates=5000, max_waves=2, convergence_ratio=0.05)))
    from mdcore._history_matching import iter_waves
    waves = list(iter_waves(failing))
    w1 = waves[0]
    assert len(w1.failures) == 5                          # l_cr = 0 on the 5 × 5 grid
    assert all(f.theta[0] < 8 and "mesh generation failed" in f.message for f in w1.failures)
    assert len(w1.runs_theta) == 20 and np.all(w1.runs_theta[:, 0] >= 8)
    assert "5 of 25 simulator runs failed and were dropped" in w1.message
    # Fewer runs near l_cr = 0 leave the emulator less sure there, so NROY can only be as
    # large or larger; the truth stays in, and every failure is where the simulator fails.
    assert w1.nroy_fraction >= hm.waves[0].nroy_fraction - 0.02
    from mdcore._history_matching import HistoryMatchResult
    assert HistoryMatchResult(failing, tuple(waves)).contains(case.theta_true)[0]
    assert all(f.theta[0] < 8 for w in waves for f in w.failures)
    assert waves[1].nroy_fraction < w1.nroy_fraction
    # Failing on most of the box is an error that names the first failure.
    strict = setup(beam_failing_on_short_cracks, case.X_train, case.z_train, case.theta_bounds,
                   **setup_arguments(dict(V_o=case.noise_var, V_m=case.V_m,
                                          initial_design=case.initial_design,
                                          n_candidates=5000, max_failed_fraction=0.1)))
    with pytest.raises(ValueError, match=r"wave 1: 5 of 25 simulator runs failed \(at most "
                                         r"10% may\); the first at θ = \[ 0\. 50\.\]: "
                                         "RuntimeError: mesh generation failed"):
        list(iter_waves(strict))


def test_history_match_with_an_executor_equals_serial():
    from mdcore._history_matching import history_match_case
    case = cases.load("beam-2d")
    serial = history_match_case(case, n_candidates=4000, max_waves=2, convergence_ratio=0.01)
    with ThreadPoolExecutor(2) as pool:
        par = history_match_case(case, n_candidates=4000, max_waves=2, convergence_ratio=0.01,
                                 executor=pool, batch_size=3)
    assert len(par.waves) == len(serial.waves)
    for a, b in zip(par.waves, serial.waves):
        np.testing.assert_array_equal(a.nroy, b.nroy)
        np.testing.assert_array_equal(a.runs_theta, b.runs_theta)


def test_history_match_on_a_dask_local_cluster_equals_serial():
    distributed = pytest.importorskip("distributed")
    from mdcore._history_matching import history_match_case
    case = cases.load("beam-1d")
    serial = history_match_case(case, n_candidates=4000, max_waves=2, convergence_ratio=0.05)
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster, \
            distributed.Client(cluster) as client:
        remote = history_match_case(case, n_candidates=4000, max_waves=2,
                                    convergence_ratio=0.05, executor=client.get_executor())
    for a, b in zip(remote.waves, serial.waves):
        np.testing.assert_array_equal(a.nroy, b.nroy)
    np.testing.assert_array_equal(remote.theta_map, serial.theta_map)
