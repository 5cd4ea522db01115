"""Diagnostics (docs/diagnostics.md): each wave's emulator by leaving out each run, what each
wave ruled out for any number of parameters, and the share of δ's variance due to θ."""

from __future__ import annotations

import dataclasses
import warnings
from typing import NamedTuple

import numpy as np
import scipy.stats
from scipy.special import logsumexp

from ._discrepancy import DiscrepancyModel
from ._emulator import _design
from ._exceptions import EmulatorWarning
from ._history_matching import (
    MULTIVARIATE,
    HistoryMatchResult,
    combine,
    elementwise_implausibility,
)
from ._multivariate import emulator_cov, implausibility_and_logdet
from ._validation import as_float_array, as_int, check_type

#: P(|e| > 3) for a standard normal e: the share of LOO errors a calibrated emulator has.
P_BEYOND_3 = float(2.0 * scipy.stats.norm.sf(3.0))
#: A wave's errors are "clearly too large" when :func:`loo_p_value` is below this.
TOO_CONFIDENT_P = 1e-3
#: The smallest p-value bound stated (advice, the app's table): below it the bound has
#: underflowed in double precision, and read "p ≤ 0.0e+00" beside a table's "1e-16".
SMALLEST_P = 1e-16
#: δ is "mostly a consequence of θ" above this share of its variance (between > within).
MOSTLY_THETA = 0.5
#: Candidates scored at once by :func:`space_views` (bounds the emulator variance array).
SCORE_BLOCK = 20_000


class EmulatorLOO(NamedTuple):
    """Leave-one-run-out ``mean``, latent ``var`` and ``error`` ``(y − mean) / √(var + σ_n²)``
    (R, N, n_out); each run's latent covariance is ``Q_x diag(s) Q_xᵀ``, ``s`` (R, n_out, N)."""

    mean: np.ndarray
    var: np.ndarray
    error: np.ndarray
    s: np.ndarray


def emulator_loo(emulator) -> EmulatorLOO:
    """Leave out each run (a θ with its N inputs) of an emulator in turn, in closed form.

    The block of ``K⁻¹`` of run r is ``C_r = Q_x diag(c_r) Q_xᵀ``, ``c_r = (Q_θ²)_r W``:
    ``E[y_r | y_−r] = y_r − C_r⁻¹ (K⁻¹ (y − F β_−r))_r``, ``Cov = C_r⁻¹`` (Dubrule 1983),
    β_−r the mean refitted without run r, same hyperparameters (docs/diagnostics.md §1).
    """
    em = emulator
    R, N, n_out = em.y_train.shape
    if R < 2:
        raise ValueError(f"leave-one-run-out needs at least 2 simulator runs; the emulator has "
                         f"{R}. Add runs (n_runs or initial_design).")
    lo, span = em.bounds[:, 0], em.bounds[:, 1] - em.bounds[:, 0]
    F = _design(em.unit_x(em.X_train), (em.theta_train - lo) / span).reshape(R, N, -1)
    Fr = np.einsum("rnq,rns->rqs", F, F)
    G = Fr.sum(axis=0) - Fr                       # FᵀF without run r, (R, q, q)
    Fty = np.einsum("rnq,rno->roq", F, em.y_train)
    # lstsq, not solve: without one run the θ columns can be collinear (few runs)
    beta = np.stack([np.linalg.lstsq(G[r], (Fty.sum(axis=0) - Fty[r]).T, rcond=None)[0].T
                     for r in range(R)])         # β_−r, (R, n_out, q)
    out, s = np.empty((3, R, N, n_out)), np.empty((R, n_out, N))
    for o, g in enumerate(em.gps):
        def kinv(M, g=g):                   # K⁻¹ vec(M) for M (R, N), run-major
            return g.Q_t @ (g.W * (g.Q_t.T @ M @ g.Q_x)) @ g.Q_x.T

        KF = np.stack([kinv(F[..., j]) for j in range(F.shape[2])], axis=2)
        a = g.A / np.exp(2 * g.log_params[0]) + np.einsum("rnq,rq->rn", KF, g.beta - beta[:, o])
        c, sn2 = g.Q_t ** 2 @ g.W, np.exp(2.0 * g.log_params[-1])               # (R, N)
        noisy = (1.0 / c) @ (g.Q_x ** 2).T
        out[0, ..., o] = em.y_train[..., o] - ((a @ g.Q_x) / c) @ g.Q_x.T
        out[1, ..., o] = np.maximum(noisy - sn2, 0.0)
        out[2, ..., o] = (em.y_train[..., o] - out[0, ..., o]) / np.sqrt(noisy)
        s[:, o] = np.maximum(1.0 / c - sn2, 0.0)
    return EmulatorLOO(out[0], out[1], out[2], s)


class WaveValidation(NamedTuple):
    """LOO check of a wave's emulator, runs ``theta`` (R, p) (:func:`validate_wave`): each run's
    combined ``loo_implausibility`` (without it) and ``simulator_implausibility`` (R,);
    ``wrongly_ruled_out`` (R,): the first above ``cutoff``, the second not; ``advice`` or None."""

    wave: int
    theta: np.ndarray
    loo: EmulatorLOO
    share_beyond_3: float
    p_value: float
    loo_implausibility: np.ndarray
    simulator_implausibility: np.ndarray
    wrongly_ruled_out: np.ndarray
    cutoff: float
    advice: str | None

    def as_dict(self) -> dict:
        """The summary for JSON (``reproduce --json``)."""
        return {"wave": self.wave, "runs": len(self.theta), "share_beyond_3": self.share_beyond_3,
                "p_value": self.p_value, "too_confident": self.p_value < TOO_CONFIDENT_P,
                "max_abs_error": float(np.max(np.abs(self.loo.error))),
                "wrongly_ruled_out": int(np.count_nonzero(self.wrongly_ruled_out))}


def loo_p_value(error) -> float:
    """Upper bound on the p-value of LOO errors ``error`` (R, N, n_out), whatever their
    correlation (docs/diagnostics.md §1): twice the smaller of ``P(X ≥ k)``, X ~ Bin(R n_out,
    min(1, N · 0.27 %)), k the (run, output) units with an error beyond ±3, and of
    ``R N n_out · P(|e| > max |error|)``, e ~ N(0, 1) (union bounds)."""
    R, N, n_out = error.shape
    k = int(np.count_nonzero(np.any(np.abs(error) > 3.0, axis=1)))
    runs = scipy.stats.binom.sf(k - 1, R * n_out, min(1.0, N * P_BEYOND_3))
    largest = error.size * 2.0 * scipy.stats.norm.sf(np.max(np.abs(error)))
    return float(min(1.0, 2.0 * runs, 2.0 * largest))


def validate_wave(wave, *, warn: bool = True) -> WaveValidation:
    """Check a wave's emulator by leaving out each run; with ``warn``, an
    :class:`~mdcore.EmulatorWarning` names the wave and what to do when the
    errors are too large or a run is wrongly ruled out."""
    em, problem = wave.emulator, wave.problem
    loo, y = emulator_loo(em), em.y_train
    if problem.options.rule == MULTIVARIATE:   # I_M², LOO covariance (docs/method.md §5)
        cov = emulator_cov(em, em.theta_train[:1])
        I_loo, I_sim = (implausibility_and_logdet(cov._replace(mean=m.transpose(0, 2, 1), s=s),
                                                  problem.z, problem.V)[0]
                        for m, s in ((loo.mean, loo.s), (y, 0.0 * loo.s)))
    else:
        I_loo, I_sim = (combine(elementwise_implausibility(problem.z, m, v, V_o=problem.V_o,
                                                           V_m=problem.V_m), problem.options.rule)
                        for m, v in ((loo.mean, loo.var), (y, 0.0)))
    wrong = (I_loo > problem.cutoff) & (I_sim <= problem.cutoff)
    share, p_value = float(np.mean(np.abs(loo.error) > 3.0)), loo_p_value(loo.error)
    parts = []
    if p_value < TOO_CONFIDENT_P:
        parts.append(f"{100 * share:.1f} % of its leave-one-out standardised errors are beyond "
                     f"±3 and the largest is {np.max(np.abs(loo.error)):.1f} (calibrated: about "
                     f"0.3 %, rarely above 4.5; p ≤ {max(p_value, SMALLEST_P):.1e}), so it is too "
                     "confident")
    if wrong.any():
        parts.append(f"{int(wrong.sum())} of its {len(wrong)} runs would be ruled out by the "
                     f"emulator without that run (implausibility up to {I_loo[wrong].max():.2f}, "
                     f"cut-off {problem.cutoff:.3g}) although the simulator itself finds them not "
                     f"implausible (at most {I_sim[wrong].max():.2f}), good θ may be lost")
    advice = None if not parts else (
        f"wave {wave.index}: " + "; ".join(parts) + ". Add simulator runs (n_runs), raise V_m "
        "if the simulator itself is near the cut-off, or, if the errors trend with θ (a mean "
        "the linear one misses), return a smoother output from the simulator (its log, say).")
    if advice and warn:
        warnings.warn(advice, EmulatorWarning, stacklevel=2)
    return WaveValidation(wave.index, em.theta_train, loo, share, p_value, I_loo, I_sim, wrong,
                          problem.cutoff, advice)


def validate_waves(hm, *, warn: bool = True) -> tuple[WaveValidation, ...]:
    """:func:`validate_wave` for every wave of a history match."""
    check_type(hm, HistoryMatchResult, "hm", "a HistoryMatchResult (mdcore.history_match_case)")
    return tuple(validate_wave(w, warn=warn) for w in hm.waves)


def _bin(theta, bounds, bins: int) -> np.ndarray:
    """Bin of each value along each parameter, ``bins`` equal bins over ``bounds`` (p, 2)."""
    unit = (theta - bounds[:, 0]) / (bounds[:, 1] - bounds[:, 0])
    return np.clip((unit * bins).astype(np.int64), 0, bins - 1)


def space_removed(samples, bounds, *, bins: int = 20) -> np.ndarray:
    """Share of each parameter's range that ``samples`` (K, p) leave empty, (p,):
    ``1 − exp(H_k) / bins``, H_k the Miller–Madow entropy of a histogram of parameter k over
    ``bounds`` (p, 2); ``1 − L / width`` for samples even over a length L (docs/diagnostics.md
    §2), 1 for none."""
    samples = np.atleast_2d(np.asarray(samples, dtype=np.float64))
    if samples.shape[0] == 0:
        return np.ones(len(bounds))
    idx = _bin(samples, bounds, bins)
    q = np.stack([np.bincount(i, minlength=bins) for i in idx.T]) / samples.shape[0]
    H = -np.sum(q * np.log(np.where(q > 0, q, 1.0)), axis=1) + (
        np.count_nonzero(q, axis=1) - 1) / (2.0 * samples.shape[0])
    return 1.0 - np.minimum(np.exp(H) / bins, 1.0)


class SpaceViews(NamedTuple):
    """What W waves ruled out, on wave 1's candidates ``theta`` (M, p) (:func:`space_views`):
    ``space_removed`` (W, p); bin ``edges`` (p, bins + 1); the lattice's panels ``pairs``
    (n_pairs, 2), (k, l) with k < l, and per bin [along k, along l] of each the smallest
    ``implausibility`` and the share of points never ruled out (NaN: no point), (n_pairs,
    bins, bins), with ``*_1d`` (p, bins) along each parameter; ``implausibility`` (M,) is
    the largest up to the wave that ruled the point out, ``ruled_out_by`` (M,) (0: none)."""

    nroy_fraction: np.ndarray
    space_removed: np.ndarray
    edges: np.ndarray
    pairs: np.ndarray
    min_implausibility: np.ndarray
    optical_depth: np.ndarray
    min_implausibility_1d: np.ndarray
    optical_depth_1d: np.ndarray
    theta: np.ndarray
    implausibility: np.ndarray
    ruled_out_by: np.ndarray
    hits: np.ndarray
    cutoff: float


def space_views(hm, *, bins: int = 20, waves: int | None = None) -> SpaceViews:
    """The space views of a history match's first ``waves`` waves (default all), ``bins``
    bins a parameter (Vernon et al. 2010; docs/diagnostics.md §2); memory O(M + p² bins²).
    A later wave's emulator is fitted inside the earlier NROY set, so it scores only the
    points the earlier waves kept."""
    bins = as_int(bins, "bins", 2, 200)
    n_w = len(hm.waves) if waves is None else as_int(waves, "waves", 1, len(hm.waves))
    chosen, cut, b = hm.waves[:n_w], hm.problem.cutoff, hm.problem.bounds
    theta, I = chosen[0].candidates, chosen[0].candidate_implausibility.copy()
    by = np.where(I > cut, 1, 0)
    for w in chosen[1:]:
        alive = np.flatnonzero(by == 0)
        for start in range(0, alive.size, SCORE_BLOCK):
            rows = alive[start:start + SCORE_BLOCK]
            Iw = w.combined_implausibility(theta[rows])
            I[rows] = np.maximum(I[rows], Iw)
            by[rows[Iw > cut]] = w.index
    idx, ok, p = _bin(theta, b, bins), (by == 0).astype(np.float64), b.shape[0]
    panels = np.array([(k, l) for k in range(p) for l in range(k, p)], np.int64)  # (k, k): 1-D
    low, depth = np.full((2, len(panels), bins * bins), np.nan)
    for c, (k, l) in enumerate(panels):       # one panel at a time: bounded memory
        cell = idx[:, k] * bins + idx[:, l]
        n, least = np.bincount(cell, minlength=bins * bins), np.full(bins * bins, np.inf)
        np.minimum.at(least, cell, I)
        kept, seen = np.bincount(cell, ok, bins * bins), n > 0
        low[c, seen], depth[c, seen] = least[seen], kept[seen] / n[seen]
    low, depth = low.reshape(-1, bins, bins), depth.reshape(-1, bins, bins)
    diag, d = panels[:, 0] == panels[:, 1], np.arange(bins)
    return SpaceViews(np.array(hm.nroy_fraction[:n_w]),
                      np.array([space_removed(w.nroy, b, bins=bins) for w in chosen]),
                      np.linspace(b[:, 0], b[:, 1], bins + 1).T, panels[~diag], low[~diag],
                      depth[~diag], low[diag][:, d, d], depth[diag][:, d, d], theta, I, by,
                      np.bincount(by, minlength=n_w + 1)[1:], float(cut))


class ThetaDeltaSplit(NamedTuple):
    """δ at J ``theta`` (J, p) of a mixture with ``weight`` (n_out, J): ``mean``, ``var``
    (J, N*, n_out) ``E[δ | θ_j]``, ``Var[δ | θ_j]``; ``between`` ``Var_θ(E[δ | θ])`` and
    ``within`` ``E_θ Var(δ | θ)`` (N*, n_out) add up to ``Var(δ)``; ``share`` (n_out,)
    ``Σ_x between / Σ_x (between + within)``."""

    theta: np.ndarray
    weight: np.ndarray
    mean: np.ndarray
    var: np.ndarray
    between: np.ndarray
    within: np.ndarray
    share: np.ndarray

    @property
    def mostly_theta(self) -> np.ndarray:
        """Per output, whether δ is mostly a consequence of θ (share > :data:`MOSTLY_THETA`)."""
        return self.share > MOSTLY_THETA

    def as_dict(self) -> dict:
        """The summary for JSON (lists per output; ``between``, ``within`` averaged over x)."""
        return {"share": self.share.tolist(), "mostly_theta": self.mostly_theta.tolist(),
                "between": self.between.mean(axis=0).tolist(),
                "within": self.within.mean(axis=0).tolist(), "n_theta": len(self.theta)}

    def advice(self, label: str, output_names) -> list[str]:
        """In plain words, per output where δ is mostly a consequence of θ."""
        return [f"{label}, {name}: {100 * share:.0f} % of δ's predictive variance comes from "
                "which θ in the NROY set is used (δ varies more across θ than at one θ). This "
                "δ is mostly a consequence of the θ chosen, not physics: narrow θ first (data "
                "that tell the parameters apart, or a smaller V_m if you can justify one) "
                "before reading its shape." for name, share, mostly
                in zip(output_names, self.share, self.mostly_theta) if mostly]


def theta_delta_split(model, X_star, *, n_theta: int = 100) -> ThetaDeltaSplit:
    """Split the predictive variance of a :class:`~mdcore.DiscrepancyModel`'s δ
    at ``X_star`` (N*, d_x) into θ's part and the rest (law of total variance).

    Per θ_j, ``E[δ | θ_j]`` and ``Var[δ | θ_j]`` are :meth:`DiscrepancyModel.predict` of
    its own φ components (Eq. 15 within θ_j). With more than ``n_theta`` θ, ``n_theta``
    are picked by systematic resampling (offset ½, so no seed) on the θ weights averaged
    over outputs, and reweighted per output (docs/diagnostics.md §3). Scenario 1 gives 0.
    """
    check_type(model, DiscrepancyModel, "model",
               "a DiscrepancyModel (MethodResult.model of scenarios 1–3)")
    X_star = as_float_array(X_star, "X_star", ndim=2)
    if X_star.shape[1] != model.X.shape[1]:
        raise ValueError(f"X_star must have shape (N*, {model.X.shape[1]}); received "
                         f"{X_star.shape}.")
    n_theta = as_int(n_theta, "n_theta", 1, 100_000)
    S, log_w = model.theta.shape[0], logsumexp(model.log_weights, axis=2)        # (n_out, S)
    w_theta = np.exp(log_w)
    if S <= n_theta:
        rows, weight = np.arange(S), w_theta
    else:
        avg = w_theta.mean(axis=0)
        cum = np.cumsum(avg)
        picks = np.searchsorted(cum, (np.arange(n_theta) + 0.5) / n_theta * cum[-1])
        rows, counts = np.unique(np.minimum(picks, S - 1), return_counts=True)
        weight = counts * w_theta[:, rows] / avg[rows]
    weight = weight / weight.sum(axis=1, keepdims=True)
    X_u, inverse = np.unique(X_star, axis=0, return_inverse=True)    # replicates once
    Ys = np.asarray(model.simulate(X_u, model.theta[rows]), dtype=np.float64)
    cache: dict = {}
    ks = np.arange(model.log_weights.shape[2])
    mean, var = np.empty((2, len(rows), X_u.shape[0], model.n_out))
    for i, j in enumerate(rows):
        lw = model.log_weights[:, j:j + 1] - np.where(                           # w_k | θ_j
            np.isfinite(log_w[:, j]), log_w[:, j], 0.0)[:, None, None]
        lw[~np.isfinite(log_w[:, j])] = 0.0       # an output where θ_j has no weight
        phi = np.stack([model._params(o, np.full_like(ks, j), ks, cache)   # one θ row at a time
                        for o in range(model.n_out)])[:, None]          # (n_out, 1, K, P)
        one = dataclasses.replace(model, theta=model.theta[j:j + 1], Y=model.Y[j:j + 1],
                                  _log_params=phi, log_weights=lw, phi_draws=None,
                                  simulate=lambda X, t, y=Ys[i:i + 1]: y)
        mean[i], var[i] = one.predict(X_u)[2:]
    mean, var = mean[:, inverse.reshape(-1)], var[:, inverse.reshape(-1)]
    total = np.einsum("oj,jno->no", weight, mean)
    between = np.einsum("oj,jno->no", weight, (mean - total) ** 2)
    within = np.einsum("oj,jno->no", weight, var)
    share = between.sum(axis=0) / np.maximum((between + within).sum(axis=0), 1e-300)
    return ThetaDeltaSplit(model.theta[rows], weight, mean, var, between, within, share)

