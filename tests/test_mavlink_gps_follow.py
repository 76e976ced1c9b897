"""How the autopilot takes up the bridge's GPS_INPUT, and what the bridge sends so that it follows the map fixes.

EKF3 fuses a GPS_INPUT position (variance: the horizontal accuracy squared, at least ``EK3_POSNE_M_NSE``, at most
100 m) and velocity (the speed accuracy squared, at least ``EK3_VELNE_M_NSE``) as white measurements at the message
rate, each accuracy through a peak-hold with a 5 s decay (ArduPilot ``AP_NavEKF3_Measurements.cpp`` readGpsData,
``AP_NavEKF3_PosVelFusion.cpp``). :func:`ekf3_follow` is that fusion on one horizontal axis (position, velocity;
``EK3_ACC_P_NSE`` process noise), driven by the EKF's own error against the bridge's output: its IMU is the SITL's,
nearly perfect, so what it does with a step of the bridge's position is the whole story. Replayed with the
bridge's recorded outputs of SITL run 29 it reproduced the recorded EKF3 track within 6 m RMS (28.8 m RMS off the
truth, the bridge 22 m): at the filter's own speed sigma (0.05-0.6 m/s) and 30-80 m of horizontal sigma EKF3 takes
minutes to take up a fix's correction. The bridge's speed accuracy floor ``sigma_h / follow_s``
(:meth:`magnav_ins.mavlink.bridge.Bridge._speed_accuracy`) makes it about ``follow_s``.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from test_mavlink_bridge_states import ARDUPILOT, LAT, LON, Heartbeat, _at_rest, _bridge, _SigmaPipeline

from magnav_ins.mavlink.bridge import MAX_SPEED_FLOOR_MPS, BridgeConfig

#: EKF3 copter defaults: EK3_VELNE_M_NSE, EK3_POSNE_M_NSE (m/s, m), EK3_ACC_P_NSE (m/s^2), its prediction step (s)
VELNE_NSE, POSNE_NSE, ACC_P_NSE, EKF_DT = 0.3, 0.5, 0.35, 0.012


def ekf3_follow(sigma_h: float, speed_acc: float, step_m: float, rate_hz: float = 10.0, after_s: float = 300.0):
    """EKF3's GPS fusion on one axis (module docstring) settled at ``sigma_h`` (m) / ``speed_acc`` (m/s), then the
    sent position steps by ``step_m`` (the sent velocity does not). Returns the time (s) to take up 63 % of the step
    and the largest velocity the step put into the EKF (m/s)."""
    Rv = max(min(speed_acc, 50.0), VELNE_NSE) ** 2
    Rp = max(min(sigma_h, 100.0), POSNE_NSE) ** 2
    x = np.zeros(2)
    P = np.diag([1.0, 0.1])
    F = np.array([[1.0, EKF_DT], [0.0, 1.0]])
    Q = np.diag([0.0, (ACC_P_NSE * EKF_DT) ** 2])
    every = round(1.0 / rate_hz / EKF_DT)
    settle = 200.0
    t63, vmax = math.inf, 0.0
    for k in range(int((settle + after_s) / EKF_DT)):
        x = F @ x
        P = F @ P @ F.T + Q
        if k % every:
            continue
        t = k * EKF_DT
        z_p = step_m if t >= settle else 0.0
        for z, R, i in ((0.0, Rv, 1), (z_p, Rp, 0)):
            S = P[i, i] + R
            K = P[:, i] / S
            x = x + K * (z - x[i])
            P = P - np.outer(K, P[i, :])
        if t >= settle:
            vmax = max(vmax, abs(x[1]))
            if math.isinf(t63) and x[0] >= 0.632 * step_m:
                t63 = t - settle
    return t63, vmax


@pytest.mark.parametrize("sigma_h", [10.0, 40.0, 80.0])
def test_ekf3_takes_up_a_position_step_in_sigma_h_over_speed_accuracy(sigma_h):
    """The rule the bridge's floor rests on: the time constant is about sigma_h / speed accuracy (EKF3's 0.3 m/s
    velocity floor aside; below about 15 s EKF3's own inertial prediction sets the pace), so at the filter's own
    speed sigma a fix's correction takes minutes."""
    for tau in (20.0, 40.0):
        t63, _ = ekf3_follow(sigma_h, sigma_h / tau, sigma_h)
        assert 0.75 * tau <= t63 <= 1.35 * tau, (sigma_h, tau, t63)
    t63_own, _ = ekf3_follow(sigma_h, 0.3, sigma_h)  # the filter's speed sigma on SITL run 29: 0.05-0.6 m/s
    assert t63_own >= 0.75 * sigma_h / 0.3, t63_own


@pytest.mark.parametrize(("sigma_h", "fast_s"), [(20.0, 25.0), (40.0, 40.0), (80.0, 80.0)])
def test_the_bridges_floor_makes_ekf3_follow_sooner_without_a_velocity_jolt(sigma_h, fast_s):
    """The filter's 0.35 m/s -> 50-300 s; the floor (20 s, at most 1.2 m/s) -> 3-4 times sooner, and a one-sigma
    correction moves EKF3's velocity by less than 0.5 m/s, inside its velocity gate (5 x 0.3 m/s)."""
    slow, _ = ekf3_follow(sigma_h, 0.35, sigma_h)
    sent = min(sigma_h / BridgeConfig().follow_s, MAX_SPEED_FLOOR_MPS)
    fast, vmax = ekf3_follow(sigma_h, sent, sigma_h)
    assert fast < fast_s and fast < slow / 2.5, (slow, fast)
    assert vmax < 0.5, vmax


def _run(config: BridgeConfig, sigma_h: float, sigma_v: float, hpl: float = math.nan) -> list[dict]:
    b, link, now = _bridge(config, make_pipeline=lambda nav0, s: _SigmaPipeline(nav0, lambda t: sigma_h, sigma_v, hpl))
    for k in range(1, 301):
        now[0] = 0.01 * k
        link.inbox.append(_at_rest(now[0]))
        if k % 100 == 1:
            link.inbox.append(Heartbeat(1, 1, 2, ARDUPILOT))
        b.poll()
    return link.gps_inputs()


@pytest.mark.parametrize(("sigma_h", "sigma_v", "follow_s", "expected"), [
    (20.0, 0.35, 20.0, 1.0),  # the floor
    (40.0, 0.35, 20.0, 1.2),  # the floor, capped under EKF3's GPS-glitch threshold
    (40.0, 2.0, 20.0, 2.0),  # the filter's own when larger
    (2.0, 0.35, 20.0, 0.35),  # GNSS-aided: the filter's own
    (40.0, 0.35, 1e6, 0.35),  # no floor
])  # fmt: skip
def test_gps_input_speed_accuracy_is_at_least_sigma_h_over_follow_s(sigma_h, sigma_v, follow_s, expected):
    init = (LAT, LON, 400.0, 0.0)
    sent = _run(
        BridgeConfig(output="gps_input", init=init, align=False, baro=False, follow_s=follow_s), sigma_h, sigma_v
    )
    healthy = [s for s in sent if s["healthy"]]
    assert len(healthy) >= 20
    assert all(s["sigma_speed"] == pytest.approx(expected, rel=1e-6) for s in healthy)
    assert all(s["sigma_h"] == pytest.approx(sigma_h, rel=1e-6) for s in healthy)


def test_the_sigma_limit_holds_even_with_a_small_protection_level():
    """EKF3 reads at most 100 m of accuracy: a position with a larger sigma is not sent as a fix, whatever its HPL."""
    init = (LAT, LON, 400.0, 0.0)
    cfg = BridgeConfig(output="gps_input", init=init, align=False, baro=False, max_sigma_m=100.0)
    assert not any(s["healthy"] for s in _run(cfg, 120.0, 0.5, hpl=300.0))
    assert all(s["healthy"] for s in _run(cfg, 60.0, 0.5, hpl=300.0)[10:])
    assert not any(s["healthy"] for s in _run(cfg, 60.0, 0.5, hpl=600.0))
    with pytest.raises(Exception, match="follow_s"):
        BridgeConfig(follow_s=0.0)
