"""Earth model for the NED mechanisation: normal gravity, Earth rate, transport rate, Coriolis.

References: Groves, *Principles of GNSS, Inertial, and Multisensor Integrated Navigation Systems*, 2nd ed.
(2013), sec. 2.4-2.5 and 5.4; Heiskanen & Moritz, *Physical Geodesy* (1967) eq. 2-151 for normal gravity
above the ellipsoid (the closed form that Li & Goetze 2001 also use). All inputs rad / m / m/s; outputs SI.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..core.frames import (
    WGS84_A,
    WGS84_B,
    WGS84_E2,
    WGS84_F,
    WGS84_GAMMA_E,
    WGS84_GM,
    WGS84_K,
    WGS84_M,
    WGS84_OMEGA_E,
    radii_of_curvature,
)

_E_LIN = np.sqrt(WGS84_A**2 - WGS84_B**2)  # linear eccentricity, m


def somigliana(lat: ArrayLike) -> NDArray[np.float64]:
    """Normal gravity on the WGS-84 ellipsoid surface (m/s^2), Somigliana's formula (Groves eq. 2.134)."""
    s2 = np.sin(np.asarray(lat, dtype=float)) ** 2
    return WGS84_GAMMA_E * (1.0 + WGS84_K * s2) / np.sqrt(1.0 - WGS84_E2 * s2)


def _q(u: NDArray[np.float64]) -> NDArray[np.float64]:
    r = _E_LIN / u
    return 0.5 * ((1.0 + 3.0 / r**2) * np.arctan(r) - 3.0 / r)


def normal_gravity(lat: ArrayLike, h: ArrayLike) -> NDArray[np.float64]:
    """Magnitude of WGS-84 normal gravity (m/s^2) at geodetic latitude ``lat`` (rad) and ellipsoidal height
    ``h`` (m), exact closed form in ellipsoidal-harmonic coordinates (Heiskanen & Moritz eq. 2-151).

    Valid at any height above the ellipsoid; at ``h = 0`` it equals :func:`somigliana` to 1e-12 relative.
    """
    lat = np.asarray(lat, dtype=float)
    h = np.asarray(h, dtype=float)
    _, r_e = radii_of_curvature(lat)
    x = (r_e + h) * np.cos(lat)  # distance from the rotation axis
    z = (r_e * (1.0 - WGS84_E2) + h) * np.sin(lat)
    e2 = _E_LIN**2
    d = x**2 + z**2 - e2
    u2 = 0.5 * d * (1.0 + np.sqrt(1.0 + 4.0 * e2 * z**2 / d**2))
    u = np.sqrt(u2)
    beta = np.arctan2(z * np.sqrt(u2 + e2), u * x)
    sb2 = np.sin(beta) ** 2
    cb2 = 1.0 - sb2
    w = np.sqrt((u2 + e2 * sb2) / (u2 + e2))
    q0 = _q(np.asarray(WGS84_B))
    qp = 3.0 * (1.0 + u2 / e2) * (1.0 - (u / _E_LIN) * np.arctan(_E_LIN / u)) - 1.0
    om2 = WGS84_OMEGA_E**2
    gamma_u = (
        -(
            WGS84_GM / (u2 + e2)
            + om2 * WGS84_A**2 * _E_LIN / (u2 + e2) * (qp / q0) * (0.5 * sb2 - 1.0 / 6.0)
            - om2 * u * cb2
        )
        / w
    )
    gamma_beta = (om2 * WGS84_A**2 / np.sqrt(u2 + e2) * _q(u) / q0 - om2 * np.sqrt(u2 + e2)) * np.sqrt(sb2 * cb2) / w
    return np.hypot(gamma_u, gamma_beta)


def gravity_n(lat: ArrayLike, h: ArrayLike) -> NDArray[np.float64]:
    """Normal gravity vector (gravitation + centrifugal) in NED, shape ``(..., 3)`` m/s^2.

    Second-order height expansion (Groves eq. 2.139-2.140, NIMA TR8350.2 eq. 4-3): the down component
    is within 1e-6 m/s^2 (0.1 mGal) of :func:`normal_gravity` below 10 km; the north component is the deflection of
    the normal plumb line, -8.08e-9 h sin(2 lat).
    """
    lat = np.asarray(lat, dtype=float)
    h = np.asarray(h, dtype=float)
    s2 = np.sin(lat) ** 2
    g0 = somigliana(lat)
    g_d = g0 * (1.0 - 2.0 / WGS84_A * (1.0 + WGS84_F + WGS84_M - 2.0 * WGS84_F * s2) * h + 3.0 * h**2 / WGS84_A**2)
    g_n = -8.08e-9 * h * np.sin(2.0 * lat)
    return np.stack(np.broadcast_arrays(g_n, np.zeros_like(g_d), g_d), axis=-1)


def gravity_n_point(lat: float, h: float) -> NDArray[np.float64]:
    """:func:`gravity_n` at one point (3,): the same operations in the same order on scalars (``h * h`` is what
    ``h**2`` of an array computes), so the same numbers bit for bit, without the array handling."""
    lat, h = np.float64(lat), np.float64(h)
    s2 = np.sin(lat) ** 2
    g0 = WGS84_GAMMA_E * (1.0 + WGS84_K * s2) / np.sqrt(1.0 - WGS84_E2 * s2)  # somigliana(lat)
    g_d = g0 * (1.0 - 2.0 / WGS84_A * (1.0 + WGS84_F + WGS84_M - 2.0 * WGS84_F * s2) * h + 3.0 * (h * h) / WGS84_A**2)
    g_n = -8.08e-9 * h * np.sin(2.0 * lat)
    return np.array([g_n, 0.0, g_d])


def omega_ie_n(lat: ArrayLike) -> NDArray[np.float64]:
    """Earth rotation rate resolved in NED (rad/s), shape ``(..., 3)``: ``[w cos(lat), 0, -w sin(lat)]``."""
    lat = np.asarray(lat, dtype=float)
    return np.stack(
        np.broadcast_arrays(WGS84_OMEGA_E * np.cos(lat), np.zeros_like(lat), -WGS84_OMEGA_E * np.sin(lat)), axis=-1
    )


def omega_en_n(lat: ArrayLike, h: ArrayLike, v_n: ArrayLike) -> NDArray[np.float64]:
    """Transport rate (rotation of NED w.r.t. ECEF) in NED (rad/s), Groves eq. 5.44."""
    lat = np.asarray(lat, dtype=float)
    h = np.asarray(h, dtype=float)
    v_n = np.asarray(v_n, dtype=float)
    r_n, r_e = radii_of_curvature(lat)
    return np.stack(
        [
            v_n[..., 1] / (r_e + h),
            -v_n[..., 0] / (r_n + h),
            -v_n[..., 1] * np.tan(lat) / (r_e + h),
        ],
        axis=-1,
    )


def coriolis_n(lat: ArrayLike, h: ArrayLike, v_n: ArrayLike) -> NDArray[np.float64]:
    """Coriolis and transport-rate acceleration ``-(2 omega_ie_n + omega_en_n) x v_n`` (m/s^2), Groves eq. 5.54."""
    w = 2.0 * omega_ie_n(lat) + omega_en_n(lat, h, v_n)
    return -np.cross(w, np.asarray(v_n, dtype=float))
