"""Physical plausibility of values for their kind: catches a unit or a quantity mistaken for another (full gravity
given as a gravity disturbance, the total field given as its anomaly, gyros in deg/s or garbage, accelerometers in
g) before it is navigated on. Each check returns None or a one-line reason; the caller refuses (navigation: ``run``,
``ins integrate``) or warns (inspection: ``map info``), and names the option that overrides it.

Limits (each stated with its source or reason):

* gravity disturbance / anomaly: the Earth's gravity disturbances and free-air anomalies stay within a few hundred
  mGal (well inside +-1000 mGal), while full gravity is 978,000-983,000 mGal (WGS-84 normal gravity from equator to
  pole). A median |value| above
  ``FULL_GRAVITY_MEDIAN_MGAL`` is full gravity; any |value| above ``MAX_GRAVITY_DISTURBANCE_MGAL`` is not a disturbance.
* total-field anomaly: the main field is 22,000-67,000 nT everywhere (IGRF-13); crustal anomalies over a region have a
  median near zero and exceed a few thousand nT only over iron ore. A median |value| above ``FULL_FIELD_MEDIAN_NT``
  is the total field with the main field (IGRF) not removed; any |value| above ``MAX_FIELD_ANOMALY_NT`` (1 G) is not
  an anomaly.
* vector field: |B| above ``MAX_VECTOR_FIELD_NT`` (10 G) saturates any magnetometer used for navigation.
* gyro: full-scale ranges of strapdown gyros reach 4000 deg/s (70 rad/s); rates above ``MAX_GYRO_RAD_S`` are a unit
  mistake or garbage.
* accelerometer: specific force above ``MAX_ACCEL_MPS2`` (100 g) is outside navigation IMUs; a median |f| below
  ``MIN_MEDIAN_ACCEL_MPS2`` over a recording is in g, not m/s^2 (a vehicle that is not in free fall feels about
  9.8 m/s^2 on average).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .types import FieldKind

FULL_GRAVITY_MEDIAN_MGAL = 10_000.0
MAX_GRAVITY_DISTURBANCE_MGAL = 3_000.0
FULL_FIELD_MEDIAN_NT = 15_000.0
MAX_FIELD_ANOMALY_NT = 100_000.0
MAX_VECTOR_FIELD_NT = 1_000_000.0
MAX_GYRO_RAD_S = 70.0
MAX_ACCEL_MPS2 = 1_000.0
MIN_MEDIAN_ACCEL_MPS2 = 3.0


def field_values_problem(values: Any, kind: FieldKind) -> str | None:
    """Why ``values`` (any shape; (..., 3) for a vector kind; NaN ignored) are implausible for ``kind``, or None."""
    v = np.asarray(values, dtype=float)
    if kind is FieldKind.VECTOR_FIELD_NT:
        mag = np.linalg.norm(v.reshape(-1, 3), axis=1)
        mag = mag[np.isfinite(mag)]
        if mag.size and mag.max() > MAX_VECTOR_FIELD_NT:
            return (
                f"|B| reaches {mag.max():.4g} nT, above {MAX_VECTOR_FIELD_NT:.0f} nT (10 G): not a magnetic field in nT"
            )
        return None
    a = np.abs(v[np.isfinite(v)])
    if a.size == 0:
        return None
    med, top = float(np.median(a)), float(a.max())
    if kind is FieldKind.GRAVITY_DISTURBANCE_MGAL:
        if med > FULL_GRAVITY_MEDIAN_MGAL:
            return (f"median |value| {med:.6g} mGal looks like full gravity (about 980,000 mGal), not a gravity "
                    "disturbance (gravity minus normal gravity, a few hundred mGal at most)")  # fmt: skip
        if top > MAX_GRAVITY_DISTURBANCE_MGAL:
            return f"|value| reaches {top:.6g} mGal; gravity disturbances stay within a few hundred mGal"
    elif kind is FieldKind.TOTAL_FIELD_ANOMALY_NT:
        if med > FULL_FIELD_MEDIAN_NT:
            return (f"median |value| {med:.6g} nT looks like the total field (22,000-67,000 nT), not its anomaly "
                    "(the main field, IGRF, removed)")  # fmt: skip
        if top > MAX_FIELD_ANOMALY_NT:
            return f"|value| reaches {top:.6g} nT, above {MAX_FIELD_ANOMALY_NT:.0f} nT (1 G): not a crustal anomaly"
    return None


def imu_problem(gyro_b: Any, accel_b: Any) -> str | None:
    """Why IMU rates ``gyro_b`` (N, 3) rad/s and specific forces ``accel_b`` (N, 3) m/s^2 are implausible, or None."""
    g = np.abs(np.asarray(gyro_b, dtype=float))
    f = np.linalg.norm(np.asarray(accel_b, dtype=float).reshape(-1, 3), axis=1)
    if g.size and np.nanmax(g) > MAX_GYRO_RAD_S:
        return (f"a gyro reads {np.nanmax(g):.4g} rad/s, above {MAX_GYRO_RAD_S:g} rad/s (4000 deg/s, the largest "
                "gyro full scale): rates must be in rad/s")  # fmt: skip
    if f.size and np.nanmax(f) > MAX_ACCEL_MPS2:
        return f"|specific force| reaches {np.nanmax(f):.4g} m/s^2 (over 100 g): accelerations must be in m/s^2"
    if f.size >= 10 and np.nanmedian(f) < MIN_MEDIAN_ACCEL_MPS2:
        return (f"median |specific force| is {np.nanmedian(f):.3g} m/s^2: in g? expected m/s^2 (about 9.8 m/s^2 "
                "unless in free fall)")  # fmt: skip
    return None
