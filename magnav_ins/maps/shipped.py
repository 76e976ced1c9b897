"""The names and files of the maps and surveys shipped in ``magnav_ins/data`` (``builtin:NAME``); what they hold
is described in :mod:`magnav_ins.maps.builtin`. No reader here, so every reader may import it."""

from __future__ import annotations

from importlib import resources
from pathlib import Path

from ..core.errors import InputError

BUILTIN_PREFIX = "builtin:"

#: shipped grids: name -> (file in magnav_ins/data, one-line description)
BUILTIN_MAPS: dict[str, tuple[str, str]] = {
    "osborne-magnetic": (
        "osborne-magnetic.nc",
        "total-field anomaly (nT), Osborne QLD, 100 m grid from the E-W flight lines (tie lines excluded), draped",
    ),
    "eigen6c4-australia-se": (
        "eigen6c4-australia-se.nc",
        "gravity disturbance (mGal) at 10 km, EIGEN-6C4 minus normal gravity, lat -40..-32, lon 142..153 deg",
    ),
}
#: shipped surveys: name -> (file, description)
BUILTIN_SURVEYS: dict[str, tuple[str, str]] = {
    "osborne-tie-lines": (
        "osborne-tie-lines.csv.xz",
        "real readings of the 22 N-S tie lines of the Osborne survey (not used by builtin:osborne-magnetic)",
    ),
}


def data_path(filename: str) -> Path:
    """Path of a file shipped in ``magnav_ins/data``."""
    return Path(str(resources.files("magnav_ins.data").joinpath(filename)))


def _strip(name: str) -> str:
    return name[len(BUILTIN_PREFIX) :] if name.startswith(BUILTIN_PREFIX) else name


def builtin_survey_path(name: str) -> Path:
    """Path of the shipped survey ``name``."""
    key = _strip(name)
    if key not in BUILTIN_SURVEYS:
        raise InputError(
            f"builtin:{key}: no such shipped survey; available: {', '.join('builtin:' + k for k in BUILTIN_SURVEYS)}"
        )
    return data_path(BUILTIN_SURVEYS[key][0])
