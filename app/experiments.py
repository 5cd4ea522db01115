"""Guided experiments of the "Things to try" tab: a question to answer before pressing,
the controls that set it up, and what to press next.

Each experiment is data; :meth:`mdcore_app.state.ExplorerState.try_experiment` applies
its settings (the case first, then the controls) and puts :attr:`Experiment.then` in the
status line. Nothing runs until the user presses the button it names, so the prediction
comes first.
"""

from __future__ import annotations

from typing import Any, NamedTuple

from mdcore._pipeline import Method

__all__ = ["EXPERIMENTS", "Experiment"]


class Experiment(NamedTuple):
    """One guided experiment.

    Attributes
    ----------
    key : str
        Identifier (CSS class of its button: ``try-<key>``).
    title : str
    predict : str
        The question to answer before pressing.
    settings : dict
        State parameters to set, ``case_name`` first.
    then : str
        What to press, and what to look at (shown in the status line).
    """

    key: str
    title: str
    predict: str
    settings: dict[str, Any]
    then: str


EXPERIMENTS = (
    Experiment(
        "waves", "Watch the waves shrink",
        "Each wave adds a few simulator runs where θ is still plausible. Will the "
        "non-implausible share of the box fall by the same amount at every wave?",
        {"case_name": "beam-1d", "preset": "teaching", "v_m": 0.05, "threshold": 3.0},
        "Press “Next wave” a few times and watch NROY % per wave (History matching tab)."),
    Experiment(
        "rule-out", "Lower V_m until the truth is ruled out",
        "V_m is how much you allow the simulator to be wrong. At V_m = 0.002 mm² (the "
        "real discrepancy is larger), what happens to NROY, and to the true θ (the star)?",
        {"case_name": "beam-1d", "preset": "teaching", "v_m": 0.002, "threshold": 3.0},
        "Press “Run to convergence”; then raise V_m back to 0.05 and compare."),
    Experiment(
        "s1-vs-s2", "Compare scenario 1's band with scenario 2's",
        "Scenario 1 fixes the GP hyperparameters at their best fit; scenario 2 also "
        "averages over θ. Which band is wider near x = 0.1, where there are few data, and "
        "which one covers the true δ?",
        {"case_name": "beam-1d", "scenarios": [Method.S1, Method.S2], "band": 2},
        "Press “Run discrepancy” and look at the δ row of the Discrepancy tab."),
    Experiment(
        "ess", "Raise N_φ and watch scenario 3's ESS",
        "Scenario 3 weights (θ, φ) pairs drawn from the prior. With N_φ = 10, how many "
        "effective samples do you expect, and what happens at N_φ = 200?",
        {"case_name": "beam-1d", "scenarios": [Method.S3], "proposal": "prior", "n_phi": 10},
        "Press “Run discrepancy”, read ESS φ and k̂ (Metrics tab), then set N_φ to 200."),
    Experiment(
        "koh", "Joint calibration against the decoupled method",
        "Kennedy–O'Hagan learns θ and δ together. Will its θ land on the truth, and will "
        "its δ be as good as scenario 1's?",
        {"case_name": "beam-1d", "scenarios": [Method.S1, Method.KOH], "koh_chain": "fast"},
        "Press “Run discrepancy”; compare the δ bands and the KOH θ posterior (Metrics)."),
    Experiment(
        "ridge", "Why does shear-5 not pin down E and ρ?",
        "The frequencies depend on E and ρ mostly through E/ρ. Predict the shape of the "
        "non-implausible set in the (E, ρ) plane.",
        {"case_name": "shear-5", "preset": "paper"},
        "Press “Run to convergence” and look at the E–ρ panel (History matching tab)."),
)
