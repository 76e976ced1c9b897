"""``magnav-ins run SCENARIO.toml``: a Monte Carlo study from a scenario file (:mod:`magnav_ins.studies`).

Writes ``OUT/metrics.json`` (keys in ``shared/DESIGN.md``), ``OUT/runs.nc``, ``OUT/report.md`` and PNG figures;
prints the metrics table. ``--runs`` and ``--seed`` override the scenario's values; results depend on them only,
not on ``--jobs`` or ``--scheduler``.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

from ..core.atomic import check_output_dir
from ..core.errors import ConfigError, warn


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("run", help="Monte Carlo study from a scenario TOML: metrics.json, runs.nc, report, plots")
    p.add_argument("scenario", type=Path, help="scenario file (TOML; keys in docs/scenarios.md)")
    p.add_argument("--out", type=Path, default=None, help="output folder (default: runs/<scenario name>)")
    p.add_argument("--runs", type=int, default=None, help="Monte Carlo runs (default: the scenario's 'runs')")
    p.add_argument("--seed", type=int, default=None, help="master seed (default: the scenario's 'seed')")
    p.add_argument("--jobs", type=int, default=1, help="local worker processes (default 1)")
    p.add_argument(
        "--duration", type=float, default=None, metavar="S", help="truncate the trajectory to S seconds (quick looks)"
    )
    p.add_argument("--scheduler", default=None, metavar="tcp://HOST:PORT", help="run on a Dask cluster instead")
    p.add_argument("--no-plots", action="store_true", help="skip the PNG figures")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(handler=handle)


def _check_map_plausible(sc, fmap) -> None:  # noqa: ANN001
    """Refuse a map whose values are implausible for its kind (:mod:`magnav_ins.core.plausibility`) unless the
    scenario says ``[map] allow_implausible = true``."""
    from ..core.plausibility import field_values_problem

    if fmap is None or sc.map is None or sc.map.allow_implausible or not hasattr(fmap, "values"):
        return
    problem = field_values_problem(fmap.values, fmap.kind)
    if problem:
        raise ConfigError(
            f"{sc.where('map.path')}: implausible for {fmap.kind.value}: {problem} "
            "(set [map] allow_implausible = true to use it anyway)"
        )


#: truth samples tested against the map's coverage before a study (evenly spaced)
_COVERAGE_SAMPLES = 2000


def _coverage_warnings(sc, truth, fmap) -> list[str]:  # noqa: ANN001
    """Before the runs: a trajectory that never crosses the map can get no fix; say so (with a hint when every
    coordinate is within +-pi: radians written as degrees)."""
    import numpy as np

    from ..core.units import RAD_TO_DEG

    if fmap is None or sc.sensor is None or not any(e.matcher for e in sc.estimators):
        return []
    k = np.unique(np.linspace(0, len(truth.t) - 1, min(len(truth.t), _COVERAGE_SAMPLES)).astype(int))
    lat, lon = np.asarray(truth.lat)[k], np.asarray(truth.lon)[k]
    on = np.asarray(fmap.covers(lat, lon), bool)
    if on.any():
        return []
    la, lo = lat * RAD_TO_DEG, lon * RAD_TO_DEG
    line = (
        f"{sc.where('trajectory')}: the trajectory (lat {la.min():.4f}..{la.max():.4f}, lon {lo.min():.4f}.."
        f"{lo.max():.4f} deg) never crosses the map {sc.map.path}"
    )
    if hasattr(fmap, "bounds_latlon"):
        b = np.asarray(fmap.bounds_latlon) * RAD_TO_DEG
        line += f" (lat {b[0]:.4f}..{b[1]:.4f}, lon {b[2]:.4f}..{b[3]:.4f} deg)"
    line += ": no fix can be attempted"
    tr = sc.trajectory
    pts = [p for p in (tr.start_deg, tr.end_deg, *(tr.points_deg or ())) if p is not None]
    if pts and all(abs(a) <= np.pi and abs(b) <= np.pi for a, b in pts):
        line += "; every coordinate is within +-pi: radians written as degrees?"
    return [line]


def handle(args: argparse.Namespace) -> int:
    from ..studies import reports, runner
    from ..studies.model import PipelineModel
    from ..studies.scenario import MAX_RUNS, load_scenario

    sc = load_scenario(args.scenario)
    if args.duration is not None:
        if not args.duration > 0:
            raise ConfigError(f"--duration must be > 0 s, got {args.duration}")
        sc = dataclasses.replace(sc, trajectory=dataclasses.replace(sc.trajectory, duration_s=args.duration))
    runs = sc.runs if args.runs is None else args.runs
    seed = sc.seed if args.seed is None else args.seed
    if not 1 <= runs <= MAX_RUNS:
        raise ConfigError(f"--runs must be in [1, {MAX_RUNS}], got {runs}")
    if seed < 0:
        raise ConfigError(f"--seed must be >= 0, got {seed}")
    if args.jobs < 1:
        raise ConfigError(f"--jobs must be >= 1, got {args.jobs}")
    out = check_output_dir(args.out if args.out is not None else Path("runs") / sc.name)  # before any work
    model = PipelineModel(sc)
    fmap = model.shared()["map"]  # builds truth + map once here: scenario errors surface before any worker starts
    _check_map_plausible(sc, fmap)
    notes = _coverage_warnings(sc, model.shared()["truth"], fmap)
    for line in notes:
        warn(line)
    doc = runner.run_study(
        model,
        runs,
        seed,
        out_dir=out,
        jobs=args.jobs,
        scheduler=args.scheduler,
        quiet=args.quiet,
        plots=not args.no_plots,
        fmap=fmap,
        command=f"magnav-ins run {args.scenario} --runs {runs} --seed {seed} --out {out}"
        + (f" --duration {args.duration:g}" if args.duration is not None else ""),
        warnings=notes,
    )
    print(reports.metrics_table(doc), end="")
    for line in doc["warnings"][len(notes) :]:
        warn(line)
    print(f"wrote {out / 'metrics.json'} ({doc['runs']} runs, {doc['wall_s']:.1f} s)")
    return 0
