"""White-noise density of an IMU channel from its Allan deviation (IEEE Std 952-1997, Annex C).

A recorded IMU stream at rest (rad/s or m/s^2 samples every ``dt`` s) gives the angle / velocity random walk that the
filter's process noise needs. ``std x sqrt(dt)`` is that density only when the samples are white: an autopilot's
samples are low-pass filtered before they are sent (ArduPilot's ``INS_GYRO_FILTER`` / ``INS_ACCEL_FILTER``, 20 Hz by
default, sampled at 50-200 Hz), so neighbouring samples are correlated, the sample variance holds only the filter's
bandwidth, and ``std x sqrt(dt)`` comes out low (ArduCopter SITL at 100 Hz: 4.2e-6 rad/sqrt(s) against 6-7e-6 from
the Allan deviation). What integrates into attitude and velocity is the noise at low frequency, which the filter
passes unchanged: the Allan deviation's white-noise part, ``sigma(tau) sqrt(tau)``, read at averaging times well
above the filter's time constant (0.1-1 s).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray


def allan_deviation(x: ArrayLike, dt: float, tau_s: float) -> NDArray[np.float64]:
    """Non-overlapping Allan deviation of the samples ``x`` ((N,) or (N, k), one row every ``dt`` s) at averaging
    time ``tau_s`` (rounded to whole samples), per column; NaN when fewer than 3 averages fit."""
    a = np.asarray(x, dtype=float)
    a = a.reshape(len(a), -1)
    m = max(1, int(round(tau_s / dt)))
    n = len(a) // m
    if n < 3:
        return np.full(a.shape[1], np.nan)
    means = a[: n * m].reshape(n, m, -1).mean(axis=1)
    return np.sqrt(0.5 * np.mean(np.diff(means, axis=0) ** 2, axis=0))


def white_noise_density(x: ArrayLike, dt: float, taus_s: tuple[float, ...] = (0.1, 0.3, 1.0)) -> NDArray[np.float64]:
    """The white-noise density (unit x sqrt(s): ARW for a gyro, VRW for an accelerometer) of each column of ``x``:
    the median over ``taus_s`` of ``allan_deviation(tau) x sqrt(tau)`` (module docstring)."""
    vals = np.array([allan_deviation(x, dt, t) * np.sqrt(t) for t in taus_s])
    return np.nanmedian(vals, axis=0)
