"""Simulator of the worked example: a simply supported steel beam under a central load.

Deflection at position x [m] of a beam of span L = 2 m, second moment of area
I = 8.33e-6 m⁴ (a 100 × 100 mm box, 10 mm wall) under P = 20 kN at mid-span
(Euler–Bernoulli, x ≤ L/2; symmetric beyond):

    w(x) = P x (3 L² − 4 x²) / (48 E I) + w₀

θ = (E [GPa], w₀ [mm]): Young's modulus and the dial gauges' zero offset.
"""

import numpy as np

SPAN, SECOND_MOMENT, LOAD = 2.0, 8.33e-6, 20e3


def deflection(X, theta):
    """simulate(X, theta) -> (n_theta, N, 1) deflections [mm] at X (N, 1) [m]."""
    X = np.asarray(X, dtype=float)
    theta = np.atleast_2d(np.asarray(theta, dtype=float))
    x = np.minimum(X[:, 0], SPAN - X[:, 0])                     # symmetric about mid-span
    shape = LOAD * x * (3 * SPAN**2 - 4 * x**2) / (48 * SECOND_MOMENT)     # [N m³ / m⁴]
    E = theta[:, :1] * 1e9
    return (1e3 * shape[None, :] / E + theta[:, 1:2])[..., None]
