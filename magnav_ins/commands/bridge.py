"""``magnav-ins bridge``: run the aided INS on a companion computer next to an ArduPilot or PX4 autopilot.

Stops cleanly on Ctrl-C, on SIGTERM (a service manager's stop) and after ``--duration``: the link is closed and the
summary printed (and written with ``--summary-json``), exit status 0.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import signal


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "bridge",
        help="MAVLink companion-computer bridge: autopilot IMU + magnetometer in, map-aided position out",
        description=(
            "Reads HIGHRES_IMU (or SCALED_IMU/RAW_IMU) from the autopilot, runs INS + map matching + fusion in real "
            "time, fuses the autopilot's own GNSS while it is healthy and continues on map fixes when it is lost, "
            "and sends the fused position back (GPS_INPUT, ODOMETRY or GLOBAL_POSITION_SENSOR)."
        ),
    )
    p.add_argument(
        "--connect", required=True, help="pymavlink URL: udpin:HOST:PORT, udpout:HOST:PORT, tcp:HOST:PORT, /dev/ttyUSB0"
    )
    p.add_argument("--baud", type=int, default=921600, help="serial baud rate (default 921600)")
    p.add_argument("--map", required=True, help="map: builtin:NAME or a NetCDF file (total-field anomaly, nT)")
    p.add_argument("--output", default="gps_input", choices=["gps_input", "odometry", "global_position_sensor"])
    p.add_argument(
        "--rate", type=float, default=10.0, help="output rate, Hz (default 10; ArduPilot wants GPS_INPUT above 5 Hz)"
    )
    p.add_argument("--imu-rate", type=float, default=100.0, help="HIGHRES_IMU rate to request, Hz (default 100)")
    p.add_argument(
        "--init", help="initial position and heading: LAT_DEG,LON_DEG,ALT_M,YAW_DEG (else from the autopilot's GNSS)"
    )
    p.add_argument("--init-sigma", type=float, default=30.0, help="1-sigma of the --init position, m (default 30)")
    p.add_argument(
        "--grade", default="autopilot", help="IMU grade of the autopilot's IMU for the filter (default autopilot: MEMS)"
    )
    p.add_argument(
        "--sample-type",
        default="auto",
        choices=["auto", "mean", "instantaneous", "increment"],
        help="what a HIGHRES_IMU sample is (default auto: instantaneous from ArduPilot, interval mean from PX4)",
    )
    p.add_argument(
        "--matcher",
        default=None,
        help=f"matcher: a kind (ml, mlr, ...) or a JSON table of its options (default: {DEFAULT_MATCHER_TEXT})",
    )
    p.add_argument("--fusion", default="ukf", choices=["ukf", "graph", "free_inertial"])
    p.add_argument("--calibration", help="magnetometer calibration JSON from 'magnav-ins calibrate'")
    p.add_argument("--date", default=None, help="date for IGRF, YYYY-MM-DD (default today)")
    p.add_argument("--reading-interval", type=float, default=0.5, help="seconds between magnetometer readings (0.5)")
    p.add_argument("--reading-sigma", type=float, default=5.0, help="1-sigma of a reading in the map's unit (5 nT)")
    p.add_argument(
        "--window",
        type=int,
        default=80,
        help="readings per matcher window (default 80: 40 s, 400 m at 10 m/s, four cells of a 100 m map; a 200 m "
        "section over a smooth map gave a likelihood wider than the search window)",
    )
    p.add_argument("--match-every", type=int, default=20, help="readings between match attempts (default 20)")
    p.add_argument(
        "--long-window",
        type=int,
        default=None,
        help="readings of a longer window matched when the --window one is ambiguous or its likelihood reaches the "
        "edge of the search window (default: twice --window; 0: none). On the 16 kept SITL flights' playbacks, "
        "untrusted stretches over 7 s (EKF3's 'position lost') 6 -> 4, the longest 119 -> 44 s, RMS 36.9 -> 35.3 m",
    )
    p.add_argument(
        "--max-sigma",
        type=float,
        default=100.0,
        help="do not send positions with a larger 1-sigma, m (default 100: EKF3 caps GPS accuracy there)",
    )
    p.add_argument(
        "--alert-limit",
        type=float,
        default=None,
        help="do not send positions whose protection level exceeds this, m (fusers with integrity; default "
        "5 x --max-sigma)",
    )
    p.add_argument(
        "--follow-s",
        type=float,
        default=20.0,
        help="GPS_INPUT speed accuracy at least the horizontal sigma / this, s (default 20): EKF3 then takes up a "
        "map fix's position correction in about this time instead of minutes",
    )
    p.add_argument("--gps-id", type=int, default=0, help="GPS_INPUT instance: 0 = GPS1 (default), 1 = GPS2")
    p.add_argument(
        "--no-gnss-aiding", action="store_true", help="do not fuse the autopilot's own GNSS (GPS_RAW_INT / GPS2_RAW)"
    )
    p.add_argument("--gnss-max-sigma", type=float, default=10.0, help="largest GNSS 1-sigma fused, m (default 10)")
    p.add_argument(
        "--gnss-lag",
        type=float,
        default=0.0,
        help="the autopilot's GNSS latency, s: a GPS_RAW_INT position is this much older than its time stamp, which "
        "is the time the fix reached the autopilot (the receiver's output delay, ArduPilot's GPSn_DELAY_MS; 0.07 s "
        "measured on ArduPilot SITL; default 0)",
    )
    p.add_argument(
        "--deny-gnss-after", type=float, default=None, metavar="S", help="stop trusting the GNSS S seconds after start"
    )
    p.add_argument(
        "--send-while-gnss",
        default="auto",
        choices=["auto", "yes", "no"],
        help="send positions while the autopilot's GNSS is healthy (auto: only to a secondary GPS_INPUT instance, "
        "--gps-id >= 1, or with --ekf-source-set)",
    )
    p.add_argument(
        "--ekf-source-set",
        type=int,
        default=None,
        help="when the GNSS is lost, switch ArduPilot's EKF to this source set (MAV_CMD_SET_EKF_SOURCE_SET; 1 back)",
    )
    p.add_argument("--no-align", action="store_true", help="no ground alignment: integrate from the first sample")
    p.add_argument(
        "--no-attitude-aid",
        action="store_true",
        help="do not use the autopilot's attitude (ATTITUDE: its accelerometers and compass) to aid the INS",
    )
    p.add_argument(
        "--imu-world",
        default="earth",
        choices=["earth", "flat"],
        help="earth (default): a real IMU; flat: the autopilot is a simulator whose world is flat and does not rotate "
        "(ArduPilot SITL): add the Earth's rate, transport rate and Coriolis terms to its samples",
    )
    p.add_argument("--signing-key", help="MAVLink 2 signing key file (32 bytes, 64 hex characters or a passphrase)")
    p.add_argument("--sysid", type=int, default=1, help="our system id (default 1, the vehicle's)")
    p.add_argument("--autopilot-sysid", type=int, default=1)
    p.add_argument("--autopilot-compid", type=int, default=1)
    p.add_argument("--geoid-height", type=float, default=0.0, help="geoid height above the ellipsoid at the site, m")
    p.add_argument(
        "--duration", type=float, default=None, help="stop after this many seconds (default: run until stopped)"
    )
    p.add_argument("--summary-json", default=None, metavar="FILE", help="write the stop summary as JSON")
    p.add_argument(
        "--track-csv",
        default=None,
        metavar="FILE",
        help="write every output (wall time, lat, lon, height, sigma, trusted, sent, state, aiding) as CSV",
    )
    p.add_argument(
        "--record-tlog",
        default=None,
        metavar="FILE",
        help="append every MAVLink frame received to FILE as a telemetry log (.tlog), for magnav_ins.mavlink.playback",
    )
    p.set_defaults(handler=run)


#: the bridge's matcher: maximum likelihood on demeaned sections (a constant offset between the readings and the map
#: does not move the fix), the map's error (10 nT) in the likelihood and a 20 m floor on the fix sigma (the map
#: gridded at 100 m, the INS track shape over a section), fixes wider than 150 m not issued. Chosen on the offline
#: copter square (bench/copter_square.py), not on the SITL flight it is then measured on. A search window of at least
#: two map cells each way (``window_floor_cells``): with the tight prior just after the GNSS is lost the window was
#: inside one 100 m cell and every attempt was refused as "flat map" (the SITL flights, README). ``edge_fix``: a
#: likelihood that reaches the edge of the widest window (a smooth field along the track: the SITL square's west leg)
#: gives the fix it holds across the track, with the prior's position and no information along it, not nothing.
#: (A window whose INS track spans less than a map cell, a copter hovering or landing, is not matched at all:
#: :class:`magnav_ins.pipeline.Pipeline`'s ``min_section_m``.) ``edge_fix_sigma_m`` 500: an edge fix
#: says nothing in a direction where the likelihood is wider than 500 m (under 4 % of a 100 m prior's information);
#: with the matcher's 10 km the playbacks of the kept SITL flights had such fixes 0.2-5.4 km off (sigma 0.5-1.9 km)
#: in 9 of 15 runs, and one sent the protection level to 9 km (issue 17).
DEFAULT_MATCHER = {
    "kind": "ml",
    "demean": True,
    "map_sigma": 10.0,
    "min_fix_sigma_m": 20.0,
    "max_fix_sigma_m": 150.0,
    "min_variability": 0.3,
    "window_floor_cells": 2.0,
    "edge_fix": True,
    "edge_fix_sigma_m": 500.0,
}
DEFAULT_MATCHER_TEXT = ", ".join(f"{k}={v}" for k, v in DEFAULT_MATCHER.items())


def parse_matcher(text: str | None):  # noqa: ANN201
    """``--matcher``: None -> :data:`DEFAULT_MATCHER`; a kind name; or a JSON table (``{"kind": "ml", ...}``)."""
    from ..core.errors import ConfigError

    if text is None:
        return dict(DEFAULT_MATCHER)
    t = text.strip()
    if not t.startswith("{"):
        return t
    try:
        d = json.loads(t)
    except json.JSONDecodeError as exc:
        raise ConfigError(f"--matcher {text!r}: not a JSON table ({exc.msg})") from None
    if not isinstance(d, dict) or "kind" not in d:
        raise ConfigError(f"--matcher {text!r}: expected a JSON table with a 'kind'")
    return d


def _parse_init(text: str | None) -> tuple[float, float, float, float] | None:
    from ..core.errors import ConfigError

    if text is None:
        return None
    parts = text.split(",")
    try:
        lat, lon, alt, yaw = (float(x) for x in parts)
    except ValueError:
        raise ConfigError(f"--init {text!r}: expected LAT_DEG,LON_DEG,ALT_M,YAW_DEG (four numbers)") from None
    if not all(math.isfinite(x) for x in (lat, lon, alt, yaw)):
        raise ConfigError(f"--init {text!r}: values must be finite")
    if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 360.0):
        raise ConfigError(f"--init {text!r}: latitude must be in [-90, 90] and longitude in [-180, 360] degrees")
    return math.radians(lat), math.radians(lon), alt, math.radians(yaw)


class _TrackWriter:
    """``--track-csv``: one line per output, flushed every second (the bridge may be stopped at any time; a
    track is a log, not a result, so it is written in place). ``sigma_h_m`` is the largest horizontal 1-sigma (what
    the output carries); ``cov_nn_m2``, ``cov_ne_m2``, ``cov_ee_m2`` the horizontal covariance (north/east, m^2),
    for a NEES against truth that an elongated ellipse does not understate."""

    COLUMNS = ("t_wall", "t", "lat_deg", "lon_deg", "h_m", "sigma_h_m", "cov_nn_m2", "cov_ne_m2", "cov_ee_m2", "hpl_m",
               "trusted", "sent", "state", "aiding")  # fmt: skip

    def __init__(self, path: str) -> None:
        from ..core.errors import ConfigError

        try:
            self._fh = open(path, "w", encoding="utf-8")  # noqa: SIM115 - closed by close()
        except OSError as exc:
            raise ConfigError(f"--track-csv {path}: cannot write ({exc.strerror})") from None
        self._fh.write(",".join(self.COLUMNS) + "\n")
        self._last_flush = 0.0

    def __call__(self, o: dict) -> None:
        c = o["cov_ne"]
        self._fh.write(
            f"{o['t_wall']:.3f},{o['t']:.4f},{math.degrees(o['lat']):.8f},{math.degrees(o['lon']):.8f},{o['h']:.2f},"
            f"{o['sigma_h']:.2f},{c[0, 0]:.2f},{c[0, 1]:.2f},{c[1, 1]:.2f},{o['hpl']:.2f},{int(o['trusted'])},{int(o['sent'])},{o['state']},{o['aiding']}\n"
        )
        if o["t_wall"] - self._last_flush > 1.0:
            self._fh.flush()
            self._last_flush = o["t_wall"]

    def close(self) -> None:
        self._fh.close()


def summary_line(health, stats: dict) -> str:  # noqa: ANN001
    h = health
    return (
        f"bridge stopped: {h.imu_samples} IMU samples, {h.readings} readings, {h.outputs_sent} outputs "
        f"({h.untrusted_outputs} untrusted), map fixes {h.map_fixes_issued} issued / {h.map_fixes_accepted} accepted, "
        f"GNSS fixes {h.gnss_fixes_accepted} of {h.gnss_fixes}, {h.imu_gaps} gaps, {h.reboots} reboots, "
        f"{h.link_losses} link losses, {h.statustexts_sent} STATUSTEXT, link: {stats}"
    )


def run(args: argparse.Namespace) -> int:
    import datetime as _dt

    import numpy as np

    from ..aiding.calibration import MagCalibration
    from ..core.atomic import write_text_atomic
    from ..core.errors import ConfigError
    from ..maps.builtin import load_map
    from ..mavlink.bridge import Bridge, BridgeConfig, ScalarAnomalyModel, warm_up
    from ..mavlink.link import MavLink, check_url, load_signing_key
    from ..mavlink.online import make_online_pipeline

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(message)s")
    check_url(args.connect)
    if args.window < 1 or args.match_every < 1:
        raise ConfigError(f"--window {args.window} / --match-every {args.match_every}: expected integers >= 1")
    long_window = 2 * args.window if args.long_window is None else args.long_window
    if long_window != 0 and long_window <= args.window:
        raise ConfigError(
            f"--long-window {long_window}: expected 0 (none) or more readings than --window ({args.window})"
        )
    config = BridgeConfig(
        output=args.output,
        output_rate_hz=args.rate,
        imu_rate_hz=args.imu_rate,
        autopilot_system=args.autopilot_sysid,
        autopilot_component=args.autopilot_compid,
        init=_parse_init(args.init),
        init_sigma_m=args.init_sigma,
        reading_interval_s=args.reading_interval,
        max_sigma_m=args.max_sigma,
        alert_limit_m=args.alert_limit,
        follow_s=args.follow_s,
        geoid_height_m=args.geoid_height,
        sample_type=args.sample_type,
        gps_id=args.gps_id,
        gnss_aiding=not args.no_gnss_aiding,
        gnss_max_sigma_m=args.gnss_max_sigma,
        gnss_lag_s=args.gnss_lag,
        deny_gnss_after_s=args.deny_gnss_after,
        send_while_gnss=args.send_while_gnss,
        ekf_source_set=args.ekf_source_set,
        align=not args.no_align,
        attitude_aid=not args.no_attitude_aid,
        imu_world=args.imu_world,
    )
    from ..core.atomic import check_output_file

    for option, path in (
        ("--summary-json", args.summary_json),
        ("--track-csv", args.track_csv),
        ("--record-tlog", args.record_tlog),
    ):
        if path:
            check_output_file(path, option)  # before the bridge runs, not when it stops
    fmap = load_map(args.map)
    calibration = MagCalibration.from_json(args.calibration) if args.calibration else None
    date = args.date or _dt.date.today().isoformat()
    key = load_signing_key(args.signing_key) if args.signing_key else None
    # a MEMS heading from the autopilot's compass (a few degrees) and tilt from levelling with a 10 mg bias
    attitude_sigma = (0.01, 0.01, 0.05) if args.grade == "autopilot" else (0.005, 0.005, 0.02)

    matcher = parse_matcher(args.matcher)
    from ..aiding.matchers.registry import build_matcher

    build_matcher({"kind": matcher} if isinstance(matcher, str) else matcher)  # a bad option fails now

    def factory(nav0, sigma_m):
        return make_online_pipeline(
            nav0, sigma_m, fmap, grade=args.grade, matcher=matcher, fusion=args.fusion,
            reading_sigma=args.reading_sigma, window=args.window, match_every=args.match_every,
            long_window=long_window or None,
            attitude_sigma_rad=attitude_sigma, background_matching=True,
        )  # fmt: skip

    logging.info("warming up the compiled kernels (the first run after an install compiles them)")
    spent = warm_up(factory, fmap, lambda la, lo: float(np.asarray(fmap.value(la, lo)).reshape(-1)[0]))
    logging.info("warm-up done in %.1f s", spent)
    link = MavLink(
        args.connect,
        baud=args.baud,
        source_system=args.sysid,
        peer_system=args.autopilot_sysid,
        peer_component=args.autopilot_compid,
        signing_key=key,
        record_path=args.record_tlog,
    )
    stop = {"signal": None}

    def on_signal(signum, _frame) -> None:  # noqa: ANN001
        stop["signal"] = signal.Signals(signum).name

    previous = signal.signal(signal.SIGTERM, on_signal)
    track = _TrackWriter(args.track_csv) if args.track_csv else None
    try:
        bridge = Bridge(link, config, factory, ScalarAnomalyModel(date, calibration), fmap=fmap, on_output=track)
        logging.info("bridge on %s, map %s, output %s at %.1f Hz", args.connect, args.map, args.output, args.rate)
        health = bridge.run(args.duration, should_stop=lambda: stop["signal"] is not None)
    finally:
        signal.signal(signal.SIGTERM, previous)
        link.close()
        if track is not None:
            track.close()
    if stop["signal"]:
        logging.info("stopped by %s", stop["signal"])
    stats = link.stats.as_dict()
    print(summary_line(health, stats), flush=True)
    if args.summary_json:
        lat_ms = np.array(bridge.latencies_s) * 1e3
        doc = {
            "stopped_by": stop["signal"] or "duration or Ctrl-C", **health.as_dict(), "link": stats,
            "latency_ms": {
                k: round(float(f(lat_ms)), 2) if len(lat_ms) else None
                for k, f in (("median", np.median), ("p95", lambda x: np.percentile(x, 95)), ("max", np.max))
            },
        }  # fmt: skip
        write_text_atomic(args.summary_json, json.dumps(doc, indent=2, default=float))
    return 0
