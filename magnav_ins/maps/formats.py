"""Grids as users download them: GeoTIFF, ER Mapper, GXF (GDAL, :mod:`magnav_ins.maps.raster`), Geosoft binary GRD
(harmonica, if installed: the only harmonica import), GMT COARDS ``z(lat, lon)`` and legacy "cf" grids, CF NetCDF
with a grid-mapping ``crs`` variable, COARDS / ERDDAP files with long variable names.

:func:`read_grid` turns any of them into a :class:`~magnav_ins.maps.grid.GridMap`:

* **No data** -> NaN: the file's declared no-data value (``_FillValue``, ``missing_value``, GeoTIFF ``nodata``,
  ERS ``NullCellValue``, GXF dummy) and the undeclared conventions -99999 and |v| >= 1e30 (EMAG2's -99999).
* **CRS**: geographic grids (degrees) become ``frame="geodetic"`` maps - on WGS-84 or a datum within ~2 m of it
  (GDA94, GDA2020, NAD83, ITRF...); another datum is refused unless ``datum="WGS84"`` is stated. Projected grids
  (UTM, Mercator, ... in metres) are used in their own CRS (``frame="projected"``, :mod:`magnav_ins.maps.projection`)
  or, with ``reproject=True``, resampled onto a geodetic grid (:func:`to_geodetic`). A grid in metres without a CRS
  needs ``crs=`` (an EPSG code, PROJ string or WKT).
* **Unit and kind, never guessed**: ``kind`` (a :class:`~magnav_ins.core.types.FieldKind`) must be given for a file
  that is not in this project's format; the unit is read from the file when it is a valid unit of that kind (nT for
  magnetic kinds; mGal, um/s^2 or m/s^2 for gravity, converted to mGal, :data:`UNIT_FACTORS`); a file without a unit,
  or with one impossible for the kind (Geoscience Australia's gravity grid says "Degree" for values in um/s^2), needs
  ``unit=``; a stated unit that contradicts a valid file unit is refused. ``altitude_m`` (ellipsoidal height of the
  grid surface, m) must be given too. Everything missing is named in one message with its CLI option and scenario
  key.

Geodetic datums other than WGS-84 are not transformed for geographic grids (a < 2 m difference for the accepted
ones); for projected grids pyproj's transformation from WGS-84 is used (``map info`` shows it).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..core.errors import MapError
from ..core.types import FieldKind
from ..core.units import DEG_TO_RAD
from .grid import GridMap
from .projection import Projection, datum_is_wgs84_compatible, describe_crs
from .raster import RASTER_SUFFIXES, ers_for, read_raster

FloatArray = NDArray[np.float64]
log = logging.getLogger(__name__)

#: accepted units per kind (normalised: lower case, no spaces, micro as "u", "**" and "²" as "^2") -> factor to the
#: kind's unit
UNIT_FACTORS: dict[FieldKind, dict[str, float]] = {
    FieldKind.TOTAL_FIELD_ANOMALY_NT: {"nt": 1.0, "nanotesla": 1.0, "nanoteslas": 1.0, "gamma": 1.0},
    FieldKind.VECTOR_FIELD_NT: {"nt": 1.0, "nanotesla": 1.0, "nanoteslas": 1.0, "gamma": 1.0},
    FieldKind.GRAVITY_DISTURBANCE_MGAL: {
        "mgal": 1.0,
        "milligal": 1.0,
        "milligals": 1.0,
        "um/s^2": 0.1,
        "um/s2": 0.1,
        "ums-2": 0.1,
        "um.s-2": 0.1,
        "gu": 0.1,
        "g.u.": 0.1,
        "m/s^2": 1e5,
        "m/s2": 1e5,
        "ms-2": 1e5,
        "m.s-2": 1e5,
    },
}
#: undeclared no-data conventions
NODATA_SENTINEL = -99999.0
NODATA_HUGE = 1e30
_OPTIONS = {
    "kind": "--kind KIND (scenario [map] kind)",
    "unit": "--unit UNIT (scenario [map] unit)",
    "altitude_m": "--altitude-m M (scenario [map] altitude_m)",
    "datum": "--datum WGS84 (scenario [map] datum)",
    "crs": "--crs EPSG:NNNN|PROJ|WKT (scenario [map] crs)",
    "variable": "--variable NAME (scenario [map] variable)",
}


def normalise_unit(unit: str) -> str:
    """A unit string in the form :data:`UNIT_FACTORS` keys use."""
    u = str(unit).strip().lower().replace(" ", "").replace("**", "^").replace("²", "^2")
    return u.replace("µ", "u").replace("μ", "u").replace("micro", "u").replace("metre", "m").replace("meter", "m")


def unit_factor(unit: str | None, kind: FieldKind) -> float | None:
    """Factor from ``unit`` to ``kind``'s unit, or None when ``unit`` is not a unit of that kind."""
    if unit is None:
        return None
    return UNIT_FACTORS[kind].get(normalise_unit(unit))


@dataclass
class ForeignGrid:
    """A grid as read from a file, before kind, unit and altitude are settled: ``values`` (ny, nx) NaN = no data,
    ``y``, ``x`` node coordinates (degrees for geographic, else the CRS's metres) in file order, the file's
    ``unit`` (None if it states none), ``crs_wkt`` (None if none), ``geographic`` (from the CRS or the coordinates'
    units), ``variable`` (the data variable or band name) and ``format`` (a short name for ``map info``)."""

    values: FloatArray
    y: FloatArray
    x: FloatArray
    unit: str | None
    crs_wkt: str | None
    geographic: bool | None
    variable: str
    format: str
    attrs: dict[str, Any] = field(default_factory=dict)


def _mask(values: FloatArray) -> FloatArray:
    v = np.asarray(values, dtype=np.float64)
    bad = (np.abs(v - NODATA_SENTINEL) < 1e-3) | (np.abs(v) >= NODATA_HUGE)
    return np.where(bad, np.nan, v)


def is_netcdf(path: Path) -> bool:
    """True when the file starts like NetCDF-3 or NetCDF-4 / HDF5."""
    with open(path, "rb") as f:
        head = f.read(8)
    return head[:3] == b"CDF" or head[:8] == b"\x89HDF\r\n\x1a\n"


def is_foreign_netcdf(ds: Any) -> bool:
    """True for a NetCDF dataset not written in this project's format (no ``magnav_*`` / ``geodetic_datum`` /
    ``altitude_m`` attributes on the file or its variables)."""
    ours = {"magnav_frame", "magnav_kind", "geodetic_datum", "altitude_m"}
    if ours & set(ds.attrs):
        return False
    return not any("magnav_kind" in ds[v].attrs for v in ds.data_vars)


def open_foreign(path: str | Path, variable: str | None = None) -> ForeignGrid:
    """Read any supported grid file (module docstring) without interpreting kind, unit or altitude."""
    p = Path(path)
    if not p.is_file():
        raise MapError(f"{p}: no such map file")
    hdr = ers_for(p)
    if hdr is not None:
        p = hdr
    suffix = p.suffix.lower()
    if suffix in RASTER_SUFFIXES:
        b = read_raster(p)
        fmt = {"GTiff": "GeoTIFF", "ERS": "ER Mapper", "GXF": "Geosoft GXF"}.get(b.driver, b.driver)
        return ForeignGrid(_mask(b.values), b.y, b.x, b.unit, b.crs_wkt, b.geographic if b.crs_wkt else None,
                           b.description or "band 1", f"{fmt} (GDAL)")  # fmt: skip
    if is_netcdf(p):
        return _open_netcdf(p, variable)
    if suffix == ".grd":
        return _open_geosoft(p)
    if p.stat().st_size == 0:
        raise MapError(f"{p}: the file is empty; expected a map (NetCDF, GeoTIFF, ER Mapper, GXF, Geosoft GRD)")
    raise MapError(
        f"{p}: not a NetCDF file (no NetCDF or HDF5 signature) nor a grid format by its suffix (GeoTIFF .tif, "
        "ER Mapper .ers, Geosoft .gxf / .grd)"
    )


def _open_geosoft(p: Path) -> ForeignGrid:
    try:
        import harmonica
    except ImportError:
        raise MapError(f"{p}: a Geosoft binary .grd needs harmonica (pip install harmonica)") from None
    try:
        da = harmonica.load_oasis_montaj_grid(p)
    except Exception as exc:  # noqa: BLE001 - any reader failure is a bad file for the user
        raise MapError(f"{p}: cannot be read as a Geosoft grid ({type(exc).__name__}: {exc})") from None
    ydim, xdim = da.dims[-2], da.dims[-1]
    return ForeignGrid(_mask(da.values), np.asarray(da[ydim].values, float), np.asarray(da[xdim].values, float),
                       da.attrs.get("units"), None, None, str(da.name or "grid"), "Geosoft GRD (harmonica)")  # fmt: skip


_LAT = ("lat", "latitude", "y_lat")
_LON = ("lon", "longitude", "long", "x_lon")
_Y = ("y", "northing", "north", "projection_y_coordinate")
_X = ("x", "easting", "east", "projection_x_coordinate")


def _open_netcdf(p: Path, variable: str | None) -> ForeignGrid:
    import xarray as xr

    try:
        ds = xr.load_dataset(p, mask_and_scale=True)
    except Exception as exc:  # noqa: BLE001 - any reader failure is a bad file for the user
        raise MapError(f"{p}: cannot be read as NetCDF ({type(exc).__name__}: {exc})") from None
    if {"x_range", "y_range", "dimension", "z"} <= set(ds.variables) and ds["z"].ndim == 1:
        return _gmt_cf(p, ds)
    grid_maps = {str(ds[v].attrs["grid_mapping"]) for v in ds.data_vars if "grid_mapping" in ds[v].attrs}
    cands = [str(v) for v in ds.data_vars if ds[v].ndim == 2 and str(v) not in grid_maps]
    if variable is not None:
        if variable not in ds.data_vars:
            raise MapError(f"{p}: no variable {variable!r}; it holds {sorted(map(str, ds.data_vars))}")
        name = variable
    elif len(cands) == 1:
        name = cands[0]
    elif not cands:
        raise MapError(f"{p}: no 2-D data variable; it holds {sorted(map(str, ds.data_vars))}")
    else:
        raise MapError(f"{p}: holds {len(cands)} grids {cands}; choose one with {_OPTIONS['variable']}")
    da = ds[name]
    dims = [str(d) for d in da.dims]
    if len(dims) != 2:
        raise MapError(f"{p} variable '{name}': expected 2 dimensions, found {dims}")
    low = [d.lower() for d in dims]
    geographic: bool | None
    if any(d in _LAT for d in low) and any(d in _LON for d in low):
        ydim = dims[next(i for i, d in enumerate(low) if d in _LAT)]
        xdim = dims[next(i for i, d in enumerate(low) if d in _LON)]
        geographic = True
    elif any(d in _Y for d in low) and any(d in _X for d in low):
        ydim = dims[next(i for i, d in enumerate(low) if d in _Y)]
        xdim = dims[next(i for i, d in enumerate(low) if d in _X)]
        geographic = None
    else:
        raise MapError(f"{p} variable '{name}': cannot tell its axes from dimensions {dims} (expected lat/lon or y/x)")
    da = da.transpose(ydim, xdim)
    crs_wkt = None
    gm = da.attrs.get("grid_mapping")
    if gm and gm in ds.variables:
        gattrs = ds[gm].attrs
        crs_wkt = gattrs.get("crs_wkt") or gattrs.get("spatial_ref")
        if crs_wkt is None and gattrs.get("grid_mapping_name") == "latitude_longitude":
            crs_wkt = (
                "EPSG:4326"
                if abs(float(gattrs.get("inverse_flattening", 298.257223563)) - 298.257223563) < 1e-6
                else None
            )
    for dim in (ydim, xdim):
        u = str(ds[dim].attrs.get("units", "")).lower() if dim in ds.variables else ""
        if u.startswith("degree"):
            geographic = True
        elif u in ("m", "metre", "meter", "metres", "meters") and geographic is None:
            geographic = False
    if crs_wkt is not None:
        geographic = describe_crs(crs_wkt, f"{p} variable '{gm}'")["geographic"]
    y = np.asarray(ds[ydim].values, float) if ydim in ds.variables else np.arange(da.shape[0], dtype=float)
    x = np.asarray(ds[xdim].values, float) if xdim in ds.variables else np.arange(da.shape[1], dtype=float)
    fmt = (
        "CF NetCDF with grid mapping"
        if crs_wkt
        else ("GMT / COARDS NetCDF" if "GMT_version" in ds.attrs else "COARDS / CF NetCDF")
    )
    unit = da.attrs.get("units")
    return ForeignGrid(_mask(np.asarray(da.values)), y, x, None if unit in (None, "") else str(unit), crs_wkt,
                       geographic, name, fmt, dict(da.attrs))  # fmt: skip


def _gmt_cf(p: Path, ds: Any) -> ForeignGrid:
    """GMT's legacy "cf" grid: 1-D ``z`` stored row by row from the top (north) row, ``x_range``, ``y_range``,
    ``spacing``, ``dimension`` = (nx, ny), node registration from ``z:node_offset`` (0 gridline, 1 pixel)."""
    nx, ny = (int(v) for v in np.asarray(ds["dimension"].values))
    x0, x1 = (float(v) for v in np.asarray(ds["x_range"].values))
    y0, y1 = (float(v) for v in np.asarray(ds["y_range"].values))
    z = np.asarray(ds["z"].values, float)
    if z.size != nx * ny:
        raise MapError(f"{p}: GMT cf grid: z holds {z.size} values, dimension says {nx} x {ny}")
    off = int(ds["z"].attrs.get("node_offset", 0))
    dx = (x1 - x0) / (nx - (0 if off else 1))
    dy = (y1 - y0) / (ny - (0 if off else 1))
    x = x0 + (np.arange(nx) + 0.5 * off) * dx
    y = y1 - (np.arange(ny) + 0.5 * off) * dy
    xu = str(ds["x_range"].attrs.get("units", "")).lower()
    geographic = True if ("longitude" in xu or "degree" in xu) else None
    unit = str(ds["z_range"].attrs.get("units", "")) if "z_range" in ds.variables else ""
    unit_s = None if unit.strip().lower() in ("", "z") else unit
    return ForeignGrid(_mask(z.reshape(ny, nx)), y, x, unit_s, None, geographic, "z", "GMT legacy cf grid")


def read_grid(
    path: str | Path,
    *,
    kind: FieldKind | str | None = None,
    unit: str | None = None,
    altitude_m: float | None = None,
    datum: str | None = None,
    crs: str | None = None,
    variable: str | None = None,
    reproject: bool = False,
) -> GridMap:
    """A downloaded grid (module docstring) as a :class:`GridMap` in ``kind``'s unit. Raises one
    :class:`MapError` naming the file, the variable and every option that is missing."""
    g = open_foreign(path, variable)
    src = f"{path} variable '{g.variable}'"
    missing: list[str] = []
    problems: list[str] = []
    the_kind = None
    if kind is None:
        missing.append("kind")
        problems.append("what it measures is not stated (kind)")
    else:
        try:
            the_kind = FieldKind(kind)
        except ValueError:
            raise MapError(f"{src}: unknown kind {kind!r}; expected one of {[k.value for k in FieldKind]}") from None
        if the_kind.components != 1:
            raise MapError(f"{src}: a single grid cannot hold kind {the_kind.value} (3 components)")
    factor = None
    if the_kind is not None:
        f_file = unit_factor(g.unit, the_kind)
        if unit is not None:
            f_user = unit_factor(unit, the_kind)
            if f_user is None:
                raise MapError(
                    f"{src}: unit {unit!r} is not a unit of {the_kind.value}; expected one of "
                    f"{sorted(UNIT_FACTORS[the_kind])}"
                )
            if f_file is not None and f_file != f_user:
                raise MapError(f"{src}: the file says units={g.unit!r} but unit={unit!r} was given")
            if g.unit is not None and f_file is None:
                log.info("%s: units=%r is not a unit of %s; using the given %r", src, g.unit, the_kind.value, unit)
            factor = f_user
        elif f_file is not None:
            factor = f_file
        else:
            missing.append("unit")
            problems.append(
                "no unit stated" if g.unit is None else f"units={g.unit!r} is not a unit of {the_kind.value}"
            )
    if altitude_m is None:
        alt = g.attrs.get("altitude_m")
        if alt is None:
            missing.append("altitude_m")
            problems.append("the height of the grid surface is not stated (ellipsoidal m)")
    projection_crs = None
    if g.crs_wkt is None and crs is not None:
        g.crs_wkt = crs
        g.geographic = describe_crs(crs, f"{src}: crs")["geographic"]
    elif g.crs_wkt is not None and crs is not None:
        same = describe_crs(crs, "crs")["wkt"] == describe_crs(g.crs_wkt, "crs")["wkt"]
        if not same:
            raise MapError(f"{src}: the file states its CRS ({describe_crs(g.crs_wkt)['name']}); crs={crs!r} conflicts")
    if g.geographic is None and g.crs_wkt is None:
        missing.append("crs")
        problems.append("its coordinates are in metres of an unknown projection (no CRS)")
    elif g.geographic:
        dname = describe_crs(g.crs_wkt)["datum"] if g.crs_wkt else None
        if datum is None and dname is None:
            missing.append("datum")
            problems.append("its latitude/longitude datum is not stated")
        elif datum is not None and str(datum).upper().replace("-", "").replace(" ", "") != "WGS84":
            raise MapError(f"{src}: datum {datum!r} is not supported; reproject the grid to WGS84 first")
        elif datum is None and dname is not None and not datum_is_wgs84_compatible(dname):
            raise MapError(
                f"{src}: its datum {dname!r} differs from WGS84; reproject it, or state {_OPTIONS['datum']} if the "
                "difference does not matter"
            )
    else:
        projection_crs = g.crs_wkt
    if missing:
        raise MapError(
            f"{src}: cannot be used as a map: {'; '.join(problems)}; give " + ", ".join(_OPTIONS[m] for m in missing)
        )
    assert the_kind is not None and factor is not None
    alt_v = float(altitude_m if altitude_m is not None else g.attrs["altitude_m"])
    y, x, v = g.y, g.x, g.values * factor
    if y.size > 1 and y[1] < y[0]:
        y, v = y[::-1], v[::-1]
    if x.size > 1 and x[1] < x[0]:
        x, v = x[::-1], v[:, ::-1]
    name = Path(path).stem
    meta = {"format": g.format, "variable": g.variable, "file_unit": g.unit, "unit_factor": factor,
            "no_data_fraction": float(np.mean(~np.isfinite(v)))}  # fmt: skip
    if g.geographic:
        fmap = GridMap(y * DEG_TO_RAD, x * DEG_TO_RAD, v, kind=the_kind, frame="geodetic", altitude_m=alt_v,
                       crs=g.crs_wkt and describe_crs(g.crs_wkt)["name"], name=name, metadata=meta)  # fmt: skip
    else:
        proj = Projection(projection_crs, where=f"{src}: crs")
        meta["crs_name"] = proj.name
        meta["transformation"] = proj.transform
        fmap = GridMap(y, x, v, kind=the_kind, frame="projected", altitude_m=alt_v, crs=proj.wkt, name=name,
                       metadata=meta)  # fmt: skip
        if reproject:
            return to_geodetic(fmap)
    return fmap


def to_geodetic(fmap: GridMap, spacing_deg: tuple[float, float] | None = None) -> GridMap:
    """``fmap`` resampled (bilinear) onto a regular WGS-84 latitude/longitude grid over its extent; the default
    spacing keeps the node spacing in metres at the map's centre. The error layer is resampled with it."""
    if fmap.frame == "geodetic":
        return fmap
    lat0, lat1, lon0, lon1 = fmap.bounds_latlon
    dn, de = fmap.spacing_m
    lat_c = fmap.origin[0]
    from ..core.frames import meters_to_latlon

    dlat, dlon = meters_to_latlon(dn, de, lat_c) if spacing_deg is None else np.deg2rad(spacing_deg)
    lat = np.arange(lat0, lat1 + 1e-12, float(dlat))
    lon = np.arange(lon0, lon1 + 1e-12, float(dlon))
    la, lo = np.meshgrid(lat, lon, indexing="ij")
    vals = fmap.value(la, lo)
    alt = fmap.altitude_m
    if np.ndim(alt):
        alt = np.asarray(fmap.with_values(np.asarray(alt)).value(la, lo))
        alt = np.where(np.isfinite(alt), alt, float(np.nanmean(alt)))
    err = fmap.error_sigma_at(la, lo) if fmap.has_error_layer else None
    meta = {**fmap.metadata, "reprojected_from": fmap.crs if fmap.frame == "projected" else "local tangent plane"}
    return GridMap(lat, lon, vals, kind=fmap.kind, frame="geodetic", altitude_m=alt, name=fmap.name, metadata=meta,
                   error_sigma=err, error_correlation_m=fmap.error_correlation_m if err is not None else None,
                   error_source=fmap.error_source)  # fmt: skip
