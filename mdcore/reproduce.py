"""End-to-end runs of a case study: history matching, then scenarios 1–3 and their metrics.

This is what ``python -m mdcore reproduce`` runs and what the app's metrics table shows.
"""

from __future__ import annotations

import time
from typing import Callable

import numpy as np

from . import cases as _cases
from .discrepancy import DiscrepancyPrediction, infer
from .history_matching import HistoryMatchResult, _in_nroy, history_match_case
from .metrics import coverage, lpl, mmd, nmse

__all__ = ["PAPER_SIZES", "score", "run_scenario", "reproduce"]

#: The paper's (N_s, N_φ) per case study (SPEC §6).
PAPER_SIZES = {"beam-1d": (1000, 500), "beam-2d": (1000, 1000), "shear-5": (1000, 500)}


def score(case, pred: DiscrepancyPrediction) -> dict:
    """SPEC §8 metrics of a prediction at ``case.X_test``, per output.

    Returns
    -------
    dict
        ``nmse_z, mmd, lpl, coverage_z_2sd, coverage_z_3sd`` as lists over outputs, and
        ``nmse_delta, coverage_delta_2sd, coverage_delta_3sd`` (lists, or None when the
        true δ is unknown).
    """
    z = case.z_test
    out = {"nmse_z": nmse(z, pred.z_mean), "mmd": mmd(z, pred.z_mean, pred.z_var, X=case.X_test),
           "lpl": lpl(z, pred.z_mean, pred.z_var),
           "coverage_z_2sd": coverage(z, pred.z_mean, pred.z_var, k=2),
           "coverage_z_3sd": coverage(z, pred.z_mean, pred.z_var, k=3)}
    delta = case.true_delta(case.X_test)
    for key, k in (("nmse_delta", None), ("coverage_delta_2sd", 2), ("coverage_delta_3sd", 3)):
        if delta is None:
            out[key] = None
        elif k is None:
            out[key] = nmse(delta, pred.delta_mean)
        else:
            out[key] = coverage(delta, pred.delta_mean, pred.delta_var, k=k)
    return {k: (None if v is None else np.asarray(v, dtype=float).tolist())
            for k, v in out.items()}


def run_scenario(case, hm: HistoryMatchResult, scenario: int, *, n_s: int, n_phi: int,
                 seed: int = 0, log_params_hat=None, progress: Callable | None = None):
    """Infer one scenario on a case and predict at its test inputs.

    Returns ``(model, prediction, seconds)``; seconds cover inference and prediction.
    """
    start = time.perf_counter()
    theta = hm.posterior_samples(n_s, seed=seed)
    model = infer(case.simulate, theta, case.X_train, case.z_train, scenario=scenario,
                  theta_map=hm.theta_map, n_phi=n_phi, phi_prior=case.phi_prior, seed=seed,
                  log_params_hat=log_params_hat, progress=progress)
    pred = model.predict(case.X_test)
    return model, pred, time.perf_counter() - start


def reproduce(name: str, *, scenarios=(1, 2, 3), n_s: int | None = None,
              n_phi: int | None = None, seed: int = 0, report: Callable | None = None) -> dict:
    """History-match a case, run the scenarios, and score them (the ``reproduce`` command).

    Parameters
    ----------
    name : str
        Case study name.
    scenarios : sequence of {1, 2, 3}
    n_s, n_phi : int, optional
        Default: the paper's sizes (:data:`PAPER_SIZES`).
    seed : int
        Seeds the case's noise, the history match, the θ samples and the φ draws.
    report : callable, optional
        Called with a line of text as each stage finishes.

    Returns
    -------
    dict
        The JSON layout of the ``reproduce`` command (see the README).
    """
    case = _cases.load(name, seed=seed)
    n_s = PAPER_SIZES[name][0] if n_s is None else n_s
    n_phi = PAPER_SIZES[name][1] if n_phi is None else n_phi
    hm = history_match_case(case, seed=seed)
    truth = None if case.theta_true is None else \
        bool(_in_nroy(hm.problem, hm.waves, case.theta_true[None])[0])
    result = {"case": name, "seed": seed, "n_s": n_s, "n_phi": n_phi,
              "history_matching": {"waves": len(hm.waves), "nroy_fraction": hm.nroy_fraction,
                                   "theta_map": hm.theta_map.tolist(), "truth_nroy": truth,
                                   "status": hm.status},
              "scenarios": {}}
    if report:
        report(hm.message)
    log_params_hat = None
    for s in sorted({int(s) for s in scenarios}):
        model, pred, seconds = run_scenario(case, hm, s, n_s=n_s, n_phi=n_phi, seed=seed,
                                            log_params_hat=log_params_hat)
        if s == 1:
            log_params_hat = model.log_params_hat
        entry = score(case, pred)
        entry["ess"] = float(np.min(model.ess)) if s == 3 else None
        entry["ess_per_output"] = model.ess.tolist()
        entry["skipped_mass"] = model.skipped_mass.tolist()
        entry["seconds"] = seconds
        result["scenarios"][str(s)] = entry
        if report:
            report(f"scenario {s}: {seconds:.2f} s")
    return result
