"""Fidelity study: a case reproduced over many seeds, summarised beside the paper's tables.

The paper reports a single run; whether its *pattern* holds is a statement over seeds (one
seed: one noise draw, history match, set of θ and φ samples and KOH chain).
"""

from __future__ import annotations

import re
import warnings
from concurrent.futures import Executor
from dataclasses import dataclass

import numpy as np

from . import _cases as cases
from ._pipeline import Settings
from ._reproduce import default_methods, parse_methods, reproduce
from ._validation import MAX_SEED, choose, short

#: The paper's published NMSE values (docs/cases.md), per case and method, [%].
PAPER = {
    "beam-1d": {"nmse_z": {"1": 0.768, "2": 0.765, "3": 0.765, "koh": 0.770},
                "nmse_delta": {"1": 1.756, "2": 2.288, "3": 1.654, "koh": 39.349}},
    "beam-2d": {"nmse_z": {"1": 0.433, "2": 0.425, "3": 0.423},
                "nmse_delta": {"1": 0.587, "2": 0.481, "3": 0.519}},
}
METRICS = ("nmse_z", "nmse_delta", "rmse_delta", "mmd", "lpl", "coverage_z_2sd",
           "coverage_z_3sd", "coverage_delta_2sd", "coverage_delta_3sd", "sd_z", "sd_delta")
#: Most seeds one study runs (each seed is a whole reproduce run).
MAX_SEEDS = 10_000


def parse_seeds(text: str) -> tuple[int, ...]:
    """Seeds from ``"0-9"``, ``"0,3,5"`` or ``"2"`` (ranges inclusive).

    Examples
    --------
    >>> parse_seeds("0-2,7")
    (0, 1, 2, 7)
    """
    seeds: list[int] = []
    for part in str(text).split(","):
        m = re.fullmatch(r"\s*(\d{1,19})\s*(?:-\s*(\d{1,19})\s*)?", part)
        if m is None or (m.group(2) is not None and int(m.group(2)) < int(m.group(1))) \
                or int(m.group(2) or m.group(1)) > MAX_SEED:
            raise ValueError(f"seeds must look like '0-9', '0,3,5' or '2' (integers from 0 to "
                             f"2**63 − 1, ranges low-high); received {short(text)}.")
        lo, hi = int(m.group(1)), int(m.group(2) or m.group(1))
        if len(seeds) + hi - lo + 1 > MAX_SEEDS:
            raise ValueError(f"seeds must name at most {MAX_SEEDS:,} seeds (each is a whole "
                             f"reproduce run); received {short(text)}, which names "
                             f"{len(seeds) + hi - lo + 1:,} or more. Give a shorter range.")
        seeds.extend(range(lo, hi + 1))
    if len(set(seeds)) != len(seeds):
        raise ValueError(f"seeds repeat in {text!r}; give each seed once.")
    return tuple(seeds)


def _one(name: str, seed: int, methods: tuple, settings: Settings,
         timeout: float | None = None, history: dict | None = None) -> dict:
    """One seed's reproduce run as its JSON dict (picklable, small: no models)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")          # collected in each method's "warnings"
        return reproduce(name, methods=methods, settings=settings, seed=seed,
                         timeout=timeout, history_matching=history).to_dict()


@dataclass(frozen=True)
class Study:
    """The runs of one ``case`` over ``seeds`` with ``settings``: ``runs`` holds each seed's
    :meth:`mdcore.CaseRun.to_dict`, in seed order."""

    case: str
    seeds: tuple
    settings: Settings
    runs: tuple

    @property
    def methods(self) -> tuple[str, ...]:
        return tuple(self.runs[0]["methods"])

    def values(self, method: str, metric: str) -> np.ndarray | None:
        """Per seed and output, shape (n_seeds, n_out), or None where the metric is unknown."""
        rows = [r["methods"][method]["metrics"][metric] for r in self.runs]
        return None if any(v is None for v in rows) else np.array(rows, dtype=float)

    def _known(self, method: str, metric: str) -> np.ndarray:
        """:meth:`values` of a metric every run has (z metrics, band widths)."""
        v = self.values(method, metric)
        if v is None:
            raise ValueError(f"the runs have no {metric!r} for method {method!r}.")
        return v

    def summary(self) -> dict:
        """method -> metric -> {"mean": [per output], "sd": [per output]} (None if unknown)."""
        out: dict = {}
        for m in self.methods:
            out[m] = {}
            for metric in METRICS:
                v = self.values(m, metric)
                out[m][metric] = None if v is None else {
                    "mean": v.mean(axis=0).tolist(),
                    "sd": (v.std(axis=0, ddof=1) if len(v) > 1 else np.zeros(v.shape[1])).tolist()}
            ess = [r["methods"][m]["importance"] for r in self.runs]
            if all(e is not None for e in ess):
                out[m]["ess"] = {"mean": np.mean([e["ess"] for e in ess], axis=0).tolist(),
                                 "min": np.min([e["ess"] for e in ess], axis=0).tolist()}
        return out

    def history(self) -> dict:
        """History matching over the seeds: the rule, the final NROY share (mean, sd), how
        many seeds keep the truth in NROY, θ_MAP's mean absolute error (None: no truth)."""
        hm = [r["history_matching"] for r in self.runs]
        share = np.array([h["nroy_fraction"][-1] for h in hm])
        truth = cases.load(self.case).theta_true
        return {"rule": hm[0].get("rule"), "nroy_mean": float(share.mean()),
                "nroy_sd": float(share.std(ddof=1)) if len(share) > 1 else 0.0,
                "truth_in": sum(bool(h["truth_nroy"]) for h in hm), "n": len(hm),
                "theta_map_error": None if truth is None else np.mean(
                    [np.abs(np.array(h["theta_map"]) - truth) for h in hm], axis=0).tolist()}

    def patterns(self) -> dict:
        """The paper's patterns over the seeds' means (None where they cannot be judged).

        KOH's δ NMSE ≥ 10× the best decoupled scenario's (Table 1); δ's ±2σ coverage does not
        fall from scenario 1 to 3; scenario 3's rank on δ NMSE; Table 3: the hardest output,
        whether the δ band widens from 1 to 3 and the best average z NMSE.
        """
        decoupled: list[str] = [m for m in ("1", "2", "3") if m in self.methods]
        nmse_z = {m: np.mean(self._known(m, "nmse_z"), axis=0) for m in decoupled}
        width = [float(np.mean(self._known(m, "sd_delta"))) for m in decoupled]
        table3 = {"hardest_output": {m: int(np.argmax(v)) + 1 for m, v in nmse_z.items()},
                  "band_widens": bool(all(b >= a for a, b in zip(width, width[1:]))),
                  "sd_delta": width,
                  "best_average_nmse_z": min(nmse_z, key=lambda m: float(np.mean(nmse_z[m])))
                  if nmse_z else None}
        mean = {m: self.values(m, "nmse_delta") for m in self.methods}
        if any(v is None for v in mean.values()):
            return {"koh_delta_ratio": None, "koh_10x_worse": None,
                    "coverage_rises": None, "s3_rank": None, **table3}
        avg = {m: float(np.mean(self._known(m, "nmse_delta"))) for m in mean}
        ratio = avg["koh"] / min(avg[m] for m in decoupled) if "koh" in avg and decoupled \
            else None
        cov = [float(np.mean(self._known(m, "coverage_delta_2sd"))) for m in decoupled]
        rank = 1 + sorted(avg[m] for m in decoupled).index(avg["3"]) if "3" in avg else None
        return {"koh_delta_ratio": ratio,
                "koh_10x_worse": None if ratio is None else bool(ratio >= 10.0),
                "coverage_rises": bool(all(b >= a - 1e-12 for a, b in zip(cov, cov[1:]))),
                "coverage_delta_2sd": cov, "s3_rank": rank, **table3}

    def to_dict(self) -> dict:
        """JSON: settings, per-seed runs, the summary, the paper's values and the patterns."""
        s = self.settings
        return {"case": self.case, "seeds": list(self.seeds),
                "settings": {"n_s": s.n_s, "n_phi": s.n_phi, "n_iter": s.n_iter,
                             "burn_in": s.burn_in, "prune": s.prune, "proposal": s.proposal,
                             "fit_iterations": s.fit_iterations},
                "summary": self.summary(), "history_matching": self.history(),
                "paper": PAPER.get(self.case), "patterns": self.patterns(), "runs": list(self.runs)}


def study(name: str, seeds, *, methods=None, settings: Settings | None = None,
          executor: Executor | None = None, timeout: float | None = None,
          history: dict | None = None) -> Study:
    """Reproduce ``name`` once per seed and collect the runs.

    Parameters
    ----------
    name : str
    seeds : iterable of int, or str
        Seeds (``"0-9"`` is accepted, see :func:`parse_seeds`).
    methods : sequence of {1, 2, 3, "koh"}, optional
        Default :func:`mdcore._reproduce.default_methods`.
    settings : Settings, optional
        Default the paper's sizes.
    executor : concurrent.futures.Executor, optional
        Runs the seeds (e.g. a ``ProcessPoolExecutor``); default: serially here. The numbers
        do not depend on it.
    timeout : float, optional
        Seconds one simulator run may take (:attr:`mdcore.Case.timeout`).
    history : dict, optional
        History-matching options for every seed (``rule``, ``V_m_length`` …).

    Returns
    -------
    Study
    """
    choose(name, "case name", cases.names())
    seeds = parse_seeds(seeds) if isinstance(seeds, str) else tuple(seeds)
    if not seeds:
        raise ValueError("seeds is empty; give at least one seed, for example '0-9'.")
    for s in seeds:
        if isinstance(s, bool) or not isinstance(s, (int, np.integer)) or s < 0:
            raise ValueError(f"seeds must be non-negative integers; received {s!r}.")
    chosen = parse_methods(default_methods(name) if methods is None else methods)
    settings = Settings.paper(name) if settings is None else settings
    seeds = tuple(int(s) for s in seeds)
    jobs = [(name, s, tuple(m.value for m in chosen), settings, timeout, history) for s in seeds]
    runs = ([_one(*job) for job in jobs] if executor is None
            else [f.result() for f in [executor.submit(_one, *job) for job in jobs]])
    return Study(name, seeds, settings, tuple(runs))

