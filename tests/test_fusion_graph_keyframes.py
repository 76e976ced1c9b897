"""Graph fuser through turns: the gtsam wheel preintegrates rotation in tangent space with Euler steps, so one long
preintegration through a turn drifts from the exact product of the per-sample rotations; ``max_preintegration_rad``
adds keyframe nodes that keep each preintegrated rotation small. Truth: a manoeuvring flight and its error-free IMU
(inverse mechanisation), which the project's strapdown reproduces to millimetres."""

from __future__ import annotations

import numpy as np
import pytest

gtsam = pytest.importorskip("gtsam")

from magnav_ins.aiding.fusion import ImuNoise, make_fuser  # noqa: E402
from magnav_ins.core.errors import ConfigError  # noqa: E402
from magnav_ins.core.frames import horizontal_error_m, meters_to_latlon  # noqa: E402
from magnav_ins.core.types import Fix, NavEstimate, NavState  # noqa: E402
from magnav_ins.ins.error_model import initial_covariance  # noqa: E402
from magnav_ins.ins.imu_models import get_grade  # noqa: E402
from magnav_ins.ins.manoeuvre import TURNS, manoeuvring_flight  # noqa: E402
from magnav_ins.ins.simulate import ideal_imu  # noqa: E402

#: the default flight with 6 deg/s turns (a rate-two turn), 600 s at 50 Hz, 70 m/s
_TURNS = tuple((start, length, 2.0 * peak) for start, length, peak in TURNS)


def _flight():
    tr = manoeuvring_flight(np.deg2rad(-22.0), np.deg2rad(140.6), 500.0, 600.0, 50.0, speed_mps=70.0, turns=_TURNS)
    imu = ideal_imu(tr)
    nav0 = NavState(tr.t[0], tr.lat[0], tr.lon[0], tr.h[0], tr.v_n[0], tr.q_nb[0])
    grade = get_grade("navigation")
    P0 = initial_covariance(grade, position_sigma_m=1.0, velocity_sigma_mps=0.01, attitude_sigma_rad=np.full(3, 1e-5))
    return tr, imu, NavEstimate(nav0, P0), ImuNoise.from_grade(grade)


def test_one_preintegration_through_a_turn_drifts_and_short_pieces_do_not() -> None:
    """The wheel's behaviour the keyframes work around: the rotation preintegrated over the 120-degree turn at
    200-240 s against the exact product of per-sample rotations, in one piece and in 1 s pieces."""
    tr, imu, _, _ = _flight()
    p = gtsam.PreintegrationCombinedParams.MakeSharedD(9.8)
    for set_cov in (p.setAccelerometerCovariance, p.setGyroscopeCovariance, p.setIntegrationCovariance):
        set_cov(np.eye(3) * 1e-8)
    sel = np.flatnonzero((imu.t > 195.0) & (imu.t <= 265.0))
    exact = gtsam.Rot3()
    for k in sel:
        exact = exact.compose(gtsam.Rot3.Expmap(imu.gyro_b[k] * (imu.t[k] - imu.t[k - 1])))

    def pieces(n: int) -> float:
        R, pim = gtsam.Rot3(), None
        for i, k in enumerate(sel):
            if i % n == 0:
                R = R if pim is None else R.compose(pim.deltaRij())
                pim = gtsam.PreintegratedCombinedMeasurements(p, gtsam.imuBias.ConstantBias())
            pim.integrateMeasurement(imu.accel_b[k], imu.gyro_b[k], float(imu.t[k] - imu.t[k - 1]))
        R = R.compose(pim.deltaRij())
        return float(np.linalg.norm(gtsam.Rot3.Logmap(R.between(exact))))

    assert np.degrees(np.linalg.norm(gtsam.Rot3.Logmap(exact))) > 100.0  # the turn is there
    one, short = pieces(len(sel)), pieces(50)
    assert one > 1e-4 and short < 0.1 * one, (one, short)


def test_keyframes_keep_the_graph_on_a_turning_flight() -> None:
    tr, imu, init, noise = _flight()
    err = {}
    for mpr in (None, 0.1):
        f = make_fuser("graph", init, noise, max_preintegration_rad=mpr)
        f.propagate(imu.slice(1, len(imu)))
        nav = f.estimate().nav
        err[mpr] = float(horizontal_error_m(nav.lat, nav.lon, tr.lat[-1], tr.lon[-1]))
    # measured: 289 m in one preintegration, 2.4 m with keyframes (the strapdown: < 0.01 m)
    assert err[0.1] < 10.0 and err[0.1] < 0.05 * err[None], err


def test_a_fix_at_a_keyframe_goes_on_that_node() -> None:
    """A fix stamped at a keyframe's time is fused on that node (it used to be refused as "not after the last
    graph node"), and pulls the estimate like a fix on a new node does."""
    tr, imu, init, noise = _flight()
    k = int(np.searchsorted(imu.t, 30.0))
    out = {}
    for keyframe in (False, True):
        f = make_fuser("graph", init, noise)
        f.propagate(imu.slice(1, k + 1))
        t = float(imu.t[k])
        if keyframe:
            f.add_node(t)
        dlat, dlon = meters_to_latlon(3.0, -2.0, tr.lat[k])
        fix = Fix(t, float(tr.lat[k] + dlat), float(tr.lon[k] + dlon), np.diag([4.0, 4.0]), source="test")
        inn = f.correct(fix)
        assert inn.accepted, inn.reason
        out[keyframe] = f.estimate().nav
    d = horizontal_error_m(out[True].lat, out[True].lon, out[False].lat, out[False].lon)
    assert d < 0.01, d  # the same solution either way
    assert horizontal_error_m(out[True].lat, out[True].lon, tr.lat[k], tr.lon[k]) > 0.3  # the fix did pull


@pytest.mark.parametrize("bad", [0.0, -0.1, 2.0, float("nan")])
def test_bad_keyframe_angle_is_a_config_error(bad: float) -> None:
    _, _, init, noise = _flight()
    with pytest.raises(ConfigError, match="max_preintegration_rad"):
        make_fuser("graph", init, noise, max_preintegration_rad=bad)


def test_held_height_is_the_default_height_of_a_fix() -> None:
    """``altitude_hold`` puts its height on a fix that brings none: the same solution as passing it explicitly."""
    tr, imu, init, noise = _flight()
    k = int(np.searchsorted(imu.t, 30.0))
    dlat, dlon = meters_to_latlon(3.0, -2.0, tr.lat[k])
    fix = Fix(float(imu.t[k]), float(tr.lat[k] + dlat), float(tr.lon[k] + dlon), np.diag([4.0, 4.0]), source="test")
    held = make_fuser("graph", init, noise, altitude_hold=480.0, altitude_hold_sigma_m=5.0)
    explicit = make_fuser("graph", init, noise)
    for f in (held, explicit):
        f.propagate(imu.slice(1, k + 1))
    held.correct(fix)
    explicit.correct(fix, height_m=480.0, height_sigma_m=5.0)
    a, b = held.estimate().nav, explicit.estimate().nav
    assert abs(a.h - b.h) < 1e-6 and abs(a.h - tr.h[k]) > 0.3  # the held height did pull (truth 500 m, 0.6 m)
    with pytest.raises(ConfigError, match="altitude_hold_sigma_m"):
        make_fuser("graph", init, noise, altitude_hold=480.0, altitude_hold_sigma_m=0.0)
    with pytest.raises(ConfigError, match="altitude_hold"):
        make_fuser("graph", init, noise, altitude_hold=float("nan"))
