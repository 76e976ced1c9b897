"""Barometric height aid: the ICAO standard atmosphere against published tables, the baro filter against synthetic
pressure series, SCALED_PRESSURE encoding, and a climbing flight through the bridge with and without a barometer."""

from __future__ import annotations

import logging
import math
import socket
import time

import numpy as np
import pytest

from magnav_ins.core import atmosphere as isa
from magnav_ins.core.errors import InputError
from magnav_ins.mavlink.baro import BaroHeight, hold_height

START = (math.radians(-21.93), math.radians(140.62))  # inside builtin:osborne-magnetic


# ------------------------------------------------------------------------------------------ ISA formula
@pytest.mark.parametrize(
    ("h_m", "geopotential", "p_hpa", "tol_hpa"),
    [
        (0.0, False, 1013.25, 1e-9),
        # U.S. Standard Atmosphere 1976 / ICAO, geometric altitude tables: 1000 m 898.76 hPa, 5000 m 540.48 hPa
        (1000.0, False, 898.76, 0.005),
        (5000.0, False, 540.48, 0.005),
        # ICAO Doc 7488/3 Table, geopotential altitude: 1000 m 898.746 hPa, 5000 m 540.199, 11000 m 226.320
        (1000.0, True, 898.746, 0.0005),
        (5000.0, True, 540.199, 0.0005),
        (11000.0, True, 226.320, 0.0005),
    ],
)
def test_isa_pressure_matches_published_tables(h_m, geopotential, p_hpa, tol_hpa):
    assert isa.isa_pressure_pa(h_m, geopotential=geopotential) / 100.0 == pytest.approx(p_hpa, abs=tol_hpa)
    # and the inverse gives the table's altitude back from the table's pressure (to the table's rounding)
    dh_dp = isa.R_AIR * isa.isa_temperature_k(h_m, geopotential=geopotential) / (isa.G0 * p_hpa * 100.0)  # m/Pa
    h_back = isa.pressure_altitude_m(p_hpa * 100.0, geopotential=geopotential)
    assert h_back == pytest.approx(h_m, abs=dh_dp * tol_hpa * 100.0 + 1e-6)


def test_isa_constants_and_temperature():
    assert isa.EXPONENT == pytest.approx(0.190263, abs=1e-6)
    assert isa.R_AIR == pytest.approx(287.05287, abs=1e-5)
    assert isa.TROPOPAUSE_P_PA == pytest.approx(22632.06, abs=0.05)  # Doc 7488: 2.263206e4 Pa at 11 km
    assert isa.isa_temperature_k(11000.0, geopotential=True) == pytest.approx(216.65)
    # 1 km geometric is 999.843 m geopotential
    assert isa.geopotential_m(1000.0) == pytest.approx(1000.0 * 6356766.0 / 6357766.0, abs=1e-9)


def test_isa_round_trip_altitude_pressure_altitude():
    h = np.linspace(-1000.0, 11000.0, 2401)
    p = isa.isa_pressure_pa(h)
    assert np.all(np.diff(p) < 0)
    np.testing.assert_allclose(isa.pressure_altitude_m(p), h, atol=1e-6)
    np.testing.assert_allclose(isa.geometric_m(isa.geopotential_m(h)), h, atol=1e-8)
    # a QNH reference shifts the zero: the altitude above the level where p = QNH
    qnh = 102_000.0
    assert isa.pressure_altitude_m(isa.isa_pressure_pa(300.0, p_ref_pa=qnh), p_ref_pa=qnh) == pytest.approx(300.0)


@pytest.mark.parametrize("p", [math.nan, -5.0, 0.0, 1000.0])
def test_isa_refuses_nonsense_pressure(p):
    with pytest.raises(InputError, match="pressure|troposphere"):
        isa.pressure_altitude_m(p)


def test_isa_refuses_heights_above_the_troposphere():
    with pytest.raises(InputError, match="troposphere"):
        isa.isa_pressure_pa(np.array([100.0, 20_000.0]))


# ------------------------------------------------------------------------------------------ the baro filter
def _climb(rate_hz: float = 20.0, seconds: float = 30.0, climb_mps: float = 2.0, noise_pa: float = 2.0, seed=1):
    """Height 300 m for 5 s, then a steady climb: times s, true height m, noisy ISA pressure Pa."""
    t = np.arange(0.0, seconds, 1.0 / rate_hz)
    h = 300.0 + climb_mps * np.clip(t - 5.0, 0.0, None)
    p = np.asarray(isa.isa_pressure_pa(h)) + np.random.default_rng(seed).normal(0.0, noise_pa, len(t))
    return t, h, p


def test_baro_height_follows_a_steady_climb_without_lag():
    t, h, p = _climb()
    b = BaroHeight()
    err, rate_err = [], []
    for k in range(len(t)):
        b.push(t[k], p[k])
        if k == 80:  # t = 4 s: the INS initialises at 1000 m (ellipsoidal); the baro height is relative to it
            b.set_reference(1000.0, t[k])
        if t[k] >= 7.0:  # 2 s into the climb: the 1 s fit window holds only climbing samples
            t_q = t[k] + 0.02  # an IMU time just after the sample
            err.append(b.height(t_q) - (1000.0 + 2.0 * (t_q - 5.0)))
            rate_err.append(b.climb_rate(t_q) - 2.0)
    err = np.array(err)
    assert b.health.samples == len(t) and b.health.state == "active"
    assert np.abs(err).max() < 0.35, np.abs(err).max()  # 2 Pa = 0.17 m noise; no lag at 2 m/s
    # no bias along the climb (the reference, a 1 s fit, is good to ~0.05 m; a lagging filter would sit 1-2 m below)
    assert abs(err.mean()) < 0.1
    assert np.abs(rate_err).max() < 0.4 and abs(np.mean(rate_err)) < 0.05


def test_baro_height_drops_and_counts_bad_pressures_and_spikes(caplog):
    t, h, p = _climb(climb_mps=0.0, seconds=10.0)
    p[50:200:10] += 600.0  # isolated 600 Pa (50 m) spikes: the running median removes them
    bad = {30: math.nan, 60: -1.0, 90: 0.0, 120: 5.0e5, 150: 1.0e3}
    b = BaroHeight()
    b.set_reference(300.0, 0.0)
    worst = 0.0
    with caplog.at_level(logging.WARNING, logger="magnav_ins.mavlink.baro"):
        for k in range(len(t)):
            b.push(t[k], bad.get(k, p[k]))
            if k > 5:
                worst = max(worst, abs(b.height(t[k]) - 300.0))
        assert not b.push(t[-1], p[-1])  # a repeated time stamp
        assert not b.push(t[-1] - 0.5, p[-1])  # a small step back
    assert b.health.rejected == 5 and b.health.out_of_order == 2
    assert b.health.samples == len(t) - 5
    assert worst < 0.4, worst
    assert "dropped (implausible" in caplog.text


def test_baro_stale_holds_the_last_height_then_recovers(caplog):
    t, h, p = _climb(seconds=20.0)
    b = BaroHeight(stale_s=2.0)
    b.set_reference(300.0, 0.0)
    for k in range(len(t)):
        if t[k] < 12.0 or t[k] >= 16.0:  # 4 s without pressure, climbing at 2 m/s
            b.push(t[k], p[k])
        if t[k] == pytest.approx(11.95):
            h_last = b.height(t[k])
        if 12.0 <= t[k] < 16.0:
            with caplog.at_level(logging.WARNING, logger="magnav_ins.mavlink.baro"):
                h_q = b.height(t[k])
            if t[k] > 14.0:  # over 2 s after the last sample (11.95 s): the last baro height held, climb rate 0
                assert b.health.state == "stale"
                assert h_q == pytest.approx(h_last, abs=0.05)
                assert b.climb_rate(t[k]) == 0.0
            elif t[k] < 13.9:  # fresh, extrapolated for at most 0.25 s past the newest median
                assert b.health.state == "active" and abs(h_q - h_last) < 2.0 * 0.4
    assert b.health.stale_events == 1 and b.health.state == "active"
    assert "no pressure sample for 2.0 s, holding the last baro height" in caplog.text
    assert b.height(t[-1]) == pytest.approx(300.0 + 2.0 * (t[-1] - 5.0), abs=0.35)


def test_baro_clock_reset_keeps_the_reference_and_deferred_reference():
    b = BaroHeight()
    b.set_reference(50.0, 0.0)
    assert b.height(0.0) is None and not b.referenced  # no pressure yet: the hold stays where it is
    p0 = float(isa.isa_pressure_pa(120.0))
    for k in range(4):
        b.push(0.05 * k, p0)
        assert b.height(0.05 * k) is None  # waiting for a full median
    b.push(0.2, p0)
    assert b.height(0.2) == pytest.approx(50.0)
    for k in range(5, 100):  # to t = 4.95 s
        b.push(0.05 * k, p0)
    for k in range(100, 140):  # climbing at 5 m/s from 120 m
        b.push(0.05 * k, float(isa.isa_pressure_pa(120.0 + 5.0 * (0.05 * k - 4.95))))
    h_last = b.height(6.95)
    assert h_last == pytest.approx(60.0, abs=0.01)
    # the autopilot reboots: the IMU clock restarts first; the last baro height is kept (no extrapolation by -6 s)
    assert b.height(1.0) == pytest.approx(h_last)
    p1 = float(isa.isa_pressure_pa(130.0))  # then the barometer, its clock back to 1 s, at 130 m
    for k in range(10):
        b.push(1.0 + 0.05 * k, p1)
    assert b.health.clock_resets == 1
    assert b.height(1.5) == pytest.approx(60.0, abs=1e-6)


def test_hold_height_moves_the_ukf_and_free_inertial_clamp_not_the_graph():
    from magnav_ins.core.frames import WGS84_OMEGA_E, q_nb_from_euler
    from magnav_ins.core.types import NavState
    from magnav_ins.ins.earth import gravity_n
    from magnav_ins.mavlink.replay import make_online_pipeline

    lat, lon = START
    nav0 = NavState(0.0, lat, lon, 400.0, np.zeros(3), q_nb_from_euler(0.0, 0.0, 0.0))
    accel = np.array([0.0, 0.0, -gravity_n(lat, 400.0)[2]])
    gyro = np.array([WGS84_OMEGA_E * math.cos(lat), 0.0, -WGS84_OMEGA_E * math.sin(lat)])
    for fusion in ("ukf", "free_inertial"):
        pipe = make_online_pipeline(nav0, 10.0, None, matcher="none", fusion=fusion)
        assert hold_height(pipe, 437.5)
        pipe.push_imu(0.01, gyro, accel)
        nav = pipe.estimate().nav
        assert nav.h == 437.5 and nav.v_n[2] == 0.0
    assert not hold_height(make_online_pipeline(nav0, 10.0, None, matcher="none", fusion="graph"), 437.5)
    free = make_online_pipeline(nav0, 10.0, None, matcher="none", fusion="ukf", altitude_hold=False)
    assert not hold_height(free, 437.5)


def test_scaled_pressure_tlog_round_trip(tmp_path):
    from magnav_ins.mavlink.link import PressureMessage, iter_tlog, write_tlog

    sent = [PressureMessage(12.345 + 0.05 * k, 95_000.0 + 13.7 * k, 21.5, 1, 1) for k in range(20)]
    write_tlog(tmp_path / "p.tlog", sent)
    got = [m for m in iter_tlog(tmp_path / "p.tlog") if isinstance(m, PressureMessage)]
    assert len(got) == 20
    for a, b in zip(sent, got, strict=True):
        assert b.t == pytest.approx(round(a.t * 1e3) * 1e-3, abs=1e-9)  # time_boot_ms
        assert b.pressure_pa == pytest.approx(a.pressure_pa, abs=0.01)  # float32 hPa: ~0.006 Pa at 950 hPa
        assert b.temperature_c == pytest.approx(21.5)


# ------------------------------------------------------------------------------------------ bridge, climbing
def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def climb_flight():
    """84 s at 20 m/s over the Osborne map, 50 Hz IMU: level at 400 m, +100 m between 10 s and 70 s (peak 2.6 m/s),
    level again."""
    from magnav_ins.maps.builtin import load_map
    from magnav_ins.mavlink.emulator import flight_over_map

    fmap = load_map("builtin:osborne-magnetic")
    flight = flight_over_map(
        fmap,
        start=START,
        heading=math.radians(80),
        speed_mps=20.0,
        duration_s=84.0,
        rate_hz=50.0,
        altitude_m=400.0,
        seed=5,
        climb_m=100.0,
        climb_window_s=(10.0, 70.0),
    )
    return fmap, flight


@pytest.mark.parametrize("pressure_rate_hz", [20.0, None], ids=["baro", "no_baro"])
def test_bridge_height_follows_a_climb_with_a_barometer(climb_flight, pressure_rate_hz, caplog):
    """Played 8x faster than real time. With SCALED_PRESSURE (20 Hz, 2 Pa noise) every healthy output's height is
    within 3 m of the truth (measured max 0.5 m), a 3 s pressure outage in the final level segment is detected and the
    height held; without it the height stays at the initial 400 m (100 m off at the end)."""
    from magnav_ins.mavlink.bridge import Bridge, BridgeConfig, ScalarAnomalyModel
    from magnav_ins.mavlink.emulator import AutopilotEmulator
    from magnav_ins.mavlink.link import MavLink
    from magnav_ins.mavlink.replay import make_online_pipeline

    fmap, flight = climb_flight
    truth = flight.truth
    port = _free_udp_port()
    link = MavLink(f"udpin:127.0.0.1:{port}", source_system=1, peer_system=1, peer_component=1)
    config = BridgeConfig(
        output="global_position_sensor", output_rate_hz=10.0, init_sigma_m=10.0, reading_interval_s=0.5,
        send_while_gnss="yes", sample_type="mean",
    )  # fmt: skip

    def factory(nav0, sigma_m):
        return make_online_pipeline(nav0, sigma_m, fmap, grade="tactical", matcher="mlr", fusion="ukf")

    bridge = Bridge(link, config, factory, ScalarAnomalyModel(flight.date))
    ap = MavLink(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1)
    emu = AutopilotEmulator(
        ap, truth, flight.imu, flight.mag_b_nt, speedup=8.0, pressure_rate_hz=pressure_rate_hz, seed=3
    )
    # the outage is set on the flight clock and the runs end on it, so a slow (loaded) machine makes the bridge late
    # (the 4 MiB receive buffer keeps every sample), not the test wrong
    emu.pause_pressure(3.0, at_s=74.0)
    with caplog.at_level(logging.WARNING, logger="magnav_ins.mavlink.baro"), emu:
        bridge.run(duration_s=60.0, should_stop=lambda: bridge.health.last_imu_t > 83.5)
        time.sleep(0.2)
    # every output (GLOBAL_POSITION_SENSOR carries the estimate also when flagged unhealthy: the horizontal sigma
    # outgrows --max-sigma late in this flight, which is not what this test is about)
    outs = [o for o in emu.record.outputs if o.kind == "global_position_sensor"]
    t = np.array([o.fields["time_usec"] * 1e-6 for o in outs])
    err = np.array([o.h for o in outs]) - np.interp(t, truth.t, truth.h)
    h = bridge.health
    print(f"height error max {np.abs(err).max():.2f} m, final {err[-1]:.2f} m; {len(outs)} outputs to {t[-1]:.1f} s")
    assert len(outs) > 60 and t[-1] > 80.0
    if pressure_rate_hz is not None:
        assert np.abs(err).max() < 3.0, np.abs(err).max()
        assert h.pressures > 1000 and h.pressures_rejected == 0
        assert h.baro_stale_events == 1 and h.baro_state == "active"
        assert "holding the last baro height" in caplog.text
    else:
        assert h.pressures == 0 and h.baro_state == "none"
        assert np.all(np.array([o.h for o in outs]) == pytest.approx(400.0, abs=0.01))
        assert err[-1] < -95.0
    link.close()
    ap.close()


class _FakeLink:
    """A link that hands the bridge queued messages and records what it sends (method name, keyword arguments)."""

    def __init__(self) -> None:
        self.inbox: list = []
        self.sent: list[tuple[str, tuple, dict]] = []

    def recv(self, timeout: float = 0.0):  # noqa: ARG002
        out, self.inbox = self.inbox, []
        return out

    def __getattr__(self, name: str):
        if not name.startswith("send_") and name not in ("request_message_interval", "reconnect", "close"):
            raise AttributeError(name)
        return lambda *a, **kw: self.sent.append((name, a, kw))


def test_bridge_sends_the_baro_height_and_climb_rate_and_says_when_the_baro_is_lost():
    """No network: a vehicle at rest on the ground whose barometer says it climbs at 2 m/s (100 Hz IMU, 20 Hz
    pressure, exact ISA values). GPS_INPUT carries the baro height and ``vd = -2``; a 3 s pressure gap sends one
    "baro lost" STATUSTEXT and holds the height, and the rate returns to 0."""
    from magnav_ins.core.frames import WGS84_OMEGA_E
    from magnav_ins.ins.earth import gravity_n
    from magnav_ins.mavlink.bridge import Bridge, BridgeConfig
    from magnav_ins.mavlink.link import ImuMessage, PressureMessage
    from magnav_ins.mavlink.replay import make_online_pipeline

    lat, lon = START
    now = [0.0]
    link = _FakeLink()
    config = BridgeConfig(output="gps_input", output_rate_hz=5.0, init=(lat, lon, 250.0, 0.3), sample_type="mean")
    bridge = Bridge(
        link,  # type: ignore[arg-type]
        config,
        lambda nav0, s: make_online_pipeline(nav0, s, None, matcher="none", fusion="ukf"),
        clock=lambda: now[0],
        wall_clock=lambda: 1.7e9 + now[0],
    )
    accel = np.array([0.0, 0.0, -gravity_n(lat, 250.0)[2]])
    gyro = np.array([WGS84_OMEGA_E * math.cos(lat), 0.0, -WGS84_OMEGA_E * math.sin(lat)])
    climb_h = []  # (t, true baro height relative to the start)
    bridge.poll()  # nothing received yet: the bridge asks for its streams
    for k in range(1, 2001):  # 20 s
        t = 0.01 * k
        now[0] = t
        link.inbox.append(ImuMessage(t, gyro, accel, None, "HIGHRES_IMU", 1, 1))
        if k % 5 == 0 and not (12.0 <= t < 15.0):
            h_rel = 2.0 * max(t - 5.0, 0.0) if t < 12.0 else 14.0 + 2.0 * (t - 15.0)
            link.inbox.append(PressureMessage(t, float(isa.isa_pressure_pa(100.0 + h_rel)), 15.0, 1, 1))
            climb_h.append((t, h_rel))
        bridge.poll()
    gps = [(kw["t_unix"] - 1.7e9, kw["h_msl"], kw["v_n"][2]) for name, _, kw in link.sent if name == "send_gps_input"]
    gps = np.array([g for g in gps if g[0] > 1.0])
    statustext = [a[1] for name, a, _ in link.sent if name == "send_statustext"]
    assert any(c[1][0] == "SCALED_PRESSURE" for c in link.sent if c[0] == "request_message_interval")
    climbing = (gps[:, 0] > 7.0) & (gps[:, 0] < 12.0)
    # the output is sent at the poll that follows the IMU sample: the INS (and its held height) is one IMU step behind
    np.testing.assert_allclose(gps[climbing, 1], 250.0 + 2.0 * (gps[climbing, 0] - 5.0), atol=0.05)
    np.testing.assert_allclose(gps[climbing, 2], -2.0, atol=1e-3)
    held = (gps[:, 0] > 14.1) & (gps[:, 0] < 15.0)
    np.testing.assert_allclose(gps[held, 1], 250.0 + 14.0, atol=0.3)  # the last baro height (at 11.95 s)
    np.testing.assert_allclose(gps[held, 2], 0.0)
    assert statustext.count("magnav: baro lost, height held") == 1 and "magnav: baro back" in statustext
    late = gps[:, 0] > 17.0
    np.testing.assert_allclose(gps[late, 1], 250.0 + 14.0 + 2.0 * (gps[late, 0] - 15.0), atol=0.05)
    assert bridge.health.pressures == len(climb_h) and bridge.health.baro_stale_events == 1
