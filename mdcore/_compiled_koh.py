"""Numba kernel of the Kennedy–O'Hagan likelihood step behind :mod:`mdcore.compiled`.

Imported lazily (needs numba); nothing here validates input. One call evaluates, for one θ,

    Σ_o log N(z_o | m_η(X, θ), Σ_η(X, X; θ) + K_δ,o + σ_n,o² I)          (SPEC §7)

from the fixed pieces of an :class:`mdcore.emulator.EmulatorAt` (its docstring has the
algebra): ``k_θ = m32(θ, Θ_train)``, ``d(θ) = (k_θ Q_θ)² W``, the mean
``lin + βᵀθ + k_θ A K_xᵀ`` and the covariance ``(prior + B) − σ_f⁴ V diag(d) Vᵀ``, then a
Cholesky with the SPEC §3 jitter ladder, one triangular solve and the log-determinant. It
computes what :func:`mdcore.koh.gaussian_log_likelihood` computes on
``EmulatorAt.moments_at(theta_terms(θ))``, in a few small buffers instead of about twenty
NumPy calls: a KOH chain step costs microseconds instead of a fraction of a millisecond.
:func:`chain_steps` runs stretches of :func:`mdcore.mcmc.adaptive_metropolis` around it, so
that the chain's own bookkeeping (the proposal, Welford's sums, the proposal's factor) does
not cost a Python loop's ~60 µs per step either.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

SQRT3 = math.sqrt(3.0)
LOG_2PI = math.log(2.0 * math.pi)


@njit(cache=True, nogil=True)
def _cholesky(C, L, n, jitter):
    """Lower Cholesky factor of ``C + jitter I`` (lower triangle of C read) into L.

    Returns False when a pivot is not positive (or not finite)."""
    for j in range(n):
        s = C[j, j] + jitter
        for k in range(j):
            s -= L[j, k] * L[j, k]
        if not s > 0.0 or not math.isfinite(s):
            return False
        ljj = math.sqrt(s)
        L[j, j] = ljj
        for i in range(j + 1, n):
            t = C[i, j]
            for k in range(j):
                t -= L[i, k] * L[j, k]
            L[i, j] = t / ljj
    return True


@njit(cache=True, nogil=True)
def log_likelihood(theta_unit, T_train, inv_ell, Q_t, W, lin, beta_t, AK, V, sf4, base, zT,
                   ladder, stats):
    """KOH log likelihood at one θ; ``-inf`` if a covariance fails the jitter ladder.

    Parameters (float64, C-contiguous)
    ----------
    theta_unit : (p,)             θ scaled to the emulator's unit box
    T_train : (R, p)              the emulator's training θ, unit box
    inv_ell : (n_out, p)          1 / ℓ_θ per output
    Q_t : (n_out, R, R)           eigenvectors of K_θ
    W : (n_out, R, N_t)           1 / (σ_f² λ_a μ_b + σ_n²)
    lin : (n_out, N)              β₀ + β_xᵀ x at the observed inputs
    beta_t : (n_out, p)           β_θ
    AK : (n_out, R, N)            A m32(X, X_train)ᵀ
    V : (n_out, N, N_t)           m32(X, X_train) Q_x
    sf4 : (n_out,)                σ_f⁴ of the emulator
    base : (n_out, N, N)          σ_f² m32(X, X) + K_δ + σ_n² I (the fixed part)
    zT : (n_out, N)               observations
    ladder : (J,)                 relative jitter steps (× mean diagonal)
    stats : (3,), updated          [matrices jittered, matrices failed, largest jitter used]
    """
    n_out, R, p = inv_ell.shape[0], T_train.shape[0], T_train.shape[1]
    N, N_t = lin.shape[1], W.shape[2]
    kt, a, d = np.empty(R), np.empty(R), np.empty(N_t)
    r, vd = np.empty(N), np.empty(N_t)
    C, L = np.empty((N, N)), np.empty((N, N))
    total = 0.0
    for o in range(n_out):
        for i in range(R):                               # k_θ = m32(θ, Θ_train)
            s = 0.0
            for k in range(p):
                t = (theta_unit[k] - T_train[i, k]) * inv_ell[o, k]
                s += t * t
            q = SQRT3 * math.sqrt(s)
            kt[i] = (1.0 + q) * math.exp(-q)
        for j in range(R):                               # a = k_θ Q_θ
            s = 0.0
            for i in range(R):
                s += kt[i] * Q_t[o, i, j]
            a[j] = s * s
        for m in range(N_t):                             # d = a² W
            s = 0.0
            for j in range(R):
                s += a[j] * W[o, j, m]
            d[m] = s
        lin_t = 0.0
        for k in range(p):
            lin_t += theta_unit[k] * beta_t[o, k]
        for n in range(N):                               # residual z − m_η(X, θ)
            s = lin[o, n] + lin_t
            for i in range(R):
                s += kt[i] * AK[o, i, n]
            r[n] = zT[o, n] - s
        mean_diag = 0.0
        for n in range(N):                               # base − σ_f⁴ V diag(d) Vᵀ (lower)
            for m in range(N_t):
                vd[m] = V[o, n, m] * d[m]
            for c in range(n + 1):
                s = 0.0
                for m in range(N_t):
                    s += vd[m] * V[o, c, m]
                C[n, c] = base[o, n, c] - sf4[o] * s
            mean_diag += C[n, n]
        mean_diag /= N
        ok = _cholesky(C, L, N, 0.0)
        if not ok:                                       # SPEC §3 jitter ladder
            for jit in ladder:
                ok = _cholesky(C, L, N, jit * mean_diag)
                if ok:
                    stats[0] += 1.0
                    stats[2] = max(stats[2], jit)
                    break
            if not ok:
                stats[1] += 1.0
                total = -np.inf
                continue
        quad, logdet = 0.0, 0.0
        for i in range(N):                               # L⁻¹ r, in place
            s = r[i]
            for k in range(i):
                s -= L[i, k] * r[k]
            r[i] = s / L[i, i]
            quad += r[i] * r[i]
            logdet += math.log(L[i, i])
        total += -0.5 * quad - logdet - 0.5 * N * LOG_2PI
    return total if math.isfinite(total) else -np.inf


@njit(cache=True, nogil=True)
def target(u, mu, sd, lo_u, hi_u, lo, span, theta_unit, T_train, inv_ell, Q_t, W, lin,
            beta_t, AK, V, sf4, base, zT, ladder, stats):
    """The KOH log target of :func:`mdcore.koh.infer_koh` in standardised coordinates
    ``u = (θ − μ) / sd``: ``-inf`` outside the box, else :func:`log_likelihood` at
    ``θ = μ + sd u`` minus ``½ uᵀu`` (the N(0, I) prior), in the NumPy path's operations."""
    d = u.size
    for k in range(d):
        if u[k] < lo_u[k] or u[k] > hi_u[k]:
            return -np.inf
    for k in range(d):
        theta_unit[k] = ((mu[k] + sd[k] * u[k]) - lo[k]) / span[k]
    value = log_likelihood(theta_unit, T_train, inv_ell, Q_t, W, lin, beta_t, AK, V, sf4,
                           base, zT, ladder, stats)
    uu = u[0] * u[0]
    for k in range(1, d):
        uu += u[k] * u[k]
    return value - 0.5 * uu


@njit(cache=True, nogil=True)
def _proposal_factor(m2, t, s_d, reg, L, M):
    """``L = chol(s_d m2 / t + reg)`` (lower triangle read, as LAPACK's ``potrf``); L is
    left as it was when a pivot is not positive (:func:`mdcore.mcmc.adaptive_metropolis`
    keeps the previous proposal). ``M`` is scratch of L's shape."""
    d = L.shape[0]
    for j in range(d):
        s = s_d * m2[j, j] / t + reg[j, j]
        for k in range(j):
            s -= M[j, k] * M[j, k]
        if not s > 0.0:
            return
        M[j, j] = math.sqrt(s)
        inv = 1.0 / M[j, j]
        for i in range(j + 1, d):
            v = s_d * m2[i, j] / t + reg[i, j]
            for k in range(j):
                v -= M[i, k] * M[j, k]
            M[i, j] = v * inv
    for i in range(d):
        for j in range(d):
            L[i, j] = M[i, j] if j <= i else 0.0


@njit(cache=True, nogil=True)
def chain_steps(t_start, t_stop, x, lp, mean, m2, L, burn_in, t0, s_d, reg, steps, log_u,
                samples, log_p, accepted, mu, sd, lo_u, hi_u, lo, span, T_train, inv_ell,
                Q_t, W, lin, beta_t, AK, V, sf4, base, zT, ladder, stats):
    """Steps ``t_start ≤ t < t_stop`` of :func:`mdcore.mcmc.adaptive_metropolis` on the KOH
    target (:func:`target`), the state updated in place; returns the new log target.

    ``steps[t − t_start]`` and ``log_u[t − t_start]`` are the step's standard normal draw
    and log uniform; ``x, mean, m2, L`` the chain state, the Welford sums and the proposal
    factor; ``samples, log_p, accepted`` the outputs. Every operation is the Python loop's
    in the same order, except ``L @ s`` (BLAS, which may fuse multiply-adds) and, for
    d ≥ 3, LAPACK's factorisation: those agree to the last bit or two.
    """
    d = x.size
    y = np.empty(d)
    delta = np.empty(d)
    M = np.zeros((d, d))
    theta_unit = np.empty(d)
    for t in range(t_start, t_stop):
        i = t - t_start
        s = steps[i]
        for a in range(d):                               # y = x + L s
            acc = L[a, 0] * s[0]
            for b in range(1, d):
                acc += L[a, b] * s[b]
            y[a] = x[a] + acc
        lq = target(y, mu, sd, lo_u, hi_u, lo, span, theta_unit, T_train, inv_ell, Q_t, W,
                    lin, beta_t, AK, V, sf4, base, zT, ladder, stats)
        if lq - lp > log_u[i]:                           # NaN and -inf are rejected
            for a in range(d):
                x[a] = y[a]
            lp = lq
            accepted[1 if t > burn_in else 0] += 1
        if t > burn_in:
            for a in range(d):
                samples[t - burn_in - 1, a] = x[a]
            log_p[t - burn_in - 1] = lp
        for a in range(d):                               # Welford, with x_t
            delta[a] = x[a] - mean[a]
        for a in range(d):
            mean[a] = mean[a] + delta[a] / (t + 1)
        for a in range(d):
            for b in range(d):
                m2[a, b] += delta[a] * (x[b] - mean[b])
        if t >= t0:
            _proposal_factor(m2, t, s_d, reg, L, M)
    return lp
