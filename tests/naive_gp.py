"""Deliberately naive GP reference: explicit kernel loops and scipy's cho_factor.

Nothing here is vectorised or shared with ``mdcore._gp``; it is the oracle the batched core
is compared against (GPflow's ``tests/.../reference.py`` pattern).
"""

import math

import numpy as np
from scipy.linalg import cho_factor, cho_solve


def matern32(r):
    return (1.0 + math.sqrt(3.0) * r) * math.exp(-math.sqrt(3.0) * r)


def unpack(log_params, d_y, d_x):
    sf = math.exp(log_params[0])
    ly = [math.exp(v) for v in log_params[1:1 + d_y]]
    lx = [math.exp(v) for v in log_params[1 + d_y:1 + d_y + d_x]]
    sn = math.exp(log_params[1 + d_y + d_x])
    return sf, ly, lx, sn


def k(log_params, ya, xa, yb, xb):
    d_y, d_x = len(ya), len(xa)
    sf, ly, lx, _ = unpack(log_params, d_y, d_x)
    ry = math.sqrt(sum((ya[d] - yb[d]) ** 2 / ly[d] ** 2 for d in range(d_y)))
    rx = math.sqrt(sum((xa[d] - xb[d]) ** 2 / lx[d] ** 2 for d in range(d_x)))
    return sf * sf * matern32(ry) * matern32(rx)


def cov(log_params, Ya, Xa, Yb, Xb):
    out = np.empty((len(Xa), len(Xb)))
    for i in range(len(Xa)):
        for j in range(len(Xb)):
            out[i, j] = k(log_params, Ya[i], Xa[i], Yb[j], Xb[j])
    return out


def nlml(log_params, Y, X, z):
    N = len(z)
    sn = math.exp(log_params[-1])
    K = cov(log_params, Y, X, Y, X) + sn * sn * np.eye(N)
    c, low = cho_factor(K, lower=True)
    alpha = cho_solve((c, low), z)
    return 0.5 * z @ alpha + np.sum(np.log(np.diag(c))) + 0.5 * N * math.log(2 * math.pi)


def predict(log_params, Y, X, z, Ys, Xs):
    N = len(z)
    sn = math.exp(log_params[-1])
    K = cov(log_params, Y, X, Y, X) + sn * sn * np.eye(N)
    Ks = cov(log_params, Ys, Xs, Y, X)
    cf = cho_factor(K, lower=True)
    mean = Ks @ cho_solve(cf, z)
    var = np.array([k(log_params, Ys[i], Xs[i], Ys[i], Xs[i]) - Ks[i] @ cho_solve(cf, Ks[i])
                    for i in range(len(Xs))])
    return mean, var, sn * sn
