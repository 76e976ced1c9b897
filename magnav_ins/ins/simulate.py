"""Truth trajectories and ideal IMU samples (inverse mechanisation).

Trajectories are :class:`~magnav_ins.core.types.NavTrajectory` (lat/lon rad, ellipsoidal h m, NED velocity m/s,
body FRD -> NED quaternions), sampled at ``rate_hz``. In every generator the velocity is the exact time derivative
of the position (both come from one high-accuracy ODE solution, ``rtol`` 1e-12), which is what the inverse
mechanisation needs.

:func:`ideal_imu` turns a trajectory into rate-type samples (the mean angular rate ``omega_ib_b`` and specific
force ``f_ib_b`` over each interval ``(t[k-1], t[k]]``). It follows the approach of pyins ``sim.generate_imu``
(N. Mayorov): the trajectory is moved to an Earth-centred inertial frame, position is interpolated by a cubic
Hermite spline through (r_i, v_i) and attitude ``C_ib`` by a cubic rotation spline; the increments are then the
exact integrals, over each interval, of the body rate and of ``C_bi (a_i - gamma_i)`` (gravitation, i.e. gravity
plus the centrifugal term, Groves 2013 eq. 2.133), evaluated with 4-point Gauss-Legendre quadrature (exact for the
polynomial parts). Earth rate, transport rate, Coriolis and gravity are therefore all inside the samples.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from scipy.integrate import solve_ivp
from scipy.interpolate import CubicHermiteSpline, CubicSpline
from scipy.spatial.transform import Rotation, RotationSpline

from ..core.errors import ConfigError, InputError, where
from ..core.frames import (
    WGS84_OMEGA_E,
    C_en,
    ecef_to_geodetic,
    geodetic_to_ecef,
    q_nb_from_euler,
    radii_of_curvature,
    wrap_angle,
)
from ..core.types import FloatArray, ImuBatch, NavTrajectory
from ..core.units import DEG_TO_RAD
from .earth import gravity_n

_RTOL = 1e-12
_ATOL = 1e-14
_G_BANK = 9.80665  # m/s^2, only for the coordinated-turn bank angle phi = atan(v omega / g)


def _check_positive(**kw: float) -> None:
    for k, v in kw.items():
        if not (isinstance(v, int | float) and math.isfinite(v) and v > 0):
            raise ConfigError(f"{k} must be a positive number, got {v!r}")


def _times(duration_s: float, rate_hz: float) -> FloatArray:
    n = int(math.floor(duration_s * rate_hz + 1e-9)) + 1
    return np.arange(n) / rate_hz


# --- stationary ----------------------------------------------------------------------------------------------
def stationary(lat: float, lon: float, h: float, yaw: float, duration_s: float, rate_hz: float) -> NavTrajectory:
    """A vehicle at rest at ``(lat, lon, h)`` (rad, rad, m) with heading ``yaw`` (rad), level, for ``duration_s``."""
    _check_positive(duration_s=duration_s, rate_hz=rate_hz)
    t = _times(duration_s, rate_hz)
    n = len(t)
    q = np.broadcast_to(q_nb_from_euler(0.0, 0.0, yaw), (n, 4))
    return NavTrajectory(t, np.full(n, lat), np.full(n, lon), np.full(n, h), np.zeros((n, 3)), q)


# --- great circle --------------------------------------------------------------------------------------------
def _nvec(lat: float, lon: float) -> FloatArray:
    return np.array([math.cos(lat) * math.cos(lon), math.cos(lat) * math.sin(lon), math.sin(lat)])


def great_circle(
    start_lat: float,
    start_lon: float,
    end_lat: float,
    end_lon: float,
    altitude_m: float,
    speed_mps: float,
    rate_hz: float,
) -> NavTrajectory:
    """Fly from start to end (rad) at constant ellipsoidal height ``altitude_m`` and constant ground speed.

    The path is the great circle of the *geodetic normal vectors* (n-vectors, Gade 2010) through the two end
    points: n(s) = cos(s) n0 + sin(s) e. It is exact on a sphere; on the WGS-84 ellipsoid it is a smooth curve whose
    heading evolves along the path but it is not the ellipsoidal geodesic (the lateral difference is of the order
    of the flattening times the path's extent; not measured here). Clairaut's constant cos(lat) sin(heading) stays
    within 0.5 % along a 600 km test path. Arc length is integrated on the ellipsoid (R_N, R_E at the height), so
    the ground speed is exactly ``speed_mps``. Level flight, zero roll,
    heading along the velocity.
    """
    _check_positive(speed_mps=speed_mps, rate_hz=rate_hz)
    n0, n1 = _nvec(start_lat, start_lon), _nvec(end_lat, end_lon)
    ang = math.atan2(np.linalg.norm(np.cross(n0, n1)), float(n0 @ n1))
    if ang < 1e-9 or ang > math.pi - 1e-6:
        raise ConfigError(
            f"great_circle: start and end must be distinct and not antipodal (central angle {ang:.3g} rad)"
        )
    e = n1 - (n0 @ n1) * n0
    e /= np.linalg.norm(e)
    h = float(altitude_m)

    def geo(s: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        c, sn = np.cos(s), np.sin(s)
        n = np.outer(c, n0) + np.outer(sn, e)
        dn = np.outer(-sn, n0) + np.outer(c, e)
        lat = np.arcsin(np.clip(n[:, 2], -1.0, 1.0))
        lon = np.arctan2(n[:, 1], n[:, 0])
        dlat = dn[:, 2] / np.cos(lat)
        dlon = (n[:, 0] * dn[:, 1] - n[:, 1] * dn[:, 0]) / (n[:, 0] ** 2 + n[:, 1] ** 2)
        r_n, r_e = radii_of_curvature(lat)
        dnorth = (r_n + h) * dlat  # m per rad of s
        deast = (r_e + h) * np.cos(lat) * dlon
        return lat, lon, dnorth, deast

    def rhs(_t: float, y: FloatArray) -> FloatArray:
        _, _, dn_, de_ = geo(np.atleast_1d(y[0]))
        return np.array([speed_mps / math.hypot(dn_[0], de_[0])])

    def done(_t: float, y: FloatArray) -> float:
        return y[0] - ang

    done.terminal = True  # type: ignore[attr-defined]
    # rough duration bound for the solver
    t_max = 2.0 * ang * 6.4e6 / speed_mps + 10.0
    sol = solve_ivp(rhs, (0.0, t_max), [0.0], method="DOP853", rtol=_RTOL, atol=_ATOL, dense_output=True, events=done)
    t_end = float(sol.t_events[0][0])
    t = np.arange(int(math.floor(t_end * rate_hz)) + 1) / rate_hz
    s = sol.sol(t)[0]
    lat, lon, dnorth, deast = geo(s)
    sdot = speed_mps / np.hypot(dnorth, deast)
    v_n = np.stack([dnorth * sdot, deast * sdot, np.zeros_like(s)], axis=-1)
    yaw = np.arctan2(v_n[:, 1], v_n[:, 0])
    q = q_nb_from_euler(np.zeros_like(yaw), np.zeros_like(yaw), yaw)
    return NavTrajectory(t, lat, wrap_angle(lon), np.full_like(s, h), v_n, q)


# --- waypoints with coordinated turns ------------------------------------------------------------------------
def _bearing(lat0: float, lon0: float, lat1: float, lon1: float) -> float:
    """Initial great-circle bearing (rad) from point 0 to point 1 (spherical)."""
    dlon = lon1 - lon0
    y = math.sin(dlon) * math.cos(lat1)
    x = math.cos(lat0) * math.sin(lat1) - math.sin(lat0) * math.cos(lat1) * math.cos(dlon)
    return math.atan2(y, x)


def _dist(lat0: float, lon0: float, lat1: float, lon1: float) -> float:
    """Haversine distance (m) on a 6371 km sphere, for waypoint switching only."""
    a = math.sin((lat1 - lat0) / 2) ** 2 + math.cos(lat0) * math.cos(lat1) * math.sin((lon1 - lon0) / 2) ** 2
    return 2.0 * 6371e3 * math.asin(min(1.0, math.sqrt(a)))


def waypoints(
    points: Sequence[Sequence[float]] | FloatArray,
    speed_mps: float,
    rate_hz: float,
    turn_rate: float = 3.0 * DEG_TO_RAD,
    climb_rate: float = 2.5,
    roll_time_constant_s: float = 1.0,
) -> NavTrajectory:
    """Fly through ``points`` (rows ``(lat, lon, h)`` rad, rad, m) at horizontal ground speed ``speed_mps``.

    Guidance: heading rate command ``r_cmd = turn_rate * tanh(psi_err / 10 deg)`` toward the next waypoint (a
    smoothly saturated coordinated turn at up to ``turn_rate`` rad/s), followed through a first-order lag of
    ``roll_time_constant_s`` (so bank changes smoothly); the next waypoint is taken within the fly-by lead distance
    ``r tan(delta_psi / 2)`` of a turn of ``delta_psi`` with radius ``r = v / turn_rate``; the flight ends abeam the last point (closest approach). Vertical: ``vd_cmd = -climb_rate * tanh(dh / 50 m)`` toward the waypoint height,
    with the same lag. Attitude: yaw = heading, roll = bank of a coordinated turn ``atan(v r / g)``, pitch =
    flight-path angle ``atan(-vd / v)``. Position and velocity come from one ODE solution, so they are
    consistent to ~1e-12.
    """
    pts = np.asarray(points, dtype=float)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 2:
        raise ConfigError(f"waypoints: points must be an (N>=2, 3) array of (lat, lon, h), got shape {pts.shape}")
    if not np.all(np.isfinite(pts)):
        raise ConfigError("waypoints: points contain NaN or inf")
    _check_positive(speed_mps=speed_mps, rate_hz=rate_hz, turn_rate=turn_rate, climb_rate=climb_rate)
    _check_positive(roll_time_constant_s=roll_time_constant_s)
    V = float(speed_mps)
    tau = float(roll_time_constant_s)
    r_turn = V / turn_rate
    # fly-by lead distance at each inner waypoint: r tan(delta_psi / 2) for a turn of delta_psi
    r_switch = np.full(len(pts), V / rate_hz)
    for i in range(1, len(pts) - 1):
        b_in = _bearing(pts[i - 1, 0], pts[i - 1, 1], pts[i, 0], pts[i, 1])
        b_out = _bearing(pts[i, 0], pts[i, 1], pts[i + 1, 0], pts[i + 1, 1])
        turn = abs(float(wrap_angle(b_out - b_in)))
        r_switch[i] = max(r_turn * math.tan(min(turn, 0.9 * math.pi) / 2.0), V / rate_hz)

    def make_rhs(i: int):  # noqa: ANN202
        lat_w, lon_w, h_w = pts[i]

        def rhs(_t: float, y: FloatArray) -> FloatArray:
            lat, lon, h, psi, r, vd = y
            r_n, r_e = radii_of_curvature(lat)
            psi_err = wrap_angle(_bearing(lat, lon, lat_w, lon_w) - psi)
            r_cmd = turn_rate * math.tanh(float(psi_err) / (10.0 * DEG_TO_RAD))
            vd_cmd = -climb_rate * math.tanh((h_w - h) / 50.0)
            return np.array(
                [
                    V * math.cos(psi) / (r_n + h),
                    V * math.sin(psi) / ((r_e + h) * math.cos(lat)),
                    -vd,
                    r,
                    (r_cmd - r) / tau,
                    (vd_cmd - vd) / tau,
                ]
            )

        def arrive(_t: float, y: FloatArray) -> float:
            if i < len(pts) - 1:
                return _dist(y[0], y[1], lat_w, lon_w) - r_switch[i]
            # last point: stop at the closest approach (the point comes abeam)
            return math.cos(_bearing(y[0], y[1], lat_w, lon_w) - y[3])

        def passed(_t: float, y: FloatArray) -> float:
            # a fly-by point missed by less than a turn radius (a small heading change, so a lead distance of a few
            # metres, on a jittery survey line) counts as passed when it comes abeam; never fires before the lead
            # circle would have been entered, so it changes nothing for a point that is hit
            if _dist(y[0], y[1], lat_w, lon_w) > r_turn:
                return 1.0
            return math.cos(_bearing(y[0], y[1], lat_w, lon_w) - y[3])

        arrive.terminal = True  # type: ignore[attr-defined]
        arrive.direction = -1  # type: ignore[attr-defined]
        passed.terminal = True  # type: ignore[attr-defined]
        passed.direction = -1  # type: ignore[attr-defined]
        return rhs, (arrive, passed) if i < len(pts) - 1 else arrive

    psi0 = _bearing(pts[0, 0], pts[0, 1], pts[1, 0], pts[1, 1])
    y = np.array([pts[0, 0], pts[0, 1], pts[0, 2], psi0, 0.0, 0.0])
    t0 = 0.0
    segments = []
    for i in range(1, len(pts)):
        if i < len(pts) - 1 and _dist(y[0], y[1], pts[i, 0], pts[i, 1]) <= r_switch[i]:
            continue  # already within the switching radius of this fly-by point: go on to the next
        rhs, arrive = make_rhs(i)
        leg = _dist(*y[:2], *pts[i, :2])
        t_max = t0 + 3.0 * leg / V + 2.0 * math.pi / turn_rate + 60.0
        sol = solve_ivp(rhs, (t0, t_max), y, method="DOP853", rtol=_RTOL, atol=1e-13, dense_output=True, events=arrive)
        if sol.status != 1:
            raise ConfigError(f"waypoints: waypoint {i} not reached (too close for turn rate {turn_rate} rad/s?)")
        segments.append((sol.t[-1], sol.sol))
        t0, y = sol.t[-1], sol.y[:, -1]
    t = np.arange(int(math.floor(t0 * rate_hz)) + 1) / rate_hz
    ys = np.empty((len(t), 6))
    v_n = np.empty((len(t), 3))
    k0 = 0
    for j, (b, dense) in enumerate(segments):
        k1 = len(t) if j == len(segments) - 1 else int(np.searchsorted(t, b, side="right"))
        if k1 > k0:
            ys[k0:k1] = dense(t[k0:k1]).T
        k0 = k1
    lat, lon, h, psi, r, vd = ys.T
    v_n[:, 0] = V * np.cos(psi)
    v_n[:, 1] = V * np.sin(psi)
    v_n[:, 2] = vd
    roll = np.arctan(V * r / _G_BANK)
    pitch = np.arctan2(-vd, V)
    q = q_nb_from_euler(roll, pitch, psi)
    return NavTrajectory(t, lat, wrap_angle(lon), h, v_n, q)


def _rdp(x: FloatArray, y: FloatArray, tol: float) -> list[int]:
    """Ramer-Douglas-Peucker simplification of a polyline (metres): indices of the kept vertices."""
    keep = np.zeros(len(x), dtype=bool)
    keep[0] = keep[-1] = True
    stack = [(0, len(x) - 1)]
    while stack:
        i0, i1 = stack.pop()
        if i1 <= i0 + 1:
            continue
        dx, dy = x[i1] - x[i0], y[i1] - y[i0]
        L = math.hypot(dx, dy)
        px, py = x[i0 + 1 : i1] - x[i0], y[i0 + 1 : i1] - y[i0]
        d = np.abs(dx * py - dy * px) / L if L > 0 else np.hypot(px, py)
        k = int(np.argmax(d))
        if d[k] > tol:
            keep[i0 + 1 + k] = True
            stack += [(i0, i0 + 1 + k), (i0 + 1 + k, i1)]
    return [int(i) for i in np.flatnonzero(keep)]


def survey_line(
    lat: FloatArray,
    lon: FloatArray,
    h: FloatArray | float,
    speed_mps: float,
    rate_hz: float,
    turn_rate: float = 3.0 * DEG_TO_RAD,
    climb_rate: float = 2.5,
    tolerance_m: float = 5.0,
) -> NavTrajectory:
    """Fly the polyline ``(lat, lon, h)`` (arrays, rad, rad, m; e.g. a survey flight line) at ``speed_mps``.

    The line is simplified with Ramer-Douglas-Peucker (vertices within ``tolerance_m`` of the simplified line are
    dropped; a survey line's fixes are often metres apart), then flown as :func:`waypoints`, so heading changes
    are smoothed into coordinated turns of at most ``turn_rate`` (corners are cut by up to about a turn radius
    ``v / turn_rate`` times (1/cos(half the heading change) - 1)).
    """
    lat = np.asarray(lat, dtype=float)
    lon = np.asarray(lon, dtype=float)
    hh = np.broadcast_to(np.asarray(h, dtype=float), lat.shape)
    if lat.ndim != 1 or lat.shape != lon.shape or len(lat) < 2:
        raise ConfigError(f"survey_line: lat {lat.shape} and lon {lon.shape} must be equal-length 1-D arrays (>=2)")
    if not (np.all(np.isfinite(lat)) and np.all(np.isfinite(lon)) and np.all(np.isfinite(hh))):
        raise ConfigError("survey_line: lat, lon and h must be finite")
    _check_positive(speed_mps=speed_mps, turn_rate=turn_rate, tolerance_m=tolerance_m)
    r_n, r_e = radii_of_curvature(lat[0])
    north = (lat - lat[0]) * r_n
    east = wrap_angle(lon - lon[0]) * r_e * math.cos(lat[0])
    keep = _rdp(north, east, tolerance_m)
    pts = np.stack([lat[keep], lon[keep], hh[keep]], axis=-1)
    return waypoints(pts, speed_mps, rate_hz, turn_rate=turn_rate, climb_rate=climb_rate)


# --- from a file ---------------------------------------------------------------------------------------------
_REQUIRED = ("t", "lat_deg", "lon_deg", "h_m")
_VEL = ("vn", "ve", "vd")
_ATT = ("roll_deg", "pitch_deg", "yaw_deg")


def trajectory_from_csv(path: str | Path) -> NavTrajectory:
    """Read a trajectory CSV with columns ``t,lat_deg,lon_deg,h_m[,vn,ve,vd,roll_deg,pitch_deg,yaw_deg]``.

    Without velocity columns the NED velocity is the derivative of a cubic spline through the positions;
    without attitude columns yaw follows the horizontal velocity, pitch the flight-path angle, roll is zero.
    Raises :class:`InputError` naming the file, row and column for missing columns, NaN, out-of-range latitude or
    time not strictly increasing.
    """
    import pandas as pd

    path = Path(path)
    try:
        df = pd.read_csv(path)
    except (OSError, pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as exc:
        raise InputError(f"{where(path)}cannot read trajectory CSV: {exc}") from exc
    cols = [c.strip() for c in df.columns]
    df.columns = cols
    for c in _REQUIRED:
        if c not in cols:
            raise InputError(
                f"{where(path, key=c)}missing column; expected {', '.join(_REQUIRED)} [+ velocity, attitude]"
            )
    has_vel = any(c in cols for c in _VEL)
    has_att = any(c in cols for c in _ATT)
    for group, present in ((_VEL, has_vel), (_ATT, has_att)):
        if present:
            for c in group:
                if c not in cols:
                    raise InputError(f"{where(path, key=c)}missing column; {', '.join(group)} come together")
    use = list(_REQUIRED) + (list(_VEL) if has_vel else []) + (list(_ATT) if has_att else [])
    extra = [c for c in cols if c not in use]
    if extra:
        raise InputError(f"{where(path, key=extra[0])}unknown column; expected {', '.join(_REQUIRED + _VEL + _ATT)}")
    if len(df) < 2:
        raise InputError(f"{where(path)}need at least 2 rows, got {len(df)}")
    data = {}
    for c in use:
        v = pd.to_numeric(df[c], errors="coerce").to_numpy(dtype=float)
        bad = np.flatnonzero(~np.isfinite(v))
        if len(bad):
            raise InputError(f"{where(path, int(bad[0]) + 1, c)}expected a finite number, got {df[c].iloc[bad[0]]!r}")
        data[c] = v
    t = data["t"]
    dt = np.diff(t)
    if np.any(dt <= 0):
        k = int(np.flatnonzero(dt <= 0)[0]) + 2
        raise InputError(f"{where(path, k, 't')}time must increase strictly, got {t[k - 1]} after {t[k - 2]}")
    bad = np.flatnonzero(np.abs(data["lat_deg"]) > 90.0)
    if len(bad):
        raise InputError(
            f"{where(path, int(bad[0]) + 1, 'lat_deg')}latitude must be in [-90, 90], got {data['lat_deg'][bad[0]]}"
        )
    lat = data["lat_deg"] * DEG_TO_RAD
    lon = wrap_angle(data["lon_deg"] * DEG_TO_RAD)
    h = data["h_m"]
    if has_vel:
        v_n = np.stack([data["vn"], data["ve"], data["vd"]], axis=-1)
    else:
        lon_u = np.unwrap(lon)
        r_n, r_e = radii_of_curvature(lat)
        v_n = np.stack(
            [
                CubicSpline(t, lat)(t, 1) * (r_n + h),
                CubicSpline(t, lon_u)(t, 1) * (r_e + h) * np.cos(lat),
                -CubicSpline(t, h)(t, 1),
            ],
            axis=-1,
        )
    if has_att:
        q = q_nb_from_euler(data["roll_deg"] * DEG_TO_RAD, data["pitch_deg"] * DEG_TO_RAD, data["yaw_deg"] * DEG_TO_RAD)
    else:
        vh = np.hypot(v_n[:, 0], v_n[:, 1])
        q = q_nb_from_euler(np.zeros_like(t), np.arctan2(-v_n[:, 2], vh), np.arctan2(v_n[:, 1], v_n[:, 0]))
    return NavTrajectory(t, lat, lon, h, v_n, q)


# --- inverse mechanisation -----------------------------------------------------------------------------------
_GL_X, _GL_W = np.polynomial.legendre.leggauss(4)


def _C_ie(t: FloatArray) -> FloatArray:
    """ECEF -> inertial rotation at time t (the frames coincide at t = 0), (N,3,3)."""
    a = WGS84_OMEGA_E * np.asarray(t, dtype=float)
    c, s = np.cos(a), np.sin(a)
    m = np.zeros(a.shape + (3, 3))
    m[..., 0, 0], m[..., 0, 1] = c, -s
    m[..., 1, 0], m[..., 1, 1] = s, c
    m[..., 2, 2] = 1.0
    return m


def _gravitation_e(lat: FloatArray, lon: FloatArray, h: FloatArray) -> FloatArray:
    """Gravitation (gravity minus centrifugal) in ECEF, m/s^2: gamma_e = g_e + Omega x (Omega x r_e)."""
    g_e = np.einsum("...ij,...j->...i", C_en(lat, lon), gravity_n(lat, h))
    r_e = geodetic_to_ecef(lat, lon, h)
    w = np.array([0.0, 0.0, WGS84_OMEGA_E])
    return g_e + np.cross(w, np.cross(w, r_e))


_CHUNK = 50_000


def _interval_means(
    t0: FloatArray, dt: FloatArray, pos: CubicHermiteSpline, acc: object, rot: RotationSpline
) -> tuple[FloatArray, FloatArray]:
    """Means of omega_ib_b and f_ib_b over the intervals (t0, t0 + dt], 4-point Gauss-Legendre."""
    n = len(dt)
    tq = (t0[:, None] + 0.5 * dt[:, None] * (_GL_X[None, :] + 1.0)).ravel()  # 4 nodes per interval
    wq = np.tile(0.5 * _GL_W, n)[:, None]  # weights of the mean over each interval
    omega_b = rot(tq, 1)
    # gravitation at the interpolated inertial position
    C_ie = _C_ie(tq)
    r_eq = np.einsum("nji,nj->ni", C_ie, pos(tq))
    latq, lonq, hq = ecef_to_geodetic(r_eq)
    gam_i = np.einsum("nij,nj->ni", C_ie, _gravitation_e(latq, lonq, hq))
    f_b = np.einsum("nji,nj->ni", rot(tq).as_matrix(), acc(tq) - gam_i)  # type: ignore[operator]
    return (omega_b * wq).reshape(n, 4, 3).sum(axis=1), (f_b * wq).reshape(n, 4, 3).sum(axis=1)


def ideal_imu(traj: NavTrajectory) -> ImuBatch:
    """Error-free rate-type IMU samples for ``traj`` (see the module docstring).

    Returns ``ImuBatch`` with the same times; sample k (k >= 1) is the mean of ``omega_ib_b`` (rad/s) and
    ``f_ib_b`` (m/s^2) over ``(t[k-1], t[k]]``; sample 0 repeats sample 1. Gravity is the project's normal gravity
    (:func:`magnav_ins.ins.earth.gravity_n`), so the forward mechanisation must use the same model.
    """
    t = traj.t
    if len(t) < 3:
        raise InputError(f"ideal_imu: need at least 3 trajectory samples, got {len(t)}")
    if np.any(np.diff(t) <= 0):
        raise InputError("ideal_imu: trajectory times must increase strictly")
    C_ie = _C_ie(t)
    C_en_ = C_en(traj.lat, traj.lon)
    r_e = geodetic_to_ecef(traj.lat, traj.lon, traj.h)
    w_ie = np.array([0.0, 0.0, WGS84_OMEGA_E])
    v_e = np.einsum("nij,nj->ni", C_en_, traj.v_n)
    r_i = np.einsum("nij,nj->ni", C_ie, r_e)
    v_i = np.einsum("nij,nj->ni", C_ie, v_e + np.cross(w_ie, r_e))
    pos = CubicHermiteSpline(t, r_i, v_i)
    acc = pos.derivative(2)
    C_ib = C_ie @ C_en_ @ Rotation.from_quat(traj.q_nb).as_matrix()
    rot = RotationSpline(t, Rotation.from_matrix(C_ib))

    dt = np.diff(t)
    gyro = np.empty((len(dt), 3))
    accel = np.empty((len(dt), 3))
    for i0 in range(0, len(dt), _CHUNK):  # bounded memory: ~2 kB per interval and chunk
        i1 = min(i0 + _CHUNK, len(dt))
        gyro[i0:i1], accel[i0:i1] = _interval_means(t[i0:i1], dt[i0:i1], pos, acc, rot)
    gyro = np.vstack([gyro[:1], gyro])
    accel = np.vstack([accel[:1], accel])
    return ImuBatch(t.copy(), gyro, accel)
