"""Options and the map loader shared by every ``magnav-ins map ...`` sub-command (``commands/maps.py`` and the
sub-commands in their own modules, e.g. ``commands/map_variability.py``): one place, no import circle."""

from __future__ import annotations

import argparse
from typing import Any

from ..core.errors import warn
from ..core.types import FieldKind


def map_options(p: argparse.ArgumentParser, *, survey: bool) -> None:
    """``--kind``, ``--altitude-m``, ``--datum``, the downloaded-grid options (``--unit``, ``--crs``, ``--variable``,
    ``--reproject``), the error-layer options and, with ``survey``, the survey options."""
    kinds = [k.value for k in FieldKind]
    p.add_argument("--kind", choices=kinds, default=None, help="what the map measures, if the file does not say")
    p.add_argument("--altitude-m", type=float, default=None, help="ellipsoidal height (m) if the file does not say")
    p.add_argument("--datum", default=None, help="geodetic datum if the file does not say (only WGS84 is supported)")
    grid_options(p)
    if survey:
        survey_options(p)
    p.add_argument("--spacing", type=float, default=None, metavar="M", help="grid spacing (m) for a survey CSV")
    p.add_argument(
        "--map-error-sigma",
        type=float,
        default=None,
        metavar="S",
        help="give the map a uniform error layer: 1-sigma map error in the map's unit (with --map-error-correlation-m)",
    )
    p.add_argument(
        "--map-error-correlation-m",
        type=float,
        default=None,
        metavar="M",
        help="correlation length (m) of the map error given by --map-error-sigma",
    )


def grid_options(p: argparse.ArgumentParser) -> None:
    """Options of a grid file as downloaded (GeoTIFF, ER Mapper, GXF, GMT / COARDS / CF NetCDF)."""
    p.add_argument(
        "--unit",
        default=None,
        help="unit of the values if the file states none or an impossible one (nT; mGal, um/s^2, m/s^2 converted)",
    )
    p.add_argument(
        "--crs", default=None, help="CRS of a grid in metres that does not say (EPSG:NNNN, a PROJ string or WKT)"
    )
    p.add_argument("--variable", default=None, help="the data variable of a file holding several grids")
    p.add_argument(
        "--reproject",
        action="store_true",
        help="resample a projected grid onto WGS-84 latitude/longitude instead of using it in its own CRS",
    )


def survey_options(p: argparse.ArgumentParser) -> None:
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


def log_to_stderr(args: argparse.Namespace) -> None:
    """Show the map readers' INFO lines (e.g. which geoid made a survey's heights ellipsoidal) unless --quiet."""
    import logging

    lg = logging.getLogger("magnav_ins.maps")
    if getattr(args, "quiet", False) or lg.handlers:
        return
    h = logging.StreamHandler()
    h.setFormatter(logging.Formatter("magnav-ins: %(message)s"))
    lg.addHandler(h)
    lg.setLevel(logging.INFO)


def load(args: argparse.Namespace, spec: str) -> Any:
    from ..core.plausibility import field_values_problem
    from ..maps.io import load_map, parse_column_mapping

    log_to_stderr(args)
    fmap = load_map(
        spec,
        grid_spacing_m=args.spacing,
        kind=args.kind,
        altitude_m=args.altitude_m,
        datum=args.datum,
        geoid_undulation_m=getattr(args, "geoid_m", None),
        columns=parse_column_mapping(getattr(args, "column", [])) or None,
        line_type=getattr(args, "line_type", None),
        exclude_line_type=getattr(args, "exclude_line_type", None),
        unit=getattr(args, "unit", None),
        crs=getattr(args, "crs", None),
        variable=getattr(args, "variable", None),
        reproject=bool(getattr(args, "reproject", False)),
        error_sigma=getattr(args, "map_error_sigma", None),
        error_correlation_m=getattr(args, "map_error_correlation_m", None),
    )
    problem = field_values_problem(fmap.values, fmap.kind) if hasattr(fmap, "values") else None
    if problem:  # inspection goes on; navigating on it ('run') is refused
        warn(f"{spec}: implausible for {fmap.kind.value}: {problem}")
    return fmap
