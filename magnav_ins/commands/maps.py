"""``magnav-ins map ...``: inspect a map, grid a survey, sample a map at points.

    magnav-ins map info MAP [--json]
    magnav-ins map grid SURVEY --spacing M [--exclude-lines ID,ID,...] [--exclude-tie-lines] [--line-type T]
                   [--exclude-line-type T] [--check-lines T] [--column OURS=THEIRS ...] [--geoid-m N] [--out MAP.nc]
    magnav-ins map sample MAP --points CSV --out CSV [--method bilinear|bicubic]

``MAP`` is a NetCDF grid, ``builtin:NAME`` or a survey CSV(.xz) (then ``--spacing`` grids it on load). Files that
lack kind/unit/datum/altitude metadata are refused; ``--kind``, ``--altitude-m``, ``--datum`` supply them explicitly.
Survey CSVs with other column names are read through ``--column OURS=THEIRS`` (repeatable); orthometric heights are
made ellipsoidal with the shipped EIGEN-6C4 geoid unless ``--geoid-m`` gives the undulation.
Outputs are written atomically; user mistakes give a one-line error and exit status 2.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

from ..core.atomic import atomic_path
from ..core.errors import InputError
from ..core.types import FieldKind
from ..core.units import DEG_TO_RAD, RAD_TO_DEG
from . import map_variability


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("map", help="maps: inspect, grid a survey, sample at points, feature variability")
    map_sub = p.add_subparsers(dest="map_command", metavar="MAP_COMMAND")
    map_sub.required = True
    _add_info(map_sub)
    _add_grid(map_sub)
    _add_sample(map_sub)
    # --- sub-commands defined in other modules register here (one line each) ---
    map_variability.add_parser(map_sub)


def _map_options(p: argparse.ArgumentParser, *, survey: bool) -> None:
    kinds = [k.value for k in FieldKind]
    p.add_argument("--kind", choices=kinds, default=None, help="what the map measures, if the file does not say")
    p.add_argument("--altitude-m", type=float, default=None, help="ellipsoidal height (m) if the file does not say")
    p.add_argument("--datum", default=None, help="geodetic datum if the file does not say (only WGS84 is supported)")
    if survey:
        _survey_options(p)
    p.add_argument("--spacing", type=float, default=None, metavar="M", help="grid spacing (m) for a survey CSV")


def _survey_options(p: argparse.ArgumentParser) -> None:
    """Options of every command that reads a survey CSV: column mapping, geoid, line selection by type."""
    p.add_argument(
        "--geoid-m",
        type=float,
        default=None,
        help="geoid undulation N (m) turning a survey's height_orthometric_m into ellipsoidal height H + N "
        "(default: the shipped EIGEN-6C4 geoid, 10')",
    )
    p.add_argument(
        "--column",
        action="append",
        default=[],
        metavar="OURS=THEIRS",
        help="survey column mapping, repeatable: e.g. --column height_ellipsoidal_m=height_ell_m --column "
        "line=line_number",
    )
    p.add_argument("--line-type", default=None, metavar="TYPE", help="use only the lines of this line_type (e.g. LINE)")
    p.add_argument(
        "--exclude-line-type", default=None, metavar="TYPE", help="leave out the lines of this line_type (e.g. TIE)"
    )


def _log_to_stderr(args: argparse.Namespace) -> None:
    """Show the map readers' INFO lines (e.g. which geoid made a survey's heights ellipsoidal) unless --quiet."""
    import logging

    lg = logging.getLogger("magnav_ins.maps")
    if getattr(args, "quiet", False) or lg.handlers:
        return
    h = logging.StreamHandler()
    h.setFormatter(logging.Formatter("magnav-ins: %(message)s"))
    lg.addHandler(h)
    lg.setLevel(logging.INFO)


def _load(args: argparse.Namespace, spec: str) -> Any:
    from ..maps.io import load_map, parse_column_mapping

    _log_to_stderr(args)
    return load_map(
        spec,
        grid_spacing_m=args.spacing,
        kind=args.kind,
        altitude_m=args.altitude_m,
        datum=args.datum,
        geoid_undulation_m=getattr(args, "geoid_m", None),
        columns=parse_column_mapping(getattr(args, "column", [])) or None,
        line_type=getattr(args, "line_type", None),
        exclude_line_type=getattr(args, "exclude_line_type", None),
    )


# ------------------------------------------------------------------------------------------------ info
def _add_info(map_sub: argparse._SubParsersAction) -> None:
    p = map_sub.add_parser("info", help="describe a map: kind, unit, frame, extent, spacing, altitude, value range")
    p.add_argument("map", metavar="MAP", help="NetCDF grid, builtin:NAME or survey CSV(.xz) with --spacing")
    _map_options(p, survey=True)
    p.add_argument("--json", action="store_true", help="print one JSON object instead of a table")
    p.set_defaults(handler=run_info)


def map_summary(fmap: Any) -> dict[str, Any]:
    """A JSON-able description of a :class:`GridMap` (degrees and metres)."""
    lat0, lat1, lon0, lon1 = fmap.bounds_latlon
    v = np.asarray(fmap.values, dtype=float)
    alt = np.asarray(fmap.altitude_m, dtype=float)
    dn, de = fmap.spacing_m
    out: dict[str, Any] = {
        "name": fmap.name,
        "kind": fmap.kind.value,
        "unit": fmap.unit,
        "frame": fmap.frame,
        "datum": fmap.datum,
        "crs": fmap.crs,
        "shape": list(fmap.shape),
        "spacing_m": [dn, de],
        "lat_deg": [lat0 * RAD_TO_DEG, lat1 * RAD_TO_DEG],
        "lon_deg": [lon0 * RAD_TO_DEG, lon1 * RAD_TO_DEG],
        "altitude_m": float(alt) if alt.ndim == 0 else [float(np.nanmin(alt)), float(np.nanmax(alt))],
        "draped": bool(alt.ndim != 0),
        "value_range": [float(np.nanmin(v)), float(np.nanmax(v))],
        "value_rms": float(np.sqrt(np.nanmean(v**2))),
        "coverage": float(np.mean(np.isfinite(v))),
    }
    if fmap.frame == "local":
        out["origin_deg_m"] = [fmap.origin[0] * RAD_TO_DEG, fmap.origin[1] * RAD_TO_DEG, fmap.origin[2]]
        w, e, s, n = fmap.region
        out["northing_m"] = [s, n]
        out["easting_m"] = [w, e]
    if fmap.metadata:
        out["metadata"] = fmap.metadata
    return out


def run_info(args: argparse.Namespace) -> int:
    fmap = _load(args, args.map)
    s = map_summary(fmap)
    if args.json:
        print(json.dumps(s, default=str))
        return 0
    alt = s["altitude_m"]
    rows = [
        ("name", s["name"]),
        ("kind", f"{s['kind']} [{s['unit']}]"),
        (
            "frame",
            s["frame"]
            + (f" (origin {s['origin_deg_m'][0]:.6f}, {s['origin_deg_m'][1]:.6f} deg)" if "origin_deg_m" in s else ""),
        ),
        ("datum / crs", f"{s['datum']} / {s['crs'] or '-'}"),
        ("shape (ny, nx)", f"{s['shape'][0]} x {s['shape'][1]}"),
        ("spacing", f"{s['spacing_m'][0]:.1f} m north, {s['spacing_m'][1]:.1f} m east"),
        ("latitude", f"{s['lat_deg'][0]:.5f} .. {s['lat_deg'][1]:.5f} deg"),
        ("longitude", f"{s['lon_deg'][0]:.5f} .. {s['lon_deg'][1]:.5f} deg"),
        ("altitude", f"{alt:.1f} m" if not s["draped"] else f"draped {alt[0]:.1f} .. {alt[1]:.1f} m (ellipsoidal)"),
        ("values", f"{s['value_range'][0]:.3f} .. {s['value_range'][1]:.3f} {s['unit']} (rms {s['value_rms']:.3f})"),
        ("coverage", f"{100 * s['coverage']:.1f} % of nodes"),
    ]
    w = max(len(k) for k, _ in rows)
    for k, v in rows:
        print(f"{k:<{w}}  {v}")
    return 0


# ------------------------------------------------------------------------------------------------ grid
def _add_grid(map_sub: argparse._SubParsersAction) -> None:
    p = map_sub.add_parser("grid", help="grid a survey CSV(.xz) into a NetCDF map (bidirectional line gridding)")
    p.add_argument(
        "survey", metavar="SURVEY", help="survey CSV(.xz): latitude, longitude, height, value[, flight_line]"
    )
    p.add_argument("--spacing", type=float, required=True, metavar="M", help="grid spacing in metres")
    p.add_argument("--exclude-lines", default="", metavar="ID,ID,...", help="line ids to leave out")
    p.add_argument(
        "--exclude-tie-lines",
        action="store_true",
        help="leave out the cross (tie) lines, found by line azimuth (more than 20 deg off the dominant direction)",
    )
    p.add_argument("--method", choices=["auto", "bidirectional", "linear", "cubic"], default="auto")
    p.add_argument("--kind", choices=[k.value for k in FieldKind], default=None, help="kind of a 'value' column")
    _survey_options(p)
    p.add_argument(
        "--check-lines",
        default=None,
        metavar="TYPE",
        help="after gridding, predict the readings of the lines of this line_type (left out of the grid, e.g. TIE) "
        "and print the misfit",
    )
    p.add_argument("--altitude-m", type=float, default=None, help="constant ellipsoidal height if no height column")
    p.add_argument("--float32", action="store_true", help="store values as float32 (half the size)")
    p.add_argument("--out", default=None, metavar="MAP.nc", help="output NetCDF (default: SURVEY name + .nc here)")
    p.add_argument("--quiet", action="store_true", help="print nothing")
    p.set_defaults(handler=run_grid)


def _parse_ids(text: str) -> list[int]:
    out = []
    for tok in filter(None, (t.strip() for t in text.split(","))):
        try:
            out.append(int(tok))
        except ValueError:
            raise InputError(f"--exclude-lines: {tok!r} is not an integer line id (expected ID,ID,...)") from None
    return out


def run_grid(args: argparse.Namespace) -> int:
    import time

    from ..maps.build import cross_lines, grid_survey, tie_line_misfit
    from ..maps.io import parse_column_mapping, read_survey, select_lines, write_map

    _log_to_stderr(args)
    exclude = _parse_ids(args.exclude_lines)
    src = Path(args.survey)
    out = Path(args.out) if args.out else Path(src.name.split(".")[0] + ".nc")
    t0 = time.perf_counter()
    survey = read_survey(
        src,
        kind=args.kind,
        geoid_undulation_m=args.geoid_m,
        altitude_m=args.altitude_m,
        columns=parse_column_mapping(args.column) or None,
    )
    check_ids: list[int] = []
    if args.check_lines is not None:
        check_ids = survey.ids_of_type(args.check_lines)
        if args.line_type == args.check_lines:
            raise InputError(f"--check-lines {args.check_lines}: the same lines cannot be gridded and checked")
    used = survey
    if args.line_type is not None or args.exclude_line_type is not None:
        used = select_lines(survey, line_type=args.line_type, exclude_line_type=args.exclude_line_type)
    ties: list[int] = []
    if args.exclude_tie_lines:
        ties = cross_lines(used)
        exclude = sorted(set(exclude) | set(ties))
    if check_ids:
        exclude = sorted(set(exclude) | (set(check_ids) & set(used.line_ids().tolist())))
    fmap = grid_survey(used, args.spacing, exclude_lines=exclude, method=args.method, name=out.stem)
    fmap.metadata["source"] = src.name
    fmap.metadata["heights"] = survey.heights
    for key, val in (("line_type", args.line_type), ("excluded_line_type", args.exclude_line_type)):
        if val is not None:
            fmap.metadata[key] = val
    misfit = None
    if check_ids:
        per = tie_line_misfit(fmap, survey, check_ids)
        misfit = _pooled_misfit(per)
        fmap.metadata["check_lines"] = {"line_type": args.check_lines, **misfit}
    write_map(fmap, out, dtype="float32" if args.float32 else "float64")
    if not args.quiet:
        dn, de = fmap.spacing_m
        print(
            f"gridded {fmap.metadata['readings']} readings ({fmap.metadata['gridder']}) -> {out}: {fmap.shape[0]} x {fmap.shape[1]} "
            f"nodes at {dn:.0f} m, {100 * np.mean(np.isfinite(fmap.values)):.0f} % covered, "
            f"{time.perf_counter() - t0:.1f} s"
        )
        if ties:
            print(f"tie lines excluded: {','.join(map(str, ties))}")
        ign = fmap.metadata.get("ignored_lines") or []
        if ign:
            print(f"cross lines not used by the line gridder: {','.join(map(str, ign))}")
        if misfit is not None:
            print(
                f"{args.check_lines} lines ({len(check_ids)}) predicted by the map: {misfit['n']} readings, misfit "
                f"(map - observed) RMS {misfit['rms']:.2f}, mean {misfit['mean']:.2f}, std {misfit['std']:.2f} "
                f"{fmap.unit}; {misfit['n_off']} off the map"
            )
    return 0


def _pooled_misfit(per: dict[int, dict]) -> dict[str, Any]:
    """Pool :func:`~magnav_ins.maps.build.tie_line_misfit`'s per-line figures over the lines (reading-weighted)."""
    n = sum(v["n"] for v in per.values())
    if n == 0:
        return {"n": 0, "n_off": sum(v["n_off"] for v in per.values()), "rms": float("nan"), "mean": float("nan"),
                "std": float("nan"), "lines": len(per)}  # fmt: skip
    ms = sum(v["rms"] ** 2 * v["n"] for v in per.values() if v["n"]) / n
    mean = sum(v["mean"] * v["n"] for v in per.values() if v["n"]) / n
    return {
        "n": int(n),
        "n_off": int(sum(v["n_off"] for v in per.values())),
        "rms": float(np.sqrt(ms)),
        "mean": float(mean),
        "std": float(np.sqrt(max(ms - mean**2, 0.0))),
        "lines": len(per),
    }


# ------------------------------------------------------------------------------------------------ sample
def _add_sample(map_sub: argparse._SubParsersAction) -> None:
    p = map_sub.add_parser("sample", help="map values at points (CSV lat_deg,lon_deg[,h_m]); NaN off the map")
    p.add_argument("map", metavar="MAP", help="NetCDF grid, builtin:NAME or survey CSV(.xz) with --spacing")
    p.add_argument("--points", required=True, metavar="CSV", help="CSV with columns lat_deg, lon_deg[, h_m]")
    p.add_argument("--out", required=True, metavar="CSV", help="output CSV: the input columns + value")
    p.add_argument("--method", choices=["bilinear", "bicubic"], default="bilinear")
    _map_options(p, survey=True)
    p.set_defaults(handler=run_sample)


def read_points(path: str | Path) -> Any:
    """Read a points CSV (``lat_deg``, ``lon_deg``[, ``h_m``]) as a DataFrame, validating every row."""
    from ..maps.io import _check_latlon, _numeric, read_csv_checked

    src = str(path)
    if not Path(path).is_file():
        raise InputError(f"{src}: no such points file")
    df = read_csv_checked(path)
    for c in ("lat_deg", "lon_deg"):
        if c not in df.columns:
            raise InputError(
                f"{src}: missing column '{c}' (expected lat_deg, lon_deg[, h_m]); found {list(df.columns)}"
            )
    if len(df) == 0:
        raise InputError(f"{src}: no data rows")
    for c in ("lat_deg", "lon_deg") + (("h_m",) if "h_m" in df.columns else ()):
        df[c] = _numeric(df, c, src, allow_nan=False)
    _check_latlon(df["lat_deg"].to_numpy(), df["lon_deg"].to_numpy(), src, "lat_deg", "lon_deg")
    return df


def run_sample(args: argparse.Namespace) -> int:
    fmap = _load(args, args.map)
    df = read_points(args.points)
    lat = df["lat_deg"].to_numpy(dtype=float) * DEG_TO_RAD
    lon = df["lon_deg"].to_numpy(dtype=float) * DEG_TO_RAD
    h = df["h_m"].to_numpy(dtype=float) if "h_m" in df.columns else None
    v = fmap.value(lat, lon, h, method=args.method)
    out = df.copy()
    if v.ndim == 2:
        for k, comp in enumerate(("north", "east", "down")):
            out[f"value_{comp}"] = v[:, k]
    else:
        out["value"] = v
    with atomic_path(args.out) as tmp:
        out.to_csv(tmp, index=False, float_format="%.10g")
        tmp.chmod(0o644)
    return 0
