"""Numba kernels behind :mod:`mdcore._compiled`: :func:`pair_range` (scenario 3's pairs)
and :func:`koh_steps` (the KOH chain), serial with the GIL released, on C-contiguous arrays
in NamedTuples (one signature each). The Matérn 3/2 kernel (Eq. 3) is :func:`_matern_parts`;
hot loops are flat loops over contiguous arrays, which LLVM vectorises.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

SQRT3 = math.sqrt(3.0)
LOG_2PI = math.log(2.0 * math.pi)
#: Modes of :func:`pair_range`.
NLML, MIXTURE = 0, 1
# exp(x) = 2^k exp(r): fdlibm's split of ln 2 (k · _LN2_HI is exact), the round-to-nearest
# shift 1.5 · 2^52, and the Taylor coefficients 1/i! of exp(r), |r| ≤ ln2/2.
_LN2_HI, _LN2_LO = 6.93147180369123816490e-01, 1.90821492927058770002e-10
_INV_LN2, _SHIFT = 1.44269504088896338700e+00, 6755399441055744.0
_C3, _C4, _C5, _C6, _C7, _C8, _C9, _C10, _C11, _C12, _C13 = (
    1.0 / math.factorial(i) for i in range(3, 14))

# IEEE semantics (no fast-math), the GIL released, and NumPy's error model (x/0 is inf);
# helpers are called from kernels only, so they need no Python entry point (less to compile).
_OPTIONS: dict = dict(cache=True, nogil=True, error_model="numpy")
_kernel = njit(**_OPTIONS)
_jit = njit(**{**_OPTIONS, "no_cpython_wrapper": True})
# A helper with one caller is typed into it: one compilation instead of two.
_inline = njit(**{**_OPTIONS, "no_cpython_wrapper": True, "inline": "always"})


@_jit
def _matern_parts(a, b, log_sf2):
    """``σ_f² m32(r_y) m32(r_x)`` (Eq. 3) from ``a = √3 r_y``, ``b = √3 r_x`` as
    ``q · exp(e)``: ``q = (1 + a)(1 + b)``, ``e = log σ_f² − a − b`` (one exponential).
    With ``b = log_sf2 = 0`` it is ``m32(r_y)`` alone."""
    s = a + b
    return a * b + s + 1.0, log_sf2 - s


@_jit
def _matern_flat(DY, DX, sy, sx, log_sf2, out, work):
    """Eq. 3 for entries whose squared input differences are ``DY`` (d_y, n) and ``DX``
    (d_x, n) per dimension, with ``sy``, ``sx`` = √3/ℓ: into ``out`` (n,). ``work`` is
    ``(a, b, bits)`` scratch at least n long.

    exp is branch-free (the C library's is a call LLVM cannot vectorise): ``exp(x) =
    2^k exp(r)``, ``k = round(x / ln 2)``, ``r = x − k ln 2`` (ln 2 in two parts, so ``r``
    is exact to rounding), ``exp(r)`` by its degree-13 Taylor polynomial (truncation below
    1e-17) and ``2^k`` from exponent bits: within about 1 ulp. Below −708 it gives
    ``exp(−708)``, zero next to any covariance entry it enters.
    """
    n = out.size
    a, b, bits = work[0][:n], work[1][:n], work[2][:n]
    for t in range(n):
        a[t] = 0.0
        b[t] = 0.0
    for k in range(sy.size):                          # squared scaled distances
        c, row = sy[k] * sy[k], DY[k]
        for t in range(n):
            a[t] += row[t] * c
    for k in range(sx.size):
        c, row = sx[k] * sx[k], DX[k]
        for t in range(n):
            b[t] += row[t] * c
    for t in range(n):
        q, e = _matern_parts(math.sqrt(a[t]), math.sqrt(b[t]), log_sf2)
        x = e if e > -708.0 else -708.0
        k = (x * _INV_LN2 + _SHIFT) - _SHIFT          # round to nearest
        r = (x - k * _LN2_HI) - k * _LN2_LO
        p = ((((_C13 * r + _C12) * r + _C11) * r + _C10) * r + _C9) * r + _C8
        p = (((((((p * r + _C7) * r + _C6) * r + _C5) * r + _C4) * r + _C3) * r + 0.5) * r
             + 1.0) * r + 1.0
        out[t] = q * p
        bits[t] = (np.int64(k) + 1023) << 52          # the bits of 2^k
    scale = bits.view(np.float64)
    for t in range(n):
        out[t] *= scale[t]


@_jit
def _sq_diffs(A, B, out):
    """Squared differences per dimension between the rows of ``A`` (N, d) and ``B`` (M, d),
    into ``out`` (d, ·): all N·M pairs by rows, or, when ``out`` has N(N+1)/2 columns and
    ``B`` is ``A``, the packed upper triangle ``i ≤ j``."""
    N, d = A.shape
    packed = out.shape[1] != N * B.shape[0]
    for k in range(d):
        p = 0
        for i in range(N):
            for j in range(i if packed else 0, B.shape[0]):
                diff = A[i, k] - B[j, k]
                out[k, p] = diff * diff
                p += 1


@_jit
def _factor(A, R, n, ladder):
    """``RᵀR = A[:, :n] + jitter I`` for the upper triangle of ``A`` (n, n + c) stored by
    rows, row by row; the c extra columns B are carried along, so ``R[:, n:] = R⁻ᵀ B``
    (``L⁻¹ B``). Every update is a contiguous row operation (it vectorises), four rows
    above at a time (so row j is loaded and stored once per four updates, the bound on
    this loop). When a pivot is not positive,
    ``ladder[t] × mean(diag A)`` is added to the diagonal, step by step. Returns
    ``(ok, step)``: the step that worked (0 without jitter), or the last tried."""
    scale = 0.0
    for i in range(n):
        scale += A[i, i]
    scale /= n
    step = 0.0
    for s in range(-1, ladder.size):                 # s = −1: no jitter
        step = 0.0 if s < 0 else ladder[s]
        ok = True
        for j in range(n):
            m = A.shape[1] - j
            rj, aj = R[j, j:], A[j, j:]
            for t in range(m):
                rj[t] = aj[t]
            rj[0] += step * scale
            k = 0
            while k + 4 <= j:
                r0, r1, r2, r3 = R[k, j:], R[k + 1, j:], R[k + 2, j:], R[k + 3, j:]
                l0, l1, l2, l3 = r0[0], r1[0], r2[0], r3[0]
                for t in range(m):
                    rj[t] -= (l0 * r0[t] + l1 * r1[t]) + (l2 * r2[t] + l3 * r3[t])
                k += 4
            for i in range(k, j):
                rk = R[i, j:]
                lk = rk[0]
                for t in range(m):
                    rj[t] -= lk * rk[t]
            if not rj[0] > 0.0:                      # also NaN
                ok = False
                break
            d = math.sqrt(rj[0])
            rj[0] = d
            for t in range(1, m):
                rj[t] /= d
        if ok:
            return True, step
    return False, step


@_jit
def _log_density(R, n, c):
    """``−½ bᵀA⁻¹b − ½ log det A`` for the extra column ``b = A[:, n + c]``, from the
    factor of :func:`_factor` (Eq. 9 without its constant)."""
    ww = 0.0
    logdet = 0.0
    for i in range(n):
        ww += R[i, n + c] * R[i, n + c]
        logdet += math.log(R[i, i])
    return -0.5 * ww - logdet


# ---------------------------------------------------------------------------------------
# Scenario 3's pairs


@_kernel
def pair_range(mode, b0, b1, pairs, test, ladder, out, acc):
    """Pairs ``b0 ≤ b < b1``: the NLML (Eq. 9) of ``(pairs.theta[b], pairs.Y[pairs.row[b]])``
    for every column of ``pairs.z`` (one factorisation) into ``out``
    (:class:`mdcore._compiled.PairOut`), and in :data:`MIXTURE` mode the sums of
    :func:`mdcore._compiled.mixture_sums` into ``acc`` (4, M). Pairs of one row of Y should
    follow each other: their differences are computed once."""
    theta, row, Y, X, z = pairs
    N, d_x = X.shape
    d_y, n_z = Y.shape[2], z.shape[1]
    M = test.X_star.shape[0] if mode == MIXTURE else 0
    T = N * (N + 1) // 2
    DX, DY = np.empty((d_x, T)), np.empty((d_y, T))      # training, packed
    DXc, DYc = np.empty((d_x, N * M)), np.empty((d_y, N * M))   # training × test
    _sq_diffs(X, X, DX)
    _sq_diffs(X, test.X_star[:M], DXc)
    A, R = np.empty((N, N + n_z)), np.empty((N, N + n_z))
    entries, V = np.empty(T), np.empty((N, M))
    mean, ss = np.empty(M), np.empty(M)
    sy, sx = np.empty(d_y), np.empty(d_x)
    n_work = T if T > N * M else N * M
    work = (np.empty(n_work), np.empty(n_work), np.empty(n_work, np.int64))
    last = -1
    for b in range(b0, b1):
        th = theta[b]
        if row[b] != last:
            last = row[b]
            _sq_diffs(Y[last], Y[last], DY)
            if mode == MIXTURE:
                _sq_diffs(Y[last], test.Y_star[last], DYc)
        for k in range(d_y):
            sy[k] = SQRT3 * math.exp(-th[1 + k])
        for k in range(d_x):
            sx[k] = SQRT3 * math.exp(-th[1 + d_y + k])
        log_sf2, log_sn = 2.0 * th[0], th[th.size - 1]
        _matern_flat(DY, DX, sy, sx, log_sf2, entries, work)
        p = 0
        for i in range(N):                           # [K_ff + σ_n² I | z] by rows
            Ai = A[i, i:N]
            for t in range(N - i):
                Ai[t] = entries[p + t]
            p += N - i
            A[i, i] += math.exp(2.0 * log_sn)
            for c in range(n_z):
                A[i, N + c] = z[i, c]
        ok, step = _factor(A, R, N, ladder)
        out.step[b] = step
        out.failed[b] = out.dropped[b] = not ok
        for c in range(n_z):
            out.nlml[b, c] = -_log_density(R, N, c) + 0.5 * N * LOG_2PI if ok else np.inf
        if mode == NLML or not ok:
            continue
        _matern_flat(DYc, DXc, sy, sx, log_sf2, V.reshape(N * M), work)       # K_f*
        for m in range(M):
            mean[m] = 0.0
            ss[m] = 0.0
        for i in range(N):                           # V = L⁻¹ K_f*, row by row
            for k in range(i):
                lk = R[k, i]
                for m in range(M):
                    V[i, m] -= lk * V[k, m]
            d = R[i, i]
            w = R[i, N]                               # (L⁻¹ z)_i
            for m in range(M):
                v = V[i, m] / d
                V[i, m] = v
                mean[m] += v * w                      # Eq. 7: K_*f K⁻¹ z
                ss[m] += v * v
        sf2 = math.exp(log_sf2)
        finite = True
        for m in range(M):
            finite &= math.isfinite(mean[m]) and math.isfinite(ss[m])
            v = sf2 - ss[m]
            ss[m] = v if v > 0.0 else 0.0             # latent variance
        if not finite:
            out.dropped[b] = True
            continue
        w = test.weight[b]
        y_out = test.y_out[row[b]]
        sn2 = math.exp(2.0 * log_sn)
        for m in range(M):
            dz = mean[m] - test.centre[0, m]
            dd = mean[m] - y_out[m] - test.centre[1, m]
            acc[0, m] += w * dz
            acc[1, m] += w * dd
            acc[2, m] += w * (ss[m] + sn2 + dz * dz)  # total variance of z*
            acc[3, m] += w * (ss[m] + dd * dd)        # latent variance goes to δ


# ---------------------------------------------------------------------------------------
# The Kennedy–O'Hagan chain


@_inline
def _koh_log_likelihood(u, em, koh, work):
    """``Σ_o log N(z_o | m_η(X, θ), Σ_η(X, X; θ) + K_δ,o + σ_n,o² I)`` at ``θ = μ + sd u``,
    with the emulator's moments (:class:`mdcore._emulator.EmulatorAt`): ``k_θ = m32(θ,
    Θ_train)``, ``m_η = lin + θᵀβ_θ + k_θ AK``, ``Σ_η = σ_f² m32(X, X) − σ_f⁴ V diag(d)
    Vᵀ`` with ``d = (k_θ Q_θ)² W``. ``-inf`` where a covariance fails the jitter ladder.
    Returns ``(value, jittered, failed, largest step)``."""
    unit, kt, a, d, vd, A, R = work
    (n_out, p), R_train, N = em.inv_ell.shape, em.T_train.shape[0], em.lin.shape[1]
    for k in range(p):
        unit[k] = ((koh.mu[k] + koh.sd[k] * u[k]) - em.t_lo[k]) / em.t_span[k]
    total = 0.0
    jittered, failed, largest = 0, 0, 0.0
    for o in range(n_out):
        for r in range(R_train):                     # k_θ, as the NumPy path forms it
            acc = 0.0
            for k in range(p):
                s = em.inv_ell[o, k]
                e = unit[k] * s - em.T_train[r, k] * s
                acc += e * e
            q, e = _matern_parts(SQRT3 * math.sqrt(acc), 0.0, 0.0)
            kt[r] = q * math.exp(e)
        for j in range(R_train):                     # (k_θ Q_θ)²
            s = 0.0
            for r in range(R_train):
                s += kt[r] * em.Q_t[o, r, j]
            a[j] = s * s
        for m in range(d.size):                      # d(θ) = (k_θ Q_θ)² W
            s = 0.0
            for j in range(R_train):
                s += a[j] * em.W[o, j, m]
            d[m] = s
        lin_t = 0.0
        for k in range(p):
            lin_t += unit[k] * em.beta_t[o, k]
        for n in range(N):                           # [prior + K_δ + σ_n² I − σ_f⁴ V diag(d)
            for m in range(d.size):                  #  Vᵀ | z − m_η], by rows
                vd[m] = em.V[o, n, m] * d[m]
            for c in range(n, N):
                s = 0.0
                for m in range(d.size):
                    s += vd[m] * em.V[o, c, m]
                A[n, c] = koh.base[o, n, c] - em.sf4[o] * s
            s = em.lin[o, n] + lin_t
            for r in range(R_train):
                s += kt[r] * em.AK[o, r, n]
            A[n, N] = koh.zT[o, n] - s
        ok, step = _factor(A, R, N, koh.ladder)
        if not ok:
            failed += 1
            total = -np.inf
            continue
        if step > 0.0:
            jittered += 1
            largest = step if step > largest else largest
        total += _log_density(R, N, R.shape[1] - N - 1) - 0.5 * N * LOG_2PI   # z − m_η
    return total if math.isfinite(total) else -np.inf, jittered, failed, largest


@_kernel
def koh_steps(t_start, lp, steps, log_u, chain, em, koh, stats):
    """Steps ``t_start …`` of :func:`mdcore._mcmc.adaptive_metropolis` (the same operations)
    on the KOH target, updating ``chain`` (:class:`mdcore._compiled.ChainState`) in place;
    returns the state's log target. ``stats`` adds up [jittered, failed, largest step]."""
    x, mean, m2, L = chain.x, chain.mean, chain.m2, chain.L
    d = x.size
    N, R_train = em.lin.shape[1], em.T_train.shape[0]
    work = (np.empty(d), np.empty(R_train), np.empty(R_train), np.empty(em.W.shape[2]),
            np.empty(em.W.shape[2]), np.empty((N, N + 1)), np.empty((N, N + 1)))
    y = np.empty(d)
    delta = np.empty(d)
    P, Rp = np.empty((d, d + 1)), np.empty((d, d + 1))   # upper triangles used
    for r in range(d):
        P[r, d] = 0.0                                # no extra column
    no_jitter = np.empty(0)
    for i in range(steps.shape[0]):
        t = t_start + i
        for r in range(d):                           # y = x + L s
            s = 0.0
            for c in range(d):
                s += L[r, c] * steps[i, c]
            y[r] = x[r] + s
        inside = True
        for k in range(d):
            inside &= y[k] >= koh.lo_u[k] and y[k] <= koh.hi_u[k]
        if inside:
            lq, jittered, failed, largest = _koh_log_likelihood(y, em, koh, work)
            stats[0] += jittered
            stats[1] += failed
            stats[2] = largest if largest > stats[2] else stats[2]
            for k in range(d):
                lq -= 0.5 * y[k] * y[k]
            if lq - lp > log_u[i]:                   # NaN and -inf are rejected
                for k in range(d):
                    x[k] = y[k]
                lp = lq
                chain.accepted[1 if t > chain.burn_in else 0] += 1
        if t > chain.burn_in:
            for k in range(d):
                chain.samples[t - chain.burn_in - 1, k] = x[k]
            chain.log_p[t - chain.burn_in - 1] = lp
        for k in range(d):                           # Welford with x_t
            delta[k] = x[k] - mean[k]
            mean[k] = mean[k] + delta[k] / (t + 1)
        for r in range(d):
            for c in range(d):
                m2[r, c] += delta[r] * (x[c] - mean[c])
        if t >= chain.t0:                            # s_d Cov + s_d ε I (Haario Eq. 2.1)
            for r in range(d):
                for c in range(r, d):
                    P[r, c] = chain.s_d * m2[c, r] / t + chain.reg[c, r]   # lower, as LAPACK
            if _factor(P, Rp, d, no_jitter)[0]:      # else keep the previous proposal
                for r in range(d):
                    for c in range(d):
                        L[r, c] = Rp[c, r] if c <= r else 0.0
    return lp
