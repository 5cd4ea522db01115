"""Results out as plain files: CSV tables of the history match and of the predictions.

No pickle anywhere: the JSON of a run is :meth:`mdcore.reproduce.CaseRun.to_dict` (a
versioned schema), and the tables here are CSV text with a header row and ``#`` comment
lines that say where they come from.

Examples
--------
>>> from mdcore import cases
>>> from mdcore.reproduce import run_case
>>> from mdcore.pipeline import Settings
>>> run = run_case(cases.load("beam-1d"), methods=[1], settings=Settings(n_s=10),
...                n_candidates=5000)
>>> nroy_csv(run.hm, run.case.theta_names, run.case.theta_units).splitlines()[1]
'wave,l_cr [mm],E [GPa],implausibility'
"""

from __future__ import annotations

import csv
import io
from pathlib import Path

import numpy as np

from .history_matching import HistoryMatchResult
from .reproduce import CaseRun

__all__ = ["nroy_csv", "predictions_csv", "write_tables"]


def _table(comment: str, header: list, rows) -> str:
    out = io.StringIO()
    out.write(f"# {comment}\n")
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(header)
    writer.writerows(rows)
    return out.getvalue()


def _labels(values, name: str, p: int) -> list | None:
    """Column labels: None, or a sequence of ``p`` strings (one per θ component)."""
    if values is None:
        return None
    if isinstance(values, str) or not all(isinstance(v, str) for v in values) \
            or len(values) != p:
        raise ValueError(f"{name} must be a list of {p} strings, one per θ component; "
                         f"received {values!r}.")
    return list(values)


def _check_run(run) -> None:
    if not isinstance(run, CaseRun):
        raise ValueError(f"run must be an mdcore.reproduce.CaseRun (reproduce or run_case); "
                         f"received {type(run).__name__}.")


def nroy_csv(hm: HistoryMatchResult, names=None, units=None) -> str:
    """The non-implausible θ of every wave with their implausibility, as CSV text.

    Parameters
    ----------
    hm : HistoryMatchResult
    names, units : sequence of str, optional
        Column names of θ (default ``theta_1 …``).

    Returns
    -------
    str
        Columns ``wave``, one per θ component, ``implausibility``; one row per retained
        candidate of each wave (uniform in that wave's NROY set).
    """
    if not isinstance(hm, HistoryMatchResult):
        raise ValueError(f"hm must be a HistoryMatchResult (history_match or "
                         f"history_match_case); received {type(hm).__name__}.")
    p = hm.problem.p
    names = _labels(names, "names", p) or [f"theta_{i + 1}" for i in range(p)]
    units = _labels(units, "units", p) or [""] * p
    head = ["wave"] + [f"{n} [{u}]" if u else n for n, u in zip(names, units)] \
        + ["implausibility"]
    rows = []
    for w in hm.waves:
        keep = w.candidate_implausibility <= hm.problem.threshold
        for theta, imp in zip(w.candidates[keep], w.candidate_implausibility[keep]):
            rows.append([w.index] + [repr(float(t)) for t in theta] + [repr(float(imp))])
    comment = (f"NROY samples per wave (I <= T = {hm.problem.threshold:g}, rule "
               f"{hm.problem.rule!r}); status {hm.status}: {hm.message}")
    return _table(comment, head, rows)


def predictions_csv(run) -> str:
    """Predictions and δ bands of every method at the test inputs, as CSV text.

    Parameters
    ----------
    run : mdcore.reproduce.CaseRun

    Returns
    -------
    str
        One row per (method, output, test input): the inputs, the observation, the
        predictive mean and sd of z, of δ, and the true δ where it is known.
    """
    _check_run(run)
    case = run.case
    truth = case.true_delta(case.X_test)
    head = (["method", "output"] + [f"{n} [{u}]" for n, u in zip(case.x_names, case.x_units)]
            + ["z_observed", "z_mean", "z_sd", "delta_mean", "delta_sd", "delta_true"])
    rows = []
    for r in run.results:
        p = r.on_test
        for o, name in enumerate(case.output_names):
            for i in range(case.X_test.shape[0]):
                rows.append([r.method.value, name]
                            + [repr(float(v)) for v in case.X_test[i]]
                            + [repr(float(v)) for v in (
                                case.z_test[i, o], p.z_mean[i, o], np.sqrt(p.z_var[i, o]),
                                p.delta_mean[i, o], np.sqrt(p.delta_var[i, o]))]
                            + ["" if truth is None else repr(float(truth[i, o]))])
    return _table(f"{case.name}: predictions at the test inputs (seed {run.seed}); z_sd "
                  "includes the noise", head, rows)


def write_tables(run, folder) -> list[Path]:
    """Write ``nroy.csv`` and ``predictions.csv`` of a run into ``folder`` (created).

    Both tables are made before anything is written, so a bad ``run`` leaves no files.
    """
    _check_run(run)
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise ValueError(f"folder {str(folder)!r} is a file; give a folder for nroy.csv and "
                         "predictions.csv.")
    texts = [nroy_csv(run.hm, run.case.theta_names, run.case.theta_units),
             predictions_csv(run)]
    folder.mkdir(parents=True, exist_ok=True)
    paths = [folder / "nroy.csv", folder / "predictions.csv"]
    for path, text in zip(paths, texts):
        path.write_text(text, encoding="utf-8")
    return paths
