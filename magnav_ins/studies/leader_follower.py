"""Storms' leader-follower experiment (Storms 2009, seed 004, sec. 3.5 and 4.5, Table 4.2).

A leader drives the L-shaped hallway route (Storms sec. 4.4.1.1) with ``sensors`` three-axis magnetometers in a row
across it (0.381 m apart, his sensor spacing), recording a reading of each every 0.5 s together with its own
*estimated* position (sec. 3.5.1). The readings are gridded at those estimated positions into the follower's map
(``griddata``: :func:`magnav_ins.maps.selfbuild.leader_follower_map`). The follower, with one magnetometer and a
motion model (the constant-velocity model of eq. 3.2 with an extra control input ``u2``, eq. 3.7), navigates on
that map with Storms' Bayes grid + Kalman filter (sec. 3.4, a fix every 1.5 s) and steers itself along the
leader's estimated trajectory with a PID controller on the cross-track error (sec. 3.5.2, Diagram 3.1:
:func:`cross_track`; gains Kp = 10, Ki = 0.05, Kd = 3.5). Both vehicles move with sigma_a = 0.02 m/s^2 (sec. 4.5:
"the largest value successfully implemented").

Outcome of a run (Table 4.2): *completed* when the follower gets at least 16 m down the side hallway, *successful*
at least 10 m, *past the turn* when it enters the side hallway, otherwise it did not make the turn. A run ends when
the follower hits a wall (its true position leaves the hallway) unless ``position_reset`` is on (sec. 4.5.1: "the
vehicle's position would be reset to the opposite side of the center of the hallway").

What Storms does not state, and we chose (each a parameter): the leader's own navigation error (a first-order
Gauss-Markov offset, ``leader_error_sigma_m`` 0.05 m per axis, ``leader_error_tau_s`` 20 s); the follower's
speed control ``u1 = k_v (v_ref - v_hat)`` toward 0.5 m/s along the leader's estimated track (the leader's "turn
commands"); the follower's start (the leader's estimated start, true position off by N(0, 0.1^2) m per axis, the
filter's 1-sigma 0.1 m); the position reset puts the vehicle at half the half-width on the other side of the centre
line with no cross-track velocity; the leader's wander gains (:mod:`magnav_ins.ins.ground_path`, 0.1).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from ..aiding.fusion.cv_kf import cv_process_noise, cv_transition

FloatArray = NDArray[np.float64]

#: Storms' PID gains (sec. 3.5.2)
STORMS_KP, STORMS_KI, STORMS_KD = 10.0, 0.05, 3.5
#: sensor spacing across the leader (m, sec. 3.2.1: 15 in)
SENSOR_SPACING_M = 0.381


def cross_track(p: FloatArray, track: FloatArray, hint: int = 0) -> tuple[float, FloatArray, int, float]:
    """Storms' cross-track error (Diagram 3.1): the point ``p`` (2,) projected on the polyline ``track`` (K, 2).

    Returns the signed cross-track error ``e`` (m, positive when ``p`` is to the right of the track's direction),
    the unit tangent (2,) of the segment, the segment index (search starts at ``hint`` and goes forward, so a route
    that passes near itself is followed in order; ``hint < 0`` searches the whole track) and the along-track
    distance of the projection (m)."""
    seg = np.diff(track, axis=0)
    ln = np.hypot(seg[:, 0], seg[:, 1])
    s0 = np.concatenate([[0.0], np.cumsum(ln)])
    lo, hi = (0, len(seg)) if hint < 0 else (max(0, hint - 5), min(len(seg), hint + 60))
    a = p - track[lo:hi]
    u = np.clip(np.einsum("ij,ij->i", a, seg[lo:hi]) / np.maximum(ln[lo:hi] ** 2, 1e-12), 0.0, 1.0)
    c = track[lo:hi] + u[:, None] * seg[lo:hi]
    d = np.hypot(*(p - c).T)
    j = int(np.argmin(d))
    k = lo + j
    tang = seg[k] / max(ln[k], 1e-12)
    r = p - c[j]
    e = float(tang[0] * r[1] - tang[1] * r[0])  # right of the direction of travel = positive (NED: north, east)
    return e, tang, k, float(s0[k] + u[j] * ln[k])


@dataclass
class PidTracker:
    """PID on the signed cross-track error (Storms sec. 3.5.2): the command is the acceleration ``-(Kp e + Ki int e
    + Kd de/dt)`` along the track's right normal (m/s^2), ``e`` in m."""

    kp: float = STORMS_KP
    ki: float = STORMS_KI
    kd: float = STORMS_KD
    integral: float = 0.0
    last: float | None = None

    def command(self, e: float, dt: float) -> float:
        self.integral += e * dt
        de = 0.0 if self.last is None or dt <= 0 else (e - self.last) / dt
        self.last = e
        return -(self.kp * e + self.ki * self.integral + self.kd * de)


@dataclass(frozen=True)
class LeaderFollowerConfig:
    """One row of Table 4.2: ``sensors`` on the leader (3 or 4), ``position_reset`` on the follower; the rest as in
    the module docstring (times s, lengths m, accelerations m/s^2, field nT)."""

    sensors: int = 3
    position_reset: bool = False
    accel_sigma: float = 0.02
    speed_mps: float = 0.5
    dt: float = 0.1
    leader_interval_s: float = 0.5
    update_interval_s: float = 1.5
    reading_sigma: float = 100.0
    leader_error_sigma_m: float = 0.05
    leader_error_tau_s: float = 20.0
    speed_gain: float = 1.0
    follower_start_sigma_m: float = 0.1
    map_spacing_m: float = 0.0381
    half_width_m: float = 1.143
    completed_m: float = 16.0
    successful_m: float = 10.0
    extra: dict[str, float] = field(default_factory=dict)

    def offsets(self) -> FloatArray:
        """Sensor offsets across the leader (m, right positive), centred."""
        k = np.arange(self.sensors) - 0.5 * (self.sensors - 1)
        return k * SENSOR_SPACING_M


@dataclass(frozen=True)
class FollowerOutcome:
    """Where a follower run ended: ``side_m`` how far down the side hallway it got (m, negative: not past the
    turn), ``hit_wall`` whether it stopped at a wall, ``resets`` position resets, ``cross_rms_m`` RMS of its true
    cross-track offset from the leader's true track (m)."""

    side_m: float
    hit_wall: bool
    resets: int
    cross_rms_m: float
    fixes: int = 0
    attempts: int = 0


def gauss_markov(n: int, dt: float, sigma: float, tau: float, rng: np.random.Generator) -> FloatArray:
    """(n, 2) first-order Gauss-Markov sequence of stationary 1-sigma ``sigma`` and time constant ``tau``."""
    a = np.exp(-dt / tau)
    w = rng.normal(0.0, sigma * np.sqrt(1.0 - a * a), (n, 2))
    x = np.empty((n, 2))
    x[0] = rng.normal(0.0, sigma, 2)
    for k in range(1, n):
        x[k] = a * x[k - 1] + w[k]
    return x


def run_follower(
    cfg: LeaderFollowerConfig,
    truth_map,  # noqa: ANN001 - a local-frame GridMap of the hallway (the field both vehicles read)
    route_ne: FloatArray,
    corner_ne: FloatArray,
    rng: np.random.Generator,
) -> FollowerOutcome:
    """One leader pass and one follower run (module docstring). ``route_ne`` (K, 2): the hallway centre-line route
    (north, east m, local plane of ``truth_map``); ``corner_ne``: where the side hallway starts (its centre line's
    start; "down the side hallway" is measured from there along it)."""
    from ..aiding.matchers import BayesGridMatcher
    from ..core.types import FieldReadings, NavEstimate, NavState
    from ..ins.ground_path import Wander, ground_path
    from ..maps.selfbuild import leader_follower_map

    origin = truth_map.origin
    # --- the leader: a wandering pass, its readings and its own (estimated) track
    leader = ground_path(route_ne, cfg.speed_mps, 1.0 / cfg.dt, origin, corner_radius_m=1.0,
                         wander=Wander(accel_sigma_mps2=cfg.accel_sigma, cross_gain=0.1, along_gain=0.1,
                                       max_offset_m=0.6), rng=rng)  # fmt: skip
    ln, le = truth_map.to_local(leader.lat, leader.lon)
    l_true = np.column_stack([ln, le])
    l_est = l_true + gauss_markov(len(l_true), cfg.dt, cfg.leader_error_sigma_m, cfg.leader_error_tau_s, rng)
    head = np.arctan2(leader.v_n[:, 1], leader.v_n[:, 0])
    every = max(1, int(round(cfg.leader_interval_s / cfg.dt)))
    ks = np.arange(0, len(l_true), every)
    off = cfg.offsets()
    right = np.column_stack([-np.sin(head[ks]), np.cos(head[ks])])
    true_pos = l_true[ks, None, :] + off[None, :, None] * right[:, None, :]  # (K, S, 2)
    est_pos = l_est[ks, None, :] + off[None, :, None] * right[:, None, :]
    lat, lon = truth_map.from_local(true_pos[..., 0].ravel(), true_pos[..., 1].ravel())
    vals = truth_map.value(lat, lon) + rng.normal(0.0, cfg.reading_sigma, (lat.size, 3))
    ok = np.all(np.isfinite(vals), axis=1)
    fmap = leader_follower_map(est_pos[..., 0].ravel()[ok], est_pos[..., 1].ravel()[ok], vals[ok],
                               kind=truth_map.kind, spacing_m=cfg.map_spacing_m, origin=origin,
                               max_distance_m=0.5 * SENSOR_SPACING_M + 0.05)  # fmt: skip
    track = l_est[ks]  # the reference trajectory handed to the follower
    # --- the follower: truth x = [n, e, vn, ve], its filter, the controller
    F, Q = cv_transition(cfg.dt), cv_process_noise(cfg.dt, cfg.accel_sigma)
    L = np.linalg.cholesky(Q)
    Bd = np.array([[0.5 * cfg.dt**2, 0.0], [0.0, 0.5 * cfg.dt**2], [cfg.dt, 0.0], [0.0, cfg.dt]])
    x_hat = np.array([track[0, 0], track[0, 1], cfg.speed_mps * np.cos(head[0]), cfg.speed_mps * np.sin(head[0])])
    x = x_hat + np.r_[rng.normal(0.0, cfg.follower_start_sigma_m, 2), 0.0, 0.0]
    P = np.diag([cfg.follower_start_sigma_m**2] * 2 + [0.01**2] * 2)
    pid = PidTracker()
    bg = BayesGridMatcher(map_sigma=0.0, guards=False)
    n_steps = int(np.ceil(1.25 * len(l_true)))
    upd = max(1, int(round(cfg.update_interval_s / cfg.dt)))
    hint = 0
    resets, hit, cross, fixes, attempts = 0, False, [], 0, 0
    side_dir = route_ne[-1] - corner_ne
    side_dir = side_dir / np.hypot(*side_dir)
    hint_true = 0
    for k in range(1, n_steps):
        e, tang, hint, _ = cross_track(x_hat[:2], track, hint)
        a2 = pid.command(e, cfg.dt) * np.array([-tang[1], tang[0]])
        a1 = cfg.speed_gain * (cfg.speed_mps * tang - x_hat[2:])
        u = a1 + a2
        x = F @ x + Bd @ u + L @ rng.standard_normal(4)
        x_hat = F @ x_hat + Bd @ u
        P = F @ P @ F.T + Q
        # the hallway walls, on the follower's true position relative to the true centre-line route
        d_true, tang_t, hint_true, _ = cross_track(x[:2], route_ne, hint_true)
        cross.append(cross_track(x[:2], l_true, -1)[0] if k % 10 == 0 else np.nan)
        if abs(d_true) > cfg.half_width_m:
            if not cfg.position_reset:
                hit = True
                break
            resets += 1
            nrm = np.array([-tang_t[1], tang_t[0]])
            x[:2] = x[:2] - (d_true + np.sign(d_true) * 0.5 * cfg.half_width_m) * nrm
            x[2:] = (x[2:] @ tang_t) * tang_t
        if k % upd == 0:
            lat, lon = truth_map.from_local(np.array([x[0]]), np.array([x[1]]))
            z = truth_map.value(lat, lon)[0] + rng.normal(0.0, cfg.reading_sigma, 3)
            if np.all(np.isfinite(z)):
                attempts += 1
                la, lo = fmap.from_local(np.array([x_hat[0]]), np.array([x_hat[1]]))
                Pf = np.eye(15) * 1e-6
                Pf[:2, :2] = P[:2, :2]
                prior = NavEstimate(NavState(k * cfg.dt, float(la[0]), float(lo[0]), 0.0, np.zeros(3),
                                             np.array([0.0, 0.0, 0.0, 1.0])), Pf)  # fmt: skip
                st = bg.update(bg.initiate(prior), FieldReadings(np.array([k * cfg.dt]), z[None], cfg.reading_sigma,
                                                                 truth_map.kind), fmap)  # fmt: skip
                fix = bg.to_fix(st)
                if fix.available:
                    fixes += 1
                    fn, fe = fmap.to_local(np.array([fix.lat]), np.array([fix.lon]))
                    H = np.eye(2, 4)
                    S = H @ P @ H.T + fix.cov_ne
                    K = np.linalg.solve(S, H @ P).T
                    x_hat = x_hat + K @ (np.array([float(fn[0]), float(fe[0])]) - x_hat[:2])
                    P = (np.eye(4) - K @ H) @ P
        if (x[:2] - corner_ne) @ side_dir > np.hypot(*(route_ne[-1] - corner_ne)):
            break
    side = float((x[:2] - corner_ne) @ side_dir)
    c = np.asarray(cross, float)
    c = c[np.isfinite(c)]
    return FollowerOutcome(
        side, hit, resets, float(np.sqrt(np.mean(c**2))) if c.size else float("nan"), fixes, attempts
    )


def table_4_2(outcomes: list[FollowerOutcome], cfg: LeaderFollowerConfig) -> dict[str, int]:
    """Storms' Table 4.2 counts: completed (>= ``completed_m`` down the side hallway), successful (>=
    ``successful_m``, including the completed), past the turn (in the side hallway), not making the turn."""
    side = np.array([o.side_m for o in outcomes])
    return {
        "runs": len(outcomes),
        "completed": int(np.sum(side >= cfg.completed_m)),
        "successful": int(np.sum(side >= cfg.successful_m)),
        "past_turn": int(np.sum(side > 0.0)),
        "not_making_turn": int(np.sum(side <= 0.0)),
    }
