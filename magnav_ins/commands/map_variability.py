"""``magnav-ins map variability MAP --window M --out FILE``: how much position information a map holds.

Writes a NetCDF (CF conventions) with the feature variability ``C_i`` (Wang et al. 2022 eq. 14), the windowed
gradient RMS and, with ``--sigma``, Cramér-Rao bounds (``maps.variability``), on the map's own grid; and a PNG of
the same rasters beside it (``FILE`` with suffix ``.png``). Both are written atomically. Registered under the
``map`` group by :func:`add_parser` (called from ``commands/maps.py``).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import numpy as np

from ..core.atomic import atomic_path, check_output_file
from ..core.errors import InputError
from ..core.units import RAD_TO_DEG
from .map_options import load, map_options


def add_parser(map_sub: argparse._SubParsersAction) -> None:
    """Register ``variability`` under the ``map`` sub-command group."""
    p = map_sub.add_parser(
        "variability",
        help="feature variability (Wang eq. 14), gradient RMS and Cramer-Rao bounds of a map -> NetCDF + PNG",
        description=__doc__,
    )
    p.add_argument("map", metavar="MAP", help="NetCDF grid, builtin:NAME or survey CSV(.xz) with --spacing")
    map_options(p, survey=True)
    p.add_argument("--window", type=float, required=True, metavar="M", help="square window width in metres")
    p.add_argument("--out", required=True, metavar="FILE", help="output NetCDF (a PNG is written beside it)")
    p.add_argument(
        "--sigma",
        type=float,
        default=None,
        metavar="S",
        help="reading noise (1 sigma, in the map's unit) for the Cramer-Rao bounds",
    )
    p.add_argument("--quiet", action="store_true", help="print nothing")
    p.set_defaults(handler=run)


def _coords(fmap: Any) -> tuple[dict[str, Any], tuple[str, str]]:
    y, x = fmap.axes
    if fmap.frame == "geodetic":
        return (
            {
                "lat": ("lat", y * RAD_TO_DEG, {"units": "degrees_north", "standard_name": "latitude"}),
                "lon": ("lon", x * RAD_TO_DEG, {"units": "degrees_east", "standard_name": "longitude"}),
            },
            ("lat", "lon"),
        )
    return (
        {
            "northing": ("northing", y, {"units": "m", "long_name": "northing in the local tangent plane"}),
            "easting": ("easting", x, {"units": "m", "long_name": "easting in the local tangent plane"}),
        },
        ("northing", "easting"),
    )


def compute(fmap: Any, window_m: float, sigma: float | None) -> dict[str, tuple[np.ndarray, str, str]]:
    """The rasters: name -> (values (ny, nx), unit, long name)."""
    from ..maps import variability as var

    unit = fmap.unit
    out = {
        "feature_variability": (
            np.asarray(var.feature_variability(fmap, window_m).values),
            f"{unit}^2",
            "map feature variability C_i (Wang et al. 2022 eq. 14)",
        ),
        "gradient_rms": (
            np.asarray(var.gradient_rms(fmap, window_m).values),
            f"{unit}/m",
            "RMS of the horizontal gradient norm over the window",
        ),
    }
    if sigma is not None:
        if not np.isfinite(sigma) or sigma <= 0:
            raise InputError(f"--sigma: expected a positive noise level in {unit}, got {sigma!r}")
        crlb = var.crlb_raster(fmap, sigma, window_m)
        out["crlb_along_gradient"] = (crlb["along_gradient"], "m", "Cramer-Rao bound of one reading, sigma/|grad|")
        out["crlb_semi_major"] = (crlb["semi_major"], "m", "Cramer-Rao 1-sigma semi-major axis, readings over window")
        out["crlb_semi_minor"] = (crlb["semi_minor"], "m", "Cramer-Rao 1-sigma semi-minor axis, readings over window")
    return out


def write_netcdf(path: Path, fmap: Any, rasters: dict[str, tuple[np.ndarray, str, str]], window_m: float) -> None:
    import xarray as xr

    coords, dims = _coords(fmap)
    data_vars = {name: (dims, vals, {"units": unit, "long_name": long}) for name, (vals, unit, long) in rasters.items()}
    attrs = {
        "Conventions": "CF-1.8",
        "title": f"information content of map {fmap.name!r}",
        "source_map_kind": fmap.kind.value,
        "frame": fmap.frame,
        "window_m": float(window_m),
        "datum": fmap.datum,
    }
    if fmap.frame == "local":
        attrs["origin_lat_deg"], attrs["origin_lon_deg"] = fmap.origin[0] * RAD_TO_DEG, fmap.origin[1] * RAD_TO_DEG
        attrs["origin_h_m"] = fmap.origin[2]
    ds = xr.Dataset(data_vars=data_vars, coords=coords, attrs=attrs)
    with atomic_path(path) as tmp:
        ds.to_netcdf(tmp, format="NETCDF4", encoding={k: {"zlib": True, "complevel": 4} for k in rasters})


def write_png(path: Path, fmap: Any, rasters: dict[str, tuple[np.ndarray, str, str]], window_m: float) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    y, x = fmap.axes
    if fmap.frame == "geodetic":
        y, x, labels = y * RAD_TO_DEG, x * RAD_TO_DEG, ("longitude (deg)", "latitude (deg)")
    else:
        labels = ("easting (m)", "northing (m)")
    extent = (x[0], x[-1], y[0], y[-1])
    n = len(rasters)
    ncols = min(3, n)
    nrows = -(-n // ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(4.4 * ncols, 3.9 * nrows), squeeze=False)
    for ax in axes.ravel()[n:]:
        ax.set_visible(False)
    for ax, (name, (vals, unit, _)) in zip(axes.ravel(), rasters.items(), strict=False):
        shown = np.where(np.isfinite(vals), vals, np.nan)
        finite = shown[np.isfinite(shown)]
        vmax = float(np.percentile(finite, 98)) if finite.size else 1.0
        im = ax.imshow(shown, origin="lower", extent=extent, aspect="auto", vmin=0.0, vmax=vmax or 1.0)
        ax.set_title(f"{name} ({unit})", fontsize=9)
        ax.set_xlabel(labels[0])
        ax.set_ylabel(labels[1])
        fig.colorbar(im, ax=ax, shrink=0.8)
    fig.suptitle(f"{fmap.name or 'map'}: window {window_m:g} m", fontsize=10)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110)
    plt.close(fig)


def run(args: argparse.Namespace) -> int:
    if not np.isfinite(args.window) or args.window <= 0:
        raise InputError(f"--window: expected a positive width in metres, got {args.window!r}")
    check_output_file(args.out)
    check_output_file(Path(args.out).with_suffix(".png"), option="--out (its PNG)")
    fmap = load(args, args.map)
    if not hasattr(fmap, "axes"):
        raise InputError(f"{args.map}: variability rasters need a gridded map, got {type(fmap).__name__}")
    rasters = compute(fmap, args.window, args.sigma)
    out = Path(args.out)
    write_netcdf(out, fmap, rasters, args.window)
    png = out.with_suffix(".png")
    write_png(png, fmap, rasters, args.window)
    if not args.quiet:
        print(f"{'raster':<22} {'unit':<10} {'median':>12} {'p10':>12} {'p90':>12}")
        for name, (vals, unit, _) in rasters.items():
            finite = vals[np.isfinite(vals)]
            if finite.size:
                p10, med, p90 = np.percentile(finite, [10, 50, 90])
                print(f"{name:<22} {unit:<10} {med:>12.4g} {p10:>12.4g} {p90:>12.4g}")
            else:
                print(f"{name:<22} {unit:<10} {'(no finite value)':>38}")
        print(f"wrote {out} and {png}")
    return 0
