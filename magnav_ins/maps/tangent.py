"""Compiled (numba) conversions between geodetic coordinates and a map's local tangent plane, the hot path of
:meth:`GridMap.value` on local maps and of :meth:`GridMap.value_ne` on geodetic maps.

They are the point-wise twins of :func:`magnav_ins.core.frames.geodetic_to_ned` / :func:`~magnav_ins.core.frames.ned_to_geodetic`
(same WGS-84 constants, imported from there; tests check them against those functions):

* :func:`geodetic_to_tangent`: the point ``(lat, lon, h0)`` in NED about the origin ``(lat0, lon0, h0)``, keeping
  north and east (the down component, the Earth's curvature drop, is dropped).
* :func:`tangent_to_geodetic`: its exact inverse: the point of height ``h0`` whose tangent-plane north/east are
  ``(n, e)``, by Newton's method (two to three steps to 1e-15 rad within 100 km).
"""

from __future__ import annotations

import numba as nb
import numpy as np
from numpy.typing import NDArray

from ..core.frames import WGS84_A, WGS84_E2

_A, _E2 = WGS84_A, WGS84_E2


@nb.njit(cache=True, inline="always")
def _ecef(lat: float, lon: float, h: float) -> tuple[float, float, float]:
    sl, cl = np.sin(lat), np.cos(lat)
    r_e = _A / np.sqrt(1.0 - _E2 * sl * sl)
    return (r_e + h) * cl * np.cos(lon), (r_e + h) * cl * np.sin(lon), (r_e * (1.0 - _E2) + h) * sl


@nb.njit(cache=True)
def geodetic_to_tangent(
    lat: NDArray[np.float64], lon: NDArray[np.float64], lat0: float, lon0: float, h0: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """North, east (m) of the points ``(lat, lon, h0)`` (rad) in the tangent plane at ``(lat0, lon0, h0)``."""
    n = lat.shape[0]
    out_n = np.empty(n)
    out_e = np.empty(n)
    x0, y0, z0 = _ecef(lat0, lon0, h0)
    s0, c0 = np.sin(lat0), np.cos(lat0)
    so, co = np.sin(lon0), np.cos(lon0)
    for k in range(n):
        x, y, z = _ecef(lat[k], lon[k], h0)
        dx, dy, dz = x - x0, y - y0, z - z0
        out_n[k] = -s0 * co * dx - s0 * so * dy + c0 * dz
        out_e[k] = -so * dx + co * dy
    return out_n, out_e


@nb.njit(cache=True)
def tangent_to_geodetic(
    north: NDArray[np.float64], east: NDArray[np.float64], lat0: float, lon0: float, h0: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Latitude, longitude (rad) of the height-``h0`` points with tangent-plane ``(north, east)`` (m) at the origin
    ``(lat0, lon0, h0)``: the exact inverse of :func:`geodetic_to_tangent`, by Newton's method on it with the
    analytic Jacobian (``d r_e / d lat = (R_N + h) u_north``, ``d r_e / d lon = (R_E + h) cos(lat) u_east``,
    Groves eq. 2.105-2.106, projected on the origin's north/east axes)."""
    n = north.shape[0]
    out_lat = np.empty(n)
    out_lon = np.empty(n)
    x0, y0, z0 = _ecef(lat0, lon0, h0)
    s0, c0 = np.sin(lat0), np.cos(lat0)
    so, co = np.sin(lon0), np.cos(lon0)
    r_n0 = _A * (1.0 - _E2) / (1.0 - _E2 * s0 * s0) ** 1.5
    r_e0 = _A / np.sqrt(1.0 - _E2 * s0 * s0)
    for k in range(n):
        nn, ee = north[k], east[k]
        lat = lat0 + nn / (r_n0 + h0)
        lon = lon0 + ee / ((r_e0 + h0) * c0)
        for _ in range(8):
            sl, cl = np.sin(lat), np.cos(lat)
            sn, cn = np.sin(lon), np.cos(lon)
            w = 1.0 - _E2 * sl * sl
            r_e = _A / np.sqrt(w)
            r_n = r_e * (1.0 - _E2) / w
            dx = (r_e + h0) * cl * cn - x0
            dy = (r_e + h0) * cl * sn - y0
            dz = (r_e * (1.0 - _E2) + h0) * sl - z0
            fn = -s0 * co * dx - s0 * so * dy + c0 * dz - nn
            fe = -so * dx + co * dy - ee
            # Jacobian of (n, e) with respect to (lat, lon)
            a = r_n + h0
            b = (r_e + h0) * cl
            j11 = a * (s0 * co * sl * cn + s0 * so * sl * sn + c0 * cl)
            j12 = b * (s0 * co * sn - s0 * so * cn)
            j21 = a * (so * sl * cn - co * sl * sn)
            j22 = b * (so * sn + co * cn)
            det = j11 * j22 - j12 * j21
            dlat = (j22 * fn - j12 * fe) / det
            dlon = (j11 * fe - j21 * fn) / det
            lat -= dlat
            lon -= dlon
            if abs(dlat) < 1e-15 and abs(dlon) < 1e-15:
                break
        out_lat[k] = lat
        out_lon[k] = lon
    return out_lat, out_lon
