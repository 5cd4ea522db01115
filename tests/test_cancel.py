"""Every long step reports progress between its chunks, and stops when that callback raises
(how the app's Cancel and a closed tab stop a job, :class:`mdcore.Cancelled`): a wave's
emulator fit, random walk and scoring, θ_MAP and the posterior draws, the φ̂ fit of
scenarios 1 and 2, and KOH's φ fit and chain.

Each test lets a step run to its k-th progress call and raises there: the step must stop
at once, with nothing cached from its unfinished work, and a second, uninterrupted call
gives what a call without progress gives.
"""

import warnings

import numpy as np
import pytest

from mdcore import Cancelled
from mdcore import _cases as cases
from mdcore._emulator import fit_emulator
from mdcore._history_matching import HistoryMatchResult, case_problem, next_wave
from mdcore._hyperfit import FitOptions, fit_hyperparameters
from mdcore._koh import KOHOptions, infer_koh
from mdcore._pipeline import Method, Settings, koh_phi_prior, run_method


class Stopper:
    """A progress callback that records the fractions and raises at call ``at``."""

    def __init__(self, at: int | None = None):
        self.at, self.fractions = at, []

    def __call__(self, fraction, *_message):
        self.fractions.append(float(fraction))
        if self.at is not None and len(self.fractions) >= self.at:
            raise Cancelled("stop")


@pytest.fixture(scope="module")
def shear5():
    case = cases.load("shear-5", seed=0)
    problem = case_problem(case, n_candidates=5_000, seed=0, convergence_ratio=0.001,
                           max_waves=3)
    first = next_wave(problem)
    return case, problem, first


def test_a_wave_reports_through_its_fit_walk_and_scoring_and_stops(shear5, monkeypatch):
    import mdcore._history_matching as hm_module
    _, problem, first = shear5
    monkeypatch.setattr(hm_module, "CHUNK_VALUES", 1000 * problem.z.size)  # 5 chunks
    seen = Stopper()
    wave = next_wave(problem, (first,), progress=seen)
    f = np.array(seen.fractions)
    assert np.all(np.diff(f) >= 0) and f.max() < 1.0
    assert np.any((f > 0.1) & (f < 0.4)), "no call during the emulator fit"
    assert np.any((f >= 0.4) & (f < 0.7)), "no call during the random walk"
    assert np.sum(f >= 0.7) >= 5, "no call between the scoring chunks"
    for at in (3, len(f) // 2, len(f) - 1):          # in the fit, the walk, the scoring
        with pytest.raises(Cancelled):
            next_wave(problem, (first,), progress=Stopper(at))
    again = next_wave(problem, (first,))
    np.testing.assert_array_equal(again.candidate_implausibility,
                                  wave.candidate_implausibility)


def test_the_emulator_fit_stops_between_optimiser_iterations(shear5):
    _, problem, first = shear5
    em = first.emulator
    seen = Stopper()
    fit_emulator(problem.X, em.theta_train, em.y_train, problem.bounds, seed=0, progress=seen)
    assert len(seen.fractions) >= 10
    with pytest.raises(Cancelled):
        fit_emulator(problem.X, em.theta_train, em.y_train, problem.bounds, seed=0,
                     progress=Stopper(5))


def test_theta_map_and_posterior_draws_stop_and_keep_nothing(shear5):
    _, problem, first = shear5
    hm = HistoryMatchResult(problem, (first,))
    with pytest.raises(Cancelled):
        hm.compute_theta_map(Stopper(4))
    assert "theta_map" not in vars(hm)                      # nothing half-done is kept
    seen = Stopper()
    found = hm.compute_theta_map(seen)
    assert len(seen.fractions) >= 5
    np.testing.assert_array_equal(found, HistoryMatchResult(problem, (first,)).theta_map)
    with pytest.raises(Cancelled):
        hm.posterior_samples(50, seed=1, progress=Stopper(3))
    np.testing.assert_array_equal(hm.posterior_samples(50, seed=1),
                                  HistoryMatchResult(problem, (first,)).posterior_samples(
                                      50, seed=1))


def test_the_phi_hat_fit_stops_in_the_swarm_and_in_the_polish():
    rng = np.random.default_rng(0)
    X = np.linspace(0, 1, 30)[:, None]
    Y = np.sin(3 * X)
    z = (Y + 0.3 * X)[:, 0] + 0.01 * rng.standard_normal(30)
    seen = Stopper()
    options = FitOptions(n_iterations=20)
    fit = fit_hyperparameters(Y, X, z, seed=0, options=options, progress=seen)
    f = np.array(seen.fractions)
    assert np.sum(f < 0.5) == 20 and np.sum(f >= 0.5) >= 3          # swarm, then polish
    for at in (5, 22):
        with pytest.raises(Cancelled):
            fit_hyperparameters(Y, X, z, seed=0, options=options, progress=Stopper(at))
    again = fit_hyperparameters(Y, X, z, seed=0, options=options)
    np.testing.assert_array_equal(again.log_params, fit.log_params)


def test_koh_stops_in_its_phi_fit_and_in_its_chain():
    case = cases.load("beam-1d", seed=0)
    first = next_wave(case_problem(case, n_candidates=2000, seed=0))
    kw = dict(theta_prior=case.theta_prior, bounds=case.theta_bounds, seed=0,
              options=KOHOptions(n_iter=2000, burn_in=500, phi_prior=koh_phi_prior(case)))
    seen = Stopper()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        infer_koh(first.emulator, case.X_train, case.z_train, progress=seen, **kw)
    f = np.array(seen.fractions)
    in_fit = int(np.sum(f < 0.05))
    assert in_fit >= 5 and np.sum(f > 0.05) >= 50                  # φ fit, then the chain
    for at in (3, in_fit + 20):
        with pytest.raises(Cancelled):
            infer_koh(first.emulator, case.X_train, case.z_train, progress=Stopper(at), **kw)


@pytest.mark.parametrize("method", [Method.S1, Method.S2, Method.KOH])
def test_run_method_stops_when_cancel_is_set_mid_run(shear5, method):
    """The pipeline's cancel event reaches every step above: set at the k-th progress
    report, the run ends with Cancelled at that report's next check."""
    import threading
    case, problem, first = shear5
    hm = HistoryMatchResult(problem, (first,))
    cancel, calls = threading.Event(), []

    def progress(fraction, message):
        calls.append(message)
        if len(calls) == 3:
            cancel.set()

    settings = Settings(n_s=20, n_phi=5, n_iter=2000, burn_in=500)
    with pytest.raises(Cancelled), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        run_method(case, hm, method, settings, seed=0, progress=progress, cancel=cancel)
    assert len(calls) == 3
