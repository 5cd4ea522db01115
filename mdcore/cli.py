"""Command line: ``python -m mdcore {cases,history-match} ...``."""

from __future__ import annotations

import argparse
import sys

import numpy as np

from . import cases
from .history_matching import history_match_case


def _cmd_cases(args) -> int:
    for name in cases.names():
        c = cases.load(name)
        theta = ", ".join(f"{n} [{u}] ∈ [{lo:g}, {hi:g}]" for n, u, (lo, hi)
                          in zip(c.theta_names, c.theta_units, c.theta_bounds))
        print(f"{name}: {c.title}\n  θ: {theta}\n  train {c.X_train.shape[0]} × test "
              f"{c.X_test.shape[0]} observations of {', '.join(c.output_names)}\n")
    return 0


def _cmd_history_match(args) -> int:
    case = cases.load(args.case, seed=args.seed)
    opts = dict(seed=args.seed, max_waves=args.max_waves, threshold=args.threshold,
                rule=args.rule)
    if args.v_m is not None:
        opts["V_m"] = args.v_m
    if args.n_candidates is not None:
        opts["n_candidates"] = args.n_candidates
    result = history_match_case(case, **opts)
    print(f"{case.title}\n{'wave':>4} {'NROY %':>8} {'runs':>5} {'max var / (V_o+V_m)':>20} "
          f"{'seconds':>8}")
    for w in result.waves:
        ratio = np.max(w.max_var / w.var_threshold)
        print(f"{w.index:>4} {100 * w.nroy_fraction:>8.2f} {len(w.runs_theta):>5} "
              f"{ratio:>20.3g} {w.seconds:>8.2f}")
    print(result.message)
    if result.status != "ruled_out":
        names = ", ".join(f"{n} = {v:.4g} {u}" for n, v, u in
                          zip(case.theta_names, result.theta_map, case.theta_units))
        print(f"θ_MAP: {names}")
    return 0 if result.status != "ruled_out" else 1


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m mdcore", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser("cases", help="list the case studies")
    hm = sub.add_parser("history-match", help="run Bayesian history matching on a case")
    hm.add_argument("case", choices=cases.names())
    hm.add_argument("--seed", type=int, default=0)
    hm.add_argument("--max-waves", type=int, default=5)
    hm.add_argument("--threshold", type=float, default=3.0)
    hm.add_argument("--rule", default="max", choices=["max", "2nd max", "3rd max"])
    hm.add_argument("--v-m", type=float, default=None, help="model-discrepancy variance")
    hm.add_argument("--n-candidates", type=int, default=None)
    args = parser.parse_args(argv)
    try:
        return {"cases": _cmd_cases, "history-match": _cmd_history_match}[args.command](args)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
