"""A batch of correlated fixes fused as one stacked measurement (aiding/fusion/batch.py, PMHT retrodiction).

Synthetic case with a known truth: a 400 s flight with turns (tactical IMU, 10 Hz, altitude held), initial errors
drawn from the initial covariance, and every 100 s a batch of 10 fixes 10 s apart whose errors share a common
offset: ``R = 1 1^T (x) R_c + I (x) R_i`` (R_c = 30 m, R_i = 8 m 1-sigma per axis), drawn from exactly that joint
covariance. Fused with the joint covariance, the filter's horizontal NEES after each batch is chi-square with 2
dof (mean 2); fused fix by fix as if independent, the common offset is counted ten times and the filter is
over-confident (NEES well above 3).
"""

from __future__ import annotations

import dataclasses
from functools import lru_cache

import numpy as np
import pytest

from magnav_ins.aiding.fusion import make_fuser
from magnav_ins.aiding.fusion.common import ImuNoise
from magnav_ins.core.types import LAYOUT_15, Fix, NavEstimate
from magnav_ins.core.units import DEG_TO_RAD
from magnav_ins.ins import imu_models, simulate
from magnav_ins.ins.error_model import apply_error, nav_error

RATE_HZ = 5.0
DURATION_S = 400.0
BATCH = 10
DT_FIX = 10.0
RC = np.diag([30.0, 30.0]) ** 2
RI = np.diag([8.0, 8.0]) ** 2
SIG0 = np.r_[[100.0] * 3, [0.5] * 3, 0.05 * DEG_TO_RAD, 0.05 * DEG_TO_RAD, 0.5 * DEG_TO_RAD]
RUNS = 8


@lru_cache(maxsize=1)
def truth():
    d = DEG_TO_RAD
    pts = np.array([[45.0, 7.0, 3000.0], [45.1, 7.1, 3000.0], [45.05, 7.3, 3000.0], [45.2, 7.4, 3000.0]])
    pts[:, :2] *= d
    traj = simulate.waypoints(pts, 60.0, RATE_HZ, turn_rate=3.0 * d)
    traj = traj.slice(0, int(DURATION_S * RATE_HZ) + 1)
    return traj, simulate.ideal_imu(traj)


def joint_cov(J: int) -> np.ndarray:
    return np.kron(np.ones((J, J)), RC) + np.kron(np.eye(J), RI)


def _run(seed: int, batch: bool) -> list[float]:
    rng = np.random.default_rng(seed)
    traj, imu = truth()
    g = imu_models.get_grade("tactical")
    err = dataclasses.replace(imu_models.draw_errors(g, rng), M_g=np.zeros((3, 3)), M_a=np.zeros((3, 3)))
    imu_c, _ = imu_models.corrupt(imu, g, rng, err)
    nz = ImuNoise.from_grade(g)
    P0 = np.diag(np.r_[SIG0, [nz.accel_bias_init_sigma] * 3, [nz.gyro_bias_init_sigma] * 3] ** 2)
    init = NavEstimate(apply_error(traj.at(0), rng.standard_normal(9) * SIG0 * np.r_[1, 1, 0, 1, 1, 0, 1, 1, 1]), P0)
    fuser = make_fuser(
        "ukf", init, nz, altitude_hold=float(traj.h[0]), buffer_s=150.0, cov_step_s=5.0, gate_probability=None
    )
    L = np.linalg.cholesky(joint_cov(BATCH))
    nees, i = [], 0
    for b in range(int(DURATION_S // (BATCH * DT_FIX))):
        times = DT_FIX * (b * BATCH + 1 + np.arange(BATCH))
        e = (L @ rng.standard_normal(2 * BATCH)).reshape(BATCH, 2)
        fixes = []
        for t, ek in zip(times, e, strict=True):
            s = traj.at(int(np.argmin(np.abs(traj.t - t))))
            noisy = apply_error(s, np.r_[ek, 0.0, np.zeros(6)])
            fixes.append(Fix(float(t), noisy.lat, noisy.lon, RC + RI, source="batch"))
        j = int(np.searchsorted(imu_c.t, times[-1] + 1e-9, side="right"))
        fuser.propagate(imu_c.slice(i, j))
        i = j
        if batch:
            inn = fuser.correct_batch(fixes, joint_cov(BATCH))
            assert inn.accepted, inn.reason
            assert inn.extra["batch"] == BATCH and inn.extra["nis_dof"] == 2 * BATCH
        else:
            for f in fixes:
                assert fuser.correct(f).accepted
        est = fuser.estimate()
        k = int(np.argmin(np.abs(traj.t - est.nav.t)))
        d = nav_error(est.nav, traj.at(k))[:2]
        nees.append(float(d @ np.linalg.solve(np.asarray(est.P)[:2, :2], d)))
    return nees


@pytest.fixture(scope="module")
def nees():
    return {mode: np.concatenate([_run(100 + r, mode) for r in range(RUNS)]) for mode in (True, False)}


def test_correlated_batch_gives_consistent_nees(nees):
    assert 1.0 <= np.mean(nees[True]) <= 3.0, np.mean(nees[True])


def test_the_same_fixes_taken_as_independent_are_over_confident(nees):
    assert np.mean(nees[False]) > 3.0 and np.mean(nees[False]) > 2.0 * np.mean(nees[True]), {
        k: float(np.mean(v)) for k, v in nees.items()
    }


def test_a_batch_equals_the_stacked_kalman_update_when_all_fixes_share_one_time():
    """Degenerate check against the closed form: J fixes at the current time with joint covariance R act like one
    fix at their R-weighted mean with covariance (1' R^-1 1)^-1 (generalised least squares)."""
    traj, imu = truth()
    nz = ImuNoise.from_grade(imu_models.get_grade("tactical"))
    P0 = np.diag(np.r_[SIG0, [nz.accel_bias_init_sigma] * 3, [nz.gyro_bias_init_sigma] * 3] ** 2)
    n = int(50 * RATE_HZ)
    t = float(imu.t[n - 1])
    s = traj.at(int(np.argmin(np.abs(traj.t - t))))
    offs = np.array([[20.0, -10.0], [35.0, 5.0], [10.0, 0.0]])
    fixes = []
    for o in offs:
        p = apply_error(s, np.r_[o, 0.0, np.zeros(6)])
        fixes.append(Fix(t, p.lat, p.lon, RC + RI, source="x"))
    R = joint_cov(3)
    a = make_fuser("ukf", NavEstimate(traj.at(0), P0, LAYOUT_15), nz, altitude_hold=3000.0, gate_probability=None)
    b = make_fuser("ukf", NavEstimate(traj.at(0), P0, LAYOUT_15), nz, altitude_hold=3000.0, gate_probability=None)
    a.propagate(imu.slice(0, n))
    b.propagate(imu.slice(0, n))
    a.correct_batch(fixes, R)
    H = np.kron(np.ones((3, 1)), np.eye(2))
    Ri = np.linalg.inv(R)
    C = np.linalg.inv(H.T @ Ri @ H)
    mean = C @ H.T @ Ri @ offs.reshape(-1)
    p = apply_error(s, np.r_[mean, 0.0, np.zeros(6)])
    b.correct(Fix(t, p.lat, p.lon, C, source="x"))
    ea, eb = a.estimate(), b.estimate()
    assert np.allclose(nav_error(ea.nav, eb.nav)[:2], 0.0, atol=1e-3)
    assert np.allclose(np.asarray(ea.P)[:2, :2], np.asarray(eb.P)[:2, :2], rtol=1e-6)
