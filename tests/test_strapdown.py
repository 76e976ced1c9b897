"""Strapdown mechanisation against independent truth: pyins's simulator and integrator, the Earth at rest, an
analytic coning motion, and the two forms (streaming / batch) and two IMU types (rate / increment) against each
other."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from magnav_ins.core.errors import InputError
from magnav_ins.core.frames import C_nb_from_q, horizontal_error_m, q_nb_from_euler
from magnav_ins.core.types import ImuBatch, ImuIncrements, NavState
from magnav_ins.ins import earth
from magnav_ins.ins.strapdown import StrapdownStepper, gravity_ned, integrate, integrate_batch


def _att_err(q_a: np.ndarray, q_b: np.ndarray) -> np.ndarray:
    """Rotation angle (rad) between attitudes."""
    return (Rotation.from_quat(q_a).inv() * Rotation.from_quat(q_b)).magnitude()


@pytest.fixture(scope="module")
def pyins_motion():
    """10 min of 100 Hz sine-velocity motion at sea level from pyins, increment-type IMU (exact integrals)."""
    sim = pytest.importorskip("pyins.sim")
    ref, imu = sim.generate_sine_velocity_motion(
        0.01, 600.0, [55.0, 37.0, 0.0], [5.0, -3.0, 0.0], velocity_change_amplitude=[1.0, 1.0, 0.0],
        sensor_type="increment",
    )  # fmt: skip
    t = imu.index.to_numpy(dtype=float)
    r0 = ref.iloc[0]
    init = NavState(
        float(t[0]), np.deg2rad(r0.lat), np.deg2rad(r0.lon), float(r0.alt), r0[["VN", "VE", "VD"]].to_numpy(float),
        q_nb_from_euler(*np.deg2rad(r0[["roll", "pitch", "heading"]].to_numpy(float))),
    )  # fmt: skip
    inc = ImuIncrements(
        t, imu[["gyro_x", "gyro_y", "gyro_z"]].to_numpy(), imu[["accel_x", "accel_y", "accel_z"]].to_numpy()
    )
    return ref, imu, init, inc


def test_gravity_ned_is_earth_gravity_n():
    lat = np.deg2rad(np.linspace(-89.0, 89.0, 37))
    for h in (-400.0, 0.0, 1500.0, 10_000.0):
        g = earth.gravity_n(lat, h)
        ours = np.array([gravity_ned(la, h) for la in lat])
        np.testing.assert_allclose(ours[:, 0], g[:, 0], rtol=0, atol=1e-12)
        np.testing.assert_allclose(ours[:, 1], g[:, 2], rtol=0, atol=1e-12)


@pytest.mark.filterwarnings("ignore:The copy keyword is deprecated")
def test_pyins_motion_at_least_as_accurate_as_pyins(pyins_motion):
    from pyins import strapdown as pyins_strapdown

    ref, imu, init, inc = pyins_motion
    ours = integrate(init, inc)
    theirs = pyins_strapdown.Integrator(ref.iloc[0], True).integrate(
        pyins_strapdown.compute_increments_from_imu(imu, "increment")
    )
    lat_t, lon_t = np.deg2rad(ref.lat.to_numpy()), np.deg2rad(ref.lon.to_numpy())
    e_ours = horizontal_error_m(ours.lat, ours.lon, lat_t, lon_t).max()
    e_pyins = horizontal_error_m(np.deg2rad(theirs.lat.to_numpy()), np.deg2rad(theirs.lon.to_numpy()), lat_t, lon_t)
    assert e_ours <= e_pyins.max()
    assert e_ours < 1e-3  # about 1e-4 m after 10 min
    np.testing.assert_allclose(ours.v_n, ref[["VN", "VE", "VD"]].to_numpy(), atol=1e-5)
    q_true = q_nb_from_euler(*np.deg2rad(ref[["roll", "pitch", "heading"]].to_numpy()).T)
    assert _att_err(ours.q_nb, q_true).max() < 1e-7


@pytest.mark.parametrize("rate_hz", [1.0, 10.0])
def test_rest_on_rotating_earth_24h(rate_hz):
    """An ideal IMU at rest (exact Earth rate and specific force -g_n at the site, h = 0) for 24 h: with the
    vertical channel held the horizontal position stays within 1 m (measured: under 1 cm)."""
    lat, lon = np.deg2rad(45.0), np.deg2rad(7.0)
    q = q_nb_from_euler(0.1, -0.2, 2.0)
    C_bn = C_nb_from_q(q).T
    n = int(86400 * rate_hz) + 1
    t = np.arange(n) / rate_hz
    gyro = np.tile(C_bn @ earth.omega_ie_n(lat), (n, 1))
    accel = np.tile(C_bn @ -earth.gravity_n(lat, 0.0), (n, 1))
    traj = integrate(NavState(0.0, lat, lon, 0.0, np.zeros(3), q), ImuBatch(t, gyro, accel), altitude_hold=0.0)
    assert horizontal_error_m(traj.lat, traj.lon, lat, lon).max() < 1.0
    assert np.abs(traj.v_n).max() < 1e-3
    assert _att_err(traj.q_nb[-1], q) < 1e-8
    # the free vertical channel is unstable: the same samples without the hold leave h meaningless within hours
    free = integrate(NavState(0.0, lat, lon, 0.0, np.zeros(3), q), ImuBatch(t, gyro, accel))
    assert abs(free.h[-1]) > 1e3


def test_stepper_equals_batch(pyins_motion):
    _, _, init, inc = pyins_motion
    k = 3000
    t, dth, dv = inc.t[:k], inc.dtheta_b[:k], inc.dv_b[:k]
    batch = integrate(init, ImuIncrements(t, dth, dv))
    step = StrapdownStepper(init)
    # the batch form uses sample 0 only as the previous increment; the stepper learns it from a first call that
    # the test makes from a state one interval earlier, then resets to init (reset keeps the coning memory)
    step.reset(NavState(t[0] - (t[1] - t[0]), init.lat, init.lon, init.h, init.v_n, init.q_nb))
    step.step_increment(t[0], dth[0], dv[0])
    step.reset(init)
    rows = []
    for j in range(1, k):
        step.step_increment(t[j], dth[j], dv[j])
        nav = step.nav
        rows.append([nav.lat, nav.lon, nav.h, *nav.v_n, *nav.q_nb])
    rows = np.array(rows)
    np.testing.assert_array_equal(rows[:, 0], batch.lat[1:])
    np.testing.assert_array_equal(rows[:, 2], batch.h[1:])
    np.testing.assert_array_equal(rows[:, 3:6], batch.v_n[1:])
    # NavState re-normalises q_nb: equal to the last bit but one
    np.testing.assert_allclose(rows[:, 6:], batch.q_nb[1:], rtol=0, atol=4e-16)
    assert step.t == t[-1]

    # advance(): the same steps in chunked compiled calls (what the CLI uses for long files)
    chunked = StrapdownStepper(init)
    chunked.prime(dth[0], dv[0])
    parts = [
        chunked.advance(ImuIncrements(t[i : i + 700], dth[i : i + 700], dv[i : i + 700])) for i in range(1, k, 700)
    ]
    np.testing.assert_array_equal(np.concatenate([p.lat for p in parts]), batch.lat[1:])
    np.testing.assert_array_equal(np.concatenate([p.v_n for p in parts]), batch.v_n[1:])
    np.testing.assert_array_equal(np.concatenate([p.q_nb for p in parts]), batch.q_nb[1:])

    # the parallel batch kernel (rate type, decimated) gives the same numbers as integrate() on the same rates
    dts = np.diff(t, prepend=t[0] - (t[1] - t[0]))[:, None]
    g, a = dth / dts, dv / dts
    single = integrate(init, ImuBatch(t, g, a))
    many = integrate_batch(
        t, np.stack([g, g]), np.stack([a, a]), np.full(2, init.lat), np.full(2, init.lon), np.full(2, init.h),
        np.tile(init.v_n, (2, 1)), np.tile(init.q_nb, (2, 1)), decimate=7,
    )  # fmt: skip
    assert many.lat.shape == (2, -(-k // 7)) and many.q_nb.shape == (2, -(-k // 7), 4)
    np.testing.assert_array_equal(many.t, t[::7])
    for r in range(2):
        np.testing.assert_array_equal(many.lat[r], single.lat[::7])
        np.testing.assert_array_equal(many.v_n[r], single.v_n[::7])
        np.testing.assert_array_equal(many.run(r).q_nb, single.q_nb[::7])


def test_rate_and_increment_types_agree(pyins_motion):
    """Mean rates over an interval are increments divided by its length: both IMU types give the same solution."""
    _, _, init, inc = pyins_motion
    dts = np.diff(inc.t, prepend=inc.t[0] - (inc.t[1] - inc.t[0]))[:, None]
    by_rate = integrate(init, ImuBatch(inc.t, inc.dtheta_b / dts, inc.dv_b / dts))
    by_inc = integrate(init, inc)
    assert horizontal_error_m(by_rate.lat, by_rate.lon, by_inc.lat, by_inc.lon).max() < 1e-6
    np.testing.assert_allclose(by_rate.v_n, by_inc.v_n, atol=1e-9)
    assert _att_err(by_rate.q_nb, by_inc.q_nb).max() < 1e-12


def _coning_imu(alpha: float, omega: float, rate_hz: float, duration: float, lat: float):
    """Classic coning at rest: q_nb(t) = exp(phi(t)), phi = alpha [0, cos wt, sin wt]. Body rate relative to NED
    (Savage 1998 Part 1 sec. on coning): w_nb_b = w [-(1 - cos a), -sin a sin wt, sin a cos wt], integrated
    analytically; the Earth rate C_bn(t) w_ie_n and specific force C_bn(t) (-g_n) by 8-point Gauss-Legendre."""
    t = np.arange(int(duration * rate_hz) + 1) / rate_hz

    def q_true(tt):
        tt = np.asarray(tt, dtype=float)
        return Rotation.from_rotvec(alpha * np.stack([0 * tt, np.cos(omega * tt), np.sin(omega * tt)], -1))

    dth = np.empty((len(t), 3))
    dth[:, 0] = -omega * (1 - np.cos(alpha)) / rate_hz
    t_prev = t - 1.0 / rate_hz
    dth[:, 1] = np.sin(alpha) * (np.cos(omega * t) - np.cos(omega * t_prev))
    dth[:, 2] = np.sin(alpha) * (np.sin(omega * t) - np.sin(omega * t_prev))
    x, w = np.polynomial.legendre.leggauss(8)
    w_ie = earth.omega_ie_n(lat)
    f_n = -earth.gravity_n(lat, 0.0)
    dv = np.zeros((len(t), 3))
    for xi, wi in zip(x, w, strict=True):
        tq = t_prev + 0.5 * (xi + 1.0) / rate_hz
        C_bn = q_true(tq).inv()
        dth += 0.5 * wi / rate_hz * C_bn.apply(w_ie)
        dv += 0.5 * wi / rate_hz * C_bn.apply(f_n)
    return t, dth, dv, q_true


def test_coning_body_rate_formula():
    """The analytic body rate used by the coning test matches a finite difference of the analytic attitude."""
    alpha, omega, tt, e = 0.05, 2 * np.pi * 5, 0.0123, 1e-6
    r = Rotation.from_rotvec(alpha * np.array([0, np.cos(omega * tt), np.sin(omega * tt)]))
    r2 = Rotation.from_rotvec(alpha * np.array([0, np.cos(omega * (tt + e)), np.sin(omega * (tt + e))]))
    r1 = Rotation.from_rotvec(alpha * np.array([0, np.cos(omega * (tt - e)), np.sin(omega * (tt - e))]))
    w_fd = ((r.inv() * r2).as_rotvec() - (r.inv() * r1).as_rotvec()) / (2 * e)
    w = omega * np.array(
        [-(1 - np.cos(alpha)), -np.sin(alpha) * np.sin(omega * tt), np.sin(alpha) * np.cos(omega * tt)]
    )
    np.testing.assert_allclose(w_fd, w, atol=1e-6)


def test_coning_correction_tracks_coning_motion():
    lat = np.deg2rad(30.0)
    t, dth, dv, q_true = _coning_imu(alpha=0.05, omega=2 * np.pi * 1.0, rate_hz=100.0, duration=60.0, lat=lat)
    init = NavState(0.0, lat, 0.0, 0.0, np.zeros(3), q_true(0.0).as_quat())
    imu = ImuIncrements(t, dth, dv)
    with_cs = integrate(init, imu, altitude_hold=0.0)
    without = integrate(init, imu, coning_sculling=False, altitude_hold=0.0)
    err_with = _att_err(with_cs.q_nb, q_true(t).as_quat())[-1]
    err_without = _att_err(without.q_nb, q_true(t).as_quat())[-1]
    # measured: 3.1e-4 rad without, 2.4e-7 rad with (the two-sample residual grows as (omega dt)^4)
    assert err_without > 1e-4
    assert err_with < 1e-6
    assert err_with < err_without / 300
    # sculling: the velocity stays near zero with the corrections (9e-5 m/s), not without (0.09 m/s)
    assert np.abs(with_cs.v_n).max() < 1e-3 < np.abs(without.v_n).max() / 10


def test_stepper_reset_and_bad_input():
    lat = np.deg2rad(10.0)
    q = q_nb_from_euler(0.0, 0.0, 0.5)
    init = NavState(5.0, lat, 0.1, 100.0, np.array([1.0, 2.0, 0.0]), q)
    st = StrapdownStepper(init, altitude_hold=100.0)
    g = np.zeros(3)
    f = C_nb_from_q(q).T @ -earth.gravity_n(lat, 100.0)
    st.step_rate(5.1, g, f)
    assert st.t == 5.1 and st.nav.h == 100.0 and st.nav.v_n[2] == 0.0
    with pytest.raises(InputError, match="time must increase"):
        st.step_rate(5.1, g, f)
    with pytest.raises(InputError, match="finite"):
        st.step_rate(5.2, np.array([np.nan, 0.0, 0.0]), f)
    moved = NavState(6.0, lat + 1e-5, 0.1, 100.0, np.zeros(3), q)
    st.reset(moved)
    assert st.nav.lat == moved.lat and st.t == 6.0
    with pytest.raises(InputError, match="init.t"):
        integrate(init, ImuBatch(np.array([0.0, 1.0]), np.zeros((2, 3)), np.zeros((2, 3))))
    with pytest.raises(InputError, match="increase"):
        integrate(init, ImuBatch(np.array([5.0, 5.0]), np.zeros((2, 3)), np.zeros((2, 3))))
