"""Regenerate measurements.csv of the worked example (synthetic: a known hidden truth).

The "real" beam has E = 195 GPa and a 0.05 mm gauge offset, and its supports settle a
little under load, which the simulator does not model: δ(x) = 0.12 sin(π x / L) mm.
Three repeated readings at 9 positions, noise sd 0.01 mm; positions 0.3, 0.9 and 1.5 m are
held out for testing.

Usage: python examples/beam_lab/make_data.py
"""

from pathlib import Path

import numpy as np
from beam_lab_simulator import SPAN, deflection

if __name__ == "__main__":
    rng = np.random.default_rng(2026)
    positions = np.round(np.linspace(0.2, 1.8, 9), 3)
    test = {0.3, 0.9, 1.5}
    positions = np.sort(np.concatenate([positions, [0.3, 0.9, 1.5]]))
    lines = ["# SYNTHETIC example data made by examples/beam_lab/make_data.py: E = 195 GPa, "
             "gauge offset 0.05 mm, support settlement 0.12 sin(pi x / L) mm, noise sd 0.01 mm.",
             "position_m,reading,deflection_mm,test"]
    for x in positions:
        true = deflection([[x]], [[195.0, 0.05]])[0, 0, 0] + 0.12 * np.sin(np.pi * x / SPAN)
        for r in range(3):
            lines.append(f"{x:.3f},{r + 1},{true + 0.01 * rng.standard_normal():.5f},"
                         f"{int(x in test)}")
    out = Path(__file__).with_name("measurements.csv")
    out.write_text("\n".join(lines) + "\n", encoding="utf-8")
    print(f"wrote {out}")
