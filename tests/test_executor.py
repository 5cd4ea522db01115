"""Pair chunks of scenarios 2–3 on executors: threads, processes and a real Dask
LocalCluster give the serial run's numbers exactly (issue 19, item 1)."""

import multiprocessing
import warnings
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor

import numpy as np
import pytest
from conftest import missing

from mdcore import _cases as cases
from mdcore import _discrepancy as discrepancy
from mdcore._discrepancy import DiscrepancyOptions, infer_discrepancy
from mdcore._history_matching import history_match_case
from mdcore._pipeline import Settings, run_method
from mdcore._reproduce import reproduce, run_case

SMALL = Settings(n_s=40, n_phi=20, n_iter=2000, burn_in=500)
HM = dict(n_candidates=5000, max_waves=2)


@pytest.fixture(scope="module")
def beam():
    case = cases.load("beam-1d", seed=0)
    hm = history_match_case(case, n_candidates=20_000, seed=0)
    return case, hm, hm.posterior_samples(60, seed=0)


@pytest.fixture
def small_chunks(monkeypatch):
    """Many chunks at test sizes (the layout is the caller's; workers only compute)."""
    monkeypatch.setattr(discrepancy, "WEIGHT_PAIRS", 700)        # 35 θ rows × 20 draws
    monkeypatch.setattr(discrepancy, "MIN_FUSED_BLOCK", 64)
    monkeypatch.setattr(discrepancy, "BLOCK_BYTES", 2**20)       # ~90 pairs on NumPy
    monkeypatch.setattr(discrepancy, "IN_FLIGHT", 3)             # the window moves
    monkeypatch.setattr(discrepancy, "KEEP_DRAWS_BYTES", 0)      # φ drawn again per block


def fit(beam, scenario, executor=None, **kwargs):
    case, hm, theta = beam
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        options = DiscrepancyOptions(n_phi=20, phi_prior=case.phi_prior, **kwargs)
        model = infer_discrepancy(case.simulate, theta, case.X_train, case.z_train,
                                  scenario=scenario, theta_map=hm.theta_map, seed=3,
                                  options=options, executor=executor)
        return model, model.predict(case.X_test, executor=executor, prune=0.0)


def assert_same(a, b):
    (ma, pa), (mb, pb) = a, b
    np.testing.assert_array_equal(ma.log_weights, mb.log_weights)
    np.testing.assert_array_equal(ma.log_params, mb.log_params)
    for x, y in zip(pa, pb):
        np.testing.assert_array_equal(x, y)


@pytest.mark.parametrize("backend", ["numba", "numpy"])
@pytest.mark.parametrize("scenario, proposal", [(2, "prior"), (3, "prior"), (3, "adaptive")])
def test_thread_pool_equals_serial(beam, small_chunks, scenario, proposal, backend):
    if backend == "numba":
        pytest.importorskip("numba")
    serial = fit(beam, scenario, backend=backend, proposal=proposal)
    with ThreadPoolExecutor(2) as pool:
        assert_same(fit(beam, scenario, pool, backend=backend, proposal=proposal), serial)


@pytest.mark.parametrize("start", ["fork", "spawn"])
def test_process_pool_pickles_the_chunks(beam, small_chunks, start):
    """Module-level functions on plain arrays: process pools (plain pickle) give the same
    numbers, spawned (fresh interpreters) or forked after the compiled backend's compute
    threads have started in this process (they are not inherited; see
    the fork hook of ``mdcore._threads``)."""
    if start not in multiprocessing.get_all_start_methods():
        missing(f"no {start} start method here")
    serial = fit(beam, 3)                     # starts the compute threads here first
    workers = 2 if start == "fork" else 1     # a spawned worker imports numba: keep it one
    with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context(start)) as pool:
        assert_same(fit(beam, 3, pool), serial)


@pytest.fixture(scope="module")
def dask_executor():
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster, \
            distributed.Client(cluster) as client:
        yield client.get_executor()


@pytest.mark.parametrize("scenario", [2, 3])
def test_dask_local_cluster_equals_serial(beam, small_chunks, dask_executor, scenario):
    serial = fit(beam, scenario)
    assert_same(fit(beam, scenario, dask_executor), serial)


def test_dask_local_cluster_equals_serial_at_the_default_chunks(beam, dask_executor):
    assert_same(fit(beam, 3, dask_executor), fit(beam, 3))


def run_dicts(executor=None):
    case = cases.load("beam-1d", seed=0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        run = run_case(case, methods=(1, 2, 3), settings=SMALL, seed=0, executor=executor,
                       **HM)
    d = run.to_dict()
    for entry in d["methods"].values():
        entry.pop("seconds")
    return run, d


@pytest.fixture(scope="module")
def serial_run():
    return run_dicts()


def assert_runs_equal(a, b):
    (run_a, dict_a), (run_b, dict_b) = a, b
    assert dict_a == dict_b
    for x, y in zip(run_a.results, run_b.results):
        for u, v in zip(x.on_test, y.on_test):
            np.testing.assert_array_equal(u, v)
    np.testing.assert_array_equal(run_a.hm.theta_map, run_b.hm.theta_map)


def test_run_case_with_a_thread_pool_equals_serial(serial_run):
    with ThreadPoolExecutor(2) as pool:
        assert_runs_equal(run_dicts(pool), serial_run)


def test_run_case_on_a_dask_local_cluster_equals_serial(serial_run, dask_executor):
    assert_runs_equal(run_dicts(dask_executor), serial_run)


def test_run_method_passes_the_executor_to_the_pair_chunks(beam, small_chunks):
    case, hm, _ = beam

    class Counting(ThreadPoolExecutor):
        submitted = 0

        def submit(self, fn, *args, **kwargs):
            Counting.submitted += 1
            return super().submit(fn, *args, **kwargs)

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        serial = run_method(case, hm, 3, SMALL, seed=0)
        with Counting(2) as pool:
            par = run_method(case, hm, 3, SMALL, seed=0, executor=pool)
    assert Counting.submitted >= 4                      # weight chunks and predict blocks
    for u, v in zip(par.on_test, serial.on_test):
        np.testing.assert_array_equal(u, v)
    assert par.metrics == serial.metrics and par.importance == serial.importance


def test_cancel_stops_and_cancels_the_queued_chunks(beam, small_chunks):
    case, hm, theta = beam

    class Stop(Exception):
        pass

    def cancel(fraction):
        raise Stop

    with ThreadPoolExecutor(1) as pool:
        with pytest.raises(Stop):
            infer_discrepancy(case.simulate, theta, case.X_train, case.z_train, scenario=3, seed=0, executor=pool,
                              progress=cancel,
        options=DiscrepancyOptions(n_phi=20, phi_prior=case.phi_prior))
        assert pool.submit(int, "7").result() == 7      # the pool is still usable


@pytest.mark.parametrize("bad", [object(), "dask://localhost:8786", 4])
def test_bad_executor_is_refused_by_name(beam, bad):
    case, hm, theta = beam
    match = "executor must be a concurrent.futures.Executor"
    with pytest.raises(ValueError, match=match):
        infer_discrepancy(case.simulate, theta, case.X_train, case.z_train, scenario=3, executor=bad,
        options=DiscrepancyOptions(n_phi=2, phi_prior=case.phi_prior))
    model = infer_discrepancy(case.simulate, theta, case.X_train, case.z_train, scenario=2,
                              theta_map=hm.theta_map,
        options=DiscrepancyOptions(log_params_hat=np.zeros((1, 4))))
    with pytest.raises(ValueError, match=match):
        model.predict(case.X_test, executor=bad)
    with pytest.raises(ValueError, match=match):
        run_method(case, hm, 2, SMALL, seed=0, executor=bad)
    with pytest.raises(ValueError, match=match):
        run_case(case, methods=(1,), settings=SMALL, executor=bad)
    with pytest.raises(ValueError, match=match):
        reproduce("beam-1d", methods=(1,), settings=SMALL, executor=bad)
