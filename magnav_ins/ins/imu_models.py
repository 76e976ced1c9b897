"""IMU grade presets and truth error injection.

Sensor model (Groves 2013 eq. 4.16-4.17, rate form, body FRD)::

    f_meas     = f_true     + b_a(t) + M_a f_true     + w_a
    omega_meas = omega_true + b_g(t) + M_g omega_true + w_g

with ``b(t) = b_turn_on + b_gm(t)`` (a random constant drawn at switch-on plus a first-order Gauss-Markov bias,
``db/dt = -b/tau + w``, stationary 1-sigma ``sigma``, Groves eq. 14.83 / Gelb 1974 Table 3.8-1), ``M`` = diagonal
scale-factor errors plus off-diagonal misalignment/cross-coupling, and ``w`` white noise of root-PSD ``N``
(angle random walk for gyros, velocity random walk for accelerometers). A rate-type sample is the mean over its
interval, so its white-noise part has standard deviation ``N / sqrt(dt)``.

Everything in :class:`ImuGrade` is SI: rad/s, rad/sqrt(s) (= rad/s/sqrt(Hz)), m/s^2, m/s/sqrt(s)
(= m/s^2/sqrt(Hz)), s, Hz, dimensionless scale factors and misalignments (rad). Per-axis quantities are
``(x, y, z)`` body-axis tuples, so "horizontal" values sit on x, y and "vertical" ones on z (for a level vehicle).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np

from ..core import units as u
from ..core.errors import ConfigError
from ..core.types import FloatArray, ImuBatch

Vec3 = tuple[float, float, float]
INF = math.inf


def _v(x: float, y: float | None = None, z: float | None = None) -> Vec3:
    return (float(x), float(x if y is None else y), float(x if z is None else z))


@dataclass(frozen=True)
class ImuGrade:
    """Error parameters of an IMU (1-sigma values, SI units, per body axis x, y, z where a tuple).

    Attributes
    ----------
    gyro_bias_sigma : Vec3 rad/s, stationary 1-sigma of the Gauss-Markov gyro bias.
    gyro_bias_tau : float s, its correlation time (``inf``: the GM part is a random constant).
    gyro_turn_on_sigma : Vec3 rad/s, 1-sigma of the constant (switch-on) gyro bias.
    arw : Vec3 rad/sqrt(s), angle random walk (gyro white-noise root-PSD, rad/s/sqrt(Hz)).
    gyro_scale_sigma : float, dimensionless scale-factor error 1-sigma.
    gyro_misalignment_sigma : float rad, 1-sigma of each off-diagonal cross-coupling term.
    accel_bias_sigma, accel_bias_tau, accel_turn_on_sigma : as for the gyro, in m/s^2 and s.
    vrw : Vec3 m/s/sqrt(s), velocity random walk (accelerometer white-noise root-PSD, m/s^2/sqrt(Hz)).
    accel_scale_sigma, accel_misalignment_sigma : dimensionless, rad.
    rate_hz : float Hz, nominal sample rate.
    source : where the numbers come from.
    """

    name: str
    gyro_bias_sigma: Vec3
    gyro_bias_tau: float
    gyro_turn_on_sigma: Vec3
    arw: Vec3
    gyro_scale_sigma: float
    gyro_misalignment_sigma: float
    accel_bias_sigma: Vec3
    accel_bias_tau: float
    accel_turn_on_sigma: Vec3
    vrw: Vec3
    accel_scale_sigma: float
    accel_misalignment_sigma: float
    rate_hz: float
    source: str

    def __post_init__(self) -> None:
        for f in fields(self):
            val = getattr(self, f.name)
            if f.name in ("name", "source"):
                continue
            vals = val if isinstance(val, tuple) else (val,)
            if f.name.endswith("_tau"):
                ok = all(v > 0 for v in vals)
            else:
                ok = all(math.isfinite(v) and v >= 0 for v in vals)
            if not ok:
                raise ConfigError(f"IMU grade {self.name!r}: {f.name} must be non-negative (tau > 0), got {val}")
        if not self.rate_hz > 0:
            raise ConfigError(f"IMU grade {self.name!r}: rate_hz must be > 0, got {self.rate_hz}")

    # array views -------------------------------------------------------------------------------------------
    def arr(self, field_name: str) -> FloatArray:
        """A per-axis field as a (3,) float array."""
        return np.asarray(getattr(self, field_name), dtype=float)

    @property
    def gyro_bias_total_sigma(self) -> FloatArray:
        """(3,) rad/s, 1-sigma of turn-on + Gauss-Markov gyro bias."""
        return np.hypot(self.arr("gyro_turn_on_sigma"), self.arr("gyro_bias_sigma"))

    @property
    def accel_bias_total_sigma(self) -> FloatArray:
        """(3,) m/s^2, 1-sigma of turn-on + Gauss-Markov accelerometer bias."""
        return np.hypot(self.arr("accel_turn_on_sigma"), self.arr("accel_bias_sigma"))


_STORMS = "Storms 2009, Table 2.2 (after Titterton & Weston via ref. [18])"
_WANG = "Wang et al. 2022, Table 1 (after Jekeli 2005); biases as random constants, no scale/misalignment given"

#: The presets. Numbers are written in the units of their source and converted with :mod:`magnav_ins.core.units`.
GRADES: dict[str, ImuGrade] = {
    # MEMS consumer IMU: TDK InvenSense ICM-20948 data sheet DS-000189 rev. 1.3, Table 1 (gyro rate noise
    # spectral density 0.015 deg/s/sqrt(Hz)) and Table 2 (accel noise 230 ug/sqrt(Hz), zero-g initial tolerance
    # +-25 mg taken as 1-sigma, sensitivity tolerance +-0.5 %, cross-axis +-2 %). The gyro zero-rate offset
    # (+-5 deg/s) is assumed removed by an at-rest start-up calibration leaving 0.05 deg/s (assumption), and the
    # gyro scale factor 1 % (assumption: typical MEMS sensitivity tolerance).
    "consumer": ImuGrade(
        name="consumer",
        gyro_bias_sigma=_v(0.0),
        gyro_bias_tau=INF,
        gyro_turn_on_sigma=_v(0.05 * u.DEG_TO_RAD),
        arw=_v(0.015 * u.DEG_TO_RAD),  # deg/s/sqrt(Hz) -> rad/s/sqrt(Hz)
        gyro_scale_sigma=0.01,
        gyro_misalignment_sigma=0.02,
        accel_bias_sigma=_v(0.0),
        accel_bias_tau=INF,
        accel_turn_on_sigma=_v(25e3 * u.MICRO_G_TO_MPS2),
        vrw=_v(230.0 * u.MICRO_G_TO_MPS2),
        accel_scale_sigma=0.005,
        accel_misalignment_sigma=0.02,
        rate_hz=100.0,
        source="TDK InvenSense ICM-20948 data sheet DS-000189 rev. 1.3 Tables 1-2; gyro residual bias and scale "
        "factor assumed (see imu_models.py)",
    ),
    "commercial": ImuGrade(
        name="commercial",
        gyro_bias_sigma=_v(1800.0 * u.DEG_PER_H_TO_RAD_PER_S),
        gyro_bias_tau=1.0 * u.HOUR_TO_S,
        gyro_turn_on_sigma=_v(0.0),
        arw=_v(2.23 * u.DEG_PER_SQRT_H_TO_RAD_PER_SQRT_S),
        gyro_scale_sigma=10000.0 * u.PPM,
        gyro_misalignment_sigma=0.0,
        accel_bias_sigma=_v(0.196),
        accel_bias_tau=1.0 * u.HOUR_TO_S,
        accel_turn_on_sigma=_v(0.0),
        vrw=_v(0.261 * u.MPS_PER_SQRT_H_TO_MPS_PER_SQRT_S),
        accel_scale_sigma=10000.0 * u.PPM,
        accel_misalignment_sigma=0.0,
        rate_hz=1.0 / 5.0e-3,
        source=_STORMS + ", Crista IMU",
    ),
    "tactical": ImuGrade(
        name="tactical",
        gyro_bias_sigma=_v(1.0 * u.DEG_PER_H_TO_RAD_PER_S),
        gyro_bias_tau=1.0 * u.HOUR_TO_S,
        gyro_turn_on_sigma=_v(0.0),
        arw=_v(0.3 * u.DEG_PER_SQRT_H_TO_RAD_PER_SQRT_S),
        gyro_scale_sigma=150.0 * u.PPM,
        gyro_misalignment_sigma=0.0,
        accel_bias_sigma=_v(0.0098),
        accel_bias_tau=1.0 * u.HOUR_TO_S,
        accel_turn_on_sigma=_v(0.0),
        vrw=_v(0.57 * u.MPS_PER_SQRT_H_TO_MPS_PER_SQRT_S),
        accel_scale_sigma=300.0 * u.PPM,
        accel_misalignment_sigma=0.0,
        rate_hz=1.0 / 10.0e-3,
        source=_STORMS + ", Honeywell HG-1700",
    ),
    "navigation": ImuGrade(
        name="navigation",
        gyro_bias_sigma=_v(0.0015 * u.DEG_PER_H_TO_RAD_PER_S),
        gyro_bias_tau=1.0 * u.HOUR_TO_S,
        gyro_turn_on_sigma=_v(0.0),
        arw=_v(0.002 * u.DEG_PER_SQRT_H_TO_RAD_PER_SQRT_S),
        gyro_scale_sigma=5.0 * u.PPM,
        gyro_misalignment_sigma=0.0,
        accel_bias_sigma=_v(2.45e-4),
        accel_bias_tau=1.0 * u.HOUR_TO_S,
        accel_turn_on_sigma=_v(0.0),
        vrw=_v(0.0143 * u.MPS_PER_SQRT_H_TO_MPS_PER_SQRT_S),
        accel_scale_sigma=100.0 * u.PPM,
        accel_misalignment_sigma=0.0,
        rate_hz=1.0 / 3.906e-3,
        source=_STORMS + ", Honeywell H764-G",
    ),
    # Wang Table 1, precision accelerometer and gyroscope (PCAG): horizontal (x, y) and vertical (z) values.
    "precision": ImuGrade(
        name="precision",
        gyro_bias_sigma=_v(0.0),
        gyro_bias_tau=INF,
        gyro_turn_on_sigma=_v(2e-5 * u.DEG_PER_H_TO_RAD_PER_S, None, 1e-3 * u.DEG_PER_H_TO_RAD_PER_S),
        arw=_v(
            1e-3 * u.DEG_PER_H_PER_SQRT_HZ_TO_RAD_PER_S_PER_SQRT_HZ,
            None,
            3e-2 * u.DEG_PER_H_PER_SQRT_HZ_TO_RAD_PER_S_PER_SQRT_HZ,
        ),
        gyro_scale_sigma=0.0,
        gyro_misalignment_sigma=0.0,
        accel_bias_sigma=_v(0.0),
        accel_bias_tau=INF,
        accel_turn_on_sigma=_v(2e-6, None, 2.5e-8),
        vrw=_v(8e-5, None, 1.6e-6),
        accel_scale_sigma=0.0,
        accel_misalignment_sigma=0.0,
        rate_hz=100.0,
        source=_WANG + " (PCAG); rate assumed 100 Hz",
    ),
    # Wang Table 1, quantum accelerometer with precision gyroscope (QAPCG).
    "quantum": ImuGrade(
        name="quantum",
        gyro_bias_sigma=_v(0.0),
        gyro_bias_tau=INF,
        gyro_turn_on_sigma=_v(2e-5 * u.DEG_PER_H_TO_RAD_PER_S, None, 1e-3 * u.DEG_PER_H_TO_RAD_PER_S),
        arw=_v(
            1e-3 * u.DEG_PER_H_PER_SQRT_HZ_TO_RAD_PER_S_PER_SQRT_HZ,
            None,
            3e-2 * u.DEG_PER_H_PER_SQRT_HZ_TO_RAD_PER_S_PER_SQRT_HZ,
        ),
        gyro_scale_sigma=0.0,
        gyro_misalignment_sigma=0.0,
        accel_bias_sigma=_v(0.0),
        accel_bias_tau=INF,
        accel_turn_on_sigma=_v(1e-8),
        vrw=_v(3e-8),
        accel_scale_sigma=0.0,
        accel_misalignment_sigma=0.0,
        rate_hz=100.0,
        source=_WANG + " (QAPCG: quantum accelerometer, precision gyroscope); rate assumed 100 Hz",
    ),
    # Autopilot MEMS IMU (Pixhawk-class flight controllers: ICM-42688-P, ICM-20602, BMI088), as the companion
    # computer receives it in HIGHRES_IMU: TDK InvenSense ICM-42688-P data sheet DS-000347 rev. 1.6, Table 1 (gyro
    # rate noise spectral density 0.0028 deg/s/sqrt(Hz), sensitivity tolerance +-0.5 %, ZRO variation over
    # temperature +-0.005 deg/s/degC) and Table 2 (accel noise 70 ug/sqrt(Hz), zero-g change over temperature
    # +-0.15 mg/degC, sensitivity +-0.5 %, cross-axis +-2 %). Assumptions, stated because a data sheet cannot give
    # them: the autopilot's own start-up calibrations (ArduPilot INS_GYR_CAL, the six-position accelerometer
    # calibration, the board's mounting) leave turn-on residuals of 0.05 deg/s and 10 mg, accelerometer scale
    # factors of 0.2 % and cross-couplings of 0.3 % (accelerometer) and 0.5 % (gyro, not calibrated), and the gyro
    # scale factor its data-sheet 0.5 %; in flight the bias wanders with temperature (Gauss-Markov, tau 600 s) by
    # 0.01 deg/s and 1 mg, a 2-7 degC change of an IMU held at a set temperature (ArduPilot BRD_HEAT_TARG; an
    # unheated board sees 20 degC: ten times more); the white noise is the data sheet's (motor vibration adds to it
    # on a real airframe: fit it from a flight log if the filter's NEES says so). The Earth's rate (0.004 deg/s),
    # which simulators such as ArduPilot SITL leave out of their gyros, is inside the turn-on residual.
    "autopilot": ImuGrade(
        name="autopilot",
        gyro_bias_sigma=_v(0.01 * u.DEG_TO_RAD),
        gyro_bias_tau=600.0,
        gyro_turn_on_sigma=_v(0.05 * u.DEG_TO_RAD),
        arw=_v(0.0028 * u.DEG_TO_RAD),
        gyro_scale_sigma=0.005,
        gyro_misalignment_sigma=0.005,
        accel_bias_sigma=_v(1e3 * u.MICRO_G_TO_MPS2),
        accel_bias_tau=600.0,
        accel_turn_on_sigma=_v(10e3 * u.MICRO_G_TO_MPS2),
        vrw=_v(70.0 * u.MICRO_G_TO_MPS2),
        accel_scale_sigma=0.002,
        accel_misalignment_sigma=0.003,
        rate_hz=100.0,
        source="TDK InvenSense ICM-42688-P data sheet DS-000347 rev. 1.6 Tables 1-2; calibration residuals, "
        "temperature wander assumed (see imu_models.py)",
    ),
}


def get_grade(name: str) -> ImuGrade:
    """The preset called ``name`` (case-insensitive); :class:`ConfigError` naming it and the valid names otherwise.

    ``name`` may also be a JSON table: a preset (``"base"``) with some fields replaced, SI as in :class:`ImuGrade`
    (a per-axis field takes one number for all axes or three), e.g. an IMU's noise measured at rest:
    ``{"base": "navigation", "arw": 4.1e-6, "vrw": 6.2e-5, "accel_scale_sigma": 0.0011}``."""
    text = str(name).strip()
    if text.startswith("{"):
        return _grade_from_table(text)
    key = text.lower()
    if key not in GRADES:
        raise ConfigError(f"unknown IMU grade {name!r}; expected one of: {', '.join(GRADES)}")
    return GRADES[key]


# ---------------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ImuErrors:
    """Random quantities drawn once per run (leading run dimensions ``...`` allowed).

    ``gyro_turn_on`` (...,3) rad/s, ``gyro_gm0`` (...,3) rad/s initial Gauss-Markov bias, ``M_g`` (...,3,3)
    scale factor (diagonal) + misalignment (off-diagonal); likewise ``accel_*`` in m/s^2 and ``M_a``.
    """

    gyro_turn_on: FloatArray
    gyro_gm0: FloatArray
    M_g: FloatArray
    accel_turn_on: FloatArray
    accel_gm0: FloatArray
    M_a: FloatArray


@dataclass(frozen=True)
class ImuErrorsTrace:
    """The errors actually injected: total biases over time ``gyro_bias`` (...,N,3) rad/s and ``accel_bias``
    (...,N,3) m/s^2 (turn-on + Gauss-Markov, white noise excluded), and the matrices ``M_g``, ``M_a`` (...,3,3)."""

    t: FloatArray
    gyro_bias: FloatArray
    accel_bias: FloatArray
    M_g: FloatArray
    M_a: FloatArray


def _draw_M(rng: np.random.Generator, shape: tuple[int, ...], scale: float, misal: float) -> FloatArray:
    m = rng.standard_normal(shape + (3, 3)) * misal
    idx = np.arange(3)
    m[..., idx, idx] = rng.standard_normal(shape + (3,)) * scale
    return m


def draw_errors(grade: ImuGrade, rng: np.random.Generator, runs: int | None = None) -> ImuErrors:
    """Draw turn-on biases, initial Gauss-Markov biases (stationary distribution) and scale/misalignment
    matrices for one run (``runs=None``: arrays (3,), (3,3)) or ``runs`` runs (leading dimension R)."""
    shape: tuple[int, ...] = () if runs is None else (int(runs),)
    g = grade
    return ImuErrors(
        gyro_turn_on=rng.standard_normal(shape + (3,)) * g.arr("gyro_turn_on_sigma"),
        gyro_gm0=rng.standard_normal(shape + (3,)) * g.arr("gyro_bias_sigma"),
        M_g=_draw_M(rng, shape, g.gyro_scale_sigma, g.gyro_misalignment_sigma),
        accel_turn_on=rng.standard_normal(shape + (3,)) * g.arr("accel_turn_on_sigma"),
        accel_gm0=rng.standard_normal(shape + (3,)) * g.arr("accel_bias_sigma"),
        M_a=_draw_M(rng, shape, g.accel_scale_sigma, g.accel_misalignment_sigma),
    )


def _gauss_markov(t: FloatArray, b0: FloatArray, sigma: FloatArray, tau: float, rng: np.random.Generator) -> FloatArray:
    """First-order Gauss-Markov sequences at times ``t`` (N,) starting from ``b0`` (...,3), exact discretisation
    ``b[k] = phi_k b[k-1] + sigma sqrt(1 - phi_k^2) w_k`` with ``phi_k = exp(-dt_k / tau)`` (Gelb 1974 sec. 3.8).
    Returns (..., N, 3)."""
    lead = b0.shape[:-1]
    n = len(t)
    out = np.broadcast_to(b0[..., None, :], lead + (n, 3)).copy()
    if not np.isfinite(tau) or not np.any(sigma > 0) or n < 2:
        return out
    dt = np.diff(t)
    phi = np.exp(-dt / tau)
    w = rng.standard_normal(lead + (n - 1, 3)) * (sigma * np.sqrt(1.0 - phi**2)[:, None])
    if np.allclose(dt, dt[0], rtol=1e-9, atol=0.0):
        # b[k] - phi b[k-1] = w[k]: one IIR filter along time, initial condition from b0
        from scipy.signal import lfilter  # here: scipy.signal costs 30 MB to import, the replay needs no simulation

        zi = (phi[0] * b0)[..., None, :]  # lfilter state: y[0] = x[0] + phi*y[-1]
        y, _ = lfilter([1.0], [1.0, -phi[0]], w, axis=-2, zi=zi)
        out[..., 1:, :] = y
    else:
        b = b0.copy()
        for k in range(n - 1):
            b = phi[k] * b + w[..., k, :]
            out[..., k + 1, :] = b
    return out


def _interval_dt(t: FloatArray, rate_hz: float) -> FloatArray:
    """Length of each sample's interval (t[k-1], t[k]] (s); the first sample uses the next interval."""
    if len(t) < 2:
        return np.full(len(t), 1.0 / rate_hz)
    dt = np.diff(t)
    if np.any(dt <= 0):
        raise ConfigError("IMU times must increase strictly to inject errors")
    return np.concatenate([dt[:1], dt])


def corrupt_arrays(
    t: FloatArray,
    gyro_b: FloatArray,
    accel_b: FloatArray,
    grade: ImuGrade,
    rng: np.random.Generator,
    errors: ImuErrors | None = None,
    runs: int | None = None,
) -> tuple[FloatArray, FloatArray, ImuErrorsTrace]:
    """Vectorised error injection for Monte Carlo.

    ``t`` (N,) s; ``gyro_b``, ``accel_b`` ideal rate samples, (N,3) or (R,N,3) (rad/s, m/s^2, body FRD).
    ``runs=R`` draws R independent error sets (or pass ``errors`` with leading dimension R); the result is
    (R,N,3) arrays. With ``runs=None`` and (N,3) inputs the result is (N,3). White noise per sample is
    ``N / sqrt(dt_k)`` (rate samples are interval means).
    """
    t = np.asarray(t, dtype=float)
    gyro_b = np.asarray(gyro_b, dtype=float)
    accel_b = np.asarray(accel_b, dtype=float)
    if errors is None:
        errors = draw_errors(grade, rng, runs)
    lead = errors.gyro_turn_on.shape[:-1]
    dt = _interval_dt(t, grade.rate_hz)
    sq = 1.0 / np.sqrt(dt)[:, None]  # (N,1)

    b_g = errors.gyro_turn_on[..., None, :] + _gauss_markov(
        t, errors.gyro_gm0, grade.arr("gyro_bias_sigma"), grade.gyro_bias_tau, rng
    )
    b_a = errors.accel_turn_on[..., None, :] + _gauss_markov(
        t, errors.accel_gm0, grade.arr("accel_bias_sigma"), grade.accel_bias_tau, rng
    )
    n = len(t)
    gyro = gyro_b + b_g + np.einsum("...ij,...nj->...ni", errors.M_g, np.broadcast_to(gyro_b, lead + (n, 3)))
    gyro += rng.standard_normal(lead + (n, 3)) * (grade.arr("arw") * sq)
    accel = accel_b + b_a + np.einsum("...ij,...nj->...ni", errors.M_a, np.broadcast_to(accel_b, lead + (n, 3)))
    accel += rng.standard_normal(lead + (n, 3)) * (grade.arr("vrw") * sq)
    return gyro, accel, ImuErrorsTrace(t, b_g, b_a, errors.M_g, errors.M_a)


def corrupt(
    imu: ImuBatch, grade: ImuGrade, rng: np.random.Generator, errors: ImuErrors | None = None
) -> tuple[ImuBatch, ImuErrorsTrace]:
    """Add ``grade``'s errors to ideal samples ``imu`` (one run). Reproducible from ``rng``; pass ``errors``
    (from :func:`draw_errors`) to fix the per-run constants."""
    gyro, accel, trace = corrupt_arrays(imu.t, imu.gyro_b, imu.accel_b, grade, rng, errors)
    return ImuBatch(imu.t, gyro, accel), trace


def _grade_from_table(text: str) -> ImuGrade:
    import json

    try:
        table = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ConfigError(f"IMU grade {text!r}: not a JSON table ({exc.msg})") from None
    if not isinstance(table, dict) or "base" not in table:
        raise ConfigError(f"IMU grade {text!r}: expected a JSON table with a 'base' preset")
    base = get_grade(str(table.pop("base")))
    names = {f.name: f for f in fields(ImuGrade)}
    changes: dict[str, object] = {"name": f"{base.name}+custom", "source": f"{base.source}; changed: {table}"}
    for key, value in table.items():
        if key not in names or key in ("name", "source"):
            raise ConfigError(f"IMU grade table: unknown field {key!r}; expected some of {', '.join(names)}")
        per_axis = isinstance(getattr(base, key), tuple)
        try:
            if per_axis:
                vals = [float(v) for v in value] if isinstance(value, list) else [float(value)]
                if len(vals) not in (1, 3):
                    raise ValueError
                changes[key] = _v(*vals) if len(vals) == 3 else _v(vals[0])
            else:
                changes[key] = float(value)
        except (TypeError, ValueError):
            raise ConfigError(
                f"IMU grade table: {key} = {value!r}: expected {'one or three numbers' if per_axis else 'a number'}"
            ) from None
    from dataclasses import replace

    return replace(base, **changes)
