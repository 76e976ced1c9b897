"""Scenario files: TOML -> validated, frozen configuration dataclasses (every key in :data:`SCHEMA`, rendered as
``docs/scenarios.md`` by :mod:`.scenario_doc`).

Every mistake raises :class:`~magnav_ins.core.errors.ConfigError` naming the file, the line, the key and what was
expected: unknown keys, missing keys, wrong types, out-of-range values (units are in the key names: ``_m``, ``_s``,
``_deg``, ``_hz``, ``_mps``), and files that do not exist.

Line numbers. :mod:`tomllib` gives none for a well-formed file, so :func:`locate_keys` scans the text lightly: it
tracks the current table header (``[a.b]``, and ``[[a]]`` with a per-array counter) and records every
``key = ...`` that starts a line (bare, quoted or dotted keys), plus the keys of an inline table ``{k = v, ...}`` on
that line (they share its line). Keys inside multi-line arrays are not needed by the schema and are not scanned. A
missing key is reported at its table's header line. Syntax errors come from tomllib, which names the line itself.

Relative paths in the file resolve against the scenario file's directory. ``builtin:NAME`` (shipped maps and
surveys) and ``synthetic:NAME`` (generated maps) are passed through unresolved.
"""

from __future__ import annotations

import math
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..core.errors import ConfigError
from ..core.types import FieldKind

#: IMU grades understood by ``ins.imu_models.get_grade`` (Storms Table 2.2; Wang Table 1)
IMU_GRADES = ("consumer", "commercial", "tactical", "navigation", "precision", "quantum")
TRAJECTORY_KINDS = ("great_circle", "waypoints", "survey_line", "file", "lawnmower", "ground_path")
#: keys of a ground path's ``wander`` table (:class:`magnav_ins.ins.ground_path.Wander`)
WANDER_KEYS = ("accel_sigma_mps2", "cross_gain", "along_gain", "max_offset_m")
SENSOR_KINDS = {
    "gravimeter": FieldKind.GRAVITY_DISTURBANCE_MGAL,
    "scalar_magnetometer": FieldKind.TOTAL_FIELD_ANOMALY_NT,
    "vector_magnetometer": FieldKind.VECTOR_FIELD_NT,
}
SENSOR_SOURCES = ("simulated", "survey")
#: name reserved for the free-inertial baseline that every study adds
FREE_INERTIAL = "free_inertial"
#: specs that are not file paths
SPEC_PREFIXES = ("builtin:", "synthetic:")


# --------------------------------------------------------------------------------------------- key tables
@dataclass(frozen=True)
class ScenarioKey:
    """One scenario key: where it lives (``table``: ``""`` for the top level, ``"trajectory"``, ``"estimator"`` for
    every ``[[estimator]]``), its TOML type, whether it is required (``default`` = :data:`REQUIRED`) or its default,
    and for numbers the accepted range (``lo`` / ``hi``; ``lo_open`` excludes ``lo``) with the reason for it.
    ``kinds``: the trajectory kinds a ``[trajectory]`` key belongs to (empty: every kind). This table is the
    documented schema (``docs/scenarios.md`` is generated from it by :func:`schema_markdown`, and a test checks
    that every key the validator accepts is in it); the validators take their ranges from it."""

    table: str
    name: str
    type: str
    doc: str
    default: Any = None
    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    why: str = ""
    kinds: tuple[str, ...] = ()

    @property
    def path(self) -> str:
        return f"{self.table}.{self.name}" if self.table else self.name

    @property
    def range_text(self) -> str:
        def num(x: float) -> str:
            return f"{int(x)}" if float(x).is_integer() and abs(x) < 1e9 else f"{x:g}"

        if self.lo is None and self.hi is None:
            return ""
        if self.lo is not None and self.hi is not None:
            return f"{'(' if self.lo_open else '['}{num(self.lo)}, {num(self.hi)}]"
        if self.lo is not None:
            return f"> {num(self.lo)}" if self.lo_open else f">= {num(self.lo)}"
        return f"<= {num(self.hi)}"  # type: ignore[arg-type]


#: marks a required key in :data:`SCHEMA`
REQUIRED = "(required)"
#: IMU rates accepted (Hz): Wang runs the INS at 1 Hz; 2 kHz is above any strapdown IMU's output rate
IMU_RATE_RANGE_HZ = (1.0, 2000.0)
#: IMU samples one run may hold (truth, ideal and corrupted IMU, the fusers' buffers: a few hundred bytes each)
MAX_IMU_SAMPLES_PER_RUN = 2e7
#: Monte Carlo runs one study may ask for
MAX_RUNS = 100_000

#: largest reading noise (1-sigma, the kind's unit) accepted per kind: above it the noise exceeds the whole signal
#: (gravity disturbances span a few hundred mGal, crustal anomalies a few thousand nT)
SENSOR_SIGMA_MAX = {
    FieldKind.GRAVITY_DISTURBANCE_MGAL: 1_000.0,
    FieldKind.TOTAL_FIELD_ANOMALY_NT: 10_000.0,
    FieldKind.VECTOR_FIELD_NT: 100_000.0,
}


SCHEMA: tuple[ScenarioKey, ...] = (
    # top level
    ScenarioKey("", "name", "string", "study name (the default output folder is runs/NAME)", REQUIRED),
    ScenarioKey("", "description", "string", "free text, copied into the report", ""),
    ScenarioKey("", "seed", "integer", "master seed; run i uses SeedSequence(seed).spawn(runs)[i]", 0, lo=0),
    ScenarioKey("", "runs", "integer", "Monte Carlo runs (--runs overrides)", 1, lo=1, hi=MAX_RUNS),
    ScenarioKey("", "trajectory", "table", "the truth trajectory", REQUIRED),
    ScenarioKey("", "imu", "table", "the IMU", REQUIRED),
    ScenarioKey("", "init", "table", "initial INS errors (1-sigma, drawn per run)", "see [init]"),
    ScenarioKey("", "map", "table", "the map the matchers use (required with any matcher)", None),
    ScenarioKey("", "sensor", "table", "the field sensor (required with any matcher)", None),
    ScenarioKey(
        "",
        "estimator",
        "array of tables",
        "the estimators ([[estimator]], one or more)",
        "none: the free-inertial baseline only",
    ),
    # [trajectory]
    ScenarioKey("trajectory", "kind", "string", "one of " + ", ".join(TRAJECTORY_KINDS), REQUIRED),
    ScenarioKey("trajectory", "start", "[lat, lon] deg", "start point", REQUIRED, kinds=("great_circle", "lawnmower")),
    ScenarioKey("trajectory", "end", "[lat, lon] deg", "end point", REQUIRED, kinds=("great_circle",)),
    ScenarioKey(
        "trajectory", "points", "[[lat, lon], ...] deg", "at least two waypoints", REQUIRED, kinds=("waypoints",)
    ),
    ScenarioKey(
        "trajectory",
        "altitude_m",
        "number",
        "ellipsoidal height, m",
        REQUIRED,
        lo=-11000.0,
        hi=1e5,
        why="from the deepest ocean to the edge of space",
        kinds=("great_circle", "waypoints", "lawnmower"),
    ),
    ScenarioKey(
        "trajectory",
        "speed_mps",
        "number",
        "ground speed, m/s",
        REQUIRED,
        lo=0.0,
        hi=3000.0,
        lo_open=True,
        why="above Mach 8 nothing navigates by maps",
        kinds=("great_circle", "waypoints", "survey_line", "lawnmower", "ground_path"),
    ),
    ScenarioKey(
        "trajectory",
        "origin",
        "[lat, lon] deg",
        "origin of a ground path's local plane",
        REQUIRED,
        kinds=("ground_path",),
    ),
    ScenarioKey(
        "trajectory",
        "points_m",
        "[[north, east], ...] m",
        "at least two corner points about the origin (a walk, a hallway route)",
        REQUIRED,
        kinds=("ground_path",),
    ),
    ScenarioKey(
        "trajectory",
        "altitude_m",
        "number",
        "ellipsoidal height of a ground path, m",
        0.0,
        lo=-11000.0,
        hi=1e5,
        why="from the deepest ocean to the edge of space",
        kinds=("ground_path",),
    ),
    ScenarioKey(
        "trajectory",
        "corner_radius_m",
        "number",
        "radius of the rounded corners, m",
        1.0,
        lo=0.0,
        kinds=("ground_path",),
    ),
    ScenarioKey(
        "trajectory",
        "wander",
        "table",
        "random walk about the path { " + ", ".join(WANDER_KEYS) + " } (magnav_ins.ins.ground_path.Wander)",
        "{}",
        kinds=("ground_path",),
    ),
    ScenarioKey(
        "trajectory", "survey", "string", "survey CSV(.xz) path or builtin:NAME", REQUIRED, kinds=("survey_line",)
    ),
    ScenarioKey(
        "trajectory",
        "line",
        "integer or list",
        "survey line id, or ids flown one after the other",
        "(line or line_type is required)",
        kinds=("survey_line",),
    ),
    ScenarioKey(
        "trajectory",
        "line_type",
        "string",
        'fly every line of this type (e.g. "TIE"), in id order (with line: those of the listed lines)',
        None,
        kinds=("survey_line",),
    ),
    ScenarioKey(
        "trajectory",
        "columns",
        "table",
        'survey column mapping { our_name = "file column" } (maps.io.SURVEY_COLUMNS)',
        None,
        kinds=("survey_line",),
    ),
    ScenarioKey(
        "trajectory",
        "geoid_m",
        "number",
        "geoid undulation for the survey's orthometric heights, m",
        "the shipped EIGEN-6C4 geoid",
        lo=-150.0,
        hi=150.0,
        why="the geoid stays within -107..+86 m of the ellipsoid",
        kinds=("survey_line",),
    ),
    ScenarioKey(
        "trajectory",
        "heading_deg",
        "number",
        "heading of the first leg, deg",
        REQUIRED,
        lo=-360.0,
        hi=360.0,
        kinds=("lawnmower",),
    ),
    ScenarioKey(
        "trajectory",
        "leg_length_m",
        "number",
        "length of each leg, m",
        REQUIRED,
        lo=0.0,
        hi=1e7,
        lo_open=True,
        kinds=("lawnmower",),
    ),
    ScenarioKey(
        "trajectory",
        "leg_spacing_m",
        "number",
        "distance between legs (the next to the right), m",
        REQUIRED,
        lo=0.0,
        hi=1e6,
        lo_open=True,
        kinds=("lawnmower",),
    ),
    ScenarioKey("trajectory", "legs", "integer", "legs per pass", REQUIRED, lo=1, hi=1e5, kinds=("lawnmower",)),
    ScenarioKey(
        "trajectory",
        "turn_rate_deg_s",
        "number",
        "turn rate between legs, deg/s",
        3.0,
        lo=0.0,
        hi=30.0,
        lo_open=True,
        why="a rate-two turn is 6 deg/s",
        kinds=("lawnmower",),
    ),
    ScenarioKey(
        "trajectory",
        "roll_time_constant_s",
        "number",
        "time constant of the roll into and out of a turn, s",
        5.0,
        lo=0.0,
        lo_open=True,
        kinds=("lawnmower",),
    ),
    ScenarioKey("trajectory", "path", "string", "trajectory CSV path", REQUIRED, kinds=("file",)),
    ScenarioKey(
        "trajectory",
        "duration_s",
        "number",
        "truncate the trajectory to this many seconds (--duration)",
        "the whole trajectory",
        lo=0.0,
        hi=1e7,
        lo_open=True,
        why="at most about 4 months",
    ),
    # [imu]
    ScenarioKey("imu", "grade", "string", "one of " + ", ".join(IMU_GRADES), REQUIRED),
    ScenarioKey(
        "imu",
        "rate_hz",
        "number",
        "IMU and INS sample rate, Hz",
        100.0,
        lo=IMU_RATE_RANGE_HZ[0],
        hi=IMU_RATE_RANGE_HZ[1],
        why="strapdown IMUs output 1 Hz (Wang) to 2 kHz",
    ),
    # [init]
    ScenarioKey(
        "init",
        "position_sigma_m",
        "number",
        "north and east position 1-sigma, m",
        10.0,
        lo=0.0,
        hi=1e5,
        why="beyond 100 km the fusers' linearisation does not hold",
    ),
    ScenarioKey("init", "velocity_sigma_mps", "number", "velocity 1-sigma per NED axis, m/s", 0.1, lo=0.0, hi=100.0),
    ScenarioKey(
        "init",
        "attitude_sigma_deg",
        "[roll, pitch, yaw] deg",
        "attitude 1-sigmas, deg",
        "[0.02, 0.02, 0.2]",
        lo=0.0,
        hi=30.0,
        why="the error model assumes small attitude errors",
    ),
    ScenarioKey(
        "init",
        "position_offset_m",
        "[north, east] m",
        "a fixed initial position error instead of a random draw (Storms Table 4.1)",
        None,
    ),
    # [map]
    ScenarioKey("map", "path", "string", "NetCDF grid, survey CSV(.xz), builtin:NAME or synthetic:NAME", REQUIRED),
    ScenarioKey("map", "kind", "string", "one of " + ", ".join(k.value for k in FieldKind), REQUIRED),
    ScenarioKey(
        "map",
        "grid_spacing_m",
        "number",
        "grid a survey CSV at this spacing on load, m",
        None,
        lo=0.0,
        hi=1e5,
        lo_open=True,
    ),
    ScenarioKey("map", "exclude_lines", "list of integers", "survey lines left out of the map", "[]"),
    ScenarioKey("map", "options", "table", "options of a synthetic map (seed, origin_deg, shape, ...)", "{}"),
    ScenarioKey("map", "columns", "table", 'survey column mapping { our_name = "file column" } (survey CSV)', None),
    ScenarioKey(
        "map",
        "geoid_m",
        "number",
        "geoid undulation for a survey's orthometric heights, m",
        "the shipped EIGEN-6C4 geoid",
        lo=-150.0,
        hi=150.0,
        why="the geoid stays within -107..+86 m of the ellipsoid",
    ),
    ScenarioKey("map", "line_type", "string", 'grid only the survey lines of this type (e.g. "LINE")', None),
    ScenarioKey("map", "exclude_line_type", "string", 'leave out the survey lines of this type (e.g. "TIE")', None),
    ScenarioKey(
        "map",
        "error_sigma",
        "number",
        "a uniform map error layer: 1-sigma map error in the map's unit",
        None,
        lo=0.0,
        lo_open=True,
    ),
    ScenarioKey(
        "map",
        "error_correlation_m",
        "number",
        "correlation length of error_sigma, m (with error_sigma)",
        None,
        lo=0.0,
        lo_open=True,
    ),
    ScenarioKey(
        "map",
        "unit",
        "string",
        "unit of a downloaded grid's values if the file states none or an impossible one (nT; mGal, um/s^2, m/s^2)",
        None,
    ),
    ScenarioKey("map", "altitude_m", "number", "ellipsoidal height of a downloaded grid's surface, m", None),
    ScenarioKey(
        "map", "datum", "string", "datum of a downloaded latitude/longitude grid that does not say (WGS84)", None
    ),
    ScenarioKey(
        "map", "crs", "string", "CRS of a downloaded grid in metres that does not say (EPSG:NNNN, PROJ, WKT)", None
    ),
    ScenarioKey("map", "variable", "string", "the data variable of a file holding several grids", None),
    ScenarioKey("map", "reproject", "boolean", "resample a projected grid onto latitude/longitude", False),
    ScenarioKey(
        "map",
        "allow_implausible",
        "boolean",
        "accept map values implausible for the map's kind (e.g. full gravity as a disturbance)",
        False,
    ),
    ScenarioKey(
        "map",
        "error_sigma",
        "number",
        "give the map a uniform error layer: 1-sigma map error in the map's unit (with error_correlation_m)",
        "the map's own layer, else the matchers' stated default",
        lo=0.0,
        lo_open=True,
    ),
    ScenarioKey(
        "map",
        "error_correlation_m",
        "number",
        "correlation length of the map error given by error_sigma, m",
        None,
        lo=0.0,
        lo_open=True,
    ),
    ScenarioKey(
        "map",
        "unit",
        "string",
        "unit of a downloaded grid's values if the file states none or a wrong one (nT; mGal, um/s^2, m/s^2)",
        None,
    ),
    ScenarioKey("map", "altitude_m", "number", "ellipsoidal height of a downloaded grid's surface, m", None),
    ScenarioKey("map", "datum", "string", "geodetic datum of a downloaded grid that does not say (WGS84)", None),
    ScenarioKey(
        "map", "crs", "string", "CRS of a downloaded grid in metres that does not say (EPSG:NNNN, PROJ or WKT)", None
    ),
    ScenarioKey("map", "variable", "string", "the data variable of a file holding several grids", None),
    ScenarioKey("map", "reproject", "boolean", "resample a projected grid onto latitude/longitude", False),
    # [sensor]
    ScenarioKey("sensor", "kind", "string", "one of " + ", ".join(SENSOR_KINDS), REQUIRED),
    ScenarioKey(
        "sensor",
        "sigma",
        "number",
        "reading noise 1-sigma, in the map's unit",
        REQUIRED,
        lo=0.0,
        lo_open=True,
        why="and at most " + ", ".join(f"{v:g} {k.unit} ({k.value})" for k, v in SENSOR_SIGMA_MAX.items()),
    ),
    ScenarioKey(
        "sensor",
        "interval_s",
        "number",
        "seconds between readings",
        REQUIRED,
        lo=0.0,
        hi=86400.0,
        lo_open=True,
        why="and at least one IMU period",
    ),
    ScenarioKey("sensor", "source", "string", "one of " + ", ".join(SENSOR_SOURCES), "simulated"),
    # [[estimator]]
    ScenarioKey("estimator", "name", "string", "unique; 'free_inertial' is reserved for the baseline", REQUIRED),
    ScenarioKey(
        "estimator",
        "matcher",
        "inline table",
        "{ kind = ..., options } (matcher kinds below)",
        "(required unless fusion is free_inertial)",
    ),
    ScenarioKey("estimator", "fusion", "inline table", "{ kind = ..., options } (fusion kinds below)", REQUIRED),
    ScenarioKey(
        "estimator",
        "window",
        "integer",
        "readings per batch-matcher window",
        "the matcher's batch, else 1",
        lo=1,
        hi=1e6,
    ),
    ScenarioKey(
        "estimator",
        "match_every",
        "integer",
        "readings between match attempts",
        "the matcher's batch, else 1",
        lo=1,
        hi=1e6,
    ),
    ScenarioKey(
        "estimator",
        "smooth",
        "integer",
        "0: the causal track; N >= 1: the smoothed track (ukf, graph)",
        0,
        lo=0,
        hi=100,
    ),
    ScenarioKey("estimator", "imu_grade", "string", "this estimator's own IMU grade", "[imu] grade"),
)


def _by_path(keys: tuple[ScenarioKey, ...]) -> dict[str, ScenarioKey]:
    """Key path -> entry. A key documented once per trajectory kind (``altitude_m``) is range-checked by the first
    of its entries that states a range."""
    out: dict[str, ScenarioKey] = {}
    for k in keys:
        old = out.get(k.path)
        if old is None or (old.lo is None and old.hi is None and (k.lo is not None or k.hi is not None)):
            out[k.path] = k
    return out


_SCHEMA_BY_PATH = _by_path(SCHEMA)


# --------------------------------------------------------------------------------------------- line scan
_HEADER = re.compile(r"^\s*(\[\[?)\s*([^\]]+?)\s*\]\]?\s*(#.*)?$")
_KEY = re.compile(r"""^\s*((?:[A-Za-z0-9_-]+|"[^"]*"|'[^']*')(?:\s*\.\s*(?:[A-Za-z0-9_-]+|"[^"]*"|'[^']*'))*)\s*=""")
_INLINE_KEY = re.compile(r"""[{,]\s*([A-Za-z0-9_-]+|"[^"]*"|'[^']*')\s*=""")


def _unquote(part: str) -> str:
    part = part.strip()
    return part[1:-1] if len(part) >= 2 and part[0] == part[-1] and part[0] in "\"'" else part


def _split_dotted(key: str) -> list[str]:
    return [_unquote(p) for p in re.findall(r"""[A-Za-z0-9_-]+|"[^"]*"|'[^']*'""", key)]


def locate_keys(text: str) -> dict[str, int]:
    """Map dotted key paths (``"trajectory.speed_mps"``, ``"estimator[1].matcher.batch"``) and table headers
    (``"trajectory"``, ``"estimator[0]"``) to 1-based line numbers in the TOML ``text``. See the module docstring."""
    lines: dict[str, int] = {}
    prefix = ""
    array_counts: dict[str, int] = {}
    depth = 0  # bracket depth of a multi-line value: keys inside are not scanned
    for n, raw in enumerate(text.splitlines(), start=1):
        line = raw
        if depth == 0:
            m = _HEADER.match(line)
            if m:
                name = ".".join(_split_dotted(m.group(2)))
                if m.group(1) == "[[":
                    idx = array_counts.get(name, 0)
                    array_counts[name] = idx + 1
                    prefix = f"{name}[{idx}]"
                else:
                    prefix = name
                lines.setdefault(prefix, n)
                continue
            m = _KEY.match(line)
            if m:
                key = ".".join(_split_dotted(m.group(1)))
                full = f"{prefix}.{key}" if prefix else key
                lines.setdefault(full, n)
                rest = line[m.end() :]
                if rest.lstrip().startswith("{"):
                    for k in _INLINE_KEY.findall(rest):
                        lines.setdefault(f"{full}.{_unquote(k)}", n)
        stripped = re.sub(r'"[^"]*"|\'[^\']*\'', "", line).split("#", 1)[0]
        depth = max(0, depth + stripped.count("[") + stripped.count("{") - stripped.count("]") - stripped.count("}"))
        if _HEADER.match(line):
            depth = 0
    return lines


# --------------------------------------------------------------------------------------------- config types
@dataclass(frozen=True)
class TrajectoryConfig:
    """Truth trajectory. Positions in degrees as written (converted to rad where the trajectory is built).

    ``kind``: ``great_circle`` (``start``, ``end`` [lat, lon] deg, ``altitude_m``, ``speed_mps``), ``waypoints``
    (``points`` [[lat, lon], ...] deg, ``altitude_m``, ``speed_mps``), ``survey_line`` (``survey`` path or
    ``builtin:NAME``, ``line`` id or list of ids, ``speed_mps``; altitude from the survey), ``file`` (``path``
    CSV), ``ground_path`` (``origin`` [lat, lon] deg, ``points_m`` [[north, east], ...] m about it,
    ``speed_mps``, optional ``altitude_m``, ``corner_radius_m`` and ``wander`` = Storms' random perturbation per run,
    :mod:`magnav_ins.ins.ground_path`). ``duration_s`` (optional) truncates the trajectory. ``lines`` holds every line id of a ``survey_line``
    flight in flying order (``line`` is the first); several lines are flown one after the other, as a survey
    aircraft flies adjacent lines (:func:`magnav_ins.studies.model.survey_line_points`). A ``survey_line`` may
    instead (or as well) name a ``line_type`` (e.g. ``"TIE"``): every line of that type, in id order (with ``line``:
    those of the listed lines); ``columns`` maps our survey column names to the file's
    (:func:`magnav_ins.maps.io.read_survey`), ``geoid_m`` replaces the shipped geoid for orthometric heights. ``lawnmower`` (``start``
    [lat, lon] deg, ``heading_deg`` of the first leg, ``leg_length_m``, ``leg_spacing_m``, ``legs``, ``altitude_m``,
    ``speed_mps``, optional ``turn_rate_deg_s``, default 3, and ``roll_time_constant_s``, default 5): parallel legs
    joined by turns, each next leg
    ``leg_spacing_m`` to the right, the pattern flown back and forth until ``duration_s``
    (:func:`magnav_ins.studies.model.lawnmower_points`): a long flight folded into one map tile.
    """

    kind: str
    start_deg: tuple[float, float] | None = None
    end_deg: tuple[float, float] | None = None
    points_deg: tuple[tuple[float, float], ...] | None = None
    altitude_m: float | None = None
    speed_mps: float | None = None
    survey: str | None = None
    line: int | None = None
    lines: tuple[int, ...] = ()
    path: str | None = None
    duration_s: float | None = None
    heading_deg: float | None = None
    leg_length_m: float | None = None
    leg_spacing_m: float | None = None
    legs: int | None = None
    turn_rate_deg_s: float | None = None
    roll_time_constant_s: float | None = None
    line_type: str | None = None
    columns: tuple[tuple[str, str], ...] = ()
    geoid_m: float | None = None
    origin_deg: tuple[float, float] | None = None
    points_m: tuple[tuple[float, float], ...] | None = None
    corner_radius_m: float = 1.0
    wander: dict[str, float] | None = field(default=None, compare=False)

    def survey_options(self) -> dict[str, Any]:
        """Keyword arguments for :func:`magnav_ins.maps.io.read_survey` (column mapping, geoid override)."""
        out: dict[str, Any] = {}
        if self.columns:
            out["columns"] = dict(self.columns)
        if self.geoid_m is not None:
            out["geoid_undulation_m"] = self.geoid_m
        return out


@dataclass(frozen=True)
class ImuConfig:
    """IMU grade (``IMU_GRADES``) and sample rate (Hz) of the simulated IMU and of the INS."""

    grade: str
    rate_hz: float = 100.0


@dataclass(frozen=True)
class InitConfig:
    """1-sigma initial INS errors drawn per run (the same draw for every estimator and the baseline).
    Defaults: a tactical INS that has just lost GNSS (DESIGN.md). ``position_offset_m`` = (north, east) m: a fixed
    initial position error instead of a drawn one (Storms Table 4.1: the filter starts 1.145 m beside the vehicle);
    ``position_sigma_m`` stays the filters' initial 1-sigma."""

    position_sigma_m: float = 10.0
    velocity_sigma_mps: float = 0.1
    attitude_sigma_deg: tuple[float, float, float] = (0.02, 0.02, 0.2)  # roll, pitch, yaw
    position_offset_m: tuple[float, float] | None = None


@dataclass(frozen=True)
class MapConfig:
    """Map spec: a NetCDF path, ``builtin:NAME``, ``synthetic:NAME`` or a survey CSV(.xz) gridded on load
    (``grid_spacing_m``, ``exclude_lines``). ``kind`` is a :class:`FieldKind` value. ``options`` holds extra
    keys for synthetic maps (e.g. ``seed``). For a survey: ``columns`` (our name -> the file's column),
    ``geoid_m`` (geoid undulation for orthometric heights; default the shipped geoid), ``line_type`` (grid only
    the lines of that type, e.g. ``"LINE"``), ``exclude_line_type`` (leave those out, e.g. ``"TIE"``). Any map:
    ``error_sigma`` (1-sigma map error, map unit) with ``error_correlation_m`` (m) gives it a uniform error layer
    (for a map that has none; it replaces one the map has). A grid file as downloaded (GeoTIFF, ER Mapper, GXF, GMT /
    COARDS / CF NetCDF; :mod:`magnav_ins.maps.formats`): ``unit`` (the values' unit if the file states none or an
    impossible one), ``altitude_m`` (ellipsoidal m), ``datum``, ``crs`` (of a grid in metres that does not say),
    ``variable``, ``reproject`` (onto latitude/longitude instead of the grid's own projection).
    ``allow_implausible``: accept values implausible for ``kind`` (:mod:`magnav_ins.core.plausibility`)."""

    path: str
    kind: FieldKind
    grid_spacing_m: float | None = None
    exclude_lines: tuple[int, ...] = ()
    options: dict[str, Any] = field(default_factory=dict, compare=False)
    columns: tuple[tuple[str, str], ...] = ()
    geoid_m: float | None = None
    line_type: str | None = None
    exclude_line_type: str | None = None
    allow_implausible: bool = False
    error_sigma: float | None = None
    error_correlation_m: float | None = None
    unit: str | None = None
    altitude_m: float | None = None
    datum: str | None = None
    crs: str | None = None
    variable: str | None = None
    reproject: bool = False
    allow_implausible: bool = False

    def grid_options(self) -> dict[str, Any]:
        """The keys of a grid file as downloaded (``unit``, ``altitude_m``, ``datum``, ``crs``, ``variable``,
        ``reproject``) as keyword arguments of :func:`magnav_ins.maps.io.load_map` (only those given)."""
        out: dict[str, Any] = {}
        for k in ("unit", "altitude_m", "datum", "crs", "variable"):
            if getattr(self, k) is not None:
                out[k] = getattr(self, k)
        if self.reproject:
            out["reproject"] = True
        return out

    def load_options(self) -> dict[str, Any]:
        """The survey keys as keyword arguments of :func:`magnav_ins.maps.io.load_map` (only those given)."""
        out: dict[str, Any] = {}
        if self.columns:
            out["columns"] = dict(self.columns)
        if self.geoid_m is not None:
            out["geoid_undulation_m"] = self.geoid_m
        if self.line_type is not None:
            out["line_type"] = self.line_type
        if self.exclude_line_type is not None:
            out["exclude_line_type"] = self.exclude_line_type
        return out


@dataclass(frozen=True)
class SensorConfig:
    """Field sensor: ``kind`` (``SENSOR_KINDS``), 1-sigma noise ``sigma`` in the map's unit, ``interval_s``
    between readings, ``source`` = ``simulated`` (map value at the truth + noise) or ``survey`` (real readings
    along the survey line, resampled to the trajectory)."""

    kind: str
    sigma: float
    interval_s: float
    source: str = "simulated"

    @property
    def field_kind(self) -> FieldKind:
        return SENSOR_KINDS[self.kind]


@dataclass(frozen=True)
class EstimatorConfig:
    """One estimator: a matcher spec (``{"kind": ..., params}``, keys checked by
    ``aiding.matchers.registry.build_matcher``), a fusion spec (``{"kind": "ukf"|"graph"|"free_inertial", options}``,
    ``aiding.fusion.make_fuser``) and the pipeline's ``window`` (readings per batch-matcher window) and
    ``match_every`` (readings between match attempts); both default to the matcher's ``batch`` when it has one
    (Wang's non-overlapping batches), else 1. ``smooth``: 0 reports the filter's causal (online) track; N >= 1
    reports a smoothed track instead, for offline studies: the UKF's Rauch-Tung-Striebel smoothed track (N passes:
    one closed-loop pass, then N - 1 relinearised ones; :meth:`magnav_ins.aiding.fusion.ukf.UkfFuser.smooth`), or
    for the graph fuser the batch Levenberg-Marquardt solution of its whole graph, whatever N >= 1
    (:meth:`magnav_ins.aiding.fusion.graph.GraphFuser.smoothed_track`). Other fusers cannot smooth.

    ``matcher`` is None for a free-inertial estimator (``fusion.kind = "free_inertial"``) without fixes: with
    ``imu_grade`` it is the free-inertial drift of another IMU grade beside the baseline (Storms Fig. 2.1).
    ``imu_grade`` (``IMU_GRADES``) gives this estimator its own IMU: the same truth and initial errors, the IMU
    corrupted with that grade's error model and the fuser using that grade's noise; None means ``[imu] grade``
    (the baseline's IMU, the same draw)."""

    name: str
    matcher: dict[str, Any] | None = field(compare=False)
    fusion: dict[str, Any] = field(compare=False)
    window: int | None = None
    match_every: int | None = None
    smooth: int = 0
    imu_grade: str | None = None

    @property
    def matcher_kind(self) -> str | None:
        return None if self.matcher is None else str(self.matcher["kind"])

    @property
    def fusion_kind(self) -> str:
        return str(self.fusion["kind"])


@dataclass(frozen=True)
class Scenario:
    """A validated scenario. ``source`` is the file it came from (None when built from a dict); ``lines`` maps
    key paths to line numbers so later stages (building matchers, loading maps) can name the line too."""

    name: str
    seed: int
    runs: int
    trajectory: TrajectoryConfig
    imu: ImuConfig
    init: InitConfig
    map: MapConfig | None
    sensor: SensorConfig | None
    estimators: tuple[EstimatorConfig, ...]
    description: str = ""
    source: Path | None = field(default=None, compare=False)
    lines: dict[str, int] = field(default_factory=dict, compare=False, repr=False)

    def where(self, key: str) -> str:
        """``"file.toml line 12 'key'"``-style prefix for error messages about ``key``."""
        return _Ctx(self.source, self.lines).where(key)


# --------------------------------------------------------------------------------------------- validation
class _Ctx:
    def __init__(self, source: Path | None, lines: dict[str, int]):
        self.source = source
        self.lines = lines

    def line_of(self, key: str) -> int | None:
        k = key
        while k:
            if k in self.lines:
                return self.lines[k]
            k = k.rsplit(".", 1)[0] if "." in k else ""
        return None

    def where(self, key: str) -> str:
        parts = [str(self.source) if self.source else "<scenario>"]
        n = self.line_of(key)
        if n is not None:
            parts.append(f"line {n}")
        return " ".join(parts) + f": '{key}'"

    def error(self, key: str, msg: str) -> ConfigError:
        return ConfigError(f"{self.where(key)}: {msg}")


def _table(ctx: _Ctx, data: dict[str, Any], key: str, required: bool = True) -> dict[str, Any] | None:
    if key not in data:
        if required:
            src = str(ctx.source) if ctx.source else "<scenario>"
            raise ConfigError(f"{src}: missing table [{key}] (required)")
        return None
    val = data[key]
    if not isinstance(val, dict):
        raise ctx.error(key, f"expected a table [{key}], got {type(val).__name__}")
    return val


def _check_keys(ctx: _Ctx, prefix: str, table: dict[str, Any], allowed: set[str], required: set[str]) -> None:
    for k in table:
        if k not in allowed:
            raise ctx.error(
                f"{prefix}.{k}" if prefix else k, f"unknown key (expected one of: {', '.join(sorted(allowed))})"
            )
    for k in sorted(required):
        if k not in table:
            where = f"{ctx.source or '<scenario>'}"
            n = ctx.line_of(prefix) if prefix else None
            loc = f"{where} line {n}" if n is not None else where
            table_name = f"[{prefix}]" if prefix else "the top level"
            raise ConfigError(f"{loc}: missing key '{prefix + '.' if prefix else ''}{k}' in {table_name} (required)")


def schema_key(key: str) -> ScenarioKey | None:
    """The :data:`SCHEMA` entry of a key path (``"estimator[2].window"`` -> the ``estimator.window`` entry)."""
    return _SCHEMA_BY_PATH.get(re.sub(r"\[\d+\]", "", key))


def _in_range(ctx: _Ctx, key: str, x: float, raw: Any) -> None:
    """The :data:`SCHEMA` range of ``key``, if it has one."""
    spec = schema_key(key)
    if spec is None or (spec.lo is None and spec.hi is None):
        return
    low = spec.lo is not None and (x <= spec.lo if spec.lo_open else x < spec.lo)
    high = spec.hi is not None and x > spec.hi
    if low or high:
        why = f": {spec.why}" if spec.why else ""
        raise ctx.error(key, f"{raw!r} is out of range; expected {spec.range_text}{why}")


def _number(ctx: _Ctx, key: str, v: Any, *, positive: bool = False, nonneg: bool = False) -> float:
    if isinstance(v, bool) or not isinstance(v, int | float):
        raise ctx.error(key, f"expected a number, got {type(v).__name__} {v!r}")
    x = float(v)
    if not math.isfinite(x):
        raise ctx.error(key, f"expected a finite number, got {v!r}")
    if positive and x <= 0:
        raise ctx.error(key, f"expected a positive number, got {v!r}")
    if nonneg and x < 0:
        raise ctx.error(key, f"expected a number >= 0, got {v!r}")
    _in_range(ctx, key, x, v)
    return x


def _int(ctx: _Ctx, key: str, v: Any, *, minimum: int | None = None) -> int:
    if isinstance(v, bool) or not isinstance(v, int):
        raise ctx.error(key, f"expected an integer, got {type(v).__name__} {v!r}")
    if minimum is not None and v < minimum:
        raise ctx.error(key, f"expected an integer >= {minimum}, got {v}")
    _in_range(ctx, key, float(v), v)
    return int(v)


def _str(ctx: _Ctx, key: str, v: Any, choices: tuple[str, ...] | None = None) -> str:
    if not isinstance(v, str):
        raise ctx.error(key, f"expected a string, got {type(v).__name__} {v!r}")
    if choices is not None and v not in choices:
        raise ctx.error(key, f"expected one of {', '.join(choices)}; got {v!r}")
    return v


def _latlon(ctx: _Ctx, key: str, v: Any) -> tuple[float, float]:
    if not isinstance(v, list) or len(v) != 2:
        raise ctx.error(key, f"expected [latitude_deg, longitude_deg], got {v!r}")
    lat = _number(ctx, key, v[0])
    lon = _number(ctx, key, v[1])
    if not -90.0 <= lat <= 90.0:
        raise ctx.error(key, f"latitude must be within [-90, 90] degrees, got {lat}")
    if not -180.0 <= lon <= 360.0:
        raise ctx.error(key, f"longitude must be within [-180, 360] degrees, got {lon}")
    return lat, lon


def _path(ctx: _Ctx, key: str, v: Any, base: Path, *, allow_spec: bool = True) -> str:
    s = _str(ctx, key, v)
    if allow_spec and s.startswith(SPEC_PREFIXES):
        return s
    p = Path(s).expanduser()
    if not p.is_absolute():
        p = base / p
    if not p.exists():
        raise ctx.error(key, f"file does not exist: {p}")
    return str(p)


_TRAJ_KEYS = {
    "great_circle": ({"start", "end", "altitude_m", "speed_mps"}, set()),
    "waypoints": ({"points", "altitude_m", "speed_mps"}, set()),
    "survey_line": ({"survey", "speed_mps"}, {"line", "line_type", "columns", "geoid_m"}),
    "file": ({"path"}, set()),
    "lawnmower": (
        {"start", "heading_deg", "leg_length_m", "leg_spacing_m", "legs", "altitude_m", "speed_mps"},
        {"turn_rate_deg_s", "roll_time_constant_s"},
    ),
    "ground_path": ({"origin", "points_m", "speed_mps"}, {"altitude_m", "corner_radius_m", "wander"}),
}


def _trajectory(ctx: _Ctx, t: dict[str, Any], base: Path) -> TrajectoryConfig:
    if "kind" not in t:
        _check_keys(ctx, "trajectory", t, set(t) | {"kind"}, {"kind"})
    kind = _str(ctx, "trajectory.kind", t["kind"], TRAJECTORY_KINDS)
    required, optional = _TRAJ_KEYS[kind]
    _check_keys(ctx, "trajectory", t, required | optional | {"kind", "duration_s"}, required)
    kw: dict[str, Any] = {"kind": kind}
    if "duration_s" in t:
        kw["duration_s"] = _number(ctx, "trajectory.duration_s", t["duration_s"], positive=True)
    if "speed_mps" in t:
        kw["speed_mps"] = _number(ctx, "trajectory.speed_mps", t["speed_mps"], positive=True)
    if "altitude_m" in t:
        kw["altitude_m"] = _number(ctx, "trajectory.altitude_m", t["altitude_m"])
    if kind == "great_circle":
        kw["start_deg"] = _latlon(ctx, "trajectory.start", t["start"])
        kw["end_deg"] = _latlon(ctx, "trajectory.end", t["end"])
        if kw["start_deg"] == kw["end_deg"]:
            raise ctx.error("trajectory.end", "end must differ from start")
    elif kind == "waypoints":
        pts = t["points"]
        if not isinstance(pts, list) or len(pts) < 2:
            raise ctx.error("trajectory.points", f"expected at least two [lat, lon] points, got {pts!r}")
        kw["points_deg"] = tuple(_latlon(ctx, "trajectory.points", p) for p in pts)
    elif kind == "survey_line":
        kw["survey"] = _path(ctx, "trajectory.survey", t["survey"], base)
        if "line" not in t and "line_type" not in t:
            n = ctx.line_of("trajectory")
            raise ConfigError(
                f"{ctx.source or '<scenario>'}{f' line {n}' if n else ''}: [trajectory] kind = 'survey_line' needs "
                "'line' (an id or a list of ids) or 'line_type' (e.g. \"TIE\": every line of that type)"
            )
        if "line" in t:
            raw = t["line"]
            ids = raw if isinstance(raw, list) else [raw]
            if not ids:
                raise ctx.error("trajectory.line", "expected a line id or a non-empty list of line ids, got []")
            kw["lines"] = tuple(_int(ctx, "trajectory.line", x) for x in ids)
            if len(set(kw["lines"])) != len(kw["lines"]):
                raise ctx.error("trajectory.line", f"a line id appears twice in {list(kw['lines'])}")
            kw["line"] = kw["lines"][0]
        if "line_type" in t:
            kw["line_type"] = _str(ctx, "trajectory.line_type", t["line_type"])
        if "columns" in t:
            kw["columns"] = _columns(ctx, "trajectory.columns", t["columns"])
        if "geoid_m" in t:
            kw["geoid_m"] = _number(ctx, "trajectory.geoid_m", t["geoid_m"])
    elif kind == "lawnmower":
        kw["start_deg"] = _latlon(ctx, "trajectory.start", t["start"])
        kw["heading_deg"] = _number(ctx, "trajectory.heading_deg", t["heading_deg"])
        kw["leg_length_m"] = _number(ctx, "trajectory.leg_length_m", t["leg_length_m"], positive=True)
        kw["leg_spacing_m"] = _number(ctx, "trajectory.leg_spacing_m", t["leg_spacing_m"], positive=True)
        kw["legs"] = _int(ctx, "trajectory.legs", t["legs"], minimum=1)
        for key in ("turn_rate_deg_s", "roll_time_constant_s"):
            if key in t:
                kw[key] = _number(ctx, f"trajectory.{key}", t[key], positive=True)
    elif kind == "ground_path":
        kw["origin_deg"] = _latlon(ctx, "trajectory.origin", t["origin"])
        pts = t["points_m"]
        if not isinstance(pts, list) or len(pts) < 2 or not all(isinstance(p, list) and len(p) == 2 for p in pts):
            raise ctx.error("trajectory.points_m", f"expected at least two [north_m, east_m] points, got {pts!r}")
        kw["points_m"] = tuple(
            (_number(ctx, "trajectory.points_m", p[0]), _number(ctx, "trajectory.points_m", p[1])) for p in pts
        )
        kw.setdefault("altitude_m", 0.0)
        if "corner_radius_m" in t:
            kw["corner_radius_m"] = _number(ctx, "trajectory.corner_radius_m", t["corner_radius_m"], nonneg=True)
        if "wander" in t:
            w = t["wander"]
            if not isinstance(w, dict):
                raise ctx.error("trajectory.wander", f"expected a table {{ accel_sigma_mps2 = ..., ... }}, got {w!r}")
            _check_keys(ctx, "trajectory.wander", w, set(WANDER_KEYS), set())
            kw["wander"] = {k: _number(ctx, f"trajectory.wander.{k}", v, nonneg=True) for k, v in w.items()}
        from ..ins.ground_path import Path2D, Wander

        try:
            Path2D.from_points(kw["points_m"], kw.get("corner_radius_m", 1.0))
            Wander(**(kw.get("wander") or {}))
        except ConfigError as exc:
            raise ctx.error("trajectory", str(exc)) from None
    else:
        kw["path"] = _path(ctx, "trajectory.path", t["path"], base, allow_spec=False)
    return TrajectoryConfig(**kw)


def _imu(ctx: _Ctx, t: dict[str, Any]) -> ImuConfig:
    _check_keys(ctx, "imu", t, {"grade", "rate_hz"}, {"grade"})
    grade = _str(ctx, "imu.grade", t["grade"], IMU_GRADES)
    rate = _number(ctx, "imu.rate_hz", t.get("rate_hz", 100.0), positive=True)
    return ImuConfig(grade, rate)


def _init(ctx: _Ctx, t: dict[str, Any] | None) -> InitConfig:
    if t is None:
        return InitConfig()
    _check_keys(
        ctx, "init", t, {"position_sigma_m", "velocity_sigma_mps", "attitude_sigma_deg", "position_offset_m"}, set()
    )
    d = InitConfig()
    pos = _number(ctx, "init.position_sigma_m", t.get("position_sigma_m", d.position_sigma_m), nonneg=True)
    vel = _number(ctx, "init.velocity_sigma_mps", t.get("velocity_sigma_mps", d.velocity_sigma_mps), nonneg=True)
    att = t.get("attitude_sigma_deg", list(d.attitude_sigma_deg))
    if not isinstance(att, list) or len(att) != 3:
        raise ctx.error("init.attitude_sigma_deg", f"expected [roll, pitch, yaw] in degrees, got {att!r}")
    att_t = tuple(_number(ctx, "init.attitude_sigma_deg", a, nonneg=True) for a in att)
    off = t.get("position_offset_m")
    if off is not None:
        if not isinstance(off, list) or len(off) != 2:
            raise ctx.error("init.position_offset_m", f"expected [north_m, east_m], got {off!r}")
        off = (_number(ctx, "init.position_offset_m", off[0]), _number(ctx, "init.position_offset_m", off[1]))
    return InitConfig(pos, vel, att_t, off)  # type: ignore[arg-type]


def _columns(ctx: _Ctx, key: str, v: Any) -> tuple[tuple[str, str], ...]:
    """A survey column mapping table ``{our name = "file column", ...}`` (``maps.io.SURVEY_COLUMNS``)."""
    from ..maps.io import SURVEY_COLUMNS

    if not isinstance(v, dict) or not v:
        raise ctx.error(key, f'expected a table like {{ height_ellipsoidal_m = "height_ell_m" }}, got {v!r}')
    out = []
    for ours, theirs in v.items():
        if ours not in SURVEY_COLUMNS:
            raise ctx.error(f"{key}.{ours}", f"not a survey column name; expected one of {', '.join(SURVEY_COLUMNS)}")
        out.append((ours, _str(ctx, f"{key}.{ours}", theirs)))
    return tuple(out)


_MAP_SURVEY_KEYS = {"columns", "geoid_m", "line_type", "exclude_line_type"}
_MAP_GRID_KEYS = {"unit", "altitude_m", "datum", "crs", "variable", "reproject"}


def _map(ctx: _Ctx, t: dict[str, Any], base: Path) -> MapConfig:
    _check_keys(
        ctx,
        "map",
        t,
        {
            "path",
            "kind",
            "grid_spacing_m",
            "exclude_lines",
            "options",
            "error_sigma",
            "error_correlation_m",
            "allow_implausible",
        }
        | _MAP_SURVEY_KEYS
        | _MAP_GRID_KEYS,
        {"path", "kind"},
    )
    path = _path(ctx, "map.path", t["path"], base)
    kind_s = _str(ctx, "map.kind", t["kind"], tuple(k.value for k in FieldKind))
    spacing = None
    if "grid_spacing_m" in t:
        spacing = _number(ctx, "map.grid_spacing_m", t["grid_spacing_m"], positive=True)
    excl = t.get("exclude_lines", [])
    if not isinstance(excl, list):
        raise ctx.error("map.exclude_lines", f"expected a list of line ids, got {excl!r}")
    excl_t = tuple(_int(ctx, "map.exclude_lines", x) for x in excl)
    opts = t.get("options", {})
    if not isinstance(opts, dict):
        raise ctx.error("map.options", f"expected a table, got {opts!r}")
    kw: dict[str, Any] = {}
    if "columns" in t:
        kw["columns"] = _columns(ctx, "map.columns", t["columns"])
    if "geoid_m" in t:
        kw["geoid_m"] = _number(ctx, "map.geoid_m", t["geoid_m"])
    for k in ("line_type", "exclude_line_type"):
        if k in t:
            kw[k] = _str(ctx, f"map.{k}", t[k])
    from ..maps.io import SURVEY_SUFFIXES

    if kw and not path.lower().endswith(SURVEY_SUFFIXES):
        k = sorted(kw)[0]
        raise ctx.error(f"map.{k}", "applies to a survey CSV map (gridded on load), not to a grid file")
    grid_kw: dict[str, Any] = {}
    for k in ("unit", "datum", "crs", "variable"):
        if k in t:
            grid_kw[k] = _str(ctx, f"map.{k}", t[k])
    if "altitude_m" in t:
        grid_kw["altitude_m"] = _number(ctx, "map.altitude_m", t["altitude_m"])
    if "reproject" in t:
        if not isinstance(t["reproject"], bool):
            raise ctx.error("map.reproject", f"expected true or false, got {t['reproject']!r}")
        grid_kw["reproject"] = t["reproject"]
    if grid_kw and (path.startswith(SPEC_PREFIXES) or path.lower().endswith(SURVEY_SUFFIXES)):
        k = sorted(grid_kw)[0]
        raise ctx.error(f"map.{k}", "applies to a grid file (GeoTIFF, ER Mapper, GXF, NetCDF), not to this map")
    kw.update(grid_kw)
    if "error_sigma" in t:
        kw["error_sigma"] = _number(ctx, "map.error_sigma", t["error_sigma"], positive=True)
        if "error_correlation_m" not in t:
            raise ctx.error("map.error_sigma", "needs error_correlation_m (m), the map error's correlation length")
    if "error_correlation_m" in t:
        if "error_sigma" not in t:
            raise ctx.error("map.error_correlation_m", "needs error_sigma (1-sigma map error in the map's unit)")
        kw["error_correlation_m"] = _number(ctx, "map.error_correlation_m", t["error_correlation_m"], positive=True)
    allow = t.get("allow_implausible", False)
    if not isinstance(allow, bool):
        raise ctx.error("map.allow_implausible", f"expected true or false, got {allow!r}")
    return MapConfig(path, FieldKind(kind_s), spacing, excl_t, dict(opts), allow_implausible=allow, **kw)


def _sensor(ctx: _Ctx, t: dict[str, Any], fmap: MapConfig, traj: TrajectoryConfig) -> SensorConfig:
    _check_keys(ctx, "sensor", t, {"kind", "sigma", "interval_s", "source"}, {"kind", "sigma", "interval_s"})
    kind = _str(ctx, "sensor.kind", t["kind"], tuple(SENSOR_KINDS))
    if SENSOR_KINDS[kind] is not fmap.kind:
        raise ctx.error(
            "sensor.kind", f"a {kind} measures {SENSOR_KINDS[kind].value} but [map] kind is {fmap.kind.value}"
        )
    sigma = _number(ctx, "sensor.sigma", t["sigma"], positive=True)
    interval = _number(ctx, "sensor.interval_s", t["interval_s"], positive=True)
    limit = SENSOR_SIGMA_MAX[SENSOR_KINDS[kind]]
    if sigma > limit:
        raise ctx.error(
            "sensor.sigma",
            f"{t['sigma']!r} {SENSOR_KINDS[kind].unit} is implausible for a {kind} (at most {limit:g}: the map's own "
            "range); is it in the map's unit?",
        )
    source = _str(ctx, "sensor.source", t.get("source", "simulated"), SENSOR_SOURCES)
    if source == "survey" and traj.kind != "survey_line":
        raise ctx.error(
            "sensor.source", f"source = 'survey' needs [trajectory] kind = 'survey_line', got {traj.kind!r}"
        )
    return SensorConfig(kind, sigma, interval, source)


def _spec(ctx: _Ctx, key: str, v: Any) -> dict[str, Any]:
    if not isinstance(v, dict):
        raise ctx.error(key, f'expected a table like {{ kind = "...", ... }}, got {v!r}')
    if "kind" not in v:
        raise ctx.error(key, "missing key 'kind'")
    _str(ctx, f"{key}.kind", v["kind"])
    return dict(v)


def _check_matcher(ctx: _Ctx, key: str, spec: dict[str, Any]) -> None:
    """Kind and keys against ``aiding.matchers.registry`` (so the error names the key's line), then a trial
    build for the value types."""
    from ..aiding.matchers import registry

    if spec["kind"] not in registry.KINDS:
        raise ctx.error(f"{key}.kind", f"unknown matcher {spec['kind']!r}; expected one of {sorted(registry.KINDS)}")
    allowed = set(registry.matcher_keys(spec["kind"]))
    for k in spec:
        if k != "kind" and k not in allowed:
            raise ctx.error(
                f"{key}.{k}", f"unknown key for matcher {spec['kind']!r}; expected one of {sorted(allowed)}"
            )
    try:
        registry.build_matcher(spec)
    except ConfigError as exc:
        raise ctx.error(key, str(exc)) from None


def _check_fusion(ctx: _Ctx, key: str, spec: dict[str, Any]) -> None:
    from ..aiding.fusion import FUSER_KINDS, FUSER_OPTIONS, check_fusion_options

    if spec["kind"] not in FUSER_KINDS:
        raise ctx.error(f"{key}.kind", f"unknown fusion {spec['kind']!r}; expected one of {', '.join(FUSER_KINDS)}")
    opts = {k: v for k, v in spec.items() if k != "kind"}
    for k in opts:
        if k not in FUSER_OPTIONS[spec["kind"]]:
            raise ctx.error(f"{key}.{k}", f"unknown key for fusion {spec['kind']!r}; expected one of "
                            f"{sorted(FUSER_OPTIONS[spec['kind']])}")  # fmt: skip
    try:
        check_fusion_options(spec["kind"], opts)
    except ConfigError as exc:
        raise ctx.error(key, str(exc)) from None


def _estimators(ctx: _Ctx, data: dict[str, Any]) -> tuple[EstimatorConfig, ...]:
    ests = data.get("estimator", [])
    if not isinstance(ests, list):
        raise ctx.error("estimator", "expected one or more [[estimator]] tables")
    out: list[EstimatorConfig] = []
    seen: set[str] = set()
    for i, e in enumerate(ests):
        p = f"estimator[{i}]"
        if not isinstance(e, dict):
            raise ctx.error(p, "expected an [[estimator]] table")
        free = isinstance(e.get("fusion"), dict) and e["fusion"].get("kind") == FREE_INERTIAL
        _check_keys(
            ctx,
            p,
            e,
            {"name", "matcher", "fusion", "window", "match_every", "smooth", "imu_grade"},
            {"name", "fusion"} if free else {"name", "matcher", "fusion"},
        )
        name = _str(ctx, f"{p}.name", e["name"])
        if not name or name == FREE_INERTIAL:
            raise ctx.error(f"{p}.name", f"{name!r} is reserved or empty; the {FREE_INERTIAL} baseline is always added")
        if name in seen:
            raise ctx.error(f"{p}.name", f"duplicate estimator name {name!r}")
        seen.add(name)
        win = _int(ctx, f"{p}.window", e["window"], minimum=1) if "window" in e else None
        every = _int(ctx, f"{p}.match_every", e["match_every"], minimum=1) if "match_every" in e else None
        matcher = None
        if "matcher" in e:
            matcher = _spec(ctx, f"{p}.matcher", e["matcher"])
            _check_matcher(ctx, f"{p}.matcher", matcher)
        else:
            for k in ("window", "match_every"):
                if k in e:
                    raise ctx.error(f"{p}.{k}", f"'{k}' needs a matcher; estimator {name!r} has none")
        fusion = _spec(ctx, f"{p}.fusion", e["fusion"])
        _check_fusion(ctx, f"{p}.fusion", fusion)
        smooth = _int(ctx, f"{p}.smooth", e["smooth"], minimum=0) if "smooth" in e else 0
        if smooth and fusion["kind"] not in ("ukf", "graph"):
            raise ctx.error(
                f"{p}.smooth",
                "smoothing is offered by the ukf (N Rauch-Tung-Striebel passes) and graph (batch Levenberg-Marquardt "
                f"solution, any N >= 1) fusers only, not {fusion['kind']!r}",
            )
        grade = _str(ctx, f"{p}.imu_grade", e["imu_grade"], IMU_GRADES) if "imu_grade" in e else None
        out.append(EstimatorConfig(name, matcher, fusion, win, every, smooth, grade))
    return tuple(out)


def estimated_duration_s(traj: TrajectoryConfig) -> float | None:
    """Flight time (s) of a great-circle or waypoint trajectory from its length on a sphere of the Earth's mean radius
    and its speed (capped by ``duration_s``); None when only the data tell (survey lines, files)."""
    if traj.kind == "great_circle" and traj.start_deg and traj.end_deg:
        pts = [traj.start_deg, traj.end_deg]
    elif traj.kind == "waypoints" and traj.points_deg:
        pts = list(traj.points_deg)
    else:
        return traj.duration_s
    length = 0.0
    for (la0, lo0), (la1, lo1) in zip(pts[:-1], pts[1:], strict=True):
        p0, p1, dl = math.radians(la0), math.radians(la1), math.radians(lo1 - lo0)
        c = math.sin(p0) * math.sin(p1) + math.cos(p0) * math.cos(p1) * math.cos(dl)
        length += _MEAN_EARTH_RADIUS_M * math.acos(max(-1.0, min(1.0, c)))
    t = length / traj.speed_mps if traj.speed_mps else math.inf
    return min(t, traj.duration_s) if traj.duration_s is not None else t


#: mean Earth radius (IUGG), m: only for the size estimate of :func:`estimated_duration_s`
_MEAN_EARTH_RADIUS_M = 6_371_008.8


def _check_sizes(ctx: _Ctx, traj: TrajectoryConfig, imu: ImuConfig, sensor: SensorConfig | None) -> None:
    """Cross-key limits: a reading interval of at least one IMU period, and at most
    :data:`MAX_IMU_SAMPLES_PER_RUN` IMU samples per run (memory), naming the keys to change."""
    if sensor is not None and sensor.interval_s * imu.rate_hz < 1.0 - 1e-9:
        raise ctx.error(
            "sensor.interval_s",
            f"{sensor.interval_s:g} s is shorter than one IMU period (1 / rate_hz = {1.0 / imu.rate_hz:g} s)",
        )
    dur = estimated_duration_s(traj)
    if dur is not None and dur * imu.rate_hz > MAX_IMU_SAMPLES_PER_RUN:
        raise ctx.error(
            "imu.rate_hz",
            f"{imu.rate_hz:g} Hz over the {dur:.4g} s trajectory is {dur * imu.rate_hz:.3g} IMU samples per run, more "
            f"than {MAX_IMU_SAMPLES_PER_RUN:.0e} (memory); lower rate_hz or set [trajectory] duration_s",
        )


_TOP_KEYS = {"name", "description", "seed", "runs", "trajectory", "imu", "init", "map", "sensor", "estimator"}


def scenario_from_dict(
    data: dict[str, Any], source: Path | None = None, lines: dict[str, int] | None = None
) -> Scenario:
    """Validate a parsed scenario (the dict tomllib returns). Relative paths resolve against ``source``'s folder."""
    ctx = _Ctx(source, lines or {})
    base = source.parent if source is not None else Path.cwd()
    # [map] and [sensor] may be left out only by a free-inertial study (no [[estimator]] with a matcher)
    ests_raw = data.get("estimator")
    matched = isinstance(ests_raw, list) and any(not isinstance(e, dict) or "matcher" in e for e in ests_raw)
    need = {"name", "trajectory", "imu"} | ({"map", "sensor"} if matched else set())
    _check_keys(ctx, "", data, _TOP_KEYS, need)
    name = _str(ctx, "name", data["name"])
    description = _str(ctx, "description", data.get("description", ""))
    seed = _int(ctx, "seed", data.get("seed", 0), minimum=0)
    runs = _int(ctx, "runs", data.get("runs", 1), minimum=1)
    traj = _trajectory(ctx, _table(ctx, data, "trajectory"), base)  # type: ignore[arg-type]
    imu = _imu(ctx, _table(ctx, data, "imu"))  # type: ignore[arg-type]
    init = _init(ctx, _table(ctx, data, "init", required=False))
    fmap = _map(ctx, _table(ctx, data, "map"), base) if "map" in data else None  # type: ignore[arg-type]
    sensor = None
    if "sensor" in data:
        if fmap is None:
            raise ctx.error("sensor", "a [sensor] needs a [map] to read from")
        sensor = _sensor(ctx, _table(ctx, data, "sensor"), fmap, traj)  # type: ignore[arg-type]
    ests = _estimators(ctx, data)
    _check_sizes(ctx, traj, imu, sensor)
    return Scenario(name, seed, runs, traj, imu, init, fmap, sensor, ests, description, source, dict(ctx.lines))


def load_scenario(path: str | Path) -> Scenario:
    """Read and validate a scenario TOML file. Raises :class:`ConfigError` naming the file, line and key."""
    path = Path(path)
    if path.is_dir():
        raise ConfigError(f"{path}: is a folder; expected a scenario file (TOML)")
    if not path.is_file():
        raise ConfigError(f"{path}: scenario file does not exist")
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the scenario file ({exc.strerror or exc})") from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = raw[: exc.start].count(b"\n") + 1
        raise ConfigError(
            f"{path} line {line}: not a text file (byte {exc.start} is not UTF-8); expected TOML"
        ) from None
    if "\x00" in text:
        line = text[: text.index("\x00")].count("\n") + 1
        raise ConfigError(f"{path} line {line}: not a text file (it holds a NUL byte); expected TOML")
    if not text.strip():
        raise ConfigError(f"{path}: the scenario file is empty")
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from None
    return scenario_from_dict(data, path.resolve(), locate_keys(text))
