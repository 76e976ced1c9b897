"""INS error-state model (15 states, :data:`magnav_ins.core.types.LAYOUT_15`) in the local navigation frame.

Error definitions (used by the fusers for feedback; every error is *estimate minus truth*)
-----------------------------------------------------------------------------------------
* ``pos`` (0:3) ``dp_n`` m, NED, curvilinear metres at the true position:
  ``dp_N = (R_N + h) (lat_est - lat)``, ``dp_E = (R_E + h) cos(lat) (lon_est - lon)``, ``dp_D = -(h_est - h)``.
* ``vel`` (3:6) ``dv_n = v_n_est - v_n`` m/s, NED.
* ``att`` (6:9) tilt ``psi`` rad, NED: ``C_nb_est = (I + [psi x]) C_nb_true`` to first order; exactly
  ``psi = rotvec(C_nb_est C_nb_true^T)`` (the ``delta C_b^n = I + [delta psi x]`` convention of Groves 2013 sec. 5.6.1 / 14.2). To correct an
  estimate: ``C_nb <- exp(-[psi x]) C_nb_est``, i.e. ``q_nb <- q(-psi) * q_nb_est``.
* ``b_a`` (9:12) ``db_a = b_a_est - b_a`` m/s^2 and ``b_g`` (12:15) ``db_g = b_g_est - b_g`` rad/s, body FRD, where
  the INS uses ``f = f_meas - b_a_est`` and ``omega = omega_meas - b_g_est``. Free inertial: ``b_est = 0``.

Dynamics (Groves 2013 sec. 14.2.4, eq. 14.63-14.71, written here for NED metres; derived from the mechanisation
in :mod:`magnav_ins.ins.strapdown`)::

    d(psi)/dt = -omega_in x psi - d(omega_in)/d(p, v) [dp; dv] - C_nb db_g + C_nb w_g
    d(dv)/dt  = -f_n x psi - C_nb db_a + C_nb w_a
                - (2 omega_ie + omega_en) x dv + v x (2 d omega_ie + d omega_en) + dg
    d(dp)/dt  = dv + (transport terms ~ v / R)
    d(db)/dt  = -db / tau + w_b

with ``omega_in = omega_ie + omega_en`` (Groves eq. 5.41, 5.44), ``f_n = C_nb f_b`` the specific force and the
vertical gravity gradient ``d g_D / d D = -d g_D / dh`` (about ``+2 g / R``, the unstable vertical channel).
Noise ``w = [w_a, w_g, w_ba, w_bg]`` with continuous PSD ``Qc = diag(VRW^2, ARW^2, 2 sigma_a^2 / tau_a,
2 sigma_g^2 / tau_g)`` (first-order Gauss-Markov driving noise; zero for random-constant biases).
Misalignment errors are not states of this model (they act through the motion only).

Optional states (:func:`augment_system`, layout ``LAYOUT_15.extended(s_a=3, s_g=3, b_map=2)``, any subset)
---------------------------------------------------------------------------------------------------------------
* ``s_a``, ``s_g``: accelerometer / gyro scale-factor errors ``ds = s_est - s`` (dimensionless, body FRD), with
  the sensor model of :mod:`ins.imu_models` ``f_meas = (I + diag(s_a)) f_b + b_a + w_a`` (gyro likewise) and
  the INS correction ``f = (f_meas - b_a_est) / (1 + s_a_est)``, so ``f - f_b = -db_a - diag(f_b) ds_a`` to first
  order (Groves 2013 eq. 14.64 with the scale-factor column of eq. 4.17)::

      d(dv)/dt  += -C_nb diag(f_b) ds_a          d(psi)/dt += -C_nb diag(omega_ib_b) ds_g
      d(ds)/dt   = -ds / tau_s + w_s             (random constant: tau_s = inf, w_s = 0)

* ``b_map``: the map-registration bias of the position fixes (north, east m): ``z = p_ne + b_map + v``; error
  ``db_map = b_map_est - b_map`` with ``d(db_map)/dt = -db_map / tau_m + w_m`` (first-order Gauss-Markov,
  PSD ``2 sigma_m^2 / tau_m``, Gelb 1974 Table 3.8-1). It does not enter the INS dynamics.
"""

from __future__ import annotations

import contextlib
import functools
import math
from collections.abc import Iterator

import numpy as np
from scipy.linalg import expm
from scipy.spatial.transform import Rotation

from ..core.errors import InputError
from ..core.frames import WGS84_A, WGS84_F, WGS84_M, WGS84_OMEGA_E, radii_of_curvature, skew, wrap_angle
from ..core.types import LAYOUT_15, FloatArray, ImuBatch, NavState, NavTrajectory, StateLayout
from .earth import gravity_n, omega_en_n, omega_ie_n, somigliana
from .imu_models import ImuGrade

N_STATES = LAYOUT_15.size
N_NOISE = 12
_P, _V, _A, _BA, _BG = (LAYOUT_15[k] for k in ("pos", "vel", "att", "b_a", "b_g"))


# --- error definitions ---------------------------------------------------------------------------------------
def _dcm(q: FloatArray) -> FloatArray:
    q = np.asarray(q, dtype=float)
    return Rotation.from_quat(q.reshape(-1, 4)).as_matrix().reshape(q.shape[:-1] + (3, 3))


def nav_error(est: NavState | NavTrajectory, truth: NavState | NavTrajectory) -> FloatArray:
    """The 9 navigation error states ``[dp_n (m), dv_n (m/s), psi (rad)]`` of ``est`` w.r.t. ``truth`` (module
    docstring). States give (9,), trajectories (or batches with leading dimensions) give (..., 9)."""
    lat, h = np.asarray(truth.lat, float), np.asarray(truth.h, float)
    r_n, r_e = radii_of_curvature(lat)
    dn = (r_n + h) * (np.asarray(est.lat) - lat)
    de = (r_e + h) * np.cos(lat) * wrap_angle(np.asarray(est.lon) - np.asarray(truth.lon))
    dd = -(np.asarray(est.h) - h)
    dv = np.asarray(est.v_n, float) - np.asarray(truth.v_n, float)
    C_est, C_true = _dcm(est.q_nb), _dcm(truth.q_nb)
    M = C_est @ np.swapaxes(C_true, -1, -2)
    psi = Rotation.from_matrix(M.reshape(-1, 3, 3)).as_rotvec().reshape(M.shape[:-1])
    dv = np.broadcast_to(dv, psi.shape)
    pos = np.stack(np.broadcast_arrays(dn, de, dd), axis=-1)
    return np.concatenate(np.broadcast_arrays(pos, dv, psi), axis=-1)


def apply_error(truth: NavState, dx: FloatArray) -> NavState:
    """The state whose error w.r.t. ``truth`` is ``dx`` = ``[dp_n, dv_n, psi]`` (9,) (inverse of :func:`nav_error`).

    To *correct* an estimate by an estimated error ``dx_hat``, use ``apply_error(est, -dx_hat)`` (exact to first
    order)."""
    dx = np.asarray(dx, dtype=float).reshape(-1)
    if dx.shape[0] < 9:
        raise InputError(f"apply_error: need 9 error states [dp, dv, psi], got {dx.shape[0]}")
    r_n, r_e = radii_of_curvature(truth.lat)
    lat = truth.lat + dx[0] / (r_n + truth.h)
    lon = truth.lon + dx[1] / ((r_e + truth.h) * math.cos(truth.lat))
    h = truth.h - dx[2]
    q = (Rotation.from_rotvec(dx[6:9]) * Rotation.from_quat(truth.q_nb)).as_quat()
    return NavState(truth.t, float(lat), float(wrap_angle(lon)), float(h), truth.v_n + dx[3:6], q)


# --- continuous-time model -----------------------------------------------------------------------------------
def _dgd_dh(lat: float, h: float) -> float:
    """Derivative of the down component of :func:`gravity_n` with respect to height, s^-2 (about -2 g / R)."""
    s2 = math.sin(lat) ** 2
    g0 = float(somigliana(lat))
    return g0 * (-2.0 / WGS84_A * (1.0 + WGS84_F + WGS84_M - 2.0 * WGS84_F * s2) + 6.0 * h / WGS84_A**2)


def system_matrices(
    lat: float, h: float, v_n: FloatArray, C_nb: FloatArray, f_b: FloatArray, grade: ImuGrade
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Continuous-time ``F`` (15,15), ``G`` (15,12) and noise PSD ``Qc`` (12,12) at one point of the trajectory.

    Inputs: ``lat`` rad, ``h`` m, ``v_n`` (3,) m/s NED, ``C_nb`` (3,3), ``f_b`` (3,) m/s^2 specific force body FRD,
    ``grade`` for bias correlation times and noise densities. Noise order ``[w_a, w_g, w_ba, w_bg]``.
    """
    v = np.asarray(v_n, dtype=float)
    C = np.asarray(C_nb, dtype=float)
    f_n = C @ np.asarray(f_b, dtype=float)
    r_n, r_e = radii_of_curvature(lat)
    rn, re = float(r_n) + h, float(r_e) + h
    sl, cl = math.sin(lat), math.cos(lat)
    tl = sl / cl
    vn, ve, vd = v
    w_ie = omega_ie_n(lat)
    w_en = omega_en_n(lat, h, v)
    w_in = w_ie + w_en

    # partial derivatives of the rates w.r.t. the error states (position in NED metres: dlat = dp_N / rn,
    # dh = -dp_D)
    dwie_dp = np.zeros((3, 3))
    dwie_dp[:, 0] = np.array([-WGS84_OMEGA_E * sl, 0.0, -WGS84_OMEGA_E * cl]) / rn
    dwen_dp = np.zeros((3, 3))
    dwen_dp[2, 0] = -ve / (cl * cl) / re / rn
    dwen_dp[:, 2] = np.array([ve / re**2, -vn / rn**2, -ve * tl / re**2])
    dwen_dv = np.array([[0.0, 1.0 / re, 0.0], [-1.0 / rn, 0.0, 0.0], [0.0, -tl / re, 0.0]])

    F = np.zeros((N_STATES, N_STATES))
    # position
    F[_P, _V] = np.eye(3)
    F[0, 0] = -vd / rn
    F[0, 2] = vn / rn
    F[1, 0] = ve * tl / rn
    F[1, 1] = -vd / re - vn * tl / rn
    F[1, 2] = ve / re
    # velocity
    W = 2.0 * w_ie + w_en
    F[_V, _P] = skew(v) @ (2.0 * dwie_dp + dwen_dp)
    F[5, 2] += -_dgd_dh(lat, h)  # d g_D / d(dp_D) = -d g_D / dh
    F[3, 2] += 8.08e-9 * math.sin(2.0 * lat)  # north gravity deflection term of gravity_n
    F[_V, _V] = -skew(W) + skew(v) @ dwen_dv
    F[_V, _A] = -skew(f_n)  # psi x f_n = -f_n x psi
    F[_V, _BA] = -C
    # attitude
    F[_A, _P] = -(dwie_dp + dwen_dp)
    F[_A, _V] = -dwen_dv
    F[_A, _A] = -skew(w_in)
    F[_A, _BG] = -C
    # biases
    F[_BA, _BA] = -np.eye(3) / grade.accel_bias_tau if math.isfinite(grade.accel_bias_tau) else 0.0
    F[_BG, _BG] = -np.eye(3) / grade.gyro_bias_tau if math.isfinite(grade.gyro_bias_tau) else 0.0

    G = np.zeros((N_STATES, N_NOISE))
    G[_V, 0:3] = C
    G[_A, 3:6] = C
    G[_BA, 6:9] = np.eye(3)
    G[_BG, 9:12] = np.eye(3)
    Qc = np.diag(np.concatenate([grade.arr("vrw") ** 2, grade.arr("arw") ** 2, bias_psd(grade, "accel"),
                                 bias_psd(grade, "gyro")]))  # fmt: skip
    return F, G, Qc


def bias_psd(grade: ImuGrade, sensor: str) -> FloatArray:
    """PSD (3,) of the Gauss-Markov bias driving noise ``2 sigma^2 / tau`` (Gelb 1974 Table 3.8-1); zero for
    random constants. ``sensor`` is ``"accel"`` or ``"gyro"``; units (m/s^2)^2/s or (rad/s)^2/s."""
    tau = getattr(grade, f"{sensor}_bias_tau")
    sig = grade.arr(f"{sensor}_bias_sigma")
    return 2.0 * sig**2 / tau if math.isfinite(tau) else np.zeros(3)


def augment_system(
    F: FloatArray,
    G: FloatArray,
    Qc: FloatArray,
    layout: StateLayout,
    *,
    C_diag_f: FloatArray | None = None,
    C_diag_w: FloatArray | None = None,
    accel_scale_sigma: float = 0.0,
    gyro_scale_sigma: float = 0.0,
    scale_tau: float = math.inf,
    map_sigma: float = 0.0,
    map_tau: float = math.inf,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """``F, G, Qc`` of :func:`system_matrices` (15 states, 12 noises) extended by the optional blocks of ``layout``
    (``s_a``, ``s_g``, ``b_map``; module docstring), one driving noise per added state (appended in layout order).

    ``C_diag_f`` = ``C_nb diag(f_b)`` (3,3) m/s^2 and ``C_diag_w`` = ``C_nb diag(omega_ib_b)`` (3,3) rad/s (or their
    averages over a step) are the scale-factor columns of the velocity and tilt rows; ``accel_scale_sigma``,
    ``gyro_scale_sigma`` (dimensionless) with ``scale_tau`` s give the Gauss-Markov PSD ``2 sigma^2 / tau`` (zero for
    random constants, ``scale_tau = inf``); ``map_sigma`` m, ``map_tau`` s likewise for ``b_map``."""
    n = layout.size
    n0, m0 = F.shape[0], G.shape[1]
    if n == n0:
        return F, G, Qc
    Fa = np.zeros((n, n))
    Fa[:n0, :n0] = F
    Ga = np.zeros((n, m0 + n - n0))
    Ga[:n0, :m0] = G
    Ga[n0:, m0:] = np.eye(n - n0)
    q = np.zeros(n - n0)

    def gm(sl: slice, sigma: float, tau: float) -> None:
        if math.isfinite(tau):
            Fa[sl, sl] = -np.eye(sl.stop - sl.start) / tau
            q[sl.start - n0 : sl.stop - n0] = 2.0 * sigma**2 / tau

    if "s_a" in layout:
        sl = layout["s_a"]
        if C_diag_f is not None:
            Fa[_V, sl] = -np.asarray(C_diag_f, float)
        gm(sl, accel_scale_sigma, scale_tau)
    if "s_g" in layout:
        sl = layout["s_g"]
        if C_diag_w is not None:
            Fa[_A, sl] = -np.asarray(C_diag_w, float)
        gm(sl, gyro_scale_sigma, scale_tau)
    if "b_map" in layout:
        gm(layout["b_map"], map_sigma, map_tau)
    Qa = np.zeros((m0 + n - n0, m0 + n - n0))
    Qa[:m0, :m0] = Qc
    Qa[m0:, m0:] = np.diag(q)
    return Fa, Ga, Qa


def augment_covariance(
    P: FloatArray,
    layout: StateLayout,
    *,
    accel_scale_sigma: float = 0.0,
    gyro_scale_sigma: float = 0.0,
    map_sigma: float = 0.0,
) -> FloatArray:
    """A (15,15) covariance padded to ``layout.size`` with independent priors for the optional blocks: scale
    factors ``accel_scale_sigma``, ``gyro_scale_sigma`` (dimensionless 1-sigma), ``b_map`` ``map_sigma`` m."""
    P = np.asarray(P, dtype=float)
    n, n0 = layout.size, P.shape[0]
    out = np.zeros((n, n))
    out[:n0, :n0] = P
    for name, sig in (("s_a", accel_scale_sigma), ("s_g", gyro_scale_sigma), ("b_map", map_sigma)):
        if name in layout:
            sl = layout[name]
            out[sl, sl] = np.eye(sl.stop - sl.start) * float(sig) ** 2
    return out


def discretize(F: FloatArray, G: FloatArray, Qc: FloatArray, dt: float) -> tuple[FloatArray, FloatArray]:
    """Transition ``Phi = expm(F dt)`` and discrete noise covariance ``Qd = int_0^dt Phi(s) G Qc G^T Phi(s)^T ds``
    by Van Loan's method (Van Loan 1978; Brown & Hwang 2012 sec. 3.9): ``B = expm([[-F, G Qc G^T], [0, F^T]] dt)``,
    ``Phi = B22^T``, ``Qd = Phi B12``."""
    n = F.shape[0]
    A = np.zeros((2 * n, 2 * n))
    A[:n, :n] = -F
    A[:n, n:] = G @ Qc @ G.T
    A[n:, n:] = F.T
    with _single_thread_blas():
        B = expm(A * dt)
    Phi = B[n:, n:].T
    Qd = Phi @ B[:n, n:]
    return Phi, 0.5 * (Qd + Qd.T)


def initial_covariance(
    grade: ImuGrade,
    position_sigma_m: float | FloatArray = 0.0,
    velocity_sigma_mps: float | FloatArray = 0.0,
    attitude_sigma_rad: float | FloatArray = 0.0,
) -> FloatArray:
    """Diagonal 15x15 ``P0``: the given position (m), velocity (m/s) and tilt (rad) 1-sigmas (scalars or (3,)),
    and the grade's total bias 1-sigmas (turn-on and Gauss-Markov)."""
    d = np.zeros(N_STATES)
    d[_P] = np.broadcast_to(position_sigma_m, (3,))
    d[_V] = np.broadcast_to(velocity_sigma_mps, (3,))
    d[_A] = np.broadcast_to(attitude_sigma_rad, (3,))
    d[_BA] = grade.accel_bias_total_sigma
    d[_BG] = grade.gyro_bias_total_sigma
    return np.diag(d**2)


def _specific_force_b(traj: NavTrajectory) -> FloatArray:
    """Specific force (N,3) body FRD implied by a trajectory: C_bn (dv/dt + (2 w_ie + w_en) x v - g)."""
    t = traj.t
    dvdt = np.gradient(traj.v_n, t, axis=0) if len(t) > 2 else np.zeros_like(traj.v_n)
    W = 2.0 * omega_ie_n(traj.lat) + omega_en_n(traj.lat, traj.h, traj.v_n)
    f_n = dvdt + np.cross(W, traj.v_n) - gravity_n(traj.lat, traj.h)
    C_bn = np.swapaxes(Rotation.from_quat(traj.q_nb).as_matrix(), -1, -2)
    return np.einsum("nij,nj->ni", C_bn, f_n)


def propagate_covariance(
    P0: FloatArray,
    traj: NavTrajectory,
    imu: ImuBatch | None,
    grade: ImuGrade,
    dt_step: float,
    *,
    altitude_hold: bool = False,
) -> tuple[FloatArray, FloatArray]:
    """Free-inertial covariance prediction along a (true or nominal) trajectory.

    Steps of ``dt_step`` s from ``traj.t[0]``; F is evaluated at the trajectory sample nearest each step's start,
    with the specific force from ``imu`` (nearest sample) or, if ``imu`` is None, from the trajectory itself.
    ``altitude_hold=True`` zeroes the down position/velocity rows and columns after every step (matching the
    strapdown's ``altitude_hold``). Returns ``t`` (M,) s and ``P`` (M,15,15), row 0 = ``P0``.
    """
    P = np.asarray(P0, dtype=float)
    if P.shape != (N_STATES, N_STATES):
        raise InputError(f"propagate_covariance: P0 must be ({N_STATES}, {N_STATES}), got {P.shape}")
    if not (dt_step > 0 and math.isfinite(dt_step)):
        raise InputError(f"propagate_covariance: dt_step must be a positive number of seconds, got {dt_step}")
    t0, t1 = float(traj.t[0]), float(traj.t[-1])
    n_steps = int(math.floor((t1 - t0) / dt_step + 1e-9))
    t_out = t0 + dt_step * np.arange(n_steps + 1)
    if imu is not None:
        f_src_t, f_src = imu.t, imu.accel_b
    else:
        f_src_t, f_src = traj.t, _specific_force_b(traj)
    C_all = Rotation.from_quat(traj.q_nb).as_matrix()
    out = np.empty((n_steps + 1, N_STATES, N_STATES))
    if altitude_hold:
        P = _hold(P)
    out[0] = P
    with _single_thread_blas():
        _propagate(P, out, t_out, traj, f_src_t, f_src, C_all, grade, dt_step, altitude_hold)
    return t_out, out


@functools.lru_cache(maxsize=1)
def _blas_controller() -> object | None:
    try:
        from threadpoolctl import ThreadpoolController
    except ImportError:  # pragma: no cover
        return None
    return ThreadpoolController()


@contextlib.contextmanager
def _single_thread_blas() -> Iterator[None]:
    """Small (30x30) matrix work is ~100x slower with a multi-threaded OpenBLAS on a busy machine (measured 21 ms
    vs 0.25 ms per expm); limit BLAS to one thread here when ``threadpoolctl`` is available (optional)."""
    ctl = _blas_controller()
    if ctl is None:  # pragma: no cover
        yield
        return
    with ctl.limit(limits=1, user_api="blas"):  # type: ignore[attr-defined]
        yield


def _propagate(P, out, t_out, traj, f_src_t, f_src, C_all, grade, dt_step, altitude_hold) -> None:  # noqa: ANN001
    n_steps = len(t_out) - 1
    cache: tuple[bytes, FloatArray, FloatArray] | None = None
    for k in range(n_steps):
        tm = t_out[k]
        i = min(int(np.searchsorted(traj.t, tm)), len(traj.t) - 1)
        j = min(int(np.searchsorted(f_src_t, tm)), len(f_src_t) - 1)
        F, G, Qc = system_matrices(traj.lat[i], traj.h[i], traj.v_n[i], C_all[i], f_src[j], grade)
        key = F.tobytes() + G.tobytes()
        if cache is None or cache[0] != key:
            Phi, Qd = discretize(F, G, Qc, dt_step)
            cache = (key, Phi, Qd)
        else:
            Phi, Qd = cache[1], cache[2]
        P = Phi @ P @ Phi.T + Qd
        if altitude_hold:
            P = _hold(P)
        out[k + 1] = P


def _hold(P: FloatArray) -> FloatArray:
    P = P.copy()
    for i in (2, 5):
        P[i, :] = 0.0
        P[:, i] = 0.0
    return P


def horizontal_sigma(P: FloatArray) -> FloatArray:
    """Horizontal 1-sigma ``sqrt(P_NN + P_EE)`` (m) of covariances (..., 15, 15) (the RMS radial error)."""
    return np.sqrt(P[..., 0, 0] + P[..., 1, 1])


__all__ = [
    "N_STATES",
    "apply_error",
    "augment_covariance",
    "augment_system",
    "bias_psd",
    "discretize",
    "horizontal_sigma",
    "initial_covariance",
    "nav_error",
    "propagate_covariance",
    "system_matrices",
]
