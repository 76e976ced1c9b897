"""Helpers shared by the fusers: a local Earth-fixed NED frame, IMU noise figures, fix validation.

Nothing here imports filterpy or gtsam.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ...core.errors import InputError
from ...core.frames import C_en, geodetic_to_ned, latlon_to_meters, ned_to_geodetic, skew
from ...core.types import Fix, ImuBatch, Innovation, NavEstimate, NavState, NavTrajectory
from ...ins.earth import gravity_n

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class LocalFrame:
    """An Earth-fixed Cartesian frame L: the NED axes at the origin ``(lat0, lon0 rad, h0 m)``, frozen to the Earth.

    Unlike the local-level NED frame it does not turn as the vehicle moves, so in L the Earth rate is a constant
    vector and there is no transport rate; the plumb-line gravity direction changes with position
    (:meth:`gravity_L`). ``C_nL`` rotates L vectors into the local-level NED at a point.
    """

    lat0: float
    lon0: float
    h0: float

    def to_L(self, lat: ArrayLike, lon: ArrayLike, h: ArrayLike) -> FloatArray:
        """Geodetic (rad, rad, m) to L coordinates (m), shape ``(..., 3)``."""
        return geodetic_to_ned(lat, lon, h, self.lat0, self.lon0, self.h0)

    def to_geodetic(self, r_L: ArrayLike) -> tuple[FloatArray, FloatArray, FloatArray]:
        """L coordinates (m) to geodetic latitude, longitude (rad), height (m)."""
        return ned_to_geodetic(r_L, self.lat0, self.lon0, self.h0)

    def C_nL(self, lat: float, lon: float) -> FloatArray:
        """Rotation from L to the local-level NED at ``(lat, lon)``: ``x_n = C_nL @ x_L``."""
        return C_en(lat, lon).T @ C_en(self.lat0, self.lon0)

    def gravity_L(self, r_L: ArrayLike) -> FloatArray:
        """Normal (plumb-line) gravity at ``r_L`` resolved in L, m/s^2 (:func:`ins.earth.gravity_n` rotated)."""
        lat, lon, h = self.to_geodetic(r_L)
        return self.C_nL(float(lat), float(lon)).T @ gravity_n(float(lat), float(h))


@dataclass(frozen=True)
class ImuNoise:
    """IMU noise for the fusers, SI, the same on the three axes.

    ``accel_noise`` m/s^2/sqrt(Hz) (velocity random walk), ``gyro_noise`` rad/s/sqrt(Hz) (angle random walk);
    ``accel_bias_sigma`` m/s^2 and ``gyro_bias_sigma`` rad/s: steady-state 1-sigma of first-order Gauss-Markov biases
    with time constants ``accel_bias_tau``, ``gyro_bias_tau`` s (``inf``: random constants); ``accel_turn_on``,
    ``gyro_turn_on``: 1-sigma of constant switch-on biases (they only enter the initial covariance). A random-walk
    bias model (GTSAM's CombinedImuFactor) uses the equivalent densities ``sigma * sqrt(2 / tau)``.
    """

    accel_noise: float
    gyro_noise: float
    accel_bias_sigma: float
    gyro_bias_sigma: float
    accel_bias_tau: float = 3600.0
    gyro_bias_tau: float = 3600.0
    accel_turn_on: float = 0.0
    gyro_turn_on: float = 0.0

    @property
    def accel_bias_rw(self) -> float:
        """Accelerometer bias random-walk density, m/s^3/sqrt(Hz) (0 for a random constant)."""
        return float(self.accel_bias_sigma * np.sqrt(2.0 / self.accel_bias_tau))

    @property
    def gyro_bias_rw(self) -> float:
        """Gyro bias random-walk density, rad/s^2/sqrt(Hz) (0 for a random constant)."""
        return float(self.gyro_bias_sigma * np.sqrt(2.0 / self.gyro_bias_tau))

    @property
    def accel_bias_init_sigma(self) -> float:
        """1-sigma of the whole accelerometer bias at switch-on (turn-on and Gauss-Markov), m/s^2."""
        return float(np.hypot(self.accel_bias_sigma, self.accel_turn_on))

    @property
    def gyro_bias_init_sigma(self) -> float:
        """1-sigma of the whole gyro bias at switch-on (turn-on and Gauss-Markov), rad/s."""
        return float(np.hypot(self.gyro_bias_sigma, self.gyro_turn_on))

    # duck-typed view for ins.error_model.system_matrices (which reads an ImuGrade)
    @property
    def vrw(self) -> float:
        return self.accel_noise

    @property
    def arw(self) -> float:
        return self.gyro_noise

    def arr(self, name: str) -> FloatArray:
        """A field as a (3,) array (the same on every axis)."""
        return np.full(3, float(getattr(self, name)))

    @classmethod
    def from_grade(cls, grade: object) -> ImuNoise:
        """From an :class:`magnav_ins.ins.imu_models.ImuGrade` (largest of the three axes for each figure;
        scale factors and misalignments are not modelled by the 15-state fusers)."""

        def mx(name: str) -> float:
            return float(np.max(np.asarray(getattr(grade, name), dtype=float)))

        return cls(
            accel_noise=mx("vrw"),
            gyro_noise=mx("arw"),
            accel_bias_sigma=mx("accel_bias_sigma"),
            gyro_bias_sigma=mx("gyro_bias_sigma"),
            accel_bias_tau=float(grade.accel_bias_tau),
            gyro_bias_tau=float(grade.gyro_bias_tau),
            accel_turn_on=mx("accel_turn_on_sigma"),
            gyro_turn_on=mx("gyro_turn_on_sigma"),
        )


def fix_problem(fix: Fix) -> str:
    """Why ``fix`` cannot be used ("" when it can): unavailable, non-finite, or a covariance that is not
    symmetric positive definite."""
    if not fix.available:
        return f"no fix: {fix.reason}" if fix.reason else "no fix"
    if not (np.isfinite(fix.t) and np.isfinite(fix.lat) and np.isfinite(fix.lon)):
        return f"non-finite fix (t={fix.t}, lat={fix.lat}, lon={fix.lon})"
    cov = np.asarray(fix.cov_ne, dtype=float)
    if cov.shape != (2, 2) or not np.all(np.isfinite(cov)):
        return f"fix covariance must be a finite 2x2 matrix, got {cov.tolist()}"
    if not np.allclose(cov, cov.T, rtol=1e-9, atol=1e-12 * max(1.0, float(np.abs(cov).max()))):
        return f"fix covariance is not symmetric: {cov.tolist()}"
    if np.linalg.eigvalsh(cov).min() <= 0.0:
        return f"fix covariance is not positive definite: {cov.tolist()}"
    return ""


def residual_ne(fix: Fix, nav: NavState) -> FloatArray:
    """Fix minus INS position, north/east metres at the INS position (local-tangent approximation)."""
    dlon = (fix.lon - nav.lon + np.pi) % (2.0 * np.pi) - np.pi
    dn, de = latlon_to_meters(fix.lat - nav.lat, dlon, nav.lat, nav.h)
    return np.array([float(dn), float(de)])


def rejected(fix: Fix, reason: str, residual: ArrayLike | None = None, S: ArrayLike | None = None, nis: float = np.nan):
    """An :class:`Innovation` for a fix that was not applied."""
    r = np.full(2, np.nan) if residual is None else np.asarray(residual, float)
    s = np.full((2, 2), np.nan) if S is None else np.asarray(S, float)
    return Innovation(float(fix.t), r, s, float(nis), False, reason, fix.source)


def symmetrise(P: ArrayLike, floor: float = 0.0) -> FloatArray:
    """``(P + P^T)/2`` with eigenvalues clipped at ``floor`` (keeps a covariance symmetric PSD/PD)."""
    P = np.asarray(P, dtype=float)
    P = 0.5 * (P + P.T)
    w, V = np.linalg.eigh(P)
    if w.min() >= floor:
        return P
    w = np.maximum(w, floor)
    return (V * w) @ V.T


def check_time(t_new: float, t_last: float, what: str) -> None:
    """Raise :class:`InputError` when time goes backwards or is not finite."""
    if not np.isfinite(t_new):
        raise InputError(f"{what}: time must be finite, got {t_new}")
    if t_new < t_last - 1e-9:
        raise InputError(f"{what}: time goes backwards: t={t_new!r} s after t={t_last!r} s")


def _dcm(q: FloatArray) -> FloatArray:
    """``C_nb`` from a unit scalar-last quaternion (the same as :func:`core.frames.C_nb_from_q`, a few µs)."""
    x, y, z, w = float(q[0]), float(q[1]), float(q[2]), float(q[3])
    return np.array([
        [1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - z * w), 2.0 * (x * z + y * w)],
        [2.0 * (x * y + z * w), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - x * w)],
        [2.0 * (x * z - y * w), 2.0 * (y * z + x * w), 1.0 - 2.0 * (x * x + y * y)],
    ])  # fmt: skip


def _expm(A: FloatArray, order: int = 10) -> FloatArray:
    """Matrix exponential by scaling and squaring with a Taylor polynomial (Moler & Van Loan 2003, method 3):
    ``exp(A) = (T_order(A / 2^s))^(2^s)`` with ``||A / 2^s||_1 <= 0.25`` (truncation below 1e-13). Only matrix
    products: for the small 30x30 Van Loan blocks it is 20-40x faster than ``scipy.linalg.expm`` on a loaded
    machine, and agrees with it to 1e-12 (tested)."""
    norm = float(np.abs(A).sum(axis=0).max())
    s = max(0, int(np.ceil(np.log2(norm / 0.25)))) if norm > 0.25 else 0
    M = A / (2.0**s)
    E = np.eye(A.shape[0])
    term = np.eye(A.shape[0])
    for k in range(1, order + 1):
        term = term @ M / k
        E = E + term
    for _ in range(s):
        E = E @ E
    return E


def discretize_fast(F: FloatArray, G: FloatArray, Qc: FloatArray, dt: float) -> tuple[FloatArray, FloatArray]:
    """Van Loan discretisation, the same formula as :func:`magnav_ins.ins.error_model.discretize`
    (``B = exp([[-F, G Qc G^T], [0, F^T]] dt)``, ``Phi = B22^T``, ``Qd = Phi B12``) with :func:`_expm`."""
    n = F.shape[0]
    A = np.zeros((2 * n, 2 * n))
    A[:n, :n] = -F
    A[:n, n:] = G @ Qc @ G.T
    A[n:, n:] = F.T
    B = _expm(A * dt)
    Phi = B[n:, n:].T
    Qd = Phi @ B[:n, n:]
    return Phi, 0.5 * (Qd + Qd.T)


class InertialCore:
    """Strapdown INS (:class:`ins.strapdown.StrapdownStepper`) with the 15-state error covariance of
    :mod:`ins.error_model` propagated alongside, plus a short replay buffer for late fixes.

    The INS integrates bias-corrected samples ``omega = omega_meas - b_g_est``, ``f = f_meas - b_a_est``. The
    covariance is propagated in steps of at most ``cov_step_s`` s: ``F, G, Qc`` at the current state and the mean
    specific force of the step, ``(Phi, Qd) = discretize(F, G, Qc, dt)`` over exactly that step (Van Loan), then
    :meth:`_predict_cov` (``Phi P Phi^T + Qd`` here; the UKF overrides it with its unscented prediction).
    (:func:`discretize_fast` is error_model's Van Loan formula with a product-only matrix exponential.)
    At every covariance step a checkpoint (state, covariance, biases, sample count) is kept for ``buffer_s`` s with
    the raw samples since the oldest one; :meth:`_rewind` restores the last checkpoint before a past time and returns
    the samples to replay, so a late fix is applied at its own time (re-propagation).
    """

    def __init__(
        self,
        init: NavEstimate,
        noise: ImuNoise,
        *,
        cov_step_s: float = 1.0,
        buffer_s: float = 120.0,
        altitude_hold: float | None = None,
        keep_history: bool = False,
    ) -> None:
        from ...ins.strapdown import StrapdownStepper

        P0 = np.asarray(init.P, dtype=float)
        if P0.shape != (15, 15):
            raise InputError(f"initial covariance must be 15x15 (LAYOUT_15), got {P0.shape}")
        if not np.all(np.isfinite(P0)):
            raise InputError("initial covariance holds non-finite values")
        if not (cov_step_s > 0 and buffer_s >= 0):
            raise InputError(f"cov_step_s must be > 0 and buffer_s >= 0, got {cov_step_s}, {buffer_s}")
        self.noise = noise
        self.cov_step_s = float(cov_step_s)
        self.buffer_s = float(buffer_s)
        self._stepper = StrapdownStepper(init.nav, altitude_hold=altitude_hold)
        self._P = symmetrise(P0, 0.0)
        self._b_a = np.zeros(3)
        self._b_g = np.zeros(3)
        self._t_cov = float(init.nav.t)
        self._clear_step_sums()
        self._samples: list[tuple[float, FloatArray, FloatArray]] = []
        self._n_dropped = 0  # samples dropped from the front of the buffer
        self._checkpoints: list[tuple] = []
        self._checkpoint()
        # smoother history, one entry per covariance step: [t, Phi (from the previous step), P-, P+, dx, nav+, b_a, b_g]
        self._history: list[list] | None = (
            [
                [
                    self.t,
                    None,
                    self._P.copy(),
                    self._P.copy(),
                    np.zeros(15),
                    self._stepper.nav,
                    self._b_a.copy(),
                    self._b_g.copy(),
                ]
            ]  # fmt: skip
            if keep_history
            else None
        )

    # ------------------------------------------------------------------------------------------- internals
    @property
    def t(self) -> float:
        """Time of the current state, s."""
        return self._stepper.t

    def _checkpoint(self) -> None:
        self._checkpoints.append(
            (
                self.t,
                self._stepper.nav,
                self._P.copy(),
                self._b_a.copy(),
                self._b_g.copy(),
                self._n_dropped + len(self._samples),
            )  # fmt: skip
        )
        t_old = self.t - self.buffer_s
        while len(self._checkpoints) > 1 and self._checkpoints[1][0] <= t_old:
            self._checkpoints.pop(0)
        drop = self._checkpoints[0][5] - self._n_dropped
        if drop > 0:
            del self._samples[:drop]
            self._n_dropped += drop

    def _clear_step_sums(self) -> None:
        """Start a covariance step: integrals of ``C_nb`` and ``C_nb f_b`` (navigation-frame specific force) over
        it, and its length; the attitude at the step start is re-read from the INS (it may have been corrected)."""
        self._C_sum = np.zeros((3, 3))
        self._fn_sum = np.zeros(3)
        self._f_dt = 0.0
        self._C_prev: FloatArray | None = None

    def _predict_cov(self, Phi: FloatArray, Qd: FloatArray) -> None:
        self._P = symmetrise(Phi @ self._P @ Phi.T + Qd, 0.0)

    def _advance_cov(self) -> None:
        """Propagate the covariance from its time to the INS time (one step) and checkpoint."""
        from ...core.frames import C_nb_from_q
        from ...ins.error_model import system_matrices

        dt = self.t - self._t_cov
        if dt <= 0.0:
            return
        nav = self._stepper.nav
        C_end = C_nb_from_q(nav.q_nb)
        F, G, Qc = system_matrices(nav.lat, nav.h, nav.v_n, C_end, np.zeros(3), self.noise)
        if self._f_dt > 0:
            # the attitude-dependent blocks averaged over the step (first Magnus term of the time-varying F):
            # mean C_nb for the bias columns, mean navigation-frame specific force for the tilt column
            C_mean = self._C_sum / self._f_dt
            F[3:6, 6:9] = -skew(self._fn_sum / self._f_dt)
            F[3:6, 9:12] = -C_mean
            F[6:9, 12:15] = -C_mean
        Phi, Qd = discretize_fast(F, G, Qc, dt)
        self._predict_cov(Phi, Qd)
        if self._history is not None:
            self._history.append([self.t, Phi, self._P.copy(), self._P.copy(), np.zeros(15), self._stepper.nav,
                                  self._b_a.copy(), self._b_g.copy()])  # fmt: skip
        self._t_cov = self.t
        self._clear_step_sums()
        self._checkpoint()

    def _step(self, t: float, w: FloatArray, f: FloatArray) -> None:
        dt = t - self.t
        f_c = f - self._b_a
        C0 = self._C_prev if self._C_prev is not None else _dcm(self._stepper.nav.q_nb)
        self._stepper.step_rate(t, w - self._b_g, f_c)
        C1 = _dcm(self._stepper.nav.q_nb)
        C_mid = 0.5 * (C0 + C1)  # attitude over the sample (trapezoid)
        self._C_prev = C1
        self._C_sum += C_mid * dt
        self._fn_sum += C_mid @ f_c * dt
        self._f_dt += dt
        if t - self._t_cov >= self.cov_step_s - 1e-9:
            self._advance_cov()

    def _rewind(self, t_past: float) -> list[tuple[float, FloatArray, FloatArray]] | None:
        """Restore the last checkpoint at or before ``t_past`` and re-step the buffered samples up to ``t_past``
        (cutting the straddling one); returns the samples to replay after it, or None if ``t_past`` is older
        than the buffer."""
        cps = [c for c in self._checkpoints if c[0] <= t_past + 1e-9]
        if not cps:
            return None
        t_c, nav, P, b_a, b_g, n_at = cps[-1]
        samples = self._samples[n_at - self._n_dropped :]
        del self._samples[n_at - self._n_dropped :]
        while self._checkpoints and self._checkpoints[-1][0] > t_c:
            self._checkpoints.pop()
        self._checkpoints.pop()  # re-created below
        self._stepper.reset(nav)
        self._P, self._b_a, self._b_g = P.copy(), b_a.copy(), b_g.copy()
        self._t_cov = t_c
        if self._history is not None:
            while len(self._history) > 1 and self._history[-1][0] > t_c + 1e-9:
                self._history.pop()
        self._clear_step_sums()
        self._checkpoint()
        rest = []
        for k, (t, w, f) in enumerate(samples):
            if t <= t_past + 1e-9:
                self._samples.append((t, w, f))
                self._step(t, w, f)
            else:
                if self.t < t_past - 1e-9:
                    self._step(t_past, w, f)  # the straddling sample, first part
                rest = samples[k:]
                break
        return rest

    def _replay(self, samples: list[tuple[float, FloatArray, FloatArray]]) -> None:
        for t, w, f in samples:
            self._samples.append((t, w, f))
            self._step(t, w, f)

    # ------------------------------------------------------------------------------------------ Fuser API
    def propagate(self, imu: ImuBatch) -> None:
        """Mechanise IMU samples after the current time (rates over ``(t[k-1], t[k]]``, body FRD); samples at or
        before it are skipped. Non-finite samples or non-increasing times raise :class:`InputError`."""
        if len(imu) == 0:
            return
        if not (np.all(np.isfinite(imu.gyro_b)) and np.all(np.isfinite(imu.accel_b)) and np.all(np.isfinite(imu.t))):
            raise InputError(f"{type(self).__name__}.propagate: IMU batch holds non-finite values")
        d = np.diff(imu.t)
        if np.any(d <= 0):
            k = int(np.argmax(d <= 0)) + 1
            raise InputError(f"{type(self).__name__}.propagate: IMU time not increasing at sample {k}: t={imu.t[k]!r}")
        check_time(float(imu.t[-1]), self.t, f"{type(self).__name__}.propagate")
        t_now = self.t
        for k in np.flatnonzero(imu.t > t_now + 1e-9):
            t, w, f = float(imu.t[k]), imu.gyro_b[k].copy(), imu.accel_b[k].copy()
            self._samples.append((t, w, f))
            self._step(t, w, f)

    def estimate(self) -> NavEstimate:
        """The current INS state and its LAYOUT_15 error covariance (propagated up to now)."""
        self._advance_cov()
        from ...core.types import LAYOUT_15

        return NavEstimate(self._stepper.nav, self._P.copy(), LAYOUT_15)

    @property
    def bias(self) -> tuple[FloatArray, FloatArray]:
        """Current accelerometer (m/s^2) and gyro (rad/s) bias estimates, body FRD."""
        return self._b_a.copy(), self._b_g.copy()

    def _record_update(self, dx: FloatArray) -> None:
        """Mark the last covariance step as updated by ``dx`` (error estimate before the reset)."""
        if self._history is not None:
            h = self._history[-1]
            h[3], h[4], h[5], h[6], h[7] = (
                self._P.copy(),
                dx.copy(),
                self._stepper.nav,
                self._b_a.copy(),
                self._b_g.copy(),
            )

    def smooth(self) -> tuple[NavTrajectory, FloatArray]:
        """Rauch-Tung-Striebel smoothing of the recorded run (``keep_history=True``), in closed-loop error-state
        form: with ``e`` the error of the filter's corrected state at each covariance step,
        ``e_s(k) = C_k (e_s(k+1) + dx_{k+1})``, ``C_k = P+_k Phi_k^T (P-_{k+1})^-1``,
        ``P_s(k) = P+_k + C_k (P_s(k+1) - P-_{k+1}) C_k^T`` (Rauch, Tung & Striebel 1965; ``dx`` is the update's
        error estimate before its reset, zero without a fix). Returns the smoothed states at the step times and
        their covariances (N,15,15)."""
        from ...ins.error_model import apply_error

        if self._history is None:
            raise InputError("smooth(): construct the fuser with keep_history=True")
        H = self._history
        n = len(H)
        e = np.zeros(15)
        Ps = H[-1][3].copy()
        out_nav = [H[-1][5]]
        out_P = [Ps]
        for k in range(n - 2, -1, -1):
            Phi, Pm1, dx1 = H[k + 1][1], H[k + 1][2], H[k + 1][4]
            Pp = H[k][3]
            C = np.linalg.solve(Pm1.T, (Pp @ Phi.T).T).T  # Pp Phi^T Pm1^-1
            e = C @ (e + dx1)
            Ps = symmetrise(Pp + C @ (Ps - Pm1) @ C.T, 0.0)
            out_nav.append(apply_error(H[k][5], -e[:9]))
            out_P.append(Ps)
        out_nav.reverse()
        out_P.reverse()
        traj = NavTrajectory(
            np.array([x.t for x in out_nav]), np.array([x.lat for x in out_nav]), np.array([x.lon for x in out_nav]),
            np.array([x.h for x in out_nav]), np.array([x.v_n for x in out_nav]), np.array([x.q_nb for x in out_nav]),
        )  # fmt: skip
        return traj, np.array(out_P)
