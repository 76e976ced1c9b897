"""``magnav-ins ins integrate IMU.csv --init INIT.json --out TRAJ.csv``: mechanise a recorded rate-type IMU.

IMU.csv: header ``t,gyro_x,gyro_y,gyro_z,accel_x,accel_y,accel_z`` (any order, no other columns): ``t`` s, gyro
rad/s (mean rate over the interval ending at ``t``), accel m/s^2 specific force, body FRD; ``--sample-type
instantaneous`` for rates sampled at ``t`` (MEMS IMUs, pyins ``sensor_type="rate"``), ``increment`` for angle (rad)
and velocity (m/s) increments over the interval (:data:`magnav_ins.ins.strapdown.SAMPLE_TYPES`). INIT.json: ``t`` (s, must
equal the first sample's time), ``lat_deg``, ``lon_deg``, ``h_m`` (ellipsoidal), ``v_n`` ([north, east, down] m/s),
``roll_deg``, ``pitch_deg``, ``yaw_deg``. TRAJ.csv: ``t,lat_deg,lon_deg,h_m,vn,ve,vd,roll_deg,pitch_deg,yaw_deg``,
one row per IMU sample (row 1 = INIT; the first IMU sample only primes the coning/sculling memory, see
:func:`magnav_ins.ins.strapdown.integrate`).

The file is read in chunks and streamed through :class:`~magnav_ins.ins.strapdown.StrapdownStepper`, so memory stays
bounded for recordings of many hours; the output goes to a temporary file renamed into place at the end, so an
error leaves no output. Every input error names the file, the data row (1-based, header = row 0) and the column.
"""

from __future__ import annotations

import argparse
import json
import math
import os
from pathlib import Path
from typing import TextIO

import numpy as np

from ..core.atomic import atomic_path, check_output_file
from ..core.errors import InputError, where
from ..core.types import SAMPLE_TYPES, ImuBatch, NavState, NavTrajectory

IMU_COLUMNS = ("t", "gyro_x", "gyro_y", "gyro_z", "accel_x", "accel_y", "accel_z")
INIT_KEYS = ("t", "lat_deg", "lon_deg", "h_m", "v_n", "roll_deg", "pitch_deg", "yaw_deg")
TRAJ_COLUMNS = ("t", "lat_deg", "lon_deg", "h_m", "vn", "ve", "vd", "roll_deg", "pitch_deg", "yaw_deg")
#: output formats: time to 1 ns, lat/lon to 1e-10 deg (~0.01 mm), height 0.1 mm, velocity 1 um/s, angles 1e-9 deg
_FMT = ("%.9f", "%.10f", "%.10f", "%.4f", "%.6f", "%.6f", "%.6f", "%.9f", "%.9f", "%.9f")
_LINE = ",".join(_FMT) + "\n"
#: a sample interval longer than this many times the median interval is a gap (unless --max-gap says otherwise)
GAP_FACTOR = 5.0
#: |INIT.t - first IMU time| allowed, s
INIT_TIME_TOLERANCE_S = 1e-6


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "integrate",
        help="mechanise a recorded IMU (CSV) from an initial state (JSON) into a trajectory (CSV)",
        description=__doc__.split("\n\n")[1],
    )
    p.add_argument("imu", type=Path, metavar="IMU.csv", help="t,gyro_x..z (rad/s),accel_x..z (m/s^2), body FRD")
    p.add_argument("--init", type=Path, required=True, metavar="INIT.json", help="initial state at the first sample")
    p.add_argument("--out", type=Path, required=True, metavar="TRAJ.csv", help="output trajectory")
    p.add_argument(
        "--max-gap",
        type=float,
        default=None,
        metavar="S",
        help=f"largest allowed sample interval, s (default: {GAP_FACTOR:g} x the median interval of the first chunk)",
    )
    p.add_argument(
        "--altitude-hold",
        type=float,
        default=None,
        metavar="M",
        help="hold the ellipsoidal height at M metres (the free vertical channel is unstable over hours)",
    )
    p.add_argument(
        "--allow-implausible",
        action="store_true",
        help="integrate rates or specific forces outside any IMU's range (refused by default: a unit mistake)",
    )
    p.add_argument(
        "--sample-type",
        default="mean",
        choices=SAMPLE_TYPES,
        help="what a sample is: mean rate over the interval ending at t (default), the instantaneous rate at t "
        "(MEMS IMUs), or the increment over the interval (rad, m/s)",
    )
    p.add_argument("--chunk-rows", type=int, default=50_000, help=argparse.SUPPRESS)
    p.set_defaults(handler=run)


def read_init(path: Path) -> NavState:
    """Read INIT.json into a :class:`NavState` (SI). Unknown, missing or non-numeric keys raise :class:`InputError`."""
    from ..core.frames import q_nb_from_euler

    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise InputError(f"{path}: cannot read the initial state ({exc.strerror})") from None
    except UnicodeDecodeError as exc:
        raise InputError(f"{path}: not a text file (byte {exc.start} is not UTF-8); expected JSON") from None
    try:
        d = json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputError(f"{path}: line {exc.lineno} column {exc.colno}: not valid JSON ({exc.msg})") from None
    if not isinstance(d, dict):
        raise InputError(f"{path}: expected a JSON object with keys {', '.join(INIT_KEYS)}")
    unknown = sorted(set(d) - set(INIT_KEYS))
    if unknown:
        raise InputError(f"{where(path, key=unknown[0])}unknown key; expected only {', '.join(INIT_KEYS)}")
    missing = [k for k in INIT_KEYS if k not in d]
    if missing:
        raise InputError(f"{where(path, key=missing[0])}missing key; expected {', '.join(INIT_KEYS)}")

    def num(key: str, value: object) -> float:
        if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
            raise InputError(f"{where(path, key=key)}expected a finite number, got {value!r}")
        return float(value)

    vals = {k: num(k, d[k]) for k in INIT_KEYS if k != "v_n"}
    v = d["v_n"]
    if not isinstance(v, list) or len(v) != 3:
        raise InputError(f"{where(path, key='v_n')}expected a list of 3 numbers [north, east, down] m/s, got {v!r}")
    v_n = np.array([num("v_n", x) for x in v])
    if not -90.0 <= vals["lat_deg"] <= 90.0:
        raise InputError(f"{where(path, key='lat_deg')}expected a latitude in [-90, 90] deg, got {vals['lat_deg']}")
    q = q_nb_from_euler(*np.deg2rad([vals["roll_deg"], vals["pitch_deg"], vals["yaw_deg"]]))
    return NavState(
        vals["t"], math.radians(vals["lat_deg"]), math.radians(vals["lon_deg"]), vals["h_m"], v_n, q
    )  # fmt: skip


def _check_header(path: Path) -> None:
    import pandas as pd

    try:
        header = pd.read_csv(path, nrows=0)
    except FileNotFoundError:
        raise InputError(f"{path}: no such IMU file") from None
    except (OSError, pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: cannot read a CSV header ({exc})") from None
    cols = [str(c).strip() for c in header.columns]
    for c in cols:
        if c not in IMU_COLUMNS:
            raise InputError(f"{where(path, row=0, key=c)}unknown column; expected {','.join(IMU_COLUMNS)}")
    for c in IMU_COLUMNS:
        if c not in cols:
            raise InputError(f"{where(path, row=0, key=c)}missing column; expected {','.join(IMU_COLUMNS)}")
    if len(set(cols)) != len(cols):
        raise InputError(f"{path} row 0: duplicated column names {cols}")


def _chunks(path: Path, chunk_rows: int):
    """Yield (first data row number, DataFrame of float columns) with every value numeric and finite."""
    import pandas as pd

    row0 = 1
    try:
        reader = pd.read_csv(path, chunksize=chunk_rows, skipinitialspace=True)
        for df in reader:
            df.columns = [str(c).strip() for c in df.columns]
            for c in IMU_COLUMNS:
                col = df[c]
                if col.dtype.kind not in "fi":
                    num = pd.to_numeric(col, errors="coerce")
                    bad = np.flatnonzero(num.isna().to_numpy() & col.notna().to_numpy())
                    if len(bad):
                        k = int(bad[0])
                        raise InputError(f"{where(path, row=row0 + k, key=c)}not a number: {col.iloc[k]!r}")
                    df[c] = num
                vals = df[c].to_numpy(dtype=float)
                bad = np.flatnonzero(~np.isfinite(vals))
                if len(bad):
                    k = int(bad[0])
                    raw = "NaN or an empty field" if np.isnan(vals[k]) else repr(float(vals[k]))
                    raise InputError(f"{where(path, row=row0 + k, key=c)}expected a finite number, got {raw}")
            yield row0, df
            row0 += len(df)
    except pd.errors.ParserError as exc:
        raise InputError(f"{path}: malformed CSV near data row {row0}+ ({exc})") from None


def _check_plausible(path: Path, row0: int, gyro: np.ndarray, accel: np.ndarray, first: bool) -> None:
    """Refuse rates and specific forces no IMU measures (:mod:`magnav_ins.core.plausibility`), naming the row and
    column; on the first chunk also a median |specific force| that says the accelerometers are in g."""
    from ..core import plausibility as pl

    override = "; --allow-implausible integrates it anyway"
    for name, data, limit, unit in (
        ("gyro", np.abs(gyro), pl.MAX_GYRO_RAD_S, "rad/s (4000 deg/s, the largest gyro full scale): rates in rad/s?"),
        ("accel", np.abs(accel), pl.MAX_ACCEL_MPS2, "m/s^2 (100 g): specific force in m/s^2?"),
    ):
        bad = np.argwhere(data > limit)
        if len(bad):
            k, axis = (int(x) for x in bad[0])
            col = f"{name}_{'xyz'[axis]}"
            raise InputError(
                f"{where(path, row=row0 + k, key=col)}{data[k, axis]:.6g} is above {limit:g} {unit}{override}"
            )
    f = np.linalg.norm(accel, axis=1)
    if first and len(f) >= 10 and np.median(f) < pl.MIN_MEDIAN_ACCEL_MPS2:
        raise InputError(
            f"{path} rows {row0}-{row0 + len(f) - 1}: median |specific force| {np.median(f):.3g} m/s^2; in g? expected "
            f"m/s^2 (about 9.8 unless in free fall){override}"
        )


def _write(fh: TextIO, traj: NavTrajectory) -> None:
    from ..core.frames import euler_from_q_nb

    roll, pitch, yaw = euler_from_q_nb(traj.q_nb)
    table = np.column_stack(
        [traj.t, np.rad2deg(traj.lat), np.rad2deg(traj.lon), traj.h, traj.v_n, np.rad2deg([roll, pitch, yaw]).T]
    )
    fh.write((_LINE * len(table)) % tuple(table.ravel().tolist()))


def integrate_file(
    imu_path: str | os.PathLike[str],
    init_path: str | os.PathLike[str],
    out_path: str | os.PathLike[str],
    *,
    max_gap: float | None = None,
    altitude_hold: float | None = None,
    chunk_rows: int = 50_000,
    allow_implausible: bool = False,
    sample_type: str = "mean",
) -> int:
    """Mechanise ``imu_path`` from ``init_path`` into ``out_path`` (see the module docstring). Returns the number of
    trajectory rows written. Raises :class:`InputError` naming the file, row and column on bad input."""
    from ..ins.strapdown import StrapdownStepper, check_sample_type, interval_means

    imu_path, init_path, out_path = Path(imu_path), Path(init_path), Path(out_path)
    check_output_file(out_path)
    if max_gap is not None and not (math.isfinite(max_gap) and max_gap > 0):
        raise InputError(f"--max-gap: expected a positive number of seconds, got {max_gap}")
    if altitude_hold is not None and not (math.isfinite(altitude_hold) and -11000.0 <= altitude_hold <= 1e5):
        raise InputError(f"--altitude-hold: expected an ellipsoidal height in [-11000, 100000] m, got {altitude_hold}")
    check_sample_type(sample_type)
    init = read_init(init_path)
    _check_header(imu_path)
    previous: tuple[float, np.ndarray, np.ndarray] | None = None  # the last raw sample of the previous chunk
    stepper: StrapdownStepper | None = None
    gap_limit = max_gap
    gap_rule = "--max-gap"
    t_last = math.nan
    rows = 0
    with atomic_path(out_path) as tmp, tmp.open("w", encoding="utf-8", newline="\n") as fh:
        fh.write(",".join(TRAJ_COLUMNS) + "\n")
        for row0, df in _chunks(imu_path, max(2, int(chunk_rows))):
            t = df["t"].to_numpy(dtype=float)
            gyro = df[["gyro_x", "gyro_y", "gyro_z"]].to_numpy(dtype=float)
            accel = df[["accel_x", "accel_y", "accel_z"]].to_numpy(dtype=float)
            t_all = t if stepper is None else np.concatenate(([t_last], t))
            dt = np.diff(t_all)
            bad = np.flatnonzero(~(dt > 0.0))
            if len(bad):
                k = int(bad[0]) + (1 if stepper is None else 0)
                prev = float(t_all[int(bad[0])])
                raise InputError(
                    f"{where(imu_path, row=row0 + k, key='t')}time must increase strictly, "
                    f"got {float(t[k])!r} after {prev!r}"
                )
            if gap_limit is None and len(dt):
                gap_limit = GAP_FACTOR * float(np.median(dt))
                gap_rule = f"{GAP_FACTOR:g} x the median interval; allow longer gaps with --max-gap S"
            if gap_limit is not None:
                bad = np.flatnonzero(dt > gap_limit)
                if len(bad):
                    k = int(bad[0]) + (1 if stepper is None else 0)
                    raise InputError(
                        f"{where(imu_path, row=row0 + k, key='t')}gap of {dt[int(bad[0])]:.6g} s before this sample "
                        f"exceeds {gap_limit:.6g} s ({gap_rule})"
                    )
            raw_last = (float(t[-1]), gyro[-1].copy(), accel[-1].copy())
            gyro, accel = interval_means(t, gyro, accel, sample_type, previous=previous)
            if not allow_implausible:  # on the rates (rad/s, m/s^2) whatever --sample-type
                _check_plausible(imu_path, row0, gyro, accel, stepper is None)
            previous = raw_last
            if stepper is None:
                if abs(t[0] - init.t) > INIT_TIME_TOLERANCE_S:
                    raise InputError(
                        f"{where(init_path, key='t')}initial time {init.t!r} s does not match the first IMU sample "
                        f"t={float(t[0])!r} s ({imu_path} row 1)"
                    )
                if len(t) < 2:
                    raise InputError(f"{imu_path}: need at least 2 IMU samples")
                stepper = StrapdownStepper(
                    NavState(float(t[0]), init.lat, init.lon, init.h, init.v_n, init.q_nb), altitude_hold=altitude_hold
                )
                d0 = t[1] - t[0]
                stepper.prime(gyro[0] * d0, accel[0] * d0)
                nav0 = stepper.nav
                _write(fh, NavTrajectory([nav0.t], [nav0.lat], [nav0.lon], [nav0.h], [nav0.v_n], [nav0.q_nb]))
                rows += 1
                t, gyro, accel = t[1:], gyro[1:], accel[1:]
            if len(t):
                traj = stepper.advance(ImuBatch(t, gyro, accel))
                _write(fh, traj)
                rows += len(t)
            t_last = float(t_all[-1])
        if stepper is None:
            raise InputError(f"{imu_path}: no IMU samples after the header")
    return rows


def run(args: argparse.Namespace) -> int:
    rows = integrate_file(
        args.imu,
        args.init,
        args.out,
        max_gap=args.max_gap,
        altitude_hold=args.altitude_hold,
        chunk_rows=args.chunk_rows,
        allow_implausible=args.allow_implausible,
        sample_type=args.sample_type,
    )
    print(f"wrote {rows} states to {args.out}")
    return 0
