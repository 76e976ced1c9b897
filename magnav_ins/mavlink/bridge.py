"""The companion-computer bridge: autopilot IMU + magnetometer in, fused position out, over MAVLink.

One event loop (:meth:`Bridge.poll`): decode what arrived, feed IMU samples to the online pipeline (INS + map matcher
+ fuser, :mod:`.online`; built with ``background_matching`` the matcher's scans run in one worker thread beside the
loop), magnetometer readings as field readings and, while the autopilot's own GNSS is healthy, its fixes
(:mod:`.gnss`); at the output rate send the fused position in the configured form. ``imu_world="flat"`` adapts a
simulator's samples to the rotating Earth first (:mod:`.flat_world`).
MAVLink encoding lives in :mod:`.link`; this module speaks SI.

Life of a flight (the state is announced by STATUSTEXT once per change, rate-limited, and logged):

``waiting_for_imu``       nothing from the autopilot yet; SET_MESSAGE_INTERVAL is sent until the streams come
``waiting_for_position``  IMU, but neither ``--init`` nor a healthy GNSS fix (GPS_RAW_INT fix type >= 3, enough
                          satellites, not 0 N 0 E): never a position from a zero or invalid message
``aligning``              on the ground and still (:mod:`.ground`): the position is held with its uncertainty, the
                          velocity is zero, roll/pitch and the gyro biases are measured; no INS drift on the ground.
                          After a flight: the autopilot says "on ground", or it says "landing" and the baro height
                          is back within ``touchdown_height_m`` of the height the bridge was aligned at, with the
                          baro climb rate under ``touchdown_climb_mps`` (its land detector waits for a still
                          velocity, and while the bridge is its position source that velocity is the bridge's own:
                          on SITL run 42 a 1.1 m/s velocity error kept ArduCopter "landing" on the ground for 130 s
                          while the INS drifted 220 m, until "EKF variance"). The position held after a landing is
                          the autopilot's own estimate when it lies within the solution's 1-sigma (sigma grown by the
                          distance), so that its estimate does not move on the ground (:meth:`Bridge._landing_hold`)
``running``               the INS runs: GNSS-aided while the autopilot's GNSS is healthy (its fixes estimate the INS
                          biases in flight), map-aided after it is lost or denied (fix lost, operator command,
                          ``deny_gnss_after_s``), without a jump
``degraded``              the solution is not trusted (IMU stale, not finite, protection level or sigma too large)

What is sent (``never a position the bridge cannot stand behind``):

============================  ===========================================================
state                          output
============================  ===========================================================
no solution                    gps_input: fix_type 1 "no fix" to keep the stream alive; others: nothing
GNSS-aided, not sending        the same as "no solution" unless ``send_while_gnss`` (default: only to a secondary
                               GPS_INPUT instance, ``gps_id`` >= 1, where the autopilot switches to it on its own)
trusted                        position, velocity, their 1-sigmas (the fix_type and accuracy fields say exactly that)
degraded                       gps_input: no fix; odometry: not sent; global_position_sensor: UNHEALTHY flag
============================  ===========================================================

Trust: a finite horizontal protection level (``NavEstimate.hpl_m``, from fusers that compute one) is compared with
``alert_limit_m``; otherwise the largest horizontal 1-sigma with ``max_sigma_m``; with hysteresis (trusted again
below ``trust_hysteresis`` of the limit) so that the state does not flap.

Autopilot reboots and link loss: every stream the bridge needs is watched; one that has not arrived for three of its
intervals is asked for again every ``request_interval_s`` until it returns (an autopilot forgets the intervals when
it reboots). A reboot (the IMU clock going back by more than ``reboot_backstep_s``) restarts the INS from the last
estimate with the position sigma grown by speed x 1 s; an IMU gap up to ``max_gap_s`` is bridged, a longer one
restarts it with sigma grown by speed x gap; the biases estimated so far are kept. The ODOMETRY origin is the
autopilot's own (GPS_GLOBAL_ORIGIN, asked for); only when it has none does the bridge send SET_GPS_GLOBAL_ORIGIN,
again after a reboot.

Height: the INS vertical channel is clamped (``altitude_hold``). With SCALED_PRESSURE the clamp follows the
barometric height (:mod:`.baro`) and the output's down velocity is the baro climb rate; without pressure the
initial height is held and GPS_INPUT says it has no vertical velocity.

IMU samples: ``sample_type`` ``auto`` takes ArduPilot's HIGHRES_IMU as instantaneous (filtered) samples and PX4's as
interval means (:data:`.online.AUTO_SAMPLE_TYPE`), from the autopilot's HEARTBEAT.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from functools import cached_property
from typing import Any, Protocol

import numpy as np

from ..core.frames import C_nb_from_q, geodetic_to_ned, horizontal_error_m, q_nb_from_euler
from ..core.types import Fix, NavEstimate, NavState
from ..ins.strapdown import SAMPLE_TYPES
from .baro import BaroHeight, hold_height
from .field_model import ScalarAnomalyModel  # noqa: F401 - re-exported (its home until now)
from .flat_world import FLAT_SPHERE_RADIUS_M, earth_imu
from .gnss import GnssMonitor
from .ground import GroundAlignment, StillDetector, normal_gravity_mps2
from .link import (
    GNSS_DENY_COMMAND,
    GPS_INPUT_IGNORE_VEL_VERT,
    MAV_RESULT_ACCEPTED,
    SET_EKF_SOURCE_SET,
    AttitudeMessage,
    CommandMessage,
    GnssMessage,
    Heartbeat,
    ImuMessage,
    LandedStateMessage,
    MavLink,
    OriginMessage,
    PositionMessage,
    PressureMessage,
    TimesyncMessage,
)
from .online import AUTO_SAMPLE_TYPE, MAX_GAP_S

log = logging.getLogger(__name__)

OUTPUT_KINDS = ("gps_input", "odometry", "global_position_sensor")

#: the largest speed accuracy the ``follow_s`` floor raises GPS_INPUT's to, m/s: under EKF3's 1.5 m/s "GPS
#: glitching" threshold (:meth:`Bridge._speed_accuracy`); the filter's own velocity sigma is sent as it is
MAX_SPEED_FLOOR_MPS = 1.2
SAMPLE_TYPE_CHOICES = ("auto", *SAMPLE_TYPES)
SEND_WHILE_GNSS = ("auto", "yes", "no")
IMU_WORLDS = ("earth", "flat")
#: protection level per horizontal 1-sigma at integrity risk 1e-3 for a circular 2-D Gaussian: sqrt(-2 ln 1e-3)
HPL_PER_SIGMA = math.sqrt(-2.0 * math.log(1e-3))
MAV_AUTOPILOT_ARDUPILOTMEGA = 3
MAV_AUTOPILOT_PX4 = 12
#: STATUSTEXT severities by state
_SEVERITY = {
    "waiting_for_imu": "info",
    "waiting_for_position": "notice",
    "aligning": "info",
    "running": "info",
    "degraded": "warning",
    "link_lost": "warning",
}


#: how the STATUSTEXT names the HIGHRES_IMU magnetometer unit the link detected (:func:`.link.highres_mag_to_nt`)
_MAG_UNIT_TEXT = {"gauss": "gauss", "milligauss": "mG", "milligauss*1000": "mG x 1000"}


class OnlinePipelineLike(Protocol):
    """What the bridge needs from :mod:`.online`: sample-by-sample input and the current estimate (an
    :class:`.online.OnlinePipeline` also takes external fixes, a static bias and a sample type)."""

    def push_imu(self, t: float, gyro_b: np.ndarray, accel_b: np.ndarray) -> None: ...

    def push_reading(self, t: float, value: float | np.ndarray) -> None: ...

    def estimate(self) -> NavEstimate: ...


#: builds a pipeline from an initial state and its 1-sigma position uncertainty (m)
PipelineFactory = Callable[[NavState, float], OnlinePipelineLike]
#: turns a body-frame magnetometer vector (nT) at a navigation state into a map reading (or None)
FieldModel = Callable[[np.ndarray, NavState], "float | np.ndarray | None"]


@dataclass(frozen=True)
class BridgeConfig:
    """Bridge settings; times in s, distances in m, rates in Hz (module docstring for the behaviour)."""

    output: str = "gps_input"
    output_rate_hz: float = 10.0
    imu_rate_hz: float = 100.0
    autopilot_system: int = 1
    autopilot_component: int = 1
    own_component: int = 191
    init: tuple[float, float, float, float] | None = None  # lat, lon (rad), h (m), yaw (rad); else from the autopilot
    init_sigma_m: float = 30.0
    reading_interval_s: float = 0.1
    max_sigma_m: float = 100.0
    alert_limit_m: float | None = None  # HPL limit; default max_sigma_m * HPL_PER_SIGMA
    trust_hysteresis: float = 0.8
    follow_s: float = 20.0  # GPS_INPUT speed accuracy >= horizontal sigma / follow_s (:meth:`Bridge._speed_accuracy`)
    max_gap_s: float = MAX_GAP_S
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
    sample_type: str = "auto"
    gps_id: int = 0  # GPS_INPUT instance: 0 = GPS1, 1 = GPS2
    gnss_aiding: bool = True  # fuse the autopilot's own GNSS while it is healthy
    gnss_min_satellites: int = 6
    gnss_max_sigma_m: float = 10.0
    gnss_fix_interval_s: float = 1.0
    gnss_lag_s: float = 0.0  # the receiver's latency: a GPS_RAW_INT position is that much older than its stamp
    gnss_timeout_s: float = 1.5
    gnss_recover_s: float = 10.0
    deny_gnss_after_s: float | None = None
    send_while_gnss: str = "auto"
    ekf_source_set: int | None = None  # MAV_CMD_SET_EKF_SOURCE_SET to this set when the GNSS is lost (and 1 back)
    align: bool = True  # ground alignment while still
    touchdown_height_m: float = 1.5  # "landing" within this of the aligned ground height (baro) counts as landed
    touchdown_climb_mps: float = 0.2  # ... once the baro climb rate is below this (m/s): the descent has ended
    attitude_aid: bool = True  # the autopilot's attitude (ATTITUDE) as a measurement of the INS attitude
    attitude_interval_s: float = 1.0
    attitude_sigma_rad: tuple[float, float, float] = (0.01, 0.01, 0.035)  # tilt about N, E; heading
    statustext_interval_s: float = 2.0
    imu_world: str = "earth"  # "flat": the autopilot is a simulator with a flat, non-rotating world (.flat_world)
    flat_sphere_radius_m: float | None = FLAT_SPHERE_RADIUS_M  # the sphere of the simulator's lat/lon (.flat_world)

    def __post_init__(self) -> None:
        from ..core.errors import ConfigError

        if self.output not in OUTPUT_KINDS:
            raise ConfigError(f"--output {self.output!r}: expected one of {', '.join(OUTPUT_KINDS)}")
        if not (0.5 <= self.output_rate_hz <= 50.0):
            raise ConfigError(
                f"--rate {self.output_rate_hz}: expected 0.5-50 Hz (ArduPilot wants GPS_INPUT more often than every "
                "215 ms on average: 10 Hz)"
            )
        if not (1.0 <= self.baro_rate_hz <= 100.0 and self.baro_stale_s > 0):
            raise ConfigError(
                f"baro rate {self.baro_rate_hz} Hz / stale time {self.baro_stale_s} s: expected 1-100 Hz and > 0 s"
            )
        if self.global_position_source not in ("magnetic", "terrain"):
            raise ConfigError(f"global position source {self.global_position_source!r}: expected magnetic or terrain")
        if self.sample_type not in SAMPLE_TYPE_CHOICES:
            raise ConfigError(f"--sample-type {self.sample_type!r}: expected one of {', '.join(SAMPLE_TYPE_CHOICES)}")
        if self.imu_world not in IMU_WORLDS:
            raise ConfigError(f"--imu-world {self.imu_world!r}: expected one of {', '.join(IMU_WORLDS)}")
        if self.send_while_gnss not in SEND_WHILE_GNSS:
            raise ConfigError(
                f"--send-while-gnss {self.send_while_gnss!r}: expected one of {', '.join(SEND_WHILE_GNSS)}"
            )
        if not (0 <= self.gps_id <= 3):
            raise ConfigError(f"--gps-id {self.gps_id}: expected 0-3 (GPS1-GPS4)")
        if self.ekf_source_set is not None and self.ekf_source_set not in (1, 2, 3):
            raise ConfigError(f"--ekf-source-set {self.ekf_source_set}: expected 1, 2 or 3")
        if self.deny_gnss_after_s is not None and not self.deny_gnss_after_s >= 0:
            raise ConfigError(f"--deny-gnss-after {self.deny_gnss_after_s}: expected seconds >= 0")
        if not (math.isfinite(self.gnss_lag_s) and 0.0 <= self.gnss_lag_s <= 1.0):
            raise ConfigError(f"--gnss-lag {self.gnss_lag_s}: expected 0-1 s")
        for name in ("init_sigma_m", "max_sigma_m", "gnss_max_sigma_m", "gnss_fix_interval_s", "follow_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ConfigError(f"bridge setting {name} = {v!r}: expected a positive number")
        if not (0.0 < self.trust_hysteresis <= 1.0):
            raise ConfigError(f"trust_hysteresis {self.trust_hysteresis}: expected 0 < h <= 1")

    @property
    def alert_limit(self) -> float:
        """The HPL limit, m: ``alert_limit_m``, by default 5 x ``max_sigma_m`` (a protection level carries a
        fault-detection margin on top of the ``HPL_PER_SIGMA`` sigmas of the covariance: on the SITL flights the
        UKF's HPL was 5-7 sigmas while map fixes came, the margin being what the last fixes' covariance reductions
        could have hidden, :mod:`..aiding.fusion.integrity`)."""
        return self.alert_limit_m if self.alert_limit_m is not None else 5.0 * self.max_sigma_m

    @property
    def gnss_instance(self) -> int:
        """Which raw GNSS message is the autopilot's own receiver: GPS2_RAW (1) when the bridge feeds GPS1 with
        GPS_INPUT (GPS_RAW_INT is then the bridge's own position coming back), else GPS_RAW_INT (0)."""
        return 1 if (self.output == "gps_input" and self.gps_id == 0) else 0


@dataclass
class BridgeHealth:
    """Counters and the current state, reported as STATUSTEXT, log lines and the stop summary."""

    state: str = "waiting_for_imu"
    healthy: bool = False
    reason: str = "no IMU yet"
    aiding: str = "none"  # none | gnss | map
    gnss_state: str = "none"
    imu_samples: int = 0
    imu_duplicates: int = 0
    imu_out_of_order: int = 0
    imu_gaps: int = 0
    reboots: int = 0
    heartbeat_gaps: int = 0
    readings: int = 0
    map_fixes: int = 0
    map_fixes_issued: int = 0
    map_fixes_accepted: int = 0
    gnss_fixes: int = 0
    gnss_fixes_accepted: int = 0
    attitude_updates: int = 0
    attitude_accepted: int = 0
    gnss_losses: int = 0
    outputs_sent: int = 0
    untrusted_outputs: int = 0
    link_losses: int = 0
    stream_requests: int = 0
    statustexts_sent: int = 0
    invalid_positions: int = 0
    alignments: int = 0
    pipeline_starts: int = 0
    pressures: int = 0
    pressures_rejected: int = 0
    baro_stale_events: int = 0
    baro_state: str = "none"  # none (no pressure: initial height held) | active | stale (last baro height held)
    sample_type: str = ""
    mag_unit: str = ""
    field_offset_nt: float = math.nan
    no_fix_reasons: dict[str, int] = field(default_factory=dict)
    rejected_reasons: dict[str, int] = field(default_factory=dict)
    last_imu_t: float = math.nan
    history: list[str] = field(default_factory=list)

    def as_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["history"] = list(self.history)
        return d


class StatusAnnouncer:
    """STATUSTEXT once per change, at most one every ``min_interval_s`` (each one is shown to the pilot and logged
    by the autopilot). Messages have a ``key`` ("state", "baro", "event"): a new text for a key replaces one still
    waiting for the same key, and a text equal to the last one sent for its key is not sent again."""

    def __init__(self, link: MavLink, min_interval_s: float, clock: Callable[[], float]) -> None:
        self.link = link
        self.min_interval_s = float(min_interval_s)
        self._clock = clock
        self._sent: dict[str, str] = {}
        self._pending: dict[str, tuple[str, str]] = {}
        self._last_t = -math.inf
        self.count = 0

    def say(self, key: str, severity: str, text: str) -> None:
        if self._sent.get(key) == text:
            self._pending.pop(key, None)
            return
        self._pending[key] = (severity, text)
        self.flush()

    def flush(self) -> None:
        now = self._clock()
        if not self._pending or now - self._last_t < self.min_interval_s:
            return
        key = next(iter(self._pending))
        severity, text = self._pending.pop(key)
        self.link.send_statustext(severity, text)
        self._sent[key] = text
        self._last_t = now
        self.count += 1


@dataclass(frozen=True)
class _Held:
    """A position held while the INS is not running: rad, m (ellipsoidal), 1-sigma m, where it came from."""

    lat: float
    lon: float
    h: float
    sigma_m: float
    source: str


def _largest_sigma(cov_ne: np.ndarray) -> float:
    """The largest 1-sigma (m) of a horizontal covariance (2, 2) m^2; inf when it is not finite."""
    cov = np.asarray(cov_ne, dtype=float)
    if not np.all(np.isfinite(cov)):
        return math.inf
    return math.sqrt(max(float(np.linalg.eigvalsh(cov).max()), 0.0))


@dataclass(frozen=True)
class _Solution:
    """What an output reports: position (rad, m ellipsoidal), NED velocity, attitude, 1-sigmas (m, m/s), the
    protection level (m, nan if none) and the horizontal covariance ``cov_ne`` (2, 2) north/east m^2; ``sigma_h``
    is its largest 1-sigma, what the output's accuracy fields carry in every direction."""

    t: float
    lat: float
    lon: float
    h: float
    v_n: np.ndarray
    q_nb: np.ndarray
    cov_ne: np.ndarray
    sigma_v: float
    sigma_speed: float
    hpl_m: float
    finite: bool

    @cached_property
    def sigma_h(self) -> float:
        return _largest_sigma(self.cov_ne)


class Bridge:
    """Runs the pipeline on a MAVLink link. Construct with a :class:`MavLink`, a config, a pipeline factory, a
    field model (magnetometer vector -> map reading) and optionally the map itself (``fmap``: to calibrate the field
    model's offset against the map while GNSS-aided); call :meth:`run` or :meth:`poll` repeatedly."""

    def __init__(
        self,
        link: MavLink,
        config: BridgeConfig,
        make_pipeline: PipelineFactory,
        field_model: FieldModel | None = None,
        clock: Callable[[], float] = time.monotonic,
        wall_clock: Callable[[], float] = time.time,
        fmap: Any = None,
        on_output: Callable[[dict[str, Any]], None] | None = None,
    ) -> None:
        self.link = link
        #: called at every output time with what the solution was and what was sent (``--track-csv``)
        self.on_output = on_output
        self.config = config
        self.make_pipeline = make_pipeline
        self.field_model = field_model
        prepare = getattr(field_model, "prepare", None)
        if callable(prepare):  # imports and first evaluations here, never on the loop (ScalarAnomalyModel.prepare)
            prepare()
        self.fmap = fmap
        self.health = BridgeHealth()
        self._clock = clock
        self._wall = wall_clock
        self._say = StatusAnnouncer(link, config.statustext_interval_s, clock)
        self._pipeline: Any = None
        self._origin: tuple[float, float, float] | None = None  # ODOMETRY origin: lat, lon rad, h ellipsoidal m
        self._origin_from_autopilot = False
        self._origin_sent_at = -math.inf
        self._origin_requested_at = -math.inf
        self._last_attitude: tuple[AttitudeMessage, float] | None = None
        self._last_position: tuple[PositionMessage, float] | None = None
        self._landed: tuple[str, float] | None = None
        self._autopilot_type: int | None = None
        self._last_imu_t = -math.inf
        self._last_reading_t = -math.inf
        self._last_rx = clock()
        self._next_heartbeat = 0.0
        self._next_request = 0.0
        self._next_output = 0.0
        self._imu_seen_at = -math.inf
        self._ap_heartbeat_at = -math.inf
        self._reset_counter = 0
        self._warned_resolution = False
        self._warned_zero_position = False
        #: for each output, seconds from the arrival of the newest IMU sample it includes to the send
        self.latencies_s: list[float] = []
        self._last_imu_rx = math.nan
        self._baro = BaroHeight(stale_s=config.baro_stale_s) if config.baro else None
        self._baro_unusable_warned = False
        self._baro_ref_set = False
        self._gnss = GnssMonitor(
            min_satellites=config.gnss_min_satellites,
            max_sigma_m=config.gnss_max_sigma_m,
            timeout_s=config.gnss_timeout_s,
            recover_s=config.gnss_recover_s,
            deny_after_s=config.deny_gnss_after_s,
        )
        self._gnss_state_seen = "none"
        self._last_gnss_fix: GnssMessage | None = None
        self._last_gnss_fix_t = -math.inf
        self._last_attitude_aid_t = -math.inf
        self._source_set_sent: int | None = None
        self._still = StillDetector()
        self._aligner = GroundAlignment()
        self._g_mps2 = 9.80665
        self._held: _Held | None = None
        self._carried_bias: tuple[np.ndarray, np.ndarray] | None = None  # gyro, accel (rad/s, m/s^2)
        self._flew = False  # the INS has run at least once (then re-alignment needs the landed state)
        self._ground_h: float | None = None  # baro height (m) where the bridge last aligned on the ground
        self._sigma_ok = True
        self._h_sigma0 = config.init_sigma_m
        self._streams = self._stream_table()
        self._stream_rx = {name: -math.inf for name in self._streams}
        self._stream_tries = {name: 0 for name in self._streams}
        self.health.sample_type = config.sample_type

    # -- the loop ----------------------------------------------------------------------------------------
    def run(self, duration_s: float | None = None, should_stop: Callable[[], bool] | None = None) -> BridgeHealth:
        """Poll until ``duration_s`` has passed or ``should_stop()`` is true (Ctrl-C also stops)."""
        t_end = math.inf if duration_s is None else self._clock() + duration_s
        try:
            while self._clock() < t_end and not (should_stop and should_stop()):
                self.poll(timeout=0.005)
        except KeyboardInterrupt:
            log.info("bridge stopped by the user")
        self._finish()
        return self.health

    def _finish(self) -> None:
        h = self.health
        h.mag_unit = getattr(self.link, "mag_unit", None) or ""
        h.statustexts_sent = self._say.count
        h.gnss_state = self._gnss.state
        h.gnss_losses = self._gnss.losses
        if self._pipeline is not None:
            self._count_fixes()
            self._close_pipeline()

    def _close_pipeline(self) -> None:
        """Free what the pipeline holds besides memory (its background matcher thread, :mod:`.online`)."""
        close = getattr(self._pipeline, "close", None)
        if close is not None:
            close()

    def poll(self, timeout: float = 0.0) -> None:
        """Handle everything that arrived, then the periodic tasks (heartbeat, streams, GNSS, outputs, link)."""
        for msg in self.link.recv(timeout):
            self._last_rx = self._clock()
            self._handle(msg)
        now = self._clock()
        if now >= self._next_heartbeat:
            self.link.send_heartbeat()
            self._next_heartbeat = now + self.config.heartbeat_interval_s
        self._check_streams(now)
        self._check_gnss(now)
        if now - self._last_rx > self.config.link_timeout_s:
            self._on_link_loss()
        if now >= self._next_output:
            self._send_output()
            self._next_output = now + 1.0 / self.config.output_rate_hz
        self._say.flush()

    # -- state -------------------------------------------------------------------------------------------
    def _set_state(self, state: str, healthy: bool, reason: str) -> None:
        h = self.health
        aiding = self._aiding() if state in ("running", "degraded") else "none"
        if (h.state, h.healthy, h.reason, h.aiding) != (state, healthy, reason, aiding):
            text = state.replace("_", " ")
            if state in ("running", "degraded"):
                text += f", {aiding.upper() if aiding == 'gnss' else aiding}-aided"
            if not healthy and reason:
                text += f" ({reason})"
            line = f"magnav: {text}"
            if state != h.state or reason != h.reason or aiding != h.aiding:
                h.history.append(line)
                log.info(line)
            self._say.say("state", _SEVERITY.get(state, "info"), line)
        h.state, h.healthy, h.reason, h.aiding = state, healthy, reason, aiding

    def _aiding(self) -> str:
        return "gnss" if (self.config.gnss_aiding and self._gnss.healthy) else "map"

    def _event(self, severity: str, text: str) -> None:
        line = f"magnav: {text}"
        self.health.history.append(line)
        log.warning(line) if severity in ("warning", "error") else log.info(line)
        self._say.say("event", severity, line)

    # -- input ---------------------------------------------------------------------------------------------
    def _handle(self, msg: object) -> None:  # noqa: C901 - a flat table of message kinds
        now = self._clock()
        if isinstance(msg, ImuMessage):
            self._stream_rx[msg.source] = now
            self._on_imu(msg)
        elif isinstance(msg, AttitudeMessage):
            self._stream_rx["ATTITUDE"] = now
            self._last_attitude = (msg, now)
            self._attitude_aid(msg)
        elif isinstance(msg, PositionMessage):
            self._stream_rx["GLOBAL_POSITION_INT"] = now
            if msg.lat == 0.0 and msg.lon == 0.0:  # ArduPilot's "no position yet"
                self.health.invalid_positions += 1
                if not self._warned_zero_position:
                    self._warned_zero_position = True
                    log.info("GLOBAL_POSITION_INT at 0 N 0 E: the autopilot has no position yet (not used)")
            else:
                self._last_position = (msg, now)
        elif isinstance(msg, GnssMessage):
            self._stream_rx["GPS_RAW_INT" if msg.instance == 0 else "GPS2_RAW"] = now
            if msg.instance == self.config.gnss_instance:
                if not msg.has_position:
                    self.health.invalid_positions += 1
                self._gnss.push(msg, now)
        elif isinstance(msg, LandedStateMessage):
            self._stream_rx["EXTENDED_SYS_STATE"] = now
            self._landed = (msg.landed, now)
        elif isinstance(msg, OriginMessage):
            self._on_origin(msg)
        elif isinstance(msg, PressureMessage):
            self._stream_rx["SCALED_PRESSURE"] = now
            self._on_pressure(msg)
        elif isinstance(msg, TimesyncMessage):
            if msg.tc1 == 0:  # a request: answer with our time (ns)
                self.link.send_timesync(int(self._wall() * 1e9), msg.ts1)
        elif isinstance(msg, CommandMessage):
            self._on_command(msg)
        elif isinstance(msg, Heartbeat):
            c = self.config
            if (msg.sysid, msg.compid) == (c.autopilot_system, c.autopilot_component):
                if now - self._ap_heartbeat_at > 1.8 and math.isfinite(self._ap_heartbeat_at):
                    self.health.heartbeat_gaps += 1
                    self._event("warning", f"autopilot silent {now - self._ap_heartbeat_at:.0f} s, asking again")
                    self._forget_streams()
                if not math.isfinite(self._ap_heartbeat_at):
                    self._next_request = 0.0  # a udpin link can only answer once the autopilot has spoken
                self._ap_heartbeat_at = now
                self._autopilot_type = msg.autopilot

    def _attitude_aid(self, m: AttitudeMessage) -> None:
        """The autopilot's attitude (its AHRS: accelerometers for the tilt, compass for the heading) every
        ``attitude_interval_s`` as a measurement of the INS attitude (:meth:`.online.OnlinePipeline.push_attitude`):
        it keeps a MEMS INS's tilt and heading from running away between map fixes."""
        c = self.config
        p = self._pipeline
        if not c.attitude_aid or p is None or not hasattr(p, "push_attitude"):
            return
        if m.t - self._last_attitude_aid_t < c.attitude_interval_s and m.t >= self._last_attitude_aid_t:
            return
        inn = p.push_attitude(m.t, q_nb_from_euler(m.roll, m.pitch, m.yaw), c.attitude_sigma_rad)
        if inn is None:
            return
        self._last_attitude_aid_t = m.t
        self.health.attitude_updates += 1
        self.health.attitude_accepted += int(inn.accepted)

    def _on_command(self, m: CommandMessage) -> None:
        c = self.config
        if m.command != GNSS_DENY_COMMAND or m.target_component not in (0, c.own_component):
            return
        if m.params[0] >= 0.5:
            self._gnss.deny("operator command")
        else:
            self._gnss.allow()
        self.link.send_command_ack(m.command, MAV_RESULT_ACCEPTED, m.sysid, m.compid)

    # -- streams -------------------------------------------------------------------------------------------
    def _stream_table(self) -> dict[str, float]:
        c = self.config
        streams = {
            "HIGHRES_IMU": c.imu_rate_hz,
            "ATTITUDE": 10.0,
            "GLOBAL_POSITION_INT": 5.0,
            "EXTENDED_SYS_STATE": 2.0,
        }
        if c.gnss_aiding or c.init is None:
            streams["GPS_RAW_INT" if c.gnss_instance == 0 else "GPS2_RAW"] = 5.0
        if c.baro:
            streams["SCALED_PRESSURE"] = c.baro_rate_hz
        return streams

    def _forget_streams(self) -> None:
        for name in self._stream_rx:
            self._stream_rx[name] = -math.inf
            self._stream_tries[name] = 0
        self._next_request = 0.0
        if self._origin is not None and not self._origin_from_autopilot:
            self._origin_sent_at = -math.inf  # the autopilot forgot it too

    def _check_streams(self, now: float) -> None:
        """Ask again for every stream missing for three of its intervals (at least 1.5 s), every
        ``request_interval_s``; after 10 unanswered requests a stream is asked for every 30 s only."""
        c = self.config
        if now < self._next_request:
            return
        self._next_request = now + c.request_interval_s
        for name, rate in self._streams.items():
            if now - self._stream_rx[name] <= max(3.0 / rate, 1.5):
                self._stream_tries[name] = 0
                continue
            tries = self._stream_tries[name]
            if tries >= 10 and tries % 15:
                self._stream_tries[name] += 1
                continue
            self.link.request_message_interval(name, rate, c.autopilot_system, c.autopilot_component)
            self._stream_tries[name] += 1
            self.health.stream_requests += 1
        if c.output == "odometry":
            self._check_origin(now)

    # -- GNSS ----------------------------------------------------------------------------------------------
    def _check_gnss(self, now: float) -> None:
        state = self._gnss.update(now)
        if state == self._gnss_state_seen:
            return
        before, self._gnss_state_seen = self._gnss_state_seen, state
        self.health.gnss_state = state
        c = self.config
        if state == "healthy":
            self._event("info", "GNSS healthy" + (", GNSS-aided" if c.gnss_aiding else ""))
            if c.ekf_source_set is not None and self._source_set_sent not in (None, 1):
                self._set_source(1)
        elif before == "healthy":
            self._event("warning", f"GNSS {'denied' if state == 'denied' else 'lost'}, map-aided")
            log.warning("GNSS %s: %s", state, self._gnss.reason)
            if c.ekf_source_set is not None:
                self._set_source(c.ekf_source_set)
            self._log_offset("GNSS lost")

    def _set_source(self, n: int) -> None:
        c = self.config
        self.link.send_command_long(SET_EKF_SOURCE_SET, (n,), c.autopilot_system, c.autopilot_component)
        self._source_set_sent = n
        log.info("asked the autopilot for EKF source set %d", n)

    def _gnss_fix(self) -> None:
        """Feed the latest healthy GNSS fix to the pipeline every ``gnss_fix_interval_s``."""
        c = self.config
        g = self._gnss.last
        if not (c.gnss_aiding and self._gnss.healthy) or g is None or g is self._last_gnss_fix:
            return
        if not hasattr(self._pipeline, "push_fix") or self._last_imu_t - self._last_gnss_fix_t < c.gnss_fix_interval_s:
            return
        # ArduPilot and PX4 stamp GPS_RAW_INT on the boot clock, as the IMU; otherwise use the arrival time
        t_fix = (g.t if abs(g.t - self._last_imu_t) < 2.0 else self._last_imu_t) - c.gnss_lag_s
        t_fix = min(t_fix, self._last_imu_t)
        s2 = self._gnss.last_sigma_m**2
        fix = Fix(t_fix, g.lat, g.lon, np.diag([s2, s2]), True, "", math.nan, "gnss")
        inn = self._pipeline.push_fix(fix)
        self._last_gnss_fix, self._last_gnss_fix_t = g, self._last_imu_t
        self.health.gnss_fixes += 1
        self.health.gnss_fixes_accepted += int(inn.accepted)

    def _gnss_held(self) -> _Held | None:
        g = self._gnss.last
        if not self._gnss.healthy or g is None:
            return None
        h = g.h_ellipsoid if math.isfinite(g.h_ellipsoid) else g.h_msl + self.config.geoid_height_m
        return _Held(g.lat, g.lon, h, self._gnss.last_sigma_m, "GNSS")

    # -- IMU -----------------------------------------------------------------------------------------------
    def _on_imu(self, m: ImuMessage) -> None:
        h = self.health
        unit = getattr(self.link, "mag_unit", None)
        if unit and unit != h.mag_unit:  # the link logs it once per change; the pilot hears it once too
            h.mag_unit = unit
            self._say.say("mag", "info", f"magnav: magnetometer in {_MAG_UNIT_TEXT.get(unit, unit)}")
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
        if self.config.imu_world == "flat":
            m = self._earth_sample(m)
            if m is None:
                return
        self._imu_seen_at = self._clock()
        self._last_imu_rx = self._imu_seen_at  # the newest sample, with the INS running or not (held, aligning)
        h.imu_samples += 1
        h.last_imu_t = m.t
        gap = math.isfinite(self._last_imu_t) and dt > self.config.max_gap_s
        if gap:
            h.imu_gaps += 1
            self._still.reset()
        if self._pipeline is None:
            self._last_imu_t = m.t
            self._pre_run(m)
            return
        if gap:
            self._restart_from_estimate(m.t, reason=f"IMU gap of {dt:.2f} s", extra_sigma_m=self._speed() * dt)
            self._last_imu_t = m.t
            return
        self._apply_baro(m.t)
        self._pipeline.push_imu(m.t, m.gyro_b, m.accel_b)
        self._last_imu_t = m.t
        self._gnss_fix()
        self._reading(m)
        if self.config.align:
            self._still.push(m.t, m.gyro_b, m.accel_b)
            landed = (self._landed_now() == "on_ground" and not self._moving()) or self._touched_down(m.t)
            if landed and self._still.still(self._g_mps2):
                self._enter_alignment()

    def _earth_sample(self, m: ImuMessage) -> ImuMessage | None:
        """A simulator's flat-world sample as a WGS84-Earth IMU would give it (:mod:`.flat_world`), at the INS's
        attitude, velocity and position (before the INS runs: the held position at rest, the autopilot's attitude).
        None while no position is known (such a sample is not used anyway)."""
        p = self._pipeline
        if p is not None:
            nav = p.nav_now() if hasattr(p, "nav_now") else p.estimate().nav
            q, v, lat, hgt = nav.q_nb, nav.v_n, nav.lat, nav.h
        else:
            held = self._held if self._held is not None else self._held_position()
            if held is None:
                return None
            att = self._last_attitude
            q = q_nb_from_euler(att[0].roll, att[0].pitch, att[0].yaw) if att is not None else np.array([0, 0, 0, 1.0])
            v, lat, hgt = np.zeros(3), held.lat, held.h
        gyro, accel = earth_imu(m.gyro_b, m.accel_b, q, v, lat, hgt, sphere_radius_m=self.config.flat_sphere_radius_m)
        return replace(m, gyro_b=gyro, accel_b=accel)

    def _reading(self, m: ImuMessage) -> None:
        if (
            m.mag_b_nt is None
            or self.field_model is None
            or m.t - self._last_reading_t < self.config.reading_interval_s
        ):
            return
        nav = self._pipeline.estimate().nav
        value = self.field_model(m.mag_b_nt, nav)
        if value is None or not np.all(np.isfinite(value)):
            return
        observe = getattr(self.field_model, "observe", None)
        if observe is not None and self.fmap is not None and self._aiding() == "gnss":
            mv = float(np.asarray(self.fmap.value(nav.lat, nav.lon)).reshape(-1)[0])
            if math.isfinite(mv) and observe(value, mv):
                self._log_offset("established")
            value = self.field_model(m.mag_b_nt, nav)  # with the offset just updated
        self._pipeline.push_reading(m.t, value)
        self._last_reading_t = m.t
        self.health.readings += 1

    def _log_offset(self, why: str) -> None:
        off = getattr(self.field_model, "offset_nt", math.nan)
        n = getattr(self.field_model, "offset_samples", 0)
        if math.isfinite(off):
            self.health.field_offset_nt = float(off)
            log.info("magnetometer offset (reading - map) %.1f nT from %d readings while GNSS-aided (%s)", off, n, why)

    def _moving(self) -> bool:
        """Evidence of motion other than the IMU's (a straight, steady flight looks still to an IMU): the landed
        state says flying, or the GNSS or the autopilot's velocity is above 0.5 m/s."""
        if self._landed_now() in ("in_air", "takeoff", "landing"):
            return True
        g = self._gnss.last
        if self._gnss.healthy and g is not None and math.isfinite(g.speed) and g.speed > 0.5:
            return True
        if self._flew and self._aiding() == "map":  # the autopilot's velocity is the bridge's own, sent to it
            return False
        pos = self._last_position
        if pos is not None and self._clock() - pos[1] < 2.0 and float(np.hypot(*pos[0].v_n[:2])) > 0.5:
            return True
        return False

    def _touched_down(self, t: float, hysteresis: float = 1.0) -> bool:
        """The autopilot says "landing" and the baro height at IMU time ``t`` is within ``touchdown_height_m``
        (times ``hysteresis``: 2 to stay aligned once down) of the height the bridge last aligned at on the ground
        (module docstring, ``aligning``). To enter (``hysteresis`` 1) the baro climb rate must also be below
        ``touchdown_climb_mps``: a steady descent looks still to an IMU, and SITL run 46 stopped its INS 2 s before
        the touchdown, 1.3 m up, descending at 0.5 m/s and drifting at 1.5 m/s, then sent a zero velocity."""
        if self._landed_now() != "landing" or self._ground_h is None or self._baro is None:
            return False
        h = self._baro.height(t)
        if h is None or abs(h - self._ground_h) > hysteresis * self.config.touchdown_height_m:
            return False
        if hysteresis > 1.0:
            return True
        climb = self._baro.climb_rate(t)
        return climb is not None and abs(climb) < self.config.touchdown_climb_mps

    def _landed_now(self) -> str:
        """The autopilot's landed state if it said so in the last 3 s, else "unknown"."""
        if self._landed is None or self._clock() - self._landed[1] > 3.0:
            return "unknown"
        return self._landed[0]

    # -- before the INS runs: waiting, aligning ------------------------------------------------------------
    def _held_position(self) -> _Held | None:
        """The best position to hold: the previous solution, --init or a healthy GNSS fix (the smaller sigma)."""
        c = self.config
        cands = [x for x in (self._held, self._gnss_held()) if x is not None]
        if c.init is not None and self._held is None:
            cands.append(_Held(c.init[0], c.init[1], c.init[2], c.init_sigma_m, "--init"))
        if not cands:
            return None
        best = min(cands, key=lambda x: x.sigma_m)
        if self._held is not None and best is not self._held:
            self._held = best  # a better fix while waiting on the ground
        return best

    def _pre_run(self, m: ImuMessage) -> None:
        c = self.config
        held = self._held_position()
        if held is None:
            self._set_state("waiting_for_position", False, "no GNSS, no --init")
            return
        if self._autopilot_type is None and c.sample_type == "auto":
            self._set_state("waiting_for_position", False, "no heartbeat yet")
            return
        self._g_mps2 = normal_gravity_mps2(held.lat, held.h)
        if self._held is None:
            self._held = held
        if self._baro is not None and not self._baro_ref_set:
            self._baro.set_reference(held.h, m.t)
            self._baro_ref_set = True
            self._h_sigma0 = held.sigma_m if held.source != "GNSS" else max(2.0 * held.sigma_m, 1.0)
        left = self._still.push(m.t, m.gyro_b, m.accel_b)
        if not self._still.full():
            return
        # after a flight only the autopilot's landed state allows a new alignment (a hover can look still)
        # "landing" at the takeoff height is on the ground too (module docstring): a touchdown's jolt or the motors
        # spinning down is no reason to start the INS again (SITL run 43: restarted 3 s after touchdown)
        touched = self._touched_down(m.t, 2.0)
        flying = not touched and (self._moving() or (self._flew and self._landed_now() != "on_ground"))
        imu_still = self._still.still(self._g_mps2)
        if c.align and touched and not imu_still:
            return
        if c.align and not flying and imu_still:
            on_ground = not self._flew or self._landed_now() == "on_ground"
            if on_ground and self._baro is not None and self._baro.referenced:
                self._ground_h = self._baro.height(m.t)
            for t, g, a in left:
                self._aligner.push(t, g, a)
            if self.health.state != "aligning":  # then the outputs' trust test (with its hysteresis) says
                ok = held.sigma_m <= c.max_sigma_m
                self._set_state("aligning", ok, "" if ok else "sigma above limit")
            return
        self._start_pipeline(m)

    def _enter_alignment(self) -> None:
        """Landed and still again: stop the INS, hold its position (the uncertainty is kept, not grown)."""
        est = self._pipeline.estimate()
        self._held = self._landing_hold(est)
        if hasattr(self._pipeline, "imu_bias"):
            self._carried_bias = self._pipeline.imu_bias
        self._count_fixes()
        self._close_pipeline()
        self._pipeline = None
        self._aligner.reset()
        self.health.alignments += 1
        self._event("info", "landed: INS stopped, position held")

    def _landing_hold(self, est: NavEstimate) -> _Held:
        """The position to hold after a landing: the solution's, or the autopilot's own estimate when that is fresh
        (under 1 s) and within the solution's 1-sigma of it, with the sigma grown by the distance (in quadrature).

        Why: the autopilot's estimate is a smoothed copy of what the bridge sent and lags it by a few metres (SITL
        run 46: 4.5 m, at a sigma of 28 m). Held at the bridge's solution, the autopilot's estimate then moves those
        metres on the ground; its position controller asks for a lean to follow (2 m is 22 deg at ArduCopter's
        default gains), and its land detector refuses a landing while more than 15 deg is asked for: the copter did
        not disarm. Holding the autopilot's estimate moves nothing, and costs less than the sigma it states."""
        sigma = _largest_sigma(est.cov_ne)
        own = _Held(est.nav.lat, est.nav.lon, est.nav.h, sigma, "solution before landing")
        pos = self._last_position
        if pos is None or self._clock() - pos[1] > 1.0 or not math.isfinite(sigma):
            return own
        ap = pos[0]
        d = float(horizontal_error_m(ap.lat, ap.lon, est.nav.lat, est.nav.lon))
        if not d <= sigma:
            return own
        log.info("landed: holding the autopilot's position, %.1f m from the solution (sigma %.1f m)", d, sigma)
        return _Held(ap.lat, ap.lon, est.nav.h, math.hypot(sigma, d), "autopilot's estimate at landing")

    def _sample_type(self) -> str:
        c = self.config
        if c.sample_type != "auto":
            return c.sample_type
        kind = {MAV_AUTOPILOT_ARDUPILOTMEGA: "ardupilot", MAV_AUTOPILOT_PX4: "px4"}.get(self._autopilot_type, "other")
        return AUTO_SAMPLE_TYPE[kind]

    def _start_pipeline(self, m: ImuMessage) -> None:
        c = self.config
        held = self._held_position()
        assert held is not None
        window = self._still.samples
        t0 = window[0][0] if window else m.t
        att = self._last_attitude[0] if self._last_attitude and self._clock() - self._last_attitude[1] < 2.0 else None
        v_n = np.zeros(3)
        aligned = self._aligner.duration_s >= 2.0
        if aligned:
            roll, pitch = self._aligner.level()
        elif att is not None:
            roll, pitch = att.roll, att.pitch
            pos = self._last_position
            if pos is not None and self._clock() - pos[1] < 2.0:
                v_n = np.asarray(pos[0].v_n, float)
        else:  # level the INS from the specific force (at rest or in steady flight)
            f = np.mean([s[2] for s in window], axis=0) if window else m.accel_b
            roll, pitch = math.atan2(-f[1], -f[2]), math.atan2(f[0], math.hypot(f[1], f[2]))
        if c.init is not None:
            yaw = c.init[3] if att is None or not self._flew else att.yaw
        elif att is not None:
            yaw = att.yaw
        else:
            self._set_state("waiting_for_position", False, "no ATTITUDE for heading")
            return
        q = q_nb_from_euler(roll, pitch, yaw)
        h = held.h
        if self._baro is not None and self._baro.referenced:
            hb = self._baro.height(t0)
            h = hb if hb is not None else h
        nav = NavState(t0, held.lat, held.lon, h, v_n, q)
        pipe = self.make_pipeline(nav, held.sigma_m)
        gyro_bias, accel_bias = self._carried_bias if self._carried_bias is not None else (np.zeros(3), np.zeros(3))
        if aligned and self._aligner.duration_s >= 5.0:
            gyro_bias = self._aligner.gyro_bias(q, held.lat)
        if hasattr(pipe, "set_static_bias"):
            pipe.set_static_bias(gyro_bias, accel_bias)
        if hasattr(pipe, "set_sample_type"):
            pipe.set_sample_type(self._sample_type())
        self.health.sample_type = self._sample_type()
        self._pipeline = pipe
        self._flew = True
        self.health.pipeline_starts += 1
        log.info(
            "INS started at t=%.2f s from %s (sigma %.1f m), %s, gyro bias %s rad/s, %s samples",
            t0, held.source, held.sigma_m, f"aligned {self._aligner.duration_s:.0f} s" if aligned else "not aligned",
            np.array2string(gyro_bias, precision=6), self.health.sample_type,
        )  # fmt: skip
        if self._origin is None:
            self._origin = (held.lat, held.lon, held.h)
        if self._baro is not None and not self._baro_ref_set:
            self._baro.set_reference(h, t0)
            self._baro_ref_set = True
            self._h_sigma0 = held.sigma_m if held.source != "GNSS" else max(2.0 * held.sigma_m, 1.0)
        for t, g, a in window:  # the samples of the window that ended the stillness
            if t > t0:
                self._apply_baro(t)
                pipe.push_imu(t, g, a)
        self._last_imu_t = m.t if not window else max(m.t, window[-1][0])
        self._still.reset()
        self._aligner.reset()
        self._held = None
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
        if self._pipeline is None:
            return
        h_baro = self._baro_height(t)
        if h_baro is None:
            return
        if not hold_height(self._pipeline, h_baro) and not self._baro_unusable_warned:
            self._baro_unusable_warned = True
            log.warning("barometer: the pipeline holds no altitude (fusion without altitude hold): baro not used")

    def _baro_height(self, t: float) -> float | None:
        """The baro height (m) at IMU time ``t``, announcing when the barometer is lost and back; None without one."""
        if self._baro is None:
            return None
        h_baro = self._baro.height(t)
        state = self._baro.health.state
        if state != self.health.baro_state:
            if state == "stale":
                self.health.baro_stale_events += 1
                self._say.say("baro", "warning", "magnav: baro lost, height held")
            elif state == "active" and self.health.baro_state == "stale":
                self._say.say("baro", "info", "magnav: baro back")
            self.health.baro_state = state
        return h_baro

    def _baro_climb_rate(self, t: float) -> float | None:
        """Baro climb rate (m/s, up) while the barometer drives the INS height, else None."""
        if self._baro is None or self._baro_unusable_warned or not self._baro.referenced:
            return None
        return self._baro.climb_rate(t)

    # -- restarts, reboots, link loss ------------------------------------------------------------------------
    def _count_fixes(self) -> None:
        """Add the current pipeline's map fixes to the counters (its lists are dropped with it)."""
        p = self._pipeline
        if p is None or not hasattr(p, "fixes"):
            return
        done = getattr(self, "_counted", (None, 0, 0, 0))
        n0, i0, a0 = (done[1], done[2], done[3]) if done[0] is p else (0, 0, 0)
        fixes, inns = p.fixes, p.innovations
        self.health.map_fixes += len(fixes) - n0
        self.health.map_fixes_issued += sum(1 for f in fixes[n0:] if f.available)
        self.health.map_fixes_accepted += sum(1 for x in inns[i0:] if x.accepted)
        for f in fixes[n0:]:
            if f.available:
                s = np.sqrt(np.clip(np.linalg.eigvalsh(np.asarray(f.cov_ne, float)), 0.0, None))
                log.info("map fix at t=%.1f s: %.7f, %.7f, sigma %.0f / %.0f m", f.t, math.degrees(f.lat),
                         math.degrees(f.lon), s[0], s[-1])  # fmt: skip
            if not f.available:
                log.info("map: no fix at t=%.1f s: %s", f.t, f.reason)
                key = f.reason.split(":")[0] or "unspecified"
                self.health.no_fix_reasons[key] = self.health.no_fix_reasons.get(key, 0) + 1
        for x in inns[i0:]:
            if not x.accepted and x.reason and x.reason != "no fix":
                key = x.reason.split(" ")[0] if x.reason.startswith(("NIS", "window")) else x.reason.split(":")[0]
                self.health.rejected_reasons[key] = self.health.rejected_reasons.get(key, 0) + 1
        self._counted = (p, len(fixes), len(inns), 0)

    def _restart_from_estimate(self, t: float, reason: str, extra_sigma_m: float) -> None:
        """Re-initialise the pipeline at time ``t`` from the current estimate with inflated position uncertainty,
        keeping the IMU biases estimated so far."""
        assert self._pipeline is not None
        est = self._pipeline.estimate()
        sigma = math.sqrt(max(np.trace(est.cov_ne) / 2.0, 0.0)) + extra_sigma_m
        nav = est.nav
        bias = self._pipeline.imu_bias if hasattr(self._pipeline, "imu_bias") else None
        self._count_fixes()
        self._close_pipeline()
        pipe = self.make_pipeline(NavState(t, nav.lat, nav.lon, nav.h, nav.v_n, nav.q_nb), sigma)
        if bias is not None and hasattr(pipe, "set_static_bias"):
            pipe.set_static_bias(*bias)
        if hasattr(pipe, "set_sample_type"):
            pipe.set_sample_type(self._sample_type())
        self._pipeline = pipe
        self._reset_counter += 1
        log.warning("%s: INS restarted from the last estimate, position sigma now %.0f m", reason, sigma)
        self._event("warning", f"{reason.split(' of ')[0]}, INS restarted")

    def _on_reboot(self, m: ImuMessage) -> None:
        self.health.reboots += 1
        self._last_imu_t = m.t
        self._forget_streams()
        self._still.reset()
        if self._pipeline is not None:
            self._restart_from_estimate(m.t, "autopilot rebooted", extra_sigma_m=self._speed() * 1.0)
        else:
            self._aligner.reset()
        if self._baro is not None and self._baro.referenced:
            pass  # the baro filter restarts on its own clock jump and keeps its reference

    def _on_link_loss(self) -> None:
        if self.health.state == "link_lost":
            return
        self.health.link_losses += 1
        prev = self.health.state
        self._set_state("link_lost", False, f"silent {self.config.link_timeout_s:.0f} s")
        try:
            self.link.reconnect()
        except Exception as exc:  # noqa: BLE001 - keep running, try again at the next timeout
            log.warning("reconnect failed: %s", exc)
        self._last_rx = self._clock()
        self._forget_streams()
        self.health.state = (
            prev if prev != "link_lost" else ("waiting_for_imu" if self._pipeline is None else "running")
        )

    def _speed(self) -> float:
        if self._pipeline is None:
            return 0.0
        return float(np.linalg.norm(self._pipeline.estimate().nav.v_n[:2]))

    # -- ODOMETRY origin -----------------------------------------------------------------------------------
    def _on_origin(self, m: OriginMessage) -> None:
        origin = (m.lat, m.lon, m.h_msl + self.config.geoid_height_m)
        if self._origin is not None and not self._origin_from_autopilot:
            d = float(horizontal_error_m(m.lat, m.lon, self._origin[0], self._origin[1]))
            if d > 1.0:
                log.warning(
                    "the autopilot's EKF origin is %.0f m from the one the bridge set: using the autopilot's", d
                )
        if self._origin != origin:
            log.info(
                "EKF origin from the autopilot: %.7f, %.7f, %.1f m", math.degrees(m.lat), math.degrees(m.lon), m.h_msl
            )
        self._origin, self._origin_from_autopilot = origin, True

    def _check_origin(self, now: float) -> None:
        """Ask for the autopilot's origin; if it has none after 5 s, set ours (again after a reboot)."""
        c = self.config
        if self._origin_from_autopilot:
            return
        if now - self._origin_requested_at >= c.request_interval_s:
            self.link.request_message("GPS_GLOBAL_ORIGIN", c.autopilot_system, c.autopilot_component)
            if self._origin_requested_at == -math.inf:
                self._origin_first_request = now
            self._origin_requested_at = now
        first = getattr(self, "_origin_first_request", now)
        if self._origin is not None and now - first > 5.0 and now - self._origin_sent_at > 10.0:
            lat, lon, hgt = self._origin
            self.link.send_set_gps_global_origin(c.autopilot_system, lat, lon, hgt - c.geoid_height_m)
            self._origin_sent_at = now
            log.info("the autopilot has no EKF origin: sent SET_GPS_GLOBAL_ORIGIN")

    # -- output --------------------------------------------------------------------------------------------
    def _vertical_sigma(self, t: float) -> float:
        """1-sigma of the output height, m: the initial height's, grown by a barometer's drift (1 m + 1 cm/s since
        its reference); without a barometer the held height is as uncertain as 10 m plus the initial sigma."""
        if self._baro is not None and self._baro.referenced and self.health.baro_state == "active":
            dt = max(t - getattr(self._baro, "_t_ref", t), 0.0)
            return math.hypot(self._h_sigma0, 1.0 + 0.01 * dt)
        return math.hypot(self._h_sigma0, 10.0)

    def _solution(self) -> _Solution | None:
        if self._pipeline is None:
            held = self._held if self.health.state == "aligning" else None
            if held is None:
                return None
            roll, pitch = self._aligner.level() if self._aligner.duration_s > 0 else (0.0, 0.0)
            att = self._last_attitude
            yaw = att[0].yaw if att is not None else (self.config.init[3] if self.config.init else 0.0)
            t = self._last_imu_t
            h_baro = self._baro_height(t)
            climb = self._baro_climb_rate(t) if h_baro is not None else None
            v_n = np.array([0.0, 0.0, -climb if climb is not None else 0.0])
            return _Solution(
                t, held.lat, held.lon, held.h if h_baro is None else h_baro, v_n, q_nb_from_euler(roll, pitch, yaw),
                np.diag([held.sigma_m**2] * 2), self._vertical_sigma(t), 0.05, math.nan, True,
            )  # fmt: skip
        est = self._pipeline.estimate()
        nav = est.nav
        v_n = nav.v_n
        climb = self._baro_climb_rate(nav.t)
        if climb is not None:  # the held vertical channel says v_D = 0: send the barometer's rate instead
            v_n = np.array([v_n[0], v_n[1], -climb])
        P = np.asarray(est.P)
        vel = est.layout["vel"]
        sigma_speed = math.sqrt(max((P[vel.start, vel.start] + P[vel.start + 1, vel.start + 1]) / 2.0, 0.0))
        finite = bool(np.all(np.isfinite(P[:9, :9])) and math.isfinite(nav.lat) and math.isfinite(nav.lon))
        hpl = float(getattr(est, "hpl_m", math.nan))
        return _Solution(nav.t, nav.lat, nav.lon, nav.h, v_n, nav.q_nb, np.asarray(est.cov_ne, float),
                         self._vertical_sigma(nav.t), sigma_speed, hpl, finite)  # fmt: skip

    def _trust(self, s: _Solution) -> tuple[bool, str]:
        c = self.config
        if self._clock() - self._imu_seen_at > c.stale_imu_s:
            return False, "IMU stale"
        if not s.finite:
            return False, "not finite"
        scale = 1.0 if self._sigma_ok else c.trust_hysteresis
        # the sigma limit always (EKF3 takes at most 100 m of accuracy: a larger sigma sent would be read as smaller),
        # the protection level's on top where the fuser computes one
        ok, why = s.sigma_h <= scale * c.max_sigma_m, "sigma above limit"
        if ok and math.isfinite(s.hpl_m):
            ok, why = s.hpl_m <= scale * c.alert_limit, "HPL above limit"
        self._sigma_ok = ok
        return (True, "") if ok else (False, why)

    def _speed_accuracy(self, s: _Solution) -> float:
        """The speed accuracy GPS_INPUT carries, m/s: the filter's velocity sigma, but at least ``sigma_h /
        follow_s``. A consumer that fuses position (variance ``sigma_h^2``) and velocity (``sigma_v^2``) as white
        measurements at one rate, as EKF3 does GPS_INPUT, takes up a change of the position with a time constant
        of about ``sigma_h / sigma_v`` (``tests/test_mavlink_gps_follow.py``). The bridge's velocity does not carry
        its map fixes' position corrections (they are steps of its position), and its position and velocity errors
        are not white but slow: at the filter's own ``sigma_v`` (0.05-0.6 m/s while ``sigma_h`` was 10-80 m) EKF3
        took 100-200 s to take up a fix, so on SITL run 29 it flew 28.8 m RMS off the truth while the bridge it
        followed was 22 m off (its model replays the recorded EKF within 6 m RMS). A larger speed accuracy says less
        than the bridge knows, never more; with ``follow_s`` = 20 s a correction of one sigma moves EKF3's velocity
        by at most 0.4 m/s (its velocity gate is 5 x 0.3 m/s). The floor stops at :data:`MAX_SPEED_FLOOR_MPS`:
        EKF3 flags "GPS glitching" (Copter: "GPS Glitch or Compass error", run 31) while the speed accuracy it
        is sent, low-passed and peak-held, is above 1.5 m/s (``calcGpsGoodForFlight``); above 24 m of sigma the
        time constant is then ``sigma_h / 1.2 m/s`` (33 s at 40 m, still 3-4 times shorter than before).

        While aligning (still on the ground, the position held: no steps to smooth) the velocity's own sigma: after
        a touchdown EKF3 should learn at once that the vehicle stopped. At 1.2 m/s it took 20 s to take up the step
        from the INS's last velocity to zero (SITL run 43, 0.9 m/s); with the velocity's sigma 10 s (run 46). In
        both runs ArduCopter then stayed "landing" and did not disarm (run 45 disarmed 2.2 s after touchdown): its
        position loop asked for a 23-29 deg lean after touching down with the bridge's velocity error (about
        1 m/s), which its land detector refuses (README, SITL runs 42-46)."""
        if self.health.state == "aligning":
            return s.sigma_speed
        return max(s.sigma_speed, min(s.sigma_h / self.config.follow_s, MAX_SPEED_FLOOR_MPS))

    def _send_while_gnss(self) -> bool:
        c = self.config
        if c.send_while_gnss != "auto":
            return c.send_while_gnss == "yes"
        return (c.output == "gps_input" and c.gps_id >= 1) or (c.output == "odometry" and c.ekf_source_set is not None)

    def _no_fix(self) -> None:
        c = self.config
        if c.output == "gps_input":  # keep the GPS stream alive with "no fix"
            self.link.send_gps_input(
                t_unix=self._wall(), lat=0.0, lon=0.0, h_msl=0.0, v_n=np.zeros(3), sigma_h=99.0, sigma_v=99.0,
                sigma_speed=99.0, healthy=False, gps_id=c.gps_id,
            )  # fmt: skip

    def _send_output(self) -> None:
        c = self.config
        self._count_fixes()  # counts (and logs) the map fixes as they come
        s = self._solution()
        if s is None:
            self._no_fix()
            return
        trusted, reason = self._trust(s)
        if self.health.state in ("running", "degraded"):
            self._set_state("running" if trusted else "degraded", trusted, reason)
        elif self.health.state == "aligning" and self.health.healthy != trusted:
            self._set_state("aligning", trusted, reason)
        quiet = self._gnss.healthy and c.gnss_aiding and not self._send_while_gnss()
        if self.on_output is not None:
            self.on_output(
                {"t_wall": self._wall(), "t": s.t, "lat": s.lat, "lon": s.lon, "h": s.h, "sigma_h": s.sigma_h,
                 "cov_ne": s.cov_ne,
                 "hpl": s.hpl_m, "trusted": trusted, "sent": not quiet and (trusted or c.output != "odometry"),
                 "state": self.health.state, "aiding": self.health.aiding}
            )  # fmt: skip
        if quiet:
            self._no_fix()  # the autopilot has its own GNSS: do not compete with it
            return
        if not trusted:
            self.health.untrusted_outputs += 1
        h_msl = s.h - c.geoid_height_m
        if c.output == "gps_input":
            ignore = 0 if (self._baro is not None and self.health.baro_state == "active") else GPS_INPUT_IGNORE_VEL_VERT
            self.link.send_gps_input(
                t_unix=self._wall(), lat=s.lat, lon=s.lon, h_msl=h_msl, v_n=s.v_n, sigma_h=s.sigma_h,
                sigma_v=s.sigma_v, sigma_speed=self._speed_accuracy(s), healthy=trusted, gps_id=c.gps_id,
                ignore_flags=ignore,
            )  # fmt: skip
        elif c.output == "odometry":
            if not trusted or self._origin is None:
                return  # ODOMETRY has no "invalid" flag ArduPilot honours: send nothing
            r_ned = geodetic_to_ned(s.lat, s.lon, s.h, *self._origin)
            v_b = C_nb_from_q(s.q_nb).T @ s.v_n
            self.link.send_odometry(
                t_usec=int(s.t * 1e6), r_ned=r_ned, q_nb=s.q_nb, v_b=v_b,
                sigma_pos=np.array([s.sigma_h, s.sigma_h, s.sigma_v]), sigma_vel=np.full(3, s.sigma_speed),
                reset_counter=self._reset_counter & 0xFF, quality=100 if trusted else 0,
            )  # fmt: skip
        else:
            self.link.send_global_position_sensor(
                target_system=c.autopilot_system, target_component=c.autopilot_component, t_usec=int(s.t * 1e6),
                processing_us=0, source=c.global_position_source, lat=s.lat, lon=s.lon, h_ellipsoid=s.h, h_msl=h_msl,
                sigma_h=s.sigma_h, sigma_v=s.sigma_v, healthy=trusted,
            )  # fmt: skip
        self.health.outputs_sent += 1
        if math.isfinite(self._last_imu_rx):
            self.latencies_s.append(self._clock() - self._last_imu_rx)


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
    cache *before* the bridge connects, not when the autopilot's first IMU sample arrives; with readings, for at least
    one full matcher window (the pipeline's ``window`` readings: with 80 and 4 s of readings no scan ran, and on the
    first run after an install the first scan in flight compiled the matcher's kernels in the worker, 2.2 s holding
    the interpreter up to 0.26 s at a time, measured; a scan in the background is waited for). Returns the seconds
    spent.
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
        if hasattr(pipe, "min_section_m"):  # the warm-up stands still: scan anyway, the kernels are what it is for
            pipe.min_section_m = 0.0
        if value_needed := field_value_at is not None:  # long enough for one full matcher window (one scan)
            seconds = max(seconds, (int(getattr(pipe, "window", 0) or 0) + 1) * reading_interval_s)
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
        if value_needed and hasattr(pipe, "finish_matching"):  # a background scan: its kernels loaded now too
            pipe.finish_matching(timeout_s=120.0)
    except MagnavError:
        raise
    except Exception as exc:  # noqa: BLE001 - warm-up only; the real run reports its own errors
        log.debug("warm-up: %s", exc)
    return time.monotonic() - t0


def _map_centre(fmap) -> tuple[float, float]:
    lat_s, lat_n, lon_w, lon_e = fmap.bounds_latlon
    return 0.5 * (lat_s + lat_n), 0.5 * (lon_w + lon_e)
