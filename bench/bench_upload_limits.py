"""Peak memory and time of the app's largest allowed upload, per built-in simulator.

Usage: python bench/bench_upload_limits.py [--cases beam-1d beam-2d shear-5]
                                           [--rows 1000] [--train 300]

Each run is a fresh child process that imports what the served app imports (Panel, Bokeh,
HoloViews), builds a measurements CSV of ``--rows`` rows for the case's simulator, of
which ``--train`` training rows, every one at a distinct input (the worst layout: the
emulator and the discrepancy GPs see as many distinct inputs as there are rows), uploads
it to an :class:`~mdcore_app.state.ExplorerState` and presses "Run discrepancy" at the
app's defaults: waves to convergence, then scenarios 1–3 (``Settings.interactive()``).
Its peak resident set size is the child's ``ru_maxrss`` (the whole process). The defaults
are the limits (``mdcore._cases.MAX_ROWS``, ``mdcore._case_file.MAX_TRAINING_ROWS``).
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
import warnings


def measurements(base: str, rows: int, train: int) -> str:
    """A CSV of ``rows`` rows (``train`` training) for ``base``'s simulator: the truth plus
    the true δ plus noise, at distinct uniform inputs over the case's span."""
    import numpy as np

    from mdcore import _cases as cases
    from mdcore._case_file import TEST_COLUMN
    c = cases.load(base, seed=0)
    rng = np.random.default_rng(1)
    lo = np.minimum(c.X_train.min(0), c.X_test.min(0))
    hi = np.maximum(c.X_train.max(0), c.X_test.max(0))
    X = lo + (hi - lo) * rng.random((rows, c.d_x))
    z = c.simulate(X, c.theta_true)[0]
    delta = c.true_delta(X)
    z = z + (0.0 if delta is None else delta) + rng.normal(0, np.sqrt(c.noise_var), z.shape)
    head = [",".join([*c.x_names, *c.output_names, TEST_COLUMN])]
    return "\n".join(head + [",".join([repr(float(v)) for v in (*x, *zz)] + [str(int(i >= train))])
                             for i, (x, zz) in enumerate(zip(X, z))]) + "\n"


def child(base: str, rows: int, train: int) -> None:
    import numpy as np

    import mdcore_app.views  # noqa: F401 - the served app's imports
    from mdcore_app.state import ExplorerState
    text = measurements(base, rows, train)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    s = ExplorerState()
    s.case_name = base
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        t0 = time.perf_counter()
        assert s.upload_measurements(text.encode(), "largest.csv"), s.error
        s.run_to_convergence()
        t1 = time.perf_counter()
        hm_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        s.run_discrepancy()
        t2 = time.perf_counter()
    assert s.error == "" and len(s.results) == 3, s.error
    peak_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    print(json.dumps({"bytes": len(text), "before_kb": before, "hm_kb": hm_kb, "peak_kb": peak_kb,
                      "waves": len(s.waves), "candidates": s.n_candidates,
                      "distinct_train": int(len(np.unique(s.case.X_train, axis=0))),
                      "hm_seconds": t1 - t0, "discrepancy_seconds": t2 - t1}), flush=True)


def main() -> None:
    from mdcore._case_file import MAX_TRAINING_ROWS
    from mdcore._cases import MAX_ROWS
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cases", nargs="+", default=["beam-1d", "beam-2d", "shear-5"])
    parser.add_argument("--rows", type=int, default=MAX_ROWS)
    parser.add_argument("--train", type=int, default=MAX_TRAINING_ROWS)
    parser.add_argument("--child", nargs=3, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        child(args.child[0], int(args.child[1]), int(args.child[2]))
        return
    print(f"largest allowed upload: {args.rows:,} rows, {args.train:,} training rows, every "
          "input distinct; the app's defaults (waves to convergence, then scenarios 1–3)")
    print(f"{'case':8s} {'bytes':>8s} {'waves':>5s} {'candidates':>10s} {'HM s':>6s} "
          f"{'disc s':>7s} {'start MB':>8s} {'HM peak MB':>10s} {'peak MB':>8s}")
    for base in args.cases:
        t0 = time.perf_counter()
        proc = subprocess.run([sys.executable, __file__, "--child", base, str(args.rows),
                               str(args.train)], capture_output=True, text=True)
        if proc.returncode:
            print(f"{base}: failed\n{proc.stderr[-2000:]}")
            continue
        r = json.loads(proc.stdout.strip().splitlines()[-1])
        print(f"{base:8s} {r['bytes']:8,d} {r['waves']:5d} {r['candidates']:10,d} "
              f"{r['hm_seconds']:6.1f} {r['discrepancy_seconds']:7.1f} "
              f"{r['before_kb'] / 1024:8.0f} {r['hm_kb'] / 1024:10.0f} {r['peak_kb'] / 1024:8.0f}"
              f"   ({time.perf_counter() - t0:.0f} s in all)", flush=True)


if __name__ == "__main__":
    main()
