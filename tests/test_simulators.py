"""Simulators against closed forms, independent quadrature and docs/cases.md check values."""

import numpy as np
import pytest
from scipy.integrate import quad

from mdcore.simulators import natural_frequencies, tip_deflection

L, W, T, P, ALPHA = 1.0, 0.5, 0.1, 10e3, 0.667


def quad_deflection(xc, lcr, E):
    """Unit-load integral by adaptive quadrature, breakpoint at the crack (mm)."""
    I0 = W * T**3 / 12
    Ic = W * (T - lcr) ** 3 / 12
    C = (I0 - Ic) / Ic

    def integrand(x):
        EI = E * I0 / (1 + C * np.exp(-2 * ALPHA * abs(x - xc) / T))
        return P * (L - x) ** 2 / EI

    val, _ = quad(integrand, 0.0, L, points=[xc], epsabs=0, epsrel=1e-13, limit=200)
    return 1e3 * val


@pytest.mark.parametrize("E", [50e9, 68e9, 71e9, 90e9])
def test_uncracked_beam_is_cantilever_formula(E):
    I0 = W * T**3 / 12
    want = 1e3 * P * L**3 / (3 * E * I0)
    got = tip_deflection(np.linspace(0, 1, 7), 0.0, E)
    np.testing.assert_allclose(got, want, rtol=1e-9)


def test_spec_reference_values():
    want = [2.3066, 2.2636, 2.1458, 2.0062, 1.8664, 1.7355, 1.6170, 1.5125, 1.4226, 1.3474,
            1.2871, 1.2414, 1.2099]
    got = tip_deflection(np.linspace(0.1, 0.9, 13), 0.038, 68e9)
    np.testing.assert_allclose(got, want, atol=1e-4)


def test_beam_matches_adaptive_quadrature(rng):
    xc = rng.uniform(0.0, 1.0, 12)
    lcr = rng.uniform(0.0, 0.06, 12)
    E = rng.uniform(50e9, 90e9, 12)
    got = tip_deflection(xc, lcr, E)
    want = [quad_deflection(*args) for args in zip(xc, lcr, E)]
    np.testing.assert_allclose(got, want, rtol=1e-8)


def test_beam_is_vectorised_over_samples_and_inputs():
    x = np.linspace(0.1, 0.9, 213)
    got = tip_deflection(x[None, :], np.full((1000, 1), 0.03), np.full((1000, 1), 70e9))
    assert got.shape == (1000, 213)


def test_beam_bad_input():
    with pytest.raises(ValueError, match=r"crack_length must lie in \[0, thickness"):
        tip_deflection(0.5, 38.0, 68e9)            # mm passed instead of m
    with pytest.raises(ValueError, match="E must be positive"):
        tip_deflection(0.5, 0.01, -1.0)
    with pytest.raises(ValueError, match="crack_location contains 1 NaN"):
        tip_deflection(np.nan, 0.01, 68e9)


def test_single_storey_is_sqrt_k_over_m():
    class OneStorey:
        n_storeys = 1
        plate = (0.35, 0.25, 0.02)
        column_width, column_thickness, storey_height, columns_per_storey = 0.05, 0.01, 0.3, 4

    E, nu, rho = 71e9, 0.33, 2770.0
    E1 = E / (1 - nu**2)
    I = 0.05 * 0.01**3 / 12
    G = E / (2 * (1 + nu))
    kappa = 10 * (1 + nu) / (12 + 11 * nu)
    Phi = 12 * E1 * I / (kappa * G * 0.05 * 0.01 * 0.3**2)
    k = 4 * 12 * E1 * I / (0.3**3 * (1 + Phi))
    m = rho * (0.35 * 0.25 * 0.02 + 0.5 * 4 * 0.05 * 0.01 * 0.3) + 0.2
    got = natural_frequencies(E, nu, rho, 0.2, added_mass_floor=1, geometry=OneStorey)
    assert got[0] == pytest.approx(np.sqrt(k / m) / (2 * np.pi), rel=1e-12)


def test_nominal_frequencies_match_spec():
    got = natural_frequencies(71e9, 0.33, 2770.0)
    np.testing.assert_allclose(got, [13.93, 40.55, 63.57, 81.12, 92.00], atol=0.05)


def test_real_structure_matches_spec_and_rocking_lowers_first_mode_most():
    real = natural_frequencies(70e9, 0.33, 2700.0, extra_floor_mass=0.03, rocking_stiffness=2.3e6)
    np.testing.assert_allclose(real, [13.34, 40.49, 63.69, 81.35, 92.29], atol=0.05)
    fixed = natural_frequencies(70e9, 0.33, 2700.0, extra_floor_mass=0.03)
    drop = (fixed - real) / fixed
    assert np.all(drop > 0) and np.argmax(drop) == 0


def test_frequency_scaling_laws(rng):
    base = natural_frequencies(71e9, 0.33, 2770.0, 0.2)
    # With ν fixed and no added mass, frequencies scale exactly as sqrt(E) and 1/sqrt(ρ).
    for s in rng.uniform(0.5, 2.0, 3):
        np.testing.assert_allclose(natural_frequencies(s * 71e9, 0.33, 2770.0, 0.0),
                                   np.sqrt(s) * natural_frequencies(71e9, 0.33, 2770.0),
                                   rtol=1e-12)
        np.testing.assert_allclose(natural_frequencies(71e9, 0.33, s * 2770.0, 0.0),
                                   natural_frequencies(71e9, 0.33, 2770.0) / np.sqrt(s),
                                   rtol=1e-12)
    assert base.shape == (5,)


def test_shear_building_batched_shapes_and_errors():
    out = natural_frequencies(np.full((4, 1), 71e9), 0.33, 2770.0, np.linspace(0, 0.5, 6))
    assert out.shape == (4, 6, 5) and np.all(np.diff(out, axis=-1) > 0)
    with pytest.raises(ValueError, match=r"nu must lie in \(-1, 0.5\)"):
        natural_frequencies(71e9, 0.7, 2770.0)
    with pytest.raises(ValueError, match="added_mass must be non-negative"):
        natural_frequencies(71e9, 0.33, 2770.0, -0.1)
    with pytest.raises(ValueError, match="rho contains 1 NaN"):
        natural_frequencies(71e9, 0.33, np.nan)
    assert natural_frequencies(np.empty(0), 0.33, 2770.0).shape == (0, 5)
