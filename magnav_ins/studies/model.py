"""The study model built from a scenario: truth, IMU errors, initial errors, readings, estimators, per run.

Per run (seed sequence ``ss``, see :mod:`.runner`), three independent generators are derived without mutating
``ss``: ``child(ss, 0)`` draws the IMU errors (``ins.imu_models.corrupt``), ``child(ss, 1)`` the initial INS errors,
``child(ss, 2)`` the sensor noise; ``child(ss, 10 + j)`` is handed to estimator ``j`` (for randomised matchers);
``child(ss, 3)`` draws the run's own truth where the trajectory wanders (a ``ground_path`` with ``wander``: Storms'
random trajectories, then the ideal IMU is computed per run).
An estimator with its own ``imu_grade`` other than ``[imu] grade`` flies an IMU corrupted with that grade's errors
drawn from :func:`grade_seed` (``child(child(ss, 0), crc32(grade))``): derived from the run's seed and the grade's
name only, so estimators of one grade share one draw and results do not depend on the estimator order or ``--jobs``.
The truth trajectory, the ideal IMU and the map are deterministic and shared by all runs; they are built once per
process and memoised (keyed by the scenario) so parallel workers do not rebuild them for every run.

Every estimator and the free-inertial baseline (``aiding.fusion`` kind ``free_inertial``: the same INS with its
covariance, no fixes) run through :class:`magnav_ins.pipeline.Pipeline` on the same corrupted IMU (or their own
grade's), perturbed initial state and readings, with the vertical channel held at the initial height
(``altitude_hold``; a barometric aid - an unaided vertical channel diverges within minutes; the graph fuser, which has
no clamp, takes the held height with every fix as a loose pseudo-measurement; keyframes every
``GRAPH_KEYFRAME_RAD`` of rotation).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ..core.errors import ConfigError, MagnavError
from ..core.frames import euler_from_q_nb, meters_to_latlon, q_nb_from_euler
from ..core.types import LAYOUT_15, FieldKind, FieldReadings, NavEstimate, NavState, NavTrajectory
from ..core.units import DEG_TO_RAD
from .runner import EstimatorOutput, RunOutput
from .scenario import FREE_INERTIAL, Scenario

_SHARED: dict[str, dict[str, Any]] = {}
_SHARED_MAX = 2
#: surveys (:func:`_read_survey`) and maps (:func:`_shared_map`) memoised per process by what they are read from:
#: every run re-reads its readings' survey line, every case its survey, and cases differing only in speed share a map
_SURVEYS: dict[str, Any] = {}
_SURVEYS_MAX = 2
_MAPS: dict[str, Any] = {}
_MAPS_MAX = 2


def _file_stamp(path: Any) -> tuple[int, int] | None:
    """``(mtime_ns, size)`` of a file path (None for ``builtin:`` / ``synthetic:`` names or no such file), so a
    memo keyed by a path is not served after the file changed."""
    from pathlib import Path

    try:
        st = Path(str(path)).stat()
    except (OSError, ValueError):
        return None
    return (st.st_mtime_ns, st.st_size)


def _memo(cache: dict[str, Any], limit: int, key: str, make: Any) -> Any:
    """``cache[key]``, made by ``make()`` on a miss; the oldest entry is dropped beyond ``limit``."""
    if key not in cache:
        value = make()
        if len(cache) >= limit:
            cache.pop(next(iter(cache)))
        cache[key] = value
    return cache[key]


def child(ss: np.random.SeedSequence, k: int) -> np.random.SeedSequence:
    """The ``k``-th child of ``ss`` without mutating it (``ss.spawn`` would advance its counter)."""
    return np.random.SeedSequence(ss.entropy, spawn_key=(*ss.spawn_key, k), pool_size=ss.pool_size)


def grade_seed(ss: np.random.SeedSequence, grade: str, baseline: str) -> np.random.SeedSequence:
    """Seed of the IMU-error draw of ``grade`` (an ``IMU_GRADES`` name) in the run seeded by ``ss``: the baseline's
    ``child(ss, 0)`` for the ``[imu] grade`` ``baseline``, else ``child(child(ss, 0), crc32(grade))`` - a function of
    the run seed and the grade's name only (CRC-32 is stable across processes, unlike ``hash``)."""
    import zlib

    c = child(ss, 0)
    return c if grade == baseline else child(c, zlib.crc32(grade.encode("utf-8")))


# ------------------------------------------------------------------------------------------------ truth & map
def build_truth(sc: Scenario) -> NavTrajectory:
    """The truth trajectory of ``sc`` at the IMU rate (``ins.simulate``), truncated to ``duration_s``."""
    from ..ins import simulate

    tr = sc.trajectory
    rate = sc.imu.rate_hz
    try:
        if tr.kind == "great_circle":
            (la0, lo0), (la1, lo1) = tr.start_deg, tr.end_deg  # type: ignore[misc]
            traj = simulate.great_circle(
                la0 * DEG_TO_RAD,
                lo0 * DEG_TO_RAD,
                la1 * DEG_TO_RAD,
                lo1 * DEG_TO_RAD,
                tr.altitude_m,
                tr.speed_mps,
                rate,
            )
        elif tr.kind == "waypoints":
            pts = np.array([(la * DEG_TO_RAD, lo * DEG_TO_RAD, tr.altitude_m) for la, lo in tr.points_deg])  # type: ignore[union-attr]
            traj = simulate.waypoints(pts, tr.speed_mps, rate)
        elif tr.kind == "ground_path":
            traj = ground_path_truth(sc)
        elif tr.kind == "survey_line":
            line = survey_line_points(sc)
            if len(np.unique(line["line"])) > 1:
                lat, lon, h = _with_run_ins(line, SURVEY_RUN_IN_M)
                traj = simulate.survey_line(lat, lon, h, tr.speed_mps, rate, turn_rate=SURVEY_TURN_RATE)
            else:
                traj = simulate.survey_line(line["lat"], line["lon"], line["h"], tr.speed_mps, rate)
        elif tr.kind == "lawnmower":
            turn = (tr.turn_rate_deg_s or LAWNMOWER_TURN_RATE_DEG_S) * DEG_TO_RAD
            tau = tr.roll_time_constant_s or LAWNMOWER_ROLL_TIME_CONSTANT_S
            traj = simulate.waypoints(
                lawnmower_points(tr), tr.speed_mps, rate, turn_rate=turn, roll_time_constant_s=tau
            )  # type: ignore[arg-type]
        else:
            traj = simulate.trajectory_from_csv(tr.path)  # type: ignore[arg-type]
    except MagnavError as exc:
        raise ConfigError(f"{sc.where('trajectory')}: {exc}") from None
    if tr.duration_s is not None:
        n = int(np.searchsorted(traj.t, traj.t[0] + tr.duration_s, side="right"))
        traj = traj.slice(0, max(n, 2))
    return traj


def ground_path_truth(sc: Scenario, rng: np.random.Generator | None = None) -> NavTrajectory:
    """A ``ground_path`` trajectory (:func:`magnav_ins.ins.ground_path.ground_path`): the nominal path, or with
    ``rng`` and a ``wander`` table one of Storms' random trajectories about it (drawn per run)."""
    from ..ins.ground_path import Wander, ground_path

    tr = sc.trajectory
    la, lo = tr.origin_deg  # type: ignore[misc]
    origin = (la * DEG_TO_RAD, lo * DEG_TO_RAD, float(tr.altitude_m or 0.0))
    wander = Wander(**tr.wander) if (tr.wander is not None and rng is not None) else None
    return ground_path(
        tr.points_m,  # type: ignore[arg-type]
        tr.speed_mps,  # type: ignore[arg-type]
        sc.imu.rate_hz,
        origin,
        corner_radius_m=tr.corner_radius_m,
        wander=wander,
        rng=rng,
    )


#: default turn rate of a lawnmower flight between legs (deg/s; 3 deg/s = a rate-one turn)
LAWNMOWER_TURN_RATE_DEG_S = 3.0
#: default roll time constant of a lawnmower flight (s): a bank change of a large aircraft. With the 1 s of
#: ``simulate.waypoints``' default, an INS sampled at 1-2 Hz cannot follow the roll-in of the turns: an ideal IMU at
#: 1 Hz mechanised along the QLD flight ends 750 m off after 6000 s (2 Hz: 130 m); with 5 s, 83 m (2 Hz: 11 m)
LAWNMOWER_ROLL_TIME_CONSTANT_S = 5.0


def lawnmower_points(tr: Any) -> np.ndarray:
    """Corner points ``(N, 3)`` (lat, lon rad, h m) of a ``lawnmower`` trajectory: ``legs`` parallel legs of
    ``leg_length_m`` starting at ``start_deg`` along ``heading_deg`` (clockwise from north), each next leg
    ``leg_spacing_m`` to the right of the previous one and flown the other way; the pattern is then flown back
    (legs in reverse order) and again, as many times as ``duration_s`` at ``speed_mps`` needs (one pass without a
    duration). Offsets are laid out on the local tangent plane of the start point (flat-Earth: the tile is small)."""
    from ..core.frames import meters_to_latlon

    lat0, lon0 = (x * DEG_TO_RAD for x in tr.start_deg)
    psi = float(tr.heading_deg) * DEG_TO_RAD
    u = np.array([np.cos(psi), np.sin(psi)])  # along the first leg (north, east)
    r = np.array([-u[1], u[0]])  # to its right
    L, S, n = float(tr.leg_length_m), float(tr.leg_spacing_m), int(tr.legs)
    one = []
    for k in range(n):
        a, b = k * S * r, k * S * r + L * u
        one += [a, b] if k % 2 == 0 else [b, a]
    one = np.array(one)
    seq = [one]
    length = float(np.sum(np.hypot(*np.diff(one, axis=0).T)))
    if tr.duration_s is not None and length > 0:
        passes = int(np.ceil(tr.duration_s * tr.speed_mps / length)) + 1
        for p in range(1, passes):
            seq.append(one[::-1][1:] if p % 2 else one[1:])
    ne = np.concatenate(seq)
    dlat, dlon = meters_to_latlon(ne[:, 0], ne[:, 1], lat0, tr.altitude_m)
    return np.column_stack([lat0 + dlat, lon0 + dlon, np.full(len(ne), float(tr.altitude_m))])


#: a several-line survey flight overshoots each line end by this much (m) before turning onto the next line
SURVEY_RUN_IN_M = 1000.0
#: turn rate between lines of a several-line survey flight (rad/s; 6 deg/s = a rate-two turn: a 670 m radius at
#: 70 m/s, so the aircraft can reverse onto a line 2 km away)
SURVEY_TURN_RATE = 6.0 * DEG_TO_RAD


def _with_run_ins(line: dict[str, np.ndarray], run_in_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The flight polyline of a several-line survey: each line extended by ``run_in_m`` (m) straight ahead before
    its first and after its last point, so turns happen off the line. Returns ``lat``, ``lon`` (rad), ``h`` (m)."""
    from ..core.frames import latlon_to_meters, meters_to_latlon

    lat, lon, h, ids = line["lat"], line["lon"], line["h"], line["line"]
    out: list[tuple[float, float, float]] = []
    starts = np.flatnonzero(np.r_[True, ids[1:] != ids[:-1]])
    ends = np.r_[starts[1:], len(ids)]
    for a, b in zip(starts, ends, strict=True):
        dn, de = latlon_to_meters(lat[b - 1] - lat[a], lon[b - 1] - lon[a], lat[a])
        u = np.array([dn, de]) / max(float(np.hypot(dn, de)), 1e-9)  # along-line unit vector (north, east)
        before = meters_to_latlon(-run_in_m * u[0], -run_in_m * u[1], lat[a], h[a])
        after = meters_to_latlon(run_in_m * u[0], run_in_m * u[1], lat[b - 1], h[b - 1])
        out.append((float(lat[a] + before[0]), float(lon[a] + before[1]), float(h[a])))
        out.extend(zip(lat[a:b], lon[a:b], h[a:b], strict=True))
        out.append((float(lat[b - 1] + after[0]), float(lon[b - 1] + after[1]), float(h[b - 1])))
    arr = np.array(out, dtype=float)
    return arr[:, 0], arr[:, 1], arr[:, 2]


def survey_line_points(sc: Scenario) -> dict[str, np.ndarray]:
    """The survey line(s) ``[trajectory] line`` of ``survey`` as one polyline to fly: ``lat``, ``lon`` (rad),
    ``h`` (m), ``value`` (map unit) and ``line`` (the id of each point).

    One line comes in recorded (along-line) order (``maps.io.read_survey_line``). Several lines are flown one after
    the other in the order given, each in the direction whose start is nearer the previous line's end (a survey
    aircraft flies adjacent lines back and forth); the legs between lines have no survey points, so no readings."""
    from ..core.frames import latlon_to_meters
    from ..maps import io as maps_io

    tr = sc.trajectory
    try:
        survey = _read_survey(tr.survey, tr.survey_options())  # type: ignore[arg-type]
    except MagnavError as exc:
        raise ConfigError(f"{sc.where('trajectory.survey')}: {exc}") from None
    ids: tuple[int, ...] = tr.lines or ((tr.line,) if tr.line is not None else ())
    if tr.line_type is not None:
        try:
            of_type = survey.ids_of_type(tr.line_type)
        except MagnavError as exc:
            raise ConfigError(f"{sc.where('trajectory.line_type')}: {exc}") from None
        if ids:  # both given: the listed lines, which must be of that type
            wrong = [i for i in ids if i not in of_type]
            if wrong:
                raise ConfigError(f"{sc.where('trajectory.line')}: lines {wrong} are not of line_type {tr.line_type!r}")
        else:
            ids = tuple(of_type)
    parts: list[dict[str, np.ndarray]] = []
    for ln in ids:
        try:
            p = maps_io.survey_line(survey, ln)
        except MagnavError as exc:
            raise ConfigError(f"{sc.where('trajectory.line')}: {exc}") from None
        if parts:
            end_lat, end_lon = float(parts[-1]["lat"][-1]), float(parts[-1]["lon"][-1])
            to_start = np.hypot(*latlon_to_meters(p["lat"][0] - end_lat, p["lon"][0] - end_lon, end_lat))
            to_end = np.hypot(*latlon_to_meters(p["lat"][-1] - end_lat, p["lon"][-1] - end_lon, end_lat))
            if to_end < to_start:
                p = {k: v[::-1] for k, v in p.items()}
        p["line"] = np.full(len(p["lat"]), int(ln), dtype=np.int64)
        parts.append(p)
    return {k: np.concatenate([p[k] for p in parts]) for k in ("lat", "lon", "h", "value", "line")}


def _read_survey(path: str, options: dict[str, Any]) -> Any:
    """``maps.io.read_survey(path, **options)``, memoised per process by the path, the options and the file's stamp
    (parsing a survey file was most of a run's set-up: the truth and every run's readings read their line from it).
    The :class:`~magnav_ins.maps.survey.Survey` is shared: callers select from it (copies), never write to it."""
    from ..maps import io as maps_io

    key = repr((path, options, _file_stamp(path)))
    return _memo(_SURVEYS, _SURVEYS_MAX, key, lambda: maps_io.read_survey(path, **options))


#: ``[map] options`` that select :func:`magnav_ins.studies.grids.read_gravity_grid` (a downloaded gravity grid read
#: with an explicit unit and optionally continued upward) instead of ``maps.io.load_map``
GRID_OPTIONS = frozenset({"unit", "continue_to_m", "variable"})


def build_map(sc: Scenario) -> Any:
    """The scenario's map: ``synthetic:random_field`` / ``synthetic:hallway`` (``maps.synthetic``, drawn from
    ``[map] options.seed``), a downloaded gravity grid when the options hold any of :data:`GRID_OPTIONS`
    (:func:`magnav_ins.studies.grids.read_gravity_grid`: ``unit``, ``altitude_m``, ``datum``, ``variable``,
    ``continue_to_m``), else ``maps.io.load_map`` (NetCDF, ``builtin:NAME``, survey gridded on load). Options
    ``error_sigma`` (map unit) and ``error_correlation_m`` (m, default two node spacings) attach a uniform error layer
    (``GridMap.with_error_layer``): 0 when the study draws its readings from the map itself. Option ``level_sigma``
    (map unit, >= 0) states the 1-sigma of a constant level offset between the readings and the map
    (``metadata["level_sigma"]``, read by :func:`magnav_ins.aiding.matchers.map_error.resolve_level`); a map stated
    exact (``error_sigma = 0``) has no level offset either, unless ``level_sigma`` says otherwise."""
    m = sc.map
    if m is None:
        raise ConfigError(f"{sc.source}: the scenario has no [map]")
    opts = dict(m.options)
    if m.path.startswith("synthetic:"):
        from ..maps import synthetic

        which = m.path.split(":", 1)[1]
        rng = np.random.default_rng(int(opts.pop("seed", 0)))
        o = opts.pop("origin_deg", None)
        if o is None:
            raise ConfigError(f"{sc.where('map.options')}: synthetic maps need options.origin_deg = [lat, lon, h]")
        origin = (o[0] * DEG_TO_RAD, o[1] * DEG_TO_RAD, float(o[2]))
        try:
            if which == "hallway":
                return synthetic.hallway_map(rng, origin=origin, **opts)
            if which in ("random_field", "road_network"):
                streets_n = opts.pop("streets_north_m", None)
                streets_e = opts.pop("streets_east_m", None)
                step = float(opts.pop("step_m", 1.0))
                max_dist = float(opts.pop("max_distance_m", 5.0))
                shape = tuple(opts.pop("shape", (200, 200)))
                grid = synthetic.random_field_map(
                    shape,  # type: ignore[arg-type]
                    float(opts.pop("spacing_m", 100.0)),
                    float(opts.pop("correlation_length_m", 1000.0)),
                    float(opts.pop("sigma", 10.0)),
                    rng,
                    kind=m.kind,
                    origin=origin,
                    altitude_m=float(opts.pop("altitude_m", origin[2])),
                )
                if opts:
                    raise TypeError(f"unknown options {sorted(opts)}")
                if which == "random_field":  # the readings are drawn from it: the map is exact (map_error.py)
                    exact = grid.with_error_layer(0.0, grid.metadata["correlation_length_m"], "synthetic: exact")
                    exact.metadata.update(level_sigma=0.0, level_sigma_source="synthetic: readings drawn from the map")
                    return exact
                from ..maps.track import road_network_from_grid

                # a street grid sampled every step_m along streets at the given northings / eastings (m)
                return road_network_from_grid(grid, streets_n or [], streets_e or [], step, max_distance_m=max_dist)
        except TypeError as exc:
            raise ConfigError(f"{sc.where('map.options')}: {exc}") from None
        raise ConfigError(
            f"{sc.where('map.path')}: unknown synthetic map {which!r} (hallway, random_field, road_network)"
        )
    from ..maps import io as maps_io

    err_sigma = opts.pop("error_sigma", None)
    err_corr = opts.pop("error_correlation_m", None)
    level_sigma = opts.pop("level_sigma", None)
    try:
        if GRID_OPTIONS & set(opts):  # a downloaded gravity grid with an explicit unit (studies.grids)
            from .grids import read_gravity_grid

            if m.kind is not FieldKind.GRAVITY_DISTURBANCE_MGAL:
                raise ConfigError(
                    f"{sc.where('map.options')}: options {sorted(GRID_OPTIONS & set(opts))} read gravity grids; "
                    f"[map] kind is {m.kind.value}"
                )
            try:
                fmap = read_gravity_grid(m.path, kind=m.kind, **opts)
            except TypeError as exc:
                raise ConfigError(f"{sc.where('map.options')}: {exc}") from None
            if m.error_sigma is not None:
                fmap = maps_io.attach_error_layer(fmap, m.error_sigma, m.error_correlation_m, where=m.path)
        else:
            if m.path.lower().endswith(maps_io.SURVEY_SUFFIXES):
                opts = {"kind": m.kind, **m.load_options(), **opts}
            elif not m.path.startswith("builtin:"):  # a grid file: [map] kind says what a downloaded grid holds
                opts = {"kind": m.kind, **m.grid_options(), **opts}
            if (
                m.error_sigma is not None
            ):  # the user's uniform layer (a survey is then gridded without cross-validation)
                opts = {"error_sigma": m.error_sigma, "error_correlation_m": m.error_correlation_m, **opts}
            fmap = maps_io.load_map(
                m.path, grid_spacing_m=m.grid_spacing_m, exclude_lines=list(m.exclude_lines) or None, **opts
            )
    except MagnavError as exc:
        if isinstance(exc, ConfigError):
            raise
        raise ConfigError(f"{sc.where('map.path')}: {exc}") from None
    if fmap.kind is not m.kind:
        raise ConfigError(f"{sc.where('map.kind')}: the map holds {fmap.kind.value}, the scenario says {m.kind.value}")
    if err_sigma is not None:  # a stated error layer (e.g. 0 when the study draws its readings from this very map)
        try:
            corr = float(err_corr) if err_corr is not None else 2.0 * float(min(fmap.spacing_m))
            fmap = fmap.with_error_layer(float(err_sigma), corr, "stated in the scenario's [map] options")
        except (MagnavError, TypeError, ValueError) as exc:
            raise ConfigError(f"{sc.where('map.options')}: error_sigma / error_correlation_m: {exc}") from None
    return _with_level(sc, fmap, level_sigma, err_sigma)


def _with_level(sc: Scenario, fmap: Any, level_sigma: Any, err_sigma: Any) -> Any:
    """``fmap`` (a copy) stating its level prior: the scenario's ``level_sigma`` option (map unit, >= 0), else 0
    when the scenario states the map exact (``error_sigma = 0``: the readings are drawn from this very map, so they
    carry no level offset); unchanged otherwise (the map's own level prior or the matchers' stated default)."""
    source = "stated in the scenario's [map] options"
    if level_sigma is None and err_sigma is not None and float(err_sigma) == 0.0:
        level_sigma, source = 0.0, "the map is stated exact (error_sigma = 0): the readings carry no level offset"
    if level_sigma is None:
        return fmap
    try:
        value = float(level_sigma)
    except (TypeError, ValueError):
        value = float("nan")
    if not (np.isfinite(value) and value >= 0.0):
        raise ConfigError(
            f"{sc.where('map.options')}: level_sigma must be a number >= 0 (map unit), got {level_sigma!r}"
        )
    if not hasattr(fmap, "with_values"):
        raise ConfigError(f"{sc.where('map.options')}: level_sigma applies to a gridded map, not {type(fmap).__name__}")
    out = fmap.with_values(fmap.values)  # a copy: a loaded map may be shared between studies
    out.metadata.update(level_sigma=value, level_sigma_source=source)
    return out


def _shared(sc: Scenario) -> dict[str, Any]:
    key = repr(sc) + repr([e.matcher for e in sc.estimators]) + repr(sc.map.options if sc.map else None)
    if key not in _SHARED:
        from ..ins.simulate import ideal_imu

        truth = build_truth(sc)
        if len(_SHARED) >= _SHARED_MAX:
            _SHARED.pop(next(iter(_SHARED)))
        _SHARED[key] = {"truth": truth, "imu": ideal_imu(truth), "map": _shared_map(sc) if sc.map else None}
    return _SHARED[key]


def _shared_map(sc: Scenario) -> Any:
    """:func:`build_map`, memoised per process by the ``[map]`` table (and the file's stamp): scenarios differing
    only in trajectory or speed (the suite's cases of one line) share one map instead of gridding it again. The map
    was already shared by every run of a scenario; nothing downstream writes to it (``_with_level`` copies)."""
    return _memo(_MAPS, _MAPS_MAX, repr((sc.map, sc.map.options, _file_stamp(sc.map.path))), lambda: build_map(sc))


# ------------------------------------------------------------------------------------------------ per-run draws
def perturbed_init(sc: Scenario, truth: NavTrajectory, rng: np.random.Generator) -> NavState:
    """The truth's first state with the ``[init]`` 1-sigma errors drawn from ``rng``: position north/east (m),
    velocity NED (m/s), and roll, pitch, yaw errors (the ``attitude_sigma_deg`` triple) added to the Euler angles."""
    s0 = truth.at(0)
    ic = sc.init
    dn, de = rng.normal(0.0, ic.position_sigma_m, 2)
    if ic.position_offset_m is not None:  # a fixed offset (Storms Table 4.1); the draw above keeps the stream
        dn, de = ic.position_offset_m
    dlat, dlon = meters_to_latlon(dn, de, s0.lat, s0.h)
    dv = rng.normal(0.0, ic.velocity_sigma_mps, 3)
    datt = rng.normal(0.0, 1.0, 3) * np.asarray(ic.attitude_sigma_deg) * DEG_TO_RAD
    roll, pitch, yaw = euler_from_q_nb(s0.q_nb)
    q = q_nb_from_euler(float(roll) + datt[0], float(pitch) + datt[1], float(yaw) + datt[2])
    return NavState(s0.t, s0.lat + float(dlat), s0.lon + float(dlon), s0.h, s0.v_n + dv, q)


def simulate_readings(sc: Scenario, truth: NavTrajectory, fmap: Any, rng: np.random.Generator) -> FieldReadings:
    """Readings every ``interval_s`` along the truth: the map at the true position plus N(0, sigma) noise, or
    (``source = "survey"``) the survey's own readings interpolated along the line at the truth positions plus
    noise. Readings off the map are dropped."""
    s = sc.sensor
    if s is None:
        raise ConfigError(f"{sc.source}: the scenario has no [sensor]")
    t = np.arange(truth.t[0] + s.interval_s, truth.t[-1] + 1e-9, s.interval_s)
    lat = np.interp(t, truth.t, truth.lat)
    lon = np.interp(t, truth.t, truth.lon)
    h = np.interp(t, truth.t, truth.h)
    if s.source == "survey":
        line = survey_line_points(sc)
        # along-line distance of the survey samples and of the truth positions (nearest-point projection)
        value = _resample_along_line(line, lat, lon, SURVEY_READING_MAX_OFFSET_M)
    else:
        value = np.asarray(fmap.value(lat, lon, h), float)
    ok = np.isfinite(value) if value.ndim == 1 else np.isfinite(value).all(axis=1)
    noise = rng.normal(0.0, s.sigma, value.shape)
    return FieldReadings(t[ok], (value + noise)[ok], s.sigma, s.field_kind)


#: a reading is taken from the survey only where the flown position is within this distance of a surveyed point (m);
#: elsewhere (the legs between lines of a several-line flight) there is no recorded reading
SURVEY_READING_MAX_OFFSET_M = 50.0


def _resample_along_line(
    line: dict[str, np.ndarray], lat: np.ndarray, lon: np.ndarray, max_offset_m: float | None = None
) -> np.ndarray:
    """The survey's recorded values at the query positions ``lat``, ``lon`` (rad): for each query the nearest
    surveyed point, then the value interpolated at that point's along-line distance on its own line. With
    ``max_offset_m``, queries farther than that (m) from every surveyed point get NaN."""
    from scipy.spatial import cKDTree

    from ..core.frames import latlon_to_meters

    lat0, lon0 = float(line["lat"][0]), float(line["lon"][0])
    sn, se = latlon_to_meters(line["lat"] - lat0, line["lon"] - lon0, lat0)
    qn, qe = latlon_to_meters(lat - lat0, lon - lon0, lat0)
    ids = np.asarray(line.get("line", np.zeros(len(sn), np.int64)))
    step = np.hypot(np.diff(sn), np.diff(se))
    step[ids[1:] != ids[:-1]] = 0.0  # along-line distance restarts on each line
    d = np.concatenate([[0.0], np.cumsum(step)])
    dist, idx = cKDTree(np.column_stack([sn, se])).query(np.column_stack([qn, qe]))
    out = np.empty(len(idx), dtype=float)
    for ln in np.unique(ids[idx]):
        q = ids[idx] == ln
        own = ids == ln
        out[q] = np.interp(d[idx[q]], d[own], line["value"][own])
    if max_offset_m is not None:
        out[dist > max_offset_m] = np.nan
    return out


# ------------------------------------------------------------------------------------------------ the model
@dataclass(frozen=True)
class PipelineModel:
    """A :class:`~magnav_ins.studies.runner.StudyModel` built from a validated :class:`Scenario`.

    Every estimator and the free-inertial baseline run through :class:`magnav_ins.pipeline.Pipeline` with the
    same corrupted IMU, initial state and readings; their outputs are reported on at most ``max_samples``
    truth times."""

    scenario: Scenario
    max_samples: int = 400

    @property
    def name(self) -> str:
        return self.scenario.name

    def estimator_names(self) -> tuple[str, ...]:
        return (*(e.name for e in self.scenario.estimators), FREE_INERTIAL)

    def shared(self) -> dict[str, Any]:
        """Truth, ideal IMU and map (memoised per process)."""
        return _shared(self.scenario)

    def crlb_metrics(self) -> dict[str, float]:
        """The flight's posterior Cramér-Rao bound (:mod:`magnav_ins.studies.crlb`): ``crlb_rms_horizontal_m`` and
        ``crlb_final_horizontal_m`` for ``metrics.json``; empty without readings or with a non-grid map."""
        from .crlb import crlb_metrics, flight_crlb

        sc = self.scenario
        sh = self.shared()
        if sc.sensor is None or sh["map"] is None or not hasattr(sh["map"], "gradient_ne"):
            return {}
        if sc.sensor.source != "simulated":
            return {}  # real readings: the bound of the simulated readings would not be theirs
        t, sig = flight_crlb(sc, sh["truth"], sh["imu"], sh["map"])
        return crlb_metrics(t, sig)

    def run(self, seed: np.random.SeedSequence) -> RunOutput:
        from ..ins import imu_models

        sc = self.scenario
        sh = self.shared()
        truth: NavTrajectory = sh["truth"]
        ideal = sh["imu"]
        if sc.trajectory.kind == "ground_path" and sc.trajectory.wander is not None:
            # Storms' Monte Carlo: every run drives its own random trajectory about the nominal path
            from ..ins.simulate import ideal_imu

            truth = ground_path_truth(sc, np.random.default_rng(child(seed, 3)))
            ideal = ideal_imu(truth)
        imus: dict[str, Any] = {}
        for g in (sc.imu.grade, *(e.imu_grade for e in sc.estimators if e.imu_grade)):
            if g not in imus:
                rng_g = np.random.default_rng(grade_seed(seed, g, sc.imu.grade))
                imus[g], _ = imu_models.corrupt(ideal, imu_models.get_grade(g), rng_g)
        imu = imus[sc.imu.grade]
        init = perturbed_init(sc, truth, np.random.default_rng(child(seed, 1)))
        readings = None
        if sc.sensor is not None:
            readings = simulate_readings(sc, truth, sh["map"], np.random.default_rng(child(seed, 2)))
        dt_out = output_dt(sc, truth, self.max_samples)
        sel = np.unique(
            np.append(
                np.searchsorted(truth.t, np.arange(truth.t[0], truth.t[-1] + 1e-9, dt_out) - 1e-6), len(truth.t) - 1
            )
        )
        t_out = truth.t[sel]
        outs = [
            run_estimator(
                sc,
                j,
                t_out,
                imus[est.imu_grade or sc.imu.grade],
                init,
                readings,
                sh["map"],
                np.random.default_rng(child(seed, 10 + j)),
            )
            for j, est in enumerate(sc.estimators)
        ]
        outs.append(run_estimator(sc, None, t_out, imu, init, None, None, None))
        return RunOutput(t_out, truth.lat[sel], truth.lon[sel], tuple(outs))


def initial_estimate(sc: Scenario, init: NavState, grade: str | None = None) -> NavEstimate:
    """The fusers' prior: ``init`` with the ``[init]`` sigmas and the bias sigmas (LAYOUT_15) of IMU ``grade``
    (default ``[imu] grade``)."""
    from ..ins.error_model import initial_covariance
    from ..ins.imu_models import get_grade

    ic = sc.init
    P0 = initial_covariance(
        get_grade(grade or sc.imu.grade),
        position_sigma_m=max(ic.position_sigma_m, 1e-3),
        velocity_sigma_mps=max(ic.velocity_sigma_mps, 1e-4),
        attitude_sigma_rad=np.maximum(np.asarray(ic.attitude_sigma_deg) * DEG_TO_RAD, 1e-7),
    )
    return NavEstimate(init, P0)


def output_dt(sc: Scenario, truth: NavTrajectory, max_samples: int) -> float:
    """Output step (s) of the estimators: a whole number of IMU periods giving at most about ``max_samples``
    samples over the run (each output sample costs a covariance update in the fusers)."""
    dt_imu = 1.0 / sc.imu.rate_hz
    span = float(truth.t[-1] - truth.t[0])
    return max(1, int(np.ceil(span / max(max_samples - 1, 1) / dt_imu))) * dt_imu


#: rotation (rad) preintegrated by the graph fuser before a keyframe node is added (studies only)
GRAPH_KEYFRAME_RAD = 0.1


def run_estimator(
    sc: Scenario,
    j: int | None,
    t_out: np.ndarray,
    imu: Any,
    init: NavState,
    readings: FieldReadings | None,
    fmap: Any,
    rng: np.random.Generator | None,
) -> EstimatorOutput:
    """Run estimator ``j`` of the scenario (``None``: the free-inertial baseline) through
    :class:`magnav_ins.pipeline.Pipeline` and resample its track and covariance onto ``t_out``. ``imu`` is the
    corrupted IMU of the estimator's grade (its ``imu_grade``, else ``[imu] grade``), whose noise the fuser uses.
    An estimator without a matcher (free inertial) gets no readings and, unless its fusion sets ``cov_step_s``,
    the baseline's covariance step, so an estimator of the baseline's grade reproduces the baseline exactly."""
    from ..aiding.fusion import ImuNoise, make_fuser
    from ..aiding.matchers.registry import RECURSIVE_KINDS, build_matcher
    from ..ins.imu_models import get_grade
    from ..pipeline import Pipeline

    hold = float(init.h)
    grade = sc.imu.grade if j is None else (sc.estimators[j].imu_grade or sc.imu.grade)
    noise = ImuNoise.from_grade(get_grade(grade))
    prior = initial_estimate(sc, init, grade)
    # covariance stepped at the output spacing where only the free INS runs: its covariance is only reported there
    dt_out = float(np.min(np.diff(t_out))) if len(t_out) > 1 else 1.0
    if j is None:
        name, mkind, fkind = FREE_INERTIAL, None, FREE_INERTIAL
        fuser = make_fuser(FREE_INERTIAL, prior, noise, altitude_hold=hold, cov_step_s=max(1.0, dt_out))
        pipe = Pipeline(fuser)
        where = sc.where("imu")
    elif sc.estimators[j].matcher is None:
        est = sc.estimators[j]
        name, mkind, fkind = est.name, None, est.fusion_kind
        where = sc.where(f"estimator[{j}]")
        fopts = {k: v for k, v in est.fusion.items() if k != "kind"}
        fopts.setdefault("altitude_hold", hold)
        fopts.setdefault("cov_step_s", max(1.0, dt_out))
        try:
            pipe = Pipeline(make_fuser(fkind, prior, noise, **fopts))
        except (MagnavError, TypeError) as exc:
            raise ConfigError(f"{where}: {exc}") from None
        readings = None
    else:
        est = sc.estimators[j]
        name, mkind, fkind = est.name, est.matcher_kind, est.fusion_kind
        where = sc.where(f"estimator[{j}]")
        try:
            fopts = {k: v for k, v in est.fusion.items() if k != "kind"}
            fopts.setdefault("altitude_hold", hold)  # the graph takes it as a loose height pseudo-measurement
            if fkind == "graph":  # keyframes through turns (GraphFuser docstring); offline no fix arrives late
                fopts.setdefault("max_preintegration_rad", GRAPH_KEYFRAME_RAD)
            if est.smooth and fkind == "ukf":
                fopts["keep_history"] = True
            fuser = make_fuser(fkind, prior, noise, **fopts)
            matcher = build_matcher(est.matcher, fmap=fmap)  # road = "map": the road map is the matched map
            batch = est.matcher.get("batch", getattr(matcher, "batch", None))
            default = int(batch) if (batch and mkind not in RECURSIVE_KINDS) else 1
            pipe = Pipeline(
                fuser,
                matcher,
                fmap,
                window=est.window or default,
                match_every=est.match_every or default,
                rng=rng,
            )
        except (MagnavError, TypeError) as exc:
            raise ConfigError(f"{where}: {exc}") from None
    try:
        res = pipe.run(imu, readings, output_dt=float(np.min(np.diff(t_out))) if len(t_out) > 1 else 1.0)
    except MagnavError as exc:
        raise ConfigError(f"{where}: {exc}") from None
    nav, P = res.trajectory, np.asarray(res.P)
    P_online, t_online = P, nav.t
    if j is not None and sc.estimators[j].smooth and fkind == "graph":
        # offline: the batch LM solution re-integrated between its nodes, reported at t_out itself
        try:
            nav, P = fuser.smoothed_track(imu, t_out)
        except MagnavError as exc:
            raise ConfigError(f"{where}: {exc}") from None
    elif j is not None and sc.estimators[j].smooth:  # offline: the RTS-smoothed track replaces the causal one
        nav, P_all = fuser.smooth(sc.estimators[j].smooth)
        pos = LAYOUT_15["pos"].start
        P = np.asarray(P_all)[:, pos : pos + 2, pos : pos + 2]
    lat = np.interp(t_out, nav.t, nav.lat)
    lon = np.interp(t_out, nav.t, np.unwrap(nav.lon))
    cov = np.stack([np.interp(t_out, nav.t, P[:, a, b]) for a in range(2) for b in range(2)], -1).reshape(-1, 2, 2)
    hpl = protection_levels(t_out, t_online, P_online, res.hpl_m, cov, res.integrity_risk)
    fixes = list(res.fixes)
    return EstimatorOutput(
        name,
        mkind,
        fkind,
        lat,
        lon,
        cov,
        np.array([f.t for f in fixes], float),
        np.array([f.lat for f in fixes], float),
        np.array([f.lon for f in fixes], float),
        np.array([np.asarray(f.cov_ne, float) for f in fixes], float).reshape(-1, 2, 2),
        np.array([f.available for f in fixes], bool),
        tuple(f.reason for f in fixes),
        fix_accepted=_accepted(fixes, list(res.innovations)),
        hpl_m=hpl,
    )


def _accepted(fixes: list[Any], innovations: list[Any]) -> np.ndarray:
    """Per fix attempt, whether the fuser applied it (the pipeline records one innovation per fix, in order)."""
    if len(innovations) != len(fixes):
        return np.zeros(0, bool)
    return np.array([bool(i.accepted) for i in innovations], bool)


def protection_levels(
    t_out: np.ndarray,
    t_online: np.ndarray,
    P_online: np.ndarray,
    hpl_online: np.ndarray,
    cov_out: np.ndarray,
    integrity_risk: float,
) -> np.ndarray | None:
    """The estimator's horizontal protection level (m) at ``t_out`` (s): the fuser's online HPL (at ``t_online``,
    with its covariances ``P_online`` (N,>=2,>=2) m^2) less its fault-free part ``K sigma_max``
    (:func:`aiding.fusion.integrity.hpl_fault_free`), i.e. the fault-detection margin or doubt, interpolated, plus
    ``K sigma_max`` of the reported covariance ``cov_out`` (n,2,2) (the smoothed one for a smoothed track, whose
    fixes are the online filter's). None when the fuser gave no HPL."""
    from ..aiding.fusion.integrity import hpl_fault_free

    h = np.asarray(hpl_online, float)
    if h.size == 0 or not np.isfinite(h).any() or len(t_online) != h.size:
        return None
    ff_online = np.array([hpl_fault_free(p[:2, :2], integrity_risk) for p in np.asarray(P_online)])
    excess = np.maximum(h - ff_online, 0.0)
    ff_out = np.array([hpl_fault_free(c, integrity_risk) for c in np.asarray(cov_out)])
    return ff_out + np.interp(t_out, t_online, excess)
