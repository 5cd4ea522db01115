"""The three case studies (docs/cases.md) and the measurement-file loader."""

from __future__ import annotations

import csv
import importlib.resources
import io
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import numpy as np

from ._priors import GaussianPrior, ThetaPrior
from ._runs import SimulatorProcess, call_with_timeout
from ._validation import (
    MAX_MAGNITUDE,
    as_float_array,
    as_positive_float,
    as_seed_int,
    choose,
    short,
)
from .simulators import natural_frequencies, tip_deflection

#: The shipped synthetic shear-5 measurements, package data (a ``Traversable``; regenerate
#: in a checkout with ``python assets/make_shear5_data.py``).
SHEAR5_CSV = importlib.resources.files("mdcore").joinpath("data", "shear5_measurements.csv")


@dataclass(frozen=True, eq=False)
class Case:
    """A calibration problem: simulator, data, bounds, truth and defaults.

    Shapes use ``p`` parameters, ``d_x`` inputs and ``n_out`` outputs; replicate
    observations are repeated rows of ``X``.

    Attributes
    ----------
    name, title, description : str
        Identifier, one-line label, and where the data come from.
    stand_in : bool
        Whether the data stand in for measurements that are not public (shear-5's).
    theta_names, theta_units : tuple of str
    theta_bounds : ndarray of shape (p, 2)
        Prior box, in ``theta_units``.
    theta_true : ndarray of shape (p,) or None
        The parameters of the data-generating structure, where known.
    x_names, x_units, output_names, output_units : tuple of str
    X_train, X_test : ndarray of shape (N, d_x)
    z_train, z_test : ndarray of shape (N, n_out)
    noise_var : ndarray of shape (n_out,)
        Variance of the measurement noise, output units².
    V_m : ndarray of shape (n_out,)
        Default model-discrepancy variance for history matching.
    phi_prior : GaussianPrior
        Prior of each output's discrepancy-GP log hyperparameters (docs/method.md §2,
        ``P = 2 + n_out + d_x``).
    theta_prior : ThetaPrior
        Gaussian prior of θ for the Kennedy–O'Hagan baseline (docs/method.md §7): ``mean`` in
        ``theta_units``, ``var`` in their squares.
    initial_design : ndarray of shape (R, p)
        θ of the first emulator's simulator runs.
    seed : int
        Seed the noise was drawn with.
    timeout : float or None, default=None
        Seconds one simulator run (one θ) may take, n × timeout for n θ (None: no limit; set
        it with ``dataclasses.replace``). Past it a run raises ``TimeoutError`` (a failed run in
        history matching, an error in the scenarios): a case file's simulator process is
        killed, another simulator's thread abandoned.
    V_m_length : ndarray of shape (n_out,), default 0
        Correlation length ℓ_m of V_m over x per output, in ``x_units``, for the multivariate
        rule (0: independent, as on the built-ins).
    V_m_corr : ndarray of shape (n_out, n_out) or None, default None
        Default correlation of the outputs' discrepancies (None: independent).
    """

    name: str
    title: str
    description: str
    stand_in: bool
    theta_names: tuple
    theta_units: tuple
    theta_bounds: np.ndarray
    theta_true: np.ndarray | None
    x_names: tuple
    x_units: tuple
    output_names: tuple
    output_units: tuple
    X_train: np.ndarray
    z_train: np.ndarray
    X_test: np.ndarray
    z_test: np.ndarray
    noise_var: np.ndarray
    V_m: np.ndarray
    phi_prior: GaussianPrior
    theta_prior: ThetaPrior
    initial_design: np.ndarray
    seed: int
    _simulator: Callable = field(repr=False)
    _true_delta: Callable | None = field(repr=False, default=None)
    timeout: float | None = None
    V_m_length: np.ndarray = field(default_factory=lambda: np.zeros(1))
    V_m_corr: np.ndarray | None = None

    def __post_init__(self):
        if self.timeout is not None:
            object.__setattr__(self, "timeout", as_positive_float(
                self.timeout, "timeout", "It is in seconds per simulator run; None: no limit."))

    @property
    def p(self) -> int:
        return self.theta_bounds.shape[0]

    def scaled_v_m(self, v_m_1: float) -> np.ndarray:
        """V_m per output (n_out,) from ``v_m_1`` for output 1: the others scale by
        ``(z̄_i / z̄_1)²``, so one number sets a discrepancy of the same relative size on every
        output (the rule of shear-5's default, docs/method.md §5)."""
        zbar = np.abs(self.z_train.mean(axis=0))
        return v_m_1 * (zbar / zbar[0]) ** 2

    @property
    def d_x(self) -> int:
        return self.X_train.shape[1]

    @property
    def n_out(self) -> int:
        return len(self.output_names)

    def _inputs(self, X) -> np.ndarray:
        X = as_float_array(X, "X", ndim=2, allow_empty=True)
        if X.shape[1] != self.d_x:
            raise ValueError(f"X must have shape (N, {self.d_x}) for {self.name} "
                             f"({', '.join(self.x_names)}); received {X.shape}.")
        return X

    def simulate(self, X, theta) -> np.ndarray:
        """The simulator at ``X`` (N, d_x) in ``x_units`` and ``theta`` (n_theta, p) or (p,) in
        ``theta_units``: outputs (n_theta, N, n_out) in ``output_units``."""
        X = self._inputs(X)
        theta = np.atleast_2d(as_float_array(theta, "theta"))
        if theta.ndim != 2 or theta.shape[1] != self.p:
            raise ValueError(f"theta must have shape (n_theta, {self.p}) for {self.name} "
                             f"({', '.join(self.theta_names)}); received {theta.shape}.")
        limit = None if self.timeout is None else self.timeout * len(theta)  # per θ
        if isinstance(self._simulator, SimulatorProcess):
            return self._simulator(X, theta, timeout=limit)
        if limit is None:
            return self._simulator(X, theta)
        return call_with_timeout(self._simulator, X, theta, limit)

    def true_delta(self, X) -> np.ndarray | None:
        """Noise-free true discrepancy at ``X`` (N, d_x) -> (N, n_out), or None if unknown."""
        return None if self._true_delta is None else self._true_delta(self._inputs(X))


# ---------------------------------------------------------------------------------------
# beam-1d and beam-2d (paper §4.1–4.2)

BEAM_NOISE_VAR = 1e-3          # mm²
BEAM_V_M = 0.05                # mm²


def _beam_prior(d_x: int) -> GaussianPrior:
    """docs/cases.md φ prior of the beams: log σ_f ~ N(log 2, 1), log ℓ_y ~ N(log 1 mm, 1),
    log ℓ_x ~ N(log 0.3 m, 1), log σ_n² ~ N(log 1e-3, 4), i.e. log σ_n ~ N(½ log 1e-3, 1)."""
    mean = [np.log(2.0), 0.0] + [np.log(0.3)] * d_x + [0.5 * np.log(1e-3)]
    return GaussianPrior(mean=np.array(mean), var=np.ones(3 + d_x))


def _beam1d_simulator(X, theta):
    # θ = (l_cr [mm], E [GPa]); x = crack location [m].
    deflection = tip_deflection(X[None, :, 0], 1e-3 * theta[:, 0, None], 1e9 * theta[:, 1, None])
    return deflection[..., None]


def _beam1d_delta(X):
    x = X[:, 0]
    return (0.3 * (1.5 - x) * np.sin(1.8 * (x - 0.2) * 2 * np.pi))[:, None]      # Eq. 19


def _beam2d_simulator(X, theta):
    # θ = (E [GPa]); x = (crack location [m], crack length [m]).
    return tip_deflection(X[None, :, 0], X[None, :, 1], 1e9 * theta[:, 0, None])[..., None]


def _beam2d_delta(X):
    x1, x2 = X[:, 0], X[:, 1]
    return (0.3 * np.sin(3 * x1 * 2 * np.pi - 0.2)
            - 0.2 * (1 - x1) * np.cos(6 * x2 * 2 * np.pi))[:, None]                # Eq. 20


def _beam_case(seed: int, theta_true, X_train, X_test, simulator, delta, **fields) -> Case:
    """A beam case whose data are ``simulator + delta`` at ``theta_true`` plus noise (train's
    draws first, then test's)."""
    rng = np.random.default_rng(seed)
    clean = [simulator(X, theta_true[None])[0] + delta(X) for X in (X_train, X_test)]
    z_train, z_test = (c + np.sqrt(BEAM_NOISE_VAR) * rng.standard_normal(c.shape) for c in clean)
    return Case(stand_in=False, theta_true=theta_true, output_names=("tip deflection",),
                output_units=("mm",), X_train=X_train, z_train=z_train, X_test=X_test,
                z_test=z_test, noise_var=np.array([BEAM_NOISE_VAR]), V_m=np.array([BEAM_V_M]),
                phi_prior=_beam_prior(X_train.shape[1]), seed=seed, _simulator=simulator,
                _true_delta=delta, **fields)


def _beam1d(seed: int) -> Case:
    grid = np.stack(np.meshgrid(np.linspace(0, 50, 5), np.linspace(50, 90, 5), indexing="ij"),
                    axis=-1).reshape(-1, 2)
    return _beam_case(
        seed, np.array([38.0, 68.0]), np.linspace(0.1, 0.9, 13)[:, None],
        np.linspace(0.1, 0.9, 200)[:, None], _beam1d_simulator, _beam1d_delta,
        name="beam-1d", title="Cracked cantilever, crack location as input (paper §4.1)",
        description=("Synthetic data from the paper's §4.1 set-up: tip deflection of a 1 m "
                     "cantilever with a Christides–Barr crack (l_cr = 38 mm, E = 68 GPa) plus "
                     "the discrepancy of Eq. 19 and Gaussian noise of variance 0.001 mm²."),
        theta_names=("l_cr", "E"), theta_units=("mm", "GPa"),
        theta_bounds=np.array([[0.0, 50.0], [50.0, 90.0]]), x_names=("crack location",),
        x_units=("m",), initial_design=grid,
        # docs/method.md §7: l_cr ~ N(35, 10) mm, E ~ N(70, 36) GPa (second argument a variance).
        theta_prior=ThetaPrior(mean=np.array([35.0, 70.0]), var=np.array([10.0, 36.0])))


def _grid2(n: int) -> np.ndarray:
    g1, g2 = np.meshgrid(np.linspace(0.1, 0.5, n), np.linspace(0.0, 0.05, n), indexing="ij")
    return np.column_stack([g1.ravel(), g2.ravel()])


def _beam2d(seed: int) -> Case:
    return _beam_case(
        seed, np.array([68.0]), _grid2(8), _grid2(20), _beam2d_simulator, _beam2d_delta,
        name="beam-2d",
        title="Cracked cantilever, crack location and length as inputs (paper §4.2)",
        description=("Synthetic data from the paper's §4.2 set-up: crack location "
                     "x₁ ∈ [0.1, 0.5] m and crack length x₂ ∈ [0, 0.05] m are inputs, "
                     "E = 68 GPa is calibrated; discrepancy of Eq. 20 and Gaussian noise of "
                     "variance 0.001 mm²."),
        theta_names=("E",), theta_units=("GPa",), theta_bounds=np.array([[50.0, 90.0]]),
        x_names=("crack location", "crack length"), x_units=("m", "m"),
        initial_design=np.linspace(50, 90, 4)[:, None],
        # Not in the paper: beam-1d's E ~ N(70, 36) GPa, the same material.
        theta_prior=ThetaPrior(mean=np.array([70.0]), var=np.array([36.0])))


# ---------------------------------------------------------------------------------------
# shear-5 (paper §5, synthetic stand-in)

SHEAR5_NOMINAL = np.array([71.0, 0.33, 2770.0])          # E [GPa], ν, ρ [kg/m³]
SHEAR5_REAL = dict(E=70e9, nu=0.33, rho=2700.0, extra_floor_mass=0.03, rocking_stiffness=2.3e6)
SHEAR5_NOISE_SD = 0.004                                  # Hz
SHEAR5_MASSES = np.round(np.arange(6) * 0.1, 10)         # kg
SHEAR5_TRAIN_MASSES = (0.0, 0.3, 0.5)
SHEAR5_REPEATS = 10
SHEAR5_OUTPUTS = tuple(f"f{i}_Hz" for i in range(1, 6))


def _shear5_simulator(X, theta):
    # θ = (E [GPa], ν, ρ [kg/m³]); x = added mass on floor 4 [kg].
    return natural_frequencies(1e9 * theta[:, 0, None], theta[:, 1, None], theta[:, 2, None],
                               X[None, :, 0])


def _shear5_real(X):
    return natural_frequencies(SHEAR5_REAL["E"], SHEAR5_REAL["nu"], SHEAR5_REAL["rho"], X[:, 0],
                               extra_floor_mass=SHEAR5_REAL["extra_floor_mass"],
                               rocking_stiffness=SHEAR5_REAL["rocking_stiffness"])


def _shear5_delta(X):
    theta = np.array([[SHEAR5_REAL["E"] / 1e9, SHEAR5_REAL["nu"], SHEAR5_REAL["rho"]]])
    return _shear5_real(X) - _shear5_simulator(X, theta)[0]


def make_shear5_measurements(seed: int = 0) -> str:
    """CSV text of the synthetic shear-5 measurements (the shipped file: ``seed=0``): ten
    noisy repeats per added mass of the "real" structure's frequencies (docs/cases.md)."""
    rng = np.random.default_rng(seed)
    X = np.repeat(SHEAR5_MASSES, SHEAR5_REPEATS)[:, None]
    z = _shear5_real(X) + SHEAR5_NOISE_SD * rng.standard_normal((X.shape[0], 5))
    out = io.StringIO()
    out.write(f"# SYNTHETIC data, not laboratory measurements. Made by assets/make_shear5_data.py "
              f"(make_shear5_measurements in mdcore/_cases.py, seed={seed}): 'real' 5-storey shear "
              "building E=70 GPa nu=0.33 rho=2700 kg/m3, +0.03 kg per floor, rocking spring "
              "2.3e6 N.m/rad, noise sd 0.004 Hz, 10 repeats per mass.\n")
    out.write("mass_kg,repeat," + ",".join(SHEAR5_OUTPUTS) + "\n")
    for i in range(X.shape[0]):
        out.write(f"{X[i, 0]:.1f},{i % SHEAR5_REPEATS + 1},"
                  + ",".join(f"{v:.6f}" for v in z[i]) + "\n")
    return out.getvalue()


class Measurements(NamedTuple):
    """Observations of a CSV file: ``X`` (N, d_x), ``z`` (N, n_out), the column names and the
    leading ``#`` lines (provenance)."""

    X: np.ndarray
    z: np.ndarray
    input_names: tuple
    output_names: tuple
    comments: tuple


#: Problems listed before a measurements file is given up on (the rest are counted).
MAX_PROBLEMS = 5
#: Most data rows of a measurements file (uploads and case files; beam-2d's template has 464).
#: Training rows have a lower limit (:data:`mdcore._case_file.MAX_TRAINING_ROWS`).
MAX_ROWS = 1_000


class MeasurementsError(ValueError):
    """A measurements file that cannot be read; ``problems``: one sentence per problem."""

    def __init__(self, problems: list[str]):
        self.problems = tuple(problems)
        super().__init__(" ".join(self.problems))


def read_measurements(path, *, inputs, outputs=None, ignore=("repeat",)) -> Measurements:
    """:func:`parse_measurements` of a UTF-8 CSV file."""
    path = Path(path)
    if not path.is_file():
        raise MeasurementsError([f"measurement file {str(path)!r} does not exist."])
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise MeasurementsError([f"{path}: not UTF-8 text ({exc.reason} at byte "
                                 f"{exc.start}); save the file as UTF-8 CSV."]) from None
    return parse_measurements(text, source=str(path), inputs=inputs, outputs=outputs,
                              ignore=ignore)


def parse_measurements(text: str, *, source: str, inputs, outputs=None,
                       ignore=("repeat",)) -> Measurements:
    """Observations of CSV text with a header row (``#`` lines before it are provenance):
    columns ``inputs`` form X, ``outputs`` z (default: all but the inputs and ``ignore``).

    It only parses (safe for uploaded text). A :class:`MeasurementsError` lists up to
    :data:`MAX_PROBLEMS` problems, each naming ``source``, the line and the column.
    """
    lines = text.removeprefix("\ufeff").splitlines()   # a BOM (Excel's UTF-8 CSV)
    header_line = next((i for i, line in enumerate(lines, start=1)
                        if line.strip() and not line.startswith("#")), None)
    if header_line is None:
        raise MeasurementsError([f"{source}: no header row found; the first non-comment line "
                                 "must name the columns."])
    comments = [line[1:].strip() for line in lines[:header_line] if line.startswith("#")]
    # A name that mdcore._export wrote with a leading "'" (it would start a formula) reads
    # back as the name.
    header = [h[1:] if h[:1] == "'" and h[1:2] in ("=", "+", "-", "@") else h
              for h in (c.strip() for c in next(csv.reader([lines[header_line - 1]])))]
    inputs = tuple(inputs)
    outputs = tuple(h for h in header if h not in inputs and h not in ignore) \
        if outputs is None else tuple(outputs)
    wanted = inputs + outputs
    missing = [c for c in wanted if c not in header]
    for sep, word in ((";", "semicolons"), ("\t", "tabs")):
        if missing and set(wanted) <= {h.strip() for h in lines[header_line - 1].split(sep)}:
            raise MeasurementsError([f"{source} line {header_line}: the columns are separated "
                                     f"by {word}; save the file as CSV with commas (the "
                                     f"columns {list(wanted)} are there)."])
    if missing:
        # The header is quoted only when it names a wanted column: this is then the
        # measurements file with a column misnamed, not some other file's first line.
        found = ("the header " + ", ".join(short(h, 30) for h in header[:20])
                 if set(header) & set(wanted) else
                 "a header with none of them (is this the measurements file?)")
        raise MeasurementsError([f"{source} line {header_line}: column(s) {missing} not found "
                                 f"in {found}; the file needs the columns {list(wanted)}."])
    if not outputs:
        raise MeasurementsError([f"{source}: no output columns; name them with outputs=."])
    repeated = [c for c in dict.fromkeys(wanted) if header.count(c) > 1]
    if repeated:                      # which of the equal names is meant is ambiguous
        raise MeasurementsError([f"{source} line {header_line}: column(s) {repeated} appear "
                                 f"more than once in the header {header}; give each column "
                                 "a distinct name."])
    cols = [header.index(c) for c in wanted]
    rows, problems = [], []
    n_rows = 0
    for lineno, line in enumerate(lines[header_line:], start=header_line + 1):
        if not line.strip() or line.startswith("#"):
            continue
        n_rows += 1
        if n_rows > MAX_ROWS:
            raise MeasurementsError([f"{source} line {lineno}: more than {MAX_ROWS:,} data rows; "
                                     f"a measurements file may have at most {MAX_ROWS:,} (keep "
                                     "a subset of the rows, or average replicate readings)."])
        cells = next(csv.reader([line]))
        if len(cells) != len(header):
            problems.append(f"{source} line {lineno}: {len(cells)} field(s), but the header "
                            f"has {len(header)}; every row needs one value per column.")
            continue
        for c in cols:
            text_c = cells[c].strip()
            try:
                v = float(text_c)
            except ValueError:
                v = np.nan
                problem = "is not a number."
            else:
                problem = ("is not finite; remove the row or fill in the value."
                           if not np.isfinite(v) else f"is larger in magnitude than "
                           f"{MAX_MAGNITUDE:g}, whose square (a variance) overflows; express the "
                           "column in other units." if abs(v) > MAX_MAGNITUDE else "")
            if problem:
                problems.append(f"{source} line {lineno}, column {header[c]!r}: "
                                f"{short(text_c, 30)} {problem}")
            rows.append(v)
    if problems:
        more = len(problems) - MAX_PROBLEMS
        raise MeasurementsError(problems[:MAX_PROBLEMS] + (
            [f"{source}: and {more} more problem(s) like these."] if more > 0 else []))
    if not rows:
        raise MeasurementsError([f"{source}: the header is followed by no data rows."])
    data = np.reshape(rows, (-1, len(cols)))
    k = len(inputs)
    return Measurements(data[:, :k], data[:, k:], inputs, outputs, tuple(comments))


def _shear5(seed: int) -> Case:
    with importlib.resources.as_file(SHEAR5_CSV) as path:      # a real file, even from a zip
        m = read_measurements(path, inputs=("mass_kg",), outputs=SHEAR5_OUTPUTS)
    train = np.isin(np.round(m.X[:, 0], 6), SHEAR5_TRAIN_MASSES)
    z_train = m.z[train]
    lo, hi = 0.85 * SHEAR5_NOMINAL, 1.15 * SHEAR5_NOMINAL
    levels = [np.linspace(a, b, 3) for a, b in zip(lo, hi)]
    design = np.stack(np.meshgrid(*levels, indexing="ij"), axis=-1).reshape(-1, 3)
    # Paper §5 priors: log ℓ² ~ N(8, 1) -> log ℓ ~ N(4, 1/4); log σ_f ~ N(0, 10);
    # log σ_n² ~ N(−11, 4) -> log σ_n ~ N(−5.5, 1).
    prior = GaussianPrior(mean=np.r_[0.0, np.full(6, 4.0), -5.5],
                          var=np.r_[10.0, np.full(6, 0.25), 1.0])
    return Case(
        name="shear-5",
        title="Five-storey shear building, added mass as input (SYNTHETIC, paper §5)",
        description=("SYNTHETIC stand-in for the paper's laboratory structure, whose "
                     "measurements are not public: a 'real' building (E = 70 GPa, ρ = 2700 kg/m³, "
                     "0.03 kg sensor mass per floor, rocking base spring) measured 10 times per "
                     "added mass with noise sd 0.004 Hz; read from " + SHEAR5_CSV.name + "."),
        stand_in=True, theta_names=("E", "ν", "ρ"), theta_units=("GPa", "-", "kg/m³"),
        theta_bounds=np.column_stack([lo, hi]),
        theta_true=np.array([SHEAR5_REAL["E"] / 1e9, SHEAR5_REAL["nu"], SHEAR5_REAL["rho"]]),
        x_names=("added mass",), x_units=("kg",),
        output_names=("ω1", "ω2", "ω3", "ω4", "ω5"), output_units=("Hz",) * 5,
        X_train=m.X[train], z_train=z_train, X_test=m.X[~train], z_test=m.z[~train],
        noise_var=np.full(5, SHEAR5_NOISE_SD**2),
        V_m=(0.03 * z_train.mean(axis=0)) ** 2,   # docs/cases.md: V_m,i = (0.03 z̄_i)², per mode
        phi_prior=prior, initial_design=design, seed=seed,
        # Not in the paper: nominal values with a 5 % standard deviation (the box is ±3 sd).
        theta_prior=ThetaPrior(mean=SHEAR5_NOMINAL, var=(0.05 * SHEAR5_NOMINAL) ** 2),
        _simulator=_shear5_simulator, _true_delta=_shear5_delta)


_BUILDERS = {"beam-1d": _beam1d, "beam-2d": _beam2d, "shear-5": _shear5}


def names() -> tuple[str, ...]:
    """Names of the built-in case studies."""
    return tuple(_BUILDERS)


def load(name: str, *, seed=0) -> Case:
    """Build a case study.

    Parameters
    ----------
    name : {"beam-1d", "beam-2d", "shear-5"}
    seed : int or numpy.random.Generator, default=0
        Seed of the train and test noise (``default_rng(seed)``; train first, then test).
        A Generator is turned into an integer seed by one draw (:attr:`Case.seed`).
        shear-5 reads its shipped measurement file, so its data do not depend on ``seed``.
    """
    choose(name, "case name", _BUILDERS)
    return _BUILDERS[name](as_seed_int(seed))
