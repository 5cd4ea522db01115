"""Warnings and exceptions of mdcore, in one place (like ``sklearn.exceptions``)."""

from __future__ import annotations

import math


class NumericalWarning(RuntimeWarning):
    """A numerical fallback was used (jitter, clipped variance, low effective sample size)."""


class ConvergenceWarning(NumericalWarning):
    """An optimiser or a Markov chain did not converge; the message says what to change."""


class LowESSWarning(NumericalWarning):
    """Importance weights rest on few samples (small effective sample size)."""


class EmulatorWarning(UserWarning):
    """A wave's emulator fails its leave-one-out check (docs/diagnostics.md §1)."""


class Cancelled(Exception):
    """The work was cancelled through its ``cancel`` event (:func:`mdcore.run_method`)."""


# The advice of the warnings above is worded here once: the core warns with it, and the
# pipeline's results carry the same text (mdcore.MethodResult.warnings).

#: Smallest ESS over (θ, φ) pairs, and largest Pareto k̂, of weights that can be trusted
#: (Vehtari et al. 2024); a chain is trusted from this many autocorrelation times.
LOW_ESS = 30.0
K_HAT_THRESHOLD = 0.7
RELIABLE_TAUS = 50


def output_label(label: str, output: int, n_out: int) -> str:
    """``label``, with the 1-based output named only when there are several."""
    return f"{label}, output {output + 1}" if n_out > 1 else label


def weights_advice(place: str, ess: float, n_s: int, n_phi: int, k_hat: float,
                   proposal: str) -> str:
    """What to do when scenario 3's importance weights cannot be trusted (low ESS or k̂)."""
    switch = " or switch to the adaptive proposal" if proposal == "prior" else ""
    return (f"{place}: the importance weights are unreliable: {ess:.1f} effective (θ, φ) "
            f"pairs of {n_s * n_phi:,}, Pareto k̂ {k_hat:.2f} (reliable: ESS ≥ {LOW_ESS:g} "
            f"and k̂ ≤ {K_HAT_THRESHOLD}); raise N_φ (now {n_phi}) or N_s (now {n_s})"
            f"{switch}.")


def chain_advice(label: str, tau: float, kept: int, burn_in: int) -> str:
    """What to do when a Markov chain is too short to trust its IAT and ESS."""
    return (f"{label}: the chain is shorter than {RELIABLE_TAUS} autocorrelation times (τ up "
            f"to {tau:.1f} with {kept:,} kept steps), so its IAT and ESS are unreliable; "
            f"raise n_iter to at least {math.ceil(RELIABLE_TAUS * tau) + burn_in:,}.")
