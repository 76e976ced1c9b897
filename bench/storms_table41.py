"""Storms (2009, seed 004) sec. 4.4.1: the Table 4.1 Monte Carlo, without and with the turn command (Figs. 4.12-4.13).

Runs ``examples/scenarios/storms_hallway.toml`` and ``storms_hallway_turn.toml`` (or reads a finished run with
``--from DIR``) and prints, per estimator, the figures Storms' two plots show: the ensemble RMS (over runs, per time)
of the horizontal error, its maximum from each run's first accepted fix on and after the initial error is resolved
(from 10 s on: ~6 updates), the pooled RMS after the first fix (``rms_after_first_fix_m``), the filter's NEES and the
fixes' NEES (2-D, each fix's error against its own covariance; 2 = consistent), availability. ``--plot FILE`` draws
the ensemble RMS vs time of every estimator (the analogue of Figs. 4.12 and 4.13).

    python bench/storms_table41.py --runs 100 --jobs 2 --plot docs/storms_fig412_413.png
    python bench/storms_table41.py --json           # one JSON line
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
SCENARIOS = ("storms_hallway", "storms_hallway_turn")
#: Storms' bounds (sec. 4.4.1.3): < 0.4 m without the turn command (Fig. 4.12), < 0.2 m with it (Fig. 4.13)
STORMS_BOUND_M = {"storms_hallway": 0.4, "storms_hallway_turn": 0.2}
#: "once the initial positioning error is resolved": statistics from this time on as well (s)
RESOLVED_S = 10.0
#: a run has lost the vehicle when its error exceeds this after RESOLVED_S (m; wider than the half hallway)
LOST_M = 1.5


def fix_nees(ds: Any, name: str) -> tuple[float | None, float | None]:
    """Mean and median 2-D NEES of the issued fixes of estimator ``name`` against their own covariances."""
    e = ds.sel(estimator=name)
    ok = np.asarray(e["fix_available"]) > 0
    dn = np.asarray(e["fix_err_north_m"], float)[ok]
    de = np.asarray(e["fix_err_east_m"], float)[ok]
    sn = np.asarray(e["fix_sigma_north_m"], float)[ok]
    se = np.asarray(e["fix_sigma_east_m"], float)[ok]
    rho = np.nan_to_num(np.asarray(e["fix_corr_ne"], float)[ok])
    with np.errstate(invalid="ignore", divide="ignore"):
        q = ((dn / sn) ** 2 - 2 * rho * dn * de / (sn * se) + (de / se) ** 2) / (1.0 - rho**2)
    q = q[np.isfinite(q)]
    return (float(q.mean()), float(np.median(q))) if q.size else (None, None)


def ensemble_rms(ds: Any, name: str, kept_only: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Time (s) and the ensemble RMS over runs of the horizontal error (m) of estimator ``name`` (``kept_only``:
    over the runs that never lose the vehicle, :func:`lost_runs`)."""
    e = ds.sel(estimator=name)
    h2 = np.asarray(e["err_north_m"], float) ** 2 + np.asarray(e["err_east_m"], float) ** 2
    if kept_only:
        h2 = h2[~lost_runs(ds, name)]
    return np.asarray(ds["time"], float), np.sqrt(np.nanmean(h2, axis=0))


def lost_runs(ds: Any, name: str) -> np.ndarray:
    """Per run: True when its horizontal error exceeds ``LOST_M`` at some time after ``RESOLVED_S``."""
    e = ds.sel(estimator=name)
    h = np.hypot(np.asarray(e["err_north_m"], float), np.asarray(e["err_east_m"], float))
    t = np.asarray(ds["time"], float)
    return np.nanmax(h[:, t >= RESOLVED_S], axis=1) > LOST_M


def first_fix_s(ds: Any, name: str) -> float | None:
    e = ds.sel(estimator=name)
    ft = np.asarray(e["fix_t_s"], float)[np.asarray(e["fix_available"]) > 0]
    return float(np.nanmin(ft)) if ft.size else None


def rows(stem: str, doc: dict[str, Any], ds: Any) -> list[dict[str, Any]]:
    out = []
    for name, m in doc["estimators"].items():
        t, ens = ensemble_rms(ds, name)
        t0 = first_fix_s(ds, name)
        after = ens[t >= t0] if t0 is not None else np.zeros(0)
        resolved = ens[t >= RESOLVED_S]
        fn_mean, fn_med = fix_nees(ds, name)
        bound = STORMS_BOUND_M[stem]
        lost = lost_runs(ds, name)
        tk, ens_k = ensemble_rms(ds, name, kept_only=True)
        ek = ds.sel(estimator=name)
        h2k = (np.asarray(ek["err_north_m"], float) ** 2 + np.asarray(ek["err_east_m"], float) ** 2)[~lost]
        out.append(
            {
                "scenario": stem,
                "estimator": name,
                "runs": doc["runs"],
                "rms_after_first_fix_m": m.get("rms_after_first_fix_m"),
                "ensemble_rms_max_after_first_fix_m": float(after.max()) if after.size else None,
                "ensemble_rms_max_after_10s_m": float(resolved.max()) if resolved.size else None,
                "ensemble_rms_median_after_10s_m": float(np.median(resolved)) if resolved.size else None,
                "runs_lost": int(lost.sum()),
                "rms_after_first_fix_kept_m": float(np.sqrt(np.nanmean(h2k[:, tk >= t0])))
                if t0 is not None and h2k.size
                else None,
                "ensemble_rms_max_after_10s_kept_m": float(ens_k[tk >= RESOLVED_S].max()) if h2k.size else None,
                "rms_horizontal_m": m["rms_horizontal_m"],
                "filter_nees": m["nees_mean"],
                "fix_nees_mean": fn_mean,
                "fix_nees_median": fn_med,
                "availability": m["availability"],
                "storms_bound_m": bound,
                "below_bound": (m.get("rms_after_first_fix_m") or np.inf) < bound,
                "wall_s": doc["wall_s"],
            }
        )
    return out


def plot(results: dict[str, tuple[dict[str, Any], Any]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from magnav_ins.core.atomic import atomic_path

    fig, axes = plt.subplots(1, len(results), figsize=(6.0 * len(results), 4.0), sharey=True, squeeze=False)
    for ax, (stem, (doc, ds)) in zip(axes[0], results.items(), strict=True):
        for k, name in enumerate(doc["estimators"]):
            t, ens = ensemble_rms(ds, name)
            ax.plot(t, ens, color=f"C{k}", label=f"{name}, all runs")
            t, ens = ensemble_rms(ds, name, kept_only=True)
            n_lost = int(lost_runs(ds, name).sum())
            ax.plot(t, ens, color=f"C{k}", ls="--", label=f"{name}, the {doc['runs'] - n_lost} runs that keep track")
        ax.axhline(STORMS_BOUND_M[stem], color="k", ls=":", lw=1, label=f"Storms: < {STORMS_BOUND_M[stem]} m")
        ax.set_title(f"{stem} ({doc['runs']} runs)" + (" - Fig. 4.13 analogue" if "turn" in stem else " - Fig. 4.12"))
        ax.set_xlabel("time (s)")
        ax.set_ylim(0, 1.6)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    axes[0][0].set_ylabel("ensemble RMS horizontal error (m)")
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110, bbox_inches="tight")
    plt.close(fig)


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
    ap.add_argument("--runs", type=int, default=None, help="Monte Carlo runs (default: the scenarios' 100)")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--out", type=Path, default=Path("runs/storms"))
    ap.add_argument("--from", dest="from_dir", type=Path, default=None, help="read DIR/<stem>/ instead of running")
    ap.add_argument("--plot", type=Path, default=None, help="write the ensemble-RMS figure here (PNG)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    results = {stem: run_or_read(stem, args) for stem in SCENARIOS}
    table = [r for stem, (doc, ds) in results.items() for r in rows(stem, doc, ds)]
    if args.plot is not None:
        plot(results, args.plot)
    if args.json:
        print(json.dumps({"storms_table41": table, "wall_s": time.perf_counter() - t0}, separators=(",", ":")))
        return 0

    def f(x: Any, d: int = 3) -> str:
        return "-" if x is None else f"{x:.{d}f}"

    print(
        "| scenario | estimator | RMS from the first fix | ensemble RMS max from the first fix / from 10 s "
        "| runs lost (> 1.5 m after 10 s) | RMS from the first fix, runs that keep track "
        "| filter NEES | fix NEES mean / median | availability | Storms |"
    )
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|---|")
    for r in table:
        print(
            f"| {r['scenario']} | {r['estimator']} | {f(r['rms_after_first_fix_m'])} m "
            f"| {f(r['ensemble_rms_max_after_first_fix_m'], 2)} / {f(r['ensemble_rms_max_after_10s_m'], 2)} m "
            f"| {r['runs_lost']} of {r['runs']} | {f(r['rms_after_first_fix_kept_m'])} m "
            f"| {f(r['filter_nees'], 2)} | {f(r['fix_nees_mean'], 2)} / {f(r['fix_nees_median'], 2)} "
            f"| {100 * (r['availability'] or 0):.0f} % | < {r['storms_bound_m']} m |"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
