"""Fix-quality metrics over a list of :class:`~magnav_ins.core.types.Fix` and the true positions, for
``metrics.json`` and the matcher comparisons.

* availability = fixes issued / fix attempts (Shockley 003 sec. 4.3.2);
* horizontal fix error bins < 3 m, 3-10 m, 10-20 m, > 20 m (as in Shockley 003 Figs. 4.8-4.19), as fractions of
  the fixes issued; ``fix_within_3m_fraction``;
* fix NEES ``e' P^-1 e`` with ``e`` the north/east error (m) and ``P`` the fix covariance: its mean is 2 for a
  consistent 2-D fix (chi-square with 2 degrees of freedom).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ...core.errors import InputError
from ...core.frames import latlon_to_meters, wrap_angle
from ...core.types import Fix

FloatArray = NDArray[np.float64]

#: Error bin edges (m) of Shockley's accuracy figures.
ERROR_BINS_M: tuple[float, ...] = (3.0, 10.0, 20.0)
BIN_NAMES: tuple[str, ...] = ("lt_3m", "3_to_10m", "10_to_20m", "gt_20m")


def _truth(fixes: Sequence[Fix], lat_true: ArrayLike, lon_true: ArrayLike) -> tuple[FloatArray, FloatArray]:
    lat = np.asarray(lat_true, float).ravel()
    lon = np.asarray(lon_true, float).ravel()
    if lat.shape != (len(fixes),) or lon.shape != (len(fixes),):
        raise InputError(
            f"fix metrics: expected one true position per fix ({len(fixes)}), got lat {lat.shape}, lon {lon.shape}"
        )
    return lat, lon


def fix_errors_ne(fixes: Sequence[Fix], lat_true: ArrayLike, lon_true: ArrayLike) -> FloatArray:
    """North/east error (m) of every fix, (N, 2); NaN rows for "no fix"."""
    lat, lon = _truth(fixes, lat_true, lon_true)
    out = np.full((len(fixes), 2), np.nan)
    for i, f in enumerate(fixes):
        if f.available:
            dn, de = latlon_to_meters(f.lat - lat[i], wrap_angle(f.lon - lon[i]), lat[i])
            out[i] = float(dn), float(de)
    return out


def availability(fixes: Sequence[Fix]) -> float:
    """Fixes issued / fix attempts (NaN for no attempts)."""
    return float(np.mean([f.available for f in fixes])) if len(fixes) else float("nan")


def fix_nees(fixes: Sequence[Fix], lat_true: ArrayLike, lon_true: ArrayLike) -> FloatArray:
    """NEES of every issued fix with a finite, positive-definite covariance (others dropped)."""
    err = fix_errors_ne(fixes, lat_true, lon_true)
    out = []
    for f, e in zip(fixes, err, strict=True):
        if not f.available:
            continue
        P = np.asarray(f.cov_ne, float)
        if not np.all(np.isfinite(P)) or np.linalg.det(P) <= 0 or P[0, 0] <= 0:
            continue
        out.append(float(e @ np.linalg.solve(P, e)))
    return np.asarray(out)


def error_bins(fixes: Sequence[Fix], lat_true: ArrayLike, lon_true: ArrayLike) -> dict[str, float]:
    """Fractions of the issued fixes with horizontal error < 3 m, 3-10 m, 10-20 m, > 20 m (NaN if none)."""
    err = fix_errors_ne(fixes, lat_true, lon_true)
    d = np.hypot(err[:, 0], err[:, 1])
    d = d[np.isfinite(d)]
    if d.size == 0:
        return {k: float("nan") for k in BIN_NAMES}
    idx = np.digitize(d, ERROR_BINS_M)
    return {name: float(np.mean(idx == k)) for k, name in enumerate(BIN_NAMES)}


def fix_within_3m_fraction(fixes: Sequence[Fix], lat_true: ArrayLike, lon_true: ArrayLike) -> float:
    """Fraction of the issued fixes within 3 m of the truth."""
    return error_bins(fixes, lat_true, lon_true)["lt_3m"]


def fix_metrics(fixes: Sequence[Fix], lat_true: ArrayLike, lon_true: ArrayLike) -> dict[str, float]:
    """All fix metrics in one JSON-ready dict: ``attempts``, ``fixes``, ``availability``, the error bins
    (``fix_error_lt_3m`` ...), ``fix_within_3m_fraction``, ``fix_rms_m``, ``fix_nees_mean``,
    ``fix_nees_count``."""
    err = fix_errors_ne(fixes, lat_true, lon_true)
    d = np.hypot(err[:, 0], err[:, 1])
    d = d[np.isfinite(d)]
    nees = fix_nees(fixes, lat_true, lon_true)
    bins = error_bins(fixes, lat_true, lon_true)
    out: dict[str, float] = {
        "attempts": float(len(fixes)),
        "fixes": float(d.size),
        "availability": availability(fixes),
        **{f"fix_error_{k}": v for k, v in bins.items()},
        "fix_within_3m_fraction": bins["lt_3m"],
        "fix_rms_m": float(np.sqrt(np.mean(d**2))) if d.size else float("nan"),
        "fix_nees_mean": float(np.mean(nees)) if nees.size else float("nan"),
        "fix_nees_count": float(nees.size),
    }
    return out


def no_fix_reasons(fixes: Sequence[Fix]) -> dict[str, int]:
    """Count of "no fix" reasons (the text before the first colon)."""
    out: dict[str, int] = {}
    for f in fixes:
        if not f.available:
            key = f.reason.split(":")[0] or "unspecified"
            out[key] = out.get(key, 0) + 1
    return out
