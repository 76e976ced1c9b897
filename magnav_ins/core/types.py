"""The shared value types: frozen dataclasses with time-first arrays, SI units, frames in the names.

These are the only objects that cross module boundaries (INS <-> matchers <-> fusers <-> studies <-> bridge).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum

import numpy as np
from numpy.typing import NDArray

from .errors import InputError

FloatArray = NDArray[np.float64]


class FieldKind(str, Enum):
    """What a map or a reading measures, with its unit in the name."""

    GRAVITY_DISTURBANCE_MGAL = "gravity_disturbance_mgal"
    TOTAL_FIELD_ANOMALY_NT = "total_field_anomaly_nt"
    VECTOR_FIELD_NT = "vector_field_nt"

    @property
    def unit(self) -> str:
        return "mGal" if self is FieldKind.GRAVITY_DISTURBANCE_MGAL else "nT"

    @property
    def components(self) -> int:
        return 3 if self is FieldKind.VECTOR_FIELD_NT else 1


def _as_float_array(name: str, a: object, shape_tail: tuple[int, ...] = ()) -> FloatArray:
    arr = np.asarray(a, dtype=float)
    if shape_tail and arr.shape[1:] != shape_tail:
        raise InputError(f"{name}: expected shape (N, {', '.join(map(str, shape_tail))}), got {arr.shape}")
    return arr


#: what an IMU sample holds about its interval ``(t[k-1], t[k]]`` (rates in rad/s and m/s^2, increments in rad and
#: m/s): ``mean`` the mean rate over the interval (the mechanisation's own input; a rate-integrating IMU's output);
#: ``instantaneous`` the rate at ``t[k]`` (a filtered MEMS sample, ArduPilot's and PX4's HIGHRES_IMU, pyins
#: ``sensor_type="rate"``); ``increment`` the integral over the interval (pyins ``sensor_type="increment"``).
#: (Here, re-exported by :mod:`magnav_ins.ins.strapdown`, so that a command's parser offers them without numba.)
SAMPLE_TYPES = ("mean", "instantaneous", "increment")


@dataclass(frozen=True)
class ImuBatch:
    """Rate-type IMU samples. ``t`` (N,) s; ``gyro_b`` (N,3) rad/s = omega_ib_b; ``accel_b`` (N,3) m/s^2 = f_ib_b
    (specific force), body FRD. Sample k is the mean rate over (t[k-1], t[k]]."""

    t: FloatArray
    gyro_b: FloatArray
    accel_b: FloatArray

    def __post_init__(self) -> None:
        t = _as_float_array("ImuBatch.t", self.t)
        g = _as_float_array("ImuBatch.gyro_b", self.gyro_b, (3,))
        a = _as_float_array("ImuBatch.accel_b", self.accel_b, (3,))
        if not (t.ndim == 1 and len(g) == len(t) == len(a)):
            raise InputError(f"ImuBatch: t {t.shape}, gyro_b {g.shape}, accel_b {a.shape} must have the same length N")
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "gyro_b", g)
        object.__setattr__(self, "accel_b", a)

    def __len__(self) -> int:
        return len(self.t)

    def slice(self, i0: int, i1: int) -> ImuBatch:
        """Samples ``i0 <= k < i1``."""
        return ImuBatch(self.t[i0:i1], self.gyro_b[i0:i1], self.accel_b[i0:i1])


@dataclass(frozen=True)
class ImuIncrements:
    """Increment-type IMU samples: ``dtheta_b`` (N,3) rad and ``dv_b`` (N,3) m/s over (t[k-1], t[k]], body FRD."""

    t: FloatArray
    dtheta_b: FloatArray
    dv_b: FloatArray

    def __post_init__(self) -> None:
        t = _as_float_array("ImuIncrements.t", self.t)
        d = _as_float_array("ImuIncrements.dtheta_b", self.dtheta_b, (3,))
        v = _as_float_array("ImuIncrements.dv_b", self.dv_b, (3,))
        if not (t.ndim == 1 and len(d) == len(t) == len(v)):
            raise InputError("ImuIncrements: t, dtheta_b and dv_b must have the same length N")
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "dtheta_b", d)
        object.__setattr__(self, "dv_b", v)

    def __len__(self) -> int:
        return len(self.t)


@dataclass(frozen=True)
class NavState:
    """Navigation solution at time ``t`` (s): latitude, longitude (rad), ellipsoidal height ``h`` (m),
    NED velocity ``v_n`` (3,) m/s, attitude ``q_nb`` (4,) scalar-last, body FRD -> NED."""

    t: float
    lat: float
    lon: float
    h: float
    v_n: FloatArray
    q_nb: FloatArray

    def __post_init__(self) -> None:
        object.__setattr__(self, "v_n", np.asarray(self.v_n, dtype=float).reshape(3))
        q = np.asarray(self.q_nb, dtype=float).reshape(4)
        object.__setattr__(self, "q_nb", q / np.linalg.norm(q))


@dataclass(frozen=True)
class StateLayout:
    """Names the slices of an error-state vector, e.g. ``{"pos": slice(0, 3), "vel": slice(3, 6), ...}``.

    Position errors are north/east/down metres, velocity errors NED m/s, attitude errors rad (NED tilt),
    biases in the sensor's SI unit. Optional blocks a fuser may append (:meth:`extended`): ``s_a``, ``s_g``
    accelerometer / gyro scale-factor errors (dimensionless, body FRD x, y, z) and ``b_map`` the map-registration
    bias of the fixes (north, east m).
    """

    slices: dict[str, slice]

    def extended(self, **sizes: int) -> StateLayout:
        """This layout with named blocks of ``sizes`` states appended in keyword order, e.g.
        ``LAYOUT_15.extended(s_a=3, s_g=3)`` (21 states). Existing slices keep their place."""
        out = dict(self.slices)
        n = self.size
        for name, k in sizes.items():
            if name in out or int(k) < 1:
                raise ValueError(f"StateLayout.extended: {name!r} exists already or has no states ({k})")
            out[name] = slice(n, n + int(k))
            n += int(k)
        return StateLayout(out)

    @property
    def size(self) -> int:
        return max(s.stop for s in self.slices.values())

    def __getitem__(self, name: str) -> slice:
        return self.slices[name]

    def __contains__(self, name: str) -> bool:
        return name in self.slices


#: The 15-state layout every fuser provides at least.
LAYOUT_15 = StateLayout(
    {"pos": slice(0, 3), "vel": slice(3, 6), "att": slice(6, 9), "b_a": slice(9, 12), "b_g": slice(12, 15)}
)


#: Default integrity risk of a horizontal protection level: the probability, per output epoch, that the true
#: horizontal error exceeds ``NavEstimate.hpl_m`` without the fault detection having flagged it.
DEFAULT_INTEGRITY_RISK = 1e-3


@dataclass(frozen=True)
class NavEstimate:
    """A navigation solution with its error covariance ``P`` laid out as ``layout`` says.

    ``hpl_m`` is the horizontal protection level (m): a radius that the true horizontal error exceeds with
    probability at most ``integrity_risk`` per epoch; NaN when the fuser does not provide one.
    """

    nav: NavState
    P: FloatArray
    layout: StateLayout = LAYOUT_15
    hpl_m: float = float("nan")
    integrity_risk: float = DEFAULT_INTEGRITY_RISK

    @property
    def cov_ne(self) -> FloatArray:
        """2x2 horizontal position covariance (north, east), m^2."""
        s = self.layout["pos"]
        return np.asarray(self.P)[s.start : s.start + 2, s.start : s.start + 2]


@dataclass(frozen=True)
class FieldReadings:
    """Map-field readings: ``t`` (N,) s; ``value`` (N,) or (N,3) in the unit of ``kind``; ``sigma`` 1-sigma noise
    in the same unit."""

    t: FloatArray
    value: FloatArray
    sigma: float
    kind: FieldKind

    def __post_init__(self) -> None:
        t = np.asarray(self.t, dtype=float)
        v = np.asarray(self.value, dtype=float)
        kind = FieldKind(self.kind)
        if t.ndim != 1 or len(v) != len(t):
            raise InputError(f"FieldReadings: t {t.shape} and value {v.shape} must have the same length")
        expected = (len(t),) if kind.components == 1 else (len(t), 3)
        if v.shape != expected:
            raise InputError(f"FieldReadings: value for kind {kind.value} must have shape {expected}, got {v.shape}")
        if not (np.isfinite(self.sigma) and self.sigma > 0):
            raise InputError(f"FieldReadings: sigma must be a positive number in {kind.unit}, got {self.sigma}")
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "value", v)
        object.__setattr__(self, "kind", kind)

    def __len__(self) -> int:
        return len(self.t)


#: the start of a batch matcher's "no fix" reason when its likelihood's peak region reaches the border of the scanned
#: window (the likelihood matchers, PMHT-MM); the pipeline tries a longer window after it
#: (:data:`magnav_ins.pipeline.LONG_WINDOW_REASONS`)
EDGE_REASON = "likelihood reaches the edge of the search window"


@dataclass(frozen=True)
class Fix:
    """A position fix from a matcher, or a "no fix" (``available=False``) with a ``reason``.

    ``lat``, ``lon`` rad; ``cov_ne`` (2,2) north/east covariance in m^2; ``score`` is matcher-specific
    (likelihood ratio, peak mass, ...); ``source`` names the matcher.
    """

    t: float
    lat: float
    lon: float
    cov_ne: FloatArray
    available: bool = True
    reason: str = ""
    score: float = float("nan")
    source: str = ""

    @classmethod
    def no_fix(cls, t: float, reason: str, source: str = "", score: float = float("nan")) -> Fix:
        """A "no fix" at time ``t`` saying why."""
        return cls(t, float("nan"), float("nan"), np.full((2, 2), np.nan), False, reason, score, source)


@dataclass(frozen=True)
class Innovation:
    """What a fuser did with a fix: residual (north, east) m, its covariance ``S`` m^2, the normalised
    innovation squared ``nis`` and whether the fix was ``accepted`` (``reason`` if not)."""

    t: float
    residual_ne: FloatArray
    S: FloatArray
    nis: float
    accepted: bool
    reason: str = ""
    source: str = ""
    extra: dict[str, float] = field(default_factory=dict)


@dataclass(frozen=True)
class NavTrajectory:
    """A time series of navigation states (truth or INS output): ``t`` (N,) s; ``lat``, ``lon`` (N,) rad;
    ``h`` (N,) m ellipsoidal; ``v_n`` (N,3) NED m/s; ``q_nb`` (N,4) scalar-last body->NED."""

    t: FloatArray
    lat: FloatArray
    lon: FloatArray
    h: FloatArray
    v_n: FloatArray
    q_nb: FloatArray

    def __post_init__(self) -> None:
        n = len(np.asarray(self.t))
        for name, tail in (("t", ()), ("lat", ()), ("lon", ()), ("h", ()), ("v_n", (3,)), ("q_nb", (4,))):
            arr = np.asarray(getattr(self, name), dtype=float)
            if arr.shape != (n, *tail):
                raise InputError(f"NavTrajectory.{name}: expected shape {(n, *tail)}, got {arr.shape}")
            object.__setattr__(self, name, arr)

    def __len__(self) -> int:
        return len(self.t)

    def at(self, k: int) -> NavState:
        """The state at sample ``k``."""
        return NavState(
            float(self.t[k]), float(self.lat[k]), float(self.lon[k]), float(self.h[k]), self.v_n[k], self.q_nb[k]
        )

    def slice(self, i0: int, i1: int) -> NavTrajectory:
        """Samples ``i0 <= k < i1``."""
        return NavTrajectory(
            self.t[i0:i1], self.lat[i0:i1], self.lon[i0:i1], self.h[i0:i1], self.v_n[i0:i1], self.q_nb[i0:i1]
        )
