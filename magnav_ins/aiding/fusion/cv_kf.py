"""Storms' 2-D constant-velocity Kalman filter (Storms 2009, seed 004, sec. 3.3-3.4.3) behind the ``Fuser`` protocol.

The filter of Storms' indoor experiments, beside the INS + UKF: no inertial mechanisation, a horizontal position and
velocity state ``x = [p_N, p_E, v_N, v_E]`` (m, m/s; north/east of the initial position, Storms' X and Y) driven by
white acceleration noise (eq. 3.2, ``E[w w^T] = sigma_a^2 I delta(tau)``). Over a step ``dt`` (eq. 3.3-3.4, exact
for any ``dt``; Storms used 0.1 s):

    Phi = [[I, dt I], [0, I]],   Qd = sigma_a^2 [[dt^3/3 I, dt^2/2 I], [dt^2/2 I, dt I]]

(with ``sigma_a = 0.08 m/s^2``, ``dt = 0.1 s`` this is eq. 3.4's ``Qd = [.0021, .032; .032, .64] x 1e-3``).
Position fixes (the Bayes grid's posterior peak and R, or any matcher's) update it with the standard Kalman
equations (sec. 2.3.1.1; Joseph form). Storms used no innovation gate, nor does the default; ``gate_probability``
sets a chi-square gate on the innovation (a rejected fix leaves the filter untouched and its :class:`Innovation`
says why). A gate hurts where the model is wrong: through a turn the filter's covariance is too small for its real
error, and the gate then refuses the right fixes (Storms hallway, 20 runs: RMS from the first fix 2.1 m with a
0.9999 gate, 0.19 m without).

Residual monitoring (``inflate_nis``; Storms sec. 4.3.3 suggests monitoring the residuals, and the issue's remedy
for the runs lost after the turn): a fix whose normalised innovation squared exceeds ``inflate_nis`` (a chi-square
value, 2 dof) says the filter's covariance is too small for its real error (a turn the constant-velocity model did
not expect), so the whole covariance is scaled by ``NIS / 2`` (the NIS it should have had) before the update, and
the fix then pulls the state by what it is worth. Unlike a gate it never refuses a fix. Off by default (Storms').

Turn command (``turn_command = true``; Storms sec. 4.4.1.3, Fig. 4.13): the filter is told the turns the vehicle
makes. Storms gave the turn as a control input ``u`` (eq. 3.3's ``B_d u``) with the heading known at all times
(sec. 3.3); here the commanded heading change over each step is the yaw rate the vehicle executes, read from the
IMU's gyro (body z, FRD, less the Earth rate's vertical component ``-Omega_e sin(lat)``), and the velocity state is
rotated by it: ``v <- R(dpsi) v`` (a known, linear transition, applied to the covariance too). Without it the IMU
is ignored: a turn is then only an unmodelled acceleration the process noise must absorb (Fig. 4.12's loss of
accuracy after the turn).

What :meth:`CvKalmanFuser.estimate` reports: the horizontal position and velocity with their covariance in the
``LAYOUT_15`` slots (``pos`` north/east, ``vel`` north/east); the height is the held height (``altitude_hold``,
else the initial height) with zero vertical velocity; the attitude is level with the heading of the velocity (or the
gyro-integrated heading under ``turn_command``). States the filter does not model (down position and velocity,
attitude, biases) carry NaN variances: not estimated. The protection level ``hpl_m`` is the fault-free one of
:func:`~magnav_ins.aiding.fusion.integrity.hpl_fault_free` (``K sigma_max`` at the default integrity risk): Storms'
filter has no fault detection, so there is no margin for undetected faults in it.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ...core.errors import ConfigError, InputError
from ...core.frames import WGS84_OMEGA_E, euler_from_q_nb, latlon_to_meters, meters_to_latlon, q_nb_from_euler
from ...core.types import LAYOUT_15, Fix, ImuBatch, Innovation, NavEstimate, NavState
from ..gating import ChiSquareGate
from .common import ImuNoise, fix_problem, rejected
from .integrity import hpl_fault_free

FloatArray = NDArray[np.float64]

#: Storms' acceleration uncertainty (Table 4.1, sec. 3.4.1), m/s^2 (root-PSD of the white acceleration, m/s^1.5)
STORMS_ACCEL_SIGMA = 0.08
#: a fix stamped this far (s) from the filter's time is refused (the filter keeps no history to re-run)
_LATE_TOL_S = 1e-6


def cv_transition(dt: float) -> FloatArray:
    """``Phi(dt)`` of eq. 3.3 for the state ``[p_N, p_E, v_N, v_E]`` (4, 4)."""
    F = np.eye(4)
    F[0, 2] = F[1, 3] = float(dt)
    return F


def cv_process_noise(dt: float, accel_sigma: float) -> FloatArray:
    """``Qd(dt)`` of eq. 3.4 (4, 4), m^2 / m^2 s^-1 / m^2 s^-2, for white acceleration of root-PSD ``accel_sigma``."""
    q = float(accel_sigma) ** 2
    a, b, c = q * dt**3 / 3.0, q * dt**2 / 2.0, q * dt
    Q = np.zeros((4, 4))
    Q[0, 0] = Q[1, 1] = a
    Q[0, 2] = Q[2, 0] = Q[1, 3] = Q[3, 1] = b
    Q[2, 2] = Q[3, 3] = c
    return Q


class CvKalmanFuser:
    """Storms' constant-velocity Kalman filter (module docstring).

    ``init``: the starting estimate (position, horizontal velocity and their covariance are used; the initial
    heading for ``turn_command``); ``noise``: accepted for the common ``make_fuser`` signature, unused (the model has
    no IMU errors); ``accel_sigma_mps2``: Storms' sigma_a (Table 4.1: 0.08; 0.02 after his tuning, sec. 4.4.2);
    ``turn_command``: rotate the velocity with the executed yaw rate (module docstring); ``gate_probability``:
    chi-square gate on each fix (None, the default: no gate, as Storms); ``inflate_nis``: residual monitoring (module
    docstring; None = off); ``altitude_hold``: the reported height (m; default the initial
    height).
    """

    name = "cv_kf"

    def __init__(
        self,
        init: NavEstimate,
        noise: ImuNoise | None = None,  # noqa: ARG002 - the common make_fuser signature
        *,
        accel_sigma_mps2: float = STORMS_ACCEL_SIGMA,
        turn_command: bool = False,
        gate_probability: float | None = None,
        inflate_nis: float | None = None,
        altitude_hold: float | None = None,
    ) -> None:
        if not (isinstance(accel_sigma_mps2, int | float) and np.isfinite(accel_sigma_mps2) and accel_sigma_mps2 > 0):
            raise ConfigError(f"cv_kf 'accel_sigma_mps2': expected a number > 0 (m/s^2), got {accel_sigma_mps2!r}")
        if not isinstance(turn_command, bool):
            raise ConfigError(f"cv_kf 'turn_command': expected true/false, got {turn_command!r}")
        nav = init.nav
        P0 = np.asarray(init.P, dtype=float)
        pos, vel = init.layout["pos"].start, init.layout["vel"].start
        idx = [pos, pos + 1, vel, vel + 1]
        P = P0[np.ix_(idx, idx)]
        if not (np.all(np.isfinite(P)) and np.linalg.eigvalsh(0.5 * (P + P.T)).min() > 0):
            raise InputError(f"cv_kf: the initial position/velocity covariance is not positive definite: {P.tolist()}")
        self.accel_sigma = float(accel_sigma_mps2)
        self.turn_command = turn_command
        self.gate_probability = None if gate_probability is None else float(gate_probability)
        self.gate = ChiSquareGate(self.gate_probability, 2)
        if inflate_nis is not None and not (isinstance(inflate_nis, int | float) and inflate_nis > 2.0):
            raise ConfigError(f"cv_kf 'inflate_nis': expected a chi-square value > 2 (2 dof), got {inflate_nis!r}")
        self.inflate_nis = None if inflate_nis is None else float(inflate_nis)
        self.lat0, self.lon0 = float(nav.lat), float(nav.lon)
        self.h = float(nav.h) if altitude_hold is None else float(altitude_hold)
        self._t = float(nav.t)
        self.x = np.array([0.0, 0.0, float(nav.v_n[0]), float(nav.v_n[1])])
        self.P = 0.5 * (P + P.T)
        self.yaw = float(euler_from_q_nb(nav.q_nb)[2])
        self.innovations: list[Innovation] = []

    # ------------------------------------------------------------------------------------------- frames
    def _to_ne(self, lat: float, lon: float) -> FloatArray:
        dlon = (lon - self.lon0 + np.pi) % (2.0 * np.pi) - np.pi
        dn, de = latlon_to_meters(lat - self.lat0, dlon, self.lat0, self.h)
        return np.array([float(dn), float(de)])

    def _to_latlon(self, n: float, e: float) -> tuple[float, float]:
        dlat, dlon = meters_to_latlon(n, e, self.lat0, self.h)
        return self.lat0 + float(dlat), self.lon0 + float(dlon)

    # --------------------------------------------------------------------------------------------- Fuser
    @property
    def t(self) -> float:
        return self._t

    def propagate(self, imu: ImuBatch) -> None:
        """Step the CV model to each sample time (the samples only matter under ``turn_command``)."""
        t = np.asarray(imu.t, dtype=float)
        if len(t) == 0:
            return
        if not np.all(np.isfinite(t)) or t[0] <= self._t - 1e-12 or np.any(np.diff(t) <= 0):
            raise InputError(f"cv_kf.propagate: sample times must increase from t={self._t!r} s, got {t[:3].tolist()}")
        earth_down = -WGS84_OMEGA_E * np.sin(self.lat0)  # Earth rate about the local down axis, rad/s
        x, P = self.x, self.P
        for k in range(len(t)):
            dt = float(t[k] - self._t)
            if dt <= 0.0:
                continue
            F = cv_transition(dt)
            if self.turn_command:
                dpsi = (float(imu.gyro_b[k, 2]) - earth_down) * dt  # level vehicle: yaw rate = body z rate
                c, s = np.cos(dpsi), np.sin(dpsi)
                Rv = np.array([[c, -s], [s, c]])
                F[2:, 2:] = Rv  # velocity turned by the commanded heading change (eq. 3.3's control input)
                F[:2, 2:] = dt * 0.5 * (np.eye(2) + Rv)  # position: mean of the velocity over the step
                self.yaw += dpsi
            x = F @ x
            P = F @ P @ F.T + cv_process_noise(dt, self.accel_sigma)
            self._t = float(t[k])
        self.x, self.P = x, 0.5 * (P + P.T)

    def correct(self, fix: Fix, *, height_m: float | None = None, height_sigma_m: float | None = None) -> Innovation:  # noqa: ARG002
        """Kalman update with a position fix (north/east); the height aid is not used (the height is held)."""
        why = fix_problem(fix)
        if why:
            inn = rejected(fix, why)
        elif abs(float(fix.t) - self._t) > _LATE_TOL_S:
            inn = rejected(fix, f"fix at t={fix.t:.6f} s but the filter is at t={self._t:.6f} s (no history kept)")
        else:
            H = np.eye(2, 4)
            R = np.asarray(fix.cov_ne, dtype=float)
            y = self._to_ne(fix.lat, fix.lon) - H @ self.x
            S = H @ self.P @ H.T + R
            nis = float(y @ np.linalg.solve(S, y))
            if self.inflate_nis is not None and nis > self.inflate_nis:  # residual monitoring (module docstring)
                self.P = self.P * (nis / 2.0)
                S = H @ self.P @ H.T + R
                nis = float(y @ np.linalg.solve(S, y))
            if not self.gate.accepts(nis):
                inn = rejected(fix, f"NIS {nis:.1f} above gate {self.gate.threshold:.1f} (2 dof)", y, S, nis)
            else:
                K = np.linalg.solve(S, H @ self.P).T
                self.x = self.x + K @ y
                A = np.eye(4) - K @ H
                P = A @ self.P @ A.T + K @ R @ K.T  # Joseph form
                self.P = 0.5 * (P + P.T)
                inn = Innovation(float(fix.t), y, S, nis, True, "", fix.source)
        self.innovations.append(inn)
        return inn

    def estimate(self) -> NavEstimate:
        """The current solution in the ``LAYOUT_15`` slots (module docstring)."""
        lat, lon = self._to_latlon(float(self.x[0]), float(self.x[1]))
        v = self.x[2:]
        yaw = self.yaw if self.turn_command or np.hypot(*v) < 1e-6 else float(np.arctan2(v[1], v[0]))
        nav = NavState(self._t, lat, lon, self.h, np.array([v[0], v[1], 0.0]), q_nb_from_euler(0.0, 0.0, yaw))
        P15 = np.full((15, 15), np.nan)
        p, w = LAYOUT_15["pos"].start, LAYOUT_15["vel"].start
        idx = [p, p + 1, w, w + 1]
        P15[np.ix_(idx, idx)] = self.P
        return NavEstimate(nav, P15, hpl_m=hpl_fault_free(self.P[:2, :2]))
