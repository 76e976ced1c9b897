"""MagNavigate as a navigator (Shockley 2012, seed 003, ch. V) and Shockley's RSS feature matching (sec. 4.6.3):
the ``solution`` fuser, particles starting at rest, road penalisation from the study's road map, and the feature
matcher against a case computed by hand."""

from __future__ import annotations

import numpy as np
import pytest
from matcher_scenarios import KIND_TF, ORIGIN, nav_estimate

from magnav_ins.aiding.fusion import make_fuser
from magnav_ins.aiding.fusion.common import ImuNoise
from magnav_ins.aiding.matchers import FeatureMatcher, ParticleFilter, build_matcher
from magnav_ins.aiding.matchers._local import LocalFrame
from magnav_ins.aiding.matchers.features import deviation, find_features, rss_fit
from magnav_ins.core.errors import ConfigError
from magnav_ins.core.protocols import MatchWindow
from magnav_ins.core.types import FieldReadings, Fix, ImuBatch
from magnav_ins.maps.synthetic import random_field_map
from magnav_ins.maps.track import TrackMap


# ---------------------------------------------------------------------------------------------- feature RSS
def _feature_road():
    """A straight 60 m road sampled every 1 m, field 0 but for feature A (points 11-13: 10, 30, 10 nT) and the
    asymmetric feature B (points 40-42: 12, 25, 6 nT)."""
    fr = LocalFrame(ORIGIN[0], ORIGIN[1])
    e = np.arange(60.0)
    lat, lon = fr.to_latlon(np.zeros_like(e), e)
    v = np.zeros(60)
    v[11:14] = [10.0, 30.0, 10.0]
    v[40:43] = [12.0, 25.0, 6.0]
    track = TrackMap(lat, lon, 0.0, v, kind=KIND_TF, metadata={"step_m": 1.0})
    return fr, track, lat, lon, v


def test_features_are_the_runs_above_threshold_with_their_peaks():
    _, _, _, _, v = _feature_road()
    dev = deviation(v[:, None], 1.0, 30.0, 1.0)  # a 31-sample running median of a zero road with bumps: 0
    np.testing.assert_allclose(dev, np.abs(v))
    f = find_features(dev, 4.0, 1)
    assert [(x.start, x.stop, x.peak) for x in f] == [(11, 14, 12), (40, 43, 41)]


def test_rss_fit_against_hand_computed_values():
    """Readings over points 31-50 forward, B read as 11, 26, 7. Aligned on the peaks, 3 samples compared:
    B forward (12, 25, 6): residuals -1, 1, 1 -> RSS sqrt(3), RMS 1.0 sigma; B reversed (6, 25, 12): 5, 1, -5 ->
    sqrt(51); A (10, 30, 10, either way): 1, -4, -3 -> sqrt(26). The fix is the map point of the last reading: B's
    peak (41) plus the 9 samples read after the observed peak -> point 50."""
    fr, track, lat, lon, v = _feature_road()
    z = v[31:51].copy()
    z[9:12] = [11.0, 26.0, 7.0]
    obs = find_features(deviation(z[:, None], 1.0, 30.0, 1.0), 4.0, 1)[0]
    assert (obs.start, obs.stop, obs.peak) == (9, 12, 10)
    m = FeatureMatcher(threshold_sigma=4.0, background_m=30.0, min_length_m=1.0)
    feats, profiles, points = m.map_features(track, 1.0)
    fits = {(f.road, f.direction, int(points[f.road][f.peak])): rss_fit(z, obs, profiles[f.road], f)[0] for f in feats}
    assert fits[(0, 0, 41)] == pytest.approx(np.sqrt(3.0))
    assert fits[(1, 1, 41)] == pytest.approx(np.sqrt(51.0))
    assert fits[(0, 0, 12)] == pytest.approx(np.sqrt(26.0))
    assert fits[(1, 1, 12)] == pytest.approx(np.sqrt(26.0))
    k, best, rms, why = m.match_profile(z, track, 1.0)
    assert why == "" and k == 50 and rms == pytest.approx(1.0)
    # thresholded: an RMS residual of 1.0 sigma is accepted at 1.5, refused at 0.9 (sec. 4.6.3's trade)
    assert FeatureMatcher(4.0, 30.0, 1.0, rss_threshold=1.5).match_profile(z, track, 1.0)[0] == 50
    k, _, _, why = FeatureMatcher(4.0, 30.0, 1.0, rss_threshold=0.9).match_profile(z, track, 1.0)
    assert k == -1 and why.startswith("no feature fits")
    # through the batch interface: readings at the INS positions of points 31-50
    rd = FieldReadings(np.arange(20.0), z, 1.0, KIND_TF)
    n = len(z)
    win = MatchWindow(
        rd, lat[31:51], lon[31:51], np.zeros(n), np.tile(np.eye(2), (n, 1, 1)), np.tile([0.0, 1.0], (n, 1))
    )
    fix = build_matcher({"kind": "feature", "threshold_sigma": 4.0, "min_length_m": 1.0}).match(win, track)
    assert fix.available, fix.reason
    assert fix.lat == pytest.approx(lat[50]) and fix.lon == pytest.approx(lon[50])
    # no complete feature in a flat section; a grid map is refused
    flat = FieldReadings(np.arange(20.0), np.zeros(20), 1.0, KIND_TF)
    win0 = MatchWindow(flat, win.lat, win.lon, win.h, win.cov_ne, win.v_ne)
    assert FeatureMatcher().match(win0, track).reason.startswith("no feature")
    grid = random_field_map((20, 20), 1.0, 5.0, 10.0, np.random.default_rng(1), kind=KIND_TF, origin=ORIGIN)
    assert not FeatureMatcher().match(win, grid).available
    with pytest.raises(ConfigError):
        FeatureMatcher(compose="median")


# ---------------------------------------------------------------------------------------------- the navigator
def test_solution_fuser_reports_the_last_solution():
    fmap = random_field_map((50, 50), 2.0, 10.0, 10.0, np.random.default_rng(3), kind=KIND_TF, origin=ORIGIN)
    init = nav_estimate(fmap, 0.0, np.array([40.0, 40.0]), np.array([3.0, 0.0]), np.eye(2) * 625.0)
    fz = make_fuser("solution", init, ImuNoise(0.0, 0.0, 0.0, 0.0))
    fz.propagate(ImuBatch(np.array([0.5, 1.0]), np.zeros((2, 3)), np.zeros((2, 3))))
    est = fz.estimate()
    assert est.nav.t == 1.0 and est.nav.lat == init.nav.lat  # no fix yet: the start, its covariance
    np.testing.assert_allclose(est.cov_ne, np.eye(2) * 625.0)
    assert np.all(np.isnan(est.P[3:5, 3:5]))  # velocity not estimated
    lat, lon = fmap.from_local(50.0, 44.0)
    inn = fz.correct(Fix(1.0, float(lat), float(lon), np.diag([4.0, 9.0])))
    assert inn.accepted and inn.residual_ne == pytest.approx([10.0, 4.0], abs=0.01)
    assert fz.estimate().nav.lat == pytest.approx(float(lat)) and fz.estimate().cov_ne[1, 1] == 9.0
    inn = fz.correct(Fix.no_fix(1.0, "flat map"))
    assert not inn.accepted and fz.estimate().nav.lat == pytest.approx(float(lat))  # kept


def test_particles_start_at_rest_and_the_posterior_is_the_cloud():
    rng = np.random.default_rng(5)
    fmap = random_field_map((100, 100), 2.0, 10.0, 10.0, rng, kind=KIND_TF, origin=ORIGIN)
    prior = nav_estimate(fmap, 0.0, np.array([100.0, 100.0]), np.array([10.0, 0.0]), np.eye(2) * 100.0)
    pf = ParticleFilter(init="disc", start_at_rest=True, fix_output="posterior")
    st = pf.initiate(prior, rng)
    assert np.all(st.vel == 0.0) and np.all(st.acc == 0.0)  # Shockley sec. 5.1: zero velocity and acceleration
    assert np.hypot(*(st.pos - st.pos.mean(axis=0)).T).max() <= 50.0 + 1.0
    st.reason = "flat map"  # a skipped update: the navigator still reports the (predicted) cloud
    fix = pf.to_fix(st)
    assert fix.available
    w = np.exp(st.logw)
    d = st.pos - w @ st.pos
    np.testing.assert_allclose(fix.cov_ne, (d * w[:, None]).T @ d, rtol=1e-9)
    assert ParticleFilter(init="disc").initiate(prior, rng).vel[0, 0] == 10.0  # default: the prior's velocity


def test_road_map_named_in_the_config_is_the_matched_map():
    fr = LocalFrame(ORIGIN[0], ORIGIN[1])
    e = np.arange(-100.0, 100.0, 1.0)
    lat, lon = fr.to_latlon(np.zeros_like(e), e)
    road = TrackMap(lat, lon, 0.0, np.zeros_like(e), kind=KIND_TF)
    assert build_matcher({"kind": "particle", "road": "map"}, fmap=road).road is road
    assert build_matcher({"kind": "particle", "road": "map"}).road is None  # checked only
    grid = random_field_map((20, 20), 1.0, 5.0, 10.0, np.random.default_rng(1), kind=KIND_TF, origin=ORIGIN)
    with pytest.raises(ConfigError, match="road map"):
        build_matcher({"kind": "particle", "road": "map"}, fmap=grid)
    with pytest.raises(ConfigError, match='expected "map"'):
        build_matcher({"kind": "particle", "road": "streets.csv"})


# ---------------------------------------------------------------------------------------------- off the map
def test_matchers_know_when_the_vehicle_is_off_the_map():
    """A 3-axis field mapped only south of northing 20 m (the Kok walks' maps hold the walked path only). The vehicle
    is 3 m north of the map's edge, where the field is another draw: with "impossible" off-map nodes the Bayes grid
    and ML put their fix on the map (within the prior), wrong, or at best call it ambiguous; with "unknown" (the field there drawn from the map's
    statistics) they say "off the map". On the map both still fix."""
    from matcher_scenarios import KIND_V, exact, latlon, make_window

    from magnav_ins.aiding.matchers import BayesGridMatcher, LikelihoodMatcher

    rng = np.random.default_rng(17)
    full = exact(random_field_map((80, 80), 0.5, 1.0, 1000.0, rng, kind=KIND_V, origin=ORIGIN))
    v = np.array(full.values)
    other = random_field_map((80, 80), 0.5, 1.0, 1000.0, rng, kind=KIND_V, origin=ORIGIN)
    v[40:] = np.nan  # northing >= 20 m: not mapped
    fmap = full.with_values(v)
    truth_fld = np.array(other.values)  # what is really there off the map
    cases = {"off": (np.array([23.0, 20.0]), truth_fld[46, 40]), "on": (np.array([15.0, 20.0]), v[30, 40])}
    P = np.eye(2) * 4.0
    n_fix = 0
    for where, (ne, value) in cases.items():
        z = value + rng.normal(0.0, 30.0, 3)
        prior = nav_estimate(fmap, 0.0, ne + [-1.5, 0.5], np.zeros(2), P)
        rd = FieldReadings(np.array([0.0]), z[None], 30.0, KIND_V)
        for off_map in ("impossible", "unknown"):
            bg = BayesGridMatcher(off_map=off_map)
            fix_bg = bg.to_fix(bg.update(bg.initiate(prior), rd, fmap))
            win = make_window(fmap, np.array([0.0]), ne[None], z[None], 30.0, KIND_V, np.array([-1.5, 0.5]), P,
                              np.zeros(2))  # fmt: skip
            fix_ml = LikelihoodMatcher(method="ml", off_map=off_map).match(win, fmap)
            for fix in (fix_bg, fix_ml):
                if where == "on":
                    assert fix.available, (off_map, fix.reason)
                elif off_map == "unknown":
                    assert not fix.available and fix.reason.startswith("off the map"), fix.reason
                elif fix.available:  # the defect the option removes: a fix on the map although the vehicle is off it
                    lat, lon = latlon(fmap, *ne)
                    assert fix.lat < lat[0]  # south of the truth, on the mapped side
                    n_fix += 1
    assert n_fix >= 1  # at least one of the two matchers shows the defect


# ---------------------------------------------------------------------------------------------- a study
def test_magnavigate_navigates_a_small_street_grid_in_a_study():
    """The particle filter's own solution through the study runner: a 700 m route with two turns through a 300 m
    street grid, 3-axis readings every 1 m (Shockley's composition), particles at rest within 50 m of the start,
    road penalisation from the map. It keeps the route (Shockley's AFIT route: RMS 8 m, max 44 m) and its
    covariance is honest (2-D NEES near 2)."""
    import tomllib
    from pathlib import Path

    from magnav_ins.studies.model import PipelineModel
    from magnav_ins.studies.runner import run_seeds, summarise_run
    from magnav_ins.studies.scenario import scenario_from_dict

    root = Path(__file__).resolve().parents[1]
    data = tomllib.loads((root / "examples" / "scenarios" / "magnavigate_route.toml").read_text())
    data["trajectory"]["points_m"] = [[100.0, 0.0], [100.0, 300.0], [300.0, 300.0], [300.0, 100.0]]
    data["map"]["options"].update(shape=[301, 301], streets_north_m=[0.0, 100.0, 300.0],
                                  streets_east_m=[0.0, 100.0, 300.0])  # fmt: skip
    data["imu"]["rate_hz"] = 10.0
    sc = scenario_from_dict(data)
    s = summarise_run(0, PipelineModel(sc).run(run_seeds(sc.seed, 1)[0]))
    m = s.estimators["magnavigate_field"].metrics
    assert np.sqrt(np.mean(m.e**2)) < 8.0 and m.e.max() < 44.0, (np.sqrt(np.mean(m.e**2)), m.e.max())
    assert 0.5 < np.nanmean(m.nees) < 4.0, np.nanmean(m.nees)
    assert m.e[-len(m.e) // 4 :].mean() < 10.0  # not lost at the end
