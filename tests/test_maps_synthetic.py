"""Synthetic fields: random-field statistics, dipole and point-mass fields against closed forms, hallway map."""

from __future__ import annotations

import numpy as np
import pytest

from magnav_ins.core.errors import InputError
from magnav_ins.core.types import FieldKind
from magnav_ins.maps import synthetic as syn


def test_random_field_std_and_correlation_length():
    rng = np.random.default_rng(42)
    ell, d = 50.0, 10.0
    f = syn.gaussian_random_field((400, 500), d, ell, 3.0, rng)
    assert f.shape == (400, 500)
    assert f.std() == pytest.approx(3.0, rel=0.08)
    # squared-exponential covariance: rho(l) = exp(-1/2), rho(2 l) = exp(-2), along both axes
    for axis in (0, 1):
        assert syn.empirical_correlation(f, 5, axis) == pytest.approx(np.exp(-0.5), abs=0.05)
        assert syn.empirical_correlation(f, 10, axis) == pytest.approx(np.exp(-2.0), abs=0.05)


def test_random_field_reproducible_and_components_independent():
    a = syn.gaussian_random_field((64, 80), (2.0, 3.0), 10.0, 1.0, np.random.default_rng(7), components=3)
    b = syn.gaussian_random_field((64, 80), (2.0, 3.0), 10.0, 1.0, np.random.default_rng(7), components=3)
    np.testing.assert_array_equal(a, b)
    assert a.shape == (64, 80, 3)
    assert abs(np.corrcoef(a[..., 0].ravel(), a[..., 1].ravel())[0, 1]) < 0.3
    with pytest.raises(InputError, match="correlation_length_m"):
        syn.gaussian_random_field((10, 10), 1.0, -1.0, 1.0, np.random.default_rng(0))


def test_dipole_field_on_axis_and_equator():
    m = 1e6  # A m^2, pointing north
    r = 100.0
    b_axis = syn.dipole_field_ned([[r, 0.0, 0.0]], [0.0, 0.0, 0.0], [m, 0.0, 0.0])[0]
    b_eq = syn.dipole_field_ned([[0.0, r, 0.0]], [0.0, 0.0, 0.0], [m, 0.0, 0.0])[0]
    k = 1e-7 * m / r**3 * 1e9  # mu0/4pi m / r^3 in nT
    np.testing.assert_allclose(b_axis, [2 * k, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(b_eq, [-k, 0.0, 0.0], atol=1e-12)
    # induced dipole at the pole seen straight above: dT = 2 k (field and moment both down)
    dt = syn.dipole_total_field_anomaly([[0.0, 0.0, -r]], [0.0, 0.0, 0.0], [0.0, 0.0, m], [0.0, 0.0, 1.0])
    assert dt[0] == pytest.approx(2 * k)
    with pytest.raises(InputError):
        syn.dipole_field_ned([[0.0, 0.0, 0.0]], [0.0, 0.0, 0.0], [m, 0.0, 0.0])


def test_direction_ned():
    np.testing.assert_allclose(syn.direction_ned(np.pi / 2, 0.3), [0.0, 0.0, 1.0], atol=1e-15)
    np.testing.assert_allclose(syn.direction_ned(0.0, np.pi / 2), [0.0, 1.0, 0.0], atol=1e-15)


def test_point_mass_gravity():
    mass, r = 1e12, 500.0
    g = syn.point_mass_gravity_mgal([[0.0, 0.0, -r], [r, 0.0, 0.0]], [0.0, 0.0, 0.0], mass)
    assert g[0] == pytest.approx(6.67430e-11 * mass / r**2 * 1e5)  # straight above: full attraction, down
    assert g[1] == pytest.approx(0.0, abs=1e-12)  # level with the mass: horizontal attraction only


def test_hallway_map_matches_storms_description():
    m = syn.hallway_map(np.random.default_rng(3))
    assert m.kind is FieldKind.VECTOR_FIELD_NT and m.frame == "local"
    assert m.spacing_m == pytest.approx((0.381, 0.381))
    inside = np.isfinite(m.values[..., 0])
    assert abs(int(inside.sum()) - 930) <= 20  # Storms sec. 3.2.1: 930 grid points
    # L shape: the corner away from both hallways is empty, the far end of the side hallway is mapped
    assert not inside[0, -1] and inside[-1, -1] and inside[0, 0]
    mean_mg = np.nanmean(m.values, axis=(0, 1)) / 100.0
    np.testing.assert_allclose(mean_mg, [40.0, 100.0, 230.0], atol=8.0)
    # Table 4.1 centre line at 1.145 m is inside the main hallway
    v = m.value_ne(np.array([5.0, 20.0]), np.array([1.145, 1.145]))
    assert np.all(np.isfinite(v))
