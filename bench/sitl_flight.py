"""The bridge flies a real ArduPilot copter GNSS-denied: ArduCopter SITL (real firmware, real EKF3) in a magnetic world.

The flight is :func:`magnav_ins.mavlink.sitl_flight.fly_square` (its docstring says what is flown and how): the copter
arms and takes off on its own GNSS, the GNSS is denied ``--deny-after-s`` after take-off, it flies a square of
``--side-m`` in GUIDED on the bridge's position alone (``magnav-ins bridge``, the real command, on SITL serial 1),
returns and lands. Truth is SITL's SIM_STATE. One JSON line (``--json``): ``gnss_denied_s``,
``bridge_rms_horizontal_m`` / ``bridge_max_horizontal_m`` / ``bridge_nees`` (the bridge's trusted outputs vs truth
while denied, with their sigma), ``ekf_rms_horizontal_m`` / ``ekf_max_horizontal_m`` (the autopilot's
GLOBAL_POSITION_INT vs truth while denied), ``landing_from_home_m``, ``fixes_issued``, ``fixes_accepted`` (the
bridge's map fixes), ``failsafes`` (every failsafe or EKF warning text), ``landed``, the output rate the autopilot
saw, the bridge's latency, IMU gaps, plus timings.

The SITL's IMU is nearly ideal (measured at rest: gyro 4e-5 rad/s and accelerometer 0.6 mg white noise per 100 Hz
sample, 0.1 mg offsets and 0.1 % scale from ``copter.parm``'s INS calibration, no drift with ``SIM_DRIFT_SPEED=0``;
its gyros miss the Earth's rate and its world is flat, 0.2-0.3 mg of apparent acceleration error at 15 m/s): the
bench tells the bridge ``--grade tactical`` (1 deg/h, 1 mg), the grade that covers it; a MEMS autopilot on a real
airframe is the bridge's default ``autopilot`` grade. ``--grade autopilot`` flies the same square with that model.
Likewise its magnetometer (no noise; 0.5 nT about a 40 s mean in flight) and its world, made from the bridge's own
survey (off the map by about 6.5 m times the field's gradient, ``bench/sitl_map_error.py``): the bench tells the
bridge ``--reading-sigma 1`` and a matcher with a map error of 0.3 nT plus 6.5 m x |gradient| over 50 m
(``SITL_READING_SIGMA_NT``, ``sitl_matcher`` in :mod:`magnav_ins.mavlink.sitl_flight`; ``--map-sigma`` sets the
0.3 nT floor, 0 = the bridge's defaults, 5 and 10 nT uniform, for a real magnetometer on a real map). ``--keep`` keeps the work directory with
``bridge.tlog``, everything the bridge received, for :mod:`magnav_ins.mavlink.playback`.

Run by hand (about 17 minutes for the default square: asked for 15 m/s, the SITL copter flies 10 m/s; the SITL runs
in real time): ``python bench/sitl_flight.py --json [--output gps_input|odometry] [--home=LAT,LON] [--side-m 2000]
[--altitude-m 80] [--speed-mps 15] [--warmup-m 150] [--grade ...] [--reading-sigma 1] [--map-sigma 0.3] [--keep]``
"""

from __future__ import annotations

import argparse
import json
import logging
import signal
import sys

from magnav_ins.mavlink.sitl import sitl_dir
from magnav_ins.mavlink.sitl_flight import SITL_GRADE, SITL_MAP_SIGMA_NT, SITL_READING_SIGMA_NT, FlightPlan, fly_square

#: square orientations: the order of the corners (fractions of the side, north and east)
ORIENTATIONS = {
    "ne": ((1.0, 0.0), (1.0, 1.0), (0.0, 1.0), (0.0, 0.0)),  # north first, clockwise
    "en": ((0.0, 1.0), (1.0, 1.0), (1.0, 0.0), (0.0, 0.0)),  # east first, anticlockwise
    "sw": ((-1.0, 0.0), (-1.0, -1.0), (0.0, -1.0), (0.0, 0.0)),  # south first, clockwise
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", action="store_true", help="print one JSON line")
    ap.add_argument("--output", default="gps_input", choices=["gps_input", "odometry"])
    ap.add_argument("--home", default="-21.94,140.76", help="LAT,LON deg inside the Osborne map (write --home=LAT,LON)")
    ap.add_argument("--home-alt-m", type=float, default=380.0)
    ap.add_argument("--side-m", type=float, default=2000.0)
    ap.add_argument("--orientation", default="ne", choices=sorted(ORIENTATIONS), help="which way the square goes")
    ap.add_argument("--altitude-m", type=float, default=80.0)
    ap.add_argument("--speed-mps", type=float, default=15.0)
    ap.add_argument("--deny-after-s", type=float, default=60.0, help="deny the GNSS this long after take-off")
    ap.add_argument(
        "--warmup-m",
        type=float,
        default=150.0,
        help="before the square, a GNSS-aided L of this size and back (east, north, home: the filter sees the vehicle "
        "tilted both ways while it has the GNSS), the GNSS denied after it (0: none; default 150)",
    )
    ap.add_argument("--denied-s", type=float, default=None, help="(informative) the square is sized by --side-m")
    ap.add_argument("--speedup", type=float, default=1.0)
    ap.add_argument("--sim-drift", action="store_true", help="keep the SITL's simulated gyro drift")
    ap.add_argument(
        "--grade", default=SITL_GRADE, help="the IMU grade the bridge's filter assumes (default: the SITL's, measured)"
    )
    ap.add_argument(
        "--reading-sigma",
        type=float,
        default=SITL_READING_SIGMA_NT,
        help="the magnetometer reading error the bridge is told, nT (default: the SITL's, measured; 0: the bridge's)",
    )
    ap.add_argument(
        "--map-sigma",
        type=float,
        default=SITL_MAP_SIGMA_NT,
        help="the gradient-free floor of the map's error against the SITL world the bridge's matcher is told, nT "
        "(default: measured over the whole map, with the gradient term; 0: the bridge's default matcher)",
    )
    ap.add_argument("--bridge-arg", action="append", default=[], help="extra magnav-ins bridge argument (repeatable)")
    ap.add_argument("--keep", action="store_true", help="keep the work directory (logs, track)")
    ap.add_argument("-v", "--verbose", action="store_true")
    args = ap.parse_args()
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING, format="%(asctime)s %(message)s")
    # a SIGTERM (or Ctrl-C) ends the flight through fly_square's clean-up: the SITL and the bridge are stopped
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    if sitl_dir() is None:
        raise SystemExit("../shared/tools/ardupilot-sitl is not beside the project")
    lat, lon = (float(x) for x in args.home.split(","))
    plan = FlightPlan(
        home=(lat, lon), home_alt_m=args.home_alt_m, side_m=args.side_m, altitude_m=args.altitude_m,
        speed_mps=args.speed_mps, deny_after_s=args.deny_after_s, output=args.output, grade=args.grade,
        speedup=args.speedup, sim_drift=args.sim_drift, bridge_args=tuple(args.bridge_arg), keep=args.keep,
        corners=ORIENTATIONS[args.orientation], warmup_m=args.warmup_m,
        reading_sigma_nt=args.reading_sigma or None, map_sigma_nt=args.map_sigma or None,
    )  # fmt: skip
    out = {**fly_square(plan), "orientation": args.orientation}
    print(json.dumps(out) if args.json else json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
