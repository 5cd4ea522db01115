"""Diagnostics of a history match and of a discrepancy model (docs/diagnostics.md).

- :func:`emulator_loo`, :func:`validate_waves`: leave-one-run-out (LOO) predictions of each
  wave's emulator in closed form, standardised errors and the runs it wrongly rules out.
- :func:`space_views`: the NROY share and the space removed per parameter after each wave,
  the lattice of 2-D projections (minimum implausibility, optical depth; Vernon et al.
  2010) and hits by wave.
- :func:`theta_delta_split`: δ(x) at θ from the final NROY set, and the share of δ's
  predictive variance that comes from θ (law of total variance).

Every function is pure and returns arrays ready to plot; only :func:`validate_waves` warns.
"""

from __future__ import annotations

import warnings
from typing import NamedTuple

import numpy as np
import scipy.stats
from scipy.special import logsumexp

from . import compiled, gp
from .exceptions import EmulatorWarning
from .history_matching import MULTIVARIATE, combine, implausibility
from .kernels import matern32, scaled_sq_dist
from .multivariate import EmulatorCov, implausibility_and_logdet
from .validation import as_float_array, as_int

__all__ = ["EmulatorLOO", "WaveValidation", "SpaceViews", "ThetaDeltaSplit", "emulator_loo",
           "loo_p_value", "validate_wave", "validate_waves", "space_views", "space_removed",
           "theta_delta_split", "theta_delta_message", "P_BEYOND_3", "TOO_CONFIDENT_P",
           "MOSTLY_THETA"]

#: P(|e| > 3) for a standard normal e: the share of LOO errors a calibrated emulator has.
P_BEYOND_3 = float(2.0 * scipy.stats.norm.sf(3.0))
#: A wave's errors are "clearly too large" when :func:`loo_p_value` is below this.
TOO_CONFIDENT_P = 1e-3
#: δ is "mostly a consequence of θ" above this share of its variance (between > within).
MOSTLY_THETA = 0.5
#: Candidates per block when :func:`space_views` scores later waves (bounds memory).
SCORE_BLOCK = 20_000
#: θ rows of :func:`theta_delta_split` (all of them when the model has fewer), and the
#: values it predicts per block of (θ, φ) pairs (bounds memory).
THETA_ROWS = 100
PAIR_VALUES = 2**20


def _blocks(n: int, size: int):
    for start in range(0, n, size):
        yield slice(start, min(n, start + size))


class EmulatorLOO(NamedTuple):
    """Leave-one-run-out predictions of an emulator at its R runs × N inputs (docs/diagnostics.md).

    Attributes
    ----------
    mean, var : ndarray of shape (R, N, n_out)
        LOO mean and latent variance (as :meth:`mdcore.emulator.Emulator.predict`) of run r
        from the other runs, same hyperparameters, linear mean refitted without run r.
    noise_var : ndarray of shape (n_out,)
        The emulator's σ_n², added to ``var`` to standardise the training values.
    error : ndarray of shape (R, N, n_out)
        Standardised errors ``(y − mean) / √(var + σ_n²)``, N(0, 1) for a calibrated emulator.
    s : ndarray of shape (R, n_out, N)
        LOO latent covariance of each run over the inputs, ``Q_x diag(s) Q_xᵀ`` per output.
    """

    mean: np.ndarray
    var: np.ndarray
    noise_var: np.ndarray
    error: np.ndarray
    s: np.ndarray


def emulator_loo(emulator) -> EmulatorLOO:
    """Leave out each simulator run (a θ with its N inputs) in turn, in closed form.

    The training covariance is ``K = σ_f² K_θ ⊗ K_x + σ_n² I``, so the block of ``K⁻¹`` of
    run r is ``C_r = Q_x diag(c_r) Q_xᵀ`` with ``c_r = (Q_θ²)_r W``, and (Dubrule 1983, by
    blocks) ``E[y_r | y_−r] = y_r − C_r⁻¹ (K⁻¹ (y − F β_−r))_r``,
    ``Cov[y_r | y_−r] = C_r⁻¹``, with β_−r the least-squares mean without run r (a rank-q
    downdate). Cost O(R² N + R N² + q R N (R + N)) per output, never (R N)³.

    Parameters
    ----------
    emulator : mdcore.emulator.Emulator
        With R ≥ 2 runs.

    Returns
    -------
    EmulatorLOO
    """
    em = emulator
    R, N, n_out = em.y_train.shape
    if R < 2:
        raise ValueError(f"leave-one-run-out needs at least 2 simulator runs; the emulator has "
                         f"{R}. Add runs (n_runs or initial_design).")
    lo, span = em.bounds[:, 0], em.bounds[:, 1] - em.bounds[:, 0]
    Xu, p = em.unit_x(em.X_train), em.theta_train.shape[1]
    F = np.concatenate([np.ones((R, N, 1)), np.broadcast_to(Xu, (R,) + Xu.shape),
                        np.broadcast_to(((em.theta_train - lo) / span)[:, None], (R, N, p))],
                       axis=2)                                                  # (R, N, q)
    FtF = np.einsum("rnq,rns->qs", F, F)
    down = np.linalg.pinv(FtF - np.einsum("rnq,rns->rqs", F, F))               # (R, q, q)
    out = np.empty((3, R, N, n_out))
    s, sn2 = np.empty((R, n_out, N)), np.empty(n_out)
    for o, g in enumerate(em.gps):
        y = em.y_train[..., o]
        Fty = np.einsum("rnq,rn->rq", F, y)
        beta = np.einsum("rqs,rs->rq", down, Fty.sum(axis=0) - Fty)             # β_−r

        def kinv(M, g=g):                   # K⁻¹ vec(M) for M (R, N), run-major
            return g.Q_t @ (g.W * (g.Q_t.T @ M @ g.Q_x)) @ g.Q_x.T

        KF = np.stack([kinv(F[..., j]) for j in range(F.shape[2])], axis=2)
        a = kinv(y - F @ g.beta) + np.einsum("rnq,rq->rn", KF, g.beta - beta)
        c = g.Q_t ** 2 @ g.W                                                     # (R, N)
        rot = a @ g.Q_x                                                          # Q_xᵀ (K⁻¹v)_r
        sn2[o] = np.exp(2.0 * g.log_params[-1])
        noisy = (1.0 / c) @ (g.Q_x ** 2).T
        out[0, ..., o] = y - (rot / c) @ g.Q_x.T
        out[1, ..., o] = np.maximum(noisy - sn2[o], 0.0)
        out[2, ..., o] = (y - out[0, ..., o]) / np.sqrt(noisy)
        s[:, o] = np.maximum(1.0 / c - sn2[o], 0.0)
    return EmulatorLOO(out[0], out[1], sn2, out[2], s)


class WaveValidation(NamedTuple):
    """LOO check of one wave's emulator (:func:`validate_wave`).

    Attributes
    ----------
    wave : int
    theta : ndarray of shape (R, p)
        The emulator's runs.
    loo : EmulatorLOO
    share_beyond_3 : float
        Share of ``loo.error`` beyond ±3 (about :data:`P_BEYOND_3` = 0.27 % if calibrated).
    p_value : float
        :func:`loo_p_value` of the errors.
    loo_implausibility, simulator_implausibility : ndarray of shape (R,)
        Each run's combined implausibility under the LOO emulator and under the simulator
        itself (emulator variance 0), by the wave's rule.
    wrongly_ruled_out : ndarray of bool, shape (R,)
        LOO implausibility above the cut-off, simulator's at or below it.
    cutoff : float
    advice : str or None
        What to do, when the share is too high (p < :data:`TOO_CONFIDENT_P`) or a run is
        wrongly ruled out.
    """

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

    @property
    def too_confident(self) -> bool:
        return self.p_value < TOO_CONFIDENT_P

    def as_dict(self) -> dict:
        """The summary for JSON (``reproduce --json``)."""
        return {"wave": self.wave, "runs": len(self.theta),
                "share_beyond_3": self.share_beyond_3, "p_value": self.p_value,
                "too_confident": self.too_confident,
                "max_abs_error": float(np.max(np.abs(self.loo.error))),
                "wrongly_ruled_out": int(np.count_nonzero(self.wrongly_ruled_out))}


def loo_p_value(error) -> float:
    """How unlikely a calibrated emulator's LOO errors ``error`` (R, N, n_out) are this large.

    The errors of one run are correlated over the N inputs, so the unit is a run and output:
    it fails when any of its N errors is beyond ±3, which for a calibrated emulator has
    probability at most ``q = min(1, N · 0.27 %)`` whatever the correlation (union bound).
    Returns the binomial tail ``P(X ≥ k)``, X ~ Bin(R n_out, q), k the failed units: an upper
    bound on the p-value.
    """
    R, N, n_out = error.shape
    k = int(np.count_nonzero(np.any(np.abs(error) > 3.0, axis=1)))
    return float(scipy.stats.binom.sf(k - 1, R * n_out, min(1.0, N * P_BEYOND_3)))


def validate_wave(wave, *, warn: bool = True) -> WaveValidation:
    """Check a :class:`~mdcore.history_matching.Wave`'s emulator by leaving out each run.

    Warns
    -----
    EmulatorWarning
        With ``warn``, naming the wave and what to do, when :attr:`WaveValidation.advice`.
    """
    em, problem = wave.emulator, wave.problem
    loo = emulator_loo(em)
    y = em.y_train
    if problem.rule == MULTIVARIATE:       # I_M² with the LOO covariance (docs/method.md §5)
        Xu, p = em.unit_x(em.X_train), em.theta_train.shape[1]
        prior = np.stack([np.exp(2 * g.log_params[0]) * np.einsum(
            "ib,ij,jb->b", g.Q_x, matern32(scaled_sq_dist(Xu, Xu, np.exp(g.log_params[1 + p:-1]))),
            g.Q_x) for g in em.gps])
        cov = EmulatorCov(loo.mean.transpose(0, 2, 1), np.stack([g.Q_x for g in em.gps]),
                          loo.s, prior)
        I_loo = implausibility_and_logdet(cov, problem.z, problem.V)[0]
        I_sim = implausibility_and_logdet(cov._replace(mean=y.transpose(0, 2, 1),
                                                       s=np.zeros_like(loo.s)),
                                          problem.z, problem.V)[0]
    else:
        def combined(mean, var):
            return combine(implausibility(problem.z, mean, var, V_o=problem.V_o,
                                          V_m=problem.V_m), problem.rule)
        I_loo, I_sim = combined(loo.mean, loo.var), combined(y, 0.0)
    cut = problem.cutoff
    wrong = (I_loo > cut) & (I_sim <= cut)
    share = float(np.mean(np.abs(loo.error) > 3.0))
    p_value = loo_p_value(loo.error)
    parts = []
    if p_value < TOO_CONFIDENT_P:
        parts.append(f"{100 * share:.1f} % of its leave-one-out standardised errors are "
                     f"beyond ±3 (a calibrated emulator: about 0.3 %; p ≤ {p_value:.1e}), so "
                     "it is too confident")
    if wrong.any():
        parts.append(f"{int(wrong.sum())} of its {len(wrong)} runs would be ruled out by "
                     "the emulator without that run although the simulator itself finds "
                     "them not implausible, so good θ may have been ruled out")
    advice = None if not parts else (
        f"wave {wave.index}: " + "; ".join(parts) + ". Add simulator runs (n_runs) so the "
        "emulator sees more of the space, raise V_m if the simulator itself is near the "
        "cut-off, or fit a different mean if the errors follow a trend.")
    if advice and warn:
        warnings.warn(advice, EmulatorWarning, stacklevel=2)
    return WaveValidation(wave.index, em.theta_train, loo, share, p_value, I_loo, I_sim, wrong,
                          cut, advice)


def validate_waves(hm, *, warn: bool = True) -> tuple[WaveValidation, ...]:
    """:func:`validate_wave` for every wave of a history match (one warning per bad wave)."""
    return tuple(validate_wave(w, warn=warn) for w in hm.waves)


def space_removed(samples, bounds, *, bins: int = 20) -> np.ndarray:
    """Share of each parameter's range that ``samples`` (K, p) do not fill, (p,).

    ``1 − exp(H_k) / width_k``, with H_k the entropy of the samples' marginal along
    parameter k (a histogram of ``bins`` bins over the box, Miller–Madow corrected): 0 when
    they fill the range evenly, ``1 − L / width`` when they fill an interval of length L
    evenly, 1 when there are none.
    """
    samples = np.atleast_2d(np.asarray(samples, dtype=np.float64))
    bounds = np.asarray(bounds, dtype=np.float64)
    if samples.shape[0] == 0:
        return np.ones(bounds.shape[0])
    u = (samples - bounds[:, 0]) / (bounds[:, 1] - bounds[:, 0])
    idx = np.clip((u * bins).astype(np.int64), 0, bins - 1)
    out = np.empty(bounds.shape[0])
    for k in range(bounds.shape[0]):
        q = np.bincount(idx[:, k], minlength=bins) / samples.shape[0]
        H = -np.sum(q[q > 0] * np.log(q[q > 0])) + (np.count_nonzero(q) - 1) / (
            2.0 * samples.shape[0])
        out[k] = 1.0 - min(np.exp(H) / bins, 1.0)
    return out


class SpaceViews(NamedTuple):
    """What each wave ruled out, on wave 1's candidates (uniform in the box), for plotting.

    Attributes
    ----------
    nroy_fraction : ndarray of shape (W,)
    space_removed : ndarray of shape (W, p)
        :func:`space_removed` of each wave's NROY samples.
    edges : ndarray of shape (p, bins + 1)
        Bin edges along each parameter, its units.
    pairs : int ndarray of shape (p (p − 1) / 2, 2)
        The lattice's panels (k, l), k < l.
    min_implausibility, optical_depth : ndarray of shape (n_pairs, bins, bins)
        Per bin [i along k, j along l] the smallest :attr:`implausibility` behind it, and
        the share of its points not ruled out (Vernon et al. 2010); NaN where no point falls.
    min_implausibility_1d, optical_depth_1d : ndarray of shape (p, bins)
        The same along each parameter (the lattice's diagonal).
    theta : ndarray of shape (M, p)
        The points: wave 1's candidates.
    implausibility : ndarray of shape (M,)
        Largest implausibility over the waves up to the one that ruled the point out (a
        later wave's emulator is fitted inside the earlier NROY set only).
    ruled_out_by : int ndarray of shape (M,)
        The wave that ruled each point out, 0 for none (hits by wave).
    hits : int ndarray of shape (W,)
        Points ruled out by each wave.
    cutoff : float
    """

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
    """The space views of a history match's first ``waves`` waves (default all).

    Wave 1's own scores are reused; each later wave scores only the points that survived
    the waves before it, in blocks of :data:`SCORE_BLOCK`, and the bins are filled with
    ``bincount`` and ``minimum.at``: memory O(M + p² bins²).
    """
    bins = as_int(bins, "bins", 2, 200)
    n_w = len(hm.waves) if waves is None else as_int(waves, "waves", 1, len(hm.waves))
    chosen, cut, b = hm.waves[:n_w], hm.problem.cutoff, hm.problem.bounds
    theta = chosen[0].candidates
    I = chosen[0].candidate_implausibility.copy()
    by = np.where(I > cut, 1, 0)
    for w in chosen[1:]:
        alive = np.flatnonzero(by == 0)
        for start in range(0, alive.size, SCORE_BLOCK):
            rows = alive[start:start + SCORE_BLOCK]
            Iw = w.implausibility(theta[rows])
            I[rows] = np.maximum(I[rows], Iw)
            by[rows[Iw > cut]] = w.index
    idx = np.clip(((theta - b[:, 0]) / (b[:, 1] - b[:, 0]) * bins).astype(np.int32), 0,
                  bins - 1)
    ok = (by == 0).astype(np.float64)

    def binned(cells, n, size):
        """Smallest I and share not ruled out per cell, (2, n, size); ``cells`` yields n
        arrays of cell indices (M,), one at a time."""
        out = np.empty((2, n, size))
        for c, cell in enumerate(cells):
            n = np.bincount(cell, minlength=size).astype(np.float64)
            low = np.full(size, np.inf)
            np.minimum.at(low, cell, I)
            with np.errstate(invalid="ignore"):
                out[:, c] = np.where(n > 0, low, np.nan), np.bincount(cell, ok, size) / n
        return out

    p = b.shape[0]
    pairs = np.array([(k, l) for k in range(p) for l in range(k + 1, p)], dtype=np.int64
                     ).reshape(-1, 2)
    two = binned((idx[:, k] * bins + idx[:, l] for k, l in pairs), len(pairs), bins * bins)
    one = binned(iter(idx.T), p, bins)
    two = two.reshape(2, len(pairs), bins, bins)
    return SpaceViews(np.array(hm.nroy_fraction[:n_w]),
                      np.array([space_removed(w.nroy, b, bins=bins) for w in chosen]),
                      np.linspace(b[:, 0], b[:, 1], bins + 1).T, pairs, two[0], two[1],
                      one[0], one[1], theta, I, by, np.bincount(by, minlength=n_w + 1)[1:],
                      float(cut))


class ThetaDeltaSplit(NamedTuple):
    """δ at J θ of a discrepancy mixture, split by the law of total variance.

    Attributes
    ----------
    theta : ndarray of shape (J, p)
    weight : ndarray of shape (n_out, J)
        Each θ's weight in the mixture (per output; sums to 1).
    mean, var : ndarray of shape (J, N*, n_out)
        ``E[δ | θ_j]`` and ``Var[δ | θ_j]`` (over φ and the GP).
    between : ndarray of shape (N*, n_out)
        ``Var_θ(E[δ | θ])``: the spread of δ across θ.
    within : ndarray of shape (N*, n_out)
        ``E_θ Var(δ | θ)``: the spread within each θ; ``between + within = Var(δ)``.
    share : ndarray of shape (n_out,)
        ``Σ_x between / Σ_x (between + within)`` over the prediction inputs.
    """

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
        """The summary for JSON (lists per output)."""
        return {"share": self.share.tolist(), "mostly_theta": self.mostly_theta.tolist(),
                "between": self.between.mean(axis=0).tolist(),
                "within": self.within.mean(axis=0).tolist(), "n_theta": len(self.theta)}


def theta_delta_split(model, X_star, *, n_theta: int = THETA_ROWS) -> ThetaDeltaSplit:
    """Split δ's predictive variance at ``X_star`` (N*, d_x) into θ's part and the rest.

    Per θ^(j), ``E[δ | θ_j]`` and ``Var[δ | θ_j]`` are the moments of its φ components
    (Eq. 15 within θ_j; components below ``model.prune × max`` skipped). With more than
    ``n_theta`` θ, J ≤ ``n_theta`` of them are taken by systematic resampling on the θ
    weights averaged over outputs (offset ½, so no seed) and reweighted per output: the
    share is then an estimate (docs/diagnostics.md §3). Scenario 1 (one θ) gives 0.

    Parameters
    ----------
    model : mdcore.discrepancy.DiscrepancyModel
    X_star : ndarray of shape (N*, d_x)
    n_theta : int, default=100

    Returns
    -------
    ThetaDeltaSplit
    """
    X_star = as_float_array(X_star, "X_star", ndim=2)
    if X_star.shape[1] != model.X.shape[1]:
        raise ValueError(f"X_star must have shape (N*, {model.X.shape[1]}); received "
                         f"{X_star.shape}.")
    n_out, S, K = model.log_weights.shape
    n_theta = as_int(n_theta, "n_theta", 1, 100_000)
    w_theta = np.exp(logsumexp(model.log_weights, axis=2))                     # (n_out, S)
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
    inverse = inverse.reshape(-1)
    Ys = np.asarray(model.simulate(X_u, model.theta[rows]), dtype=np.float64)   # (J, M, n_out)
    Y, J, M = model.Y[rows], len(rows), X_u.shape[0]
    cache: dict = {}
    phi = [None if model.phi_draws is None else model.phi_draws.between(j, j + 1, cache)[0]
           for j in rows]
    mean, var = np.empty((2, J, M, n_out))
    for o in range(n_out):
        lw = model.log_weights[o, rows]                                          # (J, K)
        lw = lw - logsumexp(lw, axis=1, keepdims=True)                           # w_k | θ_j
        keep = np.isfinite(lw) & (lw >= lw.max(axis=1, keepdims=True)
                                  + np.log(max(model.prune, 1e-300)))
        params = [model.log_params[o, j] if f is None else f for j, f in zip(rows, phi)]
        # sums about the heaviest component of each row, as DiscrepancyModel.predict
        heavy = np.stack([q[k] for q, k in zip(params, lw.argmax(axis=1))])
        ref = gp.predict(heavy, Y, model.X, model.z[:, o], Ys, X_u).mean          # (J, M)
        centre = ref - Ys[..., o]
        s1, s2 = np.zeros((2, J, M))
        if model.backend == "numba" and K > 1:      # a compiled call per θ (scenario 3)
            for i in range(J):
                acc, _ = compiled.mixture_sums(
                    compiled.Pairs(params[i][keep[i]], np.zeros(keep[i].sum(), np.int64),
                                   Y[i:i + 1], model.X, model.z[:, o]),
                    compiled.Test(Ys[i:i + 1], Ys[i:i + 1, :, o], X_u,
                                  np.exp(lw[i, keep[i]]), np.stack([ref[i], centre[i]])))
                s1[i], s2[i] = acc[1], acc[3]
        else:
            ii, kk = np.nonzero(keep)
            lp = np.concatenate([q[k] for q, k in zip(params, keep)])
            for sl in _blocks(ii.size, max(1, PAIR_VALUES // M)):
                pred = gp.predict(lp[sl], Y[ii[sl]], model.X, model.z[:, o], Ys[ii[sl]], X_u)
                dd = pred.mean - Ys[ii[sl], :, o] - centre[ii[sl]]
                w = np.where(np.all(np.isfinite(dd) & np.isfinite(pred.var), axis=1),
                             np.exp(lw[ii[sl], kk[sl]]), 0.0)[:, None]    # dropped: 0
                np.add.at(s1, ii[sl], np.where(w > 0, w * dd, 0.0))
                np.add.at(s2, ii[sl], np.where(w > 0, w * (pred.var + dd * dd), 0.0))
        mean[..., o] = centre + s1
        var[..., o] = np.maximum(s2 - s1 * s1, 0.0)
    mean, var = mean[:, inverse], var[:, inverse]
    total = np.einsum("oj,jno->no", weight, mean)
    between = np.einsum("oj,jno->no", weight, (mean - total) ** 2)
    within = np.einsum("oj,jno->no", weight, var)
    share = between.sum(axis=0) / np.maximum((between + within).sum(axis=0), 1e-300)
    return ThetaDeltaSplit(model.theta[rows], weight, mean, var, between, within, share)


def theta_delta_message(label: str, output: str, share: float) -> str | None:
    """The plain-words warning of a method's output when δ is mostly θ's, else None."""
    if not share > MOSTLY_THETA:
        return None
    return (f"{label}, {output}: {100 * share:.0f} % of δ's predictive variance comes from "
            "which θ in the NROY set is used (δ varies more across θ than at one θ). This δ "
            "is mostly a consequence of the θ chosen, not physics: narrow θ first (data that "
            "tell the parameters apart, or a smaller V_m if you can justify one) before "
            "reading its shape.")
