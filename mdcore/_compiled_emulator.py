"""Numba kernels of the history-matching emulator: at many candidate θ, and its fit (SPEC §4–5).

Imported lazily by :mod:`mdcore.compiled` (needs numba); nothing here validates input.
For output ``o`` of an :class:`mdcore.emulator.Emulator` at fixed inputs X (the algebra
of :class:`mdcore.emulator.EmulatorAt`), with ``k_θ = m32(θ, Θ_train)`` (R,)::

    E[y(θ, x_n)] = (k_θ · AK[:, n] + lin[n]) + θᵀ β_θ
    V[y(θ, x_n)] = max(σ_f² − σ_f⁴ Σ_a (k_θ Q_θ)_a² G[a, n], 0),   G = W (m32(X, X_train) Q_x)²ᵀ

and, fused (Eq. 16), ``I_n,o = |z_n,o − E| / √(V_n,o + V)`` with ``V = V_o + V_m``,
combined per θ by its ``rank``-th largest value (the "max", "2nd max", "3rd max" rules).
Only ``k_θ`` depends on θ, so a candidate costs ``R`` exponentials and ``O(R² + R N)``
flops per output, and nothing of size candidates × R is ever stored: candidates are taken
in blocks of :data:`BLOCK`, whose ``k_θ`` are built with the vectorised exponential of
:mod:`mdcore._compiled_kernels` (:func:`_qexp`, within 1 ulp). The squared distances are
formed exactly as :func:`mdcore.kernels.scaled_sq_dist` forms them (same operations in
the same order), so ``k_θ`` differs from the NumPy path only through the exponential.

The ``fit_*`` kernels and :func:`diag_quad` serve the emulator *fit*
(:func:`mdcore.emulator.fit_emulator`), whose result must not move by a bit (L-BFGS-B turns
a 1-ulp change of the NLML into ~1e-5 in the hyperparameters). They take over the
elementwise arithmetic and the sums of :func:`mdcore.emulator._kron_nlml` with the same
operations in the same order: IEEE ``+ − × ÷ √`` are correctly rounded (the same bits
anywhere; no fast-math, so no FMA contraction), every sum is NumPy's pairwise
summation (:func:`total`), and the one 3-operand ``np.einsum`` is replayed in its own order
(:func:`diag_quad`). What cannot be replayed stays in NumPy: ``exp``, ``log``, ``pow``,
the eigendecompositions and the BLAS products. ``test_emulator`` pins the bits.

Cache note: numba's on-disk cache of this file does not notice edits to
:func:`mdcore._compiled_kernels._qexp`, which is compiled into this kernel; after changing
``_qexp``, touch this file (or clear the ``*.nbi``/``*.nbc`` files) to recompile.
"""

from __future__ import annotations

import math

import numpy as np

from ._compiled_kernels import SQRT3, _jit, _qexp

#: Candidates per block: the block's k_θ (BLOCK × R) and its scratch stay in cache.
BLOCK = 64
#: Modes of :func:`candidate_range`.
MOMENTS, SCORES = 0, 1


@_jit
def _block(a, lo, n):
    """NumPy's pairwise sum of a block of ``n ≤ 128`` values: 8 running sums (one value
    at a time below 8), combined as ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))."""
    if n < 8:
        res = 0.0
        for i in range(n):
            res += a[lo + i]
        return res
    r0, r1, r2, r3 = a[lo], a[lo + 1], a[lo + 2], a[lo + 3]
    r4, r5, r6, r7 = a[lo + 4], a[lo + 5], a[lo + 6], a[lo + 7]
    i = 8
    m = n - n % 8
    while i < m:
        j = lo + i
        r0 += a[j]
        r1 += a[j + 1]
        r2 += a[j + 2]
        r3 += a[j + 3]
        r4 += a[j + 4]
        r5 += a[j + 5]
        r6 += a[j + 6]
        r7 += a[j + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        res += a[lo + i]
        i += 1
    return res


@_jit
def _pairwise(a):
    """NumPy's pairwise sum of the 1-D ``a`` (``pairwise_sum`` of its float64 add
    reduction): blocks of up to 128 values, and above that the sum of the two halves, split
    at a multiple of 8. Written with an explicit stack (numba cannot cache recursion)."""
    lo_s = np.empty(192, dtype=np.int64)          # pending ranges; a negative n: add up
    n_s = np.empty(192, dtype=np.int64)
    vals = np.empty(96)
    top = 0
    nv = 0
    lo_s[0], n_s[0] = 0, a.size
    top = 1
    while top:
        top -= 1
        lo, n = lo_s[top], n_s[top]
        if n < 0:                                   # both halves done: left + right
            nv -= 1
            vals[nv - 1] = vals[nv - 1] + vals[nv]
        elif n <= 128:
            vals[nv] = _block(a, lo, n)
            nv += 1
        else:
            n2 = n // 2
            n2 -= n2 % 8
            lo_s[top], n_s[top] = lo, -1
            lo_s[top + 1], n_s[top + 1] = lo + n2, n - n2
            lo_s[top + 2], n_s[top + 2] = lo, n2
            top += 3
    return vals[0]


@_jit
def total(a):
    """``np.sum(a)`` of a C-contiguous float64 array, bit for bit."""
    return 0.0 + _pairwise(a.reshape(a.size))


@_jit
def fit_distances(A, ell, r, t):
    """Scaled distances ``r_ij = √(Σ_k (a_ik/ℓ_k − a_jk/ℓ_k)²)`` of the rows of ``A``
    (n, d) and ``t = −√3 r``, into (n, n) arrays, formed as
    :func:`mdcore.emulator._m32_and_dlog_ell` forms them (after
    :func:`mdcore.kernels.scaled_sq_dist`)."""
    n, d = A.shape
    r[:, :] = 0.0
    for k in range(d):
        inv = 1.0 / ell[k]
        for i in range(n):
            ai = A[i, k] * inv
            for j in range(n):
                diff = ai - A[j, k] * inv
                r[i, j] += diff * diff
    for i in range(n):
        for j in range(n):
            x = math.sqrt(r[i, j])
            r[i, j] = x
            t[i, j] = -SQRT3 * x


@_jit
def fit_kernel(r, e, diffs, ell2, K, D):
    """``K = (1 + √3 r) e`` and ``D_k = 3 e Δ_k² / ℓ_k²`` from ``e = exp(−√3 r)`` (computed
    by NumPy), ``diffs`` (d, n, n) and ``ell2[k] = ℓ_k ** 2`` (NumPy's ``pow``)."""
    n = r.shape[0]
    for i in range(n):
        for j in range(n):
            K[i, j] = (1.0 + SQRT3 * r[i, j]) * e[i, j]
            c = 3.0 * e[i, j]
            for k in range(ell2.size):
                D[k, i, j] = (c * diffs[k, i, j]) / ell2[k]


@_jit
def fit_factors(T, ell_t, rt, tt, X, ell_x, rx, tx):
    """:func:`fit_distances` of the θ and the x factor, in one call (the fit is dominated
    by per-call overhead on these small matrices)."""
    fit_distances(T, ell_t, rt, tt)
    fit_distances(X, ell_x, rx, tx)


@_jit
def fit_kernels(rt, et, dt2, ell2_t, Kt, Dt, rx, ex, dx2, ell2_x, Kx, Dx):
    """:func:`fit_kernel` of the θ and the x factor, in one call."""
    fit_kernel(rt, et, dt2, ell2_t, Kt, Dt)
    fit_kernel(rx, ex, dx2, ell2_x, Kx, Dx)


@_jit
def fit_spectrum(lam, mu, sf2, sn2, SO, S):
    """Eigenvalues clipped at 0 in place (``np.maximum(·, 0.0)``, NaN kept), then
    ``SO = σ_f² λ_a μ_b`` and ``S = SO + σ_n²``."""
    for v in (lam, mu):
        for i in range(v.size):
            x = v[i]
            if not (x >= 0.0 or x != x):
                v[i] = 0.0
    for a in range(lam.size):
        for b in range(mu.size):
            SO[a, b] = sf2 * (lam[a] * mu[b])
            S[a, b] = SO[a, b] + sn2


@_jit
def fit_terms(P, S, SO, logS, Pa):
    """``Pa = P / S`` (into ``Pa``) and the sums of the NLML and of two gradient entries:
    ``(Σ Pa² S, Σ log S, Σ SO (1/S − Pa²), Σ (1/S − Pa²))``."""
    n = S.size
    Pf, Sf, SOf, Af = P.reshape(n), S.reshape(n), SO.reshape(n), Pa.reshape(n)
    x = np.empty(n)
    z = np.empty(n)
    y = np.empty(n)
    for i in range(n):
        a = Pf[i] / Sf[i]
        Af[i] = a
        pp = a * a
        x[i] = pp * Sf[i]
        z[i] = 1.0 / Sf[i] - pp
        y[i] = SOf[i] * z[i]
    return total(x), total(logS), total(y), total(z)


@_jit
def fit_trace(Q, Dd, v, S, theta_side):
    """``Σ (outer(diag(Qᵀ Dd Q), v) / S)`` (``theta_side``) or ``Σ (outer(v, diag(Qᵀ Dd
    Q)) / S)``: the trace term of one gradient entry."""
    q = diag_quad(Q, Dd)
    R, N = S.shape
    x = np.empty((R, N))
    for a in range(R):
        for b in range(N):
            x[a, b] = ((q[a] * v[b]) if theta_side else (v[a] * q[b])) / S[a, b]
    return total(x)


@_jit
def fit_dot(A, B):
    """``np.sum(A * B)`` of two C-contiguous arrays of one shape, bit for bit."""
    n = A.size
    Af, Bf = A.reshape(n), B.reshape(n)
    x = np.empty(n)
    for i in range(n):
        x[i] = Af[i] * Bf[i]
    return total(x)


@_jit
def fit_gradient(sf2, Qt, Dt, mu, Qx, Dx, lam, S, A0, DAK, KAD, g):
    """The lengthscale entries of the gradient, ``g[1 : 1 + p + d_x]``: for each θ
    dimension ``½ σ_f² (fit_trace(Q_θ, D_θ,d, μ, S) − Σ A0 ⊙ DAK_d)`` and for each x
    dimension ``½ σ_f² (fit_trace(Q_x, D_x,d, λ, S) − Σ A0 ⊙ KAD_d)``, with ``DAK_d =
    D_θ,d A0 K_x`` and ``KAD_d = K_θ A0 D_x,d`` (BLAS products, made by the caller)."""
    p = Dt.shape[0]
    for d in range(p):
        g[1 + d] = 0.5 * sf2 * (fit_trace(Qt, Dt[d], mu, S, True) - fit_dot(A0, DAK[d]))
    for d in range(Dx.shape[0]):
        g[1 + p + d] = 0.5 * sf2 * (fit_trace(Qx, Dx[d], lam, S, False)
                                    - fit_dot(A0, KAD[d]))


@_jit
def diag_quad(Q, D):
    """``diag(Qᵀ D Q)`` for square Q, D (n, n): bit for bit ``np.einsum("ra,rs,sa->a", Q,
    D, Q)``, which keeps one running sum per ``a`` over ``(r, s)`` in row-major order with
    terms ``(Q[r, a] D[r, s]) Q[s, a]``. Here ``a`` is the inner loop, so the sums vectorise
    across ``a`` without being reordered (no fast-math); ``test_emulator`` pins the bits."""
    n = Q.shape[0]
    out = np.zeros(n)
    for r in range(n):
        for s in range(n):
            c = D[r, s]
            for a in range(n):
                out[a] += Q[r, a] * c * Q[s, a]
    return out


@_jit
def _accumulate(out, C, X, R, N, nb, squared):
    """``out[n] += Σ_r C[r, n] x_r`` with ``x_r = X[r·nb : (r+1)·nb]`` (``x_r²`` if
    ``squared``), ``out`` (N, nb): a (N × R)·(R × nb) product whose inner loops run over
    the block, four rows of X at a time (so ``out`` is loaded and stored R/4 times)."""
    out[:, :] = 0.0
    r4 = R - R % 4
    for n in range(N):
        acc = out[n]
        for r in range(0, r4, 4):
            c0, c1, c2, c3 = C[r, n], C[r + 1, n], C[r + 2, n], C[r + 3, n]
            x0 = X[r * nb:(r + 1) * nb]
            x1 = X[(r + 1) * nb:(r + 2) * nb]
            x2 = X[(r + 2) * nb:(r + 3) * nb]
            x3 = X[(r + 3) * nb:(r + 4) * nb]
            if squared:
                for i in range(nb):
                    acc[i] += ((c0 * (x0[i] * x0[i]) + c1 * (x1[i] * x1[i]))
                               + (c2 * (x2[i] * x2[i]) + c3 * (x3[i] * x3[i])))
            else:
                for i in range(nb):
                    acc[i] += (c0 * x0[i] + c1 * x1[i]) + (c2 * x2[i] + c3 * x3[i])
        for r in range(r4, R):
            c = C[r, n]
            x = X[r * nb:(r + 1) * nb]
            if squared:
                for i in range(nb):
                    acc[i] += c * (x[i] * x[i])
            else:
                for i in range(nb):
                    acc[i] += c * x[i]


@_jit
def _accumulate_rows(out, Q, X, R, nb):
    """``out[j] = Σ_r Q[r, j] x_r`` for the (R, nb) row-major blocks ``out`` and ``X``:
    the block's ``k_θ Q_θ``."""
    r4 = R - R % 4
    for j in range(R):
        acc = out[j * nb:(j + 1) * nb]
        acc[:] = 0.0
        for r in range(0, r4, 4):
            c0, c1, c2, c3 = Q[r, j], Q[r + 1, j], Q[r + 2, j], Q[r + 3, j]
            x0 = X[r * nb:(r + 1) * nb]
            x1 = X[(r + 1) * nb:(r + 2) * nb]
            x2 = X[(r + 2) * nb:(r + 3) * nb]
            x3 = X[(r + 3) * nb:(r + 4) * nb]
            for i in range(nb):
                acc[i] += (c0 * x0[i] + c1 * x1[i]) + (c2 * x2[i] + c3 * x3[i])
        for r in range(r4, R):
            c = Q[r, j]
            x = X[r * nb:(r + 1) * nb]
            for i in range(nb):
                acc[i] += c * x[i]


@_jit
def candidate_range(mode, m0, m1, theta, t_lo, t_span, T_train, inv_ell, Q_t, beta_t, lin,
                    AK, G, sf2, z, vt, rank, mean, var, imp):
    """Candidates ``m0 ≤ m < m1``: emulator moments, or fused combined implausibility.

    Serial, the GIL released; :mod:`mdcore.compiled` runs ranges of candidates on its
    threads. Candidates are independent, so any split gives the same numbers. Within a
    block every array is laid out with the block's candidates last, so the inner loops
    are flat loops over candidates, which LLVM vectorises (without reassociating sums).

    Parameters (float64 and C-contiguous unless said)
    ----------
    mode : int
        :data:`MOMENTS`: write ``mean`` and ``var``. :data:`SCORES`: write ``var`` and
        ``imp`` (``mean`` unused).
    theta : (M, p)            candidates, the case's units
    t_lo, t_span : (p,)       θ's box: unit θ = (θ − t_lo) / t_span
    T_train : (R, p)          training θ, unit box
    inv_ell : (n_out, p)      1 / ℓ_θ
    Q_t : (n_out, R, R)       eigenvectors of K_θ
    beta_t : (n_out, p)       β_θ of the linear mean
    lin : (n_out, N)          β₀ + β_xᵀ x at the inputs
    AK : (n_out, R, N)        A m32(X, X_train)ᵀ
    G : (n_out, R, N)         W (m32(X, X_train) Q_x)²ᵀ
    sf2 : (n_out,)            σ_f²
    z, vt : (N, n_out)        observations and V_o + V_m (SCORES; else any)
    rank : int                1, 2 or 3: the combined I is the rank-th largest
    mean, var : (M, N, n_out) outputs (``mean`` written in MOMENTS mode only)
    imp : (M,)                output (SCORES mode)

    Returns
    -------
    int
        SCORES: the number of targets with ``V_o + V_m + var ≤ 0`` (0 otherwise).
    """
    n_out, R, p = inv_ell.shape[0], T_train.shape[0], T_train.shape[1]
    N = lin.shape[1]
    B = BLOCK
    unit = np.empty((p, B))          # unit θ of the block, by parameter
    us = np.empty((p, B))            # unit θ / ℓ
    Ts = np.empty((p, R))            # training θ / ℓ
    q = np.empty(R * B)              # (R, nb) row-major: 1 + √3 r, −√3 r, k_θ, k_θ Q_θ
    e = np.empty(R * B)
    kt = np.empty(R * B)
    a = np.empty(R * B)
    tb = np.empty(R * B)
    ib = np.empty(R * B, dtype=np.int64)
    am = np.empty((N, B))            # k_θ AK
    av = np.empty((N, B))            # (k_θ Q_θ)² G
    lt = np.empty(B)                 # θᵀ β_θ
    sc = np.empty(B)
    t0, t1, t2 = np.empty(B), np.empty(B), np.empty(B)    # the three largest I
    scores = mode == SCORES
    bad = 0
    for b0 in range(m0, m1, B):
        nb = min(B, m1 - b0)
        nR = nb * R
        for i in range(nb):
            for k in range(p):
                unit[k, i] = (theta[b0 + i, k] - t_lo[k]) / t_span[k]
        t0[:] = -np.inf
        t1[:] = -np.inf
        t2[:] = -np.inf
        for o in range(n_out):
            for k in range(p):            # (θ / ℓ − θ_r / ℓ)², as scaled_sq_dist forms it
                s = inv_ell[o, k]
                for r in range(R):
                    Ts[k, r] = T_train[r, k] * s
                for i in range(nb):
                    us[k, i] = unit[k, i] * s
            for r in range(R):
                r2 = a[r * nb:(r + 1) * nb]
                r2[:] = 0.0
                for k in range(p):
                    c = Ts[k, r]
                    u = us[k]
                    for i in range(nb):
                        d = u[i] - c
                        r2[i] += d * d
                qr = q[r * nb:(r + 1) * nb]
                er = e[r * nb:(r + 1) * nb]
                for i in range(nb):
                    x = SQRT3 * math.sqrt(r2[i])
                    qr[i] = 1.0 + x
                    er[i] = -x
            _qexp(q[:nR], e[:nR], kt[:nR], tb, ib)          # k_θ = (1 + √3 r) e^{−√3 r}
            _accumulate(am, AK[o], kt, R, N, nb, False)         # k_θ AK
            _accumulate_rows(a, Q_t[o], kt, R, nb)              # k_θ Q_θ
            _accumulate(av, G[o], a, R, N, nb, True)            # (k_θ Q_θ)² G
            lt[:nb] = 0.0
            for k in range(p):
                c = beta_t[o, k]
                for i in range(nb):
                    lt[i] += unit[k, i] * c
            s2 = sf2[o]
            s4 = s2 * s2
            for n in range(N):
                mrow, vrow = am[n], av[n]
                for i in range(nb):
                    mrow[i] = (mrow[i] + lin[o, n]) + lt[i]
                    vrow[i] = max(s2 - s4 * vrow[i], 0.0)
                for i in range(nb):
                    var[b0 + i, n, o] = vrow[i]
                if not scores:
                    for i in range(nb):
                        mean[b0 + i, n, o] = mrow[i]
                    continue
                zn, vn = z[n, o], vt[n, o]
                for i in range(nb):
                    total = vn + vrow[i]
                    bad += total <= 0.0
                    sc[i] = abs(zn - mrow[i]) / math.sqrt(total)
                for i in range(nb):                 # insert into t0 ≥ t1 ≥ t2
                    x = sc[i]
                    hi = max(t0[i], x)
                    x = min(t0[i], x)
                    t0[i] = hi
                    hi = max(t1[i], x)
                    x = min(t1[i], x)
                    t1[i] = hi
                    t2[i] = max(t2[i], x)
        if scores:
            top = t0 if rank == 1 else (t1 if rank == 2 else t2)
            for i in range(nb):
                imp[b0 + i] = top[i]
    return bad
