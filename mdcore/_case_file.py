"""Your own case from files: a TOML case file (format: the README, "Your own data"; example
``examples/beam_lab/``), a measurements CSV and a simulator ``package.module:function`` with
the signature of :meth:`mdcore.Case.simulate`: ``simulate(X, theta) -> (n_theta, N, n_out)``,
X (N, d_x) in the CSV's input units, theta (n_theta, p) in the parameters' units. Paths are
relative to the case file.
"""

from __future__ import annotations

import dataclasses
import difflib
import re
import tomllib
from pathlib import Path
from typing import Any

import numpy as np
import scipy.stats

from ._cases import Case, MeasurementsError, parse_measurements, read_measurements
from ._discrepancy import default_phi_prior
from ._history_matching import MAX_RUNS, check_correlation, replicate_summary
from ._priors import ThetaPrior
from ._runs import SimulatorError, SimulatorProcess
from ._validation import as_seed_int, short

#: The column of an uploaded measurements file that marks test rows (1) and training rows (0).
TEST_COLUMN = "test"
#: Largest case file read (a case file is a few hundred bytes; its data live in the CSV).
MAX_CASE_FILE_BYTES = 1_000_000
#: Most training rows of a case's measurements (case files and uploads): every discrepancy GP
#: factorises an N × N matrix of them, so the work grows as N³ (bench/bench_upload_limits.py).
MAX_TRAINING_ROWS = 300


class CaseFileError(ValueError):
    """A case file, its CSV or its simulator is not as documented (:mod:`mdcore._case_file`)."""


class _Reader:
    """Typed access to one table of the TOML file, with errors that name file and key."""

    def __init__(self, path: Path, table: dict, where: str = ""):
        self.path, self.table, self.where = path, table, where

    def _fail(self, key: str, expected: str, found: Any) -> CaseFileError:
        key_name = f"[{self.where}] {key}" if self.where else key
        return CaseFileError(f"{self.path}: {key_name} must be {expected}; found "
                             f"{short(found)}.")

    def has(self, key: str) -> bool:
        return key in self.table

    def sub(self, key: str) -> _Reader:
        value = self.table.get(key)
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
        """Refuse keys the format does not know, each with the nearest allowed key."""
        unknown = [k for k in self.table if k not in keys]
        if unknown and not self.where and len(unknown) == len(self.table):
            raise CaseFileError(f"{self.path}: not a case file: none of its top-level keys is "
                                f"one of {list(keys)} (see examples/beam_lab/beam_lab.toml).")
        if unknown:
            where = f"[{self.where}]" if self.where else "the top level"
            named = "; ".join(short(k) + "".join(
                f" (did you mean {near!r}?)" for near in difflib.get_close_matches(k, keys, 1))
                for k in unknown[:5])
            raise CaseFileError(f"{self.path}: {where} has unknown key(s) {named}; the keys "
                                f"allowed there are {list(keys)}. Check the spelling.")

    def texts(self, key: str, n: int | None = None, default=None) -> tuple[str, ...]:
        value = self.table.get(key, default)
        if not isinstance(value, list) or not value or (n is not None and len(value) != n) \
                or not all(isinstance(v, str) and v.strip() for v in value):
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


def _simulator(path: Path, sim: _Reader) -> SimulatorProcess:
    """The ``[simulator]`` table's function, to run in a process of its own."""
    spec = sim.text("function")
    m = re.fullmatch(r"([A-Za-z_][\w.]*):([A-Za-z_]\w*)", spec)
    if m is None:
        raise sim._fail("function", "'package.module:function'", spec)
    folder = (path.parent / sim.text("path")).resolve() if sim.has("path") else None
    if folder is not None and not folder.is_dir():
        raise CaseFileError(f"{path}: [simulator] path {str(folder)!r} is not a folder.")
    return SimulatorProcess(m.group(1), m.group(2), folder)


def _split(m, source: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """X, z and the test-row mask of measurements whose last input column marks test rows."""
    flag, column = m.X[:, -1], m.input_names[-1]
    if not np.all(np.isin(flag, (0.0, 1.0))):
        bad = flag[~np.isin(flag, (0.0, 1.0))][0]
        raise MeasurementsError([f"{source}: column {column!r} must be 0 (training row) or 1 "
                                 f"(test row) in every row; found {float(bad)!r}."])
    X, z, test = m.X[:, :-1], m.z, flag == 1.0
    n_train, n_test = int((~test).sum()), int(test.sum())
    if n_train > MAX_TRAINING_ROWS:
        raise MeasurementsError([f"{source}: {n_train:,} training rows; at most "
                                 f"{MAX_TRAINING_ROWS:,} are taken (mark more rows as test "
                                 "rows, keep a subset, or average replicate readings)."])
    if n_train < 3 or n_test < 2:
        raise MeasurementsError([f"{source}: column {column!r} marks {n_train} training row(s) "
                                 f"(0) and {n_test} test row(s) (1); at least 3 training rows "
                                 "are needed to fit the discrepancy GP and 2 test rows to score "
                                 "it. Mark more rows."])
    flat = [name for name, values in zip(m.output_names, z[test].T) if np.ptp(values) == 0]
    if flat:
        raise MeasurementsError([f"{source}: every test row (column {column!r} = 1) has the "
                                 f"same {flat[0]!r}; the NMSE divides by its variance over "
                                 f"the test rows, so mark test rows whose {flat[0]} differ."])
    return X, z, test


def _pooled_replicate_var(X: np.ndarray, z: np.ndarray) -> np.ndarray | None:
    """Noise variance per output pooled over replicate groups, (n_out,); None unless every
    input has replicates."""
    _, _, var, counts = replicate_summary(X, z)
    if np.any(counts < 2):
        return None
    dof = (counts - 1)[:, None]
    return np.sum(var * dof, axis=0) / np.sum(dof)


def load_case_file(path, *, seed=0, default_timeout: float | None = None) -> Case:
    """Build a :class:`~mdcore.Case` from a TOML case file (format: the README).

    Parameters
    ----------
    path : str or Path
    seed : int or Generator, default=0
        Seeds the Latin-hypercube initial design.
    default_timeout : float, optional
        Seconds per run when the file sets no ``[simulator] timeout`` (None: no limit);
        it also bounds the trial run at the centre of the box.

    Returns
    -------
    Case
        With ``true_delta`` unknown (None); its simulator runs (and alone imports the
        module) in a process of its own (:class:`mdcore._runs.SimulatorProcess`).

    Raises
    ------
    CaseFileError (a ValueError)
        For a malformed file, key, CSV column or value, or a simulator that cannot be
        imported, fails, times out or returns the wrong shape at the centre of the box.
    """
    path = Path(path)
    seed = as_seed_int(seed)
    if path.is_dir():
        found = sorted(p.name for p in path.glob("*.toml"))[:5]
        raise CaseFileError(f"case file {str(path)!r} is a folder; give the TOML case file "
                            "itself" + (f", e.g. one of {found}." if found else "."))
    if not path.is_file():
        raise CaseFileError(f"case file {str(path)!r} does not exist.")
    if path.stat().st_size > MAX_CASE_FILE_BYTES:
        raise CaseFileError(f"{path}: {path.stat().st_size:,} bytes is not a case file (at most "
                            f"{MAX_CASE_FILE_BYTES:,}); the measurements go in [data] file.")
    try:
        doc = tomllib.loads(path.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise CaseFileError(f"{path}: not valid TOML ({exc}).") from None
    except RecursionError:
        raise CaseFileError(f"{path}: not a case file: its arrays or tables are nested too "
                            "deeply to read (a case file nests two levels).") from None
    top = _Reader(path, doc)
    # Unknown keys first, so that a misspelt key is not reported as a missing one.
    top.only("name", "title", "description", "data", "simulator", "parameters",
             "history_matching")
    name = top.text("name", pattern=r"[A-Za-z0-9_-]+")
    title = top.text("title", default=name)
    description = top.text("description", default=f"Measurements from {path.name}.")

    data = top.sub("data")
    data.only("file", "inputs", "outputs", "input_units", "output_units", "test_column",
              "noise_var")
    csv_path = (path.parent / data.text("file")).resolve()
    inputs, outputs = data.texts("inputs"), data.texts("outputs")
    test_column = data.text("test_column")
    if test_column in inputs + outputs:
        raise CaseFileError(f"{path}: [data] test_column {test_column!r} is also an input or "
                            "an output column.")
    try:
        m = read_measurements(csv_path, inputs=inputs + (test_column,), outputs=outputs)
        X, z, test = _split(m, str(csv_path))
    except ValueError as exc:                     # names the CSV, the line and the column
        raise CaseFileError(f"{path}: [data] file: {exc}") from None
    n_out = len(outputs)
    x_units = data.texts("input_units", len(inputs), default=["-"] * len(inputs))
    out_units = data.texts("output_units", n_out, default=["-"] * n_out)
    noise = data.numbers("noise_var", n_out, positive=True) if data.has("noise_var") \
        else _pooled_replicate_var(X[~test], z[~test])
    if noise is None:
        raise CaseFileError(f"{path}: [data] noise_var is required: some training inputs have "
                            "a single row, so no replicate variance is available; give the "
                            "observation noise variance per output.")

    sim = top.sub("simulator")
    sim.only("function", "path", "timeout")
    simulate = _simulator(path, sim)
    timeout = sim.number("timeout", positive=True) if sim.has("timeout") else default_timeout

    params = doc.get("parameters")
    if not isinstance(params, list) or not params or not all(isinstance(p, dict)
                                                             for p in params):
        raise CaseFileError(f"{path}: [[parameters]] must be one or more tables, one per "
                            f"calibration parameter; found {short(params)}.")
    names, units, bounds, mean, var, true = [], [], [], [], [], []
    for i, table in enumerate(params):
        r = _Reader(path, table, f"parameters {i + 1}")
        r.only("name", "unit", "lower", "upper", "prior_mean", "prior_var", "true")
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
    hm.only("V_m", "initial_design", "V_m_length", "V_m_corr")
    V_m = hm.numbers("V_m", n_out, positive=True)
    length = hm.numbers("V_m_length", n_out) if hm.has("V_m_length") else np.zeros(n_out)
    if np.any(length < 0):
        raise hm._fail("V_m_length", f"a list of {n_out} numbers ≥ 0 (one per output, in the "
                       "inputs' units; 0: independent)", hm.table["V_m_length"])
    corr = hm.table.get("V_m_corr")
    if corr is not None:
        if not (isinstance(corr, list) and len(corr) == n_out and all(
                isinstance(row, list) and len(row) == n_out and all(
                    isinstance(v, (int, float)) and not isinstance(v, bool) for v in row)
                for row in corr)):
            raise hm._fail("V_m_corr", f"a list of {n_out} rows of {n_out} numbers (the "
                           "outputs' correlation matrix)", corr)
        try:
            corr = check_correlation(length, corr, 0.995, n_out)[1]
        except ValueError as exc:
            raise CaseFileError(f"{path}: [history_matching] {exc}") from None
    n_design = hm.integer("initial_design", 2, MAX_RUNS) if hm.has("initial_design") \
        else max(10 * p, 10)
    lhs = scipy.stats.qmc.LatinHypercube(d=p, seed=np.random.default_rng(seed))
    design = scipy.stats.qmc.scale(lhs.random(n_design), box[:, 0], box[:, 1])

    # A trial run at the box centre, within the timeout (import included): a simulator that
    # hangs cannot hang the caller.
    centre = box.mean(axis=1)[None]
    n_train = int((~test).sum())
    where = f"{path}: [simulator] function {simulate.module}:{simulate.function}"
    try:
        Y0 = simulate(X[~test], centre, timeout=timeout)
    except TimeoutError:
        raise CaseFileError(f"{where} did not answer within the timeout of {timeout:g} s at "
                            f"the centre of the parameter box {centre[0].tolist()} (its import "
                            "included); raise [simulator] timeout (or --timeout) if one run "
                            "takes longer.") from None
    except ImportError as exc:
        raise CaseFileError(f"{path}: [simulator] function: {exc}.") from None
    except SimulatorError as exc:
        raise CaseFileError(f"{where} failed at the centre of the parameter box "
                            f"{centre[0].tolist()}: {exc}") from None
    if Y0.shape != (1, n_train, n_out):
        raise CaseFileError(f"{where} must return shape (n_theta, N, n_out) = (1, {n_train}, "
                            f"{n_out}) for one θ at the {n_train} training inputs; it returned "
                            f"{Y0.shape}.")
    Y0 = Y0[0]
    if not np.all(np.isfinite(Y0)):
        raise CaseFileError(f"{where} returned NaN or inf at the centre of the parameter box "
                            f"{centre[0].tolist()}; it must return finite outputs inside the "
                            "box (check its units and the bounds).")
    phi_prior = default_phi_prior(Y0, X[~test], z[~test][:, 0])

    return Case(
        name=name, title=title, description=description, stand_in=False,
        theta_names=tuple(names), theta_units=tuple(units), theta_bounds=box,
        theta_true=None if true[0] is None else np.array(true, dtype=np.float64),
        x_names=inputs, x_units=x_units, output_names=outputs, output_units=out_units,
        X_train=X[~test], z_train=z[~test], X_test=X[test], z_test=z[test], noise_var=noise,
        V_m=V_m, V_m_length=length, V_m_corr=corr,
        phi_prior=phi_prior, theta_prior=ThetaPrior(np.array(mean), np.array(var)),
        initial_design=design, seed=0, _simulator=simulate, timeout=timeout)


def measurements_template(case: Case) -> str:
    """The CSV layout :func:`with_measurements` reads, filled with ``case``'s own data.

    Columns: the inputs, the outputs, then :data:`TEST_COLUMN` (0 = training, 1 = test row);
    one row per observation, replicates as repeated rows.
    """
    from ._export import csv_table
    head = list(case.x_names) + list(case.output_names) + [TEST_COLUMN]
    rows = [[*x_row, *z_row, flag] for X, z, flag in ((case.X_train, case.z_train, 0),
                                                      (case.X_test, case.z_test, 1))
            for x_row, z_row in zip(X, z)]
    return csv_table(head, rows)


def with_measurements(base: Case, text: str, *, source: str = "upload") -> Case:
    """``base``'s simulator, θ box, priors and V_m with your own measurements (parsed, never
    evaluated).

    Parameters
    ----------
    base : Case
    text : str
        CSV text in the layout of :func:`measurements_template`.
    source : str, default="upload"
        The file name, for messages and the case's name.

    Returns
    -------
    Case
        Named ``"<base name> · <source>"``; its noise variance is pooled over replicates when
        every training input has some, else ``base.noise_var``; θ_true and δ unknown (None).

    Raises
    ------
    MeasurementsError (a ValueError)
        One sentence per problem (``problems``), each naming the line and column.
    """
    if not isinstance(text, str):
        raise MeasurementsError([f"text must be CSV text (str); received "
                                 f"{type(text).__name__}."])
    inputs = tuple(base.x_names) + (TEST_COLUMN,)
    m = parse_measurements(text, source=source, inputs=inputs, outputs=base.output_names)
    X = m.X[:, :-1]
    lo, hi = base.X_train.min(axis=0), base.X_train.max(axis=0)
    span = np.where(hi > lo, hi - lo, 1.0)
    outside = np.any((X < lo - 0.5 * span) | (X > hi + 0.5 * span), axis=1)
    if np.any(outside):
        row = X[np.argmax(outside)]
        ranges = ", ".join(f"{n} {a:g}–{b:g} {u}"
                           for n, a, b, u in zip(base.x_names, lo, hi, base.x_units))
        raise MeasurementsError([f"{source}: {int(outside.sum())} row(s) have inputs far "
                                 f"outside the {base.name} range ({ranges}), for example "
                                 f"{row.tolist()}; check the columns' units."])
    X, z, test = _split(m, source)
    n_train = int((~test).sum())
    pooled = _pooled_replicate_var(X[~test], z[~test])
    noise = np.array(base.noise_var, dtype=np.float64) if pooled is None or np.any(pooled <= 0) \
        else pooled
    return dataclasses.replace(
        base, name=f"{base.name} · {Path(source).name}",
        title=f"{base.title.split(' (')[0]}: your measurements ({Path(source).name})",
        description=(f"Your measurements from {Path(source).name} ({n_train} training and "
                     f"{int(test.sum())} test rows) with the {base.name} simulator, θ box and "
                     f"priors. Noise variance {', '.join(f'{v:.3g}' for v in noise)} "
                     + ("(pooled over replicates)." if pooled is not None
                        else f"(the {base.name} default; add replicate rows to estimate it).")),
        stand_in=False, theta_true=None, X_train=X[~test], z_train=z[~test], X_test=X[test],
        z_test=z[test], noise_var=noise, _true_delta=None)
