"""The bridge against a real autopilot: ArduCopter SITL (real firmware, real EKF3, real MAVLink) with a magnetic world.

Skipped when ``../shared/tools/ardupilot-sitl/`` is not beside the project (a fresh clone). Every SITL runs in a
temporary directory on free loopback ports and is stopped however the test ends (:class:`Sitl` is a context manager;
:func:`fly_square` stops what it started in a ``finally``).

* the autopilot reboots mid-run (it forgets every SET_MESSAGE_INTERVAL): the bridge's IMU stream is back within 5 s of
  the autopilot's first heartbeat after the reboot; ArduPilot's GLOBAL_POSITION_INT at 0 N 0 E before its GNSS has a
  fix is never an initial position (the bridge waits for a 3D fix);
* a short GNSS-denied flight end to end (``fly_square``: arm and take off on the SITL's GNSS, deny it, about 2 minutes
  on the bridge's GPS_INPUT alone, return and land); the full square is ``bench/sitl_flight.py``.
"""

from __future__ import annotations

import json
import math
import time

import numpy as np
import pytest

from magnav_ins.maps.builtin import load_map
from magnav_ins.mavlink.bridge import Bridge, BridgeConfig, ScalarAnomalyModel
from magnav_ins.mavlink.link import MavLink
from magnav_ins.mavlink.online import make_online_pipeline
from magnav_ins.mavlink.sitl import GroundStation, Sitl, free_udp_port, sitl_dir

pytestmark = pytest.mark.skipif(sitl_dir() is None, reason="../shared/tools/ardupilot-sitl is not beside the project")

HOME = (-21.94, 140.76, 380.0, 0.0)
MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN = 246


def test_autopilot_reboot_imu_stream_back_within_5_s_and_no_position_from_0_0():
    fmap = load_map("builtin:osborne-magnetic")
    port = free_udp_port()
    with Sitl(HOME, params={"SERIAL1_PROTOCOL": 2, "SR1_EXTRA1": 0, "SIM_DRIFT_SPEED": 0}, serial1_udp_port=port) as s:
        link = MavLink(f"udpin:127.0.0.1:{port}", source_system=1, peer_system=1, peer_component=1)
        config = BridgeConfig(output="gps_input", gps_id=1, output_rate_hz=10.0)
        bridge = Bridge(
            link, config,
            lambda nav0, sigma: make_online_pipeline(nav0, sigma, fmap, grade="tactical", matcher="none"),
            ScalarAnomalyModel("2026-03-20"),
        )  # fmt: skip
        gcs = GroundStation(s.gcs_url)  # the simulation runs once something is connected to serial 0
        try:

            def run(seconds: float, until=None) -> bool:  # noqa: ANN001
                t_end = time.monotonic() + seconds
                while time.monotonic() < t_end:
                    bridge.poll(timeout=0.005)
                    gcs.pump(0.0)
                    if until is not None and until():
                        return True
                return False

            assert run(20.0, lambda: bridge.health.imu_samples > 200), bridge.health.history
            # before the SITL's GNSS has its fix (about 10 s here) ArduPilot says 0 N 0 E: never used
            h = bridge.health
            assert h.state == "waiting_for_position", h.history
            assert h.invalid_positions > 0 and bridge._pipeline is None and bridge._held is None
            run(15.0, lambda: bridge.health.state == "aligning")
            assert bridge.health.state == "aligning", bridge.health.history
            held = bridge._held
            assert held is not None and held.source == "GNSS"
            assert abs(math.degrees(held.lat) - HOME[0]) < 1e-3 and abs(math.degrees(held.lon) - HOME[1]) < 1e-3

            gcs.link.send_command_long(MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, (1.0,), 1, 1)
            t_cmd = time.monotonic()
            samples = bridge.health.imu_samples
            # the autopilot goes silent, comes back with HEARTBEAT only (it forgot the intervals) ...
            assert run(60.0, lambda: bridge.health.heartbeat_gaps >= 1), bridge.health.history
            t_back = time.monotonic()
            # ... and the bridge asks again: IMU samples of the new boot (time went back: a reboot)
            assert run(15.0, lambda: bridge.health.reboots >= 1), bridge.health.history
            t_imu = time.monotonic()
            assert t_imu - t_back < 5.0, (t_back - t_cmd, t_imu - t_back)
            run(3.0)
            assert bridge.health.imu_samples > samples + 100
            assert bridge.health.stream_requests > len(bridge._streams)  # asked again after the reboot
        finally:
            gcs.close()
            link.close()


@pytest.mark.slow
def test_short_gnss_denied_flight_on_the_bridge_lands_near_home():
    """About 2 minutes GNSS-denied on the bridge's GPS_INPUT alone (a 500 m square at 25 m, 15 m/s, denied 50 s after
    take-off: the bridge's magnetometer offset and INS biases are calibrated while GNSS-aided first): no failsafe, the
    autopilot's EKF within the issue's bounds (RMS < 50 m, max < 150 m), landing within 50 m of home, the GPS_INPUT
    stream above 9 Hz without a pause the autopilot would notice (AP_GPS wants a mean interval under 215 ms), no IMU
    gap, the bridge's trusted outputs honest (NEES)."""
    from magnav_ins.mavlink.sitl_flight import (
        SITL_GRADE,
        SITL_MAP_SIGMA_NT,
        SITL_READING_SIGMA_NT,
        FlightPlan,
        fly_square,
    )

    plan = FlightPlan(
        home=HOME[:2], side_m=500.0, altitude_m=25.0, deny_after_s=50.0, grade=SITL_GRADE, time_limit_s=360.0,
        reading_sigma_nt=SITL_READING_SIGMA_NT, map_sigma_nt=SITL_MAP_SIGMA_NT,
    )  # fmt: skip
    out = fly_square(plan)
    print(json.dumps(out))  # shown when an assertion fails
    assert out["landed"] and not out["aborted"], out
    assert out["failsafes"] == [], out["failsafes"]
    assert out["gnss_denied_s"] >= 90.0, out
    assert out["ekf_rms_horizontal_m"] < 50.0 and out["ekf_max_horizontal_m"] < 150.0, out
    assert out["landing_from_home_m"] < 50.0, out
    assert out["output_rate_hz"] > 9.0 and out["output_max_interval_s"] < 0.6, out
    assert out["imu_gaps"] == 0, out
    assert out["bridge_trusted_fraction_denied"] > 0.95, out
    assert out["bridge_nees"] < 3.0, out
    assert np.isfinite(out["bridge_rms_horizontal_m"]) and out["bridge_rms_horizontal_m"] < 50.0, out
