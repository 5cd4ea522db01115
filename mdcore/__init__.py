"""mdcore: learning model discrepancy with Gaussian processes and sampling.

Decoupled calibration (Bayesian history matching) and GP model discrepancy of
Gardner, Rogers, Lord, Barthorpe & Worden, "Learning model discrepancy: a Gaussian
process and sampling-based approach", Mechanical Systems and Signal Processing (2021).

Modules: :mod:`mdcore.gp` (batched GP core), :mod:`mdcore.cases` (case studies),
:mod:`mdcore.simulators`, :mod:`mdcore.emulator`, :mod:`mdcore.history_matching`,
:mod:`mdcore.discrepancy`, :mod:`mdcore.koh` (with :mod:`mdcore.mcmc`),
:mod:`mdcore.metrics`, :mod:`mdcore.reproduce`.
"""

from .gp import NumericalWarning as NumericalWarning

__version__ = "0.1.0"
__all__ = ["NumericalWarning", "__version__"]
