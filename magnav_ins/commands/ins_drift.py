"""``magnav-ins ins drift --grade GRADE [--duration S] [--runs N] [--seed S] [--out DIR]``: free-inertial error
growth of an IMU grade (Monte Carlo beside the error model's 1-sigma; the analogue of Storms 2009 Fig. 2.1).

Scenario: a stationary, level INS (default 40 N, 84 W, 200 m; heading north), or with ``--speed V`` straight and
level flight due north at V m/s; free vertical channel unless ``--altitude-hold``. Each run draws initial errors (default 1-sigma: 1 m position per axis, 0.01 m/s velocity per
axis, tilt 0.05 mrad about north and east and 0.5 mrad in heading) and the grade's IMU errors, and integrates the
corrupted samples with the compiled batch mechanisation. Writes DIR/drift.json and DIR/drift.png (atomically) and
prints a short table.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

from ..core.atomic import atomic_path, check_output_dir, write_text_atomic
from ..core.errors import ConfigError
from ..core.units import DEG_TO_RAD

#: largest runs x samples per run (the Monte Carlo holds (R, N, 3) arrays; ~170 bytes per sample at peak)
MAX_SAMPLES = 2e7

DEFAULTS = {"duration": 1800.0, "runs": 20, "seed": 1, "rate_hz": 20.0, "output_dt": 10.0}


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "drift",
        help="Monte Carlo free-inertial drift of an IMU grade vs the error model's 1-sigma",
        description=__doc__.split("\n\n")[1],
    )
    p.add_argument("--grade", required=True, help="consumer | commercial | tactical | navigation | precision | quantum")
    p.add_argument("--duration", default=str(DEFAULTS["duration"]), metavar="S", help="seconds (default 1800)")
    p.add_argument("--runs", default=str(DEFAULTS["runs"]), metavar="N", help="Monte Carlo runs (default 20)")
    p.add_argument("--seed", default=str(DEFAULTS["seed"]), metavar="S", help="random seed (default 1)")
    p.add_argument("--out", default="drift", type=Path, metavar="DIR", help="output directory (default ./drift)")
    p.add_argument("--rate-hz", default=str(DEFAULTS["rate_hz"]), metavar="HZ", help="IMU rate (default 20 Hz)")
    p.add_argument("--output-dt", default=str(DEFAULTS["output_dt"]), metavar="S", help="time step of the curves")
    p.add_argument("--lat-deg", default="40.0", metavar="DEG")
    p.add_argument("--lon-deg", default="-84.0", metavar="DEG")
    p.add_argument("--h-m", default="200.0", metavar="M")
    p.add_argument("--position-sigma", default="1.0", metavar="M", help="initial position 1-sigma per axis, m")
    p.add_argument("--velocity-sigma", default="0.01", metavar="MPS", help="initial velocity 1-sigma per axis, m/s")
    p.add_argument(
        "--tilt-sigma-deg",
        nargs=3,
        default=["0.002865", "0.002865", "0.02865"],
        metavar=("N", "E", "D"),
        help="initial tilt 1-sigmas about north, east, down, deg (default 0.05, 0.05, 0.5 mrad)",
    )
    p.add_argument(
        "--speed", default="0", metavar="MPS", help="0: stationary (default); > 0: straight and level due north"
    )
    p.add_argument("--altitude-hold", action="store_true", help="hold the height (perfect height aid)")
    p.add_argument("--quiet", action="store_true", help="print nothing")
    p.set_defaults(handler=run)


def _num(name: str, text: object, *, lo: float | None = None, lo_open: bool = True, hi: float | None = None) -> float:
    try:
        v = float(str(text))
    except ValueError:
        raise ConfigError(f"--{name}: expected a number, got {text!r}") from None
    if not math.isfinite(v):
        raise ConfigError(f"--{name}: expected a finite number, got {text!r}")
    if lo is not None and (v <= lo if lo_open else v < lo):
        raise ConfigError(f"--{name}: must be {'>' if lo_open else '>='} {lo:g}, got {text!r}")
    if hi is not None and v > hi:
        raise ConfigError(f"--{name}: must be <= {hi:g}, got {text!r}")
    return v


def _int(name: str, text: object, lo: int) -> int:
    try:
        v = int(str(text))
    except ValueError:
        raise ConfigError(f"--{name}: expected an integer, got {text!r}") from None
    if v < lo:
        raise ConfigError(f"--{name}: must be >= {lo}, got {text!r}")
    return v


def run(args: argparse.Namespace) -> int:
    from ..ins.drift import DriftConfig, run_drift
    from ..ins.imu_models import get_grade

    grade = get_grade(args.grade)
    cfg = DriftConfig(
        duration_s=_num("duration", args.duration, lo=0.0),
        runs=_int("runs", args.runs, 2),
        seed=_int("seed", args.seed, 0),
        rate_hz=_num("rate-hz", args.rate_hz, lo=0.0, hi=2000.0),
        output_dt_s=_num("output-dt", args.output_dt, lo=0.0),
        lat=_num("lat-deg", args.lat_deg, lo=-89.0, lo_open=False, hi=89.0) * DEG_TO_RAD,
        lon=_num("lon-deg", args.lon_deg, lo=-180.0, lo_open=False, hi=360.0) * DEG_TO_RAD,
        h=_num("h-m", args.h_m, lo=-1000.0, lo_open=False, hi=1e5),
        position_sigma_m=_num("position-sigma", args.position_sigma, lo=0.0, lo_open=False),
        velocity_sigma_mps=_num("velocity-sigma", args.velocity_sigma, lo=0.0, lo_open=False),
        tilt_sigma_rad=tuple(
            _num("tilt-sigma-deg", x, lo=0.0, lo_open=False) * DEG_TO_RAD for x in args.tilt_sigma_deg
        ),
        altitude_hold=bool(args.altitude_hold),
        speed_mps=_num("speed", args.speed, lo=0.0, lo_open=False, hi=1000.0),
    )
    n_samples = cfg.duration_s * cfg.rate_hz * cfg.runs
    if n_samples > MAX_SAMPLES:
        raise ConfigError(
            f"--duration x --rate-hz x --runs = {n_samples:.3g} IMU samples; reduce them (limit {MAX_SAMPLES:.0e}: about 170 bytes of memory per sample)"
        )
    check_output_dir(args.out)  # before the Monte Carlo
    t0 = time.perf_counter()
    res = run_drift(grade, cfg)
    wall = time.perf_counter() - t0

    out: Path = args.out
    doc = {
        "grade": grade.name,
        "grade_source": grade.source,
        "runs": cfg.runs,
        "seed": cfg.seed,
        "duration_s": cfg.duration_s,
        "rate_hz": cfg.rate_hz,
        "scenario": "stationary, level, heading north"
        if cfg.speed_mps == 0.0
        else f"straight and level due north at {cfg.speed_mps:g} m/s",
        "speed_mps": cfg.speed_mps,
        "lat_deg": cfg.lat / DEG_TO_RAD,
        "lon_deg": cfg.lon / DEG_TO_RAD,
        "h_m": cfg.h,
        "altitude_hold": cfg.altitude_hold,
        "init_sigma": {
            "position_m": cfg.position_sigma_m,
            "velocity_mps": cfg.velocity_sigma_mps,
            "tilt_rad": list(cfg.tilt_sigma_rad),
        },
        "sigma_horizontal_m_final": float(res.sigma_h_mc[-1]),
        "model_sigma_horizontal_m_final": float(res.sigma_h_model[-1]),
        "linear_regime": res.linear_regime,
        "sigma_tilt_rad_final": float(res.sigma_tilt_mc[-1]),
        "model_sigma_tilt_rad_final": float(res.sigma_tilt_model[-1]),
        "wall_s": round(wall, 3),
        "t_s": res.t.tolist(),
        "sigma_horizontal_m": res.sigma_h_mc.tolist(),
        "model_sigma_horizontal_m": res.sigma_h_model.tolist(),
        "sigma_north_m": res.sigma_n_mc.tolist(),
        "sigma_east_m": res.sigma_e_mc.tolist(),
        "model_sigma_north_m": res.sigma_n_model.tolist(),
        "model_sigma_east_m": res.sigma_e_model.tolist(),
    }
    out.mkdir(parents=True, exist_ok=True)
    _plot(res, out / "drift.png")
    write_text_atomic(out / "drift.json", json.dumps(doc, indent=1) + "\n")
    if not args.quiet:
        _table(res, wall, out)
    return 0


def _plot(res, path: Path) -> None:  # noqa: ANN001
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scale, unit = (1e3, "km") if res.sigma_h_model.max() > 5e3 else (1.0, "m")
    fig, ax = plt.subplots(figsize=(7, 4.2))
    tm = res.t / 60.0
    for r in range(min(len(res.err_h), 20)):
        ax.plot(tm, res.err_h[r] / scale, color="0.8", lw=0.6, label="runs" if r == 0 else None)
    ax.plot(tm, res.sigma_h_mc / scale, "C0", lw=2, label=f"Monte Carlo RMS ({res.config.runs} runs)")
    ax.plot(tm, res.sigma_h_model / scale, "C3--", lw=2, label="error model 1-sigma")
    ax.set_xlabel("time (min)")
    ax.set_ylabel(f"horizontal error ({unit})")
    what = "stationary" if res.config.speed_mps == 0.0 else f"{res.config.speed_mps:g} m/s due north"
    ax.set_title(f"Free-inertial drift, {res.grade.name} grade ({what})")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110)
    plt.close(fig)


def _table(res, wall: float, out: Path) -> None:  # noqa: ANN001
    w = sys.stdout.write
    w(f"free-inertial drift: grade {res.grade.name}, {res.config.runs} runs, {res.config.duration_s:g} s, "
      f"{'stationary' if res.config.speed_mps == 0.0 else f'{res.config.speed_mps:g} m/s north'} "
      f"({wall:.1f} s)\n")  # fmt: skip
    w(f"{'t [s]':>8}  {'MC RMS horiz [m]':>17}  {'model 1-sigma [m]':>17}  {'MC/model':>8}\n")
    n = len(res.t)
    for k in sorted({int(round(i * (n - 1) / 6)) for i in range(7)}):
        mc, mo = res.sigma_h_mc[k], res.sigma_h_model[k]
        ratio = mc / mo if mo > 0 else float("nan")
        w(f"{res.t[k]:8.0f}  {mc:17.4g}  {mo:17.4g}  {ratio:8.2f}\n")
    if not res.linear_regime:
        w(
            f"note: tilt 1-sigma reaches {res.sigma_tilt_model.max():.2g} rad (model), "
            f"{res.sigma_tilt_mc.max():.2g} rad (Monte Carlo): outside the small-error regime, so the linear model "
            "and the Monte Carlo need not agree\n"
        )
    w(f"wrote {out / 'drift.json'} and {out / 'drift.png'}\n")
