"""Numba kernels behind :mod:`mdcore.compiled` (imported lazily; needs numba).

Nothing here validates input. :mod:`mdcore.compiled` passes C-contiguous float64/int64
arrays of fixed rank to the one public kernel, :func:`pair_range`, so it compiles exactly
one signature, and ``cache=True`` keeps it on disk between processes. The kernel is serial
and releases the GIL; :mod:`mdcore.compiled` runs ranges of pairs on its own threads.

One (hyperparameter, Y) pair is the unit of work. Per pair a kernel builds the bordered
training matrix ``[[K_ff + σ_n² I, z], [zᵀ, c]]`` with ``c = 2 zᵀz / σ_n² + 1`` (the same
matrix as the NumPy path), factorises it with the SPEC §3 jitter ladder and reads the NLML
(Eq. 9) off the factor, whose last column holds ``L⁻¹ z``. Prediction (Eq. 7) builds
``K_f*`` in column tiles, solves ``V = L⁻¹ K_f*`` and accumulates ``mean = Vᵀ L⁻¹ z`` and
``Σ V²`` per column. Nothing of size pairs × N × N is ever formed.

Layout, chosen so that every hot loop is a flat loop from index 0 (which LLVM vectorises;
numba's negative-index handling of ``a[i + t]`` would stop it):

- the bordered matrix is stored packed, upper triangle by rows: entry (i, j ≥ i) of the
  n × n matrix at ``i n − i(i − 1)/2 + j − i``; its factor by rows of an
  (n, n + :data:`ROW_PAD`) array, so that row updates need no remainder loop;
- input differences ``|Δ|`` (one dimension) or ``Δ²`` (per dimension, several) are
  computed once in the same packed order: for X once per call, for Y once per Y row
  (pairs that share a Y row, like scenario 3's N_φ draws per θ, reuse them);
- a range of pairs allocates its small work buffers once and runs its pairs in order;
- replicated training inputs (equal rows of ``[Y, X]``, as shear-5's repeats) have equal
  kernel entries: those of the distinct inputs are computed once and copied
  (:func:`_distinct_rows`), with the same bits.

The kernel ``σ_f² (1 + √3 r_y) e^{−√3 r_y} (1 + √3 r_x) e^{−√3 r_x}`` (SPEC §3, Eq. 3) is
evaluated like the NumPy path, as ``(1 + s + a b) exp(log σ_f² − s)`` with ``a = √3 r_y``,
``b = √3 r_x``, ``s = a + b``: one exponential per entry. That exponential (:func:`_qexp`)
is branch-free so that the compiler vectorises it; it is within 1 ulp of the exact value.
When y and x are both one-dimensional, K_f* needs no exponential per entry at all
(:func:`_cross_1d`).
"""

from __future__ import annotations

import math
from decimal import Decimal, localcontext

import numpy as np
from numba import njit

SQRT3 = math.sqrt(3.0)
LOG_2PI = math.log(2.0 * math.pi)
#: Entries per tile of K_f* (N × test points): the tile and its solve stay in cache.
TILE_ENTRIES = 8192


def _exp_constants():
    """Constants of :func:`_qexp`, computed to 60 digits and rounded once."""
    with localcontext() as ctx:
        ctx.prec = 60
        ln2 = Decimal(2).ln()
        hi = np.array(float(ln2 / 32))
        hi = float((hi.view(np.int64) & ~np.int64(2**27 - 1)).view(np.float64))
        lo = float(ln2 / 32 - Decimal(hi))
        table = np.array([float(Decimal(2) ** (Decimal(j) / 32)) for j in range(32)])
        return float(32 / ln2), hi, lo, table


# exp(x) = 2^(k/32) · exp(r): k = round(32 x / ln 2), r = x − k ln2/32 with ln2/32 split in
# two (Cody–Waite; the high part has 26 significant bits, so k · high is exact); 2^(k/32) =
# 2^⌊k/32⌋ · T[k mod 32] from a correctly rounded table; exp(r) − 1 by its degree-6 Taylor
# polynomial, whose truncation error (ln2/64)^7 / 7! ≈ 4e-18 is far below half an ulp. k is
# read off the bits of 32 x / ln 2 + 1.5·2^52 and 2^⌊k/32⌋ is built from exponent bits.
_INV_LN2_32, _LN2_32_HI, _LN2_32_LO, _EXP2_TABLE = _exp_constants()
_SHIFT = 6755399441055744.0                      # 1.5 · 2^52
_SHIFT_BITS = int(np.array(_SHIFT).view(np.int64))
# Outside [_LO, _HI] (subnormal or overflowing results, NaN) the C library's exp is used.
_LO = -708.0
_HI = 709.0
_C3, _C4, _C5, _C6 = (1.0 / math.factorial(i) for i in range(3, 7))

#: Every kernel: on-disk cache, IEEE semantics (no fast-math), GIL released, and NumPy's
#: floating-point error model (x/0 gives inf, as in the NumPy path).
_jit = njit(cache=True, fastmath=False, nogil=True, error_model="numpy")

@_jit
def _exp_shift(x):
    """The first step of :func:`_qexp` for one argument: ``x`` clamped to [_LO, _HI], times
    32/ln 2, plus 1.5·2^52 (k in the low bits), and whether ``x`` is outside (or NaN)."""
    v = min(max(x, _LO), _HI)
    return v * _INV_LN2_32 + _SHIFT, not (x >= _LO and x <= _HI)


@_jit
def _qexp(q, e, out, tb, ib):
    """``out = q · exp(e)`` elementwise (1-D, same length); ``tb`` (float64) and ``ib``
    (int64) are scratch at least as long. ``out`` must not alias ``q`` or ``e``.

    Four passes, so that the arithmetic ones vectorise: k (:func:`_exp_shift`); the table
    look-up (a scalar gather, which would stop the vectorisation of the polynomial pass);
    the polynomial; and, only if some argument is outside [_LO, _HI] or NaN, the C
    library's exp there (:func:`_qexp_shifted` does all but the first).
    """
    bad = 0
    for i in range(e.size):
        tb[i], outside = _exp_shift(e[i])
        bad += outside
    _qexp_shifted(q, e, out, tb, ib, bad)


@_jit
def _qexp_shifted(q, e, out, tb, ib, bad):
    """:func:`_qexp` after its first pass: ``tb`` holds :func:`_exp_shift` of ``e``, and
    ``bad`` counts the arguments outside [_LO, _HI] or NaN."""
    n = e.size
    tbi = tb.view(np.int64)
    t = ib.view(np.float64)
    for i in range(n):
        t[i] = _EXP2_TABLE[(tbi[i] - _SHIFT_BITS) & 31]        # 2^((k mod 32)/32)
    scale = out.view(np.int64)
    for i in range(n):
        scale[i] = (((tbi[i] - _SHIFT_BITS) >> 5) + 1023) << 52   # bits of 2^⌊k/32⌋
    for i in range(n):
        v = min(max(e[i], _LO), _HI)
        k = tb[i] - _SHIFT
        r = (v - k * _LN2_32_HI) - k * _LN2_32_LO
        p = _C6 * r + _C5
        p = p * r + _C4
        p = p * r + _C3
        p = p * r + 0.5
        p = p * r + 1.0
        p = p * r                                    # exp(r) − 1
        out[i] = q[i] * ((t[i] + t[i] * p) * out[i])
    if bad:
        for i in range(n):
            v = e[i]
            if not (v >= _LO and v <= _HI):
                out[i] = q[i] * math.exp(v)


# ---------------------------------------------------------------------------------------
# Input differences, computed once and reused by every pair that shares the inputs


@_jit
def _packed_diffs(A, n, out):
    """Differences of the rows of ``A`` (N, d) in the packed upper order of an n × n
    matrix (n ≥ N; entries with a column ≥ N are 0). ``out`` (d, n(n+1)/2) receives
    ``|Δ|`` when d = 1 and ``Δ²`` per dimension otherwise."""
    N, d = A.shape
    out[:, :] = 0.0
    p = 0
    for i in range(n):
        for j in range(i, n):
            if j < N:
                for k in range(d):
                    diff = A[i, k] - A[j, k]
                    out[k, p] = abs(diff) if d == 1 else diff * diff
            p += 1


@_jit
def _tile(N, M):
    """Test points per tile: about :data:`TILE_ENTRIES` entries, at least 16 points."""
    return max(1, min(M, max(16, TILE_ENTRIES // N)))


@_jit
def _tiled_diffs(A, B, out):
    """Differences between the rows of ``A`` (N, d) and of ``B`` (M, d), by tiles of
    ``tile = out.shape[2] // N`` rows of B: ``out[c, k]`` (n_tiles, d, N·tile) holds tile c
    as an (N, nt) row-major block. ``Δ = a − b`` when d = 1 (the kernels take ``|Δ|``),
    ``Δ²`` per dimension otherwise."""
    N, d = A.shape
    M = B.shape[0]
    tile = out.shape[2] // N
    for c in range(out.shape[0]):
        m0 = c * tile
        nt = min(tile, M - m0)
        for k in range(d):
            blk = out[c, k]
            for i in range(N):
                a = A[i, k]
                row = blk[i * nt:(i + 1) * nt]
                for t in range(nt):
                    diff = a - B[m0 + t, k]
                    row[t] = diff if d == 1 else diff * diff


@_jit
def _squared_dist(D, s, out):
    """``out = Σ_k D_k s_k²`` (0 in no dimension): the squared scaled distances ``3 r²``
    from the per-dimension ``Δ²`` of :func:`_packed_diffs`/:func:`_tiled_diffs`. Reads the
    first ``out.size`` entries of each row of ``D`` (d, ≥ n)."""
    d = s.size
    n = out.size
    if d == 0:
        out[:] = 0.0
        return
    s2 = s[0] * s[0]
    d0 = D[0]
    for p in range(n):
        out[p] = d0[p] * s2
    for k in range(1, d):
        s2 = s[k] * s[k]
        dk = D[k]
        for p in range(n):
            out[p] += dk[p] * s2


@_jit
def _scaled_dist(D, s, out):
    """``out = √(Σ_k D_k s_k²)`` (``|D_0| · s_0`` in one dimension, 0 in none): the scaled
    distances ``√3 r`` from the differences of :func:`_packed_diffs`/:func:`_tiled_diffs`
    (the NumPy path's formula: ``|Δ| · √3/ℓ``, or ``√(Σ Δ² (√3/ℓ)²)``). Reads the first
    ``out.size`` entries of each row of ``D`` (d, ≥ n)."""
    n = out.size
    if s.size == 1:
        s0 = s[0]
        d0 = D[0]
        for p in range(n):
            out[p] = abs(d0[p]) * s0
    else:
        _squared_dist(D, s, out)
        for p in range(n):
            out[p] = math.sqrt(out[p])


@_jit
def _matern_entries(Dy, Dx, sy, sx, log_sf2, W, out):
    """``out = σ_f² m32(r_y) m32(r_x)`` (Eq. 3) for the entries whose differences are
    ``Dy``, ``Dx`` (d, n) (any packed or tiled layout); ``W`` is the workspace.

    The scaled distances' last step (:func:`_scaled_dist`'s square root, or the scaling of
    a one-dimensional ``|Δ|``), the factors and the first step of the exponential
    (:func:`_exp_shift`) share one pass: the operations of the separate passes, in the same
    order, without writing and reading back three arrays.
    """
    wa, wb, wq, we, tb, ib = W
    n = out.size
    ra = wa[:n]
    rb = wb[:n]
    q = wq[:n]
    e = we[:n]
    one_y = sy.size == 1
    one_x = sx.size == 1
    if not one_y:
        _squared_dist(Dy, sy, ra)
    if not one_x:
        _squared_dist(Dx, sx, rb)
    s_y = sy[0] if one_y else 0.0
    s_x = sx[0] if one_x else 0.0
    dy = Dy[0] if one_y else ra
    dx = Dx[0] if one_x else rb
    bad = 0
    for p in range(n):
        a = abs(dy[p]) * s_y if one_y else math.sqrt(dy[p])
        b = abs(dx[p]) * s_x if one_x else math.sqrt(dx[p])
        s = a + b
        q[p] = a * b + s + 1.0                       # (1 + a)(1 + b)
        x = log_sf2 - s
        e[p] = x
        tb[p], outside = _exp_shift(x)
        bad += outside
    _qexp_shifted(q, e, out, tb, ib, bad)


#: Largest ``√3 h / ℓ`` (h: half the range of a one-dimensional input, about its centre)
#: for which :func:`_cross_1d` and :func:`_grid_entries` factorise the exponentials: the
#: arguments ``±√3 u/ℓ`` then carry an absolute rounding error below 16 · 2⁻⁵³ ≈ 1.8e-15,
#: so the product stays within about 4e-15 (relative) of ``exp(−√3 |u − v| / ℓ)``, an
#: error of the size of a Cholesky's own rounding at N = 30 (N ulp). At 8, one pair in ten
#: of beam-2d's scenario 3 (h_y ≈ 1.25 mm, ℓ_y ~ logN(0, 1)) took the per-entry path.
SEPARABLE_LIMIT = 16.0


@_jit
def _cross_1d(Dy, Dx, sy, sx, sf2, Etr, Ete, out, N, nt):
    """K_f* (Eq. 3) for one-dimensional y and x without an exponential per entry.

    In one dimension ``exp(−s |u − v|)`` is the smaller of ``exp(−s u′) exp(s v′)`` and
    ``exp(s u′) exp(−s v′)``, with ``u′, v′`` centred inputs (the first when ``u ≥ v``);
    so N + nt exponentials per dimension (and as many divisions) replace N · nt. Taking
    the smaller needs no sign test, and the loop vectorises without a select (~6 % of a
    beam-1d mixture pair; the same bits on its pairs). ``Etr`` (4, N) and ``Ete`` (4, ≥ nt)
    hold ``[e^{s_y u′}, e^{−s_y u′}, e^{s_x u′}, e^{−s_x u′}]`` of the training and of the
    tile's test points; ``Dy``, ``Dx`` are the differences ``u − v``
    (:func:`_tiled_diffs`). Writes the (N, nt) tile into ``out``.
    """
    s_y = sy[0]
    s_x = sx[0]
    py, qy, px, qx = Ete[0][:nt], Ete[1][:nt], Ete[2][:nt], Ete[3][:nt]
    for i in range(N):
        dy = Dy[0, i * nt:(i + 1) * nt]
        dx = Dx[0, i * nt:(i + 1) * nt]
        o = out[i * nt:(i + 1) * nt]
        Py, Qy, Px, Qx = Etr[0, i], Etr[1, i], Etr[2, i], Etr[3, i]
        for t in range(nt):
            a = abs(dy[t]) * s_y
            b = abs(dx[t]) * s_x
            # e^{−s(u′−v′)} and e^{s(u′−v′)}: the smaller is e^{−s|u − v|}, no sign test
            ey = min(Qy * py[t], Py * qy[t])
            ex = min(Qx * px[t], Px * qx[t])
            o[t] = (a * b + (a + b) + 1.0) * (sf2 * (ey * ex))


@_jit
def _signed_exps(u1, s1, u2, s2, E, W):
    """``E = [e^{s1 u1}, e^{−s1 u1}, e^{s2 u2}, e^{−s2 u2}]`` (4, ≥ n) for vectors of
    length n, with one call of :func:`_qexp` (the negative ones as reciprocals)."""
    wa, wb, wq, we, tb, ib = W
    n = u1.size
    q = wq[:2 * n]
    e = we[:2 * n]
    out = wa[:2 * n]
    for i in range(n):
        e[i] = s1 * u1[i]
        e[n + i] = s2 * u2[i]
    q[:] = 1.0
    _qexp(q, e, out, tb, ib)
    e1, e2, e3, e4 = E[0], E[1], E[2], E[3]
    for i in range(n):
        e1[i] = out[i]
        e2[i] = 1.0 / out[i]
        e3[i] = out[n + i]
        e4[i] = 1.0 / out[n + i]


@_jit
def _centred(a, b, out_a, out_b):
    """``a``, ``b`` (1-D) minus the centre of their joint range; returns the half range."""
    lo = min(a.min(), b.min()) if b.size else a.min()
    hi = max(a.max(), b.max()) if b.size else a.max()
    c = 0.5 * (lo + hi)
    for i in range(a.size):
        out_a[i] = a[i] - c
    for i in range(b.size):
        out_b[i] = b[i] - c
    return 0.5 * (hi - lo)


@_jit
def _workspace(n_entries):
    """Scratch of :func:`_matern_entries` for up to ``n_entries`` entries."""
    return (np.empty(n_entries), np.empty(n_entries), np.empty(n_entries),
            np.empty(n_entries), np.empty(n_entries), np.empty(n_entries, dtype=np.int64))


# ---------------------------------------------------------------------------------------
# Replicated training inputs


@_jit
def _distinct_rows(Y, X, rep, of):
    """Distinct rows of the joint training input ``[Y, X]`` (N, d_y + d_x), exactly equal.

    Writes ``rep[:U]``, the first row of each distinct input, and ``of`` (N,), the
    distinct input of every row; returns U. Replicated observations (shear-5's ten repeats
    per mass) share one input, so their kernel entries are equal and computed once.
    """
    N = X.shape[0]
    U = 0
    for i in range(N):
        found = -1
        for u in range(U):
            r = rep[u]
            same = True
            for k in range(Y.shape[1]):
                if Y[i, k] != Y[r, k]:
                    same = False
                    break
            if same:
                for k in range(X.shape[1]):
                    if X[i, k] != X[r, k]:
                        same = False
                        break
            if same:
                found = u
                break
        if found < 0:
            rep[U] = i
            of[i] = U
            U += 1
        else:
            of[i] = found
    return U


@_jit
def _distinct_diffs(Y, X, rep, of, U, n, DYp, DXp, gather):
    """Differences of the U distinct rows ``rep[:U]`` of ``Y``, ``X`` in packed U × U order
    (:func:`_packed_diffs`), and ``gather`` (n(n+1)/2,): for each entry of the packed
    bordered n × n matrix, the packed U × U entry it equals (0 for the border column, which
    :func:`_train_matrix` overwrites). ``|a − b|`` and ``(a − b)²`` do not depend on the
    order of a and b, so an entry read through ``gather`` has the bits it would have had."""
    N = X.shape[0]
    Yu = np.empty((U, Y.shape[1]))
    Xu = np.empty((U, X.shape[1]))
    for u in range(U):
        Yu[u] = Y[rep[u]]
        Xu[u] = X[rep[u]]
    _packed_diffs(Yu, U, DYp)
    _packed_diffs(Xu, U, DXp)
    p = 0
    for i in range(n):
        for j in range(i, n):
            if j < N:
                a = min(of[i], of[j])
                b = max(of[i], of[j])
                gather[p] = a * U - a * (a - 1) // 2 + b - a
            else:
                gather[p] = 0
            p += 1


@_jit
def _distinct_x_diffs(DXp, xmap, DXd):
    """Distinct columns of the packed x differences ``DXp`` (d_x, T), exactly equal.

    Inputs on a grid (beam-2d's 8 × 8) repeat their differences: 289 distinct of 2,145.
    Writes ``DXd[:, :U]`` and ``xmap`` (T,), the distinct column of every entry, and
    returns U; returns 0 (not worth it) when more than half the columns are distinct.
    """
    d, T = DXp.shape
    codes = np.zeros(T, dtype=np.int64)
    stride = 1
    for k in range(d):                   # per-dimension ranks, combined into one code
        vals = np.unique(DXp[k])
        codes += np.searchsorted(vals, DXp[k]) * stride
        stride *= vals.size
        if stride > 4 * T:
            return 0
    slot = np.full(stride, -1, dtype=np.int64)
    U = 0
    for p in range(T):
        c = codes[p]
        if slot[c] < 0:
            slot[c] = U
            DXd[:, U] = DXp[:, p]
            U += 1
        xmap[p] = slot[c]
    return U if 2 * U <= T else 0


@_jit
def _grid_entries(theta, DYp, sy, sx, G, W, A):
    """Training entries of Eq. 3 with one-dimensional y and repeated x differences.

    ``σ_f² [(1 + a) e^{−a}] [(1 + b) e^{−b}]``, ``a = √3 r_y``, ``b = √3 r_x``: the x
    factor once per distinct x difference (:func:`_distinct_x_diffs`), and ``e^{−a} =
    e^{−s u_i} e^{s u_j}`` (u_i ≥ u_j, centred y) from N exponentials as :func:`_cross_1d`
    builds K_f*, instead of one exponential per entry. ``G = (U, xmap, DXd, yc, hy, E)``:
    yc the centred y of the pair's θ row and ``hy[0]`` its half range. Returns False,
    having written nothing, when ``s h_y`` exceeds :data:`SEPARABLE_LIMIT`.
    """
    U, xmap, DXd, yc, hy, E = G
    N = yc.size
    s_y = sy[0]
    if not s_y * hy[0] <= SEPARABLE_LIMIT:
        return False
    wa, wb, wq, we, tb, ib = W
    sf2 = math.exp(2.0 * theta[0])
    bu, mu, P, Q = E[0], E[1], E[2], E[3]
    _scaled_dist(DXd, sx, bu[:U])                  # √3 r_x of the distinct differences
    q = wq[:U + N]
    e = we[:U + N]
    out = wa[:U + N]
    for u in range(U):
        q[u] = 1.0 + bu[u]
        e[u] = -bu[u]
    for i in range(N):
        q[U + i] = 1.0
        e[U + i] = s_y * yc[i]
    _qexp(q, e, out, tb, ib)
    for u in range(U):
        mu[u] = out[u]                              # m32(r_x) = (1 + b) e^{−b}
    for i in range(N):
        P[i] = out[U + i]
        Q[i] = 1.0 / out[U + i]
    T = xmap.size
    mx = wb[:T]                                     # m32(r_x) of every entry: a pass of
    for p in range(T):                              # look-ups, so that the next one is
        mx[p] = mu[xmap[p]]                         # plain arithmetic (vectorised)
    p = 0
    for i in range(N):
        m = N - i
        dy = DYp[0, p:p + m]
        mi = mx[p:p + m]
        o = A[p:p + m]
        yi, Pi, Qi = yc[i], P[i], Q[i]
        yj, Pj, Qj = yc[i:N], P[i:N], Q[i:N]
        for t in range(m):          # both factors computed, then selected: vectorises
            a = dy[t] * s_y
            ey_pos = Qi * Pj[t]
            ey_neg = Pi * Qj[t]
            ey = ey_pos if yi >= yj[t] else ey_neg
            o[t] = sf2 * (((1.0 + a) * ey) * mi[t])
        o[0] = sf2                                  # zero distance: σ_f² exactly
        p += m + 1                                  # and the border entry
    return True


#: Fewest training points for which :func:`_grid_entries` builds the training matrix. Its
#: extra passes and short per-row loops cost more than the exponentials they save on small
#: problems: one matrix on 1-D grids of 13 / 24 / 32 / 48 / 64 points took 1.32 / 1.24 /
#: 1.12 / 1.03 / 0.92 times the per-entry path's time (2-D grids of 16 / 36 / 49 / 64:
#: 1.34 / 1.07 / 0.94 / 0.86). Beam-1d (N = 13) is the per-entry path's: 15 % less time per
#: NLML pair and 12–18 % per mixture pair; beam-2d (N = 64) keeps the grid path.
GRID_MIN_POINTS = 40


@_jit
def _grid_space(DXp, N, on):
    """Buffers of :func:`_grid_entries`, ``(U, xmap, DXd, yc, hy, E)``; U = 0 (the grid
    path off) unless ``on``, N ≥ :data:`GRID_MIN_POINTS` and the x differences repeat
    enough."""
    d_x, T = DXp.shape
    xmap = np.empty(T, dtype=np.int64)
    DXd = np.empty((d_x, T))
    U = _distinct_x_diffs(DXp, xmap, DXd) if on and N >= GRID_MIN_POINTS else 0
    return (U, xmap, DXd, np.zeros(N), np.full(1, np.inf), np.empty((4, max(U, N))))


# ---------------------------------------------------------------------------------------
# Bordered training matrix and its Cholesky factor (packed upper storage)


@_jit
def _unpack_scales(theta, d_y, d_x, sy, sx):
    for k in range(d_y):
        sy[k] = SQRT3 * math.exp(-theta[1 + k])      # √3 / ℓ_y
    for k in range(d_x):
        sx[k] = SQRT3 * math.exp(-theta[1 + d_y + k])


@_jit
def _train_matrix(theta, DYp, DXp, z, sy, sx, W, A, U, Au, gather, G):
    """The bordered ``[[K_ff + σ_n² I, z], [zᵀ, 2 zᵀz/σ_n² + 1]]``, packed, into ``A``.

    The diagonal comes out of :func:`_matern_entries` as ``σ_f²`` (zero distance);
    the border entries are overwritten. With ``U < N`` distinct training rows
    (:func:`_distinct_rows`), ``DYp``/``DXp`` hold the differences of the distinct rows
    only (packed U × U): their entries go into ``Au`` and are copied to every entry of
    ``A`` by ``gather`` (replicates share their rows' entries, bit for bit). Otherwise,
    with one-dimensional y and x differences that repeat (``G[0] > 0``), the entries come
    from :func:`_grid_entries` when it applies.
    """
    N = z.size
    n = N + 1
    _unpack_scales(theta, sy.size, sx.size, sy, sx)
    if U < N:
        Tu = U * (U + 1) // 2
        _matern_entries(DYp, DXp, sy, sx, 2.0 * theta[0], W, Au[:Tu])
        for p in range(gather.size):
            A[p] = Au[gather[p]]
    elif not (G[0] > 0 and _grid_entries(theta, DYp, sy, sx, G, W, A)):
        _matern_entries(DYp, DXp, sy, sx, 2.0 * theta[0], W, A)
    sn2 = math.exp(2.0 * theta[theta.size - 1])
    zz = 0.0
    off = 0
    for i in range(N):
        A[off] += sn2
        A[off + N - i] = z[i]
        zz += z[i] * z[i]
        off += n - i
    A[off] = 2.0 * zz / sn2 + 1.0


#: Outcomes of :func:`_cholesky_rows` and :func:`_factor`.
FAILED, FACTORED, ABANDONED = 0, 1, 2
#: Fewest training points for which :func:`pair_range` checks its ``stop`` row by row (on
#: beam-1d's 13 the checks cost more than the rows they save: 1.45 → 1.56 µs per pair).
EARLY_STOP_ROWS = 24


#: The factor's rows are stored with this many spare columns past the last, and every row
#: update runs over a multiple of it: whole vector iterations, no remainder loop (beam-2d's
#: NLML, N = 64: ~10 % less time per pair, the same bits).
ROW_PAD = 16


@_jit
def _factor_rows(n):
    """An (n, n + :data:`ROW_PAD`) array for :func:`_cholesky_rows`."""
    return np.zeros((n, n + ROW_PAD))


@_jit
def _cholesky_rows(A, R, n, n_cov, jitter, stop, log_floor):
    """``RᵀR = A + jitter · I_{n_cov}`` for packed upper ``A`` (n × n), into the upper
    triangle of ``R`` (n, ≥ n + :data:`ROW_PAD`), one matrix row per array row.

    Row by row (left-looking, four earlier rows per pass: every update is a contiguous
    vector operation). Each update of row j runs over its n − j entries rounded up to a
    multiple of :data:`ROW_PAD`, so the loops have no scalar remainder. The extra entries
    are spare columns ≥ n, updated only from spare columns of earlier rows: they start
    as zeros (:func:`_factor_rows`) and stay 0 (NaN after a matrix with inf or NaN),
    and no entry of the factor ever reads them, so every entry gets the operations it
    would get without the padding, in the same order. Entries left of the diagonal are
    neither written nor read. Returns :data:`FAILED` at the first pivot that is not
    positive or is NaN (LAPACK ``potrf``'s failure test), else :data:`FACTORED`.

    With a finite ``stop``, ``A`` is a bordered ``[[K, z], [zᵀ, ·]]`` (``n_cov = n − 1``)
    and the factorisation is abandoned (:data:`ABANDONED`) after the first row ``j`` where
    ``½ Σ_{i≤j} R_{i,n−1}² + Σ_{i≤j} log R_ii + (n_cov − 1 − j) · log_floor > stop``.
    That is a lower bound of ``½ zᵀK⁻¹z + ½ log det K``: each later row adds a square and
    ``log R_ii ≥ log_floor`` when every conditional variance ``R_ii²`` is at least
    ``exp(2 log_floor)`` (the noise variance σ_n² bounds them from below).
    """
    check = stop < np.inf
    ww = 0.0
    logdet = 0.0
    prod = 1.0
    off = 0
    for i in range(n):                               # A's rows
        row = R[i, i:n]
        a = A[off:off + n - i]
        for t in range(n - i):
            row[t] = a[t]
        off += n - i
    for j in range(n):
        m = n - j
        mp = -(-m // ROW_PAD) * ROW_PAD
        rj = R[j, j:j + mp]
        if j < n_cov:
            rj[0] += jitter
        k = 0
        while k + 4 <= j:
            r0, r1, r2, r3 = R[k], R[k + 1], R[k + 2], R[k + 3]
            l0, l1, l2, l3 = r0[j], r1[j], r2[j], r3[j]
            v0 = r0[j:j + mp]
            v1 = r1[j:j + mp]
            v2 = r2[j:j + mp]
            v3 = r3[j:j + mp]
            for t in range(mp):
                rj[t] -= (l0 * v0[t] + l1 * v1[t]) + (l2 * v2[t] + l3 * v3[t])
            k += 4
        while k < j:
            rk = R[k]
            l0 = rk[j]
            v0 = rk[j:j + mp]
            for t in range(mp):
                rj[t] -= l0 * v0[t]
            k += 1
        piv = rj[0]
        if not piv > 0.0:
            return FAILED
        d = math.sqrt(piv)
        rj[0] = d
        inv = 1.0 / d
        for t in range(1, m):
            rj[t] *= inv
        if check and j < n_cov:                      # the bound of the docstring
            w = rj[m - 1]
            ww += w * w
            prod *= d
            if j % 4 == 3 or j == n_cov - 1:         # one log per four rows
                logdet += math.log(prod)
                prod = 1.0
                if 0.5 * ww + logdet + (n_cov - 1 - j) * log_floor > stop:
                    return ABANDONED
    return FACTORED


@_jit
def _factor(A, R, N, ladder, stop, log_floor):
    """Cholesky of the packed bordered matrix ``A`` into the rows of ``R``
    (:func:`_cholesky_rows`), with the jitter ladder.

    When the plain factorisation fails, ``ladder[t] × mean(diag K)`` (SPEC §3) is added
    to the N covariance diagonal entries (not to the border), step by step, until one
    works or is abandoned (``stop``, ``log_floor``: :func:`_cholesky_rows`). Returns
    ``(status, step)``: the step that worked, 0.0 without jitter, the last one tried on
    failure, the one abandoned.
    """
    n = N + 1
    scale = 0.0
    step = 0.0
    for t in range(-1, ladder.size):                 # t = −1: the plain factorisation
        if t == 0:
            off = 0
            for i in range(N):
                scale += A[off]
                off += n - i
            scale /= N
        step = 0.0 if t < 0 else ladder[t]
        status = _cholesky_rows(A, R, n, N, step * scale, stop, log_floor)
        if status != FAILED:
            return status, step
    return FAILED, step


@_jit
def _nlml_from_factor(R, N):
    """Eq. 9 from the bordered factor: ``½ Σ (L⁻¹z)² + Σ log L_ii + (N/2) log 2π``."""
    ww = 0.0
    logdet = 0.0
    for i in range(N):
        w = R[i, N]
        ww += w * w
        logdet += math.log(R[i, i])
    return 0.5 * ww + logdet + 0.5 * N * LOG_2PI


# ---------------------------------------------------------------------------------------
# Prediction


@_jit
def _moments(R, N, theta, sy, sx, DYc, DXc, W, Vbuf, Lt, mean, var, S1):
    """Predictive mean and latent variance (Eq. 7) of one factorised pair.

    ``R`` is the bordered factor (:func:`_cholesky_rows`), ``DYc``/``DXc`` (n_tiles, d,
    N·tile) the tiled training-minus-test differences (:func:`_tiled_diffs`), ``Lt`` an
    (N, N + 1) scratch.
    ``S1 = (half_ranges, y_train, y_test, x_train, x_test, Etr, Ete)`` serves the separable
    one-dimensional case (:func:`_cross_1d`): centred inputs and their half ranges
    ``[h_y, h_x]`` (NaN when y or x is not one-dimensional). Writes ``mean`` and ``var`` (M,).
    """
    M = mean.size
    log_sf2 = 2.0 * theta[0]
    sf2 = math.exp(log_sf2)
    half, ytr, yte, xtr, xte, Etr, Ete = S1
    separable = sy[0] * half[0] <= SEPARABLE_LIMIT and sx[0] * half[1] <= SEPARABLE_LIMIT \
        if sy.size == 1 and sx.size == 1 else False
    if separable:
        _signed_exps(ytr, sy[0], xtr, sx[0], Etr, W)
    # L = Rᵀ by rows, with L⁻¹z in the last column (contiguous loops below)
    for k in range(N):
        for j in range(k, N):
            Lt[j, k] = R[k, j]
        Lt[k, N] = R[k, N]
    tile = DXc.shape[2] // N
    for m0 in range(0, M, tile):
        nt = min(tile, M - m0)
        V = Vbuf[:N * nt]
        if separable:
            _signed_exps(yte[m0:m0 + nt], sy[0], xte[m0:m0 + nt], sx[0], Ete, W)
            _cross_1d(DYc[m0 // tile], DXc[m0 // tile], sy, sx, sf2, Etr, Ete, V, N, nt)
        else:
            _matern_entries(DYc[m0 // tile], DXc[m0 // tile], sy, sx, log_sf2, W, V)
        mo = mean[m0:m0 + nt]
        vo = var[m0:m0 + nt]
        mo[:] = 0.0
        vo[:] = 0.0
        for i in range(N):                    # V = L⁻¹ K_f* row by row, 4 rows per pass
            vi = V[i * nt:(i + 1) * nt]
            li = Lt[i]
            k = 0
            while k + 4 <= i:
                l0, l1, l2, l3 = li[k], li[k + 1], li[k + 2], li[k + 3]
                v0 = V[k * nt:(k + 1) * nt]
                v1 = V[(k + 1) * nt:(k + 2) * nt]
                v2 = V[(k + 2) * nt:(k + 3) * nt]
                v3 = V[(k + 3) * nt:(k + 4) * nt]
                for t in range(nt):
                    vi[t] -= (l0 * v0[t] + l1 * v1[t]) + (l2 * v2[t] + l3 * v3[t])
                k += 4
            while k < i:
                l0 = li[k]
                v0 = V[k * nt:(k + 1) * nt]
                for t in range(nt):
                    vi[t] -= l0 * v0[t]
                k += 1
            inv = 1.0 / li[i]
            w = li[N]
            for t in range(nt):
                v = vi[t] * inv
                vi[t] = v
                mo[t] += v * w                        # mean = Vᵀ L⁻¹z
                vo[t] += v * v
        for t in range(nt):
            vo[t] = max(sf2 - vo[t], 0.0)             # k** − Σ V²


@_jit
def _separable_space(X, Xstar, d_y, nt):
    """Buffers of the separable path, ``(half, y_train, y_test, x_train, x_test, Etr, Ete)``,
    with x centred already; ``half = [h_y, h_x]``, NaN (never separable) unless y and x are
    one-dimensional."""
    N, d_x = X.shape
    M = Xstar.shape[0]
    half = np.full(2, np.nan)
    xtr, xte = np.zeros(N), np.zeros(M)
    if d_y == 1 and d_x == 1 and N > 0:
        half[1] = _centred(X[:, 0], Xstar[:, 0], xtr, xte)
    return (half, np.zeros(N), np.zeros(M), xtr, xte, np.empty((4, N)), np.empty((4, nt)))


@_jit
def _separable_y(S1, Yj, Ys):
    """Centre the one-dimensional y of a new (training, test) pair of rows into ``S1``."""
    half, ytr, yte = S1[0], S1[1], S1[2]
    if Yj.shape[1] == 1 and not math.isnan(half[1]):
        half[0] = _centred(Yj[:, 0], Ys[:, 0], ytr, yte)


# ---------------------------------------------------------------------------------------
# Public batched kernels


#: Modes of :func:`pair_range`.
NLML, PREDICT, MIXTURE = 0, 1, 2


@_jit
def pair_range(mode, b0, b1, theta, Y, y_index, X, z, Ystar, s_index, ystar_out, weight,
               Xstar, cz, cd, ladder, stop, nlml, mean, var, noise, jitter, failed, dropped,
               acc):
    """Pairs ``b0 ≤ b < b1`` of ``(theta[b], Y[y_index[b]])``: NLML (Eq. 9) and, by mode, more.

    One serial kernel (the GIL released) for the three jobs; :mod:`mdcore.compiled` runs
    ranges of pairs on its threads. One kernel keeps the one-off compile time down.

    Parameters
    ----------
    mode : int
        :data:`NLML`: the NLML only. :data:`PREDICT`: also the predictive mean and latent
        variance (Eq. 7) at ``(Ystar[s_index[b]], Xstar)``. :data:`MIXTURE`: also the
        weighted mixture sums of scenarios 2–3 (Eq. 13/15) about a reference component,
        added to ``acc`` (4, M): with ``w = weight[b]``, mean ``μ``, latent variance ``v``,
        noise ``σ_n²``, ``y* = ystar_out[s_index[b]]``, ``dz = μ − cz`` and
        ``dd = μ − y* − cd``::

            acc[0] += w dz,  acc[1] += w dd,  acc[2] += w (v + σ_n² + dz²),
            acc[3] += w (v + dd²)

        leaving out (``dropped``) pairs that fail to factorise or have non-finite moments.
    theta : (B, P); Y : (B_y, N, d_y); y_index : (B,) int64; X : (N, d_x); z : (N,)
    Ystar : (B_s, M, d_y); s_index : (B,) int64; ystar_out : (B_s, M); weight : (B,)
    Xstar : (M, d_x); cz, cd : (M,); ladder : (L,) relative jitter steps
        Inputs a mode does not use may be empty (M = 0 for the NLML).
    stop : float
        :data:`NLML` mode: abandon a pair as soon as its NLML is bound to exceed ``stop``:
        before its entries when ``½ zᵀz / λ_max + N log σ_n`` (+ ``(N/2) log 2π``) does,
        with ``λ_max ≤ N σ_f² + σ_n²`` plus the largest jitter, then during the
        factorisation (:func:`_cholesky_rows`); ``inf`` never does (the other modes pass
        ``inf``).
    nlml, noise, jitter, failed, dropped : (B,); mean, var : (B, M) for PREDICT, else any
        Outputs, written at the pairs of the range. ``jitter[b]`` is the ladder step that
        worked (0 if none was needed; for a failed pair the last step tried); a failed pair
        has NLML ``+inf`` and NaN moments. An abandoned pair has NLML ``+inf``, jitter 0,
        and ``dropped`` but not ``failed``.
    """
    N, d_x = X.shape
    d_y = Y.shape[2]
    M = Xstar.shape[0] if mode != NLML else 0
    n = N + 1
    T = n * (n + 1) // 2
    nt = _tile(N, M)
    n_tiles = (M + nt - 1) // nt
    DXp = np.empty((d_x, T))
    _packed_diffs(X, n, DXp)
    DXc = np.empty((n_tiles, d_x, N * nt))
    _tiled_diffs(X, Xstar[:M], DXc)
    A = np.empty(T)
    R = _factor_rows(n)
    DYp = np.empty((d_y, T))
    rep = np.empty(N, dtype=np.int64)     # replicated inputs (_distinct_rows)
    of = np.empty(N, dtype=np.int64)
    DXu = np.empty((d_x, T))
    Au = np.empty(T)
    gather = np.empty(T, dtype=np.int64)
    U = N
    G = _grid_space(DXp, N, d_y == 1)
    DYc = np.empty((n_tiles, d_y, N * nt))
    sy = np.empty(d_y)
    sx = np.empty(d_x)
    W = _workspace(max(T, N * nt, 2 * max(N, nt)))
    Vbuf = np.empty(N * nt)
    Lt = np.empty((N, n))
    S1 = _separable_space(X, Xstar[:M], d_y, nt)
    mu = np.empty(M)
    v = np.empty(M)
    a0, a1, a2, a3 = acc[0], acc[1], acc[2], acc[3]
    last, cross_j, cross_s = -1, -1, -1
    # the stop as a bound on ½ zᵀK⁻¹z + ½ log det K, checked during the factorisation
    # where that pays (N ≥ EARLY_STOP_ROWS), else on the NLML at the end
    early = stop - 0.5 * N * LOG_2PI if N >= EARLY_STOP_ROWS else np.inf
    zz = 0.0
    for i in range(N):
        zz += z[i] * z[i]
    top = 0.0                                         # the ladder's largest step
    for t in range(ladder.size):
        top = max(top, ladder[t])
    for b in range(b0, b1):
        th = theta[b]
        noise[b] = math.exp(2.0 * th[th.size - 1])
        jitter[b] = 0.0
        failed[b] = False
        dropped[b] = False
        if stop < np.inf:
            # Before any entry: ½ zᵀK⁻¹z ≥ ½ zᵀz / λ_max and ½ log det K ≥ N log σ_n, with
            # λ_max ≤ N σ_f² + σ_n² (no entry exceeds σ_f²) plus the ladder's largest
            # jitter, top × mean diag. On shear-5 this leaves out half the pairs or more.
            sf2 = math.exp(2.0 * th[0])
            lam = N * sf2 + noise[b] + top * (sf2 + noise[b])
            if 0.5 * zz / lam + N * th[th.size - 1] + 0.5 * N * LOG_2PI > stop:
                dropped[b] = True
                nlml[b] = np.inf
                continue
        j = y_index[b]
        if j != last:
            U = _distinct_rows(Y[j], X, rep, of)
            if U < N:
                _distinct_diffs(Y[j], X, rep, of, U, n, DYp, DXu, gather)
            else:
                _packed_diffs(Y[j], n, DYp)
                if G[0] > 0:
                    G[4][0] = _centred(Y[j][:, 0], Y[j][:0, 0], G[3], G[3][:0])
            last = j
        _train_matrix(th, DYp, DXu if U < N else DXp, z, sy, sx, W, A, U, Au, gather, G)
        status, step = _factor(A, R, N, ladder, early, th[th.size - 1])
        if status == ABANDONED:                       # NLML > stop: weight below the cut
            dropped[b] = True
            nlml[b] = np.inf
            continue
        jitter[b] = step
        if status == FAILED:
            failed[b] = True
            dropped[b] = True
            nlml[b] = np.inf
            if mode == PREDICT:
                mean[b, :] = np.nan
                var[b, :] = np.nan
            continue
        nlml[b] = _nlml_from_factor(R, N)
        if mode == NLML:
            if nlml[b] > stop:                        # abandoned at the end
                jitter[b] = 0.0
                dropped[b] = True
                nlml[b] = np.inf
            continue
        s = s_index[b]
        if s != cross_s or j != cross_j:
            _tiled_diffs(Y[j], Ystar[s], DYc)
            _separable_y(S1, Y[j], Ystar[s])
            cross_j, cross_s = j, s
        if mode == PREDICT:
            _moments(R, N, th, sy, sx, DYc, DXc, W, Vbuf, Lt, mean[b], var[b], S1)
            continue
        _moments(R, N, th, sy, sx, DYc, DXc, W, Vbuf, Lt, mu, v, S1)
        finite = True
        for m in range(M):
            finite &= math.isfinite(mu[m]) and math.isfinite(v[m])
        if not finite:
            dropped[b] = True
            continue
        w = weight[b]
        sn2 = noise[b]
        ys = ystar_out[s]
        for m in range(M):
            dz = mu[m] - cz[m]
            dd = mu[m] - ys[m] - cd[m]
            a0[m] += w * dz
            a1[m] += w * dd
            a2[m] += w * (v[m] + sn2 + dz * dz)             # total variance of z*
            a3[m] += w * (v[m] + dd * dd)                   # latent variance goes to δ
