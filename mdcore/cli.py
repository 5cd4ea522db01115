"""Command line: ``python -m mdcore {cases,history-match,reproduce,study} ...``."""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np

from . import cases, compiled
from .export import write_tables
from .history_matching import history_match_case
from .koh import BURN_IN, N_ITER
from .pipeline import Method, Settings
from .reproduce import reproduce, run_case
from .study import PAPER, study


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


def _fmt(value, spec: str, width: int) -> str:
    """A number in ``spec``, or "—" where it does not apply; right-aligned in ``width``."""
    return ("—" if value is None else spec.format(value)).rjust(width)


def _settings(args, name: str) -> Settings:
    """Settings from the method options, with the paper's sizes where none is given."""
    paper = Settings.paper(name)
    return Settings(n_s=paper.n_s if args.n_s is None else args.n_s,
                    n_phi=paper.n_phi if args.n_phi is None else args.n_phi,
                    n_iter=args.n_iter, burn_in=args.burn_in, proposal=args.proposal,
                    backend=args.backend)


def _cmd_reproduce(args) -> int:
    run = reproduce(args.case, methods=args.scenarios, settings=_settings(args, args.case),
                    seed=args.seed, report=lambda line: print(line, flush=True))
    return _print_run(run, args)


def _cmd_run(args) -> int:
    from .case_file import load_case_file
    case = load_case_file(args.case_file, seed=args.seed)
    run = run_case(case, methods=args.scenarios or ("1", "2", "3"),
                   settings=_settings(args, case.name), seed=args.seed,
                   report=lambda line: print(line, flush=True))
    return _print_run(run, args)


def _print_run(run, args) -> int:
    """The metrics table of a run, its warnings, and the files asked for."""
    case, hm, settings = run.case, run.hm, run.settings
    theta = ", ".join(f"{n} = {v:.4g} {u}" for n, v, u in
                      zip(case.theta_names, hm.theta_map, case.theta_units))
    print(f"\n{case.title}\nhistory matching: {len(hm.waves)} wave(s), NROY "
          f"{100 * hm.nroy_fraction[-1]:.2f} %, θ_MAP: {theta}, truth in NROY: "
          f"{run.truth_in_nroy}\nN_s = {settings.n_s}, N_φ = {settings.n_phi}, seed "
          f"{run.seed}\n")
    columns = [("method", 8), ("output", 14), ("NMSE z %", 9), ("NMSE δ %", 9), ("MMD", 7),
               ("LPL", 9), ("cov z 3σ", 8), ("cov δ 3σ", 8), ("ESS pairs", 10),
               ("ESS φ", 8), ("k̂", 6), ("seconds", 8)]
    print(" ".join(name.rjust(w) for name, w in columns))
    for r in run.results:
        m, imp = r.metrics, r.importance
        for o, name in enumerate(case.output_names):
            def pick(values, o=o):
                return None if values is None else values[o]
            low = imp is not None and imp.low[o]
            cells = [r.method.value + ("!" if low else ""), name, _fmt(m.nmse_z[o], "{:.3f}", 9),
                     _fmt(pick(m.nmse_delta), "{:.3f}", 9), _fmt(m.mmd[o], "{:.4f}", 7),
                     _fmt(m.lpl[o], "{:.1f}", 9), _fmt(m.coverage_z_3sd[o], "{:.2f}", 8),
                     _fmt(pick(m.coverage_delta_3sd), "{:.2f}", 8),
                     _fmt(None if imp is None else imp.ess[o], "{:,.1f}", 10),
                     _fmt(None if imp is None else imp.ess_phi[o], "{:.1f}", 8),
                     _fmt(None if imp is None else imp.k_hat[o], "{:.2f}", 6),
                     _fmt(r.seconds, "{:.2f}", 8)]
            print(" ".join(str(c).rjust(w) for c, (_, w) in zip(cells, columns)))
    for r in run.results:
        if r.chain is not None:
            c, post = r.chain, r.model.theta
            theta = ", ".join(f"{n} = {mu:.4g} ± {sd:.2g} {u}" for n, mu, sd, u in
                              zip(case.theta_names, post.mean(axis=0), post.std(axis=0),
                                  case.theta_units))
            print(f"\nKOH chain: {c.n_iter:,} iterations ({c.burn_in:,} burn-in), acceptance "
                  f"{c.acceptance_rate:.3f}, IAT {', '.join(f'{t:.1f}' for t in c.iat)}, "
                  f"ESS {', '.join(f'{e:,.0f}' for e in c.ess)}\nKOH posterior θ: {theta}")
    notes = [w for r in run.results for w in r.warnings]
    if notes:
        print("\n! unreliable importance weights or chain:\n"
              + "\n".join(f"  - {w}" for w in notes))
    if args.json:
        with open(args.json, "w", encoding="utf-8") as fh:
            json.dump(run.to_dict(), fh, indent=2)
        print(f"\nwrote {args.json}")
    if args.csv:
        for path in write_tables(run, args.csv):
            print(f"wrote {path}")
    if args.out:
        from mdcore_app.report import write_report  # plotting lives in the app package
        print(f"wrote {write_report(run, args.out)} (self-contained; opens offline)")
    return 0


def _cmd_study(args) -> int:
    from concurrent.futures import ProcessPoolExecutor

    settings = _settings(args, args.case)
    workers = max(1, args.workers)
    if workers == 1:
        result = study(args.case, args.seeds, methods=args.scenarios, settings=settings)
    else:
        with ProcessPoolExecutor(max_workers=workers) as pool:
            result = study(args.case, args.seeds, methods=args.scenarios, settings=settings,
                           executor=pool)
    summary, paper = result.summary(), PAPER.get(args.case, {})
    print(f"{args.case}: seeds {', '.join(map(str, result.seeds))}; N_s = {settings.n_s}, "
          f"N_φ = {settings.n_phi}; mean ± sd over seeds (paper in brackets)\n")
    shown = ("nmse_z", "nmse_delta", "rmse_delta", "coverage_delta_2sd", "sd_delta", "lpl")
    print(f"{'method':>6} {'output':>6} " + " ".join(f"{m:>24}" for m in shown))
    for method, entry in summary.items():
        n_out = len(entry["nmse_z"]["mean"])
        for o in range(n_out):
            cells = []
            for metric in shown:
                v = entry[metric]
                if v is None:
                    cells.append("—".rjust(24))
                    continue
                ref = paper.get(metric, {}).get(method)
                tail = f" [{ref:g}]" if ref is not None and n_out == 1 else ""
                cells.append(f"{v['mean'][o]:.3f} ± {v['sd'][o]:.3f}{tail}".rjust(24))
            print(f"{method:>6} {o + 1:>6} " + " ".join(cells))
    pat = result.patterns()
    if pat["koh_delta_ratio"] is not None:
        print(f"\nKOH δ NMSE / best decoupled: {pat['koh_delta_ratio']:.1f}× "
              f"(paper: ≥ 10×; holds: {pat['koh_10x_worse']})")
    if pat["s3_rank"] is not None:
        print(f"scenario 3's rank on δ NMSE among 1–3: {pat['s3_rank']} (paper: 1 on beam-1d)\n"
              f"δ ±2σ coverage rises from scenario 1 to 3: {pat['coverage_rises']} "
              f"({', '.join(f'{c:.3f}' for c in pat['coverage_delta_2sd'])})")
    if pat["sd_delta"]:
        hardest = ", ".join(f"{m}: {o}" for m, o in pat["hardest_output"].items())
        print(f"δ band (mean sd) from scenario 1 to 3: "
              f"{', '.join(f'{w:.4g}' for w in pat['sd_delta'])}; widens: {pat['band_widens']}\n"
              f"hardest output (largest z NMSE) per scenario: {hardest}; best average z NMSE: "
              f"scenario {pat['best_average_nmse_z']}")
    if args.json:
        with open(args.json, "w", encoding="utf-8") as fh:
            json.dump(result.to_dict(), fh, indent=2)
        print(f"\nwrote {args.json}")
    return 0


def _add_method_options(p) -> None:
    """The options that choose the methods and their sizes (reproduce, run and study)."""
    p.add_argument("--scenarios", nargs="+", choices=[m.value for m in Method], default=None,
                   help="decoupled scenarios 1–3 and/or koh, the Kennedy–O'Hagan baseline "
                   "(default: 1 2 3, plus koh for beam-1d)")
    p.add_argument("--n-s", type=int, default=None, help="θ samples (default: paper's 1000)")
    p.add_argument("--n-phi", type=int, default=None,
                   help="hyperparameter samples per θ (default: paper's 500; beam-2d 1000)")
    p.add_argument("--n-iter", type=int, default=N_ITER,
                   help=f"KOH chain length (default: paper's {N_ITER:,})")
    p.add_argument("--burn-in", type=int, default=BURN_IN,
                   help=f"KOH burn-in (default: paper's {BURN_IN:,})")
    p.add_argument("--proposal", choices=["prior", "adaptive"], default="prior",
                   help="scenario 3's φ proposal: the paper's prior draws, or adaptive "
                   "importance sampling (same budget)")
    p.add_argument("--backend", choices=list(compiled.BACKENDS), default="auto",
                   help="GP kernels of scenarios 1–3: numba (compiled, fast) or numpy (the "
                   "reference); auto = numba when installed. Same numbers to ~1e-12")
    p.add_argument("--json", default=None, metavar="PATH", help="also write the numbers here")


def _add_output_options(p) -> None:
    """The seed and the files a single run writes (reproduce and run)."""
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--csv", default=None, metavar="DIR",
                   help="also write nroy.csv and predictions.csv into this folder")
    p.add_argument("--out", default=None, metavar="REPORT.html",
                   help="also write a self-contained HTML report")


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
    _add_method_options(rp)
    _add_output_options(rp)
    rn = sub.add_parser("run", help="your own case: history matching + methods on a TOML "
                        "case file (see the README, 'Your own data')")
    rn.add_argument("case_file", help="the TOML case file")
    _add_method_options(rn)
    _add_output_options(rn)
    st = sub.add_parser("study", help="reproduce a case over many seeds: mean ± sd of every "
                        "metric beside the paper's values, and whether its patterns hold")
    st.add_argument("case", choices=cases.names())
    _add_method_options(st)
    st.add_argument("--seeds", default="0-9", help="seeds, e.g. 0-9 or 0,3,5 (default 0-9)")
    st.add_argument("--workers", type=int, default=2,
                    help="processes running seeds in parallel (default 2; 1 runs in this one)")
    args = parser.parse_args(argv)
    if args.command in ("reproduce", "run", "study"):
        # Load (or compile) the numba kernels while history matching runs.
        compiled.warm_up_in_background()
    try:
        return {"cases": _cmd_cases, "history-match": _cmd_history_match,
                "reproduce": _cmd_reproduce, "run": _cmd_run,
                "study": _cmd_study}[args.command](args)
    except ValueError as exc:                      # bad input: the message says what to fix
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except (OSError, RuntimeError) as exc:         # a file that cannot be written, a failure
        print(f"error: {type(exc).__name__}: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
