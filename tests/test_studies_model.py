"""The scenario -> run model: per-run draws (seeds, initial errors, readings) against their stated statistics."""

from __future__ import annotations

import numpy as np
import pytest

from magnav_ins.core.frames import euler_from_q_nb, latlon_to_meters
from magnav_ins.core.types import FieldKind
from magnav_ins.studies import model as Mdl
from magnav_ins.studies.scenario import scenario_from_dict

BASE = {
    "name": "m",
    "trajectory": {
        "kind": "great_circle",
        "start": [-35.0, 149.0],
        "end": [-35.0, 149.2],
        "altitude_m": 500.0,
        "speed_mps": 50.0,
        "duration_s": 100.0,
    },
    "imu": {"grade": "tactical", "rate_hz": 10.0},
    "init": {"position_sigma_m": 7.0, "velocity_sigma_mps": 0.3, "attitude_sigma_deg": [0.1, 0.2, 0.5]},
    "map": {
        "path": "synthetic:random_field",
        "kind": "gravity_disturbance_mgal",
        "options": {"seed": 3, "origin_deg": [-35.05, 148.95, 500.0], "shape": [120, 300], "spacing_m": 100.0},
    },
    "sensor": {"kind": "gravimeter", "sigma": 2.0, "interval_s": 5.0},
}


def test_child_does_not_mutate_and_is_distinct():
    ss = np.random.SeedSequence(42).spawn(3)[1]
    a = Mdl.child(ss, 0).generate_state(2)
    b = Mdl.child(ss, 0).generate_state(2)
    c = Mdl.child(ss, 1).generate_state(2)
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    assert ss.n_children_spawned == 0


def test_perturbed_init_statistics():
    sc = scenario_from_dict(BASE)
    truth = Mdl.build_truth(sc)
    assert truth.t[-1] - truth.t[0] == pytest.approx(100.0, abs=0.2)
    rng = np.random.default_rng(0)
    s0 = truth.at(0)
    n = 2000
    dn, de, dv, droll, dyaw = (np.empty(n) for _ in range(5))
    for k in range(n):
        st = Mdl.perturbed_init(sc, truth, rng)
        dn[k], de[k] = latlon_to_meters(st.lat - s0.lat, st.lon - s0.lon, s0.lat)
        dv[k] = st.v_n[0] - s0.v_n[0]
        r, _, y = euler_from_q_nb(st.q_nb)
        r0, _, y0 = euler_from_q_nb(s0.q_nb)
        droll[k], dyaw[k] = float(r - r0), float(np.angle(np.exp(1j * (y - y0))))
    tol = 4.0 / np.sqrt(2 * n)  # ~4 standard errors of a sample sigma
    assert np.std(dn) == pytest.approx(7.0, rel=tol) and np.std(de) == pytest.approx(7.0, rel=tol)
    assert np.std(dv) == pytest.approx(0.3, rel=tol)
    assert np.degrees(np.std(droll)) == pytest.approx(0.1, rel=0.1)
    assert np.degrees(np.std(dyaw)) == pytest.approx(0.5, rel=0.1)


def test_simulated_readings_are_map_plus_noise():
    sc = scenario_from_dict(BASE)
    truth = Mdl.build_truth(sc)
    fmap = Mdl.build_map(sc)
    r = Mdl.simulate_readings(sc, truth, fmap, np.random.default_rng(1))
    assert r.kind is FieldKind.GRAVITY_DISTURBANCE_MGAL and r.sigma == 2.0
    assert np.allclose(np.diff(r.t), 5.0)
    lat = np.interp(r.t, truth.t, truth.lat)
    lon = np.interp(r.t, truth.t, truth.lon)
    resid = r.value - fmap.value(lat, lon, np.interp(r.t, truth.t, truth.h))
    assert len(resid) == 20
    assert np.sqrt(np.mean(resid**2)) == pytest.approx(2.0, rel=0.5)
    # the same generator state gives the same readings
    r2 = Mdl.simulate_readings(sc, truth, fmap, np.random.default_rng(1))
    assert np.array_equal(r.value, r2.value)


def test_unknown_synthetic_map_names_key():
    d = {**BASE, "map": {**BASE["map"], "path": "synthetic:volcano"}}
    from magnav_ins.core.errors import ConfigError

    with pytest.raises(ConfigError, match="map.path.*volcano"):
        Mdl.build_map(scenario_from_dict(d))


SURVEY = {
    "name": "s",
    "trajectory": {
        "kind": "survey_line",
        "survey": "builtin:osborne-tie-lines",
        "line": [10158, 10159],
        "speed_mps": 70.0,
    },
    "imu": {"grade": "navigation", "rate_hz": 5.0},
    "map": {"path": "builtin:osborne-magnetic", "kind": "total_field_anomaly_nt"},
    "sensor": {"kind": "scalar_magnetometer", "source": "survey", "sigma": 1e-9, "interval_s": 1.0},
}


def _survey_ne(sc):
    from magnav_ins.maps.io import read_survey_line

    return {ln: read_survey_line(sc.trajectory.survey, ln) for ln in sc.trajectory.lines}


def test_memoised_survey_and_map_are_not_shared_for_writing():
    """The parsed survey and the map are memoised per process: a second read parses nothing, and what a caller
    gets to keep (the line points) is its own copy, so writing to it cannot leak into the next run."""
    sc = scenario_from_dict(SURVEY)
    a = Mdl.survey_line_points(sc)
    before = {k: v.copy() for k, v in a.items()}
    for v in a.values():
        v[...] = 0
    b = Mdl.survey_line_points(sc)
    assert all(np.array_equal(b[k], before[k]) for k in before)
    key = repr((sc.trajectory.survey, sc.trajectory.survey_options(), None))
    assert key in Mdl._SURVEYS  # builtin: no file stamp
    assert Mdl._shared_map(sc) is Mdl._shared_map(scenario_from_dict({**SURVEY, "name": "other speed"}))


def test_several_survey_lines_are_flown_in_order_with_their_own_readings():
    """Two adjacent tie lines flown one after the other: the flight passes over every surveyed point of both, in
    the given order, the second entered from the end nearer the first's end; readings on the lines are the
    survey's recorded values at the nearest surveyed point (brute force), none on the leg between lines."""
    sc = scenario_from_dict(SURVEY)
    assert sc.trajectory.lines == (10158, 10159) and sc.trajectory.line == 10158
    truth = Mdl.build_truth(sc)
    lines = _survey_ne(sc)
    lat0, lon0 = truth.lat[0], truth.lon[0]
    tn, te = latlon_to_meters(truth.lat - lat0, truth.lon - lon0, lat0)
    first_pass = {}
    for ln, p in lines.items():
        pn, pe = latlon_to_meters(p["lat"] - lat0, p["lon"] - lon0, lat0)
        d = np.hypot(pn[:, None] - tn[None, :], pe[:, None] - te[None, :])
        assert d.min(axis=1).max() < 30.0, f"line {ln} not flown over"
        first_pass[ln] = (truth.t[d.argmin(axis=1)][0], truth.t[d.argmin(axis=1)][-1])
    # 10158 flown first; 10159 entered from its end nearer 10158's last point
    assert max(first_pass[10158]) < min(first_pass[10159])
    end58 = lines[10158]["lat"][-1], lines[10158]["lon"][-1]
    start59 = lines[10159]["lat"][0], lines[10159]["lon"][0]
    last59 = lines[10159]["lat"][-1], lines[10159]["lon"][-1]
    entered_at_start = np.hypot(*latlon_to_meters(start59[0] - end58[0], start59[1] - end58[1], end58[0])) < np.hypot(
        *latlon_to_meters(last59[0] - end58[0], last59[1] - end58[1], end58[0])
    )
    t59 = first_pass[10159]
    assert (t59[0] < t59[1]) == entered_at_start

    r = Mdl.simulate_readings(sc, truth, None, np.random.default_rng(0))
    lat = np.interp(r.t, truth.t, truth.lat)
    lon = np.interp(r.t, truth.t, truth.lon)
    qn, qe = latlon_to_meters(lat - lat0, lon - lon0, lat0)
    allp = {k: np.concatenate([p[k] for p in lines.values()]) for k in ("lat", "lon", "value")}
    pn, pe = latlon_to_meters(allp["lat"] - lat0, allp["lon"] - lon0, lat0)
    d = np.hypot(qn[:, None] - pn[None, :], qe[:, None] - pe[None, :])
    assert d.min(axis=1).max() <= Mdl.SURVEY_READING_MAX_OFFSET_M
    assert np.allclose(r.value, allp["value"][d.argmin(axis=1)], atol=1e-6)
    # the leg between the lines (and the run-ins) has no readings: a gap of at least the 2 km spacing at 70 m/s
    assert np.diff(r.t).max() > 2000.0 / 70.0
    assert len(r.t) < (truth.t[-1] - truth.t[0]) / 1.0 - 2000.0 / 70.0


@pytest.mark.parametrize(
    ("line", "needle"),
    [([], "non-empty list"), ([10158, 10158], "appears twice"), (["10158"], "expected an integer"), (1.5, "integer")],
)
def test_survey_line_list_errors_name_the_key(line, needle):
    from magnav_ins.core.errors import ConfigError

    d = {**SURVEY, "trajectory": {**SURVEY["trajectory"], "line": line}}
    with pytest.raises(ConfigError, match=f"trajectory.line.*{needle}|{needle}"):
        scenario_from_dict(d)


def test_smoothed_estimator_beats_its_own_online_track_with_the_same_fixes():
    """``smooth = N`` reports the UKF's RTS-smoothed track: on the same run (same IMU, readings and fixes) it is
    closer to the truth than the causal track, most of all just before each fix, and its covariance is smaller."""
    from magnav_ins.core.frames import horizontal_error_m

    est = {"matcher": {"kind": "ml"}, "fusion": {"kind": "ukf"}, "window": 10, "match_every": 5}
    doc = {
        **BASE,
        "trajectory": {**BASE["trajectory"], "duration_s": 300.0},
        "map": {**BASE["map"], "options": {**BASE["map"]["options"], "sigma": 20.0, "correlation_length_m": 400.0}},
        "sensor": {"kind": "gravimeter", "sigma": 1.0, "interval_s": 2.0},
        "estimator": [{"name": "online", **est}, {"name": "smoothed", **est, "smooth": 2}],
    }
    out = Mdl.PipelineModel(scenario_from_dict(doc)).run(np.random.SeedSequence(11))
    on, sm = (e for e in out.estimators if e.name in ("online", "smoothed"))
    np.testing.assert_array_equal(on.fix_t, sm.fix_t)
    np.testing.assert_array_equal(on.fix_lat, sm.fix_lat)  # the same fixes: only the reported track differs
    assert np.sum(on.fix_available) >= 5
    e_on = horizontal_error_m(on.lat, on.lon, out.lat_true, out.lon_true)
    e_sm = horizontal_error_m(sm.lat, sm.lon, out.lat_true, out.lon_true)
    rms_on, rms_sm = np.sqrt(np.mean(e_on**2)), np.sqrt(np.mean(e_sm**2))
    assert rms_sm < 0.8 * rms_on, (rms_sm, rms_on)
    late = out.t > 60.0  # after the first fixes
    assert np.median(np.trace(sm.cov_ne[late], axis1=1, axis2=2)) < np.median(
        np.trace(on.cov_ne[late], axis1=1, axis2=2)
    )


def test_smooth_is_ukf_and_graph_only_and_names_the_key():
    from magnav_ins.core.errors import ConfigError

    doc = {**BASE, "estimator": [{"name": "f", "fusion": {"kind": "free_inertial"}, "smooth": 1}]}
    with pytest.raises(ConfigError, match=r"estimator\[0\]\.smooth.*ukf.*graph.*'free_inertial'"):
        scenario_from_dict(doc)
    ok = {**BASE, "estimator": [{"name": "g", "matcher": {"kind": "ml"}, "fusion": {"kind": "graph"}, "smooth": 3}]}
    assert scenario_from_dict(ok).estimators[0].smooth == 3


# ---------------------------------------------------------------------------------- per-estimator IMU grade (issue 8)
def _grades_doc(estimators: list[dict], duration_s: float = 120.0, init: dict | None = None) -> dict:
    """A free-inertial study (no map, no sensor): tactical baseline, 10 Hz, flying east at 100 m/s."""
    return {
        "name": "grades",
        "trajectory": {**BASE["trajectory"], "end": [-35.0, 152.0], "speed_mps": 100.0, "duration_s": duration_s},
        "imu": {"grade": "tactical", "rate_hz": 10.0},
        "init": init if init is not None else BASE["init"],
        "estimator": estimators,
    }


def _free(name: str, grade: str | None) -> dict:
    return {"name": name, "fusion": {"kind": "free_inertial"}, **({"imu_grade": grade} if grade else {})}


def test_estimator_of_the_baseline_grade_reproduces_the_baseline_exactly():
    """``imu_grade`` = ``[imu] grade`` (or no ``imu_grade``) flies the baseline's own IMU draw and initial state, so
    its track and covariance equal the free-inertial baseline's bit for bit; two estimators of another grade share
    one draw, and that draw depends on the run seed and the grade only (not on the estimator order)."""
    doc = _grades_doc(
        [_free("tac", "tactical"), _free("plain", None), _free("nav", "navigation"), _free("nav2", "navigation")]
    )
    out = Mdl.PipelineModel(scenario_from_dict(doc)).run(np.random.SeedSequence(5))
    by = {e.name: e for e in out.estimators}
    for nm in ("tac", "plain"):
        np.testing.assert_array_equal(by[nm].lat, by["free_inertial"].lat)
        np.testing.assert_array_equal(by[nm].lon, by["free_inertial"].lon)
        np.testing.assert_array_equal(by[nm].cov_ne, by["free_inertial"].cov_ne)
        assert by[nm].matcher is None and len(by[nm].fix_t) == 0
    np.testing.assert_array_equal(by["nav"].lat, by["nav2"].lat)
    assert not np.array_equal(by["nav"].lat, by["tac"].lat)
    # reversed order, another estimator in front: the navigation track is unchanged
    doc2 = _grades_doc([_free("con", "consumer"), _free("nav", "navigation")])
    out2 = Mdl.PipelineModel(scenario_from_dict(doc2)).run(np.random.SeedSequence(5))
    np.testing.assert_array_equal(out2.estimators[1].lat, by["nav"].lat)
    np.testing.assert_array_equal(out2.estimators[1].lon, by["nav"].lon)
    # the seed of a grade: the baseline's child 0 for the [imu] grade, a distinct grandchild for another grade
    ss = np.random.SeedSequence(5)
    assert Mdl.grade_seed(ss, "tactical", "tactical").spawn_key == Mdl.child(ss, 0).spawn_key
    keys = {Mdl.grade_seed(ss, g, "tactical").spawn_key for g in ("navigation", "precision", "commercial", "consumer")}
    assert len(keys) == 4 and Mdl.child(ss, 0).spawn_key not in keys


def test_navigation_grade_drifts_less_than_the_tactical_baseline_within_its_own_sigma():
    """Zero initial errors, 10 min: the drift is the IMU's alone. A navigation-grade INS (H764-G: 0.0035 deg/h,
    25 ug) ends far closer to the truth than the tactical baseline (HG-1700: 1 deg/h, 1 mg), and each final error
    lies within 4 sigma of its own fuser's covariance, which propagates that grade's noise (ImuNoise.from_grade)."""
    from magnav_ins.core.frames import horizontal_error_m

    zero = {"position_sigma_m": 0.0, "velocity_sigma_mps": 0.0, "attitude_sigma_deg": [0.0, 0.0, 0.0]}
    doc = _grades_doc([_free("nav", "navigation")], duration_s=600.0, init=zero)
    out = Mdl.PipelineModel(scenario_from_dict(doc)).run(np.random.SeedSequence(2))
    final = {}
    for e in out.estimators:
        err = horizontal_error_m(e.lat, e.lon, out.lat_true, out.lon_true)
        sigma = float(np.sqrt(np.trace(e.cov_ne[-1])))
        final[e.name] = (float(err[-1]), sigma)
        assert err[-1] < 4.0 * sigma, (e.name, err[-1], sigma)
    (e_nav, s_nav), (e_tac, s_tac) = final["nav"], final["free_inertial"]
    assert e_nav < 0.2 * e_tac, final
    assert s_nav < 0.2 * s_tac, final  # the navigation fuser's covariance is that grade's, not the baseline's


def test_study_of_estimators_without_fixes_reports_no_availability():
    """metrics.json and the report of a study whose estimators issue no fixes: availability and fix statistics are
    null / '–' (not 0), the NEES and errors are defined."""
    from magnav_ins.studies import reports, runner

    model = Mdl.PipelineModel(scenario_from_dict(_grades_doc([_free("nav", "navigation")], duration_s=60.0)))
    doc = runner.study_metrics(runner.execute(model, 2, 0), 0, 0.0, "grades")
    m = doc["estimators"]["nav"]
    assert m["matcher"] is None and m["fusion"] == "free_inertial"
    assert m["availability"] is None and m["fix_attempts"] == 0 and m["fixes_issued"] == 0
    assert m["fix_within_3m_fraction"] is None
    assert m["rms_horizontal_m"] > 0 and m["nees_mean"] > 0
    row = next(r for r in reports.metrics_table(doc).splitlines() if r.startswith("| nav "))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[1] == "–" and cells[8] == "–" and cells[9] == "–", row


def test_graph_smoothed_track_beats_its_online_track_and_matches_the_ukf_smoother():
    """``smooth = 1`` with ``fusion.kind = "graph"`` reports the batch LM solution (re-integrated between the graph's
    nodes, which sit only at the fix times) with its Marginals covariance: on the run of
    ``test_smoothed_estimator_beats_its_own_online_track_with_the_same_fixes`` it is closer to the truth than the
    graph's online track, within 30 % of the UKF's RTS-smoothed RMS (a peer smoother on the same fixes), and its
    covariance is consistent (mean 2-dof NEES finite and below 10; seed 11: 16.6 m vs 44.5 m online, UKF
    smoothed 13.4 m, NEES 8.8)."""
    from magnav_ins.core.frames import horizontal_error_m

    est = {"matcher": {"kind": "ml"}, "window": 10, "match_every": 5}
    doc = {
        **BASE,
        "trajectory": {**BASE["trajectory"], "duration_s": 300.0},
        "map": {**BASE["map"], "options": {**BASE["map"]["options"], "sigma": 20.0, "correlation_length_m": 400.0}},
        "sensor": {"kind": "gravimeter", "sigma": 1.0, "interval_s": 2.0},
        "estimator": [
            {"name": "ukf_sm", **est, "fusion": {"kind": "ukf"}, "smooth": 2},
            {"name": "graph", **est, "fusion": {"kind": "graph"}},
            {"name": "graph_sm", **est, "fusion": {"kind": "graph"}, "smooth": 1},
        ],
    }
    out = Mdl.PipelineModel(scenario_from_dict(doc)).run(np.random.SeedSequence(11))
    ukf_sm, on, sm = (next(e for e in out.estimators if e.name == n) for n in ("ukf_sm", "graph", "graph_sm"))
    np.testing.assert_array_equal(on.fix_t, sm.fix_t)
    np.testing.assert_array_equal(on.fix_lat, sm.fix_lat)  # the same fixes: only the reported track differs
    assert np.sum(sm.fix_available) >= 5

    def rms(e) -> float:
        return float(np.sqrt(np.mean(horizontal_error_m(e.lat, e.lon, out.lat_true, out.lon_true) ** 2)))

    assert rms(sm) < rms(on), (rms(sm), rms(on))
    assert abs(rms(sm) - rms(ukf_sm)) < 0.3 * rms(ukf_sm), (rms(sm), rms(ukf_sm))
    dn, de = latlon_to_meters(sm.lat - out.lat_true, sm.lon - out.lon_true, out.lat_true)
    r = np.stack([dn, de], -1)
    nees = float(np.mean(np.einsum("ni,nij,nj->n", r, np.linalg.inv(sm.cov_ne), r)))
    assert np.isfinite(nees) and nees < 10.0, nees


def test_graph_smoothed_track_follows_turns_between_sparse_nodes():
    """Nodes one minute apart on a rectangular circuit (three 90-degree turns between them): the smoothed track is
    re-integrated from the smoothed nodes with the IMU, so it follows the turns (RMS against the simulated truth a
    few metres, as the 10 m fixes allow) where a straight line between the nodes cuts the corners by hundreds of
    metres; it passes through the batch LM nodes themselves (``node_trajectory(smoothed=True)``)."""
    from magnav_ins.aiding.fusion import ImuNoise, make_fuser
    from magnav_ins.core.frames import horizontal_error_m, meters_to_latlon
    from magnav_ins.core.types import Fix, NavEstimate
    from magnav_ins.ins import imu_models, simulate
    from magnav_ins.ins.error_model import initial_covariance

    d = np.pi / 180.0
    corners = [(-35.0, 149.0), (-35.0, 149.05), (-34.97, 149.05), (-34.97, 149.0), (-35.0, 149.0)]
    truth = simulate.waypoints(np.array([(la * d, lo * d, 500.0) for la, lo in corners]), 70.0, 10.0)
    grade = imu_models.get_grade("tactical")
    imu, _ = imu_models.corrupt(simulate.ideal_imu(truth), grade, np.random.default_rng(0))
    P0 = initial_covariance(grade, position_sigma_m=5.0, velocity_sigma_mps=0.2, attitude_sigma_rad=np.full(3, 1e-3))
    fuser = make_fuser("graph", NavEstimate(truth.at(0), P0), ImuNoise.from_grade(grade))
    rng = np.random.default_rng(1)
    i = 1
    for t in np.arange(truth.t[0] + 60.0, truth.t[-1], 60.0):
        j = int(np.searchsorted(imu.t, t + 1e-9))
        fuser.propagate(imu.slice(i, j))
        i = j
        s = truth.at(j - 1)
        dlat, dlon = meters_to_latlon(*rng.normal(0.0, 10.0, 2), s.lat, s.h)
        fix = Fix(s.t, s.lat + float(dlat), s.lon + float(dlon), np.eye(2) * 100.0)
        assert fuser.correct(fix, height_m=500.0, height_sigma_m=1.0).accepted
    fuser.propagate(imu.slice(i, len(imu)))
    t_out = truth.t[::10]
    track, cov = fuser.smoothed_track(imu, t_out)
    nodes = fuser.node_trajectory(smoothed=True)  # includes the closing node at the last IMU time
    assert len(nodes) == 5 and nodes.t[-1] == pytest.approx(truth.t[-1])
    k = np.searchsorted(truth.t, t_out)
    err = horizontal_error_m(track.lat, track.lon, truth.lat[k], truth.lon[k])
    lat_lin, lon_lin = np.interp(t_out, nodes.t, nodes.lat), np.interp(t_out, nodes.t, nodes.lon)
    err_lin = horizontal_error_m(lat_lin, lon_lin, truth.lat[k], truth.lon[k])
    assert np.sqrt(np.mean(err**2)) < 15.0 and np.sqrt(np.mean(err_lin**2)) > 200.0, (err.max(), err_lin.max())
    at_nodes = np.searchsorted(t_out, nodes.t[:-1])  # the circuit starts on the output grid; nodes fall on it
    np.testing.assert_allclose(t_out[at_nodes], nodes.t[:-1], atol=1e-9)
    gap = horizontal_error_m(track.lat[at_nodes], track.lon[at_nodes], nodes.lat[:-1], nodes.lon[:-1])
    assert np.max(gap) < 1e-3, gap
    assert np.all(np.isfinite(cov)) and np.all(np.linalg.eigvalsh(cov) > 0.0)
