"""The information bound with the real readings' model (issue 13): map error in the variance, correlated readings
counted by their effective number, an unknown level as a state. Checked against cases computed by hand."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from magnav_ins.aiding.matchers.map_error import MapErrorModel
from magnav_ins.core.errors import InputError
from magnav_ins.maps.variability import fisher_information_ne, posterior_crlb
from magnav_ins.studies import model
from magnav_ins.studies.crlb import flight_crlb
from magnav_ins.studies.scenario import scenario_from_dict


def test_fisher_information_weight_and_level_by_hand():
    g = np.array([3.0, -4.0])  # |g| = 5 unit/m
    j = fisher_information_ne(g, 2.0, 0.5)
    assert np.allclose(j, 0.5 * np.outer(g, g) / 4.0)
    jl = fisher_information_ne(g, 2.0, 0.5, level=True)  # about (north, east, level): H = [g_n, g_e, 1]
    h = np.array([3.0, -4.0, 1.0])
    assert jl.shape == (3, 3) and np.allclose(jl, 0.5 * np.outer(h, h) / 4.0)
    # per-reading sigmas and weights broadcast; a vector reading has one level per component
    gs = np.tile(g, (4, 1))
    js = fisher_information_ne(gs, np.array([1.0, 2.0, 1.0, 2.0]), np.array([1.0, 1.0, 0.25, 0.0]))
    assert np.allclose(js[1], js[0] / 4.0) and np.allclose(js[2], js[0] / 4.0) and not np.any(js[3])
    gv = np.arange(6.0).reshape(3, 2)
    jv = fisher_information_ne(gv, 1.0, level=True)
    hv = np.hstack([gv, np.eye(3)])
    assert jv.shape == (5, 5) and np.allclose(jv, hv.T @ hv)
    with pytest.raises(InputError, match="weight"):
        fisher_information_ne(g, 1.0, 1.5)


def test_constant_gradient_map_with_an_unknown_level_by_hand():
    """A static position (Phi = I, Q = 0) read K times on a constant-gradient map, ``z = |g| u + c + v``: the
    level and the position along the gradient are confounded, so however many readings the bound along the gradient
    stops at ``1 / (|g|^2 / sigma_c^2 + 1 / p)``; across the gradient it stays the prior ``p``."""
    g = np.array([0.6, 0.8]) * 0.05  # 50 nT/km along the unit vector (0.6, 0.8)
    s, w, p, sc = 27.0, 0.3, 400.0**2, 30.0
    P0 = np.diag([p, p, sc**2])
    for K in (1, 10, 10000):
        J = np.tile(fisher_information_ne(g, s, w, level=True), (K, 1, 1))
        P = posterior_crlb(P0, np.tile(np.eye(3), (K, 1, 1)), np.zeros((K, 3, 3)), J)[-1]
        u = np.array([0.6, 0.8])
        a, b, d = K * w * 0.05**2 / s**2, K * w * 0.05 / s**2, K * w / s**2  # the (u, c) information by hand
        Juc = np.array([[a + 1 / p, b], [b, d + 1 / sc**2]])
        assert u @ P[:2, :2] @ u == pytest.approx(np.linalg.inv(Juc)[0, 0], rel=1e-9)
        v = np.array([-0.8, 0.6])
        assert v @ P[:2, :2] @ v == pytest.approx(p, rel=1e-9)
    assert u @ P[:2, :2] @ u == pytest.approx(1.0 / (0.05**2 / sc**2 + 1.0 / p), rel=1e-3)  # 600 m: the level's
    # with the level known the same readings pin the position far better
    Pk = posterior_crlb(
        P0[:2, :2],
        np.tile(np.eye(2), (K, 1, 1)),
        np.zeros((K, 2, 2)),
        np.tile(fisher_information_ne(g, s, w), (K, 1, 1)),
    )[-1]
    assert u @ Pk @ u < 0.01 * (u @ P[:2, :2] @ u)


def _scenario():
    return scenario_from_dict(
        {
            "name": "crlb reading model",
            "trajectory": {"kind": "great_circle", "start": [45.0, 7.0], "end": [45.0, 7.2], "altitude_m": 100.0,
                           "speed_mps": 20.0, "duration_s": 600.0},
            "imu": {"grade": "tactical", "rate_hz": 1.0},
            "init": {"position_sigma_m": 50.0},
            "map": {"path": "synthetic:random_field", "kind": "total_field_anomaly_nt",
                    "options": {"seed": 3, "origin_deg": [44.95, 6.95, 100.0], "shape": [200, 400], "spacing_m": 100.0,
                                "correlation_length_m": 1000.0, "sigma": 100.0}},
            "sensor": {"kind": "scalar_magnetometer", "sigma": 1.0, "interval_s": 10.0},
            "estimator": [{"name": "pmht+ukf", "matcher": {"kind": "pmht"}, "fusion": {"kind": "ukf"}}],
        }
    )  # fmt: skip


def test_flight_crlb_reading_model_orders_and_equivalences():
    sc = _scenario()
    sh = model.PipelineModel(sc).shared()
    args = (sc, sh["truth"], sh["imu"], sh["map"])
    t, free = flight_crlb(*args, readings=False)
    _, plain = flight_crlb(*args)
    ds = 20.0 * 10.0  # m between readings
    # map error sigma_m = sqrt(3) sensor sigma with independent readings (ell << ds): each reading is worth 1/4 ...
    _, quarter_var = flight_crlb(*args, map_error=MapErrorModel("option", np.sqrt(3.0), 1.0))
    # ... as is a reading of the sensor's variance whose weight is ds / ell = 1/4 (a negligible map error)
    _, quarter_w = flight_crlb(*args, map_error=MapErrorModel("option", 1e-9, 4.0 * ds))
    assert np.allclose(quarter_var, quarter_w, rtol=2e-3)
    # and, with Phi, Q as they are, it equals the plain bound of a sensor with twice the sigma
    sc2 = dataclasses.replace(sc, sensor=dataclasses.replace(sc.sensor, sigma=2.0))
    _, doubled = flight_crlb(sc2, *args[1:])
    assert np.allclose(quarter_var, doubled, rtol=1e-6)
    # more noise, correlation, an unknown level: each can only raise the bound; none beats the free INS
    _, with_level = flight_crlb(*args, map_error=MapErrorModel("option", 10.0, 300.0), level_sigma=30.0)
    _, no_level = flight_crlb(*args, map_error=MapErrorModel("option", 10.0, 300.0))
    _, indep = flight_crlb(*args, map_error=MapErrorModel("option", 10.0, 300.0), count_correlation=False)
    tol = 1e-9
    assert (
        np.all(plain <= quarter_var + tol) and np.all(indep <= no_level + tol) and np.all(no_level <= with_level + tol)
    )
    assert np.all(with_level <= free + tol) and with_level[-1] < 0.5 * free[-1]
    assert with_level[-1] > 1.5 * plain[-1]


def test_suite_case_bound_and_its_pooling(tmp_path):
    """The suite's bound of a case (an Osborne tie line, 60 s): on the run's output samples, below the free INS's
    covariance, pooled into every estimator's figures and the report's xCRLB column."""
    from magnav_ins.studies import suite

    case = suite.Case("osborne_tactical", suite.OSBORNE_SURVEY, suite.OSBORNE_MAP, 10152, 65.0, "tactical",
                      trajectory_keys=(("duration_s", 60.0),))  # fmt: skip
    b = suite.case_bound(case)
    assert len(b["t"]) == len(b["crlb"]) == len(b["free"]) and b["t"][-1] == pytest.approx(60.0)
    assert np.all(b["crlb"] <= b["free"] + 1e-9) and b["crlb_rms"] == pytest.approx(np.sqrt(np.mean(b["crlb"] ** 2)))
    mc = suite.case_bound(case, draws=50)
    assert mc["crlb_rms"] == b["crlb_rms"] and 0.0 <= mc["crlb_wang_mc"] <= 1.0 and 0.0 <= mc["free_wang_mc"] <= 1.0
    bi = suite.case_bound(case, count_correlation=False)
    assert bi["crlb_rms"] < b["crlb_rms"]  # every reading independent: a lower (more optimistic) bound
    two = suite.pooled_bound([b, bi])
    assert two["crlb_rms_horizontal_m"] == pytest.approx(np.sqrt(0.5 * (b["crlb_rms"] ** 2 + bi["crlb_rms"] ** 2)))
    res = suite.run_suite(seeds=1, cases=[case], estimators=("pmht+ukf",), rio_survey=tmp_path / "absent.csv.xz")
    m = res.groups["osborne_tactical"]["pmht+ukf"]
    assert m["crlb_rms_horizontal_m"] == pytest.approx(b["crlb_rms"]) and m["crlb_wang_rate"] in (0.0, 1.0)
    assert "xCRLB" in suite.report(res)


def test_bound_monte_carlo_runs_have_the_bounds_spread():
    """The Kalman filter of the linearised flight attains the bound: over many draws its horizontal mean-square error
    is the bound's ``P_NN + P_EE`` and the free INS's is the free covariance's (within the Monte Carlo spread)."""
    from magnav_ins.maps.variability import posterior_crlb
    from magnav_ins.studies.crlb import HOLD, bound_monte_carlo, flight_system

    sc = _scenario()
    sh = model.PipelineModel(sc).shared()
    args = (sc, sh["truth"], sh["imu"], sh["map"])
    edges, P0, Phi, Q, J = flight_system(*args, map_error=MapErrorModel("option", 10.0, 300.0), level_sigma=30.0)
    P = posterior_crlb(P0, Phi, Q, J, hold=HOLD)
    Pf = posterior_crlb(P0, Phi, Q, np.zeros_like(J), hold=HOLD)
    err, free = bound_monte_carlo(P0, Phi, Q, J, 2000, np.random.default_rng(5))
    for k in (len(edges) // 3, len(edges) - 1):
        # mean of a chi-square(2)-like sum over 2000 draws: ~3 % spread
        assert np.mean(err[:, k] ** 2) == pytest.approx(P[k, 0, 0] + P[k, 1, 1], rel=0.1)
        assert np.mean(free[:, k] ** 2) == pytest.approx(Pf[k, 0, 0] + Pf[k, 1, 1], rel=0.1)
    assert np.mean(err[:, -1] ** 2) < 0.3 * np.mean(free[:, -1] ** 2)


def test_suite_bounds_without_flying(capsys):
    from magnav_ins.core.errors import ConfigError
    from magnav_ins.studies import suite

    groups, text = suite.suite_bounds(quick=True, only=("osborne_navigation",), draws=10)
    m = groups["osborne_navigation"]
    assert m["cases"] == 4 and set(groups) == {"osborne_navigation"}
    assert m["free_over_crlb"] > 1.0 and 0.0 <= m["crlb_wang_mc_rate"] <= 1.0 and 0.0 <= m["crlb_wang_rate"] <= 1.0
    assert "osborne_navigation:" in text and "free/CRLB" in text
    with pytest.raises(ConfigError, match="unknown suite group"):
        suite.suite_bounds(only=("osborne",))
