"""WGS-84 geodesy and frame conversions (geodetic, ECEF, local NED) and attitude helpers.

Angles are radians, heights are ellipsoidal metres, NED is North-East-Down, body is FRD.
Rotations go through :class:`scipy.spatial.transform.Rotation` (quaternions scalar-last).
All functions accept scalars or arrays and broadcast.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

# --- WGS-84 defining and derived constants -------------------------------------------------------------
WGS84_A = 6378137.0  #: semi-major axis, m
WGS84_F = 1.0 / 298.257223563  #: flattening
WGS84_B = WGS84_A * (1.0 - WGS84_F)  #: semi-minor axis, m
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)  #: first eccentricity squared
WGS84_EP2 = WGS84_E2 / (1.0 - WGS84_E2)  #: second eccentricity squared
WGS84_GM = 3.986004418e14  #: geocentric gravitational constant, m^3/s^2
WGS84_OMEGA_E = 7.292115e-5  #: Earth rotation rate, rad/s
WGS84_GAMMA_E = 9.7803253359  #: normal gravity at the equator, m/s^2
WGS84_GAMMA_P = 9.8321849378  #: normal gravity at the poles, m/s^2
WGS84_K = (WGS84_B * WGS84_GAMMA_P) / (WGS84_A * WGS84_GAMMA_E) - 1.0  #: Somigliana constant
WGS84_M = WGS84_OMEGA_E**2 * WGS84_A**2 * WGS84_B / WGS84_GM  #: omega^2 a^2 b / GM


def radii_of_curvature(lat: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Meridian (north-south) radius ``R_N`` and prime-vertical (east-west) radius ``R_E`` in metres.

    Groves (2013) eq. 2.105-2.106. ``R_N = a(1-e^2)/(1-e^2 sin^2 lat)^1.5``, ``R_E = a/sqrt(1-e^2 sin^2 lat)``.
    """
    s2 = np.sin(np.asarray(lat, dtype=float)) ** 2
    den = 1.0 - WGS84_E2 * s2
    r_e = WGS84_A / np.sqrt(den)
    r_n = WGS84_A * (1.0 - WGS84_E2) / den**1.5
    return r_n, r_e


def geodetic_to_ecef(lat: ArrayLike, lon: ArrayLike, h: ArrayLike) -> NDArray[np.float64]:
    """Geodetic (rad, rad, m) to ECEF coordinates, shape ``(..., 3)`` in metres."""
    lat = np.asarray(lat, dtype=float)
    lon = np.asarray(lon, dtype=float)
    h = np.asarray(h, dtype=float)
    _, r_e = radii_of_curvature(lat)
    cl = np.cos(lat)
    x = (r_e + h) * cl * np.cos(lon)
    y = (r_e + h) * cl * np.sin(lon)
    z = (r_e * (1.0 - WGS84_E2) + h) * np.sin(lat)
    return np.stack(np.broadcast_arrays(x, y, z), axis=-1)


def _bowring(x, y, z):  # noqa: ANN001, ANN202
    """Bowring's latitude with two refinements on ECEF x, y, z (m; arrays or numpy scalars alike)."""
    lon = np.arctan2(y, x)
    p = np.hypot(x, y)
    beta = np.arctan2(z * WGS84_A, p * WGS84_B)
    lat = np.arctan2(z + WGS84_EP2 * WGS84_B * np.sin(beta) ** 3, p - WGS84_E2 * WGS84_A * np.cos(beta) ** 3)
    for _ in range(2):
        beta = np.arctan2((1.0 - WGS84_F) * np.sin(lat), np.cos(lat))
        lat = np.arctan2(z + WGS84_EP2 * WGS84_B * np.sin(beta) ** 3, p - WGS84_E2 * WGS84_A * np.cos(beta) ** 3)
    cl = np.cos(lat)
    sl = np.sin(lat)
    h = p * cl + z * sl - WGS84_A * np.sqrt(1.0 - WGS84_E2 * sl * sl)
    return lat, lon, h


def ecef_to_geodetic(r_e: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """ECEF (..., 3) metres to geodetic latitude, longitude (rad) and ellipsoidal height (m).

    Bowring's method with two refinements; error below 1e-9 m for heights from -10 km to 1000 km.
    """
    r = np.asarray(r_e, dtype=float)
    x, y, z = r[..., 0], r[..., 1], r[..., 2]
    return _bowring(x, y, z)


def ecef_to_geodetic_point(x: float, y: float, z: float) -> tuple[np.float64, np.float64, np.float64]:
    """:func:`ecef_to_geodetic` of one ECEF point (m): the same operations in the same order on scalars, so the
    same numbers bit for bit, without the array handling that dominates it for one point (fusers convert every IMU
    sample)."""
    x, y, z = np.float64(x), np.float64(y), np.float64(z)
    return _bowring(x, y, z)


def C_en_point(lat: float, lon: float) -> NDArray[np.float64]:
    """:func:`C_en` at one point (3, 3): the same numbers, without the broadcasting."""
    sl, cl = np.sin(np.float64(lat)), np.cos(np.float64(lat))
    so, co = np.sin(np.float64(lon)), np.cos(np.float64(lon))
    return np.array([[-sl * co, -so, -cl * co], [-sl * so, co, -cl * so], [cl, 0.0, -sl]])


def C_en(lat: ArrayLike, lon: ArrayLike) -> NDArray[np.float64]:
    """Matrix projecting NED vectors into ECEF (``x_e = C_en @ x_n``), shape ``(..., 3, 3)``."""
    lat = np.asarray(lat, dtype=float)
    lon = np.asarray(lon, dtype=float)
    sl, cl = np.sin(lat), np.cos(lat)
    so, co = np.sin(lon), np.cos(lon)
    m = np.empty(np.broadcast(lat, lon).shape + (3, 3))
    m[..., 0, 0] = -sl * co
    m[..., 0, 1] = -so
    m[..., 0, 2] = -cl * co
    m[..., 1, 0] = -sl * so
    m[..., 1, 1] = co
    m[..., 1, 2] = -cl * so
    m[..., 2, 0] = cl
    m[..., 2, 1] = 0.0
    m[..., 2, 2] = -sl
    return m


def geodetic_to_ned(
    lat: ArrayLike, lon: ArrayLike, h: ArrayLike, lat0: float, lon0: float, h0: float
) -> NDArray[np.float64]:
    """Geodetic points to local NED (m) about the origin ``(lat0, lon0, h0)``, shape ``(..., 3)``."""
    d_e = geodetic_to_ecef(lat, lon, h) - geodetic_to_ecef(lat0, lon0, h0)
    return np.einsum("ji,...j->...i", C_en(lat0, lon0), d_e)


def ned_to_geodetic(
    r_n: ArrayLike, lat0: float, lon0: float, h0: float
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Local NED points (m, shape ``(..., 3)``) about ``(lat0, lon0, h0)`` back to geodetic (rad, rad, m)."""
    r_e = geodetic_to_ecef(lat0, lon0, h0) + np.einsum("ij,...j->...i", C_en(lat0, lon0), np.asarray(r_n, float))
    return ecef_to_geodetic(r_e)


def meters_to_latlon(
    d_north: ArrayLike, d_east: ArrayLike, lat: ArrayLike, h: ArrayLike = 0.0
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Small north/east displacements (m) at ``(lat, h)`` to latitude/longitude increments (rad)."""
    r_n, r_e = radii_of_curvature(lat)
    h = np.asarray(h, dtype=float)
    return np.asarray(d_north) / (r_n + h), np.asarray(d_east) / ((r_e + h) * np.cos(lat))


def latlon_to_meters(
    d_lat: ArrayLike, d_lon: ArrayLike, lat: ArrayLike, h: ArrayLike = 0.0
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Small latitude/longitude increments (rad) at ``(lat, h)`` to north/east displacements (m)."""
    r_n, r_e = radii_of_curvature(lat)
    h = np.asarray(h, dtype=float)
    return np.asarray(d_lat) * (r_n + h), np.asarray(d_lon) * (r_e + h) * np.cos(lat)


def horizontal_error_m(lat: ArrayLike, lon: ArrayLike, lat_true: ArrayLike, lon_true: ArrayLike) -> NDArray[np.float64]:
    """Horizontal distance (m) between estimated and true positions (local-tangent approximation, < 1e-6 rel.
    error below 100 km separation)."""
    lat_true = np.asarray(lat_true, float)
    dn, de = latlon_to_meters(np.asarray(lat) - lat_true, wrap_angle(np.asarray(lon) - lon_true), lat_true)
    return np.hypot(dn, de)


def wrap_angle(a: ArrayLike) -> NDArray[np.float64]:
    """Wrap angles (rad) into ``[-pi, pi)``."""
    return (np.asarray(a, dtype=float) + np.pi) % (2.0 * np.pi) - np.pi


# --- attitude ------------------------------------------------------------------------------------------
def q_nb_from_euler(roll: ArrayLike, pitch: ArrayLike, yaw: ArrayLike) -> NDArray[np.float64]:
    """Body->NED quaternion (scalar-last) from roll, pitch, yaw (rad; aerospace Z-Y-X sequence)."""
    angles = np.stack(
        np.broadcast_arrays(np.asarray(yaw, float), np.asarray(pitch, float), np.asarray(roll, float)), -1
    )
    return Rotation.from_euler("ZYX", angles).as_quat()


def euler_from_q_nb(q_nb: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Roll, pitch, yaw (rad) from a body->NED quaternion (scalar-last)."""
    ypr = Rotation.from_quat(np.asarray(q_nb, float)).as_euler("ZYX")
    return ypr[..., 2], ypr[..., 1], ypr[..., 0]


def C_nb_from_q(q_nb: ArrayLike) -> NDArray[np.float64]:
    """Direction cosine matrix ``C_nb`` (``x_n = C_nb @ x_b``) from a scalar-last quaternion."""
    return Rotation.from_quat(np.asarray(q_nb, float)).as_matrix()


def skew(v: ArrayLike) -> NDArray[np.float64]:
    """Skew-symmetric (cross-product) matrix of ``v`` (``skew(a) @ b == cross(a, b)``), shape ``(..., 3, 3)``."""
    v = np.asarray(v, dtype=float)
    m = np.zeros(v.shape[:-1] + (3, 3))
    m[..., 0, 1] = -v[..., 2]
    m[..., 0, 2] = v[..., 1]
    m[..., 1, 0] = v[..., 2]
    m[..., 1, 2] = -v[..., 0]
    m[..., 2, 0] = -v[..., 1]
    m[..., 2, 1] = v[..., 0]
    return m
