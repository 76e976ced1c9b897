"""IMU grade presets (against the published tables) and truth error injection (statistics, reproducibility)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from magnav_ins.core.errors import ConfigError
from magnav_ins.core.types import ImuBatch
from magnav_ins.ins.imu_models import GRADES, corrupt, corrupt_arrays, draw_errors, get_grade

RAD_TO_DEG = 180.0 / math.pi


def test_storms_table_2_2_round_trip():
    # Storms 2009 Table 2.2, columns Crista / HG-1700 / H764-G, converted back to the table's units
    table = {
        "commercial": (5.0, 1800, 2.23, 10000, 0.196, 0.261, 10000),
        "tactical": (10.0, 1.0, 0.3, 150, 0.0098, 0.57, 300),
        "navigation": (3.906, 0.0015, 0.002, 5, 2.45e-4, 0.0143, 100),
    }
    for name, (ms, gb, arw, gsf, ab, vrw, asf) in table.items():
        g = get_grade(name)
        assert 1e3 / g.rate_hz == pytest.approx(ms)
        assert np.allclose(g.arr("gyro_bias_sigma") * RAD_TO_DEG * 3600.0, gb)
        assert g.gyro_bias_tau == 3600.0 and g.accel_bias_tau == 3600.0
        assert np.allclose(g.arr("arw") * RAD_TO_DEG * 60.0, arw)
        assert g.gyro_scale_sigma == pytest.approx(gsf * 1e-6)
        assert np.allclose(g.arr("accel_bias_sigma"), ab)
        assert np.allclose(g.arr("vrw") * 60.0, vrw)
        assert g.accel_scale_sigma == pytest.approx(asf * 1e-6)


def test_wang_table_1_horizontal_and_vertical():
    p, q = get_grade("precision"), get_grade("quantum")
    assert np.allclose(p.arr("accel_turn_on_sigma"), [2e-6, 2e-6, 2.5e-8])
    assert np.allclose(p.arr("vrw"), [8e-5, 8e-5, 1.6e-6])
    assert np.allclose(p.arr("gyro_turn_on_sigma") * RAD_TO_DEG * 3600.0, [2e-5, 2e-5, 1e-3])
    assert np.allclose(p.arr("arw") * RAD_TO_DEG * 3600.0, [1e-3, 1e-3, 3e-2])  # deg/h/sqrt(Hz)
    assert np.allclose(q.arr("accel_turn_on_sigma"), 1e-8) and np.allclose(q.arr("vrw"), 3e-8)
    # QAPCG keeps the precision gyroscope
    assert q.gyro_turn_on_sigma == p.gyro_turn_on_sigma and q.arw == p.arw


def test_every_grade_has_a_source_and_get_grade_errors():
    for g in GRADES.values():
        assert g.source
    assert get_grade(" Tactical ") is GRADES["tactical"]
    with pytest.raises(ConfigError, match="'hg9900'.*consumer, commercial, tactical, navigation, precision, quantum"):
        get_grade("hg9900")
    with pytest.raises(ConfigError, match="arw"):
        dataclasses.replace(GRADES["tactical"], arw=(-1.0, 0.0, 0.0))


def test_gauss_markov_and_white_noise_statistics():
    g = get_grade("tactical")
    rng = np.random.default_rng(3)
    dt = 1.0
    t = np.arange(0.0, 3600.0 + dt, dt)
    z = np.zeros((len(t), 3))
    gyro, accel, tr = corrupt_arrays(t, z, z, g, rng, runs=400)
    # stationary GM: std sigma at every time, correlation exp(-lag/tau)
    for b, sig in ((tr.gyro_bias, g.gyro_bias_sigma[0]), (tr.accel_bias, g.accel_bias_sigma[0])):
        assert np.std(b[:, 0]) / sig == pytest.approx(1.0, abs=0.06)
        assert np.std(b[:, -1]) / sig == pytest.approx(1.0, abs=0.06)
        rho = np.mean(b[:, 0] * b[:, -1]) / np.sqrt(np.mean(b[:, 0] ** 2) * np.mean(b[:, -1] ** 2))
        assert rho == pytest.approx(math.exp(-1.0), abs=0.06)
    # white noise: per-sample std N / sqrt(dt); the integrated angle is a random walk ARW sqrt(T)
    w = gyro - tr.gyro_bias
    assert np.std(w) / (g.arw[0] / math.sqrt(dt)) == pytest.approx(1.0, abs=0.01)
    angle = np.sum(w[:, 1:, :] * dt, axis=1)
    assert np.std(angle) / (g.arw[0] * math.sqrt(3600.0)) == pytest.approx(1.0, abs=0.06)
    vel = np.sum((accel - tr.accel_bias)[:, 1:, :] * dt, axis=1)
    assert np.std(vel) / (g.vrw[0] * math.sqrt(3600.0)) == pytest.approx(1.0, abs=0.06)


def test_scale_factor_misalignment_and_turn_on_are_applied_exactly(rng):
    base = get_grade("consumer")
    quiet = dataclasses.replace(base, arw=(0.0,) * 3, vrw=(0.0,) * 3)
    t = np.arange(0.0, 10.0, 0.01)
    omega = np.column_stack([np.sin(t), np.cos(t), 0.1 * t])
    f = np.column_stack([0.3 * t, -np.ones_like(t), -9.8 + 0 * t])
    err = draw_errors(quiet, rng)
    out, trace = corrupt(ImuBatch(t, omega, f), quiet, rng, errors=err)
    assert np.allclose(out.gyro_b, omega @ (np.eye(3) + err.M_g).T + err.gyro_turn_on, atol=1e-15)
    assert np.allclose(out.accel_b, f @ (np.eye(3) + err.M_a).T + err.accel_turn_on, atol=1e-15)
    assert np.allclose(trace.gyro_bias, err.gyro_turn_on)
    # the drawn cross-coupling has the grade's spread
    many = draw_errors(base, np.random.default_rng(0), runs=5000)
    assert np.std(many.M_g[:, 0, 1]) == pytest.approx(base.gyro_misalignment_sigma, rel=0.05)
    assert np.std(many.M_a[:, 2, 2]) == pytest.approx(base.accel_scale_sigma, rel=0.05)
    assert np.std(many.accel_turn_on) == pytest.approx(base.accel_turn_on_sigma[0], rel=0.05)


def test_reproducible_from_the_generator():
    g = get_grade("commercial")
    t = np.arange(0.0, 5.0, 0.005)
    z = np.zeros((len(t), 3))
    a = corrupt_arrays(t, z, z, g, np.random.default_rng(7), runs=3)
    b = corrupt_arrays(t, z, z, g, np.random.default_rng(7), runs=3)
    c = corrupt_arrays(t, z, z, g, np.random.default_rng(8), runs=3)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
    assert not np.allclose(a[0], c[0])
    assert a[0].shape == (3, len(t), 3)


def test_gauss_markov_on_irregular_times_keeps_its_statistics():
    g = get_grade("tactical")
    rng = np.random.default_rng(5)
    t = np.cumsum(rng.uniform(5.0, 40.0, 200))  # irregular sampling over ~1.7 h
    z = np.zeros((len(t), 3))
    _, _, tr = corrupt_arrays(t, z, z, g, rng, runs=2000)
    b = tr.gyro_bias[..., 0]
    assert np.std(b[:, -1]) / g.gyro_bias_sigma[0] == pytest.approx(1.0, abs=0.05)
    lag = t[-1] - t[0]
    rho = np.mean(b[:, 0] * b[:, -1]) / np.mean(b[:, 0] ** 2)
    assert rho == pytest.approx(math.exp(-lag / g.gyro_bias_tau), abs=0.05)


def test_grade_from_a_json_table_replaces_only_the_fields_given():
    import json

    base = get_grade("navigation")
    g = get_grade(
        json.dumps({"base": "Navigation", "arw": 4.2e-6, "vrw": [6e-5, 6e-5, 7e-5], "accel_scale_sigma": 1e-3})
    )
    assert g.arw == (4.2e-6,) * 3 and g.vrw == (6e-5, 6e-5, 7e-5) and g.accel_scale_sigma == 1e-3
    assert g.gyro_bias_sigma == base.gyro_bias_sigma and g.rate_hz == base.rate_hz
    assert g.name == "navigation+custom"
    for bad, words in (
        ('{"arw": 1}', "'base'"),
        ('{"base": "navigation", "arv": 1}', "unknown field 'arv'"),
        ('{"base": "navigation", "vrw": [1, 2]}', "one or three numbers"),
        ('{"base": "navigation", "arw": -1}', "non-negative"),
        ('{"base": "mems"}', "unknown IMU grade"),
        ("{base: 1}", "not a JSON table"),
    ):
        with pytest.raises(ConfigError, match=words):
            get_grade(bad)
