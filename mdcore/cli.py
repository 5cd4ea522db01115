"""Command line: ``python -m mdcore {cases,history-match,reproduce} ...``."""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np

from . import cases
from .history_matching import history_match_case
from .koh import BURN_IN, N_ITER
from .reproduce import METHODS, reproduce


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


def _fmt(values, spec):
    return "—" if values is None else spec.format(values)


def _cmd_reproduce(args) -> int:
    result = reproduce(args.case, scenarios=args.scenarios, n_s=args.n_s, n_phi=args.n_phi,
                       n_iter=args.n_iter, burn_in=args.burn_in, seed=args.seed,
                       report=lambda line: print(line, flush=True))
    case = cases.load(args.case, seed=args.seed)
    hm = result["history_matching"]
    theta = ", ".join(f"{n} = {v:.4g} {u}" for n, v, u in
                      zip(case.theta_names, hm["theta_map"], case.theta_units))
    print(f"\n{case.title}\nhistory matching: {hm['waves']} wave(s), NROY "
          f"{100 * hm['nroy_fraction'][-1]:.2f} %, θ_MAP: {theta}, truth in NROY: "
          f"{hm['truth_nroy']}\nN_s = {result['n_s']}, N_φ = {result['n_phi']}, seed "
          f"{result['seed']}\n")
    head = (f"{'scenario':>8} {'output':>6} {'NMSE z %':>9} {'NMSE δ %':>9} {'MMD':>7} "
            f"{'LPL':>9} {'cov z 3σ':>8} {'cov δ 3σ':>8} {'ESS':>9} {'seconds':>8}")
    print(head)
    for s, e in result["scenarios"].items():
        for o, name in enumerate(case.output_names):
            pick = (lambda key: None if e[key] is None else e[key][o])
            print(f"{s:>8} {name:>6} {_fmt(pick('nmse_z'), '{:9.3f}'):>9} "
                  f"{_fmt(pick('nmse_delta'), '{:9.3f}'):>9} {_fmt(pick('mmd'), '{:7.4f}'):>7} "
                  f"{_fmt(pick('lpl'), '{:9.1f}'):>9} {_fmt(pick('coverage_z_3sd'), '{:8.2f}'):>8} "
                  f"{_fmt(pick('coverage_delta_3sd'), '{:8.2f}'):>8} "
                  f"{_fmt(e['ess_per_output'][o] if s == '3' else None, '{:9.1f}'):>9} "
                  f"{e['seconds']:>8.2f}")
    if "koh" in result["scenarios"]:
        e = result["scenarios"]["koh"]
        theta = ", ".join(f"{n} = {m:.4g} ± {sd:.2g} {u}" for n, m, sd, u in
                          zip(case.theta_names, e["theta_mean"], e["theta_sd"], case.theta_units))
        print(f"\nKOH chain: {e['n_iter']:,} iterations ({e['burn_in']:,} burn-in), acceptance "
              f"{e['acceptance_rate']:.3f}, IAT {', '.join(f'{t:.1f}' for t in e['iat_per_parameter'])}"
              f", ESS {', '.join(f'{t:,.0f}' for t in e['ess_per_parameter'])}\n"
              f"KOH posterior θ: {theta}")
    if args.json:
        with open(args.json, "w", encoding="utf-8") as fh:
            json.dump(result, fh, indent=2)
        print(f"\nwrote {args.json}")
    return 0


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
    rp = sub.add_parser("reproduce", help="history matching + discrepancy scenarios + metrics "
                        "(the paper's Tables 1–3)")
    rp.add_argument("case", choices=cases.names())
    rp.add_argument("--scenarios", nargs="+", choices=list(METHODS), default=None,
                    help="decoupled scenarios 1–3 and/or koh, the Kennedy–O'Hagan baseline "
                    "(default: 1 2 3, plus koh for beam-1d)")
    rp.add_argument("--n-s", type=int, default=None, help="θ samples (default: paper's 1000)")
    rp.add_argument("--n-phi", type=int, default=None,
                    help="hyperparameter samples per θ (default: paper's 500; beam-2d 1000)")
    rp.add_argument("--n-iter", type=int, default=N_ITER,
                    help=f"KOH chain length (default: paper's {N_ITER:,})")
    rp.add_argument("--burn-in", type=int, default=BURN_IN,
                    help=f"KOH burn-in (default: paper's {BURN_IN:,})")
    rp.add_argument("--seed", type=int, default=0)
    rp.add_argument("--json", default=None, metavar="PATH", help="also write the numbers here")
    args = parser.parse_args(argv)
    try:
        return {"cases": _cmd_cases, "history-match": _cmd_history_match,
                "reproduce": _cmd_reproduce}[args.command](args)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
