"""Natural frequencies of a five-storey shear building (docs/cases.md).

Rigid floors (aluminium plates 350 × 250 × 20 mm) on four columns per storey
(50 mm wide × 10 mm thick in the bending direction, 300 mm high). Storey stiffness with
Timoshenko shear correction::

    k = 4 · 12 E′ I / (L³ (1 + Φ)),  E′ = E/(1 − ν²),  I = b h³/12,
    Φ = 12 E′ I / (κ G A L²),  G = E/(2(1 + ν)),  κ = 10(1 + ν)/(12 + 11ν)

Floor mass is ρ × plate volume plus half of the columns above and below it. Frequencies
solve the generalised eigenproblem ``K φ = ω² M φ``. A rocking base spring ``k_θ`` adds
the flexibility ``h hᵀ / k_θ`` (``h_j = j L``); the stiffness of ``F = K⁻¹ + h hᵀ/k_θ``
is formed without any inverse by Sherman–Morrison:
``F⁻¹ = K − (K h)(K h)ᵀ / (k_θ + hᵀ K h)``.
"""

from __future__ import annotations

import numpy as np

from .._validation import as_float_array


class ShearBuilding:
    """Geometry of the shear building, in metres (defaults are docs/cases.md)."""

    n_storeys = 5
    plate = (0.350, 0.250, 0.020)       # floor plate, m
    column_width = 0.050                # b, m
    column_thickness = 0.010            # h (bending direction), m
    storey_height = 0.300               # L, m
    columns_per_storey = 4


def natural_frequencies(E, nu, rho, added_mass=0.0, *, added_mass_floor: int = 4,
                        extra_floor_mass: float = 0.0, rocking_stiffness: float | None = None,
                        geometry: type[ShearBuilding] = ShearBuilding) -> np.ndarray:
    """Natural frequencies of the shear building, in Hz, batched over all arguments.

    Parameters
    ----------
    E, nu, rho : array_like
        Young's modulus (Pa), Poisson's ratio in (-1, 0.5), density (kg/m³).
    added_mass : array_like, kg
        Mass added to floor ``added_mass_floor`` (1-based).
    extra_floor_mass : float, kg
        Mass added to every floor (the "real" structure's sensors).
    rocking_stiffness : float, N·m/rad, optional
        Rotational base spring ``k_θ``; ``None`` means a fixed base.

    Returns
    -------
    ndarray of shape (..., n_storeys), Hz
        Ascending frequencies; ``...`` is the broadcast shape of E, nu, rho, added_mass.

    Examples
    --------
    >>> np.round(natural_frequencies(71e9, 0.33, 2770.0), 2)[:2]
    array([13.93, 40.55])
    """
    E, nu, rho, m_add = (as_float_array(v, name, allow_empty=True) for v, name in
                         ((E, "E"), (nu, "nu"), (rho, "rho"), (added_mass, "added_mass")))
    if np.any(E <= 0) or np.any(rho <= 0):
        raise ValueError("E and rho must be positive (Pa, kg/m³); received minimum "
                         f"E = {E.min()!r}, rho = {rho.min()!r}.")
    if np.any(nu <= -1) or np.any(nu >= 0.5):
        raise ValueError(f"nu must lie in (-1, 0.5); received range [{nu.min()!r}, {nu.max()!r}].")
    if np.any(m_add < 0):
        raise ValueError(f"added_mass must be non-negative (kg); received minimum {m_add.min()!r}.")
    g = geometry
    n = g.n_storeys
    if not 1 <= added_mass_floor <= n:
        raise ValueError(f"added_mass_floor must be in 1..{n}; received {added_mass_floor}.")
    shape = np.broadcast_shapes(E.shape, nu.shape, rho.shape, m_add.shape)
    E, nu, rho, m_add = (np.broadcast_to(a, shape) for a in (E, nu, rho, m_add))

    b, h, L = g.column_width, g.column_thickness, g.storey_height
    E1 = E / (1.0 - nu**2)
    I = b * h**3 / 12.0
    G = E / (2.0 * (1.0 + nu))
    kappa = 10.0 * (1.0 + nu) / (12.0 + 11.0 * nu)
    Phi = 12.0 * E1 * I / (kappa * G * b * h * L**2)
    k = g.columns_per_storey * 12.0 * E1 * I / (L**3 * (1.0 + Phi))      # (...,)

    # Tridiagonal storey stiffness: storey j connects floor j-1 (ground for j = 1) to floor j.
    T = 2.0 * np.eye(n) - np.eye(n, k=1) - np.eye(n, k=-1)
    T[-1, -1] = 1.0
    K = k[..., None, None] * T

    plate_mass = rho * np.prod(g.plate)
    storey_columns = rho * g.columns_per_storey * b * h * L
    m = np.broadcast_to((plate_mass + storey_columns)[..., None], shape + (n,)).copy()
    m[..., -1] -= 0.5 * storey_columns            # the top floor has no columns above it
    m += extra_floor_mass
    m[..., added_mass_floor - 1] += m_add

    if rocking_stiffness is not None:
        if rocking_stiffness <= 0:
            raise ValueError(f"rocking_stiffness must be positive (N·m/rad); received "
                             f"{rocking_stiffness!r}.")
        hvec = L * np.arange(1, n + 1)
        Kh = K @ hvec
        denom = (rocking_stiffness + Kh @ hvec)[..., None, None]
        K = K - Kh[..., :, None] * Kh[..., None, :] / denom

    s = 1.0 / np.sqrt(m)
    A = s[..., :, None] * K * s[..., None, :]     # M^{-1/2} K M^{-1/2}, symmetric
    omega2 = np.linalg.eigvalsh(A)
    return np.sqrt(np.maximum(omega2, 0.0)) / (2.0 * np.pi)
