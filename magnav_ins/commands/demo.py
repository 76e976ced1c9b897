"""``magnav-ins demo [--out DIR]``: the main job on the shipped real map, offline (:mod:`magnav_ins.studies.demo`).

A tactical-grade INS flies a real Osborne tie line with that line's real magnetometer readings, aided by map
matching against ``builtin:osborne-magnetic``, next to the same INS left free. Prints the aided-vs-free table and
writes ``DIR/summary.json``, ``DIR/track.png`` and ``DIR/error_vs_time.png``.
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

from ..core.errors import ConfigError, InputError


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="the main job on the shipped real map: aided vs free-inertial INS (offline)")
    p.add_argument("--out", type=Path, default=Path("out/demo"), help="output folder (default: out/demo)")
    p.add_argument("--line", type=int, default=None, help="tie line of builtin:osborne-tie-lines (default 10152)")
    p.add_argument("--duration", type=float, default=None, metavar="S", help="fly only the first S seconds")
    p.add_argument("--seed", type=int, default=None, help="seed of the IMU and initial errors (default 1990)")
    p.set_defaults(handler=handle)


def _check_out(out: Path) -> None:
    """A usable output folder: refuse a path that is (or sits under) a file, before any work is done."""
    for p in (out, *out.parents):
        if p.exists():
            if not p.is_dir():
                what = "is a file" if p == out else f"is under {p}, which is a file"
                raise InputError(f"--out {out}: {what}; expected a folder")
            break


def handle(args: argparse.Namespace) -> int:
    import time

    from ..studies.demo import DemoConfig, run_demo, summary_table, write_demo

    t0 = time.perf_counter()
    _check_out(args.out)
    cfg = DemoConfig()
    over = {}
    if args.line is not None:
        over["line"] = args.line
    if args.duration is not None:
        if not args.duration > 0:
            raise ConfigError(f"--duration must be > 0 s, got {args.duration}")
        over["duration_s"] = args.duration
    if args.seed is not None:
        if args.seed < 0:
            raise ConfigError(f"--seed must be >= 0, got {args.seed}")
        over["seed"] = args.seed
    cfg = replace(cfg, **over)
    result = run_demo(cfg)
    try:
        paths = write_demo(result, args.out, t_start=t0)
    except OSError as exc:
        raise InputError(f"--out {args.out}: cannot write: {exc.strerror or exc}") from None
    print(summary_table(result.summary))
    print(f"wrote {', '.join(str(p) for p in paths)} ({result.summary['wall_s']:.1f} s)")
    return 0
