"""``magnav-ins calibrate READINGS.csv --method ... --lat --lon --alt --date --out CAL.json``: magnetometer
calibration against the IGRF field at the site (Shockley 2012, sec. 2.4 and 3.1; see
:mod:`magnav_ins.aiding.calibration`). READINGS.csv has columns ``t,mx,my,mz`` (s, nT, body frame FRD)."""

from __future__ import annotations

import argparse
import datetime as _dt
import math
from pathlib import Path

import numpy as np

from ..aiding.calibration import METHODS, MagCalibration, calibrate
from ..core.atomic import check_output_file
from ..core.errors import ConfigError, InputError
from ..core.units import DEG_TO_RAD

COLUMNS = ("t", "mx", "my", "mz")


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "calibrate",
        help="calibrate a 3-axis magnetometer (bias, scale, distortion) against IGRF",
        description=(
            "Fit B = A (m - b) to magnetometer readings so that |B| matches the IGRF field at the site. "
            "modified-ellipsoid / ellipse / swinging: the platform turns about the vertical only (level circles); "
            "ellipsoid: the sensor is rotated through many attitudes."
        ),
    )
    p.add_argument("readings", type=Path, help="CSV with columns t,mx,my,mz (s, nT, body frame)")
    p.add_argument("--method", default="modified-ellipsoid", choices=METHODS, help="calibration method")
    p.add_argument("--lat", type=float, required=True, help="site latitude, deg (WGS-84)")
    p.add_argument("--lon", type=float, required=True, help="site longitude, deg")
    p.add_argument("--alt", type=float, default=0.0, help="site height above the WGS-84 ellipsoid, m")
    p.add_argument("--date", required=True, help="date of the readings, YYYY-MM-DD (for IGRF)")
    p.add_argument("--out", type=Path, default=None, help="write the calibration JSON here")
    p.add_argument("--published", action="store_true", help="use the k = 0 least-squares form as printed (eq. 2.19)")
    p.set_defaults(handler=run)


def read_readings(path: Path) -> np.ndarray:
    """Read ``t,mx,my,mz`` (nT) from CSV; returns (N, 3) nT. Missing columns / unreadable files -> InputError."""
    import pandas as pd  # here: the command-line parser stays light (pandas costs 40 MB to import)

    if not path.is_file():
        raise InputError(f"{path}: no such file")
    try:
        df = pd.read_csv(path)
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: not a readable CSV ({exc})") from exc
    df.columns = [str(c).strip() for c in df.columns]
    missing = [c for c in COLUMNS if c not in df.columns]
    if missing:
        raise InputError(f"{path}: missing column '{missing[0]}'; expected columns {','.join(COLUMNS)}")
    m = df[list(COLUMNS[1:])].apply(pd.to_numeric, errors="coerce").to_numpy(float)
    return m


def run(args: argparse.Namespace) -> int:
    from ..maps.reference import igrf_ned  # the IGRF wrapper (ppigrf) lives there

    if not -90.0 <= args.lat <= 90.0:
        raise ConfigError(f"--lat {args.lat}: expected degrees in [-90, 90]")
    if not -360.0 <= args.lon <= 360.0:
        raise ConfigError(f"--lon {args.lon}: expected degrees in [-360, 360]")
    try:
        date = _dt.date.fromisoformat(args.date)
    except ValueError as exc:
        raise ConfigError(f"--date {args.date!r}: expected YYYY-MM-DD") from exc
    if args.out is not None:
        check_output_file(args.out)
    m = read_readings(args.readings)
    lat, lon = args.lat * DEG_TO_RAD, args.lon * DEG_TO_RAD
    field = np.asarray(igrf_ned(lat, lon, args.alt, date.isoformat()), float).reshape(3)
    cal: MagCalibration = calibrate(
        m,
        args.method,
        field,
        lat=lat,
        lon=lon,
        alt=args.alt,
        date=date.isoformat(),
        published=args.published,
        source=str(args.readings),
    )
    bf, af = cal.before, cal.after
    print(f"method             {cal.method}  ({cal.n_points} readings, condition {cal.condition:.3g})")
    print(
        f"IGRF at site       |B| = {cal.field_total_nt:.1f} nT, |B_h| = {cal.field_horizontal_nt:.1f} nT "
        f"({args.lat:.5f}, {args.lon:.5f}, {args.alt:.0f} m, {cal.date})"
    )
    print(f"{'':18} {'mean |B|':>10} {'std':>9} {'max-min':>9} {'rms vs IGRF':>12}  [nT]")
    for name, s in (("before", bf), ("after", af)):
        print(f"{name:18} {s.mean_nt:10.1f} {s.std_nt:9.1f} {s.span_nt:9.1f} {s.rms_error_nt:12.1f}")
    ratio = bf.std_nt / af.std_nt if af.std_nt > 0 else math.inf
    print(f"spread ratio       {ratio:.1f}x (std of |B| before / after)")
    print("A =", np.array2string(cal.A, precision=5, suppress_small=True).replace("\n", "\n    "))
    print("b =", np.array2string(cal.b, precision=1, suppress_small=True), "nT")
    if args.out is not None:
        cal.to_json(args.out)
        print(f"wrote {args.out}")
    return 0
