"""Tip deflection of a cracked cantilever (docs/cases.md, paper Eq. 17).

Christides–Barr crack stiffness::

    EI(x) = E I₀ / (1 + C exp(−2α|x − x_c|/t)),   C = (I₀ − I_c)/I_c,
    I₀ = w t³/12,   I_c = w (t − l_cr)³/12

Unit-load method for a tip load P::

    δ_tip = ∫₀ˡ P (l − x)² / EI(x) dx
          = P/(E I₀) [ l³/3 + C (∫₀^{x_c} (l − x)² e^{−β(x_c − x)} dx
                               + ∫_{x_c}^{l} (l − x)² e^{−β(x − x_c)} dx) ],   β = 2α/t

Each half, split at the crack (the kink of |x − x_c|), is integrated in closed form.
"""

from __future__ import annotations

import numpy as np

from .._validation import as_float_array


def tip_deflection(crack_location, crack_length, E, *, length: float = 1.0, width: float = 0.5,
                   thickness: float = 0.1, load: float = 10e3, alpha: float = 0.667) -> np.ndarray:
    """Tip deflection of a cracked cantilever under a tip load, in millimetres.

    Parameters
    ----------
    crack_location : array_like, m
        Distance ``x_c`` of the crack from the clamped end, in ``[0, length]``.
    crack_length : array_like, m
        Crack depth ``l_cr`` in ``[0, thickness)``.
    E : array_like, Pa
        Young's modulus, positive.
    length, width, thickness : float, m
        Beam dimensions ``l``, ``w``, ``t``.
    load : float, N
        Tip load ``P``.
    alpha : float
        Christides–Barr constant.

    Returns
    -------
    ndarray, mm
        Broadcast shape of the three array arguments.

    Examples
    --------
    >>> round(float(tip_deflection(0.5, 0.0, 68e9)), 5)    # uncracked: P l³/(3 E I₀)
    1.17647
    """
    xc, lc, E = (as_float_array(v, name, allow_empty=True) for v, name in
                 ((crack_location, "crack_location"), (crack_length, "crack_length"), (E, "E")))
    if np.any(E <= 0):
        raise ValueError(f"E must be positive (Pa); received minimum {E.min()!r}.")
    if np.any(lc < 0) or np.any(lc >= thickness):
        raise ValueError(f"crack_length must lie in [0, thickness = {thickness}) m; received "
                         f"range [{lc.min()!r}, {lc.max()!r}]. Convert mm to m if needed.")
    if np.any(xc < 0) or np.any(xc > length):
        raise ValueError(f"crack_location must lie in [0, length = {length}] m; received "
                         f"range [{xc.min()!r}, {xc.max()!r}].")
    l, t = length, thickness
    I0 = width * t**3 / 12.0
    Ic = width * (t - lc) ** 3 / 12.0
    C = (I0 - Ic) / Ic
    beta = 2.0 * alpha / t
    a = l - xc                       # distance from crack to tip
    # ∫_{x_c}^{l} (l−x)² e^{−β(x−x_c)} dx = a²/β − 2a/β² + 2(1 − e^{−βa})/β³
    right = a**2 / beta - 2 * a / beta**2 - 2 * np.expm1(-beta * a) / beta**3
    # ∫_0^{x_c} (l−x)² e^{−β(x_c−x)} dx, s = x_c − x:  ∫_0^{x_c} (a+s)² e^{−βs} ds
    left = (a**2 / beta + 2 * a / beta**2 + 2 / beta**3
            - np.exp(-beta * xc) * (l**2 / beta + 2 * l / beta**2 + 2 / beta**3))
    return 1e3 * load / (E * I0) * (l**3 / 3.0 + C * (left + right))
