"""Ground alignment for the bridge: is the vehicle still, and what do the IMU samples say while it is.

A MEMS INS left integrating on the ground drifts by tens of metres in a minute (an uncorrected gyro bias tilts it;
the tilt turns gravity into a horizontal acceleration). Standing still is the best measurement there is, so the
bridge does not integrate then: while :class:`StillDetector` says the vehicle is still (and the autopilot does not say
it is flying), the position is held with its uncertainty, the velocity is zero, and :class:`GroundAlignment`
averages the samples. When the vehicle moves, the INS starts from the aligned state (Groves 2013 sec. 5.6.2,
coarse alignment; sec. 15.4.1, zero-velocity updates, taken to their limit):

* roll and pitch from the mean specific force: ``roll = atan2(-f_y, -f_z)``, ``pitch = atan2(f_x, hypot(f_y,
  f_z))`` (Groves eq. 5.101, FRD: at rest ``f_b = -C_bn g_n``); the levelling error is the horizontal
  accelerometer bias over g;
* the gyro bias from the mean angular rate minus the Earth's rate in the body frame,
  ``b_g = mean(omega) - C_bn omega_ie_n`` (needs the heading, from the autopilot or ``--init``; the Earth's rate is
  7.3e-5 rad/s, so a heading error of 0.1 rad leaves 7e-6 rad/s);
* heading: not from the gyros (a MEMS gyro cannot gyrocompass); the caller supplies it.

Units: s, rad/s, m/s^2, body FRD; positions rad.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np

from ..core.frames import WGS84_OMEGA_E, C_nb_from_q
from ..ins.earth import gravity_n


def normal_gravity_mps2(lat: float, h: float) -> float:
    """Magnitude of normal gravity (m/s^2) at latitude ``lat`` (rad) and height ``h`` (m)."""
    return float(np.linalg.norm(gravity_n(lat, h)))


class StillDetector:
    """Stillness over the last ``window_s`` of samples: the RMS deviation of the angular rate from its window mean
    is below ``gyro_rms_rad_s`` (rad/s), that of the specific force below ``accel_rms_mps2`` (m/s^2), and the mean
    specific force is within ``gravity_tolerance_mps2`` of normal gravity. Motor vibration on the ground passes with
    the defaults (0.05 rad/s, 0.5 m/s^2); a hand-carried or taxiing vehicle does not.

    :meth:`push` returns the sample that leaves the window (older than ``window_s``), so a caller can average only
    samples that were judged still with a whole window after them."""

    def __init__(
        self,
        window_s: float = 1.0,
        gyro_rms_rad_s: float = 0.05,
        accel_rms_mps2: float = 0.5,
        gravity_tolerance_mps2: float = 0.5,
    ) -> None:
        self.window_s = float(window_s)
        self.gyro_rms = float(gyro_rms_rad_s)
        self.accel_rms = float(accel_rms_mps2)
        self.gravity_tolerance = float(gravity_tolerance_mps2)
        self._buf: deque[tuple[float, np.ndarray, np.ndarray]] = deque()
        self._sum = np.zeros(6)
        self._sum2 = np.zeros(6)

    def reset(self) -> None:
        self._buf.clear()
        self._sum[:] = 0.0
        self._sum2[:] = 0.0

    @property
    def samples(self) -> list[tuple[float, np.ndarray, np.ndarray]]:
        """The samples in the window, oldest first: ``(t, gyro_b, accel_b)``."""
        return list(self._buf)

    def push(self, t: float, gyro_b: np.ndarray, accel_b: np.ndarray) -> list[tuple[float, np.ndarray, np.ndarray]]:
        """Add one sample; returns the samples that left the window."""
        x = np.concatenate([gyro_b, accel_b])
        self._buf.append((float(t), np.asarray(gyro_b, float), np.asarray(accel_b, float)))
        self._sum += x
        self._sum2 += x * x
        out = []
        while self._buf and self._buf[0][0] < t - self.window_s:
            t0, g0, a0 = self._buf.popleft()
            x0 = np.concatenate([g0, a0])
            self._sum -= x0
            self._sum2 -= x0 * x0
            out.append((t0, g0, a0))
        return out

    def full(self) -> bool:
        return len(self._buf) >= 2 and self._buf[-1][0] - self._buf[0][0] >= 0.9 * self.window_s

    def still(self, gravity_mps2: float) -> bool:
        """True when the window is full and its samples are still (class docstring); ``gravity_mps2`` the magnitude
        of normal gravity there (:func:`normal_gravity_mps2`)."""
        n = len(self._buf)
        if not self.full():
            return False
        mean = self._sum / n
        var = np.maximum(self._sum2 / n - mean * mean, 0.0)
        gyro_rms = math.sqrt(float(var[:3].sum()))
        accel_rms = math.sqrt(float(var[3:].sum()))
        f = float(np.linalg.norm(mean[3:]))
        return (
            gyro_rms < self.gyro_rms and accel_rms < self.accel_rms and abs(f - gravity_mps2) < self.gravity_tolerance
        )


class GroundAlignment:
    """Running means of the samples taken while still (module docstring). ``max_s``: older samples are forgotten
    (exponentially, time constant ``max_s``), so the gyro-bias estimate follows a slow warm-up drift."""

    def __init__(self, max_s: float = 120.0) -> None:
        self.max_s = float(max_s)
        self.reset()

    def reset(self) -> None:
        self._w = 0.0
        self._gyro = np.zeros(3)
        self._accel = np.zeros(3)
        self.duration_s = 0.0
        self._t_last = math.nan

    def push(self, t: float, gyro_b: np.ndarray, accel_b: np.ndarray) -> None:
        dt = 0.0 if math.isnan(self._t_last) else max(float(t) - self._t_last, 0.0)
        self._t_last = float(t)
        self.duration_s += dt
        decay = math.exp(-dt / self.max_s)
        self._w = self._w * decay + 1.0
        a = 1.0 / self._w
        self._gyro += a * (np.asarray(gyro_b, float) - self._gyro)
        self._accel += a * (np.asarray(accel_b, float) - self._accel)

    @property
    def samples(self) -> float:
        """Effective number of samples averaged."""
        return self._w

    def level(self) -> tuple[float, float]:
        """Roll and pitch (rad) from the mean specific force."""
        f = self._accel
        return math.atan2(-f[1], -f[2]), math.atan2(f[0], math.hypot(f[1], f[2]))

    @property
    def mean_gyro(self) -> np.ndarray:
        return self._gyro.copy()

    @property
    def mean_accel(self) -> np.ndarray:
        return self._accel.copy()

    def gyro_bias(self, q_nb: np.ndarray, lat: float) -> np.ndarray:
        """``mean(omega) - C_bn omega_ie_n`` (rad/s, body FRD) for attitude ``q_nb`` at latitude ``lat`` (rad)."""
        w_ie_n = WGS84_OMEGA_E * np.array([math.cos(lat), 0.0, -math.sin(lat)])
        return self._gyro - C_nb_from_q(np.asarray(q_nb, float)).T @ w_ie_n
