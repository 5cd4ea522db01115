"""Your own case from files: a TOML case file, a measurements CSV and a simulator function.

A case file names everything :class:`mdcore.cases.Case` needs. Paths are relative to the
case file. The simulator is an import path ``package.module:function`` whose function has
the signature of :meth:`mdcore.cases.Case.simulate`::

    simulate(X, theta) -> ndarray of shape (n_theta, N, n_out)
    # X: (N, d_x) inputs in the CSV's input units; theta: (n_theta, p) in the parameters' units

The format (every key is checked; errors name the file, the key, what was expected and
what was found)::

    name = "my-beam"                     # letters, digits, "-" and "_"
    title = "Cracked beam in the lab"    # optional
    description = "..."                  # optional

    [data]
    file = "measurements.csv"            # columns named below; '#' lines are comments
    inputs = ["x_m"]                     # the columns that form X
    outputs = ["deflection_mm"]          # the columns that form z
    input_units = ["m"]                  # optional, one per input
    output_units = ["mm"]                # optional, one per output
    test_column = "test"                 # 1 = held-out test row, 0 = training row
    noise_var = [0.001]                  # observation noise variance per output; optional
                                         # when every training input has replicate rows
                                         # (default: the pooled replicate variance)

    [simulator]
    function = "my_simulator:deflection" # module:function
    path = "."                           # optional folder put on sys.path to import it

    [[parameters]]                       # one table per calibration parameter θ
    name = "E"
    unit = "GPa"                         # optional
    lower = 50.0
    upper = 90.0
    prior_mean = 70.0                    # optional (KOH's Gaussian prior);
    prior_var = 36.0                     #   default: box centre and (width / 4)²
    true = 68.0                          # optional: the truth, if known (synthetic data)

    [history_matching]
    V_m = [0.05]                         # model-discrepancy variance per output (units²)
    initial_design = 20                  # optional: Latin-hypercube runs of wave 1

Examples
--------
>>> from pathlib import Path
>>> from mdcore.case_file import load_case_file
>>> examples = Path(__file__).resolve().parent.parent / "examples"
>>> case = load_case_file(examples / "beam_lab" / "beam_lab.toml")   # doctest: +SKIP
"""

from __future__ import annotations

import dataclasses
import importlib
import re
import sys
import tomllib
from pathlib import Path
from typing import Any

import numpy as np
import scipy.stats

from .cases import Case, MeasurementsError, parse_measurements, read_measurements
from .discrepancy import default_phi_prior
from .priors import ThetaPrior

__all__ = ["load_case_file", "CaseFileError", "MAX_TRAINING_ROWS", "TEST_COLUMN",
           "measurements_template", "with_measurements"]

#: The column of an uploaded measurements file that marks test rows (1) and training rows (0).
TEST_COLUMN = "test"
#: Most training rows of a case's measurements (case files and uploads; every file also has
#: at most :data:`mdcore.cases.MAX_ROWS` rows in all). Every discrepancy GP factorises an
#: N × N matrix of the training rows, per output and per (θ, φ) pair: the work grows as
#: N³. At 300 training rows and 700 test rows, all distinct, the app's defaults (waves to
#: convergence, then scenarios 1–3) peak at 0.46 GB and take up to 2 minutes (shear-5's
#: five outputs): ``python bench/bench_upload_limits.py``.
MAX_TRAINING_ROWS = 300


def _check_training_rows(source, n_train: int) -> str | None:
    """The problem with ``n_train`` training rows, or None."""
    if n_train <= MAX_TRAINING_ROWS:
        return None
    return (f"{source}: {n_train:,} training rows; at most {MAX_TRAINING_ROWS:,} are taken "
            f"(mark more rows as test rows, keep a subset, or average replicate readings).")


class CaseFileError(ValueError):
    """A case file, its CSV or its simulator is not as documented (:mod:`mdcore.case_file`)."""


class _Reader:
    """Typed access to one table of the TOML file, with errors that name file and key."""

    def __init__(self, path: Path, table: dict, where: str = ""):
        self.path, self.table, self.where = path, table, where

    def _fail(self, key: str, expected: str, found: Any) -> CaseFileError:
        key_name = f"[{self.where}] {key}" if self.where else key
        return CaseFileError(f"{self.path}: {key_name} must be {expected}; found {found!r}.")

    def has(self, key: str) -> bool:
        return key in self.table

    def sub(self, key: str, *, required: bool = True) -> _Reader:
        value = self.table.get(key)
        if value is None and not required:
            return _Reader(self.path, {}, key)
        if not isinstance(value, dict):
            raise self._fail(key, "a table ([" + key + "])", value)
        return _Reader(self.path, value, key)

    def text(self, key: str, default: str | None = None, pattern: str | None = None) -> str:
        value = self.table.get(key, default)
        if not isinstance(value, str) or not value.strip():
            raise self._fail(key, "a non-empty string", value)
        if pattern is not None and re.fullmatch(pattern, value) is None:
            raise self._fail(key, f"a string matching {pattern}", value)
        return value

    def number(self, key: str, default: float | None = None, *, positive: bool = False) -> float:
        value = self.table.get(key, default)
        if isinstance(value, bool) or not isinstance(value, (int, float)) \
                or not np.isfinite(value) or (positive and value <= 0):
            raise self._fail(key, "a positive number" if positive else "a finite number", value)
        return float(value)

    def integer(self, key: str, minimum: int, maximum: int | None = None) -> int:
        value = self.table.get(key)
        if isinstance(value, bool) or not isinstance(value, int) or value < minimum \
                or (maximum is not None and value > maximum):
            limit = "" if maximum is None else f" and ≤ {maximum:,}"
            raise self._fail(key, f"an integer ≥ {minimum}{limit}", value)
        return value

    def only(self, *keys: str) -> None:
        """Refuse keys the format does not know (a misspelt optional key is not ignored)."""
        unknown = sorted(k for k in self.table if k not in keys)
        if unknown:
            where = f"[{self.where}]" if self.where else "the top level"
            raise CaseFileError(f"{self.path}: {where} has unknown key(s) {unknown}; the keys "
                                f"allowed there are {list(keys)}. Check the spelling.")

    def texts(self, key: str, n: int | None = None, default=None) -> tuple[str, ...]:
        value = self.table.get(key, default)
        if not isinstance(value, list) or not value or not all(
                isinstance(v, str) and v.strip() for v in value) or (n is not None
                                                                     and len(value) != n):
            size = "" if n is None else f" of {n}"
            raise self._fail(key, f"a list{size} of non-empty strings", value)
        return tuple(value)

    def numbers(self, key: str, n: int, *, positive: bool = False) -> np.ndarray:
        value = self.table.get(key)
        if isinstance(value, (int, float)) and not isinstance(value, bool) and n == 1:
            value = [value]
        ok = isinstance(value, list) and len(value) == n and all(
            isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v)
            and (v > 0 or not positive) for v in value)
        if not ok:
            what = "positive numbers" if positive else "finite numbers"
            raise self._fail(key, f"a list of {n} {what} (one per output)", value)
        return np.asarray(value, dtype=np.float64)


def _import_simulator(path: Path, spec: str, folder: Path | None):
    """The function named ``module:function``, importing from ``folder`` if given."""
    m = re.fullmatch(r"([A-Za-z_][\w.]*):([A-Za-z_]\w*)", spec)
    if m is None:
        raise CaseFileError(f"{path}: [simulator] function must look like "
                            f"'package.module:function'; found {spec!r}.")
    if folder is not None:
        if not folder.is_dir():
            raise CaseFileError(f"{path}: [simulator] path {str(folder)!r} is not a folder.")
        if str(folder) not in sys.path:
            sys.path.insert(0, str(folder))
    try:
        module = importlib.import_module(m.group(1))
    except Exception as exc:
        raise CaseFileError(f"{path}: [simulator] function: cannot import module "
                            f"{m.group(1)!r} ({type(exc).__name__}: {exc}); set [simulator] "
                            "path to the folder that contains it.") from None
    fn = getattr(module, m.group(2), None)
    if not callable(fn):
        raise CaseFileError(f"{path}: [simulator] function: module {m.group(1)!r} has no "
                            f"function {m.group(2)!r}.")
    return fn


def _pooled_replicate_var(X: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Observation noise variance per output pooled over replicate groups, (n_out,)."""
    from .history_matching import replicate_summary
    _, _, var, counts = replicate_summary(X, z)
    dof = (counts - 1)[:, None]
    return np.sum(np.where(dof > 0, var * dof, 0.0), axis=0) / np.sum(dof)


def load_case_file(path, *, seed=0) -> Case:
    """Build a :class:`~mdcore.cases.Case` from a TOML case file (format in the module doc).

    Parameters
    ----------
    path : str or Path
        The case file.
    seed : int or Generator, default=0
        Seeds the Latin-hypercube initial design (the data are read, not drawn).

    Returns
    -------
    Case
        ``true_delta`` is unknown (None) for a case read from files.

    Raises
    ------
    CaseFileError (a ValueError)
        For a missing or malformed file, key, CSV column or value, or a simulator that
        cannot be imported or returns the wrong shape; the message names the file and key.
    """
    path = Path(path)
    if not path.is_file():
        raise CaseFileError(f"case file {str(path)!r} does not exist.")
    try:
        doc = tomllib.loads(path.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise CaseFileError(f"{path}: not valid TOML ({exc}).") from None
    top = _Reader(path, doc)
    name = top.text("name", pattern=r"[A-Za-z0-9_-]+")
    title = top.text("title", default=name)
    description = top.text("description", default=f"Measurements from {path.name}.")

    data = top.sub("data")
    csv_path = (path.parent / data.text("file")).resolve()
    inputs, outputs = data.texts("inputs"), data.texts("outputs")
    test_column = data.text("test_column")
    if test_column in inputs + outputs:
        raise CaseFileError(f"{path}: [data] test_column {test_column!r} is also an input or "
                            "an output column.")
    try:
        m = read_measurements(csv_path, inputs=inputs + (test_column,), outputs=outputs)
    except ValueError as exc:                     # names the CSV, the line and the column
        raise CaseFileError(f"{path}: [data] file: {exc}") from None
    flag = m.X[:, -1]
    if not np.all(np.isin(flag, (0.0, 1.0))):
        bad = flag[~np.isin(flag, (0.0, 1.0))][0]
        raise CaseFileError(f"{csv_path}: column {test_column!r} must be 0 (training row) or 1 "
                            f"(test row) in every row; found {float(bad)!r}.")
    X, z, test = m.X[:, :-1], m.z, flag == 1.0
    if not np.any(~test) or not np.any(test):
        raise CaseFileError(f"{csv_path}: column {test_column!r} must mark at least one "
                            f"training row (0) and one test row (1); found {int((~test).sum())} "
                            f"and {int(test.sum())}.")
    too_many = _check_training_rows(csv_path, int((~test).sum()))
    if too_many:
        raise CaseFileError(too_many)
    n_out = len(outputs)
    x_units = data.texts("input_units", len(inputs), default=["-"] * len(inputs))
    out_units = data.texts("output_units", n_out, default=["-"] * n_out)
    noise = data.numbers("noise_var", n_out, positive=True) if data.has("noise_var") else None
    _, counts = np.unique(X[~test], axis=0, return_counts=True)
    if noise is None and np.any(counts < 2):
        raise CaseFileError(f"{path}: [data] noise_var is required: some training inputs have "
                            "a single row, so no replicate variance is available; give the "
                            "observation noise variance per output.")

    sim = top.sub("simulator")
    folder = (path.parent / sim.text("path")).resolve() if sim.has("path") else None
    simulate = _import_simulator(path, sim.text("function"), folder)

    params = doc.get("parameters")
    if not isinstance(params, list) or not params or not all(isinstance(p, dict)
                                                             for p in params):
        raise CaseFileError(f"{path}: [[parameters]] must be one or more tables, one per "
                            f"calibration parameter; found {params!r}.")
    names, units, bounds, mean, var, true = [], [], [], [], [], []
    for i, table in enumerate(params):
        r = _Reader(path, table, f"parameters {i + 1}")
        names.append(r.text("name"))
        units.append(r.text("unit", default="-"))
        lo, hi = r.number("lower"), r.number("upper")
        if not lo < hi:
            raise r._fail("upper", f"greater than lower = {lo:g}", hi)
        bounds.append((lo, hi))
        mean.append(r.number("prior_mean", default=0.5 * (lo + hi)))
        var.append(r.number("prior_var", default=((hi - lo) / 4.0) ** 2, positive=True))
        true.append(r.number("true") if r.has("true") else None)
    if len(set(names)) != len(names):
        raise CaseFileError(f"{path}: [[parameters]] names must be distinct; found {names}.")
    if any(t is None for t in true) and not all(t is None for t in true):
        raise CaseFileError(f"{path}: [[parameters]] true must be given for every parameter "
                            "or for none.")
    p = len(names)
    box = np.array(bounds)

    hm = top.sub("history_matching")
    # Unknown keys, once the required ones are known to be there: a misspelt optional key
    # (noise_variance, initial_desing) is an error, not silently ignored.
    top.only("name", "title", "description", "data", "simulator", "parameters",
             "history_matching")
    data.only("file", "inputs", "outputs", "input_units", "output_units", "test_column",
              "noise_var")
    sim.only("function", "path")
    for i, table in enumerate(params):
        _Reader(path, table, f"parameters {i + 1}").only(
            "name", "unit", "lower", "upper", "prior_mean", "prior_var", "true")
    hm.only("V_m", "initial_design")
    V_m = hm.numbers("V_m", n_out, positive=True)
    from .history_matching import MAX_RUNS
    n_design = hm.integer("initial_design", 2, MAX_RUNS) if hm.has("initial_design") \
        else max(10 * p, 10)
    lhs = scipy.stats.qmc.LatinHypercube(d=p, seed=np.random.default_rng(seed))
    design = scipy.stats.qmc.scale(lhs.random(n_design), box[:, 0], box[:, 1])

    # The simulator must run and return (n_theta, N, n_out) at the box centre.
    centre = box.mean(axis=1)[None]
    try:
        y0 = np.asarray(simulate(X[~test][:2], centre), dtype=np.float64)
    except Exception as exc:
        raise CaseFileError(f"{path}: [simulator] function failed at the centre of the "
                            f"parameter box {centre[0].tolist()}: {type(exc).__name__}: "
                            f"{exc}") from None
    if y0.shape != (1, min(2, int((~test).sum())), n_out):
        raise CaseFileError(f"{path}: [simulator] function must return shape (n_theta, N, "
                            f"n_out) = (1, {min(2, int((~test).sum()))}, {n_out}) for one θ at "
                            f"two inputs; it returned {y0.shape}.")
    Y0 = np.asarray(simulate(X[~test], centre), dtype=np.float64)[0]
    if not (np.all(np.isfinite(y0)) and np.all(np.isfinite(Y0))):
        raise CaseFileError(f"{path}: [simulator] function returned NaN or inf at the centre of "
                            f"the parameter box {centre[0].tolist()}; it must return finite "
                            "outputs inside the box (check its units and the bounds).")
    phi_prior = default_phi_prior(Y0, X[~test], z[~test][:, 0])

    return Case(
        name=name, title=title, description=description, stand_in=False,
        theta_names=tuple(names), theta_units=tuple(units), theta_bounds=box,
        theta_true=None if true[0] is None else np.array(true, dtype=np.float64),
        x_names=inputs, x_units=x_units, output_names=outputs, output_units=out_units,
        X_train=X[~test], z_train=z[~test], X_test=X[test], z_test=z[test],
        noise_var=noise if noise is not None else _pooled_replicate_var(X[~test], z[~test]),
        V_m=V_m,
        phi_prior=phi_prior, theta_prior=ThetaPrior(np.array(mean), np.array(var)),
        initial_design=design, seed=0, _simulator=simulate, _true_delta=None)


def measurements_template(case: Case) -> str:
    """The CSV layout :func:`with_measurements` reads, filled with ``case``'s own data.

    Columns: the case's inputs, its outputs, then :data:`TEST_COLUMN` (0 = training row,
    1 = test row); one row per observation, replicates as repeated rows.
    """
    head = list(case.x_names) + list(case.output_names) + [TEST_COLUMN]
    units = ", ".join(f"{n} [{u}]" for n, u in zip(case.x_names + case.output_names,
                                                   case.x_units + case.output_units))
    lines = [f"# {case.title}: measurements for the simulator of {case.name}",
             f"# units: {units}; {TEST_COLUMN}: 1 = held-out test row, 0 = training row",
             ",".join(f'"{h}"' if "," in h else h for h in head)]
    for X, z, flag in ((case.X_train, case.z_train, 0), (case.X_test, case.z_test, 1)):
        for x_row, z_row in zip(X, z):
            lines.append(",".join([repr(float(v)) for v in (*x_row, *z_row)] + [str(flag)]))
    return "\n".join(lines) + "\n"


def with_measurements(base: Case, text: str, *, source: str = "upload") -> Case:
    """``base``'s simulator, parameters and priors with your own measurements.

    For measurements of the structure a built-in case simulates (your own beam
    deflections, say). The text is parsed, never evaluated.

    Parameters
    ----------
    base : Case
        The built-in case whose simulator, θ box, priors and V_m are kept.
    text : str
        CSV text in the layout of :func:`measurements_template`: the inputs
        ``base.x_names``, the outputs ``base.output_names`` and :data:`TEST_COLUMN`.
    source : str, default="upload"
        The file name, for messages and the case's name.

    Returns
    -------
    Case
        Named ``"<base name> · <source>"``. The observation noise variance is the
        pooled replicate variance when every training input has replicates, otherwise
        ``base.noise_var``. θ_true and the true δ are unknown (None).

    Raises
    ------
    MeasurementsError (a ValueError)
        With one sentence per problem (``problems``), each naming the line and column.
    """
    if not isinstance(text, str):
        raise MeasurementsError([f"text must be CSV text (str); received "
                                 f"{type(text).__name__}."])
    inputs = tuple(base.x_names) + (TEST_COLUMN,)
    m = parse_measurements(text, source=source, inputs=inputs, outputs=base.output_names)
    flag = m.X[:, -1]
    problems = []
    if not np.all(np.isin(flag, (0.0, 1.0))):
        bad = flag[~np.isin(flag, (0.0, 1.0))][0]
        problems.append(f"{source}: column {TEST_COLUMN!r} must be 0 (training row) or 1 "
                        f"(test row) in every row; found {float(bad)!r}.")
    X, z, test = m.X[:, :-1], m.z, flag == 1.0
    if not problems and (not np.any(~test) or not np.any(test)):
        problems.append(f"{source}: column {TEST_COLUMN!r} must mark at least one training "
                        f"row (0) and one test row (1); found {int((~test).sum())} and "
                        f"{int(test.sum())}.")
    lo, hi = base.X_train.min(axis=0), base.X_train.max(axis=0)
    span = np.where(hi > lo, hi - lo, 1.0)
    outside = np.any((X < lo - 0.5 * span) | (X > hi + 0.5 * span), axis=1)
    if np.any(outside):
        row = X[np.argmax(outside)]
        ranges = ", ".join(f"{n} {a:g}–{b:g} {u}"
                           for n, a, b, u in zip(base.x_names, lo, hi, base.x_units))
        problems.append(f"{source}: {int(outside.sum())} row(s) have inputs far outside the "
                        f"{base.name} range ({ranges}), for example {row.tolist()}; check "
                        "the columns' units.")
    n_train = int((~test).sum())
    if not problems and n_train < 3:
        problems.append(f"{source}: {n_train} training row(s); at least 3 are needed to fit "
                        "a discrepancy GP.")
    too_many = _check_training_rows(source, n_train)
    if not problems and too_many:
        problems.append(too_many)
    if problems:
        raise MeasurementsError(problems)
    _, counts = np.unique(X[~test], axis=0, return_counts=True)
    noise = (_pooled_replicate_var(X[~test], z[~test]) if np.all(counts >= 2)
             else np.array(base.noise_var, dtype=np.float64))
    if np.any(noise <= 0):
        noise = np.array(base.noise_var, dtype=np.float64)
    name = f"{base.name} · {Path(source).name}"
    # replace() keeps the simulator, the θ box and the priors of the base case.
    return dataclasses.replace(
        base, name=name,
        title=f"{base.title.split(' (')[0]}: your measurements ({Path(source).name})",
        description=(f"Your measurements from {Path(source).name} ({n_train} training and "
                     f"{int(test.sum())} test rows) with the {base.name} simulator, θ box and "
                     f"priors. Noise variance {', '.join(f'{v:.3g}' for v in noise)} "
                     + ("(pooled over replicates)." if np.all(counts >= 2)
                        else f"(the {base.name} default; add replicate rows to estimate it).")),
        stand_in=False, theta_true=None, X_train=X[~test], z_train=z[~test], X_test=X[test],
        z_test=z[test], noise_var=noise, _true_delta=None)
