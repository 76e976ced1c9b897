"""``magnav-ins bridge``: run the aided INS on a companion computer next to an ArduPilot or PX4 autopilot."""

from __future__ import annotations

import argparse
import logging
import math


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "bridge",
        help="MAVLink companion-computer bridge: autopilot IMU + magnetometer in, map-aided position out",
        description=(
            "Reads HIGHRES_IMU (or SCALED_IMU/RAW_IMU) from the autopilot, runs INS + map matching + fusion in real "
            "time and sends the fused position back (GPS_INPUT, ODOMETRY or GLOBAL_POSITION_SENSOR)."
        ),
    )
    p.add_argument(
        "--connect", required=True, help="pymavlink URL: udpin:HOST:PORT, udpout:HOST:PORT, tcp:HOST:PORT, /dev/ttyUSB0"
    )
    p.add_argument("--baud", type=int, default=921600, help="serial baud rate (default 921600)")
    p.add_argument("--map", required=True, help="map: builtin:NAME or a NetCDF file (total-field anomaly, nT)")
    p.add_argument("--output", default="gps_input", choices=["gps_input", "odometry", "global_position_sensor"])
    p.add_argument("--rate", type=float, default=5.0, help="output rate, Hz (default 5; ArduPilot wants >= 4)")
    p.add_argument("--imu-rate", type=float, default=100.0, help="HIGHRES_IMU rate to request, Hz (default 100)")
    p.add_argument(
        "--init", help="initial position and heading: LAT_DEG,LON_DEG,ALT_M,YAW_DEG (else from the autopilot)"
    )
    p.add_argument("--init-sigma", type=float, default=30.0, help="1-sigma of the initial position, m (default 30)")
    p.add_argument(
        "--grade", default="tactical", help="IMU grade of the autopilot's IMU for the filter (default tactical)"
    )
    p.add_argument("--matcher", default="mlr", help="matcher kind (default mlr)")
    p.add_argument("--fusion", default="ukf", choices=["ukf", "graph", "free_inertial"])
    p.add_argument("--calibration", help="magnetometer calibration JSON from 'magnav-ins calibrate'")
    p.add_argument("--date", default=None, help="date for IGRF, YYYY-MM-DD (default today)")
    p.add_argument("--reading-interval", type=float, default=0.1, help="seconds between magnetometer readings used")
    p.add_argument(
        "--max-sigma",
        type=float,
        default=100.0,
        help="do not send positions with a larger 1-sigma, m (default 100: EKF3 caps GPS accuracy there)",
    )
    p.add_argument("--signing-key", help="MAVLink 2 signing key file (32 bytes, 64 hex characters or a passphrase)")
    p.add_argument("--sysid", type=int, default=1, help="our system id (default 1, the vehicle's)")
    p.add_argument("--autopilot-sysid", type=int, default=1)
    p.add_argument("--autopilot-compid", type=int, default=1)
    p.add_argument("--geoid-height", type=float, default=0.0, help="geoid height above the ellipsoid at the site, m")
    p.add_argument(
        "--duration", type=float, default=None, help="stop after this many seconds (default: run until Ctrl-C)"
    )
    p.set_defaults(handler=run)


def _parse_init(text: str | None) -> tuple[float, float, float, float] | None:
    from ..core.errors import ConfigError

    if text is None:
        return None
    parts = text.split(",")
    try:
        lat, lon, alt, yaw = (float(x) for x in parts)
    except ValueError:
        raise ConfigError(f"--init {text!r}: expected LAT_DEG,LON_DEG,ALT_M,YAW_DEG (four numbers)") from None
    if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 360.0):
        raise ConfigError(f"--init {text!r}: latitude must be in [-90, 90] and longitude in [-180, 360] degrees")
    return math.radians(lat), math.radians(lon), alt, math.radians(yaw)


def run(args: argparse.Namespace) -> int:
    import datetime as _dt

    import numpy as np

    from ..aiding.calibration import MagCalibration
    from ..maps.builtin import load_map
    from ..mavlink.bridge import Bridge, BridgeConfig, ScalarAnomalyModel, warm_up
    from ..mavlink.link import MavLink, load_signing_key
    from ..mavlink.replay import make_online_pipeline

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(message)s")
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
        geoid_height_m=args.geoid_height,
    )
    fmap = load_map(args.map)
    calibration = MagCalibration.from_json(args.calibration) if args.calibration else None
    date = args.date or _dt.date.today().isoformat()
    key = load_signing_key(args.signing_key) if args.signing_key else None

    def factory(nav0, sigma_m):
        return make_online_pipeline(nav0, sigma_m, fmap, grade=args.grade, matcher=args.matcher, fusion=args.fusion)

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
    )

    bridge = Bridge(link, config, factory, ScalarAnomalyModel(date, calibration))
    logging.info("bridge on %s, map %s, output %s at %.1f Hz", args.connect, args.map, args.output, args.rate)
    health = bridge.run(args.duration)
    link.close()
    h = health
    print(
        f"bridge stopped: {h.imu_samples} IMU samples, {h.readings} readings, {h.outputs_sent} outputs "
        f"({h.untrusted_outputs} untrusted), {h.imu_gaps} gaps, {h.reboots} reboots, {h.link_losses} link losses, "
        f"link: {link.stats.as_dict()}"
    )
    return 0
