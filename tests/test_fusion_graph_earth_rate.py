"""The graph's IMU factors must know that the Earth rate they take out of the gyros depends on the attitude (issue 13).

The graph works in an Earth-fixed frame L, so the gyros measure the body rate relative to L plus the Earth rate
``C_bL omega_ie``. With the Earth rate taken out of the samples at the predicted attitude, a heading error ``psi_D``
leaves a tilt-rate error ``omega_ie x psi`` (8 mrad x 6.8e-5 rad/s = 5e-7 rad/s, 0.11 deg/h) frozen into every
factor, with no Jacobian w.r.t. the node's rotation: the graph could not see the heading through the tilt it drives
(gyrocompassing), fitted the tilt drift with heading, tilt and gyro bias, and on the Osborne eight-line study kept a
7-20 mrad heading error with a 2 mrad sigma. Referee: the linear error-state Kalman filter (``free_inertial``, the
same Groves 2013 model as the UKF's: ``d psi/dt = -omega_in x psi - C_nb db_g + ...``).

Case: straight and level at 70 m/s for 600 s, error-free IMU, no fixes, a 50 mrad heading sigma; the heading then
spreads into the tilt as ``Omega cos(lat) t sigma_D`` (2 mrad after 600 s, against 1.2 mrad from the 2e-6 rad/s
gyro-bias sigma), which makes the east tilt and the heading correlated (0.86). Measured: linear filter (and UKF) east
tilt 2.15 mrad, correlation 0.86, north velocity 6.7 m/s; graph before the fix 1.20 mrad, 0.00, 3.6 m/s; after it
2.37 mrad, 0.86, 7.1 m/s (the graph's tilt stays ~10 % above: its factors have no Schuler feedback, the gravity
direction at a node's position being a constant of the factor).
"""

from __future__ import annotations

import numpy as np
import pytest

gtsam = pytest.importorskip("gtsam")

from magnav_ins.aiding.fusion import ImuNoise, make_fuser  # noqa: E402
from magnav_ins.core.types import NavEstimate, NavState  # noqa: E402
from magnav_ins.ins.manoeuvre import manoeuvring_flight  # noqa: E402
from magnav_ins.ins.simulate import ideal_imu  # noqa: E402

_T = 600.0


def _straight_flight():
    tr = manoeuvring_flight(np.deg2rad(-21.0), np.deg2rad(140.0), 400.0, _T, 50.0, speed_mps=70.0, turns=(),
                            accelerations=(), climbs=())  # fmt: skip
    imu = ideal_imu(tr)
    nav0 = NavState(tr.t[0], tr.lat[0], tr.lon[0], tr.h[0], tr.v_n[0], tr.q_nb[0])
    noise = ImuNoise(accel_noise=2e-4, gyro_noise=5e-7, accel_bias_sigma=2e-4, gyro_bias_sigma=2e-6,
                     accel_bias_tau=np.inf, gyro_bias_tau=np.inf)  # fmt: skip
    sig = np.r_[np.full(3, 10.0), np.full(3, 0.05), 1e-4, 1e-4, 0.05, np.full(3, 2e-4), np.full(3, 2e-6)]
    return tr, imu, NavEstimate(nav0, np.diag(sig**2)), noise


@pytest.fixture(scope="module")
def covariances() -> dict[str, np.ndarray]:
    tr, imu, init, noise = _straight_flight()
    out = {}
    for kind, opts in (("free_inertial", {}), ("graph", {"max_preintegration_rad": 0.1})):
        f = make_fuser(kind, init, noise, altitude_hold=float(tr.h[0]), **opts)
        f.propagate(imu.slice(1, len(imu)))
        out[kind] = np.asarray(f.estimate().P)[:15, :15]
    return out


def test_heading_spreads_into_the_tilt_as_in_the_linear_filter(covariances: dict[str, np.ndarray]) -> None:
    """Tilt and heading sigmas within 15 % of the linear filter's, and the east-tilt/heading correlation within
    0.1 of it (0.86)."""
    ref, g = covariances["free_inertial"], covariances["graph"]
    att = slice(6, 9)
    np.testing.assert_allclose(np.sqrt(np.diag(g)[att]), np.sqrt(np.diag(ref)[att]), rtol=0.15)

    def corr(P: np.ndarray) -> float:
        return float(P[7, 8] / np.sqrt(P[7, 7] * P[8, 8]))

    assert abs(corr(ref)) > 0.5, corr(ref)  # the case tests what it says
    assert abs(corr(g) - corr(ref)) < 0.1, (corr(g), corr(ref))


def test_horizontal_velocity_sigma_follows_the_linear_filter(covariances: dict[str, np.ndarray]) -> None:
    """North/east velocity sigmas within 15 % of the linear filter's after 600 s (the tilt drives them)."""
    ref, g = covariances["free_inertial"], covariances["graph"]
    np.testing.assert_allclose(np.sqrt(np.diag(g)[3:5]), np.sqrt(np.diag(ref)[3:5]), rtol=0.15)
