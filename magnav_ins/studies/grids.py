"""Gravity grids as downloaded (Geoscience Australia, Sandwell-Smith): read with an explicit unit, continued upward.

Interim reader for the gravity comparison studies (issue 16) until :mod:`magnav_ins.maps.io` reads every format with
a unit of its own. A file whose variable states a field unit (``units = "mGal"``) is read as it says; one whose
``units`` attribute is not a field unit (GA's ``QLDWestGravity.nc`` says ``"Degree"``, while the values are um/s^2,
i.e. 0.1 mGal; ``../shared/data/PROVENANCE.md`` sec. 6) is refused unless the caller states the unit: nothing is
guessed. A stated unit that contradicts a valid file unit is refused too.

:func:`read_gravity_grid` returns a geodetic :class:`~magnav_ins.maps.grid.GridMap` in mGal; with ``continue_to_m``
the grid is continued upward from its surface (``altitude_m``) by FFT (:mod:`magnav_ins.maps.continuation`,
Blakely 1995 eq. 12.6). Scenario files reach it through ``[map] options`` (:func:`magnav_ins.studies.model.build_map`):
``unit``, ``altitude_m``, ``datum``, ``variable``, ``continue_to_m``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..core.errors import MapError
from ..core.types import FieldKind
from ..core.units import DEG_TO_RAD

#: gravity units accepted (lower-case, spaces removed) -> factor to mGal
GRAVITY_UNITS_TO_MGAL = {
    "mgal": 1.0,
    "um/s^2": 0.1,
    "um/s2": 0.1,
    "µm/s^2": 0.1,
    "micrometre/s^2": 0.1,
    "gu": 0.1,  # gravity unit = 1 um/s^2
    "m/s^2": 1e5,
    "m/s2": 1e5,
}


def _unit_factor(unit: str) -> float | None:
    return GRAVITY_UNITS_TO_MGAL.get(str(unit).strip().lower().replace(" ", ""))


def read_gravity_grid(
    path: str | Path,
    *,
    unit: str | None = None,
    altitude_m: float | None = None,
    datum: str | None = None,
    variable: str | None = None,
    kind: FieldKind | str = FieldKind.GRAVITY_DISTURBANCE_MGAL,
    continue_to_m: float | None = None,
    name: str | None = None,
) -> object:
    """A gravity grid (lat/lon in degrees, any COARDS/CF NetCDF) as a geodetic ``GridMap`` in mGal.

    ``unit``: the values' unit when the file's ``units`` attribute is missing or not a gravity unit (keys of
    :data:`GRAVITY_UNITS_TO_MGAL`); ``altitude_m``: ellipsoidal height of the grid surface (m; required unless the
    file has ``altitude_m``); ``datum``: required unless the file has ``geodetic_datum`` (only WGS-84-compatible
    datums are accepted by :class:`GridMap`); ``variable``: the data variable when the file holds several;
    ``continue_to_m``: continue the field upward to this height (m, >= ``altitude_m``)."""
    import xarray as xr

    from ..maps.continuation import upward_continue
    from ..maps.grid import GridMap

    path = Path(path)
    if not path.is_file():
        raise MapError(f"{path}: no such grid file")
    try:
        ds = xr.load_dataset(path)
    except Exception as exc:  # noqa: BLE001 - any reader failure is a bad file for the user
        raise MapError(f"{path}: cannot be read as NetCDF ({type(exc).__name__}: {exc})") from None
    names = [str(v) for v in ds.data_vars]
    if variable is None:
        if len(names) != 1:
            raise MapError(f"{path}: holds {len(names)} data variables {sorted(names)}; choose one with variable=NAME")
        variable = names[0]
    if variable not in ds.data_vars:
        raise MapError(f"{path}: no variable {variable!r}; it holds {sorted(names)}")
    da = ds[variable]
    where = f"{path} variable '{variable}'"
    file_unit = da.attrs.get("units")
    file_factor = _unit_factor(file_unit) if file_unit is not None else None
    if unit is not None:
        factor = _unit_factor(unit)
        if factor is None:
            raise MapError(
                f"{where}: unit {unit!r} is not a gravity unit; expected one of {sorted(GRAVITY_UNITS_TO_MGAL)}"
            )
        if file_factor is not None and file_factor != factor:
            raise MapError(f"{where}: the file says units={file_unit!r} but unit={unit!r} was given")
    elif file_factor is not None:
        factor = file_factor
    else:
        said = "no 'units' attribute" if file_unit is None else f"units={file_unit!r}, which is not a gravity unit"
        raise MapError(f'{where}: {said}; state the values\' unit (map option unit = "mGal" | "um/s^2" | "m/s^2")')
    alt = altitude_m if altitude_m is not None else ds.attrs.get("altitude_m")
    if alt is None:
        raise MapError(f"{path}: the grid surface height is not stated; give altitude_m (m above the ellipsoid)")
    the_datum = datum if datum is not None else ds.attrs.get("geodetic_datum")
    if the_datum is None:
        raise MapError(f'{path}: the geodetic datum is not stated; give datum (e.g. "WGS84")')
    dims = list(da.dims)
    ydim = next((d for d in dims if d in ("latitude", "lat")), None)
    xdim = next((d for d in dims if d in ("longitude", "lon")), None)
    if ydim is None or xdim is None or len(dims) != 2:
        raise MapError(f"{where}: expected dimensions (latitude, longitude), found {dims}")
    da = da.transpose(ydim, xdim)
    lat = np.asarray(ds[ydim].values, float)
    lon = np.asarray(ds[xdim].values, float)
    vals = np.asarray(da.values, float) * factor
    if lat[1] < lat[0]:
        lat, vals = lat[::-1], vals[::-1]
    if lon[1] < lon[0]:
        lon, vals = lon[::-1], vals[:, ::-1]
    # float32 coordinates of downloaded grids are regular only to ~1e-7 deg: rebuild them exactly
    lat = np.linspace(lat[0], lat[-1], lat.size)
    lon = np.linspace(lon[0], lon[-1], lon.size)
    try:
        fmap = GridMap(
            lat * DEG_TO_RAD,
            lon * DEG_TO_RAD,
            vals,
            kind=kind,
            frame="geodetic",
            altitude_m=float(alt),
            datum=str(the_datum),
            name=name or path.stem,
            metadata={"source_file": path.name, "source_variable": variable, "source_unit": str(unit or file_unit)},
        )
        if continue_to_m is not None:
            fmap = upward_continue(fmap, float(continue_to_m))
    except MapError as exc:
        raise MapError(f"{path}: {exc}") from None
    return fmap
