"""A ground vehicle along a path (corridors, roads), optionally wandering about it as in Storms' Monte Carlo.

The path is a polyline of ``points_ne`` (north, east metres in the tangent plane of ``origin``) whose inner corners
are rounded with circular arcs of ``corner_radius_m`` (so the heading, and the gyro, stay continuous), driven at
``speed_mps``. The vehicle is level; its heading is that of its velocity.

Wander (Storms 2009, seed 004, sec. 4.4.1.1 and 4.4.1.3): "the dynamics model is perturbed by white driving noise
to create a random trajectory that is centred around the nominal trajectory" - the constant-velocity model of his
eq. 3.2-3.4 with acceleration root-PSD ``accel_sigma_mps2`` (0.08 m/s^2), stepped every ``step_s`` (0.1 s) in
path coordinates (along-track distance ``s``, cross-track offset ``d``, each a [position, velocity] pair with the
discrete noise of eq. 3.4); "after each time step, the distance between the centre of the hallway and the new
position is compared. The distance between the two is then multiplied by a scale factor and subtracted from the new
generated position": ``d <- (1 - cross_gain) d``; "if a trajectory was found to break the physical barrier of the
hallway, it was rejected and the trajectory was regenerated": any ``|d| > max_offset_m`` draws the run again.
Storms gives neither the scale factor nor a control of the speed; ours: ``cross_gain`` (default 0.05 per step),
and the same control on the along-track distance against the nominal ``s = V t`` (``along_gain``, default 0.05),
so that the vehicle moves at ``V`` +- a few cm/s and every run takes the nominal time (Storms: "moving at .5 +- .08
meters per second", the turn "around 80 seconds, depending on the randomly generated trajectory"). Past the path's
end a run continues straight along the last leg. The 0.1 s positions are joined by a cubic spline (position and
velocity consistent, as :func:`magnav_ins.ins.simulate.ideal_imu` needs).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.interpolate import CubicSpline

from ..core.errors import ConfigError
from ..core.frames import q_nb_from_euler, radii_of_curvature
from ..core.types import NavTrajectory

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Wander:
    """Storms' random perturbation of a ground path (module docstring). ``accel_sigma_mps2``: root-PSD of the white
    acceleration (m/s^2, eq. 3.2); ``cross_gain`` / ``along_gain``: fraction of the cross-track offset / of the
    along-track lead or lag removed after each ``step_s`` (s); ``max_offset_m``: a run whose cross-track offset
    exceeds it is drawn again (None: never); ``max_attempts``: draws before giving up."""

    accel_sigma_mps2: float = 0.08
    cross_gain: float = 0.05
    along_gain: float = 0.05
    max_offset_m: float | None = None
    step_s: float = 0.1
    max_attempts: int = 1000

    def __post_init__(self) -> None:
        for key in ("accel_sigma_mps2", "step_s"):
            v = getattr(self, key)
            if not (np.isfinite(v) and v > 0):
                raise ConfigError(f"wander '{key}': expected a number > 0, got {v!r}")
        for key in ("cross_gain", "along_gain"):
            v = getattr(self, key)
            if not (np.isfinite(v) and 0.0 <= v < 1.0):
                raise ConfigError(f"wander '{key}': expected 0 <= gain < 1 (fraction removed per step), got {v!r}")
        if self.max_offset_m is not None and not (np.isfinite(self.max_offset_m) and self.max_offset_m > 0):
            raise ConfigError(f"wander 'max_offset_m': expected a number > 0 (m), got {self.max_offset_m!r}")


@dataclass(frozen=True)
class Path2D:
    """A polyline with rounded corners, parametrised by arc length: straight legs and circular fillets."""

    #: per piece: start arc length (m), start point (2,), start heading (rad), length (m), curvature (1/m, + = right)
    pieces: tuple[tuple[float, FloatArray, float, float, float], ...]

    @property
    def length(self) -> float:
        s0, _, _, ln, _ = self.pieces[-1]
        return s0 + ln

    @classmethod
    def from_points(cls, points_ne: ArrayLike, corner_radius_m: float) -> Path2D:
        """The path through ``points_ne`` ((K, 2) m, K >= 2) with each inner corner filleted at ``corner_radius_m``."""
        p = np.asarray(points_ne, dtype=float)
        if p.ndim != 2 or p.shape[1] != 2 or len(p) < 2 or not np.all(np.isfinite(p)):
            raise ConfigError(f"ground path: points must be (K >= 2, 2) finite north/east metres, got {p.tolist()}")
        if not (np.isfinite(corner_radius_m) and corner_radius_m >= 0):
            raise ConfigError(f"ground path: corner_radius_m must be >= 0, got {corner_radius_m!r}")
        legs = np.diff(p, axis=0)
        lens = np.hypot(legs[:, 0], legs[:, 1])
        if np.any(lens <= 0):
            raise ConfigError("ground path: two consecutive points coincide")
        head = np.arctan2(legs[:, 1], legs[:, 0])
        turn = np.array([(head[i + 1] - head[i] + np.pi) % (2 * np.pi) - np.pi for i in range(len(head) - 1)])
        cut = np.abs(corner_radius_m * np.tan(0.5 * turn))  # distance from the corner to each fillet end
        pieces: list[tuple[float, FloatArray, float, float, float]] = []
        s = 0.0
        for i in range(len(legs)):
            a = cut[i - 1] if i > 0 else 0.0
            b = cut[i] if i < len(turn) else 0.0
            straight = lens[i] - a - b
            if straight < -1e-9:
                raise ConfigError(
                    f"ground path: leg {i} ({lens[i]:.3g} m) is too short for corner radius {corner_radius_m} m"
                )
            u = legs[i] / lens[i]
            start = p[i] + a * u
            pieces.append((s, start, float(head[i]), max(straight, 0.0), 0.0))
            s += max(straight, 0.0)
            if i < len(turn) and abs(turn[i]) > 1e-12 and corner_radius_m > 0:
                arc = corner_radius_m * abs(turn[i])
                pieces.append((s, p[i + 1] - b * u, float(head[i]), arc, float(np.sign(turn[i]) / corner_radius_m)))
                s += arc
        return cls(tuple(pieces))

    def at(self, s: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Points (N, 2) m and headings (N,) rad at arc lengths ``s`` (m); beyond the ends the first / last piece
        is extended (straight, or along its circle)."""
        s = np.atleast_1d(np.asarray(s, dtype=float))
        starts = np.array([pc[0] for pc in self.pieces])
        k = np.clip(np.searchsorted(starts, s, side="right") - 1, 0, len(self.pieces) - 1)
        out = np.empty((len(s), 2))
        psi = np.empty(len(s))
        for j in np.unique(k):
            s0, p0, h0, _, kappa = self.pieces[j]
            q = k == j
            ds = s[q] - s0
            if kappa == 0.0:
                out[q] = p0 + ds[:, None] * np.array([np.cos(h0), np.sin(h0)])
                psi[q] = h0
            else:
                r = 1.0 / kappa
                hh = h0 + kappa * ds
                out[q, 0] = p0[0] + r * (np.sin(hh) - np.sin(h0))
                out[q, 1] = p0[1] - r * (np.cos(hh) - np.cos(h0))
                psi[q] = hh
        return out, psi


def _walk(n: int, dt: float, sigma: float, gain: float, rng: np.random.Generator, ref: FloatArray) -> FloatArray:
    """One axis of Storms' perturbed CV model (eq. 3.4 noise) about ``ref`` (the nominal position per step), with
    the deviation cut by ``gain`` after every step. Returns the positions (n,)."""
    q = sigma**2
    Q = np.array([[q * dt**3 / 3.0, q * dt**2 / 2.0], [q * dt**2 / 2.0, q * dt]])
    L = np.linalg.cholesky(Q)
    w = rng.standard_normal((n, 2)) @ L.T
    dev = np.zeros(n)
    pos, vel = 0.0, 0.0  # deviation from ref and its "velocity" state
    for k in range(1, n):
        pos = pos + vel * dt + w[k, 0]
        vel = vel + w[k, 1]
        pos -= gain * pos
        dev[k] = pos
    return ref + dev


def ground_path(
    points_ne: ArrayLike,
    speed_mps: float,
    rate_hz: float,
    origin: tuple[float, float, float],
    *,
    corner_radius_m: float = 1.0,
    duration_s: float | None = None,
    wander: Wander | None = None,
    rng: np.random.Generator | None = None,
) -> NavTrajectory:
    """The truth trajectory of a level ground vehicle along the path (module docstring).

    ``points_ne``: (K, 2) north/east metres about ``origin`` = ``(lat0, lon0, h0)`` (rad, rad, m; positions are
    converted with :func:`magnav_ins.maps.tangent.tangent_to_geodetic`, the same plane as a local-frame
    :class:`~magnav_ins.maps.grid.GridMap` with that origin); ``speed_mps``: the nominal speed; ``rate_hz``: sample
    rate; ``duration_s``: default the path length over the speed; ``wander`` with ``rng``: Storms' random
    perturbation (None: the nominal path exactly)."""
    from ..maps.tangent import tangent_to_geodetic

    if not (np.isfinite(speed_mps) and speed_mps > 0 and np.isfinite(rate_hz) and rate_hz > 0):
        raise ConfigError(f"ground path: speed_mps and rate_hz must be > 0, got {speed_mps!r}, {rate_hz!r}")
    path = Path2D.from_points(points_ne, corner_radius_m)
    T = path.length / speed_mps if duration_s is None else float(duration_s)
    t = np.arange(int(math.floor(T * rate_hz + 1e-9)) + 1) / rate_hz
    if wander is None:
        pts, psi = path.at(speed_mps * t)
        ne, v_ne = pts, speed_mps * np.column_stack([np.cos(psi), np.sin(psi)])
    else:
        if rng is None:
            raise ConfigError("ground path: a wandering path needs a random generator")
        dt = wander.step_s
        n = int(math.ceil(T / dt)) + 2
        tk = np.arange(n) * dt
        for _attempt in range(wander.max_attempts):
            s = _walk(n, dt, wander.accel_sigma_mps2, wander.along_gain, rng, speed_mps * tk)
            d = _walk(n, dt, wander.accel_sigma_mps2, wander.cross_gain, rng, np.zeros(n))
            if wander.max_offset_m is None or np.max(np.abs(d)) <= wander.max_offset_m:
                break
        else:
            raise ConfigError(
                f"ground path: no wandering run stayed within max_offset_m = {wander.max_offset_m} m in "
                f"{wander.max_attempts} draws (lower accel_sigma_mps2 or raise cross_gain)"
            )
        c, psi_k = path.at(s)
        pk = c + d[:, None] * np.column_stack([-np.sin(psi_k), np.cos(psi_k)])  # offset to the right
        spl = CubicSpline(tk, pk, axis=0)
        ne, v_ne = spl(t), spl(t, 1)
    lat0, lon0, h0 = (float(x) for x in origin)
    lat, lon = tangent_to_geodetic(np.ascontiguousarray(ne[:, 0]), np.ascontiguousarray(ne[:, 1]), lat0, lon0, h0)
    # NED velocity as the derivative of the geodetic position (the tangent plane turns by < 1e-5 rad over 100 m)
    r_n, r_e = radii_of_curvature(lat)
    if len(t) >= 4:
        v_n = np.column_stack(
            [
                CubicSpline(t, lat)(t, 1) * (r_n + h0),
                CubicSpline(t, lon)(t, 1) * (r_e + h0) * np.cos(lat),
                np.zeros(len(t)),
            ]
        )
    else:
        v_n = np.column_stack([v_ne, np.zeros(len(t))])
    yaw = np.unwrap(np.arctan2(v_ne[:, 1], v_ne[:, 0]))
    q = q_nb_from_euler(np.zeros(len(t)), np.zeros(len(t)), yaw)
    return NavTrajectory(t, lat, lon, np.full(len(t), h0), v_n, q)
