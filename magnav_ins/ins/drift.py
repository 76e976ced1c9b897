"""Free-inertial drift study: Monte Carlo of a stationary INS with a grade's errors, beside the error model's
predicted 1-sigma (the analogue of Storms 2009 Fig. 2.1).

Scenario: the vehicle is at rest and level at ``(lat, lon, h)``, heading north, or (``speed_mps > 0``) flies
straight and level due north from there at that ground speed (a meridian great circle). Each run draws initial navigation
errors (position, velocity, tilt; 1-sigmas in :class:`DriftConfig`) and IMU errors (turn-on and Gauss-Markov
biases, ARW/VRW, scale factor, misalignment; :mod:`magnav_ins.ins.imu_models`), integrates the corrupted IMU with
the compiled batch mechanisation (:func:`magnav_ins.ins.strapdown.integrate_batch`) and records its error; the model
curve is :func:`magnav_ins.ins.error_model.propagate_covariance` from the same initial covariance.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..core.errors import ConfigError
from ..core.frames import radii_of_curvature
from ..core.types import FloatArray, NavTrajectory
from ..core.units import DEG_TO_RAD
from . import error_model as em
from .imu_models import ImuGrade, corrupt_arrays
from .simulate import great_circle, ideal_imu, stationary
from .strapdown import integrate_batch


@dataclass(frozen=True)
class DriftConfig:
    """Drift-study settings (SI). Initial-error 1-sigmas: ``position_sigma_m`` (each of N, E, D),
    ``velocity_sigma_mps`` (each axis), ``tilt_sigma_rad`` (roll-like N, pitch-like E, heading D)."""

    duration_s: float = 1800.0
    runs: int = 20
    seed: int = 1
    rate_hz: float = 20.0
    output_dt_s: float = 10.0
    lat: float = 40.0 * DEG_TO_RAD
    lon: float = -84.0 * DEG_TO_RAD
    h: float = 200.0
    position_sigma_m: float = 1.0
    velocity_sigma_mps: float = 0.01
    tilt_sigma_rad: tuple[float, float, float] = (5e-5, 5e-5, 5e-4)
    altitude_hold: bool = False
    speed_mps: float = 0.0

    def __post_init__(self) -> None:
        for name in ("duration_s", "rate_hz", "output_dt_s"):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and math.isfinite(v) and v > 0):
                raise ConfigError(f"drift: {name} must be a positive number, got {v!r}")
        if not (math.isfinite(self.speed_mps) and 0.0 <= self.speed_mps <= 1000.0):
            raise ConfigError(f"drift: speed_mps must be in [0, 1000] m/s, got {self.speed_mps!r}")
        if not (isinstance(self.runs, int) and self.runs >= 2):
            raise ConfigError(f"drift: runs must be an integer >= 2, got {self.runs!r}")
        if self.output_dt_s < 1.0 / self.rate_hz or self.duration_s < self.output_dt_s:
            raise ConfigError(
                f"drift: need 1/rate_hz <= output_dt_s <= duration_s, got rate {self.rate_hz} Hz, "
                f"output step {self.output_dt_s} s, duration {self.duration_s} s"
            )


@dataclass(frozen=True)
class DriftResult:
    """``t`` (M,) s; Monte Carlo RMS horizontal error ``sigma_h_mc`` (M,) m, north/east RMS ``sigma_n_mc``,
    ``sigma_e_mc``; model 1-sigmas ``sigma_h_model``, ``sigma_n_model``, ``sigma_e_model`` (M,) m; per-run
    horizontal errors ``err_h`` (R, M) m; the model's largest tilt 1-sigma ``sigma_tilt_model`` (M,) rad and the
    Monte Carlo RMS of the largest tilt error ``sigma_tilt_mc`` (M,) rad (the linear model holds while these are
    small, say < 0.05 rad)."""

    grade: ImuGrade
    config: DriftConfig
    t: FloatArray
    sigma_h_mc: FloatArray
    sigma_n_mc: FloatArray
    sigma_e_mc: FloatArray
    sigma_h_model: FloatArray
    sigma_n_model: FloatArray
    sigma_e_model: FloatArray
    err_h: FloatArray
    sigma_tilt_mc: FloatArray
    sigma_tilt_model: FloatArray

    @property
    def linear_regime(self) -> bool:
        """True while the tilt errors stayed small (< 0.05 rad RMS) so that the error model is meaningful."""
        return bool(max(self.sigma_tilt_mc.max(), self.sigma_tilt_model.max()) < 0.05)


def run_drift(grade: ImuGrade, cfg: DriftConfig) -> DriftResult:
    """Run the drift study (module docstring). Reproducible from ``cfg.seed``."""
    rng = np.random.default_rng(cfg.seed)
    if cfg.speed_mps > 0.0:
        r_n, _ = radii_of_curvature(cfg.lat)
        dlat = 1.05 * cfg.speed_mps * cfg.duration_s / (float(r_n) + cfg.h) + 1e-4
        if cfg.lat + dlat > 89.0 * DEG_TO_RAD:
            raise ConfigError("drift: the northbound flight would pass 89 deg latitude; start further south")
        truth = great_circle(cfg.lat, cfg.lon, cfg.lat + dlat, cfg.lon, cfg.h, cfg.speed_mps, cfg.rate_hz)
        truth = truth.slice(0, int(round(cfg.duration_s * cfg.rate_hz)) + 1)
        imu0 = ideal_imu(truth)
        gyro0, accel0 = imu0.gyro_b, imu0.accel_b
    else:
        truth = stationary(cfg.lat, cfg.lon, cfg.h, 0.0, cfg.duration_s, cfg.rate_hz)
        # the ideal samples of a vehicle at rest are constant: compute them once on a short piece
        imu0 = ideal_imu(truth.slice(0, 4))
        gyro0 = np.broadcast_to(imu0.gyro_b[1], (len(truth), 3))
        accel0 = np.broadcast_to(imu0.accel_b[1], (len(truth), 3))
    R = cfg.runs
    gyro, accel, _ = corrupt_arrays(truth.t, gyro0, accel0, grade, rng, runs=R)

    sig0 = np.concatenate(
        [np.full(3, cfg.position_sigma_m), np.full(3, cfg.velocity_sigma_mps), np.asarray(cfg.tilt_sigma_rad)]
    )
    dx0 = rng.standard_normal((R, 9)) * sig0
    if cfg.altitude_hold:
        dx0[:, 2] = 0.0
        dx0[:, 5] = 0.0
    nav0 = truth.at(0)
    inits = [em.apply_error(nav0, dx0[r]) for r in range(R)]
    dec = max(1, int(round(cfg.output_dt_s * cfg.rate_hz)))
    batch = integrate_batch(
        truth.t,
        gyro,
        accel,
        np.array([s.lat for s in inits]),
        np.array([s.lon for s in inits]),
        np.array([s.h for s in inits]),
        np.array([s.v_n for s in inits]),
        np.array([s.q_nb for s in inits]),
        decimate=dec,
        altitude_hold=cfg.h if cfg.altitude_hold else None,
    )
    m = len(batch.t)
    sel = np.arange(0, len(truth), dec)[:m]
    tr_m = NavTrajectory(batch.t, truth.lat[sel], truth.lon[sel], truth.h[sel], truth.v_n[sel], truth.q_nb[sel])
    e = em.nav_error(batch, tr_m)  # (R, M, 9)
    err_h = np.hypot(e[..., 0], e[..., 1])
    sn = np.sqrt(np.mean(e[..., 0] ** 2, axis=0))
    se = np.sqrt(np.mean(e[..., 1] ** 2, axis=0))

    P0 = np.zeros((em.N_STATES, em.N_STATES))
    P0[:9, :9] = np.diag(sig0**2)
    P0[9:, 9:] = em.initial_covariance(grade)[9:, 9:]
    model_dt = min(cfg.output_dt_s, 10.0)
    _, P = em.propagate_covariance(P0, truth, None, grade, model_dt, altitude_hold=cfg.altitude_hold)
    every = max(1, int(round(cfg.output_dt_s / model_dt)))
    P = P[::every]
    k = min(len(P), m)
    return DriftResult(
        grade,
        cfg,
        batch.t[:k],
        np.hypot(sn, se)[:k],
        sn[:k],
        se[:k],
        em.horizontal_sigma(P)[:k],
        np.sqrt(P[:k, 0, 0]),
        np.sqrt(P[:k, 1, 1]),
        err_h[:, :k],
        np.sqrt(np.mean(e[..., 6:9] ** 2, axis=0)).max(axis=-1)[:k],
        np.sqrt(np.diagonal(P[:k, 6:9, 6:9], axis1=-2, axis2=-1)).max(axis=-1),
    )
