"""Storms (2009, seed 004): the Bayes grid's R rule (sec. 3.4.2.4), the 2-D constant-velocity Kalman filter (sec.
3.4.1), the wandering hallway trajectories (sec. 4.4.1.1) and the Table 4.1 study pieces (fixed initial offset,
``rms_after_first_fix_m``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from matcher_scenarios import KIND_V, ORIGIN, latlon, local, nav_estimate

from magnav_ins.aiding.fusion import ImuNoise, make_fuser
from magnav_ins.aiding.fusion.cv_kf import cv_process_noise, cv_transition
from magnav_ins.aiding.matchers import BayesGridMatcher
from magnav_ins.aiding.matchers.bayes_grid import storms_sigma
from magnav_ins.core.errors import ConfigError
from magnav_ins.core.types import LAYOUT_15, FieldReadings, Fix, ImuBatch, NavEstimate, NavState
from magnav_ins.ins.ground_path import Path2D, Wander, ground_path
from magnav_ins.ins.imu_models import get_grade
from magnav_ins.maps.grid import GridMap
from magnav_ins.maps.tangent import geodetic_to_tangent
from magnav_ins.studies import metrics as M

SCEN = Path(__file__).resolve().parents[1] / "examples" / "scenarios"
NOISE = ImuNoise.from_grade(get_grade("tactical"))  # unused by the CV filter; the common make_fuser signature


# ------------------------------------------------------------------------------------------------ the R rule
def _linear_vector_map(a: float, b: float) -> GridMap:
    """3-axis field x = a * north, y = b * east, z = 0 (nT; a, b in nT/m) on a 0.05 m grid, 40 m square."""
    n_ax = np.arange(0.0, 40.0, 0.05)
    e_ax = np.arange(0.0, 40.0, 0.05)
    gn, ge = np.meshgrid(n_ax, e_ax, indexing="ij")
    vals = np.stack([a * gn, b * ge, np.zeros_like(gn)], axis=-1)
    return GridMap(n_ax, e_ax, vals, kind=KIND_V, frame="local", altitude_m=0.0, origin=ORIGIN)


def _one_fix(bg: BayesGridMatcher, fmap: GridMap, truth: np.ndarray, prior_ne: np.ndarray, prior_sigma: float):
    lat, lon = latlon(fmap, truth[0], truth[1])
    z = fmap.value(lat, lon)[0]  # noise-free reading: the likelihood peaks at the truth
    P = np.eye(2) * prior_sigma**2
    st = bg.initiate(nav_estimate(fmap, 0.0, prior_ne, np.zeros(2), P))
    st = bg.update(st, FieldReadings(np.array([0.0]), z[None], 10.0, KIND_V), fmap)
    return bg.to_fix(st)


def test_storms_sigma_of_a_gaussian_line_is_its_sigma():
    x = np.arange(-10.0, 10.0, 0.01)
    pdf = 7.0 * np.exp(-0.5 * (x - 0.3) ** 2 / 1.7**2)  # any scale
    assert storms_sigma(pdf, x, 0.1587) == pytest.approx(1.7, rel=2e-3)
    assert np.isnan(storms_sigma(np.zeros_like(x), x))


def test_storms_r_is_the_likelihood_spread_not_the_posterior_by_hand():
    """Reading sigma s = 10 nT, field gradients a = 10 nT/m (north) and b = 5 nT/m (east): along the lines through
    the peak the likelihood is Gaussian with sigma s/a = 1 m (north) and s/b = 2 m (east). The prior is N(truth +
    (0, 3) m, 1 m^2 I): the posterior along east is N(3 * 1 / (1/4 + 1) = 2.4 m, 1 / (1/4 + 1) = 0.8 m^2) and along
    north N(0, 1/2 m^2). So, by hand (plus the grid's step^2/12 = 0.05^2/12):

    * the fix (the posterior peak) is at truth + (0, 2.4) m;
    * Storms' rule: R = diag(1, 4) m^2 (likelihood lines, distances to their means at the truth);
    * the posterior rule: R = diag(0.5, 0.8) m^2 (the prior counted again);
    * the old "spread" reading (distances to the peak at 2.4 m, outside the likelihood's 1-sigma band [-2, 2]):
      east sigma = 2.4 m.
    """
    fmap = _linear_vector_map(10.0, 5.0)
    truth = np.array([20.0, 17.0])
    prior = truth + np.array([0.0, 3.0])
    q = 0.05**2 / 12.0
    kw = {"window_sigma": 10.0, "map_sigma": 0.0, "tail": 0.1587}
    storms = _one_fix(BayesGridMatcher(covariance="storms", **kw), fmap, truth, prior, 1.0)
    post = _one_fix(BayesGridMatcher(covariance="posterior", **kw), fmap, truth, prior, 1.0)
    spread = _one_fix(BayesGridMatcher(covariance="spread", **kw), fmap, truth, prior, 1.0)
    for fix in (storms, post, spread):
        assert fix.available, fix.reason
        assert local(fmap, fix.lat, fix.lon) == pytest.approx(truth + [0.0, 2.4], abs=0.03)
    assert np.diag(storms.cov_ne) == pytest.approx([1.0 + q, 4.0 + q], rel=0.02)
    assert np.diag(post.cov_ne) == pytest.approx([0.5 + q, 0.8 + q], rel=0.02)
    assert np.sqrt(spread.cov_ne[1, 1] - q) == pytest.approx(2.4, rel=0.02)
    assert storms.cov_ne[0, 1] == 0.0


def test_bayes_grid_default_is_storms_rule_and_bad_rule_is_refused():
    assert BayesGridMatcher().covariance == "storms"
    with pytest.raises(ConfigError, match="'covariance'"):
        BayesGridMatcher(covariance="curvature")
    with pytest.raises(ConfigError, match="'map_sigma'"):
        BayesGridMatcher(map_sigma=-1.0)


def test_bayes_grid_uses_the_map_error_layer():
    """A uniform error layer of 30 nT on the linear map widens the likelihood as sqrt(s^2 + 30^2) / a."""
    fmap = _linear_vector_map(10.0, 5.0).with_error_layer(30.0, 1.0, "test")
    truth = np.array([20.0, 17.0])
    fix = _one_fix(BayesGridMatcher(window_sigma=10.0, tail=0.1587), fmap, truth, truth, 3.0)
    s = np.hypot(10.0, 30.0)
    assert np.sqrt(np.diag(fix.cov_ne)) == pytest.approx([s / 10.0, s / 5.0], rel=0.03)
    exact = _one_fix(BayesGridMatcher(window_sigma=10.0, tail=0.1587, map_sigma=0.0), fmap, truth, truth, 3.0)
    assert np.sqrt(np.diag(exact.cov_ne)) == pytest.approx([1.0, 2.0], rel=0.03)  # map_sigma = 0: stated exact


# ------------------------------------------------------------------------------------------------ the CV KF
def _estimate(ne=(0.0, 0.0), v=(0.5, 0.0), sig=1.5, sig_v=0.05) -> NavEstimate:
    lat, lon = ORIGIN[0], ORIGIN[1]
    P = np.eye(15) * 1e-6
    P[0, 0] = P[1, 1] = sig**2
    P[3, 3] = P[4, 4] = sig_v**2
    nav = NavState(0.0, lat, lon, 0.0, np.array([v[0], v[1], 0.0]), np.array([0.0, 0.0, 0.0, 1.0]))
    return NavEstimate(nav, P)


def test_cv_process_noise_is_storms_eq_3_4():
    Qd = cv_process_noise(0.1, 0.08) * 1e3
    assert Qd[0, 0] == pytest.approx(0.0021, abs=5e-5)
    assert Qd[0, 2] == pytest.approx(0.0320, abs=5e-5)
    assert Qd[2, 2] == pytest.approx(0.64, abs=1e-9)
    assert np.allclose(cv_transition(0.1)[:2, 2:], 0.1 * np.eye(2))


def test_cv_kf_propagation_and_update_match_the_kalman_equations():
    f = make_fuser("cv_kf", _estimate(), NOISE, accel_sigma_mps2=0.08)
    t = np.arange(1, 16) * 0.1  # 1.5 s in Storms' 0.1 s steps
    f.propagate(ImuBatch(t, np.zeros((15, 3)), np.zeros((15, 3))))
    P = np.diag([1.5**2, 1.5**2, 0.05**2, 0.05**2])
    for _ in range(15):
        P = cv_transition(0.1) @ P @ cv_transition(0.1).T + cv_process_noise(0.1, 0.08)
    est = f.estimate()
    n, e = geodetic_to_tangent(np.array([est.nav.lat]), np.array([est.nav.lon]), *ORIGIN)
    assert (float(n[0]), float(e[0])) == pytest.approx((0.75, 0.0), abs=1e-6)
    assert est.cov_ne == pytest.approx(P[:2, :2], rel=1e-9)
    s = LAYOUT_15["vel"].start
    assert est.P[s : s + 2, s : s + 2] == pytest.approx(P[2:, 2:], rel=1e-9)
    assert np.isnan(est.P[LAYOUT_15["att"].start, LAYOUT_15["att"].start])  # not estimated
    # update with a fix 1 m east of the filter, R = 0.1^2 I
    R = np.eye(2) * 0.01
    lat, lon = latlon(_dummy_frame(), np.array([0.75]), np.array([1.0]))
    inn = f.correct(Fix(1.5, float(lat[0]), float(lon[0]), R, True, "", 0.0, "test"))
    assert inn.accepted and inn.residual_ne == pytest.approx([0.0, 1.0], abs=1e-6)
    H = np.eye(2, 4)
    K = P @ H.T @ np.linalg.inv(H @ P @ H.T + R)
    assert f.x[1] == pytest.approx(K[1, 1], rel=1e-6) and f.x[3] == pytest.approx(K[3, 1], rel=1e-6)
    late = f.correct(Fix(1.0, float(lat[0]), float(lon[0]), R, True, "", 0.0, "test"))
    assert not late.accepted and "no history" in late.reason


def test_cv_kf_residual_monitoring_scales_the_covariance_by_nis_over_2():
    """A fix 2 m east with P = 0.1^2 I, R = 0.1^2 I: NIS = 4 / 0.02 = 200 > 9.21, so P is scaled by 100 first
    (position sigma 1 m) and the gain is 1 / (1 + 0.01) instead of 1/2; the NIS after scaling is 4 / 1.01."""
    f = make_fuser("cv_kf", _estimate(sig=0.1, sig_v=0.1), NOISE, inflate_nis=9.21)
    R = np.eye(2) * 0.01
    lat, lon = latlon(_dummy_frame(), np.array([0.0]), np.array([2.0]))
    inn = f.correct(Fix(0.0, float(lat[0]), float(lon[0]), R, True, "", 0.0, "test"))
    assert inn.accepted and inn.nis == pytest.approx(4.0 / 1.01, rel=1e-4)
    assert f.x[1] == pytest.approx(2.0 / 1.01, rel=1e-4)  # K = 1 / 1.01 on the east position
    assert f.P[1, 1] == pytest.approx(1.0 * 0.01 / 1.01, rel=1e-4)
    small = make_fuser("cv_kf", _estimate(sig=0.1, sig_v=0.1), NOISE, inflate_nis=9.21)
    lat, lon = latlon(_dummy_frame(), np.array([0.0]), np.array([0.3]))  # NIS 4.5: below, the plain update
    small.correct(Fix(0.0, float(lat[0]), float(lon[0]), R, True, "", 0.0, "test"))
    assert small.x[1] == pytest.approx(0.15, rel=1e-4)
    with pytest.raises(ConfigError):
        make_fuser("cv_kf", _estimate(), NOISE, inflate_nis=1.0)


def _dummy_frame() -> GridMap:
    return GridMap(np.arange(3.0), np.arange(3.0), np.zeros((3, 3)), kind="total_field_anomaly_nt",
                   frame="local", altitude_m=0.0, origin=ORIGIN)  # fmt: skip


def test_cv_kf_turn_command_turns_the_velocity_with_the_gyro():
    """A quarter turn at 0.5 rad/s: with the command the velocity ends east at the same speed, without it the
    filter keeps going north."""
    n = 314
    t = np.arange(1, n + 1) * 0.01
    gyro = np.zeros((n, 3))
    gyro[:, 2] = 0.5 + 7.292115e-5 * np.sin(ORIGIN[0]) * -1.0  # body z rate incl. the Earth-rate term removed inside
    imu = ImuBatch(t, gyro, np.zeros((n, 3)))
    turned = make_fuser("cv_kf", _estimate(), NOISE, turn_command=True)
    turned.propagate(imu)
    straight = make_fuser("cv_kf", _estimate(), NOISE)
    straight.propagate(imu)
    assert turned.x[2:] == pytest.approx([0.0, 0.5], abs=2e-3)
    assert straight.x[2:] == pytest.approx([0.5, 0.0], abs=1e-12)
    # the turned track is the quarter circle of radius v / rate = 1 m
    assert turned.x[:2] == pytest.approx([1.0, 1.0], abs=5e-3)
    with pytest.raises(ConfigError, match="accel_sigma_mps2"):
        make_fuser("cv_kf", _estimate(), NOISE, accel_sigma_mps2=0.0)


# ------------------------------------------------------------------------------------------------ ground path
def test_ground_path_corner_is_filleted_and_nominal_speed_is_kept():
    p = Path2D.from_points([[0.0, 1.0], [10.0, 1.0], [10.0, 6.0]], 1.0)
    assert p.length == pytest.approx(10.0 + 5.0 - 2.0 + np.pi / 2.0, rel=1e-12)
    pts, psi = p.at(np.array([0.0, 9.0, 9.0 + np.pi / 2.0, p.length]))
    assert pts[1] == pytest.approx([9.0, 1.0]) and pts[2] == pytest.approx([10.0, 2.0])
    assert pts[3] == pytest.approx([10.0, 6.0]) and psi[3] == pytest.approx(np.pi / 2.0)
    tr = ground_path([[0.0, 1.0], [10.0, 1.0], [10.0, 6.0]], 0.5, 20.0, ORIGIN)
    assert np.hypot(tr.v_n[:, 0], tr.v_n[:, 1]) == pytest.approx(0.5, rel=1e-4)
    with pytest.raises(ConfigError, match="too short"):
        Path2D.from_points([[0.0, 0.0], [0.5, 0.0], [0.5, 5.0]], 1.0)


def test_wandering_runs_stay_in_the_hallway_and_are_reproducible():
    pts = [[0.0, 1.143], [20.0, 1.143], [20.0, 10.0]]
    w = Wander(accel_sigma_mps2=0.08, cross_gain=0.1, along_gain=0.1, max_offset_m=0.8)
    a = ground_path(pts, 0.5, 20.0, ORIGIN, wander=w, rng=np.random.default_rng(3))
    b = ground_path(pts, 0.5, 20.0, ORIGIN, wander=w, rng=np.random.default_rng(3))
    assert np.array_equal(a.lat, b.lat)
    n, e = geodetic_to_tangent(a.lat, a.lon, *ORIGIN)
    main = n < 18.5
    assert np.max(np.abs(e[main] - 1.143)) < 0.85  # max_offset plus the spline between the 0.1 s points
    assert np.std(e[main] - 1.143) > 0.02  # it does wander
    speed = np.hypot(a.v_n[:, 0], a.v_n[:, 1])
    assert 0.4 < np.mean(speed) < 0.6
    with pytest.raises(ConfigError, match="no wandering run"):
        ground_path(
            pts, 0.5, 20.0, ORIGIN, wander=Wander(max_offset_m=1e-4, max_attempts=3), rng=np.random.default_rng(1)
        )


# ------------------------------------------------------------------------------------------------ study pieces
def test_rms_after_first_fix_pools_each_run_from_its_own_first_accepted_fix():
    t = np.arange(10.0)
    assert M.first_fix_index(t, [2.5, 4.0], [False, True]) == 4
    assert M.first_fix_index(t, [2.5], [False]) is None
    runs = [
        M.RunMetrics(e=np.r_[np.full(4, 9.0), np.full(6, 1.0)], nees=np.zeros(10), first_fix_index=4),
        M.RunMetrics(e=np.r_[np.full(2, 9.0), np.full(8, 2.0)], nees=np.zeros(10), first_fix_index=2),
        M.RunMetrics(e=np.full(10, 50.0), nees=np.zeros(10), first_fix_index=None),  # never fixed: left out
    ]
    doc = M.aggregate(runs, "bayes_grid", "cv_kf")
    assert doc["rms_after_first_fix_m"] == pytest.approx(np.sqrt((6 * 1.0 + 8 * 4.0) / 14.0))


def test_storms_scenarios_validate_with_fixed_offset():
    from magnav_ins.studies.model import perturbed_init
    from magnav_ins.studies.scenario import load_scenario

    sc = load_scenario(SCEN / "storms_hallway.toml")
    assert sc.init.position_offset_m == (0.0, -1.145)
    assert sc.trajectory.kind == "ground_path" and sc.trajectory.wander["max_offset_m"] == 0.8
    turn = load_scenario(SCEN / "storms_hallway_turn.toml")
    assert turn.estimators[0].fusion == {"kind": "cv_kf", "accel_sigma_mps2": 0.08, "turn_command": True}
    from magnav_ins.studies.model import build_truth

    truth = build_truth(sc)
    for seed in (1, 2):
        s0 = perturbed_init(sc, truth, np.random.default_rng(seed))
        dn, de = geodetic_to_tangent(np.array([s0.lat]), np.array([s0.lon]), truth.lat[0], truth.lon[0], 0.0)
        assert (float(dn[0]), float(de[0])) == pytest.approx((0.0, -1.145), abs=1e-6)


def test_storms_turn_study_two_runs(tmp_path):
    """Two runs of the turn-command Monte Carlo (the 100-run figures are in bench/storms_table41.py)."""
    from magnav_ins.studies.model import PipelineModel
    from magnav_ins.studies.runner import run_study
    from magnav_ins.studies.scenario import load_scenario

    sc = load_scenario(SCEN / "storms_hallway_turn.toml")
    doc = run_study(PipelineModel(sc), 2, sc.seed, plots=False)
    e = doc["estimators"]["bayes_grid+cv_kf_turn"]
    assert e["fusion"] == "cv_kf" and e["availability"] > 0.9
    assert e["rms_after_first_fix_m"] < 0.3
    assert doc["free_inertial"]["rms_horizontal_m"] > 10.0


def _two_wells():
    """A scalar field with two identical round wells (width 0.15 m) 0.8 m apart along north on a 0.05 m grid, a
    narrow prior (0.1 m) on the first, one noise-free reading (10 nT sigma) at the first well's bottom."""
    ax = np.arange(-2.0, 2.0001, 0.05)
    n, e = np.meshgrid(ax, ax, indexing="ij")
    well = lambda n0: np.exp(-((n - n0) ** 2 + e**2) / (2 * 0.15**2))  # noqa: E731
    fmap = GridMap(ax, ax, 100.0 * (1.0 - well(0.0) - well(0.8)), kind="total_field_anomaly_nt", frame="local",
                   altitude_m=0.0, origin=ORIGIN)  # fmt: skip
    prior = nav_estimate(fmap, 0.0, np.array([0.0, 0.0]), np.zeros(2), np.eye(2) * 0.01)
    rd = FieldReadings(np.array([0.0]), np.array([0.0]), 10.0, "total_field_anomaly_nt")
    return fmap, prior, rd


def test_cover_rivals_of_the_likelihood_widens_r_by_the_hidden_peak():
    """Two equal likelihood peaks 0.8 m apart along north (a scalar field with two identical wells), the filter's
    prior narrow (0.1 m) on the first: the posterior shows one peak (the prior suppresses the other by e^-32), so
    the posterior-rival guard sees nothing; the likelihood rivals add w d d^T with w = 1/2, d = 0.8 m north: R_NN
    grows by 0.32 m^2, R_EE not at all."""
    fmap, prior, rd = _two_wells()
    fixes = {}
    for cover in (False, True):
        m = BayesGridMatcher(guards=False, map_sigma=0.0, cover_rivals=cover, rivals_of="likelihood", quantisation=0.0)
        fixes[cover] = m.to_fix(m.update(m.initiate(prior), rd, fmap))
        assert fixes[cover].available, fixes[cover].reason
        assert np.hypot(*local(fmap, fixes[cover].lat, fixes[cover].lon)) < 0.06  # the first well
    dR = fixes[True].cov_ne - fixes[False].cov_ne
    assert dR[0, 0] == pytest.approx(0.32, rel=0.05)
    assert abs(dR[1, 1]) < 1e-9 and abs(dR[0, 1]) < 0.02
    with pytest.raises(ConfigError, match="rivals_of"):
        BayesGridMatcher(rivals_of="prior")


# ------------------------------------------------------------------ residual monitoring with a wider search
def test_research_finds_the_vehicle_outside_a_wrong_and_too_sure_prior_by_hand():
    """Linear field x = 20 nT/m north, y = 20 nT/m east, reading sigma 10 nT, noise-free reading at the truth; the
    prior N(truth + (0, 4) m, 0.1^2 m^2 I) is wrong and too sure (Storms' filter after an unannounced turn). Along
    east the log posterior is -x^2 / (2 s_p^2) - 2 (4 - x)^2 (x m from the prior towards the truth), so its peak is
    x = 16 / (4 + 1 / s_p^2):
    * s_p = 0.1 m: x = 0.154 m, residual 3.85 m x 20 nT/m = 7.7 sigma (4.4 per component): a wrong fix;
    * searched again with s_p x 4 = 0.4 m: x = 1.56 m, residual 4.9 sigma (2.8 per component > 2.5): still wrong;
    * with s_p x 16 = 1.6 m: x = 3.644 m, residual 0.36 m x 20 = 0.71 sigma (0.41 per component): issued, the fix
      0.356 m from the truth on the prior's side."""
    fmap = _linear_vector_map(20.0, 20.0)
    truth = np.array([20.0, 17.0])
    prior = truth + np.array([0.0, 4.0])
    plain = _one_fix(BayesGridMatcher(map_sigma=0.0, guards=False), fmap, truth, prior, 0.1)
    assert local(fmap, plain.lat, plain.lon) - truth == pytest.approx([0.0, 4.0 - 0.154], abs=0.03)
    bg = BayesGridMatcher(map_sigma=0.0, guards=False, research_residual_sigma=2.5)
    fix = _one_fix(bg, fmap, truth, prior, 0.1)
    assert fix.available, fix.reason
    assert local(fmap, fix.lat, fix.lon) - truth == pytest.approx([0.0, 4.0 - 3.644], abs=0.03)
    # one wider search only (s_p 0.4 m): nothing passes -> no fix, with the reason
    one = _one_fix(BayesGridMatcher(map_sigma=0.0, guards=False, research_residual_sigma=2.5, research_steps=1),
                   fmap, truth, prior, 0.1)  # fmt: skip
    assert not one.available and one.reason.startswith("large residual")


def test_research_leaves_a_consistent_fix_alone_and_checks_its_options():
    fmap = _linear_vector_map(20.0, 20.0)
    truth = np.array([20.0, 17.0])
    prior = truth + np.array([0.1, -0.2])
    a = _one_fix(BayesGridMatcher(map_sigma=0.0, guards=False), fmap, truth, prior, 0.3)
    b = _one_fix(BayesGridMatcher(map_sigma=0.0, guards=False, research_residual_sigma=2.5), fmap, truth, prior, 0.3)
    assert (a.lat, a.lon) == (b.lat, b.lon) and np.array_equal(a.cov_ne, b.cov_ne)
    for bad in ({"research_residual_sigma": 0.0}, {"research_factor": 1.0}, {"research_steps": 0}):
        with pytest.raises(ConfigError, match="research"):
            BayesGridMatcher(**bad)


def test_lobe_lines_count_a_known_rival_once_window_lines_count_it_twice():
    """The two equal wells of the test above (0.8 m apart along north), the prior narrow on the first. The rival's
    share of the peaks is 1/2, so R must grow by w d^2 = 0.32 m^2 along north for it, and by nothing more. With the
    lines over the whole window (Storms' lines as first implemented) the north line already runs through the second
    well: its pdf has two equal lobes, mean 0.4 m, so sigma_N is about 0.4 m (not the single well's width) and the
    rival term comes on top: counted twice. With ``line_extent = "lobe"`` the lines stop at the first minimum, so
    north and east spreads are the single well's (equal: the well is round) and R_NN - R_EE is the rival's 0.32."""
    fmap, prior, rd = _two_wells()
    R = {}
    for extent in ("window", "lobe"):
        for cover in (False, True):
            m = BayesGridMatcher(guards=False, map_sigma=0.0, cover_rivals=cover, rivals_of="likelihood",
                                 quantisation=0.0, line_extent=extent)  # fmt: skip
            fix = m.to_fix(m.update(m.initiate(prior), rd, fmap))
            assert fix.available, fix.reason
            R[extent, cover] = np.asarray(fix.cov_ne)
    own = R["lobe", False]
    assert own[0, 0] == pytest.approx(own[1, 1], rel=0.02)  # the lobe lines see one round well
    assert own[0, 0] < 0.02  # ... a narrow one (sigma < 0.14 m)
    assert R["lobe", True][0, 0] - own[1, 1] == pytest.approx(0.32, rel=0.05)  # the rival, once
    assert np.sqrt(R["window", False][0, 0]) == pytest.approx(0.4, abs=0.05)  # the window line: both wells
    assert R["window", True][0, 0] > R["lobe", True][0, 0] + 0.1  # ... and the rival again on top
    with pytest.raises(ConfigError, match="line_extent"):
        BayesGridMatcher(line_extent="line")


def test_fix_at_likelihood_puts_the_fix_on_the_likelihood_peak_the_prior_picked():
    """The linear field of the R-rule test: the posterior peak lies at truth + (0, 2.4) m (pulled by the prior at
    truth + (0, 3) m); the likelihood alone peaks at the truth, so with ``fix_at = "likelihood"`` the fix is the
    truth and R (the likelihood lines through it) is the same diag(1, 4) m^2."""
    fmap = _linear_vector_map(10.0, 5.0)
    truth = np.array([20.0, 17.0])
    kw = {"window_sigma": 10.0, "map_sigma": 0.0, "tail": 0.1587}
    post = _one_fix(BayesGridMatcher(**kw), fmap, truth, truth + [0.0, 3.0], 1.0)
    lik = _one_fix(BayesGridMatcher(fix_at="likelihood", **kw), fmap, truth, truth + [0.0, 3.0], 1.0)
    assert local(fmap, post.lat, post.lon) == pytest.approx(truth + [0.0, 2.4], abs=0.03)
    assert local(fmap, lik.lat, lik.lon) == pytest.approx(truth, abs=0.03)
    assert np.diag(lik.cov_ne) == pytest.approx([1.0 + 0.05**2 / 12, 4.0 + 0.05**2 / 12], rel=0.02)
    with pytest.raises(ConfigError, match="fix_at"):
        BayesGridMatcher(fix_at="prior")


def test_lobe_lines_count_the_grid_quantisation_once():
    """Linear field (a = 10, b = 5 nT/m) on a coarse 0.5 m grid, reading sigma 10 nT: the likelihood holds the node
    error |grad|^2 step^2 / 12 = 125 x 0.25 / 12 = 2.60 nT^2, so its lines are Gaussian with sigma^2 = (100 + 2.60)
    / a^2 = 1.026 m^2 (north) and / b^2 = 4.104 m^2 (east): the quantisation is in them already. The window lines add
    step^2 / 12 = 0.0208 m^2 on top (as before); the lobe lines do not (the lines of a linear field have no minimum,
    so both run over the same nodes and differ by that term only)."""
    n_ax = np.arange(0.0, 40.0, 0.5)
    gn, ge = np.meshgrid(n_ax, n_ax, indexing="ij")
    fmap = GridMap(n_ax, n_ax, np.stack([10.0 * gn, 5.0 * ge, np.zeros_like(gn)], axis=-1), kind=KIND_V,
                   frame="local", altitude_m=0.0, origin=ORIGIN)  # fmt: skip
    truth = np.array([20.0, 17.0])
    kw = {"window_sigma": 4.0, "map_sigma": 0.0, "tail": 0.1587, "quantisation": 0.0, "guards": False}
    win = _one_fix(BayesGridMatcher(line_extent="window", **kw), fmap, truth, truth, 3.0)
    lobe = _one_fix(BayesGridMatcher(line_extent="lobe", **kw), fmap, truth, truth, 3.0)
    assert np.diag(win.cov_ne - lobe.cov_ne) == pytest.approx([0.25 / 12, 0.25 / 12], rel=1e-6)
    # the 16 % tail rule on nodes 0.5 m apart: within 2 % for the 2 m east sigma, 6 % for the 1 m north one
    assert lobe.cov_ne[1, 1] == pytest.approx(102.6 / 25.0, rel=0.02)
    assert lobe.cov_ne[0, 0] == pytest.approx(102.6 / 100.0, rel=0.07)
