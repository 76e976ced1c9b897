"""Replay a recorded flight through the online pipeline the MAVLink bridge runs (``magnav-ins replay``).

The pipeline is the bridge's own (:func:`.online.make_online_pipeline`, shared by both, so that a replay reproduces
what the companion computer would have computed). Two parts here:

* :func:`read_log` - a recording as a :class:`LogRecording` in SI and our frames: PX4 ULog (through
  :mod:`.ulog`), MAVLink telemetry log (through :func:`.link.iter_tlog`) or a CSV. Bad input (not a log, a missing
  topic, NaN samples, time going backwards) raises :class:`~magnav_ins.core.errors.InputError` naming the file, the
  topic/message and the row.
* :func:`replay` - feed the recording sample by sample to the pipeline exactly as the bridge does (IMU samples to
  ``push_imu``; magnetometer vectors, decimated to ``reading_interval_s``, through
  :class:`.bridge.ScalarAnomalyModel` to ``push_reading``) and collect the fused trajectory, the fixes and
  innovations; when the log holds GNSS, the horizontal error against it. When the log holds static pressure
  (ULog ``vehicle_air_data`` or ``sensor_baro``, tlog SCALED_PRESSURE, CSV ``pressure_pa``) the INS height follows
  the barometric height as in the bridge (:mod:`.baro`).

Frames and units: IMU body FRD, gyro rad/s (mean rate over the interval ending at ``t``), specific force m/s^2;
magnetometer nT body; positions rad and ellipsoidal metres; times s on the log's clock. PX4 quaternions are
scalar-first (w, x, y, z) and are converted to our scalar-last here and nowhere else. GNSS heights: ULog
``alt_ellipsoid`` when present, else MSL + ``geoid_height_m`` (as the bridge).
"""

from __future__ import annotations

import logging
import math
import re
import warnings
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..core.errors import ConfigError, InputError
from ..core.frames import horizontal_error_m, q_nb_from_euler
from ..core.types import Fix, ImuBatch, Innovation, NavState, NavTrajectory
from ..core.units import NT_PER_GAUSS
from .baro import BaroHeight, hold_height
from .online import MAX_GAP_S, make_online_pipeline

__all__ = ["LogRecording", "ReplayResult", "make_online_pipeline", "read_log", "replay", "write_trajectory"]

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]

ULOG_MAGIC = b"ULog"
#: CSV recording columns (mag_* optional): t s, gyro rad/s, accel m/s^2 specific force (body FRD), mag nT (body)
CSV_IMU_COLUMNS = ("t", "gyro_x", "gyro_y", "gyro_z", "accel_x", "accel_y", "accel_z")
CSV_MAG_COLUMNS = ("mag_x", "mag_y", "mag_z")
CSV_PRESSURE_COLUMN = "pressure_pa"  #: optional static pressure column, Pa (blank rows: no sample)
#: trajectory CSV written by ``magnav-ins replay``
TRAJ_COLUMNS = (
    "t",
    "lat_deg",
    "lon_deg",
    "h_m",
    "vn",
    "ve",
    "vd",
    "roll_deg",
    "pitch_deg",
    "yaw_deg",
    "sigma_n_m",
    "sigma_e_m",
    "hpl_m",
)
_TOL = 1e-9
DEG_E7 = 1e7
MM_TO_M = 1e-3
US_TO_S = 1e-6
#: seconds of specific force averaged to level the INS when the log has no attitude (the vehicle must be still
#: or in steady flight over this span)
LEVELLING_S = 1.0
#: initial 1-sigmas with --init: roll/pitch levelled from the specific force (rad), a heading given by hand (rad)
INIT_TILT_SIGMA_RAD = 0.01
INIT_YAW_SIGMA_RAD = 0.05
#: IMU samples per call of the free-inertial replay (bounds the temporary arrays; the progress bar's step)
FAST_CHUNK = 16384


# ------------------------------------------------------------------------------------------------ recordings
@dataclass(frozen=True)
class GnssTrack:
    """GNSS positions from the log: ``t`` s, ``lat``/``lon`` rad, ``h`` m ellipsoidal, ``v_n`` (N,3) NED m/s,
    ``t_utc`` Unix seconds of the first fix (nan if unknown)."""

    t: FloatArray
    lat: FloatArray
    lon: FloatArray
    h: FloatArray
    v_n: FloatArray
    t_utc: float = math.nan


@dataclass(frozen=True)
class AttitudeTrack:
    """Autopilot attitude: ``t`` s, ``q_nb`` (N,4) scalar-last body FRD -> NED."""

    t: FloatArray
    q_nb: FloatArray


@dataclass(frozen=True)
class LogRecording:
    """A recording in SI: ``imu`` (body FRD), magnetometer ``mag_t`` (M,) s and ``mag_b_nt`` (M,3) nT body (empty
    when the log has none), optional ``gnss`` and ``attitude``; ``fmt`` "ulog" | "tlog" | "csv"; ``sources`` says
    which topic or message each part came from (for messages); ``notes`` what the reader dropped and why;
    ``baro_t`` (K,) s and ``baro_pa`` (K,) static pressure Pa (empty without a barometer; implausible samples are
    kept here and dropped and counted by the replay's :class:`.baro.BaroHeight`)."""

    path: Path
    fmt: str
    imu: ImuBatch
    mag_t: FloatArray
    mag_b_nt: FloatArray
    gnss: GnssTrack | None = None
    attitude: AttitudeTrack | None = None
    sources: dict[str, str] = field(default_factory=dict)
    notes: tuple[str, ...] = ()
    baro_t: FloatArray = field(default_factory=lambda: np.zeros(0))
    baro_pa: FloatArray = field(default_factory=lambda: np.zeros(0))


def _check_series(path: Path, what: str, t: FloatArray, values: dict[str, FloatArray], *, strict: bool) -> None:
    """Finite values and times that never go back (``strict``: strictly increasing), else :class:`InputError`
    naming the file, the topic/message and the 1-based row."""
    if len(t) == 0:
        return
    for name, v in {"t": t, **values}.items():
        bad = ~np.isfinite(np.asarray(v, float).reshape(len(t), -1)).all(axis=1)
        if bad.any():
            k = int(np.argmax(bad))
            bad_v = np.asarray(v, float)[k]
            raise InputError(f"{path}: {what} row {k + 1} (t={float(t[k])} s): non-finite {name} {bad_v.tolist()}")
    d = np.diff(t)
    bad = d <= 0 if strict else d < 0
    if bad.any():
        k = int(np.argmax(bad)) + 1
        raise InputError(
            f"{path}: {what} row {k + 1}: time goes backwards or repeats: t={float(t[k])} s after t={float(t[k - 1])} s"
        )


def _detect(path: Path) -> str:
    if not path.is_file():
        raise InputError(f"{path}: no such log file")
    with path.open("rb") as fh:
        head = fh.read(16)
    if head.startswith(ULOG_MAGIC):
        return "ulog"
    suffix = path.suffix.lower()
    if suffix == ".tlog" or (len(head) > 8 and head[8] in (0xFD, 0xFE)):
        return "tlog"
    if suffix in (".csv", ".txt") or head[:2] in (b"t,", b"# "):
        return "csv"
    raise InputError(
        f"{path}: not a recording: expected a PX4 ULog (.ulg), a MAVLink telemetry log (.tlog) or a CSV with columns "
        f"{','.join(CSV_IMU_COLUMNS)}[,{','.join(CSV_MAG_COLUMNS)}]"
    )


def read_log(path: str | Path, *, geoid_height_m: float = 0.0) -> LogRecording:
    """Read a ULog, tlog or CSV recording (format detected from the file's first bytes and its suffix)."""
    p = Path(path)
    fmt = _detect(p)
    if fmt == "ulog":
        return _read_ulog(p)
    if fmt == "tlog":
        return _read_tlog(p, geoid_height_m)
    return _read_csv(p)


def _vec(d: dict[str, FloatArray], name: str) -> FloatArray:
    return np.column_stack([d[f"{name}[{i}]"] for i in range(3)])


def _read_ulog(p: Path) -> LogRecording:
    from .ulog import read_ulog_topic

    sc = read_ulog_topic(p, "sensor_combined")
    gyro, accel = _vec(sc, "gyro_rad"), _vec(sc, "accelerometer_m_s2")
    _check_series(p, "topic 'sensor_combined'", sc["t"], {"gyro_rad": gyro, "accelerometer_m_s2": accel}, strict=True)
    imu = ImuBatch(sc["t"], gyro, accel)
    sources = {"imu": "sensor_combined"}
    mag_t, mag = np.zeros(0), np.zeros((0, 3))
    try:
        vm = read_ulog_topic(p, "vehicle_magnetometer", [f"magnetometer_ga[{i}]" for i in range(3)])
        mag_t, mag = vm["t"], _vec(vm, "magnetometer_ga") * NT_PER_GAUSS
        sources["mag"] = "vehicle_magnetometer"
    except InputError:
        if "magnetometer_ga[0]" in sc:  # old logs: the magnetometer rides in sensor_combined
            mag_t, mag = sc["t"], _vec(sc, "magnetometer_ga") * NT_PER_GAUSS
            sources["mag"] = "sensor_combined"
    if len(mag_t):
        _check_series(p, f"topic '{sources['mag']}'", mag_t, {"magnetometer_ga": mag}, strict=False)
    gnss = None
    try:
        g = read_ulog_topic(p, "vehicle_gps_position")
    except InputError:
        g = None
    if g is not None and len(g["t"]):
        ok = g["fix_type"] >= 3 if "fix_type" in g else np.ones(len(g["t"]), bool)
        if ok.any():
            h = g["alt_ellipsoid"] if "alt_ellipsoid" in g else g["alt"]
            v = np.column_stack([g.get(k, np.zeros(len(g["t"]))) for k in ("vel_n_m_s", "vel_e_m_s", "vel_d_m_s")])
            lat, lon = np.radians(g["lat"] / DEG_E7), np.radians(g["lon"] / DEG_E7)
            _check_series(p, "topic 'vehicle_gps_position'", g["t"][ok], {"lat": lat[ok], "lon": lon[ok]}, strict=False)
            utc = g["time_utc_usec"][ok] if "time_utc_usec" in g else np.zeros(1)
            t_utc = float(utc[0] * US_TO_S) if utc[0] > 0 else math.nan
            gnss = GnssTrack(g["t"][ok], lat[ok], lon[ok], h[ok] * MM_TO_M, v[ok], t_utc)
            sources["gnss"] = "vehicle_gps_position"
    attitude = None
    try:
        a = read_ulog_topic(p, "vehicle_attitude", [f"q[{i}]" for i in range(4)])
    except InputError:
        a = None
    if a is not None and len(a["t"]):
        q_wxyz = np.column_stack([a[f"q[{i}]"] for i in range(4)])
        _check_series(p, "topic 'vehicle_attitude'", a["t"], {"q": q_wxyz}, strict=False)
        q_nb = q_wxyz[:, [1, 2, 3, 0]]  # PX4 scalar-first -> ours scalar-last
        attitude = AttitudeTrack(a["t"], q_nb / np.linalg.norm(q_nb, axis=1, keepdims=True))
        sources["attitude"] = "vehicle_attitude"
    baro_t, baro_pa = _ulog_baro(p, sources)
    return LogRecording(p, "ulog", imu, mag_t, mag, gnss, attitude, sources, baro_t=baro_t, baro_pa=baro_pa)


def _ulog_baro(p: Path, sources: dict[str, str]) -> tuple[FloatArray, FloatArray]:
    """Static pressure (Pa) from ``vehicle_air_data.baro_pressure_pa``, else ``sensor_baro.pressure`` (hPa in PX4
    before v1.14, Pa after: told apart by the magnitude); empty without either."""
    from .ulog import read_ulog_topic

    for topic, name in (("vehicle_air_data", "baro_pressure_pa"), ("sensor_baro", "pressure")):
        try:
            d = read_ulog_topic(p, topic, [name])
        except InputError:
            continue
        if len(d["t"]):
            pa = d[name]
            if topic == "sensor_baro" and np.nanmedian(pa) < 2000.0:
                pa = pa * 100.0
            sources["baro"] = topic
            return d["t"], pa
    return np.zeros(0), np.zeros(0)


def _read_tlog(p: Path, geoid_height_m: float) -> LogRecording:
    from .link import AttitudeMessage, ImuMessage, PositionMessage, PressureMessage, iter_tlog

    imu_rows: list[tuple] = []
    mag_rows: list[tuple] = []
    att_rows: list[tuple] = []
    pos_rows: list[tuple] = []
    baro_rows: list[tuple[float, float]] = []
    imu_source = ""
    for m in iter_tlog(p):
        if isinstance(m, ImuMessage):
            if imu_source and m.source != imu_source:
                continue  # one IMU stream: the first kind seen (HIGHRES_IMU normally)
            imu_source = m.source
            imu_rows.append((m.t, *m.gyro_b, *m.accel_b))
            if m.mag_b_nt is not None:
                mag_rows.append((m.t, *m.mag_b_nt))
        elif isinstance(m, AttitudeMessage):
            att_rows.append((m.t, m.roll, m.pitch, m.yaw))
        elif isinstance(m, PositionMessage):
            pos_rows.append((m.t, m.lat, m.lon, m.h_msl + geoid_height_m, *m.v_n))
        elif isinstance(m, PressureMessage):
            baro_rows.append((m.t, m.pressure_pa))
    if not imu_rows:
        raise InputError(f"{p}: no IMU messages (HIGHRES_IMU, SCALED_IMU or RAW_IMU) in the telemetry log")
    im = np.asarray(imu_rows, float)
    mg = np.asarray(mag_rows, float).reshape(-1, 4)
    notes: list[str] = []
    dup = np.concatenate([[False], np.all(im[1:] == im[:-1], axis=1)])  # the same message logged twice
    if dup.any():
        im = im[~dup]
        if len(mg):
            mg = mg[np.concatenate([[True], np.any(mg[1:] != mg[:-1], axis=1)])]
        notes.append(f"{int(dup.sum())} duplicated {imu_source} messages dropped (as the bridge drops them)")
    what = f"message {imu_source}"
    _check_series(p, what, im[:, 0], {"gyro": im[:, 1:4], "accel": im[:, 4:7]}, strict=True)
    imu = ImuBatch(im[:, 0], im[:, 1:4], im[:, 4:7])
    sources = {"imu": imu_source}
    if len(mg):
        sources["mag"] = imu_source
    gnss = None
    if pos_rows:
        ps = np.asarray(pos_rows, float)
        _check_series(p, "message GLOBAL_POSITION_INT", ps[:, 0], {"position": ps[:, 1:4]}, strict=False)
        gnss = GnssTrack(ps[:, 0], ps[:, 1], ps[:, 2], ps[:, 3], ps[:, 4:7])
        sources["gnss"] = "GLOBAL_POSITION_INT"
    attitude = None
    if att_rows:
        at = np.asarray(att_rows, float)
        _check_series(p, "message ATTITUDE", at[:, 0], {"attitude": at[:, 1:4]}, strict=False)
        attitude = AttitudeTrack(at[:, 0], q_nb_from_euler(at[:, 1], at[:, 2], at[:, 3]).reshape(-1, 4))
        sources["attitude"] = "ATTITUDE"
    br = np.asarray(baro_rows, float).reshape(-1, 2)
    if len(br):
        sources["baro"] = "SCALED_PRESSURE"
    return LogRecording(
        p, "tlog", imu, mg[:, 0], mg[:, 1:4], gnss, attitude, sources, tuple(notes), baro_t=br[:, 0], baro_pa=br[:, 1]
    )


def _read_csv_numbers(p: Path) -> tuple[FloatArray, bool] | None:
    """The plain numeric CSV (no pressure column, every wanted field a number) as one float64 array of the wanted
    columns (:data:`CSV_IMU_COLUMNS` then :data:`CSV_MAG_COLUMNS` when all present) and whether the magnetometer is
    there, parsed straight into the array (``np.loadtxt``: no table object, no second copy, no pandas import: a
    1 M-row log takes 80 MB, ~2 s); None for anything else (the pandas path then reads it or names the problem)."""
    skip = 0
    header = ""
    try:
        with p.open(encoding="utf-8") as fh:
            for line in fh:
                skip += 1
                header = line.split("#", 1)[0].strip()
                if header:
                    break
    except (OSError, UnicodeDecodeError):
        return None
    cols = [c.strip() for c in header.split(",")]
    if '"' in header or len(set(cols)) != len(cols) or CSV_PRESSURE_COLUMN in cols:
        return None
    if any(c not in cols for c in CSV_IMU_COLUMNS):
        return None
    has_mag = all(c in cols for c in CSV_MAG_COLUMNS)
    wanted = list(CSV_IMU_COLUMNS) + (list(CSV_MAG_COLUMNS) if has_mag else [])
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # "input contained no data": said later as "fewer than 2 data rows"
            a = np.loadtxt(p, dtype=np.float64, delimiter=",", comments="#", skiprows=skip,
                           usecols=[cols.index(c) for c in wanted], ndmin=2, encoding="utf-8")  # fmt: skip
    except (ValueError, UnicodeDecodeError):
        return None
    return a, has_mag


def _read_csv(p: Path) -> LogRecording:
    fast = _read_csv_numbers(p)
    if fast is not None:
        a, has_mag = fast
        return _csv_recording(p, a, has_mag, None)
    import pandas as pd

    try:
        df = pd.read_csv(p, comment="#")
    except (ValueError, UnicodeDecodeError, pd.errors.ParserError) as exc:
        raise InputError(f"{p}: cannot read as CSV ({exc})") from None
    cols = [c.strip() for c in df.columns]
    df.columns = cols
    missing = [c for c in CSV_IMU_COLUMNS if c not in cols]
    if missing:
        raise InputError(
            f"{p}: missing column {missing[0]!r}; expected {','.join(CSV_IMU_COLUMNS)}[,mag_x,mag_y,mag_z]"
        )
    has_mag = all(c in cols for c in CSV_MAG_COLUMNS)
    wanted = list(CSV_IMU_COLUMNS) + (list(CSV_MAG_COLUMNS) if has_mag else [])
    try:
        a = df[wanted].to_numpy(dtype=float)
    except ValueError:
        for c in wanted:
            bad = pd.to_numeric(df[c], errors="coerce").isna() & df[c].notna()
            if bad.any():
                k = int(np.argmax(bad.to_numpy()))
                raise InputError(f"{p}: row {k + 1} column {c!r}: not a number: {df[c].iloc[k]!r}") from None
        raise
    return _csv_recording(p, a, has_mag, df)


def _csv_recording(p: Path, a: FloatArray, has_mag: bool, df: Any) -> LogRecording:
    """The recording from the wanted columns ``a`` of a CSV (:func:`_read_csv`); ``df`` the pandas table when it
    was read through pandas (its pressure column, if any, is read from it)."""
    wanted = list(CSV_IMU_COLUMNS) + (list(CSV_MAG_COLUMNS) if has_mag else [])
    if len(a) < 2:
        raise InputError(f"{p}: fewer than 2 data rows")
    for j, c in enumerate(wanted):
        bad = ~np.isfinite(a[:, j])
        if bad.any():
            k = int(np.argmax(bad))
            raise InputError(f"{p}: row {k + 1} column {c!r}: non-finite value {float(a[k, j])}")
    _check_series(p, "CSV", a[:, 0], {}, strict=True)
    imu = ImuBatch(a[:, 0], a[:, 1:4], a[:, 4:7])
    mag_t = a[:, 0] if has_mag else np.zeros(0)
    mag = a[:, 7:10] if has_mag else np.zeros((0, 3))
    sources = {"imu": "CSV", **({"mag": "CSV"} if has_mag else {})}
    baro_t, baro_pa = np.zeros(0), np.zeros(0)
    if df is not None and CSV_PRESSURE_COLUMN in df.columns:
        import pandas as pd

        pa = pd.to_numeric(df[CSV_PRESSURE_COLUMN], errors="coerce").to_numpy(dtype=float)
        bad = np.isnan(pa) & df[CSV_PRESSURE_COLUMN].notna().to_numpy()
        if bad.any():
            k = int(np.argmax(bad))
            raise InputError(
                f"{p}: row {k + 1} column {CSV_PRESSURE_COLUMN!r}: not a number: {df[CSV_PRESSURE_COLUMN].iloc[k]!r}"
            )
        keep = ~np.isnan(pa)  # blank: no pressure sample at this row
        baro_t, baro_pa = a[keep, 0], pa[keep]
        sources["baro"] = "CSV"
    return LogRecording(p, "csv", imu, mag_t, mag, None, None, sources, baro_t=baro_t, baro_pa=baro_pa)


# ------------------------------------------------------------------------------------------------ replay
@dataclass(frozen=True)
class ReplayResult:
    """What a replay produced: output ``t`` (N,) s, the estimated ``trajectory`` at those times, ``sigma_ne`` (N,2)
    m, every fix (also "no fix") and innovation, counts, and when the log has GNSS the horizontal error (N,) m
    against it at the output times inside the GNSS span (nan elsewhere); ``gaps``: the IMU gaps longer than
    ``max_gap_s`` after which the INS restarted (row, times, gap s, the grown position sigma m) and
    ``readings_dropped_in_gaps``."""

    t: FloatArray
    trajectory: NavTrajectory
    sigma_ne: FloatArray
    fixes: list[Fix]
    innovations: list[Innovation]
    imu_samples: int
    readings: int
    duration_s: float
    init_source: str
    map_covers_start: bool
    error_m: FloatArray | None = None
    baro: dict[str, Any] | None = None
    hpl_m: FloatArray | None = None  # (N,) the fuser's horizontal protection level, m (NaN: none)
    gaps: tuple[dict[str, Any], ...] = ()
    max_gap_s: float = MAX_GAP_S
    readings_dropped_in_gaps: int = 0
    notes: tuple[str, ...] = ()

    @property
    def navs(self) -> list[NavState]:
        """The estimates as :class:`NavState` objects (built on demand)."""
        return [self.trajectory.at(k) for k in range(len(self.trajectory))]

    def summary(self) -> dict[str, Any]:
        """Counts, fix statistics and (with GNSS) horizontal error figures, for the stdout summary and JSON."""
        issued = [f for f in self.fixes if f.available]
        no_fix = Counter(_reason_key(f.reason) for f in self.fixes if not f.available)
        rejected = Counter(_reason_key(i.reason) for i in self.innovations if not i.accepted and i.reason)
        out: dict[str, Any] = {
            "imu_samples": self.imu_samples,
            "duration_s": self.duration_s,
            "readings": self.readings,
            "fix_attempts": len(self.fixes),
            "fixes_issued": len(issued),
            "fixes_accepted": sum(1 for i in self.innovations if i.accepted),
            "no_fix_reasons": dict(no_fix.most_common()),
            "rejected_reasons": dict(rejected.most_common()),
            "init": self.init_source,
            "map_covers_start": self.map_covers_start,
        }
        if self.baro is not None:
            out["baro"] = dict(self.baro)
        if self.notes:
            out["notes"] = list(self.notes)
        if self.gaps:
            longest = max(self.gaps, key=lambda g: g["gap_s"])
            out["imu_gaps"] = {
                "count": len(self.gaps),
                "max_gap_s": self.max_gap_s,
                "longest": dict(longest),
                "readings_dropped": self.readings_dropped_in_gaps,
                "restarts": [dict(g) for g in self.gaps[:20]],
            }
        if self.error_m is not None and np.isfinite(self.error_m).any():
            e = self.error_m[np.isfinite(self.error_m)]
            out["gnss_error_m"] = {
                "rms": float(np.sqrt(np.mean(e**2))),
                "mean": float(np.mean(e)),
                "max": float(np.max(e)),
                "final": float(e[-1]),
                "samples": int(len(e)),
            }
        return out


def _reason_key(reason: str) -> str:
    """A reason without its numbers, so that reasons group ("ratio 1.3 < 2" and "ratio 1.7 < 2" are one)."""
    key = reason.split(":")[0].strip() if ":" in reason else reason
    key = re.sub(r"[-+]?\d+(\.\d*)?([eE][-+]?\d+)?", "#", key)
    return key or "(no reason given)"


def _nearest(t_series: FloatArray, t: float) -> int:
    k = int(np.searchsorted(t_series, t))
    if k == 0:
        return 0
    if k >= len(t_series):
        return len(t_series) - 1
    return k if abs(t_series[k] - t) < abs(t - t_series[k - 1]) else k - 1


def _level(imu: ImuBatch, k0: int) -> tuple[float, float]:
    """Roll and pitch (rad) from the mean specific force over the first :data:`LEVELLING_S` (FRD, at rest or in
    steady flight: ``f_b ~ -C_bn g``)."""
    k1 = max(int(np.searchsorted(imu.t, imu.t[k0] + LEVELLING_S)), k0 + 1)
    f = imu.accel_b[k0:k1].mean(axis=0)
    return math.atan2(-f[1], -f[2]), math.atan2(f[0], math.hypot(f[1], f[2]))


def initial_state(
    rec: LogRecording, init: tuple[float, float, float, float] | None = None
) -> tuple[NavState, int, str]:
    """The initial state, the index of the IMU sample it is at and where it came from.

    ``init`` (lat, lon rad, h m ellipsoidal, yaw rad): position and heading given; roll and pitch from the log's
    attitude if any (else levelled from the specific force); velocity from the log's GNSS if any (else at rest);
    starts at the first IMU sample (the pipeline then gets wider initial attitude sigmas,
    :data:`INIT_TILT_SIGMA_RAD` when levelled and :data:`INIT_YAW_SIGMA_RAD`). Without ``init`` the log must hold GNSS and attitude: starts at the first IMU
    sample at or after both. Missing both -> :class:`ConfigError` saying which option to add."""
    imu = rec.imu
    if init is not None:
        k0 = 0
        t0 = float(imu.t[0])
        lat, lon, h, yaw = init
        source = "--init"
        if rec.attitude is not None and rec.attitude.t[0] <= t0 + 1.0:
            from ..core.frames import euler_from_q_nb

            roll, pitch, _ = (float(x) for x in euler_from_q_nb(rec.attitude.q_nb[_nearest(rec.attitude.t, t0)]))
        else:
            roll, pitch = _level(imu, 0)
            source = "--init, levelled"
        v_n = np.zeros(3)
        if rec.gnss is not None and abs(rec.gnss.t[_nearest(rec.gnss.t, t0)] - t0) < 1.0:
            v_n = rec.gnss.v_n[_nearest(rec.gnss.t, t0)]
        return NavState(t0, lat, lon, h, v_n, q_nb_from_euler(roll, pitch, yaw)), k0, source
    if rec.fmt == "csv":
        raise ConfigError(
            f"{rec.path}: a CSV recording holds no GNSS position or attitude to start from: add --init "
            "LAT_DEG,LON_DEG,ALT_M,YAW_DEG"
        )
    missing = []
    if rec.gnss is None:
        missing.append(f"no GNSS position ({'vehicle_gps_position' if rec.fmt == 'ulog' else 'GLOBAL_POSITION_INT'})")
    if rec.attitude is None:
        missing.append(f"no attitude ({'vehicle_attitude' if rec.fmt == 'ulog' else 'ATTITUDE'})")
    if missing:
        raise ConfigError(
            f"{rec.path}: cannot initialise from the log ({' and '.join(missing)}): add --init LAT_DEG,LON_DEG,ALT_M,YAW_DEG"
        )
    assert rec.gnss is not None and rec.attitude is not None
    t_start = max(float(rec.gnss.t[0]), float(rec.attitude.t[0]), float(imu.t[0]))
    k0 = int(np.searchsorted(imu.t, t_start - _TOL))
    if k0 >= len(imu) - 1:
        raise InputError(f"{rec.path}: no IMU samples after the first GNSS fix and attitude (t={t_start:.3f} s)")
    t0 = float(imu.t[k0])
    g = rec.gnss
    lat = float(np.interp(t0, g.t, g.lat))
    lon = float(np.interp(t0, g.t, np.unwrap(g.lon)))
    h = float(np.interp(t0, g.t, g.h))
    v_n = np.array([np.interp(t0, g.t, g.v_n[:, i]) for i in range(3)])
    q = rec.attitude.q_nb[_nearest(rec.attitude.t, t0)]
    return NavState(t0, lat, lon, h, v_n, q), k0, f"log ({rec.sources['gnss']} + {rec.sources['attitude']})"


class _Outputs:
    """The recorded estimates as one growing array (rows :data:`_OUT_COLUMNS`), not an object per output."""

    def __init__(self, capacity: int) -> None:
        self.a = np.empty((max(int(capacity), 16), len(_OUT_COLUMNS)))
        self.n = 0

    def add(self, est: Any) -> None:
        if self.n == len(self.a):
            self.a = np.concatenate([self.a, np.empty_like(self.a)])
        nav = est.nav
        P = np.asarray(est.P)
        row = self.a[self.n]
        row[0:4] = nav.t, nav.lat, nav.lon, nav.h
        row[4:7] = nav.v_n
        row[7:11] = nav.q_nb
        row[11] = math.sqrt(max(P[0, 0], 0.0))
        row[12] = math.sqrt(max(P[1, 1], 0.0))
        row[13] = float(est.hpl_m)
        self.n += 1

    def add_rows(self, rows: FloatArray, hpl: Callable[[FloatArray], float]) -> None:
        """Estimates as rows of :data:`magnav_ins.aiding.fusion.free_run.ROW_COLUMNS`; ``hpl(P_ne)`` (m) of each."""
        m = len(rows)
        if self.n + m > len(self.a):
            self.a = np.concatenate([self.a, np.empty((max(m, len(self.a)), self.a.shape[1]))])
        out = self.a[self.n : self.n + m]
        out[:, 0:11] = rows[:, 0:11]
        out[:, 11] = np.sqrt(np.maximum(rows[:, 11], 0.0))
        out[:, 12] = np.sqrt(np.maximum(rows[:, 13], 0.0))
        P = np.empty((2, 2))
        for i, r in enumerate(rows):
            P[0, 0], P[0, 1], P[1, 0], P[1, 1] = r[11], r[12], r[12], r[13]
            out[i, 13] = hpl(P)
        self.n += m

    @property
    def last_t(self) -> float:
        return float(self.a[self.n - 1, 0])

    def done(self) -> FloatArray:
        return self.a[: self.n].copy()


#: columns of :class:`_Outputs`: t, lat, lon, h, v_n (3), q_nb (4), sigma_n, sigma_e, hpl
_OUT_COLUMNS = ("t", "lat", "lon", "h", "vn", "ve", "vd", "qx", "qy", "qz", "qw", "sigma_n", "sigma_e", "hpl")


def _gap_message(rec: LogRecording, k: int, t: FloatArray, max_gap_s: float) -> str:
    what = {"ulog": f"topic '{rec.sources.get('imu', '')}' ", "tlog": f"message {rec.sources.get('imu', '')} "}.get(
        rec.fmt, ""
    )
    return (
        f"{rec.path}: {what}row {k + 1}: IMU gap of {t[k] - t[k - 1]:.6g} s (t={t[k - 1]:.6f} -> {t[k]:.6f} s) is "
        f"longer than --max-gap {max_gap_s:g} s"
    )


def replay(
    rec: LogRecording,
    fmap: Any,
    *,
    init: tuple[float, float, float, float] | None = None,
    init_sigma_m: float = 30.0,
    field_model: Callable[[np.ndarray, NavState], float | None] | None = None,
    reading_interval_s: float = 0.1,
    output_dt: float = 0.2,
    duration_s: float | None = None,
    pipeline_factory: Callable[[NavState, float], Any] | None = None,
    baro: bool = True,
    max_gap_s: float = MAX_GAP_S,
    on_gap: str = "restart",
    progress: Callable[[int], None] | None = None,
    **pipeline_options: Any,
) -> ReplayResult:
    """Run the online pipeline over ``rec`` as the bridge would (module docstring).

    ``field_model`` turns a body magnetometer vector (nT) at the current estimate into a map reading (default: a
    :class:`.bridge.ScalarAnomalyModel` is the caller's to give; ``None`` means no readings); readings are taken
    at most every ``reading_interval_s`` s and evaluated at the last recorded estimate (the field model needs the
    position only for the IGRF, which changes by a few nT per km); the estimate is recorded every ``output_dt`` s
    (at the first IMU sample at or after each output time); ``duration_s`` stops the replay that many seconds after
    the start. ``pipeline_factory(nav0, sigma)`` builds the pipeline (default
    :func:`make_online_pipeline` with ``fmap`` and ``pipeline_options``). ``baro``: when the log holds pressure,
    the INS height follows the barometric height as in the bridge (:class:`.baro.BaroHeight`, referenced to the
    pressure at the start; each IMU step ends at the baro height at its time); the result's ``baro`` holds its
    counters.

    IMU gaps, as the bridge handles them: an interval up to ``max_gap_s`` (s) is integrated (bridged); after a
    longer one (``on_gap="restart"``) the INS restarts at the sample after the gap from its last estimate, with
    the position 1-sigma grown by speed x gap and the IMU biases estimated so far kept (readings inside the gap are
    dropped; the result's ``gaps`` lists each restart); ``on_gap="stop"`` refuses such a log before replaying it
    (:class:`InputError` naming the row and the times). Never integrated across.

    The samples between events (a reading, an output, a gap) go to the pipeline in one call
    (:meth:`.online.OnlinePipeline.push_imu_batch`: the same numbers as sample by sample, as the bridge feeds
    them); ``progress(n)`` is called with the number of IMU samples done since its last call."""
    if not (reading_interval_s >= 0 and output_dt > 0):
        raise ConfigError(
            f"reading interval must be >= 0 and output interval > 0 s, got {reading_interval_s}, {output_dt}"
        )
    if not (math.isfinite(max_gap_s) and max_gap_s > 0):
        raise ConfigError(f"--max-gap must be a positive number of seconds, got {max_gap_s!r}")
    if on_gap not in ("restart", "stop"):
        raise ConfigError(f"--on-gap must be 'restart' or 'stop', got {on_gap!r}")
    nav0, k0, init_source = initial_state(rec, init)
    if pipeline_factory is None:
        options = dict(pipeline_options)
        if init is not None and "attitude_sigma_rad" not in options:  # a heading typed by hand, maybe levelled
            options["attitude_sigma_rad"] = (INIT_TILT_SIGMA_RAD if "levelled" in init_source else 0.005,) * 2 + (
                INIT_YAW_SIGMA_RAD,
            )

        def pipeline_factory(nav: NavState, sigma: float) -> Any:
            return make_online_pipeline(nav, sigma, fmap, **options)

    pipe = pipeline_factory(nav0, init_sigma_m)
    imu = rec.imu
    k_end = len(imu)
    if duration_s is not None:
        if not duration_s > 0:
            raise ConfigError(f"--duration must be > 0 s, got {duration_s}")
        k_end = int(np.searchsorted(imu.t, imu.t[k0] + duration_s + _TOL, side="right"))
    t_all, gyro, accel = imu.t[:k_end], imu.gyro_b[:k_end], imu.accel_b[:k_end]
    n = len(t_all)
    gap_at = k0 + 1 + np.flatnonzero(np.diff(t_all[k0:]) > max_gap_s)
    if on_gap == "stop" and len(gap_at):
        raise InputError(
            _gap_message(rec, int(gap_at[0]), t_all, max_gap_s) + ": the replay would integrate across it "
            "(--on-gap restart restarts the INS from its last estimate instead)"
        )
    mag_t, mag = rec.mag_t, rec.mag_b_nt
    j = int(np.searchsorted(mag_t, t_all[k0], side="right"))
    last_reading = -math.inf
    n_readings = 0
    outs = _Outputs(int((t_all[-1] - t_all[k0]) / output_dt) + 4)
    fixes: list[Fix] = []
    innovations: list[Innovation] = []
    gaps: list[dict[str, Any]] = []
    dropped_in_gaps = 0

    last_nav = nav0

    def record() -> None:
        nonlocal last_nav
        est = pipe.estimate()
        outs.add(est)
        last_nav = est.nav

    def reading(k_mag: int) -> None:
        nonlocal last_reading, n_readings
        tm = float(mag_t[k_mag])
        if not takes_readings or tm - last_reading < reading_interval_s - _TOL:
            return
        value = field_model(mag[k_mag], last_nav)
        if value is not None and np.all(np.isfinite(value)):
            pipe.push_reading(tm, value)
            last_reading = tm
            n_readings += 1

    def next_reading() -> tuple[int, bool]:
        """The IMU sample at which the next magnetometer sample that may give a reading is handled (n: none), and
        whether it falls strictly inside that sample's interval (then it is queued before the sample)."""
        if not takes_readings:
            return n, False
        jc = max(j, int(np.searchsorted(mag_t, last_reading + reading_interval_s - 2 * _TOL, side="left")))
        while jc < len(mag_t) and float(mag_t[jc]) - last_reading < reading_interval_s - _TOL:
            jc += 1
        if jc >= len(mag_t):
            return n, False
        kr = int(np.searchsorted(t_all, mag_t[jc] - _TOL, side="left"))
        return kr, kr < n and float(mag_t[jc]) < float(t_all[kr]) - _TOL

    baro_t, baro_pa = rec.baro_t, rec.baro_pa
    bh: BaroHeight | None = None
    jb = 0
    baro_applied = False
    if baro and len(baro_t):
        bh = BaroHeight()
        jb = int(np.searchsorted(baro_t, t_all[k0], side="right"))
        for i in range(max(0, jb - bh.median_n), jb):  # the samples just before the start set the reference
            bh.push(float(baro_t[i]), float(baro_pa[i]))
        bh.set_reference(nav0.h, float(t_all[k0]))

    def baro_height(t: float) -> float | None:
        """Feed the barometer up to ``t`` and return its height there (None: none yet, or not used)."""
        nonlocal jb, bh
        if bh is None:
            return None
        while jb < len(baro_t) and baro_t[jb] <= t + _TOL:
            bh.push(float(baro_t[jb]), float(baro_pa[jb]))
            jb += 1
        h_baro = bh.height(t)
        if h_baro is not None and not baro_applied and not getattr(pipe.fuser, "holds_altitude", False):
            bh = None  # this pipeline holds no altitude (graph fusion, altitude_hold=False)
            log.warning("barometer in the log not used: the pipeline holds no altitude")
            return None
        return h_baro

    def restart(k: int) -> None:
        """After the gap ending at sample ``k``: a new pipeline at ``t[k]`` from the last estimate (as the bridge)."""
        nonlocal pipe, j, dropped_in_gaps
        est = pipe.estimate()
        gap = float(t_all[k] - t_all[k - 1])
        speed = float(np.hypot(est.nav.v_n[0], est.nav.v_n[1]))
        sigma = math.sqrt(max(float(np.trace(np.asarray(est.cov_ne))) / 2.0, 0.0)) + speed * gap
        bias = pipe.imu_bias if hasattr(pipe, "imu_bias") else None
        fixes.extend(pipe.fixes)
        innovations.extend(pipe.innovations)
        nav = est.nav
        pipe = pipeline_factory(NavState(float(t_all[k]), nav.lat, nav.lon, nav.h, nav.v_n, nav.q_nb), sigma)
        if bias is not None and hasattr(pipe, "set_static_bias"):
            pipe.set_static_bias(*bias)
        j_after = int(np.searchsorted(mag_t, t_all[k] - _TOL, side="left"))
        dropped_in_gaps += max(0, j_after - j)
        j = max(j, j_after)
        gaps.append({"row": k + 1, "t_before": float(t_all[k - 1]), "t_after": float(t_all[k]), "gap_s": gap,
                     "sigma_m": sigma})  # fmt: skip
        log.warning(
            "%s: INS restarted from the last estimate, position sigma now %.0f m",
            _gap_message(rec, k, t_all, max_gap_s),
            sigma,
        )

    # a pipeline without a matcher (free inertial) takes no readings: evaluating them would only cost time
    takes_readings = field_model is not None and getattr(pipe, "matcher", True) is not None
    record()
    t_next = t_all[k0] + output_dt
    ig = 0
    k = k0 + 1
    while k < n:
        if bh is None and not takes_readings and getattr(pipe, "can_push_outputs", False):
            # free inertial: the samples up to the next gap in chunks, the output samples marked, in one compiled
            # call each (OnlinePipeline.push_imu_outputs: the same numbers as the general path below)
            b = min(int(gap_at[ig]) if ig < len(gap_at) else n, k + FAST_CHUNK)
            if b > k:
                idx: list[int] = []
                kk = k
                while True:
                    e = max(kk, int(np.searchsorted(t_all, t_next - _TOL, side="left")))
                    if e >= b:
                        break
                    idx.append(e - k)
                    t_next += output_dt * max(1.0, math.floor((float(t_all[e]) - t_next) / output_dt + _TOL) + 1.0)
                    kk = e + 1
                rows = pipe.push_imu_outputs(t_all[k:b], gyro[k:b], accel[k:b], np.asarray(idx, dtype=np.int64))
                outs.add_rows(rows, pipe.fuser.monitor.hpl)
                j = max(j, int(np.searchsorted(mag_t, t_all[b - 1] - _TOL, side="left")))
                if idx and idx[-1] == b - 1 - k:  # an output sample: the magnetometer samples at its time are past
                    j = max(j, int(np.searchsorted(mag_t, t_all[b - 1] + _TOL, side="right")))
                if progress is not None:
                    progress(b - k)
                k = b
                continue
        # the next sample that needs handling: a gap, an output, a reading; the samples before it, and the sample
        # itself unless it ends a gap or a reading falls inside its interval, go to the pipeline in one call
        e_gap = int(gap_at[ig]) if ig < len(gap_at) else n
        e_read, inside = next_reading()
        e = min(e_gap, max(k, int(np.searchsorted(t_all, t_next - _TOL, side="left"))), max(k, e_read))
        alone = e >= n or e == e_gap or (e == e_read and inside)
        b = e if alone else e + 1
        if b > k:
            holds = None
            if bh is not None:
                hs = [baro_height(float(t)) for t in t_all[k:b]]
                if bh is not None and any(h is not None for h in hs):
                    cur = getattr(pipe.fuser, "altitude_hold_m", None)
                    holds = np.empty(b - k)
                    for i, h in enumerate(hs):
                        cur = h if h is not None else cur
                        holds[i] = cur
                    baro_applied = True
            pipe.push_imu_batch(t_all[k:b], gyro[k:b], accel[k:b], altitude_hold=holds)
            j = max(j, int(np.searchsorted(mag_t, t_all[b - 1] - _TOL, side="left")))
            if progress is not None:
                progress(b - k)
            if b >= n:
                break
        k = e
        t = float(t_all[k])
        if not alone:
            pass  # pushed with the run above
        elif ig < len(gap_at) and gap_at[ig] == k:
            ig += 1
            baro_height(t)  # keep the barometer fed; the new pipeline holds the estimate's height
            restart(k)
        else:
            h_baro = baro_height(t)
            if h_baro is not None and hold_height(pipe, h_baro):
                baro_applied = True
            while j < len(mag_t) and mag_t[j] < t - _TOL:  # strictly inside the sample: queued, applied at its time
                reading(j)
                j += 1
            pipe.push_imu(t, gyro[k], accel[k])
        while j < len(mag_t) and mag_t[j] <= t + _TOL:  # at the sample time (the bridge's case)
            reading(j)
            j += 1
        if t >= t_next - _TOL:
            record()
            t_next += output_dt * max(1.0, math.floor((t - t_next) / output_dt + _TOL) + 1.0)
        if progress is not None and alone:
            progress(1)
        k += 1
    if outs.last_t < t_all[-1] - _TOL:
        record()
    fixes.extend(pipe.fixes)
    innovations.extend(pipe.innovations)
    out = outs.done()
    t_out = out[:, 0]
    traj = NavTrajectory(t_out, out[:, 1], out[:, 2], out[:, 3], out[:, 4:7], out[:, 7:11])
    err = None
    if rec.gnss is not None:
        g = rec.gnss
        inside = (t_out >= g.t[0] - _TOL) & (t_out <= g.t[-1] + _TOL)
        lat_ref = np.interp(t_out, g.t, g.lat)
        lon_ref = np.interp(t_out, g.t, np.unwrap(g.lon))
        e_m = horizontal_error_m(traj.lat, traj.lon, lat_ref, lon_ref)
        err = np.where(inside, e_m, np.nan)
    covers = True
    if fmap is not None and hasattr(fmap, "covers"):
        covers = bool(np.asarray(fmap.covers(nav0.lat, nav0.lon)).reshape(-1)[0])
    return ReplayResult(
        t_out,
        traj,
        out[:, 11:13].copy(),
        fixes,
        innovations,
        n - k0 - 1,
        n_readings,
        float(t_all[-1] - t_all[k0]),
        init_source,
        covers,
        err,
        _baro_summary(rec, baro_applied, bh),
        out[:, 13].copy(),
        tuple(gaps),
        max_gap_s,
        dropped_in_gaps,
        ()
        if takes_readings or field_model is None
        else ("the pipeline has no matcher (free inertial): no readings taken",),
    )


def _baro_summary(rec: LogRecording, applied: bool, bh: BaroHeight | None) -> dict[str, Any] | None:
    if not len(rec.baro_t):
        return None
    out: dict[str, Any] = {"source": rec.sources.get("baro", ""), "used": applied}
    if bh is not None:
        out.update(bh.health.as_dict())
    return out


def write_trajectory(path: str | Path, result: ReplayResult) -> None:
    """The fused trajectory as CSV (:data:`TRAJ_COLUMNS`; degrees at this edge), written atomically."""
    from ..core.atomic import atomic_path
    from ..core.frames import euler_from_q_nb

    tr = result.trajectory
    roll, pitch, yaw = (np.degrees(np.asarray(x, float)) for x in euler_from_q_nb(tr.q_nb.reshape(-1, 4)))
    cols = [
        result.t,
        np.degrees(tr.lat),
        np.degrees(tr.lon),
        tr.h,
        *tr.v_n.reshape(-1, 3).T,
        roll,
        pitch,
        yaw,
        result.sigma_ne[:, 0],
        result.sigma_ne[:, 1],
        result.hpl_m if result.hpl_m is not None else np.full(len(result.t), np.nan),
    ]
    data = np.column_stack(cols)
    fmt = ["%.6f", "%.9f", "%.9f", "%.3f", "%.4f", "%.4f", "%.4f", "%.5f", "%.5f", "%.5f", "%.3f", "%.3f", "%.3f"]
    with atomic_path(path) as tmp:
        np.savetxt(tmp, data, fmt=fmt, delimiter=",", header=",".join(TRAJ_COLUMNS), comments="")
