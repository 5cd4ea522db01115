"""mdcore: learning model discrepancy with Gaussian processes and sampling.

Decoupled calibration (Bayesian history matching) and GP model discrepancy of
Gardner, Rogers, Lord, Barthorpe & Worden, "Learning model discrepancy: a Gaussian
process and sampling-based approach", Mechanical Systems and Signal Processing (2021).

The public face is small: :func:`run_method` with :class:`Method` and :class:`Settings`
(the pipeline), the warnings and :class:`Cancelled`. The modules behind it:
:mod:`mdcore.cases` and :mod:`mdcore.case_file` (case studies, your own data),
:mod:`mdcore.history_matching` (with :mod:`mdcore.emulator`, :mod:`mdcore.runs`),
:mod:`mdcore.discrepancy` (scenarios 1–3, with :mod:`mdcore.importance`),
:mod:`mdcore.koh` (with :mod:`mdcore.mcmc`), the GP core (:mod:`mdcore.gp`,
:mod:`mdcore.kernels`, :mod:`mdcore.linalg`, :mod:`mdcore.hyperfit`, :mod:`mdcore.priors`),
:mod:`mdcore.metrics`, :mod:`mdcore.reproduce`, :mod:`mdcore.study`, :mod:`mdcore.export`.
"""

from .exceptions import Cancelled as Cancelled
from .exceptions import ConvergenceWarning as ConvergenceWarning
from .exceptions import EmulatorWarning as EmulatorWarning
from .exceptions import LowESSWarning as LowESSWarning
from .exceptions import NumericalWarning as NumericalWarning
from .pipeline import Method as Method
from .pipeline import MethodResult as MethodResult
from .pipeline import Settings as Settings
from .pipeline import run_method as run_method

__version__ = "0.1.0"
__all__ = ["Cancelled", "ConvergenceWarning", "EmulatorWarning", "LowESSWarning", "Method",
           "MethodResult", "NumericalWarning", "Settings", "__version__", "run_method"]
