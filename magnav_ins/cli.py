"""The ``magnav-ins`` command. Sub-commands live in :mod:`magnav_ins.commands`, one module per group.

User mistakes (:class:`~magnav_ins.core.errors.MagnavError`) become a one-line message on stderr and exit
status 2; so does an operating-system error on a named file (a disk that filled up, a folder that vanished: the
outputs are checked before the work starts, this is the last resort). Nothing is half-written because every writer
goes through :mod:`magnav_ins.core.atomic`. The first Ctrl-C or SIGTERM stops the command (workers included, see
:mod:`magnav_ins.core.signals`) with one line and exit status 130 or 143.
"""

from __future__ import annotations

import argparse
import importlib
import re
import sys
from collections.abc import Sequence

from . import __version__
from .core.errors import MagnavError
from .core.signals import EXIT_SIGINT, EXIT_SIGTERM, Terminated, stop_signals_raise

#: command-group modules under ``magnav_ins.commands``, in the order ``--help`` lists them
COMMAND_MODULES: tuple[str, ...] = ("demo", "ins", "calibrate", "run", "suite", "maps", "bridge", "replay")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="magnav-ins",
        description="INS aided by magnetic and gravity map matching (no GNSS).",
    )
    parser.add_argument("--version", action="version", version=f"magnav-ins {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name in COMMAND_MODULES:
        importlib.import_module(f"{__package__}.commands.{name}").add_parser(sub)
    return parser


_NEGATIVE_LIST = re.compile(r"^-\d[\d.]*(,[-+]?[\d.]+(e[-+]?\d+)?)+$", re.IGNORECASE)


def _join_negative_lists(argv: Sequence[str]) -> list[str]:
    """``--init -21.9,140.6,400,0`` -> ``--init=-21.9,140.6,400,0``: argparse takes a comma list that starts with a
    minus sign for an option, so a southern latitude or western longitude would otherwise be refused."""
    out: list[str] = []
    for tok in argv:
        if out and _NEGATIVE_LIST.match(tok) and out[-1].startswith("--") and "=" not in out[-1]:
            out[-1] = f"{out[-1]}={tok}"
        else:
            out.append(tok)
    return out


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point: parse ``argv``, run the handler, map user errors to exit status 2 and signals to 130 / 143."""
    parser = build_parser()
    args = parser.parse_args(_join_negative_lists(sys.argv[1:] if argv is None else list(argv)))
    with stop_signals_raise():
        try:
            return int(args.handler(args) or 0)
        except MagnavError as exc:
            print(f"magnav-ins: error: {exc}", file=sys.stderr)
            return 2
        except Terminated:
            print("magnav-ins: terminated (SIGTERM)", file=sys.stderr)
            return EXIT_SIGTERM
        except KeyboardInterrupt:
            print("magnav-ins: interrupted", file=sys.stderr)
            return EXIT_SIGINT
        except OSError as exc:
            if exc.filename is None:
                raise
            print(f"magnav-ins: error: {exc.filename}: {exc.strerror or exc}", file=sys.stderr)
            return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
