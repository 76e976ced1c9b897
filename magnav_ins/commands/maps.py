"""``magnav-ins map ...``: inspect a map, grid a survey, sample a map at points.

    magnav-ins map info MAP [--json]
    magnav-ins map grid SURVEY --spacing M [--exclude-lines ID,ID,...] [--exclude-tie-lines] [--line-type T]
                   [--exclude-line-type T] [--check-lines T] [--error-lines T] [--column OURS=THEIRS ...] [--geoid-m N] [--out MAP.nc]
    magnav-ins map sample MAP --points CSV --out CSV [--method bilinear|bicubic]
    magnav-ins map combine FINE COARSE [--margin-m M] [--blend-m M] [--no-level] --out MAP.nc
    magnav-ins map convert FILE [--unit U] [--kind K] [--altitude-m M] [--datum D] [--crs CRS] [--variable V]
                   [--reproject] --out MAP.nc

``MAP`` is a grid file (this project's NetCDF, or as downloaded: GeoTIFF, ER Mapper ``.ers``, Geosoft GXF / GRD, GMT /
COARDS / CF NetCDF; :mod:`magnav_ins.maps.formats`), ``builtin:NAME`` or a survey CSV(.xz) (then ``--spacing`` grids
it on load). Files that lack kind/unit/datum/altitude/CRS metadata are refused in one message naming what is
missing; ``--kind``, ``--unit``, ``--altitude-m``, ``--datum``, ``--crs``, ``--variable`` supply them explicitly.
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

from ..core.atomic import atomic_path, check_output_file
from ..core.errors import InputError
from ..core.types import FieldKind
from ..core.units import DEG_TO_RAD, RAD_TO_DEG
from . import map_variability
from .map_options import load, log_to_stderr, map_options, survey_options


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("map", help="maps: inspect, grid a survey, sample at points, feature variability")
    map_sub = p.add_subparsers(dest="map_command", metavar="MAP_COMMAND")
    map_sub.required = True
    _add_info(map_sub)
    _add_grid(map_sub)
    _add_sample(map_sub)
    _add_convert(map_sub)
    _add_combine(map_sub)
    # --- sub-commands defined in other modules register here (one line each) ---
    map_variability.add_parser(map_sub)


# ------------------------------------------------------------------------------------------------ info
def _add_info(map_sub: argparse._SubParsersAction) -> None:
    p = map_sub.add_parser("info", help="describe a map: kind, unit, frame, extent, spacing, altitude, value range")
    p.add_argument("map", metavar="MAP", help="NetCDF grid, builtin:NAME or survey CSV(.xz) with --spacing")
    map_options(p, survey=True)
    p.add_argument("--json", action="store_true", help="print one JSON object instead of a table")
    p.set_defaults(handler=run_info)


def map_summary(fmap: Any) -> dict[str, Any]:
    """A JSON-able description of a :class:`GridMap` (degrees and metres)."""
    lat0, lat1, lon0, lon1 = fmap.bounds_latlon
    v = np.asarray(fmap.values, dtype=float)
    alt = np.asarray(fmap.altitude_m, dtype=float)
    dn, de = fmap.spacing_m
    meta = fmap.metadata or {}
    out: dict[str, Any] = {
        "name": fmap.name,
        "format": meta.get("format", "magnav_ins NetCDF" if "made_by" in meta or "gridder" in meta else "GridMap"),
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
        "no_data_fraction": float(np.mean(~np.isfinite(v))),
    }
    if fmap.frame == "projected":
        out["crs_name"] = fmap.projection.name
        out["used_as"] = f"in its own CRS ({fmap.projection.name}) through pyproj: {fmap.projection.transform}"
        w, e, s_, n = fmap.region
        out["northing_m"] = [s_, n]
        out["easting_m"] = [w, e]
    elif "reprojected_from" in meta:
        out["used_as"] = "reprojected onto a WGS-84 latitude/longitude grid"
    if fmap.has_error_layer:
        es = np.asarray(fmap.error_sigma, dtype=float)
        out["error_layer"] = {
            "sigma_median": float(np.median(es)),
            "sigma_p90": float(np.percentile(es, 90)),
            "sigma_range": [float(es.min()), float(es.max())],
            "correlation_m": float(fmap.error_correlation_m),
            "source": fmap.error_source,
        }
    else:
        out["error_layer"] = None
    from ..aiding.matchers.map_error import resolve_level

    lvl = resolve_level(fmap)
    out["level_sigma"] = {"sigma": lvl.sigma, "source": lvl.source, "detail": lvl.detail}
    if fmap.frame == "local":
        out["origin_deg_m"] = [fmap.origin[0] * RAD_TO_DEG, fmap.origin[1] * RAD_TO_DEG, fmap.origin[2]]
        w, e, s, n = fmap.region
        out["northing_m"] = [s, n]
        out["easting_m"] = [w, e]
    if fmap.metadata:
        out["metadata"] = fmap.metadata
    return out


def run_info(args: argparse.Namespace) -> int:
    fmap = load(args, args.map)
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
        ("format", s["format"]),
        ("datum / crs", f"{s['datum']} / {s.get('crs_name') or s['crs'] or '-'}"),
        ("shape (ny, nx)", f"{s['shape'][0]} x {s['shape'][1]}"),
        ("spacing", f"{s['spacing_m'][0]:.1f} m north, {s['spacing_m'][1]:.1f} m east"),
        ("latitude", f"{s['lat_deg'][0]:.5f} .. {s['lat_deg'][1]:.5f} deg"),
        ("longitude", f"{s['lon_deg'][0]:.5f} .. {s['lon_deg'][1]:.5f} deg"),
        ("altitude", f"{alt:.1f} m" if not s["draped"] else f"draped {alt[0]:.1f} .. {alt[1]:.1f} m (ellipsoidal)"),
        ("values", f"{s['value_range'][0]:.3f} .. {s['value_range'][1]:.3f} {s['unit']} (rms {s['value_rms']:.3f})"),
        ("no data", f"{100 * s['no_data_fraction']:.1f} % of nodes"),
        ("error layer", _error_text(s)),
        ("level offset", _level_text(s)),
    ]
    if "used_as" in s:
        rows.insert(4, ("used", s["used_as"]))
    if "northing_m" in s and s["frame"] == "projected":
        rows.insert(5, ("northing / easting", f"{s['northing_m'][0]:.1f} .. {s['northing_m'][1]:.1f} m / "
                        f"{s['easting_m'][0]:.1f} .. {s['easting_m'][1]:.1f} m (projected)"))  # fmt: skip
    w = max(len(k) for k, _ in rows)
    for k, v in rows:
        print(f"{k:<{w}}  {v}")
    return 0


def _error_text(s: dict[str, Any]) -> str:
    e = s.get("error_layer")
    if not e:
        return "no error layer (matchers use their stated default)"
    return (
        f"1-sigma median {e['sigma_median']:.3g}, 90 % {e['sigma_p90']:.3g}, range {e['sigma_range'][0]:.3g} .. "
        f"{e['sigma_range'][1]:.3g} {s['unit']}; correlation length {e['correlation_m']:.0f} m; {e['source']}"
    )


def _level_text(s: dict[str, Any]) -> str:
    lv = s["level_sigma"]
    where = "stated in the map" if lv["source"] == "map" else "the matchers' stated default"
    detail = f": {lv['detail']}" if lv["detail"] else ""
    return (
        f"1-sigma {lv['sigma']:.3g} {s['unit']} ({where}{detail}), the prior of the constant offset between a "
        "flight's readings and the map that the matchers marginalise"
    )


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
    survey_options(p)
    p.add_argument(
        "--check-lines",
        default=None,
        metavar="TYPE",
        help="after gridding, predict the readings of the lines of this line_type (left out of the grid, e.g. TIE) "
        "and print the misfit",
    )
    p.add_argument(
        "--error-lines",
        default=None,
        metavar="TYPE",
        help="lines of this line_type (not gridded, e.g. TIE) whose crossovers with the gridded lines measure the "
        "map's error between line sets (added to the cross-validated error layer; the cross lines the line gridder "
        "leaves out are used so without this option)",
    )
    p.add_argument("--altitude-m", type=float, default=None, help="constant ellipsoidal height if no height column")
    p.add_argument(
        "--error-folds",
        type=int,
        default=5,
        metavar="K",
        help="folds of the block cross-validation that estimates the map's error layer (0: no layer; default 5)",
    )
    p.add_argument(
        "--level-sigma",
        type=float,
        default=None,
        metavar="S",
        help="1-sigma (map unit) of a constant offset between a flight's readings and the map, stored with the map "
        "for the matchers to marginalise (default: none stored; the matchers then use the larger of 10 %% of the map's "
        "std and the survey's crossover level differences)",
    )
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

    log_to_stderr(args)
    if args.level_sigma is not None and not (np.isfinite(args.level_sigma) and args.level_sigma >= 0):
        raise InputError(f"--level-sigma: expected a number >= 0 (map unit), got {args.level_sigma}")
    exclude = _parse_ids(args.exclude_lines)
    src = Path(args.survey)
    out = check_output_file(Path(args.out) if args.out else Path(src.name.split(".")[0] + ".nc"))
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
    error_lines = None
    if args.error_lines is not None:
        if args.error_lines == args.line_type:
            raise InputError(f"--error-lines {args.error_lines}: the lines gridded cannot measure their own error")
        error_lines = survey.of_type(args.error_lines)
        error_lines = error_lines.select(~np.isin(error_lines.line, np.asarray(exclude, dtype=np.int64)))
        if len(error_lines) == 0:
            raise InputError(f"--error-lines {args.error_lines}: all its lines are excluded")
    if args.error_folds < 0 or args.error_folds == 1:
        raise InputError(f"--error-folds: expected 0 (no error layer) or at least 2, got {args.error_folds}")
    fmap = grid_survey(
        used,
        args.spacing,
        exclude_lines=exclude,
        method=args.method,
        name=out.stem,
        error_folds=args.error_folds,
        level_sigma=args.level_sigma,
        check_lines=error_lines,
    )
    fmap.metadata["source"] = src.name
    fmap.metadata["heights"] = survey.heights
    for key, val in (("line_type", args.line_type), ("excluded_line_type", args.exclude_line_type)):
        if val is not None:
            fmap.metadata[key] = val
    misfit = None
    if check_ids:
        per = tie_line_misfit(fmap, survey, check_ids)
        misfit = _pooled_misfit(per)
        if fmap.has_error_layer:
            misfit["z_rms"] = normalised_misfit(fmap, survey.select(np.isin(survey.line, check_ids)))
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
        print(f"error layer: {_error_text(map_summary(fmap))}")
        if misfit is not None:
            print(
                f"{args.check_lines} lines ({len(check_ids)}) predicted by the map: {misfit['n']} readings, misfit "
                f"(map - observed) RMS {misfit['rms']:.2f}, mean {misfit['mean']:.2f}, std {misfit['std']:.2f} "
                f"{fmap.unit}; {misfit['n_off']} off the map"
                + (f"; RMS of misfit / error-layer sigma {misfit['z_rms']:.2f}" if "z_rms" in misfit else "")
                + (
                    " (in-sample: these lines also measured the layer's between-line-set term)"
                    if args.error_lines is not None and args.error_lines == args.check_lines
                    else ""
                )
            )
    return 0


def normalised_misfit(fmap: Any, survey: Any) -> float:
    """RMS of (map - reading) / error-layer sigma over the readings of ``survey`` on the map (about 1 when the
    layer is honest)."""
    r = fmap.value(survey.lat, survey.lon) - survey.value
    sig = fmap.error_sigma_at(survey.lat, survey.lon)
    ok = np.isfinite(r) & np.isfinite(sig) & (sig > 0)
    return float(np.sqrt(np.mean((r[ok] / sig[ok]) ** 2))) if ok.any() else float("nan")


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


# ------------------------------------------------------------------------------------------------ convert
def _add_convert(map_sub: argparse._SubParsersAction) -> None:
    p = map_sub.add_parser(
        "convert",
        help="write any readable map (GeoTIFF, ER Mapper, GXF, GMT/COARDS/CF NetCDF, survey CSV) in magnav_ins's "
        "NetCDF format",
    )
    p.add_argument("map", metavar="FILE", help="grid file, builtin:NAME or survey CSV(.xz) with --spacing")
    map_options(p, survey=True)
    p.add_argument("--float32", action="store_true", help="store values as float32 (half the size)")
    p.add_argument("--out", required=True, metavar="MAP.nc", help="output NetCDF")
    p.add_argument("--quiet", action="store_true", help="print nothing")
    p.set_defaults(handler=run_convert)


def run_convert(args: argparse.Namespace) -> int:
    from ..maps.io import write_map

    fmap = load(args, args.map)
    out = Path(args.out)
    if out.resolve() == Path(args.map).resolve():
        raise InputError(f"--out {out}: would overwrite the input map")
    write_map(fmap, out, dtype="float32" if args.float32 else "float64")
    if not args.quiet:
        s = map_summary(fmap)
        print(
            f"wrote {out}: {s['kind']} [{s['unit']}], {s['frame']} frame, {s['shape'][0]} x {s['shape'][1]} nodes, "
            f"{100 * s['no_data_fraction']:.1f} % no data, error layer: {'yes' if s['error_layer'] else 'no'}"
        )
    return 0


# ------------------------------------------------------------------------------------------------ combine
def _add_combine(map_sub: argparse._SubParsersAction) -> None:
    p = map_sub.add_parser(
        "combine",
        help="a fine map over a coarse one (blended edge, levelled, both error layers) -> NetCDF, as MagNav.jl's "
        "map_combine",
    )
    p.add_argument("fine", metavar="FINE", help="the fine map (magnav_ins NetCDF or builtin:NAME; map convert first)")
    p.add_argument("coarse", metavar="COARSE", help="the coarse (regional) map, same kind")
    p.add_argument("--margin-m", type=float, default=None, help="widen the fine map's extent by this (default 10 %%)")
    p.add_argument("--blend-m", type=float, default=None, help="width of the blended edge (default 5 node spacings)")
    p.add_argument("--no-level", action="store_true", help="do not shift the coarse map onto the fine one's mean")
    p.add_argument("--out", required=True, metavar="MAP.nc", help="output NetCDF")
    p.add_argument("--quiet", action="store_true", help="print nothing")
    p.set_defaults(handler=run_combine)


def run_combine(args: argparse.Namespace) -> int:
    from ..maps.combine import combine_maps
    from ..maps.io import load_map, write_map

    log_to_stderr(args)
    fine, coarse = load_map(args.fine), load_map(args.coarse)
    m = combine_maps(fine, coarse, margin_m=args.margin_m, blend_m=args.blend_m, level=not args.no_level)
    write_map(m, args.out)
    if not args.quiet:
        lv = m.metadata.get("coarse_levelled_by")
        print(
            f"wrote {args.out}: {m.shape[0]} x {m.shape[1]} nodes, fine map on {100 * m.metadata['fine_fraction']:.0f} %"
            + (f", coarse levelled by {lv:+.2f} {m.unit}" if lv is not None else "")
            + f", error layer: {'yes' if m.has_error_layer else 'no (both maps need one)'}"
        )
    return 0


# ------------------------------------------------------------------------------------------------ sample
def _add_sample(map_sub: argparse._SubParsersAction) -> None:
    p = map_sub.add_parser("sample", help="map values at points (CSV lat_deg,lon_deg[,h_m]); NaN off the map")
    p.add_argument("map", metavar="MAP", help="NetCDF grid, builtin:NAME or survey CSV(.xz) with --spacing")
    p.add_argument("--points", required=True, metavar="CSV", help="CSV with columns lat_deg, lon_deg[, h_m]")
    p.add_argument("--out", required=True, metavar="CSV", help="output CSV: the input columns + value")
    p.add_argument("--method", choices=["bilinear", "bicubic"], default="bilinear")
    map_options(p, survey=True)
    p.set_defaults(handler=run_sample)


def read_points(path: str | Path) -> Any:
    """Read a points CSV (``lat_deg``, ``lon_deg``[, ``h_m``]) as a DataFrame, validating every row."""
    from ..maps.survey import _check_latlon, _numeric, read_csv_checked

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
    check_output_file(args.out)
    fmap = load(args, args.map)
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
