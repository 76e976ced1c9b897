"""Reference fields: IGRF against published test values, gravity disturbance against boule."""

from __future__ import annotations

import datetime as dt

import numpy as np
import pytest

from magnav_ins.core.errors import InputError
from magnav_ins.core.units import DEG_TO_RAD
from magnav_ins.maps import reference as ref


def test_igrf_ned_matches_published_igrf13_value():
    # Reference: the `igrf` package test suite (github.com/space-physics/igrf, tests/test_all.py), which wraps the
    # IAGA igrf13syn Fortran: 2010-07-12, geodetic 65 N 85 E, 0 km -> X 9295.415460, Y 2559.7889298,
    # Z 59670.379598 nT. 2010 lies in the definitive (DGRF) span, unchanged from IGRF-13 to IGRF-14.
    b = ref.igrf_ned(65.0 * DEG_TO_RAD, 85.0 * DEG_TO_RAD, 0.0, dt.datetime(2010, 7, 12))
    assert b.shape == (1, 3)
    np.testing.assert_allclose(b[0], [9295.415460, 2559.7889298, 59670.379598], atol=0.5)
    np.testing.assert_allclose(
        ref.igrf_total(65.0 * DEG_TO_RAD, 85.0 * DEG_TO_RAD, 0.0, "2010-07-12"), 60444.284, atol=0.5
    )
    dec, inc = ref.declination_inclination(b)
    assert dec[0] / DEG_TO_RAD == pytest.approx(15.396590, abs=1e-3)
    assert inc[0] / DEG_TO_RAD == pytest.approx(80.821575, abs=1e-3)


def test_igrf_vectorised_height_and_dates():
    lat = np.array([-35.0, 0.0, 51.5]) * DEG_TO_RAD
    lon = np.array([149.0, -30.0, 0.0]) * DEG_TO_RAD
    b0 = ref.igrf_total(lat, lon, 0.0, 2020.5)
    b10 = ref.igrf_total(lat, lon, 10_000.0, 2020.5)
    assert b0.shape == (3,)
    # Dipole-like decay with radius: |B| ~ r^-3, so 10 km up loses about 3 * 10/6371 = 0.47 %.
    np.testing.assert_allclose(b10 / b0, (6371.0 / 6381.0) ** 3, rtol=1e-3)
    # decimal year and datetime agree
    np.testing.assert_allclose(
        ref.igrf_total(lat, lon, 0.0, 2020.0), ref.igrf_total(lat, lon, 0.0, dt.date(2020, 1, 1))
    )


def test_anomaly_round_trips():
    lat, lon, h = np.array([0.6, 0.7]), np.array([2.5, 2.6]), np.array([100.0, 3000.0])
    main = ref.igrf_ned(lat, lon, h, "2021-03-01")
    d_b = np.array([[30.0, -20.0, 50.0], [-10.0, 5.0, 8.0]])
    total = np.linalg.norm(main + d_b, axis=1)
    anomaly = ref.total_field_to_anomaly(total, lat, lon, h, "2021-03-01")
    np.testing.assert_allclose(ref.anomaly_to_total_field(anomaly, lat, lon, h, "2021-03-01"), total)
    # the linearised projection is accurate to |dB|^2/|B| (< 0.1 nT here)
    np.testing.assert_allclose(anomaly, ref.project_anomaly(d_b, main), atol=0.1)
    np.testing.assert_allclose(ref.vector_to_anomaly(main + d_b, lat, lon, h, "2021-03-01"), d_b, atol=1e-9)


def test_gravity_disturbance_against_boule():
    boule = pytest.importorskip("boule")
    lat_deg = np.array([-80.0, -35.0, 0.0, 12.0, 45.0, 89.0])
    h = np.array([0.0, 500.0, 10_000.0, 2_000.0, 35_000.0, 1_000.0])
    gamma_boule = boule.WGS84.normal_gravity((np.zeros_like(lat_deg), lat_deg, h))  # mGal
    g_full = gamma_boule + np.array([12.0, -40.0, 0.0, 3.5, 100.0, -7.0])
    dg = ref.gravity_disturbance_mgal(g_full, lat_deg * DEG_TO_RAD, h)
    np.testing.assert_allclose(dg, [12.0, -40.0, 0.0, 3.5, 100.0, -7.0], atol=0.1)
    np.testing.assert_allclose(ref.full_gravity_mgal(dg, lat_deg * DEG_TO_RAD, h), g_full, atol=1e-9)


def test_bad_inputs_are_named():
    with pytest.raises(InputError, match="radians"):
        ref.igrf_total(65.0, 0.0, 0.0, 2020.0)  # degrees by mistake
    with pytest.raises(InputError, match="IGRF range"):
        ref.igrf_total(0.1, 0.1, 0.0, 1850.0)
    with pytest.raises(InputError, match="ISO date"):
        ref.igrf_total(0.1, 0.1, 0.0, "June 2020")
