"""Fuser speed: 100 Hz IMU, one position fix per second, one core. Prints how many times faster than real time each
fuser runs (target for the UKF: >= 20x), with the wall time per IMU sample and per fix.

Scenario: 120 s of a simulated flight with turns (``simulate.waypoints``, 60 m/s), tactical IMU errors, fixes =
truth + noise (sigma 5 m) at 1 Hz; each fuser is fed 1-s IMU batches (``propagate``), then ``correct`` and
``estimate``. Set OPENBLAS_NUM_THREADS=1 for one-core figures (done below before numpy loads).

    python bench/fusion_speed.py --json [--duration 120] [--fusers ukf,graph,free_inertial]
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from magnav_ins.aiding.fusion import make_fuser  # noqa: E402
from magnav_ins.aiding.fusion.common import ImuNoise  # noqa: E402
from magnav_ins.core.types import LAYOUT_15, Fix, NavEstimate  # noqa: E402
from magnav_ins.core.units import DEG_TO_RAD  # noqa: E402
from magnav_ins.ins import imu_models, simulate  # noqa: E402
from magnav_ins.ins.error_model import apply_error  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--duration", type=float, default=120.0)
    ap.add_argument("--rate", type=float, default=100.0)
    ap.add_argument("--fusers", default="ukf,graph,free_inertial")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    d = DEG_TO_RAD
    pts = np.array([[45.0, 7.0, 3000.0], [45.1, 7.1, 3000.0], [45.05, 7.3, 3000.0]])
    pts[:, :2] *= d
    traj = simulate.waypoints(pts, 60.0, a.rate, turn_rate=3.0 * d)
    traj = traj.slice(0, int(a.duration * a.rate) + 1)
    g = imu_models.get_grade("tactical")
    rng = np.random.default_rng(1)
    imu, _ = imu_models.corrupt(simulate.ideal_imu(traj), g, rng)
    nz = ImuNoise.from_grade(g)
    P0 = np.diag(np.r_[[5.0] * 3, [0.1] * 3, [1e-3] * 3, [0.01] * 3, [5e-6] * 3] ** 2)
    init = NavEstimate(apply_error(traj.at(0), np.r_[3.0, -2.0, 0.0, 0.05, 0.0, 0.0, 0.0, 0.0, 5e-4]), P0, LAYOUT_15)
    R = np.eye(2) * 25.0
    fix_idx = np.flatnonzero(np.isclose(np.mod(traj.t, 1.0), 0.0) & (traj.t > 0))
    fixes = []
    for k in fix_idx:
        s = apply_error(traj.at(int(k)), np.r_[5.0 * rng.standard_normal(2), np.zeros(7)])
        fixes.append(Fix(float(traj.t[k]), s.lat, s.lon, R))
    out: dict = {"imu_rate_hz": a.rate, "fix_rate_hz": 1.0, "duration_s": float(traj.t[-1] - traj.t[0]), "fusers": {}}
    for name in a.fusers.split(","):
        fuser = make_fuser(name, init, nz)
        i = 0
        t0 = time.perf_counter()
        for fix in fixes:
            j = int(np.searchsorted(imu.t, fix.t + 1e-9, side="right"))
            fuser.propagate(imu.slice(i, j))
            i = j
            fuser.correct(fix, height_m=float(traj.h[int(np.argmin(np.abs(traj.t - fix.t)))]), height_sigma_m=5.0)
            fuser.estimate()
        wall = time.perf_counter() - t0
        out["fusers"][name] = {
            "times_real_time": round(out["duration_s"] / wall, 1),
            "wall_s": round(wall, 3),
            "us_per_imu_sample": round(wall / len(imu) * 1e6, 1),
        }
    if a.json:
        print(json.dumps(out))
    else:
        for k, v in out["fusers"].items():
            print(f"{k:14s} {v['times_real_time']:8.1f} x real time  ({v['us_per_imu_sample']} us/sample)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
