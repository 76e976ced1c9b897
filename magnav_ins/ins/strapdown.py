"""Strapdown inertial navigation: the NED mechanisation on WGS-84, one compiled algorithm in two forms.

The algorithm (Savage, "Strapdown inertial navigation integration algorithm design", Part 1: attitude, Part 2:
velocity and position, JGCD 21(1-2), 1998 -- the form pyins also follows; Groves 2013, *Principles of GNSS,
Inertial, and Multisensor Integrated Navigation Systems*, 2nd ed., sec. 5.4 (NED equations) and 5.5 (precision
forms)) advances the state ``(lat, lon, h, v_n, q_nb)`` over one IMU interval ``(t[k-1], t[k]]`` from the angle
increment ``dtheta_b`` (rad) and the velocity increment ``dv_b`` (m/s) of that interval, body FRD, together with
the increments of the interval before:

1. Attitude (Savage Part 1, two-sample coning for a linearly varying rate): body rotation vector
   ``phi = dtheta_k + (dtheta_{k-1} x dtheta_k) / 12``; navigation-frame rotation ``zeta = omega_in_n dt`` with
   ``omega_in_n = omega_ie_n + omega_en_n`` (Earth rate and transport rate, Groves eq. 5.44) at mid-interval;
   ``q_nb(k) = q(-zeta) * q_nb(k-1) * q(phi)`` with exact rotation-vector quaternions (Groves sec. 5.5.1).
2. Specific-force velocity increment (Savage Part 2; Groves sec. 5.5.2):
   ``dv_rot = dv_k + (dtheta_k x dv_k) / 2`` (rotation compensation) ``+ (dtheta_{k-1} x dv_k + dv_{k-1} x
   dtheta_k) / 12`` (two-sample sculling), then ``dv_sf_n = (I - [zeta x] / 2) C_nb(k-1) dv_rot``.
3. Velocity: ``v_n(k) = v_n(k-1) + dv_sf_n + (g_n - (2 omega_ie_n + omega_en_n) x v_n) dt`` (Coriolis and
   transport terms of Groves eq. 5.54) with normal gravity :func:`gravity_ned` (the formula of
   :func:`magnav_ins.ins.earth.gravity_n`), both at mid-interval position and velocity (extrapolated from the start
   of the interval: second-order accurate, self-starting).
4. Position on the ellipsoid, trapezoidal (Groves sec. 5.4.4): ``h -= dt (v_D(k-1) + v_D(k)) / 2``;
   ``lat += dt (v_N(k-1) + v_N(k)) / 2 / (R_N + h)``; ``lon += dt (v_E(k-1) + v_E(k)) / 2 / ((R_E + h) cos lat)``,
   radii of curvature (Groves eq. 2.105-2.106) at the mid-interval latitude and height. Longitude is not wrapped.
   Like every latitude/longitude mechanisation it is singular at the poles (``1 / cos lat``, ``tan lat``).

Rate-type IMUs (:class:`~magnav_ins.core.types.ImuBatch`, sample k = *mean* rate over ``(t[k-1], t[k]]``) are
turned into increments ``dtheta = gyro dt``, ``dv = accel dt``; increment-type IMUs
(:class:`~magnav_ins.core.types.ImuIncrements`) are used as they are. Both then run the same step. Samples that
are instantaneous rates (MEMS autopilot IMUs, pyins ``sensor_type="rate"``) are turned into interval means first
(:data:`SAMPLE_TYPES`, :func:`interval_means`, :class:`SampleMeans`).

Forms:

* streaming: :class:`StrapdownStepper` (one sample per call, a few microseconds; for fusers and the MAVLink bridge);
* batch: :func:`integrate` (one run, returns a :class:`~magnav_ins.core.types.NavTrajectory`) and
  :func:`integrate_batch` (many runs in parallel, optionally decimated, returns a :class:`NavTrajectoryBatch`).

The vertical channel is free (unaided) and therefore unstable: a height error grows roughly as
``exp(t sqrt(2 g / R))`` (time constant about 9.5 min), so over hours the free height is meaningless and, through
the radii and the Coriolis term, it eventually corrupts the horizontal solution. Pass ``altitude_hold=H`` (metres,
ellipsoidal) to every form to clamp ``h = H`` and ``v_D = 0`` after each step (a perfect external height aid, as
for a ship or a barometer-held aircraft); ``None`` leaves the channel free.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np
from numba import njit, prange

from ..core.errors import InputError
from ..core.frames import WGS84_A, WGS84_E2, WGS84_F, WGS84_GAMMA_E, WGS84_K, WGS84_M, WGS84_OMEGA_E
from ..core.types import SAMPLE_TYPES, FloatArray, ImuBatch, ImuIncrements, NavState, NavTrajectory

__all__ = [
    "SAMPLE_TYPES",
    "AttitudeSums",
    "NavTrajectoryBatch",
    "SampleMeans",
    "StrapdownStepper",
    "gravity_ned",
    "integrate",
    "integrate_batch",
    "interval_means",
]

# Layout of the flat state vector used by the kernels: lat, lon, h, v_n (3), q_nb (4, scalar-last).
_LAT, _LON, _H, _V, _Q = 0, 1, 2, 3, 6
_NX = 10
# Layout of the "previous increment" vector: dtheta_b (3), dv_b (3), valid flag.
_NP = 7
# Stepper work vector: t, state (10), previous increment (7).
_NS = 1 + _NX + _NP

_A = WGS84_A
_E2 = WGS84_E2
_F = WGS84_F
_M = WGS84_M
_K = WGS84_K
_GE = WGS84_GAMMA_E
_W = WGS84_OMEGA_E
_NORTH_DEFLECTION = 8.08e-9  # s^-2: north component of normal gravity per metre of height per sin(2 lat)


@njit(cache=True, fastmath=False)
def gravity_ned(lat: float, h: float) -> tuple[float, float]:
    """Normal gravity (gravitation + centrifugal) in NED at geodetic ``lat`` (rad), ellipsoidal ``h`` (m):
    returns ``(g_north, g_down)`` m/s^2 (the east component is zero).

    Same formula as :func:`magnav_ins.ins.earth.gravity_n` (Somigliana, Groves eq. 2.134, with the second-order
    height expansion of Groves eq. 2.139-2.140 / NIMA TR8350.2 eq. 4-3), compiled for the mechanisation; the tests
    hold the two equal to 1e-12 m/s^2.
    """
    s = math.sin(lat)
    s2 = s * s
    g0 = _GE * (1.0 + _K * s2) / math.sqrt(1.0 - _E2 * s2)
    g_d = g0 * (1.0 - 2.0 / _A * (1.0 + _F + _M - 2.0 * _F * s2) * h + 3.0 * h * h / (_A * _A))
    g_n = -_NORTH_DEFLECTION * h * math.sin(2.0 * lat)
    return g_n, g_d


@njit(cache=True)
def _rotvec_quat(x: float, y: float, z: float) -> tuple[float, float, float, float]:
    """Scalar-last quaternion of the rotation vector (x, y, z) rad (exact; Taylor series below 1e-4 rad)."""
    n2 = x * x + y * y + z * z
    if n2 < 1e-8:
        k = 0.5 - n2 / 48.0
        c = 1.0 - n2 / 8.0 + n2 * n2 / 384.0
    else:
        n = math.sqrt(n2)
        k = math.sin(0.5 * n) / n
        c = math.cos(0.5 * n)
    return k * x, k * y, k * z, c


@njit(cache=True)
def _qmul(
    ax: float, ay: float, az: float, aw: float, bx: float, by: float, bz: float, bw: float
) -> tuple[float, float, float, float]:
    """Hamilton product ``a * b`` of scalar-last quaternions (``R(a b) = R(a) R(b)``)."""
    return (
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
        aw * bw - ax * bx - ay * by - az * bz,
    )


@njit(cache=True)
def _step(
    x: FloatArray,
    prev: FloatArray,
    dt: float,
    tx: float,
    ty: float,
    tz: float,
    vx: float,
    vy: float,
    vz: float,
    coning_sculling: bool,
    h_hold: float,
) -> None:
    """Advance the state ``x`` (layout ``_LAT.._Q``) in place over one interval of length ``dt`` (s) with the
    angle increment ``(tx, ty, tz)`` rad and velocity increment ``(vx, vy, vz)`` m/s (body FRD). ``prev`` holds
    the previous interval's increments (and a validity flag) and is updated to this interval's. ``h_hold`` NaN
    leaves the vertical channel free; otherwise ``h = h_hold``, ``v_D = 0`` after the step."""
    lat = x[_LAT]
    h = x[_H]
    vn = x[_V]
    ve = x[_V + 1]
    vd = x[_V + 2]

    # --- two-sample coning and sculling (Savage 1998 Part 1 and Part 2) ------------------------------------------
    px, py, pz = tx, ty, tz
    rx = vx + 0.5 * (ty * vz - tz * vy)
    ry = vy + 0.5 * (tz * vx - tx * vz)
    rz = vz + 0.5 * (tx * vy - ty * vx)
    if coning_sculling and prev[6] > 0.0:
        ax, ay, az = prev[0], prev[1], prev[2]
        bx, by, bz = prev[3], prev[4], prev[5]
        px += (ay * tz - az * ty) / 12.0
        py += (az * tx - ax * tz) / 12.0
        pz += (ax * ty - ay * tx) / 12.0
        rx += ((ay * vz - az * vy) + (by * tz - bz * ty)) / 12.0
        ry += ((az * vx - ax * vz) + (bz * tx - bx * tz)) / 12.0
        rz += ((ax * vy - ay * vx) + (bx * ty - by * tx)) / 12.0
    prev[0] = tx
    prev[1] = ty
    prev[2] = tz
    prev[3] = vx
    prev[4] = vy
    prev[5] = vz
    prev[6] = 1.0

    # --- mid-interval position by extrapolation ---------------------------------------------------------------
    s = math.sin(lat)
    den = 1.0 - _E2 * s * s
    r_e0 = _A / math.sqrt(den)
    r_n0 = r_e0 * (1.0 - _E2) / den
    lat_m = lat + 0.5 * dt * vn / (r_n0 + h)
    h_m = h - 0.5 * dt * vd
    s = math.sin(lat_m)
    c = math.cos(lat_m)
    den = 1.0 - _E2 * s * s
    r_e = _A / math.sqrt(den)
    r_n = r_e * (1.0 - _E2) / den
    rn_h = r_n + h_m
    re_h = r_e + h_m
    wie_n = _W * c
    wie_d = -_W * s

    # --- specific-force increment in NED (Savage 1998 Part 2) -----------------------------------------------
    q0, q1, q2, q3 = x[_Q], x[_Q + 1], x[_Q + 2], x[_Q + 3]  # x, y, z, w
    c00 = 1.0 - 2.0 * (q1 * q1 + q2 * q2)
    c01 = 2.0 * (q0 * q1 - q2 * q3)
    c02 = 2.0 * (q0 * q2 + q1 * q3)
    c10 = 2.0 * (q0 * q1 + q2 * q3)
    c11 = 1.0 - 2.0 * (q0 * q0 + q2 * q2)
    c12 = 2.0 * (q1 * q2 - q0 * q3)
    c20 = 2.0 * (q0 * q2 - q1 * q3)
    c21 = 2.0 * (q1 * q2 + q0 * q3)
    c22 = 1.0 - 2.0 * (q0 * q0 + q1 * q1)
    fn = c00 * rx + c01 * ry + c02 * rz
    fe = c10 * rx + c11 * ry + c12 * rz
    fd = c20 * rx + c21 * ry + c22 * rz
    # navigation-frame rotation over the interval with the start velocity (used only in this small term)
    zn = (wie_n + ve / re_h) * dt
    ze = (-vn / rn_h) * dt
    zd = (wie_d - ve * s / (c * re_h)) * dt
    dvn = fn - 0.5 * (ze * fd - zd * fe)
    dve = fe - 0.5 * (zd * fn - zn * fd)
    dvd = fd - 0.5 * (zn * fe - ze * fn)

    # --- gravity and Coriolis at mid-interval (Groves eq. 5.54) ----------------------------------------------
    g_n, g_d = gravity_ned(lat_m, h_m)
    vmn = vn + 0.5 * (dvn + g_n * dt)
    vme = ve + 0.5 * dve
    vmd = vd + 0.5 * (dvd + g_d * dt)
    wen_n = vme / re_h
    wen_e = -vmn / rn_h
    wen_d = -vme * s / (c * re_h)
    wn = 2.0 * wie_n + wen_n
    we = wen_e
    wd = 2.0 * wie_d + wen_d
    vn1 = vn + dvn + (g_n - (we * vmd - wd * vme)) * dt
    ve1 = ve + dve + (-(wd * vmn - wn * vmd)) * dt
    vd1 = vd + dvd + (g_d - (wn * vme - we * vmn)) * dt

    # --- position, trapezoidal (Groves sec. 5.4.4) -----------------------------------------------------------
    van = 0.5 * (vn + vn1)
    vae = 0.5 * (ve + ve1)
    vad = 0.5 * (vd + vd1)
    h1 = h - vad * dt
    lat1 = lat + van * dt / rn_h
    lon1 = x[_LON] + vae * dt / (re_h * c)

    # --- attitude: q_nb(k) = q(-zeta) q_nb(k-1) q(phi) (Savage 1998 Part 1) ----------------------------------
    zn = -(wie_n + vae / re_h) * dt
    ze = (van / rn_h) * dt
    zd = -(wie_d - vae * s / (c * re_h)) * dt
    bx, by, bz, bw = _rotvec_quat(px, py, pz)
    nx, ny, nz, nw = _rotvec_quat(zn, ze, zd)
    tx_, ty_, tz_, tw_ = _qmul(q0, q1, q2, q3, bx, by, bz, bw)
    ox, oy, oz, ow = _qmul(nx, ny, nz, nw, tx_, ty_, tz_, tw_)
    norm = math.sqrt(ox * ox + oy * oy + oz * oz + ow * ow)
    if ow < 0.0:
        norm = -norm  # keep the scalar part non-negative (a unique sign for output and comparison)

    x[_LAT] = lat1
    x[_LON] = lon1
    x[_V] = vn1
    x[_V + 1] = ve1
    if math.isnan(h_hold):
        x[_H] = h1
        x[_V + 2] = vd1
    else:
        x[_H] = h_hold
        x[_V + 2] = 0.0
    x[_Q] = ox / norm
    x[_Q + 1] = oy / norm
    x[_Q + 2] = oz / norm
    x[_Q + 3] = ow / norm


@njit(cache=True)
def _run(
    t: FloatArray,
    dtheta: FloatArray,
    dv: FloatArray,
    is_rate: bool,
    x: FloatArray,
    prev: FloatArray,
    coning_sculling: bool,
    h_hold: float,
    decimate: int,
    out: FloatArray,
    row0: int,
    k0: int,
) -> int:
    """Integrate samples ``k0..N-1`` (sample k covers ``(t[k-1], t[k]]``; ``t[k0-1]`` must exist), writing the
    state after every ``decimate``-th sample (``k % decimate == 0``) into ``out[row]`` from ``row0``. ``x`` and
    ``prev`` are updated in place. Returns the next free row."""
    row = row0
    n = t.shape[0]
    for k in range(k0, n):
        dt = t[k] - t[k - 1]
        if is_rate:
            _step(
                x,
                prev,
                dt,
                dtheta[k, 0] * dt,
                dtheta[k, 1] * dt,
                dtheta[k, 2] * dt,
                dv[k, 0] * dt,
                dv[k, 1] * dt,
                dv[k, 2] * dt,
                coning_sculling,
                h_hold,
            )
        else:
            _step(
                x,
                prev,
                dt,
                dtheta[k, 0],
                dtheta[k, 1],
                dtheta[k, 2],
                dv[k, 0],
                dv[k, 1],
                dv[k, 2],
                coning_sculling,
                h_hold,
            )
        if k % decimate == 0:
            for i in range(_NX):
                out[row, i] = x[i]
            row += 1
    return row


@njit(cache=True)
def _seed_prev(t: FloatArray, dtheta: FloatArray, dv: FloatArray, is_rate: bool, prev: FloatArray) -> None:
    """Use sample 0 (the interval ending at ``t[0]``) as the "previous increment" of the first step. Rates are
    turned into increments with the first interval ``t[1] - t[0]`` (the length of interval 0 is unknown)."""
    scale = (t[1] - t[0]) if is_rate else 1.0
    for i in range(3):
        prev[i] = dtheta[0, i] * scale
        prev[3 + i] = dv[0, i] * scale
    prev[6] = 1.0


@njit(cache=True)
def _integrate_one(
    t: FloatArray,
    dtheta: FloatArray,
    dv: FloatArray,
    is_rate: bool,
    x0: FloatArray,
    coning_sculling: bool,
    h_hold: float,
    decimate: int,
) -> FloatArray:
    n = t.shape[0]
    m = (n + decimate - 1) // decimate
    out = np.empty((m, _NX))
    x = x0.copy()
    prev = np.zeros(_NP)
    out[0, :] = x
    if n > 1:
        _seed_prev(t, dtheta, dv, is_rate, prev)
        _run(t, dtheta, dv, is_rate, x, prev, coning_sculling, h_hold, decimate, out, 1, 1)
    return out


@njit(cache=True, parallel=True)
def _integrate_many(
    t: FloatArray,
    gyro: FloatArray,
    accel: FloatArray,
    x0: FloatArray,
    coning_sculling: bool,
    h_hold: float,
    decimate: int,
) -> FloatArray:
    r_runs = gyro.shape[0]
    n = t.shape[0]
    m = (n + decimate - 1) // decimate
    out = np.empty((r_runs, m, _NX))
    for r in prange(r_runs):
        x = x0[r].copy()
        prev = np.zeros(_NP)
        for i in range(_NX):
            out[r, 0, i] = x[i]
        if n > 1:
            _seed_prev(t, gyro[r], accel[r], True, prev)
            _run(t, gyro[r], accel[r], True, x, prev, coning_sculling, h_hold, decimate, out[r], 1, 1)
    return out


@njit(cache=True)
def _stepper_step(
    s: FloatArray,
    t: float,
    a: FloatArray,
    b: FloatArray,
    is_rate: bool,
    coning_sculling: bool,
    h_hold: float,
) -> bool:
    """One streaming step on the work vector ``s`` = (t, state, prev). Returns False (and changes nothing) if
    ``t`` does not advance or a sample is not finite."""
    dt = t - s[0]
    if not (dt > 0.0):
        return False
    for i in range(3):
        if not (math.isfinite(a[i]) and math.isfinite(b[i])):
            return False
    k = dt if is_rate else 1.0
    _step(
        s[1 : 1 + _NX],
        s[1 + _NX :],
        dt,
        a[0] * k,
        a[1] * k,
        a[2] * k,
        b[0] * k,
        b[1] * k,
        b[2] * k,
        coning_sculling,
        h_hold,
    )
    s[0] = t
    return True


@njit(cache=True)
def _dcm_into(q: FloatArray, C: FloatArray) -> None:
    """``C_nb`` of the unit scalar-last quaternion ``q`` written into ``C`` (3,3) (the formula of
    :func:`magnav_ins.aiding.fusion.common._dcm`)."""
    x, y, z, w = q[0], q[1], q[2], q[3]
    C[0, 0] = 1.0 - 2.0 * (y * y + z * z)
    C[0, 1] = 2.0 * (x * y - z * w)
    C[0, 2] = 2.0 * (x * z + y * w)
    C[1, 0] = 2.0 * (x * y + z * w)
    C[1, 1] = 1.0 - 2.0 * (x * x + z * z)
    C[1, 2] = 2.0 * (y * z - x * w)
    C[2, 0] = 2.0 * (x * z - y * w)
    C[2, 1] = 2.0 * (y * z + x * w)
    C[2, 2] = 1.0 - 2.0 * (x * x + y * y)


@njit(cache=True)
def _stepper_run_sums(
    s: FloatArray,
    t: FloatArray,
    w: FloatArray,
    f: FloatArray,
    coning_sculling: bool,
    holds: FloatArray,
    C_sum: FloatArray,
    fn_sum: FloatArray,
    Cf_sum: FloatArray,
    Cw_sum: FloatArray,
    C_prev: FloatArray,
    acc: FloatArray,
    t_cov: float,
    cov_step_s: float,
    scale_sums: bool,
    q_out: FloatArray,
) -> int:
    """Rate samples ``t`` (m,) s, ``w`` rad/s, ``f`` m/s^2 (m,3) (already bias-corrected) through the stepper
    work vector ``s``, sample ``k`` with the altitude hold ``holds[k]`` (NaN: free), accumulating the attitude
    integrals of one covariance step (:class:`AttitudeSums`: trapezoid of ``C_nb`` over each sample); the attitude
    after each sample goes to ``q_out[k]``. Stops after the sample that ends a covariance step
    (``t - t_cov >= cov_step_s - 1e-9``) and returns the number of samples done; ``-(k + 1)`` when sample ``k``
    does not advance the time (nothing done from it on)."""
    C0 = np.empty((3, 3))
    C1 = np.empty((3, 3))
    x = s[1 : 1 + _NX]
    prev = s[1 + _NX :]
    m = t.shape[0]
    for k in range(m):
        dt = t[k] - s[0]
        if not (dt > 0.0):
            return -(k + 1)
        if acc[1] > 0.0:
            C0[:, :] = C_prev
        else:
            _dcm_into(x[_Q : _Q + 4], C0)
        _step(x, prev, dt, w[k, 0] * dt, w[k, 1] * dt, w[k, 2] * dt, f[k, 0] * dt, f[k, 1] * dt, f[k, 2] * dt,
              coning_sculling, holds[k])  # fmt: skip
        s[0] = t[k]
        _dcm_into(x[_Q : _Q + 4], C1)
        for i in range(4):
            q_out[k, i] = x[_Q + i]
        f0, f1, f2 = f[k, 0], f[k, 1], f[k, 2]
        for i in range(3):
            for j in range(3):
                C_mid = 0.5 * (C0[i, j] + C1[i, j])
                C_sum[i, j] += C_mid * dt
                if scale_sums:
                    Cf_sum[i, j] += C_mid * f[k, j] * dt
                    Cw_sum[i, j] += C_mid * w[k, j] * dt
            fn_sum[i] += (0.5 * (C0[i, 0] + C1[i, 0]) * f0 + 0.5 * (C0[i, 1] + C1[i, 1]) * f1
                          + 0.5 * (C0[i, 2] + C1[i, 2]) * f2) * dt  # fmt: skip
        C_prev[:, :] = C1
        acc[0] += dt
        acc[1] = 1.0
        if t[k] - t_cov >= cov_step_s - 1e-9:
            return k + 1
    return m


class AttitudeSums:
    """The attitude integrals of one covariance step, accumulated sample by sample by
    :meth:`StrapdownStepper.run_with_sums`: ``C_sum`` = int C_nb dt, ``fn_sum`` = int C_nb f_b dt, ``Cf_sum`` =
    int C_nb diag(f_b) dt, ``Cw_sum`` = int C_nb diag(omega_ib_b) dt (the last two only when asked for), over
    ``dt_sum`` s; ``C_prev`` the attitude at the last sample (the next sample's start; unset after :meth:`clear`,
    when the next sample reads the INS attitude, which a correction may have changed)."""

    __slots__ = ("C_sum", "fn_sum", "Cf_sum", "Cw_sum", "C_prev", "_acc")

    def __init__(self) -> None:
        self.C_sum = np.zeros((3, 3))
        self.fn_sum = np.zeros(3)
        self.Cf_sum = np.zeros((3, 3))
        self.Cw_sum = np.zeros((3, 3))
        self.C_prev = np.zeros((3, 3))
        self._acc = np.zeros(2)  # dt_sum, C_prev valid

    def clear(self) -> None:
        """Start a new covariance step."""
        for a in (self.C_sum, self.fn_sum, self.Cf_sum, self.Cw_sum, self._acc):
            a.fill(0.0)

    @property
    def dt_sum(self) -> float:
        """Length of the step so far, s."""
        return float(self._acc[0])


def _state_vector(nav: NavState) -> FloatArray:
    x = np.empty(_NX)
    x[_LAT], x[_LON], x[_H] = nav.lat, nav.lon, nav.h
    x[_V : _V + 3] = nav.v_n
    q = np.asarray(nav.q_nb, dtype=float)
    x[_Q : _Q + 4] = q if q[3] >= 0.0 else -q
    return x


def _hold(altitude_hold: float | None) -> float:
    return math.nan if altitude_hold is None else float(altitude_hold)


class StrapdownStepper:
    """Streaming mechanisation: one IMU sample per call (same algorithm and numbers as :func:`integrate`).

    ``step_rate(t, gyro_b, accel_b)`` takes the mean rates over ``(t_prev, t]`` (rad/s, m/s^2 specific force, body
    FRD); ``step_increment(t, dtheta_b, dv_b)`` the increments over the same interval (rad, m/s). ``t`` (s) must
    increase; the first call integrates from ``init.t``. Coning/sculling use the previous call's increments (none
    before the first call, so the first step is single-sample); :meth:`reset` replaces the navigation state (a
    fuser's feedback correction) and keeps that memory. Pass float64 numpy arrays of shape (3,) for the few-µs
    path. ``altitude_hold`` (m) clamps the vertical channel (module docstring).
    """

    __slots__ = ("_s", "_cs", "_hold")

    def __init__(self, init: NavState, *, coning_sculling: bool = True, altitude_hold: float | None = None) -> None:
        self._s = np.zeros(_NS)
        self._cs = bool(coning_sculling)
        self._hold = _hold(altitude_hold)
        self._set(init)

    def _set(self, nav: NavState) -> None:
        self._s[0] = nav.t
        self._s[1 : 1 + _NX] = _state_vector(nav)
        if not math.isnan(self._hold):
            self._s[1 + _H] = self._hold
            self._s[1 + _V + 2] = 0.0

    def _step(self, t: float, a: FloatArray, b: FloatArray, is_rate: bool) -> None:
        if not _stepper_step(self._s, t, a, b, is_rate, self._cs, self._hold):
            raise InputError(
                f"strapdown step at t={t!r}: time must increase (last t={self._s[0]!r}) and samples must be "
                f"finite, got {np.asarray(a).tolist()}, {np.asarray(b).tolist()}"
            )

    def set_altitude_hold(self, h_m: float | None) -> None:
        """Clamp the vertical channel to ``h_m`` (m above the ellipsoid) from the next step on; None frees it."""
        self._hold = _hold(h_m)

    def step_rate(self, t: float, gyro_b: FloatArray, accel_b: FloatArray) -> None:
        """Advance to ``t`` (s) with mean rates ``gyro_b`` (rad/s) and specific force ``accel_b`` (m/s^2), FRD."""
        self._step(t, gyro_b, accel_b, True)

    def step_increment(self, t: float, dtheta_b: FloatArray, dv_b: FloatArray) -> None:
        """Advance to ``t`` (s) with angle increment ``dtheta_b`` (rad) and velocity increment ``dv_b`` (m/s)."""
        self._step(t, dtheta_b, dv_b, False)

    def run_with_sums(
        self,
        t: FloatArray,
        gyro_b: FloatArray,
        accel_b: FloatArray,
        sums: AttitudeSums,
        *,
        holds: FloatArray | None = None,
        t_cov: float = -math.inf,
        cov_step_s: float = math.inf,
        scale_sums: bool = False,
        q_out: FloatArray | None = None,
    ) -> int:
        """Step through rate samples ``t`` (m,) s, ``gyro_b`` rad/s, ``accel_b`` m/s^2 (m,3) in one compiled call
        (the same numbers as :meth:`step_rate` sample by sample) while adding each sample's attitude integrals to
        ``sums`` (a fuser's covariance step, :class:`AttitudeSums`). ``holds`` (m,): the altitude hold of each
        sample (m; NaN frees the vertical channel; default the current hold). Stops after the first sample with
        ``t - t_cov >= cov_step_s - 1e-9`` (the end of a covariance step) and returns how many samples it did.
        ``q_out`` (m,4): filled with the attitude after each sample. Samples must be finite (the caller checks);
        a time that does not advance raises :class:`InputError`."""
        m = len(t)
        if holds is None:
            holds = np.full(m, self._hold)
        if q_out is None:
            q_out = np.empty((m, 4))
        n = _stepper_run_sums(self._s, t, gyro_b, accel_b, self._cs, holds, sums.C_sum, sums.fn_sum, sums.Cf_sum,
                              sums.Cw_sum, sums.C_prev, sums._acc, float(t_cov), float(cov_step_s), bool(scale_sums),
                              q_out)  # fmt: skip
        if n < 0:
            k = -n - 1
            raise InputError(f"strapdown step at t={float(t[k])!r}: time must increase (last t={self._s[0]!r})")
        if n:
            self._hold = float(holds[n - 1])
        return n

    @property
    def t(self) -> float:
        """Time of the current state, s."""
        return float(self._s[0])

    @property
    def nav(self) -> NavState:
        """The current navigation state."""
        x = self._s[1 : 1 + _NX]
        return NavState(float(self._s[0]), float(x[_LAT]), float(x[_LON]), float(x[_H]), x[_V : _V + 3].copy(),
                        x[_Q : _Q + 4].copy())  # fmt: skip

    def reset(self, nav: NavState) -> None:
        """Replace the navigation state (e.g. after a filter correction); keeps the coning/sculling memory."""
        self._set(nav)

    def prime(self, dtheta_b: FloatArray, dv_b: FloatArray) -> None:
        """Set the coning/sculling memory to the increments (rad, m/s, FRD) of the interval *ending* at the current
        time, as :func:`integrate` does with sample 0, so that the first step is two-sample too."""
        self._s[1 + _NX : 1 + _NX + 3] = dtheta_b
        self._s[1 + _NX + 3 : 1 + _NX + 6] = dv_b
        self._s[1 + _NX + 6] = 1.0

    def advance(self, imu: ImuBatch | ImuIncrements) -> NavTrajectory:
        """Step through every sample of ``imu`` (the first covers ``(self.t, imu.t[0]]``) in one compiled call and
        return the states at ``imu.t`` (same numbers as repeated :meth:`step_rate` / :meth:`step_increment`).
        For chunked processing of long recordings."""
        t = np.asarray(imu.t, dtype=float)
        if len(t) == 0:
            return _trajectory(t, np.empty((0, _NX)))
        t_ext = np.concatenate(([self._s[0]], t))
        _check_time(t_ext, "StrapdownStepper.advance")
        if isinstance(imu, ImuBatch):
            a, b, is_rate = imu.gyro_b, imu.accel_b, True
        else:
            a, b, is_rate = imu.dtheta_b, imu.dv_b, False
        if not (np.isfinite(a).all() and np.isfinite(b).all()):
            raise InputError("StrapdownStepper.advance: IMU samples must be finite")
        a_ext = np.zeros((len(t_ext), 3))
        b_ext = np.zeros((len(t_ext), 3))
        a_ext[1:] = a
        b_ext[1:] = b
        out = np.empty((len(t), _NX))
        x = self._s[1 : 1 + _NX]
        prev = self._s[1 + _NX :]
        _run(t_ext, a_ext, b_ext, is_rate, x, prev, self._cs, self._hold, 1, out, 0, 1)
        self._s[0] = t[-1]
        return _trajectory(t, out)


def _trajectory(t: FloatArray, out: FloatArray) -> NavTrajectory:
    return NavTrajectory(
        t, out[:, _LAT].copy(), out[:, _LON].copy(), out[:, _H].copy(), out[:, _V : _V + 3].copy(), out[:, _Q:].copy()
    )


def _check_time(t: FloatArray, what: str) -> None:
    if t.ndim != 1 or len(t) < 1:
        raise InputError(f"{what}: t must be a non-empty 1-D array, got shape {t.shape}")
    bad = np.flatnonzero(~(np.diff(t) > 0.0))
    if len(bad):
        k = int(bad[0]) + 1
        raise InputError(f"{what}: t must increase strictly; t[{k}]={t[k]!r} after t[{k - 1}]={t[k - 1]!r}")


def integrate(
    init: NavState,
    imu: ImuBatch | ImuIncrements,
    *,
    coning_sculling: bool = True,
    altitude_hold: float | None = None,
) -> NavTrajectory:
    """Integrate a recorded IMU from ``init`` (batch form of :class:`StrapdownStepper`).

    Row ``k`` of the result is the state at ``imu.t[k]``; row 0 is ``init`` (``init.t`` must equal ``imu.t[0]``
    within 1 µs). Sample 0 describes the interval *ending* at ``t[0]``: it is not integrated, it only serves as the
    "previous increment" of the two-sample coning and sculling corrections of the first step (for rates it is
    scaled by ``t[1] - t[0]``). Samples must be finite and ``t`` strictly increasing (:class:`InputError`).
    """
    t = np.ascontiguousarray(imu.t, dtype=float)
    _check_time(t, "integrate")
    if abs(float(init.t) - float(t[0])) > 1e-6:
        raise InputError(f"integrate: init.t={init.t!r} s must equal the first IMU time t[0]={t[0]!r} s")
    if isinstance(imu, ImuBatch):
        a, b, is_rate = imu.gyro_b, imu.accel_b, True
    elif isinstance(imu, ImuIncrements):
        a, b, is_rate = imu.dtheta_b, imu.dv_b, False
    else:
        raise InputError(f"integrate: expected ImuBatch or ImuIncrements, got {type(imu).__name__}")
    a = np.ascontiguousarray(a, dtype=float)
    b = np.ascontiguousarray(b, dtype=float)
    if not (np.isfinite(a).all() and np.isfinite(b).all()):
        k = int(np.flatnonzero(~(np.isfinite(a).all(axis=1) & np.isfinite(b).all(axis=1)))[0])
        raise InputError(f"integrate: IMU sample {k} (t={t[k]!r}) is not finite")
    x0 = _state_vector(init)
    if altitude_hold is not None:
        x0[_H], x0[_V + 2] = float(altitude_hold), 0.0
    out = _integrate_one(t, a, b, is_rate, x0, bool(coning_sculling), _hold(altitude_hold), 1)
    return _trajectory(t, out)


@dataclass(frozen=True)
class NavTrajectoryBatch:
    """Navigation states of ``R`` runs on a common time axis: ``t`` (M,) s; ``lat``, ``lon`` (R, M) rad; ``h``
    (R, M) m ellipsoidal; ``v_n`` (R, M, 3) NED m/s; ``q_nb`` (R, M, 4) scalar-last body->NED."""

    t: FloatArray
    lat: FloatArray
    lon: FloatArray
    h: FloatArray
    v_n: FloatArray
    q_nb: FloatArray

    @property
    def runs(self) -> int:
        return int(self.lat.shape[0])

    def __len__(self) -> int:
        return len(self.t)

    def run(self, r: int) -> NavTrajectory:
        """Run ``r`` as a :class:`~magnav_ins.core.types.NavTrajectory`."""
        return NavTrajectory(self.t, self.lat[r], self.lon[r], self.h[r], self.v_n[r], self.q_nb[r])


def integrate_batch(
    t: FloatArray,
    gyro_b: FloatArray,
    accel_b: FloatArray,
    lat0: FloatArray,
    lon0: FloatArray,
    h0: FloatArray,
    v0_n: FloatArray,
    q0_nb: FloatArray,
    decimate: int = 1,
    *,
    coning_sculling: bool = True,
    altitude_hold: float | None = None,
) -> NavTrajectoryBatch:
    """Integrate ``R`` rate-type IMU runs sharing the time axis ``t`` (N,) s, in parallel (numba ``prange``).

    ``gyro_b`` (R, N, 3) rad/s and ``accel_b`` (R, N, 3) m/s^2 are mean rates over ``(t[k-1], t[k]]``, body FRD;
    initial states at ``t[0]``: ``lat0``, ``lon0`` (R,) rad, ``h0`` (R,) m, ``v0_n`` (R, 3) NED m/s, ``q0_nb``
    (R, 4) scalar-last. Keeps the states at ``t[::decimate]`` (M = ceil(N / decimate) rows, row 0 = initial
    state), so long Monte Carlo runs stay in memory. Sample 0 is used as in :func:`integrate`.
    """
    t = np.ascontiguousarray(t, dtype=float)
    _check_time(t, "integrate_batch")
    gyro_b = np.ascontiguousarray(gyro_b, dtype=float)
    accel_b = np.ascontiguousarray(accel_b, dtype=float)
    n = len(t)
    if gyro_b.ndim != 3 or gyro_b.shape[1:] != (n, 3) or accel_b.shape != gyro_b.shape:
        raise InputError(f"integrate_batch: gyro_b {gyro_b.shape} and accel_b {accel_b.shape} must both be (R, {n}, 3)")
    r_runs = gyro_b.shape[0]
    if not (np.isfinite(gyro_b).all() and np.isfinite(accel_b).all()):
        r, k = np.argwhere(~(np.isfinite(gyro_b).all(axis=2) & np.isfinite(accel_b).all(axis=2)))[0]
        raise InputError(f"integrate_batch: run {r} sample {k} (t={t[k]!r}) is not finite")
    if int(decimate) < 1:
        raise InputError(f"integrate_batch: decimate must be >= 1, got {decimate}")
    x0 = np.empty((r_runs, _NX))
    for name, arr, sl in (("lat0", lat0, _LAT), ("lon0", lon0, _LON), ("h0", h0, _H)):
        a = np.broadcast_to(np.asarray(arr, dtype=float), (r_runs,)) if np.ndim(arr) == 0 else np.asarray(arr, float)
        if a.shape != (r_runs,):
            raise InputError(f"integrate_batch: {name} must have shape ({r_runs},), got {a.shape}")
        x0[:, sl] = a
    v = np.asarray(v0_n, dtype=float)
    q = np.asarray(q0_nb, dtype=float)
    if v.shape != (r_runs, 3) or q.shape != (r_runs, 4):
        raise InputError(f"integrate_batch: v0_n {v.shape} must be ({r_runs}, 3) and q0_nb {q.shape} ({r_runs}, 4)")
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    q = np.where(q[:, 3:4] < 0.0, -q, q)
    x0[:, _V : _V + 3] = v
    x0[:, _Q : _Q + 4] = q
    if altitude_hold is not None:
        x0[:, _H], x0[:, _V + 2] = float(altitude_hold), 0.0
    out = _integrate_many(t, gyro_b, accel_b, x0, bool(coning_sculling), _hold(altitude_hold), int(decimate))
    return NavTrajectoryBatch(
        t[:: int(decimate)].copy(),
        out[:, :, _LAT].copy(),
        out[:, :, _LON].copy(),
        out[:, :, _H].copy(),
        out[:, :, _V : _V + 3].copy(),
        out[:, :, _Q:].copy(),
    )


def check_sample_type(sample_type: str) -> str:
    """``sample_type`` if it is one of :data:`SAMPLE_TYPES`, else :class:`InputError` naming the choices."""
    if sample_type not in SAMPLE_TYPES:
        raise InputError(f"sample type {sample_type!r}: expected one of {', '.join(SAMPLE_TYPES)}")
    return sample_type


def interval_means(
    t: FloatArray,
    a: FloatArray,
    b: FloatArray,
    sample_type: str,
    *,
    previous: tuple[float, FloatArray, FloatArray] | None = None,
) -> tuple[FloatArray, FloatArray]:
    """Mean rates over each interval ``(t[k-1], t[k]]`` from samples of ``sample_type`` (:data:`SAMPLE_TYPES`).

    ``t`` (N,) s; ``a``, ``b`` (N, 3): gyro and accelerometer samples (rad/s and m/s^2, or rad and m/s for
    increments), body FRD. ``instantaneous``: the rate is taken as linear between samples (the model of pyins's
    ``compute_increments_from_imu`` for ``"rate"`` and of Savage 1998's two-sample algorithms), so the interval
    mean is the trapezoid ``(x[k-1] + x[k]) / 2``; treating the sample itself as the mean lags the attitude and
    velocity by half a sample. ``increment``: ``x[k] / (t[k] - t[k-1])``. ``previous`` = ``(t, a, b)`` of the sample
    before ``t[0]`` (chunked or streamed input); without it sample 0 is its own mean (its interval is unknown; the
    mechanisation only uses it to seed the coning/sculling memory) and an increment sample 0 is divided by
    ``t[1] - t[0]``. Returns the (N, 3) means.
    """
    check_sample_type(sample_type)
    t = np.asarray(t, dtype=float)
    a = np.asarray(a, dtype=float).reshape(-1, 3)
    b = np.asarray(b, dtype=float).reshape(-1, 3)
    if sample_type == "mean" or len(t) == 0:
        return a, b
    if sample_type == "instantaneous":
        a0 = a[:1] if previous is None else np.asarray(previous[1], float).reshape(1, 3)
        b0 = b[:1] if previous is None else np.asarray(previous[2], float).reshape(1, 3)
        ap = np.concatenate([a0, a[:-1]])
        bp = np.concatenate([b0, b[:-1]])
        return 0.5 * (ap + a), 0.5 * (bp + b)
    if previous is not None:
        dt = np.diff(np.concatenate([[float(previous[0])], t]))
    elif len(t) > 1:
        dt = np.diff(t)
        dt = np.concatenate([dt[:1], dt])
    else:
        raise InputError("interval_means: one increment sample without the previous time has no interval")
    if np.any(~(dt > 0)):
        raise InputError("interval_means: increment times must increase strictly")
    return a / dt[:, None], b / dt[:, None]


class SampleMeans:
    """Streaming form of :func:`interval_means`: ``means(t, a, b)`` returns the mean rates over ``(t_prev, t]`` for
    one sample of ``sample_type``; :meth:`reset` forgets the previous sample (after a gap or a restart)."""

    __slots__ = ("sample_type", "_prev")

    def __init__(self, sample_type: str = "mean") -> None:
        self.sample_type = check_sample_type(sample_type)
        self._prev: tuple[float, FloatArray, FloatArray] | None = None

    def reset(self) -> None:
        self._prev = None

    def means(self, t: float, a: FloatArray, b: FloatArray) -> tuple[FloatArray, FloatArray]:
        a = np.asarray(a, dtype=float).reshape(3)
        b = np.asarray(b, dtype=float).reshape(3)
        prev, self._prev = self._prev, (float(t), a, b)
        if self.sample_type == "mean":
            return a, b
        if self.sample_type == "instantaneous":
            return (a, b) if prev is None else (0.5 * (prev[1] + a), 0.5 * (prev[2] + b))
        if prev is None or not t > prev[0]:
            raise InputError("SampleMeans: an increment needs the previous sample's time (strictly earlier)")
        dt = float(t) - prev[0]
        return a / dt, b / dt

    def means_batch(self, t: FloatArray, a: FloatArray, b: FloatArray) -> tuple[FloatArray, FloatArray]:
        """:meth:`means` of each of the samples ``t`` (m,), ``a``, ``b`` (m,3) in turn (the same numbers,
        vectorised; :func:`interval_means` with the previous sample)."""
        t = np.asarray(t, dtype=float)
        a = np.asarray(a, dtype=float).reshape(-1, 3)
        b = np.asarray(b, dtype=float).reshape(-1, 3)
        if len(t) == 0:
            return a, b
        prev = self._prev
        if self.sample_type == "increment" and prev is None:
            self.means(float(t[0]), a[0], b[0])  # raises: no interval for the first increment
        if self.sample_type == "instantaneous" and prev is None:
            prev = (float(t[0]), a[0], b[0])  # the first sample is its own mean
        out = interval_means(t, a, b, self.sample_type, previous=prev)
        self._prev = (float(t[-1]), a[-1].copy(), b[-1].copy())
        return out


def set_threads(n: int) -> None:  # pragma: no cover - thin convenience
    """Limit the numba threads used by :func:`integrate_batch` (the machine may be shared)."""
    numba.set_num_threads(int(n))
