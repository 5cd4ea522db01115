"""A battery of bad inputs (issue 19, item 3): the public API, the command line and the app.

Every case is a distinct test id. Each asserts

(a) a ``ValueError`` whose message names the argument (or the file's key, or the app's field)
    and says what was expected and what was received, and
(b) that nothing changed: the API leaves its input arrays as they were, the command line
    exits with 2 and writes no file, the app keeps its settings and results.

Sizes that would need more memory than a machine has (``10**12`` samples) must be refused
before any work starts; those cases replace the heavy step by :func:`_attempted`, so a
regression fails at once instead of exhausting the machine.
"""

from __future__ import annotations

import dataclasses
import importlib
import re
import textwrap
import warnings
from functools import cached_property
from pathlib import Path

import numpy as np
import pytest

from mdcore import (
    _cases as cases,
)
from mdcore import (
    _export as export,
)
from mdcore import (
    _gp as gp,
)
from mdcore import (
    _importance as importance,
)
from mdcore import (
    _kernels as kernels,
)
from mdcore import (
    _koh as koh,
)
from mdcore import (
    _metrics as metrics,
)
from mdcore import (
    _runs as runs,
)
from mdcore._case_file import CaseFileError, load_case_file
from mdcore._cli import main
from mdcore._discrepancy import DiscrepancyOptions, infer_discrepancy
from mdcore._history_matching import (
    elementwise_implausibility,
    history_match,
    history_match_case,
    setup_arguments,
)
from mdcore._history_matching import setup as hm_setup
from mdcore._pipeline import Settings, run_method

HUGE = 10**12


def setup(simulate, X, z, bounds, **kwargs):
    """:func:`mdcore._history_matching.setup` with the options' fields by name."""
    return hm_setup(simulate, X, z, bounds, **setup_arguments(kwargs))


class Attempted(Exception):
    """Raised by a stand-in for heavy work that a bad input should never have reached."""


def _attempted(*args, **kwargs):
    raise Attempted("the work was attempted; the bad input should have been refused up front")


def guard(monkeypatch, *targets: str) -> None:
    """Replace each ``"module:attribute"`` by :func:`_attempted`."""
    for target in targets:
        module, attr = target.split(":")
        monkeypatch.setattr(importlib.import_module(module), attr, _attempted)


# ---------------------------------------------------------------------------------------
# Inputs

def toy(X, theta):
    """y = θ₁ sin(2πx) + θ₂ (closed form), (n_theta, N, 1)."""
    theta = np.atleast_2d(theta)
    return (theta[:, 0, None] * np.sin(2 * np.pi * X[None, :, 0]) + theta[:, 1, None])[..., None]


def toy_wrong_shape(X, theta):
    return np.zeros((len(theta), len(X)))                 # the output axis is missing


def toy_all_nan(X, theta):
    return np.full((len(theta), len(X), 1), np.nan)


X8 = np.linspace(0.05, 0.95, 8)[:, None]
Z8 = toy(X8, [[1.2, 0.3]])[0] + 0.05 * np.random.default_rng(0).standard_normal((8, 1))
BOUNDS = np.array([[0.0, 2.0], [-1.0, 1.0]])
HM_OPTIONS = dict(V_m=0.01, V_o=0.0025, n_candidates=200, max_waves=1)

X6 = np.linspace(0.0, 1.0, 6)[:, None]
Y6 = np.sin(3 * X6)
Z6 = (Y6 + X6)[:, 0]
LP = np.array([0.0, 0.0, 0.0, -2.0])


def with_value(a, index, value):
    out = np.array(a, dtype=float)
    out[index] = value
    return out


class Context:
    """Objects some cases need, built once per module and only when asked for."""

    @cached_property
    def case(self):
        return cases.load("beam-1d")

    @cached_property
    def hm(self):
        return history_match_case(self.case, n_candidates=2000, max_waves=1)

    @cached_property
    def ruled_out(self):
        result = history_match_case(self.case, n_candidates=2000, max_waves=1, V_m=1e-7,
                                    threshold=0.5)
        assert result.status == "ruled_out"
        return result


@pytest.fixture(scope="module")
def ctx():
    return Context()


def arrays_in(obj, path: str = "", depth: int = 0) -> dict:
    """Copies of every array reachable from ``obj`` (arguments, lists, dataclass fields)."""
    out: dict = {}
    if isinstance(obj, np.ndarray):
        out[path] = obj.copy()
    elif depth > 4 or callable(obj):
        pass
    elif isinstance(obj, (list, tuple)):
        for i, v in enumerate(obj):
            out.update(arrays_in(v, f"{path}[{i}]", depth + 1))
    elif isinstance(obj, dict):
        for k, v in obj.items():
            out.update(arrays_in(v, f"{path}[{k!r}]", depth + 1))
    elif dataclasses.is_dataclass(obj):
        for f in dataclasses.fields(obj):
            out.update(arrays_in(getattr(obj, f.name), f"{path}.{f.name}", depth + 1))
    return out


def assert_unchanged(before: dict, obj) -> None:
    after = arrays_in(obj)
    assert after.keys() == before.keys()
    for key, value in before.items():
        np.testing.assert_array_equal(after[key], value, err_msg=f"{key} was modified")


# ---------------------------------------------------------------------------------------
# The public API: (id, make(ctx) -> (function, args, kwargs), match, guards)

def _call(fn, *args, **kwargs):
    return fn, args, kwargs



API = [
    # --- mdcore._gp ---------------------------------------------------------------------
    ("gp.predict-X-1d", lambda c: _call(gp.predict, LP, Y6, X6[:, 0], Z6, Y6, X6),
     r"X must have 2 dimension\(s\); received shape \(6,\)", ()),
    ("gp.nlml-z-nan", lambda c: _call(gp.neg_log_marginal_likelihood, LP, Y6, X6,
                                      with_value(Z6, 2, np.nan)),
     r"z contains 1 NaN or infinite value\(s\)", ()),
    ("gp.nlml-z-wrong-length", lambda c: _call(gp.neg_log_marginal_likelihood, LP, Y6, X6,
                                               Z6[:5]),
     r"z must have shape \(N,\) = \(6,\) to match X \(6, 1\); received \(5,\)", ()),
    ("gp.nlml-log_params-wrong-P", lambda c: _call(gp.neg_log_marginal_likelihood, LP[:3], Y6,
                                                   X6, Z6),
     r"log_params must have last dimension P = 2 \+ d_y \+ d_x = 2 \+ 1 \+ 1 = 4 .*"
     r"received shape \(3,\)", ()),
    ("gp.predict-Y-inf", lambda c: _call(gp.predict, LP, with_value(Y6, (1, 0), np.inf), X6,
                                         Z6, Y6, X6),
     r"Y contains 1 NaN or infinite value\(s\)", ()),
    ("gp.predict-X_star-wrong-d_x", lambda c: _call(gp.predict, LP, Y6, X6, Z6, Y6[:3],
                                                    np.zeros((3, 2))),
     r"X_star must have shape \(N\*, d_x\) with d_x = 1 like X; received \(3, 2\)", ()),
    # --- mdcore._kernels ----------------------------------------------------------------
    ("kernels.kernel-log_params-nan", lambda c: _call(kernels.kernel, with_value(LP, 0, np.nan),
                                                      Y6, X6, Y6, X6),
     r"log_params contains 1 NaN or infinite value\(s\)", ()),
    ("kernels.kernel-log_params-wrong-P", lambda c: _call(kernels.kernel, LP[:2], Y6, X6, Y6,
                                                          X6),
     r"log_params must have last dimension P = .* = 4 .*received shape \(2,\)", ()),
    ("kernels.kernel-Yb-wrong-d_y", lambda c: _call(kernels.kernel, LP, Y6, X6,
                                                    np.zeros((3, 2)), X6[:3]),
     r"Yb must have d_y = 1 columns like Ya \(6, 1\); received \(3, 2\)", ()),
    ("kernels.kernel-Xa-1d", lambda c: _call(kernels.kernel, LP, Y6, X6[:, 0], Y6, X6),
     r"Xa must have 2 dimension\(s\); received shape \(6,\)", ()),
    # --- mdcore._history_matching ----------------------------------------------------------
    ("hm.implausibility-V_m-negative", lambda c: _call(elementwise_implausibility, 1.0, 0.0, 0.1, V_o=0.1,
                                                       V_m=np.array([-0.1])),
     r"V_m must be non-negative; received minimum -0\.1", ()),
    ("hm.implausibility-var-nan", lambda c: _call(elementwise_implausibility, 1.0, 0.0, np.array([np.nan]),
                                                  V_o=0.1, V_m=0.1),
     r"var contains 1 NaN or infinite value\(s\)", ()),
    ("hm.setup-V_m-zero", lambda c: _call(setup, toy, X8, Z8, BOUNDS,
                                          **{**HM_OPTIONS, "V_m": np.array([0.0])}),
     r"V_m must be positive; received minimum 0\.0", ()),
    ("hm.setup-V_m-inf", lambda c: _call(setup, toy, X8, Z8, BOUNDS,
                                         **{**HM_OPTIONS, "V_m": np.array([np.inf])}),
     r"V_m contains 1 NaN or infinite value\(s\)", ()),
    ("hm.setup-V_o-negative", lambda c: _call(setup, toy, X8, Z8, BOUNDS,
                                              **{**HM_OPTIONS, "V_o": np.array([-0.001])}),
     r"V_o must be non-negative; received minimum -0\.001", ()),
    ("hm.setup-threshold-zero", lambda c: _call(setup, toy, X8, Z8, BOUNDS, threshold=0.0,
                                                **HM_OPTIONS),
     r"threshold T must be a positive number; received 0\.0", ()),
    ("hm.setup-threshold-negative", lambda c: _call(setup, toy, X8, Z8, BOUNDS, threshold=-3,
                                                    **HM_OPTIONS),
     r"threshold T must be a positive number; received -3\b", ()),
    ("hm.setup-threshold-text", lambda c: _call(setup, toy, X8, Z8, BOUNDS, threshold="three",
                                                **HM_OPTIONS),
     r"threshold T must be a positive number; received 'three'", ()),
    ("hm.setup-bounds-reversed", lambda c: _call(setup, toy, X8, Z8, [[0.0, 2.0], [1.0, -1.0]],
                                                 **HM_OPTIONS),
     r"bounds needs lower < upper in every row; rows \[1\] are not", ()),
    ("hm.setup-z-wrong-rows", lambda c: _call(setup, toy, X8, Z8[:5], BOUNDS, **HM_OPTIONS),
     r"z must have shape \(N, n_out\) with N = 8 rows like X .*received \(5, 1\)", ()),
    ("hm.setup-X-inf", lambda c: _call(setup, toy, with_value(X8, (3, 0), np.inf), Z8, BOUNDS,
                                       **HM_OPTIONS),
     r"X contains 1 NaN or infinite value\(s\)", ()),
    ("hm.setup-n_runs-zero", lambda c: _call(setup, toy, X8, Z8, BOUNDS, n_runs=0,
                                             **HM_OPTIONS),
     r"n_runs must be an integer ≥ 1; received 0", ()),
    ("hm.history_match-n_candidates-huge",
     lambda c: _call(history_match, toy, X8, Z8, BOUNDS, **{**HM_OPTIONS, "n_candidates": HUGE}),
     r"n_candidates must be an integer ≥ 10 and ≤ 10,000,000; received 1000000000000",
     ("mdcore._history_matching:next_wave",)),
    ("hm.setup-convergence_ratio-inf", lambda c: _call(setup, toy, X8, Z8, BOUNDS,
                                                       convergence_ratio=np.inf, **HM_OPTIONS),
     r"convergence_ratio must be a positive number \(finite, > 0\); received inf", ()),
    ("hm.history_match-simulator-wrong-shape",
     lambda c: _call(history_match, toy_wrong_shape, X8, Z8, BOUNDS, **HM_OPTIONS),
     r"simulate\(X, theta\) must return shape \(n_theta, N, n_out\) = \(\d+, 8, 1\); it "
     r"returned \(\d+, 8\)", ()),
    ("hm.history_match-simulator-all-nan",
     lambda c: _call(history_match, toy_all_nan, X8, Z8, BOUNDS, **HM_OPTIONS),
     r"wave 1: (\d+) of \1 simulator runs failed .*returned NaN or inf\. Fix the simulator "
     r"\(simulate\)", ()),
    ("hm.nroy_samples-empty-nroy", lambda c: _call(c.ruled_out.nroy_samples, 10),
     r"no θ samples: wave 1: nothing is non-implausible.*Raise V_m .* or the threshold T", ()),
    ("hm.nroy_samples-n-huge", lambda c: _call(c.hm.nroy_samples, HUGE),
     r"n must be an integer ≥ 1 and ≤ 10,000,000; received 1000000000000",
     ("mdcore._history_matching:_uniform_in_nroy",)),
    ("hm.posterior_samples-n-zero", lambda c: _call(c.hm.posterior_samples, 0),
     r"n must be an integer ≥ 1; received 0", ()),
    # --- mdcore._runs -------------------------------------------------------------------
    ("runs.run_simulator-wrong-shape", lambda c: _call(runs.run_simulator, toy_wrong_shape, X8,
                                                       BOUNDS.T, 1),
     r"simulate\(X, theta\) must return shape \(n_theta, N, n_out\) = \(2, 8, 1\); it "
     r"returned \(2, 8\)", ()),
    ("runs.run_simulator-n_out-zero", lambda c: _call(runs.run_simulator, toy, X8, BOUNDS.T, 0),
     r"n_out must be an integer ≥ 1; received 0", ()),
    ("runs.run_simulator-theta-nan", lambda c: _call(runs.run_simulator, toy, X8,
                                                     with_value(BOUNDS.T, (0, 1), np.nan), 1),
     r"theta contains 1 NaN or infinite value\(s\)", ()),
    # --- mdcore._discrepancy (validation as it stands) ------------------------------------
    ("discrepancy-scenario-4", lambda c: _call(infer_discrepancy, toy, BOUNDS.T, X8, Z8,
                                               scenario=4, theta_map=[1.0, 0.0]),
     r"4 is not a valid scenario\. It must be one of \[1, 2, 3\]", ()),
    ("discrepancy-theta_samples-wrong-p",
     lambda c: _call(infer_discrepancy, toy, np.ones((4, 3)), X8, Z8, scenario=2,
                     theta_map=[1.0, 0.0]),
     r"theta_samples must have shape \(N_s, p\) with p = 2 like theta_map; received \(4, 3\)",
     ()),
    ("discrepancy-X-nan", lambda c: _call(infer_discrepancy, toy, BOUNDS.T,
                                          with_value(X8, (0, 0), np.nan), Z8, scenario=3),
     r"X contains 1 NaN or infinite value\(s\)", ()),
    ("discrepancy-simulator-wrong-shape",
     lambda c: _call(infer_discrepancy, toy_wrong_shape, BOUNDS.T, X8, Z8, scenario=3,
                     options=DiscrepancyOptions(n_phi=2)),
     r"simulate\(X, theta\) must return shape \(n_theta, N, n_out\) = \(2, 8, 1\); it "
     r"returned \(2, 8\)", ()),
    ("discrepancy-simulator-all-nan",
     lambda c: _call(infer_discrepancy, toy_all_nan, BOUNDS.T, X8, Z8, scenario=3,
                     options=DiscrepancyOptions(n_phi=2)),
     r"simulate\(X, theta\) returned NaN or inf", ()),
    ("discrepancy-n_phi-zero", lambda c: _call(DiscrepancyOptions, n_phi=0),
     r"n_phi must be an integer ≥ 1.*; received 0", ()),
    ("discrepancy-n_phi-huge", lambda c: _call(DiscrepancyOptions, n_phi=HUGE),
     r"n_phi must be an integer ≥ 1 and ≤ [\d,]+; received 1000000000000", ()),
    # --- mdcore._pipeline ---------------------------------------------------------------
    ("Settings-n_s-zero", lambda c: _call(Settings, n_s=0),
     r"n_s must be an integer ≥ 1; received 0", ()),
    ("Settings-n_phi-zero", lambda c: _call(Settings, n_phi=0),
     r"n_phi must be an integer ≥ 1; received 0", ()),
    ("Settings-n_s-huge", lambda c: _call(Settings, n_s=HUGE),
     r"n_s must be an integer ≥ 1 and ≤ 100,000; received 1000000000000", ()),
    ("Settings-n_phi-huge", lambda c: _call(Settings, n_phi=HUGE),
     r"n_phi must be an integer ≥ 1 and ≤ 100,000; received 1000000000000", ()),
    ("Settings-pairs-too-many", lambda c: _call(Settings, n_s=100_000, n_phi=100_000),
     r"n_s × n_phi must be at most 100,000,000 .*received n_s = 100,000 and n_phi = 100,000",
     ()),
    ("Settings-n_s-float", lambda c: _call(Settings, n_s=2.5),
     r"n_s must be an integer ≥ 1; received 2\.5", ()),
    ("Settings-n_iter-huge", lambda c: _call(Settings, n_iter=HUGE),
     r"n_iter must be an integer ≥ 2 and ≤ 100,000,000; received 1000000000000", ()),
    # n_iter − 1: Settings accepted it, then KOH refused it (one kept sample)
    ("Settings-burn_in-ge-n_iter", lambda c: _call(Settings, n_iter=1000, burn_in=999),
     r"burn_in must be smaller than n_iter − 1 = 999 so that at least two samples are kept; "
     r"received burn_in=999\. Raise n_iter or lower burn_in", ()),
    ("Settings-proposal-unknown", lambda c: _call(Settings, proposal="bogus"),
     r"'bogus' is not a valid proposal\. It must be one of \['adaptive', 'prior'\]", ()),
    ("run_method-empty-nroy", lambda c: _call(run_method, c.case, c.ruled_out, 1,
                                              Settings(n_s=5), seed=0),
     r"hm \(the history match\) ruled out every θ.*Raise V_m", ("mdcore._pipeline:infer_discrepancy",)),
    ("run_method-method-unknown", lambda c: _call(run_method, c.case, c.hm, "4",
                                                  Settings(n_s=5), seed=0),
     r"'4' is not a valid method\. It must be one of \['1', '2', '3', 'koh'\]", ()),
    ("run_method-X_extra-wrong-d_x", lambda c: _call(run_method, c.case, c.hm, 1,
                                                     Settings(n_s=5), seed=0,
                                                     X_extra=np.zeros((4, 2))),
     r"X_extra must have shape \(M, d_x\) with d_x = 1; received \(4, 2\)",
     ("mdcore._pipeline:infer_discrepancy",)),
    ("run_method-seed-negative", lambda c: _call(run_method, c.case, c.hm, 1, Settings(n_s=5),
                                                 seed=-1),
     r"seed must be an integer from 0 to 2\*\*63 − 1 or a numpy\.random\.Generator; "
     r"received -1\. Any seed in that range",
     ("mdcore._pipeline:infer_discrepancy",)),
    # --- mdcore._cases ------------------------------------------------------------------
    ("cases.load-unknown-name", lambda c: _call(cases.load, "beam-3d"),
     r"'beam-3d' is not a valid case name\. It must be one of \['beam-1d', 'beam-2d', "
     r"'shear-5'\]", ()),
    ("cases.load-name-not-text", lambda c: _call(cases.load, ["beam-1d"]),
     r"\['beam-1d'\] is not a valid case name\. It must be one of", ()),
    ("cases.load-seed-negative", lambda c: _call(cases.load, "beam-1d", seed=-5),
     r"seed must be an integer from 0 to 2\*\*63 − 1 .*received -5", ()),
    ("Case.simulate-theta-wrong-p", lambda c: _call(c.case.simulate, X8, np.ones((2, 3))),
     r"theta must have shape \(n_theta, 2\) for beam-1d \(l_cr, E\); received \(2, 3\)", ()),
    # --- mdcore._export -----------------------------------------------------------------
    ("export.nroy_csv-names-wrong-length", lambda c: _call(export.nroy_csv, c.hm, ["l_cr"]),
     r"names must be a list of 2 strings, one per θ component; received \['l_cr'\]", ()),
    ("export.nroy_csv-not-a-history-match", lambda c: _call(export.nroy_csv, {"waves": []}),
     r"hm must be a HistoryMatchResult .*; received dict", ()),
    ("export.predictions_csv-not-a-run", lambda c: _call(export.predictions_csv, c.hm),
     r"run must be an mdcore\.CaseRun .*; received HistoryMatchResult", ()),
    # --- mdcore._importance -------------------------------------------------------------
    ("importance.psis-log_weights-nan", lambda c: _call(importance.psis,
                                                        with_value(np.zeros(50), 7, np.nan)),
     r"log_weights must not contain NaN or \+inf", ()),
    ("importance.resample-n-zero", lambda c: _call(importance.resample, np.zeros(3), 0),
     r"n must be an integer ≥ 1", ()),
    # --- mdcore._koh --------------------------------------------------------------------
    ("koh.infer_koh-theta_prior-var-negative",
     lambda c: _call(koh.infer_koh, toy, X8, Z8, theta_prior=([1.0, 0.0], [-1.0, 0.25]),
                     bounds=BOUNDS, options=koh.KOHOptions(n_iter=100, burn_in=10)),
     r"theta_prior var must be positive; received \[-1\.0, 0\.25\]",
     ("mdcore._koh:_fit_phi", "mdcore._koh:adaptive_metropolis")),
    ("koh.infer_koh-n_iter-huge", lambda c: _call(koh.KOHOptions, n_iter=HUGE),
     r"n_iter must be an integer ≥ 2 and ≤ 100,000,000; received 1000000000000",
     ("mdcore._koh:_fit_phi", "mdcore._koh:adaptive_metropolis")),
    ("koh.infer_koh-burn_in-ge-n_iter",
     lambda c: _call(koh.KOHOptions, n_iter=500, burn_in=500),
     r"burn_in must be smaller than n_iter − 1 = 499 .*received burn_in=500",
     ("mdcore._koh:_fit_phi", "mdcore._koh:adaptive_metropolis")),
    ("koh.infer_koh-z-wrong-rows",
     lambda c: _call(koh.infer_koh, toy, X8, Z8[:6], theta_prior=([1.0, 0.0], [0.25, 0.25]),
                     bounds=BOUNDS, options=koh.KOHOptions(n_iter=100, burn_in=10)),
     r"z must have shape \(N, n_out\) with N = 8 rows like X .*received \(6, 1\)",
     ("mdcore._koh:_fit_phi", "mdcore._koh:adaptive_metropolis")),
    # --- mdcore._metrics ----------------------------------------------------------------
    ("metrics.lpl-var-zero", lambda c: _call(metrics.lpl, [0.0, 1.0], [0.0, 1.0], [0.0, 1.0]),
     r"var must be positive; received minimum 0\.0", ()),
    ("metrics.coverage-var-negative", lambda c: _call(metrics.coverage, [0.0, 1.0], [0.0, 1.0],
                                                      [1.0, -1.0]),
     r"var must be non-negative; received minimum -1\.0", ()),
    ("metrics.coverage-k-text", lambda c: _call(metrics.coverage, [0.0, 1.0], [0.0, 1.0],
                                                [1.0, 1.0], k="two"),
     r"k must be a positive number \(finite, > 0\); received 'two'", ()),
    ("metrics.nmse-shape-mismatch", lambda c: _call(metrics.nmse, np.arange(4.0),
                                                    np.arange(3.0)),
     r"prediction must have the same shape as the targets \(4,\); received \(3,\)", ()),
    ("metrics.mmd-X-wrong-rows", lambda c: _call(metrics.mmd, np.arange(4.0), np.arange(4.0),
                                                 np.ones(4), X=np.zeros((3, 1))),
     r"X must have one row per target \(N = 4\); received \(3, 1\)", ()),
]


def params(cases_: list) -> list:
    """Each case as a ``pytest.param`` whose id is its name (already-made params pass)."""
    return [c if hasattr(c, "marks") else pytest.param(*c, id=c[0]) for c in cases_]


@pytest.mark.parametrize("name, make, match, guards", params(API))
def test_api_refuses_bad_input_and_leaves_its_arguments_alone(ctx, monkeypatch, name, make,
                                                              match, guards):
    fn, args, kwargs = make(ctx)
    before = arrays_in((args, kwargs))
    guard(monkeypatch, *guards)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")            # a warning is not the error asked for
        with pytest.raises(ValueError, match=match):
            fn(*args, **kwargs)
    assert_unchanged(before, (args, kwargs))


def test_a_simulator_returning_nan_is_a_reported_failure_not_an_exception():
    """runs.run_simulator documents NaN outputs as failed runs (the caller decides)."""
    theta = BOUNDS.T.copy()
    out = runs.run_simulator(toy_all_nan, X8, theta, 1)
    assert out.y.shape == (0, 8, 1) and not np.any(out.ok)
    assert [f.message for f in out.failures] == ["returned NaN or inf"] * 2
    np.testing.assert_array_equal(theta, BOUNDS.T)


# ---------------------------------------------------------------------------------------
# Case files: malformed CSV and TOML, and simulators that misbehave

SIMULATOR = '''
import numpy as np

def linear(X, theta):
    theta = np.atleast_2d(theta)
    return (theta[:, :1] * X[None, :, 0] + theta[:, 1:2])[..., None]

def all_nan(X, theta):
    return np.full((len(np.atleast_2d(theta)), len(X), 1), np.nan)

def two_outputs(X, theta):
    return np.zeros((len(np.atleast_2d(theta)), len(X), 2))
'''

CSV = """# provenance
x,y,test
0.0,0.10,0
0.0,0.12,0
0.5,0.61,0
0.5,0.59,0
1.0,1.11,0
1.0,1.09,0
0.25,0.35,1
0.75,0.86,1
"""

TOML = """
name = "line"
[data]
file = "data.csv"
inputs = ["x"]
outputs = ["y"]
test_column = "test"
[simulator]
function = "bad_input_sim:linear"
path = "."
[[parameters]]
name = "slope"
lower = 0.0
upper = 2.0
[[parameters]]
name = "intercept"
lower = -1.0
upper = 1.0
[history_matching]
V_m = [0.01]
"""


def _toml(old, new):
    assert old in TOML
    return lambda files: files.update({"case.toml": TOML.replace(old, new)})


def _csv(old, new):
    assert old in CSV
    return lambda files: files.update({"data.csv": CSV.replace(old, new)})


def _raw(name, data: bytes):
    return lambda files: files.update({name: data})


CASE_FILES = [
    # CSV
    ("csv-ragged-row", _csv("0.5,0.59,0", "0.5,0.59"),
     r"data\.csv line 6: 2 field\(s\), but the header has 3"),
    ("csv-non-numeric-cell", _csv("0.59", "n/a"),
     r"data\.csv line 6, column 'y': 'n/a' is not a number"),
    ("csv-nan-cell", _csv("0.59", "nan"), r"data\.csv line 6, column 'y': 'nan' is not finite"),
    ("csv-inf-cell", _csv("1.11", "-inf"),
     r"data\.csv line 7, column 'y': '-inf' is not finite"),
    ("csv-empty-file", _csv(CSV, ""), r"data\.csv: no header row found"),
    ("csv-header-only", _csv(CSV, "x,y,test\n"),
     r"data\.csv: the header is followed by no data rows"),
    ("csv-wrong-delimiter", _csv(CSV, CSV.replace(",", ";")),
     r"data\.csv line 2: the columns are separated by semicolons; save the file as CSV with "
     r"commas \(the columns \['x', 'test', 'y'\] are there\)"),
    ("csv-duplicate-column", _csv("x,y,test", "x,y,y,test"),
     r"column\(s\) \['y'\] appear more than once in the header \['x', 'y', 'y', 'test'\]"),
    ("csv-not-utf8", _raw("data.csv", CSV.replace("provenance", "provenanc\xe9").encode("latin-1")),
     r"data\.csv: not UTF-8 text"),
    ("csv-test-flag-not-0-or-1", _csv("0.86,1", "0.86,0.5"),
     r"column 'test' must be 0 \(training row\) or 1 \(test row\) in every row; found 0\.5"),
    # TOML
    ("toml-syntax-error", _toml('name = "line"', 'name = "line'), r"case\.toml: not valid TOML"),
    ("toml-duplicate-key", _toml('name = "line"', 'name = "line"\nname = "again"'),
     r"not valid TOML \(Cannot overwrite a value"),
    ("toml-not-utf8", _raw("case.toml", TOML.replace("line", "l\xefne").encode("latin-1")),
     r"case\.toml: not valid TOML"),
    ("toml-lower-is-text", _toml("lower = 0.0", 'lower = "0"'),
     r"\[parameters 1\] lower must be a finite number; found '0'"),
    ("toml-lower-nan", _toml("lower = 0.0", "lower = nan"),
     r"\[parameters 1\] lower must be a finite number; found nan"),
    ("toml-V_m-zero", _toml("V_m = [0.01]", "V_m = [0.0]"),
     r"\[history_matching\] V_m must be a list of 1 positive numbers \(one per output\); "
     r"found \[0\.0\]"),
    ("toml-prior_var-negative", _toml("upper = 2.0", "upper = 2.0\nprior_var = -1.0"),
     r"\[parameters 1\] prior_var must be a positive number; found -1\.0"),
    ("toml-misspelt-key", _toml('test_column = "test"', 'test_column = "test"\n'
                                                         'noise_variance = [0.001]'),
     r"\[data\] has unknown key\(s\) 'noise_variance' \(did you mean 'noise_var'\?\); the "
     r"keys allowed there are .*'noise_var'"),
    ("toml-initial_design-huge", _toml("V_m = [0.01]", f"V_m = [0.01]\ninitial_design = {HUGE}"),
     r"\[history_matching\] initial_design must be an integer ≥ 2 and ≤ 10,000; "
     r"found 1000000000000"),
    ("toml-inputs-not-a-list", _toml('inputs = ["x"]', 'inputs = "x"'),
     r"\[data\] inputs must be a list of non-empty strings; found 'x'"),
    ("toml-unknown-table", _toml("[[parameters]]\nname = \"intercept\"",
                                 "[parameters_extra]\nname = \"intercept\""),
     r"the top level has unknown key\(s\) 'parameters_extra' \(did you mean 'parameters'\?\); "
     r"the keys allowed there are .*'parameters'"),
    ("toml-parameters-one-table-not-an-array",
     lambda files: files.update({"case.toml": TOML.split("[[parameters]]")[0]
                                 + "[parameters]\nname = \"slope\"\nlower = 0.0\nupper = 2.0\n"
                                 + "[history_matching]\nV_m = [0.01]\n"}),
     r"\[\[parameters\]\] must be one or more tables, one per calibration parameter; "
     r"found \{'name': 'slope'"),
    # simulators
    ("case-file-simulator-all-nan", _toml("bad_input_sim:linear", "bad_input_sim:all_nan"),
     r"\[simulator\] function bad_input_sim:all_nan returned NaN or inf at the centre of the "
     r"parameter box \[1\.0, 0\.0\]"),
    ("case-file-simulator-wrong-shape", _toml("bad_input_sim:linear",
                                              "bad_input_sim:two_outputs"),
     r"\[simulator\] function bad_input_sim:two_outputs must return shape \(n_theta, N, n_out\) "
     r"= \(1, 6, 1\) .*returned \(1, 6, 2\)"),
]


def _folder_state(folder: Path) -> dict:
    return {p.relative_to(folder): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file() and "__pycache__" not in p.parts}


def write_case_folder(folder: Path, edit=None) -> Path:
    files = {"bad_input_sim.py": SIMULATOR, "data.csv": CSV, "case.toml": TOML}
    if edit is not None:
        edit(files)
    for name, content in files.items():
        data = content if isinstance(content, bytes) else \
            textwrap.dedent(content).encode("utf-8")
        (folder / name).write_bytes(data)
    return folder / "case.toml"


@pytest.mark.parametrize("name, edit, match", params(CASE_FILES))
def test_malformed_case_files_are_refused_and_left_as_they_were(tmp_path, name, edit, match):
    path = write_case_folder(tmp_path, edit)
    before = _folder_state(tmp_path)
    with pytest.raises(CaseFileError, match=match) as info:
        load_case_file(path)
    assert str(tmp_path) in str(info.value)
    assert _folder_state(tmp_path) == before


def test_the_unedited_case_folder_loads(tmp_path):
    case = load_case_file(write_case_folder(tmp_path))
    assert case.theta_names == ("slope", "intercept") and case.X_test.shape == (2, 1)


# ---------------------------------------------------------------------------------------
# The command line: exit code 2, one "error:" line naming the argument, no files written


OUT = ["--json", "out/run.json", "--csv", "out/tables", "--out", "out/report.html"]

CLI = [
    ("history-match-unknown-case", ["history-match", "beam-3d"],
     r"argument case: invalid choice: 'beam-3d'"),
    ("history-match-threshold-zero", ["history-match", "beam-1d", "--threshold", "0"],
     r"threshold T must be a positive number; received 0\.0"),
    ("history-match-threshold-nan", ["history-match", "beam-1d", "--threshold", "nan"],
     r"threshold T must be a positive number; received nan"),
    ("history-match-threshold-text", ["history-match", "beam-1d", "--threshold", "three"],
     r"argument --threshold: invalid float value: 'three'"),
    ("history-match-v-m-zero", ["history-match", "beam-1d", "--v-m", "0"],
     r"V_m must be positive; received minimum 0\.0"),
    ("history-match-v-m-negative", ["history-match", "beam-1d", "--v-m", "-0.5"],
     r"V_m must be positive; received minimum -0\.5"),
    ("history-match-n-candidates-huge", ["history-match", "beam-1d", "--n-candidates", str(HUGE)],
     r"n_candidates must be an integer ≥ 10 and ≤ 10,000,000; received 1000000000000"),
    ("history-match-n-candidates-zero", ["history-match", "beam-1d", "--n-candidates", "0"],
     r"n_candidates must be an integer ≥ 10; received 0"),
    ("history-match-max-waves-zero", ["history-match", "beam-1d", "--max-waves", "0"],
     r"max_waves must be an integer ≥ 1; received 0"),
    ("history-match-max-waves-huge", ["history-match", "beam-1d", "--max-waves", str(HUGE)],
     r"max_waves must be an integer ≥ 1 and ≤ 100; received 1000000000000"),
    ("history-match-runs-of-all-waves", ["history-match", "beam-1d", "--n-runs", "5000",
                                         "--max-waves", "5"],
     r"the simulator runs of all waves, initial_design's rows \+ n_runs × \(max_waves − 1\), "
     r"must be at most 10,000 .*received 25 \+ 5,000 × 4 = 20,025\. Lower n_runs or "
     r"max_waves"),
    ("history-match-seed-negative", ["history-match", "beam-1d", "--seed", "-1"],
     r"argument --seed: must be a whole number from 0 to 9223372036854775807 \(2\*\*63 − 1\); "
     r"received '-1'\. Each seed gives its own reproducible run, e\.g\. --seed 0"),
    ("history-match-timeout-zero", ["history-match", "beam-1d", "--timeout", "0"],
     r"argument --timeout: must be a positive number of seconds per simulator run; received "
     r"'0'\. For example --timeout 60"),
    ("reproduce-n-s-zero", ["reproduce", "beam-1d", "--n-s", "0", *OUT],
     r"n_s must be an integer ≥ 1; received 0"),
    ("reproduce-n-phi-zero", ["reproduce", "beam-1d", "--n-phi", "0", *OUT],
     r"n_phi must be an integer ≥ 1; received 0"),
    ("reproduce-n-phi-huge", ["reproduce", "beam-1d", "--n-phi", str(HUGE), *OUT],
     r"n_phi must be an integer ≥ 1 and ≤ 100,000; received 1000000000000"),
    ("reproduce-n-s-huge", ["reproduce", "beam-2d", "--n-s", str(HUGE), *OUT],
     r"n_s must be an integer ≥ 1 and ≤ 100,000; received 1000000000000"),
    ("reproduce-n-s-not-an-integer", ["reproduce", "beam-1d", "--n-s", "1e3", *OUT],
     r"argument --n-s: invalid int value: '1e3'"),
    ("reproduce-n-iter-huge", ["reproduce", "beam-1d", "--n-iter", str(HUGE), *OUT],
     r"n_iter must be an integer ≥ 2 and ≤ 100,000,000; received 1000000000000"),
    ("reproduce-pairs-too-many", ["reproduce", "beam-1d", "--n-s", "100000", "--n-phi",
                                  "100000", *OUT],
     r"n_s × n_phi must be at most 100,000,000 \(θ, φ\) pairs"),
    ("reproduce-burn-in-ge-n-iter", ["reproduce", "beam-1d", "--n-iter", "100", "--burn-in",
                                     "99", *OUT],
     r"burn_in must be smaller than n_iter − 1 = 99 .*received burn_in=99"),
    ("reproduce-unknown-scenario", ["reproduce", "beam-1d", "--scenarios", "4", *OUT],
     r"argument (--methods/)?--scenarios: invalid choice: '4'"),
    ("run-missing-case-file", ["run", "missing.toml", *OUT],
     r"case file 'missing\.toml' does not exist"),
    ("run-malformed-toml", ["run", "case/case.toml", *OUT], r"case\.toml: not valid TOML"),
    ("run-malformed-csv", ["run", "case/case.toml", *OUT],
     r"data\.csv line 6, column 'y': 'n/a' is not a number"),
    ("run-seed-negative", ["run", "case/case.toml", "--seed", "-1", *OUT],
     r"argument --seed: must be a whole number from 0 to .*received '-1'"),
    ("run-seed-5000-digits", ["run", "case/case.toml", "--seed", "9" * 5000, *OUT],
     r"argument --seed: must be a whole number from 0 to .*received '9{29}…9{9}' "
     r"\(5,002 characters\)\. Each seed"),
    ("run-a-folder", ["run", "case", *OUT],
     r"case file 'case' is a folder; give the TOML case file itself, e\.g\. one of "
     r"\['case\.toml'\]"),
    ("run-one-test-row", ["run", "case/case.toml", *OUT],
     r"data\.csv: column 'test' marks 7 training row\(s\) \(0\) and 1 test row\(s\) \(1\); at "
     r"least 3 training rows are needed to fit the discrepancy GP and 2 test rows to score it"),
    ("run-huge-value", ["run", "case/case.toml", *OUT],
     r"data\.csv line 6, column 'y': '1e300' is larger in magnitude than 1e\+30"),
    ("run-misspelt-key", ["run", "case/case.toml", *OUT],
     r"\[data\] has unknown key\(s\) 'ouputs' \(did you mean 'outputs'\?\)"),
    ("study-seeds-huge", ["study", "beam-1d", "--seeds", f"0-{HUGE}", "--workers", "1",
                          "--json", "out/study.json"],
     r"seeds must name at most 10,000 seeds .*received '0-1000000000000'"),
    ("study-seeds-malformed", ["study", "beam-1d", "--seeds", "a-b", "--workers", "1",
                               "--json", "out/study.json"],
     r"seeds must look like '0-9', '0,3,5' or '2' .*received 'a-b'"),
    ("study-seed-5000-digits", ["study", "beam-1d", "--seeds", "9" * 5000, "--workers", "1",
                                "--json", "out/study.json"],
     r"seeds must look like .*integers from 0 to 2\*\*63 − 1.*received '9{29}…9{9}' "
     r"\(5,002 characters\)"),
    pytest.param("study-workers-zero", ["study", "beam-1d", "--seeds", "0", "--workers", "0",
                                        "--json", "out/study.json"],
                 r"workers must be an integer ≥ 1; received 0",
                 id="study-workers-zero"),
]

CLI_FOLDERS = {"run-malformed-toml": _toml('name = "line"', 'name = "line'),
               "run-malformed-csv": _csv("0.59", "n/a"),
               "run-seed-negative": _csv("0.59", "0.59"),
               "run-seed-5000-digits": _csv("0.59", "0.59"),
               "run-a-folder": _csv("0.59", "0.59"),
               "run-one-test-row": _csv("0.86,1", "0.86,0"),
               "run-huge-value": _csv("0.59", "1e300"),
               "run-misspelt-key": _toml("outputs", "ouputs")}


def run_cli(argv) -> int:
    try:
        return main(argv)
    except SystemExit as exc:                      # argparse refuses before main's body
        return exc.code


@pytest.mark.parametrize("name, argv, match", params(CLI))
def test_cli_refuses_bad_input_with_exit_2_and_writes_nothing(tmp_path, monkeypatch, capsys,
                                                              name, argv, match):
    monkeypatch.chdir(tmp_path)
    if name in CLI_FOLDERS:
        (tmp_path / "case").mkdir()
        write_case_folder(tmp_path / "case", CLI_FOLDERS[name])
    # The work a refused input must never reach: waves, the reproduce/run pipelines, seeds.
    guard(monkeypatch, "mdcore._history_matching:next_wave", "mdcore._pipeline:infer_discrepancy",
          "mdcore._pipeline:infer_koh", "mdcore._study:_one")
    before = _folder_state(tmp_path)
    assert run_cli(argv) == 2
    captured = capsys.readouterr()
    errors = [line for line in captured.err.splitlines() if "error: " in line]
    assert len(errors) == 1, captured.err
    assert re.search(match, errors[0]), errors[0]
    assert len(errors[0]) < 600                   # one readable line, no echoed file or number
    assert _folder_state(tmp_path) == before
    assert not (tmp_path / "out").exists()


# ---------------------------------------------------------------------------------------
# The app's session state


CONTROLS = ("case_name", "v_m", "threshold", "rule", "n_runs", "n_candidates", "max_waves",
            "convergence_ratio", "selected_wave", "n_s", "n_phi", "paper_sizes", "scenarios",
            "koh_chain", "proposal", "band", "seed", "slice_x2")


@pytest.fixture
def app_state():
    """A session with one wave and scenario 1's result, at tiny sizes."""
    pytest.importorskip("panel")
    from mdcore._pipeline import Method
    from mdcore_app.state import ExplorerState
    s = ExplorerState()
    s.param.update(n_candidates=2000, max_waves=2, n_s=10, n_phi=5, scenarios=[Method.S1])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        s.next_wave()
        s.run_discrepancy()
    assert s.error == "" and len(s.waves) == 1 and list(s.results) == [Method.S1], s.error
    return s


def app_snapshot(s, skip: str | None = None) -> dict:
    controls = {n: getattr(s, n) for n in CONTROLS if n in s.param and n != skip}
    return dict(controls=controls, waves=s.waves, results=dict(s.results), status=s.status,
                maps=dict(s.implausibility_maps), case=s.case, busy=s.busy)


def assert_app_unchanged(s, before: dict, skip: str | None = None) -> None:
    after = app_snapshot(s, skip)
    assert after["controls"] == before["controls"]
    assert after["waves"] is before["waves"]
    assert after["results"].keys() == before["results"].keys()
    assert all(after["results"][k] is v for k, v in before["results"].items())
    assert after["status"] == before["status"] and after["case"] is before["case"]
    assert after["maps"].keys() == before["maps"].keys() and not after["busy"]


def type_into(s, name: str, value) -> bool:
    """What the view does with a typed value: set it, or report the refusal (the field
    reverts). Returns whether the state accepted the value."""
    try:
        setattr(s, name, value)
    except ValueError as exc:
        s.reject(name, value, exc)
        return False
    return True


APP_FIELDS = [
    ("app-v_m-zero", "v_m", 0.0),
    ("app-v_m-negative", "v_m", -0.05),
    ("app-v_m-nan", "v_m", float("nan")),
    ("app-threshold-zero", "threshold", 0.0),
    ("app-threshold-negative", "threshold", -3.0),
    pytest.param("app-threshold-inf", "threshold", float("inf"), id="app-threshold-inf"),
    ("app-n_s-zero", "n_s", 0),
    ("app-n_phi-zero", "n_phi", 0),
    pytest.param("app-n_phi-huge", "n_phi", HUGE, id="app-n_phi-huge"),
    ("app-n_candidates-huge", "n_candidates", HUGE),
    ("app-n_s-not-an-integer", "n_s", 2.5),
    ("app-case-unknown", "case_name", "beam-3d"),
    ("app-rule-unknown", "rule", "median"),
    ("app-max-waves-zero", "max_waves", 0),
    ("app-seed-negative", "seed", -1),
    ("app-convergence-ratio-zero", "convergence_ratio", 0.0),
]


@pytest.mark.parametrize("name, field, value", params(APP_FIELDS))
def test_app_fields_refuse_bad_values_and_keep_the_session(app_state, monkeypatch, name, field,
                                                           value):
    s = app_state
    before, errors = app_snapshot(s), s.n_errors
    guard(monkeypatch, "mdcore_app.runs:run_method", "mdcore_app.history_model:next_wave")
    accepted = type_into(s, field, value)
    assert not accepted, f"{field} = {value!r} was accepted"
    assert s.n_errors == errors + 1
    label = s.param[field].label
    assert re.search(re.escape(label) + r": .* is not allowed \(.+\)\. The field keeps ", s.error)
    assert_app_unchanged(s, before)


APP_ACTIONS = [
    ("app-empty-nroy-then-wave", dict(v_m=1e-7, threshold=0.5),
     r"nothing is non-implausible.*Raise V_m .* or the threshold T"),
    ("app-v_m-tiny-for-shear-5-then-wave", dict(case_name="shear-5", v_m=1e-9, threshold=0.3),
     r"nothing is non-implausible.*Raise V_m .* or the threshold T"),
]


@pytest.mark.parametrize("name, settings, match", params(APP_ACTIONS))
def test_app_wave_on_settings_that_cannot_work_is_one_error_and_keeps_the_results(
        app_state, monkeypatch, name, settings, match):
    """Settings the fields accept but history matching refuses: the wave is one error
    notification, and the waves and results shown before stay."""
    s = app_state
    s.param.update(**settings)
    before, errors = app_snapshot(s), s.n_errors
    if "n_candidates" in settings:                 # must be refused before any wave runs
        guard(monkeypatch, "mdcore_app.history_model:next_wave")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        s.next_wave()
    assert s.n_errors == errors + 1 and re.search(match, s.error), s.error
    assert_app_unchanged(s, before)


def test_every_bad_input_has_its_own_id():
    ids = [p.id for table in (API, CASE_FILES, CLI, APP_FIELDS, APP_ACTIONS)
           for p in params(table)]
    assert len(ids) == len(set(ids)) >= 34
