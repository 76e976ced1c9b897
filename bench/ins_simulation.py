"""Trajectory simulation, inverse mechanisation and the error model: accuracy figures in one run.

1. Round trip: ``integrate(ideal_imu(traj))`` vs ``traj`` for 1 h at 100 Hz, a great circle (200 m/s, 10 km) and a
   waypoint flight with coordinated turns and climbs (100 m/s): maximum horizontal error (free vertical channel).
2. Peer: :func:`ideal_imu` vs pyins ``sim.generate_imu`` (increment type) on the same waypoint flight at sea level.
3. Drift: ``ins drift`` Monte Carlo (stationary, 30 min) per grade, beside the error model's 1-sigma, and a
   50-run tactical comparison (the acceptance figure: within 30 %).

Run: ``python bench/ins_simulation.py --json`` (about 2 min on 2 cores; ``--quick`` for 10 min / fewer runs).
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

D = np.pi / 180.0


def round_trip(duration_s: float) -> dict[str, float]:
    from magnav_ins.core.frames import horizontal_error_m
    from magnav_ins.ins.simulate import great_circle, ideal_imu, waypoints
    from magnav_ins.ins.strapdown import integrate

    n = int(duration_s * 100) + 1
    out: dict[str, float] = {}
    t0 = time.perf_counter()
    gc = great_circle(-38 * D, 144.5 * D, -20 * D, 160 * D, 10000.0, 200.0, 100.0).slice(0, n)
    pts = [(45 * D, 10 * D, 1000.0), (45.5 * D, 10.6 * D, 1500.0), (46.0 * D, 10.1 * D, 1200.0), (45.6 * D, 9.4 * D, 800.0),
           (45.0 * D, 10.0 * D, 1000.0), (45.4 * D, 10.9 * D, 1000.0), (46.2 * D, 10.9 * D, 2000.0)]  # fmt: skip
    wp = waypoints(pts, 100.0, 100.0).slice(0, n)
    out["trajectories_wall_s"] = round(time.perf_counter() - t0, 2)
    for name, tr in (("great_circle", gc), ("waypoints", wp)):
        t0 = time.perf_counter()
        imu = ideal_imu(tr)
        out[f"{name}_ideal_imu_wall_s"] = round(time.perf_counter() - t0, 2)
        nav = integrate(tr.at(0), imu)
        e = horizontal_error_m(nav.lat, nav.lon, tr.lat, tr.lon)
        out[f"{name}_duration_s"] = float(tr.t[-1])
        out[f"{name}_round_trip_max_horizontal_m"] = float(e.max())
        out[f"{name}_round_trip_max_vertical_m"] = float(np.abs(nav.h - tr.h).max())
    return out


def peer_pyins() -> dict[str, float]:
    from pyins import sim

    from magnav_ins.core.frames import euler_from_q_nb
    from magnav_ins.ins.simulate import ideal_imu, waypoints

    pts = [(45 * D, 10 * D, 0.0), (45.05 * D, 10.08 * D, 0.0), (45.1 * D, 10.0 * D, 0.0)]
    tr = waypoints(pts, 100.0, 100.0)
    roll, pitch, yaw = euler_from_q_nb(tr.q_nb)
    lla = np.column_stack([np.rad2deg(tr.lat), np.rad2deg(tr.lon), tr.h])
    t0 = time.perf_counter()
    _, inc = sim.generate_imu(tr.t, lla, np.rad2deg(np.column_stack([roll, pitch, yaw])), tr.v_n, "increment")
    t_py = time.perf_counter() - t0
    t0 = time.perf_counter()
    mine = ideal_imu(tr)
    t_me = time.perf_counter() - t0
    dt = np.diff(tr.t)[:, None]
    g = inc[["gyro_x", "gyro_y", "gyro_z"]].to_numpy()[1:] / dt
    a = inc[["accel_x", "accel_y", "accel_z"]].to_numpy()[1:] / dt
    return {
        "peer_samples": len(tr),
        "peer_gyro_max_diff_rad_s": float(np.abs(g - mine.gyro_b[1:]).max()),
        "peer_accel_max_diff_mps2": float(np.abs(a - mine.accel_b[1:]).max()),
        "peer_pyins_wall_s": round(t_py, 2),
        "peer_ours_wall_s": round(t_me, 2),
    }


def drift(quick: bool) -> dict[str, object]:
    from magnav_ins.ins.drift import DriftConfig, run_drift
    from magnav_ins.ins.imu_models import GRADES, get_grade

    out: dict[str, object] = {}
    dur = 600.0 if quick else 1800.0
    for name in GRADES:
        t0 = time.perf_counter()
        r = run_drift(get_grade(name), DriftConfig(duration_s=dur, runs=20, seed=1))
        out[name] = {
            "mc_sigma_h_final_m": float(r.sigma_h_mc[-1]),
            "model_sigma_h_final_m": float(r.sigma_h_model[-1]),
            "wall_s": round(time.perf_counter() - t0, 2),
        }
    r = run_drift(get_grade("tactical"), DriftConfig(duration_s=dur, runs=20 if quick else 50, seed=11, rate_hz=10.0))
    ratio = r.sigma_h_mc[1:] / r.sigma_h_model[1:]
    out["tactical_mc_over_model_final"] = float(ratio[-1])
    out["tactical_mc_over_model_worst"] = float(ratio[np.argmax(np.abs(ratio - 1))])
    out["duration_s"] = dur
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", action="store_true", help="print one JSON line")
    ap.add_argument("--quick", action="store_true", help="10 min round trips and drifts")
    args = ap.parse_args()
    res: dict[str, object] = {}
    res.update(round_trip(600.0 if args.quick else 3600.0))
    try:
        res.update(peer_pyins())
    except ImportError:
        res["peer"] = "pyins not installed"
    res["drift"] = drift(args.quick)
    if args.json:
        print(json.dumps(res))
    else:
        print(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
