"""A batch of correlated position fixes fused as one stacked measurement (PMHT-MM retrodiction, Wang et al. 2022
sec. 3.3: "update occurs after every T x dt with all navigation state components involved in the batch").

A retrodiction batch gives fixes ``z_j`` at times ``t_1 < ... < t_J`` (the smoothed states of one EM batch) whose
errors are strongly correlated (joint covariance ``R``, 2J x 2J). Fusing them one by one as if independent counts
the batch's evidence about J times. Here the batch is one measurement of the stacked past position errors,
handled by stochastic cloning (Roumeliotis & Burdick 2002, "Stochastic cloning: a generalized framework for
processing relative state measurements", ICRA; the same augmentation as a fixed-lag smoother):

1. The INS is re-run from the last checkpoint before ``t_1`` (the replay buffer must cover the batch).
2. At each ``t_j`` the north/east position error is cloned: the augmented covariance gains ``cov(dp_j, dp_i)``
   and ``cov(dx, dp_j)``; between fix times every covariance step ``P <- Phi P Phi^T + Q`` carries the cross terms
   as ``P_xc <- Phi P_xc`` (clones are constant), with the altitude hold's states decorrelated as the fuser does.
   The residuals ``y_j = fix_j - INS(t_j)`` are taken from the INS of this re-run (before any batch correction).
3. At ``t_J``: ``z = -c + v`` (c the stacked clones), ``S = P_cc + R``, ``K = -P_xc S^-1``, ``dx = K y``,
   ``P <- P - P_xc S^-1 P_xc^T``; the chi-square gate on ``y^T S^-1 y`` has 2J degrees of freedom. The correction is
   fed back in closed loop (as :mod:`.ukf`) and the rest of the buffered IMU samples are replayed.

For a linear measurement this is exactly the Kalman update of the stacked measurement (the UKF would give the
same). Not supported (the batch is rejected with the reason): fixes that measure a map-bias state.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike

from ...core.types import Fix, Innovation
from ..gating import ChiSquareGate, nis
from .common import _HELD, Samples, fix_problem, residual_ne, symmetrise


def _reject(fixes: Sequence[Fix], reason: str, y=None, S=None, v: float = float("nan")) -> Innovation:  # noqa: ANN001
    t = float(fixes[-1].t) if fixes else float("nan")
    src = fixes[-1].source if fixes else ""
    r = np.full(2, np.nan) if y is None else np.asarray(y, float)[-2:]
    s = np.full((2, 2), np.nan) if S is None else np.asarray(S, float)[-2:, -2:]
    return Innovation(t, r, s, float(v), False, reason, src, {"batch": float(len(fixes))})


def _step_to(core, samples, t_target: float):  # noqa: ANN001, ANN202
    """Step ``core`` through ``samples`` (:class:`.common.Samples`) up to ``t_target`` (cutting the straddling
    sample, as ``_rewind`` does); returns the samples still to replay."""
    return core._step_until(samples, t_target)


def correct_batch(core, fixes: Sequence[Fix], cov: ArrayLike, gate_probability: float | None) -> Innovation:  # noqa: ANN001
    """Fuse ``fixes`` (time order, all available) with their joint covariance ``cov`` (2J, 2J) m^2 into the
    :class:`~.common.InertialCore` ``core`` (module docstring). Returns one :class:`Innovation` at the last fix time
    (its residual and S the last fix's; ``nis`` the batch's, ``extra["batch"]`` = J, ``extra["nis_dof"]`` = 2J)."""
    fixes = list(fixes)
    J = len(fixes)
    R = np.asarray(cov, dtype=float)
    if J == 0:
        return _reject(fixes, "empty batch")
    if R.shape != (2 * J, 2 * J) or not np.all(np.isfinite(R)):
        return _reject(fixes, f"batch covariance must be a finite ({2 * J}, {2 * J}) matrix, got {R.shape}")
    R = 0.5 * (R + R.T)
    if np.linalg.eigvalsh(R).min() <= 0:
        return _reject(fixes, "batch covariance is not positive definite")
    for f in fixes:
        problem = fix_problem(f)
        if problem:
            return _reject(fixes, f"batch fix at t={f.t:.3f}: {problem}")
        if core.extra.biased(f):
            return _reject(fixes, "batch fixes that measure the map-bias state are not supported")
    ts = np.array([f.t for f in fixes], float)
    if np.any(np.diff(ts) < 0):
        return _reject(fixes, "batch fixes must be in time order")
    if ts[-1] > core.t + 1e-6:
        return _reject(fixes, f"fix time {ts[-1]:.6f} s is after the last IMU time {core.t:.6f} s")
    rest = Samples.empty()
    if ts[0] < core.t - 1e-6:
        r = core._rewind(float(ts[0]))
        if r is None:
            return _reject(fixes, f"batch start {ts[0]:.3f} s is older than the replay buffer ({core.buffer_s} s)")
        rest = r
    n = core.n_states
    box = [np.zeros((n, 0))]  # cross-covariance of the error state with the clones

    def hooked(Phi, Qd, _orig=core._predict_cov) -> None:  # noqa: ANN001
        _orig(Phi, Qd)
        box[0] = Phi @ box[0]
        if core._altitude_hold is not None:
            box[0][list(_HELD), :] = 0.0

    core._predict_cov = hooked
    try:
        Pcc = np.zeros((0, 0))
        ys = []
        for j, f in enumerate(fixes):
            if j > 0:
                rest = _step_to(core, rest, float(f.t))
            core._advance_cov()
            P = core._P
            Pxc = box[0]
            Pcc_new = np.zeros((2 * j + 2, 2 * j + 2))
            Pcc_new[: 2 * j, : 2 * j] = Pcc
            Pcc_new[2 * j :, : 2 * j] = Pxc[0:2, :]
            Pcc_new[: 2 * j, 2 * j :] = Pxc[0:2, :].T
            Pcc_new[2 * j :, 2 * j :] = P[0:2, 0:2]
            Pcc = Pcc_new
            box[0] = np.hstack([Pxc, P[:, 0:2]])
            ys.append(residual_ne(f, core._stepper.nav))
    finally:
        del core._predict_cov
    y = np.concatenate(ys)
    S = Pcc + R
    Pxc = box[0]
    v = nis(y, S)
    gate = ChiSquareGate(gate_probability, 2 * J)
    if not gate.accepts(v):
        core._replay(rest)
        return _reject(fixes, f"NIS {v:.1f} above gate {gate.threshold:.1f} ({2 * J} dof, batch of {J})", y, S, v)
    Si = np.linalg.inv(S)
    K = -Pxc @ Si
    dx = K @ y
    P_prior = core._P.copy()
    core._P = symmetrise(core._P - Pxc @ Si @ Pxc.T, 0.0)
    from ...ins.error_model import apply_error
    from .integrity import gain_transfer

    core._fault_update(gain_transfer(P_prior, core._P), P_prior, core._P, gate.threshold)

    nav = core._stepper.nav
    core._stepper.reset(apply_error(nav, -dx[:9]))
    core._set_aux(core._aux() - dx[9:n])
    core._record_update(dx)
    core._checkpoints.pop()
    core._checkpoint()
    core._replay(rest)
    S_last = S[-2:, -2:]
    return Innovation(
        float(ts[-1]), y[-2:], S_last, float(nis(y[-2:], S_last)), True, "", fixes[-1].source,
        {"batch": float(J), "nis_full": float(v), "nis_dof": float(2 * J)},
    )  # fmt: skip
