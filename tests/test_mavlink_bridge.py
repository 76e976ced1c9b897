"""The MAVLink bridge against an emulated autopilot on UDP loopback: start-up, outputs vs truth, robustness, signing.

Each test plays a simulated flight in real time (a few seconds) through :class:`AutopilotEmulator`; the bridge runs in
the test's thread exactly as ``magnav-ins bridge`` runs it.
"""

from __future__ import annotations

import math
import socket
import threading
import time

import numpy as np
import pytest

from magnav_ins.core.frames import horizontal_error_m
from magnav_ins.maps.builtin import load_map
from magnav_ins.mavlink.bridge import Bridge, BridgeConfig, ScalarAnomalyModel
from magnav_ins.mavlink.emulator import AutopilotEmulator, flight_over_map
from magnav_ins.mavlink.link import MavLink
from magnav_ins.mavlink.replay import make_online_pipeline

START = (math.radians(-21.93), math.radians(140.62))  # inside builtin:osborne-magnetic, varied anomaly


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def osborne():
    return load_map("builtin:osborne-magnetic")


def _bridge(
    port: int,
    fmap,
    date: str,
    *,
    output: str = "global_position_sensor",
    key: bytes | None = None,
    init=None,
    fusion: str = "ukf",
    **cfg,
) -> Bridge:
    link = MavLink(f"udpin:127.0.0.1:{port}", source_system=1, peer_system=1, peer_component=1, signing_key=key)
    cfg.setdefault("sample_type", "mean")  # the emulator's samples are interval means
    cfg.setdefault("send_while_gnss", "yes")  # these tests look at the outputs; the GNSS policy has its own
    config = BridgeConfig(output=output, output_rate_hz=5.0, init=init, init_sigma_m=10.0, **cfg)

    def factory(nav0, sigma_m):
        return make_online_pipeline(nav0, sigma_m, fmap, grade="tactical", matcher="mlr", fusion=fusion)

    return Bridge(link, config, factory, ScalarAnomalyModel(date))


def _errors(outputs, truth) -> np.ndarray:
    """Horizontal error of each healthy GLOBAL_POSITION_SENSOR output against the truth at its time stamp."""
    out = [o for o in outputs if o.kind == "global_position_sensor" and o.healthy]
    t = np.array([o.fields["time_usec"] * 1e-6 for o in out])
    lat = np.interp(t, truth.t, truth.lat)
    lon = np.interp(t, truth.t, truth.lon)
    return horizontal_error_m([o.lat for o in out], [o.lon for o in out], lat, lon)


def test_vehicle_at_rest_heartbeats_and_outputs_within_5_s_and_50_m(osborne):
    flight = flight_over_map(
        osborne, start=START, heading=0.3, speed_mps=0.0, duration_s=30.0, rate_hz=100.0, altitude_m=400.0, seed=3
    )
    port = free_udp_port()
    bridge = _bridge(port, osborne, flight.date)
    ap = MavLink(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1)
    with AutopilotEmulator(ap, flight.truth, flight.imu, flight.mag_b_nt) as emu:
        bridge.run(duration_s=8.0)
        time.sleep(0.2)
    rec = emu.record
    assert rec.first_heartbeat_s is not None and rec.first_heartbeat_s < 5.0
    assert rec.first_output_s is not None and rec.first_output_s < 5.0
    err = _errors(rec.outputs, flight.truth)
    assert len(err) >= 20, f"only {len(err)} healthy outputs in 8 s at 5 Hz"
    assert err.max() < 50.0
    assert bridge.health.imu_samples > 500
    # the bridge asked the autopilot for its streams (SET_MESSAGE_INTERVAL = MAV_CMD 511)
    assert any(c.command == 511 for c in rec.commands)
    bridge.link.close()
    ap.close()


def test_flight_over_map_tracks_truth_like_the_offline_pipeline(osborne):
    """40 s of flight at 70 m/s, 50 Hz IMU played 4x faster than real time: the bridge's outputs vs truth, and the
    same factory's pipeline run offline over the same samples."""
    flight = flight_over_map(
        osborne,
        start=START,
        heading=math.radians(80),
        speed_mps=70.0,
        duration_s=40.0,
        rate_hz=50.0,
        altitude_m=400.0,
        seed=5,
    )
    port = free_udp_port()
    bridge = _bridge(port, osborne, flight.date, reading_interval_s=0.5)
    ap = MavLink(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1)
    with AutopilotEmulator(ap, flight.truth, flight.imu, flight.mag_b_nt, speedup=4.0) as emu:
        bridge.run(duration_s=11.0)
    err_bridge = _errors(emu.record.outputs, flight.truth)
    assert len(err_bridge) >= 30

    # offline: the same pipeline over the same samples (readings every 0.5 s)
    truth, imu = flight.truth, flight.imu
    model = ScalarAnomalyModel(flight.date)
    init = truth.at(0)
    pipe = make_online_pipeline(init, 10.0, osborne, grade="tactical", matcher="mlr", fusion="ukf")
    errs = []
    next_r = 0.0
    for k in range(1, len(imu)):
        pipe.push_imu(imu.t[k], imu.gyro_b[k], imu.accel_b[k])
        if imu.t[k] >= next_r:
            pipe.push_reading(imu.t[k], model(flight.mag_b_nt[k], pipe.estimate().nav))
            next_r = imu.t[k] + 0.5
        if k % 50 == 0:
            nav = pipe.estimate().nav
            errs.append(float(horizontal_error_m(nav.lat, nav.lon, truth.lat[k], truth.lon[k])))
    rms_offline = float(np.sqrt(np.mean(np.square(errs))))
    rms_bridge = float(np.sqrt(np.mean(np.square(err_bridge))))
    assert rms_bridge < 1.5 * rms_offline + 10.0, (rms_bridge, rms_offline)
    bridge.link.close()
    ap.close()


def test_junk_reboot_and_dropout_do_not_stop_the_bridge(osborne):
    flight = flight_over_map(
        osborne, start=START, heading=0.0, speed_mps=0.0, duration_s=60.0, rate_hz=100.0, altitude_m=400.0, seed=7
    )
    port = free_udp_port()
    bridge = _bridge(port, osborne, flight.date, output="gps_input", gps_id=1)  # GPS2: GPS_RAW_INT is the GNSS
    ap = MavLink(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1)
    junk = MavLink(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1)
    rng = np.random.default_rng(11)
    stop = threading.Event()

    def flood() -> None:
        while not stop.is_set():
            for _ in range(200):
                junk.write_raw(rng.integers(0, 256, rng.integers(1, 280), dtype=np.uint8).tobytes())
            time.sleep(0.01)

    emu = AutopilotEmulator(ap, flight.truth, flight.imu, flight.mag_b_nt).start()
    flooder = threading.Thread(target=flood, daemon=True)
    flooder.start()
    bridge.run(duration_s=3.0)
    emu.reboot()  # 1.5 s silent, then the clock restarts and only HEARTBEAT comes until HIGHRES_IMU is asked for
    bridge.run(duration_s=8.0, should_stop=lambda: bridge.health.reboots >= 1)
    assert emu.record.streaming_since_reboot_s is not None and emu.record.streaming_since_reboot_s < 5.0
    bridge.run(duration_s=1.0)
    emu.dropout(1.5)  # 1.5 s of IMU samples lost
    bridge.run(duration_s=1.2)
    # at rest the bridge holds its aligned position: untrusted while the IMU is stale
    assert not bridge.health.healthy and bridge.health.state in ("aligning", "degraded")
    bridge.run(duration_s=2.5)
    stop.set()
    emu.stop()
    flooder.join()
    h = bridge.health
    assert h.reboots >= 1 and h.imu_gaps >= 1
    assert bridge.link.stats.bad_data > 100
    assert h.outputs_sent > 30
    assert h.untrusted_outputs >= 1  # during the dropout GPS_INPUT said "no fix"
    assert any("IMU stale" in line or "degraded" in line for line in h.history)
    assert h.state in ("aligning", "running") and h.healthy
    for o in emu.record.outputs:
        if o.healthy:  # every position it vouched for is near the truth
            assert horizontal_error_m(o.lat, o.lon, flight.truth.lat[0], flight.truth.lon[0]) < 50.0
    bridge.link.close()
    ap.close()
    junk.close()


def test_signing_enabled_drops_the_unsigned_autopilot(osborne):
    flight = flight_over_map(
        osborne, start=START, heading=0.0, speed_mps=0.0, duration_s=10.0, rate_hz=50.0, altitude_m=400.0, seed=9
    )
    port = free_udp_port()
    bridge = _bridge(port, osborne, flight.date, key=bytes(range(32)))
    ap = MavLink(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1)  # not signed
    with AutopilotEmulator(ap, flight.truth, flight.imu, flight.mag_b_nt):
        bridge.run(duration_s=2.0)
    assert bridge.health.imu_samples == 0 and bridge.health.state == "waiting_for_imu"
    st = bridge.link.stats
    assert st.rejected_signature > 50
    # every one of them unsigned (the autopilot does not sign), none counted as junk
    assert st.rejected_unsigned == st.rejected_signature and st.bad_data == 0
    bridge.link.close()
    ap.close()


def test_magnetometer_scale_logged_and_announced_once(osborne, caplog):
    """The emulator sends ArduPilot's old milligauss x 1000 scale in every HIGHRES_IMU (about 150 of them here): the
    unit is logged once and announced to the pilot once (STATUSTEXT), not per sample."""
    import logging

    flight = flight_over_map(
        osborne, start=START, heading=0.0, speed_mps=0.0, duration_s=10.0, rate_hz=50.0, altitude_m=400.0, seed=3
    )
    port = free_udp_port()
    bridge = _bridge(port, osborne, flight.date)
    ap = MavLink(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1)
    with caplog.at_level(logging.INFO, logger="magnav_ins.mavlink"):
        with AutopilotEmulator(ap, flight.truth, flight.imu, flight.mag_b_nt) as emu:
            bridge.run(duration_s=4.0)
            time.sleep(0.3)
    logged = [r.getMessage() for r in caplog.records if "HIGHRES_IMU magnetometer" in r.getMessage()]
    said = [x for x in emu.record.statustexts if "magnetometer" in x]
    assert bridge.health.imu_samples > 100
    assert len(logged) == 1 and "milligauss*1000" in logged[0], logged
    assert said == ["magnav: magnetometer in mG x 1000"], emu.record.statustexts
    assert bridge.health.mag_unit == "milligauss*1000"
    bridge.link.close()
    ap.close()
