"""Map and survey files: CF-1.8 NetCDF grids (xarray) and survey CSV / CSV.xz line data (pandas).

NetCDF layout written by :func:`write_map` (and required by :func:`read_map`)
-------------------------------------------------------------------------------
* One data variable named after the kind (e.g. ``total_field_anomaly_nt``) with attribute ``units`` (``nT`` /
  ``mGal``) and attribute ``magnav_kind`` (a :class:`~magnav_ins.core.types.FieldKind` value). Vector maps have a
  trailing dimension ``component`` = ``north, east, down``.
* Geodetic maps: coordinates ``latitude`` (``degrees_north``) and ``longitude`` (``degrees_east``). Local maps:
  coordinates ``northing`` and ``easting`` (``m``) and global attributes ``origin_lat_deg``, ``origin_lon_deg``,
  ``origin_h_m`` (the tangent-plane origin).
* Global attributes ``Conventions = "CF-1.8"``, ``magnav_frame`` (``geodetic`` / ``local``), ``geodetic_datum``
  (``WGS84``), ``altitude_m`` (ellipsoidal height of a flat map surface, m) - or, for draped maps, a data variable
  ``altitude`` (m) on the same grid - and optionally ``crs``, ``title`` (the map's name), ``magnav_metadata`` (JSON).
* Optionally the map error layer: a data variable ``map_error_sigma`` on the same (y, x) grid (1-sigma, the map's
  unit) with attributes ``units``, ``correlation_length_m`` (the error's correlation length) and ``source``.

A file missing the kind, the unit, the datum or the altitude is refused with a :class:`MapError` that names the
attribute and how to supply it (edit the file's attributes, or pass ``kind=`` / ``altitude_m=`` / ``datum=`` to
:func:`read_map`, ``--kind`` / ``--altitude-m`` / ``--datum`` on the command line). Nothing is guessed.

Survey CSV columns (:func:`read_survey`)
----------------------------------------
``latitude`` or ``lat_deg`` and ``longitude`` or ``lon_deg`` (degrees, WGS-84); one value column named by its kind
(``total_field_anomaly_nt``, ``gravity_disturbance_mgal``) or ``value`` with an explicit ``kind``; a height column
``height_ellipsoidal_m`` (or ``h_m``), or ``height_orthometric_m`` (above the geoid: made ellipsoidal with the
shipped EIGEN-6C4 geoid, :mod:`magnav_ins.maps.geoid`, unless a geoid undulation is given); optionally a line id
``flight_line`` or ``line`` and a line type ``line_type`` (free text such as ``LINE`` / ``TIE``). Rows with a missing
value are dropped; rows with a missing or non-numeric coordinate are refused with the row number.

A file with other column names is read through a **column mapping** ``{our name: the file's name}``, e.g. the Rio de
Janeiro survey's ``columns={"height_ellipsoidal_m": "height_ell_m", "line": "line_number"}`` (CLI: ``--column
height_ellipsoidal_m=height_ell_m``, repeatable; scenario ``columns = {...}`` in ``[map]`` and in a ``survey_line``
``[trajectory]``). Our names are :data:`SURVEY_COLUMNS`.
"""

from __future__ import annotations

import json
import logging
import lzma
import os
import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..core.atomic import atomic_path
from ..core.errors import InputError, MapError
from ..core.types import FieldKind
from ..core.units import DEG_TO_RAD, RAD_TO_DEG
from .grid import GridMap

FloatArray = NDArray[np.float64]
log = logging.getLogger(__name__)

BUILTIN_PREFIX = "builtin:"
_COMPONENTS = ("north", "east", "down")
_FILE_MODE = 0o644  # maps are data to share (mkstemp would leave 0600)
_SUFFIX_UNITS = {"nt": "nT", "mgal": "mGal"}
_QUANTITIES = ("total_field_anomaly", "gravity_disturbance", "vector_field")


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
        dims = ("northing", "easting")
        coords = {
            "northing": ("northing", y, {"units": "m", "long_name": "northing in the local tangent plane"}),
            "easting": ("easting", x, {"units": "m", "long_name": "easting in the local tangent plane"}),
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
) -> GridMap:
    """Read a NetCDF grid into a :class:`GridMap`. Keyword overrides supply metadata the file lacks (explicitly;
    they never silently replace what the file says: a conflicting override is an error)."""
    import xarray as xr

    path = Path(path)
    if not path.is_file():
        raise MapError(f"{path}: no such map file")
    try:
        ds = xr.load_dataset(path)
    except Exception as exc:  # noqa: BLE001 - any reader failure is a bad file for the user
        raise MapError(f"{path}: cannot be read as NetCDF ({type(exc).__name__}: {exc})") from None
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
    if frame == "geodetic":
        ydim = "latitude" if "latitude" in dims else "lat"
        xdim = "longitude" if "longitude" in dims else "lon"
    elif frame == "local":
        ydim, xdim = "northing", "easting"
    else:
        raise MapError(f"{path}: cannot tell the frame; set global attribute magnav_frame='geodetic' or 'local'")
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


def _norm(s: str) -> str:
    return s.upper().replace("-", "").replace(" ", "").replace("_", "")


# ============================================================================================ surveys
#: our survey column names (the keys of a column mapping)
SURVEY_COLUMNS = (
    "latitude",
    "lat_deg",
    "longitude",
    "lon_deg",
    *(k.value for k in FieldKind if k.components == 1),
    "value",
    "height_ellipsoidal_m",
    "h_m",
    "height_orthometric_m",
    "flight_line",
    "line",
    "line_type",
)


@dataclass(frozen=True)
class Survey:
    """Scattered or line survey readings: ``lat``, ``lon`` (N,) rad WGS-84, ``h`` (N,) ellipsoidal m, ``value`` (N,)
    in ``kind``'s unit, ``line`` (N,) int ids or None, ``line_type`` (N,) str (e.g. ``LINE`` / ``TIE``) or None.
    ``source`` names the file; ``heights`` says where the ellipsoidal heights came from (e.g. the geoid used)."""

    lat: FloatArray
    lon: FloatArray
    h: FloatArray
    value: FloatArray
    kind: FieldKind
    line: NDArray[np.int64] | None = None
    source: str = ""
    line_type: NDArray[np.str_] | None = None
    heights: str = ""

    def __len__(self) -> int:
        return len(self.lat)

    def select(self, mask: NDArray[np.bool_]) -> Survey:
        """The readings where ``mask`` is True."""
        return Survey(
            self.lat[mask],
            self.lon[mask],
            self.h[mask],
            self.value[mask],
            self.kind,
            None if self.line is None else self.line[mask],
            self.source,
            None if self.line_type is None else self.line_type[mask],
            self.heights,
        )

    def line_ids(self) -> NDArray[np.int64]:
        """Sorted unique line ids (error when the survey has none)."""
        if self.line is None:
            raise InputError(
                f"{self.source}: the survey has no line id column ('flight_line' or 'line'; map another column "
                "with columns={'line': NAME}, CLI --column line=NAME)"
            )
        return np.unique(self.line)

    def line_types(self) -> list[str]:
        """Sorted distinct line types (error when the survey has no ``line_type`` column)."""
        if self.line_type is None:
            raise InputError(
                f"{self.source}: the survey has no 'line_type' column (map one with columns={{'line_type': NAME}}, "
                "CLI --column line_type=NAME)"
            )
        return sorted(set(self.line_type.tolist()))

    def type_mask(self, line_type: str | Sequence[str]) -> NDArray[np.bool_]:
        """True for the readings whose ``line_type`` is ``line_type`` (or one of a list); an unknown type is an
        error that lists the survey's types."""
        want = [line_type] if isinstance(line_type, str) else list(line_type)
        have = self.line_types()
        unknown = [t for t in want if t not in have]
        if unknown or not want:
            raise InputError(f"{self.source}: no line type {unknown or want}; the survey's line types are {have}")
        return np.isin(self.line_type, want)  # type: ignore[arg-type]

    def of_type(self, line_type: str | Sequence[str]) -> Survey:
        """The readings of the lines of ``line_type`` (:meth:`type_mask`)."""
        return self.select(self.type_mask(line_type))

    def ids_of_type(self, line_type: str | Sequence[str]) -> list[int]:
        """Sorted ids of the lines of ``line_type``."""
        return [int(i) for i in self.of_type(line_type).line_ids()]


def read_csv_checked(path: str | Path) -> Any:
    """Read a CSV (``.xz``/``.gz`` by suffix) with pandas; a row with too many fields, an empty file or an unreadable
    file raises :class:`InputError` naming the file (and the line, where pandas says it). Column names are stripped."""
    import warnings

    import pandas as pd

    src = str(path)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", pd.errors.ParserWarning)
            df = pd.read_csv(path, on_bad_lines="error", skipinitialspace=True, index_col=False)
    except pd.errors.EmptyDataError:
        raise InputError(f"{src}: the file is empty") from None
    except (pd.errors.ParserError, pd.errors.ParserWarning) as exc:
        raise InputError(f"{src}: malformed CSV ({str(exc).strip()})") from None
    except (OSError, UnicodeDecodeError, EOFError, lzma.LZMAError) as exc:
        raise InputError(f"{src}: cannot be read ({type(exc).__name__}: {exc})") from None
    df.columns = [str(c).strip() for c in df.columns]
    return df


def _first(cols: Sequence[str], *names: str) -> str | None:
    for n in names:
        if n in cols:
            return n
    return None


def _numeric(df: Any, col: str, src: str, *, allow_nan: bool) -> FloatArray:
    import pandas as pd

    raw = df[col]
    num = pd.to_numeric(raw, errors="coerce")
    bad = num.isna() & raw.notna() & (raw.astype(str).str.strip() != "")
    if bad.any():
        i = int(np.flatnonzero(bad.to_numpy())[0])
        raise InputError(f"{src} row {i + 1} column '{col}': {raw.iloc[i]!r} is not a number")
    arr = num.to_numpy(dtype=float)
    if not allow_nan and np.isnan(arr).any():
        i = int(np.flatnonzero(np.isnan(arr))[0])
        raise InputError(f"{src} row {i + 1} column '{col}': missing value")
    return arr


def _value_column(cols: Sequence[str], src: str, kind: FieldKind | None) -> tuple[str, FieldKind]:
    if kind is not None and kind.value in cols:
        return kind.value, kind
    found = [k for k in FieldKind if k.value in cols]
    if kind is None and len(found) == 1:
        return found[0].value, found[0]
    if kind is not None and "value" in cols:
        return "value", kind
    # a column with a known quantity but another unit suffix: say so
    for c in cols:
        m = re.fullmatch(r"(" + "|".join(_QUANTITIES) + r")_(\w+)", c)
        if m:
            q, unit = m.groups()
            want = next((k for k in FieldKind if k.value.startswith(q)), None)
            if want is not None and (kind is None or kind is want):
                raise InputError(
                    f"{src} column '{c}': unit '{unit}' is not accepted; {q.replace('_', ' ')} must be in "
                    f"{want.unit} in a column named '{want.value}'"
                )
    if len(found) > 1:
        raise InputError(f"{src}: several value columns {[k.value for k in found]}; choose one with kind=...")
    raise InputError(
        f"{src}: no value column; expected one of {[k.value for k in FieldKind]} (or 'value' with an explicit kind), "
        f"found columns {list(cols)}"
    )


def read_survey(
    path: str | Path,
    *,
    kind: FieldKind | str | None = None,
    geoid_undulation_m: float | Callable[[FloatArray, FloatArray], FloatArray] | None = None,
    altitude_m: float | None = None,
    columns: Mapping[str, str] | None = None,
) -> Survey:
    """Read a survey CSV (``.csv`` or ``.csv.xz``) with the columns described in the module docstring.

    ``height_orthometric_m`` is made ellipsoidal, ``h = H + N``, with ``N`` from ``geoid_undulation_m`` (m, a
    constant or ``f(lat_rad, lon_rad)``) or, by default, the shipped EIGEN-6C4 geoid
    (:func:`magnav_ins.maps.geoid.geoid_undulation`; logged, and said in :attr:`Survey.heights`). ``altitude_m``
    gives a constant ellipsoidal height when the file has no height column. ``columns`` maps our column names
    (:data:`SURVEY_COLUMNS`) to the file's (module docstring). ``builtin:NAME`` reads a survey shipped with the
    package (:mod:`magnav_ins.maps.builtin`).
    """
    if isinstance(path, str) and path.startswith(BUILTIN_PREFIX):
        from .builtin import builtin_survey_path

        path = builtin_survey_path(path[len(BUILTIN_PREFIX) :])
    path = Path(path)
    src = str(path)
    if not path.is_file():
        raise InputError(f"{src}: no such survey file")
    try:
        the_kind = FieldKind(kind) if kind is not None else None
    except ValueError:
        raise InputError(f"{src}: unknown kind {kind!r}; expected one of {[k.value for k in FieldKind]}") from None
    df = read_csv_checked(path)
    if columns:
        df = _map_columns(df, columns, src)
    cols = list(df.columns)
    if len(df) == 0:
        raise InputError(f"{src}: no data rows")
    lat_c = _first(cols, "latitude", "lat_deg")
    lon_c = _first(cols, "longitude", "lon_deg")
    if lat_c is None or lon_c is None:
        raise InputError(
            f"{src}: missing column {'latitude (or lat_deg)' if lat_c is None else 'longitude (or lon_deg)'} "
            f"in degrees; found columns {cols}"
        )
    val_c, the_kind = _value_column(cols, src, the_kind)
    if the_kind.components != 1:
        raise InputError(f"{src}: survey gridding supports scalar kinds only, got {the_kind.value}")
    lat = _numeric(df, lat_c, src, allow_nan=False)
    lon = _numeric(df, lon_c, src, allow_nan=False)
    val = _numeric(df, val_c, src, allow_nan=True)
    _check_latlon(lat, lon, src, lat_c, lon_c)
    if not np.isfinite(val).any():
        raise InputError(f"{src} column '{val_c}': every value is missing (NaN)")
    h_c = _first(cols, "height_ellipsoidal_m", "h_m")
    heights = f"ellipsoidal (column '{h_c}')"
    if h_c is not None:
        h = _numeric(df, h_c, src, allow_nan=False)
    elif "height_orthometric_m" in cols:
        H = _numeric(df, "height_orthometric_m", src, allow_nan=False)
        if geoid_undulation_m is None:
            from .geoid import GEOID_NAME, geoid_undulation

            N = geoid_undulation(lat * DEG_TO_RAD, lon * DEG_TO_RAD)
            heights = f"orthometric + {GEOID_NAME}, N = {np.min(N):.1f} .. {np.max(N):.1f} m"
            log.info(
                "%s: orthometric heights made ellipsoidal with the %s (N = %.1f .. %.1f m); "
                "--geoid-m / geoid_m overrides it",
                src,
                GEOID_NAME,
                float(np.min(N)),
                float(np.max(N)),
            )
        elif callable(geoid_undulation_m):
            N = np.asarray(geoid_undulation_m(lat * DEG_TO_RAD, lon * DEG_TO_RAD), dtype=float)
            heights = "orthometric + the given geoid function"
        else:
            if not np.isfinite(float(geoid_undulation_m)):
                raise InputError(
                    f"{src}: geoid undulation must be a finite number of metres, got {geoid_undulation_m!r}"
                )
            N = np.full_like(H, float(geoid_undulation_m))
            heights = f"orthometric + a constant geoid undulation N = {float(geoid_undulation_m):.2f} m (given)"
        h = H + np.asarray(N, dtype=float)
    elif altitude_m is not None:
        h = np.full_like(lat, float(altitude_m))
        heights = f"constant {float(altitude_m):.1f} m (given)"
    else:
        raise InputError(
            f"{src}: no height column ('height_ellipsoidal_m', 'h_m' or 'height_orthometric_m'); pass altitude_m=... "
            "(CLI: --altitude-m) for a survey on a constant ellipsoidal height"
        )
    line_c = _first(cols, "flight_line", "line")
    line = None
    if line_c is not None:
        lv = _numeric(df, line_c, src, allow_nan=False)
        if np.any(lv != np.round(lv)):
            i = int(np.flatnonzero(lv != np.round(lv))[0])
            raise InputError(f"{src} row {i + 1} column '{line_c}': line id {lv[i]!r} is not an integer")
        line = lv.astype(np.int64)
    line_type = None
    if "line_type" in cols:
        raw = df["line_type"]
        if raw.isna().any():
            i = int(np.flatnonzero(raw.isna().to_numpy())[0])
            raise InputError(f"{src} row {i + 1} column 'line_type': missing value")
        line_type = raw.astype(str).str.strip().to_numpy(dtype=str)
    keep = np.isfinite(val)
    s = Survey(lat * DEG_TO_RAD, lon * DEG_TO_RAD, h, val, the_kind, line, src, line_type, heights)
    return s if keep.all() else s.select(keep)


def _map_columns(df: Any, columns: Mapping[str, str], src: str) -> Any:
    """Rename the file's columns to ours by ``columns`` = {our name: file's name} (module docstring)."""
    if not isinstance(columns, Mapping):
        raise InputError(f"{src}: the column mapping must be {{our name: file column}}, got {columns!r}")
    have = list(df.columns)
    rename: dict[str, str] = {}
    for ours, theirs in columns.items():
        if ours not in SURVEY_COLUMNS:
            raise InputError(
                f"{src}: column mapping '{ours}={theirs}': '{ours}' is not one of our survey columns {list(SURVEY_COLUMNS)}"
            )
        if not isinstance(theirs, str) or theirs not in have:
            raise InputError(
                f"{src}: column mapping '{ours}={theirs}': the file has no column {theirs!r}; found {have}"
            )
        if theirs in rename:
            raise InputError(f"{src}: column mapping: file column {theirs!r} is mapped twice")
        rename[theirs] = ours
    # a file column already named like a mapped target would be ambiguous: the mapping wins, the other is dropped
    clash = [c for c in have if c in rename.values() and c not in rename]
    return df.drop(columns=clash).rename(columns=rename)


def parse_column_mapping(items: Sequence[str], what: str = "--column") -> dict[str, str]:
    """``["height_ellipsoidal_m=height_ell_m", ...]`` -> ``{"height_ellipsoidal_m": "height_ell_m", ...}``
    (the CLI's repeatable ``--column OURS=THEIRS``)."""
    out: dict[str, str] = {}
    for it in items:
        ours, sep, theirs = (p.strip() for p in str(it).partition("="))
        if not sep or not ours or not theirs:
            raise InputError(f"{what} {it!r}: expected OUR_NAME=FILE_COLUMN, e.g. height_ellipsoidal_m=height_ell_m")
        if ours in out:
            raise InputError(f"{what}: '{ours}' is mapped twice")
        out[ours] = theirs
    return out


def _check_latlon(lat: FloatArray, lon: FloatArray, src: str, lat_c: str, lon_c: str) -> None:
    if np.any(np.abs(lat) > 90.0):
        i = int(np.flatnonzero(np.abs(lat) > 90.0)[0])
        hint = (
            "; latitude and longitude look swapped (the longitude column stays within +-90)"
            if np.all(np.abs(lon) <= 90.0)
            else ""
        )
        raise InputError(f"{src} row {i + 1} column '{lat_c}': latitude {lat[i]} deg outside [-90, 90]{hint}")
    if np.any((lon < -180.0) | (lon > 360.0)):
        i = int(np.flatnonzero((lon < -180.0) | (lon > 360.0))[0])
        raise InputError(f"{src} row {i + 1} column '{lon_c}': longitude {lon[i]} deg outside [-180, 360]")


def read_survey_line(spec: str | Path, line: int, **kwargs: Any) -> dict[str, FloatArray]:
    """One line of a survey in recorded (along-line) order: ``lat``, ``lon`` (rad), ``h`` (m ellipsoidal),
    ``value`` (map unit). ``spec`` is a CSV path or ``builtin:NAME``; ``kwargs`` go to :func:`read_survey`."""
    return survey_line(read_survey(spec, **kwargs), line)


def survey_line(s: Survey, line: int) -> dict[str, FloatArray]:
    """Line ``line`` of the survey ``s`` in recorded order (as :func:`read_survey_line`)."""
    ids = s.line_ids()
    m = s.line == int(line)
    if not m.any():
        raise InputError(f"{s.source}: no line {line}; the survey has {len(ids)} lines ({_id_summary(ids)})")
    if m.sum() < 2:
        raise InputError(f"{s.source} line {line}: only one reading")
    return {"lat": s.lat[m], "lon": s.lon[m], "h": s.h[m], "value": s.value[m]}


def select_lines(
    s: Survey,
    *,
    lines: Sequence[int] | None = None,
    line_type: str | Sequence[str] | None = None,
    exclude_lines: Sequence[int] = (),
    exclude_line_type: str | Sequence[str] | None = None,
) -> Survey:
    """The readings of ``s`` on the chosen lines: ids ``lines`` and / or lines of ``line_type`` (both: the lines
    that are both), minus ``exclude_lines`` and lines of ``exclude_line_type``. Unknown ids or types are errors.
    (Selection by azimuth: :func:`magnav_ins.maps.build.cross_lines`.)"""
    keep = np.ones(len(s), dtype=bool)
    if line_type is not None:
        keep &= s.type_mask(line_type)
    if exclude_line_type is not None:
        keep &= ~s.type_mask(exclude_line_type)
    for ids, sign in ((lines, True), (exclude_lines, False)):
        if ids is None or (not sign and not len(ids)):
            continue
        have = s.line_ids()
        unknown = sorted(set(int(i) for i in ids) - set(have.tolist()))
        if unknown:
            raise InputError(f"{s.source}: {unknown} are not line ids of the survey ({_id_summary(have)})")
        m = np.isin(s.line, np.asarray(ids, dtype=np.int64))  # type: ignore[arg-type]
        keep &= m if sign else ~m
    if not keep.any():
        raise InputError(f"{s.source}: no reading left after selecting lines")
    return s if keep.all() else s.select(keep)


def _id_summary(ids: NDArray[np.int64]) -> str:
    if len(ids) <= 12:
        return ", ".join(map(str, ids))
    return ", ".join(map(str, ids[:6])) + ", ..., " + ", ".join(map(str, ids[-3:]))


# ============================================================================================ any map spec
SURVEY_SUFFIXES = (".csv", ".csv.xz", ".csv.gz", ".csv.bz2")


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
    **unknown: Any,
) -> GridMap:
    """Any map the project accepts: ``builtin:NAME`` (shipped, :mod:`magnav_ins.maps.builtin`), a NetCDF grid
    (:func:`read_map`), or a survey CSV(.xz) gridded on load at ``grid_spacing_m`` (required) with
    :func:`magnav_ins.maps.build.grid_survey`: read with ``columns`` / ``geoid_undulation_m``
    (:func:`read_survey`), only the lines of ``line_type`` kept, ``exclude_lines`` and the lines of
    ``exclude_line_type`` left out (:func:`select_lines`)."""
    s = str(spec)
    if unknown:
        raise MapError(
            f"{s}: unknown map option(s) {sorted(unknown)}; expected grid_spacing_m, exclude_lines, kind, altitude_m, "
            "datum, geoid_undulation_m, method, columns, line_type, exclude_line_type"
        )
    survey_only = {
        "columns": columns,
        "line_type": line_type,
        "exclude_line_type": exclude_line_type,
        "geoid_undulation_m": geoid_undulation_m,
    }
    given = sorted(k for k, v in survey_only.items() if v)
    if given and not s.lower().endswith(SURVEY_SUFFIXES):
        raise MapError(f"{s}: {', '.join(given)} apply to survey CSV files, not to grids")
    if s.startswith(BUILTIN_PREFIX):
        from .builtin import load_builtin_map

        if grid_spacing_m is not None or exclude_lines:
            raise MapError(f"{s}: grid_spacing_m / exclude_lines apply to survey files, not to shipped grids")
        return load_builtin_map(s[len(BUILTIN_PREFIX) :])
    if s.lower().endswith(SURVEY_SUFFIXES):
        if grid_spacing_m is None:
            raise MapError(f"{s}: a survey file is gridded on load; give the grid spacing (grid_spacing_m / --spacing)")
        from .build import grid_survey

        survey = read_survey(
            s, kind=kind, geoid_undulation_m=geoid_undulation_m, altitude_m=altitude_m, columns=columns
        )
        if line_type is not None or exclude_line_type is not None:
            survey = select_lines(survey, line_type=line_type, exclude_line_type=exclude_line_type)
        fmap = grid_survey(survey, grid_spacing_m, exclude_lines=exclude_lines or (), method=method, name=Path(s).name)
        if line_type is not None:
            fmap.metadata["line_type"] = line_type
        if exclude_line_type is not None:
            fmap.metadata["excluded_line_type"] = exclude_line_type
        fmap.metadata["heights"] = survey.heights
        return fmap
    if grid_spacing_m is not None or exclude_lines:
        raise MapError(f"{s}: grid_spacing_m / exclude_lines apply to survey CSV files, not to NetCDF grids")
    return read_map(s, kind=kind, altitude_m=altitude_m, datum=datum)
