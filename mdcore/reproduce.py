"""End-to-end runs of a case study: history matching, scenarios 1–3, the Kennedy–O'Hagan
baseline ("koh"), and their metrics.

This is what ``python -m mdcore reproduce`` runs and what the app's metrics table shows.
"""

from __future__ import annotations

import time
from typing import Callable

import numpy as np

from . import cases as _cases
from . import koh as _koh
from .discrepancy import DiscrepancyPrediction, infer
from .gp import GaussianPrior
from .history_matching import HistoryMatchResult, _in_nroy, history_match_case
from .metrics import coverage, lpl, mmd, nmse

__all__ = ["PAPER_SIZES", "METHODS", "default_methods", "score", "run_scenario", "run_koh",
           "koh_phi_prior", "reproduce"]

#: The paper's (N_s, N_φ) per case study (SPEC §6).
PAPER_SIZES = {"beam-1d": (1000, 500), "beam-2d": (1000, 1000), "shear-5": (1000, 500)}
#: Everything ``reproduce`` can run: the decoupled scenarios and the KOH baseline.
METHODS = ("1", "2", "3", "koh")


def default_methods(name: str) -> tuple:
    """Scenarios 1–3, plus KOH on beam-1d (the only case the paper runs it on)."""
    return METHODS if name == "beam-1d" else METHODS[:3]


def _methods(values) -> list:
    """Normalise scenario labels (1, "2", "koh") to sorted unique strings of METHODS."""
    out = set()
    for v in values:
        label = str(v).strip().lower()
        if label not in METHODS or isinstance(v, bool):
            raise ValueError(f"{v!r} is not a valid scenario. It must be one of "
                             f"{list(METHODS)} (1–3: decoupled scenarios, koh: the "
                             "Kennedy–O'Hagan baseline).")
        out.add(label)
    if not out:
        raise ValueError(f"scenarios is empty; pick at least one of {list(METHODS)}.")
    return sorted(out, key=METHODS.index)


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


def koh_phi_prior(case) -> GaussianPrior:
    """The case's discrepancy prior without its ``ℓ_y`` entries: the KOH δ is a GP over x
    only, ``[log σ_f, log ℓ_x…, log σ_n]``. Used as the hyperprior of KOH's φ̂, as
    scenarios 1–2 use ``case.phi_prior`` for theirs (SPEC §7 leaves it to us)."""
    keep = np.r_[0, np.arange(1 + case.n_out, case.phi_prior.size)]
    return GaussianPrior(case.phi_prior.mean[keep], case.phi_prior.var[keep])


def run_koh(case, hm: HistoryMatchResult, *, n_iter: int = _koh.N_ITER,
            burn_in: int = _koh.BURN_IN, seed: int = 0, progress: Callable | None = None):
    """The Kennedy–O'Hagan baseline on a case with the history match's final emulator.

    Returns ``(model, prediction, seconds)``; seconds cover inference and prediction.
    """
    start = time.perf_counter()
    model = _koh.infer(hm.waves[-1].emulator, case.X_train, case.z_train,
                       theta_prior=case.theta_prior, bounds=case.theta_bounds,
                       phi_prior=koh_phi_prior(case), n_iter=n_iter, burn_in=burn_in,
                       seed=seed, progress=progress)
    pred = model.predict(case.X_test)
    return model, pred, time.perf_counter() - start


def reproduce(name: str, *, scenarios=None, n_s: int | None = None,
              n_phi: int | None = None, n_iter: int = _koh.N_ITER,
              burn_in: int = _koh.BURN_IN, seed: int = 0,
              report: Callable | None = None) -> dict:
    """History-match a case, run the scenarios, and score them (the ``reproduce`` command).

    Parameters
    ----------
    name : str
        Case study name.
    scenarios : sequence of {1, 2, 3, "koh"}, optional
        Default :func:`default_methods` (KOH is included for beam-1d).
    n_s, n_phi : int, optional
        Default: the paper's sizes (:data:`PAPER_SIZES`).
    n_iter, burn_in : int
        The KOH chain (default the paper's 150,000 and 50,000).
    seed : int
        Seeds the case's noise, the history match, the θ samples, the φ draws and the
        KOH chain.
    report : callable, optional
        Called with a line of text as each stage finishes.

    Returns
    -------
    dict
        The JSON layout of the ``reproduce`` command (see the README).
    """
    case = _cases.load(name, seed=seed)
    methods = _methods(default_methods(name) if scenarios is None else scenarios)
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
    for label in methods:
        if label == "koh":
            model, pred, seconds = run_koh(case, hm, n_iter=n_iter, burn_in=burn_in, seed=seed)
            entry = score(case, pred)
            entry.update(_koh_summary(model))
        else:
            s = int(label)
            model, pred, seconds = run_scenario(case, hm, s, n_s=n_s, n_phi=n_phi, seed=seed,
                                                log_params_hat=log_params_hat)
            if s == 1:
                log_params_hat = model.log_params_hat
            entry = score(case, pred)
            entry["ess"] = float(np.min(model.ess)) if s == 3 else None
            entry["ess_per_output"] = model.ess.tolist()
            entry["skipped_mass"] = model.skipped_mass.tolist()
        entry["seconds"] = seconds
        result["scenarios"][label] = entry
        if report:
            report(f"scenario {label}: {seconds:.2f} s")
    return result


def _koh_summary(model) -> dict:
    """The KOH entry's extra keys; ``ess`` is the smallest MCMC ESS over the parameters."""
    theta = model.theta
    return {"ess": float(np.min(model.ess)), "ess_per_output": None,
            "skipped_mass": [0.0] * model.n_out,
            "n_iter": model.chain.n_iter, "burn_in": model.chain.burn_in,
            "acceptance_rate": model.acceptance_rate,
            "iat_per_parameter": model.iat.tolist(), "ess_per_parameter": model.ess.tolist(),
            "theta_mean": theta.mean(axis=0).tolist(), "theta_sd": theta.std(axis=0).tolist(),
            "theta_interval_99": np.percentile(theta, [0.5, 99.5], axis=0).T.tolist(),
            "log_phi": model.log_phi.tolist()}
