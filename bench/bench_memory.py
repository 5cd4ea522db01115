"""Peak memory of scenarios 2 and 3 on beam-1d: the paper's N_s × N_φ against 10× as many.

Usage: python bench/bench_memory.py [--scale 10] [--scenarios 3 2] [--backend auto]

Each run is a fresh child process (``python bench/bench_memory.py --child …``) that loads
beam-1d (seed 0), history-matches it and runs one method through
:func:`mdcore.run_method`: the θ draws, the weights of every (θ, φ) pair, the
mixture prediction at the test inputs, the metrics and the importance diagnostics. Its
peak resident set size is the child's ``ru_maxrss`` as :func:`os.wait4` reports it (the
whole process: interpreter, NumPy, numba and the compiled kernels included). The child also
prints its ``ru_maxrss`` just before the method runs, so the growth due to the method alone
is ``peak − before``.

The paper's sizes on beam-1d are N_s = 1000, N_φ = 500 (500,000 pairs); ``--scale 10``
runs N_s = 10,000 (5,000,000 pairs for scenario 3, 10,000 for scenario 2). The work is
chunked (:mod:`mdcore._discrepancy`): no array of pairs × N or pairs × N* is ever formed.
What grows with the pairs is the log weights, (n_out, N_s, N_φ) float64 (40 MB at 10×),
and a few temporaries of that shape (normalising, Pareto k̂, ESS). The φ draws
(N_s, N_φ, P) are kept only up to ``mdcore._discrepancy.KEEP_DRAWS_BYTES`` (64 MB); above,
the model keeps the generator state of each chunk and draws them again when predicting
(:class:`mdcore._discrepancy.PriorDraws`), so at 10× they cost no 160 MB.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
import warnings

CASE = "beam-1d"


def child(scenario: int, n_s: int, n_phi: int, backend: str) -> None:
    """One run in this process; prints a JSON line with its figures."""
    from mdcore import _cases as cases
    from mdcore._history_matching import history_match_case
    from mdcore._pipeline import Settings, run_method

    case = cases.load(CASE, seed=0)
    hm = history_match_case(case, seed=0)
    settings = Settings(n_s=n_s, n_phi=n_phi, backend=backend)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = run_method(case, hm, scenario, settings, seed=0)
    seconds = time.perf_counter() - t0
    print(json.dumps({"before_kb": before, "seconds": seconds,
                      "nmse_delta": result.metrics.nmse_delta[0],
                      "ess": None if result.importance is None else result.importance.ess[0],
                      "n_components": int(result.model.n_components[0])}), flush=True)


def run_child(scenario: int, n_s: int, n_phi: int, backend: str) -> dict:
    """Run :func:`child` in a subprocess; its figures and its peak RSS (MB)."""
    cmd = [sys.executable, os.path.abspath(__file__), "--child", "--scenario", str(scenario),
           "--n-s", str(n_s), "--n-phi", str(n_phi), "--backend", backend]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True)
    assert proc.stdout is not None
    out = proc.stdout.read()
    _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        raise RuntimeError(f"the child run {cmd} failed with exit code {proc.returncode}")
    figures = json.loads(out.strip().splitlines()[-1])
    figures["peak_mb"] = usage.ru_maxrss / 1024          # Linux: kilobytes
    figures["before_mb"] = figures.pop("before_kb") / 1024
    return figures


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scale", type=int, default=10, help="multiple of the paper's N_s")
    ap.add_argument("--scenarios", type=int, nargs="+", default=[3, 2])
    ap.add_argument("--backend", default="auto")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--scenario", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--n-s", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--n-phi", type=int, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        child(args.scenario, args.n_s, args.n_phi, args.backend)
        return

    from mdcore._pipeline import PAPER_SIZES

    n_s, n_phi = PAPER_SIZES[CASE]
    print(f"{CASE}, backend {args.backend}; peak RSS of each child process (MB)")
    print(f"{'scenario':>8} {'N_s×N_φ':>12} {'pairs':>10} {'seconds':>8} {'before':>7} "
          f"{'peak':>7} {'growth':>7} {'ratio peak':>10} {'ratio growth':>12}")
    for scenario in args.scenarios:
        k = n_phi if scenario == 3 else 1
        rows = []
        for size in (n_s, args.scale * n_s):
            f = run_child(scenario, size, n_phi, args.backend)
            rows.append(f)
            base = rows[0]
            growth = f["peak_mb"] - f["before_mb"]
            base_growth = base["peak_mb"] - base["before_mb"]
            print(f"{scenario:>8} {f'{size}×{k}':>12} {size * k:>10,} {f['seconds']:>8.1f} "
                  f"{f['before_mb']:>7.0f} {f['peak_mb']:>7.0f} {growth:>7.0f} "
                  f"{f['peak_mb'] / base['peak_mb']:>10.2f} "
                  f"{growth / max(base_growth, 1.0):>12.2f}", flush=True)


if __name__ == "__main__":
    main()
