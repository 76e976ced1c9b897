"""IMU samples from a simulator's flat, non-rotating world, made into those of an IMU on the rotating WGS84 Earth.

ArduPilot SITL (and most vehicle simulators) move the vehicle in a flat local NED frame that does not rotate, under a
constant gravity (ArduPilot's ``GRAVITY_MSS`` = 9.80665 m/s^2 straight down); its gyros and accelerometers measure
rates and specific forces in that frame. The bridge's INS mechanises on the rotating WGS84 Earth
(:mod:`magnav_ins.ins.strapdown`): fed the simulator's samples as they are, it sees a gyro that misses the Earth's
rate and the transport rate (at rest the ground alignment takes the 7e-5 rad/s for a bias, but in the body frame:
when the copter then pitches 10 deg to cruise, 1e-5 rad/s of it is wrong, and the tilt drifts by 1 mrad every 100 s, a
1 mg acceleration error), an accelerometer without the Coriolis term (0.2 mg at 15 m/s) and a gravity 0.02 m/s^2
stronger than the normal gravity. Measured on the SITL, a square flown on the unadapted samples drifted by 143 m in
150 s; ``--imu-world flat`` adapts every sample instead (the flat world's mechanisation set equal to the Earth's,
Groves 2013 eq. 5.46 and 5.54)::

    w_ib = w_flat + C_bn (w_ie + w_en)
    f_ib = f_flat + C_bn ((2 w_ie + w_en) x v_n + g_flat - g_n)

with the INS's own current attitude ``C_bn``, velocity ``v_n``, latitude and height (errors in them change the
adaptation only to second order).

**Its latitude and longitude are on a sphere.** ArduPilot turns the simulator's metres into degrees with
``Location::offset`` on a sphere of 6,378,100 m (``RADIUS_OF_EARTH``; height ignored), so a metre north is 0.53 %
more latitude in the INS's ellipsoid (meridian radius 6,344,300 m at 22 deg S) than in the simulator's lat/lon, the
frame of its GNSS, of its truth and of the autopilot's EKF. Left as it was, the horizontal accelerations the IMU
measures and the speeds the GNSS fixes show disagreed by that much: GNSS-aided, every acceleration taught the
filter a false deceleration along the track (the bridge's "along-track deceleration bias" of the SITL flights,
0.2-0.4 mg). The adaptation scales the horizontal kinematic acceleration (the horizontal part of the specific force
in the flat world) by ``k_N = (R_N + h) / R`` north and ``k_E = (R_E + h) / R`` east (``R`` =
``sphere_radius_m``), so that the INS's velocity, integrated on the ellipsoid, moves its latitude and longitude as
the simulator moves its own: then the INS and the simulator agree on where the vehicle is in degrees.
"""

from __future__ import annotations

import math

import numpy as np

from ..core.frames import WGS84_OMEGA_E, C_nb_from_q, radii_of_curvature
from ..ins.earth import gravity_n

#: ArduPilot's GRAVITY_MSS, the simulator's gravity (m/s^2, down)
FLAT_GRAVITY_MPS2 = 9.80665
#: ArduPilot's RADIUS_OF_EARTH: the sphere on which the simulator's metres become latitude and longitude (m)
FLAT_SPHERE_RADIUS_M = 6378100.0


def earth_imu(
    gyro_b: np.ndarray,
    accel_b: np.ndarray,
    q_nb: np.ndarray,
    v_n: np.ndarray,
    lat: float,
    h: float,
    g_flat_mps2: float = FLAT_GRAVITY_MPS2,
    sphere_radius_m: float | None = FLAT_SPHERE_RADIUS_M,
) -> tuple[np.ndarray, np.ndarray]:
    """The (gyro rad/s, specific force m/s^2) body-FRD sample a WGS84-Earth IMU would give where the flat world's IMU
    gives ``gyro_b``, ``accel_b`` (module docstring); ``q_nb`` scalar-last body -> NED, ``v_n`` m/s NED, ``lat`` rad,
    ``h`` m; ``sphere_radius_m`` the radius on which the simulator's lat/lon are made (None: metres are metres on the
    ellipsoid, no horizontal scaling)."""
    c_bn = C_nb_from_q(q_nb).T
    sl, cl = math.sin(lat), math.cos(lat)
    w_ie = np.array([WGS84_OMEGA_E * cl, 0.0, -WGS84_OMEGA_E * sl])
    r_n, r_e = (float(x) for x in radii_of_curvature(lat))
    vn, ve = float(v_n[0]), float(v_n[1])
    w_en = np.array([ve / (r_e + h), -vn / (r_n + h), -ve * math.tan(lat) / (r_e + h)])
    g_n = np.asarray(gravity_n(lat, h), float).reshape(3)
    gyro = np.asarray(gyro_b, float) + c_bn @ (w_ie + w_en)
    extra_n = np.cross(2.0 * w_ie + w_en, np.asarray(v_n, float)) + np.array([0.0, 0.0, g_flat_mps2]) - g_n
    if sphere_radius_m is not None:  # the flat world's horizontal acceleration, in the ellipsoid's metres
        a_h = c_bn.T @ np.asarray(accel_b, float)
        extra_n[0] += ((r_n + h) / sphere_radius_m - 1.0) * a_h[0]
        extra_n[1] += ((r_e + h) / sphere_radius_m - 1.0) * a_h[1]
    return gyro, np.asarray(accel_b, float) + c_bn @ extra_n
