"""The bridge on a recorded ArduCopter SITL stream (:mod:`magnav_ins.mavlink.playback`): the "along-track
deceleration bias" of the SITL flights, found and fixed.

The recording (``data/sitl_north_leg.tlog.xz``, 120 s, 0.5 MB): the shared ArduCopter SITL (master of 2026-03-20,
``copter.parm``, home 21.94 S 140.76 E, Osborne world), recorded on its serial 0 with no bridge: 45 s before the
north leg (on the ground, climbing to 80 m), then the leg at 10 m/s; HIGHRES_IMU at 100 Hz, GPS_RAW_INT at 5 Hz,
ATTITUDE and SIM_STATE (truth) at 10 Hz, SCALED_PRESSURE, EXTENDED_SYS_STATE, HEARTBEAT. The bridge runs on it as on
the SITL (``--imu-world flat``, the SITL grade, GPS_INPUT to GPS2, no map matching), GNSS-aided, then denied 80 s in.

Independent truth: SIM_STATE. Two defects made the INS fall behind along the track:

* the SITL's GPS_RAW_INT position is 0.07 s older than its stamp (the time the fix reached the autopilot; measured
  against SIM_STATE): fused as current, the INS sat 1.1 m behind at 10 m/s while GNSS-aided;
* the simulator's lat/lon are made on a sphere of 6,378,100 m, the INS's on the ellipsoid (0.53 % in latitude at
  22 deg S): the GNSS speeds and the accelerometers disagreed, and every acceleration taught the filter a false
  deceleration; denied, the INS fell behind by 2.2 m in 35 s.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from magnav_ins.maps.builtin import load_map
from magnav_ins.mavlink.bridge import Bridge, BridgeConfig, ScalarAnomalyModel
from magnav_ins.mavlink.online import make_online_pipeline
from magnav_ins.mavlink.playback import play
from magnav_ins.mavlink.sitl_flight import SITL_GNSS_LAG_S, SITL_GRADE

RECORDING = Path(__file__).parent / "data" / "sitl_north_leg.tlog.xz"
DENY_S = 80.0  # from the bridge's first GNSS message, the start of the recording
R_SPHERE = 6378100.0


def _fly(gnss_lag_s: float, sphere: bool, grade_text: str = SITL_GRADE) -> dict[str, float]:
    """Along-track error (m, INS minus truth, north: the leg is flown north) while GNSS-aided in cruise (mean over
    55-80 s) and its change over the first 35 s denied."""
    fmap = load_map("builtin:osborne-magnetic")
    grade = json.loads(grade_text)
    assert grade["base"] == "navigation"

    def factory(nav0, sigma_m):  # noqa: ANN001, ANN202
        return make_online_pipeline(nav0, sigma_m, fmap, grade=grade_text, matcher="none", fusion="ukf")

    cfg = BridgeConfig(
        output="gps_input", output_rate_hz=10, gps_id=1, imu_world="flat", deny_gnss_after_s=DENY_S,
        gnss_lag_s=gnss_lag_s, flat_sphere_radius_m=R_SPHERE if sphere else None,
    )  # fmt: skip

    def make(link, clock, on_output):  # noqa: ANN001, ANN202
        return Bridge(link, cfg, factory, ScalarAnomalyModel("2026-03-20", None), clock=clock, wall_clock=clock,
                      fmap=fmap, on_output=on_output)  # fmt: skip

    pb = play(RECORDING, make)
    truth = pb.truth
    t = np.array([o["t_wall"] for o in pb.outputs])
    lat = np.array([o["lat"] for o in pb.outputs])
    aiding = np.array([o["aiding"] for o in pb.outputs])
    t0 = t[0]
    err_n = (lat - np.interp(t, truth[:, 0], truth[:, 1])) * R_SPHERE  # the SITL's own metres
    speed = np.hypot(np.interp(t, truth[:, 0], truth[:, 4]), np.interp(t, truth[:, 0], truth[:, 5]))
    cruise = (t - t0 >= 55.0) & (t - t0 < DENY_S) & (aiding == "gnss")
    assert cruise.sum() > 200 and np.all(speed[cruise] > 9.0)  # the recording is what the docstring says
    assert np.all(aiding[t - t0 > DENY_S + 1.0] == "map")

    def at(s: float) -> float:
        return float(np.interp(t0 + s, t, err_n))

    return {"aided_mean_m": float(np.mean(err_n[cruise])), "denied_drift_m": at(DENY_S + 35.0) - at(DENY_S)}


@pytest.fixture(scope="module")
def before() -> dict[str, float]:
    # the defect shown with the accelerometer bias model of its day (the navigation preset's, 2.45e-4 m/s^2, 1 h):
    # the SITL grade's in-flight bias (2e-3 m/s^2, 150 s, issue 17) takes a third of it up as a bias while
    # GNSS-aided (denied drift -1.5 m instead of -2.2 m), which would blur what this test shows
    old = {**json.loads(SITL_GRADE), "accel_bias_sigma": 2.45e-4, "accel_bias_tau": 3600.0}
    return _fly(0.0, sphere=False, grade_text=json.dumps(old))


@pytest.fixture(scope="module")
def after() -> dict[str, float]:
    return _fly(SITL_GNSS_LAG_S, sphere=True)


def test_the_recorded_stream_shows_the_along_track_defect_without_the_fixes(before):
    # measured: -1.1 m while aided, -2.2 m in 35 s denied
    assert before["aided_mean_m"] < -0.8
    assert before["denied_drift_m"] < -1.5


def test_with_the_gnss_latency_and_the_simulator_sphere_the_ins_keeps_up_along_track(after):
    # measured: -0.2 m while aided, -0.35 m in 35 s denied
    assert abs(after["aided_mean_m"]) < 0.4
    assert abs(after["denied_drift_m"]) < 0.8


def test_the_playback_clock_is_the_logs():
    """The playback serves every frame once, in order, at its receive time."""
    from magnav_ins.mavlink.playback import TlogPlayback

    now = [0.0]
    link = TlogPlayback(RECORDING, lambda: now[0])
    now[0] = link.first_t - 1.0
    assert list(link.recv()) == []
    now[0] = link.first_t + 1.0
    first = list(link.recv())
    assert 100 <= sum(type(m).__name__ == "ImuMessage" for m in first) <= 102
    now[0] = math.inf
    rest = list(link.recv())
    assert link.finished and len(first) + len(rest) > 15000
