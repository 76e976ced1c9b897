"""``magnav-ins suite``: the real-data integrity suite (:mod:`magnav_ins.studies.suite`): every estimator with
default settings over the 22 Osborne tie lines (tactical and navigation IMUs, 50 / 65 / 80 m/s) and the Rio de
Janeiro tie lines, with their own recorded readings. Prints the per-case and per-group tables (RMS, max, NEES, fix
NEES, HPL exceedance, availability, divergence, free-inertial RMS); ``--json`` prints the group figures as one JSON
line instead (the tables go to stderr).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from ..core.errors import ConfigError


def add_parser(sub: argparse._SubParsersAction) -> None:
    from ..studies.suite import DEFAULT_SEEDS, GROUPS, RIO_SURVEY_DEFAULT

    p = sub.add_parser("suite", help="the real-data integrity suite: every estimator over real survey lines")
    p.add_argument("--quick", action="store_true", help="the CI subset: 4 Osborne lines and 2 Rio lines at 65 m/s")
    p.add_argument(
        "--seeds", type=int, default=DEFAULT_SEEDS, help=f"Monte Carlo runs per case (default {DEFAULT_SEEDS})"
    )
    p.add_argument("--jobs", type=int, default=1, help="local worker processes (default 1)")
    p.add_argument("--only", default=None, help=f"comma-separated groups ({', '.join(GROUPS)}; default all)")
    p.add_argument(
        "--rio", type=Path, default=RIO_SURVEY_DEFAULT, help=f"the Rio survey (default {RIO_SURVEY_DEFAULT})"
    )
    p.add_argument("--estimators", default=None, help="comma-separated estimators to fly (e.g. pmht+ukf; default all)")
    p.add_argument("--json", action="store_true", help="print the group figures as one JSON line")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(handler=handle)


def handle(args: argparse.Namespace) -> int:
    from ..studies.suite import report, run_suite

    if args.jobs < 1:
        raise ConfigError(f"--jobs must be >= 1, got {args.jobs}")
    only = tuple(g.strip() for g in args.only.split(",") if g.strip()) if args.only else None
    from ..studies.suite import RIO_SURVEY_DEFAULT

    asked = (only is not None and "rio" in only) or Path(args.rio) != RIO_SURVEY_DEFAULT
    if asked and not Path(args.rio).is_file():  # asked for by name: not skipped in silence ("0 cases, 0 runs")
        raise ConfigError(f"--rio {args.rio}: no such file (the Rio survey lives in ../shared/data beside the project)")
    ests = tuple(e.strip() for e in args.estimators.split(",") if e.strip()) if args.estimators else None
    res = run_suite(quick=args.quick, seeds=args.seeds, jobs=args.jobs, only=only, rio_survey=args.rio,
                    quiet=args.quiet or args.json, estimators=ests)  # fmt: skip
    text = report(res)
    if args.json:
        print(text, file=sys.stderr)
        print(json.dumps({"groups": res.groups}, allow_nan=False))
    else:
        print(text)
    return 0
