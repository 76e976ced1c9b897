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
