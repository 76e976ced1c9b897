"""Gravity-map matching comparison on real grids (issue 16): every matcher on the same truth, IMU and readings.

Scenarios (``examples/scenarios/``): the comparison set is ``gravity_melbourne_sydney`` (EIGEN-6C4 10', Wang's
route), ``gravity_qld_west`` (Geoscience Australia 0.9 km grid continued to 100 m, a lawnmower flight) and
``gravity_gulf_of_alaska`` (Sandwell-Smith 2' marine grid at sea level); ``--all`` adds the variants
(``gravity_qld_west_tactical``, ``_20mgal``, ``_1km``, ``gravity_gulf_of_alaska_ship``). Each is run through the study
runner (``magnav-ins run``'s code path) or read back with ``--from DIR`` (``DIR/<stem>/metrics.json`` and ``runs.nc``).

Per scenario and estimator: mean and RMS horizontal error, final RMS, divergence rate (Wang's rule,
``studies.metrics.is_divergent``), availability (fixes issued / attempts), fix NEES mean / median over the issued
fixes (2 when the fix covariances are right), the filter's NEES, and the limit column: the posterior Cramer-Rao
bound of the flight (``metrics.json`` ``crlb_rms_horizontal_m``, ``studies.crlb``) with the ratio mean / CRLB;
the "no fix" reasons and the wall time of each study.

``--figures DIR`` also draws ``DIR/gravity_error_<stem>.png``: the RMS over runs of every estimator's horizontal
error against time, with the flight's posterior CRLB (``studies.crlb.flight_crlb``) as the limit curve.

Run: ``python bench/gravity_comparison.py [--runs N] [--jobs J] [--all | --only STEM ...] [--out DIR] [--from DIR]
[--figures DIR] [--json]``. Defaults: each scenario's own ``runs`` (20), 2 jobs, ``runs/gravity``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

from studies_matchers import EXAMPLES, _m, _pct, _run_or_read, fix_nees  # noqa: E402

COMPARISON = ("gravity_melbourne_sydney", "gravity_qld_west", "gravity_gulf_of_alaska")
VARIANTS = (
    "gravity_qld_west_tactical",
    "gravity_qld_west_20mgal",
    "gravity_qld_west_1km",
    "gravity_gulf_of_alaska_ship",
)


def rows(stem: str, doc: dict[str, Any], ds: Any) -> list[dict[str, Any]]:
    """One row per estimator (and the free-inertial baseline) of one scenario's study."""
    crlb = doc.get("crlb_rms_horizontal_m")
    out = []
    for name, e in [*doc["estimators"].items(), ("free_inertial", doc["free_inertial"])]:
        fn_mean, fn_median = fix_nees(ds, name) if (ds is not None and e.get("matcher")) else (None, None)
        mean = e["mean_horizontal_m"]
        out.append(
            {
                "scenario": stem,
                "estimator": name,
                "matcher": e.get("matcher"),
                "runs": doc["runs"],
                "mean_m": mean,
                "rms_m": e["rms_horizontal_m"],
                "final_m": e["final_horizontal_m"],
                "divergence_rate": e["divergence_rate"],
                "availability": e["availability"],
                "fix_nees_mean": fn_mean,
                "fix_nees_median": fn_median,
                "filter_nees": e["nees_mean"],
                "crlb_rms_m": crlb,
                "crlb_final_m": doc.get("crlb_final_horizontal_m"),
                "mean_over_crlb": (mean / crlb) if (mean is not None and crlb) else None,
                "no_fix_reasons": e.get("no_fix_reasons", {}),
                "wall_s": doc["wall_s"],
            }
        )
    return out


def table(stem: str, rs: list[dict[str, Any]]) -> str:
    r0 = rs[0]
    head = (
        f"#### {stem} ({r0['runs']} runs, {r0['wall_s']:.0f} s; posterior CRLB of the flight: "
        f"{_m(r0['crlb_rms_m'])} m RMS, {_m(r0['crlb_final_m'])} m at the end)\n\n"
        "| estimator | mean (m) | RMS (m) | final RMS (m) | diverged | fixes issued | fix NEES mean / median "
        "| filter NEES | mean / CRLB | no fix (reasons) |\n|---|---:|---:|---:|---:|---:|---:|---:|---:|---|"
    )
    lines = [head]
    for r in rs:
        why = ", ".join(f"{k} {v}" for k, v in sorted(r["no_fix_reasons"].items())) or "–"
        lines.append(
            f"| {r['estimator']} | {_m(r['mean_m'])} | {_m(r['rms_m'])} | {_m(r['final_m'])} "
            f"| {_pct(r['divergence_rate'])} | {_pct(r['availability'])} "
            f"| {_m(r['fix_nees_mean'], 2)} / {_m(r['fix_nees_median'], 2)} | {_m(r['filter_nees'], 2)} "
            f"| {_m(r['mean_over_crlb'], 1)} | {why if r['matcher'] else '–'} |"
        )
    return "\n".join(lines)


def error_figure(stem: str, ds: Any, out_dir: Path) -> Path:
    """``out_dir/gravity_error_<stem>.png``: RMS over runs of the horizontal error (m) vs time per estimator and
    the flight's posterior CRLB (m, ``sqrt(P_NN + P_EE)``) along the same truth."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from magnav_ins.studies.crlb import flight_crlb
    from magnav_ins.studies.model import PipelineModel
    from magnav_ins.studies.scenario import load_scenario

    sc = load_scenario(EXAMPLES / f"{stem}.toml")
    sh = PipelineModel(sc).shared()
    tc, sc_h = flight_crlb(sc, sh["truth"], sh["imu"], sh["map"])
    t = np.asarray(ds["time"], float) / 3600.0
    fig, ax = plt.subplots(figsize=(6.4, 3.3))
    for name in [str(n) for n in ds["estimator"].values]:
        e = ds.sel(estimator=name)
        h2 = np.asarray(e["err_north_m"], float) ** 2 + np.asarray(e["err_east_m"], float) ** 2
        free = name == "free_inertial"
        ax.plot(t, np.sqrt(np.nanmean(h2, axis=0)), lw=1.0 if free else 1.3, ls=":" if free else "-",
                color="0.4" if free else None, label=name.replace("+ukf", ""))  # fmt: skip
    ax.plot(tc / 3600.0, sc_h, color="k", lw=1.6, ls="--", label="CRLB")
    ax.set_yscale("log")
    ax.set_xlabel("time (h)")
    ax.set_ylabel("horizontal error, RMS (m)")
    ax.set_title(f"{stem}: {ds.sizes['run']} runs", fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, ncol=4, loc="upper left")
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / f"gravity_error_{stem}.png"
    fig.savefig(path, dpi=80, bbox_inches="tight")
    plt.close(fig)
    return path


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=None, help="Monte Carlo runs (default: each scenario's own)")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--all", action="store_true", help="the variants too")
    ap.add_argument("--only", nargs="*", default=None, help="scenario file stems")
    ap.add_argument("--out", type=Path, default=Path("runs/gravity"))
    ap.add_argument("--from", dest="from_dir", type=Path, default=None, help="read DIR/<stem>/metrics.json instead")
    ap.add_argument("--figures", type=Path, default=None, help="draw DIR/gravity_error_<stem>.png")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    stems = args.only or (list(COMPARISON) + (list(VARIANTS) if args.all else []))
    t0 = time.perf_counter()
    out: dict[str, Any] = {"scenarios": {}}
    md = []
    for stem in stems:
        doc, ds = _run_or_read(stem, args)
        rs = rows(stem, doc, ds)
        out["scenarios"][stem] = rs
        md.append(table(stem, rs))
        if args.figures is not None and ds is not None:
            error_figure(stem, ds, args.figures)
        if not args.json:
            print(md[-1] + "\n", flush=True)
    out["wall_s"] = time.perf_counter() - t0
    out["jobs"] = args.jobs
    if args.json:
        print(json.dumps(out, separators=(",", ":"), default=float))
    else:
        print(f"total wall time {out['wall_s']:.0f} s with --jobs {args.jobs} ({len(stems)} scenarios)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
