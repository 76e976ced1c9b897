"""The real-data integrity suite (issue 13), as a benchmark: ``magnav_ins.studies.suite`` (its docstring says what
is flown, against which maps, with which estimators and set-up) run from the project folder, where
``../shared/data`` holds the Rio survey.

    python bench/realdata.py --json [--quick] [--jobs 2] [--seeds N] [--only GROUP,...] [--estimators NAME,...]
    python bench/realdata.py --bound-only DRAWS [--json] [--quick] [--only GROUP,...]   # the bound alone

Prints the per-case and per-group tables (stderr with ``--json``) and, with ``--json``, one line on stdout:
``{"groups": {"osborne_tactical": {ESTIMATOR: {...}}, "osborne_navigation": {...}, "rio": {...}}}`` with, per
estimator, the ``metrics.json`` keys ``rms_horizontal_m``, ``nees_mean``, ``fix_nees_mean``, ``hpl_exceedance``,
``divergence_rate`` (and ``nees_divergence_rate``, ``max_horizontal_m``, ``availability``, ``hpl_median_m``, ``runs``) plus
``free_rms_horizontal_m``, pooled over the group's cases and runs; ``wall_s`` and the job count are printed with
the tables. The same suite: ``magnav-ins suite``.

Each estimator's figures also carry the group's information bound (``magnav_ins.studies.suite.case_bound``: the
posterior Cramér-Rao bound of the readings' model ``z = m(p) + c + b(p) + v``, about a minute for the full suite;
``--no-bound`` skips it): ``crlb_rms_horizontal_m`` (pooled as the RMS), ``crlb_free_rms_horizontal_m`` (the free
INS's covariance along the same flights), ``crlb_wang_rate`` (share of cases whose bound itself meets Wang's two
conditions) and ``crlb_free_wang_rate``; the tables' ``xCRLB`` is the RMS over the bound's.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RIO_SURVEY = ROOT.parent / "shared" / "data" / "rio_magnetic" / "rio-magnetic.csv.xz"


def main(argv: list[str] | None = None) -> int:
    from magnav_ins.studies.suite import DEFAULT_SEEDS, report, run_suite

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--json", action="store_true", help="print the group figures as one JSON line on stdout")
    p.add_argument("--quick", action="store_true", help="the CI subset (under 3 minutes on 2 cores)")
    p.add_argument(
        "--seeds", type=int, default=DEFAULT_SEEDS, help=f"Monte Carlo runs per case (default {DEFAULT_SEEDS})"
    )
    p.add_argument("--jobs", type=int, default=2, help="worker processes (default 2)")
    p.add_argument("--only", default=None, help="comma-separated groups to run (default all)")
    p.add_argument("--estimators", default=None, help="comma-separated estimators to fly (e.g. pmht+ukf; default all)")
    p.add_argument("--no-bound", action="store_true", help="leave out the information bound (crlb_* keys)")
    p.add_argument(
        "--bound-only",
        type=int,
        default=None,
        metavar="DRAWS",
        help="fly nothing: the bound per case and group, with DRAWS runs at the bound each for Wang's test",
    )
    args = p.parse_args(argv)
    if args.bound_only is not None:
        from magnav_ins.studies.suite import suite_bounds

        only = tuple(args.only.split(",")) if args.only else None
        groups, text = suite_bounds(quick=args.quick, only=only, rio_survey=RIO_SURVEY, draws=args.bound_only)
        print(text, file=sys.stderr if args.json else sys.stdout)
        if args.json:
            print(json.dumps({"bounds": groups}, allow_nan=False))
        return 0
    only = tuple(args.only.split(",")) if args.only else None
    ests = tuple(args.estimators.split(",")) if args.estimators else None
    res = run_suite(
        quick=args.quick,
        seeds=args.seeds,
        jobs=args.jobs,
        only=only,
        rio_survey=RIO_SURVEY,
        estimators=ests,
        bound=not args.no_bound,
    )
    text = report(res) + f" with {args.jobs} jobs"
    print(text, file=sys.stderr if args.json else sys.stdout)
    if args.json:
        print(json.dumps({"groups": res.groups}, allow_nan=False))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
