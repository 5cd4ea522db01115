"""mdcore: learning model discrepancy with Gaussian processes and sampling.

Decoupled calibration (Bayesian history matching) and GP model discrepancy of
Gardner, Rogers, Lord, Barthorpe & Worden, "Learning model discrepancy: a Gaussian
process and sampling-based approach", Mechanical Systems and Signal Processing (2021).
The method in our own words is in ``docs/method.md``.

Everything a user needs is imported from here; the modules behind it are private
(``mdcore._name``) and may change without notice::

    import mdcore
    case = mdcore.load_case("beam-1d", seed=0)
    hm = mdcore.history_match_case(case)
    result = mdcore.run_method(case, hm, mdcore.Method.S3, mdcore.Settings(), seed=0)
"""

from ._case_file import CaseFileError, load_case_file, measurements_template, with_measurements
from ._cases import Case, MeasurementsError
from ._cases import load as load_case
from ._cases import names as case_names
from ._diagnostics import WaveValidation, theta_delta_split, validate_waves
from ._discrepancy import (
    DiscrepancyModel,
    DiscrepancyOptions,
    DiscrepancyPrediction,
    infer_discrepancy,
)
from ._emulator import Emulator, fit_emulator
from ._exceptions import (
    Cancelled,
    ConvergenceWarning,
    EmulatorWarning,
    LowESSWarning,
    NumericalWarning,
)
from ._export import write_tables
from ._history_matching import (
    HistoryMatchOptions,
    HistoryMatchProblem,
    HistoryMatchResult,
    Wave,
    case_problem,
    history_match,
    history_match_case,
    next_wave,
)
from ._hyperfit import FitOptions
from ._koh import KOHModel, KOHOptions, infer_koh
from ._metrics import coverage, lpl, mmd, nmse
from ._pipeline import Method, MethodResult, Settings, metrics_table, run_method
from ._priors import GaussianPrior, ThetaPrior
from ._reproduce import CaseRun, reproduce, run_case
from ._study import Study, study

__version__ = "0.1.0"
__all__ = [
    # case studies and your own data
    "Case", "load_case", "case_names", "load_case_file", "measurements_template",
    "with_measurements", "CaseFileError", "MeasurementsError",
    # history matching
    "HistoryMatchOptions", "HistoryMatchProblem", "HistoryMatchResult", "Wave", "history_match",
    "history_match_case", "case_problem", "next_wave", "Emulator", "fit_emulator",
    # diagnostics: each wave's leave-one-run-out check, the θ–δ trade-off
    "validate_waves", "WaveValidation", "theta_delta_split",
    # discrepancy (scenarios 1-3) and the Kennedy-O'Hagan baseline
    "infer_discrepancy", "DiscrepancyModel", "DiscrepancyOptions", "DiscrepancyPrediction",
    "infer_koh", "KOHModel", "KOHOptions", "FitOptions", "GaussianPrior", "ThetaPrior",
    # the pipeline behind the API, the CLI and the app
    "Method", "Settings", "MethodResult", "run_method", "metrics_table",
    "reproduce", "run_case", "CaseRun", "study", "Study", "write_tables",
    # metrics
    "nmse", "lpl", "mmd", "coverage",
    # warnings and cancellation
    "Cancelled", "ConvergenceWarning", "EmulatorWarning", "LowESSWarning", "NumericalWarning",
    "__version__",
]
