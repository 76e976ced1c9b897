"""Are the matchers' fixes honest on real readings with default settings? Osborne tie lines flown with their own
recorded readings against a map gridded from the flight lines only, per run: horizontal RMS / max, the fuser's
NEES, the fix NEES of every issued fix against the truth (2 = consistent), availability, divergence (the
studies' test) and free-inertial RMS; then medians / means over the runs. One JSON line per run, a summary line.

    python bench/matchers_honesty.py --estimator '{"matcher": {"kind": "particle_ins"}, "fusion": {"kind": "ukf"}}' \
        --lines 10152 10155 --speeds 50 65 80 --grades tactical --seeds 1 2 --jobs 2 [--map builtin:osborne-magnetic]

The map (default ``builtin:osborne-magnetic``) is used with its error layer if it has one (else the matchers'
stated default). ``--map`` takes any map file, e.g. one with another error layer. Wall time is ~40 s per run on
one core (more under load).
"""

from __future__ import annotations

import argparse
import json
import time
from concurrent.futures import ProcessPoolExecutor
from typing import Any

import numpy as np

from magnav_ins.studies.model import PipelineModel
from magnav_ins.studies.runner import summarise_run
from magnav_ins.studies.scenario import scenario_from_dict


def scenario(line: int, speed: float, grade: str, est: dict[str, Any], map_path: str, seed: int):
    """One tie line flown at ``speed`` m/s with IMU ``grade``, real readings every 0.5 s (+1 nT), one estimator."""
    d = {
        "name": f"osborne_{line}",
        "seed": seed,
        "runs": 1,
        "trajectory": {"kind": "survey_line", "survey": "builtin:osborne-tie-lines", "line": line, "speed_mps": speed},
        "imu": {"grade": grade, "rate_hz": 50.0},
        "map": {"path": map_path, "kind": "total_field_anomaly_nt"},
        "sensor": {"kind": "scalar_magnetometer", "source": "survey", "sigma": 1.0, "interval_s": 0.5},
        "estimator": [est],
    }
    return scenario_from_dict(d)


def fix_nees(fav, fn, fe, sn, se, rho) -> np.ndarray:
    """NEES of the issued fixes from their north/east errors and 1-sigmas / correlation (runs.nc fields)."""
    fn, fe, sn, se, rho = (np.asarray(a, float)[fav] for a in (fn, fe, sn, se, rho))
    c = sn * se * rho
    det = sn**2 * se**2 - c**2
    return (fe**2 * sn**2 - 2 * fn * fe * c + fn**2 * se**2) / det


def one(args: tuple) -> dict[str, Any]:
    line, speed, grade, est, map_path, seed = args
    sc = scenario(line, speed, grade, est, map_path, seed)
    t0 = time.perf_counter()
    s = summarise_run(0, PipelineModel(sc).run(np.random.SeedSequence(seed)))
    e, f = s.estimators[est["name"]], s.estimators["free_inertial"]
    fav = e.fix_available
    fnees = fix_nees(fav, e.fix_err_n, e.fix_err_e, e.fix_sigma_n, e.fix_sigma_e, e.fix_corr_ne)
    m = e.metrics
    return {
        "line": line, "speed_mps": speed, "grade": grade, "seed": seed,
        "rms_m": float(np.sqrt(np.mean(m.e**2))), "max_m": float(np.max(m.e)), "nees": float(np.nanmean(m.nees)),
        "fix_nees": float(np.mean(fnees)) if fnees.size else None,
        "fix_nees_above_13_8": float(np.mean(fnees > 13.8)) if fnees.size else None,
        "fixes": int(fav.sum()), "availability": float(fav.mean()) if fav.size else None,
        "divergent": bool(m.divergent), "free_rms_m": float(np.sqrt(np.mean(f.metrics.e**2))),
        "wall_s": round(time.perf_counter() - t0, 1),
    }  # fmt: skip


def summary(rows: list[dict[str, Any]]) -> dict[str, Any]:
    def col(k: str) -> np.ndarray:
        return np.array([r[k] for r in rows if r[k] is not None], float)

    fx = col("fix_nees")
    return {
        "runs": len(rows),
        "rms_median_m": float(np.median(col("rms_m"))),
        "rms_max_m": float(np.max(col("rms_m"))),
        "nees_mean": float(np.mean(col("nees"))),
        "fix_nees_mean": float(np.mean(fx)) if fx.size else None,
        "fix_nees_max_run": float(np.max(fx)) if fx.size else None,
        "availability_mean": float(np.mean(col("availability"))),
        "divergent_runs": int(sum(r["divergent"] for r in rows)),
        "free_rms_median_m": float(np.median(col("free_rms_m"))),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--estimator", default='{"matcher": {"kind": "particle_ins"}, "fusion": {"kind": "ukf"}}')
    ap.add_argument("--lines", type=int, nargs="+", default=[10152])
    ap.add_argument("--speeds", type=float, nargs="+", default=[65.0])
    ap.add_argument("--grades", nargs="+", default=["tactical"])
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--map", default="builtin:osborne-magnetic")
    ap.add_argument("--jobs", type=int, default=1)
    a = ap.parse_args()
    est = json.loads(a.estimator)
    est.setdefault("name", "estimator")
    jobs = [(ln, sp, g, est, a.map, sd) for ln in a.lines for sp in a.speeds for g in a.grades for sd in a.seeds]
    rows = []
    with ProcessPoolExecutor(a.jobs) as ex:
        for r in ex.map(one, jobs):
            rows.append(r)
            print(json.dumps({k: round(v, 3) if isinstance(v, float) else v for k, v in r.items()}), flush=True)
    print(json.dumps({"estimator": est, "map": a.map, "summary": summary(rows)}), flush=True)


if __name__ == "__main__":
    main()
