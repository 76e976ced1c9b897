"""A manoeuvring flight for filter tests: turns, speed changes and climbs at once (unlike
:func:`magnav_ins.ins.simulate.waypoints`, which flies at constant speed), so that IMU scale-factor errors are
excited on several axes.

Kinematics (point mass over the WGS-84 ellipsoid, solved as one ODE so that position and velocity agree to the
solver tolerance, as :func:`magnav_ins.ins.simulate.ideal_imu` needs)::

    d lat/dt = V cos(psi) / (R_N + h),  d lon/dt = V sin(psi) / ((R_E + h) cos(lat)),  d h/dt = -v_D(t)
    d psi/dt = r(t),  d V/dt = a(t)

with ``V`` the horizontal ground speed (m/s), ``psi`` the track (= heading, rad), and the heading rate ``r``
(rad/s), along-track acceleration ``a`` (m/s^2) and down velocity ``v_D`` (m/s) sums of smooth pulses
``peak sin^2(pi (t - start) / length)`` (continuous with their first derivative, so the attitude rates are
continuous). Attitude (body FRD -> NED): yaw = track, roll = bank of a coordinated turn ``atan(V r / g)``, pitch =
flight-path angle ``atan(-v_D / V)``. Feed the result to :func:`magnav_ins.ins.simulate.ideal_imu` for error-free
samples (round trip through :func:`magnav_ins.ins.strapdown.integrate` tested in ``tests/test_fusion_states.py``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from scipy.integrate import solve_ivp

from ..core.errors import ConfigError
from ..core.frames import q_nb_from_euler, radii_of_curvature, wrap_angle
from ..core.types import FloatArray, NavTrajectory
from ..core.units import DEG_TO_RAD

_G_BANK = 9.80665  # m/s^2, only for the coordinated-turn bank angle (as in simulate.waypoints)

Pulses = Sequence[tuple[float, float, float]]

#: (start s, length s, peak) of the default pulses: heading rate rad/s (standard-rate 3 deg/s turns of 60-90 deg,
#: left and right), along-track acceleration m/s^2, down velocity m/s (negative: climb)
TURNS = ((40.0, 40.0, 3.0 * DEG_TO_RAD), (120.0, 40.0, -3.0 * DEG_TO_RAD), (200.0, 60.0, 3.0 * DEG_TO_RAD),
         (300.0, 40.0, -3.0 * DEG_TO_RAD), (420.0, 60.0, -3.0 * DEG_TO_RAD), (520.0, 40.0, 3.0 * DEG_TO_RAD))  # fmt: skip
ACCELERATIONS = ((20.0, 30.0, 1.5), (90.0, 30.0, -1.5), (160.0, 30.0, 1.5), (260.0, 30.0, -1.5),
                 (360.0, 30.0, 1.5), (460.0, 30.0, -1.5))  # fmt: skip
CLIMBS = ((60.0, 40.0, -8.0), (150.0, 40.0, 8.0), (250.0, 40.0, -8.0), (400.0, 40.0, 8.0))


def _check_pulses(name: str, pulses: Pulses) -> tuple[tuple[float, float, float], ...]:
    """``pulses`` as float triples, or a :class:`ConfigError` naming ``name`` and the bad pulse."""
    out = []
    for p in pulses:
        try:
            start, length, peak = (float(x) for x in p)
        except (TypeError, ValueError):
            raise ConfigError(
                f"manoeuvring_flight: {name} must be (start s, length s, peak) triples, got {p!r}"
            ) from None
        if not (math.isfinite(start) and math.isfinite(peak) and math.isfinite(length) and length > 0):
            raise ConfigError(f"manoeuvring_flight: {name} pulse {p!r} needs finite values and length > 0")
        out.append((start, length, peak))
    return tuple(out)


def _pulses(t: float, pulses: Pulses) -> float:
    """Sum of ``peak sin^2(pi (t - start) / length)`` over the pulses active at ``t`` (s)."""
    out = 0.0
    for start, length, peak in pulses:
        if start <= t <= start + length:
            out += peak * math.sin(math.pi * (t - start) / length) ** 2
    return out


def _pulses_at(t: FloatArray, pulses: Pulses) -> FloatArray:
    """:func:`_pulses` at the times ``t`` (N,) s."""
    out = np.zeros_like(t)
    for start, length, peak in pulses:
        on = (t >= start) & (t <= start + length)
        out[on] += peak * np.sin(np.pi * (t[on] - start) / length) ** 2
    return out


def manoeuvring_flight(
    lat0: float,
    lon0: float,
    h0: float,
    duration_s: float = 600.0,
    rate_hz: float = 10.0,
    *,
    speed_mps: float = 60.0,
    heading0: float = 0.0,
    turns: Pulses = TURNS,
    accelerations: Pulses = ACCELERATIONS,
    climbs: Pulses = CLIMBS,
) -> NavTrajectory:
    """The flight from ``(lat0, lon0 rad, h0 m)`` at horizontal ground speed ``speed_mps`` and track ``heading0``
    rad, sampled at ``rate_hz`` for ``duration_s`` s, with pulses ``(start s, length s, peak)`` of heading rate
    (rad/s, positive: right turn), along-track acceleration (m/s^2) and down velocity (m/s, negative: climb)
    (module docstring). The defaults give 600 s with six 3 deg/s turns (bank up to 24 deg), speeds of 60-82.5 m/s
    and +-8 m/s climbs and descents. A :class:`ConfigError` names a bad argument or a pulse set that stops the
    aircraft (speed <= 0)."""
    for k, v in (("lat0", lat0), ("lon0", lon0), ("h0", h0), ("heading0", heading0)):
        if not (isinstance(v, int | float) and math.isfinite(v)):
            raise ConfigError(f"manoeuvring_flight: {k} must be a finite number, got {v!r}")
    if abs(lat0) >= 0.5 * math.pi - 1e-6:
        raise ConfigError(f"manoeuvring_flight: lat0 must be inside (-pi/2, pi/2) rad, got {lat0!r}")
    for k, v in (("duration_s", duration_s), ("rate_hz", rate_hz), ("speed_mps", speed_mps)):
        if not (isinstance(v, int | float) and math.isfinite(v) and v > 0):
            raise ConfigError(f"manoeuvring_flight: {k} must be a positive number, got {v!r}")
    turns = _check_pulses("turns", turns)
    accelerations = _check_pulses("accelerations", accelerations)
    climbs = _check_pulses("climbs", climbs)
    n = int(math.floor(duration_s * rate_hz + 1e-9)) + 1
    if n < 3:
        raise ConfigError(f"manoeuvring_flight: need at least 3 samples, got {n} ({duration_s} s at {rate_hz} Hz)")
    t = np.arange(n) / rate_hz

    def rhs(tt: float, y: FloatArray) -> FloatArray:
        lat, _lon, h, psi, V = y
        r_n, r_e = radii_of_curvature(lat)
        return np.array([
            V * math.cos(psi) / (float(r_n) + h),
            V * math.sin(psi) / ((float(r_e) + h) * math.cos(lat)),
            -_pulses(tt, climbs),
            _pulses(tt, turns),
            _pulses(tt, accelerations),
        ])  # fmt: skip

    sol = solve_ivp(rhs, (0.0, float(t[-1])), [lat0, lon0, h0, heading0, speed_mps], method="DOP853", t_eval=t,
                    rtol=1e-12, atol=[1e-15, 1e-15, 1e-9, 1e-13, 1e-11], max_step=0.5)  # fmt: skip
    if not sol.success:  # pragma: no cover - smooth right-hand side
        raise ConfigError(f"manoeuvring_flight: the trajectory ODE failed: {sol.message}")
    lat, lon, h, psi, V = sol.y
    if np.min(V) <= 0.0:
        k = int(np.argmin(V))
        raise ConfigError(f"manoeuvring_flight: the accelerations stop the aircraft (speed {V[k]:.3g} m/s at {t[k]} s)")
    vd = _pulses_at(t, climbs)
    r = _pulses_at(t, turns)
    v_n = np.stack([V * np.cos(psi), V * np.sin(psi), vd], axis=-1)
    roll = np.arctan(V * r / _G_BANK)
    pitch = np.arctan(-vd / V)
    q = q_nb_from_euler(roll, pitch, psi)
    return NavTrajectory(t, lat, wrap_angle(lon), h, v_n, q)


__all__ = ["ACCELERATIONS", "CLIMBS", "TURNS", "manoeuvring_flight"]
