"""MagNavigate (Shockley 2012, seed 003, ch. V; Raquet et al., seed 000, sec. 3.3) as a navigator: the particle
filter's own solution, no INS, on a road network.

Runs ``examples/scenarios/magnavigate_route.toml`` (a 5 km route through a 1 km street grid, like the AFIT route),
``magnavigate_large_area.toml`` (9.5 km through a 6 x 4 km grid of long streets on a smoother field, like the
large-area map) and ``magnavigate_route_position.toml`` (the route with position-fix updates from ML and MLR
instead of the 3-axis reading), or reads finished runs with ``--from DIR``, and prints per scenario and estimator
what Shockley's error plots give (horizontal RMS and maximum error, pooled over the runs and per run) beside the
filter's own consistency (the 2-D NEES of the particle cloud's mean against its covariance; 2 = consistent) and the
runs that lose the vehicle (the mean error over the last quarter of the run above ``LOST_M``).

    python bench/magnavigate.py --jobs 1
    python bench/magnavigate.py --json           # one JSON line
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SCENARIOS = ("magnavigate_route", "magnavigate_large_area", "magnavigate_route_position")
#: Shockley's figures (horizontal RMS / max error, m): AFIT route with 1 m readings (Fig. 5.3); large area
#: (Fig. 5.10)
SHOCKLEY = {
    "magnavigate_route": "8 / 44 m (Fig. 5.3)",
    "magnavigate_large_area": "309 / 1335 m (Fig. 5.10)",
    "magnavigate_route_position": "ML, MLR as position update: RMS ~10-35 m (Fig. 5.4, 5.7)",
}
#: a run has lost the vehicle when its mean horizontal error over the last quarter of the run exceeds this (m;
#: Shockley's largest error on the AFIT route was 44 m)
LOST_M = 50.0


def errors(ds: Any, name: str) -> tuple[np.ndarray, np.ndarray]:
    """Horizontal error (runs, time) m and the 2-D NEES (runs, time) of estimator ``name``."""
    e = ds.sel(estimator=name)
    dn, de = np.asarray(e["err_north_m"], float), np.asarray(e["err_east_m"], float)
    sn, se = np.asarray(e["sigma_north_m"], float), np.asarray(e["sigma_east_m"], float)
    rho = np.nan_to_num(np.asarray(e["corr_ne"], float))
    with np.errstate(invalid="ignore", divide="ignore"):
        q = ((dn / sn) ** 2 - 2 * rho * dn * de / (sn * se) + (de / se) ** 2) / (1.0 - rho**2)
    return np.hypot(dn, de), q


def rows(stem: str, doc: dict[str, Any], ds: Any) -> list[dict[str, Any]]:
    out = []
    for name in doc["estimators"]:
        h, q = errors(ds, name)
        n = h.shape[1]
        lost = np.nanmean(h[:, 3 * n // 4 :], axis=1) > LOST_M
        rms_run = np.sqrt(np.nanmean(h**2, axis=1))
        out.append(
            {
                "scenario": stem,
                "estimator": name,
                "runs": int(h.shape[0]),
                "rms_m": float(np.sqrt(np.nanmean(h**2))),
                "max_m": float(np.nanmax(h)),
                "rms_per_run_median_m": float(np.median(rms_run)),
                "rms_per_run_min_m": float(rms_run.min()),
                "rms_per_run_max_m": float(rms_run.max()),
                "max_per_run_median_m": float(np.median(np.nanmax(h, axis=1))),
                "nees_mean": float(np.nanmean(q)),
                "nees_median": float(np.nanmedian(q)),
                "runs_lost": int(lost.sum()),
                "shockley": SHOCKLEY[stem],
                "wall_s": doc["wall_s"],
            }
        )
    return out


def run_or_read(stem: str, args: argparse.Namespace) -> tuple[dict[str, Any], Any]:
    import xarray as xr

    from magnav_ins.studies.model import PipelineModel
    from magnav_ins.studies.runner import run_study
    from magnav_ins.studies.scenario import load_scenario

    out = (args.from_dir or args.out) / stem
    if args.from_dir is None:
        sc = load_scenario(ROOT / "examples" / "scenarios" / f"{stem}.toml")
        run_study(PipelineModel(sc), args.runs or sc.runs, sc.seed, out, jobs=args.jobs, plots=False)
    doc = json.loads((out / "metrics.json").read_text())
    return doc, xr.load_dataset(out / "runs.nc")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=None, help="Monte Carlo runs (default: each scenario's own)")
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--out", type=Path, default=Path("runs/magnavigate"))
    ap.add_argument("--from", dest="from_dir", type=Path, default=None, help="read DIR/<stem>/ instead of running")
    ap.add_argument("--only", nargs="*", default=None, help="scenario stems to run (default: all)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    stems = [s for s in SCENARIOS if args.only is None or s in args.only]
    table = [r for stem in stems for r in rows(stem, *run_or_read(stem, args))]
    if args.json:
        print(json.dumps({"magnavigate": table, "wall_s": time.perf_counter() - t0}, separators=(",", ":")))
        return 0
    print(
        "| scenario | estimator | runs | RMS (pooled) | max | RMS per run median [min, max] | runs lost "
        "| NEES mean / median | Shockley RMS / max |"
    )
    print("|---|---|---:|---:|---:|---:|---:|---:|---|")
    for r in table:
        print(
            f"| {r['scenario']} | {r['estimator']} | {r['runs']} | {r['rms_m']:.1f} m | {r['max_m']:.0f} m "
            f"| {r['rms_per_run_median_m']:.1f} [{r['rms_per_run_min_m']:.1f}, {r['rms_per_run_max_m']:.1f}] m "
            f"| {r['runs_lost']} of {r['runs']} | {r['nees_mean']:.2f} / {r['nees_median']:.2f} | {r['shockley']} |"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
