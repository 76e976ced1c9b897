"""The companion-computer bridge: autopilot IMU + magnetometer in, fused position out, over MAVLink.

One event loop (:meth:`Bridge.poll`), no threads: decode what arrived, feed IMU samples to the online pipeline
(INS + map matcher + fuser, :mod:`magnav_ins.pipeline`), feed magnetometer readings as field readings, and at the output
rate send the fused position in the configured form. MAVLink encoding lives in :mod:`.link`; this module speaks SI.

Health, and what is sent when the bridge does not trust its solution (``never sends a position it does not trust``):

============================  ===========================================================
state                          output
============================  ===========================================================
waiting for IMU / for init     nothing (gps_input: fix_type 1 "no fix" to keep the stream alive)
running, sigma_h <= max        position (healthy)
IMU stale, sigma_h too large   gps_input: no fix; odometry: not sent; global_position_sensor: UNHEALTHY flag
============================  ===========================================================

Height: the INS vertical channel is clamped (``altitude_hold``). With SCALED_PRESSURE from the autopilot the clamp
follows the barometric height (:mod:`.baro`: ICAO standard atmosphere, referenced to the pressure at
initialisation, median + line-fit filtered) and the output's down velocity is the baro climb rate; when the pressure
stops for more than ``baro_stale_s`` the last baro height is held (a STATUSTEXT says so); without any pressure the
initial height is held, as before.

Timestamps come from the autopilot's ``time_usec``: duplicates and small backward steps are dropped and counted,
a jump back by more than ``reboot_backstep_s`` is an autopilot reboot (the INS is re-initialised from the last
estimate with inflated covariance), gaps up to ``max_gap_s`` are bridged, longer gaps mark the solution unhealthy until
the covariance is inflated to cover the unobserved motion.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from ..core.frames import C_nb_from_q, geodetic_to_ned, q_nb_from_euler
from ..core.types import NavEstimate, NavState
from .baro import BaroHeight, hold_height
from .link import AttitudeMessage, Heartbeat, ImuMessage, MavLink, PositionMessage, PressureMessage, TimesyncMessage

log = logging.getLogger(__name__)

OUTPUT_KINDS = ("gps_input", "odometry", "global_position_sensor")


class OnlinePipeline(Protocol):
    """What the bridge needs from :mod:`magnav_ins.pipeline`: sample-by-sample input and the current estimate."""

    def push_imu(self, t: float, gyro_b: np.ndarray, accel_b: np.ndarray) -> None: ...

    def push_reading(self, t: float, value: float | np.ndarray) -> None: ...

    def estimate(self) -> NavEstimate: ...


#: builds a pipeline from an initial state and its 1-sigma position uncertainty (m)
PipelineFactory = Callable[[NavState, float], OnlinePipeline]
#: turns a body-frame magnetometer vector (nT) at a navigation state into a map reading (or None)
FieldModel = Callable[[np.ndarray, NavState], "float | np.ndarray | None"]


@dataclass(frozen=True)
class BridgeConfig:
    """Bridge settings; times in s, distances in m, rates in Hz."""

    output: str = "gps_input"
    output_rate_hz: float = 5.0
    imu_rate_hz: float = 100.0
    autopilot_system: int = 1
    autopilot_component: int = 1
    init: tuple[float, float, float, float] | None = None  # lat, lon (rad), h (m), yaw (rad); else from the autopilot
    init_sigma_m: float = 30.0
    reading_interval_s: float = 0.1
    max_sigma_m: float = 100.0
    max_gap_s: float = 0.5
    reboot_backstep_s: float = 1.0
    stale_imu_s: float = 0.5
    link_timeout_s: float = 3.0
    heartbeat_interval_s: float = 1.0
    request_interval_s: float = 2.0
    global_position_source: str = "magnetic"
    geoid_height_m: float = 0.0  # MSL = ellipsoidal - geoid_height
    baro: bool = True  # follow SCALED_PRESSURE with the INS height (else hold the initial height)
    baro_rate_hz: float = 20.0
    baro_stale_s: float = 2.0

    def __post_init__(self) -> None:
        from ..core.errors import ConfigError

        if self.output not in OUTPUT_KINDS:
            raise ConfigError(f"--output {self.output!r}: expected one of {', '.join(OUTPUT_KINDS)}")
        if not (0.5 <= self.output_rate_hz <= 50.0):
            raise ConfigError(f"--rate {self.output_rate_hz}: expected 0.5-50 Hz (ArduPilot wants >= 4 Hz)")
        if not (1.0 <= self.baro_rate_hz <= 100.0 and self.baro_stale_s > 0):
            raise ConfigError(
                f"baro rate {self.baro_rate_hz} Hz / stale time {self.baro_stale_s} s: expected 1-100 Hz and > 0 s"
            )
        if self.global_position_source not in ("magnetic", "terrain"):
            raise ConfigError(f"global position source {self.global_position_source!r}: expected magnetic or terrain")


@dataclass
class BridgeHealth:
    """Counters and the current state, reported as STATUSTEXT and log lines."""

    state: str = "waiting_for_imu"
    healthy: bool = False
    reason: str = "no IMU yet"
    imu_samples: int = 0
    imu_duplicates: int = 0
    imu_out_of_order: int = 0
    imu_gaps: int = 0
    reboots: int = 0
    readings: int = 0
    outputs_sent: int = 0
    untrusted_outputs: int = 0
    link_losses: int = 0
    pressures: int = 0
    pressures_rejected: int = 0
    baro_stale_events: int = 0
    baro_state: str = "none"  # none (no pressure: initial height held) | active | stale (last baro height held)
    last_imu_t: float = math.nan
    history: list[str] = field(default_factory=list)


class Bridge:
    """Runs the pipeline on a MAVLink link. Construct with a :class:`MavLink`, a config, a pipeline factory and a
    field model (magnetometer vector -> map reading); call :meth:`run` or :meth:`poll` repeatedly."""

    def __init__(
        self,
        link: MavLink,
        config: BridgeConfig,
        make_pipeline: PipelineFactory,
        field_model: FieldModel | None = None,
        clock: Callable[[], float] = time.monotonic,
        wall_clock: Callable[[], float] = time.time,
    ) -> None:
        self.link = link
        self.config = config
        self.make_pipeline = make_pipeline
        self.field_model = field_model
        self.health = BridgeHealth()
        self._clock = clock
        self._wall = wall_clock
        self._pipeline: OnlinePipeline | None = None
        self._origin: tuple[float, float, float] | None = None
        self._last_attitude: AttitudeMessage | None = None
        self._last_position: PositionMessage | None = None
        self._last_imu_t = -math.inf
        self._last_reading_t = -math.inf
        self._last_rx = clock()
        self._next_heartbeat = 0.0
        self._next_request = 0.0
        self._last_request = -math.inf
        self._next_output = 0.0
        self._imu_seen_at = -math.inf
        self._reset_counter = 0
        self._warned_resolution = False
        #: for each output, seconds from the arrival of the newest IMU sample it includes to the send
        self.latencies_s: list[float] = []
        self._last_imu_rx = math.nan
        self._baro = BaroHeight(stale_s=config.baro_stale_s) if config.baro else None
        self._baro_unusable_warned = False

    # -- the loop ----------------------------------------------------------------------------------------
    def run(self, duration_s: float | None = None, should_stop: Callable[[], bool] | None = None) -> BridgeHealth:
        """Poll until ``duration_s`` has passed or ``should_stop()`` is true (Ctrl-C also stops)."""
        t_end = math.inf if duration_s is None else self._clock() + duration_s
        try:
            while self._clock() < t_end and not (should_stop and should_stop()):
                self.poll(timeout=0.005)
        except KeyboardInterrupt:
            log.info("bridge stopped by the user")
        return self.health

    def poll(self, timeout: float = 0.0) -> None:
        """Handle everything that arrived, then the periodic tasks (heartbeat, requests, outputs, link watch)."""
        now = self._clock()
        for msg in self.link.recv(timeout):
            self._last_rx = self._clock()
            self._handle(msg)
        now = self._clock()
        if now >= self._next_heartbeat:
            self.link.send_heartbeat()
            self._next_heartbeat = now + self.config.heartbeat_interval_s
        if self.health.state == "waiting_for_imu" and now >= self._next_request:
            self._request_streams()
            self._next_request = now + self.config.request_interval_s
        if now - self._last_rx > self.config.link_timeout_s:
            self._on_link_loss()
        if now >= self._next_output:
            self._send_output()
            self._next_output = now + 1.0 / self.config.output_rate_hz

    # -- input ---------------------------------------------------------------------------------------------
    def _handle(self, msg: object) -> None:
        if isinstance(msg, ImuMessage):
            self._on_imu(msg)
        elif isinstance(msg, AttitudeMessage):
            self._last_attitude = msg
        elif isinstance(msg, PositionMessage):
            self._last_position = msg
        elif isinstance(msg, PressureMessage):
            self._on_pressure(msg)
        elif isinstance(msg, TimesyncMessage):
            if msg.tc1 == 0:  # a request: answer with our time (ns)
                self.link.send_timesync(int(self._wall() * 1e9), msg.ts1)
        elif isinstance(msg, Heartbeat):
            c = self.config
            is_autopilot = (msg.sysid, msg.compid) == (c.autopilot_system, c.autopilot_component)
            if is_autopilot and self.health.state == "waiting_for_imu" and self._clock() - self._last_request > 0.5:
                self._request_streams()  # a udpin link can only answer once the autopilot has spoken

    def _request_streams(self) -> None:
        c = self.config
        self._last_request = self._clock()
        streams = [("HIGHRES_IMU", c.imu_rate_hz), ("ATTITUDE", 10.0), ("GLOBAL_POSITION_INT", 5.0)]
        if c.baro:
            streams.append(("SCALED_PRESSURE", c.baro_rate_hz))
        for name, rate in streams:
            self.link.request_message_interval(name, rate, c.autopilot_system, c.autopilot_component)

    def _set_state(self, state: str, healthy: bool, reason: str) -> None:
        h = self.health
        if (h.state, h.healthy, h.reason) != (state, healthy, reason):
            line = f"magnav: {state}{'' if healthy else ' (' + reason + ')'}"
            h.history.append(line)
            log.info(line)
            self.link.send_statustext("info" if healthy else "warning", line)
        h.state, h.healthy, h.reason = state, healthy, reason

    def _on_imu(self, m: ImuMessage) -> None:
        h = self.health
        if m.source != "HIGHRES_IMU" and not self._warned_resolution:
            log.warning(
                "%s carries 1 mrad/s and 1 mG resolution, far too coarse for a tactical INS; "
                "ask the autopilot for HIGHRES_IMU",
                m.source,
            )
            self._warned_resolution = True
        if not (np.all(np.isfinite(m.gyro_b)) and np.all(np.isfinite(m.accel_b)) and math.isfinite(m.t)):
            h.imu_out_of_order += 1
            return
        dt = m.t - self._last_imu_t
        if dt == 0.0:
            h.imu_duplicates += 1
            return
        if dt < 0.0:
            if -dt > self.config.reboot_backstep_s:
                self._on_reboot(m)
            else:
                h.imu_out_of_order += 1
            return
        self._imu_seen_at = self._clock()
        if self._pipeline is None:
            self._last_imu_t = m.t
            self._try_initialise(m)
            return
        if dt > self.config.max_gap_s:
            h.imu_gaps += 1
            self._restart_from_estimate(m.t, reason=f"IMU gap of {dt:.2f} s", extra_sigma_m=self._speed() * dt)
            self._last_imu_t = m.t
            return
        self._apply_baro(m.t)
        self._pipeline.push_imu(m.t, m.gyro_b, m.accel_b)
        self._last_imu_t = m.t
        h.imu_samples += 1
        h.last_imu_t = m.t
        self._last_imu_rx = self._imu_seen_at
        if (
            m.mag_b_nt is not None
            and self.field_model is not None
            and m.t - self._last_reading_t >= self.config.reading_interval_s
        ):
            nav = self._pipeline.estimate().nav
            value = self.field_model(m.mag_b_nt, nav)
            if value is not None and np.all(np.isfinite(value)):
                self._pipeline.push_reading(m.t, value)
                self._last_reading_t = m.t
                h.readings += 1

    def _try_initialise(self, m: ImuMessage) -> None:
        c = self.config
        if c.init is not None:
            lat, lon, hgt, yaw = c.init
            roll = pitch = 0.0
            if self._last_attitude is not None:
                roll, pitch = self._last_attitude.roll, self._last_attitude.pitch
            else:  # level the INS from the specific force (at rest or in steady flight)
                f = m.accel_b
                roll = math.atan2(-f[1], -f[2])
                pitch = math.atan2(f[0], math.hypot(f[1], f[2]))
            v_n = np.zeros(3)
        elif self._last_position is not None and self._last_attitude is not None:
            p, a = self._last_position, self._last_attitude
            lat, lon, hgt, v_n = p.lat, p.lon, p.h_msl + c.geoid_height_m, p.v_n
            roll, pitch, yaw = a.roll, a.pitch, a.yaw
        else:
            self._set_state("waiting_for_init", False, "no --init and no GLOBAL_POSITION_INT + ATTITUDE yet")
            return
        nav = NavState(m.t, lat, lon, hgt, v_n, q_nb_from_euler(roll, pitch, yaw))
        self._pipeline = self.make_pipeline(nav, c.init_sigma_m)
        if self._origin is None:
            self._origin = (lat, lon, hgt)
            if c.output == "odometry":
                self.link.send_set_gps_global_origin(c.autopilot_system, lat, lon, hgt - c.geoid_height_m)
        if self._baro is not None:
            self._baro.set_reference(hgt, m.t)
        self._set_state("running", True, "")

    # -- barometer -------------------------------------------------------------------------------------------
    def _on_pressure(self, m: PressureMessage) -> None:
        if self._baro is None:
            return
        b = self._baro
        b.push(m.t, m.pressure_pa)
        self.health.pressures, self.health.pressures_rejected = b.health.samples, b.health.rejected

    def _apply_baro(self, t: float) -> None:
        """Move the INS altitude hold to the baro height at IMU time ``t`` (s) before the step to ``t``."""
        if self._baro is None or self._pipeline is None:
            return
        h_baro = self._baro.height(t)
        state = self._baro.health.state
        if state != self.health.baro_state:
            if state == "stale":
                self.health.baro_stale_events += 1
                self.link.send_statustext("warning", "magnav: baro lost, height held")
            elif state == "active" and self.health.baro_state == "stale":
                self.link.send_statustext("info", "magnav: baro back")
            self.health.baro_state = state
        if h_baro is None:
            return
        if not hold_height(self._pipeline, h_baro) and not self._baro_unusable_warned:
            self._baro_unusable_warned = True
            log.warning("barometer: the pipeline holds no altitude (fusion without altitude hold): baro not used")

    def _baro_climb_rate(self, t: float) -> float | None:
        """Baro climb rate (m/s, up) while the barometer drives the INS height, else None."""
        if self._baro is None or self._baro_unusable_warned or not self._baro.referenced:
            return None
        return self._baro.climb_rate(t)

    def _restart_from_estimate(self, t: float, reason: str, extra_sigma_m: float) -> None:
        """Re-initialise the pipeline at time ``t`` from the current estimate with inflated position uncertainty."""
        assert self._pipeline is not None
        est = self._pipeline.estimate()
        sigma = math.sqrt(max(np.trace(est.cov_ne) / 2.0, 0.0)) + extra_sigma_m
        nav = est.nav
        self._pipeline = self.make_pipeline(NavState(t, nav.lat, nav.lon, nav.h, nav.v_n, nav.q_nb), sigma)
        self._reset_counter += 1
        log.warning("%s: INS restarted from the last estimate, position sigma now %.0f m", reason, sigma)
        self.link.send_statustext("warning", f"magnav: {reason}, INS restarted")

    def _on_reboot(self, m: ImuMessage) -> None:
        self.health.reboots += 1
        self._last_imu_t = m.t
        if self._pipeline is not None:
            self._restart_from_estimate(m.t, "autopilot clock went back (reboot?)", extra_sigma_m=self._speed() * 1.0)

    def _on_link_loss(self) -> None:
        if self.health.state == "link_lost":
            return
        self.health.link_losses += 1
        self._set_state("link_lost", False, f"nothing received for {self.config.link_timeout_s:.0f} s")
        try:
            self.link.reconnect()
        except Exception as exc:  # noqa: BLE001 - keep running, try again at the next timeout
            log.warning("reconnect failed: %s", exc)
        self._last_rx = self._clock()
        self.health.state = "waiting_for_imu" if self._pipeline is None else "running"

    def _speed(self) -> float:
        if self._pipeline is None:
            return 0.0
        return float(np.linalg.norm(self._pipeline.estimate().nav.v_n[:2]))

    # -- output --------------------------------------------------------------------------------------------
    def _trust(self, est: NavEstimate) -> tuple[bool, str]:
        now = self._clock()
        if now - self._imu_seen_at > self.config.stale_imu_s:
            return False, "IMU stale"
        cov = np.asarray(est.cov_ne)
        if not np.all(np.isfinite(cov)) or not (math.isfinite(est.nav.lat) and math.isfinite(est.nav.lon)):
            return False, "solution not finite"
        sigma_h = math.sqrt(max(np.linalg.eigvalsh(cov).max(), 0.0))
        if sigma_h > self.config.max_sigma_m:
            return False, f"horizontal sigma {sigma_h:.0f} m > {self.config.max_sigma_m:.0f} m"
        return True, ""

    def _send_output(self) -> None:
        c = self.config
        if self._pipeline is None:
            if c.output == "gps_input":  # keep the GPS stream alive with "no fix"
                self.link.send_gps_input(
                    t_unix=self._wall(),
                    lat=0.0,
                    lon=0.0,
                    h_msl=0.0,
                    v_n=np.zeros(3),
                    sigma_h=99.0,
                    sigma_v=99.0,
                    sigma_speed=99.0,
                    healthy=False,
                )
            return
        est = self._pipeline.estimate()
        trusted, reason = self._trust(est)
        if self.health.state in ("running", "degraded"):
            self._set_state("running" if trusted else "degraded", trusted, reason)
        nav = est.nav
        v_n = nav.v_n
        climb = self._baro_climb_rate(nav.t)
        if climb is not None:  # the held vertical channel says v_D = 0: send the barometer's rate instead
            v_n = np.array([v_n[0], v_n[1], -climb])
        cov = np.asarray(est.cov_ne)
        sigma_h = math.sqrt(max(float(np.linalg.eigvalsh(cov).max()), 0.0)) if np.all(np.isfinite(cov)) else math.inf
        P = np.asarray(est.P)
        pos = est.layout["pos"]
        vel = est.layout["vel"]
        sigma_v = math.sqrt(max(P[pos.start + 2, pos.start + 2], 0.0))
        sigma_speed = math.sqrt(max(np.trace(P[vel, vel]) / 3.0, 0.0))
        h_msl = nav.h - c.geoid_height_m
        if not trusted:
            self.health.untrusted_outputs += 1
        if c.output == "gps_input":
            self.link.send_gps_input(
                t_unix=self._wall(),
                lat=nav.lat,
                lon=nav.lon,
                h_msl=h_msl,
                v_n=v_n,
                sigma_h=sigma_h,
                sigma_v=sigma_v,
                sigma_speed=sigma_speed,
                healthy=trusted,
            )
        elif c.output == "odometry":
            if not trusted:
                return  # ODOMETRY has no "invalid" flag ArduPilot honours: send nothing
            assert self._origin is not None
            r_ned = geodetic_to_ned(nav.lat, nav.lon, nav.h, *self._origin)
            v_b = C_nb_from_q(nav.q_nb).T @ v_n
            self.link.send_odometry(
                t_usec=int(nav.t * 1e6),
                r_ned=r_ned,
                q_nb=nav.q_nb,
                v_b=v_b,
                sigma_pos=np.array([sigma_h, sigma_h, sigma_v]),
                sigma_vel=np.full(3, sigma_speed),
                reset_counter=self._reset_counter & 0xFF,
                quality=100 if trusted else 0,
            )
        else:
            self.link.send_global_position_sensor(
                target_system=c.autopilot_system,
                target_component=c.autopilot_component,
                t_usec=int(nav.t * 1e6),
                processing_us=0,
                source=c.global_position_source,
                lat=nav.lat,
                lon=nav.lon,
                h_ellipsoid=nav.h,
                h_msl=h_msl,
                sigma_h=sigma_h,
                sigma_v=sigma_v,
                healthy=trusted,
            )
        self.health.outputs_sent += 1
        if math.isfinite(self._last_imu_rx):
            self.latencies_s.append(self._clock() - self._last_imu_rx)


class ScalarAnomalyModel:
    """Field model for total-field anomaly maps: ``|A (m - b)| - F_IGRF(position, date)`` in nT.

    ``calibration`` (a :class:`~magnav_ins.aiding.calibration.MagCalibration`, or None for raw readings) removes the
    vehicle's hard- and soft-iron effects; the IGRF total field is recomputed when the estimate has moved more than
    ``refresh_m`` (it changes by a few nT per km).
    """

    def __init__(self, date: str, calibration: object | None = None, refresh_m: float = 2000.0) -> None:
        from ..maps.reference import igrf_total

        self._igrf_total = igrf_total
        self.date = date
        self.calibration = calibration
        self.refresh_m = refresh_m
        self._cache: tuple[float, float, float] | None = None  # lat, lon, F

    def __call__(self, mag_b_nt: np.ndarray, nav: NavState) -> float:
        m = np.asarray(mag_b_nt, float)
        if self.calibration is not None:
            m = np.asarray(self.calibration.apply(m), float).reshape(3)  # type: ignore[attr-defined]
        if self._cache is None or _distance_m(self._cache[0], self._cache[1], nav.lat, nav.lon) > self.refresh_m:
            f = float(np.asarray(self._igrf_total(nav.lat, nav.lon, nav.h, self.date)).reshape(-1)[0])
            self._cache = (nav.lat, nav.lon, f)
        return float(np.linalg.norm(m)) - self._cache[2]


def _distance_m(lat0: float, lon0: float, lat1: float, lon1: float) -> float:
    from ..core.frames import horizontal_error_m

    return float(horizontal_error_m(lat1, lon1, lat0, lon0))


def warm_up(
    make_pipeline: PipelineFactory,
    fmap,
    field_value_at: Callable[[float, float], float] | None = None,
    rate_hz: float = 100.0,
    seconds: float = 4.0,
    reading_interval_s: float = 0.1,
) -> float:
    """Run ``make_pipeline``'s pipeline over a few seconds of synthetic at-rest IMU (and map readings) at the map's
    centre so that every compiled kernel (strapdown, covariance, matcher scans) is compiled or loaded from numba's
    cache *before* the bridge connects, not when the autopilot's first IMU sample arrives. Returns the seconds spent.
    A configuration error (unknown matcher, grade, ...) is raised now; anything else is left for the real run to
    report."""
    from ..core.errors import MagnavError
    from ..core.frames import WGS84_OMEGA_E
    from ..ins.earth import gravity_n

    t0 = time.monotonic()
    try:
        lat0, lon0 = _map_centre(fmap)
        nav = NavState(0.0, lat0, lon0, 300.0, np.zeros(3), q_nb_from_euler(0.0, 0.0, 0.0))
        pipe = make_pipeline(nav, 30.0)
        g = gravity_n(lat0, 300.0)
        accel = np.array([0.0, 0.0, -g[2]])
        gyro = np.array([WGS84_OMEGA_E * math.cos(lat0), 0.0, -WGS84_OMEGA_E * math.sin(lat0)])
        value = field_value_at(lat0, lon0) if field_value_at is not None else None
        next_r = 0.0
        for k in range(1, int(seconds * rate_hz) + 1):
            t = k / rate_hz
            pipe.push_imu(t, gyro, accel)
            if value is not None and np.isfinite(value) and t >= next_r:
                pipe.push_reading(t, value)
                next_r = t + reading_interval_s
        pipe.estimate()
    except MagnavError:
        raise
    except Exception as exc:  # noqa: BLE001 - warm-up only; the real run reports its own errors
        log.debug("warm-up: %s", exc)
    return time.monotonic() - t0


def _map_centre(fmap) -> tuple[float, float]:
    lat_s, lat_n, lon_w, lon_e = fmap.bounds_latlon
    return 0.5 * (lat_s + lat_n), 0.5 * (lon_w + lon_e)
