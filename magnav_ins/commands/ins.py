"""``magnav-ins ins ...``: inertial-only commands. ``integrate`` lives in :mod:`.ins_integrate`,
``drift`` in :mod:`.ins_drift`; this module only groups them."""

from __future__ import annotations

import argparse

from . import ins_drift, ins_integrate


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("ins", help="free-inertial tools: integrate a recorded IMU, drift studies per IMU grade")
    ins_sub = p.add_subparsers(dest="ins_command", metavar="INS_COMMAND")
    ins_sub.required = True
    ins_integrate.add_parser(ins_sub)
    ins_drift.add_parser(ins_sub)
