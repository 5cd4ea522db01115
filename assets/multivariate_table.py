"""The evidence table of docs/multivariate_history_matching.md from `mdcore study --json` files.

Usage: python assets/multivariate_table.py STUDY.json [STUDY.json ...]

One row per study: the rule, ℓ_m, the cut-off, the final NROY share (mean ± sd over
seeds), how many seeds keep the truth in NROY, θ_MAP's mean absolute error per parameter,
the mean number of waves, and the δ NMSE [%] of scenarios 1–3 (mean ± sd over seeds); for
several outputs (shear-5, whose δ hardly varies over the test inputs, so that its NMSE is
meaningless: docs/method.md §8) the RMSE of δ averaged over the outputs instead.
"""

import json
import sys

import numpy as np


def row(path: str) -> str:
    doc = json.load(open(path, encoding="utf-8"))
    runs = doc["runs"]
    hm = [r["history_matching"] for r in runs]
    share = 100 * np.array([h["nroy_fraction"][-1] for h in hm])
    s = doc["history_matching"]
    corr = "" if hm[0]["V_m_corr"] is None else f", ρ {hm[0]['V_m_corr'][0][1]:g}"
    length = "—" if hm[0]["rule"] != "multivariate" else "/".join(
        f"{v:g}" for v in sorted(set(hm[0]["V_m_length"]))) + corr
    cells = [doc["case"], hm[0]["rule"], length, f"{hm[0]['cutoff']:.1f}",
        f"{share.mean():.1f} ± {share.std(ddof=1):.1f}", f"{s['truth_in']}/{s['n']}",
        ", ".join(f"{e:.3g}" for e in s["theta_map_error"]),
        f"{np.mean([h['waves'] for h in hm]):.1f}"]
    for m in ("1", "2", "3"):
        key = "nmse_delta" if len(hm[0]["theta_map"]) < 3 and len(
            runs[0]["methods"][m]["metrics"]["nmse_delta"]) == 1 else "rmse_delta"
        v = np.array([np.mean(r["methods"][m]["metrics"][key]) for r in runs])
        cells.append(f"{v.mean():.3g} ± {v.std(ddof=1):.2g}" + (" Hz" if key == "rmse_delta"
                                                                  else ""))
    return "| " + " | ".join(cells) + " |"


def main():
    print("| case | rule | ℓ_m | cut-off | final NROY % | truth in NROY | θ_MAP mean "
          "abs. error | waves | δ NMSE % (RMSE) S1 | S2 | S3 |")
    print("|" + "---|" * 11)
    for path in sys.argv[1:]:
        print(row(path))


if __name__ == "__main__":
    main()
