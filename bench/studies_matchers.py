"""Matcher acceptance studies (issue 7): Storms' Bayes grid, Wang's PMHT-MM on gravity, Shockley's ML/MLR/ABL.

Runs the example scenarios through the study runner (``magnav-ins run``'s code path) or, with ``--from DIR``, reads
the ``metrics.json`` and ``runs.nc`` that ``magnav-ins run SCENARIO --out DIR/<stem>`` wrote, and prints Markdown
tables (``--json``: one JSON line instead):

* Storms hallway: Bayes grid horizontal RMS against Storms' 100-run Monte Carlo bound (< 0.3 m, 004 sec. 4).
* PMHT gravity: per (IMU, T, sigma) the mean horizontal error, divergence rate and fix availability over the runs,
  the free-inertial mean error, the time after which the aided RMS (over runs) stays below the free-inertial
  RMS, the fix NEES (mean and median over the issued fixes; 2 when the fix covariances are right) and the filter's
  NEES; beside it Wang et al. (2022, seed 001) Table 2 (GGplus gravity field map, 250 m grid at 100 m height).
* Shockley roads: availability, share of fixes within 3 m and RMS per matcher (Shockley ch. IV).

Run: ``python bench/studies_matchers.py [--runs N] [--jobs J] [--only STEM ...] [--out DIR] [--from DIR] [--json]``.
Defaults: each scenario's own ``runs``; ``--from runs/matchers`` reads what an earlier run wrote there.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

EXAMPLES = Path(__file__).resolve().parents[1] / "examples" / "scenarios"
STORMS = "storms_hallway"
PMHT = ("pmht_gravity_1mgal", "pmht_gravity_20mgal", "pmht_gravity_tactical")
SHOCKLEY = "shockley_roads"
DEFAULT = (STORMS, *PMHT, SHOCKLEY)
FREE = "free_inertial"
MGAL = 1e-5  # m/s^2
#: Wang et al. (2022) Table 2 (GGplus vertical gravity field map): (sigma mGal, T) -> (mean error m, divergence %)
WANG_TABLE2 = {(1.0, 30): (507.0, 0.0), (1.0, 15): (510.0, 0.0), (20.0, 30): (1820.0, 6.0), (20.0, 15): (4199.0, 22.0)}
STORMS_BOUND_M = 0.3


def _run_or_read(stem: str, args: argparse.Namespace) -> tuple[dict[str, Any], Any]:
    """metrics.json as a dict and runs.nc as an xarray Dataset (or None) for one scenario."""
    import xarray as xr

    if args.from_dir is not None:
        d = args.from_dir / stem
        doc = json.loads((d / "metrics.json").read_text())
    else:
        from magnav_ins.studies import runner
        from magnav_ins.studies.model import PipelineModel
        from magnav_ins.studies.scenario import load_scenario

        sc = load_scenario(EXAMPLES / f"{stem}.toml")
        model = PipelineModel(sc)
        runs = sc.runs if args.runs is None else args.runs
        d = args.out / stem
        doc = runner.run_study(model, runs, sc.seed, d, jobs=args.jobs, quiet=True, fmap=model.shared()["map"])
    nc = d / "runs.nc"
    return doc, (xr.load_dataset(nc) if nc.exists() else None)


def _rms_over_runs(ds: Any, name: str) -> tuple[np.ndarray, np.ndarray]:
    """Time (s) and RMS over runs of the horizontal error (m) of estimator ``name``."""
    e = ds.sel(estimator=name)
    h2 = np.asarray(e["err_north_m"], float) ** 2 + np.asarray(e["err_east_m"], float) ** 2
    return np.asarray(ds["time"], float), np.sqrt(np.nanmean(h2, axis=0))


def crossover_s(ds: Any, name: str) -> float | None:
    """Earliest time (s) after which the aided RMS over runs stays below the free-inertial RMS (None: never)."""
    t, a = _rms_over_runs(ds, name)
    _, f = _rms_over_runs(ds, FREE)
    worse = np.flatnonzero(~(a < f))
    if worse.size == 0:
        return float(t[0])
    k = worse[-1] + 1
    return float(t[k]) if k < len(t) else None


def fix_nees(ds: Any, name: str) -> tuple[float | None, float | None]:
    """Mean and median over the issued fixes of all runs of the fix NEES ``d' P^-1 d`` (2-D: 2 when the fix
    covariances are right) of estimator ``name``, from the fix errors, sigmas and correlations in ``runs.nc``."""
    e = ds.sel(estimator=name)
    dn, de = np.asarray(e["fix_err_north_m"], float), np.asarray(e["fix_err_east_m"], float)
    sn, se = np.asarray(e["fix_sigma_north_m"], float), np.asarray(e["fix_sigma_east_m"], float)
    r = np.asarray(e["fix_corr_ne"], float)
    ok = (np.asarray(e["fix_available"]) > 0) & np.isfinite(dn) & np.isfinite(de) & (sn > 0) & (se > 0) & (abs(r) < 1)
    if not np.any(ok):
        return None, None
    dn, de, sn, se, r = dn[ok], de[ok], sn[ok], se[ok], r[ok]
    un, ue = dn / sn, de / se
    nees = (un**2 - 2 * r * un * ue + ue**2) / (1 - r**2)
    return float(np.mean(nees)), float(np.median(nees))


def _pct(x: float | None) -> str:
    return "–" if x is None else f"{100 * x:.0f} %"


def _m(x: float | None, nd: int = 0) -> str:
    return "–" if x is None else f"{x:,.{nd}f}"


def pmht_rows(stem: str, doc: dict[str, Any], ds: Any) -> list[dict[str, Any]]:
    from magnav_ins.studies.scenario import load_scenario

    sc = load_scenario(EXAMPLES / f"{stem}.toml")
    sigma = float(sc.sensor.sigma)
    free = doc["free_inertial"]
    rows = []
    for est in sc.estimators:
        e = doc["estimators"][est.name]
        T = int(est.matcher.get("batch", 30))
        cross = crossover_s(ds, est.name) if ds is not None else None
        fn_mean, fn_median = fix_nees(ds, est.name) if ds is not None else (None, None)
        wang = WANG_TABLE2.get((sigma, T)) if sc.imu.grade == "precision" else None
        rows.append(
            {
                "scenario": stem,
                "estimator": est.name,
                "imu": sc.imu.grade,
                "hours": round(float(sc.trajectory.duration_s or 0.0) / 3600.0, 2),
                "T": T,
                "sigma_mgal": sigma,
                "runs": doc["runs"],
                "mean_m": e["mean_horizontal_m"],
                "rms_m": e["rms_horizontal_m"],
                "final_m": e["final_horizontal_m"],
                "divergence_rate": e["divergence_rate"],
                "availability": e["availability"],
                "fixes_issued": e["fixes_issued"],
                "fix_attempts": e["fix_attempts"],
                "fix_nees_mean": fn_mean,
                "fix_nees_median": fn_median,
                "filter_nees": e["nees_mean"],
                "free_mean_m": free["mean_horizontal_m"],
                "free_final_m": free["final_horizontal_m"],
                "free_divergence_rate": free["divergence_rate"],
                "beats_free": e["mean_horizontal_m"] < free["mean_horizontal_m"],
                "below_free_after_h": None if cross is None else round(cross / 3600.0, 2),
                "wang_mean_m": None if wang is None else wang[0],
                "wang_divergence_pct": None if wang is None else wang[1],
                "wall_s": doc["wall_s"],
            }
        )
    return rows


def pmht_table(rows: list[dict[str, Any]]) -> str:
    head = (
        "| IMU | T | sigma (mGal = 1e-5 m/s^2) | runs | mean error (m) | diverged | fixes issued | final (m) "
        "| free inertial mean / final (m), diverged | aided below free after (h) | fix NEES mean / median "
        "| filter NEES | Wang Table 2: mean / diverged |\n"
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"
    )
    lines = [head]
    for r in rows:
        wang = "–" if r["wang_mean_m"] is None else f"{r['wang_mean_m']:,.0f} m / {r['wang_divergence_pct']:.0f} %"
        lines.append(
            f"| {r['imu']} ({r['hours']:g} h) | {r['T']} | {r['sigma_mgal']:g} | {r['runs']} | {_m(r['mean_m'])} "
            f"| {_pct(r['divergence_rate'])} | {_pct(r['availability'])} | {_m(r['final_m'])} "
            f"| {_m(r['free_mean_m'])} / {_m(r['free_final_m'])}, {_pct(r['free_divergence_rate'])} "
            f"| {'never' if r['below_free_after_h'] is None else r['below_free_after_h']} "
            f"| {_m(r['fix_nees_mean'], 2)} / {_m(r['fix_nees_median'], 2)} | {_m(r['filter_nees'], 2)} | {wang} |"
        )
    return "\n".join(lines)


def storms_after_first_fix(ds: Any, name: str = "bayes_grid+ukf") -> dict[str, float | None]:
    """Storms' Fig. 4.12 statistic: the ensemble RMS over runs per time. Returns the time of the first fix (s),
    the RMS pooled over runs and samples from then on, and the time (s) after which the ensemble RMS stays below
    0.3 m (None: never)."""
    e = ds.sel(estimator=name)
    h2 = np.asarray(e["err_north_m"], float) ** 2 + np.asarray(e["err_east_m"], float) ** 2
    t = np.asarray(ds["time"], float)
    ft = np.asarray(e["fix_t_s"], float)[np.asarray(e["fix_available"]) > 0]
    if ft.size == 0:
        return {"first_fix_s": None, "rms_after_first_fix_m": None, "ens_below_bound_after_s": None}
    t0 = float(np.nanmin(ft))
    ens = np.sqrt(np.nanmean(h2, axis=0))
    above = np.flatnonzero(~(ens < STORMS_BOUND_M))
    k = 0 if above.size == 0 else above[-1] + 1
    return {
        "first_fix_s": t0,
        "rms_after_first_fix_m": float(np.sqrt(np.nanmean(h2[:, t >= t0]))),
        "ens_below_bound_after_s": float(t[k]) if k < len(t) else None,
    }


def storms_row(doc: dict[str, Any], ds: Any) -> dict[str, Any]:
    e = doc["estimators"]["bayes_grid+ukf"]
    extra = storms_after_first_fix(ds) if ds is not None else {}
    return {
        **extra,
        "runs": doc["runs"],
        "rms_m": e["rms_horizontal_m"],
        "max_m": e["max_horizontal_m"],
        "availability": e["availability"],
        "nees": e["nees_mean"],
        "free_rms_m": doc["free_inertial"]["rms_horizontal_m"],
        "pass": e["rms_horizontal_m"] < STORMS_BOUND_M,
        "pass_after_first_fix": (extra.get("rms_after_first_fix_m") or np.inf) < STORMS_BOUND_M,
        "wall_s": doc["wall_s"],
    }


def shockley_rows(doc: dict[str, Any]) -> list[dict[str, Any]]:
    return [
        {
            "estimator": n,
            "runs": doc["runs"],
            "availability": e["availability"],
            "fixes_issued": e["fixes_issued"],
            "within_3m": e["fix_within_3m_fraction"],
            "bins": e["fix_error_bins"],
            "rms_m": e["rms_horizontal_m"],
            "wall_s": doc["wall_s"],
        }
        for n, e in doc["estimators"].items()
    ]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=None, help="Monte Carlo runs (default: each scenario's own)")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--only", nargs="*", default=list(DEFAULT), help="scenario file stems")
    ap.add_argument("--out", type=Path, default=Path("runs/matchers"))
    ap.add_argument("--from", dest="from_dir", type=Path, default=None, help="read DIR/<stem>/metrics.json instead")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    out: dict[str, Any] = {}
    md: list[str] = []
    pmht: list[dict[str, Any]] = []
    for stem in args.only:
        doc, ds = _run_or_read(stem, args)
        if stem == STORMS:
            r = out[STORMS] = storms_row(doc, ds)
            after = r.get("rms_after_first_fix_m")
            below = r.get("ens_below_bound_after_s")
            md.append(
                f"### Storms hallway, Bayes grid + UKF ({r['runs']} runs, {r['wall_s']:.0f} s)\n\n"
                "| estimator | RMS, all samples (m) | RMS from the first fix (m) | ensemble RMS < 0.3 m from (s) "
                "| max (m) | availability | NEES (2-D) |\n"
                "|---|---:|---:|---:|---:|---:|---:|\n"
                f"| bayes_grid+ukf | {r['rms_m']:.3f} | {_m(after, 3)} | {_m(below, 1)} | {r['max_m']:.2f} "
                f"| {_pct(r['availability'])} | {r['nees']:.2f} |\n"
                f"| free inertial | {r['free_rms_m']:.1f} | | | | | |\n\n"
                f"Storms (004 sec. 4, Fig. 4.12): RMS < 0.3 m over 100 runs. All samples: "
                f"{'pass' if r['pass'] else 'fail'}; from the first fix ({_m(r.get('first_fix_s'), 1)} s): "
                f"{'pass' if r['pass_after_first_fix'] else 'fail'}.\n"
            )
        elif stem in PMHT:
            pmht.extend(pmht_rows(stem, doc, ds))
        elif stem == SHOCKLEY:
            rows = out[SHOCKLEY] = shockley_rows(doc)
            lines = [
                f"### Shockley roads, ML / MLR / ABL + UKF ({rows[0]['runs']} runs, {rows[0]['wall_s']:.0f} s)\n",
                "| matcher | availability | fixes issued | fixes < 3 m | 3-10 m | 10-20 m | >= 20 m | RMS (m) |",
                "|---|---:|---:|---:|---:|---:|---:|---:|",
            ]
            for r in rows:
                b = r["bins"]
                lines.append(
                    f"| {r['estimator']} | {_pct(r['availability'])} | {r['fixes_issued']} | {_pct(r['within_3m'])} | "
                    f"{_pct(b['3_to_10m'])} | {_pct(b['10_to_20m'])} | {_pct(b['ge_20m'])} | {_m(r['rms_m'], 2)} |"
                )
            md.append("\n".join(lines) + "\n")
        else:
            raise SystemExit(f"studies_matchers: unknown scenario stem {stem!r}; expected one of {DEFAULT}")
    if pmht:
        out["pmht"] = pmht
        seen = dict.fromkeys((r["scenario"], r["runs"], r["wall_s"]) for r in pmht)
        walls = ", ".join(f"{sc}: {n} runs in {w:.0f} s" for sc, n, w in seen)
        md.insert(0 if STORMS not in out else 1, f"### PMHT-MM gravity ({walls})\n\n{pmht_table(pmht)}\n")
    if args.json:
        print(json.dumps(out, separators=(",", ":"), default=float))
    else:
        print("\n".join(md))
    return 0


if __name__ == "__main__":
    sys.exit(main())
