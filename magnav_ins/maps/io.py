"""Map and survey files: CF-1.8 NetCDF grids (xarray) and survey CSV / CSV.xz line data (pandas).

NetCDF layout written by :func:`write_map` (and required by :func:`read_map`)
-------------------------------------------------------------------------------
* One data variable named after the kind (e.g. ``total_field_anomaly_nt``) with attribute ``units`` (``nT`` /
  ``mGal``) and attribute ``magnav_kind`` (a :class:`~magnav_ins.core.types.FieldKind` value). Vector maps have a
  trailing dimension ``component`` = ``north, east, down``.
* Geodetic maps: coordinates ``latitude`` (``degrees_north``) and ``longitude`` (``degrees_east``). Local maps:
  coordinates ``northing`` and ``easting`` (``m``) and global attributes ``origin_lat_deg``, ``origin_lon_deg``,
  ``origin_h_m`` (the tangent-plane origin).
* Global attributes ``Conventions = "CF-1.8"``, ``magnav_frame`` (``geodetic`` / ``local`` / ``projected``: then ``northing``, ``easting`` are metres of the CRS
  in global attribute ``crs``), ``geodetic_datum``
  (``WGS84``), ``altitude_m`` (ellipsoidal height of a flat map surface, m) - or, for draped maps, a data variable
  ``altitude`` (m) on the same grid - and optionally ``crs``, ``title`` (the map's name), ``magnav_metadata`` (JSON).
* Optionally the map error layer: a data variable ``map_error_sigma`` on the same (y, x) grid (1-sigma, the map's
  unit) with attributes ``units``, ``correlation_length_m`` (the error's correlation length) and ``source``.

A file missing the kind, the unit, the datum or the altitude is refused with a :class:`MapError` that names the
attribute and how to supply it (edit the file's attributes, or pass ``kind=`` / ``altitude_m=`` / ``datum=`` to
:func:`read_map`, ``--kind`` / ``--altitude-m`` / ``--datum`` on the command line). Nothing is guessed.

Surveys (CSV line data) are read by :mod:`magnav_ins.maps.survey` (its names are re-exported here); the shipped maps
and surveys are listed in :mod:`magnav_ins.maps.shipped`. :func:`load_map` reads any map spec.
"""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..core.atomic import atomic_path
from ..core.errors import MapError
from ..core.types import FieldKind
from ..core.units import DEG_TO_RAD, RAD_TO_DEG
from .build import grid_survey
from .error_layer import DEFAULT_FOLDS
from .formats import is_foreign_netcdf, is_netcdf, normalise_unit, read_grid
from .grid import GridMap
from .raster import RASTER_SUFFIXES, ers_for
from .shipped import BUILTIN_MAPS, BUILTIN_PREFIX, data_path
from .survey import (  # re-exported: the survey readers lived here
    SURVEY_COLUMNS,
    SURVEY_SUFFIXES,
    Survey,
    _check_latlon,
    _numeric,
    parse_column_mapping,
    read_csv_checked,
    read_survey,
    read_survey_line,
    select_lines,
    survey_line,
)

__all__ = [
    "BUILTIN_PREFIX",
    "SURVEY_COLUMNS",
    "SURVEY_SUFFIXES",
    "Survey",
    "attach_error_layer",
    "load_builtin_map",
    "load_map",
    "parse_column_mapping",
    "read_csv_checked",
    "read_map",
    "read_survey",
    "read_survey_line",
    "select_lines",
    "survey_line",
    "write_map",
    "_check_latlon",
    "_numeric",
]

FloatArray = NDArray[np.float64]
log = logging.getLogger(__name__)

_COMPONENTS = ("north", "east", "down")
_FILE_MODE = 0o644  # maps are data to share (mkstemp would leave 0600)


# ============================================================================================ NetCDF grids
def write_map(fmap: GridMap, path: str | Path, *, dtype: str = "float64", compress: bool = True) -> None:
    """Write ``fmap`` to a CF-1.8 NetCDF file atomically. ``dtype="float32"`` halves the size (values only; axes
    stay float64). Round trip through :func:`read_map` is lossless for float64."""
    import xarray as xr

    kind = fmap.kind
    y, x = fmap.axes
    if fmap.frame == "geodetic":
        dims = ("latitude", "longitude")
        coords: dict[str, Any] = {
            "latitude": ("latitude", y * RAD_TO_DEG, {"units": "degrees_north", "standard_name": "latitude"}),
            "longitude": ("longitude", x * RAD_TO_DEG, {"units": "degrees_east", "standard_name": "longitude"}),
        }
    else:
        plane = "the local tangent plane" if fmap.frame == "local" else "the projected CRS (global attribute crs)"
        dims = ("northing", "easting")
        coords = {
            "northing": ("northing", y, {"units": "m", "long_name": f"northing in {plane}"}),
            "easting": ("easting", x, {"units": "m", "long_name": f"easting in {plane}"}),
        }
    vdims: tuple[str, ...] = dims
    if kind.components == 3:
        vdims = dims + ("component",)
        coords["component"] = ("component", list(_COMPONENTS))
    var_attrs = {"units": kind.unit, "magnav_kind": kind.value, "long_name": kind.value.replace("_", " ")}
    data_vars: dict[str, Any] = {kind.value: (vdims, np.asarray(fmap.values, dtype=dtype), var_attrs)}
    attrs: dict[str, Any] = {
        "Conventions": "CF-1.8",
        "title": fmap.name,
        "magnav_frame": fmap.frame,
        "magnav_kind": kind.value,
        "geodetic_datum": fmap.datum,
    }
    if np.ndim(fmap.altitude_m) == 0:
        attrs["altitude_m"] = float(fmap.altitude_m)  # type: ignore[arg-type]
    else:
        data_vars["altitude"] = (
            dims,
            np.asarray(fmap.altitude_m, dtype=dtype),
            {"units": "m", "long_name": "ellipsoidal height of the map surface (WGS84)"},
        )
    if fmap.has_error_layer:
        data_vars["map_error_sigma"] = (
            dims,
            np.asarray(fmap.error_sigma, dtype=dtype),
            {
                "units": kind.unit,
                "long_name": "1-sigma prediction error of the map",
                "correlation_length_m": float(fmap.error_correlation_m),  # type: ignore[arg-type]
                "source": fmap.error_source,
            },
        )
    # the tangent-plane origin (a geodetic map's default is its centre); always written so reads are lossless
    attrs["origin_lat_deg"] = fmap.origin[0] * RAD_TO_DEG
    attrs["origin_lon_deg"] = fmap.origin[1] * RAD_TO_DEG
    attrs["origin_h_m"] = fmap.origin[2]
    if fmap.crs:
        attrs["crs"] = fmap.crs
    if fmap.metadata:
        attrs["magnav_metadata"] = json.dumps(fmap.metadata, sort_keys=True, default=_json_default)
    ds = xr.Dataset(data_vars, coords=coords, attrs=attrs)
    enc: dict[str, Any] = {}
    if compress:
        for name in data_vars:
            enc[name] = {"zlib": True, "complevel": 6, "_FillValue": np.nan}
    with atomic_path(path) as tmp:
        ds.to_netcdf(tmp, engine="netcdf4", encoding=enc, format="NETCDF4")
        os.chmod(tmp, _FILE_MODE)


def _json_default(o: Any) -> Any:
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    raise TypeError(f"metadata value {o!r} is not JSON-serialisable")


def read_map(
    path: str | Path,
    *,
    variable: str | None = None,
    kind: FieldKind | str | None = None,
    altitude_m: float | None = None,
    datum: str | None = None,
    unit: str | None = None,
    crs: str | None = None,
    reproject: bool = False,
) -> GridMap:
    """Read a grid file into a :class:`GridMap`: this project's NetCDF format (module docstring), or any grid as
    downloaded - GeoTIFF, ER Mapper, GXF, Geosoft GRD, GMT / COARDS / CF NetCDF (:func:`magnav_ins.maps.formats.read_grid`).

    Keyword overrides supply metadata the file lacks (explicitly; they never silently replace what the file says: a
    conflicting override is an error): ``kind``, ``altitude_m`` (ellipsoidal m), ``datum``, ``variable``, and for
    downloaded grids ``unit`` (the values' unit when the file states none or an impossible one: ``"nT"``,
    ``"mGal"``, ``"um/s^2"``, ``"m/s^2"``; gravity is converted to mGal), ``crs`` (the projection of a grid in
    metres that does not say, e.g. ``"EPSG:32613"``) and ``reproject`` (resample a projected grid onto WGS-84
    latitude/longitude instead of using it in its own CRS). Geoscience Australia's gravity grid, for example::

        read_map("QLDWestGravity.nc", kind="gravity_disturbance_mgal", unit="um/s^2", altitude_m=0.0, datum="WGS84")
    """
    path = Path(path)
    if not path.is_file():
        raise MapError(f"{path}: no such map file")
    _check_not_empty(path)
    suffix = path.suffix.lower()
    if suffix in RASTER_SUFFIXES or ers_for(path) is not None or not is_netcdf(path):
        return read_grid(path, kind=kind, unit=unit, altitude_m=altitude_m, datum=datum, crs=crs,
                         variable=variable, reproject=reproject)  # fmt: skip
    ds = _PlainNetcdf.open(path)  # this project's own files, without xarray (and pandas: ~50 MB of imports)
    if ds is None:
        import xarray as xr

        try:
            ds = xr.load_dataset(path)
        except Exception as exc:  # noqa: BLE001 - any reader failure is a bad file for the user
            raise MapError(f"{path}: cannot be read as NetCDF ({type(exc).__name__}: {exc})") from None
    if is_foreign_netcdf(ds):
        return read_grid(path, kind=kind, unit=unit, altitude_m=altitude_m, datum=datum, crs=crs,
                         variable=variable, reproject=reproject)  # fmt: skip
    if crs is not None:
        raise MapError(f"{path}: crs= applies to downloaded grids; this file is in magnav_ins's format")
    names = [v for v in ds.data_vars if v not in ("altitude", "crs", "map_error_sigma")]
    if variable is not None:
        if variable not in ds.data_vars:
            raise MapError(f"{path}: no variable {variable!r}; it holds {sorted(map(str, ds.data_vars))}")
        name = variable
    elif len(names) == 1:
        name = str(names[0])
    else:
        tagged = [v for v in names if "magnav_kind" in ds[v].attrs]
        if len(tagged) != 1:
            raise MapError(
                f"{path}: holds {len(names)} data variables {sorted(map(str, names))}; choose one with variable=NAME"
            )
        name = str(tagged[0])
    da = ds[name]
    where_ = f"{path} variable '{name}'"

    # ---- kind and unit
    file_kind = da.attrs.get("magnav_kind", ds.attrs.get("magnav_kind"))
    if file_kind is None and kind is None:
        raise MapError(
            f"{where_}: attribute 'magnav_kind' is missing (what the map measures: one of "
            f"{[k.value for k in FieldKind]}); add it to the file's attributes or pass kind=... (CLI: --kind)"
        )
    try:
        fk = FieldKind(file_kind) if file_kind is not None else None
        ok = FieldKind(kind) if kind is not None else None
    except ValueError:
        raise MapError(
            f"{where_}: unknown kind {file_kind if kind is None else kind!r}; expected one of {[k.value for k in FieldKind]}"
        ) from None
    if fk is not None and ok is not None and fk is not ok:
        raise MapError(f"{where_}: the file says magnav_kind={fk.value!r} but {ok.value!r} was requested")
    the_kind = fk or ok
    assert the_kind is not None
    units = da.attrs.get("units")
    if units is None:
        raise MapError(
            f"{where_}: attribute 'units' is missing; the values must state their unit ({the_kind.unit} for "
            f"{the_kind.value}); add units='{the_kind.unit}' to the variable's attributes"
        )
    if unit is not None and normalise_unit(unit) != normalise_unit(the_kind.unit):
        raise MapError(f"{where_}: unit={unit!r} given, but a map in magnav_ins's format is in {the_kind.unit}")
    if str(units).strip().lower() != the_kind.unit.lower():
        raise MapError(
            f"{where_}: units={units!r} but kind {the_kind.value} is in {the_kind.unit}; convert the values first"
        )

    # ---- datum and altitude
    file_datum = ds.attrs.get("geodetic_datum", ds.attrs.get("datum"))
    if file_datum is None and datum is None:
        raise MapError(
            f"{path}: global attribute 'geodetic_datum' is missing (e.g. 'WGS84'); add it to the file or pass "
            "datum=... (CLI: --datum)"
        )
    the_datum = str(file_datum if file_datum is not None else datum)
    if file_datum is not None and datum is not None and _norm(str(datum)) != _norm(str(file_datum)):
        raise MapError(f"{path}: the file says geodetic_datum={file_datum!r} but {datum!r} was requested")
    alt: float | FloatArray
    if "altitude" in ds.data_vars:
        alt = np.asarray(ds["altitude"].values, dtype=float)
    elif "altitude_m" in ds.attrs:
        alt = float(ds.attrs["altitude_m"])
    elif altitude_m is not None:
        alt = float(altitude_m)
    else:
        raise MapError(
            f"{path}: global attribute 'altitude_m' (ellipsoidal height of the map surface, m) or an 'altitude' "
            "variable is missing; add it to the file or pass altitude_m=... (CLI: --altitude-m)"
        )

    # ---- axes and frame
    frame = ds.attrs.get("magnav_frame")
    dims = list(da.dims)
    if frame is None:
        frame = "geodetic" if {"latitude", "longitude"} <= set(dims) or {"lat", "lon"} <= set(dims) else None
        # metres with a CRS (UTM & co.): used in that CRS (a local tangent plane would misplace it)
        if frame is None and "crs" in ds.attrs and ({"y", "x"} <= set(dims) or {"northing", "easting"} <= set(dims)):
            frame = "projected"
    if frame == "geodetic":
        ydim = "latitude" if "latitude" in dims else "lat"
        xdim = "longitude" if "longitude" in dims else "lon"
    elif frame in ("local", "projected"):
        ydim, xdim = ("y", "x") if frame == "projected" and "y" in dims else ("northing", "easting")
    else:
        if {"x", "y"} <= set(dims) or {"easting", "northing"} <= set(dims) or "crs" in ds.attrs:
            raise MapError(  # a local tangent plane ('local') would misplace a UTM grid by up to hundreds of metres
                f"{path}: the grid is in projected coordinates (dimensions {dims}); set global attribute "
                "magnav_frame='projected' with its crs, or reproject it onto latitude/longitude "
                "(magnav-ins map convert --reproject)"
            )
        raise MapError(
            f"{path}: cannot tell the frame; set global attribute magnav_frame='geodetic', 'local' or 'projected'"
        )
    if ydim not in dims or xdim not in dims:
        raise MapError(f"{where_}: expected dimensions ({ydim}, {xdim}), found {dims}")
    order = [ydim, xdim] + (["component"] if the_kind.components == 3 else [])
    if set(order) != set(dims):
        raise MapError(f"{where_}: dimensions {dims} do not fit kind {the_kind.value} (expected {order})")
    da = da.transpose(*order)
    alt_da = ds["altitude"].transpose(ydim, xdim) if "altitude" in ds.data_vars else None
    err_da = ds["map_error_sigma"].transpose(ydim, xdim) if "map_error_sigma" in ds.data_vars else None
    err = np.asarray(err_da.values, dtype=float) if err_da is not None else None
    err_corr = None
    if err_da is not None:
        eu = str(err_da.attrs.get("units", "")).strip()
        if eu.lower() != the_kind.unit.lower():
            raise MapError(f"{path} variable 'map_error_sigma': units={eu!r}, expected {the_kind.unit!r}")
        err_corr = err_da.attrs.get("correlation_length_m")
        if err_corr is None:
            raise MapError(f"{path} variable 'map_error_sigma': attribute 'correlation_length_m' (m) is missing")
    y = np.asarray(ds[ydim].values, dtype=float)
    x = np.asarray(ds[xdim].values, dtype=float)
    vals = np.asarray(da.values, dtype=float)
    if alt_da is not None:
        alt = np.asarray(alt_da.values, dtype=float)
    if frame == "geodetic" and x.size > 2:
        wraps = np.flatnonzero(np.diff(x) < -180.0)
        if len(wraps) == 1:  # an axis wrapped at the antimeridian (..., 179.9, -179.9, ...): make it continuous
            x = x.copy()
            x[wraps[0] + 1 :] += 360.0
    if y.size > 1 and y[1] < y[0]:
        y, vals = y[::-1], vals[::-1]
        alt = alt[::-1] if np.ndim(alt) else alt
        err = err[::-1] if err is not None else None
    if x.size > 1 and x[1] < x[0]:
        x, vals = x[::-1], vals[:, ::-1]
        alt = alt[:, ::-1] if np.ndim(alt) else alt
        err = err[:, ::-1] if err is not None else None
    origin = None
    if "origin_lat_deg" in ds.attrs:
        origin = (
            float(ds.attrs["origin_lat_deg"]) * DEG_TO_RAD,
            float(ds.attrs["origin_lon_deg"]) * DEG_TO_RAD,
            float(ds.attrs["origin_h_m"]),
        )
    elif frame == "local":
        raise MapError(f"{path}: a local-frame map needs global attributes origin_lat_deg, origin_lon_deg, origin_h_m")
    if frame == "geodetic":
        y, x = y * DEG_TO_RAD, x * DEG_TO_RAD
    meta = {}
    if "magnav_metadata" in ds.attrs:
        try:
            meta = json.loads(ds.attrs["magnav_metadata"])
        except ValueError:
            raise MapError(f"{path}: attribute 'magnav_metadata' is not valid JSON") from None
    try:
        return GridMap(
            y,
            x,
            vals,
            kind=the_kind,
            frame=frame,
            altitude_m=alt,
            datum=the_datum,
            origin=origin,
            crs=ds.attrs.get("crs"),
            name=str(ds.attrs.get("title", "")) or path.stem,
            metadata=meta,
            error_sigma=err,
            error_correlation_m=float(err_corr) if err_corr is not None else None,
            error_source=str(err_da.attrs.get("source", "")) if err_da is not None else "",
        )
    except MapError as exc:
        raise MapError(f"{path}: {exc}") from None


class _PlainVariable:
    """One NetCDF variable as :func:`read_map` reads an xarray one: ``dims``, ``attrs`` (without the encoding's
    ``_FillValue``), ``values`` (float, fill values as NaN, as xarray decodes them) and ``transpose``."""

    def __init__(self, dims: tuple[str, ...], attrs: dict[str, Any], values: FloatArray) -> None:
        self.dims, self.attrs, self.values = dims, attrs, values

    def transpose(self, *order: str) -> _PlainVariable:
        return _PlainVariable(tuple(order), self.attrs, np.transpose(self.values, [self.dims.index(d) for d in order]))


class _PlainNetcdf:
    """A NetCDF file of plain float variables read with netCDF4 alone, shaped as the xarray ``Dataset`` that
    :func:`read_map` reads (``attrs``, ``data_vars``, ``ds[name]``): the same numbers, without importing xarray and
    pandas (~50 MB, a sixth of a log replay's peak memory). Anything else (packed or integer variables, strings,
    CF ``coordinates``, groups) is left to xarray: :meth:`open` returns None."""

    def __init__(self, attrs: dict[str, Any], variables: dict[str, _PlainVariable], dims: set[str]) -> None:
        self.attrs = attrs
        self._vars = variables
        self.data_vars = [v for v in variables if v not in dims]

    def __getitem__(self, name: str) -> _PlainVariable:
        return self._vars[name]

    @classmethod
    def open(cls, path: Path) -> _PlainNetcdf | None:
        try:
            import netCDF4
        except ImportError:  # pragma: no cover - netCDF4 is a dependency
            return None
        try:
            with netCDF4.Dataset(path) as nc:
                if nc.groups:
                    return None
                variables: dict[str, _PlainVariable] = {}
                for name, v in nc.variables.items():
                    names = set(v.ncattrs())
                    packed = names & {"scale_factor", "add_offset", "coordinates", "missing_value", "calendar"}
                    if v.dtype.kind != "f" or packed or " since " in str(getattr(v, "units", "")):
                        return None  # packed, masked another way, or times: xarray decodes them
                    v.set_auto_maskandscale(False)
                    values = np.asarray(v[...])
                    if "_FillValue" in names:
                        fill = v.getncattr("_FillValue")
                        if not np.isnan(fill):
                            values = np.where(values == fill, np.nan, values).astype(values.dtype)
                    attrs = {a: v.getncattr(a) for a in v.ncattrs() if a != "_FillValue"}
                    variables[str(name)] = _PlainVariable(tuple(v.dimensions), attrs, values)
                attrs = {a: nc.getncattr(a) for a in nc.ncattrs()}
                dims = set(nc.dimensions)
        except Exception:  # noqa: BLE001 - not for this reader: xarray reads it or says what is wrong
            return None
        return cls(attrs, variables, dims)


#: the first bytes of a NetCDF file: classic / 64-bit offset / CDF-5, or NetCDF-4 (HDF5)


def _check_not_empty(path: Path) -> None:
    """One clear line for an unreadable or empty file (the readers' own messages list their IO backends)."""
    try:
        with path.open("rb") as fh:
            head = fh.read(8)
    except OSError as exc:
        raise MapError(f"{path}: cannot be read ({exc.strerror or exc})") from None
    if not head:
        raise MapError(f"{path}: the file is empty; expected a map grid (NetCDF, GeoTIFF, ER Mapper, GXF, GMT)")


def _norm(s: str) -> str:
    return s.upper().replace("-", "").replace(" ", "").replace("_", "")


# ============================================================================================ any map spec


def load_map(
    spec: str | Path,
    *,
    grid_spacing_m: float | None = None,
    exclude_lines: Sequence[int] | None = None,
    kind: FieldKind | str | None = None,
    altitude_m: float | None = None,
    datum: str | None = None,
    geoid_undulation_m: float | None = None,
    method: str = "auto",
    columns: Mapping[str, str] | None = None,
    line_type: str | Sequence[str] | None = None,
    exclude_line_type: str | Sequence[str] | None = None,
    error_sigma: float | None = None,
    error_correlation_m: float | None = None,
    unit: str | None = None,
    crs: str | None = None,
    variable: str | None = None,
    reproject: bool = False,
    **unknown: Any,
) -> GridMap:
    """Any map the project accepts: ``builtin:NAME`` (shipped, :mod:`magnav_ins.maps.builtin`), a NetCDF grid
    (:func:`read_map`), or a survey CSV(.xz) gridded on load at ``grid_spacing_m`` (required) with
    :func:`magnav_ins.maps.build.grid_survey`: read with ``columns`` / ``geoid_undulation_m``
    (:func:`read_survey`), only the lines of ``line_type`` kept, ``exclude_lines`` and the lines of
    ``exclude_line_type`` left out (:func:`select_lines`); the map carries its cross-validated error layer
    (:mod:`magnav_ins.maps.error_layer`). The lines left out by ``line_type`` / ``exclude_line_type`` (e.g. the tie
    lines of a map gridded from ``LINE``) measure the error between line sets at their crossovers (``grid_survey``'s
    ``check_lines``: never gridded); ``exclude_lines`` are used for nothing (e.g. the line a study flies). ``error_sigma`` (map unit) with ``error_correlation_m`` (m) gives the map
    a uniform error layer instead (:func:`attach_error_layer`). ``unit``, ``crs``, ``variable``, ``reproject``
    (and ``kind``, ``altitude_m``, ``datum``) go to :func:`read_map` for grid files as downloaded."""
    s = str(spec)
    if unknown:
        raise MapError(
            f"{s}: unknown map option(s) {sorted(unknown)}; expected grid_spacing_m, exclude_lines, kind, altitude_m, "
            "datum, geoid_undulation_m, method, columns, line_type, exclude_line_type, error_sigma, error_correlation_m, "
            "unit, crs, variable, reproject"
        )
    survey_only = {
        "columns": columns,
        "line_type": line_type,
        "exclude_line_type": exclude_line_type,
        "geoid_undulation_m": geoid_undulation_m,
    }
    given = sorted(k for k, v in survey_only.items() if v)
    grid_only = {"unit": unit, "crs": crs, "variable": variable, "reproject": reproject}
    given_g = sorted(k for k, v in grid_only.items() if v)
    if given_g and (s.startswith(BUILTIN_PREFIX) or s.lower().endswith(SURVEY_SUFFIXES)):
        raise MapError(f"{s}: {', '.join(given_g)} apply to grid files, not to shipped maps or surveys")
    if given and not s.lower().endswith(SURVEY_SUFFIXES):
        raise MapError(f"{s}: {', '.join(given)} apply to survey CSV files, not to grids")
    if s.startswith(BUILTIN_PREFIX):
        if grid_spacing_m is not None or exclude_lines:
            raise MapError(f"{s}: grid_spacing_m / exclude_lines apply to survey files, not to shipped grids")
        fmap = load_builtin_map(s[len(BUILTIN_PREFIX) :])
    elif s.lower().endswith(SURVEY_SUFFIXES):
        if grid_spacing_m is None:
            raise MapError(f"{s}: a survey file is gridded on load; give the grid spacing (grid_spacing_m / --spacing)")
        survey = read_survey(
            s, kind=kind, geoid_undulation_m=geoid_undulation_m, altitude_m=altitude_m, columns=columns
        )
        check = None
        if exclude_lines:  # left out of everything: the grid and the error estimate
            survey = select_lines(survey, exclude_lines=exclude_lines)
        if line_type is not None or exclude_line_type is not None:
            chosen = select_lines(survey, line_type=line_type, exclude_line_type=exclude_line_type)
            if survey.line is not None and chosen is not survey:  # the other lines: the error estimate only
                check = survey.select(~np.isin(survey.line, chosen.line_ids()))
            survey = chosen
        fmap = grid_survey(
            survey,
            grid_spacing_m,
            method=method,
            name=Path(s).name,
            error_folds=0 if error_sigma is not None else DEFAULT_FOLDS,
            check_lines=check,
        )
        if exclude_lines:
            fmap.metadata["excluded_lines"] = sorted(int(i) for i in exclude_lines)
        if line_type is not None:
            fmap.metadata["line_type"] = line_type
        if exclude_line_type is not None:
            fmap.metadata["excluded_line_type"] = exclude_line_type
        fmap.metadata["heights"] = survey.heights
    else:
        if grid_spacing_m is not None or exclude_lines:
            raise MapError(f"{s}: grid_spacing_m / exclude_lines apply to survey CSV files, not to NetCDF grids")
        fmap = read_map(
            s,
            kind=kind,
            altitude_m=altitude_m,
            datum=datum,
            unit=unit,
            crs=crs,
            variable=variable,
            reproject=reproject,
        )
    return attach_error_layer(fmap, error_sigma, error_correlation_m, where=s)


def load_builtin_map(name: str) -> GridMap:
    """The shipped map ``name`` (with or without the ``builtin:`` prefix; :data:`~magnav_ins.maps.shipped.BUILTIN_MAPS`)."""
    key = name[len(BUILTIN_PREFIX) :] if name.startswith(BUILTIN_PREFIX) else name
    if key not in BUILTIN_MAPS:
        raise MapError(
            f"builtin:{key}: no such shipped map; available: {', '.join('builtin:' + k for k in BUILTIN_MAPS)}"
        )
    path = data_path(BUILTIN_MAPS[key][0])
    if not path.is_file():
        raise MapError(
            f"builtin:{key}: {path.name} is missing from the installed package (run bench/make_builtin_maps.py)"
        )
    return read_map(path)


def attach_error_layer(fmap: GridMap, sigma: float | None, correlation_m: float | None, *, where: str = "") -> GridMap:
    """``fmap`` with a uniform user-given error layer (``sigma`` in the map's unit, ``correlation_m`` m; scenario
    ``[map] error_sigma`` / ``error_correlation_m``, CLI ``--map-error-sigma`` / ``--map-error-correlation-m``),
    replacing any layer the map carries (logged); unchanged when ``sigma`` is None."""
    src = where or fmap.name
    if sigma is None:
        if correlation_m is not None:
            raise MapError(f"{src}: error_correlation_m given without error_sigma (--map-error-sigma)")
        return fmap
    if not (np.isfinite(sigma) and sigma > 0):
        raise MapError(f"{src}: error_sigma must be a positive number in {fmap.unit}, got {sigma!r}")
    if correlation_m is None:
        raise MapError(
            f"{src}: error_sigma needs its correlation length too: error_correlation_m (m; CLI "
            "--map-error-correlation-m)"
        )
    if not (np.isfinite(correlation_m) and correlation_m > 0):
        raise MapError(f"{src}: error_correlation_m must be a positive number of metres, got {correlation_m!r}")
    if fmap.has_error_layer:
        log.info("%s: the map's own error layer (%s) replaced by the given one", src, fmap.error_source)
    return fmap.with_error_layer(
        float(sigma),
        float(correlation_m),
        f"given by the user: {float(sigma):g} {fmap.unit}, {float(correlation_m):g} m",
    )
