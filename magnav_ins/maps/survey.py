"""Survey CSV / CSV.xz line data (pandas): :class:`Survey` and its readers.

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

import logging
import lzma
import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..core.errors import InputError
from ..core.types import FieldKind
from ..core.units import DEG_TO_RAD
from .geoid import GEOID_NAME, geoid_undulation
from .shipped import BUILTIN_PREFIX, builtin_survey_path

FloatArray = NDArray[np.float64]
log = logging.getLogger(__name__)

_QUANTITIES = ("total_field_anomaly", "gravity_disturbance", "vector_field")
#: suffixes of survey files (gridded on load by :func:`magnav_ins.maps.io.load_map`)
SURVEY_SUFFIXES = (".csv", ".csv.xz", ".csv.gz", ".csv.bz2")

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
