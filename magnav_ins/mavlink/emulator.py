"""An autopilot emulator for tests and benchmarks without hardware.

It plays a simulated flight over a map as an ArduPilot-like autopilot would: HEARTBEAT at 1 Hz, HIGHRES_IMU at the
IMU rate (magnetometer in ArduPilot's milligauss x 1000 scale), ATTITUDE, GLOBAL_POSITION_INT and GPS_RAW_INT (a 3D
fix from the truth, 1 m accuracy, until :meth:`AutopilotEmulator.lose_gnss`) at 5 Hz, optionally EXTENDED_SYS_STATE
and SCALED_PRESSURE from the truth height (ICAO standard atmosphere plus white noise), paced to the wall clock (or
faster by ``speedup``). Like a fresh ArduPilot link it streams only HEARTBEAT until SET_MESSAGE_INTERVAL asks for
HIGHRES_IMU, and a :meth:`~AutopilotEmulator.reboot` makes it forget that request, go silent for a moment and restart
its clock. It records every position message the bridge sends back, so a test can compare them with the truth. Runs
in a background thread; MAVLink goes through :mod:`.link` (the only pymavlink import).
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field

import numpy as np

from ..core.frames import C_nb_from_q, euler_from_q_nb
from ..core.types import ImuBatch, NavTrajectory
from .link import (
    MAV_TYPE_ONBOARD_CONTROLLER,
    MSG_ID,
    SET_MESSAGE_INTERVAL,
    CommandMessage,
    Heartbeat,
    MavLink,
    OutputMessage,
    StatusTextMessage,
)


def magnetometer_body_nt(traj: NavTrajectory, anomaly_nt: np.ndarray, main_field_ned_nt: np.ndarray) -> np.ndarray:
    """Body-frame (FRD) magnetometer vector (N,3) nT along a trajectory: the main field (NED, (3,) or (N,3)) plus a
    total-field anomaly ``anomaly_nt`` (N,) along the main-field direction (the usual small-anomaly approximation:
    the anomaly of the total field equals the projection of the anomalous vector onto the main field)."""
    b_main = np.broadcast_to(np.asarray(main_field_ned_nt, float), (len(traj), 3))
    unit = b_main / np.linalg.norm(b_main, axis=1, keepdims=True)
    b_n = b_main + np.asarray(anomaly_nt, float)[:, None] * unit
    c_nb = C_nb_from_q(traj.q_nb)
    return np.einsum("nji,nj->ni", c_nb, b_n)


@dataclass
class EmulatorRecord:
    outputs: list[OutputMessage] = field(default_factory=list)
    commands: list[CommandMessage] = field(default_factory=list)
    heartbeats_from_bridge: int = 0
    first_heartbeat_s: float | None = None
    first_output_s: float | None = None
    imu_sent: int = 0
    pressure_sent: int = 0
    statustexts: list[str] = field(default_factory=list)
    streaming_since_reboot_s: float | None = None  # wall time from a reboot until HIGHRES_IMU was asked for again


class AutopilotEmulator:
    """Streams ``imu`` (and ``mag_b_nt``) from ``truth`` over ``link`` in a background thread.

    ``speedup`` > 1 plays faster than real time; ``send_position`` sends GLOBAL_POSITION_INT + ATTITUDE from the truth
    (as an autopilot with a GNSS fix before it is lost would). ``pressure_rate_hz`` (None: no barometer) sends
    SCALED_PRESSURE at about that rate on the autopilot clock (at the first IMU sample at or after each due time):
    the ISA pressure of the truth height (:func:`magnav_ins.core.atmosphere.isa_pressure_pa`, the height taken as
    above the standard-pressure level) plus white noise of ``pressure_noise_pa`` Pa (1-sigma; 2 Pa, about 0.17 m, is
    an MS5611-class sensor), drawn from ``seed``.
    """

    def __init__(
        self,
        link: MavLink,
        truth: NavTrajectory,
        imu: ImuBatch,
        mag_b_nt: np.ndarray | None = None,
        *,
        speedup: float = 1.0,
        send_position: bool = True,
        loop: bool = False,
        stream_on_request: bool = True,
        pressure_rate_hz: float | None = None,
        pressure_noise_pa: float = 2.0,
        seed: int = 0,
        landed_state: str | None = None,
        gnss_sigma_m: float = 1.0,
    ) -> None:
        if len(truth) != len(imu):
            raise ValueError("truth and imu must have the same samples")
        self.link = link
        self.truth = truth
        self.imu = imu
        self.mag_b_nt = mag_b_nt
        self.speedup = speedup
        self.send_position = send_position
        self.loop = loop
        #: like a fresh ArduPilot link: only HEARTBEAT until SET_MESSAGE_INTERVAL asks for HIGHRES_IMU
        self.streaming = not stream_on_request
        self.record = EmulatorRecord()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._time_offset = 0.0  # added to imu.t; a reboot makes the clock restart near 1 s
        self._reboot_requested = False
        self._dropout_s = 0.0  # pending request: skip this many seconds of samples
        self._drop_until = -np.inf
        self._pressure_pause_s = 0.0  # pending request: send no pressure for this many seconds
        self._no_pressure_until = -np.inf
        self._no_pressure_window = (np.inf, np.inf)  # flight times (s) without pressure, set ahead
        self.pressure_rate_hz = pressure_rate_hz
        self.pressure_noise_pa = float(pressure_noise_pa)
        self._rng = np.random.default_rng(seed)
        self._pressure_pa: np.ndarray | None = None
        self._temperature_c: np.ndarray | None = None
        if pressure_rate_hz is not None:
            from ..core.atmosphere import isa_pressure_pa, isa_temperature_k

            if not (0.0 < pressure_rate_hz <= 200.0):
                raise ValueError(f"pressure_rate_hz must be in (0, 200] Hz, got {pressure_rate_hz}")
            self._pressure_pa = np.asarray(isa_pressure_pa(truth.h), float)
            self._temperature_c = np.asarray(isa_temperature_k(truth.h), float) - 273.15
        self.started_at = 0.0
        self.landed_state = landed_state
        self.gnss_sigma_m = float(gnss_sigma_m)
        self._gnss_on = True
        self._silent_until = -np.inf
        self._reboot_silence_s = 1.5
        self._reboot_wall: float | None = None

    def start(self) -> AutopilotEmulator:
        self.started_at = time.monotonic()
        self._thread = threading.Thread(target=self._run, name="autopilot-emulator", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> EmulatorRecord:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        return self.record

    def __enter__(self) -> AutopilotEmulator:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _drain(self) -> None:
        for msg in self.link.recv(0.0):
            now = time.monotonic() - self.started_at
            if isinstance(msg, OutputMessage):
                self.record.outputs.append(msg)
                if self.record.first_output_s is None:
                    self.record.first_output_s = now
            elif isinstance(msg, CommandMessage):
                self.record.commands.append(msg)
                if msg.command == SET_MESSAGE_INTERVAL and int(msg.params[0]) == MSG_ID["HIGHRES_IMU"]:
                    if not self.streaming and self._reboot_wall is not None:
                        self.record.streaming_since_reboot_s = time.monotonic() - self._reboot_wall
                        self._reboot_wall = None
                    self.streaming = True
            elif isinstance(msg, StatusTextMessage):
                self.record.statustexts.append(msg.text)
            elif isinstance(msg, Heartbeat) and msg.mav_type == MAV_TYPE_ONBOARD_CONTROLLER:
                # only the companion computer's: a router (MAVProxy) in between adds its own GCS heartbeats
                self.record.heartbeats_from_bridge += 1
                if self.record.first_heartbeat_s is None:
                    self.record.first_heartbeat_s = now

    def _run(self) -> None:
        t = self.imu.t
        n = len(t)
        k = 0
        next_hb = 0.0
        next_pos = 0.0
        next_press = -np.inf
        wall0 = time.monotonic()
        sim0 = t[0]
        while not self._stop.is_set():
            if k >= n:
                if not self.loop:
                    self._drain()
                    time.sleep(0.01)
                    continue
                k = 0
                wall0 = time.monotonic()
                sim0 = t[0]
                self._time_offset += t[-1] - t[0] + (t[1] - t[0])
            if not self.streaming:  # the flight goes on, unseen, until the bridge asks for the IMU
                wall0 = time.monotonic()
                sim0 = t[k] if k < n else t[-1]
            sim_now = sim0 + (time.monotonic() - wall0) * self.speedup
            if self._reboot_requested and k < n:
                self._time_offset = 1.0 - t[k]
                self._reboot_requested = False
                self.streaming = False  # a rebooted ArduPilot forgets every SET_MESSAGE_INTERVAL
                self._reboot_wall = time.monotonic()
                self._silent_until = time.monotonic() + self._reboot_silence_s
                wall0, sim0 = time.monotonic(), t[k]
            if time.monotonic() < self._silent_until:  # rebooting: nothing on the link
                time.sleep(0.01)
                continue
            if self._dropout_s > 0.0 and k < n:
                self._drop_until = t[k] + self._dropout_s
                self._dropout_s = 0.0
            while self.streaming and k < n and t[k] <= sim_now:
                if t[k] < self._drop_until:
                    k += 1
                    continue
                ts = t[k] + self._time_offset
                mag = None if self.mag_b_nt is None else self.mag_b_nt[k]
                self.link.send_highres_imu(ts, self.imu.gyro_b[k], self.imu.accel_b[k], mag)
                self.record.imu_sent += 1
                if ts < next_pos - 1.0:  # the clock went back (reboot)
                    next_pos = ts
                if self.send_position and ts >= next_pos:
                    roll, pitch, yaw = euler_from_q_nb(self.truth.q_nb[k])
                    self.link.send_attitude(ts, float(roll), float(pitch), float(yaw))
                    v = self.truth.v_n[k]
                    self.link.send_global_position_int(ts, self.truth.lat[k], self.truth.lon[k], self.truth.h[k], v)
                    if self._gnss_on:
                        self.link.send_gps_raw_int(
                            ts, 3, self.truth.lat[k], self.truth.lon[k], self.truth.h[k], sigma_h=self.gnss_sigma_m,
                            speed=float(np.hypot(v[0], v[1])), course=float(np.arctan2(v[1], v[0])),
                        )  # fmt: skip
                    else:  # the receiver lost its fix: ArduPilot reports fix type 1 at 0 N 0 E
                        self.link.send_gps_raw_int(ts, 1, 0.0, 0.0, 0.0, sigma_h=99.0, satellites=0)
                    if self.landed_state is not None:
                        self.link.send_extended_sys_state(self.landed_state)
                    next_pos = ts + 0.2
                if self._pressure_pa is not None and ts < next_press - 1.0:  # the clock went back (reboot)
                    next_press = ts
                if self._pressure_pa is not None and ts >= next_press:
                    if self._pressure_pause_s > 0.0:
                        self._no_pressure_until = ts + self._pressure_pause_s
                        self._pressure_pause_s = 0.0
                    w0, w1 = self._no_pressure_window
                    if ts >= self._no_pressure_until and not (w0 <= ts < w1):
                        p = self._pressure_pa[k] + self._rng.normal(0.0, self.pressure_noise_pa)
                        assert self._temperature_c is not None
                        self.link.send_scaled_pressure(ts, float(p), float(self._temperature_c[k]))
                        self.record.pressure_sent += 1
                    dt_p = 1.0 / self.pressure_rate_hz  # type: ignore[operator]
                    next_press = next_press + dt_p if next_press + dt_p > ts else ts + dt_p
                k += 1
            if time.monotonic() >= next_hb and time.monotonic() >= self._silent_until:
                self.link.send_heartbeat(autopilot=True)
                next_hb = time.monotonic() + 1.0
            self._drain()
            time.sleep(0.001)

    def dropout(self, duration_s: float) -> None:
        """Lose the next ``duration_s`` seconds of IMU samples (the flight goes on; the bridge sees a gap)."""
        self._dropout_s = float(duration_s)

    def pause_pressure(self, duration_s: float, at_s: float | None = None) -> None:
        """Send no SCALED_PRESSURE for ``duration_s`` seconds of flight (the IMU goes on): from now, or from the
        flight time ``at_s`` (s, the autopilot clock; set ahead, so that where the outage falls does not depend on
        how fast the receiver keeps up)."""
        if at_s is None:
            self._pressure_pause_s = float(duration_s)
        else:
            self._no_pressure_window = (float(at_s), float(at_s) + float(duration_s))

    def reboot(self, silence_s: float = 1.5) -> None:
        """Reboot like ArduPilot: ``silence_s`` of nothing on the link, then the clock restarts near 1 s and only
        HEARTBEAT is sent until HIGHRES_IMU is asked for again (the flight itself continues)."""
        self._reboot_silence_s = float(silence_s)
        self._reboot_requested = True

    def lose_gnss(self) -> None:
        """From now on GPS_RAW_INT reports no fix (GLOBAL_POSITION_INT, the autopilot's EKF, goes on)."""
        self._gnss_on = False


@dataclass(frozen=True)
class EmulatedFlight:
    """Truth, corrupted IMU samples and body magnetometer readings for the emulator."""

    truth: NavTrajectory
    imu: ImuBatch
    mag_b_nt: np.ndarray
    date: str


def flight_over_map(
    fmap,
    *,
    start: tuple[float, float],
    heading: float,
    speed_mps: float,
    duration_s: float,
    rate_hz: float,
    altitude_m: float,
    grade: str = "tactical",
    seed: int = 1,
    date: str = "2024-06-01",
    mag_noise_nt: float = 1.0,
    climb_m: float = 0.0,
    climb_window_s: tuple[float, float] = (0.0, 60.0),
) -> EmulatedFlight:
    """A straight flight (``speed_mps`` 0 = at rest) from ``start`` (lat, lon rad) on ``heading`` (rad) over a
    total-field anomaly map: ideal IMU from inverse mechanisation, ``grade``'s errors injected, and the body-frame
    magnetometer = IGRF main field + the map's anomaly along it + white noise. Reproducible from ``seed``.

    Level at ``altitude_m`` (m), unless ``climb_m`` (m, negative: descend) is given: then the height changes by
    ``climb_m`` between the times ``climb_window_s`` (s from the start) along a half cosine,
    ``h = altitude_m + climb_m (1 - cos(pi u)) / 2`` with ``u`` the fraction of the window (zero vertical speed and
    peak rate ``pi climb_m / (2 T)`` mid-window), body kept level (a multicopter's climb); position and velocity stay
    consistent (the horizontal track is computed at ``altitude_m``; the 1e-5 relative difference of the radii is
    ignored)."""
    from ..core.frames import meters_to_latlon
    from ..ins.imu_models import corrupt, get_grade
    from ..ins.simulate import great_circle, ideal_imu, stationary
    from ..maps.reference import igrf_ned

    rng = np.random.default_rng(seed)
    lat0, lon0 = start
    if speed_mps <= 0.0:
        truth = stationary(lat0, lon0, altitude_m, heading, duration_s, rate_hz)
    else:
        dist = speed_mps * duration_s * 1.2
        dlat, dlon = meters_to_latlon(dist * np.cos(heading), dist * np.sin(heading), lat0, altitude_m)
        truth = great_circle(lat0, lon0, lat0 + float(dlat), lon0 + float(dlon), altitude_m, speed_mps, rate_hz)
        n = int(round(duration_s * rate_hz)) + 1
        truth = truth.slice(0, min(n, len(truth)))
    if climb_m != 0.0:
        from ..core.types import NavTrajectory

        t_a, t_b = (float(x) for x in climb_window_s)
        if not (0.0 <= t_a < t_b):
            raise ValueError(f"climb_window_s must be (start, end) with 0 <= start < end, got {climb_window_s}")
        u = np.clip((truth.t - truth.t[0] - t_a) / (t_b - t_a), 0.0, 1.0)
        h = altitude_m + climb_m * 0.5 * (1.0 - np.cos(np.pi * u))
        v_n = truth.v_n.copy()
        v_n[:, 2] = -climb_m * np.pi / (2.0 * (t_b - t_a)) * np.sin(np.pi * u)
        truth = NavTrajectory(truth.t, truth.lat, truth.lon, h, v_n, truth.q_nb)
    imu, _ = corrupt(ideal_imu(truth), get_grade(grade), rng)
    main = igrf_ned(lat0, lon0, altitude_m, date).reshape(3)
    anomaly = np.asarray(fmap.value(truth.lat, truth.lon), float)
    anomaly = np.where(np.isfinite(anomaly), anomaly, 0.0)
    mag = magnetometer_body_nt(truth, anomaly, main) + rng.normal(0.0, mag_noise_nt, (len(truth), 3))
    return EmulatedFlight(truth, imu, mag, date)
