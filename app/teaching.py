"""The history-matching presets of the app as data: the teaching preset's wave-1 design,
runs per wave and convergence rule, and the paper's.

The app's state applies them; the "Things to try" checks (tests/test_experiments.py) build
the same history match through mdcore's API from them, so the two cannot drift apart.

Why shear-5 keeps its own 27-run design, where the waves cannot visibly shrink: its NROY
share is set by V_m, not by the emulator. The frequencies are so smooth in θ that a 5-run
emulator is already below 0.1 (V_o + V_m) after wave 1 (seed 0, 150,000 candidates):

=================  =====  ==============  =====================================
wave-1 design      ratio  V_m of ω1 Hz²   NROY % per wave
=================  =====  ==============  =====================================
5-run hypercube    0.1    0.158 (case's)  67.0 (converged at wave 1)
5-run hypercube    0.001  0.158           67.0, 64.9, 64.7, 64.5, 64.5
5-run hypercube    0.001  0.07            40.3, 39.2, 38.7, 38.6, 38.5, 38.4
27-run grid        0.1    0.158           65.3 (converged at wave 1)
=================  =====  ==============  =====================================

A smaller V_m shrinks NROY (0.07: 40 %) but in wave 1, not over the waves; a 4-run design
wrongly ruled out a sixth of the box. The ridge card shows shear-5's lesson instead.
"""

from __future__ import annotations

import numpy as np
import scipy.stats

__all__ = ["PRESETS", "TEACHING", "TEACHING_RATIO", "TEACHING_MAX_WAVES", "preset_controls",
           "teaching_design"]

#: Per case: the teaching preset's wave-1 runs (None: the case's own design) and runs per
#: wave. Small enough that the waves visibly shrink NROY (beam-1d: 5 waves, 34.8 → 21.2 %;
#: beam-2d: 3 waves, 54.5 → 37.7 %, the true θ non-implausible).
TEACHING = {"beam-1d": (4, 3), "beam-2d": (2, 1), "shear-5": (None, 15)}
#: The teaching preset converges at this × (V_o + V_m), within this many waves.
TEACHING_RATIO, TEACHING_MAX_WAVES = 0.1, 6
PRESETS = ("teaching", "paper")


def teaching_design(case, base_name: str) -> np.ndarray:
    """The teaching preset's wave-1 design: a seeded Latin hypercube of a few runs, or the
    case's own design where :data:`TEACHING` says None; shape (R0, p)."""
    r0 = TEACHING.get(base_name, (case.p + 2, case.p))[0]
    if r0 is None:
        return case.initial_design
    lhs = scipy.stats.qmc.LatinHypercube(d=case.p, seed=np.random.default_rng(0))
    b = case.theta_bounds
    return scipy.stats.qmc.scale(lhs.random(r0), b[:, 0], b[:, 1])


def preset_controls(case, base_name: str, preset: str) -> dict:
    """Runs per wave, convergence ratio and max waves of ``preset`` ("teaching" or
    "paper") for ``case`` (a built-in case's ``base_name``, or an own case's name)."""
    if preset not in PRESETS:
        raise ValueError(f"preset must be one of {list(PRESETS)}; received {preset!r}.")
    if preset == "teaching":
        return {"n_runs": TEACHING.get(base_name, (0, case.p))[1],
                "convergence_ratio": TEACHING_RATIO, "max_waves": TEACHING_MAX_WAVES}
    return {"n_runs": max(10, 5 * case.p), "convergence_ratio": 1.0, "max_waves": 5}
