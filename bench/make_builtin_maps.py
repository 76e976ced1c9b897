"""Regenerate the maps and the survey shipped in ``magnav_ins/data`` from ``../shared/data`` (reproducible provenance).

    python bench/make_builtin_maps.py [--json]

* ``osborne-magnetic.nc``: Osborne airborne magnetics (Fatiando a Terra / Geoscience Australia, CC-BY-4.0), heights
  made ellipsoidal with the EIGEN-6C4 geoid (h = H + N), gridded at 100 m from the east-west flight lines only
  (the 22 north-south tie lines, found by line azimuth, are excluded), float32, compressed.
* ``osborne-tie-lines.csv.xz``: the tie lines' real readings (line, lat, lon, ellipsoidal height, anomaly).
* ``eigen6c4-geoid-10arcmin.nc``: the EIGEN-6C4 geoid (Fatiando a Terra / GFZ ICGEM, CC-BY-4.0), global 10' grid,
  int16 in 0.1 m as published, without the duplicated 180 deg column (:mod:`magnav_ins.maps.geoid`).
* ``eigen6c4-australia-se.nc``: EIGEN-6C4 full gravity at 10 km (Fatiando a Terra / GFZ ICGEM, CC-BY-4.0) minus WGS-84
  normal gravity at 10 km = gravity disturbance (mGal), lat -40..-32, lon 142..153 deg.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import pandas as pd
import xarray as xr

from magnav_ins.core.atomic import atomic_path
from magnav_ins.core.types import FieldKind
from magnav_ins.core.units import DEG_TO_RAD, MPS2_TO_MGAL
from magnav_ins.ins.earth import normal_gravity
from magnav_ins.maps import geoid
from magnav_ins.maps.build import cross_lines, grid_survey, tie_line_misfit
from magnav_ins.maps.geoid import GEOID_FILE
from magnav_ins.maps.grid import GridMap
from magnav_ins.maps.io import read_survey, write_map

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data" / "fatiando"
OUT = ROOT / "magnav_ins" / "data"
OSBORNE_SPACING_M = 100.0
SE_AUS_REGION_DEG = (-40.0, -32.0, 142.0, 153.0)  # lat_min, lat_max, lon_min, lon_max
EIGEN_HEIGHT_M = 10_000.0


def make_geoid() -> dict:
    """The shipped geoid: the published int16 (0.1 m) grid, the duplicated lon = 180 deg column dropped."""
    ds = xr.open_dataset(SHARED / "earth-geoid-10arcmin.nc", mask_and_scale=False)
    raw = np.asarray(ds.geoid.values)
    if raw.dtype != np.int16 or float(ds.geoid.attrs["scale_factor"]) != 0.1 or np.any(raw[:, 0] != raw[:, -1]):
        raise SystemExit("earth-geoid-10arcmin.nc: unexpected encoding (expected int16 x 0.1 m, lon -180..180)")
    attrs = {
        "units": "m",
        "scale_factor": 0.1,
        "long_name": "geoid height above the WGS84 ellipsoid (EIGEN-6C4, degree 720, tide-free)",
        "standard_name": "geoid_height_above_reference_ellipsoid",
    }
    out = xr.Dataset(
        {"geoid": (("latitude", "longitude"), raw[:, :-1], attrs)},
        coords={
            "latitude": ("latitude", np.asarray(ds.latitude.values, float), {"units": "degrees_north"}),
            "longitude": ("longitude", np.asarray(ds.longitude.values[:-1], float), {"units": "degrees_east"}),
        },
        attrs={
            "Conventions": "CF-1.8",
            "title": "EIGEN-6C4 geoid height above WGS84, 10 arc-minute grid",
            "source": "Fatiando a Terra earth-geoid-10arcmin v1 (EIGEN-6C4, GFZ/ICGEM, doi:10.5880/icgem.2015.1)",
            "license": "CC-BY-4.0",
            "made_by": "bench/make_builtin_maps.py",
        },
    )
    path = OUT / GEOID_FILE
    with atomic_path(path) as tmp:
        out.to_netcdf(tmp, encoding={"geoid": {"zlib": True, "complevel": 9, "shuffle": True, "dtype": "int16"}})
        tmp.chmod(0o644)
    geoid._grid.cache_clear()
    return {"geoid_shape": list(raw[:, :-1].shape), "geoid_bytes": path.stat().st_size}


def make_osborne() -> dict:
    t0 = time.perf_counter()
    survey = read_survey(SHARED / "osborne-magnetic.csv.xz")  # orthometric heights through the shipped geoid
    ties = cross_lines(survey)
    fmap = grid_survey(survey, OSBORNE_SPACING_M, exclude_lines=ties, name="osborne-magnetic")
    fmap.metadata.update(
        {
            "source": "Fatiando a Terra osborne-magnetic v1 (Geoscience Australia MIM P1029, 1990), CC-BY-4.0",
            "tie_lines_excluded": ties,
            "heights": "ellipsoidal = orthometric + EIGEN-6C4 geoid (10' grid)",
            "made_by": "bench/make_builtin_maps.py",
        }
    )
    write_map(fmap, OUT / "osborne-magnetic.nc", dtype="float32")
    m = np.isin(survey.line, ties)
    df = pd.DataFrame(
        {
            "flight_line": survey.line[m],
            "latitude": np.round(np.rad2deg(survey.lat[m]), 6),
            "longitude": np.round(np.rad2deg(survey.lon[m]), 6),
            "height_ellipsoidal_m": np.round(survey.h[m], 1),
            "total_field_anomaly_nt": survey.value[m],
        }
    )
    with atomic_path(OUT / "osborne-tie-lines.csv.xz") as tmp:
        df.to_csv(tmp, index=False, compression="xz")
        tmp.chmod(0o644)
    mis = tie_line_misfit(fmap, survey, ties)
    n = sum(v["n"] for v in mis.values())
    return {
        "osborne_shape": list(fmap.shape),
        "osborne_tie_lines": ties,
        "osborne_tie_rms_nt": float(np.sqrt(sum(v["rms"] ** 2 * v["n"] for v in mis.values()) / n)),
        "osborne_bytes": (OUT / "osborne-magnetic.nc").stat().st_size,
        "tie_lines_bytes": (OUT / "osborne-tie-lines.csv.xz").stat().st_size,
        "osborne_wall_s": time.perf_counter() - t0,
    }


def make_eigen() -> dict:
    ds = xr.load_dataset(SHARED / "earth-gravity-10arcmin.nc")
    la0, la1, lo0, lo1 = SE_AUS_REGION_DEG
    sub = ds.sel(latitude=slice(la0, la1), longitude=slice(lo0, lo1))
    h = np.asarray(sub.height.values, dtype=float)
    if not np.allclose(h, EIGEN_HEIGHT_M):
        raise SystemExit(f"unexpected EIGEN-6C4 grid height {h.min()}..{h.max()} m")
    lat = np.asarray(sub.latitude.values) * DEG_TO_RAD
    lon = np.asarray(sub.longitude.values) * DEG_TO_RAD
    g = np.asarray(sub.gravity.values, dtype=float)  # mGal, full gravity
    la, _ = np.meshgrid(lat, lon, indexing="ij")
    dist = g - normal_gravity(la, EIGEN_HEIGHT_M) * MPS2_TO_MGAL
    fmap = GridMap(
        lat,
        lon,
        dist,
        kind=FieldKind.GRAVITY_DISTURBANCE_MGAL,
        frame="geodetic",
        altitude_m=EIGEN_HEIGHT_M,
        name="eigen6c4-australia-se",
        metadata={
            "source": "Fatiando a Terra earth-gravity-10arcmin v1 (EIGEN-6C4, GFZ/ICGEM, doi:10.5880/icgem.2015.1), "
            "CC-BY-4.0",
            "method": "EIGEN-6C4 gravity at 10 km minus WGS-84 normal gravity at 10 km (magnav_ins.ins.earth)",
            "made_by": "bench/make_builtin_maps.py",
        },
    )
    write_map(fmap, OUT / "eigen6c4-australia-se.nc", dtype="float32")
    return {
        "eigen_shape": list(fmap.shape),
        "eigen_range_mgal": [float(np.min(dist)), float(np.max(dist))],
        "eigen_bytes": (OUT / "eigen6c4-australia-se.nc").stat().st_size,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--json", action="store_true", help="print one JSON line")
    args = ap.parse_args()
    if not SHARED.is_dir():
        raise SystemExit(f"{SHARED} not found: ../shared/data must sit beside the project")
    res = {**make_geoid(), **make_eigen(), **make_osborne()}
    print(json.dumps(res) if args.json else json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
