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

from .io import load_builtin_map, load_map, read_survey
from .shipped import BUILTIN_MAPS, BUILTIN_PREFIX, BUILTIN_SURVEYS, builtin_survey_path, data_path
from .survey import Survey

__all__ = [
    "BUILTIN_MAPS",
    "BUILTIN_SURVEYS",
    "builtin_survey_path",
    "data_path",
    "load_builtin_map",
    "load_map",
    "load_survey_lines",
]


def load_survey_lines(spec: str = "builtin:osborne-tie-lines") -> Survey:
    """A shipped (``builtin:NAME``) or on-disk survey CSV as a :class:`~magnav_ins.maps.survey.Survey` (rad, m)."""
    return read_survey(spec if not spec.startswith(BUILTIN_PREFIX) else builtin_survey_path(spec))
