"""Fusion back ends behind :class:`magnav_ins.core.protocols.Fuser`: a UKF (filterpy), a factor graph (GTSAM,
iSAM2 + batch LM), a free-inertial baseline, Storms' 2-D constant-velocity Kalman filter (``cv_kf``) and the
matcher's own solution (``solution``: a stand-alone navigator such as MagNavigate). :func:`make_fuser` builds one by
name without importing the other back ends' libraries; :func:`check_fusion_options` validates a fusion spec without
building (or importing) anything."""

from __future__ import annotations

from typing import Any

from ...core.errors import ConfigError
from ...core.types import NavEstimate
from .common import ExtraStates, ImuNoise, LocalFrame

FUSER_KINDS = ("ukf", "graph", "free_inertial", "cv_kf", "solution")

#: optional error states of the inertial fusers (:class:`common.ExtraStates`)
EXTRA_STATE_OPTIONS = ("scale_factors", "scale_factor_tau_s", "map_bias_sigma_m", "map_bias_tau_s", "map_bias_sources")

_CORE = ("cov_step_s", "buffer_s", "altitude_hold", "keep_history")

#: fault detection, exclusion and protection level (:class:`integrity.FaultMonitor`)
INTEGRITY_OPTIONS = ("reset_after", "fault_window", "fault_window_s", "fault_probability", "integrity_risk")

#: the keyword options each fuser's constructor takes (tested against the constructors' signatures)
FUSER_OPTIONS: dict[str, tuple[str, ...]] = {
    "ukf": ("gate_probability", *_CORE, *INTEGRITY_OPTIONS, "alpha", "beta", "kappa", *EXTRA_STATE_OPTIONS),
    "graph": (
        "gate_probability",
        "huber_k",
        "vertical_sigma_m",
        "factorization",
        "relinearize_skip",
        "gravity_update_s",
        "integration_sigma",
        *INTEGRITY_OPTIONS,
        "max_preintegration_rad",
        "altitude_hold",
        "altitude_hold_sigma_m",
    ),
    "free_inertial": ("gate_probability", *_CORE, "integrity_risk", *EXTRA_STATE_OPTIONS),
    "cv_kf": ("accel_sigma_mps2", "turn_command", "gate_probability", "inflate_nis", "altitude_hold"),
    "solution": ("altitude_hold",),
}


def check_fusion_options(kind: str, options: dict[str, Any], noise: ImuNoise | None = None) -> None:
    """Raise a :class:`ConfigError` naming the first unknown option of fuser ``kind`` or the first invalid value
    of the optional-state options (``scale_factors`` a bool, ``map_bias_sigma_m`` / ``map_bias_tau_s`` /
    ``scale_factor_tau_s`` numbers > 0, ...; :meth:`common.ExtraStates.from_options`). With ``noise`` it also
    checks that ``scale_factors = true`` has non-zero scale-factor sigmas."""
    if kind not in FUSER_OPTIONS:
        raise ConfigError(f"unknown fusion kind {kind!r}; expected one of {', '.join(FUSER_KINDS)}")
    allowed = FUSER_OPTIONS[kind]
    for key in options:
        if key not in allowed:
            raise ConfigError(f"unknown fusion option {key!r} for {kind!r}; expected one of {', '.join(allowed)}")
    extra = {k: v for k, v in options.items() if k in EXTRA_STATE_OPTIONS}
    if extra:
        probe = (
            noise if noise is not None else ImuNoise(0.0, 0.0, 0.0, 0.0, accel_scale_sigma=1.0, gyro_scale_sigma=1.0)
        )
        ExtraStates.from_options(probe, **extra)


def make_fuser(kind: str, init: NavEstimate, noise: ImuNoise, **options):
    """A fuser of ``kind`` ("ukf", "graph" or "free_inertial") starting from ``init`` with IMU ``noise``;
    ``options`` go to its constructor (:data:`FUSER_OPTIONS`; a :class:`ConfigError` names an unknown kind or
    option or a bad optional-state value). E.g. the 21 + 2 state UKF:
    ``make_fuser("ukf", init, noise, scale_factors=True, map_bias_sigma_m=50.0, map_bias_tau_s=3600.0)``."""
    check_fusion_options(kind, options, noise)
    if kind == "ukf":
        from .ukf import UkfFuser

        return UkfFuser(init, noise, **options)
    if kind == "graph":
        from .graph import GraphFuser

        return GraphFuser(init, noise, **options)
    if kind == "cv_kf":
        from .cv_kf import CvKalmanFuser

        return CvKalmanFuser(init, noise, **options)
    if kind == "solution":
        from .solution import SolutionFuser

        return SolutionFuser(init, noise, **options)
    from .free_inertial import FreeInertial

    return FreeInertial(init, noise, **options)


__all__ = [
    "EXTRA_STATE_OPTIONS",
    "FUSER_KINDS",
    "FUSER_OPTIONS",
    "INTEGRITY_OPTIONS",
    "ExtraStates",
    "ImuNoise",
    "LocalFrame",
    "check_fusion_options",
    "make_fuser",
]
