"""Unit checks of the fusion helpers against independent truth: the chi-square gate (closed form for 2 dof),
the product-only Van Loan discretisation (against scipy's expm through ins.error_model.discretize), the local
Earth-fixed frame, the graph's frame/covariance mapping (round trip), and a stationary INS that must stay put
(Earth rate and gravity handled by both fusers)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg import expm

from magnav_ins.aiding.fusion import make_fuser
from magnav_ins.aiding.fusion.common import ImuNoise, LocalFrame, _expm, discretize_fast
from magnav_ins.aiding.gating import ChiSquareGate, chi2_threshold, consistency_band, nis
from magnav_ins.core.errors import ConfigError
from magnav_ins.core.frames import C_nb_from_q, horizontal_error_m, q_nb_from_euler
from magnav_ins.core.types import LAYOUT_15, ImuBatch, NavEstimate, NavState
from magnav_ins.ins import imu_models
from magnav_ins.ins.earth import gravity_n, omega_ie_n
from magnav_ins.ins.error_model import discretize, system_matrices

NOISE = ImuNoise(1e-3, 1e-5, 1e-3, 1e-6)


def test_chi_square_gate_closed_form() -> None:
    for p in (0.5, 0.95, 0.999):
        assert chi2_threshold(2, p) == pytest.approx(-2.0 * np.log(1.0 - p), rel=1e-12)
    gate = ChiSquareGate(0.95, 2)
    assert gate.accepts(5.9) and not gate.accepts(6.0) and not gate.accepts(float("nan"))
    S = np.array([[4.0, 1.0], [1.0, 2.0]])
    r = np.array([1.0, -2.0])
    assert nis(r, S) == pytest.approx(r @ np.linalg.inv(S) @ r)
    assert nis(r, np.zeros((2, 2))) == float("inf")
    lo, hi = consistency_band(2, 50)
    assert lo < 2.0 < hi and hi - 2.0 == pytest.approx(2.0 - lo, rel=0.2)
    with pytest.raises(ConfigError):
        chi2_threshold(2, 1.0)


def test_product_only_discretisation_matches_scipy() -> None:
    A = np.random.default_rng(3).standard_normal((30, 30)) * 2.0
    assert np.allclose(_expm(A), expm(A), rtol=1e-10, atol=1e-10)
    g = imu_models.get_grade("tactical")
    q = q_nb_from_euler(0.1, -0.05, 2.0)
    F, G, Qc = system_matrices(
        0.8, 3000.0, np.array([150.0, -40.0, 2.0]), C_nb_from_q(q), np.array([0.5, 0.2, -9.9]), g
    )
    for dt in (0.01, 1.0, 10.0):
        Phi0, Qd0 = discretize(F, G, Qc, dt)
        Phi1, Qd1 = discretize_fast(F, G, Qc, dt)
        assert np.allclose(Phi1, Phi0, rtol=1e-9, atol=1e-12)
        assert np.allclose(Qd1, Qd0, rtol=1e-8, atol=1e-14 * np.abs(Qd0).max())


def test_local_frame() -> None:
    fr = LocalFrame(0.7, 0.2, 500.0)
    assert np.allclose(fr.to_L(0.7, 0.2, 500.0), 0.0, atol=1e-6)
    assert np.allclose(fr.gravity_L(np.zeros(3)), gravity_n(0.7, 500.0), atol=1e-9)
    r = np.array([20e3, -15e3, -300.0])
    lat, lon, h = fr.to_geodetic(r)
    assert np.allclose(fr.to_L(lat, lon, h), r, atol=1e-6)
    # 25 km away the plumb line has turned by about 25e3 / 6.37e6 rad
    tilt = np.arccos(fr.gravity_L(r)[2] / np.linalg.norm(fr.gravity_L(r)))
    assert tilt == pytest.approx(25e3 / 6.37e6, rel=0.02)


def _init(yaw: float = 0.7) -> NavEstimate:
    nav = NavState(0.0, 0.8, 0.15, 300.0, np.array([30.0, -10.0, 0.5]), q_nb_from_euler(0.05, -0.02, yaw))
    A = np.random.default_rng(0).standard_normal((15, 15)) * 0.1
    sig = np.r_[[3.0] * 3, [0.1] * 3, [1e-3] * 3, [1e-3] * 3, [1e-5] * 3]
    P = np.diag(sig) @ (np.eye(15) + A @ A.T) @ np.diag(sig)
    return NavEstimate(nav, P, LAYOUT_15)


@pytest.mark.parametrize("kind", ["ukf", "graph", "free_inertial"])
def test_initial_estimate_round_trip(kind: str) -> None:
    init = _init()
    est = make_fuser(kind, init, NOISE).estimate()
    assert horizontal_error_m(est.nav.lat, est.nav.lon, init.nav.lat, init.nav.lon) < 1e-6
    assert est.nav.h == pytest.approx(init.nav.h, abs=1e-6)
    assert np.allclose(est.nav.v_n, init.nav.v_n, atol=1e-9)
    assert np.allclose(C_nb_from_q(est.nav.q_nb), C_nb_from_q(init.nav.q_nb), atol=1e-12)
    # the graph maps P through its own tangent spaces (body-frame pose perturbations) and back
    assert np.allclose(est.P, init.P, rtol=1e-6, atol=1e-12)


@pytest.mark.parametrize("kind", ["ukf", "graph"])
def test_stationary_ins_stays_put(kind: str) -> None:
    lat, lon, h = 0.8, 0.15, 300.0
    q = q_nb_from_euler(0.0, 0.0, 0.4)
    C_bn = C_nb_from_q(q).T
    nav = NavState(0.0, lat, lon, h, np.zeros(3), q)
    fuser = make_fuser(kind, NavEstimate(nav, np.diag(np.r_[[1.0] * 15]) * 1e-6, LAYOUT_15), NOISE)
    t = np.arange(1, 1201) * 0.1  # 120 s at 10 Hz
    f_b = C_bn @ -gravity_n(lat, h)
    w_b = C_bn @ omega_ie_n(lat)
    fuser.propagate(ImuBatch(t, np.tile(w_b, (len(t), 1)), np.tile(f_b, (len(t), 1))))
    est = fuser.estimate().nav
    assert horizontal_error_m(est.lat, est.lon, lat, lon) < 0.05
    assert abs(est.h - h) < 0.05 and np.all(np.abs(est.v_n) < 2e-3)


def test_covariance_step_follows_a_turn() -> None:
    """A 1-s covariance step across a fast turn (90 deg/s yaw, 1 m/s^2 forward) must give the covariance that
    100 steps of 10 ms give: the bias and tilt columns of F use the attitude and navigation-frame specific force
    averaged over the step, not their end values (with end values the gyro-bias/attitude cross-covariance is
    turned by 45 deg and this fails by ~60 %). (Products of two rotating blocks, e.g. velocity/tilt, are second
    order in the step and not checked.)"""
    lat, h = 0.8, 300.0
    nav = NavState(0.0, lat, 0.15, h, np.array([10.0, 0.0, 0.0]), q_nb_from_euler(0.0, 0.0, 0.0))
    sig = np.r_[[1.0] * 3, [0.1] * 3, [1e-3] * 3, [0.05] * 3, [0.01] * 3]
    init = NavEstimate(nav, np.diag(sig**2), LAYOUT_15)
    t = np.arange(1, 101) * 0.01
    w_b = np.tile([0.0, 0.0, np.pi / 2], (len(t), 1))
    f_b = np.tile([1.0, 0.0, -gravity_n(lat, h)[2]], (len(t), 1))
    P = {}
    for step in (1.0, 0.01):
        fuser = make_fuser("ukf", init, NOISE, cov_step_s=step)
        fuser.propagate(ImuBatch(t, w_b, f_b))
        P[step] = fuser.estimate().P
    fine, coarse = P[0.01], P[1.0]
    for blk in ((slice(6, 9), slice(12, 15)), (slice(3, 6), slice(9, 12))):  # bias columns: first order exact
        ref = fine[blk]
        assert np.abs(coarse[blk] - ref).max() < 0.02 * np.abs(ref).max(), blk
    assert np.allclose(np.diag(coarse)[6:9], np.diag(fine)[6:9], rtol=0.02)
