"""``magnav-ins replay LOG --map MAP``: run the bridge's online pipeline over a recorded flight.

LOG is a PX4 ULog (``.ulg``), a MAVLink telemetry log (``.tlog``) or a CSV (``t,gyro_x,gyro_y,gyro_z,accel_x,
accel_y,accel_z[,mag_x,mag_y,mag_z]``: s, rad/s, m/s^2 specific force, nT, body FRD). The pipeline is the one the
bridge builds (:func:`magnav_ins.mavlink.replay.make_online_pipeline`), fed sample by sample as the bridge feeds it.
Writes the fused trajectory (``--out``: ``t,lat_deg,lon_deg,h_m,vn,ve,vd,roll_deg,pitch_deg,yaw_deg,sigma_n_m,
sigma_e_m,hpl_m``, the last the fuser's horizontal protection level at integrity risk 1e-3) and prints a summary: samples, duration, fixes issued/accepted, the reasons of the "no fix"es and, when
the log holds GNSS, the horizontal error against it. A log far from the map still replays (every fix attempt is a
"no fix": off the map).
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import math
import sys
import time
from pathlib import Path

from ..core.atomic import check_output_file, write_text_atomic
from ..core.errors import ConfigError

#: as :data:`magnav_ins.mavlink.online.MAX_GAP_S` (the bridge's; not imported here: the parser stays light)
MAX_GAP_S = 0.5


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "replay",
        help="run the bridge's pipeline (INS + map matching + fusion) over a ULog, tlog or CSV recording",
        description=__doc__.split("\n\n")[1],
    )
    p.add_argument("log", type=Path, metavar="LOG", help="recording: .ulg (PX4 ULog), .tlog (MAVLink) or .csv")
    p.add_argument(
        "--map", required=True, help="map: builtin:NAME, a NetCDF grid or a survey CSV (total-field anomaly, nT)"
    )
    p.add_argument("--out", type=Path, default=None, metavar="TRAJ.csv", help="write the fused trajectory here")
    p.add_argument("--summary-json", type=Path, default=None, metavar="FILE", help="also write the summary as JSON")
    p.add_argument("--grade", default="tactical", help="IMU grade assumed by the filter (default tactical)")
    p.add_argument("--init", default=None, help="LAT_DEG,LON_DEG,ALT_M,YAW_DEG (default: the log's GNSS + attitude)")
    p.add_argument("--init-sigma", type=float, default=30.0, help="1-sigma of the initial position, m (default 30)")
    p.add_argument("--calibration", default=None, help="magnetometer calibration JSON from 'magnav-ins calibrate'")
    p.add_argument(
        "--date", default=None, help="date for the IGRF, YYYY-MM-DD (default: the log's GNSS date, else today)"
    )
    p.add_argument("--matcher", default="mlr", help="matcher kind (default mlr; 'none' for no matching)")
    p.add_argument("--fusion", default="ukf", choices=["ukf", "graph", "free_inertial"], help="fuser (default ukf)")
    p.add_argument("--reading-interval", type=float, default=0.1, help="seconds between magnetometer readings (0.1)")
    p.add_argument("--reading-sigma", type=float, default=5.0, help="1-sigma of a reading in the map's unit (5 nT)")
    p.add_argument("--window", type=int, default=30, help="readings per matcher window (default 30)")
    p.add_argument("--match-every", type=int, default=10, help="readings between match attempts (default 10)")
    p.add_argument("--output-interval", type=float, default=0.2, help="trajectory output interval, s (default 0.2)")
    p.add_argument("--duration", type=float, default=None, help="replay only this many seconds from the start")
    p.add_argument("--geoid-height", type=float, default=0.0, help="geoid height above the ellipsoid, m (tlog MSL)")
    p.add_argument(
        "--max-gap",
        type=float,
        default=MAX_GAP_S,
        help=f"longest IMU interval integrated, s (default {MAX_GAP_S:g}, as the bridge); a longer gap: see --on-gap",
    )
    p.add_argument(
        "--on-gap",
        choices=["restart", "stop"],
        default="restart",
        help="after an IMU gap longer than --max-gap: restart the INS from its last estimate with the position sigma "
        "grown by speed x gap, as the bridge does (default), or stop: refuse the log",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar (shown on a terminal, on stderr)")
    p.set_defaults(handler=run)


def parse_init(text: str | None) -> tuple[float, float, float, float] | None:
    """``LAT_DEG,LON_DEG,ALT_M,YAW_DEG`` -> (lat rad, lon rad, h m, yaw rad)."""
    if text is None:
        return None
    try:
        lat, lon, alt, yaw = (float(x) for x in text.split(","))
    except ValueError:
        raise ConfigError(f"--init {text!r}: expected LAT_DEG,LON_DEG,ALT_M,YAW_DEG (four numbers)") from None
    if not all(math.isfinite(x) for x in (lat, lon, alt, yaw)):
        raise ConfigError(f"--init {text!r}: values must be finite")
    if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 360.0):
        raise ConfigError(f"--init {text!r}: latitude must be in [-90, 90] and longitude in [-180, 360] degrees")
    return math.radians(lat), math.radians(lon), alt, math.radians(yaw)


def _date(args: argparse.Namespace, rec) -> tuple[str, str]:  # noqa: ANN001
    if args.date is not None:
        try:
            _dt.date.fromisoformat(args.date)
        except ValueError:
            raise ConfigError(f"--date {args.date!r}: expected YYYY-MM-DD") from None
        return args.date, "--date"
    if rec.gnss is not None and math.isfinite(rec.gnss.t_utc):
        return _dt.datetime.fromtimestamp(rec.gnss.t_utc, _dt.UTC).date().isoformat(), "GNSS time in the log"
    return _dt.date.today().isoformat(), "today (no --date, no GNSS time in the log)"


def format_summary(s: dict, rec, map_spec: str, date: str, date_source: str) -> str:  # noqa: ANN001
    """The human-readable summary printed on stdout."""
    src = ", ".join(f"{k} {v}" for k, v in rec.sources.items())
    lines = [
        f"replay {rec.path.name} ({rec.fmt}: {src})",
        f"  {s['imu_samples']} IMU samples over {s['duration_s']:.1f} s, {s['readings']} magnetometer readings, "
        f"init from {s['init']}, IGRF date {date} ({date_source})",
        f"  fixes: {s['fix_attempts']} attempts, {s['fixes_issued']} issued, {s['fixes_accepted']} accepted",
    ]
    if "replay_cpu_s" in s:
        rate = s["imu_samples"] / max(s["replay_cpu_s"], 1e-9)
        lines.insert(2, f"  replayed in {s['replay_cpu_s']:.1f} s of CPU ({rate:,.0f} IMU samples/s)")
    if s["no_fix_reasons"]:
        lines.append("  no fix: " + "; ".join(f"{r} x{n}" for r, n in s["no_fix_reasons"].items()))
    if s["rejected_reasons"]:
        rej = {r: n for r, n in s["rejected_reasons"].items() if r != "no fix"}
        if rej:
            lines.append("  rejected by the fuser: " + "; ".join(f"{r} x{n}" for r, n in rej.items()))
    if not s["map_covers_start"]:
        lines.append(f"  note: the map {map_spec} does not cover the start position: the INS ran unaided")
    g = s.get("imu_gaps")
    if g:
        lg = g["longest"]
        lines.append(
            f"  IMU gaps: {g['count']} longer than {g['max_gap_s']:g} s, never integrated across: the INS restarted from "
            f"its last estimate after each, position sigma grown by speed x gap (the longest {lg['gap_s']:.1f} s at row "
            f"{lg['row']}, t={lg['t_before']:.3f} -> {lg['t_after']:.3f} s, sigma then {lg['sigma_m']:.0f} m; "
            f"{g['readings_dropped']} magnetometer samples inside gaps dropped)"
        )
    lines += [f"  note: {n}" for n in s.get("notes", [])]
    lines += [f"  note: {n}" for n in rec.notes]
    if rec.mag_t.size == 0:
        lines.append("  note: the log holds no magnetometer data: the INS ran unaided")
    e = s.get("gnss_error_m")
    if e:
        lines.append(
            f"  horizontal error vs the log's GNSS: rms {e['rms']:.1f} m, mean {e['mean']:.1f} m, max {e['max']:.1f} m, "
            f"final {e['final']:.1f} m ({e['samples']} samples)"
        )
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    import numpy as np
    from tqdm.auto import tqdm

    from ..aiding.calibration import MagCalibration
    from ..maps.builtin import load_map
    from ..mavlink.field_model import ScalarAnomalyModel
    from ..mavlink.replay import initial_state, read_log, replay, write_trajectory

    init = parse_init(args.init)
    for option, path in (("--out", args.out), ("--summary-json", args.summary_json)):
        if path is not None:
            check_output_file(path, option)  # before the replay, not after it
    for name in ("init_sigma", "reading_sigma", "output_interval"):
        v = getattr(args, name)
        if not (math.isfinite(v) and v > 0):
            raise ConfigError(f"--{name.replace('_', '-')} {v!r}: expected a positive number")
    if not (math.isfinite(args.reading_interval) and args.reading_interval >= 0):
        raise ConfigError(f"--reading-interval {args.reading_interval!r}: expected a number >= 0 s")
    if not (math.isfinite(args.max_gap) and args.max_gap > 0):
        raise ConfigError(f"--max-gap {args.max_gap!r}: expected a positive number of seconds")
    if args.window < 1 or args.match_every < 1:
        raise ConfigError(f"--window {args.window} / --match-every {args.match_every}: expected integers >= 1")
    rec = read_log(args.log, geoid_height_m=args.geoid_height)
    fmap = load_map(args.map)
    calibration = MagCalibration.from_json(args.calibration) if args.calibration else None
    date, date_source = _date(args, rec)
    _, k0, _ = initial_state(rec, init)
    total = len(rec.imu) - k0 - 1
    if args.duration is not None and args.duration > 0:
        total = int(np.searchsorted(rec.imu.t, rec.imu.t[k0] + args.duration + 1e-9, side="right")) - k0 - 1
    # a bar on a terminal only (tqdm's disable=None), on stderr, gone when done; --quiet: none
    bar = tqdm(total=total, desc="replay", unit="sample", unit_scale=True, mininterval=0.5, leave=False,
               disable=True if args.quiet else None, file=sys.stderr)  # fmt: skip
    cpu0 = time.process_time()
    with bar:
        res = replay(
            rec,
            fmap,
            init=init,
            init_sigma_m=args.init_sigma,
            field_model=ScalarAnomalyModel(date, calibration),
            reading_interval_s=args.reading_interval,
            output_dt=args.output_interval,
            duration_s=args.duration,
            grade=args.grade,
            matcher=args.matcher,
            fusion=args.fusion,
            reading_sigma=args.reading_sigma,
            window=args.window,
            match_every=args.match_every,
            max_gap_s=args.max_gap,
            on_gap=args.on_gap,
            progress=bar.update,
        )
    summary = res.summary()
    summary["replay_cpu_s"] = time.process_time() - cpu0
    if args.out is not None:
        write_trajectory(args.out, res)
    if args.summary_json is not None:
        write_text_atomic(args.summary_json, json.dumps({"log": str(args.log), "map": args.map, **summary}, indent=2))
    print(format_summary(summary, rec, args.map, date, date_source))
    if args.out is not None:
        print(f"  trajectory: {args.out} ({len(res.t)} rows)")
    return 0
