"""The project's exceptions. Every message names what was wrong, where, and what was expected.

The CLI turns any :class:`MagnavError` into a one-line message and exit status 2; anything else is a bug.
"""

from __future__ import annotations


class MagnavError(Exception):
    """Base class for errors caused by the user's input or configuration (never a bug)."""


class InputError(MagnavError, ValueError):
    """Bad input data: a malformed file, a NaN reading, time going backwards, a wrong column.

    Build the message with :func:`where` so that it names the file, row or key.
    """


class ConfigError(MagnavError, ValueError):
    """Bad configuration: an unknown or missing key, a value out of range, an unknown grade or method."""


class MapError(MagnavError, ValueError):
    """A map that cannot be used: missing unit/kind/datum metadata, empty or all-NaN grid, query off the map."""


class OutputError(MagnavError):
    """An output that cannot be written: a folder where a file is meant (or the reverse), a path under a file, a
    read-only place. Raised before the work starts where possible (:mod:`magnav_ins.core.atomic`)."""


class LinkError(MagnavError):
    """A MAVLink connection that cannot be opened or used."""


def warn(message: str) -> None:
    """Print a one-line warning on stderr (``magnav-ins: warning: ...``): something the user should know that does
    not stop the command (a run without fixes, an implausible map under inspection)."""
    import sys

    print(f"magnav-ins: warning: {message}", file=sys.stderr)


def where(file: object | None = None, row: int | None = None, key: str | None = None) -> str:
    """Format a location prefix such as ``"imu.csv row 12 column 'gyro_x': "`` for error messages.

    Rows are 1-based data rows (the header is row 0), as a user counts them in a spreadsheet.
    """
    parts: list[str] = []
    if file is not None:
        parts.append(str(file))
    if row is not None:
        parts.append(f"row {row}")
    if key is not None:
        parts.append(f"'{key}'")
    return (" ".join(parts) + ": ") if parts else ""
