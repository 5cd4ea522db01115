"""Command line: ``python -m mdcore {cases,history-match,reproduce,run,study} ...`` (exit codes:
:data:`EXIT_CODES`)."""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import sys
import warnings
from collections import Counter
from pathlib import Path

import numpy as np

from . import _cases as cases
from . import _compiled as compiled
from . import _threads as threads
from ._diagnostics import space_removed, validate_waves
from ._export import write_tables
from ._history_matching import RULE_NAMES, HistoryMatchResult, case_problem, iter_waves
from ._koh import BURN_IN, N_ITER
from ._pipeline import Method, Settings, metric_text, metrics_table
from ._reproduce import CaseRun, default_methods, run_methods
from ._study import PAPER, study
from ._validation import MAX_SEED, as_int, as_positive_float, as_seed_int, short


def _cmd_cases(args) -> int:
    for name in cases.names():
        c = cases.load(name)
        theta = ", ".join(f"{n} [{u}] ∈ [{lo:g}, {hi:g}]" for n, u, (lo, hi)
                          in zip(c.theta_names, c.theta_units, c.theta_bounds))
        print(f"{name}: {c.title}\n  θ: {theta}\n  train {c.X_train.shape[0]} × test "
              f"{c.X_test.shape[0]} observations of {', '.join(c.output_names)}\n")
    return 0


def _v_m(case, values):
    """``--v-m``: one V_m per output, or output 1's, scaled to the others as in the app."""
    if values is None:
        return None
    if len(values) == 1:
        return case.scaled_v_m(values[0])
    if len(values) != case.n_out:
        raise ValueError(f"--v-m takes 1 value or one per output ({case.n_out} for "
                         f"{case.name}: {', '.join(case.output_names)}); received {len(values)}.")
    return np.asarray(values, dtype=np.float64)


def _v_m_corr(case, values):
    """``--v-m-corr``: one ρ for every pair of outputs, or the n_out² entries row by row."""
    if values is None:
        return None
    n = case.n_out
    if len(values) == 1:
        return np.full((n, n), values[0]) + (1.0 - values[0]) * np.eye(n)
    if len(values) != n * n:
        raise ValueError(f"--v-m-corr takes 1 value (ρ for every pair of outputs) or the "
                         f"{n} × {n} = {n * n} entries of the outputs' correlation matrix row "
                         f"by row ({case.name} has {n} output(s)); received {len(values)}.")
    return np.reshape(np.asarray(values, dtype=np.float64), (n, n))


def _history_options(args, case) -> dict:
    """The history-matching options given on the command line (others: the case's)."""
    opts = {k: getattr(args, k, None) for k in (
        "threshold", "rule", "max_waves", "n_runs", "n_candidates", "convergence_ratio",
        "chi2_probability", "v_m_length")}
    opts.update(V_m=_v_m(case, args.v_m), V_m_length=opts.pop("v_m_length"),
                V_m_corr=_v_m_corr(case, args.v_m_corr))
    return {k: v for k, v in opts.items() if v is not None}


def _history_match(case, args, executor=None) -> HistoryMatchResult:
    """Run the waves with a progress bar (on a terminal) and return the history match."""
    problem = case_problem(case, seed=args.seed, executor=executor,
                           **_history_options(args, case))
    waves = []
    with _Bar("history matching", problem.options.max_waves, "wave") as bar:
        for wave in iter_waves(problem):
            waves.append(wave)
            bar.fraction(len(waves) / bar.total, f"wave {wave.index}: NROY "
                         f"{100 * wave.nroy_fraction:.2f} %")
    return HistoryMatchResult(problem, tuple(waves))


def _print_checks(case, hm, validation, splits=None) -> None:
    """Space removed, each wave's LOO check, the θ–δ shares and advice (docs/diagnostics.md)."""
    print("\nspace removed along each parameter's range: " + ", ".join(
        f"{n} {100 * r:.0f} %" for n, r in zip(case.theta_names, space_removed(
            hm.waves[-1].nroy, hm.problem.bounds))))
    print("\nemulator check, leaving out each run (a calibrated emulator: |e| > 3 for about "
          "0.3 %):\n" + _table(["wave", "runs", "|e| > 3 %", "p (bound)", "wrongly ruled out"],
                               [[str(v.wave), str(len(v.theta)), f"{100 * v.share_beyond_3:.2f}",
                                 f"{v.p_value:.2g}", str(int(v.wrongly_ruled_out.sum()))]
                                for v in validation]))
    advice = [v.advice for v in validation if v.advice]
    if splits:
        print("\nθ–δ trade-off: the share of δ's predictive variance that comes from θ "
              "(above 0.5 δ is mostly the θ chosen's)\n" + _table(
                  ["method", "output", "share from θ"],
                  [[m, name, f"{t.share[o]:.2f}"] for m, t in splits.items()
                   for o, name in enumerate(case.output_names)]))
        advice += [a for m, t in splits.items()
                   for a in t.advice(Method.parse(m).label, case.output_names)]
    print("".join(f"! {line}\n" for line in advice), end="")


def _cmd_history_match(args) -> int:
    case = _with_timeout(cases.load(args.case, seed=args.seed), args)
    with _executor(args) as executor:
        result = _history_match(case, args, executor)
    rows = [[str(w.index), f"{100 * w.nroy_fraction:.2f}", str(len(w.runs_theta)),
             str(len(w.failures)), f"{np.max(w.max_var / w.var_threshold):.3g}",
             f"{w.seconds:.2f}"] for w in result.waves]
    print(case.title)
    print(_table(["wave", "NROY %", "runs", "failed", "max var / (V_o+V_m)", "seconds"], rows))
    failed = [f for w in result.waves for f in w.failures]
    if failed:
        print(f"{len(failed)} simulator run(s) failed and were dropped; the first at θ = "
              f"{np.array2string(failed[0].theta, precision=4)}: {failed[0].message}")
    print(result.message)
    _print_checks(case, result, validate_waves(result, warn=False))
    if result.status == "ruled_out":
        return 2                                          # bad input: raise V_m or T
    print(f"θ_MAP: {_theta_text(case, result.theta_map)}")
    return 0


def _theta_text(case, theta) -> str:
    return ", ".join(f"{n} = {v:.4g} {u}" for n, v, u in
                     zip(case.theta_names, theta, case.theta_units))


def _with_timeout(case, args):
    """The case with ``--timeout`` as its simulator timeout, when given."""
    return case if args.timeout is None else dataclasses.replace(case, timeout=args.timeout)


def _table(header: list[str], rows: list[list[str]]) -> str:
    """Right-aligned columns, each as wide as its widest cell."""
    widths = [max(len(str(c)) for c in col) for col in zip(header, *rows)]
    return "\n".join(" ".join(str(c).rjust(w) for c, w in zip(line, widths))
                     for line in [header, *rows])


class _Bar:
    """A tqdm progress bar with ETA on stderr when it is a terminal; silent otherwise."""

    def __init__(self, label: str, total: float, unit: str):
        from tqdm import tqdm
        self.total = total
        self._bar = tqdm(total=total, desc=label, unit=unit, leave=False, file=sys.stderr,
                         dynamic_ncols=True, disable=not sys.stderr.isatty())

    def __enter__(self):
        return self

    def fraction(self, f: float, message: str = "") -> None:
        """The pipeline's ``progress(fraction, message)``."""
        self._bar.n = min(int(round(f * self.total)), self.total)
        if message:
            self._bar.set_postfix_str(message, refresh=False)
        self._bar.refresh()

    def __exit__(self, *exc):
        self._bar.close()


@contextlib.contextmanager
def _executor(args):
    """The executor of ``--dask ADDRESS`` or ``--workers N`` (a local Dask cluster); None."""
    address, workers = getattr(args, "dask", None), getattr(args, "dask_workers", None)
    if address is None and workers is None:
        yield None
        return
    try:
        from distributed import Client, LocalCluster
    except ImportError:
        raise ValueError("--dask and --workers need dask and distributed: pip install "
                         "'mdcore[dask]'.") from None
    if address is not None:
        with Client(address, timeout="10s") as client:
            yield client.get_executor()
        return
    workers = as_int(workers, "--workers", 1, 1024)
    # One compute thread per worker process, or N workers × every core oversubscribe.
    with LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                      dashboard_address=None, env={"MDCORE_NUM_THREADS": "1"}) as cluster, \
            Client(cluster) as client:
        yield client.get_executor()


def _settings(args, name: str) -> Settings:
    """Settings from the method options, with the paper's sizes where none is given."""
    paper = Settings.paper(name)
    return Settings(n_s=paper.n_s if args.n_s is None else args.n_s,
                    n_phi=paper.n_phi if args.n_phi is None else args.n_phi,
                    n_iter=args.n_iter, burn_in=args.burn_in, proposal=args.proposal,
                    backend=args.backend)


def _run(case, args, methods, settings_name: str) -> int:
    """History match with a bar, then the methods with a bar each, then the tables."""
    settings = _settings(args, settings_name)
    with _executor(args) as executor:
        hm = _history_match(case, args, executor)
        print(hm.message, flush=True)
        with contextlib.ExitStack() as bars:
            def bar_for(method):
                bars.close()                        # the previous method's bar
                total, unit = {Method.S1: (100, "%"), Method.S2: (settings.n_s, "θ"),
                               Method.S3: (settings.n_s * settings.n_phi, "pairs"),
                               Method.KOH: (settings.n_iter, "iterations")}[method]
                return bars.enter_context(_Bar(method.label, total, unit)).fraction

            def report(line: str) -> None:
                bars.close()                        # end the bar before the line
                print(line, flush=True)

            results = run_methods(case, hm, methods, settings, seed=args.seed, report=report,
                                  progress_for=bar_for, executor=executor)
    return _print_run(CaseRun(case, hm, settings, as_seed_int(args.seed), results), args)


def _cmd_reproduce(args) -> int:
    case = _with_timeout(cases.load(args.case, seed=args.seed), args)
    return _run(case, args, args.scenarios or default_methods(args.case), args.case)


def _cmd_run(args) -> int:
    from ._case_file import load_case_file
    case = _with_timeout(load_case_file(args.case_file, seed=args.seed,
                                        default_timeout=args.timeout), args)
    return _run(case, args, args.scenarios or ("1", "2", "3"), case.name)


def _print_run(run, args) -> int:
    """The metrics table of a run, its warnings, and the files asked for."""
    case, hm, settings = run.case, run.hm, run.settings
    print(f"\n{case.title}\nhistory matching: {len(hm.waves)} wave(s), NROY "
          f"{100 * hm.nroy_fraction[-1]:.2f} %, θ_MAP: {_theta_text(case, hm.theta_map)}, "
          f"truth in NROY: {run.truth_in_nroy}\nN_s = {settings.n_s}, N_φ = {settings.n_phi}, "
          f"seed {run.seed}\n")
    shown = ("NMSE z %", "NMSE δ %", "RMSE δ", "MMD", "LPL", "cover z ±3σ", "cover δ ±3σ",
             "ESS pairs", "ESS φ", "k̂", "seconds")
    print(_table(["method", "output", *shown],
                 [[row["method"].value + ("!" if row["unreliable"] else ""), row["output"],
                   *(metric_text(c, row[c]) for c in shown)]
                  for row in metrics_table(run.results, case.output_names)]))
    _print_checks(case, hm, run.validation, run.theta_delta)
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
    args.shown.update(notes)                # not repeated in the warnings summary
    if notes:
        print("\n! unreliable importance weights or chain:\n"
              + "\n".join(f"  - {w}" for w in notes))
    _write_json(args.json, run.to_dict)
    if args.csv:
        for path in write_tables(run, args.csv):
            print(f"wrote {path}")
    if args.out:
        print(f"wrote {_report_writer()(run, _made(args.out))} (self-contained; opens offline)")
    return 0


def _write_json(path: str | None, to_dict) -> None:
    if path:
        with open(_made(path), "w", encoding="utf-8") as fh:
            json.dump(to_dict(), fh, indent=2)
        print(f"\nwrote {path}")


def _made(path: str) -> str:
    """``path`` with its folder created: ``--out results/report.html`` needs no mkdir."""
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    return path


def _report_writer():
    """The HTML report's ``write(run, path) -> path``: plotting is not the core's, so a
    package registers it under the ``mdcore.report`` entry point (the app does)."""
    from importlib.metadata import entry_points
    found = entry_points(group="mdcore.report", name="html")
    if not found:
        raise ValueError("--out needs the HTML report of the app package, which is not "
                         "installed: pip install mdcore (with its app), or leave out --out.")
    return next(iter(found)).load()


def _cmd_study(args) -> int:
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    settings = _settings(args, args.case)
    workers = as_int(args.workers, "--workers", 1, 1024)
    history = _history_options(args, cases.load(args.case))
    with contextlib.ExitStack() as stack:
        executor = None
        if args.dask is not None:
            executor = stack.enter_context(_executor(args))
        elif workers > 1:
            # Fresh interpreters, not forks: a fork copies the locks that this process's
            # threads (the kernels' background warm-up, BLAS) hold, and its children hang.
            executor = stack.enter_context(ProcessPoolExecutor(
                max_workers=workers, mp_context=multiprocessing.get_context("spawn")))
        result = study(args.case, args.seeds, methods=args.scenarios, settings=settings,
                       executor=executor, timeout=args.timeout, history=history)
    summary, paper, hm = result.summary(), PAPER.get(args.case, {}), result.history()
    print(f"{args.case}: seeds {', '.join(map(str, result.seeds))}; N_s = {settings.n_s}, "
          f"N_φ = {settings.n_phi}; mean ± sd over seeds (paper in brackets)\n")
    error = "" if hm["theta_map_error"] is None else ", θ_MAP mean |error| " + ", ".join(
        f"{e:.4g}" for e in hm["theta_map_error"])
    print(f"history matching ({hm['rule']} rule): final NROY {100 * hm['nroy_mean']:.2f} ± "
          f"{100 * hm['nroy_sd']:.2f} % of the box, truth in NROY {hm['truth_in']}/{hm['n']}"
          f"{error}\n")
    shown = ("nmse_z", "nmse_delta", "rmse_delta", "coverage_delta_2sd", "sd_delta", "lpl")
    print(f"{'method':>6} {'output':>6} " + " ".join(f"{m:>24}" for m in shown))
    for method, entry in summary.items():
        n_out = len(entry["nmse_z"]["mean"])
        refs = [paper.get(m, {}).get(method) if n_out == 1 else None for m in shown]
        for o in range(n_out):
            cells = ["—" if v is None else f"{v['mean'][o]:.3f} ± {v['sd'][o]:.3f}"
                     + ("" if ref is None else f" [{ref:g}]")
                     for v, ref in zip((entry[m] for m in shown), refs)]
            print(f"{method:>6} {o + 1:>6} " + " ".join(c.rjust(24) for c in cells))
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
    _write_json(args.json, result.to_dict)
    return 0


def _seed(text: str) -> int:
    """``--seed``: an integer from 0 to 2**63 − 1 (argparse type)."""
    try:
        if len(text) > 25:                    # int() of 5,000 digits is slow, then refused
            raise ValueError(text)
        return as_seed_int(int(text))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"must be a whole number from 0 to {MAX_SEED} (2**63 − 1); received "
            f"{short(text)}. Each seed gives its own reproducible run, e.g. --seed 0."
        ) from None


def _timeout(text: str) -> float:
    """``--timeout``: seconds > 0 (argparse type)."""
    try:
        return as_positive_float(text, "")
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"must be a positive number of seconds per simulator run; received "
            f"{short(text)}. For example --timeout 60.") from None


SEED_HELP = "seeds every random step (default 0): the same seed, the same numbers"
#: The options of each command: (flags, help, the other add_argument keywords).
METHOD_OPTIONS = [
    ("--methods --scenarios", "decoupled scenarios 1–3 and/or koh, the Kennedy–O'Hagan baseline "
     "(default: 1 2 3, plus koh for beam-1d)",
     dict(dest="scenarios", nargs="+", choices=[m.value for m in Method])),
    ("--n-s", "θ samples (default: paper's 1000)", dict(type=int)),
    ("--n-phi", "hyperparameter samples per θ (default: paper's 500; beam-2d 1000)",
     dict(type=int)),
    ("--n-iter", f"KOH chain length (default: paper's {N_ITER:,})", dict(type=int, default=N_ITER)),
    ("--burn-in", f"KOH burn-in (default: paper's {BURN_IN:,})", dict(type=int, default=BURN_IN)),
    ("--proposal", "scenario 3's φ proposal: adaptive importance sampling (default; reliable "
     "weights) or the paper's prior draws (same budget)",
     dict(choices=["adaptive", "prior"], default=Settings.proposal)),
    ("--backend", "GP kernels of scenarios 1–3: numba (compiled, fast) or numpy (the reference); "
     "auto = numba when installed. Same numbers to ~1e-12",
     dict(choices=list(compiled.BACKENDS), default="auto")),
    ("--json", "also write the numbers here", dict(metavar="PATH"))]
OUTPUT_OPTIONS = [
    ("--seed", SEED_HELP, dict(type=_seed, default=0)),
    ("--csv", "also write nroy.csv and predictions.csv into this folder", dict(metavar="DIR")),
    ("--out", "also write a self-contained HTML report", dict(metavar="REPORT.html"))]
RULE_OPTIONS = [
    ("--v-m", "model-discrepancy variance (output units²): one per output, or one for output 1 "
     "that the others scale by (z̄_i / z̄_1)², as in the app",
     dict(type=float, nargs="+", metavar="V")),
    ("--threshold", "implausibility threshold T of the max rules (default 3)",
     dict(type=float, metavar="T")),
    ("--rule", "how the targets' implausibilities combine (default max); multivariate: I_M² over "
     "all targets with the full covariance, against a χ² quantile", dict(choices=list(RULE_NAMES))),
    ("--v-m-length", "correlation length ℓ_m of V_m over the inputs (inputs' units), one or one "
     "per output; 0: independent. Used by the multivariate rule (default: the case's)",
     dict(type=float, nargs="+", metavar="L")),
    ("--v-m-corr", "correlation of the outputs' discrepancies: one ρ for every pair, or the "
     "n_out × n_out matrix row by row (multivariate rule; default none)",
     dict(type=float, nargs="+", metavar="RHO")),
    ("--chi2-probability", "the multivariate rule's cut-off is the χ² quantile at P (default "
     "0.995)", dict(type=float, metavar="P"))]
RUN_OPTIONS = [
    ("--max-waves", "at most this many waves", dict(type=int)),
    ("--n-runs", "simulator runs added per wave (default max(10, 5 p))", dict(type=int)),
    ("--n-candidates", "candidate θ scored per wave (default 50,000 p)", dict(type=int)),
    ("--convergence-ratio", "stop when the emulator variance < R (V_o + V_m) (default 1)",
     dict(type=float, metavar="R")),
    ("--timeout", "seconds one simulator run may take; a longer run is stopped and counts as "
     "failed (default: the case file's [simulator] timeout, or none)",
     dict(type=_timeout, metavar="SECONDS"))]
DASK_OPTIONS = [
    ("--dask", "run simulator batches on the Dask scheduler at ADDRESS, e.g. tcp://10.0.0.5:8786; "
     "the numbers equal a serial run's", dict(metavar="ADDRESS")),
    ("--workers", "start a local Dask cluster of N processes for the simulator runs",
     dict(dest="dask_workers", type=int, metavar="N"))]
STUDY_OPTIONS = [
    ("--seeds", "seeds, e.g. 0-9 or 0,3,5 (default 0-9)", dict(default="0-9")),
    ("--workers", "processes running seeds in parallel (default 2; 1 runs in this one)",
     dict(type=int, default=2)),
    ("--dask", "run the seeds on the Dask scheduler at ADDRESS instead", dict(metavar="ADDRESS")),
    ("--timeout", "seconds one simulator run may take (default: no limit)",
     dict(type=_timeout, metavar="SECONDS"))]
HISTORY_GROUP = "history matching (default: the case's settings)"
DASK_GROUP = "simulator runs on a cluster (default: in this process)"


def _add(parser, options) -> None:
    for flags, text, kwargs in options:
        parser.add_argument(*flags.split(), help=text, **kwargs)


EXIT_CODES = ("exit codes: 0 done; 2 bad input (the message names the option or file and "
              "what to fix, as for a history match that rules out every θ: raise V_m or T); "
              "1 a failure (a file that cannot be written, a simulator or cluster that "
              "fails). Progress bars appear on a terminal only.")
EXAMPLES = {
    "cases": "example:\n  python -m mdcore cases",
    "history-match": "examples:\n  python -m mdcore history-match beam-1d\n"
                     "  python -m mdcore history-match shear-5 --v-m 0.2 --threshold 3.5\n"
                     "  python -m mdcore history-match beam-2d --n-runs 10 "
                     "--convergence-ratio 0.1 --max-waves 8",
    "reproduce": "examples:\n  python -m mdcore reproduce beam-1d            "
                 "# the paper's Table 1 (about a minute)\n"
                 "  python -m mdcore reproduce beam-2d --methods 1 3 --proposal prior\n"
                 "  python -m mdcore reproduce shear-5 --n-s 200 --n-phi 100 --json out.json "
                 "--csv results/ --out report.html",
    "run": "examples:\n  python -m mdcore run examples/beam_lab/beam_lab.toml\n"
           "  python -m mdcore run my_case.toml --methods 1 2 --v-m 0.02 --out report.html\n"
           "  python -m mdcore run my_case.toml --dask tcp://scheduler:8786",
    "study": "examples:\n  python -m mdcore study beam-1d --seeds 0-9\n"
             "  python -m mdcore study beam-2d --seeds 0,3,5 --methods 3 --proposal prior "
             "--json study.json",
}

#: Warning classes in words, for the summary.
WARNING_WORDS = {"LowESSWarning": "few effective importance samples",
                 "ConvergenceWarning": "did not converge",
                 "NumericalWarning": "numerical fallback",
                 "RuntimeWarning": "numerical"}


def _summarise(caught, shown: set[str]) -> None:
    """Print each distinct warning once, with how often it came, in words, leaving out
    the advice already printed with a run's table (``shown``)."""
    counts = Counter((w.category.__name__, str(w.message)) for w in caught
                     if str(w.message) not in shown)
    if not counts:
        return
    print(f"\n{sum(counts.values())} warning(s) while running, each listed once:",
          file=sys.stderr)
    for (category, message), n in counts.items():
        kind = WARNING_WORDS.get(category, category)
        print(f"  - {kind}{f' (×{n})' if n > 1 else ''}: {message}", file=sys.stderr)


def console_main() -> int:
    """``python -m mdcore`` and the ``mdcore`` script: :func:`main` with BLAS limited to one
    thread for the whole process (:func:`mdcore._threads.single_threaded_blas_for_process`)."""
    threads.single_threaded_blas_for_process()
    return main()


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m mdcore", formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Model discrepancy (Gardner et al., MSSP 2021): history matching, GP "
        "discrepancy scenarios 1–3 and the Kennedy–O'Hagan baseline.",
        epilog="\n\n".join([EXAMPLES["reproduce"], EXAMPLES["run"], EXIT_CODES]))
    sub = parser.add_subparsers(dest="command", required=True)
    commands = {
        "cases": ("list the case studies", [], []),
        "history-match": ("run Bayesian history matching on a case (waves until converged) and "
                          "print each wave's NROY share and θ_MAP", [OUTPUT_OPTIONS[0]],
                          [RULE_OPTIONS + RUN_OPTIONS, DASK_OPTIONS]),
        "reproduce": ("history matching + discrepancy scenarios + metrics (the paper's Tables "
                      "1–3)", METHOD_OPTIONS + OUTPUT_OPTIONS,
                      [RULE_OPTIONS + RUN_OPTIONS, DASK_OPTIONS]),
        "run": ("your own case: history matching + methods on a TOML case file (see the "
                "README, 'Your own data')", METHOD_OPTIONS + OUTPUT_OPTIONS,
                [RULE_OPTIONS + RUN_OPTIONS, DASK_OPTIONS]),
        "study": ("reproduce a case over many seeds: mean ± sd of every metric beside the "
                  "paper's values, and whether its patterns hold", METHOD_OPTIONS + STUDY_OPTIONS,
                  [RULE_OPTIONS])}
    for name, (text, options, groups) in commands.items():
        p = sub.add_parser(name, help=text, description=text, epilog=EXAMPLES[name] + "\n\n"
                           + EXIT_CODES, formatter_class=argparse.RawDescriptionHelpFormatter)
        if name == "run":
            p.add_argument("case_file", help="the TOML case file")
        elif name != "cases":
            p.add_argument("case", choices=cases.names())
        _add(p, options)
        for title, group in zip((HISTORY_GROUP, DASK_GROUP), groups):
            _add(p.add_argument_group(title), group)
    args = parser.parse_args(argv)
    if args.command in ("reproduce", "run", "study"):
        # Load (or compile) the numba kernels while history matching runs.
        compiled.warm_up_in_background()
    args.shown = set()              # advice printed with a run's table
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            code = {"cases": _cmd_cases, "history-match": _cmd_history_match,
                    "reproduce": _cmd_reproduce, "run": _cmd_run,
                    "study": _cmd_study}[args.command](args)
        except ValueError as exc:                  # bad input: the message says what to fix
            print(f"error: {exc}", file=sys.stderr)
            code = 2
        except (OSError, RuntimeError) as exc:     # a file that cannot be written, a failure
            print(f"error: {type(exc).__name__}: {exc}", file=sys.stderr)
            code = 1
    _summarise(caught, args.shown)
    return code


if __name__ == "__main__":
    sys.exit(main())
