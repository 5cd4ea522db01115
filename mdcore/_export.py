"""Results out as plain CSV tables (a header row, one row per record), each with a JSON
sidecar saying where it comes from; the JSON of a whole run is :meth:`mdcore.CaseRun.to_dict`.
"""

from __future__ import annotations

import csv
import io
import json
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np

from ._history_matching import HistoryMatchResult
from ._reproduce import CaseRun
from ._validation import check_type

#: Most NROY samples written per wave: the candidates are independent uniform draws, so the
#: first ones retained are a uniform sample of the NROY set too.
NROY_ROWS_PER_WAVE = 10_000
#: The start of a text cell that a spreadsheet runs as a formula (OWASP formula injection).
_FORMULA = ("=", "+", "-", "@", "\t", "\r")


def csv_cell(value, number: Callable[[float], str] = repr):
    """One CSV cell: text a spreadsheet would run gets a leading ``'``; numbers go through
    ``number`` unescaped.

    >>> csv_cell("=1+2"), csv_cell("-x"), csv_cell(-1.5), csv_cell("ω1")
    ("'=1+2", "'-x", '-1.5', 'ω1')
    """
    if isinstance(value, str):
        return "'" + value if value.startswith(_FORMULA) else value
    if isinstance(value, (bool, int, np.integer)):
        return str(int(value))
    return number(float(value))


def with_unit(name: str, unit: str) -> str:
    """A column heading: ``name [unit]``, or ``name`` alone when it has no unit or already
    ends with it ("position_m", "mass (kg)": the unit is not said twice).

    >>> with_unit("E", "GPa"), with_unit("position_m", "m"), with_unit("x [m]", "m")
    ('E [GPa]', 'position_m', 'x [m]')
    """
    said = any(name.endswith(end) for end in (f"_{unit}", f"[{unit}]", f"({unit})", f" {unit}"))
    return name if not unit or said else f"{name} [{unit}]"


def csv_table(header: list, rows: Iterable, number: Callable[[float], str] = repr) -> str:
    """CSV text of a header and rows, every cell through :func:`csv_cell`."""
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow([csv_cell(h) for h in header])
    writer.writerows([csv_cell(c, number) for c in row] for row in rows)
    return out.getvalue()


def _labels(values, name: str, p: int) -> list | None:
    """None, or ``p`` column labels (one per θ component)."""
    if values is None:
        return None
    if isinstance(values, str) or not all(isinstance(v, str) for v in values) \
            or len(values) != p:
        raise ValueError(f"{name} must be a list of {p} strings, one per θ component; "
                         f"received {values!r}.")
    return list(values)


def _kept(wave, threshold: float) -> np.ndarray:
    """Indices of the wave's retained candidates that the table holds (the first ones)."""
    return np.flatnonzero(wave.candidate_implausibility <= threshold)[:NROY_ROWS_PER_WAVE]


def nroy_csv(hm: HistoryMatchResult, names=None, units=None) -> str:
    """CSV text of each wave's first :data:`NROY_ROWS_PER_WAVE` non-implausible θ: columns
    ``wave``, θ (``names`` and ``units``, default ``theta_1 …``) and ``implausibility``, to 7
    significant digits (random draws)."""
    check_type(hm, HistoryMatchResult, "hm",
               "a HistoryMatchResult (history_match or history_match_case)")
    p = hm.problem.p
    names = _labels(names, "names", p) or [f"theta_{i + 1}" for i in range(p)]
    units = _labels(units, "units", p) or [""] * p
    head = ["wave"] + [with_unit(n, u) for n, u in zip(names, units)] + ["implausibility"]
    rows: list = []
    for w in hm.waves:
        keep = _kept(w, hm.problem.options.threshold)
        rows += ([w.index, *theta, imp] for theta, imp in
                 zip(w.candidates[keep], w.candidate_implausibility[keep]))
    return csv_table(head, rows, number=lambda v: f"{v:.7g}")


def predictions_csv(run) -> str:
    """CSV text with a row per (method, output, test input) of a :class:`mdcore.CaseRun`: the
    inputs, the observation, mean and sd of z (noise included) and δ, and the true δ (or "")."""
    check_type(run, CaseRun, "run", "an mdcore.CaseRun (reproduce or run_case)")
    case = run.case
    truth = case.true_delta(case.X_test)
    head = (["method", "output"] + [with_unit(n, u) for n, u in zip(case.x_names, case.x_units)]
            + ["z_observed", "z_mean", "z_sd", "delta_mean", "delta_sd", "delta_true"])
    rows = []
    for r in run.results:
        p = r.on_test
        for o, name in enumerate(case.output_names):
            for i in range(case.X_test.shape[0]):
                rows.append([r.method.value, name, *case.X_test[i], case.z_test[i, o],
                             p.z_mean[i, o], np.sqrt(p.z_var[i, o]), p.delta_mean[i, o],
                             np.sqrt(p.delta_var[i, o]),
                             "" if truth is None else truth[i, o]])
    return csv_table(head, rows)


def write_tables(run, folder) -> list[Path]:
    """Write ``nroy.csv``, ``predictions.csv`` and their JSON sidecars into ``folder``
    (created); every table is made before anything is written. Returns the paths."""
    check_type(run, CaseRun, "run", "an mdcore.CaseRun (reproduce or run_case)")
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise ValueError(f"folder {str(folder)!r} is a file; give a folder for nroy.csv and "
                         "predictions.csv.")
    hm, threshold = run.hm, run.hm.problem.options.threshold
    nroy = {"table": "nroy.csv", "case": run.case.name, "threshold": threshold,
            "rule": hm.problem.options.rule, "status": hm.status, "message": hm.message,
            "waves": [{"wave": w.index, "nroy_fraction": w.nroy_fraction,
                       "candidates": len(w.candidates), "nroy_candidates": len(w.nroy),
                       "rows": len(_kept(w, threshold))} for w in hm.waves],
            "rows_per_wave": f"the first {NROY_ROWS_PER_WAVE:,} non-implausible candidates "
                             "of each wave, uniform in its NROY set"}
    predictions = {"table": "predictions.csv", "case": run.case.name, "seed": run.seed,
                   "methods": [r.method.label for r in run.results],
                   "z_sd": "includes the observation noise",
                   "delta_true": "empty where the true discrepancy is unknown"}
    texts = {"nroy.csv": nroy_csv(hm, run.case.theta_names, run.case.theta_units),
             "nroy.json": json.dumps(nroy, indent=1), "predictions.csv": predictions_csv(run),
             "predictions.json": json.dumps(predictions, indent=1)}
    folder.mkdir(parents=True, exist_ok=True)
    for name, text in texts.items():
        (folder / name).write_text(text, encoding="utf-8")
    return [folder / name for name in texts]
