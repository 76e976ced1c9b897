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


class LinkError(MagnavError):
    """A MAVLink connection that cannot be opened or used."""


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
