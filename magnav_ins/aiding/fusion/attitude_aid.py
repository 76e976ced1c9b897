"""An attitude measurement for the inertial fusers: roll, pitch and heading from an independent attitude source.

On a drone the autopilot's own attitude estimate (ArduPilot/PX4 AHRS: gravity from the accelerometers and heading
from the compass, at 10-50 Hz in ATTITUDE) bounds the two errors that make a MEMS INS useless within a minute: the
tilt (which turns gravity into a horizontal acceleration) and the heading (which rotates every velocity change).
The companion computer's INS takes it as a measurement of its attitude error state:

    z = psi_meas = rotvec(C_nb_ins C_nb_src^T)      (the error definition of :mod:`magnav_ins.ins.error_model`:
    h(x) = x[att] = psi,  H = [0 0 I 0 ...],          ``C_nb_est = (I + [psi x]) C_nb_true``)
    R = diag(sigma_roll^2, sigma_pitch^2, sigma_yaw^2)  (rad^2; in NED: the first two are tilt about north and
                                                        east, the third about down: the heading)

a linear Kalman update (Joseph form) of the error state, gated by the chi-square of ``gate_probability`` with 3 dof,
then the same closed-loop feedback as a position fix (attitude, position, velocity and biases corrected, error state
reset; Groves 2013 sec. 14.2.7). The caller computes ``z`` from its INS attitude and the source's at the source's
time stamp and applies it now (the attitude error changes slowly; the attitude itself does not).

The source's error is mostly a slowly varying bias (an AHRS levelled on accelerometers with their biases, a compass
with its deviation), not white noise: fused as independent measurements every second it would drive the INS
attitude sigma to ``sigma / sqrt(n)``, an over-confidence that the first turn exposes. So an axis is only updated
while the INS is less certain than the source (its variance above ``sigma^2``): the INS attitude sigma then stays
between about ``sigma / sqrt(2)`` and ``sigma``, never better than the source it leans on.

Works on any :class:`~.common.InertialCore` (the UKF's error state is linear in this measurement, so the Kalman update
is its unscented update exactly).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from ...core.types import Innovation
from ..gating import ChiSquareGate, nis
from .common import symmetrise


def correct_attitude(
    core, psi_meas: ArrayLike, sigma_rad: ArrayLike, gate_probability: float | None = 0.9999, t: float | None = None
) -> Innovation:  # noqa: ANN001
    """Apply ``psi_meas`` (3,) rad, the INS attitude error against the source, with 1-sigmas ``sigma_rad`` (3,) rad
    (module docstring) to ``core`` at its current time, on the axes where the INS is less certain than the source.
    Returns the innovation (``nis`` over the axes used, ``extra["axes"]`` their bit mask: 1 roll, 2 pitch, 4
    heading); a rejected one leaves ``core`` untouched."""
    from ...ins.error_model import apply_error

    z = np.asarray(psi_meas, dtype=float).reshape(3)
    s = np.asarray(sigma_rad, dtype=float).reshape(3)
    t_now = float(core.t if t is None else t)
    if not (np.all(np.isfinite(z)) and np.all(np.isfinite(s)) and np.all(s > 0)):
        return Innovation(t_now, z[:2], np.full((2, 2), np.nan), np.nan, False, "bad attitude measurement", "attitude")
    core._advance_cov()
    att = core.layout["att"]
    P = core._P
    n = P.shape[0]
    rows = [i for i in range(3) if P[att.start + i, att.start + i] > s[i] ** 2]
    if not rows:
        return Innovation(t_now, z[:2], np.full((2, 2), np.nan), np.nan, False, "INS attitude already as certain as "
                          "the source", "attitude")  # fmt: skip
    H = np.zeros((len(rows), n))
    for r, i in enumerate(rows):
        H[r, att.start + i] = 1.0
    R = np.diag(s[rows] ** 2)
    z = z[rows]
    S = H @ P @ H.T + R
    y = z
    v = nis(y, S)
    gate = ChiSquareGate(gate_probability, len(rows))
    extra = {"nis_full": float(v), "nis_dof": float(len(rows)), "axes": float(sum(1 << i for i in rows))}
    y2 = np.full(2, np.nan)
    S2 = np.full((2, 2), np.nan)
    if not gate.accepts(v):
        return Innovation(
            t_now, y2, S2, float(v), False, f"NIS {v:.1f} above gate {gate.threshold:.1f} ({len(rows)} dof)",
            "attitude", extra,
        )  # fmt: skip
    K = P @ H.T @ np.linalg.inv(S)
    dx = K @ y
    IKH = np.eye(n) - K @ H
    core._P = symmetrise(IKH @ P @ IKH.T + K @ R @ K.T, 0.0)
    core._fault_update(IKH, P, core._P, 0.0)  # an attitude aid shrinks an earlier fault's error; no fault of its own
    nav = core._stepper.nav
    core._stepper.reset(apply_error(nav, -dx[:9]))
    core._set_aux(core._aux() - dx[9:n])
    core._record_update(dx)
    core._checkpoints.pop()
    core._checkpoint()
    return Innovation(t_now, y2, S2, float(v), True, "", "attitude", extra)


def ins_attitude(core) -> np.ndarray:  # noqa: ANN001
    """The INS attitude ``q_nb`` (scalar-last) of ``core`` now, without propagating its covariance (``estimate()``
    would)."""
    return np.asarray(core._stepper.nav.q_nb, dtype=float)


def attitude_error(q_ins: ArrayLike, q_src: ArrayLike) -> np.ndarray:
    """``psi = rotvec(C_nb_ins C_nb_src^T)`` (3,) rad, NED: the INS attitude error against a source (scalar-last
    quaternions body -> NED)."""
    from scipy.spatial.transform import Rotation

    return (
        Rotation.from_quat(np.asarray(q_ins, float)) * Rotation.from_quat(np.asarray(q_src, float)).inv()
    ).as_rotvec()
