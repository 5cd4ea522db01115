"""The words a newcomer meets on screen, defined once: the app's tooltips and the README's
Glossary (tests/test_glossary.py holds them equal). ``GLOSSARY``: term as written on
screen -> a sentence or two; ``SECTION``: term -> the section of docs/method.md on it.
:func:`in_app_words` puts the app's control labels for mdcore's option names in its
messages.
"""

from __future__ import annotations

import html
import re

GLOSSARY = {
    "θ": "The simulator's calibration parameters, e.g. crack length l_cr and Young's "
         "modulus E.",
    "δ": "Model discrepancy: what the simulator misses even at the true θ.",
    "V_o": "Observation variance: how much the measurements scatter (the noise variance; "
           "with repeated readings, their sample variance).",
    "V_m": "Model-discrepancy variance: how far the simulator may be from the real "
           "structure at the true θ. Too small rules out the truth; too large rules out "
           "nothing.",
    "implausibility": "How many standard deviations the emulator's prediction at θ is from "
                      "the data, counting V_o, V_m and the emulator's own variance (Eq. 16).",
    "T": "Implausibility threshold (default 3): θ whose implausibility is above T is ruled "
         "out.",
    "NROY": "Not ruled out yet: the θ whose implausibility is at most T, the ones that "
            "could have produced the data given V_o and V_m.",
    "wave": "One round of history matching: run the simulator, fit the emulator, rule "
            "out θ.",
    "θ_MAP": "The most likely θ in NROY under history matching's Gaussian likelihood, "
             "drawn as a star (the true θ, where known, is the ×).",
    "scenario 1": "δ learnt by one GP at θ_MAP, its hyperparameters φ fitted to the data.",
    "scenario 2": "Scenario 1's φ, averaged over N_s samples of θ from the history-matching "
                  "posterior (Eq. 13).",
    "scenario 3": "Averaged over N_s samples of θ and N_φ samples of φ per θ, weighted by "
                  "importance sampling (Eq. 15).",
    "KOH": "Kennedy–O'Hagan: θ and δ learnt together in one model, the baseline the paper "
           "compares with.",
    "N_s, N_φ": "Samples of θ, and samples of φ per θ (scenario 3).",
    "ESS": "Effective sample size of importance weights, 1 / Σ w²: how many equally "
           "weighted samples they are worth.",
    "ESS over φ": "The ESS of the φ weights within one θ, averaged over θ: about 1 means "
                  "scenario 3 relies on one φ per θ.",
    "k̂": "Pareto shape of the largest importance weights; below 0.7 the weights can be "
          "trusted.",
    "IAT": "Integrated autocorrelation time of KOH's Markov chain: how many steps make one "
           "independent sample.",
    "NMSE": "Normalised mean squared error in percent of the target's variance: 0 is "
            "perfect, 100 no better than the target's mean. Meaningless when the target "
            "hardly varies (shear-5's δ).",
    "RMSE δ": "Root mean squared error of the predicted δ against the true δ, in the "
              "output's units.",
    "MMD": "Maximum mean discrepancy between the repeated test readings and the predictive "
           "distribution; smaller is better.",
    "LPL": "Log predictive likelihood of the test data under the predictive mean and "
           "variance; larger is better.",
}

SECTION = {"θ": 1, "δ": 1, "V_o": 5, "V_m": 5, "implausibility": 5, "T": 5, "NROY": 5,
           "wave": 5, "θ_MAP": 5, "scenario 1": 6, "scenario 2": 6, "scenario 3": 6,
           "KOH": 7, "N_s, N_φ": 6, "ESS": 6, "ESS over φ": 6, "k̂": 6, "IAT": 7, "NMSE": 8,
           "RMSE δ": 8, "MMD": 8, "LPL": 8}


def tooltip(term: str) -> str:
    """The definition of ``term`` with where to read more, for a tooltip."""
    return f"{GLOSSARY[term]} (docs/method.md §{SECTION[term]})"


def terms_html(*words: str) -> str:
    """HTML naming ``words``, each an ``<abbr>`` whose title is its :func:`tooltip`."""
    spans = " · ".join(f'<abbr title="{html.escape(tooltip(w))}">{html.escape(w)}</abbr>'
                       for w in words)
    return f"Words on this tab (hover for their meaning): {spans}"


#: mdcore's options that its messages name -> the label of the app's control for it.
CONTROL_LABELS = {"n_runs": "Runs per wave", "n_candidates": "Candidates per wave",
                  "max_waves": "Max waves", "convergence_ratio": "Convergence ratio",
                  "n_s": "N_s", "n_phi": "N_φ"}
_OPTION = re.compile(r"\b(" + "|".join(CONTROL_LABELS) + r")\b")


def in_app_words(message: str) -> str:
    """``message`` (mdcore's advice, a warning) with each option name it gives as the
    app's control label, quoted: the advice said "n_runs" beside a field called "Runs
    per wave"."""
    return _OPTION.sub(lambda m: f"“{CONTROL_LABELS[m.group(1)]}”", message)
