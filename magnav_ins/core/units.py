"""Named unit conversions. Multiply a value in the unit on the left of ``_TO_`` to get the unit on the right.

Everything inside the package is SI; these constants are used only at the edges (files, CLI, presets).
"""

from __future__ import annotations

import math

DEG_TO_RAD = math.pi / 180.0
RAD_TO_DEG = 180.0 / math.pi
ARCSEC_TO_RAD = DEG_TO_RAD / 3600.0

HOUR_TO_S = 3600.0
SQRT_HOUR_TO_SQRT_S = 60.0  # sqrt(3600 s)

DEG_PER_H_TO_RAD_PER_S = DEG_TO_RAD / HOUR_TO_S
#: angle random walk deg/sqrt(h) -> rad/sqrt(s) (= rad/s/sqrt(Hz))
DEG_PER_SQRT_H_TO_RAD_PER_SQRT_S = DEG_TO_RAD / SQRT_HOUR_TO_SQRT_S
#: gyro noise density deg/h/sqrt(Hz) -> rad/s/sqrt(Hz)
DEG_PER_H_PER_SQRT_HZ_TO_RAD_PER_S_PER_SQRT_HZ = DEG_PER_H_TO_RAD_PER_S
#: velocity random walk m/s/sqrt(h) -> m/s/sqrt(s) (= m/s^2/sqrt(Hz))
MPS_PER_SQRT_H_TO_MPS_PER_SQRT_S = 1.0 / SQRT_HOUR_TO_SQRT_S

PPM = 1e-6
G0 = 9.80665  # standard gravity, m/s^2 (for specs quoted in g / micro-g)
MICRO_G_TO_MPS2 = 1e-6 * G0
MGAL_TO_MPS2 = 1e-5
MPS2_TO_MGAL = 1e5

NT_PER_GAUSS = 1e5
NT_PER_MILLIGAUSS = 100.0
NT_PER_MICROTESLA = 1e3

KNOT_TO_MPS = 1852.0 / 3600.0
