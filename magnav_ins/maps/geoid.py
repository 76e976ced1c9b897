"""The shipped global geoid: EIGEN-6C4 geoid heights above the WGS-84 ellipsoid on a 10' grid.

Survey files often give orthometric heights ``H`` (above the geoid, "above sea level"); navigation needs ellipsoidal
heights ``h = H + N`` (Hofmann-Wellenhof & Moritz, *Physical Geodesy*, eq. 4-56), with ``N`` the geoid undulation.
:func:`geoid_undulation` gives ``N`` (m) anywhere on Earth by bilinear interpolation of the EIGEN-6C4 model's geoid
(Förste et al. 2014, doi:10.5880/icgem.2015.1, degree 720, tide-free, computed by the ICGEM calculation service and
compiled by Fatiando a Terra, CC-BY-4.0; attribution in ``magnav_ins/data/DATA_LICENSES.md``).

Stored in ``magnav_ins/data/eigen6c4-geoid-10arcmin.nc``: 1081 x 2160 nodes (lat -90..90, lon -180..180 - 10'), int16
in units of 0.1 m (the resolution of the published grid), zlib-compressed (1.3 MB); ``bench/make_builtin_maps.py``
regenerates it from ``../shared/data/fatiando/earth-geoid-10arcmin.nc``. At 10' (~18 km) the model omits the geoid's
short wavelengths: its difference to a local geoid is typically 0.1-0.5 m, far below the tens of metres a survey
height may be off by without it.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..core.errors import MapError
from ..core.units import DEG_TO_RAD
from . import interp
from .shipped import data_path

FloatArray = NDArray[np.float64]

#: file in magnav_ins/data holding the geoid grid
GEOID_FILE = "eigen6c4-geoid-10arcmin.nc"
#: one-line description used in log lines and map metadata
GEOID_NAME = "EIGEN-6C4 geoid (10', shipped with magnav_ins)"


@lru_cache(maxsize=1)
def _grid() -> tuple[FloatArray, float, float, float, float]:
    """(values (ny, nx, 1) m, lat0, dlat, lon0, dlon) in rad; read once (the file is read-only package data)."""
    import xarray as xr

    path = data_path(GEOID_FILE)
    if not path.is_file():
        raise MapError(
            f"{path}: the shipped geoid is missing from the installed package (run bench/make_builtin_maps.py)"
        )
    ds = xr.load_dataset(path)
    lat = np.asarray(ds["latitude"].values, dtype=float) * DEG_TO_RAD
    lon = np.asarray(ds["longitude"].values, dtype=float) * DEG_TO_RAD
    n = np.asarray(ds["geoid"].values, dtype=float)
    n = np.ascontiguousarray(np.concatenate([n, n[:, :1]], axis=1))  # the wrap column (lon + 360 deg) for the last cell
    return n, float(lat[0]), float(lat[1] - lat[0]), float(lon[0]), float(lon[1] - lon[0])


def geoid_undulation(lat: ArrayLike, lon: ArrayLike) -> FloatArray:
    """EIGEN-6C4 geoid height ``N`` (m above the WGS-84 ellipsoid) at ``lat``, ``lon`` (rad), bilinear on the 10'
    grid (longitude wraps around the globe). Shape of the broadcast inputs."""
    la, lo = np.broadcast_arrays(np.asarray(lat, dtype=float), np.asarray(lon, dtype=float))
    v, y0, dy, x0, dx = _grid()
    out = interp.bilinear_scalar(
        v, y0, dy, x0, dx, np.ascontiguousarray(la.ravel()), np.ascontiguousarray(lo.ravel()), 2.0 * np.pi
    )
    if np.isnan(out).any():
        i = int(np.flatnonzero(np.isnan(out))[0])
        raise MapError(f"geoid: latitude {la.ravel()[i] / DEG_TO_RAD!r} deg is outside [-90, 90] (or NaN)")
    return out.reshape(la.shape)
