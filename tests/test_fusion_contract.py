"""Contract tests run against every fuser (UKF and factor graph), on simulated truth.

Scenario: a 10-minute flight with turns (``simulate.waypoints``, 60 m/s, 10 Hz IMU), tactical IMU errors
(``imu_models``; scale factors and misalignments switched off because the 15-state fusers do not model them),
initial errors drawn from the initial covariance, north/east fixes every 10 s = truth + noise with a known
correlated covariance, and a height aid (sigma 5 m) with each fix. Statistical checks (Bar-Shalom et al. 2001,
sec. 5.4): the per-epoch average NEES (horizontal position, 2 dof) over the runs inside its 95 % chi-square band at
most epochs, and the mean NIS of the accepted fixes inside its 95 % band.
"""

from __future__ import annotations

import dataclasses
from functools import lru_cache

import numpy as np
import pytest

from magnav_ins.aiding.fusion import make_fuser
from magnav_ins.aiding.fusion.common import ImuNoise
from magnav_ins.aiding.gating import consistency_band
from magnav_ins.core.errors import InputError
from magnav_ins.core.types import LAYOUT_15, Fix, ImuBatch, NavEstimate, NavTrajectory
from magnav_ins.core.units import DEG_TO_RAD
from magnav_ins.ins import imu_models, simulate
from magnav_ins.ins.error_model import apply_error, nav_error

FUSERS = ["ukf", "graph"]
RUNS = {"ukf": 8, "graph": 4}  # default run; the slow-marked study uses 30 each
SLOW_RUNS = 30
DURATION_S = 400.0
RATE_HZ = 10.0
FIX_EVERY_S = 10.0
R_FIX = np.array([[25.0, 6.0], [6.0, 16.0]])  # m^2, north/east
H_SIGMA = 5.0
SIG0 = np.r_[[10.0] * 3, [0.1] * 3, 0.02 * DEG_TO_RAD, 0.02 * DEG_TO_RAD, 0.2 * DEG_TO_RAD]


@lru_cache(maxsize=1)
def truth() -> tuple[NavTrajectory, ImuBatch]:
    d = DEG_TO_RAD
    pts = np.array([[45.0, 7.0, 3000.0], [45.1, 7.1, 3000.0], [45.05, 7.3, 3000.0], [45.2, 7.4, 3000.0]])
    pts[:, :2] *= d
    traj = simulate.waypoints(pts, 60.0, RATE_HZ, turn_rate=3.0 * d)
    n = int(DURATION_S * RATE_HZ) + 1
    traj = traj.slice(0, min(n, len(traj)))
    return traj, simulate.ideal_imu(traj)


def grade():
    return imu_models.get_grade("tactical")


def noise() -> ImuNoise:
    return ImuNoise.from_grade(grade())


def P0() -> np.ndarray:
    nz = noise()
    return np.diag(np.r_[SIG0, [nz.accel_bias_init_sigma] * 3, [nz.gyro_bias_init_sigma] * 3] ** 2)


@lru_cache(maxsize=64)
def run_inputs(seed: int) -> tuple[NavEstimate, ImuBatch, list[tuple[Fix, float]]]:
    """Initial estimate (truth + drawn error), corrupted IMU and (fix, height) pairs for one run."""
    rng = np.random.default_rng(seed)
    traj, imu = truth()
    g = grade()
    err = imu_models.draw_errors(g, rng)
    err = dataclasses.replace(err, M_g=np.zeros((3, 3)), M_a=np.zeros((3, 3)))
    imu_c, _ = imu_models.corrupt(imu, g, rng, err)
    dx0 = rng.standard_normal(9) * SIG0
    init = NavEstimate(apply_error(traj.at(0), dx0), P0(), LAYOUT_15)
    fixes = []
    L = np.linalg.cholesky(R_FIX)
    for k in np.flatnonzero(np.isclose(np.mod(traj.t, FIX_EVERY_S), 0.0) & (traj.t > 0)):
        s = traj.at(int(k))
        e = L @ rng.standard_normal(2)
        noisy = apply_error(s, np.r_[e, 0.0, np.zeros(6)])
        fixes.append(
            (Fix(s.t, noisy.lat, noisy.lon, R_FIX, source="noisy-truth"), s.h + H_SIGMA * rng.standard_normal())
        )
    return init, imu_c, fixes


@lru_cache(maxsize=128)
def fly(kind: str, seed: int, *, delay_s: float = 0.0, outliers: float = 0.0):
    """Run one fuser; returns (fuser, horizontal NEES after each fix, horizontal errors (m) after each fix,
    horizontal 1-sigma after each fix, estimates after each fix)."""
    traj, _ = truth()
    init, imu, fixes = run_inputs(seed)
    rng = np.random.default_rng(seed + 1000)
    fuser = make_fuser(kind, init, noise())
    nees, errs, sig, ests = [], [], [], []
    i = 0
    every = round(1.0 / outliers) if outliers else 0
    for n, (fix, h) in enumerate(fixes):
        if every and n % every == every // 2:  # exactly the given fraction, spread over the run
            bearing = rng.uniform(0.0, 2.0 * np.pi)
            fix = dataclasses.replace(
                fix,
                lat=fix.lat + 2000.0 * np.cos(bearing) / 6.37e6,
                lon=fix.lon + 2000.0 * np.sin(bearing) / (6.37e6 * np.cos(fix.lat)),
            )  # 2 km away
        arrival = fix.t + delay_s
        j = int(np.searchsorted(imu.t, arrival + 1e-9, side="right"))
        fuser.propagate(imu.slice(i, j))
        i = j
        fuser.correct(fix, height_m=h, height_sigma_m=H_SIGMA)
        est = fuser.estimate()
        k = int(np.argmin(np.abs(traj.t - est.nav.t)))
        e = nav_error(est.nav, traj.at(k))[:2]
        P = np.asarray(est.P)[:2, :2]
        nees.append(float(e @ np.linalg.solve(P, e)))
        errs.append(float(np.hypot(*e)))
        sig.append(float(np.sqrt(np.trace(P))))
        ests.append(est)
    return fuser, np.array(nees), np.array(errs), np.array(sig), ests


@pytest.fixture(params=FUSERS)
def kind(request) -> str:
    return request.param


def check_consistency(kind: str, runs: int) -> None:
    results = [fly(kind, seed) for seed in range(runs)]
    nees = np.array([r[1] for r in results])  # (runs, epochs)
    lo, hi = consistency_band(2, runs, 0.95)
    anees = nees.mean(axis=0)
    inside = np.mean((anees >= lo) & (anees <= hi))
    assert inside >= 0.8, f"{kind}: ANEES inside [{lo:.2f}, {hi:.2f}] at only {inside:.0%} of epochs: {anees.round(2)}"
    lo_all, hi_all = consistency_band(2, nees.size, 0.95)
    # the epochs of one run are correlated: widen the grand-mean band by the effective sample size (runs)
    lo_r, hi_r = consistency_band(2, runs, 0.95)
    assert lo_r <= nees.mean() <= hi_r, f"{kind}: mean NEES {nees.mean():.2f} outside [{lo_r:.2f}, {hi_r:.2f}]"
    nis = np.array([inn.nis for r in results for inn in r[0].innovations if inn.accepted])
    assert len(nis) >= 0.95 * runs * int(DURATION_S / FIX_EVERY_S)
    lo_n, hi_n = consistency_band(2, len(nis), 0.95)
    assert lo_n <= nis.mean() <= hi_n, f"{kind}: mean NIS {nis.mean():.3f} outside [{lo_n:.3f}, {hi_n:.3f}]"
    assert lo_all < hi_all


def test_nees_and_nis_inside_chi_square_bands(kind: str) -> None:
    check_consistency(kind, RUNS[kind])


@pytest.mark.slow
@pytest.mark.parametrize("which", FUSERS)
def test_monte_carlo_consistency_30_runs(which: str) -> None:
    check_consistency(which, SLOW_RUNS)


def test_fusers_agree_within_one_sigma() -> None:
    for seed in (0,):
        _, _, _, sig_u, est_u = fly("ukf", seed)
        _, _, _, sig_g, est_g = fly("graph", seed)
        d = np.array([nav_error(a.nav, b.nav)[:2] for a, b in zip(est_u, est_g, strict=True)])  # metres between the two
        dist = np.hypot(d[:, 0], d[:, 1])
        sig = np.minimum(sig_u, sig_g)
        assert np.sqrt(np.mean(dist**2)) < np.sqrt(np.mean(sig**2)), (dist.round(2), sig.round(2))


def test_outliers_rejected_and_no_divergence(kind: str) -> None:
    fuser, _, errs, sig, _ = fly(kind, 3, outliers=0.1)
    rej = [inn for inn in fuser.innovations if not inn.accepted]
    assert len(rej) == 4, "10 % of 40 fixes displaced by 2 km should all be rejected, and only they"
    assert all("NIS" in inn.reason for inn in rej)
    assert all(inn.nis > 100.0 for inn in rej)
    assert errs[-10:].max() < 4.0 * sig[-10:].max() and errs.max() < 60.0, errs.round(1)


def test_late_fix_applied_at_its_time(kind: str) -> None:
    _, _, errs0, _, _ = fly(kind, 1)
    f, _, errs1, _, _ = fly(kind, 1, delay_s=3.0)
    assert all(inn.accepted for inn in f.innovations)
    # the late run's estimates are 3 s later; compare both against truth
    assert np.sqrt(np.mean(errs1**2)) < 1.05 * np.sqrt(np.mean(errs0**2)) + 0.5
    assert np.sqrt(np.mean(errs1**2)) < 10.0


def test_free_inertial_baseline_drifts_and_rejects() -> None:
    f, nees, errs, sig, _ = fly("free_inertial", 1)
    assert all((not inn.accepted) and inn.reason == "free inertial" for inn in f.innovations)
    _, _, errs_u, _, _ = fly("ukf", 1)
    assert errs[-1] > 5.0 * np.sqrt(np.mean(errs_u**2))
    assert sig[-1] > sig[0] and errs[-1] > errs[5]


def test_bad_input_is_rejected_or_refused(kind: str) -> None:
    init, imu, fixes = run_inputs(0)
    fuser = make_fuser(kind, init, noise())
    fuser.propagate(imu.slice(0, 101))
    t = float(imu.t[100])
    nan_fix = Fix(t, float("nan"), init.nav.lon, R_FIX)
    inn = fuser.correct(nan_fix)
    assert not inn.accepted and "non-finite" in inn.reason
    bad_cov = Fix(t, init.nav.lat, init.nav.lon, np.array([[1.0, 2.0], [2.0, 1.0]]))
    inn = fuser.correct(bad_cov)
    assert not inn.accepted and "positive definite" in inn.reason
    inn = fuser.correct(Fix.no_fix(t, "off map"))
    assert not inn.accepted and "off map" in inn.reason
    inn = fuser.correct(Fix(t + 100.0, init.nav.lat, init.nav.lon, R_FIX))
    assert not inn.accepted and "after the last IMU time" in inn.reason
    with pytest.raises(InputError, match="backwards|not increasing"):
        fuser.propagate(ImuBatch(np.array([t - 5.0]), imu.gyro_b[:1], imu.accel_b[:1]))
    with pytest.raises(InputError, match="non-finite"):
        fuser.propagate(ImuBatch(np.array([t + 0.1]), np.full((1, 3), np.nan), imu.accel_b[:1]))
    est = fuser.estimate()  # still usable
    assert np.all(np.isfinite(est.P)) and np.isfinite(est.nav.lat)


def test_ukf_rts_smoother_beats_the_filter() -> None:
    traj, _ = truth()
    init, imu, fixes = run_inputs(4)
    fuser = make_fuser("ukf", init, noise(), keep_history=True)
    i = 0
    filt = []
    for fix, h in fixes:
        j = int(np.searchsorted(imu.t, fix.t + 1e-9, side="right"))
        fuser.propagate(imu.slice(i, j))
        i = j
        fuser.correct(fix, height_m=h, height_sigma_m=H_SIGMA)
    hist_t = np.array([h[0] for h in fuser._history])
    filt = np.array([nav_error(h[5], traj.at(int(np.argmin(np.abs(traj.t - h[0])))))[:2] for h in fuser._history])
    sm, Ps = fuser.smooth()
    assert np.allclose(sm.t, hist_t) and Ps.shape == (len(hist_t), 15, 15)
    smo = np.array([nav_error(sm.at(k), traj.at(int(np.argmin(np.abs(traj.t - sm.t[k])))))[:2] for k in range(len(sm))])
    rms_f = np.sqrt(np.mean(np.sum(filt[20:] ** 2, axis=1)))
    rms_s = np.sqrt(np.mean(np.sum(smo[20:] ** 2, axis=1)))
    assert rms_s < 0.8 * rms_f, (rms_s, rms_f)
    # smoothed covariance never above the filtered one, and consistent with the smoothed errors
    assert np.all(Ps[:, 0, 0] <= np.array([h[3][0, 0] for h in fuser._history]) * (1 + 1e-9))
    nees = np.array([e @ np.linalg.solve(P[:2, :2], e) for e, P in zip(smo, Ps, strict=True)])
    assert 0.5 < nees[20:].mean() < 4.0
