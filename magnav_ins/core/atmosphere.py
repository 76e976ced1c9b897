"""The ICAO standard atmosphere, troposphere only: pressure <-> altitude for a barometric height aid.

Values from ICAO Doc 7488/3, *Manual of the ICAO Standard Atmosphere* (3rd ed., 1993), Table A and Part I (identical
to the U.S. Standard Atmosphere 1976 below 32 km):

=====================================  ======================  ============================
sea-level pressure ``P0``              101 325 Pa
sea-level temperature ``T0``           288.15 K
temperature gradient ``L``             -6.5 K per km           geopotential height 0-11 km
standard gravity ``G0``                9.806 65 m/s^2
universal gas constant ``R*``          8 314.32 J/(kmol K)
molar mass of dry air ``M``            28.964 420 kg/kmol
Earth radius for geopotential ``r0``   6 356 766 m
=====================================  ======================  ============================

In the troposphere the hydrostatic equation with a linear temperature profile gives (Doc 7488 eq. 14)

    ``p = P0 (1 - L H / T0) ^ (G0 M / (R* L))``   and its inverse   ``H = T0 / L (1 - (p / P0) ^ (R* L / (G0 M)))``

with ``H`` the *geopotential* height and ``L`` = 0.0065 K/m (the exponent ``R* L / (G0 M)`` is 0.190263). Geometric
height ``h`` (what a GNSS or the INS gives) and geopotential height are related by ``H = r0 h / (r0 + h)``
(Doc 7488 eq. 8): 0.16 m apart at 1 km, 3.9 m at 5 km, and 1.3 cm per 100 m of climb at a few hundred metres. The
functions below take and return geometric heights unless ``geopotential=True``.

A barometer measures pressure, not height: on a non-standard day a pressure-altitude *difference* is off by the ratio
of the true to the standard mean temperature of the layer (about 3.5 % per 10 K), and weather moves the sea-level
pressure by about 1 hPa (8 m) per hour at worst. Referencing to the pressure at initialisation (the height aid of
:mod:`magnav_ins.mavlink.baro`) removes the sea-level pressure; what is left is that scale error and the drift.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .errors import InputError
from .units import G0

P0_PA = 101_325.0  #: ICAO sea-level pressure, Pa
T0_K = 288.15  #: ICAO sea-level temperature, K
LAPSE_K_PER_M = 0.0065  #: troposphere temperature gradient (temperature falls with height), K/m
R_STAR = 8_314.32  #: universal gas constant (Doc 7488 value), J/(kmol K)
M_AIR = 28.964_420  #: molar mass of dry air at sea level, kg/kmol
R_AIR = R_STAR / M_AIR  #: specific gas constant of dry air, J/(kg K) (287.05287)
R0_GEOPOTENTIAL_M = 6_356_766.0  #: nominal Earth radius for geopotential heights, m
TROPOPAUSE_H_M = 11_000.0  #: top of the troposphere, geopotential m
#: the exponent R L / (g M) of the troposphere formula (0.190263)
EXPONENT = R_AIR * LAPSE_K_PER_M / G0
#: pressure at the tropopause, Pa (22 632.06 Pa in Doc 7488): the formula's lower limit
TROPOPAUSE_P_PA = P0_PA * (1.0 - LAPSE_K_PER_M * TROPOPAUSE_H_M / T0_K) ** (1.0 / EXPONENT)

FloatArray = NDArray[np.float64]


def geopotential_m(h_m: ArrayLike) -> FloatArray | float:
    """Geopotential height (m) of a geometric height ``h_m`` (m): ``H = r0 h / (r0 + h)``."""
    h = np.asarray(h_m, dtype=float)
    out = R0_GEOPOTENTIAL_M * h / (R0_GEOPOTENTIAL_M + h)
    return float(out) if out.ndim == 0 else out


def geometric_m(geopotential_h_m: ArrayLike) -> FloatArray | float:
    """Geometric height (m) of a geopotential height ``H`` (m): ``h = r0 H / (r0 - H)``."""
    H = np.asarray(geopotential_h_m, dtype=float)
    out = R0_GEOPOTENTIAL_M * H / (R0_GEOPOTENTIAL_M - H)
    return float(out) if out.ndim == 0 else out


def isa_temperature_k(h_m: ArrayLike, *, geopotential: bool = False) -> FloatArray | float:
    """ISA temperature (K) at height ``h_m`` (m, geometric unless ``geopotential``), troposphere."""
    H = np.asarray(h_m, dtype=float) if geopotential else np.asarray(geopotential_m(h_m), dtype=float)
    _check_height(H)
    out = T0_K - LAPSE_K_PER_M * H
    return float(out) if out.ndim == 0 else out


def isa_pressure_pa(h_m: ArrayLike, *, p_ref_pa: float = P0_PA, geopotential: bool = False) -> FloatArray | float:
    """ISA static pressure (Pa) at height ``h_m`` (m above the level where the pressure is ``p_ref_pa``; geometric
    unless ``geopotential``). Troposphere only: heights above 11 km (geopotential) raise :class:`InputError`."""
    H = np.asarray(h_m, dtype=float) if geopotential else np.asarray(geopotential_m(h_m), dtype=float)
    _check_height(H)
    out = float(p_ref_pa) * (1.0 - LAPSE_K_PER_M * H / T0_K) ** (1.0 / EXPONENT)
    return float(out) if out.ndim == 0 else out


def pressure_altitude_m(
    pressure_pa: ArrayLike, *, p_ref_pa: float = P0_PA, geopotential: bool = False
) -> FloatArray | float:
    """Height (m) at which the ISA pressure is ``pressure_pa`` (Pa), above the level where it is ``p_ref_pa``
    (101 325 Pa: the standard pressure altitude; the QNH: the altitude above mean sea level). Geometric unless
    ``geopotential``. Non-finite, non-positive or above-the-troposphere pressures raise :class:`InputError`."""
    p = np.asarray(pressure_pa, dtype=float)
    if not (np.all(np.isfinite(p)) and np.all(p > 0.0)):
        raise InputError(f"pressure must be a finite positive number of Pa, got {_first_bad(p, p > 0.0)!r}")
    if not (np.isfinite(p_ref_pa) and p_ref_pa > 0.0):
        raise InputError(f"reference pressure must be a finite positive number of Pa, got {p_ref_pa!r}")
    H = T0_K / LAPSE_K_PER_M * (1.0 - (p / float(p_ref_pa)) ** EXPONENT)
    _check_height(H)
    out = H if geopotential else np.asarray(geometric_m(H), dtype=float)
    return float(out) if np.ndim(out) == 0 else out


def _check_height(H: FloatArray) -> None:
    ok = np.isfinite(H) & (H <= TROPOPAUSE_H_M + 1.0) & (H > -5_000.0)  # 1 m: rounded tropopause pressures
    if not np.all(ok):
        raise InputError(
            f"height {_first_bad(H, ok)!r} m (geopotential) is outside the ISA troposphere formula's range "
            f"(-5000 m to {TROPOPAUSE_H_M:.0f} m)"
        )


def _first_bad(x: FloatArray, ok: FloatArray) -> float:
    flat_x, flat_ok = np.atleast_1d(x), np.atleast_1d(ok & np.isfinite(x))
    return float(flat_x[int(np.argmin(flat_ok))])
