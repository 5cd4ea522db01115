"""Warnings and exceptions of mdcore, in one place (like ``sklearn.exceptions``)."""

from __future__ import annotations

__all__ = ["NumericalWarning", "ConvergenceWarning", "LowESSWarning", "EmulatorWarning",
           "Cancelled"]


class NumericalWarning(RuntimeWarning):
    """A numerical fallback was used (jitter, clipped variance, low effective sample size)."""


class ConvergenceWarning(NumericalWarning):
    """An optimiser or a Markov chain did not converge; the message says what to change."""


class LowESSWarning(NumericalWarning):
    """Importance weights rest on few samples (small effective sample size)."""


class EmulatorWarning(UserWarning):
    """A wave's emulator fails its leave-one-out check (docs/diagnostics.md §1)."""


class Cancelled(Exception):
    """The work was cancelled through its ``cancel`` event (:func:`mdcore.pipeline.run_method`)."""
