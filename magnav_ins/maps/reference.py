"""Reference fields: the IGRF main magnetic field (via ``ppigrf``) and normal gravity, and the conversions
between full fields and the anomalies/disturbances that maps hold.

This is the only module that imports ``ppigrf``. ``ppigrf.igrf(lon_deg, lat_deg, h_km, date)`` works in geodetic
coordinates and returns ``(B_east, B_north, B_up)`` in nT; here everything is rad / m in and NED nT out.

* Main field (IGRF-14, Alken et al. 2025; IGRF-13, Alken et al. 2021, Earth Planets Space 73:49).
* Total-field anomaly: ``dT = |B| - |B_IGRF|`` (Canciani & Raquet 2016 sec. II; the scalar map value).
  For an anomaly small next to the main field, ``dT ~= b_hat . dB`` with ``b_hat`` the main-field direction
  (Blakely, *Potential Theory in Gravity and Magnetic Applications*, 1995, eq. 12.1).
* Gravity disturbance: ``dg = g(P) - gamma(P)`` at the same point (Hofmann-Wellenhof & Moritz, *Physical
  Geodesy*, 2006, eq. 2-142), with ``gamma`` the exact WGS-84 normal gravity of :func:`magnav_ins.ins.earth.normal_gravity`.
"""

from __future__ import annotations

import datetime as _dt

import numpy as np
import ppigrf
from numpy.typing import ArrayLike, NDArray

from ..core.errors import InputError
from ..core.units import MPS2_TO_MGAL, RAD_TO_DEG
from ..ins.earth import normal_gravity

FloatArray = NDArray[np.float64]

M_TO_KM = 1e-3

DateLike = _dt.datetime | _dt.date | np.datetime64 | float | str


def to_datetime(date: DateLike) -> _dt.datetime:
    """A date as :class:`datetime.datetime`. Accepts a ``datetime``/``date``, a ``numpy.datetime64``, an ISO
    string (``"2020-06-01"``) or a decimal year (``2020.42``)."""
    if isinstance(date, _dt.datetime):
        return date
    if isinstance(date, _dt.date):
        return _dt.datetime(date.year, date.month, date.day)
    if isinstance(date, np.datetime64):
        return _dt.datetime.fromisoformat(str(date.astype("datetime64[us]")))
    if isinstance(date, str):
        try:
            return _dt.datetime.fromisoformat(date)
        except ValueError as exc:
            raise InputError(f"date {date!r}: expected an ISO date such as '2020-06-01'") from exc
    if isinstance(date, int | float | np.floating | np.integer):
        year = int(np.floor(date))
        if not 1900 <= year <= 2035:
            raise InputError(f"date {date!r}: decimal year outside the IGRF range 1900-2035")
        start = _dt.datetime(year, 1, 1)
        days = (_dt.datetime(year + 1, 1, 1) - start).days
        return start + _dt.timedelta(days=(float(date) - year) * days)
    raise InputError(f"date {date!r}: expected a datetime, date, numpy.datetime64, ISO string or decimal year")


def _broadcast(lat: ArrayLike, lon: ArrayLike, h: ArrayLike) -> tuple[FloatArray, FloatArray, FloatArray]:
    lat_a, lon_a, h_a = np.broadcast_arrays(
        np.atleast_1d(np.asarray(lat, float)),
        np.atleast_1d(np.asarray(lon, float)),
        np.atleast_1d(np.asarray(h, float)),
    )
    if lat_a.ndim != 1:
        raise InputError(f"lat/lon/h: expected 1-D arrays or scalars, got shape {lat_a.shape}")
    if np.any(np.abs(lat_a) > np.pi / 2 + 1e-12):
        raise InputError(f"lat: expected radians in [-pi/2, pi/2], got max |lat| = {np.max(np.abs(lat_a)):.6g}")
    return lat_a, lon_a, h_a


def igrf_ned(lat: ArrayLike, lon: ArrayLike, h: ArrayLike, date: DateLike) -> FloatArray:
    """IGRF main field in NED components (nT), shape ``(N, 3)``.

    ``lat``, ``lon`` geodetic (rad), ``h`` ellipsoidal height (m), one ``date`` for all points (see
    :func:`to_datetime`). North and down are relative to the ellipsoid normal (geodetic frame).
    """
    lat_a, lon_a, h_a = _broadcast(lat, lon, h)
    when = to_datetime(date)
    b_e, b_n, b_u = ppigrf.igrf(lon_a * RAD_TO_DEG, lat_a * RAD_TO_DEG, h_a * M_TO_KM, when)
    # ppigrf returns shape (n_dates=1, N)
    return np.stack([np.asarray(b_n)[0], np.asarray(b_e)[0], -np.asarray(b_u)[0]], axis=-1)


def igrf_total(lat: ArrayLike, lon: ArrayLike, h: ArrayLike, date: DateLike) -> FloatArray:
    """IGRF total intensity ``|B|`` (nT), shape ``(N,)``. Positions rad / m as :func:`igrf_ned`."""
    return np.linalg.norm(igrf_ned(lat, lon, h, date), axis=-1)


def declination_inclination(b_ned: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Declination ``atan2(B_E, B_N)`` and inclination ``atan2(B_D, H)`` (rad) of NED field vectors (..., 3)."""
    b = np.asarray(b_ned, float)
    return np.arctan2(b[..., 1], b[..., 0]), np.arctan2(b[..., 2], np.hypot(b[..., 0], b[..., 1]))


def total_field_to_anomaly(
    total_nt: ArrayLike, lat: ArrayLike, lon: ArrayLike, h: ArrayLike, date: DateLike
) -> FloatArray:
    """Scalar total-field anomaly ``|B| - |B_IGRF|`` (nT) from measured total intensity (nT)."""
    return np.asarray(total_nt, float) - igrf_total(lat, lon, h, date)


def anomaly_to_total_field(
    anomaly_nt: ArrayLike, lat: ArrayLike, lon: ArrayLike, h: ArrayLike, date: DateLike
) -> FloatArray:
    """Total intensity (nT) from a total-field anomaly (nT): the inverse of :func:`total_field_to_anomaly`."""
    return np.asarray(anomaly_nt, float) + igrf_total(lat, lon, h, date)


def vector_to_anomaly(b_ned_nt: ArrayLike, lat: ArrayLike, lon: ArrayLike, h: ArrayLike, date: DateLike) -> FloatArray:
    """Vector anomaly ``B - B_IGRF`` (NED nT, shape (N, 3)) from measured NED field vectors (nT)."""
    return np.asarray(b_ned_nt, float) - igrf_ned(lat, lon, h, date)


def project_anomaly(anomaly_ned_nt: ArrayLike, main_ned_nt: ArrayLike) -> FloatArray:
    """Linearised total-field anomaly ``b_hat . dB`` (nT) of a vector anomaly ``dB`` in a main field with NED
    components ``main_ned_nt`` (Blakely 1995 eq. 12.1); exact to O(|dB|^2 / |B|)."""
    main = np.asarray(main_ned_nt, float)
    b_hat = main / np.linalg.norm(main, axis=-1, keepdims=True)
    return np.sum(np.asarray(anomaly_ned_nt, float) * b_hat, axis=-1)


def normal_gravity_mgal(lat: ArrayLike, h: ArrayLike) -> FloatArray:
    """WGS-84 normal gravity magnitude (mGal) at geodetic ``lat`` (rad) and ellipsoidal ``h`` (m)."""
    return normal_gravity(lat, h) * MPS2_TO_MGAL


def gravity_disturbance_mgal(g_full_mgal: ArrayLike, lat: ArrayLike, h: ArrayLike) -> FloatArray:
    """Gravity disturbance ``g - gamma`` (mGal): measured gravity magnitude (mGal) minus WGS-84 normal gravity at
    the same point (``lat`` rad, ``h`` ellipsoidal m); Hofmann-Wellenhof & Moritz (2006) eq. 2-142."""
    return np.asarray(g_full_mgal, float) - normal_gravity_mgal(lat, h)


def full_gravity_mgal(disturbance_mgal: ArrayLike, lat: ArrayLike, h: ArrayLike) -> FloatArray:
    """Gravity magnitude (mGal) from a disturbance (mGal): the inverse of :func:`gravity_disturbance_mgal`."""
    return np.asarray(disturbance_mgal, float) + normal_gravity_mgal(lat, h)
