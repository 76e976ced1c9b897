"""The closed-loop pipeline, with a test-only "noisy truth" matcher (truth + noise of known covariance) and a
flat stub map, so that what is tested is the plumbing: priors handed to the matcher, fixes fed to the fuser,
online == offline, outputs at the requested rate, bad input refused."""

from __future__ import annotations

import dataclasses
from functools import lru_cache

import numpy as np
import pytest

from magnav_ins.aiding.fusion import make_fuser
from magnav_ins.aiding.fusion.common import ImuNoise
from magnav_ins.core.errors import ConfigError, InputError
from magnav_ins.core.frames import horizontal_error_m
from magnav_ins.core.protocols import MatchWindow
from magnav_ins.core.types import LAYOUT_15, FieldKind, FieldReadings, Fix, NavEstimate
from magnav_ins.core.units import DEG_TO_RAD
from magnav_ins.ins import imu_models, simulate
from magnav_ins.ins.error_model import apply_error
from magnav_ins.pipeline import Pipeline

R_FIX = np.array([[16.0, 4.0], [4.0, 9.0]])
RATE_HZ = 10.0
DURATION_S = 200.0


class FlatMap:
    """Test-only map: zero field everywhere."""

    kind = FieldKind.GRAVITY_DISTURBANCE_MGAL

    def value(self, lat, lon, h=None):
        return np.zeros(np.shape(lat))

    def gradient_ne(self, lat, lon, h=None):
        return np.zeros(np.shape(lat) + (2,))

    def covers(self, lat, lon):
        return np.ones(np.shape(lat), dtype=bool)


class NoisyTruthMatcher:
    """Test-only batch matcher: the true position at the window's last reading plus noise ~ N(0, R_FIX); the
    noise is keyed on the time so that two runs over the same data get the same fixes. Keeps the windows."""

    name = "noisy-truth"

    def __init__(self, traj) -> None:
        self.traj = traj
        self.windows: list[MatchWindow] = []

    def match(self, window: MatchWindow, fmap) -> Fix:
        self.windows.append(window)
        t = float(window.readings.t[-1])
        k = int(np.argmin(np.abs(self.traj.t - t)))
        e = np.linalg.cholesky(R_FIX) @ np.random.default_rng(int(round(t * 1000))).standard_normal(2)
        s = apply_error(self.traj.at(k), np.r_[e, np.zeros(7)])
        return Fix(t, s.lat, s.lon, R_FIX, score=1.0, source=self.name)


@lru_cache(maxsize=1)
def scenario():
    d = DEG_TO_RAD
    traj = simulate.great_circle(45.0 * d, 7.0 * d, 45.3 * d, 7.4 * d, 2000.0, 80.0, RATE_HZ)
    traj = traj.slice(0, int(DURATION_S * RATE_HZ) + 1)
    imu = simulate.ideal_imu(traj)
    g = imu_models.get_grade("tactical")
    rng = np.random.default_rng(7)
    err = imu_models.draw_errors(g, rng)
    err = dataclasses.replace(err, M_g=np.zeros((3, 3)), M_a=np.zeros((3, 3)))
    imu_c, _ = imu_models.corrupt(imu, g, rng, err)
    nz = ImuNoise.from_grade(g)
    sig0 = np.r_[[10.0] * 3, [0.1] * 3, [0.02 * d] * 2, 0.2 * d, [nz.accel_bias_init_sigma] * 3,
                 [nz.gyro_bias_init_sigma] * 3]  # fmt: skip
    init = NavEstimate(apply_error(traj.at(0), np.r_[8.0, -6.0, 0.0, 0.05, 0.0, 0.0, 0.0, 0.0, 0.001]),
                       np.diag(sig0**2), LAYOUT_15)  # fmt: skip
    t_r = np.arange(1.0, DURATION_S + 0.5, 1.0) + 0.05  # readings at 1 Hz, between IMU samples
    readings = FieldReadings(t_r, np.zeros(len(t_r)), 1.0, FieldKind.GRAVITY_DISTURBANCE_MGAL)
    return traj, imu_c, init, nz, readings


def height_aid(traj):
    def aid(t: float):
        k = int(np.argmin(np.abs(traj.t - t)))
        return float(traj.h[k]), 3.0

    return aid


@pytest.mark.parametrize("kind", ["ukf", "graph"])
def test_offline_run_aids_the_ins(kind: str) -> None:
    traj, imu, init, nz, readings = scenario()
    matcher = NoisyTruthMatcher(traj)
    pipe = Pipeline(make_fuser(kind, init, nz), matcher, FlatMap(), window=10, match_every=10,
                    height_aid=height_aid(traj))  # fmt: skip
    res = pipe.run(imu, readings, output_dt=2.0)
    assert np.allclose(res.trajectory.t, traj.t[0] + 2.0 * np.arange(len(res.trajectory)))
    assert res.P.shape == (len(res.trajectory), 15, 15)
    assert len(res.fixes) == len(res.innovations) == int(np.sum(readings.t <= imu.t[-1])) // 10
    assert all(inn.accepted for inn in res.innovations)
    k = np.searchsorted(traj.t, res.trajectory.t - 1e-9)
    err = horizontal_error_m(res.trajectory.lat, res.trajectory.lon, traj.lat[k], traj.lon[k])
    sig = np.sqrt(res.P[:, 0, 0] + res.P[:, 1, 1])
    free = Pipeline(make_fuser("free_inertial", init, nz)).run(imu, None, output_dt=2.0)
    err_free = horizontal_error_m(free.trajectory.lat, free.trajectory.lon, traj.lat[k], traj.lon[k])
    assert np.sqrt(np.mean(err[50:] ** 2)) < 12.0  # 4-5 m fixes every 10 s, straight flight (yaw weakly observable)
    assert np.sqrt(np.mean(err[50:] ** 2)) < np.sqrt(np.mean(err_free[50:] ** 2)) / 3.0
    assert np.mean(err[10:] < 3.0 * sig[10:]) > 0.9
    # the matcher's prior: INS positions at the reading times, with their covariance
    w = matcher.windows[-1]
    assert w.cov_ne.shape == (10, 2, 2) and w.v_ne.shape == (10, 2)
    kk = np.array([int(np.argmin(np.abs(traj.t - t))) for t in w.readings.t])
    d = horizontal_error_m(w.lat, w.lon, traj.lat[kk], traj.lon[kk])
    assert np.all(d < 4.0 * np.sqrt(w.cov_ne[:, 0, 0] + w.cov_ne[:, 1, 1]) + 2.0)


def test_online_equals_offline() -> None:
    traj, imu, init, nz, readings = scenario()
    n = int(60 * RATE_HZ)
    imu = imu.slice(0, n)
    rd = FieldReadings(readings.t[readings.t < imu.t[-1]], readings.value[readings.t < imu.t[-1]], 1.0, readings.kind)
    off = Pipeline(make_fuser("ukf", init, nz), NoisyTruthMatcher(traj), FlatMap(), window=10, match_every=10)
    off.run(imu, rd)
    on = Pipeline(make_fuser("ukf", init, nz), NoisyTruthMatcher(traj), FlatMap(), window=10, match_every=10,
                  reading_sigma=1.0)  # fmt: skip
    r = 0
    for k in range(1, len(imu)):
        if r < len(rd) and rd.t[r] <= imu.t[k]:
            assert on.push_reading(float(rd.t[r]), rd.value[r]) is None  # ahead of the IMU: queued
            r += 1
        on.push_imu(float(imu.t[k]), imu.gyro_b[k], imu.accel_b[k])
    a, b = off.estimate().nav, on.estimate().nav
    assert abs(a.t - b.t) < 1e-9
    # the offline run also stops at its output times (extra covariance steps): equal to well below a millimetre
    assert horizontal_error_m(a.lat, a.lon, b.lat, b.lon) < 1e-3
    assert len(on.fixes) == len(off.fixes) == 5


def test_bad_input_and_configuration() -> None:
    traj, imu, init, nz, readings = scenario()
    with pytest.raises(ConfigError, match="needs a map"):
        Pipeline(make_fuser("ukf", init, nz), NoisyTruthMatcher(traj))
    pipe = Pipeline(make_fuser("ukf", init, nz), NoisyTruthMatcher(traj), FlatMap(), reading_sigma=1.0)
    pipe.push_imu(float(imu.t[1]), imu.gyro_b[1], imu.accel_b[1])
    with pytest.raises(InputError, match="time must increase"):
        pipe.push_imu(float(imu.t[0]), imu.gyro_b[0], imu.accel_b[0])
    with pytest.raises(InputError, match="non-finite"):
        pipe.push_imu(float(imu.t[2]), np.full(3, np.nan), imu.accel_b[2])
    with pytest.raises(InputError, match="non-finite"):
        pipe.push_reading(float(imu.t[1]), float("nan"))
    with pytest.raises(ConfigError):
        make_fuser("kalman", init, nz)


class NoisyTruthRecursive:
    """Test-only recursive matcher: keeps the readings' times; ``to_fix`` = truth at the last one + noise."""

    name = "noisy-truth-recursive"

    def __init__(self, traj) -> None:
        self.inner = NoisyTruthMatcher(traj)
        self.calls = {"initiate": 0, "predict": 0, "update": 0}

    def initiate(self, prior: NavEstimate, rng: np.random.Generator):
        self.calls["initiate"] += 1
        return {"t": prior.nav.t}

    def predict(self, state, prior: NavEstimate):
        self.calls["predict"] += 1
        return {"t": prior.nav.t}

    def update(self, state, readings: FieldReadings, fmap):
        self.calls["update"] += 1
        return {"t": float(readings.t[-1])}

    def to_fix(self, state) -> Fix:
        win = MatchWindow(FieldReadings(np.array([state["t"]]), np.zeros(1), 1.0, FieldKind.GRAVITY_DISTURBANCE_MGAL),
                          np.zeros(1), np.zeros(1), np.zeros(1), np.zeros((1, 2, 2)), np.zeros((1, 2)))  # fmt: skip
        return self.inner.match(win, None)


def test_recursive_matcher_loop() -> None:
    traj, imu, init, nz, readings = scenario()
    m = NoisyTruthRecursive(traj)
    res = Pipeline(make_fuser("ukf", init, nz), m, FlatMap(), match_every=10).run(imu.slice(0, 601), readings)
    n = int(np.sum(readings.t <= imu.t[600]))
    assert m.calls == {"initiate": 1, "predict": n - 1, "update": n}
    assert len(res.fixes) == n // 10 and all(inn.accepted for inn in res.innovations)


class CellMap(FlatMap):
    """Test-only flat map with 100 m cells (the default shortest section)."""

    spacing_m = (100.0, 100.0)


def test_a_window_that_did_not_move_is_not_matched() -> None:
    """A hovering or parked vehicle: its readings repeat one value, so a profile matcher would fit anywhere the map is
    flat. Such windows get "no fix: section too short" without a scan; the moving flight above is matched."""
    d = DEG_TO_RAD
    still = simulate.stationary(45.0 * d, 7.0 * d, 500.0, 0.3, 60.0, RATE_HZ)
    imu = simulate.ideal_imu(still)
    nz = ImuNoise.from_grade(imu_models.get_grade("tactical"))
    sig0 = np.r_[[10.0] * 3, [0.1] * 3, [0.02 * d] * 3, [1e-3] * 3, [1e-6] * 3]
    init = NavEstimate(still.at(0), np.diag(sig0**2), LAYOUT_15)
    t_r = np.arange(1.0, 59.5, 1.0) + 0.05
    rd = FieldReadings(t_r, np.zeros(len(t_r)), 1.0, FieldKind.GRAVITY_DISTURBANCE_MGAL)
    matcher = NoisyTruthMatcher(still)
    res = Pipeline(make_fuser("ukf", init, nz), matcher, CellMap(), window=10, match_every=10).run(imu, rd)
    assert matcher.windows == [] and len(res.fixes) == 5
    assert all(not f.available and f.reason.startswith("section too short") for f in res.fixes)
    assert all(not inn.accepted for inn in res.innovations)
    # the same still vehicle with the test turned off is matched; the moving flight (800 m a window) passes the default
    matcher = NoisyTruthMatcher(still)
    Pipeline(make_fuser("ukf", init, nz), matcher, CellMap(), window=10, match_every=10, min_section_m=0.0).run(imu, rd)
    assert len(matcher.windows) == 5
    traj, imu, init, nz, readings = scenario()
    matcher = NoisyTruthMatcher(traj)
    res = Pipeline(make_fuser("ukf", init, nz), matcher, CellMap(), window=10, match_every=10).run(imu, readings)
    assert len(matcher.windows) == len(res.fixes) > 0 and all(f.available for f in res.fixes)
    with pytest.raises(ConfigError, match="min_section_m"):
        Pipeline(make_fuser("ukf", init, nz), matcher, CellMap(), min_section_m=float("nan"))


class ShortSightedMatcher(NoisyTruthMatcher):
    """Test-only: a window under ``need`` readings is "no fix" with ``reason`` (an ambiguous likelihood: the section
    holds too few features); a longer one gets the noisy-truth fix."""

    def __init__(self, traj, need: int, reason: str) -> None:
        super().__init__(traj)
        self.need, self.reason = need, reason

    def match(self, window: MatchWindow, fmap) -> Fix:
        if len(window.readings) < self.need:
            self.windows.append(window)
            return Fix.no_fix(float(window.readings.t[-1]), self.reason, self.name)
        return super().match(window, fmap)


def test_an_ambiguous_window_is_tried_again_with_the_long_window() -> None:
    """``long_window``: a window whose fix is ambiguous (or reaches the search window's edge) is matched again over
    the last ``long_window`` readings, which end at the same reading; other "no fix" reasons are final."""
    traj, imu, init, nz, readings = scenario()
    matcher = ShortSightedMatcher(traj, 20, "ambiguous: 3 likelihood peaks in the search window")
    pipe = Pipeline(make_fuser("ukf", init, nz), matcher, FlatMap(), window=10, match_every=10, long_window=20)
    res = pipe.run(imu, readings)
    n = len(res.fixes)
    assert n >= 15
    # the first window (10 readings stored) cannot be tried again; every later one is, over 20 readings
    assert not res.fixes[0].available and res.fixes[0].reason.startswith("ambiguous")
    assert all(f.available for f in res.fixes[1:])
    lengths = [len(w.readings) for w in matcher.windows]
    assert lengths == [10] + [10, 20] * (n - 1)
    for short, long in zip(matcher.windows[1::2], matcher.windows[2::2], strict=True):
        assert long.readings.t[-1] == short.readings.t[-1] and np.all(long.readings.t[-10:] == short.readings.t)
    # a reason a longer window cannot help (here "flat map") is final; so is an ambiguous long window, with both reasons
    flat = ShortSightedMatcher(traj, 20, "flat map: feature variability 0.1 below 0.3")
    res = Pipeline(make_fuser("ukf", init, nz), flat, FlatMap(), window=10, match_every=10, long_window=20).run(
        imu, readings
    )
    assert [len(w.readings) for w in flat.windows] == [10] * len(res.fixes) and not any(f.available for f in res.fixes)
    never = ShortSightedMatcher(traj, 99, "ambiguous: 2 likelihood peaks")
    res = Pipeline(make_fuser("ukf", init, nz), never, FlatMap(), window=10, match_every=10, long_window=20).run(
        imu, readings
    )
    assert "; 20 readings: ambiguous" in res.fixes[-1].reason
    with pytest.raises(ConfigError, match="long_window"):
        Pipeline(make_fuser("ukf", init, nz), never, FlatMap(), window=10, long_window=10)


def test_the_bridge_s_background_scan_tries_the_long_window_too() -> None:
    from magnav_ins.mavlink.online import OnlinePipeline

    traj, imu, init, nz, readings = scenario()
    matcher = ShortSightedMatcher(traj, 20, "likelihood reaches the edge of the search window")
    pipe = OnlinePipeline(make_fuser("ukf", init, nz), matcher, FlatMap(), window=10, match_every=10, long_window=20,
                          reading_sigma=1.0, background_matching=True)  # fmt: skip
    r = 0
    for k in range(1, int(45 * RATE_HZ)):
        if r < len(readings) and readings.t[r] <= imu.t[k]:
            pipe.push_reading(float(readings.t[r]), readings.value[r])
            r += 1
        pipe.push_imu(float(imu.t[k]), imu.gyro_b[k], imu.accel_b[k])
    pipe.finish_matching(timeout_s=30.0)
    assert [len(w.readings) for w in matcher.windows] == [10, 10, 20, 10, 20, 10, 20]
    assert [f.available for f in pipe.fixes] == [False, True, True, True]
