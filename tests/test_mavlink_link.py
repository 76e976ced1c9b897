"""mavlink.link: SI decoding over real UDP loopback, unit quirks, signing, foreign senders, junk on the link."""

from __future__ import annotations

import math
import socket
import time

import numpy as np
import pytest

from magnav_ins.core.errors import InputError
from magnav_ins.mavlink import link as L


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def pair(**bridge_kwargs):
    port = free_udp_port()
    br = L.MavLink(f"udpin:127.0.0.1:{port}", source_system=1, source_component=191, **bridge_kwargs)
    ap = L.MavLink(
        f"udpout:127.0.0.1:{port}", source_system=1, source_component=1, signing_key=bridge_kwargs.get("signing_key")
    )
    return br, ap


def collect(link: L.MavLink, want, timeout: float = 2.0) -> list:
    got: list = []
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        got.extend(link.recv(0.02))
        if want(got):
            break
    return got


def test_highres_imu_round_trip_in_si():
    br, ap = pair()
    try:
        mag_nt = np.array([21000.0, 3000.0, 45000.0])
        ap.send_heartbeat(autopilot=True)
        ap.send_highres_imu(12.5, np.array([0.01, -0.02, 0.03]), np.array([0.1, 0.2, -9.8]), mag_nt)
        got = collect(br, lambda g: any(isinstance(m, L.ImuMessage) for m in g))
        imu = next(m for m in got if isinstance(m, L.ImuMessage))
        hb = next(m for m in got if isinstance(m, L.Heartbeat))
        assert hb.compid == 1 and imu.source == "HIGHRES_IMU"
        assert imu.t == pytest.approx(12.5, abs=1e-6)
        np.testing.assert_allclose(imu.gyro_b, [0.01, -0.02, 0.03], rtol=1e-6)
        np.testing.assert_allclose(imu.accel_b, [0.1, 0.2, -9.8], rtol=1e-6)
        np.testing.assert_allclose(imu.mag_b_nt, mag_nt, rtol=1e-5)  # sent in ArduPilot's mG*1000, read back in nT
    finally:
        br.close()
        ap.close()


@pytest.mark.parametrize(
    ("raw", "unit"),
    [
        ([0.21, 0.03, 0.45], "gauss"),
        ([210.0, 30.0, 450.0], "milligauss"),
        ([210000.0, 30000.0, 450000.0], "milligauss*1000"),
    ],
)
def test_magnetometer_scale_detection(raw, unit):
    nt, detected = L.highres_mag_to_nt(np.array(raw))
    assert detected == unit
    np.testing.assert_allclose(nt, [21000.0, 3000.0, 45000.0], rtol=1e-9)


def test_magnetometer_scale_refuses_nonsense():
    with pytest.raises(InputError, match="fits no known unit"):
        L.highres_mag_to_nt(np.array([5.0, 0.0, 0.0]))


def test_gps_week_and_odometry_covariance():
    # 2023-11-14T22:13:20Z: GPS week 2288 started 2023-11-12; + 18 leap seconds
    assert L.unix_to_gps_week(1_700_000_000.0) == (2288, (2 * 86400 + 22 * 3600 + 13 * 60 + 20 + 18) * 1000)
    for sigma in (0.5, 7.0, 120.0):
        c = L.odometry_covariance_entry(sigma)
        assert L.odometry_collapsed_sigma(c, c, c) == pytest.approx(sigma, rel=1e-12)


def test_signing_drops_unsigned_and_wrongly_signed():
    key = bytes(range(32))
    port = free_udp_port()
    br = L.MavLink(f"udpin:127.0.0.1:{port}", source_system=1, source_component=191, signing_key=key)
    good = L.MavLink(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1, signing_key=key)
    bad = L.MavLink(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1, signing_key=bytes(32))
    plain = L.MavLink(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1)
    try:
        for k in range(5):
            bad.send_highres_imu(1.0 + k, np.zeros(3), np.array([0, 0, -9.8]), None)
            plain.send_highres_imu(2.0 + k, np.zeros(3), np.array([0, 0, -9.8]), None)
        time.sleep(0.05)
        good.send_highres_imu(3.0, np.zeros(3), np.array([0, 0, -9.8]), None)
        got = collect(br, lambda g: any(isinstance(m, L.ImuMessage) and m.t == 3.0 for m in g))
        imus = [m for m in got if isinstance(m, L.ImuMessage)]
        assert [m.t for m in imus] == [3.0]
        assert br.stats.rejected_signature == 10
    finally:
        for x in (br, good, bad, plain):
            x.close()


def test_foreign_sender_is_dropped():
    port = free_udp_port()
    br = L.MavLink(f"udpin:127.0.0.1:{port}", source_system=1, source_component=191, peer_system=1, peer_component=1)
    stranger = L.MavLink(f"udpout:127.0.0.1:{port}", source_system=7, source_component=1)
    ap = L.MavLink(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1)
    try:
        stranger.send_highres_imu(5.0, np.zeros(3), np.array([0, 0, -9.8]), None)
        time.sleep(0.05)
        ap.send_highres_imu(6.0, np.zeros(3), np.array([0, 0, -9.8]), None)
        got = collect(br, lambda g: any(isinstance(m, L.ImuMessage) for m in g))
        assert [m.t for m in got if isinstance(m, L.ImuMessage)] == [6.0]
        assert br.stats.foreign_source == 1
    finally:
        for x in (br, stranger, ap):
            x.close()


def test_junk_truncated_and_forged_frames_do_not_stop_decoding():
    """10^5 junk datagrams (random bytes, truncated real frames, frames signed with the wrong key) interleaved with
    1000 real IMU messages: every real message that reaches the socket is decoded, nothing raises."""
    key = bytes(range(32))
    port = free_udp_port()
    br = L.MavLink(f"udpin:127.0.0.1:{port}", source_system=1, source_component=191, signing_key=key)
    ap = L.MavLink(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1, signing_key=key)
    forger = L.MavLink(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1, signing_key=bytes(32))
    rng = np.random.default_rng(7)
    real_frame = ap.mav.highres_imu_encode(1, 0, 0, -9.8, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0).pack(ap.mav)
    sent_real = []
    got: list = []
    try:
        for burst in range(1000):
            for _ in range(100):
                r = rng.random()
                if r < 0.6:
                    ap.write_raw(rng.integers(0, 256, rng.integers(1, 280), dtype=np.uint8).tobytes())
                elif r < 0.8:
                    ap.write_raw(real_frame[: rng.integers(1, len(real_frame) - 1)])
                else:
                    forger.send_highres_imu(5000.0 + burst, np.zeros(3), np.array([0, 0, -9.8]), None)
            t_real = 10.0 + burst
            ap.send_highres_imu(t_real, np.zeros(3), np.array([0, 0, -9.8]), None)
            sent_real.append(t_real)
            got.extend(br.recv(0.0))
        got.extend(collect(br, lambda g: any(isinstance(m, L.ImuMessage) and m.t == sent_real[-1] for m in g), 10.0))
        decoded = {m.t for m in got if isinstance(m, L.ImuMessage)}
        assert not any(t >= 5000.0 for t in decoded)  # forged frames never pass
        assert sent_real[-1] in decoded
        assert len(decoded & set(sent_real)) >= 0.9 * len(sent_real)  # UDP may drop a few under the flood
        assert br.stats.bad_data > 0 and br.stats.rejected_signature > 0
    finally:
        for x in (br, ap, forger):
            x.close()


def test_gps_input_and_global_position_sensor_encode_si():
    br, ap = pair()
    try:
        lat, lon = math.radians(-21.9), math.radians(140.6)
        ap.send_heartbeat(autopilot=True)  # a udpin link answers whoever spoke to it last
        collect(br, lambda g: any(isinstance(m, L.Heartbeat) for m in g))
        br.send_gps_input(
            t_unix=1.7e9,
            lat=lat,
            lon=lon,
            h_msl=320.0,
            v_n=np.array([10.0, -2.0, 0.5]),
            sigma_h=12.0,
            sigma_v=3.0,
            sigma_speed=0.2,
            healthy=True,
        )
        br.send_global_position_sensor(
            target_system=1,
            target_component=1,
            t_usec=5_000_000,
            processing_us=0,
            source="magnetic",
            lat=lat,
            lon=lon,
            h_ellipsoid=360.0,
            h_msl=320.0,
            sigma_h=12.0,
            sigma_v=3.0,
            healthy=False,
        )
        got = collect(ap, lambda g: sum(isinstance(m, L.OutputMessage) for m in g) >= 2)
        outs = {m.kind: m for m in got if isinstance(m, L.OutputMessage)}
        gi = outs["gps_input"]
        assert gi.healthy and gi.lat == pytest.approx(lat, abs=1e-8) and gi.sigma_h == pytest.approx(12.0)
        assert gi.fields["fix_type"] == 3 and gi.fields["time_week"] > 2000
        gps = outs["global_position_sensor"]
        assert not gps.healthy and gps.lon == pytest.approx(lon, abs=1e-8)
    finally:
        br.close()
        ap.close()


def test_record_path_writes_every_received_frame_as_a_playable_tlog(tmp_path):
    """``record_path`` (``magnav-ins bridge --record-tlog``) appends each frame received, junk left out, as a tlog
    that the playback (and ``iter_tlog``) reads back with the same content; a reconnect does not stop it."""
    from magnav_ins.mavlink.playback import TlogPlayback

    rec = tmp_path / "bridge.tlog"
    br, ap = pair(record_path=rec)
    try:
        ap.send_heartbeat(autopilot=True)
        for k in range(5):
            ap.send_highres_imu(1.0 + 0.01 * k, np.array([0.01, 0.0, 0.0]), np.array([0.0, 0.0, -9.8]), None)
        ap.write_raw(b"\xfd\x09junk that is not a frame")
        got = collect(br, lambda g: sum(isinstance(m, L.ImuMessage) for m in g) == 5)
        br.reconnect()
        ap.send_highres_imu(1.05, np.array([0.01, 0.0, 0.0]), np.array([0.0, 0.0, -9.8]), None)
        got += collect(br, lambda g: any(isinstance(m, L.ImuMessage) for m in g))
    finally:
        br.close()
        ap.close()
    assert sum(isinstance(m, L.ImuMessage) for m in got) == 6
    back = [m for m in L.iter_tlog(rec) if isinstance(m, L.ImuMessage)]
    assert [round(m.t, 3) for m in back] == [1.0, 1.01, 1.02, 1.03, 1.04, 1.05]
    now = [math.inf]
    play = TlogPlayback(rec, lambda: now[0])
    assert sum(isinstance(m, L.ImuMessage) for m in play.recv()) == 6
    assert time.time() - 60 < play.first_t <= time.time()  # stamped with the receive time (Unix s)


def test_ekf_status_report_is_decoded():
    """EKF_STATUS_REPORT (the SITL ground station logs it): flags and the test ratios EKF3 calls variances."""
    br, ap = pair()
    try:
        ap.mav.ekf_status_report_send(831, 0.1, 0.25, 0.05, 0.3, 0.0)
        got = collect(br, lambda g: any(isinstance(m, L.EkfStatusMessage) for m in g))
    finally:
        br.close()
        ap.close()
    s = next(m for m in got if isinstance(m, L.EkfStatusMessage))
    assert s.flags == 831 and (s.velocity, s.pos_horiz, s.pos_vert, s.compass) == pytest.approx((0.1, 0.25, 0.05, 0.3))
