"""Guided experiments of the "Things to try" tab, each a script: a question to answer before
pressing, every control it depends on, what to press and where to look, and the effect it
promises, which tests/test_experiments.py checks through mdcore's API.

Each experiment is data; :meth:`mdcore_app.state.ExplorerState.try_experiment` applies
its settings, runs what its ``expect`` needs (the history match; the methods too for the
facts in :data:`METHOD_FACTS`) and puts :attr:`Experiment.look` in the status line. The
card shows its question above its button, so the prediction comes first.

Fields (the first five are the original shape; the others were added after them):

key, title, predict, then
    Identifier (CSS class ``try-<key>``), title, the question, what to do after the run.
settings : dict
    EVERY control the card depends on, so the cards work in any order: the app's defaults
    (:func:`controls`) with the card's own values over them. Apply ``case_name`` first,
    then ``preset`` and ``paper_sizes`` (their watchers set runs per wave, convergence,
    N_s and N_φ), then the rest, which restate what those watchers set.
look : str
    The tab and plot where the effect shows.
promise : str
    The effect, in words, as the card promises it.
expect : dict
    The same effect as numbers to check, one entry per fact (all must hold):

    - ``"truth_in_nroy"``: bool, the true θ is (not) in the final NROY set;
    - ``"nroy_empty"``: bool, the final NROY set is (not) empty;
    - ``"shrinks"``: int n, at least n waves, and the NROY share falls at every wave;
    - ``"wider_band"``: (wide, narrow, x_max): method ``wide``'s mean δ band sd over the
      test inputs x ≤ x_max is larger than method ``narrow``'s;
    - ``"covers_better"``: (better, worse): method ``better`` covers more of the true δ
      within the card's ±band σ than ``worse`` (over the test inputs);
    - ``"ess_phi_grows"``: n_phi, scenario 3's ESS over φ at ``n_phi`` exceeds the card's;
    - ``"delta_worse"``: (method, than, factor): ``method``'s δ NMSE is at least
      ``factor`` × ``than``'s;
    - ``"ridge"``: (r, f), a band along E/ρ: the final NROY samples of the first and
      third θ (E and ρ) correlate above r, each spans over 95 % of its box range, and
      their ratio spans under f of the ratio's range over the box.
"""

from __future__ import annotations

from typing import Any, NamedTuple

from mdcore import Settings, load_case
from mdcore._koh import BURN_IN, FAST, N_ITER
from mdcore._pipeline import Method

from .teaching import preset_controls, teaching_design

__all__ = ["EXPERIMENTS", "Experiment", "KOH_CHAINS", "METHOD_FACTS", "controls",
           "history_options", "method_settings"]

_INTERACTIVE = Settings.interactive()
#: The KOH chain lengths of the app's "KOH chain" control.
KOH_CHAINS = {"fast": dict(FAST), "paper": {"n_iter": N_ITER, "burn_in": BURN_IN}}
#: The ``expect`` facts about the discrepancy methods: a card with one runs them too.
METHOD_FACTS = frozenset({"wider_band", "covers_better", "ess_phi_grows", "delta_worse"})


class Experiment(NamedTuple):
    """One guided experiment (the fields are described in the module docstring)."""

    key: str
    title: str
    predict: str
    settings: dict[str, Any]
    then: str
    look: str = ""
    promise: str = ""
    expect: dict[str, Any] = {}

    @property
    def tab(self) -> str:
        """The tab where the card shows its point: the first named in :attr:`look`."""
        return self.look.split(" tab", 1)[0]


def controls(case_name: str, **own) -> dict[str, Any]:
    """Every control a card depends on: the app's defaults for ``case_name`` (its V_m, the
    preset's runs, convergence and waves), then ``own`` over them, in the order to apply."""
    case = load_case(case_name)
    preset = own.pop("preset", "teaching")
    out = {"case_name": case_name, "preset": preset, "paper_sizes": False,
           "v_m": float(case.V_m[0]), "threshold": 3.0, "rule": "max",
           **preset_controls(case, case_name, preset), "n_candidates": 50_000,
           "scenarios": [Method.S1, Method.S2, Method.S3], "band": 3,
           "n_s": _INTERACTIVE.n_s, "n_phi": _INTERACTIVE.n_phi,
           "proposal": _INTERACTIVE.proposal, "koh_chain": "fast", "seed": 0}
    unknown = set(own) - set(out)
    if unknown:
        raise ValueError(f"unknown control(s) {sorted(unknown)}; expected some of {list(out)}.")
    return {**out, **own}


def history_options(settings: dict) -> dict:
    """The keyword arguments of :func:`mdcore.history_match_case` that the app's history
    match uses for a card's ``settings`` (V_m scaled from ω1's, seed 0)."""
    case = load_case(settings["case_name"])
    design = ({"initial_design": teaching_design(case, settings["case_name"])}
              if settings["preset"] == "teaching" else {})
    return dict(V_m=case.scaled_v_m(settings["v_m"]), threshold=settings["threshold"],
                rule=settings["rule"], n_runs=settings["n_runs"],
                n_candidates=settings["n_candidates"], max_waves=settings["max_waves"],
                convergence_ratio=settings["convergence_ratio"], seed=0, **design)


def method_settings(settings: dict) -> Settings:
    """The :class:`mdcore.Settings` of the app's discrepancy run for a card's ``settings``."""
    return Settings(n_s=settings["n_s"], n_phi=settings["n_phi"],
                    proposal=settings["proposal"],
                    fit_iterations=_INTERACTIVE.fit_iterations,
                    **KOH_CHAINS[settings["koh_chain"]])


EXPERIMENTS = (
    Experiment(
        "waves", "Watch the waves shrink",
        "Each wave adds a few simulator runs where θ is still plausible. Will the "
        "non-implausible share of the box fall by the same amount at every wave?",
        controls("beam-1d"),
        "Step “Wave shown” back through the waves and watch NROY % per wave.",
        look="History matching tab: NROY % per wave, and the non-implausible θ closing in "
             "on the truth ×.",
        promise="NROY falls at every wave, by less each time (34.8, 25.3, 23.4, 21.7, "
                "21.4 %), and the truth × stays inside.",
        expect={"shrinks": 4, "truth_in_nroy": True}),
    Experiment(
        "rule-out", "Lower V_m until the truth is ruled out",
        "V_m is how much you allow the simulator to be wrong. At V_m = 0.014 mm², a little "
        "less than the real discrepancy needs, what happens to NROY, and to the true θ "
        "(the ×)?",
        controls("beam-1d", v_m=0.014),
        "Raise V_m back to 0.05, press “Run to convergence” and compare. Is it the "
        "emulator's fault? The simulator itself at the true θ has implausibility 3.07 "
        "> T = 3 at V_m = 0.014 mm² (1.67 at 0.05): V_m rules the truth out.",
        look="History matching tab: the legend's verdict on the truth ×, and the "
             "non-implausible θ around it and θ_MAP (the star).",
        promise="A small NROY set (0.37 % of the box) survives, but the truth × is "
                "outside it: too small a V_m rules out the truth and keeps a wrong θ. "
                "Below about 0.01 mm² nothing survives at all.",
        expect={"truth_in_nroy": False, "nroy_empty": False}),
    Experiment(
        "s1-vs-s2", "Compare scenario 1's band with scenario 2's",
        "Scenario 1 fixes θ at θ_MAP and the GP hyperparameters at their best fit; "
        "scenario 2 also averages over θ. Which band is wider near x = 0.1, at the edge of "
        "the data, and which one covers the true δ?",
        controls("beam-1d", scenarios=[Method.S1, Method.S2], band=2),
        "Compare the bands near x = 0.1 and where they miss the true δ.",
        look="Discrepancy tab, δ row: the ±2σ bands of scenarios 1 and 2 against the true δ.",
        promise="Scenario 2's band is wider near x = 0.1 (sd 0.11 against 0.017 mm for "
                "x ≤ 0.2) and covers all of the true δ, scenario 1's 70 %.",
        expect={"wider_band": (Method.S2, Method.S1, 0.2),
                "covers_better": (Method.S2, Method.S1)}),
    Experiment(
        "ess", "Raise N_φ and watch scenario 3's ESS",
        "Scenario 3 weights (θ, φ) pairs drawn from the prior. With N_φ = 10, how many "
        "effective samples do you expect, and what happens at N_φ = 200?",
        controls("beam-1d", scenarios=[Method.S3], proposal="prior", n_phi=10),
        "Read ESS φ and k̂ (Metrics tab), then set N_φ to 200 and read them again.",
        look="Metrics tab: ESS φ and k̂ of scenario 3.",
        promise="ESS over φ grows with N_φ: about 1 effective φ per θ at N_φ = 10 (the "
                "weights are unreliable, k̂ > 0.7), about 4 at 200.",
        expect={"ess_phi_grows": 200}),
    Experiment(
        "koh", "Joint calibration against the decoupled method",
        "Kennedy–O'Hagan learns θ and δ together. Will its θ land on the truth, and will "
        "its δ be as good as scenario 1's?",
        controls("beam-1d", scenarios=[Method.S1, Method.KOH]),
        "Compare the δ bands and the KOH θ posterior (Metrics).",
        look="Discrepancy tab, δ row; Metrics tab: NMSE δ % of scenario 1 and KOH.",
        promise="KOH predicts z as well, but its δ NMSE is many times scenario 1's (32×: "
                "64 against 2.0 %; the paper's Table 1: 22×): θ and δ trade off when learnt "
                "together.",
        expect={"delta_worse": (Method.KOH, Method.S1, 5.0)}),
    Experiment(
        "ridge", "Why does shear-5 not pin down E and ρ?",
        "The frequencies depend on E and ρ mostly through E/ρ. Predict the shape of the "
        "non-implausible set in the (E, ρ) plane.",
        controls("shear-5", preset="paper"),
        "Add KOH under Scenarios, press “Run discrepancy”, and compare its E and ρ.",
        look="History matching tab, the E–ρ panel: NROY, the truth × and θ_MAP (the star).",
        promise="NROY is a diagonal band: every E and every ρ of the box survives, but only "
                "in pairs whose E/ρ lies in about half of its range (E and ρ correlate at "
                "0.57), the truth × inside. θ_MAP sits at the band's low-E end: the "
                "likelihood is flat along it. KOH (add it under Scenarios) finds E and ρ "
                "from the added mass.",
        expect={"ridge": (0.5, 0.6), "truth_in_nroy": True, "nroy_empty": False}),
)
