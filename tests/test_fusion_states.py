"""The optional UKF states behind ``make_fuser`` options (:class:`magnav_ins.aiding.fusion.common.ExtraStates`):
accelerometer / gyro scale factors (``scale_factors``) and the map-registration bias of the fixes
(``map_bias_sigma_m``, ``map_bias_tau_s``, ``map_bias_sources``), tested against independent truth on the
manoeuvring flight of :mod:`magnav_ins.ins.manoeuvre`.

* The flight generator itself: round trip ideal IMU -> strapdown, analytic speed / heading / height.
* The scale-factor columns of the error model against the strapdown (linear propagation of a known scale-factor
  error vs the INS error it causes).
* A tactical IMU with known scale factors (``imu_models`` truth injection), fixes = truth + 1 m noise every 2 s:
  the 21-state UKF recovers the excited scale factors and beats the 15-state filter on the same data.
* Fixes from a map shifted by a known vector (truth + offset) mixed with sparse unbiased fixes: the map-bias state
  converges to the offset and the position is unbiased, where the 15-state filter follows the shifted map.
* Without options the filter is the 15-state one; unexcited extra states leave it unchanged; bad options are
  named in a :class:`ConfigError`.
"""

from __future__ import annotations

import dataclasses
import math
import re
from functools import lru_cache

import numpy as np
import pytest

from magnav_ins.aiding.fusion import EXTRA_STATE_OPTIONS, check_fusion_options, make_fuser
from magnav_ins.aiding.fusion.common import ExtraStates, ImuNoise, step_matrices
from magnav_ins.core.errors import ConfigError
from magnav_ins.core.frames import C_nb_from_q, euler_from_q_nb, radii_of_curvature
from magnav_ins.core.types import LAYOUT_15, Fix, ImuBatch, NavEstimate, NavTrajectory
from magnav_ins.core.units import DEG_TO_RAD, PPM
from magnav_ins.ins import imu_models
from magnav_ins.ins.error_model import apply_error, nav_error
from magnav_ins.ins.manoeuvre import ACCELERATIONS, TURNS, manoeuvring_flight
from magnav_ins.ins.simulate import ideal_imu
from magnav_ins.ins.strapdown import integrate

D = DEG_TO_RAD
LAT0, LON0, H0 = 45.0 * D, 7.0 * D, 3000.0
RATE_HZ = 10.0
#: twice the default heading rates (6 deg/s, bank up to ~43 deg) and 1.5x the accelerations (2.25 m/s^2): the
#: default standard-rate turns excite the gyro scale factors too weakly for 1 m fixes
STRONG = {
    "turns": tuple((s, n, 2.0 * p) for s, n, p in TURNS),
    "accelerations": tuple((s, n, 1.5 * p) for s, n, p in ACCELERATIONS),
}
S_A = np.array([2000.0, -1500.0, 2500.0]) * PPM  # true scale-factor errors, body FRD x, y, z
S_G = np.array([-2000.0, 3000.0, 1500.0]) * PPM
SF_SIGMA = 2000.0 * PPM  # the prior (and the grade's) scale-factor 1-sigma
SIG0 = np.r_[[10.0] * 3, [0.1] * 3, 0.02 * D, 0.02 * D, 0.2 * D]  # initial nav 1-sigma: m, m/s, rad
H_SIGMA = 3.0  # m, height aid with each fix


def horizontal_rms(e: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(np.asarray(e)[:, :2] ** 2, axis=1))))


# --- the manoeuvring flight ----------------------------------------------------------------------------------
def test_manoeuvring_flight_round_trip_and_kinematics() -> None:
    """Ideal IMU of the default flight (100 Hz, 600 s) integrated by the strapdown gives the flight back; speed,
    track and height follow the integrals of the pulses (each ``peak * length / 2``)."""
    traj = manoeuvring_flight(LAT0, LON0, H0, 600.0, 100.0)
    nav = integrate(traj.at(0), ideal_imu(traj))
    e = nav_error(nav, traj)
    assert np.abs(e[:, :2]).max() < 0.01  # measured 1.2 mm
    assert np.abs(e[:, 2]).max() < 0.05  # measured 5 mm (the unstable vertical channel)
    assert np.abs(e[:, 3:6]).max() < 1e-4 and np.abs(e[:, 6:9]).max() < 1e-8  # 1.7e-5 m/s, 2e-10 rad
    # velocity is the derivative of the position
    r_n, r_e = radii_of_curvature(traj.lat)
    v_fd = np.stack([np.gradient(traj.lat, traj.t) * (r_n + traj.h),
                     np.gradient(np.unwrap(traj.lon), traj.t) * (r_e + traj.h) * np.cos(traj.lat),
                     -np.gradient(traj.h, traj.t)], axis=-1)  # fmt: skip
    assert np.abs(v_fd - traj.v_n)[1:-1].max() < 1e-4
    # analytic states after whole pulses
    speed = np.hypot(traj.v_n[:, 0], traj.v_n[:, 1])
    k = {s: int(round(s * 100.0)) for s in (50.0, 100.0, 600.0)}
    assert speed[k[50.0]] == pytest.approx(60.0 + 1.5 * 15.0, abs=1e-6)  # after the first acceleration pulse
    assert traj.h[k[100.0]] == pytest.approx(H0 + 8.0 * 20.0, abs=1e-5)  # after the first climb
    assert speed[-1] == pytest.approx(60.0, abs=1e-6) and traj.h[-1] == pytest.approx(H0, abs=1e-5)
    roll, pitch, yaw = euler_from_q_nb(traj.q_nb)
    assert yaw[k[100.0]] == pytest.approx(3.0 * D * 20.0, abs=1e-9)  # after the first turn (60 deg right)
    assert abs(yaw[-1]) < 1e-9  # the turns cancel
    assert np.max(roll) == pytest.approx(math.atan(np.max(speed * 3.0 * D) / 9.80665), abs=0.01)
    assert np.allclose(np.tan(pitch), -traj.v_n[:, 2] / speed, atol=1e-12)


def test_manoeuvring_flight_bad_input() -> None:
    with pytest.raises(ConfigError, match="duration_s"):
        manoeuvring_flight(LAT0, LON0, H0, -1.0)
    with pytest.raises(ConfigError, match="turns pulse"):
        manoeuvring_flight(LAT0, LON0, H0, turns=((10.0, 0.0, 0.05),))
    with pytest.raises(ConfigError, match="accelerations must be"):
        manoeuvring_flight(LAT0, LON0, H0, accelerations=((10.0, 5.0),))
    with pytest.raises(ConfigError, match="stop the aircraft"):
        manoeuvring_flight(LAT0, LON0, H0, 100.0, accelerations=((10.0, 40.0, -5.0),))
    with pytest.raises(ConfigError, match="lat0"):
        manoeuvring_flight(float("nan"), LON0, H0)


# --- the error model's scale-factor columns ------------------------------------------------------------------
def test_scale_factor_columns_predict_the_strapdown_error() -> None:
    """A known scale-factor error on an ideal IMU: the INS error of the strapdown over 200 s of the strong flight
    agrees with the linear propagation ``x <- Phi x`` of :func:`step_matrices` (21 states, 1 s steps along the
    truth) started from ``ds = -s`` (error = estimate 0 minus truth)."""
    traj = manoeuvring_flight(LAT0, LON0, H0, 200.0, RATE_HZ, **STRONG)
    imu = ideal_imu(traj)
    bad = ImuBatch(imu.t, imu.gyro_b * (1.0 + S_G), imu.accel_b * (1.0 + S_A))
    e_ins = nav_error(integrate(traj.at(0), bad), traj)
    noise = ImuNoise(0.0, 0.0, 0.0, 0.0, math.inf, math.inf, accel_scale_sigma=1e-3, gyro_scale_sigma=1e-3)
    extra = ExtraStates.from_options(noise, scale_factors=True)
    x = np.r_[np.zeros(15), -S_A, -S_G]
    C = C_nb_from_q(traj.q_nb)
    per = int(RATE_HZ)
    pred = [x[:9].copy()]
    for k0 in range(0, len(traj) - 1, per):
        C_sum, fn_sum, Cf_sum, Cw_sum, T = np.zeros((3, 3)), np.zeros(3), np.zeros((3, 3)), np.zeros((3, 3)), 0.0
        for k in range(k0 + 1, k0 + per + 1):
            dt = traj.t[k] - traj.t[k - 1]
            C_mid = 0.5 * (C[k - 1] + C[k])
            C_sum += C_mid * dt
            fn_sum += C_mid @ imu.accel_b[k] * dt
            Cf_sum += C_mid * imu.accel_b[k] * dt
            Cw_sum += C_mid * imu.gyro_b[k] * dt
            T += dt
        Phi, _ = step_matrices(traj.at(k0 + per), C_sum, fn_sum, T, T, noise, extra, Cf_sum, Cw_sum)
        x = Phi @ x
        pred.append(x[:9].copy())
    pred = np.array(pred)
    ins = e_ins[::per]
    assert np.abs(ins[:, :2]).max() > 300.0  # the scale factors matter: 360 m horizontal after 200 s
    # measured: 1.4 m of 360 m, 0.024 m/s of 5.6 m/s, 1e-5 rad of 5e-3 rad
    assert np.abs(pred[:, :2] - ins[:, :2]).max() < 0.01 * np.abs(ins[:, :2]).max()
    assert np.abs(pred[:, 3:5] - ins[:, 3:5]).max() < 0.01 * np.abs(ins[:, 3:5]).max()
    assert np.abs(pred[:, 6:9] - ins[:, 6:9]).max() < 0.01 * np.abs(ins[:, 6:9]).max()


# --- scale-factor states on the manoeuvring flight -----------------------------------------------------------
@lru_cache(maxsize=1)
def strong_flight() -> tuple[NavTrajectory, ImuBatch]:
    traj = manoeuvring_flight(LAT0, LON0, H0, 600.0, RATE_HZ, **STRONG)
    return traj, ideal_imu(traj)


def sf_grade() -> imu_models.ImuGrade:
    """Tactical (HG-1700) noise and biases with 2000 ppm scale-factor sigmas, no misalignment."""
    return dataclasses.replace(imu_models.get_grade("tactical"), accel_scale_sigma=SF_SIGMA, gyro_scale_sigma=SF_SIGMA)


@lru_cache(maxsize=2)
def sf_inputs(seed: int = 0) -> tuple[NavEstimate, ImuBatch, list[tuple[Fix, float]], imu_models.ImuErrorsTrace]:
    """Initial estimate, IMU with the known scale factors ``S_A``, ``S_G`` (plus the grade's drawn biases and
    noise), (fix, height) pairs every 2 s (truth + N(0, 1 m^2) north/east, height sigma ``H_SIGMA``)."""
    traj, imu = strong_flight()
    rng = np.random.default_rng(seed)
    g = sf_grade()
    err = dataclasses.replace(imu_models.draw_errors(g, rng), M_a=np.diag(S_A), M_g=np.diag(S_G))
    imu_c, trace = imu_models.corrupt(imu, g, rng, err)
    noise = ImuNoise.from_grade(g)
    P0 = np.diag(np.r_[SIG0, [noise.accel_bias_init_sigma] * 3, [noise.gyro_bias_init_sigma] * 3] ** 2)
    init = NavEstimate(apply_error(traj.at(0), rng.standard_normal(9) * SIG0), P0, LAYOUT_15)
    fixes = []
    step = int(round(2.0 * RATE_HZ))
    for k in range(step, len(traj), step):
        s = traj.at(k)
        noisy = apply_error(s, np.r_[rng.standard_normal(2), np.zeros(7)])
        fixes.append(
            (Fix(s.t, noisy.lat, noisy.lon, np.eye(2), source="truth+noise"), s.h + H_SIGMA * rng.standard_normal())
        )
    return init, imu_c, fixes, trace


def fly(init: NavEstimate, imu: ImuBatch, fixes, noise: ImuNoise, truth: NavTrajectory, delay_s: float = 0.0, **opt):
    """Run a UKF over the fixes (each applied ``delay_s`` after its time); returns the fuser, the horizontal errors
    (m) and covariances after each fix."""
    f = make_fuser("ukf", init, noise, **opt)
    i, errs, covs = 0, [], []
    for fix, h in fixes:
        j = int(np.searchsorted(imu.t, fix.t + delay_s + 1e-9, side="right"))
        f.propagate(imu.slice(i, j))
        i = j
        f.correct(fix, height_m=h, height_sigma_m=H_SIGMA)
        est = f.estimate()
        errs.append(nav_error(est.nav, truth.at(int(round(est.nav.t * RATE_HZ))))[:2])
        covs.append(np.asarray(est.P))
    return f, np.array(errs), np.array(covs)


@lru_cache(maxsize=4)
def sf_run(states: int, delay_s: float = 0.0):
    traj, _ = strong_flight()
    init, imu, fixes, _ = sf_inputs()
    opt = {"scale_factors": True} if states == 21 else {}
    return fly(init, imu, fixes, ImuNoise.from_grade(sf_grade()), traj, delay_s, **opt)


def test_scale_factor_states_recover_the_injected_scale_factors() -> None:
    f, _, covs = sf_run(21)
    s_est = np.r_[f.scale_factor]
    s_true = np.r_[S_A, S_G]
    sig = np.sqrt(np.diag(covs[-1])[15:21])
    assert f.layout["s_a"] == slice(15, 18) and f.layout["s_g"] == slice(18, 21)
    # seed 0, ppm (estimate / truth / 1-sigma): s_a 893 / 2000 / 1196, -10 / -1500 / 1997, 1542 / 2500 / 583;
    # s_g -1728 / -2000 / 354, 3323 / 3000 / 437, 1496 / 1500 / 432
    excited = sig < 0.5 * SF_SIGMA
    names = ["s_ax", "s_ay", "s_az", "s_gx", "s_gy", "s_gz"]
    assert [n for n, e in zip(names, excited, strict=True) if e] == ["s_az", "s_gx", "s_gy", "s_gz"], sig / PPM
    err = s_est - s_true
    assert np.all(np.abs(err) < 3.0 * sig), (err / sig).round(2)  # every state, excited or not
    # the excited ones: at least half of the scale-factor error removed
    assert np.all(np.abs(err[excited]) < 0.5 * np.abs(s_true[excited])), (s_est / PPM).round(0)
    # the fed-back estimates are what the filter reports
    assert np.allclose(f._aux()[6:12], s_est)


def test_scale_factor_states_beat_the_15_state_filter() -> None:
    _, e15, _ = sf_run(15)
    _, e21, c21 = sf_run(21)
    rms15, rms21 = horizontal_rms(e15), horizontal_rms(e21)
    assert rms21 < 0.9 * rms15, (rms21, rms15)  # measured 0.872 m vs 1.103 m
    nees = np.array([e @ np.linalg.solve(P[:2, :2], e) for e, P in zip(e21, c21, strict=True)])
    assert 0.5 < nees.mean() < 3.0, nees.mean()  # 2 dof; measured 2.21 (the 15-state filter: 3.67)


def test_scale_factor_states_with_late_fixes() -> None:
    """Fixes arriving 3 s late are applied at their time (rewind and replay of the scale-factor estimates too)."""
    f0, _, c0 = sf_run(21)
    f3, e3, _ = sf_run(21, 3.0)
    assert all(inn.accepted for inn in f3.innovations)
    sig = np.sqrt(np.diag(c0[-1])[15:21])
    assert np.all(np.abs(np.r_[f3.scale_factor] - np.r_[f0.scale_factor]) < 0.05 * sig)
    assert horizontal_rms(e3) < 1.5  # the late run's estimates are 3 s after the fix


# --- map-registration bias -----------------------------------------------------------------------------------
OFFSET = np.array([40.0, -25.0])  # m north, east: the map is shifted by this vector


@lru_cache(maxsize=1)
def map_inputs(seed: int = 0):
    """Default manoeuvring flight, tactical IMU (no scale factors); fixes every 3 s from a map shifted by
    ``OFFSET`` (source "map", truth + OFFSET + N(0, 25 m^2)) and every 30 s unbiased (source "gnss", sigma 5 m)."""
    traj = manoeuvring_flight(LAT0, LON0, H0, 600.0, RATE_HZ)
    imu = ideal_imu(traj)
    rng = np.random.default_rng(seed)
    g = imu_models.get_grade("tactical")
    err = dataclasses.replace(imu_models.draw_errors(g, rng), M_a=np.zeros((3, 3)), M_g=np.zeros((3, 3)))
    imu_c, _ = imu_models.corrupt(imu, g, rng, err)
    noise = ImuNoise.from_grade(g)
    P0 = np.diag(np.r_[SIG0, [noise.accel_bias_init_sigma] * 3, [noise.gyro_bias_init_sigma] * 3] ** 2)
    init = NavEstimate(apply_error(traj.at(0), rng.standard_normal(9) * SIG0), P0, LAYOUT_15)
    fixes = []
    for k in range(int(3 * RATE_HZ), len(traj), int(3 * RATE_HZ)):
        s = traj.at(k)
        for every, src, off in ((30.0, "gnss", np.zeros(2)), (3.0, "map", OFFSET)):
            if k % int(every * RATE_HZ) == 0:
                noisy = apply_error(s, np.r_[off + 5.0 * rng.standard_normal(2), np.zeros(7)])
                fix = Fix(s.t, noisy.lat, noisy.lon, 25.0 * np.eye(2), source=src)
                fixes.append((fix, s.h + H_SIGMA * rng.standard_normal()))
    return traj, init, imu_c, fixes, noise


def test_map_bias_state_estimates_a_shifted_map() -> None:
    traj, init, imu, fixes, noise = map_inputs()
    f, e, covs = fly(init, imu, fixes, noise, traj, map_bias_sigma_m=50.0, map_bias_tau_s=math.inf,
                     map_bias_sources=["map"])  # fmt: skip
    assert f.layout["b_map"] == slice(15, 17)
    b, sig = f.map_bias, np.sqrt(np.diag(covs[-1])[15:17])
    # seed 0: b_map (38.70, -22.98) m, 1-sigma 1.17 m (prior 50 m); position mean error (1.53, -1.73) m, 1-sigma
    # 2.78 m; the 15-state filter's mean error (40.90, -24.64) m
    assert np.all(sig < 3.0), sig
    assert np.all(np.abs(b - OFFSET) < 3.0 * sig), (b, sig)
    assert all(inn.accepted for inn in f.innovations)
    half = len(e) // 2
    pos_sig = np.sqrt(np.mean(covs[half:, [0, 1], [0, 1]], axis=0))
    mean_err = e[half:].mean(axis=0)
    assert np.all(np.abs(mean_err) < pos_sig), (mean_err, pos_sig)  # unbiased: mean error below one 1-sigma
    # the 15-state filter on the same data follows the shifted map (its position is off by about the offset)
    _, e15, _ = fly(init, imu, fixes, noise, traj)
    mean15 = e15[half:].mean(axis=0)
    assert np.all(np.abs(mean15 - OFFSET) < 0.2 * np.abs(OFFSET)), mean15
    assert horizontal_rms(e) < 0.3 * horizontal_rms(e15), (horizontal_rms(e), horizontal_rms(e15))


# --- the default filter and unexcited extra states -----------------------------------------------------------
@pytest.mark.parametrize("kind", ["ukf", "free_inertial"])
def test_default_filter_has_15_states(kind: str) -> None:
    init, imu, _, _ = sf_inputs()
    noise = ImuNoise.from_grade(sf_grade())
    f = make_fuser(kind, init, noise)
    f.propagate(imu.slice(0, 51))
    est = f.estimate()
    assert f.layout is LAYOUT_15 and est.layout is LAYOUT_15 and np.asarray(est.P).shape == (15, 15)
    assert not np.any(f.scale_factor[0]) and not np.any(f.map_bias)
    for opt, n, blocks in (
        ({"scale_factors": True}, 21, {"s_a": (15, 18), "s_g": (18, 21)}),
        ({"map_bias_sigma_m": 20.0}, 17, {"b_map": (15, 17)}),
        ({"scale_factors": True, "map_bias_sigma_m": 20.0}, 23, {"s_a": (15, 18), "s_g": (18, 21), "b_map": (21, 23)}),
    ):
        g = make_fuser(kind, init, noise, **opt)
        P = np.asarray(g.estimate().P)
        assert P.shape == (n, n) and g.estimate().layout.size == n
        for name, (a, b) in blocks.items():
            assert g.layout[name] == slice(a, b)
        assert np.allclose(P[:15, :15], np.asarray(init.P))  # the 15-state prior untouched, extra priors appended
        if "s_a" in blocks:
            assert np.allclose(np.diag(P)[15:21], SF_SIGMA**2)
        if "b_map" in blocks:
            assert np.allclose(np.diag(P)[blocks["b_map"][0] : blocks["b_map"][1]], 400.0)


def test_unexcited_extra_states_leave_the_15_state_filter_unchanged() -> None:
    """A map-bias state that no fix measures (sources do not match) changes nothing; scale-factor states with a
    negligible prior (1e-9) reproduce the 15-state filter (to 2e-9 m)."""
    traj, _ = strong_flight()
    init, imu, fixes, _ = sf_inputs()
    noise = ImuNoise.from_grade(sf_grade())
    fixes = fixes[:60]  # 120 s
    f15, e15, c15 = fly(init, imu, fixes, noise, traj)
    f17, e17, c17 = fly(init, imu, fixes, noise, traj, map_bias_sigma_m=30.0, map_bias_sources=["some map"])
    sd = np.sqrt(np.einsum("nii->ni", c15))

    def corr_diff(c: np.ndarray) -> float:
        """Largest difference of the 15-state blocks, scaled by the 15-state filter's standard deviations."""
        return float(np.abs((c[:, :15, :15] - c15) / (sd[:, :, None] * sd[:, None, :])).max())

    assert np.abs(e17 - e15).max() < 1e-9  # measured 0
    assert corr_diff(c17) < 1e-9  # measured 5e-15
    assert np.abs(f17.map_bias).max() < 1e-9  # round-off only (1e-15 m with numpy 2.4)
    assert np.allclose(c17[-1][15:17, 15:17], 900.0 * np.eye(2))
    assert np.abs(c17[:, :15, 15:]).max() < 1e-20  # never correlated with the navigation states
    tiny = dataclasses.replace(noise, accel_scale_sigma=1e-9, gyro_scale_sigma=1e-9)
    f21, e21, c21 = fly(init, imu, fixes, tiny, traj, scale_factors=True)
    assert np.abs(e21 - e15).max() < 1e-6  # measured 2e-9 m
    assert corr_diff(c21) < 1e-6  # measured 3e-11
    assert np.all(np.abs(np.r_[f21.scale_factor]) < 1e-12)


# --- option validation ---------------------------------------------------------------------------------------
BAD_OPTIONS = [
    ("ukf", {"scale_factor": True}, "'scale_factor'"),  # typo of scale_factors
    ("graph", {"scale_factors": True}, "'scale_factors' for 'graph'"),  # the graph has no optional states
    ("ukf", {"scale_factors": "yes"}, "scale_factors: expected true or false"),
    ("ukf", {"scale_factors": True, "scale_factor_tau_s": -5.0}, "scale_factor_tau_s: expected a number > 0"),
    ("ukf", {"scale_factor_tau_s": 100.0}, "scale_factor_tau_s needs scale_factors"),
    ("ukf", {"map_bias_sigma_m": 0.0}, "map_bias_sigma_m: expected a number > 0"),
    ("free_inertial", {"map_bias_sigma_m": float("nan")}, "map_bias_sigma_m: expected a number > 0"),
    ("ukf", {"map_bias_sigma_m": True}, "map_bias_sigma_m: expected a number > 0"),
    ("ukf", {"map_bias_sigma_m": 10.0, "map_bias_tau_s": "1 h"}, "map_bias_tau_s: expected a number > 0"),
    ("ukf", {"map_bias_tau_s": 100.0}, "map_bias_tau_s needs map_bias_sigma_m"),
    ("ukf", {"map_bias_sources": ["map"]}, "map_bias_sources needs map_bias_sigma_m"),
    ("ukf", {"map_bias_sigma_m": 10.0, "map_bias_sources": [1, 2]}, "map_bias_sources: expected a list"),
    ("ukf", {"map_bias_sigma_m": 10.0, "map_bias_sources": []}, "map_bias_sources: expected a list"),
    ("ekf", {}, "unknown fusion kind 'ekf'"),
]


@pytest.mark.parametrize(("kind", "options", "needle"), BAD_OPTIONS)
def test_bad_options_raise_config_error_naming_them(kind: str, options: dict, needle: str) -> None:
    init, _, _, _ = sf_inputs()
    noise = ImuNoise.from_grade(sf_grade())
    with pytest.raises(ConfigError, match=re.escape(needle)):
        make_fuser(kind, init, noise, **options)
    with pytest.raises(ConfigError, match=re.escape(needle)):
        check_fusion_options(kind, options)  # without building (or a noise model)


def test_scale_factors_need_scale_factor_sigmas_and_options_are_listed() -> None:
    init, _, _, _ = sf_inputs()
    plain = ImuNoise.from_grade(dataclasses.replace(sf_grade(), accel_scale_sigma=0.0))
    with pytest.raises(ConfigError, match="scale-factor sigmas > 0"):
        make_fuser("ukf", init, plain, scale_factors=True)
    check_fusion_options("ukf", {"scale_factors": True})  # no noise given: the sigmas are not checked
    assert set(EXTRA_STATE_OPTIONS) == {
        "scale_factors", "scale_factor_tau_s", "map_bias_sigma_m", "map_bias_tau_s", "map_bias_sources"
    }  # fmt: skip


def test_scenario_names_a_bad_fusion_option(tmp_path) -> None:
    from test_studies_scenario import GOOD

    from magnav_ins.studies.scenario import load_scenario

    for bad, key in (
        ('fusion = { kind = "ukf", scale_factor = true }', "estimator[0].fusion.scale_factor"),
        ('fusion = { kind = "ukf", map_bias_sigma_m = -3.0 }', "estimator[0].fusion"),
    ):
        text = GOOD.replace('fusion = { kind = "ukf" }', bad, 1)
        assert text != GOOD
        p = tmp_path / "s.toml"
        p.write_text(text)
        with pytest.raises(ConfigError) as ei:
            load_scenario(p)
        assert f"'{key}'" in str(ei.value), str(ei.value)
    good = GOOD.replace('fusion = { kind = "ukf" }', 'fusion = { kind = "ukf", scale_factors = true, '
                        'map_bias_sigma_m = 30.0, map_bias_sources = ["ml"] }', 1)  # fmt: skip
    p = tmp_path / "s.toml"
    p.write_text(good)
    sc = load_scenario(p)
    assert sc.estimators[0].fusion["scale_factors"] is True


def test_rts_smoother_with_scale_factor_states() -> None:
    """``keep_history`` and :meth:`smooth` with the 21-state layout: the smoothed track beats the filter's and its
    covariances carry the scale-factor block."""
    traj, _ = strong_flight()
    init, imu, fixes, _ = sf_inputs()
    f = make_fuser("ukf", init, ImuNoise.from_grade(sf_grade()), keep_history=True, scale_factors=True)
    i = 0
    for fix, h in fixes:
        j = int(np.searchsorted(imu.t, fix.t + 1e-9, side="right"))
        f.propagate(imu.slice(i, j))
        i = j
        f.correct(fix, height_m=h, height_sigma_m=H_SIGMA)
    hist = f._history
    filt = np.array([nav_error(h[5], traj.at(int(round(h[0] * RATE_HZ))))[:2] for h in hist])
    sm, Ps = f.smooth()
    assert Ps.shape == (len(hist), 21, 21)
    smo = np.array([nav_error(sm.at(k), traj.at(int(round(sm.t[k] * RATE_HZ))))[:2] for k in range(len(sm))])
    assert horizontal_rms(smo) < 0.6 * horizontal_rms(filt), (horizontal_rms(smo), horizontal_rms(filt))
    # measured 0.40 m vs 1.30 m (at every covariance step, between fixes too)
    assert np.all(Ps[:, 15:21, 15:21].diagonal(axis1=1, axis2=2) <= SF_SIGMA**2 * (1 + 1e-9))


# --- the altitude hold a height aid moves ---------------------------------------------------------------------
def test_set_altitude_hold_moves_the_clamped_height() -> None:
    """After ``set_altitude_hold(h)`` the next IMU step ends at ``h`` with zero down velocity; a fuser with a free
    vertical channel refuses it with a message (the barometric aid then leaves it alone)."""
    from magnav_ins.core.errors import InputError

    init, imu, _, _ = sf_inputs()
    noise = ImuNoise.from_grade(sf_grade())
    f = make_fuser("ukf", init, noise, altitude_hold=float(init.nav.h))
    assert f.holds_altitude
    f.propagate(imu.slice(0, 51))
    assert abs(f.estimate().nav.h - init.nav.h) < 1e-9
    f.set_altitude_hold(float(init.nav.h) + 37.5)
    f.propagate(imu.slice(50, 101))
    nav = f.estimate().nav
    assert abs(nav.h - (init.nav.h + 37.5)) < 1e-9 and nav.v_n[2] == 0.0
    free = make_fuser("ukf", init, noise, altitude_hold=None)
    assert not free.holds_altitude
    with pytest.raises(InputError, match="without altitude_hold"):
        free.set_altitude_hold(100.0)
    with pytest.raises(InputError, match="finite"):
        f.set_altitude_hold(float("nan"))
