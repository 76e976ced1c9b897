"""Helpers shared by the fusers: a local Earth-fixed NED frame, IMU noise figures, fix validation.

Nothing here imports filterpy or gtsam.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ...core.errors import ConfigError, InputError
from ...core.frames import (
    C_en,
    C_en_point,
    ecef_to_geodetic,
    ecef_to_geodetic_point,
    geodetic_to_ecef,
    latlon_to_meters,
    skew,
)
from ...core.types import (
    DEFAULT_INTEGRITY_RISK,
    LAYOUT_15,
    Fix,
    ImuBatch,
    Innovation,
    NavEstimate,
    NavState,
    NavTrajectory,
    StateLayout,
)
from ...ins.earth import gravity_n_point

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

    # the origin's ECEF position and NED-to-ECEF matrix, computed once (the fusers convert every IMU sample); the
    # conversions below are core.frames.geodetic_to_ned / ned_to_geodetic with these two terms taken from the cache
    @cached_property
    def _r0_e(self) -> FloatArray:
        return geodetic_to_ecef(self.lat0, self.lon0, self.h0)

    @cached_property
    def _C_en0(self) -> FloatArray:
        return C_en(self.lat0, self.lon0)

    def to_L(self, lat: ArrayLike, lon: ArrayLike, h: ArrayLike) -> FloatArray:
        """Geodetic (rad, rad, m) to L coordinates (m), shape ``(..., 3)``."""
        return np.einsum("ji,...j->...i", self._C_en0, geodetic_to_ecef(lat, lon, h) - self._r0_e)

    def to_geodetic(self, r_L: ArrayLike) -> tuple[FloatArray, FloatArray, FloatArray]:
        """L coordinates (m) to geodetic latitude, longitude (rad), height (m)."""
        r_e = self._r0_e + np.einsum("ij,...j->...i", self._C_en0, np.asarray(r_L, float))
        if r_e.shape == (3,):  # one point (every IMU sample of the graph fuser): the same numbers, faster
            return ecef_to_geodetic_point(r_e[0], r_e[1], r_e[2])  # type: ignore[return-value]
        return ecef_to_geodetic(r_e)

    def C_nL(self, lat: float, lon: float) -> FloatArray:
        """Rotation from L to the local-level NED at ``(lat, lon)``: ``x_n = C_nL @ x_L``."""
        if np.ndim(lat) == 0 and np.ndim(lon) == 0:
            return C_en_point(lat, lon).T @ self._C_en0
        return C_en(lat, lon).T @ self._C_en0

    def gravity_L(self, r_L: ArrayLike) -> FloatArray:
        """Normal (plumb-line) gravity at ``r_L`` resolved in L, m/s^2 (:func:`ins.earth.gravity_n` rotated)."""
        lat, lon, h = self.to_geodetic(r_L)
        return self.C_nL(float(lat), float(lon)).T @ gravity_n_point(float(lat), float(h))


@dataclass(frozen=True)
class ImuNoise:
    """IMU noise for the fusers, SI, the same on the three axes.

    ``accel_noise`` m/s^2/sqrt(Hz) (velocity random walk), ``gyro_noise`` rad/s/sqrt(Hz) (angle random walk);
    ``accel_bias_sigma`` m/s^2 and ``gyro_bias_sigma`` rad/s: steady-state 1-sigma of first-order Gauss-Markov biases
    with time constants ``accel_bias_tau``, ``gyro_bias_tau`` s (``inf``: random constants); ``accel_turn_on``,
    ``gyro_turn_on``: 1-sigma of constant switch-on biases (they only enter the initial covariance). A random-walk
    bias model (GTSAM's CombinedImuFactor) uses the equivalent densities ``sigma * sqrt(2 / tau)``.
    ``accel_scale_sigma``, ``gyro_scale_sigma``: dimensionless scale-factor 1-sigma, the prior of the optional
    scale-factor states (:class:`ExtraStates`; unused by the 15-state filters).
    """

    accel_noise: float
    gyro_noise: float
    accel_bias_sigma: float
    gyro_bias_sigma: float
    accel_bias_tau: float = 3600.0
    gyro_bias_tau: float = 3600.0
    accel_turn_on: float = 0.0
    gyro_turn_on: float = 0.0
    accel_scale_sigma: float = 0.0
    gyro_scale_sigma: float = 0.0

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
        misalignments are not modelled; scale factors only with ``scale_factors=True``, :class:`ExtraStates`)."""

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
            accel_scale_sigma=mx("accel_scale_sigma"),
            gyro_scale_sigma=mx("gyro_scale_sigma"),
        )


def _number(key: str, value: object, *, allow_inf: bool) -> float:
    """``value`` as a positive float, or a :class:`ConfigError` naming ``key`` and the value."""
    ok = isinstance(value, (int, float, np.floating, np.integer)) and not isinstance(value, (bool, np.bool_))
    x = float(value) if ok else math.nan  # type: ignore[arg-type]
    if not (x > 0 and (math.isfinite(x) or (allow_inf and x == math.inf))):
        inf = " (inf: random constant)" if allow_inf else ""
        raise ConfigError(f"fusion option {key}: expected a number > 0{inf}, got {value!r}")
    return x


@dataclass(frozen=True)
class ExtraStates:
    """The optional error states of the inertial fusers beyond LAYOUT_15 (:func:`ins.error_model.augment_system`).

    ``scale_factors``: 6 states ``s_a``, ``s_g`` (accelerometer and gyro scale-factor errors, dimensionless, body
    FRD x, y, z), prior 1-sigma the noise's ``accel_scale_sigma`` / ``gyro_scale_sigma``, random constants
    (``scale_factor_tau_s = inf``) or first-order Gauss-Markov with that correlation time (s); fed back into the
    INS correction ``f = (f_meas - b_a) / (1 + s_a)``, ``omega = (omega_meas - b_g) / (1 + s_g)``.
    ``map_bias_sigma_m`` (None: no state): 2 states ``b_map`` (north, east m), the common registration offset of
    the map the fixes come from, first-order Gauss-Markov with 1-sigma ``map_bias_sigma_m`` and correlation time
    ``map_bias_tau_s`` (inf: random constant); a fix measures ``z = p_ne + b_map + v``. ``map_bias_sources``:
    only fixes whose ``Fix.source`` is one of these see the bias (None: every fix).
    """

    scale_factors: bool = False
    scale_factor_tau_s: float = math.inf
    accel_scale_sigma: float = 0.0
    gyro_scale_sigma: float = 0.0
    map_bias_sigma_m: float | None = None
    map_bias_tau_s: float = 3600.0
    map_bias_sources: tuple[str, ...] | None = None

    @classmethod
    def from_options(
        cls,
        noise: ImuNoise,
        *,
        scale_factors: object = False,
        scale_factor_tau_s: object = None,
        map_bias_sigma_m: object = None,
        map_bias_tau_s: object = None,
        map_bias_sources: object = None,
    ) -> ExtraStates:
        """Validated options (a :class:`ConfigError` names the option and its bad value)."""
        if not isinstance(scale_factors, (bool, np.bool_)):
            raise ConfigError(f"fusion option scale_factors: expected true or false, got {scale_factors!r}")
        sf = bool(scale_factors)
        if scale_factor_tau_s is not None and not sf:
            raise ConfigError("fusion option scale_factor_tau_s needs scale_factors = true")
        sf_tau = math.inf if scale_factor_tau_s is None else _number("scale_factor_tau_s", scale_factor_tau_s,
                                                                      allow_inf=True)  # fmt: skip
        if sf and not (noise.accel_scale_sigma > 0 and noise.gyro_scale_sigma > 0):
            raise ConfigError(
                "fusion option scale_factors = true needs the IMU's scale-factor sigmas > 0, got accel "
                f"{noise.accel_scale_sigma}, gyro {noise.gyro_scale_sigma}"
            )
        mb = None if map_bias_sigma_m is None else _number("map_bias_sigma_m", map_bias_sigma_m, allow_inf=False)
        if mb is None and (map_bias_tau_s is not None or map_bias_sources is not None):
            key = "map_bias_tau_s" if map_bias_tau_s is not None else "map_bias_sources"
            raise ConfigError(f"fusion option {key} needs map_bias_sigma_m")
        mb_tau = 3600.0 if map_bias_tau_s is None else _number("map_bias_tau_s", map_bias_tau_s, allow_inf=True)
        sources = None
        if map_bias_sources is not None:
            src = [map_bias_sources] if isinstance(map_bias_sources, str) else map_bias_sources
            if not isinstance(src, (list, tuple)) or not src or not all(isinstance(x, str) for x in src):
                raise ConfigError(
                    f"fusion option map_bias_sources: expected a list of fix sources, got {map_bias_sources!r}"
                )
            sources = tuple(src)
        return cls(sf, sf_tau, float(noise.accel_scale_sigma), float(noise.gyro_scale_sigma), mb, mb_tau, sources)

    @property
    def layout(self) -> StateLayout:
        """LAYOUT_15 extended by ``s_a, s_g`` (15:18, 18:21) and/or ``b_map`` (next two)."""
        extra: dict[str, int] = {}
        if self.scale_factors:
            extra.update(s_a=3, s_g=3)
        if self.map_bias_sigma_m is not None:
            extra["b_map"] = 2
        return LAYOUT_15.extended(**extra) if extra else LAYOUT_15

    def biased(self, fix: Fix) -> bool:
        """Whether ``fix`` measures the map bias."""
        return self.map_bias_sigma_m is not None and (
            self.map_bias_sources is None or fix.source in self.map_bias_sources
        )

    def decay(self, dt: float) -> float:
        """Gauss-Markov mean decay ``exp(-dt / tau)`` of the map-bias estimate over ``dt`` s."""
        return math.exp(-dt / self.map_bias_tau_s) if math.isfinite(self.map_bias_tau_s) else 1.0

    def augment(self, F: FloatArray, G: FloatArray, Qc: FloatArray, Cf: FloatArray | None, Cw: FloatArray | None):
        """:func:`ins.error_model.augment_system` with these options."""
        from ...ins.error_model import augment_system

        return augment_system(
            F, G, Qc, self.layout, C_diag_f=Cf, C_diag_w=Cw, accel_scale_sigma=self.accel_scale_sigma,
            gyro_scale_sigma=self.gyro_scale_sigma, scale_tau=self.scale_factor_tau_s,
            map_sigma=self.map_bias_sigma_m or 0.0, map_tau=self.map_bias_tau_s,
        )  # fmt: skip

    def prior(self, P15: FloatArray) -> FloatArray:
        """A (15,15) prior padded with the optional states' priors (:func:`ins.error_model.augment_covariance`)."""
        from ...ins.error_model import augment_covariance

        return augment_covariance(
            P15, self.layout, accel_scale_sigma=self.accel_scale_sigma, gyro_scale_sigma=self.gyro_scale_sigma,
            map_sigma=self.map_bias_sigma_m or 0.0,
        )  # fmt: skip


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


def _positive_definite_where_live(C: FloatArray, live: NDArray[np.bool_]) -> bool:
    """True when the states with a positive variance (``live``) form a positive definite block (its Cholesky
    factor exists) and the others are exactly uncorrelated zeros: then every eigenvalue is >= 0."""
    if not live.all():
        dead = ~live
        if np.any(C[dead, :]) or np.any(C[:, dead]):
            return False
        C = C[np.ix_(live, live)]
    try:
        np.linalg.cholesky(C)
    except np.linalg.LinAlgError:
        return False
    return True


def symmetrise(P: ArrayLike, floor: float = 0.0) -> FloatArray:
    """``(P + P^T)/2`` with eigenvalues clipped at ``floor`` (keeps a covariance symmetric PSD/PD).

    With ``floor == 0`` the clipping is done on the correlation-scaled matrix ``D^-1 P D^-1`` (``D`` = the
    standard deviations): a 15-state covariance spans ~25 orders of magnitude (km^2 positions, precision gyro
    biases ~1e-17 rad^2/s^2), and an eigen-decomposition of the raw matrix puts errors of ``eps * max eig`` into
    every entry, which swamps the small states."""
    P = np.asarray(P, dtype=float)
    P = 0.5 * (P + P.T)
    if floor == 0.0:
        d = np.diag(P)
        sd = np.sqrt(np.where(d > 0, d, 1.0))
        C = P / np.outer(sd, sd)
        if _positive_definite_where_live(C, d > 0):  # the common case, without the eigen-decomposition
            return P
        w, V = np.linalg.eigh(C)
        if w.min() >= 0.0:
            return P
        return ((V * np.maximum(w, 0.0)) @ V.T) * np.outer(sd, sd)
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


def _constants(noise: ImuNoise) -> tuple[float, float, FloatArray]:
    """:func:`.cov_step.noise_constants` (memoised for the immutable :class:`ImuNoise`)."""
    from .cov_step import noise_constants, noise_constants_cached

    try:
        return noise_constants_cached(noise)
    except TypeError:  # not hashable (an ImuGrade)
        return noise_constants(noise)


def step_matrices(
    nav: NavState,
    C_sum: FloatArray,
    fn_sum: FloatArray,
    sum_dt: float,
    dt: float,
    noise: ImuNoise,
    extra: ExtraStates | None = None,
    Cf_sum: FloatArray | None = None,
    Cw_sum: FloatArray | None = None,
) -> tuple[FloatArray, FloatArray]:
    """``(Phi, Qd)`` of one covariance step of ``dt`` s ending at ``nav``: ``F, G, Qc`` from
    :func:`ins.error_model.system_matrices` at ``nav``, with the attitude-dependent blocks averaged over the step
    (the first Magnus term of the time-varying ``F``): ``-mean(C_nb)`` for the bias columns and
    ``-[mean(f_n) x]`` for the tilt column, from the step integrals ``C_sum`` = int C_nb dt, ``fn_sum`` =
    int C_nb f_b dt over ``sum_dt`` s; then Van Loan (:func:`discretize_fast`). With ``extra`` the optional
    states are appended (:meth:`ExtraStates.augment`), their scale-factor columns averaged likewise from
    ``Cf_sum`` = int C_nb diag(f_b) dt and ``Cw_sum`` = int C_nb diag(omega_ib_b) dt."""
    from ...ins.error_model import system_matrices

    if extra is None or extra.layout.size == 15:  # the compiled twin of the code below (cov_step.py)
        from .cov_step import step_matrices_15

        return step_matrices_15(nav.lat, nav.h, nav.v_n, _dcm(nav.q_nb), C_sum, fn_sum, sum_dt, dt, _constants(noise))
    F, G, Qc = system_matrices(nav.lat, nav.h, nav.v_n, _dcm(nav.q_nb), np.zeros(3), noise)
    if sum_dt > 0:
        C_mean = C_sum / sum_dt
        F[3:6, 6:9] = -skew(fn_sum / sum_dt)
        F[3:6, 9:12] = -C_mean
        F[6:9, 12:15] = -C_mean
    if extra is not None and extra.layout.size > 15:
        ok = sum_dt > 0 and Cf_sum is not None and Cw_sum is not None
        Cf = Cf_sum / sum_dt if ok else None
        Cw = Cw_sum / sum_dt if ok else None
        F, G, Qc = extra.augment(F, G, Qc, Cf, Cw)
    return discretize_fast(F, G, Qc, dt)


#: down position and down velocity (LAYOUT_15), frozen in the covariance under an altitude hold
_HELD = (2, 5)


def _held_transition(Phi: FloatArray) -> FloatArray:
    """The transition that the altitude hold gives a covariance step: ``Phi`` with the held states (:data:`_HELD`)
    carried over unchanged (their rows the identity's) and decoupled from the others (their columns zero in the
    other rows). With it ``Phi_h P+ Phi_h^T + Q_h`` is the held prediction of :meth:`InertialCore._advance_cov`
    (``Q_h``: ``Qd`` and the held states' ``Phi`` columns' share, ``Phi_rD P_DD Phi_rD^T``, on the other states),
    so the smoother's gain ``P+ Phi_h^T (P-)^-1`` and mean ``Phi_h m`` belong to the model its covariances follow."""
    out = np.array(Phi, dtype=float)
    held = list(_HELD)
    out[:, held] = 0.0
    out[held, :] = 0.0
    out[held, held] = 1.0
    return out


def _clamped(nav: NavState, h_m: float) -> NavState:
    """``nav`` with the altitude hold's vertical channel: height ``h_m`` (m), down velocity 0."""
    v = np.array(nav.v_n, dtype=float)
    v[2] = 0.0
    return NavState(nav.t, nav.lat, nav.lon, float(h_m), v, nav.q_nb)


class Samples:
    """IMU samples as arrays: ``t`` (m,) s, ``w`` gyro rad/s, ``f`` specific force m/s^2 (m,3), body FRD (raw:
    before the fuser's bias correction)."""

    __slots__ = ("t", "w", "f")

    def __init__(self, t: FloatArray, w: FloatArray, f: FloatArray) -> None:
        self.t, self.w, self.f = t, w, f

    def __len__(self) -> int:
        return len(self.t)

    def __getitem__(self, k: slice) -> Samples:
        return Samples(self.t[k], self.w[k], self.f[k])

    @staticmethod
    def empty() -> Samples:
        return Samples(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3)))


class _SampleBuffer:
    """The raw samples since the oldest checkpoint (growable arrays; appends, front drops and a cut at an index
    without a Python object per sample)."""

    def __init__(self, capacity: int = 1024) -> None:
        self._t = np.empty(capacity)
        self._w = np.empty((capacity, 3))
        self._f = np.empty((capacity, 3))
        self._start = 0
        self._end = 0

    def __len__(self) -> int:
        return self._end - self._start

    def extend(self, x: Samples) -> None:
        m = len(x)
        if self._end + m > len(self._t):
            n = len(self)
            cap = max(2 * (n + m), 1024)
            if cap > len(self._t) or self._start > 0:
                t, w, f = np.empty(cap), np.empty((cap, 3)), np.empty((cap, 3))
                t[:n], w[:n], f[:n] = (
                    self._t[self._start : self._end],
                    self._w[self._start : self._end],
                    self._f[self._start : self._end],
                )
                self._t, self._w, self._f = t, w, f
                self._start, self._end = 0, n
        e = self._end
        self._t[e : e + m], self._w[e : e + m], self._f[e : e + m] = x.t, x.w, x.f
        self._end = e + m

    def drop_front(self, n: int) -> None:
        self._start += min(int(n), len(self))

    def cut(self, i: int) -> Samples:
        """Remove and return the samples from position ``i`` on (copies)."""
        a = self._start + int(i)
        out = Samples(self._t[a : self._end].copy(), self._w[a : self._end].copy(), self._f[a : self._end].copy())
        self._end = max(a, self._start)
        return out


class InertialCore:
    """Strapdown INS (:class:`ins.strapdown.StrapdownStepper`) with the 15-state error covariance of
    :mod:`ins.error_model` propagated alongside, plus a short replay buffer for late fixes.

    The INS integrates bias-corrected samples ``omega = omega_meas - b_g_est``, ``f = f_meas - b_a_est``. The
    covariance is propagated in steps of at most ``cov_step_s`` s: ``F, G, Qc`` at the current state with the
    attitude and navigation-frame specific force averaged over the step (:func:`step_matrices`; the end-of-step
    attitude is wrong by the whole turn of the step), ``(Phi, Qd) = discretize(F, G, Qc, dt)`` over exactly that
    step (Van Loan), then
    :meth:`_predict_cov` (``Phi P Phi^T + Qd`` here; the UKF overrides it with its unscented prediction).
    (:func:`discretize_fast` is error_model's Van Loan formula with a product-only matrix exponential.)
    At every covariance step a checkpoint (state, covariance, biases, sample count, fault stack) is kept for
    ``buffer_s`` s with the raw samples since the oldest one; :meth:`_rewind` restores the last checkpoint before a past time and returns
    the samples to replay, so a late fix is applied at its own time (re-propagation).

    Optional states (:class:`ExtraStates`; ``scale_factors``, ``scale_factor_tau_s``, ``map_bias_sigma_m``,
    ``map_bias_tau_s``, ``map_bias_sources``): the layout grows to ``self.layout`` (21, 17 or 23 states), the
    samples are corrected ``f = (f_meas - b_a_est) / (1 + s_a_est)`` (gyro likewise), the map-bias estimate decays
    as its Gauss-Markov mean between steps; the initial covariance may be 15x15 (the optional priors are appended)
    or full size. Without them everything is the 15-state filter, bit for bit.
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
        scale_factors: bool = False,
        scale_factor_tau_s: float | None = None,
        map_bias_sigma_m: float | None = None,
        map_bias_tau_s: float | None = None,
        map_bias_sources: tuple[str, ...] | None = None,
        integrity_risk: float = DEFAULT_INTEGRITY_RISK,
    ) -> None:
        from ...ins.strapdown import AttitudeSums, StrapdownStepper
        from .integrity import FaultMonitor

        self.extra = ExtraStates.from_options(
            noise, scale_factors=scale_factors, scale_factor_tau_s=scale_factor_tau_s,
            map_bias_sigma_m=map_bias_sigma_m, map_bias_tau_s=map_bias_tau_s, map_bias_sources=map_bias_sources,
        )  # fmt: skip
        self.layout = self.extra.layout
        n = self.n_states = self.layout.size
        P0 = np.asarray(init.P, dtype=float)
        if P0.shape == (15, 15) and n > 15:
            P0 = self.extra.prior(P0)
        if P0.shape != (n, n):
            raise InputError(f"initial covariance must be 15x15 (LAYOUT_15) or {n}x{n}, got {P0.shape}")
        if not np.all(np.isfinite(P0)):
            raise InputError("initial covariance holds non-finite values")
        if not (cov_step_s > 0 and buffer_s >= 0):
            raise InputError(f"cov_step_s must be > 0 and buffer_s >= 0, got {cov_step_s}, {buffer_s}")
        self.noise = noise
        #: the protection level's monitor; without fixes (free inertial) the HPL is the covariance's alone
        self.monitor = FaultMonitor(None, integrity_risk=integrity_risk)
        self.cov_step_s = float(cov_step_s)
        self.buffer_s = float(buffer_s)
        self._init_nav = init.nav
        self._P0 = symmetrise(P0, 0.0)
        self._altitude_hold = altitude_hold
        self._raw: list[Samples] = []  # every sample once, in chunks (keep_history only)
        self._fix_log: list[tuple] = []  # accepted fixes (keep_history only): (t, fix, height_m, height_sigma_m)
        self._stepper = StrapdownStepper(init.nav, altitude_hold=altitude_hold)
        self._sums = AttitudeSums()
        self._P = symmetrise(P0, 0.0)
        #: the fault stack (k, n, n): bounds on the state error an undetected fault on a recent accepted fix may
        #: have left, as it evolves since (:func:`integrity.fault_update`; the HPL's fault margin)
        self._M = np.zeros((1, n, n))
        self._b_a = np.zeros(3)
        self._b_g = np.zeros(3)
        self._s_a = np.zeros(3)  # scale-factor estimates (dimensionless; used with extra.scale_factors only)
        self._s_g = np.zeros(3)
        self._b_map = np.zeros(2)  # map-bias estimate, north/east m (with extra.map_bias_sigma_m only)
        self._t_cov = float(init.nav.t)
        self._clear_step_sums()
        self._samples = _SampleBuffer()
        self._n_dropped = 0  # samples dropped from the front of the buffer
        self._checkpoints: list[tuple] = []
        self._checkpoint()
        # smoother history, one entry per covariance step:
        # [t, Phi (from the previous step), P-, P+, dx, nav+, b_a, b_g, aux (all estimates behind the layout's 9:n)]
        self._history: list[list] | None = (
            [
                [
                    self.t,
                    None,
                    self._P.copy(),
                    self._P.copy(),
                    np.zeros(n),
                    self._stepper.nav,
                    self._b_a.copy(),
                    self._b_g.copy(),
                    self._aux(),
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

    def _aux(self) -> FloatArray:
        """The estimates behind the error states 9:n of the layout: ``[b_a, b_g(, s_a, s_g)(, b_map)]``."""
        parts = [self._b_a, self._b_g]
        if self.extra.scale_factors:
            parts += [self._s_a, self._s_g]
        if self.extra.map_bias_sigma_m is not None:
            parts.append(self._b_map)
        return np.concatenate(parts)

    def _set_aux(self, aux: FloatArray) -> None:
        aux = np.asarray(aux, dtype=float)
        self._b_a, self._b_g = aux[0:3].copy(), aux[3:6].copy()
        if self.extra.scale_factors:
            self._s_a, self._s_g = aux[6:9].copy(), aux[9:12].copy()
        if self.extra.map_bias_sigma_m is not None:
            self._b_map = aux[-2:].copy()

    def _corrected(self, w: FloatArray, f: FloatArray, aux: FloatArray) -> tuple[FloatArray, FloatArray]:
        """IMU sample corrected by the estimates ``aux`` (:meth:`_aux` order): ``omega = (w - b_g) / (1 + s_g)``,
        ``f = (f - b_a) / (1 + s_a)`` (no division without scale-factor states)."""
        f_c, w_c = f - aux[0:3], w - aux[3:6]
        if self.extra.scale_factors:
            f_c, w_c = f_c / (1.0 + aux[6:9]), w_c / (1.0 + aux[9:12])
        return w_c, f_c

    def _propagate_aux(self, aux: FloatArray, dt: float) -> FloatArray:
        """The estimates ``aux`` after ``dt`` s: constant, but the map bias decays as its Gauss-Markov mean."""
        if self.extra.map_bias_sigma_m is None:
            return aux
        out = np.array(aux, dtype=float)
        out[-2:] *= self.extra.decay(dt)
        return out

    def _fix_rows(self, fix: Fix) -> FloatArray:
        """``H`` (2, n) of a north/east fix on the error state: ``z = fix - INS - b_map_est = -dp_NE - db_map + v``
        (the map-bias columns only when the fix measures the bias, :meth:`ExtraStates.biased`)."""
        Hm = np.zeros((2, self.n_states))
        Hm[0, 0] = Hm[1, 1] = -1.0
        if self.extra.biased(fix):
            b = self.layout["b_map"].start
            Hm[0, b] = Hm[1, b + 1] = -1.0
        return Hm

    def _checkpoint(self) -> None:
        self._checkpoints.append(
            (self.t, self._stepper.nav, self._P.copy(), self._aux(), self._n_dropped + len(self._samples),
             self._M.copy())
        )  # fmt: skip
        t_old = self.t - self.buffer_s
        while len(self._checkpoints) > 1 and self._checkpoints[1][0] <= t_old:
            self._checkpoints.pop(0)
        drop = self._checkpoints[0][4] - self._n_dropped
        if drop > 0:
            self._samples.drop_front(drop)
            self._n_dropped += drop

    def _clear_step_sums(self) -> None:
        """Start a covariance step: integrals of ``C_nb`` and ``C_nb f_b`` (navigation-frame specific force) over
        it (with scale factors also ``C_nb diag(f_b)`` and ``C_nb diag(omega_ib_b)``), and its length; the attitude
        at the step start is re-read from the INS (it may have been corrected). :class:`ins.strapdown.AttitudeSums`."""
        self._sums.clear()

    def _predict_cov(self, Phi: FloatArray, Qd: FloatArray) -> None:
        self._P = symmetrise(Phi @ self._P @ Phi.T + Qd, 0.0)

    def _advance_cov(self) -> None:
        """Propagate the covariance from its time to the INS time (one step) and checkpoint."""
        dt = self.t - self._t_cov
        if dt <= 0.0:
            return
        sm = self._sums
        Phi, Qd = step_matrices(self._stepper.nav, sm.C_sum, sm.fn_sum, sm.dt_sum, dt, self.noise, self.extra,
                                sm.Cf_sum, sm.Cw_sum)  # fmt: skip
        held = np.diag(self._P)[list(_HELD)].copy() if self._altitude_hold is not None else None
        self._predict_cov(Phi, Qd)
        if len(self._M) > 1 or self._M.any():  # the faults follow the error dynamics without the process noise
            self._M = Phi @ self._M @ Phi.T
        if held is not None:  # the INS holds the altitude: no down error growth (the unstable vertical channel,
            # e-folding every ~570 s, would otherwise blow the covariance up and leak into the horizontal)
            self._P[_HELD, :] = 0.0
            self._P[:, _HELD] = 0.0
            self._P[_HELD, _HELD] = held
            self._M[:, _HELD, :] = 0.0
            self._M[:, :, _HELD] = 0.0
        if self.extra.map_bias_sigma_m is not None:
            self._b_map = self._b_map * self.extra.decay(dt)
        if self._history is not None:
            self._history.append([self.t, Phi, self._P.copy(), self._P.copy(), np.zeros(self.n_states),
                                  self._stepper.nav, self._b_a.copy(), self._b_g.copy(), self._aux()])  # fmt: skip
        self._t_cov = self.t
        self._clear_step_sums()
        self._checkpoint()

    def _run(
        self, x: Samples, holds: FloatArray | None = None, q_out: FloatArray | None = None, *, buffer: bool = True
    ) -> None:
        """Mechanise the raw samples ``x`` (after the current time, finite), with a covariance step wherever one
        ends (``cov_step_s``): bias (and scale-factor) correction, then the compiled stepper with the attitude
        integrals (:meth:`ins.strapdown.StrapdownStepper.run_with_sums`; the same numbers sample by sample or in
        one call). ``holds`` (m,): the altitude hold of each sample (default: the current one); ``q_out`` (m,4):
        the attitude after each sample; ``buffer``: keep the samples for a rewind (not the first part of a cut
        sample)."""
        m = len(x)
        if m == 0:
            return
        if self.extra.scale_factors:
            w_c, f_c = self._corrected(x.w, x.f, self._aux())
        else:
            w_c, f_c = x.w - self._b_g, x.f - self._b_a
        if q_out is None:
            q_out = np.empty((m, 4))
        i = 0
        while i < m:  # a covariance step changes no estimate used in the correction
            n = self._stepper.run_with_sums(
                x.t[i:], w_c[i:], f_c[i:], self._sums, holds=None if holds is None else holds[i:],
                t_cov=self._t_cov, cov_step_s=self.cov_step_s, scale_sums=self.extra.scale_factors, q_out=q_out[i:],
            )  # fmt: skip
            if buffer:
                self._samples.extend(x[i : i + n])
            i += n
            if i < m or x.t[m - 1] - self._t_cov >= self.cov_step_s - 1e-9:
                self._advance_cov()

    def _step(self, t: float, w: FloatArray, f: FloatArray) -> None:
        """One raw sample ending at ``t`` (:meth:`_run`), not buffered."""
        self._run(
            Samples(np.array([float(t)]), np.asarray(w, float).reshape(1, 3), np.asarray(f, float).reshape(1, 3)),
            buffer=False,
        )

    def _rewind(self, t_past: float) -> Samples | None:
        """Restore the last checkpoint at or before ``t_past`` and re-step the buffered samples up to ``t_past``
        (cutting the straddling one); returns the samples to replay after it, or None if ``t_past`` is older
        than the buffer."""
        cps = [c for c in self._checkpoints if c[0] <= t_past + 1e-9]
        if not cps:
            return None
        t_c, nav, P, aux, n_at, M = cps[-1]
        samples = self._samples.cut(n_at - self._n_dropped)
        while self._checkpoints and self._checkpoints[-1][0] > t_c:
            self._checkpoints.pop()
        self._checkpoints.pop()  # re-created below
        self._stepper.reset(nav)
        self._P = P.copy()
        self._M = M.copy()
        self._set_aux(aux)
        self._t_cov = t_c
        if self._history is not None:
            while len(self._history) > 1 and self._history[-1][0] > t_c + 1e-9:
                self._history.pop()
        self._clear_step_sums()
        self._checkpoint()
        return self._step_until(samples, t_past)

    def _step_until(self, samples: Samples, t_target: float) -> Samples:
        """Step through the samples at or before ``t_target``, then the first part of the straddling one (up to
        ``t_target``); returns the samples still to replay (from the straddling one on)."""
        k = int(np.searchsorted(samples.t, t_target + 1e-9, side="right"))
        self._run(samples[:k])
        rest = samples[k:]
        if len(rest) and self.t < t_target - 1e-9:
            self._step(t_target, rest.w[0], rest.f[0])  # the straddling sample, first part (buffered in full later)
        return rest

    def _replay(self, samples: Samples) -> None:
        self._run(samples)

    def _fault_update(self, A: FloatArray, P_prior: FloatArray, P_post: FloatArray, threshold: float) -> None:
        """An accepted update (full covariances before and after it, ``A = I - K H``, the gate's chi-square
        ``threshold``; inf or 0 for trusted fixes) moves the fault stack (:func:`integrity.fault_update`)."""
        from .integrity import fault_update

        self._M = fault_update(self._M, A, P_prior, P_post, threshold)

    def fault_margin(self) -> float:
        """The HPL's fault-detection margin now (m): the largest ``sqrt(lambda_max)`` of the fault stack's
        north/east blocks (:func:`integrity.fault_margin`; as of the last covariance step, :meth:`estimate`)."""
        from .integrity import fault_margin

        return fault_margin(self._M)

    # ------------------------------------------------------------------------------------------ Fuser API
    def propagate(self, imu: ImuBatch, *, altitude_hold: FloatArray | None = None, attitudes: bool = False):
        """Mechanise IMU samples after the current time (rates over ``(t[k-1], t[k]]``, body FRD); samples at or
        before it are skipped. Non-finite samples or non-increasing times raise :class:`InputError`.
        ``altitude_hold`` (N,): the altitude hold (m) of each sample instead of the current one (as
        :meth:`set_altitude_hold` before each; only for a fuser built with ``altitude_hold``); ``attitudes``:
        return the INS attitude ``q_nb`` (M,4) after each sample mechanised (else None)."""
        if len(imu) == 0:
            return np.zeros((0, 4)) if attitudes else None
        if not (np.all(np.isfinite(imu.gyro_b)) and np.all(np.isfinite(imu.accel_b)) and np.all(np.isfinite(imu.t))):
            raise InputError(f"{type(self).__name__}.propagate: IMU batch holds non-finite values")
        d = np.diff(imu.t)
        if np.any(d <= 0):
            k = int(np.argmax(d <= 0)) + 1
            raise InputError(f"{type(self).__name__}.propagate: IMU time not increasing at sample {k}: t={imu.t[k]!r}")
        check_time(float(imu.t[-1]), self.t, f"{type(self).__name__}.propagate")
        k0 = int(np.searchsorted(imu.t, self.t + 1e-9, side="right"))
        x = Samples(
            np.asarray(imu.t[k0:], float), np.asarray(imu.gyro_b[k0:], float), np.asarray(imu.accel_b[k0:], float)
        )
        holds = None
        if altitude_hold is not None:
            if self._altitude_hold is None:
                raise InputError("propagate: altitude_hold given to a fuser built without altitude_hold")
            holds = np.asarray(altitude_hold, float)[k0:]
            if len(holds) != len(x) or not np.all(np.isfinite(holds)):
                raise InputError("propagate: altitude_hold must hold one finite height (m) per IMU sample")
        if self._history is not None and len(x):
            self._raw.append(Samples(x.t.copy(), x.w.copy(), x.f.copy()))
        q_out = np.empty((len(x), 4))
        self._run(x, holds, q_out)
        if holds is not None and len(holds):
            self._altitude_hold = float(holds[-1])
        return q_out if attitudes else None

    @property
    def holds_altitude(self) -> bool:
        """True when the vertical channel is clamped (``altitude_hold`` given at construction)."""
        return self._altitude_hold is not None

    @property
    def altitude_hold_m(self) -> float | None:
        """The height (m) the vertical channel is clamped to now (None: free)."""
        return self._altitude_hold

    def set_altitude_hold(self, h_m: float) -> None:
        """Move the vertical-channel clamp to ``h_m`` (m above the ellipsoid) from the next IMU sample on: a height
        aid such as :mod:`magnav_ins.mavlink.baro` moves it as the vehicle climbs. Only for a fuser built with
        ``altitude_hold``; a late fix that re-runs the INS from a checkpoint uses the latest height."""
        if self._altitude_hold is None:
            raise InputError("set_altitude_hold: this fuser was built without altitude_hold (free vertical channel)")
        if not np.isfinite(h_m):
            raise InputError(f"set_altitude_hold: height must be finite, got {h_m!r}")
        self._altitude_hold = float(h_m)
        self._stepper.set_altitude_hold(float(h_m))

    def estimate(self) -> NavEstimate:
        """The current INS state and its error covariance (propagated up to now) in ``self.layout`` (LAYOUT_15
        unless optional states were asked for), with the horizontal protection level of :attr:`monitor`."""
        self._advance_cov()
        P = self._P.copy()
        m = self.monitor
        return NavEstimate(self._stepper.nav, P, self.layout, m.hpl(P[0:2, 0:2], self.fault_margin()), m.integrity_risk)

    @property
    def bias(self) -> tuple[FloatArray, FloatArray]:
        """Current accelerometer (m/s^2) and gyro (rad/s) bias estimates, body FRD."""
        return self._b_a.copy(), self._b_g.copy()

    @property
    def scale_factor(self) -> tuple[FloatArray, FloatArray]:
        """Current accelerometer and gyro scale-factor estimates (dimensionless, body FRD; zeros without the
        ``scale_factors`` states)."""
        return self._s_a.copy(), self._s_g.copy()

    @property
    def map_bias(self) -> FloatArray:
        """Current map-bias estimate, north/east m (zeros without the map-bias state)."""
        return self._b_map.copy()

    def _record_update(self, dx: FloatArray) -> None:
        """Mark the last covariance step as updated by ``dx`` (error estimate before the reset). Several updates at
        one step (fixes with the same time) add up: each is relative to the state the previous one corrected, so
        the step's total correction of its predicted state is their sum (to first order)."""
        if self._history is not None:
            h = self._history[-1]
            h[3], h[4], h[5], h[6], h[7], h[8] = (
                self._P.copy(),
                h[4] + dx,
                self._stepper.nav,
                self._b_a.copy(),
                self._b_g.copy(),
                self._aux(),
            )

    def _record_inflated_prior(self) -> None:
        """The online filter inflated its covariance before an update (recovery): the smoother must use that
        inflated prior as the step's predicted covariance, or its gain ``P+ Phi^T (P-)^-1`` mixes two priors
        (only for the first update of a step; a later one inflates a posterior)."""
        if self._history is not None and not np.any(self._history[-1][4]):
            self._history[-1][2] = self._P.copy()

    def _record_fix(self, fix: Fix, height_m: float | None, height_sigma_m: float | None) -> None:
        """Log an accepted fix for the relinearised smoother passes (keep_history only)."""
        if self._history is not None:
            self._fix_log.append((float(fix.t), fix, height_m, height_sigma_m))

    def smooth(self, iterations: int = 1) -> tuple[NavTrajectory, FloatArray]:
        """Rauch-Tung-Striebel smoothing of the recorded run (``keep_history=True``).

        Pass 1, in closed-loop error-state form: with ``e`` the error of the filter's corrected state at each
        covariance step (all ``self.layout`` states), ``e_s(k) = C_k (e_s(k+1) + dx_{k+1})``, ``C_k = P+_k Phi_k^T (P-_{k+1})^-1``,
        ``P_s(k) = P+_k + C_k (P_s(k+1) - P-_{k+1}) C_k^T`` (Rauch, Tung & Striebel 1965; ``dx`` is the update's
        error estimate before its reset, zero without a fix). It is linearised about the filter's trajectory,
        which drifts between sparse fixes. Each further pass (``iterations`` > 1) relinearises about the previous
        smoothed trajectory and biases (iterated extended Kalman smoother = Gauss-Newton on the batch problem,
        Bell 1994): :meth:`_relinearised_pass`. Under an altitude hold every pass uses the filter's held model: the
        down position and velocity errors (:data:`_HELD`) are carried unchanged and uncorrelated
        (:func:`_held_transition`, as the covariance prediction holds them) and each smoothed state reports the hold
        in force over its step (height, zero down velocity), as the INS does. Returns the smoothed states at the
        step times and their covariances (N,n,n)."""
        from ...ins.error_model import apply_error

        if self._history is None:
            raise InputError("smooth(): construct the fuser with keep_history=True")
        if int(iterations) < 1:
            raise InputError(f"smooth(): iterations must be >= 1, got {iterations}")
        H = self._history
        n = len(H)
        n_x = self.n_states
        holds = self._holds()
        e = np.zeros(n_x)
        Ps = H[-1][3].copy()
        out_nav = [H[-1][5]]
        out_b = [H[-1][8]]
        out_P = [Ps]
        for k in range(n - 2, -1, -1):
            Phi, Pm1, dx1 = H[k + 1][1], H[k + 1][2], H[k + 1][4]
            if holds is not None:
                Phi = _held_transition(Phi)
            Pp = H[k][3]
            C = np.linalg.solve(Pm1.T, (Pp @ Phi.T).T).T  # Pp Phi^T Pm1^-1
            e = C @ (e + dx1)
            Ps = symmetrise(Pp + C @ (Ps - Pm1) @ C.T, 0.0)
            nav = apply_error(H[k][5], -e[:9])
            out_nav.append(nav if holds is None else _clamped(nav, holds[k]))
            out_b.append(H[k][8] - e[9:n_x])
            out_P.append(Ps)
        out_nav.reverse()
        out_b.reverse()
        out_P.reverse()
        for _ in range(int(iterations) - 1):
            out_nav, out_b, out_P = self._relinearised_pass(out_nav, out_b)
        traj = NavTrajectory(
            np.array([x.t for x in out_nav]), np.array([x.lat for x in out_nav]), np.array([x.lon for x in out_nav]),
            np.array([x.h for x in out_nav]), np.array([x.v_n for x in out_nav]), np.array([x.q_nb for x in out_nav]),
        )  # fmt: skip
        return traj, np.array(out_P)

    def _holds(self) -> list[float] | None:
        """The altitude hold in force at each smoother step (m; None without a hold): the height of the INS state
        recorded there, which the hold clamps (:meth:`set_altitude_hold` may move it during a run)."""
        if self._altitude_hold is None or self._history is None:
            return None
        return [float(h[5].h) for h in self._history]

    def _relinearised_pass(self, nom: list[NavState], b_nom: list[FloatArray]) -> tuple[list, list, list]:
        """One Kalman filter + RTS pass about a nominal trajectory ``nom`` (NavState at each step time) with
        nominal estimates ``b_nom`` ((n-9,) ``[b_a, b_g(, s_a, s_g)(, b_map)]``, :meth:`_aux`, held over the step
        that starts there; the map bias decays as its mean).

        The state is the nominal's error ``e_k = nom_k - truth_k`` (LAYOUT_15). The INS is re-run over each step
        from ``nom_k`` with the samples corrected by ``b_nom_k`` to ``x~_{k+1}``; with the defect
        ``d_{k+1} = x~_{k+1} - nom_{k+1}`` (:func:`ins.error_model.nav_error`; biases ``b_nom_k - b_nom_{k+1}``),
        ``e_{k+1} = Phi_k e_k - d_{k+1} + w_k``, ``(Phi_k, Qd_k)`` from :func:`step_matrices` along the re-run.
        Prior ``e_0 ~ N(nom_0 - init, P0)``. Each logged (accepted) fix: ``z = fix - nom`` (north/east m), ``z = -e[N,E]
        + v`` (with a map bias: ``z = fix - nom - b_map_nom = -e[N,E] - e[b_map] + v``; with a height:
        ``h_src - h_nom = e_D + v``), Joseph update. Then the RTS recursion
        ``m_s(k) = m+_k + C_k (m_s(k+1) - m-_{k+1})`` and the new nominal ``nom_k - m_s(k)``. Recovery
        inflation of the online filter is not repeated (the fixes count at their own noise).

        Altitude hold (:meth:`_holds`: the hold in force at each step, which :meth:`set_altitude_hold` may move):
        the nominal's height and down velocity are set to the hold's, the INS re-run clamps to the step's hold, so
        the held states' defect is zero; their error is propagated as the online filter's covariance holds it
        (``Phi_h``, :func:`_held_transition`). Propagating them as free states instead (the unstable vertical
        channel, with the clamp's jump fed back as a defect at every step) made the smoothed height and down
        velocity run away over a long run and drag the horizontal track (issue 4: 1.6 km after two passes on a
        3,530 s flight)."""
        from ...ins.error_model import apply_error, nav_error
        from ...ins.strapdown import StrapdownStepper

        n = len(nom)
        n_x = self.n_states
        holds = self._holds()
        if holds is not None:
            nom = [_clamped(x, h) for x, h in zip(nom, holds, strict=True)]
        times = np.array([x.t for x in nom])
        T = np.concatenate([r.t for r in self._raw]) if self._raw else np.zeros(0)
        W = np.concatenate([r.w for r in self._raw]) if self._raw else np.zeros((0, 3))
        Fr = np.concatenate([r.f for r in self._raw]) if self._raw else np.zeros((0, 3))
        fixes: dict[int, list] = {}
        for entry in self._fix_log:
            k = int(np.argmin(np.abs(times - entry[0])))
            if abs(times[k] - entry[0]) < 1e-6:
                fixes.setdefault(k, []).append(entry)
        init = self._init_nav if holds is None else _clamped(self._init_nav, holds[0])
        m = np.r_[nav_error(nom[0], init), b_nom[0]]  # the filter starts from zero biases
        P = self._P0.copy()
        m_minus, P_minus, m_plus, P_plus, Phis = [], [], [], [], [None]
        j = int(np.searchsorted(T, times[0] + 1e-9))
        prev: tuple[FloatArray, FloatArray] | None = None
        for k in range(n):
            if k > 0:
                b = b_nom[k - 1]
                st = StrapdownStepper(nom[k - 1], altitude_hold=None if holds is None else holds[k])
                if prev is not None:
                    st.prime(*prev)
                C_sum, fn_sum, sum_dt = np.zeros((3, 3)), np.zeros(3), 0.0
                Cf_sum, Cw_sum = np.zeros((3, 3)), np.zeros((3, 3))
                C0 = _dcm(nom[k - 1].q_nb)
                while j < len(T):
                    t_end = min(T[j], times[k])
                    dt = t_end - st.t
                    if dt > 1e-12:
                        w_c, f_c = self._corrected(W[j], Fr[j], b)
                        st.step_rate(t_end, w_c, f_c)
                        C1 = _dcm(st.nav.q_nb)
                        C_mid = 0.5 * (C0 + C1)
                        C0 = C1
                        C_sum += C_mid * dt
                        fn_sum += C_mid @ f_c * dt
                        if self.extra.scale_factors:
                            Cf_sum += C_mid * f_c * dt
                            Cw_sum += C_mid * w_c * dt
                        sum_dt += dt
                        prev = (w_c * dt, f_c * dt)
                    if T[j] <= times[k] + 1e-9:
                        j += 1
                    if t_end >= times[k] - 1e-9:
                        break
                end = st.nav
                dt_k = times[k] - times[k - 1]
                Phi, Qd = step_matrices(end, C_sum, fn_sum, sum_dt, dt_k, self.noise, self.extra, Cf_sum, Cw_sum)
                d = np.r_[nav_error(end, nom[k]), self._propagate_aux(b, dt_k) - b_nom[k]]
                P_held = np.diag(P)[list(_HELD)].copy()
                P = symmetrise(Phi @ P @ Phi.T + Qd, 0.0)
                if holds is not None:  # the online filter's held prediction (_advance_cov), its transition Phi_h
                    P[_HELD, :] = 0.0
                    P[:, _HELD] = 0.0
                    P[_HELD, _HELD] = P_held
                    Phi = _held_transition(Phi)
                    d[list(_HELD)] = 0.0  # the re-run and the nominal share the hold (zero up to rounding)
                m = Phi @ m - d
                Phis.append(Phi)
            m_minus.append(m.copy())
            P_minus.append(P.copy())
            for _, fix, h_m, h_sig in fixes.get(k, []):
                z = residual_ne(fix, nom[k])
                if self.extra.biased(fix):
                    z = z - b_nom[k][-2:]
                Hm = self._fix_rows(fix)
                R = np.asarray(fix.cov_ne, float)
                if h_m is not None:
                    z = np.r_[z, float(h_m) - nom[k].h]
                    Hm = np.vstack([Hm, np.eye(n_x)[2]])
                    R = np.block([[R, np.zeros((2, 1))], [np.zeros((1, 2)), np.array([[float(h_sig) ** 2]])]])
                S = Hm @ P @ Hm.T + R
                K = np.linalg.solve(S, Hm @ P).T
                m = m + K @ (z - Hm @ m)
                IKH = np.eye(n_x) - K @ Hm
                P = symmetrise(IKH @ P @ IKH.T + K @ R @ K.T, 0.0)
            m_plus.append(m.copy())
            P_plus.append(P.copy())

        def corrected(k: int, ms: FloatArray) -> NavState:
            nav = apply_error(nom[k], -ms[:9])
            return nav if holds is None else _clamped(nav, holds[k])

        ms, Ps = m_plus[-1], P_plus[-1]
        out_nav, out_b, out_P = [corrected(n - 1, ms)], [b_nom[-1] - ms[9:n_x]], [Ps]
        for k in range(n - 2, -1, -1):
            Pm1 = P_minus[k + 1]
            C = np.linalg.solve(Pm1.T, (P_plus[k] @ Phis[k + 1].T).T).T
            ms = m_plus[k] + C @ (ms - m_minus[k + 1])
            Ps = symmetrise(P_plus[k] + C @ (Ps - Pm1) @ C.T, 0.0)
            out_nav.append(corrected(k, ms))
            out_b.append(b_nom[k] - ms[9:n_x])
            out_P.append(Ps)
        return out_nav[::-1], out_b[::-1], out_P[::-1]
