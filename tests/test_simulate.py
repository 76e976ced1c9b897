"""Trajectories and the inverse mechanisation: analytic cases, geometry, and round trips through the strapdown."""

from __future__ import annotations

import math

import numpy as np
import pytest

from magnav_ins.core.errors import ConfigError, InputError
from magnav_ins.core.frames import WGS84_OMEGA_E, euler_from_q_nb, horizontal_error_m, radii_of_curvature
from magnav_ins.core.units import DEG_TO_RAD as D
from magnav_ins.ins.earth import gravity_n
from magnav_ins.ins.simulate import (
    great_circle,
    ideal_imu,
    stationary,
    survey_line,
    trajectory_from_csv,
    waypoints,
)
from magnav_ins.ins.strapdown import integrate


def _round_trip_error(traj):
    nav = integrate(traj.at(0), ideal_imu(traj))
    return horizontal_error_m(nav.lat, nav.lon, traj.lat, traj.lon), nav


def test_stationary_imu_is_earth_rate_and_gravity():
    lat, yaw = 40.0 * D, 30.0 * D
    traj = stationary(lat, -84.0 * D, 250.0, yaw, 5.0, 50.0)
    imu = ideal_imu(traj)
    c, s = math.cos(yaw), math.sin(yaw)
    C_bn = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
    w_n = np.array([WGS84_OMEGA_E * math.cos(lat), 0.0, -WGS84_OMEGA_E * math.sin(lat)])
    f_n = -gravity_n(lat, 250.0)
    assert np.allclose(imu.gyro_b, C_bn @ w_n, atol=1e-12)
    assert np.allclose(imu.accel_b, C_bn @ f_n, atol=1e-9)


def test_great_circle_geometry():
    V, rate = 250.0, 10.0
    traj = great_circle(-38.0 * D, 144.5 * D, -35.0 * D, 150.0 * D, 10000.0, V, rate)
    speed = np.linalg.norm(traj.v_n, axis=1)
    assert np.allclose(speed, V, rtol=1e-9) and np.allclose(traj.h, 10000.0) and np.allclose(traj.v_n[:, 2], 0.0)
    # ends within one sample of the end point; the velocity is the derivative of the position
    end = horizontal_error_m(traj.lat[-1], traj.lon[-1], -35.0 * D, 150.0 * D)
    assert end < V / rate
    r_n, r_e = radii_of_curvature(traj.lat)
    vn_fd = np.gradient(traj.lat, traj.t) * (r_n + traj.h)
    ve_fd = np.gradient(np.unwrap(traj.lon), traj.t) * (r_e + traj.h) * np.cos(traj.lat)
    assert np.allclose(vn_fd[1:-1], traj.v_n[1:-1, 0], atol=1e-5)
    assert np.allclose(ve_fd[1:-1], traj.v_n[1:-1, 1], atol=1e-5)
    # heading evolves along a great circle: Clairaut's constant cos(lat) sin(azimuth) holds on the sphere to ~f
    _, _, yaw = euler_from_q_nb(traj.q_nb)
    clairaut = np.cos(traj.lat) * np.sin(yaw)
    assert np.ptp(yaw) > 2.0 * D
    assert np.ptp(clairaut) < 5e-3 * abs(clairaut.mean())
    with pytest.raises(ConfigError, match="distinct"):
        great_circle(0.1, 0.2, 0.1, 0.2, 0.0, 100.0, 10.0)


def test_waypoints_coordinated_turns_and_climbs():
    V, w = 60.0, 3.0 * D
    pts = [(45.0 * D, 10.0 * D, 1000.0), (45.05 * D, 10.05 * D, 1200.0), (45.0 * D, 10.1 * D, 1100.0)]
    traj = waypoints(pts, V, 20.0, turn_rate=w, climb_rate=2.0)
    assert np.allclose(np.hypot(traj.v_n[:, 0], traj.v_n[:, 1]), V)
    assert np.max(np.abs(traj.v_n[:, 2])) <= 2.0 + 1e-9
    roll, pitch, yaw = euler_from_q_nb(traj.q_nb)
    # bank of a coordinated turn at the full turn rate: atan(v omega / g)
    assert np.max(np.abs(roll)) == pytest.approx(math.atan(V * w / 9.80665), rel=0.02)
    assert np.allclose(np.tan(pitch), -traj.v_n[:, 2] / V, atol=1e-12)
    # passes the middle waypoint within a turn radius, heights reach the waypoint heights
    d_mid = horizontal_error_m(traj.lat, traj.lon, pts[1][0], pts[1][1]).min()
    assert d_mid < V / w
    assert 1150.0 < traj.h.max() < 1200.0
    assert np.max(np.abs(traj.v_n[:, 2])) == pytest.approx(2.0, rel=0.02)
    with pytest.raises(ConfigError, match="points"):
        waypoints([(0.0, 0.0, 0.0)], V, 20.0)


def test_survey_line_drops_close_vertices_and_flies_the_line():
    lat = 45.0 * D + np.linspace(0.0, 0.1, 1000) * D  # ~11 km north in 11 m steps
    lon = np.full_like(lat, 10.0 * D)
    lon[500:] += np.linspace(0.0, 0.07, 500) * D  # then north-east
    lat += np.random.default_rng(0).normal(0.0, 1.0 / 6.4e6, lat.shape)  # 1 m jitter of the fixes
    traj = survey_line(lat, lon, 500.0, 50.0, 10.0)
    # ends abeam the last vertex, never far from the polyline
    assert horizontal_error_m(traj.lat[-1], traj.lon[-1], lat[-1], lon[-1]) < 10.0
    d = np.array(
        [horizontal_error_m(la, lo, lat, lon).min() for la, lo in zip(traj.lat[::20], traj.lon[::20], strict=True)]
    )
    assert d.max() < 100.0  # measured 49 m (45 deg corner, turn radius 955 m)


def test_round_trip_great_circle_and_waypoints_10_min():
    gc = great_circle(-38.0 * D, 144.5 * D, -35.0 * D, 150.0 * D, 10000.0, 200.0, 100.0).slice(0, 60001)
    e, _ = _round_trip_error(gc)
    assert e.max() < 0.02  # measured 0.005 m
    pts = [
        (45 * D, 10 * D, 1000.0),
        (45.05 * D, 10.08 * D, 1500.0),
        (45.1 * D, 10.0 * D, 1200.0),
        (45.0 * D, 9.95 * D, 900.0),
    ]
    wp = waypoints(pts, 100.0, 100.0, turn_rate=3 * D)
    e, nav = _round_trip_error(wp)
    assert e.max() < 0.02
    assert np.abs(nav.v_n - wp.v_n).max() < 1e-3


@pytest.mark.slow
def test_round_trip_one_hour_100_hz():
    gc = great_circle(-38 * D, 144.5 * D, -20 * D, 160 * D, 10000.0, 200.0, 100.0).slice(0, 360001)
    e, _ = _round_trip_error(gc)
    assert e.max() < 0.1  # measured 0.042 m
    pts = [(45 * D, 10 * D, 1000.0), (45.5 * D, 10.6 * D, 1500.0), (46.0 * D, 10.1 * D, 1200.0), (45.6 * D, 9.4 * D, 800.0),
           (45.0 * D, 10.0 * D, 1000.0), (45.4 * D, 10.9 * D, 1000.0), (46.2 * D, 10.9 * D, 2000.0)]  # fmt: skip
    wp = waypoints(pts, 100.0, 100.0).slice(0, 360001)
    e, _ = _round_trip_error(wp)
    assert e.max() < 0.1  # measured 0.049 m


def test_trajectory_csv(tmp_path):
    traj = waypoints([(45 * D, 10 * D, 100.0), (45.02 * D, 10.03 * D, 150.0)], 40.0, 10.0)
    roll, pitch, yaw = euler_from_q_nb(traj.q_nb)
    full = tmp_path / "full.csv"
    cols = np.column_stack([traj.t, traj.lat / D, traj.lon / D, traj.h, traj.v_n, roll / D, pitch / D, yaw / D])
    np.savetxt(full, cols, delimiter=",", fmt="%.12f",
               header="t,lat_deg,lon_deg,h_m,vn,ve,vd,roll_deg,pitch_deg,yaw_deg", comments="")  # fmt: skip
    back = trajectory_from_csv(full)
    assert np.allclose(back.lat, traj.lat, atol=1e-13) and np.allclose(back.v_n, traj.v_n, atol=1e-9)
    assert np.allclose(np.abs(np.sum(back.q_nb * traj.q_nb, axis=1)), 1.0, atol=1e-12)
    pos_only = tmp_path / "pos.csv"
    np.savetxt(pos_only, cols[:, :4], delimiter=",", fmt="%.12f", header="t,lat_deg,lon_deg,h_m", comments="")
    derived = trajectory_from_csv(pos_only)
    assert np.abs(derived.v_n[5:-5] - traj.v_n[5:-5]).max() < 0.05  # spline derivative of the positions

    bad = tmp_path / "bad.csv"
    bad.write_text("t,lat_deg,lon_deg\n0,1,2\n1,1,2\n")
    with pytest.raises(InputError, match="bad.csv 'h_m': missing column"):
        trajectory_from_csv(bad)
    bad.write_text("t,lat_deg,lon_deg,h_m\n0,1,2,3\n1,nan,2,3\n")
    with pytest.raises(InputError, match="bad.csv row 2 'lat_deg'"):
        trajectory_from_csv(bad)
    bad.write_text("t,lat_deg,lon_deg,h_m\n0,1,2,3\n0,1,2,3\n")
    with pytest.raises(InputError, match="row 2 't': time must increase"):
        trajectory_from_csv(bad)
    bad.write_text("t,lat_deg,lon_deg,h_m,vn\n0,1,2,3,4\n1,1,2,3,4\n")
    with pytest.raises(InputError, match="'ve': missing column"):
        trajectory_from_csv(bad)


def test_ideal_imu_matches_pyins_generate_imu():
    """Peer check: pyins ``sim.generate_imu`` (increment type) on the same waypoint flight at sea level (where the two
    normal-gravity models agree to ~1e-7 m/s^2)."""
    sim = pytest.importorskip("pyins.sim")
    pts = [(45 * D, 10 * D, 0.0), (45.03 * D, 10.05 * D, 0.0), (45.06 * D, 10.0 * D, 0.0)]
    tr = waypoints(pts, 100.0, 50.0)
    roll, pitch, yaw = euler_from_q_nb(tr.q_nb)
    rph = np.rad2deg(np.column_stack([roll, pitch, yaw]))
    lla = np.column_stack([np.rad2deg(tr.lat), np.rad2deg(tr.lon), tr.h])
    _, inc = sim.generate_imu(tr.t, lla, rph, tr.v_n, sensor_type="increment")
    mine = ideal_imu(tr)
    dt = np.diff(tr.t)[:, None]
    gyro = inc[["gyro_x", "gyro_y", "gyro_z"]].to_numpy()[1:] / dt
    accel = inc[["accel_x", "accel_y", "accel_z"]].to_numpy()[1:] / dt
    assert np.abs(gyro - mine.gyro_b[1:]).max() < 1e-11  # measured 9e-13 rad/s
    assert np.abs(accel - mine.accel_b[1:]).max() < 5e-7  # measured 1.4e-7 m/s^2 (gravity models)
