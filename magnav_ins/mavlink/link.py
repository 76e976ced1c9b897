"""The one module that imports pymavlink: a MAVLink link speaking SI on its public face.

Everything MAVLink-specific stays here: degE7 latitudes, millimetre altitudes, ``time_usec``, scaled IMU units
(mG, mrad/s, mgauss), the magnetometer scale quirk of ArduPilot's HIGHRES_IMU, message ids, signing. The bridge and the
autopilot emulator both use :class:`MavLink` and receive plain dataclasses (:class:`ImuMessage`, ...).

Frames: MAVLink IMU messages are body FRD (x forward, y right, z down), the same as ours; accelerations are specific
force (about -9.81 m/s^2 on z at rest). Magnetometer values are returned in nT.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
import select
import socket
import struct
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

os.environ.setdefault("MAVLINK20", "1")  # MAVLink 2 framing (needed for signing and message ids > 255)

from pymavlink import mavutil  # noqa: E402
from pymavlink.dialects.v20 import ardupilotmega as mavlink2  # noqa: E402

from ..core.errors import InputError, LinkError  # noqa: E402
from ..core.units import G0, NT_PER_GAUSS  # noqa: E402

log = logging.getLogger(__name__)

DEG_E7 = 1e7  #: MAVLink integer latitude/longitude unit, 1e-7 deg
GPS_EPOCH_UNIX_S = 315964800.0  #: 1980-01-06T00:00:00Z as a Unix time
GPS_MINUS_UTC_S = 18.0  #: leap seconds between GPS time and UTC (since 2017)
SECONDS_PER_WEEK = 604800.0

MAV_TYPE_ONBOARD_CONTROLLER = mavlink2.MAV_TYPE_ONBOARD_CONTROLLER
MAV_COMP_ID_ONBOARD_COMPUTER = mavlink2.MAV_COMP_ID_ONBOARD_COMPUTER  # 191
MAV_FRAME_LOCAL_FRD = mavlink2.MAV_FRAME_LOCAL_FRD
MAV_FRAME_BODY_FRD = mavlink2.MAV_FRAME_BODY_FRD

#: message ids the bridge asks the autopilot for with SET_MESSAGE_INTERVAL
MSG_ID = {
    "HIGHRES_IMU": mavlink2.MAVLINK_MSG_ID_HIGHRES_IMU,
    "RAW_IMU": mavlink2.MAVLINK_MSG_ID_RAW_IMU,
    "SCALED_IMU": mavlink2.MAVLINK_MSG_ID_SCALED_IMU,
    "ATTITUDE": mavlink2.MAVLINK_MSG_ID_ATTITUDE,
    "GLOBAL_POSITION_INT": mavlink2.MAVLINK_MSG_ID_GLOBAL_POSITION_INT,
    "SCALED_PRESSURE": mavlink2.MAVLINK_MSG_ID_SCALED_PRESSURE,
    "GPS_RAW_INT": mavlink2.MAVLINK_MSG_ID_GPS_RAW_INT,
    "GPS2_RAW": mavlink2.MAVLINK_MSG_ID_GPS2_RAW,
    "EXTENDED_SYS_STATE": mavlink2.MAVLINK_MSG_ID_EXTENDED_SYS_STATE,
    "GPS_GLOBAL_ORIGIN": mavlink2.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN,
    "SIM_STATE": mavlink2.MAVLINK_MSG_ID_SIM_STATE,
    "EKF_STATUS_REPORT": mavlink2.MAVLINK_MSG_ID_EKF_STATUS_REPORT,
    "HOME_POSITION": mavlink2.MAVLINK_MSG_ID_HOME_POSITION,
}

SET_MESSAGE_INTERVAL = mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL  # 511
REQUEST_MESSAGE = mavlink2.MAV_CMD_REQUEST_MESSAGE  # 512
SET_EKF_SOURCE_SET = mavlink2.MAV_CMD_SET_EKF_SOURCE_SET  # 42007, ArduPilot 4.1+
#: COMMAND_LONG to the bridge's own component: param1 = 1 marks the autopilot's GNSS untrusted (operator denial),
#: 0 trusts it again (MAV_CMD_USER_1, a command id MAVLink leaves to the user)
GNSS_DENY_COMMAND = mavlink2.MAV_CMD_USER_1
MAV_RESULT_ACCEPTED = mavlink2.MAV_RESULT_ACCEPTED
LANDED_STATE = {
    mavlink2.MAV_LANDED_STATE_UNDEFINED: "undefined",
    mavlink2.MAV_LANDED_STATE_ON_GROUND: "on_ground",
    mavlink2.MAV_LANDED_STATE_IN_AIR: "in_air",
    mavlink2.MAV_LANDED_STATE_TAKEOFF: "takeoff",
    mavlink2.MAV_LANDED_STATE_LANDING: "landing",
}
#: GPS_INPUT ignore_flags bits
GPS_INPUT_IGNORE_VEL = mavlink2.GPS_INPUT_IGNORE_FLAG_VEL_HORIZ | mavlink2.GPS_INPUT_IGNORE_FLAG_VEL_VERT
GPS_INPUT_IGNORE_VEL_VERT = mavlink2.GPS_INPUT_IGNORE_FLAG_VEL_VERT
GPS_INPUT_IGNORE_SPEED_ACCURACY = mavlink2.GPS_INPUT_IGNORE_FLAG_SPEED_ACCURACY
MAV_MODE_FLAG_SAFETY_ARMED = mavlink2.MAV_MODE_FLAG_SAFETY_ARMED

SEVERITY = {"emergency": 0, "alert": 1, "critical": 2, "error": 3, "warning": 4, "notice": 5, "info": 6, "debug": 7}
GLOBAL_POSITION_SOURCE = {
    "magnetic": mavlink2.GLOBAL_POSITION_SRC_MAGNETIC,
    "terrain": mavlink2.GLOBAL_POSITION_SRC_TERRAIN,
}
GLOBAL_POSITION_UNHEALTHY = 1
GLOBAL_POSITION_PRIMARY = 2

MILLI_G_TO_MPS2 = G0 / 1000.0
MILLIRAD_TO_RAD = 1e-3


# --- what the link hands to its users (SI, our frames) ---------------------------------------------------
@dataclass(frozen=True)
class Heartbeat:
    """HEARTBEAT: ``armed`` from ``base_mode``; ``custom_mode`` the autopilot's flight mode number."""

    sysid: int
    compid: int
    mav_type: int
    autopilot: int
    base_mode: int = 0
    custom_mode: int = 0
    system_status: int = 0

    @property
    def armed(self) -> bool:
        return bool(self.base_mode & MAV_MODE_FLAG_SAFETY_ARMED)


@dataclass(frozen=True)
class ImuMessage:
    """One IMU sample: ``t`` s on the autopilot clock, ``gyro_b`` rad/s, ``accel_b`` m/s^2 specific force (FRD),
    ``mag_b_nt`` nT or None, ``source`` the message name (HIGHRES_IMU, SCALED_IMU, RAW_IMU)."""

    t: float
    gyro_b: np.ndarray
    accel_b: np.ndarray
    mag_b_nt: np.ndarray | None
    source: str
    sysid: int
    compid: int


@dataclass(frozen=True)
class AttitudeMessage:
    t: float
    roll: float
    pitch: float
    yaw: float
    sysid: int
    compid: int


@dataclass(frozen=True)
class PositionMessage:
    """GLOBAL_POSITION_INT: ``lat``, ``lon`` rad, ``h_msl`` m, ``v_n`` NED m/s."""

    t: float
    lat: float
    lon: float
    h_msl: float
    v_n: np.ndarray
    sysid: int
    compid: int


@dataclass(frozen=True)
class GnssMessage:
    """GPS_RAW_INT (``instance`` 0) or GPS2_RAW (1): the autopilot's raw GNSS receiver, not its EKF.

    ``t`` s (``time_usec``: ArduPilot and PX4 stamp it on the boot clock), ``fix_type`` (0-1 no fix, 2 2D, 3 3D,
    4 DGPS, 5-6 RTK), ``lat``/``lon`` rad, ``h_msl`` m, ``h_ellipsoid`` m (nan when not sent), ``sigma_h`` /
    ``sigma_v`` m (``h_acc``/``v_acc``; nan when not sent), ``hdop`` (nan if unknown), ``satellites`` (-1 if
    unknown), ``speed`` m/s and ``course`` rad (nan if unknown)."""

    t: float
    instance: int
    fix_type: int
    lat: float
    lon: float
    h_msl: float
    h_ellipsoid: float
    sigma_h: float
    sigma_v: float
    hdop: float
    satellites: int
    speed: float
    course: float
    sysid: int
    compid: int

    @property
    def has_position(self) -> bool:
        """A 3D fix with a position that is not the 0 N 0 E placeholder."""
        return self.fix_type >= 3 and not (self.lat == 0.0 and self.lon == 0.0)


@dataclass(frozen=True)
class LandedStateMessage:
    """EXTENDED_SYS_STATE: ``landed`` one of :data:`LANDED_STATE`'s values."""

    landed: str
    sysid: int
    compid: int


@dataclass(frozen=True)
class OriginMessage:
    """GPS_GLOBAL_ORIGIN: the autopilot's EKF origin, ``lat``/``lon`` rad, ``h_msl`` m."""

    lat: float
    lon: float
    h_msl: float
    sysid: int
    compid: int


@dataclass(frozen=True)
class StatusTextMessage:
    """STATUSTEXT: ``severity`` 0 (emergency) .. 7 (debug), ``text``."""

    severity: int
    text: str
    sysid: int
    compid: int


@dataclass(frozen=True)
class CommandAckMessage:
    command: int
    result: int
    sysid: int
    compid: int


@dataclass(frozen=True)
class ParamMessage:
    """PARAM_VALUE: ``name``, ``value``."""

    name: str
    value: float
    sysid: int
    compid: int


@dataclass(frozen=True)
class TruthMessage:
    """SIM_STATE (ArduPilot SITL's simulated truth): ``lat``/``lon`` rad, ``h_msl`` m, ``v_n`` NED m/s, ``roll``,
    ``pitch``, ``yaw`` rad; ``t_rx`` monotonic receive time, s."""

    t_rx: float
    lat: float
    lon: float
    h_msl: float
    v_n: np.ndarray
    roll: float
    pitch: float
    yaw: float
    sysid: int
    compid: int


@dataclass(frozen=True)
class EkfStatusMessage:
    """EKF_STATUS_REPORT (ArduPilot): ``flags`` (EKF_STATUS_FLAGS bits), and the innovation test ratios EKF3 reports
    as "variances" (``velocity``, ``pos_horiz``, ``pos_vert``, ``compass``, ``terrain``; 1.0 = at the gate,
    dimensionless); ``t_rx`` monotonic receive time, s."""

    t_rx: float
    flags: int
    velocity: float
    pos_horiz: float
    pos_vert: float
    compass: float
    terrain: float
    sysid: int
    compid: int


@dataclass(frozen=True)
class PressureMessage:
    """SCALED_PRESSURE: ``t`` s on the autopilot clock (``time_boot_ms``), static ``pressure_pa`` Pa (the message
    carries hPa), ``temperature_c`` degC."""

    t: float
    pressure_pa: float
    temperature_c: float
    sysid: int
    compid: int


@dataclass(frozen=True)
class TimesyncMessage:
    tc1: int
    ts1: int
    sysid: int
    compid: int


@dataclass(frozen=True)
class CommandMessage:
    """COMMAND_LONG received (the emulator answers SET_MESSAGE_INTERVAL)."""

    command: int
    params: tuple[float, ...]
    sysid: int
    compid: int
    target_system: int = 0
    target_component: int = 0


@dataclass(frozen=True)
class OutputMessage:
    """A position output seen by a receiver (the emulator records what the bridge sent): ``lat``, ``lon`` rad,
    ``h`` m, ``sigma_h`` m, ``healthy``, ``kind`` (gps_input, odometry, global_position_sensor), receive time ``t_rx``
    (s, monotonic)."""

    kind: str
    t_rx: float
    lat: float
    lon: float
    h: float
    sigma_h: float
    healthy: bool
    fields: dict


@dataclass
class LinkStats:
    """Counters of what the link dropped and why."""

    received: int = 0
    bad_data: int = 0
    rejected_signature: int = 0  # every frame dropped by signing: unsigned or wrongly signed
    rejected_unsigned: int = 0  # of which unsigned (the peer does not sign)
    foreign_source: int = 0
    sent: int = 0

    def as_dict(self) -> dict[str, int]:
        return dataclasses.asdict(self)


# --- magnetometer scale ----------------------------------------------------------------------------------
def highres_mag_to_nt(m: np.ndarray) -> tuple[np.ndarray, str]:
    """Convert HIGHRES_IMU ``x/y/zmag`` to nT, detecting the unit from the magnitude.

    The message definition says gauss, but ArduPilot fills milligauss x 1000 (about 224015 for a 0.224 G field; see
    ../shared/MAVLINK_NOTES.md). The Earth's field is 0.25-0.65 G; allowing for interference we accept 0.1-1.5 G in
    gauss, milligauss or ArduPilot's micro-gauss scale. Returns the field in nT and the unit detected.
    """
    mag = float(np.linalg.norm(m))
    for unit, to_gauss in (("gauss", 1.0), ("milligauss", 1e-3), ("milligauss*1000", 1e-6)):
        g = mag * to_gauss
        if 0.1 <= g <= 1.5:
            return np.asarray(m, float) * to_gauss * NT_PER_GAUSS, unit
    raise InputError(f"HIGHRES_IMU magnetometer magnitude {mag:g} fits no known unit (gauss, mG, ArduPilot mG*1000)")


def odometry_covariance_entry(sigma: float) -> float:
    """The value for ODOMETRY pose_covariance c[0], c[6], c[11] such that ArduPilot's collapse
    ``cbrt(c0^2 + c6^2 + c11^2)`` returns ``sigma`` (m): ``sqrt(sigma^3 / 3)``."""
    return math.sqrt(sigma**3 / 3.0)


def odometry_collapsed_sigma(c0: float, c6: float, c11: float) -> float:
    """What ArduPilot (AP_VisualOdom via GCS_MAVLink handle_odometry) makes of the pose covariance entries."""
    return (c0**2 + c6**2 + c11**2) ** (1.0 / 3.0)


def unix_to_gps_week(t_unix: float) -> tuple[int, int]:
    """GPS week number and milliseconds of week for a Unix time (s), as GPS_INPUT wants them."""
    t_gps = t_unix - GPS_EPOCH_UNIX_S + GPS_MINUS_UTC_S
    week = int(t_gps // SECONDS_PER_WEEK)
    return week, int(round((t_gps - week * SECONDS_PER_WEEK) * 1000.0))


#: pymavlink URL schemes that take HOST:PORT
_NET_SCHEMES = ("udpin", "udpout", "udp", "udpbcast", "tcp", "tcpin")


def check_url(url: str) -> str:
    """``url`` if it is a connection the bridge can open (``udpin:HOST:PORT``, ``udpout:``, ``udp:``, ``tcp:``,
    ``tcpin:`` with a port 1-65535, or a serial device path), else :class:`LinkError` with a one-line message (pymavlink
    itself answers a bad port with "invalid literal for int()")."""
    expected = "expected udpin:HOST:PORT, udpout:HOST:PORT, tcp:HOST:PORT, tcpin:HOST:PORT or a serial device"
    text = str(url).strip()
    scheme, sep, rest = text.partition(":")
    if sep and scheme.lower() in _NET_SCHEMES:
        host, _, port = rest.rpartition(":")
        if not host:
            raise LinkError(f"--connect {url!r}: no host; {expected}")
        if not port.isdigit() or not 0 < int(port) < 65536:
            raise LinkError(f"--connect {url!r}: port {port!r} is not a number 1-65535; {expected}")
        return text
    device = text.split(",")[0]
    if device.startswith(("/dev/", "COM", "/tmp/", "./")) or Path(device).exists():
        if not Path(device).exists() and not device.startswith("COM"):
            raise LinkError(f"--connect {url!r}: no such serial device {device}")
        return text
    raise LinkError(f"--connect {url!r}: {expected}")


def load_signing_key(path: str | os.PathLike[str]) -> bytes:
    """Read a 32-byte MAVLink 2 signing key: a file holding 32 raw bytes, 64 hex characters, or a passphrase line
    (hashed with SHA-256 as MAVProxy's ``signing setup`` does)."""
    import hashlib

    p = Path(path)
    try:
        raw = p.read_bytes()
    except OSError as exc:
        raise InputError(f"{p}: cannot read the signing key ({exc.strerror})") from exc
    if len(raw) == 32:
        return raw
    text = raw.decode("utf-8", errors="replace").strip()
    if len(text) == 64:
        try:
            return bytes.fromhex(text)
        except ValueError:
            pass
    if not text:
        raise InputError(f"{p}: the signing key file is empty (want 32 bytes, 64 hex characters or a passphrase)")
    return hashlib.sha256(text.encode()).digest()


#: UDP receive buffer asked for, bytes: a companion computer's loop that stalls (a busy CPU) should lose nothing of
#: 100-400 Hz HIGHRES_IMU for several seconds; Linux caps it at ``net.core.rmem_max`` (raise that if the log says so)
UDP_RECEIVE_BUFFER = 4 * 1024 * 1024


def _grow_receive_buffer(conn) -> None:  # noqa: ANN001
    sock = getattr(conn, "port", None)
    if not isinstance(sock, socket.socket) or sock.type != socket.SOCK_DGRAM:
        return
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, UDP_RECEIVE_BUFFER)
        got = sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF) // 2  # Linux reports twice what it books
    except OSError as exc:
        log.info("UDP receive buffer left at the default (%s)", exc)
        return
    if got < UDP_RECEIVE_BUFFER:
        log.info(
            "UDP receive buffer %d kB (asked %d kB; net.core.rmem_max caps it)", got // 1024, UDP_RECEIVE_BUFFER // 1024
        )


class MavLink:
    """A MAVLink 2 connection (any pymavlink URL: ``udpin:HOST:PORT``, ``udpout:``, ``tcp:``, ``/dev/ttyUSB0``).

    ``peer_system``/``peer_component`` (None = any) restrict which sender is accepted for data messages; messages from
    anyone else are dropped and counted in ``stats.foreign_source``. With a ``signing_key`` outgoing messages are signed
    and unsigned or wrongly signed incoming messages are dropped and counted.
    """

    def __init__(
        self,
        url: str,
        *,
        baud: int = 115200,
        source_system: int = 1,
        source_component: int = MAV_COMP_ID_ONBOARD_COMPUTER,
        peer_system: int | None = None,
        peer_component: int | None = None,
        signing_key: bytes | None = None,
        accept_unsigned: bool = False,
        record_path: str | os.PathLike[str] | None = None,
    ) -> None:
        self.url = url
        #: every frame received is appended here as a telemetry log (pymavlink's tlog record: receive time as an
        #: 8-byte big-endian count of microseconds since the Unix epoch, then the frame), for
        #: :mod:`.playback`; None: nothing recorded
        self._record = open(record_path, "ab") if record_path is not None else None  # noqa: SIM115
        self.stats = LinkStats()
        self.peer_system = peer_system
        self.peer_component = peer_component
        self._baud = baud
        self._source = (source_system, source_component)
        self._signing_key = signing_key
        self._accept_unsigned = accept_unsigned
        #: HIGHRES_IMU magnetometer unit found from the magnitude (:func:`highres_mag_to_nt`); None before the first
        self.mag_unit: str | None = None
        self._warned_unsigned = False
        self._conn = self._open()

    # -- connection --------------------------------------------------------------------------------------
    def _open(self):
        if not self.url.lower().endswith((".tlog", ".bin")):
            check_url(self.url)
        try:
            conn = mavutil.mavlink_connection(
                self.url,
                baud=self._baud,
                source_system=self._source[0],
                source_component=self._source[1],
                dialect="ardupilotmega",
                robust_parsing=True,
                autoreconnect=True,
            )
        except Exception as exc:  # pymavlink raises bare OSError/SerialException/ValueError
            raise LinkError(f"cannot open MAVLink connection {self.url!r}: {exc}") from exc
        _grow_receive_buffer(conn)
        if self._signing_key is not None:
            unsigned_ok: Callable[[object, int], bool] | None = (
                (lambda _mav, _id: True) if self._accept_unsigned else (lambda _mav, _id: False)
            )
            conn.setup_signing(self._signing_key, sign_outgoing=True, allow_unsigned_callback=unsigned_ok)
        return conn

    def reconnect(self) -> None:
        """Close and reopen the connection (after link loss on serial/TCP); the recording goes on."""
        try:
            self._conn.close()
        except Exception:  # noqa: BLE001 - closing a dead link must not raise
            pass
        self._conn = self._open()

    def close(self) -> None:
        try:
            self._conn.close()
        except Exception:  # noqa: BLE001 - closing a dead link must not raise
            pass
        rec = getattr(self, "_record", None)
        if rec is not None:
            rec.close()
            self._record = None

    # -- receiving ---------------------------------------------------------------------------------------
    def _accept_source(self, msg) -> bool:
        sysid, compid = msg.get_srcSystem(), msg.get_srcComponent()
        if self.peer_system is not None and sysid != self.peer_system:
            return False
        return self.peer_component is None or compid == self.peer_component

    def _pending(self, timeout: float = 0.0) -> bool:
        """True if the socket/serial port has bytes to read (waiting up to ``timeout`` s)."""
        fd = getattr(self._conn, "fd", None)
        if fd is None:
            return False
        try:
            return bool(select.select([fd], [], [], timeout)[0])
        except (OSError, ValueError):
            return False

    def recv(self, timeout: float = 0.0, budget_s: float = 0.05) -> Iterator[object]:
        """Yield every decoded message available now (waiting up to ``timeout`` s for data), as the dataclasses above.

        Garbage, bad CRCs, bad signatures and foreign senders are dropped and counted. At most ``budget_s`` is spent
        decoding per call, so that a flood of junk cannot starve the caller's periodic work.
        """
        if timeout > 0:
            self._pending(timeout)
        t_end = time.monotonic() + budget_s
        while True:
            rejected = self._rejected()
            try:
                batch = self._read_messages()
            except Exception as exc:  # noqa: BLE001 - a broken frame or socket error must not stop the bridge
                if self._rejected() == rejected:  # signing rejections are counted as such, not as junk
                    self.stats.bad_data += 1
                log.debug("receive error: %s", exc)
                batch = []
            self._count_signing()
            if not batch:
                if time.monotonic() < t_end and self._pending():
                    continue
                return
            for msg in batch:
                out = self._screen(msg)
                if out is not None:
                    yield out
            if time.monotonic() > t_end:
                return

    def _read_messages(self) -> list:
        """Messages from one read. On UDP every datagram is parsed on its own (the parser is reset first), so a
        truncated or junk datagram can never swallow the frames of the next one; serial and TCP are byte streams."""
        if isinstance(self._conn, mavutil.mavudp):
            data = self._conn.recv()
            if not data:
                return []
            mav = self._conn.mav
            mav.buf = bytearray()  # internal parser state of pymavlink's MAVLink class
            mav.buf_index = 0
            mav.expected_length = mavlink2.HEADER_LEN_V1 + 2
            mav.have_prefix_error = False
            msgs = []
            m = mav.parse_char(data)
            while m is not None:
                msgs.append(m)
                rejected = self._rejected()
                try:
                    m = mav.parse_char(b"")
                except Exception:  # noqa: BLE001 - the rest of a junk datagram
                    if self._rejected() == rejected:
                        self.stats.bad_data += 1
                    break
            for m in msgs:
                self._conn.post_message(m)
            if not msgs:
                self.stats.bad_data += 1  # a datagram that held no frame at all
            return msgs
        msg = self._conn.recv_msg()
        return [] if msg is None else [msg]

    def _screen(self, msg) -> object | None:
        """Decode one pymavlink message, counting and dropping junk and foreign senders."""
        kind = msg.get_type()
        if kind in ("BAD_DATA", "UNKNOWN"):
            if "signature" not in str(getattr(msg, "reason", "")).lower():  # signing drops are counted as such
                self.stats.bad_data += 1
            return None
        rec = getattr(self, "_record", None)
        if rec is not None:
            rec.write(struct.pack(">Q", int(time.time() * 1e6)) + bytes(msg.get_msgbuf()))
        self.stats.received += 1
        out = self._decode(msg, kind)
        if out is None:
            return None
        always = (Heartbeat, OutputMessage, CommandMessage, TimesyncMessage, StatusTextMessage, CommandAckMessage)
        if not isinstance(out, always) and not self._accept_source(msg):
            self.stats.foreign_source += 1
            return None
        return out

    def _rejected(self) -> int:
        return int(self._conn.mav.signing.reject_count)

    def _count_signing(self) -> None:
        """Frames dropped by signing (pymavlink's counters): every rejection, and of them the unsigned ones (a
        rejected frame with a bad signature also counts as a bad signature; an unsigned one does not)."""
        signing = self._conn.mav.signing
        self.stats.rejected_signature = int(signing.reject_count)
        self.stats.rejected_unsigned = max(0, int(signing.reject_count) - int(signing.badsig_count))
        if self.stats.rejected_unsigned and not self._warned_unsigned:
            self._warned_unsigned = True
            log.warning(
                "signing is on but the peer sends unsigned MAVLink 2 frames: they are dropped "
                "(the peer does not sign; give it the same key, README 'Signing')"
            )

    def _decode(self, msg, kind: str):  # noqa: C901 - a flat table of message kinds
        src = (msg.get_srcSystem(), msg.get_srcComponent())
        try:
            if kind == "HEARTBEAT":
                return Heartbeat(
                    *src, int(msg.type), int(msg.autopilot), int(msg.base_mode), int(msg.custom_mode),
                    int(msg.system_status),
                )  # fmt: skip
            if kind == "HIGHRES_IMU":
                fields = int(msg.fields_updated)
                mag = None
                m = np.array([msg.xmag, msg.ymag, msg.zmag], float)
                if (fields & 0b111000000 or fields == 0) and np.all(np.isfinite(m)) and np.linalg.norm(m) > 0:
                    try:
                        mag, unit = highres_mag_to_nt(m)
                    except InputError:
                        mag = None
                    else:
                        if unit != self.mag_unit:
                            log.info(
                                "HIGHRES_IMU magnetometer from %d/%d is in %s (|B| = %.5g in that unit)%s",
                                *src, unit, float(np.linalg.norm(m)),
                                "" if self.mag_unit is None else f"; was {self.mag_unit}",
                            )  # fmt: skip
                            self.mag_unit = unit
                return ImuMessage(
                    msg.time_usec * 1e-6,
                    np.array([msg.xgyro, msg.ygyro, msg.zgyro], float),
                    np.array([msg.xacc, msg.yacc, msg.zacc], float),
                    mag,
                    "HIGHRES_IMU",
                    *src,
                )
            if kind in ("SCALED_IMU", "RAW_IMU"):
                t = msg.time_boot_ms * 1e-3 if kind == "SCALED_IMU" else msg.time_usec * 1e-6
                return ImuMessage(
                    t,
                    np.array([msg.xgyro, msg.ygyro, msg.zgyro], float) * MILLIRAD_TO_RAD,
                    np.array([msg.xacc, msg.yacc, msg.zacc], float) * MILLI_G_TO_MPS2,
                    np.array([msg.xmag, msg.ymag, msg.zmag], float) * 1e-3 * NT_PER_GAUSS,
                    kind,
                    *src,
                )
            if kind == "ATTITUDE":
                return AttitudeMessage(msg.time_boot_ms * 1e-3, msg.roll, msg.pitch, msg.yaw, *src)
            if kind == "GLOBAL_POSITION_INT":
                return PositionMessage(
                    msg.time_boot_ms * 1e-3,
                    math.radians(msg.lat / DEG_E7),
                    math.radians(msg.lon / DEG_E7),
                    msg.alt * 1e-3,
                    np.array([msg.vx, msg.vy, msg.vz], float) * 1e-2,
                    *src,
                )
            if kind in ("GPS_RAW_INT", "GPS2_RAW"):
                d = msg.to_dict()
                h_ell = d.get("alt_ellipsoid", 0)
                h_acc, v_acc = d.get("h_acc", 0), d.get("v_acc", 0)
                return GnssMessage(
                    msg.time_usec * 1e-6,
                    0 if kind == "GPS_RAW_INT" else 1,
                    int(msg.fix_type),
                    math.radians(msg.lat / DEG_E7),
                    math.radians(msg.lon / DEG_E7),
                    msg.alt * 1e-3,
                    h_ell * 1e-3 if h_ell else math.nan,
                    h_acc * 1e-3 if h_acc else math.nan,
                    v_acc * 1e-3 if v_acc else math.nan,
                    msg.eph * 1e-2 if msg.eph != 0xFFFF else math.nan,
                    int(msg.satellites_visible) if msg.satellites_visible != 0xFF else -1,
                    msg.vel * 1e-2 if msg.vel != 0xFFFF else math.nan,
                    math.radians(msg.cog * 1e-2) if msg.cog != 0xFFFF else math.nan,
                    *src,
                )
            if kind == "EXTENDED_SYS_STATE":
                return LandedStateMessage(LANDED_STATE.get(int(msg.landed_state), "undefined"), *src)
            if kind == "GPS_GLOBAL_ORIGIN":
                return OriginMessage(
                    math.radians(msg.latitude / DEG_E7), math.radians(msg.longitude / DEG_E7), msg.altitude * 1e-3, *src
                )
            if kind == "STATUSTEXT":
                text = msg.text if isinstance(msg.text, str) else bytes(msg.text).decode("ascii", "replace")
                return StatusTextMessage(int(msg.severity), text.rstrip("\x00"), *src)
            if kind == "COMMAND_ACK":
                return CommandAckMessage(int(msg.command), int(msg.result), *src)
            if kind == "PARAM_VALUE":
                name = msg.param_id if isinstance(msg.param_id, str) else bytes(msg.param_id).decode("ascii", "replace")
                return ParamMessage(name.rstrip("\x00"), float(msg.param_value), *src)
            if kind == "SIM_STATE":
                lat = msg.lat_int / DEG_E7 if getattr(msg, "lat_int", 0) else msg.lat
                lon = msg.lon_int / DEG_E7 if getattr(msg, "lon_int", 0) else msg.lon
                return TruthMessage(
                    time.monotonic(), math.radians(lat), math.radians(lon), float(msg.alt),
                    np.array([msg.vn, msg.ve, msg.vd], float), float(msg.roll), float(msg.pitch), float(msg.yaw), *src,
                )  # fmt: skip
            if kind == "EKF_STATUS_REPORT":
                return EkfStatusMessage(
                    time.monotonic(), int(msg.flags), float(msg.velocity_variance), float(msg.pos_horiz_variance),
                    float(msg.pos_vert_variance), float(msg.compass_variance), float(msg.terrain_alt_variance), *src,
                )  # fmt: skip
            if kind == "SCALED_PRESSURE":
                return PressureMessage(msg.time_boot_ms * 1e-3, msg.press_abs * 100.0, msg.temperature * 1e-2, *src)
            if kind == "TIMESYNC":
                return TimesyncMessage(int(msg.tc1), int(msg.ts1), *src)
            if kind == "COMMAND_LONG":
                params = (msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6, msg.param7)
                return CommandMessage(int(msg.command), params, *src, int(msg.target_system), int(msg.target_component))
            if kind == "GPS_INPUT":
                healthy = msg.fix_type >= 3
                return OutputMessage(
                    "gps_input",
                    time.monotonic(),
                    math.radians(msg.lat / DEG_E7),
                    math.radians(msg.lon / DEG_E7),
                    msg.alt,
                    msg.horiz_accuracy,
                    healthy,
                    msg.to_dict(),
                )
            if kind == "GLOBAL_POSITION_SENSOR":
                healthy = not (msg.flags & GLOBAL_POSITION_UNHEALTHY)
                return OutputMessage(
                    "global_position_sensor",
                    time.monotonic(),
                    math.radians(msg.lat / DEG_E7),
                    math.radians(msg.lon / DEG_E7),
                    msg.alt_ellipsoid,
                    msg.eph,
                    healthy,
                    msg.to_dict(),
                )
            if kind == "ODOMETRY":
                c = msg.pose_covariance
                sigma_h = odometry_collapsed_sigma(c[0], c[6], c[11]) if math.isfinite(c[0]) else math.nan
                return OutputMessage(
                    "odometry", time.monotonic(), msg.x, msg.y, msg.z, sigma_h, msg.quality > 0, msg.to_dict()
                )
        except (AttributeError, TypeError, ValueError) as exc:
            self.stats.bad_data += 1
            log.debug("undecodable %s: %s", kind, exc)
        return None

    # -- sending -----------------------------------------------------------------------------------------
    @property
    def mav(self):
        return self._conn.mav

    def _send(self, send: Callable[[], None]) -> None:
        try:
            send()
            self.stats.sent += 1
        except OSError as exc:  # link down: the caller's health logic reconnects
            log.debug("send failed: %s", exc)

    def send_heartbeat(self, *, autopilot: bool = False, mav_type: int | None = None) -> None:
        """Our heartbeat: an onboard controller (companion computer), or an autopilot when emulating one."""
        if autopilot:
            t = mavlink2.MAV_TYPE_QUADROTOR if mav_type is None else mav_type
            ap = mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA
        else:
            t = MAV_TYPE_ONBOARD_CONTROLLER if mav_type is None else mav_type
            ap = mavlink2.MAV_AUTOPILOT_INVALID
        self._send(lambda: self.mav.heartbeat_send(t, ap, 0, 0, mavlink2.MAV_STATE_ACTIVE))

    def request_message_interval(self, name: str, rate_hz: float, target_system: int, target_component: int) -> None:
        """SET_MESSAGE_INTERVAL (MAV_CMD 511) for message ``name`` at ``rate_hz``."""
        interval_us = 1e6 / rate_hz
        self._send(
            lambda: self.mav.command_long_send(
                target_system,
                target_component,
                mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL,
                0,
                MSG_ID[name],
                interval_us,
                0,
                0,
                0,
                0,
                0,
            )
        )

    def request_message(self, name: str, target_system: int, target_component: int) -> None:
        """MAV_CMD_REQUEST_MESSAGE (512): send message ``name`` once (e.g. GPS_GLOBAL_ORIGIN)."""
        self.send_command_long(REQUEST_MESSAGE, (MSG_ID[name],), target_system, target_component)

    def send_command_long(
        self, command: int, params: Iterable[float], target_system: int, target_component: int
    ) -> None:
        """COMMAND_LONG ``command`` with up to seven parameters (missing ones 0)."""
        p = [float(x) for x in params][:7]
        p += [0.0] * (7 - len(p))
        self._send(lambda: self.mav.command_long_send(target_system, target_component, int(command), 0, *p))

    def send_command_ack(self, command: int, result: int, target_system: int, target_component: int) -> None:
        self._send(
            lambda: self.mav.command_ack_send(
                int(command), int(result), 0, 0, int(target_system), int(target_component)
            )
        )

    def send_timesync(self, tc1: int, ts1: int) -> None:
        self._send(lambda: self.mav.timesync_send(tc1, ts1))

    def send_statustext(self, severity: str, text: str) -> None:
        sev = SEVERITY[severity]
        payload = text.encode("ascii", errors="replace")[:50]
        self._send(lambda: self.mav.statustext_send(sev, payload))

    def send_set_gps_global_origin(self, target_system: int, lat: float, lon: float, h_msl: float) -> None:
        self._send(
            lambda: self.mav.set_gps_global_origin_send(
                target_system,
                int(round(math.degrees(lat) * DEG_E7)),
                int(round(math.degrees(lon) * DEG_E7)),
                int(round(h_msl * 1000.0)),
                0,
            )
        )

    def send_gps_input(
        self,
        *,
        t_unix: float,
        lat: float,
        lon: float,
        h_msl: float,
        v_n: np.ndarray,
        sigma_h: float,
        sigma_v: float,
        sigma_speed: float,
        healthy: bool,
        satellites: int = 10,
        gps_id: int = 0,
        ignore_flags: int = 0,
    ) -> None:
        """GPS_INPUT for ArduPilot ``GPSn_TYPE=14`` (``gps_id`` 0 = GPS1, 1 = GPS2). Unhealthy -> fix_type 1 (no fix),
        position zeroed: the stream keeps flowing (a pause makes ArduPilot report "Bad fix") but no untrusted position
        is sent. HDOP and VDOP are ``sigma / 3`` (a 3 m user range error; the position has no satellite geometry),
        at least 0.5; ``ignore_flags``: :data:`GPS_INPUT_IGNORE_VEL` and friends for fields the sender does not
        know."""
        week, week_ms = unix_to_gps_week(t_unix)
        fix_type = 3 if healthy else 1
        lat_e7 = int(round(math.degrees(lat) * DEG_E7)) if healthy else 0
        lon_e7 = int(round(math.degrees(lon) * DEG_E7)) if healthy else 0
        hdop = max(0.5, sigma_h / 3.0) if healthy else 99.0
        vdop = max(0.5, sigma_v / 3.0) if healthy and math.isfinite(sigma_v) else 99.0
        self._send(
            lambda: self.mav.gps_input_send(
                int(t_unix * 1e6),
                int(gps_id),
                int(ignore_flags),
                week_ms,
                week,
                fix_type,
                lat_e7,
                lon_e7,
                float(h_msl if healthy else 0.0),
                hdop,
                vdop,
                float(v_n[0]),
                float(v_n[1]),
                float(v_n[2]),
                float(sigma_speed),
                float(sigma_h),
                float(sigma_v),
                satellites if healthy else 0,
                0,
            )
        )

    def send_odometry(
        self,
        *,
        t_usec: int,
        r_ned: np.ndarray,
        q_nb: np.ndarray,
        v_b: np.ndarray,
        sigma_pos: np.ndarray,
        sigma_vel: np.ndarray,
        reset_counter: int,
        quality: int,
    ) -> None:
        """ODOMETRY with ``frame_id = MAV_FRAME_LOCAL_FRD``, ``child_frame_id = MAV_FRAME_BODY_FRD``; ``v_b`` is the
        body-frame (FRD) velocity, angular rates are sent as NaN (ArduPilot's pose + velocity path).

        ArduPilot collapses the pose covariance to one sigma as ``posErr = cbrt(c[0]^2 + c[6]^2 + c[11]^2)`` (and the
        same over c[15], c[18], c[20] for attitude), treating the entries as if they were not variances. To make that
        collapse yield the intended sigma we fill the three entries with ``sqrt(sigma^3 / 3)``, sigma being the RMS of
        the per-axis position sigmas. Upper-triangular row-major (21 entries)."""
        sigma = float(np.sqrt(np.mean(np.square(sigma_pos))))
        att_sigma = 0.05  # rad: attitude accuracy we claim (the autopilot keeps its own attitude)
        cov = [0.0] * 21
        cov[0] = cov[6] = cov[11] = odometry_covariance_entry(sigma)
        cov[15] = cov[18] = cov[20] = odometry_covariance_entry(att_sigma)
        vcov = [0.0] * 21
        vcov[0], vcov[6], vcov[11] = (float(s) ** 2 for s in sigma_vel)
        qw = [float(q_nb[3]), float(q_nb[0]), float(q_nb[1]), float(q_nb[2])]  # MAVLink: w, x, y, z
        self._send(
            lambda: self.mav.odometry_send(
                t_usec,
                MAV_FRAME_LOCAL_FRD,
                MAV_FRAME_BODY_FRD,
                float(r_ned[0]),
                float(r_ned[1]),
                float(r_ned[2]),
                qw,
                float(v_b[0]),
                float(v_b[1]),
                float(v_b[2]),
                math.nan,
                math.nan,
                math.nan,
                cov,
                vcov,
                reset_counter,
                mavlink2.MAV_ESTIMATOR_TYPE_NAIVE,
                quality,
            )
        )

    def send_global_position_sensor(
        self,
        *,
        target_system: int,
        target_component: int,
        t_usec: int,
        processing_us: int,
        source: str,
        lat: float,
        lon: float,
        h_ellipsoid: float,
        h_msl: float,
        sigma_h: float,
        sigma_v: float,
        healthy: bool,
        sensor_id: int = 1,
    ) -> None:
        """GLOBAL_POSITION_SENSOR (296) for PX4 auxiliary global position; unhealthy -> GLOBAL_POSITION_UNHEALTHY.

        ``sensor_id`` (1-255) is matched by PX4 >= 1.18 against ``EKF2_AGPn_ID``, where 0 disables a slot, so it must
        not be 0."""
        flags = 0 if healthy else GLOBAL_POSITION_UNHEALTHY
        self._send(
            lambda: self.mav.global_position_sensor_send(
                target_system,
                target_component,
                sensor_id,
                t_usec,
                processing_us,
                GLOBAL_POSITION_SOURCE[source],
                flags,
                int(round(math.degrees(lat) * DEG_E7)),
                int(round(math.degrees(lon) * DEG_E7)),
                float(h_ellipsoid),
                float(h_msl),
                float(sigma_h),
                float(sigma_v),
            )
        )

    # -- used by the autopilot emulator --------------------------------------------------------------------
    def send_highres_imu(
        self,
        t: float,
        gyro_b: np.ndarray,
        accel_b: np.ndarray,
        mag_b_nt: np.ndarray | None,
        *,
        ardupilot_mag_scale: bool = True,
    ) -> None:
        """HIGHRES_IMU as ArduPilot sends it (magnetometer in milligauss x 1000 when ``ardupilot_mag_scale``)."""
        if mag_b_nt is None:
            mag = (0.0, 0.0, 0.0)
            fields = 0b111111
        else:
            scale = (1e6 if ardupilot_mag_scale else 1.0) / NT_PER_GAUSS
            mag = tuple(float(x) * scale for x in mag_b_nt)
            fields = 0b111111111
        self._send(
            lambda: self.mav.highres_imu_send(
                int(round(t * 1e6)),
                float(accel_b[0]),
                float(accel_b[1]),
                float(accel_b[2]),
                float(gyro_b[0]),
                float(gyro_b[1]),
                float(gyro_b[2]),
                *mag,
                1013.25,
                0.0,
                0.0,
                20.0,
                fields,
                0,
            )
        )

    def send_attitude(self, t: float, roll: float, pitch: float, yaw: float) -> None:
        self._send(lambda: self.mav.attitude_send(int(t * 1e3) & 0xFFFFFFFF, roll, pitch, yaw, 0.0, 0.0, 0.0))

    def send_global_position_int(self, t: float, lat: float, lon: float, h_msl: float, v_n: np.ndarray) -> None:
        self._send(
            lambda: self.mav.global_position_int_send(
                int(t * 1e3) & 0xFFFFFFFF,
                int(round(math.degrees(lat) * DEG_E7)),
                int(round(math.degrees(lon) * DEG_E7)),
                int(round(h_msl * 1000)),
                0,
                int(round(v_n[0] * 100)),
                int(round(v_n[1] * 100)),
                int(round(v_n[2] * 100)),
                65535,
            )
        )

    def send_gps_raw_int(
        self,
        t: float,
        fix_type: int,
        lat: float,
        lon: float,
        h_msl: float,
        *,
        sigma_h: float = 1.0,
        sigma_v: float = 2.0,
        satellites: int = 12,
        speed: float = 0.0,
        course: float = 0.0,
    ) -> None:
        """GPS_RAW_INT (the autopilot's GNSS receiver): ``t`` s on the boot clock, lat/lon rad, h m MSL."""
        self._send(
            lambda: self.mav.gps_raw_int_send(
                int(round(t * 1e6)),
                int(fix_type),
                int(round(math.degrees(lat) * DEG_E7)),
                int(round(math.degrees(lon) * DEG_E7)),
                int(round(h_msl * 1000)),
                int(round(sigma_h * 100)),
                int(round(sigma_v * 100)),
                int(round(speed * 100)),
                int(round(math.degrees(course % (2 * math.pi)) * 100)) % 36000,
                int(satellites),
                int(round(h_msl * 1000)),
                int(round(sigma_h * 1000)),
                int(round(sigma_v * 1000)),
                100,
                0,
                0,
            )
        )

    def send_extended_sys_state(self, landed: str) -> None:
        code = {v: k for k, v in LANDED_STATE.items()}[landed]
        self._send(lambda: self.mav.extended_sys_state_send(0, code))

    def send_gps_global_origin(self, lat: float, lon: float, h_msl: float) -> None:
        self._send(
            lambda: self.mav.gps_global_origin_send(
                int(round(math.degrees(lat) * DEG_E7)), int(round(math.degrees(lon) * DEG_E7)), int(round(h_msl * 1e3))
            )
        )

    # -- used by a ground station (the SITL benchmark and tests) -------------------------------------------
    def param_set(self, name: str, value: float, target_system: int = 1, target_component: int = 1) -> None:
        self._send(
            lambda: self.mav.param_set_send(
                target_system, target_component, name.encode(), float(value), mavlink2.MAV_PARAM_TYPE_REAL32
            )
        )

    def param_request(self, name: str, target_system: int = 1, target_component: int = 1) -> None:
        self._send(lambda: self.mav.param_request_read_send(target_system, target_component, name.encode(), -1))

    def set_mode(self, mode: str, target_system: int = 1, target_component: int = 1) -> None:
        """MAV_CMD_DO_SET_MODE to an ArduCopter flight mode by name (GUIDED, LAND, RTL, ...)."""
        number = {v: k for k, v in mavutil.mode_mapping_acm.items()}.get(mode.upper())
        if number is None:
            raise InputError(f"unknown ArduCopter mode {mode!r}")
        self.send_command_long(
            mavlink2.MAV_CMD_DO_SET_MODE,
            (mavlink2.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, number),
            target_system,
            target_component,
        )

    @staticmethod
    def copter_mode_name(custom_mode: int) -> str:
        return mavutil.mode_mapping_acm.get(int(custom_mode), str(custom_mode))

    def arm(self, arm: bool = True, target_system: int = 1, target_component: int = 1) -> None:
        self.send_command_long(
            mavlink2.MAV_CMD_COMPONENT_ARM_DISARM, (1.0 if arm else 0.0,), target_system, target_component
        )

    def takeoff(self, altitude_m: float, target_system: int = 1, target_component: int = 1) -> None:
        """MAV_CMD_NAV_TAKEOFF to ``altitude_m`` above home (GUIDED)."""
        self.send_command_long(
            mavlink2.MAV_CMD_NAV_TAKEOFF, (0, 0, 0, 0, 0, 0, altitude_m), target_system, target_component
        )

    def goto(
        self, lat: float, lon: float, altitude_m: float, target_system: int = 1, target_component: int = 1
    ) -> None:
        """SET_POSITION_TARGET_GLOBAL_INT (GUIDED): fly to ``lat``/``lon`` rad at ``altitude_m`` above home."""
        mask = 0b110111111000  # position only
        self._send(
            lambda: self.mav.set_position_target_global_int_send(
                0, target_system, target_component, mavlink2.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, mask,
                int(round(math.degrees(lat) * DEG_E7)), int(round(math.degrees(lon) * DEG_E7)), float(altitude_m),
                0, 0, 0, 0, 0, 0, 0, 0,
            )
        )  # fmt: skip

    def send_scaled_pressure(self, t: float, pressure_pa: float, temperature_c: float = 15.0) -> None:
        """SCALED_PRESSURE: ``t`` s (sent as ``time_boot_ms``), static pressure Pa (sent as hPa), temperature degC."""
        self._send(lambda: self.mav.send(_scaled_pressure(self.mav, t, pressure_pa, temperature_c)))

    def write_raw(self, data: bytes) -> None:
        """Write raw bytes on the link (tests: junk and truncated frames)."""
        self._send(lambda: self._conn.write(data))


def _scaled_pressure(mav, t: float, pressure_pa: float, temperature_c: float):
    return mav.scaled_pressure_encode(
        int(round(t * 1e3)) & 0xFFFFFFFF, float(pressure_pa) / 100.0, 0.0, int(round(temperature_c * 100.0)), 0
    )


def iter_tlog(path: str | os.PathLike[str]) -> Iterator[object]:
    """Decoded messages of a telemetry log (.tlog) as the dataclasses above (for ``magnav-ins replay``)."""
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: no such tlog file")
    try:
        conn = mavutil.mavlink_connection(str(p), dialect="ardupilotmega", robust_parsing=True)
    except Exception as exc:  # noqa: BLE001
        raise InputError(f"{p}: cannot read as a MAVLink telemetry log: {exc}") from exc
    reader = MavLink.__new__(MavLink)
    reader.stats = LinkStats()
    reader.peer_system = None
    reader.peer_component = None
    reader.mag_unit = None
    reader._warned_unsigned = False
    reader._conn = conn
    try:
        while True:
            msg = conn.recv_match(blocking=False)
            if msg is None:
                break
            kind = msg.get_type()
            if kind in ("BAD_DATA", "UNKNOWN"):
                continue
            out = reader._decode(msg, kind)
            if out is not None:
                yield out
    finally:
        conn.close()


def write_tlog(
    path: str | os.PathLike[str],
    messages: Iterable[ImuMessage | AttitudeMessage | PositionMessage | PressureMessage],
    *,
    ardupilot_mag_scale: bool = True,
    t_unix0: float = 1.6e9,
) -> None:
    """Write SI messages as a MAVLink 2 telemetry log (tests and replays of simulated flights).

    Each message is encoded as the autopilot would send it (ImuMessage -> HIGHRES_IMU, with the magnetometer in
    ArduPilot's milligauss x 1000 when ``ardupilot_mag_scale``; AttitudeMessage -> ATTITUDE; PositionMessage ->
    GLOBAL_POSITION_INT with ``h_msl``; PressureMessage -> SCALED_PRESSURE) and stored as pymavlink's tlog record: the receive time as an 8-byte
    big-endian count of microseconds since the Unix epoch (``t_unix0 + t``), then the frame. Written atomically.
    """
    import struct

    from ..core.atomic import atomic_path

    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    out = bytearray()
    for m in messages:
        if isinstance(m, ImuMessage):
            if m.mag_b_nt is None:
                mag, fields = (0.0, 0.0, 0.0), 0b111111
            else:
                scale = (1e6 if ardupilot_mag_scale else 1.0) / NT_PER_GAUSS
                mag, fields = tuple(float(x) * scale for x in m.mag_b_nt), 0b111111111
            msg = mav.highres_imu_encode(
                int(round(m.t * 1e6)),
                *(float(x) for x in m.accel_b),
                *(float(x) for x in m.gyro_b),
                *mag,
                1013.25,
                0.0,
                0.0,
                20.0,
                fields,
                0,
            )
        elif isinstance(m, AttitudeMessage):
            msg = mav.attitude_encode(int(round(m.t * 1e3)) & 0xFFFFFFFF, m.roll, m.pitch, m.yaw, 0.0, 0.0, 0.0)
        elif isinstance(m, PositionMessage):
            msg = mav.global_position_int_encode(
                int(round(m.t * 1e3)) & 0xFFFFFFFF,
                int(round(math.degrees(m.lat) * DEG_E7)),
                int(round(math.degrees(m.lon) * DEG_E7)),
                int(round(m.h_msl * 1000)),
                0,
                *(int(round(v * 100)) for v in m.v_n),
                65535,
            )
        elif isinstance(m, PressureMessage):
            msg = _scaled_pressure(mav, m.t, m.pressure_pa, m.temperature_c)
        else:
            raise InputError(f"write_tlog: cannot encode {type(m).__name__}")
        out += struct.pack(">Q", int(round((t_unix0 + m.t) * 1e6))) + msg.pack(mav)
    with atomic_path(path) as tmp:
        Path(tmp).write_bytes(bytes(out))
