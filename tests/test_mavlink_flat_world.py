"""``--imu-world flat`` (:mod:`magnav_ins.mavlink.flat_world`): a simulator's flat, non-rotating world made into the
WGS84 Earth the INS mechanises on. Independent truth: in the flat world a vehicle in steady, straight flight feels
no rotation and exactly ``GRAVITY_MSS`` of specific force; fed the adapted samples, the WGS84 strapdown must keep
that flight steady and straight (the distance along the ellipsoid equal to speed x time), where the unadapted ones
make it drift as the SITL flight did."""

from __future__ import annotations

import math

import numpy as np
import pytest

from magnav_ins.core.frames import C_nb_from_q, latlon_to_meters, q_nb_from_euler
from magnav_ins.core.types import NavState
from magnav_ins.ins.earth import gravity_n, omega_ie_n
from magnav_ins.ins.strapdown import StrapdownStepper
from magnav_ins.mavlink.flat_world import FLAT_GRAVITY_MPS2, earth_imu

LAT, LON, H = math.radians(-21.94), math.radians(140.76), 460.0


def test_at_rest_the_adapted_sample_is_what_an_earth_imu_measures():
    q = q_nb_from_euler(0.05, -0.17, 1.1)
    c_bn = C_nb_from_q(q).T
    f_flat = c_bn @ np.array([0.0, 0.0, -FLAT_GRAVITY_MPS2])
    gyro, accel = earth_imu(np.zeros(3), f_flat, q, np.zeros(3), LAT, H)
    np.testing.assert_allclose(gyro, c_bn @ omega_ie_n(LAT), atol=1e-15)
    np.testing.assert_allclose(accel, -c_bn @ np.asarray(gravity_n(LAT, H)).reshape(3), atol=1e-12)


def _fly(adapt: bool, seconds: float = 200.0, rate_hz: float = 100.0) -> tuple[float, float, float]:
    """Steady flight north at 15 m/s, pitched 10 deg nose down (a cruising copter), as the flat world measures it.
    Returns (north distance error m, east error m, speed error m/s) of the WGS84 strapdown after ``seconds``."""
    v = np.array([15.0, 0.0, 0.0])
    q = q_nb_from_euler(0.0, math.radians(-10.0), 0.0)
    c_bn = C_nb_from_q(q).T
    gyro_flat, f_flat = np.zeros(3), c_bn @ np.array([0.0, 0.0, -FLAT_GRAVITY_MPS2])
    ins = StrapdownStepper(NavState(0.0, LAT, LON, H, v, q), altitude_hold=H)
    for k in range(1, int(seconds * rate_hz) + 1):
        if adapt:
            nav = ins.nav
            gyro, accel = earth_imu(gyro_flat, f_flat, nav.q_nb, nav.v_n, nav.lat, nav.h)
        else:
            gyro, accel = gyro_flat, f_flat
        ins.step_rate(k / rate_hz, gyro, accel)
    nav = ins.nav
    dn, de = latlon_to_meters(nav.lat - LAT, nav.lon - LON, LAT)
    return float(dn) - 15.0 * seconds, float(de), float(np.linalg.norm(nav.v_n - v))


@pytest.mark.parametrize("adapt", [True, False], ids=["adapted", "raw"])
def test_steady_flight_of_the_flat_world_stays_steady_on_the_earth(adapt):
    en, ee, ev = _fly(adapt)
    if adapt:
        # measured: 0.21 m along 3 km, 7e-8 m/s
        assert abs(en) < 0.5 and abs(ee) < 0.5 and ev < 0.01, (en, ee, ev)
    else:
        # the Earth's rate missing from the gyros tilts the INS, Coriolis pushes it sideways: measured 898 m
        assert math.hypot(en, ee) > 20.0, (en, ee, ev)


@pytest.mark.parametrize("sphere", [True, False], ids=["sphere", "metres"])
def test_an_acceleration_moves_the_ins_in_degrees_as_the_simulator_moves(sphere):
    """The simulator's lat/lon are on ArduPilot's 6,378,100 m sphere: 20 s at 0.5 m/s^2 north-east from rest (a
    level vehicle, 100 m north and east in the flat world) must move the WGS84 INS by 100 m / R in latitude and
    100 m / (R cos lat) in longitude (measured: within 0.4 mm). Without the sphere the INS overshoots in latitude by
    0.53 % (measured 0.53 m north, -0.05 m east)."""
    from magnav_ins.mavlink.flat_world import FLAT_SPHERE_RADIUS_M

    a, seconds, rate_hz = 0.5, 20.0, 100.0
    q = q_nb_from_euler(0.0, 0.0, 0.0)
    f_flat = np.array([a, a, -FLAT_GRAVITY_MPS2])  # level, accelerating north and east
    ins = StrapdownStepper(NavState(0.0, LAT, LON, H, np.zeros(3), q), altitude_hold=H)
    radius = FLAT_SPHERE_RADIUS_M if sphere else None
    for k in range(1, int(seconds * rate_hz) + 1):
        nav = ins.nav
        gyro, accel = earth_imu(np.zeros(3), f_flat, nav.q_nb, nav.v_n, nav.lat, nav.h, sphere_radius_m=radius)
        ins.step_rate(k / rate_hz, gyro, accel)
    d = 0.5 * a * seconds**2
    dn_sphere = (ins.nav.lat - LAT) * FLAT_SPHERE_RADIUS_M - d  # m, in the simulator's own metres
    de_sphere = (ins.nav.lon - LON) * FLAT_SPHERE_RADIUS_M * math.cos(LAT) - d
    if sphere:
        assert abs(dn_sphere) < 0.02 and abs(de_sphere) < 0.02, (dn_sphere, de_sphere)
    else:
        assert dn_sphere > 0.4, (dn_sphere, de_sphere)
