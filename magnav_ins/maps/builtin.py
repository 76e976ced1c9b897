"""Maps and surveys shipped inside the package (``magnav_ins/data``), addressed as ``builtin:NAME``.

* ``builtin:osborne-magnetic`` - total-field magnetic anomaly (nT), Osborne Mine, Queensland, gridded at 100 m from
  the 285 east-west FLIGHT lines of the 1990 survey with the bidirectional gridder (:mod:`magnav_ins.maps.build`);
  the 22 north-south TIE lines are excluded, so that a tie line flown over the map with its real readings
  (``builtin:osborne-tie-lines``) is an independent test. Local tangent-plane frame, draped at the survey height
  (ellipsoidal = orthometric + EIGEN-6C4 geoid), with its block cross-validated error layer
  (:mod:`magnav_ins.maps.error_layer`).
* ``builtin:eigen6c4-australia-se`` - gravity disturbance (mGal) at 10 km ellipsoidal height, lat -40..-32 deg,
  lon 142..153 deg (Melbourne to Sydney with margins), 10' grid: EIGEN-6C4 full gravity minus WGS-84 normal gravity
  (:func:`magnav_ins.ins.earth.normal_gravity`) at 10 km; a uniform 3.0 mGal error layer (16 km correlation), the
  RMS difference against an independent grid (Sandwell & Smith marine gravity, Gulf of Alaska, at 10 km).
* ``builtin:osborne-tie-lines`` (a survey, :func:`load_survey_lines`) - the real readings of the 22 tie lines:
  ``flight_line, latitude, longitude, height_ellipsoidal_m, total_field_anomaly_nt``.

``bench/make_builtin_maps.py`` regenerates all three from ``../shared/data``; sources and licences (CC-BY-4.0) are in
``magnav_ins/data/DATA_LICENSES.md``.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

from ..core.errors import InputError, MapError
from .grid import GridMap
from .io import BUILTIN_PREFIX, Survey, load_map, read_map, read_survey

__all__ = [
    "BUILTIN_MAPS",
    "BUILTIN_SURVEYS",
    "builtin_survey_path",
    "load_builtin_map",
    "load_map",
    "load_survey_lines",
]

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


def load_builtin_map(name: str) -> GridMap:
    """The shipped map ``name`` (with or without the ``builtin:`` prefix)."""
    key = _strip(name)
    if key not in BUILTIN_MAPS:
        raise MapError(
            f"builtin:{key}: no such shipped map; available: {', '.join('builtin:' + k for k in BUILTIN_MAPS)}"
        )
    path = data_path(BUILTIN_MAPS[key][0])
    if not path.is_file():
        raise MapError(
            f"builtin:{key}: {path.name} is missing from the installed package (run bench/make_builtin_maps.py)"
        )
    return read_map(path)


def builtin_survey_path(name: str) -> Path:
    """Path of the shipped survey ``name``."""
    key = _strip(name)
    if key not in BUILTIN_SURVEYS:
        raise InputError(
            f"builtin:{key}: no such shipped survey; available: {', '.join('builtin:' + k for k in BUILTIN_SURVEYS)}"
        )
    return data_path(BUILTIN_SURVEYS[key][0])


def load_survey_lines(spec: str = "builtin:osborne-tie-lines") -> Survey:
    """A shipped (``builtin:NAME``) or on-disk survey CSV as a :class:`~magnav_ins.maps.io.Survey` (rad, m)."""
    return read_survey(spec if not spec.startswith(BUILTIN_PREFIX) else builtin_survey_path(spec))
