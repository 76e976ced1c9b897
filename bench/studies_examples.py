"""Run the example scenarios (examples/scenarios/*.toml) through the study runner and report their metrics.

Each scenario runs ``--runs`` Monte Carlo runs (default 2; the files ask for 20-100) and writes its outputs under
``--out`` (default ``runs/bench_studies``). Prints a table, or one JSON line with ``--json``:
``{"scenario": {"wall_s": ..., "estimators": {name: {"rms_horizontal_m": ..., ...}}, "free_inertial": {...}}}``.

Run: ``python bench/studies_examples.py [--runs N] [--jobs J] [--only NAME ...] [--json]``
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from magnav_ins.studies import reports, runner
from magnav_ins.studies.model import PipelineModel
from magnav_ins.studies.scenario import load_scenario

EXAMPLES = Path(__file__).resolve().parents[1] / "examples" / "scenarios"
KEYS = ("rms_horizontal_m", "final_horizontal_m", "divergence_rate", "availability", "nees_mean")
#: quick by default: the long gravity flights are opt-in with --only
DEFAULT = ("drift_tactical", "storms_hallway", "osborne_tie_lines", "shockley_roads")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=2)
    ap.add_argument("--seed", type=int, default=None)
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--only", nargs="*", default=list(DEFAULT), help="scenario file stems")
    ap.add_argument("--out", type=Path, default=Path("runs/bench_studies"))
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    result: dict[str, dict] = {}
    for stem in args.only:
        sc = load_scenario(EXAMPLES / f"{stem}.toml")
        model = PipelineModel(sc)
        fmap = model.shared()["map"]
        seed = sc.seed if args.seed is None else args.seed
        doc = runner.run_study(model, args.runs, seed, args.out / stem, jobs=args.jobs, quiet=True, fmap=fmap)
        result[stem] = {
            "runs": doc["runs"],
            "wall_s": round(doc["wall_s"], 2),
            "estimators": {n: {k: e[k] for k in KEYS} for n, e in doc["estimators"].items()},
            "free_inertial": {k: doc["free_inertial"][k] for k in KEYS},
        }
        if not args.json:
            print(f"## {stem} ({doc['runs']} runs, {doc['wall_s']:.1f} s)\n")
            print(reports.metrics_table(doc))
    if args.json:
        print(json.dumps(result, separators=(",", ":")))
    return 0


if __name__ == "__main__":
    sys.exit(main())
