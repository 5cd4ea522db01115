"""Scenario 3's adaptive prediction from PREDICT_DRAWS pairs drawn by weight, against the full
mixture: the stated error bound (docs/scenario3.md), and metrics against their spread over
seeds. The app's sizes (N_s = 100, N_φ = 50) on the beams; shear-5 predicts at 3 inputs, so
from 10 × PREDICT_DRAWS pairs: N_φ = 500 there, for more pairs than that."""

import warnings

import numpy as np
import pytest

from mdcore import _cases as cases
from mdcore import _gp as gp
from mdcore._discrepancy import (
    PREDICT_DRAWS,
    PREDICT_WORK,
    DiscrepancyOptions,
    infer_discrepancy,
)
from mdcore._history_matching import history_match_case
from mdcore._pipeline import scores

CASES = ("beam-1d", "beam-2d", "shear-5")
N_PHI = {"beam-1d": 50, "beam-2d": 50, "shear-5": 500}


def fitted(name, seed):
    case = cases.load(name, seed=seed)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        hm = history_match_case(case, seed=seed, n_candidates=5000)
        model = infer_discrepancy(case.simulate, hm.posterior_samples(100, seed=seed),
                                  case.X_train, case.z_train, scenario=3, seed=seed,
                                  options=DiscrepancyOptions(n_phi=N_PHI[name],
                                                             phi_prior=case.phi_prior))
    assert model.proposal == "adaptive" and model.draw_seed is not None
    return case, model


def components(model, case, o, Xs):
    """Every pair's predictive mean, latent variance and noise variance of output ``o`` at
    ``Xs`` by :func:`mdcore.gp.predict` (one pair at a time in blocks), its simulator output
    y* there, and its weight."""
    S, K = model.log_weights.shape[1:]
    j, k = np.divmod(np.arange(S * K), K)
    Ys = case.simulate(Xs, model.theta)
    mean, var, noise = [], [], []
    for b in range(0, S * K, 500):
        sl = slice(b, b + 500)
        p = gp.predict(model.log_params[o][j[sl], k[sl]], model.Y[j[sl]], model.X,
                       model.z[:, o], Ys[j[sl]], Xs)
        mean.append(p.mean)
        var.append(p.var)
        noise.append(np.broadcast_to(p.noise_var[:, None], p.var.shape))
    return (np.concatenate(mean), np.concatenate(var), np.concatenate(noise), Ys[j, :, o],
            model.weights[o].ravel())


@pytest.mark.parametrize("name", CASES)
def test_resampled_moments_are_within_the_stated_bound(name):
    """Each field f of the mixture (z and δ means; z and δ variances, Eq. 15) is a weighted
    mean Σ w c over pairs. Drawing n ≥ PREDICT_DRAWS pairs by weight estimates it with an
    error whose sd is at most sqrt(Var_w(c) / n) (stratified draws: no more than
    multinomial). For the means Var_w(c) ≤ the predictive variance, so the error's sd is
    at most 1/√n ≤ 2.2 % of the predictive sd: the rms over test inputs must stay within
    it, and every input within 4.5 of its own bound."""
    case, model = fitted(name, 8)
    Xs = np.unique(case.X_test, axis=0)[::8]
    full = model.predict(Xs, prune=0.0)
    res = model.predict(Xs)
    n = min(max(PREDICT_DRAWS, PREDICT_WORK // len(Xs)), 10 * PREDICT_DRAWS)
    for o in range(model.n_out):
        m, v, s2, ystar, w = components(model, case, o, Xs)
        d = m - ystar
        mz, md = w @ m, w @ d
        cz, cd = v + s2 + (m - mz) ** 2, v + (d - md) ** 2
        # the naive loop is the reference: the full mixture of predict() agrees with it
        np.testing.assert_allclose(full.z_mean[:, o], mz, rtol=1e-8, atol=1e-10)
        np.testing.assert_allclose(full.delta_var[:, o], w @ cd, rtol=1e-6)
        for est, ref, c in ((res.z_mean, mz, m), (res.delta_mean, md, d),
                            (res.z_var, w @ cz, cz), (res.delta_var, w @ cd, cd)):
            bound = np.sqrt((w @ (c - w @ c) ** 2) / n)
            assert np.all(np.abs(est[:, o] - ref) <= 4.5 * bound + 1e-12), name
        for est, ref, var in ((res.z_mean, mz, w @ cz), (res.delta_mean, md, w @ cd)):
            rms = np.sqrt(np.mean((est[:, o] - ref) ** 2 / var))
            assert rms <= 1 / np.sqrt(n), (name, o, rms)


@pytest.mark.parametrize("name", CASES)
def test_resampling_moves_metrics_less_than_the_seeds_do(name):
    """Over five seeds, each metric (NMSE z, RMSE δ, mean δ band sd, LPL) of the resampled
    prediction differs from the full mixture's by less than the full mixture's sd over the
    seeds, on every seed. Not LPL on shear-5: its data are one fixed set, so its spread
    over seeds is the importance sampling's alone (an ESS of ~30,000 pairs), which draws
    far fewer than the ESS cannot match; the LPL there moved by up to 1.4 sd (8 sd for one
    mode), by the z variance's sampling error (docs/scenario3.md)."""
    full, res = [], []
    for seed in range(5):
        case, model = fitted(name, seed)
        for out, kw in ((full, {"prune": 0.0}), (res, {})):
            m = scores(case, model.predict(case.X_test, **kw))
            out.append([np.mean(m.nmse_z), np.mean(m.rmse_delta), np.mean(m.sd_delta)]
                       + ([np.mean(m.lpl)] if name != "shear-5" else []))
    full, res = np.array(full), np.array(res)
    spread = full.std(axis=0, ddof=1)
    assert np.all(np.abs(res - full) < spread), (name, np.abs(res - full) / spread)
